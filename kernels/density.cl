/* density.cl -- #N_r(p) for every sorted point and the density weight 1 / #N_r(p) that
 * the operators read as W when built with DENSITY=1 (weights.h).
 *
 * One work-item per sorted point; same fixed-order neighbour walk as the operators, so the
 * count equals the operators' count column.
 */
#include "common.h"
#include "neighbors.h"

/* #N_r(p) for every sorted point, and the density weight 1 / #N_r(p). */
__kernel void count_neighbors(__global const REAL *X, __global const REAL *Y,
                              __global const REAL *Z, __global const uint *cell_of,
                              __global const uint2 *ranges, const uint n, const REAL2 ball,
                              __global uint *count, __global REAL *weight)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const uint co = cell_of[g];
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
    REALV cnt = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(XA, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        cnt += select((REALV)0, (REALV)1, m);
    NEIGHBOR_CHUNKS_END
    const uint c = (uint)hsum(cnt);
    count[g] = c;
    weight[g] = (REAL)1 / (REAL)c;
}
