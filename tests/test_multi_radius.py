"""Several radii in one neighbour walk: features (features.cl, NR balls per walk) and
curvature(method='variation'/covariances, radius=[...]) are bit-identical to separate
single-radius calls on the same DeviceCloud (same binning, hence the same candidate order
and the same float32 offsets); plain calls, binned at their own radius, agree to float32
round-off."""
import numpy as np
import pytest

import clcurv
from clcurv.constants import OK

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


@pytest.mark.parametrize("method", ["variation", "2dcov1", "3dcov"])
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
