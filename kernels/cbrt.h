/* cbrt.h -- cbrt_pos(x): the cube root of VW non-negative lanes, for the omnivariance
 * (features.cl: one per point).
 *
 * In double, the builtin cbrt. In float, without a division or a library call (PoCL's
 * vector cbrt cost ~4 ms of the 1M-point features kernel, ~5%, on a 2-core AVX2 CPU): an
 * estimate of z = x^(-1/3) from the bits of x (one integer division by 3 of the biased
 * exponent and mantissa, 0x54a21d2a - bits / 3, within ~3.5%), three Newton steps
 * z <- z + z (1 - x z^3) / 3 (the error e becomes ~2 e^2: 3.5e-2, 2.5e-3, 1.2e-5, below
 * float round-off), then y = x z^2 and one Newton step on y itself,
 * y <- y + (x - y^3) z^2 / 3 (the residual by a multiply-add), which leaves y within ~1 ulp
 * of the exact cube root (tests/test_cbrt.py; OpenCL allows the builtin 2). The steps are
 * fma, not mad, whose fused or unfused rounding is the compiler's choice: Intel's CPU
 * runtime (AVX-512) chose differently in two builds of features.cl (ROW_PRUNE on and off),
 * and the omnivariance of ~10% of the points then differed by 1 ulp. Subnormal x
 * are scaled by 2^24 first and y by 2^-8; x = 0 gives 0. Negative, NaN or infinite x:
 * undefined (the caller's values are eigenvalue ratios in [0, 1]).
 */
#ifndef CLCURV_CBRT_H
#define CLCURV_CBRT_H
#include "common.h"

#if REAL_IS_DOUBLE
#define cbrt_pos cbrt
#else
inline REALV cbrt_pos(REALV x)
{
    const IREALV sub = isless(x, (REALV)FLT_MIN);
    const REALV xs = select(x, x * 16777216.0f, sub);           /* 2^24: normal */
    REALV z = CAT(as_, REALV)((IREALV)0x54a21d2a - CAT(as_, IREALV)(xs) / 3);
    for (int it = 0; it < 3; ++it) {
        const REALV r = fma(-xs * z, z * z, (REALV)1);
        z = fma(z * r, (REALV)(1.0f / 3.0f), z);
    }
    const REALV z2 = z * z;
    REALV y = xs * z2;
    y = fma(fma(-y * y, y, xs), z2 * (1.0f / 3.0f), y);
    y = select(y, y * 0.00390625f, sub);                         /* 2^-8 */
    return select((REALV)0, y, isgreater(x, (REALV)0));
}
#endif

#endif
