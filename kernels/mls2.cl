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
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"
#include "frame.h"
#include "solve6.h"

/* Unit eigenvector (in the parameter plane) of the 2x2 matrix s for its eigenvalue lam. */
inline REAL2 eigvec2(REAL s00, REAL s01, REAL s10, REAL s11, REAL lam)
{
    const REAL2 a = (REAL2)(s01, lam - s00), b = (REAL2)(lam - s11, s10);
    const REAL na = dot(a, a), nb = dot(b, b);
    const REAL2 v = na >= nb ? a : b;
    const REAL nv = sqrt(fmax(na, nb));
    return nv > (REAL)1e-12 * (fabs(s00) + fabs(s11) + fabs(s01) + fabs(s10)) && nv > 0
           ? v / nv : (REAL2)(1, 0);
}

/* Frame and normal equations of the sorted point g (lane k), once its PCA is known: v0
 * oriented by the reference normal, the tangent frame, Q - p, and sum w phi phi^T (packed)
 * and sum w h phi for phi = (1, x, y, x^2, xy, y^2). Returns the status. */
inline uchar mls2_system(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                         __global const REAL *NX, __global const REAL *NY,
                         __global const REAL *NZ, __global const REAL *W,
                         __global const uint2 *ranges, uint cell, uint g, const pca_batch_t *pb,
                         uint k, REAL r, REAL ih2, int use_ref, REAL3 *v0_out, REAL3 *t1_out,
                         REAL3 *t2_out, REAL3 *qo_out, REAL M[21], REAL b[6])
{
    const REAL3 p = (REAL3)(X[g], Y[g], Z[g]);
    const REAL r2 = r * r, ir = (REAL)1 / r;
    REAL3 v0 = (REAL3)(pb->v0x[k], pb->v0y[k], pb->v0z[k]);
    const REAL3 mu = (REAL3)(pb->mux[k], pb->muy[k], pb->muz[k]);
    uchar st = pca_status(pb, k, 6);
    if (use_ref) {
        const REAL s = dot(v0, (REAL3)(NX[g], NY[g], NZ[g]));
        if (!(s != 0)) st = st == ST_OK ? ST_DEGENERATE : st;   /* also NaN */
        if (s < 0) v0 = -v0;
    }
    REAL3 t1, t2;
    tangent_frame(v0, &t1, &t2);
    const REAL3 qo = dot(mu, v0) * v0;             /* Q - p */
    *v0_out = v0; *t1_out = t1; *t2_out = t2; *qo_out = qo;
    for (int e = 0; e < 21; ++e) M[e] = (REAL)(e == 0 || e == 2 || e == 5 || e == 9 || e == 14 || e == 20);
    for (int e = 0; e < 6; ++e) b[e] = 0;           /* identity system for failed points */
    if (st != ST_OK) return st;
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
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);
        const REALV x = dx * u1.x + dy * u1.y + dz * u1.z;
        const REALV y = dx * u2.x + dy * u2.y + dz * u2.z;
        const REALV h = dx * v0.x + dy * v0.y + dz * v0.z - cv0;
        const REALV xx = x * x, xy = x * y, yy = y * y;
        const REALV wxx = w * xx, wxy = w * xy, wyy = w * yy;
        s30 += wxx * x; s21 += wxx * y; s12 += wxy * y; s03 += wyy * y;
        s40 += wxx * xx; s31 += wxx * xy; s22 += wxx * yy; s13 += wxy * yy; s04 += wyy * yy;
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
    for (int e = 0; e < 21; ++e) M[e] = packed[e];
    b[0] = 0; b[1] = sw * dot(v0, C1) * ir; b[2] = sw * dot(v0, C2) * ir;
    b[3] = hsum(hxx); b[4] = hsum(hxy); b[5] = hsum(hyy);
    return st;
}

/* Curvatures, directions, normal and the record of one point from the fitted coefficients a.
 * Record: shift xyz | k1 k2 | dir1 xyz | dir2 xyz | normal xyz | count | status. */
inline void mls2_store(uchar st, const REAL a[6], REAL r, REAL3 v0, REAL3 t1, REAL3 t2, REAL3 qo,
                       uint count_k, size_t j, __global REAL *out)
{
    REAL16 rec = (REAL16)(NAN);
    rec.se = UINT_AS_REAL(count_k);
    rec.sf = (REAL)st;
    if (st != ST_OK) {
        STORE_RECORD(rec, j, out);
        return;
    }
    const REAL ir = (REAL)1 / r;
    const REAL gx = a[1] * ir, gy = a[2] * ir;
    const REAL gxx = 2 * a[3] * ir * ir, gxy = a[4] * ir * ir, gyy = 2 * a[5] * ir * ir;
    const REAL q = 1 + gx * gx + gy * gy, iq = (REAL)1 / q, wn = rsqrt(q);
    const REAL Lxx = gxx * wn, Lxy = gxy * wn, Lyy = gyy * wn;          /* II */
    const REAL i00 = (1 + gy * gy) * iq, i01 = -gx * gy * iq, i11 = (1 + gx * gx) * iq;  /* I^-1 */
    const REAL S00 = i00 * Lxx + i01 * Lxy, S01 = i00 * Lxy + i01 * Lyy;
    const REAL S10 = i01 * Lxx + i11 * Lxy, S11 = i01 * Lxy + i11 * Lyy;
    const REAL hmean = (REAL)0.5 * (S00 + S11);
    const REAL disc = sqrt(fmax(hmean * hmean - (S00 * S11 - S01 * S10), (REAL)0));
    const REAL lo = hmean - disc;                    /* -> k1 = -lo (the largest k) */
    const REAL2 e = eigvec2(S00, S01, S10, S11, lo);
    const REAL3 nfit = (v0 - gx * t1 - gy * t2) * wn;
    const REAL3 d1 = normalize(e.x * (t1 + gx * v0) + e.y * (t2 + gy * v0));
    rec.s012 = qo + a[0] * v0;
    rec.s34 = (REAL2)(-lo, -(hmean + disc));
    rec.s567 = d1;
    rec.s89a = cross(nfit, d1);
    rec.sbcd = nfit;
    STORE_RECORD(rec, j, out);
}


/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): PCA of the
 * VW balls with one vectorised eigen solve, then each point's normal equations, then the VW
 * 6x6 systems solved at once in the vector lanes, then the per-point curvatures. */
__kernel void mls2(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                   __global const REAL *NX, __global const REAL *NY, __global const REAL *NZ,
                   __global const REAL *W, __global const uint *cell_of,
                   __global const uint2 *ranges, __global const uint *order, const uint n,
                   const REAL r, const REAL ih2, const int use_ref,
                   __global REAL *out)
{
    const uint g0 = get_global_id(0) * VW;
    if (g0 >= n) return;
    const uint kn = min((uint)VW, n - g0);
    pca_batch_t pb;
    pca_batch(X, Y, Z, W, cell_of, ranges, g0, kn, r * r, ih2, &pb);
    REAL Ml[21][VW], bl[6][VW];
    REAL3 v0[VW], t1[VW], t2[VW], qo[VW];
    uchar st[VW];
    for (uint k = 0; k < VW; ++k) {
        REAL M[21], b[6];
        if (k < kn) {
            const uint g = g0 + k;
            st[k] = mls2_system(X, Y, Z, NX, NY, NZ, W, ranges, cell_of[g], g, &pb, k, r, ih2,
                                use_ref, &v0[k], &t1[k], &t2[k], &qo[k], M, b);
        } else {
            for (int e = 0; e < 21; ++e) M[e] = (REAL)(e == 0 || e == 2 || e == 5 || e == 9 || e == 14 || e == 20);
            for (int e = 0; e < 6; ++e) b[e] = 0;
        }
        for (int e = 0; e < 21; ++e) Ml[e][k] = M[e];
        for (int e = 0; e < 6; ++e) bl[e][k] = b[e];
    }
    REALV Mv[21], bv[6], xv[6];
    for (int e = 0; e < 21; ++e) Mv[e] = VLOADV(0, Ml[e]);
    for (int e = 0; e < 6; ++e) bv[e] = VLOADV(0, bl[e]);
    const IREALV ok = solve6_v(Mv, bv, xv);
    REAL xl[6][VW];
    IREAL okl[VW];
    for (int e = 0; e < 6; ++e) VSTOREV(xv[e], 0, xl[e]);
    CAT(vstore, VW)(ok, 0, okl);
    for (uint k = 0; k < kn; ++k) {
        const REAL a[6] = {xl[0][k], xl[1][k], xl[2][k], xl[3][k], xl[4][k], xl[5][k]};
        const uchar s = (st[k] == ST_OK && !okl[k]) ? ST_SINGULAR : st[k];
        mls2_store(s, a, r, v0[k], t1[k], t2[k], qo[k], pb.count[k], order[g0 + k], out);
    }
}
