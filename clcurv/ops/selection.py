"""A radius chosen per point by predicted error (issue 51, ``select="error"``): host-side
NumPy, independent of OpenCL. :func:`select_by_error` is :func:`fit_bias` then
:func:`choose`; between them a caller may pool the coefficient over each point's
neighbours (:func:`clcurv.ops.pooling.pool_bias`, on the device).

Given one operator's estimate ``v_j`` (say the mean curvature H) and its standard error
``s_j`` at each of ``k`` radii ``r_1 < ... < r_k``, every point keeps the radius of least
predicted mean squared error

    MSE_j = s_j^2 + b_j^2,   b_j = c r_j^order,

where ``b_j`` is the estimate's bias at ``r_j`` (its difference from the ``r -> 0`` limit)
and ``c`` a per-point coefficient fitted to how the estimate moves between the radii.

The bias model (the leading term of the paper's expansions)
-----------------------------------------------------------
Digne & Morel 2013 (Numer. Math., DOI 10.1007/s00211-013-0584-y; /work/shared/PAPER.md):

* **MLS2** (Theorem 6): the quadric fitted in the ball recovers the intrinsic coefficients
  ``a20 + r^2/8 (a22 + 6 a40) + O(r^4)`` and ``a02 + r^2/8 (a22 + 6 a04) + O(r^4)``
  (``z = sum a_ij x^i y^j``, principal frame at ``p``). With clcurv's sign ``H = -(a20 +
  a02)`` at the origin, so ``H(r) = H - r^2/4 (3 a40 + a22 + 3 a04) + O(r^4)``: order 2,
  ``c = -(3 a40 + a22 + 3 a04) / 4`` (the surface's fourth derivatives, not the curvature).
  The cubic terms ``a30 .. a03`` move only the linear coefficients (``a10 + r^2/6 (a12 +
  3 a30)``), which enter H squared: ``O(r^4)``.
* **MLS0 and MLS1** (Lemma 2 and Theorem 5): ``o - p = H r^2 / 4 n + o(r^2)``, hence
  ``H(r) = 4 <p - o, n> / r^2 = H + o(1)``; the paper gives no next term. It is ``O(r^2)``:
  the ball is symmetric under ``(x, y) -> (-x, -y)`` about ``p``, so every odd-degree term
  of the height's Taylor expansion (and the odd part of the area element) integrates to 0
  over it, and the height's mean over the ball has only even powers, ``H r^2/4 + O(r^4)``
  (the ball-versus-cylinder correction of Lemma 1 is even too); the regression plane's tilt
  is ``O(r^2)`` for the same reason and moves ``<p - p', n>`` by ``O(r^6)``. So order 2 as
  well. (On a sphere, MLS0's ``H(r)`` is exact: the cap's barycenter is at depth
  ``r^2 / (4 R)``; ``c = 0`` there.)

So ``order=2`` for the mean curvature of MLS0, MLS1 and MLS2 (and for MLS2's k1, k2, whose
coefficients carry the same ``r^2`` terms). Other operators' leading terms differ (the
covariance operators are ``O(r)`` relative in their square roots): pass their order.

The fit
-------
Per point, over its usable radii (``v_j`` and ``s_j`` finite), ``v_j = H0 + c x_j + e_j`` with
``x_j = r_j^order`` is fitted by generalised least squares, ``Cov(e)`` from the SEs and one
of two correlation models:

* ``correlation="nested"`` (default): the balls are nested, and the larger ball holds the
  smaller one's points. For a least-squares fit at two radii with the same design (frame)
  and independent noise, ``Cov(v_small, v_large) = Var(v_large)`` exactly (the large fit is
  the small one plus independent information), so ``Cov(v_i, v_j) = min(s_i, s_j)^2``. Then
  the differences between consecutive usable radii, ``d = v_i - v_j``, are independent with
  ``Var(d) = |s_i^2 - s_j^2|`` (floored at 1% of ``s_i^2 + s_j^2``, so that two equal SEs do
  not make a difference exact), ``H0`` drops out, and ``c`` is their weighted regression
  through the origin on ``x_i - x_j``: ``c = sum(w dx d) / sum(w dx^2)``, ``w = 1 / Var(d)``,
  ``Var(c) = 1 / sum(w dx^2)``. This holds for MLS2 (up to the frame changing with ``r``);
  for MLS0 and MLS1 the point's own noise enters every radius's H, scaled by ``1/r^2``,
  and the model then overstates ``Var(d)`` (``Var(c_hat)`` too large: more is subtracted
  from ``c_hat^2`` below, the choice leans to larger radii). Measured on MLS2 (the chirp of
  tests/test_selection.py, noise-only part of ``c_hat``): ``(c_hat - c_clean) / coef_se``
  has standard deviation 1.05 with this model, 0.78 with the independent one.
* ``correlation="independent"``: ``Cov(e) = diag(s_j^2)``, ordinary weighted least squares
  with weights ``1 / s_j^2`` and an intercept. Overstates ``Var(d)`` more for nested balls.

The fitted ``c`` is noisy: ``E[c_hat^2] = c^2 + Var(c_hat)``, so ``c_hat^2`` overstates the
squared bias, most where the truth is smallest. ``bias_noise="subtract"`` (default) uses
``max(c_hat^2 - Var(c_hat), 0)``, unbiased where positive; ``"none"`` uses ``c_hat^2``. The
predicted error is then ``sqrt(s_j^2 + b2 r_j^(2 order))``, ``b2`` that estimate of ``c^2``.

Conventions and edge cases
--------------------------
* Units: ``values`` in any unit ``U`` (``1/L`` for H), ``se`` in ``U``, ``radii`` in ``L``:
  ``coef`` is in ``U / L^order``, ``error`` and ``bias`` in ``U``.
* A column is usable at a point where its value and SE are both finite (NaN marks a radius
  that failed there: too few neighbours, singular fit); negative SEs and infinities are
  errors (ValueError), not failures.
* An SE of 0 is an exact estimate. SEs of a row below ``1e-6`` times the row's largest are
  raised to it (finite weights); if every SE of the row is 0 (noise-free input) the fit is
  unweighted and ``Var(c_hat) = 0``.
* Rows with no usable column: ``index = -1``, every float output NaN. Rows with one usable
  column (and every row when ``k = 1``): that column, ``coef`` and ``coef_se`` NaN, and
  ``error = se``: no bias can be fitted from one radius, so the error there is a lower
  bound (the bias is taken as 0).
* Ties of the predicted MSE go to the smaller radius (the first column).
* What it achieves (tests/test_selection.py, MLS2's H on a noisy chirp, float64
  reference, 4 radii ``0.025 * 1.6^j``, noise 0.5% of the median radius): median
  ``|H - H_true|`` 6.7% below the best fixed radius, far below it on the most curved
  points (top two deciles of ``|H_true|``: 0.66x, 0.39x), up to 12% above it in the
  middle deciles. Not the issue's 20%. Why: the bias is resolved only through the
  differences between radii, whose noise ``sqrt(s_i^2 - s_(i+1)^2)`` is of the order of
  the larger SE, so ``c_hat`` is noisy exactly where the choice is close. On the same data
  a choice with the noise-free bias reaches 33% below (an oracle), a fit with ``H0``
  known 32%, ``c`` fitted to the noise-free estimates (``H0`` free) 20%; ``order`` 3 or
  4, ``correlation="independent"``, subtracting ``2 Var(c_hat)`` or a Wiener shrinkage
  ``c^4 / (c^2 + Var)``: 4-10%; Lepski's rule and the intersection of confidence
  intervals lose to the best fixed radius. MLS2's SE at large radii also holds the
  quadric's misfit (roughness 3.6 sigma at the largest radius there; z std 0.46):
  rescaling it by the smallest radius's roughness changed little (7%). (These
  alternatives were measured on a twin run, wavelengths rounded to 1.571 and 0.157, where
  this function gives 7.1%.)
* Pooling (:func:`fit_bias`, :func:`clcurv.ops.pooling.pool_bias`, :func:`choose`):
  ``c_hat`` averaged over each point's ball on the device. Same chirp, median error
  against the best fixed radius of each set (and absolute), worst decile ratio::

      radii 0.025*q^j    q=1.6 (best 0.064)   q=1.8 (best 0.081)   q=2.0 (best 0.1)
      per point          -6.7% .0480 1.12     -8.4% .0460 1.08     -29.5% .0482 1.07
      pool r1, inv var   -12.8% .0449 1.11    -12.8% .0438 1.04    -31.2% .0471 1.07
      pool r2, inv var   -16.6% .0429 1.09    -13.0% .0437 1.05    -31.5% .0469 1.06
      pool r2, uniform   -15.8% .0433 1.08    -11.0% .0447 1.06    -30.3% .0477 1.08
      pool r4, inv var   -9.2% .0467 1.04     +0.1% .0502 1.23     -19.9% .0548 1.55

  (interior of each set's largest ball; the best fixed radii: .0515, .0502, .0684; among
  all radii computed, 0.08 gave the least, .0469 on the interior of 0.2, where q=1.6
  pooled at r2 gives .0421.) The second radius is best: a smaller ball pools too
  little, the largest mixes coefficients of opposite sign across the ridges (``c`` changes
  sign with the fourth derivative). The ratio 2 "wins" against a poorer baseline (its
  radii skip 0.064-0.08), not in absolute error. The pooled variance is taken as if the
  ``c_q`` were independent (``1 / sum w``); the pooled noise is about 3.5x that SD
  (neighbours share points). Other variances in the noise correction, and the pretest
  (keep ``c`` where ``|c| > z SE(c)``, else bias 0, ``z = 1.96``), pooled at r2, radii
  q=1.6, on the chirp (seed 1), a second and third case (seed 2; seed 1 with the noise
  halved and doubled; best fixed radius 0.064 in all four, median .0515, .0529, .0407,
  .0746), median against the best fixed radius and worst decile ratio::

      variant                        seed 1       seed 2       sigma / 2    sigma x 2
      Var independent (default)      -16.6% 1.09  -20.0% 1.04  -11.7% 1.05  -26.9% 1.10
      Var 0                          -16.5% 1.09  -19.9% 1.04  -11.5% 1.05  -26.9% 1.10
      Var x12.5 (3.5x the SD)        -16.8% 1.09  -21.0% 1.04  -11.6% 1.11  -27.0% 1.10
      Var (sum w sd_q / sum w)^2     -15.8% 1.09  -21.3% 1.05  -11.1% 1.37  -26.8% 1.23
      Var x count / n_eff (areas)    -16.1% 1.09  -21.2% 1.05  -11.0% 1.37  -26.8% 1.24
      Var the c_q's spread in ball   -7.2% 1.16   -13.9% 1.20  +0.6% 1.40   -23.6% 1.18
      pretest, SE x3.5               -17.0% 1.09  -20.8% 1.04  -11.3% 1.10  -26.9% 1.10
      pretest, SE (sum w sd_q/sum w) -8.8% 1.35   -16.1% 1.13  -7.1% 1.50   -21.7% 1.39
      pretest, SE the spread         +9.2% 1.59   +3.6% 1.80   +16.8% 1.62  -12.8% 1.94
      c r^2 + d r^4 (GLS, pooled)    -13.3% 1.10  -14.3% 1.05  -10.8% 1.17  -19.0% 1.07

  (``n_eff = max(1, (r2 / r_fit)^2)`` for any fitting radius of the four: 1, the
  correlated bound; the pretest with z = 1, 1.645 or 2.576 is no better.) A larger variance
  only moves points to larger radii, and that loses. The noise of the pooled ``c`` is not
  what limits the choice, the model is: on the noise-free twin of seed 1 the pooled ``c``'s
  noise has SD 2.0 against the spread of ``c`` (96) and the pooling's own bias (29), and
  the choice with ``c`` fitted to the noise-free estimates reaches 18.4% (pooled 20.2%,
  decile 7, from 0, still 1.09), with ``c r^2 + d r^4`` fitted to them 24.0% (decile 7:
  1.02), with the true bias 33.1%. There the true bias of the lower deciles is about flat
  in ``r`` from 0.025 to 0.064 (0.01-0.02), not ``c r^2``. Pooling ``c_q^2 - Var(c_q)``
  instead of ``c_q``: 11-12% at r2. None meets the issue's 20% with every decile below
  (deciles around the median ``|H_true|`` stay 0-9% above).
* The choice assumes the bias model holds across the radii given (``c r^order`` the
  leading term): radii far in the asymptotic range's outside (``k r`` of order 1) make
  ``c`` a fit of the whole curve, and the choice follows the fit.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Selection", "BiasFit", "select_by_error", "fit_bias", "choose", "CORRELATIONS",
           "BIAS_NOISE"]

CORRELATIONS = ("nested", "independent")
BIAS_NOISE = ("subtract", "none")
#: SEs of a row below this fraction of its largest are raised to it
SE_FLOOR = 1e-6
#: the nested model's variance of a difference is at least this fraction of s_i^2 + s_j^2
NESTED_FLOOR = 0.01


class Selection(NamedTuple):
    """Per point (arrays of shape (N,)): the chosen column and what the choice predicts."""
    #: int64 column of the chosen radius, -1 where no radius is usable
    index: np.ndarray
    #: the chosen radius (``L``), NaN where ``index == -1``
    radius: np.ndarray
    #: the estimate at the chosen radius (``values[i, index]``)
    value: np.ndarray
    #: its standard error (``se[i, index]``)
    se: np.ndarray
    #: predicted error ``sqrt(se^2 + b2 r^(2 order))`` at the chosen radius
    error: np.ndarray
    #: the fitted bias coefficient ``c_hat`` (``U / L^order``; NaN with < 2 usable radii)
    coef: np.ndarray
    #: its standard error ``sqrt(Var(c_hat))`` under the correlation model
    coef_se: np.ndarray
    #: the predicted signed bias at the chosen radius, ``c_hat r^order`` (not corrected)
    bias: np.ndarray


def _check(values, se, radii, order, correlation, bias_noise):
    v = np.asarray(values, dtype=np.float64)
    s = np.asarray(se, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"values must have shape (N, k), got {v.shape}")
    if s.shape != v.shape:
        raise ValueError(f"se must have the shape of values {v.shape}, got {s.shape}")
    if r.shape != (v.shape[1],):
        raise ValueError(f"radii must have shape ({v.shape[1]},), one per column, got {r.shape}")
    if v.shape[1] == 0:
        raise ValueError("at least one radius is needed, got 0 columns")
    if not (np.all(np.isfinite(r)) and np.all(r > 0)):
        raise ValueError(f"radii must be finite and positive, got {r.tolist()}")
    if np.any(np.diff(r) <= 0):
        raise ValueError(f"radii must be strictly increasing, got {r.tolist()}")
    if not (np.isscalar(order) and np.isfinite(order) and order > 0):
        raise ValueError(f"order must be a positive number, got {order!r}")
    for name, a in (("values", v), ("se", s)):
        bad = int(np.count_nonzero(np.isinf(a)))
        if bad:
            raise ValueError(f"{name} must be finite or NaN, got {bad} infinite entries")
    neg = int(np.count_nonzero(s < 0))
    if neg:
        raise ValueError(f"se must be non-negative (or NaN), got {neg} negative entries")
    if correlation not in CORRELATIONS:
        raise ValueError(f"correlation must be one of {CORRELATIONS}, got {correlation!r}")
    if bias_noise not in BIAS_NOISE:
        raise ValueError(f"bias_noise must be one of {BIAS_NOISE}, got {bias_noise!r}")
    return v, s, r


class BiasFit(NamedTuple):
    """Per point (arrays of shape (N,)): the bias coefficient fitted by :func:`fit_bias`."""
    #: ``c_hat`` (``U / L^order``), NaN where fewer than 2 radii are usable
    coef: np.ndarray
    #: ``Var(c_hat)`` under the correlation model (``U^2 / L^(2 order)``), NaN likewise, 0 on
    #: rows whose SEs are all 0
    coef_var: np.ndarray


def _floored_se(s, usable):
    """The SEs with the row floor (SE_FLOOR of the row's largest), 1 on all-zero rows
    (``exact``: noise-free, fitted unweighted), NaN where unusable; and ``exact``."""
    count = usable.sum(axis=1)
    smax = np.max(np.where(usable, s, -np.inf), axis=1, initial=-np.inf)
    exact = (count > 0) & (smax == 0)
    floor = np.where(exact, 1.0, SE_FLOOR * np.where(smax > 0, smax, 1.0))
    sw = np.where(usable, np.maximum(np.where(exact[:, None], 1.0, s), floor[:, None]), np.nan)
    return sw, exact


def fit_bias(values, se, radii, order=2, *, correlation="nested"):
    """Fit per point ``v_j = H0 + c r_j^order`` over the usable radii: ``c_hat`` and
    ``Var(c_hat)`` (module docstring: the fit, the correlation models).

    Parameters are those of :func:`select_by_error`. Returns a :class:`BiasFit` of (N,)
    float64 arrays. The first half of :func:`select_by_error`: a caller may pool the
    coefficient over each point's neighbours (:func:`clcurv.ops.pooling.pool_bias`) before
    :func:`choose`."""
    v, s, r = _check(values, se, radii, order, correlation, "none")
    n, k = v.shape
    usable = np.isfinite(v) & np.isfinite(s)
    sw, exact = _floored_se(s, usable)
    x = (r / r[-1]) ** order                      # scaled abscissae (conditioning)
    fitted = usable.sum(axis=1) >= 2
    with np.errstate(invalid="ignore", divide="ignore"):
        if correlation == "nested":
            sxx, sxy = np.zeros(n), np.zeros(n)
            last_v, last_s, last_x = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
            for j in range(k):
                u = usable[:, j]
                pair = u & np.isfinite(last_v)
                var = np.abs(last_s ** 2 - sw[:, j] ** 2)
                var = np.maximum(var, NESTED_FLOOR * (last_s ** 2 + sw[:, j] ** 2))
                dx, dv = last_x - x[j], last_v - v[:, j]
                sxx += np.where(pair, dx * dx / var, 0.0)
                sxy += np.where(pair, dx * dv / var, 0.0)
                last_v = np.where(u, v[:, j], last_v)
                last_s = np.where(u, sw[:, j], last_s)
                last_x = np.where(u, x[j], last_x)
            c_scaled = sxy / sxx
            var_scaled = 1.0 / sxx
        else:
            w = np.where(usable, 1.0 / sw ** 2, 0.0)
            vz = np.where(usable, v, 0.0)
            s0, s1, s2 = w.sum(1), (w * x).sum(1), (w * x * x).sum(1)
            t0, t1 = (w * vz).sum(1), (w * x * vz).sum(1)
            det = s0 * s2 - s1 * s1
            c_scaled = (s0 * t1 - s1 * t0) / det
            var_scaled = s0 / det
    var_scaled = np.where(exact, 0.0, var_scaled)
    scale = r[-1] ** order                         # c = c_scaled / r_k^order
    return BiasFit(coef=np.where(fitted, c_scaled, np.nan) / scale,
                   coef_var=np.where(fitted, var_scaled, np.nan) / scale ** 2)


def choose(values, se, radii, coef, coef_var, order=2, *, bias_noise="subtract"):
    """Choose per point the radius of least predicted error ``sqrt(SE^2 + b2 r^(2 order))``
    given a bias coefficient: :func:`fit_bias`'s, or one pooled over each point's
    neighbours (:func:`clcurv.ops.pooling.pool_bias`).

    Parameters
    ----------
    values, se, radii, order, bias_noise
        As :func:`select_by_error`.
    coef : array_like, shape (N,)
        The bias coefficient ``c`` (``U / L^order``) of each point, NaN where unknown: the
        bias is then taken as 0 (the error is a lower bound, as with one usable radius).
    coef_var : array_like, shape (N,)
        ``Var(coef)``, non-negative, finite where ``coef`` is (``bias_noise="subtract"``:
        ``b2 = max(coef^2 - coef_var, 0)``; ``"none"``: ``b2 = coef^2``).

    Returns
    -------
    Selection
        As :func:`select_by_error`, ``coef`` and ``coef_se`` those given (NaN where no
        radius is usable).
    """
    v, s, r = _check(values, se, radii, order, "nested", bias_noise)
    n, k = v.shape
    c = np.asarray(coef, dtype=np.float64)
    cv = np.asarray(coef_var, dtype=np.float64)
    for name, a in (("coef", c), ("coef_var", cv)):
        if a.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), one per row, got {a.shape}")
        bad = int(np.count_nonzero(np.isinf(a)))
        if bad:
            raise ValueError(f"{name} must be finite or NaN, got {bad} infinite entries")
    known = np.isfinite(c)
    bad = int(np.count_nonzero(known & ~(cv >= 0)))
    if bad:
        raise ValueError(f"coef_var must be non-negative and finite where coef is, got {bad} "
                         "entries that are not")
    usable = np.isfinite(v) & np.isfinite(s)
    count = usable.sum(axis=1)
    scale = r[-1] ** order
    x = (r / r[-1]) ** order
    c_scaled, var_scaled = c * scale, cv * scale ** 2
    with np.errstate(invalid="ignore"):
        if bias_noise == "subtract":
            b2 = np.maximum(c_scaled ** 2 - var_scaled, 0.0)
        else:
            b2 = c_scaled ** 2
    b2 = np.where(known, b2, 0.0)                 # no coefficient: no bias estimate
    mse = np.where(usable, s * s + b2[:, None] * x[None, :] ** 2, np.inf)
    index = np.argmin(mse, axis=1).astype(np.int64)
    index[count == 0] = -1
    rows = np.arange(n)
    ok = index >= 0
    col = np.where(ok, index, 0)

    def pick(a):
        return np.where(ok, a[rows, col], np.nan)

    chosen_x = np.where(ok, x[col], np.nan)
    return Selection(index=index, radius=np.where(ok, r[col], np.nan), value=pick(v),
                     se=pick(s), error=np.sqrt(pick(mse)),
                     coef=np.where(ok, c, np.nan),
                     coef_se=np.where(ok & known, np.sqrt(cv), np.nan),
                     bias=c_scaled * chosen_x)


def select_by_error(values, se, radii, order=2, *, correlation="nested",
                    bias_noise="subtract"):
    """Choose per point the radius of least predicted error ``sqrt(SE^2 + bias^2)``.

    Parameters
    ----------
    values : array_like, shape (N, k)
        The estimate at each radius (one column per radius, ascending radii), NaN where
        that radius failed at that point.
    se : array_like, shape (N, k)
        Its standard errors, same unit, non-negative, NaN where unknown.
    radii : array_like, shape (k,)
        The radii, strictly increasing, positive, in the points' length unit ``L``.
    order : float, default 2
        The bias's leading power of ``r``: ``bias = c r^order``. 2 for the mean curvature
        of MLS0, MLS1 and MLS2 (module docstring: paper Theorem 6, Lemma 2, Theorem 5).
    correlation : {"nested", "independent"}
        How the estimates at the radii are correlated (module docstring).
    bias_noise : {"subtract", "none"}
        ``"subtract"``: the squared bias is ``max(c_hat^2 - Var(c_hat), 0) r^(2 order)``;
        ``"none"``: ``c_hat^2 r^(2 order)``.

    Returns
    -------
    Selection
        ``index`` (int64, -1 where no radius is usable), ``radius``, ``value``, ``se``,
        ``error`` (predicted, same unit as values), ``coef`` (``c_hat``), ``coef_se``,
        ``bias`` (``c_hat r^order`` at the chosen radius), each of shape (N,).

    Examples
    --------
    >>> import numpy as np
    >>> r = np.array([0.1, 0.2, 0.4])
    >>> h = 1.0 + 5.0 * r ** 2                      # H0 = 1, c = 5, exact
    >>> sel = select_by_error(h[None, :], [[0.2, 0.05, 0.0125]], r)
    >>> int(sel.index[0]), round(float(sel.coef[0]), 6)
    (1, 5.0)
    """
    _check(values, se, radii, order, correlation, bias_noise)
    fit = fit_bias(values, se, radii, order, correlation=correlation)
    return choose(values, se, radii, fit.coef, fit.coef_var, order, bias_noise=bias_noise)
