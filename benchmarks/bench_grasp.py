"""Grasp fidelity (issue 13): scripted pick-and-place and 3-stack over seeded resets; prints the success
rate, the share of block-steps with a block on its side, and the finger position while holding.

    python benchmarks/bench_grasp.py [--seeds 100] [--env-dir DIR]

A block is on its side when |roll| or |pitch| > 0.5 rad in gym-robotics' `mat2euler` convention
(computed here from the block's rotation matrix, so that an env with another Euler convention is
measured the same way). `--env-dir` imports fetch5_env.py (and its assets/) from DIR instead of this
checkout: the "before" numbers come from the old env, e.g. `git show b3d02ef:fetch5_env.py`.
The scripted controllers are the tests' own (tests/test_env.py), so bench and tests grasp alike.
"""

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TIP_ANGLE = 0.5  # rad: |roll| or |pitch| beyond this = the block lies on its side (issue 13)


def roll_pitch(xmat: np.ndarray) -> np.ndarray:
    """(n, 2) roll and pitch of row-major rotation matrices (n, 9), R = Rx(roll) Ry(pitch) Rz(yaw)."""
    roll = np.arctan2(-xmat[:, 5], xmat[:, 8])
    pitch = np.arctan2(xmat[:, 2], np.hypot(xmat[:, 5], xmat[:, 8]))
    return np.stack([roll, pitch], axis=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=100, help="seeded resets per task")
    parser.add_argument("--env-dir", type=Path, default=ROOT, help="folder holding the fetch5_env.py to measure")
    args = parser.parse_args()
    sys.path[:0] = [str(args.env_dir.resolve()), str(ROOT), str(ROOT / "tests")]
    import test_env as scripted  # noqa: PLC0415 (the tests' controllers, on the same fetch5_env)

    import fetch5_env  # noqa: PLC0415 (from --env-dir, chosen at run time)
    import oracle_graph as og  # noqa: PLC0415

    n = 5
    nc = n * (n - 1) // 2

    def stack_three(env):
        scripted.pick_and_place(env, 0, 1)
        return scripted.pick_and_place(env, 2, 0)

    tasks = {
        # task: (script, the "on" relations it must build; no other block may end up on another)
        "pick-and-place": (lambda env: scripted.pick_and_place(env, 0, 1), [(0, 1)]),
        "3-stack": (stack_three, [(0, 1), (2, 0)]),
    }
    print(f"env: {Path(fetch5_env.__file__).resolve()}, {args.seeds} seeded resets per task, {n} blocks")
    for name, (script, on) in tasks.items():
        want = og.make_config(n, above=on)[nc:]
        successes, tipped, holds = 0, [], []
        for seed in range(args.seeds):
            env = fetch5_env.FetchManipulateEnv(n_blocks=n)
            env.reset(seed=seed)
            env.step = recording_step(env, n, fetch5_env, tipped, holds)
            obs = script(env)
            successes += bool((obs["achieved_goal"][nc:] == want).all())
        hold = statistics.median(holds) if holds else float("nan")
        print(
            f"  {name:15s} success {successes / args.seeds:6.1%}   block on its side {np.mean(tipped):6.2%}"
            f" of {len(tipped):,} block-steps   finger position holding (median) {hold:.4f} m"
        )


def recording_step(env, n, fetch5_env, tipped, holds):
    """env.step, appending per block whether it lies on its side to `tipped`, and the mean finger
    position to `holds` while the fingers close on a lifted block at the grip site."""
    real_step, first_block = env.step, env.model.body("object0").id

    def step(action):
        out = real_step(action)
        rp = roll_pitch(env.data.xmat[first_block : first_block + n])
        tipped.extend((np.abs(rp) > TIP_ANGLE).any(axis=1))
        rel = out[0]["observation"][10:].reshape(n, 15)[:, 12:15]  # block - grip site
        lifted = env.block_positions()[:, 2] > fetch5_env.TABLE_Z + fetch5_env.BLOCK_HALF + 0.01
        if action[3] < 0 and (lifted & (np.linalg.norm(rel, axis=1) < 0.02)).any():
            holds.append(float(np.mean(out[0]["observation"][3:5])))
        return out

    return step


if __name__ == "__main__":
    main()
