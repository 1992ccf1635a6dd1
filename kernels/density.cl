/* density.cl -- the density weight 1 / #N_r(p) of every sorted point, which the operators
 * read as W when built with DENSITY=1 (weights.h).
 *
 * One work-item per sorted point; same fixed-order neighbour walk as the operators, so the
 * count equals the operators' count column.
 */
#include "common.h"
#include "neighbors.h"

/* The density weight 1 / #N_r(p) of every sorted point (weight: n + PAD, padding left as
 * it is: the lanes that read it are masked). */
__kernel void count_neighbors(__global const REAL *X, __global const REAL *Y,
                              __global const REAL *Z, __global const uint *cell_of,
                              __global const uint2 *ranges, const uint n, const REAL2 ball,
                              __global REAL *weight)
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
    weight[g] = (REAL)1 / hsum(cnt);
}
