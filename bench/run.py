"""clcurv benchmark: every OpenCL device against Open3D and the float64 NumPy reference.

Run from the repository root::

    python -m bench.run                 # 1M points, ~30 and ~100 neighbours, 3 repeats
    python -m bench.run --quick         # 100k points, smoke run
    python -m bench.run --no-open3d

The cloud is a uniform sample of the unit sphere (``clcurv.shapes.sphere``) in random order,
plus a spatially sorted copy (k-d tree leaf order). Radii give ~k neighbours:
r = sqrt(4 k / n) (area 4 pi, k = n pi r^2 / (4 pi)). Every timing is the minimum of
``--repeats`` runs after an untimed warm-up (so program builds are cached), except where the
table says otherwise. Each block (reference, clcurv per device and neighbour count, Open3D,
orientation) runs between two checks that both cores are free (a PoCL kernel timed with 1 and
2 threads); busy blocks are flagged. Prints a table, writes ``bench/results/bench-<devicekind>.json`` and
``bench/results/bench.md``.
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
from clcurv.grid import bin_points
from clcurv.moments import device_moments

RESULTS = Path(__file__).resolve().parent / "results"
REPO = Path(__file__).resolve().parent.parent
METHODS = ("variation", "mls0", "mls1")
STAGES = ("binning", "upload", "build", "cell_ranges", "build_moments", "kernel_moments", "download")

COS_TOL = 1e-4            # normals: 1 - |cos| against the float64 reference (tests/test_moments.py)
VAR_MEDIAN_TOL = 1e-3     # surface variation: median relative error against the reference
THREADS_MIN_GAIN = 1.6    # two PoCL threads must be this much faster than one (quiet: ~2.0)
AGREE_MIN = 0.998         # fraction of cap-interior points whose counts equal the reference's

E2E_VS_OPEN3D = 5.0       # targets
KERNEL_MPTS_AT_30 = 5.0
VS_REFERENCE = 50.0
ORIENT_VS_OPEN3D = 10.0


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
    """The float32 coordinates the device sees (centred in float64, then cast), input order."""
    g = bin_points(pts, r, np.float32)
    out = np.empty((len(pts), 3))
    out[g.order] = np.stack([g.x[:len(pts)], g.y[:len(pts)], g.z[:len(pts)]], axis=1)
    return out


def bench_reference(pts, r, cap):
    """The float64 NumPy reference on the cap (timed once; it is slow and deterministic).

    Also run (untimed) on the float32-rounded coordinates the device works with: the
    difference to that run is the kernels' own arithmetic error, the difference to the
    float64 run includes the rounding of the input to float32."""
    sub = pts[cap]
    t0 = time.perf_counter()
    ref = reference.moments(sub, r)
    seconds = time.perf_counter() - t0
    ref32 = reference.moments(device_coordinates(pts, r)[cap], r)
    return {"points": len(sub), "seconds": seconds, "mpts": mpts(len(sub), seconds),
            "mean_count": float(ref["count"].mean()), "result": ref, "result_f32_input": ref32}


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


def clcurv_label(index, k):
    return f"clcurv device {index} ~{k}"


def bench_device(info, clouds, radii, refs, caps, repeats, guard):
    """All clcurv measurements on one device, per neighbour count."""
    log(f"device {info}: cold build (no PoCL cache, subprocess)")
    out = {"device": device_record(info), "cold_build_no_cache": cold_build(info.index), "k": {}}
    k0 = next(iter(radii))
    log(f"  first run in this process, ~{k0} neighbours (not repeated, not guarded)")
    out["first_in_process"] = {"k": k0, **split_once(clouds["random"], radii[k0], info.index)}
    for k, r in radii.items():
        def measure():
            log(f"  ~{k} neighbours: stages, end to end")
            return (bench_split(clouds["random"], r, info.index, repeats),
                    *bench_e2e(clouds, r, info.index, repeats))
        split, seconds, results = guard.block(clcurv_label(info.index, k), measure)
        check = check_against_reference(results, refs[k]["result"], caps[k],
                                        cap_interior(clouds["random"], caps[k], r),
                                        refs[k]["result_f32_input"])
        out["k"][k] = {"radius": r, "e2e_s": seconds, "split": split, "check": check,
                       "threads": guard.gains(clcurv_label(info.index, k)),
                       "mean_count": float(results["variation"].count.mean())}
    return out


def device_record(info):
    return {"index": info.index, "name": info.name, "platform": info.platform, "kind": info.kind,
            "driver": info.driver, "version": info.version, "compute_units": info.compute_units}


# ----------------------------------------------------------------------------- ratios, targets
def ratios(n, dev_k, ref, o3d_k):
    """Throughputs and ratios of one device at one neighbour count (None when not measured)."""
    e2e = dev_k["e2e_s"]["variation"]
    o3d_normals = o3d_k["sorted"]["normals_s"] if o3d_k else None
    return {"e2e_variation_mpts": mpts(n, e2e),
            "kernel_mpts": mpts(n, dev_k["split"]["warm"]["kernel_moments"]),
            "vs_open3d_normals_sorted": o3d_normals / e2e if o3d_normals else None,
            "vs_reference": ref["seconds"] / ref["points"] * n / e2e,
            "binning_over_kernel": (dev_k["split"]["warm"]["binning"]
                                    / dev_k["split"]["warm"]["kernel_moments"])}


def targets(dev, rat, orientation):
    """(name, value, threshold, pass) rows; pass is None when the value was not measured."""
    rows = []
    for k, ra in rat.items():
        v = ra["vs_open3d_normals_sorted"]
        rows.append((f"normals+variation e2e / Open3D estimate_normals (sorted), ~{k} nbrs",
                     v, f">= {E2E_VS_OPEN3D:g}x", None if v is None else v >= E2E_VS_OPEN3D))
    k30 = min(rat, key=lambda k: abs(k - 30))
    v = rat[k30]["kernel_mpts"]
    rows.append((f"kernel-only M pts/s (curvature kernel, λ0 refined), ~{k30} nbrs", v, f">= {KERNEL_MPTS_AT_30:g}",
                 v >= KERNEL_MPTS_AT_30))
    for k, ra in rat.items():
        v = ra["vs_reference"]
        rows.append((f"e2e variation / NumPy reference, ~{k} nbrs", v, f">= {VS_REFERENCE:g}x",
                     v >= VS_REFERENCE))
    for k, ra in rat.items():
        v = ra["binning_over_kernel"]
        rows.append((f"binning / kernel time, ~{k} nbrs", v, "<= 1", v <= 1))
    v = (orientation["open3d_s"] / orientation["clcurv_s"]) if "open3d_s" in orientation else None
    rows.append((f"orientation (k=10, {orientation['points'] // 1000}k pts) / Open3D", v,
                 f">= {ORIENT_VS_OPEN3D:g}x", None if v is None else v >= ORIENT_VS_OPEN3D))
    for k, d in dev["k"].items():
        c = d["check"]
        rows.append((f"accuracy vs reference (counts, normals, variation), ~{k} nbrs", None,
                     "see table", c["pass"]))
    return rows


# ----------------------------------------------------------------------------- table
def fmt(v, spec=".2f", unit=""):
    return "–" if v is None else f"{v:{spec}}{unit}"


def pass_fail(ok):
    return "n/a" if ok is None else "PASS" if ok else "FAIL"


def device_rows(n, dev, refs, o3d, rat, ks):
    """Table rows (label, one cell per neighbour count) for one device."""
    K = dev["k"]
    ms = lambda s: fmt(None if s is None else s * 1e3, ".1f")
    rows = [("radius", [f"{K[k]['radius']:.5f}" for k in ks]),
            ("mean neighbour count, point included", [f"{K[k]['mean_count']:.1f}" for k in ks]),
            ("**end to end, orient=None, random order**", ["M pts/s (ms)"] * len(ks))]
    for m in METHODS + ("normals",):
        label = f"clcurv.curvature({m})" if m != "normals" else "clcurv.normals"
        rows.append((label, [f"{mpts(n, K[k]['e2e_s'][m]):.2f} ({ms(K[k]['e2e_s'][m])})"
                             for k in ks]))
    rows.append(("curvature(variation), sorted input (info)",
                 [f"{mpts(n, K[k]['e2e_s']['variation_sorted_input']):.2f}" for k in ks]))
    rows.append(("**stages, ms (min of warm runs)**", [""] * len(ks)))
    for st in STAGES:
        rows.append((st, [ms(K[k]["split"]["warm"][st]) for k in ks]))
    first = dev["first_in_process"]
    rows.append((f"first run in process (~{first['k']}): build + build_moments + kernel",
                 [f"{ms(first['build'])} + {ms(first['build_moments'])} + "
                  f"{ms(first['kernel_moments'])}"] + [""] * (len(ks) - 1)))
    cold = dev["cold_build_no_cache"]
    if "error" not in cold:
        rows.append(("build + build_moments with PoCL's disk cache off",
                     [f"{ms(cold['build'])} + {ms(cold['build_moments'])}"] + [""] * (len(ks) - 1)))
    rows.append(("host rest ≈ e2e variation − Σ warm stages (ms)",
                 [ms(K[k]["e2e_s"]["variation"] - sum(K[k]["split"]["warm"].values()))
                  for k in ks]))
    rows.append(("kernel-only M pts/s (λ0 refined, curvature / one pass, normals)",
                 [f"{rat[k]['kernel_mpts']:.2f} / {mpts(n, K[k]['split']['kernel_single_pass_s']):.2f}"
                  for k in ks]))
    rows.append(("**peers, M pts/s**", [""] * len(ks)))
    rows.append((f"NumPy reference (float64), {refs[ks[0]]['points'] // 1000}k-pt cap",
                 [f"{refs[k]['mpts']:.4f}" for k in ks]))
    if o3d:
        for op in ("normals", "covariances"):
            rows.append((f"Open3D estimate_{op}, sorted / random",
                         [f"{mpts(n, o3d[k]['sorted'][f'{op}_s']):.3f} / "
                          f"{mpts(n, o3d[k]['random'][f'{op}_s']):.3f}" for k in ks]))
    rows.append(("**ratios**", [""] * len(ks)))
    rows.append(("e2e variation / Open3D estimate_normals (sorted)",
                 [fmt(rat[k]["vs_open3d_normals_sorted"], ".1f", "x") for k in ks]))
    rows.append(("e2e variation / NumPy reference",
                 [fmt(rat[k]["vs_reference"], ".0f", "x") for k in ks]))
    rows.append(("binning / kernel", [fmt(rat[k]["binning_over_kernel"], ".2f") for k in ks]))
    rows.append(("**accuracy vs reference on the cap**", [""] * len(ks)))
    rows.append((f"cap interior: counts equal to reference (>= {AGREE_MIN:.1%})",
                 [f"{K[k]['check']['interior_counts_agree']:.3%} of {K[k]['check']['interior']} "
                  f"{pass_fail(K[k]['check']['counts_pass'])}" for k in ks]))
    rows.append(("cap points compared (equal counts, status ok)",
                 [f"{K[k]['check']['compared']} of {K[k]['check']['of']}" for k in ks]))
    rows.append((f"normals 1−|cos| worst (curv / normals), tol {COS_TOL:g}",
                 [f"{K[k]['check']['curvature_cos_worst']:.1e} / "
                  f"{K[k]['check']['normals_cos_worst']:.1e} "
                  f"{pass_fail(K[k]['check']['normals_pass'])}" for k in ks]))
    rows.append((f"variation rel. error median (p99.9), tol {VAR_MEDIAN_TOL:g}",
                 [f"{K[k]['check']['variation_rel_median']:.1e} "
                  f"({K[k]['check']['variation_rel_p999']:.1e}) "
                  f"{pass_fail(K[k]['check']['variation_pass'])}" for k in ks]))
    rows.append(("same vs reference on the float32 input (kernel arithmetic only)",
                 [f"{K[k]['check']['variation_rel_median_f32_input']:.1e} "
                  f"({K[k]['check']['variation_rel_p999_f32_input']:.1e})" for k in ks]))
    rows.append(("**cores free? 2-thread gain of a PoCL spin kernel, before / after**",
                 [""] * len(ks)))
    rows.append(("clcurv block", [K[k]["threads"] for k in ks]))
    if o3d:
        rows.append(("Open3D block", [o3d[k]["threads"] for k in ks]))
    return rows


def render_text(header, rows):
    w0 = max(len(r[0]) for r in rows + [header]) + 2
    w = [max(len(c) for c in col) + 2 for col in zip(*[header[1]] + [r[1] for r in rows])]
    lines = [header[0].ljust(w0) + "".join(c.rjust(x) for c, x in zip(header[1], w))]
    for label, cells in rows:
        if label.startswith("**"):
            lines.append(label.strip("*"))
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


def summary_text(env, args, threads):
    plats = "; ".join(f"{k}: {v}" for k, v in env["platforms"].items())
    return "\n".join([
        f"clcurv {env['clcurv']} benchmark, {env['date']}: unit sphere, n = {args.n:,}, "
        f"min of {args.repeats} repeats after a warm-up",
        f"CPU {env['cpu']} ({env['cpus']} logical, {' '.join(env['cpu_flags'])}), Python {env['python']}, numpy {env['numpy']}, "
        f"pyopencl {env['pyopencl']}, open3d {env['open3d'] or 'not available'}",
        f"OpenCL platforms: {plats}",
        "thread checks (PoCL spin kernel, 1 vs 2 threads; BUSY when 2 threads are less than "
        f"x{THREADS_MIN_GAIN} faster):",
        *("  " + describe_threads(check, when) for when, check in threads.items()),
        "Ratios use clcurv on the random-order cloud and Open3D on the spatially sorted copy "
        "(Open3D is several times slower on random order; both orders are listed). The NumPy "
        "reference runs once on a polar cap of the same cloud at the same radius (same "
        "neighbour counts); its points/s is extrapolated linearly to n."])


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
def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="points (default 1,000,000)")
    ap.add_argument("--neighbours", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ref-points", type=int, default=100_000,
                    help="points of the NumPy reference subsample (at most n/4)")
    ap.add_argument("--orient-points", type=int, default=100_000)
    ap.add_argument("--quick", action="store_true", help="n=100k, 2 repeats, 20k-point subsamples")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--wait-quiet", type=float, default=60, metavar="SECONDS",
                    help="before each block, wait up to this long for both cores to be free")
    ap.add_argument("--retries", type=int, default=2,
                    help="measure a block again (up to this many times) when the cores were busy")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.repeats = 100_000, 2
        args.ref_points, args.orient_points = 20_000, 20_000
        args.wait_quiet, args.retries = min(args.wait_quiet, 15), min(args.retries, 1)
    args.ref_points = min(args.ref_points, args.n // 4)
    return args


def main(argv=None):
    args = parse_args(argv)
    env = environment()
    guard = Guard(args.wait_quiet, args.retries)
    o3d = None if args.no_open3d else open3d_or_none()
    infos = clcurv.devices()
    if not infos:
        raise SystemExit("no OpenCL device: " + clcurv.device.APT_HINT)

    pts, sorted_pts = make_clouds(args.n)
    clouds = {"random": pts, "sorted": sorted_pts}
    ks = list(args.neighbours)
    radii = {k: radius_for(k, args.n) for k in ks}
    caps = {k: cap_indices(pts, args.ref_points) for k in ks}
    refs = {k: guard.block(f"NumPy reference ~{k}",
                           lambda k=k: bench_reference(pts, radii[k], caps[k])) for k in ks}

    devs = [bench_device(info, clouds, radii, refs, caps, args.repeats, guard) for info in infos]

    o3d_res = {}
    if o3d is not None:
        for k in ks:
            label = f"Open3D ~{k}"
            o3d_res[k] = guard.block(label, lambda k=k: bench_open3d(o3d, clouds, radii[k],
                                                                    args.repeats))
            o3d_res[k]["threads"] = guard.gains(label)
    orientation = guard.block("orientation", lambda: bench_orientation(
        o3d, args.orient_points, infos[0].index))

    report(args, env, guard, ks, refs, o3d_res, orientation, devs)


def report(args, env, guard, ks, refs, o3d_res, orientation, devs):
    """Print the tables and write JSON (one file per device kind) and bench.md."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    threads = guard.checks
    text = [summary_text(env, args, threads), orientation_text(orientation)]
    if guard.busy():
        text.append(f"WARNING: cores were busy around: {', '.join(guard.busy())}; their figures "
                    "are pessimistic and ratios involving them are unreliable: rerun on a quiet "
                    "machine")
    md = ["# clcurv benchmark", "", "```", *text, "```"]
    kinds_seen = {}
    for dev in devs:
        rat = {k: ratios(args.n, dev["k"][k], refs[k], o3d_res.get(k)) for k in ks}
        d = dev["device"]
        title = f"[{d['index']}] {d['name']} — {d['platform']}, driver {d['driver']}, {d['version']}"
        header = (f"n = {args.n:,}", [f"~{k} nbrs" for k in ks])
        rows = device_rows(args.n, dev, refs, o3d_res, rat, ks)
        tgt = target_lines(targets(dev, rat, orientation))
        text += ["", title, render_text(header, rows), "", "targets", render_targets(tgt)]
        md += ["", f"## {title}", "", render_markdown(header, rows), "",
               "| target | value | threshold | result |", "|---|---:|---|---|"]
        md += [md_row(list(t)) for t in tgt]
        kind = d["kind"]
        kinds_seen[kind] = kinds_seen.get(kind, 0) + 1
        suffix = kind if kinds_seen[kind] == 1 else f"{kind}{kinds_seen[kind]}"
        write_json(RESULTS / f"bench-{suffix}.json", {
            "args": vars(args), "env": env, "threads": threads, "device": dev,
            "reference": {k: {x: v for x, v in refs[k].items() if not x.startswith("result")}
                          for k in ks},
            "open3d": o3d_res, "orientation": orientation, "ratios": rat,
            "targets": [dict(zip(("name", "value", "threshold", "result"), t)) for t in tgt]})
    print("\n".join(text))
    (RESULTS / "bench.md").write_text("\n".join(md) + "\n")
    log(f"wrote {RESULTS}/bench-*.json and bench.md")


def write_json(path, obj):
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        raise TypeError(type(o).__name__)
    path.write_text(json.dumps(obj, indent=1, default=default, allow_nan=True) + "\n")


if __name__ == "__main__":
    main()
