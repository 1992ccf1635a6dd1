"""eig3_sym_v (VW matrices per call, one per vector lane) against numpy.linalg.eigh, with the
tolerances of test_eig3.py, for several vector widths; and its agreement with eig3_sym."""
import numpy as np
import pyopencl as cl
import pytest

from test_eig3 import (Eig3, check, cl_env, covariances, random_symmetric,  # noqa: F401
                       with_eigenvalues, N, UPPER)

SOURCE_V = r"""
#include "eig3.h"
/* a: 6 entries per matrix; each work-item decomposes VW consecutive matrices at once */
__kernel void eig3_test(__global const REAL *a, __global REAL *out, const int n)
{
    const int i0 = get_global_id(0) * VW;
    if (i0 >= n)
        return;
    REAL m[6][VW];
    for (int k = 0; k < VW; ++k)
        for (int e = 0; e < 6; ++e)
            m[e][k] = i0 + k < n ? a[6 * (i0 + k) + e] : (REAL)(e == 0);
    REALV w0, w1, w2;
    eig3_v3_v v0, v1, v2;
    eig3_sym_v(VLOADV(0, m[0]), VLOADV(0, m[1]), VLOADV(0, m[2]), VLOADV(0, m[3]),
               VLOADV(0, m[4]), VLOADV(0, m[5]), &w0, &w1, &w2, &v0, &v1, &v2);
    REAL o[12][VW];
    CAT(vstore, VW)(w0, 0, o[0]); CAT(vstore, VW)(w1, 0, o[1]); CAT(vstore, VW)(w2, 0, o[2]);
    CAT(vstore, VW)(v0.x, 0, o[3]); CAT(vstore, VW)(v0.y, 0, o[4]); CAT(vstore, VW)(v0.z, 0, o[5]);
    CAT(vstore, VW)(v1.x, 0, o[6]); CAT(vstore, VW)(v1.y, 0, o[7]); CAT(vstore, VW)(v1.z, 0, o[8]);
    CAT(vstore, VW)(v2.x, 0, o[9]); CAT(vstore, VW)(v2.y, 0, o[10]); CAT(vstore, VW)(v2.z, 0, o[11]);
    for (int k = 0; k < VW && i0 + k < n; ++k)
        for (int e = 0; e < 12; ++e)
            out[12 * (i0 + k) + e] = o[e][k];
}
"""


@pytest.fixture(scope="module", params=[("float", 8), ("float", 4), ("float", 16), ("double", 8)],
                ids=lambda p: f"{p[0]}-vw{p[1]}")
def eig3v(request, cl_env):  # noqa: F811
    device, ctx, queue = cl_env
    precision, vw = request.param
    if precision == "double" and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64")
    return Eig3(ctx, queue, precision, SOURCE_V, vw)


def special_matrices(rng):
    """Zero, multiples of the identity, diagonal, axis-aligned planes, denormal-scaled,
    repeated eigenvalues, mixed with random ones so that every lane position sees them."""
    mats = [np.zeros((3, 3)), 2.5 * np.eye(3), -np.eye(3), np.diag([3.0, 1.0, 2.0]),
            np.diag([1.0, 1.0, 0.0]), np.diag([0.0, 2.0, 2.0]), np.diag([1e-30, 1.0, 1.0]),
            np.eye(3) + 1e-40 * (np.ones((3, 3)) - np.eye(3)),
            with_eigenvalues(rng, np.array([[1.0, 1.0, 2.0]]))[0],
            with_eigenvalues(rng, np.array([[-1.0, 2.0, 2.0]]))[0]]
    mats = np.array(mats)
    out = np.concatenate([mats, random_symmetric(rng, 3 * len(mats))])
    return out[rng.permutation(len(out))]


def test_vector_random_symmetric(eig3v):
    check(eig3v, random_symmetric(np.random.default_rng(1), N + 3))


def test_vector_covariances(eig3v):
    check(eig3v, covariances(np.random.default_rng(2), N + 5))


def test_vector_special(eig3v):
    A = special_matrices(np.random.default_rng(4))
    Ain, w, V = eig3v(A)
    assert np.isfinite(w).all() and np.isfinite(V).all()
    zero = np.abs(Ain).max((1, 2)) == 0
    assert (w[zero] == 0).all()
    ident = np.array([np.all(a == a[0, 0] * np.eye(3)) for a in Ain])
    assert np.array_equal(V[ident], np.repeat([[[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]], ident.sum(), 0))
    diag = np.array([np.all(a == np.diag(np.diag(a))) for a in Ain])
    assert np.array_equal(np.sort(np.diagonal(Ain[diag], axis1=1, axis2=2), 1), w[diag])


def test_vector_matches_scalar(eig3v, cl_env):  # noqa: F811
    """Lanes agree with eig3_sym to a few eps (the same operations; only the compiler's
    contraction and the math library's vector variants may differ)."""
    _, ctx, queue = cl_env
    scalar = Eig3(ctx, queue, eig3v.precision)
    A = covariances(np.random.default_rng(5), 2000)
    _, w, V = eig3v(A)
    _, ws, Vs = scalar(A)
    eps = eig3v.eps
    assert np.abs(w - ws).max() <= 8 * eps * np.abs(ws).max()
    assert (1 - np.abs(np.einsum("ni,ni->n", V[:, :, 0], Vs[:, :, 0]))).max() <= 64 * eps


@pytest.mark.parametrize("precision", ["float", "double"])
def test_widths_bit_identical(precision, cl_env):  # noqa: F811
    """The same matrices give the same bits at every vector width: features.cl decomposes
    two balls at once in twice the lanes (pca.h: pca_decompose_pair) and promises results
    bit-identical to a single-radius call, which decomposes VW at a time."""
    device, ctx, queue = cl_env
    if precision == "double" and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64")
    rng = np.random.default_rng(6)
    A = np.concatenate([covariances(rng, 1000), special_matrices(rng), random_symmetric(rng, 300)])
    out = {vw: Eig3(ctx, queue, precision, SOURCE_V, vw)(A) for vw in (4, 8, 16)}
    for vw in (4, 16):
        for a, b in zip(out[vw][1:], out[8][1:]):
            assert np.array_equal(a, b), f"vw={vw} differs from vw=8"
