/* covariances.cl -- the normal-based "fundamental forms" of Digne & Morel (Section 4):
 *   COV_METHOD 1  2dcov1: covariance of alpha_i = <d_i, n> (<d_i, t1>, <d_i, t2>)  (Theorem 1)
 *   COV_METHOD 2  2dcov2: covariance of the neighbours' unit normals projected on the
 *                 tangent plane at p (Theorem 2; PCL's PrincipalCurvaturesEstimation)
 *   COV_METHOD 3  3dcov:  covariance of the neighbours' unit normals (Theorem 3)
 * with d_i = q_i - p and (t1, t2, n) the tangent frame of p's unit normal n.
 * Covariances are weighted and normalised by the sum of weights (= Sigma / n_p for uniform
 * weights, the paper's count normalisation). The 3D normals are accumulated relative to n
 * (a shift leaves a covariance unchanged and keeps float32 sums small).
 *
 * Signs: the normals need to agree within each ball only, not across the cloud. Each
 * neighbour's normal n_i is first aligned with p's: n_i := -n_i where <n_i, n> < 0 (kept
 * where <n_i, n> = 0; the paper's "orientation made consistent with n", Theorem 3), so the
 * sign of any neighbour's normal changes nothing. The sign of n itself changes no
 * eigenvalue and no magnitude either, bit for bit: tangent_frame(-n) = (-t1, t2), so
 *   2dcov1: s_i = <d_i, n> flips, f_i = s_i (<d_i, t1>, <d_i, t2>) becomes (f_a, -f_b);
 *   2dcov2: the aligned n_i flip with n, f_i = (<n_i, t1>, <n_i, t2>) becomes (f_a, -f_b);
 *   3dcov:  f_i = n_i - n becomes -f_i;
 * negating feature coordinates negates the off-diagonal entry ab (2D) or nothing (3D), and
 * every operation here is exact under negation (round to nearest). What may change is the
 * sign of the directions: 2dcov1/2dcov2's dir1 = +-(e_a t1 + e_b t2) follows eig2_sym's
 * branch (flips when a >= c), 3dcov's dir1 is the same (t1, which flips, on a flat ball),
 * and dir2 = n x dir1 keeps (dir1, dir2, n) right-handed, so it flips when n flips and dir1
 * does not. The host returns the normals it was given (their signs are the caller's).
 *
 * Outputs per point (one record, input order): count, status, eigenvalues (descending; 2
 * or 3), the curvature magnitudes k1 >= k2 >= 0 (1/length) and the unit tangent directions
 * dir1, dir2 (dir2 = n x dir1). A NaN normal anywhere in the ball gives status DEGENERATE.
 * Build options: COV_METHOD, DENSITY, POINT_RADIUS (radius.h), MIN_COUNT and the record columns COL_EIGENVALUES (2,
 * or 3 for 3dcov), COL_K1, COL_K2, COL_DIR1 (3), COL_DIR2 (3), COL_COUNT, COL_STATUS
 * (clcurv/operators.py).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "frame.h"
#include "eig3.h"
#include "radius.h"

#if !defined(COV_METHOD) || !defined(MIN_COUNT) || !defined(COL_EIGENVALUES) \
    || !defined(COL_K1) || !defined(COL_K2) || !defined(COL_DIR1) || !defined(COL_DIR2) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "covariances.cl needs COV_METHOD, MIN_COUNT and its record columns (clcurv/operators.py)"
#endif

/* |k1| >= |k2| from 2dcov1's count-normalised eigenvalues (Theorem 1), keeping the root
 * m+ of m = (k1 + k2)^2 (the k1 k2 >= 0 solution whenever one exists), as
 * reference.invert_theorem1 documents. */
inline REAL2 invert_theorem1(REAL l1, REAL l2, REAL r)
{
    /* u = l1 / c with c = r^6 / 256, as two factors: 256 / r^6 itself overflows float32
       for r < 2^-19 and r^6 for r > 2^21, where l1 (~ k^2 r^6) is still representable */
    const REAL r2 = r * r, a = (REAL)16 / r2, b = (REAL)16 / (r2 * r2);
    const REAL u = l1 * a * b, v = l2 * a * b, S = u + v;
    const REAL m = (S + sqrt(fmax((REAL)8 * u * v - S * S, (REAL)0))) / (REAL)8;
    return (REAL2)(sqrt(fmax(u - m, (REAL)0) * (REAL)0.25), sqrt(fmax(v - m, (REAL)0) * (REAL)0.25));
}

/* Weighted covariance c = aa ab ad bb bd dd (the 2D methods use aa ab bb) of the features
 * f_i of the ball of sorted point g (see the top); returns the neighbour count. */
inline uint cov_ball(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *NX, __global const REAL *NY, __global const REAL *NZ,
                      __global const REAL *W, __global const uint2 *ranges, uint cell, REAL3 p,
                      REAL3 nrm, REAL3 t1, REAL3 t2, REAL2 ball, REAL c[6])
{
    REALV sc = 0, sw = 0, sa = 0, sb = 0, sd = 0, saa = 0, sab = 0, sad = 0, sbb = 0, sbd = 0, sdd = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, (REAL)0);
#if COV_METHOD == 1
        const REALV s = dx * nrm.x + dy * nrm.y + dz * nrm.z;
        const REALV fa0 = s * (dx * t1.x + dy * t1.y + dz * t1.z);
        const REALV fb0 = s * (dx * t2.x + dy * t2.y + dz * t2.z);
        const REALV fd0 = 0;
#else
        /* align each neighbour's normal with p's: q := -q where <q, n> < 0 (= 0 or NaN: kept) */
        const REALV qx0 = VLOADV(0, NX + i), qy0 = VLOADV(0, NY + i), qz0 = VLOADV(0, NZ + i);
        const IREALV flip = isless(qx0 * nrm.x + qy0 * nrm.y + qz0 * nrm.z, (REALV)0);
        const REALV qx = select(qx0, -qx0, flip), qy = select(qy0, -qy0, flip);
        const REALV qz = select(qz0, -qz0, flip);
#if COV_METHOD == 2
        const REALV fa0 = qx * t1.x + qy * t1.y + qz * t1.z;
        const REALV fb0 = qx * t2.x + qy * t2.y + qz * t2.z;
        const REALV fd0 = 0;
#else
        const REALV fa0 = qx - nrm.x, fb0 = qy - nrm.y, fd0 = qz - nrm.z;
#endif
#endif
        /* zero outside the ball: a NaN normal there must not leak (w = 0 would not stop
         * it), and with uniform weights the sums are then plain adds and multiply-adds */
        const REALV fa = select((REALV)0, fa0, m), fb = select((REALV)0, fb0, m);
        const REALV fd = select((REALV)0, fd0, m);
#if DENSITY || GAUSSIAN
        sc += select((REALV)0, (REALV)1, m);
        const REALV wa = w * fa, wb = w * fb;
        sw += w; sa += wa; sb += wb; saa += wa * fa; sab += wa * fb; sbb += wb * fb;
#if COV_METHOD == 3
        const REALV wd = w * fd;
        sd += wd; sad += wa * fd; sbd += wb * fd; sdd += wd * fd;
#endif
#else                                   /* uniform weights: zeroed values (weights.h) */
        (void)w;
        MASKED_ADD(sw, m, (REAL)1)
        sa += fa; sb += fb;
        saa = mad(fa, fa, saa); sab = mad(fa, fb, sab); sbb = mad(fb, fb, sbb);
#if COV_METHOD == 3
        sd += fd;
        sad = mad(fa, fd, sad); sbd = mad(fb, fd, sbd); sdd = mad(fd, fd, sdd);
#endif
#endif
    NEIGHBOR_CHUNKS_END
    const REAL iw = (REAL)1 / hsum(sw);
    const REAL ma = hsum(sa) * iw, mb = hsum(sb) * iw, md = hsum(sd) * iw;
    c[0] = hsum(saa) * iw - ma * ma; c[1] = hsum(sab) * iw - ma * mb;
    c[2] = hsum(sad) * iw - ma * md; c[3] = hsum(sbb) * iw - mb * mb;
    c[4] = hsum(sbd) * iw - mb * md; c[5] = hsum(sdd) * iw - md * md;
#if DENSITY || GAUSSIAN
    return (uint)hsum(sc);
#else
    (void)sc;
    return (uint)hsum(sw);                  /* w = 1: the sum of the weights is the count */
#endif
}

/* Eigenvalues (descending), magnitudes, directions and the record of one point. lam3/e3 are
 * the 3dcov eigen decomposition (largest eigenvalue's vector e3), unused otherwise. */
inline void cov_finish(uint count, int finite, REAL a, REAL b, REAL c, REAL3 nrm, REAL3 t1,
                       REAL3 t2, REAL r, REAL3 lam3, REAL3 e3, size_t j, __global REAL *out)
{
#if COV_METHOD == 3
    REAL3 lam = fmax(lam3, (REAL3)0);
    const REAL3 tang = e3 - dot(e3, nrm) * nrm;           /* largest, on the tangent plane */
    REAL3 e1 = length(tang) > (REAL)1e-3 ? normalize(tang) : t1;
    REAL2 k = (REAL)2 / r * sqrt(lam.xy);
#else
    REAL l1, l2;
    REAL2 ev;
    eig2_sym(a, b, c, &l1, &l2, &ev);
    REAL3 lam = fmax((REAL3)(l1, l2, 0), (REAL3)0);
    REAL3 e1 = ev.x * t1 + ev.y * t2;
#if COV_METHOD == 1
    REAL2 k = invert_theorem1(lam.x, lam.y, r);
#else
    REAL2 k = (REAL)2 / r * sqrt(lam.xy);
#endif
#endif
    /* a NaN normal in the ball makes the sums NaN (fmax above would hide it in lam) */
    finite = finite && isfinite(nrm.x) && isfinite(nrm.y) && isfinite(nrm.z) && isfinite(e1.x);
    uchar st = ST_OK;
    if (count < MIN_COUNT) st = ST_TOO_FEW;
    else if (!finite) st = ST_DEGENERATE;
    /* record: eigenvalues (descending; 2, or 3 for 3dcov) | k1 k2 | dir1 | dir2 | count |
       status */
    REAL16 rec = (REAL16)(NAN);
    if (st == ST_OK) {
#if COV_METHOD == 3
        rec.COL_EIGENVALUES = lam;
#else
        rec.COL_EIGENVALUES = lam.xy;
#endif
        rec.COL_K1 = k.x;
        rec.COL_K2 = k.y;
        rec.COL_DIR1 = e1;
        rec.COL_DIR2 = cross(nrm, e1);
    }
    REC_COUNT_STATUS(rec, count, st);
    REC_STORE(rec, j, out);
}

#define VSTOREV CAT(vstore, VW)

/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)); 3dcov's VW
 * eigen decompositions run at once in the vector lanes (eig3_sym_v). */
__kernel void covariance(OPERATOR_ARGS)
{
    const REAL r = par.x;
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    uint cnt[VW];
    int fin[VW];
    REAL cs[6][VW];
    for (uint k = 0; k < VW; ++k) {
        REAL c[6] = {1, 0, 0, 1, 0, 1};              /* unused lane: the identity */
        cnt[k] = 0;
        if (k < kn) {
            const uint g = g0 + k;
            const REAL3 nrm = (REAL3)(NX[g], NY[g], NZ[g]);
            REAL3 t1, t2;
            tangent_frame(nrm, &t1, &t2);
            const uint co = cell_of[g];
            __global const REAL *XA = x_rows(X, co, n);
            cnt[k] = cov_ball(XA, Y, Z, NX, NY, NZ, W, ranges, co & CELL_MASK,
                              (REAL3)(XA[g], Y[g], Z[g]), nrm, t1, t2,
                              POINT_BALL(W, g, ball), c);
        }
        int f = 1;
        for (int e = 0; e < 6; ++e) {
            f = f && isfinite(c[e]);
            cs[e][k] = isfinite(c[e]) ? c[e] : (REAL)0;
        }
        fin[k] = f;
    }
    REAL l0[VW], l1[VW], l2[VW], ex[VW], ey[VW], ez[VW];
#if COV_METHOD == 3
    REALV w0, w1, w2;
    eig3_v3_v e0, e1, e2;
    eig3_sym_v(VLOADV(0, cs[0]), VLOADV(0, cs[1]), VLOADV(0, cs[2]),
               VLOADV(0, cs[3]), VLOADV(0, cs[4]), VLOADV(0, cs[5]),
               &w0, &w1, &w2, &e0, &e1, &e2);
    VSTOREV(w0, 0, l0); VSTOREV(w1, 0, l1); VSTOREV(w2, 0, l2);
    VSTOREV(e2.x, 0, ex); VSTOREV(e2.y, 0, ey); VSTOREV(e2.z, 0, ez);
#endif
    for (uint k = 0; k < kn; ++k) {
        const uint g = g0 + k;
        const REAL3 nrm = (REAL3)(NX[g], NY[g], NZ[g]);
        REAL3 t1, t2;
        tangent_frame(nrm, &t1, &t2);
        REAL3 lam3 = (REAL3)(0), e3 = t1;
#if COV_METHOD == 3
        lam3 = (REAL3)(l2[k], l1[k], l0[k]);                             /* descending */
        e3 = (REAL3)(ex[k], ey[k], ez[k]);
#endif
        cov_finish(cnt[k], fin[k], cs[0][k], cs[1][k], cs[3][k], nrm, t1, t2, BALL_R(W, g, r),
                   lam3, e3, REC_INDEX(g), out);
    }
}
