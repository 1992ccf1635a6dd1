"""Host binning of a point cloud into a sparse uniform grid.

Points are binned into cubic cells of size ``cell >= radius`` from the corner ``origin`` of
their bounding box; the cell key is
``(iz * ny + iy) * nx + ix`` (x fastest, so the three cells ix-1..ix+1 of a row have
consecutive keys). Only occupied cells are stored: memory is O(N) whatever the bounding box.

Points of one cell keep their input order (a stable sort), so the layout, and every result
computed on it, does not depend on numpy's sort algorithm.

Device layout (sorted by cell key):
  ``x, y, z``      coordinates relative to the corner of the point's cell, computed in
                   float64 before the cast to the device precision, padded with ``PAD``
                   zeros. Values lie in [0, cell) whatever the cloud's extent or offset
                   (UTM, state plane, ...), so offsets between neighbours keep the device
                   precision relative to the radius. On the device (grid.cl:expand_x) x
                   becomes three copies relative to 3-cell blocks and ``cell_of`` gets the
                   alignment of each point's rows in its top bits (kernels/neighbors.h).
  ``order``        sorted position -> input index
  ``keys``         sorted unique int64 keys of the occupied cells
  ``cell_start``   CSR start of each occupied cell in the sorted points (ncells + 1)
  ``cell_of``      occupied-cell id of each sorted point
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constants import CELL_BITS, CELL_MASK, PAD   # noqa: F401 (CELL_BITS: grid users)

MAX_KEY = 2 ** 62


@dataclass
class Grid:
    n: int
    origin: np.ndarray      # (3,) float64: the corner of cell (0, 0, 0)
    cell: float             # cell size, same unit as the points
    dims: tuple             # (nx, ny, nz)
    order: np.ndarray       # (N,) int64
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    keys: np.ndarray        # (ncells,) int64
    cell_start: np.ndarray  # (ncells + 1,) uint32
    cell_of: np.ndarray     # (N,) uint32

    @property
    def ncells(self):
        return len(self.keys)

    def cell_index(self):
        """(N, 3) int64 cell coordinates (ix, iy, iz) of the sorted points."""
        nx, ny, _ = self.dims
        k = self.keys[self.cell_of]
        return np.stack([k % nx, (k // nx) % ny, k // (nx * ny)], axis=1)

    def positions(self):
        """(N, 3) float64 positions that the stored coordinates represent, sorted order (the
        input up to the rounding of the cell-relative values to the device precision)."""
        ijk = self.cell_index()
        rel = np.stack([c[:self.n] for c in (self.x, self.y, self.z)], axis=1)
        return self.origin + ijk * self.cell + rel


def _bounding_box(points):
    """Per-column min and max of a C-contiguous (N, 3) array. ``points.min(axis=0)`` runs a
    3-wide inner loop (about 30x slower); blocks of 1024 rows reduce at full SIMD width."""
    n = len(points)
    m = n - n % 1024
    los, his = [], []
    if m:
        blk = points[:m].reshape(-1, 3 * 1024)
        los.append(blk.min(axis=0).reshape(-1, 3).min(axis=0))
        his.append(blk.max(axis=0).reshape(-1, 3).max(axis=0))
    if m < n:
        los.append(points[m:].min(axis=0))
        his.append(points[m:].max(axis=0))
    return np.min(los, axis=0), np.max(his, axis=0)


def _sort_keys(key, ncells_box):
    """(order, sorted keys): a stable sort of the cell keys (ties keep the input order, so
    the layout does not depend on numpy's sort algorithm). When key and index fit in 63
    bits together, one in-place sort of ``key << bits | index`` replaces the much slower
    argsort (which moves 16 bytes per element and is not vectorised)."""
    n = len(key)
    bits = max(1, (n - 1).bit_length())
    if ncells_box <= 2 ** (63 - bits):
        comp = key                      # key is ours (a temporary): reuse its memory
        comp <<= bits
        comp |= np.arange(n, dtype=np.int64)
        comp.sort()
        order = comp & ((1 << bits) - 1)
        comp >>= bits
        return order, comp
    order = np.argsort(key, kind="stable")
    return order, key[order]


def bin_points(points, cell, dtype=np.float32):
    """Bin ``points`` (N, 3) float64 into cells of size ``cell``; see the module docstring."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    lo, hi = _bounding_box(points)
    inv = 1.0 / cell
    dims = np.floor((hi - lo) * inv).astype(np.int64) + 1
    box = float(dims[0]) * float(dims[1]) * float(dims[2])
    if box >= MAX_KEY:
        raise ValueError(f"bounding box {hi - lo} is too large for cell size {cell}: "
                         "more than 2^62 cells; use a larger radius or split the cloud")
    nx, ny, nz = (int(d) for d in dims)
    key, i = np.empty(n, np.int64), np.empty(n, np.int64)
    rel = np.empty((3, n), dtype)
    u = np.empty(n)                               # float64 scratch, reused for every axis
    for d, m in ((2, nz), (1, ny), (0, nx)):
        np.subtract(points[:, d], lo[d], out=u)
        u *= inv                                  # >= 0: position in cells
        np.copyto(i, u, casting="unsafe")         # the cell (truncation = floor)
        if d == 2:
            key[:] = i
        else:
            key *= m
            key += i
        # (u - i) * cell: the rounding of u costs 1e-16 x the extent, far below the cast
        np.subtract(u, i, out=u)
        np.multiply(u, cell, out=rel[d], casting="same_kind")
    order, skey = _sort_keys(key, box)
    new_cell = np.empty(n, dtype=bool)
    new_cell[0] = True
    np.not_equal(skey[1:], skey[:-1], out=new_cell[1:])
    starts = np.flatnonzero(new_cell)
    if len(starts) > CELL_MASK:
        raise ValueError(f"{len(starts)} occupied cells: at most {CELL_MASK}; "
                         "use a larger radius or split the cloud")
    cell_start = np.empty(len(starts) + 1, dtype=np.uint32)
    cell_start[:-1] = starts
    cell_start[-1] = n
    cell_of = np.cumsum(new_cell, dtype=np.uint32)
    cell_of -= 1
    coords = []
    for d in range(3):                            # gather the 4- or 8-byte values in order
        c = np.empty(n + PAD, dtype=dtype)
        c[n:] = 0
        np.take(rel[d], order, out=c[:n])
        coords.append(c)
    return Grid(n=n, origin=lo, cell=float(cell), dims=(nx, ny, nz), order=order,
                x=coords[0], y=coords[1], z=coords[2], keys=skey[starts],
                cell_start=cell_start, cell_of=cell_of)
