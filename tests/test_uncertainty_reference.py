"""The float64 reference's error bars (clcurv.reference.uncertainty, issue 51).

* the values beside the errors are :func:`clcurv.reference.operators.mls2`'s and MLS1's;
  the delta method's gradients match finite differences;
* calibration (seeded patches of bench.uncertainty, 10^4 points, ~40 neighbours, interior
  points, radii where the bias is under a tenth of the SE): the z-score
  ``(estimate - truth) / SE`` has its standard deviation in [0.85, 1.2] and 92-97.5% of
  points within 1.96 (the issue's targets), for MLS2's H and k1 and MLS1's H; at a sphere's
  umbilics k1's z is shifted (the larger of two noisy eigenvalues), as documented; at large
  radii the bias breaks calibration;
* scaling: the SE doubles with the noise; MLS2's halves when the density is multiplied by 4,
  MLS1's does not (the point's own noise);
* roughness = sigma within 10% on a noisy plane and sphere;
* Monte Carlo on one neighbourhood: the standard deviation of H over 2000 noise draws equals
  the predicted SE within 10% (MLS2 with the ball and the Gaussian kernel, MLS1).
"""
import numpy as np
import pytest

from bench.uncertainty import patch
from clcurv.data import shapes
from clcurv.reference import operators as ops
from clcurv.reference import uncertainty as unc

STD_RANGE = (0.85, 1.2)
COVER_RANGE = (0.92, 0.975)
KMAX = {"sphere": 1.0, "ellipsoid": 2.3, "wave": 0.1 * (2 * np.pi) ** 2}


def zscore(shape, kr, c, estimator, seed=0):
    """z of ``estimator`` ('mls2 H', 'mls2 k1', 'mls1 H' (noise='quadric', the default),
    'mls1 H plane') on the interior of a seeded patch at ``r = kr / k_max`` with noise
    ``c r``."""
    r = kr / KMAX[shape]
    s = patch(shape, r, c, seed=seed)
    se_key = None
    if estimator.startswith("mls2"):
        out = unc.mls2_uncertainty(s["points"], r, s["normals"])
        key = {"k1": "k1", "debiased": "k1_debiased"}.get(estimator.split()[-1], "mean")
        se_key = "k1_se" if key.startswith("k1") else None
    else:
        noise = "plane" if estimator.endswith("plane") else "quadric"
        out = unc.mls1_uncertainty(s["points"], r, s["normals"], noise=noise)
        key = "mean"
    truth = s["k1"] if key.startswith("k1") else s["H"]
    z = ((out[key] - truth) / out[se_key or key + "_se"])[s["inner"]]
    assert np.isfinite(z).all()
    return z


def summary(z):
    return float(z.std()), float(np.mean(np.abs(z) < 1.96))


CALIBRATED = [("sphere", 0.04, 0.01, "mls2 H"), ("ellipsoid", 0.08, 0.005, "mls2 H"),
              ("wave", 0.04, 0.02, "mls2 H"), ("ellipsoid", 0.08, 0.01, "mls2 k1"),
              ("wave", 0.04, 0.02, "mls2 k1"), ("sphere", 0.02, 0.01, "mls1 H"),
              ("wave", 0.08, 0.005, "mls1 H"), ("ellipsoid", 0.04, 0.01, "mls1 H"),
              ("ellipsoid", 0.02, 0.01, "mls1 H plane"),
              ("sphere", 0.04, 0.01, "mls2 k1 debiased"),
              ("ellipsoid", 0.08, 0.02, "mls2 k1 debiased")]


@pytest.mark.parametrize("shape,kr,c,estimator", CALIBRATED,
                         ids=[f"{e.replace(' ', '-')}-{s}-kr{k}-c{c}" for s, k, c, e in CALIBRATED])
def test_calibrated(shape, kr, c, estimator):
    std, cover = summary(zscore(shape, kr, c, estimator))
    assert STD_RANGE[0] <= std <= STD_RANGE[1], std
    assert COVER_RANGE[0] <= cover <= COVER_RANGE[1], cover


def test_k1_at_umbilics_is_shifted():
    """On a sphere k1 = max of two noisy eigenvalues: z has mean ~ +0.73 (the order
    statistic, 1.25 SE of the deviator over sqrt(3)), std ~ 0.88, ~91% within 1.96
    (module docstring), below the issue's 92%; H on the same patch is centred, and the
    debiased k1 (test_calibrated) is calibrated."""
    z = zscore("sphere", 0.04, 0.01, "mls2 k1")
    assert 0.6 < z.mean() < 0.85
    std, cover = summary(z)
    assert STD_RANGE[0] <= std <= 0.95
    assert 0.89 < cover < 0.935
    assert abs(zscore("sphere", 0.04, 0.01, "mls2 H").mean()) < 0.1


@pytest.mark.parametrize("estimator,kr", [("mls2 H", 0.64), ("mls1 H", 1.28)])
def test_bias_breaks_calibration(estimator, kr):
    """On the wave (sigma = 0.5% r) the bias dominates the SE at k r = 0.64 for MLS2 and
    at 1.28 for MLS1 (whose SE, ~4 sigma / r^2, is larger)."""
    std, cover = summary(zscore("wave", kr, 0.005, estimator))
    assert std > STD_RANGE[1] or cover < COVER_RANGE[0], (std, cover)


def test_plane_noise_is_conservative_when_curvature_spreads_the_heights():
    """MLS1's plane residual holds the sphere's height spread k^2 r^4 / 48: with
    sigma = 0.5% r at k r = 0.08 it is ~2.6 sigma^2, so z shrinks (std ~ 0.6); the quadric
    noise estimate stays calibrated."""
    std_plane, _ = summary(zscore("sphere", 0.08, 0.005, "mls1 H plane"))
    std_quad, cover = summary(zscore("sphere", 0.08, 0.005, "mls1 H"))
    assert std_plane < 0.8
    assert STD_RANGE[0] <= std_quad <= STD_RANGE[1] and COVER_RANGE[0] <= cover


def plane(n, side, noise, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-side / 2, side / 2, (n, 2))
    pts = np.column_stack([xy, rng.normal(scale=noise, size=n)])
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    return pts, nrm, np.all(np.abs(xy) < side / 2 - 2 * 0.1, axis=1)


def test_values_are_the_operators():
    s = shapes.ellipsoid(3000, (1.0, 0.8, 0.6), noise=0.002, seed=3, cap=0.5)
    r = 0.08
    for kw in ({}, {"weights": "density"}, {"kernel": "gaussian"}):
        got = unc.mls2_uncertainty(s["points"], r, s["normals"], **kw)
        ref = ops.mls2(s["points"], r, s["normals"], **kw)
        np.testing.assert_array_equal(got["status"], ref["status"])
        np.testing.assert_array_equal(got["count"], ref["count"])
        for key in ("mean", "gaussian", "k1", "k2", "normals"):
            np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=1e-9)
        if not kw:                                      # uniform ball: n - 6 residual dof
            np.testing.assert_allclose(got["dof"], got["count"] - 6.0, rtol=0, atol=1e-9)
            np.testing.assert_allclose(got["n_eff"], got["count"], rtol=0, atol=1e-9)
    mom = ops.moments(s["points"], r)
    flip = np.einsum("ij,ij->i", mom["normals"], s["normals"]) < 0
    nrm = np.where(flip[:, None], -mom["normals"], mom["normals"])
    for method in ("mls1", "mls0"):
        got = unc.mls1_uncertainty(s["points"], r, s["normals"], method=method)
        ref = ops.finish(method, mom, s["points"], r, nrm,
                         user=s["normals"] if method == "mls0" else None)
        np.testing.assert_allclose(got["mean"], ref["mean"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["mls1", "mls2"])
def test_normal_se_calibrated(method):
    """The angle between the estimated and the true normal, over its SE: RMS ~1 and ~95%
    below 1.73 SE (an isotropic 2D Gaussian)."""
    r = 0.04 / KMAX["ellipsoid"]
    s = patch("ellipsoid", r, 0.01, seed=5)
    f = unc.mls1_uncertainty if method == "mls1" else unc.mls2_uncertainty
    out = f(s["points"], r, s["normals"])
    cos = np.einsum("ij,ij->i", out["normals"], s["normals"])[s["inner"]]
    a = np.arccos(np.clip(cos, -1, 1)) / out["normal_se"][s["inner"]]
    assert np.sqrt(np.mean(a * a)) == pytest.approx(1.0, abs=0.1)
    assert 0.92 < np.mean(a < np.sqrt(-np.log(0.05))) < 0.975


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    coef = rng.normal(scale=[0.1, 0.3, 0.3, 0.2, 0.2, 0.2], size=(50, 6))
    r = 0.7
    val, jac = unc.curvature_jacobian(coef, r)
    step = 1e-6
    for j in range(6):
        up, dn = coef.copy(), coef.copy()
        up[:, j] += step
        dn[:, j] -= step
        num = (unc.curvature_jacobian(up, r)[0] - unc.curvature_jacobian(dn, r)[0]) / (2 * step)
        np.testing.assert_allclose(jac[:, :, j], num, rtol=1e-5, atol=1e-6)


def test_se_scales_with_noise():
    r = 0.04
    a = patch("ellipsoid", r, 0.01, points=5000, seed=1)
    b = patch("ellipsoid", r, 0.02, points=5000, seed=1)     # same positions, noise x2
    for f, key in ((unc.mls2_uncertainty, "mean_se"), (unc.mls2_uncertainty, "k1_se"),
                   (unc.mls2_uncertainty, "normal_se"), (unc.mls1_uncertainty, "mean_se")):
        sa = f(a["points"], r, a["normals"])[key][a["inner"]]
        sb = f(b["points"], r, b["normals"])[key][b["inner"]]
        assert np.median(sb / sa) == pytest.approx(2.0, rel=0.1), key
    # the plane's noise holds the curvature's spread too: it scales with sigma on a plane
    pa, na, inner = plane(6000, 2.0, 0.002)
    pb = pa.copy()
    pb[:, 2] *= 2.0
    sa = unc.mls1_uncertainty(pa, 0.1, na, noise="plane")["mean_se"][inner]
    sb = unc.mls1_uncertainty(pb, 0.1, na, noise="plane")["mean_se"][inner]
    assert np.median(sb / sa) == pytest.approx(2.0, rel=0.1)
    sa = unc.pca_uncertainty(pa, 0.1)["normal_se"][inner]          # the PCA normal's too
    sb = unc.pca_uncertainty(pb, 0.1)["normal_se"][inner]
    assert np.median(sb / sa) == pytest.approx(2.0, rel=0.1)


def test_se_scales_with_density():
    """MLS2: 4x the points per ball halves the SE; MLS1's SE ~ 4 sigma / r^2 sqrt((n-1)/n)
    hardly moves (the point's own noise, not a mean)."""
    r, c = 0.04, 0.01
    lo = patch("sphere", r, c, points=2500, nb=20, seed=2)
    hi = patch("sphere", r, c, points=10000, nb=80, seed=2)        # same cap, 4x denser
    m_lo = unc.mls2_uncertainty(lo["points"], r, lo["normals"])["mean_se"][lo["inner"]]
    m_hi = unc.mls2_uncertainty(hi["points"], r, hi["normals"])["mean_se"][hi["inner"]]
    assert np.median(m_hi) / np.median(m_lo) == pytest.approx(0.5, rel=0.1)
    q_lo = unc.mls1_uncertainty(lo["points"], r, lo["normals"])
    q_hi = unc.mls1_uncertainty(hi["points"], r, hi["normals"])
    ratio = np.median(q_hi["mean_se"][hi["inner"]]) / np.median(q_lo["mean_se"][lo["inner"]])
    assert ratio == pytest.approx(np.sqrt((79 / 80) / (19 / 20)), rel=0.1)


def test_roughness_is_sigma():
    sigma, r = 0.004, 0.1
    pts, nrm, inner = plane(8000, 2.0, sigma)
    m2 = unc.mls2_uncertainty(pts, r, nrm)
    m1 = unc.mls1_uncertainty(pts, r, nrm)
    pca = unc.pca_uncertainty(pts, r)
    for rough in (m2["roughness"], m1["roughness"], pca["roughness"]):
        assert np.median(rough[inner]) == pytest.approx(sigma, rel=0.1)
    np.testing.assert_allclose(m1["normal_se"], pca["normal_se"])
    s = patch("sphere", 0.02, 0.01, seed=4)                  # sigma = 2e-4, k r = 0.02
    rough = unc.mls2_uncertainty(s["points"], 0.02, s["normals"])["roughness"][s["inner"]]
    assert np.median(rough) == pytest.approx(2e-4, rel=0.1)
    rough = unc.pca_uncertainty(s["points"], 0.02)["roughness"][s["inner"]]
    assert np.median(rough) == pytest.approx(2e-4, rel=0.1)   # k^2 r^4 / 48 << sigma^2


def one_neighbourhood(draws, sigma, seed=0):
    """``draws`` copies, far apart, of one sphere neighbourhood (R = 1, r = 0.1, ~40
    points inside 0.97 r, so no noise moves one across the rim), each with its own noise
    along the normals; the centre is row 0 of each copy."""
    r = 0.1
    rng = np.random.default_rng(seed)
    s = shapes.sphere(400, 1.0, seed=seed, cap=np.arccos(1 - 5 * r * r))   # ~40 per ball
    centre = np.array([0.0, 0.0, 1.0])
    keep = np.linalg.norm(s["points"] - centre, axis=1) < 0.97 * r
    base = np.vstack([centre, s["points"][keep]])
    nrm = np.vstack([centre, s["normals"][keep]])
    m = len(base)
    shift = np.repeat(np.arange(draws) * 10.0 * r, m)[:, None] * [1.0, 0.0, 0.0]
    pts = np.tile(base, (draws, 1)) + shift
    pts += rng.normal(scale=sigma, size=(len(pts), 1)) * np.tile(nrm, (draws, 1))
    return pts, np.tile(nrm, (draws, 1)), np.arange(draws) * m, r


@pytest.mark.parametrize("case", ["mls2 ball", "mls2 gaussian", "mls2 density", "mls1"])
def test_monte_carlo_se(case):
    """The standard deviation of H at one point over 2000 noise draws equals the
    predicted SE (its RMS over the draws) within 10%."""
    pts, nrm, rows, r = one_neighbourhood(2000, 0.002)
    assert 30 < len(pts) / 2000 <= 60
    if case == "mls1":
        out = unc.mls1_uncertainty(pts, r, nrm)
    else:
        kw = {"kernel": "gaussian"} if case == "mls2 gaussian" else (
            {"weights": "density"} if case == "mls2 density" else {})
        out = unc.mls2_uncertainty(pts, r, nrm, **kw)
    h, se = out["mean"][rows], out["mean_se"][rows]
    assert np.isfinite(h).all()
    assert np.std(h) == pytest.approx(np.sqrt(np.mean(se ** 2)), rel=0.1)


def test_covariance_output():
    """``covariance=True`` returns the quadric's coefficients and their covariance, from
    which the delta method gives back ``mean_se``."""
    s = patch("wave", 0.02, 0.01, points=3000, seed=6)
    out = unc.mls2_uncertainty(s["points"], 0.02, s["normals"], covariance=True)
    ok = out["status"] == 0
    val, jac = unc.curvature_jacobian(out["coef"][ok], 0.02)
    np.testing.assert_allclose(val[:, 0], out["mean"][ok], rtol=1e-12)
    se = np.sqrt(np.einsum("ni,nij,nj->n", jac[:, 0], out["coef_cov"][ok], jac[:, 0]))
    np.testing.assert_allclose(se, out["mean_se"][ok], rtol=1e-9)
    assert np.all(out["k1_debiased"][ok] <= out["k1"][ok] + 1e-12)
    assert np.all(out["k2_debiased"][ok] >= out["k2"][ok] - 1e-12)


def test_empty_and_errors():
    out = unc.mls2_uncertainty(np.empty((0, 3)), 1.0, np.empty((0, 3)))
    assert out["mean_se"].shape == (0,) and out["status"].dtype == np.uint8
    out = unc.mls2_uncertainty(np.empty((0, 3)), 1.0, np.empty((0, 3)), covariance=True)
    assert out["coef_cov"].shape == (0, 6, 6)
    with pytest.raises(ValueError, match="shape"):
        unc.mls2_uncertainty(np.zeros((4, 2)), 1.0, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="noise"):
        unc.mls1_uncertainty(np.zeros((4, 3)), 1.0, np.zeros((4, 3)), noise="x")
    few = np.random.default_rng(0).normal(size=(5, 3))
    out = unc.mls2_uncertainty(few, 0.1, few)             # every ball holds only its point
    assert np.isnan(out["mean_se"]).all() and (out["status"] != 0).all()
