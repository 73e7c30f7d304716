"""Stop a run at random moments and resume it: is the result the uninterrupted run? For each of SIGINT,
SIGTERM and kill -9, --trials runs of tests/test_gangstr.py's STOPPED configuration (1 process, CPU,
fixed seed, the social partner on) are stopped at a random moment (a random cycle of a random epoch,
plus a random delay), and --write-trials more the moment a checkpoint write begins
(checkpoint.pt.tmp appears); each is resumed to the end, and its progress.csv (every non-timing
column) and TensorBoard rows are compared with the uninterrupted run's, every epoch once. Prints each
trial's exit code; not part of the test suite (which stops one run per signal).

With --person, a person partner instead (tests/test_person_stops.py's run, a scripted person answering the
page the same way in every run): each trial stops the run while a random question waits (kill -9: one
after the first epoch's checkpoint), resumes it with the same person, and checks that the resumed run asks
that question again, then the uninterrupted run's questions, and that its progress.csv and picks.csv are
the uninterrupted run's in every non-timing column.

    python benchmarks/stress_interrupts.py [--trials 10] [--write-trials 4] [--num-envs 1]
    python benchmarks/stress_interrupts.py --person [--trials 10]
"""

import argparse
import collections
import csv
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
from test_gangstr import STOPPED, TIMING, tensorboard_rows  # noqa: E402
from test_person_stops import FLAGS as PERSON  # noqa: E402
from test_person_stops import outputs, start  # noqa: E402

EPOCHS, CYCLES = 6, 3  # STOPPED's
WORKERS = ["--num-envs", "1"]  # workers in the process (--num-envs)


def rows(run: Path) -> list[dict]:
    with (run / "progress.csv").open() as f:
        return [{k: v for k, v in r.items() if not k.startswith(TIMING)} for r in csv.DictReader(f)]


def trial(runs: Path, sig: signal.Signals | None, moment: str, rng: random.Random) -> tuple[Path, str]:
    """Run STOPPED, stop it with sig at the moment, resume it to the end; (run folder, what happened)."""
    cmd = [sys.executable, "-u", "gangstr_hme.py", *STOPPED, *WORKERS, "--runs-dir", str(runs)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    what = ""
    if sig is not None:
        first = 1 if sig == signal.SIGKILL else 0  # kill -9 needs an epoch's checkpoint to resume from
        at = "epoch   0" if moment == "write" else f"  epoch {rng.randint(first, EPOCHS - 2)} cycle "
        at += "" if moment == "write" else f"{rng.randint(1, CYCLES)}/{CYCLES}"
        for line in proc.stdout:
            if line.startswith(at):
                break
        (run,) = runs.iterdir()
        if moment == "write":  # the next checkpoint write
            while proc.poll() is None and not (run / "checkpoint.pt.tmp").exists():
                time.sleep(0.0001)
        else:
            time.sleep(rng.uniform(0.0, 0.3))
        during_write = (run / "checkpoint.pt.tmp").exists()
        proc.send_signal(sig)
        what = f"at '{at.strip()}': exit {proc.wait(timeout=120)}" + (", during a checkpoint write" * during_write)
    proc.communicate(timeout=120)
    (run,) = runs.iterdir()
    if proc.returncode != 0:
        out = subprocess.run([sys.executable, "gangstr_hme.py", "--resume", str(run / "checkpoint.pt")], cwd=ROOT,
                             capture_output=True, text=True, timeout=300)  # fmt: skip
        assert out.returncode == 0, out.stderr
    return run, what


def person_run(runs: Path, sig: signal.Signals | None = None, at: int = 0) -> tuple[tuple, list[dict], str]:
    """Run PERSON with a scripted person; with sig, stop it by sig while question `at` waits, then resume it
    with the same person. ((progress rows, picks rows), the questions the last run asked, what happened)."""
    runs.mkdir(parents=True)
    waiting = []
    proc, person, _ = start(runs, *PERSON, stop_at=at, stop=lambda p, q: [waiting.append(q), p.send_signal(sig)])
    code, what = proc.wait(timeout=300), ""
    person.join(10)
    if sig is not None:
        q = waiting[0] if waiting else None
        what = f"question {at}" + (f" (epoch {q['epoch']} cycle {q['cycle']})" if q else " never asked")
        (run,) = [p for p in runs.iterdir() if p.is_dir()]
        proc, person, _ = start(runs, "--resume", str(run / "checkpoint.pt"))
        what += f": exit {code}, resumed: exit {proc.wait(timeout=300)}"
        person.join(10)
        what += ", asked again" if q is not None and q in person.asked else ", NOT ASKED AGAIN"
    return outputs(runs), person.asked, what


def person_trials(trials: int, rng: random.Random) -> int:
    """--person: every signal stops `trials` runs while a random question waits."""
    with tempfile.TemporaryDirectory() as tmp:
        expected, asked, _ = person_run(Path(tmp) / "reference")
        after_checkpoint = [q["id"] for q in asked if q["epoch"] >= 1]  # kill -9 resumes from epoch 0's checkpoint
        good = 0
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            for k in range(trials):
                at = rng.choice(after_checkpoint if sig == signal.SIGKILL else [q["id"] for q in asked])
                got, again, what = person_run(Path(tmp) / f"{sig.name}_{k}", sig, at)
                same = got == expected and again == asked[len(asked) - len(again) :] and "asked again" in what
                good += same
                print(f"{sig.name:8s} {what:75s} {'same rows' if same else 'DIFFERENT ROWS'}", flush=True)
        print(f"uninterrupted run: {len(asked)} questions, {len(expected[0])} epochs")
        print(f"{good} of {3 * trials} runs stopped while a question waited resumed into the uninterrupted run")
    return 0 if good == 3 * trials else 1


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10, help="random moments per signal")
    parser.add_argument("--write-trials", type=int, default=4, help="moments a checkpoint write begins, per signal")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-envs", type=int, default=1, help="workers in the process")
    parser.add_argument("--person", action="store_true", help="a person partner, stopped while a question waits")
    args = parser.parse_args()
    if args.person:
        sys.exit(person_trials(args.trials, random.Random(args.seed)))
    WORKERS[1] = str(args.num_envs)
    rng, outcomes = random.Random(args.seed), collections.Counter()
    with tempfile.TemporaryDirectory() as tmp:
        reference = trial(Path(tmp) / "reference", None, "", rng)[0]
        expected = (rows(reference), tensorboard_rows(reference))
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            for k, moment in enumerate(["random"] * args.trials + ["write"] * args.write_trials):
                run, what = trial(Path(tmp) / f"{sig.name}_{k}", sig, moment, rng)
                same = (rows(run), tensorboard_rows(run)) == expected
                outcomes[sig.name, what.split("exit ")[1].split(",")[0], "write" in what, same] += 1
                print(f"{sig.name:8s} {what:60s} {'same rows' if same else 'DIFFERENT ROWS'}", flush=True)
        print(f"uninterrupted run: {len(expected[0])} epochs")
        for (name, code, write, same), n in sorted(outcomes.items()):
            print(f"{name:8s} exit {code:4s} {'during a write' if write else '              '} "
                  f"{'same rows' if same else 'DIFFERENT ROWS'}: {n}")  # fmt: skip
        n = 3 * (args.trials + args.write_trials)
        good = sum(v for k, v in outcomes.items() if k[3])
        print(f"{good} of {n} stopped runs resumed into the uninterrupted run")
    sys.exit(0 if good == n else 1)


if __name__ == "__main__":
    main()
