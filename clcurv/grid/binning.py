"""Host binning of a point cloud into a sparse uniform grid.

Points are binned into cubic cells of size ``cell >= radius`` from the corner ``origin`` of
their bounding box; the cell key is
``(iz * ny + iy) * nx + ix`` (x fastest, so the three cells ix-1..ix+1 of a row have
consecutive keys). Only occupied cells are stored: memory is O(N) whatever the bounding box.

Points of one cell keep their input order (a stable sort), so the layout, and every result
computed on it, does not depend on numpy's sort algorithm.

Layout (sorted by cell key, but for ``rel``):
  ``rel``          (N, 3) coordinates relative to the corner of the point's cell, in the
                   *input* order, computed in float64 before the cast to the device
                   precision. Values lie in [0, cell) whatever the cloud's extent or offset
                   (UTM, state plane, ...), so offsets between neighbours keep the device
                   precision relative to the radius.
  ``x, y, z``      the same in the sorted order, padded with ``PAD`` zeros: gathered from
                   ``rel`` on first use on the host; a DeviceCloud gathers its own on the
                   device (gather.cl), where x becomes three copies relative to 3-cell
                   blocks and ``cell_of`` gets the alignment of each point's rows in its top
                   bits (grid.cl:expand_x, kernels/neighbors.h).
  ``order``        sorted position -> input index
  ``keys``         sorted unique int64 keys of the occupied cells
  ``cell_start``   CSR start of each occupied cell in the sorted points (ncells + 1)
  ``cell_of``      occupied-cell id of each sorted point (made on first use on the host;
                   a DeviceCloud makes its own, grid.cl:expand_x)

The passes run over blocks of :data:`BLOCK` points, so their float64 and int64 temporaries
stay in the core's cache instead of costing full-size arrays (memory traffic and fresh
pages). The bounding box, the cell keys and the sort use up to 4 cores from
:data:`MIN_PARALLEL` points on, as large numpy calls on the host thread pool
(clcurv._shared.host_threads; numpy releases the GIL in them), but for clouds of up to
:data:`RADIX_POINTS` points, whose keys are sorted by radix passes on one core, faster.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from clcurv._shared.constants import CELL_BITS, CELL_MASK, PAD   # noqa: F401 (CELL_BITS: grid users)
from clcurv._shared.host_threads import cores, parallel
from clcurv._shared.validate import check_finite_box

MAX_KEY = 2 ** 62
#: Occupied cells per work-item of grid.cl (cell_ranges, expand_x): the rows of a cell are
#: searched from where the previous cell of the block found them.
CELLS_PER_ITEM = 32
#: Entries = int64 max after the cell keys that grid.cl reads (its probes of 4 keys need
#: no bounds checks): :func:`sentinel_keys`.
KEY_SENTINELS = 4
#: Points per block of bin_points' passes (their temporaries stay in the core's cache).
BLOCK = 1 << 13
#: Points per block of the cell-key pass when it runs on several cores: fewer, larger numpy
#: calls, since every call hands the GIL over (1M points on 2 cores, median of 9: 12.0 ms
#: on one core, 13.2 on two with BLOCK, 10.4 with this; the keys and coordinates are the
#: same).
PARALLEL_BLOCK = 1 << 15
#: Fewest points for which the bounding box, the cell keys and the sort use several cores.
MIN_PARALLEL = 1 << 16


@dataclass
class Grid:
    n: int
    origin: np.ndarray      # (3,) float64: the corner of cell (0, 0, 0)
    cell: float             # cell size, same unit as the points
    dims: tuple             # (nx, ny, nz)
    order: np.ndarray       # (N,) int64
    rel: np.ndarray         # (N, 3) device precision, input order
    keys: np.ndarray        # (ncells,) int64
    cell_start: np.ndarray  # (ncells + 1,) uint32

    @property
    def ncells(self):
        return len(self.keys)

    def _sorted(self, d):
        """Column ``d`` of ``rel`` in the sorted order, padded with PAD zeros."""
        c = np.zeros(self.n + PAD, self.rel.dtype)
        np.take(self.rel[:, d], self.order, out=c[:self.n])
        return c

    @cached_property
    def cell_of(self):
        """(N,) uint32 occupied-cell id of each sorted point (made on first use; a
        DeviceCloud makes its own, grid.cl:expand_x)."""
        ids = np.arange(self.ncells, dtype=np.uint32)
        return np.repeat(ids, np.diff(self.cell_start))

    @cached_property
    def x(self):
        return self._sorted(0)

    @cached_property
    def y(self):
        return self._sorted(1)

    @cached_property
    def z(self):
        return self._sorted(2)

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


def _parts(n, align=1, threads=None):
    """The bounds of min(``threads`` or the cores, 4) near-equal parts of range(n) (one
    below MIN_PARALLEL), inner bounds multiples of ``align``."""
    k = min(threads or cores(), 4) if n >= MIN_PARALLEL else 1
    cuts = [n * j // k // align * align for j in range(1, k)]
    return list(zip([0] + cuts, cuts + [n]))


def bounding_box(points, threads=None):
    """Per-column min and max of a C-contiguous (N, 3) array, parts of it on several cores
    (at most ``threads``)."""
    boxes = parallel(_box_part, [(points[a:b],) for a, b in _parts(len(points), 1024, threads)])
    return (np.min([lo for lo, _ in boxes], axis=0), np.max([hi for _, hi in boxes], axis=0))


def _box_part(points):
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


def _sort_distinct(a, threads=None):
    """Sort the distinct values ``a`` in place: with several cores, one selection
    (np.partition) puts every value in the part of its rank, then the parts are sorted
    on threads; the values being distinct, the result is the one of ``a.sort()``."""
    parts = _parts(len(a), 1, threads)
    if len(parts) > 1:
        a.partition([b for _, b in parts[:-1]])
    parallel(lambda lo, hi: a[lo:hi].sort(), parts)


def _index_bits(n, ncells_box):
    """Bits of a point index packed below the cell key (``key << bits | index``), or 0
    when key and index do not fit 63 bits together."""
    bits = max(1, (n - 1).bit_length())
    return bits if ncells_box <= 2 ** (63 - bits) else 0


def _blocks(n, size=BLOCK):
    return ((s, min(s + size, n)) for s in range(0, n, size))


def _cell_keys(points, lo, cell, dims, dtype, bits, threads=None):
    """(key, rel): the cell key of every point (``key << bits | index`` when ``bits``) and
    the (N, 3) coordinates relative to the corner of its cell in ``dtype``; parts of the
    points on several cores from :data:`MIN_PARALLEL` points on (:func:`_cell_keys_part`)."""
    n = len(points)
    key, rel = np.empty(n, np.int64), np.empty((n, 3), dtype)
    parts = _parts(n, PARALLEL_BLOCK, threads)
    size = BLOCK if len(parts) == 1 else PARALLEL_BLOCK
    parallel(lambda a, b: _cell_keys_part(points, lo, cell, dims, bits, key, rel, a, b, size),
             parts)
    return key, rel


def _cell_keys_part(points, lo, cell, dims, bits, key, rel, start, stop, size):
    """:func:`_cell_keys` of the points [start, stop) into ``key`` and ``rel``, by blocks of
    ``size`` points. The float passes run over the x, y, z of a block at once (flat,
    contiguous: numpy's inner loops at full SIMD width) with ``lo`` tiled to the block's
    length."""
    (nx, ny, _), inv = dims, 1.0 / cell
    m = 3 * min(size, stop - start)
    if m == 0:
        return
    u, f, i = np.empty(m), np.empty(m), np.empty(m, np.int64)    # block scratch
    lo3 = np.tile(np.asarray(lo, np.float64), m // 3)
    flat, rel_flat = points.reshape(-1), rel.reshape(-1)
    for s, e in _blocks(stop - start, size):
        s, e = s + start, e + start
        k, m = key[s:e], 3 * (e - s)
        uu, ff, ii = u[:m], f[:m], i[:m]
        np.subtract(flat[3 * s:3 * e], lo3[:m], out=uu)
        uu *= inv                                     # >= 0: position in cells
        np.trunc(uu, out=ff)                          # the cell (>= 0: trunc = floor)
        np.copyto(ii, ff, casting="unsafe")
        np.multiply(ii[2::3], ny, out=k)              # (iz ny + iy) nx + ix
        k += ii[1::3]
        k *= nx
        k += ii[0::3]
        # (u - i) * cell: the rounding of u costs 1e-16 x the extent, far below the cast
        uu -= ff
        uu *= cell
        np.copyto(rel_flat[3 * s:3 * e], uu, casting="same_kind")
        if bits:
            k <<= bits
            k |= np.arange(s, e, dtype=np.int64)


def _sort_cells(key, bits, threads=None):
    """(order, keys, cell_start) of the keys of :func:`_cell_keys`, sorted stably (ties
    keep the input order, so the layout does not depend on numpy's sort algorithm). Packed
    keys (``bits``) are unique: one in-place sort of them replaces the much slower stable
    argsort (16 bytes moved per element, not vectorised), and ``key`` then becomes
    ``order``. Raises ValueError beyond CELL_MASK occupied cells."""
    n, size = len(key), 4 * BLOCK         # one int64 scratch here, not three: larger blocks
    if bits:
        _sort_distinct(key, threads)
        order, skey, sk = key, None, np.empty(min(size, n), np.int64)
    else:
        order = _stable_order(key)
        skey = key[order]
    first = np.empty(min(size, n), dtype=bool)
    heads, starts, last = [], [], None
    for s, e in _blocks(n, size):
        if bits:
            k = sk[:e - s]
            np.right_shift(order[s:e], bits, out=k)
            order[s:e] &= (1 << bits) - 1
        else:
            k = skey[s:e]
        new = first[:e - s]                      # the block's points that start a cell
        np.not_equal(k[1:], k[:-1], out=new[1:])
        new[0] = last is None or k[0] != last
        last = k[-1]
        at = np.flatnonzero(new)
        heads.append(k[at])
        at += s
        starts.append(at)
    ncells = sum(map(len, heads))
    if ncells > CELL_MASK:
        raise ValueError(f"{ncells} occupied cells: at most {CELL_MASK}; "
                         "use a larger radius or split the cloud")
    cell_start = np.empty(ncells + 1, dtype=np.uint32)
    np.concatenate(starts, out=cell_start[:-1], casting="unsafe")
    cell_start[-1] = n
    return order, np.concatenate(heads), cell_start


#: Cells in the bounding box (keys below 2^32) and points up to which the keys are sorted
#: by :func:`_stable_order`'s radix passes rather than packed with the point index and
#: sorted in place (bin_points on a 2-core EPYC, best of 5: 0.25M points 7 ms against 13,
#: 1M 35-41 against 52-59, 2M 96 against 101, 4M 210 against 200, 8M 930 against 530: the
#: passes' gathers by the order go to random places, in cache only for small clouds)
RADIX_CELLS = 2.0 ** 32
RADIX_POINTS = 1 << 21


def _stable_order(key):
    """The stable argsort of the non-negative int64 ``key``: for keys below 2^32 by two
    passes of numpy's stable argsort on 16-bit digits, the low digit first (numpy sorts
    16-bit integers by radix, in linear time: ~7 ms a pass at 1M points, where the argsort
    of the int64 keys takes ~115 ms and the in-place sort of the packed keys ~35 on two
    cores, tests/test_grid_layout.py); beyond, numpy's stable argsort."""
    top = int(key.max()) if len(key) else 0
    if top >= 1 << 32:
        return np.argsort(key, kind="stable")
    order = np.argsort((key & 0xFFFF).astype(np.uint16), kind="stable")
    if top >= 1 << 16:
        high = (key >> 16).astype(np.uint16)[order]
        order = order[np.argsort(high, kind="stable")]
    return order


def sentinel_keys(keys):
    """``keys`` followed by KEY_SENTINELS int64 maxima, as grid.cl reads them."""
    out = np.empty(len(keys) + KEY_SENTINELS, np.int64)
    out[:len(keys)] = keys
    out[len(keys):] = np.iinfo(np.int64).max
    return out


def _check_inside(points, frame, cell, threads=None):
    """Refuse a frame of another cell size, or one some point lies outside of."""
    if float(cell) != frame.cell:
        raise ValueError(f"frame cell {frame.cell} differs from cell {cell}")
    if len(points):
        lo, hi = bounding_box(points, threads)
        check_finite_box(points, lo, hi)
        ijk_lo, ijk_hi = frame.cells_of(np.stack([lo, hi]))
        if (ijk_lo < 0).any() or (ijk_hi >= np.asarray(frame.dims)).any():
            raise ValueError(f"points from {format_point(lo)} to {format_point(hi)} lie outside "
                             "the frame "
                             f"of origin {format_point(frame.origin)} and {frame.dims} cells of "
                             f"size {cell:.6g}")


class ExtentError(ValueError):
    """The cloud's bounding box has more than 2^62 cells of the requested size (a far
    outlier such as a 3.4e38 "no data" value, or a radius tiny for the extent)."""


def _dims(points, lo, hi, cell):
    """(nx, ny, nz) cells of size ``cell`` covering [lo, hi], or :class:`ExtentError`.

    Computed and checked in float64 *before* any cast to int64: a coordinate such as
    3.4e38 gives a count of cells that no int64 holds (the cast would wrap, and every key
    with it). Within the bound, keys, cell indices and the kernels' int64 key arithmetic
    (key +- 1 +- nx +- nx ny) cannot overflow."""
    with np.errstate(over="ignore", invalid="ignore"):
        span = np.floor((hi - lo) * (1.0 / cell)) + 1.0    # as the cells of bin_points
        box = float(np.prod(span))
    if np.isfinite(box) and box < MAX_KEY:
        return tuple(int(d) for d in span)
    raise ExtentError(f"the points span {format_point(hi - lo)} (from {format_point(lo)} to "
                      f"{format_point(hi)}): "
                      f"{box:.3g} cells of size {cell:.6g}, more than the 2^62 a grid key "
                      f"holds. {outlier_sentence(points)}Drop far outliers and \"no data\" "
                      "values, use a larger radius, or split the cloud into tiles")


def format_point(v):
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"


def outlier_sentence(points):
    """A sentence naming the point farthest from the median (only on the error path)."""
    med = np.median(points, axis=0)
    far = int(np.argmax(np.max(np.abs(points - med), axis=1)))
    return (f"The farthest point from the median {format_point(med)} is #{far} at "
            f"{format_point(points[far])}. ")


@dataclass(frozen=True)
class Frame:
    """The cells of one grid: cell (0, 0, 0) has its corner at ``origin`` (float64), cells
    have size ``cell``, and ``dims`` (nx, ny, nz) of them cover the points. Points binned
    in one frame get the same cell-relative coordinates, cell keys and order within a cell
    whatever subset of the cloud they are binned with: the tiles of clcurv.tiles.engine share the
    frame of the whole cloud, so each computes exactly what the whole cloud's run does."""
    origin: tuple
    cell: float
    dims: tuple

    @classmethod
    def covering(cls, lo, hi, cell, points=None):
        """The frame whose origin is ``lo``, covering the box [lo, hi] (ExtentError when
        more than 2^62 cells; ``points`` only name the farthest one in the message)."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        dims = _dims(points if points is not None else np.stack([lo, hi]), lo, hi, cell)
        return cls(tuple(float(v) for v in lo), float(cell), dims)

    def cells_of(self, points):
        """(N, 3) int64 cell coordinates of float64 ``points`` (as :func:`bin_points`)."""
        u = (np.asarray(points, np.float64) - np.asarray(self.origin)) * (1.0 / self.cell)
        return u.astype(np.int64)

    def cells_xy(self, points):
        """(N, 2) int64 x-y cell coordinates of float64 ``points`` (as :meth:`cells_of`)."""
        u = (np.asarray(points, np.float64)[:, :2] - np.asarray(self.origin[:2])) \
            * (1.0 / self.cell)
        return u.astype(np.int64)


def bin_points(points, cell, dtype=np.float32, frame=None, threads=None, box=None):
    """Bin ``points`` (N, 3) float64 into cells of size ``cell``; see the module docstring.

    ``frame`` (a :class:`Frame` of cell size ``cell`` containing every point) bins them in
    that frame instead of the one of their own bounding box. ``threads`` caps the cores the
    passes use (default: up to 4; 1 for a binning on a worker thread beside another one,
    clcurv.ops.knn_radius). ``box``: the points' :func:`bounding_box` (lo, hi) when the caller
    has it already (clcurv.ops.knn_radius bins the same points twice), saving its pass."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    if frame is None:
        lo, hi = bounding_box(points, threads) if box is None else box
        check_finite_box(points, lo, hi)
        nx, ny, nz = _dims(points, lo, hi, cell)
    else:
        lo, (nx, ny, nz) = np.asarray(frame.origin, np.float64), frame.dims
        _check_inside(points, frame, cell, threads)
    box_cells = float(nx) * float(ny) * float(nz)
    # the radix sort of _stable_order (keys below 2^32, up to RADIX_POINTS), else the
    # point index packed below the keys
    radix = box_cells <= RADIX_CELLS and n <= RADIX_POINTS
    bits = 0 if radix else _index_bits(n, box_cells)
    key, rel = _cell_keys(points, lo, cell, (nx, ny, nz), dtype, bits, threads)
    order, keys, cell_start = _sort_cells(key, bits, threads)
    return Grid(n=n, origin=lo, cell=float(cell), dims=(nx, ny, nz), order=order, rel=rel,
                keys=keys, cell_start=cell_start)


#: Neighbour pairs (sum over the points of #N_r(p)) above which a run is refused: about a
#: minute of MLS2 on a 2-core CPU, hours for the float64 reference. A radius that puts most
#: of the cloud in every ball makes every operator quadratic in N.
MAX_PAIRS = 2e10


#: sampled balls counted exactly by :func:`neighbour_estimate` (each costs up to N distances)
EXACT_SAMPLE = 16


class RadiusTooLargeError(ValueError):
    """The radius puts so many points in every ball that the run would be quadratic."""


def _sample_candidates(grid, sample, seed):
    """(sorted positions of ``sample`` random points, for each the sorted positions of the
    points of the 27 cells around its own)."""
    rng = np.random.default_rng(seed)
    js = np.sort(rng.choice(grid.n, size=min(sample, grid.n), replace=False))
    nx, ny, nz = grid.dims
    ijk = _cell_index(grid, js)
    steps = np.array([(dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1)
                      for dx in (-1, 0, 1)], dtype=np.int64)
    c = ijk[:, None, :] + steps[None, :, :]                       # (S, 27, 3)
    inside = np.all((c >= 0) & (c < np.array([nx, ny, nz])), axis=2)
    near = np.where(inside, (c[..., 2] * ny + c[..., 1]) * nx + c[..., 0], -1)
    pos = np.minimum(np.searchsorted(grid.keys, near), grid.ncells - 1)
    hit = inside & (grid.keys[pos] == near)
    lo = np.where(hit, grid.cell_start[pos], 0).astype(np.int64)
    hi = np.where(hit, grid.cell_start[pos + 1], 0).astype(np.int64)
    return js, lo, hi


def _cell_index(grid, js):
    """(len(js), 3) cell coordinates of the sorted points ``js``."""
    nx, ny, _ = grid.dims
    k = grid.keys[np.searchsorted(grid.cell_start, js, side="right") - 1]
    return np.stack([k % nx, (k // nx) % ny, k // (nx * ny)], axis=1)


def neighbour_estimate(grid, points, radius, sample=64, seed=0):
    """Estimated mean #N_r(p) (point included) of the cloud, for :func:`check_pairs`.

    First an upper bound, the points of the 27 cells around ``sample`` random points; when
    that bound allows :data:`MAX_PAIRS` it is returned as is. Otherwise the balls of the
    sample are counted exactly (``points``: the (N, 3) float64 input, input order)."""
    js, lo, hi = _sample_candidates(grid, sample, seed)
    bound = float((hi - lo).sum(axis=1).mean())
    if bound * grid.n <= MAX_PAIRS:
        return bound
    r2, counts = radius * radius, []
    for j, a, b in list(zip(js, lo, hi))[:EXACT_SAMPLE]:
        for s, e in zip(a, b):
            if e > s:
                d = points[grid.order[s:e]] - points[grid.order[j]]
                counts.append(np.count_nonzero(np.einsum("ij,ij->i", d, d) < r2))
    return float(np.sum(counts)) / min(len(js), EXACT_SAMPLE)


def check_pairs(grid, points, radius):
    """Raise :class:`RadiusTooLargeError` when about N x mean #N_r(p) > :data:`MAX_PAIRS`."""
    mean = neighbour_estimate(grid, points, radius)
    if mean * grid.n > MAX_PAIRS:
        raise RadiusTooLargeError(
            f"radius {radius:.6g} puts about {mean:.0f} points in every ball (mean over "
            f"sampled points; about 30 is typical): {mean * grid.n:.2g} neighbour pairs for "
            f"{grid.n} points, a quadratic run of many minutes. Use a smaller radius (or "
            f"raise clcurv.grid.binning.MAX_PAIRS = {MAX_PAIRS:.0e} if you mean it)")
