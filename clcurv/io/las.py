"""LAS (``.las``) and LAZ (``.laz``, compressed LAS) through ``laspy``.

``laspy`` is needed for both, and a LAZ backend (``pip install "laspy[lazrs]"``) for LAZ;
without them reading and writing raise :class:`MissingDependencyError` saying what to
install.

Reading
-------
``points`` equal ``las.x, las.y, las.z`` (X * scale + offset in float64). Every other
dimension (intensity, classification, return_number, gps_time, red, ..., extra bytes) is an
attribute; extra dimensions named ``nx, ny, nz`` are the normals. ``Cloud.header`` is the
``laspy.LasHeader``; ``Cloud.format`` is ``'las'`` or ``'laz'``.

Writing
-------
With ``like`` (a Cloud read from a LAS/LAZ file with the same number of points): its header
(version, point format, scales, offsets, VLRs) is kept, so a point read from that file is
written back to the same integer; its attributes (classification, intensity, GPS time,
extra bytes...) are copied, and its normals when none are given. Without ``like``: LAS 1.4,
point format 6, scale 0.001 on each axis, offsets = the per-axis minimum, so coordinates are
kept within 0.0005 units. Each field is added as an extra-bytes dimension (float32, or its
integer type; names of at most 32 characters) through ``laspy.ExtraBytesParams``, described
``clcurv``; a field named like an existing dimension (e.g. ``classification``) overwrites
it. Normals are stored as float32 extra dimensions ``nx, ny, nz``. LAS cannot hold NaN
coordinates, nor coordinates outside int32 at the header's scale and offset (WriteError).
"""
from __future__ import annotations

import copy

import numpy as np

from ._common import (CorruptFileError, Format, MissingDependencyError, WriteError, _int_as,
                      _native, _split_named)

LAZ_HINT = 'pip install "laspy[lazrs]"'
_INTS = [np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8")]


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


def _is_laz(path):
    return path.suffix.lower() == ".laz"


# --------------------------------------------------------------------------- read

def read(path):
    laz = _is_laz(path)
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


# --------------------------------------------------------------------------- write

def _target_header(laspy, path, pts, like):
    """(header, attributes to copy, normals to use when none are given) for the output."""
    n = len(pts)
    if like is None:
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = pts.min(axis=0) if n else np.zeros(3)
        return header, {}, None
    if not isinstance(getattr(like, "header", None), laspy.LasHeader):
        raise WriteError(f"{path}: like= must be a Cloud read from a LAS/LAZ file")
    if len(like.points) != n:
        raise WriteError(f"{path}: like= has {len(like.points)} points but {n} are given")
    return copy.deepcopy(like.header), dict(like.attributes), like.normals


def _scaled_ints(path, pts, header):
    """The int32 X, Y, Z columns of ``pts`` with the header's scales and offsets."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    ints = np.round((pts - offsets) / scales)
    if len(pts) and (ints.min() < -2**31 or ints.max() > 2**31 - 1):
        raise WriteError(f"{path}: coordinates do not fit LAS int32 with scales {scales} and "
                         f"offsets {offsets}")
    return ints


def _extra_dims(laspy, path, columns, header):
    """ExtraBytesParams for the columns that are not dimensions of the header already."""
    existing = set(header.point_format.dimension_names)
    new = []
    for name, a in columns.items():
        if name in existing:
            continue
        if len(name) > 32:
            raise WriteError(f"{path}: LAS extra-bytes names have at most 32 characters: "
                             f"{name!r}")
        dt = np.dtype("f4") if a.dtype.kind == "f" else _int_as(path, name, a, _INTS)
        new.append(laspy.ExtraBytesParams(name=name, type=dt, description="clcurv"))
    return new


def _store(laspy, path, las, header, values):
    """Set every dimension of ``las`` named in ``values``; WriteError if one cannot hold it."""
    try:
        for name, a in values.items():
            if name in las.point_format.dimension_names:
                las[name] = a
    except (ValueError, OverflowError, laspy.LaspyException) as exc:
        raise WriteError(f"{path}: cannot store field {name!r} in LAS point format "
                         f"{header.point_format.id}: {exc}") from exc


def write(path, pts, fields, normals, like):
    laspy = _import_laspy(path, _is_laz(path))
    if not np.isfinite(pts).all():
        raise WriteError(f"{path}: LAS cannot store NaN/Inf coordinates "
                         f"({int((~np.isfinite(pts).all(axis=1)).sum())} rows)")
    header, keep, like_normals = _target_header(laspy, path, pts, like)
    normals = like_normals if normals is None else normals
    ints = _scaled_ints(path, pts, header)
    columns = dict(fields)
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        columns = {"nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], **columns}
    new = _extra_dims(laspy, path, columns, header)
    las = laspy.LasData(header, points=laspy.ScaleAwarePointRecord.zeros(len(pts),
                                                                          header=header))
    if new:
        las.add_extra_dims(new)
    las.X, las.Y, las.Z = (ints[:, i].astype(np.int32) for i in range(3))
    _store(laspy, path, las, header, {**keep, **columns})
    las.write(str(path))


FORMAT = Format(reads={".las": "LAS", ".laz": "LAZ (compressed LAS)"}, read=read,
                writes={".las": "LAS", ".laz": "LAZ"}, write=write)
