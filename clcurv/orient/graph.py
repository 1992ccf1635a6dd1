"""The orientation graph of a cloud, on its device (issue 11): for every point with a valid
normal, its ``k`` nearest other points with valid normals strictly within the radius,
ordered by (squared distance, input index), and the symmetric edge weight

    w = 1 - |n_i . n_j| + |e . n_i| |e . n_j|,   e the unit vector from p_i to p_j

(the second term is 0 for coincident points): Hoppe's weight plus a penalty for edges that
cross a thin sheet (e along both normals) rather than run along the surface (e tangent).
:func:`clcurv.orient.orientation.edge_weights` is the same formula in float64 for the host reference.
kernels/knn.cl computes it; :mod:`clcurv.orient.forest` takes its minimum spanning forest.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl

from clcurv.grid.cloud import DeviceMemoryError, upload_sorted
from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import build, launch

#: Longest neighbour list (``KMAX`` in kernels/orient.h).
KMAX = 32
#: Marks "no neighbour", "no edge", "invalid normal" in the device's uint arrays.
NONE = np.uint32(0xFFFFFFFF)
#: Largest work-group of knn_graph on a CPU device. A work-item walks its own candidates in
#: data-dependent loops over explicit vectors, so a larger group only wraps a work-item loop
#: around that (PoCL 3.1, 1M sphere, ~30 neighbours: kernel CPU time about 5% lower at 1 than
#: at 128). Other devices keep program.launch's default (a work-group size that fills them).
CPU_GROUP = 1


def knn_defines(cloud):
    """Build options of the k-NN kernels (knn.cl here, knn_radius.cl for the k-NN radius) on
    ``cloud``'s device: the cloud's, with ``VW`` (candidates per vector) raised on a CPU
    device to its native vector width for the precision when that is 8 or 16 (queried: 16
    floats with AVX-512, where knn.cl's CPU time is ~5% lower than at 8 on PoCL 3.1 and
    knn_radius.cl's ~25% lower, with the levels of clcurv.ops.knn_radius.knn_levels; outputs
    identical)."""
    dev = cloud.device.cl_device
    native = (dev.native_vector_width_double if cloud.precision == "double"
              else dev.native_vector_width_float)
    vw = int(cloud.defines["VW"])
    if cloud.device.info.kind == "cpu" and native in (8, 16) and native > vw:
        vw = native
    return dict(cloud.defines, VW=vw)


def _row_norms2(a, block=32768):
    """|row|^2 of a float64 (N, 3) array by blocks that stay in cache (about 3x faster than
    einsum's 3-wide rows at 1M; no BLAS call, whose spinning threads would compete with the
    device's for the cores)."""
    out = np.empty(len(a))
    buf = np.empty((min(block, len(a)), 3))
    with np.errstate(over="ignore", invalid="ignore"):    # inf and NaN rows: invalid
        for s in range(0, len(a), block):
            b = buf[:min(block, len(a) - s)]
            o = out[s:s + len(b)]
            np.multiply(a[s:s + len(b)], a[s:s + len(b)], out=b)
            np.add(b[:, 0], b[:, 1], out=o)
            np.add(o, b[:, 2], out=o)
    return out


def _valid_normals(normals, n):
    """(normals as float64 (N, 3) with NaN rows where invalid, count of valid rows)."""
    a = np.asarray(normals, dtype=np.float64)
    if a.shape != (n, 3):
        raise ValueError(f"normals must have shape ({n}, 3), got {a.shape}")
    # one pass: |n|^2 is finite and > 0 exactly for the finite nonzero rows (but for
    # overflow of huge components, which the full test below then settles)
    sq = _row_norms2(a)
    ok = np.isfinite(sq) & (sq > 0)
    nvalid = int(np.count_nonzero(ok))
    if nvalid < n:
        ok = np.isfinite(a).all(axis=1) & (a != 0).any(axis=1)
        nvalid = int(np.count_nonzero(ok))
    if nvalid < n:
        a = a.copy()
        a[~ok] = np.nan
    return a, nvalid


@dataclass
class Graph:
    """The k-NN orientation graph of a cloud, kept on its device (:func:`knn_graph`).

    ``nbr`` and ``wgt`` are device buffers of ``n * k`` uint32 / float32 in the cloud's
    sorted order (row g: sorted point g; entries are sorted indices, 0xFFFFFFFF past the
    list's end); ``normals`` the three sorted normal columns (NaN rows invalid).
    :meth:`neighbors` and :meth:`weights` bring them to the host in input order.
    """
    cloud: object
    radius: float
    k: int
    nbr: object
    wgt: object
    normals: tuple
    nvalid: int
    timings: dict = field(default_factory=dict)

    def _sorted(self, buf, dtype):
        out = np.empty((self.cloud.n, self.k), dtype)
        cl.enqueue_copy(self.cloud.device.queue, out, buf)
        return out

    def neighbors(self):
        """(N, k) int64: row i lists the input indices of point i's neighbours, nearest
        first (ties: smaller input index first), -1 past the end of the list."""
        order = self.cloud.grid.order
        s = self._sorted(self.nbr, np.uint32)
        out = np.full((self.cloud.n, self.k), -1, np.int64)
        have = s != NONE
        rows = np.where(have, order[np.where(have, s, 0)], -1)
        out[order] = rows
        return out

    def weights(self):
        """(N, k) float32: the weight of each entry of :meth:`neighbors` as computed in that
        point's list (NaN past the end). An edge held by both lists uses the weight of the
        list of its endpoint with the smaller input index (:meth:`edges`)."""
        out = np.empty((self.cloud.n, self.k), np.float32)
        out[self.cloud.grid.order] = self._sorted(self.wgt, np.float32)
        return out

    def edges(self):
        """The undirected edges the forest uses, each once: ``(lo, hi, w)`` with lo < hi
        (int64 input indices) and w (float32) the weight of the kept slot."""
        nb, w = self.neighbors(), self.weights()
        i = np.repeat(np.arange(self.cloud.n), self.k)
        j, w = nb.ravel(), w.ravel()
        have = j >= 0
        i, j, w = i[have], j[have], w[have]
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        # the slot of the smaller endpoint wins; a one-sided edge keeps its only slot
        pri = (i != lo).astype(np.int64)
        o = np.lexsort((pri, hi, lo))
        lo, hi, w = lo[o], hi[o], w[o]
        first = np.ones(len(lo), bool)
        first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
        return lo[first], hi[first], w[first]


def _check_graph_memory(cloud, k):
    """DeviceMemoryError unless the graph and the forest's buffers fit beside the cloud."""
    item = np.dtype(cloud.dtype).itemsize
    # graph (nbr, wgt), two edge lists of up to k edges per point (3 uints each), the
    # per-point forest arrays (comp, rank, bw, blo, bhi, 2 links, flo, fhi, par) and the
    # outputs (label, parity, elo, ehi)
    per_point = 8 * k + 24 * k + 9 * 4 + 1 + 13
    plan = cloud.plan("forest", per_point, reserve=3 * item, widest=12 * k,
                      label="the coordinates, the grid, the normals and the orientation graph")
    if plan.count > 1:
        raise DeviceMemoryError(
            f"{cloud.n} points do not fit the device for the orientation graph with k = {k}: "
            f"about {per_point} bytes per point besides the cloud and the normals; about "
            f"{plan.chunk} points of this cloud fit. Use a smaller k, split the cloud into "
            "tiles, or use a device with more memory")


def knn_graph(cloud, radius, normals, k=10, point_r2=None):
    """The k-nearest-neighbour orientation graph of ``cloud`` on its device.

    Parameters
    ----------
    cloud : clcurv.grid.cloud.DeviceCloud
    radius : float, same length unit as the points
        Neighbours lie strictly within it (|q - p| < radius); at most ``cloud.cell``.
    normals : (N, 3) array_like, input order
        Unit normals (any sign). Rows with a non-finite component, or all zero, are invalid:
        such points have no neighbours and are nobody's neighbour.
    k : int, 1 <= k <= KMAX
        Longest neighbour list; a list is shorter when the ball holds fewer valid points.
    point_r2 : device buffer, optional
        Each point's own squared radius (sorted order, padded: clcurv.ops.knn_radius), at most
        ``radius``: neighbours lie within the point's own ball, whose rows beyond it the
        walk skips (ROW_PRUNE). With a k-NN radius of K > k points the k nearest lie within
        it, so the graph is that of the largest radius but for invalid normals.

    Squared distances are those of the device precision, compared as float32 (with
    ``precision='double'`` rounded to float32 first, so near ties go to the smaller input
    index). Weights are float32 and equal to the bit in both lists that hold an edge.

    Returns
    -------
    Graph
        Device buffers and host accessors (:meth:`Graph.neighbors`, :meth:`Graph.weights`,
        :meth:`Graph.edges`); ``timings`` holds ``upload_normals`` and ``knn`` (seconds).
    """
    r = cloud.check_radius(radius)
    k = int(k)
    if not 1 <= k <= KMAX:
        raise ValueError(f"k must be in [1, {KMAX}], got {k}")
    if cloud.n >= 2 ** 31:
        raise ValueError(f"at most 2^31 - 1 points, got {cloud.n}")
    _check_graph_memory(cloud, k)
    t0 = time.perf_counter()
    nrm, nvalid = _valid_normals(normals, cloud.n)
    cols = upload_sorted(cloud, nrm)
    per_point = point_r2 is not None
    prg = build(cloud.device, "knn.cl", dict(knn_defines(cloud), POINT_RADIUS=int(per_point),
                                             ROW_PRUNE=int(per_point)))
    q = cloud.device.queue
    ranges = cloud.with_middles() if per_point else cloud.ranges
    nbr = device_buffer(cloud.device, 4 * cloud.n * k)
    wgt = device_buffer(cloud.device, 4 * cloud.n * k)
    q.finish()
    t1 = time.perf_counter()
    launch(cloud.device, prg.knn_graph, cloud.n, cloud.x, cloud.y, cloud.z, *cols,
           cloud.cell_of, ranges, cloud.order, np.uint32(cloud.n), cloud.ball(r),
           np.uint32(k), nbr, wgt, point_r2 if per_point else cloud.x,
           **({"limit": CPU_GROUP} if cloud.device.info.kind == "cpu"
                                       else {}))
    q.finish()
    t2 = time.perf_counter()
    return Graph(cloud, r, k, nbr, wgt, tuple(cols), nvalid,
                 {"upload_normals": t1 - t0, "knn": t2 - t1})
