"""person_partner.py, a person as the social partner (--partner person): the questions, the answers, the
fall-back on the oracle's draw, picks.csv, and every request the page's server must refuse. Without a
browser; tests/test_person_browser.py drives the page in one."""

import csv
import http.client
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import fetch5_env
import gangstr_hme as gh
import oracle_graph as og
import person_partner as pp

ROOT = Path(__file__).resolve().parent.parent
N = 3


class Asking:
    """A PersonPartner serving on a free port, and a worker standing in the scene; ask() runs in a thread
    (the run's side), the test plays the page through HTTP requests."""

    def __init__(self, folder: Path, timeout: float = 30.0, stopping=lambda: False):
        args = gh.Args(n_blocks=N, partner="person", person_port=0, person_timeout=timeout)
        self.counts = Counter()
        self.partner = pp.PersonPartner(gh.SocialPartner(N), args, lambda: (2, 7), lambda k: self.counts.update([k]))
        self.partner.open(folder, stopping)
        self.folder, self.port, self.token = folder, self.partner.port, self.partner.token
        self.worker = SimpleNamespace(index=0, rng=np.random.default_rng(4), env=fetch5_env.FetchManipulateEnv(N),
                                      segments=[])  # fmt: skip
        self.worker.env.reset(seed=1)
        self.graph = gh.SemanticGraph(N, args)
        self.result = None

    def ask_beyond(self, here: int = 0):
        """Start a beyond question from `here` (all apart by default) and wait until the page can see it."""
        self.thread = threading.Thread(target=lambda: setattr(self, "result", self.beyond(here)))
        self.thread.start()
        while self.partner.question is None and self.thread.is_alive():
            time.sleep(0.01)
        return self.partner.question

    def beyond(self, here):
        return self.partner.beyond_goal(self.graph, here, self.worker)

    def request(self, method, path, body=None, token=True, headers=None):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        sep = "&" if "?" in path else "?"
        url = f"{path}{sep}token={self.token}" if token is True else (f"{path}{sep}token={token}" if token else path)
        data = body if isinstance(body, bytes) or body is None else json.dumps(body).encode()
        heads = {"Content-Type": "application/json"} if data is not None else {}
        conn.request(method, url, body=data, headers=heads | (headers or {}))
        r = conn.getresponse()
        payload = r.read()
        conn.close()
        return r.status, payload

    def close(self):
        self.partner.close()

    def picks(self) -> list[dict]:
        with (self.folder / "picks.csv").open(newline="") as f:
            return list(csv.DictReader(f))


@pytest.fixture
def asking(tmp_path):
    a = Asking(tmp_path)
    yield a
    a.partner.stopping = lambda: True  # a question still waiting ends at once
    if hasattr(a, "thread"):
        a.thread.join(5)
    a.close()


def beyond_candidates(here=0):
    return gh.SocialPartner(N).beyond_candidates(gh.SemanticGraph(N, gh.Args(n_blocks=N)), here).tolist()


# ------------------------------------------------------------------------------------------------
# A question, its answer, and what reaches the agent
# ------------------------------------------------------------------------------------------------
def test_the_page_sees_the_question_with_the_simulated_partners_candidates_and_the_pick_reaches_the_agent(asking):
    q = asking.ask_beyond()
    status, body = asking.request("GET", "/state")
    state = json.loads(body)
    assert status == 200 and state["question"]["id"] == q["id"] and state["question"]["kind"] == "beyond"
    offered = [c["mask"] for c in state["question"]["candidates"]]
    assert offered == beyond_candidates() and len(offered) > 2  # exactly the oracle partner's candidates
    assert state["question"]["here"]["text"] == "all blocks apart" and state["n_blocks"] == N
    stack = int(og.to_mask(og.make_config(N, close=[(0, 1)], above=[(0, 1)])))
    view = next(c for c in state["question"]["candidates"] if c["mask"] == stack)
    assert (view["cls"], view["text"], view["above"]) == ("S2", "red on blue", [[0, 1]])
    assert asking.request("GET", "/")[0] == 200 and b"you are the social partner" in asking.request("GET", "/")[1]
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=stack)) == (200, b'{"ok": true}')
    asking.thread.join(5)
    assert asking.result == stack  # the goal the agent is given
    # the agent's attempt: one segment towards it, reached; picks.csv then has the row, with the outcome
    asking.worker.segments.append(SimpleNamespace(g=og.from_mask(stack, N)))
    asking.partner.outcome(asking.worker, stack, True)
    (row,) = asking.picks()
    assert (row["by"], row["picked"], row["first_goal"], row["outcome"]) == (
        "person",
        str(stack),
        str(stack),
        "reached",
    )
    assert (row["epoch"], row["cycle"], row["kind"], row["picked_class"]) == ("2", "7", "beyond", "S2")
    assert row["offered"] == " ".join(map(str, offered))
    assert asking.counts == Counter(person_picks=1)
    last = json.loads(asking.request("GET", "/state")[1])["last"]
    assert last["outcome"] == "reached" and last["picked"]["mask"] == stack and last["by"] == "person"


def test_no_goal_this_time_proposes_nothing(asking):
    q = asking.ask_beyond()
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=None))[0] == 200
    asking.thread.join(5)
    assert asking.result is None
    (row,) = asking.picks()
    assert (row["by"], row["picked"], row["outcome"]) == ("skipped", "", "")
    assert asking.counts == Counter(person_skips=1)


def test_with_no_answer_in_time_the_oracle_draws_as_it_would_alone(tmp_path):
    a = Asking(tmp_path, timeout=0.3)
    try:
        start = time.monotonic()
        a.ask_beyond()
        a.thread.join(5)
        assert time.monotonic() - start < 3
        alone = gh.SocialPartner(N).choose(SimpleNamespace(rng=np.random.default_rng(4)), np.array(beyond_candidates()))
        assert a.result == alone  # the same draw from the worker's stream
        a.partner.outcome(a.worker, a.result, False)
        (row,) = a.picks()
        assert (row["by"], row["picked"], row["outcome"]) == ("timeout", str(alone), "not reached")
        assert a.counts == Counter(person_timeouts=1)
    finally:
        a.close()


def test_a_stop_request_drops_the_waiting_question_at_once(tmp_path):
    stop = threading.Event()
    a = Asking(tmp_path, timeout=60, stopping=stop.is_set)
    try:
        q = a.ask_beyond()
        stop.set()  # Ctrl-C or SIGTERM
        a.thread.join(5)
        assert not a.thread.is_alive() and a.result in beyond_candidates()
        a.partner.outcome(a.worker, a.result, None)
        (row,) = a.picks()
        assert (row["question"], row["by"], row["outcome"]) == (str(q["id"]), "dropped", "cut off")
        assert not a.counts  # not a choice of anyone's: picks.csv only
        assert a.request("POST", "/answer", dict(question=q["id"], goal=a.result))[0] == 409  # not replayed
    finally:
        a.close()


def test_nothing_to_propose_asks_nothing(asking):
    everything = gh.SocialPartner(N)
    graph = asking.graph
    for k in range(len(everything.edge_heads)):  # every oracle edge tried: no candidate anywhere
        graph.add_config(int(everything.edge_heads[k]))
        graph.add_config(int(everything.edge_tails[k]))
        graph.edge_class(int(everything.edge_heads[k]), int(everything.edge_tails[k]))
    assert asking.partner.frontier_goal(graph, 0, asking.worker) is None
    assert asking.partner.beyond_goal(graph, 0, asking.worker) is None
    assert asking.partner.asked == 0 and asking.picks() == []


# ------------------------------------------------------------------------------------------------
# Every bad request: a 4xx, and nothing changes
# ------------------------------------------------------------------------------------------------
def oversized(a, q):
    return a.request("POST", "/answer", json.dumps(dict(question=q, goal=1, pad="x" * 2000)).encode())


def no_length(a, q):
    conn = socket.create_connection(("127.0.0.1", a.port), timeout=10)
    conn.sendall(f"POST /answer?token={a.token} HTTP/1.1\r\nHost: 127.0.0.1:{a.port}\r\n"
                 "Content-Type: application/json\r\nConnection: close\r\n\r\n".encode())  # fmt: skip
    reply = conn.recv(4096).decode()
    conn.close()
    return int(reply.split()[1]), reply


def raw(a, head: str, body: bytes = b""):
    """A request written by hand (what http.client will not send), and its status."""
    conn = socket.create_connection(("127.0.0.1", a.port), timeout=10)
    conn.sendall(head.replace("TOKEN", a.token).encode() + b"\r\n\r\n" + body)
    reply = b""
    while chunk := conn.recv(4096):
        reply += chunk
    conn.close()
    text = reply.decode()
    return int(text.split()[1]), text.split("\r\n\r\n", 1)[-1].encode()


BAD = {
    "wrong token": (lambda a, q: a.request("POST", "/answer", dict(question=q, goal=1), token="nope"), 403),
    "no token": (lambda a, q: a.request("POST", "/answer", dict(question=q, goal=1), token=None), 403),
    "wrong token, reading": (lambda a, q: a.request("GET", "/state", token="x" * 24), 403),
    "foreign Host header": (lambda a, q: a.request("GET", "/state", headers={"Host": f"evil.example:{a.port}"}), 403),
    "unknown question": (lambda a, q: a.request("POST", "/answer", dict(question=q + 40, goal=1)), 409),
    "stale question": (lambda a, q: a.request("POST", "/answer", dict(question=q - 1, goal=1)), 409),
    "candidate not offered": (lambda a, q: a.request("POST", "/answer", dict(question=q, goal=2**8)), 422),
    "not JSON": (lambda a, q: a.request("POST", "/answer", b"question=1&goal=1"), 400),
    "not UTF-8": (lambda a, q: a.request("POST", "/answer", b"\xff\xfe{}"), 400),
    "missing goal": (lambda a, q: a.request("POST", "/answer", dict(question=q)), 400),
    "extra field": (lambda a, q: a.request("POST", "/answer", dict(question=q, goal=1, by="me")), 400),
    "goal not an integer": (lambda a, q: a.request("POST", "/answer", dict(question=q, goal="1")), 400),
    "question a boolean": (lambda a, q: a.request("POST", "/answer", dict(question=True, goal=1)), 400),
    "a list": (lambda a, q: a.request("POST", "/answer", [q, 1]), 400),
    "oversized body": (oversized, 413),
    "no Content-Length": (no_length, 411),
    "not application/json": (
        lambda a, q: a.request(
            "POST", "/answer", b'{"question": 1, "goal": 1}', headers={"Content-Type": "text/plain"}
        ),
        415,
    ),
    "unknown page": (lambda a, q: a.request("GET", "/admin"), 404),
    "unknown frame": (lambda a, q: a.request("GET", f"/frame/q{q + 5}.png"), 404),
    "GET an answer": (lambda a, q: a.request("GET", "/answer"), 405),
    "PUT an answer": (lambda a, q: a.request("PUT", "/answer", dict(question=q, goal=1)), 405),
    "DELETE": (lambda a, q: a.request("DELETE", "/state"), 405),
    "deeply nested JSON": (lambda a, q: a.request("POST", "/answer", b"[" * 1000), 400),
    "negative Content-Length": (
        lambda a, q: raw(
            a,
            f"POST /answer?token=TOKEN HTTP/1.0\r\nHost: 127.0.0.1:{a.port}\r\n"
            "Content-Type: application/json\r\nContent-Length: -5",
        ),  # fmt: skip
        400,
    ),
    "no Host header": (lambda a, q: raw(a, "GET /state?token=TOKEN HTTP/1.0"), 403),
    "POST the state": (lambda a, q: a.request("POST", "/state", dict(question=q, goal=1)), 405),
}


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_request_gets_a_4xx_and_changes_nothing(asking, name):
    first = asking.ask_beyond()  # a first question, answered: the next one's id - 1 is stale
    assert asking.request("POST", "/answer", dict(question=first["id"], goal=None))[0] == 200
    asking.thread.join(5)
    q = asking.ask_beyond()
    before = json.loads(asking.request("GET", "/state")[1])
    send, want = BAD[name]
    status, body = send(asking, q["id"])
    assert status == want, body
    assert 400 <= status < 500
    if status != 411:
        assert json.loads(body)["error"]  # a clear reason
    assert asking.partner.answer is None and asking.partner.question is q and asking.thread.is_alive()
    after = json.loads(asking.request("GET", "/state")[1])
    assert after["run"] == before["run"] and after["question"]["id"] == q["id"]
    one = next(c["mask"] for c in q["candidates"] if c["mask"] != 0)
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=one))[0] == 200  # still answerable
    asking.thread.join(5)
    assert asking.result == one


class Parked(threading.Condition):
    """The partner's lock, whose waiting run thread stays parked (lock released) until `go` is set."""

    def __init__(self):
        super().__init__()
        self.go = threading.Event()

    def wait(self, timeout=None):
        if self.go.is_set():
            return super().wait(timeout)
        self.release()
        self.go.wait(10)
        self.acquire()
        return False


def test_a_second_answer_to_a_question_is_refused_and_the_first_one_counts(asking):
    asking.partner.lock = Parked()
    q = asking.ask_beyond()
    one, two = [c["mask"] for c in q["candidates"][:2]]
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=one))[0] == 200
    status, body = asking.request("POST", "/answer", dict(question=q["id"], goal=two))  # a double click, two tabs
    assert status == 409 and "already answered" in json.loads(body)["error"]
    asking.partner.lock.go.set()
    asking.thread.join(5)
    assert asking.result == one


def test_a_request_that_breaks_in_the_server_gets_a_500_and_the_run_goes_on(asking, monkeypatch):
    q = asking.ask_beyond()
    monkeypatch.setattr(asking.partner, "progress", lambda: 1 / 0)
    status, body = asking.request("GET", "/state")
    assert status == 500 and "ZeroDivisionError" in json.loads(body)["error"]
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=None))[0] == 200
    asking.thread.join(5)
    assert asking.result is None and not asking.thread.is_alive()


# ------------------------------------------------------------------------------------------------
# The command line: bad values, torchrun, a port in use
# ------------------------------------------------------------------------------------------------
TINY = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "1", "--n-segments", "2", "--n-updates", "1",
        "--batch-size", "16", "--segment-len", "6", "--stable-steps", "3", "--eval-goals-per-class", "1",
        "--threads", "1"]  # fmt: skip


def script(*argv, runs, env=None, timeout=120):
    cmd = [sys.executable, "gangstr_hme.py", *argv, "--runs-dir", str(runs)]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=env)


@pytest.mark.parametrize(
    "argv, named",
    [
        (["--partner", "robot"], "'robot'"),
        (["--partner", "person", "--person-timeout", "0"], "--person-timeout"),
        (["--partner", "person", "--person-port", "70000"], "70000"),
    ],
)
def test_bad_partner_options_exit_2_with_one_line_and_write_nothing(tmp_path, argv, named):
    out = script(*argv, *TINY, runs=tmp_path / "runs")
    assert out.returncode == 2 and named in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()


def test_a_person_partner_under_torchrun_is_refused_in_one_line(tmp_path):
    env = os.environ | dict(WORLD_SIZE="2", RANK="0", LOCAL_RANK="0")
    out = script("--partner", "person", *TINY, runs=tmp_path / "runs", env=env)
    assert out.returncode == 2 and "--partner person takes one process" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "argv, named",
    [
        (["--person-timeout", "inf"], "--person-timeout"),
        (["--person-host", "::1"], "--person-host"),
        (["--person-host", ""], "--person-host"),
    ],
)
def test_a_person_partner_with_bad_page_options_exits_2(tmp_path, argv, named):
    out = script("--partner", "person", "--sp-ratio", "1", *argv, *TINY, runs=tmp_path / "runs")
    assert out.returncode == 2 and named in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()


def test_a_person_partner_with_no_social_cycle_to_ask_in_is_refused(tmp_path):
    out = script("--partner", "person", *TINY, runs=tmp_path / "runs")  # neither --sp-ratio nor --ask-after
    assert out.returncode == 2 and "needs social cycles" in out.stderr and not (tmp_path / "runs").exists()


def test_a_port_in_use_exits_2_before_anything_is_written(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = script("--partner", "person", "--person-port", str(port), "--sp-ratio", "1", *TINY, runs=tmp_path / "r")
    assert out.returncode == 2 and f"127.0.0.1:{port}" in out.stderr, out.stderr
    assert not (tmp_path / "r").exists()


def test_an_unattended_run_finishes_by_timeouts_and_counts_them(tmp_path):
    out = script("--partner", "person", "--person-port", "0", "--person-timeout", "0.2", "--sp-ratio", "1", *TINY,
                 runs=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "person partner: open http://127.0.0.1:" in out.stdout and "?token=" in out.stdout
    (run,) = tmp_path.iterdir()
    with (run / "picks.csv").open(newline="") as f:
        picks = list(csv.DictReader(f))
    assert picks and {p["by"] for p in picks} == {"timeout"}
    assert all(p["picked"] in p["offered"].split() for p in picks)
    with (run / "progress.csv").open(newline="") as f:
        (row,) = csv.DictReader(f)
    assert float(row["person_timeouts"]) == len(picks) and float(row["person_picks"]) == 0


def test_asked_only_when_the_learner_asks_and_a_resume_numbers_questions_on(tmp_path):
    flags = ["--partner", "person", "--person-port", "0", "--person-timeout", "0.2", "--ask-after", "1",
             "--n-epochs", "1", "--n-cycles", "4", *TINY[TINY.index("--n-segments") :]]  # fmt: skip
    assert script(*flags, "--n-blocks", "3", runs=tmp_path).returncode == 0
    (run,) = tmp_path.iterdir()
    with (run / "progress.csv").open(newline="") as f:
        (row,) = csv.DictReader(f)
    with (run / "picks.csv").open(newline="") as f:
        first = list(csv.DictReader(f))
    assert float(row["queries"]) > 0 and float(row["social_share"]) == float(row["help_cycles"]) / 4
    assert first and {int(p["cycle"]) for p in first} <= set(range(4))  # questions in help cycles only
    torchrun = os.environ | dict(WORLD_SIZE="2", RANK="0", LOCAL_RANK="0")  # the checkpoint's --partner person
    out = script("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", runs=tmp_path, env=torchrun)
    assert out.returncode == 2 and "--partner person takes one process" in out.stderr
    out = script("--resume", str(run / "checkpoint.pt"), "--n-epochs", "2", "--person-port", "0", runs=tmp_path)
    assert out.returncode == 0, out.stderr  # a new port on resume: the page's options may change
    with (run / "picks.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["question"]) for r in rows] == list(range(1, len(rows) + 1)) and len(rows) > len(first)
    assert {r["epoch"] for r in rows[len(first) :]} == {"1"}
