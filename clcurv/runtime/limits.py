"""What clcurv may use of a device's memory: :func:`device_limits`, queried at every plan
(:meth:`clcurv.grid.cloud.DeviceCloud.plan`) and by the buffer pool
(:func:`clcurv.runtime.memory.hold_limit`). ``DEVICE_MEMORY`` / ``CLCURV_DEVICE_MEMORY``
caps the budget.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

#: Use at most this many bytes of device memory (None: what the device reports). A knob for
#: tests and for leaving room to other users of the device; the environment variable
#: ``CLCURV_DEVICE_MEMORY`` (bytes) sets it when this is None. Read at every plan.
DEVICE_MEMORY = None
#: Fraction of the device's reported global memory that clcurv plans to use (drivers, other
#: contexts and allocation granularity take some); not applied to DEVICE_MEMORY.
HEADROOM = 0.9


@dataclass(frozen=True)
class Limits:
    """What clcurv may use of one device now: ``budget`` bytes in all, ``max_alloc`` per
    buffer, and what they come from (for messages)."""
    budget: int
    max_alloc: int
    source: str


def device_limits(device):
    """The :class:`Limits` of ``device``, queried now (PoCL reports different values within
    one boot, so nothing is cached) and capped by DEVICE_MEMORY / CLCURV_DEVICE_MEMORY."""
    dev = device.cl_device
    total, alloc = int(dev.global_mem_size), int(dev.max_mem_alloc_size)
    source = (f"{device.info.name}: global memory {total / 2**20:.0f} MiB, max single "
              f"allocation {alloc / 2**20:.0f} MiB")
    budget = int(total * HEADROOM)
    cap = DEVICE_MEMORY if DEVICE_MEMORY is not None else os.environ.get("CLCURV_DEVICE_MEMORY")
    if cap not in (None, ""):
        cap = int(cap)
        if cap < budget:
            budget = cap
            source += (f", capped at {cap} bytes (CLCURV_DEVICE_MEMORY, "
                       "clcurv.runtime.limits.DEVICE_MEMORY)")
        alloc = min(alloc, cap)
    return Limits(budget, alloc, source)
