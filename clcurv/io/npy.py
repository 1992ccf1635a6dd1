"""NumPy files: ``.npy`` (read) and ``.npz`` (read and write); no pickles.

Reading
-------
* **NPY**: an ``(N, >=3)`` numeric array, with the rule of headerless text (columns 0-2 are
  x y z; columns 3-5 are the normals when there are exactly 6 columns of unit vectors;
  otherwise columns 3, 4, ... are attributes ``col3``, ``col4``, ...), or a 1-D structured
  array whose field names follow the rule of named columns (x y z required, ``nx ny nz`` /
  ``normal_x...`` normals, other fields attributes in their dtype). ``Cloud.format`` is
  ``'npy'``.
* **NPZ**: key ``points`` (N, 3) numeric is required, ``normals`` (N, 3) optional; other
  arrays whose first dimension is N are attributes, the rest go into ``Cloud.header`` (a
  dict, or None when there are none). ``Cloud.format`` is ``'npz'``.

Writing
-------
NPZ only (uncompressed ``np.savez``): ``points`` (float64), ``normals``, the input's
attributes (``like=``, :mod:`clcurv.io.carry`) and each field by name, dtypes unchanged;
fields may not be named ``points`` or ``normals``.
"""
from __future__ import annotations

import math
import zipfile

import numpy as np

from .common import (CorruptFileError, Format, WriteError, check_claim, finish,
                     split_named, split_positional, struct_columns)


# --------------------------------------------------------------------------- read

#: the largest expansion of each zip method NumPy reads (deflate: 1032:1)
_ZIP_RATIOS = {zipfile.ZIP_STORED: 1, zipfile.ZIP_DEFLATED: 1032}


def _npy_header(fp):
    """(shape, dtype) from the NPY header at the position of ``fp``, leaving ``fp`` at the
    first data byte."""
    version = np.lib.format.read_magic(fp)
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)
    shape, _, dtype = read(fp)
    return shape, dtype


def check_npy(path, fp, have, what="NPY"):
    """CorruptFileError unless the ``have`` bytes after the NPY header at ``fp`` hold the
    array its header claims (checked before NumPy allocates the array from the shape)."""
    shape, dtype = _npy_header(fp)
    if dtype.hasobject:
        return  # np.load refuses it (allow_pickle=False)
    count = math.prod(shape)
    claim = f"{what} shape {shape} of {dtype}"
    if any(d < 0 for d in shape) or (count and not dtype.itemsize):
        raise CorruptFileError(f"{path}: the header claims {claim}, which is not an array "
                               "(negative dimension or zero-byte items)")
    check_claim(path, claim, count * dtype.itemsize, have - fp.tell())


def _read_npy(path):
    with open(path, "rb") as fp:
        check_npy(path, fp, path.stat().st_size)
    a = np.load(path, allow_pickle=False)
    if a.dtype.names:
        if a.ndim != 1:
            raise CorruptFileError(f"{path}: expected a 1-D structured array, got shape "
                                   f"{a.shape}")
        return split_named(path, "npy", struct_columns(a))
    if a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[1] < 3:
        raise CorruptFileError(f"{path}: expected an (N, 3) or (N, >=3) numeric array, got "
                               f"shape {a.shape} dtype {a.dtype}")
    return split_positional(path, "npy", a.astype(np.float64))


def _check_member(path, zf, info, size):
    """CorruptFileError unless the zip member ``info`` can hold what its entry and its NPY
    header claim, given an archive of ``size`` bytes."""
    name = info.filename
    ratio = _ZIP_RATIOS.get(info.compress_type)
    if ratio is None:
        raise CorruptFileError(f"{path}: member {name!r} uses zip compression method "
                               f"{info.compress_type}; NPZ members are stored or deflated")
    check_claim(path, f"member {name!r} of {info.compress_size} compressed bytes",
                info.compress_size, size, exact=False)
    check_claim(path, f"member {name!r} of {info.file_size} bytes ({ratio}:1 at most)",
                -(-info.file_size // ratio), info.compress_size, exact=False)
    if name.endswith(".npy"):
        with zf.open(info) as fp:
            check_npy(path, fp, info.file_size, what=f"member {name!r} of")


def _check_npz(path):
    """Every member of the archive checked by :func:`_check_member`."""
    size = path.stat().st_size
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            _check_member(path, zf, info, size)


def _read_npz(path):
    _check_npz(path)
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
    return finish(path, "npz", pts, normals, attributes, extra or None)


def read(path):
    return _read_npz(path) if path.suffix.lower() == ".npz" else _read_npy(path)


# --------------------------------------------------------------------------- write

def write(path, pts, fields, normals, like, carried):
    clash = {"points", "normals"} & set(fields)
    if clash:
        raise WriteError(f"{path}: field names {sorted(clash)} are reserved in NPZ")
    arrays = {"points": pts}
    if normals is not None:
        arrays["normals"] = np.asarray(normals)
    arrays.update(carried)              # the input's attributes (clcurv.io.carry)
    arrays.update(fields)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


FORMAT = Format(reads={".npy": "NumPy array (N, >=3)",
                       ".npz": "NumPy archive (points, normals, ...)"},
                read=read, writes={".npz": "NumPy archive"}, write=write, carries="npz")
