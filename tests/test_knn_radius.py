"""The k-NN radius (clcurv.ops.knn_radius, kernels/knn_radius.cl): radii against a k-d tree,
balls of k points, each operator's constants at its point's own radius, the 10x
density-varying sphere, and k > N, duplicates, isolated points."""
from pathlib import Path

import numpy as np
import pytest

import clcurv
import clcurv.ops.knn_radius as kr
from clcurv._shared.constants import DEGENERATE, OK, TOO_FEW
from clcurv.ops.knn_radius import knn_radii
from clcurv.reference.features import knn_radii as ref_knn_radii
from conftest import data_path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"      # when present


def sphere_10x(n, R=1.0, seed=0):
    """A sphere whose point density grows 10x from the north pole (z = R) to the south pole
    (z = -R): the area density is proportional to 1 + 9 u, u = (1 - z/R) / 2 (z is uniform on
    a uniformly sampled sphere, so u is drawn with the pdf (1 + 9 u) / 5.5 by inversion)."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 1, n)
    u = (-1 + np.sqrt(1 + 99 * t)) / 9
    z = R * (1 - 2 * u)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(np.maximum(R * R - z * z, 0))
    return np.c_[s * np.cos(phi), s * np.sin(phi), z]


def kth_squared(cloud, k, known=None, levels=None, extend=False, reach=None):
    """The squared distance to the k-th nearest point within the cloud's cell (device
    values as float64, input order; +inf where fewer than k points lie within it), or with
    ``extend`` within each point's reach (clcurv.ops.knn_radius.reach): knn_radius.cl run
    once (``known``, input order: the points with a finite value keep it; ``levels`` and
    ``reach``: as clcurv.ops.knn_radius._kth_launch)."""
    order = cloud.grid.order
    prev = None if known is None else known[order].astype(cloud.dtype)
    res = np.empty(cloud.n)
    res[order] = kr._kth_fetch(cloud, kr._kth_launch(cloud, k, prev, levels, extend, reach))
    return res


@pytest.fixture(scope="module")
def sphere():
    return sphere_10x(40000)


@pytest.mark.parametrize("k", [1, 4, 30, 100])
def test_radii_against_kdtree(sphere, device, k):
    got = knn_radii(sphere[::2], k, device=device)
    ref = ref_knn_radii(sphere[::2], k)
    assert not got.isolated.any()
    # float32 offsets from the cell corner, then sqrt: a few float32 ulps of r
    np.testing.assert_allclose(got.radius, ref, rtol=4e-6, atol=0 if k > 1 else 0)
    assert got.cloud.cell >= np.nanmax(got.radius)


@pytest.mark.parametrize("k", [4, 30])
def test_both_kernel_paths_select_the_same_distance(sphere, device, k):
    """knn_radius.cl's one-walk selection (the smallest d^2 kept per lane) and its counting
    path (forced by keeping one value per lane) give the same k-th distances, bit for bit,
    and those of the k-d tree (within float32 rounding of the offsets). With 4 values kept
    per lane most lanes drop some: the selection must take the k-th from the kept values
    only when it is at most the smallest largest kept value of those lanes (every value
    below that one is kept), and send the other points down the counting path."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    pts = sphere[::2]
    ref = cKDTree(pts).query(pts, k)[0][:, -1]
    cloud = DeviceCloud(pts, 1.6 * np.median(ref), device=device)
    fast = kth_squared(cloud, k)
    slow = kth_squared(cloud, k, levels=1)
    ok = np.isfinite(fast)
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(fast, kth_squared(cloud, k, levels=4))
    np.testing.assert_allclose(np.sqrt(fast[ok]), ref[ok], rtol=4e-6)
    assert (ref[~ok] >= 0.999 * cloud.cell).all()     # unresolved: k-th beyond the cell


@pytest.mark.parametrize("levels", range(1, 16))
def test_merge_network_keeps_the_smallest_sorted(levels):
    """merge_comparators(levels, batch), applied as knn_radius.cl applies them (KNN_CE: min
    to i, max to j; KNN_LO: the min only; KNN_HI: the max only), leaves in the kept
    positions the ``levels`` smallest of the kept values and the batch, sorted, for batches
    of 1 to 8 (values with many ties, and +inf, the empty slots); a batch of 2 costs 12
    min/max per chunk at 8 levels against 15 for one chunk at a time."""
    from clcurv.ops.knn_radius import merge_comparators
    rng = np.random.default_rng(levels)
    for batch in range(1, 9):
        net = merge_comparators(levels, batch)
        for _ in range(200):
            a = rng.integers(0, 12, levels).astype(float)
            b = rng.integers(0, 12, batch).astype(float)
            a[rng.random(levels) < 0.2] = np.inf
            b[rng.random(batch) < 0.2] = np.inf
            a.sort()
            v = np.r_[a, b]
            for i, j, kind in net:
                lo, hi = min(v[i], v[j]), max(v[i], v[j])
                if kind in ("ce", "lo"):
                    v[i] = lo
                if kind in ("ce", "hi"):
                    v[j] = hi
            np.testing.assert_array_equal(v[:levels], np.sort(np.r_[a, b])[:levels])
    ops = lambda net: sum(2 if kind == "ce" else 1 for *_, kind in net)
    if levels == 8:
        assert ops(merge_comparators(8, 1)) == 15 and ops(merge_comparators(8, 2)) == 24


@pytest.mark.parametrize("batch", [1, 3, 5])
def test_batched_merge_gives_the_same_distances(sphere, device, monkeypatch, batch):
    """Chunks merged into the kept values KNN_BATCH at a time (2 by default) keep each
    lane's smallest d^2 as merging each chunk alone does: the same k-th distances, bit for
    bit, with batches of 1, 3 and 5, at the default levels and at 4 (most lanes drop
    values), with and without the extended reach."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    pts = sphere[::2]
    cloud = DeviceCloud(pts, 1.3 * np.median(cKDTree(pts).query(pts, 30)[0][:, -1]),
                        device=device)
    runs = [(30, None, False), (30, 4, False), (30, None, True), (7, 4, True)]
    want = [kth_squared(cloud, k, levels=lv, extend=e) for k, lv, e in runs]
    monkeypatch.setattr(kr, "KNN_BATCH", batch)
    for w, (k, lv, e) in zip(want, runs):
        np.testing.assert_array_equal(kth_squared(cloud, k, levels=lv, extend=e), w)


def uniform_sphere(n, seed=3):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def test_extended_reach_resolves_more_points_exactly(device):
    """With extend (knn_radii's first level) a point's walk resolves its k-th distance
    anywhere within its reach, the cell plus its distance to the nearest face of its own
    cell (every point within it is among the walk's candidates), not only within the
    cell: what the cell resolves is unchanged, bit for bit; the points resolved beyond it
    get the k-d tree's distance; an unresolved point's k-th neighbour lies beyond its
    reach; the counting path gives the same values. On a uniform sphere at a cell of 1.13x
    the median k-th distance (knn_radii's first cell there) the points left unresolved go
    from ~9% to ~2% (8.6% and 1.8% on a 1M-point sphere)."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    from clcurv.ops.knn_radius import reach
    pts = uniform_sphere(20000)
    ref = cKDTree(pts).query(pts, 30)[0][:, -1]
    cloud = DeviceCloud(pts, 1.13 * np.median(ref), device=device)
    plain = kth_squared(cloud, 30)
    ext = kth_squared(cloud, 30, extend=True)
    ok, got = np.isfinite(plain), np.isfinite(ext)
    np.testing.assert_array_equal(ext[ok], plain[ok])
    assert (got >= ok).all() and 1 - got.mean() < 0.4 * (1 - ok.mean())
    assert (np.sqrt(ext[got & ~ok]) >= 0.99 * cloud.cell).all() and (got & ~ok).sum() > 100
    np.testing.assert_allclose(np.sqrt(ext[got]), ref[got], rtol=4e-6)
    assert (ref[~got] >= reach(cloud)[~got]).all()
    np.testing.assert_array_equal(kth_squared(cloud, 30, levels=1, extend=True), ext)


def test_radii_found_beyond_the_first_cell_take_the_next_cells(device, monkeypatch):
    """A first cell just below the largest k-NN radius of a uniform sphere, on the path of
    clouds that are not tight (TIGHT = 0 makes this one so): the first level's reach
    resolves every point, some beyond its cell, so the operators run on the cloud binned
    ahead at 1.5x that cell (no second walk): radii as the k-d tree's, every one within the
    operators' cell, each ball holding its k points."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    pts = uniform_sphere(20000)
    ref = cKDTree(pts).query(pts, 30)[0][:, -1]
    monkeypatch.setattr(kr, "FIRST_CELL", 1.5)
    monkeypatch.setattr(kr, "TIGHT", 0.0)
    got = knn_radii(pts, 30, device=device)
    first = got.levels[0]
    assert first < ref.max() and (ref < kr.reach(DeviceCloud(pts, first, device=device))).all()
    assert got.levels == [first, kr.GROWTH * first] and got.cloud.cell == kr.GROWTH * first
    np.testing.assert_allclose(got.radius, ref, rtol=4e-6)
    res = clcurv.features(pts, k=30, features=("eigenvalue_sum",), device=device)
    assert (res.count >= 30).all() and (res.count == 30).mean() > 0.999     # ties enter


@pytest.mark.parametrize("levels", [None, 1])
def test_a_narrower_reach_resolves_what_lies_within_it(device, levels):
    """A reach of ~0.65 of the cell (the first walk of a tight cloud, FIRST_REACH): every k-th
    distance below the reach is the full walk's, bit for bit, the others +inf, whose k-th
    neighbour lies at or beyond the reach by the k-d tree; a second walk at the whole cell
    from those values (known) gives the full walk's. Also on the counting path
    (levels = 1)."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    pts = uniform_sphere(20000)
    ref = cKDTree(pts).query(pts, 30)[0][:, -1]
    cloud = DeviceCloud(pts, 1.2 * ref.max(), device=device)
    full = kth_squared(cloud, 30, levels=levels)
    assert np.isfinite(full).all()
    rho = 1.05 * np.median(ref)                    # ~0.65 of the cell
    part = kth_squared(cloud, 30, levels=levels, reach=rho)
    inside = full < np.float32(rho * rho)          # the walk's open ball, in float
    assert 0.4 < inside.mean() < 0.8
    np.testing.assert_array_equal(part[inside], full[inside])
    assert np.isinf(part[~inside]).all() and (ref[~inside] >= 0.999999 * rho).all()
    np.testing.assert_array_equal(kth_squared(cloud, 30, known=part, levels=levels), full)


@pytest.mark.parametrize("first_reach", [None, 0.6])
def test_a_tight_cloud_is_binned_once(device, monkeypatch, first_reach):
    """A uniform sphere is tight (its median k-NN radius near the mean-density one): it is
    binned once, at GROWTH times the first cell, the operators' cloud too; its radii are
    one full walk's of that cloud, bit for bit (the first walk within FIRST_REACH of the
    cell, then the points left: most of them with FIRST_REACH = 0.6), and the k-d tree's;
    each ball holds its k points."""
    from clcurv.grid.binning import bounding_box
    if first_reach is not None:
        monkeypatch.setattr(kr, "FIRST_REACH", first_reach)
    pts = uniform_sphere(20000)
    c, tight = kr._first_cell(pts, 30, *bounding_box(pts))
    assert tight
    got = knn_radii(pts, 30, device=device)
    assert got.levels == [kr.GROWTH * c] and got.cloud.cell == np.float32(kr.GROWTH * c)
    np.testing.assert_array_equal(got.radius, np.sqrt(kth_squared(got.cloud, 30)))
    np.testing.assert_allclose(got.radius, ref_knn_radii(pts, 30), rtol=4e-6)
    res = clcurv.features(got.cloud, k=30, features=("eigenvalue_sum",), device=device)
    assert (res.count >= 30).all() and (res.count == 30).mean() > 0.999


def test_double_precision_radii(device):
    """precision='double' (devices with fp64): the k-NN radii of a tight cloud (binned once)
    and of an uneven one (a dense patch in a sparse plane: levels) are the k-d tree's to
    float64 round-off."""
    if not device.info.fp64:
        pytest.skip("the device has no float64")
    rng = np.random.default_rng(4)
    patch = np.c_[0.3 * rng.random((7500, 2)), np.zeros(7500)]
    far = np.c_[rng.random((2500, 2)) * 3.0 + 0.3, np.zeros(2500)]
    for pts, once in ((uniform_sphere(10000), True), (np.concatenate([patch, far]), False)):
        got = knn_radii(pts, 30, device=device, precision="double")
        assert (len(got.levels) == 1) == once
        np.testing.assert_allclose(got.radius, ref_knn_radii(pts, 30), rtol=1e-12)


def test_tightness_of_the_density():
    """_tight: a uniform sphere and a plane are tight; a dense patch within a sparse plane
    10x its area holding a quarter of the points (a depth image's near object and far
    background: the mean-density cell ~2.5x the median point's radius) is not; nor is the
    Kinect scene of the shared data (c / median 1.9, when present)."""
    from clcurv.grid.binning import bounding_box
    rng = np.random.default_rng(5)

    def tight(p):
        return kr._first_cell(p, 30, *bounding_box(p))[1]

    plane = np.c_[rng.random((50000, 2)), np.zeros(50000)]
    patch = np.c_[0.3 * rng.random((37500, 2)), np.zeros(37500)]
    far = np.c_[rng.random((12500, 2)) * 3.0 + 0.3, np.full(12500, 0.0)]
    assert tight(uniform_sphere(50000)) and tight(plane)
    assert not tight(np.concatenate([patch, far]))
    kinect = DATA / "pcl_milk_cartoon_all_small_clorox.finite.xyz"
    if kinect.exists():
        assert not tight(np.loadtxt(kinect))


@pytest.mark.parametrize("k", [27, 30, 64, 100])
def test_counting_path_with_a_full_gather(sphere, device, k):
    """Balls of ~500 candidates (a cell 4x the median k-th distance on the 10x sphere): the
    counting path narrows to intervals of up to KNN_CAP = 64 candidates, exactly 64 for some
    points, whose gather must keep all 64 (the lanes after the last one once overwrote it,
    and those points got their (k+1)-th distance: 39-115 of 20000 points wrong)."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    pts = sphere[::2]
    ref = cKDTree(pts).query(pts, k)[0][:, -1]
    cloud = DeviceCloud(pts, 0.2353, device=device)
    fast = kth_squared(cloud, k)
    ok = np.isfinite(fast)
    assert ok.mean() > 0.95
    np.testing.assert_array_equal(fast, kth_squared(cloud, k, levels=1))
    np.testing.assert_allclose(np.sqrt(fast[ok]), ref[ok], rtol=4e-6)


@pytest.mark.parametrize("k", [5, 9, 30, 100, 128, 130])
def test_selection_with_equal_distances(device, k):
    """A lattice (every distance repeated 4 to 8 times) with each point twice: the kernel's
    selection among equal d^2 (its sub-bin rounds take more than one minimum), its counting
    path and a k-d tree give the same k-th distance. k = 128 and 130: either side of the
    bound of first_field's packed comparison (KNN_K <= 128; above it a loop)."""
    from scipy.spatial import cKDTree
    from clcurv.grid.cloud import DeviceCloud
    g = np.arange(40) * 0.25
    pts = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    pts = np.c_[pts, np.zeros(len(pts))]
    pts = np.concatenate([pts, pts])
    ref = cKDTree(pts).query(pts, k)[0][:, -1]
    cloud = DeviceCloud(pts, 1.5 * np.max(ref) + 0.01, device=device)
    fast = kth_squared(cloud, k)
    np.testing.assert_array_equal(fast, kth_squared(cloud, k, levels=1))
    assert np.isfinite(fast).all()
    np.testing.assert_allclose(np.sqrt(fast), ref, rtol=1e-6)


def test_rebinned_at_the_largest_radius(device):
    """A first cell far above every radius (collinear points: the surface guess is ~3x
    their k-NN radius): the operators' cloud is binned again at the largest radius, the
    per-point r^2 (made on the device, knn_radius.cl:ball_r2) are the radii's squares
    widened by the grid's round-off and MARGIN in its sorted order, and every ball holds its
    k points."""
    import pyopencl as cl
    from clcurv.ops.knn_radius import MARGIN, ROUND_OFF
    x = np.random.default_rng(3).permutation(np.linspace(0.0, 1.0, 3001))
    pts = np.c_[x, 0.5 * x, np.zeros_like(x)]          # (in random order)
    got = knn_radii(pts, 5, device=device)
    assert len(got.levels) == 2 and got.levels[1] < got.levels[0] / 2
    np.testing.assert_allclose(got.radius, ref_knn_radii(pts, 5), rtol=4e-6)
    n = len(pts)
    host = np.empty(n, got.cloud.dtype)
    cl.enqueue_copy(got.cloud.device.queue, host, got.r2_sorted)
    r2 = np.empty(n)
    r2[got.cloud.grid.order] = host
    d2 = got.radius ** 2
    assert (r2 >= d2).all()
    slack = ROUND_OFF * np.finfo(np.float32).eps * got.levels[0]     # the last level's cell
    # float32: sqrt, add, square and widen, each rounded
    np.testing.assert_allclose(r2, (got.radius + slack) ** 2 * (1 + MARGIN), rtol=4e-7)
    assert (clcurv.features(pts, k=5, features=["linearity"], device=device).count == 5).all()


def test_balls_hold_k_points(sphere, device):
    """The ball of each point at its own radius holds exactly k points (the margin of a few
    ulps adds only exact ties, absent here); the reference's closed balls of radius d_k agree,
    and so do the features."""
    f = clcurv.features(sphere, k=30, device=device)
    assert (f.count == 30).mean() > 0.999 and (f.count >= 30).all()
    ref = clcurv.features(sphere, k=30, backend="numpy")
    assert (ref.count == 30).all()
    np.testing.assert_allclose(f.radius, ref.radius, rtol=4e-6)
    same = f.count == ref.count
    np.testing.assert_allclose(f["planarity"][same], ref["planarity"][same], atol=2e-5)


def test_mls2_adapts_where_a_fixed_radius_fails(sphere, device):
    """MLS2 with k=30 (30 points in every ball) gives H within 3% of 1/R everywhere; a
    fixed radius picked for 30 neighbours at the dense pole, as good there, leaves more
    than 10% of the sparse cap NaN or more than 5% off (measured: 75%, most of them with
    fewer than 6 neighbours)."""
    res = clcurv.curvature(sphere, method="mls2", k=30, device=device)
    assert (res.status == OK).all()
    assert (res.count >= 30).all() and (res.count == 30).mean() > 0.999     # ties enter
    assert np.max(np.abs(res.mean - 1.0)) < 0.03
    assert res.radius.shape == (len(sphere),)
    z = sphere[:, 2]
    dense, sparse = z < -0.9, z > 0.9
    r_dense = float(np.median(res.radius[dense]))
    assert np.median(res.radius[sparse]) > 2.5 * r_dense        # ~sqrt(10) apart
    fixed = clcurv.curvature(sphere, r_dense, method="mls2", device=device)

    def failed(h):
        """NaN or more than 5% off."""
        with np.errstate(invalid="ignore"):
            return np.isnan(h) | (np.abs(h - 1) > 0.05)

    assert failed(fixed.mean[dense]).mean() < 0.01              # right for the dense pole
    assert failed(fixed.mean[sparse]).mean() > 0.10             # wrong for the sparse cap
    assert not failed(res.mean[sparse]).any()                   # where k=30 is right


def test_each_point_uses_its_own_radius(sphere, device):
    """The constants take each point's radius: MLS1 H = -4 <o - p, n> r(p)^-2 (host), 2dcov2
    and 3dcov k = 2 / r(p) sqrt(l) (kernel), 2dcov1's Theorem 1 inverted at r(p): all close
    to 1/R on the unit sphere, at 10x density contrast."""
    pts = sphere[::2]
    for method, tol in (("mls1", 0.05), ("2dcov1", 0.35), ("2dcov2", 0.2), ("3dcov", 0.2)):
        res = clcurv.curvature(pts, method=method, k=30, device=device)
        val = res.mean if method == "mls1" else 0.5 * (res.k1 + res.k2)
        assert abs(np.median(val) - 1.0) < tol, (method, np.median(val))
        if method in ("2dcov2", "3dcov"):
            # the kernel's r is the ball's, d_k widened by the grid's round-off (ROUND_OFF
            # eps of the largest cell: here up to ~1.5e-5 of the densest points' d_k)
            np.testing.assert_allclose(res.k1, 2 / res.radius * np.sqrt(res.eigenvalues[:, 0]),
                                       rtol=3e-5)
    mls1 = clcurv.curvature(pts, method="mls1", k=30, device=device)
    var = clcurv.curvature(pts, method="variation", k=30, device=device)
    assert np.array_equal(mls1.radius, var.radius)


def test_k_larger_than_n_and_bad_k(device):
    pts = clcurv.shapes.sphere(50, 1.0)["points"]
    with pytest.raises(ValueError, match="exceeds the number of points"):
        clcurv.curvature(pts, method="variation", k=51, device=device)
    with pytest.raises(ValueError, match="k must be"):
        clcurv.features(pts, k=0, device=device)
    with pytest.raises(ValueError, match="knn:K"):
        clcurv.features(pts, "knn:many", device=device)
    with pytest.raises(ValueError, match="not both"):
        clcurv.curvature(pts, 0.1, method="variation", k=5, device=device)
    with pytest.raises(ValueError, match="not both"):
        clcurv.curvature(pts, [0.1, 0.2], method="variation", k=5, device=device)
    with pytest.raises(ValueError, match="density"):
        clcurv.curvature(pts, method="variation", k=5, weights="density", device=device)
    # k = N: every ball is the whole cloud
    whole = clcurv.features(pts, k=50, device=device)
    assert (whole.count == 50).all()


def test_duplicates_and_isolated_points(device):
    """k coincident points: radius 0, a ball of the coincident points, status 2 (NaN). An
    isolated point (its k-th neighbour farther than 4x the 90th percentile of the k-NN
    radii): radius NaN, status 1, and the other results do not change (but for a point whose
    ball gains or loses a tie within the margins of d_k on the other grid)."""
    base = clcurv.shapes.sphere(5000, 1.0, seed=3)["points"]
    dup = np.vstack([base, np.repeat(base[:1], 12, axis=0)])     # 13 copies of point 0
    f = clcurv.features(dup, k=10, device=device)
    copies = np.r_[0, np.arange(5000, 5012)]
    assert (f.radius[copies] == 0).all() and (f.status[copies] == DEGENERATE).all()
    assert (f.count[copies] == 13).all() and np.isnan(f["planarity"][copies]).all()
    far = np.vstack([base, [[500.0, 0, 0]]])
    with_far = clcurv.curvature(far, method="variation", k=10, device=device)
    alone = clcurv.curvature(base, method="variation", k=10, device=device)
    assert with_far.status[-1] == TOO_FEW and np.isnan(with_far.radius[-1])
    assert np.isnan(with_far.variation[-1])
    np.testing.assert_allclose(with_far.radius[:-1], alone.radius, rtol=1e-6)
    same = with_far.count[:-1] == alone.count
    assert same.mean() > 0.998
    np.testing.assert_allclose(with_far.variation[:-1][same], alone.variation[same],
                               rtol=1e-4, atol=1e-7)


def test_levels_kept_per_lane():
    """knn_levels: the fewest levels for which the expected share of points whose lane holds
    more of their k nearest than it keeps (Poisson, mean k / VW) is at most OVERFLOW_RATE;
    at k = 30 the fastest measured, 8 at VW 8 and 6 at VW 16 (kernels/knn_radius.cl), within
    4 .. 15 (a lane's count per bin fits a nibble), and growing with k."""
    from math import exp, factorial
    from clcurv.ops.knn_radius import OVERFLOW_RATE, knn_levels
    assert knn_levels(30, 8) == 8 and knn_levels(30, 16) == 6
    for vw in (2, 4, 8, 16):
        got = [knn_levels(k, vw) for k in range(1, 257)]
        assert min(got) >= 4 and max(got) <= 15
        assert all(a <= b for a, b in zip(got, got[1:]))
        for k, lv in zip(range(1, 257), got):
            mu = k / vw
            tail = lambda L: 1 - sum(exp(-mu) * mu ** i / factorial(i) for i in range(L + 1))
            if lv < 15:
                assert vw * tail(lv) <= OVERFLOW_RATE + 1e-12
            if lv > 4:
                assert vw * tail(lv - 1) > OVERFLOW_RATE


def test_isolation_cap_is_the_percentile_of_all_radii():
    """_isolation_cap: 4x numpy.quantile(radii, 0.9) of all n radii, from the resolved ones
    alone (the unresolved, +inf, are the largest), as soon as the percentile's two order
    statistics are resolved; None before. (The 90th percentile of the resolved radii alone
    is smaller whenever some are unresolved.)"""
    from clcurv.ops.knn_radius import ISOLATION, _isolation_cap
    rng = np.random.default_rng(1)
    for n in (1, 2, 5, 11, 1000, 100001):
        r = np.sort(rng.random(n).astype(np.float32))
        want = ISOLATION * np.quantile(r.astype(np.float64), 0.9)
        at = (n - 1) * 0.9
        need = int(np.floor(at)) + (2 if at % 1 else 1)
        for resolved in {n, need, need - 1, max(n - n // 20, need)} - {0}:
            d2 = (r.astype(np.float64) ** 2).astype(np.float32)
            d2[resolved:] = np.inf
            perm = rng.permutation(n)
            got = _isolation_cap(d2[perm], resolved)
            if resolved < need:
                assert got is None
            else:
                assert abs(got - want) <= 4e-7 * want, (n, resolved, got, want)


def test_none_isolated_implies_the_cap_holds_every_radius():
    """_none_isolated, the count that spares the percentile's partition: whenever it says
    so, the largest radius is within the exact cap (_isolation_cap); on the boundary (n >=
    10: a tenth of the radii at the largest, the rest just above or below it / ISOLATION) it
    says so exactly when the cap holds the largest radius with room; and it does not
    when one radius is far out."""
    from clcurv.ops.knn_radius import ISOLATION, _isolation_cap, _none_isolated
    rng = np.random.default_rng(2)
    said = 0
    for n in (1, 2, 10, 11, 1000, 30001):
        for spread in (1.5, 3.9, 4.1, 8.0, 100.0):
            r = rng.uniform(1.0, spread, n)
            d2 = (r * r).astype(np.float32)
            if _none_isolated(d2):
                said += 1
                assert np.sqrt(float(d2.max())) <= _isolation_cap(d2, n)
        top = 4.0
        for f in (1 - 1e-3, 1 + 1e-3) if n >= 10 else ():
            r = np.full(n, top / ISOLATION * f)
            r[:max(n // 10, 1)] = top
            d2 = (r * r).astype(np.float32)
            holds = np.sqrt(float(d2.max())) <= _isolation_cap(d2, n)
            assert _none_isolated(d2) == (holds and f > 1), (n, f)
        d2 = np.ones(n, np.float32)
        d2[0] = 1e4
        assert not _none_isolated(d2) or n < 10
    assert said >= 12


def _isolation_cases():
    """A ground plane whose density falls as a power of the distance from the origin (a long
    tail of k-NN radii, like the sparse edges of an aerial tile), and the Autzen tile."""
    rng = np.random.default_rng(0)
    rho = rng.pareto(1.2, 30000) + 1.0
    ang = rng.uniform(0, 2 * np.pi, 30000)
    yield np.c_[rho * np.cos(ang), rho * np.sin(ang), np.zeros(30000)]
    autzen = data_path("laspy_autzen_trim.laz")
    if autzen is not None:
        yield clcurv.io.read(autzen).points


def test_isolated_points_are_those_beyond_the_cap(device):
    """The documented rule, exactly: a point is isolated when its k-th neighbour is farther
    than 4x the 90th percentile of all the k-NN radii (k-d tree), and only then. (With the
    percentile of the radii resolved at the first binning that resolved 90%, 69-139 of the
    plane's 30000 points and 58 of Autzen's 110000 were isolated with a k-th neighbour
    within the cap.)"""
    from scipy.spatial import cKDTree
    for pts in _isolation_cases():
        got = knn_radii(pts, 30, device=device)
        d = cKDTree(pts).query(pts, 30)[0][:, -1]
        cap = 4 * np.quantile(d, 0.9)
        near = np.abs(d - cap) <= 1e-5 * cap                     # float32 radii at the cap
        assert (got.isolated == (d > cap))[~near].all()
        assert 0 < got.isolated.sum() < 0.05 * len(pts)
        # float32 offsets from the corners of cells up to the last level's: a few ulps of it
        np.testing.assert_allclose(got.radius[~got.isolated], d[~got.isolated], rtol=4e-6,
                                   atol=2.0 ** -21 * max(got.levels))


@pytest.mark.parametrize("dense, warned", [(0.1, False), (0.01, True)])
def test_balls_hold_k_points_where_the_radius_varies_100x(device, dense, warned):
    """A sparse blob (sigma 1) beside a dense one (sigma 0.1 or 0.01): k-NN radii 15x and
    150x apart on one grid whose cell the sparse points set. Every ball still holds at
    least k points (the radius widened by the grid's float round-off: before, 15 and 3114
    dense balls held k - 1 or k - 2), ties within that round-off enter too, the values
    match the float64 reference where the counts do, and the 150x case (round-off over
    1e-3 of the smallest radii) warns."""
    import warnings
    k = 10
    rng = np.random.default_rng(3)
    pts = np.vstack([rng.normal(0, 1.0, (3000, 3)),
                     rng.normal(0, dense, (10000, 3)) + [0, 5, 0]])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f = clcurv.features(pts, k=k, features=["planarity"], device=device)
    ref = clcurv.features(pts, k=k, features=["planarity"], backend="numpy")
    live = np.isfinite(f.radius)
    assert live.mean() > 0.99
    assert (f.count[live] >= k).all()
    assert (f.count[live] == k).mean() > (0.99 if not warned else 0.9)
    np.testing.assert_allclose(f.radius[live], ref.radius[live], rtol=2e-4)
    same = live & (f.count == ref.count)
    np.testing.assert_allclose(f["planarity"][same], ref["planarity"][same], atol=2e-4)
    msgs = [str(w.message) for w in caught if "round-off" in str(w.message)]
    assert bool(msgs) == warned, msgs


def test_k_below_three_warns_and_bool_k_is_refused(device):
    """k = 1 or 2: every ball holds k points, fewer than a covariance needs; features and
    curvature say so (all NaN, status 1), naming k. k=True is not k = 1: TypeError."""
    pts = clcurv.shapes.sphere(2000, 1.0, seed=2)["points"]
    for call in (lambda: clcurv.features(pts, k=2, device=device),
                 lambda: clcurv.curvature(pts, method="variation", k=2, device=device)):
        with pytest.warns(RuntimeWarning, match=r"k = 2\).*k must be at least 3"):
            res = call()
        assert (res.status == TOO_FEW).all()
    for bad in (True, np.bool_(True)):
        with pytest.raises(TypeError, match="k must be an integer"):
            clcurv.features(pts, k=bad, device=device)
        with pytest.raises(TypeError, match="k must be an integer"):
            clcurv.curvature(pts, method="variation", k=bad, device=device)


def test_a_far_point_does_not_coarsen_the_first_cell(device):
    """One far point beside a small cloud: the first cell comes from the extents of the
    middle 98% of the points, not the bounding box (which made the cell as large as the
    outlier's distance: every radius of a 0.15-wide cloud was 1.1 instead of ~0.014 with a
    point at 1e7, status 0). At 1e3 the far point is isolated and every other radius is the
    k-d tree's; at 1e7 the grid cannot span the cloud: ExtentError, as with a fixed
    radius."""
    from clcurv.grid.binning import ExtentError
    from scipy.spatial import cKDTree
    pts = clcurv.shapes.sphere(400, 0.075, seed=4)["points"]
    for far, fits in ((1e3, True), (1e7, False)):
        q = pts.copy()
        q[7] = far
        if not fits:
            with pytest.raises(ExtentError):
                clcurv.features(q, k=10, device=device)
            continue
        f = clcurv.features(q, k=10, features=["planarity"], device=device)
        truth = cKDTree(q).query(q, 10)[0][:, -1]
        keep = np.arange(len(q)) != 7
        assert f.status[7] == TOO_FEW and np.isnan(f.radius[7])
        np.testing.assert_allclose(f.radius[keep], truth[keep], rtol=1e-6)
        assert (f.status[keep] == OK).all()


def test_orientation_graph_walks_each_points_own_ball(sphere, device):
    """With a k-NN radius of K points the orientation graph (k < K nearest) walks each
    point's own ball (rows beyond it skipped) instead of the grid's largest radius: with
    every normal valid, the same lists and weights bit for bit."""
    from clcurv.orient.graph import knn_graph
    got = knn_radii(sphere, 30, device=device)
    normals = sphere / np.linalg.norm(sphere, axis=1)[:, None]
    r = got.cloud.cell
    a = knn_graph(got.cloud, r, normals, 10)
    b = knn_graph(got.cloud, r, normals, 10, point_r2=got.r2_sorted)
    np.testing.assert_array_equal(a.neighbors(), b.neighbors())
    np.testing.assert_array_equal(a.weights(), b.weights())


def test_pruned_rows_change_no_bit_with_per_point_radii(device, monkeypatch):
    """The walks of a k-NN radius skip the rows beyond each point's own ball (ROW_PRUNE):
    the same outputs bit for bit as walking every row of the largest radius's cells, on a
    cloud whose radii vary 10x."""
    import importlib
    pts = sphere_10x(20000, seed=5)
    calls = (lambda: clcurv.features(pts, k=20, features="all", device=device),
             lambda: clcurv.curvature(pts, method="mls2", k=20, orient=None, device=device),
             lambda: clcurv.curvature(pts, method="2dcov1", k=20, device=device))
    pruned = [c() for c in calls]
    # the operators' driver and the features' run (which imports it from the driver)
    for module in ("clcurv.ops.driver", "clcurv.ops.features"):
        monkeypatch.setattr(importlib.import_module(module), "row_prune",
                            lambda cloud, r, per_point=False: 0)
    for a, c in zip(pruned, calls):
        b = c()
        arrays = (a.values, b.values) if hasattr(a, "values") else (a.arrays(), b.arrays())
        for key, v in arrays[0].items():
            assert np.array_equal(v, arrays[1][key], equal_nan=True), key
        assert np.array_equal(a.count, b.count)


def test_normals_with_a_knn_radius(sphere, device):
    """clcurv.normals(k=30) (or radius="knn:30"): each point's PCA normal of its 30 nearest
    points (the point itself the first), as a float64 k-d tree PCA gives it; outward on the
    closed 10x density sphere (MST orientation); the variation pass's normals at k=30 up to
    sign and round-off; an isolated point NaN; k with a radius, or with density weights,
    refused."""
    from scipy.spatial import cKDTree
    pts = sphere[::2]
    n = clcurv.normals(pts, k=30, device=device)
    np.testing.assert_array_equal(n, clcurv.normals(pts, "knn:30", device=device))
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", n, radial).min() > 0.99       # outward, ~r/2R at most off
    sample = np.random.default_rng(5).choice(len(pts), 300, replace=False)
    _, nb = cKDTree(pts).query(pts[sample], 30)
    for s, idx in zip(sample, nb):
        q = pts[idx] - pts[idx].mean(axis=0)
        ref = np.linalg.eigh(q.T @ q)[1][:, 0]
        assert abs(n[s] @ ref) > 1 - 1e-5, s                    # float32 offsets, cell-relative
    var = clcurv.curvature(pts, method="variation", k=30, device=device)
    assert np.abs(np.einsum("ij,ij->i", n, var.normals)).min() > 1 - 1e-5
    base = clcurv.shapes.sphere(5000, 1.0, seed=3)["points"]
    far = clcurv.normals(np.vstack([base, [[500.0, 0, 0]]]), k=10, device=device)
    assert np.isnan(far[-1]).all() and np.isfinite(far[:-1]).all()
    with pytest.raises(ValueError, match="not both"):
        clcurv.normals(base, 0.1, k=5, device=device)
    with pytest.raises(ValueError, match="density"):
        clcurv.normals(base, k=5, weights="density", device=device)
