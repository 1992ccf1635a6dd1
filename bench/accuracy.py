"""The bench's accuracy checks: the whole-cloud clcurv runs against the float64 reference
run on a polar cap of the same cloud (bench.peers.bench_reference), with the tolerances of
bench.targets (the ones the tests assert)."""
from __future__ import annotations

import math

import numpy as np

from clcurv.ops.registry import OPERATORS

from .harness import cap_interior
from .ops import NORMAL_OPS
from .targets import (AGREE_MIN, COS_TOL, COV_K1_TOL, MLS2_K_TOL, SS_TOL,
                      VAR_MEDIAN_TOL)

SS_HOPS = 2.5             # cap interior for 2 iterations: balls of radius 2.5 r inside the cap


def quantiles(err):
    if not len(err):
        return {"median": math.nan, "p999": math.nan, "max": math.nan}
    return {"median": float(np.median(err)), "p999": float(np.quantile(err, 0.999)),
            "max": float(err.max())}


def comparable(got_count, got_status, ref):
    """Points whose neighbour counts equal the reference's and whose status is OK in both."""
    return (got_count == ref["count"]) & (got_status == 0) & (ref["status"] == 0)


def variation_error(var, ref, cap):
    """Relative error of surface variation on the cap points with equal counts, status ok."""
    same = comparable(var.count[cap], var.status[cap], ref)
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
    same = comparable(var.count[cap], var.status[cap], ref)
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


def op_errors(d, rf, m):
    """(points compared, {k: error quantiles}) of operator ``m`` against one reference run:
    a signed operator's k1 and k2 relative to max(|k1|, |k2|) of the reference, the
    magnitudes' k1 relative to itself."""
    same = comparable(d["count"], d["status"], rf)
    if OPERATORS[m].signed:
        scale = np.maximum(np.abs(rf["k1"][same]), np.abs(rf["k2"][same]))
        return same, {k: quantiles(np.abs(d[k][same] - rf[k][same]) / scale) for k in ("k1", "k2")}
    return same, {"k1": quantiles(np.abs(d["k1"][same] - rf["k1"][same]) / np.abs(rf["k1"][same]))}


def check_ops(kept, ref):
    """The operators run with normals given (covariances' k1 relative; MLS2's k1, k2 relative
    to max |k|) against the float64 reference, on the cap points whose counts agree and whose
    status is OK in both; and (information) against the reference run on the float32-rounded
    input."""
    out = {}
    for m in NORMAL_OPS:
        same, err = op_errors(kept[m], ref["ops"][m], m)
        c = {"compared": int(same.sum()), "of": len(same), **err,
             "f32_input": op_errors(kept[m], ref["ops_f32_input"][m], m)[1]}
        c["pass"] = bool(max(e["p999"] for e in err.values()) <= tolerance(m))
        out[m] = c
    return out


def check_scale_space(disp2, ref, pts, cap, r):
    """Positions after 2 iterations on the cap interior (balls of radius SS_HOPS r inside the
    cap), |d| / r, against the float64 reference (and, for information, the reference run on
    the float32-rounded input)."""
    inner = cap_interior(pts, cap, SS_HOPS * r)
    d64 = np.linalg.norm(disp2[inner] - ref["ops"]["scale_space_disp2"][inner], axis=1) / r
    d32 = np.linalg.norm(disp2[inner] - ref["ops"]["scale_space_disp2_f32_input"][inner],
                         axis=1) / r
    out = {"compared": int(inner.sum()), "of": len(cap), "err": quantiles(d64),
           "err_f32_input": quantiles(d32)}
    out["pass"] = bool(out["err"]["p999"] <= SS_TOL)
    return out


def tolerance(m):
    """The tolerance of operator ``m``'s curvatures (bench.targets)."""
    return MLS2_K_TOL if OPERATORS[m].signed else COV_K1_TOL
