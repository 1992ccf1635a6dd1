"""Benchmark of clcurv.features, several radii in one walk and the k-NN radius (issue 14).

    python -m bench.features            # 1M points, ~30 neighbours
    python -m bench.features --quick    # 100k points, fewer repeats

On a random-order unit-sphere sample (bench.harness.make_clouds) at the radius for ~30
neighbours, end to end from the numpy array in to the arrays out, every ratio from
interleaved runs (bench.harness.paired_rounds: a, b, a, b, ...; best of each, and the
per-round ratios beside), so that a drift of the shared machine's speed hits both sides.
21 rounds (REPEATS): with 7, one session's three runs on the Zen 3 EPYC gave 0.53-0.61x for
the three radii and 1.02-1.21x for the features, as the machine's slow phases, tens of
seconds long, took some runs' every round; the pairs' 21 rounds add about half a minute.

- the feature set (DEFAULT_FEATURES, jakteristics' list) vs clcurv.normals(orient=None):
  target <= 1.2x;
- three radii (r / sqrt 2, r, r sqrt 2) in one walk vs three separate calls: target <= 0.6x;
- the k-NN radius pass (K = 30, clcurv.ops.knn_radius.knn_radii, binning included) vs one
  moments pass (curvature(method='variation', orient=None), binning included): target <=
  1.5x;
- jakteristics.compute_features (same features, 2 threads, k-d tree included) and PDAL's
  filters.covariancefeatures (bench.pdal_cli: a pdal command, $CLCURV_PDAL or on the PATH)
  when they are installed, on the same cloud in the same run.

Every call's peak RSS is taken in a fresh process (the high-water mark reset just before the
call: :func:`_peak_rss`). Writes bench/results/features.md and features.json; the free-cores
check of bench.contention runs before and after.
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

import clcurv
from clcurv.ops.knn_radius import knn_radii

from .contention import describe_threads, thread_check
from .harness import (REPO, environment, log, make_clouds, mpts, paired_rounds, radius_for,
                      run_python, timed)
from .pdal_cli import pdal_command, pdal_version, time_covariance_features

TARGETS = {"features_vs_normals": 1.2, "three_radii_vs_separate": 0.6,
           "three_radii_same_cloud": None, "knn_vs_moments": 1.5}
JAK_NAMES = ["eigenvalue_sum", "omnivariance", "eigenentropy", "anisotropy", "planarity",
             "linearity", "PCA1", "PCA2", "surface_variation", "sphericity", "verticality",
             "nx", "ny", "nz", "number_of_neighbors"]


def _bench_pdal(pts, r):
    """PDAL's filters.covariancefeatures (bench.pdal_cli: the pdal command, Raw mode, the
    10 features of PDAL_FEATURES, radius r, 2 threads, KD-tree included): the pipeline's
    time less the time to read its LAS file, one run each."""
    cmd, why = pdal_command()
    if cmd is None:
        return {"skipped": why}
    try:
        out = time_covariance_features(cmd, pts, r, threads=2)
    except Exception as exc:  # noqa: BLE001 - an optional peer, reported in the table
        return {"skipped": f"{type(exc).__name__}: {exc}"}
    out["version"] = pdal_version(cmd)
    return out


#: One call in a fresh process: its programs built and the context made on a small cloud,
#: then the VmHWM high-water mark reset (/proc/self/clear_refs) just before the call on the
#: n-point sphere of make_clouds (bench.measure.peak_rss does the same for the lead table).
_PEAK_RSS = """
import json, math, sys, time
import clcurv
from clcurv.ops.knn_radius import knn_radii
from bench.harness import make_clouds, radius_for
n, what = int(sys.argv[1]), sys.argv[2]
def status_mb(key):
    with open("/proc/self/status") as f:
        return int(next(ln for ln in f if ln.startswith(key + ":")).split()[1]) / 1024
def call(pts, r):
    radii = [r / math.sqrt(2), r, r * math.sqrt(2)]
    return {"features": lambda: clcurv.features(pts, r),
            "normals": lambda: clcurv.normals(pts, r, orient=None),
            "three_radii": lambda: clcurv.features(pts, radii),
            "knn": lambda: knn_radii(pts, 30),
            "variation": lambda: clcurv.curvature(pts, r, method="variation",
                                                  orient=None)}[what]
small, _ = make_clouds(20_000)
call(small, radius_for(30, 20_000))()
pts, _ = make_clouds(n)
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
base = status_mb("VmRSS")
t0 = time.perf_counter()
out = call(pts, radius_for(30, n))()
print(json.dumps({"seconds": time.perf_counter() - t0, "base_mb": base,
                  "peak_mb": status_mb("VmHWM")}))
"""

#: the calls of each row of the table, measured (a) and baseline (b), for _PEAK_RSS
RSS_CALLS = {"features_vs_normals": ("features", "normals"),
             "three_radii_vs_separate": ("three_radii", "features"),
             "knn_vs_moments": ("knn", "variation")}


def _peak_rss(n, what):
    """Peak RSS of one call (``what``, a key of _PEAK_RSS's table) on the n-point sphere in
    a fresh process, MB: {"peak_mb", "base_mb", "delta_mb"} or {"error"}."""
    try:
        out = json.loads(run_python(_PEAK_RSS, n, what).strip().splitlines()[-1])
    except Exception as exc:  # noqa: BLE001 - reported in the table, the bench goes on
        return {"error": str(exc)}
    out["delta_mb"] = out["peak_mb"] - out["base_mb"]
    return out


def _stages(pts, r, repeats=3):
    """Stage times (s, best of ``repeats``) of features and normals calls on one DeviceCloud
    at r: what the two share (binning, upload, cell ranges) and what each adds (kernel,
    download)."""
    cloud = clcurv.DeviceCloud(pts, r)
    out = {"binning": sum(cloud.timings[k] for k in ("binning", "upload", "cell_ranges"))}
    for _ in range(repeats):
        got = {}
        clcurv.features(cloud, r)
        got.update(features_kernel=cloud.timings["kernel_features"],
                   features_download=cloud.timings["download"])
        clcurv.normals(cloud, r, orient=None)
        got.update(normals_kernel=cloud.timings["kernel_moments"],
                   normals_download=cloud.timings["download"])
        out.update({k: min(v, out.get(k, v)) for k, v in got.items()})
    return out


def run(n, repeats):
    env = environment()
    before = thread_check()
    log(describe_threads(before, "before"))
    pts, _ = make_clouds(n)
    r = radius_for(30, n)
    radii = [r / math.sqrt(2), r, r * math.sqrt(2)]
    dev = clcurv.get_device()
    log(f"{n} points, r = {r:.5g} (~30 neighbours), device {dev.info.name}")
    # warm-up: builds every program once
    clcurv.features(pts[:20000], r * math.sqrt(n / 20000))
    clcurv.features(pts[:20000], [x * math.sqrt(n / 20000) for x in radii])
    knn_radii(pts[:20000], 30)
    clcurv.normals(pts[:20000], r * math.sqrt(n / 20000), orient=None)
    clcurv.curvature(pts[:20000], r * math.sqrt(n / 20000), method="variation", orient=None)

    rows = {}
    rows["features_vs_normals"] = paired_rounds(
        lambda: clcurv.features(pts, r), lambda: clcurv.normals(pts, r, orient=None), repeats)
    rows["three_radii_vs_separate"] = paired_rounds(
        lambda: clcurv.features(pts, radii), lambda: [clcurv.features(pts, x) for x in radii],
        repeats)
    cloud = clcurv.DeviceCloud(pts, max(radii))
    rows["three_radii_same_cloud"] = paired_rounds(
        lambda: clcurv.features(cloud, radii), lambda: [clcurv.features(cloud, x) for x in radii],
        repeats)
    rows["knn_vs_moments"] = paired_rounds(
        lambda: knn_radii(pts, 30),
        lambda: clcurv.curvature(pts, r, method="variation", orient=None), repeats)
    stages = knn_radii(pts, 30)
    split = _stages(pts, r)
    f = clcurv.features(pts, r)
    mean_count = float(np.mean(f.count))

    peers = {}
    try:
        import jakteristics as jak
        s, J = timed(lambda: jak.compute_features(pts, r, feature_names=JAK_NAMES,
                                                  num_threads=2))
        peers["jakteristics"] = {"seconds": s, "mean_count": float(np.mean(J[:, -1]))}
    except Exception as exc:  # noqa: BLE001 - optional peer
        peers["jakteristics"] = {"skipped": f"{type(exc).__name__}: {exc}"}
    peers["pdal"] = _bench_pdal(pts, r)
    rss = {what: _peak_rss(n, what) for what in sorted({w for p in RSS_CALLS.values()
                                                         for w in p})}
    after = thread_check()
    log(describe_threads(after, "after"))
    out = {"points": n, "radius": r, "radii": radii, "mean_count": mean_count,
           "repeats": repeats, "device": dev.info.name, "environment": env,
           "threads_before": before, "threads_after": after, "peers": peers,
           "knn_levels": stages.levels, "knn_stages": stages.timings, "stages": split,
           "peak_rss": rss,
           "rows": {k: _row(a, b, TARGETS[k]) for k, (a, b) in rows.items()}}
    return out


def _row(a, b, target):
    """One ratio's record from the interleaved rounds' times a, b (s): the headline is the
    best of each side (``paired``), ``met`` its test against the target; the per-round ratios
    a_i / b_i (a and b of the same seconds) show how far the machine's noise moves it."""
    best_a, best_b = min(a), min(b)
    rounds = [x / y for x, y in zip(a, b)]
    return {"a_seconds": best_a, "b_seconds": best_b, "ratio": best_a / best_b,
            "target": target, "met": None if target is None else best_a / best_b <= target,
            "a_rounds": list(a), "b_rounds": list(b), "round_ratios": rounds,
            "round_median": float(np.median(rounds)),
            "rounds_met": None if target is None else sum(x <= target for x in rounds)}


def report(res):
    n = res["points"]
    names = {"features_vs_normals": ("features(P, r) (12 features)", "normals(P, r, orient=None)"),
             "three_radii_vs_separate": ("features(P, [r1, r2, r3])", "3 x features(P, ri)"),
             "three_radii_same_cloud": ("features(C, [r1, r2, r3])",
                                        "3 x features(C, ri), C = DeviceCloud(P, r3)"),
             "knn_vs_moments": ("knn_radii(P, 30)", "curvature(P, r, 'variation', orient=None)")}
    lines = [f"# clcurv.features bench ({time.strftime('%Y-%m-%d')})", "",
             f"{n:,} points on a unit sphere in random order, r = {res['radius']:.5g} "
             f"(mean {res['mean_count']:.1f} neighbours), device {res['device']}; best of "
             f"{res['repeats']} interleaved runs of each pair (a, b, a, b, ...), end to end "
             "(numpy in, numpy out, binning included); a / b and met are of the best of each "
             "side, and the per-round ratios of the a and b run in the same round show the "
             "machine's noise.", "",
             "| measured (a) | against (b) | a | b | a / b | target | met | a_i / b_i per round: "
             "median (range), rounds met | peak RSS a, b |",
             "|---|---|---:|---:|---:|---:|---|---|---|"]
    for k, row in res["rows"].items():
        a, b = names[k]
        target = "" if row["target"] is None else f"<= {row['target']}"
        met = "" if row["met"] is None else ("yes" if row["met"] else "NO")
        rss = ", ".join(_rss_text(res.get("peak_rss", {}).get(w)) for w in RSS_CALLS.get(k, ()))
        lines.append(f"| `{a}` | `{b}` | {row['a_seconds'] * 1e3:.0f} ms | "
                     f"{row['b_seconds'] * 1e3:.0f} ms | {row['ratio']:.2f} | {target} | {met} "
                     f"| {_rounds_text(row)} | {rss} |")
    lines += ["", "Peak RSS: one call in a fresh process (programs built and context made "
              "beforehand), the high-water mark reset just before it; in parentheses what "
              "the call added to the RSS before it (interpreter, context, the input cloud); for "
              "the three separate calls, one call at r."]
    sp = {k: v * 1e3 for k, v in res["stages"].items()}
    lines += ["", f"stages (best of 3) on a DeviceCloud at r: binning, upload and cell ranges "
              f"{sp['binning']:.0f} ms (both); features kernel {sp['features_kernel']:.0f} ms, "
              f"download {sp['features_download']:.0f} ms; normals kernel "
              f"{sp['normals_kernel']:.0f} ms, download {sp['normals_download']:.0f} ms"]
    st = res["knn_stages"]
    binnings = ("one binning: a tight cloud, clcurv.ops.knn_radius._tight"
                if len(res["knn_levels"]) == 1 else
                "a level binned ahead on a worker thread where the cloud is not tight")
    lines += [f"k-NN radius cells binned: {', '.join(f'{c:.4g}' for c in res['knn_levels'])}"
              f"; stages of one run: first cell {st['first_cell'] * 1e3:.0f} ms, binning "
              f"{st['binning'] * 1e3:.0f} ms ({binnings}), k-th distance "
              f"{st['kth'] * 1e3:.0f} ms",
              "", "| peer, same cloud, same run | time | M pts/s |", "|---|---:|---:|"]
    feat = res["rows"]["features_vs_normals"]["a_seconds"]
    lines.append(f"| clcurv.features (12 features) | {feat:.2f} s | {mpts(n, feat):.2f} |")
    for name, p in res["peers"].items():
        if "seconds" in p:
            what = (f"PDAL {p['version']} filters.covariancefeatures, Raw mode (2 threads, "
                    f"tree included; pipeline {p['pipeline_seconds']:.2f} s less reading the "
                    f"LAS file {p['read_seconds']:.2f} s)" if name == "pdal" else
                    f"{name} (2 threads, tree included)")
            lines.append(f"| {what} | {p['seconds']:.2f} s | {mpts(n, p['seconds']):.2f} |")
        else:
            lines.append(f"| {name} | skipped: {p['skipped']} | |")
    lines += ["", describe_threads(res["threads_before"], "cores before"),
              describe_threads(res["threads_after"], "cores after"), ""]
    return "\n".join(lines)


def _rounds_text(row):
    rr = row.get("round_ratios")
    if not rr:
        return ""
    met = "" if row.get("rounds_met") is None else f", {row['rounds_met']} of {len(rr)}"
    return f"{row['round_median']:.3f} ({min(rr):.3f}-{max(rr):.3f}){met}"


def _rss_text(r):
    if not r:
        return ""
    if "error" in r:
        return f"failed ({r['error']})"
    return f"{r['peak_mb']:.0f} MB (+{r['delta_mb']:.0f})"


#: Interleaved rounds of each pair in the reference run (the module's docstring says why).
REPEATS = 21


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="100k points, 3 repeats")
    ap.add_argument("--points", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args(argv)
    n = args.points or (100_000 if args.quick else 1_000_000)
    res = run(n, args.repeats or (3 if args.quick else REPEATS))
    md = report(res)
    print(md)
    if not args.quick and args.points is None:        # the reference run only
        out = REPO / "bench" / "results"
        (out / "features.md").write_text(md)
        (out / "features.json").write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
