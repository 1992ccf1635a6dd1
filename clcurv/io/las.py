"""LAS (``.las``) and LAZ (``.laz``, compressed LAS) through ``laspy``.

``laspy`` is needed for both, and a LAZ backend (``pip install "laspy[lazrs]"``) for LAZ;
without them reading and writing raise :class:`MissingDependencyError` saying what to
install.

Reading
-------
``points`` equal ``las.x, las.y, las.z`` (X * scale + offset in float64). Every other
dimension (intensity, classification, return_number, gps_time, red, ..., extra bytes) is an
attribute; extra dimensions named ``nx, ny, nz`` are the normals. ``Cloud.header`` is the
``laspy.LasHeader``; ``Cloud.format`` is ``'las'`` or ``'laz'``, from the content (the
compression bit of the point format), so a LAZ file named ``.las`` or a LAS file named
``.laz`` is read correctly.

A COPC file (``.copc.laz``, Cloud Optimized Point Cloud) is a LAZ 1.4 file and is read as
one: its points in the order the file stores them (COPC's octree order: the root node's
points first, then each node's), which is the order of every output. Its COPC VLRs and
EVLRs (the info VLR, the hierarchy EVLR) stay in ``Cloud.header``; an output leaves them out
(below).

Before laspy sees the file, the public header block is checked against the file size
(laspy trusts its counts for allocation): signature, version 1.0-1.5, header size, point
format 0-10 and a record length at least the format's, finite non-zero scales and finite
offsets, the VLRs (54-byte headers plus their data) between the header and the point data,
the point data starting within the file, the EVLRs (60-byte headers) within the file, the
LAS 1.4 legacy count equal to the 64-bit count (or 0). For LAS the point data must hold the
header's count (``offset + count * record length <= file size``, or the first EVLR); for LAZ
the count must fit the chunk table (``number of chunks * chunk size``) and the points are
decoded in bounded steps, the array growing with the decoded points only. Any mismatch, and
any difference between the points decoded and the header's count, is a
:class:`CorruptFileError` naming the claimed value and what the file holds, never a partial
read. A header claiming 0 points is an empty cloud.

Writing
-------
With ``like`` (a Cloud read from a LAS/LAZ file with the same number of points): its header
(version, point format, scales, offsets, VLRs and EVLRs) is kept, so a point read from that
file is written back to the same integer; its attributes (classification, intensity, GPS
time, extra bytes...) are copied, and its normals, in their own dimensions, when none are
given. The output is a plain LAS/LAZ, never COPC (whatever its name): the VLRs and EVLRs
of a COPC input (user id ``copc``), which describe its octree, and any record laspy cannot
write, are left out (:func:`output_header`); the points keep the input's order. From a
``like`` Cloud read from another format (PLY, PCD, text, NPY...): a fresh header, its
normals when none are given, its attributes as extra bytes in their own types
(:func:`carried_plan`, :mod:`clcurv.io.carry`: names mended to 32 characters, one named like
a dimension of the point format suffixed ``_input``), and an 8- or 16-bit ``red, green,
blue`` triple as the RGB of point format 7 (8-bit values times 257, LAS colours being
16-bit). Anything else than a Cloud (or one of another size) is a WriteError.

Without a LAS ``like``, a fresh header: LAS 1.4, point format 6 (7 with RGB), and each axis
its own offset and scale (as PDAL's ``scale_x=auto, offset_x=auto``; :func:`fresh_scales`):
the offset is the axis's minimum and the scale :func:`scale_for_extent` of the axis's own
extent (the finest power of ten that keeps the integers within 2**30, half the int32
range), so each coordinate is kept within half its axis's scale (0.5e-9 to 5e-9 times that
axis's extent; 0.001 when all are equal), and one far point coarsens its own axis only.
When far points make an axis's scale coarser than :data:`PRECISION` (1e-6) times the extent
of 98% of the points on it, a :class:`LasPrecisionWarning` says so (the axis, the extents,
the precision kept; PLY and NPZ keep float64).

Each field is added as an extra-bytes dimension (float32, or its integer type; names of at
most 32 characters) through ``laspy.ExtraBytesParams``, described ``clcurv``. A field named
like a dimension of a LAS ``like`` (:func:`extra_dims`):

* an extra-bytes dimension (e.g. ``mean_curvature`` stored by another tool as a scaled
  integer, an array, another type): *replaced* by the field's own dimension (float32 or its
  integer type, added after the others; kept in place when it already is that dimension,
  e.g. an earlier clcurv output), so no value is quantised and NaN stays NaN;
* a standard dimension of the point format (``classification``, ``intensity``,
  ``gps_time``...): the values are stored in it when it holds every one of them exactly (an
  integer dimension or bit field: integers in its range; ``gps_time``: any), else a
  WriteError naming the dimension (:func:`check_fits`). clcurv's own field names name no
  standard dimension.

The tiled writer (:func:`clcurv.io.stream.write_las`) follows the same rules, so a run in
tiles writes what the run in memory writes. Normals are stored as float32 extra dimensions
``nx, ny, nz``. LAS cannot hold NaN coordinates, nor coordinates outside int32 at a ``like``
header's scale and offset (WriteError).
"""
from __future__ import annotations

import copy
import math
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import carry
from .common import (CorruptFileError, Format, MissingDependencyError, WriteError,
                     find_triple, int_as, native, split_names, split_named)

LAZ_HINT = 'pip install "laspy[lazrs]"'
_INTS = [np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8")]


def import_laspy(path, laz):
    hint = LAZ_HINT if laz else 'pip install laspy (or "laspy[lazrs]" for LAZ)'
    try:
        import laspy        # here: LAS/LAZ only need it, and LAZ one of its backends
    except ImportError:
        raise MissingDependencyError(f"{path}: LAS/LAZ needs the laspy package: {hint}"
                                     ) from None
    if laz and not laspy.LazBackend.detect_available():
        raise MissingDependencyError(f"{path}: LAZ needs a LAZ backend for laspy (none is "
                                     f"installed): {LAZ_HINT}")
    return laspy


def is_laz(path):
    return path.suffix.lower() == ".laz"


def laz_backends(laspy):
    """The LAZ backends laspy tries, in this order: lazrs' parallel one (its chunks decoded
    and encoded on rayon's threads, as many as the cores, or ``RAYON_NUM_THREADS``, which
    the Dask workers set to their share: :mod:`clcurv.tiles.workers`), then the sequential
    ones. Parallel is measured faster to read and to write on 2 cores
    (``bench/results/io.md``)."""
    b = laspy.LazBackend
    return tuple(x for x in (b.LazrsParallel, b.Lazrs, b.Laszip) if x.is_available())


# --------------------------------------------------------------------------- read

#: public header size by minor version (LAS 1.0-1.5; 1.5 is read by laspy 2.6+)
_HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375, 5: 393}
#: smallest record length of point formats 0-10 (LAS 1.4 R15, table 7 ff.)
_RECORD_SIZES = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
_VLR_HEADER, _EVLR_HEADER = 54, 60
_LASZIP_VLR = (b"laszip encoded", 22204)
_VARIABLE_CHUNKS = 0xFFFFFFFF
#: points are decoded in steps of at most this many bytes of records
_STEP_BYTES = 1 << 26
#: a LAZ file's records are first allocated for at most this many times its size (more
#: only as decoded points arrive), so a header count is never trusted for allocation alone
_LAZ_TRUSTED_RATIO = 64


@dataclass(frozen=True)
class _Layout:
    """What the public header block says, checked against the file size by :func:`read_layout`."""

    size: int
    version: str
    offset_to_points: int
    point_format: int
    compressed: bool
    record_length: int
    count: int


def read_layout(path):
    """Parse and check the header, the (E)VLR headers and, for LAS, the point data's size.

    Raises CorruptFileError naming the claimed value and what the file holds, before laspy
    sees the file (laspy trusts the VLR count and the point count for its allocations).
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(max(_HEADER_SIZES.values()))
        if size < _HEADER_SIZES[0]:
            raise CorruptFileError(f"{path}: {size} bytes, shorter than a LAS header "
                                   f"({_HEADER_SIZES[0]} bytes)")
        if head[:4] != b"LASF":
            raise CorruptFileError(f"{path}: not a LAS/LAZ file (signature {head[:4]!r}, "
                                   f"expected b'LASF')")
        major, minor = head[24], head[25]
        version = f"{major}.{minor}"
        if major != 1 or minor not in _HEADER_SIZES:
            raise CorruptFileError(f"{path}: LAS version {version} in the header; 1.0 to "
                                   f"1.{max(_HEADER_SIZES)} are known")
        header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
        if not _HEADER_SIZES[minor] <= header_size <= size:
            raise CorruptFileError(f"{path}: header size {header_size} in the header; a LAS "
                                   f"{version} header has at least {_HEADER_SIZES[minor]} "
                                   f"bytes and the file has {size}")
        raw_format, record_length, legacy_count = struct.unpack_from("<BHI", head, 104)
        fmt, compressed = raw_format & 0x3F, raw_format & 0xC0 == 0x80
        if fmt >= len(_RECORD_SIZES):
            raise CorruptFileError(f"{path}: point format {fmt} (header byte {raw_format}) "
                                   f"is not a LAS point format (0 to {len(_RECORD_SIZES) - 1})")
        if record_length < _RECORD_SIZES[fmt]:
            raise CorruptFileError(f"{path}: point record length {record_length} in the "
                                   f"header; point format {fmt} needs at least "
                                   f"{_RECORD_SIZES[fmt]} bytes")
        scales = struct.unpack_from("<3d", head, 131)
        offsets = struct.unpack_from("<3d", head, 155)
        if not all(math.isfinite(s) and s != 0 for s in scales):
            raise CorruptFileError(f"{path}: scale factors {scales} in the header; each must "
                                   f"be finite and non-zero")
        if not all(math.isfinite(o) for o in offsets):
            raise CorruptFileError(f"{path}: offsets {offsets} in the header; each must be "
                                   f"finite")
        count, evlr_start, n_evlrs = legacy_count, 0, 0
        if minor >= 4:
            evlr_start, n_evlrs, count = struct.unpack_from("<QIQ", head, 235)
            if legacy_count and legacy_count != count:
                raise CorruptFileError(f"{path}: the legacy point count ({legacy_count}) and "
                                       f"the 64-bit point count ({count}) of the header "
                                       f"disagree")
        if offset < header_size + n_vlrs * _VLR_HEADER:
            raise CorruptFileError(
                f"{path}: the header claims {n_vlrs} VLRs ({n_vlrs * _VLR_HEADER} bytes at "
                f"least) but the point data starts at byte {offset}, "
                f"{max(offset - header_size, 0)} bytes after the {header_size}-byte header")
        if offset > size:
            raise CorruptFileError(f"{path}: the header puts the point data at byte {offset} "
                                   f"but the file has {size} bytes (truncated?)")
        f.seek(header_size)
        laszip = _walk_vlrs(path, f.read(offset - header_size), n_vlrs, header_size, offset)
        end = size
        if n_evlrs:
            _walk_evlrs(path, f, n_evlrs, evlr_start, offset, size)
            end = evlr_start
        layout = _Layout(size, version, offset, fmt, compressed, record_length, count)
        if not compressed:
            room = (end - offset) // record_length
            if count > room:
                raise CorruptFileError(
                    f"{path}: the header claims {count} points of {record_length} bytes but "
                    f"the file has {size} bytes, room for {room} points after byte {offset}")
        elif count:
            if laszip is None:
                raise CorruptFileError(f"{path}: compressed point format {fmt} but no LASzip "
                                       f"VLR describes the compression")
            _check_chunk_table(path, f, layout, laszip, end)
    return layout


def _walk_vlrs(path, area, n_vlrs, start, offset):
    """Check each VLR ends before the point data; the LASzip VLR's data, or None."""
    pos, laszip = 0, None
    for i in range(n_vlrs):
        user_id = area[pos + 2:pos + 18].split(b"\0", 1)[0]
        record_id, length = struct.unpack_from("<HH", area, pos + 18)
        if pos + _VLR_HEADER + length > len(area):
            raise CorruptFileError(
                f"{path}: VLR {i + 1} of {n_vlrs} (at byte {start + pos}) claims {length} "
                f"bytes of data, past the start of the point data at byte {offset}")
        if (user_id, record_id) == _LASZIP_VLR:
            laszip = area[pos + _VLR_HEADER:pos + _VLR_HEADER + length]
        pos += _VLR_HEADER + length
    return laszip


def _walk_evlrs(path, f, n_evlrs, start, offset, size):
    """Check the EVLRs lie after the point data and within the file."""
    if start < offset or start + n_evlrs * _EVLR_HEADER > size:
        raise CorruptFileError(
            f"{path}: the header claims {n_evlrs} EVLRs ({n_evlrs * _EVLR_HEADER} bytes at "
            f"least) from byte {start}, but the point data starts at byte {offset} and the "
            f"file has {size} bytes")
    pos = start
    for i in range(n_evlrs):
        f.seek(pos + 20)
        length, = struct.unpack("<Q", f.read(8))
        if pos + _EVLR_HEADER + length > size:
            raise CorruptFileError(f"{path}: EVLR {i + 1} of {n_evlrs} (at byte {pos}) "
                                   f"claims {length} bytes of data but the file has {size}")
        pos += _EVLR_HEADER + length


def _check_chunk_table(path, f, layout, laszip, end):
    """Bound a LAZ point count by its chunk table (fixed-size chunks).

    LASzip (compressors 2 and 3) writes the points in chunks of at most ``chunk_size``
    points (the LASzip VLR) and, at the end, a chunk table whose position is the int64 at
    the start of the point data (or, when that is -1, the last 8 bytes of the file); the
    table starts with its version and number of chunks (uint32). Each chunk takes at
    least one byte, so ``n_chunks <= compressed bytes`` and ``count <= n_chunks *
    chunk_size``. A table that cannot be located is left to the decoder, whose reading
    is bounded anyway (:func:`_read_points`); one past the end of the file is a truncation.
    """
    if len(laszip) < 16:
        raise CorruptFileError(f"{path}: LASzip VLR of {len(laszip)} bytes, shorter than "
                               f"its 34-byte header")
    compressor, = struct.unpack_from("<H", laszip, 0)
    chunk_size, = struct.unpack_from("<I", laszip, 12)
    if compressor not in (2, 3) or chunk_size == _VARIABLE_CHUNKS:
        return
    start = layout.offset_to_points
    f.seek(start)
    table = struct.unpack("<q", f.read(8))[0] if start + 8 <= end else None
    if table == -1 and layout.size >= 8:
        f.seek(layout.size - 8)
        table, = struct.unpack("<q", f.read(8))
    if table is not None and table > layout.size - 8:
        raise CorruptFileError(f"{path}: the LAZ chunk table should be at byte {table} but the "
                               f"file has {layout.size} bytes (truncated?)")
    if table is None or not start + 8 <= table <= end - 8:
        return
    f.seek(table)
    _, n_chunks = struct.unpack("<II", f.read(8))
    data = table - start - 8
    if n_chunks > data:
        raise CorruptFileError(f"{path}: the LAZ chunk table claims {n_chunks} chunks in "
                               f"{data} bytes of compressed points")
    if layout.count > n_chunks * chunk_size:
        raise CorruptFileError(
            f"{path}: the header claims {layout.count} points but the LAZ chunk table lists "
            f"{n_chunks} chunks of at most {chunk_size} points ({n_chunks * chunk_size} "
            f"points at most)")


def _read_points(laspy, path, layout):
    """The LasData of ``path``, decoded in bounded steps and exactly ``layout.count`` points.

    The records array is allocated for the header's count when the file can hold it (LAS,
    checked by :func:`read_layout`), else (LAZ) for at most :data:`_LAZ_TRUSTED_RATIO` times the
    file size and grown as decoded points arrive; data ending early is a CorruptFileError.
    """
    count, rec = layout.count, layout.record_length
    step = max(1, _STEP_BYTES // rec)
    first = count if not layout.compressed else \
        min(count, max(step, _LAZ_TRUSTED_RATIO * layout.size // rec))
    got = 0
    with laspy.open(str(path), laz_backend=laz_backends(laspy)) as reader:
        header = reader.header
        out = np.empty(first, dtype=header.point_format.dtype())
        try:
            for chunk in reader.chunk_iterator(step):
                k = len(chunk)
                if k == 0 or got + k > count:
                    break
                if got + k > len(out):
                    grown = np.empty(min(count, max(2 * len(out), got + k)), out.dtype)
                    grown[:got] = out[:got]
                    out = grown
                out[got:got + k] = chunk.array
                got += k
        except MemoryError:
            raise
        except Exception as exc:
            if layout.compressed:
                got = _decodable(laspy, path, got, min(count, got + step))
            raise CorruptFileError(f"{path}: the header claims {count} points but only {got} "
                                   f"could be decoded ({type(exc).__name__}: {exc})") from exc
    if got != count:
        raise CorruptFileError(f"{path}: the header claims {count} points but the point data "
                               f"holds {got}")
    points = laspy.ScaleAwarePointRecord(out, header.point_format, header.scales,
                                         header.offsets)
    return laspy.LasData(header=header, points=points)


def read_range(laspy, path, first, stop, size, backend=None):
    """The records (laspy ``ScaleAwarePointRecord``) of the points first..stop-1 of the
    LAS/LAZ file ``path``, at most about ``size`` at a time, in file order (fewer than
    stop - first when the file ends early: the caller says so).

    A LAZ file is entered at the chunk that holds ``first``, through its chunk table:
    laspy's own seek for fixed-size chunks; for variable-size chunks (every COPC file),
    whose seek is wrong in lazrs 0.8 (:mod:`clcurv.io.pieces`), the chunks from the one
    holding ``first`` are decoded here by the table's counts and byte sizes
    (:func:`_variable_chunks`; lazrs)."""
    if first >= stop:
        return
    table = _variable_chunks(laspy, path) if first and is_laz(Path(path)) else None
    if table is not None:
        yield from _read_variable(laspy, path, first, stop, size, *table)
        return
    with laspy.open(str(path), laz_backend=backend) as reader:
        if first:
            reader.seek(first)
        at = first
        while at < stop:
            rec = reader.read_points(min(size, stop - at))
            if not len(rec):
                return
            at += len(rec)
            yield rec


def _variable_chunks(laspy, path):
    """(header, LASzip VLR data, chunk table (k, 2) of (points, bytes), byte of the first
    chunk) of a LAZ file of variable-size chunks read with lazrs; None for fixed-size
    chunks, or without lazrs (LASzip's own seek is right in both)."""
    try:
        import lazrs
    except ImportError:
        return None
    with open(path, "rb") as f:
        header = laspy.LasHeader.read_from(f)
        zips = [v for v in header.vlrs if v.user_id == "laszip encoded"]
        if not zips or len(zips[0].record_data) < 16:
            return None
        laszip = bytes(zips[0].record_data)
        if struct.unpack_from("<I", laszip, 12)[0] != _VARIABLE_CHUNKS:
            return None
        f.seek(header.offset_to_point_data)
        try:
            table = lazrs.read_chunk_table(f, lazrs.LazVlr(laszip))
        except (lazrs.LazrsError, ValueError, OSError, RuntimeError) as exc:
            raise CorruptFileError(f"{path}: cannot read the LAZ chunk table: {exc}"
                                   ) from exc
    table = np.asarray(table, np.int64).reshape(-1, 2)
    return header, laszip, table, header.offset_to_point_data + 8


def _read_variable(laspy, path, first, stop, size, header, laszip, table, start):
    """:func:`read_range` in a LAZ file of variable-size chunks: its chunks decoded about
    ``size`` points at a time (a chunk whole), from the one that holds ``first``."""
    import lazrs
    fmt = header.point_format
    ends = np.cumsum(table[:, 0])
    byte = start + np.r_[0, np.cumsum(table[:, 1])]
    k = int(np.searchsorted(ends, first, side="right"))
    with open(path, "rb") as f:
        while k < len(table) and ends[k] - table[k, 0] < stop:
            j = k + 1
            while (j < len(table) and ends[j - 1] - ends[k] + table[k, 0] < size
                   and ends[j - 1] < stop):
                j += 1
            f.seek(int(byte[k]))
            raw = f.read(int(byte[j] - byte[k]))
            lo, n = int(ends[k] - table[k, 0]), int(ends[j - 1] - ends[k] + table[k, 0])
            if len(raw) != byte[j] - byte[k]:
                raise CorruptFileError(f"{path}: the LAZ chunks of points {lo}..{lo + n - 1} "
                                       "are cut short (truncated file?)")
            out = np.zeros(n * fmt.size, np.uint8)
            try:
                lazrs.decompress_points_with_chunk_table(
                    raw, laszip, out, [tuple(c) for c in table[k:j].tolist()])
            except (lazrs.LazrsError, ValueError, OSError) as exc:
                raise CorruptFileError(f"{path}: cannot decode the points {lo}.."
                                       f"{lo + n - 1}: {exc}") from exc
            rec = laspy.PackedPointRecord.from_buffer(out, fmt)
            a, b = max(first, lo) - lo, min(stop, lo + n) - lo
            yield laspy.ScaleAwarePointRecord(rec.array[a:b], fmt, header.scales,
                                              header.offsets)
            k = j


def _decodable(laspy, path, start, stop):
    """How many points of a LAZ file decode, knowing ``start`` do and ``stop`` do not.

    A failed step says only that some point of it is missing; this decodes that step again
    with the sequential decoder from the chunk holding ``start``, in sub-steps of 4096 and
    then of one point, so the message can say where the data ends.
    """
    backend = laspy.LazBackend.Lazrs if laspy.LazBackend.Lazrs.is_available() else None
    for size in (4096, 1):
        try:
            with laspy.open(str(path), laz_backend=backend) as reader:
                if start:
                    reader.seek(start)
                while start < stop:
                    k = len(reader.read_points(min(size, stop - start)))
                    if k == 0:
                        return start
                    start += k
        except MemoryError:
            raise
        except Exception:  # the decoder fails where the data ends
            pass
    return start


def read(path):
    layout = read_layout(path)
    laspy = import_laspy(path, layout.compressed)
    try:
        las = _read_points(laspy, path, layout)
    except laspy.LaspyException as exc:
        if "backend" in str(exc).lower():
            raise MissingDependencyError(f"{path}: compressed LAS data needs a LAZ backend: "
                                         f"{LAZ_HINT}") from exc
        raise CorruptFileError(f"{path}: cannot read as LAS/LAZ: {exc}") from exc
    points = np.column_stack([np.asarray(las.x, dtype=np.float64),
                              np.asarray(las.y, dtype=np.float64),
                              np.asarray(las.z, dtype=np.float64)])
    columns = {n: native(np.asarray(las[n])) for n in las.point_format.dimension_names
               if n not in ("X", "Y", "Z")}
    return split_named(path, "laz" if layout.compressed else "las", columns, las.header,
                       points=points)


# --------------------------------------------------------------------------- write

#: fresh headers keep coordinates within this many integer steps of the offset, half the
#: int32 range (the other half is margin)
_FRESH_STEPS = 2**30
_FRESH_DEFAULT_SCALE = 1e-3
#: finest scale exponent (10**-300 is still a normal float64)
_FRESH_FINEST = -300


def scale_for_extent(extent):
    """The LAS scale factor of a fresh header for coordinates spanning ``extent`` units.

    The finest power of ten ``10**k`` with ``extent / 10**k <= 2**30``: with the offset at the
    per-axis minimum, the integers stay within ``[0, 2**30]``, half the int32 range, and a
    coordinate is kept within ``scale / 2``, i.e. between ``0.47e-9`` and ``4.7e-9`` times the
    extent. An extent of 0 (one point, or all equal) gives 0.001; the scale is never finer
    than ``1e-300``.

    >>> scale_for_extent(1e5), scale_for_extent(1.0), scale_for_extent(1e-3)
    (0.0001, 1e-09, 1e-12)
    """
    extent = float(extent)
    if not math.isfinite(extent) or extent < 0:
        raise ValueError(f"extent must be finite and >= 0, got {extent}")
    if extent == 0:
        return _FRESH_DEFAULT_SCALE
    k = max(math.ceil(math.log10(extent) - math.log10(_FRESH_STEPS)), _FRESH_FINEST)
    while extent / 10.0**k > _FRESH_STEPS:  # log10 rounding
        k += 1
    while k > _FRESH_FINEST and extent / 10.0**(k - 1) <= _FRESH_STEPS:
        k -= 1
    return 10.0**k


class LasPrecisionWarning(UserWarning):
    """A fresh LAS header cannot keep most of the points to :data:`PRECISION` of their own
    extent on some axis: far points stretch the extent that the 32-bit integers must span
    (:func:`fresh_scales`)."""


#: the precision a fresh header keeps, relative to the extent of the bulk of the points
#: (the 1st to the 99th percentile) on each axis; coarser gives a LasPrecisionWarning
PRECISION = 1e-6
_BULK = (0.01, 0.99)
#: the percentiles are taken on every k-th point, k = N // this (at least 1)
_BULK_SAMPLE = 100_000


def fresh_scales(path, pts):
    """(scales, offsets) of a fresh LAS header for the (N, 3) finite points ``pts``.

    Each axis has its own (PDAL's ``scale_x=auto, offset_x=auto``): the offset is the
    axis's minimum and the scale :func:`scale_for_extent` of the axis's own extent, so a
    point far away on one axis does not coarsen the others. When far points stretch an
    axis so much that its scale is coarser than :data:`PRECISION` times the extent of the
    bulk of the points on that axis (1st to 99th percentile), the 32-bit integers of LAS
    cannot keep those points to that precision: a :class:`LasPrecisionWarning` names the
    axis, the extents and the precision kept (half the scale). The points are written
    all the same, each within half its axis's scale.
    """
    pts = np.asarray(pts, dtype=np.float64)
    if not len(pts):
        return np.full(3, _FRESH_DEFAULT_SCALE), np.zeros(3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    with np.errstate(over="ignore"):
        extent = hi - lo
    if not np.isfinite(extent).all():
        raise WriteError(f"{path}: coordinates span more than float64 can hold "
                         f"(min {lo}, max {hi}); LAS cannot store them")
    scales = np.array([scale_for_extent(e) for e in extent])
    sample = pts[::max(1, len(pts) // _BULK_SAMPLE)]
    q = np.quantile(sample, _BULK, axis=0)
    bulk = q[1] - q[0]
    for i in np.flatnonzero((scales > PRECISION * bulk) & (bulk > 0)):
        axis = "xyz"[i]
        warnings.warn(
            f"{path}: LAS stores coordinates as 32-bit integers: {axis} spans "
            f"{extent[i]:.6g} (from {lo[i]:.10g} to {hi[i]:.10g}) while 98% of the points "
            f"span {bulk[i]:.6g}, so the {axis} scale is {scales[i]:g} and {axis} is kept "
            f"within {scales[i] / 2:g}, coarser than {PRECISION:g} of that extent: drop the "
            "far points, or write PLY or NPZ (float64)", LasPrecisionWarning, stacklevel=2)
    return scales, lo


def _fresh_header(laspy, path, pts, point_format=6):
    """LAS 1.4, point format 6 (7: with RGB), scales and offsets per axis
    (:func:`fresh_scales`)."""
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales, header.offsets = fresh_scales(path, pts)
    return header


#: 8-bit colours become LAS's 16-bit ones times 257 (0 -> 0, 255 -> 65535)
_RGB = ("red", "green", "blue")


def _rgb(attributes):
    """The names of an integer red, green, blue triple of 8- or 16-bit unsigned values in
    ``attributes`` (case-insensitive), or None."""
    found = find_triple(list(attributes), _RGB)
    if found is None:
        return None
    ok = all(np.asarray(attributes[k]).dtype in (np.dtype("u1"), np.dtype("u2"))
             and np.ndim(attributes[k]) == 1 for k in found)
    return found if ok else None


def carried_plan(path, like, fields):
    """For a LAS/LAZ output from ``like`` read from another format (PLY, PCD, text...): (the
    point format, the RGB names or None, the :func:`clcurv.io.carry.plan` of the other
    attributes as extra bytes). An 8- or 16-bit red, green, blue triple fills the RGB of
    point format 7 (8-bit values times 257); an attribute named like a dimension of the
    point format takes the suffix ``_input``."""
    import laspy            # here: laspy is needed for LAS/LAZ only (import_laspy)
    rgb = _rgb(like.attributes)
    fmt = 7 if rgb else 6
    rest = {k: v for k, v in like.attributes.items() if not rgb or k not in rgb}
    reserved = laspy.PointFormat(fmt).dimension_names
    return fmt, rgb, carry.plan(path, carry.specs_of(rest), list(fields), "las", reserved)


#: user ids of the VLRs and EVLRs an output leaves out: COPC's (the info VLR, the hierarchy
#: EVLR, copclib's extents VLR) describe the octree layout of the input file, which the
#: output (a plain LAS/LAZ, its points in the input's order) does not have
_DROPPED_USER_IDS = ("copc",)


def _writable(vlr):
    """True when ``vlr`` is kept in an output: not COPC's, and laspy can write its data."""
    if str(getattr(vlr, "user_id", "")).rstrip("\0").lower() in _DROPPED_USER_IDS:
        return False
    try:
        vlr.record_data_bytes()
    except NotImplementedError:       # a record laspy reads but cannot write
        return False
    return True


def output_header(header):
    """A copy of the input's LAS header for an output: every VLR and EVLR kept except COPC's
    (user id ``copc``: the octree of a COPC input, which the output does not have) and any
    other record laspy cannot write. The output is a plain LAS/LAZ, never COPC."""
    from laspy.vlrs.vlrlist import VLRList      # here: laspy for LAS/LAZ only
    out = copy.deepcopy(header)
    out.vlrs = VLRList([v for v in out.vlrs if _writable(v)])
    if out.evlrs is not None:
        out.evlrs = VLRList([v for v in out.evlrs if _writable(v)])
    return out


def _target_header(laspy, path, pts, like, fields):
    """(header, attributes to copy, their extra-bytes dtypes, normals to use when none are
    given) for the output."""
    carry.check_like(path, like, len(pts))
    if like is None:
        return _fresh_header(laspy, path, pts), {}, {}, None
    if not isinstance(like.header, laspy.LasHeader):
        # like= from PLY, PCD...: a fresh header, its attributes as extra bytes (and RGB)
        fmt, rgb, plan = carried_plan(path, like, fields)
        keep = carry.columns(path, plan, like.attributes)
        dtypes = {c.name: c.dtype for c in plan}
        if rgb:
            for dim, k in zip(_RGB, rgb):
                v = np.asarray(like.attributes[k])
                keep[dim] = v.astype(np.uint16) * np.uint16(257) if v.dtype == np.uint8 else v
        return _fresh_header(laspy, path, pts, fmt), keep, dtypes, like.normals
    return output_header(like.header), dict(like.attributes), {}, like.normals


def _scaled_ints(path, pts, header):
    """The X, Y, Z integers of ``pts`` with the header's scales and offsets (float64,
    rounded: ``round((pts - offsets) / scales)``, computed in place)."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    ints = np.subtract(pts, offsets)
    ints /= scales
    np.rint(ints, out=ints)
    if len(pts) and (ints.min() < -2**31 or ints.max() > 2**31 - 1):
        raise WriteError(f"{path}: coordinates do not fit LAS int32 with scales {scales} and "
                         f"offsets {offsets}")
    return ints


#: extra-bytes dimensions a LAS file can describe: its ExtraBytes VLR (192 bytes each) has
#: a 16-bit length
MAX_EXTRA_DIMS = 65535 // 192


def check_extra_count(path, count):
    """WriteError when ``count`` extra-bytes dimensions exceed what LAS can describe."""
    if count > MAX_EXTRA_DIMS:
        raise WriteError(f"{path}: {count} extra-bytes dimensions, but a LAS file describes "
                         f"at most {MAX_EXTRA_DIMS} (its ExtraBytes VLR has a 16-bit length): "
                         "write fewer fields (radii, features), or NPZ or PLY")


#: clcurv's count fields (``neighbours``: #N_r(p), the point itself included): stored
#: unsigned, in the first of :data:`COUNT_TYPES` that holds the largest count of the file
#: (:func:`count_dtype`)
COUNT_FIELDS = ("neighbours",)
#: uint16 (counts up to 65,535), else uint32; a count is never clipped nor wrapped
COUNT_TYPES = (np.dtype("u2"), np.dtype("u4"))


def count_dtype(path, name, a):
    """The extra-bytes type of the count field ``name`` (:data:`COUNT_FIELDS`) with values
    ``a``: uint16 when every count is at most 65,535, else uint32 (its own type when ``a``
    already has one of :data:`COUNT_TYPES`: the tiled writer's choice,
    :func:`clcurv.io.stream.write_las`). WriteError for a negative count or one beyond
    uint32."""
    a = np.asarray(a)
    if a.dtype in COUNT_TYPES:
        return a.dtype
    lo, hi = (int(a.min()), int(a.max())) if a.size else (0, 0)
    if lo < 0:
        raise WriteError(f"{path}: the count field {name!r} has a negative value ({lo})")
    for dt in COUNT_TYPES:
        if hi <= np.iinfo(dt).max:
            return dt
    raise WriteError(f"{path}: the count field {name!r} has a value ({hi}) beyond "
                     f"{COUNT_TYPES[-1]}, the widest count type")


#: the step of quantised extra bytes (``quantize=``): normals and principal directions
#: (unit vectors) 1e-4; curvatures 1e-4 / radius (1/length), the Gaussian curvature
#: 1e-4 / radius^2; the surface variation 1e-5 (:func:`quantization`)
QUANTUM = 1e-4
_UNIT_VECTORS = ("nx", "ny", "nz") + tuple(f"dir{i}_{a}" for i in "12" for a in "xyz")


def quantization(name, radius):
    """(integer dtype, scale) of clcurv's real field ``name`` stored quantised with ``radius``
    (the run's, in the file's unit), or None for a field kept float32 (``knn_radius``,
    features, the input's). The value is ``raw * scale`` (offset 0), within ``scale / 2`` of
    the computed (float64) value; the type's most negative value (uint16: its largest) is the
    descriptor's ``no_data``, for NaN (:func:`quantized`).

    =====================================  =======  ==================  ==================
    field                                  type     scale (step)        range
    =====================================  =======  ==================  ==================
    ``nx ny nz``, ``dir1_*``, ``dir2_*``    int16    1e-4                +-3.2767
    ``mean_curvature``, ``k1``, ``k2``      int32    1e-4 / r            +-214,748 / r
    ``gaussian_curvature``                  int32    1e-4 / r^2          +-214,748 / r^2
    ``surface_variation``                   uint16   1e-5                0 to 0.65534
    =====================================  =======  ==================  ==================

    A step of 1e-4 / r is a sag of 5e-5 r across the ball, far below LiDAR noise. The
    curvatures take 32 bits: LAZ compresses their high bytes to almost nothing (int16 would
    save little and clip the rare large values; bench/results/io.md)."""
    r = float(radius)
    if name in _UNIT_VECTORS:
        return np.dtype("i2"), QUANTUM
    if name in ("mean_curvature", "k1", "k2"):
        return np.dtype("i4"), QUANTUM / r
    if name == "gaussian_curvature":
        return np.dtype("i4"), QUANTUM / (r * r)
    if name == "surface_variation":
        return np.dtype("u2"), QUANTUM / 10
    return None


def no_data(dt):
    """The ``no_data`` value of quantised type ``dt``: its most negative value (unsigned:
    its largest)."""
    info = np.iinfo(dt)
    return int(info.min) if dt.kind == "i" else int(info.max)


def quantized(path, name, a, dt, scale):
    """The raw integers (``dt``) of the values ``a`` stored with ``scale``: the value (in
    float64) divided by ``scale`` and rounded to the nearest; NaN is :func:`no_data`.
    WriteError for a value the type cannot hold (an infinity, or beyond the range of
    :func:`quantization`): never clipped."""
    v = np.asarray(a, np.float64)
    nan = np.isnan(v)
    with np.errstate(invalid="ignore", over="ignore"):
        q = np.round(v / scale)
    info, nd = np.iinfo(dt), no_data(dt)
    lo, hi = (int(info.min) + 1, int(info.max)) if dt.kind == "i" else (0, int(info.max) - 1)
    bad = ~nan & ~((q >= lo) & (q <= hi))
    if bad.any():
        raise WriteError(f"{path}: field {name!r} has {int(bad.sum())} value(s) that quantised "
                         f"extra bytes cannot hold ({dt.name}, step {scale:.6g}: "
                         f"{lo * scale:.6g} to {hi * scale:.6g}; e.g. {v[bad][0]:.6g}): "
                         "write it without quantize")
    q[nan] = nd
    return q.astype(dt)


def raw_column(path, name, a, quantize):
    """The raw values of field ``name`` in the extra-bytes dimension :func:`extra_dims` made
    for it: :func:`quantized` when ``quantize`` (the run's radius) applies to it, else the
    values."""
    spec = _quantization_of(name, a, quantize)
    return a if spec is None else quantized(path, name, a, *spec)


def _quantization_of(name, a, quantize):
    if quantize is None or np.asarray(a).dtype.kind != "f":
        return None
    return quantization(name, quantize)


def _field_dtype(path, name, a, dtypes=None):
    """(the extra-bytes dtype clcurv writes field ``name`` with, its description): float32
    for real values, :func:`count_dtype` for a count field (:data:`COUNT_FIELDS`), the
    integer type of another integer field, ``dtypes[name]`` when given."""
    if dtypes and name in dtypes:
        return np.dtype(dtypes[name]), "the input's"
    a = np.asarray(a)
    if a.dtype.kind == "f":
        return np.dtype("f4"), "clcurv"
    if name in COUNT_FIELDS and a.dtype.kind in "iu":
        return count_dtype(path, name, a), "clcurv"
    return int_as(path, name, a, _INTS), "clcurv"


def _holds_as_is(info, dt):
    """True when the input's extra dimension ``info`` is the dimension clcurv would create
    with dtype ``dt`` (unscaled, no offset, one element of that type)."""
    return (info.scales is None and info.offsets is None and info.num_elements == 1
            and info.dtype is not None and np.dtype(info.dtype) == dt)


def extra_dims(laspy, path, columns, header, dtypes=None, quantize=None):
    """Make ``header`` (the output's, modified in place) hold the columns; returns the names
    of the extra-bytes dimensions created for them, whose raw values are the values
    (:func:`raw_column`: quantised with ``quantize``, the run's radius, for the fields
    :func:`quantization` names: an integer type with the descriptor's scale, offset 0 and
    ``no_data``).

    A column named like no dimension gets a new extra-bytes dimension (float32, or the
    integer type of the field, ``dtypes[name]`` when given), described ``clcurv``. A column
    named like an extra-bytes dimension of the input *replaces* it: that dimension is
    removed and the new one added at the end, unless it already is exactly that dimension
    (an earlier clcurv output); a scaled integer, another type or an array would quantise the
    values or turn NaN into a number. A column named like a standard dimension of the point
    format (``classification``, ``gps_time``...) is stored in it and must fit it
    (:func:`check_fits`)."""
    fmt = header.point_format
    extra = {d.name: d for d in fmt.extra_dimensions}
    standard = set(fmt.standard_dimension_names)
    plan, replaced = [], []
    for name, a in columns.items():
        if name in standard:
            continue
        if len(name) > 32:
            raise WriteError(f"{path}: LAS extra-bytes names have at most 32 characters: "
                             f"{name!r}")
        spec = _quantization_of(name, a, quantize) if not (dtypes and name in dtypes) \
            else None
        if spec is not None:
            dt, scale = spec
            if name in extra:
                replaced.append(name)
            plan.append(laspy.ExtraBytesParams(
                name=name, type=dt, description="clcurv", scales=np.array([scale]),
                offsets=np.array([0.0]), no_data=np.array([no_data(dt)])))
            continue
        dt, what = _field_dtype(path, name, a, dtypes)
        if name in extra:
            if _holds_as_is(extra[name], dt):
                continue
            replaced.append(name)
        plan.append(laspy.ExtraBytesParams(name=name, type=dt, description=what))
    check_extra_count(path, len(extra) - len(replaced) + len(plan))
    if replaced:
        header.remove_extra_dims(replaced)
    if plan:
        header.add_extra_dims(plan)
    return {p.name for p in plan}


def check_fits(path, point_format, name, a):
    """WriteError unless the existing unscaled integer or bit-field dimension ``name`` of
    ``point_format`` (a standard dimension of the input file that a field is stored in)
    holds the values ``a`` exactly: a feature in [0, 1] stored in a uint8 was all 0, counts
    over 255 wrapped, a 5-bit ``classification`` holds 0 to 31. Float dimensions
    (``gps_time``) hold any value."""
    info = point_format.dimension_by_name(name)
    kind = getattr(info.kind, "name", "")
    if kind == "BitField":
        lo, hi, what = 0, 2 ** info.num_bits - 1, f"a {info.num_bits}-bit field"
    else:
        dt = np.dtype(info.dtype) if info.dtype is not None else None
        if dt is None or dt.kind not in "iu" or getattr(info, "scales", None) is not None:
            return
        lo, hi, what = np.iinfo(dt).min, np.iinfo(dt).max, dt.name
    v = np.asarray(a)
    if v.dtype.kind in "iub":
        ok = not v.size or (v.min() >= lo and v.max() <= hi)
    else:
        with np.errstate(invalid="ignore"):
            ok = bool(np.all(np.isfinite(v) & (v == np.round(v)) & (v >= lo) & (v <= hi)))
    if not ok:
        raise WriteError(f"{path}: the LAS dimension {name!r} of point format "
                         f"{point_format.id} is {what} ({lo} to {hi}), which cannot hold "
                         f"the values of field {name!r} (fractions, NaN or out of range): "
                         "rename the field, or write another format")


def is_bitfield(point_format, name):
    return getattr(point_format.dimension_by_name(name).kind, "name", "") == "BitField"


#: points of each batch of records the in-memory writer hands to the codec (lazrs' parallel
#: encoder shares a batch's LAZ chunks, of 50,000 points, among its threads)
WRITE_BATCH = 1 << 20
#: points of each block of a batch whose columns are set together: its records (a few MB)
#: stay in the cache while every column is set
WRITE_BLOCK = 1 << 16


def _records(laspy, path, header, ints, values, raw, n):
    """The point records of ``header`` for the in-memory writer, :data:`WRITE_BATCH` points
    at a time (one empty batch for no point, as LasData.write), set :data:`WRITE_BLOCK`
    points at a time: X, Y, Z from ``ints`` (scaled, rounded), every dimension named in
    ``values`` set through laspy (bit fields packed, scaled dimensions scaled), the
    quantised extra bytes ``raw`` as they are. ``values`` are checked first against their
    dimensions (:func:`check_fits`): a WriteError before any point is written."""
    fmt = header.point_format
    values = {k: np.asarray(v) for k, v in values.items() if k in fmt.dimension_names}
    for name, a in values.items():
        check_fits(path, fmt, name, a)
    bits = {k for k in values if is_bitfield(fmt, k)}
    for a0 in range(0, max(n, 1), WRITE_BATCH):
        rec = laspy.ScaleAwarePointRecord.zeros(min(n, a0 + WRITE_BATCH) - a0, header=header)
        for a in range(a0, a0 + len(rec), WRITE_BLOCK):
            b = min(a0 + len(rec), a + WRITE_BLOCK)
            block = rec[a - a0:b - a0]                # a view of rec's records
            for i, axis in enumerate("XYZ"):
                block.array[axis] = ints[a:b, i]
            try:
                for name, v in values.items():
                    block[name] = v[a:b].astype(np.int64) if name in bits else v[a:b]
            except (ValueError, OverflowError, laspy.LaspyException) as exc:
                raise WriteError(f"{path}: cannot store field {name!r} in LAS point format "
                                 f"{header.point_format.id}: {exc}") from exc
            for name, v in raw.items():
                block.array[name] = v[a:b]
        yield rec


def _normal_names(header):
    """The names of the normal triple of a LAS header's dimensions (as clcurv.io.read)."""
    dims = [n for n in header.point_format.dimension_names if n not in ("X", "Y", "Z")]
    return split_names(dims, xyz=False)[1]


class ExtraStats:
    """The minimum and maximum of each extra-bytes dimension over every point written (raw
    values, no-data values and NaN left out), set in the descriptors of the header written
    (:func:`write_records`)."""

    def __init__(self, header):
        self.lo, self.hi = {}, {}
        vlrs = header.vlrs.get("ExtraBytesVlr")
        self.structs = [s for s in (vlrs[0].extra_bytes_structs if vlrs else [])
                        if s.data_type != 0]

    def grow(self, array):
        if not len(array):
            return
        for s in self.structs:
            name = s.format_name()
            if name not in (array.dtype.names or ()):
                continue
            v = np.asarray(array[name]).reshape(len(array), -1)
            nd = s.no_data
            for i in range(v.shape[1]):
                c = v[:, i]
                if nd is not None:
                    c = c[c != nd[i]]
                if not len(c):
                    continue
                if c.dtype.kind == "f":           # NaN left out (all NaN: no value)
                    lo, hi = np.fmin.reduce(c), np.fmax.reduce(c)
                    if np.isnan(lo):
                        continue
                    lo, hi = lo + 0.0, hi + 0.0   # -0.0 as 0.0: the same whatever the order
                else:
                    lo, hi = c.min(), c.max()
                key = (name, i)
                self.lo[key] = lo if key not in self.lo else min(self.lo[key], lo)
                self.hi[key] = hi if key not in self.hi else max(self.hi[key], hi)

    def state(self):
        """The statistics, picklable: [(name, element, min, max)]."""
        return [(k[0], k[1], self.lo[k].item(), self.hi[k].item()) for k in self.lo]

    def merge(self, state):
        """Add the statistics of another writer's records (:meth:`state`)."""
        for name, i, lo, hi in state:
            key = (name, i)
            self.lo[key] = lo if key not in self.lo else min(self.lo[key], lo)
            self.hi[key] = hi if key not in self.hi else max(self.hi[key], hi)

    def put(self, header):
        """Set the statistics in the descriptors of ``header`` (the writer's copy); a
        dimension without a value gets none (its min and max bits cleared)."""
        vlrs = header.vlrs.get("ExtraBytesVlr")
        for s in (vlrs[0].extra_bytes_structs if vlrs else []):
            if s.data_type == 0:
                continue
            name, n = s.format_name(), s.num_elements()
            if all((name, i) in self.lo for i in range(n)):
                s.options |= s.MIN_BIT_MASK | s.MAX_BIT_MASK
                s._raw_min()[:] = [self.lo[name, i] for i in range(n)]
                s._raw_max()[:] = [self.hi[name, i] for i in range(n)]
            else:
                s.options &= ~(s.MIN_BIT_MASK | s.MAX_BIT_MASK)


def write_records(laspy, path, header, chunks, evlrs=None):
    """Write ``path`` (LAZ when its extension says so, :func:`laz_backends`) with ``header``
    and the point records ``chunks`` (``laspy.ScaleAwarePointRecord`` of that header, in
    order), then ``evlrs``; both writers use it (:func:`write` in memory, one chunk;
    :func:`clcurv.io.stream.write_las` in tiles, a window at a time).

    The minimum and maximum that each extra-bytes descriptor holds are those of every point
    (:class:`ExtraStats`): laspy's own take the first point of each chunk written, so they
    would be wrong and would differ between a file written at once and one written in
    chunks."""
    compress = is_laz(path)
    # the file opened here, as LasData.write does: a failed write (disk full) is then the
    # OSError, not lazrs' "Failed to call flush"
    with open(path, "wb+") as f, \
            laspy.open(f, mode="w", header=header, do_compress=compress, closefd=False,
                       laz_backend=laz_backends(laspy) if compress else None) as writer:
        stats = ExtraStats(writer.header)
        for rec in chunks:
            writer.write_points(rec)
            stats.grow(rec.array)
        stats.put(writer.header)
        if evlrs:
            writer.write_evlrs(evlrs)


def write(path, pts, fields, normals, like, carried, quantize=None):
    """The LAS/LAZ writer of :func:`clcurv.io.write`; ``quantize``: the run's radius, to
    store clcurv's real fields as quantised extra bytes (:func:`quantization`), or None
    (float32)."""
    laspy = import_laspy(path, is_laz(path))
    if not np.isfinite(pts).all():
        raise WriteError(f"{path}: LAS cannot store NaN/Inf coordinates "
                         f"({int((~np.isfinite(pts).all(axis=1)).sum())} rows)")
    del carried                     # LAS keeps what like= has itself (Format.carries None)
    header, keep, dtypes, like_normals = _target_header(laspy, path, pts, like, fields)
    if normals is None and like_normals is not None and isinstance(like.header,
                                                                   laspy.LasHeader):
        # a LAS like's own normals stay in its own dimensions, as the input has them
        names = _normal_names(like.header)
        keep.update({k: like_normals[:, i] for i, k in enumerate(names)})
        like_normals = None
    normals = like_normals if normals is None else normals
    ints = _scaled_ints(path, pts, header)
    columns = dict(fields)
    if normals is not None:
        # float32 fields; quantised ones from the float64 values, as the tiled writer's
        nrm = np.asarray(normals, dtype=np.float32 if quantize is None else np.float64)
        columns = {"nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], **columns}
    if dtypes:                      # carried from a non-LAS like: extra bytes, first
        columns = {**{k: keep[k] for k in dtypes}, **columns}
    added = extra_dims(laspy, path, columns, header, dtypes, quantize)
    keep = {k: v for k, v in keep.items() if k not in columns}
    raw = {k: raw_column(path, k, v, quantize) for k, v in columns.items()
           if k in added and _quantization_of(k, v, quantize) is not None}
    values = {**keep, **{k: v for k, v in columns.items() if k not in raw}}
    write_records(laspy, path, header, _records(laspy, path, header, ints, values, raw,
                                                len(pts)),
                  header.evlrs if header.version.minor >= 4 else None)


FORMAT = Format(reads={".las": "LAS", ".laz": "LAZ (compressed LAS)"}, read=read,
                writes={".las": "LAS", ".laz": "LAZ"}, write=write)
