/* ln.h -- ln_pos(x): the natural logarithm of VW positive lanes, for the eigenentropy
 * (features.cl: three per point).
 *
 * In double, the builtin log. In float, without a division (the builtin's vector log cost
 * ~1 ms of the 1M-point features kernel, ~2% on PoCL): x = m 2^e with m in [sqrt(1/2),
 * sqrt(2)), ln x = e ln 2 + ln(1 + t), t = m - 1, ln(1 + t) = t - t^2 / 2 + t^3 P(t) with
 * the minimax P of Cephes's logf, and ln 2 in two parts (0.693359375 - 2.12194440e-4) so
 * that e ln 2 adds no rounding. Subnormal x are scaled by 2^24 first. Within 1 ulp of the
 * exact ln on normal and subnormal floats (0.78 measured, tests/test_ln.py); x = 0, negative,
 * NaN or infinite: undefined (the caller selects those out).
 */
#ifndef CLCURV_LN_H
#define CLCURV_LN_H
#include "common.h"

#if REAL_IS_DOUBLE
#define ln_pos log
#else
inline REALV ln_pos(REALV x)
{
    const IREALV sub = isless(x, (REALV)FLT_MIN);
    x = select(x, x * 16777216.0f, sub);
    const IREALV bits = CAT(as_, IREALV)(x);
    IREALV e = ((bits >> 23) & 0xff) - select((IREALV)127, (IREALV)151, sub);
    REALV m = CAT(as_, REALV)((bits & 0x007fffff) | 0x3f800000);     /* [1, 2) */
    const IREALV big = isgreater(m, (REALV)1.41421356f);
    m = select(m, m * 0.5f, big);
    e -= big;                                   /* a true comparison is -1 */
    const REALV t = m - 1.0f, z = t * t, fe = CAT(convert_, REALV)(e);
    REALV p = 7.0376836292e-2f;
    p = p * t - 1.1514610310e-1f;
    p = p * t + 1.1676998740e-1f;
    p = p * t - 1.2420140846e-1f;
    p = p * t + 1.4249322787e-1f;
    p = p * t - 1.6668057665e-1f;
    p = p * t + 2.0000714765e-1f;
    p = p * t - 2.4999993993e-1f;
    p = p * t + 3.3333331174e-1f;
    REALV y = t * z * p;
    y = fe * -2.12194440e-4f + y;
    y = -0.5f * z + y;
    return fe * 0.693359375f + (t + y);
}
#endif

#endif
