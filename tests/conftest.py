import ctypes.util
import os
import sys
from pathlib import Path

import pytest

# Under pytest-xdist (the test command's -n 2) each worker process has a core: torch's threads, and those of
# the runs the tests start, would only contend with the other worker's (a SAC test ran 1.4-3x slower so).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
# torch.compile's kernels compiled in the test's process: inductor's pool of compile workers, each importing
# torch (10 processes here), costs more than it saves for the few kernels a test compiles
os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")

# Headless machines render through OSMesa (Debian's libosmesa6), if it is installed: asking for it
# without the library would break `import mujoco` itself, and every test with it. A desktop keeps its GL.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY") and ctypes.util.find_library("OSMesa"):
    os.environ["MUJOCO_GL"] = "osmesa"

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def pytest_configure(config):
    """Under -n 2, the tests of one xdist_group run on one worker: those that share a costly module fixture (a
    torchrun launch, an uninterrupted run) make it once, not once a worker. -n alone means xdist's "load";
    this makes it "loadgroup" (pytest-xdist: the controller schedules by group, each worker names its tests'
    groups in their ids)."""
    if getattr(config.option, "dist", "no") == "load":
        config.option.dist = "loadgroup"
    if getattr(config, "workerinput", {}).get("loadgroup"):
        config.option.loadgroup = True


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """pytest-xdist's hook, on the controller, for each worker before it starts: what it is told."""
    node.workerinput["loadgroup"] = node.config.option.dist == "loadgroup"


@pytest.fixture(autouse=True)
def torch_threads():
    """torch's thread count as each test found it: a run in the test's process sets its own (--threads, --overlap)."""
    import torch  # noqa: PLC0415 (after the environment above is set)

    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def gl():
    """MuJoCo, with a working OpenGL backend. Rendering must work in CI (CI=true); elsewhere a machine
    without a GL backend skips with the reason."""
    mujoco = pytest.importorskip("mujoco")
    import fetch5_env  # noqa: PLC0415 (after MUJOCO_GL is set)

    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY") and not os.environ.get("CI"):
        pytest.skip("no OpenGL backend: no display, no OSMesa (apt-get install libosmesa6 to render headless)")
    try:
        mujoco.Renderer(fetch5_env.build_model(2), 8, 8).close()
    except Exception as e:  # noqa: BLE001 (any GL failure means: no backend here)
        if os.environ.get("CI"):
            raise
        pytest.skip(f"no OpenGL backend (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {e}")
    return mujoco
