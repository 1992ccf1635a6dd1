"""The minimum spanning forest of the orientation graph, on the device (issue 11).

Hoppe et al. (1992) orient normals by propagating a sign along a minimum spanning tree of a
k-nearest-neighbour graph. :mod:`clcurv.orient.graph` builds that graph on the OpenCL device of a
:class:`~clcurv.grid.cloud.DeviceCloud`; :func:`spanning_forest` takes its minimum spanning
forest and returns, for every point, its component and its sign *parity* relative to the
component's root; choosing each component's global sign is left to the caller
(:mod:`clcurv.orient.orientation`).

:func:`spanning_forest` is Boruvka's algorithm on the undirected graph (an edge {i, j} when j
is in i's list or i in j's) under the strict order (weight, smaller input index, larger
input index), hence unique, with 32-bit ``atomic_min`` only (three passes per round), so the
result is bit-identical across runs, work-group sizes and devices computing the same float
weights. See kernels/forest.cl. The edge parity ``n_u . n_v < 0`` is evaluated at the device
precision (``float``: the normals rounded to float32, ``fma(z, z', fma(y, y', x x'))``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import build, launch

#: Points per work-item of the kernels that read the neighbour lists; the edges that these
#: points' lists give stay in the block's own stride of BLOCK * k edges, compacted in place.
BLOCK = 512
#: Longest hook chain followed link by link in a round; longer ones are finished by pointer
#: jumping (a launch and a read-back per halving).
CHASE = 64


@dataclass
class Forest:
    """A minimum spanning forest (:func:`spanning_forest`), host arrays in input order.

    label : (N,) int64
        The input index of the point's component root; -1 for an invalid normal. An
        isolated point is its own root. (When every point is valid and in one component
        the device writes no labels: the host fills in the root.)
    parity : (N,) bool
        True where the point's normal must be negated to agree with its root's normal
        along the tree (XOR of ``n_u . n_v < 0`` over the tree path to the root).
    edges : (M, 2) int64, or None
        The forest's edges (input indices, lo < hi), M = valid points - components; row
        order: by the input index of the component root that hooked through the edge.
        None when :func:`spanning_forest` was called with ``edges=False``.
    rounds : int
        Boruvka rounds that hooked components.
    timings : dict
        Seconds: ``init`` (buffers), ``rounds`` (a list, one per round), ``output``.
    edge_counts : list of int
        Edges joining two components at the start of every round from the second (round 1
        reads the neighbour lists).
    components : int
        Connected components of the valid points.
    """
    label: np.ndarray
    parity: np.ndarray
    edges: np.ndarray
    rounds: int
    timings: dict
    edge_counts: list
    components: int = 0


#: When a dict, every kernel launch of spanning_forest waits for its end and adds its time
#: (seconds) under the kernel's name: a profile, for benchmarks only.
PROFILE = None
#: The kernels whose work-items take BLOCK points (or entries) each: a few thousand long
#: work-items. On a CPU device they run in work-groups of CPU_GROUP, so that the device's
#: threads take them one at a time (in groups of 128 a 1M-point cloud has about 16 groups
#: for the cores, and the last ones run alone).
BLOCK_KERNELS = frozenset({"first_weight", "first_other", "next_edges", "min_weight", "min_lo",
                           "min_hi", "count_roots", "write_roots", "count_edges",
                           "write_edges"})
CPU_GROUP = 1


def _launch(dev, kernel, n, *args):
    limit = {}
    if dev.info.kind == "cpu" and kernel.function_name in BLOCK_KERNELS:
        limit = {"limit": CPU_GROUP}
    if PROFILE is None:
        return launch(dev, kernel, n, *args, **limit)
    t = time.perf_counter()
    launch(dev, kernel, n, *args, **limit)
    dev.queue.finish()
    PROFILE[kernel.function_name] = PROFILE.get(kernel.function_name, 0.0) + \
        time.perf_counter() - t


def _blocks(m, blk):
    return -(-m // blk)


#: Points per work-item of the block kernels on devices other than CPUs: a GPU needs tens
#: of thousands of work-items (1M points make 15,600 blocks of 64; BLOCK = 512, tuned on
#: PoCL, would leave 2,000). Not yet measured on a GPU.
GPU_BLOCK = 64


def block_size(dev):
    """Points per work-item of the block kernels on ``dev``: BLOCK on a CPU device (a few
    thousand long work-items for its few cores), at most GPU_BLOCK on the others."""
    return BLOCK if dev.info.kind == "cpu" else min(BLOCK, GPU_BLOCK)


def spanning_forest(cloud, graph, edges=True):
    """Boruvka's minimum spanning forest of ``graph`` (:func:`clcurv.orient.graph.knn_graph`) on its device.

    Edges are ordered strictly by (float32 weight, smaller input index, larger input
    index), so the forest is unique. Each round every component finds its lightest edge
    (three passes of 32-bit ``atomic_min``), hooks onto the component across it (of a
    mutual pair the root with the smaller input index stays root), roots are pointer-jumped
    with their parities, and edges inside a component are dropped from the list.
    ``edges=False`` skips the edge output (``Forest.edges`` is None): orienting needs only
    the labels and parities.

    Returns
    -------
    Forest
    """
    if graph.cloud is not cloud:
        raise ValueError("the graph was built on another DeviceCloud")
    n, k, dev = cloud.n, graph.k, cloud.device
    blk = block_size(dev)
    q = dev.queue
    prg = build(dev, "forest.cl", cloud.defines)
    u32 = np.uint32
    t0 = time.perf_counter()
    buf = lambda nbytes: device_buffer(dev, max(int(nbytes), 4))
    comp, rank, bw, blo, bhi, flo, fhi, fmask = (buf(4 * n) for _ in range(8))
    links = [buf(4 * n), buf(4 * n)]
    par = buf(n)
    flag = buf(4)
    total = np.empty(1, np.uint32)
    one = np.ones(1, np.uint32)
    nx, ny, nz = graph.normals
    _launch(dev, prg.forest_init, n, u32(n), cloud.order, comp, par, rank, bw, blo, bhi, flo)
    nb = _blocks(n, blk)
    counts = buf(4 * nb)
    tot = buf(4)
    q.finish()
    t1 = time.perf_counter()
    timings = {"init": t1 - t0, "rounds": []}
    edge_counts, rounds = [], 0

    rlists = [buf(4 * n), buf(4 * n)]
    rcounts, roffsets, rtot = buf(4 * nb), buf(4 * nb), buf(4)
    nroots = np.empty(1, np.uint32)

    def merge(nr, rl):
        """Hook the nr roots of the round (rl; None: all points, round 1) across their
        lightest edges, follow the chains, relabel; the roots that stay, in order, into the
        other root list (their number in rtot)."""
        first = rl is None
        every = u32(first)
        rl = rl if rl is not None else rlists[0]
        if first:       # own_o in links[1], own_j in blo
            _launch(dev, prg.first_hook, n, u32(n), cloud.order, rank, nx, ny, nz, links[1],
                    blo, bw, bhi, links[0], flo, fhi)
        else:
            _launch(dev, prg.hook, nr, u32(nr), rl, comp, par, rank, nx, ny, nz, bw, blo, bhi,
                    links[0], flo, fhi)
        _launch(dev, prg.break_pairs, nr, u32(nr), rl, every, cloud.order, links[0], links[1],
                flo)
        # hook chains: followed to their end (resolve), pointer jumping for a chain longer
        # than CHASE
        cl.enqueue_copy(q, flag, one)
        _launch(dev, prg.resolve, nr, u32(nr), rl, every, links[1], u32(CHASE), links[0], flag)
        a = 0
        cl.enqueue_copy(q, total, flag)
        while total[0] != 1:
            cl.enqueue_copy(q, flag, one)
            _launch(dev, prg.jump, nr, u32(nr), rl, every, links[a], links[1 - a], flag)
            a = 1 - a
            cl.enqueue_copy(q, total, flag)
        _launch(dev, prg.relabel, n, u32(n), comp, par, links[a])
        out = rlists[1] if rl is rlists[0] else rlists[0]
        nrb = _blocks(nr, blk)
        _launch(dev, prg.count_roots, nrb, u32(nr), rl, every, u32(blk), comp, rcounts)
        _launch(dev, prg.scan_blocks, 1, rcounts, u32(nrb), roffsets, rtot)
        _launch(dev, prg.write_roots, nrb, u32(nr), rl, every, u32(blk), comp, roffsets, out)
        return out

    # round 1 on the neighbour lists (every point its own component)
    ta = time.perf_counter()
    # own_w, own_o, own_j in links[0], links[1] (free until hook), blo (free in round 1)
    _launch(dev, prg.first_weight, nb, graph.nbr, graph.wgt, cloud.order, u32(n), u32(k),
            u32(blk), bw, fmask, links[0], links[1], blo)
    _launch(dev, prg.first_other, nb, graph.nbr, graph.wgt, cloud.order, links[0],
            links[1], u32(n), u32(k), u32(blk), bw, bhi)
    rl = merge(n, None)
    rounds += 1
    timings["rounds"].append(time.perf_counter() - ta)
    # round 2 on the neighbour lists, writing the edges that join two components (at most
    # one per pair of components and block) into blocks of stride edges; later rounds
    # compact each block in place
    stride = blk * k
    eu, ev, ew = (buf(4 * nb * stride) for _ in range(3))
    m = 1
    while m > 0:
        ta = time.perf_counter()
        if rounds == 1:
            _launch(dev, prg.next_edges, nb, graph.nbr, graph.wgt, cloud.order, fmask,
                    comp, u32(n), u32(k), u32(blk), u32(stride), counts, bw, eu, ev, ew)
        else:
            _launch(dev, prg.min_weight, nb, eu, ev, ew, u32(nb), u32(stride), counts, comp,
                    cloud.order, bw)
        _launch(dev, prg.total, 1, counts, u32(nb), tot)
        cl.enqueue_copy(q, nroots, rtot, is_blocking=False)
        cl.enqueue_copy(q, total, tot)
        m = int(total[0])
        edge_counts.append(m)
        if rounds == 1 and int(nroots[0]) == n:
            rounds = 0          # round 1 hooked nothing: no edges at all
        if m == 0:
            timings["rounds"].append(time.perf_counter() - ta)
            break
        _launch(dev, prg.min_lo, nb, eu, ev, ew, u32(nb), u32(stride), counts, comp,
                cloud.order, bw, blo)
        _launch(dev, prg.min_hi, nb, eu, ev, ew, u32(nb), u32(stride), counts, comp,
                cloud.order, bw, blo, bhi)
        rl = merge(int(nroots[0]), rl)
        rounds += 1
        timings["rounds"].append(time.perf_counter() - ta)
    t2 = time.perf_counter()
    # outputs in buffers free by now (when large enough: eu and ev hold blk k uints a block)
    fits = lambda b, nbytes: b if b.size >= nbytes else buf(nbytes)
    label, parity, elo, ehi = fits(eu, 8 * n), links[0], blo, bhi
    # one root and no invalid normal (each would be a root): every label is that root
    one = int(nroots[0]) == 1 and graph.nvalid == n
    _launch(dev, prg.forest_out, n, u32(n), cloud.order, nx, comp, par, flo, fhi, u32(not one),
            u32(edges), label, parity, elo, ehi)
    h_par = np.empty(n, np.uint8)
    cl.enqueue_copy(q, h_par, parity, is_blocking=False)
    if one:
        root = np.empty(1, np.uint32)
        cl.enqueue_copy(q, root, rl)
        h_label = np.full(n, cloud.grid.order[root[0]], np.int64)
    else:
        h_label = np.empty(n, np.int64)
        cl.enqueue_copy(q, h_label, label, is_blocking=False)
    h_edges = None
    if edges:
        _launch(dev, prg.count_edges, nb, u32(n), u32(blk), elo, counts)
        _launch(dev, prg.scan_blocks, 1, counts, u32(nb), fmask, tot)
        cl.enqueue_copy(q, total, tot)
        h_edges = np.empty((int(total[0]), 2), np.int64)
        if len(h_edges):
            out = fits(ev, h_edges.nbytes)
            _launch(dev, prg.write_edges, nb, u32(n), u32(blk), elo, ehi, fmask, out)
            cl.enqueue_copy(q, h_edges, out)
    q.finish()
    # every invalid point is a root of its own
    res = Forest(h_label, h_par.view(bool), h_edges, rounds, timings, edge_counts,
                 int(nroots[0]) - (n - graph.nvalid))
    timings["output"] = time.perf_counter() - t2
    return res
