"""Moment kernels (counts, PCA normals, eigenvalues, variation, barycenter shift) against the
float64 NumPy reference, on PoCL.

Tolerances (float32 kernels vs float64 oracle), compared on the points whose neighbour
sets agree (a neighbour within ~1e-7 r of the sphere |q - p| = r may fall on either side in
float32; those points are counted, and must be rare):
  normals        1 - |cos| <= 1e-4
  eigenvalues    |d lambda_i| <= 4 (n + 32) eps32 * lambda_2   (float32 sums of n = #N_r(p)
                 terms, plus the eigen solver's 32 eps)
  lambda_0, variation   relative <= 1e-3 for 99.9% of points (second-pass lambda_0)
  shift o - p    |d| <= 4 (n + 32) eps32 * r
"""
import sys
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.reference import operators as reference
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import run_kernel
from clcurv.ops.registry import PCA

from conftest import bumpy_surface, worst

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the repo root: bench/
from bench.targets import AGREE_MIN, COS_TOL, L0_REL_TOL  # noqa: E402

F32_EPS = float(np.finfo(np.float32).eps)


def check_moments(points, radius, weights, device, precision="float"):
    cloud = DeviceCloud(points, radius, device=device, precision=precision)
    got = run_kernel(PCA, cloud, radius, weights=weights)
    ref = reference.moments(points, radius, weights=weights)
    same = got["count"] == ref["count"]
    assert same.mean() >= AGREE_MIN, f"counts differ on {np.count_nonzero(~same)} points"
    np.testing.assert_array_equal(got["status"][same], ref["status"][same])
    ok = same & (ref["status"] == 0)
    assert ok.sum() > 0.5 * len(points)
    bad = got["status"] != 0
    assert np.isnan(got["normals"][bad]).all() and np.isnan(got["variation"][bad]).all()
    n_g, n_r = got["normals"][ok].astype(float), ref["normals"][ok]
    one_minus_cos = 1 - np.abs(np.einsum("ij,ij->i", n_g, n_r))
    assert one_minus_cos.max() <= COS_TOL, worst(one_minus_cos)
    e_g, e_r = got["eigenvalues"][ok].astype(float), ref["eigenvalues"][ok]
    # float32 sums of n terms plus the eigen solver: error bound 4 (n + 32) eps
    bound = 4 * (got["count"][ok] + 32) * F32_EPS
    err = (np.abs(e_g - e_r) / e_r[:, 2:3]).max(axis=1) / bound
    assert err.max() <= 1, worst(err)
    flat = e_r[:, 0] > 1e-6 * e_r[:, 2]     # lambda0 relative error is meaningful
    rel0 = np.abs(e_g[flat, 0] - e_r[flat, 0]) / e_r[flat, 0]
    assert np.quantile(rel0, 0.999) <= L0_REL_TOL, worst(rel0)
    relv = np.abs(got["variation"][ok][flat] - ref["variation"][ok][flat]) / ref["variation"][ok][flat]
    assert np.quantile(relv, 0.999) <= L0_REL_TOL, worst(relv)
    derr = np.linalg.norm(got["shift"][ok] - ref["shift"][ok], axis=1) / (radius * bound)
    assert derr.max() <= 1, worst(derr)
    return got, ref


@pytest.mark.parametrize("weights", ["uniform", "density"])
@pytest.mark.parametrize("radius", [0.04, 0.08, 0.15])
def test_kernel_matches_reference_on_smooth_patch(device, radius, weights):
    check_moments(bumpy_surface(20000, seed=1), radius, weights, device)


@pytest.mark.parametrize("weights", ["uniform", "density"])
def test_kernel_matches_reference_on_random_blob(device, weights):
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(10000, 3))
    got, ref = check_moments(pts, 0.3, weights, device)
    assert (ref["status"] == 1).sum() > 50   # sparse tails exercise the too-few branch


def test_double_precision_matches_reference_tightly(device):
    if not device.info.fp64:
        pytest.skip(f"{device.info.name} has no cl_khr_fp64")
    pts = bumpy_surface(5000, seed=3)
    cloud = DeviceCloud(pts, 0.1, device=device, precision="double")
    got = run_kernel(PCA, cloud, 0.1)
    ref = reference.moments(pts, 0.1)
    ok = (got["count"] == ref["count"]) & (ref["status"] == 0)
    assert ok.mean() > 0.999
    np.testing.assert_allclose(got["eigenvalues"][ok], ref["eigenvalues"][ok], rtol=1e-9, atol=1e-14)
    cos = np.abs(np.einsum("ij,ij->i", got["normals"][ok], ref["normals"][ok]))
    assert (1 - cos).max() < 1e-12


def test_numpy_backend_equals_opencl_through_api(device):
    pts = bumpy_surface(8000, seed=4)
    a = clcurv.curvature(pts, 0.1, method="mls1", device=device)
    b = clcurv.curvature(pts, 0.1, method="mls1", backend="numpy")
    ok = (a.count == b.count) & a.valid
    assert ok.mean() > 0.998
    # same orientation procedure on nearly identical normals: same signs
    assert np.all(np.einsum("ij,ij->i", a.normals[ok], b.normals[ok]) > 0.9999)
    np.testing.assert_allclose(a.mean[ok], b.mean[ok], rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(a.points[ok], b.points[ok], atol=1e-6)


def test_deterministic_bit_identical(device):
    pts = bumpy_surface(20000, seed=5)
    runs = [clcurv.curvature(pts, 0.08, method="mls1", weights="density", device=device)
            for _ in range(2)]
    for name, arr in runs[0].arrays().items():
        np.testing.assert_array_equal(arr, runs[1].arrays()[name], err_msg=name)


def test_fields_subset_is_the_same_numbers(device):
    """``fields=`` only limits what comes back: the same normals, counts and statuses."""
    pts = bumpy_surface(5000, seed=4)
    cloud = DeviceCloud(pts, 0.1, device=device)
    full = run_kernel(PCA, cloud, 0.1, defines={"REFINE_L0": 0})
    part = run_kernel(PCA, cloud, 0.1, defines={"REFINE_L0": 0}, fields=("normals",))
    assert set(part) == {"normals", "count", "status"}
    for k in part:
        np.testing.assert_array_equal(part[k], full[k])
