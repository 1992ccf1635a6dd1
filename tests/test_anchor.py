"""Anchor normals and the one-walk lambda0 (clcurv/grid/anchor.py, kernels/anchor.cl, pca.h).

* anchor.cl's cell normals against the float64 reference: the same cells have one, and
  they agree up to sign to 1 - |cos| <= 1e-4 where the cell's own covariance separates
  its smallest eigenvalue (l1 - l0 > 1e-2 l2; cells within a factor 2 of the rank
  threshold are left out, float32 may decide them the other way);
* the anchored lambda0 against the second walk it replaces (ANCHOR_SIN2 = 0 forces the
  second walk everywhere): normals and l1, l2 bit for bit (the same sums), lambda0 and the
  surface variation within 1e-4 relative for 99.9% of the points (both are float32
  evaluations of sum w <q - o, v0>^2 / sum w; tests/test_moments.py holds both to the
  float64 reference);
* points without an anchor (cells and rows of fewer than 3 points) take the second walk:
  their lambda0 is that of the forced second walk bit for bit.
"""
import numpy as np
import pyopencl as cl
import pytest

import clcurv
from clcurv.grid.anchor import cell_normals
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import run_kernel
from clcurv.ops.registry import PCA


#: fewest points of a cell whose anchor comes from its own points (kernels/anchor.cl:
#: ANCHOR_MIN_POINTS)
MIN_POINTS = 6
#: the anchor's rank test: l1 > RANK_RATIO l2 (kernels/anchor.cl)
RANK_RATIO = 1e-3


def reference_cell_normals(grid, points):
    """The anchors of :func:`cell_normals`, float64 NumPy, for a :class:`clcurv.grid.binning.Grid`
    of ``points`` (N, 3) (input order): (ncells, 3) unit normals, zero rows where there is
    none, and (ncells, 3) the ascending eigenvalues of the points used (zero for fewer
    than 3), to tell borderline and ill-conditioned cells.
    Same rules as the kernel: the cell's points, or with fewer than MIN_POINTS those of the
    row of three cells along x; at least 3 points and l1 > RANK_RATIO l2."""
    pos = np.asarray(points, np.float64)[grid.order]
    nx, ny, _ = grid.dims
    keys, start = grid.keys, grid.cell_start.astype(np.int64)
    a, b = start[:-1].copy(), start[1:].copy()
    few = b - a < MIN_POINTS
    ix, row = keys % nx, keys - keys % nx
    lo = np.searchsorted(keys, row + np.maximum(ix - 1, 0))
    hi = np.searchsorted(keys, row + np.minimum(ix + 1, nx - 1), side="right")
    a[few], b[few] = start[lo[few]], start[hi[few]]
    out, eig = np.zeros((len(keys), 3)), np.zeros((len(keys), 3))
    for c in range(len(keys)):
        q = pos[a[c]:b[c]]
        if len(q) < 3:
            continue
        eig[c], v = np.linalg.eigh(np.cov(q.T, bias=True))
        if eig[c, 1] > RANK_RATIO * eig[c, 2]:
            out[c] = v[:, 0]
    return out, eig


def _anchors(cloud):
    buf = cell_normals(cloud)
    out = np.empty((cloud.grid.ncells, 3), cloud.dtype)
    cl.enqueue_copy(cloud.device.queue, out, buf)
    return out.astype(np.float64)


def _clouds():
    rng = np.random.default_rng(5)
    sphere = clcurv.shapes.sphere(20000, 1.0, noise=1e-3, seed=4)["points"]
    blob = rng.normal(size=(3000, 3))                          # sparse: many small cells
    return {"sphere": (sphere, 0.05), "blob": (blob, 0.3)}


@pytest.mark.parametrize("name", ["sphere", "blob"])
def test_cell_normals_match_reference(device, name):
    pts, r = _clouds()[name]
    cloud = DeviceCloud(pts, r, device=device)
    got = _anchors(cloud)
    want, eig = reference_cell_normals(cloud.grid, pts)
    ratio = eig[:, 1] / np.maximum(eig[:, 2], 1e-300)
    clear = (ratio > 2 * RANK_RATIO) | (ratio < 0.5 * RANK_RATIO)
    has_got = np.any(got != 0, axis=1)
    has_want = np.any(want != 0, axis=1)
    np.testing.assert_array_equal(has_got[clear], has_want[clear])
    both = has_got & has_want & clear
    assert both.sum() > 0.5 * cloud.grid.ncells if name == "sphere" else both.sum() > 10
    np.testing.assert_allclose(np.linalg.norm(got[both], axis=1), 1, atol=1e-5)
    # well-separated smallest eigenvalue: the direction is well-conditioned
    sep = both & (eig[:, 1] - eig[:, 0] > 1e-2 * eig[:, 2])
    assert sep.sum() > 0.5 * both.sum()
    cos = np.abs(np.einsum("ij,ij->i", got[sep], want[sep]))
    assert (1 - cos).max() <= 1e-4


def _pair(device, pts, r):
    cloud = DeviceCloud(pts, r, device=device)
    anchored = run_kernel(PCA, cloud, r)
    second = run_kernel(PCA, cloud, r, defines={"ANCHOR_SIN2": 0})
    return cloud, anchored, second


@pytest.mark.parametrize("shape", ["sphere", "torus", "noisy"])
def test_anchored_l0_matches_second_walk(device, shape):
    if shape == "torus":
        pts, r = clcurv.shapes.torus(30000, 1.0, 0.3, seed=3)["points"], 0.05
    else:
        pts = clcurv.shapes.sphere(30000, 1.0, noise=1e-3 if shape == "noisy" else 0.0,
                                   seed=2)["points"]
        r = 0.04
    _, a, b = _pair(device, pts, r)
    np.testing.assert_array_equal(a["status"], b["status"])
    ok = a["status"] == 0
    assert ok.mean() > 0.99
    np.testing.assert_array_equal(a["normals"], b["normals"])
    np.testing.assert_array_equal(a["eigenvalues"][:, 1:], b["eigenvalues"][:, 1:])
    for got, want in ((a["eigenvalues"][ok, 0], b["eigenvalues"][ok, 0]),
                      (a["variation"][ok], b["variation"][ok])):
        rel = np.abs(got - want) / want
        assert np.quantile(rel, 0.999) <= 1e-4, np.quantile(rel, [0.5, 0.999, 1])


def test_points_without_anchor_take_the_second_walk(device):
    # a sparse blob: most cells and rows hold fewer than 3 points (no anchor)
    pts, r = _clouds()["blob"]
    cloud, a, b = _pair(device, pts, r)
    none = ~np.any(_anchors(cloud) != 0, axis=1)
    sorted_none = none[cloud.grid.cell_of & ((1 << 30) - 1)]
    at = np.zeros(len(pts), bool)
    at[cloud.grid.order] = sorted_none                           # input order
    at &= a["status"] == 0
    assert at.sum() > 50
    np.testing.assert_array_equal(a["eigenvalues"][at], b["eigenvalues"][at])
    np.testing.assert_array_equal(a["variation"][at], b["variation"][at])
