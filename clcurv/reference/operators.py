"""Independent float64 reference ("oracle") of the clcurv operators (Digne & Morel 2013).

The host-side ground truth the OpenCL kernels are checked against: NumPy and SciPy only,
float64 throughout, clarity and numerical care before speed (still ~10^5 points in
seconds, and ~10^6 in memory bounded by blocks).

What is shared with the kernel path, and what is not
----------------------------------------------------
``clcurv.curvature(..., backend="numpy")`` (and :func:`clcurv.normals`) runs this module
for every step that decides a result:

* the operators (:func:`moments`, :func:`covariance_ops`, :func:`mls2`,
  :func:`scale_space`), never a kernel;
* the finishing step from the operator's fields to the result (:func:`finish`: MLS0's and
  MLS1's H and points, MLS2's H and K from the shape operator's trace and determinant),
  not the kernel path's ``clcurv.ops.registry._finish_*``;
* the orientation (:func:`orientation_flips`, :func:`mst_flips`: the sign of every
  normal, so of H, k1, k2, K), not :mod:`clcurv.orient.orientation` (whose ``flip_by_propagation``
  is the host twin of the device's forest, and shares ``component_signs`` with it).
  The kernel path's ``_flip_mls2`` (MLS2 fitted first, its normals flipped afterwards)
  has no counterpart here: the numpy backend orients the PCA normals first and fits
  with them, so a wrong flip shows as a difference between the backends.

Shared (not independent): the input checks and normalisation of the normals
(:mod:`clcurv._shared.validate`), the choice of orientation an ``orient`` value stands for
(``clcurv.api.curvature._orientation``), the status codes and minimum counts
(:mod:`clcurv._shared.constants`), the result container (:class:`clcurv.api.result.CurvatureResult`),
the registry's adapters that rename fields (``clcurv.ops.registry._ref_*``: the MLS2
projection handed over as ``shift``), the loop of ``projections`` (``clcurv.api.curvature._project``)
and, in :func:`clcurv.api.features`, the step that turns normals towards ``orient='up'`` (its
float64 features are :mod:`clcurv.reference.features`). The definitions
(strict balls, weights, the tangent frame's rule, the orientation graph's neighbours and
weights) are the same by specification, written twice. tests/test_reference_independent.py
checks both sides' finishing, MLS2 flip and orientation against exact values.

Engine
------
Every operator runs on one ball-neighbourhood engine, in the steps of the kernels
(``kernels/neighbors.h``, ``weights.h``, ``pca.h``):

1. neighbourhoods -- :class:`_Ball`: the strict balls as a row-sorted graph in k-d tree
   order, walked in blocks of whole rows of bounded edge count (:class:`_Block`);
2. weights -- :func:`_edge_weights`: uniform or density, times the Gaussian MLS2 kernel;
3. weighted moments -- :func:`_row_sums` (per-point sums of per-neighbour values, block by
   block) and :func:`_mean_cov` (weighted mean and centred covariance of features);
4. per-point finish -- :func:`_eigh`, :func:`_pca` (eigen decomposition, status) and
   :func:`_finish` (back to input order, NaN where the status is not OK).

Conventions
-----------
* ``points`` is ``(N, 3)`` in an arbitrary length unit ``L``; ``radius`` is in ``L``.
* The neighbourhood of ``p`` is the open ball ``N_r(p) = {q : |q - p| < r}``, ``p``
  included (paper Section 2, as the kernels). ``scipy.spatial.cKDTree`` tests ``<=``, so it
  is queried with ``np.nextafter(r, 0)``: distances exactly ``r`` (as the k-d tree computes
  them in float64) are excluded. ``query_ball_point`` (:func:`ball_neighbors`,
  :func:`neighbor_counts`) and ``query_pairs`` (the engine) apply the same distance test, so
  the neighbourhoods agree exactly. Offsets ``q - p`` are formed relative to ``p``
  (translation safe).
* Weights: ``"uniform"`` gives every neighbour weight 1 (the case of the paper's theorems);
  ``"density"`` gives neighbour ``q`` the weight ``1 / #N_r(q)`` (Section 3).
* Normals: :func:`moments` returns **unoriented** PCA normals (sign as ``numpy.linalg.eigh``
  gives it; :mod:`clcurv.orient.orientation` orients them). :func:`mls2` and :func:`mls2_iterate` take
  normals **oriented outward** (user normals or oriented PCA normals); :func:`covariance_ops`
  uses the normals as given, or, with ``align=True``, takes normals of any signs (it then
  aligns each neighbour's with its query point's). They are normalised again here; a
  non-finite or zero row is invalid.
* Curvature sign (clcurv): outward normals, a surface bending away from its normal is
  positive (sphere of radius R: ``k1 = k2 = H = +1/R``, ``K = 1/R^2``), ``k1 >= k2``.
  :func:`covariance_ops` returns magnitudes ``k1 >= k2 >= 0``, :func:`mls2` signed values.
* Eigenvalue order: :func:`moments` ascending ``l0 <= l1 <= l2``; :func:`covariance_ops`
  descending. Round-off negatives are clipped to 0.
* Status codes (:mod:`clcurv._shared.constants`, as the kernels): ``OK`` 0; ``TOO_FEW`` 1 (fewer
  than ``MIN_COUNT_PCA`` = 3 neighbours, ``MIN_COUNT_MLS2`` = 6 for MLS2); ``DEGENERATE`` 2
  (covariance of rank < 2: ``l1 <= RANK_TOL * l2`` or ``l2 == 0``, or an invalid normal);
  ``SINGULAR`` 3 (MLS2 system). Every float64 output is NaN where the status is not OK.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import (breadth_first_order, connected_components,
                                  minimum_spanning_tree)
from scipy.spatial import cKDTree

from clcurv._shared.options import choices
from clcurv._shared.constants import (DEGENERATE, MIN_COUNT_MLS2, MIN_COUNT_PCA, OK, SINGULAR,
                                      TOO_FEW)

__all__ = ["OK", "TOO_FEW", "DEGENERATE", "SINGULAR", "MIN_COUNT_PCA", "MIN_COUNT_MLS2",
           "STATUS_OK", "STATUS_TOO_FEW", "STATUS_DEGENERATE", "STATUS_SINGULAR", "MIN_COUNT",
           "RANK_TOL", "SINGULAR_RCOND", "COV_METHODS", "ball_neighbors", "neighbor_counts",
           "moments", "tangent_frame", "covariance_ops", "invert_theorem1", "mls2",
           "mls2_iterate", "scale_space", "finish", "orientation_flips", "mst_flips"]

# Former names of the shared constants (clcurv._shared.constants).
STATUS_OK, STATUS_TOO_FEW, STATUS_DEGENERATE, STATUS_SINGULAR = OK, TOO_FEW, DEGENERATE, SINGULAR
MIN_COUNT = MIN_COUNT_PCA

#: Relative threshold on the middle eigenvalue below which a covariance has rank < 2.
RANK_TOL = 1e-10
#: The 6x6 MLS2 normal equations are singular when their smallest singular value is
#: <= SINGULAR_RCOND times the largest (coordinates scaled by 1/r).
SINGULAR_RCOND = 1e-10
COV_METHODS = ("2dcov1", "2dcov2", "3dcov")
_WEIGHTS = choices("weights")     # the options' declaration (clcurv._shared.options)
_KERNELS = choices("kernel")
# Edges per block of rows: bounds the per-edge temporaries (~30 arrays this long for MLS2).
_BLOCK_EDGES = 1 << 16


# --- input validation ---
def _as_cloud(points, radius):
    """``points`` as a C-contiguous float64 ``(N, 3)`` array and ``radius`` as a positive
    float (ValueError if the shape is wrong or a value is not finite)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain non-finite coordinates")
    return pts, _as_radius(radius)


def _as_radius(radius):
    """``radius`` as a positive finite Python float."""
    r = float(radius)
    if not (np.isfinite(r) and r > 0.0):
        raise ValueError(f"radius must be positive and finite, got {radius!r}")
    return r


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


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


def _empty(*columns):
    """Result of an empty cloud: count, status and float64 ``(name, width)`` columns
    (width 0: one value per point)."""
    out = {"count": np.empty(0, dtype=np.int32), "status": np.empty(0, dtype=np.uint8)}
    for name, width in columns:
        out[name] = np.empty((0, width) if width else 0)
    return out


# --- small geometric helpers ---
def _unit_rows(v):
    """Rows of ``v`` divided by their Euclidean norm."""
    return v / np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]


def _rowdot3(a, b):
    """Column-wise dot products of two ``(3, E)`` stacks."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _upper(k):
    """Index pairs ``(u, v)``, ``u <= v``, of the upper triangle of a ``k x k`` matrix."""
    return [(u, v) for u in range(k) for v in range(u, k)]


def _symmetric(packed, k):
    """``(n, k, k)`` symmetric matrices from their :func:`_upper` rows ``packed`` (m, n)."""
    out = np.empty((packed.shape[1], k, k))
    for col, (u, v) in enumerate(_upper(k)):
        out[:, u, v] = packed[col]
        out[:, v, u] = packed[col]
    return out


def tangent_frame(normals):
    """Deterministic orthonormal tangent basis ``(t1, t2)`` with ``t1 x t2 = n``.

    ``t1`` is ``n x e`` normalised, ``e`` being the coordinate axis least aligned with ``n``
    (the first such axis on ties); ``t2 = n x t1``, so ``t1 x t2 = t1 x (n x t1) = n``
    (``kernels/frame.h`` uses the same rule). ``normals`` (N, 3): unit normals, NaN rows
    give NaN frames. Returns ``t1, t2``, each (N, 3), dimensionless.
    """
    n = np.asarray(normals, dtype=np.float64)
    a = np.abs(np.nan_to_num(n))
    e = np.zeros_like(n)
    e[np.arange(len(n)), np.argmin(a, axis=1)] = 1.0
    t1 = _unit_rows(np.cross(n, e))
    t2 = np.cross(n, t1)
    return t1, t2


# --- engine, step 1: neighbourhoods ---
def _strict(radius):
    """Largest float64 below ``radius``: turns the k-d tree's ``<=`` into ``<``."""
    return float(np.nextafter(radius, 0.0))


def _query_ball(points, radius, **kw):
    """``cKDTree.query_ball_point`` of every point in its strict ball (None if empty)."""
    pts, r = _as_cloud(points, radius)
    if len(pts) == 0:
        return None
    return cKDTree(pts).query_ball_point(pts, _strict(r), workers=-1, **kw)


def ball_neighbors(points, radius):
    """Neighbour index lists of every point: ``result[i]`` holds, in increasing order, the
    indices ``j`` with ``|points[j] - points[i]| < radius``, ``i`` itself included.
    ``points`` (N, 3) and ``radius`` (> 0) in the same length unit ``L``."""
    lists = _query_ball(points, radius, return_sorted=True)
    return [] if lists is None else [list(x) for x in lists]


def neighbor_counts(points, radius):
    """``#N_r(p)`` of every point, ``p`` included (so >= 1), as int32 (N,); ``points``
    (N, 3) and ``radius`` (> 0) in the same length unit ``L``, strict ball."""
    counts = _query_ball(points, radius, return_length=True)
    return np.empty(0, dtype=np.int32) if counts is None else np.asarray(counts, dtype=np.int32)


class _Ball:
    """The strict balls of every point, ``p`` included, as a row-sorted graph (CSR).

    Points are taken in k-d tree order ``q = pts[perm]`` (spatially coherent, so the
    gathers stay in cache; :func:`_finish` permutes back). Row ``i`` lists the neighbours
    of ``q_i`` in ``cols[indptr[i]:indptr[i + 1]]``; ``counts[i] = #N_r(q_i)``; ``x`` holds
    the coordinates as a ``(3, n)`` stack. The pairs come from ``cKDTree.query_pairs`` with
    the same distance test as :func:`ball_neighbors`.
    """

    def __init__(self, pts, r):
        n = self.n = len(pts)
        self.perm = cKDTree(pts, balanced_tree=False).indices
        self.q = pts[self.perm]
        self.x = self.q.T.copy()
        pairs = cKDTree(self.q).query_pairs(_strict(r), output_type="ndarray")
        i, j = pairs.T.astype(np.int32)          # i < j, each pair once (tree order)
        self.counts = (1 + np.bincount(i, minlength=n)
                       + np.bincount(j, minlength=n)).astype(np.int32)
        own = np.arange(n, dtype=np.int32)
        del pairs
        order = np.argsort(np.concatenate([i, j, own]), kind="stable")
        self.cols = np.concatenate([j, i, own])[order]
        self.indptr = np.zeros(n + 1, dtype=np.intp)
        np.cumsum(self.counts, out=self.indptr[1:])

    def blocks(self):
        """:class:`_Block` objects covering all rows in order, ~``_BLOCK_EDGES`` edges each."""
        n, ip = self.n, self.indptr
        r0 = 0
        while r0 < n:
            r1 = int(np.searchsorted(ip, ip[r0] + _BLOCK_EDGES, side="right")) - 1
            r1 = min(max(r1, r0 + 1), n)
            yield _Block(self, r0, r1)
            r0 = r1


class _Block:
    """Rows ``r0:r1`` of a :class:`_Ball` and their edges (every row holds its own point).

    ``b``: neighbour index of every edge; ``d``: offsets ``q - p`` (3, E), ``p`` the row's
    point; per-point arrays (last axis n) seen on the edges: :meth:`nb` at the neighbour
    ``q``, :meth:`row` at ``p``; :meth:`sum` adds per-edge values over each row.
    """

    def __init__(self, ball, r0, r1):
        self.rows = slice(r0, r1)
        e0, e1 = ball.indptr[r0], ball.indptr[r1]
        self.b = ball.cols[e0:e1]
        self._rep = ball.counts[r0:r1]
        self._starts = ball.indptr[r0:r1] - e0
        self._x = ball.x

    @cached_property
    def d(self):
        return self.nb(self._x) - self.row(self._x)

    def nb(self, arr):
        return np.take(arr, self.b, axis=-1)

    def row(self, arr):
        return np.repeat(arr[..., self.rows], self._rep, axis=-1)

    def sum(self, vals):
        return np.add.reduceat(vals, self._starts, axis=-1)


# --- engine, step 2: weights ---
def _edge_weights(ball, weights, kernel="ball", h=None):
    """Weight of every edge of a block, as a function of the block: the neighbour's own
    weight (1, or ``1 / #N_r(q)`` for ``"density"``), times ``exp(-|q - p|^2 / h^2)`` for
    the Gaussian kernel."""
    if weights == "uniform":
        wpt = np.ones(ball.n)
    else:
        wpt = 1.0 / ball.counts.astype(np.float64)
    if kernel == "ball":
        return lambda blk: blk.nb(wpt)
    inv_h2 = 1.0 / (h * h)
    return lambda blk: blk.nb(wpt) * np.exp(-_rowdot3(blk.d, blk.d) * inv_h2)


# --- engine, step 3: weighted moments ---
def _row_sums(ball, values):
    """Per-point sums over each ball of per-edge values, block by block: ``values(blk)``
    lists arrays of shape (E,) or (k_i, E); their sums are the rows of a (sum k_i, n) array."""
    out = None
    for blk in ball.blocks():
        sums = [np.atleast_2d(blk.sum(v)) for v in values(blk)]
        if out is None:
            out = np.zeros((sum(len(v) for v in sums), ball.n))
        out[:, blk.rows] = np.concatenate(sums)
    return out


def _mean_cov(ball, weight, features):
    """Weighted mean and centred covariance of per-neighbour features, per point.

    ``weight(blk)`` gives the edge weights ``w`` (E,) and ``features(blk)`` the features
    ``F`` (k, E) of a block. Two passes (mean first, then centred products). Returns
    ``mean = sum w F / sum w`` (k, n) and ``cov = sum w (F - mean)(F - mean)^T / sum w``
    (n, k, k).
    """
    def first(blk):
        w = weight(blk)
        return [w, w * features(blk)]

    s1 = _row_sums(ball, first)
    wsum = s1[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1[1:] / wsum
    k = len(mean)

    def second(blk):
        c, w = features(blk) - blk.row(mean), weight(blk)
        return [w * (c[u] * c[v]) for u, v in _upper(k)]

    s2 = _row_sums(ball, second)
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 /= wsum
    return mean, _symmetric(s2, k)


# --- engine, step 4: per-point finish ---
def _eigh(cov, ok):
    """Ascending eigenvalues (clipped at 0) and eigenvectors of the rows ``ok``, else NaN."""
    n, k = cov.shape[:2]
    lam = np.full((n, k), np.nan)
    vec = np.full((n, k, k), np.nan)
    if np.any(ok):
        w, v = np.linalg.eigh(cov[ok])
        lam[ok] = np.maximum(w, 0.0)
        vec[ok] = v
    return lam, vec


def _pca(ball, weight, min_count):
    """Weighted PCA of every ball (``pca.h``): shift ``o - p`` (3, n), ascending
    eigenvalues (n, 3), unoriented normal ``v0`` (n, 3) and status (TOO_FEW below
    ``min_count`` neighbours, else DEGENERATE for rank < 2)."""
    m, cov = _mean_cov(ball, weight, lambda blk: blk.d)
    lam, vec = _eigh(cov, ball.counts >= min_count)
    status = np.full(ball.n, OK, dtype=np.uint8)
    with np.errstate(invalid="ignore"):
        status[(lam[:, 2] == 0.0) | (lam[:, 1] <= RANK_TOL * lam[:, 2])] = DEGENERATE
    status[ball.counts < min_count] = TOO_FEW
    return m, lam, vec[:, :, 0].copy(), status


def _finish(out, perm):
    """Back to input order (``res[perm] = out``); NaN float rows where status != OK."""
    res = {}
    for key, val in out.items():
        res[key] = np.empty(val.shape, dtype=val.dtype)
        res[key][perm] = val
    bad = res["status"] != OK
    for arr in res.values():
        if arr.dtype == np.float64:
            arr[bad] = np.nan
    return res


# --- operators 4 and 5: PCA moments, surface variation, MLS0 ---
def moments(points, radius, weights="uniform"):
    """Weighted PCA moments of every strict-ball neighbourhood.

    For each point ``p`` with neighbourhood ``N_r(p)`` (``p`` included) and weights ``w_q``:

    * barycenter ``o = sum w_q q / sum w_q``,
    * covariance ``C = sum w_q (q - o)(q - o)^T / sum w_q``,
    * ascending eigenvalues ``l0 <= l1 <= l2`` of ``C``,
    * surface variation ``l0 / (l0 + l1 + l2)`` (Pauly et al., operator 4 of Digne & Morel
      2013; tends to ``r^2/16 ((k1^2 + k2^2)/2 - k1 k2/3)``),
    * MLS0 shift ``o - p`` (operator 5; ``o - p ~ -(H r^2/4) n_out`` with the clcurv sign
      convention, i.e. ``H = 4 <p - o, n_out> / r^2``).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates, in length unit ``L``; must be finite.
    radius : float
        Ball radius ``r`` in unit ``L`` (> 0); strict balls ``|q - p| < r``.
    weights : {"uniform", "density"}, optional
        ``"uniform"``: ``w_q = 1`` (default, the case of the theorems). ``"density"``:
        ``w_q = 1 / #N_r(q)``, the inverse of ``q``'s own neighbour count (Section 3).

    Returns
    -------
    dict
        ``"count"`` int32 (N,): ``#N_r(p)``, ``p`` included.
        ``"status"`` uint8 (N,): OK; TOO_FEW (``count < 3``); DEGENERATE
        (``l1 <= 1e-10 * l2`` or ``l2 == 0``).
        ``"eigenvalues"`` float64 (N, 3): ascending eigenvalues of ``C``, unit ``L^2``
        (round-off negatives clipped to 0).
        ``"normals"`` float64 (N, 3): unit eigenvector of ``l0`` (PCA normal), unoriented.
        ``"variation"`` float64 (N,): ``l0 / (l0 + l1 + l2)``, dimensionless, in [0, 1/3].
        ``"shift"`` float64 (N, 3): ``o - p``, unit ``L``.
        Every float64 entry is NaN where ``status != OK``.

    ValueError if ``weights`` is unknown, ``points`` is not a finite ``(N, 3)`` array, or
    ``radius`` is not positive (likewise for every operator below).
    """
    _check_choice("weights", weights, _WEIGHTS)
    pts, r = _as_cloud(points, radius)
    if len(pts) == 0:
        return _empty(("eigenvalues", 3), ("normals", 3), ("variation", 0), ("shift", 3))
    ball = _Ball(pts, r)
    m, lam, v0, status = _pca(ball, _edge_weights(ball, weights), MIN_COUNT_PCA)
    with np.errstate(invalid="ignore", divide="ignore"):
        variation = lam[:, 0] / lam.sum(axis=1)
    return _finish({"count": ball.counts, "status": status, "eigenvalues": lam,
                    "normals": v0, "variation": variation, "shift": m.T}, ball.perm)


# --- operators 1, 2, 3: normal-based covariances ---
def invert_theorem1(lam1, lam2, radius):
    """Curvature magnitudes from the count-normalised 2dcov1 eigenvalues.

    Theorem 1 (Digne & Morel 2013): ``lam1 -> c (5 k1^2 + 2 k1 k2 + k2^2)``,
    ``lam2 -> c (k1^2 + 2 k1 k2 + 5 k2^2)``, ``c = r^6 / 256``. With ``u = lam1 / c``,
    ``v = lam2 / c`` and ``m = (k1 + k2)^2`` this reads ``u = 4 k1^2 + m``,
    ``v = 4 k2^2 + m``; eliminating gives ``32 m^2 - 8 S m + S^2 - 4 u v = 0``
    (``S = u + v``), whose two roots ``m_pm = (S +- sqrt(8 u v - S^2)) / 8`` are the two
    sign hypotheses: the sign of ``k1 k2`` belonging to a root is that of ``6 m - S``
    (``m_-`` always gives ``k1 k2 <= 0``; ``m_+`` gives ``k1 k2 >= 0`` iff ``u/v <= 5``).

    **Sign rule.** Both roots always give non-negative squares (``0 <= m <= v`` for
    ``1 <= u/v <= 3 + 2 sqrt 2``), so the data cannot tell the two hypotheses apart (e.g.
    the sphere ``(k, k)`` and the saddle ``(sqrt2 k, -sqrt2 k)`` have identical
    eigenvalues). We always keep the larger root ``m_+``: it is the ``k1 k2 >= 0`` solution
    whenever one exists (eigenvalue ratio ``u/v <= 5``: from 1 for an umbilic to 5 for a
    cylinder), and for ``5 < u/v <= 3 + 2 sqrt 2`` (only reachable by ``k1 k2 < 0``) the
    ``k1 k2 < 0`` solution continuous with it. Ratios beyond ``3 + 2 sqrt 2`` are not
    attainable by Theorem 1 (sampling error): the discriminant is clipped at 0. Then
    ``|k1| = sqrt(max(u - m, 0) / 4)``, ``|k2| = sqrt(max(v - m, 0) / 4)``.

    ``lam1 >= lam2 >= 0``: the largest and smallest count-normalised eigenvalues (array_like,
    unit ``L^4``: (k^2 r^6 / 256)); ``radius``: ``r`` (unit ``L``). Returns the magnitudes ``k1, k2``
    (arrays, ``|k1| >= |k2| >= 0``, unit ``1/L``).
    """
    c = float(radius) ** 6 / 256.0
    u = np.asarray(lam1, dtype=np.float64) / c
    v = np.asarray(lam2, dtype=np.float64) / c
    s = u + v
    m = (s + np.sqrt(np.maximum(8.0 * u * v - s * s, 0.0))) / 8.0
    return np.sqrt(np.maximum(u - m, 0.0) / 4.0), np.sqrt(np.maximum(v - m, 0.0) / 4.0)


def _aligned(nb, n):
    """The neighbours' normals ``nb`` (3, m) aligned with their query point's normal ``n``
    (3, m): ``n_i := -n_i`` where ``<n_i, n> < 0`` (kept where it is 0 or NaN)."""
    return np.where(_rowdot3(nb, n) < 0, -nb, nb)


def covariance_ops(points, radius, normals, method, weights="uniform", align=False):
    """Normal-based covariance curvature operators 2dcov1, 2dcov2 and 3dcov.

    For every point ``p`` with unit outward normal ``n``, tangent basis ``(t1, t2)``
    (:func:`tangent_frame`), strict-ball neighbourhood ``N_r(p)`` (``p`` included,
    ``n_p = #N_r(p)`` points) and weights ``w_i`` (1, or ``1 / #N_r(q_i)`` for
    ``weights="density"``), a feature ``f_i`` is formed for each neighbour ``q_i``
    (normal ``n_i``):

    * ``"2dcov1"`` (Berkmann & Caelli; operator 1): ``s_i = <q_i - p, n>``,
      ``f_i = s_i (<q_i - p, t1>, <q_i - p, t2>)`` (2D, unit ``L^2``);
    * ``"2dcov2"`` (operator 2, PCL's PrincipalCurvaturesEstimation):
      ``f_i = (<n_i, t1>, <n_i, t2>)``, ``n_i`` projected on the tangent plane at ``p``
      (2D, dimensionless);
    * ``"3dcov"`` (operator 3): ``f_i = n_i`` (3D).

    **Signs.** By default (``align=False``) the normals are used as given: 2dcov2 is then
    PCL's PrincipalCurvaturesEstimation with the same normals, and 2dcov2 and 3dcov need
    normals that agree in sign across each ball (outward ones do). With ``align=True``
    (the kernels' ALIGN_NORMALS 1) every neighbour's normal is first aligned with ``n``
    for 2dcov2 and 3dcov: ``n_i := -n_i`` where ``<n_i, n> < 0`` (kept where it is 0), the
    paper's "orientation made consistent with n". The normals then need to agree within
    each ball only (unoriented PCA normals will do): the sign of a neighbour's normal
    changes nothing, and the sign of ``n`` changes no eigenvalue and no magnitude (``-n``
    gives the frame ``(-t1, t2)``, so the features become ``(f_a, -f_b)`` for 2dcov1 and
    2dcov2, ``-f`` for 3dcov: the same eigenvalues). It may change the sign of ``dir1``
    and ``dir2`` (``dir2 = n x dir1`` keeps the frame right-handed). 2dcov1 reads the
    normal at ``p`` alone: ``align`` changes nothing there.

    **Count normalisation.** The reported eigenvalues are those of
    ``C = sum_i w_i (f_i - f_mean)(f_i - f_mean)^T / sum_i w_i`` with
    ``f_mean = sum_i w_i f_i / sum_i w_i``, i.e. the weighted scatter matrix divided by
    ``n_p * w_mean`` (``w_mean = sum_i w_i / n_p``). For uniform weights this is exactly
    ``Sigma / n_p``, the count-normalised quantity of Theorems 1-3 (population covariance,
    divisor ``n_p``). For 2dcov2 with uniform weights the two eigenvalues equal PCL's
    ``pc1 = eigenvalues_[2] / indices.size()`` and ``pc2 = eigenvalues_[1] /
    indices.size()`` (``principal_curvatures.hpp``: eigenvalues of the unnormalised 3x3
    scatter of the projected normals ``(I - n n^T) n_i``, the non-zero ones of ours).

    **Curvatures.**

    * 2dcov1: Theorem 1, ``lam1, lam2 -> r^6/256 (5 k1^2 + 2 k1 k2 + k2^2),
      r^6/256 (k1^2 + 2 k1 k2 + 5 k2^2)``, inverted by :func:`invert_theorem1` (sign
      rule documented there). ``dir1`` = eigenvector of the largest eigenvalue.
    * 2dcov2 and 3dcov: Theorems 2 and 3, ``lam_j -> k_j^2 r^2 / 4``, so
      ``|k_j| = (2 / r) sqrt(lam_j)`` with ``lam1 >= lam2`` the two largest eigenvalues of
      ``C``. ``dir1`` = eigenvector of ``lam1`` (3dcov: projected on the tangent plane at
      ``p`` and normalised; if that projection is shorter than 1e-3, a flat neighbourhood
      where the direction is meaningless, ``t1`` is used).

    2D eigenvectors ``(a, b)`` map to ``a t1 + b t2``; ``dir2 = n x dir1`` (so
    ``(dir1, dir2, n)`` is a right-handed orthonormal frame).

    Parameters
    ----------
    points, radius : array_like (N, 3), float
        Coordinates and ball radius ``r`` (> 0), unit ``L``, as for :func:`moments`.
    normals : array_like, shape (N, 3)
        Unit normals at every point (normalised again here); see **Signs**.
    method : {"2dcov1", "2dcov2", "3dcov"}
    weights : {"uniform", "density"}, optional
    align : bool, optional
        Align each neighbour's normal with the query point's (see **Signs**); default
        False, the normals as given.

    Returns
    -------
    dict
        ``"count"`` int32 (N,): ``#N_r(p)``, ``p`` included.
        ``"status"`` uint8 (N,): OK; TOO_FEW (``count < 3``); DEGENERATE: the normal at
        ``p`` (2dcov1) or a normal in the ball (2dcov2, 3dcov) is invalid.
        ``"eigenvalues"`` float64 (N, 2) (2dcov1: unit ``L^4``; 2dcov2: dimensionless) or
        (N, 3) (3dcov, dimensionless): descending eigenvalues of ``C`` (clipped at 0).
        ``"k1"``, ``"k2"`` float64 (N,): magnitudes ``k1 >= k2 >= 0`` (unit ``1/L``).
        ``"dir1"``, ``"dir2"`` float64 (N, 3): orthogonal unit tangent directions of ``k1``
        and ``k2``.
        NaN in every float64 output where ``status != OK``.
    """
    _check_choice("method", method, COV_METHODS)
    _check_choice("weights", weights, _WEIGHTS)
    pts, r = _as_cloud(points, radius)
    n = len(pts)
    nrm_in = _as_normals(normals, n)
    k = 3 if method == "3dcov" else 2
    if n == 0:
        return _empty(("eigenvalues", k), ("k1", 0), ("k2", 0), ("dir1", 3), ("dir2", 3))

    ball = _Ball(pts, r)
    nrm = nrm_in[ball.perm]
    t1, t2 = tangent_frame(nrm)
    nt, t1t, t2t = nrm.T.copy(), t1.T.copy(), t2.T.copy()
    if method == "2dcov1":
        def features(blk):
            s = _rowdot3(blk.d, blk.row(nt))
            return np.stack([s * _rowdot3(blk.d, blk.row(t1t)),
                             s * _rowdot3(blk.d, blk.row(t2t))])
    elif method == "2dcov2":
        def features(blk):
            nb = _aligned(blk.nb(nt), blk.row(nt)) if align else blk.nb(nt)
            return np.stack([_rowdot3(nb, blk.row(t1t)), _rowdot3(nb, blk.row(t2t))])
    else:
        def features(blk):
            own = blk.row(nt)
            nb = _aligned(blk.nb(nt), own) if align else blk.nb(nt)
            return nb - own                          # shifted by n(p): same covariance

    _, cov = _mean_cov(ball, _edge_weights(ball, weights), features)
    enough = ball.counts >= MIN_COUNT_PCA
    finite = np.all(np.isfinite(cov.reshape(n, -1)), axis=1)
    lam, vec = _eigh(cov, enough & finite)
    lam, vec = np.ascontiguousarray(lam[:, ::-1]), np.ascontiguousarray(vec[:, :, ::-1])

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
    if method == "2dcov1":
        k1, k2 = invert_theorem1(lam[:, 0], lam[:, 1], r)
    else:
        k1, k2 = 2.0 / r * np.sqrt(lam[:, 0]), 2.0 / r * np.sqrt(lam[:, 1])

    status = np.full(n, OK, dtype=np.uint8)
    status[~finite | ~np.all(np.isfinite(nrm), axis=1)] = DEGENERATE
    status[~enough] = TOO_FEW
    return _finish({"count": ball.counts, "status": status, "eigenvalues": lam, "k1": k1,
                    "k2": k2, "dir1": dir1, "dir2": np.cross(nrm, dir1)}, ball.perm)


# --- operator 7: MLS2, and the iterations ---
def solvable(amat, status):
    """The rows of ``status`` OK whose 6x6 system ``amat`` is not singular (its smallest
    singular value above SINGULAR_RCOND times its largest); the others OK before are set
    SINGULAR in ``status``."""
    idx = np.flatnonzero(status == OK)
    if len(idx):
        sv = np.linalg.svd(amat[idx], compute_uv=False)
        singular = ~(sv[:, -1] > SINGULAR_RCOND * sv[:, 0])
        status[idx[singular]] = SINGULAR
        idx = idx[~singular]
    return idx


def _eigvec_2x2(s11, s12, s21, s22, lam):
    """Eigenvector ``(a, b)`` of ``[[s11, s12], [s21, s22]]`` for the eigenvalue ``lam``
    (not normalised): the longer of the vectors orthogonal to the two rows of
    ``S - lam I``; ``(1, 0)`` when both vanish (``S = lam I``, an umbilic, where every
    direction is principal)."""
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


def mls2(points, radius, normals, weights="uniform", kernel="ball", h=None):
    """MLS2: local quadratic height fit (paper operator 7), signed curvatures.

    For every point ``p`` with neighbourhood ``N_r(p)`` (strict ball, ``p`` included) and
    neighbour weights ``w_i``:

    1. Weighted PCA of the ball: barycenter ``o``, centred covariance
       ``sum w_i (q_i - o)(q_i - o)^T / sum w_i``, ``v0`` = eigenvector of the smallest
       eigenvalue, flipped so that ``<v0, n> > 0`` (``n`` the given oriented normal at
       ``p``).
    2. ``Q = p - <p - o, v0> v0`` (projection on the regression plane) and the frame
       ``(t1, t2, v0)``, ``(t1, t2) = tangent_frame(v0)``.
    3. Heights ``h_i = <q_i - Q, v0>`` and scaled coordinates ``x_i = <q_i - Q, t1> / r``,
       ``y_i = <q_i - Q, t2> / r``; weighted least squares of
       ``g = a00 + a10 x + a01 y + a20 x^2 + a11 x y + a02 y^2`` through the 6x6 normal
       equations ``A a = b``, ``A = sum w phi phi^T``, ``b = sum w h phi``,
       ``phi = (1, x, y, x^2, x y, y^2)``. ``A`` is *singular* (SINGULAR) when its smallest
       singular value is ``<= SINGULAR_RCOND *`` its largest (1e-10).
    4. Unscaled derivatives at the origin: ``gx = a10 / r``, ``gy = a01 / r``,
       ``gxx = 2 a20 / r^2``, ``gxy = a11 / r^2``, ``gyy = 2 a02 / r^2``.
    5. Projection ``Q + a00 v0``; fitted normal
       ``(-gx t1 - gy t2 + v0) / sqrt(1 + gx^2 + gy^2)`` (outward, as ``v0``).
    6. Shape operator ``S = I^-1 II`` with ``I = [[1 + gx^2, gx gy], [gx gy, 1 + gy^2]]``,
       ``II = [[gxx, gxy], [gxy, gyy]] / sqrt(1 + gx^2 + gy^2)``. The height is measured
       along the *outward* ``v0``, so a sphere is a concave graph: clcurv's curvatures are
       ``k = -eigenvalues(S)`` (sphere of radius R: ``k1 = k2 = +1/R``), ``k1 >= k2``,
       ``mean = (k1 + k2) / 2 = -tr(S) / 2``, ``gaussian = k1 k2 = det S``. ``dir1``: the
       eigenvector ``(a, b)`` of ``S`` for ``-k1``, mapped to
       ``a (t1 + gx v0) + b (t2 + gy v0)`` and normalised (at an umbilic, ``S = -k I``,
       ``(a, b) = (1, 0)``); ``dir2 = normal x dir1`` (so ``(dir1, dir2, normal)`` is
       right-handed and orthonormal; the eigenvectors of ``S`` are ``I``-orthogonal, so
       this is the direction of ``k2``).

    Weights ``w_i`` (used for both the PCA and the fit): ``kernel="ball"``: 1 for every
    neighbour in the ball; ``kernel="gaussian"``: ``exp(-d_i^2 / h^2)``,
    ``d_i = |q_i - p|``, ``h = r / 2`` by default (weight ``exp(-4) = 0.018`` at the
    ball's rim); neighbours are still limited to the strict ball. With
    ``weights="density"`` both are multiplied by ``1 / #N_r(q_i)``.

    Parameters
    ----------
    points, radius : array_like (N, 3), float
        Coordinates and ball radius ``r`` (> 0), unit ``L``, as for :func:`moments`.
    normals : array_like, shape (N, 3)
        Oriented (outward) normals; only used to orient ``v0``.
    weights : {"uniform", "density"}, optional
    kernel : {"ball", "gaussian"}, optional
    h : float, optional
        Gaussian width (unit ``L``, > 0); default ``r / 2``. Ignored for the ball kernel.

    Returns
    -------
    dict
        ``"count"`` int32 (N,): ``#N_r(p)``.
        ``"status"`` uint8 (N,): OK; TOO_FEW (``count < 6``); DEGENERATE: rank < 2 PCA
        (middle eigenvalue ``<= 1e-10 *`` the largest, or the largest is 0, e.g.
        collinear neighbours), an invalid normal at ``p``, or ``<v0, n> = 0``;
        SINGULAR: singular 6x6 system.
        ``"points"`` (N, 3): MLS2 projection of ``p`` (unit ``L``).
        ``"k1"``, ``"k2"`` (N,): signed principal curvatures, ``k1 >= k2`` (unit ``1/L``).
        ``"dir1"``, ``"dir2"`` (N, 3): unit principal directions.
        ``"mean"`` (N,): ``H`` (``1/L``); ``"gaussian"`` (N,): ``K`` (``1/L^2``).
        ``"normals"`` (N, 3): unit fitted normals, outward.
        NaN in every float64 output where ``status != OK``.
    """
    _check_choice("weights", weights, _WEIGHTS)
    _check_choice("kernel", kernel, _KERNELS)
    pts, r = _as_cloud(points, radius)
    hh = r / 2.0 if h is None else _as_radius(h)
    n = len(pts)
    nrm_in = _as_normals(normals, n)
    if n == 0:
        return _empty(("points", 3), ("k1", 0), ("k2", 0), ("dir1", 3), ("dir2", 3),
                      ("mean", 0), ("gaussian", 0), ("normals", 3))

    ball = _Ball(pts, r)
    nrm = nrm_in[ball.perm]
    weight = _edge_weights(ball, weights, kernel, hh)

    # 1. weighted PCA (offsets d = q - p, so m = o - p), v0 oriented by the normal at p
    m, _, v0, status = _pca(ball, weight, MIN_COUNT_MLS2)
    with np.errstate(invalid="ignore"):
        side = np.einsum("ij,ij->i", v0, nrm)
        status[(status == OK) & ~(np.abs(side) > 0.0)] = DEGENERATE  # invalid n or <v0, n> = 0
    v0 *= np.where(side < 0.0, -1.0, 1.0)[:, None]
    v0[status != OK] = np.nan

    # 2. frame at Q = p + sq v0, sq = <o - p, v0> (NaN rows give NaN sums)
    t1, t2 = tangent_frame(v0)
    sq = np.einsum("ij,ji->i", v0, m)
    qoff = (sq[:, None] * v0).T.copy()
    v0t, t1t, t2t = v0.T.copy(), t1.T.copy(), t2.T.copy()
    inv_r = 1.0 / r

    # 3. normal equations: the 21 packed sums of A and the 6 of b, per point
    iu = _upper(6)

    def system(blk):
        e = blk.d - blk.row(qoff)
        hgt = _rowdot3(e, blk.row(v0t))
        xs = _rowdot3(e, blk.row(t1t)) * inv_r
        ys = _rowdot3(e, blk.row(t2t)) * inv_r
        phi = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys])
        wphi = weight(blk) * phi
        return [wphi[u] * phi[v] for u, v in iu] + [wphi * hgt]

    sums = _row_sums(ball, system)
    amat, sb = _symmetric(sums[:len(iu)], 6), sums[len(iu):]

    coef = np.full((n, 6), np.nan)
    idx = solvable(amat, status)
    if len(idx):
        coef[idx] = np.linalg.solve(amat[idx], sb[:, idx].T[:, :, None])[:, :, 0]

    # 4. derivatives, projection, normal, shape operator S = I^-1 II
    a00, a10, a01, a20, a11, a02 = coef.T
    gx, gy = a10 * inv_r, a01 * inv_r
    gxx, gxy, gyy = 2.0 * a20 * inv_r ** 2, a11 * inv_r ** 2, 2.0 * a02 * inv_r ** 2
    proj = ball.q + (sq + a00)[:, None] * v0
    wn = np.sqrt(1.0 + gx * gx + gy * gy)
    normal = (v0 - gx[:, None] * t1 - gy[:, None] * t2) / wn[:, None]
    e_, f_, g_ = 1.0 + gx * gx, gx * gy, 1.0 + gy * gy
    l_, m_, n_ = gxx / wn, gxy / wn, gyy / wn
    det_i = e_ * g_ - f_ * f_
    s11 = (g_ * l_ - f_ * m_) / det_i
    s12 = (g_ * m_ - f_ * n_) / det_i
    s21 = (e_ * m_ - f_ * l_) / det_i
    s22 = (e_ * n_ - f_ * m_) / det_i
    half_tr = 0.5 * (s11 + s22)
    det_s = (l_ * n_ - m_ * m_) / det_i
    disc = np.sqrt(np.maximum(0.25 * (s11 - s22) ** 2 + s12 * s21, 0.0))
    k1, k2 = -half_tr + disc, -half_tr - disc
    with np.errstate(invalid="ignore"):
        ab = _eigvec_2x2(s11, s12, s21, s22, -k1)
        dir1 = _unit_rows(ab[:, :1] * (t1 + gx[:, None] * v0)
                          + ab[:, 1:] * (t2 + gy[:, None] * v0))
    return _finish({"count": ball.counts, "status": status, "points": proj, "k1": k1,
                    "k2": k2, "dir1": dir1, "dir2": np.cross(normal, dir1),
                    "mean": -half_tr, "gaussian": det_s, "normals": normal}, ball.perm)


def mls2_iterate(points, radius, normals, iterations, **kw):
    """Apply the MLS2 projection ``iterations`` times to the whole cloud.

    Each iteration calls :func:`mls2` on the current cloud (neighbourhoods recomputed on
    the moved points) and moves every point with status OK to its projection; points with
    another status stay where they are for that iteration. The orientation normals are
    then re-estimated as the (uniform-ball, :func:`moments`) PCA normals of the moved
    cloud, flipped to agree with the previous iterate's normals (dot >= 0); where the PCA
    normal is undefined the previous normal is kept.

    ``points``, ``radius``, ``normals`` (outward) as for :func:`mls2`; ``iterations`` >= 0
    projections (0 returns a copy of ``points``); ``**kw``: ``weights``, ``kernel``, ``h``,
    passed to :func:`mls2` (``weights`` also to the PCA normal re-estimation).

    Returns
    -------
    dict
        ``"points"`` (N, 3): the final points (unit ``L``).
        ``"status"`` uint8 (N,): the first non-OK :func:`mls2` status met by the point
        over the iterations (OK if it was always projected).
        ``"normals"`` (N, 3): the final oriented (outward) unit PCA normals.
        NaN in ``points`` and ``normals`` where ``status != OK``.
    """
    it = int(iterations)
    if it != iterations or it < 0:
        raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
    cur, r = _as_cloud(points, radius)
    cur = cur.copy()
    nrm = _as_normals(normals, len(cur))
    status = np.full(len(cur), OK, dtype=np.uint8)
    for _ in range(it):
        res = mls2(cur, r, nrm, **kw)
        ok = res["status"] == OK
        first = (status == OK) & ~ok
        status[first] = res["status"][first]
        cur[ok] = res["points"][ok]
        pca = moments(cur, r, kw.get("weights", "uniform"))["normals"]
        with np.errstate(invalid="ignore"):
            flip = np.einsum("ij,ij->i", pca, nrm) < 0.0
        pca[flip] *= -1.0
        keep = ~np.all(np.isfinite(pca), axis=1)
        pca[keep] = nrm[keep]
        nrm = pca
    bad = status != OK
    cur[bad] = np.nan
    nrm[bad] = np.nan
    return {"points": cur, "status": status, "normals": nrm}


def scale_space(points, radius, iterations, weights="uniform"):
    """Float64 MLS1 scale space (paper operator 6, iterated: a discrete mean curvature
    motion).

    ``iterations`` times, every point is projected on the weighted PCA regression plane of
    its ball, ``p <- p - <p - o, v0> v0`` (:func:`moments`: ``o`` barycenter, ``v0`` PCA
    normal; the sign of ``v0`` does not matter), all points together, neighbourhoods
    recomputed on the moved cloud each time; points whose status is not OK stay.

    ``points`` (N, 3) and ``radius`` (> 0) in unit ``L`` and ``weights`` as for
    :func:`moments`. Returns the list of the ``iterations + 1`` iterates (input first),
    each an (N, 3) float64 array, unit ``L``.
    """
    pts = np.array(points, dtype=np.float64)
    out = [pts.copy()]
    for _ in range(int(iterations)):
        m = moments(pts, radius, weights=weights)
        ok = m["status"] == OK
        n = m["normals"][ok]
        along = np.einsum("ij,ij->i", m["shift"][ok], n)
        pts = pts.copy()
        pts[ok] += along[:, None] * n
        out.append(pts.copy())
    return out


# --- the API's host steps, the reference's own: finishing and orientation ---
#
# clcurv.curvature(..., backend="numpy") runs the operators above and then these, never
# the kernel path's finishing steps (clcurv.ops.registry: _finish_*, _flip_mls2) nor its
# orientation (clcurv.orient.orientation). They are written from the paper's formulas and Hoppe's
# algorithm as stated here, not from that code.

def finish(method, raw, points, radius, normals, user=None):
    """The result attributes of ``method`` (float64 arrays in input order, NaN where the
    status is not OK) from its reference fields ``raw``.

    ``raw``: the fields of :func:`moments` (variation, MLS0, MLS1), :func:`covariance_ops`
    (2dcov1, 2dcov2, 3dcov) or :func:`mls2` (MLS2), with the position field given as
    ``shift`` (``o - p`` for the moments, the projection minus ``p`` for MLS2: the form
    the operator registry hands over). ``normals``: the unit normals the call used (the
    oriented PCA normals, or the user's); ``user``: the user's unit normals or None.

    * variation: the PCA normals (``normals``), the ascending eigenvalues and
      ``l0 / (l0 + l1 + l2)``, as :func:`moments` gives them.
    * MLS0 (Lemma 2): the barycenter ``o = p + shift`` and ``H = 4 <p - o, n> / r^2``, ``n``
      the user's normal when given, else the oriented PCA normal.
    * MLS1 (Theorem 5): ``p'`` = ``p`` projected on the plane through ``o`` normal to the
      oriented PCA normal ``n``, ``p' = p - <p - o, n> n``, and ``H = 4 <p - p', n> / r^2``.
    * 2dcov1, 2dcov2, 3dcov: the magnitudes, directions and eigenvalues as
      :func:`covariance_ops` gives them, and the normals used.
    * MLS2: as :func:`mls2` gives them, the projection ``p + shift``; ``mean`` and
      ``gaussian`` are its ``-tr(S) / 2`` and ``det S`` of the shape operator, not
      ``(k1 + k2) / 2`` and ``k1 k2`` (the kernel path's host step forms those).
    """
    pts = np.asarray(points, dtype=np.float64)
    r = float(radius)
    n = np.asarray(normals, dtype=np.float64)
    bad = np.asarray(raw["status"]) != OK
    if method in ("variation", "mls0", "mls1"):
        out = {"normals": n, "eigenvalues": raw["eigenvalues"], "variation": raw["variation"]}
        o = pts + raw["shift"]                                  # the barycenter
        if method == "mls0":
            nref = n if user is None else np.asarray(user, dtype=np.float64)
            out["mean"] = 4.0 * np.einsum("ij,ij->i", pts - o, nref) / r ** 2
            out["points"] = o
        elif method == "mls1":
            proj = pts - np.einsum("ij,ij->i", pts - o, n)[:, None] * n
            out["mean"] = 4.0 * np.einsum("ij,ij->i", pts - proj, n) / r ** 2
            out["points"] = proj
    elif method in COV_METHODS:
        out = {k: raw[k] for k in ("k1", "k2", "dir1", "dir2", "eigenvalues")}
        out["normals"] = n
    elif method == "mls2":
        out = {k: raw[k] for k in ("k1", "k2", "dir1", "dir2", "normals", "mean", "gaussian")}
        out["points"] = pts + raw["shift"]
    else:
        raise ValueError(f"unknown method {method!r}")
    out = {k: np.array(v, dtype=np.float64) for k, v in out.items()}
    for k in ("mean", "points"):
        if k in out:
            out[k][bad] = np.nan
    return out


def _against(normals, directions):
    """True where ``<n, d> < 0`` (rows; False where either is NaN or the product is 0)."""
    with np.errstate(invalid="ignore"):
        return np.einsum("ij,ij->i", normals, directions) < 0.0


def orientation_flips(points, normals, how, reference=None, viewpoint=None, k=10,
                      radius=None):
    """Flip mask (True: negate the row) of the unoriented ``normals`` (N, 3) of ``points``
    for the orientation ``how`` of :func:`clcurv.curvature`: a direction (3,) (the normals
    agree with it), 'normals' (each agrees with the row of ``reference``), 'viewpoint'
    (each faces ``viewpoint``: ``<n, v - p> >= 0``), 'mst' (:func:`mst_flips` over the
    ``k`` nearest points within ``radius``) or None (no flip). A NaN normal, or one
    perpendicular to its reference, is not flipped."""
    n = np.asarray(normals, dtype=np.float64)
    if how is None:
        return np.zeros(len(n), dtype=bool)
    if isinstance(how, np.ndarray):
        return _against(n, np.broadcast_to(how.astype(np.float64), n.shape))
    if how == "normals":
        return _against(n, np.asarray(reference, dtype=np.float64))
    if how == "viewpoint":
        return _against(n, np.asarray(viewpoint, dtype=np.float64)
                        - np.asarray(points, dtype=np.float64))
    if how == "mst":
        return mst_flips(points, n, k=k, radius=radius)
    raise ValueError(f"unknown orientation {how!r}")


#: components of fewer points are not propagated over (each point faces away from the
#: centroid of all valid points); :data:`clcurv.orient.orientation.MIN_COMPONENT`
MST_MIN_COMPONENT = 3
#: components of at least this many points take part in the nesting check
MST_NEST_MIN = 100
#: added to every edge weight (Hoppe's graph stores no zero weights)
MST_EDGE_EPS = 1e-6


def _mst_graph(p, u, k, radius):
    """Upper-triangular CSR of the orientation graph: each point joined to its ``k``
    nearest other points closer than ``radius`` (None: any distance), weight
    ``1 - |u_i . u_j| + |e . u_i| |e . u_j| + MST_EDGE_EPS`` (``e`` the unit offset, 0 for
    coincident points)."""
    m = len(p)
    kk = min(k, m - 1)
    bound = np.inf if radius is None else float(radius)
    dist, nb = cKDTree(p).query(p, k=kk + 1, distance_upper_bound=bound)
    me = np.arange(m)[:, None]
    other = (nb < m) & (nb != me)
    # at most k others per row (when coincident points hide the point itself)
    other &= np.cumsum(other, axis=1) <= kk
    i = np.broadcast_to(me, nb.shape)[other]
    j = nb[other]
    a, b = np.minimum(i, j), np.maximum(i, j)
    key = np.sort(a.astype(np.int64) * m + b)
    key = key[np.r_[True, key[1:] != key[:-1]]]            # each edge once
    a, b = key // m, key % m
    e = p[b] - p[a]
    le = np.linalg.norm(e, axis=1)
    eh = e / np.where(le > 0, le, 1.0)[:, None]
    ua, ub = u[a], u[b]
    w = (1.0 - np.abs(np.einsum("ij,ij->i", ua, ub))
         + np.abs(np.einsum("ij,ij->i", eh, ua)) * np.abs(np.einsum("ij,ij->i", eh, ub))
         + MST_EDGE_EPS)
    return coo_matrix((w, (a, b)), shape=(m, m)).tocsr()


def _propagated(u, tree, labels, ncomp):
    """The unit normals ``u`` made consistent along the spanning forest ``tree``: from each
    component's first point, breadth first, a normal is negated where it points against
    its parent's (already propagated) normal (Hoppe 1992)."""
    m = len(u)
    t = tree.tocoo()
    roots = np.unique(labels, return_index=True)[1]      # the first point of each component
    # one breadth-first search from a virtual node m joined to every root
    rows = np.concatenate([t.row, t.col, np.full(ncomp, m)])
    cols = np.concatenate([t.col, t.row, roots])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m + 1, m + 1)).tocsr()
    order, pred = breadth_first_order(g, m, directed=True, return_predecessors=True)
    depth = np.zeros(m + 1, dtype=np.int64)
    for node in order[1:]:                  # breadth first: a parent comes before its child
        depth[node] = depth[pred[node]] + 1
    out = u.copy()
    nodes = order[1:][np.argsort(depth[order[1:]], kind="stable")]
    cuts = np.flatnonzero(np.diff(depth[nodes])) + 1
    for at in np.split(nodes, cuts)[1:]:    # level by level, the roots' (depth 1) first
        par = out[pred[at]]
        out[at] *= np.where(np.einsum("ij,ij->i", u[at], par) < 0.0, -1.0, 1.0)[:, None]
    return out


def _inside(q, surface, normals):
    """For each row of ``q``: whether it lies inside the solid bounded by the oriented
    samples ``surface`` (outward ``normals``): the nearest sample's normal points away from
    it, ``<q - s, n_s> < 0``."""
    _, near = cKDTree(surface).query(q)
    return np.einsum("ij,ij->i", q - surface[near], normals[near]) < 0.0


def mst_flips(points, normals, k=10, radius=None):
    """Flip mask of Hoppe's propagation, written on its own (not :mod:`clcurv.orient.orientation`).

    1. Valid rows (finite point and normal, normal not zero) only; the others get False.
       Fewer than :data:`MST_MIN_COMPONENT` valid points: each faces away from their
       centroid.
    2. The graph of each point's ``k`` nearest other points within ``radius``, weights
       ``1 - |n_i . n_j| + |e . n_i| |e . n_j|`` (+1e-6; ``e`` the unit offset: an edge
       across a thin sheet costs more), and its minimum spanning forest.
    3. In each tree, breadth first from its first point, each normal is negated where it
       points against its parent's.
    4. Each component then faces outward: its normals, summed, point away from its
       centroid (``sum <n_i, p_i - c> >= 0``), else all are negated. Components of fewer
       than :data:`MST_MIN_COMPONENT` points: each point faces away from the centroid of
       all valid points.
    5. Nesting: components of at least :data:`MST_NEST_MIN` points, largest bounding box
       first; one whose box lies in the boxes of larger ones, and whose points lie (in the
       majority) inside the solid those bound, is the wall of a cavity: it faces the
       cavity, i.e. its sign of step 4 is reversed. Inside means: the nearest point of
       those larger components has a normal pointing away from it.
    """
    p_all = np.asarray(points, dtype=np.float64)
    n_all = np.asarray(normals, dtype=np.float64)
    flip = np.zeros(len(p_all), dtype=bool)
    valid = (np.all(np.isfinite(p_all), axis=1) & np.all(np.isfinite(n_all), axis=1)
             & np.any(np.nan_to_num(n_all) != 0.0, axis=1))
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return flip
    p = p_all[idx]
    u = n_all[idx] / np.linalg.norm(n_all[idx], axis=1)[:, None]
    centre = p.mean(axis=0)
    if len(idx) < MST_MIN_COMPONENT:
        flip[idx] = np.einsum("ij,ij->i", u, p - centre) < 0.0
        return flip
    tree = minimum_spanning_tree(_mst_graph(p, u, int(k), radius))
    ncomp, labels = connected_components(tree, directed=False)
    o = _propagated(u, tree, labels, ncomp)
    size = np.bincount(labels, minlength=ncomp)
    sign = np.ones(ncomp)
    members = np.split(np.argsort(labels, kind="stable"), np.cumsum(size)[:-1])
    for c, rows in enumerate(members):
        vote = np.einsum("ij,ij->", o[rows], p[rows] - p[rows].mean(axis=0))
        sign[c] = -1.0 if vote < 0.0 else 1.0
    big = [c for c in range(ncomp) if size[c] >= MST_NEST_MIN]
    lo = {c: p[members[c]].min(axis=0) for c in big}
    hi = {c: p[members[c]].max(axis=0) for c in big}
    big.sort(key=lambda c: -np.linalg.norm(hi[c] - lo[c]))
    for i, c in enumerate(big):
        outer = [a for a in big[:i] if np.all(lo[a] <= lo[c]) and np.all(hi[a] >= hi[c])]
        if not outer:
            continue
        rows = np.concatenate([members[a] for a in outer])
        each = np.repeat([sign[a] for a in outer], [len(members[a]) for a in outer])
        q = p[members[c][::max(1, size[c] // 1000)]]          # about 1000 of its points
        if np.mean(_inside(q, p[rows], o[rows] * each[:, None])) > 0.5:
            sign[c] = -sign[c]
    o *= sign[labels][:, None]
    small = size[labels] < MST_MIN_COMPONENT
    o[small] = u[small] * np.where(np.einsum("ij,ij->i", u[small], p[small] - centre) < 0.0,
                                   -1.0, 1.0)[:, None]
    flip[idx] = np.einsum("ij,ij->i", o, u) < 0.0
    return flip
