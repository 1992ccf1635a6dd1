"""kernels/ball_mean.cl (clcurv.ops.pooling.ball_mean) against its float64 oracle
(clcurv.reference.pooling, cKDTree), on every device and both precisions.

Tolerance: the mean within ``TOL[precision]`` of the values' half-range (the kernel sums
values centred on their midpoint), the weight sum within ``TOL`` relative. Measured on the
clouds below (default device): float 1.0e-7, double 2.7e-14 of the half-range.
"""
import numpy as np
import pytest

from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.pooling import ball_mean, pool_bias
from clcurv.ops.selection import BiasFit
from clcurv.reference.pooling import ball_mean as ref_ball_mean

TOL = {"float": 1e-5, "double": 1e-12}


def precisions(device):
    return ["float"] + (["double"] if device.info.fp64 else [])


def slab(n=6000, seed=0):
    """Points in a thin slab (a surface-like cloud) far from the origin, a field with an
    offset of 100, 10% NaN values, weights in [0, 1) with 5% NaN."""
    rng = np.random.default_rng(seed)
    p = rng.random((n, 3)) * [1.0, 1.0, 0.05] + [1000.0, -500.0, 20.0]
    v = 100.0 + rng.normal(size=n)
    v[rng.random(n) < 0.1] = np.nan
    w = rng.random(n)
    w[rng.random(n) < 0.05] = np.nan
    return p, v, w


def check_ball_mean(cloud, points, values, radius, weights, precision):
    mean, wsum = ball_mean(cloud, values, radius, weights, return_weight=True)
    ref, ref_w = ref_ball_mean(points, values, radius, weights)
    assert mean.dtype == np.float64 and mean.shape == (len(points),)
    assert np.array_equal(np.isnan(mean), np.isnan(ref))
    half = 0.5 * np.ptp(values[np.isfinite(values)])
    err = np.abs(mean - ref)
    worst = np.nanargmax(err) if np.isfinite(err).any() else 0
    assert np.nanmax(err, initial=0.0) <= TOL[precision] * half, (worst, mean[worst], ref[worst])
    assert np.allclose(wsum, ref_w, rtol=TOL[precision], atol=0)
    return mean, wsum


@pytest.mark.parametrize("weighted", [False, True], ids=["uniform", "weighted"])
@pytest.mark.parametrize("frac", [0.2, 1.0], ids=["r=0.2cell", "r=cell"])   # pruned / not
def test_ball_mean_matches_the_reference(device, weighted, frac):
    p, v, w = slab()
    for precision in precisions(device):
        cloud = DeviceCloud(p, 0.06, device=device.info.index, precision=precision)
        check_ball_mean(cloud, p, v, frac * 0.06, w if weighted else None, precision)


def test_unweighted_weight_sum_is_the_count_of_finite_values(device):
    p, v, _ = slab(2000, seed=1)
    cloud = DeviceCloud(p, 0.05, device=device.info.index)
    mean, count = ball_mean(cloud, v, 0.05, return_weight=True)
    _, ref_count = ref_ball_mean(p, v, 0.05)
    assert np.array_equal(count, ref_count)
    # constant weights change nothing (they are scaled by their largest on the host)
    assert np.allclose(ball_mean(cloud, v, 0.05, np.full(len(p), 7.5)), mean, rtol=0,
                       atol=TOL["float"] * 5, equal_nan=True)


def test_nan_values_and_empty_balls(device):
    """An isolated point's ball is itself: its own value, or NaN (and weight 0) if that is
    NaN; a NaN neighbour is skipped, not averaged; a NaN or 0 weight removes the point."""
    p = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.6, 0, 0], [5.0, 0, 0], [9.0, 0, 0]])
    v = np.array([1.0, np.nan, 3.0, 4.0, np.nan])
    for precision in precisions(device):
        cloud = DeviceCloud(p, 1.0, device=device.info.index, precision=precision)
        mean, wsum = ball_mean(cloud, v, 1.0, return_weight=True)
        assert mean[:3].tolist() == [2.0, 2.0, 2.0] and wsum[:3].tolist() == [2, 2, 2]
        assert mean[3] == 4.0 and wsum[3] == 1
        assert np.isnan(mean[4]) and wsum[4] == 0
        w = np.array([1.0, 1.0, np.nan, 2.0, 1.0])
        mean, wsum = ball_mean(cloud, v, 0.5, w, return_weight=True)   # balls of 0.5
        assert mean[0] == 1.0 and mean[1] == 1.0 and wsum[1] == 1.0   # 1: own NaN, 2's weight NaN
        assert np.isnan(mean[2]) and wsum[2] == 0                       # 2: NaN weight, 1 NaN
        assert mean[3] == 4.0 and wsum[3] == 2.0
        zero = ball_mean(cloud, v, 1.0, np.array([0.0, 1, 0, 0, 1]))
        assert np.isnan(zero[0]) and np.isnan(zero[3])           # weights sum to 0: NaN
        allnan = ball_mean(cloud, np.full(5, np.nan), 1.0, return_weight=True)
        assert np.all(np.isnan(allnan[0])) and np.all(allnan[1] == 0)


def test_deterministic(device):
    p, v, w = slab(3000, seed=2)
    cloud = DeviceCloud(p, 0.06, device=device.info.index)
    a = ball_mean(cloud, v, 0.05, w)
    b = ball_mean(cloud, v, 0.05, w)
    assert np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(values=np.ones(3)), ValueError, "shape"),
    (dict(values=np.array([1.0, np.inf, 0, 0, 0])), ValueError, "infinite"),
    (dict(weights=-np.ones(5)), ValueError, "non-negative"),
    (dict(weights=np.full(5, np.inf)), ValueError, "infinite"),
    (dict(radius=2.0), ValueError, "cell size"),
    (dict(cloud=np.zeros((5, 3))), TypeError, "DeviceCloud"),
])
def test_bad_input_raises(device, kwargs, error, match):
    p = np.random.default_rng(0).random((5, 3))
    args = dict(cloud=DeviceCloud(p, 1.0, device=device.info.index), values=np.ones(5), radius=0.5)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        ball_mean(**args)


def test_pool_bias_is_the_ball_mean_of_the_coefficient(device):
    """pool_bias: the inverse-variance (or plain) mean of c over the ball, its variance as
    if the c_q were independent (1 / sum w; mean Var / count); exact rows weigh most."""
    p, c, _ = slab(3000, seed=3)
    var = np.random.default_rng(4).uniform(0.5, 2.0, len(p))
    fit = BiasFit(coef=c, coef_var=np.where(np.isfinite(c), var, np.nan))
    cloud = DeviceCloud(p, 0.06, device=device.info.index)
    pooled = pool_bias(cloud, fit, 0.05)
    ref, wsum = ref_ball_mean(p, c, 0.05, 1.0 / var)
    half = 0.5 * np.ptp(c[np.isfinite(c)])
    assert np.allclose(pooled.coef, ref, rtol=0, atol=TOL["float"] * half, equal_nan=True)
    assert np.allclose(pooled.coef_var, 1.0 / wsum, rtol=1e-5, equal_nan=True)
    uni = pool_bias(cloud, fit, 0.05, weights="uniform")
    ref_u, count = ref_ball_mean(p, c, 0.05)
    ref_v, _ = ref_ball_mean(p, fit.coef_var, 0.05)
    assert np.allclose(uni.coef, ref_u, rtol=0, atol=TOL["float"] * half, equal_nan=True)
    assert np.allclose(uni.coef_var, ref_v / count, rtol=1e-5, equal_nan=True)
    # an exact row (Var 0) dominates its neighbours; all exact: the plain mean
    q = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])
    small = DeviceCloud(q, 1.0, device=device.info.index)
    exact = pool_bias(small, BiasFit(np.array([1.0, 5.0, 9.0]), np.array([0.0, 1, 1])), 0.15)
    assert exact.coef[0] == pytest.approx(1.0) and exact.coef[2] == pytest.approx(7.0)
    flat = pool_bias(small, BiasFit(np.array([1.0, 5.0, 9.0]), np.zeros(3)), 0.15)
    assert flat.coef.tolist() == [3.0, 5.0, 7.0]
    with pytest.raises(ValueError, match="weights"):
        pool_bias(small, exact, 0.1, weights="median")
