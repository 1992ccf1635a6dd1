"""Unit tests of the tiled engine's parts (issue 48, item 4), each against an independent
computation (NumPy by brute force, or values worked out by hand): the buckets and the split
into tile files (clcurv.tiles.buckets), the id windows and the merge (clcurv.tiles.results), the
planning (clcurv.tiles.planning: densest, plan_tiles), the orientation across tiles
(clcurv.tiles.orient: reconcile, flip_mask, flip_fields), the scale space's state
(clcurv.tiles.scale: State, init_state, the gather by state) and the Dask plugin and
retries (clcurv.tiles.workers). No OpenCL device is needed here."""
import os
import threading

import numpy as np
import pytest

import clcurv
from clcurv.tiles import (workers as cluster, results as tile_results, orient as tiled_orient,
                          scale as tiled_scale, planning as tiling)
from clcurv.tiles.buckets import READ_CHUNK, Buckets, bucket_grid
from clcurv.grid.binning import Frame
from clcurv.io import stream
from clcurv.orient.orientation import MIN_COMPONENT
from clcurv.tiles.results import Windows, partition, tile_file, to_windows, window_points
from clcurv.tiles.planning import Tiling, TilingError
from clcurv.tiles.workspace import CorruptWorkspace, save_sealed

CELL = 0.5                  # a power of two: (x - o) / CELL is exact, cell edges are exact


# --------------------------------------------------------------------------- helpers


def _cloud(n=6000, seed=11):
    """Points on a 1/64 grid over 37.3 x 23.1 (x, y), with points exactly on cell and
    tile edges (multiples of CELL from the corner), duplicates, and a few outside the
    bucket grid of :func:`_buckets` (clamped into its edge buckets); normals too."""
    rng = np.random.default_rng(seed)
    p = np.round(rng.uniform([0, 0, -1], [37.3, 23.1, 1], (n, 3)) * 64) / 64
    k = rng.integers(0, 60, size=(300, 2)) * CELL              # on cell (and tile) edges
    p[:100, 0] = k[:100, 0]
    p[100:200, 1] = k[100:200, 1]
    p[200:300, :2] = k[200:300]
    p[300:400] = p[rng.integers(400, n, 100)]                  # duplicates
    p[400:410, :2] = [[-3.5, 4], [41.0, 2], [5, -2.25], [5, 27.5], [-1, -1],
                      [44.0, 30.0], [37.3, 23.1], [0, 0], [-0.5, 23.1], [37.3, -0.5]]
    p = p[rng.permutation(n)]
    nrm = rng.normal(size=(n, 3))
    return p, nrm / np.linalg.norm(nrm, axis=1)[:, None]


def _buckets(folder, pts, nrm=None, origin=(0.0, 0.0), side=5.0, shape=(8, 5),
             chunks=(0, 1000, 1001, 2500, 4096)):
    """Buckets of a grid of ``side`` from ``origin``, filled in chunks of uneven sizes
    (starting at the ids ``chunks``): as pass (1) fills them."""
    folder.mkdir()
    b = Buckets(folder, origin, side, shape, nrm is not None)
    cuts = list(chunks) + [len(pts)]
    for a, e in zip(cuts[:-1], cuts[1:]):
        b.add(a, pts[a:e], None if nrm is None else nrm[a:e])
    return b


def _cells(pts, frame):
    """The x-y cells of ``pts`` in ``frame`` by plain division (cells of CELL: exact)."""
    return np.floor((pts[:, :2] - np.asarray(frame.origin[:2])) / frame.cell).astype(np.int64)


def _reach(c, tl):
    """{tile id: (ids of the points in its cells or halo, which of them it owns)} by brute
    force over all the tiles of ``tl``: tile (tx, ty) reads the cells
    [tx s - h, (tx + 1) s + h) x [ty s - h, (ty + 1) s + h) and owns [tx s, (tx + 1) s) x
    [ty s, (ty + 1) s)."""
    s, h = tl.size, tl.halo
    nx, ny, _ = tl.frame.dims
    ntx, nty = -(-nx // s), -(-ny // s)
    out = {}
    for tx in range(ntx):
        for ty in range(nty):
            inx = (c[:, 0] >= tx * s - h) & (c[:, 0] < (tx + 1) * s + h)
            iny = (c[:, 1] >= ty * s - h) & (c[:, 1] < (ty + 1) * s + h)
            ids = np.flatnonzero(inx & iny)
            if len(ids):
                own = (c[ids, 0] // s == tx) & (c[ids, 1] // s == ty)
                out[tx + ntx * ty] = (ids, own)
    return out


# --------------------------------------------------------------------------- buckets


def test_buckets_file_every_point_once_in_its_clamped_cell(tmp_path):
    """Buckets.add: each point in the bucket floor((x, y) - origin) / side (clamped into the
    grid: points outside it land in an edge bucket), once, in id order, with its position
    and normal bit for bit; counts, bounds and sums are those of the points."""
    pts, nrm = _cloud()
    b = _buckets(tmp_path / "b", pts, nrm)
    ij = np.floor(pts[:, :2] / 5.0).astype(np.int64)
    ij[:, 0] = np.clip(ij[:, 0], 0, 7)
    ij[:, 1] = np.clip(ij[:, 1], 0, 4)
    want = np.zeros((8, 5), np.int64)
    np.add.at(want, (ij[:, 0], ij[:, 1]), 1)
    assert np.array_equal(b.counts, want)
    assert np.array_equal(b.lo, pts.min(axis=0)) and np.array_equal(b.hi, pts.max(axis=0))
    assert b.normals_finite
    assert list(b.nonempty()) == [tuple(map(int, x)) for x in np.argwhere(want > 0)]
    for i in range(8):
        for j in range(5):
            rec = b.read(i, j)              # checked against the written sums
            ids = np.flatnonzero((ij[:, 0] == i) & (ij[:, 1] == j))
            assert np.array_equal(rec["id"], ids), (i, j)       # in id order
            assert np.array_equal(rec["p"], pts[ids])
            assert np.array_equal(rec["n"], nrm[ids])
            blocks = list(b.blocks(i, j, block=97)) if want[i, j] else []
            if blocks:
                assert np.array_equal(np.concatenate([r for r, _ in blocks]), rec)
    # the state round trip keeps everything a worker needs
    back = Buckets.from_state(b.folder, b.state())
    assert np.array_equal(back.counts, b.counts) and back.crc.sums == b.crc.sums
    assert np.array_equal(back.read(0, 0), b.read(0, 0))
    # a NaN normal is remembered (the file's normals are then not used)
    bad = nrm.copy()
    bad[17, 1] = np.nan
    assert not _buckets(tmp_path / "nan", pts, bad).normals_finite


def test_a_bucket_changed_on_disk_is_corrupt(tmp_path):
    pts, _ = _cloud(2000)
    b = _buckets(tmp_path / "b", pts, chunks=(0, 700))
    i, j = next(b.nonempty())
    path = b.path(i, j)
    data = bytearray(path.read_bytes())
    data[12] ^= 1                                   # one bit of a coordinate
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptWorkspace, match="CRC"):
        b.read(i, j)
    with pytest.raises(CorruptWorkspace, match="CRC-32 differs"):
        list(b.blocks(i, j))
    path.write_bytes(bytes(data[:-b.dtype.itemsize]))                # a record lost
    with pytest.raises(CorruptWorkspace, match="records where"):
        b.read(i, j)
    path.unlink()
    with pytest.raises(CorruptWorkspace, match="missing"):
        list(b.blocks(i, j))


@pytest.mark.parametrize("size, halo", [(4, 1), (3, 2), (2, 2), (7, 1), (200, 1)])
def test_split_puts_every_point_in_its_owner_and_the_halos_that_reach_it(tmp_path, size,
                                                                        halo):
    """Buckets.split: each point is in its owner tile's file exactly once with own = 1,
    and in the file of exactly those other tiles whose reach (cells and halo) holds it,
    with own = 0; no other file is written; the returned sums check every file; and
    Buckets.gather (the other way a tile finds its points) finds the same points."""
    pts, nrm = _cloud()
    b = _buckets(tmp_path / "b", pts, nrm)
    frame = Frame.covering(b.lo, b.hi, CELL)
    tl = Tiling(frame, size, halo)
    sums = b.split(tl, tmp_path / "tiles_in")
    truth = _reach(_cells(pts, frame), tl)
    assert sorted(map(int, sums)) == sorted(truth) == tl.occupied(sums)
    assert sorted(int(p.stem) for p in (tmp_path / "tiles_in" / "p0").iterdir()) == \
        sorted(truth)
    owners = []
    for k, (t, (ids, own)) in enumerate(truth.items()):
        rec = b.read_tile(tmp_path / "tiles_in", t, expect=sums[str(t)])
        assert np.array_equal(rec["id"], ids), t             # each once, in id order
        assert np.array_equal(rec["own"].astype(bool), own), t
        assert np.array_equal(rec["p"], pts[ids]) and np.array_equal(rec["n"], nrm[ids])
        owners.append(rec["id"][rec["own"] == 1])
        if k % max(1, len(truth) // 40) == 0:               # about 40 tiles: its cost
            assert np.array_equal(b.gather(tl, t)["id"], ids), t
    owned = np.concatenate(owners)
    assert np.array_equal(np.sort(owned), np.arange(len(pts)))       # one owner each
    # a tile file that does not match its sums is corrupt; an absent one is empty
    t = next(iter(truth))
    with pytest.raises(CorruptWorkspace):
        b.read_tile(tmp_path / "tiles_in", t, expect={"p0": [sums[str(t)]["p0"][0], 0]})
    assert sums[str(t)]["p0"][2] == int(truth[t][1].sum())          # its points owned
    assert len(b.read_tile(tmp_path / "tiles_in", 10 ** 9)) == 0


def test_overlapping_names_the_buckets_that_may_hold_a_box(tmp_path):
    """Buckets.overlapping(lo, hi): every non-empty bucket holding a point of the box, by
    brute force over the points, is named (and only non-empty ones)."""
    pts, _ = _cloud()
    b = _buckets(tmp_path / "b", pts)
    rng = np.random.default_rng(2)
    ij = np.floor(pts[:, :2] / 5.0).astype(np.int64)
    ij = np.clip(ij, 0, [7, 4])
    for _ in range(40):
        lo = rng.uniform([-5, -5], [40, 25])
        hi = lo + rng.uniform(0.1, 20, 2)
        inside = np.all((pts[:, :2] >= lo) & (pts[:, :2] < hi), axis=1)
        need = {tuple(map(int, x)) for x in ij[inside]}
        named = set(b.overlapping(lo, hi))
        assert need <= named, (lo, hi)
        assert all(b.counts[i, j] > 0 for i, j in named)


# --------------------------------------------------------------------------- windows


def test_window_points_fit_the_window_bytes():
    """A power of two, at most WINDOW, the largest whose records fit WINDOW_BYTES (at least
    4096 however wide the records)."""
    for width in (1, 3, 20, 100, 1000, 30_000):
        dt = np.dtype([("id", "<i8"), ("f", "<f8", (width,))])
        w = window_points(dt)
        assert w & (w - 1) == 0 and 4096 <= w <= tile_results.WINDOW
        assert w * dt.itemsize <= tile_results.WINDOW_BYTES or w == 4096
        assert w == tile_results.WINDOW or 2 * w * dt.itemsize > tile_results.WINDOW_BYTES


def _windows(folder, n, seed=0, drop=(), extra=()):
    """Windows of n ids (4096 a window), their records appended in shuffled chunks;
    ``drop`` ids left out, ``extra`` ids written twice."""
    dt = np.dtype([("id", "<i8"), ("v", "<f8"), ("w", "<f4", (2,))])
    win = Windows(folder, n, dt)
    assert win.size == 4096
    folder.mkdir()
    ids = np.setdiff1d(np.arange(n), drop)
    ids = np.concatenate([ids, np.asarray(extra, np.int64)])
    rng = np.random.default_rng(seed)
    ids = ids[rng.permutation(len(ids))]
    rec = np.empty(len(ids), dt)
    rec["id"], rec["v"] = ids, ids * 3.5 + 1
    rec["w"] = np.stack([ids, -ids], axis=1)
    for part in np.array_split(rec, 7):
        to_windows(part, win.path, win.size)
    return win


def test_windows_rows_are_the_ids_in_order_across_windows(tmp_path, monkeypatch):
    """Windows.rows(a, b): the records of ids a..b-1 in order, whatever windows they span
    (a window of 4096 here), and none for a >= b; the transform acts on a copy."""
    monkeypatch.setattr(tile_results, "WINDOW", 1 << 12)
    n = 10_000
    win = _windows(tmp_path / "w", n)
    assert win.count == 3
    cases = [(0, 0), (0, 1), (4095, 4097), (0, n), (4096, 8192), (8191, n), (9999, n),
             (5000, 4000), (12, 4096), (4096, 4097), (100, 9000)]
    rng = np.random.default_rng(1)
    cases += [tuple(sorted(rng.integers(0, n + 1, 2))) for _ in range(20)]
    for a, e in cases:
        rows = win.rows(a, e)
        ids = np.arange(a, max(a, e))
        assert np.array_equal(rows["id"], ids), (a, e)
        assert np.array_equal(rows["v"], ids * 3.5 + 1)
        assert np.array_equal(rows["w"], np.stack([ids, -ids], axis=1).astype(np.float32))
    win.transform = lambda r: (r.__setitem__("v", -r["v"]), r)[1]
    assert np.array_equal(win.rows(4000, 4200)["v"], -(np.arange(4000, 4200) * 3.5 + 1))
    assert np.array_equal(win.window(0)["v"], np.arange(4096) * 3.5 + 1)   # untouched


@pytest.mark.parametrize("fault, words", [
    (dict(drop=[5000]), "1 missing, 0 more than once, 0 out of range"),
    (dict(extra=[4096]), "0 missing, 1 more than once, 0 out of range"),
    (dict(drop=[0, 1], extra=[3, 3]), "2 missing, 1 more than once, 0 out of range")])
def test_a_window_without_each_id_exactly_once_is_corrupt(tmp_path, monkeypatch, fault,
                                                          words):
    monkeypatch.setattr(tile_results, "WINDOW", 1 << 12)
    win = _windows(tmp_path / "w", 10_000, **fault)
    w = (list(fault.get("drop", [])) + list(fault.get("extra", [])))[0] // 4096
    with pytest.raises(CorruptWorkspace, match=words):
        win.rows(0, 10_000)
    with pytest.raises(CorruptWorkspace):
        win.window(w)
    # an id of another window in a window's file
    good = _windows(tmp_path / "g", 10_000)
    rec = np.fromfile(good.path(2), good.dtype)[:1]
    with open(good.path(0), "ab") as f:
        rec.tofile(f)
    with pytest.raises(CorruptWorkspace, match="1 out of range"):
        good.rows(0, 10)


SPECS = [("mean_curvature", None, np.float64), ("normals", 3, np.float64),
         ("status", None, np.uint8)]


def _tile_results(ws, n, tiles=4, seed=3, mst=False):
    """Tile result files of ``n`` points owned by ``tiles`` tiles at random (ids in
    tile order), as compute_tile writes them; the records by id."""
    (ws / "tiles").mkdir(parents=True)
    dt = tile_results.tile_dtype(SPECS, mst)
    rng = np.random.default_rng(seed)
    owner = rng.integers(0, tiles, n)
    allrec = np.zeros(n, dt)
    allrec["id"] = np.arange(n)
    allrec["mean_curvature"] = rng.normal(size=n)
    allrec["normals"] = rng.normal(size=(n, 3))
    allrec["status"] = rng.integers(0, 4, n)
    halos = {}
    if mst:
        allrec["node"] = (owner.astype(np.int64) << 32) | rng.integers(0, 3, n)
        allrec["nl"] = rng.normal(size=(n, 3))
        allrec["pd"] = rng.normal(size=n)
    for t in range(tiles):
        save_sealed(tile_file(ws, t), allrec[owner == t])
        if mst:
            sel = np.flatnonzero(rng.random(n) < 0.05)
            h = np.zeros(len(sel), tiled_orient.HALO_DTYPE)
            h["id"], h["node"] = sel, (t << 32) | 7
            h["nl"] = rng.normal(size=(len(sel), 3))
            halos[t] = h
            save_sealed(tile_file(ws, t).with_suffix(".halo.npy"), h)
    return allrec, owner, halos


@pytest.mark.parametrize("mst", [False, True])
def test_partition_regroups_the_tiles_by_id_windows(tmp_path, monkeypatch, mst):
    """partition: every tile's records land in their id's window (rows 0..n-1 are the
    records by id), the status counts are summed, and (MST) the halo records go to their
    windows' halo files."""
    monkeypatch.setattr(tile_results, "WINDOW", 1 << 12)
    n = 9000
    allrec, _, halos = _tile_results(tmp_path, n, mst=mst)
    win = partition(tmp_path, n, range(4), SPECS, mst)
    assert np.array_equal(win.rows(0, n), allrec)
    assert win.status.tolist() == np.bincount(allrec["status"], minlength=4).tolist()
    if mst:
        halo = np.concatenate(list(halos.values()))
        got = np.concatenate([np.fromfile(win.halo_path(w), tiled_orient.HALO_DTYPE)
                              for w in range(win.count) if win.halo_path(w).exists()])
        key = lambda h: np.lexsort((h["node"], h["id"]))               # noqa: E731
        assert np.array_equal(got[key(got)], halo[key(halo)])
        for w in range(win.count):
            if win.halo_path(w).exists():
                h = np.fromfile(win.halo_path(w), tiled_orient.HALO_DTYPE)
                assert np.all(h["id"] // win.size == w)


def test_partition_with_a_missing_id_or_tile_is_corrupt(tmp_path, monkeypatch):
    """A tile result without one of its points: partition merges, but reading the window
    that lacks it raises CorruptWorkspace (never a partial output); a tile file absent or
    changed on disk raises at once."""
    monkeypatch.setattr(tile_results, "WINDOW", 1 << 12)
    n = 9000
    allrec, owner, _ = _tile_results(tmp_path / "a", n)
    t = int(owner[6000])
    mine = allrec[owner == t]
    save_sealed(tile_file(tmp_path / "a", t), mine[mine["id"] != 6000])
    win = partition(tmp_path / "a", n, range(4), SPECS)
    assert np.array_equal(win.rows(0, 4096), allrec[:4096])          # other windows fine
    with pytest.raises(CorruptWorkspace, match="1 missing"):
        win.rows(0, n)
    _tile_results(tmp_path / "b", n)
    tile_file(tmp_path / "b", 2).unlink()
    with pytest.raises(CorruptWorkspace, match="missing"):
        partition(tmp_path / "b", n, range(4), SPECS)
    _tile_results(tmp_path / "c", n)
    path = tile_file(tmp_path / "c", 1)
    data = bytearray(path.read_bytes())
    data[200] ^= 4
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptWorkspace, match="CRC-32"):
        partition(tmp_path / "c", n, range(4), SPECS)


# --------------------------------------------------------------------------- planning


def _source_buckets(folder, pts, budget):
    """The buckets of pass (1) for an NPY file of ``pts`` and this budget (the grid of
    :func:`bucket_grid`, as clcurv.tiles.engine._prepare builds it)."""
    folder.mkdir()
    np.save(folder / "c.npy", pts)
    src = stream.open_source(folder / "c.npy")
    origin, side, shape = bucket_grid(src, budget // tiling.TILE_BYTES_PER_POINT)
    (folder / "b").mkdir()
    b = Buckets(folder / "b", origin, side, shape, False)
    for start, xyz, nrm in src.chunks(READ_CHUNK):
        b.add(start, xyz, nrm)
    return b


def _largest_tile(pts, tl):
    """The most points any tile of ``tl`` reads with its halo, by brute force: every point
    counted in each tile (tx, ty) with tx s - h <= cx < (tx + 1) s + h (and y alike)."""
    c = np.floor((pts[:, :2] - np.asarray(tl.frame.origin[:2])) / tl.frame.cell
                 ).astype(np.int64)
    s, h = tl.size, tl.halo
    nx, ny, _ = tl.frame.dims
    ntx, nty = -(-nx // s), -(-ny // s)
    keys = []
    for dx in range(-(h // s) - 1, h // s + 2):
        for dy in range(-(h // s) - 1, h // s + 2):
            tx, ty = c[:, 0] // s + dx, c[:, 1] // s + dy
            ok = ((tx >= 0) & (tx < ntx) & (ty >= 0) & (ty < nty)
                  & (tx * s - h <= c[:, 0]) & (c[:, 0] < (tx + 1) * s + h)
                  & (ty * s - h <= c[:, 1]) & (c[:, 1] < (ty + 1) * s + h))
            keys.append((tx + ntx * ty)[ok])
    return int(np.unique(np.concatenate(keys), return_counts=True)[1].max())


def _plan_cloud(kind, n=20_000):
    """The clouds of the planning tests: ordinary ones, and clustered ones (seeded where
    the planning fails; see REFUSED and OVER)."""
    rng = np.random.default_rng({"aerial": 1, "uniform": 2, "torus": 3, "clusters, refused": 0,
                                 "clusters, over": 3}[kind])
    if kind == "aerial":
        return clcurv.shapes.aerial_scene(n, extent=(120.0, 90.0), seed=1)["points"]
    if kind == "uniform":
        return np.column_stack([rng.uniform(0, 150, (n, 2)), rng.normal(size=n)])
    if kind == "torus":
        return clcurv.shapes.torus(n, 20.0, 7.0, seed=5)["points"]
    # 12 blobs (sigma 3 m) over 200 m: buildings, trees, a town among fields
    centres = rng.uniform(10, 190, (12, 2))
    xy = centres[rng.integers(0, 12, n)] + rng.normal(size=(n, 2)) * 3.0
    return np.column_stack([xy, rng.normal(size=n)])


@pytest.mark.parametrize("kind, points, halo", [
    ("aerial", 3000, 1), ("aerial", 6000, 2), ("uniform", 3000, 2), ("uniform", 6000, 1),
    ("torus", 3000, 1), ("torus", 5000, 2),
    # clustered clouds: a corner bucket holding a blob (the bucket estimate refused a
    # budget that fits), blobs the buckets' uniform spread underestimated (11% over)
    ("clusters, refused", 4000, 1), ("clusters, over", 4000, 1)])
def test_plan_tiles_estimate_bounds_the_largest_tile_within_the_budget(tmp_path, kind, points,
                                                                      halo):
    """plan_tiles from a budget of ``points`` points a tile: the largest tile's true count
    (points with their halo, by brute force) is at most the budget's, and densest's
    estimate for the chosen tiling is at least that true count."""
    budget = points * tiling.TILE_BYTES_PER_POINT
    pts = _plan_cloud(kind)
    b = _source_buckets(tmp_path / "p", pts, budget)
    tl = tiling.plan_tiles(b, 1.0, halo, budget)
    most = _largest_tile(pts, tl)
    est = tiling.densest(b, tl)
    if est is None:                         # buckets too coarse: the occupancy decides
        est = tiling.occupancy(b, tl.frame).densest(tl)
    assert tl.halo == halo and tl.size >= halo
    assert most <= points, f"the largest tile holds {most} points, the budget {points}"
    assert est >= most, f"densest estimates {est} points where a tile holds {most}"


@pytest.mark.parametrize("kind", ["aerial", "clusters, over"])
def test_occupancy_of_single_cells_is_exact(tmp_path, kind):
    """The occupancy in blocks of one cell counts exactly: its densest is the brute-force
    largest tile for every tile size, and occupied_tiles are exactly the owners."""
    pts = _plan_cloud(kind, 8000)
    b = _source_buckets(tmp_path / "p", pts, 2000 * tiling.TILE_BYTES_PER_POINT)
    frame = tiling.covering(b, 1.0)
    occ = tiling.occupancy(b, frame)
    assert occ.g == 1 and occ.count.sum() == len(pts)
    for size, halo in ((1, 1), (3, 2), (7, 1), (16, 2), (10 ** 6, 1)):
        tl = Tiling(frame, min(size, max(frame.dims[:2])), halo)
        assert occ.densest(tl) == _largest_tile(pts, tl), (size, halo)
        c = _cells(pts, frame) // tl.size
        owners = np.unique(c[:, 0] + tl.shape[0] * c[:, 1])
        assert np.array_equal(tiling.occupied_tiles(b, tl), owners)


def test_a_given_tile_size_is_whole_cells_and_at_least_the_halo(tmp_path):
    pts = _plan_cloud("uniform", 4000)
    b = _source_buckets(tmp_path / "p", pts, 64 << 20)
    for tile, cells in ((8.0, 8), (8.99, 8), (2.0, 2), (1e300, None)):
        tl = tiling.plan_tiles(b, 1.0, 2, 64 << 20, tile)
        assert tl.size == (cells if cells is not None else max(tl.frame.dims[:2]))
        assert tl.frame.cell == 1.0 and tl.frame.origin == tuple(map(float, b.lo))
    with pytest.raises(TilingError, match="smaller than the halo"):
        tiling.plan_tiles(b, 1.0, 2, 64 << 20, 1.9)
    with pytest.raises(TilingError, match="too small for one tile"):
        tiling.plan_tiles(b, 1.0, 1, tiling.TILE_BYTES_PER_POINT)    # one point a tile


# --------------------------------------------------------------------------- orientation


def _sphere(n, centre, seed):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return u + np.asarray(centre, float), u


def _node(t, label):
    return (t << 32) | label


A, B, C = _node(0, 0), _node(1, 0), _node(2, 5)      # one sphere cut in three tiles
D, E = _node(3, 1), _node(4, 2)                      # another, in two
F = _node(5, 0)                                      # a group smaller than MIN_COMPONENT
ORIGIN = np.array([-2.0, -2.0, -2.0])


def _components():
    """Points, their stored normals (outward times the node's stored sign) and nodes: A and
    C outward, B inward; D and E both inward (the whole second sphere); F two points."""
    p1, out1 = _sphere(3000, (0, 0, 0), 1)
    sector = np.digitize(np.arctan2(p1[:, 1], p1[:, 0]), [-1.0, 1.0])
    node1 = np.array([A, B, C])[sector]
    sign1 = np.array([1.0, -1.0, 1.0])[sector]
    p2, out2 = _sphere(1000, (5, 0, 0), 2)
    node2 = np.where(p2[:, 2] > 0, D, E)
    p3 = np.array([[0.0, 3.0, 0.0], [0.0, 3.1, 0.1]])
    n3 = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    assert MIN_COMPONENT > len(p3)
    pts = np.concatenate([p1, p2, p3])
    outward = np.concatenate([out1, out2, n3])
    nl = np.concatenate([out1 * sign1[:, None], -out2, n3]).astype(np.float32)
    node = np.concatenate([node1, node2, [F, F]])
    return pts, outward, nl, node


VOTES = {(A, B): -300, (B, C): -250,
         (A, C): -3,                  # a weak vote against the strong ones: outvoted
         (D, E): 80,
         (C, D): 0,                   # no vote: the spheres stay two components
         (A, _node(99, 0)): 500}      # a node no tile reported: ignored


def test_reconcile_flips_the_nodes_of_hand_made_votes():
    """reconcile: the strongest votes first (the weak contradiction of A and C is outvoted),
    each component turned outward by its own vote (the inward sphere D-E flipped whole),
    the small group named, the centroid the mean of all points from the origin."""
    pts, _, nl, node = _components()
    sums = [tiled_orient.node_sums(pts[node >> 32 == t], nl[node >> 32 == t],
                                   node[node >> 32 == t], ORIGIN) for t in range(6)]
    assert sum(len(s) for s in sums) == 6
    flips, centroid, small = tiled_orient.reconcile(sums, VOTES)
    assert {k: v for k, v in flips.items() if k != F} == {A: False, B: True, C: False,
                                                         D: True, E: True}
    assert small == {F}
    assert np.allclose(centroid, (pts - ORIGIN).mean(axis=0), rtol=0, atol=1e-12)
    # the same nodes, the votes in another order and the tiles' sums in another order
    rev = dict(reversed(list(VOTES.items())))
    assert tiled_orient.reconcile(sums[::-1], rev)[0] == flips
    # the first sphere stored outward everywhere (its unit normals are its points): the
    # votes agree and nothing flips
    first = node >> 32 < 3
    out, _, _ = tiled_orient.reconcile([tiled_orient.node_sums(
        pts[first], pts[first].astype(np.float32), node[first], ORIGIN)],
        {(A, B): 10, (B, C): 10})
    assert out == {A: False, B: False, C: False}


def test_flip_mask_turns_every_point_outward_and_small_groups_from_the_centroid():
    """flip_mask with reconcile's flips: every point of the spheres faces out after the
    flip; the small group's points face away from the centroid of all points (as
    clcurv.orient.orientation does in memory); points without a node are never flipped."""
    pts, outward, nl, node = _components()
    sums = [tiled_orient.node_sums(pts, nl, node, ORIGIN)]
    flips, centroid, small = tiled_orient.reconcile(sums, VOTES)
    rec = np.zeros(len(pts) + 1, tiled_orient.NODE_FIELDS)
    rec["node"][:-1], rec["node"][-1] = node, -1
    rec["nl"][:-1], rec["nl"][-1] = nl, (0, 0, -1)
    rec["pd"][:-1] = np.einsum("ij,ij->i", nl.astype(np.float64), pts - ORIGIN)
    mask = tiled_orient.flip_mask(rec, flips, centroid, small)
    final = np.where(mask[:-1, None], -nl, nl).astype(np.float64)
    sphere = node != F
    assert np.all(np.einsum("ij,ij->i", final[sphere], outward[sphere]) > 0)
    away = np.einsum("ij,ij->i", final[~sphere], pts[~sphere] - ORIGIN - centroid)
    assert np.all(away >= 0) and mask[:-1][~sphere].tolist() == [True, False]
    assert not mask[-1]
    assert not tiled_orient.flip_mask(rec[:0], flips, centroid, small).any()


def test_flip_fields_negates_the_signed_fields_only():
    """A flip negates the normals and H; for MLS2 (k1, k2) -> (-k2, -k1) with dir1 and
    dir2 swapped; K, the status and the unflipped rows are unchanged."""
    names = ["mean_curvature", "gaussian_curvature", "k1", "k2", "status"]
    dirs = [f"dir{i}_{c}" for i in (1, 2) for c in "xyz"]
    dt = np.dtype([("id", "<i8"), ("normals", "<f8", (3,))]
                  + [(n, "<f8") for n in names + dirs])
    rec = np.zeros(3, dt)
    rec["normals"] = [[0, 0, 1], [0, 1, 0], [1, 0, 0]]
    rec["mean_curvature"], rec["gaussian_curvature"] = [1, 2, 3], [4, 5, 6]
    rec["k1"], rec["k2"], rec["status"] = [7, 8, 9], [-1, -2, -3], [0, 1, 2]
    for i, d in enumerate(dirs):
        rec[d] = np.arange(3) + 10 * (i + 1)
    mask = np.array([True, False, True])
    for method in ("mls2", "mls1"):
        got = tiled_orient.flip_fields(rec.copy(), mask, method)
        want = rec.copy()
        want["normals"][[0, 2]] *= -1
        want["mean_curvature"][[0, 2]] = [-1, -3]
        if method == "mls2":
            want["k1"][[0, 2]], want["k2"][[0, 2]] = [1, 3], [-7, -9]
            for c in "xyz":
                want[f"dir1_{c}"][[0, 2]] = rec[f"dir2_{c}"][[0, 2]]
                want[f"dir2_{c}"][[0, 2]] = rec[f"dir1_{c}"][[0, 2]]
        assert got.tobytes() == want.tobytes(), method
    assert tiled_orient.flip_fields(rec.copy(), np.zeros(3, bool), "mls2").tobytes() \
        == rec.tobytes()


# --------------------------------------------------------------------------- scale space


def test_state_join_and_key():
    """State.join: each record with its state row, its bucket and its row number; the rows
    must be in step (RuntimeError). State.key: the binned position 'pb', or the smoothed
    one p + d (d in the device's precision, added in float64)."""
    real = "<f4"
    st_dt = tiled_scale.state_dtype(np.dtype(real))
    rec_dt = np.dtype([("id", "<i8"), ("p", "<f8", (3,))])
    rng = np.random.default_rng(0)
    rec = np.zeros(5, rec_dt)
    rec["id"], rec["p"] = [3, 9, 12, 40, 41], rng.normal(size=(5, 3)) * 1e5
    st = np.zeros(5, st_dt)
    st["pb"] = rec["p"] + 0.25
    st["it"] = rng.normal(size=(5, 5))
    st["d"] = rng.normal(size=(5, 3)) * 0.01
    s = tiled_scale.State("unused", real, "pb", 0.3)
    j = s.join(rec, st, 7, 100)
    assert j.dtype == s.joined_dtype(rec_dt)
    assert j.dtype.names == ("id", "p", "b", "row", "pb", "it", "d")
    for name in rec_dt.names:
        assert np.array_equal(j[name], rec[name])
    for name in st_dt.names:
        assert np.array_equal(j[name], st[name])
    assert j["b"].tolist() == [7] * 5 and j["row"].tolist() == [100, 101, 102, 103, 104]
    assert np.array_equal(s.key(j), st["pb"])
    smooth = tiled_scale.State("unused", real, "smoothed", 0.3)
    want = rec["p"] + st["d"].astype(np.float64)
    assert smooth.key(j).dtype == np.float64 and np.array_equal(smooth.key(j), want)
    with pytest.raises(RuntimeError, match="out of step"):
        s.join(rec, st[:4], 7, 0)


@pytest.mark.parametrize("real", ["<f4", "<f8"])
def test_the_state_places_the_points_by_their_binned_positions(tmp_path, real):
    """init_state: a row per point of each bucket, in its order (pb = p, iterate and d
    zero). With the binned positions moved (by less than the margin), gather and split
    place each point by pb: a tile reads exactly the points whose pb lies in its cells or
    halo, joined with their own state rows."""
    pts, _ = _cloud(4000)
    b = _buckets(tmp_path / "b", pts, chunks=(0, 1000, 1001, 2500))
    folder = tmp_path / "state"
    tiled_scale.init_state(b, folder, real)
    dt = tiled_scale.state_dtype(np.dtype(real))
    for i in range(8):
        for j in range(5):
            path = folder / f"s{i}_{j}.bin"
            assert path.exists() == bool(b.counts[i, j])
            if path.exists():
                st = np.fromfile(path, dt)
                assert np.array_equal(st["pb"], b.read(i, j)["p"])
                assert not st["it"].any() and not st["d"].any()
    # move the binned positions: pb = p + a shift of up to 1.5 cells, per point
    rng = np.random.default_rng(4)
    shift = rng.uniform(-0.75, 0.75, (len(pts), 3))
    pb = pts + shift
    for i, j in b.nonempty():
        path = folder / f"s{i}_{j}.bin"
        st = np.fromfile(path, dt)
        ids = b.read(i, j)["id"]
        st["pb"], st["d"] = pb[ids], shift[ids] * 0.5
        st.tofile(path)
    state = tiled_scale.State(str(folder), real, "pb", 0.75)
    frame = Frame.covering(pb.min(axis=0), pb.max(axis=0), CELL)
    tl = Tiling(frame, 6, 1)
    truth = _reach(_cells(pb, frame), tl)
    sums = b.split(tl, tmp_path / "split", state=state)
    assert sorted(map(int, sums)) == sorted(truth)
    for k, (t, (ids, own)) in enumerate(truth.items()):
        rec = b.read_tile(tmp_path / "split", t, state=state, expect=sums[str(t)])
        assert np.array_equal(rec["id"], ids) and np.array_equal(rec["own"] == 1, own)
        assert np.array_equal(rec["pb"], pb[ids]) and np.array_equal(rec["p"], pts[ids])
        assert np.array_equal(rec["d"], (shift[ids] * 0.5).astype(real))
        # b and row name the bucket and the row the state came from
        for flat, row, i_ in zip(rec["b"][:5], rec["row"][:5], rec["id"][:5]):
            assert b.read(*divmod(int(flat), 5))["id"][row] == i_
        if k % 10 == 0:
            got = b.gather(tl, t, state=state)
            assert np.array_equal(got["id"], ids)
            assert np.array_equal(got["pb"], pb[ids])


# --------------------------------------------------------------------------- Dask


class _Worker:
    """What ClcurvWorker.setup reads of a Dask worker."""

    def __init__(self, address, peers):
        self.address, self._peers = address, peers

    def scheduler_info(self):
        return {"workers": {a: {} for a in self._peers}}


class _Dev:
    def __init__(self, index, kind, simulator=False):
        self.index, self.kind, self.simulator = index, kind, simulator


PEERS = ["tcp://10.0.0.1:4000", "tcp://10.0.0.1:3000", "tcp://10.0.0.2:3500",
         "tcp://10.0.0.1:5000"]


def _clean_env(monkeypatch, keep=None):
    """The thread variables unset for the test (and restored after it), but ``keep``."""
    for var in cluster.THREAD_VARIABLES:
        monkeypatch.setenv(var, "x")                 # restored (or unset) afterwards
        monkeypatch.delenv(var)
    for var, value in (keep or {}).items():
        monkeypatch.setenv(var, value)


def test_the_worker_plugin_caps_threads_and_picks_the_device(monkeypatch):
    """ClcurvWorker.setup: every thread variable not already set becomes the host's cores
    divided by the workers on that host (3 of the 4 here: 12 cores, 4 each); the device
    asked for is kept."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(cluster, "usable_cores", lambda: 12)
    _clean_env(monkeypatch, {"OMP_NUM_THREADS": "7"})
    w = _Worker("tcp://10.0.0.1:4000", PEERS)
    cluster.worker_plugin("1").setup(w)
    assert w.clcurv_device == "1"
    for var in cluster.THREAD_VARIABLES:
        assert os.environ[var] == ("7" if var == "OMP_NUM_THREADS" else "4"), var
    # one worker alone on its host: every core
    _clean_env(monkeypatch)
    w = _Worker("tcp://10.0.0.2:3500", PEERS)
    cluster.worker_plugin(None).setup(w)
    assert os.environ["POCL_MAX_PTHREAD_COUNT"] == "12"


@pytest.mark.parametrize("gpus, want", [(3, {3000: 10, 4000: 11, 5000: 12}),
                                        (1, {3000: None, 4000: None, 5000: None})])
def test_the_worker_plugin_spreads_the_workers_over_the_gpus(monkeypatch, gpus, want):
    """No device asked for: with several GPUs (a simulator is not one), the worker of rank
    k among its host's workers (by address) takes GPU k mod count; one GPU: the default."""
    pytest.importorskip("distributed")
    devs = [_Dev(0, "cpu"), _Dev(9, "gpu", simulator=True)] + \
        [_Dev(10 + g, "gpu") for g in range(gpus)]
    monkeypatch.setattr(cluster, "devices", lambda: devs)
    monkeypatch.setattr(cluster, "usable_cores", lambda: 2)
    _clean_env(monkeypatch)
    for port, index in want.items():
        w = _Worker(f"tcp://10.0.0.1:{port}", PEERS)
        cluster.worker_plugin(None).setup(w)
        assert w.clcurv_device == index, port


class _Task:
    def __init__(self, t):
        self.t = t


_CALLS = {}
_LOCK = threading.Lock()


def flaky_square(task):
    """Fails the first time it runs a task (in this process: an in-process cluster)."""
    with _LOCK:
        _CALLS[task.t] = _CALLS.get(task.t, 0) + 1
        first = _CALLS[task.t] == 1
    if first:
        raise RuntimeError(f"planted failure of tile {task.t}")
    return task.t, task.t ** 2


def test_map_tiles_retries_a_task_that_fails(monkeypatch):
    """cluster.map_tiles submits with retries=RETRIES: a task that raises once is run
    again, every result comes back once; with RETRIES = 0 the failure reaches the caller."""
    distributed = pytest.importorskip("distributed")
    _clean_env(monkeypatch, {v: "1" for v in cluster.THREAD_VARIABLES})   # setup's
    assert cluster.RETRIES >= 1
    lc = distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None)
    client = distributed.Client(lc)
    try:
        _CALLS.clear()
        got = list(cluster.map_tiles(flaky_square, [_Task(t) for t in range(12)],
                                     client=client))
        assert sorted(got) == [(t, t * t) for t in range(12)]
        assert _CALLS == {t: 2 for t in range(12)}
        _CALLS.clear()
        monkeypatch.setattr(cluster, "RETRIES", 0)
        with pytest.raises(RuntimeError, match="planted failure of tile"):
            list(cluster.map_tiles(flaky_square, [_Task(t) for t in range(3)],
                                   client=client))
    finally:
        client.close()
        lc.close()


def test_auto_runs_in_memory_whenever_the_cloud_fits_half_the_ram(monkeypatch):
    """memory='auto': a cloud whose in-memory estimate (550 bytes a point for MLS2, the
    largest; a LAS input's reading and writing at least 300 + 4 x its record length) fits
    half the available RAM runs in memory, however many points; tiles only beyond, planned
    with a budget of at most AUTO_CAP."""
    from clcurv.jobs.job import in_tiles
    monkeypatch.setattr(tiling, "available_memory", lambda: 8 << 30)
    assert tiling.fit_budget("auto") == 4 << 30
    assert tiling.budget_of("auto") == tiling.AUTO_CAP
    assert tiling.fit_budget("2GiB") == tiling.budget_of("2GiB") == 2 << 30
    assert not in_tiles(5_000_000, tiling.fit_budget("auto"))      # 3.0 GB: in memory
    assert in_tiles(8_000_000, tiling.fit_budget("auto"))          # 4.8 GB: tiles
    assert in_tiles(1000, tiling.fit_budget("auto"), forced=True)
    assert tiling.in_memory_bytes() == tiling.in_memory_bytes("mls2") == 550
    assert tiling.in_memory_bytes("variation") == 250
    assert tiling.in_memory_bytes("variation", record_length=34) == 436     # format 3
    assert tiling.in_memory_bytes("features", None, 16 * 16 + 64) == 410
    assert not in_tiles(12_000_000, tiling.fit_budget("auto"), method="variation")  # 3.0 GB


def test_a_tiled_summary_takes_exact_counts_and_a_systematic_sample(monkeypatch):
    """engine.tile_info / values_summary: the NaN counts and the mean neighbour count are
    exact, and the percentiles come from the ids that are multiples of n / SAMPLE_POINTS
    (whatever the tiles): with 10,000 of 100,000 points, p1 and p99 lie within a rank of
    0.5% of the whole cloud's (5 standard errors of a sample's rank) and the median within
    2% (4)."""
    from clcurv.tiles.engine import CurvatureParams, tile_info, values_summary
    from clcurv.tiles.results import tile_dtype
    from clcurv.tiles import engine
    monkeypatch.setattr(engine, "SAMPLE_POINTS", 10_000)
    rng = np.random.default_rng(7)
    n = 100_000
    specs = [("mean_curvature", None, np.float64), ("gaussian_curvature", None, np.float64),
             ("k1", None, np.float64), ("k2", None, np.float64),
             ("neighbours", None, np.int32), ("status", None, np.uint8)]
    rec = np.zeros(n, tile_dtype(specs))
    rec["id"] = np.arange(n)
    for k in ("mean_curvature", "gaussian_curvature", "k1", "k2"):
        rec[k] = rng.standard_cauchy(n)
    rec["mean_curvature"][rng.choice(n, 321, replace=False)] = np.nan
    rec["neighbours"] = rng.integers(5, 90, n)
    params = CurvatureParams("mls2", 1.0, "uniform", "up", None, None, None, None, "float",
                             False)
    owner = rng.integers(0, 5, n)                       # five tiles, ids interleaved
    infos = [tile_info(rec[owner == t], (0,), params, n) for t in range(5)]
    s = values_summary(infos, params)
    assert s["sample"] == 10_000
    assert s["neighbours"][0] == rec["neighbours"].mean()
    for k in ("mean_curvature", "k1"):
        q, nan = s["ranges"][k]
        v = rec[k][np.isfinite(rec[k])]
        assert nan == (321 if k == "mean_curvature" else 0)
        for got, p in zip(q, (1, 50, 99)):
            band = 2.0 if p == 50 else 0.5
            lo, hi = np.percentile(v, [max(p - band, 0), p + band])
            assert lo <= got <= hi, (k, p, got, lo, hi)


def test_buckets_filed_in_parts_read_as_one_writer_filed_them(tmp_path):
    """Buckets written by several part writers (pass (1) on the workers) and merged read
    back, bucket by bucket, the same records in the same order as one writer's, and split
    into the same tile inputs; their occupancies, each part's counted apart (at most
    ``limit`` blocks each) and merged, are the whole cloud's at the merged block size."""
    from clcurv.tiles.buckets import occupancy_part, OccupancyTask
    pts, nrm = _cloud()
    one = _buckets(tmp_path / "one", pts, nrm)
    cuts = [0, 1500, 1501, 4000, len(pts)]
    states = []
    for k, (a, e) in enumerate(zip(cuts[:-1], cuts[1:])):
        w = Buckets(tmp_path / "parts", one.origin, one.side, one.shape, True, part=k)
        for s in range(a, e, 700):
            w.add(s, pts[s:min(s + 700, e)], nrm[s:min(s + 700, e)])
        states.append(w.state())
    many = Buckets.merge(tmp_path / "parts", states[::-1])       # in any order
    assert many.parts == [0, 1, 2, 3]
    assert np.array_equal(many.counts, one.counts)
    assert np.array_equal(many.lo, one.lo) and np.array_equal(many.hi, one.hi)
    for i, j in one.nonempty():
        assert np.array_equal(many.read(i, j), one.read(i, j)), (i, j)
    frame = Frame.covering(one.lo, one.hi, CELL)
    tl = Tiling(frame, 5, 1)
    s1, s2 = one.split(tl, tmp_path / "t1"), many.split(tl, tmp_path / "t2")
    assert sorted(s1) == sorted(s2)
    for t in s1:
        assert np.array_equal(one.read_tile(tmp_path / "t1", t, expect=s1[t]),
                              many.read_tile(tmp_path / "t2", t, expect=s2[t]))
    whole = tiling.occupancy(one, frame, limit=None)
    for limit in (None, 300):
        parts = [occupancy_part(OccupancyTask(str(many.folder), k, many.state(), frame,
                                              limit)) for k in many.parts]
        merged = tiling.merge_occupancy(frame, parts, limit=None)
        ref = tiling.occupancy(one, frame, g=merged.g, limit=None)
        assert merged.count.sum() == whole.count.sum() == len(pts)
        assert np.array_equal(np.stack([merged.bx, merged.by, merged.count]),
                              np.stack([ref.bx, ref.by, ref.count])), limit
        assert (merged.g == 1) == (limit is None)
