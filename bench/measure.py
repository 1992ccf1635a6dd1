"""The clcurv measurements on one OpenCL device: stages, end to end per registered operator,
each operator kernel alone (``cloud.timings`` of :func:`clcurv.ops.driver.run_kernel`), the MLS1
scale space and the pipeline; then the accuracy checks of those runs."""
from __future__ import annotations

import json
import math

import clcurv
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import run_kernel
from clcurv.ops.registry import OPERATORS, PCA, tuning

from .accuracy import check_against_reference, check_ops, check_scale_space
from .harness import cap_interior, log, paired, run_python, timed, timeit
from .ops import (CALL_ROWS, HEADLINE, NORMAL_OPS, POINT_OPS, SIGN_OPS, SS_ITERATIONS,
                  VARIANTS, call, orient_none)

PAIRED_REPEATS = 5        # interleaved (operator, clcurv.normals) pairs for the time ratios
BUILD_PCA, KERNEL_PCA = f"build_{PCA.name}", f"kernel_{PCA.name}"   # cloud.timings keys
#: the stages of one moments run (DeviceCloud, then run_kernel(PCA)), in order
STAGES = ("binning", "upload", "build", "cell_ranges", BUILD_PCA, KERNEL_PCA, "download")

_COLD_BUILD = r"""
import sys, time, clcurv
from clcurv.ops.registry import PCA
from clcurv.runtime.program import build, precision_defines
dev = clcurv.get_device(int(sys.argv[1]))
d = precision_defines(dev, "float")
t0 = time.perf_counter(); build(dev, "grid.cl", d); t1 = time.perf_counter()
build(dev, PCA.file, dict(d, **PCA.build_defines(), DENSITY=0, GAUSSIAN=0, REF_NORMALS=0))
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def cold_build(index):
    """Build times of grid.cl and moments.cl in a fresh process with PoCL's cache disabled."""
    try:
        grid, mom = map(float, run_python(_COLD_BUILD, index,
                                          env={"POCL_KERNEL_CACHE": "0"}).split())
        return {"build": grid, BUILD_PCA: mom}
    except Exception as exc:  # noqa: BLE001
        return {"error": str(exc)}


def split_once(pts, r, index, refine=True):
    """One DeviceCloud + moments kernel run; its stage timings (s)."""
    cloud = DeviceCloud(pts, r, device=index)
    run_kernel(PCA, cloud, r, defines=None if refine else {"REFINE_L0": 0})
    return dict(cloud.timings)


def bench_split(pts, r, index, repeats):
    """Stages, min of warm runs each; and the kernel time of the one-pass (normals) program."""
    warm = {k: math.inf for k in STAGES}
    for _ in range(1 + repeats):  # the first one is a warm-up
        t = split_once(pts, r, index)
        warm = {k: min(warm[k], t[k]) for k in STAGES}
    single = min(split_once(pts, r, index, refine=False)[KERNEL_PCA]
                 for _ in range(1 + repeats))  # the first one builds the REFINE_L0=0 program
    return {"warm": warm, "kernel_single_pass_s": single}


def bench_calls(clouds, nrm, r, index, repeats):
    """The lead table: every row of ops.CALL_ROWS called with each of ops.VARIANTS (the
    default arguments, orient=None, the exact normals), end to end on the random-order cloud,
    min of ``repeats`` runs after a warm-up; and curvature(HEADLINE) with default arguments
    on the spatially sorted copy.

    Returns ({row: {variant: seconds}}, {"<HEADLINE>_sorted_input": seconds}) and the
    warm-up results of the orient=None runs of HEADLINE and normals (the accuracy check)."""
    pts = clouds["random"]
    seconds, results = {}, {}
    for row in CALL_ROWS:
        seconds[row] = {}
        for variant in VARIANTS:
            fn = call(row, variant, pts, r, nrm, index)
            res = fn()  # warm-up (builds the programs)
            if variant == "orient_none" and row in (HEADLINE, "normals"):
                results[row] = res
            seconds[row][variant] = timeit(fn, repeats, warmup=0)
    extra = {f"{HEADLINE}_sorted_input": timeit(call(HEADLINE, "default", clouds["sorted"], r,
                                                     device=index), repeats)}
    return (seconds, extra), results


_PEAK_RSS = r"""
import json, sys, time
import numpy as np
from clcurv import shapes
from bench.harness import radius_for
from bench.ops import call
n, k, index, row, variant = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
def status_mb(key):
    with open("/proc/self/status") as f:
        return int(next(ln for ln in f if ln.startswith(key + ":")).split()[1]) / 1024
small = shapes.sphere(20_000, 1.0, seed=3)["points"]   # the programs built, the context made
call(row, variant, small, radius_for(k, 20_000), small, index)()
pts = shapes.sphere(n, 1.0)["points"]
nrm = pts / np.linalg.norm(pts, axis=1)[:, None] if variant == "normals" else None
with open("/proc/self/clear_refs", "w") as f:       # the high-water mark := the current RSS
    f.write("5")
base = status_mb("VmRSS")
t0 = time.perf_counter()
call(row, variant, pts, radius_for(k, n), nrm, index)()
print(json.dumps({"seconds": time.perf_counter() - t0, "base_mb": base,
                  "peak_mb": status_mb("VmHWM")}))
"""


def peak_rss(n, k, index, row, variant="default"):
    """Peak RSS of one call in a fresh process (Linux): the high-water mark VmHWM, reset
    (/proc/self/clear_refs) just before the call, read after it; and the RSS before the call
    (the interpreter, the OpenCL context and programs from a call on a 20k-point sphere, the
    n-point input cloud): the call's own peak is the difference."""
    try:
        out = json.loads(run_python(_PEAK_RSS, n, k, index, row, variant).strip().splitlines()[-1])
    except Exception as exc:  # noqa: BLE001 - reported in the table, the bench goes on
        return {"error": str(exc)}
    out["delta_mb"] = out["peak_mb"] - out["base_mb"]
    return out


def bench_peak_rss(col, index, variants=("default",)):
    """Peak RSS (:func:`peak_rss`) of every lead-table row, one child process per call."""
    return {row: {v: peak_rss(col["n"], col["k"], index, row, v) for v in variants}
            for row in CALL_ROWS}


def bench_ops(pts, nrm, r, index, repeats, cap):
    """The operators whose kernel reads normals, with the exact normals (the operator alone)
    and, for those that only take their sign, with orient=None (their own PCA frame), end to
    end; each kernel alone on one DeviceCloud (``cloud.timings``). Returns (seconds, kernel
    and upload seconds, cap slices of the results)."""
    seconds, kept = {}, {}
    normals = lambda: clcurv.normals(pts, r, orient=None, device=index)
    normals()
    calls = {m: (lambda m=m: clcurv.curvature(pts, r, method=m, normals=nrm, device=index))
             for m in NORMAL_OPS}
    calls.update({orient_none(m): (lambda m=m: clcurv.curvature(pts, r, method=m, orient=None,
                                                                device=index))
                  for m in SIGN_OPS})
    for name, fn in calls.items():
        if name in NORMAL_OPS:
            res = fn()  # warm-up (builds the program)
            kept[name] = {a: getattr(res, a)[cap] for a in ("count", "status", "k1", "k2")}
        # interleaved with clcurv.normals, for the time ratio (PAIRED_REPEATS pairs)
        seconds[name], seconds[f"normals_paired_{name}"] = paired(fn, normals,
                                                                  max(repeats, PAIRED_REPEATS))
    cloud = DeviceCloud(pts, r, device=index)
    runs = {m: (OPERATORS[m].kernel, nrm) for m in NORMAL_OPS}
    runs.update({orient_none(m): (OPERATORS[m].kernel, None) for m in SIGN_OPS})
    kernel, upload = {}, {}
    for name, (spec, given) in runs.items():
        best, up = math.inf, math.inf
        for i in range(1 + repeats):
            run_kernel(spec, cloud, r, normals=given)
            if i:
                best = min(best, cloud.timings[f"kernel_{spec.name}"])
                up = min(up, cloud.timings["upload_normals"])
        kernel[name], upload[name] = best, up
    return seconds, {"kernel": kernel, "upload_normals": upload}, kept


def bench_scale_space(pts, nrm, r, index, repeats, cap, iterations=SS_ITERATIONS):
    """MLS1 scale space: 1 iteration end to end; ``iterations`` iterations end to end with
    their stats (of the fastest run). Also the displacement after 2 iterations on the cap
    (for the check). The pipeline curvature(mls2, scale_space=iterations) is a row of
    :func:`bench_calls`."""
    ss = clcurv.scale_space
    out = {"iterations": iterations,
           "one_iteration_s": timeit(lambda: ss(pts, r, 1, device=index), repeats)}
    best, stats = math.inf, None
    for i in range(1 + repeats):
        s, (_, st) = timed(lambda: ss(pts, r, iterations, device=index, return_stats=True))
        if i and s < best:
            best, stats = s, st
    out.update(e2e_s=best, rebins=stats["rebins"], binning_s=stats["binning"],
               steps_s=stats["steps"],
               per_iteration_s=(stats["binning"] + stats["steps"]) / iterations)
    disp2 = ss(pts, r, 2, device=index)[cap] - pts[cap]
    return out, disp2


def clcurv_label(index, cid):
    return f"clcurv device {index} {cid}"


def device_record(info):
    return {"index": info.index, "name": info.name, "platform": info.platform, "kind": info.kind,
            "driver": info.driver, "version": info.version, "compute_units": info.compute_units,
            "tuning": tuning(clcurv.get_device(info.index))}


def bench_device(info, cols, data, refs, repeats, guard, rss_min_points=1_000_000):
    """All clcurv measurements on one device, per column (size, neighbour count); the peak
    RSS of the lead table's default calls for the columns of at least ``rss_min_points``
    points (one child process per call, outside the timed blocks)."""
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
            log(f"  {cid}: stages")
            split = bench_split(pts, r, info.index, repeats)
            log(f"  {cid}: public calls (default arguments, orient=None, normals=)")
            seconds, results = bench_calls(d, nrm, r, info.index, repeats)
            log(f"  {cid}: {', '.join(NORMAL_OPS)}")
            op_s, kern, kept = bench_ops(pts, nrm, r, info.index, repeats, cap)
            log(f"  {cid}: scale space, pipeline")
            ss, disp2 = bench_scale_space(pts, nrm, r, info.index, repeats, cap)
            return split, seconds, results, op_s, kern, kept, ss, disp2

        split, seconds, results, op_s, kern, kept, ss, disp2 = guard.block(
            clcurv_label(info.index, cid), measure)
        calls, extra = seconds
        seconds = {**extra, "normals": calls["normals"]["orient_none"],
                   **{m: calls[m]["orient_none"] for m in POINT_OPS}}
        ss["pipeline_s"] = calls["pipeline"]["normals"]
        rss = None
        if col["n"] >= rss_min_points:
            log(f"  {cid}: peak RSS of the default calls (a child process each)")
            rss = bench_peak_rss(col, info.index)
        ref = refs[cid]
        check = check_against_reference(results, ref["result"], cap, cap_interior(pts, cap, r),
                                        ref["result_f32_input"])
        out["k"][cid] = {"n": col["n"], "neighbours": col["k"], "radius": r,
                         "calls_s": calls, "peak_rss": rss,
                         "e2e_s": {**seconds, **op_s}, "split": split, "ops_kernel": kern,
                         "scale_space": ss, "check": check, "check_ops": check_ops(kept, ref),
                         "check_scale_space": check_scale_space(disp2, ref, pts, cap, r),
                         "threads": guard.gains(clcurv_label(info.index, cid)),
                         "mean_count": float(results[HEADLINE].count.mean())}
    return out
