/* moments.cl -- the PCA moments of the ball N_r(p) around each point (surface variation,
 * MLS0, MLS1 and clcurv.normals).
 *
 * One work-item per VW consecutive sorted points (see there). Offsets are taken relative to
 * the query point p, so the sums are small numbers and large coordinates do not matter.
 * Outputs are one record per point at its input index (common.h).
 *
 * Build options: DENSITY (0|1) weights w(q) = 1/#N_r(q) read from W;
 *                REFINE_L0 (0|1) an accurate lambda0 = sum w <q - o, v0>^2 / sum w (float32
 *                one-pass moments lose ~2 digits of it on smooth surfaces): from the
 *                sums of the same walk taken in the anchor's frame (pca.h, PCA_ANCHOR; CN
 *                from anchor.cl), or a second pass where the anchor is missing or too far;
 *                MIN_COUNT and the record columns COL_NORMALS (3), COL_EIGENVALUES (3),
 *                COL_VARIATION, COL_SHIFT (3), COL_COUNT, COL_STATUS (clcurv/ops/registry.py).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"

#if !defined(REFINE_L0) || !defined(MIN_COUNT) || !defined(COL_NORMALS) \
    || !defined(COL_EIGENVALUES) || !defined(COL_VARIATION) || !defined(COL_SHIFT) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "moments.cl needs REFINE_L0, MIN_COUNT and its record columns (clcurv/ops/registry.py)"
#endif

/* Per point: count, PCA normal v0 (unoriented), ascending eigenvalues of the weighted
 * covariance, surface variation l0/(l0+l1+l2), barycenter shift o - p, status.
 *
 * One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the
 * neighbour sums of the VW points are computed one after the other, then their VW
 * covariances are decomposed at once by eig3_sym_v (one per vector lane: a scalar
 * eig3_sym per point cost more than all the neighbour loops together), then the lambda0
 * refinement and the stores run per point again. */
__kernel void moments(OPERATOR_ARGS)
{
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);       /* points of this work-item */

    /* 1-2. neighbour sums point by point, VW eigen decompositions at once */
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, CN, cell_of, ranges, n, g0, kn, ball, (REAL)0, &pb);

    /* 3. per point: status, lambda0 refinement, stores */
    for (uint k = 0; k < kn; ++k) {
        const uint g = g0 + k;
        const uint c = pb.count[k];
        REAL3 lam = (REAL3)(pb.l0[k], pb.l1[k], pb.l2[k]);
        const REAL3 v0 = (REAL3)(pb.v0x[k], pb.v0y[k], pb.v0z[k]);
        const REAL3 mu = (REAL3)(pb.mux[k], pb.muy[k], pb.muz[k]);
        const uchar st = pca_status(&pb, k, MIN_COUNT);
#if REFINE_L0
        lam.x = pb.l0a[k];                  /* anchored (pca.h), else the second pass */
        if (st == ST_OK && isnan(lam.x)) {
            const uint co = cell_of[g];
            __global const REAL *XA = x_rows(X, co, n);
            lam.x = pca_refine_l0(XA, Y, Z, W, ranges, co & CELL_MASK,
                                  (REAL3)(XA[g], Y[g], Z[g]), POINT_BALL(W, g, ball), v0,
                                  mu, pb.iw[k]);
        }
#endif
        /* record: normal | eigenvalues (ascending) | variation | shift o - p | count | status */
        REAL16 rec = (REAL16)(NAN);
        if (st == ST_OK) {
            rec.COL_NORMALS = v0;
            rec.COL_EIGENVALUES = lam;
            rec.COL_VARIATION = lam.x / (lam.x + lam.y + lam.z);
            rec.COL_SHIFT = mu;
        }
        REC_COUNT_STATUS(rec, c, st);
        REC_STORE(rec, REC_INDEX(g), out);
    }
}
