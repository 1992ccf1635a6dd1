"""Every registered operator (clcurv.ops.registry.OPERATORS) through the public API, kernels
against the float64 reference, and the registry's promises (outputs, options, empty
clouds, the README's methods table, DeviceCloud reuse).

Cloud: a noisy torus (R = 2, a = 0.5, noise 0.002) at r = 0.2 (~60 neighbours), normals
given where the operator uses their values. Compared on the points whose neighbour counts
agree and whose status is 0 in both. Tolerances (float32 kernels vs float64 reference):
  unit vectors (normals, directions where k1 - k2 > 10% of k1):  1 - |cos| <= 1e-4
  curvatures, mean, gaussian: |d| <= 2e-3 x max |value| (p99.9) and 2e-2 x max (all)
  points: |d| <= 1e-5 r; eigenvalues: <= 1e-3 x the largest; variation: <= 1e-3 relative
"""
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv import shapes
from clcurv.ops.registry import METHODS, OPERATORS

README = Path(__file__).resolve().parent.parent / "README.md"
R = 0.2


@pytest.fixture(scope="module")
def torus():
    s = shapes.torus(20000, 2.0, 0.5, seed=17)
    rng = np.random.default_rng(3)
    return s["points"] + rng.normal(0, 0.002, s["points"].shape), s["normals"]


def _compare(name, a, b, width, r):
    if name in ("normals", "dir1", "dir2"):
        return 1 - np.abs(np.einsum("ij,ij->i", a, b)), 1e-4, 1e-4
    if name == "points":
        return np.linalg.norm(a - b, axis=1) / r, 1e-5, 1e-5
    if name == "eigenvalues":
        return np.abs(a - b).max(axis=1) / np.abs(b).max(axis=1), 1e-3, 1e-3
    if name == "variation":
        return np.abs(a - b) / np.abs(b), 1e-3, 2e-2
    scale = np.nanmax(np.abs(b))
    return np.abs(a - b) / scale, 2e-3, 2e-2


@pytest.mark.parametrize("method", METHODS)
def test_every_registered_operator_matches_its_reference(device, torus, method):
    op = OPERATORS[method]
    pts, nrm = torus
    kw = dict(method=method, normals=nrm if op.normals != "none" else None)
    got = clcurv.curvature(pts, R, device=device, **kw)
    ref = clcurv.curvature(pts, R, backend="numpy", **kw)
    ok = (got.count == ref.count) & got.valid & ref.valid
    assert ok.mean() > 0.99, f"{method}: {ok.mean():.4f} comparable points"
    for out in op.outputs:
        a, b = getattr(got, out.name), getattr(ref, out.name)
        assert a is not None and b is not None, out.name
        assert a.shape == b.shape == ((len(pts),) if out.width == 1 else (len(pts), out.width))
        assert np.isnan(a[~got.valid]).all(), f"{out.name}: status != 0 must be NaN"
        sel = ok
        if out.name in ("dir1", "dir2"):            # directions are defined where k1 != k2
            sel = ok & (np.abs(ref.k1 - ref.k2) > 0.1 * np.abs(ref.k1))
        err, p999, worst = _compare(out.name, a[sel], b[sel], out.width, R)
        assert np.quantile(err, 0.999) <= p999, (method, out.name, np.quantile(err, 0.999))
        assert err.max() <= worst, (method, out.name, err.max())


@pytest.mark.parametrize("method", METHODS)
def test_empty_cloud_has_every_output(method):
    res = clcurv.curvature(np.empty((0, 3)), 0.1, method=method)
    for out in OPERATORS[method].outputs:
        v = getattr(res, out.name)
        assert v.shape == ((0,) if out.width == 1 else (0, out.width)), out.name
    assert res.count.dtype == np.int64 and res.status.dtype == np.uint8


@pytest.mark.parametrize("method", [m for m in METHODS if m != "mls2"])
@pytest.mark.parametrize("option", [{"kernel": "gaussian"}, {"kernel": "ball"}, {"h": 0.05},
                                    {"projections": 1}])
def test_mls2_options_raise_for_other_methods(method, option):
    with pytest.raises(ValueError, match="not an option of method"):
        clcurv.curvature(np.random.default_rng(0).random((50, 3)), 0.3, method=method,
                         **option)


def test_h_needs_the_gaussian_kernel():
    with pytest.raises(ValueError, match="h is the width of kernel='gaussian'"):
        clcurv.curvature(np.random.default_rng(0).random((50, 3)), 0.3, method="mls2", h=0.1)


def test_device_cloud_is_binned_once_for_several_operators(device, torus):
    pts, nrm = torus
    cloud = clcurv.DeviceCloud(pts, R, device=device)
    for method in ("variation", "3dcov", "mls2"):
        a = clcurv.curvature(cloud, R, method=method, normals=nrm)
        b = clcurv.curvature(pts, R, method=method, normals=nrm, device=device)
        for k, v in a.arrays().items():
            np.testing.assert_array_equal(v, b.arrays()[k], err_msg=f"{method} {k}")
    np.testing.assert_array_equal(clcurv.normals(cloud, R), clcurv.normals(pts, R, device=device))
    with pytest.raises(ValueError, match="exceeds the cell size"):
        clcurv.curvature(cloud, 2 * R, method="variation")


def methods_table():
    """The README's methods table (markdown), generated from the registry."""
    rows = ["| method | operator (Digne & Morel) | outputs | signed | min. neighbours |",
            "|---|---|---|---|---|"]
    for op in OPERATORS.values():
        outs = ", ".join(f"`{o.name}`" for o in op.outputs)
        rows.append(f"| `\"{op.name}\"` | {op.title}; {op.formula} | {outs} | "
                    f"{'yes' if op.signed else 'no'} | {op.min_count} |")
    return "\n".join(rows)


def test_readme_methods_table_is_the_registry():
    assert methods_table() in README.read_text(), \
        "README's methods table differs from tests/test_registry.py's methods_table(): paste it"
