"""The timing harness of the bench: timers, the test clouds, subprocess runs and a record of
the machine and library versions."""
from __future__ import annotations

import datetime
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import clcurv
from clcurv import shapes
from clcurv.grid.binning import bin_points

REPO = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------- timers
def timeit(fn, repeats, warmup=1, setup=None):
    """Minimum wall time (s) of ``fn(*setup())`` over ``repeats`` runs after ``warmup`` runs.

    ``setup`` (untimed) builds fresh arguments for every run.
    """
    best = math.inf
    for i in range(warmup + repeats):
        args = setup() if setup else ()
        t0 = time.perf_counter()
        fn(*args)
        dt = time.perf_counter() - t0
        if i >= warmup:
            best = min(best, dt)
    return best


def paired_rounds(fn_a, fn_b, repeats):
    """Wall times (s) of ``fn_a`` and ``fn_b``, two lists of ``repeats`` interleaved runs
    (a, b, a, b, ...): round i's a and b ran in the same seconds of the shared machine."""
    times = ([], [])
    for _ in range(repeats):
        for fn, which in ((fn_a, 0), (fn_b, 1)):
            t0 = time.perf_counter()
            fn()
            times[which].append(time.perf_counter() - t0)
    return times


def paired(fn_a, fn_b, repeats):
    """Minimum wall times (s) of ``fn_a`` and ``fn_b`` over ``repeats`` interleaved runs
    (a, b, a, b, ...): their ratio then compares runs made in the same seconds, which on a
    shared machine whose speed drifts between minutes is far steadier than two separate
    minima."""
    a, b = paired_rounds(fn_a, fn_b, repeats)
    return min(a), min(b)


def timed(fn):
    """(seconds, result) of one call."""
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def mpts(n, seconds):
    """Millions of points per second (None when not measured)."""
    return None if seconds is None else n / seconds / 1e6


def log(msg):
    print(msg, file=sys.stderr, flush=True)


def run_python(code, *args, env=None):
    """Run ``code`` in a fresh interpreter (repo root as cwd); return its stdout, or raise."""
    full_env = dict(os.environ, **(env or {}))
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=REPO, env=full_env,
                         capture_output=True, text=True, timeout=300)
    if out.returncode:
        raise RuntimeError(out.stderr.strip().splitlines()[-1] if out.stderr else "failed")
    return out.stdout


# ----------------------------------------------------------------------------- files
def copc_config(copc, fmt, scale, offset, lo, hi, divisions):
    """copclib's writer configuration (``copc``: the copclib module, an optional extra) of
    a COPC file of point format ``fmt`` with ``scale`` and ``offset`` (3 each), the header's
    bounds ``lo``, ``hi``, and an octree whose root cube holds them, of spacing its side
    over ``divisions``."""
    span = float((np.asarray(hi) - np.asarray(lo)).max())
    cfg = copc.CopcConfigWriter(fmt, scale=tuple(scale), offset=tuple(offset))
    cfg.las_header.min = copc.Vector3(*lo)
    cfg.las_header.max = copc.Vector3(*hi)
    info = cfg.copc_info
    info.center_x, info.center_y, info.center_z = np.asarray(lo) + span / 2
    info.halfsize = span / 2
    info.spacing = span / divisions
    return cfg


# ----------------------------------------------------------------------------- clouds
def radius_for(k, n):
    """Radius giving ~k neighbours besides the point itself on a unit sphere of n points."""
    return math.sqrt(4.0 * k / n)


def make_clouds(n):
    """Random-order unit-sphere sample and the same points in k-d tree leaf order."""
    pts = shapes.sphere(n, 1.0)["points"]
    sorted_pts = np.ascontiguousarray(pts[cKDTree(pts, balanced_tree=False).indices])
    return pts, sorted_pts


def exact_normals(pts):
    """The exact outward normals of the unit-sphere sample."""
    return pts / np.linalg.norm(pts, axis=1)[:, None]


def cap_indices(pts, m):
    """Indices of the ~m points of the polar cap z > 1 - 2 m / n: a spatial subsample in which
    interior points keep exactly the neighbour sets they have in the whole cloud."""
    return np.flatnonzero(pts[:, 2] > 1.0 - 2.0 * m / len(pts))


def cap_interior(pts, cap, reach):
    """Mask over ``cap`` of the points whose whole ball of radius ``reach`` lies in the cap."""
    z = pts[cap, 2]
    return z - reach > z.min()


def device_coordinates(pts, r):
    """The positions the device's float32 (cell-relative) coordinates represent, input order."""
    g = bin_points(pts, r, np.float32)
    out = np.empty((len(pts), 3))
    out[g.order] = g.positions()
    return out


# ----------------------------------------------------------------------------- environment
def cpu_model():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def cpu_flags():
    """The vector extensions that matter for PoCL's code generation."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    flags = next((ln.split(":", 1)[1].split() for ln in text.splitlines()
                  if ln.startswith("flags")), [])
    return [f for f in ("avx2", "fma", "avx512f") if f in flags]


def loadavg():
    return Path("/proc/loadavg").read_text().split()[:3]


def hugepage_settings():
    """Transparent huge pages: the kernel's enabled/defrag modes and whether numpy advises
    them for its large arrays. With defrag 'madvise', numpy's advice can make a fresh output
    array stall on compaction (numpy issue #31590): single calls then vary by 100s of ms."""
    out = {}
    for k in ("enabled", "defrag"):
        try:
            text = open(f"/sys/kernel/mm/transparent_hugepage/{k}").read()
            out[k] = text.split("[")[1].split("]")[0]
        except (OSError, IndexError):
            out[k] = None
    get = getattr(getattr(np, "_core", np.core).multiarray, "_get_madvise_hugepage", None)
    out["numpy_madvise"] = None if get is None else bool(get())
    return out


def environment():
    """Machine and library versions."""
    import pyopencl as cl
    env = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
           "cpu": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count(),
           "python": platform.python_version(), "numpy": np.__version__,
           "pyopencl": cl.VERSION_TEXT, "clcurv": clcurv.__version__, "open3d": None,
           "loadavg": loadavg(), "hugepages": hugepage_settings()}
    # the OpenCL platforms before Open3D: importing it first hides Intel's CPU runtime
    env["platforms"] = {p.name.strip(): p.version.strip() for p in cl.get_platforms()}
    try:
        import open3d
        env["open3d"] = open3d.__version__
    except Exception:  # noqa: BLE001 - open3d is optional (and may fail to load its libs)
        pass
    return env
