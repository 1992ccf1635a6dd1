"""Float64 reference of :func:`clcurv.api.features` and of the k-NN radius (NumPy/SciPy only).

Written apart from the kernels and from :mod:`clcurv.api.features` (whose formulas live in
``kernels/features.cl``): a k-d tree ball query (open ball: ``cKDTree`` tests ``<=``, so it
is queried with ``nextafter(r, 0)``), two-pass centred covariances per ball, ``eigh``, then
the formulas of :data:`clcurv.api.features.FEATURES` written again here with NumPy. Status as
the kernels: 1 (fewer than 3 points), 2 (``l2 <= RANK_TOL * l1``: collinear or coincident).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from clcurv._shared.constants import DEGENERATE, MIN_COUNT_PCA, OK, TOO_FEW

#: rank-2 test of the float64 reference (clcurv.reference.operators.RANK_TOL)
RANK_TOL = 1e-10


def _balls(points, radius):
    """(rows, cols) of the open balls |q - p| < radius (scalar or per point), rows sorted."""
    tree = cKDTree(points)
    r = np.nextafter(np.asarray(radius, dtype=np.float64), 0)
    if r.ndim == 0:
        r = np.full(len(points), float(r))
    nb = tree.query_ball_point(points, np.where(r > 0, r, 0.0), return_sorted=True)
    counts = np.fromiter((len(x) for x in nb), dtype=np.int64, count=len(points))
    rows = np.repeat(np.arange(len(points)), counts)
    cols = np.fromiter((j for x in nb for j in x), dtype=np.int64, count=int(counts.sum()))
    return rows, cols, counts


def covariances(points, radius, ddof=0):
    """(count, cov (N, 3, 3)): the covariance sum (q - o)(q - o)^T / (n - ddof) of every
    ball, two passes (barycentre, then centred products), offsets relative to p."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    rows, cols, count = _balls(pts, radius)
    d = pts[cols] - pts[rows]
    n = np.maximum(count, 1).astype(np.float64)
    mean = np.stack([np.bincount(rows, d[:, a], len(pts)) for a in range(3)], 1) / n[:, None]
    c = d - mean[rows]
    cov = np.empty((len(pts), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(rows, c[:, a] * c[:, b], len(pts))
    cov /= np.maximum(n - ddof, 1)[:, None, None]
    return count, cov


def features(points, radius, names, ddof=0, up=None):
    """(values, count, status) of the features ``names`` (canonical) at ``radius`` (a
    number or per-point radii): float64, NaN where status != 0. ``up``: a unit direction
    the normals are turned towards (a normal with <n, up> < 0 negated), else eigh's sign."""
    count, cov = covariances(points, radius, ddof)
    ok = count >= MIN_COUNT_PCA
    cov[~ok] = np.eye(3)
    w, v = np.linalg.eigh(cov)                  # ascending
    w = np.maximum(w, 0.0)
    status = np.where(ok, OK, TOO_FEW).astype(np.uint8)
    status[ok & ~((w[:, 2] > 0) & (w[:, 1] > RANK_TOL * w[:, 2]))] = DEGENERATE
    l1, l2, l3 = w[:, 2], w[:, 1], w[:, 0]
    e1, e2, e3 = v[:, :, 2], v[:, :, 1], v[:, :, 0]
    if up is not None:                          # the reference's own orientation step
        e3 = np.where((np.einsum("ij,j->i", e3, np.asarray(up, np.float64)) < 0)[:, None],
                      -e3, e3)
    s = l1 + l2 + l3
    with np.errstate(divide="ignore", invalid="ignore"):
        ent = -sum(np.where(x > 0, x * np.log(np.where(x > 0, x, 1.0)), 0.0)
                   for x in (l1, l2, l3))
        u = l1[:, None] * abs(e1) + l2[:, None] * abs(e2) + l3[:, None] * abs(e3)
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), count.shape)
        table = {
            "eigenvalue_sum": s, "omnivariance": np.cbrt(l1 * l2 * l3), "eigenentropy": ent,
            "anisotropy": (l1 - l3) / l1, "planarity": (l2 - l3) / l1,
            "linearity": (l1 - l2) / l1, "PCA1": l1 / s, "PCA2": l2 / s,
            "surface_variation": l3 / s, "sphericity": l3 / l1,
            "verticality": 1.0 - abs(e3[:, 2]),
            "guinard_verticality": u[:, 2] / np.linalg.norm(u, axis=1),
            "eigenvalue1": l1, "eigenvalue2": l2, "eigenvalue3": l3,
            "density": count / (4.0 / 3.0 * np.pi * r ** 3),
            "normals": e3,
        }
    bad = status != OK
    out = {}
    for n in names:
        a = np.array(table[n], dtype=np.float64)
        a[bad] = np.nan
        out[n] = a
    return out, count, status


def knn_radii(points, k):
    """The distance of every point to its k-th nearest point (the point itself the first),
    float64, by a k-d tree."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    d, _ = cKDTree(pts).query(pts, k=[k])
    return d[:, 0]
