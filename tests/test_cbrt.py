"""kernels/cbrt.h (cbrt_pos: the omnivariance's cube root, division-free in float) against
numpy's long double cbrt (its float64 cbrt is itself up to 3 ulp off), on every device:
float within 1 ulp of the exact result on zero, normal and subnormal floats across the
whole exponent range, and the builtin cbrt in double."""
import numpy as np
import pytest

from test_eig3 import cl_env, lane_function  # noqa: F401  (the fixture)

#: float: ours, measured 0.95 ulp at most on PoCL, 0.75 on Intel (whose mad is a fused
#: multiply-add); double: the builtin cbrt, which OpenCL allows 2 ulp (0.54 measured)
ULPS = {"float": 1.0, "double": 2.0}


def _inputs(dtype):
    rng = np.random.default_rng(5)
    fi = np.finfo(dtype)
    tiny = float(fi.smallest_subnormal)
    x = [np.logspace(np.log10(tiny), np.log10(float(fi.max)) - 0.01, 200000),
         rng.uniform(0, 1, 200000),                      # the omnivariance's ratios
         rng.uniform(1e-12, 1e-3, 50000),
         np.ldexp(1.0, np.arange(-149, 128)),            # powers of 2: exponent residues
         np.arange(1, 2000) ** 3.0 / 1e6,                # exact cubes
         [0.0, tiny, float(fi.tiny), float(fi.tiny) * (1 - fi.eps), 1.0]]
    x = np.concatenate(x).astype(dtype)
    return x[(x >= 0) & np.isfinite(x)]


@pytest.mark.parametrize("precision", ["float", "double"])
def test_cbrt_pos_within_an_ulp(cl_env, precision):
    device, ctx, queue = cl_env
    if precision == "double" and "cl_khr_fp64" not in device.extensions:
        pytest.skip("the device has no float64")
    if precision == "double" and np.finfo(np.longdouble).nmant <= 52:
        pytest.skip("numpy's longdouble is float64 here: no exact reference for double")
    dtype = np.float64 if precision == "double" else np.float32
    x = _inputs(dtype)
    got = lane_function(ctx, queue, precision, "cbrt.h", "cbrt_pos", x).astype(np.longdouble)
    want = np.cbrt(x.astype(np.longdouble))            # x86: 64-bit mantissa
    zero = x == 0
    assert (got[zero] == 0).all()
    # the error in units of the spacing of floats at the exact result
    ulp = np.spacing(want.astype(dtype)).astype(np.longdouble)
    err = np.abs(got - want)[~zero] / ulp[~zero]
    assert err.max() <= ULPS[precision], (err.max(), x[~zero][np.argmax(err)])
