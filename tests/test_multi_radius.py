"""Several radii in one neighbour walk: features (features.cl, NR balls per walk) and
curvature(method='variation'/covariances, radius=[...]) are bit-identical to separate
single-radius calls on the same DeviceCloud (same binning, hence the same candidate order
and the same float32 offsets); plain calls, binned at their own radius, agree to float32
round-off."""
import numpy as np
import pytest

import clcurv
from clcurv._shared.constants import OK

RADII = [0.06, 0.1, 0.15]


@pytest.fixture(scope="module")
def torus():
    return clcurv.shapes.torus(30000, noise=0.003, seed=11)["points"]


def _same(a, b):
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_array_equal(a.status, b.status)
    for k, v in a.values.items():
        np.testing.assert_array_equal(v, b.values[k], err_msg=k)


def test_features_bit_identical_to_single_radius(torus, device):
    cloud = clcurv.DeviceCloud(torus, max(RADII), device=device)
    multi = clcurv.features(cloud, RADII, "all")
    assert [m.radius for m in multi] == RADII
    for r, m in zip(RADII, multi):
        _same(m, clcurv.features(cloud, r, "all"))
    # the balls grow with r: counts do, and every point is a neighbour of itself
    assert (multi[0].count <= multi[1].count).all() and (multi[1].count <= multi[2].count).all()


# features that do not use l3, the anchored smallest eigenvalue
L3_FREE = ("eigenvalue1", "eigenvalue2", "linearity", "verticality", "nx", "ny", "nz")


def test_features_in_double(torus, device):
    """In double, on the same DeviceCloud: counts, statuses and every feature that does not
    use l3 bit for bit. l3 comes from the anchor frame's formula (pca.h: pca_anchor_l0),
    accurate to about eps l1 by its cancellation; on PoCL it is bit for bit as well, while
    Intel's CPU runtime rounds it differently in the one-walk and the single-radius
    kernels (in ~7% of the points here, by at most 0.05 eps l1). So l3 within eps l1, and
    each feature that uses it within what such an l3 moves it: eps-sized for the ratios
    and sums, cbrt(eps) l1 for the omnivariance (a cube root of l1 l2 l3 with l3 near 0),
    eps l1 (1 + |ln(eps l1)|) for the eigenentropy (its l3 ln l3)."""
    if not device.info.fp64:
        pytest.skip(f"{device.info.name} has no cl_khr_fp64")
    cloud = clcurv.DeviceCloud(torus, max(RADII), device=device, precision="double")
    eps = np.finfo(np.float64).eps
    for r, m in zip(RADII, clcurv.features(cloud, RADII, "all")):
        s = clcurv.features(cloud, r, "all")
        np.testing.assert_array_equal(m.count, s.count)
        np.testing.assert_array_equal(m.status, s.status)
        l1 = s["eigenvalue1"]
        d = eps * l1                                       # l3's accuracy
        tol = {"eigenvalue3": d, "eigenvalue_sum": 2 * d, "omnivariance": np.cbrt(eps) * l1,
               "eigenentropy": d * (1 + np.abs(np.log(d)))}
        for k in s.values:
            a, b = m[k], s[k]
            if k in L3_FREE or k == "normals":
                np.testing.assert_array_equal(a, b, err_msg=k)
                continue
            t = tol.get(k, 8 * eps)                        # ratios of l's: eps-sized
            t = np.broadcast_to(t, b.shape)
            ok = (np.isnan(a) & np.isnan(b)) | (np.abs(a - b) <= t)
            assert ok.all(), (k, r, np.abs(a - b)[~ok][:3], t[~ok][:3])


def test_more_radii_than_one_walk(torus, device):
    """Five radii: two walks (4 + 1), still identical to single calls; the order given is
    kept (not sorted)."""
    radii = [0.15, 0.05, 0.08, 0.12, 0.1]
    cloud = clcurv.DeviceCloud(torus, 0.15, device=device)
    multi = clcurv.features(cloud, radii, ["planarity", "normals"])
    for r, m in zip(radii, multi):
        _same(m, clcurv.features(cloud, r, ["planarity", "normals"]))


def test_plain_calls_agree_to_round_off(torus, device):
    """Without a shared DeviceCloud the list bins once at 0.15 and a single call at its own
    radius: the float32 offsets differ in the last bits, not more (counts equal but for
    points within round-off of the sphere)."""
    multi = clcurv.features(torus, RADII, ["eigenvalue1", "planarity"], device=device)
    single = clcurv.features(torus, RADII[0], ["eigenvalue1", "planarity"], device=device)
    same = multi[0].count == single.count
    assert same.mean() > 0.999
    same &= single.status == OK
    np.testing.assert_allclose(multi[0]["eigenvalue1"][same], single["eigenvalue1"][same],
                               rtol=1e-5)


@pytest.mark.parametrize("method", ["variation", "2dcov1", "2dcov2", "3dcov"])
def test_curvature_radius_list(torus, device, method):
    cloud = clcurv.DeviceCloud(torus, max(RADII), device=device)
    multi = clcurv.curvature(cloud, RADII, method=method)
    assert len(multi) == 3
    for r, m in zip(RADII, multi):
        one = clcurv.curvature(cloud, r, method=method)
        assert m.radius == r
        for k, v in one.arrays().items():
            np.testing.assert_array_equal(getattr(m, k), v, err_msg=f"{method} {r} {k}")


def test_radius_list_refusals(torus, device):
    with pytest.raises(ValueError, match="list of radii"):
        clcurv.curvature(torus[:1000], RADII, method="mls2", device=device)
    with pytest.raises(ValueError, match="repeat"):
        clcurv.features(torus[:1000], [0.1, 0.1], device=device)
    with pytest.raises(ValueError, match="radius"):
        clcurv.features(torus[:1000], [0.1, -1], device=device)


@pytest.mark.parametrize("precision", ["float", "double"])
def test_covariances_pca_of_every_radius_in_one_walk(torus, device, precision):
    """The PCA normals the covariance operators take for a list of radii come from one walk
    of the features kernel built as the moments kernel's normals pass (REFINE_L0=0): normals,
    count and status identical, bit for bit, to that pass at each radius, on a cloud with
    points of every status (an isolated point, too few; a collinear cluster, degenerate)."""
    if precision == "double" and not device.info.fp64:
        pytest.skip(f"{device.info.name} has no cl_khr_fp64")
    from clcurv.api.curvature import _Run
    from clcurv.ops.features import run_features
    line = np.column_stack([np.linspace(0, 0.05, 12), np.zeros(12), np.zeros(12)]) + [3, 0, 0]
    pts = np.vstack([torus[:20000], [[5.0, 5.0, 5.0]], line])
    cloud = clcurv.DeviceCloud(pts, max(RADII), device=device, precision=precision)
    walk = run_features(cloud, RADII, ("normals",), anchored=False)
    for r, (vals, count, status) in zip(RADII, walk):
        one = _Run("opencl", pts, r, device, precision, cloud).pca_normals("uniform")
        np.testing.assert_array_equal(vals["normals"], one["normals"], err_msg=str(r))
        np.testing.assert_array_equal(count, one["count"])
        np.testing.assert_array_equal(status, one["status"])
        assert set(np.unique(status)) == {0, 1, 2}       # every status is exercised


def test_covariances_walk_the_pca_once(torus, device, monkeypatch):
    """curvature(method='2dcov1', radius=[3 radii]) runs no moments pass (the PCA of the
    three radii is one features walk) and one covariance pass per radius; its results are
    those of the single calls (test_curvature_radius_list)."""
    import importlib
    from clcurv.ops.registry import PCA
    api = importlib.import_module("clcurv.api.curvature")   # the driver as the API calls it
    runs = []
    real = api.run_kernel

    def spy(kernel, *args, **kw):
        runs.append(kernel.name)
        return real(kernel, *args, **kw)
    monkeypatch.setattr(api, "run_kernel", spy)
    cloud = clcurv.DeviceCloud(torus, max(RADII), device=device)
    clcurv.curvature(cloud, RADII, method="2dcov1", orient=None)
    assert runs.count(PCA.name) == 0 and runs.count("2dcov1") == 3, runs
    runs.clear()
    clcurv.curvature(cloud, RADII[0], method="2dcov1", orient=None)
    assert runs == [PCA.name, "2dcov1"]


@pytest.mark.parametrize("size", [3, 16, 32])
def test_walk_buffer_size_keeps_the_bits(torus, device, monkeypatch, size):
    """FEATURES_BUF, the chunks the multi-radius walk keeps before each ball's sums run
    over them (the host's choice per device, clcurv.runtime.program.features_buffer), changes how
    often the sums pause, not their additions or order: the features of three radii and
    the covariance operators' PCA normals are the same bits at any size (3: many partial
    runs a point) as with the device's own."""
    import clcurv.grid.cloud
    from clcurv.ops.features import run_features
    from clcurv.runtime.program import features_buffer
    own = clcurv.DeviceCloud(torus, max(RADII), device=device)
    ref = clcurv.features(own, RADII, "all")
    ref_normals = run_features(own, RADII, ("normals",), anchored=False)
    real = clcurv.grid.cloud.precision_defines
    monkeypatch.setattr(clcurv.grid.cloud, "precision_defines",
                        lambda dev, prec: dict(real(dev, prec), FEATURES_BUF=size))
    cloud = clcurv.DeviceCloud(torus, max(RADII), device=device)
    assert cloud.defines["FEATURES_BUF"] == size
    assert own.defines["FEATURES_BUF"] == features_buffer(device.info)
    for a, b in zip(clcurv.features(cloud, RADII, "all"), ref):
        _same(a, b)
    for (va, ca, sa), (vb, cb, sb) in zip(run_features(cloud, RADII, ("normals",),
                                                       anchored=False), ref_normals):
        np.testing.assert_array_equal(va["normals"], vb["normals"])
        np.testing.assert_array_equal(ca, cb)
        np.testing.assert_array_equal(sa, sb)


def test_walk_buffer_choice():
    """32 chunks on CPU devices, 16 on the others (GPUs: private arrays in slow memory)."""
    import dataclasses
    from clcurv.runtime.program import features_buffer
    base = clcurv.runtime.device.DeviceInfo(0, "d", "p", "v", "cpu", "1", "1.2", True, 1, 1, 1, 1, 1)
    assert features_buffer(base) == 32
    assert features_buffer(dataclasses.replace(base, kind="gpu")) == 16
