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

/* Frame and normal equations of the sorted point g (lane k), once its PCA is known: v0
 * oriented by the reference normal, the tangent frame, Q - p, and sum w phi phi^T (packed)
 * and sum w h phi for phi = (1, x, y, x^2, xy, y^2). Returns the status. */
inline uchar mls2_system(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                         __global const REAL *NX, __global const REAL *NY,
                         __global const REAL *NZ, __global const REAL *W,
                         __global const uint2 *ranges, uint cell, uint g, const pca_batch_t *pb,
                         uint k, REAL r, REAL ih2, REAL2 ball, REAL fr[12][VW],
                         REAL M[21][VW], REAL b[6][VW])
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

/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): PCA of the
 * VW balls with one vectorised eigen solve, then each point's normal equations, then the VW
 * 6x6 systems solved at once in the vector lanes, then the per-point curvatures. */
__kernel void mls2(OPERATOR_ARGS)
{
    const REAL r = par.x, ih2 = par.y;
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, CN, cell_of, ranges, n, g0, kn, ball, ih2, &pb);
    REAL Ml[21][VW], bl[6][VW], fr[12][VW];
    uchar st[VW];
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            const uint co = cell_of[g];
            st[k] = mls2_system(x_rows(X, co, n), Y, Z, NX, NY, NZ, W, ranges, co & CELL_MASK, g,
                                &pb, k, r, ih2, POINT_BALL(W, g, ball), fr, Ml, bl);
        } else {
            identity_system(Ml, bl, k);
            for (int e = 0; e < 12; ++e) fr[e][k] = (REAL)(e == 0 || e == 4 || e == 8);
        }
    }
    REALV Mv[21], bv[6], xv[6];
    for (int e = 0; e < 21; ++e) Mv[e] = VLOADV(0, Ml[e]);
    for (int e = 0; e < 6; ++e) bv[e] = VLOADV(0, bl[e]);
    const IREALV ok = solve6_v(Mv, bv, xv);
    IREAL okl[VW];
    CAT(vstore, VW)(ok, 0, okl);
    REAL o[14][VW];
    mls2_finish_v(xv, fr, r, o);
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
    }
}
