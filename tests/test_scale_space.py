"""MLS1 scale space on the device (ping-pong, re-binning as needed) against the float64
reference and against mean curvature motion (Digne & Morel, Theorem 5 and Table 1).

Tolerance kernel vs reference: |d position| <= 1e-5 r after N iterations (float32 positions
relative to the cloud centre; the displacement is accumulated separately, so the error
does not grow with the coordinates)."""
import sys
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.reference import operators as reference
from clcurv import shapes

from conftest import bumpy_surface

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the repo root: bench/
from bench.targets import SS_TOL  # noqa: E402


@pytest.mark.parametrize("weights", ["uniform", "density"])
@pytest.mark.parametrize("iterations", [1, 2, 3, 4, 5])
def test_matches_reference(device, iterations, weights):
    pts = bumpy_surface(15000, seed=8, noise=0.01)
    r = 0.08
    got = clcurv.scale_space(pts, r, iterations, weights=weights, device=device)
    ref = reference.scale_space(pts, r, iterations, weights=weights)[-1]
    err = np.linalg.norm(got - ref, axis=1).max()
    assert err <= SS_TOL * r, err


def test_rebinning_path_matches_reference(device):
    """Noise of 0.1 r makes the first iterations move points far enough to re-bin."""
    s = shapes.sphere(20000, 2.0, noise=0.03, seed=9)
    got, stats = clcurv.scale_space(s["points"], 0.3, 5, return_stats=True, device=device)
    assert stats["rebins"] >= 1
    ref = reference.scale_space(s["points"], 0.3, 5)[-1]
    assert np.linalg.norm(got - ref, axis=1).max() <= SS_TOL * 0.3


def test_iterates_and_input_order(device):
    pts = bumpy_surface(3000, seed=10)
    its = clcurv.scale_space(pts, 0.15, 3, return_iterates=True, device=device)
    assert len(its) == 4 and np.array_equal(its[0], pts)
    np.testing.assert_allclose(its[3], clcurv.scale_space(pts, 0.15, 3, device=device), atol=1e-12)


def test_one_iteration_moves_inward_by_h_r2_over_4(device):
    s = shapes.sphere(200_000, 2.0, seed=11)
    r = 0.2
    moved = clcurv.scale_space(s["points"], r, 1, device=device)
    shift = np.linalg.norm(moved, axis=1) - 2.0
    assert abs(np.mean(shift) / (-0.5 * r * r / 4) - 1) <= 0.05


def test_iterations_follow_mean_curvature_motion(device):
    """A sphere under MCM with step r^2/4 per iteration: R_N^2 = R^2 - N r^2 / 2."""
    s = shapes.sphere(200_000, 2.0, seed=12)
    r, N = 0.2, 8
    its = clcurv.scale_space(s["points"], r, N, return_iterates=True, device=device)
    for k, p in enumerate(its):
        R = np.mean(np.linalg.norm(p, axis=1))
        expected = np.sqrt(4.0 - k * r * r / 2)
        assert abs((2.0 - R) - (2.0 - expected)) <= 0.05 * (2.0 - expected) + 1e-9, (k, R, expected)


def test_noisy_sphere_mean_curvature_std_decreases(device):
    """The paper's Table 1 trend: MLS1 H std falls over the first iterations."""
    s = shapes.sphere(60_000, 2.0, noise=0.02, seed=13)
    r = 0.2
    stds = []
    for k in range(4):
        pts = clcurv.scale_space(s["points"], r, k, device=device)
        stds.append(np.nanstd(clcurv.curvature(pts, r, method="mls1", device=device).mean))
    assert all(b < 0.8 * a for a, b in zip(stds, stds[1:])), stds


@pytest.mark.parametrize("method", clcurv.METHODS)
def test_pipeline_scale_space_then_operator(device, method):
    s = shapes.sphere(40_000, 2.0, noise=0.01, seed=14)
    r = 0.25
    res = clcurv.curvature(s["points"], r, method=method, scale_space=3, device=device)
    smoothed = clcurv.scale_space(s["points"], r, 3, device=device)
    direct = clcurv.curvature(smoothed, r, method=method, device=device)
    assert res.info["scale_space"] == 3 and len(res) == len(s["points"])
    for name, arr in direct.arrays().items():
        np.testing.assert_allclose(res.arrays()[name], arr, rtol=1e-6, atol=1e-9, err_msg=name)
    if method in ("mls0", "mls1", "mls2"):
        assert abs(np.nanmedian(res.mean) - 0.5) < 0.03
    if res.points is not None and method not in ("mls0", "mls1", "mls2"):
        np.testing.assert_array_equal(res.points, smoothed)


def test_bad_steps():
    with pytest.raises(ValueError, match="steps must be >= 0"):
        clcurv.scale_space(bumpy_surface(100, 0), 0.1, -1)
    with pytest.raises(ValueError, match="scale_space must be >= 0"):
        clcurv.curvature(bumpy_surface(100, 0), 0.1, scale_space=-2)
    assert clcurv.scale_space(np.empty((0, 3)), 0.1, 3).shape == (0, 3)
