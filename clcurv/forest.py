"""The orientation graph and its minimum spanning forest, on the device (issue 11).

Hoppe et al. (1992) orient normals by propagating a sign along a minimum spanning tree of a
k-nearest-neighbour graph. This module builds that graph and its forest on the OpenCL device
of a :class:`~clcurv.cloud.DeviceCloud` and returns, for every point, its component and its
sign *parity* relative to the component's root; choosing each component's global sign is
left to the caller (:mod:`clcurv.orient`).

- :func:`knn_graph`: for every point with a valid normal, the ``k`` nearest other points
  with valid normals strictly within ``radius``, ordered by (squared distance, input
  index), and the symmetric edge weight
  ``w = 1 - |n_i . n_j| + |e . n_i| |e . n_j|`` with ``e`` the unit vector from p_i to p_j
  (the second term is 0 for coincident points). The second term penalises edges that cross
  a thin sheet (e along both normals) rather than run along the surface (e tangent).
- :func:`spanning_forest`: Boruvka's minimum spanning forest of the undirected graph (an
  edge {i, j} when j is in i's list or i in j's) under the strict order (weight, smaller
  input index, larger input index), hence unique, with 32-bit ``atomic_min`` only (three
  passes per round), so the result is bit-identical across runs, work-group sizes and
  devices computing the same float weights. See kernels/forest.cl.

Both run in the cloud's precision; weights are float32 either way, and the edge parity
``n_u . n_v < 0`` is evaluated at the device precision (``float``: the normals rounded to
float32, ``fma(z, z', fma(y, y', x x'))``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .cloud import DeviceMemoryError, upload_sorted
from .constants import PAD
from .program import build, launch

#: Longest neighbour list (``KMAX`` in kernels/forest.cl).
KMAX = 32
#: Edges (graph_*: points) per work-item of the edge kernels: a block's kept edges are
#: written in order from its offset (a prefix sum over the blocks).
BLOCK = 256
#: Longest hook chain followed link by link in a round; longer ones are finished by pointer
#: jumping (a launch and a read-back per halving).
CHASE = 64
#: Marks "no neighbour", "no edge", "invalid normal" in the device's uint arrays.
NONE = np.uint32(0xFFFFFFFF)


def _valid_normals(normals, n):
    """(normals as float64 (N, 3) with NaN rows where invalid, count of valid rows)."""
    a = np.asarray(normals, dtype=np.float64)
    if a.shape != (n, 3):
        raise ValueError(f"normals must have shape ({n}, 3), got {a.shape}")
    ok = np.isfinite(a).all(axis=1)
    ok &= (a != 0).any(axis=1)
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
        import pyopencl as cl
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


def knn_graph(cloud, radius, normals, k=10):
    """The k-nearest-neighbour orientation graph of ``cloud`` on its device.

    Parameters
    ----------
    cloud : clcurv.cloud.DeviceCloud
    radius : float, same length unit as the points
        Neighbours lie strictly within it (|q - p| < radius); at most ``cloud.cell``.
    normals : (N, 3) array_like, input order
        Unit normals (any sign). Rows with a non-finite component, or all zero, are invalid:
        such points have no neighbours and are nobody's neighbour.
    k : int, 1 <= k <= KMAX
        Longest neighbour list; a list is shorter when the ball holds fewer valid points.

    Squared distances are those of the device precision, compared as float32 (with
    ``precision='double'`` rounded to float32 first, so near ties go to the smaller input
    index). Weights are float32 and equal to the bit in both lists that hold an edge.

    Returns
    -------
    Graph
        Device buffers and host accessors (:meth:`Graph.neighbors`, :meth:`Graph.weights`,
        :meth:`Graph.edges`); ``timings`` holds ``upload_normals`` and ``knn`` (seconds).
    """
    import pyopencl as cl
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
    prg = build(cloud.device, "forest.cl", cloud.defines)
    ctx, mf, q = cloud.device.context, cl.mem_flags, cloud.device.queue
    nbr = cl.Buffer(ctx, mf.READ_WRITE, size=4 * cloud.n * k)
    wgt = cl.Buffer(ctx, mf.READ_WRITE, size=4 * cloud.n * k)
    q.finish()
    t1 = time.perf_counter()
    launch(cloud.device, prg.knn_graph, cloud.n, cloud.x, cloud.y, cloud.z, *cols,
           cloud.cell_of, cloud.ranges, cloud.order, np.uint32(cloud.n), cloud.ball(r),
           np.uint32(k), nbr, wgt)
    q.finish()
    t2 = time.perf_counter()
    return Graph(cloud, r, k, nbr, wgt, tuple(cols), nvalid,
                 {"upload_normals": t1 - t0, "knn": t2 - t1})


@dataclass
class Forest:
    """A minimum spanning forest (:func:`spanning_forest`), host arrays in input order.

    label : (N,) int64
        The input index of the point's component root; -1 for an invalid normal. An
        isolated point is its own root.
    parity : (N,) bool
        True where the point's normal must be negated to agree with its root's normal
        along the tree (XOR of ``n_u . n_v < 0`` over the tree path to the root).
    edges : (M, 2) int64
        The forest's edges (input indices, lo < hi), M = valid points - components; row
        order: by the input index of the component root that hooked through the edge.
    rounds : int
        Boruvka rounds that hooked components.
    timings : dict
        Seconds: ``init`` (edge list), ``rounds`` (a list, one per round), ``output``.
    edge_counts : list of int
        Edges joining two components at the start of every round.
    """
    label: np.ndarray
    parity: np.ndarray
    edges: np.ndarray
    rounds: int
    timings: dict
    edge_counts: list


#: When a dict, every kernel launch of spanning_forest waits for its end and adds its time
#: (seconds) under the kernel's name: a profile, for benchmarks only.
PROFILE = None


def _launch(dev, kernel, n, *args):
    if PROFILE is None:
        return launch(dev, kernel, n, *args)
    t = time.perf_counter()
    launch(dev, kernel, n, *args)
    dev.queue.finish()
    PROFILE[kernel.function_name] = PROFILE.get(kernel.function_name, 0.0) + \
        time.perf_counter() - t


def _blocks(m):
    return -(-m // BLOCK)


def spanning_forest(cloud, graph):
    """Boruvka's minimum spanning forest of ``graph`` (:func:`knn_graph`) on its device.

    Edges are ordered strictly by (float32 weight, smaller input index, larger input
    index), so the forest is unique. Each round every component finds its lightest edge
    (three passes of 32-bit ``atomic_min``), hooks onto the component across it (of a
    mutual pair the root with the smaller input index stays root), roots are pointer-jumped
    with their parities, and edges inside a component are dropped from the list.

    Returns
    -------
    Forest
    """
    import pyopencl as cl
    if graph.cloud is not cloud:
        raise ValueError("the graph was built on another DeviceCloud")
    n, k, dev = cloud.n, graph.k, cloud.device
    q, ctx, mf = dev.queue, dev.context, cl.mem_flags
    prg = build(dev, "forest.cl", cloud.defines)
    u32 = np.uint32
    t0 = time.perf_counter()
    buf = lambda nbytes: cl.Buffer(ctx, mf.READ_WRITE, size=max(int(nbytes), 4))
    comp, rank, bw, blo, bhi, flo, fhi = (buf(4 * n) for _ in range(7))
    links = [buf(4 * n), buf(4 * n)]
    par = buf(n)
    flag = buf(4)
    total = np.empty(1, np.uint32)
    one = np.ones(1, np.uint32)
    nx, ny, nz = graph.normals
    _launch(dev, prg.forest_init, n, u32(n), cloud.order, comp, par, rank, bw, blo, bhi, flo)
    # the initial edge list: each undirected edge once
    nb = _blocks(n)
    counts = buf(4 * max(nb, _blocks(n * k)))
    offsets = buf(4 * max(nb, _blocks(n * k)))
    tot = buf(4)
    _launch(dev, prg.graph_count, nb, graph.nbr, cloud.order, u32(n), u32(k), u32(BLOCK), counts)
    _launch(dev, prg.scan_blocks, 1, counts, u32(nb), offsets, tot)
    cl.enqueue_copy(q, total, tot)
    m = int(total[0])
    lists = [[buf(4 * m) for _ in range(3)] for _ in range(2)]
    _launch(dev, prg.graph_edges, nb, graph.nbr, graph.wgt, cloud.order, u32(n), u32(k),
           u32(BLOCK), offsets, *lists[0])
    q.finish()
    t1 = time.perf_counter()
    timings = {"init": t1 - t0, "rounds": []}
    edge_counts, rounds = [], 0
    cur = 0
    while m > 0:
        ta = time.perf_counter()
        eu, ev, ew = lists[cur]
        nb = _blocks(m)
        _launch(dev, prg.min_weight, nb, eu, ev, ew, u32(m), u32(BLOCK), comp, bw, counts)
        _launch(dev, prg.scan_blocks, 1, counts, u32(nb), offsets, tot)
        cl.enqueue_copy(q, total, tot)
        m2 = int(total[0])
        edge_counts.append(m2)
        if m2 == 0:
            timings["rounds"].append(time.perf_counter() - ta)
            break
        out = lists[1 - cur]
        _launch(dev, prg.min_lo, nb, eu, ev, ew, u32(m), u32(BLOCK), offsets, comp, cloud.order,
               bw, blo, *out)
        cur, m = 1 - cur, m2
        eu, ev, ew = out
        _launch(dev, prg.min_hi, _blocks(m), eu, ev, ew, u32(m), u32(BLOCK), comp, cloud.order,
               bw, blo, bhi)
        _launch(dev, prg.hook, n, u32(n), comp, par, rank, nx, ny, nz, bw, blo, bhi, links[0],
               flo, fhi)
        _launch(dev, prg.break_pairs, n, u32(n), comp, cloud.order, links[0], links[1], flo)
        # hook chains: followed to their end (resolve), pointer jumping for a chain longer
        # than CHASE
        cl.enqueue_copy(q, flag, one)
        _launch(dev, prg.resolve, n, u32(n), comp, links[1], u32(CHASE), links[0],
                flag)
        a = 0
        cl.enqueue_copy(q, total, flag)
        while total[0] != 1:
            cl.enqueue_copy(q, flag, one)
            _launch(dev, prg.jump, n, u32(n), comp, links[a], links[1 - a], flag)
            a = 1 - a
            cl.enqueue_copy(q, total, flag)
        _launch(dev, prg.relabel, n, u32(n), comp, par, links[a])
        q.finish()
        rounds += 1
        timings["rounds"].append(time.perf_counter() - ta)
    t2 = time.perf_counter()
    label, parity, elo, ehi = buf(4 * n), buf(n), buf(4 * n), buf(4 * n)
    _launch(dev, prg.forest_out, n, u32(n), cloud.order, nx, comp, par, flo, fhi, label, parity,
           elo, ehi)
    h_label = np.empty(n, np.int32)
    h_par = np.empty(n, np.uint8)
    h_lo = np.empty(n, np.int32)
    h_hi = np.empty(n, np.int32)
    for h, b in ((h_label, label), (h_par, parity), (h_lo, elo), (h_hi, ehi)):
        cl.enqueue_copy(q, h, b)
    q.finish()
    hooked = h_lo >= 0
    edges = np.stack([h_lo[hooked], h_hi[hooked]], axis=1).astype(np.int64)
    res = Forest(h_label.astype(np.int64), h_par.view(bool), edges, rounds, timings,
                 edge_counts)
    timings["output"] = time.perf_counter() - t2
    return res
