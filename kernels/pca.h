/* pca.h -- weighted PCA of the ball N_r(p): count, barycenter shift mu = o - p and the
 * centred covariance, accumulated in one fixed-order pass relative to p (weights.h decides
 * the weights). Used by every kernel that needs the PCA frame before its own pass. */
#ifndef CLCURV_PCA_H
#define CLCURV_PCA_H
#include "common.h"
#include "neighbors.h"
#include "weights.h"

typedef struct {
    uint count;
    REAL wsum;
    REAL3 mu;                        /* o - p */
    REAL cxx, cxy, cxz, cyy, cyz, czz;
} pca_t;

inline pca_t pca_ball(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const uint2 *ranges, uint cell,
                      REAL3 p, REAL r2, REAL ih2)
{
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);
        sc += select((REALV)0, (REALV)1, m);
        const REALV wx = w * dx, wy = w * dy, wz = w * dz;
        sw += w; sx += wx; sy += wy; sz += wz;
        sxx += wx * dx; sxy += wx * dy; sxz += wx * dz;
        syy += wy * dy; syz += wy * dz; szz += wz * dz;
    NEIGHBOR_CHUNKS_END
    pca_t r;
    r.count = (uint)hsum(sc);
    r.wsum = hsum(sw);
    const REAL iw = (REAL)1 / r.wsum;
    r.mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw;
    r.cxx = hsum(sxx) * iw - r.mu.x * r.mu.x;
    r.cxy = hsum(sxy) * iw - r.mu.x * r.mu.y;
    r.cxz = hsum(sxz) * iw - r.mu.x * r.mu.z;
    r.cyy = hsum(syy) * iw - r.mu.y * r.mu.y;
    r.cyz = hsum(syz) * iw - r.mu.y * r.mu.z;
    r.czz = hsum(szz) * iw - r.mu.z * r.mu.z;
    return r;
}
#endif
