"""Bad input gets a clear error or a documented, tested behaviour."""
import dataclasses
import warnings

import numpy as np
import pytest

import clcurv
from clcurv.runtime.program import PrecisionError, precision_defines
from clcurv.api.result import DEGENERATE, TOO_FEW

from conftest import bumpy_surface


@pytest.mark.parametrize("bad", [np.zeros((5, 2)), np.zeros(5), np.zeros((2, 5, 3)), [[1, 2]]])
def test_wrong_shape(bad):
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        clcurv.curvature(bad, 0.1)


@pytest.mark.parametrize("bad", [np.zeros((4, 3), complex), np.zeros((4, 3), bool),
                                 np.array([["a", "b", "c"]]), np.array([[None] * 3])])
def test_wrong_dtype(bad):
    with pytest.raises(TypeError, match="real numeric"):
        clcurv.curvature(bad, 0.1)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_points(value):
    pts = bumpy_surface(100, seed=0)
    pts[[3, 7], 1] = value
    with pytest.raises(ValueError, match=r"2 row\(s\) with NaN or Inf \(first at index 3\)"):
        clcurv.curvature(pts, 0.1)


CALLS = {
    "variation": lambda p, **kw: clcurv.curvature(p, 0.1, method="variation", **kw),
    "mls2 scale_space": lambda p, **kw: clcurv.curvature(p, 0.1, method="mls2",
                                                        scale_space=2, **kw),
    "mls2 projections": lambda p, **kw: clcurv.curvature(p, 0.1, method="mls2",
                                                        projections=1, **kw),
    "radii": lambda p, **kw: clcurv.curvature(p, [0.05, 0.1], method="3dcov", **kw),
    "k": lambda p, **kw: clcurv.curvature(p, method="mls1", k=10, **kw),
    "normals viewpoint": lambda p, **kw: clcurv.normals(p, 0.1, viewpoint=(0, 0, 5), **kw),
    "project": lambda p, **kw: clcurv.project(p, 0.1, **kw),
    "features": lambda p, **kw: clcurv.features(p, 0.1, **kw),
    "features k": lambda p, **kw: clcurv.features(p, k=10, **kw),
    "features optimal": lambda p, **kw: clcurv.features(p, [0.05, 0.1], optimal=True, **kw),
}


@pytest.mark.parametrize("call", list(CALLS))
def test_every_call_refuses_non_finite_points(call, device):
    """On the OpenCL backend the finiteness check is the binning's (on its bounding box),
    not a pass of its own at the API: every public call still refuses NaN and Inf rows with
    the same message, before a kernel runs."""
    pts = bumpy_surface(400, seed=0)
    pts[[3, 7], 1] = [np.nan, -np.inf]
    with pytest.raises(ValueError, match=r"2 row\(s\) with NaN or Inf \(first at index 3\)"):
        CALLS[call](pts, device=device)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_points_of_a_device_cloud(value, device):
    """DeviceCloud, host_binning and a binning in a given frame (tiles) find them on the
    bounding box (clcurv._shared.validate.check_finite_box), with the same message."""
    from clcurv.grid.cloud import host_binning
    from clcurv.grid.binning import Frame, bin_points
    pts = bumpy_surface(100, seed=0)
    frame = Frame.covering(pts.min(axis=0) - 1, pts.max(axis=0) + 1, 0.1)
    pts[[3, 7], 1] = value
    msg = r"2 row\(s\) with NaN or Inf \(first at index 3\)"
    with pytest.raises(ValueError, match=msg):
        clcurv.DeviceCloud(pts, 0.1, device=device)
    with pytest.raises(ValueError, match=msg):
        host_binning(pts, 0.1)
    with pytest.raises(ValueError, match=msg):
        bin_points(pts, 0.1, frame=frame)


@pytest.mark.parametrize("radius", [0, -1, np.nan, np.inf])
def test_bad_radius(radius):
    with pytest.raises(ValueError, match="radius must be a positive finite"):
        clcurv.curvature(bumpy_surface(100, 0), radius)


def test_radius_not_a_number():
    with pytest.raises(TypeError, match="radius must be a number"):
        clcurv.curvature(bumpy_surface(100, 0), "big")


def test_no_radius_and_no_k_says_what_to_give():
    pts = bumpy_surface(100, 0)
    for fn in (clcurv.curvature, clcurv.normals):
        with pytest.raises(ValueError, match="give radius="):
            fn(pts)


@pytest.mark.parametrize("radius", [True, np.bool_(True), [0.1, True]])
def test_radius_bool_is_refused(radius):
    """A bool is no radius (float(True) would make it 1.0): single or in a list."""
    pts = bumpy_surface(100, 0)
    with pytest.raises(TypeError, match="radius must be a number"):
        clcurv.features(pts, radius)
    if np.ndim(radius) == 0:
        with pytest.raises(TypeError, match="radius must be a number"):
            clcurv.curvature(pts, radius)


@pytest.mark.parametrize("kw", [{"method": "mls9"}, {"weights": "gauss"}, {"backend": "cuda"},
                                {"orient": "inward"}, {"precision": "half"}])
def test_bad_options(kw, device):
    with pytest.raises(ValueError):
        clcurv.curvature(bumpy_surface(100, 0), 0.1, device=device, **kw)


def test_bad_normals_shape():
    with pytest.raises(ValueError, match="one row per point"):
        clcurv.curvature(bumpy_surface(100, 0), 0.1, normals=np.ones((99, 3)))
    with pytest.raises(ValueError, match="zero-length"):
        clcurv.curvature(bumpy_surface(100, 0), 0.1, normals=np.zeros((100, 3)))


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_empty_cloud(backend):
    res = clcurv.curvature(np.empty((0, 3)), 0.1, method="mls1", backend=backend)
    assert res.normals.shape == (0, 3) and res.mean.shape == (0,) and res.points.shape == (0, 3)
    assert clcurv.normals(np.empty((0, 3)), 0.1).shape == (0, 3)


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_single_point(backend):
    with pytest.warns(RuntimeWarning, match="fewer than 3 neighbours"):
        res = clcurv.curvature([[1.0, 2.0, 3.0]], 0.1, method="mls1", backend=backend)
    assert res.count.tolist() == [1] and res.status.tolist() == [TOO_FEW]
    assert np.isnan(res.mean).all() and np.isnan(res.normals).all() and np.isnan(res.points).all()


def test_radius_with_no_neighbours(device):
    pts = bumpy_surface(2000, 0)
    with pytest.warns(RuntimeWarning, match="radius is probably too small"):
        res = clcurv.curvature(pts, 1e-6, method="mls1", device=device)
    assert (res.count == 1).all() and (res.status == TOO_FEW).all()
    assert np.isnan(res.mean).all() and np.isnan(res.variation).all()


def test_duplicated_points_do_not_change_moments(device):
    pts = bumpy_surface(5000, 1)
    one = clcurv.curvature(pts, 0.1, method="mls1", device=device)
    two = clcurv.curvature(np.concatenate([pts, pts]), 0.1, method="mls1", device=device)
    np.testing.assert_array_equal(two.count[:5000], 2 * one.count)
    np.testing.assert_allclose(two.eigenvalues[:5000], one.eigenvalues, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(two.mean[:5000], one.mean, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(two.normals[:5000], two.normals[5000:])


def test_coincident_and_collinear_points_are_degenerate(device):
    same = np.tile([[1.0, 1.0, 1.0]], (10, 1))
    line = np.column_stack([np.linspace(0, 1, 50), 2 * np.linspace(0, 1, 50), np.zeros(50)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for pts in (same, line):
            res = clcurv.curvature(pts, 0.2, method="mls1", device=device)
            assert (res.status == DEGENERATE).all()
            assert np.isnan(res.normals).all() and np.isnan(res.mean).all()


def test_far_from_origin_gives_same_results(device):
    pts = bumpy_surface(20000, 2)
    offset = np.array([512_345.678, 4_987_654.321, 250.0])      # UTM-like
    a = clcurv.curvature(pts, 0.08, method="mls1", device=device)
    b = clcurv.curvature(pts + offset, 0.08, method="mls1", device=device)
    np.testing.assert_array_equal(a.count, b.count)
    cos = np.einsum("ij,ij->i", a.normals, b.normals)
    assert (cos[a.valid] > 1 - 1e-6).all()
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(a.variation, b.variation, rtol=1e-4)
    np.testing.assert_allclose(b.points - offset, a.points, atol=1e-6)


def test_integer_and_float32_input(device):
    """Integer and float32 coordinates are read as the float64 numbers they stand for:
    the results equal those of the float64 array bit for bit, and match the float64
    reference's. On an integer grid squared distances are exact integers, many exactly
    r^2 = 9 ((3, 0, 0), (2, 2, 1)): the counts equal the reference's, so the ball is open
    (|q - p| < r) for every input type."""
    pts = np.random.default_rng(3).integers(0, 20, size=(3000, 3))
    want = clcurv.curvature(pts.astype(np.float64), 3.0, method="variation", device=device,
                            orient=None)
    ref = clcurv.curvature(pts.astype(np.float64), 3.0, method="variation", backend="numpy",
                           orient=None)
    assert want.valid.mean() > 0.99
    d2 = ((pts[:300, None, :] - pts[None, :, :]) ** 2).sum(axis=2)
    assert (d2 == 9).sum() > 100                            # the case is exercised
    np.testing.assert_array_equal(want.count, ref.count)
    ok = want.valid & ref.valid
    np.testing.assert_allclose(want.variation[ok], ref.variation[ok], rtol=1e-3, atol=1e-6)
    for dtype in (np.int64, np.int32, np.int16, np.uint8, np.float32):
        got = clcurv.curvature(pts.astype(dtype), 3.0, method="variation", device=device,
                               orient=None)
        for k, v in want.arrays().items():
            np.testing.assert_array_equal(got.arrays()[k], v, err_msg=f"{dtype.__name__} {k}")


def test_double_on_device_without_fp64(device):
    no_fp64 = dataclasses.replace(device.info, fp64=False)
    fake = type("D", (), {"info": no_fp64})()
    with pytest.raises(PrecisionError, match="no float64 support"):
        precision_defines(fake, "double")


def test_unknown_device():
    with pytest.raises(clcurv.NoDeviceError, match="no OpenCL device matches"):
        clcurv.curvature(bumpy_surface(100, 0), 0.1, device="no-such-accelerator")


def test_huge_bounding_box_is_an_error_not_a_dense_grid(device):
    pts = np.array([[0.0, 0.0, 0.0], [1e9, 1e9, 1e9], [1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"more than the 2\^62"):
        clcurv.curvature(pts, 1e-6, device=device)


def test_large_lidar_tile_uses_a_sparse_grid(device):
    """A 10 km x 10 km tile at r = 0.5 m: 2e4 x 2e4 cells in x, y, but memory O(N)."""
    from clcurv.grid.cloud import DeviceCloud
    rng = np.random.default_rng(4)
    centres = rng.uniform(0, 10_000, (200, 2))                 # 200 patches of 100 points
    xy = (centres[:, None, :] + rng.uniform(-1, 1, (200, 100, 2))).reshape(-1, 2)
    pts = np.column_stack([xy + [512_000.0, 4_870_000.0], rng.normal(100, 0.01, len(xy))])
    cloud = DeviceCloud(pts, 0.5, device=device)
    assert cloud.grid.dims[0] * cloud.grid.dims[1] > 3e8     # a dense grid would be huge
    assert cloud.grid.ncells <= len(pts) and len(cloud.grid.cell_start) == cloud.grid.ncells + 1
    res = clcurv.curvature(pts, 0.5, method="variation", orient=None, device=device)
    assert res.valid.mean() > 0.95 and np.nanmedian(res.variation) < 1e-3   # flat patches


def test_normals_length_does_not_matter(device):
    """Normals of any length (1e-60 .. 1e60 per row: beyond float32) give the results of the
    unit ones: MLS2 and the moment methods use only their sign, the others normalise them."""
    pts = bumpy_surface(3000, seed=5)
    unit = clcurv.normals(pts, 0.12, orient=None, device=device)
    unit[:, 2] = np.abs(unit[:, 2])
    ok = np.isfinite(unit).all(axis=1)
    pts, unit = pts[ok], unit[ok]
    scale = np.geomspace(1e-60, 1e60, len(pts))[np.random.default_rng(0).permutation(len(pts))]
    for method in ("mls2", "mls0", "mls1", "2dcov2"):
        a = clcurv.curvature(pts, 0.12, method=method, normals=unit, device=device)
        b = clcurv.curvature(pts, 0.12, method=method, normals=unit * scale[:, None],
                             device=device)
        np.testing.assert_allclose(b.mean if b.mean is not None else b.k1,
                                   a.mean if a.mean is not None else a.k1, rtol=1e-6, atol=1e-9,
                                   err_msg=method)


def test_bad_normals_of_a_large_cloud_still_raise(device):
    """From api.DEFER_MIN points the normals are checked on a host thread while the cloud
    is binned: their errors must still reach the caller, before any result."""
    from clcurv.api.curvature import DEFER_MIN
    pts = bumpy_surface(DEFER_MIN, seed=8)
    nrm = np.tile([0.0, 0.0, 1.0], (DEFER_MIN, 1))
    nrm[123] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        clcurv.curvature(pts, 0.02, method="2dcov2", normals=nrm, device=device)
    nrm[123] = 0.0
    with pytest.raises(ValueError, match="zero-length"):
        clcurv.curvature(pts, 0.02, method="mls2", normals=nrm, device=device)
    nrm[123] = (0.0, 0.0, 1.0)
    res = clcurv.curvature(pts, 0.02, method="2dcov2", normals=nrm * 3.0, device=device)
    np.testing.assert_allclose(res.normals[:5], np.tile([0.0, 0.0, 1.0], (5, 1)))
