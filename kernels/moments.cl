/* moments.cl -- neighbour counts and the PCA moments of the ball N_r(p) around each point.
 *
 * count_neighbors: one work-item per sorted point; moments: one work-item per VW
 * consecutive sorted points (see there). Offsets are taken relative to the query point p,
 * so the sums are small numbers and large coordinates do not matter. Outputs are
 * scattered to the input order through `order`.
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

/* Neighbour sums of the query point p (in cell `cell`): count c, 1 / sum w, mu = o - p and
   the centred weighted covariance cov = (xx, xy, xz, yy, yz, zz). */
inline void point_moments(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                          __global const REAL *W, __global const uint2 *ranges, uint cell,
                          REAL3 p, REAL r2, uint *c, REAL *iw_out, REAL3 *mu_out, REAL *cov)
{
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, i, end)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
        const REALV w = select((REALV)0, CHUNK_WEIGHT(i), m);
#if DENSITY
        sc += select((REALV)0, (REALV)1, m);
#endif
        const REALV wx = w * dx, wy = w * dy, wz = w * dz;
        sw += w; sx += wx; sy += wy; sz += wz;
        sxx += wx * dx; sxy += wx * dy; sxz += wx * dz;
        syy += wy * dy; syz += wy * dz; szz += wz * dz;
    NEIGHBOR_CHUNKS_END
    const REAL w_sum = hsum(sw);
#if DENSITY
    *c = (uint)hsum(sc);
#else
    *c = (uint)w_sum;                 /* w = 1: the sum of the weights is the count (exact) */
#endif
    const REAL iw = (REAL)1 / w_sum;
    const REAL3 mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw;   /* o - p */
    *iw_out = iw;
    *mu_out = mu;
    cov[0] = hsum(sxx) * iw - mu.x * mu.x; cov[1] = hsum(sxy) * iw - mu.x * mu.y;
    cov[2] = hsum(sxz) * iw - mu.x * mu.z; cov[3] = hsum(syy) * iw - mu.y * mu.y;
    cov[4] = hsum(syz) * iw - mu.y * mu.z; cov[5] = hsum(szz) * iw - mu.z * mu.z;
}

#define VSTOREV CAT(vstore, VW)

/* Per point: count, PCA normal v0 (unoriented), ascending eigenvalues of the weighted
 * covariance, surface variation l0/(l0+l1+l2), barycenter shift o - p, status.
 *
 * One work-item per VW consecutive sorted points (global size >= ceil(n / VW)): the
 * neighbour sums of the VW points are computed one after the other, then their VW
 * covariances are decomposed at once by eig3_sym_v (one per vector lane: a scalar
 * eig3_sym per point cost more than all the neighbour loops together), then the lambda0
 * refinement and the stores run per point again. */
__kernel void moments(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const uint *cell_of,
                      __global const uint2 *ranges, __global const uint *order,
                      const uint n, const REAL r2,
                      __global uint *count, __global uchar *status,
                      __global REAL *normal, __global REAL *eigval,
                      __global REAL *variation, __global REAL *shift)
{
    const uint g0 = get_global_id(0) * VW;
    if (g0 >= n) return;
    const uint kn = min((uint)VW, n - g0);       /* points of this work-item */

    /* 1. neighbour sums, point by point, into lane k of the staging arrays */
    REAL cov[6][VW], iws[VW], mux[VW], muy[VW], muz[VW];
    uint cs[VW];
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            REAL c6[6];
            REAL3 mu;
            point_moments(X, Y, Z, W, ranges, cell_of[g], (REAL3)(X[g], Y[g], Z[g]), r2,
                          &cs[k], &iws[k], &mu, c6);
            for (int e = 0; e < 6; ++e) cov[e][k] = c6[e];
            mux[k] = mu.x; muy[k] = mu.y; muz[k] = mu.z;
        } else {                                  /* unused lane: the identity */
            for (int e = 0; e < 6; ++e) cov[e][k] = (REAL)(e == 0 || e == 3 || e == 5);
        }
    }

    /* 2. VW eigen decompositions at once */
    REALV w0, w1, w2;
    eig3_v3_v e0, e1, e2;
    eig3_sym_v(VLOADV(0, cov[0]), VLOADV(0, cov[1]), VLOADV(0, cov[2]),
               VLOADV(0, cov[3]), VLOADV(0, cov[4]), VLOADV(0, cov[5]),
               &w0, &w1, &w2, &e0, &e1, &e2);
    REAL l0s[VW], l1s[VW], l2s[VW], nx[VW], ny[VW], nz[VW];
    VSTOREV(fmax(w0, (REALV)0), 0, l0s);
    VSTOREV(fmax(w1, (REALV)0), 0, l1s);
    VSTOREV(fmax(w2, (REALV)0), 0, l2s);
    VSTOREV(e0.x, 0, nx); VSTOREV(e0.y, 0, ny); VSTOREV(e0.z, 0, nz);

    /* 3. per point: status, lambda0 refinement, stores */
    for (uint k = 0; k < kn; ++k) {
        const uint g = g0 + k;
        const uint c = cs[k];
        REAL3 lam = (REAL3)(l0s[k], l1s[k], l2s[k]);
        const REAL3 v0 = (REAL3)(nx[k], ny[k], nz[k]);
        const REAL3 mu = (REAL3)(mux[k], muy[k], muz[k]);
        uchar st = ST_OK;
        if (c < 3) st = ST_TOO_FEW;
        else if (!(lam.z > 0) || lam.y <= DEGENERATE_RATIO * lam.z) st = ST_DEGENERATE;
#if REFINE_L0
        if (st == ST_OK) {
            const REAL3 p = (REAL3)(X[g], Y[g], Z[g]);
            /* h = <q - o, v0> = <q - p, v0> - <o - p, v0>: both terms are heights above the
               tangent plane, small on a smooth surface, so the split costs no accuracy */
            const REAL h0 = dot(mu, v0);
            REALV s0 = 0;
            REALV dx, dy, dz;
            NEIGHBOR_CHUNKS_BEGIN(ranges, cell_of[g], i, end)
                const IREALV m = chunk_offsets(X, Y, Z, i, end, p, r2, &dx, &dy, &dz);
                const REALV h = dx * v0.x + dy * v0.y + dz * v0.z - h0;
#if DENSITY
                s0 += select((REALV)0, CHUNK_WEIGHT(i), m) * h * h;
#else
                const REALV hm = select((REALV)0, h, m);
                s0 += hm * hm;
#endif
            NEIGHBOR_CHUNKS_END
            lam.x = hsum(s0) * iws[k];
        }
#endif
        const size_t j = order[g];
        count[j] = c;
        status[j] = st;
        if (st != ST_OK) {
            const REAL nan3 = NAN;
            store3(normal, j, (REAL3)nan3); store3(eigval, j, (REAL3)nan3);
            store3(shift, j, (REAL3)nan3); variation[j] = nan3;
            continue;
        }
        store3(normal, j, v0);
        store3(eigval, j, lam);
        store3(shift, j, mu);
        variation[j] = lam.x / (lam.x + lam.y + lam.z);
    }
}
