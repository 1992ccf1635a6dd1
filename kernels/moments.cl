/* moments.cl -- neighbour counts and the PCA moments of the ball N_r(p) around each point.
 *
 * count_neighbors: one work-item per sorted point; moments: one work-item per VW
 * consecutive sorted points (see there). Offsets are taken relative to the query point p,
 * so the sums are small numbers and large coordinates do not matter. Outputs are one
 * record per point at its input index (common.h).
 *
 * Build options: DENSITY (0|1) weights w(q) = 1/#N_r(q) read from W;
 *                REFINE_L0 (0|1) second pass giving lambda0 = sum w <q - o, v0>^2 / sum w
 *                directly (float32 otherwise loses ~2 digits of lambda0 on smooth surfaces).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"

#ifndef REFINE_L0
#define REFINE_L0 1
#endif

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

/* Per point: count, PCA normal v0 (unoriented), ascending eigenvalues of the weighted
 * covariance, surface variation l0/(l0+l1+l2), barycenter shift o - p, status.
 *
 * One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the
 * neighbour sums of the VW points are computed one after the other, then their VW
 * covariances are decomposed at once by eig3_sym_v (one per vector lane: a scalar
 * eig3_sym per point cost more than all the neighbour loops together), then the lambda0
 * refinement and the stores run per point again. */
__kernel void moments(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const uint *cell_of,
                      __global const uint2 *ranges, __global const uint *order,
                      const uint n, const REAL2 ball,
                      __global REAL *out)
{
    const uint g0 = get_global_id(0) * VW;
    if (g0 >= n) return;
    const uint kn = min((uint)VW, n - g0);       /* points of this work-item */

    /* 1-2. neighbour sums point by point, VW eigen decompositions at once */
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, cell_of, ranges, n, g0, kn, ball, (REAL)0, &pb);

    /* 3. per point: status, lambda0 refinement, stores */
    for (uint k = 0; k < kn; ++k) {
        const uint g = g0 + k;
        const uint c = pb.count[k];
        REAL3 lam = (REAL3)(pb.l0[k], pb.l1[k], pb.l2[k]);
        const REAL3 v0 = (REAL3)(pb.v0x[k], pb.v0y[k], pb.v0z[k]);
        const REAL3 mu = (REAL3)(pb.mux[k], pb.muy[k], pb.muz[k]);
        const uchar st = pca_status(&pb, k, 3);
#if REFINE_L0
        if (st == ST_OK) {
            const uint co = cell_of[g];
            __global const REAL *XA = x_rows(X, co, n);
            const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
            /* h = <q - o, v0> = <q - p, v0> - <o - p, v0>: both terms are heights above the
               tangent plane, small on a smooth surface, so the split costs no accuracy */
            const REAL h0 = dot(mu, v0);
            REALV s0 = 0;
            REALV dx, dy, dz;
            NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
                const IREALV m = chunk_offsets(XA, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
                const REALV h = dx * v0.x + dy * v0.y + dz * v0.z - h0;
#if DENSITY
                s0 += chunk_weights(W, i, dx, dy, dz, m, (REAL)0) * h * h;
#else
                const REALV hm = select((REALV)0, h, m);
                s0 += hm * hm;
#endif
            NEIGHBOR_CHUNKS_END
            lam.x = hsum(s0) * pb.iw[k];
        }
#endif
        /* record: normal xyz | eigenvalues (ascending) | variation | shift xyz | count | status */
        REAL16 rec = (REAL16)(NAN);
        if (st == ST_OK) {
            rec.s012 = v0;
            rec.s345 = lam;
            rec.s6 = lam.x / (lam.x + lam.y + lam.z);
            rec.s789 = mu;
        }
        rec.sa = UINT_AS_REAL(c);
        rec.sb = (REAL)st;
        STORE_RECORD(rec, order[g], out);
    }
}
