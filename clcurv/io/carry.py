"""What an output keeps of its input's per-point attributes (``write(..., like=cloud)``).

A LAS/LAZ output from a LAS/LAZ input keeps its header and every dimension
(:mod:`clcurv.io.las`); from another format, the attributes as extra bytes by the rules
below (kind ``"las"``: every numeric type kept, names of at most 32 characters, a name of
the point format's dimensions suffixed ``_input``) and a colour triple as LAS RGB
(:func:`clcurv.io.las.carried_plan`). The other outputs (PLY, NPZ, CSV/TXT/XYZ) keep the attributes of
``like`` (colours, intensity, classification, GPS time, confidence, a PCD's packed
``rgb``...) whatever format it was read from, between the normals and the computed fields,
in the input's order, so that ``clcurv compute scan.ply -o out.ply`` does not lose the
scan's colours:

- values as read, in their dtype where the format has it: PLY keeps float32, float64 and
  the 8-, 16- and 32-bit integers, writes bool as uchar and 64-bit integers as 32-bit ones
  when every value fits (else WriteError, as for a field); text writes float64 with
  ``%.17g``, float32 with ``%.9g``, integers with ``%d``; NPZ keeps every array as it is;
- a computed field of the same name replaces the attribute (a second run's
  ``mean_curvature`` replaces the first's);
- names: in PLY, text and LAS, characters outside ``[A-Za-z0-9_.-]`` become ``_`` (a LAS
  extra dimension "Amplitude Value" is ``Amplitude_Value``) and a leading digit gets a
  ``_``; an attribute named like a coordinate or normal component (a lone ``nx`` that was
  not part of a normal triple) gets the suffix ``_input``; in NPZ so do ``points`` and
  ``normals``; names that then coincide get ``_2``, ``_3``...;
- an ``(N, k)`` attribute (a PCD field with COUNT > 1) is k columns ``name_0`` ..
  ``name_{k-1}`` in PLY and text, one array in NPZ;
- attributes PLY or text cannot hold (strings, complex, objects) and object arrays in NPZ
  are left out with a warning naming them;
- when no normals are written (``normals=None``), the input's normals are.

The tiled writers (:mod:`clcurv.io.stream`) take the same :func:`plan` over the sources'
attribute dtypes and :func:`columns` over each chunk, so an output written in tiles equals
the one written in memory byte for byte.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass

import numpy as np

from .common import RESERVED, Cloud, WriteError

#: output kinds of :func:`plan`: PLY, text (CSV/TXT/XYZ), NPZ, and LAS/LAZ extra bytes (from
#: an input of another format: clcurv.io.las)
KINDS = ("ply", "text", "npz", "las")
#: longest name of each kind (LAS extra bytes: 32 characters)
_NAME_LIMIT = {"las": 32}
_UNSAFE = re.compile(r"[^A-Za-z0-9_.\-]")
#: integer dtypes PLY holds (64-bit ones go to the 32-bit type of their sign, values checked)
_PLY_INTS = {np.dtype(t) for t in ("i1", "u1", "i2", "u2", "i4", "u4")}


@dataclass(frozen=True)
class Column:
    """One carried output column: its name, the input attribute ``src`` (column ``col`` of
    an (N, k) attribute, None for an (N,) one) and the dtype written (:func:`plan`)."""
    name: str
    src: str
    col: int | None
    dtype: np.dtype


def specs_of(attributes):
    """{name: (dtype, trailing shape)} of a Cloud's attributes (what :func:`plan` takes)."""
    return {k: (np.asarray(v).dtype, np.asarray(v).shape[1:]) for k, v in attributes.items()}


def _out_dtype(dt, kind):
    """The dtype ``kind`` writes for input dtype ``dt``, or None when it cannot hold it."""
    if kind == "npz":
        return None if dt.kind == "O" else dt.newbyteorder("=")
    if dt.kind == "b":
        return np.dtype("u1")
    if dt.kind == "f" and dt.itemsize in (4, 8):
        return dt.newbyteorder("=")
    if dt.kind == "f" and dt.itemsize < 4:
        return np.dtype("f4")
    if dt.kind in "iu":
        if kind == "ply" and dt not in _PLY_INTS:
            return np.dtype("i4" if dt.kind == "i" else "u4")
        return dt.newbyteorder("=")
    return None


def _fit(stem, suffix, limit):
    """``stem + suffix`` within ``limit`` characters (the stem shortened)."""
    return (stem if limit is None else stem[:limit - len(suffix)]) + suffix


def _safe_name(name, kind, reserved):
    if kind == "npz":
        return f"{name}_input" if name in ("points", "normals") else name
    out = _UNSAFE.sub("_", str(name)) or "_"
    if not (out[0].isalpha() or out[0] == "_"):
        out = "_" + out
    limit = _NAME_LIMIT.get(kind)
    if out.lower() in RESERVED or out.lower() in reserved:
        return _fit(out, "_input", limit)
    return _fit(out, "", limit)


def plan(path, specs, fields, kind, reserved=()):
    """The carried columns (a list of :class:`Column`, output order) of attributes
    ``specs`` ({name: (dtype, trailing shape)}, input order) beside the computed ``fields``
    (names) in a ``kind`` output (see the module notes); ``reserved``: more names (lower
    case) that take the suffix ``_input`` (the LAS point format's own dimensions). Warns
    for what is left out."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    reserved = {r.lower() for r in reserved}
    limit = _NAME_LIMIT.get(kind)
    taken, out, left = set(fields), [], []
    for src, (dt, trailing) in specs.items():
        dt = np.dtype(dt)
        odt = _out_dtype(dt, kind)
        width = int(np.prod(trailing)) if len(trailing) else None
        if odt is None or (kind != "npz" and len(trailing) > 1):
            shape = f", shape (N, {', '.join(map(str, trailing))})" if trailing else ""
            left.append(f"{src} ({dt}{shape})")
            continue
        base = _safe_name(src, kind, reserved)
        if base in fields:
            continue                        # the computed field replaces it
        cols = [None] if width is None or kind == "npz" else list(range(width))
        for c in cols:
            stem = base if c is None else _fit(base, f"_{c}", limit)
            name, i = stem, 2
            while name in taken:
                name, i = _fit(stem, f"_{i}", limit), i + 1
            taken.add(name)
            out.append(Column(name, src, c, odt))
    if left:
        warnings.warn(f"{path}: the input's attributes {', '.join(left)} cannot be written "
                      f"to this format and are left out", RuntimeWarning, stacklevel=4)
    return out


def columns(path, plan_, attributes):
    """{output name: array} of the carried columns ``plan_`` from ``attributes`` (name ->
    array, the rows to write): each in its planned dtype; WriteError when a 64-bit integer
    does not fit the 32-bit type PLY writes it as."""
    out = {}
    for c in plan_:
        a = np.asarray(attributes[c.src])
        if c.col is not None:
            a = a.reshape(len(a), -1)[:, c.col]
        if a.dtype.kind in "iu" and c.dtype.kind in "iu" and a.dtype.itemsize > c.dtype.itemsize:
            info = np.iinfo(c.dtype)
            if a.size and (a.min() < info.min or a.max() > info.max):
                raise WriteError(f"{path}: the input's integer attribute {c.src!r} "
                                 f"({a.dtype}) has values outside the range of {c.dtype}, "
                                 "the widest integer type of this format")
        out[c.name] = a.astype(c.dtype, copy=False)
    return out


def check_like(path, like, n):
    """WriteError unless ``like`` is None or a :class:`Cloud` of ``n`` points whose
    attributes have a row per point."""
    if like is None:
        return
    if not isinstance(like, Cloud):
        raise WriteError(f"{path}: like= must be a Cloud (from clcurv.io.read), got "
                         f"{type(like).__name__}")
    if len(like.points) != n:
        raise WriteError(f"{path}: like= has {len(like.points)} points but {n} are given")
    bad = [k for k, v in like.attributes.items() if np.shape(v)[:1] != (n,)]
    if bad:
        raise WriteError(f"{path}: like='s attributes {bad} do not have one row per point "
                         f"({n})")


def from_like(path, like, n, fields, normals, kind):
    """({output name: array} carried from ``like``, the normals to write) for a ``kind``
    output of ``n`` points with computed ``fields`` and ``normals`` (None: ``like``'s).
    ``like`` None carries nothing; anything but a :class:`Cloud` of n points is a
    WriteError (:func:`check_like`)."""
    check_like(path, like, n)
    if like is None:
        return {}, normals
    cols = columns(path, plan(path, specs_of(like.attributes), fields, kind),
                   like.attributes)
    return cols, like.normals if normals is None else normals
