"""Stop a run at random moments and resume it: is the result the uninterrupted run? For each of SIGINT,
SIGTERM and kill -9, --trials runs of tests/test_gangstr.py's STOPPED configuration (1 process, CPU,
fixed seed, the social partner on) are stopped at a random moment after their first checkpoint, and
--write-trials more the moment a checkpoint write begins (checkpoint.pt.tmp appears); each is resumed
to the end and its progress.csv compared with the uninterrupted run's in every non-timing column, with
every epoch once. Not part of the test suite (the suite stops one run per signal).

    python benchmarks/stress_interrupts.py [--trials 10] [--write-trials 4]
"""

import argparse
import csv
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_gangstr import STOPPED, TIMING  # noqa: E402


def rows(run: Path) -> list[dict]:
    with (run / "progress.csv").open() as f:
        return [{k: v for k, v in r.items() if not k.startswith(TIMING)} for r in csv.DictReader(f)]


def run_to_end(runs: Path, sig: signal.Signals | None, moment: str, rng: random.Random) -> tuple[list[dict], str]:
    cmd = [sys.executable, "-u", "gangstr_hme.py", *STOPPED, "--runs-dir", str(runs)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    what = "not stopped"
    if sig is not None:
        for line in proc.stdout:
            if line.startswith("epoch   0"):  # the first checkpoint exists
                break
        (run,) = runs.iterdir()
        if moment == "write":
            while proc.poll() is None and not (run / "checkpoint.pt.tmp").exists():
                time.sleep(0.0002)
        else:
            time.sleep(rng.uniform(0.0, 1.5))
        during_write = (run / "checkpoint.pt.tmp").exists()
        proc.send_signal(sig)
        what = f"exit {proc.wait(timeout=120)}" + (" (signal during a checkpoint write)" if during_write else "")
    proc.communicate(timeout=120)
    (run,) = runs.iterdir()
    if proc.returncode != 0:
        out = subprocess.run([sys.executable, "gangstr_hme.py", "--resume", str(run / "checkpoint.pt")], cwd=ROOT,
                             capture_output=True, text=True, timeout=300)  # fmt: skip
        assert out.returncode == 0, out.stderr
    return rows(run), what


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10, help="random moments per signal")
    parser.add_argument("--write-trials", type=int, default=4, help="moments a checkpoint write begins, per signal")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        reference, _ = run_to_end(Path(tmp) / "reference", None, "", rng)
        failures = 0
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            for k, moment in enumerate(["random"] * args.trials + ["write"] * args.write_trials):
                got, what = run_to_end(Path(tmp) / f"{sig.name}_{k}", sig, moment, rng)
                ok = got == reference
                failures += not ok
                print(f"{sig.name:8s} {moment:6s} {what:50s} {'same rows' if ok else 'DIFFERENT ROWS'}", flush=True)
        n = 3 * (args.trials + args.write_trials)
        print(f"{n - failures} of {n} stopped runs resumed into the uninterrupted run ({len(reference)} epochs each)")
    os._exit(1 if failures else 0)


if __name__ == "__main__":
    main()
