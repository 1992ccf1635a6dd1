/* mls2.cl -- MLS2 (Digne & Morel operator 7): weighted least-squares quadric in the PCA frame.
 *
 * Per point p: weighted PCA of the ball (pca.h) gives o and v0, oriented to agree with the
 * reference normal of p when REF_NORMALS is given (user or oriented PCA normals); Q is the
 * projection of p on the regression plane, (t1, t2, v0) the frame at Q. The heights
 * h = <q - Q, v0> are fitted by g(x, y) = a0 + a1 x + a2 y + a3 x^2 + a4 xy + a5 y^2 with
 * (x, y) = (<q - Q, t1>, <q - Q, t2>) / r (scaled for conditioning), a 6x6 LDL^T solve.
 * The projection is Q + a0 v0. Principal curvatures: eigenvalues of the shape operator
 * I^-1 II of the graph at the origin, negated to clcurv's convention (outward normal, a
 * sphere is positive), k1 >= k2; directions mapped to 3D through (1, 0, gx), (0, 1, gy).
 *
 * Outputs (one record per point, input order): count, status, shift = projection - p, k1 k2,
 * dir1, dir2 (= normal x dir1), the fitted unit normal.
 * Build options: REF_NORMALS (0|1: NX, NY, NZ orient v0), DENSITY, GAUSSIAN (par.y = 1 / h^2),
 * MIN_COUNT and the record columns COL_SHIFT (3), COL_K1, COL_K2, COL_DIR1 (3), COL_DIR2 (3),
 * COL_NORMALS (3), COL_COUNT, COL_STATUS (clcurv/ops/registry.py).
 * UNCERTAINTY (0|1): a second record per point in out2 (the error record, columns
 * COL_MEAN_SE, COL_GAUSSIAN_SE, COL_K1_SE, COL_K2_SE, COL_NORMAL_SE, COL_ROUGHNESS, and
 * ECOL_COUNT, ECOL_STATUS): the standard errors of the curvatures and of the fitted normal,
 * and the roughness, from the same walk (mls2_errors_v; the formulas are those of
 * clcurv/reference/uncertainty.py, which documents the model).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"
#include "frame.h"
#include "solve6.h"

#if !defined(REF_NORMALS) || !defined(MIN_COUNT) || !defined(COL_SHIFT) || !defined(COL_K1) \
    || !defined(COL_K2) || !defined(COL_DIR1) || !defined(COL_DIR2) || !defined(COL_NORMALS) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "mls2.cl needs REF_NORMALS, MIN_COUNT and its record columns (clcurv/ops/registry.py)"
#endif
#ifndef UNCERTAINTY
#define UNCERTAINTY 0
#endif
#if UNCERTAINTY && (!defined(COL_MEAN_SE) || !defined(COL_GAUSSIAN_SE) || !defined(COL_K1_SE) \
    || !defined(COL_K2_SE) || !defined(COL_NORMAL_SE) || !defined(COL_ROUGHNESS) \
    || !defined(ECOL_COUNT) || !defined(ECOL_STATUS))
#error "mls2.cl with UNCERTAINTY needs its error record's columns (clcurv/ops/registry.py)"
#endif
/* the error sums of one point beside its normal equations: sum w h^2 and, for weights that
 * are not 0 or 1, B = sum w^2 phi phi^T (packed as the normal matrix) */
typedef struct {
    REAL hh[VW];
#if DENSITY || GAUSSIAN
    REAL B[21][VW];
#endif
} mls2_err_t;

/* Unit eigenvectors (ex, ey) (in the parameter plane) of the VW 2x2 matrices s for their
 * eigenvalues lam; (1, 0) where the matrix is a multiple of the identity. */
inline void eigvec2_v(REALV s00, REALV s01, REALV s10, REALV s11, REALV lam, REALV *ex,
                      REALV *ey)
{
    const REALV ax = s01, ay = lam - s00, bx = lam - s11, by = s10;
    const REALV na = ax * ax + ay * ay, nb = bx * bx + by * by;
    const IREALV use_a = isgreaterequal(na, nb);
    const REALV nv = sqrt(fmax(na, nb));
    const IREALV ok = isgreater(nv, (REAL)1e-12 * (fabs(s00) + fabs(s11) + fabs(s01) + fabs(s10)))
                      & isgreater(nv, (REALV)0);
    const REALV inv = (REAL)1 / select((REALV)1, nv, ok);
    *ex = select((REALV)1, select(bx, ax, use_a) * inv, ok);
    *ey = select((REALV)0, select(by, ay, use_a) * inv, ok);
}

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
    const REAL rhs[6] = {0, sw * dot(v0, C1) * ir, sw * dot(v0, C2) * ir,
                         hsum(hxx), hsum(hxy), hsum(hyy)};
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

/* Curvatures, directions and normals of the VW lanes from the fitted coefficients a and
 * the frames fr (v0, t1, t2, Q - p), into o[14][VW]: shift xyz | k1 k2 | dir1 xyz |
 * dir2 xyz | normal xyz (the record's first 14 columns). */
inline void mls2_finish_v(const REALV a[6], REAL fr[12][VW], REAL r, REAL o[14][VW])
{
    const REALV v0x = VLOADV(0, fr[0]), v0y = VLOADV(0, fr[1]), v0z = VLOADV(0, fr[2]);
    const REALV t1x = VLOADV(0, fr[3]), t1y = VLOADV(0, fr[4]), t1z = VLOADV(0, fr[5]);
    const REALV t2x = VLOADV(0, fr[6]), t2y = VLOADV(0, fr[7]), t2z = VLOADV(0, fr[8]);
    const REAL ir = (REAL)1 / r;
    const REALV gx = a[1] * ir, gy = a[2] * ir;
    const REALV gxx = 2 * a[3] * (ir * ir), gxy = a[4] * (ir * ir), gyy = 2 * a[5] * (ir * ir);
    const REALV q = 1 + gx * gx + gy * gy, iq = (REAL)1 / q, wn = rsqrt(q);
    const REALV Lxx = gxx * wn, Lxy = gxy * wn, Lyy = gyy * wn;                 /* II */
    const REALV i00 = (1 + gy * gy) * iq, i01 = -gx * gy * iq, i11 = (1 + gx * gx) * iq;  /* I^-1 */
    const REALV S00 = i00 * Lxx + i01 * Lxy, S01 = i00 * Lxy + i01 * Lyy;
    const REALV S10 = i01 * Lxx + i11 * Lxy, S11 = i01 * Lxy + i11 * Lyy;
    const REALV hmean = (REAL)0.5 * (S00 + S11);
    /* the discriminant from differences: hmean^2 - det cancels at umbilics (k1 = k2) and
       left sqrt(eps) x H there in float32 */
    const REALV hd = (REAL)0.5 * (S00 - S11);
    const REALV disc = sqrt(fmax(hd * hd + S01 * S10, (REALV)0));
    const REALV lo = hmean - disc;                   /* -> k1 = -lo (the largest k) */
    REALV ex, ey;
    eigvec2_v(S00, S01, S10, S11, lo, &ex, &ey);
    /* fitted normal (v0 - gx t1 - gy t2) / |.| and dir1 ~ ex (t1 + gx v0) + ey (t2 + gy v0) */
    const REALV nx = (v0x - gx * t1x - gy * t2x) * wn;
    const REALV ny = (v0y - gx * t1y - gy * t2y) * wn;
    const REALV nz = (v0z - gx * t1z - gy * t2z) * wn;
    REALV dx = ex * (t1x + gx * v0x) + ey * (t2x + gy * v0x);
    REALV dy = ex * (t1y + gx * v0y) + ey * (t2y + gy * v0y);
    REALV dz = ex * (t1z + gx * v0z) + ey * (t2z + gy * v0z);
    const REALV id = rsqrt(dx * dx + dy * dy + dz * dz);
    dx *= id; dy *= id; dz *= id;
    const REALV out[14] = {VLOADV(0, fr[9]) + a[0] * v0x, VLOADV(0, fr[10]) + a[0] * v0y,
                           VLOADV(0, fr[11]) + a[0] * v0z, -lo, -(hmean + disc), dx, dy, dz,
                           ny * dz - nz * dy, nz * dx - nx * dz, nx * dy - ny * dx, nx, ny, nz};
    for (int e = 0; e < 14; ++e) VSTOREV(out[e], 0, o[e]);
}

#if UNCERTAINTY
/* sum_ij u_i P_ij v_j over the indices 1..5 of a symmetric 6x6 P (full, P[i][j]) */
inline REALV form5_v(const REALV u[5], REALV P[6][6], const REALV v[5])
{
    REALV t = 0;
    for (int i = 0; i < 5; ++i) {
        REALV row = 0;
        for (int j = 0; j < 5; ++j) row += P[i + 1][j + 1] * v[j];
        t += u[i] * row;
    }
    return t;
}

/* The error record's six values of the VW lanes, into e[6][VW]: SE(H), SE(K), SE(k1),
 * SE(k2), SE of the fitted normal's angle (radians) and the roughness sigma_hat (length),
 * from the fitted coefficients a (scaled coordinates, heights along v0), the factorised
 * normal matrix (m, s, d, ok: factor6_v), its right-hand side b, the error sums and the
 * neighbour counts (float). clcurv/reference/uncertainty.py (mls2_uncertainty,
 * curvature_jacobian) has the model and the formulas:
 *   RSS = sum w h^2 - a . b, nu = n - 6 (uniform ball) or sum w - tr(A^-1 B),
 *   sigma^2 = RSS / nu, Cov(a) = sigma^2 A^-1 B A^-1 (B = A for the uniform ball),
 *   SE(X)^2 = J_X Cov(a) J_X^T by the delta method, gradients included;
 *   k1,2 = H +- D, D = sqrt(H^2 - K) (dD = 0 where D = 0). NaN where nu <= 0. */
inline void mls2_errors_v(const REALV a[6], const REALV m[21], const REALV s[6],
                          const REALV d[6], const IREALV ok, const REALV b[6],
                          const mls2_err_t *err, const REALV count, REAL r, REALV e[6])
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
    REALV Bf[6][6], T[6][6], C[6][6];
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
    REALV (*C)[6] = Ai;
#endif
    const IREALV dof = isgreater(nu, (REALV)0);
    const REALV sigma2 = select((REALV)0, rss / select((REALV)1, nu, dof), dof);
    /* the curvatures from the coefficients, clcurv's signs (height along the outward v0) */
    const REAL ir = (REAL)1 / r, ir2 = ir * ir;
    const REALV p = a[1] * ir, q = a[2] * ir;
    const REALV L = 2 * a[3] * ir2, M = a[4] * ir2, N = 2 * a[5] * ir2;
    const REALV w = 1 + p * p + q * q, w3 = w * sqrt(w), iw3 = (REAL)1 / w3;
    const REALV H = -((1 + q * q) * L - 2 * p * q * M + (1 + p * p) * N) * (REAL)0.5 * iw3;
    const REALV K = (L * N - M * M) / (w * w);
    /* gradients with respect to (a10, a01, a20, a11, a02): d/d(p, q, L, M, N) times the
       chain factors (1/r, 1/r, 2/r^2, 1/r^2, 2/r^2) */
    const REALV jH[5] = {(-(p * N - q * M) * iw3 - 3 * p * H / w) * ir,
                         (-(q * L - p * M) * iw3 - 3 * q * H / w) * ir,
                         -(1 + q * q) * iw3 * ir2, p * q * iw3 * ir2,
                         -(1 + p * p) * iw3 * ir2};
    const REALV jK[5] = {-4 * p * K / w * ir, -4 * q * K / w * ir, 2 * N / (w * w) * ir2,
                         -2 * M / (w * w) * ir2, 2 * L / (w * w) * ir2};
    const REALV D = sqrt(fmax(H * H - K, (REALV)0));
    const IREALV pos = isgreater(D, (REALV)0);
    const REALV iD = select((REALV)0, (REAL)0.5 / select((REALV)1, D, pos), pos);
    REALV jD[5];
    for (int i = 0; i < 5; ++i) jD[i] = (2 * H * jH[i] - jK[i]) * iD;
    const REALV vH = form5_v(jH, C, jH), vK = form5_v(jK, C, jK), vD = form5_v(jD, C, jD);
    const REALV cHD = form5_v(jH, C, jD);
    /* the fitted normal (-p, -q, 1) / sqrt(w): angle variance tr(G Cov(p, q)),
       G = (I - g g^T / w) / w, g = (p, q), Cov(p, q) = C[1..2][1..2] / r^2 */
    const REALV iw = (REAL)1 / w;
    const REALV g00 = (1 - p * p * iw) * iw, g01 = -p * q * iw * iw, g11 = (1 - q * q * iw) * iw;
    const REALV nv = (g00 * C[1][1] + 2 * g01 * C[1][2] + g11 * C[2][2]) * ir2;
    const REALV v[6] = {vH, vK, vH + vD + 2 * cHD, vH + vD - 2 * cHD, nv, (REALV)1};
    for (int i = 0; i < 6; ++i)      /* fmax drops a NaN: the dof test restores it */
        e[i] = select((REALV)(NAN), sqrt(fmax(sigma2 * v[i], (REALV)0)), dof);
}
#endif

/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): PCA of the
 * VW balls with one vectorised eigen solve, then each point's normal equations, then the VW
 * 6x6 systems solved at once in the vector lanes, then the per-point curvatures. */
__kernel void mls2(OPERATOR_ARGS, __global REAL *out2)
{
    const REAL r = par.x, ih2 = par.y;
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, CN, cell_of, ranges, n, g0, kn, ball, ih2, &pb);
    REAL Ml[21][VW], bl[6][VW], fr[12][VW];
    mls2_err_t err;
    uchar st[VW];
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            const uint co = cell_of[g];
            st[k] = mls2_system(x_rows(X, co, n), Y, Z, NX, NY, NZ, W, ranges, co & CELL_MASK, g,
                                &pb, k, r, ih2, POINT_BALL(W, g, ball), fr, Ml, bl, &err);
        } else {
            identity_system(Ml, bl, k);
#if UNCERTAINTY
            identity_errors(&err, k);
#endif
            for (int e = 0; e < 12; ++e) fr[e][k] = (REAL)(e == 0 || e == 4 || e == 8);
        }
    }
    REALV Mv[21], bv[6], xv[6], sv[6], dv[6];
    for (int e = 0; e < 21; ++e) Mv[e] = VLOADV(0, Ml[e]);
    for (int e = 0; e < 6; ++e) bv[e] = VLOADV(0, bl[e]);
    const IREALV ok = solve6_v(Mv, sv, dv, bv, xv);
    IREAL okl[VW];
    CAT(vstore, VW)(ok, 0, okl);
    REAL o[14][VW];
    mls2_finish_v(xv, fr, r, o);
#if UNCERTAINTY
    REAL eo[6][VW];
    {
        REAL cnt[VW];
        for (uint k = 0; k < VW; ++k) cnt[k] = (REAL)pb.count[k];
        REALV ev[6];
        mls2_errors_v(xv, Mv, sv, dv, ok, bv, &err, VLOADV(0, cnt), r, ev);
        for (int e = 0; e < 6; ++e) VSTOREV(ev[e], 0, eo[e]);
    }
#endif
    /* the records: shift | k1 k2 | dir1 | dir2 | normal | count | status */
    for (uint k = 0; k < kn; ++k) {
        const uchar s = (st[k] == ST_OK && !okl[k]) ? ST_SINGULAR : st[k];
        REAL16 rec = (REAL16)(NAN);
        if (s == ST_OK) {
            rec.COL_SHIFT = (REAL3)(o[0][k], o[1][k], o[2][k]);
            rec.COL_K1 = o[3][k];
            rec.COL_K2 = o[4][k];
            rec.COL_DIR1 = (REAL3)(o[5][k], o[6][k], o[7][k]);
            rec.COL_DIR2 = (REAL3)(o[8][k], o[9][k], o[10][k]);
            rec.COL_NORMALS = (REAL3)(o[11][k], o[12][k], o[13][k]);
        }
        REC_COUNT_STATUS(rec, pb.count[k], s);
        REC_STORE(rec, REC_INDEX(g0 + k), out);
#if UNCERTAINTY
        /* the error record: SE(H) SE(K) SE(k1) SE(k2) SE(normal) roughness | count | status */
        REAL16 er = (REAL16)(NAN);
        if (s == ST_OK) {
            er.COL_MEAN_SE = eo[0][k];
            er.COL_GAUSSIAN_SE = eo[1][k];
            er.COL_K1_SE = eo[2][k];
            er.COL_K2_SE = eo[3][k];
            er.COL_NORMAL_SE = eo[4][k];
            er.COL_ROUGHNESS = eo[5][k];
        }
        er.ECOL_COUNT = UINT_AS_REAL(pb.count[k]);
        er.ECOL_STATUS = (REAL)s;
        REC_STORE(er, REC_INDEX(g0 + k), out2);
#endif
    }
}
