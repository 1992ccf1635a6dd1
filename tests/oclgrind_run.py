"""Run every registered operator and support kernel on one small cloud on a named device.

    python tests/oclgrind_run.py CASE VARIANT [DEVICE]     (VARIANT: float, double, float-cpu)

tests/test_oclgrind.py runs this in a subprocess under Oclgrind (DEVICE "oclgrind", the
default), with its checks switched on by environment variables; it reads Oclgrind's report
and which kernels ran. CASES are the edge shapes: N = 1, a block with empty cells, points
on cell borders, N not a multiple of the vector width. Every call of :func:`run` goes
through the public API (so the host code that sizes the buffers is what is checked); the
operators come from the registry (clcurv.OPERATORS), so a new operator is run here too.
Prints one line per call: its name and how many of its outputs are finite.
"""
import dataclasses
import sys

import numpy as np

import clcurv
from clcurv.api.features import FEATURES as FEATURE_NAMES

R = 0.25          # a power of two: lattice points at multiples of R / 2 lie on cell borders
K = 6             # neighbours of the k-NN radius
FEATURES = tuple(FEATURE_NAMES)


def _vw_remainder():
    """37 points (not a multiple of 4, 8 or 16) on a bumpy patch, ~10 neighbours."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 0.7, (37, 2))
    return np.column_stack([xy, 0.1 * np.sin(4 * xy[:, 0]) * np.cos(3 * xy[:, 1])])


def _borders():
    """A lattice of spacing R / 2 (exact in float): every point on a cell border, and
    neighbours at exactly R (outside the open ball), 5 x 5 x 2 points."""
    g = np.arange(5) * (R / 2)
    x, y, z = np.meshgrid(g, g, np.array([0.0, R]), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def _empty_cells():
    """Two clusters 3.5 cells apart (blocks holding empty cells and empty rows), a point
    alone in a cell with empty neighbours, and duplicates."""
    rng = np.random.default_rng(4)
    a = rng.normal(0, 0.05, (12, 3))
    b = rng.normal(0, 0.05, (9, 3)) + [3.5 * R, 3.5 * R, 0.0]
    alone = [[0.0, 3.5 * R, 3.5 * R]]
    return np.vstack([a, b, alone, a[:3]])


def _sphere():
    """90 points on a unit sphere: orientation needs several Boruvka rounds."""
    return clcurv.shapes.sphere(90, 1.0, seed=5)["points"] * (2 * R)


CASES = {
    "n1": lambda: np.array([[0.1, 0.2, 0.3]]),
    "vw_remainder": _vw_remainder,
    "borders": _borders,
    "empty_cells": _empty_cells,
    "sphere": _sphere,
}


def _finite(res):
    """Finite rows of every float array of a result (a list of results: of each)."""
    if isinstance(res, list):
        return [_finite(r) for r in res]
    if isinstance(res, np.ndarray):
        return int(np.isfinite(res.reshape(len(res), -1)).all(axis=1).sum())
    fields = res if isinstance(res, dict) else vars(res)
    return {k: _finite(v) for k, v in fields.items()
            if isinstance(v, dict) or isinstance(v, np.ndarray) and v.dtype.kind == "f" and v.ndim}


def _small_radius(points, common):
    """A fifth of the cell's radius on a DeviceCloud: the walks that skip rows (ROW_PRUNE,
    below clcurv.ops.driver.PRUNE_BELOW cells)."""
    from clcurv.ops.driver import PRUNE_BELOW
    cloud = clcurv.DeviceCloud(points, R, **common)
    assert R / 5 < PRUNE_BELOW * cloud.cell
    return [clcurv.curvature(cloud, R / 5, method="variation", orient=None),
            clcurv.features(cloud, R / 5, features=FEATURES)]


def calls(points, precision, device):
    """(name, thunk) of every call: each registered operator (unoriented, and with the
    normals given where it reads them), MST orientation (knn.cl, forest.cl), density
    weights, the Gaussian MLS2 kernel, the scale space and the MLS2 projection."""
    common = dict(device=device, precision=precision)
    k = min(K, len(points))               # k <= N (N = 1: k = 1)
    given = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    out = []
    for name, op in clcurv.OPERATORS.items():
        out.append((name, lambda m=name: clcurv.curvature(points, R, method=m, orient=None,
                                                          **common)))
        if op.kernel.reads_normals:
            out.append((f"{name}+normals", lambda m=name: clcurv.curvature(
                points, R, method=m, normals=given, **common)))
    out += [
        ("mls1+mst", lambda: clcurv.curvature(points, R, method="mls1", orient="mst",
                                              **common)),
        ("mls1+density", lambda: clcurv.curvature(points, R, method="mls1", orient=None,
                                                  weights="density", **common)),
        ("mls2+gaussian", lambda: clcurv.curvature(points, R, method="mls2", orient=None,
                                                   kernel="gaussian", **common)),
        # the error records (quadric.h): MLS2's, and the moments kernel's second walk
        ("mls2+uncertainty+density", lambda: clcurv.curvature(
            points, R, method="mls2", orient=None, weights="density", uncertainty=True,
            **common)),
        ("mls1+uncertainty", lambda: clcurv.curvature(points, R, method="mls1", orient=None,
                                                      uncertainty=True, **common)),
        # the normals' pass with its error record and no quadric walk (NOISE_WALK=0)
        ("2dcov2+uncertainty", lambda: clcurv.curvature(points, R, method="2dcov2",
                                                        orient=None, uncertainty=True,
                                                        **common)),
        # a radius per point: every radius with its errors, the pooled bias (ball_mean.cl)
        ("mls2+select", lambda: clcurv.curvature(points, [R / 2, R / 1.4, R], method="mls2",
                                                 orient=None, select="error", **common)),
        ("scale_space+density", lambda: clcurv.scale_space(points, R, 2, weights="density",
                                                           **common)),
        ("project", lambda: clcurv.project(points, R, projections=1, orient=None, **common)),
        ("variation+radii", lambda: clcurv.curvature(points, [R / 2, R], method="variation",
                                                     orient=None, **common)),
        # the PCA normals of a radius list in one features walk, built without the anchor
        ("3dcov+radii", lambda: clcurv.curvature(points, [R / 3, R / 2, R], method="3dcov",
                                                 orient=None, **common)),
        # MST orientation: knn.cl's graph on each point's own ball (POINT_RADIUS, pruned rows)
        ("mls2+knn_radius+graph", lambda: clcurv.curvature(points, method="mls2", k=k,
                                                           orient="mst", **common)),
        ("features", lambda: clcurv.features(points, R, features=FEATURES, **common)),
        # three balls: two eigen solves paired in twice the lanes, one alone
        ("features+three_radii", lambda: clcurv.features(points, [R / 3, R / 2, R],
                                                         features=FEATURES, **common)),
        ("variation+features+pruned_rows", lambda: _small_radius(points, common)),
        ("features+knn_radius", lambda: clcurv.features(points, k=k, features=FEATURES,
                                                        **common)),
        ("forest+edges", lambda: _forest(points, R, common)),
        ("forest+small_blocks", lambda: _forest(points, R, common, block=4, chase=1)),
    ]
    return out


def _forest(points, r, common, block=None, chase=None):
    """The orientation graph and its spanning forest with the edge output (which the API
    does not ask for); ``block`` and ``chase`` shrink clcurv.orient.forest.BLOCK (points per
    work-item: several blocks on a tiny cloud) and CHASE (hook chains followed link by
    link: 1 forces the pointer-jumping kernel) for the call. Returns the labels."""
    from clcurv.orient import forest, graph
    from clcurv.grid.cloud import DeviceCloud
    saved = forest.BLOCK, forest.CHASE
    forest.BLOCK = block or forest.BLOCK
    forest.CHASE = chase or forest.CHASE
    try:
        cloud = DeviceCloud(points, r, **common)
        n = clcurv.normals(cloud, r, orient=None)
        fo = forest.spanning_forest(cloud, graph.knn_graph(cloud, r, n), edges=True)
    finally:
        forest.BLOCK, forest.CHASE = saved
    return fo.label[:, None].astype(float)


def as_cpu(device):
    """Make clcurv treat ``device`` as a CPU device (Oclgrind reports itself as a GPU): the
    CPU choices (VW 8, work-groups of 1 for knn_graph and the forest's block kernels, mapped
    host buffers) are then checked too."""
    dev = clcurv.get_device(device)           # the cached Device every call gets
    dev.info = dataclasses.replace(dev.info, kind="cpu")


def main(case, variant="float", device="oclgrind"):
    """Run every call on ``CASES[case]``; ``variant`` is 'float' or 'double' (the
    precision), or 'float-cpu' (float, with the device treated as a CPU device)."""
    precision = variant.split("-")[0]
    if variant.endswith("-cpu"):
        as_cpu(device)
    points = CASES[case]()
    for name, thunk in calls(points, precision, device):
        print(f"call {name}: {_finite(thunk())}", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
