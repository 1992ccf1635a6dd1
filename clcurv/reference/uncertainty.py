"""Float64 reference of clcurv's per-point error bars (issue 51): standard errors of the
curvatures and of the normals, and the roughness, from one pass of weighted sums per ball.

NumPy in, NumPy out, float64, independent of the kernel path (it imports only
:mod:`clcurv._shared` and the public names of :mod:`clcurv.reference.operators`). The
neighbourhoods, weights, frames and fits are those of :func:`~clcurv.reference.operators.mls2`
and :func:`~clcurv.reference.operators.moments` (strict balls ``|q - p| < r`` with ``p``
included; weights ``w`` = 1 or ``1 / #N_r(q)``, times ``exp(-|q - p|^2 / h^2)`` for MLS2's
Gaussian kernel), written again here: the values returned beside the errors equal those
functions' (tests/test_uncertainty_reference.py checks it).

Model and assumptions (all formulas)
------------------------------------
The samples are ``q_i = s_i + eps_i n``: points ``s_i`` of the smooth surface plus
independent noise of mean 0 and one variance ``sigma^2`` along the normal. The standard
errors (SE) are first order in ``sigma`` and describe the **random** part of the error
only: the **bias** of each operator (its ``O(r^2)`` term, paper Theorems 5 and Section 4.7)
is *not* included, so they are calibrated only where the bias is small against the SE (see
bench/results/uncertainty.md for where that holds and where it breaks). ``sigma`` is
estimated per point from the residuals, so the SE also contains whatever of the geometry the
fitted model leaves in them (cubic terms for the quadric, the whole curvature for the plane).
Errors of neighbouring points are correlated (their balls overlap); the SEs are marginal,
point by point. Units: ``L`` the length unit of ``points``; curvature SEs in ``1/L``
(``K``: ``1/L^2``), ``normal_se`` in radians, ``roughness`` in ``L``. Signs follow clcurv
(outward normals, sphere positive, ``k1 >= k2``); an SE is non-negative and does not depend
on the orientation.

Per-ball sums (``d_i = q_i - p``, weights ``w_i``, ``W = sum w``, ``W2 = sum w^2``;
Kish's effective number of points ``n_eff = W^2 / W2``, ``= n`` for uniform weights).

**MLS2** (``mls2``: PCA frame ``(t1, t2, v0)`` at ``Q``, scaled coordinates ``x, y``
(``/ r``), heights ``h``, ``phi = (1, x, y, x^2, xy, y^2)``, ``g = phi . a``):

* ``A = sum w phi phi^T`` and ``b = sum w h phi`` (the fit, ``a = A^-1 b``), ``B = sum w^2
  phi phi^T`` (``B = A`` when every weight is 0 or 1: uniform ball), ``sum w h^2``.
* weighted residual sum ``RSS = sum w (h - phi . a)^2 = sum w h^2 - a . b`` (one pass);
  degrees of freedom ``nu = W - tr(A^-1 B)``, exactly ``E[RSS] = sigma^2 nu`` (``nu = n - 6``
  for uniform weights; about ``W (1 - 6 / n_eff)`` otherwise); ``sigma_hat^2 = RSS / nu``.
* coefficient covariance (sandwich, weights not equal to inverse variances)
  ``Cov(a) = sigma_hat^2 A^-1 B A^-1``.
* derivatives ``p = a10 / r``, ``q = a01 / r``, ``L = 2 a20 / r^2``, ``M = a11 / r^2``,
  ``N = 2 a02 / r^2``, ``W3 = (1 + p^2 + q^2)^(3/2)``; the curvatures of the graph at the
  origin, exactly as ``mls2`` computes them from ``S = I^-1 II`` (height along the
  outward ``v0``, hence the minus):
  ``H = -((1 + q^2) L - 2 p q M + (1 + p^2) N) / (2 W3)``,
  ``K = (L N - M^2) / (1 + p^2 + q^2)^2``, ``k1,2 = H +- D``, ``D = sqrt(H^2 - K)``.
* delta method: ``SE(X)^2 = J_X Cov(a) J_X^T`` with the exact gradients
  (:func:`curvature_jacobian`), the gradient (linear) terms ``p, q`` included:
  ``dH/dL = -(1 + q^2) / (2 W3)``, ``dH/dM = p q / W3``, ``dH/dN = -(1 + p^2) / (2 W3)``,
  ``dH/dp = -(p N - q M) / W3 - 3 p H / (1 + p^2 + q^2)`` (``q`` likewise),
  ``dK/dL = N / w^2``, ``dK/dN = L / w^2``, ``dK/dM = -2 M / w^2``, ``dK/dp = -4 p K / w``
  (``w = 1 + p^2 + q^2``), ``dk1,2 = dH +- (2 H dH - dK) / (2 D)``. ``H`` is linear in
  ``(L, M, N)`` (for given ``p, q``): its SE holds at any signal-to-noise ratio. ``K`` is a
  product: its first-order SE is calibrated only where ``SE(k)`` is small against ``|k|``
  (on the sphere, ``sigma = 0.5% r``: std z 1.33 at ``k r = 0.01`` where ``SE(H) ~ H / 2``,
  1.02 at ``k r = 0.08``; bench/results/uncertainty.md). At an exact umbilic
  (``D = 0``, only in noise-free data) ``dD`` is taken as 0. Near an umbilic ``k1 = max``
  of two noisy eigenvalues is biased upwards by about ``1.25 SE(D)`` (an order-statistic
  bias, not in the SE): on a sphere only ~90% of the z-scores of ``k1`` lie within 1.96.
  No SE fixes that (a wider one breaks the std); the estimator can:
  :func:`debiased_principal` (``k1_debiased``, 95% on the sphere; bench).
* fitted normal ``(-p, -q, 1) / sqrt(w)``: its angle's variance is
  ``tr(G Cov(p, q))``, ``G = (I - g g^T / w) / w``, ``g = (p, q)``; ``normal_se`` is
  its square root (RMS angle, radians).
* ``roughness = sigma_hat`` (the dof-corrected weighted residual RMS to the quadric,
  ``sqrt(RSS / nu)``; the raw RMS is ``sqrt(RSS / W)``).

**MLS1 and MLS0** (``H = 4 <p - o, n> / r^2``, ``o = sum w q / W``):

* ``<p - o, n> = sum (w_i / W) <p - q_i, n>`` is linear in the heights, and **the point's
  own noise enters with weight** ``1 - w_p / W`` (``w_p`` its weight in its own ball), the
  neighbours' heights with ``-w_i / W``:
  ``Var(H) = (16 / r^4) (sigma_p^2 (1 - w_p / W)^2 + s^2 (W2 - w_p^2) / W^2)``
  (for uniform weights ``(n - 1)^2 / n^2`` and ``(n - 1) / n^2``). So ``SE(H) ~ 4 sigma /
  r^2``: it does **not** fall as ``1 / sqrt(n)`` (the estimate is a height difference
  between ``p`` and a mean), only the second term does.
* ``s^2``, the neighbours' height variance about the plane, is the plane's residual variance
  ``l0 n_eff / (n_eff - 3)`` (``l0`` the smallest PCA eigenvalue, the mean squared distance
  to the regression plane; ``tr(A^-1 B) ~ 3 W2 / W`` for a plane). It holds the noise
  *and* the curvature's spread of heights over the ball, ``r^4 (H^2 / 16 - K / 24)`` (a
  sphere: ``k^2 r^4 / 48``): over random sample positions the neighbours' mean height
  varies by both, so both belong there.
* ``sigma_p^2``, the point's own noise: ``noise="quadric"`` (default) takes ``sigma_hat^2``
  of MLS2's quadric fit on the same ball (the noise alone; costs the 6x6 fit), calibrated
  in every case of bench/results/uncertainty.md. ``noise="plane"`` (the issue's first
  rule, no fit) takes ``s^2``: it holds the curvature's spread too, so the SE is
  conservative once ``k r`` passes about ``4 sigma / r`` on a sphere (``std z`` 0.66 at
  ``k r = 0.08``, ``sigma = 1% r``), and misses the targets there.
* the normal's own error changes ``<p - o, n>`` only by ``|p - o|_tangent * angle``, of order
  ``sigma / n``: neglected.
* ``roughness`` (plane) ``= sqrt(l0 n_eff / (n_eff - 3))`` in both modes: the noise *and*
  the curvature's spread about the plane, like CloudCompare's roughness.

**Normals (PCA)**: for ``C = sum w (q - o)(q - o)^T / W`` with eigenvalues ``l0 <= l1 <= l2``
(eigenvectors ``v0, e1, e2``), first-order perturbation of ``v0`` by noise along ``v0``:
``delta v0 = -sum_j e_j (sum_i w_i x_ij eps_i) / (W (l_j - l0))``, ``x_ij = <q_i - o, e_j>``,
so ``Var(theta_j) = sigma^2 S_j / (W^2 (l_j - l0)^2)``, ``S_j = sum w^2 x_ij^2``
(uniform weights: ``sigma^2 l_j / (n (l_j - l0)^2)``, and with ``sigma^2 ~ l0 n / (n - 3)``
the classical ``l0 l_j / ((n - 3)(l_j - l0)^2)``). ``normal_se = sqrt(Var theta_1 +
Var theta_2)`` (RMS angle, radians), ``sigma^2`` the plane's ``sigma_hat^2`` (its curvature
part acts as an independent residual for a ball centred at ``p``: the tilt stays calibrated).
Assumes ``l1, l2 >> l0`` (a surface, not an edge or a blob).

Outputs are NaN where the status is not OK, and the SEs also where the dof are not positive
(e.g. exactly 6 neighbours for MLS2, 3 for a plane).

What a kernel accumulates (one work-item per point, beside the sums it has)
--------------------------------------------------------------------------
* PCA pass: ``W2 = sum w^2`` and ``w_p`` (MLS0/MLS1 SE); for the PCA normal's SE with
  non-0/1 weights ``Q1 = sum w^2 d`` (3) and ``Q2 = sum w^2 d d^T`` (6), centred on ``o`` in
  the finish (``sum w^2 (d - m)(d - m)^T = Q2 - m Q1^T - Q1 m^T + W2 m m^T``, ``m = o - p``);
  with uniform ball weights ``sum w^2 x_j^2 = W l_j`` and nothing more is needed.
* MLS2 fit pass: ``sum w h^2`` (1); ``B = sum w^2 phi phi^T`` (21) only for non-0/1 weights
  (density, Gaussian kernel): for the uniform ball ``B = A``, ``tr(A^-1 B) = 6`` and
  ``Cov(a) = sigma_hat^2 A^-1``.
* finish: ``RSS = sum w h^2 - a . b`` (in float32 this subtracts two sums of squared
  heights: the heights include the curvature's ``k r^2 / 2``, so with little noise and a
  large ``k r`` relative precision is lost, about ``(k r^2 / sigma)^2`` times the float32
  epsilon); the SEs need ``J A^-1 B A^-1 J^T`` for the 4 rows ``J`` of
  :func:`curvature_jacobian` and the 2 gradient rows: 6 solves with ``A``'s factorisation
  (``u = A^-1 J^T``), then ``u^T B u`` (uniform ball: ``J . u``). The debiased ``k1, k2``
  (if adopted) also need ``cov(L, N)`` and ``var(M)``: the same with the unit rows of
  ``a20, a11, a02``.
* MLS0/MLS1 with ``noise="quadric"``: the MLS2 fit's ``RSS`` and ``nu`` (a fit pass in the
  PCA frame); ``noise="plane"``: nothing beyond ``W2`` and ``w_p``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from clcurv._shared.constants import DEGENERATE, MIN_COUNT_MLS2, MIN_COUNT_PCA, OK, TOO_FEW
from clcurv._shared.options import choices
from clcurv.reference.operators import RANK_TOL, solvable, tangent_frame

__all__ = ["mls2_uncertainty", "mls1_uncertainty", "pca_uncertainty", "curvature_jacobian",
           "debiased_principal", "FIELDS"]

#: the issue's field names and their units (``L``: the length unit of the points)
FIELDS = {"mean_curvature_se": "1/L", "gaussian_curvature_se": "1/L^2", "k1_se": "1/L",
          "k2_se": "1/L", "normal_se": "rad", "roughness": "L"}

#: edges per block of rows (bounds the per-edge temporaries, ~70 arrays for MLS2)
_BLOCK_EDGES = 1 << 16
_UPPER6 = [(u, v) for u in range(6) for v in range(u, 6)]
_UPPER3 = [(u, v) for u in range(3) for v in range(u, 3)]


# --- neighbourhoods and weights (the definitions of clcurv.reference.operators) ---
class _Balls:
    """Strict balls ``|q - p| < r`` (``p`` included) of every point as CSR rows in input
    order: ``cols[indptr[i]:indptr[i + 1]]``, ``counts`` = ``#N_r(p)``."""

    def __init__(self, pts, r):
        n = self.n = len(pts)
        pairs = cKDTree(pts).query_pairs(float(np.nextafter(r, 0.0)), output_type="ndarray")
        i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
        j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
        order = np.argsort(i, kind="stable")
        self.rows_of_edges, self.cols = i[order], j[order]
        self.counts = np.bincount(i, minlength=n).astype(np.int32)
        self.indptr = np.zeros(n + 1, dtype=np.intp)
        np.cumsum(self.counts, out=self.indptr[1:])

    def blocks(self):
        """``(rows slice, local row of every edge, neighbour of every edge, own-edge mask)``
        over blocks of whole rows of about ``_BLOCK_EDGES`` edges."""
        r0 = 0
        while r0 < self.n:
            r1 = int(np.searchsorted(self.indptr, self.indptr[r0] + _BLOCK_EDGES, "right")) - 1
            r1 = min(max(r1, r0 + 1), self.n)
            e = slice(self.indptr[r0], self.indptr[r1])
            rows = self.rows_of_edges[e]
            yield slice(r0, r1), rows - r0, self.cols[e], self.cols[e] == rows
            r0 = r1


def _sums(balls, per_edge):
    """Per-point sums over each ball of the per-edge rows returned by ``per_edge(rows, local,
    cols, own)`` (a (k, E) array); result (k, n)."""
    out = None
    for rows, local, cols, own in balls.blocks():
        vals = per_edge(rows, local, cols, own)
        m = rows.stop - rows.start
        block = np.stack([np.bincount(local, weights=v, minlength=m) for v in vals])
        if out is None:
            out = np.zeros((len(block), balls.n))
        out[:, rows] = block
    return out


def _weights(pts, balls, weights, kernel, h):
    """Edge weights as a function of ``(local, cols, own, d)``: 1 or ``1 / #N_r(q)`` times
    ``exp(-|d|^2 / h^2)`` for the Gaussian kernel."""
    for name, value in (("weights", weights), ("kernel", kernel)):
        if value not in choices(name):         # the options' declaration (clcurv._shared)
            raise ValueError(f"{name} must be one of {choices(name)}, got {value!r}")
    wpt = np.ones(balls.n) if weights == "uniform" else 1.0 / balls.counts
    if kernel == "ball":
        return lambda cols, d: wpt[cols]
    inv_h2 = 1.0 / (h * h)
    return lambda cols, d: wpt[cols] * np.exp(-np.einsum("ij,ij->j", d, d) * inv_h2)


def _check(points, radius, normals=None):
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"points contain {np.count_nonzero(~np.isfinite(pts))} non-finite "
                         "coordinates")
    r = float(radius)
    if not (np.isfinite(r) and r > 0.0):
        raise ValueError(f"radius must be positive and finite, got {radius!r}")
    if normals is None:
        return pts, r, None
    nrm = np.array(normals, dtype=np.float64)
    if nrm.shape != pts.shape:
        raise ValueError(f"normals must have shape {pts.shape}, got {nrm.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    nrm[~np.all(np.isfinite(nrm), axis=1)] = np.nan
    return pts, r, nrm


# --- pass 1: weighted PCA with the squared-weight sums ---
def _pca_pass(pts, balls, weight, min_count):
    """Weighted PCA of every ball and the sums the errors need.

    Returns a dict: ``W``, ``W2``, ``wp`` (own weight), ``m`` = ``o - p`` (n, 3),
    ``lam`` ascending (n, 3), ``vec`` (n, 3, 3) (columns), ``M2`` = ``sum w^2 (q - o)(q - o)^T``
    (n, 3, 3), ``status``."""
    def per_edge(rows, local, cols, own):
        d = (pts[cols] - pts[rows][local]).T
        w = weight(cols, d)
        w2 = w * w
        return ([w, w2, w * own] + [w * c for c in d] + [w2 * c for c in d]
                + [w * d[u] * d[v] for u, v in _UPPER3] + [w2 * d[u] * d[v] for u, v in _UPPER3])

    s = _sums(balls, per_edge)
    big_w, w2, wp = s[0], s[1], s[2]
    s1, q1, s2, q2 = s[3:6].T, s[6:9].T, s[9:15], s[15:21]
    n = balls.n
    sym = np.empty((2, n, 3, 3))
    for col, (u, v) in enumerate(_UPPER3):
        sym[0, :, u, v] = sym[0, :, v, u] = s2[col]
        sym[1, :, u, v] = sym[1, :, v, u] = q2[col]
    with np.errstate(invalid="ignore", divide="ignore"):
        m = s1 / big_w[:, None]
    cov = sym[0] / big_w[:, None, None] - m[:, :, None] * m[:, None, :]
    # sum w^2 (d - m)(d - m)^T
    m2 = (sym[1] - m[:, :, None] * q1[:, None, :] - q1[:, :, None] * m[:, None, :]
          + w2[:, None, None] * m[:, :, None] * m[:, None, :])
    enough = balls.counts >= min_count
    lam = np.full((n, 3), np.nan)
    vec = np.full((n, 3, 3), np.nan)
    if np.any(enough):
        lw, lv = np.linalg.eigh(cov[enough])
        lam[enough], vec[enough] = np.maximum(lw, 0.0), lv
    status = np.full(n, OK, dtype=np.uint8)
    with np.errstate(invalid="ignore"):
        status[(lam[:, 2] == 0.0) | (lam[:, 1] <= RANK_TOL * lam[:, 2])] = DEGENERATE
    status[~enough] = TOO_FEW
    return {"W": big_w, "W2": w2, "wp": wp, "m": m, "lam": lam, "vec": vec, "M2": m2,
            "status": status}


def _plane_errors(pca):
    """``sigma_hat^2`` of the plane (``l0 n_eff / (n_eff - 3)``), ``n_eff`` and the PCA
    normal's angular SE (radians)."""
    lam, vec, m2 = pca["lam"], pca["vec"], pca["M2"]
    with np.errstate(invalid="ignore", divide="ignore"):
        n_eff = pca["W"] ** 2 / pca["W2"]
        s2 = np.where(n_eff > 3.0, lam[:, 0] * n_eff / (n_eff - 3.0), np.nan)
        var = np.zeros(len(lam))
        for j in (1, 2):
            e = vec[:, :, j]
            sj = np.einsum("ni,nij,nj->n", e, m2, e)
            var += s2 * sj / (pca["W"] ** 2 * (lam[:, j] - lam[:, 0]) ** 2)
    return s2, n_eff, np.sqrt(var)


def pca_uncertainty(points, radius, weights="uniform"):
    """Angular SE of the PCA normal and plane roughness of every point (operators
    variation, MLS0, MLS1 and every method using PCA normals).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Coordinates, length unit ``L``, finite.
    radius : float
        Ball radius ``r`` (> 0), unit ``L``; strict balls, ``p`` included.
    weights : {"uniform", "density"}, optional
        As :func:`clcurv.reference.operators.moments`.

    Returns
    -------
    dict
        ``"count"`` int32, ``"status"`` uint8 (as ``moments``), ``"normal_se"`` (N,) RMS
        angle in radians of the PCA normal (module docstring), ``"roughness"`` (N,) unit
        ``L``: ``sqrt(l0 n_eff / (n_eff - 3))``, ``"n_eff"`` (N,) Kish's ``W^2 / W2``.
        NaN where the status is not OK (and ``n_eff <= 3``).
    """
    pts, r, _ = _check(points, radius)
    if len(pts) == 0:
        return _empty("normal_se", "roughness", "n_eff")
    balls = _Balls(pts, r)
    pca = _pca_pass(pts, balls, _weights(pts, balls, weights, "ball", None), MIN_COUNT_PCA)
    s2, n_eff, nse = _plane_errors(pca)
    return _done({"count": balls.counts, "status": pca["status"], "normal_se": nse,
                  "roughness": np.sqrt(s2), "n_eff": n_eff})


def mls1_uncertainty(points, radius, normals, weights="uniform", method="mls1",
                     noise="quadric"):
    """MLS1 (or MLS0) mean curvature with its standard error, and the PCA normal's SE.

    ``H = 4 <p - o, n> / r^2`` (paper Lemma 2 and Theorem 5, clcurv's sign), ``o`` the
    weighted barycenter of the ball, ``n`` the PCA normal oriented like ``normals``
    (``method="mls1"``) or ``normals`` themselves (``method="mls0"`` with the user's
    normals); ``SE(H)`` as in the module docstring.

    Parameters
    ----------
    points, radius, weights
        As :func:`pca_uncertainty`.
    normals : array_like, shape (N, 3)
        Outward normals (orient the PCA normal; MLS0's ``n``).
    method : {"mls1", "mls0"}
    noise : {"quadric", "plane"}
        The point's own noise ``sigma_p``: from MLS2's quadric fit on the same ball (default;
        ball kernel, same weights) or from the plane's residuals (cheaper, conservative
        where the curvature spreads the heights; module docstring).

    Returns
    -------
    dict
        ``"count"``, ``"status"``, ``"mean"`` (H, ``1/L``), ``"mean_se"`` (``1/L``),
        ``"normals"`` (N, 3): the oriented PCA normals (MLS1's ``n``),
        ``"normal_se"`` (rad), ``"roughness"`` (``L``, plane: ``s``), ``"sigma"`` (``L``,
        the point's own ``sigma_p``), ``"n_eff"``; NaN where the status is not OK.
    """
    if method not in ("mls0", "mls1"):
        raise ValueError(f"method must be 'mls0' or 'mls1', got {method!r}")
    if noise not in ("plane", "quadric"):
        raise ValueError(f"noise must be 'plane' or 'quadric', got {noise!r}")
    pts, r, nrm = _check(points, radius, normals)
    if len(pts) == 0:
        return _empty("mean", "mean_se", "normals", "normal_se", "roughness", "sigma", "n_eff")
    balls = _Balls(pts, r)
    weight = _weights(pts, balls, weights, "ball", None)
    pca = _pca_pass(pts, balls, weight, MIN_COUNT_PCA)
    s2, n_eff, nse = _plane_errors(pca)
    status = pca["status"]
    v0 = pca["vec"][:, :, 0]
    with np.errstate(invalid="ignore"):
        side = np.einsum("ij,ij->i", v0, nrm)
    oriented = v0 * np.where(side < 0.0, -1.0, 1.0)[:, None]
    n_use = oriented if method == "mls1" else nrm
    status[(status == OK) & ~np.all(np.isfinite(n_use), axis=1)] = DEGENERATE
    mean = -4.0 * np.einsum("ij,ij->i", pca["m"], n_use) / r ** 2
    sigma2 = s2
    if noise == "quadric":
        fit = _mls2_pass(pts, r, balls, weight, pca, v0)
        sigma2 = fit["sigma2"]
        status[(status == OK) & (fit["status"] != OK)] = fit["status"][(status == OK)
                                                                       & (fit["status"] != OK)]
    with np.errstate(invalid="ignore", divide="ignore"):
        big_w, wp = pca["W"], pca["wp"]
        own, others = (1.0 - wp / big_w) ** 2, (pca["W2"] - wp * wp) / big_w ** 2
        se = 4.0 / r ** 2 * np.sqrt(sigma2 * own + s2 * others)
    return _done({"count": balls.counts, "status": status, "mean": mean, "mean_se": se,
                  "normals": oriented,
                  "normal_se": nse, "roughness": np.sqrt(s2), "sigma": np.sqrt(sigma2),
                  "n_eff": n_eff})


# --- pass 2: the MLS2 quadric with its error sums ---
def _mls2_pass(pts, r, balls, weight, pca, v0):
    """The quadric fit of ``mls2`` in the PCA frame (``v0`` any sign: the residuals do not
    depend on it) with ``B``, ``sum w h^2``, ``nu`` and ``sigma_hat^2``.

    Returns ``coef`` (n, 6) (scaled coordinates), ``cov`` (n, 6, 6) = ``sigma_hat^2 A^-1 B
    A^-1``, ``sigma2``, ``dof`` (``nu``), ``rss``, ``status`` (SINGULAR added)."""
    n = balls.n
    status = pca["status"].copy()
    status[(status == OK) & (balls.counts < MIN_COUNT_MLS2)] = TOO_FEW
    with np.errstate(invalid="ignore", divide="ignore"):      # NaN rows: NaN frames
        t1, t2 = tangent_frame(v0)
    sq = np.einsum("ij,ij->i", v0, pca["m"])
    qoff = sq[:, None] * v0
    inv_r = 1.0 / r

    def per_edge(rows, local, cols, own):
        d = (pts[cols] - pts[rows][local]).T
        w = weight(cols, d)
        e = d - qoff[rows][local].T
        hgt = np.einsum("ij,ji->i", e.T, v0[rows][local].T)
        xs = np.einsum("ij,ji->i", e.T, t1[rows][local].T) * inv_r
        ys = np.einsum("ij,ji->i", e.T, t2[rows][local].T) * inv_r
        phi = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys])
        wphi, w2phi = w * phi, (w * w) * phi
        return ([wphi[u] * phi[v] for u, v in _UPPER6] + list(wphi * hgt)
                + [w * hgt * hgt] + [w2phi[u] * phi[v] for u, v in _UPPER6])

    s = _sums(balls, per_edge)
    k = len(_UPPER6)
    amat, bmat = np.empty((n, 6, 6)), np.empty((n, 6, 6))
    for col, (u, v) in enumerate(_UPPER6):
        amat[:, u, v] = amat[:, v, u] = s[col]
        bmat[:, u, v] = bmat[:, v, u] = s[k + 7 + col]
    rhs, shh = s[k:k + 6].T, s[k + 6]

    coef = np.full((n, 6), np.nan)
    cov = np.full((n, 6, 6), np.nan)
    sigma2, dof, rss = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    idx = solvable(amat, status)
    if len(idx):
        a_inv = np.linalg.inv(amat[idx])
        c = np.linalg.solve(amat[idx], rhs[idx][:, :, None])[:, :, 0]
        coef[idx] = c
        rss[idx] = np.maximum(shh[idx] - np.einsum("ij,ij->i", c, rhs[idx]), 0.0)
        dof[idx] = amat[idx, 0, 0] - np.einsum("nij,nji->n", a_inv, bmat[idx])
        with np.errstate(invalid="ignore", divide="ignore"):
            sigma2[idx] = np.where(dof[idx] > 0.0, rss[idx] / dof[idx], np.nan)
        cov[idx] = sigma2[idx][:, None, None] * (a_inv @ bmat[idx] @ a_inv)
    return {"coef": coef, "cov": cov, "sigma2": sigma2, "dof": dof, "rss": rss,
            "status": status}


def curvature_jacobian(coef, radius):
    """Curvatures of the MLS2 quadric at the origin and their gradients with respect to its
    coefficients.

    ``coef`` (n, 6): ``a00, a10, a01, a20, a11, a02`` of ``g`` in coordinates scaled by
    ``1 / radius`` (as :func:`clcurv.reference.operators.mls2` fits them, height along the
    outward normal). Returns ``values`` (n, 4): ``H, K, k1, k2`` (clcurv's signs, as
    ``mls2``: ``H = -tr(S) / 2``, ``K = det S``, ``k1,2 = H +- sqrt(H^2 - K)``) and
    ``jac`` (n, 4, 6): ``d(H, K, k1, k2) / d coef`` (column 0, ``a00``, is zero). At an exact
    umbilic (``H^2 = K``) the derivative of ``sqrt(H^2 - K)`` is taken as 0.
    """
    c = np.asarray(coef, dtype=np.float64)
    r = float(radius)
    p, q = c[:, 1] / r, c[:, 2] / r
    ll, mm, nn = 2.0 * c[:, 3] / r ** 2, c[:, 4] / r ** 2, 2.0 * c[:, 5] / r ** 2
    w = 1.0 + p * p + q * q
    w3 = w ** 1.5
    num = (1.0 + q * q) * ll - 2.0 * p * q * mm + (1.0 + p * p) * nn
    h = -num / (2.0 * w3)
    kk = (ll * nn - mm * mm) / (w * w)
    # gradients with respect to (p, q, L, M, N)
    dh = np.stack([-(p * nn - q * mm) / w3 - 3.0 * p * h / w,
                   -(q * ll - p * mm) / w3 - 3.0 * q * h / w,
                   -(1.0 + q * q) / (2.0 * w3), p * q / w3, -(1.0 + p * p) / (2.0 * w3)], axis=1)
    dk = np.stack([-4.0 * p * kk / w, -4.0 * q * kk / w, nn / w ** 2, -2.0 * mm / w ** 2,
                   ll / w ** 2], axis=1)
    disc2 = h * h - kk
    dd = np.sqrt(np.maximum(disc2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        ddisc = np.where((dd > 0.0)[:, None], (2.0 * h[:, None] * dh - dk) / (2.0 * dd[:, None]),
                         0.0)
    chain = np.array([1.0 / r, 1.0 / r, 2.0 / r ** 2, 1.0 / r ** 2, 2.0 / r ** 2])
    jac = np.zeros((len(c), 4, 6))
    for row, g in enumerate((dh, dk, dh + ddisc, dh - ddisc)):
        jac[:, row, 1:] = g * chain
    return np.stack([h, kk, h + dd, h - dd], axis=1), jac


def debiased_principal(mean, gaussian, mean_se, coef, cov, radius):
    """Principal curvatures with the umbilic bias of ``D = sqrt(H^2 - K)`` removed (a
    proposal for the operator, not ``mls2``'s ``k1, k2``).

    ``D`` estimated from noisy coefficients is biased upwards, ``E[D_hat^2] = D^2 + T`` with
    ``T = SE(H)^2 - (cov(L, N) - var(M)) / w^2`` to second order (``E[H_hat^2] = H^2 +
    Var H``, ``E[K_hat] = K + (cov(L, N) - var M) / w^2``); at an umbilic that makes ``k1`` the
    larger of two noisy eigenvalues, ``~1.25 SE(D)`` too high. Returns
    ``H +- sqrt(max(D_hat^2 - T, 0))`` (n,) each, unit ``1/L``. ``mean``, ``gaussian``,
    ``mean_se`` (n,): ``H``, ``K``, ``SE(H)``; ``coef`` (n, 6), ``cov`` (n, 6, 6): the scaled
    quadric's coefficients and their covariance; ``radius``: ``r``.
    """
    r = float(radius)
    scale = np.array([2.0, 1.0, 2.0]) / r ** 2          # (L, M, N) from (a20, a11, a02)
    c = cov[:, 3:6, 3:6] * scale[:, None] * scale[None, :]
    p, q = coef[:, 1] / r, coef[:, 2] / r
    w = 1.0 + p * p + q * q
    t = mean_se ** 2 - (c[:, 0, 2] - c[:, 1, 1]) / w ** 2
    d = np.sqrt(np.maximum(mean * mean - gaussian - t, 0.0))
    return mean + d, mean - d


def mls2_uncertainty(points, radius, normals, weights="uniform", kernel="ball", h=None, *,
                     covariance=False):
    """MLS2 curvatures (as :func:`clcurv.reference.operators.mls2`) with their standard
    errors, the fitted normal's angular SE and the roughness to the quadric.

    Parameters
    ----------
    points, radius, normals, weights, kernel, h
        As :func:`clcurv.reference.operators.mls2` (``normals`` outward, used to orient
        ``v0``; ``h`` defaults to ``r / 2`` for the Gaussian kernel).

    Returns
    -------
    dict
        ``"count"`` int32, ``"status"`` uint8 (as ``mls2``);
        ``"mean"``, ``"gaussian"``, ``"k1"``, ``"k2"``: the curvatures (``1/L``, ``1/L^2``;
        equal to ``mls2``'s);
        ``"mean_se"``, ``"gaussian_se"``, ``"k1_se"``, ``"k2_se"``: their SEs (delta
        method on ``sigma_hat^2 A^-1 B A^-1``);
        ``"normals"`` (N, 3): the fitted normals (outward, as ``mls2``'s);
        ``"normal_se"`` (rad): SE of the fitted normal's angle;
        with ``covariance=True`` also ``"coef"`` (N, 6): the quadric's coefficients
        ``a00, a10, a01, a20, a11, a02`` (coordinates scaled by ``1 / r``, heights in ``L``)
        and ``"coef_cov"`` (N, 6, 6): their covariance ``sigma_hat^2 A^-1 B A^-1``;
        ``"roughness"`` (``L``): ``sigma_hat``, the dof-corrected residual RMS to the quadric;
        ``"k1_debiased"``, ``"k2_debiased"``: a proposal, not ``mls2``'s values:
        ``H +- sqrt(max(D^2 - T, 0))`` (:func:`debiased_principal`), whose z-scores with
        ``k1_se`` are calibrated at umbilics too;
        ``"dof"``: the residual degrees of freedom in points, ``nu W / W2`` (``n - 6`` for
        uniform weights; ``nu`` itself is in weight units); ``"n_eff"``: ``W^2 / W2``.
        NaN where the status is not OK; the SEs and roughness also where ``nu <= 0``.
    """
    pts, r, nrm = _check(points, radius, normals)
    names = ("mean", "gaussian", "k1", "k2", "normals", "mean_se", "gaussian_se", "k1_se", "k2_se",
             "normal_se", "roughness", "dof", "n_eff", "k1_debiased", "k2_debiased")
    if len(pts) == 0:
        out = _empty(*names)
        if covariance:
            out["coef"], out["coef_cov"] = np.empty((0, 6)), np.empty((0, 6, 6))
        return out
    hh = r / 2.0 if h is None else float(h)
    balls = _Balls(pts, r)
    weight = _weights(pts, balls, weights, kernel, hh)
    pca = _pca_pass(pts, balls, weight, MIN_COUNT_MLS2)
    v0 = pca["vec"][:, :, 0].copy()
    with np.errstate(invalid="ignore"):
        side = np.einsum("ij,ij->i", v0, nrm)
    pca["status"][(pca["status"] == OK) & ~(np.abs(side) > 0.0)] = DEGENERATE
    v0 *= np.where(side < 0.0, -1.0, 1.0)[:, None]
    v0[pca["status"] != OK] = np.nan
    fit = _mls2_pass(pts, r, balls, weight, pca, v0)
    values, jac = curvature_jacobian(fit["coef"], r)
    var = np.einsum("nki,nij,nkj->nk", jac, fit["cov"], jac)
    p, q = fit["coef"][:, 1] / r, fit["coef"][:, 2] / r
    w = 1.0 + p * p + q * q
    gcov = fit["cov"][:, 1:3, 1:3] / r ** 2
    g = np.stack([p, q], axis=1)
    metric = (np.eye(2)[None] - g[:, :, None] * g[:, None, :] / w[:, None, None]) / w[:, None, None]
    nvar = np.einsum("nij,nji->n", metric, gcov)
    se = np.sqrt(np.maximum(var, 0.0))
    k1d, k2d = debiased_principal(values[:, 0], values[:, 1], se[:, 0], fit["coef"],
                                  fit["cov"], r)
    with np.errstate(invalid="ignore", divide="ignore"):
        n_eff = pca["W"] ** 2 / pca["W2"]
    t1, t2 = tangent_frame(np.where(np.isfinite(v0), v0, 1.0))
    fitted = (v0 - p[:, None] * t1 - q[:, None] * t2) / np.sqrt(w)[:, None]
    out = {"count": balls.counts, "status": fit["status"], "mean": values[:, 0], "normals": fitted,
           "gaussian": values[:, 1], "k1": values[:, 2], "k2": values[:, 3],
           "mean_se": se[:, 0], "gaussian_se": se[:, 1], "k1_se": se[:, 2], "k2_se": se[:, 3],
           "normal_se": np.sqrt(np.maximum(nvar, 0.0)), "roughness": np.sqrt(fit["sigma2"]),
           "dof": fit["dof"] * pca["W"] / pca["W2"], "n_eff": n_eff,
           "k1_debiased": k1d, "k2_debiased": k2d}
    if covariance:
        out["coef"], out["coef_cov"] = fit["coef"], fit["cov"]
    return _done(out)


def _empty(*names):
    out = {"count": np.empty(0, dtype=np.int32), "status": np.empty(0, dtype=np.uint8)}
    out.update({k: np.empty((0, 3) if k == "normals" else 0) for k in names})
    return out


def _done(out):
    """float64 outputs NaN where the status is not OK."""
    bad = out["status"] != OK
    for key, val in out.items():
        if val.dtype == np.float64:
            val[bad] = np.nan
    return out
