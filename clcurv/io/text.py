"""Text tables: ``.xyz``, ``.xyzn``, ``.txt``, ``.csv`` and ``.asc`` (read); ``.csv``, ``.txt``
and ``.xyz`` (write).

Reading
-------
Comma-, semicolon- or whitespace-separated (from the first data line); lines starting with
``#`` or ``//`` are comments, except a header. A header is the first non-blank line that is
not all numbers, is not a comment, or is a comment naming x, y and z (its ``#`` or ``//`` is
stripped, so CloudCompare's ``//X,Y,Z,...`` works); columns named x, y, z are then required,
``nx ny nz`` / ``normal_x...`` are normals, other columns are attributes by name (float64).
Without a header, columns 0-2 are x, y, z; if there are **exactly 6 columns and columns 3-5
are unit vectors** (| |n| - 1 | <= 1e-3 on every row where they are finite) they are the
normals; otherwise columns 3, 4, ... are attributes ``col3``, ``col4``, ...
``Cloud.format`` is ``'text'``; there is no header object.

Writing
-------
A header line ``x,y,z[,nx,ny,nz][,attributes...][,fields...]`` (space-separated for
.txt/.xyz; the attributes are the input's, ``like=``, :mod:`clcurv.io.carry`), then points
with ``%.17g`` (float64 round-trips exactly), normals and float fields with ``%.9g`` (exact
for float32), float64 attributes with ``%.17g``, integers with ``%d``; NaN as ``nan``.
Lines end with ``\\n``.
"""
from __future__ import annotations

import re

import numpy as np

from .common import CorruptFileError, Format, quiet, split_named, split_positional

_COMMENTS = ("#", "//")
#: a leading UTF-8 BOM (Excel's CSV) is dropped; a non-UTF-8 byte (a latin-1 comment)
#: becomes U+FFFD instead of stopping the reader
_OPEN = {"encoding": "utf-8-sig", "errors": "replace"}


# --------------------------------------------------------------------------- read

def _is_number(tok):
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _scan(path):
    """(header names or None, lines to skip before the data, first data line or None)."""
    names, skip, first_data = None, 0, None
    with open(path, "r", **_OPEN) as f:
        for i, line in enumerate(f):
            s = line.strip()
            if not s:
                continue
            stripped = s.lstrip("#/").strip() if s.startswith(_COMMENTS) else s
            toks = [t for t in re.split(r"[,;\s]+", stripped) if t]
            if toks and all(_is_number(t) for t in toks):
                if s.startswith(_COMMENTS):
                    continue  # a commented-out data row
                first_data, skip = s, i
                break
            if s.startswith(_COMMENTS) and not {"x", "y", "z"} <= {t.lower() for t in toks}:
                continue  # an ordinary comment
            if names is None:
                names, skip = toks, i + 1
            else:
                raise CorruptFileError(f"{path}: line {i + 1} is not numeric: {s[:80]!r} "
                                       "(expected one header line, then numbers)")
    return names, skip, first_data


def _load(path, names, skip, first_data):
    """The numeric table after the header, (0, len(names)) when there is no data row."""
    if first_data is None:  # header only, or empty
        if names is None:
            raise CorruptFileError(f"{path}: no data (expected lines of x y z ...)")
        return np.empty((0, len(names)))
    delim = "," if "," in first_data else (";" if ";" in first_data else None)
    with quiet(), open(path, "r", **_OPEN) as f:
        return np.loadtxt(f, dtype=np.float64, delimiter=delim, skiprows=skip,
                          comments=list(_COMMENTS), ndmin=2)


def read(path):
    names, skip, first_data = _scan(path)
    table = _load(path, names, skip, first_data)
    if names is None:
        return split_positional(path, "text", table)
    if table.shape[1] != len(names):
        raise CorruptFileError(f"{path}: header names {len(names)} columns {names} but the "
                               f"data has {table.shape[1]}")
    if len(set(names)) != len(names):
        raise CorruptFileError(f"{path}: header has duplicate column names {names}")
    return split_named(path, "text", {n: table[:, j] for j, n in enumerate(names)})


# --------------------------------------------------------------------------- write

def _columns(pts, fields, normals, carried):
    """(names, columns, printf formats) in file order."""
    names = ["x", "y", "z"]
    cols, fmts = [pts[:, 0], pts[:, 1], pts[:, 2]], ["%.17g"] * 3
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        names += ["nx", "ny", "nz"]
        cols += [nrm[:, 0], nrm[:, 1], nrm[:, 2]]
        fmts += ["%.9g"] * 3
    for name, a in carried.items():     # the input's attributes, float64 to the last digit
        names.append(name)
        cols.append(a)
        fmts.append(("%.17g" if a.dtype.itemsize == 8 else "%.9g") if a.dtype.kind == "f"
                    else "%d")
    for name, a in fields.items():
        names.append(name)
        cols.append(a)
        fmts.append("%.9g" if a.dtype.kind == "f" else "%d")
    return names, cols, fmts


def write(path, pts, fields, normals, like, carried):
    delim = "," if path.suffix.lower() == ".csv" else " "
    names, cols, fmts = _columns(pts, fields, normals, carried)
    rec = np.empty(len(pts), dtype=[(f"f{i}", c.dtype) for i, c in enumerate(cols)])
    for i, c in enumerate(cols):
        rec[f"f{i}"] = c
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(delim.join(names) + "\n")
        np.savetxt(f, rec, fmt=fmts, delimiter=delim)


FORMAT = Format(
    reads={".xyz": "text (x y z ...)", ".xyzn": "text (x y z nx ny nz)",
           ".txt": "text (x y z ...)", ".csv": "text (x,y,z,...)", ".asc": "text (x y z ...)"},
    read=read,
    writes={".csv": "comma-separated text with a header line",
            ".txt": "space-separated text with a header line",
            ".xyz": "space-separated text with a header line"},
    write=write, carries="text")
