"""Means of a per-point field over each point's ball, on the device (kernels/ball_mean.cl):
the pooling of a noisy per-point estimate over its neighbours (issue 51: the bias
coefficient of :mod:`clcurv.ops.selection`, pooled between its fit and the choice).

``ball_mean(cloud, values, radius)`` is, for every point p of a
:class:`~clcurv.grid.cloud.DeviceCloud`, the mean of ``values`` over
``N_r(p) = {q : |q - p| < r}`` (p included; the operators' ball, tested by the same
expression, kernels/neighbors.h), weighted by ``weights`` if given. The float64 oracle is
:func:`clcurv.reference.pooling.ball_mean` (cKDTree).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from clcurv._shared.constants import PAD
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import row_prune
from clcurv.ops.selection import BiasFit
from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import build, launch

__all__ = ["ball_mean", "pool_bias", "POOL_WEIGHTS"]

#: How :func:`pool_bias` weights the neighbours' coefficients
POOL_WEIGHTS = ("inverse_variance", "uniform")
#: inverse-variance pooling floors Var(c_q) at this fraction of the largest
VAR_FLOOR = 1e-12


def _field(values, n, name):
    """``values`` as a float64 (N,) array: finite or NaN, no infinity."""
    a = np.asarray(values, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), one per point of the cloud, "
                         f"got {a.shape}")
    bad = int(np.count_nonzero(np.isinf(a)))
    if bad:
        raise ValueError(f"{name} must be finite or NaN, got {bad} infinite entries")
    return a


def _sorted_padded(cloud, a):
    """``a`` (input order, float64) in the cloud's sorted order, device precision, PAD zeros
    after: a read-only device buffer."""
    host = np.zeros(cloud.n + PAD, dtype=cloud.dtype)
    host[:cloud.n] = a[cloud.grid.order]
    mf = cl.mem_flags
    return cl.Buffer(cloud.device.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=host)


def ball_mean(cloud, values, radius, weights=None, *, return_weight=False):
    """The (weighted) mean of a per-point field over every point's ball, on the device.

    Parameters
    ----------
    cloud : DeviceCloud
        The points, binned on their device (its precision is the arithmetic's).
    values : array_like, shape (N,)
        One value per point of ``cloud``, input order; NaN where unknown. A NaN value is
        skipped (the mean is over the ball's finite values); infinities raise ValueError.
    radius : float, same length unit as the points
        The ball ``|q - p| < radius`` (p included), at most ``cloud.cell``.
    weights : array_like, shape (N,), optional
        Non-negative weight of each point as a neighbour (say ``1 / Var``), NaN to skip the
        point; infinities and negatives raise ValueError. Default: every weight 1.
    return_weight : bool
        Also return the sum of the contributing weights (the count of finite values in the
        ball when unweighted).

    Returns
    -------
    mean : ndarray, shape (N,), float64, input order
        ``sum w_q v_q / sum w_q`` over the q of p's ball with ``v_q`` and ``w_q`` finite;
        NaN where no neighbour contributes (every value NaN, or the weights sum to 0).
    weight : ndarray, shape (N,), float64 (``return_weight`` only)
        ``sum w_q`` over the same q, 0 where none.

    Notes
    -----
    The values are centred in float64 on the host (the midpoint of their finite range is
    subtracted before the cast to the device precision and added back after), and the
    weights scaled by their largest, so float32 sums lose no digits to an offset and cannot
    overflow; a weight below ``1e-38`` times the largest flushes to 0 in float32. Against
    the float64 reference the mean agrees to about ``1e-5`` (float) or ``1e-12`` (double)
    of the values' half-range (tests/test_pooling.py). One work-item per point, fixed
    summation order: the same device gives the same bits every time.

    Examples
    --------
    >>> import numpy as np
    >>> from clcurv.grid.cloud import DeviceCloud
    >>> pts = np.array([[0.0, 0, 0], [0.5, 0, 0], [2.0, 0, 0]])
    >>> cloud = DeviceCloud(pts, 1.0)
    >>> ball_mean(cloud, [1.0, 3.0, np.nan], 1.0).tolist()
    [2.0, 2.0, nan]
    """
    if not isinstance(cloud, DeviceCloud):
        raise TypeError(f"cloud must be a DeviceCloud, got {type(cloud).__name__}")
    n = cloud.n
    v = _field(values, n, "values")
    r = cloud.check_radius(radius)
    w = None
    if weights is not None:
        w = _field(weights, n, "weights")
        neg = int(np.count_nonzero(w < 0))
        if neg:
            raise ValueError(f"weights must be non-negative (or NaN), got {neg} negative entries")
    finite = np.isfinite(v) if w is None else np.isfinite(v) & np.isfinite(w)
    wmax = float(np.max(w[finite], initial=0.0)) if w is not None else 1.0
    if not finite.any() or wmax == 0:            # nothing can contribute: no kernel
        mean = np.full(n, np.nan)
        return (mean, np.zeros(n)) if return_weight else mean
    lo, hi = float(v[finite].min()), float(v[finite].max())
    shift = 0.5 * (lo + hi)
    if 0.5 * (hi - lo) > 0.01 * np.finfo(cloud.dtype).max:
        raise ValueError(f"values span [{lo:.3g}, {hi:.3g}], too wide for "
                         f"precision={cloud.precision!r} sums")
    item = np.dtype(cloud.dtype).itemsize
    plan = cloud.plan("ball_mean", 2 * item, reserve=(1 + (w is not None)) * item,
                      label="the coordinates, the grid and the pooled field")
    prune = row_prune(cloud, r)
    ranges = cloud.with_middles() if prune else cloud.ranges
    prg = build(cloud.device, "ball_mean.cl",
                dict(cloud.defines, WEIGHTED=int(w is not None), ROW_PRUNE=prune))
    vbuf = _sorted_padded(cloud, v - shift)
    wbuf = _sorted_padded(cloud, w / wmax) if w is not None else vbuf
    mean_s = np.empty(n, dtype=cloud.dtype)
    wsum_s = np.empty(n, dtype=cloud.dtype)
    out_m = device_buffer(cloud.device, plan.chunk * item)
    out_w = device_buffer(cloud.device, plan.chunk * item)
    q = cloud.device.queue
    for first, stop in plan.ranges():
        launch(cloud.device, prg.ball_mean, stop - first, cloud.x, cloud.y, cloud.z,
               cloud.cell_of, ranges, np.uint32(n), np.uint32(first), np.uint32(stop),
               cloud.ball(r), vbuf, wbuf, out_m, out_w)
        cl.enqueue_copy(q, mean_s[first:stop], out_m)
        cl.enqueue_copy(q, wsum_s[first:stop], out_w)
    q.finish()
    order = cloud.grid.order
    mean = np.empty(n)
    mean[order] = mean_s.astype(np.float64) + shift
    if not return_weight:
        return mean
    weight = np.empty(n)
    weight[order] = wsum_s.astype(np.float64) * wmax
    return mean, weight


def pool_bias(cloud, fit, radius, *, weights="inverse_variance", mean=None):
    """The bias coefficient of :func:`clcurv.ops.selection.fit_bias` pooled over every
    point's ball, for :func:`clcurv.ops.selection.choose` (issue 51).

    Parameters
    ----------
    cloud : DeviceCloud
        The points whose rows ``fit`` holds, input order.
    fit : BiasFit
        ``coef`` and ``coef_var`` per point (:func:`~clcurv.ops.selection.fit_bias`).
    radius : float, same length unit as the points
        The pooling ball ``|q - p| < radius``; at most ``cloud.cell``. Measured best on the
        chirp (clcurv.ops.selection's docstring): the second of the four radii.
    weights : {"inverse_variance", "uniform"}
        ``w_q = 1 / Var(c_q)`` (``Var(c_q)`` floored at ``VAR_FLOOR`` times the
        largest, so an exact row, ``Var`` 0, weighs most; every weight 1 when all are 0),
        or every finite ``c_q`` alike.
    mean : callable, optional
        ``mean(values, radius, weights) -> (mean, weight sum)``, the ball mean to pool
        with (default :func:`ball_mean` on ``cloud``; ``backend="numpy"`` passes the
        float64 reference's, :func:`clcurv.reference.pooling.ball_mean`).

    Returns
    -------
    BiasFit
        ``coef``: the weighted mean of ``c_q`` over the ball (NaN values skipped; NaN where
        none is finite); ``coef_var``: its variance **as if the c_q were independent**,
        ``sum w^2 Var(c_q) / (sum w)^2`` (``1 / sum w`` for inverse-variance weights).

    Notes
    -----
    Neighbouring ``c_q`` are correlated (their balls overlap and share points), so the
    independent variance understates the pooled one: :func:`~clcurv.ops.selection.choose`
    then subtracts too little from ``coef^2``. The alternatives measured on the chirp (the
    fully correlated bound ``(sum w sd_q / sum w)^2``, 12.5x, 0, the coefficients' spread in
    the ball, and a pretest ``|coef| > 1.96 SE``) were no better (clcurv.ops.selection's
    docstring: the pooled noise is small against what the model ``c r^2`` misses). The mean
    is also biased towards the ball's average coefficient where ``c`` varies within the
    ball (it changes sign across a ridge): hence a small pooling radius.
    """
    if weights not in POOL_WEIGHTS:
        raise ValueError(f"weights must be one of {POOL_WEIGHTS}, got {weights!r}")
    c = np.asarray(fit.coef, dtype=np.float64)
    var = np.asarray(fit.coef_var, dtype=np.float64)
    if mean is None:
        def mean(v, r, w):
            return ball_mean(cloud, v, r, w, return_weight=True)
    if weights == "uniform":
        avg, count = mean(c, radius, None)
        with np.errstate(invalid="ignore", divide="ignore"):
            pooled_var = mean(np.where(np.isfinite(c), var, np.nan), radius, None)[0] / count
    else:
        # exact rows (Var 0) weigh most: Var floored at VAR_FLOOR of the largest (all 0:
        # noise-free input, every weight 1)
        top = float(np.max(var[np.isfinite(c) & np.isfinite(var)], initial=0.0))
        if top > 0:
            w = 1.0 / np.maximum(var, VAR_FLOOR * top)
        else:
            w = np.where(np.isnan(var), np.nan, 1.0)
        avg, wsum = mean(c, radius, w)
        with np.errstate(divide="ignore"):
            pooled_var = np.where(wsum > 0, 1.0 / wsum, np.nan)
    return BiasFit(coef=avg, coef_var=np.where(np.isfinite(avg), pooled_var, np.nan))
