"""Grasp fidelity (ENV_VERSION 2 and 3, commits 96deb0b, 22634d4): scripted pick-and-place, 3-stack and
finger landing over seeded resets, in ENV_VERSION 2's physics and in this env's, side by side; prints the
success rate, the share of block-steps with a block on its side, the gripper's largest roll, how many
episodes landed a finger on a block's top face, and the finger position while holding.

    python benchmarks/bench_grasp.py [--seeds 100] [--env-dir DIR]

A block is on its side when |roll| or |pitch| > 0.5 rad in gym-robotics' `mat2euler` convention
(computed here from the block's rotation matrix, so that an env with another Euler convention is
measured the same way). The gripper's roll is its pointing axis' angle from straight down, taken after
every physics substep. "Version 2" is this env's scene compiled without the fingers' explicit
inertials (ENV_VERSION 3, SPEC §3): their 4 kg then sit in their boxes, as in ENV_VERSION 2. `--env-dir`
imports fetch5_env.py (and its assets/) from DIR instead of this checkout, e.g. `git show
b3d02ef:fetch5_env.py` for version 1. The scripted controllers are the tests' own (tests/test_env.py),
so bench and tests grasp alike; "finger landing" is the roll test's descent onto block 0 of each reset.
"""

import argparse
import contextlib
import statistics
import sys
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TIP_ANGLE = 0.5  # rad: |roll| or |pitch| beyond this = the block lies on its side


def roll_pitch(xmat: np.ndarray) -> np.ndarray:
    """(n, 2) roll and pitch of row-major rotation matrices (n, 9), R = Rx(roll) Ry(pitch) Rz(yaw)."""
    roll = np.arctan2(-xmat[:, 5], xmat[:, 8])
    pitch = np.arctan2(xmat[:, 2], np.hypot(xmat[:, 5], xmat[:, 8]))
    return np.stack([roll, pitch], axis=1)


@contextlib.contextmanager
def without_finger_inertials(fetch5_env):
    """Envs built inside compile the scene as ENV_VERSION 2 did: no explicit finger inertials, each
    finger's 4 kg in its box, so that the gripper's rotational inertia is its boxes' alone."""
    real_build = fetch5_env.build_model

    def build_model(n_blocks):
        spec = mujoco.MjSpec.from_file(str(fetch5_env.ASSET_PATH))
        # Every body's inertia from its geoms, as version 2's asset (no <inertial>) compiled to: the
        # same model, array for array (checked against git show 2f9820b:assets/fetch_manipulate.xml).
        spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
        for side in ("r", "l"):
            spec.geom(f"finger_{side}_geom").mass = 4.0
        for i in range(n_blocks, 5):  # the asset holds five (fetch5_env.build_model)
            spec.delete(spec.body(f"object{i}"))
        return spec.compile()

    fetch5_env.build_model = build_model
    try:
        yield
    finally:
        fetch5_env.build_model = real_build


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

    def finger_landing(env):
        scripted.land_a_finger(env, 0)
        return scripted.hold(env, 0, 10)

    tasks = {
        # task: (script, the "on" relations it must build, or None: no goal; no other block may end up on another)
        "pick-and-place": (lambda env: scripted.pick_and_place(env, 0, 1), [(0, 1)]),
        "3-stack": (stack_three, [(0, 1), (2, 0)]),
        "finger landing": (finger_landing, None),
    }
    physics = {"version 2": lambda: without_finger_inertials(fetch5_env), "this env": contextlib.nullcontext}
    print(f"env: {Path(fetch5_env.__file__).resolve()} (ENV_VERSION {fetch5_env.ENV_VERSION})")
    print(f"{args.seeds} seeded resets per task, {n} blocks; roll: the gripper's, largest per episode")
    print(
        f"  {'task':15s} {'physics':10s} {'success':>8s} {'on its side':>12s} {'roll: max':>10s} {'median':>7s}"
        f" {'landings':>9s} {'holding':>8s}"
    )
    for name, (script, on) in tasks.items():
        for label, building in physics.items():
            successes, tipped, holds, rolls, landings = 0, [], [], [], 0
            for seed in range(args.seeds):
                with building():
                    env = fetch5_env.FetchManipulateEnv(n_blocks=n)
                env.reset(seed=seed)
                record = Recorder(env, n, fetch5_env, scripted, tipped, holds)
                with record.substeps():
                    obs = script(env)
                want = og.make_config(n, above=on or [])[nc:]
                successes += bool((obs["achieved_goal"][nc:] == want).all())
                rolls.append(np.degrees(record.largest_roll))
                landings += record.landed
            hold = f"{statistics.median(holds):.4f}" if holds else "-"
            success = f"{successes / args.seeds:.0%}" if on else "-"
            print(
                f"  {name:15s} {label:10s} {success:>8s} {np.mean(tipped):12.2%} {max(rolls):9.1f}°"
                f" {statistics.median(rolls):6.1f}° {landings:9d} {hold:>8s}"
            )
    print("on its side: share of block-steps; landings: episodes where a finger touched a block's top face")


class Recorder:
    """Wraps env.step: appends per block whether it lies on its side to `tipped`, the mean finger
    position to `holds` while the fingers close on a lifted block at the grip site, and notes whether a
    finger touched a block's top face; `substeps()` tracks the gripper's largest roll substep by substep."""

    def __init__(self, env, n, fetch5_env, scripted, tipped, holds):
        self.largest_roll, self.landed = 0.0, False
        real_step, first_block, gripper = env.step, env.model.body("object0").id, env.model.body("gripper").id
        self.gripper, self.data = gripper, env.data

        def step(action):
            out = real_step(action)
            rp = roll_pitch(env.data.xmat[first_block : first_block + n])
            tipped.extend((np.abs(rp) > TIP_ANGLE).any(axis=1))
            rel = out[0]["observation"][10:].reshape(n, 15)[:, 12:15]  # block - grip site
            lifted = env.block_positions()[:, 2] > fetch5_env.TABLE_Z + fetch5_env.BLOCK_HALF + 0.01
            if action[3] < 0 and (lifted & (np.linalg.norm(rel, axis=1) < 0.02)).any():
                holds.append(float(np.mean(out[0]["observation"][3:5])))
            self.landed |= any(scripted.finger_on_top_face(env, i) for i in range(n))
            return out

        env.step = step

    @contextlib.contextmanager
    def substeps(self):
        """mujoco.mj_step one substep at a time, noting the gripper's roll after each."""
        real_step = mujoco.mj_step

        def mj_step(model, data, nstep=1):
            for _ in range(nstep):
                real_step(model, data)
                down = -data.xmat[self.gripper][6]  # the pointing axis' z component, negated
                self.largest_roll = max(self.largest_roll, float(np.arccos(min(1.0, down))))

        mujoco.mj_step = mj_step
        try:
            yield
        finally:
            mujoco.mj_step = real_step


if __name__ == "__main__":
    main()
