/* pca.h -- weighted PCA of the ball N_r(p), shared by every kernel that needs it.
 *
 *   pca_ball   the sums of one point, one fixed-order pass relative to p (weights.h decides
 *              the weights): count, 1/sum w, mu = o - p and the centred covariance;
 *   pca_batch  pca_ball for the VW consecutive sorted points g0 .. g0 + kn - 1 of one
 *              work-item, then their VW covariances decomposed at once by eig3_sym_v (a
 *              scalar eig3 per point costs more than the neighbour loops together);
 *   pca_refine_l0  lambda0 from a second pass (float32 one-pass moments lose ~2 digits);
 *   PCA_ANCHOR (on when the kernel is built with REFINE_L0=1)  lambda0 without the second
 *              pass: the walk sums the offsets in the anchor frame, reflected (Householder)
 *              so that the anchor a (the PCA normal of the query's cell, anchor.cl) is the
 *              z axis; the heights above the anchor plane are then a coordinate of their
 *              own whose small sums keep their digits, and pca_anchor_l0 evaluates
 *              <v0, C v0> there before it reflects v0, v2 and mu back; lanes whose anchor
 *              is too far from v0 (or missing) are marked for the second pass;
 *   PCA_REFLECT, PCA_ACCUMULATE, pca_store_sums, pca_decompose, PCA_REFINE_ACCUMULATE
 *              their steps, which the multi-radius walk of features.cl uses too
 *              (bit-identical sums).
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

#if defined(REFINE_L0) && REFINE_L0
#define PCA_ANCHOR 1
#else
#define PCA_ANCHOR 0
#endif
/* sin^2 of the largest angle between the anchor and v0 for which the anchored lambda0 is
 * used (its error grows as sin^2; the second pass runs beyond) */
#ifndef ANCHOR_SIN2
#define ANCHOR_SIN2 1e-2
#endif

/* PCA of VW consecutive points, lane k for point g0 + k (k < kn). */
typedef struct {
    uint count[VW];
    REAL iw[VW], mux[VW], muy[VW], muz[VW];
    REAL l0[VW], l1[VW], l2[VW];     /* ascending, clamped at 0 */
    REAL v0x[VW], v0y[VW], v0z[VW];  /* eigenvector of l0: the unoriented PCA normal */
    REAL v2x[VW], v2y[VW], v2z[VW];  /* eigenvector of l2 (the largest) */
    REAL c[6][VW];                   /* centred covariance xx xy xz yy yz zz (with
                                        PCA_ANCHOR: in the lane's anchor frame) */
#if PCA_ANCHOR
    REAL fu[3][VW], fw[3][VW];       /* the anchor frame's u and w (PCA_FRAME; 0: none) */
    REAL l0a[VW];                    /* anchored lambda0, NaN: take the second pass */
#endif
} pca_batch_t;

/* One chunk's contribution to the weighted sums of a ball (w: chunk_weights, m: the ball's
 * lane mask): count (with DENSITY or GAUSSIAN only), sum w, sum w d, sum w d d^T. Shared by
 * pca_ball and the multi-radius walk of features.cl, so that their sums are the same
 * operations in the same order (bit-identical results). */
#if DENSITY || GAUSSIAN
#define PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    {                                                                                      \
        sc += select((REALV)0, (REALV)1, m);                                               \
        const REALV wx_ = (w) * (dx), wy_ = (w) * (dy), wz_ = (w) * (dz);                 \
        sw += (w); sx += wx_; sy += wy_; sz += wz_;                                        \
        sxx += wx_ * (dx); sxy += wx_ * (dy); sxz += wx_ * (dz);                           \
        syy += wy_ * (dy); syz += wy_ * (dz); szz += wz_ * (dz);                           \
    }
#else
/* Uniform weights: each sum a masked update of the ball's lanes (weights.h: MASKED_ADD) */
#define PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    {                                                                                      \
        MASKED_ADD(sw, m, (REAL)1) MASKED_ADD(sx, m, dx) MASKED_ADD(sy, m, dy)             \
        MASKED_ADD(sz, m, dz) MASKED_ADD(sxx, m, (dx) * (dx))                              \
        MASKED_ADD(sxy, m, (dx) * (dy)) MASKED_ADD(sxz, m, (dx) * (dz))                    \
        MASKED_ADD(syy, m, (dy) * (dy)) MASKED_ADD(syz, m, (dy) * (dz))                    \
        MASKED_ADD(szz, m, (dz) * (dz))                                                    \
    }
#endif

/* The anchor frame (PCA_ANCHOR): the Householder reflection H = I - u w^T, w = 2 u / |u|^2,
 * u = a + sign(a_z) e_z, maps the anchor normal a to -sign(a_z) e_z (no cancellation in u:
 * |u|^2 >= 2 for a unit a). H is symmetric and its own inverse: H v = v - <w, v> u both
 * ways. A missing anchor (a = 0) gives u = w = 0, the identity. In that frame the heights
 * above the anchor plane are the z offsets: their sums, small numbers, keep the digits that
 * lambda0 needs (pca_anchor_l0), at 6 operations per chunk (the former separate height sums
 * cost 9 and 5 more accumulators). */
#define PCA_FRAME(a, u, w)                                                               \
    {                                                                                    \
        const REAL3 u_ = (REAL3)((a).x, (a).y, (a).z + ((a).z < 0 ? (REAL)-1 : (REAL)1)); \
        const int has_ = (a).x != 0 || (a).y != 0 || (a).z != 0;                         \
        u = has_ ? u_ : (REAL3)(0);                                                      \
        w = has_ ? u_ * ((REAL)2 / dot(u_, u_)) : (REAL3)(0);                            \
    }
/* Lane k of b keeps the frame (u, w) for pca_anchor_l0 */
#define PCA_KEEP_FRAME(b, k, u, w)                                                       \
    {                                                                                    \
        (b)->fu[0][k] = (u).x; (b)->fu[1][k] = (u).y; (b)->fu[2][k] = (u).z;             \
        (b)->fw[0][k] = (w).x; (b)->fw[1][k] = (w).y; (b)->fw[2][k] = (w).z;             \
    }
/* (ex, ey, ez) = H (dx, dy, dz) for a chunk's offsets */
#define PCA_REFLECT(u, w, dx, dy, dz, ex, ey, ez)                                        \
    {                                                                                    \
        const REALV t_ = (dx) * (w).x + (dy) * (w).y + (dz) * (w).z;                     \
        ex = (dx) - t_ * (u).x; ey = (dy) - t_ * (u).y; ez = (dz) - t_ * (u).z;          \
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
 * covariance (with PCA_ANCHOR in the frame of the anchor a, PCA_FRAME, kept in b).
 * (Results go through arrays, not a returned struct: PoCL spills struct copies in the
 * work-item loop at a large cost.) */
inline void pca_ball(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                     __global const REAL *W, __global const uint2 *ranges, uint cell,
                     REAL3 p, REAL2 ball, REAL ih2, REAL3 a, pca_batch_t *b, uint k)
{
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
#if PCA_ANCHOR
    REAL3 fu, fw;
    PCA_FRAME(a, fu, fw)
#endif
    REALV dx, dy, dz;
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);
#if PCA_ANCHOR
        PCA_REFLECT(fu, fw, dx, dy, dz, dx, dy, dz)
#endif
        PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz)
    NEIGHBOR_CHUNKS_END
    pca_store_sums(sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz, b, k);
#if PCA_ANCHOR
    PCA_KEEP_FRAME(b, k, fu, fw)
#endif
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

#if PCA_ANCHOR
/* The anchored lambda0 of every lane (after pca_decompose, in the anchor frame of
 * PCA_FRAME, where the anchor is the z axis), then v0, v2 and mu reflected back to the
 * cloud's frame. With v0 = (vx, vy, vz) in that frame,
 *     <v0, C v0> = vz^2 C_zz + 2 vz (vx C_xz + vy C_yz) + <u, C u>,  u = (vx, vy, 0),
 * the first two terms from the sums of the heights (small numbers, full relative precision),
 * only the last from the tangential sums, whose rounding it scales by |u|^2 = sin^2 of the
 * angle between the anchor and v0. Lanes with |u|^2 > ANCHOR_SIN2, or without an anchor,
 * get NaN, the mark for the second pass. */
inline void pca_anchor_l0(pca_batch_t *b)
{
    const REALV vx = VLOADV(0, b->v0x), vy = VLOADV(0, b->v0y), vz = VLOADV(0, b->v0z);
    const REALV c0 = VLOADV(0, b->c[0]), c1 = VLOADV(0, b->c[1]), c2 = VLOADV(0, b->c[2]);
    const REALV c3 = VLOADV(0, b->c[3]), c4 = VLOADV(0, b->c[4]), c5 = VLOADV(0, b->c[5]);
    const REALV ucu = vx * (c0 * vx + (REAL)2 * c1 * vy) + c3 * vy * vy;
    const REALV uca = vx * c2 + vy * c4;
    const REALV l0 = vz * vz * c5 + (REAL)2 * vz * uca + ucu;
    const REALV u2 = vx * vx + vy * vy;
    /* the frame of every lane (PCA_FRAME; w = 0: no anchor) */
    const REALV ux = VLOADV(0, b->fu[0]), uy = VLOADV(0, b->fu[1]), uzz = VLOADV(0, b->fu[2]);
    const REALV wx = VLOADV(0, b->fw[0]), wy = VLOADV(0, b->fw[1]), wz = VLOADV(0, b->fw[2]);
    const IREALV has = isnotequal(wx, (REALV)0) | isnotequal(wy, (REALV)0)
                       | isnotequal(wz, (REALV)0);
    VSTOREV(select((REALV)NAN, fmax(l0, (REALV)0), isless(u2, (REALV)ANCHOR_SIN2) & has),
            0, b->l0a);
    REALV t, x, y, z;
#define PCA_UNREFLECT(fx, fy, fz)                                                        \
    x = VLOADV(0, fx); y = VLOADV(0, fy); z = VLOADV(0, fz);                             \
    t = x * wx + y * wy + z * wz;                                                        \
    VSTOREV(x - t * ux, 0, fx); VSTOREV(y - t * uy, 0, fy); VSTOREV(z - t * uzz, 0, fz);
    PCA_UNREFLECT(b->v0x, b->v0y, b->v0z)
    PCA_UNREFLECT(b->v2x, b->v2y, b->v2z)
    PCA_UNREFLECT(b->mux, b->muy, b->muz)
#undef PCA_UNREFLECT
}
#endif

/* Lane k of b unused (past the work-item's points): the identity covariance, no count, no
 * anchor, so that the vector eigen solve and pca_anchor_l0 see a harmless matrix. */
inline void pca_empty_lane(pca_batch_t *b, uint k)
{
    for (int e = 0; e < 6; ++e) b->c[e][k] = (REAL)(e == 0 || e == 3 || e == 5);
    b->count[k] = 0;
#if PCA_ANCHOR
    for (int e = 0; e < 3; ++e) b->fu[e][k] = b->fw[e][k] = 0;
    b->mux[k] = b->muy[k] = b->muz[k] = 0;
#endif
}

/* CN: the anchor normals of the cells (anchor.cl), read only with PCA_ANCHOR (else 0). */
inline void pca_batch(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,
                      __global const REAL *W, __global const REAL *CN,
                      __global const uint *cell_of, __global const uint2 *ranges, uint n,
                      uint g0, uint kn, REAL2 ball, REAL ih2, pca_batch_t *b)
{
    for (uint k = 0; k < VW; ++k) {
        if (k < kn) {
            const uint g = g0 + k;
            const uint co = cell_of[g];
            __global const REAL *XA = x_rows(X, co, n);
#if PCA_ANCHOR
            const REAL3 a = vload3(co & CELL_MASK, CN);
#else
            const REAL3 a = (REAL3)(0);
#endif
            pca_ball(XA, Y, Z, W, ranges, co & CELL_MASK, (REAL3)(XA[g], Y[g], Z[g]),
                     POINT_BALL(W, g, ball), ih2, a, b, k);
        } else {
            pca_empty_lane(b, k);
        }
    }
    pca_decompose(b);
#if PCA_ANCHOR
    pca_anchor_l0(b);
#endif
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
