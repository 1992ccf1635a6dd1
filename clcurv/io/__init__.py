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

Formats
-------
One module per format, reader and writer together, each documenting what it reads and
writes: :mod:`~clcurv.io.ply`, :mod:`~clcurv.io.pcd`, :mod:`~clcurv.io.las` (LAS and LAZ),
:mod:`~clcurv.io.text` (XYZ/TXT/CSV...), :mod:`~clcurv.io.npy` (NPY and NPZ). Each declares
itself as ``FORMAT = Format(reads={ext: description}, read=..., writes={...}, write=...)``
(:class:`clcurv.io._common.Format`); :data:`FORMATS` lists them, and the extension tables
:data:`READ_FORMATS` and :data:`WRITE_FORMATS` are built from it. Adding a format is one
module and one entry in :data:`FORMATS`.
"""
from __future__ import annotations

import os
from pathlib import Path

from . import las, npy, pcd, ply, text
from ._common import (Cloud, CorruptFileError, MissingDependencyError, MissingFileError,
                      ReadError, UnknownFormatError, WriteError, _check_fields,
                      _check_normals, _check_points)
from .las import LAZ_HINT  # noqa: F401  (kept importable from clcurv.io)
from .pcd import _lzf_decompress_py, lzf_decompress  # noqa: F401

__all__ = ["Cloud", "read", "write", "lzf_decompress", "ReadError", "MissingFileError",
           "UnknownFormatError", "CorruptFileError", "MissingDependencyError", "WriteError",
           "READ_FORMATS", "WRITE_FORMATS"]

for _public in (Cloud, ReadError, MissingFileError, UnknownFormatError, CorruptFileError,
                MissingDependencyError, WriteError):
    _public.__module__ = __name__  # shown (and pickled) as clcurv.io.<name>, as before
del _public

#: The registry: every supported format, one entry per format module.
FORMATS = (ply.FORMAT, pcd.FORMAT, las.FORMAT, text.FORMAT, npy.FORMAT)


def _by_extension(kind):
    """Extension -> (description, function) over :data:`FORMATS`; ``kind`` is read/write."""
    table = {}
    for fmt in FORMATS:
        for ext, description in getattr(fmt, kind + "s").items():
            if ext in table:
                raise ImportError(f"clcurv.io: two formats {kind} {ext}")
            table[ext] = (description, getattr(fmt, kind))
    return table


_READERS = _by_extension("read")
_WRITERS = _by_extension("write")
#: Extensions understood by :func:`read` (lower case) and what each one means.
READ_FORMATS = {ext: description for ext, (description, _) in _READERS.items()}
#: Extensions understood by :func:`write`.
WRITE_FORMATS = {ext: description for ext, (description, _) in _WRITERS.items()}


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
    What each format reads (fields, normals, attributes, header) is described in the
    docstring of its module: :mod:`clcurv.io.ply`, :mod:`clcurv.io.pcd`,
    :mod:`clcurv.io.las`, :mod:`clcurv.io.text`, :mod:`clcurv.io.npy`.
    """
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    if ext not in _READERS:
        raise UnknownFormatError(
            f"{path}: unknown point cloud extension {ext or '(none)'!r}; expected one of "
            f"{', '.join(READ_FORMATS)}")
    kind, reader = _READERS[ext]
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
    How each format stores points, normals and fields (types, precision, header line,
    LAS scales and extra bytes) is described in the docstring of its module:
    :mod:`clcurv.io.ply`, :mod:`clcurv.io.las`, :mod:`clcurv.io.text`, :mod:`clcurv.io.npy`.
    """
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    if ext not in _WRITERS:
        raise WriteError(f"{path}: cannot write extension {ext or '(none)'!r}; expected one "
                         f"of {', '.join(WRITE_FORMATS)}")
    pts = _check_points(path, points)
    normals = _check_normals(path, normals, len(pts))
    fields = _check_fields(path, fields, len(pts))
    _WRITERS[ext][1](path, pts, fields, normals, like)
    return path
