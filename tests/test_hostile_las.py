"""Hostile LAS/LAZ input (issue 10): crafted headers are refused with one CorruptFileError
naming what the header claims and what the file holds, never a hang, a MemoryError or a
silently partial read; LAS output from non-LAS input gets a header scaled per axis to its
extent (issue 47: one far point no longer collapses the other axes; a precision LAS cannot
keep is a LasPrecisionWarning); an input dimension named like an output field is replaced
(extra bytes) or must hold the values (standard dimensions), the same in memory and in
tiles (issue 47: it was quantised, NaN written as 0 or a traceback).

Every crafted file starts from a valid file written by :func:`clcurv.io.write` and has
header bytes patched with ``struct`` (offsets of the LAS 1.4 public header block). Reads
that could hang or allocate without bound run in a child process limited to 2 GiB of
address space and 10 s, so a regression fails instead of stalling the suite.
"""
import json
import math
import re
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest

from clcurv import io as cio
from clcurv.io import las as cl

from hostile import assert_clean_failure, run_cli

laspy = pytest.importorskip("laspy", reason="laspy not installed")
HAS_LAZ = bool(laspy.LazBackend.detect_available())
needs_laz = pytest.mark.skipif(not HAS_LAZ, reason='no LAZ backend (pip install "laspy[lazrs]")')

# public header block offsets (LAS 1.4)
OFFSET_TO_POINTS, NUMBER_OF_VLRS, POINT_FORMAT, RECORD_LENGTH = 96, 100, 104, 105
LEGACY_COUNT, SCALES, OFFSETS, COUNT_64 = 107, 131, 155, 247
VERSION_MINOR = 25

N = 300
CHILD_LIMIT_BYTES = 2 << 30
CHILD_SECONDS = 10.0

_CHILD = """
import json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))
from clcurv import io
try:
    cloud = io.read(sys.argv[1])
    print(json.dumps({{"points": len(cloud.points)}}))
except BaseException as exc:
    print(json.dumps({{"type": type(exc).__name__, "message": str(exc),
                      "corrupt": isinstance(exc, io.CorruptFileError)}}))
"""


def guarded_read(path):
    """``clcurv.io.read(path)`` in a child with 2 GiB of address space and 10 s: a dict with
    ``points`` (the number read) or ``type``, ``message`` and ``corrupt``."""
    try:
        p = subprocess.run([sys.executable, "-c", _CHILD.format(limit=CHILD_LIMIT_BYTES),
                            str(path)], capture_output=True, text=True, timeout=CHILD_SECONDS)
    except subprocess.TimeoutExpired:
        pytest.fail(f"reading {path} still running after {CHILD_SECONDS} s")
    assert p.returncode == 0 and p.stdout.strip(), p.stderr[-2000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def assert_corrupt(path, *words):
    """Reading ``path`` raises CorruptFileError whose message starts with the path and
    contains each of ``words`` (the claimed value, what the file has)."""
    got = guarded_read(path)
    assert got.get("corrupt"), got
    msg = got["message"]
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg, msg
    for w in words:
        assert str(w) in msg, (w, msg)
    return msg


def make_points(n=N, seed=0):
    return np.random.default_rng(seed).normal(scale=10.0, size=(n, 3)) + [500.0, -20.0, 3.0]


def valid_file(tmp_path, name="a.las"):
    """A valid LAS 1.4 file of N points with one VLR (the extra-bytes description of k)."""
    path = cio.write(tmp_path / name, make_points(), {"k": np.arange(N, dtype=np.float64)})
    return path, bytearray(path.read_bytes())


def patched(tmp_path, name, data, **fields):
    """A copy of ``data`` with header fields replaced: field=(format, value)."""
    data = bytearray(data)
    for at, (fmt, value) in fields.items():
        struct.pack_into("<" + fmt, data, globals()[at.upper()], *np.atleast_1d(value))
    path = tmp_path / name
    path.write_bytes(bytes(data))
    return path


def header_info(data):
    hs, off, nvlr = struct.unpack_from("<HII", data, 94)
    return hs, off, nvlr, len(data)


# --------------------------------------------------------------- crafted files, one per defect

def craft(tmp_path, kind):
    """The crafted file for ``kind`` and the words its error message must contain."""
    _, data = valid_file(tmp_path)
    hs, off, nvlr, size = header_info(data)
    if kind == "vlr_count":
        return patched(tmp_path, "vlrs.las", data, number_of_vlrs=("I", 0x0FFFFFFF)), \
            [0x0FFFFFFF, off]
    if kind == "count_1e8":
        return patched(tmp_path, "big.las", data, count_64=("Q", 10**8)), [10**8, size]
    if kind == "count_u32max":
        return patched(tmp_path, "huge.las", data, count_64=("Q", 0xFFFFFFFF),
                       legacy_count=("I", 0xFFFFFFFF)), [0xFFFFFFFF, size]
    if kind == "count_plus_one":
        return patched(tmp_path, "plus1.las", data, count_64=("Q", N + 1)), [N + 1, N]
    if kind == "offset_past_end":
        return patched(tmp_path, "off.las", data, offset_to_points=("I", size + 1000)), \
            [size + 1000, size]
    if kind in ("scale_nan", "scale_zero", "scale_inf", "offset_inf"):
        value = {"scale_nan": math.nan, "scale_zero": 0.0, "scale_inf": math.inf,
                 "offset_inf": math.inf}[kind]
        at = "offsets" if kind == "offset_inf" else "scales"
        return patched(tmp_path, f"{kind}.las", data, **{at: ("3d", [1e-3, value, 1e-3])}), \
            [at[:-1], {math.nan: "nan", 0.0: "0.0", math.inf: "inf"}[value]]
    if kind == "format_unknown":
        return patched(tmp_path, "fmt.las", data, point_format=("B", 13)), ["13"]
    if kind == "record_short":
        return patched(tmp_path, "rec.las", data, record_length=("H", 20)), \
            ["20", "30", "format 6"]
    if kind == "truncated_in_vlrs":
        assert nvlr == 1 and off > hs + 54
        path = tmp_path / "trunc.las"
        path.write_bytes(bytes(data[:hs + 60]))
        return path, [off, hs + 60]
    if kind == "legacy_disagrees":
        return patched(tmp_path, "legacy.las", data, legacy_count=("I", N - 7)), [N - 7, N]
    if kind == "version":
        return patched(tmp_path, "version.las", data, version_minor=("B", 9)), ["1.9"]
    if kind == "laz_count_1e8":
        src = cio.write(tmp_path / "a.laz", make_points())
        return patched(tmp_path, "big.laz", src.read_bytes(), count_64=("Q", 10**8)), \
            [10**8]
    if kind == "laz_count_plus_one":
        src = cio.write(tmp_path / "a.laz", make_points())
        return patched(tmp_path, "plus1.laz", src.read_bytes(), count_64=("Q", N + 1)), \
            [N + 1, N]
    if kind == "laz_truncated":
        src = cio.write(tmp_path / "a.laz", make_points())
        data = src.read_bytes()
        path = tmp_path / "cut.laz"
        path.write_bytes(data[:len(data) * 2 // 3])
        return path, [len(data) * 2 // 3, "chunk table"]
    raise AssertionError(kind)


LAS_KINDS = ["vlr_count", "count_1e8", "count_u32max", "count_plus_one", "offset_past_end",
             "scale_nan", "scale_zero", "scale_inf", "offset_inf", "format_unknown",
             "record_short", "truncated_in_vlrs", "legacy_disagrees", "version"]
LAZ_KINDS = ["laz_count_1e8", "laz_count_plus_one", "laz_truncated"]
ALL_KINDS = LAS_KINDS + [pytest.param(k, marks=needs_laz) for k in LAZ_KINDS]


def test_vlr_count_is_checked_against_the_space_before_the_points(tmp_path):
    path, words = craft(tmp_path, "vlr_count")
    msg = assert_corrupt(path, *words)
    assert "VLR" in msg


@pytest.mark.parametrize("kind", ["count_1e8", "count_u32max", "count_plus_one"])
def test_point_count_is_checked_against_the_file_size(tmp_path, kind):
    path, words = craft(tmp_path, kind)
    assert_corrupt(path, *words)


@pytest.mark.parametrize("kind,extra", [
    ("offset_past_end", ()), ("scale_nan", ()), ("scale_zero", ()), ("scale_inf", ()),
    ("offset_inf", ()), ("format_unknown", ("point format",)), ("record_short", ()),
    ("truncated_in_vlrs", ()), ("legacy_disagrees", ()), ("version", ())])
def test_corrupt_header_fields(tmp_path, kind, extra):
    """Offsets past the end, non-finite or zero scales and offsets, an unknown point
    format, a record shorter than its format, VLRs cut short, 1.4 counts that disagree, an
    unknown version: one CorruptFileError naming the claimed value."""
    path, words = craft(tmp_path, kind)
    assert_corrupt(path, *words, *extra)


@needs_laz
def test_laz_count_bounded_by_the_chunk_table(tmp_path):
    path, words = craft(tmp_path, "laz_count_1e8")
    msg = assert_corrupt(path, *words)
    assert "chunk" in msg


@needs_laz
def test_truncated_laz(tmp_path):
    path, words = craft(tmp_path, "laz_truncated")
    assert_corrupt(path, *words)


@needs_laz
def test_laz_count_larger_than_the_data_is_not_a_partial_read(tmp_path):
    path, words = craft(tmp_path, "laz_count_plus_one")
    assert_corrupt(path, *words)


def test_header_claiming_zero_points_is_an_empty_cloud(tmp_path):
    _, data = valid_file(tmp_path)
    path = patched(tmp_path, "zero.las", data, count_64=("Q", 0))
    cloud = cio.read(path)
    assert cloud.points.shape == (0, 3)


def test_legacy_count_equal_to_the_64bit_count_is_fine(tmp_path):
    _, data = valid_file(tmp_path)
    path = patched(tmp_path, "legacy_ok.las", data, legacy_count=("I", N))
    assert len(cio.read(path)) == N


@needs_laz
@pytest.mark.parametrize("written,named", [(".laz", ".las"), (".las", ".laz")])
def test_content_decides_compression_not_the_extension(tmp_path, written, named):
    pts = make_points()
    src = cio.write(tmp_path / f"src{written}", pts)
    path = tmp_path / f"renamed{named}"
    shutil.copyfile(src, path)
    got = cio.read(path)
    assert np.array_equal(got.points, cio.read(src).points)
    assert got.format == written[1:]


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_cli_fails_cleanly_on_crafted_las(tmp_path, kind):
    path, _ = craft(tmp_path, kind)
    outcome = run_cli("compute", path, "-o", tmp_path / "o.ply", "-q", timeout=30)
    assert_clean_failure(outcome, what=kind)


# --------------------------------------------------------------- LAS output from other input

def _sphere(n=400):
    rng = np.random.default_rng(3)
    v = rng.normal(size=(n, 3))
    return 2.0 * v / np.linalg.norm(v, axis=1, keepdims=True) + [1000.0, 2000.0, 50.0]


def write_input(path, pts):
    """``pts`` as a PCD (ASCII, written here), NPY (``np.save``) or what clcurv writes."""
    if path.suffix == ".pcd":
        head = ["VERSION .7", "FIELDS x y z", "SIZE 8 8 8", "TYPE F F F", "COUNT 1 1 1",
                f"WIDTH {len(pts)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0",
                f"POINTS {len(pts)}", "DATA ascii"]
        path.write_text("\n".join(head + [" ".join(map(repr, p)) for p in pts.tolist()]) + "\n")
        return path
    if path.suffix == ".npy":
        np.save(path, pts)
        return path
    return cio.write(path, pts)


@pytest.mark.parametrize("src_ext,out_ext", [
    (".pcd", ".las"), (".ply", ".las"),
    pytest.param(".npy", ".laz", marks=needs_laz)])
def test_cli_writes_las_from_other_formats(tmp_path, src_ext, out_ext):
    pts = _sphere()
    src = write_input(tmp_path / f"in{src_ext}", pts)
    out = tmp_path / f"out{out_ext}"
    outcome = run_cli("compute", src, "-o", out, "--radius", "0.8", "-q")
    assert outcome.code == 0, outcome.stderr[-2000:]
    back = cio.read(out)
    header = laspy.read(str(out)).header
    scales = np.asarray(header.scales)
    assert list(scales) == [cl.scale_for_extent(e) for e in np.ptp(pts, axis=0)]
    assert np.all(np.abs(back.points - pts) <= scales / 2 * (1 + 1e-6))
    assert "mean_curvature" in back.attributes and back.normals is not None


def test_like_from_another_format_is_ignored_and_a_non_cloud_is_refused(tmp_path):
    pts = _sphere(50)
    ply = cio.read(cio.write(tmp_path / "a.ply", pts))
    path = cio.write(tmp_path / "b.las", pts, like=ply)
    assert np.abs(cio.read(path).points - pts).max() <= cl.scale_for_extent(4.0)
    with pytest.raises(cio.WriteError, match="like="):
        cio.write(tmp_path / "c.las", pts, like={"header": None})


def test_scale_rule_on_a_huge_utm_extent():
    # UTM-like: easting 1e6 m, spanning 1e5 m
    s = cl.scale_for_extent(1e5)
    assert s == 1e-4
    assert 1e5 / s < 2**30 and 1e5 / (s / 10) >= 2**30  # the finest power of ten that fits


def test_scale_rule_on_a_tiny_extent():
    s = cl.scale_for_extent(1e-3)
    assert s == 1e-12
    assert 1e-3 / s < 2**30 and 1e-3 / (s / 10) >= 2**30


def test_scale_rule_degenerate_extent():
    assert cl.scale_for_extent(0.0) == 1e-3
    with pytest.raises(ValueError):
        cl.scale_for_extent(math.inf)


@pytest.mark.parametrize("offset,extent", [(1e6, 1e5), (0.0, 1e-3), (-3e5, 7.0)])
def test_round_trip_within_the_chosen_scale(tmp_path, offset, extent):
    rng = np.random.default_rng(4)
    pts = offset + extent * rng.random(size=(1000, 3))
    path = cio.write(tmp_path / "r.las", pts)
    header = laspy.read(str(path)).header
    scales = np.array([cl.scale_for_extent(e) for e in np.ptp(pts, axis=0)])
    assert np.array_equal(header.scales, scales)
    assert np.array_equal(header.offsets, pts.min(axis=0))
    err = np.abs(cio.read(path).points - pts).max(axis=0)
    assert np.all(err <= scales / 2 + 4 * np.spacing(abs(offset) + extent)), (err, scales)


# --------------------------------------------- a fresh header: one scale and offset per axis

def _far(pts, axis, distance):
    """``pts`` and one more point ``distance`` away from the first along ``axis``."""
    far = pts[0].copy()
    far[axis] += distance
    return np.vstack([pts, far])


def _written(path, pts):
    """(the points read back, the header, the LasPrecisionWarnings) of ``pts`` written to
    ``path`` without like=."""
    import warnings
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cio.write(path, pts)
    header = laspy.read(str(path)).header
    precision = [w for w in caught if issubclass(w.category, cl.LasPrecisionWarning)]
    return cio.read(path).points, header, precision


@pytest.mark.parametrize("axis,distance", [(0, 1e7), (1, -3e6), (2, 5e5), (0, 1e4)])
def test_a_far_point_does_not_collapse_the_other_axes(tmp_path, axis, distance):
    """A point far away along one axis: the two other axes keep the precision of their own
    extent (they took the scale of the largest extent: 1e7 away made every z one of 3
    values); the far axis is kept within half its own scale, and a LasPrecisionWarning
    names it when that scale is coarser than 1e-6 of the extent of the other points."""
    pts = _far(_sphere(), axis, distance)
    back, header, precision = _written(tmp_path / "far.las", pts)
    scales = np.asarray(header.scales)
    expect = np.array([cl.scale_for_extent(e) for e in np.ptp(pts, axis=0)])
    assert np.array_equal(scales, expect)
    assert np.array_equal(header.offsets, pts.min(axis=0))
    err = np.abs(back - pts).max(axis=0)
    assert np.all(err <= scales / 2 + 4 * np.spacing(np.abs(pts).max(axis=0))), (err, scales)
    for other in set(range(3)) - {axis}:
        assert scales[other] <= 1e-8                  # the sphere's own 4-unit extent
        assert err[other] <= 5e-9
        assert len(np.unique(back[:-1, other])) == len(np.unique(pts[:-1, other]))
    far_scale_is_coarse = expect[axis] > cl.PRECISION * 4.0
    assert len(precision) == int(far_scale_is_coarse), [str(w.message) for w in precision]
    if precision:
        msg = str(precision[0].message)
        assert msg.startswith(str(tmp_path / "far.las")) and f"{'xyz'[axis]} spans" in msg
        assert f"{expect[axis]:g}" in msg and "PLY or NPZ" in msg


def test_no_precision_warning_without_far_points(tmp_path):
    """An ordinary cloud, UTM-like or tiny, a flat one (z constant), a line: no warning,
    every axis within half its own scale."""
    rng = np.random.default_rng(7)
    utm = rng.random((2000, 3)) * [800.0, 600.0, 40.0] + [481200.0, 4390100.0, 12.0]
    tiny = rng.random((2000, 3)) * 1e-3
    flat = utm.copy()
    flat[:, 2] = 101.25
    line = np.column_stack([np.linspace(0, 1e4, 2000), np.zeros(2000), np.full(2000, 3.0)])
    for name, pts in (("utm", utm), ("tiny", tiny), ("flat", flat), ("line", line)):
        back, header, precision = _written(tmp_path / f"{name}.las", pts)
        assert precision == [], (name, [str(w.message) for w in precision])
        scales = np.asarray(header.scales)
        assert np.all(np.abs(back - pts) <= scales / 2 + 4 * np.spacing(np.abs(pts).max())), \
            name
    assert np.all(cio.read(tmp_path / "flat.las").points[:, 2] == 101.25)


def test_a_precision_int32_cannot_keep_is_a_warning_naming_the_axes(tmp_path):
    """A far "no data" point at (0, 0, 0) beside a UTM-like survey: x and y span millions of
    metres, so their scales are coarser than 1e-6 of the survey's extent (warned, each
    named); z keeps its own precision."""
    rng = np.random.default_rng(8)
    pts = np.vstack([rng.random((3000, 3)) * [90.0, 70.0, 8.0] + [481200.0, 4390100.0, 310.0],
                     [[0.0, 0.0, 0.0]]])
    back, header, precision = _written(tmp_path / "nodata.las", pts)
    warned = sorted(re.search(r"integers: (\w) spans", str(w.message)).group(1)
                    for w in precision)
    assert warned == ["x", "y"], [str(w.message) for w in precision]
    scales = np.asarray(header.scales)
    assert scales[2] == cl.scale_for_extent(np.ptp(pts[:, 2]))
    assert np.abs(back[:, 2] - pts[:, 2]).max() <= scales[2] / 2 + 1e-12


def test_the_command_warns_once_per_coarse_axis(tmp_path):
    pts = _far(_sphere(), 0, 1e7)
    src = write_input(tmp_path / "far.ply", pts)
    out = tmp_path / "far.las"
    outcome = run_cli("compute", src, "-o", out, "--radius", "0.8", "-q")
    assert outcome.code == 0, outcome.stderr[-2000:]
    warnings = [ln for ln in outcome.lines if "32-bit integers" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("clcurv: warning: ")
    assert "x spans" in warnings[0], warnings
    back = cio.read(out)
    assert np.abs(back.points[:, 2] - pts[:, 2]).max() <= 5e-9


# --------------------------------- an input dimension named like an output field (issue 47)

R_CLASH = 1.0
SCALE_CLASH = 2.0 ** -7


def _clash_input(path, extra, fmt=6, values=None):
    """A LAS/LAZ of an aerial scene (point format ``fmt``) with the extra-bytes dimensions
    ``extra`` (ExtraBytesParams), each filled with ``values(name, n)`` or 0.5."""
    import clcurv
    s = clcurv.shapes.aerial_scene(4000, extent=(25.3, 21.9), seed=2)
    pts = np.round(s["points"] / SCALE_CLASH) * SCALE_CLASH
    header = laspy.LasHeader(point_format=fmt, version="1.4")
    header.scales, header.offsets = [SCALE_CLASH] * 3, np.floor(pts.min(axis=0))
    if extra:
        header.add_extra_dims(extra)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.classification = s["kind"]
    for p in extra:
        shape = (len(pts),) + p.type.shape
        las[p.name] = values(p.name, shape) if values else np.full(shape, 0.5)
    las.write(str(path))
    return path


def _scaled(name, dtype, scale, offset=0.0):
    return laspy.ExtraBytesParams(name, dtype, scales=np.array([scale]),
                                  offsets=np.array([offset]))


CLASHES = {
    "scaled_i4": [_scaled("mean_curvature", "i4", 0.01)],
    "scaled_u2_offset": [_scaled("mean_curvature", "u2", 0.001, -30.0)],
    "unscaled_i2": [laspy.ExtraBytesParams("mean_curvature", "i2")],
    "float64": [laspy.ExtraBytesParams("mean_curvature", "f8")],
    "array_3f4": [laspy.ExtraBytesParams("mean_curvature", "3f4")],
    "u1_neighbours": [laspy.ExtraBytesParams("neighbours", "u1")],
    "scaled_normals": [_scaled(k, "i2", 1e-4) for k in ("nx", "ny", "nz")],
    "several": [_scaled("mean_curvature", "i2", 0.01), laspy.ExtraBytesParams("keep_me", "f4"),
                laspy.ExtraBytesParams("surface_variation", "u1")],
}


def _dims(path):
    las = laspy.read(str(path))
    return las, {n: np.asarray(las[n]) for n in las.point_format.dimension_names}


@needs_laz
@pytest.mark.parametrize("case", list(CLASHES))
def test_a_clashing_extra_dimension_is_replaced_in_memory_and_in_tiles(tmp_path, case):
    """An extra-bytes dimension of the input named like an output field is replaced by the
    field's own float32 (or integer) dimension: NaN stays NaN and nothing is quantised.
    The in-memory and tiled outputs are the same, and equal the run on the same input
    without the clashing dimensions (the other dimensions, ``keep_me``, kept)."""
    from clcurv.jobs.job import curvature_file
    params = CLASHES[case]
    src = _clash_input(tmp_path / "in.laz", params)
    plain = _clash_input(tmp_path / "plain.laz",
                         [p for p in params if p.name == "keep_me"])
    fields = ["normals", "mean_curvature", "surface_variation", "neighbours", "status"]
    outs = {}
    for name, inp, tile in (("mem", src, None), ("til", src, 7.0), ("ref", plain, None)):
        outs[name] = tmp_path / f"{name}.laz"
        curvature_file(inp, outs[name], R_CLASH, method="mls1", fields=fields,
                       orient="up", ignore_normals=True, tile=tile, memory="64GiB")
    las, mem = _dims(outs["mem"])
    _, til = _dims(outs["til"])
    _, ref = _dims(outs["ref"])
    assert list(mem) == list(til)
    assert [n for n in mem if not np.array_equal(mem[n], til[n], equal_nan=True)] == []
    assert sorted(mem) == sorted(ref)
    for n in ref:
        assert np.array_equal(mem[n], ref[n], equal_nan=True), n
    h = mem["mean_curvature"]
    assert h.dtype == np.float32 and np.isnan(h).any() and (mem["status"] != 0).any()
    assert np.array_equal(np.isnan(h), mem["status"] != 0)
    assert len(np.unique(h[np.isfinite(h)])) > 0.5 * np.isfinite(h).sum()   # not quantised
    extra = {d.name: d for d in las.point_format.extra_dimensions}
    for name in ("nx", "mean_curvature", "surface_variation"):
        assert extra[name].scales is None and np.dtype(extra[name].dtype) == np.float32, name
    assert all(mem[n].dtype == ref[n].dtype for n in ref)


@needs_laz
def test_the_input_normals_are_kept_as_stored_when_no_normals_are_written(tmp_path):
    """Input normals in scaled int16 extra bytes, no ``normals`` field: the output keeps
    the input's dimensions and their raw values, in memory and in tiles."""
    from clcurv.jobs.job import curvature_file
    rng = np.random.default_rng(3)

    def values(name, shape):
        return np.round(rng.uniform(-1, 1, size=shape) / 1e-4) * 1e-4

    params = [_scaled(k, "i2", 1e-4) for k in ("nx", "ny", "nz")]
    src = _clash_input(tmp_path / "in.laz", params, values=values)
    outs = []
    for tile in (None, 7.0):
        out = tmp_path / f"o{tile}.laz"
        curvature_file(src, out, R_CLASH, method="mls1", orient="up",
                       fields=["mean_curvature"], tile=tile, memory="64GiB")
        outs.append(out)
    a, da = _dims(outs[0])
    _, db = _dims(outs[1])
    inp = laspy.read(str(src))
    for k in ("nx", "ny", "nz"):
        assert a.point_format.dimension_by_name(k).scales is not None
        assert np.array_equal(a.points.array[k], inp.points.array[k]), k
        assert np.array_equal(da[k], db[k]), k


@pytest.mark.parametrize("fmt,name,values,ok", [
    (1, "classification", np.full(N, 2.0), True),             # 5-bit field, integral float
    (1, "classification", np.full(N, 40), False),             # over 31
    (1, "classification", np.r_[np.nan, np.full(N - 1, 2.0)], False),
    (6, "classification", np.full(N, 2.5), False),            # uint8, a fraction
    (6, "return_number", np.full(N, 2.5), False),             # 4-bit field, a fraction
    (6, "return_number", np.full(N, 15), True),
    (6, "intensity", np.full(N, 70000), False),
    (6, "gps_time", np.r_[np.nan, np.linspace(0, 1, N - 1)], True),   # float64 holds it
])
def test_a_field_in_a_standard_dimension_must_fit_it(tmp_path, fmt, name, values, ok):
    """A field named like a standard dimension of the input's point format is stored in it
    when the dimension holds every value exactly, else a WriteError naming the dimension
    (never a TypeError, a wrapped integer or NaN written as 0); clcurv.io.write and the
    tiled writer (clcurv.io.stream.write_las) alike."""
    from clcurv.io import stream
    header = laspy.LasHeader(point_format=fmt, version="1.4" if fmt >= 6 else "1.2")
    header.scales, header.offsets = [1e-3] * 3, [0, 0, 0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = make_points().T
    las.write(str(tmp_path / "in.las"))
    like = cio.read(tmp_path / "in.las")
    rec = np.empty(N, [(name, np.asarray(values).dtype)])
    rec[name] = values
    writers = {
        "io.write": lambda out: cio.write(out, like.points, {name: values}, like=like),
        "stream": lambda out: stream.write_las(out, stream.open_source(tmp_path / "in.las"),
                                               [name], lambda a, b: rec[a:b], chunk=128),
    }
    for kind, write in writers.items():
        out = tmp_path / f"{kind}.las"
        if ok:
            write(out)
            got = np.asarray(laspy.read(str(out))[name])
            assert np.array_equal(got, np.asarray(values).astype(got.dtype), equal_nan=True)
        else:
            with pytest.raises(cio.WriteError, match=f"dimension '{name}'.*cannot hold"):
                write(out)
