/* frame.h -- small geometric helpers shared by the normal-based and MLS kernels:
 * a deterministic tangent frame and a closed-form symmetric 2x2 eigen solver. */
#ifndef CLCURV_FRAME_H
#define CLCURV_FRAME_H
#include "common.h"

/* Unit tangents (t1, t2) with t1 x t2 = n for a unit n: t1 = n x e / |n x e| with e the
 * coordinate axis least aligned with n, t2 = n x t1 (same rule as reference.tangent_frame). */
inline void tangent_frame(REAL3 n, REAL3 *t1, REAL3 *t2)
{
    const REAL3 a = fabs(n);
    REAL3 e = (REAL3)(1, 0, 0);
    if (a.y < a.x && a.y <= a.z) e = (REAL3)(0, 1, 0);
    else if (a.z < a.x && a.z < a.y) e = (REAL3)(0, 0, 1);
    *t1 = normalize(cross(n, e));
    *t2 = cross(n, *t1);
}

/* Eigen decomposition of [[a, b], [b, c]]: l1 >= l2 and the unit eigenvector (c1, s1) of
 * l1 (the one of l2 is (-s1, c1)). Exact for diagonal input, no division by zero. */
inline void eig2_sym(REAL a, REAL b, REAL c, REAL *l1, REAL *l2, REAL2 *e1)
{
    const REAL h = (REAL)0.5 * (a - c);
    /* hypot without the library call (slow on PoCL): scaled so that tiny entries (2dcov1's
       are ~ r^6 k^2) cannot underflow when squared */
    const REAL big = fmax(fabs(h), fabs(b));
    const REAL ib = big > 0 ? (REAL)1 / big : (REAL)0;
    const REAL rad = big * sqrt((h * ib) * (h * ib) + (b * ib) * (b * ib));
    const REAL m = (REAL)0.5 * (a + c);
    *l1 = m + rad;
    *l2 = m - rad;
    /* eigenvector of l1: (h + rad, b) or (b, rad - h), the better conditioned one */
    REAL2 v = (h >= 0) ? (REAL2)(h + rad, b) : (REAL2)(b, rad - h);
    const REAL nv = length(v);
    *e1 = nv > 0 ? v / nv : (REAL2)(1, 0);
}
#endif
