/* solve6.h -- solve a symmetric positive (semi)definite 6x6 system by an LDL^T
 * factorisation without pivoting, in private memory, with a singularity flag.
 *
 * The matrix is passed as its 21-entry packed lower triangle, row by row:
 *   m[0] = A00; m[1..2] = A10 A11; m[3..5] = A20 A21 A22; ... m[15..20] = A50 .. A55.
 * The system is first scaled symmetrically by D = diag(1/sqrt(A_ii)) (Jacobi scaling), so
 * the test "pivot <= SOLVE6_TOL" is relative and independent of units; a pivot below it
 * (rank deficiency: collinear or too few distinct samples) returns 0 and leaves x as zeros.
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

/* Solves A x = b. Returns 1 on success, 0 when A is (numerically) singular. */
inline int solve6(REAL m[21], const REAL b[6], REAL x[6])
{
    REAL s[6], y[6], d[6];
    for (int i = 0; i < 6; ++i) {
        x[i] = 0;
        const REAL aii = m[S6(i, i)];
        if (!(aii > 0)) return 0;
        s[i] = rsqrt(aii);
    }
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j <= i; ++j)
            m[S6(i, j)] *= s[i] * s[j];
    /* LDL^T in place: L below the diagonal (unit diagonal implied), D on it */
    for (int j = 0; j < 6; ++j) {
        REAL dj = m[S6(j, j)];
        for (int k = 0; k < j; ++k)
            dj -= m[S6(j, k)] * m[S6(j, k)] * d[k];
        if (!(dj > SOLVE6_TOL)) return 0;
        d[j] = dj;
        for (int i = j + 1; i < 6; ++i) {
            REAL lij = m[S6(i, j)];
            for (int k = 0; k < j; ++k)
                lij -= m[S6(i, k)] * m[S6(j, k)] * d[k];
            m[S6(i, j)] = lij / dj;
        }
    }
    for (int i = 0; i < 6; ++i) {                 /* L y = D^-1/2-scaled b */
        REAL v = b[i] * s[i];
        for (int k = 0; k < i; ++k) v -= m[S6(i, k)] * y[k];
        y[i] = v;
    }
    for (int i = 5; i >= 0; --i) {                /* D L^T z = y, x = S z */
        REAL v = y[i] / d[i];
        for (int k = i + 1; k < 6; ++k) v -= m[S6(k, i)] * x[k];
        x[i] = v;
    }
    for (int i = 0; i < 6; ++i) x[i] *= s[i];
    return 1;
}
#endif
