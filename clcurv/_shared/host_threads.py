"""The one host thread pool: numpy work that releases the GIL (the binning's large passes in
parts, the casts of results, the check of user normals while the cloud is binned) runs on
it beside the calling thread. Its tasks never wait for other tasks of the pool, so a caller
that waits for them cannot deadlock it."""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

_POOL, _LOCK = None, threading.Lock()


def cores():
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:              # not on every platform
        return os.cpu_count() or 1


def host_pool():
    """The shared ThreadPoolExecutor (min(4, cores) workers), made on first use."""
    global _POOL
    with _LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=min(4, cores()),
                                       thread_name_prefix="clcurv-host")
    return _POOL


def parallel(fn, pieces):
    """[fn(*p) for p in pieces], the first on the calling thread, the others on the pool.
    Only for a few large numpy calls each, which release the GIL: fine-grained calls on
    several threads were slower (GIL handoffs), measured."""
    futures = [host_pool().submit(fn, *p) for p in pieces[1:]]
    return [fn(*pieces[0])] + [f.result() for f in futures]
