"""Env speed (fetch5_env.py): median env steps/s with random actions, resetting every 40 steps,
and the share of a step spent inside raw `mujoco.mj_step` (20 substeps) versus Python.

    python benchmarks/bench_env.py [--n-blocks 5] [--steps 4000] [--repeats 7] [--baseline REV]

mj_step is timed in place, inside env.step, by wrapping it: the same states, contacts and caches.
`--baseline REV` also times fetch5_env.py and its asset as of git revision REV, interleaving the
repeats of both in the same run (on a shared machine, separate runs differ by more than a change does).
"""

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import fetch5_env  # noqa: E402


def import_env_at(rev: str, folder: Path):
    """fetch5_env as of git revision `rev`, written to `folder` with its asset, as module fetch5_env_<rev>."""
    (folder / "assets").mkdir(parents=True, exist_ok=True)
    for path in ("fetch5_env.py", "assets/fetch_manipulate.xml"):
        text = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True).stdout
        (folder / path).write_bytes(text)
    spec = importlib.util.spec_from_file_location(f"fetch5_env_{rev}", folder / "fetch5_env.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-blocks", type=int, default=5)
    parser.add_argument("--steps", type=int, default=4000, help="env steps per repeat")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--baseline", default=None, help="git revision whose env to time alongside, e.g. b3d02ef")
    args = parser.parse_args()

    modules = {"this checkout": fetch5_env}
    with tempfile.TemporaryDirectory() as tmp:
        if args.baseline:
            modules[args.baseline] = import_env_at(args.baseline, Path(tmp))
        envs = {name: module.FetchManipulateEnv(n_blocks=args.n_blocks) for name, module in modules.items()}
        results = time_steps(envs, args)

    print(f"{args.n_blocks} blocks, {args.steps} steps x {args.repeats} repeats (medians)")
    for name, (step, mj) in results.items():
        print(f"{name}:")
        print(f"  env.step         {step:.3f} ms  ({1e3 / step:,.0f} steps/s)")
        print(f"  raw mj_step x20  {mj:.3f} ms  ({mj / step:.0%} of a step)")
        print(f"  Python           {step - mj:.3f} ms  ({(step - mj) / step:.0%} of a step)")
    if args.baseline:
        ratio = results["this checkout"][0] / results[args.baseline][0]
        print(f"env.step time, this checkout / {args.baseline}: {ratio:.3f}")


def time_steps(envs: dict, args) -> dict:
    """{name: (median env.step ms, median mj_step ms)}; each repeat times every env in turn."""
    actions = np.random.default_rng(0).uniform(-1, 1, size=(args.steps, 4)).astype(np.float32)
    real_step, in_mj = mujoco.mj_step, [0]

    def timed_mj_step(*a, **k):
        t = time.perf_counter_ns()
        real_step(*a, **k)
        in_mj[0] += time.perf_counter_ns() - t

    step_ms = {name: [] for name in envs}
    mj_ms = {name: [] for name in envs}
    mujoco.mj_step = timed_mj_step
    try:
        for r in range(args.repeats):
            for name, env in envs.items():
                env.reset(seed=r)
                in_mj[0], t_steps = 0, 0
                for i, a in enumerate(actions):
                    if i and i % fetch5_env.MAX_EPISODE_STEPS == 0:
                        env.reset()  # resets are part of collection, but not of a step
                    t = time.perf_counter_ns()
                    env.step(a)
                    t_steps += time.perf_counter_ns() - t
                step_ms[name].append(t_steps / args.steps / 1e6)
                mj_ms[name].append(in_mj[0] / args.steps / 1e6)
    finally:
        mujoco.mj_step = real_step
    return {name: (statistics.median(step_ms[name]), statistics.median(mj_ms[name])) for name in envs}


if __name__ == "__main__":
    main()
