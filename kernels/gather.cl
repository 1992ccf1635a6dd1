/* gather.cl -- gather_sorted: per-point rows in the input order (user normals) to padded
 * SoA columns in the grid's sorted order, the layout the operator kernels read. */
#include "common.h"

/* Sorted SoA columns (padded: entries n .. n + PAD - 1 are 0) of input-order rows: V holds
 * the rows of the input indices [lo, hi) (all of them, or one chunk staged by the host,
 * clcurv/cloud.py:upload_sorted); sorted points whose row is elsewhere are left as they are. */
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
