"""clcurv.io.pieces: a LAS/LAZ output assembled from pieces written apart (issue 50).

Every assembled file is compared with laspy writing the same points in one go: the points,
the header's counts, bounds, points by return, GPS range and extra-bytes min/max, the
VLRs and EVLRs; with windows aligned on the chunk size the files are byte for byte laspy's.
"""
import concurrent.futures
import copy
import errno
import os
import struct

import laspy
import lazrs
import numpy as np
import pytest
from laspy.vlrs.vlrlist import VLRList

from clcurv.io import WriteError, las, read
from clcurv.io.pieces import (CHUNK_SIZE, VARIABLE_CHUNKS, PieceError, PieceWriter,
                              assemble, read_piece_info, windows, write_piece)

BACKENDS = {"lazrs": laspy.LazBackend.Lazrs, "lazrs-parallel": laspy.LazBackend.LazrsParallel}
#: (point format, LAS version): 1 and 3 in LAS 1.2 and 1.4 (EVLRs), 6 in LAS 1.4
FORMATS = [(1, "1.2"), (3, "1.4"), (6, "1.4")]
#: window sizes (fractions of N) for 1, 3 and 7 pieces: unequal, one empty
CUTS = {1: [1.0], 3: [0.13, 0.61, 0.26], 7: [0.05, 0.2, 0.0, 0.31, 0.01, 0.17, 0.26]}
#: points per chunk in the small tests: pieces of several chunks, a short last one
SMALL_CHUNK = 1500


def make_header(fmt, version, evlr=True):
    header = laspy.LasHeader(point_format=fmt, version=version)
    header.add_extra_dims([laspy.ExtraBytesParams("mean_curvature", np.float32),
                           laspy.ExtraBytesParams("label", np.uint8),
                           laspy.ExtraBytesParams("normal", "3f4",
                                                  no_data=[-9999.0] * 3)])
    header.scales = np.array([0.001, 0.001, 0.01])
    header.offsets = np.array([481200.0, 4390100.0, 0.0])
    header.vlrs.append(laspy.VLR("clcurv", 7, "a test VLR", b"hello VLR"))
    if evlr and header.version.minor >= 4:
        header.evlrs = VLRList([laspy.VLR("clcurv", 8, "a test EVLR", b"x" * 300)])
    return header


def make_points(header, n, seed=0):
    """A synthetic aerial-like cloud in ``header``'s point format: every standard dimension
    filled, returns 1..7 (and 0), GPS times, extra bytes: a float32 field with NaN, a
    uint8 one and a 3-float32 array with no-data values (whose min/max laspy computes
    over all the points but those)."""
    rng = np.random.default_rng(seed)
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    rec.x = 481200.25 + rng.uniform(0, 97.3, n)
    rec.y = 4390100.5 + rng.uniform(0, 61.9, n)
    rec.z = 12.0 + 3 * np.sin(np.asarray(rec.x) / 7) + rng.normal(0, 0.2, n)
    rec.intensity = rng.integers(0, 65535, n)
    nr = rng.integers(1, 6, n)
    rec.number_of_returns = nr
    rec.return_number = np.minimum(rng.integers(0, 7, n), 7)
    rec.classification = rng.integers(0, 19 if header.point_format.id < 6 else 64, n) % 32
    rec.point_source_id = rng.integers(0, 9, n)
    rec.gps_time = 3.0e8 + rng.uniform(0, 60, n)
    if "red" in rec.point_format.dimension_names:
        for c in ("red", "green", "blue"):
            rec[c] = rng.integers(0, 65535, n)
    curv = rng.normal(0, 0.3, n).astype(np.float32)
    curv[rng.random(n) < 0.01] = np.nan
    rec["mean_curvature"] = curv
    rec["label"] = rng.integers(0, 256, n)
    normal = rng.normal(0, 1, (n, 3)).astype(np.float32)
    normal[rng.random((n, 3)) < 0.05] = -9999.0          # no data: out of the min/max
    rec["normal"] = normal
    return rec


def cut(n, parts):
    sizes = [int(round(f * n)) for f in CUTS[parts]]
    sizes[-1] = n - sum(sizes[:-1])
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    return list(zip(bounds[:-1], bounds[1:]))


def write_pieces(folder, header, rec, bounds, laz, chunk_size=SMALL_CHUNK):
    paths = []
    for i, (a, b) in enumerate(bounds):
        p = folder / f"piece-{i}.{'laz' if laz else 'las'}piece"
        write_piece(p, header, rec[a:b], laz=laz, chunk_size=chunk_size)
        paths.append(p)
    return paths


def laspy_reference(path, header, rec, backend=laspy.LazBackend.Lazrs):
    points = laspy.ScaleAwarePointRecord(rec.array.copy(), rec.point_format, rec.scales,
                                         rec.offsets)
    las = laspy.LasData(copy.deepcopy(header), points=points)
    las.write(str(path), laz_backend=backend if str(path).endswith(".laz") else None)
    return path


def assert_same_records(a, b, what=""):
    """The records ``a`` and ``b`` are the same bytes (NaN included)."""
    assert a.dtype == b.dtype and len(a) == len(b), what
    same = (np.ascontiguousarray(a).view(np.uint8).reshape(len(a), a.dtype.itemsize)
            == np.ascontiguousarray(b).view(np.uint8).reshape(len(b), b.dtype.itemsize)).all(axis=1)
    assert same.all(), f"{what}: {int((~same).sum())} records differ, first at " \
        f"{int(np.argmin(same))}"


def check_same(out, ref, backend):
    """The points and header facts of ``out`` equal those of laspy's ``ref``."""
    a = laspy.read(str(out), laz_backend=backend)
    b = laspy.read(str(ref), laz_backend=backend)
    assert a.header.point_count == b.header.point_count == len(b.points)
    assert_same_records(a.points.array, b.points.array)
    np.testing.assert_array_equal(a.header.mins, b.header.mins)
    np.testing.assert_array_equal(a.header.maxs, b.header.maxs)
    np.testing.assert_array_equal(a.header.number_of_points_by_return,
                                  b.header.number_of_points_by_return)
    assert a.header.point_format == b.header.point_format
    assert (a.header.version, a.header.are_points_compressed) == \
        (b.header.version, b.header.are_points_compressed)
    ea, eb = (h.vlrs.get("ExtraBytesVlr")[0].record_data_bytes() for h in (a.header, b.header))
    assert ea == eb                              # the extra bytes' min/max too
    own = [(v.user_id, v.record_id, v.record_data_bytes()) for v in a.header.vlrs
           if v.user_id == "clcurv"]
    assert own == [(v.user_id, v.record_id, v.record_data_bytes()) for v in b.header.vlrs
                   if v.user_id == "clcurv"]
    if b.header.evlrs:
        assert [bytes(v.record_data) for v in a.header.evlrs] == \
            [bytes(v.record_data) for v in b.header.evlrs]
    return a


def chunk_table(path):
    """(the LASzip VLR's chunk size, the chunk table [(points, bytes)]) of a LAZ file, as
    lazrs reads it; with fixed-size chunks, the last chunk's count is the rest of the
    points (lazrs reports the chunk size for it)."""
    with laspy.open(str(path)) as r:
        data = r.header.vlrs.get("LasZipVlr")[0].record_data
        n = r.header.point_count
        vlr = lazrs.LazVlr(data)
        with open(path, "rb") as f:
            f.seek(r.header.offset_to_point_data)
            table = [(int(c), int(b)) for c, b in lazrs.read_chunk_table(f, vlr)]
    size = vlr.chunk_size()
    if size != VARIABLE_CHUNKS:
        table = [(min(size, n - i * size), b) for i, (_, b) in enumerate(table)]
    return size, table


# --------------------------------------------------------------------------- equality

@pytest.mark.parametrize("kind", ["laz", "las"])
@pytest.mark.parametrize("parts", [1, 3, 7])
@pytest.mark.parametrize("fmt,version", FORMATS, ids=[f"fmt{f}" for f, _ in FORMATS])
def test_assembled_equals_laspy(tmp_path, fmt, version, parts, kind):
    n = 20_011
    header = make_header(fmt, version)
    rec = make_points(header, n, seed=fmt * 10 + parts)
    bounds = cut(n, parts)
    paths = write_pieces(tmp_path, header, rec, bounds, kind == "laz")
    out = assemble(tmp_path / f"out.{kind}", header, paths)
    ref = laspy_reference(tmp_path / f"ref.{kind}", header, rec)
    for backend in BACKENDS.values():
        check_same(out, ref, backend)
    cloud = read(out)                            # clcurv's own checked reader
    assert len(cloud) == n and np.isnan(cloud.attributes["mean_curvature"]).sum() == \
        np.isnan(np.asarray(rec["mean_curvature"])).sum()
    if kind == "las":
        assert out.read_bytes() == ref.read_bytes()
        return
    size, table = chunk_table(out)
    expected = [c for p in paths for c in read_piece_info(p).chunks]
    assert table == expected
    assert sum(c for c, _ in expected) == n
    per_piece = [-(-(b - a) // SMALL_CHUNK) for a, b in bounds]
    assert len(table) == sum(per_piece)
    assert size == (VARIABLE_CHUNKS if parts > 1 else SMALL_CHUNK)


@pytest.mark.parametrize("kind", ["laz", "las"])
@pytest.mark.parametrize("fmt,version", FORMATS, ids=[f"fmt{f}" for f, _ in FORMATS])
def test_aligned_windows_are_laspy_bytes(tmp_path, fmt, version, kind):
    """Windows on chunk boundaries (windows()): the assembled file is the very file laspy
    writes (fixed-size chunks, the same chunk table)."""
    n = 2 * CHUNK_SIZE + 1234
    header = make_header(fmt, version)
    rec = make_points(header, n, seed=fmt)
    bounds = windows(n, 3)
    assert [b - a for a, b in bounds] == [50_000, 50_000, 1234]
    paths = write_pieces(tmp_path, header, rec, bounds, kind == "laz", chunk_size=CHUNK_SIZE)
    out = assemble(tmp_path / f"out.{kind}", header, paths)
    ref = laspy_reference(tmp_path / f"ref.{kind}", header, rec)
    assert out.read_bytes() == ref.read_bytes()
    if kind == "laz":
        size, table = chunk_table(out)
        assert size == CHUNK_SIZE and len(table) == 3


def test_pieces_from_worker_processes(tmp_path):
    """Pieces written by two other processes assemble into laspy's points."""
    n = 30_000
    header = make_header(6, "1.4")
    rec = make_points(header, n, seed=5)
    bounds = cut(n, 3)
    paths = [tmp_path / f"w{i}.lazpiece" for i in range(len(bounds))]
    with concurrent.futures.ProcessPoolExecutor(2) as pool:
        infos = list(pool.map(_worker, [(str(p), header, rec.array[a:b]) for p, (a, b)
                                        in zip(paths, bounds)]))
    assert [i.points for i in infos] == [b - a for a, b in bounds]
    out = assemble(tmp_path / "out.laz", header, paths)
    ref = laspy_reference(tmp_path / "ref.laz", header, rec)
    for backend in BACKENDS.values():
        check_same(out, ref, backend)


def test_output_header_of_a_laz_input(tmp_path):
    """The header clcurv builds for an output (clcurv.io.las.output_header of the input's,
    extra_dims for the fields), the input's records copied and the fields set: the pieces
    assemble into the file laspy writes from the same header and records."""
    src = make_header(3, "1.2", evlr=False)             # its mean_curvature is kept in place
    n = 12_345
    inp = laspy_reference(tmp_path / "in.laz", src, make_points(src, n, seed=2))
    with laspy.open(str(inp)) as r:
        header = las.output_header(r.header)
        records = r.read_points(n)
    fields = {"k1": np.linspace(-1, 1, n).astype(np.float32),
              "mean_curvature": np.cos(np.arange(n)).astype(np.float32)}
    las.extra_dims(laspy, tmp_path / "out.laz", fields, header)
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for name in records.array.dtype.names:
        rec.array[name] = records.array[name]
    for name, a in fields.items():
        rec.array[name] = a
    out = assemble(tmp_path / "out.laz", header,
                   write_pieces(tmp_path, header, rec, cut(n, 3), True))
    ref = laspy_reference(tmp_path / "ref.laz", header, rec)
    for backend in BACKENDS.values():
        check_same(out, ref, backend)


def test_kernel_copy_falls_back(tmp_path, monkeypatch):
    """verify=False copies with os.copy_file_range; where the kernel refuses (another file
    system, an old kernel) the bytes are copied by read and write, the same file."""
    header = make_header(6, "1.4")
    rec = make_points(header, 9000, seed=8)
    paths = write_pieces(tmp_path, header, rec, cut(9000, 3), True)
    fast = assemble(tmp_path / "fast.laz", header, paths, verify=False)

    def refuse(*args, **kw):
        raise OSError(errno.EXDEV, "Invalid cross-device link")
    monkeypatch.setattr(os, "copy_file_range", refuse, raising=False)
    slow = assemble(tmp_path / "slow.laz", header, paths, verify=False)
    assert slow.read_bytes() == fast.read_bytes()
    ref = laspy_reference(tmp_path / "ref.laz", header, rec)
    check_same(slow, ref, laspy.LazBackend.Lazrs)


def _worker(args):
    path, header, arr = args
    return write_piece(path, header, arr, chunk_size=7000)


@pytest.mark.parametrize("evlr", [False, True], ids=["", "evlr"])
@pytest.mark.parametrize("kind", ["laz", "las"])
def test_all_pieces_empty(tmp_path, kind, evlr):
    """0 points: laspy's LAS file byte for byte; laspy's LAZ has a chunk table of one empty
    chunk where ours has none, the same points and header otherwise."""
    header = make_header(6, "1.4", evlr=evlr)
    rec = make_points(header, 0)
    paths = write_pieces(tmp_path, header, rec, [(0, 0), (0, 0)], kind == "laz")
    assert [read_piece_info(p).points for p in paths] == [0, 0]
    out = assemble(tmp_path / f"out.{kind}", header, paths)
    ref = laspy_reference(tmp_path / f"ref.{kind}", header, rec)
    for backend in BACKENDS.values():
        a = check_same(out, ref, backend)
        assert len(a.points) == 0
    if kind == "las":
        assert out.read_bytes() == ref.read_bytes()
    else:
        assert chunk_table(out)[1] == []


# --------------------------------------------------------------------------- readers

@pytest.mark.parametrize("backend", list(BACKENDS), ids=list(BACKENDS))
def test_chunk_iterator_variable_chunks(tmp_path, backend):
    n = 20_011
    header = make_header(3, "1.4")
    rec = make_points(header, n, seed=3)
    paths = write_pieces(tmp_path, header, rec, cut(n, 7), True)
    out = assemble(tmp_path / "out.laz", header, paths)
    assert chunk_table(out)[0] == VARIABLE_CHUNKS
    with laspy.open(str(out), laz_backend=BACKENDS[backend]) as r:
        got = np.concatenate([c.array for c in r.chunk_iterator(4321)])
    assert_same_records(got, rec.array)


@pytest.mark.parametrize("backend", list(BACKENDS), ids=list(BACKENDS))
def test_seek_fixed_chunks(tmp_path, backend):
    """Windows from windows() give fixed-size chunks: laspy's seek reads the right points
    anywhere, the first, the middle and the last chunk."""
    n, chunk = 20_011, 2000
    header = make_header(6, "1.4")
    rec = make_points(header, n, seed=4)
    paths = write_pieces(tmp_path, header, rec, windows(n, 3, chunk), True, chunk_size=chunk)
    out = assemble(tmp_path / "out.laz", header, paths)
    assert chunk_table(out)[0] == chunk
    for at in (0, 5, 1999, 2000, 7777, 13999, 20_000, n - 11):
        with laspy.open(str(out), laz_backend=BACKENDS[backend]) as r:
            r.seek(at)
            got = r.read_points(10)
        assert_same_records(got.array, rec.array[at:at + 10], f"seek {at}")


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="lazrs 0.8 seeks wrongly in variable-size chunks (the point "
                   "within a chunk is taken as the index modulo the chunk's count): use "
                   "windows() for seekable output")
@pytest.mark.parametrize("backend", list(BACKENDS), ids=list(BACKENDS))
def test_seek_variable_chunks(tmp_path, backend):
    n = 20_011
    header = make_header(6, "1.4")
    rec = make_points(header, n, seed=4)
    paths = write_pieces(tmp_path, header, rec, cut(n, 3), True)
    out = assemble(tmp_path / "out.laz", header, paths)
    for at in (2601, 7777, 15000):
        with laspy.open(str(out), laz_backend=BACKENDS[backend]) as r:
            r.seek(at)
            got = r.read_points(10)
        assert_same_records(got.array, rec.array[at:at + 10], f"seek {at}")


@pytest.mark.skipif(not laspy.LazBackend.Laszip.is_available(),
                    reason="LASzip (the reference C++ implementation) NOT RUN: laspy's Laszip "
                    "backend needs the 'laszip' package, not installed here")
@pytest.mark.parametrize("parts", [1, 3, 7])
@pytest.mark.parametrize("fmt,version", FORMATS, ids=[f"fmt{f}" for f, _ in FORMATS])
def test_laszip_reads_and_seeks(tmp_path, fmt, version, parts):
    """LASzip itself reads the assembled files, variable-size chunks too, and seeks in them
    (where lazrs 0.8 does not)."""
    n = 20_011
    header = make_header(fmt, version)
    rec = make_points(header, n, seed=parts)
    out = assemble(tmp_path / "out.laz", header,
                   write_pieces(tmp_path, header, rec, cut(n, parts), True))
    got = laspy.read(str(out), laz_backend=laspy.LazBackend.Laszip)
    assert_same_records(got.points.array, rec.array, "LASzip read")
    for at in (0, 2601, 7777, n - 10):
        with laspy.open(str(out), laz_backend=laspy.LazBackend.Laszip) as r:
            r.seek(at)
            assert_same_records(r.read_points(10).array, rec.array[at:at + 10], f"seek {at}")


def test_windows():
    assert windows(0, 3) == [(0, 0)] * 3
    assert windows(10, 1) == [(0, 10)]
    w = windows(1_000_001, 4, 1000)
    assert w[0][0] == 0 and w[-1][1] == 1_000_001
    assert all(b == c for (_, b), (c, _) in zip(w, w[1:]))
    assert all((b - a) % 1000 == 0 for a, b in w[:-1])
    assert max(b - a for a, b in w) - min(b - a for a, b in w) <= 1000
    assert windows(2500, 4, 1000) == [(0, 0), (0, 1000), (1000, 2000), (2000, 2500)]
    with pytest.raises(ValueError):
        windows(10, 0)


# --------------------------------------------------------------------------- refusals

@pytest.fixture(params=["laz", "las"])
def assembled(request, tmp_path):
    """(kind, header, piece paths, output path holding an earlier file)."""
    kind = request.param
    header = make_header(6, "1.4")
    rec = make_points(header, 9000, seed=9)
    paths = write_pieces(tmp_path, header, rec, cut(9000, 3), kind == "laz")
    out = tmp_path / f"out.{kind}"
    out.write_bytes(b"the previous output")
    return kind, header, paths, out


def check_refused(tmp_path, out, header, paths, match, **kw):
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(PieceError, match=match):
        assemble(out, header, paths, **kw)
    assert out.read_bytes() == b"the previous output"
    assert sorted(os.listdir(tmp_path)) == before          # no temporary left


@pytest.mark.parametrize("cut_bytes", [1, 24, 30, 5000])
def test_truncated_piece_refused(tmp_path, assembled, cut_bytes):
    kind, header, paths, out = assembled
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[:-cut_bytes])
    check_refused(tmp_path, out, header, paths, str(paths[1]))
    with pytest.raises(PieceError, match="truncated|footer|CRC"):
        read_piece_info(paths[1])


def test_payload_truncated_refused(tmp_path, assembled):
    """Bytes missing from the middle (the payload) while the footer is whole."""
    kind, header, paths, out = assembled
    data = paths[2].read_bytes()
    paths[2].write_bytes(data[:100] + data[200:])
    check_refused(tmp_path, out, header, paths, "truncated or extended")


@pytest.mark.parametrize("verify", [True, False])
def test_corrupted_payload(tmp_path, assembled, verify):
    """A flipped payload byte fails the CRC during the copy: the output is untouched.
    Without verify the sizes are checked only, and the byte is copied as it is."""
    kind, header, paths, out = assembled
    data = bytearray(paths[0].read_bytes())
    data[len(data) // 3] ^= 0x40
    paths[0].write_bytes(bytes(data))
    if verify:
        check_refused(tmp_path, out, header, paths, "payload fails its CRC")
    else:
        assemble(out, header, paths, verify=False)
        assert out.stat().st_size > 1000


def test_corrupted_metadata_refused(tmp_path, assembled):
    kind, header, paths, out = assembled
    data = bytearray(paths[1].read_bytes())
    data[-40] ^= 0x01
    paths[1].write_bytes(bytes(data))
    check_refused(tmp_path, out, header, paths, "metadata fails its CRC")


def test_missing_piece_refused(tmp_path, assembled):
    kind, header, paths, out = assembled
    check_refused(tmp_path, out, header, paths + [tmp_path / "nope.piece"], "cannot open")


def test_piece_of_another_header_refused(tmp_path, assembled):
    kind, header, paths, out = assembled
    other = copy.deepcopy(header)
    other.scales = np.array([0.01, 0.01, 0.01])
    check_refused(tmp_path, out, other, paths, "scales")
    narrower = make_header(6, "1.4")
    narrower.remove_extra_dims(["label"])
    check_refused(tmp_path, out, narrower, paths, "record length|layout")


def test_piece_of_the_other_kind_refused(tmp_path, assembled):
    kind, header, paths, out = assembled
    wrong = out.with_suffix(".las" if kind == "laz" else ".laz")
    with pytest.raises(PieceError, match="kind of output"):
        assemble(wrong, header, paths)
    assert not wrong.exists()


def test_not_a_piece_refused(tmp_path):
    p = tmp_path / "x.piece"
    p.write_bytes(b"\0" * 100)
    with pytest.raises(PieceError, match="footer"):
        read_piece_info(p)
    p.write_bytes(b"\0" * 10)
    with pytest.raises(PieceError, match="shorter"):
        read_piece_info(p)


def test_wrong_records_refused(tmp_path):
    header = make_header(6, "1.4")
    rec = make_points(make_header(3, "1.4"), 10)
    with pytest.raises(WriteError, match="point format 6"):
        write_piece(tmp_path / "p.piece", header, rec.array)
    rescaled = make_points(header, 10)
    rescaled.change_scaling(scales=[0.01, 0.01, 0.01])
    with pytest.raises(WriteError, match="scales"):
        write_piece(tmp_path / "p.piece", header, rescaled)
    with pytest.raises(WriteError, match="chunk_size"):
        write_piece(tmp_path / "p.piece", header, make_points(header, 10), chunk_size=0)
    assert not os.listdir(tmp_path)


def test_piece_is_written_atomically(tmp_path):
    """A piece that cannot be written leaves the previous piece file as it was."""
    header = make_header(6, "1.4")
    p = tmp_path / "p.lazpiece"
    info = write_piece(p, header, make_points(header, 100))
    before = p.read_bytes()
    with pytest.raises(WriteError):
        write_piece(p, header, np.zeros(5))
    assert p.read_bytes() == before and read_piece_info(p) == info
    assert os.listdir(tmp_path) == ["p.lazpiece"]


@pytest.mark.parametrize("laz", [True, False], ids=["laz", "las"])
def test_piece_writer_in_batches(tmp_path, laz):
    """Batches of any size (empty, within a chunk, across several) give the piece that
    write_piece writes from all the records at once, byte for byte."""
    header = make_header(6, "1.4")
    rec = make_points(header, 10_000, seed=6)
    whole = write_piece(tmp_path / "whole.piece", header, rec, laz=laz, chunk_size=1500)
    cuts = [0, 0, 7, 1500, 1501, 4000, 4000, 9000, 9999, 10_000]
    buffer = np.zeros(10_000, rec.array.dtype)
    with PieceWriter(tmp_path / "batches.piece", header, laz=laz, chunk_size=1500) as w:
        for a, b in zip(cuts[:-1], cuts[1:]):
            buffer[:b - a] = rec.array[a:b]             # one buffer reused for every batch
            w.write(buffer[:b - a])
            if laz:
                assert w._n_pending < 1500           # full chunks are compressed at once
    assert w.info.chunks == whole.chunks and w.info.points == 10_000
    assert (tmp_path / "batches.piece").read_bytes() == (tmp_path / "whole.piece").read_bytes()


def test_piece_writer_error_leaves_nothing(tmp_path):
    header = make_header(6, "1.4")
    p = tmp_path / "p.lazpiece"
    p.write_bytes(b"an earlier piece")
    with pytest.raises(KeyError):
        with PieceWriter(p, header, chunk_size=100) as w:
            w.write(make_points(header, 250))
            raise KeyError("the worker failed")
    assert p.read_bytes() == b"an earlier piece" and os.listdir(tmp_path) == ["p.lazpiece"]
    w = PieceWriter(tmp_path / "q.lazpiece", header)
    w.write(make_points(header, 10))
    with pytest.raises(WriteError, match="point format"):
        w.write(np.zeros(3))                         # aborts the piece
    with pytest.raises(WriteError, match="closed"):
        w.write(make_points(header, 10))
    assert os.listdir(tmp_path) == ["p.lazpiece"]


def test_piece_layout(tmp_path):
    """The footer's numbers: magic, version, metadata length and CRC; the payload of a
    LAZ piece is its chunks, of a LAS piece the records."""
    header = make_header(1, "1.2")
    rec = make_points(header, 4000)
    for laz in (True, False):
        p = tmp_path / "p.piece"
        info = write_piece(p, header, rec, laz=laz, chunk_size=1500)
        data = p.read_bytes()
        magic, version, length, _ = struct.unpack("<8sIQI", data[-24:])
        assert (magic, version) == (b"CLCPIECE", 1)
        assert info.payload_bytes + length + 24 == len(data)
        if laz:
            assert [c for c, _ in info.chunks] == [1500, 1500, 1000]
        else:
            assert data[:info.payload_bytes] == rec.array.tobytes()
        assert sum(info.by_return) == int((np.asarray(rec.return_number) > 0).sum())
