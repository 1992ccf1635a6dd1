"""2dcov1, 2dcov2, 3dcov and MLS2 kernels on PoCL: against the float64 reference and against
the analytic limits of Digne & Morel (Theorems 1-3, operator 7).

Kernel vs reference (float32 vs float64, points whose neighbour counts agree):
  eigenvalues  |d| <= 1e-3 (2dcov1: products s * x cancel in float32) or 1e-4 of lambda_1
  k1, k2       covariances: relative 1e-3; MLS2: |d| <= 1e-3 max(|k1|, |k2|)
  directions   1 - |cos| <= 1e-5 where the two eigenvalues differ by > 10%
  MLS2 projection |d| <= 1e-5 r, fitted normal 1 - cos <= 1e-6
Analytic limits (exact normals given; medians over points of relative errors with an
absolute floor z: |est - true| / max(|true|, z)); r and the samples per ball n_p are chosen
so that neither sampling noise (~0.5/sqrt(n_p) on 2dcov/3dcov at an umbilic) nor the o(r^2)
terms dominate, as explained in tests/test_reference_ops.py:
  2dcov2, 3dcov |k1|, |k2| within 5% (z = 0.4/R, i.e. 0.02/R absolute for a zero curvature)
  2dcov1 eigenvalues within 8% of Theorem 1
  MLS2 signed k1, k2, H, K within 2% (z = 0.5/R), directions within 5 degrees
"""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.reference import operators as reference
from clcurv import shapes
from clcurv.grid.cloud import DeviceCloud
from clcurv._shared.constants import SINGULAR, TOO_FEW
from clcurv.ops.driver import run_kernel
from clcurv.ops.registry import OPERATORS


def device_covariances(cloud, r, normals, method, weights="uniform"):
    return run_kernel(OPERATORS[method].kernel, cloud, r, normals=normals, weights=weights)


def device_mls2(cloud, r, normals, weights="uniform", kernel="ball"):
    return run_kernel(OPERATORS["mls2"].kernel, cloud, r, normals=normals, weights=weights,
                      h=r / 2 if kernel == "gaussian" else None)

from conftest import worst

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the repo root: bench/
from bench.targets import AGREE_MIN, COV_K1_TOL, MLS2_K_TOL, MLS2_PROJ_TOL  # noqa: E402

COV = ("2dcov1", "2dcov2", "3dcov")


def bumpy(n=20000, seed=1):
    """z = 0.2 sin(3x) cos(2y) over [-1, 1]^2 with its exact unit normals."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    f = 0.2 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
    fx = 0.6 * np.cos(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
    fy = -0.4 * np.sin(3 * xy[:, 0]) * np.sin(2 * xy[:, 1])
    nrm = np.column_stack([-fx, -fy, np.ones(n)])
    return np.column_stack([xy, f]), nrm / np.linalg.norm(nrm, axis=1)[:, None]


def rowdot(a, b):
    return np.einsum("ij,ij->i", a, b)


def check_cov(pts, nrm, r, method, weights, device):
    got = device_covariances(DeviceCloud(pts, r, device=device), r, nrm, method, weights=weights)
    ref = reference.covariance_ops(pts, r, nrm, method, weights=weights)
    ok = (got["count"] == ref["count"]) & (ref["status"] == 0)
    assert ok.mean() > AGREE_MIN
    np.testing.assert_array_equal(got["status"][ok], 0)
    e_g, e_r = got["eigenvalues"][ok].astype(float), ref["eigenvalues"][ok]
    rel = np.abs(e_g - e_r).max(axis=1) / e_r[:, 0]
    assert rel.max() <= (1e-3 if method == "2dcov1" else 1e-4), worst(rel)
    krel = np.abs(got["k1"][ok] - ref["k1"][ok]) / ref["k1"][ok]
    assert krel.max() <= COV_K1_TOL, worst(krel)
    sep = e_r[:, 0] - e_r[:, 1] > 0.1 * e_r[:, 0]
    cos = np.abs(rowdot(got["dir1"][ok].astype(float), ref["dir1"][ok]))[sep]
    assert (1 - cos).max() <= 1e-5
    assert np.abs(rowdot(got["dir1"][ok].astype(float), nrm[ok])).max() < 1e-5   # tangent


def check_mls2(pts, nrm, r, weights, kernel, device):
    got = device_mls2(DeviceCloud(pts, r, device=device), r, nrm, weights=weights, kernel=kernel)
    ref = reference.mls2(pts, r, nrm, weights=weights, kernel=kernel)
    ok = (got["count"] == ref["count"]) & (ref["status"] == 0)
    assert ok.mean() > AGREE_MIN
    np.testing.assert_array_equal(got["status"][ok], 0)
    scale = np.maximum(np.abs(ref["k1"][ok]), np.abs(ref["k2"][ok]))
    for k in ("k1", "k2"):
        err = np.abs(got[k][ok] - ref[k][ok]) / scale
        assert err.max() <= MLS2_K_TOL, f"{k}: {worst(err)}"
    proj = np.linalg.norm(pts[ok] + got["shift"][ok] - ref["points"][ok], axis=1) / r
    assert proj.max() <= MLS2_PROJ_TOL, worst(proj)
    assert (1 - rowdot(got["normals"][ok].astype(float), ref["normals"][ok])).max() <= 1e-6
    sep = np.abs(ref["k1"][ok] - ref["k2"][ok]) > 0.1 * scale
    cos = np.abs(rowdot(got["dir1"][ok].astype(float), ref["dir1"][ok]))[sep]
    assert (1 - cos).max() <= 1e-5


@pytest.mark.parametrize("weights", ["uniform", "density"])
@pytest.mark.parametrize("r", [0.06, 0.12])
@pytest.mark.parametrize("method", COV)
def test_covariance_kernel_matches_reference_on_smooth_patch(device, method, r, weights):
    pts, nrm = bumpy()
    check_cov(pts, nrm, r, method, weights, device)


@pytest.mark.parametrize("kernel", ["ball", "gaussian"])
@pytest.mark.parametrize("weights", ["uniform", "density"])
@pytest.mark.parametrize("r", [0.06, 0.12])
def test_mls2_kernel_matches_reference_on_smooth_patch(device, r, weights, kernel):
    pts, nrm = bumpy()
    check_mls2(pts, nrm, r, weights, kernel, device)


@pytest.mark.parametrize("method", COV + ("mls2",))
def test_kernels_match_reference_on_torus(device, method):
    s = shapes.torus(60000, 2.0, 0.5, seed=21)
    if method == "mls2":
        check_mls2(s["points"], s["normals"], 0.1, "uniform", "ball", device)
    else:
        check_cov(s["points"], s["normals"], 0.1, method, "uniform", device)


def test_mls2_float32_at_umbilics(device):
    """On a sphere every point is umbilic (k1 = k2): the shape operator's eigenvalues must
    come from a discriminant without cancellation (hmean^2 - det left sqrt(eps) ~ 4e-4 x H
    in float32). Tolerance: 1e-4 x H for every ball of at least 16 points (about half the
    mean, 27), 2e-5 at the 99th percentile of all. Smaller balls are a separate matter: the
    6-term quadric on ~12 points amplifies float32 round-off whatever the discriminant
    (seeds 1-8: up to 5.8e-4 below 16 points, at most 6.6e-5 from 16 on, with either order
    of rounding in the PCA sums); 1e-3 bounds them."""
    s = shapes.sphere(30000, 1.0, seed=3)
    pts, nrm, r = s["points"], s["normals"], 0.06
    got = device_mls2(DeviceCloud(pts, r, device=device), r, nrm)
    ref = reference.mls2(pts, r, nrm)
    ok = (got["count"] == ref["count"]) & (ref["status"] == 0)
    assert ok.mean() > AGREE_MIN
    full = got["count"][ok] >= 16
    assert full.mean() > 0.95
    for k in ("k1", "k2"):
        err = np.abs(got[k][ok] - ref[k][ok])          # H = 1
        assert err[full].max() <= 1e-4, f"{k}: {worst(err[full])}"
        assert err.max() <= 1e-3 and np.percentile(err, 99) <= 2e-5, f"{k}: {worst(err)}"


# ---------------------------------------------------------------- analytic limits
SAMPLES = {
    "sphere": lambda n: shapes.sphere(n, 2.0, seed=31),
    "cylinder": lambda n: shapes.cylinder(n, 1.0, 1.0, seed=32),
    "torus": lambda n: shapes.torus(n, 2.0, 0.5, seed=33),
}
FLOOR = {"sphere": 2.0, "cylinder": 1.0, "torus": 2.0}   # R of the floor z = c / R


def interior(name, s, r):
    if name == "cylinder":
        return np.abs(s["points"][:, 2]) < 0.5 - r
    return np.ones(len(s["points"]), bool)


def rel_err(est, true, z):
    return np.abs(est - true) / np.maximum(np.abs(true), z)


# (shape, radius, points) for ~1500 samples per ball on the sphere, ~300 on the cylinder
# (r small: 3dcov's |k2| = r k1^2/4 must stay under the floor) and ~150 on the torus
COV_CASES = [("sphere", 0.3, 270_000), ("cylinder", 0.05, 240_000), ("torus", 0.1, 190_000)]


@pytest.mark.parametrize("name,r,npts", COV_CASES, ids=[c[0] for c in COV_CASES])
def test_2dcov2_3dcov_magnitudes(device, name, r, npts):
    s = SAMPLES[name](npts)
    inner = interior(name, s, r)
    z = 0.4 / FLOOR[name]
    for method in ("2dcov2", "3dcov"):
        res = clcurv.curvature(s["points"], r, method=method, normals=s["normals"], device=device)
        assert res.valid[inner].all()
        for k in ("k1", "k2"):
            med = np.median(rel_err(getattr(res, k)[inner], np.abs(s[k][inner]), z))
            assert med <= 0.05, f"{name} {method} {k}: median error {med:.4f}"
        if name != "sphere":    # directions are defined where k1 != k2
            ang = np.degrees(np.arccos(np.minimum(1, np.abs(rowdot(res.dir1, s["dir1"])))))
            assert np.median(ang[inner]) <= 5


@pytest.mark.parametrize("name,r,npts", COV_CASES, ids=[c[0] for c in COV_CASES])
def test_2dcov1_eigenvalues_theorem1(device, name, r, npts):
    s = SAMPLES[name](npts)
    inner = interior(name, s, r)
    res = clcurv.curvature(s["points"], r, method="2dcov1", normals=s["normals"], device=device)
    k1, k2 = s["k1"][inner], s["k2"][inner]
    c = r ** 6 / 256
    th = np.column_stack([c * (5 * k1 ** 2 + 2 * k1 * k2 + k2 ** 2),
                          c * (k1 ** 2 + 2 * k1 * k2 + 5 * k2 ** 2)])
    ratio = np.mean(res.eigenvalues[inner], axis=0) / np.mean(th, axis=0)
    assert np.all(np.abs(ratio - 1) <= 0.08), f"{name}: eigenvalues / Theorem 1 = {ratio}"


# MLS2: k r <= 0.15 everywhere (bias ~ (k r)^2 / 4 <= 0.6%), ~120 samples per ball
MLS2_CASES = [("sphere", 0.3, 25_000), ("cylinder", 0.15, 12_000), ("torus", 0.075, 280_000)]


@pytest.mark.parametrize("name,r,npts", MLS2_CASES, ids=[c[0] for c in MLS2_CASES])
def test_mls2_signed_curvatures(device, name, r, npts):
    s = SAMPLES[name](npts)
    inner = interior(name, s, r)
    res = clcurv.curvature(s["points"], r, method="mls2", device=device)   # PCA normals, MST
    assert res.valid[inner].all()
    z = 0.5 / FLOOR[name]
    zk = 0.5 / 0.5 if name == "torus" else z
    for key, true, floor in (("k1", "k1", zk), ("k2", "k2", z), ("mean", "H", z),
                             ("gaussian", "K", zk * z)):
        med = np.median(rel_err(getattr(res, key)[inner], s[true][inner], floor))
        assert med <= 0.02, f"{name} {key}: median error {med:.4f}"
    if name != "sphere":
        ang = np.degrees(np.arccos(np.minimum(1, np.abs(rowdot(res.dir1, s["dir1"])))))
        assert np.median(ang[inner]) <= 5
    assert np.mean(rowdot(res.normals, s["normals"]) > 0) >= 0.999      # outward


def test_mls2_saddle_signs(device):
    s = shapes.saddle(60_000, c=1.0, extent=1.0, seed=34)
    r = 0.15
    near = np.linalg.norm(s["points"][:, :2], axis=1) < 0.3
    res = clcurv.curvature(s["points"], r, method="mls2", normals=s["normals"], device=device)
    for key, true in (("k1", "k1"), ("k2", "k2"), ("mean", "H"), ("gaussian", "K")):
        med = np.median(rel_err(getattr(res, key)[near], s[true][near], 0.5))
        assert med <= 0.02, f"saddle {key}: {med:.4f}"
    assert np.all(res.k1[near] > 0) and np.all(res.k2[near] < 0) and np.all(res.gaussian[near] < 0)


@pytest.mark.parametrize("name", ["sphere", "torus"])
def test_mls2_projection_is_fourth_order(device, name):
    """Halving r divides the mean |displacement| by 2^4 = 16; the next-order term is
    ~(kr)^2 relative and the sampling leaves a few %: accepted range [13, 19]. The torus's
    displacements (~3e-6 at r = 0.08) are near float32 resolution of its coordinates
    (2.5 * 6e-8), so it runs in double where the device has it."""
    prec = "float"
    if name == "sphere":
        s, radii = shapes.sphere(200_000, 2.0, seed=35), (0.4, 0.2)
    else:   # below r ~ 0.08 the random sampling's cubic residuals dominate a00
        s, radii = shapes.torus(400_000, 2.0, 0.5, seed=36), (0.16, 0.08)
        prec = "double" if device.info.fp64 else "float"
    disp = []
    for r in radii:
        res = clcurv.curvature(s["points"], r, method="mls2", normals=s["normals"], device=device,
                               precision=prec)
        disp.append(np.mean(np.linalg.norm(res.points - s["points"], axis=1)))
    assert 13 <= disp[0] / disp[1] <= 19, f"{name}: ratio {disp[0] / disp[1]:.2f}"


def test_mls2_too_few_or_collinear_is_nan(device):
    rng = np.random.default_rng(7)
    sparse = rng.uniform(-1, 1, (5, 3))            # every ball has < 6 points
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = clcurv.curvature(sparse, 10.0, method="mls2", device=device, orient=None)
    assert (res.status == TOO_FEW).all() and np.isnan(res.k1).all() and np.isnan(res.points).all()
    t = np.linspace(0, 1, 40)
    line = np.column_stack([t, 2 * t, 3 * t])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = clcurv.curvature(line, 0.3, method="mls2", device=device, orient=None)
    assert (res.status != 0).all() and np.isnan(res.k1).all() and np.isnan(res.dir1).all()
    # neighbours on two crossing lines: PCA is fine (rank 2) but the quadric is not determined
    cross = np.concatenate([np.column_stack([t - 0.5, 0 * t, 0 * t]),
                            np.column_stack([0 * t, t - 0.5, 0 * t])])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = clcurv.curvature(cross, 2.0, method="mls2", device=device, orient=None)
    assert (res.status == SINGULAR).all() and np.isnan(res.mean).all()


def test_iterated_mls2_projection_matches_reference(device):
    s = shapes.sphere(8000, 2.0, seed=37)
    got = clcurv.project(s["points"], 0.5, projections=2, normals=s["normals"], device=device)
    ref = reference.mls2_iterate(s["points"], 0.5, s["normals"], 2)["points"]
    np.testing.assert_allclose(got, ref, atol=2e-6)
    # fourth order: after 2 iterations the sphere keeps its radius to ~ 2 r^4 / (48 R^3)
    assert np.abs(np.linalg.norm(got, axis=1) - 2.0).max() < 1e-3


@pytest.mark.parametrize("method", ["2dcov2", "3dcov"])
def test_nan_normal_in_the_ball_gives_degenerate(device, method):
    pts, nrm = bumpy(5000, seed=3)
    nrm = nrm.copy()
    nrm[0] = np.nan
    got = device_covariances(DeviceCloud(pts, 0.1, device=device), 0.1, nrm, method)
    near = np.linalg.norm(pts - pts[0], axis=1) < 0.1 * (1 - 1e-6)
    far = np.linalg.norm(pts - pts[0], axis=1) > 0.1 * (1 + 1e-6)
    assert (got["status"][near] == 2).all() and np.isnan(got["k1"][near]).all()
    assert (got["status"][far] == 0).mean() > 0.99 and np.isfinite(got["k1"][far]).mean() > 0.99


@pytest.mark.parametrize("method", COV + ("mls2",))
def test_tiny_units_give_the_same_curvatures(device, method):
    """The same torus in metres and in 'kilometres' (x 1e-3): 2dcov1's covariances are
    ~ r^6 k^2 (1e-25 here), which must not underflow in float32 closed forms."""
    s = shapes.torus(60000, 2.0, 0.5, seed=41)
    a = clcurv.curvature(s["points"], 0.1, method=method, normals=s["normals"], device=device)
    b = clcurv.curvature(s["points"] * 1e-3, 0.1e-3, method=method, normals=s["normals"],
                         device=device)
    ok = a.valid & b.valid & (a.count == b.count)     # scaling moves boundary ties
    assert ok.mean() > 0.99
    np.testing.assert_allclose(b.k1[ok] * 1e-3, a.k1[ok], rtol=1e-3, atol=1e-3 * np.abs(a.k1).max())
    np.testing.assert_allclose(b.k2[ok] * 1e-3, a.k2[ok], rtol=1e-3, atol=1e-3 * np.abs(a.k1).max())
