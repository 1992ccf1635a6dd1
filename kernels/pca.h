/* pca.h -- weighted PCA of the ball N_r(p), shared by every kernel that needs it.
 *
 *   pca_ball   the sums of one point, one fixed-order pass relative to p (weights.h decides
 *              the weights): count, 1/sum w, mu = o - p and the centred covariance;
 *   pca_batch  pca_ball for the VW consecutive sorted points g0 .. g0 + kn - 1 of one
 *              work-item, then their VW covariances decomposed at once by eig3_sym_v (a
 *              scalar eig3 per point costs more than the neighbour loops together);
 *   pca_refine_l0  lambda0 from a second pass (float32 one-pass moments lose ~2 digits);
 *   PCA_ACCUMULATE, pca_store_sums, pca_decompose, PCA_REFINE_ACCUMULATE  their steps, which
 *              the multi-radius walk of features.cl uses too (bit-identical sums).
 */
#ifndef CLCURV_PCA_H
#define CLCURV_PCA_H
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "eig3.h"
#include "radius.h"

#if REAL_IS_DOUBLE
#define DEGENERATE_RATIO 1e-10
#else
#define DEGENERATE_RATIO 1e-5f
#endif

/* PCA of VW consecutive points, lane k for point g0 + k (k < kn). */
typedef struct {
    uint count[VW];
    REAL iw[VW], mux[VW], muy[VW], muz[VW];
    REAL l0[VW], l1[VW], l2[VW];     /* ascending, clamped at 0 */
    REAL v0x[VW], v0y[VW], v0z[VW];  /* eigenvector of l0: the unoriented PCA normal */
    REAL v2x[VW], v2y[VW], v2z[VW];  /* eigenvector of l2 (the largest) */
    REAL c[6][VW];                   /* centred covariance xx xy xz yy yz zz */
} pca_batch_t;

/* One chunk's contribution to the weighted sums of a ball (w: chunk_weights, m: the ball's
 * lane mask): count (with DENSITY or GAUSSIAN only), sum w, sum w d, sum w d d^T. Shared by
 * pca_ball and the multi-radius walk of features.cl, so that their sums are the same
 * operations in the same order (bit-identical results). */
#if DENSITY || GAUSSIAN
#define PCA_COUNT(sc, m) sc += select((REALV)0, (REALV)1, m);
#else
#define PCA_COUNT(sc, m)
#endif
#define PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    {                                                                                      \
        PCA_COUNT(sc, m)                                                                   \
        const REALV wx_ = (w) * (dx), wy_ = (w) * (dy), wz_ = (w) * (dz);                 \
        sw += (w); sx += wx_; sy += wy_; sz += wz_;                                        \
        sxx += wx_ * (dx); sxy += wx_ * (dy); sxz += wx_ * (dz);                           \
        syy += wy_ * (dy); syz += wy_ * (dz); szz += wz_ * (dz);                           \
    }

/* Lane k of b from the sums of PCA_ACCUMULATE: count, 1/sum w, mu = o - p and the centred
 * covariance. */
inline void pca_store_sums(REALV sc, REALV sw, REALV sx, REALV sy, REALV sz, REALV sxx,
                           REALV sxy, REALV sxz, REALV syy, REALV syz, REALV szz,
                           pca_batch_t *b, uint k)
{
    const REAL wsum = hsum(sw);
#if DENSITY || GAUSSIAN
    b->count[k] = (uint)hsum(sc);
#else
    b->count[k] = (uint)wsum;        /* w = 1: the sum of the weights is the count (exact) */
#endif
    const REAL iw = (REAL)1 / wsum;
    const REAL3 mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw;
    b->iw[k] = iw;
    b->mux[k] = mu.x; b->muy[k] = mu.y; b->muz[k] = mu.z;
    b->c[0][k] = hsum(sxx) * iw - mu.x * mu.x;
    b->c[1][k] = hsum(sxy) * iw - mu.x * mu.y;
    b->c[2][k] = hsum(sxz) * iw - mu.x * mu.z;
    b->c[3][k] = hsum(syy) * iw - mu.y * mu.y;
    b->c[4][k] = hsum(syz) * iw - mu.y * mu.z;
    b->c[5][k] = hsum(szz) * iw - mu.z * mu.z;
}

/* The sums of the ball of p into lane k of b: count, 1/sum w, mu = o - p and the centred
 * covariance. (Results go through arrays, not a returned struct: PoCL spills struct
 * copies in the work-item loop at a large cost.) */
inline void pca_ball(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                     __global const REAL *W, __global const uint2 *ranges, uint cell,
                     REAL3 p, REAL2 ball, REAL ih2, pca_batch_t *b, uint k)
{
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);
        PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz)
    NEIGHBOR_CHUNKS_END
    pca_store_sums(sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz, b, k);
}

#define VSTOREV CAT(vstore, VW)

/* The VW covariances of b decomposed at once (eig3_sym_v): eigenvalues clamped at 0, the
 * eigenvectors of the smallest and the largest. */
inline void pca_decompose(pca_batch_t *b)
{
    REALV w0, w1, w2;
    eig3_v3_v e0, e1, e2;
    eig3_sym_v(VLOADV(0, b->c[0]), VLOADV(0, b->c[1]), VLOADV(0, b->c[2]),
               VLOADV(0, b->c[3]), VLOADV(0, b->c[4]), VLOADV(0, b->c[5]),
               &w0, &w1, &w2, &e0, &e1, &e2);
    VSTOREV(fmax(w0, (REALV)0), 0, b->l0);
    VSTOREV(fmax(w1, (REALV)0), 0, b->l1);
    VSTOREV(fmax(w2, (REALV)0), 0, b->l2);
    VSTOREV(e0.x, 0, b->v0x); VSTOREV(e0.y, 0, b->v0y); VSTOREV(e0.z, 0, b->v0z);
    VSTOREV(e2.x, 0, b->v2x); VSTOREV(e2.y, 0, b->v2y); VSTOREV(e2.z, 0, b->v2z);
}


inline void pca_batch(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const uint *cell_of,
                      __global const uint2 *ranges, uint n, uint g0, uint kn, REAL2 ball,
                      REAL ih2,
                      pca_batch_t *b)
{
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            const uint co = cell_of[g];
            __global const REAL *XA = x_rows(X, co, n);
            pca_ball(XA, Y, Z, W, ranges, co & CELL_MASK, (REAL3)(XA[g], Y[g], Z[g]),
                     POINT_BALL(W, g, ball), ih2, b, k);
        } else {                     /* unused lane: the identity */
            for (int e = 0; e < 6; ++e) b->c[e][k] = (REAL)(e == 0 || e == 3 || e == 5);
            b->count[k] = 0;
        }
    }
    pca_decompose(b);
}

/* One chunk's contribution to the lambda0 refinement sum w h^2, h = <q - o, v0> = <q - p,
 * v0> - h0 with h0 = <o - p, v0> (pca_refine_l0; the multi-radius walk of features.cl). */
#if DENSITY
#define PCA_REFINE_ACCUMULATE(s0, W, i, dx, dy, dz, m, v0, h0)                          \
    {                                                                                    \
        const REALV h_ = (dx) * (v0).x + (dy) * (v0).y + (dz) * (v0).z - (h0);          \
        s0 += chunk_weights(W, i, dx, dy, dz, m, (REAL)0) * h_ * h_;                     \
    }
#else
#define PCA_REFINE_ACCUMULATE(s0, W, i, dx, dy, dz, m, v0, h0)                          \
    {                                                                                    \
        const REALV h_ = (dx) * (v0).x + (dy) * (v0).y + (dz) * (v0).z - (h0);          \
        const REALV hm_ = select((REALV)0, h_, m);                                       \
        s0 += hm_ * hm_;                                                                 \
    }
#endif

/* lambda0 = sum w <q - o, v0>^2 / sum w by a second pass over the ball of p (X: p's x copy,
 * x_rows): float32 one-pass moments lose ~2 digits of lambda0 on smooth surfaces. Both
 * terms of h are heights above the tangent plane, small on a smooth surface, so the split
 * costs no accuracy. */
inline REAL pca_refine_l0(__global const REAL *X, __global const REAL *Y,
                          __global const REAL *Z, __global const REAL *W,
                          __global const uint2 *ranges, uint cell, REAL3 p, REAL2 ball,
                          REAL3 v0, REAL3 mu, REAL iw)
{
    const REAL h0 = dot(mu, v0);
    REALV s0 = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        PCA_REFINE_ACCUMULATE(s0, W, i, dx, dy, dz, m, v0, h0)
    NEIGHBOR_CHUNKS_END
    return hsum(s0) * iw;
}

/* Status of lane k: too few neighbours (< min_count) or a covariance of rank < 2. */
inline uchar pca_status(const pca_batch_t *b, uint k, uint min_count)
{
    if (b->count[k] < min_count) return ST_TOO_FEW;
    if (!(b->l2[k] > 0) || b->l1[k] <= DEGENERATE_RATIO * b->l2[k]) return ST_DEGENERATE;
    return ST_OK;
}
#endif
