"""The person partner's page under random requests: --requests of them, each a request the page serves
with up to three of its fields varied (method, path, the query's other fields, version, Host, token,
Content-Type, Content-Length, body, headers; methods, paths and query fields partly generated character by
character; tests/test_person.py's random_request, drawn here by Python's random), sent on raw sockets
to a live page with a question waiting. Each reply is checked as the test checks it: the status SPEC
§7.1 gives for the request's first fault, in the page's JSON form; the page still serving; picks.csv one
row longer for each answer taken, and unchanged otherwise. Prints what was tried (by method, by field
varied, by status), the median time per request, and any reply that broke the rules. Not part of the
test suite (whose test sends 300 of these).

    python benchmarks/bench_person_page.py [--requests 5000] [--seed 0] [--timeout 0.5]
"""

import argparse
import math
import random
import statistics
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
from test_person import METHODS, Asking, play, random_request  # noqa: E402


def table(title: str, counts: Counter, times: dict | None = None):
    print(f"{title}:")
    for key, n in sorted(counts.items(), key=lambda kv: (-kv[1], str(kv[0]))):
        median = f"  median {statistics.median(times[key]) * 1000:6.1f} ms" if times else ""
        print(f"  {str(key):36s} {n:6d}{median}")


def bombard(page: Asking, n: int, rng: random.Random) -> dict:
    """n random requests to the page; what was tried, each status's times, the replies against the rules."""
    tried = dict(methods=Counter(), varied=Counter(), statuses=Counter(), times=defaultdict(list), broken=[], taken=0)
    for i in range(n):
        request = random_request(rng.choice, rng.randint)
        tried["methods"][request["method"] if request["method"] in METHODS else "(another token, generated)"] += 1
        tried["varied"].update(request["varied"] or ["(nothing: a request the page serves)"])
        t = time.perf_counter()
        try:
            status = play(page, request)
        except AssertionError as e:  # a reply against the rules (play's message says which)
            status = "against the rules"
            tried["broken"].append((i, request["varied"], " ".join(str(e).split())[:300]))
        tried["statuses"][status] += 1
        tried["times"][status].append(time.perf_counter() - t)
        tried["taken"] += status == 200 and request["method"] == "POST"  # an answer taken (elsewhere: 404, 405)
    return tried


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=0.5,
                        help="the page's connection timeout in seconds: how long a body that never comes whole "
                        "is awaited (a run's page: 15)")  # fmt: skip
    args = parser.parse_args()
    if args.requests < 1:
        parser.error(f"--requests must be 1 or more, got {args.requests}")
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        parser.error(f"--timeout must be a number of seconds above 0, got {args.timeout}")
    with tempfile.TemporaryDirectory() as folder:
        page = Asking(Path(folder), timeout=3600.0)
        page.partner.frame = lambda w: None  # no pictures: questions come at once (and every frame is a 404)
        page.partner.server.RequestHandlerClass.timeout = args.timeout
        page.ask_beyond()
        try:
            start = time.perf_counter()
            tried = bombard(page, args.requests, random.Random(args.seed))
            seconds = time.perf_counter() - start
            serving = page.request("GET", "/state")[0] == 200
            rows = page.picks()
        finally:
            page.partner.stopping = lambda: True  # the question waiting ends at once
            page.thread.join(5)
            page.close()
    every = [t for ts in tried["times"].values() for t in ts]
    print(f"{args.requests} random requests in {seconds:.1f} s (seed {args.seed}), "
          f"median {statistics.median(every) * 1000:.1f} ms a request")  # fmt: skip
    table("by method", tried["methods"])
    table("by field varied (up to three a request)", tried["varied"])
    table("by status (None: no reply, to a connection that sent no request line)", tried["statuses"], tried["times"])
    recorded = Counter(r["by"] for r in rows)
    once = len(rows) == recorded["person"] + recorded["skipped"] == tried["taken"]
    print(f"answers taken: {tried['taken']}; picks.csv: {len(rows)} rows, by {dict(recorded)} "
          f"(one a taken answer, nothing else: {'yes' if once else 'NO'})")  # fmt: skip
    print(f"the page still serving at the end: {'yes' if serving else 'NO'}")
    print(f"replies against the rules: {len(tried['broken'])}")
    for i, fields, why in tried["broken"][:10]:
        print(f"  request {i} (varied: {', '.join(fields) or 'nothing'}): {why}")
    return 0 if serving and once and not tried["broken"] else 1


if __name__ == "__main__":
    sys.exit(main())
