"""features(..., radius=[...], optimal=True): each point's radius of least eigenentropy of
its sum-normalised eigenvalues (clcurv.ops.optimal), against the float64 reference's choice,
bit-identical to single-radius calls at the chosen radii, on a shape whose answer is known,
and its documented edge cases."""
import numpy as np
import pytest

import clcurv
from clcurv._shared.constants import OK, TOO_FEW
from clcurv.ops.optimal import choose, eigenentropy_normalised
from test_features import synthetic_scene

RADII = [0.1, 0.14, 0.2, 0.28]
NAMES = ["planarity", "eigenentropy", "eigenvalue3", "normals"]


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(0)[::2]          # 11.5k points: plane, cylinder, sphere, blob


def test_entropy_and_choice_rules():
    """E of known spectra (a line 0, an isotropic plane ln 2, a volume ln 3; 0 ln 0 = 0);
    the choice: least E among status-0 candidates, ties to the smallest radius, the
    largest where none is ok."""
    e = eigenentropy_normalised([1, 1, 1, 2, np.nan], [0, 1, 1, 0, 1], [0, 0, 1, 0, 1])
    np.testing.assert_allclose(e[:4], [0, np.log(2), np.log(3), 0], rtol=1e-15, atol=0)
    assert np.isnan(e[4])
    ent = np.array([[0.5, 0.2, 0.3], [0.4, 0.2, 0.1], [0.4, 0.1, 0.2]])
    st = np.array([[OK, OK, 1], [OK, OK, 1], [OK, 2, 1]], np.uint8)
    idx, ok = choose(ent, st)
    np.testing.assert_array_equal(idx, [1, 0, 2])    # 0.4 twice: the smaller radius
    np.testing.assert_array_equal(ok, [True, True, False])


def test_choice_matches_the_float64_reference(scene, device):
    """The device's choice is the reference's (cKDTree, float64 eigh) wherever the best
    two candidates' entropies differ by more than 1e-4 (float32 eigenvalues move E by
    ~1e-6: measured agreement 100% here); the values there agree with the reference's at
    the same radius."""
    dev = clcurv.features(scene, RADII, NAMES, optimal=True, device=device)
    ref = clcurv.features(scene, RADII, NAMES, optimal=True, backend="numpy")
    i, j = dev.info["optimal_index"], ref.info["optimal_index"]
    ents = np.sort(np.stack([eigenentropy_normalised(*_ref_eig(scene, r)) for r in RADII]),
                   axis=0)
    clear = (ents[1] - ents[0]) > 1e-4
    assert clear.mean() > 0.95
    np.testing.assert_array_equal(i[clear], j[clear])
    assert (i == j).mean() > 0.999
    np.testing.assert_array_equal(dev.radius, np.asarray(RADII)[i])
    same = (i == j) & (dev.status == OK)
    np.testing.assert_array_equal(dev.count[i == j], ref.count[i == j])
    np.testing.assert_allclose(dev["planarity"][same], ref["planarity"][same], rtol=1e-4,
                               atol=2.0 ** -20)


def _ref_eig(pts, r):
    v, _, _ = clcurv.reference.features.features(pts, r, ["eigenvalue1", "eigenvalue2",
                                                          "eigenvalue3"])
    return v["eigenvalue1"], v["eigenvalue2"], v["eigenvalue3"]


def test_bit_identical_to_single_radius_calls(scene, device):
    """Each point's values, count and status are those of a single-radius call at its
    chosen radius on the same DeviceCloud, bit for bit; the radii's order does not matter."""
    cloud = clcurv.DeviceCloud(scene, max(RADII), device=device)
    res = clcurv.features(cloud, RADII[::-1], NAMES, optimal=True)
    assert res.info["radii"] == RADII
    idx = res.info["optimal_index"]
    assert len(np.unique(idx)) == len(RADII)         # every candidate chosen somewhere
    for j, r in enumerate(RADII):
        one = clcurv.features(cloud, r, NAMES)
        m = idx == j
        np.testing.assert_array_equal(res.count[m], one.count[m])
        np.testing.assert_array_equal(res.status[m], one.status[m])
        for n in NAMES:
            np.testing.assert_array_equal(res[n][m], one[n][m], err_msg=n)


def test_a_wire_above_a_plane_keeps_to_the_wire(device):
    """A straight wire 0.25 above a plane: balls smaller than 0.25 hold wire points only
    (a line: E ~ 0), larger ones plane points too (E grows), so the wire's points away
    from its ends choose a radius below 0.25."""
    rng = np.random.default_rng(5)
    plane = np.c_[rng.uniform(-1, 1, (20000, 2)), rng.normal(0, 0.002, 20000)]
    x = np.linspace(-1, 1, 400)
    wire = np.c_[x, rng.normal(0, 0.001, 400), 0.25 + rng.normal(0, 0.001, 400)]
    res = clcurv.features(np.vstack([plane, wire]), [0.06, 0.1, 0.16, 0.3, 0.45],
                          ["linearity"], optimal=True, device=device)
    mid = np.abs(x) < 0.5
    r_wire = res.radius[20000:][mid]
    assert (r_wire < 0.25).all(), np.unique(r_wire, return_counts=True)
    assert (res["linearity"][20000:][mid] > 0.99).all()


def test_edge_cases(device):
    """An isolated point: no candidate of status 0, the largest radius and its status
    (NaN values). Errors: one radius, optimal with k. Empty input: an empty result; a
    single point: status 1 and the sparse-ball warning."""
    pts = np.vstack([clcurv.shapes.sphere(3000, 1.0, seed=3)["points"], [[10.0, 10, 10]]])
    res = clcurv.features(pts, [0.1, 0.2], ["planarity"], optimal=True, device=device)
    assert res.radius[-1] == 0.2 and res.status[-1] == TOO_FEW
    assert np.isnan(res["planarity"][-1])
    assert (res.status[:-1] == OK).all()
    with pytest.raises(ValueError, match="at least two radii"):
        clcurv.features(pts, 0.1, optimal=True, device=device)
    with pytest.raises(ValueError, match="at least two radii"):
        clcurv.features(pts, [0.1], optimal=True, device=device)
    with pytest.raises(ValueError, match="not with k"):
        clcurv.features(pts, k=10, optimal=True, device=device)
    empty = clcurv.features(np.empty((0, 3)), [0.1, 0.2], ["planarity"], optimal=True,
                            device=device)
    assert len(empty) == 0 and len(empty["planarity"]) == 0
    with pytest.warns(RuntimeWarning, match="within their own radius"):
        one = clcurv.features([[1.0, 2.0, 3.0]], [0.1, 0.2], optimal=True, device=device)
    assert one.radius.tolist() == [0.2] and one.status.tolist() == [TOO_FEW]


def test_cli_optimal(tmp_path):
    """`clcurv features --optimal`: one set of fields plus optimal_radius, as the API; with
    one radius, exit code 2."""
    from clcurv.cli.main import main
    pts = clcurv.shapes.sphere(4000, 1.0, noise=0.005, seed=8)["points"]
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    clcurv.io.write(src, pts)
    assert main(["features", str(src), "-o", str(out), "--radius", "0.15,0.2,0.3",
                 "--features", "planarity", "--optimal"]) == 0
    attrs = clcurv.io.read(out).attributes
    api = clcurv.features(pts, [0.15, 0.2, 0.3], ["planarity"], optimal=True)
    np.testing.assert_allclose(attrs["optimal_radius"], api.radius, rtol=1e-7)  # PLY: float32
    np.testing.assert_allclose(attrs["planarity"], api["planarity"], rtol=1e-6)
    assert main(["features", str(src), "-o", str(out), "--radius", "0.2", "--optimal"]) == 2
