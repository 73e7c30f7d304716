# Docs: README.md, docs/training.md, docs/scaling.md; SPEC §10 (outputs, checkpoints), §11 (processes).
"""What is not the algorithm, written once for the three training scripts: the command line, processes,
checkpoints and the paper's trained agent, outputs and interruptions.

A reader of the paper can skip this file: gangstr_hme.py, lp_baseline.py and vds_baseline.py each hold
the whole algorithm (CleanRL's single-file rule) and import what is here, as CleanRL's scripts import
cleanrl_utils. It imports no training script and knows no goal sampler. A script passes in what is its
own: its Args class (the command line and checkpoints read its fields and docstrings), its run, its
`evaluate`, and its sampler's `check_sampler_args`; a sampler is reached only through the hooks of
`Sampler`'s docstring. What it reads of a run is what every script's Run has: args, n_workers, workers
(each one's index, rng, batch_rng, env and seed()), classes, epoch, cycle, tally, rows, sampler, and the learner's
agent (SAC's networks, optimizers, normalizer, n_updates), buffer, graph, encountered, segments, plan_seconds
and waiting. Arrows run one way: scripts -> plumbing -> speed (whether bf16 pays here), fetch5_env, oracle_graph.
The update's speed tricks are speed.py's; Adam's rates, this file's adam_rates (SPEC §12).

Sections: command line; processes (SPEC §11); checkpoints (SPEC §10) and the paper's trained agent;
outputs (progress.csv, TensorBoard, console, --eval-only results and videos); interruptions; a run's
folder and the top level's steps (parse_command_line, job, RunFolder, evaluate_checkpoint, run_main).
"""

from __future__ import annotations

import argparse
import ast
import collections
import contextlib
import copy
import csv
import dataclasses
import datetime
import gc
import hashlib
import inspect
import itertools
import json
import math
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn

import fetch5_env
import oracle_graph as og
import speed


# ------------------------------------------------------------------------------------------------
# Command line (plumbing): argparse built from Args, each field's docstring its --help line
# ------------------------------------------------------------------------------------------------
def _field_docs(cls) -> dict[str, str]:
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {
        a.target.id: b.value.value
        for a, b in zip(body, body[1:], strict=False)
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
    }


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):
        """Bad input: one line naming the value, exit code 2 (not argparse's screen of usage)."""
        self.exit(2, f"{self.prog}: error: {message} (--help lists every option)\n")


def make_parser(Args: type, with_defaults: bool = True) -> argparse.ArgumentParser:
    """argparse built from a script's Args, each field's docstring and default its --help line; the script's
    docstring's first paragraph its description. Without defaults, parsing yields only the flags the user
    gave (see given_flags)."""
    description = (inspect.getmodule(Args).__doc__ or "").split("\n\n")[0]
    parser = OneLineParser(description=description, allow_abbrev=False)
    if not with_defaults:
        parser.argument_default = argparse.SUPPRESS
    docs = {k: v.replace("%", "%%") for k, v in _field_docs(Args).items()}  # argparse formats help with %
    for f in dataclasses.fields(Args):
        flag, default = "--" + f.name.replace("_", "-"), f.default if with_defaults else argparse.SUPPRESS
        text = docs[f.name] + (f" (default: {f.default!r})" if with_defaults else "")
        if f.type in ("bool", bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=text)
        else:
            kind = {"int": int, "float": float, "str": str}[f.type]
            parser.add_argument(flag, type=kind, default=default, help=text, metavar=kind.__name__.upper())
    return parser


def parse_args(Args: type, check_sampler_args, argv=None):
    """The script's Args from the command line, or exit 2 with one line naming the first bad value."""
    parser = make_parser(Args)
    a, given = Args(**vars(parser.parse_args(argv))), given_flags(Args, argv)  # --help: the parser with defaults
    if problem := check_args(a, check_sampler_args) or check_needs(a, given):
        parser.error(problem)  # exit code 2, the message names the value
    return a


# Flags that do nothing unless another is set, refused alone: flag -> (the flag it needs, why); and Args.NEEDS'.
NEEDS = {k: ("init_from", "a run started from a trained agent") for k in
         ("init_prior_count", "init_lr_scale", "init_warmup", "init_learning_starts")}  # fmt: skip


def check_needs(a, given: set[str]) -> str | None:
    """A flag of NEEDS (or Args.NEEDS) given without the one it needs: refused (not with --resume: the run's own)."""
    for name, (needed, why) in (NEEDS | getattr(type(a), "NEEDS", {})).items():
        if name in given and not getattr(a, needed) and not a.resume:
            value, flag, other = getattr(a, name), *(f"--{x.replace('_', '-')}" for x in (name, needed))
            return f"{flag} {value if value != '' else repr(value)} does nothing without {other} ({why})"
    return None


# --- Adam's rates (SPEC §12): the one place the rule is applied ----------------------------------
PAPER_RATE, FEW_WORKERS, FEW_SCALE = 1e-3, 24, 0.3  # below 24 workers, x0.3 of the paper's (measured)
FEW_TEXT, MANY_TEXT = f"x{FEW_SCALE:g} of the paper's: below {FEW_WORKERS} workers", f"{FEW_WORKERS} workers or more"


def adam_rates(args, trained: bool = True) -> list[tuple[float, str]]:
    """Adam's rates, the actor's and the critic's, each with why, however the Args were built (command line, code,
    checkpoint): one given (not 0) as given, else the paper's 1e-3, x0.3 below 24 workers (--num-envs x processes)
    unless --paper-rates; after --init-from (SPEC §10), the paper's x --init-lr-scale (trained=False: not scaled)."""
    many, given = args.num_envs * processes() >= FEW_WORKERS, (args.lr_actor, args.lr_critic)
    papers = "--paper-rates" if args.paper_rates else "--init-from" if args.init_from else MANY_TEXT if many else ""
    rule = (PAPER_RATE, f"the paper's: {papers}") if papers else (PAPER_RATE * FEW_SCALE, FEW_TEXT)
    if not (args.init_from and trained):
        return [(r, "given") if r else rule for r in given]
    scale, warmup = args.init_lr_scale, f", after a {args.init_warmup:,}-update warm-up" if args.init_warmup else ""
    of = {r: f"{r:g} given" if r else "the paper's" for r in given}
    return [((r or PAPER_RATE) * scale, f"x{scale:g} of {of[r]}: --init-lr-scale{warmup}") for r in given]


def rates_text(lrs: list[float], whys: list[str]) -> str:
    """The first line's rates: what Adam was given (the actor's, the critic's), each with why."""
    if whys[0] == whys[1]:
        return f"{lrs[0]:g} / {lrs[1]:g} ({whys[0]})"
    return " / ".join(f"{lr:g} ({why})" for lr, why in zip(lrs, whys, strict=True))


def given_flags(Args: type, argv=None) -> set[str]:
    """The Args fields the command line sets explicitly (whatever their value)."""
    return set(vars(make_parser(Args, with_defaults=False).parse_args(argv)))


def check_args(a, check_sampler_args) -> str | None:
    """The first bad value in a (a script's Args), described, or None; its sampler's options: check_sampler_args."""
    for f in dataclasses.fields(a):
        value = getattr(a, f.name)
        if f.type in ("float", float) and not math.isfinite(value):
            return f"--{f.name.replace('_', '-')} must be a finite number, got {value}"
    at_least_1 = ("n_epochs", "n_cycles", "n_segments", "batch_size", "segment_len", "buffer_size", "k_shortest",
                  "eval_goals_per_class", "stable_steps", "target_update_every", "max_eval_subgoals",
                  "init_prior_count", "num_envs")  # fmt: skip
    for name in at_least_1:
        if getattr(a, name) < 1:
            return f"--{name.replace('_', '-')} must be at least 1, got {getattr(a, name)}"
    for name in ("n_updates", "her_k", "threads", "video_episodes", "init_warmup", "init_learning_starts", "alpha",
                 "lr_actor", "lr_critic"):  # fmt: skip  # a rate of 0: the rule's (adam_rates)
        if getattr(a, name) < 0:
            return f"--{name.replace('_', '-')} must be non-negative, got {getattr(a, name)}"
    for name in ("shortest_ratio", "gamma", "polyak", "sr_ema", "sr_prior"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            return f"--{name.replace('_', '-')} must be in [0, 1], got {getattr(a, name)}"
    if not 0 <= a.seed < 2**32:
        return f"--seed must be in [0, 2**32), got {a.seed}"
    if a.init_lr_scale <= 0:
        return f"--init-lr-scale must be positive, got {a.init_lr_scale}"
    if a.paper_rates and a.init_from:  # SPEC §12: its rates are --init-lr-scale's share of the paper's
        return "--paper-rates does nothing with --init-from (its rates: --init-lr-scale x the paper's; 1 gives them)"
    if not og.MIN_BLOCKS <= a.n_blocks <= og.MAX_BLOCKS:
        return f"--n-blocks must be in [{og.MIN_BLOCKS}, {og.MAX_BLOCKS}], got {a.n_blocks}"
    for name, allowed in dict(her_strategy=("final", "future"), plan_on=("agent", "oracle"),
                              precision=("fp32", "bf16", "")).items():  # fmt: skip  # '': speed.precision_of's
        if getattr(a, name) not in allowed:
            return f"--{name.replace('_', '-')} must be {' or '.join(map(repr, allowed))}, got {getattr(a, name)!r}"
    if a.max_path_len < 2:
        return f"--max-path-len must be at least 2 (start and goal), got {a.max_path_len}"
    if a.stable_steps > a.segment_len:
        return f"--stable-steps must be at most --segment-len ({a.segment_len}), got {a.stable_steps}"
    if a.init_learning_starts > a.buffer_size // a.segment_len:  # else no update would ever run
        return (f"--init-learning-starts {a.init_learning_starts} is more segments than a replay holds "
                f"({a.buffer_size // a.segment_len}: --buffer-size / --segment-len)")  # fmt: skip
    if a.buffer_size < a.n_segments * a.segment_len:
        return f"--buffer-size must hold one cycle ({a.n_segments * a.segment_len} transitions), got {a.buffer_size}"
    n = a.n_blocks  # replay bytes: float32 observations and actions, int8 configs; SPEC §12's memory limit
    replay_bytes = a.num_envs * a.buffer_size * (4 * fetch5_env.obs_size(n) + og.config_dim(n) + 16)
    if replay_bytes > os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"):
        return (f"--buffer-size {a.buffer_size} x --num-envs {a.num_envs} needs {replay_bytes / 2**30:.1f} GiB, more "
                "memory than this machine has")  # fmt: skip
    if a.batch_size > MAX_BATCH:  # one update's activations grow as batch x edges x 256 floats
        return f"--batch-size must be at most {MAX_BATCH} (the paper's is 256), got {a.batch_size}"
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.+=-]*", a.exp_name):
        return f"--exp-name must be a plain name (letters, digits, _ . + = -), got {a.exp_name!r}"
    if a.plain and (a.compile or a.precision == "bf16"):
        return f"--plain turns every speed trick off: not with {'--compile' if a.compile else '--precision bf16'}"
    return check_device(a) or check_run_control(a) or check_sampler_args(a)


def check_device(a) -> str | None:
    """--cuda and --precision bf16 against this machine: checked on the command line, and again on what a
    checkpoint brings (a run trained with them may be resumed where they do not hold). Probes that make no
    CUDA context: a torchrun process must make its first on its own GPU (init_workers)."""
    if a.cuda and not torch.cuda.is_available():
        return "--cuda: no CUDA device here (torch.cuda.is_available() is False)"
    if a.cuda and local_gpu() >= torch.cuda.device_count():  # else set_device's traceback ("invalid device ordinal")
        return (f"--cuda: this process's GPU is LOCAL_RANK {local_gpu()}, but this machine has "
                f"{torch.cuda.device_count()} GPU(s): one process per GPU (torchrun --nproc-per-node no "
                "more)")  # fmt: skip
    if a.precision == "bf16" and not speed.fast_bf16(a.cuda):
        device = "GPU (compute capability under 8.0)" if a.cuda else "CPU (neither AMX nor AVX512-BF16)"
        return f"--precision bf16: this {device} has no bf16 matrix instructions, where bf16 is no faster; use fp32"
    return None


def local_gpu() -> int:
    """The GPU of this process: torchrun's LOCAL_RANK (0 without torchrun)."""
    return int(os.environ.get("LOCAL_RANK", "0"))


MAX_BATCH = 8192  # 32x the paper's batch; a 5-block batch of 100,000 took 4.4 GB of activations


def check_run_control(a) -> str | None:
    """What --resume, --init-from, --eval-only, --checkpoint, --capture-video, --plan-on and --runs-dir need."""
    if a.resume and a.eval_only:
        return "--resume and --eval-only exclude each other (evaluate with --eval-only --checkpoint PATH)"
    if a.init_from and (a.resume or a.eval_only):
        return (f"--init-from {a.init_from!r} starts a new run: not with --resume (which continues one) or "
                "--eval-only (evaluate the file with --eval-only --checkpoint PATH)")  # fmt: skip
    if a.resume and not os.path.isfile(a.resume):
        return f"--resume: cannot read checkpoint {a.resume!r}"
    if a.init_from not in ("", "paper") and not os.path.isfile(a.init_from):  # paper: see paper_file
        return f"--init-from: cannot read {a.init_from!r}"
    if a.eval_only and a.checkpoint != "paper" and not os.path.isfile(a.checkpoint):
        return f"--eval-only needs a readable --checkpoint, got {a.checkpoint!r}"
    if a.checkpoint and not a.eval_only:
        return f"--checkpoint {a.checkpoint!r} is read by --eval-only only (to continue a run: --resume)"
    if a.capture_video and not a.eval_only:
        return "--capture-video films an --eval-only evaluation; add --eval-only --checkpoint PATH"
    if a.plan_on != "agent" and not a.eval_only:
        return f"--plan-on {a.plan_on!r} plans an --eval-only evaluation; add --eval-only --checkpoint PATH"
    if not (a.resume or a.eval_only):
        parent = Path(a.runs_dir).absolute()
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            return f"--runs-dir {a.runs_dir!r}: cannot create a run folder under {str(parent)!r}"
    return None


# ------------------------------------------------------------------------------------------------
# Processes (plumbing; SPEC §11): one by default; under torchrun, several, holding the workers
# ------------------------------------------------------------------------------------------------
def init_workers(args) -> torch.device:
    """Torch's threads (--threads); join the torchrun job if there is one (gloo on CPU, nccl on GPU); this
    process's device."""
    if args.threads:
        torch.set_num_threads(args.threads)
    cuda = args.cuda and torch.cuda.is_available()
    if cuda and args.precision == "bf16":  # cuBLAS would otherwise sum bf16 products in bf16, not fp32 as on CPU
        torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = False  # (test_update's bounds)
    if processes() > 1 and not dist.is_initialized():
        if cuda:
            torch.cuda.set_device(local_gpu())
        dist.init_process_group("nccl" if cuda else "gloo", timeout=COLLECTIVE_TIMEOUT)
    return torch.device("cuda", torch.cuda.current_device()) if cuda else torch.device("cpu")


# How long a process waits at a collective: while process 0 saves a checkpoint, the others wait at the next
# one; a replay of several GB on a slow disk takes minutes. Gloo's default; nccl's (10 minutes) would abort.
COLLECTIVE_TIMEOUT = datetime.timedelta(minutes=30)


def rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


def world() -> int:
    return dist.get_world_size() if dist.is_initialized() else 1


def processes() -> int:
    """torchrun's processes (its WORLD_SIZE; 1 without torchrun), known before the job is joined (world())."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def _comm_device() -> torch.device:
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")


def all_sum(x: np.ndarray) -> np.ndarray:
    """Element-wise sum over processes (float64)."""
    if world() == 1:
        return x
    t = torch.as_tensor(x, dtype=torch.float64, device=_comm_device())
    dist.all_reduce(t)
    return t.cpu().numpy()


def gather_workers(local: np.ndarray) -> np.ndarray:
    """(all workers, ...) float64 rows from this process's (num_envs, ...) rows, in global worker order: a
    sum of zero-padded copies, which adds nothing but zeros to any value."""
    if world() == 1:
        return np.asarray(local, dtype=np.float64)
    full = np.zeros((world() * len(local), *np.shape(local)[1:]))
    full[rank() * len(local) : (rank() + 1) * len(local)] = local
    return all_sum(full)


def all_gather_rows(rows: np.ndarray) -> np.ndarray:
    """Every process's int64 rows (any number each), concatenated in rank order, so in global worker order
    when each process gives its workers' rows in order: the same in every process."""
    rows = np.asarray(rows, dtype=np.int64)
    if world() == 1:
        return rows
    dev = _comm_device()
    counts = [torch.zeros(1, dtype=torch.int64, device=dev) for _ in range(world())]
    dist.all_gather(counts, torch.tensor([len(rows)], device=dev))
    counts = [int(c) for c in counts]
    padded = torch.zeros((max(counts), *rows.shape[1:]), dtype=torch.int64, device=dev)
    padded[: len(rows)] = torch.as_tensor(rows, device=dev)
    parts = [torch.empty_like(padded) for _ in counts]
    dist.all_gather(parts, padded)
    return torch.cat([p[:c] for p, c in zip(parts, counts, strict=True)]).cpu().numpy()


def broadcast_params(*modules: nn.Module):
    """Every process starts from process 0's parameters."""
    if world() > 1:
        for t in (t for m in modules for t in m.state_dict().values()):
            dist.broadcast(t, src=0)


def sum_grads(params: list[torch.Tensor]):
    """Gradients summed over processes, in one all-reduce (within a process, the losses already sum its
    workers', see SAC.losses): the sum over all workers of SPEC §11."""
    if world() > 1:
        grads = [p.grad for p in params]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        for g, synced in zip(grads, flat.split([g.numel() for g in grads]), strict=True):
            g.copy_(synced.view_as(g))


def check_budgets(run):
    """After a cycle: every worker spent exactly its budget of segments (a cycle spends all of w.left, Sampler).
    Otherwise stop now, naming the sampler and the worker: with one worker a short cycle would silently store
    fewer segments, with several the replays would fail to stack far from the cause. (A cycle that asks for
    more is stopped by the driver at the first segment too many: budget_error.)"""
    for w in run.workers:
        if w.left != 0:
            n = run.args.n_segments
            budget_error(f"{type(run.sampler).__name__}.cycle", f"spent {n - w.left} of worker {w.index}'s {n}")


def budget_error(program: str, what: str):
    """Stop the run with one line: what `program` (a sampler's cycle) did with a worker's segments."""
    sys.exit(f"error: {program} {what} segments this cycle; a cycle spends exactly w.left (see Sampler)")


def summed(counts: collections.Counter, keys: list[str]) -> dict[str, float]:
    """Counts of this process's workers (a goal sampler's stats), summed over every process."""
    return dict(zip(keys, all_sum(np.array([counts[k] for k in keys], dtype=np.float64)), strict=True))


# ------------------------------------------------------------------------------------------------
# Checkpoints (plumbing; SPEC §10): the run's state, atomic saves, safe loads, what --resume and
# --eval-only may change
# ------------------------------------------------------------------------------------------------
ENV_VERSION = fetch5_env.ENV_VERSION  # a checkpoint names the environment it was trained in (and its script)
CHECKPOINT_KEYS = ("args", "counters", "actor", "critic")
NETWORKS = ("actor", "critic", "critic_target", "actor_opt", "critic_opt")  # SAC's, as saved
REPLAY = speed.REPLAY  # ReplayBuffer's arrays (what --overlap's process is sent too)
WORKER_RNGS = dict(rng=lambda w: w.rng, env_rng=lambda w: w.env.np_random, batch_rng=lambda w: w.batch_rng)
# Args fields newer than some checkpoints, each with the value that computes what the run computed before it:
# one started with --init-from before the fine-tuning defaults (SPEC §10) keeps its rates; before --overlap, its order.
PREDATED = dict(init_lr_scale=1.0, init_warmup=0, init_learning_starts=0, overlap=False)


def script_of(Args: type) -> str:
    """The script whose Args these are (gangstr_hme, lp_baseline, vds_baseline): it wrote the checkpoint."""
    return Path(inspect.getfile(Args)).stem


def library_versions() -> dict[str, str]:
    """The versions of the libraries a run's numbers depend on: MuJoCo's physics, Gymnasium's seeding, numpy's
    random streams and torch's arithmetic. A checkpoint records them (its ENV_VERSION names the scene alone)."""
    import gymnasium  # noqa: PLC0415 (fetch5_env's import: loaded already)
    import mujoco  # noqa: PLC0415

    versions = dict(mujoco=mujoco.__version__, gymnasium=gymnasium.__version__, numpy=np.__version__,
                    torch=torch.__version__)  # fmt: skip
    return {name: str(v) for name, v in versions.items()}  # plain strings (torch's is a str subclass)


def version_warning(state: dict) -> str | None:
    """One line if the checkpoint was written under other library versions than these (a warning: the run
    goes on, but cannot repeat the uninterrupted one exactly); None if the same, or not recorded (older
    checkpoints)."""
    saved, now = state.get("versions"), library_versions()
    saved = saved if isinstance(saved, dict) else now
    if not (changed := [f"{k} {saved[k]} -> {now[k]}" for k in now if saved.get(k, now[k]) != now[k]]):
        return None
    return (f"warning: --resume: the checkpoint was written under other library versions ({', '.join(changed)}): "
            "the run goes on, but will not repeat the uninterrupted one exactly")  # fmt: skip


def save_state(run) -> dict:
    """Everything the rest of the run depends on (SPEC §10): a resumed run is the uninterrupted one."""
    agent, learner = run.learner.agent, run.learner
    rates = [rate for rate, _ in adam_rates(run.args, trained=False)]  # the rule's, kept: resumed elsewhere too
    state = dict(
        script=script_of(type(run.args)), env_version=ENV_VERSION, versions=library_versions(),
        args=dataclasses.asdict(run.args) | dict(lr_actor=rates[0], lr_critic=rates[1]),
        counters=dict(epoch=run.epoch, cycle=run.cycle, segments=learner.segments, goals=run.sampler.goals,
                      n_updates=agent.n_updates),
        epoch_so_far=dict(tally=copy.deepcopy(run.tally), stats=plain(run.sampler.stats),
                          plan_seconds=learner.plan_seconds),
        rows=copy.deepcopy(run.rows),
        **{name: getattr(agent, name).state_dict() for name in NETWORKS},
        normalizer=dict(sum=torch.tensor(agent.normalizer.sum), sumsq=torch.tensor(agent.normalizer.sumsq),
                        count=agent.normalizer.count),
        graph=learner.graph.state_dict(),
        encountered=torch.tensor(sorted(learner.encountered), dtype=torch.int64),
        **run.sampler.state_dict(),
        **{key: [json.dumps(rng(w).bit_generator.state) for w in run.workers] for key, rng in WORKER_RNGS.items()},
    )  # fmt: skip
    if run.args.save_buffer:
        b, n = learner.buffer, learner.buffer.size
        # One tensor per worker: a view of worker i's first n segments holds only them, where a view of
        # every worker's would hold (and torch.save write) the whole array between them.
        saved = {k: [torch.from_numpy(getattr(b, k)[i, :n]) for i in range(len(run.workers))] for k in REPLAY}
        state["buffer"] = dict(ptr=b.ptr, **saved)
    return state


def load_adam(opt: torch.optim.Optimizer, saved: dict):
    """A checkpoint's optimizer state into opt, which steps as this run's command line says (--plain or not,
    speed.fuse_adams), not as the checkpoint's run did: each group keeps its own `fused`, so that torch's load
    puts each step count where this run's step keeps it (the parameter's device when fused, else the CPU)."""
    groups = saved["param_groups"]
    if len(groups) == len(opt.param_groups):  # else torch's load names the difference
        groups = [{**g, "fused": ours.get("fused")} for g, ours in zip(groups, opt.param_groups, strict=True)]
    opt.load_state_dict({**saved, "param_groups": groups})


def load_state(run, s: dict):
    """The run as save_state saw it (process 0's random streams and replays; see below for the others)."""
    agent, learner = run.learner.agent, run.learner
    if not isinstance(s.get("rng", []), list):
        raise ValueError("written before --num-envs (one random stream per worker): retrain, or use that version")
    c, so_far = s["counters"], s["epoch_so_far"]
    run.epoch, run.cycle, learner.segments, run.sampler.goals = c["epoch"], c["cycle"], c["segments"], c["goals"]
    agent.n_updates = c["n_updates"]
    run.tally, learner.plan_seconds = so_far["tally"], so_far["plan_seconds"]
    run.tally.setdefault("wall", run.tally["collect"] + run.tally["update"])  # saved before time_epoch: no overlap
    run.sampler.stats = collections.Counter(so_far["stats"])
    run.rows = s["rows"]
    for name in NETWORKS:
        part = getattr(agent, name)
        if isinstance(part, torch.optim.Optimizer):
            load_adam(part, s[name])
        else:
            part.load_state_dict(s[name])
    agent.normalizer.sum[:], agent.normalizer.sumsq[:], agent.normalizer.count = 0.0, 0.0, 0
    agent.normalizer.add(s["normalizer"]["sum"].numpy(), s["normalizer"]["sumsq"].numpy(), s["normalizer"]["count"])
    learner.graph.load_state_dict(s["graph"])
    learner.encountered = set(s["encountered"].tolist())
    run.sampler.load_state_dict(s)
    if rank() > 0:  # the checkpoint holds process 0's random streams and replays: the others start anew
        for w in run.workers:
            w.seed(run.args.seed + w.index, run.epoch, run.cycle)
        run.sampler.stats.clear()  # this epoch's counts so far are process 0's own: the others start again
        run.tally.update(wins=0, tries=0)
        return
    for key, rng in WORKER_RNGS.items():  # none for --eval-only, which draws from its own seeds; no batch_rng
        for w, saved in zip(run.workers, s.get(key, []), strict=False):  # before --overlap: its own seeds
            rng(w).bit_generator.state = json.loads(saved)
    if "buffer" in s:
        b, n = learner.buffer, len(s["buffer"]["obs"][0])
        for k in REPLAY:
            for i, saved in enumerate(s["buffer"][k]):
                getattr(b, k)[i, :n] = saved.numpy()
        b.size, b.ptr = n, s["buffer"]["ptr"]


def plain(d: dict) -> dict:
    """d with numpy scalars as Python numbers: a weights_only load accepts nothing else."""
    return {k: v.item() if isinstance(v, np.generic) else v for k, v in d.items()}


# --- files: atomic saves, safe loads --------------------------------------------------------------
def save_checkpoint(state: dict, path: Path):
    """Write then rename: an interrupted save (even kill -9) never leaves a broken checkpoint."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(Args: type, path: str, flag: str = "--resume") -> dict:
    """A checkpoint of the script whose Args these are, or the paper's agent (see from_paper), or exit 2 with
    one line saying what the file is instead. Loading never runs code from the file (weights_only, with the
    paper's numpy arrays as the only addition to what torch allows)."""
    try:
        with torch.serialization.safe_globals(PAPER_GLOBALS):
            state = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # noqa: BLE001 (any unreadable file gets the same one-line error)
        if "Weights only load failed" in str(e):  # torch's refusal of an object outside the allowed ones
            found = re.search(r"GLOBAL (\S+)|but got (<.*?>)|unrecognized function (.*?)$", str(e), re.MULTILINE)
            what = next(g for g in found.groups() if g) if found else "an object"
            checkpoint_error(flag, path, f"refused: it holds {what}, which no checkpoint holds (nothing was run)")
        checkpoint_error(flag, path, f"not a checkpoint ({type(e).__name__}: {e})")
    if isinstance(state, list):
        return from_paper(state, path, flag)
    if not isinstance(state, dict) or not all(k in state for k in CHECKPOINT_KEYS):
        checkpoint_error(flag, path, "not a checkpoint of this project (a torch file without its keys)")
    version = state.get("env_version", 1)  # checkpoints older than ENV_VERSION: version 1
    if version != ENV_VERSION:
        checkpoint_error(flag, path, f"trained in environment version {version}, but fetch5_env.py is now version "
                                     f"{ENV_VERSION} (the environment changed): retrain")  # fmt: skip
    script = script_of(Args)
    if state.get("script", script) != script:
        checkpoint_error(flag, path, f"a checkpoint of {state['script']}.py, not of {script}.py: use that script")
    state["args"] = PREDATED | state["args"]  # a run begun before these flags resumes as it began
    try:
        Args(**state["args"])
    except TypeError as e:
        checkpoint_error(flag, path, f"written by another version of {script}.py ({e})")
    return state


def restore(run, state: dict, path: str, flag: str):
    """load_state, or exit 2 with one line if the checkpoint does not fit these networks (written by
    another version of the script, say)."""
    try:
        load_state(run, state)
    except (KeyError, RuntimeError, ValueError, TypeError, IndexError) as e:
        checkpoint_error(flag, path, f"{type(e).__name__}: {e}")


def checkpoint_error(flag: str, path: str, reason: str):
    fail(f"{flag}: cannot load checkpoint {path!r}: {' '.join(str(reason).split())[:300]}")  # one line, however long


def fail(message: str):
    """Bad input: one line that names it, exit code 2 (before anything is written)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


# What --resume may change:
RUN_CONTROL = ("n_epochs", "threads", "cuda", "compile", "precision", "plain", "save_buffer", "resume")
# --eval-only's own; among them precision: acting never computes in bf16 (speed.fast_nets), so a run trained
# in bf16 is evaluated in fp32 unless the flag says otherwise, where bf16 is slow too.
EVAL_CONTROL = ("seed", "eval_goals_per_class", "max_eval_subgoals", "capture_video", "video_episodes", "plan_on",
                "threads", "cuda", "precision", "plain", "eval_only", "checkpoint", "runs_dir", "exp_name", "num_envs",
                "resume")  # fmt: skip


def args_from_checkpoint(args, given: set[str], state: dict, flag: str):
    """The checkpoint's arguments with this command line's run-control flags; exit 2 naming every given
    flag that contradicts the checkpoint (it would silently be ignored otherwise)."""
    saved = type(args)(**state["args"])
    # besides plumbing's own, a script's Args may name what --resume may change in its RESUMABLE
    allowed = EVAL_CONTROL if args.eval_only else RUN_CONTROL + tuple(getattr(type(args), "RESUMABLE", ()))
    same = getattr(type(args), "SAME", {})  # a script's values that mean the same: no difference
    meaning = lambda k, v: same.get(k, {}).get(v, v)  # noqa: E731
    bad = [f"--{k.replace('_', '-')} {getattr(args, k)!r} (checkpoint: {getattr(saved, k)!r})"
           for k in sorted(given - set(allowed))
           if meaning(k, getattr(args, k)) != meaning(k, getattr(saved, k))]  # fmt: skip
    if bad:
        fail(f"{flag}: flags that differ from the checkpoint's run: {'; '.join(bad)}")
    # Evaluation settings come from this command line (defaults included); a resumed run keeps its own
    # unless given again (threads, say: a different thread count changes float sums).
    keep = [k for k in allowed if args.eval_only or k in given or k == "resume"]
    merged = dataclasses.replace(saved, **{k: getattr(args, k) for k in keep})
    if why := check_device(merged):
        fail(f"{flag}: {why} (the checkpoint's setting; give the flag anew)")
    return merged


# --- the paper's trained agent (--init-from, --eval-only --checkpoint) ----------------------------
# The authors' hipstr/gangstr.pt: a legacy torch.save of [o_mean, o_std, g_mean, g_std] (float32 numpy
# arrays) and the actor's and critic's state dicts, named as below. Loading it needs numpy's array
# unpickler (under the name numpy 1, the authors', wrote, and numpy 2's), the array and dtype classes and
# the float32 dtype: float32 arrays and nothing else.
_reconstruct = np.zeros(0, np.float32).__reduce__()[0]
PAPER_GLOBALS = [*((_reconstruct, f"numpy.{core}.multiarray._reconstruct") for core in ("core", "_core")),
                 np.ndarray, np.dtype, type(np.dtype(np.float32))]  # fmt: skip
PAPER_LAYERS = (  # (the authors' layer, our network and layer): SPEC §5's roles in order. Two layers of theirs
    # mapped to one of ours are stacked in this order: our head's mean rows above its log-std rows.
    ("phi_actor.linear1", "actor", "node.hidden"),
    ("phi_actor.linear2", "actor", "node.out"),
    ("rho_actor.linear1", "actor", "head.hidden"),
    ("rho_actor.mean_linear", "actor", "head.out"),
    ("rho_actor.log_std_linear", "actor", "head.out"),
    ("mp_critic.linear1", "critic", "message.hidden"),
    ("mp_critic.linear2", "critic", "message.out"),
    ("phi_critic.linear1", "critic", "q_nodes.0.hidden"),
    ("phi_critic.linear2", "critic", "q_nodes.0.out"),
    ("phi_critic.linear4", "critic", "q_nodes.1.hidden"),
    ("phi_critic.linear5", "critic", "q_nodes.1.out"),
    ("rho_critic.linear1", "critic", "q_heads.0.hidden"),
    ("rho_critic.linear3", "critic", "q_heads.0.out"),
    ("rho_critic.linear4", "critic", "q_heads.1.hidden"),
    ("rho_critic.linear6", "critic", "q_heads.1.out"),
)


def from_paper(items: list, path: str, flag: str) -> dict:
    """The paper's file as {actor, critic: our state dicts; normalizer: mean and std; n_blocks} (read from
    the observation size), or exit 2 with one line. It holds no target network, optimizer, graph or
    counters; its goals were not normalized (g_mean 0, g_std 1), as SPEC §5 has it."""
    arrays, nets = items[:4], items[4:]
    if len(items) != 6 or not all(isinstance(x, np.ndarray) and x.ndim == 1 for x in arrays) or \
            not all(isinstance(x, dict) for x in nets):  # fmt: skip
        checkpoint_error(flag, path, "not a checkpoint of this project, nor the paper's agent (a list)")
    o_mean, o_std, g_mean, g_std = arrays
    n = (len(o_mean) - fetch5_env.obs_size(0)) // (fetch5_env.obs_size(1) - fetch5_env.obs_size(0))
    if not og.MIN_BLOCKS <= n <= og.MAX_BLOCKS or {len(o_mean), len(o_std)} != {fetch5_env.obs_size(n)} or \
            {len(g_mean), len(g_std)} != {og.config_dim(n)}:  # fmt: skip
        checkpoint_error(flag, path, f"the paper's format, but statistics of sizes {len(o_mean)} and {len(g_mean)}")
    if (g_mean != 0).any() or (g_std != 1).any():
        checkpoint_error(flag, path, "the paper's format, but with normalized goals (SPEC §5 normalizes none)")
    theirs = dict(actor=nets[0], critic=nets[1])
    for net, tensors in theirs.items():
        expected = {f"{layer}.{p}" for layer, of, _ in PAPER_LAYERS if of == net for p in ("weight", "bias")}
        if set(tensors) != expected or not all(isinstance(v, torch.Tensor) for v in tensors.values()):
            odd = sorted(set(tensors) ^ expected) or ["a value that is not a tensor"]
            checkpoint_error(flag, path, f"the paper's format, but its {net} differs: {', '.join(odd)}")
    state = dict(format="paper", n_blocks=n, normalizer=dict(mean=o_mean, std=o_std), actor={}, critic={})
    for layer, net, ours in PAPER_LAYERS:
        for p in ("weight", "bias"):
            before, weights = state[net].get(f"{ours}.{p}"), theirs[net][f"{layer}.{p}"]
            try:
                state[net][f"{ours}.{p}"] = weights if before is None else torch.cat([before, weights])
            except RuntimeError as e:  # stacked layers of different widths
                checkpoint_error(flag, path, f"the paper's format, but {layer}.{p}: {e}")
    return state


def blocks_of(state: dict) -> int:
    return state["n_blocks"] if state.get("format") == "paper" else state["args"]["n_blocks"]


def load_weights(agent, state: dict, args, path: str, flag: str):
    """A checkpoint's networks and normalizer (ours or the paper's), nothing else: what --init-from starts from,
    and all that the paper's file holds. The target critic is a copy of the critic, as in any new run (the
    paper's file has none). The paper's statistics come without a count: they count as --init-prior-count
    observations that had this mean and std, against which later data weighs in as against as many of ours;
    ours keep their own count."""
    try:
        agent.actor.load_state_dict(state["actor"])
        agent.critic.load_state_dict(state["critic"])
    except (KeyError, RuntimeError) as e:
        checkpoint_error(flag, path, f"{type(e).__name__}: {e}")
    agent.critic_target.load_state_dict(agent.critic.state_dict())
    stats = state["normalizer"]
    if "count" in stats:
        agent.normalizer.add(stats["sum"].numpy(), stats["sumsq"].numpy(), stats["count"])
    else:
        n, (mean, std) = args.init_prior_count, (np.asarray(stats[k], np.float64) for k in ("mean", "std"))
        agent.normalizer.add(n * mean, n * (std**2 + mean**2), n)


def args_with_blocks_of(args, given: set[str], state: dict, path: str, flag: str):
    """--init-from (a new run) and --eval-only of the paper's file (which holds no arguments): this command
    line's arguments, with the file's block count; exit 2 if --n-blocks says otherwise."""
    n = blocks_of(state)
    if "n_blocks" in given and args.n_blocks != n:
        fail(f"{flag}: --n-blocks {args.n_blocks}, but {path!r} holds a {n}-block agent")
    return dataclasses.replace(args, n_blocks=n)


# `paper` for --init-from or --checkpoint: the authors' file at the commit that added it, checked against the
# sha256 that results/*/config.json record, kept in one cache folder. Tests point these at a local server.
PAPER_COMMIT = "f95e3900401cd690c068deeadad9607cef095afa"  # of https://github.com/akakzia/gangstr
PAPER_URL = f"https://raw.githubusercontent.com/akakzia/gangstr/{PAPER_COMMIT}/hipstr/gangstr.pt"
PAPER_SHA256 = "0e37c60367ca83994028529553599eced86f1ab8731b06fcc691a7b42c9ed0e8"
PAPER_TIMEOUT, PAPER_WAIT = 30, 300  # seconds: a silent server waited for; a torchrun process, for its node's download


def paper_file(flag: str) -> str:
    """The authors' file in $XDG_CACHE_HOME (or ~/.cache)/hme-gangstr/, downloaded the first time (torch.hub:
    the hash checked, the file renamed into place once whole, a progress bar on a terminal); or exit 2 with one
    line, the cache as it was (after a Ctrl-C or SIGTERM too, which then goes on as an interruption). Under torchrun the
    command line is read before the processes meet: one process a node downloads (LOCAL_RANK 0); the others
    wait up to PAPER_WAIT seconds for its file, and check it themselves (if it fails, torchrun ends them)."""
    path = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "hme-gangstr" / "gangstr.pt"
    downloads = local_gpu() == 0  # torchrun's LOCAL_RANK
    made = next((p for p in reversed(path.parents) if not p.exists()), None) if downloads else None  # to remove
    timeout = socket.getdefaulttimeout()
    # A scheduler's stop (SIGTERM, before any Stopper) as a Ctrl-C, for the process that writes to the cache; one
    # that waits has nothing to undo, and ends silently when torchrun stops it (its node's download failed)
    catches = downloads and threading.current_thread() is threading.main_thread()  # signal's rule
    term = signal.signal(signal.SIGTERM, signal.default_int_handler) if catches else None
    try:
        if downloads and not path.is_file():
            progress(f"{flag} paper: downloading the authors' agent (1.2 MB) to {path}", final=True)
            socket.setdefaulttimeout(PAPER_TIMEOUT)  # urlopen's, inside torch.hub
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.hub.download_url_to_file(PAPER_URL, str(path), PAPER_SHA256, progress=sys.stderr.isatty())
        deadline = time.monotonic() + PAPER_WAIT
        while not path.is_file():  # another process downloads: its file appears whole (renamed) or not at all
            if time.monotonic() > deadline:
                raise TimeoutError(f"LOCAL_RANK 0 did not download it in {PAPER_WAIT} s")
            time.sleep(0.1)
        with open(path, "rb") as f:  # a file put there by hand, or by another process, is checked too
            if (digest := hashlib.file_digest(f, "sha256").hexdigest()) != PAPER_SHA256:
                raise ValueError(f"{path} is not the authors' file, its sha256 is {digest}")
    except BaseException as e:  # noqa: BLE001 (offline, a silent server, a wrong hash, a full disk, a Ctrl-C)
        if made is not None:
            shutil.rmtree(made, ignore_errors=True)
        if not isinstance(e, Exception):
            raise  # a Ctrl-C or SIGTERM: run_main says so and exits 130
        fail(f"{flag} paper: {type(e).__name__}: {' '.join(str(e).split())}; download {PAPER_URL} and put it at {path}")
    finally:
        socket.setdefaulttimeout(timeout)
        if catches:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if term is None else term)  # None: set outside Python
    return str(path)


# ------------------------------------------------------------------------------------------------
# Outputs (plumbing; SPEC §10): progress.csv, TensorBoard, console, --eval-only results and videos
# ------------------------------------------------------------------------------------------------
# --- the epoch's row ---------------------------------------------------------------------------
LOSSES = ("critic_loss", "actor_loss", "q", "target", "entropy")  # fixed columns, NaN before any update


def new_tally(env_steps: int) -> dict:
    """An epoch's running totals for its progress.csv row: segment outcomes, the last cycle's losses,
    seconds per phase."""
    return dict(wins=0, tries=0, losses=dict.fromkeys(LOSSES, math.nan), collect=0.0, update=0.0, eval=0.0,
                wall=0.0, env_steps_at_start=env_steps)  # fmt: skip  # wall: the cycles' (with --overlap, not the sum)


def finish_epoch(run, sr: dict[str, float]) -> dict:
    """The epoch's progress.csv row (SPEC §10; TensorBoard groups its columns, see tensorboard_tag); the
    run moves on to the next epoch."""
    learner, tally = run.learner, run.tally
    steps = learner.segments * run.args.segment_len  # all workers'
    goals, wins, tries = all_sum(np.array([run.sampler.goals, tally["wins"], tally["tries"]], dtype=np.float64))
    seconds = tally["wall"] + tally["eval"]  # the epoch's wall time
    met = np.array(sorted(learner.encountered), dtype=np.int64)  # configs met at any step of a segment
    nodes = np.asarray(learner.graph.masks, dtype=np.int64)
    row = plain(dict(
        epoch=run.epoch, goals=int(goals), segments=learner.segments, env_steps=steps, global_sr=sr["global"],
        train_success=wins / max(1, tries),
        **{f"sr_{k}": sr[k] for k in run.classes},
        **{f"encounters_{k}": int(np.isin(og.to_mask(m), met).sum()) for k, m in run.classes.items()},
        # discoveries: the class's configs that are agent-graph nodes (met at the start or the end of a training
        # segment whose end is stable, with their block permutations: SPEC §6)
        **{f"agent_nodes_{k}": int(np.isin(og.to_mask(m), nodes).sum()) for k, m in run.classes.items()},
        **run.sampler.epoch_stats(),
        agent_nodes=learner.graph.n_nodes, agent_edges=learner.graph.n_edges, sr_classes=len(learner.graph.sr),
        **tally["losses"],
        time_collect=tally["collect"], time_update=tally["update"], time_eval=tally["eval"],
        time_plan_and_graph=learner.plan_seconds, time_epoch=seconds,
        steps_per_second=(steps - tally["env_steps_at_start"]) / max(seconds, 1e-9),
    ))  # fmt: skip
    run.rows.append(row)
    run.epoch, run.cycle = run.epoch + 1, 0
    run.tally, learner.plan_seconds = new_tally(steps), 0.0
    run.sampler.stats.clear()
    return row


def learning_text(args, critic_loss: float, waiting: tuple[int, int] | None = None) -> str:
    """What the last cycle's SAC updates did, for the console: the critic loss (nan if it diverged), or that
    none ran (--n-updates 0; with --freeze-normalizer as well, a fixed agent; `waiting`, the learner's (held,
    needed): the replays still filling for --init-learning-starts, where progress.csv logs nan)."""
    if waiting is not None and args.n_updates > 0:
        return f"no SAC update yet: replays filling, {waiting[0]:,} of {waiting[1]:,} segments (--init-learning-starts)"
    if args.n_updates > 0:
        return f"critic loss {critic_loss:.3f}"
    return "fixed agent: no SAC update, normalizer frozen" if args.freeze_normalizer else "no SAC update"


def update_means(infos: list[dict]) -> dict[str, float]:
    """The mean over a cycle's updates of each value they log (0-d tensors, on the device), read in one transfer:
    a read waits for the GPU to finish the work before it, so once a cycle rather than once an update. Each
    value is a mean over this process's workers' batches; under torchrun, the mean over every process's, so
    that a row means what it means with --num-envs (SPEC §10): processes hold equal numbers of workers."""
    keys = list(infos[0]) if infos else []
    if not keys:
        return {}
    values = torch.stack([torch.stack([i[k].detach().double() for k in keys]) for i in infos]).cpu().numpy()
    means = np.array([np.mean(values[:, j]) for j in range(len(keys))])  # as np.mean of the numbers
    if world() > 1:
        means = all_sum(means) / world()
    return {k: float(m) for k, m in zip(keys, means, strict=True)}


def cycle_progress(run, detail: str):
    """The in-epoch console line, after the first cycle and every tenth of an epoch: where the run is, the
    script's `detail` and learning_text, env steps per second while training (collecting and updating; the
    epoch's line also counts its evaluation), and the time left in the epoch and in the run, from this
    epoch's cycles so far and the last epoch's evaluation time (none yet in the first epoch)."""
    a, tally = run.args, run.tally
    if run.cycle != 1 and run.cycle % max(1, a.n_cycles // 10) != 0:
        return
    seconds = tally["wall"]
    rate = (run.learner.segments * a.segment_len - tally["env_steps_at_start"]) / max(seconds, 1e-9)
    per_cycle, per_eval = seconds / max(1, run.cycle), run.rows[-1]["time_eval"] if run.rows else 0.0
    epoch_left = per_cycle * (a.n_cycles - run.cycle) + per_eval
    run_left = epoch_left + (a.n_epochs - run.epoch - 1) * (per_cycle * a.n_cycles + per_eval)
    learning = learning_text(a, tally["losses"]["critic_loss"], run.learner.waiting)
    progress(f"  epoch {run.epoch} cycle {run.cycle}/{a.n_cycles} | {detail} | {learning} | train {rate:.0f} steps/s | "
             f"left: epoch {duration(epoch_left)}, run {duration(run_left)}")  # fmt: skip


def duration(seconds: float) -> str:
    """4:05 (minutes:seconds) or 3:04:05 (hours:minutes:seconds)."""
    m, s = divmod(round(seconds), 60)
    return f"{m // 60}:{m % 60:02d}:{s:02d}" if m >= 60 else f"{m}:{s:02d}"


# --- progress.csv and TensorBoard ----------------------------------------------------------------
class Logger:
    """progress.csv (one row per epoch) and TensorBoard scalars with the same names. On resume, both are
    rebuilt from the checkpoint's rows: an epoch logged after the checkpoint is dropped, one missing is
    written, so every epoch appears once whenever the run was stopped."""

    def __init__(self, run_dir: Path, rows: list[dict], resumed: bool):
        from torch.utils.tensorboard import SummaryWriter  # noqa: PLC0415 (slow import, only when training)

        self.path, self.rows = run_dir / "progress.csv", rows  # the run's rows (finish_epoch appends to them)
        if resumed:
            write_csv(self.path, rows)
        # TensorBoard hides the events of steps >= purge_step, then gets the last row again.
        purge = (rows[-1]["epoch"] if rows else 0) if resumed else None
        self.writer = SummaryWriter(str(run_dir), purge_step=purge)
        if resumed and rows:
            self.add_scalars(rows[-1])

    def log(self, row: dict):
        """The epoch's row, already the last of `rows`: progress.csv rewritten whole (write_csv: every column
        under its name, even after a resume from an older version whose rows have fewer), then TensorBoard."""
        write_csv(self.path, self.rows)
        self.add_scalars(row)

    def add_scalars(self, row: dict):
        for k, v in row.items():
            if k != "epoch":
                self.writer.add_scalar(tensorboard_tag(k), v, row["epoch"])
        self.writer.flush()

    def close(self):
        self.writer.close()


def tensorboard_tag(column: str) -> str:
    """A progress.csv column's TensorBoard name, grouped: eval/, losses/, graph/, time/, charts/, and
    sampler/ for the goal sampler's columns (whatever the others are not)."""
    if column == "global_sr" or (column.startswith("sr_") and column != "sr_classes"):
        return f"eval/{column}"
    if column in LOSSES:
        return f"losses/{column}"
    if column.startswith(("encounters_", "agent_nodes")) or column in ("agent_edges", "sr_classes"):
        return f"graph/{column}"
    if column.startswith("time_") or column == "steps_per_second":
        return f"time/{column}"
    return f"charts/{column}" if column in ("goals", "segments", "env_steps", "train_success") else f"sampler/{column}"


def write_csv(path: Path, rows: list[dict]):
    """progress.csv holding exactly these rows, written then renamed. Its columns: every row's, in the order of
    the newest (a run resumed from an older version's checkpoint has rows with fewer); a row without one: empty."""
    if not rows:  # stopped within the first epoch: no row yet, and no file (the next row writes the header)
        path.unlink(missing_ok=True)
        return
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(dict.fromkeys([k for r in rows[::-1] for k in r])), restval="")
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)


def progress(text: str, final: bool = False):
    """A live status line on a terminal; every line in a log file. Worker 0 speaks for all."""
    if rank() == 0:
        live = sys.stdout.isatty()  # the line rewritten in place until a final one
        print("\r" + text.ljust(100) if live else text, end="" if live and not final else "\n", flush=True)


# --- --eval-only: results and videos --------------------------------------------------------------
def write_video(path: Path, frames: list[np.ndarray], fps: float):
    """An H.264 mp4 through the ffmpeg binary that imageio-ffmpeg ships; written, then renamed."""
    import imageio_ffmpeg  # noqa: PLC0415 (needed only for --capture-video)

    tmp = path.with_name(path.stem + ".tmp.mp4")  # ffmpeg picks the container from the extension
    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, macro_block_size=1)
    writer.send(None)  # start ffmpeg
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()
    os.replace(tmp, path)


def rendering_problem() -> str | None:
    """Why MuJoCo cannot render on this machine, or None."""
    backend = os.environ.get("MUJOCO_GL")
    if backend is None and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        return "no display, and MUJOCO_GL is not set"
    import mujoco  # noqa: PLC0415 (needed only for --capture-video)

    hook, sys.unraisablehook = sys.unraisablehook, lambda _: None  # a failed Renderer complains when freed
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mujoco.Renderer(fetch5_env.build_model(og.MIN_BLOCKS), 8, 8).close()
    except Exception as e:  # noqa: BLE001 (any GL failure means: no backend here)
        return f"MUJOCO_GL={backend}: {type(e).__name__}: {' '.join(str(e).split())[:120]}"
    finally:
        gc.collect()
        sys.unraisablehook = hook
    return None


def claim_name(folder: Path, stem: str) -> Path:
    """folder/stem.json, or stem_2.json, stem_3.json...: the first name no earlier result holds, created
    empty (so two evaluations in one folder never overwrite each other)."""
    for n in itertools.count(1):
        path = folder / (f"{stem}.json" if n == 1 else f"{stem}_{n}.json")
        with contextlib.suppress(FileExistsError):
            path.open("x").close()
            return path


def evaluate_checkpoint(run, state: dict, evaluate, planner=None) -> int:
    """--eval-only: the saved agent's SR per class (SPEC §9) by the script's evaluate(run, video, planner),
    printed and saved as JSON beside the checkpoint (the paper's file: in --runs-dir), named after it; with
    --capture-video, an mp4 per class of its first evaluation episodes, in videos/ beside the JSON.
    `planner`: the graph that plans sub-goals instead of the agent's."""
    args = run.args
    state = {k: v for k, v in state.items() if k not in ("buffer", "rng", "env_rng")}  # no replay; its own seeds
    paper = state.get("format") == "paper"
    if paper:  # networks and normalizer are all it holds
        load_weights(run.learner.agent, state, args, args.checkpoint, "--checkpoint")
    else:
        restore(run, state, args.checkpoint, "--checkpoint")
    for w in run.workers:  # the evaluation's own seeds, not the run's
        w.seed(args.seed + w.index)
    video = {} if args.capture_video and rank() == 0 else None
    t = time.perf_counter()
    sr = evaluate(run, video, planner)
    if rank() > 0:
        return 0
    checkpoint = Path(args.checkpoint).resolve()
    agent = "paper" if paper else f"epoch{run.epoch}"  # the paper's file does not say its epoch
    # a run's checkpoint: beside it, in its run folder; the paper's file (`paper`: in the download cache) is no
    # run's: in --runs-dir, where a run's results are
    folder = Path(args.runs_dir).resolve() if paper else checkpoint.parent
    folder.mkdir(parents=True, exist_ok=True)
    out = claim_name(folder, f"eval_{checkpoint.stem}_{agent}_seed{args.seed}{'_oracle' * (args.plan_on == 'oracle')}")
    result = dict(checkpoint=str(checkpoint), agent="the paper's" if paper else "ours",
                  epoch=None if paper else run.epoch, seed=args.seed, goals_per_class=args.eval_goals_per_class,
                  planner=args.plan_on, sr=sr, seconds=time.perf_counter() - t)  # fmt: skip
    tmp = out.with_suffix(".tmp")
    try:
        tmp.write_text(json.dumps(result, indent=2))
        os.replace(tmp, out)
    except BaseException:  # Ctrl-C, a full disk: no empty result left behind
        out.unlink(missing_ok=True)
        tmp.unlink(missing_ok=True)
        raise
    print("\n".join(f"{name:>6}  SR {sr[name]:.3f}" for name in run.classes))
    who = "the paper's agent" if paper else f"epoch {run.epoch}"
    print(f"global  SR {sr['global']:.3f}  ({args.eval_goals_per_class} goals per class, {who}, "
          f"sub-goals planned on the {args.plan_on}'s graph)")  # fmt: skip
    print(f"saved {out}")
    for name, frames in (video or {}).items():
        path = folder / "videos" / f"{out.stem}_{name}.mp4"
        path.parent.mkdir(exist_ok=True)
        write_video(path, frames, fps=1 / run.workers[0].env.dt)
        print(f"video {path} ({len(frames)} frames)")
    return 0


# ------------------------------------------------------------------------------------------------
# Interruptions (plumbing): stop at a cycle boundary, so that a resumed run is the uninterrupted one
# ------------------------------------------------------------------------------------------------
class CycleGivenUp(Exception):  # noqa: N818 (not an error: the run stops as a stop request asked)
    """Raised by a goal sampler's cycle(w), before the cycle's segments are learnt from, when a stop request
    ends a wait (a person's answer): RunFolder.cycle checkpoints the state from before that cycle."""


class Stopper:
    """Ctrl-C (SIGINT) or SIGTERM asks the run to stop at the next cycle boundary, where a checkpoint
    holds everything the rest of the run depends on. During an evaluation (one process) it stops at
    once, saving the state from before the evaluation. A second signal aborts at once; the last
    checkpoint stays as it was (saves are atomic)."""

    def __init__(self, tmp: Path):
        self.tmp, self.requested, self.abortable_now = tmp, False, False
        # set even if a parent started us with SIGINT ignored; the handlers before, which RunFolder gives back
        self.before = {sig: signal.signal(sig, self.handle) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handle(self, signum, frame):
        name = signal.Signals(signum).name
        if self.requested:
            self.tmp.unlink(missing_ok=True)
            os.write(2, f"\naborted by a second {name}: the last checkpoint is kept as it was\n".encode())
            os._exit(130)
        self.requested = True
        if rank() == 0:  # os.write: print() inside a signal handler can meet a print it interrupted
            os.write(2, f"\n{name}: stopping at the next cycle boundary with a checkpoint (again: abort)\n".encode())
        if self.abortable_now:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def abortable(self, allowed: bool):
        """Within this block a stop request interrupts at once (if allowed)."""
        if allowed and self.requested:
            raise KeyboardInterrupt
        self.abortable_now = allowed
        try:
            yield
        finally:
            self.abortable_now = False

    def agreed(self) -> bool:
        """Whether any worker was asked to stop: every worker stops at the same cycle."""
        return bool(all_sum(np.array([float(self.requested)]))[0] > 0)


# ------------------------------------------------------------------------------------------------
# The top level's steps (plumbing): what a script's main calls, in order
# ------------------------------------------------------------------------------------------------
def parse_command_line(Args: type, check_sampler_args, argv=None):
    """(args, state, init): the script's Args from the command line, with the checkpoint the flags name
    loaded and checked (state: --resume's or --eval-only's; init: --init-from's), or exit 2 with one line.
    args is None when --resume has nothing left to train (said so). --eval-only's args hold what the
    evaluation needs: a replay of one segment, the checkpoint's run with this command line's evaluation flags."""
    args, state, init = parse_args(Args, check_sampler_args, argv), None, None
    for flag, field in (("--init-from", "init_from"), ("--checkpoint", "checkpoint")):
        if getattr(args, field) == "paper":  # every other flag checked first: a bad one downloads nothing
            args = dataclasses.replace(args, **{field: paper_file(flag)})
    if args.resume or args.eval_only:
        flag, path = ("--resume", args.resume) if args.resume else ("--checkpoint", args.checkpoint)
        state = load_checkpoint(Args, path, flag)
        if state.get("format") == "paper" and args.resume:
            checkpoint_error(flag, path, "the paper's agent, not a run: train from it with --init-from PATH")
        if state.get("format") == "paper":
            args = args_with_blocks_of(args, given_flags(Args, argv), state, path, flag)
        else:
            args = args_from_checkpoint(args, given_flags(Args, argv), state, flag)
            if (why := check_sampler_args(args)) is not None:  # the checkpoint's options, in this job
                fail(f"{flag}: {why}")
        if args.resume and state["counters"]["epoch"] >= args.n_epochs:
            print(f"nothing to do: {args.resume} has finished epoch {state['counters']['epoch'] - 1} "
                  f"(--n-epochs {args.n_epochs}); give a larger --n-epochs to train on")  # fmt: skip
            return None, None, None
    elif args.init_from:
        init = load_checkpoint(Args, args.init_from, "--init-from")
        given = given_flags(Args, argv)
        args = args_with_blocks_of(args, given, init, args.init_from, "--init-from")
        if "freeze_normalizer" not in given:  # fine-tuning keeps the file's statistics (--no-freeze-normalizer: not)
            args = dataclasses.replace(args, freeze_normalizer=True)
    if args.capture_video and (why := rendering_problem()):  # every worker: all leave together
        fail(f"--capture-video: MuJoCo cannot render here ({why}); install Debian's libosmesa6 and set "
             "MUJOCO_GL=osmesa (MUJOCO_GL=egl on a GPU machine)")  # fmt: skip
    if args.eval_only:  # evaluation stores no segment
        args = dataclasses.replace(args, buffer_size=args.segment_len)
    return args, state, init


class RunFolder(contextlib.AbstractContextManager):  # `with`: itself
    """A training run's outputs and stops (SPEC §10): the run restored from --resume's checkpoint (or started
    from --init-from's networks), in that checkpoint's folder or a new one, runs/{exp_name}__{seed}__{time},
    holding config.json; progress.csv and TensorBoard (process 0); the checkpoint; the Stopper that Ctrl-C
    and SIGTERM talk to. A context: the logs are closed at its end."""

    def __init__(self, run, state: dict | None, init: dict | None = None):
        args, agent = run.args, run.learner.agent
        lrs = [opt.defaults["lr"] for opt in (agent.actor_opt, agent.critic_opt)]  # what Adam was given (SPEC §12)
        precision, why = speed.precision_of(args)  # SPEC §12: the default ('') is this machine's
        if state is not None:
            restore(run, state, args.resume, "--resume")
            progress(f"resumed {args.resume} at epoch {run.epoch}, cycle {run.cycle}", final=True)
            if (warning := version_warning(state)) and rank() == 0:
                print(warning, file=sys.stderr, flush=True)
        if init is not None:  # before the folder: a file that does not fit exits 2 with nothing written
            load_weights(agent, init, args, args.init_from, "--init-from")
        if state is not None:
            self.dir = Path(args.resume).resolve().parent
        else:
            self.dir = Path(args.runs_dir) / f"{args.exp_name}__{args.seed}__{int(time.time())}"
            if rank() == 0:
                try:
                    self.dir.mkdir(parents=True, exist_ok=True)
                except OSError as e:
                    fail(f"--runs-dir {args.runs_dir!r}: cannot create {str(self.dir)!r}: {e}")
                config = dict(dataclasses.asdict(args), workers=run.n_workers, adam_rates=lrs, precision=precision)
                if args.init_from:  # which file (the paper's agent is not in the repository: its hash names it)
                    with open(args.init_from, "rb") as f:
                        config["init_from_sha256"] = hashlib.file_digest(f, "sha256").hexdigest()
                (self.dir / "config.json").write_text(json.dumps(config, indent=2))
        if init is not None:
            progress(f"initialized from {args.init_from} (its networks and normalizer; the rest is new)", final=True)
        self.logger = Logger(self.dir, run.rows, resumed=state is not None) if rank() == 0 else None
        self.checkpoint, self.stopper = self.dir / "checkpoint.pt", Stopper(self.dir / "checkpoint.pt.tmp")
        self.saved_at, self.before_evaluation, self.before_cycle = None, None, None  # see end_epoch, evaluate, cycle
        whys = [why for _, why in adam_rates(args)] if state is None else ["the run's own"] * 2  # as it began
        self.overlap, how = speed.overlap_of(run)  # with it, unless --threads, torch's threads: one
        progress(f"run folder {self.dir} | {args.n_blocks} blocks | {run.n_workers} worker(s) on {agent.device} | "
                 f"rates {rates_text(lrs, whys)} | precision {precision} ({why}) | {how}", final=True)  # fmt: skip
        self.run, self.sampler = run, run.sampler
        self.sampler.open(self.dir, lambda: self.stopper.requested)  # its own files; whether to stop waiting

    def __exit__(self, *exc):
        self.sampler.close()
        speed.close_updates(self.run)  # --overlap's process
        if self.logger is not None:
            self.logger.close()
        for sig, handler in self.stopper.before.items():  # main()'s caller (Python's) gets its own back
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)  # None: set outside Python

    def stop_requested(self) -> bool:
        """Whether Ctrl-C or SIGTERM reached any process: all stop at the same cycle boundary."""
        return self.stopper.agreed()

    def cycle(self, run, one_cycle) -> bool:
        """one_cycle(run); False if the goal sampler gave it up (CycleGivenUp: a stop request while it waited,
        for a person's answer, person_partner.py): the checkpoint stop() saves is then the state from before
        the cycle, and --resume runs the cycle again. Only for a sampler that says it may (its gives_up_cycles),
        in one process, as a person partner is."""
        gives_up = world() == 1 and run.sampler.gives_up_cycles
        self.before_cycle, t = save_state(run) if gives_up else None, time.perf_counter()  # cheap: views
        try:
            speed.overlapped_cycle(run, sys.modules[one_cycle.__module__]) if self.overlap else one_cycle(run)
        except CycleGivenUp:
            if self.before_cycle is None:
                raise
            return False
        self.before_cycle, run.tally["wall"] = None, run.tally["wall"] + time.perf_counter() - t
        return True

    def evaluate(self, run, evaluate) -> dict | None:
        """evaluate(run), timed for the epoch's row. In one process a stop request ends it at once: None,
        and the checkpoint stop() saves is the state from before it (under torchrun the processes finish it)."""
        self.before_evaluation, t = save_state(run) if world() == 1 else None, time.perf_counter()  # cheap: views
        try:
            with self.stopper.abortable(allowed=self.before_evaluation is not None):
                sr = evaluate(run)
        except KeyboardInterrupt:
            return None
        run.tally["eval"], self.before_evaluation = time.perf_counter() - t, None
        return sr

    def end_epoch(self, run, sr: dict[str, float]):
        """The epoch's row (finish_epoch); a checkpoint, then the row in progress.csv and TensorBoard (a
        row is never logged unless a checkpoint holds it); the console's epoch line."""
        row = finish_epoch(run, sr)
        if self.logger is not None:
            save_checkpoint(save_state(run), self.checkpoint)
            self.logger.log(row)
        self.saved_at = (run.epoch, run.cycle)
        per_class = " ".join(f"{k} {sr[k]:.2f}" for k in run.classes)
        waiting = run.learner.waiting  # --init-learning-starts: the replays still filling
        learned = f"{learning_text(run.args, math.nan, waiting)} | " if run.args.n_updates == 0 or waiting else ""
        progress(f"epoch {row['epoch']:3d} | steps {row['env_steps']:,} | SR {sr['global']:.3f} | {per_class} | "
                 f"{learned}"
                 f"{row['steps_per_second']:.0f} steps/s | {row['time_epoch']:.0f} s",
                 final=True)  # fmt: skip

    def stop(self, run) -> int:
        """Stopped on request: process 0 saves the checkpoint --resume continues from (where the run stands,
        or the state before an evaluation the request interrupted; nothing if the last checkpoint holds it)
        and says how to resume; exit code 130."""
        if rank() == 0:
            state = self.before_evaluation if self.before_evaluation is not None else self.before_cycle
            if state is None and self.saved_at != (run.epoch, run.cycle):
                state = save_state(run)
            if state is not None:
                save_checkpoint(state, self.checkpoint)
            c = state["counters"] if state is not None else dict(epoch=run.epoch, cycle=run.cycle)
            print(f"interrupted: checkpoint saved to {self.checkpoint} (epoch {c['epoch']}, cycle {c['cycle']}); "
                  f"continue with --resume {self.checkpoint}", flush=True)  # fmt: skip
        return 130


def leave(code: int):
    """Exit with code. A distributed worker leaves through os._exit, its outputs flushed and closed:
    at interpreter exit, gloo's worker thread could abort the process (SIGABRT) after all the work."""
    if processes() > 1:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


@contextlib.contextmanager
def job(args):
    """init_workers; at the end, however it ends, the torchrun job (if any) is left."""
    device = init_workers(args)
    try:
        yield device
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def run_main(main):
    """A script's `if __name__ == "__main__"`: main(), then exit with its code (130 for a Ctrl-C, or a SIGTERM
    during the paper's download, before the run could stop at a cycle boundary: nothing to save yet)."""
    try:
        code = main()
    except KeyboardInterrupt:
        print("interrupted (nothing to save yet)", file=sys.stderr)
        code = 130
    leave(code)
