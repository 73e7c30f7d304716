"""Throughput with 1 and 2 workers (SPEC §11): collected env steps per second of whole training cycles
(collection, graph updates and SAC updates; no evaluation), medians over repeats.

Each repeat is a fresh run of gangstr_hme.py for one epoch of --n-cycles cycles with the paper's
settings otherwise (5 blocks, 10 segments and 30 updates of batch 256 per cycle and worker), read
from its progress.csv. Conditions: one process with all cores for torch, one process with one
thread, and `torchrun --nproc-per-node 2` with one thread per worker.

    python benchmarks/bench_scaling.py [--n-cycles 10] [--repeats 3] [--n-blocks 5]
"""

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def steps_per_second(launcher: list[str], threads: int, args) -> float:
    with tempfile.TemporaryDirectory() as runs:
        cmd = [*launcher, "gangstr_hme.py", "--n-blocks", str(args.n_blocks), "--n-epochs", "1",
               "--n-cycles", str(args.n_cycles), "--eval-goals-per-class", "1", "--threads", str(threads),
               "--no-save-buffer", "--runs-dir", runs]  # fmt: skip
        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True)
        (progress,) = Path(runs).glob("*/progress.csv")
        with progress.open() as f:
            row = next(csv.DictReader(f))  # collection and updates only, not the evaluation
            return float(row["env_steps"]) / (float(row["time_collect"]) + float(row["time_update"]))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-cycles", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--n-blocks", type=int, default=5)
    args = parser.parse_args()
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]  # = torchrun
    conditions = {
        "1 process, all cores": ([sys.executable], 0),
        "1 process, 1 thread": ([sys.executable], 1),
        "2 workers (torchrun), 1 thread each": (torchrun, 1),
    }
    results = {}
    for _ in range(args.repeats):  # interleaved, so that drifts in machine load hit every condition
        for name, (launcher, threads) in conditions.items():
            results.setdefault(name, []).append(steps_per_second(launcher, threads, args))
    med = {name: statistics.median(v) for name, v in results.items()}
    print(f"{args.n_blocks} blocks, {args.n_cycles} cycles per run, median of {args.repeats} runs")
    for name, v in med.items():
        print(f"  {name:38s} {v:7.0f} env steps/s   (runs: {', '.join(f'{x:.0f}' for x in results[name])})")
    two = med["2 workers (torchrun), 1 thread each"]
    print(f"  ratio 2 workers / 1 process, all cores: {two / med['1 process, all cores']:.2f}x")
    print(f"  ratio 2 workers / 1 process, 1 thread:  {two / med['1 process, 1 thread']:.2f}x")


if __name__ == "__main__":
    main()
