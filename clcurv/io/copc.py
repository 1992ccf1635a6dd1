"""COPC (Cloud Optimized Point Cloud, ``.copc.laz``) read by region, through its octree.

A COPC file is a LAZ 1.4 file whose points are stored node by node of an octree: each
node's points are one LAZ chunk, and the hierarchy (pages of 32-byte entries in an EVLR,
a page's entry with a count of -1 pointing to another page) gives each node's key
(level, x, y, z), the byte range of its chunk and its point count. A node's bounds are
the cube of its key in the root cube (the info VLR's center +- halfsize).

    index = open_index("survey.copc.laz")        # the header, the info VLR, every page
    ids, xyz = index.read_region(((x0, y0), (x1, y1)))

:func:`open_index` reads the hierarchy whole and checks it before any point is decoded
(:class:`CorruptFileError` naming the entry): every page within the file, after the
point data's start, a whole number of entries, read once; every node's chunk after the
chunk-table pointer and within the file, no two chunks overlapping, no key twice; the
counts summing to the header's point count; and the nodes, in file order, equal to the
LAZ chunk table entry for entry (count and bytes). The nodes sorted by offset are then
the file's point order: a node's first *global id* (the point's index in
:func:`clcurv.io.read`) is the sum of the counts before it.

:meth:`CopcIndex.read_region` decodes the nodes whose bounds meet an x-y box (bounds
inclusive, widened by :attr:`CopcIndex.pad`), each by a seek and a read of its bytes,
and gives the global ids and the float64 coordinates of their points inside the box
(inclusive), in global-id order. Coordinates are laspy's ``X * scale + offset``, as
:func:`clcurv.io.read` has them, bit for bit. What the hierarchy claims of positions is
checked on every node decoded: a point outside its node's (widened) bounds is an
:class:`UntrustedBounds` error, as is a point outside the header's bounds, so a node
that a box skips holds no point in that box. Which point belongs where is never decided
by node bounds (:mod:`clcurv.tiles.regions` decides by cells).

Reading needs laspy and lazrs (the LAZ backend that decodes chunks by a chunk table).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import las
from .common import CorruptFileError, MissingDependencyError

#: one hierarchy entry: the key, the offset, bytes and points of its chunk (or page)
ENTRY = np.dtype([("level", "<i4"), ("x", "<i4"), ("y", "<i4"), ("z", "<i4"),
                  ("offset", "<u8"), ("size", "<i4"), ("count", "<i4")])
#: the node table of an index: key, chunk offset and bytes, points, first global id
NODE = np.dtype([("level", np.int32), ("x", np.int64), ("y", np.int64), ("z", np.int64),
                 ("offset", np.int64), ("size", np.int64), ("count", np.int64),
                 ("first", np.int64)])
#: points a region decodes at a time at most (more for a larger node): its memory
BATCH_POINTS = 1 << 20
#: most hierarchy pages an index reads (a loop of pages is caught before this anyway)
MAX_PAGES = 1 << 20
_INFO_BYTES = 160
_VLR_HEADER = 54


class UntrustedBounds(CorruptFileError):
    """The points are not where the file says: a point outside its node's bounds or the
    header's min/max. The points themselves decode (the file reads as a plain LAZ)."""


def is_copc(path):
    """Is ``path`` a COPC file: a LAS 1.4 file whose first VLR is COPC's info VLR?"""
    try:
        with open(path, "rb") as f:
            head = f.read(375 + _VLR_HEADER)
    except OSError:
        return False
    if len(head) < 100 or head[:4] != b"LASF" or (head[24], head[25]) != (1, 4):
        return False
    header_size, = struct.unpack_from("<H", head, 94)
    n_vlrs, = struct.unpack_from("<I", head, 100)
    vlr = head[header_size:header_size + _VLR_HEADER]
    return (n_vlrs > 0 and len(vlr) == _VLR_HEADER
            and vlr[2:18].split(b"\0", 1)[0] == b"copc"
            and struct.unpack_from("<H", vlr, 18)[0] == 1)


def _laspy():
    laspy = las.import_laspy(Path("x.laz"), True)
    try:
        import lazrs        # an optional extra: imported only to read COPC
    except ImportError as exc:
        raise MissingDependencyError('reading COPC by region needs lazrs: pip install '
                                     '"laspy[lazrs]"') from exc
    return laspy, lazrs


@dataclass
class CopcIndex:
    """The header and the checked hierarchy of a COPC file (:func:`open_index`): small
    (no point), picklable."""
    path: str
    n: int
    scales: np.ndarray
    offsets: np.ndarray
    mins: np.ndarray            # the header's bounds, as the file says them
    maxs: np.ndarray
    center: np.ndarray
    halfsize: float
    laszip: bytes               # the LASzip VLR's data: how the chunks decode
    nodes: np.ndarray           # NODE, the non-empty nodes sorted by offset (file order)

    @property
    def pad(self):
        """How far a node's bounds are widened, on each side, for the selection and the
        check (a COPC writer places a point by its own arithmetic): one unit of the
        coarsest x-y scale, and more than any rounding of the bounds."""
        big = float(np.max(np.abs(self.center[:2]))) + self.halfsize
        return max(float(np.max(np.abs(self.scales[:2]))), 64 * np.finfo(float).eps * big)

    def bounds(self, nodes=None):
        """(lo, hi), each (k, 3): the cubes of ``nodes`` (default: all), not widened."""
        nodes = self.nodes if nodes is None else nodes
        side = 2.0 * self.halfsize / np.exp2(nodes["level"].astype(np.float64))
        root = self.center - self.halfsize
        key = np.stack([nodes["x"], nodes["y"], nodes["z"]], axis=1).astype(np.float64)
        return root + key * side[:, None], root + (key + 1) * side[:, None]

    def select(self, box):
        """The nodes whose widened x-y bounds meet the x-y ``box`` ((x0, y0), (x1, y1)),
        inclusive, in file order."""
        (x0, y0), (x1, y1) = box
        lo, hi = self.bounds()
        p = self.pad
        hit = ((lo[:, 0] - p <= x1) & (hi[:, 0] + p >= x0)
               & (lo[:, 1] - p <= y1) & (hi[:, 1] + p >= y0))
        return self.nodes[hit]

    def region(self, box):
        """What a worker needs to read the points of ``box``: a small :class:`Region`."""
        return Region(self.path, self.laszip, self.scales, self.offsets, self.mins,
                      self.maxs, self.center, self.halfsize, self.pad, self.select(box))

    def read_region(self, box):
        """(global ids (m,) int64, xyz (m, 3) float64) of the points in the x-y ``box``
        ((x0, y0), (x1, y1), inclusive), in global-id order."""
        (x0, y0), (x1, y1) = box
        return self.region(box).read(lambda p: (p[:, 0] >= x0) & (p[:, 0] <= x1)
                                     & (p[:, 1] >= y0) & (p[:, 1] <= y1))


@dataclass
class Region:
    """Some nodes of a COPC file and how to decode them (:meth:`read`)."""
    path: str
    laszip: bytes
    scales: np.ndarray
    offsets: np.ndarray
    mins: np.ndarray
    maxs: np.ndarray
    center: np.ndarray
    halfsize: float
    pad: float
    nodes: np.ndarray

    def read(self, keep=None):
        """(global ids, xyz float64) of the points of the nodes, in global-id order: all,
        or those of the mask ``keep(xyz)``; each node's points checked within its widened
        x-y bounds, and every point within the header's bounds (:class:`UntrustedBounds`).
        The nodes are decoded :data:`BATCH_POINTS` points at a time at most (a node whole),
        each batch filtered by ``keep`` before the next."""
        laspy, lazrs = _laspy()
        nodes = self.nodes
        ids, xyz = [np.empty(0, np.int64)], [np.empty((0, 3))]
        with open(self.path, "rb") as f:
            fmt = laspy.LasHeader.read_from(f).point_format
            cut = np.cumsum(nodes["count"]) // BATCH_POINTS
            for b in np.unique(cut):
                i, p = self._decode(f, nodes[cut == b], fmt, laspy, lazrs)
                if keep is not None:
                    k = keep(p)
                    i, p = i[k], p[k]
                ids.append(i)
                xyz.append(p)
        return np.concatenate(ids), np.concatenate(xyz)

    def _decode(self, f, nodes, fmt, laspy, lazrs):
        """(global ids, xyz) of every point of ``nodes`` (checked), read from ``f``."""
        raw = bytearray(int(nodes["size"].sum()))
        view, at = memoryview(raw), 0
        for o, s in zip(nodes["offset"].tolist(), nodes["size"].tolist()):
            f.seek(o)
            got = f.readinto(view[at:at + s])
            if got != s:
                raise CorruptFileError(f"{self.path}: the COPC node at byte {o} claims "
                                       f"{s} bytes but the file ends after {got}")
            at += s
        m = int(nodes["count"].sum())
        out = np.zeros(m * fmt.size, np.uint8)
        table = list(zip(nodes["count"].tolist(), nodes["size"].tolist()))
        xyz_only = lazrs.DecompressionSelection(lazrs.SELECTIVE_DECOMPRESS_XY_RETURNS_CHANNEL
                                                | lazrs.SELECTIVE_DECOMPRESS_Z)
        try:
            lazrs.decompress_points_with_chunk_table(bytes(raw), self.laszip, out, table,
                                                     xyz_only)
        except (lazrs.LazrsError, ValueError, OSError) as exc:
            raise CorruptFileError(f"{self.path}: cannot decode the COPC nodes at bytes "
                                   f"{nodes['offset'].tolist()[:8]}...: {exc}") from exc
        rec = laspy.PackedPointRecord.from_buffer(out, fmt)
        pts = laspy.ScaleAwarePointRecord(rec.array, fmt, self.scales, self.offsets)
        xyz = np.empty((m, 3))
        xyz[:, 0], xyz[:, 1], xyz[:, 2] = pts.x, pts.y, pts.z
        ids = np.repeat(nodes["first"] - np.cumsum(nodes["count"]) + nodes["count"],
                        nodes["count"]) + np.arange(m)
        self._check(nodes, xyz)
        return ids, xyz

    def _check(self, nodes, xyz):
        side = 2.0 * self.halfsize / np.exp2(nodes["level"].astype(np.float64))
        root = self.center[:2] - self.halfsize
        key = np.stack([nodes["x"], nodes["y"]], axis=1).astype(np.float64)
        lo = np.repeat(root + key * side[:, None] - self.pad, nodes["count"], axis=0)
        hi = np.repeat(root + (key + 1) * side[:, None] + self.pad, nodes["count"], axis=0)
        bad = ((xyz[:, :2] < lo) | (xyz[:, :2] > hi)).any(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            k = int(np.searchsorted(np.cumsum(nodes["count"]), i, side="right"))
            nd = nodes[k]
            raise UntrustedBounds(
                f"{self.path}: a point at {tuple(xyz[i].tolist())} is outside the bounds "
                f"of its COPC node {(int(nd['level']), int(nd['x']), int(nd['y']), int(nd['z']))}"
                " (the octree does not hold the points where its hierarchy says)")
        out = ((xyz < self.mins) | (xyz > self.maxs)).any(axis=1)
        if out.any():
            i = int(np.flatnonzero(out)[0])
            raise UntrustedBounds(
                f"{self.path}: a point at {tuple(xyz[i].tolist())} is outside the header's "
                f"bounds {tuple(self.mins.tolist())} - {tuple(self.maxs.tolist())}")


def open_index(path):
    """The :class:`CopcIndex` of the COPC file ``path``, its hierarchy read whole and
    checked (the module docstring); CorruptFileError naming what is wrong."""
    path = Path(path)
    laspy, lazrs = _laspy()
    layout = las.read_layout(path)          # the header, VLRs and EVLRs against the file
    if not is_copc(path):
        raise CorruptFileError(f"{path}: not a COPC file (its first VLR is not COPC's "
                               "info VLR)")
    size = layout.size
    with open(path, "rb") as f:
        header = laspy.LasHeader.read_from(f)
        vlrs = [v for v in header.vlrs if v.user_id == "laszip encoded"]
        if not vlrs:
            raise CorruptFileError(f"{path}: a COPC file without a LASzip VLR")
        laszip = bytes(vlrs[0].record_data)
        f.seek(_header_size(path) + _VLR_HEADER)
        info = f.read(_INFO_BYTES)
        if len(info) != _INFO_BYTES:
            raise CorruptFileError(f"{path}: the COPC info VLR is cut short")
        cx, cy, cz, half, _, root_offset, root_size = struct.unpack_from("<5dQQ", info)
        center = np.array([cx, cy, cz])
        if not (np.isfinite(center).all() and np.isfinite(half) and half > 0):
            raise CorruptFileError(f"{path}: the COPC info VLR's root cube (center "
                                   f"{tuple(center.tolist())}, halfsize {half}) is not a cube")
        start = layout.offset_to_points + 8         # the chunk-table pointer, then chunks
        entries = _pages(path, f, root_offset, root_size, start, size)
        nodes = _nodes(path, entries, start, size, layout.count)
        f.seek(layout.offset_to_points)
        try:
            table = lazrs.read_chunk_table(f, lazrs.LazVlr(laszip))
        except (lazrs.LazrsError, ValueError, OSError, RuntimeError) as exc:
            raise CorruptFileError(f"{path}: cannot read the LAZ chunk table of the COPC "
                                   f"file: {exc}") from exc
    _match_chunks(path, nodes, table, start)
    return CopcIndex(str(path), int(layout.count), np.asarray(header.scales, float),
                     np.asarray(header.offsets, float), np.asarray(header.mins, float),
                     np.asarray(header.maxs, float), center, float(half), laszip, nodes)


def _header_size(path):
    with open(path, "rb") as f:
        f.seek(94)
        return struct.unpack("<H", f.read(2))[0]


def _pages(path, f, offset, size, start, end):
    """Every entry of the hierarchy, page after page from the root page."""
    todo, seen, out = [(offset, size, "the root page")], set(), []
    while todo:
        offset, size, what = todo.pop()
        if (offset, size) in seen:
            raise CorruptFileError(f"{path}: the COPC hierarchy reads {what} (byte {offset}) "
                                   "twice: its pages loop")
        seen.add((offset, size))
        if len(seen) > MAX_PAGES:
            raise CorruptFileError(f"{path}: more than {MAX_PAGES} COPC hierarchy pages")
        if size <= 0 or size % ENTRY.itemsize or offset < start or offset + size > end:
            raise CorruptFileError(
                f"{path}: COPC hierarchy {what} claims bytes {offset} to {offset + size}; a "
                f"page is a whole number of {ENTRY.itemsize}-byte entries after the point "
                f"data's start (byte {start}) and within the file ({end} bytes)")
        f.seek(offset)
        page = np.frombuffer(f.read(size), ENTRY)
        out.append(page)
        for e in page[page["count"] == -1]:
            todo.append((int(e["offset"]), int(e["size"]),
                         f"the page of node {_key(e)}"))
    return np.concatenate(out)


def _key(e):
    return (int(e["level"]), int(e["x"]), int(e["y"]), int(e["z"]))


def _nodes(path, entries, start, end, count):
    """The NODE table of the entries that hold points, checked, in file order."""
    bad = entries[(entries["count"] < -1) | (entries["level"] < 0) | (entries["level"] > 60)
                  | (entries["x"] < 0) | (entries["y"] < 0) | (entries["z"] < 0)]
    if len(bad):
        raise CorruptFileError(f"{path}: COPC hierarchy entry {_key(bad[0])} with count "
                               f"{int(bad[0]['count'])} is not a valid entry")
    span = np.left_shift(1, entries["level"].astype(np.int64))
    bad = entries[(entries["x"] >= span) | (entries["y"] >= span) | (entries["z"] >= span)]
    if len(bad):
        raise CorruptFileError(f"{path}: COPC node {_key(bad[0])} lies outside the octree")
    keys = np.stack([entries[k].astype(np.int64) for k in ("level", "x", "y", "z")], axis=1)
    if len(np.unique(keys, axis=0)) != len(keys):
        raise CorruptFileError(f"{path}: the COPC hierarchy lists a node twice")
    e = entries[entries["count"] > 0]
    e = e[np.argsort(e["offset"], kind="stable")]
    nodes = np.zeros(len(e), NODE)
    for k in ("level", "x", "y", "z", "offset", "size", "count"):
        nodes[k] = e[k]
    for nd in nodes:
        if nd["size"] <= 0 or nd["offset"] < start or nd["offset"] + nd["size"] > end:
            raise CorruptFileError(
                f"{path}: COPC node {_key(nd)} claims bytes {int(nd['offset'])} to "
                f"{int(nd['offset']) + int(nd['size'])}; its points lie after the point "
                f"data's start (byte {start}) and within the file ({end} bytes)")
    over = np.flatnonzero(nodes["offset"][1:] < nodes["offset"][:-1] + nodes["size"][:-1])
    if len(over):
        a, b = nodes[over[0]], nodes[over[0] + 1]
        raise CorruptFileError(f"{path}: COPC nodes {_key(a)} and {_key(b)} claim "
                               f"overlapping bytes (from {int(a['offset'])} and "
                               f"{int(b['offset'])})")
    total = int(nodes["count"].sum())
    if total != count:
        raise CorruptFileError(f"{path}: the COPC hierarchy's nodes hold {total} points and "
                               f"the header claims {count}")
    nodes["first"] = np.cumsum(nodes["count"]) - nodes["count"]
    return nodes


def _match_chunks(path, nodes, table, start):
    """The nodes in file order are the LAZ chunks: same counts, same bytes, contiguous
    from ``start`` (so their global ids are the file's point order)."""
    got = np.asarray(table, np.int64).reshape(-1, 2)
    want = np.stack([nodes["count"], nodes["size"]], axis=1)
    contiguous = (not len(nodes) or nodes["offset"][0] == start) and np.array_equal(
        nodes["offset"][1:], nodes["offset"][:-1] + nodes["size"][:-1])
    if got.shape != want.shape or not np.array_equal(got, want) or not contiguous:
        raise CorruptFileError(
            f"{path}: the COPC hierarchy's {len(nodes)} nodes are not the {len(got)} chunks "
            "of the LAZ chunk table (points and bytes, in file order)")
