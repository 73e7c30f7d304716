"""The SAC update's speed tricks (docs/speed.md): the fast fp32 update computes SPEC §5's losses, TD targets
and gradients to float tolerance, checked against a plain re-implementation written here; --precision bf16
keeps weights, optimizer state, targets and losses in fp32, and is refused where the device has no fast bf16."""

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import gangstr_hme as gh
import oracle_graph as og
import plumbing
import speed

N_BLOCKS, BATCH = 5, 128


def spec_losses(actor: dict, critic: dict, target: dict, t: dict, gamma: float, alpha: float):
    """SPEC §5 written out plainly, from the networks' parameters by name (`actor`, `critic`, `target`:
    name -> tensor) and a batch of normalized tensors `t`: the critic loss, the actor loss and the TD target.
    Loops over nodes and edges; no code of the training script."""
    n = N_BLOCKS
    close = {tuple(pair): k for k, pair in enumerate(og.close_pairs(n).tolist())}
    above = {tuple(pair): len(close) + k for k, pair in enumerate(og.above_pairs(n).tolist())}

    def mlp(p, name, x, out_relu=True):  # Linear -> ReLU -> Linear (-> ReLU)
        h = torch.relu(x @ p[f"{name}.hidden.weight"].T + p[f"{name}.hidden.bias"])
        y = h @ p[f"{name}.out.weight"].T + p[f"{name}.out.bias"]
        return torch.relu(y) if out_relu else y

    def block(obs, i):  # block i's 15 features; its position is the first 3
        return obs[:, 10 + 15 * i : 25 + 15 * i]

    def messages(p, obs, gap):  # node i: max over the edges (i, j) of the message net on the edge input
        out = []
        for i in range(n):
            edges = [torch.cat([gap[:, [close[min(i, j), max(i, j)]]], gap[:, [above[i, j]]],
                                block(obs, i)[:, :3], block(obs, j)[:, :3]], dim=1)
                     for j in range(n) if j != i]  # fmt: skip
            out.append(torch.stack([mlp(p, "message", e) for e in edges]).amax(0))
        return out

    def policy(obs, msg, noise):  # squashed Gaussian sample and its log-probability
        nodes = sum(mlp(actor, "node", torch.cat([obs[:, :10], block(obs, i), msg[i]], 1)) for i in range(n))
        mean, log_std = mlp(actor, "head", nodes, out_relu=False).chunk(2, dim=1)
        log_std = log_std.clamp(-20, 2)
        a = torch.tanh(mean + log_std.exp() * noise)
        normal = -0.5 * noise**2 - log_std - 0.5 * np.log(2 * np.pi)
        return a, (normal - torch.log(1 - a**2 + 1e-6)).sum(1)

    def twin_q(p, obs, action, msg):
        qs = []
        for k in range(2):
            x = [torch.cat([action, obs[:, :10], block(obs, i), msg[i]], 1) for i in range(n)]
            nodes = sum(mlp(p, f"q_nodes.{k}", xi) for xi in x)
            qs.append(mlp(p, f"q_heads.{k}", nodes, out_relu=False)[:, 0])
        return qs

    with torch.no_grad():
        gap2 = t["g"] - t["ag_next"]
        a2, logp2 = policy(t["obs_next"], messages(critic, t["obs_next"], gap2), t["noise_next"])
        q_next = torch.min(*twin_q(target, t["obs_next"], a2, messages(target, t["obs_next"], gap2)))
        y = t["reward"] + gamma * (q_next - alpha * logp2)  # every transition bootstraps
    msg = messages(critic, t["obs"], t["g"] - t["ag"])
    q1, q2 = twin_q(critic, t["obs"], t["action"], msg)
    critic_loss = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
    pi, logp = policy(t["obs"], [m.detach() for m in msg], t["noise_pi"])
    fixed = {k: v.detach() for k, v in critic.items()}  # the actor loss moves the actor only
    q_pi = torch.min(*twin_q(fixed, t["obs"], pi, [m.detach() for m in msg]))
    actor_loss = (alpha * logp - q_pi).mean()
    return critic_loss, actor_loss, y


def realistic_batch(agent: gh.SAC, seed: int = 0) -> dict:
    """A batch from a replay of random segments (HER relabelled), the normalizer fitted to them."""
    rng = np.random.default_rng(seed)
    dim, obs_dim, n_seg, T = og.config_dim(N_BLOCKS), 10 + 15 * N_BLOCKS, 20, 10
    buf = gh.ReplayBuffer(1, n_seg, T, obs_dim, dim)
    obs = rng.normal(size=(1, n_seg, T + 1, obs_dim)).astype(np.float32)
    ag = rng.choice(np.int8([-1, 1]), size=(1, n_seg, T + 1, dim))
    buf.store(obs, ag, rng.choice(np.int8([-1, 1]), size=(1, n_seg, dim)), rng.uniform(-1, 1, (1, n_seg, T, 4)))
    agent.normalizer.update(obs)
    return buf.sample(BATCH, [rng], 0.8, "final")


def update_and_reference(precision: str):
    """One update of a fresh agent, and SPEC §5's losses, target and gradients from the same weights and
    batch: (update's critic loss, actor loss, target, gradients by name), the same from spec_losses."""
    torch.manual_seed(0)
    args = gh.Args(n_blocks=N_BLOCKS, precision=precision)
    agent = gh.SAC(args, 10 + 15 * N_BLOCKS, torch.device("cpu"))
    batch = realistic_batch(agent)
    t = agent.to_tensors(batch)
    actor = {k: v.clone().requires_grad_() for k, v in agent.actor.state_dict().items()}
    critic = {k: v.clone().requires_grad_() for k, v in agent.critic.state_dict().items()}
    target = {k: v.clone() for k, v in agent.critic_target.state_dict().items()}
    info = agent.update(batch)
    grads = {f"actor.{k}": p.grad for k, p in agent.actor.named_parameters()}
    grads |= {f"critic.{k}": p.grad for k, p in agent.critic.named_parameters()}
    critic_loss, actor_loss, y = spec_losses(actor, critic, target, t, args.gamma, args.alpha)
    ref_grads = {}
    for prefix, loss, params in (("critic", critic_loss, critic), ("actor", actor_loss, actor)):
        ref_grads |= {
            f"{prefix}.{k}": g for k, g in zip(params, torch.autograd.grad(loss, list(params.values())), strict=True)
        }
    got = (info["critic_loss"], info["actor_loss"], agent.last_target, grads)
    return got, (critic_loss.item(), actor_loss.item(), y, ref_grads), agent


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    """|a - b| / |b| (norms): how far a tensor is from its reference, as a share of its size."""
    return float((a.double() - b.double()).norm() / b.double().norm())


def test_the_fast_fp32_update_computes_the_spec_losses_targets_and_gradients_to_float_tolerance():
    (critic_loss, actor_loss, y, grads), (ref_critic, ref_actor, ref_y, ref_grads), _ = update_and_reference("fp32")
    assert critic_loss == pytest.approx(ref_critic, rel=1e-5)
    assert actor_loss == pytest.approx(ref_actor, rel=1e-5)
    assert relative(y, ref_y) < 1e-5
    assert grads.keys() == ref_grads.keys()
    worst = max(ref_grads, key=lambda k: relative(grads[k], ref_grads[k]))
    assert relative(grads[worst], ref_grads[worst]) < 1e-5, worst


def test_bf16_keeps_weights_optimizer_state_targets_and_losses_in_fp32_and_computes_the_same_update():
    if not speed.fast_bf16(cuda=False):
        pytest.skip("this CPU has no bf16 matrix instructions (--precision bf16 is refused here)")
    (critic_loss, actor_loss, y, grads), (ref_critic, ref_actor, ref_y, ref_grads), agent = update_and_reference("bf16")
    nets = [agent.actor, agent.critic, agent.critic_target]
    assert all(p.dtype == torch.float32 for net in nets for p in net.parameters())
    assert all(g.dtype == torch.float32 for g in grads.values()) and y.dtype == torch.float32
    adam = [s for opt in (agent.actor_opt, agent.critic_opt) for s in opt.state.values()]
    assert adam and all(v.dtype == torch.float32 for s in adam for v in s.values() if v.dim())
    assert critic_loss == pytest.approx(ref_critic, rel=BF16_BOUNDS["losses"])
    assert actor_loss == pytest.approx(ref_actor, rel=BF16_BOUNDS["losses"])
    assert relative(y, ref_y) < BF16_BOUNDS["targets"]
    assert max(relative(grads[k], ref_grads[k]) for k in ref_grads) < BF16_BOUNDS["gradients"]


# The bf16 update is the fp32 one, rounded: bf16 keeps 8 significant bits. These bounds (relative; gradients: the
# worst relative norm) catch a wrong computation (a lost ReLU mask, a transposed gradient: errors of order 1), not
# the rounding, measured on CPU at 0.06% (losses), 0.24% (targets) and up to 4.4% (gradients, the message net's
# first layer worst). benchmarks/gpu_smoke.py holds a GPU's bf16 update to them too.
BF16_BOUNDS = dict(losses=0.05, targets=0.05, gradients=0.2)


def test_bf16_is_refused_with_one_line_where_the_device_has_no_fast_bf16(monkeypatch, capsys):
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: False)
    with pytest.raises(SystemExit) as e:
        plumbing.parse_args(gh.Args, gh.check_sampler_args, ["--precision", "bf16"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--precision bf16" in err and len(err.strip().splitlines()) == 1
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: True)
    assert plumbing.check_args(gh.Args(precision="bf16"), gh.check_sampler_args) is None


def test_a_bf16_checkpoint_resumed_where_bf16_is_slow_is_refused_unless_fp32_is_given(monkeypatch, capsys):
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: False)
    state = {"args": dataclasses.asdict(gh.Args(precision="bf16", n_blocks=3))}
    with pytest.raises(SystemExit) as e:
        plumbing.args_from_checkpoint(gh.Args(resume="run.pt"), {"resume"}, state, "--resume")
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1 and "--precision bf16" in err
    given = gh.Args(resume="run.pt", precision="fp32")
    args = plumbing.args_from_checkpoint(given, {"resume", "precision"}, state, "--resume")
    assert args.precision == "fp32" and args.n_blocks == 3


def test_the_default_precision_computes_the_bf16_update_where_the_cpu_has_bf16_matrix_units_else_the_fp32_one(
    monkeypatch,
):
    def losses(precision: str) -> tuple:  # one update's losses and gradients
        (critic_loss, actor_loss, _, grads), _, _ = update_and_reference(precision)
        return critic_loss, actor_loss, [g.tolist() for g in grads.values()]

    bf16_here = speed.fast_bf16(cuda=False)
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: False)
    fp32 = losses("fp32")
    assert losses("") == fp32
    if not bf16_here:  # oneDNN may have no bf16 products here at all
        pytest.skip("this CPU has no bf16 matrix instructions: the bf16 half is not computed here")
    monkeypatch.setattr(speed, "fast_bf16", lambda cuda: True)
    assert losses("bf16") == losses("") != fp32  # bf16's rounding: not fp32's numbers


@pytest.mark.parametrize(
    "flags, fast", [({"avx2": True}, False), ({"avx512_bf16": True}, True), ({"amx_bf16": True}, True)]
)
def test_fast_bf16_on_cpu_means_amx_or_avx512_bf16(monkeypatch, flags, fast):
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: flags)
    assert speed.fast_bf16(cuda=False) == (fast and torch.backends.mkldnn.is_available())


# --- the update's CPU kernels (speed.NodeNet, fused_edge_max, Head) against the plain nets --------------------
def nets_and_grads(fused: bool, dtype: torch.dtype, seed: int = 0):
    """A node net's readout, a head on it and a message net's max over edges, forward and every gradient, within
    speed.fast_nets: by the CPU kernels (fused) or the plain nets (their products in dtype) and torch's autograd.
    The node readout as the actor loss uses it (weights fixed, gradients to the action alone, zero for a third of
    the samples, as min(Q1, Q2) leaves them, and for all of them once) and as the critic loss does (weights and
    messages); both nets with gradients and without (the TD target's; the messages then in chunks: 70 samples,
    not a multiple of the chunk)."""
    torch.manual_seed(seed)
    b, n = 70, N_BLOCKS
    node, message = gh.MLP(4 + 10 + 15 + 24, 256, 159, large=True), gh.MLP(8, 256, 24, large=True)
    head = gh.MLP(159, 256, 1, out_relu=False)
    glob, local, edges = torch.randn(b, 14, requires_grad=True), torch.randn(b, n, 39), torch.randn(b, n * (n - 1), 8)
    local.requires_grad_()
    weights = list(node.parameters()) + list(message.parameters()) + list(head.parameters())
    out = {}
    with speed.fast_nets(gh, dtype, kernels=fused):
        live = torch.rand(b, 1) < 0.67  # the samples whose twin was the min
        fixed = speed.weight_view(node)  # the actor loss reads the critic's weights as constants
        (gh.node_sum(fixed, glob, local.detach()) * live * torch.randn(b, 159)).sum().backward()
        out["actor loss: action"] = glob.grad.clone()
        glob.grad = None
        (gh.node_sum(fixed, glob, local.detach()) * 0).sum().backward()  # no live sample at all: 0 rows
        assert not glob.grad.any()
        glob.grad = None
        readout = gh.node_sum(node, glob.detach(), local)
        msg = gh.edge_max(message, edges, n)
        (head(readout).squeeze(-1) * torch.randn(b)).sum().backward()
        (msg.float() * torch.randn(b, n, 24)).sum().backward()
        with torch.no_grad():
            out["target messages"] = gh.edge_max(message, edges, n).float()
            out["target readout"] = gh.node_sum(node, glob, local)
    out |= {"readout": readout.detach(), "messages": msg.detach().float(), "local": local.grad}
    out |= {f"weight {i}": p.grad for i, p in enumerate(weights)}
    return out


def test_the_cpu_kernels_compute_the_plain_nets_and_their_gradients_in_fp32():
    fused, plain = (nets_and_grads(f, torch.float32) for f in (True, False))
    assert fused.keys() == plain.keys()
    worst = max(plain, key=lambda k: relative(fused[k], plain[k]))
    assert relative(fused[worst], plain[worst]) < 1e-5, worst
    assert (fused["actor loss: action"] != 0).any(1).float().mean() < 0.8  # the dead samples' rows stay zero


def test_the_cpu_kernels_compute_the_plain_nets_in_bf16_on_any_cpu(monkeypatch):
    """torch's bf16 products in place of oneDNN's (which need bf16 instructions): the kernels' bf16 casts and
    fp32 sums, checked where --precision bf16 itself is refused."""
    monkeypatch.setattr(speed, "ONEDNN", False)
    fused, plain = (nets_and_grads(f, torch.bfloat16) for f in (True, False))
    assert fused["readout"].dtype == torch.float32 and all(g.dtype == torch.float32 for k, g in fused.items())
    assert max(relative(fused[k], plain[k]) for k in plain) < BF16_BOUNDS["gradients"]
    fp32 = nets_and_grads(True, torch.float32)
    assert max(relative(fused[k], fp32[k]) for k in fp32) < BF16_BOUNDS["gradients"]


def test_cpu_line_names_the_cpu_and_its_matrix_instructions(monkeypatch):
    caps = {"cpu_name": "Some Xeon", "amx_bf16": True, "avx512_bf16": False, "avx512_f": True, "avx2": True}
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: caps)
    line = speed.cpu_line()
    assert line.startswith("CPU: Some Xeon") and "AMX yes, AVX512-BF16 no, AVX512 yes, AVX2 yes" in line
    caps.update(amx_bf16=False, avx512_bf16=True, avx512_f=False)
    assert "AMX no, AVX512-BF16 yes, AVX512 no, AVX2 yes" in speed.cpu_line()
    caps.update(avx512_bf16=False)
    assert "fast bf16: False" in speed.cpu_line()


def test_the_max_over_edges_shares_its_gradient_among_exact_ties_as_amax_does():
    # Small integers throughout: every product and sum is exact in fp32, whatever order a kernel sums in, so
    # edges with the same input tie exactly; node i's two edges get the same input in half the samples.
    gen = torch.Generator().manual_seed(0)
    b, n = 16, 3
    ints = lambda *shape: torch.randint(-2, 3, shape, generator=gen).float()  # noqa: E731
    w1, b1, w2, b2 = ints(6, 8), ints(6), ints(4, 6), ints(4)
    edges = ints(b, n * (n - 1), 8)
    edges.view(b, n, n - 1, 8)[::2, :, 1] = edges.view(b, n, n - 1, 8)[::2, :, 0]
    grad = ints(b, n, 4)
    weights = [t.clone().requires_grad_() for t in (w1, b1, w2, b2)]
    (speed.EdgeMax.apply(edges, *weights, n, torch.float32) * grad).sum().backward()
    ref = [t.clone().requires_grad_() for t in (w1, b1, w2, b2)]
    y = F.relu(F.linear(F.relu(F.linear(edges, ref[0], ref[1])), ref[2], ref[3])).view(b, n, n - 1, 4)
    (y.amax(dim=2) * grad).sum().backward()
    ties = ((y == y.amax(dim=2, keepdim=True)) & (y > 0)).sum(2) > 1
    assert ties.sum() >= 10  # exact ties, where the gradient is shared
    for mine, theirs in zip(weights, ref, strict=True):
        torch.testing.assert_close(mine.grad, theirs.grad, rtol=0, atol=0)
