"""PLY (``.ply``): ascii, binary little-endian or binary big-endian.

Reading
-------
Only the ``vertex`` element is read; other elements (faces, range grids, triangle strips)
are skipped and list properties of the vertex are ignored, but their rows must be in the
file: a file cut anywhere is a CorruptFileError, never a cloud read as whole (binary rows
after the vertices are measured, :func:`check_binary_rest`). ``x y z`` are the points,
``nx ny nz`` or ``normal_x normal_y normal_z`` (case-insensitive) the normals, every other
scalar property an attribute in its file dtype. ``Cloud.header`` is a dict: ``format``,
``elements`` (name -> count), ``comments`` and ``obj_info``.

plyfile parses ascii rows one by one in Python (seconds for the Stanford scans with their
faces or range grids). When the vertex element comes first and has only scalar properties
(the usual case), its rows alone are parsed with NumPy (``frombuffer`` for binary,
``loadtxt`` for ascii) from the header parsed here; otherwise plyfile reads the whole file.

Writing
-------
Binary little-endian, vertex element only, comment ``written by clcurv``: ``x y z`` as
``double`` (float32 would lose the digits of georeferenced coordinates), ``nx ny nz`` as
``float``, then the input's attributes (``like=``: colours, intensity... in their own
types, :mod:`clcurv.io.carry`), then each field as a ``float`` property, or an integer
property of the same type for integer fields (int64/uint64 as int32/uint32 when in range,
bool as uchar). NaN is written as NaN. CloudCompare and MeshLab show the extra properties
as scalar fields.
"""
from __future__ import annotations

import io
import re

import numpy as np
import plyfile

from .common import (CorruptFileError, Format, check_claim, int_as, quiet, split_named,
                     struct_columns)

TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2",
         "ushort": "u2", "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4",
         "int32": "i4", "uint32": "u4", "float": "f4", "float32": "f4",
         "double": "f8", "float64": "f8"}
_INTS = [np.dtype(t) for t in ("i1", "u1", "i2", "u2", "i4", "u4")]
#: bytes of each type name plyfile accepts (its aliases i1 ... f8 included)
_SIZES = {**{name: np.dtype(t).itemsize for name, t in TYPES.items()},
          **{t: np.dtype(t).itemsize for t in ("i1", "u1", "i2", "u2", "i4", "u4", "f4",
                                                "f8")}}


# --------------------------------------------------------------------------- read

def parse_header(raw, path):
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
    for name, count, block in elements:
        if count and len(block) == 1:
            raise CorruptFileError(f"{path}: PLY element {name!r} claims {count} rows but "
                                   "has no properties")
    return fmt, preamble, elements, m.end()


def _min_row_bytes(block, fmt):
    """The fewest bytes one row of an element (header lines ``block``) takes: in binary the
    sizes of its scalars and list lengths (an empty list), in ascii two per value (a digit
    and a separator; a list at least its length). An unknown type counts 1 byte (plyfile
    rejects it before reading any data)."""
    props = [ln.split() for ln in block[1:]]
    if fmt == "ascii":
        return 2 * len(props)
    types = [p[2] if p[1:2] == ["list"] and len(p) > 2 else (p[1:2] or [""])[0]
             for p in props]
    return sum(_SIZES.get(t, 1) for t in types)


def _check_elements(path, fmt, elements, have):
    """CorruptFileError unless the rows that the header claims can fit in the ``have``
    bytes after the header (checked before plyfile allocates every element)."""
    need = sum(count * _min_row_bytes(block, fmt) for _, count, block in elements)
    claim = "elements " + ", ".join(f"{name} {count}" for name, count, _ in elements)
    check_claim(path, claim, need - 1 if fmt == "ascii" and need else need, have,
                exact=False)


def _ascii_header(raw, start):
    """``raw`` with every non-ASCII byte of the header replaced by ``?`` (plyfile decodes
    the header as strict ASCII; a latin-1 comment would stop it)."""
    return raw[:start].translate(_TO_ASCII) + raw[start:]


_TO_ASCII = bytes(range(128)) + b"?" * 128


def _preamble_values(preamble, keyword):
    """The text after ``keyword`` on each preamble line starting with it."""
    return [ln.split(None, 1)[1] if " " in ln else ""
            for ln in preamble if ln.split()[0] == keyword]


def _binary_vertices(raw, start, n, props, fmt, path, later=()):
    """The vertex rows of a binary PLY whose first element is the vertex element with
    scalar properties; ``later``: the elements after it ([name, count, header lines]), whose
    rows must be in the file too (:func:`check_binary_rest`)."""
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(p[2], order + TYPES[p[1]]) for p in props])
    check_claim(path, f"{n} vertices of {dtype.itemsize} bytes", n * dtype.itemsize,
                len(raw) - start)
    check_binary_rest(path, raw, start, start + n * dtype.itemsize, later, order)
    return struct_columns(np.frombuffer(raw, dtype=dtype, count=n, offset=start))


def check_binary_rest(path, raw, start, at, elements, order, whole=True):
    """CorruptFileError unless the binary rows of ``elements`` fit in ``raw`` from byte
    ``at``: a file cut inside its faces read as whole before. A row of scalars has a fixed
    size; a row with one list (faces: ``list uchar int vertex_indices``) is measured when
    every row has the list length of the first (triangles, quads), else the rows are read
    by plyfile (which fails on a cut file), slower but exact; with ``whole`` false (the
    tiled source, which does not hold the file in memory) those rows are not checked.
    Bytes after the last row are allowed."""
    for name, count, block in elements:
        props = [ln.split() for ln in block[1:]]
        lists = [i for i, p in enumerate(props) if p[1:2] == ["list"]]
        if not count:
            continue
        if any(len(p) != (5 if p[1:2] == ["list"] else 3) for p in props) or len(lists) > 1 \
                or any(t not in TYPES for p in props for t in
                       (p[2:4] if p[1:2] == ["list"] else p[1:2])):
            return _check_by_plyfile(path, raw, start) if whole else None
        sizes = [np.dtype(TYPES[p[1]]).itemsize for p in props if p[1:2] != ["list"]]
        exact = True
        if not lists:
            need = count * sum(sizes)
        else:
            i = lists[0]
            head = sum(np.dtype(TYPES[p[1]]).itemsize for p in props[:i])
            ctype = np.dtype(order + TYPES[props[i][2]])
            item = np.dtype(TYPES[props[i][3]]).itemsize
            exact = at + head + ctype.itemsize <= len(raw)
            if not exact:
                need = head + ctype.itemsize         # not even the first length is there
            else:
                first = int(np.frombuffer(raw, ctype, 1, at + head)[0])
                if first < 0:                       # a signed length: not a PLY row
                    return _check_by_plyfile(path, raw, start) if whole else None
                row = sum(sizes) + ctype.itemsize + first * item
                have = min(count, (len(raw) - at - head - ctype.itemsize) // row + 1)
                lens = np.array(np.ndarray((have,), ctype, raw, at + head, (row,)))  # copy
                if not (lens == first).all():
                    return _check_by_plyfile(path, raw, start) if whole else None
                need = count * row
        check_claim(path, f"elements {name} {count} (after the vertices)", need,
                    len(raw) - at, exact=exact)
        at += need


def _check_by_plyfile(path, raw, start):
    """Read the whole file with plyfile, which raises on rows missing from it."""
    try:
        with quiet():
            plyfile.PlyData.read(io.BytesIO(_ascii_header(raw, start)))
    except Exception as exc:  # noqa: BLE001 - plyfile's errors for a short file vary
        raise CorruptFileError(f"{path}: the rows after the vertices cannot be read "
                               f"(truncated?): {type(exc).__name__}: {exc}") from exc


def _ascii_vertices(raw, start, n, props, path, later=0):
    """One vertex per line (``later``: the rows of the elements after the vertices)."""
    dtype = np.dtype([(p[2], TYPES[p[1]]) for p in props])
    # each value takes a digit and a separator: bound the rows before loadtxt allocates them
    check_claim(path, f"{n} vertices of {len(props)} values", 2 * n * len(props) - 1,
                len(raw) - start, exact=False)
    _check_ascii_lines(path, raw, start, n, later)
    with quiet():  # loadtxt warns on an empty body
        v = np.loadtxt(io.StringIO(raw[start:].decode("ascii", errors="replace")),
                       dtype=dtype, ndmin=1, max_rows=n, comments=None)
    if len(v) != n:
        raise CorruptFileError(f"{path}: PLY header says {n} vertices but the ascii data "
                               f"has {len(v)} lines")
    return struct_columns(v)


def _check_ascii_lines(path, raw, start, n, later):
    """CorruptFileError unless the ascii body has a line for each of the ``n`` vertices and
    ``later`` rows of the elements after them, and, when the vertices are the last rows, a
    newline after the last one: a file cut inside its last vertex line parsed as a shorter
    number (z -0.0197253 read as -0.0), and one cut before its other elements was read as
    if whole."""
    body = raw[start:]
    end = body.rstrip(b" \t")
    lines = body.count(b"\n") + (1 if end and not end.endswith(b"\n") else 0)
    if lines < n + later:
        raise CorruptFileError(f"{path}: PLY header says {n} vertices and {later} rows of "
                               f"other elements but the ascii data has {lines} lines "
                               "(truncated?)")
    if not later and n and end and not end.endswith((b"\n", b"\r")):
        raise CorruptFileError(f"{path}: the ascii PLY data ends inside its last line "
                               "(truncated?): the last vertex may be cut short; if "
                               "the file is whole, end it with a newline")


def _vertex_columns(raw, path):
    """Columns of the PLY vertex element and the header dict (see the module docstring)."""
    fmt, preamble, elements, start = parse_header(raw, path)
    counts = {e[0]: e[1] for e in elements}
    header = {"format": fmt, "elements": counts,
              "comments": _preamble_values(preamble, "comment"),
              "obj_info": _preamble_values(preamble, "obj_info")}
    if "vertex" not in counts:
        raise CorruptFileError(f"{path}: PLY file has no 'vertex' element (elements: "
                               f"{list(counts)})")
    _, n, block = elements[0]
    props = [ln.split() for ln in block[1:]]
    simple = elements[0][0] == "vertex" and all(
        len(p) == 3 and p[1] in TYPES for p in props)
    if simple and fmt != "ascii":
        return _binary_vertices(raw, start, n, props, fmt, path, elements[1:]), header
    if simple:
        return _ascii_vertices(raw, start, n, props, path,
                               sum(e[1] for e in elements[1:])), header
    _check_elements(path, fmt, elements, len(raw) - start)
    with quiet():  # plyfile warns on empty ascii elements
        ply = plyfile.PlyData.read(io.BytesIO(_ascii_header(raw, start)))
    return struct_columns(ply["vertex"].data), header


def read(path):
    columns, header = _vertex_columns(path.read_bytes(), path)
    return split_named(path, "ply", columns, header)


# --------------------------------------------------------------------------- write

def vertex_dtype(path, fields, with_normals, carried=None):
    """The vertex record: x y z double, nx ny nz float, the carried attributes in their
    dtype (clcurv.io.carry), the fields (float, or their integer type)."""
    spec = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if with_normals:
        spec += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    spec += [(name, np.dtype(a.dtype).newbyteorder("<")) for name, a in (carried or {}).items()]
    for name, a in fields.items():
        dt = np.dtype("<f4") if a.dtype.kind == "f" else int_as(path, name, a, _INTS)
        spec.append((name, dt.newbyteorder("<")))
    return spec


def write(path, pts, fields, normals, like, carried):
    rec = np.empty(len(pts), dtype=vertex_dtype(path, fields, normals is not None, carried))
    rec["x"], rec["y"], rec["z"] = pts.T
    if normals is not None:
        rec["nx"], rec["ny"], rec["nz"] = np.asarray(normals, dtype=np.float64).T
    for name, a in {**carried, **fields}.items():
        rec[name] = a
    el = plyfile.PlyElement.describe(rec, "vertex")
    plyfile.PlyData([el], text=False, byte_order="<", comments=["written by clcurv"]
                    ).write(str(path))


FORMAT = Format(reads={".ply": "PLY (ascii or binary; the vertex element of a mesh)"},
                read=read, writes={".ply": "binary little-endian PLY"}, write=write,
                carries="ply")
