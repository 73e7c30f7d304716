"""person_partner.py, a person as the social partner (--partner person): the questions, the answers, the
fall-back on the oracle's draw, picks.csv, and every request the page's server must refuse. Without a
browser; tests/test_person_browser.py drives the page in one."""

import csv
import http.client
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import inprocess
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fetch5_env
import gangstr_hme as gh
import oracle_graph as og
import person_partner as pp
import plumbing

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

        def ask():
            try:
                self.result = self.beyond(here)
            except plumbing.CycleGivenUp as e:  # a stop while it waited: the run gives up the cycle
                self.result = e

        self.thread = threading.Thread(target=ask)
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


def test_a_pick_never_pursued_is_in_picks_csv_by_the_next_question_even_one_with_nothing_to_ask(asking):
    # --strategy beyond: the frontier goal picked is hidden, and the beyond goal after it may have no candidate;
    # the pick's row is written then, before a checkpoint can count its question while a kill -9 loses the row
    q = asking.ask_beyond()
    goal = q["candidates"][0]["mask"]
    assert asking.request("POST", "/answer", dict(question=q["id"], goal=goal))[0] == 200
    asking.thread.join(5)
    assert asking.result == goal and asking.picks() == []  # its row waits for the attempt's outcome
    assert asking.partner.ask(asking.worker, "beyond", 0, np.array([], dtype=np.int64), asking.graph) is None
    (row,) = asking.picks()
    assert (row["question"], row["picked"], row["outcome"]) == (str(q["id"]), str(goal), "")


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
        assert not a.thread.is_alive() and isinstance(a.result, plumbing.CycleGivenUp)  # the run gives up the cycle
        (row,) = a.picks()
        assert (row["question"], row["by"], row["picked"], row["outcome"]) == (str(q["id"]), "dropped", "", "")
        assert not a.counts  # not a choice of anyone's: picks.csv only (until --resume asks it again)
        one = q["candidates"][0]["mask"]
        assert a.request("POST", "/answer", dict(question=q["id"], goal=one))[0] == 409  # not replayed
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


def with_lengths(a, q, values):
    """A valid answer to q but for its Content-Length headers, values(n) for a body of n bytes; all sent, then
    the connection's sending side closed (exchange, below)."""
    body = json.dumps(dict(question=q, goal=None)).encode()
    head = (f"POST /answer?token={a.token} HTTP/1.1\r\nHost: 127.0.0.1:{a.port}\r\nContent-Type: application/json\r\n"
            + "".join(f"Content-Length: {v}\r\n" for v in values(len(body))))  # fmt: skip
    status, _, reply = parsed(exchange(a.port, head.encode("latin-1") + b"\r\n" + body))
    return status, reply


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
    "Content-Length past the body's end": (lambda a, q: with_lengths(a, q, lambda n: [n + 5]), 400),
    "two Content-Lengths": (lambda a, q: with_lengths(a, q, lambda n: [n, n]), 400),
    "Content-Length not a number": (lambda a, q: with_lengths(a, q, lambda n: [f"{n}.0"]), 400),
    "Content-Length in other digits": (lambda a, q: with_lengths(a, q, lambda n: ["\N{SUPERSCRIPT TWO}"]), 400),
    "Content-Length of 5,000 digits": (lambda a, q: with_lengths(a, q, lambda n: ["9" * 5000]), 413),
    "a body in UTF-16": (
        lambda a, q: a.request("POST", "/answer", json.dumps(dict(question=q, goal=None)).encode("utf-16")),
        400,
    ),
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


@pytest.mark.parametrize("content_type, named", [("text/plain; charset=utf-8", "'text/plain; charset=utf-8'"),
                                                  (None, "no Content-Type")])  # fmt: skip
def test_an_answer_of_another_content_type_is_refused_naming_the_one_it_has(asking, content_type, named):
    q = asking.ask_beyond()
    head = f"POST /answer?token=TOKEN HTTP/1.0\r\nHost: 127.0.0.1:{asking.port}\r\nContent-Length: 2"
    status, body = raw(asking, head + ("" if content_type is None else f"\r\nContent-Type: {content_type}"), b"{}")
    assert status == 415 and json.loads(body)["error"] == f"answers are application/json, not {named}"
    assert asking.partner.question is q and asking.partner.answer is None


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
# Every refusal in the page's JSON form, and random requests (SPEC §7.1: the statuses, the order)
# ------------------------------------------------------------------------------------------------
STATUSES = (200, 400, 403, 404, 405, 408, 409, 411, 413, 414, 415, 422, 431, 500, 501, 505)  # SPEC §7.1's list
SECURITY = {"Cache-Control": "no-store", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer"}


def exchange(port: int, data: bytes, keep_open: bool = False) -> bytes:
    """`data` on a new connection, whose sending side is then closed (as by a client that said all it had
    to say) unless keep_open; the whole reply, b"" for none. The timeout bounds a page that never answers."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
        try:
            conn.sendall(data)
            if not keep_open:
                conn.shutdown(socket.SHUT_WR)
        except OSError:  # refused before all was read (a 414, a 431), the connection already closed
            pass
        reply = b""
        try:
            while chunk := conn.recv(65536):
                reply += chunk
        except ConnectionResetError:
            pass
    return reply


def parsed(reply: bytes) -> tuple[int, dict, bytes]:
    """A reply's status, headers and body, once checked to be in the page's form: a status line, the headers
    every reply carries, a Content-Length that is the body's, and for a refusal a JSON body with its reason."""
    head, _, body = reply.partition(b"\r\n\r\n")
    first, *lines = head.decode("latin-1").split("\r\n")
    assert re.fullmatch(r"HTTP/1\.0 [0-9]{3} .+", first), reply[:300]
    status, headers = int(first.split()[1]), dict(line.split(": ", 1) for line in lines)
    assert headers.items() >= SECURITY.items() and int(headers["Content-Length"]) == len(body), headers
    if status != 200:
        assert headers["Content-Type"] == "application/json" and json.loads(body)["error"], body
    return status, headers, body


REFUSED_BY_THE_PARSER = {  # what http.server itself refuses, before the page's own checks (HOST: the server's)
    "an unknown method": ("BREW /state?token=TOKEN HTTP/1.1\r\nHost: HOST", 501),
    "a lower-case method": ("get /state?token=TOKEN HTTP/1.1\r\nHost: HOST", 501),
    "HTTP/2.0": ("GET /state?token=TOKEN HTTP/2.0\r\nHost: HOST", 505),
    "HTTP/0.9, no version": ("GET /state?token=TOKEN", 505),
    "HTTP/0.9 named": ("GET /state?token=TOKEN HTTP/0.9\r\nHost: HOST", 505),
    "a version that is none": ("GET /state?token=TOKEN HTTP/1\r\nHost: HOST", 400),
    "a request line of four words": ("GET /state?token=TOKEN x HTTP/1.1\r\nHost: HOST", 400),
    "a request line of one word": ("GET", 400),
    "a request line over 64 KiB": ("GET /state?token=TOKEN&x=" + "x" * 70_000 + " HTTP/1.1\r\nHost: HOST", 414),
    "over 100 headers": ("GET /state?token=TOKEN HTTP/1.1\r\nHost: HOST" + "\r\nX-A: 1" * 101, 431),
    "a header line over 64 KiB": ("GET /state?token=TOKEN HTTP/1.1\r\nHost: HOST\r\nX-A: " + "a" * 70_000, 431),
}


@pytest.mark.parametrize("name", list(REFUSED_BY_THE_PARSER))
def test_a_request_the_http_parser_refuses_gets_the_pages_json_refusal_and_changes_nothing(asking, name):
    q = asking.ask_beyond()
    head, want = REFUSED_BY_THE_PARSER[name]
    head = head.replace("TOKEN", asking.token).replace("HOST", f"127.0.0.1:{asking.port}")
    status, _, body = parsed(exchange(asking.port, head.encode() + b"\r\n\r\n"))
    assert status == want, body
    assert asking.request("GET", "/state")[0] == 200  # still serving
    assert asking.partner.answer is None and asking.partner.question is q and asking.picks() == []


@pytest.mark.parametrize("kind", ["Application/JSON", "application/json; charset=utf-8"])
def test_an_answers_content_type_is_application_json_in_any_case_with_parameters(asking, kind):
    q = asking.ask_beyond()
    answer = dict(question=q["id"], goal=None)
    assert asking.request("POST", "/answer", answer, headers={"Content-Type": kind}) == (200, b'{"ok": true}')
    asking.thread.join(5)
    assert asking.result is None and asking.picks()[0]["by"] == "skipped"


def test_a_body_that_never_comes_whole_gets_a_408_after_the_connections_timeout(asking, monkeypatch):
    monkeypatch.setattr(asking.partner.server.RequestHandlerClass, "timeout", 0.3)
    q = asking.ask_beyond()
    body = json.dumps(dict(question=q["id"], goal=None)).encode()
    head = (f"POST /answer?token={asking.token} HTTP/1.1\r\nHost: 127.0.0.1:{asking.port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body) + 1}\r\n\r\n")  # fmt: skip
    start = time.monotonic()
    status, _, reply = parsed(exchange(asking.port, head.encode() + body, keep_open=True))  # the last byte: never
    assert status == 408 and time.monotonic() - start < 3, reply
    assert asking.partner.answer is None and asking.partner.question is q and asking.picks() == []


# --- random requests: a served one with up to three fields varied --------------------------------------------
METHODS = ("GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "HEAD", "BREW", "get", "M-SEARCH", "TRACE", "CONNECT")
PATHS = ("/", "/state", "/answer", "/admin", "/state/", "/answer/", "/frame/q1.png", "/frame/a1.png", "/frame/",
         "*", "/STATE", "/%73tate", "/index.html", "/state;x", "/../state")  # fmt: skip
PATH_CHARS = "abcdefghijklmnopqrstuvwxyzABCXYZ0123456789-._~%!$&'()*+,;=:@"  # no / ? # or space
METHOD_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz-_!#$*+.^|~"  # any token's (RFC 9110)
FIELD_CHARS = "abcdefghijklmnopqrstuvwxyzT0123456789-._~%+"  # a query field's name and value: no & = # or space
VERSIONS = {"HTTP/1.0": 0, "HTTP/1.1": 0, "HTTP/1.2": 0, "HTTP/2.0": 505, "HTTP/3.0": 505, "HTTP/0.9": 505,
            "HTTP/00.9": 505, "HTTP/1": 400, "http/1.1": 400, "HTTP/1.x": 400, "HTTP/1.1.1": 400, "HTTPS/1.1": 400,
            "": 0}  # the status the last word of a request line calls for ("": the line has no version)  # fmt: skip
HOSTS = ("127.0.0.1:PORT", "localhost:PORT", None, "evil.example:PORT", "127.0.0.1", "127.0.0.1:OTHER",
         "[::1]:PORT", "LOCALHOST:PORT")  # fmt: skip
TOKENS = {  # how the token travels (t: the run's): the query's first non-empty one, else X-Token's
    "in the query": (lambda t: (f"?token={t}", None), True),
    "among other fields": (lambda t: (f"?a=1&token={t}&b=", None), True),
    "percent-encoded": (lambda t: ("?token=" + "".join(f"%{ord(c):02X}" for c in t), None), True),
    "in X-Token": (lambda t: ("", t), True),
    "empty in the query, in X-Token": (lambda t: ("?token=", t), True),
    "the query's over a wrong X-Token": (lambda t: (f"?token={t}", "nope"), True),
    "missing": (lambda t: ("", None), False),
    "wrong": (lambda t: ("?token=nope", None), False),
    "cut short": (lambda t: (f"?token={t[:-1]}", None), False),
    "wrong, then right": (lambda t: (f"?token=nope&token={t}", None), False),
    "wrong in the query, right in X-Token": (lambda t: ("?token=nope", t), False),
    "wrong in X-Token": (lambda t: ("", "nope"), False),
}
CONTENT_TYPES = {"application/json": True, "application/json; charset=utf-8": True, "Application/JSON": True,
                 None: False, "": False, "text/plain": False, "application/jsonp": False,
                 "application/x-www-form-urlencoded": False}  # fmt: skip
LENGTHS = {  # Content-Length headers, from the body's length n and a number k in [1, 60]
    "exact": lambda n, k: [str(n)],
    "leading zeros": lambda n, k: [f"00{n}"],
    "spaces around": lambda n, k: [f"{n}  "],
    "missing": lambda n, k: [],
    "empty": lambda n, k: [""],
    "a word": lambda n, k: ["twelve"],
    "signed": lambda n, k: [f"+{n}"],
    "negative": lambda n, k: [f"-{n}"],
    "a decimal": lambda n, k: [f"{n}.0"],
    "a superscript digit": lambda n, k: ["\N{SUPERSCRIPT TWO}"],
    "an underscore": lambda n, k: [f"1_{n}"],
    "twice": lambda n, k: [str(n), str(n)],
    "two different": lambda n, k: [str(n), str(n + k)],
    "5,000 digits": lambda n, k: ["9" * 5000],
    "over the limit": lambda n, k: ["1025"],
    "too long": lambda n, k: [str(n + k)],
    "too short": lambda n, k: [str(max(0, n - k))],
}
BODIES = ("a pick", "no goal", "a pick, padded", "a pick, then junk", "a pick in UTF-16", "a stale question",
          "another question", "a goal maybe offered", "the goal as text", "the goal as a float", "the goal NaN",
          "the question true", "an extra field", "no goal field", "a list", "deeply nested", "empty",
          "random bytes")  # fmt: skip


def query_field(choose, number) -> str:
    """A field of the query string other than the token: `name=value`, `name=` or `name` (never named token)."""
    name = "".join(choose(FIELD_CHARS) for _ in range(number(1, 6)))
    value = "".join(choose(FIELD_CHARS) for _ in range(number(0, 8)))
    return ("x" if name == "token" else "") + name + choose(("=" + value, "=", ""))


def vary_body(choose, number):
    kind = choose(BODIES)
    if kind == "random bytes":
        return kind, bytes(number(0, 255) for _ in range(number(0, 30)))
    return kind, number(0, 1100)


VARY = {  # a field of a request: a random value for it (the answer's first: hypothesis favours the first)
    "body": vary_body,
    "length": lambda choose, number: (choose(tuple(LENGTHS)), number(1, 60)),
    "token": lambda choose, number: choose(tuple(TOKENS)),
    "content type": lambda choose, number: choose(tuple(CONTENT_TYPES)),
    "host": lambda choose, number: choose(HOSTS),
    "method": lambda choose, number: choose(METHODS) if number(0, 2) else "".join(
        choose(METHOD_CHARS) for _ in range(number(1, 10))),
    "query": lambda choose, number: tuple([query_field(choose, number) for _ in range(number(0, 3))] for _ in "ab"),
    "path": lambda choose, number: choose(PATHS) if number(0, 2) else "/" + "".join(
        choose(PATH_CHARS) for _ in range(number(1, 12))),
    "version": lambda choose, number: choose(tuple(VERSIONS)),
    "extra word": lambda choose, number: choose(("x", "HTTP/1.1", "HTTP/2.0")),
    "keep open": lambda choose, number: True,
    "junk headers": lambda choose, number: [
        ("X-Junk-" + "".join(choose(PATH_CHARS[:26]) for _ in range(number(1, 6))),
         "".join(chr(number(32, 126)) for _ in range(number(0, 20)))) for _ in range(number(1, 4))],
    "a line that is no header": lambda choose, number: choose(("no colon here", "{}", "GET / HTTP/1.1")),
    "nothing sent": lambda choose, number: choose((b"", b"\r\n")),
    "long line": lambda choose, number: True,
    "over 100 headers": lambda choose, number: True,
    "a long header": lambda choose, number: True,
}  # fmt: skip
FIELDS = (*VARY, "body", "body", "body", "body", "length", "length", "token", "method", "version")  # weights
SERVED = (  # requests the page serves, before any field is varied
    dict(method="GET", path="/", body=("none", 0), length=("missing", 1), **{"content type": None}),
    dict(method="GET", path="/state", body=("none", 0), length=("missing", 1), **{"content type": None}),
    dict(method="POST", path="/answer", body=("a pick", 0)),
    dict(method="POST", path="/answer", body=("a pick", 1)),
    dict(method="POST", path="/answer", body=("no goal", 0)),
)
DEFAULTS = {"version": "HTTP/1.1", "extra word": None, "long line": False, "host": "127.0.0.1:PORT", "query": ([], []),
            "token": "in the query", "content type": "application/json", "length": ("exact", 1), "keep open": False,
            "junk headers": [], "over 100 headers": False, "a long header": False, "a line that is no header": None,
            "nothing sent": None}  # fmt: skip


def random_request(choose, number) -> dict:
    """A request to the page: a served one, with up to three of its fields varied (listed in "varied").
    `choose(options)` and `number(low, high)` draw: hypothesis's in the test, random's in the benchmark."""
    request = DEFAULTS | choose(SERVED) | {"varied": []}
    for _ in range(number(0, 3)):
        field = choose(FIELDS)
        request[field] = VARY[field](choose, number)
        request["varied"].append(field)
    return request


def answer_body(kind: str, m, q: dict) -> bytes:
    """The body of kind `kind` (BODIES) for the waiting question q; m: a number (or the random bytes)."""
    if kind == "random bytes":
        return m
    qid, offered = q["id"], [c["mask"] for c in q["candidates"]]
    pick = offered[m % len(offered)]
    text = json.dumps(dict(question=qid, goal=pick))
    bodies = {"a pick": text, "no goal": json.dumps(dict(question=qid, goal=None)), "a pick, padded": text + " " * m,
              "a pick, then junk": text + "x", "a stale question": json.dumps(dict(question=qid - 1, goal=pick)),
              "another question": json.dumps(dict(question=qid + 1 + m, goal=pick)),
              "a goal maybe offered": json.dumps(dict(question=qid, goal=m - 3)),
              "the goal as text": json.dumps(dict(question=qid, goal=str(pick))),
              "the goal as a float": json.dumps(dict(question=qid, goal=float(pick))),
              "the goal NaN": f'{{"question": {qid}, "goal": NaN}}',
              "the question true": json.dumps(dict(question=True, goal=pick)),
              "an extra field": json.dumps(dict(question=qid, goal=pick, by="me")),
              "no goal field": json.dumps(dict(question=qid)), "a list": json.dumps([qid, pick]),
              "deeply nested": "[" * 1000, "empty": "", "none": ""}  # fmt: skip
    return text.encode("utf-16") if kind == "a pick in UTF-16" else bodies[kind].encode()


def on_the_wire(request: dict, a: Asking, q: dict) -> tuple[str, list[str], bytes]:
    """The request line, the header lines and the body that `request` sends."""
    query, x_token = TOKENS[request["token"]][0](a.token)
    before, after = request["query"]  # other fields around the token's: the page reads the token alone
    fields = [*before, *([query[1:]] if query else []), *after]
    query = "?" + "&".join(fields) if fields else ""
    path = request["path"] + ("x" * 70_000 if request["long line"] else "")
    words = [request["method"], path + query, request["extra word"], request["version"]]
    host = request["host"] and request["host"].replace("PORT", str(a.port)).replace("OTHER", str(a.port + 1))
    body = answer_body(*request["body"], q)
    lines = [request["a line that is no header"], host and f"Host: {host}", x_token and f"X-Token: {x_token}",
             request["content type"] is not None and f"Content-Type: {request['content type']}",
             *(f"Content-Length: {v}" for v in LENGTHS[request["length"][0]](len(body), request["length"][1])),
             *(f"{name}: {value}" for name, value in request["junk headers"]),
             *(["X-Many: 1"] * 101 if request["over 100 headers"] else []),
             "X-Long: " + "a" * 70_000 if request["a long header"] else None]  # fmt: skip
    return " ".join(w for w in words if w), [h for h in lines if h], body


def expected(request: dict, line: str, lines: list[str], body: bytes, port: int, q: dict):
    """What SPEC §7.1 says the page answers: the status of the first check that fails, or 200 (None: no reply),
    and the answer the page takes (a dict) or None."""
    if request["nothing sent"] is not None:
        return None, None  # no request line
    if len(line) + 2 > 65536:
        return 414, None
    words = line.split(" ")
    if len(words) == 2:
        return 505, None  # HTTP/0.9
    if VERSIONS.get(words[-1], 400):
        return VERSIONS.get(words[-1], 400), None
    if len(words) != 3:
        return 400, None
    if len(lines) > 100 or max(map(len, lines), default=0) + 2 > 65536:
        return 431, None
    method, path = words[0], words[1].split("?")[0]
    if method not in ("GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "HEAD"):
        return 501, None
    headers = {}  # the values of each header, up to the first line that is no header (which ends them)
    for h in lines:
        if ": " not in h:
            break
        headers.setdefault(h.split(": ")[0].lower(), []).append(h.split(": ", 1)[1])
    if headers.get("host", [""])[0] not in (f"127.0.0.1:{port}", f"localhost:{port}"):
        return 403, None
    if not TOKENS[request["token"]][1]:
        return 403, None
    if method not in ("GET", "POST"):
        return 405, None
    if method == "GET":
        return (200 if path in ("/", "/state") else 405 if path == "/answer" else 404), None
    if path != "/answer":
        return (405 if path in ("/", "/state") else 404), None
    if not CONTENT_TYPES[request["content type"]]:
        return 415, None
    lengths = headers.get("content-length", [])
    if not lengths:
        return 411, None
    if len(lengths) > 1 or not re.fullmatch("[0-9]+", lengths[0].strip(" ")):
        return 400, None
    if len(lengths[0].strip(" ")) > 10 or int(lengths[0]) > 1024:  # SPEC: at most 1,024 bytes
        return 413, None
    n = int(lengths[0])
    if len(body) < n:
        return (408 if request["keep open"] else 400), None
    try:
        data = json.loads(body[:n].decode("utf-8"))
    except (ValueError, RecursionError):
        return 400, None
    if not isinstance(data, dict) or sorted(data) != ["goal", "question"]:
        return 400, None
    if type(data["question"]) is not int or not (data["goal"] is None or type(data["goal"]) is int):
        return 400, None
    if data["question"] != q["id"]:
        return 409, None
    if data["goal"] is not None and data["goal"] not in [c["mask"] for c in q["candidates"]]:
        return 422, None
    return 200, data


def play(a: Asking, request: dict) -> int | None:
    """Sends `request` while a question waits and checks the reply against SPEC §7.1, that the page still
    serves, and that picks.csv gains a row for an answer taken only, exactly one (then a new question waits).
    Returns the status (None: no reply)."""
    if a.partner.question is None:  # taken by a request before, against the rules (reported there): a new one
        a.thread.join(5)
        a.ask_beyond()
    q, before = a.partner.question, a.picks()
    line, lines, body = on_the_wire(request, a, q)
    want, answer = expected(request, line, lines, body, a.port, q)
    data = request["nothing sent"]
    if data is None:
        data = (line + "\r\n" + "".join(h + "\r\n" for h in lines) + "\r\n").encode("latin-1") + body
    reply = exchange(a.port, data, keep_open=request["keep open"])
    status = parsed(reply)[0] if reply else None
    assert status == want and status in (*STATUSES, None), (status, want, line[:200], lines[:6], body[:200])
    assert a.request("GET", "/state")[0] == 200  # still serving
    if answer is None:
        assert a.partner.answer is None and a.partner.question is q and a.thread.is_alive()
        assert a.picks() == before
        return status
    a.thread.join(5)
    assert a.result == answer["goal"]  # the goal the agent is given
    if a.result is not None:
        a.partner.outcome(a.worker, a.result, True)
    rows = a.picks()
    picked, by = ("", "skipped") if a.result is None else (str(a.result), "person")
    assert len(rows) == len(before) + 1 and rows[:-1] == before  # one row more, for this question
    assert (rows[-1]["question"], rows[-1]["picked"], rows[-1]["by"]) == (str(q["id"]), picked, by)
    a.ask_beyond()
    return status


def test_random_requests_get_the_status_the_spec_says_and_only_a_valid_answer_is_recorded_once(asking, monkeypatch):
    monkeypatch.setattr(asking.partner, "frame", lambda w: None)  # no pictures (fast questions; every frame a 404)
    monkeypatch.setattr(asking.partner.args, "person_timeout", 600.0)  # no question times out meanwhile
    monkeypatch.setattr(asking.partner.server.RequestHandlerClass, "timeout", 0.5)  # for "keep open"
    asking.ask_beyond()
    seen = Counter()

    @settings(max_examples=300, deadline=None, derandomize=True)  # the same requests every run
    @given(data=st.data())
    def one_request(data):
        request = random_request(lambda options: data.draw(st.sampled_from(options)),
                                 lambda low, high: data.draw(st.integers(low, high)))  # fmt: skip
        seen[play(asking, request)] += 1

    one_request()
    assert asking.partner.asked > 20 and len(seen) >= 10, seen  # answers taken (each: a new question), refusals


# ------------------------------------------------------------------------------------------------
# The command line: bad values, torchrun, a port in use
# ------------------------------------------------------------------------------------------------
TINY = ["--n-blocks", "3", "--n-epochs", "1", "--n-cycles", "1", "--n-segments", "2", "--n-updates", "1",
        "--batch-size", "16", "--segment-len", "6", "--stable-steps", "3", "--eval-goals-per-class", "1",
        "--threads", "1"]  # fmt: skip


def script(*argv, runs, env=None) -> subprocess.CompletedProcess:
    """gangstr_hme.py's run: in this process (inprocess.py), or in a new one with an environment of its own."""
    if env is None:
        return inprocess.run_script("gangstr_hme.py", *argv, runs_dir=runs)
    cmd = [sys.executable, "gangstr_hme.py", *argv, "--runs-dir", str(runs)]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)


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
