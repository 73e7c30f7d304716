# Docs: README.md, section "You as the social partner"; docs/SPEC.md §7.1. Imported only with --partner person.
"""A person as the social partner: `python gangstr_hme.py --partner person ...`.

The paper's partner is a program standing in for a person (its Broader impact: "facilitating human
teaching of artificial robots"). Here a person takes its place: at each social moment the run asks, on a
page in the browser, which goal to propose, among exactly the goals the simulated partner would draw
from (SPEC §7): a frontier goal (a stepping stone the agent can reach) or a goal just beyond where the
agent stands (an untried neighbour). The agent then pursues the pick as it would the oracle's.

- The page: the scene now (a rendered frame), the question, each candidate drawn as blocks (stacks,
  pyramids, blocks close together) with its class, "no goal this time"; then the outcome and the frame
  after; between questions the run's state. It polls the run, so it may be opened late or reloaded.
- Never hangs: with no answer within --person-timeout seconds the oracle's uniform draw is taken (and
  recorded as a timeout), so an unattended run finishes. Ctrl-C and SIGTERM drop a pending question: the run
  gives up that cycle, its checkpoint is the state before it, and --resume asks the question again.
- Safe by default: the server binds to 127.0.0.1, every request must carry the run's random token, on a
  loopback address the Host header must name the server (no DNS rebinding), and an answer must name the
  waiting question and one of its candidates, in a small JSON body; anything else is refused (a 4xx, or
  501/505 for a method or an HTTP version it does not speak), in the page's JSON form, and changes nothing.
  The statuses and the order of the checks: Handler's docstring and docs/SPEC.md §7.1.
- picks.csv in the run folder records every question (PICK_COLUMNS); progress.csv counts the person's
  picks, skips and timeouts per epoch.
Standard library only (http.server in a thread, zlib for the PNG frames), besides numpy, mujoco and
plumbing's quiet check that MuJoCo can render.
"""

from __future__ import annotations

import csv
import hmac
import http.server
import ipaddress
import json
import math
import os
import re
import secrets
import struct
import sys
import threading
import time
import urllib.parse
import zlib
from pathlib import Path

import numpy as np

import oracle_graph as og
import plumbing

COLOURS = [("red", "#d93333"), ("blue", "#338cd9"), ("green", "#40b34d"), ("yellow", "#f2bf26"), ("purple", "#994dbf")]
FRAME = 360  # rendered frames are FRAME x FRAME pixels
MAX_BODY = 1024  # bytes: an answer is {"question": 12, "goal": 123456789}
PARTNERS = ("oracle", "person")  # --partner
PICK_COLUMNS = ("time", "epoch", "cycle", "worker", "question", "kind", "here", "offered", "picked", "picked_class",
                "picked_text", "by", "first_goal", "segments", "outcome")  # fmt: skip


# ------------------------------------------------------------------------------------------------
# What a person reads: a configuration in words and in parts
# ------------------------------------------------------------------------------------------------
def config_view(mask: int, n_blocks: int, oracle: og.OracleGraph) -> dict:
    """A config as the page draws it: its bit mask, the blocks on other blocks, the pairs close together,
    its evaluation class ("" if none), and the same in words (block colours as in the scene)."""
    c = og.from_mask(mask, n_blocks)
    close = og.close_pairs(n_blocks)[c[: len(og.close_pairs(n_blocks))] > 0].tolist()
    above = og.above_pairs(n_blocks)[c[len(og.close_pairs(n_blocks)) :] > 0].tolist()
    name = lambda i: COLOURS[i][0]  # noqa: E731
    words = [f"{name(i)} on {name(j)}" for i, j in above]
    stacked = {tuple(sorted(p)) for p in above}
    words += [f"{name(i)} close to {name(j)}" for i, j in close if (i, j) not in stacked]
    return dict(mask=int(mask), above=above, close=close, cls=str(oracle.class_of(c)),
                text=", ".join(words) or "all blocks apart")  # fmt: skip


def png(rgb: np.ndarray) -> bytes:
    """An (h, w, 3) uint8 image as PNG bytes (zlib only)."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))  # filter type 0 per row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


class Rejected(Exception):
    """A request refused: its HTTP status and a one-line reason."""

    def __init__(self, status: int, reason: str):
        super().__init__(reason)
        self.status, self.reason = status, reason


# ------------------------------------------------------------------------------------------------
# The partner: asks the page, waits, falls back on the oracle's draw
# ------------------------------------------------------------------------------------------------
class PersonPartner:
    """The social partner of gangstr_hme.py with a person's choices: the candidates are the simulated
    partner's (`partner`, a SocialPartner), the choice is the person's, made on the page; everything
    else (stepping stones, classes) is the simulated partner's. `clock()` gives (epoch, cycle); `count(k)`
    adds one to the sampler's count k (progress.csv)."""

    def __init__(self, partner, args, clock, count):
        if plumbing.processes() > 1:  # however it came (a resumed run's options included)
            plumbing.fail("--partner person takes one process (one page), not torchrun's")
        self.partner, self.args, self.clock, self.count = partner, args, clock, count
        self.n_blocks = args.n_blocks
        self.token = secrets.token_urlsafe(18)
        self.lock = threading.Condition()
        self.question: dict | None = None  # the one waiting for an answer (under lock)
        self.answer: tuple[int, int | None] | None = None  # (question id, picked mask or None: no goal)
        self.asked, self.last, self.status, self.frames = 0, None, {}, {}
        self.tally = dict(person=0, skipped=0, timeout=0, dropped=0)
        self.open_rows: dict[int, dict] = {}  # worker -> its pick waiting for the outcome
        self.renderers, self.render_problem = {}, None
        self.folder, self.picks, self.stopping = None, None, lambda: False
        self.resumed_at: int | None = None  # the questions asked when the checkpoint --resume continues was saved
        try:  # bound now, before the run folder exists: a port in use exits 2 with nothing written
            self.server = http.server.ThreadingHTTPServer((args.person_host, args.person_port), self.handler())
        except OSError as e:
            plumbing.fail(f"--partner person: cannot serve the page on {args.person_host}:{args.person_port}: {e}")
        self.server.daemon_threads = True
        self.server.handle_error = lambda request, address: None  # a browser gone mid-reply: not the run's concern
        self.port = self.server.server_address[1]
        self.thread = None

    COUNTS = ("person_picks", "person_skips", "person_timeouts")  # progress.csv: who chose, per epoch

    @classmethod
    def of(cls, sampler) -> PersonPartner:
        """The partner of gangstr_hme.py's GoalSampler `sampler`, which holds the hooks (after_cycle: publish;
        epoch_stats: COUNTS; open, close): its simulated partner's candidates, the run's epoch and cycle, and
        the counts in the sampler's stats."""
        args, per_cycle = sampler.args, sampler.args.n_segments * len(sampler.workers)
        clock = lambda: divmod(sampler.learner.segments // per_cycle, args.n_cycles)  # noqa: E731
        return cls(sampler.sp, args, clock, count=lambda k: sampler.stats.update([k]))

    def __getattr__(self, name):  # stepping_stones, oracle, ...: the simulated partner's
        if name == "partner":
            raise AttributeError(name)
        return getattr(self.partner, name)

    # --- the run's side (its main thread) ---------------------------------------------------------
    def open(self, folder: Path, stopping):
        """Serve the page (its address printed on one line) and append to the folder's picks.csv. A resumed
        run's picks.csv is first cut back to the questions its checkpoint had asked: those asked since (lost
        to a kill -9, or in the cycle a stop gave up) are asked again, under the same numbers."""
        self.folder, self.stopping = Path(folder), stopping
        path, rows = self.folder / "picks.csv", []
        if path.exists():
            with path.open(newline="") as f:
                rows = list(csv.DictReader(f))
        if self.resumed_at is not None:
            rows = [r for r in rows if r["question"].isdigit() and int(r["question"]) <= self.resumed_at]
            self.asked = self.resumed_at
        else:  # a new run, or one resumed from a checkpoint written before the questions were checkpointed
            self.asked = max((int(r["question"]) for r in rows if r["question"].isdigit()), default=0)
        with (tmp := path.with_name("picks.csv.tmp")).open("w", newline="") as f:  # replaced whole, or not at all
            writer = csv.DictWriter(f, fieldnames=PICK_COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, path)
        self.picks = path.open("a", newline="")
        self.writer = csv.DictWriter(self.picks, fieldnames=PICK_COLUMNS)
        # polled every 0.05 s, not socketserver's 0.5: close() waits for the next poll (each test's run, too)
        serve = lambda: self.server.serve_forever(poll_interval=0.05)  # noqa: E731
        self.thread = threading.Thread(target=serve, name="person-partner", daemon=True)
        self.thread.start()
        self.publish(None)
        host = self.args.person_host
        shown = f"[{host}]" if ":" in host else host
        print(f"person partner: open http://{shown}:{self.port}/?token={self.token} in a browser "
              f"(questions wait {self.args.person_timeout:g} s, then the oracle draws)", flush=True)  # fmt: skip
        if not self.loopback():
            print(f"person partner: the page is served on {host}, beyond this machine: anyone with the "
                  "address above can answer", file=sys.stderr, flush=True)  # fmt: skip

    def state_dict(self) -> dict:
        """Its checkpoint entry (in the goal sampler's): the questions asked so far."""
        return dict(asked=self.asked)

    def load_state_dict(self, s: dict):
        self.resumed_at = int(s["asked"])  # open() cuts picks.csv back to them

    def close(self):
        for w in list(self.open_rows):
            self.write(self.open_rows.pop(w))  # a pick never pursued (a hidden frontier: --strategy beyond)
        if self.thread is not None:
            self.server.shutdown()
            self.thread = None
        self.server.server_close()
        if self.picks is not None:
            self.picks.close()
            self.picks = None
        for r in self.renderers.values():
            r.close()
        self.renderers = {}

    def frontier_goal(self, graph, current: int, w, elsewhere: bool = False) -> int | None:
        return self.ask(w, "frontier", current, self.partner.frontier_candidates(graph, current, elsewhere), graph)

    def beyond_goal(self, graph, config: int, w) -> int | None:
        return self.ask(w, "beyond", config, self.partner.beyond_candidates(graph, config), graph)

    def ask(self, w, kind: str, here: int, candidates: np.ndarray, graph) -> int | None:
        """Ask the page which candidate to propose, and wait: the person's pick, None for "no goal this
        time", or, with no answer in time, the oracle's uniform draw. A stop requested before an answer raises
        plumbing.CycleGivenUp: the run gives up the cycle (plumbing.RunFolder.cycle) and --resume asks again."""
        if w.index in self.open_rows:  # its previous pick was never pursued: written now, before a checkpoint
            self.write(self.open_rows.pop(w.index))
        if len(candidates) == 0:
            return None  # nothing to propose: nothing to ask
        self.publish(graph)
        epoch, cycle = self.clock()
        views = [config_view(int(m), self.n_blocks, self.partner.oracle) for m in candidates]
        frame = self.frame(w)
        with self.lock:
            self.asked += 1
            qid = self.asked
            self.frames[f"q{qid}"] = frame
            self.frames = {k: v for k, v in self.frames.items() if int(k[1:]) >= qid - 2}  # the recent ones
            self.question = dict(id=qid, worker=w.index, kind=kind, epoch=epoch, cycle=cycle,
                                 goes_there=kind == "beyond" or self.args.strategy != "beyond",
                                 here=config_view(here, self.n_blocks, self.partner.oracle), candidates=views,
                                 deadline=time.monotonic() + self.args.person_timeout,
                                 frame=frame is not None)  # fmt: skip
            self.answer = None
            while self.answer is None and time.monotonic() < self.question["deadline"] and not self.stopping():
                self.lock.wait(0.1)
            answered, self.question = self.answer, None
        if answered is not None:
            picked, by = answered[1], "person" if answered[1] is not None else "skipped"
        else:
            picked, by = self.partner.choose(w, candidates), "dropped" if self.stopping() else "timeout"
        picked = None if by == "dropped" else picked  # a stop's: no goal pursued, the cycle given up
        with self.lock:
            self.tally[by] += 1
        if by != "dropped":  # a stop's: in picks.csv only
            self.count({"person": "person_picks", "skipped": "person_skips", "timeout": "person_timeouts"}[by])
        view = next((v for v in views if v["mask"] == picked), None)
        row = dict(time=time.strftime("%Y-%m-%dT%H:%M:%S"), epoch=epoch, cycle=cycle, worker=w.index, question=qid,
                   kind=kind, here=here, offered=" ".join(str(v["mask"]) for v in views),
                   picked="" if view is None else view["mask"], picked_class="" if view is None else view["cls"],
                   picked_text="" if view is None else view["text"], by=by, first_goal="", segments=0, outcome="",
                   since=len(w.segments))  # fmt: skip
        if picked is None:
            self.write(row)
            self.show_last(row, None)
            if by == "dropped":
                raise plumbing.CycleGivenUp  # the checkpoint: the state before the cycle; --resume asks again
        else:
            self.open_rows[w.index] = row
        return picked

    def outcome(self, w, goal: int, reached: bool | None):
        """The attempt at a pick is over: its row in picks.csv, and the page shows it with the frame after."""
        row = self.open_rows.pop(w.index, None)
        if row is None:
            return
        if row["picked"] != goal:  # not this pick's attempt: the pick's row is kept, without an outcome
            self.write(row)
            return
        tried = w.segments[row["since"] :]
        row |= dict(first_goal=int(og.to_mask(tried[0].g)) if tried else "", segments=len(tried),
                    outcome={True: "reached", False: "not reached", None: "cut off"}[reached])  # fmt: skip
        self.write(row)
        self.show_last(row, self.frame(w))

    def publish(self, graph):
        """The run's state for the page (read by the server thread): agent-graph nodes per class."""
        masks = np.asarray([] if graph is None else graph.masks, dtype=np.int64)
        nodes = {k: int(np.isin(og.to_mask(m), masks).sum()) for k, m in self.partner.oracle.classes.items()}
        epoch, cycle = self.clock()
        with self.lock:
            self.status = dict(epoch=epoch, cycle=cycle, nodes=nodes, agent_nodes=len(masks))

    def show_last(self, row: dict, frame: bytes | None):
        with self.lock:
            self.frames[f"a{row['question']}"] = frame
            self.last = {k: row[k] for k in ("question", "kind", "by", "outcome", "segments")} | dict(
                picked=config_view(row["picked"], self.n_blocks, self.partner.oracle) if row["picked"] != "" else None,
                frame=frame is not None,
            )

    def write(self, row: dict):
        if self.picks is not None:
            self.writer.writerow({k: row[k] for k in PICK_COLUMNS})
            self.picks.flush()

    def frame(self, w) -> bytes | None:
        """The worker's scene now, as PNG; None where MuJoCo cannot render: the page says why beside the scene,
        the terminal once (asked first of plumbing.rendering_problem, which tries quietly: no GLFW warnings)."""
        if not self.renderers and self.render_problem is None:
            self.no_pictures(plumbing.rendering_problem())
        if self.render_problem is not None:
            return None
        try:
            import mujoco  # noqa: PLC0415

            if w.index not in self.renderers:
                self.renderers[w.index] = mujoco.Renderer(w.env.model, height=FRAME, width=FRAME)
            r = self.renderers[w.index]
            r.update_scene(w.env.data, camera="external")
            return png(np.ascontiguousarray(r.render()))
        except Exception as e:  # noqa: BLE001 (no GL here: questions go on without pictures of the scene)
            self.no_pictures(f"{type(e).__name__}: {' '.join(str(e).split())[:120]}")
            return None

    def no_pictures(self, why: str | None):
        if why is not None:
            self.render_problem = f"MuJoCo cannot render here ({why}): install libosmesa6, set MUJOCO_GL=osmesa"
            print(f"person partner: no pictures of the scene on the page: {self.render_problem}", file=sys.stderr,
                  flush=True)  # fmt: skip

    # --- the server's side (its threads) ----------------------------------------------------------
    def loopback(self) -> bool:
        try:
            return ipaddress.ip_address(self.args.person_host).is_loopback
        except ValueError:
            return self.args.person_host == "localhost"

    def check(self, handler) -> str:
        """The request's path, once its Host header and token are right (else Rejected, 4xx)."""
        host = handler.headers.get("Host", "")
        names = {self.args.person_host, "127.0.0.1", "localhost"}
        if self.loopback() and host not in {f"{name}:{self.port}" for name in names}:
            raise Rejected(403, f"Host {host!r} is not this server's")
        url = urllib.parse.urlsplit(handler.path)
        query = urllib.parse.parse_qs(url.query)
        token = query.get("token", [""])[0] or handler.headers.get("X-Token", "")
        if not hmac.compare_digest(token.encode(), self.token.encode()):
            raise Rejected(403, "wrong or missing token (use the address the run printed)")
        return url.path

    def state(self) -> dict:
        """What the page shows: the run's state, the waiting question, the last outcome."""
        with self.lock:
            q = self.question
            question = None
            if q is not None:
                left = max(0.0, q["deadline"] - time.monotonic())
                question = {k: v for k, v in q.items() if k != "deadline"} | dict(seconds_left=round(left, 1))
            state = dict(run=self.status | dict(asked=self.asked, **self.tally), question=question, last=self.last,
                         n_blocks=self.n_blocks, timeout=self.args.person_timeout,
                         render_problem=self.render_problem)  # fmt: skip
        state["run"] |= self.progress()
        return state

    def progress(self) -> dict:
        """The last logged epoch and its global SR, from progress.csv (written by the run, read here)."""
        try:
            with (self.folder / "progress.csv").open(newline="") as f:
                rows = list(csv.DictReader(f))
            return dict(logged_epoch=int(rows[-1]["epoch"]), global_sr=float(rows[-1]["global_sr"])) if rows else {}
        except (OSError, TypeError, ValueError, KeyError, IndexError):
            return {}

    def take_answer(self, body: bytes):
        """An answer from the page: {"question": id, "goal": mask or null}, in UTF-8. Checked whole before it counts."""
        try:
            data = json.loads(body.decode("utf-8"))  # not json.loads(body), which would take UTF-16 and UTF-32 too
        except (ValueError, UnicodeDecodeError, RecursionError):
            raise Rejected(400, "the body is not JSON") from None
        if not isinstance(data, dict) or set(data) != {"question", "goal"}:
            raise Rejected(400, 'the body must be {"question": <id>, "goal": <mask or null>}')
        qid, goal = data["question"], data["goal"]
        if type(qid) is not int or (goal is not None and type(goal) is not int):
            raise Rejected(400, "question and goal must be integers (goal: or null)")
        with self.lock:
            q = self.question
            if q is None or q["id"] != qid:
                known = 0 < qid <= self.asked
                raise Rejected(409, f"question {qid} is {'no longer waiting (stale)' if known else 'unknown'}")
            if goal is not None and goal not in [c["mask"] for c in q["candidates"]]:
                raise Rejected(422, f"goal {goal} was not offered in question {qid}")
            if self.answer is not None:
                raise Rejected(409, f"question {qid} is already answered")
            self.answer = (qid, goal)
            self.lock.notify_all()

    def handler(self):
        partner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            """One request per connection (HTTP/1.0), every reply with a status line, JSON but for the page and
            its frames. Checked in this order, the first check that fails answers (SPEC §7.1):
            414 a request line over 64 KiB; 505 HTTP/0.9 (no version, or major version 0) or HTTP/2 and above;
            400 a request line that is not `METHOD target HTTP/x.y`; 431 over 100 headers or a line over 64 KiB;
            501 a method other than GET, POST, PUT, DELETE, PATCH, OPTIONS, HEAD; 403 a foreign Host (on a
            loopback address), then a wrong or missing token; 405 PUT ... HEAD, GET /answer, POST / or /state;
            404 any other page, or a frame not kept; then a POST /answer: 415 not application/json; 411 no
            Content-Length; 400 not one, or not in ASCII digits; 413 over MAX_BODY; 408 no byte of the body
            for `timeout` s (per read); 400 the body ends early, or is not {"question": <int>, "goal": <int or null>} in
            UTF-8; 409 a question not waiting, or answered already; 422 a goal not offered; 200 the answer is
            taken. 500: a failure of the server's own, for that request alone. A connection that sends nothing,
            or not a whole request line and headers within `timeout`, is closed without a reply."""

            server_version = "person-partner"
            timeout = 15  # seconds a connection may keep a thread waiting for its request

            def log_message(self, *a):  # quiet: the run's console is the training's
                pass

            def parse_request(self):
                # HTTP/0.9 is refused before its (absent) headers are awaited: its reply would have no status line
                self.requestline = str(self.raw_requestline, "iso-8859-1").rstrip("\r\n")
                words = self.requestline.split()
                if len(words) == 2 or (len(words) > 2 and re.fullmatch(r"HTTP/0+\.[0-9]+", words[-1])):
                    self.command = None
                    self.send_error(505, "HTTP/0.9 is not served: send HTTP/1.0 or HTTP/1.1")
                    return False
                return super().parse_request()

            def send_error(self, code, message=None, explain=None):
                """The standard library's refusals (the request line, the version, the headers, the method) in
                the page's JSON form, with a status line whatever version the request named."""
                self.request_version, self.close_connection = "HTTP/1.0", True
                self.reply(code, dict(error=(message or self.responses.get(code, ("refused",))[0])[:200]))

            def send(self, status: int, body: bytes, kind: str):
                self.send_response(status)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.send_header("X-Content-Type-Options", "nosniff")
                self.send_header("Referrer-Policy", "no-referrer")
                self.end_headers()
                self.wfile.write(body)

            def reply(self, status: int, data):
                self.send(status, json.dumps(data).encode(), "application/json")

            def guarded(self, serve):
                try:
                    serve(partner.check(self))
                except Rejected as e:
                    self.reply(e.status, dict(error=e.reason))
                except Exception as e:  # never the run's problem: this request fails alone
                    self.reply(500, dict(error=f"{type(e).__name__}: {e}"))

            def do_GET(self):
                self.guarded(self.get)

            def do_POST(self):
                self.guarded(self.post)

            def refuse(self):
                def serve(path: str):
                    raise Rejected(405, f"{self.command} is not served")

                self.guarded(serve)

            do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_HEAD = refuse

            def get(self, path: str):
                if path == "/":
                    self.send(200, PAGE.encode(), "text/html; charset=utf-8")
                elif path == "/state":
                    self.reply(200, partner.state())
                elif path.startswith("/frame/") and path.endswith(".png"):
                    with partner.lock:
                        frame = partner.frames.get(path[len("/frame/") : -len(".png")])
                    if frame is None:
                        raise Rejected(404, f"no frame {path}")
                    self.send(200, frame, "image/png")
                elif path == "/answer":
                    raise Rejected(405, "answers are POSTed")
                else:
                    raise Rejected(404, f"no such page {path!r}")

            def post(self, path: str):
                if path != "/answer":
                    raise Rejected(404 if path not in ("/", "/state") else 405, f"nothing to POST at {path!r}")
                got = self.headers.get("Content-Type")
                if (got or "").split(";")[0].strip(" \t").lower() != "application/json":
                    named = "no Content-Type" if got is None else repr(got[:80])  # (a header's line: up to 64 KiB)
                    raise Rejected(415, f"answers are application/json, not {named}")
                partner.take_answer(self.body())
                self.reply(200, dict(ok=True))

            def body(self) -> bytes:
                """The body, whole: one Content-Length in digits, at most MAX_BODY, every byte within `timeout`."""
                lengths = self.headers.get_all("Content-Length") or []
                if not lengths:
                    raise Rejected(411, "Content-Length is missing")
                value = lengths[0].strip(" \t")
                if len(lengths) > 1 or not (value.isascii() and value.isdigit()):
                    raise Rejected(400, f"Content-Length must be one number of bytes, got {', '.join(lengths)[:40]!r}")
                if len(value.lstrip("0")) > len(str(MAX_BODY)) or int(value) > MAX_BODY:  # no int() of 5,000 digits
                    raise Rejected(413, f"the body is {value[:20]} bytes; an answer takes at most {MAX_BODY}")
                length = int(value)
                try:
                    body = self.rfile.read(length)
                except TimeoutError:
                    raise Rejected(408, f"no byte of the body for {self.timeout:g} s") from None
                if len(body) < length:  # the client closed its side early: a cut answer is no answer
                    raise Rejected(400, f"the body ended after {len(body)} of its {length} bytes")
                return body

        return Handler


# ------------------------------------------------------------------------------------------------
# The page (one file, no library: it polls /state and POSTs /answer)
# ------------------------------------------------------------------------------------------------
PAGE = (
    """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>HME: you as the social partner</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,sans-serif;margin:0;background:#f4f4f2;color:#222}
header{background:#2d3e50;color:#fff;padding:10px 18px}header h1{font-size:18px;margin:0}
#status{font-size:13px;margin-top:4px;opacity:.9}main{display:flex;gap:18px;padding:14px 18px;flex-wrap:wrap}
section{background:#fff;border-radius:8px;padding:12px;box-shadow:0 1px 3px #0002}
#scene img{width:360px;height:360px;border-radius:6px;background:#ddd}#noframe{max-width:360px;font-size:13px}
#cands{display:flex;flex-wrap:wrap;gap:10px;max-width:760px}
button.candidate{background:#fff;border:2px solid #ccd;border-radius:8px;padding:6px;cursor:pointer;width:170px}
button.candidate:hover{border-color:#2d7be5}button.skip{margin-top:12px;padding:8px 14px}
.cls{font-weight:600}.text{font-size:12px;color:#555}.wait{color:#777}
#nodes td{padding:1px 8px;font-size:13px}#last img{width:240px;height:240px;border-radius:6px}
</style></head><body>
<header><h1>Help Me Explore: you are the social partner</h1><div id="status">connecting...</div></header>
<main>
<section id="scene"><h3 id="scenetitle">The scene</h3><div id="frame"></div><div id="noframe" class="wait"></div>
<div id="here"></div></section>
<section id="ask"><h3 id="title">Waiting for the agent to ask...</h3><div id="hint" class="wait"></div>
<div id="cands"></div><div id="skipbox"></div></section>
<section id="side"><h3>Last outcome</h3><div id="last" class="wait">none yet</div>
<h3>Agent-graph nodes per class</h3><table id="nodes"></table></section>
</main>
<script>
const TOKEN = new URLSearchParams(location.search).get("token") || "";
const T = `token=${encodeURIComponent(TOKEN)}`;
const COLOURS = """
    + json.dumps([hexa for _, hexa in COLOURS])
    + """;
const $ = (id) => document.getElementById(id);
let shown = 0;  // the question on screen (minus its id once answered)

function layout(v, n) {
  // blocks on others sit above them (a pyramid's top between its two); close ones side by side
  const on = {}, link = Array.from({length: n}, () => []);
  for (const [i, j] of v.above) (on[i] = on[i] || []).push(j);
  for (const [i, j] of v.close.concat(v.above)) { link[i].push(j); link[j].push(i); }
  const group = Array(n).fill(-1);
  let groups = 0;
  for (let s = 0; s < n; s++) {
    if (group[s] >= 0) continue;
    const todo = [s];
    group[s] = groups;
    while (todo.length) {
      for (const x of link[todo.pop()]) if (group[x] < 0) { group[x] = groups; todo.push(x); }
    }
    groups++;
  }
  const x = Array(n), y = Array(n);
  let col = 0;
  for (let k = 0; k < groups; k++) {
    for (let b = 0; b < n; b++) if (group[b] === k && !on[b]) { x[b] = col++; y[b] = 0; }
    col += 0.6;
  }
  for (let pass = 0; pass < n; pass++) {
    for (let b = 0; b < n; b++) {
      if (!on[b] || !on[b].every((s) => y[s] !== undefined)) continue;
      x[b] = on[b].reduce((a, s) => a + x[s], 0) / on[b].length;
      y[b] = Math.max(...on[b].map((s) => y[s])) + 1;
    }
  }
  return {x, y, width: Math.max(col, n)};
}

function drawConfig(v, n, size) {
  const {x, y, width} = layout(v, n), u = size / width;
  const h = Math.max(1, ...y.map((t) => (t || 0) + 1)), H = u * (h + 0.4);
  let svg = `<svg width="${size}" height="${Math.min(size, H)}" viewBox="0 0 ${width * u} ${H}">`;
  svg += `<rect x="0" y="${u * h}" width="100%" height="${u * 0.4}" fill="#b08c62"/>`;
  for (let b = 0; b < n; b++) {
    const top = (h - 1 - (y[b] || 0)) * u + 2;
    svg += `<rect x="${x[b] * u + 2}" y="${top}" width="${u - 4}" height="${u - 4}" rx="4"`;
    svg += ` fill="${COLOURS[b]}" stroke="#333"/>`;
  }
  return svg + "</svg>";
}

function view(v, n, size) {
  return `${drawConfig(v, n, size)}<div class="cls">${v.cls || "no class"}</div><div class="text">${v.text}</div>`;
}

async function answer(id, goal) {
  const body = JSON.stringify({question: id, goal: goal});
  try {
    const r = await fetch(`/answer?${T}`, {method: "POST", headers: {"Content-Type": "application/json"}, body});
    $("hint").textContent = r.ok ? "sent: the agent is on it" : (await r.json()).error;
  } catch (e) {
    $("hint").textContent = "not sent: the run is not answering";
  }
  shown = -id;
  tick();
}

function showRun(s) {
  const run = s.run;
  let line = `epoch ${run.epoch ?? "-"}, cycle ${run.cycle ?? "-"}`;
  if (run.global_sr !== undefined) line += ` | global SR ${run.global_sr.toFixed(2)} (epoch ${run.logged_epoch})`;
  line += ` | questions: ${run.asked} asked, ${run.person} picked by you, ${run.skipped} skipped,`;
  line += ` ${run.timeout} timed out | agent graph: ${run.agent_nodes ?? 0} nodes`;
  $("status").textContent = line;
  const rows = Object.entries(run.nodes || {}).map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`);
  $("nodes").innerHTML = rows.join("");
  if (!s.last) return;
  const l = s.last, pic = l.frame ? `<img src="/frame/a${l.question}.png?${T}">` : "";
  const what = l.picked ? `${l.picked.cls || "no class"}: ${l.picked.text}` : "no goal";
  const how = l.outcome ? `, <b>${l.outcome}</b> in ${l.segments} segment(s)` : "";
  $("last").innerHTML = `<div>question ${l.question} (${l.kind}): ${what}, chosen by ${l.by}${how}</div>${pic}`;
}

function showQuestion(q, n) {
  $("title").textContent = q.kind !== "frontier"
    ? `Question ${q.id}: which new configuration should it try? (a goal beyond)`
    : q.goes_there ? `Question ${q.id}: which known configuration should the agent go to? (a frontier goal)`
    : `Question ${q.id}: from which known configuration should the next goal go on? (a frontier, not visited)`;
  $("scenetitle").textContent = "The scene now";
  $("frame").innerHTML = q.frame ? `<img alt="the scene" src="/frame/q${q.id}.png?${T}">` : "";
  $("here").innerHTML = `<p>The agent stands at:</p>${view(q.here, n, 150)}`;
  $("cands").innerHTML = "";
  for (const c of q.candidates) {
    const b = document.createElement("button");
    b.className = "candidate";
    b.dataset.goal = c.mask;
    b.innerHTML = view(c, n, 150);
    b.onclick = () => answer(q.id, c.mask);
    $("cands").appendChild(b);
  }
  const skip = document.createElement("button");
  skip.className = "skip";
  skip.textContent = "No goal this time";
  skip.onclick = () => answer(q.id, null);
  $("skipbox").replaceChildren(skip);
}

async function tick() {
  let s;
  try {
    const r = await fetch(`/state?${T}`);
    s = await r.json();
    if (!r.ok) { $("status").textContent = s.error; return; }
  } catch (e) {
    $("status").textContent = "the run is not answering (finished or stopped?)";
    return;
  }
  showRun(s);
  $("noframe").textContent = s.render_problem ? `No picture of the scene: ${s.render_problem}` : "";
  const q = s.question;
  if (!q) {
    if (shown !== 0) {
      $("scenetitle").textContent = `The scene at question ${Math.abs(shown)}`;
      shown = 0;
      $("title").textContent = "Waiting for the agent to ask...";
      $("cands").innerHTML = "";
      $("skipbox").innerHTML = "";
    }
    $("hint").textContent = "";
    return;
  }
  $("hint").textContent = `${q.seconds_left.toFixed(0)} s left, then the oracle draws one`;
  if (shown === q.id || shown === -q.id) return;
  shown = q.id;
  showQuestion(q, s.n_blocks);
}

setInterval(tick, 700);
tick();
</script></body></html>
"""
)


def check_args(a) -> str | None:
    """The options of this file (--partner, --person-*): the first bad value, described, or None."""
    if a.partner not in PARTNERS:
        return f"--partner must be one of {', '.join(PARTNERS)}, got {a.partner!r}"
    if not (math.isfinite(a.person_timeout) and a.person_timeout > 0):
        return f"--person-timeout must be a number of seconds above 0, got {a.person_timeout}"
    if not 0 <= a.person_port <= 65535:
        return f"--person-port must be in [0, 65535], got {a.person_port}"
    if not a.person_host or ":" in a.person_host:
        return f"--person-host must be an IPv4 address or a host name, got {a.person_host!r}"
    if a.partner == "person" and plumbing.processes() > 1:
        return f"--partner person takes one process (one page), not {plumbing.processes()} under torchrun"
    if a.partner == "person" and a.sp_ratio == 0 and a.ask_after == 0 and not a.eval_only:
        return "--partner person needs social cycles to ask in: give --sp-ratio above 0 or --ask-after above 0"
    return None
