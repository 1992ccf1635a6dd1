"""Hostile LAS/LAZ input (issue 10): crafted headers are refused with one CorruptFileError
naming what the header claims and what the file holds, never a hang, a MemoryError or a
silently partial read; LAS output from non-LAS input gets a header scaled to the extent.

Every crafted file starts from a valid file written by :func:`clcurv.io.write` and has
header bytes patched with ``struct`` (offsets of the LAS 1.4 public header block). Reads
that could hang or allocate without bound run in a child process limited to 2 GiB of
address space and 10 s, so a regression fails instead of stalling the suite.
"""
import json
import math
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
    scale = float(header.scales[0])
    assert scale == cl.scale_for_extent(np.ptp(pts, axis=0).max())
    assert np.abs(back.points - pts).max() <= scale / 2 * (1 + 1e-6)
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
    scale = cl.scale_for_extent(np.ptp(pts, axis=0).max())
    assert np.all(header.scales == scale)
    err = np.abs(cio.read(path).points - pts).max()
    assert err <= scale / 2 + 4 * np.spacing(abs(offset) + extent), (err, scale)
