"""fetch5_env.py: the Fetch Manipulate scene, its action law, predicates and API (SPEC §3)."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker
from hypothesis import given, settings
from hypothesis import strategies as st

import fetch5_env as fe
import oracle_graph as og

Z0 = fe.TABLE_Z + fe.BLOCK_HALF  # a block resting on the table
FAR = [(1.10, 0.50), (1.10, 1.00), (1.50, 0.50), (1.50, 1.00), (1.30, 1.02)]  # far apart, away from the gripper


def make(n=5, **kw):
    env = fe.FetchManipulateEnv(n_blocks=n, **kw)
    env.reset(seed=0)
    return env


def settle(env, steps):
    for _ in range(steps):
        obs, *_ = env.step(np.zeros(4))
    return obs


# ------------------------------------------------------------------------------------------------
# Scripted controllers: the grip site is driven by a P-controller through the env's own action law.
# ------------------------------------------------------------------------------------------------
def move_to(env, target, finger, max_steps=60, tol=0.005):
    obs = env._get_obs()
    for _ in range(max_steps):
        err = np.asarray(target) - obs["observation"][:3]
        if np.linalg.norm(err) < tol:
            break
        obs, *_ = env.step(np.append(np.clip(err / fe.ACTION_SCALE, -1, 1), finger))
    return obs


def hold(env, finger, steps):
    for _ in range(steps):
        obs, *_ = env.step([0.0, 0.0, 0.0, finger])
    return obs


def pick_and_place(env, src, dst):
    p = env.block_positions()
    move_to(env, p[src] + (0, 0, 0.10), finger=1)  # above the block, fingers open
    move_to(env, p[src], finger=1)  # grip site at the block centre
    hold(env, -1, 8)  # close
    move_to(env, np.r_[p[src][:2], p[dst][2] + 0.12], finger=-1)  # lift
    move_to(env, p[dst] + (0, 0, 0.12), finger=-1)  # carry
    move_to(env, p[dst] + (0, 0, 0.055), finger=-1)  # lower onto the target block
    hold(env, 1, 5)  # release
    move_to(env, p[dst] + (0, 0, 0.15), finger=1)  # retreat
    return hold(env, 0, 10)


def push_together(env, i, j, stop=0.075):
    p = env.block_positions()
    u = p[j] - p[i]
    u[2] = 0.0
    u /= np.linalg.norm(u)
    move_to(env, p[i] - 0.06 * u + (0, 0, 0.08), finger=-1)
    move_to(env, p[i] - 0.06 * u, finger=-1)  # fingers behind block i, at its height
    for _ in range(80):
        p = env.block_positions()
        if np.linalg.norm(p[i] - p[j]) < stop:
            break
        env.step(np.append(0.3 * u[:2], [0.0, -1.0]))
    move_to(env, env._get_obs()["observation"][:3] + (0, 0, 0.1), finger=-1)
    return hold(env, 0, 10)


def first_all_apart_seed(n=5):
    for seed in range(100):
        env = fe.FetchManipulateEnv(n_blocks=n)
        obs, _ = env.reset(seed=seed)
        if (obs["achieved_goal"] == -1).all():
            return env
    raise AssertionError("no reset with all blocks apart in 100 seeds")


# ------------------------------------------------------------------------------------------------
# 1-2. Gymnasium API and shapes
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 4, 5])
@pytest.mark.filterwarnings("error")  # clean: no checker warning either
def test_registered_env_passes_gymnasium_check_env_without_warnings(n):
    # check_env's own render check opens every render mode, "human" included, which needs a display;
    # rgb_array rendering goes through the same passive checker below.
    env = gym.make(f"FetchManipulate{n}-v0")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("n, obs_dim, goal_dim", [(5, 85, 30), (3, 55, 9), (2, 40, 3), (4, 70, 18)])
def test_observation_and_goal_sizes_follow_10_plus_15n_and_layout(n, obs_dim, goal_dim):
    env = gym.make(f"FetchManipulate{n}-v0")
    obs, _ = env.reset(seed=1)
    assert obs["observation"].shape == (obs_dim,) and obs["observation"].dtype == np.float32
    for key in ("achieved_goal", "desired_goal"):
        assert obs[key].shape == (goal_dim,) and obs[key].dtype == np.float32
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs["observation"].dtype == np.float32 and isinstance(reward, float)
    assert terminated is False and truncated is False
    assert env.spec.max_episode_steps == 40


def test_observation_slices_hold_grip_fingers_and_block_features():
    env = make(5)
    p = np.array([[x, y, Z0] for x, y in FAR])
    obs = env.place_blocks(p)["observation"]
    grip = obs[0:3]
    np.testing.assert_allclose(grip, fe.INITIAL_GRIP_POS, atol=1e-6)
    np.testing.assert_allclose(obs[3:5], 0.0, atol=1e-9)
    for i in range(5):
        b = obs[10 + 15 * i : 25 + 15 * i]
        np.testing.assert_allclose(b[0:3], p[i], atol=1e-6)  # position
        np.testing.assert_allclose(b[3:6], 0.0, atol=1e-6)  # upright: zero Euler angles
        np.testing.assert_allclose(b[12:15], p[i] - grip, atol=1e-6)  # relative position


def test_block_velocities_are_scaled_by_dt_and_relative_to_the_gripper():
    env = make(3)
    obs = settle(env, 1)
    for _ in range(3):
        before = obs["observation"][:3].copy()
        obs, *_ = env.step([1.0, 0.0, 0.0, 0.0])  # the gripper moves, the blocks rest
    o = obs["observation"]
    grip_vel = o[5:8]
    # Velocity x dt is metres per 0.04 s step: about the last step's displacement (a few cm), not m/s.
    step = o[:3] - before
    assert step[0] > 0.01 and 0.5 < grip_vel[0] / step[0] < 2 and np.abs(grip_vel[1:]).max() < 0.005
    for i in range(3):
        np.testing.assert_allclose(o[10 + 15 * i + 9 : 10 + 15 * i + 12], -grip_vel, atol=1e-3)


# ------------------------------------------------------------------------------------------------
# 2b. Euler angles: gym-robotics' rotations.mat2euler convention (SPEC §3)
# ------------------------------------------------------------------------------------------------
def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def from_euler(roll, pitch, yaw):
    """gym-robotics' convention by definition: rotate about x, then the new y, then the new z."""
    return rot_x(roll) @ rot_y(pitch) @ rot_z(yaw)


def angle_gap(a, b):
    return np.abs((np.asarray(a) - b + np.pi) % (2 * np.pi) - np.pi)  # compared modulo 2 pi


def random_euler(n=1000, seed=0):
    """n (roll, pitch, yaw) triples inside the convention's ranges, a quarter each about one, two
    (every pair) and three axes, plus a quarter near the +-pi wrap of roll and yaw."""
    rng = np.random.default_rng(seed)
    e = rng.uniform((-np.pi, -np.pi / 2 + 1e-3, -np.pi), (np.pi, np.pi / 2 - 1e-3, np.pi), (n, 3))
    k = n // 4
    e[:k] *= np.eye(3)[rng.integers(0, 3, k)]  # one axis
    e[k : 2 * k] *= 1 - np.eye(3)[rng.integers(0, 3, k)]  # two axes
    e[3 * k :, [0, 2]] = np.pi - rng.uniform(0, 1e-3, (n - 3 * k, 2)) * rng.choice([-1, 1], (n - 3 * k, 2))
    return e


def test_euler_from_mat_recovers_1000_rotations_in_gym_robotics_mat2euler_convention():
    euler = random_euler()
    mats = np.stack([from_euler(*e) for e in euler]).reshape(-1, 9)
    got = fe.euler_from_mat(mats)
    assert angle_gap(got, euler).max() < 1e-5
    # The convention is MuJoCo's intrinsic "xyz" too (what gym-robotics says it follows).
    quat, mat = np.zeros(4), np.zeros(9)
    for e in euler[::50]:
        mujoco.mju_euler2Quat(quat, e, "xyz")
        mujoco.mju_quat2Mat(mat, quat)
        assert angle_gap(fe.euler_from_mat(mat), e).max() < 1e-5


def test_euler_from_mat_at_gimbal_lock_sets_roll_to_zero_and_keeps_the_rotation():
    for pitch in (np.pi / 2, -np.pi / 2):
        r = from_euler(0.4, pitch, 1.1)
        roll, got_pitch, yaw = fe.euler_from_mat(r.reshape(9))
        assert roll == 0.0 and abs(got_pitch - pitch) < 1e-7
        np.testing.assert_allclose(from_euler(roll, got_pitch, yaw), r, atol=1e-7)


def test_observed_block_orientation_is_its_mat2euler_angles():
    env = make(5)
    env.place_blocks(np.array([[x, y, Z0 + 0.2] for x, y in FAR]))  # in the air: nothing touches them
    euler = random_euler(5, seed=1)
    for i, e in enumerate(euler):
        mujoco.mju_euler2Quat(env._block_qpos[i, 3:], e, "xyz")
    obs = env._get_obs()["observation"]  # a float32 observation
    for i, e in enumerate(euler):
        assert angle_gap(obs[10 + 15 * i + 3 : 10 + 15 * i + 6], e).max() < 1e-5


# ------------------------------------------------------------------------------------------------
# 3. Predicates on constructed scenes; stacks are stable
# ------------------------------------------------------------------------------------------------
def scene(*blocks):
    """Blocks given as (x, y, level); the rest go far away."""
    p = [(x, y, Z0 + 2 * fe.BLOCK_HALF * level) for x, y, level in blocks]
    return np.array(p + [(x, y, Z0) for x, y in FAR[len(p) :]])


X, Y = 1.22, 0.62  # build site, away from the gripper
SCENES = {
    "all apart": (scene(), og.make_config(5)),
    "one close pair": (scene((X, Y, 0), (X + 0.07, Y, 0)), og.make_config(5, close=[(0, 1)])),
    "2-stack": (scene((X, Y, 0), (X, Y, 1)), og.make_config(5, close=[(0, 1)], above=[(1, 0)])),
    "3-stack": (
        scene((X, Y, 0), (X, Y, 1), (X, Y, 2)),
        og.make_config(5, close=[(0, 1), (1, 2)], above=[(1, 0), (2, 1)]),
    ),
    "two 2-stacks": (
        scene((X, Y, 0), (X, Y, 1), (X + 0.2, Y + 0.3, 0), (X + 0.2, Y + 0.3, 1)),
        og.make_config(5, close=[(0, 1), (2, 3)], above=[(1, 0), (3, 2)]),
    ),
    "pyramid": (
        scene((X, Y, 0), (X + 0.052, Y, 0), (X + 0.026, Y, 1)),
        og.make_config(5, close=[(0, 1), (0, 2), (1, 2)], above=[(2, 0), (2, 1)]),
    ),
    "5-stack": (
        scene(*[(X, Y, k) for k in range(5)]),
        og.make_config(5, close=[(k, k + 1) for k in range(4)], above=[(k + 1, k) for k in range(4)]),
    ),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_constructed_scene_has_exact_predicates_and_stays_put(name):
    positions, expected = SCENES[name]
    env = make(5)
    env.place_blocks(positions)
    obs = settle(env, 5)
    np.testing.assert_array_equal(obs["achieved_goal"], expected)
    before = env.block_positions()
    obs = settle(env, 100)
    moved = np.linalg.norm(env.block_positions() - before, axis=1)
    assert moved.max() < 0.005, f"{name}: a block moved {moved.max() * 1e3:.1f} mm"
    np.testing.assert_array_equal(obs["achieved_goal"], expected)


def test_semantic_config_thresholds_match_spec():
    def cfg(p):
        return fe.semantic_config(np.array(p))

    assert cfg([[0, 0, 0], [0.089, 0, 0]])[0] == 1 and cfg([[0, 0, 0], [0.091, 0, 0]])[0] == -1
    # above(1 on 0) is index 1 + 1 for 2 blocks: [close{0,1}, above(0,1), above(1,0)]
    assert cfg([[0, 0, 0], [0.049, 0, 0.05]]).tolist() == [1, -1, 1]
    assert cfg([[0, 0, 0], [0.051, 0, 0.05]]).tolist() == [1, -1, -1]  # too far sideways
    assert cfg([[0, 0, 0], [0, 0, 0.029]]).tolist() == [1, -1, -1]  # too low
    assert cfg([[0, 0, 0], [0, 0, 0.061]]).tolist() == [1, -1, -1]  # too high: floating
    batch = fe.semantic_config(np.zeros((4, 7, 3, 3)))  # any leading batch axes
    assert batch.shape == (4, 7, 9)


# ------------------------------------------------------------------------------------------------
# 4. Grasping and pushing with scripted controllers
# ------------------------------------------------------------------------------------------------
def test_scripted_pick_and_place_builds_block0_on_block1_and_nothing_else():
    env = first_all_apart_seed()
    obs = pick_and_place(env, 0, 1)
    np.testing.assert_array_equal(obs["achieved_goal"], og.make_config(5, close=[(0, 1)], above=[(0, 1)]))


def test_scripted_push_brings_the_closest_pair_together_into_c1():
    env = first_all_apart_seed()
    p = env.block_positions()
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + 9 * np.eye(5)
    i, j = np.unravel_index(d.argmin(), d.shape)
    obs = push_together(env, i, j)
    np.testing.assert_array_equal(obs["achieved_goal"], og.make_config(5, close=[(i, j)]))
    assert env.block_positions()[:, 2].max() < Z0 + 0.005  # pushed, not lifted


# ------------------------------------------------------------------------------------------------
# 4b. The Fetch gripper's geometry, contacts and limits (SPEC §3)
# ------------------------------------------------------------------------------------------------
def test_opening_fingers_for_20_steps_overshoots_the_0_05_limit_by_at_most_2mm():
    env = make(5)
    widest = max(hold(env, 1.0, 1)["observation"][3:5].max() for _ in range(20))
    assert 0.048 < widest <= 0.052  # Fetch's stiff limit: 0.0516; the soft default reached 0.061


def test_a_grasped_block_holds_the_fingers_at_fetchs_0_024():
    env = first_all_apart_seed()
    p = env.block_positions()[0]
    move_to(env, p + (0, 0, 0.10), finger=1)
    move_to(env, p, finger=1)
    hold(env, -1, 8)
    obs = move_to(env, p + (0, 0, 0.10), finger=-1)  # lifted: only the fingers hold it
    assert env.block_positions()[0, 2] > Z0 + 0.08
    # Fetch's jaw faces sit 0.0159 - 0.008 - 0.007 = 0.0009 m off centre: a 5 cm block stops them at
    # 0.025 - 0.0009 = 0.0241 (Fetch's measured hold: 0.024).
    np.testing.assert_allclose(obs["observation"][3:5], 0.024, atol=0.005)


def test_finger_boxes_sit_8mm_inward_with_fetchs_contact_and_limit_parameters():
    m = make(2).model
    for side, inward in (("r", -1), ("l", 1)):
        geom, joint = m.geom(f"finger_{side}_geom"), m.joint(f"finger_{side}_joint")
        np.testing.assert_allclose(geom.pos, (0, inward * 0.008, 0))
        np.testing.assert_allclose(geom.margin, 0.001)
        np.testing.assert_allclose(geom.solimp[:3], (0.99, 0.99, 0.01))
        np.testing.assert_allclose(geom.solref, (0.01, 1))
        assert joint.limited
        np.testing.assert_allclose(joint.range, (0, 0.05))
        np.testing.assert_allclose(joint.solimp[:3], (0.99, 0.999, 0.01))
        np.testing.assert_allclose(joint.solref, (0.01, 1))


# ------------------------------------------------------------------------------------------------
# 4c. The gripper resists rotation as Fetch's does (SPEC §3)
# ------------------------------------------------------------------------------------------------
# A diagonal descent, forward in x and down at equal rates with the fingers open, from a start pose
# that brings the bottom of finger_r (the +y finger) to the height of a block's top face as the finger
# passes over the block's centre: about 0.8 m/s along the diagonal, as an agent comes down on a block.
LANDING = np.array([0.7, 0.0, -0.7, 1.0])
LANDING_RUN = 0.12  # metres of descent (and of forward travel) from the start pose to the top face
FINGER_BOTTOM = 0.0385 - fe.GRIP_OFFSET  # a finger box's lower end, below the grip site


def land_a_finger(env, block):
    """Open the fingers, come down diagonally (LANDING) until finger_r touches the top face of `block`
    (resting upright), then lift. Returns the grip site's speed over the landing step (m/s; None if no
    finger landed on the top face) and the gripper's largest tilt seen after a step (rad)."""
    obs = hold(env, 1.0, 10)
    finger_y = 0.0159 + obs["observation"][3] - 0.008  # finger_r's box centre, off the grip site in y
    top = env.block_positions()[block] + (0, 0, fe.BLOCK_HALF)
    start = top + (-LANDING_RUN, -finger_y, FINGER_BOTTOM + LANDING_RUN)
    move_to(env, start + (0, 0, 0.05), finger=1)  # from above: the finger clears the block
    move_to(env, start, finger=1, tol=0.002)
    obs = hold(env, 1.0, 5)  # at rest
    speed, tilt = None, gripper_tilt(env)
    for _ in range(2 * round(LANDING_RUN / (fe.ACTION_SCALE * LANDING[0]))):  # the face is about halfway
        before = obs["observation"][:3]
        obs, *_ = env.step(LANDING)
        tilt = max(tilt, gripper_tilt(env))
        if finger_on_top_face(env, block):
            speed = np.linalg.norm(obs["observation"][:3] - before) / env.dt
            break
    for _ in range(10):
        env.step([0.0, 0.0, 1.0, 1.0])  # lift off
        tilt = max(tilt, gripper_tilt(env))
    return speed, tilt


def gripper_tilt(env) -> float:
    """Angle (rad) between the gripper's pointing axis (its body +x) and straight down."""
    return float(np.arccos(np.clip(-env.data.xmat[env._gripper][6], -1.0, 1.0)))


def finger_on_top_face(env, block) -> bool:
    """Whether a finger geom touches `block` on its top face: a contact with a vertical normal, at the
    height of the top face, inside its square."""
    m, c = env.model, env.data.contact
    fingers = [m.geom("finger_r_geom").id, m.geom("finger_l_geom").id]
    box = m.body_geomadr[m.body(f"object{block}").id]
    pair = np.isin(c.geom, fingers).any(axis=1) & (c.geom == box).any(axis=1)
    centre = env.block_positions()[block]
    on_top = (np.abs(c.pos[:, 2] - centre[2] - fe.BLOCK_HALF) < 0.003) & (np.abs(c.frame[:, 2]) > 0.95)
    inside = (np.abs(c.pos[:, :2] - centre[:2]) < fe.BLOCK_HALF).all(axis=1)
    return bool((pair & on_top & inside).any())


def test_a_finger_landing_on_a_blocks_top_face_at_0_8_m_s_rolls_the_gripper_under_3_degrees():
    env = make(5)
    env.place_blocks(scene((1.30, 0.70, 0)))
    speed, tilt = land_a_finger(env, 0)
    assert speed is not None, "no finger came down on the block's top face"
    assert 0.6 < speed < 1.0, f"landed at {speed:.2f} m/s, not about 0.8"  # SPEC §3's landing
    # Fetch's gripper turns about 1 degree here; one whose inertia is its boxes' alone, about 17 (SPEC §3).
    assert np.degrees(tilt) < 3.0, f"the gripper rolled {np.degrees(tilt):.1f} degrees"


# ------------------------------------------------------------------------------------------------
# 4d. The workspace box (SPEC §3)
# ------------------------------------------------------------------------------------------------
# The grip site sits GRIP_OFFSET below the gripper body that follows the clipped mocap. The weld is
# soft: in free space the body lags or overshoots the target by under 1 mm, but a finger pressed
# against the table's side pushes the gripper out by more (at most 2.2 cm over 540 random and
# bang-bang sequences of 400 steps; the worst had a finger on the table). The mocap target never leaves.
PUSH = 0.03


def grip_box(margin: float = PUSH):
    """(low, high) corners the grip site must stay within (a function: benchmarks/bench_grasp.py imports
    this file's controllers against older envs without a workspace)."""
    offset = (0, 0, fe.GRIP_OFFSET)
    return fe.WORKSPACE_LOW - offset - margin, fe.WORKSPACE_HIGH - offset + margin


CORNERS = [np.r_[x, y, z, 0.0] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]


def assert_stays_in_the_workspace(actions, seed):
    env = fe.FetchManipulateEnv(3)
    env.reset(seed=seed)
    low, high = grip_box()
    for a in actions:
        obs, *_ = env.step(a)
        grip = obs["observation"][:3]
        assert np.all(grip >= low) and np.all(grip <= high), f"grip site at {grip}"
        target = env.data.mocap_pos[0]
        assert np.all(target >= fe.WORKSPACE_LOW) and np.all(target <= fe.WORKSPACE_HIGH), f"mocap at {target}"
        assert env.observation_space.contains(obs)
    return grip


@pytest.mark.parametrize("corner", range(8))
def test_400_steps_toward_a_corner_stop_the_gripper_at_that_corner_of_the_workspace(corner):
    a = CORNERS[corner]
    grip = assert_stays_in_the_workspace([a] * 400, seed=corner)
    wall = np.where(a[:3] > 0, *grip_box(margin=0.0)[::-1])
    # Reaches its corner, except that going down the table stops it first.
    np.testing.assert_allclose(grip[:2], wall[:2], atol=0.003)
    assert abs(grip[2] - wall[2]) < 0.003 or (a[2] < 0 and grip[2] > fe.TABLE_Z)


@settings(max_examples=12, deadline=None, derandomize=True)  # the same examples every run
@given(
    seed=st.integers(0, 2**16),
    hold_steps=st.sampled_from([1, 5, 40]),
    extreme=st.booleans(),
)
def test_no_400_step_action_sequence_takes_the_gripper_out_of_the_workspace(seed, hold_steps, extreme):
    rng = np.random.default_rng(seed)
    n = 400 // hold_steps
    actions = rng.choice([-1.0, 1.0], (n, 4)) * 3 if extreme else rng.uniform(-1, 1, (n, 4))  # beyond the box too
    assert_stays_in_the_workspace(np.repeat(actions, hold_steps, axis=0), seed % 100)


def test_env_version_names_this_physics_as_version_3():
    # Checkpoints store it and are refused under another version: bumped with this physics (commit 22634d4).
    assert isinstance(fe.ENV_VERSION, int) and fe.ENV_VERSION == 3


# ------------------------------------------------------------------------------------------------
# 5. Action law and initial state
# ------------------------------------------------------------------------------------------------
def test_initial_grip_site_is_at_the_fetch_start_pose_with_fingers_closed():
    for seed in range(3):
        env = fe.FetchManipulateEnv(5)
        obs, _ = env.reset(seed=seed)
        assert np.abs(obs["observation"][:3] - fe.INITIAL_GRIP_POS).max() < 1e-3
        assert np.abs(obs["observation"][3:5]).max() < 1e-6


def test_ten_full_x_actions_move_the_grip_site_20_to_35_cm():
    env = make(5)
    start = env._get_obs()["observation"][:3].copy()
    for _ in range(10):
        obs, *_ = env.step([1.0, 0.0, 0.0, 0.0])
    dx, dy, dz = obs["observation"][:3] - start
    assert 0.20 <= dx <= 0.35 and abs(dy) < 0.005 and abs(dz) < 0.005


def test_each_step_puts_the_mocap_target_0_05_per_unit_action_from_the_gripper_body():
    env = make(3)
    for a in ([1.0, 0.0, 0.0, 0.0], [0.3, -0.6, 0.2, 0.0], [-1.0, 0.5, 1.0, 1.0], [0.0, 0.0, -0.4, -1.0]):
        body = env.data.body("gripper").xpos.copy()  # where the step snaps the mocap to (SPEC §3)
        env.step(a)
        np.testing.assert_allclose(env.data.mocap_pos[0], body + 0.05 * np.array(a[:3]), atol=1e-9)


def test_finger_action_opens_to_about_5cm_and_closes_again():
    env = make(5)
    obs = hold(env, 1.0, 10)
    np.testing.assert_allclose(obs["observation"][3:5], 0.05, atol=0.002)
    obs = hold(env, -1.0, 10)
    np.testing.assert_allclose(obs["observation"][3:5], 0.0, atol=0.002)


def test_actions_are_clipped_to_the_unit_box():
    a, b = make(5), make(5)
    for _ in range(5):
        oa, *_ = a.step([5.0, -7.0, 3.0, 9.0])
        ob, *_ = b.step([1.0, -1.0, 1.0, 1.0])
    np.testing.assert_array_equal(oa["observation"], ob["observation"])


# ------------------------------------------------------------------------------------------------
# 6. Seeding and reset distribution
# ------------------------------------------------------------------------------------------------
def rollout(seed, actions):
    env = fe.FetchManipulateEnv(5)
    obs, _ = env.reset(seed=seed)
    out = [obs["observation"]]
    for a in actions:
        out.append(env.step(a)[0]["observation"])
    return np.array(out)


def test_same_seed_and_actions_reproduce_observations_exactly():
    actions = np.random.default_rng(0).uniform(-1, 1, (40, 4))
    np.testing.assert_array_equal(rollout(7, actions), rollout(7, actions))
    assert not np.array_equal(rollout(7, actions)[0], rollout(8, actions)[0])


def test_resets_rest_blocks_on_the_table_apart_and_never_stacked():
    env = fe.FetchManipulateEnv(5)
    env.reset(seed=123)
    nc = 10
    close_seen = False
    for _ in range(300):
        obs, _ = env.reset()
        p = env.block_positions()
        d = np.linalg.norm(p[:, None, :2] - p[None, :, :2], axis=-1) + np.eye(5)
        assert d.min() >= fe.MIN_SPAWN_DIST - 1e-12
        np.testing.assert_allclose(p[:, 2], Z0)
        assert np.all(np.abs(p[:, :2] - fe.INITIAL_GRIP_POS[:2]) <= fe.SPAWN_RANGE)
        assert (obs["achieved_goal"][nc:] == -1).all()
        close_seen |= bool((obs["achieved_goal"][:nc] == 1).any())
    assert close_seen  # close pairs may be true at reset (SPEC §3)


# ------------------------------------------------------------------------------------------------
# 7. Rewards
# ------------------------------------------------------------------------------------------------
def test_compute_reward_is_vectorised_and_matches_is_success():
    env = make(3)
    goal = og.make_config(3, close=[(0, 1)], above=[(0, 1)])
    obs, _ = env.reset(seed=0, options={"goal": goal})
    np.testing.assert_array_equal(obs["desired_goal"], goal)
    obs, reward, _, _, info = env.step(np.zeros(4))
    assert reward == 0.0 and info["is_success"] == reward
    ach = np.stack([goal, -goal, goal])
    des = np.stack([goal, goal, -np.ones(9, dtype=np.float32)])
    np.testing.assert_array_equal(env.compute_reward(ach, des, {}), [1.0, 0.0, 0.0])
    assert env.compute_reward(np.zeros((2, 5, 9)), np.zeros((2, 5, 9)), {}).shape == (2, 5)
    # The reward of a step is the reward of its achieved goal.
    env.set_goal(obs["achieved_goal"])
    obs, reward, _, _, info = env.step(np.zeros(4))
    assert reward == 1.0 and info["is_success"] == 1.0


def test_set_goal_changes_the_goal_but_not_the_physics():
    env = make(3)
    settle(env, 3)
    before = env.data.qpos.copy(), env.data.qvel.copy()
    goal = og.make_config(3, close=[(1, 2)])
    obs = env.set_goal(goal)
    np.testing.assert_array_equal(obs["desired_goal"], goal)
    np.testing.assert_array_equal(env.data.qpos, before[0])
    np.testing.assert_array_equal(env.data.qvel, before[1])


# ------------------------------------------------------------------------------------------------
# 8. Bad input
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "goal, message",
    [(np.ones(29), r"shape \(30,\).*\(29,\)"), (np.r_[np.ones(29), 0.5], r"-1 or \+1.*0\.5"), ([np.nan] * 30, "nan")],
)
def test_bad_goals_raise_a_value_error_naming_the_value(goal, message):
    env = make(5)
    with pytest.raises(ValueError, match=message):
        env.reset(options={"goal": goal})
    with pytest.raises(ValueError, match=message):
        env.set_goal(goal)


def test_nan_or_misshaped_actions_raise_a_value_error_naming_the_value():
    env = make(5)
    with pytest.raises(ValueError, match="nan"):
        env.step([0.0, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"\(3,\)"):
        env.step([0.0, 0.0, 0.0])


@pytest.mark.parametrize("n", [1, 6, 0, 2.5, "3", True])
def test_n_blocks_outside_2_to_5_is_rejected_naming_the_value(n):
    with pytest.raises(ValueError, match=repr(n) if isinstance(n, str | float | bool) else str(n)):
        fe.FetchManipulateEnv(n_blocks=n)


def test_unknown_render_mode_is_rejected():
    with pytest.raises(ValueError, match="'depth'"):
        fe.FetchManipulateEnv(3, render_mode="depth")


# ------------------------------------------------------------------------------------------------
# 9. Rendering (headless in CI through OSMesa)
# ------------------------------------------------------------------------------------------------
def test_rgb_array_render_shows_the_table_and_every_block(gl):
    mujoco = gl
    env = fe.FetchManipulateEnv(5, render_mode="rgb_array", width=320, height=240)
    env.reset(seed=0)
    env_render_passive_checker(env)
    img = env.render()
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8 and img.std() > 10
    # Which geoms are visible: segmentation rendering from the same camera.
    seg = mujoco.Renderer(env.model, 240, 320)
    seg.enable_segmentation_rendering()
    seg.update_scene(env.data, camera="external")
    ids = seg.render()[..., 0]
    visible = {env.model.geom(int(g)).name for g in np.unique(ids) if g >= 0}
    assert "table" in visible
    bodies = {env.model.body(int(env.model.geom_bodyid[g])).name for g in np.unique(ids) if g >= 0}
    assert {f"object{i}" for i in range(5)} <= bodies, f"visible bodies: {bodies}"
    seg.close()
    env.close()
