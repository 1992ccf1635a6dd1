"""OpenCL device choice and capability record.

Order of choice: the ``device=`` argument, else the ``CLCURV_DEVICE`` environment
variable, else the first GPU found, else the first CPU device (PoCL on Debian).

A device specification is an int (index in :func:`devices`), a ``"platform:device"``
pair of indices, or a case-insensitive substring of the device or platform name
(``"pocl"``, ``"nvidia"``, ``"cpu"``, ``"gpu"``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache

APT_HINT = ("no OpenCL platform found; on Debian/Ubuntu install PoCL with: "
            "apt-get install -y pocl-opencl-icd ocl-icd-libopencl1")


class NoDeviceError(RuntimeError):
    """Raised when no OpenCL device is available or the requested one does not exist."""


@dataclass(frozen=True)
class DeviceInfo:
    """What clcurv needs to know about one OpenCL device."""
    index: int
    name: str
    platform: str
    vendor: str
    kind: str                 # "gpu", "cpu" or "other"
    driver: str
    version: str
    fp64: bool
    global_mem: int           # bytes
    max_alloc: int            # bytes, CL_DEVICE_MAX_MEM_ALLOC_SIZE
    local_mem: int            # bytes
    max_work_group: int
    compute_units: int

    def __str__(self):
        return f"[{self.index}] {self.name} ({self.platform}, {self.kind}, fp64={'yes' if self.fp64 else 'no'})"


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency declared in pyproject
        raise NoDeviceError("pyopencl is not installed: pip install pyopencl") from exc
    return cl


@lru_cache(maxsize=None)
def _all_devices():
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    found = []
    for p in platforms:
        try:
            found.extend((p, d) for d in p.get_devices())
        except cl.Error:
            continue
    return tuple(found)


def _kind(dev):
    cl = _cl()
    if dev.type & cl.device_type.GPU:
        return "gpu"
    if dev.type & cl.device_type.CPU:
        return "cpu"
    return "other"


def _info(index, platform, dev) -> DeviceInfo:
    return DeviceInfo(
        index=index, name=dev.name.strip(), platform=platform.name.strip(),
        vendor=dev.vendor.strip(), kind=_kind(dev), driver=dev.driver_version,
        version=dev.version, fp64=bool(dev.double_fp_config),
        global_mem=dev.global_mem_size, max_alloc=dev.max_mem_alloc_size,
        local_mem=dev.local_mem_size, max_work_group=dev.max_work_group_size,
        compute_units=dev.max_compute_units)


def devices():
    """List the OpenCL devices clcurv can use, as :class:`DeviceInfo` records."""
    return [_info(i, p, d) for i, (p, d) in enumerate(_all_devices())]


def _match(spec, found):
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        i = int(spec)
        if 0 <= i < len(found):
            return i
        raise NoDeviceError(f"device index {i} out of range: {len(found)} device(s) found: "
                            f"{_listing(found)}")
    if isinstance(spec, str) and ":" in spec:
        return _match_pair(spec, found)
    if isinstance(spec, str):
        s = spec.lower()
        for i, (p, d) in enumerate(found):
            if s in d.name.lower() or s in p.name.lower() or s == _kind(d):
                return i
        names = ", ".join(d.name.strip() for _, d in found)
        raise NoDeviceError(f"no OpenCL device matches {spec!r}; available: {names}")
    raise TypeError(f"device must be an int or a str, got {type(spec).__name__}")


def _listing(found):
    """'index: device | platform' of every device, for error messages."""
    return "; ".join(f"{i}: {d.name.strip()} | {p.name.strip()}"
                     for i, (p, d) in enumerate(found))


def _match_pair(spec, found):
    """The index of ``'platform:device'`` (two integers, as ``clcurv devices`` numbers the
    platforms and their devices), or NoDeviceError listing what exists."""
    try:
        pi, di = (int(s) for s in spec.split(":", 1))
    except ValueError:
        raise NoDeviceError(f"device {spec!r}: 'platform:device' takes two integers; "
                            f"devices: {_listing(found)}") from None
    plats = []
    for p, _ in found:
        if p not in plats:
            plats.append(p)
    if 0 <= pi < len(plats):
        devs = [d for p, d in found if p == plats[pi]]
        if 0 <= di < len(devs):
            return found.index((plats[pi], devs[di]))
    raise NoDeviceError(f"no device {spec!r} ({len(plats)} platform(s)); devices: "
                        f"{_listing(found)}")


def _default(found):
    for i, (_, d) in enumerate(found):
        if _kind(d) == "gpu":
            return i
    return 0


class Device:
    """An OpenCL context and in-order queue on one device, created once per device."""

    def __init__(self, index):
        cl = _cl()
        platform, dev = _all_devices()[index]
        self.info = _info(index, platform, dev)
        self.cl_device = dev
        self.context = cl.Context([dev])
        self.queue = cl.CommandQueue(self.context)

    def __repr__(self):
        return f"Device({self.info})"


@lru_cache(maxsize=None)
def _device_at(index) -> Device:
    return Device(index)


def get_device(device=None) -> Device:
    """Return the :class:`Device` for ``device`` (see module docstring), cached."""
    if isinstance(device, Device):
        return device
    found = _all_devices()
    if not found:
        raise NoDeviceError(APT_HINT)
    if device is None:
        device = os.environ.get("CLCURV_DEVICE") or None
    index = _default(found) if device is None else _match(device, found)
    return _device_at(index)
