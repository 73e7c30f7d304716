"""A training script's run in the test's own process, answered as a new process's would be.

A new process spends 2-3 s of a 2-core machine's CPU importing torch before the run's first line: most of
what a tiny run costs, and most of what the suite costs. The tests that need a process of its own (a signal,
kill -9, torchrun, an environment of its own, a fork run as its user runs it) start one; the others run the
script's main() here.
"""

import contextlib
import importlib
import io
import signal
import subprocess
from pathlib import Path


class TimedOut(BaseException):  # not an Exception: no `except Exception` in the run takes it for its own
    """A run in the test's process still running after its time: the test fails, as a new process's run
    would be killed (a bug that lets a tiny run go on with the full defaults would take hours)."""


def run_script(script: str, *argv, runs_dir=None, timeout: float = 120) -> subprocess.CompletedProcess:
    """`python script *argv [--runs-dir runs_dir]`, run by its main() in this process: its exit code (as main
    returns it, or as it exits: 2 for bad input) and everything it printed. An exception is raised, not
    printed; TimedOut after `timeout` seconds (SIGALRM). Ctrl-C and SIGTERM are handed back to pytest
    afterwards (a run's Stopper takes them)."""
    main = importlib.import_module(Path(script).stem).main
    argv = [str(a) for a in argv] + (["--runs-dir", str(runs_dir)] if runs_dir is not None else [])
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)}

    def expire(signum, frame):
        raise TimedOut(f"{script} {' '.join(argv)}: still running after {timeout:g} s")

    out, err = io.StringIO(), io.StringIO()
    signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, timeout)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    except SystemExit as e:
        code = e.code
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return subprocess.CompletedProcess([script, *argv], code, out.getvalue(), err.getvalue())
