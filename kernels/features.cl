/* features.cl -- the covariance ("dimensionality") features of the balls N_r(p) of every
 * point, at up to four radii in one neighbour walk (clcurv/api/features.py).
 *
 * A sibling of moments.cl: the same weighted PCA (pca.h: PCA_ACCUMULATE, pca_store_sums,
 * pca_decompose, PCA_REFINE_ACCUMULATE), so that its eigenvalues and normals are those of
 * the moments kernel bit for bit. The walk runs once over the candidates of the cloud's
 * cells (cell >= the largest radius) and accumulates the sums of every ball: ball j's lanes
 * are those of chunk_offsets' mask (at the largest ball) with d^2 < r_j^2, d^2 computed by
 * chunk_offsets' own expression, so the same lanes and the same additions in the same order
 * as a single-radius walk: every radius's record is bit-identical to a call at that radius
 * alone on the same cloud. lambda0 is anchored as in moments.cl (pca.h: PCA_ANCHOR, the
 * same sums per ball); the balls whose anchor is missing or too far share one second walk.
 * The balls' eigen solves run two at a time (pca.h: pca_decompose_pair), the features of
 * the VW points of a work-item at once in the vector lanes.
 *
 * Eigenvalues: l1 >= l2 >= l3 of the count-normalised covariance sum (q - o)(q - o)^T / n,
 * times n / (n - ddof) (ddof = par.z: 1 gives the sample covariance of jakteristics).
 * Features (clcurv/api/features.py documents them with their sources):
 *   EIGENVALUE_SUM l1 + l2 + l3       OMNIVARIANCE cbrt(l1 l2 l3)
 *   EIGENENTROPY -sum li ln li (0 ln 0 = 0)
 *   ANISOTROPY (l1 - l3) / l1         PLANARITY (l2 - l3) / l1    LINEARITY (l1 - l2) / l1
 *   PCA1 l1 / sum                     PCA2 l2 / sum               SURFACE_VARIATION l3 / sum
 *   SPHERICITY l3 / l1                VERTICALITY 1 - |e3_z|
 *   GUINARD_VERTICALITY |u_z| / |u|, u = l1 |e1| + l2 |e2| + l3 |e3| (componentwise |.|)
 *   EIGENVALUE1..3 l1, l2, l3         DENSITY n / (4/3 pi r^3)
 *   NORMALS e3 (unoriented, 3 columns)
 * with e1, e2, e3 the unit eigenvectors of l1, l2, l3.
 *
 * Build options: NR (1..4) radii, their r^2 in r2s (x, y, z, w), or with POINT_RADIUS
 * (NR = 1) each point's own r^2 in W (radius.h); the records of radius j go to out (j = 0),
 * out1, out2, out3 (one record per point, REC_INDEX), or with REC_BALLS (= NR) all to out,
 * in blocks of REC_BLOCK points (common.h: REC_IN_BLOCKS; records.cl's split with NB);
 * REFINE_L0, DENSITY, MIN_COUNT,
 * and the records' columns: CIX_COUNT, CIX_STATUS, one CIX_<FEATURE> (its first column) per
 * feature wanted and REC_USED their mask (clcurv/ops/features.py, lanes_records.h).
 */
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "pca.h"
#include "radius.h"
#include "ln.h"
#include "cbrt.h"
#include "lanes_records.h"

#if !defined(NR) || NR < 1 || NR > 4 || !defined(REFINE_L0) || !defined(MIN_COUNT) \
    || !defined(CIX_COUNT) || !defined(CIX_STATUS) || !defined(REC_USED) || !defined(REC_BALLS) \
    || !defined(REC_BLOCK)
#error "features.cl needs NR (1..4), REFINE_L0, MIN_COUNT, REC_BALLS, REC_BLOCK and its record columns (clcurv/ops/features.py)"
#endif

#if REAL_IS_DOUBLE
#define FOUR_THIRDS_PI 4.18879020478639098
#else
#define FOUR_THIRDS_PI 4.18879020f
#endif

/* The lanes of a chunk in ball j (d^2 < r2): chunk_offsets_d2's mask m at the largest ball,
 * and its d2 < r2 (the value chunk_offsets compares, so the mask is the one it gives at r2,
 * bit for bit: tests/test_multi_radius.py). */
inline IREALV ball_mask(IREALV m, REALV d2, REAL r2)
{
    return m & isless(d2, (REALV)r2);
}

#if NR > 1
#if DENSITY || GAUSSIAN || POINT_RADIUS
#error "features.cl: several radii take uniform weights and one radius for all points"
#endif
/* A ball's lanes among the kept chunks: d2 < r2 as integers, the same mask as isless bit
 * for bit (the kept d2 are +0 or more, or +inf, never NaN, and r2 > 0 is finite: such floats
 * order as their bits do), evaluated on the vector integer units instead of the FP pipes
 * that bound the sums (three balls' kernel ~2 ms faster at 1M points on the Zen 4 EPYC) */
#define BALL_LESS(d2, r2) (CAT(as_, IREALV)(d2) < (IREALV)CAT(as_, IREAL)(r2))
/* FEATURES_BUF (the host's choice, clcurv/runtime/program.py:features_buffer): chunks of
 * candidates kept before each ball's sums run over them (features_pca). Each run loads and
 * stores the ball's 10 accumulators: 32 chunks, about a point's whole walk at 30
 * neighbours, halve those moves against 16 (three balls' kernel ~4-8 ms faster at 1M
 * points on the Zen 3 EPYC, AVX2) in 4-8 KB of a CPU's stack; a GPU keeps 16, whose
 * private arrays live in slow memory. */
#ifndef FEATURES_BUF
#define FEATURES_BUF 16
#endif
#if FEATURES_BUF > 32
#error "features.cl: FEATURES_BUF is at most 32 (one bit a chunk of the buffer in a uint)"
#endif
/* Ball j's sums over chunk t of the buffer: lanes of the largest ball with d^2 < r2[j]
 * (ball_mask's test on the kept d^2, +inf outside the largest ball, so that the one test
 * is the mask). */
#define FEATURES_SUM_CHUNK(t)                                                             \
    {                                                                                     \
        const IREALV m = BALL_LESS(bd[t], r2[j]);                                         \
        const REALV w = select((REALV)0, (REALV)1, m);                                    \
        PCA_ACCUMULATE(w, m, bx[t], by[t], bz[t], c1, w1, x1, y1, z1, xx1, xy1, xz1, yy1, \
                       yz1, zz1)                                                          \
    }
/* Each ball's sums over the buffer's chunks in the order of the walk. With the zeroed
 * sums (MASKED_SUMS 0) over the chunks with a lane in the largest ball only, the set bits
 * of kept: a chunk left out has no lane in any ball, and would add +0 to every lane of
 * every sum, which changes no bit (no sum is ever -0), so the sums are a single-radius
 * walk's, which adds every chunk. (With the masked sums of AVX-512 devices, not measured
 * there, every chunk.) */
#if MASKED_SUMS
#define KEPT_BIT(m) 0u
#define FEATURES_SUM_CHUNKS for (uint t = 0; t < nb; ++t) FEATURES_SUM_CHUNK(t)
#else
#define KEPT_BIT(m) ((uint)any_lane(m))
#define FEATURES_SUM_CHUNKS                                                               \
    for (uint bits = kept; bits; bits &= bits - 1) {                                      \
        const uint t = 31 - clz(bits & (0u - bits));          /* the lowest set bit */    \
        FEATURES_SUM_CHUNK(t)                                                             \
    }
#endif
#define FEATURES_FLUSH                                                                    \
    for (int j = 0; j < NR; ++j) {                                                        \
        REALV c1 = sc[j], w1 = sw[j], x1 = sx[j], y1 = sy[j], z1 = sz[j];                 \
        REALV xx1 = sxx[j], xy1 = sxy[j], xz1 = sxz[j], yy1 = syy[j], yz1 = syz[j];       \
        REALV zz1 = szz[j];                                                               \
        FEATURES_SUM_CHUNKS                                                               \
        sc[j] = c1; sw[j] = w1; sx[j] = x1; sy[j] = y1; sz[j] = z1; sxx[j] = xx1;         \
        sxy[j] = xy1; sxz[j] = xz1; syy[j] = yy1; syz[j] = yz1; szz[j] = zz1;             \
    }                                                                                     \
    kept = 0;
#endif

#if NR > 1
/* The walk of features_pca for NR balls, offsets in the anchor frame of axis AX (a
 * constant: PCA_BY_AXIS): every chunk of candidates is stored in the next slot of the
 * buffer (offsets in the anchor frame, chunk_offsets_d2's d^2, +inf outside the largest
 * ball), FEATURES_BUF at a time, its bit in kept set when it has a lane in the largest
 * ball (KEPT_BIT); each ball's sums then run over the buffer with only that ball's
 * accumulators live (with every ball's at once, 10 vectors each, the registers spilled:
 * three balls cost 245 ms at 1M points against 222 for three single-radius walks). On the
 * 1M sphere 15.7 of a point's 28.4 chunks at r√2 have a lane in the largest ball: the
 * three balls' kernel 2-8 ms faster on the Zen 3 EPYC (AVX2) than with every chunk summed.
 * The slot is the chunk's count whatever its lanes: a slot advanced only for kept chunks
 * made the buffer's store addresses, and so the next chunk's loads, wait for each chunk's
 * test (+13 ms). Summing the largest ball as the walk goes (its accumulators live through
 * the walk) was slower too. */
#define FEATURES_WALK(AX)                                                                 \
    {                                                                                     \
        REALV bx[FEATURES_BUF], by[FEATURES_BUF], bz[FEATURES_BUF], bd[FEATURES_BUF];     \
        uint nb = 0, kept = 0;                                                            \
        NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)                \
            const IREALV mmax = chunk_offsets_d2(XA, Y, Z, i, end, pr, bmax, &dx, &dy, &dz, \
                                                 &d2);                                    \
            FEATURES_FRAME(AX)                                                            \
            bx[nb] = ex; by[nb] = ey; bz[nb] = ez;                                        \
            bd[nb] = select((REALV)INFINITY, d2, mmax);                                   \
            kept |= KEPT_BIT(mmax) << nb;                                                 \
            if (++nb == FEATURES_BUF) {                                                   \
                FEATURES_FLUSH                                                            \
                nb = 0;                                                                   \
            }                                                                             \
        NEIGHBOR_CHUNKS_END                                                               \
        FEATURES_FLUSH                                                                    \
    }
#if PCA_ANCHOR
#define FEATURES_FRAME(AX) PCA_SHEAR(AX, fs, dx, dy, dz, ex, ey, ez)  /* masks: from d */
#else
#define FEATURES_FRAME(AX) ex = dx; ey = dy; ez = dz;
#endif
#endif

/* The PCA of the NR balls of the VW consecutive sorted points g0 .. g0 + kn - 1: one walk
 * per point at the cloud's cells, ball j's lanes masked at r2[j] (NR = 1: pca_ball). */
inline void features_pca(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                         __global const REAL *W, __global const REAL *CN,
                         __global const uint *cell_of,
                         __global const uint2 *ranges, uint n, uint g0, uint kn, REAL2 ball,
                         const REAL r2[NR], pca_batch_t pb[NR])
{
    REAL r2max = r2[0];
    for (int j = 1; j < NR; ++j) r2max = fmax(r2max, r2[j]);
    for (uint k = 0; k < VW; ++k) {
        if (k >= kn) {
            for (int j = 0; j < NR; ++j) pca_empty_lane(&pb[j], k);
            continue;
        }
        const uint g = g0 + k;
        const uint co = cell_of[g];
        __global const REAL *XA = x_rows(X, co, n);
        const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
#if PCA_ANCHOR
        const REAL3 a = vload3(co & CELL_MASK, CN);
#else
        const REAL3 a = (REAL3)(0);
#endif
        const REAL2 bmax = (REAL2)(BALL_R2(W, g, r2max), ball.y);
#if NR == 1
        pca_ball_framed(XA, Y, Z, W, ranges, co & CELL_MASK, p, bmax, (REAL)0, a, &pb[0], k);
#else
        REALV sc[NR], sw[NR], sx[NR], sy[NR], sz[NR];
        REALV sxx[NR], sxy[NR], sxz[NR], syy[NR], syz[NR], szz[NR];
        for (int j = 0; j < NR; ++j) {
            sc[j] = sw[j] = sx[j] = sy[j] = sz[j] = 0;
            sxx[j] = sxy[j] = sxz[j] = syy[j] = syz[j] = szz[j] = 0;
        }
        REALV dx, dy, dz, d2, ex, ey, ez;
        int ax = 2;
        REAL2 fs = (REAL2)(0);
#if PCA_ANCHOR
        PCA_FRAME(a, ax, fs)
#endif
        PCA_BY_AXIS(ax, FEATURES_WALK)
        for (int j = 0; j < NR; ++j) {
            pca_store_sums(sc[j], sw[j], sx[j], sy[j], sz[j], sxx[j], sxy[j], sxz[j], syy[j],
                           syz[j], szz[j], &pb[j], k);
#if PCA_ANCHOR
            PCA_KEEP_FRAME(&pb[j], k, ax, fs, a)
#endif
        }
#endif
    }
#ifdef VW2
    /* the balls' eigen solves two at a time, in VW2 lanes: the solve is a chain of dependent
       operations that VW lanes leave mostly idle (tests/test_eig3_vector.py: the same
       results at every width); three balls' kernel ~5 ms faster at 1M points */
    int j0 = 0;
    for (; j0 + 1 < NR; j0 += 2) pca_decompose_pair(&pb[j0], &pb[j0 + 1]);
    for (; j0 < NR; ++j0) pca_decompose(&pb[j0]);
#else
    for (int j = 0; j < NR; ++j) pca_decompose(&pb[j]);
#endif
#if PCA_ANCHOR
    for (int j = 0; j < NR; ++j) pca_anchor_l0(&pb[j]);
#endif
}

/* lambda0 of the balls of sorted point g (lane k) whose status is OK and whose anchored
 * lambda0 is missing (pca.h: NaN), one second walk (pca_refine_l0's sums, ball by ball). */
inline void features_refine(__global const REAL *X, __global const REAL *Y,
                            __global const REAL *Z, __global const REAL *W,
                            __global const uint *cell_of, __global const uint2 *ranges, uint n,
                            uint g, uint k, REAL2 ball, const REAL r2[NR],
                            const pca_batch_t pb[NR], const uchar st[NR], REAL l0[NR])
{
    const uint co = cell_of[g];
    __global const REAL *XA = x_rows(X, co, n);
    const REAL3 p = (REAL3)(XA[g], Y[g], Z[g]);
    REAL3 v0[NR];
    REAL h0[NR];
    REALV s0[NR];
    for (int j = 0; j < NR; ++j) {
        v0[j] = (REAL3)(pb[j].v0x[k], pb[j].v0y[k], pb[j].v0z[k]);
        h0[j] = dot((REAL3)(pb[j].mux[k], pb[j].muy[k], pb[j].muz[k]), v0[j]);
        s0[j] = 0;
    }
    REAL r2max = r2[0];
    for (int j = 1; j < NR; ++j) r2max = fmax(r2max, r2[j]);
    const REAL2 bmax = (REAL2)(BALL_R2(W, g, r2max), ball.y);
    REALV dx, dy, dz, d2;
    NEIGHBOR_CHUNKS_BEGIN(ranges, co & CELL_MASK, p, ball, i, end, pr)
        const IREALV mmax = chunk_offsets_d2(XA, Y, Z, i, end, pr, bmax, &dx, &dy, &dz, &d2);
        for (int j = 0; j < NR; ++j) {
            const IREALV m = NR == 1 ? mmax
                             : ball_mask(mmax, d2, BALL_R2(W, g, r2[j]));
            PCA_REFINE_ACCUMULATE(s0[j], W, i, dx, dy, dz, m, v0[j], h0[j])
        }
    NEIGHBOR_CHUNKS_END
    for (int j = 0; j < NR; ++j)
        if (st[j] == ST_OK && isnan(l0[j])) l0[j] = hsum(s0[j]) * pb[j].iw[k];
}

/* x ln x, 0 at 0 (its limit) */
inline REALV xlogx(REALV x)
{
    return select((REALV)0, x * ln_pos(x), isgreater(x, (REALV)0));
}

/* record column c of the lanes: the feature's value where the status is OK, NaN elsewhere */
#define FEATURE_COLUMN(c, expr) col[c] = select((REALV)(NAN), (expr), ok);

/* One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the sums of
 * the NR balls of each point in one walk, the VW x NR eigen decompositions in the vector
 * lanes, the lambda0 refinement per point, then for each radius the features of the VW
 * points at once in the vector lanes (log, cbrt, divisions: a scalar evaluation per point
 * cost more than the walks) and their records from those columns (lanes_records.h). */
__kernel void features(OPERATOR_ARGS, const REAL4 r2s, __global REAL *out1,
                       __global REAL *out2, __global REAL *out3)
{
    const uint g0 = first + get_global_id(0) * VW;
    if (g0 >= stop) return;
    const uint kn = min((uint)VW, stop - g0);
    const uint ddof = (uint)par.z;
    const REAL all_r2[4] = {r2s.x, r2s.y, r2s.z, r2s.w};
    REAL r2[NR];
    for (int j = 0; j < NR; ++j) r2[j] = all_r2[j];
    pca_batch_t pb[NR];
    features_pca(X, Y, Z, W, CN, cell_of, ranges, n, g0, kn, ball, r2, pb);
    /* the balls' status (the VW lanes at once) and lambda0 */
    REAL l0[NR][VW];
    REALV stv[NR];
    IREALV again = 0;                       /* lanes with a ball for the second walk */
    for (int j = 0; j < NR; ++j) {
        stv[j] = pca_status_v(&pb[j], kn, MIN_COUNT);
#if PCA_ANCHOR
        const REALV l0v = VLOADV(0, pb[j].l0a);   /* anchored (pca.h), NaN: the second walk */
#else
        const REALV l0v = VLOADV(0, pb[j].l0);
#endif
        VSTOREV(l0v, 0, l0[j]);
        again |= isequal(stv[j], (REALV)ST_OK) & isnan(l0v);
    }
#if REFINE_L0
    /* the second walk only for the points that need it (~0.1% on a smooth surface): its
       set-up for every point cost ~2 ms of the 1M-point kernel (86 ms), and the status
       point by point ~2.5 ms more (scalar tests and branches) */
    if (any_lane(again)) {
        IREAL ag[VW];
        REAL stl[NR][VW];
        CAT(vstore, VW)(again, 0, ag);
        for (int j = 0; j < NR; ++j) VSTOREV(stv[j], 0, stl[j]);
        for (uint k = 0; k < kn; ++k) {
            if (!ag[k]) continue;
            REAL l0k[NR];
            uchar stk[NR];
            for (int j = 0; j < NR; ++j) {
                stk[j] = (uchar)stl[j][k];
                l0k[j] = l0[j][k];
            }
            features_refine(X, Y, Z, W, cell_of, ranges, n, g0 + k, k, ball, r2, pb, stk, l0k);
            for (int j = 0; j < NR; ++j) l0[j][k] = l0k[j];
        }
    }
#endif
    for (int j = 0; j < NR; ++j) {
        /* the VW lanes' eigenvalues (descending, scaled by n / (n - ddof)), e1, e3 */
        const REALV cnt = CAT(convert_, REALV)(CAT(vload, VW)(0, pb[j].count));
        const REALV sv = select((REALV)1, cnt / (cnt - (REAL)ddof),
                                isgreater(cnt, (REALV)(REAL)ddof));
        const REALV L1 = VLOADV(0, pb[j].l2) * sv, L2 = VLOADV(0, pb[j].l1) * sv;
        const REALV L3 = VLOADV(0, l0[j]) * sv;
        const REALV e1x = VLOADV(0, pb[j].v2x), e1y = VLOADV(0, pb[j].v2y);
        const REALV e1z = VLOADV(0, pb[j].v2z);
        const REALV e3x = VLOADV(0, pb[j].v0x), e3y = VLOADV(0, pb[j].v0y);
        const REALV e3z = VLOADV(0, pb[j].v0z);
        /* summed as moments.cl does (l0 + l1 + l2): surface_variation is its variation */
        const REALV sum = L3 + L2 + L1, i1 = (REAL)1 / L1, isum = (REAL)1 / sum;
        (void)sum; (void)i1; (void)isum; (void)e1x; (void)e1y; (void)e1z; (void)e3x;
        (void)e3y;
        const REALV stf = stv[j];
        const IREALV ok = (stf == (REALV)ST_OK);
        REALV col[16];                      /* the record columns (lanes_records.h) */
        col[CIX_COUNT] = LANES_COUNT(pb[j].count);
        col[CIX_STATUS] = stf;
#ifdef CIX_EIGENVALUE_SUM
        FEATURE_COLUMN(CIX_EIGENVALUE_SUM, sum)
#endif
#ifdef CIX_OMNIVARIANCE
        /* one cube root: of the ratios' product, which cannot overflow */
        FEATURE_COLUMN(CIX_OMNIVARIANCE, L1 * cbrt_pos((L2 * i1) * (L3 * i1)))
#endif
#ifdef CIX_EIGENENTROPY
        FEATURE_COLUMN(CIX_EIGENENTROPY, -(xlogx(L1) + xlogx(L2) + xlogx(L3)))
#endif
#ifdef CIX_ANISOTROPY
        FEATURE_COLUMN(CIX_ANISOTROPY, (L1 - L3) * i1)
#endif
#ifdef CIX_PLANARITY
        FEATURE_COLUMN(CIX_PLANARITY, (L2 - L3) * i1)
#endif
#ifdef CIX_LINEARITY
        FEATURE_COLUMN(CIX_LINEARITY, (L1 - L2) * i1)
#endif
#ifdef CIX_PCA1
        FEATURE_COLUMN(CIX_PCA1, L1 * isum)
#endif
#ifdef CIX_PCA2
        FEATURE_COLUMN(CIX_PCA2, L2 * isum)
#endif
#ifdef CIX_SURFACE_VARIATION
        FEATURE_COLUMN(CIX_SURFACE_VARIATION, L3 / sum)  /* bit for bit the variation of moments.cl */
#endif
#ifdef CIX_SPHERICITY
        FEATURE_COLUMN(CIX_SPHERICITY, L3 * i1)
#endif
#ifdef CIX_VERTICALITY
        FEATURE_COLUMN(CIX_VERTICALITY, 1 - fabs(e3z))
#endif
#ifdef CIX_GUINARD_VERTICALITY
        {
            /* e2 = e3 x e1 / |.|; u = L1 |e1| + L2 |e2| + L3 |e3|; |u_z| / |u| */
            REALV e2x = e3y * e1z - e3z * e1y, e2y = e3z * e1x - e3x * e1z;
            REALV e2z = e3x * e1y - e3y * e1x;
            const REALV ie2 = rsqrt(e2x * e2x + e2y * e2y + e2z * e2z);
            e2x *= ie2; e2y *= ie2; e2z *= ie2;
            const REALV ux = L1 * fabs(e1x) + L2 * fabs(e2x) + L3 * fabs(e3x);
            const REALV uy = L1 * fabs(e1y) + L2 * fabs(e2y) + L3 * fabs(e3y);
            const REALV uz = L1 * fabs(e1z) + L2 * fabs(e2z) + L3 * fabs(e3z);
            FEATURE_COLUMN(CIX_GUINARD_VERTICALITY, uz * rsqrt(ux * ux + uy * uy + uz * uz))
        }
#endif
#ifdef CIX_EIGENVALUE1
        FEATURE_COLUMN(CIX_EIGENVALUE1, L1)
#endif
#ifdef CIX_EIGENVALUE2
        FEATURE_COLUMN(CIX_EIGENVALUE2, L2)
#endif
#ifdef CIX_EIGENVALUE3
        FEATURE_COLUMN(CIX_EIGENVALUE3, L3)
#endif
#ifdef CIX_DENSITY
        {
            REAL rr[VW];
            for (uint k = 0; k < VW; ++k) rr[k] = k < kn ? BALL_R2(W, g0 + k, r2[j]) : (REAL)1;
            const REALV r2v = VLOADV(0, rr);
            FEATURE_COLUMN(CIX_DENSITY, cnt / (FOUR_THIRDS_PI * r2v * sqrt(r2v)))
        }
#endif
#ifdef CIX_NORMALS
        FEATURE_COLUMN(CIX_NORMALS, e3x)
        FEATURE_COLUMN(CIX_NORMALS + 1, e3y)
        FEATURE_COLUMN(CIX_NORMALS + 2, e3z)
#endif
#if REC_BALLS
        {
            /* the NR balls' records in out, in blocks (common.h: REC_IN_BLOCKS): a point's
               NR scattered lines land close together */
            REAL t_[16][VW];
            REC_STAGE_LANES(col, t_, REC_USED)
            for (uint k = 0; k < kn; ++k) {
                const uint i = REC_INDEX(g0 + k);
                REC_EMIT(t_, k, REC_USED, REC_IN_BLOCKS(i / REC_BLOCK, i % REC_BLOCK, j, NR),
                         out)
            }
        }
#else
        __global REAL *o = j == 0 ? out : j == 1 ? out1 : j == 2 ? out2 : out3;
        REC_STORE_LANES(col, kn, g0, o, REC_USED)
#endif
    }
}
