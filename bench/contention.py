"""Is the machine free? A PoCL spin kernel timed with 1 and 2 threads around every measured
block (:class:`Guard`); blocks measured while another process held a core are measured
again, and flagged if still busy."""
from __future__ import annotations

import time

from .harness import loadavg, log, run_python
from .targets import THREADS_MIN_GAIN

_THREAD_PROBE = r"""
import sys, time
import numpy as np
import pyopencl as cl
SRC = '''__kernel void spin(__global float *out, const int iters) {
    const size_t g = get_global_id(0);
    float a = (float)g * 1e-6f, b = 0.5f;
    for (int i = 0; i < iters; ++i) { a = fma(a, 0.9999f, 1e-7f); b = fma(b, 0.9998f, a); }
    out[g] = a + b;
}'''
plat = next(p for p in cl.get_platforms() if "portable" in p.name.lower())
ctx = cl.Context(plat.get_devices()[:1])
q = cl.CommandQueue(ctx)
k = cl.Program(ctx, SRC).build().spin
n = 1 << 16
out = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, 4 * n)
best = float("inf")
for i in range(4):
    t0 = time.perf_counter()
    k(q, (n,), (64,), out, np.int32(2000))
    q.finish()
    if i:
        best = min(best, time.perf_counter() - t0)
print(best)
"""


def thread_check():
    """Time a small compute kernel on PoCL with 1 and 2 threads (fresh processes).

    On a machine whose cores are free, 2 threads are ~2x faster; when they are not, the
    machine is shared and every figure below is pessimistic.
    """
    try:
        t1 = float(run_python(_THREAD_PROBE, env={"POCL_MAX_PTHREAD_COUNT": "1"}))
        t2 = float(run_python(_THREAD_PROBE, env={"POCL_MAX_PTHREAD_COUNT": "2"}))
    except Exception as exc:  # noqa: BLE001 - no PoCL: report, do not stop the benchmark
        return {"ok": None, "note": f"thread check unavailable: {exc}"}
    gain = t1 / t2
    return {"one_thread_s": t1, "two_threads_s": t2, "gain": gain, "loadavg": loadavg(),
            "ok": gain >= THREADS_MIN_GAIN}


def describe_threads(check, when):
    if check.get("ok") is None:
        return f"{when}: {check['note']}"
    return (f"{when}: 1 thread {check['one_thread_s'] * 1e3:.0f} ms, 2 threads "
            f"{check['two_threads_s'] * 1e3:.0f} ms -> x{check['gain']:.2f}"
            f"{'' if check['ok'] else ' BUSY'}, loadavg {' '.join(check['loadavg'])}")


class Guard:
    """Thread checks around every measured block, waiting up to ``wait`` s for free cores.

    The machine may be shared: a block measured while another process holds a core is
    flagged (its figures are pessimistic, and ratios against a peer measured at another
    time are off)."""

    def __init__(self, wait, retries):
        self.wait = wait
        self.retries = retries
        self.checks = {}

    def _quiet(self):
        deadline = time.monotonic() + self.wait
        check = thread_check()
        while check.get("ok") is False and time.monotonic() < deadline:
            log(f"  cores busy (x{check['gain']:.2f}), waiting")
            time.sleep(5)
            check = thread_check()
        return check

    def block(self, label, fn):
        """Run ``fn()`` between two thread checks, again (up to ``retries`` times) while a
        check says the cores were busy; return the result of the last run."""
        for attempt in range(1 + self.retries):
            self.checks[f"{label}, before"] = before = self._quiet()
            log(describe_threads(before, f"{label}, before"))
            result = fn()
            self.checks[f"{label}, after"] = after = thread_check()
            log(describe_threads(after, f"{label}, after"))
            if before.get("ok") is not False and after.get("ok") is not False:
                break
            if attempt < self.retries:
                log(f"{label}: cores were busy, measuring again")
        return result

    def gains(self, label):
        """'2.01x / 1.98x': the 2-thread gain before / after the block."""
        g = [self.checks.get(f"{label}, {w}", {}).get("gain") for w in ("before", "after")]
        return " / ".join("–" if x is None else f"{x:.2f}x" for x in g)

    def busy(self):
        return sorted({k.rsplit(",", 1)[0] for k, c in self.checks.items() if c.get("ok") is False})
