"""Learner speed (gangstr_hme.py), medians over repeats, CPU:

- one SAC update of the GNN actor-critic (batch 256), also with --precision bf16 where the CPU has bf16
  instructions, and, as a yardstick in the same run, one SAC update of plain MLPs (two hidden layers of 256)
  on the flat [obs, ag, g] input (benchmarks/bench_update.py compares the update with the machine's limit);
- one single-observation action (the per-step cost of acting);
- the safest path and the k = 5 shortest paths on a synthetic semantic graph of 13,000 nodes and
  about 300,000 edges (each node linked to 23 nodes among its 2,000 neighbours by id, so that paths
  are several edges long, as in the real graph);
- the share of real training cycles spent in planning and graph updates.

    python benchmarks/bench_learner.py [--threads 2] [--n-blocks 5]
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import gangstr_hme as gh  # noqa: E402
import speed  # noqa: E402


def median_ms(fn, repeats, warmup=3):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


class MLPSAC:
    """The yardstick: the same SAC update with plain 256 x 256 MLPs on [obs, ag, g]."""

    def __init__(self, n_in):
        def net(i, o):
            return nn.Sequential(nn.Linear(i, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, o))

        self.actor = net(n_in, 8)
        self.q = nn.ModuleList([net(n_in + 4, 1), net(n_in + 4, 1)])
        self.q_target = nn.ModuleList([net(n_in + 4, 1), net(n_in + 4, 1)])
        self.q_target.load_state_dict(self.q.state_dict())
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=1e-3)
        self.q_opt = torch.optim.Adam(self.q.parameters(), lr=1e-3)

    def sample(self, x):
        mean, log_std = self.actor(x).chunk(2, dim=-1)
        log_std = log_std.clamp(-20, 2)
        noise = torch.randn_like(mean)
        a = torch.tanh(mean + log_std.exp() * noise)
        return a, (-0.5 * noise**2 - log_std - 0.919 - torch.log(1 - a**2 + 1e-6)).sum(-1)

    def update(self, x, x2, a, r):
        with torch.no_grad():
            a2, logp2 = self.sample(x2)
            q2 = torch.min(*[q(torch.cat([x2, a2], 1)).squeeze(-1) for q in self.q_target])
            y = r + 0.99 * (q2 - 0.2 * logp2)
        qs = [q(torch.cat([x, a], 1)).squeeze(-1) for q in self.q]
        loss = F.mse_loss(qs[0], y) + F.mse_loss(qs[1], y)
        self.q_opt.zero_grad()
        loss.backward()
        self.q_opt.step()
        pi, logp = self.sample(x)
        actor_loss = (0.2 * logp - torch.min(*[q(torch.cat([x, pi], 1)).squeeze(-1) for q in self.q])).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        with torch.no_grad():
            for tp, p in zip(self.q_target.parameters(), self.q.parameters(), strict=True):
                tp.mul_(0.95).add_(p, alpha=0.05)


def synthetic_graph(n_nodes=13_000, degree=23, window=1_000, seed=0):
    rng = np.random.default_rng(seed)
    g = gh.SemanticGraph(3, gh.Args(n_blocks=3))
    for i in range(n_nodes):
        g._add_node(i)  # plain ids as configs
    offsets = rng.integers(-window, window + 1, size=(n_nodes, degree))
    targets = (np.arange(n_nodes)[:, None] + offsets) % n_nodes
    n_classes = n_nodes * degree // 120  # one SR per class of permutation-equivalent edges
    g.sr = rng.uniform(0.05, 1.0, size=n_classes).tolist()
    classes = rng.integers(n_classes, size=(n_nodes, degree))
    for u in range(n_nodes):
        for v, c in dict(zip(targets[u].tolist(), classes[u].tolist(), strict=True)).items():
            if v != u:
                g._add_edge(u, v, c)
    return g


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--n-blocks", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    print(speed.cpu_line())
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    n = args.n_blocks
    cfg = gh.Args(n_blocks=n, n_cycles=5, seed=0)
    run = gh.Run(cfg, torch.device("cpu"))
    learner = run.learner
    # Fill the replay with real segments so that the batch is realistic.
    (w,) = run.workers
    goal = int(gh.og.to_mask(w.env.goal))
    learner.learn_from([[gh.run_segments(learner.agent, [w], [gh.Request(goal, False)])[0] for _ in range(30)]])
    rng = np.random.default_rng(0)
    batch = learner.buffer.sample(256, [rng], 0.8, "final")
    gnn_ms = median_ms(lambda: learner.agent.update(batch), args.repeats)
    bf16_ms = None
    if speed.fast_bf16(cuda=False):
        bf16 = gh.SAC(gh.Args(n_blocks=n, precision="bf16"), learner.agent.normalizer.sum.shape[0], torch.device("cpu"))
        for net in ("actor", "critic", "critic_target"):
            getattr(bf16, net).load_state_dict(getattr(learner.agent, net).state_dict())
        bf16.normalizer = learner.agent.normalizer
        bf16_ms = median_ms(lambda: bf16.update(batch), args.repeats)

    t = learner.agent.to_tensors(batch)
    flat = torch.cat([t["obs"], t["ag"], t["g"]], 1)
    flat2 = torch.cat([t["obs_next"], t["ag_next"], t["g"]], 1)
    mlp = MLPSAC(flat.shape[1])
    mlp_ms = median_ms(lambda: mlp.update(flat, flat2, t["action"], t["reward"]), args.repeats)

    obs = {k: v[None] for k, v in w.env.reset(seed=1)[0].items()}
    noise = np.zeros((1, 4), np.float32)
    act = lambda: learner.agent.act(obs["observation"], obs["achieved_goal"], obs["desired_goal"], noise)  # noqa: E731
    act_blocks = [median_ms(act, 1000) for _ in range(5)]  # 5 blocks of 1,000 calls: shows the machine's drift
    act_ms = statistics.median(act_blocks)

    g = synthetic_graph()
    pairs = rng.integers(g.n_nodes, size=(40, 2))
    safest = [median_ms(lambda s=s, e=e: gh.safest_path(g, s, e, rng), 1, warmup=0) for s, e in pairs]
    kshort = [median_ms(lambda s=s, e=e: gh.k_shortest_paths(g, s, e, 5), 1, warmup=0) for s, e in pairs[:20]]
    lengths = [len(gh.safest_path(g, int(s), int(e), rng) or []) for s, e in pairs]

    learner.plan_seconds = 0.0
    t0 = time.perf_counter()
    for _ in range(cfg.n_cycles):
        gh.one_cycle(run)  # collect, learn_from, the SAC updates
    cycle_s = (time.perf_counter() - t0) / cfg.n_cycles
    share = learner.plan_seconds / cfg.n_cycles / cycle_s

    print(f"{n} blocks, {torch.get_num_threads()} torch threads, medians")
    print(f"  SAC update, GNN (batch 256)      {gnn_ms:7.1f} ms")
    if bf16_ms is not None:
        print(f"  ... with --precision bf16        {bf16_ms:7.1f} ms")
    print(f"  SAC update, 256x256 MLP          {mlp_ms:7.1f} ms   (GNN / MLP = {gnn_ms / mlp_ms:.2f}x)")
    print(f"  single-observation action        {act_ms:7.3f} ms   (medians of 5 x 1,000 calls: "
          f"{min(act_blocks):.3f}-{max(act_blocks):.3f})")  # fmt: skip
    typical = statistics.median(lengths)
    print(f"  synthetic graph: {g.n_nodes:,} nodes, {g.n_edges:,} edges, safest paths of {typical:.0f} configs")
    print(f"  safest path (Dijkstra)           {statistics.median(safest):7.1f} ms")
    print(f"  5 shortest paths (Yen + A*)      {statistics.median(kshort):7.1f} ms")
    print(f"  real cycle {cycle_s:.2f} s: planning + graph updates {share:.1%} "
          f"(agent graph {learner.graph.n_nodes:,} nodes, {learner.graph.n_edges:,} edges)")  # fmt: skip


if __name__ == "__main__":
    main()
