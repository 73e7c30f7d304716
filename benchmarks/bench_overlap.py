"""What --overlap buys a cycle (docs/speed.md): a learner of gangstr_hme.py with the main job's settings (SP-20%,
one worker, the paper's cycle of 10 segments and 30 updates of 256), built in this process, its cycles timed one
after the other (one_cycle, --no-overlap) with torch on 1 and on 2 threads, and with the updates beside the
collection (speed.overlapped_cycle, --overlap: in a process of their own, torch on 1 thread in each, a core each;
and on 2 threads in each, --overlap --threads 2).
Each condition's seconds a cycle (the median over --cycles cycles after --warmup ones), and the overlap's speed-up
over each. Conditions run one after the other, in turn, --repeats times; medians, and each repeat's ratios (the
machine's speed drifts).

    python benchmarks/bench_overlap.py [--n-blocks 3 5] [--precision fp32 bf16] [--cycles 8] [--repeats 2]
"""

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import gangstr_hme as gh  # noqa: E402
import speed  # noqa: E402

MODES = {"one after the other, 1 thread": (False, 1), "one after the other, 2 threads": (False, 2),
         "overlap, 1 thread": (True, 1), "overlap, 2 threads": (True, 2)}  # fmt: skip


def cycle_seconds(n_blocks: int, precision: str, overlap: bool, threads: int, args) -> float:
    """The median wall seconds of a training cycle."""
    torch.set_num_threads(threads)
    torch.manual_seed(args.seed)
    cfg = gh.Args(n_blocks=n_blocks, sp_ratio=0.2, seed=args.seed, precision=precision, threads=threads,
                  overlap=overlap)  # fmt: skip
    run, seconds = gh.Run(cfg, torch.device("cpu")), []
    try:
        for cycle in range(args.warmup + args.cycles):
            t = time.perf_counter()
            speed.overlapped_cycle(run, gh) if overlap else gh.one_cycle(run)
            if cycle >= args.warmup:
                seconds.append(time.perf_counter() - t)
    finally:
        speed.close_updates(run)
    return statistics.median(seconds)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n-blocks", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--precision", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    parser.add_argument("--cycles", type=int, default=8, help="timed training cycles (after --warmup)")
    parser.add_argument("--warmup", type=int, default=3, help="cycles first, untimed: the replay holds segments")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(speed.cpu_line())
    cases = list(itertools.product(args.n_blocks, args.precision))
    got: dict[tuple, list[float]] = {(*c, m): [] for c in cases for m in MODES}
    for _ in range(args.repeats):
        for (blocks, precision), mode in itertools.product(cases, MODES):
            got[blocks, precision, mode].append(cycle_seconds(blocks, precision, *MODES[mode], args))
    for blocks, precision in cases:
        print(f"\n{blocks} blocks, {precision}: seconds a cycle, median of {args.repeats}")
        overlapped = got[blocks, precision, "overlap, 1 thread"]
        for mode in MODES:
            times = got[blocks, precision, mode]
            ratios = ", ".join(f"{a / b:.2f}" for a, b in zip(times, overlapped, strict=True))
            print(f"  {mode:32s} {statistics.median(times):6.3f} s   overlap's speed-up, each repeat: {ratios}")


if __name__ == "__main__":
    main()
