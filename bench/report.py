"""The bench's results: ratios, the targets (bench.targets) evaluated, the table rows of
each device, their text and markdown renderings, bench/results/bench.md and the JSON."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from clcurv.ops.registry import OPERATORS

from .accuracy import SS_HOPS, tolerance
from .contention import describe_threads
from .harness import log, mpts
from .measure import BUILD_PCA, KERNEL_PCA, PAIRED_REPEATS, STAGES
from .ops import (CALL_ROWS, HEADLINE, NORMAL_OPS, PAIRED, POINT_OPS, SIGNED_NORMAL_OPS,
                  SS_ITERATIONS, UNSIGNED_NORMAL_OPS, base, call_text,
                  default_orientation, label)
from .peers import JAK_FEATURES, ORIENT_K, VARIATION_PAIRS, ref_extrapolated
from .targets import (AGREE_MIN, BINNING_OVER_KERNEL_MAX, COS_TOL, COV_VS_NORMALS,
                      DEFAULT_VARIATION_VS_OPEN3D, KERNEL_MPTS_AT_30, MLS2_VS_NORMALS,
                      MLS2_VS_REFERENCE, ORIENT_MPTS, ORIENT_VS_OPEN3D, PIPELINE_DEFAULT_MAX_S,
                      PIPELINE_MAX_S, SS_TOL, SS_VS_OPEN3D, THREADS_MIN_GAIN, VAR_MEDIAN_TOL,
                      VS_REFERENCE)

RESULTS = Path(__file__).resolve().parent / "results"


# ----------------------------------------------------------------------------- ratios, targets
def ratios(n, dev_k, ref, o3d_k, jak_k, device=None):
    """Throughputs and ratios of one device (index ``device``) in one column (None when not
    measured)."""
    e = dev_k["e2e_s"]
    e2e = dev_k["calls_s"][HEADLINE]["default"]     # curvature(method=HEADLINE), defaults
    warm = dev_k["split"]["warm"]
    o3d_normals = o3d_k["sorted"]["normals_s"] if o3d_k else None
    ss = dev_k["scale_space"]
    pair = (o3d_k or {}).get("paired")
    pair = pair if pair and pair["device"] == device else None
    out = {"e2e_variation_mpts": mpts(n, e2e),
           # the same two calls interleaved (peers.bench_variation_pairs): the target's ratio
           "vs_open3d_paired": pair["open3d_s"] / pair["clcurv_s"] if pair else None,
           "kernel_mpts": mpts(n, warm[KERNEL_PCA]),
           "vs_open3d_normals_sorted": o3d_normals / e2e if o3d_normals else None,
           "vs_reference": ref["seconds"] / ref["points"] * n / e2e,
           "binning_over_kernel": warm["binning"] / warm[KERNEL_PCA],
           "vs_jakteristics_sorted": jak_k["sorted"]["seconds"] / e2e if jak_k else None,
           "op_vs_reference": {k: ref_extrapolated(ref, base(k), n) / e[k] for k in PAIRED},
           # against clcurv.normals runs interleaved with the operator's (harness.paired)
           "op_over_normals": {k: e[k] / e[f"normals_paired_{k}"] for k in PAIRED}}
    per_it = ss["per_iteration_s"]
    out["ss_iteration_vs_reference"] = ref_extrapolated(ref, "scale_space_iteration", n) / per_it
    out["ss_iteration_vs_open3d"] = (o3d_normals / per_it) if o3d_normals else None
    out["ss_one_iteration_e2e_vs_open3d"] = ((o3d_normals / ss["one_iteration_s"])
                                             if o3d_normals else None)
    return out


def target_columns(cols):
    """The columns the targets are evaluated at: those of the largest size."""
    top = max(c["n"] for c in cols)
    return [c for c in cols if c["n"] == top]


def at_least(name, v, thr, unit="x"):
    return name, v, f">= {thr:g}{unit}", None if v is None else v >= thr


def at_most(name, v, thr, unit="x"):
    return name, v, f"<= {thr:g}{unit}", None if v is None else v <= thr


def evaluate_targets(dev, rat, orientation, cols):
    """(name, value, threshold, pass) rows; pass is None when the value was not measured."""
    tcols = [c["id"] for c in target_columns(cols)]
    c30 = min(tcols, key=lambda c: abs(dev["k"][c]["neighbours"] - 30))
    v = dev["k"][c30]["calls_s"]["pipeline"]["default"]
    rows = [at_most(f"{call_text('pipeline')} e2e, default arguments, seconds, {c30}", v,
                    PIPELINE_DEFAULT_MAX_S, " s")]
    for cid in tcols:               # interleaved pairs where measured, else the two blocks
        paired = rat[cid]["vs_open3d_paired"]
        how = "interleaved pairs" if paired is not None else "separate blocks"
        rows.append(at_least(f"{call_text(HEADLINE)} e2e, default arguments / Open3D "
                             f"estimate_normals (sorted), {how}, {cid}",
                             paired if paired is not None else
                             rat[cid]["vs_open3d_normals_sorted"], DEFAULT_VARIATION_VS_OPEN3D))
    top = max(orientation["sizes"])
    o = orientation["sizes"][top]
    rows.append(at_least(f"orientation alone (flip_on_device) M pts/s, {top:,} pts", o["mpts"],
                         ORIENT_MPTS, ""))
    o = next((x for x in orientation["sizes"].values() if "open3d_s" in x), None)
    rows.append(at_least(
        f"orientation alone / Open3D orient_normals_consistent_tangent_plane({ORIENT_K})"
        + (f", {o['n']:,} pts" if o else ""),
        o["open3d_s"] / o["seconds"] if o else None, ORIENT_VS_OPEN3D))
    rows.append(at_least(f"kernel-only M pts/s (curvature kernel, λ0 refined), {c30}",
                         rat[c30]["kernel_mpts"], KERNEL_MPTS_AT_30, ""))
    rows += [at_least(f"e2e variation (defaults) / NumPy reference, {cid}", rat[cid]["vs_reference"],
                      VS_REFERENCE) for cid in tcols]
    rows += [at_most(f"binning / kernel time, {cid}", rat[cid]["binning_over_kernel"],
                     BINNING_OVER_KERNEL_MAX, "") for cid in tcols]
    for cid in tcols:
        ra, K = rat[cid], dev["k"][cid]
        for m in SIGNED_NORMAL_OPS:
            M = m.upper()
            rows.append(at_least(f"{M} e2e (normals=) / NumPy reference {M}, {cid}",
                                 ra["op_vs_reference"][m], MLS2_VS_REFERENCE))
            rows.append(at_most(f"{M} e2e (normals=) time / clcurv.normals(orient=None) time, "
                                f"{cid}", ra["op_over_normals"][m], MLS2_VS_NORMALS))
        rows += [at_most(f"{m} e2e (normals=) time / clcurv.normals time, {cid}",
                         ra["op_over_normals"][m], COV_VS_NORMALS) for m in UNSIGNED_NORMAL_OPS]
        v = K["scale_space"]["pipeline_s"]
        rows.append((f"{call_text('pipeline', 'normals')} e2e, seconds, {cid}", v,
                     f"< {PIPELINE_MAX_S:g} s", v < PIPELINE_MAX_S))
        rows.append(at_least(f"scale-space iteration ((binning+steps)/{SS_ITERATIONS}) / Open3D "
                             f"estimate_normals (sorted), {cid}", ra["ss_iteration_vs_open3d"],
                             SS_VS_OPEN3D))
        rows.append(at_least(f"scale space, 1 iteration e2e / Open3D estimate_normals (sorted), "
                             f"{cid}", ra["ss_one_iteration_e2e_vs_open3d"], SS_VS_OPEN3D))
    for cid, d in dev["k"].items():
        rows.append((f"accuracy vs reference (counts, normals, variation), {cid}", None,
                     "see table", d["check"]["pass"]))
        rows.append((f"accuracy vs reference ({', '.join(UNSIGNED_NORMAL_OPS)} k1; "
                     f"{', '.join(m.upper() for m in SIGNED_NORMAL_OPS)} k1, k2), {cid}", None,
                     "see table", all(c["pass"] for c in d["check_ops"].values())))
        rows.append((f"accuracy vs reference (scale space, 2 iterations), {cid}", None,
                     "see table", d["check_scale_space"]["pass"]))
    return rows


# ----------------------------------------------------------------------------- table
def fmt(v, spec=".2f", unit=""):
    return "–" if v is None else f"{v:{spec}}{unit}"


def pass_fail(ok):
    return "n/a" if ok is None else "PASS" if ok else "FAIL"


def ms(s):
    return fmt(None if s is None else s * 1e3, ".1f")


def q3(e):
    """'median / p99.9 / max' of an error's quantiles."""
    return f"{e['median']:.1e} / {e['p999']:.1e} / {e['max']:.1e}"


def device_rows(dev, refs, o3d, jak, rat, cols):
    """Table rows (label, one cell per column) for one device."""
    K = dev["k"]
    ids = [c["id"] for c in cols]
    N = {c["id"]: c["n"] for c in cols}
    blank = [""] * len(ids)
    first_only = lambda s: [s] + [""] * (len(ids) - 1)

    def e2e(key):
        return [f"{mpts(N[c], K[c]['e2e_s'][key]):.2f} ({ms(K[c]['e2e_s'][key])})" for c in ids]

    rows = [("radius", [f"{K[c]['radius']:.5f}" for c in ids]),
            ("mean neighbour count, point included", [f"{K[c]['mean_count']:.1f}" for c in ids]),
            (f"{call_text(HEADLINE)} on the spatially sorted copy, M pts/s (ms)",
             e2e(f"{HEADLINE}_sorted_input"))]
    rows.append(("**end to end, interleaved with normals(P, r, orient=None) (the ratios)**",
                 ["M pts/s (ms)"] * len(ids)))
    rows += [(f"{call_text(base(k), 'orient_none' if k != base(k) else 'normals')}", e2e(k))
             for k in PAIRED]
    rows.append(("**stages, ms (min of warm runs)**", blank))
    rows += [(st, [ms(K[c]["split"]["warm"][st]) for c in ids]) for st in STAGES]
    first = dev["first_in_process"]
    rows.append((f"first run in process ({first['k']}): build + {BUILD_PCA} + kernel",
                 first_only(f"{ms(first['build'])} + {ms(first[BUILD_PCA])} + "
                            f"{ms(first[KERNEL_PCA])}")))
    cold = dev["cold_build_no_cache"]
    if "error" not in cold:
        rows.append((f"build + {BUILD_PCA} with PoCL's disk cache off",
                     first_only(f"{ms(cold['build'])} + {ms(cold[BUILD_PCA])}")))
    rows.append((f"host rest ≈ e2e {HEADLINE} orient=None − Σ warm stages (ms)",
                 [ms(K[c]["e2e_s"][HEADLINE] - sum(K[c]["split"]["warm"].values()))
                  for c in ids]))
    rows.append(("kernel-only M pts/s (λ0 refined, curvature / one pass, normals)",
                 [f"{rat[c]['kernel_mpts']:.2f} / "
                  f"{mpts(N[c], K[c]['split']['kernel_single_pass_s']):.2f}" for c in ids]))
    rows.append(("**kernel only (cloud.timings), ms (M pts/s)**", blank))
    for key in PAIRED:
        name = f"kernel_{OPERATORS[base(key)].kernel.name}"
        kern = {c: K[c]["ops_kernel"]["kernel"][key] for c in ids}
        rows.append((name if key == base(key) else f"{name}, no normals",
                     [f"{ms(kern[c])} ({mpts(N[c], kern[c]):.2f})" for c in ids]))
    rows.append((f"upload of the normals (ms), {' / '.join(NORMAL_OPS)}",
                 [" / ".join(ms(K[c]["ops_kernel"]["upload_normals"][m]) for m in NORMAL_OPS)
                  for c in ids]))
    rows += scale_space_rows(K, ids, N)
    rows += peer_rows(refs, o3d, jak, ids, N)
    rows += ratio_rows(rat, ids, jak)
    rows += accuracy_rows(K, ids)
    rows.append(("**cores free? 2-thread gain of a PoCL spin kernel, before / after**", blank))
    rows.append(("clcurv block", [K[c]["threads"] for c in ids]))
    for name, res in (("Open3D", o3d), ("jakteristics", jak)):
        if res:
            rows.append((f"{name} block", [res[c]["threads"] for c in ids]))
    return rows


def scale_space_rows(K, ids, N):
    S = {c: K[c]["scale_space"] for c in ids}
    rate = lambda c, key: f"{ms(S[c][key])} ({mpts(N[c], S[c][key]):.2f})"
    return [("**MLS1 scale space (clcurv.scale_space), ms**", [""] * len(ids)),
            ("1 iteration end to end (M pts/s)", [rate(c, "one_iteration_s") for c in ids]),
            (f"{SS_ITERATIONS} iterations end to end", [ms(S[c]["e2e_s"]) for c in ids]),
            ("  of which binning (rebins) / steps (return_stats)",
             [f"{ms(S[c]['binning_s'])} ({S[c]['rebins']}) / {ms(S[c]['steps_s'])}"
              for c in ids]),
            (f"per iteration, (binning + steps) / {SS_ITERATIONS} (M pts/s)",
             [rate(c, "per_iteration_s") for c in ids]),
            (f"pipeline {call_text('pipeline', 'normals')} e2e",
             [ms(S[c]["pipeline_s"]) for c in ids])]


def peer_rows(refs, o3d, jak, ids, N):
    rows = [("**peers, M pts/s**", [""] * len(ids)),
            ("NumPy reference (float64) on a cap of", [f"{refs[c]['points']:,} pts" for c in ids])]
    for op, what in (("moments", f"moments ({', '.join(POINT_OPS)}, normals)"),
                     *((m, m) for m in NORMAL_OPS),
                     ("scale_space_iteration", "MLS1 scale-space iteration")):
        rows.append((f"  reference {what}", [f"{refs[c]['op_mpts'][op]:.4f}" for c in ids]))
    if o3d:
        for op in ("normals", "covariances"):
            rows.append((f"Open3D estimate_{op}, sorted / random",
                         [f"{mpts(N[c], o3d[c]['sorted'][f'{op}_s']):.3f} / "
                          f"{mpts(N[c], o3d[c]['random'][f'{op}_s']):.3f}" for c in ids]))
    if jak:
        rows.append((f"jakteristics compute_features ({len(JAK_FEATURES)} features), sorted / "
                     "random", [f"{mpts(N[c], jak[c]['sorted']['seconds']):.3f} / "
                                f"{mpts(N[c], jak[c]['random']['seconds']):.3f}" for c in ids]))
        rows.append(("  jakteristics mean number_of_neighbors",
                     [f"{jak[c]['mean_count']:.1f}" for c in ids]))
    return rows


def ratio_rows(rat, ids, jak):
    col = lambda key, spec: [fmt(rat[c][key], spec, "x") for c in ids]
    rows = [("**ratios**", [""] * len(ids)),
            (f"e2e {call_text(HEADLINE)} / Open3D estimate_normals (sorted)",
             col("vs_open3d_normals_sorted", ".1f")),
            (f"the same, {VARIATION_PAIRS} interleaved pairs (min of each)",
             col("vs_open3d_paired", ".1f"))]
    if jak:
        rows.append((f"e2e {call_text(HEADLINE)} / jakteristics (sorted)",
                     col("vs_jakteristics_sorted", ".1f")))
    rows.append((f"e2e {call_text(HEADLINE)} / NumPy reference (extrapolated)",
                 col("vs_reference", ".0f")))
    rows += [(f"e2e {label(k)} / NumPy reference {base(k)} (extrapolated)",
              [fmt(rat[c]["op_vs_reference"][k], ".0f", "x") for c in ids]) for k in PAIRED]
    rows.append(("scale-space iteration / NumPy reference iteration",
                 col("ss_iteration_vs_reference", ".0f")))
    rows += [(f"time {label(k)} / time clcurv.normals",
              [fmt(rat[c]["op_over_normals"][k], ".2f", "x") for c in ids]) for k in PAIRED]
    rows.append(("scale-space iteration / Open3D estimate_normals (sorted)",
                 col("ss_iteration_vs_open3d", ".1f")))
    rows.append(("binning / kernel", [fmt(rat[c]["binning_over_kernel"], ".2f") for c in ids]))
    return rows


def accuracy_rows(K, ids):
    C = {c: K[c]["check"] for c in ids}
    O = {c: K[c]["check_ops"] for c in ids}
    compared = lambda ops: ("  points compared (equal counts, status ok), " + " / ".join(ops),
                            [" / ".join(f"{O[c][m]['compared']}" for m in ops)
                             + f" of {O[c][ops[0]]['of']}" for c in ids])
    rows = [("**accuracy vs reference on the cap**", [""] * len(ids)),
            (f"cap interior: counts equal to reference (>= {AGREE_MIN:.1%})",
             [f"{C[c]['interior_counts_agree']:.3%} of {C[c]['interior']} "
              f"{pass_fail(C[c]['counts_pass'])}" for c in ids]),
            ("cap points compared (equal counts, status ok)",
             [f"{C[c]['compared']} of {C[c]['of']}" for c in ids]),
            (f"normals 1−|cos| worst (curv / normals), tol {COS_TOL:g}",
             [f"{C[c]['curvature_cos_worst']:.1e} / {C[c]['normals_cos_worst']:.1e} "
              f"{pass_fail(C[c]['normals_pass'])}" for c in ids]),
            (f"variation rel. error median (p99.9), tol {VAR_MEDIAN_TOL:g}",
             [f"{C[c]['variation_rel_median']:.1e} ({C[c]['variation_rel_p999']:.1e}) "
              f"{pass_fail(C[c]['variation_pass'])}" for c in ids]),
            ("same vs reference on the float32 input (kernel arithmetic only)",
             [f"{C[c]['variation_rel_median_f32_input']:.1e} "
              f"({C[c]['variation_rel_p999_f32_input']:.1e})" for c in ids])]
    ops = UNSIGNED_NORMAL_OPS
    rows += [(f"{m} k1 rel. error median / p99.9 / max, tol p99.9 <= {tolerance(m):g}",
              [f"{q3(O[c][m]['k1'])} {pass_fail(O[c][m]['pass'])}" for c in ids]) for m in ops]
    rows.append((f"  same vs reference on the float32 input, {' / '.join(ops)} p99.9",
                 [" / ".join(f"{O[c][m]['f32_input']['k1']['p999']:.1e}" for m in ops)
                  for c in ids]))
    rows.append(compared(ops))
    for m in SIGNED_NORMAL_OPS:
        rows += [(f"{m} {k} |err|/max|k| median / p99.9 / max, tol p99.9 <= {tolerance(m):g}",
                  [f"{q3(O[c][m][k])} {pass_fail(O[c][m]['pass'])}" for c in ids])
                 for k in ("k1", "k2")]
        rows.append(("  same vs reference on the float32 input, k1 / k2 p99.9 (max)",
                     [" / ".join(f"{O[c][m]['f32_input'][k]['p999']:.1e} "
                                 f"({O[c][m]['f32_input'][k]['max']:.1e})" for k in ("k1", "k2"))
                      for c in ids]))
        rows.append(compared((m,)))
    SC = {c: K[c]["check_scale_space"] for c in ids}
    rows.append((f"scale space, 2 iterations: |d|/r median / p99.9 / max, tol p99.9 <= {SS_TOL:g}",
                 [f"{q3(SC[c]['err'])} {pass_fail(SC[c]['pass'])}" for c in ids]))
    rows.append(("  same vs reference on the float32 input (kernel arithmetic only)",
                 [q3(SC[c]["err_f32_input"]) for c in ids]))
    rows.append((f"  cap interior compared (balls of {SS_HOPS:g} r inside the cap)",
                 [f"{SC[c]['compared']} of {SC[c]['of']}" for c in ids]))
    return rows


# ----------------------------------------------------------------------------- lead tables
LEAD_HEADER = ["default orients", "defaults: M pts/s (ms)", "peak RSS MB (+rise)",
               "orient=None", "normals=exact"]


def lead_rows(K):
    """One column's lead table: every public call with its default arguments, then the same
    call with orient=None and with the exact normals; the default call's peak RSS."""
    n = K["n"]
    cell = lambda s: f"{mpts(n, s):.2f} ({ms(s)})"
    rows = []
    for row in CALL_ROWS:
        S = K["calls_s"][row]
        how = default_orientation(row)
        rss = (K.get("peak_rss") or {}).get(row, {}).get("default")
        if rss is None:
            mem = "–"
        elif "error" in rss:
            mem = "error"
        else:
            mem = f"{rss['peak_mb']:.0f} (+{rss['delta_mb']:.0f})"
        rows.append((call_text(row), ["MST on device" if how == "mst" else "none",
                                      cell(S["default"]), mem, cell(S["orient_none"]),
                                      cell(S["normals"])]))
    return rows


LEAD_NOTE = (
    "Public calls end to end (numpy in, numpy out; random point order), min of the repeats "
    "after a warm-up. 'defaults': the call as written (orient='auto': signed methods orient "
    "their normals on the device by Hoppe's MST, unsigned ones do not orient, so their "
    "orient=None call is the same call timed again); 'orient=None': no global orientation; "
    "'normals=exact': the sphere's exact normals given (the operators that read normals run "
    "without their PCA pass; the others orient to them). Peak RSS: a fresh process runs the "
    "default call once on the same cloud; its high-water mark (VmHWM, reset just before the "
    "call) during the call, and in brackets the rise over its RSS before the call (the "
    "interpreter, the OpenCL context and programs, the input cloud).")


def tuning_text(d):
    """'VW 8, masked sums, work-groups 128' (clcurv.ops.registry.tuning: chosen per device
    from queries)."""
    t = d.get("tuning")
    if not t:
        return "tuning not recorded"
    sizes = sorted(set(t["work_group"].values()))
    wg = f"{sizes[0]}" if len(sizes) == 1 else f"{sizes[0]}-{sizes[-1]}"
    sums = {1: ", masked sums", 0: ", zeroed sums"}.get(t.get("MASKED_SUMS"), "")
    return f"VW {t['VW']}{sums}, work-groups {wg} (queried)"


CROSS_NOTE = ("Every public call with its default arguments (the 'defaults' column of each "
              "device's lead table): M pts/s on each device, and in brackets its ratio to the "
              "fastest device for that call (1.00: the fastest).")


def cross_device_rows(devs, cols):
    """(header, rows) of the cross-device summary: per column and call, the default call's
    M pts/s on every device and its ratio to the fastest device."""
    head = ("call, n ~neighbours", [f"[{d['device']['index']}] {d['device']['platform']}"
                                    for d in devs])
    rows = []
    for c in cols:
        for row in CALL_ROWS:
            rate = [mpts(c["n"], d["k"][c["id"]]["calls_s"][row]["default"]) for d in devs]
            top = max(rate)
            rows.append((f"{call_text(row)}, {c['id']}",
                         [f"{v:.2f} ({v / top:.2f})" for v in rate]))
    return head, rows


def orientation_rows(o):
    """The orientation-alone section: a column per size."""
    sizes = sorted(o["sizes"])
    S = [o["sizes"][n] for n in sizes]
    col = lambda f: [f(x) for x in S]
    opt = lambda key, f: [f(x) if key in x else "" for x in S]
    rows = [("radius (~30 neighbours)", col(lambda x: f"{x['radius']:.5f}")),
            (f"clcurv.orient.orientation.flip_on_device (k={o['k']}), M pts/s (ms)",
             col(lambda x: f"{x['mpts']:.2f} ({ms(x['seconds'])})")),
            ("  k-NN graph (orient_graph), ms", col(lambda x: ms(x["stages"]["orient_graph"]))),
            ("  spanning forest (orient_forest), ms",
             col(lambda x: ms(x["stages"]["orient_forest"]))),
            ("    one run by hand: Borůvka rounds, Σ round ms (init + output ms)",
             col(lambda x: f"{x['rounds']}, {ms(sum(x['round_s']))} ({ms(x['forest_init_s'])} "
                           f"+ {ms(x['forest_output_s'])})")),
            ("    ms per round",
             col(lambda x: " ".join(f"{t * 1e3:.0f}" for t in x["round_s"]))),
            ("  signs (orient_signs), ms", col(lambda x: ms(x["stages"]["orient_signs"]))),
            ("  components; outward fraction",
             col(lambda x: f"{x['components']}; {x['outward']:.4%}")),
            ("host reference flip_by_propagation (same graph), M pts/s (ms)",
             opt("host_s", lambda x: f"{mpts(x['n'], x['host_s']):.3f} ({ms(x['host_s'])})")),
            ("  outward fraction; flips equal to the device's",
             opt("host_s", lambda x: f"{x['host_outward']:.4%}; {x['host_agree']:.4%}")),
            (f"Open3D orient_normals_consistent_tangent_plane({o['k']}), one run, M pts/s (ms)",
             opt("open3d_s",
                 lambda x: f"{mpts(x['n'], x['open3d_s']):.3f} ({ms(x['open3d_s'])})")),
            ("  outward fraction", opt("open3d_s", lambda x: f"{x['open3d_outward']:.4%}")),
            ("device / host reference; device / Open3D",
             opt("host_s", lambda x: f"{x['host_s'] / x['seconds']:.1f}x; " + (
                 f"{x['open3d_s'] / x['seconds']:.1f}x" if "open3d_s" in x else "–")))]
    return [f"{n:,} pts" for n in sizes], rows


ORIENT_NOTE = (
    "Orientation alone: the unoriented PCA normals (normals(P, r, orient=None)) of the bench "
    "sphere oriented on a DeviceCloud binned beforehand (binning not included), min of the "
    "repeats after a warm-up; stage times of the fastest run; the forest's rounds from one "
    "more run of clcurv.orient.graph.knn_graph + clcurv.orient.forest.spanning_forest. The host reference "
    "builds the same graph (k nearest within the radius) in float64.")


# ----------------------------------------------------------------------------- rendering
def render_text(header, rows):
    w0 = max(len(r[0]) for r in rows + [header]) + 2
    w = [max(len(c) for c in col) + 2 for col in zip(*[header[1]] + [r[1] for r in rows])]
    lines = [header[0].ljust(w0) + "".join(c.rjust(x) for c, x in zip(header[1], w))]
    for name, cells in rows:
        head = name.strip("*") if name.startswith("**") else "  " + name
        lines.append(head.ljust(w0) + "".join(c.rjust(x) for c, x in zip(cells, w)))
    return "\n".join(lines)


def md_row(cells):
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def render_markdown(header, rows):
    lines = [md_row([header[0]] + header[1]), "|---" + "|---:" * len(header[1]) + "|"]
    lines += [md_row([name] + cells) for name, cells in rows]
    return "\n".join(lines)


def target_lines(rows):
    return [(name, "" if v is None else f"{v:.2f}", thr, pass_fail(ok))
            for name, v, thr, ok in rows]


def render_targets(rows):
    w = max(len(r[0]) + len(r[2]) for r in rows) + 6
    return "\n".join(f"  {name} ({thr})".ljust(w) + f"{val:>8}  {ok}" for name, val, thr, ok in rows)


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
        "transparent huge pages: " + ", ".join(f"{k} {v}" for k, v in
                                              env.get("hugepages", {}).items()),
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


# ----------------------------------------------------------------------------- files
def report(args, env, guard, cols, refs, o3d_res, jak_res, jak_note, orientation, devs):
    """Print the tables and write JSON (one file per device kind) and bench.md: per device,
    the default calls first, then orientation alone, every row, the targets."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    threads = guard.checks
    text = [summary_text(env, args, threads, jak_note)]
    if guard.busy():
        text.append(f"WARNING: cores were busy around: {', '.join(guard.busy())}; their figures "
                    "are pessimistic and ratios involving them are unreliable: rerun on a quiet "
                    "machine")
    md = ["# clcurv benchmark", "", "```", *text, "```"]
    kinds_seen = {}
    ids = [c["id"] for c in cols]
    o_sizes, o_rows = orientation_rows(orientation)
    for dev in devs:
        rat = {c["id"]: ratios(c["n"], dev["k"][c["id"]], refs[c["id"]], o3d_res.get(c["id"]),
                               jak_res.get(c["id"]), dev["device"]["index"]) for c in cols}
        d = dev["device"]
        title = (f"[{d['index']}] {d['name']} — {d['platform']} "
                 f"({env['platforms'].get(d['platform'], '?')}), driver {d['driver']}, "
                 f"{d['version']}, {d['compute_units']} compute units, {tuning_text(d)}")
        text += ["", title, "", "WHAT THE DEFAULT CALL COSTS", LEAD_NOTE]
        md += ["", f"## {title}", "", "### What the default call costs", "", LEAD_NOTE]
        for cid in ids:
            K = dev["k"][cid]
            head = (f"{cid} (r = {K['radius']:.5f}, {K['mean_count']:.1f} neighbours)",
                    LEAD_HEADER)
            lead = lead_rows(K)
            text += ["", render_text(head, lead)]
            md += ["", render_markdown(head, lead)]
        if d["index"] == orientation.get("device"):
            head = (f"orientation alone, k={orientation['k']}", o_sizes)
            text += ["", "ORIENTATION ALONE", ORIENT_NOTE, render_text(head, o_rows)]
            md += ["", "### Orientation alone", "", ORIENT_NOTE, "", render_markdown(head, o_rows)]
        header = ("n, neighbours", ids)
        rows = device_rows(dev, refs, o3d_res, jak_res, rat, cols)
        tgt = target_lines(evaluate_targets(dev, rat, orientation, cols))
        text += ["", "EVERY ROW", render_text(header, rows), "", "TARGETS (bench/targets.py)",
                 render_targets(tgt)]
        md += ["", "### Every row", "", render_markdown(header, rows), "", "### Targets", "",
               "| target | value | threshold | result |", "|---|---:|---|---|"]
        md += [md_row(list(t)) for t in tgt]
        kind = d["kind"]
        kinds_seen[kind] = kinds_seen.get(kind, 0) + 1
        suffix = kind if kinds_seen[kind] == 1 else f"{kind}{kinds_seen[kind]}"
        write_json(RESULTS / f"bench-{suffix}.json", {
            "args": vars(args), "env": env, "threads": threads, "device": dev,
            "columns": [{x: v for x, v in c.items() if x != "cap"} for c in cols],
            "reference": {c: {x: v for x, v in refs[c].items()
                              if not x.startswith("result") and not x.startswith("ops")}
                          for c in ids},
            "open3d": o3d_res, "jakteristics": jak_res or {"skipped": jak_note},
            "orientation": orientation, "ratios": rat,
            "targets": [dict(zip(("name", "value", "threshold", "result"), t)) for t in tgt]})
    head, rows = cross_device_rows(devs, cols)
    text += ["", "ACROSS DEVICES", CROSS_NOTE, render_text(head, rows)]
    md += ["", "## Across devices", "", CROSS_NOTE, "", render_markdown(head, rows)]
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
