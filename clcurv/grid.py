"""Host binning of a point cloud into a sparse uniform grid.

Points are centred in float64 (on the midpoint of their bounding box) *before* any cast
to the device precision, so georeferenced coordinates (UTM, state plane, ...) keep their
digits. They are binned into cubic cells of size ``cell >= radius``; the cell key is
``(iz * ny + iy) * nx + ix`` (x fastest, so the three cells ix-1..ix+1 of a row have
consecutive keys). Only occupied cells are stored: memory is O(N) whatever the bounding box.

Points of one cell keep their input order (a stable sort), so the layout, and every result
computed on it, does not depend on numpy's sort algorithm.

Device layout (sorted by cell key):
  ``x, y, z``      coordinates relative to ``center``, padded with ``PAD`` zeros
  ``order``        sorted position -> input index
  ``keys``         sorted unique int64 keys of the occupied cells
  ``cell_start``   CSR start of each occupied cell in the sorted points (ncells + 1)
  ``cell_of``      occupied-cell id of each sorted point
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PAD = 16          # padding of the coordinate arrays: the widest vector load reads past the end
MAX_KEY = 2 ** 62


@dataclass
class Grid:
    n: int
    center: np.ndarray      # (3,) float64
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


def _cell_coords(col, lo, inv_cell):
    """Integer cell coordinate along one axis (values are >= 0, so truncation is floor)."""
    t = col - lo
    t *= inv_cell
    return t.astype(np.int64)


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
    center = 0.5 * (lo + hi)
    inv = 1.0 / cell
    dims = np.floor((hi - lo) * inv).astype(np.int64) + 1
    box = float(dims[0]) * float(dims[1]) * float(dims[2])
    if box >= MAX_KEY:
        raise ValueError(f"bounding box {hi - lo} is too large for cell size {cell}: "
                         "more than 2^62 cells; use a larger radius or split the cloud")
    nx, ny, nz = (int(d) for d in dims)
    key = _cell_coords(points[:, 2], lo[2], inv)
    key *= ny
    key += _cell_coords(points[:, 1], lo[1], inv)
    key *= nx
    key += _cell_coords(points[:, 0], lo[0], inv)
    order, skey = _sort_keys(key, box)
    new_cell = np.empty(n, dtype=bool)
    new_cell[0] = True
    np.not_equal(skey[1:], skey[:-1], out=new_cell[1:])
    starts = np.flatnonzero(new_cell)
    cell_start = np.empty(len(starts) + 1, dtype=np.uint32)
    cell_start[:-1] = starts
    cell_start[-1] = n
    cell_of = np.cumsum(new_cell, dtype=np.uint32)
    cell_of -= 1
    # centre and cast each column (a sequential pass), then gather the 4- or 8-byte values in
    # sorted order: cheaper than gathering 24-byte float64 rows (np.take(points, order, 0))
    coords = []
    col = np.empty(n, dtype=dtype)
    for d in range(3):
        np.subtract(points[:, d], center[d], out=col, casting="unsafe")
        c = np.empty(n + PAD, dtype=dtype)
        c[n:] = 0
        np.take(col, order, out=c[:n])
        coords.append(c)
    return Grid(n=n, center=center, cell=float(cell), dims=(nx, ny, nz), order=order,
                x=coords[0], y=coords[1], z=coords[2], keys=skey[starts],
                cell_start=cell_start, cell_of=cell_of)
