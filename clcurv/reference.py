"""Independent float64 reference ("oracle") for the neighbourhood moments.

This module is the host-side ground truth against which the OpenCL kernels are
checked. It deliberately shares no code with the OpenCL side: it uses only
NumPy and SciPy, works entirely in float64 and favours clarity and numerical
care over speed (it is still vectorised enough for ~10^5 points in seconds).

Conventions
-----------
* ``points`` is an ``(N, 3)`` array of coordinates in an arbitrary length
  unit ``L``; ``radius`` is in the same unit ``L``.
* The neighbourhood of ``p`` is the **strict** ball
  ``N_r(p) = {q : |q - p| < r}``, the point ``p`` itself included
  (Digne & Morel 2013, Section 2). The strict inequality is obtained from
  ``scipy.spatial.cKDTree`` (which tests ``<=``) by querying with
  ``np.nextafter(radius, 0)``; distances exactly equal to ``r`` (as computed by
  the k-d tree in float64) are excluded. :func:`ball_neighbors` and
  :func:`neighbor_counts` use ``cKDTree.query_ball_point``, :func:`moments`
  uses ``cKDTree.query_pairs``; both apply the same k-d tree distance test,
  so the neighbourhoods agree exactly.
* Weights: ``"uniform"`` gives every neighbour weight 1 (the case analysed by
  the paper's theorems); ``"density"`` gives neighbour ``q`` the weight
  ``1 / #N_r(q)`` (its own neighbour count, Section 3 of the paper).
* Normals returned here are **unoriented** (sign as ``numpy.linalg.eigh``
  gives it); see :mod:`clcurv.orient` to orient them.

Status codes (mirroring ``kernels/common.h``):

* ``0`` ok,
* ``1`` too few neighbours (``count < 3``),
* ``2`` degenerate covariance (rank < 2: ``l1 <= 1e-10 * l2`` or ``l2 == 0``
  with ascending eigenvalues ``l0 <= l1 <= l2``).

Points with a non-zero status get NaN in every floating-point output.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "STATUS_OK",
    "STATUS_TOO_FEW",
    "STATUS_DEGENERATE",
    "MIN_COUNT",
    "RANK_TOL",
    "ball_neighbors",
    "neighbor_counts",
    "moments",
]

STATUS_OK = 0
STATUS_TOO_FEW = 1
STATUS_DEGENERATE = 2

#: Minimum neighbour count (point included) for a covariance to be computed.
MIN_COUNT = 3
#: Relative threshold on the middle eigenvalue below which the covariance is
#: considered of rank < 2.
RANK_TOL = 1e-10

_WEIGHTS = ("uniform", "density")
# Number of neighbour pairs processed at once when accumulating moments.
_EDGE_CHUNK = 1 << 21


# --------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------
def _as_points(points):
    """Return ``points`` as a C-contiguous float64 ``(N, 3)`` array.

    Raises
    ------
    ValueError
        If the shape is not ``(N, 3)`` or a coordinate is not finite.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain non-finite coordinates")
    return pts


def _as_radius(radius):
    """Return ``radius`` as a positive finite Python float."""
    r = float(radius)
    if not (np.isfinite(r) and r > 0.0):
        raise ValueError(f"radius must be positive and finite, got {radius!r}")
    return r


# --------------------------------------------------------------------------
# neighbourhoods
# --------------------------------------------------------------------------
def _strict_radius(radius):
    """Largest float64 below ``radius``: turns the k-d tree's ``<=`` into ``<``."""
    return float(np.nextafter(radius, 0.0))


def ball_neighbors(points, radius):
    """Neighbour index lists of every point in the strict ball.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates, in length unit ``L``.
    radius : float
        Ball radius ``r`` in unit ``L`` (> 0).

    Returns
    -------
    list of list of int
        ``result[i]`` holds, in increasing order, the indices ``j`` with
        ``|points[j] - points[i]| < radius``; ``i`` itself is always included.
    """
    pts = _as_points(points)
    r = _as_radius(radius)
    if len(pts) == 0:
        return []
    tree = cKDTree(pts)
    lists = tree.query_ball_point(pts, _strict_radius(r), workers=-1,
                                  return_sorted=True)
    return [list(x) for x in lists]


def _ball_pairs(tree, r):
    """Unordered neighbour pairs ``(i, j)``, ``i < j``, with ``|p_i - p_j| < r``.

    Uses the same k-d tree distance test as :func:`ball_neighbors`
    (``<= nextafter(r, 0)``), without building Python lists.
    """
    pairs = tree.query_pairs(_strict_radius(r), output_type="ndarray")
    return pairs[:, 0].astype(np.intp), pairs[:, 1].astype(np.intp)


def neighbor_counts(points, radius):
    """Number of points in the strict ball of every point.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates, in length unit ``L``.
    radius : float
        Ball radius ``r`` in unit ``L`` (> 0).

    Returns
    -------
    numpy.ndarray of int32, shape (N,)
        ``#N_r(p)`` including ``p`` itself (so always >= 1).
    """
    pts = _as_points(points)
    r = _as_radius(radius)
    if len(pts) == 0:
        return np.empty(0, dtype=np.int32)
    tree = cKDTree(pts)
    counts = tree.query_ball_point(pts, _strict_radius(r), workers=-1,
                                   return_length=True)
    return np.asarray(counts, dtype=np.int32)


# --------------------------------------------------------------------------
# moments
# --------------------------------------------------------------------------
def _point_weights(counts, weights):
    """Weight of every point as a neighbour: 1, or ``1/#N_r(q)`` (density)."""
    if weights == "uniform":
        return np.ones(len(counts))
    return 1.0 / counts.astype(np.float64)


def _chunks(n, size):
    """Yield ``slice`` objects covering ``range(n)`` in blocks of ``size``."""
    for s in range(0, n, size):
        yield slice(s, min(n, s + size))


def _scatter(n, i, j, wi, wj, vi, vj):
    """``out[i] += wj * vi`` and ``out[j] += wi * vj`` for every pair."""
    return (np.bincount(i, weights=wj * vi, minlength=n)
            + np.bincount(j, weights=wi * vj, minlength=n))


def _weighted_moments(pts, i, j, w):
    """Weighted barycenter offset and centred covariance of every ball.

    The ball of ``p`` holds ``p`` itself (weight ``w[p]``) and, for each pair
    ``(i, j)``, ``j`` in the ball of ``i`` (weight ``w[j]``) and ``i`` in the
    ball of ``j`` (weight ``w[i]``).

    Two-pass, translation-safe algorithm: neighbour offsets ``d = q - p`` are
    formed relative to the query point ``p`` (so large coordinate offsets of
    the cloud cost no digits); the weighted mean offset ``m = o - p`` is
    accumulated first, then ``C = sum w (d - m)(d - m)^T / sum w``.

    Returns
    -------
    shift : ndarray, shape (N, 3)
        ``o - p`` (unit ``L``).
    cov : ndarray, shape (N, 3, 3)
        Weighted centred covariance (unit ``L^2``).
    """
    n = len(pts)
    x = [np.ascontiguousarray(pts[:, k]) for k in range(3)]  # unit-stride
    wsum = w.copy()              # the point itself...
    s1 = np.zeros((3, n))        # ...whose offset d = 0 adds nothing
    for sl in _chunks(len(i), _EDGE_CHUNK):
        a, b = i[sl], j[sl]
        wa, wb = w[a], w[b]
        wsum += _scatter(n, a, b, wa, wb, 1.0, 1.0)
        for k in range(3):
            d = x[k][b] - x[k][a]
            s1[k] += _scatter(n, a, b, wa, wb, d, -d)
    m = s1 / wsum

    # second pass: centred products, c = d - m (self term: c = -m)
    iu = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    s2 = np.stack([w * m[u] * m[v] for u, v in iu])
    for sl in _chunks(len(i), _EDGE_CHUNK):
        a, b = i[sl], j[sl]
        wa, wb = w[a], w[b]
        ca, cb = [], []
        for k in range(3):
            d = x[k][b] - x[k][a]
            ca.append(d - m[k][a])   # j seen from i
            cb.append(-d - m[k][b])  # i seen from j
        for col, (u, v) in enumerate(iu):
            s2[col] += _scatter(n, a, b, wa, wb, ca[u] * ca[v], cb[u] * cb[v])
    s2 /= wsum
    cov = np.empty((n, 3, 3))
    for col, (u, v) in enumerate(iu):
        cov[:, u, v] = s2[col]
        cov[:, v, u] = s2[col]
    return m.T.copy(), cov


def _classify(counts, evals):
    """Status codes from neighbour counts and ascending eigenvalues."""
    status = np.zeros(len(counts), dtype=np.uint8)
    l1, l2 = evals[:, 1], evals[:, 2]
    degenerate = (l2 == 0.0) | (l1 <= RANK_TOL * l2)
    status[degenerate] = STATUS_DEGENERATE
    status[counts < MIN_COUNT] = STATUS_TOO_FEW
    return status


def _empty_moments():
    """The :func:`moments` dictionary of an empty cloud."""
    return {
        "count": np.empty(0, dtype=np.int32),
        "status": np.empty(0, dtype=np.uint8),
        "eigenvalues": np.empty((0, 3)),
        "normals": np.empty((0, 3)),
        "variation": np.empty(0),
        "shift": np.empty((0, 3)),
    }


def moments(points, radius, weights="uniform"):
    """Weighted PCA moments of every strict-ball neighbourhood.

    For each point ``p`` with neighbourhood ``N_r(p)`` (``p`` included) and
    weights ``w_q``:

    * barycenter ``o = sum w_q q / sum w_q``,
    * covariance ``C = sum w_q (q - o)(q - o)^T / sum w_q``,
    * ascending eigenvalues ``l0 <= l1 <= l2`` of ``C``,
    * surface variation ``l0 / (l0 + l1 + l2)`` (Pauly et al., operator 4 of
      Digne & Morel 2013; tends to ``r^2/16 ((k1^2 + k2^2)/2 - k1 k2/3)``),
    * MLS0 shift ``o - p`` (operator 5; ``o - p ~ -(H r^2/4) n_out`` with the
      clcurv sign convention, i.e. ``H = 4 <p - o, n_out> / r^2``).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates, in length unit ``L``; must be finite.
    radius : float
        Ball radius ``r`` in unit ``L`` (> 0). Neighbourhoods are strict
        balls ``|q - p| < r``.
    weights : {"uniform", "density"}, optional
        ``"uniform"``: ``w_q = 1`` (default, the case of the theorems).
        ``"density"``: ``w_q = 1 / #N_r(q)``, the inverse of ``q``'s own
        neighbour count (density reweighting, Section 3).

    Returns
    -------
    dict
        ``"count"`` : int32 (N,)
            ``#N_r(p)``, ``p`` included.
        ``"status"`` : uint8 (N,)
            0 ok, 1 too few neighbours (``count < 3``), 2 degenerate
            covariance (``l1 <= 1e-10 * l2`` or ``l2 == 0``).
        ``"eigenvalues"`` : float64 (N, 3)
            Ascending eigenvalues of ``C``, unit ``L^2``. Tiny negative
            round-off values are clipped to 0.
        ``"normals"`` : float64 (N, 3)
            Unit eigenvector of ``l0`` (PCA normal), unoriented.
        ``"variation"`` : float64 (N,)
            ``l0 / (l0 + l1 + l2)``, dimensionless, in ``[0, 1/3]``.
        ``"shift"`` : float64 (N, 3)
            ``o - p``, unit ``L``.

        Every float64 entry is NaN where ``status != 0``.

    Raises
    ------
    ValueError
        If ``weights`` is not ``"uniform"`` or ``"density"``, ``points`` is
        not a finite ``(N, 3)`` array, or ``radius`` is not positive.
    """
    if weights not in _WEIGHTS:
        raise ValueError(f"weights must be one of {_WEIGHTS}, got {weights!r}")
    pts = _as_points(points)
    r = _as_radius(radius)
    n = len(pts)
    if n == 0:
        return _empty_moments()

    # Work in k-d tree order: spatially coherent, so the gathers and
    # scatters over neighbour pairs stay in cache; results are permuted back.
    perm = cKDTree(pts, balanced_tree=False).indices
    q = pts[perm]
    i, j = _ball_pairs(cKDTree(q), r)
    counts_q = (1 + np.bincount(i, minlength=n)
                + np.bincount(j, minlength=n)).astype(np.int32)
    shift_q, cov_q = _weighted_moments(q, i, j,
                                       _point_weights(counts_q, weights))
    counts = np.empty(n, dtype=np.int32)
    shift = np.empty((n, 3))
    cov = np.empty((n, 3, 3))
    counts[perm], shift[perm], cov[perm] = counts_q, shift_q, cov_q

    evals = np.full((n, 3), np.nan)
    normals = np.full((n, 3), np.nan)
    enough = counts >= MIN_COUNT
    if np.any(enough):
        lam, vec = np.linalg.eigh(cov[enough])
        evals[enough] = np.maximum(lam, 0.0)
        normals[enough] = vec[:, :, 0]
    status = _classify(counts, np.where(enough[:, None], evals, 0.0))

    bad = status != STATUS_OK
    with np.errstate(invalid="ignore", divide="ignore"):
        variation = evals[:, 0] / evals.sum(axis=1)
    evals[bad] = np.nan
    normals[bad] = np.nan
    variation[bad] = np.nan
    shift[bad] = np.nan
    return {
        "count": counts,
        "status": status,
        "eigenvalues": evals,
        "normals": normals,
        "variation": variation,
        "shift": shift,
    }
