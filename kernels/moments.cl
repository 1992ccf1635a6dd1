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
#include "quadric.h"

#if !defined(REFINE_L0) || !defined(MIN_COUNT) || !defined(COL_NORMALS) \
    || !defined(COL_EIGENVALUES) || !defined(COL_VARIATION) || !defined(COL_SHIFT) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "moments.cl needs REFINE_L0, MIN_COUNT and its record columns (clcurv/ops/registry.py)"
#endif
/* NOISE_WALK (0|1, default 1): the quadric walk for the point's own noise (COL_SIGMA,
 * MLS0/MLS1's SE(H)); 0 leaves COL_SIGMA NaN and walks only for density weights, whose
 * normal SE needs its sums of w^2 (variation and the covariance operators' normals) */
#ifndef NOISE_WALK
#define NOISE_WALK 1
#endif
#if UNCERTAINTY && (!defined(COL_NORMAL_SE) || !defined(COL_ROUGHNESS) || !defined(COL_SIGMA) \
    || !defined(COL_OWN) || !defined(COL_OTHERS) || !defined(ECOL_COUNT) || !defined(ECOL_STATUS))
#error "moments.cl with UNCERTAINTY needs its error record's columns (clcurv/ops/registry.py)"
#endif

#if UNCERTAINTY
/* sigma_hat^2 of MLS2's quadric on each lane's ball (NaN where it has no residual degrees
 * of freedom or its system is singular), the frames (fr) and the error sums (err). */
inline void moments_quadric(__global const REAL *X, __global const REAL *Y,
                            __global const REAL *Z, __global const REAL *W,
                            __global const uint *cell_of, __global const uint2 *ranges,
                            const uint n, const REAL2 ball, const REAL r, const uint g0,
                            const uint kn, const pca_batch_t *pb, REAL fr[12][VW],
                            mls2_err_t *err, REAL sig2[VW])
{
    REAL Ml[21][VW], bl[6][VW];
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            const uint co = cell_of[g];
            mls2_system(x_rows(X, co, n), Y, Z, X, Y, Z, W, ranges, co & CELL_MASK, g, pb, k, r,
                        (REAL)0, POINT_BALL(W, g, ball), fr, Ml, bl, err);
        } else {
            identity_system(Ml, bl, k);
            identity_errors(err, k);
            for (int e = 0; e < 12; ++e) fr[e][k] = (REAL)(e == 0 || e == 4 || e == 8);
        }
    }
    REALV Mv[21], bv[6], xv[6], sv[6], dv[6], C[6][6], s2;
    REAL cnt[VW];
    for (uint k = 0; k < VW; ++k) cnt[k] = (REAL)pb->count[k];
    for (int e = 0; e < 21; ++e) Mv[e] = VLOADV(0, Ml[e]);
    for (int e = 0; e < 6; ++e) bv[e] = VLOADV(0, bl[e]);
    const IREALV ok = solve6_v(Mv, sv, dv, bv, xv);
    const IREALV dof = quadric_cov_v(xv, Mv, sv, dv, ok, bv, err, VLOADV(0, cnt), C, &s2);
    VSTOREV(select((REALV)(NAN), s2, dof), 0, sig2);
}
#endif

/* Per point: count, PCA normal v0 (unoriented), ascending eigenvalues of the weighted
 * covariance, surface variation l0/(l0+l1+l2), barycenter shift o - p, status.
 *
 * One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the
 * neighbour sums of the VW points are computed one after the other, then their VW
 * covariances are decomposed at once by eig3_sym_v (one per vector lane: a scalar
 * eig3_sym per point cost more than all the neighbour loops together), then the lambda0
 * refinement and the stores run per point again. */
__kernel void moments(OPERATOR_ARGS, __global REAL *out2)
{
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);       /* points of this work-item */

    /* 1-2. neighbour sums point by point, VW eigen decompositions at once */
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, CN, cell_of, ranges, n, g0, kn, ball, (REAL)0, &pb);
#if UNCERTAINTY
    REAL fr[12][VW], sig2[VW];
    mls2_err_t err;
#if NOISE_WALK || DENSITY
    moments_quadric(X, Y, Z, W, cell_of, ranges, n, ball, par.x, g0, kn, &pb, fr, &err, sig2);
#else
    for (uint k = 0; k < VW; ++k) sig2[k] = NAN;    /* no quadric walk: no point noise */
#endif
#endif

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
#if UNCERTAINTY
        /* the error record (clcurv/reference/uncertainty.py: pca_uncertainty,
           mls1_uncertainty): W = sum w, W2 = sum w^2, n_eff = W^2 / W2, the plane's
           s^2 = l0 n_eff / (n_eff - 3), the normal's Var(theta_j) = s^2 S_j / (W^2
           (l_j - l0)^2) with S_j = sum w^2 <q - o, e_j>^2 (W l_j for 0/1 weights), the
           point's own weight w_p */
        REAL16 er = (REAL16)(NAN);
        if (st == ST_OK) {
            const REAL sw = (REAL)1 / pb.iw[k];
#if DENSITY
            const REAL sw2 = err.B[0][k], wp = W[g];
            /* S_j from the tangent-frame sums of w^2 (quadric.h, coordinates / r), centred
               on o: e_j has no v0 component */
            const REAL3 t1 = (REAL3)(fr[3][k], fr[4][k], fr[5][k]);
            const REAL3 t2 = (REAL3)(fr[6][k], fr[7][k], fr[8][k]);
            const REAL r = par.x;
            const REAL mx = dot(mu, t1) / r, my = dot(mu, t2) / r;
            const REAL q0 = err.B[0][k], qx = err.B[1][k], qy = err.B[3][k];
            const REAL sxx = err.B[2][k] - 2 * mx * qx + mx * mx * q0;
            const REAL sxy = err.B[4][k] - mx * qy - my * qx + mx * my * q0;
            const REAL syy = err.B[5][k] - 2 * my * qy + my * my * q0;
            const REAL3 e2 = (REAL3)(pb.v2x[k], pb.v2y[k], pb.v2z[k]);
            const REAL3 e1 = cross(v0, e2);
            const REAL a1 = dot(e1, t1), b1 = dot(e1, t2), a2 = dot(e2, t1), b2 = dot(e2, t2);
            const REAL S1 = (a1 * a1 * sxx + 2 * a1 * b1 * sxy + b1 * b1 * syy) * r * r;
            const REAL S2 = (a2 * a2 * sxx + 2 * a2 * b2 * sxy + b2 * b2 * syy) * r * r;
#else
            const REAL sw2 = sw, wp = 1;
            const REAL S1 = sw * lam.y, S2 = sw * lam.z;
#endif
            const REAL neff = sw * sw / sw2;
            const REAL s2 = neff > 3 ? lam.x * neff / (neff - 3) : NAN;
            const REAL d1 = lam.y - lam.x, d2 = lam.z - lam.x;
            const REAL nv = s2 / (sw * sw) * (S1 / (d1 * d1) + S2 / (d2 * d2));
            er.COL_NORMAL_SE = sqrt(nv);
            er.COL_ROUGHNESS = sqrt(s2);
            er.COL_SIGMA = sqrt(sig2[k]);
            er.COL_OWN = (1 - wp / sw) * (1 - wp / sw);
            er.COL_OTHERS = (sw2 - wp * wp) / (sw * sw);
        }
        er.ECOL_COUNT = UINT_AS_REAL(c);
        er.ECOL_STATUS = (REAL)st;
        REC_STORE(er, REC_INDEX(g), out2);
#endif
    }
}
