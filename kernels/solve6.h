/* solve6.h -- VW symmetric positive (semi)definite 6x6 systems solved at once, one per
 * vector lane, by an LDL^T factorisation without pivoting, with a per-lane singularity mask.
 *
 * Each matrix is passed as its 21-entry packed lower triangle, row by row:
 *   m[0] = A00; m[1..2] = A10 A11; m[3..5] = A20 A21 A22; ... m[15..20] = A50 .. A55,
 * every entry a REALV whose lane k belongs to system k. The systems are first scaled
 * symmetrically by D = diag(1/sqrt(A_ii)) (Jacobi scaling), so the test "pivot <= SOLVE6_TOL"
 * is relative and unit-free; a lane whose pivot falls below it (rank deficiency: collinear or
 * too few distinct samples) gets mask 0 and x = 0. No branches: lanes never diverge.
 */
#ifndef CLCURV_SOLVE6_H
#define CLCURV_SOLVE6_H
#include "common.h"

#if REAL_IS_DOUBLE
#define SOLVE6_TOL 1e-12
#else
#define SOLVE6_TOL 1e-6f
#endif

#define S6(i, j) ((i) * ((i) + 1) / 2 + (j))   /* packed index of A_ij, i >= j */

/* Factorises A_k = S^-1 L D L^T S^-1 in every lane k, in place (m then holds L below the
 * diagonal of the scaled system), S = diag(s), D = diag(d); returns the mask of the lanes
 * whose pivots all pass SOLVE6_TOL. */
inline IREALV factor6_v(REALV m[21], REALV s[6], REALV d[6])
{
    IREALV ok = (IREALV)(-1);
    for (int i = 0; i < 6; ++i) {
        const IREALV pos = isgreater(m[S6(i, i)], (REALV)0);
        ok &= pos;
        s[i] = rsqrt(select((REALV)1, m[S6(i, i)], pos));
    }
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j <= i; ++j)
            m[S6(i, j)] *= s[i] * s[j];
    /* LDL^T in place: L below the diagonal (unit diagonal implied), D on it */
    for (int j = 0; j < 6; ++j) {
        REALV dj = m[S6(j, j)];
        for (int k = 0; k < j; ++k)
            dj -= m[S6(j, k)] * m[S6(j, k)] * d[k];
        const IREALV good = isgreater(dj, (REALV)SOLVE6_TOL);
        ok &= good;
        d[j] = select((REALV)1, dj, good);
        for (int i = j + 1; i < 6; ++i) {
            REALV lij = m[S6(i, j)];
            for (int k = 0; k < j; ++k)
                lij -= m[S6(i, k)] * m[S6(j, k)] * d[k];
            m[S6(i, j)] = lij / d[j];
        }
    }
    return ok;
}

/* x = A^-1 b in every lane from factor6_v's m, s, d (0 in the lanes where ok is 0). */
inline void subst6_v(const REALV m[21], const REALV s[6], const REALV d[6], const IREALV ok,
                     const REALV b[6], REALV x[6])
{
    REALV y[6];
    for (int i = 0; i < 6; ++i) {                 /* L y = S b */
        REALV v = b[i] * s[i];
        for (int k = 0; k < i; ++k) v -= m[S6(i, k)] * y[k];
        y[i] = v;
    }
    for (int i = 5; i >= 0; --i) {                /* D L^T z = y */
        REALV v = y[i] / d[i];
        for (int k = i + 1; k < 6; ++k) v -= m[S6(k, i)] * x[k];
        x[i] = v;
    }
    for (int i = 0; i < 6; ++i) x[i] = select((REALV)0, x[i] * s[i], ok);   /* x = S z */
}

/* Solves A_k x_k = b_k in every lane k; returns the mask of the lanes that succeeded. m is
 * left factorised (factor6_v), for further right-hand sides (subst6_v). */
inline IREALV solve6_v(REALV m[21], REALV s[6], REALV d[6], const REALV b[6], REALV x[6])
{
    const IREALV ok = factor6_v(m, s, d);
    subst6_v(m, s, d, ok, b, x);
    return ok;
}
#endif
