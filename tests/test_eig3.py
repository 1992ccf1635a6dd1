"""kernels/eig3.h (closed-form symmetric 3x3 eigen solver) against numpy.linalg.eigh.

Every matrix is rounded to the kernel precision first; the reference is eigh (float64) of the
rounded matrix, so only the solver's own error is measured.

Tolerances, in units of the kernel's machine epsilon eps (float 1.19e-7, double 2.22e-16):
  * eigenvalues, residual |A v_i - w_i v_i|:  32 eps * max|lambda|
        (float 3.8e-6, double 7.1e-15). The solver is backward stable: its error is a sum of
        ~20 roundings (shift, normalisation, cross products, rotation, Rayleigh quotient), each
        <= eps * max|lambda|. Measured max on 10^4 random matrices: 4.6 eps (float), 8 eps
        (double); 32 eps leaves room for devices whose sqrt / division are only 2.5-3 ulp
        accurate, as OpenCL allows for float. (double: far tighter than 1e-12.)
  * orthonormality |V^T V - I|, det(V) - 1:  16 eps (float 1.9e-6, double 3.6e-15);
        measured <= 5 eps.
  * eigenvectors: perturbation theory bounds the angle to the true eigenvector by
        eps * max|lambda| / gap_i (gap_i: distance to the nearest other eigenvalue), so we assert
        sin(angle) <= 16 eps * max|lambda| / gap_i  (measured factor <= 4.3), and for well
        separated eigenvalues (gap_i >= 1e-2 max|lambda|) also 1 - |cos| <= 16 eps.
  * surface normal: lambda0 / lambda2 = 1e-6 in float32: |cos(v0, v0_true)| >= 1 - 1e-5.
Special inputs (zero, diagonal, axis-aligned planes, multiples of the identity) are exact.
"""
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import clcurv
from clcurv._shared.constants import kernel_defines
from conftest import DEVICES, NAMES

KERNELS = Path(__file__).resolve().parent.parent / "kernels"

SOURCE = r"""
#include "eig3.h"
/* a: 6 entries per matrix (a00 a01 a02 a11 a12 a22); out: w, v0, v1, v2 (12 REALs) */
__kernel void eig3_test(__global const REAL *a, __global REAL *out, const int n)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    __global const REAL *m = a + 6 * i;
    REAL3 w, v0, v1, v2;
    eig3_sym(m[0], m[1], m[2], m[3], m[4], m[5], &w, &v0, &v1, &v2);
    __global REAL *o = out + 12 * i;
    vstore3(w, 0, o);
    vstore3(v0, 1, o);
    vstore3(v1, 2, o);
    vstore3(v2, 3, o);
}
"""

UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
N = 10_000
EIG_FACTOR = 32      # eigenvalues and residuals: 32 eps * max|lambda|
ORTH_FACTOR = 16     # V^T V - I, det V - 1, 1 - |cos| for separated eigenvalues: 16 eps
VEC_FACTOR = 16      # sin(angle) <= 16 eps * max|lambda| / gap
SEPARATED = 1e-2     # relative gap of a "well separated" eigenvalue


# --------------------------------------------------------------------------- build helpers
@pytest.fixture(scope="module", params=DEVICES or [None], ids=lambda i: NAMES.get(i, "none"))
def cl_env(request):
    """Every real OpenCL device (conftest.DEVICES), with a context and a queue (fails, like
    conftest.device, when there is none)."""
    if request.param is None:
        pytest.fail("no OpenCL device found")
    device = clcurv.get_device(request.param).cl_device
    ctx = cl.Context([device])
    return device, ctx, cl.CommandQueue(ctx)


def build_program(ctx, precision, source=None, vw=8):
    """Build ``source`` (default SOURCE) for 'float' or 'double' with the host's constants."""
    options = ["-I", str(KERNELS), "-D", f"REAL_IS_DOUBLE={int(precision == 'double')}",
               "-D", f"VW={vw}"] + [f"-D{k}={v}" for k, v in kernel_defines().items()]
    return cl.Program(ctx, source or SOURCE).build(options=options)


def lane_function(ctx, queue, precision, header, fn, x, vw=8):
    """``fn`` of ``header`` (a REALV -> REALV function of the kernels) on the values ``x``,
    VW lanes at a time on the device of ``queue``: its results, in ``x``'s dtype."""
    source = f"""
#include "{header}"
__kernel void lane_test(__global const REAL *x, __global REAL *out, const uint n)
{{
    const uint i = get_global_id(0) * VW;
    if (i >= n) return;
    CAT(vstore, VW)({fn}(VLOADV(0, x + i)), 0, out + i);
}}
"""
    prg = build_program(ctx, precision, source, vw)
    n = len(x)
    pad = np.ones(-(-n // vw) * vw, x.dtype)
    pad[:n] = x
    mf = cl.mem_flags
    xb = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=pad)
    ob = cl.Buffer(ctx, mf.WRITE_ONLY, pad.nbytes)
    prg.lane_test(queue, (len(pad) // vw,), None, xb, ob, np.uint32(len(pad)))
    out = np.empty_like(pad)
    cl.enqueue_copy(queue, out, ob)
    return out[:n]


class Eig3:
    """Runs eig3_sym on a stack of symmetric matrices in one precision; ``vw`` matrices per
    work-item (``source`` holding an eig3_test kernel of that shape)."""

    def __init__(self, ctx, queue, precision, source=None, vw=1):
        self.ctx, self.queue, self.precision, self.vw = ctx, queue, precision, vw
        self.dtype = np.float64 if precision == "double" else np.float32
        self.eps = float(np.finfo(self.dtype).eps)
        program = build_program(ctx, precision, source, vw if source else 8)
        self.kernel = cl.Kernel(program, "eig3_test")

    def __call__(self, A):
        """A: (n, 3, 3) symmetric. Returns (A as seen by the kernel in float64, w, V) with
        w (n, 3) and V (n, 3, 3) whose columns are v0, v1, v2, both in float64."""
        A = np.asarray(A, dtype=np.float64).reshape(-1, 3, 3)
        n = len(A)
        a = np.ascontiguousarray(np.stack([A[:, i, j] for i, j in UPPER], 1), dtype=self.dtype)
        out = np.empty((n, 12), self.dtype)
        mf = cl.mem_flags
        a_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
        o_buf = cl.Buffer(self.ctx, mf.WRITE_ONLY, out.nbytes)
        self.kernel(self.queue, (-(-n // self.vw),), None, a_buf, o_buf, np.int32(n))
        cl.enqueue_copy(self.queue, out, o_buf)
        seen = np.zeros((n, 3, 3))
        for k, (i, j) in enumerate(UPPER):
            seen[:, i, j] = seen[:, j, i] = a[:, k]
        w = out[:, :3].astype(np.float64)
        V = out[:, 3:].reshape(n, 3, 3).transpose(0, 2, 1).astype(np.float64)
        return seen, w, V


@pytest.fixture(scope="module", params=["float", "double"])
def eig3(request, cl_env):
    device, ctx, queue = cl_env
    if request.param == "double" and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64")
    return Eig3(ctx, queue, request.param)


# --------------------------------------------------------------------------- generators
def rotations(rng, n):
    """n uniformly random rotation matrices (det +1)."""
    Q, R = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    Q = Q * np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]
    Q[np.linalg.det(Q) < 0, :, 0] *= -1
    return Q


def with_eigenvalues(rng, lam):
    """R diag(lam) R^T for random rotations R; lam (n, 3)."""
    R = rotations(rng, len(lam))
    return np.einsum("nij,nj,nkj->nik", R, lam, R)


def random_symmetric(rng, n=N):
    X = rng.uniform(-1, 1, (n, 3, 3))
    return (X + X.transpose(0, 2, 1)) / 2


def covariances(rng, n=N):
    """SPD, eigenvalue ratios log-uniform in [1e-6, 1], overall scale log-uniform."""
    lam = 10.0 ** rng.uniform(-6, 0, (n, 3))
    return with_eigenvalues(rng, lam * 10.0 ** rng.uniform(-3, 3, (n, 1)))


# --------------------------------------------------------------------------- checks
def gaps(wr):
    """Distance of each reference eigenvalue to the nearest other one."""
    d = np.abs(wr[:, :, None] - wr[:, None, :]) + np.diag([np.inf] * 3)
    return d.min(2)


def check(eig3, A):
    """Assert the decomposition of A (n, 3, 3) against eigh with the module tolerances.
    Eigenvectors are compared only where the gap makes them well defined, so repeated
    eigenvalues are covered by the orthonormality and residual checks."""
    Ain, w, V = eig3(A)
    eps = eig3.eps
    assert np.isfinite(w).all() and np.isfinite(V).all(), "NaN/Inf in output"
    assert (np.diff(w, axis=1) >= 0).all(), "eigenvalues not ascending"

    wr, Vr = np.linalg.eigh(Ain)
    scale = np.abs(wr).max(1)
    err = np.abs(w - wr).max(1)
    assert (err <= EIG_FACTOR * eps * scale).all(), \
        f"eigenvalue error {np.max(err / np.where(scale > 0, scale, 1)) / eps:.3g} eps"

    orth = np.abs(np.einsum("nji,njk->nik", V, V) - np.eye(3)).max((1, 2))
    assert (orth <= ORTH_FACTOR * eps).all(), f"|V^T V - I| = {orth.max() / eps:.3g} eps"
    det = np.linalg.det(V)
    assert (np.abs(det - 1) <= ORTH_FACTOR * eps).all(), \
        f"det(V) - 1 = {np.abs(det - 1).max() / eps:.3g} eps (not right-handed?)"

    res = np.linalg.norm(np.einsum("nij,njk->nik", Ain, V) - V * w[:, None, :], axis=1).max(1)
    assert (res <= EIG_FACTOR * eps * scale).all(), \
        f"residual {np.max(res / np.where(scale > 0, scale, 1)) / eps:.3g} eps"

    g = gaps(wr)
    sin = np.linalg.norm(np.cross(V.transpose(0, 2, 1), Vr.transpose(0, 2, 1)), axis=2)
    bound = VEC_FACTOR * eps * scale[:, None] / np.where(g > 0, g, 1.0)
    bad = (g > 0) & (sin > bound)
    assert not bad.any(), f"{bad.sum()} eigenvectors outside 16 eps*max|lambda|/gap"
    cos = np.abs(np.einsum("nik,nik->nk", V, Vr))
    sep = (g > 0) & (g >= SEPARATED * scale[:, None])
    assert (1 - cos[sep] <= ORTH_FACTOR * eps).all(), \
        f"1 - |cos| = {np.max(1 - cos[sep]) / eps:.3g} eps for separated eigenvalues"
    return Ain, w, V


# --------------------------------------------------------------------------- tests
def test_random_symmetric(eig3):
    check(eig3, random_symmetric(np.random.default_rng(1)))


def test_covariances(eig3):
    check(eig3, covariances(np.random.default_rng(2)))


def test_plane_normal(eig3):
    """lambda0 / lambda2 = 1e-6 (nearly flat neighbourhood): v0 is the surface normal."""
    rng = np.random.default_rng(3)
    lam = np.stack([np.full(N, 1e-6), rng.uniform(0.5, 1, N), rng.uniform(0.5, 1, N)], 1)
    Ain, w, V = check(eig3, with_eigenvalues(rng, lam))
    _, Vr = np.linalg.eigh(Ain)
    cos = np.abs(np.einsum("ni,ni->n", V[:, :, 0], Vr[:, :, 0]))
    assert cos.min() >= 1 - 1e-5


@pytest.mark.parametrize("pattern", ["aab", "abb", "aaa"])
def test_repeated_eigenvalues(eig3, pattern):
    """Random rotations of diag(a,a,b), diag(a,b,b), a*I: any basis of the repeated
    eigenspace is right, so check eigenvalues, residuals and the isolated eigenvector."""
    rng = np.random.default_rng(4)
    a, b = rng.uniform(-1, 1, (2, N))
    a[: N // 10] = 0          # rotated lines / planes through the origin
    b[N // 10: N // 5] = 0
    cols = {"a": a, "b": b}
    lam = np.stack([cols[c] for c in pattern], 1)
    check(eig3, with_eigenvalues(rng, lam))


def test_diagonal_exact(eig3):
    """Diagonal and permuted-diagonal matrices (distinct, repeated, zero, negative entries):
    eigenvalues are the sorted diagonal and eigenvectors are +-axis vectors, exactly."""
    diags = [(3.0, 2.0, 1.0), (1.0, 1.0, 2.0), (-1.0, 0.0, 1.0), (0.0, 0.0, 5.0),
             (-2.0, -2.0, 7.0), (1e-3, 1.0, 1e3), (0.0, -1.0, -1.0)]
    perms = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    A = np.array([np.diag(np.array(d)[list(p)]) for d in diags for p in perms])
    Ain, w, V = check(eig3, A)
    assert np.array_equal(w, np.sort(np.diagonal(Ain, axis1=1, axis2=2), 1))
    assert np.array_equal(np.abs(V), np.round(np.abs(V)))      # a signed permutation
    assert np.array_equal(np.einsum("nji,njk->nik", V, V), np.broadcast_to(np.eye(3), V.shape))


def test_axis_planes_exact(eig3):
    """Covariance of an axis-aligned plane: lambda0 = 0 and v0 = the missing axis, exactly."""
    A = np.array([np.diag([1.0, 1.0, 0.0]), np.diag([0.0, 1.0, 1.0]), np.diag([1.0, 0.0, 1.0]),
                  np.diag([2.0, 0.5, 0.0]), np.diag([0.0, 3.0, 1e-4])])
    normals = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0]], float)
    _, w, V = check(eig3, A)
    assert np.array_equal(w[:, 0], np.zeros(len(A)))
    assert np.array_equal(np.abs(V[:, :, 0]), normals)


def test_multiple_of_identity_and_zero(eig3):
    """a*I (a = 0 included): w = (a, a, a) and the documented basis v0, v1, v2 = e_z, e_x, e_y."""
    a = np.array([0.0, 1.0, -2.5, 1e-20, 1e20])
    _, w, V = check(eig3, a[:, None, None] * np.eye(3))
    assert np.array_equal(w, np.repeat(a.astype(eig3.dtype)[:, None], 3, 1).astype(float))
    basis = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float)    # columns e_z, e_x, e_y
    assert np.array_equal(V, np.broadcast_to(basis, V.shape))


def test_rank_deficient(eig3):
    """u u^T (rank 1) and u u^T + s v v^T (rank 2)."""
    rng = np.random.default_rng(5)
    u, v = rng.standard_normal((2, N, 3))
    s = rng.uniform(-2, 2, (N, 1, 1))
    A1 = np.einsum("ni,nj->nij", u, u)
    A2 = A1 + s * np.einsum("ni,nj->nij", v, v)
    _, w1, _ = check(eig3, A1)
    check(eig3, A2)
    scale = np.abs(w1).max(1)
    assert (np.abs(w1[:, :2]).max(1) <= EIG_FACTOR * eig3.eps * scale).all()


@pytest.mark.parametrize("factor", [1e-30, 1e-20, 1e15, 1e20])
def test_tiny_and_huge(eig3, factor):
    """Scaled random and covariance matrices: relative accuracy does not depend on scale."""
    rng = np.random.default_rng(6)
    check(eig3, factor * random_symmetric(rng, 2000))
    check(eig3, factor * covariances(rng, 2000))


def test_power_of_two_scaling_is_exact(eig3):
    """Scaling A by 2^k scales w by 2^k exactly and leaves V bit-identical (k keeps all
    entries normal: +-60 in float, +-600 in double)."""
    rng = np.random.default_rng(7)
    A = np.concatenate([random_symmetric(rng, 1000), covariances(rng, 1000)])
    A = A.astype(eig3.dtype).astype(np.float64)
    _, w, V = eig3(A)
    kmax = 600 if eig3.dtype == np.float64 else 60
    for k in (-kmax, kmax):
        _, wk, Vk = eig3(np.ldexp(A, k))
        assert np.array_equal(wk, np.ldexp(w, k))
        assert np.array_equal(Vk, V)


def test_wide_dynamic_range(eig3):
    """Entries with magnitudes 10^-30 .. 10^30 mixed in one matrix: no NaN/Inf, accurate
    relative to max|lambda| (the solver scales by the largest entry; smaller ones may
    underflow after scaling, which is below the tolerance)."""
    rng = np.random.default_rng(8)
    A = random_symmetric(rng, N) * 10.0 ** rng.uniform(-30, 30, (N, 3, 3))
    check(eig3, (A + A.transpose(0, 2, 1)) / 2)
