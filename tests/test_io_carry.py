"""What an output keeps of its input's attributes (clcurv.io.carry): colours, intensity,
labels and GPS time survive a PLY, NPZ or text output in their values (and PLY/NPZ
dtypes), a computed field replaces an attribute of its name, names PLY cannot hold are
mended, and an output written in tiles equals the in-memory one byte for byte."""
import warnings

import numpy as np
import pytest

import clcurv
import clcurv.io as cio
from clcurv.io.common import Cloud

plyfile = pytest.importorskip("plyfile")
laspy = pytest.importorskip("laspy")

N = 500


def _colored_ply(path, n=N, seed=0, normals=False):
    """A binary PLY with float xyz, uchar RGB, a double quality, an int label and a lone
    'nx' (no ny, nz: not normals)."""
    rng = np.random.default_rng(seed)
    spec = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if normals:
        spec += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    spec += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("quality", "f8"),
             ("label", "i4")]
    if not normals:
        spec += [("nx", "f4")]
    rec = np.zeros(n, spec)
    s = clcurv.shapes.torus(n, 2.0, 0.7, seed=seed)
    rec["x"], rec["y"], rec["z"] = s["points"].T
    if normals:
        rec["nx"], rec["ny"], rec["nz"] = s["normals"].T
    else:
        rec["nx"] = rng.random(n)
    rec["red"], rec["green"], rec["blue"] = rng.integers(0, 256, (3, n))
    rec["quality"] = rng.random(n) * np.pi * 1e6       # needs all 17 digits
    rec["label"] = rng.integers(-2**31, 2**31 - 1, n)
    plyfile.PlyData([plyfile.PlyElement.describe(rec, "vertex")]).write(str(path))
    return rec


def _ply_props(path):
    return [p.name for p in plyfile.PlyData.read(str(path))["vertex"].properties]


def test_ply_keeps_attributes_in_their_types(tmp_path):
    rec = _colored_ply(tmp_path / "in.ply")
    src = cio.read(tmp_path / "in.ply")
    k = np.linspace(-1, 1, N)
    cio.write(tmp_path / "o.ply", src.points, {"k": k, "quality": np.zeros(N)},
              normals=np.tile([0.0, 0.0, 1.0], (N, 1)), like=src)
    assert _ply_props(tmp_path / "o.ply") == ["x", "y", "z", "nx", "ny", "nz", "red",
                                              "green", "blue", "label", "nx_input", "k",
                                              "quality"]
    back = cio.read(tmp_path / "o.ply")
    for c in ("red", "green", "blue", "label"):
        assert back.attributes[c].dtype == rec[c].dtype
        np.testing.assert_array_equal(back.attributes[c], rec[c])
    np.testing.assert_array_equal(back.attributes["nx_input"], rec["nx"])   # lone nx kept
    np.testing.assert_array_equal(back.attributes["quality"], 0)   # the field replaced it
    np.testing.assert_array_equal(back.attributes["k"], k.astype(np.float32))
    np.testing.assert_array_equal(back.normals[:, 2], 1)


@pytest.mark.parametrize("ext", ["csv", "txt", "npz"])
def test_text_and_npz_keep_attributes_exactly(tmp_path, ext):
    rec = _colored_ply(tmp_path / "in.ply")
    src = cio.read(tmp_path / "in.ply")
    cio.write(tmp_path / f"o.{ext}", src.points, {"k": np.ones(N)}, like=src)
    back = cio.read(tmp_path / f"o.{ext}")
    np.testing.assert_array_equal(back.attributes["quality"], rec["quality"])  # %.17g
    np.testing.assert_array_equal(back.attributes["label"], rec["label"])
    np.testing.assert_array_equal(back.attributes["red"], rec["red"])
    if ext == "npz":
        assert back.attributes["red"].dtype == np.uint8
        np.testing.assert_array_equal(back.attributes["nx"], rec["nx"])   # no rename in NPZ
    else:                                     # float32 in 9 digits: exact back in float32
        np.testing.assert_array_equal(back.attributes["nx_input"].astype(np.float32),
                                      rec["nx"])


def test_like_normals_when_none_given(tmp_path):
    rec = _colored_ply(tmp_path / "in.ply", normals=True)
    src = cio.read(tmp_path / "in.ply")
    for ext in ("ply", "npz", "las"):
        cio.write(tmp_path / f"o.{ext}", src.points, {"k": np.ones(N)}, like=src)
        back = cio.read(tmp_path / f"o.{ext}")
        np.testing.assert_allclose(back.normals, np.column_stack(
            [rec["nx"], rec["ny"], rec["nz"]]), rtol=0, atol=1e-7)


def test_bad_like_is_an_error(tmp_path):
    _colored_ply(tmp_path / "in.ply")
    src = cio.read(tmp_path / "in.ply")
    for ext in ("ply", "npz", "csv", "las"):
        with pytest.raises(cio.WriteError, match="like= has 500 points but 499"):
            cio.write(tmp_path / f"o.{ext}", src.points[:-1], like=src)
        with pytest.raises(cio.WriteError, match="like= must be a Cloud"):
            cio.write(tmp_path / f"o.{ext}", src.points, like={"red": 1})
        assert not (tmp_path / f"o.{ext}").exists()
    bad = Cloud(src.points, None, {"red": np.zeros(N - 1)})
    for ext in ("ply", "npz", "csv"):
        with pytest.raises(cio.WriteError, match="one row per point"):
            cio.write(tmp_path / f"o.{ext}", src.points, like=bad)


def test_names_shapes_and_types_a_format_cannot_hold(tmp_path):
    pts = np.random.default_rng(1).random((N, 3))
    attrs = {"Amplitude Value": np.arange(N, dtype=np.float32),     # a LAS extra-bytes name
             "3d": np.ones(N, np.uint16),
             "rgba": np.arange(2 * N, dtype=np.uint8).reshape(N, 2),   # PCD COUNT 2
             "big": np.array([2**40] + [0] * (N - 1), np.int64),
             "small": np.arange(N, dtype=np.int64),
             "flag": np.arange(N) % 2 == 0,
             "name": np.array(["a"] * N)}
    like = Cloud(pts, None, attrs)
    with pytest.raises(cio.WriteError, match="'big'.*int32"), \
            pytest.warns(RuntimeWarning, match="left out"):
        cio.write(tmp_path / "o.ply", pts, like=like)
    del attrs["big"]
    with pytest.warns(RuntimeWarning, match=r"name \(<U1\).*left out"):
        cio.write(tmp_path / "o.ply", pts, like=like)
    assert _ply_props(tmp_path / "o.ply") == ["x", "y", "z", "Amplitude_Value", "_3d",
                                              "rgba_0", "rgba_1", "small", "flag"]
    back = cio.read(tmp_path / "o.ply").attributes
    np.testing.assert_array_equal(back["rgba_1"], attrs["rgba"][:, 1])
    assert back["small"].dtype == np.int32 and back["flag"].dtype == np.uint8
    np.testing.assert_array_equal(back["small"], attrs["small"])
    np.testing.assert_array_equal(back["flag"], attrs["flag"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")                        # NPZ holds every one of them
        cio.write(tmp_path / "o.npz", pts, like=like)
    z = np.load(tmp_path / "o.npz")
    np.testing.assert_array_equal(z["rgba"], attrs["rgba"])
    np.testing.assert_array_equal(z["name"], attrs["name"])


def _las_with_attributes(path, n=20_000, seed=4):
    s = clcurv.shapes.torus(n, 2.0, 0.7, seed=seed)
    rng = np.random.default_rng(seed)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [1e-4] * 3
    hdr.offsets = [-3.0, -3.0, -1.0]
    hdr.add_extra_dim(laspy.ExtraBytesParams(name="Amplitude Value", type=np.float32))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = s["points"].T
    las.classification = rng.integers(0, 20, n)
    las.intensity = rng.integers(0, 65536, n)
    las.gps_time = rng.random(n) * 1e9
    las.red = rng.integers(0, 65536, n)
    las["Amplitude Value"] = rng.random(n).astype(np.float32)
    las.write(str(path))
    return path


def _same_output(a, b):
    """Two outputs hold the same thing: PLY byte for byte; NPZ (whose ZIP entries carry a
    time stamp) the same members in the same order, dtypes and values."""
    if a.suffix == ".ply":
        assert a.read_bytes() == b.read_bytes()
        return
    za, zb = np.load(a), np.load(b)
    assert za.files == zb.files
    for k in za.files:
        assert za[k].dtype == zb[k].dtype, k
        np.testing.assert_array_equal(za[k], zb[k], err_msg=k)


@pytest.mark.parametrize("out", ["ply", "npz"])
def test_tiled_output_keeps_the_same_attributes(tmp_path, out):
    """LAS in, PLY or NPZ out: the tiled writer carries the LAS dimensions as the in-memory
    one does (the same names, dtypes, order and values; PLY byte for byte)."""
    src = _las_with_attributes(tmp_path / "in.las")
    for name, tile in (("mem", None), ("til", 1.5)):
        clcurv.curvature_file(src, tmp_path / f"{name}.{out}", 0.15, method="2dcov1",
                              tile=tile, memory="64GiB", fields=["k1"])
    _same_output(tmp_path / f"mem.{out}", tmp_path / f"til.{out}")
    back = cio.read(tmp_path / f"til.{out}")
    las = laspy.read(str(src))
    np.testing.assert_array_equal(back.attributes["gps_time"], las.gps_time)
    np.testing.assert_array_equal(back.attributes["intensity"], las.intensity)
    key = "Amplitude_Value" if out == "ply" else "Amplitude Value"
    np.testing.assert_array_equal(back.attributes[key], las["Amplitude Value"])
    assert "k1" in back.attributes and back.normals is None


def test_tiled_ply_in_ply_out_keeps_colours(tmp_path):
    """A coloured PLY with normals, fields without normals: the file's normals and colours
    go to the output, in tiles as in memory."""
    rec = _colored_ply(tmp_path / "in.ply", n=20_000, normals=True)
    for name, tile in (("mem", None), ("til", 1.5)):
        clcurv.curvature_file(tmp_path / "in.ply", tmp_path / f"{name}.ply", 0.15,
                              method="2dcov1", tile=tile, memory="64GiB",
                              fields=["k1"])
    assert (tmp_path / "mem.ply").read_bytes() == (tmp_path / "til.ply").read_bytes()
    back = cio.read(tmp_path / "til.ply")
    np.testing.assert_array_equal(back.attributes["red"], rec["red"])
    np.testing.assert_array_equal(back.normals[:, 0], rec["nx"])


def test_tiled_npy_columns_carried(tmp_path):
    s = clcurv.shapes.torus(20_000, 2.0, 0.7, seed=5)
    table = np.column_stack([s["points"], np.arange(20_000) * 0.25]).astype(np.float32)
    np.save(tmp_path / "in.npy", table)
    for name, tile in (("mem", None), ("til", 1.5)):
        clcurv.curvature_file(tmp_path / "in.npy", tmp_path / f"{name}.npz", 0.15,
                              method="2dcov1", tile=tile, memory="64GiB")
    _same_output(tmp_path / "mem.npz", tmp_path / "til.npz")
    z = np.load(tmp_path / "til.npz")
    assert z["col3"].dtype == np.float64                 # as clcurv.io.read has it
    np.testing.assert_array_equal(z["col3"], table[:, 3])


def test_cli_compute_keeps_colours_and_says_so(tmp_path):
    """`clcurv compute scan.ply -o out.ply` on a coloured scan: the colours come out as they
    went in, and the summary names what was kept."""
    import subprocess
    import sys
    rec = _colored_ply(tmp_path / "scan.ply", n=5000, normals=True)
    p = subprocess.run([sys.executable, "-m", "clcurv.cli.main", "compute", str(tmp_path / "scan.ply"),
                        "-o", str(tmp_path / "out.ply"), "--method", "mls2", "--radius", "0.3",
                        "-q"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "kept from the input: red, green, blue, quality, label" in p.stdout
    back = cio.read(tmp_path / "out.ply")
    for c in ("red", "green", "blue", "quality", "label"):
        np.testing.assert_array_equal(back.attributes[c], rec[c])
    assert np.isfinite(back.attributes["mean_curvature"]).mean() > 0.95


def test_las_output_from_another_format(tmp_path):
    """PLY in, LAS out: a fresh header of point format 7 whose RGB holds the 8-bit colours
    times 257, the other attributes as extra bytes in their types (names mended to LAS's 32
    characters, one named like a LAS dimension suffixed _input), the file's normals."""
    rec = _colored_ply(tmp_path / "in.ply", normals=True)
    src = cio.read(tmp_path / "in.ply")
    src.attributes["intensity"] = np.linspace(0, 1, N).astype(np.float32)   # PCL's float
    src.attributes["a name longer than thirty-two characters"] = np.arange(N, dtype=np.int64)
    cio.write(tmp_path / "o.las", src.points, {"k": np.ones(N)}, like=src)
    las = laspy.read(str(tmp_path / "o.las"))
    assert las.header.point_format.id == 7
    for c in ("red", "green", "blue"):
        np.testing.assert_array_equal(las[c], rec[c].astype(np.uint16) * 257)
    assert list(las.point_format.extra_dimension_names) == [
        "quality", "label", "intensity_input", "a_name_longer_than_thirty-two_ch", "nx", "ny",
        "nz", "k"]
    np.testing.assert_array_equal(las["quality"], rec["quality"])              # float64 kept
    np.testing.assert_array_equal(las["label"], rec["label"])
    np.testing.assert_array_equal(las["intensity_input"], src.attributes["intensity"])
    np.testing.assert_array_equal(las.intensity, 0)
    assert las["a_name_longer_than_thirty-two_ch"].dtype == np.int64
    np.testing.assert_allclose(np.column_stack([las["nx"], las["ny"], las["nz"]]),
                               src.normals, atol=1e-7)
    assert cio.kept_attributes(tmp_path / "o.las", src, ["k"]) == [
        "red", "green", "blue", "quality", "label", "intensity",
        "a name longer than thirty-two characters"]
    # without a colour triple: point format 6; float colours stay extra bytes
    plain = Cloud(src.points, None, {"red": np.ones(N), "green": np.ones(N),
                                     "blue": np.ones(N)})
    cio.write(tmp_path / "p.las", src.points, like=plain)
    las = laspy.read(str(tmp_path / "p.las"))
    assert las.header.point_format.id == 6
    assert list(las.point_format.extra_dimension_names) == ["red", "green", "blue"]


def test_tiled_features_of_a_ply_with_normals(tmp_path):
    """clcurv.features_file in tiles on a PLY with normals and colours (the tiled run read
    FeatureParams.ignore_normals, which did not exist: AttributeError): byte for byte the
    in-memory output, colours and the file's normals kept."""
    rec = _colored_ply(tmp_path / "in.ply", n=20_000, normals=True)
    clcurv.features_file(tmp_path / "in.ply", tmp_path / "mem.ply", [0.15, 0.3],
                         memory="64GiB")
    s = clcurv.features_file(tmp_path / "in.ply", tmp_path / "til.ply", [0.15, 0.3],
                             tile=1.5, memory="64GiB")
    assert s["tiled"] and s["tiles"] > 1
    assert (tmp_path / "mem.ply").read_bytes() == (tmp_path / "til.ply").read_bytes()
    back = cio.read(tmp_path / "til.ply")
    np.testing.assert_array_equal(back.attributes["blue"], rec["blue"])
    np.testing.assert_array_equal(back.normals[:, 2], rec["nz"])
    assert np.isfinite(back.attributes["planarity_r0.3"]).mean() > 0.99
