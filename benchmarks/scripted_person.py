"""A scripted person for --partner person: answers the page's questions through the page's own requests
(GET /state, POST /answer), always picking the candidate with the tallest tower (then the most blocks on
others). It starts the run itself, then prints what the run opened and how many picks it took.
(README.md, section "You as the social partner": the ten-minute demo.)

    python benchmarks/scripted_person.py -- --n-blocks 5 --init-from paper --n-updates 0 \
        --freeze-normalizer --sp-ratio 0.1 --n-epochs 6 --eval-goals-per-class 6 --exp-name teach

Everything after -- goes to gangstr_hme.py (which gets --partner person --person-port 0 added).
"""

import argparse
import csv
import json
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HARD = ("S3", "S2&S2", "S2&S3", "P3&S2", "S4", "S5")


def tower(view: dict) -> tuple[int, int]:
    """(height of its tallest stack, blocks on other blocks) of a config as the page sees it."""
    on = {}
    for i, j in view["above"]:
        on.setdefault(i, []).append(j)

    def height(b, seen=()):
        return 1 + max((height(s, (*seen, b)) for s in on.get(b, []) if s not in seen), default=0)

    blocks = {b for pair in view["above"] for b in pair}
    return max((height(b) for b in blocks), default=1), len(view["above"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_args", nargs=argparse.REMAINDER, help="-- then gangstr_hme.py's arguments")
    args = parser.parse_args()
    run_args = args.run_args[1:] if args.run_args[:1] == ["--"] else args.run_args
    cmd = [sys.executable, "-u", str(ROOT / "gangstr_hme.py"), *run_args, "--partner", "person", "--person-port", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    folder, address = None, None
    for line in proc.stdout:
        print(line, end="", flush=True)
        if m := re.match(r"run folder (\S+) ", line):
            folder = Path(m.group(1))
        if m := re.search(r"open (http://\S+) in a browser", line):
            address = m.group(1)
            break
    if address is None:
        return proc.wait()
    base, token = address.split("/?token=")
    answered, start = set(), time.monotonic()
    relay = __import__("threading").Thread(target=lambda: [print(x, end="", flush=True) for x in proc.stdout])
    relay.start()
    while proc.poll() is None:
        try:
            state = json.load(urllib.request.urlopen(f"{base}/state?token={token}", timeout=10))
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            time.sleep(0.2)
            continue
        q = state["question"]
        if q is not None and q["id"] not in answered:
            best = max(q["candidates"], key=tower)
            body = json.dumps(dict(question=q["id"], goal=best["mask"])).encode()
            request = urllib.request.Request(f"{base}/answer?token={token}", data=body, method="POST",
                                             headers={"Content-Type": "application/json"})  # fmt: skip
            try:
                urllib.request.urlopen(request, timeout=10)
                answered.add(q["id"])
            except urllib.error.HTTPError as e:  # the question timed out meanwhile (409): the next one
                print(f"scripted person: question {q['id']}: {e.code} {e.read().decode()}", flush=True)
        time.sleep(0.05)
    relay.join()
    code = proc.wait()
    with (folder / "picks.csv").open(newline="") as f:
        picks = list(csv.DictReader(f))
    with (folder / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    by = {k: sum(p["by"] == k for p in picks) for k in ("person", "skipped", "timeout", "dropped")}
    print(f"\nscripted person: {len(picks)} questions in {(time.monotonic() - start) / 60:.1f} min: {by}")
    social = sum(round(float(r["social_share"]) * (int(r["segments"]) - (int(rows[i - 1]["segments"]) if i else 0))
                       / 10) for i, r in enumerate(rows))  # fmt: skip
    print(
        f"social cycles: {social}; per hard class, the first epoch with a discovered configuration, and the "
        "person's picks by its end:"
    )
    for cls in HARD:
        found = [int(r["epoch"]) for r in rows if float(r.get(f"agent_nodes_{cls}", 0)) > 0]
        if found:
            upto = sum(p["by"] == "person" and int(p["epoch"]) <= found[0] for p in picks)
            print(f"  {cls}: epoch {found[0]} ({upto} picks), {rows[-1][f'agent_nodes_{cls}']} configs at the end")
        else:
            print(f"  {cls}: never")
    reached = [p for p in picks if p["by"] == "person"]
    towers = sum(p["picked_class"] in ("S3", "S4", "S5") for p in reached)
    print(
        f"picks of stacks of 3 or more: {towers}, reached: {sum(p['outcome'] == 'reached' for p in reached)} "
        f"of {len(reached)} picks; run folder {folder}"
    )
    return code


if __name__ == "__main__":
    sys.exit(main())
