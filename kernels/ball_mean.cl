/* ball_mean.cl -- the mean of a per-point field over each point's ball
 * N_r(p) = {q : |q - p| < r} (p included), optionally weighted (clcurv/ops/pooling.py).
 *
 * One work-item per sorted point, the fixed-order neighbour walk of neighbors.h (the same
 * as density.cl's), so the ball is the operators' ball to the last bit and the sums are
 * bit-reproducible. A neighbour q contributes w_q v_q to the numerator and w_q to the
 * denominator where v_q (and, WEIGHTED, w_q) is finite: a NaN value is skipped, it does not
 * poison the mean. Where nothing contributes (or the weights sum to 0) the mean is NaN.
 *
 * Build options: WEIGHTED=0|1 (W read, or every weight 1), ROW_PRUNE (neighbors.h).
 * V and W: sorted order, padded with PAD entries (read, masked, by the last chunk).
 */
#include "common.h"
#include "neighbors.h"

#ifndef WEIGHTED
#error "ball_mean.cl needs -D WEIGHTED=0|1 (clcurv/ops/pooling.py)"
#endif

/* For the sorted points g of [first, stop) (a chunk, clcurv/grid/cloud.py:Plan), at g - first:
 * mean = sum w v / sum w over the contributing q of g's ball, wsum = sum w (the count of
 * finite values when not WEIGHTED). W is not read unless WEIGHTED. */
__kernel void ball_mean(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                        __global const uint *cell_of, __global const uint2 *ranges,
                        const uint n, const uint first, const uint stop, const REAL2 ball,
                        __global const REAL *V, __global const REAL *W,
                        __global REAL *mean, __global REAL *wsum)
{
    const uint g = first + (uint)get_global_id(0);
    if (g >= stop) return;
    const uint co = cell_of[g];
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
    REALV s = 0, sw = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(XA, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV v = VLOADV(0, V + i);
#if WEIGHTED
        const REALV w = VLOADV(0, W + i);
        const IREALV use = m & isfinite(v) & isfinite(w);
        s += select((REALV)0, w * v, use);
        sw += select((REALV)0, w, use);
#else
        const IREALV use = m & isfinite(v);
        s += select((REALV)0, v, use);
        sw += select((REALV)0, (REALV)1, use);
#endif
    NEIGHBOR_CHUNKS_END
    const REAL t = hsum(sw);
    mean[g - first] = t > 0 ? hsum(s) / t : (REAL)NAN;
    wsum[g - first] = t;
}
