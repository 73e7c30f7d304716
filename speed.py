# Docs: docs/speed.md (what each trick bought, measured on which CPU); SPEC §12 (implementation choices).
"""The training scripts' speed tricks, in one file beside them, as LeanRL keeps its fast SAC beside the plain one.

gangstr_hme.py, lp_baseline.py and vds_baseline.py hold the plain algorithm: their nets as written (MLP,
node_sum, edge_max) and torch's Adam. Unless --plain, a script's SAC calls fast_update, and its update then
computes the same losses faster (docs/speed.md has each trick's figure):
  - fast nets: within an update, the script's node_sum, edge_max and MLP.forward are this file's
    (fast_nets). On the CPU, kernels with their backward written out (NodeNet, fused_edge_max, Head); with
    --precision bf16, the large nets' products in bf16. A probe at start (fast_nets_compute) checks that they
    still compute the script's own losses and gradients: a fork that changed MLP or an aggregation gets the
    plain nets, said in one line. tests/test_update.py holds them to the plain nets.
  - Adam's fused step, in the script's own optimizers, every parameter group and setting kept (fuse_adams; a
    fork's optimizer that the fused step cannot stand in for is kept as built, said in one line); on the
    CPU, glibc told to keep the update's freed memory (keep_freed_memory).
Whatever --plain says, three that change no number: acting through views of the weights that do not
require grad (weight_view), a batch sent to a GPU in one pinned copy (to_device), and the envs stepped in
threads (step_envs, physics_first). --overlap's process, which changes the order of a cycle, not its math: a
cycle's SAC updates beside its collection (overlapped_cycle, Updates; SPEC §12). And what the command line and the
benchmarks ask of the machine: fast_bf16, cpu_line. It imports no training script (--overlap's process loads the
run's by its path) and knows a goal sampler by Sampler's hooks alone: scripts and plumbing.py -> this file ->
fetch5_env, oracle_graph.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import ctypes
import dataclasses
import functools
import importlib.util
import io
import json
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn
import torch.nn.functional as F
from torch.optim.adam import Adam  # torch's, whatever a fork binds torch.optim.Adam to
from torch.optim.adamw import AdamW

import fetch5_env
import oracle_graph as og


# ------------------------------------------------------------------------------------------------
# The update's fast path: what a training script's SAC turns on unless --plain
# ------------------------------------------------------------------------------------------------
def fast_update(agent):
    """The fast path of a training script's SAC `agent`: its losses (agent.compute_losses, eager or --compile's)
    computed within fast_nets, if the probe finds that they compute the script's own nets (agent.fast_nets
    says whether); Adam's fused step (fuse_adams), one pass per tensor (on the CPU, torch's default is a dozen small
    ops per tensor: 4x slower); on the CPU, glibc's kept memory."""
    script = sys.modules[type(agent).__module__]  # the training script whose SAC this is
    dtype = dict(fp32=torch.float32, bf16=torch.bfloat16)[precision_of(agent.args)[0]]  # the large products'
    kernels = agent.device.type == "cpu"
    agent.fast_nets = fast_nets_compute(agent, script, kernels)
    if agent.fast_nets:
        losses = agent.compute_losses

        def compute_losses(batch: dict):
            with fast_nets(script, dtype, kernels):
                return losses(batch)

        agent.compute_losses = compute_losses
    fuse_adams(agent)
    if kernels:
        keep_freed_memory()


def fuse_adams(agent):
    """Adam's fused step for the SAC `agent`'s two optimizers, turned on in place, as torch's own load of a
    checkpoint sets it: every parameter group keeps its weights and settings (rate, betas, eps, weight decay,
    amsgrad, AdamW's), the optimizer its defaults and moments, and whatever holds it (the warm-up of SAC.update,
    a fork's rate schedule) still steers it. One that the fused step cannot stand in for (fused_adam_refuses) is
    kept as the script built it, said in one line."""
    kept = []
    for name in ("actor", "critic"):
        opt = getattr(agent, f"{name}_opt")
        if why := fused_adam_refuses(opt):
            kept.append(f"the {name}'s optimizer {why}")
            continue
        for settings in (opt.defaults, *opt.param_groups):
            settings["fused"] = True
        if opt.state:  # moments already taken: torch's load moves each step count where the fused step keeps it
            opt.load_state_dict(opt.state_dict())
    if kept and not (dist.is_initialized() and dist.get_rank() > 0):
        print(f"fused Adam off: {'; '.join(kept)}: kept as the script built it", flush=True)


def fused_adam_refuses(opt: torch.optim.Optimizer) -> str:
    """Why Adam's fused step cannot stand in for `opt`'s, or '': a class other than torch's Adam and AdamW (a
    subclass may step otherwise), or a setting that the fused step refuses (differentiable, foreach) or that
    asks for the unfused one (fused=False)."""
    if type(opt) not in (Adam, AdamW):
        return f"is {type(opt).__name__}, not torch's Adam or AdamW"
    for key, value in (("differentiable", True), ("foreach", True), ("fused", False)):
        if any(group.get(key) is value for group in opt.param_groups):
            return f"sets {key}={value}"
    return ""


FAST = dict(dtype=None, kernels=False, own=None)  # within fast_nets: its arguments, and the script's own nets


@contextlib.contextmanager
def fast_nets(script, dtype: torch.dtype, kernels: bool = True):
    """Within it, the nets of `script` (a training script's module) compute as in a fast SAC update: its
    node_sum, edge_max and MLP.forward are this file's, the same math. On the CPU, if `kernels`, the kernels
    below (not while torch.compile traces: --compile fuses the plain ops itself); elsewhere the large nets'
    products in `dtype` (--precision; sums, heads, losses and targets stay fp32). The script looks these names
    up at call time: outside this block (acting, evaluation, a goal sampler's own use), its own nets run."""
    own, before = (script.node_sum, script.edge_max, script.MLP.forward), dict(FAST)
    FAST.update(dtype=dtype, kernels=kernels, own=own)
    script.node_sum, script.edge_max, script.MLP.forward = fast_node_sum, fast_edge_max, fast_forward
    try:
        yield
    finally:
        script.node_sum, script.edge_max, script.MLP.forward = own
        FAST.update(before)


def kernels_here(x: torch.Tensor) -> bool:
    """Whether the CPU kernels compute the net that x goes through: within fast_nets with kernels, on the CPU."""
    return FAST["kernels"] and x.is_cpu and not torch.compiler.is_compiling()


def fast_node_sum(net, glob: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """The script's node_sum (a node net summed over nodes): on the CPU by NodeNet, else the script's own."""
    if kernels_here(local):
        return NodeNet.apply(glob, local, *net.params(), FAST["dtype"])
    return FAST["own"][0](net, glob, local)


def fast_edge_max(net, edges: torch.Tensor, n: int) -> torch.Tensor:
    """The script's edge_max (a net on every edge, max over each node's): on the CPU by fused_edge_max, else the
    script's own."""
    if kernels_here(edges):
        return fused_edge_max(edges, *net.params(), n, FAST["dtype"])
    return FAST["own"][1](net, edges, n)


def fast_forward(net, x: torch.Tensor) -> torch.Tensor:
    """The script's MLP.forward: a head (no output ReLU) by Head on the CPU; a large net (run on every edge or
    node) Linear -> ReLU -> Linear (-> ReLU) with its products in the update's dtype (in fp32, the same ops as
    the script's); any other net, the script's own."""
    if kernels_here(x) and not net.out_relu:
        return Head.apply(x, *net.params())
    if not net.large:
        return FAST["own"][2](net, x)
    x, w1, b1, w2, b2 = (t.to(FAST["dtype"]) for t in (x, *net.params()))
    x = F.linear(F.relu(F.linear(x, w1, b1)), w2, b2)
    return F.relu(x) if net.out_relu else x


def fast_nets_compute(agent, script, kernels: bool) -> bool:
    """Whether fast_nets compute `script`'s SAC losses (agent.losses) as its own nets do, on small batches of
    random inputs on the agent's device: the losses, TD targets and the gradients of the networks' weights,
    within fast_nets in fp32 (with the kernels if `kernels`, which stand in for every net the products path
    runs, so that they answer for --compile's too; without them, a GPU's path) and outside it, equal up to
    float rounding. The fast nets implement the scripts' MLP as written (Linear -> ReLU
    -> Linear (-> ReLU), max over edges, sum over nodes); a fork that changes MLP or an aggregation changes its
    own nets alone. Then False, said in one line: the update runs the plain nets. Draws from its own generator
    (the run's random streams are untouched) and changes no weight or gradient."""
    gen = torch.Generator().manual_seed(0)
    rows, obs_dim, dim = 16, fetch5_env.obs_size(agent.args.n_blocks), og.config_dim(agent.args.n_blocks)
    params = [*agent.actor.parameters(), *agent.critic.parameters()]

    def random_batch() -> dict[str, torch.Tensor]:
        normal = lambda *shape: torch.randn(*shape, generator=gen)  # noqa: E731
        config = lambda: torch.randint(0, 2, (rows, dim), generator=gen).float() * 2 - 1  # noqa: E731
        batch = dict(obs=normal(rows, obs_dim), obs_next=normal(rows, obs_dim), ag=config(), ag_next=config(),
                     g=config(), action=normal(rows, 4).tanh(),
                     reward=torch.randint(0, 2, (rows,), generator=gen).float(), noise_next=normal(rows, 4),
                     noise_pi=normal(rows, 4))  # fmt: skip
        return {k: v.to(agent.device) for k, v in batch.items()}

    def values(within, batch: dict) -> tuple[torch.Tensor, torch.Tensor] | Exception:
        """The losses and TD targets; the gradients of the weights (an unused weight's: nan)."""
        try:
            with within:
                critic_loss, actor_loss, target, _ = agent.losses(batch)
            grads = torch.autograd.grad(critic_loss + actor_loss, params, allow_unused=True)
            grads = [target.new_full((1,), math.nan) if g is None else g.reshape(-1) for g in grads]
            losses = torch.stack([critic_loss.detach().reshape(()), actor_loss.detach().reshape(())])
            return torch.cat([losses, target]), torch.cat(grads)
        except Exception as e:  # noqa: BLE001 (a net the fast nets cannot run, of another shape: not theirs)
            return e

    def agree(batch: dict) -> tuple[bool, bool]:
        """Whether the two paths' values agree on `batch`, and whether their gradients do too."""
        plain, fast = values(contextlib.nullcontext(), batch), values(fast_nets(script, torch.float32, kernels), batch)
        if not (isinstance(plain, tuple) and isinstance(fast, tuple)):
            return False, False
        same = [f.shape == p.shape and torch.allclose(f, p, rtol=1e-4, atol=1e-4, equal_nan=True)
                for f, p in zip(fast, plain, strict=True)]  # fmt: skip
        return same[0], all(same)

    # A gradient is not continuous at a kink (a ReLU's 0, a max's tie, the min of the twin Qs), a value is: a
    # pre-activation within float rounding of one (-4e-8 in one path, +4e-8 in the other) sends a sample's
    # gradient one way in one path and the other way in the other, with the same values. Measured: the first
    # batch's gradients disagreed for 10 of 3,000 seeds at 3 blocks and 3 of 600 at 5, the second batch agreed
    # for each. A net computed otherwise disagrees on every batch; a kink, on one batch alone: where only the
    # first batch's gradients disagree, a second batch tells them apart. Values that disagree are no kink's.
    values_agree, same = agree(random_batch())
    same = same or (values_agree and all(agree(random_batch())))
    if not same and not (dist.is_initialized() and dist.get_rank() > 0):
        print("fast nets off: speed.py's no longer compute this script's nets (MLP, node_sum or edge_max changed); "
              "the SAC update runs the plain nets, in fp32", flush=True)  # fmt: skip
    return same


def keep_freed_memory():
    """Keep the update's freed tensors in this process's heap for the next update (docs/speed.md). By default
    glibc returns a freed block of a few MB to the system and faults its pages back in, zeroed, on the next
    allocation: about 1,500 page faults and a tenth of a CPU update's time."""
    libc = ctypes.CDLL(None) if os.name == "posix" else None
    if hasattr(libc, "mallopt"):  # glibc: blocks up to 32 MB from the heap, which keeps up to 1 GB free
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD


# ------------------------------------------------------------------------------------------------
# Whatever --plain says: acting's weight views, a batch's one copy to a GPU (neither changes a number)
# ------------------------------------------------------------------------------------------------
def weight_view(module: nn.Module) -> nn.Module:
    """A copy of `module` whose parameters are views of the original's that do not require grad: it
    follows every optimizer step and checkpoint load, and spares acting the dispatch cost that torch
    pays for each op on a tensor that requires grad (even under inference_mode). The actor loss reads the
    critic's weights through one as constants (SAC.losses)."""
    view = copy.copy(module)
    view._modules = {name: weight_view(child) for name, child in module._modules.items()}
    view.__dict__.update(view._modules)  # found without nn.Module.__getattr__, which is slow
    view._parameters = {}
    for name, p in module._parameters.items():
        setattr(view, name, None if p is None else p.detach())  # plain tensors: no Parameter subclass either
    return view


def to_device(arrays: dict[str, np.ndarray], device: torch.device) -> dict[str, torch.Tensor]:
    """float32 arrays (an update's batch) as tensors on `device` (a speed trick; docs/scaling.md).
    On CPU, the arrays themselves: no copy. On a GPU, one copy of them all from pinned memory, which the CPU
    need not wait for: it draws the next batch while the GPU works (it took ten blocking copies, the observations
    twice, before). Torch's cache of pinned memory reuses the block once its copy is done."""
    if device.type == "cpu":
        return {k: torch.from_numpy(v) for k, v in arrays.items()}
    sizes = [v.size for v in arrays.values()]
    assert all(v.dtype == np.float32 for v in arrays.values()), {k: v.dtype for k, v in arrays.items()}
    staging = torch.empty(sum(sizes), dtype=torch.float32, pin_memory=torch.cuda.is_available())
    np.concatenate([v.ravel() for v in arrays.values()], out=staging.numpy())
    parts = staging.to(device, non_blocking=True).split(sizes)
    return {k: t.view(v.shape) for (k, v), t in zip(arrays.items(), parts, strict=True)}


# ------------------------------------------------------------------------------------------------
# Stepping the workers' envs in threads (MuJoCo releases the GIL while it simulates): the same steps
# ------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def physics_first(n_envs: int):
    """Within it, torch runs one thread while this process's n_envs envs step in several: torch's idle threads
    would spin on the cores the envs step on, and acting batches are small (measured: physics 1.7x faster)."""
    threads = torch.get_num_threads()
    if physics_threads(n_envs) > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def step_envs(envs: list, actions: np.ndarray, obs_out: np.ndarray, ag_out: np.ndarray, n_envs: int = 1):
    """Every env one step, in up to physics_threads(n_envs) threads (n_envs: this process's, of which `envs`
    may be fewer); observations written to obs_out and ag_out (K, .)."""

    def step_some(ks):
        for k in ks:
            obs = envs[k].step(actions[k])[0]
            obs_out[k], ag_out[k] = obs["observation"], obs["achieved_goal"]

    threads = physics_threads(n_envs)
    n = min(len(envs), threads)
    if n == 1:
        step_some(range(len(envs)))
    else:
        list(physics_pool(threads).map(step_some, [range(i, len(envs), n) for i in range(n)]))


@functools.cache
def physics_threads(n_envs: int) -> int:
    """Threads that step n_envs envs: one per env, at most this process's share of the node's cores."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(n_envs, cores // int(os.environ.get("LOCAL_WORLD_SIZE", "1"))))


@functools.cache
def physics_pool(threads: int) -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="physics")


# ------------------------------------------------------------------------------------------------
# Both cores at work (--overlap): a cycle's SAC updates in a process of their own, beside its collection
# ------------------------------------------------------------------------------------------------
def overlap_of(run) -> tuple[bool, str]:
    """Whether a cycle's SAC updates run beside its collection (--overlap), and the run's first line's words: not
    under torchrun (its processes take the cores) or --cuda (the GPU is this process's), nor for a goal sampler
    with an after_update of its own (the updates' process has no sampler: VDS's heads learn from each update) or
    that may give a cycle up (a person partner). With it, torch runs one thread in each process unless --threads."""
    sampler, args, script = run.sampler, run.args, sys.modules[type(run).__module__]
    hooked = type(sampler).after_update is not script.Sampler.after_update
    why = ("torchrun: its processes take the cores" if int(os.environ.get("WORLD_SIZE", "1")) > 1
           else "--cuda: the GPU is this process's" if args.cuda
           else "its goal sampler learns from each update" if hooked
           else "a person's cycles may be given up" if sampler.gives_up_cycles else "")  # fmt: skip
    if not args.overlap or why:
        return False, "updates after collecting" + (f" (not --overlap: {why})" if args.overlap else "")
    if not args.threads:
        torch.set_num_threads(1)
    return True, "updates beside collecting, in a process of their own (--overlap)"


def overlapped_cycle(run, script):
    """script.one_cycle's steps, the SAC updates beside the collection (--overlap; SPEC §12). While this process's
    workers collect cycle c (script.run_cycle), acting with the agent as the cycle began, cycle c's updates run in
    the updates' process (Updates) on its copy of the learner: the replay and normalizer as cycle c - 1 left them,
    each worker's batches from its stream for them (Worker.batch_rng). Then the agent here takes the updated
    networks, optimizers and streams, and the cycle's segments are merged and learnt from, as in one_cycle; the
    next cycle's request brings them to the copy. Between cycles the agent here holds everything: a checkpoint
    is what it is without the overlap, --resume continues exactly, and a run is the same whatever the load."""
    learner, tally, t = run.learner, run.tally, time.perf_counter()
    if "updates" not in run.__dict__:
        run.updates = Updates(run, script)
    run.updates.request()
    try:
        per_worker = script.run_cycle(run)
    finally:  # on an error too: nothing goes on beside what comes next
        waited = time.perf_counter()
        losses, tally_update = run.updates.answer()
        waited = time.perf_counter() - waited
    run.sampler.after_cycle()
    learner.learn_from(per_worker)
    tally["wins"] += sum(s.success for ws in per_worker for s in ws)
    tally["tries"] += sum(len(ws) for ws in per_worker)
    tally["collect"] += time.perf_counter() - t - waited  # this process's work, not its wait for the updates
    tally["update"] += tally_update
    tally["losses"].update(losses)
    run.updates.learnt(per_worker)
    run.cycle += 1


def close_updates(run):
    """The updates' process of `run`, if any, told to end, and waited for (at the run's end, however it ends)."""
    if (updates := run.__dict__.pop("updates", None)) is not None:
        updates.close()


class Updates:
    """The SAC updates' own process (--overlap): the script's Learner, built from the run's Args in a fresh process
    (torch's threads are not forked), loaded with this process's state (networks, optimizers, update
    count, the workers' batch streams, normalizer, replay). Each cycle, request() sends it the last cycle's
    segments and the normalizer and starts its updates; answer() waits for them and loads what they changed into
    this process's agent. Messages are torch.save's bytes, read with weights_only. Ctrl-C and SIGTERM are this
    process's (it stops at a cycle boundary): the updates' process ignores them, and ends when this one closes
    the pipe or dies."""

    def __init__(self, run, script):
        # a fork of a server that imported torch and this file once (spawned: torch's threads are not forked), or a
        # spawned interpreter where there is none (Windows)
        forks = "forkserver" in multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("forkserver" if forks else "spawn")
        if forks:
            ctx.set_forkserver_preload([__name__])
        (self.conn, theirs), (alive, self.alive) = ctx.Pipe(), ctx.Pipe(duplex=False)
        self.process = ctx.Process(target=updates_process, name="updates", daemon=True, args=(
            theirs, alive, script.__file__, dataclasses.asdict(run.args), torch.get_num_threads()))  # fmt: skip
        self.process.start()
        theirs.close()
        alive.close()
        self.run, self.new, buffer = run, None, run.learner.buffer
        replay = {k: torch.from_numpy(getattr(buffer, k)[:, : buffer.size]) for k in REPLAY}
        self.send(learned(run.learner.agent, [w.batch_rng for w in run.workers]) | dict(replay=replay, ptr=buffer.ptr))

    def send(self, message: dict):
        try:
            self.conn.send_bytes(pack(message))
        except OSError:
            self.died()

    def request(self):
        """The cycle's updates begin there, once the copy has learnt the last cycle's segments."""
        self.send(dict(new=self.new, normalizer=normalizer_state(self.run.learner.agent.normalizer)))
        self.new = None

    def answer(self) -> tuple[dict, float]:
        """Waits for the cycle's updates (HUNG at most); the agent here takes what they changed. Their logged means,
        seconds."""
        try:
            if not self.conn.poll(HUNG):
                self.died(f"answered nothing for {HUNG:g} s (hung) and was stopped")
            got = unpack(self.conn.recv_bytes())
        except (EOFError, OSError):
            self.died()
        if "failed" in got:
            sys.exit(f"error: the SAC updates failed in their process ({got['failed']}: its traceback above); the "
                     "last checkpoint holds the run as it was")  # fmt: skip
        load_learned(self.run.learner.agent, [w.batch_rng for w in self.run.workers], got)
        self.run.learner.waiting = got["waiting"]
        return got["losses"], got["seconds"]

    def learnt(self, per_worker: list):
        """The cycle's segments, as the replay here stored them (each worker's newest), for the next request."""
        buffer, n = self.run.learner.buffer, len(per_worker[0])
        index = (buffer.ptr - n + np.arange(n)) % buffer.obs.shape[1]
        self.new = {k: torch.from_numpy(getattr(buffer, k)[:, index]) for k in REPLAY}

    def died(self, how: str = ""):
        self.process.join(0 if how else 5)  # a hung one is stopped as the run ends (close)
        run, how = self.run, how or f"ended (exit code {self.process.exitcode})"
        sys.exit(
            f"error: the SAC updates' process {how} in epoch {run.epoch}, cycle {run.cycle + 1} of "
            f"{run.args.n_cycles}; the last checkpoint holds the run as it was"
        )

    def close(self):
        self.conn.close()  # it reads the end of its messages, and ends
        self.alive.close()
        self.process.join(10)
        if self.process.is_alive():
            self.process.kill()


STATE = ("actor", "critic", "critic_target", "actor_opt", "critic_opt")  # what the updates change, with n_updates
REPLAY = ("obs", "ag", "g", "actions")  # ReplayBuffer's arrays, in store()'s order
HUNG = 600.0  # seconds without an answer that end a run: a cycle's updates take seconds (24 workers: 14 s)


def learned(agent, rngs: list) -> dict:
    """What a cycle's updates change: the agent's networks and optimizers, its update count, the batch streams."""
    return dict(**{k: getattr(agent, k).state_dict() for k in STATE}, n_updates=agent.n_updates,
                rngs=[json.dumps(rng.bit_generator.state) for rng in rngs])  # fmt: skip


def load_learned(agent, rngs: list, state: dict):
    for k in STATE:
        getattr(agent, k).load_state_dict(state[k])
    agent.n_updates = state["n_updates"]
    for rng, saved in zip(rngs, state["rngs"], strict=True):
        rng.bit_generator.state = json.loads(saved)


def normalizer_state(normalizer) -> dict:
    return dict(sum=torch.from_numpy(normalizer.sum), sumsq=torch.from_numpy(normalizer.sumsq), count=normalizer.count)


def pack(message: dict) -> bytes:
    data = io.BytesIO()
    torch.save(message, data)
    return data.getvalue()


def unpack(data: bytes) -> dict:
    return torch.load(io.BytesIO(data), weights_only=True)


def orphaned(alive):
    """Ends this process once the collecting one is gone (kill -9, a second Ctrl-C: its end of `alive` closes, and
    it never writes there), even within an update that never ends."""
    with contextlib.suppress(EOFError, OSError):
        alive.recv()
    os._exit(1)


def updates_process(conn, alive, path: str, args: dict, threads: int):
    """The updates' process: the training script at `path`, its Learner built from `args`; loaded, then one cycle's
    updates a request, until the other end closes the pipe. A failure is told in one line, its traceback shown."""
    for sig in (signal.SIGINT, signal.SIGTERM):  # the collecting process's: it stops the run at a cycle boundary
        signal.signal(sig, signal.SIG_IGN)
    threading.Thread(target=orphaned, args=(alive,), daemon=True).start()
    torch.set_num_threads(threads)
    spec = importlib.util.spec_from_file_location("overlapped_script", path)
    script = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    learner = script.Learner(script.Args(**args), torch.device("cpu"))
    agent, buffer, rngs = learner.agent, learner.buffer, [np.random.default_rng() for _ in range(learner.args.num_envs)]
    try:
        state = unpack(conn.recv_bytes())
        load_learned(agent, rngs, state)
        buffer.store(*(state["replay"][k].numpy() for k in REPLAY))
        buffer.ptr = state["ptr"]
        while True:
            try:
                asked = unpack(conn.recv_bytes())
            except EOFError:
                return
            if asked["new"] is not None:
                buffer.store(*(asked["new"][k].numpy() for k in REPLAY))
            n, got = agent.normalizer, asked["normalizer"]  # as the collecting process holds it
            n.sum[:], n.sumsq[:], n.count = 0.0, 0.0, 0
            n.add(got["sum"].numpy(), got["sumsq"].numpy(), got["count"])
            start = time.perf_counter()
            losses = learner.train(rngs)
            answer = dict(losses=losses, seconds=time.perf_counter() - start, waiting=learner.waiting)
            conn.send_bytes(pack(learned(agent, rngs) | answer))
    except Exception as e:  # noqa: BLE001 (any failure: told to the collecting process in one line, then shown)
        traceback.print_exc()
        conn.send_bytes(pack(dict(failed=f"{type(e).__name__}: {e}")))


# ------------------------------------------------------------------------------------------------
# The SAC update's CPU kernels (a speed trick, docs/speed.md: the update 1.06-1.11x that of commit 25d2c6b on
# an AVX2 CPU, paired): the message and node nets and the heads of the training scripts, the same math, each
# one autograd node with its backward written out. Products by oneDNN, ReLUs fused into them or applied in
# place, only the gradients that are needed.
# ------------------------------------------------------------------------------------------------
ONEDNN = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def product(x: torch.Tensor, w: torch.Tensor, bias: torch.Tensor | None = None, relu: bool = False):
    """x (rows, in) times w (out, in) transposed, + bias, ReLU if asked, summed in fp32: oneDNN's linear, which
    applies the ReLU while the output is still in cache (torch's CPU product goes to MKL, slow on AMD)."""
    if ONEDNN:
        return torch.ops.mkldnn._linear_pointwise(x, w, bias, "relu" if relu else "none", [], "")
    y = F.linear(x, w, bias)
    return y.relu_() if relu else y


def weight_grad(g: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """g^T x in fp32: the gradient of a layer's weight, for its output gradient g (rows, out) and input x
    (rows, in). oneDNN copies a transposed first operand, so the narrower one goes first."""
    w = product(g.t(), x.t()) if g.shape[1] <= x.shape[1] else product(x.t(), g.t()).t()
    return w.float().contiguous()


def bias_grad(g: torch.Tensor) -> torch.Tensor:
    return g.sum(0, dtype=torch.float32)


def relu_backward_(g: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """g zeroed in place where the ReLU's output y is 0."""
    return torch.ops.aten.threshold_backward.grad_input(g, y, 0, grad_input=g)


def live_rows(grad: torch.Tensor, multiple: int = 32) -> torch.Tensor:
    """The rows of grad that are not all zero, then zero rows up to a multiple of 32: oneDNN builds a product
    for each new shape (about 1 ms), so a few shapes, not one per count."""
    live = grad.any(1)
    k = min(len(grad), -(-int(live.sum()) // multiple) * multiple)
    return live.byte().argsort(descending=True, stable=True)[:k]


class NodeNet(torch.autograd.Function):
    """The scripts' node_sum of one Linear -> ReLU -> Linear -> ReLU net. Its backward skips the samples whose
    gradient is zero: in the actor loss, min(Q1, Q2) sends each sample's gradient to one twin, so each twin
    back-propagates about half the batch."""

    @staticmethod
    def forward(ctx, glob, local, w1, b1, w2, b2, dtype):
        b, n, _ = local.shape
        x = torch.cat([glob[:, None].expand(-1, n, -1), local], dim=-1).view(b * n, -1).to(dtype)  # [glob, local_i]
        w1, w2 = w1.to(dtype), w2.to(dtype)
        h = product(x, w1, b1.to(dtype), relu=True)  # (B n, hidden)
        y = product(h, w2, b2.to(dtype), relu=True)  # (B n, out)
        ctx.save_for_backward(x, h, y, w1, w2)
        ctx.shape = b, n, glob.shape[1]
        return y.view(b, n, -1).sum(1, dtype=torch.float32)

    @staticmethod
    def backward(ctx, grad):
        x, h, y, w1, w2 = ctx.saved_tensors
        (b, n, k), need = ctx.shape, ctx.needs_input_grad
        rows = None if need[2] else live_rows(grad)  # without weight gradients: live samples alone
        if rows is not None:
            grad, h, y = grad[rows], *(t.view(b, n, -1)[rows].flatten(0, 1) for t in (h, y))
        m, hidden, out = len(grad), len(w1), len(w2)  # (sizes spelled out: m may be 0)
        g = grad.to(w2.dtype)[:, None].expand(m, n, out)  # every node's output gets the sum's gradient
        g = torch.ops.aten.threshold_backward(g, y.view(m, n, out), 0).view(m * n, out)
        gh = relu_backward_(product(g, w2.t()), h)  # (B n, hidden)
        grads = [None] * 7
        if need[0]:
            grads[0] = gh.view(m, n, hidden).sum(1, dtype=torch.float32) @ w1[:, :k].float()
        if need[1]:
            grads[1] = product(gh, w1[:, k:].t().contiguous()).view(m, n, len(w1[0]) - k).float()
        if rows is not None:  # zeros for the samples without gradient
            grads[:2] = [t if t is None else t.new_zeros(b, *t.shape[1:]).index_copy_(0, rows, t) for t in grads[:2]]
        if need[2]:
            grads[2:6] = weight_grad(gh, x), bias_grad(gh), weight_grad(g, h), bias_grad(g)
        return tuple(grads)


def fused_edge_max(edges, w1, b1, w2, b2, n: int, dtype):
    """The scripts' edge_max of one Linear -> ReLU -> Linear -> ReLU net. Without gradients (the TD target's),
    in chunks of 64 samples, so that each chunk's hidden layer is still in cache for its second product."""
    if torch.is_grad_enabled() and w1.requires_grad:
        return EdgeMax.apply(edges, w1, b1, w2, b2, n, dtype)
    return torch.cat([edge_nets(e, w1, b1, w2, b2, n, dtype)[3] for e in edges.split(64)])


def edge_nets(edges, w1, b1, w2, b2, n: int, dtype):
    """The net on every edge (B, E, in), and its max over each node's n - 1 edges: (x, h, y, max)."""
    x = edges.reshape(-1, edges.shape[-1]).to(dtype)
    h = product(x, w1.to(dtype), b1.to(dtype), relu=True)  # (B E, hidden)
    y = product(h, w2.to(dtype), b2.to(dtype), relu=True).view(len(edges), n, n - 1, -1)
    return x, h, y, y.amax(dim=2)


class EdgeMax(torch.autograd.Function):
    """fused_edge_max with gradients. The max's gradient goes to the edge that gave it (shared among exact ties, as
    torch's amax does), where the ReLU let it through."""

    @staticmethod
    def forward(ctx, edges, w1, b1, w2, b2, n, dtype):
        x, h, y, out = edge_nets(edges, w1, b1, w2, b2, n, dtype)
        ctx.save_for_backward(x, h, y, out, w2.to(dtype))
        return out

    @staticmethod
    def backward(ctx, grad):
        x, h, y, out, w2 = ctx.saved_tensors
        hit = (y == out[:, :, None]) & (y > 0)
        g = torch.where(hit, grad.to(y.dtype)[:, :, None], 0) / hit.sum(2, keepdim=True).clamp_min_(1)
        g = g.view(-1, y.shape[-1])  # (B E, out)
        gh = relu_backward_(product(g, w2.t()), h)
        return None, weight_grad(gh, x), bias_grad(gh), weight_grad(g, h), bias_grad(g), None, None


class Head(torch.autograd.Function):
    """A head (Linear -> ReLU -> Linear, fp32, on the node read-out), its products by oneDNN as the kernels
    above: torch's go to MKL, at half oneDNN's rate on the AMD EPYC with AVX512-BF16 (docs/speed.md)."""

    @staticmethod
    def forward(ctx, x, w1, b1, w2, b2):
        h = product(x, w1, b1, relu=True)
        ctx.save_for_backward(x, h, w1, w2)
        return product(h, w2, b2)

    @staticmethod
    def backward(ctx, grad):
        x, h, w1, w2 = ctx.saved_tensors
        g = grad.contiguous()
        gh = relu_backward_(product(g, w2.t()), h)
        grad_x = product(gh, w1.t()) if ctx.needs_input_grad[0] else None
        if not ctx.needs_input_grad[1]:  # the actor loss: the critic's heads are constants there
            return grad_x, None, None, None, None
        return grad_x, weight_grad(gh, x), bias_grad(gh), weight_grad(g, h), bias_grad(g)


# ------------------------------------------------------------------------------------------------
# The machine: whether bf16 pays here (--precision bf16 is refused where not), the line that names it
# ------------------------------------------------------------------------------------------------
def fast_bf16(cuda: bool) -> bool:
    """Whether --precision bf16 can pay here: this process's GPU has bf16 tensor cores (compute capability 8.0
    on, or AMD's), or the CPU has bf16 matrix instructions (x86: AMX or AVX512-BF16; ARM: BF16) for oneDNN;
    without them, bf16 products are emulated."""
    if cuda:  # not torch.cuda.is_bf16_supported(): it counts emulation (V100, T4) and makes a context on GPU 0
        gpu = int(os.environ.get("LOCAL_RANK", "0"))  # this process's (torchrun's LOCAL_RANK)
        return bool(torch.version.hip) or torch.cuda.get_device_capability(gpu) >= (8, 0)
    caps = torch.cpu.get_capabilities()
    has_bf16 = any(caps.get(name) for name in ("amx_bf16", "avx512_bf16", "bf16", "sve_bf16"))
    return torch.backends.mkldnn.is_available() and has_bf16


def precision_of(args) -> tuple[str, str]:
    """The precision of the update's large products, and why: --precision as given; else (its default, '') bf16 on
    a CPU with bf16 matrix units, where it learnt more per hour than fp32 (SPEC §12, docs/results.md), fp32 with
    --plain (no speed trick), with --cuda (not measured there) and on a CPU without them."""
    if args.precision:
        return args.precision, "given"
    why = ("--plain" if args.plain else "--cuda: bf16 not measured there" if args.cuda
           else "" if fast_bf16(cuda=False) else "no bf16 matrix units on this CPU")  # fmt: skip
    return ("fp32", why) if why else ("bf16", "this CPU's bf16 matrix units")


def cpu_line() -> str:
    """This CPU and its matrix instructions, on the first line of every speed benchmark: each figure names its
    machine (docs/speed.md). A vague model name ('AMD EPYC' in a VM) gets its family and model numbers."""
    caps = torch.cpu.get_capabilities()
    info = Path("/proc/cpuinfo").read_text().split("\n\n")[0] if os.path.exists("/proc/cpuinfo") else ""
    fields = dict(line.split(":", 1) for line in info.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    name = caps.get("cpu_name") or fields.get("model name") or "unknown CPU"
    if "cpu family" in fields:
        name += f" (family {fields['cpu family']}, model {fields.get('model', '?')})"
    isa = [f"{label} {'yes' if caps.get(key) else 'no'}" for label, key in
           (("AMX", "amx_bf16"), ("AVX512-BF16", "avx512_bf16"), ("AVX512", "avx512_f"), ("AVX2", "avx2"))]  # fmt: skip
    bf16 = fast_bf16(cuda=False)
    return f"CPU: {name}, {os.cpu_count()} CPUs; {', '.join(isa)}; fast bf16: {bf16}; torch {torch.__version__}"
