import os
import sys
from pathlib import Path

# Headless machines render through OSMesa (Debian's libosmesa6); a desktop keeps its own GL.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "osmesa"

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
