/* grid.cl -- per occupied cell, the 9 index ranges of the sorted points in its 27-cell block.
 *
 * Layout: ranges[9 c + j], j = 0..8: row j = (dz, dy) = (j / 3 - 1, j % 3 - 1) of the block,
 * i.e. the cells (cx - 1 .. cx + 1, cy + dy, cz + dz), in increasing key order; (0, 0) for
 * an empty row. The neighbour walk (neighbors.h) uses j to place the row's coordinates.
 *
 * Searches in the sorted cell keys: rows of the block have increasing keys, and the rows of
 * the cell's own z-slab are close to the cell itself, so most rows are found by galloping
 * from a nearby index (a few probes) instead of a full binary search over all cells (17
 * probes for 10^5 cells, most of them mispredicted branches). Even the rows of the z-1 and
 * z+1 slabs, about one slab of cells away, are found faster by galloping from the cell than
 * by a full binary search (measured). */
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

__kernel void cell_ranges(__global const long *keys, const uint ncells,
                          __global const uint *cell_start,
                          const long nx, const long ny, const long nz,
                          __global uint2 *ranges)
{
    const uint c = get_global_id(0);
    if (c >= ncells) return;
    const long k = keys[c];
    const long ixy = k % (nx * ny), iz = k / (nx * ny);
    const long ix = ixy % nx, iy = ixy / nx;
    const long x0 = max(ix - 1, 0L), x1 = min(ix + 1, nx - 1);
    __global uint2 *out = ranges + (size_t)c * 9;
    for (long dz = -1; dz <= 1; ++dz) {
        const long z = iz + dz;
        uint h = c;                           /* search guess: c, then the previous row's end */
        for (long dy = -1; dy <= 1; ++dy) {
            const long y = iy + dy;
            uint2 range = (uint2)(0, 0);
            if (y >= 0 && y < ny && z >= 0 && z < nz) {
                const long row = (z * ny + y) * nx;
                const uint a = gallop(keys, ncells, row + x0, h);
                uint b = a;                   /* the row has at most 3 cells from a */
                while (b < ncells && keys[b] <= row + x1) ++b;
                if (b > a)
                    range = (uint2)(cell_start[a], cell_start[b]);
                h = b;
            }
            out[(dz + 1) * 3 + dy + 1] = range;
        }
    }
}

/* The three copies of x of neighbors.h: X holds 3 arrays of n + PAD, the first filled by
 * the host with x relative to the corner of the point's cell (then zeros). Copy a becomes x
 * relative to the corner of the point's 3-cell block starting at an index = a mod 3, i.e.
 * plus (ix - a) mod 3 cells. cell_of gets the alignment (ix - 1) mod 3 of the point's own
 * rows in its top bits. */
__kernel void expand_x(__global const long *keys, const long nx, const uint n, const REAL cell,
                       __global REAL *X, __global uint *cell_of)
{
    const uint s = get_global_id(0);
    if (s >= n) return;
    const uint co = cell_of[s];
    const int m = (int)((keys[co] % nx) % 3);
    const size_t stride = (size_t)n + PAD;
    const REAL x = X[s];
    for (int a = 2; a >= 0; --a)                 /* copy 0 last: it holds x */
        X[a * stride + s] = x + (REAL)((m - a + 3) % 3) * cell;
    cell_of[s] = co | ((uint)((m + 2) % 3) << CELL_BITS);
}
