# Docs: README.md, section "How to read gangstr_hme.py beside the paper"; paper Sections 3-4;
# every number: SPEC §5-§7, §9-§12.
"""GANGSTR + Help Me Explore, in one file.

GANGSTR (paper Section 3.3) is an autotelic agent: a goal-conditioned SAC+HER learner whose actor and
critic are graph neural networks over the blocks, plus a *semantic graph* of the block configurations it
has met, used to decompose a goal into a path of easier sub-goals. HME (Section 3.1, 3.4) adds a social
partner who sometimes proposes a goal at the agent's frontier and a goal just beyond it.

    python gangstr_hme.py --sp-ratio 0.2                  # the paper's SP-20%, 5 blocks
    python gangstr_hme.py --sp-ratio 0 --n-blocks 3       # pure autotelic GANGSTR, 3 blocks

The paper's pseudo-code (appendix; Algorithm 1: autotelic, Algorithm 2: social), line by line:
    initialize Π, G_s, PE, B, B_i          Run: Learner (SAC, SemanticGraph, ReplayBuffer), GoalSampler
    loop                                   train_loop, one_cycle: run_cycle, then learn, then update
      Alg. 2: g ← SP.propose_frontier(G_s)    SocialPartner.frontier_goal, in GoalSampler.social_cycle
              g_b ← SP.propose_beyond(G_s, g) SocialPartner.beyond_goal, in GoalSampler.beyond_goals
              B_i.store(g, g_b)               GoalSampler.internalize, merged in after_cycle
      Alg. 1: (g, g_b) ← B_i.sample()         GoalSampler.rehearsal_cycle
              g ← G_s.sample_node()           Sampler.autotelic_goal, in Sampler.autotelic_cycle
      path ← PE.sample_path(g, G_s)        sample_path: the safest path, or one of the k shortest
      trajectory ← E.rollout(g_i)          follow_path yields one Request per sub-goal; drive runs
                                           every worker's segment together (run_segments)
      G_s.update, PE.update, B.update      Learner.learn_from, once per cycle (SPEC §5's schedule)
      Π.update(B)                          Learner.train: SAC.update on HER batches

Read top to bottom: Args, the networks (SPEC §5), normalizer and HER replay, SAC, the semantic graph
and its path estimator (SPEC §6), rollouts, goal samplers (Sampler: the hooks) and HME's (SPEC §7),
learning, evaluation (SPEC §9), the main loop, main(). What is not the algorithm (command line, processes,
checkpoints and the paper's trained agent, outputs, interruptions) is written once for the three training
scripts in plumbing.py, which a reader of the paper may skip, and what only makes it faster in speed.py.
"""

from __future__ import annotations

import collections
import collections.abc
import heapq
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import fetch5_env
import oracle_graph as og
import plumbing  # what is not the algorithm: command line, processes, checkpoints, outputs, interruptions
import speed  # what only makes it faster, the same math (the update's fast path: off with --plain)
from plumbing import all_gather_rows, all_sum, broadcast_params, gather_workers, rank, sum_grads, summed, world


@dataclass
class Args:
    exp_name: str = Path(__file__).stem
    """name of this experiment, by default the script's (the run folder is runs/{exp_name}__{seed}__{time})"""
    seed: int = 0
    """seed of numpy, torch and the environment"""
    n_blocks: int = 5
    """number of blocks (2-5; the paper uses 5)"""
    # --- the goal sampler: HME (SPEC §7) ---
    sp_ratio: float = 0.0
    """probability that a cycle is social (0.2 = the paper's SP-20%, 0 = pure autotelic GANGSTR)"""
    strategy: str = "frontier-and-beyond"
    """what the social partner proposes: 'frontier-and-beyond' (the paper's), 'frontier' or 'beyond'"""
    internalization_prob: float = 0.5
    """probability that a non-social cycle rehearses a failed social proposal (0 = the 'NI' ablation)"""
    ask_after: int = 0
    """beyond the paper (SPEC §7.1, learner_query.py): the learner asks the partner for help once its progress
    (--ask-progress) has stalled for this many cycles (0 = it never asks: the coin, --sp-ratio, alone brings it)"""
    help_cycles: int = 3
    """with --ask-after (refused without): social cycles in a row one query brings at most; the help stops sooner
    after a social cycle that added no progress (the partner had nothing new to show)"""
    ask_progress: str = ""
    """with --ask-after (refused without): the query's progress, 'nodes' of the semantic graph ('' = nodes) or its SR
    'classes' (kinds of transition): they grow longer, so it asks later (a pilot: epoch 6, not 1; towers later too)"""
    learner_picks: str = ""
    """beyond the paper: the learner picks among the partner's candidates by 'novelty' (new configs, then unseen
    pairs of facts) or 'zpd' (its surest frontier, then novelty, the critic's hardest); '': uniform (the paper's)"""
    partner: str = "oracle"
    """who chooses the partner's goals: 'oracle' (the paper's simulated partner, uniform draws) or 'person'
    (you, at a page the run serves: README.md, section "You as the social partner")"""
    person_timeout: float = 60.0
    """--partner person: seconds a question waits for an answer; then the oracle's draw is taken"""
    person_host: str = "127.0.0.1"
    """--partner person: the address the page is served on (by default, this machine only)"""
    person_port: int = 8765
    """--partner person: the page's port (0: any free one)"""
    RESUMABLE = ("person_timeout", "person_host", "person_port")  # --resume may change them (where the page is)
    NEEDS = {k: ("ask_after", "the learner never asks") for k in ("help_cycles", "ask_progress")}  # else refused
    SAME = dict(ask_progress={"": "nodes"})  # values that mean the same: --resume takes one for the other
    # --- schedule (SPEC §12) ---
    n_epochs: int = 100
    """number of epochs (one epoch = n-cycles cycles, then an evaluation)"""
    n_cycles: int = 50
    """cycles per epoch"""
    n_segments: int = 10
    """40-step segments collected per cycle"""
    n_updates: int = 30
    """SAC updates per cycle"""
    segment_len: int = 40
    """environment steps per segment (one sub-goal)"""
    # --- SAC + HER (SPEC §5) ---
    batch_size: int = 256
    """transitions per SAC update"""
    buffer_size: int = 1_000_000
    """replay capacity in transitions (FIFO)"""
    her_strategy: str = "final"
    """HER relabelling: 'final' (the segment's last achieved config, the paper's) or 'future'"""
    her_k: int = 4
    """HER ratio: a goal is relabelled with probability 1 - 1/(1 + k)"""
    gamma: float = 0.99
    """discount factor"""
    alpha: float = 0.2
    """SAC entropy coefficient (fixed)"""
    polyak: float = 0.95
    """target networks keep this share of their weights at each soft update"""
    target_update_every: int = 2
    """SAC updates between soft target updates"""
    lr_actor: float = 0.0
    """actor learning rate (Adam); 0: by SPEC §12's rule, the paper's 1e-3 at 24 workers or more, x0.3 below"""
    lr_critic: float = 0.0
    """critic learning rate (Adam); 0: as --lr-actor's"""
    paper_rates: bool = False
    """the paper's rates however few the workers (the rates not given; refused with --init-from, SPEC §12)"""
    # --- the semantic graph and its paths (SPEC §6) ---
    sr_ema: float = 0.01
    """EMA rate of an edge's success-rate estimate"""
    sr_prior: float = 0.5
    """success rate given to a new edge"""
    stable_steps: int = 10
    """a segment updates the graph only if its final config held over this many last steps"""
    k_shortest: int = 5
    """number of shortest paths to pick from"""
    shortest_ratio: float = 0.5
    """probability of following one of the k shortest paths instead of the safest (training only)"""
    max_path_len: int = 10
    """longest path in configs, start included (2 = no decomposition, the 'NG' ablation)"""
    # --- evaluation (SPEC §9) ---
    eval_goals_per_class: int = 24
    """evaluation goals per class"""
    max_eval_subgoals: int = 9
    """sub-goal segments an evaluation episode may use"""
    eval_only: bool = False
    """evaluate the --checkpoint and exit, no training: SR per class, printed and saved beside the checkpoint (the
    paper's file lives in a download cache, not a run folder: its results go to --runs-dir)"""
    checkpoint: str = ""
    """checkpoint to evaluate with --eval-only (paper: the authors' agent, fetched once into a cache)"""
    plan_on: str = "agent"
    """with --eval-only: plan sub-goals on the 'agent' graph (SPEC §9) or the 'oracle' graph (its shortest paths)"""
    capture_video: bool = False
    """with --eval-only: write an mp4 per class of its first --video-episodes evaluation episodes"""
    video_episodes: int = 3
    """evaluation episodes per class filmed by --capture-video"""
    # --- run and hardware (SPEC §10-§12) ---
    num_envs: int = 1
    """workers in this process (SPEC §11), stepped in lockstep; under torchrun, this many per process"""
    threads: int = 0
    """torch CPU threads (0: all cores; one with --overlap, and while several envs step in threads, see drive)"""
    overlap: bool = True
    """a cycle's SAC updates beside its collection, in a process of their own, on the replay before it (SPEC §12)"""
    cuda: bool = False
    """train on the GPU if one is available"""
    compile: bool = False
    """compile the SAC losses with torch.compile (start-up: about a minute on 2 CPU cores; docs/speed.md)"""
    precision: str = ""
    """the update's large products: 'fp32' or 'bf16' (bf16 products; weights, losses, targets fp32: docs/speed.md);
    '': bf16 on a CPU with bf16 matrix units (AMX, AVX512-BF16), else fp32 (SPEC §12)"""
    plain: bool = False
    """the update's speed tricks off: the plain nets (no CPU kernels), Adam unfused, glibc's memory default"""
    resume: str = ""
    """checkpoint to resume from (its run folder is continued)"""
    init_from: str = ""
    """start a new run from this file's networks and normalizer (a checkpoint; paper: the authors' agent); rest fresh"""
    init_prior_count: int = 100_000
    """with --init-from the paper's file: its normalizer statistics count as this many observations"""
    init_lr_scale: float = 0.1
    """with --init-from: both learning rates times this; at one worker 1 lost the paper's agent, 0.2 (Adam's square-root
    rule) kept S5 at 0.43-0.82 over 10 epochs, 0.1 at 0.80-0.92 (docs/results.md, "Continuing the paper's training")"""
    init_warmup: int = 2000
    """with --init-from: SAC updates over which both rates rise linearly from 0 (a fresh Adam's first steps move every
    weight by about lr, a trained net's too; 2,000 = 2 / (1 - beta2): Ma and Yarats 2021's untuned warm-up); 0: none"""
    init_learning_starts: int = 0
    """with --init-from: segments every worker's replay holds before a SAC update runs (0: measured no better)"""
    freeze_normalizer: bool = False
    """keep the normalizer's statistics as they start (with --n-updates 0: a fixed agent; docs/training.md); with
    --init-from it is on unless --no-freeze-normalizer: updating them lost the paper's agent (docs/results.md)"""
    save_buffer: bool = True
    """put the replay buffer in checkpoints (needed for an exact resume)"""
    runs_dir: str = "runs"
    """folder holding the run folders"""


# ------------------------------------------------------------------------------------------------
# The GNN actor-critic (SPEC §5; paper appendix "Object-centered architecture")
# ------------------------------------------------------------------------------------------------
BODY, PER_BLOCK, MSG = 10, 15, 24  # body features, features per block, message size
# The node nets' output widths: the authors' code's, 3 x their input widths (3 x 49, 3 x 53), which loading
# the paper's trained agent needs (SPEC §5).
ACTOR_NODE_OUT, CRITIC_NODE_OUT = 147, 159


class MLP(nn.Module):
    """Linear -> ReLU -> Linear (-> ReLU), the shape of every net in SPEC §5, written once for acting and
    updates. One module with a functional forward rather than an nn.Sequential of four: acting runs these
    nets on one observation, where each extra module call costs about as much as the small matmul it wraps.
    `large`: a net run on every edge or node (message and node nets), whose products --precision bf16
    computes in bf16 (speed.py). A fork may change it: speed.py's fast nets then step aside (see SAC)."""

    def __init__(self, n_in: int, n_hidden: int, n_out: int, out_relu: bool = True, large: bool = False):
        super().__init__()
        self.hidden, self.out, self.out_relu = nn.Linear(n_in, n_hidden), nn.Linear(n_hidden, n_out), out_relu
        self.large = large

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w1, b1, w2, b2 = self.params()
        x = F.linear(F.relu(F.linear(x, w1, b1)), w2, b2)
        return F.relu(x) if self.out_relu else x

    def params(self) -> tuple[torch.Tensor, ...]:
        return self.hidden.weight, self.hidden.bias, self.out.weight, self.out.bias


def node_sum(net: MLP, glob: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """sum_i net([glob, local_i]) (B, out), in fp32 whatever the net's precision, for the graph-wide features
    glob (B, .) and each node's own local (B, n, .): the node net's readout (SPEC §5)."""
    x = torch.cat([glob[:, None].expand(-1, local.shape[1], -1), local], dim=-1)  # node i: [glob, local_i]
    return net(x).sum(1, dtype=torch.float32)


def edge_max(net: MLP, edges: torch.Tensor, n: int) -> torch.Tensor:
    """(B, n, out): for node i, the max over its n - 1 outgoing edges (i, j) of net(edge input); edges
    (B, E, .) ordered by i (GraphIndex). The message passing of SPEC §5."""
    m = net(edges)
    return m.reshape(len(m), n, n - 1, m.shape[-1]).amax(dim=2)


def init_weights(module: nn.Module):
    """Xavier-uniform weights, zero biases (SPEC §5)."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.xavier_uniform_(m.weight)
            nn.init.zeros_(m.bias)


class GraphIndex:
    """Index tensors of the fully connected block graph: edge (i, j) for every ordered pair, ordered
    by i, so that the n - 1 outgoing edges of node i are contiguous."""

    def __init__(self, n_blocks: int, device):
        src, dst = og.above_pairs(n_blocks).T
        lookup = {(int(i), int(j)): k for k, (i, j) in enumerate(og.close_pairs(n_blocks))}
        close = [lookup[min(i, j), max(i, j)] for i, j in zip(src, dst, strict=True)]
        self.n = n_blocks
        # Edge inputs are one gather from [g - ag (dim), block slices (15n)]: for edge (i, j), the entries
        # close{i,j} and "i on j" of g - ag, then the positions of i and j (first 3 of their slices).
        dim = og.config_dim(n_blocks)
        above = np.arange(len(src)) + len(og.close_pairs(n_blocks))
        pos = dim + PER_BLOCK * np.stack([src, dst], axis=1)[:, :, None] + np.arange(3)  # (E, 2, 3)
        index = np.column_stack([close, above, pos.reshape(len(src), 6)])  # (E, 8)
        self.edge_index = torch.tensor(index.ravel(), device=device)


def split_obs(obs: torch.Tensor, n: int):
    """(B, 10 + 15n) -> body (B, 10), blocks (B, n, 15)."""
    return obs[:, :BODY], obs[:, BODY:].reshape(len(obs), n, PER_BLOCK)


class Critic(nn.Module):
    """Twin Q heads over shared messages. The message net belongs to the critic (and learns from the
    critic loss only); the actor reads the messages it computes."""

    def __init__(self, n_blocks: int):
        super().__init__()
        self.message = MLP(8, 256, MSG, large=True)  # edge input: [g - ag at close{i,j}, at i on j, pos i, pos j]
        node_in = 4 + BODY + PER_BLOCK + MSG
        self.q_nodes = nn.ModuleList([MLP(node_in, 256, CRITIC_NODE_OUT, large=True) for _ in range(2)])
        self.q_heads = nn.ModuleList([MLP(CRITIC_NODE_OUT, 256, 1, out_relu=False) for _ in range(2)])
        init_weights(self)

    def messages(self, gi: GraphIndex, blocks, gap) -> torch.Tensor:
        """(B, n, 24) from the goal gap g - ag (B, dim): node i = max over its outgoing edges (i, j) of
        the edge messages."""
        b = len(blocks)
        features = torch.cat([gap, blocks.reshape(b, -1)], dim=1)
        return edge_max(self.message, features[:, gi.edge_index].reshape(b, -1, 8), gi.n)  # edge inputs (B, E, 8)

    def q(self, body, blocks, action, msg):
        """Twin Q values; node input [action, body, block i, message i] (built once for both twins),
        summed over nodes (in fp32, whatever the node nets' precision: the heads and Q values stay fp32)."""
        glob, local = torch.cat([action, body], dim=1), torch.cat([blocks, msg], dim=2)
        heads = zip(self.q_nodes, self.q_heads, strict=True)
        return [head(node_sum(node, glob, local)).squeeze(-1) for node, head in heads]


class Actor(nn.Module):
    def __init__(self, n_blocks: int):
        super().__init__()
        self.node = MLP(BODY + PER_BLOCK + MSG, 256, ACTOR_NODE_OUT, large=True)
        # SPEC §5's head Linear(147, 256) -> ReLU, then its mean and log-std layers, Linear(256, 4) each,
        # stacked in one Linear(256, 8): one matmul for both, cheaper acting.
        self.head = MLP(ACTOR_NODE_OUT, 256, 8, out_relu=False)
        init_weights(self)
        nn.init.xavier_uniform_(self.head.out.weight.data[:4])  # Xavier bounds of two (256 -> 4) layers
        nn.init.xavier_uniform_(self.head.out.weight.data[4:])

    def forward(self, body, blocks, msg):
        """Node input [body, block i, message i], summed over nodes (in fp32, as the critic's), then the
        Gaussian head."""
        nodes = node_sum(self.node, body, torch.cat([blocks, msg], dim=2))
        mean, log_std = self.head(nodes).chunk(2, dim=-1)
        return mean, log_std.clamp(-20, 2)

    def sample(self, body, blocks, msg, noise):
        """Squashed Gaussian action and its log-probability (with the tanh correction), for the standard
        normal draws `noise` (B, 4): drawn by the caller, from each worker's own random stream."""
        mean, log_std = self(body, blocks, msg)
        u = mean + log_std.exp() * noise  # reparameterised Gaussian sample
        a = torch.tanh(u)
        gauss_log_prob = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
        return a, (gauss_log_prob - torch.log(1 - a.pow(2) + 1e-6)).sum(-1)


# ------------------------------------------------------------------------------------------------
# Observation normalizer and HER replay (SPEC §5)
# ------------------------------------------------------------------------------------------------
class Normalizer:
    """Running mean/std of raw observations clipped to +-5; std floored at 0.01; output clipped to +-5."""

    def __init__(self, size: int, eps: float = 0.01, clip: float = 5.0):
        self.eps, self.clip = eps, clip
        self.sum, self.sumsq, self.count = np.zeros(size), np.zeros(size), 0
        self.mean, self.std = np.zeros(size), np.ones(size)

    def update(self, x: np.ndarray):
        """Add x (workers, ..., size): this process's workers' new observations. The sums of every worker,
        in global worker order (SPEC §11): the same statistics however the workers share processes."""
        x = np.clip(x.reshape(len(x), -1, len(self.sum)), -self.clip, self.clip).astype(np.float64)
        per_worker = np.concatenate([x.sum(1), (x * x).sum(1), np.full((len(x), 1), x.shape[1])], axis=1)
        stats = gather_workers(per_worker).sum(0)
        self.add(stats[: len(self.sum)], stats[len(self.sum) : -1], int(stats[-1]))

    def add(self, s, ss, count):
        self.sum += s
        self.sumsq += ss
        self.count += count
        if self.count == 0:  # nothing seen yet (a checkpoint from before the first cycle): the identity
            self.mean, self.std = np.zeros_like(self.sum), np.ones_like(self.sum)
            return
        self.mean = self.sum / self.count
        self.std = np.sqrt(np.maximum(self.eps**2, self.sumsq / self.count - self.mean**2))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.clip(x, -self.clip, self.clip)
        return np.clip((x - self.mean) / self.std, -self.clip, self.clip).astype(np.float32)


class ReplayBuffer:
    """Each worker's own FIFO replay of segments (SPEC §5, §11), for all the workers of this process in
    one array: axis 0 is the worker, axis 1 its segments; goals stored as int8 (+-1). Every worker
    stores a cycle's segments at once, so all fill alike."""

    def __init__(self, n_workers: int, n_segments: int, seg_len: int, obs_dim: int, goal_dim: int):
        self.obs = np.zeros((n_workers, n_segments, seg_len + 1, obs_dim), np.float32)
        self.ag = np.zeros((n_workers, n_segments, seg_len + 1, goal_dim), np.int8)
        self.g = np.zeros((n_workers, n_segments, goal_dim), np.int8)
        self.actions = np.zeros((n_workers, n_segments, seg_len, 4), np.float32)
        self.ptr, self.size = 0, 0

    def store(self, obs, ag, g, actions):
        """Add each worker's segments: obs (W, S, T+1, .), ag (W, S, T+1, .), g (W, S, .), actions (W, S, T, 4)."""
        capacity = self.obs.shape[1]
        idx = (self.ptr + np.arange(obs.shape[1])) % capacity
        self.obs[:, idx], self.ag[:, idx], self.g[:, idx], self.actions[:, idx] = obs, ag, g, actions
        self.ptr = int((self.ptr + obs.shape[1]) % capacity)
        self.size = min(self.size + obs.shape[1], capacity)

    def sample(self, batch: int, rngs: list[np.random.Generator], her_prob: float, strategy: str) -> dict:
        """`batch` transitions from each worker's replay (uniform segments and steps), drawn with that
        worker's random stream as if it were alone in its process, concatenated in worker order. A goal
        is relabelled with probability her_prob, the reward recomputed. With them, the standard normal
        draws of the update's two policy samples (SPEC §5), from the same streams: an update depends on
        its batch alone, however the workers share processes."""
        seg_len = self.actions.shape[2]
        draws = []
        for rng in rngs:  # a handful of draws per worker; the gathers below are one for all workers
            ep, t, her = rng.integers(self.size, size=batch), rng.integers(seg_len, size=batch), rng.random(batch)
            if strategy == "final":
                future = np.full(batch, seg_len)
            else:  # a later achieved config of the same segment, in [t + 1, T]
                future = t + 1 + (rng.random(batch) * (seg_len - t)).astype(np.int64)
            draws.append((ep, t, her < her_prob, future, rng.standard_normal((batch, 8), dtype=np.float32)))
        ep, t, her, future, noise = (np.concatenate(x) for x in zip(*draws, strict=True))
        w = np.repeat(np.arange(len(rngs)), batch)
        g = self.g[w, ep]
        g[her] = self.ag[w[her], ep[her], future[her]]
        ag_next = self.ag[w, ep, t + 1]
        return dict(
            obs=self.obs[w, ep, t],
            obs_next=self.obs[w, ep, t + 1],
            ag=self.ag[w, ep, t].astype(np.float32),
            ag_next=ag_next.astype(np.float32),
            g=g.astype(np.float32),
            action=self.actions[w, ep, t],
            reward=fetch5_env.goal_reached(ag_next, g).astype(np.float32),
            noise_next=noise[:, :4],  # for the next action in the critic's target
            noise_pi=noise[:, 4:],  # for the action the actor loss scores
        )


# ------------------------------------------------------------------------------------------------
# SAC (SPEC §5)
# ------------------------------------------------------------------------------------------------
class SAC:
    def __init__(self, args: Args, obs_dim: int, device):
        self.args, self.device = args, torch.device(device)
        self.gi = GraphIndex(args.n_blocks, device)
        self.actor = Actor(args.n_blocks).to(device)
        self.critic = Critic(args.n_blocks).to(device)
        self.critic_target = Critic(args.n_blocks).to(device)
        broadcast_params(self.actor, self.critic)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.acting_actor, self.acting_critic = speed.weight_view(self.actor), speed.weight_view(self.critic)
        (lr_actor, _), (lr_critic, _) = plumbing.adam_rates(args)  # SPEC §12 (after --init-from, §10; see update)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=lr_actor)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=lr_critic)
        self.lrs = [g["lr"] for g in (*self.actor_opt.param_groups, *self.critic_opt.param_groups)]  # each group's
        self.normalizer = Normalizer(obs_dim)
        self.n_updates = 0
        # --compile: the losses as one torch.compile graph (forward and backward); eager is the reference.
        self.compute_losses = torch.compile(self.losses) if args.compile else self.losses
        if not args.plain:  # the fast path, the same losses (CPU kernels, --precision bf16, fused Adam): speed.py
            speed.fast_update(self)

    @torch.inference_mode()
    def act(self, obs: np.ndarray, ag: np.ndarray, g: np.ndarray, noise: np.ndarray | None = None) -> np.ndarray:
        """Actions (K, 4) of K workers in one forward pass: obs (K, .), ag and g (K, .). `noise` (K, 4)
        holds each worker's standard normal draws, zeros for the deterministic policy (its mean: the
        sample is mean + std x noise); None: deterministic for all."""
        o = torch.from_numpy(self.normalizer(obs)).to(self.device)  # from_numpy: cheaper than as_tensor
        body, blocks = split_obs(o, self.gi.n)
        msg = self.acting_critic.messages(self.gi, blocks, torch.from_numpy(g - ag).to(self.device))
        mean, log_std = self.acting_actor(body, blocks, msg)
        u = mean if noise is None else mean + log_std.exp() * torch.from_numpy(noise).to(self.device)
        return torch.tanh(u).cpu().numpy()

    def losses(self, batch: dict):
        """Critic and actor losses of SPEC §5 on a batch of (normalized) tensors holding each of this
        process's workers' samples: each loss is the sum over workers of their mean losses, whose
        gradient is the sum of the workers' gradients (SPEC §11)."""
        a, gi, workers = self.args, self.gi, self.args.num_envs
        body, blocks = split_obs(batch["obs"], gi.n)
        body2, blocks2 = split_obs(batch["obs_next"], gi.n)
        with torch.no_grad():
            gap2 = batch["g"] - batch["ag_next"]
            msg2 = self.critic.messages(gi, blocks2, gap2)
            a2, logp2 = self.actor.sample(body2, blocks2, msg2, batch["noise_next"])
            tmsg2 = self.critic_target.messages(gi, blocks2, gap2)
            q_next = torch.min(*self.critic_target.q(body2, blocks2, a2, tmsg2))
            target = batch["reward"] + a.gamma * (q_next - a.alpha * logp2)  # no terminal masking
        msg = self.critic.messages(gi, blocks, batch["g"] - batch["ag"])
        q1, q2 = self.critic.q(body, blocks, batch["action"], msg)
        critic_loss = workers * (F.mse_loss(q1, target) + F.mse_loss(q2, target))
        # The actor loss reaches the actor's weights alone: its gradient flows through the critic's Q heads to
        # the action, but the critic's weights are constants there (acting_critic), and its messages detached
        # (the message net learns from the critic loss only).
        pi, logp = self.actor.sample(body, blocks, msg.detach(), batch["noise_pi"])
        q_pi = torch.min(*self.acting_critic.q(body, blocks, pi, msg.detach()))
        actor_loss = workers * (a.alpha * logp - q_pi).mean()
        return critic_loss, actor_loss, target, dict(q=q1.mean(), entropy=-logp.mean())

    def update(self, np_batch: dict) -> dict:
        batch = self.to_tensors(np_batch)
        if self.args.init_from and self.n_updates < self.args.init_warmup:  # --init-warmup (0: none)
            scale = (self.n_updates + 1) / self.args.init_warmup
            for group, lr in zip((*self.actor_opt.param_groups, *self.critic_opt.param_groups), self.lrs, strict=True):
                group["lr"] = lr * scale
        critic_loss, actor_loss, target, stats = self.compute_losses(batch)
        self.last_batch, self.last_target = batch, target  # for goal samplers that learn from TD targets (VDS)
        self.actor_opt.zero_grad()
        self.critic_opt.zero_grad()
        (critic_loss + actor_loss).backward()  # each loss reaches its own network's weights only (see losses)
        sum_grads(list(self.actor.parameters()) + list(self.critic.parameters()))
        self.critic_opt.step()
        self.actor_opt.step()
        self.n_updates += 1
        if self.n_updates % self.args.target_update_every == 0:
            self.soft_update()
        workers = self.args.num_envs  # the losses are sums over workers; the logs show one worker's mean
        info = dict(critic_loss=critic_loss.double() / workers, actor_loss=actor_loss.double() / workers,
                    target=target.mean(), **stats)  # fmt: skip
        return {k: v.detach() for k, v in info.items()}  # tensors: a read waits for the update (Learner.train's)

    @torch.no_grad()
    def soft_update(self):
        for tp, p in zip(self.critic_target.parameters(), self.critic.parameters(), strict=True):
            tp.mul_(self.args.polyak).add_(p, alpha=1 - self.args.polyak)

    def to_tensors(self, b: dict) -> dict:
        """The batch on the device, obs and obs_next normalized (the raw ones stay here): speed.to_device."""
        b = b | dict(obs=self.normalizer(b["obs"]), obs_next=self.normalizer(b["obs_next"]))
        return speed.to_device(b, self.device)


# ------------------------------------------------------------------------------------------------
# The agent's semantic graph and goal decomposition (SPEC §6; paper Section 3.3, appendix)
# ------------------------------------------------------------------------------------------------
YEN_PATHS_PER_SHAPE = 4  # Yen's work bound in k_shortest_paths: at most 4k paths examined for k shapes


class SemanticGraph:
    """Configs the agent has met (as int masks, see oracle_graph) linked by small steps it has made.

    Every node comes with all its block permutations, and every edge with all its joint permutations;
    equivalent edges share one success-rate estimate (the paper's "edge permutation bias"), keyed by
    the canonical form of the ordered pair. Adjacency is kept as Python lists: the graph grows a little
    after every cycle, and the path searches walk it node by node."""

    def __init__(self, n_blocks: int, args: Args):
        self.n, self.dim, self.args = n_blocks, og.config_dim(n_blocks), args
        self.masks: list[int] = []  # node id -> config mask
        self.node_of: dict[int, int] = {}  # config mask -> node id
        self.succ: list[list[int]] = []  # node id -> successor node ids
        self.succ_class: list[list[int]] = []  # ... and the SR class of each of those edges
        self.edge_log: list[tuple[int, int, int]] = []  # (u, v, class) in creation order
        self.class_of_key: dict[int, int] = {}  # canonical key of an ordered pair -> SR class
        self.sr: list[float] = []  # SR class -> success-rate estimate
        self._cache: dict = {}  # arrays derived from the edges (CSR, edge keys); cleared on any change

    @property
    def n_nodes(self) -> int:
        return len(self.masks)

    @property
    def n_edges(self) -> int:
        return len(self.edge_log)

    def add_config(self, mask: int):
        """A config and all its block permutations become nodes."""
        if mask in self.node_of:
            return
        for m in dict.fromkeys(og.permute_masks(mask, self.n).tolist()):
            if m not in self.node_of:
                self._add_node(m)

    def _add_node(self, mask: int):
        self.node_of[mask] = len(self.masks)
        self.masks.append(mask)
        self.succ.append([])
        self.succ_class.append([])
        self._cache.clear()

    def edge_class(self, s: int, f: int) -> int:
        """SR class of the edge s -> f, creating it with all its joint permutations if it is new."""
        ps, pf = og.permute_masks(np.array([s, f]), self.n)
        key = int(((ps << self.dim) | pf).min())  # canonical form of the ordered pair
        c = self.class_of_key.get(key)
        if c is None:
            c = self.class_of_key[key] = len(self.sr)
            self.sr.append(self.args.sr_prior)
            for u, v in dict.fromkeys(zip(ps.tolist(), pf.tolist(), strict=True)):
                self._add_edge(self.node_of[u], self.node_of[v], c)
        return c

    def _add_edge(self, u: int, v: int, c: int):
        self.succ[u].append(v)
        self.succ_class[u].append(c)
        self.edge_log.append((u, v, c))
        self._cache.clear()

    def update(self, start: int, final: int, target: int, success: bool):
        """Learn from one stable segment (SPEC §6): new nodes, a new edge for a new small step, and the
        EMA of the success rate of start -> target when the target is a known node."""
        self.add_config(start)
        self.add_config(final)
        if start != final and is_small_step(start, final, self.n):
            self.edge_class(start, final)
        if target in self.node_of and start != target and is_small_step(start, target, self.n):
            c = self.edge_class(start, target)
            self.sr[c] += self.args.sr_ema * (float(success) - self.sr[c])

    def sample_node(self, rng: np.random.Generator) -> int | None:
        return self.masks[rng.integers(self.n_nodes)] if self.masks else None

    def csr(self, by: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Edges grouped by their tail (by=0: successor lists) or head (by=1: predecessor lists), as CSR:
        indptr, the other end of each edge, and its SR class."""
        if by not in self._cache:
            edges = np.array(self.edge_log, dtype=np.int64).reshape(-1, 3)
            order = np.argsort(edges[:, by], kind="stable")
            indptr = np.searchsorted(edges[order, by], np.arange(self.n_nodes + 1))
            self._cache[by] = (indptr, edges[order, 1 - by], edges[order, 2])
        return self._cache[by]

    def reachable(self, start: int) -> np.ndarray:
        """Masks of the nodes reachable from config `start` along agent edges, start included."""
        s = self.node_of.get(start)
        if s is None:
            return np.array([start], dtype=np.int64)
        return np.asarray(self.masks, dtype=np.int64)[og.bfs_hops(*self.csr(0)[:2], s) >= 0]

    def edge_keys(self) -> np.ndarray:
        """Sorted int keys (mask_u << dim | mask_v) of the agent's edges, for set look-ups in numpy."""
        if "keys" not in self._cache:
            masks = np.asarray(self.masks, dtype=np.int64)
            edges = np.array(self.edge_log, dtype=np.int64).reshape(-1, 3)
            self._cache["keys"] = np.sort((masks[edges[:, 0]] << self.dim) | masks[edges[:, 1]])
        return self._cache["keys"]

    def state_dict(self) -> dict:
        return dict(
            masks=torch.tensor(self.masks, dtype=torch.int64),
            edges=torch.tensor(self.edge_log, dtype=torch.int64).reshape(-1, 3),
            class_keys=torch.tensor(list(self.class_of_key.items()), dtype=torch.int64).reshape(-1, 2),
            sr=torch.tensor(self.sr, dtype=torch.float64),
        )

    def load_state_dict(self, state: dict):
        self.__init__(self.n, self.args)
        for m in state["masks"].tolist():
            self._add_node(m)
        for u, v, c in state["edges"].tolist():
            self._add_edge(u, v, c)
        self.class_of_key = dict(map(tuple, state["class_keys"].tolist()))
        self.sr = state["sr"].tolist()


def is_small_step(a: int, b: int, n: int) -> bool:
    return bool(og.is_small_step(og.from_mask(a, n), og.from_mask(b, n)))


# --- the path estimator (the paper's PE.sample_path; SPEC §6) -----------------------------------
def sample_path(graph: SemanticGraph, start: int, goal: int, rng: np.random.Generator, explore: bool) -> list[int]:
    """Sub-goal path [start, ..., goal] (SPEC §6). Training (explore) follows one of the k shortest
    paths with probability shortest_ratio, else the safest; without a path: [start, goal]. A path
    longer than max_path_len keeps its start and its last max_path_len - 1 configs."""
    if explore and rng.random() < graph.args.shortest_ratio:
        paths = k_shortest_paths(graph, start, goal, graph.args.k_shortest)
        path = paths[rng.integers(len(paths))] if paths else None
    else:
        path = safest_path(graph, start, goal, rng)
    path = path or [start, goal]
    cap = graph.args.max_path_len
    return path if len(path) <= cap else [path[0]] + path[-(cap - 1) :]


def safest_path(graph: SemanticGraph, start: int, goal: int, rng: np.random.Generator) -> list[int] | None:
    """Path maximising the product of edge SRs: Dijkstra (binary heap, early exit) on -log SR.
    Equally safe paths are equally likely (SPEC §6): a beginner's edges all sit at the prior, so
    every path of the same length ties, and always taking the same one would repeat its mistakes."""
    s, t = graph.node_of.get(start), graph.node_of.get(goal)
    if s is None or t is None or s == t:
        return None
    cost = (-np.log(np.clip(graph.sr, 1e-12, 1.0))).tolist()
    dist, order, heap = [math.inf] * graph.n_nodes, {}, [(0.0, s)]
    dist[s] = 0.0
    succ, succ_class = graph.succ, graph.succ_class
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue  # a stale heap entry
        order[u] = len(order)  # settled: dist[u] is final
        if u == t:
            return [graph.masks[i] for i in _sample_tight_path(graph, s, t, dist, order, cost, rng)]
        for v, c in zip(succ[u], succ_class[u]):  # noqa: B905 (equal lengths by construction; hot loop)
            nd = d + cost[c]
            if nd < dist[v]:
                dist[v] = nd
                heapq.heappush(heap, (nd, v))
    return None


def _sample_tight_path(graph: SemanticGraph, s: int, t: int, dist: list, order: dict, cost: list, rng) -> list[int]:
    """One of the optimal s -> t paths of a finished Dijkstra, uniformly. An edge u -> v is on an
    optimal path when u was settled before v and dist[u] + cost = dist[v] (up to 1e-9: costs are
    float sums in different orders); all of them are settled when t is. Counting the optimal paths
    into each node, then walking back from t choosing each predecessor in proportion to its count,
    gives every optimal path the same chance. Only the nodes on optimal paths are visited."""
    indptr, tails, classes = graph.csr(1)
    preds, todo = {}, [t]
    while todo:  # the optimal-path DAG, backwards from t
        v = todo.pop()
        if v in preds or v == s:
            continue
        lo, hi = int(indptr[v]), int(indptr[v + 1])
        preds[v] = [
            u
            for u, c in zip(tails[lo:hi].tolist(), classes[lo:hi].tolist(), strict=True)
            if order.get(u, math.inf) < order[v] and abs(dist[u] + cost[c] - dist[v]) <= 1e-9
        ]
        todo += preds[v]
    count = {s: 1}
    for v in sorted(preds, key=order.__getitem__):  # settle order: predecessors first
        count[v] = sum(count[u] for u in preds[v])
    path = [t]
    while path[-1] != s:
        options = preds[path[-1]]
        if len(options) > 1:
            r = rng.random() * count[path[-1]]
            for u in options:
                r -= count[u]
                if r < 0:
                    break
        else:
            u = options[0]
        path.append(u)
    return path[::-1]


def k_shortest_paths(graph: SemanticGraph, start: int, goal: int, k: int) -> list[list[int]]:
    """Up to k shortest loopless paths in number of edges, of k different shapes (SPEC §6): Yen's
    algorithm, each spur path found by A* guided by the exact hop count to the goal in the whole
    graph (admissible when Yen removes nodes and edges, so each search stays close to the shortest
    paths). A path with the sequence of SR classes of a kept one (a block permutation of it) stays
    in Yen's list, which the next spurs need, but is not kept. Yen stops after YEN_PATHS_PER_SHAPE * k
    paths: one shape can have dozens of block permutations, and each further path costs one search
    per node of the previous one."""
    s, t = graph.node_of.get(start), graph.node_of.get(goal)
    if s is None or t is None or s == t or k < 1:
        return []
    hops = og.bfs_hops(*graph.csr(1)[:2], t).tolist()  # hop count to t along predecessor lists
    first = _astar(graph, s, t, hops, set(), set())
    if first is None:
        return []
    found, candidates, seen = [first], [], {tuple(first)}
    kept = {_shape(graph, first): first}  # shape -> its shortest path, in Yen's order
    while len(kept) < k and len(found) < YEN_PATHS_PER_SHAPE * k:
        last = found[-1]
        for i in range(len(last) - 1):
            root = last[: i + 1]
            banned_edges = {(p[i], p[i + 1]) for p in found if len(p) > i + 1 and p[: i + 1] == root}
            spur = _astar(graph, last[i], t, hops, set(root[:-1]), banned_edges)
            if spur is not None and tuple(root[:-1] + spur) not in seen:
                seen.add(tuple(root[:-1] + spur))
                heapq.heappush(candidates, (len(root) + len(spur), root[:-1] + spur))
        if not candidates:
            break
        found.append(heapq.heappop(candidates)[1])
        kept.setdefault(_shape(graph, found[-1]), found[-1])
    return [[graph.masks[i] for i in p] for p in kept.values()]


def _shape(graph: SemanticGraph, path: list[int]) -> tuple[int, ...]:
    """The SR classes of a path's edges: equal for paths that are block permutations of each other."""
    return tuple(graph.succ_class[u][graph.succ[u].index(v)] for u, v in zip(path, path[1:], strict=False))


def _astar(
    graph: SemanticGraph, s: int, t: int, hops: list[int], banned_nodes: set, banned_edges: set
) -> list[int] | None:
    if hops[s] < 0:
        return None
    dist, prev, heap = {s: 0}, {s: -1}, [(hops[s], 0, s)]
    while heap:
        _, neg_d, u = heapq.heappop(heap)
        if u == t:
            return _trace(prev, t)
        if -neg_d > dist[u]:
            continue
        nd = 1 - neg_d
        for v in graph.succ[u]:
            if hops[v] < 0 or v in banned_nodes or (u, v) in banned_edges or nd >= dist.get(v, math.inf):
                continue
            dist[v], prev[v] = nd, u
            heapq.heappush(heap, (nd + hops[v], -nd, v))  # ties: deepest first
    return None


def _trace(prev, t: int) -> list[int]:
    """Walk the predecessor map (a list or a dict, -1 at the start) back from t."""
    path = [t]
    while prev[path[-1]] >= 0:
        path.append(prev[path[-1]])
    return path[::-1]


# ------------------------------------------------------------------------------------------------
# Rollouts: workers, segments, and the driver that steps every worker together (SPEC §5, §6, §11)
# ------------------------------------------------------------------------------------------------
@dataclass
class Segment:
    obs: np.ndarray  # (T + 1, obs_dim) raw observations
    ag: np.ndarray  # (T + 1, goal_dim) achieved configs
    g: np.ndarray  # (goal_dim,) the sub-goal
    actions: np.ndarray  # (T, 4)
    success: bool  # ended on g (fetch5_env.goal_reached)
    stable: bool  # the final config held over the last stable_steps steps

    @property
    def start(self) -> int:
        return int(og.to_mask(self.ag[0]))

    @property
    def final(self) -> int:
        return int(og.to_mask(self.ag[-1]))


class Request(NamedTuple):
    """What a worker's program asks for next: one segment toward the config `goal` (a mask), from
    wherever its blocks are (no reset: sub-goals chain). `frames`, a list, gets an image per step."""

    goal: int
    deterministic: bool
    frames: list | None = None


class Worker:
    """One of SPEC §11's workers: its own env, seed (seed + global worker index) and random stream, and
    the segments it may still run this cycle. A process holds --num-envs of them; under torchrun, process
    r holds workers r x num_envs ... r x num_envs + num_envs - 1. What the paper's workers share after
    each sync (networks, normalizer, semantic graph, internalized pairs) is the Learner's and the
    GoalSampler's."""

    def __init__(self, args: Args, index: int):
        self.index = index
        render_mode = "rgb_array" if args.capture_video else None
        self.env = fetch5_env.FetchManipulateEnv(n_blocks=args.n_blocks, render_mode=render_mode)
        self.seed(args.seed + index)
        self.left, self.segments = 0, []  # segments it may still run this cycle; those it ran

    def seed(self, *words: int):
        """Independent random streams from the seed words (SPEC §3, §11): the worker's own (self.rng: cycle
        kinds, goals, paths, noise, HER draws), its env's (block placements) and, with --overlap, its updates'
        batches' (batch_rng). Children of one SeedSequence: seeding two with one number would make one stream."""
        mine, env, batches = np.random.SeedSequence(words).spawn(3)
        self.rng, self.batch_rng = np.random.default_rng(mine), np.random.default_rng(batches)
        self.env.reset(seed=int(env.generate_state(1)[0]))


def current_config(env) -> int:
    return int(og.to_mask(env.set_goal(env.goal)["achieved_goal"]))


def follow_path(w: Worker, path: list[int], deterministic: bool, frames: list | None = None):
    """Program step: one segment per sub-goal of path[1:], moving on only while each is reached and
    the worker has segments left. Returns whether the path's last config was reached, or None if the
    cycle's budget ran out first: an attempt cut off is no outcome, neither success nor failure."""
    for sub in path[1:]:
        if w.left <= 0:
            return None
        segment = yield Request(sub, deterministic, frames)
        if not segment.success:
            return False
    return True


def pursue(learner: Learner, w: Worker, goal: int, explore: bool, deterministic: bool):
    """Program step: a path from the current config to goal (sample_path on the semantic graph), then
    follow it. Returns whether goal was reached (None: cut off by the budget, see follow_path)."""
    t = time.perf_counter()
    path = sample_path(learner.graph, current_config(w.env), goal, w.rng, explore)
    learner.plan_seconds += time.perf_counter() - t
    return (yield from follow_path(w, path, deterministic))


# --- the driver: every worker's program in lockstep (SPEC §11) ------------------------------------
def drive(agent: SAC, programs: dict[Worker, collections.abc.Generator], name: str = "evaluation"):
    """Run one program per worker (a generator of Requests that receives each finished Segment) until
    all are done. Each round, every worker with a request gets its segment, all stepped together;
    each segment goes to its worker's list. A program that asks for more than its worker's budget (w.left)
    stops the run, named `name`."""
    requests = {}

    def advance(w, segment):
        try:
            requests[w] = programs[w].send(segment)
        except StopIteration:
            requests.pop(w, None)

    with speed.physics_first(agent.args.num_envs):  # envs stepped in threads, torch's waiting (speed.py)
        for w in programs:
            advance(w, None)
        while requests:
            workers = list(requests)
            segments = run_segments(agent, workers, [requests[w] for w in workers])
            for w, segment in zip(workers, segments, strict=True):
                w.segments.append(segment)
                w.left -= 1
                if w.left < 0:  # a forked cycle that ignores its budget: stop it now, not after it (never) ends
                    plumbing.budget_error(name, f"asked for more than worker {w.index}'s")
                advance(w, segment)


def run_segments(agent: SAC, workers: list[Worker], requests: list[Request]) -> list[Segment]:
    """One segment per worker, in lockstep: at each of the T steps, one forward pass acts for all of
    them, then their envs step in parallel threads (speed.step_envs: MuJoCo releases the GIL while it simulates).
    Exploration noise comes from each worker's own random stream."""
    a, K, env = agent.args, len(workers), workers[0].env
    T = a.segment_len
    goals = og.from_mask(np.array([r.goal for r in requests], dtype=np.int64), a.n_blocks)
    o = np.empty((K, T + 1, env.obs_dim), np.float32)
    ag = np.empty((K, T + 1, env.goal_dim), np.float32)
    actions = np.empty((K, T, 4), np.float32)
    noise = np.zeros((K, T, 4), np.float32)
    for k, (w, r) in enumerate(zip(workers, requests, strict=True)):
        first = w.env.set_goal(goals[k])
        o[k, 0], ag[k, 0] = first["observation"], first["achieved_goal"]
        if not r.deterministic:
            noise[k] = w.rng.standard_normal((T, 4), dtype=np.float32)
    filming = [(w.env, r.frames) for w, r in zip(workers, requests, strict=True) if r.frames is not None]
    for t in range(T):
        actions[:, t] = agent.act(o[:, t], ag[:, t], goals, noise[:, t])
        speed.step_envs([w.env for w in workers], actions[:, t], o[:, t + 1], ag[:, t + 1], a.num_envs)
        for film_env, frames in filming:  # in this thread: a GL context belongs to the thread that made it
            frames.append(film_env.render())
    success = fetch5_env.goal_reached(ag[:, -1], goals)
    stable = (ag[:, T - a.stable_steps :] == ag[:, -1:]).all((1, 2))
    return [Segment(o[k], ag[k], goals[k], actions[k], bool(success[k]), bool(stable[k])) for k in range(K)]


# ------------------------------------------------------------------------------------------------
# Goal samplers: the hooks the rest of the file calls, and the autotelic cycle they share (SPEC §6)
# ------------------------------------------------------------------------------------------------
class Sampler:
    """A goal sampler decides what every cycle does. The rest of the file and plumbing.py reach it through these
    hooks alone, its contract with the run (this base gives each a default; a sampler overrides what it changes):
      GoalSampler(args, learner, workers): built once per run (Run), after the Learner.
      cycle(w): worker w's cycle program; yields Requests and spends exactly w.left (every worker runs n_segments
        segments a cycle: run_cycle checks it). Each w.env.reset() starts a goal: add 1 to goals.
      goal_outcome(w, goal, reached): an autotelic goal's outcome (an attempt the budget cut off has none).
      after_cycle(): after every worker's cycle: merge what workers share, in worker order (SPEC §11).
      after_update(batch, target): after each SAC update; returns a dict of 0-d tensors to log (a cycle's mean). A
        sampler with its own runs without --overlap (the updates' process has no sampler: speed.overlap_of).
        batch (SAC.to_tensors): the update's tensors on its device, B = batch_size x num_envs rows (this
        process's workers, in order): obs, obs_next (B, 10 + 15n), normalized; ag, ag_next and g
        (B, og.config_dim(n)), +-1, g relabelled by HER; action (B, 4); reward (B,), 1 where ag_next reaches g
        (fetch5_env.goal_reached), else 0; noise_next, noise_pi (B, 4), the policy samples' normal draws.
        target (B,): the critic's TD targets, without grad.
      epoch_stats(): its progress.csv columns this epoch, the same keys every epoch. stats are this process's:
        a count goes through plumbing.summed, which sums it over processes (right under torchrun). Only such
        per-process counts: a number every process already holds whole (merged in after_cycle) would be
        multiplied by the number of processes.
      state_dict(), load_state_dict(s): its checkpoint entries, top-level keys of the checkpoint, which
        load_state_dict gets whole; never one of plumbing.save_state's own: script, env_version, versions, args,
        counters, epoch_so_far, rows, actor, critic, critic_target, actor_opt, critic_opt, normalizer, graph,
        encountered, rng, env_rng, batch_rng, buffer (nor format). Values that torch.load(weights_only=True)
        accepts: tensors, Python numbers, str, bool, None, and lists, tuples and dicts of them (no numpy).
        state_dict is called at cycle boundaries only: after after_cycle (the epoch's checkpoint, a stop's),
        or, where gives_up_cycles, also before each cycle; load_state_dict on --resume, after the Learner's
        own state: its graph comes back with its nodes in their saved order, so a draw over nodes by index
        (as autotelic_goal's) is the uninterrupted run's.
      open(folder, stopping), close(): a training run's folder, for files of its own, and whether Ctrl-C or
        SIGTERM asked the run to stop (a sampler that waits stops waiting); then the run's end.
      gives_up_cycles: whether its cycle may raise plumbing.CycleGivenUp (False here), before the cycle's segments
        are learnt from, when a stop request ends a wait (`stopping`): the run then gives the cycle up, its
        checkpoint the state saved before the cycle (one process only), and --resume runs it again.
      stats: this epoch's counts (a Counter of numbers; checkpointed, cleared each epoch); goals: this process's
        goals so far, one per reset (checkpointed; progress.csv's goals sums them over processes).
      check_sampler_args(args), a function beside the class: the first bad value of its options, or None.
      Args.RESUMABLE (optional, as NEEDS and SAME; in the sampler's group of Args, kept or remade by a fork that
        replaces the group): the sampler's options --resume may change (it refuses any other), as where a page is.
      Args.NEEDS: flag -> (the flag it needs, why): a flag that would do nothing, given alone, is refused.
      Args.SAME: flag -> {value: the value it means}: values --resume takes for each other ('' for 'nodes').
    Every random draw of a cycle comes from its worker's own stream, w.rng (never np.random, random, torch's
    global generator or a generator of the sampler's own): exact --resume and the same run under any split of
    the workers into processes (--num-envs, torchrun) depend on it (SPEC §11).
    This base is the plain autotelic sampler of paper Algorithm 1: every cycle autotelic (autotelic_cycle),
    goals uniform over the agent's nodes (autotelic_goal), outcomes counted (goal_outcome)."""

    gives_up_cycles = False

    def __init__(self, args: Args, learner: Learner, workers: list[Worker]):
        self.args, self.learner, self.workers = args, learner, workers
        self.stats, self.goals = collections.Counter(), 0
        self.classes = og.evaluation_classes(args.n_blocks)  # goals counted by class (progress.csv: own_S2, ...)
        self.class_of = {int(m): name for name, configs in self.classes.items() for m in og.to_mask(configs)}
        self.own_counts = [f"own_{kind}{name}" for kind in ("", "reached_") for name in self.classes]

    def cycle(self, w: Worker):
        self.stats["cycles"] += 1
        yield from self.autotelic_cycle(w)

    def autotelic_cycle(self, w: Worker):
        """Program, Algorithm 1's autotelic branch (SPEC §6): reset, a goal (autotelic_goal) pursued along
        a sampled path; until the cycle's segments are spent."""
        while w.left > 0:
            w.env.reset()
            self.goals += 1
            goal = self.autotelic_goal(w)
            reached = yield from pursue(self.learner, w, goal, explore=True, deterministic=False)
            if reached is not None:  # None: the cycle's budget cut the attempt off, which is no outcome
                self.goal_outcome(w, goal, reached)

    def autotelic_goal(self, w: Worker) -> int:
        """G_s.sample_node(): uniform over the agent's nodes; before any exists, a uniform random +-1 vector."""
        node = self.learner.graph.sample_node(w.rng)
        if node is None:
            return int(og.to_mask(w.rng.choice([-1.0, 1.0], size=og.config_dim(self.args.n_blocks))))
        return node

    def goal_outcome(self, w: Worker, goal: int, reached: bool):
        self.stats["autotelic_goals"] += 1
        self.stats["autotelic_reached"] += reached
        if (name := self.class_of.get(goal)) is not None:
            self.stats[f"own_{name}"] += 1
            self.stats[f"own_reached_{name}"] += reached

    def after_cycle(self):
        pass

    def after_update(self, batch: dict, target: torch.Tensor) -> dict:
        return {}

    def epoch_stats(self) -> dict:
        counts = summed(self.stats, ["autotelic_goals", "autotelic_reached", *self.own_counts])
        reached = counts["autotelic_reached"] / max(1, counts["autotelic_goals"])
        return dict(autotelic_goals_reached=reached, **{k: counts[k] for k in self.own_counts})

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, s: dict):
        pass

    def open(self, folder: Path, stopping: collections.abc.Callable[[], bool]):
        pass

    def close(self):
        pass


# ------------------------------------------------------------------------------------------------
# The goal sampler: HME, the social partner and internalization (SPEC §7; paper Sections 3.1, 3.4)
# ------------------------------------------------------------------------------------------------
class GoalSampler(Sampler):
    """HME (SPEC §7): each cycle is social with probability sp_ratio (the paper's Algorithm 2), or when the
    learner has asked for help (learner_query.Query, off by default); otherwise it rehearses a failed social
    proposal with probability internalization_prob, if there is one (Algorithm 1's first branch), else it
    is autotelic (its second, Sampler.autotelic_cycle)."""

    def __init__(self, args: Args, learner: Learner, workers: list[Worker]):
        super().__init__(args, learner, workers)
        self.sp = SocialPartner(args.n_blocks)
        self.person = None  # beyond the paper: a person chooses instead (person_partner.py, its page)
        if args.partner != "oracle" and not args.eval_only:
            import person_partner  # noqa: PLC0415

            self.sp = self.person = person_partner.PersonPartner.of(self)
            self.gives_up_cycles = True  # a stop while a question waits (see Sampler)
        self.query = None  # beyond the paper (SPEC §7.1): learner_query.py, imported only when its flags are set
        if args.ask_after or args.learner_picks:
            import learner_query  # noqa: PLC0415

            self.query = learner_query.Query(args, learner) if args.ask_after else None
            if args.learner_picks:  # the learner picks among the partner's candidates
                self.sp = learner_query.LearnerPicks(self.sp, args, learner, split_obs)
        self.internalization_buffer: list[tuple[int, int]] = []  # distinct failed (frontier, beyond) pairs
        names = [*self.classes, "other"]  # the classes proposals are counted in
        kinds = ("frontier", "beyond", "frontier_arrived", "beyond_reached")  # goals proposed; goals reached (count)
        self.partner_counts = [f"sp_{kind}_{k}" for kind in kinds for k in names]
        for w in workers:
            w.new_pairs = []  # pairs it failed this cycle, not yet merged with the other workers'

    def cycle(self, w: Worker):
        self.stats["cycles"] += 1
        helped = self.query is not None and self.query.asks()  # the same for every worker: read from what they share
        coin = self.args.sp_ratio > 0 and w.rng.random() < self.args.sp_ratio  # --sp-ratio
        if helped or coin:
            self.stats["social_cycles"] += 1
            self.stats["help_cycles"] += helped
            self.stats["queries"] += helped and self.query.state["helped"] == 1 and w.index == 0  # by worker 0
            proposed = yield from self.social_cycle(w)
            self.stats["help_nothing"] += helped and not proposed
        elif self.internalization_buffer and w.rng.random() < self.args.internalization_prob:  # --internalization-prob
            self.stats["rehearsal_cycles"] += 1
            yield from self.rehearsal_cycle(w)
        else:
            yield from self.autotelic_cycle(w)

    # --- the cycles: Algorithm 2 (social), then Algorithm 1's rehearsal ---------------------------
    def social_cycle(self, w: Worker):
        """Program, Algorithm 2: reset; the social partner proposes a frontier goal and the agent goes
        there; then goals just beyond, chained while they succeed; a failed one is internalized. When the
        partner has nothing to propose, the rest of the cycle is autotelic. The ablations (--strategy)
        keep only the frontier leg or only a beyond goal. Returns whether the partner proposed anything."""
        strategy, graph, n_segments = self.args.strategy, self.learner.graph, w.left
        while w.left > 0:
            w.env.reset()
            self.goals += 1
            here, before = current_config(w.env), w.left
            only_frontier = strategy == "frontier"  # its goal is the journey: one the agent must move to
            frontier = self.sp.frontier_goal(graph, here, w, elsewhere=only_frontier)
            base = here if frontier is None else frontier  # no reachable frontier: beyond the current config
            if strategy == "frontier-and-beyond":  # the paper's
                arrived = True
                if frontier is not None:
                    arrived = yield from self.proposed_frontier(w, frontier)
                if arrived:
                    yield from self.beyond_goals(w, base)
            elif strategy == "frontier":  # --strategy frontier: go there deterministically, then reset
                if frontier is not None:
                    yield from self.proposed_frontier(w, frontier)
            else:  # --strategy beyond: the frontier stays hidden; one goal beyond it, retried until reached
                yield from self.attempt_until_reached(w, self.sp.beyond_goal(graph, base, w))
            if w.left == before:
                break  # nothing to propose: the rest of the cycle is autotelic
        proposed = w.left < n_segments
        yield from self.autotelic_cycle(w)
        return proposed

    def proposed_frontier(self, w: Worker, frontier: int):
        """Program step: the partner's frontier goal, proposed, then gone to (go_to_frontier; already there
        counts as arrived); each counted in its class. Returns whether the agent arrived."""
        self.count("frontier", frontier)
        arrived = yield from self.go_to_frontier(w, frontier)
        self.sp.outcome(w, frontier, arrived)
        if arrived:
            self.count("frontier_arrived", frontier)
        return arrived

    def go_to_frontier(self, w: Worker, frontier: int):
        """Program step: deterministic policy along the safest path (SPEC §7); already there counts as
        arrived. Returns whether it arrived."""
        if current_config(w.env) == frontier:
            return True
        return (yield from pursue(self.learner, w, frontier, explore=False, deterministic=True))

    def beyond_goals(self, w: Worker, start: int):
        """Program step: goals just beyond `start`, one stochastic segment each, chained while they
        succeed. On a failure the pair (the config the attempt started from, the beyond goal) is
        internalized: after chaining, that config is the frontier the failed step left from."""
        while w.left > 0:
            beyond = self.sp.beyond_goal(self.learner.graph, start, w)
            if beyond is None:
                break
            self.count("beyond", beyond)
            segment = yield Request(beyond, deterministic=False)
            self.sp.outcome(w, beyond, segment.success)
            if not segment.success:
                self.internalize(w, start, beyond)
                break
            self.count("beyond_reached", beyond)
            start = beyond

    def attempt_until_reached(self, w: Worker, beyond: int | None):
        """Program step, --strategy beyond (SPEC §7): one beyond goal attempted from where the agent is,
        segment after segment without reset until reached or the budget is spent. Nothing is stored."""
        if beyond is None:
            return
        self.count("beyond", beyond)
        reached = None  # a budget already spent: no attempt
        while w.left > 0:
            segment = yield Request(beyond, deterministic=False)
            reached = segment.success
            if segment.success:
                self.count("beyond_reached", beyond)
                break
        self.sp.outcome(w, beyond, reached)

    def internalize(self, w: Worker, frontier: int, beyond: int):
        """B_i.store(g, g_b): a failed pair is stored once, however often it fails (SPEC §7)."""
        if (pair := (frontier, beyond)) not in self.internalization_buffer and pair not in w.new_pairs:
            w.new_pairs.append(pair)

    def rehearsal_cycle(self, w: Worker):
        """Program, Algorithm 1's rehearsal: reset, draw a stored (frontier, beyond) pair, go to the
        frontier deterministically, then attempt the beyond goal once, without reset, "exactly as if the
        social partner was there" (paper Section 3.4); until the cycle's segments are spent."""
        while w.left > 0:
            w.env.reset()
            self.goals += 1
            frontier, beyond = self.internalization_buffer[w.rng.integers(len(self.internalization_buffer))]
            arrived = yield from self.go_to_frontier(w, frontier)
            if arrived and w.left > 0:
                yield Request(beyond, deterministic=False)

    # --- bookkeeping: logs, what workers share, checkpoints ---------------------------------------
    def count(self, kind: str, goal: int):
        """One of the partner's goals in its class: proposed ('frontier', 'beyond'), or the agent reached
        it ('frontier_arrived': at the stepping stone; 'beyond_reached': the beyond goal's segment succeeded)."""
        self.stats[f"sp_{kind}_{self.class_of.get(goal, 'other')}"] += 1

    def after_cycle(self):
        """Workers merge the pairs they stored this cycle, in worker order: every worker rehearses all
        of them (SPEC §11). A person's page is shown the run's state."""
        mine = np.array([p for w in self.workers for p in w.new_pairs], dtype=np.int64).reshape(-1, 2)
        merged = list(map(tuple, all_gather_rows(mine).tolist()))
        self.internalization_buffer = merge_pairs(self.internalization_buffer, merged)
        for w in self.workers:
            w.new_pairs = []
        if self.person:
            self.person.publish(self.learner.graph)

    def epoch_stats(self) -> dict:
        """Besides autotelic success: the share of social and rehearsal cycles, the learner's queries (the
        social cycles they brought, those in which the partner had nothing to propose, and the cycles
        without a new node at the epoch's end), stepping stones left, the number of distinct internalized
        pairs, the partner's proposals per class (frontier and beyond) and those the agent reached."""
        queries = ["queries", "help_cycles", "help_nothing"]
        person = self.person.COUNTS if self.person else ()  # --partner person: who chose (person_partner.py)
        counts = summed(self.stats, ["cycles", "social_cycles", "rehearsal_cycles", *queries, *person,
                                     *self.partner_counts])  # fmt: skip
        cycles = max(1, counts["cycles"])
        return super().epoch_stats() | dict(
            social_share=counts["social_cycles"] / cycles,
            rehearsal_share=counts["rehearsal_cycles"] / cycles,
            **{k: counts[k] for k in queries},  # the learner's query (learner_query.Query): counts this epoch
            stalled_cycles=self.query.state["stalled"] if self.query else 0,  # its signal at the epoch's end
            **{k: counts[k] for k in person},
            stepping_stones=len(self.sp.stepping_stones(self.learner.graph)),
            internalized_pairs=len(self.internalization_buffer),
            **{k: counts[k] for k in self.partner_counts},
        )

    def open(self, folder: Path, stopping: collections.abc.Callable[[], bool]):
        if self.person:
            self.person.open(folder, stopping)  # the page is served from now on; picks.csv in the folder

    def close(self):
        if self.person:
            self.person.close()

    def state_dict(self) -> dict:
        pairs = torch.tensor(self.internalization_buffer, dtype=torch.int64).reshape(-1, 2)
        return (dict(internalization=pairs) | (dict(query=self.query.state_dict()) if self.query else {})
                | (dict(person=self.person.state_dict()) if self.person else {}))  # fmt: skip

    def load_state_dict(self, s: dict):
        self.internalization_buffer = merge_pairs([], [tuple(p) for p in s["internalization"].tolist()])
        if self.query is not None and "query" in s:  # one written before the learner could ask has none
            self.query.load_state_dict(s["query"])
        if self.person is not None and "person" in s:  # one written before questions were checkpointed has none
            self.person.load_state_dict(s["person"])


STRATEGIES = ("frontier-and-beyond", "frontier", "beyond")


def check_sampler_args(a: Args) -> str | None:
    """The goal sampler's options (HME, SPEC §7): the first bad value, described, or None."""
    if a.strategy not in STRATEGIES:
        return f"--strategy must be one of {', '.join(STRATEGIES)}, got {a.strategy!r}"
    for name in ("sp_ratio", "internalization_prob"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            return f"--{name.replace('_', '-')} must be in [0, 1], got {getattr(a, name)}"
    if a.ask_after < 0:
        return f"--ask-after must be 0 (never ask) or more, got {a.ask_after}"
    if a.help_cycles < 1:
        return f"--help-cycles must be 1 or more, got {a.help_cycles}"
    if a.learner_picks or a.ask_progress != Args.ask_progress:  # beyond the paper: that file's own options
        import learner_query  # noqa: PLC0415

        if (problem := learner_query.check_args(a)) is not None:
            return problem
    if any(getattr(a, k) != getattr(Args, k) for k in ("partner", "person_timeout", "person_host", "person_port")):
        import person_partner  # noqa: PLC0415 (beyond the paper: a person as the partner, that file's options)

        return person_partner.check_args(a)
    return None


# --- the social partner (SPEC §7; paper Section 3.1) ----------------------------------------------
class SocialPartner:
    """Knows every config and which ones are semantically adjacent (the oracle graph, SPEC §4), and
    sees the agent's semantic graph. It proposes a frontier goal (a known config from which the agent
    has not yet tried some adjacent config) and then a goal just beyond it."""

    def __init__(self, n_blocks: int):
        self.oracle = og.OracleGraph(n_blocks)
        heads = np.repeat(np.arange(self.oracle.n_nodes), np.diff(self.oracle.indptr))
        self.edge_heads = self.oracle.masks[heads]  # every oracle edge, as (head, tail) masks
        self.edge_tails = self.oracle.masks[self.oracle.indices]
        self.dim = og.config_dim(n_blocks)

    def _untried(self, graph: SemanticGraph) -> np.ndarray:
        """Oracle edges whose head is an agent node but that the agent graph lacks."""
        keys = (self.edge_heads << self.dim) | self.edge_tails
        known = np.isin(self.edge_heads, np.asarray(graph.masks, dtype=np.int64))
        return known & ~np.isin(keys, graph.edge_keys())

    def stepping_stones(self, graph: SemanticGraph) -> np.ndarray:
        """Agent nodes that are oracle nodes with an oracle neighbour the agent has no edge to."""
        return np.unique(self.edge_heads[self._untried(graph)])

    def frontier_goal(self, graph: SemanticGraph, current: int, w: Worker, elsewhere: bool = False) -> int | None:
        """Uniform among the stepping stones reachable in the agent graph from `current` (included,
        unless `elsewhere`: a goal the agent must move to)."""
        return self.choose(w, self.frontier_candidates(graph, current, elsewhere))

    def frontier_candidates(self, graph: SemanticGraph, current: int, elsewhere: bool = False) -> np.ndarray:
        stones = np.intersect1d(self.stepping_stones(graph), graph.reachable(current))
        return stones[stones != current] if elsewhere else stones

    def beyond_goal(self, graph: SemanticGraph, config: int, w: Worker) -> int | None:
        """Uniform among the oracle neighbours c' of `config` with no agent edge config -> c'."""
        return self.choose(w, self.beyond_candidates(graph, config))

    def beyond_candidates(self, graph: SemanticGraph, config: int) -> np.ndarray:
        i = int(self.oracle.index(og.from_mask(config, self.oracle.n_blocks)))
        if i < 0:  # not a config of the oracle: no neighbour
            return np.zeros(0, dtype=np.int64)
        tails = self.oracle.masks[self.oracle.neighbour_indices(i)]
        keys = (np.int64(config) << self.dim) | tails
        return tails[~np.isin(keys, graph.edge_keys())]

    def choose(self, w: Worker, candidates: np.ndarray) -> int | None:
        """The simulated partner's choice: uniform, from the worker's stream (None: nothing to propose).
        A person at a browser chooses instead with --partner person (person_partner.py)."""
        return int(candidates[w.rng.integers(len(candidates))]) if len(candidates) else None

    def outcome(self, w: Worker, goal: int, reached: bool | None):
        """What came of a proposed goal (None: the cycle's budget cut the attempt off). The simulated
        partner needs nothing of it; a person's page shows it."""


def merge_pairs(kept: list[tuple[int, int]], new: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The internalization buffer is a set of distinct (frontier, beyond) pairs (SPEC §7), kept as a
    list in first-stored order so that a seeded draw picks the same pair on every worker: the kept
    pairs, then those of `new` (every worker's, in global worker order) not already in."""
    return list(dict.fromkeys([*kept, *new]))


# ------------------------------------------------------------------------------------------------
# Learning: replay, normalizer, semantic graph, SAC updates (Algorithm 1: B, G_s and PE updates; Π.update)
# ------------------------------------------------------------------------------------------------
class Learner:
    """What learns from the workers' segments: the agent (SAC and its normalizer), each worker's replay,
    the semantic graph with its success rates (the paper's G_s and PE), and the configs met."""

    def __init__(self, args: Args, device):
        self.args, obs_dim, goal_dim = args, BODY + PER_BLOCK * args.n_blocks, og.config_dim(args.n_blocks)
        self.agent = SAC(args, obs_dim, device)
        self.graph = SemanticGraph(args.n_blocks, args)
        seg_capacity = max(1, args.buffer_size // args.segment_len)
        self.buffer = ReplayBuffer(args.num_envs, seg_capacity, args.segment_len, obs_dim, goal_dim)
        self.encountered: set[int] = set()  # every config met at any step of a training segment
        self.segments = 0  # every worker's, so far
        self.plan_seconds, self.waiting = 0.0, None  # planning + graph updates this epoch (speed report); see train

    def learn_from(self, per_worker: list[list[Segment]]):
        """Store each worker's segments (per_worker[i]: worker i's, as many for each) in its replay, update
        the normalizer and the semantic graph. The normalizer and the graph learn from every worker's
        segments, in global worker order, so that they are the same in every process and whatever the
        split of workers into processes (SPEC §11)."""
        stack = lambda field: np.array([[getattr(s, field) for s in ws] for ws in per_worker])  # noqa: E731
        ag, obs = stack("ag"), stack("obs")  # (workers, segments, T + 1, .)
        self.buffer.store(obs, ag, stack("g"), stack("actions"))
        if not self.args.freeze_normalizer:  # --freeze-normalizer
            self.agent.normalizer.update(obs)
        segments = [s for ws in per_worker for s in ws]
        t = time.perf_counter()
        outcomes = all_gather_rows([(s.start, s.final, og.to_mask(s.g), s.success, s.stable) for s in segments])
        for start, final, target, success, stable in outcomes.tolist():
            if stable:
                self.graph.update(start, final, target, bool(success))
        self.encountered.update(all_gather_rows(np.unique(og.to_mask(ag))).tolist())
        self.plan_seconds += time.perf_counter() - t
        self.segments += len(outcomes)

    def train(self, rngs: list[np.random.Generator], after_update=lambda batch, target: {}) -> dict:
        """The cycle's SAC updates, each on a batch from every worker's replay (drawn with `rngs`, the
        workers' streams); after each, the goal sampler's hook. The mean of each logged value, read once a cycle."""
        args, infos, her_prob = self.args, [], 1 - 1 / (1 + self.args.her_k)
        # --init-learning-starts (SPEC §10): no update until every worker's replay, in every process, holds that many
        # segments (all processes update together or none; a resumed job's emptied replays fill again first)
        n = args.init_learning_starts if args.init_from else 0
        held = int(gather_workers(np.full((args.num_envs, 1), self.buffer.size)).min()) if n else 0
        self.waiting = (held, n) if held < n else None  # (segments the smallest replay holds, n) while no update runs
        for _ in range(args.n_updates if self.buffer.size and not self.waiting else 0):
            info = self.agent.update(self.buffer.sample(args.batch_size, rngs, her_prob, args.her_strategy))
            infos.append(info | after_update(self.agent.last_batch, self.agent.last_target))
        return plumbing.update_means(infos)  # one wait for the GPU a cycle, not one an update


# ------------------------------------------------------------------------------------------------
# Evaluation (SPEC §9)
# ------------------------------------------------------------------------------------------------
def evaluate(run: Run, video: dict | None = None, graph: SemanticGraph | None = None) -> dict[str, float]:
    """SR per class: every worker runs its share of the goals (see evaluation), all in lockstep.
    `video`, if given, receives the frames of each class's first video_episodes (worker 0's);
    `graph`, if given, plans instead of the agent's (the oracle's, for --plan-on oracle)."""
    wins = np.zeros((len(run.workers), len(run.classes)))
    for w in run.workers:
        w.left, w.segments = math.inf, []
    graph = graph or run.learner.graph
    drive(run.learner.agent, {w: evaluation(run, w, graph, wins[i], video) for i, w in enumerate(run.workers)})
    for w in run.workers:
        w.segments = []  # test segments are neither stored nor used to update the graph
    rates = all_sum(wins.sum(0)) / max(1, run.args.eval_goals_per_class)
    sr = dict(zip(run.classes, rates.tolist(), strict=True))
    sr["global"] = float(np.mean(rates))
    return sr


def evaluation(run: Run, w: Worker, graph: SemanticGraph, wins: np.ndarray, video: dict | None):
    """Program: per class, goals drawn uniformly, goal i of the class to worker i mod workers (SPEC §9);
    reset, plan the safest path, follow it deterministically with at most max_eval_subgoals segments;
    success = the last segment ends on the goal. Adds the successes per class to `wins`."""
    args = run.args
    for k, (name, members) in enumerate(run.classes.items()):
        share = len(range(w.index, args.eval_goals_per_class, run.n_workers))
        for i, goal in enumerate(members[w.rng.integers(len(members), size=share)]):
            w.env.reset()
            filmed = video is not None and w.index == 0 and i < args.video_episodes
            path = sample_path(graph, current_config(w.env), int(og.to_mask(goal)), w.rng, explore=False)
            path = [path[0]] + path[1:][-args.max_eval_subgoals :]
            wins[k] += yield from follow_path(w, path, True, video.setdefault(name, []) if filmed else None)


def oracle_planner(args: Args) -> SemanticGraph:
    """The oracle graph (SPEC §4) as a semantic graph whose edges all share one SR, the prior: its safest
    paths are then its shortest ones, drawn uniformly. For evaluation only (--plan-on oracle): it tells
    the policy's skill apart from the agent graph's, and plans for an agent that has no graph (the paper's)."""
    oracle = og.OracleGraph(args.n_blocks)
    heads = np.repeat(np.arange(oracle.n_nodes), np.diff(oracle.indptr))
    graph = SemanticGraph(args.n_blocks, args)
    graph.load_state_dict(dict(
        masks=torch.from_numpy(oracle.masks),
        edges=torch.from_numpy(np.column_stack([heads, oracle.indices, np.zeros_like(heads)])),  # SR class 0
        class_keys=torch.zeros((0, 2), dtype=torch.int64),
        sr=torch.tensor([args.sr_prior], dtype=torch.float64),
    ))  # fmt: skip
    return graph


# ------------------------------------------------------------------------------------------------
# The main loop: epochs of cycles, each cycle collect -> learn -> update (SPEC §5)
# ------------------------------------------------------------------------------------------------
class Run:
    """A run: its workers, what learns, the goal sampler, and where it stands (all a checkpoint saves)."""

    def __init__(self, args: Args, device):
        self.args, self.n_workers = args, world() * args.num_envs  # every process's workers
        self.workers = [Worker(args, rank() * args.num_envs + i) for i in range(args.num_envs)]
        self.learner = Learner(args, device)
        self.sampler = GoalSampler(args, self.learner, self.workers)
        self.classes = og.evaluation_classes(args.n_blocks)  # SPEC §9's: name -> configs (the sampler's too)
        self.epoch, self.cycle = 0, 0
        self.tally = plumbing.new_tally(0)  # this epoch's segment outcomes, losses and timings, for its row
        self.rows: list[dict] = []  # every epoch's progress.csv row (checkpointed: logs are rebuilt on resume)


def run_cycle(run: Run) -> list[list[Segment]]:
    """One cycle of every worker (its goal sampler's program), in lockstep. Each worker's segments."""
    for w in run.workers:
        w.left, w.segments = run.args.n_segments, []
    drive(run.learner.agent, {w: run.sampler.cycle(w) for w in run.workers}, f"{type(run.sampler).__name__}.cycle")
    plumbing.check_budgets(run)  # each worker spent exactly its segments (a forked sampler may not)
    return [w.segments for w in run.workers]


def one_cycle(run: Run):
    """Collect a cycle's segments, merge what the workers share (SPEC §11), learn from them (replay, normalizer,
    semantic graph), then the cycle's SAC updates (SPEC §5), with --overlap beside the collection (speed.py)."""
    tally, t = run.tally, time.perf_counter()
    per_worker = run_cycle(run)
    run.sampler.after_cycle()
    run.learner.learn_from(per_worker)
    tally["wins"] += sum(s.success for ws in per_worker for s in ws)
    tally["tries"] += sum(len(ws) for ws in per_worker)
    tally["collect"] += (t_update := time.perf_counter()) - t
    tally["losses"].update(run.learner.train([w.rng for w in run.workers], run.sampler.after_update))
    tally["update"] += time.perf_counter() - t_update
    run.cycle += 1


def train_loop(run: Run, out: plumbing.RunFolder) -> int:
    """Epochs of cycles; each epoch ends with an evaluation, a checkpoint, then its progress.csv row (in that
    order: a row is never logged unless a checkpoint holds it). Ctrl-C or SIGTERM stops it at a cycle boundary
    (or during a one-process evaluation) with a checkpoint that --resume continues exactly (plumbing.Stopper)."""
    while run.epoch < run.args.n_epochs:
        while run.cycle < run.args.n_cycles:
            if not out.cycle(run, one_cycle):  # a stop while a person's question waits: the cycle given up
                return out.stop(run)
            plumbing.cycle_progress(run, f"nodes {run.learner.graph.n_nodes:,}")  # then the critic loss, or no update
            if out.stop_requested():
                return out.stop(run)
        sr = out.evaluate(run, evaluate)  # SR per class (SPEC §9); None: a stop request interrupted it
        if sr is None:
            return out.stop(run)
        out.end_epoch(run, sr)  # its row (plumbing.finish_epoch), checkpointed, then logged
        if out.stop_requested():
            return out.stop(run)
    return 0


# ------------------------------------------------------------------------------------------------
# main: parse, build the run, train or evaluate it (the rest is plumbing.py's)
# ------------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    args, state, init = plumbing.parse_command_line(Args, check_sampler_args, argv)  # bad input: one line, exit 2
    if args is None:  # --resume of a run that has trained all its epochs (said so)
        return 0
    with plumbing.job(args) as device:  # torch's threads; under torchrun, this process's device, the job joined
        torch.manual_seed(args.seed + rank())  # the initial weights (every process takes process 0's: SAC)
        run = Run(args, device)
        if args.eval_only:  # the checkpoint's agent: SR per class (SPEC §9), printed and saved beside it
            planner = oracle_planner(args) if args.plan_on == "oracle" else None
            return plumbing.evaluate_checkpoint(run, state, evaluate, planner)
        with plumbing.RunFolder(run, state, init) as out:  # --resume's run restored, or a new one; logs, stops
            return train_loop(run, out)


if __name__ == "__main__":
    plumbing.run_main(main)
