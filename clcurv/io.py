"""Read and write point clouds: PLY, PCD, LAS/LAZ, XYZ/TXT/CSV, NPY and NPZ.

:func:`read` returns a :class:`Cloud` (NumPy arrays in float64), :func:`write` writes points,
normals and per-point fields (curvatures, ...) in a format chosen by the file extension.

Rules common to every format
----------------------------
* Points come out as a C-contiguous ``(N, 3)`` float64 array, in file order. Organised clouds
  (PCD with ``HEIGHT > 1``) are flattened row-major, i.e. in storage order.
* Rows whose x, y or z is NaN or +-Inf are dropped on reading, from the points, the normals and
  every attribute alike; ``Cloud.dropped`` counts them. Non-finite *normals* or attributes
  are kept as they are (PCL writes NaN normals where estimation failed).
* Normals are taken from columns or properties named ``nx, ny, nz`` or
  ``normal_x, normal_y, normal_z`` (case-insensitive), when all three are present.
* Every other per-point value becomes an entry of ``Cloud.attributes`` (name -> array whose
  first dimension is N; a PCD field with ``COUNT > 1`` gives an ``(N, COUNT)`` array).
* :func:`write` never reorders, adds or removes points.

Errors on reading are subclasses of :class:`ReadError`, and their messages start with the
file name: :class:`MissingFileError` (also a ``FileNotFoundError``),
:class:`UnknownFormatError` and :class:`CorruptFileError` (also ``ValueError``), and
:class:`MissingDependencyError` (also ``ImportError``; an optional package such as ``lazrs``
is needed). Bad arguments to :func:`write` raise :class:`WriteError` (a ``ValueError``).

Optional packages: ``laspy`` for LAS, ``laspy[lazrs]`` for LAZ, and ``python-lzf`` (module
``lzf``) to speed up binary_compressed PCD (a pure-Python LZF decoder is used without it).
"""
from __future__ import annotations

import copy
import io
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Cloud", "read", "write", "lzf_decompress", "ReadError", "MissingFileError",
           "UnknownFormatError", "CorruptFileError", "MissingDependencyError", "WriteError",
           "READ_FORMATS", "WRITE_FORMATS"]

#: Extensions understood by :func:`read` (lower case) and what each one means.
READ_FORMATS = {
    ".ply": "PLY (ascii or binary; the vertex element of a mesh)",
    ".pcd": "PCD (ascii, binary or binary_compressed)",
    ".las": "LAS", ".laz": "LAZ (compressed LAS)",
    ".xyz": "text (x y z ...)", ".xyzn": "text (x y z nx ny nz)", ".txt": "text (x y z ...)",
    ".csv": "text (x,y,z,...)", ".asc": "text (x y z ...)",
    ".npy": "NumPy array (N, >=3)", ".npz": "NumPy archive (points, normals, ...)",
}
#: Extensions understood by :func:`write`.
WRITE_FORMATS = {
    ".ply": "binary little-endian PLY", ".las": "LAS", ".laz": "LAZ",
    ".npz": "NumPy archive", ".csv": "comma-separated text with a header line",
    ".txt": "space-separated text with a header line",
    ".xyz": "space-separated text with a header line",
}

LAZ_HINT = 'pip install "laspy[lazrs]"'
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_RESERVED = {"x", "y", "z", "nx", "ny", "nz", "normal_x", "normal_y", "normal_z"}
_NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))


# --------------------------------------------------------------------------- errors

class ReadError(Exception):
    """A point cloud file could not be read. The message starts with the file name."""


class MissingFileError(ReadError, FileNotFoundError):
    """The file does not exist."""


class UnknownFormatError(ReadError, ValueError):
    """The extension is not one of :data:`READ_FORMATS`."""


class CorruptFileError(ReadError, ValueError):
    """The file exists but its content is not what its extension promises."""


class MissingDependencyError(ReadError, ImportError):
    """An optional package needed for this format is missing (raised by read and write)."""


class WriteError(ValueError):
    """:func:`write` was given arguments it cannot write (shape, name, format...)."""


# --------------------------------------------------------------------------- Cloud

@dataclass(repr=False, eq=False)
class Cloud:
    """A point cloud read from a file.

    Attributes
    ----------
    points : (N, 3) ndarray of float64
        Finite coordinates, in file order.
    normals : (N, 3) ndarray of float64 or None
        Normals stored in the file, if any (may contain NaN).
    attributes : dict of str -> ndarray
        Other per-point values (intensity, classification, red/green/blue, confidence, ...),
        each with first dimension N, in the file's dtype (text formats: float64).
    header : object or None
        Format-specific information: the ``laspy.LasHeader`` for LAS/LAZ (used by
        ``write(..., like=cloud)``), a dict for PLY/PCD, extra non-per-point arrays for NPZ.
    dropped : int
        Number of rows dropped because x, y or z was not finite.
    path : pathlib.Path or None
        The file read.
    format : str or None
        ``'ply'``, ``'pcd'``, ``'las'``, ``'laz'``, ``'text'``, ``'npy'`` or ``'npz'``.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    header: object = None
    dropped: int = 0
    path: Path | None = None
    format: str | None = None

    def __len__(self):
        return len(self.points)

    def __repr__(self):
        return (f"Cloud({len(self.points)} points, normals={self.normals is not None}, "
                f"attributes={list(self.attributes)}, dropped={self.dropped}, "
                f"format={self.format!r}, path={str(self.path)!r})")


# --------------------------------------------------------------------------- read

def read(path) -> Cloud:
    """Read a point cloud; the format is chosen by the file extension.

    Parameters
    ----------
    path : str or os.PathLike
        A file whose extension is one of :data:`READ_FORMATS` (case-insensitive).

    Returns
    -------
    Cloud
        Points (float64), normals, attributes, header and the number of dropped rows.

    Raises
    ------
    UnknownFormatError
        The extension is not supported.
    MissingFileError
        The file does not exist.
    CorruptFileError
        The content cannot be parsed as the format of its extension.
    MissingDependencyError
        LAS needs ``laspy``; LAZ needs ``laspy`` with a LAZ backend (``pip install
        "laspy[lazrs]"``).

    Notes
    -----
    Format details:

    * **PLY** (``plyfile``): the ``vertex`` element, ascii or binary; other elements (faces,
      range grids, triangle strips) are skipped; list properties of the vertex are ignored.
    * **PCD**: ascii, binary and binary_compressed (LZF). Fields ``x y z``, ``normal_x/y/z``;
      ``rgb``/``rgba`` (packed) become ``red``, ``green``, ``blue`` (and ``alpha``) uint8
      attributes (ascii rgb may be PCL's uint32 form or the float itself); ``_`` padding
      fields are skipped; others (``curvature``...) are attributes.
      ``header`` holds the PCD header (with ``width``/``height`` of organised clouds).
    * **LAS/LAZ** (``laspy``): ``points`` equal ``las.x, las.y, las.z`` (X * scale + offset
      in float64). Every other dimension (intensity, classification, return_number, gps_time,
      red, ..., extra bytes) is an attribute; extra dimensions named ``nx, ny, nz`` are the
      normals. ``header`` is the ``laspy.LasHeader``.
    * **Text** (``.xyz .xyzn .txt .csv .asc``): comma-, semicolon- or whitespace-separated
      (from the first data line); lines starting with ``#`` or ``//`` are comments, except a
      header. A header is the first non-blank line that is not all numbers, is not a
      comment, or is a comment naming x, y and z (its ``#`` or ``//`` is stripped, so
      CloudCompare's ``//X,Y,Z,...`` works); columns named x, y, z are then required,
      ``nx ny nz`` / ``normal_x...`` are normals, other columns are attributes by name.
      Without a header, columns 0-2 are x, y, z; if there are **exactly 6 columns and columns
      3-5 are unit vectors** (| |n| - 1 | <= 1e-3 on every row where they are finite) they are
      the normals; otherwise columns 3, 4, ... are attributes ``col3``, ``col4``, ...
    * **NPY**: an ``(N, >=3)`` numeric array, with the same column rule as headerless text, or
      a structured array whose field names follow the header rule.
    * **NPZ**: key ``points`` (N, 3) is required, ``normals`` (N, 3) optional; other arrays
      whose first dimension is N are attributes, the rest go into ``header`` (a dict).
    """
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    reader = _READERS.get(ext)
    if reader is None:
        raise UnknownFormatError(
            f"{path}: unknown point cloud extension {ext or '(none)'!r}; expected one of "
            f"{', '.join(READ_FORMATS)}")
    kind = READ_FORMATS[ext]
    if not path.exists():
        raise MissingFileError(f"{path}: no such file (expected a {kind} point cloud)")
    if not path.is_file():
        raise CorruptFileError(f"{path}: not a regular file (expected a {kind} point cloud)")
    try:
        return reader(path)
    except ReadError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # parser-specific errors, re-raised with the file name
        raise CorruptFileError(f"{path}: cannot read as {kind}: {type(exc).__name__}: {exc}"
                               ) from exc


def _finish(path, fmt, points, normals=None, attributes=None, header=None):
    """Build a Cloud, dropping rows with non-finite coordinates."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    attributes = dict(attributes or {})
    keep = np.isfinite(points).all(axis=1)
    dropped = int(keep.size - np.count_nonzero(keep))
    if dropped:
        points = points[keep]
        normals = None if normals is None else np.asarray(normals)[keep]
        attributes = {k: np.asarray(v)[keep] for k, v in attributes.items()}
    points = np.ascontiguousarray(points)
    if normals is not None:
        normals = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    attributes = {k: np.ascontiguousarray(v) for k, v in attributes.items()}
    return Cloud(points, normals, attributes, header, dropped, path, fmt)


def _native(a):
    """A writable, native-byte-order copy of ``a``."""
    a = np.asarray(a)
    return a.astype(a.dtype.newbyteorder("="), copy=True)


def _find(names, wanted):
    """Index of ``wanted`` in ``names``: exact match first, then case-insensitive."""
    if wanted in names:
        return names.index(wanted)
    lower = [n.lower() for n in names]
    return lower.index(wanted) if wanted in lower else None


def _split_named(path, fmt, columns, header=None, points=None):
    """Split named per-point columns into points, normals and attributes.

    ``columns`` maps names to arrays of first dimension N; x, y, z are required unless
    ``points`` is given.
    """
    names = list(columns)
    used = set()
    if points is None:
        idx = [_find(names, c) for c in "xyz"]
        if None in idx:
            raise CorruptFileError(f"{path}: columns {names} have no x, y and z; expected "
                                   "columns named x, y and z")
        points = np.column_stack([np.asarray(columns[names[i]], dtype=np.float64)
                                  for i in idx])
        used.update(names[i] for i in idx)
    normals = None
    for triple in _NORMAL_NAMES:
        idx = [_find(names, c) for c in triple]
        if None not in idx:
            normals = np.column_stack([np.asarray(columns[names[i]], dtype=np.float64)
                                       for i in idx])
            used.update(names[i] for i in idx)
            break
    attributes = {n: columns[n] for n in names if n not in used}
    return _finish(path, fmt, points, normals, attributes, header)


def _looks_like_normals(a):
    """True when every finite row of the (N, 3) array ``a`` is a unit vector (1e-3)."""
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a).all(axis=1)]
    if len(a) == 0:
        return False
    return bool(np.all(np.abs(np.linalg.norm(a, axis=1) - 1.0) <= 1e-3))


def _split_positional(path, fmt, table, header=None):
    """Columns 0-2 are x y z; 3-5 are normals if exactly 6 columns of unit vectors."""
    table = np.asarray(table)
    if table.ndim != 2 or table.shape[1] < 3:
        raise CorruptFileError(f"{path}: expected at least 3 columns (x y z), got an array "
                               f"of shape {table.shape}")
    normals = None
    first_attr = 3
    if table.shape[1] == 6 and _looks_like_normals(table[:, 3:6]):
        normals, first_attr = table[:, 3:6], 6
    attributes = {f"col{j}": table[:, j] for j in range(first_attr, table.shape[1])}
    return _finish(path, fmt, table[:, :3], normals, attributes, header)


# --------------------------------------------------------------------------- PLY

_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2",
              "ushort": "u2", "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4",
              "int32": "i4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


def _ply_header(raw, path):
    """Parse a PLY header: (format, preamble lines, [[name, count, lines]], body offset)."""
    m = re.search(rb"end_header[ \t]*\r?\n", raw[:1 << 20])
    if not raw.startswith(b"ply") or m is None:
        raise CorruptFileError(f"{path}: not a PLY file (expected a 'ply' magic line and an "
                               "'end_header' line)")
    lines = raw[:m.end()].decode("ascii", errors="replace").splitlines()
    preamble, elements, fmt = [], [], None
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] == "end_header":
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
            preamble.append(line)
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise CorruptFileError(f"{path}: bad PLY header line {line!r}")
            elements.append([tok[1], int(tok[2]), [line]])
        elif tok[0] == "property" and elements:
            elements[-1][2].append(line)
        else:
            preamble.append(line)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise CorruptFileError(f"{path}: unknown PLY format {fmt!r}; expected ascii, "
                               "binary_little_endian or binary_big_endian")
    return fmt, preamble, elements, m.end()


def _ply_vertex_columns(raw, path):
    """Columns of the PLY vertex element and the header dict.

    plyfile parses ascii rows one by one in Python (seconds for the Stanford scans with
    their faces or range grids). When the vertex element comes first and has only scalar
    properties (the usual case), its rows alone are parsed with NumPy (``frombuffer`` for
    binary, ``loadtxt`` for ascii) from the header parsed here; otherwise plyfile reads the
    whole file.
    """
    import plyfile
    fmt, preamble, elements, start = _ply_header(raw, path)
    counts = {e[0]: e[1] for e in elements}
    header = {"format": fmt, "elements": counts,
              "comments": [ln.split(None, 1)[1] if " " in ln else ""
                           for ln in preamble if ln.split()[0] == "comment"],
              "obj_info": [ln.split(None, 1)[1] if " " in ln else ""
                           for ln in preamble if ln.split()[0] == "obj_info"]}
    if "vertex" not in counts:
        raise CorruptFileError(f"{path}: PLY file has no 'vertex' element (elements: "
                               f"{list(counts)})")
    _, n, block = elements[0]
    props = [ln.split() for ln in block[1:]]
    simple = elements[0][0] == "vertex" and all(
        len(p) == 3 and p[1] in _PLY_TYPES for p in props)
    if simple and fmt != "ascii":
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(p[2], order + _PLY_TYPES[p[1]]) for p in props])
        if len(raw) - start < n * dtype.itemsize:
            raise CorruptFileError(f"{path}: PLY vertex data is truncated ({len(raw) - start} "
                                   f"bytes, expected {n * dtype.itemsize} for {n} vertices)")
        v = np.frombuffer(raw, dtype=dtype, count=n, offset=start)
        return {name: _native(v[name]) for name in v.dtype.names}, header
    if simple:  # ascii: one vertex per line
        dtype = np.dtype([(p[2], _PLY_TYPES[p[1]]) for p in props])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on an empty body
            v = np.loadtxt(io.StringIO(raw[start:].decode("ascii", errors="replace")),
                           dtype=dtype, ndmin=1, max_rows=n, comments=None)
        if len(v) != n:
            raise CorruptFileError(f"{path}: PLY header says {n} vertices but the ascii data "
                                   f"has {len(v)} lines")
        return {name: _native(v[name]) for name in v.dtype.names}, header
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # plyfile warns on empty ascii elements
        ply = plyfile.PlyData.read(io.BytesIO(raw))
    v = ply["vertex"].data
    return {name: _native(v[name]) for name in v.dtype.names if v.dtype[name] != object}, header


def _read_ply(path):
    columns, header = _ply_vertex_columns(path.read_bytes(), path)
    return _split_named(path, "ply", columns, header)


# --------------------------------------------------------------------------- PCD

_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2",
              ("U", 4): "<u4", ("U", 8): "<u8", ("I", 1): "i1", ("I", 2): "<i2",
              ("I", 4): "<i4", ("I", 8): "<i8"}


def _pcd_header(raw, path):
    """Parse the PCD header; return (dict, offset of the first data byte)."""
    hdr, pos = {}, 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > 1 << 20:
            raise CorruptFileError(f"{path}: PCD header has no DATA line (expected "
                                   "'DATA ascii|binary|binary_compressed')")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        hdr[key.upper()] = vals
        if key.upper() == "DATA":
            break
    try:
        fields = hdr["FIELDS"]
        sizes = [int(s) for s in hdr["SIZE"]]
        types = [t.upper() for t in hdr["TYPE"]]
        counts = [int(c) for c in hdr.get("COUNT", ["1"] * len(fields))]
        width = int(hdr["WIDTH"][0]) if "WIDTH" in hdr else None
        height = int(hdr["HEIGHT"][0]) if "HEIGHT" in hdr else 1
        npts = int(hdr["POINTS"][0]) if "POINTS" in hdr else width * height
        width = npts if width is None else width
        data = hdr["DATA"][0].lower()
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise CorruptFileError(f"{path}: bad PCD header ({type(exc).__name__}: {exc}); "
                               "expected FIELDS, SIZE, TYPE, WIDTH/POINTS and DATA") from None
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise CorruptFileError(f"{path}: PCD header has {len(fields)} FIELDS but "
                               f"{len(sizes)} SIZE, {len(types)} TYPE, {len(counts)} COUNT")
    bad = [(t, s) for t, s in zip(types, sizes) if (t, s) not in _PCD_TYPES]
    if bad:
        raise CorruptFileError(f"{path}: unsupported PCD TYPE/SIZE {bad}")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise CorruptFileError(f"{path}: unknown PCD DATA {data!r}; expected ascii, binary "
                               "or binary_compressed")
    names, seen = [], set()
    for i, f in enumerate(fields):  # unique names for the structured dtype
        name = f if f not in seen else f"{f}__{i}"
        seen.add(name)
        names.append(name)
    info = {"version": (hdr.get("VERSION") or [None])[0], "fields": fields, "size": sizes,
            "type": types, "count": counts, "width": width, "height": height,
            "viewpoint": [float(v) for v in hdr.get("VIEWPOINT", [])], "points": npts,
            "data": data, "_names": names}
    return info, pos


def _pcd_columns(raw, pos, h, path):
    """Per-field arrays (N,) or (N, COUNT) from the PCD body."""
    npts = h["points"]
    specs = [(n, _PCD_TYPES[(t, s)], c) for n, t, s, c in
             zip(h["_names"], h["type"], h["size"], h["count"])]
    dtype = np.dtype([(n, t) if c == 1 else (n, t, (c,)) for n, t, c in specs])
    if h["data"] == "ascii":
        packed = {n for n, f, s, c in zip(h["_names"], h["fields"], h["size"], h["count"])
                  if f in ("rgb", "rgba") and s == 4 and c == 1}
        text_dtype = np.dtype([(n, "f8") if n in packed else (n, dtype[n])
                               for n in dtype.names])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on an empty body
            rows = np.loadtxt(io.StringIO(raw[pos:].decode("ascii")), dtype=text_dtype,
                              comments="#", ndmin=1, max_rows=npts)
        if len(rows) != npts:
            raise CorruptFileError(f"{path}: PCD header says POINTS {npts} but the ascii "
                                   f"data has {len(rows)} rows")
        return {n: _ascii_packed_color(rows[n]) if n in packed else _native(rows[n])
                for n, _, _ in specs}
    if h["data"] == "binary":
        need = npts * dtype.itemsize
        if len(raw) - pos < need:
            raise CorruptFileError(f"{path}: binary PCD data is truncated ({len(raw) - pos} "
                                   f"bytes, expected {need} for {npts} points)")
        rows = np.frombuffer(raw, dtype=dtype, count=npts, offset=pos)
        return {n: _native(rows[n]) for n, _, _ in specs}
    # binary_compressed: two uint32 sizes, LZF data, fields stored one after the other (SoA)
    if len(raw) - pos < 8:
        raise CorruptFileError(f"{path}: binary_compressed PCD has no size words")
    csize, usize = struct.unpack_from("<II", raw, pos)
    need = npts * dtype.itemsize
    if usize != need:
        raise CorruptFileError(f"{path}: binary_compressed PCD uncompressed size {usize} != "
                               f"{need} expected for {npts} points of {dtype.itemsize} bytes")
    comp = raw[pos + 8:pos + 8 + csize]
    if len(comp) != csize:
        raise CorruptFileError(f"{path}: binary_compressed PCD is truncated ({len(comp)} of "
                               f"{csize} compressed bytes)")
    try:
        buf = lzf_decompress(comp, usize)
    except ValueError as exc:
        raise CorruptFileError(f"{path}: corrupt LZF data in binary_compressed PCD: {exc}"
                               ) from None
    out, off = {}, 0
    for n, t, c in specs:
        dt = np.dtype(t) if c == 1 else np.dtype((t, (c,)))
        out[n] = _native(np.frombuffer(buf, dtype=dt, count=npts, offset=off))
        off += npts * dt.itemsize
    return out


def _ascii_packed_color(a):
    """Packed rgb/rgba from ascii PCD as uint32.

    PCL writes ``rgb`` (TYPE F) in ascii as the uint32 of its bits (e.g. 4286611584); older
    writers print the float itself (a tiny denormal-like number). Integral values in
    [0, 2**32) are taken as the uint32, anything else as the float32 whose bits are kept.
    """
    a = np.asarray(a, dtype=np.float64)
    fin = np.isfinite(a)
    v = a[fin]
    if np.all((v == np.floor(v)) & (v >= 0) & (v < 2.0 ** 32)):
        return np.where(fin, a, 0).astype(np.uint32)
    return a.astype(np.float32).view(np.uint32)


def _read_pcd(path):
    raw = path.read_bytes()
    h, pos = _pcd_header(raw, path)
    cols = _pcd_columns(raw, pos, h, path)
    columns = {}
    for name, field_name in zip(h["_names"], h["fields"]):
        a = cols[name]
        if field_name == "_":
            continue  # padding
        if field_name in ("rgb", "rgba") and a.ndim == 1 and a.dtype.itemsize == 4:
            v = a.view(np.uint32)
            columns["red"] = ((v >> 16) & 255).astype(np.uint8)
            columns["green"] = ((v >> 8) & 255).astype(np.uint8)
            columns["blue"] = (v & 255).astype(np.uint8)
            if field_name == "rgba":
                columns["alpha"] = ((v >> 24) & 255).astype(np.uint8)
            continue
        columns[name] = a
    header = {k: v for k, v in h.items() if not k.startswith("_")}
    return _split_named(path, "pcd", columns, header)


def lzf_decompress(data, size):
    """Decompress LZF ``data`` (liblzf format, as in PCD binary_compressed) to ``size`` bytes.

    Uses the C extension ``lzf`` (PyPI ``python-lzf``) when installed, else a pure-Python
    decoder (about 0.6 s for 5 MB of output).

    Parameters
    ----------
    data : bytes-like
        Compressed bytes.
    size : int
        Exact size of the decompressed data.

    Returns
    -------
    bytes

    Raises
    ------
    ValueError
        The data is corrupt or does not decompress to exactly ``size`` bytes.
    """
    if size == 0:
        if len(data):
            raise ValueError(f"{len(data)} compressed bytes for an empty output")
        return b""
    try:
        import lzf
    except ImportError:
        return _lzf_decompress_py(data, size)
    out = lzf.decompress(bytes(data), size)
    if out is None or len(out) != size:
        raise ValueError(f"LZF data does not decompress to {size} bytes")
    return out


def _lzf_decompress_py(data, size):
    """Pure-Python LZF decoder (see :func:`lzf_decompress`)."""
    src = bytes(data)
    out = bytearray(size)
    ip = op = 0
    n = len(src)
    try:
        while ip < n:
            ctrl = src[ip]
            ip += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                ctrl += 1
                if ip + ctrl > n or op + ctrl > size:
                    raise ValueError(f"literal run overflows at input byte {ip - 1}")
                out[op:op + ctrl] = src[ip:ip + ctrl]
                ip += ctrl
                op += ctrl
                continue
            length = ctrl >> 5  # back reference
            if length == 7:
                length += src[ip]
                ip += 1
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                raise ValueError(f"back reference out of range at input byte {ip - 1}")
            dist = op - ref
            if dist >= length:
                out[op:op + length] = out[ref:ref + length]
            else:  # overlapping copy repeats the last `dist` bytes
                out[op:op + length] = (out[ref:op] * (length // dist + 1))[:length]
            op += length
    except IndexError:
        raise ValueError("LZF data is truncated") from None
    if op != size:
        raise ValueError(f"LZF data decompresses to {op} bytes, expected {size}")
    return bytes(out)


# --------------------------------------------------------------------------- LAS / LAZ

def _import_laspy(path, laz):
    hint = LAZ_HINT if laz else 'pip install laspy (or "laspy[lazrs]" for LAZ)'
    try:
        import laspy
    except ImportError:
        raise MissingDependencyError(f"{path}: LAS/LAZ needs the laspy package: {hint}"
                                     ) from None
    if laz and not laspy.LazBackend.detect_available():
        raise MissingDependencyError(f"{path}: LAZ needs a LAZ backend for laspy (none is "
                                     f"installed): {LAZ_HINT}")
    return laspy


def _read_las(path):
    laz = path.suffix.lower() == ".laz"
    laspy = _import_laspy(path, laz)
    try:
        las = laspy.read(str(path))
    except laspy.LaspyException as exc:
        if "backend" in str(exc).lower():
            raise MissingDependencyError(f"{path}: compressed LAS data needs a LAZ backend: "
                                         f"{LAZ_HINT}") from exc
        raise CorruptFileError(f"{path}: cannot read as LAS/LAZ: {exc}") from exc
    points = np.column_stack([np.asarray(las.x, dtype=np.float64),
                              np.asarray(las.y, dtype=np.float64),
                              np.asarray(las.z, dtype=np.float64)])
    columns = {n: _native(np.asarray(las[n])) for n in las.point_format.dimension_names
               if n not in ("X", "Y", "Z")}
    return _split_named(path, "laz" if laz else "las", columns, las.header, points=points)


# --------------------------------------------------------------------------- text

def _is_number(tok):
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _read_text(path):
    names, skip, first_data = None, 0, None
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for i, line in enumerate(f):
            s = line.strip()
            if not s:
                continue
            stripped = s.lstrip("#/").strip() if s.startswith(("#", "//")) else s
            toks = [t for t in re.split(r"[,;\s]+", stripped) if t]
            if toks and all(_is_number(t) for t in toks):
                if s.startswith(("#", "//")):
                    continue  # a commented-out data row
                first_data, skip = s, i
                break
            if s.startswith(("#", "//")) and not {"x", "y", "z"} <= {t.lower() for t in toks}:
                continue  # an ordinary comment
            if names is None:
                names, skip = toks, i + 1
            else:
                raise CorruptFileError(f"{path}: line {i + 1} is not numeric: {s[:80]!r} "
                                       "(expected one header line, then numbers)")
    if first_data is None:  # header only, or empty
        if names is None:
            raise CorruptFileError(f"{path}: no data (expected lines of x y z ...)")
        table = np.empty((0, len(names)))
    else:
        delim = "," if "," in first_data else (";" if ";" in first_data else None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = np.loadtxt(path, dtype=np.float64, delimiter=delim, skiprows=skip,
                               comments=["#", "//"], ndmin=2, encoding="utf-8")
    if names is None:
        return _split_positional(path, "text", table)
    if table.shape[1] != len(names):
        raise CorruptFileError(f"{path}: header names {len(names)} columns {names} but the "
                               f"data has {table.shape[1]}")
    if len(set(names)) != len(names):
        raise CorruptFileError(f"{path}: header has duplicate column names {names}")
    return _split_named(path, "text", {n: table[:, j] for j, n in enumerate(names)})


# --------------------------------------------------------------------------- NumPy

def _read_npy(path):
    a = np.load(path, allow_pickle=False)
    if a.dtype.names:
        if a.ndim != 1:
            raise CorruptFileError(f"{path}: expected a 1-D structured array, got shape "
                                   f"{a.shape}")
        return _split_named(path, "npy", {n: _native(a[n]) for n in a.dtype.names})
    if a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[1] < 3:
        raise CorruptFileError(f"{path}: expected an (N, 3) or (N, >=3) numeric array, got "
                               f"shape {a.shape} dtype {a.dtype}")
    return _split_positional(path, "npy", a.astype(np.float64))


def _read_npz(path):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    pts = arrays.pop("points", None)
    if pts is None or pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "fiu":
        raise CorruptFileError(f"{path}: expected a numeric 'points' array of shape (N, 3); "
                               f"keys: {list(arrays) + (['points'] if pts is not None else [])}")
    n = len(pts)
    normals = arrays.pop("normals", None)
    if normals is not None and normals.shape != (n, 3):
        raise CorruptFileError(f"{path}: 'normals' has shape {normals.shape}, expected "
                               f"{(n, 3)}")
    attributes = {k: v for k, v in arrays.items() if v.ndim >= 1 and len(v) == n}
    extra = {k: v for k, v in arrays.items() if k not in attributes}
    return _finish(path, "npz", pts, normals, attributes, extra or None)


_READERS = {".ply": _read_ply, ".pcd": _read_pcd, ".las": _read_las, ".laz": _read_las,
            ".xyz": _read_text, ".xyzn": _read_text, ".txt": _read_text, ".csv": _read_text,
            ".asc": _read_text, ".npy": _read_npy, ".npz": _read_npz}


# --------------------------------------------------------------------------- write

def write(path, points, fields=None, normals=None, like=None):
    """Write points, optional normals and per-point fields; the format follows the extension.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its extension is one of :data:`WRITE_FORMATS`.
    points : (N, 3) array_like
        Coordinates (any real dtype; written from float64).
    fields : dict of str -> (N,) array_like, optional
        Per-point scalars such as ``mean_curvature``, ``gaussian_curvature``, ``k1``, ``k2``,
        ``surface_variation``. Names must match ``[A-Za-z_][A-Za-z0-9_.-]*`` and must not be
        x, y, z, nx, ny, nz or normal_x/y/z (any case). Written in the given order.
    normals : (N, 3) array_like, optional
        Unit normals.
    like : Cloud, optional
        Only for LAS/LAZ output: a Cloud read from a LAS/LAZ file with the same number of
        points. Its header (version, point format, scales, offsets, VLRs) and its attributes
        (classification, intensity, GPS time, extra bytes...) are kept. Ignored for the other
        formats.

    Returns
    -------
    pathlib.Path
        The file written.

    Raises
    ------
    WriteError
        Unknown extension, bad shapes or names, NaN coordinates in LAS, coordinates out of
        the range of the LAS scale and offset, or a field that LAS cannot hold.
    MissingDependencyError
        LAS needs ``laspy``, LAZ needs ``laspy[lazrs]``.

    Notes
    -----
    * **PLY**: binary little-endian, vertex element only: ``x y z`` as ``double`` (float32
      would lose the digits of georeferenced coordinates), ``nx ny nz`` as ``float``, then each
      field as a ``float`` property, or an integer property of the same type for integer
      fields (int64/uint64 as int32/uint32 when in range, bool as uchar). NaN is written as
      NaN. CloudCompare and MeshLab show the extra properties as scalar fields.
    * **LAS/LAZ**: with ``like``, the points are stored with its scales and offsets (a point
      read from that file is written back to the same integer), original dimensions are
      copied from ``like.attributes``, and each field is added as an extra-bytes dimension
      (float32, or its integer type) through ``laspy.ExtraBytesParams``; a field named like
      an existing dimension (e.g. ``classification``) overwrites it. Without ``like``: LAS
      1.4, point format 6, scale 0.001 on each axis, offsets = the per-axis minimum, so
      coordinates are kept within 0.0005 units. Normals are stored as float32 extra
      dimensions ``nx, ny, nz``. LAS cannot hold NaN coordinates (WriteError).
    * **NPZ**: ``points`` (float64), ``normals`` and each field by name, dtypes unchanged.
    * **CSV/TXT/XYZ**: a header line ``x,y,z[,nx,ny,nz][,fields...]`` (space-separated for
      .txt/.xyz), then points with ``%.17g`` (float64 round-trips exactly), normals and float
      fields with ``%.9g`` (exact for float32), integer fields with ``%d``; NaN as ``nan``.
    """
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    writer = _WRITERS.get(ext)
    if writer is None:
        raise WriteError(f"{path}: cannot write extension {ext or '(none)'!r}; expected one "
                         f"of {', '.join(WRITE_FORMATS)}")
    pts = np.asarray(points)
    if pts.dtype.kind not in "fiu" or pts.ndim != 2 or pts.shape[1] != 3:
        raise WriteError(f"{path}: points must be a real (N, 3) array, got shape {pts.shape} "
                         f"dtype {pts.dtype}")
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    n = len(pts)
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (n, 3) or normals.dtype.kind not in "fiu":
            raise WriteError(f"{path}: normals must be a real ({n}, 3) array, got shape "
                             f"{normals.shape} dtype {normals.dtype}")
    fields = _check_fields(path, fields, n)
    writer(path, pts, fields, normals, like)
    return path


def _check_fields(path, fields, n):
    out = {}
    for name, values in (fields or {}).items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise WriteError(f"{path}: field name {name!r} must match [A-Za-z_][A-Za-z0-9_.-]*")
        if name.lower() in _RESERVED:
            raise WriteError(f"{path}: field name {name!r} is reserved for coordinates or "
                             "normals")
        a = np.asarray(values)
        if a.shape != (n,):
            raise WriteError(f"{path}: field {name!r} must have shape ({n},), got {a.shape}")
        if a.dtype.kind == "b":
            a = a.astype(np.uint8)
        if a.dtype.kind not in "fiu":
            raise WriteError(f"{path}: field {name!r} must be numeric, got dtype {a.dtype}")
        out[name] = a
    return out


def _int_as(path, name, a, allowed):
    """The dtype for integer field ``a``: its own if in ``allowed``, else the 32-bit type of
    the same signedness when the values fit (int64 -> int32, uint64 -> uint32)."""
    if a.dtype in allowed:
        return a.dtype
    dt = np.dtype(np.int32 if a.dtype.kind == "i" else np.uint32)
    if a.size == 0 or (a.min() >= np.iinfo(dt).min and a.max() <= np.iinfo(dt).max):
        return dt
    raise WriteError(f"{path}: integer field {name!r} ({a.dtype}) has values outside the "
                     f"range of {dt}, the widest integer type of this format")


_PLY_INTS = [np.dtype(t) for t in ("i1", "u1", "i2", "u2", "i4", "u4")]


def _write_ply(path, pts, fields, normals, like):
    import plyfile
    spec = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        spec += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    for name, a in fields.items():
        dt = np.dtype("<f4") if a.dtype.kind == "f" else _int_as(path, name, a, _PLY_INTS)
        spec.append((name, dt.newbyteorder("<")))
    rec = np.empty(len(pts), dtype=spec)
    rec["x"], rec["y"], rec["z"] = pts.T
    if normals is not None:
        rec["nx"], rec["ny"], rec["nz"] = np.asarray(normals, dtype=np.float64).T
    for name, a in fields.items():
        rec[name] = a
    el = plyfile.PlyElement.describe(rec, "vertex")
    plyfile.PlyData([el], text=False, byte_order="<", comments=["written by clcurv"]
                    ).write(str(path))


_LAS_INTS = [np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8")]


def _write_las(path, pts, fields, normals, like):
    laz = path.suffix.lower() == ".laz"
    laspy = _import_laspy(path, laz)
    if not np.isfinite(pts).all():
        raise WriteError(f"{path}: LAS cannot store NaN/Inf coordinates "
                         f"({int((~np.isfinite(pts).all(axis=1)).sum())} rows)")
    n = len(pts)
    if like is not None:
        if not isinstance(getattr(like, "header", None), laspy.LasHeader):
            raise WriteError(f"{path}: like= must be a Cloud read from a LAS/LAZ file")
        if len(like.points) != n:
            raise WriteError(f"{path}: like= has {len(like.points)} points but {n} are given")
        header = copy.deepcopy(like.header)
        keep = dict(like.attributes)
        if normals is None and like.normals is not None:
            normals = like.normals
    else:
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = pts.min(axis=0) if n else np.zeros(3)
        keep = {}
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    ints = np.round((pts - offsets) / scales)
    if n and (ints.min() < -2**31 or ints.max() > 2**31 - 1):
        raise WriteError(f"{path}: coordinates do not fit LAS int32 with scales {scales} and "
                         f"offsets {offsets}")
    columns = dict(fields)
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        columns = {"nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], **columns}
    existing = set(header.point_format.dimension_names)
    new = []
    for name, a in columns.items():
        if name in existing:
            continue
        if len(name) > 32:
            raise WriteError(f"{path}: LAS extra-bytes names have at most 32 characters: "
                             f"{name!r}")
        dt = np.dtype("f4") if a.dtype.kind == "f" else _int_as(path, name, a, _LAS_INTS)
        new.append(laspy.ExtraBytesParams(name=name, type=dt, description="clcurv"))
    las = laspy.LasData(header, points=laspy.ScaleAwarePointRecord.zeros(n, header=header))
    if new:
        las.add_extra_dims(new)
    las.X, las.Y, las.Z = (ints[:, i].astype(np.int32) for i in range(3))
    try:
        for name, a in {**keep, **columns}.items():
            if name in las.point_format.dimension_names:
                las[name] = a
    except (ValueError, OverflowError, laspy.LaspyException) as exc:
        raise WriteError(f"{path}: cannot store field {name!r} in LAS point format "
                         f"{header.point_format.id}: {exc}") from exc
    las.write(str(path))


def _write_npz(path, pts, fields, normals, like):
    clash = {"points", "normals"} & set(fields)
    if clash:
        raise WriteError(f"{path}: field names {sorted(clash)} are reserved in NPZ")
    arrays = {"points": pts}
    if normals is not None:
        arrays["normals"] = np.asarray(normals)
    arrays.update(fields)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _write_text(path, pts, fields, normals, like):
    delim = "," if path.suffix.lower() == ".csv" else " "
    names = ["x", "y", "z"]
    cols, fmts = [pts[:, 0], pts[:, 1], pts[:, 2]], ["%.17g"] * 3
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        names += ["nx", "ny", "nz"]
        cols += [nrm[:, 0], nrm[:, 1], nrm[:, 2]]
        fmts += ["%.9g"] * 3
    for name, a in fields.items():
        names.append(name)
        cols.append(a)
        fmts.append("%.9g" if a.dtype.kind == "f" else "%d")
    rec = np.empty(len(pts), dtype=[(f"f{i}", c.dtype) for i, c in enumerate(cols)])
    for i, c in enumerate(cols):
        rec[f"f{i}"] = c
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(delim.join(names) + "\n")
        np.savetxt(f, rec, fmt=fmts, delimiter=delim)


_WRITERS = {".ply": _write_ply, ".las": _write_las, ".laz": _write_las, ".npz": _write_npz,
            ".csv": _write_text, ".txt": _write_text, ".xyz": _write_text}
