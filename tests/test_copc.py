"""COPC input (issue 47, item 3): a ``.copc.laz`` file is read as the LAZ that it is, and
written as a plain LAZ/LAS (its COPC VLRs and EVLRs, which describe the octree of the input
file and which laspy cannot write, are left out), in memory, in tiles and by the command.

The COPC files are made here by copclib (PyPI ``copclib``, the ``test`` extra), the way a
COPC writer does: the points are split into the nodes of an octree (a sample of the cloud at
the root, the rest in the depth-1 and depth-2 cells), so the file holds them in octree
order, not in the order they were given. Each point carries its index in the given order
(``gps_time``), so the tests can tell one order from the other.

The reference is the same points in a plain LAZ written by laspy in the COPC file's order:
the outputs must be equal to it bit for bit (same input, same computation), in the COPC
file's order. Against the plain LAZ of the points in their given order (a different order
of computation), the values of each point must agree to 1e-4 (float32 sums in another
order), matched by the point's index.
"""
import os
import struct
from types import SimpleNamespace

import numpy as np
import pytest

import clcurv
from bench.harness import copc_config
from tests.hostile import assert_same_las, las_dims
from clcurv import io as cio
from clcurv.io import copc as ccopc
from clcurv.io import pieces, stream
from clcurv.io.common import CorruptFileError
from clcurv.tiles import engine, regions, writing

from hostile import run_cli

laspy = pytest.importorskip("laspy", reason="laspy not installed")
copc = pytest.importorskip("copclib", reason='copclib not installed (pip install -e ".[test]")')
if not laspy.LazBackend.detect_available():
    pytest.skip('no LAZ backend (pip install "laspy[lazrs]")', allow_module_level=True)

R = 1.0
SCALE = 2.0 ** -7                      # coordinates are exact binary fractions
N = 6000


def _scene(n=N, seed=5):
    """An aerial scene on the LAS grid of SCALE, with a class and an RGB colour per point."""
    s = clcurv.shapes.aerial_scene(n, extent=(31.3, 27.9), seed=seed)
    pts = np.round(s["points"] / SCALE) * SCALE
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 65536, size=(len(pts), 3))
    return pts, s["kind"], rgb


def write_copc(path, pts, kind, rgb=None, fmt=6, seed=0):
    """A COPC file of ``pts`` written by copclib; returns the indices of ``pts`` in the
    file's order (octree order: the root node first, then the depth-1 and depth-2 nodes).

    ``gps_time`` is the index of each point in ``pts``, ``classification`` its ``kind``,
    ``intensity`` the index modulo 65536 and, for point formats 7 and 8, ``rgb`` the colour.
    The header's min/max are the points'.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = float((hi - lo).max())
    cfg = copc_config(copc, fmt, (SCALE,) * 3, np.floor(lo), lo, hi, 32)
    writer = copc.FileWriter(str(path), cfg)
    header = writer.copc_config.las_header

    def node(idx):
        points = copc.Points(header)
        for i in idx:
            p = points.CreatePoint()
            p.gps_time = float(i)
            p.intensity = int(i) % 65536
            p.classification = int(kind[i])
            p.return_number, p.number_of_returns = 1, 1
            if fmt in (7, 8):
                p.red, p.green, p.blue = (int(c) for c in rgb[i])
            points.AddPoint(p)
        points.x, points.y, points.z = (list(pts[idx, k]) for k in range(3))
        return points

    order = []
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(pts))
    root, rest = perm[:len(pts) // 8], perm[len(pts) // 8:]
    writer.AddNode(copc.VoxelKey(0, 0, 0, 0), node(root))
    order.append(root)
    depth1, depth2 = rest[:len(rest) // 3], rest[len(rest) // 3:]
    for depth, idx in ((1, depth1), (2, depth2)):
        cell = np.clip(((pts[idx] - lo) / (span / 2 ** depth)).astype(int), 0, 2 ** depth - 1)
        keys = cell[:, 0] * 16 + cell[:, 1] * 4 + cell[:, 2]
        for key in np.unique(keys):
            sel = idx[keys == key]
            writer.AddNode(copc.VoxelKey(depth, *map(int, cell[keys == key][0])), node(sel))
            order.append(sel)
    writer.Close()
    assert copc.FileReader(str(path)).ValidateSpatialBounds()   # a valid octree
    return np.concatenate(order)


def write_plain(path, src):
    """``src`` (a COPC file) as a plain LAZ/LAS written by laspy: the same header fields,
    records and order, without the COPC VLRs and EVLRs."""
    las = laspy.read(str(src))
    header = laspy.LasHeader(point_format=las.header.point_format.id, version="1.4")
    header.scales, header.offsets = las.header.scales, las.header.offsets
    out = laspy.LasData(header)
    out.points = las.points.copy()
    out.write(str(path))
    return path


def write_given_order(path, pts, kind, rgb, fmt):
    """The points in their given order (gps_time = index) as a plain LAZ."""
    header = laspy.LasHeader(point_format=fmt, version="1.4")
    header.scales, header.offsets = [SCALE] * 3, np.floor(pts.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.gps_time = np.arange(len(pts), dtype=float)
    las.intensity = np.arange(len(pts)) % 65536
    las.classification = kind
    las.return_number = las.number_of_returns = np.ones(len(pts), np.uint8)
    if fmt in (7, 8):
        las.red, las.green, las.blue = rgb.T
    las.write(str(path))
    return path


@pytest.fixture(scope="module", params=[6, 7])
def files(request, tmp_path_factory):
    """(folder, the COPC file, the same points as a plain LAZ in the COPC's order, in
    their given order, the given points, the COPC order) for point format 6 and 7."""
    fmt = request.param
    d = tmp_path_factory.mktemp(f"copc{fmt}")
    pts, kind, rgb = _scene(seed=fmt)
    src = d / "survey.copc.laz"
    order = write_copc(src, pts, kind, rgb, fmt=fmt, seed=fmt)
    plain = write_plain(d / "plain.laz", src)
    given = write_given_order(d / "given.laz", pts, kind, rgb, fmt)
    return d, src, plain, given, pts, order


_dims, assert_same = las_dims, assert_same_las


def assert_plain(path):
    """``path`` is a plain LAS/LAZ: no COPC VLR or EVLR, and laspy's COPC reader refuses it."""
    las = laspy.read(str(path))
    ids = [v.user_id for v in las.header.vlrs] + [v.user_id for v in las.header.evlrs or []]
    assert "copc" not in ids, ids
    with pytest.raises(Exception):
        laspy.CopcReader.open(str(path))


def test_the_copc_files_are_copc_in_octree_order(files):
    """The inputs are what the tests claim: COPC files (laspy's COPC reader opens them) whose
    points are not in the given order."""
    _, src, _, _, pts, order = files
    with laspy.CopcReader.open(str(src)) as r:
        assert r.header.point_count == len(pts)
    las = laspy.read(str(src))
    assert [v.user_id for v in las.header.vlrs][0] == "copc"
    assert np.array_equal(np.asarray(las.gps_time), order)
    assert not np.array_equal(order, np.arange(len(pts)))


def test_copc_is_read_as_the_laz_it_is_in_file_order(files):
    _, src, plain, _, pts, order = files
    a, b = cio.read(src), cio.read(plain)
    assert a.format == "laz" and len(a) == len(pts) and a.dropped == 0
    assert np.array_equal(a.points, pts[order])                  # the file's order
    assert np.array_equal(a.points, b.points)
    assert list(a.attributes) == list(b.attributes)
    for k in a.attributes:
        assert np.array_equal(a.attributes[k], b.attributes[k]), k


@pytest.mark.parametrize("ext", [".laz", ".las"])
def test_io_write_from_a_copc_like_is_a_plain_file(files, tmp_path, ext):
    """clcurv.io.write with like= a COPC Cloud: the header, records and other VLRs kept,
    the COPC ones left out; the points in the file's order."""
    _, src, _, _, _, _ = files
    cloud = cio.read(src)
    k = np.linspace(-1, 1, len(cloud))
    out = cio.write(tmp_path / f"o{ext}", cloud.points, {"k1": k}, like=cloud)
    assert_plain(out)
    back = cio.read(out)
    assert np.array_equal(back.points, cloud.points)
    assert np.array_equal(back.attributes["k1"], k.astype(np.float32))
    for name, a in cloud.attributes.items():
        assert np.array_equal(back.attributes[name], a), name
    las = laspy.read(str(out))
    assert las.header.point_format.id == cloud.header.point_format.id
    assert np.array_equal(las.header.scales, cloud.header.scales)
    assert np.array_equal(las.header.offsets, cloud.header.offsets)
    assert cloud.header.vlrs[0].user_id == "copc"                   # like= is not modified


@pytest.mark.parametrize("method,tile", [("mls1", None), ("mls1", 8.0), ("2dcov2", None),
                                         ("2dcov2", 8.0)])
def test_copc_runs_equal_the_plain_laz_runs(files, method, tile):
    """In memory and in tiles: the output of the COPC input equals the output of the same
    points in a plain LAZ (same order), bit for bit, and is a plain LAZ in the COPC's
    order."""
    d, src, plain, _, pts, order = files
    tag = f"{method}_{tile}"
    a, b = d / f"copc_{tag}.laz", d / f"plain_{tag}.laz"
    ra = clcurv.curvature_file(src, a, R, method=method, tile=tile, memory="64GiB")
    rb = clcurv.curvature_file(plain, b, R, method=method, tile=tile, memory="64GiB")
    assert ra["tiled"] == rb["tiled"] == (tile is not None)
    assert_plain(a)
    assert_same(a, b)
    las, dims = _dims(a)
    assert np.array_equal(np.column_stack([las.x, las.y, las.z]), pts[order])
    assert np.array_equal(dims["gps_time"], order)
    assert (dims["status"] == 0).mean() > 0.9


def test_tiled_copc_equals_in_memory_copc(files):
    d, src, _, _, _, _ = files
    a, b = d / "mem_t.laz", d / "til_t.laz"
    clcurv.curvature_file(src, a, R, method="mls1", memory="64GiB")
    clcurv.curvature_file(src, b, R, method="mls1", tile=6.0, memory="64GiB")
    assert_same(a, b)


def test_each_value_goes_to_its_point(files):
    """The COPC output against the points in their given order (another order of
    computation): each point's values agree to 1e-4, matched by its index (gps_time)."""
    d, src, _, given, pts, order = files
    a, b = d / "order_copc.laz", d / "order_given.laz"
    clcurv.curvature_file(src, a, R, method="mls1", fields=["mean_curvature", "status"],
                          memory="64GiB")
    clcurv.curvature_file(given, b, R, method="mls1", fields=["mean_curvature", "status"],
                          memory="64GiB")
    _, da = _dims(a)
    _, db = _dims(b)
    assert np.array_equal(db["gps_time"], np.arange(len(pts)))
    idx = da["gps_time"].astype(np.int64)
    assert np.array_equal(da["status"], db["status"][idx])
    h_a, h_b = da["mean_curvature"], db["mean_curvature"][idx]
    ok = np.isfinite(h_b)
    assert ok.mean() > 0.9 and np.array_equal(np.isfinite(h_a), ok)
    np.testing.assert_allclose(h_a[ok], h_b[ok], rtol=1e-4, atol=1e-4)
    # and the same comparison fails when the values are taken in the given order
    assert not np.allclose(da["mean_curvature"][ok], db["mean_curvature"][ok], atol=1e-4,
                           equal_nan=True)


@pytest.mark.parametrize("extra", [[], ["--tile-size", "8"]])
def test_the_command_on_copc(files, tmp_path, extra):
    _, src, plain, _, _, order = files
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    for inp, out in ((src, a), (plain, b)):
        p = run_cli("compute", inp, "-o", out, "--radius", "1", "--method", "mls1", "-q",
                    *extra, timeout=120)
        assert p.code == 0, p.stderr[-2000:]
        assert "Traceback" not in p.stderr
    assert_plain(a)
    assert_same(a, b)


def test_output_named_copc_laz_is_plain_laz(files, tmp_path):
    """clcurv writes no COPC: an output named .copc.laz is a plain LAZ (documented)."""
    _, src, plain, _, _, _ = files
    a = tmp_path / "out.copc.laz"
    clcurv.curvature_file(src, a, R, method="mls1", fields=["mean_curvature"], memory="64GiB")
    assert_plain(a)


def test_evlrs_that_can_be_written_are_kept_in_memory_and_in_tiles(tmp_path):
    """What is dropped is what laspy cannot write (COPC's); other VLRs and EVLRs of a LAS
    1.4 input are kept, in memory and in tiles alike."""
    pts, kind, _ = _scene(3000, seed=9)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [SCALE] * 3, np.floor(pts.min(axis=0))
    header.vlrs.append(laspy.VLR("clcurv_test", 7, "a VLR", b"vlr data"))
    header.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("clcurv_test", 8, "an EVLR", b"evlr data" * 100)])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.classification = kind
    src = tmp_path / "evlr.laz"
    las.write(str(src))
    assert len(laspy.read(str(src)).header.evlrs) == 1
    outs = []
    for tile in (None, 8.0):
        out = tmp_path / f"out_{tile}.laz"
        clcurv.curvature_file(src, out, R, method="mls1", fields=["mean_curvature"], tile=tile,
                              memory="64GiB")
        back = laspy.read(str(out))
        assert [(v.user_id, v.record_id, v.record_data) for v in back.header.evlrs] == \
            [("clcurv_test", 8, b"evlr data" * 100)], tile
        assert ("clcurv_test", 7) in [(v.user_id, v.record_id) for v in back.header.vlrs]
        outs.append(out)
    assert_same(*outs)


@pytest.mark.parametrize("tile", [None, 8.0])
def test_features_of_copc_equal_those_of_the_plain_laz(files, tile):
    """clcurv.features_file (covariance features), in memory and in tiles: the same rule."""
    d, src, plain, _, _, order = files
    a, b = d / f"feat_copc_{tile}.laz", d / f"feat_plain_{tile}.laz"
    clcurv.features_file(src, a, R, tile=tile, memory="64GiB")
    clcurv.features_file(plain, b, R, tile=tile, memory="64GiB")
    assert_plain(a)
    assert_same(a, b)
    assert np.array_equal(_dims(a)[1]["gps_time"], order)


def test_a_catalog_names_the_output_of_a_copc_file_laz(files, tmp_path):
    """A catalog's output of ``x.copc.laz`` is ``x.laz``: it is a plain LAZ, and PDAL and
    QGIS choose their COPC reader by the ``.copc.laz`` extension."""
    d, src, plain, _, _, _ = files
    far = laspy.read(str(plain))
    far.header.offsets = far.header.offsets + [1000.0, 0.0, 0.0]    # another tile, apart
    far.x = np.asarray(far.x) + 1000.0
    far.write(str(tmp_path / "far.laz"))
    folder = tmp_path / "out"
    folder.mkdir()
    clcurv.curvature_file([str(src), str(tmp_path / "far.laz")], folder, R, method="mls1")
    assert sorted(os.listdir(folder)) == ["far.laz", "index.vpc", "survey.laz"]
    assert_plain(folder / "survey.laz")
    ref = tmp_path / "ref.laz"
    clcurv.curvature_file(src, ref, R, method="mls1", tile=8.0)
    assert_same(folder / "survey.laz", ref)       # the far file: the same grid frame


# --------------------------------------------------------------------------- region reads
# A tiled run of one COPC file reads each tile's region through the octree
# (clcurv.tiles.regions, clcurv.io.copc): its output must equal, bit for bit, the in-memory
# output of the same points given as a plain LAZ in the COPC file's order.

def _inside(ref, box):
    (x0, y0), (x1, y1) = box
    return np.flatnonzero((ref[:, 0] >= x0) & (ref[:, 0] <= x1)
                          & (ref[:, 1] >= y0) & (ref[:, 1] <= y1))


@pytest.mark.parametrize("batch", [1 << 20, 700])
def test_the_hierarchy_and_regions_read_as_the_file(files, monkeypatch, batch):
    """The node table is the file's point order; a region is the points of its box
    (inclusive), with their global ids and the coordinates clcurv.io.read gives, bit for
    bit, decoded in batches of nodes or at once; a small box decodes a few nodes only."""
    _, src, _, _, pts, order = files
    monkeypatch.setattr(ccopc, "BATCH_POINTS", batch)
    index = ccopc.open_index(src)
    ref = cio.read(src).points
    nodes = index.nodes
    assert index.n == len(ref) == int(nodes["count"].sum()) == N
    assert len(nodes) > 10 and np.all(np.diff(nodes["offset"]) > 0)
    assert np.array_equal(nodes["first"], np.r_[0, np.cumsum(nodes["count"])[:-1]])
    assert np.array_equal(index.mins, ref.min(axis=0))
    assert np.array_equal(index.maxs, ref.max(axis=0))
    lo, hi = ref.min(axis=0), ref.max(axis=0)
    p, q = ref[17], ref[4000]                      # edges through points: inclusive
    boxes = [((lo[0] - 1, lo[1] - 1), (hi[0] + 1, hi[1] + 1)),
             ((min(p[0], q[0]), min(p[1], q[1])), (max(p[0], q[0]), max(p[1], q[1]))),
             ((lo[0] + 3.0, lo[1] + 2.5), (lo[0] + 9.25, lo[1] + 6.0))]
    for box in boxes:
        ids, xyz = index.read_region(box)
        want = _inside(ref, box)
        assert len(want) > 50
        assert np.array_equal(ids, want)
        assert np.array_equal(xyz, ref[want])
    assert {17, 4000} <= set(index.read_region(boxes[1])[0].tolist())
    assert len(index.select(boxes[2])) < len(nodes) // 2


def _no_bucket_pass(*args, **kwargs):
    raise AssertionError("a COPC input read by region makes no bucket")


def _no_client_merge(*args, **kwargs):
    raise AssertionError("a LAS/LAZ output of a region run is written in pieces on the "
                         "workers, not merged and written by the client")


def _count_joins(monkeypatch):
    """Spy on clcurv.io.pieces.assemble (the client's join of the workers' pieces): the
    list of the piece counts of its calls."""
    joins, assemble = [], pieces.assemble

    def spy(dst, header, parts, **kw):
        joins.append(len(parts))
        return assemble(dst, header, parts, **kw)
    monkeypatch.setattr(pieces, "assemble", spy)
    return joins


@pytest.mark.parametrize("method,tile,memory,workers,ext", [
    ("mls1", 6.0, "64GiB", None, ".laz"), ("2dcov2", 8.0, "64GiB", None, ".laz"),
    ("mls1", None, "3MiB", None, ".laz"), ("mls1", 6.0, "64GiB", 2, ".laz"),
    ("mls1", 6.0, "64GiB", 2, ".las")],
    ids=["mls1-tile6", "2dcov2-halo2", "mls1-budget", "mls1-2workers", "mls1-2workers-las"])
def test_region_tiles_equal_the_in_memory_plain_laz(files, tmp_path, monkeypatch, method,
                                                     tile, memory, workers, ext):
    """The output of a region run equals the in-memory output of the same points as a
    plain LAZ, and is byte for byte the in-memory output of the COPC file itself: written
    in pieces by the tile tasks' processes (the workers with ``workers``) and joined by
    the client (clcurv.io.pieces.assemble), which never merges nor writes the points."""
    _, src, plain, _, _, order = files
    monkeypatch.setattr(engine, "_prepare", _no_bucket_pass)
    monkeypatch.setattr(engine, "partition", _no_client_merge)
    monkeypatch.setattr(writing, "write_output", _no_client_merge)
    joins = _count_joins(monkeypatch)
    a, b, c = tmp_path / f"copc{ext}", tmp_path / "plain.laz", tmp_path / f"mem{ext}"
    said = []
    ra = clcurv.curvature_file(src, a, R, method=method, tile=tile, memory=memory,
                               workers=workers, out=said.append)
    rb = clcurv.curvature_file(plain, b, R, method=method, memory="64GiB")
    rc = clcurv.curvature_file(src, c, R, method=method, memory="64GiB")
    assert ra["tiled"] and ra.get("regions") and not rb["tiled"] and not rc["tiled"]
    assert ra["tiles"] >= 4 and ra["points"] == N
    assert "merging" not in ra["times"] and "writing" in ra["times"]
    assert joins == [len(writing.piece_windows(N, workers or 0))]   # whole chunks: 1
    assert any("read by region" in s for s in said), said
    assert_plain(a)
    assert_same(a, b)
    assert a.read_bytes() == c.read_bytes()          # the in-memory writer's file
    las, dims = _dims(a)
    assert np.array_equal(dims["gps_time"], order)
    assert ra["status"] == [int(np.count_nonzero(dims["status"] == k)) for k in range(4)]
    assert sorted(os.listdir(tmp_path)) == sorted([a.name, "plain.laz", c.name])  # no workspace


@pytest.mark.parametrize("workers", [None, 2])
def test_region_pieces_span_many_windows(tmp_path, monkeypatch, workers):
    """A COPC file of 110,000 points (bench.catalog.make_copc: an octree of levels 0-2
    whose coarse levels sample the whole scene) written in windows of 50,000 points: every
    tile owns points of several windows, each window's task gathers them from every tile
    that owns some, the client joins three pieces; byte for byte the in-memory output.
    (The pieces read the input's records from the middle of the COPC file: its chunks
    differ in size, where lazrs' own seek is wrong; clcurv.io.las.read_range.)"""
    from bench.catalog import make_copc
    src = tmp_path / "big.copc.laz"
    n = make_copc(src, 110_000, 1, extent=33.0, node_points=8000)
    monkeypatch.setattr(writing, "PIECE_POINTS", 50_000)
    monkeypatch.setattr(engine, "partition", _no_client_merge)
    monkeypatch.setattr(writing, "write_output", _no_client_merge)
    joins = _count_joins(monkeypatch)
    a, c = tmp_path / "copc.laz", tmp_path / "mem.laz"
    ra = clcurv.curvature_file(src, a, 0.6, method="mls1", tile=10.0, memory="64GiB",
                               workers=workers)
    clcurv.curvature_file(src, c, 0.6, method="mls1", memory="64GiB")
    assert ra.get("regions") and ra["tiles"] >= 9 and ra["points"] == n
    assert joins == [len(writing.piece_windows(n, workers or 0))] == [3]
    assert a.read_bytes() == c.read_bytes()


@pytest.mark.parametrize("ext", [".npz", ".ply"])
def test_region_run_to_npz_or_ply_is_merged_by_the_client(files, tmp_path, ext):
    """An NPZ or PLY output of a region run is merged and written by the client, as for
    any tiled input: the in-memory output of the COPC file, array for array."""
    _, src, _, _, _, _ = files
    a, c = tmp_path / f"copc{ext}", tmp_path / f"mem{ext}"
    ra = clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB")
    clcurv.curvature_file(src, c, R, method="mls1", memory="64GiB")
    assert ra.get("regions") and "merging" in ra["times"]
    ta, tc = cio.read(a), cio.read(c)
    assert np.array_equal(ta.points, tc.points)
    assert sorted(ta.attributes) == sorted(tc.attributes)
    for k in tc.attributes:
        assert np.array_equal(ta.attributes[k], tc.attributes[k], equal_nan=True), k


def _lattice(tmp_path):
    """A COPC file of points on a 0.5 lattice from (100, 200): with R = 1 and tiles of 4.0
    one point in 4 lies on a cell border and one in 16 on a tile border."""
    g = np.arange(0.0, 24.0 + 1e-9, 0.5)
    x, y = np.meshgrid(g, g, indexing="ij")
    z = np.round((0.05 * x * x - 0.03 * y * y + 0.1 * x * y / 4) / SCALE) * SCALE
    pts = np.column_stack([100.0 + x.ravel(), 200.0 + y.ravel(), 10.0 + z.ravel()])
    src = tmp_path / "lattice.copc.laz"
    order = write_copc(src, pts, np.zeros(len(pts), np.uint8), seed=3)
    return src, write_plain(tmp_path / "lattice.laz", src), pts, order


def test_points_on_tile_borders_are_owned_once(tmp_path):
    src, plain, pts, order = _lattice(tmp_path)
    n = len(pts)
    params = SimpleNamespace(radius=R, bytes_per_point=lambda: 900)
    plan = regions.plan(stream.open_source(src), params, 1 << 30, 4.0, 1)
    assert plan.tiling.size == 4 and plan.tiling.frame.origin[:2] == (100.0, 200.0)
    owned, reach = [], 0
    for t in plan.tiles:
        ids, xyz, own = regions.read_tile(plan.region(t), plan.tiling, t)
        assert np.all(np.diff(ids) > 0)                      # global-id order
        owned.append(ids[own])
        reach += len(ids)
    owned = np.concatenate(owned)
    assert len(owned) == n and np.array_equal(np.sort(owned), np.arange(n))   # once each
    ref = cio.read(src).points                  # node edges at 100 + 6 k: points on them
    for box in (((100.0, 200.0), (106.0, 206.0)), ((106.0, 200.0), (112.0, 224.0)),
                ((94.0, 194.0), (100.0, 200.0))):
        ids, xyz = plan.index.read_region(box)
        want = _inside(ref, box)
        assert len(want) and np.array_equal(ids, want) and np.array_equal(xyz, ref[want])
    on_border = (np.mod(pts[order, 0] - 100.0, 4.0) == 0) | (np.mod(pts[order, 1] - 200.0,
                                                                    4.0) == 0)
    assert on_border.sum() > 300 and reach > n                # halos overlap
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    ra = clcurv.curvature_file(src, a, R, method="mls1", tile=4.0, memory="64GiB")
    clcurv.curvature_file(plain, b, R, method="mls1", memory="64GiB")
    assert ra.get("regions") and ra["tiles"] == len(plan.tiles) >= 25
    assert_same(a, b)


def _edit_hierarchy(src, dst, edit):
    """A copy of the COPC file ``src`` at ``dst`` with its root hierarchy page's entries
    (ccopc.ENTRY, writable) and info VLR's root page (offset, size) given to ``edit``."""
    data = bytearray(src.read_bytes())
    info = struct.unpack_from("<H", data, 94)[0] + 54
    offset, size = struct.unpack_from("<QQ", data, info + 40)
    page = np.frombuffer(bytes(data[offset:offset + size]), ccopc.ENTRY).copy()
    root = edit(page, (offset, size), len(data)) or (offset, size)
    data[offset:offset + size] = page.tobytes()
    struct.pack_into("<QQ", data, info + 40, *root)
    dst.write_bytes(bytes(data))
    return dst


def _nth(page, k=0):
    """The index in ``page`` of the k-th node holding points, in file order."""
    held = np.flatnonzero(page["count"] > 0)
    return held[np.argsort(page["offset"][held])][k]


def _set(k, field, value):
    """An edit of _edit_hierarchy: the k-th node's ``field`` = value(its field, file size)."""
    def edit(page, root, n):
        i = _nth(page, k)
        page[field][i] = value(int(page[field][i]), n)
    return edit


#: damage -> (the edit, the message)
DAMAGES = {
    "offset into the header": (_set(3, "offset", lambda v, n: 200),
                               "after the point data's start"),
    "offset past the end": (_set(3, "offset", lambda v, n: n - 10), "within the file"),
    "byte size": (_set(0, "size", lambda v, n: v + 9), "overlapping bytes"),
    "last byte size": (_set(-1, "size", lambda v, n: v - 1),
                       "not the .* chunks of the LAZ chunk table"),
    "negative byte size": (_set(2, "size", lambda v, n: -v), "claims bytes"),
    "count": (_set(5, "count", lambda v, n: v + 1),
              f"hold {N + 1} points and the header claims {N}"),
    "page size": (lambda p, r, n: (r[0], r[1] - 5), "whole number of 32-byte entries"),
    "page in the header": (lambda p, r, n: (100, r[1]), "whole number of 32-byte entries"),
}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_a_damaged_hierarchy_fails_before_any_output(files, tmp_path, damage):
    _, src, _, _, _, _ = files
    edit, message = DAMAGES[damage]
    bad = _edit_hierarchy(src, tmp_path / "bad.copc.laz", edit)
    with pytest.raises(CorruptFileError, match=message):
        ccopc.open_index(bad)
    dst = tmp_path / "out.laz"
    with pytest.raises(CorruptFileError, match=message) as err:
        clcurv.curvature_file(bad, dst, R, method="mls1", tile=6.0, memory="64GiB")
    assert "bad.copc.laz" in str(err.value)
    assert sorted(os.listdir(tmp_path)) == ["bad.copc.laz"]         # no output, no workspace


def test_an_undamaged_copy_reads(files, tmp_path):
    """The damage tests' copy is sound when nothing is edited (they test the edits)."""
    _, src, _, _, _, _ = files
    good = _edit_hierarchy(src, tmp_path / "good.copc.laz", lambda p, r, n: None)
    assert len(ccopc.open_index(good).nodes) == len(ccopc.open_index(src).nodes)


def _fallback(tmp_path, src, plain):
    """The tiled run of ``src`` falls back to the buckets (saying why) and equals the
    in-memory run of ``plain``; returns what it said."""
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    said = []
    ra = clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB",
                               out=said.append)
    clcurv.curvature_file(plain, b, R, method="mls1", memory="64GiB")
    assert ra["tiled"] and not ra.get("regions")
    assert_same(a, b)
    return " ".join(said)


@pytest.mark.parametrize("end,axis,delta", [
    ("max", 0, 0.5), ("max", 2, 0.25), ("max", 1, -0.5), ("max", 0, 2.0 ** -30),
    ("min", 0, -0.5), ("min", 1, 0.25)],
    ids=["wide-max-x", "wide-max-z", "narrow-max-y", "one-ulp-max-x", "wide-min-x",
         "narrow-min-y"])
def test_wrong_header_bounds_are_caught(files, tmp_path, end, axis, delta):
    """A header max beyond the points' would shift the frame (the owned points' box
    differs), one short of them leaves points outside it (the tiles see them): either way
    the run starts again through the buckets and equals the in-memory run."""
    _, src, plain, _, _, _ = files
    data = bytearray(src.read_bytes())
    at = 179 + 16 * axis + (8 if end == "min" else 0)      # max x, min x, max y...
    true = struct.unpack_from("<d", data, at)[0]
    struct.pack_into("<d", data, at, true + delta)
    bad = tmp_path / "bounds.copc.laz"
    bad.write_bytes(bytes(data))
    index = ccopc.open_index(bad)
    assert (index.maxs if end == "max" else index.mins)[axis] == true + delta != true
    said = _fallback(tmp_path, bad, plain)
    wide = delta > 0 if end == "max" else delta < 0
    why = "are not the points'" if wide else "outside the header's bounds"
    assert why in said and "plain LAZ instead" in said, said


def test_nodes_that_do_not_hold_their_points_are_caught(files, tmp_path):
    """Two nodes' keys swapped: their points are outside their bounds, a region could miss
    them; the run starts again through the buckets."""
    _, src, plain, _, _, _ = files

    def swap(page, root, n):
        deep = np.flatnonzero((page["level"] == 2) & (page["count"] > 0))
        i, j = deep[0], deep[-1]
        for k in ("x", "y", "z"):
            page[k][i], page[k][j] = page[k][j], page[k][i]
    bad = _edit_hierarchy(src, tmp_path / "swapped.copc.laz", swap)
    with pytest.raises(ccopc.UntrustedBounds, match="outside the bounds of its COPC node"):
        ccopc.open_index(bad).read_region(((-1e9, -1e9), (1e9, 1e9)))
    said = _fallback(tmp_path, bad, plain)
    assert "outside the bounds of its COPC node" in said


def test_an_interrupted_region_run_resumes(files, tmp_path, monkeypatch):
    """Tiles done before an interruption are kept (their owned boxes too) and skipped by
    the same command; the output equals the in-memory run."""
    _, src, plain, _, _, _ = files
    compute, done = engine.compute_tile, []

    def flaky(task, device=None):
        if len(done) == 3:
            raise KeyboardInterrupt("interrupted")
        done.append(task.t)
        return compute(task, device)
    monkeypatch.setattr(engine, "compute_tile", flaky)
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    with pytest.raises(KeyboardInterrupt):
        clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB")
    ws = [p for p in os.listdir(tmp_path) if p.endswith(".clcurv-tiles")]
    assert len(ws) == 1 and not a.exists()
    assert len(list((tmp_path / ws[0] / "tiles").glob("*.box.npy"))) == 3
    monkeypatch.setattr(engine, "compute_tile", compute)
    said = []
    ra = clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB",
                               out=said.append)
    assert ra.get("regions") and ra["skipped"] == 3 and any("resuming" in s for s in said)
    clcurv.curvature_file(plain, b, R, method="mls1", memory="64GiB")
    assert_same(a, b)
    assert sorted(os.listdir(tmp_path)) == ["a.laz", "b.laz"]


def test_a_region_run_interrupted_while_writing_resumes(files, tmp_path, monkeypatch):
    """Every tile done, the run interrupted while the pieces are written: no output, and
    the same command skips every tile and writes the in-memory output byte for byte (the
    pieces are made again, never trusted from the interrupted run)."""
    _, src, _, _, _, _ = files
    piece = writing.write_piece

    def flaky(task):
        piece(task)             # one piece written, then the interruption
        raise KeyboardInterrupt("interrupted")
    monkeypatch.setattr(writing, "write_piece", flaky)
    a, c = tmp_path / "a.laz", tmp_path / "c.laz"
    with pytest.raises(KeyboardInterrupt):
        clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB")
    assert not a.exists()
    monkeypatch.setattr(writing, "write_piece", piece)
    said = []
    ra = clcurv.curvature_file(src, a, R, method="mls1", tile=6.0, memory="64GiB",
                               out=said.append)
    assert ra.get("regions") and ra["skipped"] == ra["tiles"] >= 4
    assert any("resuming" in s for s in said)
    clcurv.curvature_file(src, c, R, method="mls1", memory="64GiB")
    assert a.read_bytes() == c.read_bytes()
    assert sorted(os.listdir(tmp_path)) == ["a.laz", "c.laz"]


def test_a_copc_file_is_entered_at_any_point(tmp_path):
    """clcurv.io.las.read_range (what the bucket pass's parts and the output's pieces read)
    gives the records first..stop-1 of a COPC file (variable-size chunks, where lazrs'
    seek is wrong) as laspy reads them whole, for ranges starting inside a chunk, on a
    chunk's first point, and crossing many chunks."""
    from bench.catalog import make_copc
    from clcurv.io import las as clas
    src = tmp_path / "big.copc.laz"
    n = make_copc(src, 60_000, 1, extent=24.0, node_points=4000)
    ref = laspy.read(str(src)).points.array
    firsts = ccopc.open_index(src).nodes["first"]
    with laspy.open(str(src)) as r:                 # the bug this works around
        r.seek(int(firsts[3]) + 5)
        assert not np.array_equal(r.read_points(10).array, ref[firsts[3] + 5:][:10])
    cases = [(0, n, 1000), (1, n, 7000), (int(firsts[2]), int(firsts[5]), 10 ** 6),
             (int(firsts[4]) + 1, n - 3, 2500), (n - 5, n, 10), (17, 17, 5)]
    for a, b, size in cases:
        got = list(clas.read_range(laspy, src, a, b, size))
        arr = np.concatenate([g.array for g in got]) if got else ref[:0]
        assert np.array_equal(arr, ref[a:b]), (a, b, size)
    part = stream.open_source(src).chunks(3000, first=int(firsts[4]) + 1, stop=n - 3)
    xyz = np.concatenate([p for _, p, _ in part])
    assert np.array_equal(xyz, cio.read(src).points[int(firsts[4]) + 1:n - 3])


def test_a_copc_file_in_parts_through_the_buckets(tmp_path, monkeypatch):
    """A COPC file read through the buckets (scale_space: not by region) in parts of
    20,000 points, which enter it in the middle: the in-memory output byte for byte."""
    from bench.catalog import make_copc
    src = tmp_path / "big.copc.laz"
    make_copc(src, 60_000, 1, extent=24.0, node_points=4000)
    monkeypatch.setattr(stream, "PART_POINTS", 20_000)
    a, c = tmp_path / "a.laz", tmp_path / "c.laz"
    ra = clcurv.curvature_file(src, a, 0.6, method="mls1", scale_space=1, tile=8.0,
                               memory="64GiB")
    clcurv.curvature_file(src, c, 0.6, method="mls1", scale_space=1, memory="64GiB")
    assert ra["tiled"] and not ra.get("regions")
    assert a.read_bytes() == c.read_bytes()
