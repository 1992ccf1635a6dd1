/* pca.h -- weighted PCA of the ball N_r(p), shared by every kernel that needs it.
 *
 *   pca_ball   the sums of one point, one fixed-order pass relative to p (weights.h decides
 *              the weights): count, 1/sum w, mu = o - p and the centred covariance;
 *   pca_batch  pca_ball for the VW consecutive sorted points g0 .. g0 + kn - 1 of one
 *              work-item, then their VW covariances decomposed at once by eig3_sym_v (a
 *              scalar eig3 per point costs more than the neighbour loops together);
 *   pca_refine_l0  lambda0 from a second pass (float32 one-pass moments lose ~2 digits);
 *   PCA_ANCHOR (on when the kernel is built with REFINE_L0=1)  lambda0 without the second
 *              pass: the walk sums the offsets in the anchor frame, sheared along the
 *              anchor a's dominant axis (the PCA normal of the query's cell, anchor.cl) so
 *              that the heights above the anchor plane (over a's component) are a
 *              coordinate of their own whose small sums keep their digits;
 *              pca_decompose shears the covariance back, pca_anchor_l0 evaluates
 *              <v0, C v0> from the sheared sums and takes v0, v2 and mu back to the
 *              cloud's axes; lanes whose anchor is too far from v0 (or missing) are marked
 *              for the second pass;
 *   pca_ball_framed  pca_ball in the anchor frame (PCA_FRAME; one walk per axis);
 *   pca_decompose_pair  pca_decompose of two batches at once, in VW2 = 2 VW lanes (VW <= 8;
 *              the several balls of features.cl);
 *   PCA_SHEAR, PCA_ACCUMULATE, pca_store_sums, pca_decompose, PCA_REFINE_ACCUMULATE
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

/* status 2 (degenerate) when the middle eigenvalue is at most DEGENERATE_RATIO of the
 * largest: 1e-10 in double (as clcurv/reference/operators.py), 1e-5 in float, where the sums resolve
 * the second direction of a thinner ball only to a few per cent (docs/methods.md, NaN
 * policy: a wire thinner than ~0.005 r is degenerate in float only) */
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
                                        PCA_ANCHOR: of the sheared offsets, PCA_SHEAR) */
#if PCA_ANCHOR
    REAL fs[2][VW], fax[VW], fh[VW]; /* the anchor frame (PCA_FRAME: s, axis; has one) */
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
/* Uniform weights: the offsets zeroed outside the ball (3 selects: a masked lane's values,
 * whatever they are, are never read), then plain adds and multiply-adds of the zeroed
 * offsets, e = m ? d : 0, s += e, s2 += e_i e_j: a masked lane adds +0 exactly. The
 * products are PCA_MAD, fma(a, b, c) where the device has an FMA (one instruction), not
 * mad(a, b, c), which PoCL 3.1 makes a multiply and an add (the flush loop of features.cl's
 * three radii: 30 -> 24 instructions a chunk). */
#if !defined(PCA_FMA)
#error "pca.h needs PCA_FMA (0|1, clcurv/runtime/program.py: precision_defines)"
#elif PCA_FMA
/* The device has a fused multiply-add (clcurv/runtime/program.py: fused_sums): every product sum is
 * one, spelled out, so that both forms below fuse alike whatever the compiler's reading. */
#define PCA_MAD(a, b, c) fma(a, b, c)
#else
#define PCA_MAD(a, b, c) ((a) * (b) + (c))
#endif
#if !defined(MASKED_SUMS)
#error "pca.h needs MASKED_SUMS (0|1, clcurv/runtime/program.py: precision_defines)"
#elif MASKED_SUMS
/* MASKED_SUMS (the host's choice for CPU devices with 512-bit vectors, AVX-512): each sum
 * updated only in the lanes of the mask, s = m ? s + d : s, s2 = m ? d_i d_j + s2 : s2, which
 * AVX-512 does in one masked instruction per sum (10 a chunk against 13 above). The same
 * values bit for bit: a lane outside the mask keeps s, where the form above adds +0 to it
 * (tests/test_masked_sums.py). Where a select is an instruction of its own (AVX2: a blend)
 * it costs 6 more a chunk: the moments kernel 20% slower under Intel's runtime built for
 * AVX2, 8-10% faster under PoCL and Intel's runtime on the Zen 4 EPYC's AVX-512. */
#define PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    {                                                                                      \
        const REALV dx_ = (dx), dy_ = (dy), dz_ = (dz);                                    \
        MASKED_COUNT(sw, m)                                                                \
        sx = select(sx, sx + dx_, m); sy = select(sy, sy + dy_, m);                        \
        sz = select(sz, sz + dz_, m);                                                      \
        sxx = select(sxx, PCA_MAD(dx_, dx_, sxx), m);                                      \
        sxy = select(sxy, PCA_MAD(dx_, dy_, sxy), m);                                      \
        sxz = select(sxz, PCA_MAD(dx_, dz_, sxz), m);                                      \
        syy = select(syy, PCA_MAD(dy_, dy_, syy), m);                                      \
        syz = select(syz, PCA_MAD(dy_, dz_, syz), m);                                      \
        szz = select(szz, PCA_MAD(dz_, dz_, szz), m);                                      \
    }
#else
#define PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    {                                                                                      \
        const REALV ex_ = select((REALV)0, dx, m), ey_ = select((REALV)0, dy, m);          \
        const REALV ez_ = select((REALV)0, dz, m);                                         \
        MASKED_COUNT(sw, m)                                                                \
        sx += ex_; sy += ey_; sz += ez_;                                                   \
        sxx = PCA_MAD(ex_, ex_, sxx); sxy = PCA_MAD(ex_, ey_, sxy);                        \
        sxz = PCA_MAD(ex_, ez_, sxz); syy = PCA_MAD(ey_, ey_, syy);                        \
        syz = PCA_MAD(ey_, ez_, syz); szz = PCA_MAD(ez_, ez_, szz);                        \
    }
#endif
#endif

/* The anchor frame (PCA_ANCHOR): a shear along the axis of the anchor a's largest
 * component. With that axis ax and the two others t1, t2 in cyclic order after it (ax = z:
 * x, y; ax = x: y, z; ax = y: z, x), an offset d becomes
 *     e = (d_t1, d_t2, d_ax + s1 d_t1 + s2 d_t2),  s = (a_t1, a_t2) / a_ax  (|s_i| <= 1),
 * so e_3 = <d, a> / a_ax is the height above the anchor plane over a_ax (1 / sqrt 3 <=
 * |a_ax| <= 1): small numbers whose sums keep the digits that lambda0 needs
 * (pca_anchor_l0), at 2 operations per chunk. (The Householder reflection that mapped a to
 * e_z before cost 6: the 1M-point features kernel took 55.8 ms with it, 52.5 with the
 * shear, the moments kernel of surface variation 52.5 and 48.8. The shear needs the axis
 * known at compile time, so each walk has a copy per axis: pca_ball_x, _y, _z,
 * PCA_BY_AXIS.) A missing anchor (a = 0) gives ax = z, s = 0: the identity. */
#define PCA_FRAME(a, ax, s)                                                              \
    {                                                                                    \
        const REAL3 m_ = fabs(a);                                                        \
        ax = m_.z >= m_.x && m_.z >= m_.y ? 2 : m_.x >= m_.y ? 0 : 1;                   \
        const REAL3 r_ = ax == 2 ? (a) : ax == 0 ? (a).yzx : (a).zxy;                    \
        s = r_.z != 0 ? r_.xy / r_.z : (REAL2)(0);                                       \
    }
/* (ex, ey, ez) = e for a chunk's offsets, AX (0, 1, 2: x, y, z) a compile-time constant */
#define PCA_SHEAR(AX, s, dx, dy, dz, ex, ey, ez)                                         \
    {                                                                                    \
        const REALV t1_ = (AX) == 2 ? (dx) : (AX) == 0 ? (dy) : (dz);                    \
        const REALV t2_ = (AX) == 2 ? (dy) : (AX) == 0 ? (dz) : (dx);                    \
        const REALV h_ = (AX) == 2 ? (dz) : (AX) == 0 ? (dx) : (dy);                     \
        ex = t1_; ey = t2_; ez = h_ + (s).x * t1_ + (s).y * t2_;                         \
    }
/* BODY(AX) for the run-time axis ax, unswitched: each copy with AX a constant */
#define PCA_BY_AXIS(ax, BODY)                                                            \
    if ((ax) == 2) { BODY(2) } else if ((ax) == 0) { BODY(0) } else { BODY(1) }
/* Lane k of b keeps the frame (ax, s) of the anchor a for pca_decompose and
 * pca_anchor_l0 */
#define PCA_KEEP_FRAME(b, k, ax, s, a)                                                   \
    {                                                                                    \
        (b)->fs[0][k] = (s).x; (b)->fs[1][k] = (s).y;                                    \
        (b)->fax[k] = (REAL)(ax); (b)->fh[k] = (REAL)any((a) != (REAL3)(0));             \
    }

/* Lane k of b from the sums of PCA_ACCUMULATE: count, 1/sum w, mu = o - p and the centred
 * covariance. */
inline void pca_store_sums(REALV sc, REALV sw, REALV sx, REALV sy, REALV sz, REALV sxx,
                           REALV sxy, REALV sxz, REALV syy, REALV syz, REALV szz,
                           pca_batch_t *b, uint k)
{
#if DENSITY || GAUSSIAN
    const REAL wsum = hsum(sw);
    b->count[k] = (uint)hsum(sc);
#else
    const REAL wsum = COUNT_TOTAL(sw);   /* w = 1: the sum of the weights is the count */
    b->count[k] = (uint)wsum;
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
 * covariance (with PCA_ANCHOR of the offsets sheared along axis AX by s, PCA_SHEAR). One
 * function per axis, pca_ball_x, _y, _z (AX a constant in each: PoCL does not inline
 * pca_ball into its callers, so a parameter would stay a run-time choice per chunk).
 * (Results go through arrays, not a returned struct: PoCL spills struct copies in the
 * work-item loop at a large cost.) */
#if PCA_ANCHOR
#define PCA_BALL_SHEAR(AX) PCA_SHEAR(AX, s, dx, dy, dz, dx, dy, dz)
#else
#define PCA_BALL_SHEAR(AX)
#endif
#define PCA_BALL(name, AX)                                                                \
inline void name(__global const REAL *X, __global const REAL *Y, __global const REAL *Z,   \
                 __global const REAL *W, __global const uint2 *ranges, uint cell, REAL3 p, \
                 REAL2 ball, REAL ih2, REAL2 s, pca_batch_t *b, uint k)                    \
{                                                                                         \
    REALV sc = 0, sw = 0, sx = 0, sy = 0, sz = 0;                                         \
    REALV sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;                           \
    REALV dx, dy, dz;                                                                     \
    (void)s;                                                                              \
    NEIGHBOR_CHUNKS_BEGIN(ranges, cell, p, ball, i, end, pr)                              \
        const IREALV m = chunk_offsets(X, Y, Z, i, end, pr, ball, &dx, &dy, &dz);         \
        const REALV w = chunk_weights(W, i, dx, dy, dz, m, ih2);                          \
        PCA_BALL_SHEAR(AX)                                                                \
        PCA_ACCUMULATE(w, m, dx, dy, dz, sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz) \
    NEIGHBOR_CHUNKS_END                                                                   \
    pca_store_sums(sc, sw, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz, b, k);               \
}
PCA_BALL(pca_ball_z, 2)
#if PCA_ANCHOR
PCA_BALL(pca_ball_x, 0)
PCA_BALL(pca_ball_y, 1)
#endif
#undef PCA_BALL
#undef PCA_BALL_SHEAR

/* pca_ball of p into lane k of b, with PCA_ANCHOR in the frame of the anchor a (PCA_FRAME,
 * kept in b), the walk unswitched by its axis. */
inline void pca_ball_framed(__global const REAL *X, __global const REAL *Y,
                            __global const REAL *Z, __global const REAL *W,
                            __global const uint2 *ranges, uint cell, REAL3 p, REAL2 ball,
                            REAL ih2, REAL3 a, pca_batch_t *b, uint k)
{
#if PCA_ANCHOR
    int ax;
    REAL2 s;
    PCA_FRAME(a, ax, s)
    if (ax == 2) pca_ball_z(X, Y, Z, W, ranges, cell, p, ball, ih2, s, b, k);
    else if (ax == 0) pca_ball_x(X, Y, Z, W, ranges, cell, p, ball, ih2, s, b, k);
    else pca_ball_y(X, Y, Z, W, ranges, cell, p, ball, ih2, s, b, k);
    PCA_KEEP_FRAME(b, k, ax, s, a)
#else
    (void)a;
    pca_ball_z(X, Y, Z, W, ranges, cell, p, ball, ih2, (REAL2)(0), b, k);
#endif
}

#define VSTOREV CAT(vstore, VW)

/* The body of pca_decompose on lanes of type T (eig3's vector struct V3, its solver EIG):
 * LD(f) loads the lanes of field f of the batch(es), ST(v, f) stores them. With PCA_ANCHOR
 * the covariance of the sheared offsets E (c, kept for pca_anchor_l0) is sheared back first:
 * C = S^-1 E S^-T, S^-1 = I - e_3 (s1, s2, 0)^T, the covariance in the axes (t1, t2, ax) of
 * each lane's frame; the eigenvectors stay in those axes (pca_anchor_l0 takes them back). */
#if PCA_ANCHOR
#define PCA_EIG(T, LD, EIG)                                                              \
    const T s1 = LD(fs[0]), s2 = LD(fs[1]);                                              \
    const T m31 = LD(c[2]) - s1 * c0 - s2 * c1;                  /* row 3 of S^-1 E */   \
    const T m32 = LD(c[4]) - s1 * c1 - s2 * c3;                                          \
    const T m33 = LD(c[5]) - s1 * LD(c[2]) - s2 * LD(c[4]);                              \
    EIG(c0, c1, m31, c3, m32, m33 - s1 * m31 - s2 * m32, &w0, &w1, &w2, &e0, &e1, &e2);
#else
#define PCA_EIG(T, LD, EIG)                                                              \
    EIG(c0, c1, LD(c[2]), c3, LD(c[4]), LD(c[5]), &w0, &w1, &w2, &e0, &e1, &e2);
#endif
#define PCA_DECOMPOSE(T, V3, EIG, LD, ST)                                                \
    {                                                                                    \
        T w0, w1, w2;                                                                    \
        V3 e0, e1, e2;                                                                   \
        const T c0 = LD(c[0]), c1 = LD(c[1]), c3 = LD(c[3]);                             \
        PCA_EIG(T, LD, EIG)                                                              \
        ST(fmax(w0, (T)0), l0) ST(fmax(w1, (T)0), l1) ST(fmax(w2, (T)0), l2)             \
        ST(e0.x, v0x) ST(e0.y, v0y) ST(e0.z, v0z)                                        \
        ST(e2.x, v2x) ST(e2.y, v2y) ST(e2.z, v2z)                                        \
    }

/* The VW covariances of b decomposed at once (eig3_sym_v): eigenvalues clamped at 0, the
 * eigenvectors of the smallest and the largest (PCA_DECOMPOSE). */
#define ONE_LD(f) VLOADV(0, b->f)
#define ONE_ST(v, f) VSTOREV((v), 0, b->f);
inline void pca_decompose(pca_batch_t *b)
{
    PCA_DECOMPOSE(REALV, eig3_v3_v, eig3_sym_v, ONE_LD, ONE_ST)
}
#undef ONE_LD
#undef ONE_ST

#ifdef VW2
/* pca_decompose of two batches a, b at once, their lanes side by side (REALW: VW2 lanes):
 * the same operations lane by lane, the same results bit for bit (eig3.h) */
#define PAIR_LD(f) ((REALW)(VLOADV(0, a->f), VLOADV(0, b->f)))
#define PAIR_ST(v, f) { const REALW v_ = (v); VSTOREV(v_.lo, 0, a->f); VSTOREV(v_.hi, 0, b->f); }
inline void pca_decompose_pair(pca_batch_t *a, pca_batch_t *b)
{
    PCA_DECOMPOSE(REALW, eig3_v3_w, eig3_sym_g_w, PAIR_LD, PAIR_ST)
}
#undef PAIR_LD
#undef PAIR_ST
#endif

#if PCA_ANCHOR
/* (x, y, z) from the frame's axes (t1, t2, ax) of every lane (PCA_FRAME), in place */
#define PCA_TO_CLOUD_AXES(fx, fy, fz)                                                    \
    {                                                                                    \
        const REALV t1_ = VLOADV(0, fx), t2_ = VLOADV(0, fy), h_ = VLOADV(0, fz);        \
        VSTOREV(select(select(t2_, h_, is0), t1_, is2), 0, fx);                          \
        VSTOREV(select(select(h_, t1_, is0), t2_, is2), 0, fy);                          \
        VSTOREV(select(select(t1_, t2_, is0), h_, is2), 0, fz);                          \
    }
/* The anchored lambda0 of every lane (after pca_decompose), then v0, v2 and mu taken to the
 * cloud's axes. With v0 = (v1, v2, v3) in the lane's axes (t1, t2, ax) and
 * w = S^-T v0 = (v1 - s1 v3, v2 - s2 v3, v3),
 *     <v0, C v0> = <w, E w> = v3^2 E_33 + 2 v3 (w1 E_13 + w2 E_23) + <u, E u>, u = (w1, w2, 0),
 * the first two terms from the sums of the heights (small numbers, full relative precision),
 * only the last from the tangential sums, whose rounding it scales by |u|^2 (0 when v0 is
 * the anchor; <= ~6 sin^2 of their angle). Lanes with |u|^2 > ANCHOR_SIN2, or without an
 * anchor, get NaN, the mark for the second pass. */
inline void pca_anchor_l0(pca_batch_t *b)
{
    const REALV vx = VLOADV(0, b->v0x), vy = VLOADV(0, b->v0y), vz = VLOADV(0, b->v0z);
    const REALV s1 = VLOADV(0, b->fs[0]), s2 = VLOADV(0, b->fs[1]);
    const REALV c0 = VLOADV(0, b->c[0]), c1 = VLOADV(0, b->c[1]), c2 = VLOADV(0, b->c[2]);
    const REALV c3 = VLOADV(0, b->c[3]), c4 = VLOADV(0, b->c[4]), c5 = VLOADV(0, b->c[5]);
    const REALV wx = vx - s1 * vz, wy = vy - s2 * vz;
    const REALV ucu = wx * (c0 * wx + (REAL)2 * c1 * wy) + c3 * wy * wy;
    const REALV uca = wx * c2 + wy * c4;
    const REALV l0 = vz * vz * c5 + (REAL)2 * vz * uca + ucu;
    const REALV u2 = wx * wx + wy * wy;
    const IREALV has = isnotequal(VLOADV(0, b->fh), (REALV)0);
    VSTOREV(select((REALV)NAN, fmax(l0, (REALV)0), isless(u2, (REALV)ANCHOR_SIN2) & has),
            0, b->l0a);
    /* mu: S^-1 of the sheared mean, then every vector to the cloud's axes */
    const REALV m1 = VLOADV(0, b->mux), m2 = VLOADV(0, b->muy);
    VSTOREV(VLOADV(0, b->muz) - s1 * m1 - s2 * m2, 0, b->muz);
    const REALV ax = VLOADV(0, b->fax);
    const IREALV is0 = isequal(ax, (REALV)0), is2 = isequal(ax, (REALV)2);
    PCA_TO_CLOUD_AXES(b->v0x, b->v0y, b->v0z)
    PCA_TO_CLOUD_AXES(b->v2x, b->v2y, b->v2z)
    PCA_TO_CLOUD_AXES(b->mux, b->muy, b->muz)
}
#undef PCA_TO_CLOUD_AXES
#endif

/* Lane k of b unused (past the work-item's points): the identity covariance, no count, no
 * anchor, so that the vector eigen solve and pca_anchor_l0 see a harmless matrix. */
inline void pca_empty_lane(pca_batch_t *b, uint k)
{
    for (int e = 0; e < 6; ++e) b->c[e][k] = (REAL)(e == 0 || e == 3 || e == 5);
    b->count[k] = 0;
#if PCA_ANCHOR
    b->fs[0][k] = b->fs[1][k] = 0;
    b->fax[k] = 2;
    b->fh[k] = 0;
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
            pca_ball_framed(XA, Y, Z, W, ranges, co & CELL_MASK, (REAL3)(XA[g], Y[g], Z[g]),
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

/* A covariance of rank < 2 (l1 <= l2 ascending): no largest eigenvalue, or a middle one at
 * most DEGENERATE_RATIO of it. Scalars (0/1) or vectors (lane masks) alike. */
#define PCA_IS_DEGENERATE(l1, l2) (!((l2) > 0) || (l1) <= DEGENERATE_RATIO * (l2))

/* Status of lane k: too few neighbours (< min_count) or a covariance of rank < 2. */
inline uchar pca_status(const pca_batch_t *b, uint k, uint min_count)
{
    if (b->count[k] < min_count) return ST_TOO_FEW;
    if (PCA_IS_DEGENERATE(b->l1[k], b->l2[k])) return ST_DEGENERATE;
    return ST_OK;
}

/* pca_status of the VW lanes at once, as REALV (lanes k >= kn: ST_TOO_FEW): the same
 * tests, without a branch per lane. */
inline REALV pca_status_v(const pca_batch_t *b, uint kn, uint min_count)
{
    const REALV l2 = VLOADV(0, b->l2), l1 = VLOADV(0, b->l1);
    const IREALV few = CAT(convert_, IREALV)(CAT(vload, VW)(0, b->count)
                                               < (CAT(uint, VW))min_count)
                       | (LANES >= (IREALV)(IREAL)kn);
    const IREALV degen = PCA_IS_DEGENERATE(l1, l2);
    return select(select((REALV)ST_OK, (REALV)ST_DEGENERATE, degen), (REALV)ST_TOO_FEW, few);
}
#endif
