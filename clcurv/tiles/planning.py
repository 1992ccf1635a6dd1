"""The geometry and the budget of a tiled run (:mod:`clcurv.tiles.engine`): tiles are blocks of
whole cells of one global grid frame, each read with a halo of whole cells; their size comes
from the memory budget and the density measured by the buckets."""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np

from clcurv.grid import binning as grid
from clcurv.grid.binning import ExtentError, Frame
from clcurv.ops.registry import OPERATORS

#: peak host bytes per point of a tile's run (its points with their halo): the records of
#: the buckets, the float64 points, the DeviceCloud's host arrays, the result and its fields
#: (measured on an MLS2 run; see bench/tiled.py)
TILE_BYTES_PER_POINT = 900


#: peak host bytes per point of an in-memory file job (clcurv.jobs.job) while it computes,
#: by method, above the process's baseline (~180 MB: the interpreter, OpenCL, the kernels
#: cached), to decide whether a cloud fits the budget. Measured (/usr/bin/time peak RSS,
#: PoCL, AMD EPYC Zen 4, `clcurv compute` of a 1M-point aerial scene, --radius 0.6 (~30
#: neighbours), default fields; docs/performance.md): binary PLY in and out, MLS2 549,
#: MLS1 524, 2dcov2 331, 3dcov 340, variation 248; "features": the base of
#: :func:`clcurv.features_file`, whose columns and radii add
#: :meth:`clcurv.tiles.features.FeatureParams.extra_in_memory` (16 a column, 64 a radius:
#: the default set at one radius, 16 columns, measured 349, estimated 410; every feature
#: at three radii, 63 columns, 1,116 and 1,290)
IN_MEMORY_BYTES = {"mls2": 550, "mls1": 525, "mls0": 510, "variation": 250,
                   "2dcov1": 345, "2dcov2": 345, "3dcov": 345, "features": 90}
#: the largest: a run whose method is not known
IN_MEMORY_BYTES_PER_POINT = max(IN_MEMORY_BYTES.values())
#: a LAS/LAZ file job's reading and writing take about LAS_IO_BASE + LAS_IO_PER_BYTE x the
#: record length bytes a point (the file's records, kept for the output, and the output's
#: batches: a 1M-point LAZ of point format 3, 34-byte records, peaks at 438 bytes a point
#: with variation, whose computation takes less); a run's estimate is the larger of that and
#: its computation's
LAS_IO_BASE, LAS_IO_PER_BYTE = 300, 4


#: fraction of the available RAM that memory="auto" uses: a run that fits it runs in memory
AUTO_FRACTION = 0.5


#: with memory="auto", the budget a tiled run plans its tiles with is at most AUTO_CAP bytes:
#: tiles of at most ~600k points, whose peak memory does not grow with the cloud
#: (bench/tiled.py), and a larger tile is not faster
AUTO_CAP = 512 << 20


class TilingError(ValueError):
    """A tiled run cannot be planned: a budget too small for one tile, a tile smaller than
    its halo, or options a tiled run does not take."""


def parse_memory(memory):
    """Bytes of a budget: an int, or a string like ``"2GiB"``, ``"500MB"``, ``"1.5G"``."""
    if isinstance(memory, (int, np.integer)) and not isinstance(memory, bool):
        value = int(memory)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(i?[bB]?)\s*", str(memory))
        if not m:
            raise ValueError(f"memory must be 'auto', a number of bytes or a size like "
                             f"'2GiB', got {memory!r}")
        unit = m.group(2).upper()
        base = 1024 if m.group(3).lower().startswith("i") or not m.group(3) else 1000
        value = int(float(m.group(1)) * base ** " KMGT".index(unit or " "))
    if value <= 0:
        raise ValueError(f"memory must be positive, got {memory!r}")
    return value


def available_memory():
    """Bytes of RAM available now (Linux MemAvailable; else total / 2)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError):
        return 4 << 30


def budget_of(memory):
    """The byte budget a tiled run plans its tiles with, of ``memory`` ('auto':
    AUTO_FRACTION of the available RAM, at most AUTO_CAP)."""
    return min(fit_budget(memory), AUTO_CAP) if memory in (None, "auto") else fit_budget(memory)


def fit_budget(memory):
    """The byte budget a whole cloud must fit to run in memory, of ``memory`` ('auto':
    AUTO_FRACTION of the available RAM: a run that fits comfortably runs in memory)."""
    if memory is None or memory == "auto":
        return int(available_memory() * AUTO_FRACTION)
    return parse_memory(memory)


#: Host bytes more per point of an in-memory run with ``uncertainty=True``: the error record
#: (16 device REALs), its six fields as float64 host arrays, the result's copies and the
#: written fields (an estimate from the arrays' sizes: 64 + 48 + 48 + 48)
UNCERTAINTY_BYTES = 210


def in_memory_bytes(method=None, record_length=None, extra=0):
    """The bytes a point of an in-memory run of ``method`` takes at its peak: its
    computation's (:data:`IN_MEMORY_BYTES`, None: the largest; ``extra`` more, e.g. more
    output fields), or, for LAS/LAZ input of ``record_length``-byte records, its reading and
    writing's when larger (:data:`LAS_IO_BASE`); within 25% of the measured peaks
    (docs/performance.md)."""
    b = IN_MEMORY_BYTES.get(method, IN_MEMORY_BYTES_PER_POINT) + extra
    if record_length:
        b = max(b, LAS_IO_BASE + LAS_IO_PER_BYTE * int(record_length))
    return b


def fits_memory(n, budget, extra_per_point=0, method=None, record_length=None):
    """Does an in-memory run of ``n`` points fit ``budget`` bytes (:func:`in_memory_bytes`
    of ``method``, the LAS ``record_length`` and ``extra_per_point``)?"""
    return n * in_memory_bytes(method, record_length, extra_per_point) <= budget


def halo_cells(method, weights="uniform", file_normals=False):
    """Cells of halo a tile needs for ``method`` so that its own points' results are exact:
    one per neighbourhood pass that feeds the next (see the module docstring)."""
    op = OPERATORS[method]
    passes = 2 if (op.kernel.reads_normals and op.normals == "values"
                   and not file_normals) else 1
    return passes * (2 if weights == "density" else 1)


@dataclass(frozen=True)
class Tiling:
    """Tiles of ``size`` x ``size`` cells (x, y) of ``frame``, each reading ``halo`` more
    cells around; tile t = tx + ntx * ty (an int64 that one far point makes large: loop
    over the tiles that hold points, :meth:`occupied`, :func:`occupied_tiles`)."""
    frame: Frame
    size: int
    halo: int

    @property
    def shape(self):
        nx, ny, _ = self.frame.dims
        return -(-nx // self.size), -(-ny // self.size)

    @property
    def count(self):
        a, b = self.shape
        return a * b

    def occupied(self, written):
        """The ids of the tiles that hold points, in order: those of ``written``, the sums
        by tile of the files :meth:`clcurv.tiles.buckets.Buckets.split` wrote (a tile owns points,
        or holds its neighbours' in its halo). A per-tile loop goes over these, never over
        ``range(count)``: one far point makes ``count`` (the tiles of the frame's extent)
        astronomical, the points' tiles stay few."""
        return sorted(int(t) for t in written)

    def cells(self, t, halo=True):
        """(cx0, cx1, cy0, cy1): the half-open cell ranges of tile t (with its halo)."""
        ntx, _ = self.shape
        tx, ty = t % ntx, t // ntx
        h = self.halo if halo else 0
        return (tx * self.size - h, (tx + 1) * self.size + h,
                ty * self.size - h, (ty + 1) * self.size + h)

    def box(self, t):
        """(lo, hi) x-y coordinates of tile t with its halo (for the bucket search)."""
        cx0, cx1, cy0, cy1 = self.cells(t)
        o, c = self.frame.origin, self.frame.cell
        return (o[0] + cx0 * c, o[1] + cy0 * c), (o[0] + cx1 * c, o[1] + cy1 * c)


def within(cells, rng):
    cx0, cx1, cy0, cy1 = rng
    return ((cells[:, 0] >= cx0) & (cells[:, 0] < cx1)
            & (cells[:, 1] >= cy0) & (cells[:, 1] < cy1))


def check_tile_size(tile):
    """The tile side ``tile`` (a length in the file's unit) as a float, None for None;
    :class:`TilingError` unless it is a finite number > 0 (``inf``, ``1e300`` and ``nan``
    used to end in an OverflowError or "cannot convert float NaN to integer")."""
    if tile is None:
        return None
    try:
        value = None if isinstance(tile, (bool, np.bool_)) else float(tile)
    except (TypeError, ValueError, OverflowError):
        value = None
    if value is None or not math.isfinite(value) or value <= 0:
        raise TilingError(f"the tile size must be a finite number > 0 (a length in the "
                          f"file's unit), got {tile!r}")
    return value


def tile_cells(tile, frame, halo):
    """Cells per side of tiles of side ``tile`` (a length) in ``frame``: a tile larger than
    the cloud is one tile of the whole frame (never a count of cells that overflows)."""
    value = check_tile_size(tile)
    nx, ny, _ = frame.dims
    whole = max(nx, ny, halo, 1)
    cells = value / frame.cell                       # inf for a huge tile: one tile
    size = whole if not cells < whole else int(math.floor(cells))
    if size < max(halo, 1):
        raise TilingError(f"tile size {tile} is smaller than the halo: a tile needs at "
                          f"least {max(halo, 1)} cell(s) of {frame.cell:.6g}, i.e. "
                          f"--tile-size >= {max(halo, 1) * frame.cell:.6g}")
    return size


def covering(buckets, cell):
    """The frame of the cloud of ``buckets`` at ``cell`` (:meth:`Frame.covering` of its
    exact bounds), or the in-memory run's :class:`ExtentError`, word for word: the sentence
    naming the point farthest from the median is computed from the points on disk (the
    median exactly, by :func:`_order_statistics`), as :func:`clcurv.grid.binning.bin_points` does
    from the points in memory."""
    try:
        return Frame.covering(buckets.lo, buckets.hi, cell)
    except ExtentError as exc:
        lo, hi = np.asarray(buckets.lo, float), np.asarray(buckets.hi, float)
        stub = grid.outlier_sentence(np.stack([lo, hi]))
        med, far, point = _farthest_from_median(buckets)
        sentence = (f"The farthest point from the median {grid.format_point(med)} is #{far} "
                    f"at "
                    f"{grid.format_point(point)}. ")
        raise ExtentError(str(exc).replace(stub, sentence)) from None


def _points(buckets):
    """The (ids, positions) of every point of ``buckets``, a block at a time."""
    for i, j in np.argwhere(buckets.counts > 0):
        for rec, pos in buckets.blocks(int(i), int(j)):
            yield rec["id"], pos


#: bins per pass of :func:`_order_statistics`, and the points of a range it sorts instead
SELECT_BINS = 4096
SELECT_SORT = 1 << 20


def _order_statistics(buckets, ranks):
    """(3, len(ranks)) values of the 0-based ``ranks`` of each coordinate over the points of
    ``buckets`` (as np.sort(points, axis=0)[ranks].T), out of core: each pass counts the
    values of the range that holds a rank in SELECT_BINS bins and keeps the bin of the rank,
    until at most SELECT_SORT values are left, which are sorted (a few passes)."""
    want = [(a, k) for a in range(3) for k in ranks]
    lo = {w: float(buckets.lo[w[0]]) for w in want}                # range [lo, hi)
    hi = {w: float(np.nextafter(buckets.hi[w[0]], np.inf)) for w in want}
    below = dict.fromkeys(want, 0)                                  # values < lo
    sort = dict.fromkeys(want, False)
    found = {}
    while len(found) < len(want):
        live = [w for w in want if w not in found]
        f = np.linspace(0.0, 1.0, SELECT_BINS + 1)          # (hi - lo may overflow)
        edges = {w: np.maximum.accumulate(lo[w] * (1 - f) + hi[w] * f) for w in live}
        hist = {w: np.zeros(SELECT_BINS, np.int64) for w in live}
        kept = {w: [] for w in live}
        for _, pos in _points(buckets):
            for w in live:
                v = pos[:, w[0]]
                v = v[(v >= lo[w]) & (v < hi[w])]
                if sort[w]:
                    kept[w].append(v)
                else:
                    hist[w] += np.bincount(np.searchsorted(edges[w], v, side="right") - 1,
                                           minlength=SELECT_BINS)
        for w in live:
            k = w[1] - below[w]
            if sort[w]:
                found[w] = float(np.sort(np.concatenate(kept[w]))[k])
                continue
            cum = np.cumsum(hist[w])
            b = int(np.searchsorted(cum, k, side="right"))
            below[w] += int(cum[b - 1]) if b else 0
            shrunk = (edges[w][b], edges[w][b + 1]) != (lo[w], hi[w])
            lo[w], hi[w] = float(edges[w][b]), float(edges[w][b + 1])
            if np.nextafter(lo[w], np.inf) >= hi[w]:
                found[w] = lo[w]                   # one value left: the rank's
            sort[w] = hist[w][b] <= SELECT_SORT or not shrunk
    return np.array([[found[(a, k)] for k in ranks] for a in range(3)])


def _farthest_from_median(buckets):
    """(median, id, position) of the point of ``buckets`` farthest from the median of all
    points (np.median; the largest coordinate difference, the first in input order), as
    clcurv.grid.binning names it when the extent is refused."""
    n = int(buckets.counts.sum())
    ranks = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    stats = _order_statistics(buckets, ranks)
    med = stats[:, 0] if n % 2 else (stats[:, 0] + stats[:, 1]) / 2
    best, far, point = -1.0, -1, None
    for ids, pos in _points(buckets):
        d = np.max(np.abs(pos - med), axis=1)
        top = d.max()
        first = int(ids[d == top].min())
        if top > best or (top == best and first < far):
            best, far = float(top), first
            point = pos[np.flatnonzero(ids == first)[0]]
    return med, far, point


def plan_tiles(buckets, radius, halo, budget, tile=None, frame=None,
               bytes_per_point=TILE_BYTES_PER_POINT, state=None, occupy=None,
               density=None):
    """The :class:`Tiling` of the whole cloud: its frame from the exact bounds (or
    ``frame``), and tiles of ``tile`` (length) or, from the budget, as large as the
    densest tile allows at ``bytes_per_point`` (a tile's peak host bytes per point).

    Its cost does not depend on the extent of the frame (one far point makes it billions
    of cells): the densest tile is estimated from the non-empty buckets, or, when the
    buckets are much larger than the tiles, from the points' occupancy of the cells
    (:func:`occupancy`, one pass over the buckets; ``state``: the scale space's, to place
    the points by their binned positions; ``occupy(frame)``, when given, computes it
    instead: on the workers, :mod:`clcurv.tiles.engine`). ``density``: an
    :class:`Occupancy` to size the tiles with instead (a COPC input's, from its nodes'
    counts: clcurv.tiles.regions; then ``buckets`` is not read and ``frame`` is given)."""
    check_tile_size(tile)                           # first: no pass over the points
    frame = frame if frame is not None else covering(buckets, radius)
    if tile is not None:
        return Tiling(frame, tile_cells(tile, frame, halo), halo)
    limit = max(int(budget // bytes_per_point), 1)
    nx, ny, _ = frame.dims
    size = max(nx, ny, halo, 1)
    occ = density
    while True:
        tiling = Tiling(frame, size, halo)
        worst = densest(buckets, tiling, occ)
        if occ is None and (worst is None or _finer_than_buckets(buckets, tiling)):
            # buckets far larger than the tiles, or not much smaller: their counts spread
            # uniformly misjudge clustered points (both ways); the cells' counts do not
            occ = occupancy(buckets, frame, state) if occupy is None else occupy(frame)
            worst = densest(buckets, tiling, occ)
        if worst <= limit:
            return tiling
        if size <= max(halo, 1):
            raise TilingError(
                f"the memory budget ({budget / 2**20:.0f} MiB) is too small for one tile: "
                f"the densest tile of {size} x {size} cells of the radius holds about "
                f"{worst} points with its halo, {bytes_per_point} bytes each; give "
                "more memory (--memory) or a smaller radius")
        size = max(max(halo, 1), int(size * min(0.7, math.sqrt(limit / worst))))


def _finer_than_buckets(buckets, tiling):
    """Is a tile with its halo less than two buckets wide (the buckets' counts then say
    little about where in a bucket its points lie)?"""
    return (tiling.size + 2 * tiling.halo) * tiling.frame.cell < 2 * buckets.side


#: (bucket, tile) pairs up to which :func:`densest` spreads the buckets' counts over the
#: tiles; more (buckets far larger than the tiles, as when one far point stretches the
#: bucket grid) and it needs the points' :func:`occupancy`
BUCKET_PAIRS = 1 << 16
#: most blocks an :func:`occupancy` keeps (its blocks of g x g cells double until they fit)
OCCUPANCY_BLOCKS = 1 << 18
#: blocks an :func:`occupancy` holds unmerged (at least): its memory follows the blocks
OCCUPANCY_MERGE = 1 << 16


def densest(buckets, tiling, occ=None):
    """An estimate of the most points a tile of ``tiling`` reads (with its halo): the
    counts of ``occ`` (an :class:`Occupancy`) or else of the non-empty buckets, each spread
    uniformly over its area (an edge bucket counted whole in every tile that overlaps it:
    it also holds the points clamped into the grid). None when the buckets are too coarse
    for the tiles (more than :data:`BUCKET_PAIRS` pairs of a bucket and a tile that
    overlaps it). Only tiles near points are visited: the cost does not depend on the
    frame's extent."""
    if occ is not None:
        return occ.densest(tiling)
    b = buckets
    ij = np.argwhere(b.counts > 0)
    if not len(ij):
        return 0
    o, c = tiling.frame.origin, tiling.frame.cell
    s, h = tiling.size, tiling.halo
    ntx, nty = tiling.shape
    start = np.asarray(b.origin, float)[None, :] + ij * b.side        # bucket corners
    # candidate tiles per axis: those whose box with its halo may meet the bucket (one
    # more on each side; the exact overlap below keeps the right ones)
    t0 = np.floor(((start - np.asarray(o[:2])) / c - h) / s) - 1
    t1 = np.floor(((start + b.side - np.asarray(o[:2])) / c + h) / s) + 1
    t0 = np.clip(t0, 0, [ntx - 1, nty - 1]).astype(np.int64)
    t1 = np.clip(t1, 0, [ntx - 1, nty - 1]).astype(np.int64)
    span = t1 - t0 + 1
    per = span[:, 0] * span[:, 1]
    if per.sum() > BUCKET_PAIRS:
        return None
    k = np.repeat(np.arange(len(ij)), per)
    off = np.arange(len(k)) - np.repeat(np.cumsum(per) - per, per)
    tx = t0[k, 0] + off // span[k, 1]
    ty = t0[k, 1] + off % span[k, 1]
    ox = _overlap(o[0] + (tx * s - h) * c, o[0] + ((tx + 1) * s + h) * c,
                  start[k, 0], start[k, 0] + b.side)
    oy = _overlap(o[1] + (ty * s - h) * c, o[1] + ((ty + 1) * s + h) * c,
                  start[k, 1], start[k, 1] + b.side)
    counts = b.counts[ij[:, 0], ij[:, 1]][k].astype(np.float64)
    edge = ((ij[:, 0] == 0) | (ij[:, 0] == b.shape[0] - 1)
            | (ij[:, 1] == 0) | (ij[:, 1] == b.shape[1] - 1))[k]
    area = ox * oy
    est = np.where(edge & (area > 0), counts, counts / (b.side * b.side) * area)
    return int(_largest_sum(tx + ntx * ty, est))


def _overlap(a0, a1, b0, b1):
    return np.maximum(0.0, np.minimum(a1, b1) - np.maximum(a0, b0))


def _largest_sum(keys, values):
    """The largest sum of ``values`` over equal ``keys`` (0 for none)."""
    if not len(keys):
        return 0.0
    _, inv = np.unique(keys, return_inverse=True)
    return float(np.bincount(inv.ravel(), weights=values).max())


@dataclass
class Occupancy:
    """The points of a cloud counted per block of ``g`` x ``g`` cells (x, y) of a frame:
    only the occupied blocks (``bx``, ``by``, ``count``), so its size follows the points,
    never the frame's extent."""
    frame: Frame
    g: int
    bx: np.ndarray
    by: np.ndarray
    count: np.ndarray

    def densest(self, tiling):
        """The most points a tile of ``tiling`` reads with its halo, each block's count
        spread uniformly over its cells (exact for g = 1)."""
        nx, ny, _ = self.frame.dims
        s, h, g = tiling.size, tiling.halo, self.g
        ntx, nty = tiling.shape
        a = np.stack([self.bx, self.by], axis=1) * g                    # block cells
        e = np.minimum(a + g, [nx, ny])                                 # [a, e)
        t0 = np.clip((a - h) // s, 0, [ntx - 1, nty - 1])
        t1 = np.clip((e - 1 + h) // s, 0, [ntx - 1, nty - 1])
        span = t1 - t0 + 1
        per = span[:, 0] * span[:, 1]
        if per.sum() > 16 * OCCUPANCY_BLOCKS:       # tiles far smaller than the blocks
            cells = (e - a).prod(axis=1)
            return int(np.ceil((self.count / cells).max() * (s + 2 * h) ** 2))
        k = np.repeat(np.arange(len(per)), per)
        off = np.arange(len(k)) - np.repeat(np.cumsum(per) - per, per)
        tx = t0[k, 0] + off // span[k, 1]
        ty = t0[k, 1] + off % span[k, 1]
        ox = _overlap(tx * s - h, (tx + 1) * s + h, a[k, 0], e[k, 0])
        oy = _overlap(ty * s - h, (ty + 1) * s + h, a[k, 1], e[k, 1])
        share = ox * oy / ((e - a)[k, 0] * (e - a)[k, 1])
        return int(np.ceil(_largest_sum(tx + ntx * ty, self.count[k] * share)))

    def tiles(self, tiling):
        """The ids of the tiles of ``tiling`` (without halo) that may own points: those
        that share a cell with an occupied block (exact when g divides the tile size)."""
        s, g = tiling.size, self.g
        ntx, _ = tiling.shape
        a = np.stack([self.bx, self.by], axis=1) * g
        t0, t1 = a // s, (a + g - 1) // s
        span = t1 - t0 + 1
        per = span[:, 0] * span[:, 1]
        k = np.repeat(np.arange(len(per)), per)
        off = np.arange(len(k)) - np.repeat(np.cumsum(per) - per, per)
        return np.unique((t0[k, 0] + off // span[k, 1]) + ntx * (t0[k, 1] + off % span[k, 1]))


def occupancy(buckets, frame, state=None, g=1, limit=OCCUPANCY_BLOCKS, block=1 << 18):
    """The :class:`Occupancy` of the points of ``buckets`` (placed by ``state.key`` with a
    scale space's ``state``) in blocks of ``g`` cells of ``frame``, or of 2 g, 4 g ... until
    at most ``limit`` blocks are occupied (None: no limit). One pass over the buckets; its
    memory follows the occupied blocks."""
    ny = frame.dims[1]
    g = max(int(g), 1)
    parts, held, kept = [], 0, 0

    def merge(parts):
        u, inv = np.unique(np.concatenate([k for k, _ in parts]), return_inverse=True)
        n = np.bincount(inv.ravel(), weights=np.concatenate([n for _, n in parts]))
        return u, n.astype(np.int64)

    def coarser(u, n, g):               # the blocks of 2 g from those of g (key bx nby + by)
        bx, by = np.divmod(u, -(-ny // g))
        return merge([((bx // 2) * -(-ny // (2 * g)) + by // 2, n)])

    for i, j in np.argwhere(buckets.counts > 0):
        for _, pos in buckets.blocks(int(i), int(j), state, block):
            c = frame.cells_xy(pos) // g
            parts.append(np.unique(c[:, 0] * -(-ny // g) + c[:, 1], return_counts=True))
            held += len(parts[-1][0])
            if held > 2 * max(kept, limit or 0, OCCUPANCY_MERGE):   # memory: the blocks
                u, n = merge(parts)
                while limit is not None and len(u) > limit:
                    u, n = coarser(u, n, g)
                    g *= 2
                parts, held, kept = [(u, n)], len(u), len(u)
    u, n = merge(parts) if parts else (np.empty(0, np.int64), np.empty(0, np.int64))
    while limit is not None and len(u) > limit:
        u, n = coarser(u, n, g)
        g *= 2
    bx, by = np.divmod(u, -(-ny // g))
    return Occupancy(frame, g, bx, by, n)


def merge_occupancy(frame, parts, limit=OCCUPANCY_BLOCKS):
    """One :class:`Occupancy` of ``frame`` from those of parts of the cloud (each at its own
    block size): all brought to the largest block size, counts summed per block, blocks
    doubled until at most ``limit`` are occupied."""
    ny = frame.dims[1]
    g = max([p.g for p in parts] + [1])
    keys, counts = [], []
    for p in parts:
        f = g // p.g                                      # block sizes are g0 * 2^k
        keys.append((p.bx // f) * -(-ny // g) + p.by // f)
        counts.append(p.count)
    if not keys:
        return Occupancy(frame, g, *(np.empty(0, np.int64),) * 3)
    u, inv = np.unique(np.concatenate(keys), return_inverse=True)
    n = np.bincount(inv.ravel(), weights=np.concatenate(counts)).astype(np.int64)
    while limit is not None and len(u) > limit:
        bx, by = np.divmod(u, -(-ny // g))
        u, inv = np.unique((bx // 2) * -(-ny // (2 * g)) + by // 2, return_inverse=True)
        n = np.bincount(inv.ravel(), weights=n).astype(np.int64)
        g *= 2
    bx, by = np.divmod(u, -(-ny // g))
    return Occupancy(frame, g, bx, by, n)


def occupied_tiles(buckets, tiling, state=None):
    """The sorted ids of the tiles of ``tiling`` that own points of ``buckets`` (placed by
    ``state.key`` with a scale space's ``state``): one pass over the buckets, exact; their
    number, not the ``tiling.count`` tiles of the frame's extent, is what a per-tile loop
    costs."""
    occ = occupancy(buckets, tiling.frame, state, g=tiling.size, limit=None)
    return occ.tiles(tiling)
