"""The peers clcurv is timed against: the float64 NumPy reference of every registered
operator, Open3D (normals, covariances, orientation) and jakteristics."""
from __future__ import annotations

import math
import time

import numpy as np

import clcurv
from clcurv.orient import orientation as orient
from clcurv.reference import operators as reference
from clcurv.ops.registry import OPERATORS, PCA

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


#: interleaved (clcurv, Open3D) pairs of the default-call target (bench.targets
#: DEFAULT_VARIATION_VS_OPEN3D)
VARIATION_PAIRS = 5


def bench_variation_pairs(o3d, clouds, r, device, repeats=VARIATION_PAIRS):
    """``curvature(P, r, method="variation")`` with default arguments on the random-order
    cloud (on ``device``) and Open3D's ``estimate_normals`` on the sorted copy, interleaved
    (clcurv, Open3D, clcurv, ...): the minimum of each over ``repeats`` pairs, so that the
    target's ratio compares runs made in the same seconds (the separate blocks run minutes
    apart on a machine whose speed drifts). Open3D gets a fresh PointCloud per run, built
    outside the timed region."""
    param = o3d.geometry.KDTreeSearchParamRadius(r)
    pts, srt = clouds["random"], clouds["sorted"]
    clcurv.curvature(pts, r, method="variation", device=device)          # warm-up
    best_c = best_o = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = clcurv.curvature(pts, r, method="variation", device=device)
        best_c = min(best_c, time.perf_counter() - t0)
        del res
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(srt))
        t0 = time.perf_counter()
        pcd.estimate_normals(param)
        best_o = min(best_o, time.perf_counter() - t0)
        del pcd
    return {"clcurv_s": best_c, "open3d_s": best_o, "pairs": repeats, "device": device}


#: the orientation graph's neighbour count (clcurv's default orient_k; Open3D's argument)
ORIENT_K = 10
#: the stages of clcurv.orient.orientation.flip_on_device, in its cloud.timings
ORIENT_STAGES = ("orient_graph", "orient_forest", "orient_signs")


def outward(n, pts):
    """Fraction of normals pointing outward on the unit sphere (n . p > 0)."""
    return float(np.mean(np.einsum("ij,ij->i", n, pts) > 0))


def oriented(nrm, flip):
    n = nrm.copy()
    n[flip] *= -1
    return n


def bench_orientation(o3d, clouds, host_points, device, repeats):
    """Orientation alone (Hoppe, k = ORIENT_K nearest within the radius of ~30 neighbours) of
    the unoriented normals (clcurv.normals, orient=None) of each cloud ({n: points}):
    clcurv.orient.orientation.flip_on_device on a DeviceCloud binned beforehand (min of ``repeats`` runs
    after a warm-up; its stage times from the fastest run), then one run of its stages by
    hand for the forest's rounds (clcurv.orient.graph.knn_graph, clcurv.orient.forest.spanning_forest).
    On the cloud of ``host_points`` also the host reference flip_by_propagation (same graph;
    min of 2) and Open3D's orient_normals_consistent_tangent_plane(ORIENT_K) (one run)."""
    from clcurv.orient import forest, graph
    from clcurv.grid.cloud import DeviceCloud
    out = {"k": ORIENT_K, "device": device, "sizes": {}}
    for n, pts in sorted(clouds.items()):
        r = radius_for(30, n)
        nrm = clcurv.normals(pts, r, orient=None, device=device)
        cloud = DeviceCloud(pts, r, device=device)
        orient.flip_on_device(cloud, nrm, r, ORIENT_K)   # warm-up (builds the programs)
        best, flip, stages = math.inf, None, None
        for _ in range(repeats):
            s, f = timed(lambda: orient.flip_on_device(cloud, nrm, r, ORIENT_K))
            if s < best:
                best, flip, stages = s, f, {k: cloud.timings[k] for k in ORIENT_STAGES}
        g = graph.knn_graph(cloud, r, nrm, ORIENT_K)
        fo = forest.spanning_forest(cloud, g)
        rec = {"n": n, "radius": r, "seconds": best, "mpts": mpts(n, best), "stages": stages,
               "graph": dict(g.timings), "rounds": fo.rounds,
               "round_s": list(fo.timings["rounds"]), "forest_init_s": fo.timings["init"],
               "forest_output_s": fo.timings["output"], "edge_counts": list(fo.edge_counts),
               "components": int(len(np.unique(fo.label[fo.label >= 0]))),
               "outward": outward(oriented(nrm, flip), pts)}
        if n == host_points:
            host = orient.flip_by_propagation(pts, nrm, k=ORIENT_K, radius=r)
            rec["host_s"] = min(timeit(lambda: orient.flip_by_propagation(
                pts, nrm, k=ORIENT_K, radius=r), 1, warmup=0) for _ in range(2))
            rec["host_outward"] = outward(oriented(nrm, host), pts)
            rec["host_agree"] = float(np.mean(host == flip))
            if o3d is not None:
                pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                pcd.normals = o3d.utility.Vector3dVector(nrm)
                t0 = time.perf_counter()
                pcd.orient_normals_consistent_tangent_plane(ORIENT_K)
                rec["open3d_s"] = time.perf_counter() - t0
                rec["open3d_outward"] = outward(np.asarray(pcd.normals), pts)
        out["sizes"][n] = rec
    return out
