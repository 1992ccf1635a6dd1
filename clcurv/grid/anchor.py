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
