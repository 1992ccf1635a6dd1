"""The float64 oracle of kernels/ball_mean.cl (:func:`clcurv.ops.pooling.ball_mean`): the
(weighted) mean of a per-point field over every point's ball ``|q - p| < r`` by a cKDTree
ball query, NaN values (and NaN weights) skipped."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["ball_mean"]


def ball_mean(points, values, radius, weights=None):
    """(mean, weight sum) of ``values`` over each point's open ball of ``radius`` (the point
    included), weighted by ``weights`` (default 1); a neighbour counts where its value and
    weight are finite. Mean NaN and weight sum 0 where none does. float64, input order."""
    p = np.asarray(points, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    w = np.ones_like(v) if weights is None else np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(v) & np.isfinite(w)
    wv = np.where(ok, w * np.where(ok, v, 0.0), 0.0)
    wz = np.where(ok, w, 0.0)
    tree = cKDTree(p)
    # query_ball_point's ball is closed (|q - p| <= r): shrink r by one ulp for the open one
    balls = tree.query_ball_point(p, np.nextafter(radius, 0.0))
    lens = np.fromiter((len(b) for b in balls), dtype=np.int64, count=len(p))
    idx = np.fromiter((i for b in balls for i in b), dtype=np.int64, count=int(lens.sum()))
    owner = np.repeat(np.arange(len(p)), lens)
    num = np.bincount(owner, wv[idx], minlength=len(p))
    den = np.bincount(owner, wz[idx], minlength=len(p))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(den > 0, num / den, np.nan)
    return mean, den
