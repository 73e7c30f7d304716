"""Env speed (issue: fetch5_env): median env steps/s with random actions, resetting every 40 steps,
and the share of a step spent inside raw `mujoco.mj_step` (20 substeps) versus Python.

    python benchmarks/bench_env.py [--n-blocks 5] [--steps 4000] [--repeats 7]

mj_step is timed in place, inside env.step, by wrapping it: the same states, contacts and caches.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import fetch5_env  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-blocks", type=int, default=5)
    parser.add_argument("--steps", type=int, default=4000, help="env steps per repeat")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()

    env = fetch5_env.FetchManipulateEnv(n_blocks=args.n_blocks)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(args.steps, 4)).astype(np.float32)
    real_step, in_mj = mujoco.mj_step, [0]

    def timed_mj_step(*a, **k):
        t = time.perf_counter_ns()
        real_step(*a, **k)
        in_mj[0] += time.perf_counter_ns() - t

    step_ms, mj_ms = [], []
    mujoco.mj_step = timed_mj_step
    try:
        for r in range(args.repeats):
            env.reset(seed=r)
            in_mj[0], t_steps = 0, 0
            for i, a in enumerate(actions):
                if i and i % fetch5_env.MAX_EPISODE_STEPS == 0:
                    env.reset()  # resets are part of collection, but not of a step
                t = time.perf_counter_ns()
                env.step(a)
                t_steps += time.perf_counter_ns() - t
            step_ms.append(t_steps / args.steps / 1e6)
            mj_ms.append(in_mj[0] / args.steps / 1e6)
    finally:
        mujoco.mj_step = real_step

    step, mj = statistics.median(step_ms), statistics.median(mj_ms)
    print(f"{args.n_blocks} blocks, {args.steps} steps x {args.repeats} repeats (medians)")
    print(f"  env.step         {step:.3f} ms  ({1e3 / step:,.0f} steps/s)")
    print(f"  raw mj_step x20  {mj:.3f} ms  ({mj / step:.0%} of a step)")
    print(f"  Python           {step - mj:.3f} ms  ({(step - mj) / step:.0%} of a step)")


if __name__ == "__main__":
    main()
