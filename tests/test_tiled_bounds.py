"""Tiled runs stay bounded whatever the extent (issue 47, item 4): one far "no data" point
(0, 0, 0 beside a projected survey) makes the frame billions of tiles, but planning and the
per-tile loops cost O(points + occupied tiles), and the outcome is the in-memory run's: the
same output, or the same refusal word for word. Hangs are caught by an alarm, never by a
timing assertion. Item 5: a tile size that is not a finite number > 0 is refused clearly."""

import numpy as np
import pytest

import clcurv
from tests.hostile import deadline
from clcurv.tiles import planning as tiling
from clcurv.tiles.buckets import READ_CHUNK, Buckets, bucket_grid
from clcurv.grid.binning import ExtentError
from clcurv.io import stream
from clcurv.jobs.job import features_file
from clcurv.tiles.planning import TilingError

SURVEY = np.array([500000.0, 4000000.0, 100.0])       # a projected (UTM-like) survey


def _survey(n=4000, seed=1):
    s = clcurv.shapes.aerial_scene(n, extent=(30.0, 20.0), seed=seed)
    return s["points"] - s["points"].min(axis=0) + SURVEY


def _with(points, far, at=None):
    """``points`` with the point ``far`` inserted at index ``at`` (default: in the middle)."""
    at = len(points) // 2 if at is None else at
    return np.concatenate([points[:at], np.asarray([far], float), points[at:]])


@pytest.fixture(scope="module")
def far_cloud(tmp_path_factory):
    d = tmp_path_factory.mktemp("bounds")
    path = d / "far.npy"
    np.save(path, _with(_survey(), (0.0, 0.0, 0.0)))
    return d, path


def _buckets(path, folder, budget=512 << 20):
    src = stream.open_source(path)
    folder.mkdir()
    origin, side, shape = bucket_grid(src, budget // tiling.TILE_BYTES_PER_POINT)
    b = Buckets(folder, origin, side, shape, src.has_normals)
    for start, xyz, nrm in src.chunks(READ_CHUNK):
        b.add(start, xyz, nrm)
    return b


def _same_npz(a, b):
    a, b = np.load(a), np.load(b)
    assert sorted(a.files) == sorted(b.files)
    diff = [k for k in a.files if not np.array_equal(a[k], b[k], equal_nan=True)]
    assert diff == [], f"tiled and in-memory outputs differ in {diff}"


def _owners(points, tl):
    """The tiles of ``tl`` that own ``points`` and the most points a tile reads with its
    halo, by brute force over the points (the truth the planning must meet)."""
    c = tl.frame.cells_xy(points)
    ntx, _ = tl.shape
    own = np.unique(c[:, 0] // tl.size + ntx * (c[:, 1] // tl.size))
    most = max(int(tiling.within(c, tl.cells(int(t))).sum()) for t in own)
    return own, most


# --------------------------------------------------------------------------- planning


@pytest.mark.parametrize("budget, tile", [(2 << 20, None), (512 << 20, 8.0),
                                          (512 << 20, 1e300)])
def test_planning_a_far_point_costs_its_tiles_not_the_extent(far_cloud, tmp_path, budget,
                                                             tile):
    """The tiles of the frame number about 1e11 (tile 8) or 5e8 (from a 2 MiB budget); the
    plan, the occupied tiles and the split visit only the ~20 that hold points, exactly
    those that own points, and the budget's estimate is the true densest tile's."""
    _, path = far_cloud
    pts = np.load(path)
    with deadline(60):
        b = _buckets(path, tmp_path / "b", budget)
        tl = tiling.plan_tiles(b, 1.0, 1, budget, tile)
        occupied = tiling.occupied_tiles(b, tl)
        sums = b.split(tl, tmp_path / "tiles_in")
    own, most = _owners(pts, tl)
    if tile == 1e300:
        assert tl.count == 1                          # larger than the cloud: one tile
    else:
        assert tl.count > 10 ** 8                     # the frame: astronomically many tiles
    assert np.array_equal(occupied, own)
    assert set(own) <= set(tl.occupied(sums))         # split wrote every owner's file ...
    assert len(tl.occupied(sums)) <= 9 * len(own)     # ... and the halos' of neighbours only
    if tile is None:                                  # the budget holds for the true tiles
        assert most <= budget // tiling.TILE_BYTES_PER_POINT
        exact = tiling.occupancy(b, tl.frame)         # g = 1 cell: counts exact
        assert exact.g == 1
        assert exact.densest(tl) == most


@pytest.mark.parametrize("block", [1 << 18, 97])
def test_occupancy_coarsens_to_its_limit(far_cloud, tmp_path, monkeypatch, block):
    """Blocks of g cells double until at most ``limit`` are occupied (merged as they come
    when the points come in many small blocks): every point is still counted once, and
    the tiles it names hold every owner."""
    _, path = far_cloud
    pts = np.load(path)
    b = _buckets(path, tmp_path / "b")
    tl = tiling.plan_tiles(b, 1.0, 1, 512 << 20, 8.0)
    monkeypatch.setattr(tiling, "OCCUPANCY_MERGE", 8)
    occ = tiling.occupancy(b, tl.frame, limit=40, block=block)
    assert occ.g > 1 and len(occ.count) <= 40 and occ.count.sum() == len(pts)
    own, _ = _owners(pts, tl)
    assert set(own) <= set(occ.tiles(tl))
    assert occ.densest(tl) > 0
    exact = tiling.occupancy(b, tl.frame, g=tl.size, limit=None, block=block)
    assert np.array_equal(exact.tiles(tl), own)


def test_budget_estimate_unchanged_without_outliers(tmp_path):
    """On an ordinary cloud the buckets' estimate still decides (no extra pass) and gives a
    tile size whose densest tile fits the budget."""
    path = tmp_path / "plain.npy"
    pts = _survey(20_000)
    np.save(path, pts)
    budget = 4 << 20
    b = _buckets(path, tmp_path / "b", budget)
    tl = tiling.plan_tiles(b, 1.0, 1, budget)
    assert tiling.densest(b, tl) is not None          # the buckets were fine enough
    _, most = _owners(pts, tl)
    assert most <= budget // tiling.TILE_BYTES_PER_POINT


def test_order_statistics_equal_numpy(tmp_path, monkeypatch):
    """The exact median out of core (a few histogram passes, then a sort) is numpy's, with
    duplicates, a far point and few bins/sort room forcing many passes."""
    rng = np.random.default_rng(5)
    pts = np.round(rng.normal(size=(3001, 3)) * 50, 1) + SURVEY
    pts[::7] = pts[3]                                  # many duplicates
    pts = _with(pts, (-3.4e38, 0.0, 3.4e38))
    path = tmp_path / "p.npy"
    np.save(path, pts)
    b = _buckets(path, tmp_path / "b")
    monkeypatch.setattr(tiling, "SELECT_BINS", 8)
    monkeypatch.setattr(tiling, "SELECT_SORT", 5)
    n = len(pts)
    ranks = [0, 1, n // 2 - 1, n // 2, n - 1]
    assert np.array_equal(tiling._order_statistics(b, ranks), np.sort(pts, axis=0)[ranks].T)
    med, far, point = tiling._farthest_from_median(b)
    assert np.array_equal(med, np.median(pts, axis=0))
    assert far == np.argmax(np.max(np.abs(pts - med), axis=1)) == 3001 // 2
    assert np.array_equal(point, pts[far])


# --------------------------------------------------------------------------- same outcome


@pytest.mark.parametrize("far", [(1e7, 1e7, 1e7), (3.4e38, 3.4e38, 3.4e38)])
@pytest.mark.parametrize("scale_space", [0, 1])
def test_an_extent_too_large_is_refused_as_in_memory(tmp_path, far, scale_space):
    """A far point that no int64 grid key spans: the tiled run refuses with the in-memory
    run's ExtentError word for word (the farthest point from the median named by its index
    in the file), before any tile, the workspace removed."""
    path = tmp_path / "ext.npy"
    survey = _survey(2000)
    np.save(path, _with(survey, far))
    kw = dict(method="mls2", orient="up", scale_space=scale_space)
    with pytest.raises(ExtentError) as mem:
        clcurv.curvature_file(path, tmp_path / "mem.npz", 1.0, **kw)
    with deadline(60), pytest.raises(ExtentError) as tiles:
        clcurv.curvature_file(path, tmp_path / "tiles.npz", 1.0, tile=8.0, **kw)
    assert str(tiles.value) == str(mem.value)
    assert f"is #{len(survey) // 2} at" in str(mem.value)
    assert not (tmp_path / "tiles.npz").exists()
    assert [p.name for p in tmp_path.iterdir() if "clcurv" in p.name] == []


def test_a_tile_larger_than_the_cloud_is_one_tile(far_cloud, tmp_path):
    d, path = far_cloud
    mem = clcurv.curvature_file(path, tmp_path / "mem.npz", 1.0, method="mls2", orient="up")
    with deadline(60):
        one = clcurv.curvature_file(path, tmp_path / "one.npz", 1.0, method="mls2",
                                    orient="up", tile=1e300)
    assert not mem["tiled"] and one["tiled"] and one["tiles"] == 1
    _same_npz(tmp_path / "mem.npz", tmp_path / "one.npz")


def test_mst_orientation_of_a_far_point_in_tiles(tmp_path):
    """The default orientation of a signed method on NPY input is MST propagation, whose
    nodes are numbered (t << 32) | component: tile ids t beyond 2^31 (a survey beside a
    "no data" point at the origin, in 8 m tiles) must not overflow them (negative: the
    normals of whole tiles voided). MST in tiles agrees with the in-memory MST up to the
    sign of components: the unsigned fields and the status are the in-memory run's."""
    survey = _survey()

    def ids(pts):                   # the ids of the survey's 8 m tiles, the origin at 0
        tl = tiling.Tiling(clcurv.grid.binning.Frame.covering(np.zeros(3), pts.max(axis=0), 1.0),
                           8, 1)
        c = tl.frame.cells_xy(pts) // 8
        return c[:, 0] + tl.shape[0] * c[:, 1], tl.shape[0]
    t, ntx = ids(survey)
    # north by whole tile rows, until the ids have bit 31 set (t << 32 is then negative)
    survey[:, 1] += 8.0 * ((((3 << 30) - int(t.min()) % 2 ** 32) % 2 ** 32) // ntx)
    t, _ = ids(survey)
    assert (t > 2 ** 31).all() and ((t >> 31) & 1).all()
    path = tmp_path / "far.npy"
    np.save(path, _with(survey, (0.0, 0.0, 0.0)))
    clcurv.curvature_file(path, tmp_path / "mem.npz", 1.0, method="mls2")
    with deadline(30):
        s = clcurv.curvature_file(path, tmp_path / "tiles.npz", 1.0, method="mls2", tile=8.0)
    a, b = np.load(tmp_path / "mem.npz"), np.load(tmp_path / "tiles.npz")
    assert s["tiles"] > 1
    for name in ("status", "neighbours", "gaussian_curvature"):
        assert np.array_equal(a[name], b[name], equal_nan=True), name


@pytest.mark.parametrize("factor", [0, 10 ** 9], ids=["split", "gather"])
def test_scale_space_steps_split_or_gather_alike(tmp_path, monkeypatch, factor):
    """A step's tiles read their points from files split once (buckets far larger than the
    tiles: one far point stretches the bucket grid, and every tile would read it whole) or
    gather them from the buckets around them: the in-memory scale space either way."""
    from clcurv.tiles import scale as tiled_scale
    monkeypatch.setattr(tiled_scale, "GATHER_FACTOR", factor)
    path = tmp_path / "s.npy"
    np.save(path, _survey(3000))
    kw = dict(method="mls1", orient="up", scale_space=2)
    clcurv.curvature_file(path, tmp_path / "mem.npz", 1.0, **kw)
    used = []
    split = clcurv.tiles.buckets.Buckets.split
    monkeypatch.setattr(clcurv.tiles.buckets.Buckets, "split",
                        lambda self, *a, **k: used.append(1) or split(self, *a, **k))
    with deadline(60):
        clcurv.curvature_file(path, tmp_path / "tiles.npz", 1.0, tile=6.0, **kw)
    assert len(used) == (3 if factor == 0 else 1)        # 2 steps and the operator's pass
    _same_npz(tmp_path / "mem.npz", tmp_path / "tiles.npz")


@pytest.mark.parametrize("kind", ["mls2", "scale_space", "features"])
def test_a_far_point_runs_in_tiles_as_in_memory(far_cloud, tmp_path, kind):
    """A small survey and one "no data" point at (0, 0, 0), in 8 m tiles: the run finishes
    (an alarm, not a timing) and its output is the in-memory run's bit for bit."""
    _, path = far_cloud
    if kind == "features":
        run = lambda dst, **kw: features_file(path, dst, 1.0, **kw)         # noqa: E731
    else:
        kw = dict(method="mls2", orient="up", scale_space=int(kind == "scale_space"))
        run = lambda dst, **more: clcurv.curvature_file(path, dst, 1.0, **kw, **more)  # noqa
    mem = run(tmp_path / "mem.npz")
    with deadline(10):                        # ~1 s: the kernels are built above
        tiles = run(tmp_path / "tiles.npz", tile=8.0)
    assert not mem["tiled"] and tiles["tiled"]
    assert 1 < tiles["tiles"] < 100
    _same_npz(tmp_path / "mem.npz", tmp_path / "tiles.npz")


# --------------------------------------------------------------------------- tile sizes

BAD_TILES = [float("inf"), float("nan"), 0.0, -8.0, "abc", True, 1e400]


@pytest.mark.parametrize("tile", BAD_TILES, ids=repr)
def test_a_bad_tile_size_is_refused_by_the_api(far_cloud, tmp_path, tile):
    _, path = far_cloud
    msg = "tile size must be a finite number > 0"
    with pytest.raises(TilingError, match=msg):
        clcurv.curvature_file(path, tmp_path / "c.npz", 1.0, orient="up", tile=tile)
    with pytest.raises(TilingError, match=msg):
        features_file(path, tmp_path / "f.npz", 1.0, tile=tile)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["inf", "1e400", "nan", "0", "-1", "abc"])
@pytest.mark.parametrize("command", ["compute", "features"])
def test_a_bad_tile_size_is_refused_by_the_command(far_cloud, tmp_path, capsys, value,
                                                   command):
    """Exit 2 with the reason, before any point is read (was an OverflowError traceback or
    "cannot convert float NaN to integer")."""
    from clcurv.cli import main as cli
    _, path = far_cloud
    with pytest.raises(SystemExit) as done:
        cli.main([command, str(path), "-o", str(tmp_path / "o.npz"), "--radius", "1",
                  f"--tile-size={value}"])
    err = capsys.readouterr().err
    assert done.value.code == 2, err
    assert "argument --tile-size: the tile size must be a finite number > 0" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []
