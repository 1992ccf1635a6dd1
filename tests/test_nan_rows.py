"""Rows whose x, y or z is NaN or +-Inf, the same in memory and in tiles: clcurv.io.read drops
them (from the points, normals and attributes alike) and counts them; the stream sources
of a tiled run (clcurv.io.stream: NPY, binary PLY) leave them out the same way, so that a
tiled run writes the in-memory output bit for bit, which is the output of the file
without those rows. A file whose every row is non-finite gives the empty output of an
empty file, in both paths."""
import numpy as np
import pytest

import clcurv
from clcurv import io
from clcurv.tiles import buckets
from clcurv.io import stream
from clcurv.jobs.job import features_file

R = 1.0
RUN = dict(method="mls1", orient=None, memory="64GiB")
CHUNK = 512                   # the bucketing pass's chunks in these tests (READ_CHUNK)


def _ply(path, rec):
    """A binary little-endian PLY of the structured vertex records ``rec``."""
    types = {"f8": "double", "f4": "float", "u2": "ushort", "u1": "uchar", "i4": "int"}
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(rec)}"]
    head += [f"property {types[rec.dtype[k].str[1:]]} {k}" for k in rec.dtype.names]
    head += ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode("ascii"))
        rec.astype(rec.dtype.newbyteorder("<")).tofile(f)
    return path


def _records(pts, seed=0):
    """Vertex records of ``pts``: x y z double, unit normals (float), two attributes."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=pts.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rec = np.empty(len(pts), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("nx", "f4"),
                              ("ny", "f4"), ("nz", "f4"), ("intensity", "u2"),
                              ("confidence", "f4")])
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["nx"], rec["ny"], rec["nz"] = nrm.T
    rec["intensity"] = rng.integers(0, 65535, len(pts))
    rec["confidence"] = rng.random(len(pts))
    return rec


def _spoil(n, where, seed=0):
    """The rows of an n-row cloud made non-finite, and the (row, column, value) of each."""
    rng = np.random.default_rng(seed)
    rows = {"none": np.zeros(0, int),
            "first": np.array([0]),
            "last": np.array([n - 1]),
            "chunk": np.arange(2 * CHUNK, 3 * CHUNK),         # a whole chunk of reading
            "scattered": np.sort(rng.choice(n, n // 20, replace=False)),
            "all": np.arange(n)}[where]
    cols = rng.integers(0, 3, len(rows))
    vals = rng.choice([np.nan, np.inf, -np.inf], len(rows))
    return rows, cols, vals


def _write(path, pts, where, seed=0, columns=3):
    """``path`` (.npy: ``columns`` columns; .ply: the records of :func:`_records`) of
    ``pts`` with the rows ``where`` spoilt; returns the kept rows' mask."""
    rows, cols, vals = _spoil(len(pts), where, seed)
    keep = np.ones(len(pts), bool)
    keep[rows] = False
    if path.suffix == ".npy":
        rng = np.random.default_rng(seed)
        a = np.column_stack([pts, rng.random((len(pts), columns - 3))])
        if columns == 6:                                    # unit normals
            a[:, 3:] -= 0.5
            a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
        a[rows, cols] = vals
        np.save(path, a)
        return keep
    rec = _records(pts, seed)
    for r, c, v in zip(rows, cols, vals):
        rec["xyz"[c]][r] = v
    _ply(path, rec)
    return keep


def _finite_copy(path, dst, keep):
    """``dst``: the file ``path`` without the rows not in ``keep`` (the same format)."""
    if path.suffix == ".npy":
        np.save(dst, np.load(path)[keep])
    else:
        from clcurv.io.stream import PlySource
        src = PlySource(path)
        with open(path, "rb") as f:
            f.seek(src.offset)
            rec = np.fromfile(f, src.dtype, count=src.rows)
        _ply(dst, rec[keep])
    return dst


def _same_output(a, b):
    """Two outputs hold the same bits (NPZ: every member; PLY: every byte)."""
    if a.suffix == ".ply":
        assert a.read_bytes() == b.read_bytes(), (a, b)
        return
    za, zb = np.load(a), np.load(b)
    assert za.files == zb.files, (za.files, zb.files)
    for k in za.files:
        assert za[k].dtype == zb[k].dtype and za[k].shape == zb[k].shape, k
        assert za[k].tobytes() == zb[k].tobytes(), k


@pytest.fixture(scope="module")
def scene():
    return clcurv.shapes.aerial_scene(5000, extent=(30.3, 20.9), seed=1)["points"]


@pytest.fixture
def small_chunks(monkeypatch):
    """The bucketing pass reads CHUNK rows at a time (so 'chunk' spoils a whole one)."""
    monkeypatch.setattr(buckets, "READ_CHUNK", CHUNK)


# --------------------------------------------------------------------------- the sources

@pytest.mark.parametrize("kind", ["npy3", "npy4", "npy6", "ply"])
@pytest.mark.parametrize("where", ["none", "first", "last", "chunk", "scattered", "all"])
def test_a_source_reads_what_io_read_reads(tmp_path, scene, kind, where):
    """n, dropped, the box and every chunk (of any size: starts contiguous, each ``size``
    rows but the last, none empty) give the points, normals and attributes of
    clcurv.io.read, bit for bit."""
    pts = scene[:2000]
    path = tmp_path / f"c.{kind[:3]}"
    keep = _write(path, pts, where, seed=3, columns=int(kind[3:] or 3))
    cloud = io.read(path)
    src = stream.open_source(path)
    assert (src.n, src.dropped, src.rows) == (int(keep.sum()), int((~keep).sum()), len(pts))
    assert (src.n, src.dropped) == (len(cloud), cloud.dropped)
    assert src.has_normals == (cloud.normals is not None)
    assert (kind in ("npy6", "ply")) == src.has_normals
    box = src.bounds_hint()
    if src.n:
        assert np.array_equal(box[0], cloud.points.min(axis=0))
        assert np.array_equal(box[1], cloud.points.max(axis=0))
    else:
        assert box is None
    specs = src.attribute_specs()
    assert sorted(specs) == sorted(cloud.attributes)
    for size in (1, 37, CHUNK, 5000):
        got = list(src.chunks(size, attributes=True))
        starts = [c[0] for c in got]
        lengths = [len(c[1]) for c in got]
        assert starts == [sum(lengths[:i]) for i in range(len(got))], size
        assert all(m == size for m in lengths[:-1]) and all(m > 0 for m in lengths)
        assert sum(lengths) == src.n
        if not got:
            continue
        xyz = np.concatenate([c[1] for c in got])
        assert xyz.dtype == np.float64 and xyz.tobytes() == cloud.points.tobytes()
        if src.has_normals:
            nrm = np.concatenate([c[2] for c in got])
            assert nrm.tobytes() == cloud.normals.tobytes()
        for k, v in cloud.attributes.items():
            a = np.concatenate([c[3][k] for c in got])
            assert a.dtype == v.dtype == specs[k][0] and a.tobytes() == v.tobytes(), k
        plain = list(src.chunks(size))                      # without attributes: the same
        assert [c[0] for c in plain] == starts
        assert np.concatenate([c[1] for c in plain]).tobytes() == xyz.tobytes()


def test_a_catalog_counts_its_files_rows(tmp_path, scene):
    paths = []
    for i, where in enumerate(("first", "all", "none", "scattered")):
        paths.append(tmp_path / f"{i}.npy")
        _write(paths[-1], scene[i * 1000:(i + 1) * 1000], where, seed=i)
    cat = stream.Catalog(paths)
    parts = [io.read(p) for p in paths]
    assert cat.n == sum(len(c) for c in parts)
    assert cat.dropped == sum(c.dropped for c in parts) == 1 + 1000 + 50
    assert list(cat.offsets) == list(np.cumsum([0] + [len(c) for c in parts]))
    got = np.concatenate([c[1] for c in cat.chunks(300)])
    assert got.tobytes() == np.concatenate([c.points for c in parts]).tobytes()


def test_a_file_changed_after_the_scan_is_refused(tmp_path, scene):
    path = tmp_path / "c.npy"
    _write(path, scene, "first")
    src = stream.open_source(path)
    _write(path, scene, "none")                     # one more finite row since
    with pytest.raises(io.CorruptFileError, match="changed"):
        list(src.chunks(CHUNK))


# --------------------------------------------------------------------------- the runs

@pytest.mark.parametrize("fmt", ["npy", "ply"])
@pytest.mark.parametrize("where", ["first", "last", "chunk", "scattered", "all"])
def test_tiles_equal_memory_and_the_finite_rows(tmp_path, scene, small_chunks, fmt, where):
    """In memory and in 8 m tiles, the output of a file with non-finite rows is the output
    of the file without them, bit for bit; both runs report how many were dropped."""
    src = tmp_path / f"in.{fmt}"
    keep = _write(src, scene, where, seed=5)
    ref_in = _finite_copy(src, tmp_path / f"finite.{fmt}", keep)
    ext = ".npz" if fmt == "npy" else ".ply"
    mem, til, ref = (tmp_path / f"{k}{ext}" for k in ("mem", "til", "ref"))
    m = clcurv.curvature_file(src, mem, R, **RUN)
    t = clcurv.curvature_file(src, til, R, tile=8.0, **RUN)
    clcurv.curvature_file(ref_in, ref, R, **RUN)
    assert not m["tiled"] and t["tiled"]
    assert m["points"] == t["points"] == keep.sum()
    if where != "all":
        assert t["tiles"] >= 6
    _same_output(mem, til)
    _same_output(mem, ref)
    if "dropped" in t:                              # once clcurv.tiles.engine reports it
        assert t["dropped"] == (~keep).sum()
    if "dropped" in m:
        assert m["dropped"] == (~keep).sum()


def test_every_row_non_finite_gives_the_empty_output(tmp_path):
    """A file of non-finite rows only: the output of an empty file, in memory and in tiles,
    for NPY and PLY outputs."""
    pts = np.zeros((0, 3))
    for fmt in ("npy", "ply"):
        empty = tmp_path / f"empty.{fmt}"
        bad = tmp_path / f"bad.{fmt}"
        _write(empty, pts, "none")
        _write(bad, np.ones((700, 3)), "all")
        assert stream.open_source(bad).n == 0 and stream.open_source(bad).dropped == 700
        for ext in (".npz", ".ply"):
            outs = {}
            for name, src, tile in (("e_mem", empty, None), ("e_til", empty, 8.0),
                                    ("b_mem", bad, None), ("b_til", bad, 8.0)):
                outs[name] = tmp_path / f"{fmt}_{name}{ext}"
                s = clcurv.curvature_file(src, outs[name], R, tile=tile, **RUN)
                assert s["points"] == 0
            for name in ("e_til", "b_mem", "b_til"):
                _same_output(outs["e_mem"], outs[name])


def test_features_in_tiles_drop_the_same_rows(tmp_path, scene, small_chunks):
    src = tmp_path / "in.ply"
    keep = _write(src, scene, "scattered", seed=7)
    m = features_file(src, tmp_path / "mem.npz", R, memory="64GiB")
    t = features_file(src, tmp_path / "til.npz", R, memory="64GiB", tile=8.0)
    assert not m["tiled"] and t["tiled"] and m["points"] == t["points"] == keep.sum()
    assert m["dropped"] == (~keep).sum()
    if "dropped" in t:                              # once clcurv.tiles.engine reports it
        assert t["dropped"] == m["dropped"]
    _same_output(tmp_path / "mem.npz", tmp_path / "til.npz")


def test_a_catalog_drops_each_files_rows(tmp_path, scene, small_chunks):
    """A catalog of NPY files (one cloud), one of them non-finite only: its outputs are
    the in-memory output of the finite rows of all its files, one file's rows each."""
    paths, kept, dropped = [], [], 0
    for i, where in enumerate(("chunk", "all", "scattered")):
        paths.append(tmp_path / f"part{i}.npy")
        keep = _write(paths[-1], scene[i * 1700:(i + 1) * 1700], where, seed=i)
        kept.append(np.load(paths[-1])[keep])
        dropped += int((~keep).sum())
    assert len(kept[1]) == 0 and dropped == 512 + 1700 + 80
    whole = tmp_path / "whole.npy"
    np.save(whole, np.concatenate(kept))
    clcurv.curvature_file(whole, tmp_path / "whole.npz", R, **RUN)
    ref = np.load(tmp_path / "whole.npz")
    out = tmp_path / "out"
    out.mkdir()
    s = clcurv.curvature_file(paths, out, R, tile=8.0, **RUN)
    assert s["tiled"] and s["points"] == sum(len(k) for k in kept)
    if "dropped" in s:                              # once clcurv.tiles.engine reports it
        assert s["dropped"] == dropped
    off = 0
    for k, d in zip(kept, s["dst"]):
        z = np.load(d)
        assert z.files == ref.files
        for name in z.files:
            assert z[name].tobytes() == ref[name][off:off + len(k)].tobytes(), (d, name)
        off += len(k)


# --------------------------------------------------------------------------- the command

def test_the_command_reports_the_dropped_rows(tmp_path, scene):
    from tests.hostile import run_cli
    src = tmp_path / "in.npy"
    keep = _write(src, scene, "scattered", seed=9)
    n, dropped = int(keep.sum()), int((~keep).sum())
    args = ("--radius", "1", "--method", "mls1", "--orient", "none", "-q")
    r = run_cli("compute", src, "-o", tmp_path / "mem.npz", *args)
    line = f"{n} points from {src} ({dropped} non-finite dropped)"
    assert r.code == 0 and line in r.stdout, r.stdout + r.stderr
    r = run_cli("compute", src, "-o", tmp_path / "til.npz", *args, "--tile-size", "8")
    assert r.code == 0, r.stderr
    _same_output(tmp_path / "mem.npz", tmp_path / "til.npz")
    if "non-finite dropped" in r.stdout:            # once clcurv.jobs.tiled_job prints it
        assert line in r.stdout, r.stdout
    r = run_cli("features", src, "-o", tmp_path / "f.npz", "--radius", "1",
                "--tile-size", "8", "-q")
    assert r.code == 0, r.stderr
    if "non-finite dropped" in r.stdout:            # once clcurv.tiles.engine reports it
        assert f"{n} points ({dropped} non-finite dropped)" in r.stdout, r.stdout
