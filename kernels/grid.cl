/* grid.cl -- per occupied cell, the 9 index ranges of the sorted points in its 27-cell block. */
#include "common.h"

inline uint lower_bound(__global const long *keys, uint n, long k)
{
    uint lo = 0, hi = n;
    while (lo < hi) {
        const uint mid = (lo + hi) >> 1;
        if (keys[mid] < k) lo = mid + 1; else hi = mid;
    }
    return lo;
}

__kernel void cell_ranges(__global const long *keys, const uint ncells,
                          __global const uint *cell_start,
                          const long nx, const long ny, const long nz,
                          __global uint2 *ranges)
{
    const uint c = get_global_id(0);
    if (c >= ncells) return;
    const long k = keys[c];
    const long ix = k % nx, iy = (k / nx) % ny, iz = k / (nx * ny);
    const long x0 = max(ix - 1, 0L), x1 = min(ix + 1, nx - 1);
    int j = 0;
    for (long dz = -1; dz <= 1; ++dz) {
        for (long dy = -1; dy <= 1; ++dy, ++j) {
            const long y = iy + dy, z = iz + dz;
            uint2 r = (uint2)(0, 0);
            if (y >= 0 && y < ny && z >= 0 && z < nz) {
                const long row = (z * ny + y) * nx;
                const uint a = lower_bound(keys, ncells, row + x0);
                const uint b = lower_bound(keys, ncells, row + x1 + 1);
                r = (uint2)(cell_start[a], cell_start[b]);
            }
            ranges[(size_t)c * 9 + j] = r;
        }
    }
}
