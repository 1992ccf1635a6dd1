"""Tiles of one COPC input, each read by region through the octree (:mod:`clcurv.io.copc`).

A tiled run (:mod:`clcurv.tiles.engine`) of a single ``.copc.laz`` file, without a scale
space, without MST orientation and without normals read from the file, skips passes (1)
and (1b): no bucket, no split file, and the client decodes no point. It reads the COPC
hierarchy (checked whole: :func:`clcurv.io.copc.open_index`), and

* the frame is that of the header's min/max (:meth:`Frame.covering`, as the in-memory run
  makes it from the points' exact min/max);
* the tile size comes from the budget and a density of the nodes' counts, each node's
  count spread over its x-y square (:func:`occupancy`; for sizing only);
* each tile's task reads its own region, its cells and halo (all z) widened by one cell,
  from the file: the nodes that meet it are decoded by the worker (:func:`read_tile`), and
  its points are those whose cells are in its reach, its own those whose cells are in its
  block, by the same half-open rule on the global grid as the bucket path, in global-id
  (file) order.

What is trusted is checked. Every node decoded is checked to hold its points within its
(widened) bounds and the header's min/max (:class:`clcurv.io.copc.UntrustedBounds`
otherwise), so a node a region skips holds none of its points; after the tiles,
:func:`check` asks that the owned counts sum to the header's count (every point owned once:
the tiles' blocks are disjoint and each reads a node once) and that the union of the owned
points' min/max is the header's min/max exactly (the frame is the in-memory run's). On any
of these the engine starts again through the buckets (which read the file as a plain LAZ)
and says why; a hierarchy that fails its own checks is a CorruptFileError.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clcurv.grid.binning import ExtentError, Frame
from clcurv.io import copc, stream
from clcurv.tiles.planning import (OCCUPANCY_BLOCKS, Occupancy, Tiling, plan_tiles,
                                   within)

#: most tiles a region run plans (the tiles of the frame: one COPC cube bounds the points)
MAX_TILES = 1 << 20


def applies(source, params):
    """Does a tiled run of ``params`` read ``source`` by region: one COPC file, no scale
    space, no file normals read, no MST orientation?"""
    if not isinstance(source, stream.LasSource) or params.scale_space:
        return False
    if source.has_normals and not params.ignore_normals:
        return False
    if not copc.is_copc(source.path):
        return False
    how = params.orientation(source, False)
    return not (isinstance(how, str) and how == "mst")


@dataclass
class Plan:
    """The checked index of the file, the tiling and the tiles to compute."""
    index: copc.CopcIndex
    tiling: Tiling
    tiles: list

    def key(self):
        """What a resumed run must find the same (the input's content is in the run's)."""
        f = self.tiling.frame
        return {"size": self.tiling.size, "halo": self.tiling.halo,
                "origin": list(map(float, f.origin)), "cell": f.cell, "tiles": len(self.tiles)}

    def region(self, t):
        """The :class:`clcurv.io.copc.Region` of tile t: its reach widened by one cell."""
        (x0, y0), (x1, y1) = self.tiling.box(t)
        c = self.tiling.frame.cell
        return self.index.region(((x0 - c, y0 - c), (x1 + c, y1 + c)))


def plan(source, params, budget, tile, halo):
    """The :class:`Plan` of a region run of ``source`` (:func:`applies`); UntrustedBounds
    when the header's bounds cannot make the frame (then the buckets' path says why)."""
    index = copc.open_index(source.path)
    lo, hi = index.mins, index.maxs
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all()):
        raise copc.UntrustedBounds(f"{source.path}: the header's bounds {lo.tolist()} - "
                                   f"{hi.tolist()} are not a box")
    try:
        frame = Frame.covering(lo, hi, params.radius)
    except ExtentError as exc:
        raise copc.UntrustedBounds(f"{source.path}: {exc}") from None
    occ = occupancy(index, frame)
    tiling = plan_tiles(None, params.radius, halo, budget, tile, frame=frame,
                        bytes_per_point=params.bytes_per_point(), density=occ)
    if tiling.count > MAX_TILES:
        raise copc.UntrustedBounds(f"{source.path}: {tiling.count} tiles in the header's "
                                   "box")
    return Plan(index, tiling, occupied(index, tiling))


def _squares(index, frame):
    """(a, e, count): each non-empty (level, x, y) column of nodes as its x-y square in
    cells of ``frame`` (floats, clipped to the frame) and its points."""
    nodes = index.nodes
    col = np.stack([nodes["level"].astype(np.int64), nodes["x"], nodes["y"]], axis=1)
    u, inv = np.unique(col, axis=0, return_inverse=True)
    count = np.bincount(inv.ravel(), weights=nodes["count"]).astype(np.float64)
    side = 2.0 * index.halfsize / np.exp2(u[:, 0].astype(np.float64))
    root = index.center[:2] - index.halfsize
    lo = root + u[:, 1:] * side[:, None]
    o, c = np.asarray(frame.origin[:2]), frame.cell
    dims = np.asarray(frame.dims[:2], np.float64)
    a = np.clip((lo - o) / c, 0, dims)
    e = np.clip((lo + side[:, None] - o) / c, 0, dims)
    return a, e, count


def occupancy(index, frame, limit=OCCUPANCY_BLOCKS):
    """An :class:`clcurv.tiles.planning.Occupancy` of ``frame`` from the nodes' counts,
    each spread uniformly over its x-y square (a square outside the frame counted in its
    nearest block): for sizing tiles only. Blocks of g x g cells, g the smallest power of
    two that keeps at most ``limit`` blocks."""
    nx, ny, _ = frame.dims
    g = 1
    while -(-nx // g) * -(-ny // g) > limit:
        g *= 2
    nby = -(-ny // g)
    a, e, count = _squares(index, frame)
    b0 = np.minimum(np.floor(a / g), [-(-nx // g) - 1, nby - 1]).astype(np.int64)
    b1 = np.maximum(np.ceil(e / g).astype(np.int64) - 1, b0)
    span = b1 - b0 + 1
    per = span[:, 0] * span[:, 1]
    k = np.repeat(np.arange(len(per)), per)
    off = np.arange(len(k)) - np.repeat(np.cumsum(per) - per, per)
    bx, by = b0[k, 0] + off // span[k, 1], b0[k, 1] + off % span[k, 1]
    ox = np.maximum(0.0, np.minimum(e[k, 0], (bx + 1) * g) - np.maximum(a[k, 0], bx * g))
    oy = np.maximum(0.0, np.minimum(e[k, 1], (by + 1) * g) - np.maximum(a[k, 1], by * g))
    area = (e - a).prod(axis=1)[k]
    share = np.where(area > 0, ox * oy / np.where(area > 0, area, 1.0), 1.0 / per[k])
    keys, inv = np.unique(bx * nby + by, return_inverse=True)
    n = np.bincount(inv.ravel(), weights=count[k] * share)
    ubx, uby = np.divmod(keys, nby)
    return Occupancy(frame, g, ubx, uby, n)


def occupied(index, tiling):
    """The sorted ids of the tiles whose blocks meet a non-empty node's widened square (a
    tile that may own points; :func:`check` makes sure none was left out)."""
    ntx, nty = tiling.shape
    f = tiling.frame
    lo, hi = index.bounds()
    pad = index.pad + f.cell
    o = np.asarray(f.origin[:2])
    c0 = np.floor((lo[:, :2] - pad - o) / f.cell) // tiling.size
    c1 = np.floor((hi[:, :2] + pad - o) / f.cell) // tiling.size
    c0 = np.clip(c0, 0, [ntx - 1, nty - 1]).astype(np.int64)
    c1 = np.clip(c1, 0, [ntx - 1, nty - 1]).astype(np.int64)
    mask = np.zeros((ntx, nty), bool)
    for (x0, y0), (x1, y1) in zip(c0.tolist(), c1.tolist()):
        mask[x0:x1 + 1, y0:y1 + 1] = True
    tx, ty = np.nonzero(mask)
    return sorted((tx + ntx * ty).tolist())


def read_tile(region, tiling, t):
    """(global ids, xyz float64, owned mask) of tile t's points with its halo, in global-id
    order, read from ``region`` (:meth:`Plan.region`) by the worker."""
    reach = tiling.cells(t)
    ids, xyz = region.read(lambda p: within(tiling.frame.cells_xy(p), reach))
    return ids, xyz, within(tiling.frame.cells_xy(xyz), tiling.cells(t, halo=False))


def owned_box(pos, own):
    """(2, 3) float64: the min and max of the owned points (NaN without any)."""
    if not own.any():
        return np.full((2, 3), np.nan)
    p = pos[own]
    return np.stack([p.min(axis=0), p.max(axis=0)])


def box_file(tile_file):
    """Where a tile read by region keeps its :func:`owned_box` (for a resumed run)."""
    return tile_file.with_suffix(".box.npy")


def check(index, boxes, owned):
    """UntrustedBounds unless the tiles owned the header's count of points, together,
    and the union of their owned points' min/max (``boxes``, from :func:`owned_box`) is
    the header's min/max exactly: what the run trusted (the frame, the nodes' bounds)
    held (``boxes``: a (2, 3) box per tile, NaN for one that owns none)."""
    if owned != index.n:
        raise copc.UntrustedBounds(
            f"{index.path}: the tiles read by region own {owned} points and the file holds "
            f"{index.n} (the hierarchy's node bounds do not hold every point)")
    boxes = np.asarray(boxes, np.float64).reshape(-1, 2, 3)
    boxes = boxes[~np.isnan(boxes).any(axis=(1, 2))]
    lo = boxes[:, 0].min(axis=0) if len(boxes) else np.full(3, math.nan)
    hi = boxes[:, 1].max(axis=0) if len(boxes) else np.full(3, math.nan)
    if not (np.array_equal(lo, index.mins) and np.array_equal(hi, index.maxs)):
        raise copc.UntrustedBounds(
            f"{index.path}: the header's bounds {index.mins.tolist()} - "
            f"{index.maxs.tolist()} are not the points' {lo.tolist()} - {hi.tolist()}")
