"""Device scratch memory: a pool per device that keeps the buffers one call frees for the
next call.

Every public call bins its cloud into fresh device buffers (coordinates, grid, output
records: ~150 bytes per point in float32) and frees them when it returns. Fresh memory is
not free: on a CPU device every new page is faulted in and zeroed when a kernel first
writes it, which cost ~25 ms of the ~190 ms of ``curvature(P, r, method="variation")`` on
1M points (PoCL, 2 cores; the records' scattered stores alone ~15 ms). So device buffers
come from a :class:`pyopencl.tools.MemoryPool` per device, as CuPy's and PyTorch's
allocators do: a freed buffer goes back to the pool and the next request of a similar size
(bins of 1/16 of a power of two) reuses it.

What that means for a user:
  - memory the last calls used stays allocated after they return (for a 1M-point call,
    ~150-300 MB), up to :func:`hold_limit` (a quarter of clcurv's device budget,
    :func:`clcurv.runtime.limits.device_limits`); beyond that the pool lets go of what it
    holds;
  - :func:`release_memory` gives it back now; ``CLCURV_POOL=0`` in the environment (read
    when a device's pool is made) turns holding off: every buffer is then freed at once;
  - a stage that has to run in chunks (the device is short of memory,
    :meth:`clcurv.grid.cloud.DeviceCloud.plan`) first releases what the pool holds, and tiled
    runs (:func:`clcurv.tiles.engine.compute_tile`, :func:`clcurv.tiles.scale.step_tile`) release
    it after each tile, so that their memory budget holds as if every buffer were freed;
  - simulators (Oclgrind) get exact-size buffers that are never reused, so that their
    out-of-bounds checks see the buffer a kernel was given.

Pooled buffers may be larger than asked for; kernels never rely on a buffer's size.
"""
from __future__ import annotations

import os
import threading

import numpy as np
import pyopencl as cl
import pyopencl.tools as clt

from clcurv._shared import host_memory
from clcurv.runtime.device import get_device
from clcurv.runtime.limits import device_limits

_POOLS, _LOCK = {}, threading.Lock()
#: The fraction of the device budget (clcurv.runtime.limits.device_limits) the pool may
#: hold unused between calls.
HOLD_FRACTION = 0.25
#: Debugging: when set (a float32 value, e.g. NaN), every buffer is filled with it before it
#: is handed out, as glibc's MALLOC_PERTURB_ does; tests/test_memory.py uses NaN to show that
#: no kernel reads memory it did not write.
FILL = None


def _pool(device):
    """The MemoryPool of ``device`` (a clcurv.runtime.device.Device), or None for a simulator."""
    if device.info.simulator:
        return None
    with _LOCK:
        pool = _POOLS.get(id(device))
        if pool is None:
            pool = clt.MemoryPool(clt.ImmediateAllocator(device.queue))
            if os.environ.get("CLCURV_POOL", "1").strip() == "0":
                pool.stop_holding()
            _POOLS[id(device)] = pool
        return pool


def hold_limit(device):
    """Bytes the pool of ``device`` may hold unused."""
    return int(device_limits(device).budget * HOLD_FRACTION)


def buffer(device, nbytes):
    """A READ_WRITE device buffer of at least ``nbytes`` bytes (>= 1) on ``device`` (a
    clcurv.runtime.device.Device), from its pool (see the module docstring). Its content is
    undefined."""
    nbytes = max(int(nbytes), 1)
    pool = _pool(device)
    if pool is None:
        buf = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, size=nbytes)
    else:
        if pool.managed_bytes - pool.active_bytes > hold_limit(device):
            pool.free_held()
        buf = pool.allocate(nbytes)
    if FILL is not None:
        size = buf.size - buf.size % 4
        if size:
            cl.enqueue_fill_buffer(device.queue, buf, np.float32(FILL), 0, size)
    return buf


def release_memory(device=None):
    """Free the memory that clcurv's pools hold unused: the device memory of ``device`` (as
    :func:`clcurv.runtime.device.get_device` takes it), or when None of every device and the host
    blocks of dropped result arrays (:mod:`clcurv._shared.host_memory`). Buffers and arrays in use
    (a live :class:`~clcurv.grid.cloud.DeviceCloud`, a result) are not touched. Returns the
    bytes freed."""
    with _LOCK:
        pools = list(_POOLS.values()) if device is None else \
            [p for p in [_POOLS.get(id(get_device(device)))] if p is not None]
    freed = host_memory.release() if device is None else 0
    for pool in pools:
        freed += int(pool.managed_bytes - pool.active_bytes)
        pool.free_held()
    return freed
