/* eig3.h -- closed-form eigen decomposition of a symmetric 3x3 matrix (float or double).
 *
 * Entry points, the same algorithm and the same operations:
 *   eig3_sym    one matrix (REAL entries, REAL3 results);
 *   eig3_sym_v  VW matrices at once, one per lane of REALV (see common.h), results as
 *               eig3_v3_v structs of three REALV. It has no branches at all (every special
 *               case is a select), so it runs at the full SIMD width of a CPU: a scalar
 *               eig3_sym is a long chain of dependent divisions and square roots, about
 *               300 ns per call on one core; eight matrices at once cost little more than one;
 *   eig3_sym_g_w  (VW <= 8) 2 VW matrices at once, in REALW (common.h: VW2 lanes), for
 *               two batches of points: the chain still leaves VW lanes mostly idle (on the
 *               Zen 4 EPYC, 10.6 ms per 1M matrices at 8 lanes, 6.8 at 16). Every width
 *               gives the same bits (tests/test_eig3_vector.py).
 * The algorithm body below is written once, for a generic type EIG3_T (REAL, REALV or
 * REALW), and instantiated by including this file again (EIG3_GENERIC_PASS).
 *
 * Method (no iterations, no data-dependent loops):
 *   1. Scale A by a power of two (exact) so that its max-abs entry lies in [1, 2).
 *   2. Shift by q = trace/3 and scale again by a power of two:  C = (A/2^e1 - qI) / 2^e2,
 *      then normalise D = C / p with p = sqrt(trace(C^2)/6), so that trace(D) = 0 and
 *      trace(D^2) = 6: the eigenvalues beta of D satisfy beta^3 - 3 beta = det(D) and lie in
 *      [-2, 2]; they are beta_k = 2 cos(acos(det(D)/2)/3 + 2 pi k/3) (trigonometric method;
 *      the one eigenvalue taken from it comes from Newton steps on the cubic, step 3).
 *   3. Only the most isolated eigenvalue is taken from the formula: it is beta_2 (largest) when
 *      det(D) >= 0, else beta_0 (smallest), and it is at least sqrt(3) away from the other two.
 *      Its eigenvector is the largest cross product of two rows of D - beta I (norm >= sqrt(3)).
 *   4. The other two eigenvectors come from the 2x2 problem of D restricted to the orthogonal
 *      complement of the first one, solved by one exact Jacobi rotation: repeated eigenvalues
 *      therefore give an orthonormal basis and never a division by zero.
 *   5. The pair is ordered by its Rayleigh quotients in D.
 *   6. Eigenvalues are the Rayleigh quotients v^T (A/2^e1) v in the unshifted matrix, times 2^e1.
 *      This avoids the O(sqrt(eps)) error of the trigonometric formula for (nearly) repeated
 *      eigenvalues, and is exact for axis-aligned input (a plane z = 0 gives lambda0 = 0).
 *      lambda0 of a PSD matrix can still come out slightly negative (about -eps * lambda2).
 *
 * Accuracy: backward stable, eigenvalue errors are a few eps * max|lambda|; the eigenvector of an
 * eigenvalue separated by gap has an angle error of about eps * max|lambda| / gap (this is what
 * makes the normal accurate when lambda0 << lambda1 <= lambda2).
 * Overflow: only if an eigenvalue itself exceeds the largest finite REAL (entries close to it).
 * Scaling A by a power of two scales w exactly and leaves v0, v1, v2 bit-identical.
 * Denormal inputs are handled if the device does not flush them to zero.
 * Ideas from D. Eberly, "A Robust Eigensolver for 3x3 Symmetric Matrices" (Geometric Tools).
 */
#ifndef EIG3_GENERIC_PASS
#ifndef CLCURV_EIG3_H
#define CLCURV_EIG3_H

#include "common.h"

#if REAL_IS_DOUBLE
#define EIG3_C(x) x          /* REAL literal */
#define EIG3_MANT 52
#define EIG3_BIAS 1023
#define EIG3_DENORM_SCALE 9007199254740992.0   /* 2^(MANT+1): makes any denormal normal */
#define EIG3_BIG 0x1p100     /* |theta| clamp of the Jacobi rotation: BIG^2 is finite, 1/BIG << eps */
#else
#define EIG3_C(x) x##f
#define EIG3_MANT 23
#define EIG3_BIAS 127
#define EIG3_DENORM_SCALE 16777216.0f
#define EIG3_BIG 0x1p40f
#endif

/* ---- scalar instantiation: eig3_sym_g on REAL ---- */
#define EIG3_GENERIC_PASS
#define EIG3_T REAL
#define EIG3_I IREAL                                  /* integer of the width of REAL */
#define EIG3_SEL(a, b, c) ((c) ? (EIG3_T)(b) : (EIG3_T)(a))   /* c ? b : a */
#define EIG3_SELI(a, b, c) ((c) ? (EIG3_I)(b) : (EIG3_I)(a))
#define EIG3_AS_I(x) CAT(as_, IREAL)(x)
#define EIG3_AS_R(b) CAT(as_, REAL)(b)
#define EIG3_FN(name) name
#include "eig3.h"                           /* undefines the EIG3_ parameters */

/* ---- vector instantiation: eig3_sym_g_v on REALV (VW matrices, one per lane) ---- */
#define EIG3_T REALV
#define EIG3_I IREALV
#define EIG3_SEL(a, b, c) select((EIG3_T)(a), (EIG3_T)(b), (c))  /* lane-wise c ? b : a (c: a comparison) */
#define EIG3_SELI(a, b, c) select((EIG3_I)(a), (EIG3_I)(b), (c))
#define EIG3_AS_I(x) CAT(as_, IREALV)(x)
#define EIG3_AS_R(b) CAT(as_, REALV)(b)
#define EIG3_FN(name) name##_v
#include "eig3.h"                           /* undefines the EIG3_ parameters */

/* ---- pair instantiation: eig3_sym_g_w on REALW (2 VW matrices: two batches at once) ---- */
#if VW <= 8
#define EIG3_T REALW
#define EIG3_I IREALW
#define EIG3_SEL(a, b, c) select((EIG3_T)(a), (EIG3_T)(b), (c))
#define EIG3_SELI(a, b, c) select((EIG3_I)(a), (EIG3_I)(b), (c))
#define EIG3_AS_I(x) CAT(as_, IREALW)(x)
#define EIG3_AS_R(b) CAT(as_, REALW)(b)
#define EIG3_FN(name) name##_w
#include "eig3.h"                           /* undefines the EIG3_ parameters */
#endif
#undef EIG3_GENERIC_PASS

/* Eigen decomposition of the symmetric matrix [[a00,a01,a02],[a01,a11,a12],[a02,a12,a22]].
   Writes eigenvalues ascending into *w (w->x <= w->y <= w->z) and unit eigenvectors v0, v1, v2
   (v0 for w->x, ...) forming a right-handed orthonormal basis (v2 = cross(v0, v1)).
   Multiple of the identity (including the zero matrix): w = (a, a, a) and v0, v1, v2 = e_z, e_x, e_y.
   For other repeated eigenvalues the basis of the eigenspace is arbitrary but orthonormal. */
inline void eig3_sym(REAL a00, REAL a01, REAL a02, REAL a11, REAL a12, REAL a22,
                     REAL3 *w, REAL3 *v0, REAL3 *v1, REAL3 *v2)
{
    REAL w0, w1, w2;
    eig3_v3 u0, u1, u2;
    eig3_sym_g(a00, a01, a02, a11, a12, a22, &w0, &w1, &w2, &u0, &u1, &u2);
    *w = (REAL3)(w0, w1, w2);
    *v0 = (REAL3)(u0.x, u0.y, u0.z);
    *v1 = (REAL3)(u1.x, u1.y, u1.z);
    *v2 = (REAL3)(u2.x, u2.y, u2.z);
}

/* The same for VW matrices at once (lane k of every argument is matrix k): eigenvalues
   *w0 <= *w1 <= *w2 and eigenvectors v0, v1, v2 as structs {x, y, z} of REALV. */
inline void eig3_sym_v(REALV a00, REALV a01, REALV a02, REALV a11, REALV a12, REALV a22,
                       REALV *w0, REALV *w1, REALV *w2, eig3_v3_v *v0, eig3_v3_v *v1, eig3_v3_v *v2)
{
    eig3_sym_g_v(a00, a01, a02, a11, a12, a22, w0, w1, w2, v0, v1, v2);
}

#endif /* CLCURV_EIG3_H */

#else /* EIG3_GENERIC_PASS: the algorithm on EIG3_T (REAL or REALV), mask/exponent type EIG3_I */

#define EIG3_V3 EIG3_FN(eig3_v3)
#define EIG3_M3 EIG3_FN(eig3_m3)

typedef struct { EIG3_T x, y, z; } EIG3_V3;
/* Symmetric 3x3 matrix stored by its upper triangle. */
typedef struct { EIG3_T a00, a01, a02, a11, a12, a22; } EIG3_M3;

inline EIG3_V3 EIG3_FN(eig3_vec)(EIG3_T x, EIG3_T y, EIG3_T z)
{
    EIG3_V3 r = { x, y, z };
    return r;
}

/* c ? b : a, lane-wise */
inline EIG3_V3 EIG3_FN(eig3_sel3)(EIG3_V3 a, EIG3_V3 b, EIG3_I c)
{
    return EIG3_FN(eig3_vec)(EIG3_SEL(a.x, b.x, c), EIG3_SEL(a.y, b.y, c), EIG3_SEL(a.z, b.z, c));
}

inline EIG3_T EIG3_FN(eig3_dot)(EIG3_V3 a, EIG3_V3 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

inline EIG3_V3 EIG3_FN(eig3_cross)(EIG3_V3 a, EIG3_V3 b)
{
    return EIG3_FN(eig3_vec)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

inline EIG3_V3 EIG3_FN(eig3_lin)(EIG3_T s, EIG3_V3 a, EIG3_T t, EIG3_V3 b)        /* s a + t b */
{
    return EIG3_FN(eig3_vec)(s * a.x + t * b.x, s * a.y + t * b.y, s * a.z + t * b.z);
}

/* Largest absolute entry. */
inline EIG3_T EIG3_FN(eig3_max_abs)(EIG3_M3 m)
{
    EIG3_T d = fmax(fmax(fabs(m.a00), fabs(m.a11)), fabs(m.a22));
    EIG3_T o = fmax(fmax(fabs(m.a01), fabs(m.a02)), fabs(m.a12));
    return fmax(d, o);
}

/* m * s for every entry. */
inline EIG3_M3 EIG3_FN(eig3_scale)(EIG3_M3 m, EIG3_T s)
{
    EIG3_M3 r = { m.a00 * s, m.a01 * s, m.a02 * s, m.a11 * s, m.a12 * s, m.a22 * s };
    return r;
}

/* m - s I */
inline EIG3_M3 EIG3_FN(eig3_shift)(EIG3_M3 m, EIG3_T s)
{
    m.a00 -= s;
    m.a11 -= s;
    m.a22 -= s;
    return m;
}

/* 2^h for |h| well inside the normal exponent range, from its bits (no library call). */
inline EIG3_T EIG3_FN(eig3_exp2i)(EIG3_I h)
{
    return EIG3_AS_R((h + (EIG3_I)EIG3_BIAS) << (EIG3_I)EIG3_MANT);
}

/* floor(log2(x)) of a positive finite x, read from the bits; a denormal x is first scaled
   exactly by 2^(MANT+1), which makes it normal. */
inline EIG3_I EIG3_FN(eig3_ilogb)(EIG3_T x)
{
    const EIG3_I emask = (EIG3_I)(2 * EIG3_BIAS + 1);
    const EIG3_I den = ((EIG3_AS_I(x) >> (EIG3_I)EIG3_MANT) & emask) == (EIG3_I)0;
    const EIG3_T xs = EIG3_SEL(x, x * EIG3_DENORM_SCALE, den);
    const EIG3_I biased = (EIG3_AS_I(xs) >> (EIG3_I)EIG3_MANT) & emask;
    return biased - (EIG3_I)EIG3_BIAS - EIG3_SELI(0, EIG3_MANT + 1, den);
}

/* 2^e as two exact power-of-two factors (each within the exponent range even when 2^e is
   not), so scaling by them is exact and costs multiplications, not ldexp calls. */
inline void EIG3_FN(eig3_pow2)(EIG3_I e, EIG3_T *f1, EIG3_T *f2)
{
    const EIG3_I h = e >> (EIG3_I)1;
    *f1 = EIG3_FN(eig3_exp2i)(h);
    *f2 = EIG3_FN(eig3_exp2i)(e - h);
}

/* m * 2^e for every entry (exact unless the result is denormal). */
inline EIG3_M3 EIG3_FN(eig3_ldexp)(EIG3_M3 m, EIG3_I e)
{
    EIG3_T f1, f2;
    EIG3_FN(eig3_pow2)(e, &f1, &f2);
    return EIG3_FN(eig3_scale)(EIG3_FN(eig3_scale)(m, f1), f2);
}

/* Matrix-vector product m v. */
inline EIG3_V3 EIG3_FN(eig3_mul)(EIG3_M3 m, EIG3_V3 v)
{
    return EIG3_FN(eig3_vec)(m.a00 * v.x + m.a01 * v.y + m.a02 * v.z,
                             m.a01 * v.x + m.a11 * v.y + m.a12 * v.z,
                             m.a02 * v.x + m.a12 * v.y + m.a22 * v.z);
}

/* Rayleigh quotient v^T m v of a unit vector v. */
inline EIG3_T EIG3_FN(eig3_rayleigh)(EIG3_M3 m, EIG3_V3 v)
{
    return EIG3_FN(eig3_dot)(v, EIG3_FN(eig3_mul)(m, v));
}

/* Isolated eigenvalue of a matrix d with trace 0 and trace(d^2) = 6: the largest one
   2 cos(acos(r)/3) if r = det(d)/2 >= 0, else the smallest, -2 cos(acos(-r)/3). That is
   sign(r) t with t the root in [sqrt(3), 2] of t^3 - 3 t - 2 |r| = 0, computed by three
   Newton steps from a quadratic fit of t(|r|) (error <= 3.4e-3): the cubic is convex there
   and its slope 3 t^2 - 3 >= 6, so after the first step the steps converge from above,
   to within an ulp in float and double (checked on a 2e6-point grid of |r|: 7.9e-6, 4.5e-11, 2.2e-16), well
   conditioned also when the other two eigenvalues are (nearly) equal (|r| close to 1, slope 9).
   The acos/cos pair it replaces cost 3.5 ms of the 66 ms moments kernel at 1M points. */
inline EIG3_T EIG3_FN(eig3_isolated_eigenvalue)(EIG3_M3 d)
{
    EIG3_T det = d.a00 * (d.a11 * d.a22 - d.a12 * d.a12)
           - d.a01 * (d.a01 * d.a22 - d.a12 * d.a02)
           + d.a02 * (d.a01 * d.a12 - d.a11 * d.a02);
    EIG3_T r = clamp(EIG3_C(0.5) * det, EIG3_C(-1.0), EIG3_C(1.0));
    const EIG3_T s = fabs(r);
    EIG3_T b = EIG3_C(1.7320508075688772)
               + s * (EIG3_C(0.3333333333333333) - EIG3_C(0.0653841409022105) * s);
    for (int it = 0; it < 3; ++it) {
        const EIG3_T b2 = b * b;
        b -= (b * (b2 - EIG3_C(3.0)) - EIG3_C(2.0) * s) / (EIG3_C(3.0) * b2 - EIG3_C(3.0));
    }
    return EIG3_SEL(-b, b, r >= EIG3_C(0.0));
}

/* Unit vector spanning the kernel of the rank-2 matrix m = d - beta I: the longest of the
   cross products of its rows (for a simple eigenvalue beta they are all parallel to the
   eigenvector; the longest has norm >= sqrt(3) here). */
inline EIG3_V3 EIG3_FN(eig3_null_vector)(EIG3_M3 d, EIG3_T beta)
{
    EIG3_M3 m = EIG3_FN(eig3_shift)(d, beta);
    EIG3_V3 r0 = EIG3_FN(eig3_vec)(m.a00, m.a01, m.a02);
    EIG3_V3 r1 = EIG3_FN(eig3_vec)(m.a01, m.a11, m.a12);
    EIG3_V3 r2 = EIG3_FN(eig3_vec)(m.a02, m.a12, m.a22);
    EIG3_V3 c01 = EIG3_FN(eig3_cross)(r0, r1), c02 = EIG3_FN(eig3_cross)(r0, r2);
    EIG3_V3 c12 = EIG3_FN(eig3_cross)(r1, r2);
    EIG3_T n01 = EIG3_FN(eig3_dot)(c01, c01), n02 = EIG3_FN(eig3_dot)(c02, c02);
    EIG3_T n12 = EIG3_FN(eig3_dot)(c12, c12);
    EIG3_I t = n02 > n01;
    EIG3_V3 c = EIG3_FN(eig3_sel3)(c01, c02, t);
    EIG3_T n = EIG3_SEL(n01, n02, t);
    t = n12 > n;
    c = EIG3_FN(eig3_sel3)(c, c12, t);
    n = EIG3_SEL(n, n12, t);
    const EIG3_I ok = n > EIG3_C(0.0);       /* always, for finite input; keeps NaN out */
    const EIG3_T s = sqrt(EIG3_SEL(EIG3_C(1.0), n, ok));
    return EIG3_FN(eig3_vec)(EIG3_SEL(EIG3_C(0.0), c.x / s, ok), EIG3_SEL(EIG3_C(0.0), c.y / s, ok),
                             EIG3_SEL(EIG3_C(1.0), c.z / s, ok));
}

/* Unit vectors u, v with (w, u, v) a right-handed orthonormal basis, for a unit vector w.
   u is built from the two largest components of w, so its norm before scaling is >= 1/sqrt(2). */
inline void EIG3_FN(eig3_complement)(EIG3_V3 w, EIG3_V3 *u, EIG3_V3 *v)
{
    const EIG3_I bx = fabs(w.x) > fabs(w.y);
    /* bx: u = (-w.z, 0, w.x) / |(w.x, w.z)|, else u = (0, w.z, -w.y) / |(w.y, w.z)| */
    const EIG3_T s = EIG3_SEL(w.y, w.x, bx);
    const EIG3_T nrm = sqrt(s * s + w.z * w.z);
    *u = EIG3_FN(eig3_vec)(EIG3_SEL(EIG3_C(0.0), -w.z, bx) / nrm,
                           EIG3_SEL(w.z, EIG3_C(0.0), bx) / nrm,
                           EIG3_SEL(-w.y, w.x, bx) / nrm);
    *v = EIG3_FN(eig3_cross)(w, *u);
}

/* Jacobi rotation (c, s) diagonalising the symmetric 2x2 [[m00, m01], [m01, m11]]: the
   eigenvectors are (c, -s) and (s, c). t = tan of the smaller of the two possible angles,
   t = sign(theta) / (|theta| + sqrt(theta^2 + 1)), theta = (m11 - m00) / (2 m01), and t = 0
   when m01 == 0. |theta| is clamped to EIG3_BIG (theta^2 stays finite; beyond it t < 1/BIG
   is far below eps, where the rotation is the identity to working precision). */
inline void EIG3_FN(eig3_jacobi2)(EIG3_T m00, EIG3_T m01, EIG3_T m11, EIG3_T *c, EIG3_T *s)
{
    const EIG3_I nz = m01 != EIG3_C(0.0);
    const EIG3_T theta = (m11 - m00) / (EIG3_C(2.0) * EIG3_SEL(EIG3_C(1.0), m01, nz));
    const EIG3_T at = fmin(fabs(theta), EIG3_BIG);
    EIG3_T t = EIG3_C(1.0) / (at + sqrt(at * at + EIG3_C(1.0)));
    t = EIG3_SEL(t, -t, theta < EIG3_C(0.0));
    t = EIG3_SEL(EIG3_C(0.0), t, nz);
    *c = EIG3_C(1.0) / sqrt(t * t + EIG3_C(1.0));
    *s = t * *c;
}

inline void EIG3_FN(eig3_sym_g)(EIG3_T a00, EIG3_T a01, EIG3_T a02, EIG3_T a11, EIG3_T a12, EIG3_T a22,
                                EIG3_T *w0, EIG3_T *w1, EIG3_T *w2, EIG3_V3 *v0, EIG3_V3 *v1, EIG3_V3 *v2)
{
    const EIG3_T zero = EIG3_C(0.0), one = EIG3_C(1.0);
    EIG3_M3 a = { a00, a01, a02, a11, a12, a22 };

    /* 1. exact scaling: max-abs entry in [1, 2). The zero matrix (or NaN input) is answered
       at the end; meanwhile its lanes run on harmless values. */
    const EIG3_T amax = EIG3_FN(eig3_max_abs)(a);
    const EIG3_I is_zero = !(amax > zero);
    const EIG3_I e1 = EIG3_FN(eig3_ilogb)(EIG3_SEL(amax, one, is_zero));
    a = EIG3_FN(eig3_ldexp)(a, -e1);

    /* 2. shift to trace 0, rescale exactly, normalise to trace(d^2) = 6. A multiple of the
       identity (c = 0) is answered at the end. */
    const EIG3_T q = (a.a00 + a.a11 + a.a22) / EIG3_C(3.0);
    EIG3_M3 c = EIG3_FN(eig3_shift)(a, q);
    const EIG3_T cmax = EIG3_FN(eig3_max_abs)(c);
    const EIG3_I is_ident = !(cmax > zero);
    c = EIG3_FN(eig3_ldexp)(c, -EIG3_FN(eig3_ilogb)(EIG3_SEL(cmax, one, is_ident)));
    EIG3_T p = sqrt((c.a00 * c.a00 + c.a11 * c.a11 + c.a22 * c.a22
                 + EIG3_C(2.0) * (c.a01 * c.a01 + c.a02 * c.a02 + c.a12 * c.a12))
                / EIG3_C(6.0));                        /* >= 1/sqrt(6) unless c = 0 */
    p = EIG3_SEL(p, one, is_ident);
    const EIG3_M3 d = EIG3_FN(eig3_scale)(c, one / p);

    /* 3. most isolated eigenvalue and its eigenvector */
    const EIG3_T beta = EIG3_FN(eig3_isolated_eigenvalue)(d);
    const EIG3_V3 vi = EIG3_FN(eig3_null_vector)(d, beta);

    /* 4. 2x2 problem in the orthogonal complement (vi, u, v) */
    EIG3_V3 u, v;
    EIG3_FN(eig3_complement)(vi, &u, &v);
    const EIG3_V3 du = EIG3_FN(eig3_mul)(d, u), dv = EIG3_FN(eig3_mul)(d, v);
    EIG3_T cs, sn;
    EIG3_FN(eig3_jacobi2)(EIG3_FN(eig3_dot)(u, du), EIG3_FN(eig3_dot)(u, dv),
                          EIG3_FN(eig3_dot)(v, dv), &cs, &sn);
    EIG3_V3 ea = EIG3_FN(eig3_lin)(cs, u, -sn, v);          /* (vi, ea, eb) stays right-handed */
    EIG3_V3 eb = EIG3_FN(eig3_lin)(sn, u, cs, v);

    /* 5. order the pair by its Rayleigh quotients in d (the isolated one is >= sqrt(3) away);
       (ea, eb) <- (eb, -ea) keeps handedness */
    const EIG3_I swap = EIG3_FN(eig3_rayleigh)(d, eb) < EIG3_FN(eig3_rayleigh)(d, ea);
    const EIG3_V3 nea = EIG3_FN(eig3_vec)(-ea.x, -ea.y, -ea.z);
    const EIG3_V3 fa = EIG3_FN(eig3_sel3)(ea, eb, swap);
    const EIG3_V3 fb = EIG3_FN(eig3_sel3)(eb, nea, swap);
    /* isolated = largest if beta >= 0, else smallest */
    const EIG3_I top = beta >= zero;
    EIG3_V3 x0 = EIG3_FN(eig3_sel3)(vi, fa, top);
    EIG3_V3 x1 = EIG3_FN(eig3_sel3)(fa, fb, top);
    EIG3_V3 x2 = EIG3_FN(eig3_sel3)(fb, vi, top);

    /* 6. eigenvalues = Rayleigh quotients in the unshifted matrix (exactly scaled): as accurate
       as the entries allow, exact for axis-aligned input (e.g. a plane z = 0 gives 0, not
       +-eps). Rounding may break ties the wrong way by an ulp: restore the order. */
    const EIG3_T l0 = EIG3_FN(eig3_rayleigh)(a, x0);
    const EIG3_T l1 = fmax(EIG3_FN(eig3_rayleigh)(a, x1), l0);
    const EIG3_T l2 = fmax(EIG3_FN(eig3_rayleigh)(a, x2), l1);
    EIG3_T f1, f2;
    EIG3_FN(eig3_pow2)(e1, &f1, &f2);

    /* Multiple of the identity (including the zero matrix): w = (a, a, a), basis e_z, e_x, e_y. */
    const EIG3_I dflt = is_ident | is_zero;
    const EIG3_T wid = EIG3_SEL(q * f1 * f2, zero, is_zero);
    *w0 = EIG3_SEL(l0 * f1 * f2, wid, dflt);
    *w1 = EIG3_SEL(l1 * f1 * f2, wid, dflt);
    *w2 = EIG3_SEL(l2 * f1 * f2, wid, dflt);
    *v0 = EIG3_FN(eig3_sel3)(x0, EIG3_FN(eig3_vec)(zero, zero, one), dflt);
    *v1 = EIG3_FN(eig3_sel3)(x1, EIG3_FN(eig3_vec)(one, zero, zero), dflt);
    *v2 = EIG3_FN(eig3_sel3)(x2, EIG3_FN(eig3_vec)(zero, one, zero), dflt);
}

#undef EIG3_V3
#undef EIG3_M3
/* the instantiation's parameters, so that the next one can define them again */
#undef EIG3_T
#undef EIG3_I
#undef EIG3_SEL
#undef EIG3_SELI
#undef EIG3_AS_I
#undef EIG3_AS_R
#undef EIG3_FN

#endif /* EIG3_GENERIC_PASS */
