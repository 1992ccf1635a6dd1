"""OpenCL device choice, capability record, and the ICD files the loader read.

Order of choice: the ``device=`` argument, else the ``CLCURV_DEVICE`` environment
variable, else the first GPU found, else the first CPU device (PoCL on Debian), else the
first other device. Simulators and emulators (Oclgrind, Intel's FPGA emulator: see
:data:`SIMULATOR_WORDS`) are never chosen by default nor by a kind (``"gpu"``, ``"cpu"``):
they are about 1000x slower and are used only when named (``device="oclgrind"``).

A device specification is an int (index in :func:`devices`), a ``"platform:device"``
pair of indices, a kind (``"gpu"``, ``"cpu"``, ``"accelerator"``), or a case-insensitive
substring of the platform name or vendor (``"pocl"`` matches PoCL, whose platform is
"Portable Computing Language" by "The pocl project"; ``"intel"``, ``"nvidia"``,
``"oclgrind"``), else of the device name. A platform match wins over a device-name
match, a real device over a simulator, then the lower index.

Which OpenCL implementations exist is decided by the ICD loader: it reads the ``.icd``
files of the folder ``OCL_ICD_VENDORS`` names (else ``/etc/OpenCL/vendors``), and the
pyopencl wheel's loader also those in ``pyopencl/.libs``. Each file names one library.
:func:`devices` reports those files (``devices().icds``) and which library each device
came from, so that an ICD whose library is missing (the Intel wheel's own ``.icd`` names a
placeholder path) shows up. ``make intel-opencl`` and ``make oclgrind`` write ``.icd``
files into ``.venv/etc/OpenCL/vendors``; ``make test`` and ``make bench`` point
``OCL_ICD_VENDORS`` there.
"""
from __future__ import annotations

import ctypes
import os
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import pyopencl as cl

APT_HINT = ("no OpenCL platform found; on Debian/Ubuntu install PoCL with: "
            "apt-get install -y pocl-opencl-icd ocl-icd-libopencl1")

#: lower-case words that mark a simulator or emulator in a platform or device name
SIMULATOR_WORDS = ("oclgrind", "emulat", "simulat")

KINDS = ("gpu", "cpu", "accelerator")


class NoDeviceError(RuntimeError):
    """Raised when no OpenCL device is available or the requested one does not exist."""


@dataclass(frozen=True)
class DeviceInfo:
    """What clcurv needs to know about one OpenCL device."""
    index: int
    name: str
    platform: str
    vendor: str
    kind: str                 # "gpu", "cpu", "accelerator" or "other"
    driver: str
    version: str
    fp64: bool
    global_mem: int           # bytes
    max_alloc: int            # bytes, CL_DEVICE_MAX_MEM_ALLOC_SIZE
    local_mem: int            # bytes
    max_work_group: int
    compute_units: int
    simulator: bool = False   # a simulator or emulator: never the default
    library: str | None = None  # the ICD library it came from (None where unknown)
    native_float_width: int = 1  # CL_DEVICE_NATIVE_VECTOR_WIDTH_FLOAT (16: 512-bit vectors)
    fma_float: bool = False   # CL_FP_FMA in CL_DEVICE_SINGLE_FP_CONFIG: a fused multiply-add
    fma_double: bool = False  # CL_FP_FMA in CL_DEVICE_DOUBLE_FP_CONFIG

    def __str__(self):
        sim = ", simulator" if self.simulator else ""
        return (f"[{self.index}] {self.name} ({self.platform}, {self.kind}{sim}, "
                f"fp64={'yes' if self.fp64 else 'no'})")


@dataclass(frozen=True)
class Icd:
    """One ``.icd`` file the loader read: the library it names, and how many devices came
    from that library (0: the library is missing, failed to load, or has no device)."""
    path: str
    library: str
    devices: int

    def __str__(self):
        if self.devices:
            return f"{self.path} -> {self.library}: {self.devices} device(s)"
        missing = os.path.isabs(self.library) and not os.path.exists(self.library)
        why = "library not found" if missing else "loaded no device"
        return f"{self.path} -> {self.library}: {why}"


class DeviceList(list):
    """The :class:`DeviceInfo` records of :func:`devices`, with what the loader read.

    ``icds``: the :class:`Icd` files found; ``vendors``: the folders they were read from;
    ``default``: the index of the default device (None when there is none) and
    ``reason``: why it is the default, or why there is none; ``idle_venv_icds``: the
    ``.icd`` files of :func:`venv_vendors` when the loader did not read that folder.
    """

    def __init__(self, infos, icds, vendors, default, reason):
        super().__init__(infos)
        self.icds, self.vendors, self.default, self.reason = icds, vendors, default, reason
        venv = venv_vendors()
        read = {os.path.realpath(v) for v in vendors}
        self.idle_venv_icds = ([str(f) for f in sorted(venv.glob("*.icd"))]
                               if venv.is_dir() and os.path.realpath(venv) not in read else [])


@lru_cache(maxsize=None)
def _all_devices():
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
    if dev.type & cl.device_type.GPU:
        return "gpu"
    if dev.type & cl.device_type.CPU:
        return "cpu"
    if dev.type & cl.device_type.ACCELERATOR:
        return "accelerator"
    return "other"


def _is_simulator(platform, dev):
    """A simulator or emulator: named so, or claiming to be a CPU and a GPU at once
    (Oclgrind sets every device-type bit)."""
    names = f"{platform.name} {platform.vendor} {dev.name}".lower()
    both = dev.type & cl.device_type.CPU and dev.type & cl.device_type.GPU
    return bool(both) or any(w in names for w in SIMULATOR_WORDS)


def _info(index, platform, dev) -> DeviceInfo:
    return DeviceInfo(
        index=index, name=dev.name.strip(), platform=platform.name.strip(),
        vendor=dev.vendor.strip(), kind=_kind(dev), driver=dev.driver_version,
        version=dev.version, fp64=bool(dev.double_fp_config),
        global_mem=dev.global_mem_size, max_alloc=dev.max_mem_alloc_size,
        local_mem=dev.local_mem_size, max_work_group=dev.max_work_group_size,
        compute_units=dev.max_compute_units, simulator=_is_simulator(platform, dev),
        library=_platform_library(platform),
        native_float_width=int(dev.native_vector_width_float),
        fma_float=bool(dev.single_fp_config & cl.device_fp_config.FMA),
        fma_double=bool(dev.double_fp_config & cl.device_fp_config.FMA))


# ------------------------------------------------------------------------ ICD files
def vendor_dirs():
    """The folders whose ``.icd`` files the loader reads: ``OCL_ICD_VENDORS`` (a folder)
    or ``/etc/OpenCL/vendors``, and the pyopencl wheel's own ``pyopencl/.libs``."""
    env = os.environ.get("OCL_ICD_VENDORS")
    dirs = [Path(env) if env else Path("/etc/OpenCL/vendors")]
    bundled = Path(cl.__file__).parent / ".libs"
    if bundled.is_dir():
        dirs.append(bundled)
    return dirs


def venv_vendors():
    """``<sys.prefix>/etc/OpenCL/vendors``, where ``make intel-opencl`` and ``make
    oclgrind`` write their ``.icd`` files (it may not exist)."""
    return Path(sys.prefix) / "etc" / "OpenCL" / "vendors"


def _icd_files():
    """(path, library) of every ``.icd`` file in :func:`vendor_dirs`."""
    out = []
    for d in vendor_dirs():
        if d.is_file():   # OCL_ICD_VENDORS may name one library or .icd directly
            out.append((str(d), d.read_text().strip() if d.suffix == ".icd" else str(d)))
            continue
        for f in sorted(d.glob("*.icd")) if d.is_dir() else []:
            try:
                out.append((str(f), f.read_text().strip()))
            except OSError:
                out.append((str(f), "(unreadable)"))
    return out


def _mappings():
    """(start, end, readable, path or '') of this process's memory mappings (Linux only;
    empty elsewhere)."""
    maps = []
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                parts = line.split()
                lo, hi = (int(x, 16) for x in parts[0].split("-"))
                maps.append((lo, hi, parts[1].startswith("r"),
                             parts[5] if len(parts) >= 6 else ""))
    except (OSError, ValueError, IndexError):
        return []
    return maps


def _platform_library(platform):
    """The library a platform came from: an ICD platform object starts with a pointer to
    its dispatch table, which lies in the ICD's library. Read only where /proc/self/maps
    shows the object in readable memory; None where that cannot be told."""
    maps = _mappings()
    ptr = platform.int_ptr
    if not any(lo <= ptr and ptr + 8 <= hi and readable for lo, hi, readable, _ in maps):
        return None
    table = ctypes.c_void_p.from_address(ptr).value
    for lo, hi, _, path in maps:
        if table is not None and lo <= table < hi and path.startswith("/"):
            return path
    return None


def _same_library(named, loaded):
    if loaded is None:
        return False
    if os.path.isabs(named):
        return os.path.realpath(named) == os.path.realpath(loaded)
    return os.path.basename(named) in (os.path.basename(loaded),
                                       os.path.basename(os.path.realpath(loaded)))


def _icds(infos):
    return [Icd(path, lib, sum(_same_library(lib, i.library) for i in infos))
            for path, lib in _icd_files()]


# ------------------------------------------------------------------------ choice
def _default(infos):
    """(index, reason) of the default device, or (None, why there is none)."""
    for kind, why in (("gpu", "the first GPU"), ("cpu", "the first CPU device (no GPU)"),
                      (None, "the first device (no GPU nor CPU device)")):
        for i in infos:
            if not i.simulator and (kind is None or i.kind == kind):
                return i.index, why
    sims = ", ".join(f"{i.name} | {i.platform}" for i in infos)
    return None, (f"only simulators or emulators found ({sims}): they are used only when "
                  "named (device=..., CLCURV_DEVICE); " + APT_HINT)


@lru_cache(maxsize=None)
def _infos():
    return tuple(_info(i, p, d) for i, (p, d) in enumerate(_all_devices()))


def devices():
    """List the OpenCL devices as :class:`DeviceInfo` records, in a :class:`DeviceList`
    that also says which ICD files were found and which device is the default, and why."""
    found = _all_devices()
    infos = list(_infos())
    env = os.environ.get("CLCURV_DEVICE") or None
    if env is not None and found:
        try:
            default, reason = _match(env, infos), f"CLCURV_DEVICE={env!r}"
        except NoDeviceError as exc:
            default, reason = None, str(exc)
    else:
        default, reason = _default(infos) if found else (None, APT_HINT)
    return DeviceList(infos, _icds(infos), [str(d) for d in vendor_dirs()], default, reason)


def _match(spec, infos):
    if isinstance(spec, int) or (isinstance(spec, str) and spec.strip().isdigit()):
        i = int(spec)
        if 0 <= i < len(infos):
            return i
        raise NoDeviceError(f"device index {i} out of range: {len(infos)} device(s) found: "
                            f"{_listing(infos)}")
    if isinstance(spec, str) and ":" in spec:
        return _match_pair(spec, infos)
    if isinstance(spec, str):
        return _match_name(spec, infos)
    raise TypeError(f"device must be an int or a str, got {type(spec).__name__}")


def _match_name(spec, infos):
    """A kind (real devices only), else the best substring match of the platform name or
    vendor, then of the device name (real devices before simulators, then by index)."""
    s = spec.strip().lower()
    if s in KINDS:
        for i in infos:
            if i.kind == s and not i.simulator:
                return i.index
        raise NoDeviceError(f"no OpenCL {s} device (simulators are used only when named); "
                            f"devices: {_listing(infos)}")
    found = _all_devices()
    ranked = []
    for i in infos:
        p, d = found[i.index]
        if s in f"{p.name} {p.vendor}".lower():
            ranked.append((0, i.simulator, i.index))
        elif s in d.name.lower():
            ranked.append((1, i.simulator, i.index))
    if ranked:
        return min(ranked)[2]
    raise NoDeviceError(f"no OpenCL device matches {spec!r} (by platform or device name); "
                        f"devices: {_listing(infos)}")


def _listing(infos):
    """'index: device | platform' of every device, for error messages."""
    return "; ".join(f"{i.index}: {i.name} | {i.platform}" for i in infos) or "none"


def _match_pair(spec, infos):
    """The index of ``'platform:device'`` (two integers, as ``clcurv devices`` numbers the
    platforms and their devices), or NoDeviceError listing what exists."""
    try:
        pi, di = (int(s) for s in spec.split(":", 1))
    except ValueError:
        raise NoDeviceError(f"device {spec!r}: 'platform:device' takes two integers; "
                            f"devices: {_listing(infos)}") from None
    found = _all_devices()
    plats = []
    for p, _ in found:
        if p not in plats:
            plats.append(p)
    if 0 <= pi < len(plats):
        devs = [d for p, d in found if p == plats[pi]]
        if 0 <= di < len(devs):
            return found.index((plats[pi], devs[di]))
    raise NoDeviceError(f"no device {spec!r} ({len(plats)} platform(s)); devices: "
                        f"{_listing(infos)}")


class Device:
    """An OpenCL context and in-order queue on one device, created once per device."""

    def __init__(self, index):
        _, dev = _all_devices()[index]
        self.info = _infos()[index]
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
    infos = _infos()
    if device is None:
        device = os.environ.get("CLCURV_DEVICE") or None
    if device is None:
        index, reason = _default(infos)
        if index is None:
            raise NoDeviceError(reason)
    else:
        index = _match(device, infos)
    return _device_at(index)
