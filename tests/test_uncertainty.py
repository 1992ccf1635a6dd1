"""The kernels' error bars (``uncertainty=True``, issue 51) against the float64 reference
(clcurv.reference.uncertainty) on every device, and their calibration through the kernels.

* Agreement: the standard errors and roughness of the kernels (default float precision)
  equal the reference's to a relative 2e-4 (measured on PoCL: median 3e-7, largest 5e-6),
  on a noisy ellipsoid cap (no umbilic) and a noisy sphere. The rule that leaves out the
  ill-posed points: SE(k1) and SE(k2) go through the gradient of D = sqrt(H^2 - K) = (k1 -
  k2) / 2, whose float32 value is only ~eps H^2 / D^2 relative near an umbilic, so they are
  compared where |k1 - k2| >= 0.05 (|k1| + |k2|) (the sphere: none, checked only for
  finiteness), to a relative 1e-3: SE(k1,2)^2 = Var H + Var D +- 2 cov(H, D) also
  cancels (measured up to 2.3e-4 with the Gaussian kernel). float64 devices: 1e-9.
* The error record changes nothing else: every output of a call is bit-identical with and
  without ``uncertainty=True``.
* Calibration through the kernels (float32, the default): the issue's targets, std of the
  z-score (estimate - truth) / SE in [0.85, 1.2] and 92-97.5% of |z| < 1.96, for MLS2's H
  and k1 and MLS1's H, on patches of bench.uncertainty at radii where the bias is under a
  tenth of the SE. MLS2's k1 at a sphere's umbilics is the documented exception (90%:
  the larger of two noisy eigenvalues; docs/uncertainty.md).
"""
import numpy as np
import pytest

import clcurv
from bench.uncertainty import patch
from clcurv.data import shapes
from clcurv.reference import uncertainty as unc

REL_FLOAT, REL_DOUBLE, REL_K_FLOAT = 2e-4, 1e-9, 1e-3
STD_RANGE = (0.85, 1.2)
COVER_RANGE = (0.92, 0.975)
KMAX = {"sphere": 1.0, "ellipsoid": 2.3, "wave": 0.1 * (2 * np.pi) ** 2}


def _cap(seed=3):
    """A noisy ellipsoid cap (no umbilic) and its outward normals, ~40 neighbours at 0.1."""
    s = shapes.ellipsoid(12000, (1.0, 0.8, 0.6), noise=0.002, seed=seed, cap=1.0,
                         axis=(0.0, 1.0, 0.3))
    return s["points"], s["normals"], 0.1


def _close(a, b, rel, what):
    both = np.isfinite(a) & np.isfinite(b)
    assert np.array_equal(np.isfinite(a), np.isfinite(b)), f"{what}: NaN where the other is not"
    err = np.abs(a[both] - b[both]) / np.abs(b[both])
    assert err.max() <= rel, f"{what}: relative error {err.max():.2e} > {rel:g}"


def _fp64(device):
    return bool(device.info.fp64)


CASES = [("mls2", "uniform", None), ("mls2", "density", None), ("mls2", "uniform", "gaussian"),
         ("mls1", "uniform", None), ("mls1", "density", None), ("mls0", "uniform", None),
         ("variation", "uniform", None), ("variation", "density", None)]


@pytest.mark.parametrize("method,weights,kernel", CASES,
                         ids=[f"{m}-{w}-{k or 'ball'}" for m, w, k in CASES])
@pytest.mark.parametrize("precision", ["float", "double"])
def test_kernels_match_the_reference(device, method, weights, kernel, precision):
    if precision == "double" and not _fp64(device):
        pytest.skip("the device has no cl_khr_fp64")
    pts, nrm, r = _cap()
    extra = {"kernel": kernel} if kernel else {}
    res = clcurv.curvature(pts, r, method=method, weights=weights, normals=nrm, device=device,
                           precision=precision, uncertainty=True, **extra)
    ok = res.status == 0
    assert ok.mean() > 0.95
    rel = REL_FLOAT if precision == "float" else REL_DOUBLE
    if method == "mls2":
        ref = unc.mls2_uncertainty(pts, r, nrm, weights=weights, kernel=kernel or "ball")
        names = ("mean_se", "gaussian_se", "k1_se", "k2_se", "normal_se", "roughness")
        posed = np.abs(res.k1 - res.k2) >= 0.05 * (np.abs(res.k1) + np.abs(res.k2))
    elif method in ("mls0", "mls1"):
        ref = unc.mls1_uncertainty(pts, r, nrm, weights=weights, method=method)
        names = ("mean_se", "normal_se", "roughness")
        posed = ok
    else:
        ref = unc.pca_uncertainty(pts, r, weights=weights)
        names = ("normal_se", "roughness")
        posed = ok
    both = ok & (ref["status"] == 0)
    assert both.sum() > 0.95 * ok.sum()
    for name in names:
        principal = name in ("k1_se", "k2_se")
        keep = both & posed if principal else both
        tol = REL_K_FLOAT if principal and precision == "float" else rel
        _close(getattr(res, name)[keep], ref[name][keep], tol, f"{method} {name}")
        assert np.all(np.isnan(getattr(res, name)[~ok])), f"{name} not NaN where status != 0"


def test_sphere_k_se_finite_at_umbilics(device):
    """Every point of a sphere is an umbilic: SE(k1), SE(k2) finite, close to the
    reference's in the median (the gradient of D is ill-posed point by point there)."""
    s = shapes.sphere(20000, 1.0, noise=0.003, seed=1)
    res = clcurv.curvature(s["points"], 0.12, method="mls2", normals=s["normals"],
                           device=device, uncertainty=True)
    ref = unc.mls2_uncertainty(s["points"], 0.12, s["normals"])
    for name in ("k1_se", "k2_se"):
        v = getattr(res, name)
        assert np.isfinite(v).all()
        assert abs(np.median(v) / np.median(ref[name]) - 1) < 1e-3


@pytest.mark.parametrize("method", ["mls2", "mls1", "mls0", "variation"])
def test_outputs_unchanged_by_uncertainty(device, method):
    pts, nrm, r = _cap(seed=5)
    a = clcurv.curvature(pts, r, method=method, device=device)
    b = clcurv.curvature(pts, r, method=method, device=device, uncertainty=True)
    for name, v in a.arrays().items():
        assert np.array_equal(v, getattr(b, name), equal_nan=True), name
    for o in clcurv.ops.registry.OPERATORS[method].errors:
        assert getattr(a, o.name) is None and getattr(b, o.name).shape == (len(pts),)


def test_mst_orientation_swaps_the_principal_errors(device):
    """MLS2 oriented afterwards (orient='mst', the fit's own normals flipped): SE(k1) goes
    with k1, i.e. equals the call with the true outward normals."""
    pts, nrm, r = _cap(seed=7)
    own = clcurv.curvature(pts, r, method="mls2", orient="mst", device=device, uncertainty=True)
    given = clcurv.curvature(pts, r, method="mls2", normals=nrm, device=device,
                             uncertainty=True)
    ok = (own.status == 0) & (given.status == 0)
    assert np.nanmedian(np.einsum("ij,ij->i", own.normals, nrm)) > 0.99
    for name in ("k1_se", "k2_se", "mean_se"):
        a, b = getattr(own, name)[ok], getattr(given, name)[ok]
        assert np.median(np.abs(a - b) / b) < 1e-3, name


def test_bad_uncertainty_requests(device):
    pts, nrm, r = _cap()
    with pytest.raises(ValueError, match="k-NN radius"):
        clcurv.curvature(pts, method="mls2", k=30, uncertainty=True, device=device)
    with pytest.raises(TypeError, match="uncertainty must be True or False"):
        clcurv.curvature(pts, r, method="mls2", uncertainty="yes", device=device)


@pytest.mark.parametrize("method", ["2dcov1", "2dcov2", "3dcov"])
@pytest.mark.parametrize("weights", ["uniform", "density"])
def test_covariance_operators_have_their_normals_errors(device, method, weights):
    """The covariance operators' normal_se and roughness are those of their PCA normals'
    pass (one-pass float32 sums, REFINE_L0=0: measured 2.2e-5 relative; tolerance 2e-4),
    their other outputs unchanged bit for bit; with your normals both are NaN."""
    pts, nrm, r = _cap()
    a = clcurv.curvature(pts, r, method=method, weights=weights, device=device)
    b = clcurv.curvature(pts, r, method=method, weights=weights, device=device,
                         uncertainty=True)
    for name, v in a.arrays().items():
        assert np.array_equal(v, getattr(b, name), equal_nan=True), name
    ref = unc.pca_uncertainty(pts, r, weights=weights)
    ok = (b.status == 0) & (ref["status"] == 0)
    assert ok.mean() > 0.95
    for name in ("normal_se", "roughness"):
        _close(getattr(b, name)[ok], ref[name][ok], REL_FLOAT, f"{method} {name}")
    c = clcurv.curvature(pts, r, method=method, normals=nrm, device=device, uncertainty=True)
    assert np.isnan(c.normal_se).all() and np.isnan(c.roughness).all()
    d = clcurv.curvature(pts, r, method=method, weights=weights, backend="numpy",
                         uncertainty=True)
    _close(d.normal_se[ok], ref["normal_se"][ok], 1e-12, f"{method} numpy normal_se")


def test_empty_cloud_has_error_columns():
    res = clcurv.curvature(np.empty((0, 3)), 0.1, method="mls2", uncertainty=True)
    assert res.mean_se.shape == (0,) and res.roughness.shape == (0,)


def _z(shape, kr, c, estimator, device, seed=0):
    r = kr / KMAX[shape]
    s = patch(shape, r, c, seed=seed)
    method, what = estimator.split()
    res = clcurv.curvature(s["points"], r, method=method, normals=s["normals"], device=device,
                           uncertainty=True)
    if what == "k1":
        z = (res.k1 - s["k1"]) / res.k1_se
    else:
        z = (res.mean - s["H"]) / res.mean_se
    z = z[s["inner"]]
    assert np.isfinite(z).all()
    return float(z.std()), float(np.mean(np.abs(z) < 1.96))


#: radii (k_max r) and noise (sigma / r) where the bias is under a tenth of the SE
#: (bench/results/uncertainty.md)
CALIBRATED = [("sphere", 0.08, 0.005, "mls2 H"), ("ellipsoid", 0.16, 0.01, "mls2 H"),
              ("wave", 0.08, 0.01, "mls2 H"), ("ellipsoid", 0.16, 0.005, "mls2 k1"),
              ("wave", 0.16, 0.02, "mls2 k1"), ("sphere", 0.02, 0.01, "mls1 H"),
              ("ellipsoid", 0.04, 0.01, "mls1 H"), ("wave", 0.08, 0.02, "mls1 H")]


@pytest.mark.parametrize("shape,kr,c,estimator", CALIBRATED,
                         ids=[f"{s}-{e.replace(' ', '_')}-kr{k}-c{c}" for s, k, c, e in CALIBRATED])
def test_kernels_calibrated(device, shape, kr, c, estimator):
    std, cover = _z(shape, kr, c, estimator, device)
    assert STD_RANGE[0] <= std <= STD_RANGE[1], f"std z {std:.3f}"
    assert COVER_RANGE[0] <= cover <= COVER_RANGE[1], f"{cover:.1%} within 1.96"


def test_kernels_k1_at_umbilics_below_coverage(device):
    """The documented exception: MLS2's k1 on a sphere (every point an umbilic) is the
    larger of two noisy eigenvalues; its std stays in range, its coverage is ~90%."""
    std, cover = _z("sphere", 0.08, 0.01, "mls2 k1", device)
    assert STD_RANGE[0] <= std <= STD_RANGE[1]
    assert 0.85 <= cover < 0.92, f"{cover:.1%}"
