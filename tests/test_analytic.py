"""Analytic limits on dense noise-free samples (uniform in area).

Asserted per shape (interior points only for the open cylinder):
- surface variation: mean over points within 5% of Theorem 4's r^2/16((k1^2+k2^2)/2 - k1k2/3)
  evaluated per point;
- MLS1 mean curvature (PCA normals, oriented by MST) and MLS0 mean curvature (barycenter
  shift along the supplied exact normals): mean H within 3% of the mean true H, and the
  per-point median relative error within 6% (random sampling of ~150-400 neighbours
  leaves a per-point scatter; the bias is what the theorems bound);
- orientation: >= 99.9% of the normals outward (dot with the exact normal > 0).
"""
import numpy as np
import pytest

import clcurv
from clcurv import shapes

CASES = {
    # name: (sampler, radius, interior mask)
    "sphere": (lambda: shapes.sphere(160_000, 2.0, seed=11), 0.2, None),
    "cylinder": (lambda: shapes.cylinder(100_000, 1.0, 4.0, seed=12), 0.15, 1.8),
    "torus": (lambda: shapes.torus(300_000, 2.0, 0.5, seed=13), 0.08, None),
}


@pytest.fixture(scope="module", params=list(CASES))
def shape(request):
    sampler, r, zmax = CASES[request.param]
    s = sampler()
    inner = np.ones(len(s["points"]), bool) if zmax is None else np.abs(s["points"][:, 2]) < zmax
    return request.param, s, r, inner


def test_variation_theorem4(shape, device):
    name, s, r, inner = shape
    res = clcurv.curvature(s["points"], r, method="variation", orient=None, device=device)
    k1, k2 = s["k1"], s["k2"]
    theory = r * r / 16 * ((k1 ** 2 + k2 ** 2) / 2 - k1 * k2 / 3)
    ratio = np.mean(res.variation[inner]) / np.mean(theory[inner])
    assert abs(ratio - 1) <= 0.05, f"{name}: variation / theory = {ratio:.4f}"


@pytest.mark.parametrize("method", ["mls0", "mls1"])
def test_mean_curvature_and_orientation(shape, device, method):
    name, s, r, inner = shape
    kw = {"normals": s["normals"]} if method == "mls0" else {}
    res = clcurv.curvature(s["points"], r, method=method, device=device, **kw)
    assert res.valid.all()
    H, h = s["H"][inner], res.mean[inner]
    bias = np.mean(h) / np.mean(H) - 1
    assert abs(bias) <= 0.03, f"{name} {method}: mean H bias {bias:+.4f}"
    med = np.median(np.abs(h - H) / np.abs(H))
    assert med <= 0.06, f"{name} {method}: median per-point relative error {med:.4f}"
    outward = np.mean(np.einsum("ij,ij->i", res.normals, s["normals"]) > 0)
    assert outward >= 0.999, f"{name}: only {outward:.4%} normals outward"


def test_mls1_projection_moves_inward_by_h_r2_over_4(device):
    s = shapes.sphere(160_000, 2.0, seed=14)
    r = 0.2
    res = clcurv.curvature(s["points"], r, method="mls1", device=device)
    radial = np.linalg.norm(res.points, axis=1) - 2.0      # Theorem 5: -H r^2/4 = -0.005
    assert abs(np.mean(radial) / (-0.5 * r * r / 4) - 1) <= 0.03


@pytest.mark.parametrize("seed", range(3))
def test_open_noisy_cylinder_comes_out_outward(device, seed):
    """The outward vote of the whole component, not of a rim point (where PCA normals of a
    half-empty ball tilt), decides: an open noisy cylinder is oriented outward."""
    s = shapes.cylinder(40_000, 1.0, 6.0, noise=0.05, seed=seed)
    n = clcurv.normals(s["points"], 0.2, device=device)
    assert np.mean(np.einsum("ij,ij->i", n, s["normals"]) > 0) >= 0.999
