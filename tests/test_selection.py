"""A radius per point by predicted error (clcurv.ops.selection, issue 51), host-side NumPy.

* exact synthetic inputs ``v_j = H0 + c r_j^2``: the fitted ``c`` and its SE equal a dense
  generalised least squares with the stated covariance (nested: ``min(s_i, s_j)^2``;
  independent: ``diag(s^2)``), and the chosen column is the analytic optimum of
  ``s_j^2 + max(c^2 - Var(c), 0) r_j^4``;
* NaN columns, one usable radius, ``k = 1``, all-NaN rows, SE = 0; bad input raises;
* shapes.chirp's truth against finite differences of its documented profile;
* the issue's target through the float64 reference (MLS2's H on a noisy chirp, 4 radii):
  measured, with what is and is not met (module docstring of this test's last section).
"""
import numpy as np
import pytest
from scipy.integrate import cumulative_trapezoid
from scipy.interpolate import CubicSpline

from clcurv.data import shapes
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.pooling import pool_bias
from clcurv.ops.selection import choose, fit_bias, select_by_error
from clcurv.reference.uncertainty import mls2_uncertainty

RADII = np.array([0.1, 0.16, 0.256, 0.4096])


def dense_gls(v, s, radii, order, correlation):
    """(c, Var(c)) of v = H0 + c r^order by dense GLS, for one row (the oracle)."""
    x = radii ** order
    if correlation == "nested":
        # (the module floors Var(v_i - v_j) at 1% of s_i^2 + s_j^2: inactive here, SEs differ)
        cov = np.minimum.outer(s ** 2, s ** 2)
    else:
        cov = np.diag(s ** 2)
    a = np.stack([np.ones_like(x), x], axis=1)
    ci = np.linalg.inv(cov)
    info = a.T @ ci @ a
    beta = np.linalg.solve(info, a.T @ ci @ v)
    return beta[1], np.linalg.inv(info)[1, 1]


@pytest.mark.parametrize("correlation", ["nested", "independent"])
@pytest.mark.parametrize("c", [0.0, 0.3, 2.0, 8.0, -8.0, 40.0])
def test_exact_quadratic_picks_the_analytic_optimum(correlation, c):
    s = 0.05 * (RADII[0] / RADII) ** 3                  # MLS2-like: SE ~ r^-3
    v = 1.5 + c * RADII ** 2
    sel = select_by_error(v[None], s[None], RADII, correlation=correlation)
    c_ref, var_ref = dense_gls(v, s, RADII, 2, correlation)
    assert sel.coef[0] == pytest.approx(c, abs=1e-9)
    assert sel.coef_se[0] ** 2 == pytest.approx(var_ref, rel=1e-9)
    mse = s ** 2 + max(c * c - var_ref, 0.0) * RADII ** 4
    assert sel.index[0] == np.argmin(mse)
    assert sel.error[0] == pytest.approx(np.sqrt(mse.min()), rel=1e-12)
    assert sel.radius[0] == RADII[sel.index[0]] and sel.value[0] == v[sel.index[0]]
    assert sel.bias[0] == pytest.approx(c * RADII[sel.index[0]] ** 2, abs=1e-12)
    none = select_by_error(v[None], s[None], RADII, correlation=correlation, bias_noise="none")
    assert none.index[0] == np.argmin(s ** 2 + c * c * RADII ** 4)


def test_noisy_rows_agree_with_dense_gls_and_the_optimum_moves_with_c():
    rng = np.random.default_rng(3)
    s = 0.05 * (RADII[0] / RADII) ** 3
    cs = np.array([0.0, 1.0, 4.0, 16.0, 64.0])
    v = 1.0 + cs[:, None] * RADII ** 2 + rng.normal(size=(5, 4)) * s
    for corr in ("nested", "independent"):
        sel = select_by_error(v, np.tile(s, (5, 1)), RADII, correlation=corr)
        for i in range(5):
            c_ref, var_ref = dense_gls(v[i], s, RADII, 2, corr)
            assert sel.coef[i] == pytest.approx(c_ref, rel=1e-9, abs=1e-9)
            assert sel.coef_se[i] == pytest.approx(np.sqrt(var_ref), rel=1e-9)
    exact = select_by_error(1.0 + cs[:, None] * RADII ** 2, np.tile(s, (5, 1)), RADII)
    assert np.all(np.diff(exact.index) <= 0)          # more bias, smaller radius
    assert exact.index[0] == 3 and exact.index[-1] == 0


def test_order_is_the_power_of_the_bias():
    s = np.full(4, 1e-3)
    v = 2.0 + 7.0 * RADII ** 3
    sel = select_by_error(v[None], s[None], RADII, order=3, correlation="independent")
    assert sel.coef[0] == pytest.approx(7.0, rel=1e-9)


def test_nan_columns_rows_and_single_radius():
    s = 0.05 * (RADII[0] / RADII) ** 3
    v = 1.0 + 3.0 * RADII ** 2
    rows = np.tile(v, (5, 1))
    ses = np.tile(s, (5, 1))
    rows[1, 2] = np.nan                      # a failed middle radius: fit on the others
    ses[2, 0] = np.nan                       # an unknown SE makes its column unusable
    rows[3, :3] = np.nan                     # one usable radius
    rows[4, :] = np.nan                      # none
    sel = select_by_error(rows, ses, RADII)
    assert sel.coef[1] == pytest.approx(3.0) and sel.index[1] != 2
    assert sel.coef[2] == pytest.approx(3.0) and sel.index[2] != 0
    assert sel.index[3] == 3 and np.isnan(sel.coef[3]) and np.isnan(sel.coef_se[3])
    assert sel.error[3] == s[3] and np.isnan(sel.bias[3])
    assert sel.index[4] == -1
    for field in ("radius", "value", "se", "error", "coef", "coef_se", "bias"):
        assert np.isnan(getattr(sel, field)[4]), field
    one = select_by_error(v[:1, None].T[:, :1], s[None, :1], RADII[:1])
    assert one.index.tolist() == [0] and np.isnan(one.coef[0]) and one.error[0] == s[0]
    empty = select_by_error(np.empty((0, 4)), np.empty((0, 4)), RADII)
    assert empty.index.shape == (0,) and empty.error.shape == (0,)


def test_zero_standard_errors():
    v = 1.0 + 3.0 * RADII ** 2
    exact = select_by_error(v[None], np.zeros((1, 4)), RADII)     # noise-free: unweighted
    assert exact.coef[0] == pytest.approx(3.0) and exact.coef_se[0] == 0.0
    assert exact.index[0] == 0 and exact.error[0] == pytest.approx(3.0 * RADII[0] ** 2)
    flat = select_by_error(np.ones((1, 4)), np.zeros((1, 4)), RADII)
    assert flat.index[0] == 0 and flat.error[0] == 0.0            # ties: the smaller radius
    s = 0.05 * (RADII[0] / RADII) ** 3
    s[3] = 0.0                                                    # one exact column
    mixed = select_by_error(v[None], s[None], RADII)
    assert np.isfinite(mixed.coef[0]) and mixed.coef[0] == pytest.approx(3.0)


@pytest.mark.parametrize("kwargs, match", [
    (dict(values=np.ones(4), se=np.ones(4)), "shape"),
    (dict(se=np.ones((2, 3))), "shape of values"),
    (dict(radii=RADII[:3]), "one per column"),
    (dict(radii=RADII[::-1]), "strictly increasing"),
    (dict(radii=np.array([0.0, 1, 2, 3])), "positive"),
    (dict(se=-np.ones((2, 4))), "non-negative"),
    (dict(values=np.full((2, 4), np.inf)), "infinite"),
    (dict(order=0), "order"),
    (dict(order=np.nan), "order"),
    (dict(correlation="full"), "correlation"),
    (dict(bias_noise="half"), "bias_noise"),
    (dict(values=np.ones((2, 0)), se=np.ones((2, 0)), radii=np.ones(0)), "at least one"),
])
def test_bad_input_raises(kwargs, match):
    args = dict(values=np.ones((2, 4)), se=np.ones((2, 4)), radii=RADII)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        select_by_error(**args)


# --- the chirp's truth against finite differences of its documented profile ---
def test_chirp_truth_matches_finite_differences():
    amp, wl, ext, power = 0.05, (1.0, 0.25), (2.0, 0.5), 0.5
    s = shapes.chirp(4000, amp, wl, ext, power, seed=2)
    w0, w1 = 2 * np.pi / wl[0], 2 * np.pi / wl[1]
    b = np.log(w1 / w0) / ext[0]
    grid = np.linspace(-0.01, ext[0] + 0.01, 200001)  # phi by numerical integration of w(x)
    w = w0 * np.exp(b * grid)
    phi = CubicSpline(grid, cumulative_trapezoid(w, grid, initial=0.0) - w0 * (1 - np.exp(
        -0.01 * b)) / b)                             # phi(0) = 0: the exact integral over [-0.01, 0]

    def f(x):
        return amp * (w0 / (w0 * np.exp(b * x))) ** power * np.sin(phi(x))

    x, y, z = s["points"].T
    assert np.allclose(z, f(x), atol=1e-9)
    h = 1e-4
    f1 = (f(x + h) - f(x - h)) / (2 * h)
    f2 = (f(x + h) - 2 * f(x) + f(x - h)) / h ** 2
    ww = np.sqrt(1 + f1 ** 2)
    kappa = -f2 / ww ** 3
    scale = np.abs(kappa).max()
    assert np.allclose(s["H"], kappa / 2, atol=1e-5 * scale)
    assert np.allclose(s["k1"] + s["k2"], kappa, atol=1e-5 * scale)
    assert np.all(s["k1"] >= s["k2"]) and np.all(s["K"] == 0) and np.all(s["k1"] * s["k2"] == 0)
    nrm = np.stack([-f1, 0 * f1, np.ones_like(f1)], axis=1) / ww[:, None]
    assert np.allclose(s["normals"], nrm, atol=1e-7)
    assert np.allclose(s["omega"], w0 * np.exp(b * x))
    # the envelope's growth: (w1 / w0)^(2 - power) = 8 between the ends; over windows of
    # 0.2 at the ends the largest |H| is that over exp(0.2 b (2 - power)) (the window's width)
    lo, hi = x < 0.2, x > ext[0] - 0.2
    ratio = np.abs(s["H"][hi]).max() / np.abs(s["H"][lo]).max()
    expected = 8.0 / np.exp(0.2 * b * (2 - power))
    assert 0.85 * expected < ratio < 1.15 * expected


# --- the issue's target through the float64 reference ---
#: a chirp of constant slope 0.5 (power 1): |H| envelope 1 to 10 (10x) across x, wavelengths
#: 1.57 to 0.157; 20000 points on 2 x 0.6 (~31 neighbours at the smallest radius, ~510 at
#: the largest); radii 0.025 * 1.6^j; noise sigma = 0.00026 along the normal, 0.5% of the
#: median radius (r1 + r2) / 2 = 0.052.
CHIRP = dict(amplitude=0.125, wavelengths=(2 * np.pi / 4, 2 * np.pi / 40), extent=(2.0, 0.6),
             power=1.0)
TARGET_RADII = 0.025 * 1.6 ** np.arange(4)
SIGMA = 0.00026


@pytest.fixture(scope="module")
def chirp_run():
    s = shapes.chirp(20000, **CHIRP, noise=SIGMA, seed=1)
    cols = [mls2_uncertainty(s["points"], r, s["normals"]) for r in TARGET_RADII]
    values = np.stack([c["mean"] for c in cols], axis=1)
    se = np.stack([c["mean_se"] for c in cols], axis=1)
    # interior: the largest ball lies inside the sampled rectangle (no border point)
    x, y = s["points"][:, 0], s["points"][:, 1]
    rmax, (lx, ly) = TARGET_RADII[-1], CHIRP["extent"]
    inner = (x > rmax) & (x < lx - rmax) & (y > rmax) & (y < ly - rmax)
    return s, values, se, inner


def pooled(chirp_run, radius=TARGET_RADII[1]):
    """choose() after pool_bias (inverse-variance mean of c_hat over the ball of ``radius``,
    by kernels/ball_mean.cl on the default device, float)."""
    s, values, se, _ = chirp_run
    fit = fit_bias(values, se, TARGET_RADII)
    pool = pool_bias(DeviceCloud(s["points"], TARGET_RADII[-1]), fit, radius)
    return choose(values, se, TARGET_RADII, pool.coef, pool.coef_var)


def figures(chirp_run, sel=None, **kwargs):
    s, values, se, inner = chirp_run
    if sel is None:
        sel = select_by_error(values, se, TARGET_RADII, **kwargs)
    assert np.all(sel.index[inner] >= 0)
    err = np.abs(values - s["H"][:, None])[inner]
    chosen = np.abs(sel.value - s["H"])[inner]
    fixed = np.median(err, axis=0)
    best = int(np.argmin(fixed))
    a = np.abs(s["H"][inner])
    edges = np.quantile(a, np.linspace(0, 1, 11))
    dec = np.clip(np.searchsorted(edges, a, "right") - 1, 0, 9)
    per = np.array([[np.median(err[dec == d, j]) for j in range(4)] for d in range(10)])
    sel_dec = np.array([np.median(chosen[dec == d]) for d in range(10)])
    return {"fixed": fixed, "best": best, "selected": float(np.median(chosen)),
            "ratio": float(np.median(chosen) / fixed[best]), "per_decile": per,
            "selected_decile": sel_dec, "vs_best": sel_dec / per[:, best],
            "vs_best_in_decile": sel_dec / per.min(axis=1),
            "counts": np.bincount(sel.index[inner], minlength=4)}


def test_selection_beats_every_fixed_radius_in_median(chirp_run):
    """Measured (seed 1, 11771 interior points, setup ~11 s): median |H - H_true| at the
    fixed radii 0.025, 0.04, 0.064, 0.1024: 0.389, 0.117, 0.0514, 0.0735 (best: 0.064);
    selected (nested, subtract): 0.0480, 6.7% below the best fixed radius (chosen 250,
    3198, 4203, 4120 times). Per decile of |H_true|, selected / best fixed radius: 1.04
    0.85 0.92 0.77 1.02 1.04 1.10 1.12 0.66 0.39. The issue's target (20%, every decile) is
    not met: xfail below."""
    f = figures(chirp_run)
    print({k: np.round(v, 4) for k, v in f.items()})
    assert TARGET_RADII[f["best"]] == pytest.approx(0.064)
    assert f["ratio"] < 0.96
    # no decile of |H_true| loses more than 20% against the best fixed radius (measured: 12%)
    assert np.all(f["vs_best"] < 1.2)
    # and where the curvature is largest (top two deciles) it wins by a wide margin
    assert np.all(f["vs_best"][8:] < 0.7)


def test_pooled_coefficient_beats_the_per_point_fit(chirp_run):
    """c_hat pooled over the ball of the second radius (inverse variance, the kernel on the
    default device): median 16.6% below the best fixed radius (0.0429 against 0.0515; the
    per-point fit: 6.7%); per decile of |H_true| 0.97 0.71 0.77 0.63 1.00 0.97 1.00 1.09
    0.61 0.40 (measured, float; clcurv.ops.selection's docstring: the other poolings)."""
    f = figures(chirp_run, pooled(chirp_run))
    print({k: np.round(v, 4) for k, v in f.items()})
    assert f["ratio"] < 0.86
    assert f["ratio"] < figures(chirp_run)["ratio"] - 0.08
    assert np.all(f["vs_best"] < 1.12) and np.all(f["vs_best"][8:] < 0.65)


@pytest.mark.xfail(strict=True, reason="issue 51's target not met: the best measured, c_hat "
                   "pooled over the second radius's ball (inverse variance), is 16.6% (not "
                   "20%) below the best fixed radius, deciles 4, 6, 7 of |H_true| 0-9% above it; "
                   "a larger Var(c_hat) (correlated neighbours) or a pretest |c| > 1.96 SE is "
                   "no better (seed 2, noise x0.5, x2 too); the limit is the model c r^2: fitted "
                   "to the noise-free estimates it gives 18.4%, the true bias 33% "
                   "(clcurv.ops.selection's docstring)")
def test_issue_target_twenty_percent_and_every_decile(chirp_run):
    f = figures(chirp_run, pooled(chirp_run))
    assert f["ratio"] <= 0.8 and np.all(f["vs_best"] < 1.0)
