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


# ==========================================================================
# Normal-based covariance operators and MLS2 (Digne & Morel 2013, operators
# 1, 2, 3 and 7)
# ==========================================================================
#
# Conventions shared by :func:`covariance_ops`, :func:`mls2` and
# :func:`mls2_iterate` (in addition to the module conventions above):
#
# * ``normals`` are the caller's unit normals, ORIENTED outward (user normals,
#   or PCA normals oriented with :mod:`clcurv.orient`). They are normalised
#   again here (only directions matter); a row that is not finite or is zero
#   is *invalid*.
# * Tangent basis at ``p``: ``(t1, t2)`` built deterministically from the
#   normal ``n`` by :func:`tangent_frame`, orthonormal with ``t1 x t2 = n``.
# * Sign convention of clcurv: outward normals; a surface bending away from
#   its normal has positive curvature (sphere of radius R: ``k = +1/R``).
#   ``covariance_ops`` returns magnitudes, ``mls2`` signed values.
# * Status codes: 0 ok, 1 too few neighbours, 2 degenerate, 3 singular fit;
#   every float64 output is NaN on rows whose status is not 0.

__all__ += [
    "STATUS_SINGULAR",
    "MIN_COUNT_MLS2",
    "SINGULAR_RCOND",
    "COV_METHODS",
    "tangent_frame",
    "covariance_ops",
    "invert_theorem1",
    "mls2",
    "mls2_iterate",
]

STATUS_SINGULAR = 3
#: Minimum neighbour count (point included) for the 6-coefficient MLS2 fit.
MIN_COUNT_MLS2 = 6
#: The 6x6 MLS2 normal equations are singular when their smallest singular
#: value is <= SINGULAR_RCOND times the largest (coordinates scaled by 1/r).
SINGULAR_RCOND = 1e-10
COV_METHODS = ("2dcov1", "2dcov2", "3dcov")
_KERNELS = ("ball", "gaussian")


def _as_normals(normals, n):
    """Unit float64 ``(n, 3)`` copy of ``normals``; invalid rows become NaN."""
    nrm = np.array(normals, dtype=np.float64, copy=True)
    if nrm.shape != (n, 3):
        raise ValueError(f"normals must have shape ({n}, 3), got {nrm.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
        bad = ~np.isfinite(length) | (length == 0.0)
        nrm /= np.where(bad, 1.0, length)[:, None]
    nrm[bad] = np.nan
    return nrm


def _unit_rows(v):
    """Rows of ``v`` divided by their Euclidean norm."""
    return v / np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]


def tangent_frame(normals):
    """Deterministic orthonormal tangent basis ``(t1, t2)`` with ``t1 x t2 = n``.

    ``t1`` is ``n x e`` normalised, ``e`` being the coordinate axis least
    aligned with ``n`` (the first such axis on ties); ``t2 = n x t1``. Then
    ``t1 x t2 = t1 x (n x t1) = n``.

    Parameters
    ----------
    normals : array_like, shape (N, 3)
        Unit normals; NaN rows give NaN frames.

    Returns
    -------
    t1, t2 : numpy.ndarray, shape (N, 3)
    """
    n = np.asarray(normals, dtype=np.float64)
    a = np.abs(np.nan_to_num(n))
    e = np.zeros_like(n)
    e[np.arange(len(n)), np.argmin(a, axis=1)] = 1.0
    t1 = _unit_rows(np.cross(n, e))
    t2 = np.cross(n, t1)
    return t1, t2


# Edges per block of rows in the row-sorted ball graph (bounds the memory of
# the per-edge temporaries: ~30 arrays of this length for MLS2).
_ROW_BLOCK_EDGES = 1 << 18


class _BallGraph:
    """Strict-ball graph in k-d tree order, stored by rows (CSR).

    ``q = pts[perm]`` (spatially coherent order); row ``i`` holds the
    neighbours of ``q_i`` (``i`` itself included) in
    ``cols[indptr[i]:indptr[i + 1]]``, ``counts[i] = #N_r(q_i)``. Same
    distance test as :func:`moments` (``cKDTree.query_pairs``).
    """

    def __init__(self, pts, r):
        n = len(pts)
        self.n = n
        self.perm = cKDTree(pts, balanced_tree=False).indices
        self.q = pts[self.perm]
        i, j = _ball_pairs(cKDTree(self.q), r)
        self.counts = (1 + np.bincount(i, minlength=n)
                       + np.bincount(j, minlength=n)).astype(np.int32)
        self_ = np.arange(n, dtype=np.intp)
        rows = np.concatenate([i, j, self_])
        cols = np.concatenate([j, i, self_])
        self.cols = cols[np.argsort(rows.astype(np.int32), kind="stable")]
        self.indptr = np.zeros(n + 1, dtype=np.intp)
        np.cumsum(self.counts, out=self.indptr[1:])

    def blocks(self):
        """Yield :class:`_Block` objects covering all rows in order."""
        n, ip = self.n, self.indptr
        r0 = 0
        while r0 < n:
            r1 = int(np.searchsorted(ip, ip[r0] + _ROW_BLOCK_EDGES, side="right")) - 1
            r1 = min(max(r1, r0 + 1), n)
            yield _Block(self, r0, r1)
            r0 = r1


class _Block:
    """Rows ``r0:r1`` of a :class:`_BallGraph` and their edges.

    ``b``: neighbour (column) index of every edge; :meth:`row` broadcasts a
    per-row array to the edges (``np.repeat``); :meth:`sum` adds per-edge
    values over each row (``np.add.reduceat``, every row is non-empty).
    """

    def __init__(self, g, r0, r1):
        self.rows = slice(r0, r1)
        e0, e1 = g.indptr[r0], g.indptr[r1]
        self.b = g.cols[e0:e1]
        self._rep = g.counts[r0:r1]
        self._starts = g.indptr[r0:r1] - e0

    def row(self, arr):
        return np.repeat(arr[..., self.rows], self._rep, axis=-1)

    def sum(self, vals):
        return np.add.reduceat(vals, self._starts, axis=-1)


def _row_mean_cov(g, features):
    """Weighted mean and centred covariance of per-edge features, per row.

    ``features(blk)`` returns ``(w, F)`` for the edges of a block: weights
    ``w`` (E,) and features ``F`` (k, E). Two passes (mean first, then
    centred products). Returns ``wsum`` (n,), ``mean`` (k, n) and
    ``cov`` (n, k, k) ``= sum w (F - mean)(F - mean)^T / sum w``.
    """
    n = g.n
    wsum = np.zeros(n)
    s1 = None
    for blk in g.blocks():
        w, f = features(blk)
        if s1 is None:
            s1 = np.zeros((len(f), n))
        wsum[blk.rows] = blk.sum(w)
        s1[:, blk.rows] = blk.sum(w * f)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / wsum
    k = len(mean)
    iu = [(u, v) for u in range(k) for v in range(u, k)]
    s2 = np.zeros((len(iu), n))
    for blk in g.blocks():
        w, f = features(blk)
        c = f - blk.row(mean)
        prod = np.stack([c[u] * c[v] for u, v in iu])
        s2[:, blk.rows] = blk.sum(w * prod)
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 /= wsum
    cov = np.empty((n, k, k))
    for col, (u, v) in enumerate(iu):
        cov[:, u, v] = s2[col]
        cov[:, v, u] = s2[col]
    return wsum, mean, cov


def _rowdot3(a, b):
    """Column-wise dot products of two ``(3, E)`` stacks."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _eigh_desc(cov, ok):
    """Descending eigenvalues (clipped at 0) and eigenvectors on rows ``ok``."""
    n, k = cov.shape[:2]
    lam = np.full((n, k), np.nan)
    vec = np.full((n, k, k), np.nan)
    if np.any(ok):
        w, v = np.linalg.eigh(cov[ok])
        lam[ok] = np.maximum(w[:, ::-1], 0.0)
        vec[ok] = v[:, :, ::-1]
    return lam, vec


def invert_theorem1(lam1, lam2, radius):
    """Curvature magnitudes from the count-normalised 2dcov1 eigenvalues.

    Theorem 1 (Digne & Morel 2013): ``lam1 -> c (5 k1^2 + 2 k1 k2 + k2^2)``,
    ``lam2 -> c (k1^2 + 2 k1 k2 + 5 k2^2)``, ``c = r^6 / 256``. With
    ``u = lam1 / c``, ``v = lam2 / c`` and ``m = (k1 + k2)^2`` this reads
    ``u = 4 k1^2 + m``, ``v = 4 k2^2 + m``; eliminating gives
    ``32 m^2 - 8 S m + S^2 - 4 u v = 0`` (``S = u + v``), whose two roots
    ``m_pm = (S +- sqrt(8 u v - S^2)) / 8`` are the two sign hypotheses:
    the sign of ``k1 k2`` belonging to a root is that of ``6 m - S``
    (``m_-`` always gives ``k1 k2 <= 0``; ``m_+`` gives ``k1 k2 >= 0`` iff
    ``u/v <= 5``).

    **Sign rule.** Both roots always give non-negative squares (``0 <= m <= v``
    for ``1 <= u/v <= 3 + 2 sqrt 2``), so the data cannot tell the two
    hypotheses apart (e.g. the sphere ``(k, k)`` and the saddle
    ``(sqrt2 k, -sqrt2 k)`` have identical eigenvalues). We always keep the
    larger root ``m_+``: it is the ``k1 k2 >= 0`` solution whenever one
    exists (eigenvalue ratio ``u/v <= 5``: from 1 for an umbilic to 5 for a
    cylinder), and for ``5 < u/v <= 3 + 2 sqrt 2`` (only reachable by
    ``k1 k2 < 0``) the ``k1 k2 < 0`` solution continuous with it. Ratios
    beyond ``3 + 2 sqrt 2`` are not attainable by Theorem 1 (sampling
    error): the discriminant is clipped at 0. Then
    ``|k1| = sqrt(max(u - m, 0) / 4)``, ``|k2| = sqrt(max(v - m, 0) / 4)``.

    Parameters
    ----------
    lam1, lam2 : array_like
        Largest and smallest count-normalised eigenvalues (unit ``L^6``),
        ``lam1 >= lam2 >= 0``.
    radius : float
        Ball radius ``r`` (unit ``L``).

    Returns
    -------
    k1, k2 : numpy.ndarray
        Magnitudes ``|k1| >= |k2| >= 0`` (unit ``1/L``).
    """
    c = float(radius) ** 6 / 256.0
    u = np.asarray(lam1, dtype=np.float64) / c
    v = np.asarray(lam2, dtype=np.float64) / c
    s = u + v
    m = (s + np.sqrt(np.maximum(8.0 * u * v - s * s, 0.0))) / 8.0
    return np.sqrt(np.maximum(u - m, 0.0) / 4.0), np.sqrt(np.maximum(v - m, 0.0) / 4.0)


def _empty_cov(method):
    k = 3 if method == "3dcov" else 2
    return {"count": np.empty(0, dtype=np.int32), "status": np.empty(0, dtype=np.uint8),
            "eigenvalues": np.empty((0, k)), "k1": np.empty(0), "k2": np.empty(0),
            "dir1": np.empty((0, 3)), "dir2": np.empty((0, 3))}


def covariance_ops(points, radius, normals, method, weights="uniform"):
    """Normal-based covariance curvature operators 2dcov1, 2dcov2 and 3dcov.

    For every point ``p`` with unit outward normal ``n``, tangent basis
    ``(t1, t2)`` (:func:`tangent_frame`), strict-ball neighbourhood
    ``N_r(p)`` (``p`` included, ``n_p = #N_r(p)`` points) and weights ``w_i``
    (1, or ``1 / #N_r(q_i)`` for ``weights="density"``), a feature ``f_i`` is
    formed for each neighbour ``q_i`` (normal ``n_i``):

    * ``"2dcov1"`` (Berkmann & Caelli; paper operator 1):
      ``s_i = <q_i - p, n>``,
      ``f_i = s_i (<q_i - p, t1>, <q_i - p, t2>)`` (2D, unit ``L^2``);
    * ``"2dcov2"`` (operator 2, PCL's PrincipalCurvaturesEstimation):
      ``f_i = (<n_i, t1>, <n_i, t2>)``, the projection of ``n_i`` on the
      tangent plane at ``p`` (2D, dimensionless);
    * ``"3dcov"`` (operator 3): ``f_i = n_i`` (3D; the normals must already
      be consistently oriented, which outward normals are).

    **Count normalisation.** The reported eigenvalues are those of

        ``C = sum_i w_i (f_i - f_mean)(f_i - f_mean)^T / sum_i w_i``,
        ``f_mean = sum_i w_i f_i / sum_i w_i``,

    i.e. the weighted scatter matrix ``Sigma_w = sum_i w_i (f_i - f_mean)
    (f_i - f_mean)^T`` divided by ``n_p * w_mean`` where ``w_mean =
    sum_i w_i / n_p`` is the mean weight. For uniform weights this is exactly
    ``Sigma / n_p``, the count-normalised quantity of the paper's Theorems
    1-3 (population covariance, divisor ``n_p``, not ``n_p - 1``). For
    2dcov2 with uniform weights the two eigenvalues equal PCL's ``pc1`` and
    ``pc2`` (``principal_curvatures.hpp``: ``covariance_matrix_`` is the
    *unnormalised* 3x3 scatter of the projected normals ``(I - n n^T) n_i``
    about their mean, and ``pc1 = eigenvalues_[2] / indices.size()``,
    ``pc2 = eigenvalues_[1] / indices.size()``; the 3x3 scatter of tangent
    vectors has the same non-zero eigenvalues as our 2x2 one).

    **Curvatures.**

    * 2dcov1: Theorem 1, ``lam1, lam2 -> r^6/256 (5 k1^2 + 2 k1 k2 + k2^2),
      r^6/256 (k1^2 + 2 k1 k2 + 5 k2^2)``, inverted by
      :func:`invert_theorem1` (sign rule documented there: keep the
      ``k1 k2 >= 0`` hypothesis when it exists). ``dir1`` = eigenvector of
      the largest eigenvalue (the direction of the larger ``|k|``).
    * 2dcov2 and 3dcov: Theorems 2 and 3, ``lam_j -> k_j^2 r^2 / 4``, so
      ``|k_j| = (2 / r) sqrt(lam_j)`` with ``lam1 >= lam2`` the two largest
      eigenvalues of ``C``. ``dir1`` = eigenvector of ``lam1`` (3dcov:
      projected on the tangent plane at ``p`` and normalised; if that
      projection is shorter than 1e-3, i.e. a flat neighbourhood where the
      direction is meaningless, ``t1`` is used).

    In every case 2D eigenvectors ``(a, b)`` map to ``a t1 + b t2`` and
    ``dir2 = n x dir1`` (so ``(dir1, dir2, n)`` is a right-handed orthonormal
    frame).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates (unit ``L``), finite.
    radius : float
        Ball radius ``r`` (unit ``L``, > 0), strict ball.
    normals : array_like, shape (N, 3)
        Oriented (outward) unit normals at every point.
    method : {"2dcov1", "2dcov2", "3dcov"}
    weights : {"uniform", "density"}, optional

    Returns
    -------
    dict
        ``"count"`` int32 (N,): ``#N_r(p)``, ``p`` included.
        ``"status"`` uint8 (N,): 0 ok; 1 too few neighbours (``count < 3``);
        2 degenerate: the normal at ``p`` (2dcov1) or a normal in the ball
        (2dcov2, 3dcov) is invalid (non-finite or zero).
        ``"eigenvalues"`` float64 (N, 2) (2dcov1: unit ``L^6``; 2dcov2:
        dimensionless) or (N, 3) (3dcov, dimensionless): descending
        eigenvalues of ``C`` (round-off negatives clipped to 0).
        ``"k1"``, ``"k2"`` float64 (N,): magnitudes ``k1 >= k2 >= 0``
        (unit ``1/L``).
        ``"dir1"``, ``"dir2"`` float64 (N, 3): unit tangent directions of
        ``k1`` and ``k2``, orthogonal.
        NaN in every float64 output where ``status != 0``.
    """
    if method not in COV_METHODS:
        raise ValueError(f"method must be one of {COV_METHODS}, got {method!r}")
    if weights not in _WEIGHTS:
        raise ValueError(f"weights must be one of {_WEIGHTS}, got {weights!r}")
    pts = _as_points(points)
    r = _as_radius(radius)
    n = len(pts)
    nrm_in = _as_normals(normals, n)
    if n == 0:
        return _empty_cov(method)

    g = _BallGraph(pts, r)
    perm, counts_q = g.perm, g.counts
    nrm = nrm_in[perm]
    t1, t2 = tangent_frame(nrm)
    wpt = _point_weights(counts_q, weights)
    x = g.q.T.copy()
    nt, t1t, t2t = nrm.T.copy(), t1.T.copy(), t2.T.copy()

    if method == "2dcov1":
        def features(blk):
            d = x[:, blk.b] - blk.row(x)
            s = _rowdot3(d, blk.row(nt))
            return wpt[blk.b], np.stack([s * _rowdot3(d, blk.row(t1t)),
                                         s * _rowdot3(d, blk.row(t2t))])
    elif method == "2dcov2":
        def features(blk):
            nb = nt[:, blk.b]
            return wpt[blk.b], np.stack([_rowdot3(nb, blk.row(t1t)),
                                         _rowdot3(nb, blk.row(t2t))])
    else:
        def features(blk):
            # shifted by n(p): same covariance, smaller magnitudes
            return wpt[blk.b], nt[:, blk.b] - blk.row(nt)

    _, _, cov = _row_mean_cov(g, features)
    enough = counts_q >= MIN_COUNT
    finite = np.all(np.isfinite(cov.reshape(n, -1)), axis=1)
    lam, vec = _eigh_desc(cov, enough & finite)

    if method == "3dcov":
        e1 = vec[:, :, 0]
        p1 = e1 - np.einsum("ij,ij->i", e1, nrm)[:, None] * nrm
        length = np.sqrt(np.einsum("ij,ij->i", p1, p1))
        with np.errstate(invalid="ignore"):
            flat = length < 1e-3
            dir1 = p1 / np.where(flat, 1.0, length)[:, None]
        dir1[flat] = t1[flat]
    else:
        dir1 = vec[:, 0, 0][:, None] * t1 + vec[:, 1, 0][:, None] * t2
    dir2 = np.cross(nrm, dir1)

    if method == "2dcov1":
        k1, k2 = invert_theorem1(lam[:, 0], lam[:, 1], r)
    else:
        k1 = 2.0 / r * np.sqrt(lam[:, 0])
        k2 = 2.0 / r * np.sqrt(lam[:, 1])

    status = np.zeros(n, dtype=np.uint8)
    status[~finite | ~np.all(np.isfinite(nrm), axis=1)] = STATUS_DEGENERATE
    status[~enough] = STATUS_TOO_FEW
    out = {"count": counts_q, "status": status, "eigenvalues": lam,
           "k1": k1, "k2": k2, "dir1": dir1, "dir2": dir2}
    return _unpermute_nan(out, perm)


def _unpermute_nan(out, perm):
    """Back to input order (``res[perm] = out``); NaN float rows where status != 0."""
    res = {}
    for key, val in out.items():
        arr = np.empty_like(val)
        arr[perm] = val
        res[key] = arr
    bad = res["status"] != STATUS_OK
    for key, arr in res.items():
        if arr.dtype == np.float64:
            arr[bad] = np.nan
    return res


def _eigvec_2x2(s11, s12, s21, s22, lam):
    """Eigenvector ``(a, b)`` of the 2x2 matrix ``[[s11, s12], [s21, s22]]``
    for the eigenvalue ``lam`` (not normalised): the longer of the vectors
    orthogonal to the two rows of ``S - lam I``; ``(1, 0)`` when both vanish
    (``S = lam I``, an umbilic, where every direction is principal)."""
    va = np.stack([s12, lam - s11], axis=-1)
    vb = np.stack([lam - s22, s21], axis=-1)
    na = np.einsum("ij,ij->i", va, va)
    nb = np.einsum("ij,ij->i", vb, vb)
    v = np.where((na >= nb)[:, None], va, vb)
    scale = s11 ** 2 + s22 ** 2 + s12 ** 2 + s21 ** 2
    tiny = np.maximum(na, nb) <= 1e-28 * scale
    tiny |= np.maximum(na, nb) == 0.0
    v[tiny] = (1.0, 0.0)
    return v


def _empty_mls2():
    e1, e3 = np.empty(0), np.empty((0, 3))
    return {"count": np.empty(0, dtype=np.int32), "status": np.empty(0, dtype=np.uint8),
            "points": e3, "k1": e1, "k2": e1.copy(), "dir1": e3.copy(), "dir2": e3.copy(),
            "mean": e1.copy(), "gaussian": e1.copy(), "normals": e3.copy()}


def mls2(points, radius, normals, weights="uniform", kernel="ball", h=None):
    """MLS2: local quadratic height fit (paper operator 7), signed curvatures.

    For every point ``p`` with neighbourhood ``N_r(p)`` (strict ball, ``p``
    included, ``n_p`` points) and neighbour weights ``w_i``:

    1. Weighted PCA of the ball: barycenter ``o``, centred covariance
       ``sum w_i (q_i - o)(q_i - o)^T / sum w_i``, ``v0`` = eigenvector of the
       smallest eigenvalue, flipped so that ``<v0, n> > 0`` (``n`` the given
       oriented normal at ``p``).
    2. ``Q = p - <p - o, v0> v0`` (projection on the regression plane) and the
       frame ``(t1, t2, v0)``, ``(t1, t2) = tangent_frame(v0)``.
    3. Heights ``h_i = <q_i - Q, v0>`` and scaled coordinates
       ``x_i = <q_i - Q, t1> / r``, ``y_i = <q_i - Q, t2> / r``; weighted
       least squares of
       ``g = a00 + a10 x + a01 y + a20 x^2 + a11 x y + a02 y^2`` through the
       6x6 normal equations ``A a = b``, ``A = sum w phi phi^T``,
       ``b = sum w h phi``, ``phi = (1, x, y, x^2, x y, y^2)``. ``A`` is
       *singular* (status 3) when its smallest singular value is
       ``<= SINGULAR_RCOND * `` its largest (1e-10).
    4. Unscaled derivatives at the origin (unit ``L``): ``gx = a10 / r``,
       ``gy = a01 / r``, ``gxx = 2 a20 / r^2``, ``gxy = a11 / r^2``,
       ``gyy = 2 a02 / r^2``.
    5. Projection ``Q + a00 v0``; fitted normal
       ``(-gx t1 - gy t2 + v0) / sqrt(1 + gx^2 + gy^2)`` (outward, as ``v0``).
    6. Shape operator ``S = I^-1 II`` with
       ``I = [[1 + gx^2, gx gy], [gx gy, 1 + gy^2]]``,
       ``II = [[gxx, gxy], [gxy, gyy]] / sqrt(1 + gx^2 + gy^2)``.
       The height is measured along the *outward* ``v0``, so a sphere is a
       concave graph: clcurv's curvatures are ``k = -eigenvalues(S)``
       (sphere of radius R: ``k1 = k2 = +1/R``), ``k1 >= k2``,
       ``mean = (k1 + k2) / 2 = -tr(S) / 2``, ``gaussian = k1 k2 = det S``.
       ``dir1``: the eigenvector ``(a, b)`` of ``S`` for the eigenvalue
       ``-k1``, mapped to ``a (t1 + gx v0) + b (t2 + gy v0)`` and normalised
       (at an umbilic, ``S = -k I``, ``(a, b) = (1, 0)``);
       ``dir2 = normal x dir1`` (so ``(dir1, dir2, normal)`` is right-handed
       and orthonormal; the eigenvectors of ``S`` are ``I``-orthogonal, so
       this is the direction of ``k2``).

    Offsets are formed relative to ``p`` (translation safe).

    Weights ``w_i`` (used for both the PCA and the fit):
    ``kernel="ball"``: 1 for every neighbour in the ball;
    ``kernel="gaussian"``: ``exp(-d_i^2 / h^2)``, ``d_i = |q_i - p|``, with
    ``h = r / 2`` by default (the weight at the ball's rim is
    ``exp(-4) = 0.018``); neighbours are still limited to the strict ball.
    With ``weights="density"`` both are multiplied by ``1 / #N_r(q_i)``.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates (unit ``L``), finite.
    radius : float
        Ball radius ``r`` (unit ``L``, > 0).
    normals : array_like, shape (N, 3)
        Oriented (outward) normals; only used to orient ``v0``.
    weights : {"uniform", "density"}, optional
    kernel : {"ball", "gaussian"}, optional
    h : float, optional
        Gaussian width (unit ``L``, > 0); default ``r / 2``. Ignored for the
        ball kernel.

    Returns
    -------
    dict
        ``"count"`` int32 (N,): ``#N_r(p)``.
        ``"status"`` uint8 (N,): 0 ok; 1 ``count < 6``; 2 degenerate PCA
        (middle eigenvalue ``<= 1e-10 *`` the largest, or the largest is 0:
        e.g. collinear neighbours), or an invalid normal at ``p``, or
        ``<v0, n> = 0``; 3 singular 6x6 system.
        ``"points"`` (N, 3): MLS2 projection of ``p`` (unit ``L``).
        ``"k1"``, ``"k2"`` (N,): signed principal curvatures, ``k1 >= k2``
        (unit ``1/L``).
        ``"dir1"``, ``"dir2"`` (N, 3): unit principal directions.
        ``"mean"`` (N,): ``H`` (``1/L``); ``"gaussian"`` (N,): ``K``
        (``1/L^2``).
        ``"normals"`` (N, 3): unit fitted normals, outward.
        NaN in every float64 output where ``status != 0``.
    """
    if weights not in _WEIGHTS:
        raise ValueError(f"weights must be one of {_WEIGHTS}, got {weights!r}")
    if kernel not in _KERNELS:
        raise ValueError(f"kernel must be one of {_KERNELS}, got {kernel!r}")
    pts = _as_points(points)
    r = _as_radius(radius)
    hh = r / 2.0 if h is None else _as_radius(h)
    n = len(pts)
    nrm_in = _as_normals(normals, n)
    if n == 0:
        return _empty_mls2()

    g = _BallGraph(pts, r)
    perm, q, counts = g.perm, g.q, g.counts
    nrm = nrm_in[perm]
    wpt = _point_weights(counts, weights)
    x = q.T.copy()
    inv_h2 = 1.0 / (hh * hh)

    def edge_weights(blk, d):
        if kernel == "ball":
            return wpt[blk.b]
        return wpt[blk.b] * np.exp(-_rowdot3(d, d) * inv_h2)

    def offsets(blk):
        d = x[:, blk.b] - blk.row(x)
        return edge_weights(blk, d), d

    # 1. weighted PCA (offsets d = q - p, so mean = o - p)
    wsum, m, cov = _row_mean_cov(g, offsets)
    enough = counts >= MIN_COUNT_MLS2
    lam = np.full((n, 3), np.nan)
    v0 = np.full((n, 3), np.nan)
    if np.any(enough):
        w_, v_ = np.linalg.eigh(cov[enough])
        lam[enough] = np.maximum(w_, 0.0)
        v0[enough] = v_[:, :, 0]
    with np.errstate(invalid="ignore"):
        degenerate = (lam[:, 2] == 0.0) | (lam[:, 1] <= RANK_TOL * lam[:, 2])
        side = np.einsum("ij,ij->i", v0, nrm)
        degenerate |= ~(np.abs(side) > 0.0)      # invalid normal or <v0, n> = 0
    v0 *= np.where(side < 0.0, -1.0, 1.0)[:, None]
    status = np.zeros(n, dtype=np.uint8)
    status[enough & degenerate] = STATUS_DEGENERATE
    status[~enough] = STATUS_TOO_FEW
    good = status == STATUS_OK
    v0[~good] = np.nan

    # 2. frame at Q = p + sq v0, sq = <o - p, v0>
    t1, t2 = tangent_frame(v0)
    sq = np.einsum("ij,ji->i", v0, m)
    # offset of Q from p, and the frame, per row (NaN rows give NaN sums)
    qoff = (sq[:, None] * v0).T.copy()
    v0t, t1t, t2t = v0.T.copy(), t1.T.copy(), t2.T.copy()
    inv_r = 1.0 / r

    # 3. normal equations: 21 + 6 weighted sums per row
    iu = [(u, v) for u in range(6) for v in range(u, 6)]
    sa = np.zeros((len(iu), n))
    sb = np.zeros((6, n))
    for blk in g.blocks():
        d = x[:, blk.b] - blk.row(x)
        w = edge_weights(blk, d)
        e = d - blk.row(qoff)
        hgt = _rowdot3(e, blk.row(v0t))
        xs = _rowdot3(e, blk.row(t1t)) * inv_r
        ys = _rowdot3(e, blk.row(t2t)) * inv_r
        phi = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys])
        wphi = w * phi
        sa[:, blk.rows] = blk.sum(np.stack([wphi[u] * phi[v] for u, v in iu]))
        sb[:, blk.rows] = blk.sum(wphi * hgt)
    amat = np.empty((n, 6, 6))
    for col, (u, v) in enumerate(iu):
        amat[:, u, v] = sa[col]
        amat[:, v, u] = sa[col]

    coef = np.full((n, 6), np.nan)
    if np.any(good):
        idx = np.flatnonzero(good)
        sv = np.linalg.svd(amat[idx], compute_uv=False)
        singular = ~(sv[:, -1] > SINGULAR_RCOND * sv[:, 0])
        status[idx[singular]] = STATUS_SINGULAR
        idx = idx[~singular]
        if len(idx):
            coef[idx] = np.linalg.solve(amat[idx], sb[:, idx].T[:, :, None])[:, :, 0]
    good = status == STATUS_OK
    coef[~good] = np.nan

    # 4. derivatives, projection, normal, shape operator
    a00, a10, a01, a20, a11, a02 = coef.T
    gx, gy = a10 * inv_r, a01 * inv_r
    gxx, gxy, gyy = 2.0 * a20 * inv_r ** 2, a11 * inv_r ** 2, 2.0 * a02 * inv_r ** 2
    proj = q + (sq + a00)[:, None] * v0
    wn = np.sqrt(1.0 + gx * gx + gy * gy)
    normal = (v0 - gx[:, None] * t1 - gy[:, None] * t2) / wn[:, None]
    e_, f_, g_ = 1.0 + gx * gx, gx * gy, 1.0 + gy * gy
    l_, m_, n_ = gxx / wn, gxy / wn, gyy / wn
    det_i = e_ * g_ - f_ * f_
    # S = I^-1 II
    s11 = (g_ * l_ - f_ * m_) / det_i
    s12 = (g_ * m_ - f_ * n_) / det_i
    s21 = (e_ * m_ - f_ * l_) / det_i
    s22 = (e_ * n_ - f_ * m_) / det_i
    half_tr = 0.5 * (s11 + s22)
    det_s = (l_ * n_ - m_ * m_) / det_i
    disc = np.sqrt(np.maximum(0.25 * (s11 - s22) ** 2 + s12 * s21, 0.0))
    k1 = -half_tr + disc
    k2 = -half_tr - disc
    ab = _eigvec_2x2(s11, s12, s21, s22, -k1)
    dir1 = _unit_rows(ab[:, :1] * (t1 + gx[:, None] * v0)
                      + ab[:, 1:] * (t2 + gy[:, None] * v0))
    dir2 = np.cross(normal, dir1)

    out = {"count": counts, "status": status, "points": proj, "k1": k1, "k2": k2,
           "dir1": dir1, "dir2": dir2, "mean": -half_tr, "gaussian": det_s,
           "normals": normal}
    with np.errstate(invalid="ignore"):
        return _unpermute_nan(out, perm)


def mls2_iterate(points, radius, normals, iterations, **kw):
    """Apply the MLS2 projection ``iterations`` times to the whole cloud.

    Each iteration calls :func:`mls2` on the current cloud (neighbourhoods
    recomputed on the moved points) and moves every point with status 0 to
    its projection; points with a non-zero status stay where they are for
    that iteration. The orientation normals are then re-estimated as the
    (uniform-ball, :func:`moments`) PCA normals of the moved cloud, flipped to
    agree with the previous iterate's normals (dot >= 0); where the PCA
    normal is undefined the previous normal is kept.

    Parameters
    ----------
    points, radius, normals :
        As for :func:`mls2` (``normals`` oriented outward).
    iterations : int
        Number of projections (>= 0; 0 returns a copy of ``points``).
    **kw :
        ``weights``, ``kernel``, ``h``, passed to :func:`mls2` (``weights``
        also to the PCA normal re-estimation).

    Returns
    -------
    dict
        ``"points"`` (N, 3): the final points (unit ``L``).
        ``"status"`` uint8 (N,): the first non-zero :func:`mls2` status met
        by the point over the iterations (0 if it was always projected).
        ``"normals"`` (N, 3): the final oriented PCA normals.
        NaN in ``points`` and ``normals`` where ``status != 0``.
    """
    it = int(iterations)
    if it != iterations or it < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    cur = _as_points(points).copy()
    r = _as_radius(radius)
    nrm = _as_normals(normals, len(cur))
    status = np.zeros(len(cur), dtype=np.uint8)
    for _ in range(it):
        res = mls2(cur, r, nrm, **kw)
        ok = res["status"] == STATUS_OK
        first = (status == STATUS_OK) & ~ok
        status[first] = res["status"][first]
        cur[ok] = res["points"][ok]
        pca = moments(cur, r, kw.get("weights", "uniform"))["normals"]
        with np.errstate(invalid="ignore"):
            flip = np.einsum("ij,ij->i", pca, nrm) < 0.0
        pca[flip] *= -1.0
        keep = ~np.all(np.isfinite(pca), axis=1)
        pca[keep] = nrm[keep]
        nrm = pca
    bad = status != STATUS_OK
    cur[bad] = np.nan
    nrm[bad] = np.nan
    return {"points": cur, "status": status, "normals": nrm}


def scale_space(points, radius, iterations, weights="uniform"):
    """Float64 MLS1 scale space: ``iterations`` projections p <- p - <p - o, v0> v0 of every
    point on the weighted PCA plane of its ball, all points together, neighbourhoods
    recomputed on the moved cloud each time; points with status != 0 stay. Returns the
    list of the iterates (input first), each (N, 3) float64."""
    pts = np.array(points, dtype=np.float64)
    out = [pts.copy()]
    for _ in range(int(iterations)):
        m = moments(pts, radius, weights=weights)
        ok = m["status"] == STATUS_OK
        n = m["normals"][ok]
        along = np.einsum("ij,ij->i", m["shift"][ok], n)
        pts = pts.copy()
        pts[ok] += along[:, None] * n
        out.append(pts.copy())
    return out
