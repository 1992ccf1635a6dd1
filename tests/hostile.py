"""Shared helpers of the tests/test_hostile*.py files: run the ``clcurv`` command on a crafted
input in a child process and measure what a user would see (exit code, stderr lines, wall
time, the child's peak RSS)."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass

#: what a crafted bad file may cost the CLI (issue 10): one line, exit 3, <5 s, <500 MB
MAX_SECONDS = 5.0
MAX_PEAK_MB = 500.0


@dataclass
class Outcome:
    code: int
    stdout: str
    stderr: str
    seconds: float
    peak_mb: float

    @property
    def lines(self):
        return [l for l in self.stderr.splitlines() if l.strip()]


def run_cli(*args, env=None, timeout=60, preexec_fn=None):
    """Run ``python -m clcurv.cli ARGS``; the child's own peak RSS comes from ``os.wait4``
    (a timer kills it after ``timeout`` seconds, which fails the test)."""
    import threading
    t = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "clcurv.cli", *map(str, args)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=None if env is None else {**os.environ, **env},
                         preexec_fn=preexec_fn)
    got = {}
    readers = [threading.Thread(target=lambda k=k, f=f: got.__setitem__(k, f.read()))
               for k, f in (("out", p.stdout), ("err", p.stderr))]
    for r in readers:
        r.start()
    killer = threading.Timer(timeout, p.kill)
    killer.start()
    try:
        _, status, usage = os.wait4(p.pid, 0)
    finally:
        killer.cancel()
    for r in readers:
        r.join()
    p.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - t
    if seconds >= timeout:
        raise AssertionError(f"clcurv {' '.join(map(str, args))} still running after "
                             f"{timeout} s; stderr: {got.get('err', '')[-2000:]}")
    return Outcome(p.returncode, got["out"], got["err"], seconds, usage.ru_maxrss / 1024.0)


def assert_clean_failure(outcome, code=3, what="", max_seconds=MAX_SECONDS,
                         max_mb=MAX_PEAK_MB):
    """One ``clcurv: error:`` line naming the problem, exit ``code``, within the budgets
    (run ``compute`` with ``-q``: its progress bars also go to stderr). The budgets are the
    issue's for a crafted file; a failure that needs the OpenCL platform (whose start
    alone takes ~3 s and ~150 MB with PoCL) passes larger ones."""
    assert outcome.code == code, (what, outcome.code, outcome.stderr[-2000:])
    assert len(outcome.lines) == 1, (what, outcome.stderr[-2000:])
    assert outcome.lines[0].startswith("clcurv: error: "), (what, outcome.lines)
    assert outcome.seconds < max_seconds, (what, outcome.seconds)
    assert outcome.peak_mb < max_mb, (what, outcome.peak_mb)
