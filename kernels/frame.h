/* frame.h -- small geometric helpers shared by the normal-based and MLS kernels:
 * a deterministic tangent frame and a closed-form symmetric 2x2 eigen solver (VW lanes). */
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

/* Eigen decompositions of the VW matrices [[a, b], [b, c]] of the lanes: l1 >= l2 and the
 * unit eigenvector (e1x, e1y) of l1 (the one of l2 is (-e1y, e1x)). Exact for diagonal
 * input, no division by zero; entries as small as 2dcov1's (~ r^6 k^2) are scaled before
 * they are squared, so nothing underflows (no library hypot or length: slow on PoCL). */
inline void eig2_sym_v(REALV a, REALV b, REALV c, REALV *l1, REALV *l2, REALV *e1x,
                       REALV *e1y)
{
    const REALV h = (REAL)0.5 * (a - c);
    const REALV big = fmax(fabs(h), fabs(b));
    const REALV ib = select((REALV)0, (REAL)1 / big, isgreater(big, (REALV)0));
    const REALV rad = big * sqrt((h * ib) * (h * ib) + (b * ib) * (b * ib));
    const REALV m = (REAL)0.5 * (a + c);
    *l1 = m + rad;
    *l2 = m - rad;
    /* eigenvector of l1: (h + rad, b) or (b, rad - h), the better conditioned one */
    const IREALV pos = isgreaterequal(h, (REALV)0);
    const REALV vx = select(b, h + rad, pos), vy = select(rad - h, b, pos);
    const REALV vm = fmax(fabs(vx), fabs(vy));
    const IREALV any = isgreater(vm, (REALV)0);
    const REALV iv = select((REALV)0, (REAL)1 / vm, any);
    const REALV nv = vm * sqrt((vx * iv) * (vx * iv) + (vy * iv) * (vy * iv));
    *e1x = select((REALV)1, vx / nv, any);
    *e1y = select((REALV)0, vy / nv, any);
}
#endif
