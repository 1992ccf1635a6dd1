"""clcurv.io: reading every shared data file, round trips for every format, and clear errors.

The shared files (../shared/data, made outside the project) are skipped, with the reason,
when absent; LAZ tests are skipped when laspy has no LAZ backend.
"""
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from clcurv import io as cio
from conftest import data_params, data_path
from hostile import lzf_literals

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MILK = "pcl_milk_cartoon_all_small_clorox"

# file: (finite points per the data README, normals in the file?, dropped)
FILES = {
    "pcl_bun0.pcd": (397, True, 0),
    "stanford_bun_zipper.ply": (35947, False, 0),
    "stanford_bun000.ply": (40256, False, 0),
    "stanford_bun045.ply": (40097, False, 0),
    "igea_cyberware.ply": (134345, False, 0),
    "laspy_autzen_trim.laz": (110000, False, 0),
    "laspy_simple.las": (1065, False, 0),
    f"{MILK}.pcd": (241407, False, 307200 - 241407),
    f"{MILK}.finite.xyz": (241407, False, 0),
    "cgal_jet_fitting_in_points_d4.txt": (17, False, 0),
}


def data_file(name):
    """The shared data file ``name``, or its copy shipped in tests/data (conftest.data_path);
    skips, naming it, when neither is there (the large scans are not shipped)."""
    path = data_path(name)
    if path is None:
        pytest.skip(f"{name} not present: ../shared/data is absent and the file is too large "
                    "to ship in tests/data")
    return path


def laspy_or_skip(laz=False):
    laspy = pytest.importorskip("laspy", reason="laspy not installed")
    if laz and not laspy.LazBackend.detect_available():
        pytest.skip('no LAZ backend for laspy (pip install "laspy[lazrs]")')
    return laspy


# ------------------------------------------------------------------ shared data files

@pytest.mark.parametrize("name", data_params(FILES))
def test_read_shared_file_counts(name):
    path = data_file(name)
    if path.suffix == ".laz":
        laspy_or_skip(laz=True)
    if path.suffix == ".las":
        laspy_or_skip()
    npts, has_normals, dropped = FILES[name]
    cloud = cio.read(path)
    assert cloud.points.shape == (npts, 3) and cloud.points.dtype == np.float64
    assert cloud.points.flags.c_contiguous and np.isfinite(cloud.points).all()
    assert (cloud.normals is not None) == has_normals
    assert cloud.dropped == dropped
    assert cloud.path == path and len(cloud) == npts
    for key, value in cloud.attributes.items():
        assert len(value) == npts, key


def test_pcl_bun0_normals_and_curvature():
    cloud = cio.read(data_file("pcl_bun0.pcd"))
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1, atol=1e-5)
    assert list(cloud.attributes) == ["curvature"]
    assert cloud.attributes["curvature"].dtype == np.float32
    assert cloud.points[0].tolist() == [np.float32(v) for v in (0.0054215998, 0.11349, 0.040748999)]
    assert cloud.header["data"] == "ascii" and cloud.header["width"] == 397


def test_milk_cartoon_equals_finite_xyz_in_order():
    pcd = cio.read(data_file(f"{MILK}.pcd"))
    xyz = cio.read(data_file(f"{MILK}.finite.xyz"))
    # the .xyz holds the float32 values written with %.9g: exact after a float32 cast
    assert np.array_equal(pcd.points, xyz.points.astype(np.float32).astype(np.float64))
    assert (pcd.header["width"], pcd.header["height"]) == (640, 480)
    assert pcd.header["data"] == "binary_compressed"
    assert set(pcd.attributes) == {"red", "green", "blue", "alpha"}
    assert all(a.dtype == np.uint8 for a in pcd.attributes.values())


def test_milk_cartoon_pure_python_lzf(monkeypatch):
    path = data_file(f"{MILK}.pcd")
    monkeypatch.setitem(sys.modules, "lzf", None)  # `import lzf` raises ImportError
    cloud = cio.read(path)
    assert len(cloud) == 241407 and cloud.dropped == 65793
    assert (cloud.header["width"], cloud.header["height"]) == (640, 480)
    monkeypatch.undo()
    assert np.array_equal(cloud.points, cio.read(path).points)


def test_lzf_python_matches_c_extension():
    lzf = pytest.importorskip("lzf", reason="python-lzf not installed")
    raw = data_file(f"{MILK}.pcd").read_bytes()
    pos = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    csize, usize = struct.unpack_from("<II", raw, pos)
    comp = raw[pos + 8:pos + 8 + csize]
    assert cio.pcd.lzf_decompress_py(comp, usize) == lzf.decompress(comp, usize)


def test_las_coordinates_equal_laspy_scaled_values():
    laspy = laspy_or_skip()
    path = data_file("laspy_simple.las")
    las = laspy.read(str(path))
    cloud = cio.read(path)
    assert np.array_equal(cloud.points[:, 0], np.asarray(las.x))
    assert np.array_equal(cloud.points[:, 1], np.asarray(las.y))
    assert np.array_equal(cloud.points[:, 2], np.asarray(las.z))
    assert np.array_equal(cloud.points[:, 0], las.X * las.header.scales[0] + las.header.offsets[0])
    assert np.array_equal(cloud.attributes["classification"], np.asarray(las.classification))
    assert np.array_equal(cloud.attributes["gps_time"], np.asarray(las.gps_time))
    assert isinstance(cloud.header, laspy.LasHeader) and cloud.format == "las"


def test_autzen_laz_classes_and_coordinates():
    laspy = laspy_or_skip(laz=True)
    path = data_file("laspy_autzen_trim.laz")
    cloud = cio.read(path)
    las = laspy.read(str(path))
    assert np.array_equal(cloud.points, np.column_stack([las.x, las.y, las.z]))
    classes, counts = np.unique(cloud.attributes["classification"], return_counts=True)
    assert dict(zip(classes.tolist(), counts.tolist())) == {1: 83893, 2: 26107}
    assert cloud.header.version == "1.2" and cloud.header.point_format.id == 3


def test_ply_mesh_vertex_properties():
    from plyfile import PlyData
    zipper = data_file("stanford_bun_zipper.ply")
    cloud = cio.read(zipper)
    assert set(cloud.attributes) == {"confidence", "intensity"}
    assert cloud.header["elements"] == {"vertex": 35947, "face": 69451}
    v = PlyData.read(str(zipper))["vertex"].data  # the slow, complete parse
    assert np.array_equal(cloud.points, np.column_stack([v["x"], v["y"], v["z"]]))
    assert np.array_equal(cloud.attributes["confidence"], v["confidence"])
    igea = data_file("igea_cyberware.ply")
    v = PlyData.read(str(igea))["vertex"].data
    cloud = cio.read(igea)
    assert np.array_equal(cloud.points, np.column_stack([v["x"], v["y"], v["z"]]))


def test_cgal_points_on_the_paraboloid(tmp_path):
    """clcurv reads CGAL's 17-point jet-fitting input (Jet_fitting_3's in_points_d4.txt:
    no header, bare ".2" decimals, no newline after the last row) as the text says: every
    row in order, each value the float64 Python's float() gives, nothing else (no
    normals, no attributes, nothing dropped); the same with a final newline or Windows
    line ends. The copy in tests/data (a bare clone) and the shared one, when present."""
    copies = [folder / "cgal_jet_fitting_in_points_d4.txt"
              for folder in (Path(__file__).resolve().parent / "data", DATA)]
    copies = [c for c in copies if c.is_file()]
    if not copies:
        pytest.skip("cgal_jet_fitting_in_points_d4.txt in neither tests/data nor "
                    f"{DATA}")
    for path in copies:
        raw = path.read_bytes()
        assert b" ." in raw and not raw.endswith(b"\n")       # the quirks are exercised
        want = np.array([[float(v) for v in row.split()] for row in raw.decode().split("\n")])
        assert want.shape == (17, 3)
        cloud = cio.read(path)
        assert cloud.points.dtype == np.float64
        np.testing.assert_array_equal(cloud.points, want)
        assert cloud.normals is None and cloud.attributes == {} and cloud.dropped == 0
        for variant in (raw + b"\n", raw.replace(b"\n", b"\r\n")):
            copy = tmp_path / path.name
            copy.write_bytes(variant)
            np.testing.assert_array_equal(cio.read(copy).points, want)


# ------------------------------------------------------------------ round trips

def make_cloud(n=500, seed=0, offset=(512345.678, 5123456.789, 123.4)):
    """Georeferenced-looking points (digits float32 would lose), unit normals, fields."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-50, 50, (n, 3)) + np.asarray(offset)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    fields = {"mean_curvature": rng.normal(size=n), "gaussian_curvature": rng.normal(size=n),
              "k1": rng.normal(size=n).astype(np.float32), "surface_variation": rng.random(n),
              "label": rng.integers(-5, 100000, n).astype(np.int32)}
    fields["mean_curvature"][::7] = np.nan
    return pts, nrm, fields


def test_ply_round_trip(tmp_path):
    pts, nrm, fields = make_cloud()
    path = cio.write(tmp_path / "c.ply", pts, fields, normals=nrm)
    cloud = cio.read(path)
    assert np.array_equal(cloud.points, pts)  # float64: bit-exact
    assert np.array_equal(cloud.normals, nrm.astype(np.float32).astype(np.float64))
    assert list(cloud.attributes) == list(fields)
    for name, a in fields.items():
        expect = a.astype(np.float32) if a.dtype.kind == "f" else a
        assert cloud.attributes[name].dtype == expect.dtype, name
        assert np.array_equal(cloud.attributes[name], expect, equal_nan=True), name
    from plyfile import PlyData
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    types = {p.name: p.val_dtype for p in ply["vertex"].properties}
    assert types["x"] in ("f8", "<f8", "float64") or np.dtype(types["x"]) == np.float64
    assert np.dtype(types["label"]) == np.int32 and np.dtype(types["k1"]) == np.float32


@pytest.mark.parametrize("text,order", [(True, "="), (False, "<"), (False, ">")])
@pytest.mark.parametrize("vertex_first", [True, False])
def test_ply_mesh_variants_match_plyfile(tmp_path, text, order, vertex_first):
    from plyfile import PlyData, PlyElement
    rng = np.random.default_rng(5)
    vert = np.zeros(30, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"),
                               ("ny", "f4"), ("nz", "f4"), ("quality", "u1")])
    for name in ("x", "y", "z", "nx", "ny", "nz"):
        vert[name] = rng.normal(size=30)
    vert["x"][4] = np.nan
    vert["quality"] = np.arange(30)
    faces = np.array([(rng.integers(0, 30, 3),) for _ in range(20)],
                     dtype=[("vertex_indices", "i4", (3,))])
    els = [PlyElement.describe(vert, "vertex"), PlyElement.describe(faces, "face")]
    path = tmp_path / "mesh.ply"
    PlyData(els if vertex_first else els[::-1], text=text, byte_order=order,
            comments=["made in a test"]).write(str(path))
    cloud = cio.read(path)
    keep = np.isfinite(vert["x"])
    assert cloud.dropped == 1 and len(cloud) == 29
    assert np.array_equal(cloud.points[:, 1], vert["y"][keep].astype(np.float64))
    assert np.array_equal(cloud.normals[:, 2], vert["nz"][keep].astype(np.float64))
    assert cloud.attributes["quality"].tolist() == np.arange(30)[keep].tolist()
    assert cloud.header["elements"] == {"vertex": 30, "face": 20}
    assert cloud.header["comments"] == ["made in a test"]


def test_ply_int64_and_bool_fields(tmp_path):
    pts = np.arange(12.0).reshape(4, 3)
    cio.write(tmp_path / "i.ply", pts, {"big": np.array([0, 1, 2, 3]), "flag":
                                        np.array([True, False, True, True])})
    cloud = cio.read(tmp_path / "i.ply")
    assert cloud.attributes["big"].dtype == np.int32
    assert cloud.attributes["flag"].dtype == np.uint8
    with pytest.raises(cio.WriteError, match="big"):
        cio.write(tmp_path / "j.ply", pts, {"big": np.array([0, 1, 2, 2**40])})


def test_npz_round_trip_exact(tmp_path):
    pts, nrm, fields = make_cloud()
    cio.write(tmp_path / "c.npz", pts, fields, normals=nrm)
    cloud = cio.read(tmp_path / "c.npz")
    assert np.array_equal(cloud.points, pts) and np.array_equal(cloud.normals, nrm)
    assert list(cloud.attributes) == list(fields)
    for name, a in fields.items():
        assert cloud.attributes[name].dtype == a.dtype
        assert np.array_equal(cloud.attributes[name], a, equal_nan=True)


@pytest.mark.parametrize("ext", [".csv", ".txt", ".xyz"])
def test_text_round_trip(tmp_path, ext):
    pts, nrm, fields = make_cloud()
    path = cio.write(tmp_path / f"c{ext}", pts, fields, normals=nrm)
    first = path.read_text().splitlines()[0]
    sep = "," if ext == ".csv" else " "
    assert first == sep.join(["x", "y", "z", "nx", "ny", "nz", *fields])
    cloud = cio.read(path)
    assert np.array_equal(cloud.points, pts)  # %.17g: bit-exact
    np.testing.assert_allclose(cloud.normals, nrm, rtol=1e-8, atol=1e-9)
    assert list(cloud.attributes) == list(fields)
    for name, a in fields.items():
        np.testing.assert_allclose(cloud.attributes[name], a, rtol=1e-8, equal_nan=True)
    assert np.array_equal(cloud.attributes["label"], fields["label"])


def test_las_round_trip_without_like(tmp_path):
    laspy = laspy_or_skip()
    pts, nrm, fields = make_cloud()
    path = cio.write(tmp_path / "c.las", pts, fields, normals=nrm)
    las = laspy.read(str(path))
    assert las.header.version == "1.4" and las.header.point_format.id == 6
    scales = [cio.las.scale_for_extent(e) for e in np.ptp(pts, axis=0)]     # one per axis
    assert np.array_equal(las.header.scales, scales)
    assert np.array_equal(las.header.offsets, pts.min(axis=0))
    assert list(las.point_format.extra_dimension_names) == ["nx", "ny", "nz", *fields]
    for name, a in fields.items():  # extra bytes readable by laspy directly
        expect = a.astype(np.float32) if a.dtype.kind == "f" else a
        assert np.array_equal(np.asarray(las[name]), expect, equal_nan=True), name
    cloud = cio.read(path)
    # half the axis's scale, plus the float64 rounding of X * scale + offset
    assert np.all(np.abs(cloud.points - pts).max(axis=0)
                  <= np.array(scales) / 2 + 4 * np.spacing(np.abs(pts).max()))
    assert np.array_equal(cloud.normals, nrm.astype(np.float32).astype(np.float64))
    assert np.array_equal(cloud.attributes["label"], fields["label"])


def test_las_round_trip_with_like_keeps_header_and_points(tmp_path):
    laspy = laspy_or_skip()
    src = cio.read(data_file("laspy_simple.las"))
    rng = np.random.default_rng(1)
    fields = {"mean_curvature": rng.normal(size=len(src)), "k2": rng.normal(size=len(src))}
    path = cio.write(tmp_path / "simple_curv.las", src.points, fields, like=src)
    las = laspy.read(str(path))
    assert las.header.version == src.header.version and las.header.point_format.id == 3
    assert np.array_equal(las.header.scales, src.header.scales)
    assert np.array_equal(las.header.offsets, src.header.offsets)
    assert list(las.point_format.extra_dimension_names) == list(fields)
    assert np.array_equal(np.asarray(las.mean_curvature), fields["mean_curvature"].astype("f4"))
    back = cio.read(path)
    assert np.array_equal(back.points, src.points)  # same integers, same scale and offset
    for name, a in src.attributes.items():
        assert np.array_equal(back.attributes[name], a), name
    # writing again with the same field names overwrites the extra dimensions
    cio.write(tmp_path / "again.las", back.points, {"k2": np.zeros(len(src))}, like=back)
    las = laspy.read(str(tmp_path / "again.las"))
    assert list(las.point_format.extra_dimension_names) == list(fields)
    assert not np.any(las.k2) and np.array_equal(las.mean_curvature, back.attributes["mean_curvature"])
    assert src.header.point_format.num_extra_bytes == 0  # like's header is not modified


def test_laz_round_trip_with_like_keeps_vlrs(tmp_path):
    laspy = laspy_or_skip(laz=True)
    src = cio.read(data_file("laspy_autzen_trim.laz"))
    k1 = np.linspace(-1, 1, len(src))
    for ext in (".laz", ".las"):
        path = cio.write(tmp_path / f"autzen{ext}", src.points, {"k1": k1}, like=src)
        las = laspy.read(str(path))
        assert len(las.header.vlrs) == len(src.header.vlrs) + 1  # + the extra-bytes VLR
        assert [type(v).__name__ for v in las.header.vlrs[:-1]] == \
            [type(v).__name__ for v in src.header.vlrs]  # CRS VLRs kept
        assert np.array_equal(np.asarray(las.k1), k1.astype(np.float32))
        back = cio.read(path)
        assert np.array_equal(back.points, src.points)
        assert np.array_equal(back.attributes["classification"],
                              src.attributes["classification"])


def test_laz_without_backend_says_how_to_install(tmp_path, monkeypatch):
    laspy = laspy_or_skip()
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    path = data_file("laspy_autzen_trim.laz")
    with pytest.raises(cio.MissingDependencyError, match=r'pip install "laspy\[lazrs\]"') as e:
        cio.read(path)
    assert str(path) in str(e.value) and isinstance(e.value, ImportError)
    with pytest.raises(cio.MissingDependencyError, match="lazrs"):
        cio.write(tmp_path / "x.laz", np.zeros((2, 3)))


def test_las_without_laspy_says_how_to_install(tmp_path, monkeypatch):
    path = data_file("laspy_simple.las")
    monkeypatch.setitem(sys.modules, "laspy", None)  # `import laspy` raises ImportError
    with pytest.raises(cio.MissingDependencyError, match="pip install laspy") as e:
        cio.read(path)
    assert str(path) in str(e.value) and isinstance(e.value, cio.ReadError)
    with pytest.raises(cio.MissingDependencyError, match="laspy"):
        cio.write(tmp_path / "x.las", np.zeros((2, 3)))


def test_write_keeps_count_and_order(tmp_path):
    pts = np.random.default_rng(3).normal(size=(257, 3))
    pts[5] = pts[200]  # duplicates are kept
    for ext in (".ply", ".npz", ".csv"):
        assert np.array_equal(cio.read(cio.write(tmp_path / f"o{ext}", pts)).points, pts)
    laspy_or_skip()
    back = cio.read(cio.write(tmp_path / "o.las", pts)).points
    assert back.shape == pts.shape and np.abs(back - pts).max() <= 0.0005 + 1e-12


def test_nan_points_written_then_dropped_on_read(tmp_path):
    pts, nrm, fields = make_cloud(50)
    pts[[3, 10]] = np.nan
    pts[20, 2] = np.inf
    for ext in (".ply", ".npz", ".csv"):
        cloud = cio.read(cio.write(tmp_path / f"n{ext}", pts, fields, normals=nrm))
        keep = np.isfinite(pts).all(axis=1)
        assert cloud.dropped == 3 and np.array_equal(cloud.points, pts[keep])
        assert np.array_equal(cloud.attributes["label"], fields["label"][keep])
    with pytest.raises(cio.WriteError, match="NaN"):
        cio.write(tmp_path / "n.las", pts)


# ------------------------------------------------------------------ PCD variants

def pcd_bytes(fields, types, rows, data, width, height, counts=None):
    counts = counts or [1] * len(fields)
    sizes = [np.dtype(t).itemsize for t in types]
    kinds = [{"f": "F", "u": "U", "i": "I"}[np.dtype(t).kind] for t in types]
    head = ("# .PCD v0.7\nVERSION 0.7\n"
            f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
            f"TYPE {' '.join(kinds)}\nCOUNT {' '.join(map(str, counts))}\n"
            f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {width * height}\nDATA {data}\n").encode()
    dtype = np.dtype([(f if f != "_" else f"_{i}", t) if c == 1 else (f, t, (c,))
                      for i, (f, t, c) in enumerate(zip(fields, types, counts))])
    rec = np.zeros(width * height, dtype=dtype)
    for name, col in rows.items():
        rec[name] = col
    if data == "ascii":
        lines = [" ".join(repr(float(v)) if not isinstance(v, np.integer) else str(v)
                          for name in dtype.names for v in np.atleast_1d(r[name]))
                 for r in rec]
        return head + ("\n".join(lines) + "\n").encode()
    if data == "binary":
        return head + rec.tobytes()
    soa = b"".join(np.ascontiguousarray(rec[name]).tobytes() for name in dtype.names)
    comp = lzf_literals(soa)
    return head + struct.pack("<II", len(comp), len(soa)) + comp


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_organised_with_nans_rgb_padding_and_counts(tmp_path, data):
    w, h = 4, 3
    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(w * h, 3)).astype(np.float32)
    xyz[[1, 6, 11], :] = np.nan
    rgb = np.array([(10 * i) << 16 | (i + 1) << 8 | 200 for i in range(w * h)], np.uint32)
    hist = rng.random((w * h, 3)).astype(np.float32)
    rows = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "rgb": rgb.view(np.float32),
            "hist": hist, "label": np.arange(w * h, dtype=np.int16)}
    raw = pcd_bytes(["x", "y", "z", "_", "rgb", "hist", "label"],
                    ["f4", "f4", "f4", "u1", "f4", "f4", "i2"], rows, data, w, h,
                    counts=[1, 1, 1, 1, 1, 3, 1])
    (tmp_path / "o.pcd").write_bytes(raw)
    cloud = cio.read(tmp_path / "o.pcd")
    keep = np.isfinite(xyz).all(axis=1)
    assert cloud.dropped == 3 and len(cloud) == w * h - 3
    assert np.array_equal(cloud.points, xyz[keep].astype(np.float64))
    assert set(cloud.attributes) == {"red", "green", "blue", "hist", "label"}
    assert np.array_equal(cloud.attributes["red"], ((rgb >> 16) & 255)[keep])
    assert np.array_equal(cloud.attributes["blue"], np.full(keep.sum(), 200))
    assert cloud.attributes["hist"].shape == (keep.sum(), 3)
    assert np.array_equal(cloud.attributes["hist"], hist[keep])
    assert np.array_equal(cloud.attributes["label"], np.arange(w * h)[keep])
    assert (cloud.header["width"], cloud.header["height"]) == (w, h)


def test_pcd_ascii_rgb_written_as_uint32_by_pcl(tmp_path):
    path = tmp_path / "rgb.pcd"  # PCL's ascii writer prints rgb (TYPE F) as its uint32 bits
    path.write_text("VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\n"
                    "COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
                    "1 2 3 4286611584\n4 5 6 16711935\n")
    c = cio.read(path)
    assert c.attributes["red"].tolist() == [128, 255] and c.attributes["green"].tolist() == [
        128, 0] and c.attributes["blue"].tolist() == [128, 255]


def test_lzf_back_references():
    # literal "ab"; a long reference (length field 7, extra byte 0: 9 bytes) at distance 2
    # (overlapping copy); a long one of 12 bytes at distance 11; a short one of 3 at distance 1
    stream = bytes([1]) + b"ab" + bytes([0xE0, 0, 1, 0xE0, 3, 10, 0x20, 0])
    expect = b"ab" + b"ababababa"
    expect += (expect * 2)[:12]
    expect += expect[-1:] * 3
    assert cio.pcd.lzf_decompress_py(stream, len(expect)) == expect
    assert cio.lzf_decompress(stream, len(expect)) == expect
    for bad in (stream[:-1], bytes([(1 << 5), 5]), bytes([5]) + b"ab"):
        with pytest.raises(ValueError):
            cio.pcd.lzf_decompress_py(bad, len(expect))
    with pytest.raises(ValueError):
        cio.pcd.lzf_decompress_py(stream, len(expect) + 1)


# ------------------------------------------------------------------ text and NumPy rules

def test_text_header_rules(tmp_path):
    p = tmp_path / "cc.txt"  # CloudCompare style header, columns in any order
    p.write_text("//X,Y,Z,R,Nx,Ny,Nz\n1,2,3,255,0,0,1\n4,5,6,0,1,0,0\n")
    c = cio.read(p)
    assert c.points.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert c.normals.tolist() == [[0, 0, 1], [1, 0, 0]] and list(c.attributes) == ["R"]
    p = tmp_path / "h.csv"
    p.write_text("# exported\nintensity, z, y, x\n7, 3, 2, 1\nnan, 1, 1, 1\n8, 6, nan, 4\n")
    c = cio.read(p)
    assert c.points.tolist() == [[1, 2, 3], [1, 1, 1]] and c.dropped == 1
    assert np.isnan(c.attributes["intensity"][1])
    p.write_text("a b c\n1 2 3\n")
    with pytest.raises(cio.CorruptFileError, match=r"h\.csv.*x, y and z"):
        cio.read(p)


def test_text_headerless_six_columns(tmp_path):
    p = tmp_path / "n.xyz"
    p.write_text("0 0 0 0 0 1\n1 0 0 0.6 0.8 0\n")
    c = cio.read(p)
    assert c.normals.tolist() == [[0, 0, 1], [0.6, 0.8, 0]] and c.attributes == {}
    p.write_text("0 0 0 255 128 0\n1 0 0 10 20 30\n")  # colours, not unit vectors
    c = cio.read(p)
    assert c.normals is None and list(c.attributes) == ["col3", "col4", "col5"]
    p.write_text("0 0 0 0.1\n")
    assert list(cio.read(p).attributes) == ["col3"]


def test_npy_plain_and_structured(tmp_path):
    pts, nrm, _ = make_cloud(20)
    np.save(tmp_path / "a.npy", pts)
    assert np.array_equal(cio.read(tmp_path / "a.npy").points, pts)
    np.save(tmp_path / "b.npy", np.hstack([pts, nrm]))
    c = cio.read(tmp_path / "b.npy")
    assert np.array_equal(c.points, pts) and np.array_equal(c.normals, nrm)
    rec = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u2")])
    rec["intensity"] = [1, 2, 3]
    np.save(tmp_path / "c.npy", rec)
    c = cio.read(tmp_path / "c.npy")
    assert c.points.shape == (3, 3) and c.attributes["intensity"].tolist() == [1, 2, 3]
    np.save(tmp_path / "d.npy", np.zeros((4, 2)))
    with pytest.raises(cio.CorruptFileError, match=r"d\.npy.*\(N, 3\)"):
        cio.read(tmp_path / "d.npy")


def test_npz_extra_keys_go_to_header(tmp_path):
    np.savez(tmp_path / "e.npz", points=np.zeros((3, 3)), radius=np.float64(0.5),
             label=np.arange(3))
    c = cio.read(tmp_path / "e.npz")
    assert list(c.attributes) == ["label"] and float(c.header["radius"]) == 0.5
    np.savez(tmp_path / "f.npz", xyz=np.zeros((3, 3)))
    with pytest.raises(cio.CorruptFileError, match=r"f\.npz.*'points'"):
        cio.read(tmp_path / "f.npz")


# ------------------------------------------------------------------ errors

def test_missing_file(tmp_path):
    path = tmp_path / "nope.ply"
    with pytest.raises(cio.MissingFileError, match="nope.ply") as e:
        cio.read(path)
    assert isinstance(e.value, FileNotFoundError) and isinstance(e.value, cio.ReadError)


def test_unknown_extension(tmp_path):
    path = tmp_path / "cloud.e57"
    path.write_bytes(b"x")
    with pytest.raises(cio.UnknownFormatError, match=r"cloud\.e57.*\.ply") as e:
        cio.read(path)
    assert isinstance(e.value, ValueError)
    with pytest.raises(cio.WriteError, match="e57"):
        cio.write(path, np.zeros((1, 3)))


@pytest.mark.parametrize("name,content", [
    ("bad.ply", b"not a ply file at all\n"),
    ("trunc.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
                  b"property double x\nproperty double y\nproperty double z\nend_header\n" +
                  b"\0" * 100),
    ("noxyz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n"),
    ("bad.pcd", b"hello\nworld\n"),
    ("trunc.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                  b"WIDTH 5\nHEIGHT 1\nPOINTS 5\nDATA binary\n" + b"\0" * 20),
    ("lzf.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                b"WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n"
                + struct.pack("<II", 3, 12) + bytes([31, 1, 2])),
    ("bad.las", b"LASF" + b"\0" * 50),
    ("bad.npz", b"PK not a zip"),
    ("bad.npy", b"\x93NUMPY garbage"),
    ("bad.csv", b"x,y,z\n1,2,3\n4,five,6\n"),
    ("short.xyz", b"1 2\n3 4\n"),
    ("empty.txt", b"\n\n"),
])
def test_corrupt_files_name_the_file(tmp_path, name, content):
    if name.endswith(".las"):
        laspy_or_skip()
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(cio.CorruptFileError) as e:
        cio.read(path)
    assert name in str(e.value) and isinstance(e.value, ValueError)


def test_write_argument_errors(tmp_path):
    pts = np.zeros((3, 3))
    with pytest.raises(cio.WriteError, match=r"\(N, 3\)"):
        cio.write(tmp_path / "a.ply", np.zeros((3, 2)))
    with pytest.raises(cio.WriteError, match="normals"):
        cio.write(tmp_path / "a.ply", pts, normals=np.zeros((2, 3)))
    with pytest.raises(cio.WriteError, match="reserved"):
        cio.write(tmp_path / "a.ply", pts, {"NX": np.zeros(3)})
    with pytest.raises(cio.WriteError, match="must match"):
        cio.write(tmp_path / "a.csv", pts, {"mean curvature": np.zeros(3)})
    with pytest.raises(cio.WriteError, match=r"shape \(3,\)"):
        cio.write(tmp_path / "a.ply", pts, {"k1": np.zeros(4)})
    with pytest.raises(cio.WriteError, match="reserved in NPZ"):
        cio.write(tmp_path / "a.npz", pts, {"points": np.zeros(3)})
    laspy_or_skip()
    src = cio.read(data_file("laspy_simple.las"))
    with pytest.raises(cio.WriteError, match="1065 points"):
        cio.write(tmp_path / "a.las", pts, like=src)
    with pytest.raises(cio.WriteError, match="like="):
        cio.write(tmp_path / "a.las", pts, like="not a cloud")
    # a like= from another format is ignored: a fresh header
    other = cio.read(cio.write(tmp_path / "p.npz", pts))
    assert np.allclose(cio.read(cio.write(tmp_path / "a.las", pts, like=other)).points, pts)
    far = src.points + [1e12, 0, 0]          # beyond int32 at the file's scale and offset
    with pytest.raises(cio.WriteError, match="int32"):
        cio.write(tmp_path / "a.las", far, like=src)
