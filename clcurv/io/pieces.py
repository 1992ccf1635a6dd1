"""One LAS/LAZ file assembled from pieces that workers write in parallel (issue 50).

A *piece* is a window of consecutive points of the output, written by a worker (another
process, maybe another machine on a shared file system) with :func:`write_piece` (or
:class:`PieceWriter`, from its records a batch at a time); the client
joins the pieces with :func:`assemble`, whose serial work is a header, a byte copy of each
piece's payload and, for LAZ, a chunk table. No point is decoded or encoded by the client.

    header = las.output_header(src.header); las.extra_dims(laspy, out, columns, header)
    # on each worker, for its window start..stop of the output's points:
    write_piece(f"piece-{i}.lazpiece", header, records, laz=True)
    # on the client, once every worker is done:
    assemble("out.laz", header, [f"piece-{i}.lazpiece" for i in range(k)])

Why LAZ pieces can be joined: LASzip (compressors 2 and 3) compresses points in *chunks*,
each one restarting the arithmetic coder and its contexts, and lists the chunks' sizes in a
chunk table at the end of the point data (its position is the int64 that starts the point
data). Chunks compressed apart, in separate processes, are therefore concatenated into one
valid stream, and the table written for the whole. When the chunks differ in size (the
last chunk of each piece is short) the LASzip VLR says ``chunk_size = 0xFFFFFFFF``
("variable-size chunks", as COPC files do) and the table holds each chunk's point count
too; when every chunk but the last has the same count (windows that are multiples of the
chunk size, :func:`windows`), the file has ordinary fixed-size chunks.

The piece file
--------------
``payload | metadata (JSON, UTF-8) | footer`` where the footer is 24 bytes: the magic
``b"CLCPIECE"``, the format version (uint32), the metadata's length (uint64) and its CRC-32
(uint32). The payload is the LAZ chunks one after the other (no chunk-table offset, no
table), or for LAS the raw point records. The metadata holds what the assembler needs and
what it checks: ``kind`` ('laz'/'las'), the point format, record length, record layout
(field names, types, offsets), scales and offsets of the header it was written for, the
LASzip items (LAZ), the point count, the payload's size and CRC-32, each chunk's point
count and byte size, the number of points by return (15 counts, as laspy counts them) and
*extreme records*: the piece's first record and the records holding each axis', the GPS
time's and each extra-bytes element's minimum and maximum, from which the assembler grows
the output header exactly as laspy grows it when it writes the points itself (bounds, GPS
time range, the extra-bytes VLR's min/max). A piece is written under a temporary name,
flushed to disk and renamed (:func:`clcurv.io.atomic_output`), so that a reader, on this
machine or another, sees a whole piece or none.

The assembled file is laspy's: with windows from :func:`windows` (every piece but the last a
multiple of the chunk size, the default :data:`CHUNK_SIZE` laspy uses too) it is the very
file ``laspy.LasData(header, points).write(path)`` writes, byte for byte (tested for point
formats 1, 3 and 6, LAS and LAZ); with other windows, the same header and points, only the
chunking (LAZ) differs.

Checks
------
:func:`read_piece_info` refuses (:class:`PieceError`, naming the file) a piece whose footer
or metadata is missing, truncated or corrupted (magic, version, length, CRC), whose sizes
disagree (payload + metadata + footer = file size; chunks' bytes = payload; chunks'
points = points; LAS: points * record length = payload). :func:`assemble` reads every
piece's metadata before it writes anything, refuses a piece written for another header
(point format, record layout, scales, offsets, LASzip items) or of the other kind than the
output's extension, and with ``verify=True`` (the default) checks each payload's CRC-32 while
copying it. The output is written atomically (:func:`clcurv.io.atomic_output`): on any error
the previous file at the path, if any, is left byte for byte and nothing else remains.

Compatibility: laspy (backends Lazrs, LazrsParallel and Laszip, i.e. LASzip itself) reads
the assembled files, fixed or variable chunks, and its ``chunk_iterator`` works on all of
them; LASzip also seeks in both. lazrs 0.8's *seek* (laspy's ``LasReader.seek``) is wrong in
files with variable-size chunks (it takes the position within a chunk as the point index
modulo the chunk's count); with windows from :func:`windows` the output has fixed-size
chunks and seeking works with every backend. clcurv's own readers of a range of points
(the tiled run's parts and pieces) enter a file of variable-size chunks, such as a COPC
input, by its chunk table instead (:func:`clcurv.io.las.read_range`).

Costs: a worker's :func:`write_piece` costs what laspy's LAZ write of its points costs (one
lazrs compression, plus a pass over the records for the extremes, 0.04 s a million points);
:func:`assemble` reads each piece's metadata, writes the header and copies the payloads
(``verify=True`` reads them once more for the CRC), then flushes the file to disk.
``bench/lazchunks.py`` measures both.
"""
from __future__ import annotations

import base64
import copy
import io
import json
import os
import shutil
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from laspy.vlrs.known import LasZipVlr

from . import atomic_output
from .common import (LAS_FORMATS, CorruptFileError, MissingDependencyError, WriteError,
                     is_las)
from .las import LAZ_HINT, is_laz

__all__ = ["write_piece", "PieceWriter", "assemble", "read_piece_info", "windows", "PieceInfo",
           "PieceError", "CHUNK_SIZE", "VARIABLE_CHUNKS"]

#: points per LAZ chunk in a piece (LASzip's default)
CHUNK_SIZE = 50_000
#: the chunk size of the LASzip VLR that announces variable-size chunks
VARIABLE_CHUNKS = 0xFFFFFFFF
_MAGIC = b"CLCPIECE"
_VERSION = 1
_FOOTER = struct.Struct("<8sIQI")
#: the metadata of a piece is at most this long (it holds a few dozen records)
_MAX_META = 1 << 24
#: the chunk-size field of the LASzip VLR's record data (uint32 at byte 12)
_CHUNK_FIELD = slice(12, 16)
#: records scanned at a time for their extremes (a block stays in the CPU's cache)
_SCAN_ROWS = 1 << 14
#: bytes copied at a time when a payload's CRC is checked during the copy
_COPY_BYTES = 8 << 20


class PieceError(CorruptFileError):
    """A piece cannot be used: missing, truncated or corrupted (sizes, CRC), or written for
    another header or kind of output. The message starts with the piece's path. A
    :class:`clcurv.io.CorruptFileError` (a ``ValueError``)."""


@dataclass(frozen=True)
class PieceInfo:
    """What a piece holds (its metadata, checked by :func:`read_piece_info`).

    Attributes
    ----------
    path : pathlib.Path
    kind : str
        ``'laz'`` (compressed chunks) or ``'las'`` (raw records).
    points : int
    payload_bytes : int
        Bytes of the payload, at the start of the file.
    crc32 : int
        CRC-32 of the payload.
    chunks : tuple of (int, int)
        LAZ: each chunk's (point count, byte size), in order; LAS: empty.
    by_return : tuple of int
        Points with return number 1 to 15.
    meta : dict
        The whole metadata (layout, scales, offsets, extreme records...).
    """

    path: Path
    kind: str
    points: int
    payload_bytes: int
    crc32: int
    chunks: tuple
    by_return: tuple
    meta: dict


# --------------------------------------------------------------------------- header facts

def _lazrs(path):
    try:
        import lazrs        # here: LAZ pieces only; LAS pieces need laspy alone
    except ImportError:
        raise MissingDependencyError(f"{path}: LAZ pieces need the lazrs package: "
                                     f"{LAZ_HINT}") from None
    return lazrs


def _layout(header):
    """The record layout of ``header``'s point format, as JSON keeps it: [[name, type,
    offset], ...] (an extra-bytes array field's type includes its shape)."""
    dt = header.point_format.dtype()
    return [[name, dt.fields[name][0].str if not dt.fields[name][0].shape else
             f"{dt.fields[name][0].base.str}{list(dt.fields[name][0].shape)}",
             dt.fields[name][1]] for name in dt.names]


def _laszip_vlr(lazrs, point_format, chunk_size):
    """The lazrs ``LazVlr`` for ``point_format`` with ``chunk_size`` points per chunk
    (:data:`VARIABLE_CHUNKS`: variable-size chunks)."""
    vlr = lazrs.LazVlr.new_for_compression(point_format.id, point_format.num_extra_bytes)
    data = bytearray(vlr.record_data())
    data[_CHUNK_FIELD] = struct.pack("<I", chunk_size)
    return lazrs.LazVlr(bytes(data))


def _items(vlr):
    """The LASzip VLR's record data but its chunk size: what two pieces must share to be
    one stream (compressor, coder, version, items)."""
    data = bytearray(vlr.record_data())
    data[_CHUNK_FIELD] = bytes(4)
    return data.hex()


def _facts(header, kind, lazrs=None):
    """The metadata a piece must share with the header it is assembled under."""
    facts = {"kind": kind, "point_format": header.point_format.id,
             "record_length": header.point_format.size, "layout": _layout(header),
             "scales": [float(s) for s in header.scales],
             "offsets": [float(o) for o in header.offsets]}
    if kind == "laz":
        facts["laszip_items"] = _items(_laszip_vlr(lazrs, header.point_format, CHUNK_SIZE))
    return facts


def _records(path, header, points):
    """``points`` as a C-contiguous structured array of ``header``'s point format."""
    arr = getattr(points, "array", points)
    if isinstance(points, laspy.ScaleAwarePointRecord):
        if not (np.array_equal(points.scales, header.scales)
                and np.array_equal(points.offsets, header.offsets)):
            raise WriteError(f"{path}: the points have scales {list(points.scales)} and "
                             f"offsets {list(points.offsets)}, the header "
                             f"{list(header.scales)} and {list(header.offsets)}")
    want = header.point_format.dtype()
    if not isinstance(arr, np.ndarray) or arr.dtype != want or arr.ndim != 1:
        got = getattr(arr, "dtype", type(arr).__name__)
        raise WriteError(f"{path}: the points must be records of the header's point format "
                         f"{header.point_format.id} ({want.itemsize} bytes: {want.names}), "
                         f"got {got}")
    return np.ascontiguousarray(arr)


# --------------------------------------------------------------------------- worker

def _extreme_rows(header, arr):
    """Indices of the first record and of the records holding the minimum and the maximum
    of X, Y, Z, the GPS time and each element of each extra-bytes dimension (NaN counts as
    both, as NumPy's min and max return it; an extra-bytes ``no_data`` value is left out,
    as laspy does). The first record comes first: laspy 2.7 takes the extra-bytes min/max
    of a scalar dimension from the first record it grows the header with (``pts[..., 0]``),
    so the assembled header has the values laspy writes in one go."""
    if not len(arr):
        return np.zeros(0, dtype=np.int64)
    no_data = {}
    for vlr in header.vlrs.get("ExtraBytesVlr"):
        for eb in vlr.extra_bytes_structs:
            if eb.no_data is not None:
                no_data[eb.format_name()] = np.asarray(eb.no_data)
    names = ["X", "Y", "Z"] + [n for n in ("gps_time",) if n in arr.dtype.names]
    names += [d.name for d in header.point_format.extra_dimensions]
    columns = [(name, j, None if name not in no_data else no_data[name].reshape(-1)[j])
               for name in names for j in range(int(np.prod(arr.dtype[name].shape)))]
    lows, highs = [[] for _ in columns], [[] for _ in columns]
    for start in range(0, len(arr), _SCAN_ROWS):   # block by block: one pass over memory
        block = arr[start:start + _SCAN_ROWS]
        for k, (name, j, nd) in enumerate(columns):
            c = block[name].reshape(len(block), -1)[:, j]
            if nd is None:
                lows[k].append(start + np.argmin(c))
                highs[k].append(start + np.argmax(c))
                continue
            idx = np.flatnonzero(c != nd)
            if len(idx):
                lows[k].append(start + idx[np.argmin(c[idx])])
                highs[k].append(start + idx[np.argmax(c[idx])])
    rows = [0]
    for (name, j, _), lo, hi in zip(columns, lows, highs):
        if lo:          # the blocks' candidates in order: NaN and ties give the first row
            lo, hi = np.asarray(lo), np.asarray(hi)
            rows += [lo[np.argmin(arr[name].reshape(len(arr), -1)[lo, j])],
                     hi[np.argmax(arr[name].reshape(len(arr), -1)[hi, j])]]
    return np.unique(np.asarray(rows, dtype=np.int64))


def _by_return(header, arr):
    """Points with return number 1..15, as ``LasHeader.grow`` counts them."""
    rn = np.asarray(laspy.PackedPointRecord(arr, header.point_format).return_number)
    return [int(c) for c in np.bincount(rn.astype(np.int64), minlength=16)[1:16]]


def write_piece(path, header, points, *, laz=True, chunk_size=CHUNK_SIZE, parallel=False):
    """Write the piece file ``path``: ``points``, a window of consecutive points of the
    output, compressed as independent LAZ chunks (``laz=True``) or as raw LAS records.

    Parameters
    ----------
    path : str or os.PathLike
        The piece file (any name; ``.lazpiece``/``.laspiece`` say what it is). Written
        under a temporary name in its folder, flushed to disk and renamed onto ``path``.
    header : laspy.LasHeader
        The output's header (point format with its extra bytes, scales, offsets), the one
        given to :func:`assemble`: e.g. :func:`clcurv.io.las.output_header` with
        :func:`clcurv.io.las.extra_dims`.
    points : laspy.ScaleAwarePointRecord, laspy.PackedPointRecord or ndarray
        The records (the header's point format, exactly); a ScaleAwarePointRecord must have
        the header's scales and offsets. May be empty (a piece of 0 points).
    laz : bool
        LAZ chunks (True) or LAS records (False); the output's extension must agree.
    chunk_size : int
        Points per LAZ chunk (the last chunk of the piece holds the rest).
    parallel : bool
        Compress the chunks on several threads (lazrs' rayon pool); a worker process that
        has its own cores may set it.

    Returns
    -------
    PieceInfo

    Raises
    ------
    WriteError
        ``points`` are not records of the header's point format, or ``chunk_size`` < 1.
    MissingDependencyError
        LAZ needs lazrs.

    See Also
    --------
    PieceWriter : the same piece, from the records given a batch at a time.
    """
    with PieceWriter(path, header, laz=laz, chunk_size=chunk_size, parallel=parallel) as w:
        w.write(points)
    return w.info


class PieceWriter:
    """Write a piece from its records given a batch at a time, in order (a window larger
    than memory); the file is the one :func:`write_piece` writes from all of them at once.

        with PieceWriter("p3.lazpiece", header) as w:
            for batch in batches:          # records of the header's point format
                w.write(batch)
        w.info                             # the PieceInfo, once the block is left

    LAZ: full chunks are compressed as soon as they are complete, so at most
    ``chunk_size - 1`` records wait in memory. The file appears at its path when the
    ``with`` block ends without an error (:meth:`close`); an error in the block, or
    :meth:`abort`, leaves no file (and any earlier file at the path as it was). Arguments
    as :func:`write_piece`.
    """

    def __init__(self, path, header, *, laz=True, chunk_size=CHUNK_SIZE, parallel=False):
        self.path = Path(os.fspath(path))
        if (not isinstance(chunk_size, (int, np.integer)) or isinstance(chunk_size, bool)
                or not 1 <= chunk_size < VARIABLE_CHUNKS):
            raise WriteError(f"{self.path}: chunk_size must be an integer in [1, 2**32 - 1), "
                             f"got {chunk_size!r}")
        self.header, self.laz, self.parallel = header, bool(laz), bool(parallel)
        self.chunk_size = int(chunk_size)
        self._lazrs = _lazrs(self.path) if laz else None
        self._meta = _facts(header, "laz" if laz else "las", self._lazrs)
        self._vlr = (_laszip_vlr(self._lazrs, header.point_format, self.chunk_size)
                     if laz else None)
        self._dtype = header.point_format.dtype()
        self._pending = []                      # LAZ: records of the chunk being filled
        self._n_pending = 0
        self._chunks, self._points, self._bytes, self._crc = [], 0, 0, 0
        self._by_return = np.zeros(15, dtype=np.int64)
        self._extremes = np.zeros(0, self._dtype)
        self.info = None
        self._output = atomic_output(self.path)
        self._tmp = self._output.__enter__()
        try:
            self._file = open(self._tmp, "wb")
        except BaseException as exc:
            self._output.__exit__(type(exc), exc, exc.__traceback__)
            raise

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is None:
            self.close()
        else:
            self.abort(exc)
        return False

    def write(self, points):
        """Add the records ``points`` (as :func:`write_piece` takes them) after those
        written before. An error (records of another format...) aborts the piece."""
        if self._file is None:
            raise WriteError(f"{self.path}: the piece is closed")
        try:
            arr = _records(self.path, self.header, points)
            if not len(arr):
                return
            self._grow(arr)
            if not self.laz:
                self._put(memoryview(arr.view(np.uint8)))
                return
            self._pending.append(arr)
            self._n_pending += len(arr)
            if self._n_pending >= self.chunk_size:
                ready = (self._pending[0] if len(self._pending) == 1
                         else np.concatenate(self._pending))
                full = len(ready) - len(ready) % self.chunk_size
                self._compress(ready[:full])
                self._pending = [ready[full:]] if full < len(ready) else []
                self._n_pending = len(ready) - full
            # the caller may reuse its buffer: the records waiting (< chunk_size) are copied
            self._pending = [np.array(a) for a in self._pending]
        except BaseException as exc:
            self.abort(exc)
            raise

    def close(self):
        """Compress what is left, write the metadata and the footer, and put the piece at
        its path; returns its :class:`PieceInfo` (also ``self.info``)."""
        if self._file is None:
            return self.info
        try:
            if self._pending:
                self._compress(self._pending[0] if len(self._pending) == 1
                               else np.concatenate(self._pending))
                self._pending, self._n_pending = [], 0
            meta = dict(self._meta, points=self._points, payload_bytes=self._bytes,
                        crc32=self._crc, chunks=self._chunks,
                        by_return=[int(c) for c in self._by_return],
                        extremes=base64.b64encode(self._extremes.tobytes()).decode("ascii"))
            blob = json.dumps(meta, separators=(",", ":")).encode("utf-8")
            self._file.write(blob)
            self._file.write(_FOOTER.pack(_MAGIC, _VERSION, len(blob), zlib.crc32(blob)))
            self._file.close()
            self._file = None
            self._output.__exit__(None, None, None)
        except BaseException as exc:
            self.abort(exc)
            raise
        self.info = _info(self.path, meta)
        return self.info

    def abort(self, exc=None):
        """Give the piece up: its temporary file is removed, nothing appears at its path."""
        if self._file is None:
            return
        self._file.close()
        self._file = None
        exc = exc if exc is not None else RuntimeError("piece aborted")
        try:
            self._output.__exit__(type(exc), exc, exc.__traceback__)
        except BaseException:
            pass                        # the caller raises its own error

    def _put(self, data):
        self._file.write(data)
        self._bytes += len(data)
        self._crc = zlib.crc32(data, self._crc)

    def _grow(self, arr):
        """Count the returns and keep the extreme records of all records so far."""
        self._by_return += _by_return(self.header, arr)
        both = np.concatenate([self._extremes, arr[_extreme_rows(self.header, arr)]])
        self._extremes = both[_extreme_rows(self.header, both)]
        self._points += len(arr)

    def _compress(self, arr):
        """Compress ``arr`` (whole chunks, but the piece's last) and append the chunks."""
        data = self._lazrs.compress_points(self._vlr, arr.view(np.uint8), self.parallel)
        table_at, = struct.unpack_from("<q", data, 0)
        table = self._lazrs.read_chunk_table(io.BytesIO(data), self._vlr)
        sizes = [int(b) for _, b in table]
        counts = [min(self.chunk_size, len(arr) - i * self.chunk_size)
                  for i in range(len(table))]
        if sum(sizes) != table_at - 8 or sum(counts) != len(arr) or min(counts) < 1:
            raise WriteError(f"{self.path}: lazrs gave {len(table)} chunks of {sum(sizes)} "
                             f"bytes for {len(arr)} points, its table at byte {table_at}")
        self._put(memoryview(data)[8:table_at])
        self._chunks += [[c, b] for c, b in zip(counts, sizes)]


# --------------------------------------------------------------------------- client

def _info(path, meta):
    return PieceInfo(path=path, kind=meta["kind"], points=meta["points"],
                     payload_bytes=meta["payload_bytes"], crc32=meta["crc32"],
                     chunks=tuple(tuple(c) for c in meta["chunks"]),
                     by_return=tuple(meta["by_return"]), meta=meta)


def _int(meta, key, path):
    v = meta.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise PieceError(f"{path}: the piece's metadata has {key} = {v!r}, not a count")
    return v


def read_piece_info(path):
    """The :class:`PieceInfo` of the piece file ``path``, its footer, metadata and sizes
    checked (not the payload's CRC: :func:`assemble` checks it while copying).

    Raises
    ------
    PieceError
        Missing file, no or a corrupted footer (magic, version), metadata of the wrong
        length or CRC, or sizes that disagree (payload + metadata + footer = file size,
        the chunks' bytes = payload, the chunks' points = points, LAS: points * record
        length = payload): a truncated, extended or overwritten piece.
    """
    path = Path(os.fspath(path))
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise PieceError(f"{path}: cannot open the piece: {exc.strerror or exc}") from exc
    with f:
        size = os.fstat(f.fileno()).st_size
        if size < _FOOTER.size:
            raise PieceError(f"{path}: {size} bytes, shorter than a piece's "
                             f"{_FOOTER.size}-byte footer (truncated?)")
        f.seek(size - _FOOTER.size)
        magic, version, length, crc = _FOOTER.unpack(f.read(_FOOTER.size))
        if magic != _MAGIC:
            raise PieceError(f"{path}: not a clcurv piece or truncated: its last bytes are "
                             f"not the footer (magic {magic!r}, expected {_MAGIC!r})")
        if version != _VERSION:
            raise PieceError(f"{path}: piece format version {version}, this clcurv reads "
                             f"{_VERSION}")
        if length > min(_MAX_META, size - _FOOTER.size):
            raise PieceError(f"{path}: the footer claims {length} bytes of metadata but the "
                             f"piece has {size} bytes (truncated?)")
        f.seek(size - _FOOTER.size - length)
        blob = f.read(length)
    if zlib.crc32(blob) != crc:
        raise PieceError(f"{path}: the piece's metadata fails its CRC-32 (corrupted)")
    try:
        meta = json.loads(blob)
    except ValueError as exc:
        raise PieceError(f"{path}: the piece's metadata is not JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("kind") not in LAS_FORMATS:
        raise PieceError(f"{path}: the piece's metadata names no kind (las or laz)")
    n = _int(meta, "points", path)
    payload = _int(meta, "payload_bytes", path)
    _int(meta, "crc32", path)
    if payload + length + _FOOTER.size != size:
        raise PieceError(f"{path}: the piece claims a payload of {payload} bytes and "
                         f"{length} bytes of metadata, {payload + length + _FOOTER.size} "
                         f"bytes with the footer, but has {size} (truncated or extended)")
    chunks = meta.get("chunks")
    if not isinstance(chunks, list) or not all(
            isinstance(c, list) and len(c) == 2 and all(
                isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in c)
            for c in chunks):
        raise PieceError(f"{path}: the piece's chunk list is not pairs of positive counts")
    if meta["kind"] == "laz":
        if sum(c[0] for c in chunks) != n or sum(c[1] for c in chunks) != payload:
            raise PieceError(f"{path}: the piece's {len(chunks)} chunks hold "
                             f"{sum(c[0] for c in chunks)} points in "
                             f"{sum(c[1] for c in chunks)} bytes, its metadata {n} points "
                             f"in {payload} bytes")
    elif n * _int(meta, "record_length", path) != payload or chunks:
        raise PieceError(f"{path}: a LAS piece of {n} records of {meta['record_length']} "
                         f"bytes but a payload of {payload} bytes")
    br = meta.get("by_return")
    if (not isinstance(br, list) or len(br) != 15
            or not all(isinstance(v, int) and v >= 0 for v in br) or sum(br) > n):
        raise PieceError(f"{path}: the piece's points by return {br!r} are not 15 counts "
                         f"of at most {n} points")
    return _info(path, meta)


def _check_piece(info, facts):
    """PieceError unless the piece was written for the header and kind of ``facts``."""
    for key, want in facts.items():
        got = info.meta.get(key)
        if got != want:
            what = {"kind": "kind of output", "layout": "record layout",
                    "laszip_items": "LASzip items"}.get(key, key.replace("_", " "))
            raise PieceError(f"{info.path}: the piece was written for another {what} "
                             f"({got!r}) than the output's ({want!r})")


def _extremes(info, header):
    try:
        raw = base64.b64decode(info.meta.get("extremes", ""), validate=True)
        arr = np.frombuffer(raw, dtype=header.point_format.dtype())
    except (ValueError, TypeError) as exc:
        raise PieceError(f"{info.path}: the piece's extreme records are unreadable: "
                         f"{exc}") from None
    if len(arr) > info.points or (info.points and not len(arr)):
        raise PieceError(f"{info.path}: {len(arr)} extreme records for {info.points} points")
    return arr


def _output_header(path, header, infos, laz, vlr):
    """The assembled file's header: ``header`` reset and grown as laspy's LasWriter does
    (bounds, GPS time range, extra-bytes min/max from the pieces' extreme records; the
    point count and points by return summed), with the LASzip VLR for LAZ."""
    out = copy.deepcopy(header)
    for v in out.vlrs.get("LasZipVlr"):
        out.vlrs.remove(v)
    out.partial_reset()
    out.are_points_compressed = laz
    if laz:
        out.vlrs.append(LasZipVlr(vlr.record_data()))
    ext = [_extremes(i, header) for i in infos]
    ext = np.concatenate(ext) if ext else np.zeros(0, header.point_format.dtype())
    total = sum(i.points for i in infos)
    if total > out.max_point_count():
        raise WriteError(f"{path}: LAS {out.version} holds at most {out.max_point_count()} points, "
                         f"the pieces have {total}")
    if len(ext):
        out.grow(laspy.PackedPointRecord(ext, out.point_format))
    else:
        out.mins, out.maxs = np.zeros(3), np.zeros(3)     # as LasWriter.close
    out.point_count = total
    out.number_of_points_by_return = np.sum(
        [np.asarray(i.by_return, dtype=np.uint64) for i in infos] or [np.zeros(15)],
        axis=0).astype(np.uint64)
    return out


def _chunk_vlr(lazrs, header, chunks):
    """The output's LASzip VLR: fixed-size chunks when every chunk but the last has the
    same count (and the last no more), else variable-size chunks (:data:`VARIABLE_CHUNKS`);
    a single chunk of at most CHUNK_SIZE points announces CHUNK_SIZE, as laspy does."""
    counts = [c for c, _ in chunks]
    # one chunk: the chunk size laspy (and the pieces) write with, unless the chunk is larger
    fixed = counts[0] if len(counts) > 1 else max(counts + [CHUNK_SIZE])
    if all(c == fixed for c in counts[:-1]) and (not counts or counts[-1] <= fixed):
        return _laszip_vlr(lazrs, header.point_format, fixed)
    return _laszip_vlr(lazrs, header.point_format, VARIABLE_CHUNKS)


def _copy(src, dst, n, crc, path):
    """Copy the first ``n`` bytes of ``src`` to the end of ``dst`` (open files); with ``crc``
    (an int) check their CRC-32 on the way, else a kernel-side copy when there is one."""
    src.seek(0)
    if crc is None:
        left = n
        copy_range = getattr(os, "copy_file_range", None)
        while left and copy_range is not None:
            try:
                done = copy_range(src.fileno(), dst.fileno(), left)
            except OSError:             # not supported between these files: plain copy
                break
            if not done:
                break
            left -= done
        if left:
            src.seek(n - left)
            dst.seek(0, os.SEEK_END)
            _copy_plain(src, dst, left, path)
        dst.seek(0, os.SEEK_END)
        return
    value, left = 0, n
    while left:
        block = src.read(min(_COPY_BYTES, left))
        if not block:
            raise PieceError(f"{path}: the piece ended {left} bytes before its payload's end "
                             f"(changed while assembling?)")
        value = zlib.crc32(block, value)
        dst.write(block)
        left -= len(block)
    if value != crc:
        raise PieceError(f"{path}: the piece's payload fails its CRC-32 (corrupted)")


def _copy_plain(src, dst, n, path):
    before = dst.tell()
    shutil.copyfileobj(io.BufferedReader(_Limited(src, n)), dst, _COPY_BYTES)
    if dst.tell() - before != n:
        raise PieceError(f"{path}: the piece ended before its payload's end "
                         f"(changed while assembling?)")


class _Limited(io.RawIOBase):
    """The next ``n`` bytes of the file ``f``."""

    def __init__(self, f, n):
        self._f, self._left = f, n

    def readable(self):
        return True

    def readinto(self, b):
        k = self._f.readinto(memoryview(b)[:min(len(b), self._left)])
        self._left -= k or 0
        return k


def assemble(path, header, pieces, *, verify=True, finish=None):
    """Write the LAS/LAZ file ``path`` holding the points of ``pieces``, in order.

    Parameters
    ----------
    path : str or os.PathLike
        The output, ``.laz`` (the pieces must be LAZ pieces) or ``.las`` (LAS pieces).
    header : laspy.LasHeader
        The header the pieces were written for (:func:`write_piece`): version, point
        format, scales, offsets, VLRs and, LAS 1.4+, EVLRs are written as given; the point
        count, bounds, points by return, GPS time range and extra-bytes min/max are the
        pieces', as laspy would compute them writing the points itself.
    pieces : sequence of str or os.PathLike
        The piece files, in the order of their points (pieces of 0 points are allowed).
    verify : bool
        Check each payload's CRC-32 while copying it (one read of each piece). Without it,
        the sizes are checked only and the bytes are copied by the kernel
        (``os.copy_file_range``: a server-side copy on file systems that have one).
    finish : callable(header) or None
        Called on the output's header before it is written, to set what the caller knows
        better (clcurv's writers: each extra-bytes descriptor's min and max over every point,
        :class:`clcurv.io.las.ExtraStats`).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    PieceError
        A piece is missing, truncated, corrupted or written for another header or kind
        (checked on every piece before the output is written; the CRC during the copy).
    OutputPathError, WriteFailedError
        As :func:`clcurv.io.write`: the output cannot be written, or the write failed.
        On any error the previous file at ``path`` is untouched and no file remains.
    """
    path = Path(os.fspath(path))
    if not is_las(path):
        raise WriteError(f"{path}: pieces assemble into .las or .laz, not "
                         f"{path.suffix or '(none)'}")
    laz = is_laz(path)
    lazrs = _lazrs(path) if laz else None
    facts = _facts(header, "laz" if laz else "las", lazrs)
    infos = [read_piece_info(p) for p in pieces]
    for info in infos:
        _check_piece(info, facts)
    chunks = [c for i in infos for c in i.chunks]
    vlr = _chunk_vlr(lazrs, header, chunks) if laz else None
    out = _output_header(path, header, infos, laz, vlr)
    if finish is not None:
        finish(out)
    table = b""
    if laz:
        buf = io.BytesIO()
        lazrs.write_chunk_table(buf, [(c, b) for c, b in chunks], vlr)
        table = buf.getvalue()
    evlrs = header.evlrs if header.version.minor >= 4 and header.evlrs else None
    head = io.BytesIO()
    out.write_to(head)                       # sets out.offset_to_point_data
    start = out.offset_to_point_data
    payload = sum(i.payload_bytes for i in infos)
    end = start + (8 if laz else 0) + payload + len(table)
    if evlrs:
        out.number_of_evlrs, out.start_of_first_evlr = len(evlrs), end
        head = io.BytesIO()
        out.write_to(head)
    with atomic_output(path) as tmp, open(tmp, "w+b") as dst:
        dst.write(head.getvalue())
        if laz:
            dst.write(struct.pack("<q", start + 8 + payload))
        for info in infos:
            dst.flush()
            with open(info.path, "rb") as src:
                _copy(src, dst, info.payload_bytes, info.crc32 if verify else None,
                      info.path)
        dst.write(table)
        if evlrs:
            evlrs.write_to(dst, as_extended=True)
        if dst.tell() < end:
            raise WriteError(f"{path}: wrote {dst.tell()} bytes, expected {end} at least")
    return path


def windows(n, parts, chunk_size=CHUNK_SIZE):
    """``parts`` windows ``(start, stop)`` covering ``range(n)`` in order, each but the last
    a multiple of ``chunk_size`` points, as equal as that allows: pieces written with that
    ``chunk_size`` assemble into a LAZ file with fixed-size chunks (readable by every LAZ
    reader, seekable with lazrs 0.8). Windows may be empty when ``n`` is small."""
    if parts < 1 or chunk_size < 1 or n < 0:
        raise ValueError(f"windows needs n >= 0, parts >= 1 and chunk_size >= 1, got {n}, "
                         f"{parts}, {chunk_size}")
    n_chunks = -(-n // chunk_size)
    bounds = [min(n, (n_chunks * k // parts) * chunk_size) for k in range(parts)] + [n]
    return list(zip(bounds[:-1], bounds[1:]))
