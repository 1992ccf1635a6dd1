/* quadric.h -- the weighted least-squares quadric of MLS2 in the PCA frame (mls2.cl), and
 * its error sums and covariance (UNCERTAINTY: mls2.cl's standard errors, moments.cl's
 * quadric noise for MLS0 and MLS1), shared so that both kernels fit the same quadric.
 * Needs MIN_COUNT; REF_NORMALS (0|1) says whether NX, NY, NZ orient v0 (0 when undefined:
 * the residuals and the covariance do not depend on v0's sign).
 */
#ifndef CLCURV_QUADRIC_H
#define CLCURV_QUADRIC_H
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"
#include "frame.h"
#include "solve6.h"

#ifndef REF_NORMALS
#define REF_NORMALS 0
#endif
/* QUADRIC_FULL: every moment from the fit's own walk, none from the PCA sums (which
 * PCA_ANCHOR keeps in a sheared frame: moments.cl with REFINE_L0) */
#ifndef QUADRIC_FULL
#define QUADRIC_FULL PCA_ANCHOR
#endif
#ifndef UNCERTAINTY
#define UNCERTAINTY 0
#endif
/* the error sums of one point beside its normal equations: sum w h^2 and, for weights that
 * are not 0 or 1, B = sum w^2 phi phi^T (packed as the normal matrix) */
typedef struct {
    REAL hh[VW];
#if DENSITY || GAUSSIAN
    REAL B[21][VW];
#endif
} mls2_err_t;

/* Lane k of the packed 6x6 systems: the identity, right-hand side 0. */
inline void identity_system(REAL M[21][VW], REAL b[6][VW], uint k)
{
    for (int e = 0; e < 21; ++e) M[e][k] = (REAL)(e == 0 || e == 2 || e == 5 || e == 9 || e == 14 || e == 20);
    for (int e = 0; e < 6; ++e) b[e][k] = 0;
}

/* Lane k of the error sums: those of the identity system (failed or unused lanes). */
inline void identity_errors(mls2_err_t *err, uint k)
{
    err->hh[k] = 0;
#if DENSITY || GAUSSIAN
    for (int e = 0; e < 21; ++e)
        err->B[e][k] = (REAL)(e == 0 || e == 2 || e == 5 || e == 9 || e == 14 || e == 20);
#endif
}

/* Frame and normal equations of the sorted point g (lane k), once its PCA is known: v0
 * oriented by the reference normal, the tangent frame, Q - p, and sum w phi phi^T (packed)
 * and sum w h phi for phi = (1, x, y, x^2, xy, y^2). Returns the status. */
inline uchar mls2_system(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                         __global const REAL *NX, __global const REAL *NY,
                         __global const REAL *NZ, __global const REAL *W,
                         __global const uint2 *ranges, uint cell, uint g, const pca_batch_t *pb,
                         uint k, REAL r, REAL ih2, REAL2 ball, REAL fr[12][VW],
                         REAL M[21][VW], REAL b[6][VW], mls2_err_t *err)
{
    const REAL3 p = (REAL3)(X[g], Y[g], Z[g]);
    const REAL ir = (REAL)1 / r;
    REAL3 v0 = (REAL3)(pb->v0x[k], pb->v0y[k], pb->v0z[k]);
    const REAL3 mu = (REAL3)(pb->mux[k], pb->muy[k], pb->muz[k]);
    uchar st = pca_status(pb, k, MIN_COUNT);
    if (REF_NORMALS) {
        const REAL s = dot(v0, (REAL3)(NX[g], NY[g], NZ[g]));
        if (!(s != 0)) st = st == ST_OK ? ST_DEGENERATE : st;   /* also NaN */
        if (s < 0) v0 = -v0;
    }
    REAL3 t1, t2;
    tangent_frame(v0, &t1, &t2);
    const REAL3 qo = dot(mu, v0) * v0;             /* Q - p */
    const REAL frame[12] = {v0.x, v0.y, v0.z, t1.x, t1.y, t1.z, t2.x, t2.y, t2.z,
                            qo.x, qo.y, qo.z};
    for (int e = 0; e < 12; ++e) fr[e][k] = frame[e];
    if (st != ST_OK) {                              /* identity system for failed points */
        identity_system(M, b, k);
#if UNCERTAINTY
        identity_errors(err, k);
#endif
        return st;
    }
    /* x = <q - Q, t1> / r = <d, t1> / r (Q - p is along v0), likewise y;
       h = <d, v0> - <Q - p, v0>. The moments of degree <= 2 follow from the PCA sums
       (W = sum w, mu, centred covariance C; S = W (C + mu mu^T) = sum w d d^T):
         sum w = W, sum w x = W <mu, t1> / r, sum w x y = t1^T S t2 / r^2 (likewise xx, yy),
         sum w h = 0, sum w h x = W v0^T C t1 / r (likewise y);
       only those of degree 3 and 4 need the second pass. */
    const REAL cv0 = dot(qo, v0);
    const REAL3 u1 = t1 * ir, u2 = t2 * ir;
    REALV s30 = 0, s21 = 0, s12 = 0, s03 = 0, s40 = 0, s31 = 0, s22 = 0, s13 = 0, s04 = 0;
    REALV hxx = 0, hxy = 0, hyy = 0;
#if QUADRIC_FULL
    REALV f00 = 0, f10 = 0, f01 = 0, f20 = 0, f11 = 0, f02 = 0, h0 = 0, hx = 0, hy = 0;
#endif
#if UNCERTAINTY
    REALV hh = 0;
#if DENSITY || GAUSSIAN
    /* sum w^2 x^i y^j, i + j <= 4 */
    REALV q00 = 0, q10 = 0, q01 = 0, q20 = 0, q11 = 0, q02 = 0, q30 = 0, q21 = 0, q12 = 0;
    REALV q03 = 0, q40 = 0, q31 = 0, q22 = 0, q13 = 0, q04 = 0;
#endif
#endif
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);
        /* zeroed outside the ball (weights.h): every term below is then 0 there */
        const REALV x = select((REALV)0, dx * u1.x + dy * u1.y + dz * u1.z, m);
        const REALV y = select((REALV)0, dx * u2.x + dy * u2.y + dz * u2.z, m);
        const REALV h = select((REALV)0, dx * v0.x + dy * v0.y + dz * v0.z - cv0, m);
        const REALV xx = x * x, xy = x * y, yy = y * y;
#if DENSITY || GAUSSIAN
        const REALV wxx = w * xx, wxy = w * xy, wyy = w * yy;
#else
        (void)w;                                    /* uniform: the terms themselves */
        const REALV wxx = xx, wxy = xy, wyy = yy;
#endif
        /* a * b + c, fused where the device has an FMA (pca.h: PoCL's mad is not) */
        s30 += wxx * x; s21 += wxx * y; s12 += wxy * y;
        s03 += wyy * y; s40 += wxx * xx; s31 += wxx * xy;
        s22 += wxx * yy; s13 += wxy * yy; s04 += wyy * yy;
        hxx += wxx * h; hxy += wxy * h; hyy += wyy * h;
#if QUADRIC_FULL
#if DENSITY || GAUSSIAN
        const REALV wv = w;
#else
        const REALV wv = select((REALV)0, (REALV)1, m);
#endif
        f00 += wv; f10 += wv * x; f01 += wv * y; f20 += wxx; f11 += wxy; f02 += wyy;
        h0 += wv * h; hx += wv * x * h; hy += wv * y * h;
#endif
#if UNCERTAINTY
#if DENSITY || GAUSSIAN
        hh += w * h * h;
        {
            const REALV w2 = w * w, w2xx = w2 * xx, w2xy = w2 * xy, w2yy = w2 * yy;
            q00 += w2; q10 += w2 * x; q01 += w2 * y;
            q20 += w2xx; q11 += w2xy; q02 += w2yy;
            q30 += w2xx * x; q21 += w2xx * y; q12 += w2xy * y; q03 += w2yy * y;
            q40 += w2xx * xx; q31 += w2xx * xy; q22 += w2xx * yy; q13 += w2xy * yy;
            q04 += w2yy * yy;
        }
#else
        hh += h * h;
#endif
#endif
    NEIGHBOR_CHUNKS_END
#if QUADRIC_FULL
    const REAL S00 = hsum(f00), S10 = hsum(f10), S01 = hsum(f01);
    const REAL S20 = hsum(f20), S11 = hsum(f11), S02 = hsum(f02);
    const REAL B0 = hsum(h0), B1 = hsum(hx), B2 = hsum(hy);
#else
    const REAL sw = (REAL)1 / pb->iw[k];
    const REAL c0 = pb->c[0][k], c1 = pb->c[1][k], c2 = pb->c[2][k];
    const REAL c3 = pb->c[3][k], c4 = pb->c[4][k], c5 = pb->c[5][k];
    const REAL3 C1 = (REAL3)(c0 * t1.x + c1 * t1.y + c2 * t1.z, c1 * t1.x + c3 * t1.y + c4 * t1.z,
                             c2 * t1.x + c4 * t1.y + c5 * t1.z);
    const REAL3 C2 = (REAL3)(c0 * t2.x + c1 * t2.y + c2 * t2.z, c1 * t2.x + c3 * t2.y + c4 * t2.z,
                             c2 * t2.x + c4 * t2.y + c5 * t2.z);
    const REAL m1 = dot(mu, t1), m2 = dot(mu, t2), ir2 = ir * ir;
    const REAL S00 = sw, S10 = sw * m1 * ir, S01 = sw * m2 * ir;
    const REAL S20 = sw * (dot(t1, C1) + m1 * m1) * ir2;
    const REAL S11 = sw * (dot(t2, C1) + m1 * m2) * ir2;
    const REAL S02 = sw * (dot(t2, C2) + m2 * m2) * ir2;
    const REAL B0 = 0, B1 = sw * dot(v0, C1) * ir, B2 = sw * dot(v0, C2) * ir;
#endif
    const REAL S30 = hsum(s30), S21 = hsum(s21), S12 = hsum(s12), S03 = hsum(s03);
    const REAL S40 = hsum(s40), S31 = hsum(s31), S22 = hsum(s22), S13 = hsum(s13);
    const REAL S04 = hsum(s04);
    const REAL packed[21] = {S00,
                             S10, S20,
                             S01, S11, S02,
                             S20, S30, S21, S40,
                             S11, S21, S12, S31, S22,
                             S02, S12, S03, S22, S13, S04};
    for (int e = 0; e < 21; ++e) M[e][k] = packed[e];
    const REAL rhs[6] = {B0, B1, B2, hsum(hxx), hsum(hxy), hsum(hyy)};
    for (int e = 0; e < 6; ++e) b[e][k] = rhs[e];
#if UNCERTAINTY
    err->hh[k] = hsum(hh);
#if DENSITY || GAUSSIAN
    {
        const REAL Q20 = hsum(q20), Q11 = hsum(q11), Q02 = hsum(q02);
        const REAL Q30 = hsum(q30), Q21 = hsum(q21), Q12 = hsum(q12), Q03 = hsum(q03);
        const REAL Q22 = hsum(q22);
        const REAL bp[21] = {hsum(q00),
                             hsum(q10), Q20,
                             hsum(q01), Q11, Q02,
                             Q20, Q30, Q21, hsum(q40),
                             Q11, Q21, Q12, hsum(q31), Q22,
                             Q02, Q12, Q03, Q22, hsum(q13), hsum(q04)};
        for (int e = 0; e < 21; ++e) err->B[e][k] = bp[e];
    }
#endif
#endif
    return st;
}

/* The quadric's residual variance and coefficient covariance in the VW lanes, from the
 * fitted coefficients a, the factorised normal matrix (m, s, d, ok: factor6_v), its
 * right-hand side b, the error sums err and the neighbour counts (clcurv/reference/
 * uncertainty.py):
 *   RSS = sum w h^2 - a . b (floored at 0), nu = n - 6 (uniform ball: every weight 0 or 1)
 *   or sum w - tr(A^-1 B), sigma^2 = RSS / nu, C = A^-1 B A^-1 (A^-1 for the uniform ball),
 *   so that Cov(a) = sigma^2 C. Returns the lanes with nu > 0 and a solved system; sigma2
 *   is 0 in the others. */
inline IREALV quadric_cov_v(const REALV a[6], const REALV m[21], const REALV s[6],
                            const REALV d[6], const IREALV ok, const REALV b[6],
                            const mls2_err_t *err, const REALV count, REALV C[6][6],
                            REALV *sigma2)
{
    REALV Ai[6][6];                                  /* A^-1, column by column */
    for (int c = 0; c < 6; ++c) {
        REALV u[6], x[6];
        for (int i = 0; i < 6; ++i) u[i] = (REALV)(i == c ? 1 : 0);
        subst6_v(m, s, d, ok, u, x);
        for (int i = 0; i < 6; ++i) Ai[i][c] = x[i];
    }
    REALV rss = VLOADV(0, err->hh);
    for (int i = 0; i < 6; ++i) rss -= a[i] * b[i];
    rss = fmax(rss, (REALV)0);
#if DENSITY || GAUSSIAN
    REALV Bf[6][6], T[6][6];
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j <= i; ++j)
            Bf[i][j] = Bf[j][i] = VLOADV(0, err->B[S6(i, j)]);
    REALV tr = 0;
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) tr += Ai[i][j] * Bf[j][i];
    const REALV nu = (REAL)1 / (s[0] * s[0]) - tr;  /* sum w = A00 = 1 / s0^2 (factor6_v) */
    for (int i = 0; i < 6; ++i)                      /* T = B A^-1 */
        for (int j = 0; j < 6; ++j) {
            REALV t = 0;
            for (int k = 0; k < 6; ++k) t += Bf[i][k] * Ai[k][j];
            T[i][j] = t;
        }
    for (int i = 0; i < 6; ++i)                      /* C = A^-1 B A^-1 */
        for (int j = 0; j < 6; ++j) {
            REALV t = 0;
            for (int k = 0; k < 6; ++k) t += Ai[i][k] * T[k][j];
            C[i][j] = t;
        }
#else
    const REALV nu = count - 6;
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) C[i][j] = Ai[i][j];
#endif
    const IREALV dof = isgreater(nu, (REALV)0) & ok;
    *sigma2 = select((REALV)0, rss / select((REALV)1, nu, dof), dof);
    return dof;
}
#endif
