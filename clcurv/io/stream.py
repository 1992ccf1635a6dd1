"""Chunked reading and writing for clouds larger than memory (:mod:`clcurv.tiles.engine`).

A *source* yields a file's points in input order, a bounded number at a time:

    src = open_source("survey.laz")         # LAS/LAZ (laspy's chunk iterator) or NPY (mmap)
    src.n, src.format, src.bounds_hint()    # point count, 'las'/'laz'/'npy', box (or None)
    src.dropped                             # rows left out: a non-finite x, y or z
    for start, xyz, normals in src.chunks(1_000_000):
        ...                                 # xyz (m, 3) float64 of points start..start+m-1

A :class:`Catalog` is several files read as one cloud: a list of paths, a folder or a
``.vpc`` (:func:`is_catalog`), checked before any point is decoded.

``xyz`` equals what :func:`clcurv.io.read` gives for the same rows (LAS: X * scale + offset
in float64), so a computation on the chunks can equal the in-memory one bit for bit.
``normals`` are the file's normals as :func:`clcurv.io.read` finds them (LAS extra
dimensions ``nx, ny, nz``; NPY columns 3-5 of a 6-column array of unit vectors), else None.

Rows whose x, y or z is NaN or +-Inf are left out, as :func:`clcurv.io.read` drops them
(from the points, normals and attributes alike): the NPY and PLY sources scan the file
once when opened, ``n`` is the count of the other rows, ``dropped`` theirs, and ``chunks``
yields only those rows, their ``start`` counting them alone (contiguous ids 0..n-1), in
chunks of ``size`` rows but the last, as without them. Everything read from a source (the
buckets, the ids, the writers, which read it again) sees the cloud of
:func:`clcurv.io.read`; a file whose every row is non-finite is a source of 0 points (the
empty output of an empty file). LAS/LAZ coordinates are integers times a finite scale:
``dropped`` is 0.

The sources check what they read: a LAS/LAZ header is checked against the file size before
any point is decoded (clcurv.io.las), a LAZ file that ends early or decodes fewer points
than its header claims is a :class:`CorruptFileError` (never a partial cloud), and NPY data
must be a numeric (N, >= 3) array. A file that changes between the scan and a later read
(another count of finite rows) is a :class:`CorruptFileError` too.

Writers (:func:`write_las`, :func:`write_npz`) take the output fields as a function giving
the records of a range of points, and write them chunk by chunk, in input order.
"""
from __future__ import annotations

import mmap
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile

from . import carry, las, pieces, ply, vpc
from .common import (CatalogError, CorruptFileError, MissingFileError, UnknownFormatError,
                     check_claim, refuse_urls,
                     LAS_SUFFIXES, from_las, is_las, looks_like_normals, native, split_names)
from .npy import check_npy

#: formats a tiled run reads and writes
STREAM_READS = (*LAS_SUFFIXES, ".npy", ".ply")
STREAM_WRITES = (*LAS_SUFFIXES, ".npz", ".ply")
#: bytes of the file read at a time by the scan of an NPY or PLY source
SCAN_BYTES = 16 << 20


def open_source(path):
    """The chunked source of ``path`` (:class:`LasSource` or :class:`NpySource`)."""
    refuse_urls(path)
    path = Path(path)
    if not path.exists():
        raise MissingFileError(f"{path}: no such file")
    ext = path.suffix.lower()
    if is_las(path):
        return LasSource(path)
    if ext == ".npy":
        return NpySource(path)
    if ext == ".ply":
        return PlySource(path)
    raise UnknownFormatError(f"{path}: a tiled run reads {', '.join(STREAM_READS)} "
                             f"(got {ext or 'no extension'}); convert it, or run in memory")


def is_catalog(src):
    """Is ``src`` a catalog: a list of paths, a folder, or a ``.vpc`` file name?"""
    if isinstance(src, (list, tuple)):
        return True
    return vpc.is_vpc(src) or (isinstance(src, (str, Path)) and Path(src).is_dir())


def folder_files(folder):
    """The LAS/LAZ files of ``folder`` (``*.las``, ``*.laz``, ``*.copc.laz``, any case; not
    its subfolders) in sorted name order (Python's string order of the names: code point
    by code point, ``B.las`` before ``a.las``, ``t10.laz`` before ``t2.laz``), the order of
    a catalog's global ids. CatalogError for a folder without any."""
    folder = Path(folder)
    names = sorted(p.name for p in folder.iterdir())
    files = [folder / n for n in names if is_las(n) and (folder / n).is_file()]
    if not files:
        held = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise CatalogError(f"{folder}: no LAS/LAZ file (.las, .laz, .copc.laz) in the folder"
                           + (f" (it holds {held})" if names else " (it is empty)"))
    return files


def _catalog_files(src):
    """(the files of the catalog ``src``, its ``.vpc`` or None, the ``.vpc``'s items or
    None): ``src`` a list of paths (one folder or ``.vpc`` alone stands for itself), a
    folder or a ``.vpc``."""
    if isinstance(src, (list, tuple)):
        src = [Path(p) for p in src]
        if not src:
            raise CatalogError("an empty list of input files")
        nested = [p for p in src if p.is_dir() or vpc.is_vpc(p)]
        if not nested:
            return src, None, None
        if len(src) > 1:
            raise CatalogError(f"{nested[0]}: a folder or a .vpc is a catalog by itself; "
                               "give it alone, or list the files")
        src = nested[0]
    src = Path(src)
    if not vpc.is_vpc(src):
        return folder_files(src), None, None
    items = vpc.read(src)
    if not items:
        raise CatalogError(f"{src}: the virtual point cloud has no items")
    return [it.path for it in items], src, items


class Catalog:
    """Several files read as one cloud (lidR's catalog), given as a list of LAS/LAZ (or of
    NPY) paths, a folder (:func:`folder_files`) or a ``.vpc`` (:mod:`clcurv.io.vpc`, its
    items' order): the points of file k have the global ids offsets[k] .. offsets[k + 1] -
    1. The file normals are used only when every file has them.

    Checked when made, before any point is decoded (nothing is written yet): every file
    exists (the missing ones named together) and its header holds (clcurv.io.las: against
    the file size, a truncated LAZ's chunk table too); all LAS/LAZ or all NPY; a ``.vpc``'s
    ``pc:count`` equals each file's header count. LAS/LAZ files of other point formats,
    versions, scales or offsets are one cloud (each read as float64 coordinates; each
    output keeps its own input's header); files of two CRS (their WKT or EPSG code, see
    :func:`clcurv.io.vpc.header_crs`; none stated counts as one) are refused."""

    def __init__(self, paths):
        refuse_urls(paths)
        paths, self.vpc, items = _catalog_files(paths)
        missing = [p for p in paths if not p.exists()]
        if missing:
            where = f"{self.vpc}: names " if self.vpc else ""
            raise MissingFileError(f"{where}{len(missing)} missing file(s): "
                                   + ", ".join(map(str, missing)))
        if items is not None and vpc.data_files(items):
            raise UnknownFormatError(f"{self.vpc}: names {vpc.data_files(items)[0]}, not a "
                                     "LAS/LAZ file")
        self.parts = [open_source(p) for p in paths]
        kinds = {}
        for s in self.parts:
            kinds.setdefault("las" if from_las(s) else s.format, s.path)
        if len(kinds) > 1:
            (ka, a), (kb, b) = list(kinds.items())[:2]
            raise UnknownFormatError(f"{b}: a catalog is all LAS/LAZ or all NPY files, not "
                                     f"{kb.upper()} with {ka.upper()} ({a})")
        if items is not None:
            self._check_counts(items)
        if "las" in kinds:
            self._check_crs()
        self.format = self.parts[0].format
        self.path = self.parts[0].path
        self.paths = [s.path for s in self.parts]
        self.offsets = np.cumsum([0] + [s.n for s in self.parts])
        self.n = int(self.offsets[-1])
        self.dropped = sum(s.dropped for s in self.parts)
        self.has_normals = all(s.has_normals for s in self.parts)

    def _check_counts(self, items):
        """CatalogError when the .vpc states another point count than a file's header."""
        for it, s in zip(items, self.parts):
            if it.count is not None and it.count != s.n:
                raise CatalogError(f"{self.vpc}: states {it.count} points for {s.path}, whose "
                                   f"header has {s.n} (the .vpc is stale: build it again)")

    def _check_crs(self):
        """CatalogError naming two files of different CRS."""
        first = {}
        for s in self.parts:
            crs = vpc.header_crs(s.header)
            first.setdefault(crs.key, (s.path, crs))
            if len(first) > 1:
                (a, ca), (b, cb) = first.values()
                raise CatalogError(f"the files of a catalog have one CRS: {a} has {ca}, {b} "
                                   f"has {cb}; reproject them to one (e.g. PDAL's "
                                   "filters.reprojection)")

    def bounds_hint(self):
        boxes = [s.bounds_hint() for s in self.parts]
        if any(b is None for b in boxes):
            return None
        return (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))

    def chunks(self, size):
        for off, part in zip(self.offsets, self.parts):
            for start, xyz, nrm in part.chunks(size):
                yield int(off) + start, xyz, nrm if self.has_normals else None


class LasSource:
    """A LAS/LAZ file read with ``laspy.open(...).chunk_iterator`` (its coordinates are
    integers times finite scales: none is dropped)."""

    dropped = 0

    def __init__(self, path):
        self.path = path
        self.layout = las.read_layout(path)          # header checked against the file size
        self.laspy = las.import_laspy(path, self.layout.compressed)
        self.format = "laz" if self.layout.compressed else "las"
        self.n = self.layout.count
        with self.laspy.open(str(path)) as f:
            self.header = f.header
        dims = [n for n in self.header.point_format.dimension_names
                if n not in ("X", "Y", "Z")]
        _, self.nrm, self.attributes = split_names(dims, xyz=False)   # as clcurv.io.read
        self.has_normals = self.nrm is not None

    def attribute_specs(self):
        """{name: (dtype, trailing shape)} of the attributes clcurv.io.read gives (one point
        decoded: scaled extra bytes are float64 there)."""
        if not self.n:
            return {}
        for _, _, _, attrs in self.chunks(1, attributes=True):
            return carry.specs_of(attrs)

    def bounds_hint(self):
        """The header's (mins, maxs): a hint only, never trusted for correctness."""
        lo, hi = np.asarray(self.header.mins, float), np.asarray(self.header.maxs, float)
        return (lo, hi) if np.isfinite(lo).all() and np.isfinite(hi).all() else None

    def chunks(self, size, attributes=False, first=0, stop=None):
        """(start, xyz, normals or None) of each ``size`` points; with ``attributes``
        (start, xyz, normals, {name: values} of the attributes, as clcurv.io.read has them).
        ``first``, ``stop``: only the points first..stop-1 (a part of the file,
        :func:`parts_of`; a LAZ file is entered at the chunk that holds ``first``, through
        its chunk table)."""
        stop = self.n if stop is None else min(int(stop), self.n)
        start = first = int(first)
        try:
            for rec in las.read_range(self.laspy, self.path, first, stop, size):
                m = len(rec)
                xyz = np.empty((m, 3))
                xyz[:, 0], xyz[:, 1], xyz[:, 2] = rec.x, rec.y, rec.z
                nrm = None
                if self.has_normals:
                    nrm = np.column_stack([np.asarray(rec[k], np.float64)
                                           for k in self.nrm])
                if attributes:
                    yield start, xyz, nrm, {k: native(np.asarray(rec[k]))
                                            for k in self.attributes}
                else:
                    yield start, xyz, nrm
                start += m
        except (self.laspy.LaspyException, ValueError, OSError, IndexError,
                RuntimeError) as exc:       # RuntimeError: lazrs.LazrsError, bad LAZ data
            raise CorruptFileError(f"{self.path}: cannot decode the points after #{start}: "
                                   f"{exc}") from exc
        if start != stop:
            raise CorruptFileError(f"{self.path}: the header claims {self.n} points but "
                                   f"{start} were decoded (a truncated file?)")


def _regroup(blocks, size, n, path):
    """(start, xyz, normals, attributes) of exactly ``size`` rows (the last: the rest) from
    ``blocks``, the (xyz, normals or None, attributes or None) of the finite rows of the
    file's successive blocks; ``start`` counts the rows yielded before. Blocks already of
    ``size`` rows (a file without non-finite rows) pass as they are. CorruptFileError
    unless ``n`` rows in all (the count of the scan: the file changed since)."""
    pending, have, start = [], 0, 0
    for block in blocks:
        m = len(block[0])
        if not m:
            continue
        if not pending and m == size:
            yield (start,) + block
            start += m
            continue
        pending.append(block)
        have += m
        if have >= size:                # blocks have at most size rows: once at most
            whole = _join(pending)
            yield (start,) + _cut(whole, 0, size)
            start += size
            have -= size
            pending = [_cut(whole, size, size + have)] if have else []
    if have:
        yield (start,) + _join(pending)
        start += have
    if start != n:
        raise CorruptFileError(f"{path}: {start} rows of finite coordinates read, {n} when "
                               "the file was opened (it changed during the run?)")


def _join(blocks):
    """One (xyz, normals, attributes) block of the rows of ``blocks``, in order."""
    if len(blocks) == 1:
        return blocks[0]
    xyz = np.concatenate([b[0] for b in blocks])
    nrm = None if blocks[0][1] is None else np.concatenate([b[1] for b in blocks])
    attrs = blocks[0][2]
    if attrs is not None:
        attrs = {k: np.concatenate([b[2][k] for b in blocks]) for k in attrs}
    return xyz, nrm, attrs


def _cut(block, a, b):
    """Rows a..b-1 of the (xyz, normals, attributes) ``block``."""
    xyz, nrm, attrs = block
    return (xyz[a:b], None if nrm is None else nrm[a:b],
            None if attrs is None else {k: v[a:b] for k, v in attrs.items()})


def _scan_blocks(blocks):
    """(finite rows, non-finite rows, (mins, maxs) of the finite rows or None) of the
    (m, 3) float64 coordinate blocks ``blocks``."""
    n = bad = 0
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for xyz in blocks:
        keep = np.isfinite(xyz).all(axis=1)
        k = int(np.count_nonzero(keep))
        n, bad = n + k, bad + len(xyz) - k
        if k:
            fin = xyz if k == len(xyz) else xyz[keep]
            lo, hi = np.minimum(lo, fin.min(axis=0)), np.maximum(hi, fin.max(axis=0))
    return n, bad, ((lo, hi) if n else None)


class NpySource:
    """An (N, >= 3) numeric NPY array, read a block of rows at a time; ``rows`` is N,
    ``n`` the count of rows with finite x, y, z (the others are left out: ``dropped``)."""

    def __init__(self, path):
        self.path, self.format = path, "npy"
        with open(path, "rb") as fp:
            check_npy(path, fp, path.stat().st_size)
        a = np.load(path, mmap_mode="r", allow_pickle=False)
        if a.dtype.names or a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[1] < 3:
            raise CorruptFileError(f"{path}: a tiled run reads an (N, >= 3) numeric NPY "
                                   f"array, got shape {a.shape} dtype {a.dtype}")
        self.array, self.rows = a, a.shape[0]
        # rows are read with plain file reads (memory-mapped pages would stay resident)
        self.offset = a.offset if a.flags.c_contiguous else None
        self.row = a.dtype.itemsize * a.shape[1]
        self._scan()

    def _scan(self):
        """One pass over the rows: ``n``, ``dropped``, the box of the finite rows and
        ``has_normals``, the rule of clcurv.io (columns 3-5 of exactly 6 are normals when
        every finite row of them is a unit vector, on every row of the file: the rule is
        applied before the non-finite coordinates are dropped)."""
        six = self.array.shape[1] == 6
        state = {"seen": False, "unit": six}
        step = max(SCAN_BYTES // self.row, 1)

        def blocks():
            for s in range(0, self.rows, step):
                block = self._rows(s, min(step, self.rows - s))
                if state["unit"]:
                    nrm = block[:, 3:6]
                    fin = np.isfinite(nrm).all(axis=1)
                    if fin.any():
                        state["seen"] = True
                        state["unit"] = looks_like_normals(nrm[fin])
                yield block[:, :3]
        self.n, self.dropped, self._box = _scan_blocks(blocks())
        self.has_normals = six and state["unit"] and state["seen"]

    def bounds_hint(self):
        """The exact (mins, maxs) of the finite rows (from the scan), None without any."""
        return self._box

    def _rows(self, s, m):
        if self.offset is None:                       # Fortran order: through the map
            return np.asarray(self.array[s:s + m], np.float64)
        with open(self.path, "rb") as f:
            f.seek(self.offset + s * self.row)
            a = np.fromfile(f, self.array.dtype, count=m * self.array.shape[1])
        return a.reshape(m, self.array.shape[1]).astype(np.float64, copy=False)

    def _attribute_columns(self):
        """The columns clcurv.io.read makes attributes: col3, col4, ... (col6 ... after
        normals)."""
        return range(6 if self.has_normals else 3, self.array.shape[1])

    def attribute_specs(self):
        """{name: (dtype, trailing shape)} of the attributes clcurv.io.read gives (float64,
        as the whole array there)."""
        return {f"col{j}": (np.dtype(np.float64), ()) for j in self._attribute_columns()}

    def chunks(self, size, attributes=False):
        """(start, xyz, normals or None) of each ``size`` points; with ``attributes``
        (start, xyz, normals, {name: values} of the attributes, as clcurv.io.read has them)."""
        def blocks():
            for s in range(0, self.rows, size):
                block = self._rows(s, min(size, self.rows - s))
                keep = np.isfinite(block[:, :3]).all(axis=1)
                if not keep.all():
                    block = block[keep]
                xyz = np.ascontiguousarray(block[:, :3])
                nrm = np.ascontiguousarray(block[:, 3:6]) if self.has_normals else None
                attrs = ({f"col{j}": np.ascontiguousarray(block[:, j])
                          for j in self._attribute_columns()} if attributes else None)
                yield xyz, nrm, attrs
        for start, xyz, nrm, attrs in _regroup(blocks(), size, self.n, self.path):
            yield (start, xyz, nrm, attrs) if attributes else (start, xyz, nrm)


class PlySource:
    """A binary PLY whose vertex element comes first with scalar properties only (what
    scanners and clcurv write): its rows read with plain file reads at their offset;
    ``rows`` is the vertex count, ``n`` the count of vertices with finite x, y, z (the
    others are left out: ``dropped``)."""

    def __init__(self, path):
        self.path, self.format = path, "ply"
        with open(path, "rb") as f:
            head = f.read(1 << 20)
        fmt, _, elements, start = ply.parse_header(head, path)
        ok = elements and elements[0][0] == "vertex" and fmt != "ascii"
        props = [ln.split() for ln in elements[0][2][1:]] if elements else []
        if not ok or not all(len(p) == 3 and p[1] in ply.TYPES for p in props):
            raise UnknownFormatError(
                f"{path}: a tiled run reads binary PLY whose first element is the vertex "
                "element with scalar properties only (this one is "
                f"{fmt}{'' if ok else ', another layout'}); convert it, or run in memory")
        order = "<" if fmt == "binary_little_endian" else ">"
        self.dtype = np.dtype([(p[2], order + ply.TYPES[p[1]]) for p in props])
        self.rows, self.offset = elements[0][1], start
        check_claim(path, f"{self.rows} vertices of {self.dtype.itemsize} bytes",
                    self.rows * self.dtype.itemsize, path.stat().st_size - start)
        if len(elements) > 1:               # the rows after the vertices, as io.read checks
            with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                ply.check_binary_rest(path, m, start, start + self.rows * self.dtype.itemsize,
                                      elements[1:], order, whole=False)
        self.xyz, self.nrm, self.attributes = split_names(self.dtype.names)  # as io.read
        if self.xyz is None:
            raise CorruptFileError(f"{path}: the vertex element has no x, y and z")
        self.has_normals = self.nrm is not None
        step = max(SCAN_BYTES // self.dtype.itemsize, 1)
        self.n, self.dropped, self._box = _scan_blocks(
            self._xyz(rec) for _, rec in self._records(step))

    def attribute_specs(self):
        """{name: (dtype, trailing shape)} of the attributes clcurv.io.read gives."""
        return {k: (self.dtype[k].newbyteorder("="), ()) for k in self.attributes}

    def bounds_hint(self):
        """The exact (mins, maxs) of the finite rows (from the scan), None without any."""
        return self._box

    def _records(self, size):
        """(first row, records) of each ``size`` vertices of the file."""
        with open(self.path, "rb") as f:
            for s in range(0, self.rows, size):
                f.seek(self.offset + s * self.dtype.itemsize)
                m = min(size, self.rows - s)
                rec = np.fromfile(f, self.dtype, count=m)
                if len(rec) != m:
                    raise CorruptFileError(f"{self.path}: vertex {s + len(rec)} is past the "
                                           "end of the file (it changed during the run?)")
                yield s, rec

    def _xyz(self, rec):
        return np.column_stack([rec[k].astype(np.float64) for k in self.xyz])

    def chunks(self, size, attributes=False):
        """(start, xyz, normals or None) of each ``size`` points; with ``attributes``
        (start, xyz, normals, {name: values} of the attributes, as clcurv.io.read has them)."""
        def blocks():
            for _, rec in self._records(size):
                xyz = self._xyz(rec)
                keep = np.isfinite(xyz).all(axis=1)
                if not keep.all():
                    rec, xyz = rec[keep], np.ascontiguousarray(xyz[keep])
                nrm = (np.column_stack([rec[k].astype(np.float64) for k in self.nrm])
                       if self.has_normals else None)
                attrs = ({k: native(rec[k]) for k in self.attributes} if attributes
                         else None)
                yield xyz, nrm, attrs
        for start, xyz, nrm, attrs in _regroup(blocks(), size, self.n, self.path):
            yield (start, xyz, nrm, attrs) if attributes else (start, xyz, nrm)


#: points of a part of one LAS/LAZ file, at most (:func:`parts_of`): a multiple of
#: LASzip's default chunk of 50,000 points, so that parts start at a chunk
PART_POINTS = 4_000_000


@dataclass(frozen=True)
class Part:
    """Points ``first``..``stop``-1 of the file ``path``, whose global ids start at
    ``offset``; ``normals``: read the file's normals (a catalog reads them only when every
    file has them). Small and picklable: what a worker needs to read its points itself."""
    path: str
    first: int
    stop: int
    offset: int
    normals: bool

    @property
    def n(self):
        return self.stop - self.first


def parts_of(source, most=None):
    """The :class:`Part` list of ``source`` (a source or a :class:`Catalog`), in global-id
    order: every file of a catalog apart, and a LAS/LAZ file of more than ``most`` points
    in ranges of ``most`` (NPY and PLY files whole: their ids count finite rows only)."""
    files = source.parts if isinstance(source, Catalog) else [source]
    offsets = source.offsets if isinstance(source, Catalog) else [0]
    normals = bool(source.has_normals)
    most = PART_POINTS if most is None else most
    out = []
    for off, src in zip(offsets, files):
        step = max(int(most), 1) if isinstance(src, LasSource) else max(src.n, 1)
        for a in range(0, max(src.n, 1), step):
            out.append(Part(str(src.path), a, min(a + step, src.n), int(off) + a, normals))
    return out


def read_part(part, size):
    """(global start, xyz, normals or None) of each ``size`` points of ``part``, read by
    whoever calls it (a worker): the file is opened here."""
    src = open_source(Path(part.path))
    if isinstance(src, LasSource):
        it = src.chunks(size, first=part.first, stop=part.stop)
    else:
        it = src.chunks(size)
    for start, xyz, nrm in it:
        yield part.offset + start - part.first, xyz, nrm if part.normals else None


# --------------------------------------------------------------------------- writing

class _WiderCounts(Exception):
    """A count of a later chunk does not fit the count type chosen from the first rows
    (:func:`write_las` writes the file again with the wider type)."""


def write_las(path, src, names, rows, chunk=1_000_000, quantize=None):
    """Write a LAS/LAZ ``path`` holding the points of LAS/LAZ ``src`` (a :class:`LasSource`:
    its header, scales, offsets, VLRs, EVLRs and every dimension kept, the records copied as
    read) with the fields ``names`` added as extra-bytes dimensions; ``"normals"`` becomes
    ``nx ny nz``. The header and dimensions follow the rules of the in-memory writer
    (:func:`clcurv.io.las.output_header`: a COPC input's VLRs and EVLRs left out, a plain
    LAS/LAZ written; :func:`clcurv.io.las.extra_dims`: float32 for real fields, a field
    replacing an extra-bytes dimension of its name, one stored in a standard dimension must
    fit it), so both outputs are the same. ``rows(start, stop)`` gives the structured
    records (one field per name) of the points start..stop-1. Written chunk by chunk in
    input order.

    A count field (:data:`clcurv.io.las.COUNT_FIELDS`) is uint16 unless some count exceeds
    65,535 (:func:`clcurv.io.las.count_dtype`, which sees the whole column in memory): the
    first rows choose the type, and a later chunk with a count beyond it makes the file
    be written again with uint32, so both outputs are the same and no count is clipped.

    ``quantize``: the run's radius, to store clcurv's real fields quantised
    (:func:`clcurv.io.las.quantization`), as the in-memory writer does."""
    try:
        _write_las(path, src, names, rows, chunk, quantize, wide=False)
    except _WiderCounts:
        _write_las(path, src, names, rows, chunk, quantize, wide=True)


def _write_las(path, src, names, rows, chunk, quantize, wide):
    plan = LasPlan.make(path, src, names, rows(0, min(1, src.n)), quantize, wide)
    laspy = plan.laspy
    with laspy.open(str(src.path), laz_backend=las.laz_backends(laspy)) as reader:
        las.write_records(laspy, path, plan.header, plan.records(
            path, reader.chunk_iterator(chunk), rows, 0), plan.evlrs)   # as in memory


def _las_columns(names, rec):
    """{dimension name: values} of the fields ``names`` of the records ``rec`` (normals as
    nx ny nz, first)."""
    out = {}
    for name in sorted(names, key=lambda k: k != "normals"):          # nx ny nz first
        if name == "normals":
            out.update(nx=rec[name][:, 0], ny=rec[name][:, 1], nz=rec[name][:, 2])
        else:
            out[name] = rec[name]
    return out


class LasPlan:
    """The header of a LAS/LAZ output of a LAS/LAZ source with clcurv's fields, and how its
    records are made from the source's (:func:`write_las`; a worker's piece of it,
    :func:`write_las_piece`): small and picklable (the header, the field names)."""

    def __init__(self, path, header, names, added, counts, quantize):
        self.path, self.header, self.names = str(path), header, list(names)
        self.added, self.counts, self.quantize = set(added), list(counts), quantize

    @classmethod
    def make(cls, path, src, names, first, quantize=None, wide=False):
        """The plan of ``path`` from ``src`` (a :class:`LasSource`): ``first``, records of
        the fields (a row, or none), whose types decide the dimensions' (``wide``: counts
        as uint32)."""
        laspy = las.import_laspy(path, las.is_laz(path))
        header = las.output_header(src.header)
        cols = _las_columns(names, first)
        counts = [k for k in cols if k in las.COUNT_FIELDS]
        if wide:
            cols.update({k: np.asarray(cols[k]).astype(las.COUNT_TYPES[-1]) for k in counts})
        added = las.extra_dims(laspy, path, cols, header, quantize=quantize)
        return cls(path, header, names, added, counts, quantize)

    @property
    def laspy(self):
        return las.import_laspy(Path(self.path), las.is_laz(Path(self.path)))

    @property
    def evlrs(self):
        return self.header.evlrs if self.header.version.minor >= 4 else None

    def records(self, path, chunks, rows, start):
        """The output records of the source's records ``chunks`` (laspy point records, in
        order, the first one of point ``start``), their fields from ``rows(a, b)``."""
        laspy, header = self.laspy, self.header
        dims = set(header.point_format.dimension_names)
        for rec in chunks:
            m = len(rec)
            out = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            _copy_records(rec.array, out.array)       # the raw records: integers as read
            for name, a in _las_columns(self.names, rows(start, start + m)).items():
                if name in self.added:                # unscaled extra bytes: raw = value
                    if name in self.counts:
                        _check_counts(path, name, a, out.array.dtype[name])
                    out.array[name] = las.raw_column(path, name, a, self.quantize)
                elif name in dims:
                    las.check_fits(path, header.point_format, name, a)
                    out[name] = (np.asarray(a).astype(np.int64)
                                 if las.is_bitfield(header.point_format, name) else a)
            yield out
            start += m


def write_las_piece(piece, plan, src_path, first, stop, rows, chunk=1_000_000):
    """A worker's piece of a LAS/LAZ output (:mod:`clcurv.io.pieces`): the output records of
    the source's points first..stop-1 (entered through the LAZ chunk table) with their
    fields ``rows(a, b)`` (a, b counted from ``first``), written to the piece file
    ``piece``; returns the extra-bytes statistics of its records
    (:meth:`clcurv.io.las.ExtraStats.state`), which the output's header holds."""
    laspy = plan.laspy
    path = Path(plan.path)

    def chunks():
        at = first
        for rec in las.read_range(laspy, src_path, first, stop, chunk,
                                  las.laz_backends(laspy)):
            at += len(rec)
            yield rec
        if at != stop:
            raise CorruptFileError(f"{src_path}: points {at}..{stop - 1} cannot be read "
                                   "(the file changed during the run?)")
    stats = las.ExtraStats(plan.header)
    with pieces.PieceWriter(piece, plan.header, laz=las.is_laz(path)) as writer:
        for out in plan.records(path, chunks(), lambda a, b: rows(a - first, b - first),
                                first):
            writer.write(out.array)
            stats.grow(out.array)
    return stats.state()


def _check_counts(path, name, a, dt):
    """_WiderCounts when a count of ``a`` exceeds the type ``dt`` chosen for it (a wider one
    exists), WriteError when none holds it: never a count clipped or wrapped."""
    if not len(a):
        return
    lo, hi = int(np.min(a)), int(np.max(a))
    if lo >= 0 and hi <= np.iinfo(dt).max:
        return
    if lo >= 0 and dt != las.COUNT_TYPES[-1]:
        raise _WiderCounts(name)
    las.count_dtype(path, name, a)                    # its WriteError


def _copy_records(src, dst):
    """Copy the records ``src`` into the fields of ``dst`` of the same names (the same
    fields at the same offsets, extra bytes appended after them, or some replaced): one
    strided byte copy when the layouts allow it, else field by field (a field ``dst`` does
    not have, an extra dimension a field replaces, is left out)."""
    a, b = src.dtype, dst.dtype
    same = all(n in b.fields and b.fields[n][1] == a.fields[n][1]
               and b.fields[n][0] == a.fields[n][0] for n in a.names)
    if same and a.itemsize <= b.itemsize and src.flags.c_contiguous and dst.flags.c_contiguous:
        dst.view(np.uint8).reshape(len(dst), b.itemsize)[:, :a.itemsize] = \
            src.view(np.uint8).reshape(len(src), a.itemsize)
        return
    for name in a.names:
        if name in b.fields and b.fields[name][0] == a.fields[name][0]:
            dst[name] = src[name]


def _carried(path, src, names, kind):
    """(the carried-attribute plan of ``src`` in a ``kind`` output with fields ``names``,
    whether the source's normals are written as the input's, the source's attribute specs):
    what clcurv.io.write does with like= in memory (clcurv.io.carry), so that both outputs
    are the same."""
    fields = [k for k in names if k != "normals"]
    specs = src.attribute_specs()             # a LAS source decodes a point for them
    plan = carry.plan(path, specs, fields, kind)
    return plan, "normals" not in names and src.has_normals, specs


def _chunk_rows(src, names, rows, chunk, plan, own_normals, path):
    """(start, xyz, normals to write or None, carried columns, records) of each chunk."""
    for start, xyz, nrm, attrs in src.chunks(chunk, attributes=True):
        rec = rows(start, start + len(xyz))
        normals = rec["normals"] if "normals" in names else nrm if own_normals else None
        yield start, xyz, normals, carry.columns(path, plan, attrs), rec


def write_npz(path, src, names, rows, n, specs, chunk=1_000_000):
    """Write an NPZ (``points``, ``normals``, the input's attributes, then the fields, as
    :mod:`clcurv.io.npy` writes) from the points of ``src`` and the records
    ``rows(start, stop)``, in one pass over the points: each member goes first to a raw
    file beside ``path``, then into the (uncompressed, ZIP64) archive."""
    folder = Path(path).parent
    plan, own_normals, attr_specs = _carried(path, src, names, "npz")
    fields = [k for k in names if k != "normals"]
    with_normals = "normals" in names or own_normals
    order = ["points"] + (["normals"] if with_normals else []) + [c.name for c in plan] + fields
    shapes = {"points": ((n, 3), np.dtype(np.float64))}
    if with_normals:
        dt = specs["normals"][1] if "normals" in names else np.float64
        shapes["normals"] = ((n, 3), np.dtype(dt))
    for c in plan:
        shapes[c.name] = ((n,) + tuple(attr_specs[c.src][1]), c.dtype)
    for name in fields:
        width, dtype = specs[name]
        shapes[name] = ((n,) if width is None else (n, width), np.dtype(dtype))
    raws = {k: folder / f".{Path(path).name}.{k}.raw" for k in order}
    try:
        files = {k: open(p, "wb") for k, p in raws.items()}
        try:
            for _, xyz, normals, carried, rec in _chunk_rows(src, names, rows, chunk, plan,
                                                            own_normals, path):
                files["points"].write(np.ascontiguousarray(xyz).tobytes())
                cols = {**carried, **({"normals": normals} if with_normals else {}),
                        **{k: rec[k] for k in fields}}
                for k in order[1:]:
                    files[k].write(np.ascontiguousarray(cols[k], shapes[k][1]).tobytes())
        finally:
            for f in files.values():
                f.close()
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
            for k in order:
                shape, dtype = shapes[k]
                with z.open(f"{k}.npy", "w", force_zip64=True) as m, open(raws[k], "rb") as r:
                    np.lib.format.write_array_header_2_0(
                        m, {"descr": np.lib.format.dtype_to_descr(dtype),
                            "fortran_order": False, "shape": shape})
                    while True:
                        block = r.read(1 << 24)
                        if not block:
                            break
                        m.write(block)
    finally:
        for p in raws.values():
            p.unlink(missing_ok=True)


def write_ply(path, src, names, rows, n, specs, chunk=1_000_000):
    """Write a binary PLY as clcurv.io.ply writes it (x y z double, nx ny nz float, the
    input's attributes, then the fields) from the points of ``src`` and the records
    ``rows(start, stop)``, chunk by chunk: the header from plyfile for the same vertex
    layout, the rows after it."""
    plan, own_normals, _ = _carried(path, src, names, "ply")
    fields = {k: np.empty(0, np.dtype(specs[k][1])) for k in names if k != "normals"}
    carried = {c.name: np.empty(0, c.dtype) for c in plan}
    with_normals = "normals" in names or own_normals
    dtype = np.dtype(ply.vertex_dtype(path, fields, with_normals, carried))
    el = plyfile.PlyElement.describe(np.empty(0, dtype), "vertex")
    header = plyfile.PlyData([el], text=False, byte_order="<",
                             comments=["written by clcurv"]).header
    header = header.replace("element vertex 0", f"element vertex {n}")
    with open(path, "wb") as f:
        f.write((header + "\n").encode("ascii"))
        for _, xyz, normals, cols, rec in _chunk_rows(src, names, rows, chunk, plan,
                                                      own_normals, path):
            out = np.empty(len(xyz), dtype)
            out["x"], out["y"], out["z"] = xyz.T
            if with_normals:
                out["nx"], out["ny"], out["nz"] = np.asarray(normals).T
            for k, a in cols.items():
                out[k] = a
            for k in fields:
                out[k] = rec[k]
            out.tofile(f)
