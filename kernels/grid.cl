/* grid.cl -- per occupied cell, the 9 index ranges of the sorted points in its 27-cell block,
 * and the three copies of x (neighbors.h).
 *
 * Layout: uint2 ranges[1 + 9 ncells] (with middles: 1 + 18 ncells): ranges[0] = (ncells,
 * middles); ranges[ROW_INDEX(c, j)] = ranges[1 + 9 c + j], j = 0..8: row j = (dz, dy) =
 * (j / 3 - 1, j % 3 - 1) of the block of cell c, i.e. the cells (cx - 1 .. cx + 1, cy + dy,
 * cz + dz), in increasing key order: the row's points [start, end), (0, 0) for an empty
 * row; with middles (cell_ranges' flag; clcurv.grid.cloud.DeviceCloud.with_middles, for the
 * pruned walks only), then ranges[MIDDLE_INDEX(ranges, c, j)] = ranges[1 + 9 ncells + 9 c
 * + j]: those of the row's middle cell (cx, cy + dy, cz + dz) (start = end where that cell
 * is empty: the first point after it; (0, 0) for an empty row). The neighbour walk
 * (neighbors.h) uses j to place the row's coordinates, and the middle cell to leave out a
 * first or last cell beyond a small ball. The rows of all cells come first, contiguous:
 * each cell's middles interleaved with its rows (a uint4 per row, or 18 uint2 per cell)
 * made the k-NN radius walk, which reads no middle, ~9% slower on PoCL.
 *
 * Both kernels run over blocks of `per_item` consecutive occupied cells, one work-item per
 * block (clcurv.grid.binning.CELLS_PER_ITEM). cell_ranges searches each row in the sorted cell keys
 * from where it found the same row for the previous cell of the block: the first key
 * (z' ny + y') nx + max(x - 1, 0) of a row is key + const - (x > 0), which does not
 * decrease from one cell to the next (keys grow by >= 1), so the row starts at or after
 * that index, most often within 3 cells: four branch-free probes find it, a gallop when
 * they do not (measured: the old per-cell gallops from the cell itself, 9 per cell and
 * about one slab of cells away for the z - 1 and z + 1 rows, cost twice as much). The first
 * cell of a block gallops from its own index. expand_x walks the points of the block's
 * cells (x copies and cell_of), so the cell's x index costs one division per cell. */
#include "common.h"
#include "neighbors.h"

/* First i in [lo, hi) with keys[i] >= k, or hi (keys sorted). Branch-free body. */
inline uint search_range(__global const long *keys, uint lo, uint hi, long k)
{
    uint len = hi - lo;
    while (len > 0) {
        const uint step = len >> 1;
        const uint mid = lo + step;
        const int lt = keys[mid] < k;
        lo = lt ? mid + 1 : lo;
        len = lt ? len - step - 1 : step;
    }
    return lo;
}

/* First i in [0, n) with keys[i] >= k (or n), searched outwards from the guess h <= n. */
inline uint gallop(__global const long *keys, uint n, long k, uint h)
{
    uint step = 1;
    if (h < n && keys[h] < k) {               /* answer in (h, n] */
        uint lo = h + 1;
        for (;;) {
            const uint probe = lo + step - 1;
            if (probe >= n) return search_range(keys, lo, n, k);
            if (keys[probe] >= k) return search_range(keys, lo, probe, k);
            lo = probe + 1;
            step <<= 1;
        }
    }
    uint hi = h;                              /* answer in [0, h] */
    for (;;) {
        if (hi < step) return search_range(keys, 0, hi, k);
        const uint probe = hi - step;
        if (keys[probe] < k) return search_range(keys, probe + 1, hi, k);
        hi = probe;
        step <<= 1;
    }
}

/* Cell coordinates of key k = (iz ny + iy) nx + ix: two 64-bit divisions. */
inline void key_cell(long k, long nx, long ny, long *ix, long *iy, long *iz)
{
    const long q = k / nx;
    *ix = k - q * nx;
    *iz = q / ny;
    *iy = q - *iz * ny;
}

/* How many of keys[i], .., keys[i + 3] are < k, branch-free: keys holds 4 entries = LONG_MAX
 * after its ncells (clcurv.grid.binning.sentinel_keys), so any i <= ncells may be probed. Keys are
 * sorted, so when that is below 4 the first index with keys >= k is i plus it. */
inline uint below4(__global const long *keys, uint i, long k)
{
    return (keys[i] < k) + (keys[i + 1] < k) + (keys[i + 2] < k) + (keys[i + 3] < k);
}

__kernel void cell_ranges(__global const long *keys, const uint ncells,
                          __global const uint *cell_start,
                          const long nx, const long ny, const long nz, const uint per_item,
                          const uint middles, __global uint2 *ranges)
{
    const uint c0 = get_global_id(0) * per_item;
    if (c0 == 0) ranges[0] = (uint2)(ncells, middles);       /* the header */
    if (c0 >= ncells) return;
    const uint c1 = min(c0 + per_item, ncells);
    uint h[9];                 /* where each row was last found in the block (none: ncells) */
    for (int j = 0; j < 9; ++j) h[j] = ncells;
    long first = -nx, ix, iy = 0, iz = 0;     /* key of the x = 0 cell of the current row */
    for (uint c = c0; c < c1; ++c) {
        const long k = keys[c];
        if (k - first < nx)                   /* the same row as the previous cell */
            ix = k - first;
        else {
            key_cell(k, nx, ny, &ix, &iy, &iz);
            first = k - ix;
        }
        const long x0 = max(ix - 1, 0L), x1 = min(ix + 1, nx - 1);
        __global uint2 *out = ranges + ROW_INDEX(c, 0);
        __global uint2 *mid = ranges + MIDDLE_AT(ncells, c, 0);   /* the header: not yet */
        for (int j = 0; j < 9; ++j) {
            const long y = iy + j % 3 - 1, z = iz + j / 3 - 1;
            uint4 range = (uint4)(0, 0, 0, 0);
            if (y >= 0 && y < ny && z >= 0 && z < nz) {
                const long row = (z * ny + y) * nx;
                uint a;
                if (h[j] == ncells)           /* not found yet: search from the cell */
                    a = gallop(keys, ncells, row + x0, c);
                else {                        /* at or after h[j], most often within 3 */
                    a = h[j] + below4(keys, h[j], row + x0);
                    if (a == h[j] + 4)
                        a = gallop(keys, ncells, row + x0, a);
                }
                /* the row has at most 3 cells from a; its middle one (key row + ix) is
                   at m when present (the cell before it, at most one, comes first) */
                const uint b = a + below4(keys, a, row + x1 + 1);
                const uint m = a + (keys[a] < row + ix);
                const uint m1 = m + (m < b && keys[m] == row + ix);
                range = b > a ? (uint4)(cell_start[a], cell_start[b], cell_start[min(m, b)],
                                        cell_start[min(m1, b)]) : range;
                h[j] = a;
            }
            out[j] = range.xy;
            if (middles) mid[j] = range.zw;
        }
    }
}

/* The three copies of x of neighbors.h: X holds 3 arrays of n + PAD, the first filled
 * with x relative to the corner of the point's cell (then zeros). Copy a becomes x relative
 * to the corner of the point's 3-cell block starting at an index = a mod 3, i.e. plus
 * (ix - a) mod 3 cells. cell_of[s] = the alignment (ix - 1) mod 3 of the point's own rows
 * in the top bits, its cell c below. Over the points of blocks of cells, so ix costs one
 * division per cell instead of one per point. */
__kernel void expand_x(__global const long *keys, const uint ncells,
                       __global const uint *cell_start, const long nx, const uint per_item,
                       const uint n, const REAL cell, __global REAL *X,
                       __global uint *cell_of)
{
    const uint c0 = get_global_id(0) * per_item;
    if (c0 >= ncells) return;
    const uint c1 = min(c0 + per_item, ncells);
    const size_t stride = (size_t)n + PAD;
    for (uint c = c0; c < c1; ++c) {
        const int m = (int)((keys[c] % nx) % 3);
        const uint co = (uint)((m + 2) % 3) << CELL_BITS | c;
        const uint end = cell_start[c + 1];
        for (uint s = cell_start[c]; s < end; ++s) {
            const REAL x = X[s];
            for (int a = 2; a >= 0; --a)         /* copy 0 last: it holds x */
                X[a * stride + s] = x + (REAL)((m - a + 3) % 3) * cell;
            cell_of[s] = co;
        }
    }
}
