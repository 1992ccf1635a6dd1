"""Orientation on the device (issue 11): the device forest's flips against the host Hoppe
reference (orient.flip_by_propagation, the same graph: k nearest within the radius),
outward on closed shapes (nested ones included), invariance, and bad input. Real kernels on
every OpenCL device present."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import clcurv
from clcurv.orient import orientation as orient
from clcurv import shapes
from clcurv.data import sample_path
from conftest import DEVICES

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
K = 10


def _radius(points, k=30):
    """The median distance to the k-th neighbour (~k neighbours per ball)."""
    return float(np.median(cKDTree(points).query(points[:3000], k=k + 1)[0][:, -1]))


def _case(name):
    """(points, exact outward normals or None) of a named test shape."""
    if name == "sphere":
        s = shapes.sphere(100_000, 1.0)
    elif name == "torus":
        s = shapes.torus(100_000)
    elif name == "two spheres":
        s = shapes.two_spheres(60_000)
    elif name == "hollow shell":
        s = shapes.hollow_shell(60_000)
    elif name.startswith("thin box"):
        s = shapes.thin_box(0.01, 0.01 * float(name.split()[-1]))
    elif name == "bunny":
        return clcurv.io.read(sample_path()).points, None
    elif name == "igea":
        path = DATA / "igea_cyberware.ply"
        if not path.exists():
            pytest.skip("../shared/data/igea_cyberware.ply not present")
        return clcurv.io.read(path).points, None
    return s["points"], s["normals"]


CASES = ["sphere", "torus", "bunny", "igea", "two spheres", "hollow shell", "thin box 4",
         "thin box 2"]
#: outward fraction required of the closed shapes (thin box 2: see test_thin_box_limit)
OUTWARD = {"sphere": 0.999, "torus": 0.999, "two spheres": 0.999, "hollow shell": 0.999,
           "thin box 4": 0.999}


@pytest.mark.parametrize("name", CASES)
def test_device_flips_equal_the_host_reference(name, device):
    """Within each component, up to its sign (and here with the same sign rule), the device
    forest's flips equal the host MST's on >= 99.99% of the valid points."""
    pts, exact = _case(name)
    r = _radius(pts)
    cloud = clcurv.DeviceCloud(pts, r, device=device)
    n = clcurv.normals(cloud, r, orient=None)
    dev = orient.flip_on_device(cloud, n, r, K)
    host = orient.flip_by_propagation(pts, n, k=K, radius=r)
    ok = np.isfinite(n).all(axis=1)
    assert ok.mean() > 0.98
    agree = np.mean(dev[ok] == host[ok])
    assert agree >= 0.9999, (name, agree)
    if name in OUTWARD:
        o = np.where(dev[:, None], -n, n)
        out = np.mean(np.einsum("ij,ij->i", o[ok], exact[ok]) > 0)
        assert out >= OUTWARD[name], (name, out)


def test_thin_box_limit():
    """A closed box 2 samples thick at a ~30-neighbour radius: the ball spans both faces, so
    the PCA normals tilt (median |n . N| ~ 0.92) and some forest edges still cross the
    sheet. Documented: ~98% outward (>= 97%) with the sheet-penalising weight; Hoppe's weight
    alone gives ~50%."""
    s = shapes.thin_box(0.01, 0.02)
    pts, exact = s["points"], s["normals"]
    r = _radius(pts)
    n = clcurv.normals(pts, r, orient=None)
    o = np.where(orient.flip_by_propagation(pts, n, k=K, radius=r)[:, None], -n, n)
    assert np.mean(np.einsum("ij,ij->i", o, exact) > 0) >= 0.97
    hoppe = orient.edge_weights
    try:
        orient.edge_weights = lambda a, b, e: 1.0 - np.abs(np.einsum("...k,...k->...", a, b))
        o = np.where(orient.flip_by_propagation(pts, n, k=K, radius=r)[:, None], -n, n)
    finally:
        orient.edge_weights = hoppe
    assert np.mean(np.einsum("ij,ij->i", o, exact) > 0) < 0.9


def test_default_call_is_outward_and_deterministic(device):
    """clcurv.normals and a signed curvature by default: outward, and bit-identical twice."""
    s = shapes.hollow_shell(40_000)
    r = _radius(s["points"])
    a = clcurv.normals(s["points"], r, device=device)
    b = clcurv.normals(s["points"], r, device=device)
    np.testing.assert_array_equal(a, b)
    ok = np.isfinite(a).all(axis=1)
    assert np.mean(np.einsum("ij,ij->i", a[ok], s["normals"][ok]) > 0) >= 0.999
    res = clcurv.curvature(s["points"], r, method="mls2", device=device)
    assert res.info["orientation"] == "mst"
    v = res.valid
    assert np.mean(np.sign(res.mean[v]) == np.sign(s["H"][v])) >= 0.999   # inner wall < 0


def test_rotations_give_the_same_outward_choice(device):
    s = shapes.torus(40_000)
    r = _radius(s["points"])
    rng = np.random.default_rng(7)
    for _ in range(3):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        n = clcurv.normals(s["points"] @ q.T, r, device=device)
        ok = np.isfinite(n).all(axis=1)
        assert np.mean(np.einsum("ij,ij->i", n[ok], (s["normals"] @ q.T)[ok]) > 0) >= 0.999


def test_signs_equal_on_every_device():
    """The same normals give the same flips on every OpenCL device present (simulators
    excepted: conftest.DEVICES)."""
    s = shapes.sphere(20_000, 1.0)
    r = _radius(s["points"])
    n = clcurv.normals(s["points"], r, orient=None)
    flips = [orient.flip_on_device(clcurv.DeviceCloud(s["points"], r, device=d), n, r, K)
             for d in DEVICES]
    for f in flips[1:]:
        np.testing.assert_array_equal(f, flips[0])


def test_bad_input_gets_documented_flips(device):
    """NaN normals: flip False; isolated points and one-point components: away from the
    centroid of all valid points; never a crash."""
    s = shapes.sphere(5000, 1.0)
    pts = np.vstack([s["points"], [[5.0, 0, 0], [0, 6.0, 0]]])       # two isolated points
    r = _radius(s["points"])
    cloud = clcurv.DeviceCloud(pts, r, device=device)
    n = np.vstack([s["normals"] * np.where(np.arange(5000) % 2, 1, -1)[:, None],
                   [[-1.0, 0, 0], [0, 1.0, 0]]])
    n[::97] = np.nan
    flip = orient.flip_on_device(cloud, n, r, K)
    assert not flip[::97].any()
    assert flip[-2] and not flip[-1]                    # both end up facing away (+x, +y)
    o = np.where(flip[:, None], -n, n)
    ok = np.isfinite(n).all(axis=1)
    truth = np.vstack([s["normals"], [[1.0, 0, 0], [0, 1.0, 0]]])
    assert np.all(np.einsum("ij,ij->i", o[ok], truth[ok]) > 0)
    np.testing.assert_array_equal(flip, orient.flip_by_propagation(pts, n, k=K, radius=r))


def test_up_and_direction_orientations():
    """orient='up' (PDAL's always_up) and a direction vector: every valid normal makes a
    non-negative dot product with it; the signed curvature of a bump follows."""
    from conftest import bumpy_surface
    pts = bumpy_surface(20_000, seed=3)
    n = clcurv.normals(pts, 0.08, orient="up")
    ok = np.isfinite(n).all(axis=1)
    assert ok.mean() > 0.99 and np.all(n[ok, 2] >= 0)
    d = np.array([1.0, -2.0, 0.5])
    m = clcurv.normals(pts, 0.08, orient=d)
    assert np.all(m[ok] @ d >= 0)
    with pytest.raises(ValueError, match="direction"):
        clcurv.normals(pts, 0.08, orient=(0, 0, 0))
    res = clcurv.curvature(pts, 0.08, method="mls2", orient="up")
    assert np.all(res.normals[res.valid, 2] >= 0)


def test_unsigned_methods_pay_for_no_orientation():
    """Their default call orients nothing (info['orientation'] is None) and gives the
    values of an oriented call."""
    s = shapes.torus(20_000)
    r = _radius(s["points"])
    for method in ("variation", "2dcov1", "2dcov2", "3dcov"):
        a = clcurv.curvature(s["points"], r, method=method)
        b = clcurv.curvature(s["points"], r, method=method, orient="mst")
        assert a.info["orientation"] is None and b.info["orientation"] == "mst"
        field = "variation" if method == "variation" else "k1"
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-4,
                                   atol=1e-6 * np.nanmax(np.abs(getattr(b, field))))


def test_cli_orients_las_up_by_default(tmp_path):
    from conftest import bumpy_surface
    pts = bumpy_surface(5000, seed=4) * 100.0                 # a terrain tile, in metres
    clcurv.io.write(tmp_path / "t.las", pts)
    from clcurv.cli import main as cli
    assert cli.main(["compute", str(tmp_path / "t.las"), "-o", str(tmp_path / "o.ply"),
                     "--method", "mls2", "-q"]) == 0
    out = clcurv.io.read(tmp_path / "o.ply")
    ok = out.attributes["status"] == 0
    assert ok.mean() > 0.9 and np.all(out.normals[ok, 2] >= 0)
    # a viewpoint below wins over the LAS default
    assert cli.main(["compute", str(tmp_path / "t.las"), "-o", str(tmp_path / "m.ply"),
                     "--method", "mls2", "--viewpoint", "0", "0", "-1000", "-q"]) == 0
    m = clcurv.io.read(tmp_path / "m.ply")
    assert np.all(m.normals[ok, 2] <= 0)


def test_mls2_orients_its_own_normals(device):
    """By default MLS2 runs once without reference normals and orients its fitted normals
    afterwards (Operator.flip: n -> -n, (k1, k2) -> (-k2, -k1), dir1 <-> dir2): the same
    values as a run oriented by the exact normals, with no PCA pass first."""
    s = shapes.torus(50_000)
    a = clcurv.curvature(s["points"], 0.1, method="mls2", device=device)
    b = clcurv.curvature(s["points"], 0.1, method="mls2", normals=s["normals"], device=device)
    v = a.valid & b.valid
    assert v.mean() > 0.99
    assert np.all(np.einsum("ij,ij->i", a.normals[v], b.normals[v]) > 0.999)
    for f in ("k1", "k2", "mean", "gaussian"):
        np.testing.assert_allclose(getattr(a, f)[v], getattr(b, f)[v], rtol=1e-5, atol=1e-5)
    gap = (a.k1 - a.k2)[v] > 0.1                       # directions defined
    assert np.all(np.abs(np.einsum("ij,ij->i", a.dir1[v][gap], b.dir1[v][gap])) > 0.999)
    assert np.all(np.einsum("ij,ij->i", np.cross(a.normals, a.dir1)[v], a.dir2[v]) > 0.999)


def test_orient_k_bound_is_the_graph_bound():
    from clcurv.api.curvature import MAX_ORIENT_K
    from clcurv.orient.graph import KMAX
    assert MAX_ORIENT_K == KMAX
