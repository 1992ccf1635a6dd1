"""Anchor normals: one reference normal per occupied cell of a :class:`DeviceCloud`.

The kernels that need an accurate smallest eigenvalue lambda0 (surface variation, the
covariance features) used to walk every ball twice, because float32 one-pass moments lose
about two digits of lambda0 on smooth surfaces. With an anchor normal ``a`` near the ball's
own normal, one walk suffices: it sums the offsets sheared along ``a``'s dominant axis, so
that the heights above the anchor plane (over that component of ``a``) are a coordinate of
their own, small numbers that keep their digits, and lambda0 = <v0, C v0> is evaluated
from those sums (kernels/pca.h, PCA_ANCHOR). The anchor of a cell is the PCA normal of the cell's own points
(kernels/anchor.cl); a cell with fewer than 3 points or collinear points has none (the zero
vector), and its points, like those whose anchor is too far from their normal, take the
second walk as before.

The anchors depend on the cell's points only, so a tile binned in the whole cloud's frame
(clcurv.tiles.engine) gets the same anchors, and the same results, as the whole cloud.
"""
from __future__ import annotations

import numpy as np

from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import build, launch


def cell_normals(cloud):
    """The anchor normals of ``cloud``'s occupied cells: a device buffer of 3 REALs per cell
    (unit, sign arbitrary; zero for a cell without one). Computed once per cloud."""
    buf = getattr(cloud, "_anchors", None)
    if buf is not None:
        return buf
    g, dev = cloud.grid, cloud.device
    ncells = max(g.ncells, 1)
    item = np.dtype(cloud.dtype).itemsize
    buf = device_buffer(dev, 3 * ncells * item)
    prg = build(dev, "anchor.cl", cloud.defines)
    vw = int(cloud.defines["VW"])
    launch(dev, prg.cell_normals, -(-g.ncells // vw), cloud.x, cloud.y, cloud.z,
           cloud.cell_start, cloud.cell_of, cloud.ranges, np.uint32(cloud.n), np.uint32(g.ncells), buf)
    cloud._anchors = buf
    return buf


#: fewest points of a cell whose anchor comes from its own points (kernels/anchor.cl)
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
