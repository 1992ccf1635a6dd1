"""The bytes a LAS/LAZ output costs: the default fields (no principal directions), the count
field ``neighbours`` as uint16 (uint32 when a count exceeds 65,535, never clipped), the
status as uint8; the same in memory (:func:`clcurv.io.write`) and in tiles
(:func:`clcurv.io.stream.write_las`), byte for byte."""
from __future__ import annotations

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from clcurv import io                                       # noqa: E402
from clcurv.io import las as cl_las, stream                # noqa: E402
from clcurv.io.common import WriteError                     # noqa: E402

HAS_LAZ = bool(laspy.LazBackend.detect_available())
N = 100


def _make_las(path, n=N, seed=0):
    rng = np.random.default_rng(seed)
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales, hdr.offsets = [0.001] * 3, [1000.0, 2000.0, 0.0]
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=hdr)
    pts = rng.uniform(0, 10, size=(n, 3)) + hdr.offsets
    rec.x, rec.y, rec.z = pts.T
    rec.classification = rng.integers(0, 10, n)
    with laspy.open(str(path), mode="w", header=hdr) as w:
        w.write_points(rec)
    return path


def _fields(counts, seed=1):
    rng = np.random.default_rng(seed)
    n = len(counts)
    return {"mean_curvature": rng.normal(size=n), "neighbours": np.asarray(counts, np.int64),
            "status": (np.arange(n) % 4).astype(np.uint8)}


def _rows(fields, normals):
    """A tiled run's ``rows(start, stop)``: the records of its windows (float64 reals,
    integer counts: int64 here, so that one beyond uint32 can be given)."""
    n = len(normals)
    dt = [("mean_curvature", "f8"), ("neighbours", "i8"), ("status", "u1"),
          ("normals", "f8", (3,))]
    rec = np.empty(n, dt)
    for k in ("mean_curvature", "neighbours", "status"):
        rec[k] = fields[k]
    rec["normals"] = normals
    return lambda a, b: rec[a:b]


def _normals(n, seed=2):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


@pytest.mark.parametrize("ext", [".las"] + ([".laz"] if HAS_LAZ else []))
@pytest.mark.parametrize("big", [0, 65535, 65536, 4_000_000_000], ids=lambda b: f"max{b}")
def test_counts_narrowest_unsigned_type_same_in_memory_and_in_tiles(tmp_path, ext, big):
    """uint16 while every count is at most 65,535, uint32 beyond (the tiled writer sees the
    big count only in its last chunk: it writes the file again); the values exact."""
    src = _make_las(tmp_path / "in.las")
    counts = np.arange(N) + 3
    counts[-1] = max(big, counts[-1])
    fields, nrm = _fields(counts), _normals(N)
    cloud = io.read(src)
    mem = io.write(tmp_path / f"mem{ext}", cloud.points, fields, normals=nrm, like=cloud)
    til = tmp_path / f"til{ext}"
    stream.write_las(til, stream.open_source(src), ["mean_curvature", "neighbours", "status",
                                                    "normals"], _rows(fields, nrm), chunk=16)
    want = np.dtype("u2") if big <= 65535 else np.dtype("u4")
    for path in (mem, til):
        back = laspy.read(str(path))
        assert back.point_format.dimension_by_name("neighbours").dtype == want
        assert back.point_format.dimension_by_name("status").dtype == np.dtype("u1")
        np.testing.assert_array_equal(np.asarray(back["neighbours"], np.int64), counts)
        # bytes per record: format 6 (30) + 3 normals + 1 curvature (float32) + count + status
        assert back.header.point_format.size == 30 + 4 * 4 + want.itemsize + 1
    assert mem.read_bytes() == til.read_bytes()


def test_extra_bytes_statistics_of_every_point_whatever_the_chunks(tmp_path):
    """Each descriptor's min and max are those of all points (NaN left out), written at once
    or 16 points at a time (laspy's own would take each chunk's first point)."""
    src = _make_las(tmp_path / "in.las")
    fields, nrm = _fields(np.arange(N) + 3), _normals(N)
    fields["mean_curvature"][[0, 5]] = np.nan
    cloud = io.read(src)
    mem = io.write(tmp_path / "mem.las", cloud.points, fields, normals=nrm, like=cloud)
    til = tmp_path / "til.las"
    stream.write_las(til, stream.open_source(src), ["mean_curvature", "neighbours", "status",
                                                    "normals"], _rows(fields, nrm), chunk=16)
    assert mem.read_bytes() == til.read_bytes()
    eb = {s.format_name(): s for s in
          laspy.read(str(mem)).header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs}
    h = fields["mean_curvature"].astype(np.float32)
    assert eb["mean_curvature"].min[0] == np.nanmin(h)
    assert eb["mean_curvature"].max[0] == np.nanmax(h)
    assert (eb["neighbours"].min[0], eb["neighbours"].max[0]) == (3, N + 2)
    assert (eb["status"].min[0], eb["status"].max[0]) == (0, 3)
    assert eb["nz"].max[0] == nrm[:, 2].astype(np.float32).max()


def test_counts_beyond_uint32_or_negative_are_refused(tmp_path):
    src = _make_las(tmp_path / "in.las")
    cloud = io.read(src)
    for bad, what in ((2**32, "beyond"), (-1, "negative")):
        counts = np.arange(N, dtype=np.int64)
        counts[7] = bad
        with pytest.raises(WriteError, match=what):
            io.write(tmp_path / "x.las", cloud.points, {"neighbours": counts}, like=cloud)
    with pytest.raises(WriteError, match="negative"):
        counts = np.arange(N, dtype=np.int32)
        counts[-1] = -5
        stream.write_las(tmp_path / "y.las", stream.open_source(src), ["neighbours"],
                         _rows({"mean_curvature": np.zeros(N), "neighbours": counts,
                                "status": np.zeros(N, np.uint8)}, _normals(N)), chunk=16)


def test_count_dtype_rule():
    assert cl_las.count_dtype("p", "neighbours", np.array([0, 65535], np.int32)) == "u2"
    assert cl_las.count_dtype("p", "neighbours", np.array([65536], np.int64)) == "u4"
    assert cl_las.count_dtype("p", "neighbours", np.zeros(0, np.int32)) == "u2"
    # an array already of a count type keeps it (the tiled writer's choice)
    assert cl_las.count_dtype("p", "neighbours", np.array([1], np.uint32)) == "u4"


# --------------------------------------------------------------------------- quantised

R = 0.5


def _quantised_fields(n, seed=3):
    rng = np.random.default_rng(seed)
    f = {"mean_curvature": rng.normal(scale=2.0, size=n),
         "gaussian_curvature": rng.normal(scale=4.0, size=n),
         "surface_variation": rng.uniform(0, 1 / 3, size=n),
         "knn_radius": rng.uniform(0.1, 1, size=n),
         "neighbours": rng.integers(6, 300, size=n).astype(np.int32),
         "status": np.zeros(n, np.uint8)}
    f["mean_curvature"][[1, 9]] = np.nan
    f["surface_variation"][4] = np.nan
    f["gaussian_curvature"][[1, 50]] = np.nan
    return f


@pytest.mark.parametrize("ext", [".las"] + ([".laz"] if HAS_LAZ else []))
def test_quantised_extra_bytes_read_back_within_half_a_step(tmp_path, ext):
    """laspy reads each quantised field as raw * scale, within scale / 2 of the float64
    value; NaN is the descriptor's no_data; knn_radius and the counts are not quantised.
    The tiled writer (16 points at a time) writes the same bytes."""
    src = _make_las(tmp_path / "in.las")
    f, nrm = _quantised_fields(N), _normals(N)
    nrm[2] = np.nan
    cloud = io.read(src)
    mem = io.write(tmp_path / f"mem{ext}", cloud.points, f, normals=nrm, like=cloud,
                   quantize=R)
    back = laspy.read(str(mem))
    fmt = back.point_format
    want = {"nx": ("i2", 1e-4), "nz": ("i2", 1e-4), "mean_curvature": ("i4", 1e-4 / R),
            "gaussian_curvature": ("i4", 1e-4 / R**2), "surface_variation": ("u2", 1e-5)}
    eb = {s.format_name(): s for s in back.header.vlrs.get("ExtraBytesVlr")[0]
          .extra_bytes_structs}
    for name, (dt, step) in want.items():
        info = fmt.dimension_by_name(name)
        assert np.dtype(info.dtype) == np.dtype(dt), name
        assert info.scales[0] == pytest.approx(step, rel=1e-15) and info.offsets[0] == 0
        nd = np.iinfo(dt).min if dt[0] == "i" else np.iinfo(dt).max
        assert eb[name].no_data[0] == nd
        v = f[name] if name in f else nrm[:, "xyz".index(name[1])]
        exact = np.asarray(v, np.float64)
        got = np.asarray(back[name], np.float64)
        raw = np.asarray(back.points.array[name])
        ok = ~np.isnan(exact)
        assert np.abs(got[ok] - exact[ok]).max() <= step / 2 * (1 + 1e-9), name
        assert np.all(raw[~ok] == nd) and (~ok).sum() >= 1, name
    assert np.dtype(fmt.dimension_by_name("knn_radius").dtype) == np.float32
    assert fmt.dimension_by_name("knn_radius").scales is None
    assert np.dtype(fmt.dimension_by_name("neighbours").dtype) == np.uint16
    # bytes: format 6 (30) + 3 int16 + 2 int32 + uint16 + float32 + uint16 + uint8
    assert back.header.point_format.size == 30 + 6 + 8 + 2 + 4 + 2 + 1
    names = list(f) + ["normals"]
    dt = [(k, f[k].dtype) for k in f] + [("normals", "f8", (3,))]
    rec = np.empty(N, dt)
    for k in f:
        rec[k] = f[k]
    rec["normals"] = nrm
    til = tmp_path / f"til{ext}"
    stream.write_las(til, stream.open_source(src), names, lambda a, b: rec[a:b], chunk=16,
                     quantize=R)
    assert mem.read_bytes() == til.read_bytes()


def test_quantised_values_out_of_range_are_refused(tmp_path):
    src = _make_las(tmp_path / "in.las")
    cloud = io.read(src)
    top = (2**31 - 1) * 1e-4 / R                 # the largest int32 value at this step
    for bad in (top * 1.001, -np.inf, np.inf):
        h = np.zeros(N)
        h[5] = bad
        with pytest.raises(WriteError, match="quantised extra bytes cannot hold"):
            io.write(tmp_path / "x.las", cloud.points, {"mean_curvature": h}, like=cloud,
                     quantize=R)
    h = np.zeros(N)
    h[5] = top * 0.999                         # within the range: kept
    io.write(tmp_path / "x.las", cloud.points, {"mean_curvature": h}, like=cloud, quantize=R)
    assert np.asarray(laspy.read(str(tmp_path / "x.las"))["mean_curvature"], float)[5] == \
        pytest.approx(h[5], abs=1e-4 / R)
    with pytest.raises(WriteError, match="LAS/LAZ"):
        io.write(tmp_path / "x.ply", cloud.points, {"mean_curvature": h}, quantize=R)
