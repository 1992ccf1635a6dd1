"""Load the OpenCL sources in ``kernels/`` and build them once per (context, file, options).

Programs are built with ``-I <kernels dir>`` so that ``#include "common.h"`` works, with
the host's constants (:func:`clcurv._shared.constants.kernel_defines`) and ``-D`` options for
precision, vector width and the operator's own defines. Built programs are memoised per
(context, file, options); a failed build raises :class:`BuildError` carrying the log.

A successful build's log is read: pyopencl's ``CompilerWarning`` ("non-empty compiler
output") is silenced during the build because Intel's CPU runtime always logs its progress
and vectoriser remarks ("Compilation started", "remark: loop not vectorized", "Kernel ...
was successfully vectorized"); the lines that say ``warning`` or ``error`` are re-raised
as a :class:`BuildWarning` naming the file, so a real compiler warning is never hidden
(when the program is compiled from source: a program pyopencl loads from its binary cache,
which it uses on Intel's runtime but not on PoCL, comes with no compiler messages). One
kind of line is dropped (:data:`ABI_NOTE`): clang's note that a 512-bit vector argument
"without 'avx512f' enabled changes the ABI", which PoCL logs on every AVX2 CPU for each
float16/ulong8 value passed to one of its builtins. It concerns calls between objects
compiled for different targets; PoCL compiles the kernel and its builtin library for the
same CPU, so there is nothing to act on. (clang's -Wno-psabi would silence it at the
source, but build options beyond the OpenCL standard's are refused by other runtimes.)
PoCL's clang also writes its count ("20 warnings generated.") straight to the process's
standard error on a compile that is not in PoCL's kernel cache: during a build, file
descriptor 2 goes to a temporary file, whose lines but those counts are written back to
standard error afterwards (:func:`_stderr_counts_dropped`; a line another thread writes
meanwhile is delayed, not lost).
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import pyopencl as cl

from clcurv._shared.constants import kernel_defines
from clcurv._shared.options import choices


class BuildError(RuntimeError):
    """An OpenCL program failed to build; the message contains the build log."""


class BuildWarning(UserWarning):
    """A kernel built, but its compiler warned; the message holds the log's warning lines."""


class PrecisionError(RuntimeError):
    """float64 was requested on a device without cl_khr_fp64."""


def kernels_dir() -> Path:
    """Directory holding the ``.cl``/``.h`` sources: installed package data, else the source tree."""
    here = Path(__file__).resolve().parents[1]          # the package: clcurv/
    for d in (here / "kernels", here.parent / "kernels"):   # installed, then source tree
        if (d / "common.h").is_file():
            return d
    raise FileNotFoundError("clcurv kernels not found (expected clcurv/kernels or ../kernels)")


_cache = {}
_lock = threading.Lock()


def precision_defines(device, precision):
    """``-D`` options for ``precision`` ('float' or 'double') on ``device``, and the
    device-dependent choices of the kernels: VW (:func:`clcurv.ops.registry.tuning`),
    MASKED_SUMS (:func:`masked_sums`), PCA_FMA (:func:`fused_sums`) and FEATURES_BUF
    (:func:`features_buffer`)."""
    if precision not in choices("precision"):
        raise ValueError(f"precision must be {' or '.join(map(repr, choices('precision')))}, "
                         f"got {precision!r}")
    if precision == "double" and not device.info.fp64:
        raise PrecisionError(f"device {device.info.name!r} has no float64 support "
                             "(cl_khr_fp64); use precision='float'")
    vw = 8 if device.info.kind == "cpu" else 4
    return {"REAL_IS_DOUBLE": int(precision == "double"), "VW": vw,
            "MASKED_SUMS": masked_sums(device.info), "PCA_FMA": fused_sums(device.info, precision),
            "FEATURES_BUF": features_buffer(device.info)}


def fused_sums(info, precision):
    """pca.h's PCA_FMA: 1 where the device has a fused multiply-add in ``precision``
    (CL_FP_FMA), and the sums of products are then written fma(a, b, c); 0 elsewhere (a * b
    + c, fused or not as the compiler likes). Spelled out, the fusing no longer depends on
    the compiler's reading of the two forms of MASKED_SUMS: Intel's runtime fused them
    differently in float64 (1 ulp apart in 5% of the smallest eigenvalues)."""
    return int(info.fma_double if precision == "double" else info.fma_float)


def features_buffer(info):
    """features.cl's FEATURES_BUF: the chunks of candidates its multi-radius walk keeps
    before each ball's sums run over them. 32 on CPU devices: each run loads and stores
    the ball's 10 accumulators, half as often as with 16 (three radii's kernel ~4-8 ms
    faster at 1M points on the Zen 3 EPYC; 4-8 KB of the stack); 16 elsewhere, as a GPU's
    private arrays live in slow memory. Any size gives the same sums bit for bit."""
    return 32 if info.kind == "cpu" else 16


def masked_sums(info):
    """1 for CPU devices with 512-bit vectors (native float width 16: AVX-512), whose
    compilers turn pca.h's masked sums into one masked instruction each (the PCA kernels'
    walks 8-10% faster on the Zen 4 EPYC, PoCL and Intel's runtime alike); 0 elsewhere: on
    AVX2 the masked form costs a blend per sum (20% slower), and GPUs select per lane
    anyway. Both forms give the same sums bit for bit (kernels/pca.h)."""
    return int(info.kind == "cpu" and info.native_float_width >= 16)


class Program:
    """A built program whose kernels are created once and reused (``prg.name``)."""

    def __init__(self, program):
        self.program = program
        self._kernels = {k.function_name: k for k in program.all_kernels()}

    def __getattr__(self, name):
        try:
            return self._kernels[name]
        except KeyError:
            raise AttributeError(f"no kernel {name!r} in this program") from None


def build(device, filename, defines=None):
    """Return the built :class:`Program` for ``kernels/<filename>`` with ``defines`` on ``device``.

    Not thread-safe to *launch* kernels of one program from several threads at once
    (kernel arguments are per kernel object); building is.
    """
    defines = dict(kernel_defines(), **(defines or {}))
    key = (device.context.int_ptr, filename, tuple(sorted(defines.items())))
    with _lock:
        prg = _cache.get(key)
        if prg is not None:
            return prg
        kdir = kernels_dir()
        source = (kdir / filename).read_text()
        options = ["-I", str(kdir)] + [f"-D{k}={v}" for k, v in sorted(defines.items())]
        try:
            with warnings.catch_warnings(), _stderr_counts_dropped():
                warnings.simplefilter("ignore", cl.CompilerWarning)   # read below
                built = cl.Program(device.context, source).build(options=options)
        except cl.Error as exc:
            raise BuildError(f"building {filename} with {options} failed:\n{exc}") from exc
        _warn_from_log(device, filename, built)
        prg = Program(built)
        _cache[key] = prg
        return prg


_WARNING_LINE = re.compile(r"\b(warning|error)\b", re.IGNORECASE)
#: clang's -Wpsabi note on a vector wider than the target's registers (see the module notes)
ABI_NOTE = re.compile(r"warning: .*\bAVX vector (argument|return) of type '[^']*' "
                      r"\([^)]*\) without '[\w.]+' enabled changes the ABI\s*$")


#: clang's count of its diagnostics, written to standard error (see the module notes)
COUNT_LINE = re.compile(rb"^\d+ (warning|error)s? generated\.\s*$")


def _flush_stderr():
    """Flush Python's standard error, whatever replaced it (may be None, closed)."""
    try:
        sys.stderr.flush()
    except (AttributeError, ValueError, OSError):
        pass


@contextlib.contextmanager
def _stderr_counts_dropped():
    """File descriptor 2 to a temporary file for the block; then its lines, but for
    :data:`COUNT_LINE`'s, written to the real standard error. Does nothing where fd 2 is not
    open."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        _flush_stderr()
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            _flush_stderr()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            kept = [ln for ln in tmp.read().splitlines(keepends=True)
                    if not COUNT_LINE.match(ln)]
            if kept:
                os.write(2, b"".join(kept))


def log_warnings(log):
    """The lines of a build ``log`` that say ``warning`` or ``error``, but for
    :data:`ABI_NOTE`'s."""
    return [ln for ln in log.splitlines()
            if _WARNING_LINE.search(ln) and not ABI_NOTE.search(ln)]


def _warn_from_log(device, filename, program):
    """Raise a :class:`BuildWarning` with the build log's warning/error lines
    (:func:`log_warnings`), if any."""
    try:
        log = program.get_build_info(device.cl_device, cl.program_build_info.LOG) or ""
    except cl.Error:
        return
    lines = log_warnings(log)
    if lines:
        warnings.warn(f"{filename} on {device.info.name}: " + "\n".join(lines),
                      BuildWarning, stacklevel=3)


def local_size(device, kernel, limit=128):
    """A work-group size for ``kernel`` on ``device``, queried, never assumed: the largest
    multiple of the preferred size multiple that is <= min(limit, kernel max)."""
    dev = device.cl_device
    kmax = kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, dev)
    mult = kernel.get_work_group_info(
        cl.kernel_work_group_info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE, dev)
    top = max(1, min(limit, kmax))
    return max(1, (top // mult) * mult) if mult <= top else top


def batches(n, defines):
    """Work-items for a kernel that handles VW consecutive points per work-item."""
    return -(-n // int(defines["VW"]))


def launch(device, kernel, n, *args, limit=128):
    """Enqueue ``kernel`` over ``n`` work-items (the kernel must ignore ids >= n).

    The global size is padded to a multiple of a fixed local size, so that PoCL compiles
    the work-group function once instead of once per cloud size. ``n == 0`` enqueues nothing.
    """
    if n == 0:
        return None
    ls = local_size(device, kernel, limit)
    gs = -(-n // ls) * ls
    return kernel(device.queue, (gs,), (ls,), *args)
