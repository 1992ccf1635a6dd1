"""Hostile input (issue 10, items 10 and 12): small crafted files whose headers claim huge
or impossible counts must fail with a :class:`clcurv.io.CorruptFileError` naming the claim
and what the file holds, without allocating from the claim; and the encoding quirks of real
files (a UTF-8 BOM, latin-1 bytes in comments) must be read.

Every test here runs under a cap on the address space (the ``memory_cap`` fixture), so an
allocation from a header count fails quickly with a MemoryError instead of swapping.
"""
import io
import resource
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from clcurv import io as cio
from hostile import assert_clean_failure, run_cli

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"

#: address space the reader may add to the test process (the crafted files are < 1 KB)
CAP_BYTES = 2 << 30


@pytest.fixture(autouse=True)
def memory_cap():
    """Limit the address space to what the process uses now plus :data:`CAP_BYTES`."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as f:
        used = int(f.read().split()[0]) * resource.getpagesize()
    cap = used + CAP_BYTES
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ------------------------------------------------------------------ crafted files

def ply_bytes(fmt, elements, body):
    """A PLY file: ``elements`` is [(name, count, [property lines])]."""
    head = [f"ply\nformat {fmt} 1.0\ncomment crafted\n"]
    for name, count, props in elements:
        head.append(f"element {name} {count}\n")
        head += [f"property {p}\n" for p in props]
    return "".join(head).encode() + b"end_header\n" + body


XYZ = ["float x", "float y", "float z"]
FACES = ["list uchar int vertex_indices"]


def pcd_header(data, points, fields="x y z", size="4 4 4", type_="F F F", count="1 1 1",
               width=None, height=1):
    width = points if width is None else width
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {type_}\n"
            f"COUNT {count}\nWIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {points}\nDATA {data}\n").encode()


def npy_bytes(descr, shape, body):
    """An NPY (version 1.0) file whose header claims ``shape``, followed by ``body``."""
    head = repr({"descr": descr, "fortran_order": False, "shape": shape})
    head += " " * (-(10 + len(head) + 1) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(head)) + head.encode() + body


def zip_bytes(members, claim=None):
    """A stored (uncompressed) zip of {name: bytes}; ``claim`` overwrites the compressed and
    uncompressed sizes of every member in the local and central headers."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    raw = bytearray(buf.getvalue())
    if claim is not None:
        for sig, at in ((b"PK\x03\x04", 18), (b"PK\x01\x02", 20)):
            pos = raw.find(sig)
            while pos >= 0:
                struct.pack_into("<II", raw, pos + at, claim, claim)
                pos = raw.find(sig, pos + 4)
    return bytes(raw)


N_HUGE_PCD = (1 << 32) // 12  # x y z float: 4 GiB - 4 bytes uncompressed
LZF_BODY = bytes([31]) + bytes(32)  # one literal run of 32 zero bytes
NPY_SHAPE = (10 ** 11, 3)
NPZ_SHAPE = (10 ** 8, 3)  # 2.4 GB, within the 32-bit sizes of a plain zip
NPZ_CLAIM = 128 + 24 * 10 ** 8

#: name -> (content, what the header claims, bytes the file holds for it): each claim is
#: impossible for a file of that size, and the error must name both numbers
CRAFTED = {
    # binary PLY, a face element of 10^9 rows before the vertex element (plyfile path)
    "face_first.ply": (ply_bytes("binary_little_endian",
                                 [("face", 10 ** 9, FACES), ("vertex", 3, XYZ)], bytes(36)),
                       10 ** 9, 36),
    # ascii PLY claiming 10^10 vertices (loadtxt path)
    "ascii_huge.ply": (ply_bytes("ascii", [("vertex", 10 ** 10, XYZ)], b"0 0 0\n"),
                       10 ** 10, 6),
    # a vertex element with a list property (plyfile path), 10^9 rows
    "vertex_list.ply": (ply_bytes("binary_little_endian",
                                  [("vertex", 10 ** 9, XYZ + ["list uchar float extra"])],
                                  bytes(13)), 10 ** 9, 13),
    # a count beyond 2^63
    "count_2_64.ply": (ply_bytes("binary_little_endian", [("vertex", 2 ** 64 + 1, XYZ)],
                                 bytes(12)), 2 ** 64 + 1, 12),
    # binary_compressed PCD claiming 4 GiB uncompressed from 33 compressed bytes
    "lzf_4gib.pcd": (pcd_header("binary_compressed", N_HUGE_PCD)
                     + struct.pack("<II", len(LZF_BODY), N_HUGE_PCD * 12) + LZF_BODY,
                     N_HUGE_PCD * 12, 8 + len(LZF_BODY)),
    # ascii PCD claiming 10^10 points
    "ascii_huge.pcd": (pcd_header("ascii", 10 ** 10) + b"0 0 0\n", 10 ** 10, 6),
    # binary PCD with COUNT 10^9 on one field
    "count_huge.pcd": (pcd_header("binary", 1, count="1 1 1000000000") + bytes(12),
                       10 ** 9, 12),
    # NPY header shape (10^11, 3) float64 over 24 bytes of data
    "huge.npy": (npy_bytes("<f8", NPY_SHAPE, bytes(24)), 10 ** 11, 24),
    # NPZ member whose NPY header claims (10^11, 3)
    "member_shape.npz": (zip_bytes({"points.npy": npy_bytes("<f8", NPY_SHAPE, bytes(24))}),
                         10 ** 11, 24),
    # NPZ member whose zip entry claims 2.4 GB (header shape consistent with it)
    "member_size.npz": (zip_bytes({"points.npy": npy_bytes("<f8", NPZ_SHAPE, bytes(24))},
                                  claim=NPZ_CLAIM), NPZ_CLAIM, None),
}


def crafted(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(CRAFTED[name][0])
    return path


def assert_names(msg, *numbers):
    for n in numbers:
        assert str(n) in msg, (n, msg)


# ------------------------------------------------------------------ counts and sizes

@pytest.mark.parametrize("name", list(CRAFTED))
def test_impossible_claim_is_corrupt_and_named(tmp_path, name):
    path = crafted(tmp_path, name)
    content, claimed, holds = CRAFTED[name]
    with pytest.raises(cio.CorruptFileError) as e:
        cio.read(path)
    msg = str(e.value)
    assert msg.startswith(str(path)), msg
    assert_names(msg, claimed, len(content) if holds is None else holds)


def test_pcd_negative_points(tmp_path):
    path = tmp_path / "neg.pcd"
    path.write_bytes(pcd_header("ascii", -1, width=1) + b"1 2 3\n")
    with pytest.raises(cio.CorruptFileError, match="POINTS -1"):
        cio.read(path)


@pytest.mark.parametrize("key", ["WIDTH", "HEIGHT"])
def test_pcd_negative_width_or_height(tmp_path, key):
    path = tmp_path / "neg.pcd"
    w, h = (-1, 1) if key == "WIDTH" else (1, -1)
    path.write_bytes(pcd_header("ascii", 1, width=w, height=h) + b"1 2 3\n")
    with pytest.raises(cio.CorruptFileError, match=f"{key} -1"):
        cio.read(path)


def test_pcd_width_times_height_must_equal_points(tmp_path):
    path = tmp_path / "wh.pcd"
    path.write_bytes(pcd_header("ascii", 3, width=2, height=2) + b"1 2 3\n4 5 6\n7 8 9\n")
    with pytest.raises(cio.CorruptFileError) as e:
        cio.read(path)
    assert_names(str(e.value), "WIDTH 2", "HEIGHT 2", "POINTS 3")


def test_lzf_claim_must_match_points(tmp_path):
    path = tmp_path / "usize.pcd"
    body = bytes([11]) + bytes(12)
    path.write_bytes(pcd_header("binary_compressed", 1) + struct.pack("<II", 13, 24) + body)
    with pytest.raises(cio.CorruptFileError) as e:
        cio.read(path)
    assert_names(str(e.value), 24, 12)


def test_pure_python_lzf_refuses_impossible_size():
    with pytest.raises(ValueError) as e:
        cio.pcd.lzf_decompress_py(LZF_BODY, 1 << 32)
    assert_names(str(e.value), 1 << 32, len(LZF_BODY))


def test_binary_ply_truncated_names_claim_and_size(tmp_path):
    path = tmp_path / "trunc.ply"
    path.write_bytes(ply_bytes("binary_big_endian", [("vertex", 5, XYZ)], bytes(50)))
    with pytest.raises(cio.CorruptFileError) as e:
        cio.read(path)
    assert_names(str(e.value), 5, 60, 50)


# ------------------------------------------------------------------ encodings (item 12)

@pytest.mark.parametrize("text", ["\ufeffx,y,z\n1,2,3\n4,5,6\n", "\ufeff1 2 3\n4 5 6\n"])
def test_text_with_utf8_bom(tmp_path, text):
    path = tmp_path / "bom.csv"
    path.write_bytes(text.encode("utf-8"))
    cloud = cio.read(path)
    assert cloud.points.tolist() == [[1, 2, 3], [4, 5, 6]]


LATIN1 = "caf\xe9 d\xe9j\xe0 vu".encode("latin-1")


@pytest.mark.parametrize("where", ["header", "body"])
def test_text_latin1_comment(tmp_path, where):
    path = tmp_path / "l1.txt"
    rows = b"1 2 3\n4 5 6\n"
    content = (b"# " + LATIN1 + b"\n" + rows if where == "header"
               else b"x y z\n1 2 3\n# " + LATIN1 + b"\n4 5 6\n")
    path.write_bytes(content)
    assert cio.read(path).points.tolist() == [[1, 2, 3], [4, 5, 6]]


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("vertex_first", [True, False], ids=["numpy", "plyfile"])
def test_ply_latin1_comment(tmp_path, fmt, vertex_first):
    rows = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    vbody = (b"1 2 3\n4 5 6\n" if fmt == "ascii" else rows.tobytes())
    fbody = b"0\n" if fmt == "ascii" else b"\0"
    elements = [("vertex", 2, XYZ), ("face", 1, FACES)]
    body = vbody + fbody if vertex_first else fbody + vbody
    raw = ply_bytes(fmt, elements if vertex_first else elements[::-1], body)
    raw = raw.replace(b"comment crafted", b"comment " + LATIN1)
    path = tmp_path / "l1.ply"
    path.write_bytes(raw)
    cloud = cio.read(path)
    assert cloud.points.tolist() == rows.tolist()
    assert len(cloud.header["comments"]) == 1


@pytest.mark.parametrize("data", ["ascii", "binary"])
def test_pcd_latin1_comment(tmp_path, data):
    rows = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    body = b"1 2 3\n# " + LATIN1 + b"\n4 5 6\n" if data == "ascii" else rows.tobytes()
    raw = b"# " + LATIN1 + b"\n" + pcd_header(data, 2) + body
    path = tmp_path / "l1.pcd"
    path.write_bytes(raw)
    assert cio.read(path).points.tolist() == rows.tolist()


# ------------------------------------------------------------------ what a user sees

CLI_CASES = ["face_first.ply", "ascii_huge.ply", "lzf_4gib.pcd", "huge.npy",
             "member_size.npz"]


@pytest.mark.parametrize("name", CLI_CASES)
def test_cli_fails_cleanly_on_crafted_file(tmp_path, name):
    out = run_cli("compute", crafted(tmp_path, name), "-o", tmp_path / "o.ply", "-q")
    assert_clean_failure(out, what=name)
    assert_names(out.lines[0], CRAFTED[name][1])


_ASCII_MESH = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
               "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
               "end_header\n0 0 0.125\n1 0 0.25\n0 1 -0.0197253\n3 0 1 2\n")


@pytest.mark.parametrize("cut, what", [
    (len(_ASCII_MESH) - len("3 0 1 2\n"), "rows of other elements"),   # the faces lost
    (len(_ASCII_MESH) - len("0197253\n3 0 1 2\n"), "rows of other elements"),
])
def test_ascii_ply_cut_before_its_last_rows_is_corrupt(tmp_path, cut, what):
    """An ascii PLY cut inside its last vertex line read the cut number (z -0.0197253 as
    -0.0) and one cut before its other elements read as whole: both CorruptFileError."""
    p = tmp_path / "cut.ply"
    p.write_bytes(_ASCII_MESH[:cut].encode())
    with pytest.raises(cio.CorruptFileError, match=what):
        cio.read(p)


def _binary_mesh(faces):
    """A binary little-endian PLY of 4 vertices, the faces given (lists of indices), and a
    1-row scalar element after them."""
    verts = np.arange(12, dtype="<f4").tobytes()
    rows = b"".join(bytes([len(f)]) + np.array(f, "<i4").tobytes() for f in faces)
    cam = np.array([1.5, 2.5], "<f8").tobytes()
    return ply_bytes("binary_little_endian", [("vertex", 4, XYZ), ("face", len(faces), FACES),
                                              ("camera", 1, ["double a", "double b"])],
                     verts + rows + cam)


@pytest.mark.parametrize("faces", [[[0, 1, 2], [1, 2, 3], [0, 2, 3]],
                                   [[0, 1, 2, 3], [1, 2, 3]]],      # mixed: read by plyfile
                         ids=["triangles", "mixed"])
@pytest.mark.parametrize("cut", [0, 5, 16, 40])
def test_binary_ply_cut_after_its_vertices_is_corrupt(tmp_path, faces, cut):
    """A binary PLY cut inside its faces, or inside an element after them, read as whole
    (its vertices were there): CorruptFileError; the whole file reads."""
    whole = _binary_mesh(faces)
    p = tmp_path / "m.ply"
    p.write_bytes(whole)
    np.testing.assert_array_equal(cio.read(p).points.ravel(), np.arange(12))
    if cut:
        p.write_bytes(whole[:-cut])
        with pytest.raises(cio.CorruptFileError, match="face|camera|after the vertices"):
            cio.read(p)


def test_real_binary_mesh_cut_inside_its_strips(tmp_path):
    """The Igea scan (binary, one triangle-strip row of ~270k indices after its vertices):
    whole it reads, cut by 1 kB it is CorruptFileError, in memory and for a tiled run."""
    src = DATA / "igea_cyberware.ply"
    if not src.exists():
        pytest.skip(f"{src} not present (../shared/data)")
    raw = src.read_bytes()
    assert len(cio.read(src).points) == 134345
    cut = tmp_path / "igea_cut.ply"
    cut.write_bytes(raw[:-1000])
    with pytest.raises(cio.CorruptFileError, match="tristrips"):
        cio.read(cut)
    from clcurv.io.stream import open_source
    with pytest.raises(cio.CorruptFileError, match="tristrips"):
        open_source(cut)


def test_ascii_ply_vertices_cut_at_the_end_are_corrupt(tmp_path):
    """Vertices only, the file cut inside the last line (no newline after it): an error,
    not a shorter last number; the whole file reads."""
    whole = ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
             "property float z\nend_header\n0 0 0.125\n0 1 -0.0197253\n")
    p = tmp_path / "v.ply"
    p.write_bytes(whole.encode())
    assert cio.read(p).points[-1, 2] == np.float32(-0.0197253)
    p.write_bytes(whole[:-5].encode())
    with pytest.raises(cio.CorruptFileError, match="ends inside its last line"):
        cio.read(p)


def test_ascii_pcd_cut_inside_its_last_line_is_corrupt(tmp_path):
    """An ascii PCD cut inside its last row read a shortened last number (0.01566753 as
    0.015): CorruptFileError; the whole file reads."""
    whole = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z curvature\nSIZE 4 4 4 4\nTYPE F F F F\n"
             "COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
             "0 0 0 0.5\n1 0 0 0.01566753\n")
    p = tmp_path / "c.pcd"
    p.write_bytes(whole.encode())
    assert cio.read(p).attributes["curvature"][-1] == np.float32(0.01566753)
    p.write_bytes(whole[:-6].encode())
    with pytest.raises(cio.CorruptFileError, match="ends inside its last line"):
        cio.read(p)
