/* gather.cl -- between the input order and the grid's sorted order (order[s]: the input
 * index of sorted point s):
 *   gather_sorted  per-point rows in the input order (user normals) to padded SoA columns
 *                  in the sorted order, the layout the operator kernels read;
 *   to_input, to_sorted  one column from one order to the other (clcurv/ops/knn_radius.py:
 *                  the k-th distances of one binning as the next binning's known ones). */
#include "common.h"

/* Sorted SoA columns (padded: entries n .. n + PAD - 1 are 0) of input-order rows: V holds
 * the rows of the input indices [lo, hi) (all of them, or one chunk staged by the host,
 * clcurv/grid/cloud.py:upload_sorted); sorted points whose row is elsewhere are left as they are. */
__kernel void gather_sorted(__global const REAL *V, __global const uint *order, const uint n,
                            const uint lo, const uint hi,
                            __global REAL *OX, __global REAL *OY, __global REAL *OZ)
{
    const uint s = get_global_id(0);
    if (s >= n + PAD) return;
    const uint i = s < n ? order[s] : hi;
    if (s < n && (i < lo || i >= hi)) return;
    const REAL3 v = s < n ? vload3(i - lo, V) : (REAL3)(0);
    OX[s] = v.x; OY[s] = v.y; OZ[s] = v.z;
}

/* dst[order[s]] = src[s], s < n: a sorted column to the input order. */
__kernel void to_input(__global const REAL *src, __global const uint *order, const uint n,
                       __global REAL *dst)
{
    const uint s = get_global_id(0);
    if (s < n) dst[order[s]] = src[s];
}

/* dst[s] = src[order[s]], s < n, and 0 in the PAD entries after: an input-order column to
 * the sorted order, padded. */
__kernel void to_sorted(__global const REAL *src, __global const uint *order, const uint n,
                        __global REAL *dst)
{
    const uint s = get_global_id(0);
    if (s < n) dst[s] = src[order[s]];
    else if (s < n + PAD) dst[s] = 0;
}
