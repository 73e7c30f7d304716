"""Throughput of several workers (SPEC §11): collected env steps and updated samples per wall second of
whole training cycles (collection, graph updates and SAC updates; no evaluation), medians over repeats;
then the seconds of one cycle of the paper's 24-worker configuration in one process, and where they go.

Each repeat of the first part is a fresh run of gangstr_hme.py for one epoch of --n-cycles cycles with
the paper's settings otherwise (5 blocks, 10 segments and 30 updates of batch 256 per cycle and
worker), read from its progress.csv: the epoch's wall seconds less its evaluation's (which include the
first cycle's wait for the updates' process to start, with --overlap). Conditions, interleaved so that
drifts in machine load hit each: one process with one worker, its updates beside its collection
(--overlap, the default) or after it on torch's threads (--no-overlap); one process with two workers
(--num-envs 2); two processes of one worker (`torchrun --nproc-per-node 2 ... --threads 1`). Updated
samples count each worker's: torchrun's summed update is 2 x 256 of them.

The second part builds a 24-worker learner in this process (--num-envs 24) and times --cycles-24
cycles after a first one (which fills the replays), split into acting (the batched forward passes),
physics (the envs' steps), planning and graph updates, SAC updates (each over 24 x 256 samples), and
the rest (the workers' programs, segment bookkeeping, replay stores, normalizer); with --cuda, the peak GPU memory.

    python benchmarks/bench_scaling.py [--n-cycles 10] [--repeats 3] [--n-blocks 5] [--cycles-24 2] [--cuda]
                                       [--precision bf16]
"""

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import gangstr_hme as gh  # noqa: E402
import plumbing  # noqa: E402
import speed  # noqa: E402


def per_second(launcher: list[str], flags: list[str], workers: int, args) -> tuple[float, float]:
    """Env steps and updated samples per wall second of one run's cycles."""
    with tempfile.TemporaryDirectory() as runs:
        cmd = [*launcher, "gangstr_hme.py", "--n-blocks", str(args.n_blocks), "--n-epochs", "1",
               "--n-cycles", str(args.n_cycles), "--eval-goals-per-class", "1", "--no-save-buffer",
               "--runs-dir", runs, "--precision", args.precision, *flags]  # fmt: skip
        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True)
        (progress,) = Path(runs).glob("*/progress.csv")
        with progress.open() as f:
            row = next(csv.DictReader(f))  # collection and updates only, not the evaluation
        seconds = float(row["time_epoch"]) - float(row["time_eval"])
        return float(row["env_steps"]) / seconds, workers * args.n_cycles * 30 * 256 / seconds


def timed(seconds: dict, key: str, fn):
    def wrapper(*a, **kw):
        t = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            seconds[key] += time.perf_counter() - t

    return wrapper


def cycle_profile(args) -> tuple[float, dict]:
    """Seconds per cycle of --num-envs 24 in this process, and their split."""
    cfg = gh.Args(n_blocks=args.n_blocks, num_envs=24, sp_ratio=0.2, cuda=args.cuda, seed=0, precision=args.precision)
    torch.manual_seed(0)
    run = gh.Run(cfg, plumbing.init_workers(cfg))
    learner = run.learner
    seconds = dict.fromkeys(["acting", "physics", "SAC updates"], 0.0)
    learner.agent.act = timed(seconds, "acting", learner.agent.act)
    speed.step_envs = timed(seconds, "physics", speed.step_envs)  # run_segments looks it up at call time
    learner.train = timed(seconds, "SAC updates", learner.train)

    def one_cycle():
        gh.one_cycle(run)  # collect, learn_from, the SAC updates
        if args.cuda:
            torch.cuda.synchronize()

    one_cycle()  # fills the replays; compiles nothing, but warms caches and allocators
    for k in seconds:
        seconds[k] = 0.0
    learner.plan_seconds = 0.0
    t = time.perf_counter()
    for _ in range(args.cycles_24):
        one_cycle()
    total = (time.perf_counter() - t) / args.cycles_24
    split = {k: v / args.cycles_24 for k, v in seconds.items()}
    split["planning + graph"] = learner.plan_seconds / args.cycles_24
    split["rest"] = total - sum(split.values())
    return total, split


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-cycles", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--n-blocks", type=int, default=5)
    parser.add_argument("--cycles-24", type=int, default=2, help="timed cycles of the 24-worker learner")
    parser.add_argument("--cuda", action="store_true", help="the 24-worker learner on the GPU")
    parser.add_argument("--skip-scaling", action="store_true", help="only the 24-worker cycle")
    parser.add_argument("--skip-24", action="store_true", help="only the 1- and 2-worker conditions")
    parser.add_argument("--precision", default="fp32", choices=["fp32", "bf16"], help="the update's (docs/speed.md)")
    args = parser.parse_args()
    print(speed.cpu_line())
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]  # = torchrun
    conditions = {  # name: launcher, flags, workers
        "1 process, 1 worker (--overlap)": ([sys.executable], ["--num-envs", "1"], 1),
        "1 process, 1 worker (--no-overlap)": ([sys.executable], ["--num-envs", "1", "--no-overlap"], 1),
        "1 process, 2 workers (--num-envs 2)": ([sys.executable], ["--num-envs", "2"], 2),
        "2 processes x 1 worker (torchrun)": (torchrun, ["--threads", "1"], 2),
    }
    if not args.skip_scaling:
        results = {}
        for _ in range(args.repeats):
            for name, (launcher, flags, workers) in conditions.items():
                results.setdefault(name, []).append(per_second(launcher, flags, workers, args))
        print(f"{args.n_blocks} blocks, {args.precision}, {args.n_cycles} cycles a run, median of {args.repeats} runs")
        med = {}
        for name, v in results.items():
            med[name] = [statistics.median(x[i] for x in v) for i in (0, 1)]
            runs = ", ".join(f"{x[0]:.0f}" for x in v)
            print(f"  {name:38s} {med[name][0]:5.0f} env steps/s (runs: {runs}), {med[name][1]:6.0f} samples updated/s")
        one = med["1 process, 1 worker (--overlap)"]
        for name, (steps, samples) in med.items():
            print(f"  {name:38s} {steps / one[0]:.2f}x the env steps, {samples / one[1]:.2f}x the samples of --overlap")
    if args.skip_24:
        return
    total, split = cycle_profile(args)
    device = torch.cuda.get_device_name() if args.cuda else f"CPU, {torch.get_num_threads()} torch threads"
    print(f"24 workers in one process ({device}): {total:.2f} s per cycle "
          f"(mean of {args.cycles_24}; 24 x 10 segments x 40 steps, 30 updates of 24 x 256)")  # fmt: skip
    for k, v in split.items():
        print(f"  {k:18s} {v:7.2f} s  {100 * v / total:5.1f}%")
    if args.cuda:  # the 24 workers' networks, optimizers and update activations (replays stay in host memory)
        print(f"  peak GPU memory    {torch.cuda.max_memory_allocated() / 2**30:7.2f} GiB")


if __name__ == "__main__":
    main()
