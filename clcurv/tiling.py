"""The geometry and the budget of a tiled run (:mod:`clcurv.tiled`): tiles are blocks of
whole cells of one global grid frame, each read with a halo of whole cells; their size comes
from the memory budget and the density measured by the buckets."""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np

from .grid import Frame
from .operators import OPERATORS

#: peak host bytes per point of a tile's run (its points with their halo): the records of
#: the buckets, the float64 points, the DeviceCloud's host arrays, the result and its fields
#: (measured on an MLS2 run; see bench/tiled.py)
TILE_BYTES_PER_POINT = 900


#: peak host bytes per point of an in-memory file job (clcurv.job.run), to decide whether a
#: cloud fits memory="auto"
IN_MEMORY_BYTES_PER_POINT = 1300


#: fraction of the available RAM that memory="auto" uses, at most AUTO_CAP bytes: the
#: default run of a large file streams through tiles of at most ~600k points, whose peak
#: memory does not grow with the cloud (bench/tiled.py), and a larger tile is not faster
AUTO_FRACTION = 0.5


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
    """The byte budget of ``memory`` ('auto': AUTO_FRACTION of the available RAM, at most
    AUTO_CAP)."""
    if memory is None or memory == "auto":
        return int(min(available_memory() * AUTO_FRACTION, AUTO_CAP))
    return parse_memory(memory)


def fits_memory(n, budget, extra_per_point=0):
    """Does an in-memory run of ``n`` points fit ``budget`` bytes (``extra_per_point``: the
    bytes per point a run needs beyond a curvature file job's, e.g. more output fields)?"""
    return n * (IN_MEMORY_BYTES_PER_POINT + extra_per_point) <= budget


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
    cells around; tile t = tx + ntx * ty."""
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


def plan_tiles(buckets, radius, halo, budget, tile=None, frame=None,
               bytes_per_point=TILE_BYTES_PER_POINT):
    """The :class:`Tiling` of the whole cloud: its frame from the exact bounds (or
    ``frame``), and tiles of ``tile`` (length) or, from the budget, as large as the
    densest tile allows at ``bytes_per_point`` (a tile's peak host bytes per point)."""
    frame = frame if frame is not None else Frame.covering(buckets.lo, buckets.hi, radius)
    limit = max(int(budget // bytes_per_point), 1)
    if tile is not None:
        size = int(math.floor(float(tile) / frame.cell))
        if size < max(halo, 1):
            raise TilingError(f"tile size {tile} is smaller than the halo: a tile needs at "
                              f"least {halo} cell(s) of the radius {radius:.6g}, i.e. "
                              f"--tile-size >= {max(halo, 1) * frame.cell:.6g}")
        return Tiling(frame, size, halo)
    nx, ny, _ = frame.dims
    size = max(nx, ny)
    while True:
        tiling = Tiling(frame, size, halo)
        worst = densest(buckets, tiling)
        if worst <= limit:
            return tiling
        if size <= max(halo, 1):
            raise TilingError(
                f"the memory budget ({budget / 2**20:.0f} MiB) is too small for one tile: "
                f"the densest tile of {size} x {size} cells of the radius holds about "
                f"{worst} points with its halo, {bytes_per_point} bytes each; give "
                "more memory (--memory) or a smaller radius")
        size = max(max(halo, 1), int(size * min(0.7, math.sqrt(limit / worst))))


def densest(buckets, tiling):
    """An estimate of the most points a tile of ``tiling`` reads: the buckets' counts
    spread uniformly over their area."""
    b = buckets
    ntx, nty = tiling.shape
    density = b.counts / (b.side * b.side)
    worst = 0.0
    step = max(1, int(max(ntx, nty) // 256))
    for t in range(0, tiling.count, step if tiling.count > 65536 else 1):
        lo, hi = tiling.box(t)
        est = 0.0
        for i, j in b.overlapping(lo, hi):
            bx0 = b.origin[0] + i * b.side
            by0 = b.origin[1] + j * b.side
            ox = max(0.0, min(hi[0], bx0 + b.side) - max(lo[0], bx0))
            oy = max(0.0, min(hi[1], by0 + b.side) - max(lo[1], by0))
            edge = i in (0, b.shape[0] - 1) or j in (0, b.shape[1] - 1)
            est += b.counts[i, j] if edge and ox * oy > 0 else density[i, j] * ox * oy
        worst = max(worst, est)
    return int(worst)
