"""Do 2-worker runs exit cleanly? Launches many tiny `torchrun --nproc-per-node 2` runs of each training
script and counts their exit codes (the defect it checks: gloo's worker thread could abort the interpreter's exit with
SIGABRT after all the work was done). Not part of the test suite: 300 runs take about half an hour.

    python benchmarks/stress_workers.py [--runs 100] [--scripts gangstr_hme.py lp_baseline.py vds_baseline.py]
"""

import argparse
import collections
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "2", "--n-segments", "2", "--n-updates", "2",
        "--batch-size", "32", "--segment-len", "10", "--stable-steps", "3", "--eval-goals-per-class", "1",
        "--threads", "1"]  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100, help="runs per script")
    parser.add_argument("--scripts", nargs="+", default=["gangstr_hme.py", "lp_baseline.py", "vds_baseline.py"])
    args = parser.parse_args()
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]  # = torchrun
    for script in args.scripts:
        codes, t = collections.Counter(), time.perf_counter()
        for i in range(args.runs):
            with tempfile.TemporaryDirectory() as runs:
                out = subprocess.run([*torchrun, script, *TINY, "--runs-dir", runs], cwd=ROOT, capture_output=True,
                                     text=True, timeout=600)  # fmt: skip
            codes[out.returncode] += 1
            if out.returncode != 0:
                print(f"{script} run {i}: exit {out.returncode}\n{out.stderr[-2000:]}", flush=True)
        print(f"{script}: {codes[0]} of {args.runs} runs exited 0 {dict(codes)} "
              f"({(time.perf_counter() - t) / args.runs:.1f} s a run)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
