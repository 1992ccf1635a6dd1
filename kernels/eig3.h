/* eig3.h -- closed-form eigen decomposition of a symmetric 3x3 matrix (float or double).
 *
 * Method (no iterations, no data-dependent loops):
 *   1. Scale A by a power of two (exact) so that its max-abs entry lies in [1, 2).
 *   2. Shift by q = trace/3 and scale again by a power of two:  C = (A/2^e1 - qI) / 2^e2,
 *      then normalise D = C / p with p = sqrt(trace(C^2)/6), so that trace(D) = 0 and
 *      trace(D^2) = 6: the eigenvalues beta of D satisfy beta^3 - 3 beta = det(D) and lie in
 *      [-2, 2]; they are beta_k = 2 cos(acos(det(D)/2)/3 + 2 pi k/3) (trigonometric method).
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
 * Overflow: only if an eigenvalue itself exceeds REAL_MAX (entries close to REAL_MAX).
 * Scaling A by a power of two scales w exactly and leaves v0, v1, v2 bit-identical.
 * Denormal inputs are handled if the device does not flush them to zero.
 * Ideas from D. Eberly, "A Robust Eigensolver for 3x3 Symmetric Matrices" (Geometric Tools).
 */
#ifndef CLCURV_EIG3_H
#define CLCURV_EIG3_H

#include "common.h"

#if REAL_IS_DOUBLE
#define EIG3_C(x) x          /* REAL literal */
#else
#define EIG3_C(x) x##f
#endif

/* Symmetric 3x3 matrix stored by its upper triangle. */
typedef struct {
    REAL a00, a01, a02, a11, a12, a22;
} eig3_mat;

/* Largest absolute entry. */
inline REAL eig3_max_abs(eig3_mat m)
{
    REAL d = fmax(fmax(fabs(m.a00), fabs(m.a11)), fabs(m.a22));
    REAL o = fmax(fmax(fabs(m.a01), fabs(m.a02)), fabs(m.a12));
    return fmax(d, o);
}

/* m * s for every entry. */
inline eig3_mat eig3_scale(eig3_mat m, REAL s)
{
    eig3_mat r = { m.a00 * s, m.a01 * s, m.a02 * s, m.a11 * s, m.a12 * s, m.a22 * s };
    return r;
}

/* 2^e as two exact power-of-two factors (each within the exponent range even when 2^e is
   not), so scaling by them is exact and costs multiplications, not ldexp calls. */
#if REAL_IS_DOUBLE
#define EIG3_MANT 52
#define EIG3_BIAS 1023
#define EIG3_AS_REAL(b) as_double(b)
#define EIG3_AS_BITS(x) as_long(x)
typedef long eig3_bits;
#else
#define EIG3_MANT 23
#define EIG3_BIAS 127
#define EIG3_AS_REAL(b) as_float(b)
#define EIG3_AS_BITS(x) as_int(x)
typedef int eig3_bits;
#endif

/* 2^h for |h| well inside the normal exponent range, from its bits (no library call). */
inline REAL eig3_exp2i(int h)
{
    return EIG3_AS_REAL(((eig3_bits)(h + EIG3_BIAS)) << EIG3_MANT);
}

/* floor(log2(x)) of a positive finite x: read from the bits, ilogb only for denormals. */
inline int eig3_ilogb(REAL x)
{
    const int biased = (int)((EIG3_AS_BITS(x) >> EIG3_MANT) & (2 * EIG3_BIAS + 1));
    return biased != 0 ? biased - EIG3_BIAS : ilogb(x);
}

inline void eig3_pow2(int e, REAL *f1, REAL *f2)
{
    const int h = e / 2;
    *f1 = eig3_exp2i(h);
    *f2 = eig3_exp2i(e - h);
}

/* m * 2^e for every entry (exact unless the result is denormal). */
inline eig3_mat eig3_ldexp(eig3_mat m, int e)
{
    REAL f1, f2;
    eig3_pow2(e, &f1, &f2);
    return eig3_scale(eig3_scale(m, f1), f2);
}

/* m - s I */
inline eig3_mat eig3_shift(eig3_mat m, REAL s)
{
    m.a00 -= s;
    m.a11 -= s;
    m.a22 -= s;
    return m;
}

/* Matrix-vector product m v. */
inline REAL3 eig3_mul(eig3_mat m, REAL3 v)
{
    return (REAL3)(m.a00 * v.x + m.a01 * v.y + m.a02 * v.z,
                   m.a01 * v.x + m.a11 * v.y + m.a12 * v.z,
                   m.a02 * v.x + m.a12 * v.y + m.a22 * v.z);
}

/* Rayleigh quotient v^T m v of a unit vector v. */
inline REAL eig3_rayleigh(eig3_mat m, REAL3 v)
{
    return dot(v, eig3_mul(m, v));
}

/* Isolated eigenvalue of a matrix d with trace 0 and trace(d^2) = 6: the largest one
   2 cos(acos(r)/3) if r = det(d)/2 >= 0, else the smallest, -2 cos(acos(-r)/3). The
   angle acos(|r|)/3 lies in [0, pi/6], where cos is flat: the value is accurate even
   when the other two eigenvalues are (nearly) equal, i.e. |r| close to 1. */
inline REAL eig3_isolated_eigenvalue(eig3_mat d)
{
    REAL det = d.a00 * (d.a11 * d.a22 - d.a12 * d.a12)
             - d.a01 * (d.a01 * d.a22 - d.a12 * d.a02)
             + d.a02 * (d.a01 * d.a12 - d.a11 * d.a02);
    REAL r = clamp(EIG3_C(0.5) * det, EIG3_C(-1.0), EIG3_C(1.0));
    REAL b = EIG3_C(2.0) * cos(acos(fabs(r)) / EIG3_C(3.0));
    return r >= EIG3_C(0.0) ? b : -b;
}

/* Unit vector spanning the kernel of the rank-2 matrix m = d - beta I: the longest of the
   cross products of its rows (for a simple eigenvalue beta they are all parallel to the
   eigenvector; the longest has norm >= sqrt(3) here). */
inline REAL3 eig3_null_vector(eig3_mat d, REAL beta)
{
    eig3_mat m = eig3_shift(d, beta);
    REAL3 r0 = (REAL3)(m.a00, m.a01, m.a02);
    REAL3 r1 = (REAL3)(m.a01, m.a11, m.a12);
    REAL3 r2 = (REAL3)(m.a02, m.a12, m.a22);
    REAL3 c01 = cross(r0, r1), c02 = cross(r0, r2), c12 = cross(r1, r2);
    REAL n01 = dot(c01, c01), n02 = dot(c02, c02), n12 = dot(c12, c12);
    REAL3 c = c01;
    REAL n = n01;
    if (n02 > n) { c = c02; n = n02; }
    if (n12 > n) { c = c12; n = n12; }
    if (!(n > EIG3_C(0.0)))           /* unreachable for finite input; keeps NaN out */
        return (REAL3)(EIG3_C(0.0), EIG3_C(0.0), EIG3_C(1.0));
    return c / sqrt(n);
}

/* Unit vectors u, v with (w, u, v) a right-handed orthonormal basis, for a unit vector w.
   u is built from the two largest components of w, so its norm before scaling is >= 1/sqrt(2). */
inline void eig3_complement(REAL3 w, REAL3 *u, REAL3 *v)
{
    if (fabs(w.x) > fabs(w.y))
        *u = (REAL3)(-w.z, EIG3_C(0.0), w.x) / sqrt(w.x * w.x + w.z * w.z);
    else
        *u = (REAL3)(EIG3_C(0.0), w.z, -w.y) / sqrt(w.y * w.y + w.z * w.z);
    *v = cross(w, *u);
}

/* Jacobi rotation (c, s) diagonalising the symmetric 2x2 [[m00, m01], [m01, m11]]: the
   eigenvectors are (c, -s) and (s, c). t = tan of the smaller of the two possible angles,
   computed without overflow (hypot) and without dividing by m01 == 0. */
inline void eig3_jacobi2(REAL m00, REAL m01, REAL m11, REAL *c, REAL *s)
{
    REAL t = EIG3_C(0.0);
    if (m01 != EIG3_C(0.0)) {
        REAL theta = (m11 - m00) / (EIG3_C(2.0) * m01);     /* may be +-inf: then t = 0 */
        t = EIG3_C(1.0) / (fabs(theta) + hypot(theta, EIG3_C(1.0)));
        if (theta < EIG3_C(0.0))
            t = -t;
    }
    *c = EIG3_C(1.0) / sqrt(t * t + EIG3_C(1.0));
    *s = t * *c;
}

/* Eigen decomposition of the symmetric matrix [[a00,a01,a02],[a01,a11,a12],[a02,a12,a22]].
   Writes eigenvalues ascending into *w (w->x <= w->y <= w->z) and unit eigenvectors v0, v1, v2
   (v0 for w->x, ...) forming a right-handed orthonormal basis (v2 = cross(v0, v1)).
   Multiple of the identity (including the zero matrix): w = (a, a, a) and v0, v1, v2 = e_z, e_x, e_y.
   For other repeated eigenvalues the basis of the eigenspace is arbitrary but orthonormal. */
inline void eig3_sym(REAL a00, REAL a01, REAL a02, REAL a11, REAL a12, REAL a22,
                     REAL3 *w, REAL3 *v0, REAL3 *v1, REAL3 *v2)
{
    const REAL zero = EIG3_C(0.0), one = EIG3_C(1.0);
    eig3_mat a = { a00, a01, a02, a11, a12, a22 };

    /* Default answer for a multiple of the identity. */
    *v0 = (REAL3)(zero, zero, one);
    *v1 = (REAL3)(one, zero, zero);
    *v2 = (REAL3)(zero, one, zero);

    /* 1. exact scaling: max-abs entry in [1, 2) */
    REAL amax = eig3_max_abs(a);
    if (!(amax > zero)) {
        *w = (REAL3)(zero, zero, zero);
        return;
    }
    int e1 = eig3_ilogb(amax);
    a = eig3_ldexp(a, -e1);

    /* 2. shift to trace 0, rescale exactly, normalise to trace(d^2) = 6 */
    REAL q = (a.a00 + a.a11 + a.a22) / EIG3_C(3.0);
    eig3_mat c = eig3_shift(a, q);
    REAL cmax = eig3_max_abs(c);
    if (!(cmax > zero)) {
        REAL f1, f2;
        eig3_pow2(e1, &f1, &f2);
        *w = (REAL3)(q * f1 * f2);
        return;
    }
    int e2 = eig3_ilogb(cmax);
    c = eig3_ldexp(c, -e2);
    REAL p = sqrt((c.a00 * c.a00 + c.a11 * c.a11 + c.a22 * c.a22
                   + EIG3_C(2.0) * (c.a01 * c.a01 + c.a02 * c.a02 + c.a12 * c.a12))
                  / EIG3_C(6.0));                      /* >= 1/sqrt(6) */
    eig3_mat d = eig3_scale(c, one / p);

    /* 3. most isolated eigenvalue and its eigenvector */
    REAL beta = eig3_isolated_eigenvalue(d);
    REAL3 vi = eig3_null_vector(d, beta);

    /* 4. 2x2 problem in the orthogonal complement (vi, u, v) */
    REAL3 u, v;
    eig3_complement(vi, &u, &v);
    REAL3 du = eig3_mul(d, u), dv = eig3_mul(d, v);
    REAL cs, sn;
    eig3_jacobi2(dot(u, du), dot(u, dv), dot(v, dv), &cs, &sn);
    REAL3 ea = cs * u - sn * v;               /* (vi, ea, eb) stays right-handed */
    REAL3 eb = sn * u + cs * v;

    /* 5. order the pair by its Rayleigh quotients in d (the isolated one is >= sqrt(3) away) */
    if (eig3_rayleigh(d, eb) < eig3_rayleigh(d, ea)) {
        REAL3 t = ea;                         /* (ea, eb) <- (eb, -ea) keeps handedness */
        ea = eb;
        eb = -t;
    }
    if (beta >= zero) {                       /* isolated = largest */
        *v0 = ea; *v1 = eb; *v2 = vi;
    } else {                                  /* isolated = smallest */
        *v0 = vi; *v1 = ea; *v2 = eb;
    }

    /* 6. eigenvalues = Rayleigh quotients in the unshifted matrix (exactly scaled): as accurate
       as the entries allow, exact for axis-aligned input (e.g. a plane z = 0 gives 0, not
       +-eps). Rounding may break ties the wrong way by an ulp: restore the order. */
    REAL l0 = eig3_rayleigh(a, *v0);
    REAL l1 = fmax(eig3_rayleigh(a, *v1), l0);
    REAL l2 = fmax(eig3_rayleigh(a, *v2), l1);
    REAL f1, f2;
    eig3_pow2(e1, &f1, &f2);
    *w = (REAL3)(l0, l1, l2) * f1 * f2;
}

#endif
