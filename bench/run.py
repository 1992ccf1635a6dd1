"""clcurv benchmark: every OpenCL device against Open3D, jakteristics and the float64 NumPy reference.

Run from the repository root::

    python -m bench.run                 # 100k and 1M points, ~30 and ~100 neighbours, 3 repeats
    python -m bench.run --quick         # 100k points, ~30 neighbours: smoke run (< 1 min)
    python -m bench.run --sizes 1M --neighbours 30
    python -m bench.run --no-open3d --no-jakteristics

The cloud is a uniform sample of the unit sphere (``clcurv.shapes.sphere``) in random order,
plus a spatially sorted copy (k-d tree leaf order); its exact normals are the points. Radii
give ~k neighbours: r = sqrt(4 k / n) (area 4 pi, k = n pi r^2 / (4 pi)). Every timing is the
minimum of ``--repeats`` runs after an untimed warm-up (so program builds are cached), except
where the table says otherwise.

Measured, per device, size and neighbour count: the moment operators (variation, mls0, mls1,
normals; ``orient=None``), the normal-based operators 2dcov1, 2dcov2, 3dcov and MLS2 with the
exact normals given (``normals=``: the operator alone, no PCA pass) and MLS2 with
``orient=None`` (its own PCA frame, solver's sign), each end to end and kernel only
(``cloud.timings``); the MLS1 scale space (1 iteration end to end; 5 iterations with
``scale_space.last_stats``) and the pipeline ``curvature(method="mls2", scale_space=5,
normals=...)``. Peers: the NumPy reference of every operator (timed once on a polar cap of the
same cloud, extrapolated linearly), Open3D ``estimate_normals``/``estimate_covariances`` and
jakteristics ``compute_features``. Results are checked against the reference on the cap.

Each block (reference, clcurv per device and column, Open3D, jakteristics, orientation) runs
between two checks that both cores are free (a PoCL kernel timed with 1 and 2 threads); busy
blocks are measured again, and flagged if still busy. Prints a table, writes
``bench/results/bench-<devicekind>.json`` and ``bench/results/bench.md``.
"""
from __future__ import annotations

import argparse
import datetime
import json
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
from clcurv import orient, reference, shapes
from clcurv.cloud import DeviceCloud
from clcurv.covariances import device_covariances
from clcurv.grid import bin_points
from clcurv.mls import device_mls2
from clcurv.moments import device_moments

RESULTS = Path(__file__).resolve().parent / "results"
REPO = Path(__file__).resolve().parent.parent
METHODS = ("variation", "mls0", "mls1")
COV = ("2dcov1", "2dcov2", "3dcov")
OPS = COV + ("mls2",)        # the normal-based operators and MLS2, timed with normals= given
SS_ITERATIONS = 5         # scale-space iterations timed (and the pipeline's)
JAK_FEATURES = ["nx", "ny", "nz", "surface_variation", "eigenvalue_sum", "number_of_neighbors"]
STAGES = ("binning", "upload", "build", "cell_ranges", "build_moments", "kernel_moments", "download")

COS_TOL = 1e-4            # normals: 1 - |cos| against the float64 reference (tests/test_moments.py)
VAR_MEDIAN_TOL = 1e-3     # surface variation: median relative error against the reference
THREADS_MIN_GAIN = 1.6    # two PoCL threads must be this much faster than one (quiet: ~2.0)
AGREE_MIN = 0.998         # fraction of cap-interior points whose counts equal the reference's
# float32 kernels vs float64 reference (tests/test_operators.py, tests/test_scale_space.py
# assert these on the max over 15k-60k-point clouds; here, on ~100k cap points, the tolerance
# applies to the 99.9th percentile, the max is listed: equal counts do not guarantee equal
# neighbour sets when a neighbour sits at distance ~r)
COV_K1_TOL = 1e-3         # covariance operators: |k1 - k1_ref| / k1_ref
MLS2_K_TOL = 1e-3         # MLS2: |k - k_ref| / max(|k1_ref|, |k2_ref|), k1 and k2
SS_TOL = 1e-5             # scale space: |position - reference| / r after 2 iterations
SS_HOPS = 2.5             # cap interior for 2 iterations: balls of radius 2.5 r inside the cap

E2E_VS_OPEN3D = 5.0       # targets
KERNEL_MPTS_AT_30 = 5.0
VS_REFERENCE = 50.0
ORIENT_VS_OPEN3D = 10.0
MLS2_VS_REFERENCE = 50.0  # MLS2 (normals=) e2e vs the NumPy reference's MLS2
MLS2_VS_NORMALS = 2.0     # MLS2 (normals=) e2e time / clcurv.normals(orient=None) time, at most
COV_VS_NORMALS = 1.5      # each covariance operator (normals=) time / clcurv.normals time, at most
PIPELINE_MAX_S = 5.0      # scale_space=5 + MLS2 end to end at 1M / ~30, seconds
PAIRED_REPEATS = 5        # interleaved (operator, clcurv.normals) pairs for the time ratios
SS_VS_OPEN3D = 5.0        # scale-space iteration points/s / Open3D estimate_normals points/s


# ----------------------------------------------------------------------------- helpers
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


def paired(fn_a, fn_b, repeats):
    """Minimum wall times (s) of ``fn_a`` and ``fn_b`` over ``repeats`` interleaved runs
    (a, b, a, b, ...): their ratio then compares runs made in the same seconds, which on a
    shared machine whose speed drifts between minutes is far steadier than two separate
    minima."""
    best_a = best_b = math.inf
    for _ in range(repeats):
        for fn, which in ((fn_a, 0), (fn_b, 1)):
            t0 = time.perf_counter()
            fn()
            dt = time.perf_counter() - t0
            if which:
                best_b = min(best_b, dt)
            else:
                best_a = min(best_a, dt)
    return best_a, best_b


def radius_for(k, n):
    """Radius giving ~k neighbours besides the point itself on a unit sphere of n points."""
    return math.sqrt(4.0 * k / n)


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


def environment():
    """Machine and library versions."""
    import pyopencl as cl
    env = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
           "cpu": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count(), "python": platform.python_version(),
           "numpy": np.__version__, "pyopencl": cl.VERSION_TEXT, "clcurv": clcurv.__version__,
           "open3d": None, "loadavg": Path("/proc/loadavg").read_text().split()[:3]}
    try:
        import open3d
        env["open3d"] = open3d.__version__
    except Exception:  # noqa: BLE001 - open3d is optional (and may fail to load its libs)
        pass
    env["platforms"] = {p.name.strip(): p.version.strip() for p in cl.get_platforms()}
    return env


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
    return {"one_thread_s": t1, "two_threads_s": t2, "gain": gain,
            "loadavg": Path("/proc/loadavg").read_text().split()[:3],
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
        """'x2.01 / x1.98': the 2-thread gain before / after the block."""
        g = [self.checks.get(f"{label}, {w}", {}).get("gain") for w in ("before", "after")]
        return " / ".join(fmt(x, ".2f", "x") for x in g)

    def busy(self):
        return sorted({k.rsplit(",", 1)[0] for k, c in self.checks.items() if c.get("ok") is False})


# ----------------------------------------------------------------------------- clouds
def make_clouds(n):
    """Random-order unit-sphere sample and the same points in k-d tree leaf order."""
    pts = shapes.sphere(n, 1.0)["points"]
    sorted_pts = np.ascontiguousarray(pts[cKDTree(pts, balanced_tree=False).indices])
    return pts, sorted_pts


def cap_indices(pts, m):
    """Indices of the ~m points of the polar cap z > 1 - 2 m / n: a spatial subsample in which
    interior points keep exactly the neighbour sets they have in the whole cloud."""
    return np.flatnonzero(pts[:, 2] > 1.0 - 2.0 * m / len(pts))


def cap_interior(pts, cap, r):
    """Mask over ``cap`` of the points whose whole ball of radius r lies inside the cap."""
    z = pts[cap, 2]
    return z - r > z.min()


# ----------------------------------------------------------------------------- peers
def device_coordinates(pts, r):
    """The positions the device's float32 (cell-relative) coordinates represent, input order."""
    g = bin_points(pts, r, np.float32)
    out = np.empty((len(pts), 3))
    out[g.order] = g.positions()
    return out


def exact_normals(pts):
    """The exact outward normals of the unit-sphere sample."""
    return pts / np.linalg.norm(pts, axis=1)[:, None]


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def bench_reference(pts, r, cap, normals=None):
    """The float64 NumPy reference of every operator on the cap (each timed once; it is slow
    and deterministic): moments (variation, mls0, mls1 and normals are one pass), the three
    covariance operators and MLS2 with the exact normals, and the MLS1 scale space
    (2 iterations, timed: seconds per iteration = half).

    Every operator also runs (untimed) on the float32-rounded coordinates the
    device works with: the difference to that run is the kernels' own arithmetic error, the
    difference to the float64 run includes the rounding of the input to float32."""
    sub = pts[cap]
    seconds, ref = timed(lambda: reference.moments(sub, r))
    sub32 = device_coordinates(pts, r)[cap]
    ref32 = reference.moments(sub32, r)
    out = {"points": len(sub), "seconds": seconds, "mpts": mpts(len(sub), seconds),
           "mean_count": float(ref["count"].mean()), "result": ref, "result_f32_input": ref32,
           "op_seconds": {"moments": seconds}, "ops": {}}
    if normals is None:
        return out
    nsub = normals[cap]
    for m in COV:
        out["op_seconds"][m], out["ops"][m] = timed(
            lambda m=m: reference.covariance_ops(sub, r, nsub, m))
    out["op_seconds"]["mls2"], out["ops"]["mls2"] = timed(lambda: reference.mls2(sub, r, nsub))
    out["ops_f32_input"] = {m: reference.covariance_ops(sub32, r, nsub, m) for m in COV}
    out["ops_f32_input"]["mls2"] = reference.mls2(sub32, r, nsub)
    s, its = timed(lambda: reference.scale_space(sub, r, 2))
    out["op_seconds"]["scale_space_iteration"] = s / 2
    out["ops"]["scale_space_disp2"] = its[2] - sub
    out["ops"]["scale_space_disp2_f32_input"] = reference.scale_space(sub32, r, 2)[2] - sub32
    out["op_mpts"] = {k: mpts(len(sub), v) for k, v in out["op_seconds"].items()}
    return out


def ref_extrapolated(ref, op, n):
    """Seconds the reference would take for ``op`` on n points (linear in the points)."""
    return ref["op_seconds"][op] / ref["points"] * n


def jakteristics_or_reason():
    """(module, None), or (None, why it is not available)."""
    try:
        import jakteristics
        return jakteristics, None
    except Exception as exc:  # noqa: BLE001 - optional peer
        return None, f"{type(exc).__name__}: {exc}"


def bench_jakteristics(jak, clouds, r, repeats):
    """jakteristics.compute_features (k-d tree build included, all cores) on both orders:
    sorted min(repeats, 2) runs, random one run. Features: JAK_FEATURES."""
    out = {"features": JAK_FEATURES, "threads_used": "num_threads=-1 (all)"}
    for order, p in clouds.items():
        reps = min(repeats, 2) if order == "sorted" else 1
        call = lambda p=p: jak.compute_features(p, search_radius=r, feature_names=JAK_FEATURES)
        best = math.inf
        for _ in range(reps):
            s, f = timed(call)
            best = min(best, s)
        out[order] = {"seconds": best, "runs": reps}
        if order == "random":
            out["mean_count"] = float(np.mean(f[:, JAK_FEATURES.index("number_of_neighbors")]))
    return out


def open3d_or_none():
    try:
        import open3d as o3d
        return o3d
    except Exception:  # noqa: BLE001
        return None


def bench_open3d(o3d, clouds, r, repeats):
    """Open3D estimate_normals / estimate_covariances with a radius search, on both orders.

    A fresh PointCloud per run (estimate_normals aligns to normals already present), built
    outside the timed region. Random order: one run (it is ~4x slower)."""
    def fresh(p):
        return lambda: (o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)),)

    param = o3d.geometry.KDTreeSearchParamRadius(r)
    out = {}
    for order, p in clouds.items():
        reps = repeats if order == "sorted" else 1
        out[order] = {
            "normals_s": timeit(lambda c: c.estimate_normals(param), reps, 0, fresh(p)),
            "covariances_s": timeit(lambda c: c.estimate_covariances(param), reps, 0, fresh(p)),
            "runs": reps}
    return out


def bench_orientation(o3d, m, device):
    """Hoppe orientation (k = 10) on m sphere points: clcurv (min of 2) vs Open3D (run once)."""
    pts = shapes.sphere(m, 1.0, seed=1)["points"]
    nrm = clcurv.normals(pts, radius_for(30, m), orient=None, device=device)

    def outward(n):  # fraction of normals pointing outward, and consistency (either way)
        frac = float(np.mean(np.einsum("ij,ij->i", n, pts) > 0))
        return frac, max(frac, 1 - frac)

    flip = orient.flip_by_propagation(pts, nrm, k=10)
    seconds = timeit(lambda: orient.flip_by_propagation(pts, nrm, k=10), 2, warmup=0)
    n_cl = nrm.copy()
    n_cl[flip] *= -1
    out = {"points": m, "clcurv_s": seconds, "clcurv_outward": outward(n_cl)[0]}
    if o3d is not None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.normals = o3d.utility.Vector3dVector(nrm)
        t0 = time.perf_counter()
        pcd.orient_normals_consistent_tangent_plane(10)
        out["open3d_s"] = time.perf_counter() - t0
        out["open3d_outward"], out["open3d_consistent"] = outward(np.asarray(pcd.normals))
    return out


# ----------------------------------------------------------------------------- clcurv
_COLD_BUILD = r"""
import sys, time, clcurv
from clcurv.program import build, precision_defines
dev = clcurv.get_device(int(sys.argv[1]))
d = precision_defines(dev, "float")
t0 = time.perf_counter(); build(dev, "grid.cl", d); t1 = time.perf_counter()
build(dev, "moments.cl", dict(d, DENSITY=0, REFINE_L0=1)); t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def cold_build(index):
    """Build times of grid.cl and moments.cl in a fresh process with PoCL's cache disabled."""
    try:
        grid, mom = map(float, run_python(_COLD_BUILD, index,
                                          env={"POCL_KERNEL_CACHE": "0"}).split())
        return {"build": grid, "build_moments": mom}
    except Exception as exc:  # noqa: BLE001
        return {"error": str(exc)}


def split_once(pts, r, index, refine=True):
    """One DeviceCloud + device_moments run; its stage timings (s)."""
    cloud = DeviceCloud(pts, r, device=index)
    device_moments(cloud, r, refine=refine)
    return dict(cloud.timings)


def bench_split(pts, r, index, repeats):
    """Stages, min of warm runs each; and the kernel time of the one-pass (normals) program."""
    warm = {k: math.inf for k in STAGES}
    for _ in range(1 + repeats):  # the first one is a warm-up
        t = split_once(pts, r, index)
        warm = {k: min(warm[k], t[k]) for k in STAGES}
    single = min(split_once(pts, r, index, refine=False)["kernel_moments"]
                 for _ in range(1 + repeats))  # the first one builds the refine=0 program
    return {"warm": warm, "kernel_single_pass_s": single}


def bench_e2e(clouds, r, index, repeats):
    """Public API end to end (orient=None): the three curvature methods and normals.

    Returns seconds per operator and the warm-up results used for the accuracy check."""
    pts = clouds["random"]
    seconds, results = {}, {}
    for m in METHODS:
        call = lambda m=m: clcurv.curvature(pts, r, method=m, orient=None, device=index)
        results[m] = call()  # warm-up
        seconds[m] = timeit(call, repeats, warmup=0)
    call = lambda: clcurv.normals(pts, r, orient=None, device=index)
    results["normals"] = call()
    seconds["normals"] = timeit(call, repeats, warmup=0)
    sorted_pts = clouds["sorted"]
    seconds["variation_sorted_input"] = timeit(
        lambda: clcurv.curvature(sorted_pts, r, method="variation", orient=None, device=index),
        repeats)
    return seconds, results


def variation_error(var, ref, cap):
    """Relative error of surface variation on the cap points with equal counts, status ok."""
    same = (var.count[cap] == ref["count"]) & (var.status[cap] == 0) & (ref["status"] == 0)
    rel = np.abs(var.variation[cap][same] - ref["variation"][same]) / ref["variation"][same]
    return float(np.median(rel)), float(np.quantile(rel, 0.999))


def check_against_reference(results, ref, cap, interior, ref32):
    """Normals and variation of the whole-cloud run, on the cap, against the float64 reference.

    Counts must agree on the cap interior (points farther than r from the cap border, whose
    whole ball lies in the cap; float32 may put a neighbour at distance ~r on the other
    side). Normals and variation are compared on the cap points whose counts agree and whose
    status is OK in both."""
    var = results["variation"]
    equal = var.count[cap] == ref["count"]
    same = equal & (var.status[cap] == 0) & (ref["status"] == 0)
    out = {"compared": int(same.sum()), "of": len(cap),
           "interior": int(interior.sum()), "interior_counts_agree": float(equal[interior].mean())}
    for name, n in (("curvature", var.normals[cap]), ("normals", results["normals"][cap])):
        one_minus_cos = 1 - np.abs(np.einsum("ij,ij->i", n[same], ref["normals"][same]))
        out[f"{name}_cos_worst"] = float(one_minus_cos.max())
        out[f"{name}_cos_fail"] = int(np.count_nonzero(one_minus_cos > COS_TOL))
    out["variation_rel_median"], out["variation_rel_p999"] = variation_error(var, ref, cap)
    out["variation_rel_median_f32_input"], out["variation_rel_p999_f32_input"] = \
        variation_error(var, ref32, cap)
    out["normals_pass"] = out["curvature_cos_fail"] == 0 and out["normals_cos_fail"] == 0
    out["variation_pass"] = out["variation_rel_median"] <= VAR_MEDIAN_TOL
    out["counts_pass"] = out["interior_counts_agree"] >= AGREE_MIN
    out["pass"] = out["normals_pass"] and out["variation_pass"] and out["counts_pass"]
    return out


def bench_ops(pts, nrm, r, index, repeats, cap):
    """2dcov1, 2dcov2, 3dcov and MLS2 with the exact normals (the operator alone), and MLS2
    with orient=None (its own PCA frame), end to end; each kernel alone on one DeviceCloud
    (``cloud.timings``). Returns (seconds, kernel seconds, cap slices of the results)."""
    seconds, kept = {}, {}
    normals = lambda: clcurv.normals(pts, r, orient=None, device=index)
    normals()
    for m in OPS:
        call = lambda m=m: clcurv.curvature(pts, r, method=m, normals=nrm, device=index)
        res = call()  # warm-up (builds the program)
        kept[m] = {a: getattr(res, a)[cap] for a in ("count", "status", "k1", "k2")}
        # interleaved with clcurv.normals, for the time ratio (PAIRED_REPEATS pairs)
        seconds[m], seconds[f"normals_paired_{m}"] = paired(call, normals,
                                                            max(repeats, PAIRED_REPEATS))
    mls2_none = lambda: clcurv.curvature(pts, r, method="mls2", orient=None, device=index)
    seconds["mls2_orient_none"], seconds["normals_paired_mls2_orient_none"] = paired(
        mls2_none, normals, max(repeats, PAIRED_REPEATS))
    cloud = DeviceCloud(pts, r, device=index)
    runs = {m: (lambda m=m: device_covariances(cloud, r, nrm, m), f"kernel_{m}") for m in COV}
    runs["mls2"] = (lambda: device_mls2(cloud, r, nrm), "kernel_mls2")
    runs["mls2_orient_none"] = (lambda: device_mls2(cloud, r, None), "kernel_mls2")
    kernel, upload = {}, {}
    for name, (fn, key) in runs.items():
        best, up = math.inf, math.inf
        for i in range(1 + repeats):
            fn()
            if i:
                best, up = min(best, cloud.timings[key]), min(up, cloud.timings["upload_normals"])
        kernel[name], upload[name] = best, up
    return seconds, {"kernel": kernel, "upload_normals_and_build": upload}, kept


def bench_scale_space(pts, nrm, r, index, repeats, cap, iterations=SS_ITERATIONS):
    """MLS1 scale space: 1 iteration end to end; ``iterations`` iterations end to end with
    ``last_stats`` (of the fastest run); the pipeline curvature(mls2, scale_space=iterations,
    normals=exact). Also the displacement after 2 iterations on the cap (for the check)."""
    ss = clcurv.scale_space
    out = {"iterations": iterations,
           "one_iteration_s": timeit(lambda: ss(pts, r, 1, device=index), repeats)}
    best, stats = math.inf, None
    for i in range(1 + repeats):
        s, _ = timed(lambda: ss(pts, r, iterations, device=index))
        if i and s < best:
            best, stats = s, dict(ss.last_stats)
    out.update(e2e_s=best, rebins=stats["rebins"], binning_s=stats["binning"],
               steps_s=stats["steps"], per_iteration_s=(stats["binning"] + stats["steps"]) / iterations)
    disp2 = ss(pts, r, 2, device=index)[cap] - pts[cap]
    out["pipeline_s"] = timeit(lambda: clcurv.curvature(
        pts, r, method="mls2", scale_space=iterations, normals=nrm, device=index), repeats)
    return out, disp2


def quantiles(err):
    return {"median": float(np.median(err)), "p999": float(np.quantile(err, 0.999)),
            "max": float(err.max())} if len(err) else {"median": math.nan, "p999": math.nan,
                                                       "max": math.nan}


def op_errors(d, rf, m):
    """(points compared, {k: error quantiles}) of one operator against one reference run."""
    same = (d["count"] == rf["count"]) & (d["status"] == 0) & (rf["status"] == 0)
    if m == "mls2":
        scale = np.maximum(np.abs(rf["k1"][same]), np.abs(rf["k2"][same]))
        return same, {k: quantiles(np.abs(d[k][same] - rf[k][same]) / scale) for k in ("k1", "k2")}
    return same, {"k1": quantiles(np.abs(d["k1"][same] - rf["k1"][same]) / np.abs(rf["k1"][same]))}


def check_ops(kept, ref):
    """Covariance operators' k1 (relative) and MLS2's k1, k2 (relative to max |k|) against the
    float64 reference, on the cap points whose counts agree and whose status is OK in both;
    and (information) against the reference run on the float32-rounded input."""
    out = {}
    for m in OPS:
        same, err = op_errors(kept[m], ref["ops"][m], m)
        c = {"compared": int(same.sum()), "of": len(same), **err,
             "f32_input": op_errors(kept[m], ref["ops_f32_input"][m], m)[1]}
        tol = MLS2_K_TOL if m == "mls2" else COV_K1_TOL
        c["pass"] = bool(max(e["p999"] for k, e in err.items()) <= tol)
        out[m] = c
    return out


def check_scale_space(disp2, ref, pts, cap, r):
    """Positions after 2 iterations on the cap interior (balls of radius SS_HOPS r inside the
    cap), |d| / r, against the float64 reference (and, for information, the reference run on
    the float32-rounded input)."""
    z = pts[cap, 2]
    inner = z - SS_HOPS * r > z.min()
    d64 = np.linalg.norm(disp2[inner] - ref["ops"]["scale_space_disp2"][inner], axis=1) / r
    d32 = np.linalg.norm(disp2[inner] - ref["ops"]["scale_space_disp2_f32_input"][inner], axis=1) / r
    out = {"compared": int(inner.sum()), "of": len(cap), "err": quantiles(d64),
           "err_f32_input": quantiles(d32)}
    out["pass"] = bool(out["err"]["p999"] <= SS_TOL)
    return out


def clcurv_label(index, cid):
    return f"clcurv device {index} {cid}"


def bench_device(info, cols, data, refs, repeats, guard):
    """All clcurv measurements on one device, per column (size, neighbour count)."""
    log(f"device {info}: cold build (no PoCL cache, subprocess)")
    out = {"device": device_record(info), "cold_build_no_cache": cold_build(info.index), "k": {}}
    c0 = cols[0]
    log(f"  first run in this process, {c0['id']} (not repeated, not guarded)")
    out["first_in_process"] = {"k": c0["id"], **split_once(data[c0["n"]]["random"], c0["r"],
                                                           info.index)}
    for col in cols:
        cid, r, d, cap = col["id"], col["r"], data[col["n"]], col["cap"]
        pts, nrm = d["random"], d["normals"]

        def measure():
            log(f"  {cid}: stages, end to end")
            split = bench_split(pts, r, info.index, repeats)
            seconds, results = bench_e2e(d, r, info.index, repeats)
            log(f"  {cid}: 2dcov1, 2dcov2, 3dcov, mls2")
            op_s, kern, kept = bench_ops(pts, nrm, r, info.index, repeats, cap)
            log(f"  {cid}: scale space, pipeline")
            ss, disp2 = bench_scale_space(pts, nrm, r, info.index, repeats, cap)
            return split, seconds, results, op_s, kern, kept, ss, disp2

        split, seconds, results, op_s, kern, kept, ss, disp2 = guard.block(
            clcurv_label(info.index, cid), measure)
        ref = refs[cid]
        check = check_against_reference(results, ref["result"], cap,
                                        cap_interior(pts, cap, r), ref["result_f32_input"])
        out["k"][cid] = {"n": col["n"], "neighbours": col["k"], "radius": r,
                         "e2e_s": {**seconds, **op_s}, "split": split, "ops_kernel": kern,
                         "scale_space": ss, "check": check, "check_ops": check_ops(kept, ref),
                         "check_scale_space": check_scale_space(disp2, ref, pts, cap, r),
                         "threads": guard.gains(clcurv_label(info.index, cid)),
                         "mean_count": float(results["variation"].count.mean())}
    return out


def device_record(info):
    return {"index": info.index, "name": info.name, "platform": info.platform, "kind": info.kind,
            "driver": info.driver, "version": info.version, "compute_units": info.compute_units}


# ----------------------------------------------------------------------------- ratios, targets
def ratios(n, dev_k, ref, o3d_k, jak_k):
    """Throughputs and ratios of one device in one column (None when not measured)."""
    e = dev_k["e2e_s"]
    e2e = e["variation"]
    o3d_normals = o3d_k["sorted"]["normals_s"] if o3d_k else None
    ss = dev_k["scale_space"]
    out = {"e2e_variation_mpts": mpts(n, e2e),
           "kernel_mpts": mpts(n, dev_k["split"]["warm"]["kernel_moments"]),
           "vs_open3d_normals_sorted": o3d_normals / e2e if o3d_normals else None,
           "vs_reference": ref["seconds"] / ref["points"] * n / e2e,
           "binning_over_kernel": (dev_k["split"]["warm"]["binning"]
                                   / dev_k["split"]["warm"]["kernel_moments"]),
           "vs_jakteristics_sorted": jak_k["sorted"]["seconds"] / e2e if jak_k else None}
    out["op_vs_reference"] = {m: ref_extrapolated(ref, m, n) / e[m] for m in OPS}
    out["op_vs_reference"]["mls2_orient_none"] = ref_extrapolated(ref, "mls2", n) / e["mls2_orient_none"]
    # against clcurv.normals runs interleaved with the operator's (see paired)
    out["op_over_normals"] = {m: e[m] / e[f"normals_paired_{m}"]
                              for m in OPS + ("mls2_orient_none",)}
    out["ss_iteration_vs_reference"] = ref_extrapolated(ref, "scale_space_iteration", n) / ss["per_iteration_s"]
    out["ss_iteration_vs_open3d"] = (o3d_normals / ss["per_iteration_s"]) if o3d_normals else None
    out["ss_one_iteration_e2e_vs_open3d"] = (o3d_normals / ss["one_iteration_s"]) if o3d_normals else None
    return out


def target_columns(cols):
    """The columns the targets are evaluated at: those of the largest size."""
    top = max(c["n"] for c in cols)
    return [c for c in cols if c["n"] == top]


def targets(dev, rat, orientation, cols):
    """(name, value, threshold, pass) rows; pass is None when the value was not measured."""
    rows = []
    tcols = [c["id"] for c in target_columns(cols)]
    for cid in tcols:
        v = rat[cid]["vs_open3d_normals_sorted"]
        rows.append((f"normals+variation e2e / Open3D estimate_normals (sorted), {cid}",
                     v, f">= {E2E_VS_OPEN3D:g}x", None if v is None else v >= E2E_VS_OPEN3D))
    c30 = min(tcols, key=lambda c: abs(dev["k"][c]["neighbours"] - 30))
    v = rat[c30]["kernel_mpts"]
    rows.append((f"kernel-only M pts/s (curvature kernel, λ0 refined), {c30}", v,
                 f">= {KERNEL_MPTS_AT_30:g}", v >= KERNEL_MPTS_AT_30))
    for cid in tcols:
        v = rat[cid]["vs_reference"]
        rows.append((f"e2e variation / NumPy reference, {cid}", v, f">= {VS_REFERENCE:g}x",
                     v >= VS_REFERENCE))
    for cid in tcols:
        v = rat[cid]["binning_over_kernel"]
        rows.append((f"binning / kernel time, {cid}", v, "<= 1", v <= 1))
    v = (orientation["open3d_s"] / orientation["clcurv_s"]) if "open3d_s" in orientation else None
    rows.append((f"orientation (k=10, {orientation['points'] // 1000}k pts) / Open3D", v,
                 f">= {ORIENT_VS_OPEN3D:g}x", None if v is None else v >= ORIENT_VS_OPEN3D))
    for cid in tcols:
        ra, K = rat[cid], dev["k"][cid]
        v = ra["op_vs_reference"]["mls2"]
        rows.append((f"MLS2 e2e (normals=) / NumPy reference MLS2, {cid}", v,
                     f">= {MLS2_VS_REFERENCE:g}x", v >= MLS2_VS_REFERENCE))
        v = ra["op_over_normals"]["mls2"]
        rows.append((f"MLS2 e2e (normals=) time / clcurv.normals(orient=None) time, {cid}", v,
                     f"<= {MLS2_VS_NORMALS:g}x", v <= MLS2_VS_NORMALS))
        for m in COV:
            v = ra["op_over_normals"][m]
            rows.append((f"{m} e2e (normals=) time / clcurv.normals time, {cid}", v,
                         f"<= {COV_VS_NORMALS:g}x", v <= COV_VS_NORMALS))
        v = K["scale_space"]["pipeline_s"]
        rows.append((f"pipeline scale_space={SS_ITERATIONS} + MLS2 e2e, seconds, {cid}", v,
                     f"< {PIPELINE_MAX_S:g} s", v < PIPELINE_MAX_S))
        v = ra["ss_iteration_vs_open3d"]
        rows.append((f"scale-space iteration ((binning+steps)/{SS_ITERATIONS}) / Open3D "
                     f"estimate_normals (sorted), {cid}", v, f">= {SS_VS_OPEN3D:g}x",
                     None if v is None else v >= SS_VS_OPEN3D))
        v = ra["ss_one_iteration_e2e_vs_open3d"]
        rows.append((f"scale space, 1 iteration e2e / Open3D estimate_normals (sorted), {cid}",
                     v, f">= {SS_VS_OPEN3D:g}x", None if v is None else v >= SS_VS_OPEN3D))
    for cid, d in dev["k"].items():
        rows.append((f"accuracy vs reference (counts, normals, variation), {cid}", None,
                     "see table", d["check"]["pass"]))
        rows.append((f"accuracy vs reference (2dcov1, 2dcov2, 3dcov k1; MLS2 k1, k2), {cid}", None,
                     "see table", all(c["pass"] for c in d["check_ops"].values())))
        rows.append((f"accuracy vs reference (scale space, 2 iterations), {cid}", None,
                     "see table", d["check_scale_space"]["pass"]))
    return rows


# ----------------------------------------------------------------------------- table
def fmt(v, spec=".2f", unit=""):
    return "–" if v is None else f"{v:{spec}}{unit}"


def pass_fail(ok):
    return "n/a" if ok is None else "PASS" if ok else "FAIL"


def device_rows(dev, refs, o3d, jak, rat, cols):
    """Table rows (label, one cell per column) for one device."""
    K = dev["k"]
    ids = [c["id"] for c in cols]
    N = {c["id"]: c["n"] for c in cols}
    ms = lambda s: fmt(None if s is None else s * 1e3, ".1f")
    blank = [""] * len(ids)
    first_only = lambda s: [s] + [""] * (len(ids) - 1)

    def e2e(key):
        return [f"{mpts(N[c], K[c]['e2e_s'][key]):.2f} ({ms(K[c]['e2e_s'][key])})" for c in ids]

    rows = [("radius", [f"{K[c]['radius']:.5f}" for c in ids]),
            ("mean neighbour count, point included", [f"{K[c]['mean_count']:.1f}" for c in ids]),
            ("**end to end, orient=None, random order**", ["M pts/s (ms)"] * len(ids))]
    for m in METHODS + ("normals",):
        rows.append((f"clcurv.curvature({m})" if m != "normals" else "clcurv.normals", e2e(m)))
    rows.append(("curvature(variation), sorted input (info)",
                 [f"{mpts(N[c], K[c]['e2e_s']['variation_sorted_input']):.2f}" for c in ids]))
    rows.append(("**end to end, exact normals given (normals=: operator alone)**",
                 ["M pts/s (ms)"] * len(ids)))
    for m in OPS:
        rows.append((f"clcurv.curvature({m}, normals=)", e2e(m)))
    rows.append(("clcurv.curvature(mls2, orient=None) (its own PCA frame)", e2e("mls2_orient_none")))
    rows.append(("**stages, ms (min of warm runs)**", blank))
    for st in STAGES:
        rows.append((st, [ms(K[c]["split"]["warm"][st]) for c in ids]))
    first = dev["first_in_process"]
    rows.append((f"first run in process ({first['k']}): build + build_moments + kernel",
                 first_only(f"{ms(first['build'])} + {ms(first['build_moments'])} + "
                            f"{ms(first['kernel_moments'])}")))
    cold = dev["cold_build_no_cache"]
    if "error" not in cold:
        rows.append(("build + build_moments with PoCL's disk cache off",
                     first_only(f"{ms(cold['build'])} + {ms(cold['build_moments'])}")))
    rows.append(("host rest ≈ e2e variation − Σ warm stages (ms)",
                 [ms(K[c]["e2e_s"]["variation"] - sum(K[c]["split"]["warm"].values()))
                  for c in ids]))
    rows.append(("kernel-only M pts/s (λ0 refined, curvature / one pass, normals)",
                 [f"{rat[c]['kernel_mpts']:.2f} / "
                  f"{mpts(N[c], K[c]['split']['kernel_single_pass_s']):.2f}" for c in ids]))
    rows.append(("**kernel only (cloud.timings), ms (M pts/s)**", blank))
    for m in OPS + ("mls2_orient_none",):
        label = f"kernel_{m}" if m != "mls2_orient_none" else "kernel_mls2, no normals"
        rows.append((label, [f"{ms(K[c]['ops_kernel']['kernel'][m])} "
                             f"({mpts(N[c], K[c]['ops_kernel']['kernel'][m]):.2f})" for c in ids]))
    rows.append(("upload of the normals + program lookup, 2dcov2 / mls2 (ms)",
                 [f"{ms(K[c]['ops_kernel']['upload_normals_and_build']['2dcov2'])} / "
                  f"{ms(K[c]['ops_kernel']['upload_normals_and_build']['mls2'])}" for c in ids]))
    rows.append(("**MLS1 scale space (clcurv.scale_space), ms**", blank))
    S = {c: K[c]["scale_space"] for c in ids}
    rows.append(("1 iteration end to end (M pts/s)",
                 [f"{ms(S[c]['one_iteration_s'])} ({mpts(N[c], S[c]['one_iteration_s']):.2f})"
                  for c in ids]))
    rows.append((f"{SS_ITERATIONS} iterations end to end", [ms(S[c]["e2e_s"]) for c in ids]))
    rows.append(("  of which binning (rebins) / steps (last_stats)",
                 [f"{ms(S[c]['binning_s'])} ({S[c]['rebins']}) / {ms(S[c]['steps_s'])}"
                  for c in ids]))
    rows.append((f"per iteration, (binning + steps) / {SS_ITERATIONS} (M pts/s)",
                 [f"{ms(S[c]['per_iteration_s'])} ({mpts(N[c], S[c]['per_iteration_s']):.2f})"
                  for c in ids]))
    rows.append((f"pipeline curvature(mls2, scale_space={SS_ITERATIONS}, normals=) e2e",
                 [ms(S[c]["pipeline_s"]) for c in ids]))
    rows.append(("**peers, M pts/s**", blank))
    rows.append(("NumPy reference (float64) on a cap of", [f"{refs[c]['points']:,} pts" for c in ids]))
    for op, label in (("moments", "moments (variation, mls0, mls1, normals)"),
                      *((m, m) for m in OPS),
                      ("scale_space_iteration", "MLS1 scale-space iteration")):
        rows.append((f"  reference {label}", [f"{refs[c]['op_mpts'][op]:.4f}" for c in ids]))
    if o3d:
        for op in ("normals", "covariances"):
            rows.append((f"Open3D estimate_{op}, sorted / random",
                         [f"{mpts(N[c], o3d[c]['sorted'][f'{op}_s']):.3f} / "
                          f"{mpts(N[c], o3d[c]['random'][f'{op}_s']):.3f}" for c in ids]))
    if jak:
        rows.append(("jakteristics compute_features (6 features), sorted / random",
                     [f"{mpts(N[c], jak[c]['sorted']['seconds']):.3f} / "
                      f"{mpts(N[c], jak[c]['random']['seconds']):.3f}" for c in ids]))
        rows.append(("  jakteristics mean number_of_neighbors",
                     [f"{jak[c]['mean_count']:.1f}" for c in ids]))
    rows.append(("**ratios**", blank))
    rows.append(("e2e variation / Open3D estimate_normals (sorted)",
                 [fmt(rat[c]["vs_open3d_normals_sorted"], ".1f", "x") for c in ids]))
    if jak:
        rows.append(("e2e variation / jakteristics (sorted)",
                     [fmt(rat[c]["vs_jakteristics_sorted"], ".1f", "x") for c in ids]))
    rows.append(("e2e variation / NumPy reference (extrapolated)",
                 [fmt(rat[c]["vs_reference"], ".0f", "x") for c in ids]))
    for m in OPS + ("mls2_orient_none",):
        rows.append((f"e2e {m if m != 'mls2_orient_none' else 'mls2 orient=None'} / NumPy "
                     f"reference {'mls2' if m == 'mls2_orient_none' else m} (extrapolated)",
                     [fmt(rat[c]["op_vs_reference"][m], ".0f", "x") for c in ids]))
    rows.append(("scale-space iteration / NumPy reference iteration",
                 [fmt(rat[c]["ss_iteration_vs_reference"], ".0f", "x") for c in ids]))
    for m in OPS + ("mls2_orient_none",):
        rows.append((f"time {m if m != 'mls2_orient_none' else 'mls2 orient=None'} / time "
                     f"clcurv.normals", [fmt(rat[c]["op_over_normals"][m], ".2f", "x") for c in ids]))
    rows.append(("scale-space iteration / Open3D estimate_normals (sorted)",
                 [fmt(rat[c]["ss_iteration_vs_open3d"], ".1f", "x") for c in ids]))
    rows.append(("binning / kernel", [fmt(rat[c]["binning_over_kernel"], ".2f") for c in ids]))
    rows.append(("**accuracy vs reference on the cap**", blank))
    C = {c: K[c]["check"] for c in ids}
    rows.append((f"cap interior: counts equal to reference (>= {AGREE_MIN:.1%})",
                 [f"{C[c]['interior_counts_agree']:.3%} of {C[c]['interior']} "
                  f"{pass_fail(C[c]['counts_pass'])}" for c in ids]))
    rows.append(("cap points compared (equal counts, status ok)",
                 [f"{C[c]['compared']} of {C[c]['of']}" for c in ids]))
    rows.append((f"normals 1−|cos| worst (curv / normals), tol {COS_TOL:g}",
                 [f"{C[c]['curvature_cos_worst']:.1e} / {C[c]['normals_cos_worst']:.1e} "
                  f"{pass_fail(C[c]['normals_pass'])}" for c in ids]))
    rows.append((f"variation rel. error median (p99.9), tol {VAR_MEDIAN_TOL:g}",
                 [f"{C[c]['variation_rel_median']:.1e} ({C[c]['variation_rel_p999']:.1e}) "
                  f"{pass_fail(C[c]['variation_pass'])}" for c in ids]))
    rows.append(("same vs reference on the float32 input (kernel arithmetic only)",
                 [f"{C[c]['variation_rel_median_f32_input']:.1e} "
                  f"({C[c]['variation_rel_p999_f32_input']:.1e})" for c in ids]))
    q = lambda e: f"{e['median']:.1e} / {e['p999']:.1e} / {e['max']:.1e}"
    for m in COV:
        rows.append((f"{m} k1 rel. error median / p99.9 / max, tol p99.9 <= {COV_K1_TOL:g}",
                     [f"{q(K[c]['check_ops'][m]['k1'])} {pass_fail(K[c]['check_ops'][m]['pass'])}"
                      for c in ids]))
    rows.append(("  same vs reference on the float32 input, 2dcov1 / 2dcov2 / 3dcov p99.9",
                 [" / ".join(f"{K[c]['check_ops'][m]['f32_input']['k1']['p999']:.1e}" for m in COV)
                  for c in ids]))
    rows.append(("  points compared (equal counts, status ok), 2dcov2",
                 [f"{K[c]['check_ops']['2dcov2']['compared']} of {K[c]['check_ops']['2dcov2']['of']}"
                  for c in ids]))
    for k in ("k1", "k2"):
        rows.append((f"mls2 {k} |err|/max|k| median / p99.9 / max, tol p99.9 <= {MLS2_K_TOL:g}",
                     [f"{q(K[c]['check_ops']['mls2'][k])} "
                      f"{pass_fail(K[c]['check_ops']['mls2']['pass'])}" for c in ids]))
    rows.append(("  same vs reference on the float32 input, k1 / k2 p99.9 (max)",
                 [" / ".join(f"{K[c]['check_ops']['mls2']['f32_input'][k]['p999']:.1e} "
                             f"({K[c]['check_ops']['mls2']['f32_input'][k]['max']:.1e})"
                             for k in ("k1", "k2")) for c in ids]))
    rows.append(("  points compared (equal counts, status ok), mls2",
                 [f"{K[c]['check_ops']['mls2']['compared']} of {K[c]['check_ops']['mls2']['of']}"
                  for c in ids]))
    SC = {c: K[c]["check_scale_space"] for c in ids}
    rows.append((f"scale space, 2 iterations: |d|/r median / p99.9 / max, tol p99.9 <= {SS_TOL:g}",
                 [f"{q(SC[c]['err'])} {pass_fail(SC[c]['pass'])}" for c in ids]))
    rows.append(("  same vs reference on the float32 input (kernel arithmetic only)",
                 [q(SC[c]["err_f32_input"]) for c in ids]))
    rows.append((f"  cap interior compared (balls of {SS_HOPS:g} r inside the cap)",
                 [f"{SC[c]['compared']} of {SC[c]['of']}" for c in ids]))
    rows.append(("**cores free? 2-thread gain of a PoCL spin kernel, before / after**", blank))
    rows.append(("clcurv block", [K[c]["threads"] for c in ids]))
    if o3d:
        rows.append(("Open3D block", [o3d[c]["threads"] for c in ids]))
    if jak:
        rows.append(("jakteristics block", [jak[c]["threads"] for c in ids]))
    return rows


def render_text(header, rows):
    w0 = max(len(r[0]) for r in rows + [header]) + 2
    w = [max(len(c) for c in col) + 2 for col in zip(*[header[1]] + [r[1] for r in rows])]
    lines = [header[0].ljust(w0) + "".join(c.rjust(x) for c, x in zip(header[1], w))]
    for label, cells in rows:
        if label.startswith("**"):
            lines.append(label.strip("*").ljust(w0) + "".join(c.rjust(x) for c, x in zip(cells, w)))
            continue
        lines.append(("  " + label).ljust(w0) + "".join(c.rjust(x) for c, x in zip(cells, w)))
    return "\n".join(lines)


def md_row(cells):
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def render_markdown(header, rows):
    lines = [md_row([header[0]] + header[1]), "|---" + "|---:" * len(header[1]) + "|"]
    lines += [md_row([label] + cells) for label, cells in rows]
    return "\n".join(lines)


def render_targets(rows):
    w = max(len(r[0]) + len(r[2]) for r in rows) + 6
    return "\n".join(f"  {name} ({thr})".ljust(w) + f"{val:>8}  {ok}" for name, val, thr, ok in rows)


def target_lines(rows):
    out = []
    for name, v, thr, ok in rows:
        val = "" if v is None else f"{v:.2f}"
        out.append((name, val, thr, pass_fail(ok)))
    return out


def summary_text(env, args, threads, jak_note):
    plats = "; ".join(f"{k}: {v}" for k, v in env["platforms"].items())
    return "\n".join([
        f"clcurv {env['clcurv']} benchmark, {env['date']}: unit sphere, n = "
        f"{', '.join(f'{n:,}' for n in args.sizes)}, ~{', ~'.join(map(str, args.neighbours))} "
        f"neighbours, min of {args.repeats} repeats after a warm-up",
        f"CPU {env['cpu']} ({env['cpus']} logical, {' '.join(env['cpu_flags'])}), Python "
        f"{env['python']}, numpy {env['numpy']}, pyopencl {env['pyopencl']}, open3d "
        f"{env['open3d'] or 'not available'}, jakteristics {env.get('jakteristics') or 'not available'}",
        f"OpenCL platforms: {plats}",
        *([f"jakteristics skipped: {jak_note}"] if jak_note else []),
        "thread checks (PoCL spin kernel, 1 vs 2 threads; BUSY when 2 threads are less than "
        f"x{THREADS_MIN_GAIN} faster):",
        *("  " + describe_threads(check, when) for when, check in threads.items()),
        "Ratios use clcurv on the random-order cloud and Open3D / jakteristics on the spatially "
        "sorted copy (they are several times slower on random order; both orders are listed). "
        "The NumPy reference runs each operator once on a polar cap of the same cloud at the "
        "same radius (same neighbour counts); its points/s is extrapolated linearly to n. "
        "Normal-based operators get the exact sphere normals (normals=); their 'time X / time "
        f"clcurv.normals' ratios are minima over {PAIRED_REPEATS} interleaved (X, normals) pairs, "
        "so both sides run in the same seconds of this shared machine. jakteristics computes "
        f"{', '.join(JAK_FEATURES)} (its k-d tree build included, all cores). Targets are "
        "evaluated at the largest size."])


def orientation_text(o):
    line = (f"orientation, {o['points']:,} sphere points, k=10: clcurv flip_by_propagation "
            f"{o['clcurv_s']:.2f} s ({o['points'] / o['clcurv_s'] / 1e3:.0f} k pts/s, "
            f"{o['clcurv_outward'] * 100:.2f}% outward)")
    if "open3d_s" in o:
        line += (f"; Open3D orient_normals_consistent_tangent_plane(10) {o['open3d_s']:.2f} s, "
                 f"one run ({o['points'] / o['open3d_s'] / 1e3:.0f} k pts/s, "
                 f"{o['open3d_consistent'] * 100:.2f}% consistent)")
    return line


# ----------------------------------------------------------------------------- main
def parse_size(text):
    """'100k', '1M', '250000' -> int."""
    t = text.strip().lower().replace("_", "").replace(",", "")
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:], 1)
    return int(float(t[:-1] if mult > 1 else t) * mult)


def size_label(n):
    if n >= 1_000_000 and n % 100_000 == 0:
        return f"{n / 1e6:g}M"
    if n >= 1_000 and n % 1_000 == 0:
        return f"{n // 1000}k"
    return str(n)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[100_000, 1_000_000],
                    metavar="N", help="cloud sizes (e.g. 100k 1M; default 100k 1M)")
    ap.add_argument("--n", type=parse_size, default=None, help="one size (same as --sizes N)")
    ap.add_argument("--neighbours", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ref-points", type=int, default=100_000,
                    help="points of the NumPy reference subsample (at most n/4)")
    ap.add_argument("--orient-points", type=int, default=100_000)
    ap.add_argument("--quick", action="store_true",
                    help="100k points, ~30 neighbours, 1 repeat, 20k-point subsamples (< 1 min)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--no-jakteristics", action="store_true")
    ap.add_argument("--wait-quiet", type=float, default=60, metavar="SECONDS",
                    help="before each block, wait up to this long for both cores to be free")
    ap.add_argument("--retries", type=int, default=2,
                    help="measure a block again (up to this many times) when the cores were busy")
    args = ap.parse_args(argv)
    if args.n is not None:
        args.sizes = [args.n]
    if args.quick:
        args.sizes, args.neighbours, args.repeats = [100_000], [30], 1
        args.ref_points, args.orient_points = 20_000, 20_000
        args.wait_quiet, args.retries = min(args.wait_quiet, 15), min(args.retries, 1)
    args.sizes = sorted(set(args.sizes))
    return args


def main(argv=None):
    args = parse_args(argv)
    env = environment()
    guard = Guard(args.wait_quiet, args.retries)
    o3d = None if args.no_open3d else open3d_or_none()
    jak, jak_note = (None, "--no-jakteristics") if args.no_jakteristics else jakteristics_or_reason()
    if jak is not None:
        import importlib.metadata
        try:
            env["jakteristics"] = importlib.metadata.version("jakteristics")
        except importlib.metadata.PackageNotFoundError:
            env["jakteristics"] = getattr(jak, "__version__", "?")
    elif not args.no_jakteristics:
        log(f"jakteristics not available ({jak_note}): skipped (pip install jakteristics)")
    infos = clcurv.devices()
    if not infos:
        raise SystemExit("no OpenCL device: " + clcurv.device.APT_HINT)

    data, cols = {}, []
    for n in args.sizes:
        pts, sorted_pts = make_clouds(n)
        data[n] = {"random": pts, "sorted": sorted_pts, "normals": exact_normals(pts)}
        for k in args.neighbours:
            r = radius_for(k, n)
            cols.append({"id": f"{size_label(n)} ~{k}", "n": n, "k": k, "r": r,
                         "cap": cap_indices(pts, min(args.ref_points, n // 4))})
    refs = {c["id"]: guard.block(f"NumPy reference {c['id']}", lambda c=c: bench_reference(
        data[c["n"]]["random"], c["r"], c["cap"], data[c["n"]]["normals"])) for c in cols}

    devs = [bench_device(info, cols, data, refs, args.repeats, guard) for info in infos]

    o3d_res, jak_res = {}, {}
    for c in cols:
        clouds = {"random": data[c["n"]]["random"], "sorted": data[c["n"]]["sorted"]}
        if o3d is not None:
            label = f"Open3D {c['id']}"
            o3d_res[c["id"]] = guard.block(label, lambda: bench_open3d(o3d, clouds, c["r"],
                                                                       args.repeats))
            o3d_res[c["id"]]["threads"] = guard.gains(label)
        if jak is not None:
            label = f"jakteristics {c['id']}"
            jak_res[c["id"]] = guard.block(label, lambda: bench_jakteristics(jak, clouds, c["r"],
                                                                             args.repeats))
            jak_res[c["id"]]["threads"] = guard.gains(label)
    orientation = guard.block("orientation", lambda: bench_orientation(
        o3d, args.orient_points, infos[0].index))

    report(args, env, guard, cols, refs, o3d_res, jak_res, jak_note, orientation, devs)


def report(args, env, guard, cols, refs, o3d_res, jak_res, jak_note, orientation, devs):
    """Print the tables and write JSON (one file per device kind) and bench.md."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    threads = guard.checks
    text = [summary_text(env, args, threads, jak_note), orientation_text(orientation)]
    if guard.busy():
        text.append(f"WARNING: cores were busy around: {', '.join(guard.busy())}; their figures "
                    "are pessimistic and ratios involving them are unreliable: rerun on a quiet "
                    "machine")
    md = ["# clcurv benchmark", "", "```", *text, "```"]
    kinds_seen = {}
    ids = [c["id"] for c in cols]
    for dev in devs:
        rat = {c["id"]: ratios(c["n"], dev["k"][c["id"]], refs[c["id"]], o3d_res.get(c["id"]),
                               jak_res.get(c["id"])) for c in cols}
        d = dev["device"]
        title = (f"[{d['index']}] {d['name']} — {d['platform']} "
                 f"({env['platforms'].get(d['platform'], '?')}), driver {d['driver']}, "
                 f"{d['version']}, {d['compute_units']} compute units")
        header = ("n, neighbours", ids)
        rows = device_rows(dev, refs, o3d_res, jak_res, rat, cols)
        tgt = target_lines(targets(dev, rat, orientation, cols))
        text += ["", title, render_text(header, rows), "", "targets", render_targets(tgt)]
        md += ["", f"## {title}", "", render_markdown(header, rows), "",
               "| target | value | threshold | result |", "|---|---:|---|---|"]
        md += [md_row(list(t)) for t in tgt]
        kind = d["kind"]
        kinds_seen[kind] = kinds_seen.get(kind, 0) + 1
        suffix = kind if kinds_seen[kind] == 1 else f"{kind}{kinds_seen[kind]}"
        write_json(RESULTS / f"bench-{suffix}.json", {
            "args": vars(args), "env": env, "threads": threads, "device": dev,
            "columns": [{x: v for x, v in c.items() if x != "cap"} for c in cols],
            "reference": {c: {x: v for x, v in refs[c].items()
                              if not x.startswith("result") and not x.startswith("ops")} for c in ids},
            "open3d": o3d_res, "jakteristics": jak_res or {"skipped": jak_note},
            "orientation": orientation, "ratios": rat,
            "targets": [dict(zip(("name", "value", "threshold", "result"), t)) for t in tgt]})
    print("\n".join(text))
    (RESULTS / "bench.md").write_text("\n".join(md) + "\n")
    log(f"wrote {RESULTS}/bench-*.json and bench.md")


def write_json(path, obj):
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(type(o).__name__)
    path.write_text(json.dumps(obj, indent=1, default=default, allow_nan=True) + "\n")


if __name__ == "__main__":
    main()
