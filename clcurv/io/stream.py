"""Chunked reading and writing for clouds larger than memory (:mod:`clcurv.tiled`).

A *source* yields a file's points in input order, a bounded number at a time:

    src = open_source("survey.laz")         # LAS/LAZ (laspy's chunk iterator) or NPY (mmap)
    src.n, src.format, src.bounds_hint()    # point count, 'las'/'laz'/'npy', header box
    for start, xyz, normals in src.chunks(1_000_000):
        ...                                 # xyz (m, 3) float64 of points start..start+m-1

``xyz`` equals what :func:`clcurv.io.read` gives for the same rows (LAS: X * scale + offset
in float64), so a computation on the chunks can equal the in-memory one bit for bit.
``normals`` are the file's normals as :func:`clcurv.io.read` finds them (LAS extra
dimensions ``nx, ny, nz``; NPY columns 3-5 of a 6-column array of unit vectors), else None.

The sources check what they read: a LAS/LAZ header is checked against the file size before
any point is decoded (clcurv.io.las), a LAZ file that ends early or decodes fewer points
than its header claims is a :class:`CorruptFileError` (never a partial cloud), and NPY data
must be a numeric (N, >= 3) array of finite coordinates.

Writers (:func:`write_las`, :func:`write_npz`) take the output fields as arrays that may be
memory maps and write them chunk by chunk, in input order.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import CorruptFileError, UnknownFormatError, _looks_like_normals

#: formats a tiled run reads and writes
STREAM_READS = (".las", ".laz", ".npy")
STREAM_WRITES = (".las", ".laz", ".npz")


def open_source(path):
    """The chunked source of ``path`` (:class:`LasSource` or :class:`NpySource`)."""
    path = Path(path)
    if not path.exists():
        from ._common import MissingFileError
        raise MissingFileError(f"{path}: no such file")
    ext = path.suffix.lower()
    if ext in (".las", ".laz"):
        return LasSource(path)
    if ext == ".npy":
        return NpySource(path)
    raise UnknownFormatError(f"{path}: a tiled run reads {', '.join(STREAM_READS)} "
                             f"(got {ext or 'no extension'}); convert it, or run in memory")


class LasSource:
    """A LAS/LAZ file read with ``laspy.open(...).chunk_iterator``."""

    def __init__(self, path):
        from . import las
        self.path = path
        self.layout = las._layout(path)          # header checked against the file size
        self.laspy = las._import_laspy(path, self.layout.compressed)
        self.format = "laz" if self.layout.compressed else "las"
        self.n = self.layout.count
        with self.laspy.open(str(path)) as f:
            self.header = f.header
        names = set(self.header.point_format.dimension_names)
        self.has_normals = {"nx", "ny", "nz"} <= names

    def bounds_hint(self):
        """The header's (mins, maxs): a hint only, never trusted for correctness."""
        lo, hi = np.asarray(self.header.mins, float), np.asarray(self.header.maxs, float)
        return (lo, hi) if np.isfinite(lo).all() and np.isfinite(hi).all() else None

    def chunks(self, size):
        start = 0
        try:
            with self.laspy.open(str(self.path)) as f:
                for rec in f.chunk_iterator(size):
                    m = len(rec)
                    if m == 0:
                        break
                    xyz = np.empty((m, 3))
                    xyz[:, 0], xyz[:, 1], xyz[:, 2] = rec.x, rec.y, rec.z
                    nrm = None
                    if self.has_normals:
                        nrm = np.column_stack([np.asarray(rec[k], np.float64)
                                               for k in ("nx", "ny", "nz")])
                    yield start, xyz, nrm
                    start += m
                    if start > self.n:
                        break
        except (self.laspy.LaspyException, ValueError, OSError) as exc:
            raise CorruptFileError(f"{self.path}: cannot decode the points after #{start}: "
                                   f"{exc}") from exc
        if start != self.n:
            raise CorruptFileError(f"{self.path}: the header claims {self.n} points but "
                                   f"{start} were decoded (a truncated file?)")


class NpySource:
    """An (N, >= 3) numeric NPY array, memory-mapped."""

    def __init__(self, path):
        from .npy import _check_npy
        self.path, self.format = path, "npy"
        with open(path, "rb") as fp:
            _check_npy(path, fp, path.stat().st_size)
        a = np.load(path, mmap_mode="r", allow_pickle=False)
        if a.dtype.names or a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[1] < 3:
            raise CorruptFileError(f"{path}: a tiled run reads an (N, >= 3) numeric NPY "
                                   f"array, got shape {a.shape} dtype {a.dtype}")
        self.array, self.n = a, a.shape[0]
        self.has_normals = a.shape[1] == 6 and self._unit_normals()

    def _unit_normals(self, step=1 << 22):
        """The rule of clcurv.io (columns 3-5 of exactly 6 are normals when every finite
        row is a unit vector), checked a block at a time."""
        seen = False
        for s in range(0, self.n, step):
            block = np.asarray(self.array[s:s + step, 3:6], np.float64)
            fin = np.isfinite(block).all(axis=1)
            if fin.any():
                seen = True
                if not _looks_like_normals(block[fin]):
                    return False
        return seen

    def bounds_hint(self):
        return None

    def chunks(self, size):
        for s in range(0, self.n, size):
            block = np.asarray(self.array[s:s + size], np.float64)
            xyz = np.ascontiguousarray(block[:, :3])
            bad = ~np.isfinite(xyz).all(axis=1)
            if bad.any():
                raise CorruptFileError(
                    f"{self.path}: row {s + int(np.argmax(bad))} has a non-finite coordinate "
                    f"({int(bad.sum())} in rows {s}..{s + len(xyz) - 1}); a tiled run needs "
                    "finite coordinates: drop those rows first")
            nrm = np.ascontiguousarray(block[:, 3:6]) if self.has_normals else None
            yield s, xyz, nrm


# --------------------------------------------------------------------------- writing

def write_las(path, src, fields, normals=None, chunk=1_000_000):
    """Write a LAS/LAZ ``path`` holding the points of LAS/LAZ ``src`` (a :class:`LasSource`;
    its header, scales, offsets, VLRs and every dimension kept, records copied as read) with
    ``fields`` (name -> (N,) array, may be memory maps) added as extra-bytes dimensions (or
    overwriting a dimension of that name) and ``normals`` ((N, 3) or None) as ``nx ny nz``.
    Written chunk by chunk in input order."""
    import copy
    from . import las
    laspy = las._import_laspy(path, las._is_laz(path))
    header = copy.deepcopy(src.header)
    columns = {}
    if normals is not None:
        columns.update(nx=normals[:, 0], ny=normals[:, 1], nz=normals[:, 2])
    columns.update(fields)
    probe = {k: np.asarray(v[:1]) for k, v in columns.items()}
    new = las._extra_dims(laspy, path, probe, header)
    if new:
        header.add_extra_dims(new)
    names = set(header.point_format.dimension_names)
    with laspy.open(str(src.path)) as reader, \
            laspy.open(str(path), mode="w", header=header) as writer:
        start = 0
        for rec in reader.chunk_iterator(chunk):
            m = len(rec)
            out = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            for dim in rec.array.dtype.names:         # the raw records: integers as read
                out.array[dim] = rec.array[dim]
            for name, a in columns.items():
                if name in names:
                    out[name] = np.asarray(a[start:start + m])
            writer.write_points(out)
            start += m


def write_npz(path, points, fields, normals=None):
    """Write an NPZ (``points``, ``normals``, fields) from arrays that may be memory maps;
    numpy writes each member in bounded buffers."""
    arrays = {"points": points}
    if normals is not None:
        arrays["normals"] = normals
    arrays.update(fields)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
