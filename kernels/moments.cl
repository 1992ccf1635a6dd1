/* moments.cl -- neighbour counts and the PCA moments of the ball N_r(p) around each point.
 *
 * One work-item per sorted point. Offsets are taken relative to the query point p, so the
 * sums are small numbers and large coordinates do not matter. Outputs are scattered to the
 * input order through `order`.
 *
 * Build options: DENSITY (0|1) weights w(q) = 1/#N_r(q) read from W;
 *                REFINE_L0 (0|1) second pass giving lambda0 = sum w <q - o, v0>^2 / sum w
 *                directly (float32 otherwise loses ~2 digits of lambda0 on smooth surfaces).
 */
#include "common.h"
#include "neighbors.h"
#include "eig3.h"

#ifndef DENSITY
#define DENSITY 0
#endif
#ifndef REFINE_L0
#define REFINE_L0 1
#endif
#if REAL_IS_DOUBLE
#define DEGENERATE_RATIO 1e-10
#else
#define DEGENERATE_RATIO 1e-5f
#endif

/* #N_r(p) for every sorted point, and the density weight 1 / #N_r(p). */
__kernel void count_neighbors(__global const REAL *X, __global const REAL *Y,
                              __global const REAL *Z, __global const uint *cell_of,
                              __global const uint2 *ranges, const uint n, const REAL r2,
                              __global uint *count, __global REAL *weight)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const REAL3 p = (REAL3)(X[g], Y[g], Z[g]);
    REALV cnt = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell_of[g], i, end)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
        cnt += select((REALV)0, (REALV)1, m);
    NEIGHBOR_CHUNKS_END
    const uint c = (uint)hsum(cnt);
    count[g] = c;
    weight[g] = (REAL)1 / (REAL)c;
}

#if DENSITY
#define CHUNK_WEIGHT(i) VLOADV(0, W + (i))
#else
#define CHUNK_WEIGHT(i) ((REALV)1)
#endif

inline void store3(__global REAL *a, size_t j, REAL3 v)
{
    a[3 * j] = v.x; a[3 * j + 1] = v.y; a[3 * j + 2] = v.z;
}

/* Per point: count, PCA normal v0 (unoriented), ascending eigenvalues of the weighted
 * covariance, surface variation l0/(l0+l1+l2), barycenter shift o - p, status. */
__kernel void moments(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const uint *cell_of,
                      __global const uint2 *ranges, __global const uint *order,
                      const uint n, const REAL r2,
                      __global uint *count, __global uchar *status,
                      __global REAL *normal, __global REAL *eigval,
                      __global REAL *variation, __global REAL *shift)
{
    const uint g = get_global_id(0);
    if (g >= n) return;
    const REAL3 p = (REAL3)(X[g], Y[g], Z[g]);
    const uint cell = cell_of[g];
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
        const REALV w = select((REALV)0, CHUNK_WEIGHT(i), m);
        sc += select((REALV)0, (REALV)1, m);
        const REALV wx = w * dx, wy = w * dy, wz = w * dz;
        sw += w; sx += wx; sy += wy; sz += wz;
        sxx += wx * dx; sxy += wx * dy; sxz += wx * dz;
        syy += wy * dy; syz += wy * dz; szz += wz * dz;
    NEIGHBOR_CHUNKS_END
    const uint c = (uint)hsum(sc);
    const REAL iw = (REAL)1 / hsum(sw);
    const REAL3 mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw;   /* o - p */
    const REAL cxx = hsum(sxx) * iw - mu.x * mu.x, cxy = hsum(sxy) * iw - mu.x * mu.y;
    const REAL cxz = hsum(sxz) * iw - mu.x * mu.z, cyy = hsum(syy) * iw - mu.y * mu.y;
    const REAL cyz = hsum(syz) * iw - mu.y * mu.z, czz = hsum(szz) * iw - mu.z * mu.z;
    REAL3 lam, v0, v1, v2;
    eig3_sym(cxx, cxy, cxz, cyy, cyz, czz, &lam, &v0, &v1, &v2);
    lam = fmax(lam, (REAL3)0);
    uchar st = ST_OK;
    if (c < 3) st = ST_TOO_FEW;
    else if (!(lam.z > 0) || lam.y <= DEGENERATE_RATIO * lam.z) st = ST_DEGENERATE;
#if REFINE_L0
    if (st == ST_OK) {
        REALV s0 = 0;
        NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
            const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
            const REALV h = (dx - mu.x) * v0.x + (dy - mu.y) * v0.y + (dz - mu.z) * v0.z;
            s0 += select((REALV)0, CHUNK_WEIGHT(i), m) * h * h;
        NEIGHBOR_CHUNKS_END
        lam.x = hsum(s0) * iw;
    }
#endif
    const size_t j = order[g];
    count[j] = c;
    status[j] = st;
    if (st != ST_OK) {
        const REAL nan3 = NAN;
        store3(normal, j, (REAL3)nan3); store3(eigval, j, (REAL3)nan3);
        store3(shift, j, (REAL3)nan3); variation[j] = nan3;
        return;
    }
    store3(normal, j, v0);
    store3(eigval, j, lam);
    store3(shift, j, mu);
    variation[j] = lam.x / (lam.x + lam.y + lam.z);
}
