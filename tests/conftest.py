import os
import sys
from pathlib import Path

import pytest

# Headless machines render through OSMesa (Debian's libosmesa6); a desktop keeps its own GL.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "osmesa"

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


@pytest.fixture
def gl():
    """MuJoCo, with a working OpenGL backend. Rendering must work in CI; elsewhere a machine without a
    GL backend skips with the reason."""
    mujoco = pytest.importorskip("mujoco")
    import fetch5_env  # noqa: PLC0415 (after MUJOCO_GL is set)

    try:
        mujoco.Renderer(fetch5_env.build_model(2), 8, 8).close()
    except Exception as e:  # noqa: BLE001 (any GL failure means: no backend here)
        if os.environ.get("CI"):
            raise
        pytest.skip(f"no OpenGL backend (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {e}")
    return mujoco
