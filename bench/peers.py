"""The peers clcurv is timed against: the float64 NumPy reference of every registered
operator, Open3D (normals, covariances, orientation) and jakteristics."""
from __future__ import annotations

import math
import time

import numpy as np

import clcurv
from clcurv import orient, reference, shapes
from clcurv.operators import OPERATORS, PCA

from .harness import device_coordinates, mpts, radius_for, timed, timeit
from .ops import HEADLINE, NORMAL_OPS

JAK_FEATURES = ["nx", "ny", "nz", "surface_variation", "eigenvalue_sum", "number_of_neighbors"]


# ----------------------------------------------------------------------------- reference
def bench_reference(pts, r, cap, normals=None):
    """The float64 NumPy reference of every operator on the cap (each timed once; it is slow
    and deterministic): the moments (every operator whose kernel is PCA's: one pass), each
    operator whose kernel reads normals with the exact normals, and the MLS1 scale space
    (2 iterations, timed: seconds per iteration = half).

    Every operator also runs (untimed) on the float32-rounded coordinates the device works
    with: the difference to that run is the kernels' own arithmetic error, the difference
    to the float64 run includes the rounding of the input to float32."""
    sub = pts[cap]
    moments = OPERATORS[HEADLINE].reference      # the moments kernel's reference
    seconds, ref = timed(lambda: moments(sub, r, None, "uniform"))
    sub32 = device_coordinates(pts, r)[cap]
    out = {"points": len(sub), "seconds": seconds, "mpts": mpts(len(sub), seconds),
           "mean_count": float(ref["count"].mean()), "result": ref,
           "result_f32_input": moments(sub32, r, None, "uniform"),
           "op_seconds": {PCA.name: seconds}, "ops": {}, "ops_f32_input": {}}
    if normals is None:
        return out
    nsub = normals[cap]
    for m in NORMAL_OPS:
        run = OPERATORS[m].reference
        out["op_seconds"][m], out["ops"][m] = timed(lambda: run(sub, r, nsub, "uniform"))
        out["ops_f32_input"][m] = run(sub32, r, nsub, "uniform")
    s, its = timed(lambda: reference.scale_space(sub, r, 2))
    out["op_seconds"]["scale_space_iteration"] = s / 2
    out["ops"]["scale_space_disp2"] = its[2] - sub
    out["ops"]["scale_space_disp2_f32_input"] = reference.scale_space(sub32, r, 2)[2] - sub32
    out["op_mpts"] = {k: mpts(len(sub), v) for k, v in out["op_seconds"].items()}
    return out


def ref_extrapolated(ref, op, n):
    """Seconds the reference would take for ``op`` on n points (linear in the points)."""
    return ref["op_seconds"][op] / ref["points"] * n


# ----------------------------------------------------------------------------- jakteristics
def jakteristics_or_reason():
    """(module, None), or (None, why it is not available)."""
    try:
        import jakteristics
        return jakteristics, None
    except Exception as exc:  # noqa: BLE001 - optional peer
        return None, f"{type(exc).__name__}: {exc}"


def jakteristics_version(jak):
    import importlib.metadata
    try:
        return importlib.metadata.version("jakteristics")
    except importlib.metadata.PackageNotFoundError:
        return getattr(jak, "__version__", "?")


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


# ----------------------------------------------------------------------------- Open3D
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
