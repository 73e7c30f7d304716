"""Fetch Manipulate with 2-5 blocks in modern MuJoCo (SPEC §3; paper Section 3.2).

A parallel-jaw gripper, welded to a mocap body, moves above a table with n 5 cm cubes. The agent
controls the gripper's 3D displacement and its fingers (4-D action in [-1, 1]); it observes the
gripper, fingers and blocks (10 + 15n floats) and a semantic configuration of close/above predicates
(oracle_graph.py owns the layout). The reward is sparse: 1.0 iff the achieved configuration equals
the desired one.

    import gymnasium as gym, fetch5_env
    env = gym.make("FetchManipulate5-v0")          # or FetchManipulate3-v0, 2..5 blocks
    obs, info = env.reset(seed=0, options={"goal": goal})
    env.unwrapped.set_goal(next_goal)              # change the goal without resetting physics (SPEC §6)

Conventions follow Gymnasium-Robotics: dict observations, a vectorised `compute_reward`, all
randomness from `self.np_random`.
"""

from __future__ import annotations

import functools
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

import oracle_graph as og

# Bump ENV_VERSION whenever the scene, its physics parameters or the observations change (what a policy
# sees or does): the training scripts store it in their checkpoints and refuse one trained on another
# version. A new MuJoCo release changes no ENV_VERSION: checkpoints record the MuJoCo, Gymnasium, numpy and
# torch versions instead, and --resume under other ones says so in one line (plumbing.library_versions).
# 1: first release; 2: Fetch's finger offset, contact and limit parameters, mat2euler angles, workspace;
# 3: Fetch's finger inertials, so that the gripper resists rotation as Fetch's does (SPEC §3).
ENV_VERSION = 3
ASSET_PATH = Path(__file__).resolve().parent / "assets" / "fetch_manipulate.xml"
N_SUBSTEPS = 20  # 20 x 0.002 s physics steps per control step (SPEC §3)
MAX_EPISODE_STEPS = 40  # one segment (SPEC §3)
ACTION_SCALE = 0.05  # metres of mocap displacement per unit action (Fetch's pos_ctrl *= 0.05)
GRIP_OFFSET = 0.02  # grip site, along the gripper's pointing axis (local +x)
# The arm's reach, as a box the mocap target is clipped to (SPEC §3): never binding above the table,
# but no action sequence takes the gripper out of the observation bounds.
WORKSPACE_LOW, WORKSPACE_HIGH = np.array([1.0, 0.3, 0.38]), np.array([1.6, 1.2, 0.95])
DOWN_QUAT = np.array([1.0, 0.0, 1.0, 0.0]) / np.sqrt(2.0)  # local +x points to world -z
INITIAL_GRIP_POS = np.array([1.3419, 0.7491, 0.5347])
BLOCK_HALF = 0.025
TABLE_Z = 0.40
SPAWN_RANGE = 0.15  # blocks spawn in initial grip xy +- 0.15
MIN_SPAWN_DIST = np.sqrt(2.0) * 2 * BLOCK_HALF  # no two blocks closer than a diagonal at reset
OBS_BOUND = 10.0
CLOSE_DIST = 0.09  # close(i, j) iff |p_i - p_j| < 0.09
GIMBAL_EPS = 4 * np.finfo(np.float64).eps  # cos(pitch) below this: gimbal lock (gym-robotics' _EPS4)
ABOVE_XY, ABOVE_DZ = 0.05, (0.03, 0.06)  # i on j iff |xy_i - xy_j| < 0.05 and 0.03 < z_i - z_j < 0.06


@functools.cache
def _pair_incidence(n_blocks: int) -> np.ndarray:
    """(dim, n) matrix E with E @ positions = p_i - p_j for every predicate's pair, in layout order."""
    pairs = og.predicate_blocks(n_blocks)
    e = np.zeros((len(pairs), n_blocks))
    e[np.arange(len(pairs)), pairs[:, 0]] = 1.0
    e[np.arange(len(pairs)), pairs[:, 1]] = -1.0
    e.setflags(write=False)
    return e


def semantic_config(positions: np.ndarray) -> np.ndarray:
    """Close/above predicates of block centres `positions` (..., n, 3) as a +-1 float32 config (..., dim)."""
    p = np.asarray(positions, dtype=np.float64)
    n = p.shape[-2]
    nc = n * (n - 1) // 2
    d = _pair_incidence(n) @ p  # all pairwise differences in one matmul: no gathers
    sq = d * d
    xy2 = sq[..., 0] + sq[..., 1]
    pred = xy2 + sq[..., 2] < CLOSE_DIST**2  # right for the close rows; the above rows are overwritten
    dz = d[..., nc:, 2]
    pred[..., nc:] = (xy2[..., nc:] < ABOVE_XY**2) & (dz > ABOVE_DZ[0]) & (dz < ABOVE_DZ[1])
    return np.where(pred, np.float32(1.0), np.float32(-1.0))


def obs_size(n_blocks: int) -> int:
    """Floats in an observation of n_blocks blocks (SPEC §3): 10 of the gripper, 15 per block."""
    return 10 + 15 * n_blocks


def goal_reached(achieved_goal, desired_goal) -> np.ndarray:
    """Success, written once for the env and every learner (its reward, HER's relabelled reward, a
    segment's success): the achieved config equals the goal on every predicate. Bool, batched over
    leading axes; configs as +-1 values of any numeric dtype."""
    return np.all(np.asarray(achieved_goal) == np.asarray(desired_goal), axis=-1)


def euler_from_mat(mat: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Euler angles (roll, pitch, yaw) of row-major rotation matrices (..., 9), in gym-robotics'
    `rotations.mat2euler` convention (SPEC §3): rotating axes x, then y, then z, so that
    R = Rx(roll) @ Ry(pitch) @ Rz(yaw); pitch in [-pi/2, pi/2], roll and yaw in [-pi, pi].

    At gimbal lock (pitch = +-pi/2, when only roll + yaw or yaw - roll is defined) roll is 0, as there.
    """
    m = np.asarray(mat)
    out = np.empty(m.shape[:-1] + (3,)) if out is None else out
    # R[0, 2] = sin(pitch); R[1, 2] = -sin(roll) cos(pitch), R[2, 2] = cos(roll) cos(pitch);
    # R[0, 1] = -cos(pitch) sin(yaw), R[0, 0] = cos(pitch) cos(yaw).
    cos_pitch = np.hypot(m[..., 5], m[..., 8])
    np.arctan2(-m[..., 5], m[..., 8], out=out[..., 0])
    np.arctan2(m[..., 2], cos_pitch, out=out[..., 1])  # asin(R[0, 2]) without clipping
    np.arctan2(-m[..., 1], m[..., 0], out=out[..., 2])
    locked = cos_pitch <= GIMBAL_EPS
    if locked.any():  # a block never gets here in practice; a test does
        out[..., 0] = np.where(locked, 0.0, out[..., 0])
        out[..., 2] = np.where(locked, np.arctan2(m[..., 3], m[..., 4]), out[..., 2])
    return out


def build_model(n_blocks: int) -> mujoco.MjModel:
    """Compile the scene with blocks object0..object{n-1} (the asset holds five)."""
    spec = mujoco.MjSpec.from_file(str(ASSET_PATH))
    for i in range(n_blocks, og.MAX_BLOCKS):
        spec.delete(spec.body(f"object{i}"))
    return spec.compile()


class FetchManipulateEnv(gym.Env):
    """Goal-conditioned block manipulation with semantic goals (SPEC §3)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 25}

    def __init__(self, n_blocks: int = 5, render_mode: str | None = None, width: int = 480, height: int = 480):
        self.n_blocks = og.check_n_blocks(n_blocks)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode, self.width, self.height = render_mode, width, height
        self.goal_dim = og.config_dim(self.n_blocks)
        self.obs_dim = obs_size(self.n_blocks)

        self.model = build_model(self.n_blocks)
        self.data = mujoco.MjData(self.model)
        self.dt = self.model.opt.timestep * N_SUBSTEPS

        # qpos/qvel addresses, resolved once so that each step is a few numpy gathers.
        # Views into MuJoCo's arrays, resolved once: each step reads them without fancy-index copies.
        m, d = self.model, self.data
        self._gripper, self._grip_site = m.body("gripper").id, m.site("grip").id
        gq, gv = m.jnt_qposadr[m.joint("gripper_free").id], m.jnt_dofadr[m.joint("gripper_free").id]
        self._grip_qpos, self._grip_qvel = d.qpos[gq : gq + 3], d.qvel[gv : gv + 6]
        fq, fv = m.jnt_qposadr[m.joint("finger_r_joint").id], m.jnt_dofadr[m.joint("finger_r_joint").id]
        self._finger_qpos, self._finger_qvel = d.qpos[fq : fq + 2], d.qvel[fv : fv + 2]  # r, l
        b0 = m.body("object0").id
        bq, bv = m.jnt_qposadr[m.body_jntadr[b0]], m.jnt_dofadr[m.body_jntadr[b0]]
        n = self.n_blocks
        assert [m.body(f"object{i}").id for i in range(n)] == list(range(b0, b0 + n)), "blocks must be consecutive"
        self._block_qpos = d.qpos[bq : bq + 7 * n].reshape(n, 7)  # (pos 3, quat 4) per block
        self._block_qvel = d.qvel[bv : bv + 6 * n].reshape(n, 6)  # (linear world 3, angular local 3)
        self._block_xpos, self._block_xmat = d.xpos[b0 : b0 + n], d.xmat[b0 : b0 + n]
        self._obs_buffer = np.zeros(self.obs_dim, dtype=np.float32)

        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        goal_box = spaces.Box(-1.0, 1.0, shape=(self.goal_dim,), dtype=np.float32)
        self.observation_space = spaces.Dict(
            {
                # Finite bounds (check_env asks for them): metres, radians and metres per step all stay
                # far inside +-10 in a scene whose floor is 3 m wide.
                "observation": spaces.Box(-OBS_BOUND, OBS_BOUND, shape=(self.obs_dim,), dtype=np.float32),
                "achieved_goal": goal_box,
                "desired_goal": goal_box,
            }
        )
        self.goal = -np.ones(self.goal_dim, dtype=np.float32)
        self._renderer = None
        self._viewer = None

    # ------------------------------------------------------------------------------------------
    # Goals and rewards
    # ------------------------------------------------------------------------------------------
    def check_goal(self, goal) -> np.ndarray:
        """Return goal as a float32 config, or raise a ValueError naming what is wrong with it."""
        g = np.asarray(goal, dtype=np.float32)
        if g.shape != (self.goal_dim,):
            raise ValueError(f"goal must have shape ({self.goal_dim},) for {self.n_blocks} blocks, got shape {g.shape}")
        bad = g[(g != 1.0) & (g != -1.0)]
        if bad.size:
            raise ValueError(f"goal values must be -1 or +1, got {bad.tolist()}")
        return g.copy()

    def set_goal(self, goal) -> dict:
        """Change the desired goal without touching the physics (sub-goal chaining, SPEC §6)."""
        self.goal = self.check_goal(goal)
        return self._get_obs()

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        """Sparse reward, 1.0 iff the goal is reached (goal_reached); vectorised over leading batch axes."""
        return goal_reached(achieved_goal, desired_goal).astype(np.float32)

    # ------------------------------------------------------------------------------------------
    # Gymnasium API
    # ------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        goal = (options or {}).get("goal")
        self.goal = -np.ones(self.goal_dim, dtype=np.float32) if goal is None else self.check_goal(goal)

        # Initial state = the compiled model's: gripper on its mocap, fingers closed, nothing moving.
        mujoco.mj_resetData(self.model, self.data)
        # Blocks rest on the table, one at a time, never closer than a diagonal to one already placed.
        placed = np.empty((0, 2))
        while len(placed) < self.n_blocks:
            xy = INITIAL_GRIP_POS[:2] + self.np_random.uniform(-SPAWN_RANGE, SPAWN_RANGE, size=2)
            if np.all(np.linalg.norm(placed - xy, axis=1) >= MIN_SPAWN_DIST):
                placed = np.vstack([placed, xy])
        self._block_qpos[:, :2] = placed
        self._block_qpos[:, 2] = TABLE_Z + BLOCK_HALF
        self._block_qpos[:, 3:] = (1.0, 0.0, 0.0, 0.0)
        mujoco.mj_forward(self.model, self.data)
        if self.render_mode == "human":
            self.render()
        return self._get_obs(), {}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (4,):
            raise ValueError(f"action must have shape (4,), got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"action must be finite, got {a.tolist()}")
        a = np.minimum(np.maximum(a, -1.0), 1.0)
        # Snap the mocap to the gripper body, then displace it within the workspace (SPEC §3); orientation
        # stays pointing down.
        target = self._grip_qpos + ACTION_SCALE * a[:3]
        np.minimum(np.maximum(target, WORKSPACE_LOW, out=target), WORKSPACE_HIGH, out=self.data.mocap_pos[0])
        self.data.mocap_quat[0] = DOWN_QUAT
        # Relative position control of the fingers: a[3] > 0 opens; the actuators' ctrlrange clips.
        self.data.ctrl[:] = self._finger_qpos + a[3]
        mujoco.mj_step(self.model, self.data, nstep=N_SUBSTEPS)

        obs = self._get_obs()
        reward = float(self.compute_reward(obs["achieved_goal"], self.goal))
        if self.render_mode == "human":
            self.render()
        return obs, reward, False, False, {"is_success": reward}

    def block_positions(self) -> np.ndarray:
        """(n, 3) block-centre positions of the current physics state."""
        return self._block_qpos[:, :3].copy()

    def place_blocks(self, positions) -> dict:
        """Put the blocks at `positions` (n, 3), upright and at rest (for tests, demos and scripted
        scenes); the gripper and the goal are left as they are. Returns the new observation."""
        p = np.asarray(positions, dtype=np.float64)
        if p.shape != (self.n_blocks, 3) or not np.isfinite(p).all():
            raise ValueError(f"positions must be finite with shape ({self.n_blocks}, 3), got {p.tolist()}")
        self._block_qpos[:, :3] = p
        self._block_qpos[:, 3:] = (1.0, 0.0, 0.0, 0.0)
        self._block_qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        return self._get_obs()

    def _get_obs(self) -> dict:
        d, dt, n = self.data, self.dt, self.n_blocks
        # mj_step leaves poses one substep behind qpos; refresh them (cheap: no collision, no dynamics).
        mujoco.mj_kinematics(self.model, d)
        grip_pos = d.site_xpos[self._grip_site]
        gv = self._grip_qvel
        # Site velocity = v + w x r, with r = R (0.02, 0, 0) and w = R w_local (free joints report the
        # angular velocity in the body frame), so w x r = 0.02 R (0, w_z, -w_y).
        grip_vel = gv[:3] + GRIP_OFFSET * (d.xmat[self._gripper].reshape(3, 3) @ (0.0, gv[5], -gv[4]))

        obs = self._obs_buffer
        obs[0:3] = grip_pos
        obs[3:5] = self._finger_qpos
        obs[5:8] = grip_vel * dt
        obs[8:10] = self._finger_qvel * dt
        blocks = obs[10:].reshape(n, 15)  # a view: the writes below fill obs
        pos, mats, qvel = self._block_xpos, self._block_xmat, self._block_qvel
        blocks[:, 0:3] = pos
        euler_from_mat(mats, out=blocks[:, 3:6])
        blocks[:, 6:9] = np.matmul(mats.reshape(n, 3, 3), qvel[:, 3:, None])[:, :, 0] * dt
        blocks[:, 9:12] = (qvel[:, :3] - grip_vel) * dt
        blocks[:, 12:15] = pos - grip_pos
        return {
            "observation": obs.copy(),
            "achieved_goal": semantic_config(pos),
            "desired_goal": self.goal.copy(),
        }

    def render(self):
        if self.render_mode == "rgb_array":
            if self._renderer is None:
                self._renderer = mujoco.Renderer(self.model, height=self.height, width=self.width)
            self._renderer.update_scene(self.data, camera="external")
            return self._renderer.render()
        if self.render_mode == "human":
            if self._viewer is None:
                from mujoco import viewer  # noqa: PLC0415 (needs a display: imported only when asked for)

                self._viewer = viewer.launch_passive(self.model, self.data)
            self._viewer.sync()
        return None

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


for _n in range(og.MIN_BLOCKS, og.MAX_BLOCKS + 1):
    if f"FetchManipulate{_n}-v0" not in gym.registry:
        gym.register(
            id=f"FetchManipulate{_n}-v0",
            entry_point=FetchManipulateEnv,
            max_episode_steps=MAX_EPISODE_STEPS,
            kwargs={"n_blocks": _n},
        )
