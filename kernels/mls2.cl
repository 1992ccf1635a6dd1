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
#include "quadric.h"

#if !defined(REF_NORMALS) || !defined(MIN_COUNT) || !defined(COL_SHIFT) || !defined(COL_K1) \
    || !defined(COL_K2) || !defined(COL_DIR1) || !defined(COL_DIR2) || !defined(COL_NORMALS) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "mls2.cl needs REF_NORMALS, MIN_COUNT and its record columns (clcurv/ops/registry.py)"
#endif
#if UNCERTAINTY && (!defined(COL_MEAN_SE) || !defined(COL_GAUSSIAN_SE) || !defined(COL_K1_SE) \
    || !defined(COL_K2_SE) || !defined(COL_NORMAL_SE) || !defined(COL_ROUGHNESS) \
    || !defined(ECOL_COUNT) || !defined(ECOL_STATUS))
#error "mls2.cl with UNCERTAINTY needs its error record's columns (clcurv/ops/registry.py)"
#endif

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
 * curvature_jacobian) has the model and the formulas: Cov(a) = sigma^2 A^-1 B A^-1
 * (quadric_cov_v), SE(X)^2 = J_X Cov(a) J_X^T by the delta method, gradients included;
 *   k1,2 = H +- D, D = sqrt(H^2 - K) (dD = 0 where D = 0). NaN where nu <= 0. */
inline void mls2_errors_v(const REALV a[6], const REALV m[21], const REALV s[6],
                          const REALV d[6], const IREALV ok, const REALV b[6],
                          const mls2_err_t *err, const REALV count, REAL r, REALV e[6])
{
    REALV C[6][6], sigma2;
    const IREALV dof = quadric_cov_v(a, m, s, d, ok, b, err, count, C, &sigma2);
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
