"""kernels/ln.h (ln_pos: the eigenentropy's logarithm, division-free in float) against
numpy's float64 log, on every device: float within 1 ulp of the exact result, on
normal and subnormal floats across the whole exponent range (and near 1, where ln -> 0 and
its relative accuracy matters), and the builtin log in double."""
import numpy as np
import pytest

from test_eig3 import cl_env, lane_function  # noqa: F401  (the fixture)

#: float: ours, measured 0.78 ulp at most on PoCL and Intel; double: the builtin log, which
#: OpenCL allows 3 ulp
ULPS = {"float": 1.0, "double": 3.0}


def _inputs(dtype):
    rng = np.random.default_rng(3)
    tiny = np.finfo(dtype).smallest_subnormal if hasattr(np.finfo(dtype), "smallest_subnormal") \
        else np.finfo(dtype).tiny * np.finfo(dtype).eps
    x = [np.logspace(np.log10(float(tiny)), np.log10(float(np.finfo(dtype).max)) - 0.01, 200000),
         1 + rng.uniform(-0.3, 0.42, 100000),                  # ln(1 + t) near 0
         1 + np.linspace(-1e-6, 1e-6, 20001),
         np.sqrt(0.5) * (1 + np.linspace(-1e-5, 1e-5, 2001)),     # the range split
         np.sqrt(2.0) * (1 + np.linspace(-1e-5, 1e-5, 2001)),
         np.ldexp(1.0, np.arange(-149, 128)).clip(float(tiny), None),
         rng.uniform(1e-12, 1e-3, 50000)]                          # eigenvalues ~ r^2
    x = np.concatenate(x).astype(dtype)
    return x[(x > 0) & np.isfinite(x)]


@pytest.mark.parametrize("precision", ["float", "double"])
def test_ln_pos_within_an_ulp(cl_env, precision):
    device, ctx, queue = cl_env
    if precision == "double" and "cl_khr_fp64" not in device.extensions:
        pytest.skip("the device has no float64")
    dtype = np.float64 if precision == "double" else np.float32
    x = _inputs(dtype)
    got = lane_function(ctx, queue, precision, "ln.h", "ln_pos", x).astype(np.float64)
    want = np.log(x.astype(np.float64))
    # the error in units of the spacing of floats at the exact result (ulp of |ln x|; for
    # ln x = 0 exactly, x = 1, the result must be 0)
    ulp = np.spacing(np.abs(want).astype(dtype)).astype(np.float64)
    zero = want == 0
    assert (got[zero] == 0).all()
    err = np.abs(got - want)[~zero] / ulp[~zero]
    assert err.max() <= ULPS[precision], (err.max(), x[~zero][np.argmax(err)])
