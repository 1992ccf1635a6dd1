"""What the format modules of :mod:`clcurv.io` share.

* :class:`Format`, the declaration each format module makes (``FORMAT``) and the registry in
  ``clcurv/io/__init__.py`` is built from;
* :class:`Cloud`, the result of :func:`clcurv.io.read`, and the errors;
* reading helpers: :func:`finish` (drops rows with non-finite coordinates and builds the
  Cloud), :func:`split_named` (columns by name: x y z, normals ``nx ny nz`` /
  ``normal_x ...``, attributes), :func:`split_positional` (headerless tables: columns 0-2
  are x y z, 3-5 normals when exactly 6 columns of unit vectors), :func:`native`,
  :func:`struct_columns` and :func:`quiet`; :func:`check_claim`, the guard against
  hostile headers (a count is checked against the bytes the file holds before anything is
  allocated from it);
* :func:`refuse_urls`: a URL given as a path (``s3://``, ``https://``...) is an error that
  says so (clcurv reads and writes files by path only);
* writing helpers: :func:`check_points`, :func:`check_normals`, :func:`check_fields`
  (names ``[A-Za-z_][A-Za-z0-9_.-]*``, not reserved for coordinates or normals, shape
  ``(N,)``, numeric; bool becomes uint8) and :func:`int_as` (the integer type a format
  stores an integer field in).
"""
from __future__ import annotations

import os
import re
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
RESERVED = {"x", "y", "z", "nx", "ny", "nz", "normal_x", "normal_y", "normal_z"}
_NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))


#: the extensions of LAS and LAZ files (a COPC file is a .copc.laz)
LAS_SUFFIXES = (".las", ".laz")
#: ``Cloud.format`` (and a stream source's ``format``) of a cloud read from LAS or LAZ
LAS_FORMATS = ("las", "laz")


def is_las(path):
    """Is ``path`` a LAS/LAZ file name (by its extension, any case)? LAS/LAZ clouds are
    z-up (ASPRS: Z is elevation) and their outputs keep the input's header."""
    return Path(str(path)).suffix.lower() in LAS_SUFFIXES


def from_las(cloud):
    """Was ``cloud`` (a :class:`Cloud`, or a stream source of :mod:`clcurv.io.stream`) read
    from a LAS/LAZ file (by its content)?"""
    return getattr(cloud, "format", None) in LAS_FORMATS


# --------------------------------------------------------------------------- registry entry

@dataclass(frozen=True)
class Format:
    """A file format, as its module declares it (``FORMAT = Format(...)``).

    Attributes
    ----------
    reads : dict of str -> str
        Extensions read (lower case, with the dot) -> description used in messages.
    read : callable
        ``read(path: Path) -> Cloud``; raises :class:`ReadError` or any exception (which
        :func:`clcurv.io.read` turns into :class:`CorruptFileError`).
    writes : dict of str -> str
        Extensions written -> description; empty for a read-only format.
    write : callable or None
        ``write(path, points, fields, normals, like, carried)`` with checked arguments:
        points ``(N, 3)`` float64, fields from :func:`check_fields`, normals ``(N, 3)`` or
        None, ``carried`` the input's attributes to keep (:mod:`clcurv.io.carry`: name ->
        array in the dtype to write, written between the normals and the fields).
    carries : str or None
        The :func:`clcurv.io.carry.plan` kind of the output ('ply', 'text', 'npz'): what it
        keeps of ``like``'s attributes; None when the writer keeps them itself from
        ``like`` (LAS: its header and dimensions), ``carried`` then empty.
    """

    reads: dict
    read: Callable
    writes: dict = field(default_factory=dict)
    write: Callable | None = None
    carries: str | None = None


# --------------------------------------------------------------------------- errors

class ReadError(Exception):
    """A point cloud file could not be read. The message starts with the file name."""


class MissingFileError(ReadError, FileNotFoundError):
    """The file does not exist."""


class UnknownFormatError(ReadError, ValueError):
    """The extension is not one of :data:`READ_FORMATS`."""


class CorruptFileError(ReadError, ValueError):
    """The file exists but its content is not what its extension promises."""


class CatalogError(ReadError, ValueError):
    """The files of a catalog (several paths, a folder, a ``.vpc``) cannot be read as one
    cloud: none, two CRS, a ``.vpc`` stating other point counts than the files' headers."""


class MissingDependencyError(ReadError, ImportError):
    """An optional package needed for this format is missing (raised by read and write)."""


class WriteError(ValueError):
    """:func:`write` was given arguments it cannot write (shape, name, format...)."""


#: a URL's scheme at the start of a path: two characters at least (``C:/`` is a Windows
#: drive), one slash at least after the colon (pathlib folds ``s3://b/k`` to ``s3:/b/k``)
_URL = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]+):/")


def url_scheme(path):
    """The scheme of ``path`` when it is a URL (``'s3'``, ``'https'``, ``'file'``...) that
    names no local file, else None."""
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else None
    if not isinstance(text, str):
        return None
    m = _URL.match(text)
    if m is None or Path(text).exists():
        return None
    return m.group(1).lower()


def url_message(path, scheme):
    """Why the URL ``path`` is not read or written, and what to do instead."""
    if scheme == "file":
        return (f"{os.fspath(path)}: a file: URL; give the file's path itself "
                f"(clcurv takes paths, not URLs)")
    return (f"{os.fspath(path)}: a URL ({scheme}://); clcurv reads and writes files by path "
            "only, on a local file system or a shared one that every Dask worker mounts at "
            "the same path (NFS, Lustre...): copy the file there, or mount the storage "
            "(e.g. s3fs, rclone mount) and give the mounted path")


def refuse_urls(src):
    """MissingFileError when ``src`` (a path, or a list of paths) is or holds a URL that
    names no local file: clcurv does not read s3://, http(s):// or other fsspec URLs."""
    for p in (src if isinstance(src, (list, tuple)) else [src]):
        scheme = url_scheme(p)
        if scheme is not None:
            raise MissingFileError(url_message(p, scheme))


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


# --------------------------------------------------------------------------- reading

def finish(path, fmt, points, normals=None, attributes=None, header=None):
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


def check_claim(path, claim, need, have, exact=True):
    """Raise CorruptFileError unless the ``need`` bytes that the header's ``claim`` takes
    (exactly, or at least when ``exact`` is false) fit in the ``have`` bytes the file holds.

    Called before allocating anything from a header count, so that a few hundred bytes
    claiming 10^10 points fail at once instead of allocating gigabytes.
    """
    if need > have:
        size = f"{need} bytes" if exact else f"at least {need} bytes"
        raise CorruptFileError(f"{path}: truncated or corrupt: the header claims {claim}, "
                               f"which takes {size}, but the file has only {have} bytes "
                               "for it")


def native(a):
    """A writable, native-byte-order copy of ``a``."""
    a = np.asarray(a)
    return a.astype(a.dtype.newbyteorder("="), copy=True)


def struct_columns(rec):
    """Name -> native copy of each non-object field of the structured array ``rec``."""
    return {name: native(rec[name]) for name in rec.dtype.names if rec.dtype[name] != object}


@contextmanager
def quiet():
    """Silence warnings (``np.loadtxt`` on an empty body, plyfile on empty elements)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _find(names, wanted):
    """Index of ``wanted`` in ``names``: exact match first, then case-insensitive."""
    if wanted in names:
        return names.index(wanted)
    lower = [n.lower() for n in names]
    return lower.index(wanted) if wanted in lower else None


def split_names(names, xyz=True):
    """(the x, y, z names or None, the normal triple's names or None, the attributes' names)
    of a file's named columns ``names`` by the rules of :func:`split_named` (x y z and a
    normal triple, exact names first, then case-insensitive)."""
    names = list(names)
    pos = find_triple(names, "xyz") if xyz else None
    nrm = next(filter(None, (find_triple(names, t) for t in _NORMAL_NAMES)), None)
    used = set(pos or ()) | set(nrm or ())
    return pos, nrm, [n for n in names if n not in used]


def find_triple(names, wanted):
    """The names of ``names`` matching the three ``wanted`` (:func:`_find`: exact, then
    case-insensitive), or None when one is missing."""
    idx = [_find(names, c) for c in wanted]
    return None if None in idx else [names[i] for i in idx]


def split_named(path, fmt, columns, header=None, points=None):
    """Split named per-point columns into points, normals and attributes.

    ``columns`` maps names to arrays of first dimension N; x, y, z are required unless
    ``points`` is given (:func:`split_names` says which columns are which).
    """
    pos, nrm, rest = split_names(columns, xyz=points is None)
    if points is None:
        if pos is None:
            raise CorruptFileError(f"{path}: columns {list(columns)} have no x, y and z; "
                                   "expected columns named x, y and z")
        points = _float_stack(columns, pos)
    normals = None if nrm is None else _float_stack(columns, nrm)
    attributes = {n: columns[n] for n in rest}
    return finish(path, fmt, points, normals, attributes, header)


def _float_stack(columns, names):
    """The (N, 3) float64 stack of the three columns ``names``."""
    return np.column_stack([np.asarray(columns[n], dtype=np.float64) for n in names])


def looks_like_normals(a):
    """True when every finite row of the (N, 3) array ``a`` is a unit vector (1e-3)."""
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a).all(axis=1)]
    if len(a) == 0:
        return False
    return bool(np.all(np.abs(np.linalg.norm(a, axis=1) - 1.0) <= 1e-3))


def split_positional(path, fmt, table, header=None):
    """Columns 0-2 are x y z; 3-5 are normals if exactly 6 columns of unit vectors."""
    table = np.asarray(table)
    if table.ndim != 2 or table.shape[1] < 3:
        raise CorruptFileError(f"{path}: expected at least 3 columns (x y z), got an array "
                               f"of shape {table.shape}")
    normals = None
    first_attr = 3
    if table.shape[1] == 6 and looks_like_normals(table[:, 3:6]):
        normals, first_attr = table[:, 3:6], 6
    attributes = {f"col{j}": table[:, j] for j in range(first_attr, table.shape[1])}
    return finish(path, fmt, table[:, :3], normals, attributes, header)


# --------------------------------------------------------------------------- writing

def check_points(path, points):
    """``points`` as a C-contiguous (N, 3) float64 array, or WriteError."""
    pts = np.asarray(points)
    if pts.dtype.kind not in "fiu" or pts.ndim != 2 or pts.shape[1] != 3:
        raise WriteError(f"{path}: points must be a real (N, 3) array, got shape {pts.shape} "
                         f"dtype {pts.dtype}")
    return np.ascontiguousarray(pts, dtype=np.float64)


def check_normals(path, normals, n):
    """``normals`` as a real (n, 3) array (dtype kept), None if None, or WriteError."""
    if normals is None:
        return None
    normals = np.asarray(normals)
    if normals.shape != (n, 3) or normals.dtype.kind not in "fiu":
        raise WriteError(f"{path}: normals must be a real ({n}, 3) array, got shape "
                         f"{normals.shape} dtype {normals.dtype}")
    return normals


def check_fields(path, fields, n):
    """The fields as name -> numeric (n,) arrays (bool as uint8), or WriteError."""
    out = {}
    for name, values in (fields or {}).items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise WriteError(f"{path}: field name {name!r} must match [A-Za-z_][A-Za-z0-9_.-]*")
        if name.lower() in RESERVED:
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


def int_as(path, name, a, allowed):
    """The dtype for integer field ``a``: its own if in ``allowed``, else the 32-bit type of
    the same signedness when the values fit (int64 -> int32, uint64 -> uint32)."""
    if a.dtype in allowed:
        return a.dtype
    dt = np.dtype(np.int32 if a.dtype.kind == "i" else np.uint32)
    if a.size == 0 or (a.min() >= np.iinfo(dt).min and a.max() <= np.iinfo(dt).max):
        return dt
    raise WriteError(f"{path}: integer field {name!r} ({a.dtype}) has values outside the "
                     f"range of {dt}, the widest integer type of this format")
