"""Shared helpers of the tests/test_hostile*.py files: run the ``clcurv`` command on a crafted
input in a child process and measure what a user would see (exit code, stderr lines, wall
time, the child's own peak RSS)."""
from __future__ import annotations

import contextlib
import os
import signal
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


#: the child's entry point: the CLI, then its own peak RSS (VmHWM of its address space,
#: which starts at exec; the rusage of a child also counts the parent's pages at fork time)
_LAUNCH = """
import atexit, os, runpy, sys
def _hwm():
    with open("/proc/self/status") as f:
        kb = next(l.split()[1] for l in f if l.startswith("VmHWM"))
    with open(os.environ["CLCURV_TEST_HWM"], "w") as f:
        f.write(kb)
atexit.register(_hwm)
sys.argv[0] = "clcurv"
runpy.run_module("clcurv.cli.main", run_name="__main__")
"""


def run_cli(*args, env=None, timeout=60, preexec_fn=None):
    """Run the ``clcurv`` command line with ``args`` in a child process (killed after
    ``timeout`` seconds, which fails the test); its peak RSS is its VmHWM at exit."""
    import tempfile
    fd, hwm = tempfile.mkstemp(prefix="clcurv-hwm-")
    os.close(fd)
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", _LAUNCH, *map(str, args)],
                           capture_output=True, text=True, timeout=timeout,
                           env={**os.environ, **(env or {}), "CLCURV_TEST_HWM": hwm},
                           preexec_fn=preexec_fn)
    except subprocess.TimeoutExpired as e:
        raise AssertionError(f"clcurv {' '.join(map(str, args))} still running after "
                             f"{timeout} s; stderr: {(e.stderr or b'')[-2000:]!r}") from None
    seconds = time.perf_counter() - t
    with open(hwm) as f:
        text = f.read().strip()
    os.unlink(hwm)
    peak = float(text) / 1024.0 if text else float("nan")   # none: killed before exit
    return Outcome(p.returncode, p.stdout, p.stderr, seconds, peak)


def assert_clean_failure(outcome, code=3, what="", max_seconds=MAX_SECONDS,
                         max_mb=MAX_PEAK_MB):
    """One ``clcurv: error:`` line naming the problem, exit ``code``, within the memory
    budget (run ``compute`` with ``-q``: its progress bars also go to stderr). The budgets
    are the issue's for a crafted file; a failure that needs the OpenCL platform (whose
    start alone takes ~3 s and ~150 MB with PoCL) passes larger ones. Time is not asserted
    (a loaded machine takes longer): ``max_seconds`` is a hang's bound, 20 times the
    budget (run_cli's own timeout also stops a hang)."""
    assert outcome.code == code, (what, outcome.code, outcome.stderr[-2000:])
    assert len(outcome.lines) == 1, (what, outcome.stderr[-2000:])
    assert outcome.lines[0].startswith("clcurv: error: "), (what, outcome.lines)
    assert outcome.seconds < 20 * max_seconds, ("a hang?", what, outcome.seconds)
    assert outcome.peak_mb < max_mb, (what, outcome.peak_mb)


def lzf_literals(data):
    """A valid LZF stream made of literal runs only (for crafting binary_compressed PCD)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


@contextlib.contextmanager
def deadline(seconds):
    """TimeoutError when the block runs longer than ``seconds`` (a hang, not a timing)."""
    def fire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s: a hang")
    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def las_dims(path):
    """(the LasData of ``path``, {dimension name: its values})."""
    import laspy
    import numpy as np
    las = laspy.read(str(path))
    return las, {n: np.asarray(las[n]) for n in las.point_format.dimension_names}


def assert_same_las(a, b):
    """Every dimension of the LAS/LAZ files ``a`` and ``b`` equal, NaN included."""
    import numpy as np
    la, da = las_dims(a)
    lb, db = las_dims(b)
    assert la.header.point_count == lb.header.point_count
    assert list(da) == list(db)
    diff = [n for n in da if not np.array_equal(da[n], db[n], equal_nan=True)]
    assert diff == [], f"dimensions differ: {diff}"
