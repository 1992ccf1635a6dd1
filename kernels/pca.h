/* pca.h -- weighted PCA of the ball N_r(p), shared by every kernel that needs it.
 *
 *   pca_ball   the sums of one point, one fixed-order pass relative to p (weights.h decides
 *              the weights): count, 1/sum w, mu = o - p and the centred covariance;
 *   pca_batch  pca_ball for the VW consecutive sorted points g0 .. g0 + kn - 1 of one
 *              work-item, then their VW covariances decomposed at once by eig3_sym_v (a
 *              scalar eig3 per point costs more than the neighbour loops together).
 */
#ifndef CLCURV_PCA_H
#define CLCURV_PCA_H
#include "common.h"
#include "neighbors.h"
#include "weights.h"
#include "eig3.h"

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
    REAL c[6][VW];                   /* centred covariance xx xy xz yy yz zz */
} pca_batch_t;

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
#if DENSITY || GAUSSIAN
        sc += select((REALV)0, (REALV)1, m);
#endif
        const REALV wx = w * dx, wy = w * dy, wz = w * dz;
        sw += w; sx += wx; sy += wy; sz += wz;
        sxx += wx * dx; sxy += wx * dy; sxz += wx * dz;
        syy += wy * dy; syz += wy * dz; szz += wz * dz;
    NEIGHBOR_CHUNKS_END
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

#define VSTOREV CAT(vstore, VW)

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
            pca_ball(XA, Y, Z, W, ranges, co & CELL_MASK, (REAL3)(XA[g], Y[g], Z[g]), ball, ih2,
                     b, k);
        } else {                     /* unused lane: the identity */
            for (int e = 0; e < 6; ++e) b->c[e][k] = (REAL)(e == 0 || e == 3 || e == 5);
            b->count[k] = 0;
        }
    }
    REALV w0, w1, w2;
    eig3_v3_v e0, e1, e2;
    eig3_sym_v(VLOADV(0, b->c[0]), VLOADV(0, b->c[1]), VLOADV(0, b->c[2]),
               VLOADV(0, b->c[3]), VLOADV(0, b->c[4]), VLOADV(0, b->c[5]),
               &w0, &w1, &w2, &e0, &e1, &e2);
    VSTOREV(fmax(w0, (REALV)0), 0, b->l0);
    VSTOREV(fmax(w1, (REALV)0), 0, b->l1);
    VSTOREV(fmax(w2, (REALV)0), 0, b->l2);
    VSTOREV(e0.x, 0, b->v0x); VSTOREV(e0.y, 0, b->v0y); VSTOREV(e0.z, 0, b->v0z);
}

/* Status of lane k: too few neighbours (< min_count) or a covariance of rank < 2. */
inline uchar pca_status(const pca_batch_t *b, uint k, uint min_count)
{
    if (b->count[k] < min_count) return ST_TOO_FEW;
    if (!(b->l2[k] > 0) || b->l1[k] <= DEGENERATE_RATIO * b->l2[k]) return ST_DEGENERATE;
    return ST_OK;
}
#endif
