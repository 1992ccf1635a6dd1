"""Host memory for large arrays: the blocks of the arrays a caller drops are kept for the
next call, as :mod:`clcurv.runtime.memory` keeps device buffers.

A 1M-point ``curvature(P, r, method="variation")`` returns ~65 MB of new arrays (normals,
eigenvalues, variation: float64; count, status) and its binning makes ~25 MB of
temporaries. Fresh memory is not free: the operating system faults in and zeroes every new
page on its first write, and with transparent huge pages in ``madvise`` mode (numpy asks
for them) a fault may first wait for memory compaction. On the 2-core bench machine the
result arrays alone cost 17 ms per call on plain pages and 12-48 ms on huge pages, against
7.5 ms when their pages had been written before. So :func:`empty` hands out arrays whose
memory is an anonymous mapping from a pool: when the last array (or view) on a block is
gone, the block goes back to the pool (a :func:`weakref.finalize` on the block's holder
array), and the next request of a similar size (bins of 1/16 of a power of two) reuses its
pages.

What that means for a user:
  - after a call's results are dropped, their memory stays with the process, up to
    :func:`hold_limit` bytes (``min(1 GiB, RAM / 16)``); beyond that the blocks returned
    longest ago are unmapped, so sizes no longer asked for make room for current ones;
  - :func:`clcurv.release_memory` (no argument) unmaps what the pool holds now;
    ``CLCURV_POOL=0`` in the environment (read at the first request) turns holding off for
    host and device pools alike;
  - the arrays are ordinary writable, C-contiguous ndarrays; they do not own their memory
    (``a.flags.owndata`` is False), so ``a.resize()`` in place is refused, as for any view.

Arrays below :data:`MIN_BYTES` come from ``numpy.empty``. New mappings are plain pages: they
do not ask for transparent huge pages, as numpy does for its own large arrays. The results
are written once and in sequence, where huge pages save little, while a fresh huge page may
first wait for memory compaction (numpy issue #31590). On the bench machine (Zen 4 EPYC
VM, THP ``madvise``), ``features(P, [r1, r2, r3])`` on 1M points (387 MB of results) took
424-491 ms (median 443) as the first call of a fresh process, against 497-938 ms (median
676) when the mappings asked for huge pages; warm calls the same (232-265 against 247-292
ms, 4 fresh processes each, alternated).
"""
from __future__ import annotations

import math
import mmap
import os
import threading
import weakref

import numpy as np

#: arrays smaller than this come from numpy.empty (the allocator's own reuse is cheap there)
MIN_BYTES = 1 << 20
#: the most the pool holds unused, whatever the machine
MAX_HOLD = 1 << 30

_LOCK = threading.RLock()          # a finalizer may run inside a locked section (GC)
_FREE: list = []                   # (bin size, mapping), oldest returned first
_STATE = {"held": 0, "holding": None}


def _holding():
    if _STATE["holding"] is None:
        _STATE["holding"] = os.environ.get("CLCURV_POOL", "1").strip() != "0"
    return _STATE["holding"]


def hold_limit():
    """Bytes the pool may hold unused: min(:data:`MAX_HOLD`, physical memory / 16), 0 when
    holding is off."""
    if not _holding():
        return 0
    try:
        ram = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        ram = 16 * MAX_HOLD
    return int(min(MAX_HOLD, ram // 16))


def _bin(nbytes):
    """``nbytes`` rounded up to a multiple of 1/16 of its power of two (and of the page)."""
    step = max(1 << max(int(math.ceil(math.log2(nbytes))) - 4, 0), mmap.PAGESIZE)
    return -(-nbytes // step) * step


def _give_back(block, size):
    """Finalizer of a block's holder: keep the mapping for the next request, letting go of
    the blocks returned longest ago when the pool would exceed :func:`hold_limit` (so that
    blocks of sizes no longer asked for do not crowd out the current ones). A mapping let
    go of is unmapped with its last reference (for the block being returned: just after
    its holder has released its buffer; the finalizer runs first, so it must not close the
    mapping)."""
    limit = hold_limit()
    with _LOCK:
        if size > limit:
            return
        _FREE.append((size, block))
        _STATE["held"] += size
        while _STATE["held"] > limit:
            old, _ = _FREE.pop(0)
            _STATE["held"] -= old


def empty(shape, dtype=np.float64):
    """An uninitialised C-contiguous array of ``shape`` and ``dtype``, its memory from the
    pool when it has at least :data:`MIN_BYTES` (see the module docstring)."""
    dtype = np.dtype(dtype)
    shape = (shape,) if np.isscalar(shape) else tuple(shape)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes < MIN_BYTES or not _holding():
        return np.empty(shape, dtype)
    size = _bin(nbytes)
    block = None
    with _LOCK:
        for j in range(len(_FREE) - 1, -1, -1):        # the most recently returned first
            if _FREE[j][0] == size:
                block = _FREE.pop(j)[1]
                _STATE["held"] -= size
                break
    if block is None:
        # private (copy-on-write after a fork, as numpy's memory), not mmap's default shared
        block = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE)
    holder = np.frombuffer(block, np.uint8, count=nbytes)
    fin = weakref.finalize(holder, _give_back, block, size)
    fin.atexit = False
    return holder.view(dtype).reshape(shape)


def release():
    """Unmap every block the pool holds unused; returns the bytes freed."""
    with _LOCK:
        blocks = [b for _, b in _FREE]
        _FREE.clear()
        freed, _STATE["held"] = _STATE["held"], 0
    for b in blocks:
        try:
            b.close()
        except BufferError:     # still exported (a holder being deallocated): unmapped
            pass                # with its last reference instead
    return freed
