"""Success is defined once (fetch5_env.goal_reached, SPEC §2): the env's reward, step's is_success, the
HER reward of every training script and a segment's success agree on random configs."""

import ast
import inspect
from pathlib import Path

import numpy as np
import pytest
import torch

import fetch5_env as fe
import gangstr_hme as gh
import lp_baseline
import oracle_graph as og
import vds_baseline

ROOT = Path(__file__).resolve().parent.parent
N = 3
DIM = og.config_dim(N)


def random_pairs(rng, n):
    """(achieved, desired) configs: half of them equal, half differing in 1 to 3 predicates."""
    ag = rng.choice([-1.0, 1.0], size=(n, DIM)).astype(np.float32)
    g = ag.copy()
    for i in range(n // 2, n):
        g[i, rng.choice(DIM, size=rng.integers(1, 4), replace=False)] *= -1
    return ag, g


def test_the_env_reward_is_the_one_success_rule_on_random_configs():
    ag, g = random_pairs(np.random.default_rng(0), 200)
    env = fe.FetchManipulateEnv(n_blocks=N)
    expected = [float(np.array_equal(a, b)) for a, b in zip(ag, g, strict=True)]  # brute force, pair by pair
    np.testing.assert_array_equal(env.compute_reward(ag, g), expected)
    np.testing.assert_array_equal(fe.goal_reached(ag, g), np.array(expected, dtype=bool))


def test_step_success_agrees_with_the_env_reward_for_random_goals():
    env = fe.FetchManipulateEnv(n_blocks=N)
    obs, _ = env.reset(seed=1)
    rng = np.random.default_rng(1)
    _, goals = random_pairs(rng, 20)
    goals[: len(goals) // 2] = obs["achieved_goal"]  # half of them the config the blocks are in
    outcomes = []
    for goal in goals:
        env.set_goal(goal)
        obs, reward, _, _, info = env.step(np.zeros(4))  # the blocks rest: the config stays
        assert reward == info["is_success"] == env.compute_reward(obs["achieved_goal"], goal)
        outcomes.append(reward)
    assert set(outcomes) == {0.0, 1.0}


@pytest.mark.parametrize("script", [gh, lp_baseline, vds_baseline])
def test_her_rewards_agree_with_the_env_reward_on_random_configs(script):
    rng = np.random.default_rng(2)
    buf = script.ReplayBuffer(1, 50, 5, gh.BODY + gh.PER_BLOCK * N, DIM)
    ag = rng.choice([-1, 1], size=(1, 50, 6, DIM)).astype(np.int8)
    ag[:, ::2, 1:] = ag[:, ::2, :1]  # every other segment never moves: its relabelled goals are reached
    obs = rng.normal(size=(1, 50, 6, buf.obs.shape[-1])).astype(np.float32)
    buf.store(obs, ag, ag[:, :, -1].copy(), rng.normal(size=(1, 50, 5, 4)).astype(np.float32))
    batch = buf.sample(400, [rng], her_prob=0.5, strategy="future")
    env = fe.FetchManipulateEnv(n_blocks=N)
    np.testing.assert_array_equal(batch["reward"], env.compute_reward(batch["ag_next"], batch["g"]))
    assert 0 < batch["reward"].mean() < 1


def test_segment_success_agrees_with_the_env_reward():
    args = gh.Args(n_blocks=N, segment_len=3, stable_steps=2, num_envs=2)
    torch.manual_seed(0)
    agent = gh.SAC(args, gh.BODY + gh.PER_BLOCK * N, torch.device("cpu"))
    workers = [gh.Worker(args, i) for i in range(2)]
    rng = np.random.default_rng(3)
    successes = []
    for _ in range(4):
        here = [gh.current_config(w.env) for w in workers]
        other = [int(og.to_mask(g)) for g in random_pairs(rng, 2)[1]]
        for goals in (here, other):
            requests = [gh.Request(goal, deterministic=True) for goal in goals]
            for w, seg in zip(workers, gh.run_segments(agent, workers, requests), strict=True):
                assert seg.success == bool(w.env.compute_reward(seg.ag[-1], seg.g))
                assert seg.success == bool(w.env.compute_reward(w.env.set_goal(seg.g)["achieved_goal"], seg.g))
                successes.append(seg.success)
    assert set(successes) == {True, False}


@pytest.mark.parametrize("name", ["gangstr_hme.py", "lp_baseline.py", "vds_baseline.py"])
def test_success_is_written_once_and_the_learners_call_it(name):
    """HER rewards and segment success go through fetch5_env.goal_reached, the rule the env's
    compute_reward (and so step) uses; no script writes its own array comparison for them."""
    tree = ast.parse((ROOT / name).read_text())
    calls = {
        fn.name: {ast.unparse(c.func) for c in ast.walk(fn) if isinstance(c, ast.Call)}
        for fn in ast.walk(tree)
        if isinstance(fn, ast.FunctionDef)
    }
    assert "fetch5_env.goal_reached" in calls["sample"] and "fetch5_env.goal_reached" in calls["run_segments"]
    assert "goal_reached" in inspect.getsource(fe.FetchManipulateEnv.compute_reward)
    assert "self.compute_reward" in inspect.getsource(fe.FetchManipulateEnv.step)
