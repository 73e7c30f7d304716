"""gangstr_hme.py, the learner: GNN actor-critic, SAC, HER, normalizer, semantic graph and planners,
the training loop, its outputs, resume and command line (SPEC §5, §6, §9, §10)."""

import contextlib
import copy
import csv
import dataclasses
import itertools
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import inprocess
import numpy as np
import pytest
import torch
from chisquare import uniform_pvalue

import fetch5_env
import gangstr_hme as gh
import lp_baseline as lp
import oracle_graph as og
import plumbing
import speed
import vds_baseline as vds

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--n-epochs", "1", "--n-cycles", "2", "--n-segments", "3", "--n-updates", "2", "--batch-size", "16",
        "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "1", "--threads", "1"]  # fmt: skip


def run_script(*args, runs_dir) -> subprocess.CompletedProcess:
    return inprocess.run_script("gangstr_hme.py", *args, runs_dir=runs_dir)  # as in a new process (see there)


def read_rows(run_dir: Path):
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def tensorboard_scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar TensorBoard shows for a run folder: tag -> its (step, value) events."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: PLC0415

    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})  # 0: keep every event
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


# ------------------------------------------------------------------------------------------------
# 1. Smoke: the whole loop writes a run folder
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_blocks", [3, 5])
def test_tiny_run_collects_updates_evaluates_logs_and_checkpoints(tmp_path, n_blocks):
    out = run_script("--sp-ratio", "0", "--n-blocks", str(n_blocks), *TINY, runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    (run_dir,) = tmp_path.iterdir()
    assert run_dir.name.startswith("gangstr_hme__0__")
    assert {"config.json", "progress.csv", "checkpoint.pt"} <= {p.name for p in run_dir.iterdir()}
    assert any(p.name.startswith("events.out.tfevents") for p in run_dir.iterdir())
    (row,) = read_rows(run_dir)
    assert int(row["env_steps"]) == 2 * 3 * 10
    assert 0.0 <= float(row["global_sr"]) <= 1.0 and f"sr_{list(og.evaluation_classes(n_blocks))[-1]}" in row
    # TensorBoard: every progress.csv column but the epoch (its step) exactly once, under its group.
    scalars = tensorboard_scalars(run_dir)
    columns = [c for c in row if c != "epoch"]
    groups = ("eval", "losses", "graph", "time", "charts", "sampler")
    assert Counter(tag.split("/", 1)[-1] for tag in scalars) == Counter(columns)
    assert sorted(scalars) == sorted(plumbing.tensorboard_tag(c) for c in columns)
    assert all(tag.split("/")[0] in groups and tag.count("/") == 1 for tag in scalars)
    assert {tag.split("/")[0] for tag in scalars} == set(groups)
    for c in columns:
        ((step, value),) = scalars[plumbing.tensorboard_tag(c)]
        assert step == 0 and value == pytest.approx(float(row[c]), rel=1e-6, nan_ok=True), c
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert state["counters"]["epoch"] == 1 and state["args"]["n_blocks"] == n_blocks
    assert "SR" in out.stdout and "epoch   0" in out.stdout and re.search(r"\| critic loss \d+\.\d{3} \|", out.stdout)


# ------------------------------------------------------------------------------------------------
# 2. The GNN
# ------------------------------------------------------------------------------------------------
def random_inputs(n, batch=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, 10 + 15 * n, generator=g)
    ag = torch.where(torch.rand(batch, og.config_dim(n), generator=g) < 0.3, 1.0, -1.0)
    goal = torch.where(torch.rand(batch, og.config_dim(n), generator=g) < 0.3, 1.0, -1.0)
    act = torch.rand(batch, 4, generator=g) * 2 - 1
    return obs, ag, goal, act


def forward(agent, obs, ag, goal, act):
    body, blocks = gh.split_obs(obs, agent.gi.n)
    msg = agent.critic.messages(agent.gi, blocks, goal - ag)
    mean, log_std = agent.actor(body, blocks, msg)
    return torch.cat([mean, log_std, *[q[:, None] for q in agent.critic.q(body, blocks, act, msg)]], dim=1)


@pytest.mark.parametrize("n", [3, 5])
def test_gnn_outputs_are_invariant_to_a_consistent_permutation_of_the_blocks(n):
    agent = gh.SAC(gh.Args(n_blocks=n), 10 + 15 * n, torch.device("cpu"))
    obs, ag, goal, act = random_inputs(n)
    ref = forward(agent, obs, ag, goal, act)
    perms = og.permutations(n)
    for k in [1, len(perms) // 2, len(perms) - 1]:
        p = torch.tensor(perms[k])
        blocks = obs[:, 10:].reshape(len(obs), n, 15)
        moved = torch.empty_like(blocks)
        moved[:, p] = blocks  # block p(a) takes block a's place
        obs_p = torch.cat([obs[:, :10], moved.reshape(len(obs), -1)], dim=1)
        src = torch.tensor(og.permutation_sources(n)[k])
        out = forward(agent, obs_p, ag[:, src], goal[:, src], act)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(forward(agent, obs, ag, -goal, act), ref)  # the goal matters


def test_a_blocks_message_is_the_max_over_its_outgoing_edges_of_the_message_net_on_the_spec_edge_input():
    n = 3
    agent = gh.SAC(gh.Args(n_blocks=n), 10 + 15 * n, torch.device("cpu"))
    obs, ag, goal, _ = random_inputs(n)
    _, blocks = gh.split_obs(obs, n)
    gap = goal - ag
    close = {frozenset(p): k for k, p in enumerate(og.close_pairs(n).tolist())}
    above = {tuple(p): len(close) + k for k, p in enumerate(og.above_pairs(n).tolist())}
    expected = torch.empty(len(obs), n, 24)
    with torch.no_grad():
        for i in range(n):  # SPEC §5: edge (i, j) reads [gap at close{i,j}, gap at i on j, pos i, pos j]
            edges = [torch.cat([gap[:, [close[frozenset((i, j))], above[i, j]]], blocks[:, i, :3], blocks[:, j, :3]],
                               dim=1) for j in range(n) if j != i]  # fmt: skip
            expected[:, i] = torch.stack([agent.critic.message(e) for e in edges]).amax(0)
        torch.testing.assert_close(agent.critic.messages(agent.gi, blocks, gap), expected)


@pytest.mark.parametrize("out_relu", [True, False])
def test_every_net_is_linear_relu_linear_with_the_final_relu_only_where_the_spec_has_it(out_relu):
    torch.manual_seed(0)
    net = gh.MLP(7, 16, 5, out_relu=out_relu)
    x = torch.randn(3, 4, 7)
    h = (x @ net.hidden.weight.T + net.hidden.bias).clamp(min=0)
    y = h @ net.out.weight.T + net.out.bias
    torch.testing.assert_close(net(x), y.clamp(min=0) if out_relu else y)
    assert (y < 0).any()  # so that the final ReLU, or its absence, shows
    torch.testing.assert_close(speed.weight_view(net)(x), net(x))  # the acting view computes the same


def test_parameter_count_matches_the_layer_sizes_of_the_spec():
    def linear(i, o):
        return i * o + o

    message = linear(8, 256) + linear(256, 24)
    actor = linear(49, 256) + linear(256, 147) + linear(147, 256) + 2 * linear(256, 4)
    critic = message + 2 * (linear(53, 256) + linear(256, 159) + linear(159, 256) + linear(256, 1))
    agent = gh.SAC(gh.Args(n_blocks=5), 85, torch.device("cpu"))
    assert sum(p.numel() for p in agent.actor.parameters()) == actor
    assert sum(p.numel() for p in agent.critic.parameters()) == critic
    assert all(b.abs().sum() == 0 for name, b in agent.critic.named_parameters() if name.endswith("bias"))


# ------------------------------------------------------------------------------------------------
# 3. HER, SAC, target updates, normalizer
# ------------------------------------------------------------------------------------------------
def filled_buffer(n_seg=50, T=10, dim=9, seed=0):
    rng = np.random.default_rng(seed)
    buf = gh.ReplayBuffer(1, n_seg, T, 55, dim)  # one worker's
    ag = np.where(rng.random((1, n_seg, T + 1, dim)) < 0.5, 1, -1).astype(np.float32)
    g = np.ones((1, n_seg, dim), np.float32)  # never achieved: any match with an achieved config is a relabel
    buf.store(rng.normal(size=(1, n_seg, T + 1, 55)).astype(np.float32), ag, g, rng.normal(size=(1, n_seg, T, 4)))
    return buf


def test_acting_follows_every_update_and_checkpoint_load_of_the_trained_weights():
    agent = gh.SAC(gh.Args(n_blocks=3), 55, torch.device("cpu"))
    agent.normalizer.add(np.zeros(55), np.ones(55) * 4, 4)
    obs, ag, goal, _ = random_inputs(3, batch=1)
    o, a, g = obs[0].numpy(), ag[0].numpy(), goal[0].numpy()

    def policy_mean():  # the trainable networks' deterministic action
        with torch.no_grad():
            return torch.tanh(forward(agent, obs, ag, goal, torch.zeros(1, 4))[0, :4]).numpy()

    before = agent.act(o[None], a[None], g[None])[0]
    np.testing.assert_allclose(before, policy_mean(), rtol=1e-5, atol=1e-6)
    agent.update(filled_buffer().sample(32, [np.random.default_rng(0)], 0.8, "final"))
    after = agent.act(o[None], a[None], g[None])[0]
    assert not np.allclose(before, after)
    np.testing.assert_allclose(after, policy_mean(), rtol=1e-5, atol=1e-6)
    other = gh.SAC(gh.Args(n_blocks=3, seed=9), 55, torch.device("cpu"))
    agent.actor.load_state_dict(other.actor.state_dict())
    agent.critic.load_state_dict(other.critic.state_dict())
    np.testing.assert_allclose(agent.act(o[None], a[None], g[None])[0], policy_mean(), rtol=1e-5, atol=1e-6)
    acting = [*vars(agent.acting_actor.node.hidden).values(), agent.acting_critic.message.hidden.weight]
    assert not any(isinstance(t, torch.Tensor) and t.requires_grad for t in acting)


def sample_origins(buf, b) -> np.ndarray:
    """(segment, step) of each transition of batch b, found by its observation (all differ in filled_buffer)."""
    seg_len = buf.actions.shape[2]
    where = {buf.obs[0, e, t].tobytes(): (e, t) for e in range(buf.size) for t in range(seg_len)}
    return np.array([where[o.tobytes()] for o in b["obs"]])


def test_her_final_relabels_about_80_percent_with_the_last_achieved_config_and_recomputes_rewards():
    buf = filled_buffer()
    rng = np.random.default_rng(1)
    b = buf.sample(20000, [rng], her_prob=1 - 1 / (1 + 4), strategy="final")
    seg = sample_origins(buf, b)[:, 0]
    relabelled = (b["g"] == buf.ag[0, seg, -1]).all(1)  # the final config of the transition's own segment
    assert abs(relabelled.mean() - 0.8) < 0.015
    assert ((b["g"] == 1).all(1) | relabelled).all()  # every goal is the original or its segment's final config
    np.testing.assert_array_equal(b["reward"], (b["ag_next"] == b["g"]).all(1).astype(np.float32))
    assert 0 < b["reward"].mean() < 1


def test_her_future_relabels_with_a_later_achieved_config_of_the_same_segment():
    buf = filled_buffer(n_seg=20, T=10)
    b = buf.sample(4000, [np.random.default_rng(2)], her_prob=1.0, strategy="future")
    seg, t = sample_origins(buf, b).T
    matches = (buf.ag[0, seg] == b["g"][:, None, :]).all(-1)  # (4000, 11): the own segment's configs equal to g
    later = np.arange(11)[None, :] > t[:, None]
    assert (matches & later).any(1).all()  # each goal: an achieved config of its segment after its step
    assert len(np.unique(seg)) == 20


@pytest.mark.parametrize("her_k, share", [(4, 0.8), (1, 0.5), (0, 0.0)])
def test_training_relabels_1_minus_1_over_1_plus_her_k_of_its_goals(monkeypatch, her_k, share):
    """SPEC §5: HER relabels with probability 1 - 1 / (1 + k), 0.8 for the paper's k = 4 (Learner.train)."""
    learner = gh.Learner(gh.Args(n_blocks=3, her_k=her_k, n_updates=1, batch_size=4000), torch.device("cpu"))
    learner.buffer = filled_buffer()  # goals never achieved: a goal that is not all ones was relabelled
    batches = []
    monkeypatch.setattr(learner.agent, "update", lambda batch: batches.append(batch) or {})
    learner.agent.last_batch = learner.agent.last_target = None
    learner.train([np.random.default_rng(0)])
    (batch,) = batches
    assert abs((batch["g"] != 1).any(1).mean() - share) < 0.03


def squashed_gaussian(actor, body, blocks, msg, noise):
    """SPEC §5's action and log-probability, written out: u = mean + std x noise, a = tanh(u),
    log pi = log N(u; mean, std) - sum log(1 - a^2 + 1e-6) (the tanh correction)."""
    mean, log_std = actor(body, blocks, msg)
    u = mean + log_std.exp() * noise
    a = torch.tanh(u)
    gauss = torch.distributions.Normal(mean, log_std.exp()).log_prob(u).sum(-1)
    return a, gauss - torch.log(1 - a.pow(2) + 1e-6).sum(-1)


def test_sac_losses_follow_the_spec_on_a_tiny_batch():
    args = gh.Args(n_blocks=3)
    agent = gh.SAC(args, 55, torch.device("cpu"))
    agent.normalizer.add(np.zeros(55), np.ones(55) * 4, 4)  # mean 0, std 1: normalizing is clipping
    torch.manual_seed(1)
    agent.critic_target.load_state_dict(gh.Critic(3).state_dict())  # a target critic unlike the critic
    obs, ag, goal, act = random_inputs(3, batch=3)
    obs2, ag2, _, _ = random_inputs(3, batch=3, seed=1)
    batch = dict(obs=obs.numpy(), obs_next=obs2.numpy(), ag=ag.numpy(), ag_next=ag2.numpy(), g=goal.numpy(),
                 action=act.numpy(), reward=np.array([1.0, 0.0, 1.0], np.float32),
                 noise_next=np.float32([[0.1, -2, 0.5, 0]] * 3),  # the draws of the next action's sample
                 noise_pi=np.float32([[1, 0.3, -0.2, 0.7]] * 3))  # ... and of the actor loss's  # fmt: skip
    t = agent.to_tensors(batch)
    critic_loss, actor_loss, _, _ = agent.losses(t)
    # By hand, with the same standard normal draws.
    b1, k1 = gh.split_obs(t["obs"], 3)
    b2, k2 = gh.split_obs(t["obs_next"], 3)
    with torch.no_grad():
        msg2 = agent.critic.messages(agent.gi, k2, t["g"] - t["ag_next"])
        a2, logp2 = squashed_gaussian(agent.actor, b2, k2, msg2, t["noise_next"])
        tq = agent.critic_target.q(b2, k2, a2, agent.critic_target.messages(agent.gi, k2, t["g"] - t["ag_next"]))
        y = t["reward"] + 0.99 * (torch.min(tq[0], tq[1]) - 0.2 * logp2)
        msg = agent.critic.messages(agent.gi, k1, t["g"] - t["ag"])
        q1, q2 = agent.critic.q(b1, k1, t["action"], msg)
        expected_critic = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
        pi, logp = squashed_gaussian(agent.actor, b1, k1, msg, t["noise_pi"])
        qp = agent.critic.q(b1, k1, pi, msg)
        expected_actor = (0.2 * logp - torch.min(qp[0], qp[1])).mean()
    torch.testing.assert_close(critic_loss, expected_critic, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(actor_loss, expected_actor, rtol=1e-5, atol=1e-5)


def test_actor_loss_moves_the_actor_only_and_the_message_net_learns_from_the_critic_loss():
    batch = filled_buffer().sample(32, [np.random.default_rng(0)], 0.8, "final")
    agents = []
    for _ in range(2):  # the same networks twice: one updated, one to take each loss's gradient alone
        torch.manual_seed(0)
        agents.append(gh.SAC(gh.Args(n_blocks=3, precision="fp32"), 55, torch.device("cpu")))  # as the plain nets
        agents[-1].normalizer.add(np.zeros(55), np.ones(55) * 4, 4)
    agent, alone = agents
    actor_before = [p.clone() for p in agent.actor.parameters()]
    agent.update(batch)
    critic_loss, actor_loss, _, _ = alone.losses(alone.to_tensors(batch))
    critic_params, actor_params = list(alone.critic.parameters()), list(alone.actor.parameters())
    # The critic, its message net included, gets the critic loss's gradient and nothing of the actor loss's;
    # the actor gets the actor loss's.
    for p, g in zip(agent.critic.parameters(), torch.autograd.grad(critic_loss, critic_params), strict=True):
        torch.testing.assert_close(p.grad, g)
    for p, g in zip(agent.actor.parameters(), torch.autograd.grad(actor_loss, actor_params), strict=True):
        torch.testing.assert_close(p.grad, g)
    assert all(p.grad.abs().sum() > 0 for p in agent.critic.message.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(actor_before, agent.actor.parameters(), strict=True))


def test_target_critic_is_polyak_averaged_with_0_95_every_second_update():
    agent = gh.SAC(gh.Args(n_blocks=3), 55, torch.device("cpu"))
    agent.normalizer.add(np.zeros(55), np.ones(55) * 4, 4)
    buf = filled_buffer()
    rng = np.random.default_rng(0)
    target0 = [p.clone() for p in agent.critic_target.parameters()]
    agent.update(buf.sample(32, [rng], 0.8, "final"))
    assert all(torch.equal(a, b) for a, b in zip(target0, agent.critic_target.parameters(), strict=True))
    agent.update(buf.sample(32, [rng], 0.8, "final"))
    for t0, t1, p in zip(target0, agent.critic_target.parameters(), agent.critic.parameters(), strict=True):
        torch.testing.assert_close(t1, 0.95 * t0 + 0.05 * p)
    target2 = [p.clone() for p in agent.critic_target.parameters()]
    agent.update(buf.sample(32, [rng], 0.8, "final"))  # the third: no target update
    assert all(torch.equal(a, b) for a, b in zip(target2, agent.critic_target.parameters(), strict=True))
    agent.update(buf.sample(32, [rng], 0.8, "final"))  # the fourth: one
    for t2, t4, p in zip(target2, agent.critic_target.parameters(), agent.critic.parameters(), strict=True):
        torch.testing.assert_close(t4, 0.95 * t2 + 0.05 * p)


def test_a_compiled_update_computes_the_eager_updates_losses_and_gradients():
    """--compile (torch.compile of the losses) changes speed, not the update. (Parameters are not compared:
    Adam's first step is about +-lr for any gradient, so a float-rounding sign flip of a near-zero one
    shows as 2 lr.)"""
    got = {}
    for compiled in (False, True):
        torch.manual_seed(0)
        agent = gh.SAC(gh.Args(n_blocks=3, compile=compiled, precision="fp32"), 55, torch.device("cpu"))
        agent.normalizer.add(np.zeros(55), np.ones(55) * 4, 4)
        info = agent.update(filled_buffer().sample(32, [np.random.default_rng(0)], 0.8, "final"))
        info = {k: float(v) for k, v in info.items()}  # 0-d tensors, read by Learner.train once a cycle
        grads = {n: p.grad for net in (agent.actor, agent.critic) for n, p in net.named_parameters()}
        got[compiled] = info, grads
    (eager_info, eager_grads), (info, grads) = got[False], got[True]
    assert info == pytest.approx(eager_info, rel=1e-5, abs=1e-6)
    for name, g in eager_grads.items():
        torch.testing.assert_close(grads[name], g, rtol=1e-3, atol=1e-4 * float(g.abs().max()))  # float32 sums
    # After more updates, the compiled losses still read the current weights (none frozen into the graph).
    for _ in range(2):
        agent.update(filled_buffer().sample(32, [np.random.default_rng(1)], 0.8, "final"))
    batch = agent.to_tensors(filled_buffer().sample(32, [np.random.default_rng(2)], 0.8, "final"))
    compiled, eager = agent.compute_losses(batch), agent.losses(batch)
    for c, e in zip(compiled[:3], eager[:3], strict=True):
        torch.testing.assert_close(c, e, rtol=1e-4, atol=1e-5)


def test_normalizer_clips_raw_values_floors_the_std_and_clips_its_output():
    norm = gh.Normalizer(3)
    norm.update(np.array([[100.0, 1.0, 0.0]] * 10))  # 100 counts as 5; constant columns
    np.testing.assert_allclose(norm.mean, [5.0, 1.0, 0.0])
    np.testing.assert_allclose(norm.std, [0.01, 0.01, 0.01])
    np.testing.assert_allclose(norm(np.array([5.0, 1.005, -3.0])), [0.0, 0.5, -5.0], atol=1e-5)
    norm.update(np.array([[0.0, 3.0, 0.0]] * 10))
    np.testing.assert_allclose(norm.mean, [2.5, 2.0, 0.0])
    np.testing.assert_allclose(norm.std, [2.5, 1.0, 0.01])


# ------------------------------------------------------------------------------------------------
# 4. The semantic graph and its planners
# ------------------------------------------------------------------------------------------------
def M(n, close=(), above=()):
    return int(og.to_mask(og.make_config(n, close=close, above=above)))


def test_a_new_config_brings_all_its_permutations_as_nodes():
    g = gh.SemanticGraph(3, gh.Args(n_blocks=3))
    g.add_config(M(3, close=[(0, 1)], above=[(0, 1)]))
    assert g.n_nodes == 6  # "a on b" for the 6 ordered pairs
    g.add_config(M(3))
    assert g.n_nodes == 7


def test_edges_are_created_for_small_steps_only_with_all_joint_permutations_sharing_one_sr():
    args = gh.Args(n_blocks=3)
    g = gh.SemanticGraph(3, args)
    apart, c01 = M(3), M(3, close=[(0, 1)])
    g.update(apart, c01, target=c01, success=True)  # target unknown before: no SR update... then known
    assert g.n_edges == 3 and len(g.sr) == 1  # apart -> close{a,b} for the 3 pairs
    assert g.sr[0] == pytest.approx(0.5 + 0.01 * (1 - 0.5))  # the target became a node: EMA step
    two_moved = M(3, close=[(0, 1), (1, 2), (0, 2)], above=[(0, 1)])
    unknown = M(3, close=[(0, 1)], above=[(1, 0)])
    g.update(c01, M(3, close=[(0, 2), (1, 2)]), target=unknown, success=False)  # not small: no new edge
    assert g.n_edges == 3
    g.update(apart, two_moved, target=two_moved, success=False)  # block 0 alone? no: 0,1,2 all change
    assert g.n_edges == 3
    # An outcome on one edge moves the shared estimate of every equivalent edge.
    g.update(apart, M(3, close=[(1, 2)]), target=M(3, close=[(0, 2)]), success=False)
    assert len(g.sr) == 1 and g.sr[0] == pytest.approx(0.505 + 0.01 * (0 - 0.505))


def test_sr_ema_converges_to_the_success_frequency():
    g = gh.SemanticGraph(3, gh.Args(n_blocks=3))
    apart, c01 = M(3), M(3, close=[(0, 1)])
    g.add_config(c01)
    for i in range(2000):
        g.update(apart, apart, target=c01, success=i % 4 == 0)
    assert g.sr[0] == pytest.approx(0.25, abs=0.03)


def test_unstable_segments_leave_the_graph_unchanged():
    args = gh.Args(n_blocks=3, segment_len=10, stable_steps=3)
    learner = gh.Learner(args, torch.device("cpu"))
    ag = np.tile(og.make_config(3), (11, 1))
    ag[-2] = og.make_config(3, close=[(0, 1)])  # the final config changed within the last 3 steps
    seg = gh.Segment(np.zeros((11, 55), np.float32), ag, og.make_config(3), np.zeros((10, 4)), True, stable=False)
    learner.learn_from([[seg]])
    assert learner.graph.n_nodes == 0 and learner.buffer.size == 1
    stable = gh.Segment(seg.obs, np.tile(og.make_config(3, close=[(0, 1)]), (11, 1)), seg.g, seg.actions, False, True)
    learner.learn_from([[stable]])
    assert learner.graph.n_nodes == 3


def test_autotelic_goals_are_uniform_over_the_agents_nodes_and_random_configs_before_any():
    run = gh.Run(gh.Args(n_blocks=3, buffer_size=400), torch.device("cpu"))
    (w,) = run.workers
    before = {run.sampler.autotelic_goal(w) for _ in range(200)}
    assert len(before) > 100  # a uniform random +-1 vector: 512 configs for 3 blocks
    graph = run.learner.graph
    graph.add_config(M(3, close=[(0, 1)]))  # 3 nodes
    graph.add_config(M(3, close=[(0, 1)], above=[(0, 1)]))  # 6 more
    counts = Counter(run.sampler.autotelic_goal(w) for _ in range(2700))
    assert set(counts) == set(graph.masks) and len(counts) == 9
    assert uniform_pvalue(list(counts.values())) > 1e-3  # SPEC §6: uniform over all nodes


class ScriptedConfigs:
    """A stand-in env whose achieved config switches from `before` to `after` at step `switch`."""

    obs_dim, goal_dim = 55, 9

    def __init__(self, before, after, switch):
        self.before, self.after, self.switch, self.t = before, after, switch, 0

    def obs(self):
        ag = self.after if self.t >= self.switch else self.before
        return {"observation": np.zeros(55, np.float32), "achieved_goal": ag.astype(np.float32)}

    def set_goal(self, goal):
        return self.obs()

    def step(self, action):
        self.t += 1
        return self.obs(), 0.0, False, False, {}


@pytest.mark.parametrize("switch, stable", [(1, True), (3, True), (4, False), (6, False)])
def test_a_segment_is_stable_only_if_its_final_config_held_over_the_last_stable_steps(switch, stable):
    args = gh.Args(n_blocks=3, segment_len=6, stable_steps=3)
    run = gh.Run(args, torch.device("cpu"))
    apart, pair = og.make_config(3), og.make_config(3, close=[(0, 1)])
    (w,) = run.workers
    w.env = ScriptedConfigs(apart, pair, switch)
    (seg,) = gh.run_segments(run.learner.agent, [w], [gh.Request(int(og.to_mask(pair)), deterministic=True)])
    assert seg.obs.shape == (7, 55) and seg.ag.shape == (7, 9) and seg.actions.shape == (6, 4)
    assert seg.stable == stable  # the config after step 3 must already be the final one
    assert seg.success  # success reads the final config only


def random_graph(n_nodes, p, seed):
    """A SemanticGraph whose nodes are plain ids and whose every edge has its own random SR."""
    rng = np.random.default_rng(seed)
    g = gh.SemanticGraph(3, gh.Args(n_blocks=3))
    for i in range(n_nodes):
        g._add_node(i)  # plain ids as configs
    for u, v in itertools.permutations(range(n_nodes), 2):
        if rng.random() < p:
            g._add_edge(u, v, len(g.sr))
            g.sr.append(float(rng.uniform(0.05, 1.0)))
    return g


def all_simple_paths(g, s, t):
    paths, stack = [], [[s]]
    while stack:
        path = stack.pop()
        if path[-1] == t:
            paths.append(path)
            continue
        stack += [path + [v] for v in g.succ[path[-1]] if v not in path]
    return paths


def path_sr(g, path):
    cls = {(u, v): c for u, v, c in g.edge_log}
    return math.prod(g.sr[cls[u, v]] for u, v in zip(path, path[1:], strict=False))


@pytest.mark.parametrize("seed", range(12))
def test_safest_path_is_the_most_reliable_path_of_a_brute_force_enumeration(seed):
    g = random_graph(7, 0.35, seed)
    for s, t in itertools.permutations(range(7), 2):
        paths = all_simple_paths(g, s, t)
        found = gh.safest_path(g, s, t, np.random.default_rng(seed))
        if not paths:
            assert found is None
            continue
        assert found in paths
        assert path_sr(g, found) == pytest.approx(max(path_sr(g, p) for p in paths))


@pytest.mark.parametrize("seed", range(12))
def test_yen_k_shortest_paths_match_a_brute_force_enumeration(seed):
    g = random_graph(7, 0.35, seed)
    for s, t in itertools.permutations(range(7), 2):
        paths = all_simple_paths(g, s, t)
        found = gh.k_shortest_paths(g, s, t, 5)
        assert len(found) == min(5, len(paths))
        assert all(p in paths for p in found) and len({tuple(p) for p in found}) == len(found)
        assert sorted(len(p) for p in found) == sorted(len(p) for p in paths)[: len(found)]
        assert [len(p) for p in found] == sorted(len(p) for p in found)


def test_equally_safe_paths_are_chosen_uniformly_and_a_less_safe_one_never():
    g = random_graph(9, 0.0, 0)
    sr = {(0, 1): 0.5, (0, 2): 0.5, (1, 3): 0.5, (2, 3): 0.5, (3, 5): 0.5,  # two paths into 3, then 5
          (0, 4): 0.25, (4, 5): 0.5,  # 4 has one path in: a walk back from 5 must not favour it
          (0, 7): 0.5, (7, 8): 0.5**1.5, (8, 5): 0.5**0.5,  # 1/8 as well, up to rounding
          (0, 6): 0.5, (6, 5): 0.2}  # fmt: skip
    for (u, v), p in sr.items():
        g._add_edge(u, v, len(g.sr))
        g.sr.append(p)
    best = max(path_sr(g, p) for p in all_simple_paths(g, 0, 5))
    optimal = {tuple(p) for p in all_simple_paths(g, 0, 5) if math.isclose(path_sr(g, p), best)}
    assert len(optimal) == 4  # all but 0 -> 6 -> 5
    rng = np.random.default_rng(0)
    drawn = [tuple(gh.safest_path(g, 0, 5, rng)) for _ in range(2000)]
    paths, counts = zip(*Counter(drawn).items(), strict=True)
    assert set(paths) == optimal
    assert uniform_pvalue(counts) > 1e-3  # SPEC §6: uniform among the safest


def random_graph_with_shared_srs(n_nodes, p, n_classes, seed):
    """Plain-id nodes whose edges share n_classes SR classes, so that different paths can have the
    same sequence of classes (the shape of block permutations of one path)."""
    rng = np.random.default_rng(seed)
    g = random_graph(n_nodes, 0.0, seed)
    g.sr = rng.uniform(0.05, 1.0, size=n_classes).tolist()
    for u, v in itertools.permutations(range(n_nodes), 2):
        if rng.random() < p:
            g._add_edge(u, v, int(rng.integers(n_classes)))
    return g


@pytest.mark.parametrize("seed", range(8))
def test_the_k_shortest_paths_are_the_shortest_paths_of_k_different_shapes(seed):
    g = random_graph_with_shared_srs(7, 0.45, 2, seed)
    cls = {(u, v): c for u, v, c in g.edge_log}
    for s, t in itertools.permutations(range(7), 2):
        paths = all_simple_paths(g, s, t)
        shortest_of_shape = {}
        for p in sorted(paths, key=len):
            shortest_of_shape.setdefault(tuple(cls[e] for e in zip(p, p[1:], strict=False)), len(p))
        found = gh.k_shortest_paths(g, s, t, 5)
        shapes = [tuple(cls[e] for e in zip(p, p[1:], strict=False)) for p in found]
        assert all(p in paths for p in found) and len(set(shapes)) == len(found)  # SPEC §6: k shapes
        if len(paths) <= gh.YEN_PATHS_PER_SHAPE * 5:  # within Yen's bound: exactly the k shortest shapes
            assert sorted(len(p) for p in found) == sorted(shortest_of_shape.values())[:5]


def test_the_k_shortest_paths_on_real_configs_are_the_shortest_of_different_shapes_up_to_block_permutation():
    n, oracle = 3, og.OracleGraph(3)
    g = gh.SemanticGraph(n, gh.Args(n_blocks=n))
    for u in range(oracle.n_nodes):
        for v in oracle.neighbour_indices(u).tolist():
            g.add_config(int(oracle.masks[u]))
            g.add_config(int(oracle.masks[v]))
            g.edge_class(int(oracle.masks[u]), int(oracle.masks[v]))
    dim = og.config_dim(n)

    def shape(path):  # each edge's canonical form: the least key over joint block permutations
        ends = [og.permute_masks(np.array([u, v]), n) for u, v in zip(path, path[1:], strict=False)]
        return tuple(int(((pu << dim) | pv).min()) for pu, pv in ends)

    apart, chain = M(3), M(3, close=[(0, 1), (1, 2)])  # 0-1 then 1-2, or 1-2 then 0-1: one shape
    s, t = g.node_of[apart], g.node_of[chain]
    shortest_of_shape = {}
    for p in sorted(all_simple_paths(g, s, t), key=len):
        shortest_of_shape.setdefault(shape([g.masks[i] for i in p]), len(p))
    found = gh.k_shortest_paths(g, apart, chain, 5)
    assert len({shape(p) for p in found}) == len(found) == 5
    assert sorted(len(p) for p in found) == sorted(shortest_of_shape.values())[:5]


def test_training_plans_take_a_shortest_path_with_probability_shortest_ratio_else_the_safest():
    g = random_graph(4, 0.0, 0)
    g.args = gh.Args(n_blocks=3, shortest_ratio=0.2, k_shortest=1)
    for (u, v), p in {(0, 3): 0.1, (0, 1): 0.9, (1, 2): 0.9, (2, 3): 0.9}.items():  # short and risky, or safe
        g._add_edge(u, v, len(g.sr))
        g.sr.append(p)
    rng = np.random.default_rng(0)
    paths = Counter(tuple(gh.sample_path(g, 0, 3, rng, explore=True)) for _ in range(2000))
    assert set(paths) == {(0, 3), (0, 1, 2, 3)}
    assert abs(paths[0, 3] / 2000 - 0.2) < 4 * np.sqrt(0.2 * 0.8 / 2000)
    assert {tuple(gh.sample_path(g, 0, 3, rng, explore=False)) for _ in range(50)} == {(0, 1, 2, 3)}


def test_plans_without_a_path_go_straight_and_long_paths_keep_start_and_last_configs():
    args = gh.Args(n_blocks=3, max_path_len=4, shortest_ratio=0.0)
    g = random_graph(12, 0.0, 0)
    g.args = args
    for u in range(11):  # a chain 0 -> 1 -> ... -> 11
        g._add_edge(u, u + 1, len(g.sr))
        g.sr.append(0.9)
    rng = np.random.default_rng(0)
    assert gh.sample_path(g, 0, 11, rng, explore=False) == [0, 9, 10, 11]
    assert gh.sample_path(g, 0, 2, rng, explore=False) == [0, 1, 2]
    assert gh.sample_path(g, 5, 0, rng, explore=False) == [5, 0]  # unreachable
    assert gh.sample_path(g, 3, 3, rng, explore=False) == [3, 3]  # start == goal
    assert gh.sample_path(g, 0, 99, rng, explore=False) == [0, 99]  # unknown goal


def test_evaluation_follows_the_last_max_eval_subgoals_of_a_longer_path_those_that_end_at_the_goal(monkeypatch):
    run = gh.Run(gh.Args(n_blocks=3, eval_goals_per_class=1, max_eval_subgoals=3), torch.device("cpu"))
    (w,) = run.workers
    plans = []

    def long_path(graph, start, goal, rng, explore):  # start, 7 configs between, then the goal
        plans.append([start, *range(1000 + 10 * len(plans), 1007 + 10 * len(plans)), goal])
        return plans[-1]

    monkeypatch.setattr(gh, "sample_path", long_path)
    program, asked = gh.evaluation(run, w, run.learner.graph, np.zeros(len(run.classes)), None), []
    w.left = math.inf
    request = next(program)
    with contextlib.suppress(StopIteration):
        while True:  # every sub-goal reached, at once
            asked.append(request.goal)
            request = program.send(gh.Segment(None, None, None, None, success=True, stable=True))
    assert len(plans) == len(run.classes)
    assert asked == [sub for path in plans for sub in path[-3:]]  # the last 3, ending at each goal


def test_agent_nodes_per_class_count_the_class_configs_in_the_agent_graph_not_those_met():
    run = gh.Run(gh.Args(n_blocks=3), torch.device("cpu"))
    stack = int(og.to_mask(og.make_config(3, close=[(0, 1)], above=[(0, 1)])))
    run.learner.graph.add_config(stack)  # a node, with its block permutations (SPEC §6)
    run.learner.encountered = {stack, int(og.to_mask(og.make_config(3, close=[(1, 2)])))}  # met, not nodes
    row = plumbing.finish_epoch(run, dict.fromkeys([*run.classes, "global"], 0.0))
    nodes = set(run.learner.graph.masks)
    for name, members in run.classes.items():
        assert row[f"agent_nodes_{name}"] == sum(int(og.to_mask(m)) in nodes for m in members), name
    assert row["agent_nodes_S2"] == len(run.classes["S2"]) > row["encounters_S2"] == 1
    assert row["agent_nodes_C1"] == 0 and row["encounters_C1"] == 1
    assert plumbing.tensorboard_tag("agent_nodes_S2") == "graph/agent_nodes_S2"
    assert plumbing.tensorboard_tag("sp_frontier_arrived_S2") == "sampler/sp_frontier_arrived_S2"
    assert plumbing.tensorboard_tag("sp_beyond_reached_S2") == "sampler/sp_beyond_reached_S2"


def test_a_fixed_agent_leaves_networks_optimizers_and_normalizer_bit_identical_while_the_graph_grows():
    args = gh.Args(n_blocks=3, n_updates=0, freeze_normalizer=True, n_segments=3, segment_len=10, stable_steps=3)
    run = gh.Run(args, torch.device("cpu"))
    agent = run.learner.agent
    mean = np.linspace(-1, 1, 55)  # and std 0.5, counted as 1000 observations: as --init-from's file would
    agent.normalizer.add(1000 * mean, 1000 * (0.5**2 + mean**2), 1000)

    def state():
        nets = {k: copy.deepcopy(getattr(agent, k).state_dict()) for k in plumbing.NETWORKS}
        return nets, {k: copy.deepcopy(getattr(agent.normalizer, k)) for k in ("sum", "sumsq", "count", "mean", "std")}

    (nets, norm), segments = state(), []
    for _ in range(3):
        gh.one_cycle(run)
        segments.append(run.learner.segments)
    (nets_after, norm_after) = state()
    assert segments == [3, 6, 9] and run.learner.graph.n_nodes > 0  # goals sampled, segments run, graph updated
    assert norm_after["count"] == norm["count"] == 1000
    for k in ("sum", "sumsq", "mean", "std"):
        assert np.array_equal(norm_after[k], norm[k]), k
    for net in ("actor", "critic", "critic_target"):  # every weight, bit for bit
        assert all(torch.equal(nets_after[net][k], nets[net][k]) for k in nets[net]), net
    for opt in ("actor_opt", "critic_opt"):  # Adam never stepped
        assert nets_after[opt]["state"] == nets[opt]["state"] == {}, opt
    assert math.isnan(run.tally["losses"]["critic_loss"])
    assert plumbing.learning_text(args, math.nan) == "fixed agent: no SAC update, normalizer frozen"
    assert plumbing.learning_text(gh.Args(), math.nan) == "critic loss nan"  # updates ran and diverged: say so
    assert plumbing.learning_text(gh.Args(), math.nan, (3, 50)) == (  # --init-learning-starts: none yet
        "no SAC update yet: replays filling, 3 of 50 segments (--init-learning-starts)"
    )
    assert plumbing.learning_text(args, math.nan, (3, 50)) == "fixed agent: no SAC update, normalizer frozen"


def test_plans_on_real_configs_are_paths_of_configs_along_agent_edges():
    args = gh.Args(n_blocks=3)
    g = gh.SemanticGraph(3, args)
    apart, c01, stack = M(3), M(3, close=[(0, 1)]), M(3, close=[(0, 1)], above=[(0, 1)])
    g.update(apart, c01, target=c01, success=True)
    g.update(c01, stack, target=stack, success=True)
    rng = np.random.default_rng(0)
    expected = [apart, c01, stack]
    assert gh.safest_path(g, apart, stack, rng) == expected
    assert gh.k_shortest_paths(g, apart, stack, 5)[0] == expected
    for explore in (False, True):
        assert gh.sample_path(g, apart, stack, rng, explore) == expected


def test_graph_state_round_trips_through_a_checkpoint(tmp_path):
    g = random_graph(9, 0.4, 3)
    torch.save(g.state_dict(), tmp_path / "g.pt")
    h = gh.SemanticGraph(3, g.args)
    h.load_state_dict(torch.load(tmp_path / "g.pt", weights_only=True))
    assert (h.masks, h.succ, h.succ_class, h.sr, h.edge_log) == (g.masks, g.succ, g.succ_class, g.sr, g.edge_log)


# ------------------------------------------------------------------------------------------------
# 5. Resume and Ctrl-C
# ------------------------------------------------------------------------------------------------
RESUME = ["--sp-ratio", "0", "--n-blocks", "3", "--n-cycles", "2", "--n-segments", "4", "--n-updates", "3",
          "--batch-size", "16", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "2",
          "--threads", "1", "--seed", "3"]  # fmt: skip
TIMING = ("time_", "steps_per_second")


def test_a_run_restored_from_a_checkpoint_runs_the_next_cycle_as_the_original_does(tmp_path):
    """save_state and load_state in one process, mid-epoch (SPEC §10): every part of the run the next cycle
    depends on (random streams, networks, optimizers, normalizer, graph, replay, pairs, counters) comes back.
    (The smoke tests below check whole runs through the command line.)"""
    args = gh.Args(n_blocks=3, sp_ratio=0.5, n_segments=4, segment_len=5, stable_steps=2, n_updates=3, batch_size=8,
                   buffer_size=400, runs_dir=str(tmp_path))  # fmt: skip
    torch.manual_seed(0)
    run = gh.Run(args, torch.device("cpu"))
    for _ in range(2):
        gh.one_cycle(run)
    run.rows = [{"epoch": 0, "global_sr": 0.25}]  # an earlier epoch's row
    # Stored pairs, whatever the cycles drew (the next cycle may rehearse them):
    stored = [tuple(int(m) for m in og.OracleGraph(3).masks[i : i + 2]) for i in (0, 2)]
    run.sampler.internalization_buffer = gh.merge_pairs(run.sampler.internalization_buffer, stored)
    plumbing.save_checkpoint(plumbing.save_state(run), tmp_path / "checkpoint.pt")
    torch.manual_seed(1)  # other networks, and fresh streams, replay, graph: all must come from the file
    restored = gh.Run(args, torch.device("cpu"))
    plumbing.load_state(restored, plumbing.load_checkpoint(gh.Args, str(tmp_path / "checkpoint.pt")))
    assert run.sampler.internalization_buffer and restored.sampler.internalization_buffer == \
        run.sampler.internalization_buffer  # fmt: skip
    for r in (run, restored):
        gh.one_cycle(r)
    (w,), (v,) = run.workers, restored.workers
    assert w.rng.bit_generator.state == v.rng.bit_generator.state
    assert w.env.np_random.bit_generator.state == v.env.np_random.bit_generator.state
    assert all(np.array_equal(a.obs, b.obs) and a.g.tolist() == b.g.tolist() for a, b in zip(w.segments, v.segments,
                                                                                             strict=True))  # fmt: skip
    mine, theirs = run.learner, restored.learner
    for net in ("actor", "critic", "critic_target"):
        for (name, p), q in zip(getattr(mine.agent, net).named_parameters(), getattr(theirs.agent, net).parameters(),
                                strict=True):  # fmt: skip
            assert torch.equal(p, q), f"{net}.{name}"
    for field in ("sum", "sumsq", "count"):
        assert np.array_equal(getattr(mine.agent.normalizer, field), getattr(theirs.agent.normalizer, field)), field
    for field in ("obs", "ag", "g", "actions", "ptr", "size"):
        assert np.array_equal(getattr(mine.buffer, field), getattr(theirs.buffer, field)), field
    assert (mine.graph.masks, mine.graph.edge_log, mine.graph.sr) == (theirs.graph.masks, theirs.graph.edge_log,
                                                                      theirs.graph.sr)  # fmt: skip
    assert run.sampler.internalization_buffer == restored.sampler.internalization_buffer
    assert (mine.agent.n_updates, mine.segments, run.cycle, run.sampler.goals, run.rows) == (
        theirs.agent.n_updates, theirs.segments, restored.cycle, restored.sampler.goals, restored.rows)  # fmt: skip
    assert {k: run.tally[k] for k in ("wins", "tries")} == {k: restored.tally[k] for k in ("wins", "tries")}


def test_resuming_after_an_epoch_reproduces_the_uninterrupted_run(tmp_path):
    assert run_script(*RESUME, "--n-epochs", "3", runs_dir=tmp_path / "a").returncode == 0
    out = run_script(*RESUME, "--n-epochs", "1", runs_dir=tmp_path / "b")
    assert out.returncode == 0
    (run_b,) = (tmp_path / "b").iterdir()
    out = run_script("--resume", str(run_b / "checkpoint.pt"), "--n-epochs", "3", runs_dir=tmp_path / "b")
    assert out.returncode == 0, out.stderr
    (run_a,) = (tmp_path / "a").iterdir()
    rows_a, rows_b = read_rows(run_a), read_rows(run_b)
    assert len(rows_a) == len(rows_b) == 3
    for ra, rb in zip(rows_a, rows_b, strict=True):
        assert {k: v for k, v in ra.items() if not k.startswith(TIMING)} == {
            k: v for k, v in rb.items() if not k.startswith(TIMING)
        }


def test_a_run_resumed_from_an_older_versions_checkpoint_logs_every_column_under_its_own_name(tmp_path):
    assert run_script(*RESUME, "--n-epochs", "1", runs_dir=tmp_path).returncode == 0
    (run,) = tmp_path.iterdir()
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    newer = [k for k in state["rows"][0] if k.startswith("agent_nodes_")]  # columns an older version did not log
    state["rows"] = [{k: v for k, v in row.items() if k not in newer} for row in state["rows"]]
    plumbing.save_checkpoint(state, run / "checkpoint.pt")
    out = run_script("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    old, new = read_rows(run)
    assert all(old[k] == "" for k in newer) and all(new[k] != "" for k in newer)
    assert {k: v for k, v in old.items() if k not in newer} == {k: str(v) for k, v in state["rows"][0].items()}
    assert new["epoch"] == "1" and int(new["segments"]) == 2 * int(old["segments"])  # its own columns, aligned


def test_a_run_resumed_under_other_library_versions_says_so_in_one_line_and_goes_on(tmp_path):
    assert run_script(*RESUME, "--n-epochs", "1", runs_dir=tmp_path).returncode == 0
    (run,) = tmp_path.iterdir()
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["versions"] == plumbing.library_versions() and plumbing.version_warning(state) is None
    assert set(state["versions"]) == {"mujoco", "gymnasium", "numpy", "torch"}
    state["versions"]["mujoco"] = "3.0.0"
    plumbing.save_checkpoint(state, run / "checkpoint.pt")
    out = run_script("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    (warning,) = [line for line in out.stderr.splitlines() if "warning" in line]
    assert f"mujoco 3.0.0 -> {plumbing.library_versions()['mujoco']}" in warning and "gymnasium" not in warning
    assert len(read_rows(run)) == 2  # a warning, not a refusal
    del state["versions"]  # a checkpoint from before versions were recorded: nothing to compare
    assert plumbing.version_warning(state) is None


# with the partner: more draws; and the learner's query, whose state a stop must keep
STOPPED = [*RESUME, "--sp-ratio", "0.3", "--n-cycles", "3", "--n-epochs", "6", "--ask-after", "2", "--help-cycles", "2"]


def same_rows(rows_a: list[dict], rows_b: list[dict]):
    assert [r["epoch"] for r in rows_b] == [str(e) for e in range(len(rows_a))]  # each epoch once, in order
    for ra, rb in zip(rows_a, rows_b, strict=True):
        assert {k: v for k, v in ra.items() if not k.startswith(TIMING)} == {
            k: v for k, v in rb.items() if not k.startswith(TIMING)
        }


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> list[dict]:
    runs = tmp_path_factory.mktemp("uninterrupted")
    assert run_script(*STOPPED, runs_dir=runs).returncode == 0
    (run,) = runs.iterdir()
    rows = read_rows(run)
    assert sum(float(r["queries"]) for r in rows) > 0  # the learner asked
    return rows


def stop_then_resume(runs: Path, sig: signal.Signals, at: str, delay: float, **popen) -> tuple[Path, int, str]:
    """Start the STOPPED run, send sig `delay` seconds after its first output line starting with `at`
    (at least two epochs before its end), resume it to the end."""
    cmd = [sys.executable, "-u", "gangstr_hme.py", *STOPPED, "--runs-dir", str(runs)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)
    for line in proc.stdout:
        if line.startswith(at):
            break
    time.sleep(delay)
    proc.send_signal(sig)
    said = proc.communicate(timeout=120)[0]
    (run,) = runs.iterdir()
    out = run_script("--resume", str(run / "checkpoint.pt"), runs_dir=runs)
    assert out.returncode == 0, out.stdout + out.stderr
    return run, proc.returncode, said


def tensorboard_rows(run: Path) -> list[tuple[int, float]]:
    """The (epoch, global SR) pairs TensorBoard shows for a run folder."""
    return tensorboard_scalars(run)[plumbing.tensorboard_tag("global_sr")]


@pytest.mark.xdist_group("uninterrupted")  # under -n 2, on one worker: its fixture made once (conftest.py)
@pytest.mark.parametrize(
    "sig, at",
    [
        (signal.SIGINT, "  epoch 0 cycle 1/3"),  # within the first epoch: no row logged yet
        (signal.SIGTERM, "  epoch 2 cycle 2/3"),
        (signal.SIGKILL, "  epoch 3 cycle 3/3"),  # the epoch's evaluation, checkpoint and row come next
    ],
    ids=["ctrl-c", "sigterm", "kill-9"],
)
def test_a_stopped_run_resumes_into_the_uninterrupted_run(tmp_path, uninterrupted, sig, at):
    """Ctrl-C and SIGTERM stop at the next cycle boundary with a checkpoint (exit 130); kill -9 loses the
    work since the last epoch's checkpoint. Either way the resumed run's rows are the uninterrupted run's,
    each epoch once, in progress.csv and in TensorBoard. (benchmarks/stress_interrupts.py: many moments.)"""
    run, code, said = stop_then_resume(tmp_path, sig, at, random.Random(int(sig)).uniform(0.0, 0.05))
    assert code == (-9 if sig == signal.SIGKILL else 130), said
    if sig != signal.SIGKILL:
        assert "interrupted: checkpoint saved" in said and "--resume" in said
    same_rows(uninterrupted, read_rows(run))
    assert tensorboard_rows(run) == [(int(r["epoch"]), pytest.approx(float(r["global_sr"]))) for r in uninterrupted]


@pytest.mark.xdist_group("uninterrupted")
def test_ctrl_c_stops_the_run_even_when_the_parent_ignores_sigint(tmp_path, uninterrupted):
    ignore = dict(preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))  # as `cmd &` in a script does
    run, code, said = stop_then_resume(tmp_path, signal.SIGINT, "  epoch 1 cycle 2/3", 0.0, **ignore)
    assert code == 130, said
    same_rows(uninterrupted, read_rows(run))


def test_a_python_caller_of_main_gets_its_ctrl_c_and_sigterm_back(tmp_path):
    """main() called from Python (a notebook, a fork driving the script): the run's Stopper takes Ctrl-C and
    SIGTERM while it runs and gives the caller's handlers back at its end (kept, a second Ctrl-C would end the
    caller's process: Stopper.handle)."""
    mine = lambda signum, frame: None  # noqa: E731
    before = {sig: signal.signal(sig, mine) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert gh.main([*RESUME, "--n-epochs", "1", "--runs-dir", str(tmp_path)]) == 0
        assert signal.getsignal(signal.SIGINT) is mine and signal.getsignal(signal.SIGTERM) is mine
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def test_a_second_ctrl_c_aborts_at_once_and_keeps_the_last_checkpoint(tmp_path):
    slow = [*RESUME, "--n-cycles", "1", "--n-epochs", "3", "--n-updates", "300"]  # cycles of a second or more
    cmd = [sys.executable, "-u", "gangstr_hme.py", *slow, "--runs-dir", str(tmp_path)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in proc.stdout:
        if line.startswith("epoch   0 |"):  # epoch 0's checkpoint is saved; epoch 1's long cycle is under way
            break
    (run,) = tmp_path.iterdir()
    saved = torch.load(run / "checkpoint.pt", weights_only=True)["counters"]
    proc.send_signal(signal.SIGINT)
    for line in proc.stdout:
        if "stopping at the next cycle boundary" in line:  # the first one was handled
            break
    proc.send_signal(signal.SIGINT)
    said = proc.communicate(timeout=60)[0]
    assert proc.returncode == 130 and "aborted by a second SIGINT" in said and "Traceback" not in said, said
    assert not (run / "checkpoint.pt.tmp").exists()
    assert torch.load(run / "checkpoint.pt", weights_only=True)["counters"] == saved  # the epoch's, as it was


# ------------------------------------------------------------------------------------------------
# 8. Bad command lines
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv, named",
    [
        (["--n-epochs", "-1"], "-1"),
        (["--n-updates", "-3"], "-3"),
        (["--sp-ratio", "1.5"], "1.5"),
        (["--sp-ratio", "-0.1"], "-0.1"),
        (["--her-strategy", "episode"], "'episode'"),
        (["--n-blocks", "6"], "6"),
        (["--resume", "/nonexistent/checkpoint.pt"], "/nonexistent/checkpoint.pt"),
        (["--batch-size", "many"], "'many'"),
        (["--eval-only", "--checkpoint", "/nonexistent/run/checkpoint.pt"], "/nonexistent/run/checkpoint.pt"),
        (["--video-episodes", "-2"], "-2"),
        (["--seed", "-1"], "-1"),
        (["--seed", str(2**64 + 1)], str(2**64 + 1)),
        (["--alpha", "nan"], "nan"),
        (["--alpha", "inf"], "inf"),
        (["--alpha", "-1"], "-1"),
        (["--lr-actor", "nan"], "nan"),
        (["--lr-actor", "inf"], "inf"),
        (["--lr-critic", "-0.001"], "--lr-critic must be non-negative, got -0.001"),
        (["--lr-critic", "-1"], "-1"),
        (["--eval-goals-per-class", "0"], "0"),
        (["--batch-size", "100000"], "100000"),
        (["--k-shortest", "0"], "0"),
        (["--stable-steps", "0"], "0"),
        (["--buffer-size", "1"], "1"),
        (["--capture-video"], "--capture-video"),
        (["--exp-name", "../../x"], "'../../x'"),
        (["--max-path-len", "1"], "1"),
        (["--checkpoint", "x.pt"], "x.pt"),
        (["--buffer-size", "10000000000"], "10000000000"),
    ],
)
def test_bad_command_line_values_exit_2_naming_the_value(argv, named, capsys):
    with pytest.raises(SystemExit) as e:
        plumbing.parse_args(gh.Args, gh.check_sampler_args, argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert named in err and len(err.strip().splitlines()) == 1 and "Args(" not in err


@pytest.mark.parametrize("argv", [["--seed", "-1"], ["--alpha", "nan"], ["--exp-name", "../../x"]])
def test_a_bad_value_writes_nothing(tmp_path, argv):
    out = run_script(*argv, runs_dir=tmp_path / "runs")
    assert out.returncode == 2 and not (tmp_path / "runs").exists() and not (tmp_path.parent / "x").exists()


def test_an_unwritable_runs_dir_exits_2_naming_it(tmp_path):
    (tmp_path / "file").write_text("")  # a file where a folder should be: even root cannot write under it
    out = run_script(*TINY, runs_dir=tmp_path / "file" / "runs")
    assert out.returncode == 2 and "--runs-dir" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_help_shows_every_default():
    out = inprocess.run_script("gangstr_hme.py", "--help")
    # Each option's entry: from its line "  --flag ..." to the next option's.
    entries = {}
    for line in out.stdout.split("\n"):
        if line.startswith("  --"):
            flag = line.split()[0].rstrip(",")
            entries[flag] = line
        elif entries and line.startswith("   "):
            entries[flag] += " " + line.strip()
    for field in dataclasses.fields(gh.Args):
        flag = "--" + field.name.replace("_", "-")
        assert flag in entries, flag
        text = " ".join(entries[flag].split())
        assert text.endswith(f"(default: {field.default!r})"), text


# The update's settings by the number of workers (SPEC §12): one worker's update was measured against the paper's
# summed one and against smaller rates (docs/results.md). Below the paper's 24 workers, the rates not given are
# x0.3 of the paper's; 24 workers, however split into processes, train with the paper's settings. The rule is
# applied where Adam is built (plumbing.adam_rates), so the command line, an Args built in code and --resume
# all go through it.
PAPERS_TABLE = dict(n_cycles=50, n_segments=10, n_updates=30, segment_len=40, batch_size=256, buffer_size=10**6,
                    her_strategy="final", her_k=4, gamma=0.99, alpha=0.2, polyak=0.95, sr_ema=0.01, sr_prior=0.5,
                    k_shortest=5, shortest_ratio=0.5, internalization_prob=0.5)  # fmt: skip


def rates_of(monkeypatch, processes, *argv):
    """Adam's rates in a learner built from this command line, in one of `processes` torchrun processes."""
    monkeypatch.setenv("WORLD_SIZE", str(processes))
    monkeypatch.setattr(plumbing.os, "sysconf", lambda name: 2**20)  # the memory check: 24 replays are not made
    sac = gh.SAC(plumbing.parse_args(gh.Args, gh.check_sampler_args, list(argv)), fetch5_env.obs_size(5), "cpu")
    return [g["lr"] for o in (sac.actor_opt, sac.critic_opt) for g in o.param_groups]


@pytest.mark.parametrize("num_envs, processes", [(1, 1), (2, 1), (1, 2), (12, 1)])
def test_fewer_than_24_workers_learn_at_three_tenths_of_the_papers_rates(monkeypatch, num_envs, processes):
    assert rates_of(monkeypatch, processes, "--num-envs", str(num_envs)) == pytest.approx([3e-4, 3e-4], rel=1e-12)


@pytest.mark.parametrize("num_envs, processes", [(24, 1), (12, 2), (1, 24), (32, 1)])
def test_24_workers_or_more_however_split_keep_every_setting_of_the_papers_table(monkeypatch, num_envs, processes):
    assert rates_of(monkeypatch, processes, "--num-envs", str(num_envs)) == [1e-3, 1e-3]
    args = dataclasses.asdict(plumbing.parse_args(gh.Args, gh.check_sampler_args, ["--num-envs", str(num_envs)]))
    assert {k: args[k] for k in PAPERS_TABLE} == PAPERS_TABLE


def test_given_rates_are_used_as_given_and_paper_rates_gives_one_worker_the_papers(monkeypatch, tmp_path):
    assert rates_of(monkeypatch, 1, "--lr-actor", "5e-4") == pytest.approx([5e-4, 3e-4], rel=1e-12)
    assert rates_of(monkeypatch, 1, "--lr-critic", "1e-3") == pytest.approx([3e-4, 1e-3], rel=1e-12)
    assert rates_of(monkeypatch, 1, "--num-envs", "24", "--lr-critic", "2e-3") == [1e-3, 2e-3]
    assert rates_of(monkeypatch, 1, "--paper-rates") == [1e-3, 1e-3]
    assert rates_of(monkeypatch, 1, "--paper-rates", "--lr-actor", "5e-4") == [5e-4, 1e-3]
    (tmp_path / "agent.pt").write_bytes(b"")  # read later (SPEC §10 scales its rates its own way)
    assert rates_of(monkeypatch, 1, "--init-from", str(tmp_path / "agent.pt")) == pytest.approx([1e-4, 1e-4])
    assert rates_of(monkeypatch, 24, "--init-from", str(tmp_path / "agent.pt"), "--lr-critic", "2e-3",
                    "--init-lr-scale", "0.5") == pytest.approx([5e-4, 1e-3])  # fmt: skip


@pytest.mark.parametrize("script", [gh, lp, vds])
@pytest.mark.parametrize("num_envs, want", [(1, 3e-4), (24, 1e-3)])
def test_an_args_built_in_code_gets_the_rates_the_command_line_gets(monkeypatch, script, num_envs, want):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    sac = script.SAC(script.Args(n_blocks=3, num_envs=num_envs), fetch5_env.obs_size(3), "cpu")  # no parse_args
    assert sac.lrs == pytest.approx([want, want], rel=1e-12)
    assert script.Args.lr_actor == script.Args.lr_critic == 0  # not given: the rule's (adam_rates)
    sac = script.SAC(script.Args(n_blocks=3, num_envs=num_envs, lr_critic=2e-3), fetch5_env.obs_size(3), "cpu")
    assert sac.lrs == pytest.approx([want, 2e-3], rel=1e-12)  # one given, as given; the other by the rule


def test_paper_rates_with_init_from_is_refused_in_one_line(tmp_path, capsys):
    (tmp_path / "agent.pt").write_bytes(b"")
    with pytest.raises(SystemExit) as e:
        gh.main(["--paper-rates", "--init-from", str(tmp_path / "agent.pt"), "--runs-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1 and not (tmp_path / "runs").exists()
    assert "--paper-rates does nothing with --init-from" in err


def first_line(monkeypatch, capsys, tmp_path, *argv, processes=1) -> str:
    """The first line a new run prints (its run folder, workers and rates), from a run built from this command
    line; no training."""
    monkeypatch.setenv("WORLD_SIZE", str(processes))  # the rule counts torchrun's processes; none joins here
    argv = [*TINY, "--n-blocks", "3", "--buffer-size", "400", *argv, "--runs-dir", str(tmp_path / "runs")]
    run = gh.Run(plumbing.parse_args(gh.Args, gh.check_sampler_args, argv), "cpu")
    capsys.readouterr()
    with plumbing.RunFolder(run, None):
        pass
    return capsys.readouterr().out.splitlines()[0]


@pytest.mark.parametrize(
    "argv, processes, says",
    [
        ([], 1, "| 1 worker(s) on cpu | rates 0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers)"),
        (["--num-envs", "11"], 2, "| rates 0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers)"),  # 22
        (["--num-envs", "12"], 2, "| rates 0.001 / 0.001 (the paper's: 24 workers or more)"),  # 12 x 2 processes
        (["--num-envs", "24"], 1, "| 24 worker(s) on cpu | rates 0.001 / 0.001 (the paper's: 24 workers or more)"),
        (["--num-envs", "24", "--lr-actor", "3e-4", "--lr-critic", "3e-4"], 1, "| rates 0.0003 / 0.0003 (given)"),
        (["--paper-rates"], 1, "| rates 0.001 / 0.001 (the paper's: --paper-rates)"),
        (["--lr-actor", "5e-4"], 1, "| rates 0.0005 (given) / 0.0003 (x0.3 of the paper's: below 24 workers)"),
        (["--lr-critic", "2e-3", "--paper-rates"], 1, "| rates 0.001 (the paper's: --paper-rates) / 0.002 (given)"),
        (
            ["--init-from", "{file}"],
            1,
            "| rates 0.0001 / 0.0001 (x0.1 of the paper's: --init-lr-scale, after a 2,000-update warm-up)",
        ),
        (
            ["--init-from", "{file}", "--num-envs", "24", "--init-warmup", "0", "--lr-critic", "2e-3"],
            1,
            "| rates 0.0001 (x0.1 of the paper's: --init-lr-scale) / 0.0002 (x0.1 of 0.002 given: --init-lr-scale)",
        ),
    ],
)
def test_the_first_line_prints_the_rates_adam_was_given_and_why_by_the_rule(monkeypatch, capsys, tmp_path, argv,
                                                                               processes, says):  # fmt: skip
    (tmp_path / "agent.pt").write_bytes(b"")  # --init-from's file: only its hash is read here (config.json)
    line = first_line(monkeypatch, capsys, tmp_path, *[a.format(file=tmp_path / "agent.pt") for a in argv],
                      processes=processes)  # fmt: skip
    assert f"{says} | " in line, line  # then whether the updates run beside collecting (tests/test_overlap.py)


@pytest.mark.parametrize(
    "argv, fast, says",
    [
        ([], True, "bf16 (this CPU's bf16 matrix units)"),
        ([], False, "fp32 (no bf16 matrix units on this CPU)"),
        (["--plain"], True, "fp32 (--plain)"),
        (["--precision", "fp32"], True, "fp32 (given)"),
        (["--precision", "bf16"], True, "bf16 (given)"),
    ],
)
def test_the_first_line_and_config_name_the_precision_bf16_by_default_only_where_the_cpu_has_bf16_matrix_units(
    monkeypatch, capsys, tmp_path, argv, fast, says
):
    if fast and not speed.fast_bf16(cuda=False) and "bf16" in says:  # oneDNN may have no bf16 products here at all
        pytest.skip("this CPU has no bf16 matrix instructions: a bf16 agent is not built here")
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: fast)  # the machine's bf16 matrix units (SPEC §12)
    assert f"| precision {says} | " in first_line(monkeypatch, capsys, tmp_path, *argv)
    (run,) = (tmp_path / "runs").iterdir()
    config = json.loads((run / "config.json").read_text())
    assert config["precision"] == says.split()[0] and config["workers"] == 1  # what it computed in
    assert speed.precision_of(gh.Args(cuda=True)) == ("fp32", "--cuda: bf16 not measured there")


@pytest.mark.parametrize(
    "workers, rates",
    [(1, "0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers)"),
     (2, "0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers)"),
     (24, "0.001 / 0.001 (the paper's: 24 workers or more)")],
)  # fmt: skip
def test_the_first_line_names_one_machines_defaults_and_why_for_1_2_and_24_workers(monkeypatch, capsys, tmp_path,
                                                                                   workers, rates):  # fmt: skip
    """SPEC §12: the rates by the workers, bf16 on a CPU with bf16 matrix units, the updates beside collecting."""
    if not speed.fast_bf16(cuda=False):
        pytest.skip("this CPU has no bf16 matrix instructions: a bf16 agent is not built here")
    line = first_line(monkeypatch, capsys, tmp_path, "--num-envs", str(workers))
    assert line.endswith(
        f"| 3 blocks | {workers} worker(s) on cpu | rates {rates} | precision bf16 (this CPU's bf16 "
        "matrix units) | updates beside collecting, in a process of their own (--overlap)"
    ), line


def test_the_first_line_names_the_rates_and_a_resumed_run_keeps_the_rates_it_started_with(tmp_path, capsys):
    def lines(*argv, runs_dir) -> list[str]:  # a run in this process (no interpreter to start): what it printed
        assert gh.main([*argv, "--runs-dir", str(runs_dir)]) == 0
        return capsys.readouterr().out.splitlines()

    first = lines(*RESUME, "--n-epochs", "1", runs_dir=tmp_path / "a")[0]
    assert "rates 0.0003 / 0.0003 (x0.3 of the paper's: below 24 workers) | " in first
    (run,) = (tmp_path / "a").iterdir()
    assert json.loads((run / "config.json").read_text())["adam_rates"] == pytest.approx([3e-4, 3e-4], rel=1e-12)
    state = torch.load(run / "checkpoint.pt", weights_only=True)  # as a run started before x0.3 saved it
    state["args"] = {k: v for k, v in state["args"].items() if k != "paper_rates"} | dict(lr_actor=1e-3, lr_critic=1e-3)
    for opt in ("actor_opt", "critic_opt"):
        state[opt]["param_groups"][0]["lr"] = 1e-3
    torch.save(state, run / "checkpoint.pt")
    out = lines("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", runs_dir=tmp_path / "a")
    assert "| rates 0.001 / 0.001 (the run's own)" in out[1]  # after "resumed"
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert [state[o]["param_groups"][0]["lr"] for o in ("actor_opt", "critic_opt")] == [1e-3, 1e-3]
    first = lines(*RESUME, "--n-epochs", "1", "--lr-actor", "5e-4", "--lr-critic", "6e-4", runs_dir=tmp_path / "b")[0]
    assert "| rates 0.0005 / 0.0006 (given) | " in first
    (run,) = (tmp_path / "b").iterdir()
    out = lines("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", runs_dir=tmp_path / "b")
    assert "| rates 0.0005 / 0.0006 (the run's own)" in out[1]
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["counters"]["epoch"] == 2 and (state["args"]["lr_actor"], state["args"]["lr_critic"]) == (5e-4, 6e-4)
    assert [state[o]["param_groups"][0]["lr"] for o in ("actor_opt", "critic_opt")] == [5e-4, 6e-4]


@pytest.mark.parametrize("content", [b"not a checkpoint", b""])
def test_an_unreadable_checkpoint_exits_2_with_one_line(tmp_path, content):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(content)
    out = run_script("--resume", str(bad), runs_dir=tmp_path)
    assert out.returncode == 2 and str(bad) in out.stderr and len(out.stderr.strip().splitlines()) == 1


def saved_run(path: Path, module=gh, **fields) -> dict:
    """A fresh 3-block run's checkpoint at path (no training needed to test loading rules)."""
    run = module.Run(module.Args(n_blocks=3, buffer_size=400, runs_dir=str(path.parent), **fields), "cpu")
    state = plumbing.save_state(run)
    plumbing.save_checkpoint(state, path)
    return state


@pytest.mark.parametrize(
    "content, says",
    [
        (b"hello, I am a text file\n", "not a checkpoint"),
        (None, "not a checkpoint of this project"),
        ("lp", "a checkpoint of lp_baseline.py, not of gangstr_hme.py"),
        ("old env", "the environment changed"),
    ],
    ids=["text", "other torch file", "other script", "other environment"],
)
def test_a_file_that_is_not_this_scripts_checkpoint_gets_one_line_saying_what_it_is(tmp_path, content, says):
    path = tmp_path / "file.pt"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is None:
        torch.save({"weights": torch.zeros(3)}, path)
    elif content == "lp":
        import lp_baseline  # noqa: PLC0415

        saved_run(path, lp_baseline)
    else:
        state = saved_run(path)  # as written before the environment had a version
        torch.save({k: v for k, v in state.items() if k not in ("env_version", "script")}, path)
    for argv in (["--resume", str(path)], ["--eval-only", "--checkpoint", str(path)]):
        out = run_script(*argv, runs_dir=tmp_path)
        assert out.returncode == 2 and says in out.stderr and str(path) in out.stderr, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("mode", ["--resume", "--eval-only"])
def test_flags_that_contradict_the_checkpoint_exit_2_naming_each(tmp_path, mode):
    state = saved_run(tmp_path / "checkpoint.pt", sp_ratio=0.3)
    state["counters"]["epoch"] = 1  # a finished epoch: resuming to --n-epochs 1 has nothing to do
    plumbing.save_checkpoint(state, tmp_path / "checkpoint.pt")
    where = ["--resume", str(tmp_path / "checkpoint.pt"), "--n-epochs", "1"] if mode == "--resume" else [
        "--eval-only", "--checkpoint", str(tmp_path / "checkpoint.pt"), "--eval-goals-per-class", "1"]  # fmt: skip
    out = run_script(*where, "--n-blocks", "5", "--sp-ratio", "0.2", "--threads", "1", runs_dir=tmp_path)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert "--n-blocks 5 (checkpoint: 3)" in out.stderr and "--sp-ratio 0.2 (checkpoint: 0.3)" in out.stderr
    same = run_script(*where, "--n-blocks", "3", "--sp-ratio", "0.3", "--threads", "1", runs_dir=tmp_path)
    assert same.returncode == 0, same.stderr


def test_resume_with_nothing_left_to_train_says_so(tmp_path):
    assert run_script("--n-blocks", "3", *TINY, runs_dir=tmp_path).returncode == 0
    (run,) = tmp_path.iterdir()
    out = run_script("--resume", str(run / "checkpoint.pt"), "--n-epochs", "1", runs_dir=tmp_path)
    assert out.returncode == 0 and "nothing to do" in out.stdout and len(read_rows(run)) == 1


def test_eval_only_on_a_corrupt_checkpoint_exits_2_naming_it(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    out = run_script("--eval-only", "--checkpoint", str(bad), runs_dir=tmp_path)
    assert out.returncode == 2 and "--checkpoint" in out.stderr and str(bad) in out.stderr


@pytest.mark.parametrize("flag", ["--resume", "--checkpoint"])
def test_a_checkpoint_from_other_networks_exits_2_naming_the_mismatch(tmp_path, flag):
    run = gh.Run(gh.Args(n_blocks=3, buffer_size=400, runs_dir=str(tmp_path)), torch.device("cpu"))
    state = plumbing.save_state(run)
    state["actor"]["mean.weight"] = state["actor"].pop("head.out.weight")  # as an older version named it
    path = tmp_path / "other.pt"
    torch.save(state, path)
    out = run_script(
        *([flag, str(path)] if flag == "--resume" else ["--eval-only", flag, str(path)]), runs_dir=tmp_path
    )
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert flag in out.stderr and str(path) in out.stderr and "head.out.weight" in out.stderr


def test_help_lists_every_field_with_its_docstring():
    out = inprocess.run_script("gangstr_hme.py", "--help")
    assert out.returncode == 0
    for flag, words in [("--sp-ratio", "probability that a cycle is social"), ("--her-strategy", "HER relabelling")]:
        assert flag in out.stdout and words in " ".join(out.stdout.split())


# ------------------------------------------------------------------------------------------------
# 9. Watching a trained agent: --eval-only and --capture-video
# ------------------------------------------------------------------------------------------------
def test_eval_only_prints_sr_per_class_saves_it_and_films_playable_mp4s(tmp_path, gl):
    import imageio_ffmpeg  # noqa: PLC0415

    assert run_script("--sp-ratio", "0", "--n-blocks", "3", *TINY, runs_dir=tmp_path).returncode == 0
    (run,) = tmp_path.iterdir()
    argv = ["--eval-only", "--checkpoint", str(run / "checkpoint.pt"), "--eval-goals-per-class", "2",
            "--capture-video", "--video-episodes", "1", "--seed", "4", "--threads", "1",
            "--num-envs", "2"]  # two workers evaluate (the checkpoint's run had one); worker 0 films  # fmt: skip
    out = run_script(*argv, runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    classes = list(og.evaluation_classes(3))
    for name in classes:
        assert f"{name:>6}  SR " in out.stdout
    result = json.loads((run / "eval_checkpoint_epoch1_seed4.json").read_text())
    assert set(result["sr"]) == {*classes, "global"} and result["goals_per_class"] == 2
    assert result["sr"]["global"] == pytest.approx(np.mean([result["sr"][k] for k in classes]))
    for name in classes:
        video = run / "videos" / f"eval_checkpoint_epoch1_seed4_{name}.mp4"
        frames = int(re.search(rf"{video.name} \((\d+) frames\)", out.stdout).group(1))
        reader = imageio_ffmpeg.read_frames(str(video))
        meta = next(reader)
        decoded = [np.frombuffer(f, np.uint8) for f in reader]
        assert meta["size"] == (480, 480) and meta["fps"] == pytest.approx(25.0)
        assert len(decoded) == frames and frames % 10 == 0 and 10 <= frames <= 10 * 9  # whole 10-step segments
        assert decoded[0].size == 480 * 480 * 3 and decoded[0].std() > 10  # a picture, not a blank


def test_a_second_evaluation_of_a_checkpoint_is_saved_beside_the_first_never_over_it(tmp_path):
    run = gh.Run(gh.Args(n_blocks=3, buffer_size=400, runs_dir=str(tmp_path)), torch.device("cpu"))
    plumbing.save_checkpoint(plumbing.save_state(run), tmp_path / "agent.pt")
    argv = ["--eval-only", "--checkpoint", str(tmp_path / "agent.pt"), "--eval-goals-per-class", "1", "--threads", "1"]
    for _ in range(2):
        assert run_script(*argv, runs_dir=tmp_path).returncode == 0
    assert sorted(p.name for p in tmp_path.glob("eval_*")) == ["eval_agent_epoch0_seed0.json",
                                                               "eval_agent_epoch0_seed0_2.json"]  # fmt: skip


def test_eval_only_evaluates_the_checkpoint_of_a_resumed_finished_run(tmp_path):
    """A resumed run's checkpoint holds its --resume path; --eval-only evaluates it all the same (it once
    answered "nothing to do", taking the evaluation for a resume of a finished run)."""
    path = tmp_path / "agent.pt"
    run = gh.Run(gh.Args(n_blocks=3, n_epochs=1, buffer_size=400, resume=str(path)), torch.device("cpu"))
    run.epoch = 1  # its one epoch done
    plumbing.save_checkpoint(plumbing.save_state(run), path)
    out = run_script("--eval-only", "--checkpoint", str(path), "--eval-goals-per-class", "1", runs_dir=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "global  SR" in out.stdout and "nothing to do" not in out.stdout
    assert [p.name for p in tmp_path.glob("eval_*")] == ["eval_agent_epoch1_seed0.json"]


def test_capture_video_without_a_display_or_gl_backend_exits_2_saying_what_to_install(tmp_path):
    run = gh.Run(gh.Args(n_blocks=3, buffer_size=400, runs_dir=str(tmp_path)), torch.device("cpu"))
    plumbing.save_checkpoint(plumbing.save_state(run), tmp_path / "agent.pt")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "PYOPENGL_PLATFORM")}
    cmd = [sys.executable, "gangstr_hme.py", "--eval-only", "--checkpoint", str(tmp_path / "agent.pt"),
           "--capture-video", "--runs-dir", str(tmp_path)]  # fmt: skip
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "libosmesa6" in out.stderr and "MUJOCO_GL=osmesa" in out.stderr
    assert not list(tmp_path.glob("eval_*")) and not (tmp_path / "videos").exists()
