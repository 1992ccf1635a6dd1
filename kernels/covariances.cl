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
 * Signs. The neighbours' normals n_i are used as given (ALIGN_NORMALS 0): the normals a
 * caller passes are data, and 2dcov2 is then PCL's PrincipalCurvaturesEstimation with the
 * same normals (tests/test_pcl_oracle.py). With ALIGN_NORMALS 1 (the host's choice for the
 * PCA normals it estimates itself, whose signs are arbitrary, or when asked for), each
 * neighbour's normal is first aligned with p's: n_i := -n_i where <n_i, n> < 0 (kept where
 * <n_i, n> = 0; the paper's "orientation made consistent with n", Theorem 3), so the
 * normals need to agree within each ball only, not across the cloud, and the sign of any
 * neighbour's normal changes nothing. The sign of n itself changes no eigenvalue and no
 * magnitude either (with ALIGN_NORMALS 1, or for 2dcov1, which reads n alone), bit for bit:
 * tangent_frame(-n) = (-t1, t2), so
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
 * Build options: COV_METHOD, ALIGN_NORMALS (0 or 1; 2dcov2, 3dcov), DENSITY, POINT_RADIUS (radius.h), MIN_COUNT and the record
 * columns COL_EIGENVALUES (2, or 3 for 3dcov), COL_K1, COL_K2, COL_DIR1 (3), COL_DIR2 (3),
 * COL_COUNT, COL_STATUS, with their first columns' numbers CIX_<FIELD> and their mask
 * REC_USED (lanes_records.h; clcurv/ops/registry.py).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "frame.h"
#include "eig3.h"
#include "radius.h"
#include "lanes_records.h"

#if !defined(COV_METHOD) || !defined(ALIGN_NORMALS) || !defined(MIN_COUNT) \
    || !defined(COL_EIGENVALUES) \
    || !defined(COL_K1) || !defined(COL_K2) || !defined(COL_DIR1) || !defined(COL_DIR2) \
    || !defined(COL_COUNT) || !defined(COL_STATUS)
#error "covariances.cl needs COV_METHOD, ALIGN_NORMALS, MIN_COUNT and its record columns (clcurv/ops/registry.py)"
#endif

/* |k1| >= |k2| from 2dcov1's count-normalised eigenvalues (Theorem 1) in the VW lanes,
 * keeping the root m+ of m = (k1 + k2)^2 (the k1 k2 >= 0 solution whenever one exists), as
 * reference.invert_theorem1 documents. */
inline void invert_theorem1_v(REALV l1, REALV l2, REALV r, REALV *k1, REALV *k2)
{
    /* u = l1 / c with c = r^6 / 256, as two factors: 256 / r^6 itself overflows float32
       for r < 2^-19 and r^6 for r > 2^21, where l1 (~ k^2 r^6) is still representable */
    const REALV r2 = r * r, a = (REAL)16 / r2, b = (REAL)16 / (r2 * r2);
    const REALV u = l1 * a * b, v = l2 * a * b, S = u + v;
    const REALV m = (S + sqrt(fmax((REAL)8 * u * v - S * S, (REALV)0))) / (REAL)8;
    *k1 = sqrt(fmax(u - m, (REALV)0) * (REAL)0.25);
    *k2 = sqrt(fmax(v - m, (REALV)0) * (REAL)0.25);
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
#if ALIGN_NORMALS
        /* align each neighbour's normal with p's: q := -q where <q, n> < 0 (= 0 or NaN: kept) */
        const REALV qx0 = VLOADV(0, NX + i), qy0 = VLOADV(0, NY + i), qz0 = VLOADV(0, NZ + i);
        const IREALV flip = isless(qx0 * nrm.x + qy0 * nrm.y + qz0 * nrm.z, (REALV)0);
        const REALV qx = select(qx0, -qx0, flip), qy = select(qy0, -qy0, flip);
        const REALV qz = select(qz0, -qz0, flip);
#else                                   /* the normals as given */
        const REALV qx = VLOADV(0, NX + i), qy = VLOADV(0, NY + i), qz = VLOADV(0, NZ + i);
#endif
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
        MASKED_COUNT(sw, m)
        sa += fa; sb += fb;
        saa += fa * fa; sab += fa * fb; sbb += fb * fb;          /* fused: pca.h */
#if COV_METHOD == 3
        sd += fd;
        sad += fa * fd; sbd += fb * fd; sdd += fd * fd;
#endif
#endif
    NEIGHBOR_CHUNKS_END
#if DENSITY || GAUSSIAN
    const REAL iw = (REAL)1 / hsum(sw);
#else
    const REAL iw = (REAL)1 / COUNT_TOTAL(sw);       /* w = 1: the count (common.h) */
#endif
    const REAL ma = hsum(sa) * iw, mb = hsum(sb) * iw, md = hsum(sd) * iw;
    c[0] = hsum(saa) * iw - ma * ma; c[1] = hsum(sab) * iw - ma * mb;
    c[2] = hsum(sad) * iw - ma * md; c[3] = hsum(sbb) * iw - mb * mb;
    c[4] = hsum(sbd) * iw - mb * md; c[5] = hsum(sdd) * iw - md * md;
#if DENSITY || GAUSSIAN
    return (uint)hsum(sc);
#else
    (void)sc;
    return (uint)COUNT_TOTAL(sw);           /* w = 1: the sum of the weights is the count */
#endif
}


/* record column c of the lanes: the value where the status is OK, NaN elsewhere */
#define COV_COLUMN(c, expr) col[c] = select((REALV)(NAN), (expr), ok);

/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the sums
 * point by point, then in the vector lanes the eigen decompositions (3dcov: eig3_sym_v;
 * the 2D methods: eig2_sym_v), the magnitudes, directions and status, and the records from
 * their columns (lanes_records.h; evaluated point by point, this part took ~10 ms of the
 * 1M-point 3dcov kernel, ~15 of 2dcov2's, on a 2-core AVX2 CPU). */
__kernel void covariance(OPERATOR_ARGS)
{
    const REAL r = par.x;
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    uint cnt[VW];
    int fin[VW];
    REAL cs[6][VW];
    REAL fr[9][VW];                                 /* n, t1, t2 of each lane */
    REAL rad[VW];
    for (uint k = 0; k < VW; ++k) {
        REAL c[6] = {1, 0, 0, 1, 0, 1};              /* unused lane: the identity */
        REAL3 nrm = (REAL3)(0, 0, 1), t1, t2;
        cnt[k] = 0;
        rad[k] = 1;
        if (k < kn) {
            const uint g = g0 + k;
            nrm = (REAL3)(NX[g], NY[g], NZ[g]);
            rad[k] = BALL_R(W, g, r);
        }
        tangent_frame(nrm, &t1, &t2);
        if (k < kn) {
            const uint g = g0 + k;
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
        fr[0][k] = nrm.x; fr[1][k] = nrm.y; fr[2][k] = nrm.z;
        fr[3][k] = t1.x; fr[4][k] = t1.y; fr[5][k] = t1.z;
        fr[6][k] = t2.x; fr[7][k] = t2.y; fr[8][k] = t2.z;
    }
    const REALV nx = VLOADV(0, fr[0]), ny = VLOADV(0, fr[1]), nz = VLOADV(0, fr[2]);
    const REALV t1x = VLOADV(0, fr[3]), t1y = VLOADV(0, fr[4]), t1z = VLOADV(0, fr[5]);
    const REALV R = VLOADV(0, rad);
    REALV lam0, lam1, k1, k2, e1x, e1y, e1z;
#if COV_METHOD == 3
    REALV w0, w1, w2;
    eig3_v3_v v0, v1, v2;
    eig3_sym_v(VLOADV(0, cs[0]), VLOADV(0, cs[1]), VLOADV(0, cs[2]),
               VLOADV(0, cs[3]), VLOADV(0, cs[4]), VLOADV(0, cs[5]),
               &w0, &w1, &w2, &v0, &v1, &v2);
    lam0 = fmax(w2, (REALV)0);                      /* descending */
    lam1 = fmax(w1, (REALV)0);
    const REALV lam2 = fmax(w0, (REALV)0);
    /* dir1: the largest eigenvalue's vector on the tangent plane (t1 where it has none) */
    const REALV d = v2.x * nx + v2.y * ny + v2.z * nz;
    const REALV tx = v2.x - d * nx, ty = v2.y - d * ny, tz = v2.z - d * nz;
    const REALV tl = sqrt(tx * tx + ty * ty + tz * tz);
    const IREALV tang = isgreater(tl, (REALV)1e-3);
    e1x = select(t1x, tx / tl, tang);
    e1y = select(t1y, ty / tl, tang);
    e1z = select(t1z, tz / tl, tang);
    k1 = (REAL)2 / R * sqrt(lam0);
    k2 = (REAL)2 / R * sqrt(lam1);
#else
    const REALV t2x = VLOADV(0, fr[6]), t2y = VLOADV(0, fr[7]), t2z = VLOADV(0, fr[8]);
    REALV l1, l2, ea, eb;
    eig2_sym_v(VLOADV(0, cs[0]), VLOADV(0, cs[1]), VLOADV(0, cs[3]), &l1, &l2, &ea, &eb);
    lam0 = fmax(l1, (REALV)0);
    lam1 = fmax(l2, (REALV)0);
    e1x = ea * t1x + eb * t2x;
    e1y = ea * t1y + eb * t2y;
    e1z = ea * t1z + eb * t2z;
#if COV_METHOD == 1
    invert_theorem1_v(lam0, lam1, R, &k1, &k2);
#else
    k1 = (REAL)2 / R * sqrt(lam0);
    k2 = (REAL)2 / R * sqrt(lam1);
#endif
#endif
    /* status: too few neighbours; a NaN normal anywhere in the ball (the sums are then
       NaN: fmax would hide it in the eigenvalues) or at p */
    const IREALV finite = (CAT(convert_, IREALV)(CAT(vload, VW)(0, fin)) != (IREALV)0)
                          & isfinite(nx) & isfinite(ny) & isfinite(nz) & isfinite(e1x);
    const IREALV few = CAT(convert_, IREALV)(CAT(vload, VW)(0, cnt) < (CAT(uint, VW))MIN_COUNT);
    const REALV stf = select(select((REALV)ST_OK, (REALV)ST_DEGENERATE, !finite),
                             (REALV)ST_TOO_FEW, few);
    const IREALV ok = stf == (REALV)ST_OK;
    /* record: eigenvalues (descending; 2, or 3 for 3dcov) | k1 k2 | dir1 | dir2 | count |
       status */
    REALV col[16];
    COV_COLUMN(CIX_EIGENVALUES, lam0)
    COV_COLUMN(CIX_EIGENVALUES + 1, lam1)
#if COV_METHOD == 3
    COV_COLUMN(CIX_EIGENVALUES + 2, lam2)
#endif
    COV_COLUMN(CIX_K1, k1)
    COV_COLUMN(CIX_K2, k2)
    COV_COLUMN(CIX_DIR1, e1x)
    COV_COLUMN(CIX_DIR1 + 1, e1y)
    COV_COLUMN(CIX_DIR1 + 2, e1z)
    COV_COLUMN(CIX_DIR2, ny * e1z - nz * e1y)                      /* n x dir1 */
    COV_COLUMN(CIX_DIR2 + 1, nz * e1x - nx * e1z)
    COV_COLUMN(CIX_DIR2 + 2, nx * e1y - ny * e1x)
    col[CIX_COUNT] = LANES_COUNT(cnt);
    col[CIX_STATUS] = stf;
    REC_STORE_LANES(col, kn, g0, out, REC_USED)
}
