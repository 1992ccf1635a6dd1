"""The optimal neighbourhood: each point's radius, among candidates, that minimises the
eigenentropy of its ball (``clcurv.features(..., radius=[...], optimal=True)``).

Criterion (Weinmann, Jutzi, Hinz & Mallet 2015, "Semantic point cloud interpretation based
on optimal neighborhoods, relevant features and efficient classifiers", the one of PDAL's
``filters.optimalneighborhood``): the Shannon entropy of the sum-normalised eigenvalues

    E(r) = - sum_i e_i ln e_i,   e_i = l_i / (l1 + l2 + l3),   0 ln 0 = 0,

in [0, ln 3]: 0 for a ball whose points lie on a line, ln 2 for an isotropic plane, ln 3 for
an isotropic volume. The radius of least E is the one at which the ball looks most like
one dimensionality (noise makes small balls isotropic, curvature and clutter make large
ones so). PDAL scans k nearest neighbours from ``min_k`` to ``max_k`` (Weinmann's scale
parameter); here the candidates are radii, as in Demantke, Mallet, David & Vallet 2011
(who scanned radii with another entropy): pass a geometric range (e.g. 8 radii from r to
4r) for the same kind of search. E does not depend on ``ddof`` (it cancels in e_i).

How: the eigenvalues of every candidate ball come from features.cl's multi-radius walks on
one grid (cells of the largest radius, up to four radii per walk, bit-identical to a single
call at each radius); E is evaluated on the host in float64 and each point takes the
candidate of least E among those with status 0 (ties: the smallest radius). A second walk
then computes the features asked for at each point's own radius (the per-point radius of
the k-NN path, radius.h), so every point's values are those of a single-radius call at its
radius, bit for bit (tests/test_optimal.py). A point with no candidate of status 0 gets the
largest radius and that radius's status (its features NaN).

Cost: ceil(m / 4) walks of m candidates at the largest radius plus one walk at each point's
radius, with the largest radius's cells.
"""
from __future__ import annotations

import numpy as np

from clcurv._shared.constants import OK
from clcurv.grid.cloud import upload_point_r2
from clcurv.ops.features import run_features
from clcurv.reference import features as ref

#: the eigenvalue columns the criterion needs
EIGEN = ("eigenvalue1", "eigenvalue2", "eigenvalue3")


def eigenentropy_normalised(l1, l2, l3):
    """E = -sum e_i ln e_i of the sum-normalised eigenvalues (float64, 0 ln 0 = 0; NaN
    where the eigenvalues are NaN or their sum is not positive)."""
    lam = np.stack([np.asarray(x, np.float64) for x in (l1, l2, l3)])
    s = lam.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = lam / s
        t = np.where(e > 0, e * np.log(np.where(e > 0, e, 1.0)), 0.0)
        out = -t.sum(axis=0)
    out[~(s > 0)] = np.nan
    return out


def choose(entropies, statuses):
    """(index of the chosen candidate per point, any candidate ok) from (m, N) entropies
    and statuses of candidates sorted by radius: the least entropy among status-0
    candidates, ties to the smallest radius; the largest radius where none is ok."""
    e = np.where(np.asarray(statuses) == OK, np.asarray(entropies, np.float64), np.inf)
    e[np.isnan(e)] = np.inf
    idx = np.argmin(e, axis=0)
    ok = np.isfinite(e[idx, np.arange(e.shape[1])])
    idx[~ok] = e.shape[0] - 1
    return idx, ok


def optimal_features(cloud, radii, names, ddof=0):
    """(values, count, status, radius per point, chosen index) of ``names`` at each point's
    optimal radius among ``radii`` (sorted ascending, at least 2) on ``cloud`` (a
    DeviceCloud whose cell is >= the largest): see the module notes. Input order."""
    radii = [float(r) for r in radii]
    cand = run_features(cloud, radii, list(EIGEN), ddof)
    ent = np.stack([eigenentropy_normalised(*(v[n] for n in EIGEN)) for v, _, _ in cand])
    idx, _ = choose(ent, np.stack([s for _, _, s in cand]))
    del cand, ent
    r2 = np.array([cloud.dtype(r * r) for r in radii], dtype=cloud.dtype)  # as the fixed path
    buf = upload_point_r2(cloud, r2[idx[cloud.grid.order]])
    vals, count, status = run_features(cloud, [radii[-1]], names, ddof, point_r2=buf)[0]
    return vals, count, status, np.asarray(radii)[idx], idx


def reference_optimal_features(points, radii, names, ddof=0, up=None):
    """:func:`optimal_features` by the float64 reference (clcurv.reference.features at each
    of the sorted ``radii``, the same criterion and choice), for the tests."""
    need = list(dict.fromkeys(list(names) + list(EIGEN)))
    cand = [ref.features(points, r, need, ddof=ddof, up=up) for r in radii]
    ent = np.stack([eigenentropy_normalised(*(v[n] for n in EIGEN)) for v, _, _ in cand])
    idx, _ = choose(ent, np.stack([s for _, _, s in cand]))
    rows = np.arange(len(points))
    pick = lambda arrays: np.stack(arrays)[idx, rows]
    vals = {n: pick([v[n] for v, _, _ in cand]) for n in names}
    count, status = pick([c for _, c, _ in cand]), pick([s for _, _, s in cand])
    return vals, count, status, np.asarray(radii, np.float64)[idx], idx
