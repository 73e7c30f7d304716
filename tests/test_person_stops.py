"""A stop while the page shows a question (--partner person): Ctrl-C, SIGTERM and kill -9 stop the run as
they stop any run, and --resume asks that question again. With a person who answers the same way, the
resumed run's progress.csv and picks.csv are the uninterrupted run's in every non-timing column.
(benchmarks/stress_interrupts.py --person: many moments.)"""

import csv
import json
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from test_gangstr import TIMING

pytestmark = pytest.mark.xdist_group("person_stops")  # under -n 2, on one worker: the uninterrupted run made once
ROOT = Path(__file__).resolve().parent.parent
FLAGS = ["--partner", "person", "--person-port", "0", "--person-timeout", "60", "--sp-ratio", "1", "--n-blocks", "3",
         "--n-epochs", "2", "--n-cycles", "3", "--n-segments", "2", "--n-updates", "1", "--batch-size", "16",
         "--segment-len", "6", "--stable-steps", "3", "--eval-goals-per-class", "1", "--threads", "1"]  # fmt: skip
AT = (1, 1)  # the stop comes at this (epoch, cycle)'s last question: mid-epoch, after epoch 0's checkpoint (which
# kill -9 resumes from), and after questions answered earlier in the cycle (the cycle --resume runs again)


def choose(q: dict) -> int | None:
    """The scripted person's answer, the same in every run: by the question's number, a candidate, or no
    goal every fifth question."""
    masks = [c["mask"] for c in q["candidates"]]
    return None if q["id"] % 5 == 0 else masks[q["id"] % len(masks)]


class Person(threading.Thread):
    """A person at the page of the run `proc` (its output in `log`), through the page's own requests: answers
    each question by `choose`, except question number `stop_at`, where it calls `stop(proc, question)` and
    answers nothing more. `asked`: every question as the page showed it (its
    seconds left aside)."""

    def __init__(self, proc: subprocess.Popen, log: Path, stop_at=None, stop=None):
        super().__init__(daemon=True)
        self.proc, self.log, self.stop_at, self.stop = proc, log, stop_at, stop
        self.asked: list[dict] = []
        self.start()

    def address(self) -> str | None:
        while self.proc.poll() is None:
            if m := re.search(r"open (http://\S+) in a browser", self.log.read_text()):
                return m.group(1).replace("/?token=", "/{}?token=")
            time.sleep(0.05)
        return None

    def run(self):
        url = self.address()
        while url is not None and self.proc.poll() is None:
            try:
                q = json.load(urllib.request.urlopen(url.format("state"), timeout=10))["question"]
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                continue  # the run is ending
            if q is None or (self.asked and q["id"] == self.asked[-1]["id"]):
                time.sleep(0.02)
                continue
            self.asked.append({k: v for k, v in q.items() if k != "seconds_left"})
            if q["id"] == self.stop_at:
                self.stop(self.proc, self.asked[-1])
                return
            body = json.dumps(dict(question=q["id"], goal=choose(q))).encode()
            answer = urllib.request.Request(url.format("answer"), data=body, method="POST",
                                            headers={"Content-Type": "application/json"})  # fmt: skip
            urllib.request.urlopen(answer, timeout=10)


def start(runs: Path, *argv, stop_at=None, stop=None) -> tuple[subprocess.Popen, Person, Path]:
    log = runs / f"out{len(list(runs.glob('out*')))}.txt"
    cmd = [sys.executable, "-u", "gangstr_hme.py", *argv, "--runs-dir", str(runs)]
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, text=True)
    return proc, Person(proc, log, stop_at, stop), log


def finish(proc: subprocess.Popen, person: Person, log: Path, code: int = 0) -> str:
    proc.wait(timeout=120)
    person.join(10)
    said = log.read_text()
    assert proc.returncode == code, said
    return said


def outputs(runs: Path) -> tuple[list[dict], list[dict]]:
    """progress.csv and picks.csv of the run folder in runs, timing columns aside."""
    (run,) = [p for p in runs.iterdir() if p.is_dir()]
    with (run / "progress.csv").open(newline="") as f:
        progress = [{k: v for k, v in r.items() if not k.startswith(TIMING)} for r in csv.DictReader(f)]
    with (run / "picks.csv").open(newline="") as f:
        picks = [{k: v for k, v in r.items() if k != "time"} for r in csv.DictReader(f)]
    return progress, picks


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> tuple[list[dict], list[dict], list[dict]]:
    runs = tmp_path_factory.mktemp("uninterrupted")
    proc, person, log = start(runs, *FLAGS)
    finish(proc, person, log)
    progress, picks = outputs(runs)
    assert {p["by"] for p in picks} == {"person", "skipped"}
    assert len([q for q in person.asked if (q["epoch"], q["cycle"]) == AT]) > 1
    return progress, picks, person.asked


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["ctrl-c", "sigterm", "kill-9"])
def test_a_stop_while_a_question_waits_resumes_into_the_uninterrupted_run(tmp_path, uninterrupted, sig):
    """Ctrl-C and SIGTERM exit 130 with a checkpoint, kill -9 loses the work since epoch 0's; --resume asks
    the waiting question again (its number, kind and candidates), then every question the uninterrupted run
    asked after it, and its progress.csv and picks.csv are the uninterrupted run's."""
    progress, picks, asked = uninterrupted
    at = [q["id"] for q in asked if (q["epoch"], q["cycle"]) == AT][-1]
    waiting = []
    proc, person, log = start(tmp_path, *FLAGS, stop_at=at, stop=lambda p, q: [waiting.append(q), p.send_signal(sig)])
    said = finish(proc, person, log, code=-9 if sig == signal.SIGKILL else 130)
    assert len(waiting) == 1 and waiting[0] == asked[at - 1], said
    if sig != signal.SIGKILL:
        assert "interrupted: checkpoint saved" in said
    (run,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    proc, again, log = start(tmp_path, "--resume", str(run / "checkpoint.pt"))
    finish(proc, again, log)
    assert waiting[0] in again.asked  # asked again: the same number, the same candidates
    assert again.asked == asked[len(asked) - len(again.asked) :]  # and from there, what the uninterrupted run asked
    if sig != signal.SIGKILL:  # the cycle it was asked in, from its start
        assert again.asked[0]["id"] < at and (again.asked[0]["epoch"], again.asked[0]["cycle"]) == AT
    assert outputs(tmp_path) == (progress, picks)
