"""The k-nearest-neighbour radius: each point's ball radius is the distance to its k-th
nearest point (the point itself the first), found on the device with the grid
(``kernels/knn_radius.cl``), so that every ball holds k points however the density varies.

How: a first cell c is guessed from the bounding box, assuming a surface
(:data:`FIRST_CELL`), and the kernel finds the k-th smallest squared distance among the
candidates within each point's reach in one walk of the cloud binned at a cell (each
vector lane keeps its smallest d^2, :func:`merge_network`; dense spots take a counting
path with more walks, same result). Two paths, by the density (:func:`_tight`, a k-d tree
on a 4000-point subsample, ~2 ms):

- a *tight* cloud, whose median point's k-NN radius is near the mean-density one (a
  uniform sphere, the scans of objects and the aerial tile of the shared data), is binned
  once, at GROWTH c: its largest radii lie near 1.3c (1.32c on a 1M-point uniform sphere),
  so that grid serves the k-NN pass and the operators that follow. Its first walk reaches
  :data:`FIRST_REACH` of that cell (fewer lanes then hold more candidates than they keep),
  the points left walk the whole cell again on the same grid (4 of 1M on the sphere).
  Against binning at c and again at GROWTH c, one binning and its upload less (~60 ms at
  1M) for a walk ~15 ms longer.
- otherwise (a depth image, whose sparse background makes the mean-density cell ~2x the
  median point's radius: the dense points would walk 2.25x the candidates) the cloud is
  binned at c, and the next level at GROWTH c on a worker thread beside it
  (:func:`_bin_ahead`). The first level's reach is each point's largest ball inside its 27
  cells, c plus its distance to its own cell's nearest face (:func:`reach`: c to 1.5c,
  ~1.125c on average; on a 1M-point uniform sphere it leaves 1.8% of the points for the
  next level instead of 8.6%).

A point with fewer than k candidates within its level's reach is unresolved, and the
cloud is binned again at GROWTH (1.5) times the cell for the unresolved points only (up to
:data:`ISOLATION` times the 90th percentile of the k-NN radii: points still unresolved are
isolated); the distances found go from one binning's order to the next's on the device
(gather.cl, :func:`_permute`). The
operators then run on one cloud whose cell is the largest radius (the last level's, the
one binned ahead when the first level's reach resolved every point but some beyond its
cell, or binned again at the largest radius when that cell is much larger), every
point's ball of squared radius r^2 = (d_k + e)^2 (1 + :data:`MARGIN`), e the float
round-off of a distance on a grid of the largest cell c (:data:`ROUND_OFF` eps c, ~2e-6 c
in float), so that their strict ball test holds the k points on any grid (ties, and
distances within ~1e-6 of d_k or within e of it, enter too). The constants (2 / r, ...)
take the ball's radius, d_k + e to ~1e-6. Where the radius varies more than ~500x across a
cloud (float; the sparsest points set c), e exceeds 1e-3 of the smallest radii: a
RuntimeWarning says so, as their balls may then take a few more points than k and their
constants a radius that much larger (precision='double' makes e ~4e-15 c).

Cost: the operators walk cells as large as the largest radius (one grid for the whole
cloud), skipping the rows of cells beyond each point's own ball (ROW_PRUNE) and the whole
chunks of a row's first or last cell when that cell lies beyond it too (the rows' middle
cells: DeviceCloud.with_middles), and so does the MST orientation's graph (its k < K
nearest lie in the point's ball): on the Kinect scene of the shared data (241k points,
radii varying ~19x) MLS2 with k=30 and MST orientation took 4.2 s without the pruning, then
1.24 s with whole rows and 0.74 s with the rows' cells trimmed (2026-12-03).

Documented behaviour:

- ``k`` larger than the number of points: ValueError; ``k`` < 1 or > :data:`MAX_K`:
  ValueError.
- k or more coincident points: radius 0, a ball of the coincident points only (status 2,
  degenerate: NaN).
- isolated points (the k-th neighbour farther than ISOLATION = 4 x the 90th percentile of
  the k-NN radii):
  radius NaN, status 1 (too few neighbours), NaN outputs; they change no other result.
- weights='density' is refused with a k-NN radius: every ball holds k points, so the
  density weights 1 / #N_r(q) would be 1 / k everywhere.

Caveat: Digne & Morel's asymptotic analysis (the constants H = 4 <p - o, n> / r^2, the 2 / r
factors, Theorem 4) is for one fixed r. Each point uses its own r in them, which is the
fixed-radius formula applied to that point's ball; the bias terms then vary from point to
point with r(p), and nothing in the paper bounds the error of a radius that varies in space.
"""
from __future__ import annotations

import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl
from scipy.spatial import cKDTree

from clcurv._shared.constants import PAD
from clcurv._shared.host_memory import empty as host_empty
from clcurv._shared.validate import as_number, as_points, check_finite_box
from clcurv.grid.binning import bounding_box
from clcurv.grid.cloud import DeviceCloud, host_binning, upload_point_r2
from clcurv.orient.graph import knn_defines
from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import build, launch

#: largest k (the kernel keeps k distances per work-item in private memory)
MAX_K = 256
#: a point whose k-th neighbour is farther than this many times the 90th percentile of the
#: k-NN radii is isolated (status 1): the grid would otherwise need cells as large as its distance, and
#: every point's walk would cover them
ISOLATION = 4.0
#: the ball's r^2 is (d_k + ROUND_OFF eps c)^2 (1 + MARGIN): the relative margin covers the
#: rounding of r^2 itself and of d^2 (a few ulps); points within the margins of d_k (ties)
#: enter too
MARGIN = 2.0 ** -19
#: the ball's radius also exceeds d_k by ROUND_OFF device epsilons of the last level's cell
#: c: the absolute round-off of a distance on a grid of cell at most c (each offset q - p is
#: made of coordinates stored relative to cell corners, exact to half an ulp of 3c, and of
#: a row shift: ~5 eps c at most on d, whatever d), on the level that found d_k and again on
#: the operators' grid. A relative MARGIN alone (2^-16 before) covered it only for radii
#: near the cell: where the k-NN radius varies 15x and more across a cloud (one grid, cells
#: of the largest radius) the balls of the densest points held k - 1 points (k - 2) in float
ROUND_OFF = 16
#: warn when ROUND_OFF eps c exceeds this fraction of the radius of more than
#: ROUND_OFF_SHARE of the points: points so much denser than the sparsest have balls whose
#: edge the float grid blurs (precision='double' resolves it); a few near-coincident points
#: (a tiny k-th distance at small k) do not warn
ROUND_OFF_WARN = 1e-3
ROUND_OFF_SHARE = 1e-3
#: the extended reach of knn_radius.cl (reach2) is below the cell plus the distance to the
#: nearest face of the own cell by this many device epsilons of the cell (its build option
#: KNN_REACH_SLACK, :func:`program_defines`)
REACH_SLACK = 64
#: the first cell is this many times the k-NN radius estimated for a surface at the cloud's
#: mean density (:func:`_first_cell`): ~1.13x the median k-NN radius of a 1M-point uniform
#: sphere, where 1.8% of the points (k = 30; 8.6% within the cell alone) need the next
#: level; 1.15 and 1.2 (10% and 4.6%) were no faster with the reach (2026-12-03). (1.6,
#: ~1.5x the median radius, still left 2 of 1M sphere points for the next level and its
#: larger walk made the whole pass slower, 767 vs 693 ms: the walk grows with the cell's
#: area.)
FIRST_CELL = 1.25
#: a cloud whose first cell is at most this many times the estimated median k-NN radius
#: (:func:`_tight`) is binned once, at GROWTH times the first cell, its first walk reaching
#: FIRST_REACH of it: c / median 1.11-1.31 on the uniform sphere, the bunny scans, Igea,
#: Autzen and a sphere whose density varies 10x; 1.9-2.1 on the Kinect scene (the tree:
#: TIGHT_SAMPLE points of the subsample, TIGHT_QUERIES of them queried for their TIGHT_K-th)
TIGHT = 1.5
TIGHT_SAMPLE = 4000
TIGHT_QUERIES = 500
TIGHT_K = 8
#: the first walk of a cloud binned once (tight) reaches this fraction of its cell, the
#: points left then walking the whole cell on the same grid: on the 1M sphere 4 points are
#: left and both walks take ~98 ms (0.8: 128 left, ~98 ms; 0.9: ~103 ms), against ~108
#: reaching the whole cell at once (where more lanes hold more candidates than they keep)
FIRST_REACH = 0.85
#: the cell grows by this factor from one binning to the next (the last cell is then within
#: this factor of the largest radius: the operators walk it)
GROWTH = 1.5
#: bin again at the largest radius when the last level's cell exceeds it by this factor
REBIN_FACTOR = 1.6
_MAX_LEVELS = 64


@dataclass
class KnnRadii:
    """The k-NN radii of a cloud: ``radius`` (N,) float64 input order (NaN: isolated),
    ``isolated`` (N,) bool, ``cloud`` the DeviceCloud the operators run on (cell >= every
    radius), ``r2_sorted`` a device buffer of the per-point r^2 in its sorted order (device
    precision, padded; 0 for isolated points), ``levels`` the cells binned."""
    k: int
    radius: np.ndarray
    isolated: np.ndarray
    cloud: object
    r2_sorted: object
    levels: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)


def check_k(k, n):
    """``k`` as an int in [1, min(MAX_K, n)], or TypeError / ValueError."""
    kk = as_number(k, "k", int, "an integer")
    if kk != k or kk < 1 or kk > MAX_K:
        raise ValueError(f"k must be an integer in [1, {MAX_K}], got {k!r}")
    if kk > n:
        raise ValueError(f"k={kk} exceeds the number of points ({n}): no point has a "
                         f"{kk}-th neighbour")
    return kk


def _first_cell(pts, k, lo, hi, sample=20000):
    """(c, tight): a first cell size c, the radius holding ~1.6 k points at the cloud's mean
    density as a surface, its area estimated from the cells of size s that a subsample of
    ``sample`` points occupies (s large enough for ~20 subsample points per cell of a
    plane; a surface crosses ~1.5 cells per s^2 of its area on average); ``tight`` when
    that mean density is also about the median point's (:func:`_tight`)."""
    c, sub = _mean_density_cell(pts, k, lo, hi, sample)
    return c, _tight(sub, k, len(pts), c)


def _mean_density_cell(pts, k, lo, hi, sample):
    """(c, the subsample) of :func:`_first_cell`."""
    n = len(pts)
    # a contiguous copy: the strided rows cost a cache miss each in every pass below
    sub = np.array(pts[::max(n // sample, 1)], dtype=np.float64)
    # the extents of the subsample's middle 98% (per axis; the bounding box when that is
    # empty): a far outlier or a "no data" point would otherwise make the cell as large
    # as its distance, and every other point's float offsets within it imprecise (one
    # point at 1e7 beside a 0.15 bunny gave every radius 1.1 instead of 0.014)
    if len(sub) >= 50:
        # numpy.quantile's 'lower' 1% and 'higher' 99% order statistics, by one partition
        m = len(sub)
        i, j = math.floor(0.01 * (m - 1)), math.ceil(0.99 * (m - 1))
        part = np.partition(sub.T, [i, j], axis=1)
        slo, shi = part[:, i], part[:, j]
        if (shi - slo).max() > 0:
            lo, hi = slo, shi
            inside = (sub >= lo) & (sub <= hi)
            sub = sub[inside[:, 0] & inside[:, 1] & inside[:, 2]]
    ext = np.sort(hi - lo)[::-1]
    if not ext[0] > 0:
        return 1.0, sub                            # all coincident: any cell holds them
    if not ext[1] > 0:
        return 1.5 * ext[0] * k / n, sub           # collinear
    s = np.sqrt(20.0 * ext[0] * ext[1] / len(sub))
    if not ext[0] / s < 2.0 ** 40:                 # a needle: the bounding-box guess
        return float(1.5 * np.sqrt(k * ext[0] * ext[1] / (np.pi * n))), sub
    cells = np.floor((sub - lo) / s).astype(np.int64)
    dims = cells.max(axis=0) + 1                   # < 2^21 per axis: sample ~ 2e4 points
    occupied = len(np.unique((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]))
    area = max(occupied * s * s / 1.5, 1e-300)
    return float(FIRST_CELL * np.sqrt(k * area / (np.pi * n))), sub


def _tight(sub, k, n, c):
    """Whether the first cell ``c`` is at most :data:`TIGHT` times the median point's k-NN
    radius, estimated from the subsample ``sub`` of the ``n`` points: its distances to their
    TIGHT_K-th nearest within up to TIGHT_SAMPLE of its points (a k-d tree; ~2 ms), scaled
    to k of n points as on a surface. Then the cloud's radii cluster near the mean-density
    one, and :func:`knn_radii` bins it once, at GROWTH c (see there). Not tight where most
    points are much denser than the mean (a depth image's sparse background inflates the
    area: the Kinect scene of the shared data, 1.9x)."""
    t = sub[::max(len(sub) // TIGHT_SAMPLE, 1)]
    if len(t) <= 4 * TIGHT_K:
        return False
    q = t[::max(len(t) // TIGHT_QUERIES, 1)]
    d = cKDTree(t).query(q, TIGHT_K + 1)[0][:, TIGHT_K]
    med = float(np.median(d)) * math.sqrt(k * len(t) / (TIGHT_K * n))
    return bool(c <= TIGHT * med)


#: the share of points allowed to take knn_radius.cl's counting path (see knn_levels)
OVERFLOW_RATE = 0.12


def knn_levels(k, vw):
    """The d^2 values knn_radius.cl keeps per vector lane (KNN_LEVELS, 4 to 15) for ``k`` on
    ``vw`` lanes: the fewest for which the points with a lane holding more of their k nearest
    than it keeps, the points that take the slower counting path, are expected to be at
    most OVERFLOW_RATE of them, a lane's share of the k nearest being about Poisson with
    mean k / vw (expected share vw P(X > levels)). Each level costs a min and a max per
    chunk of candidates, so too many cost as well: at k = 30 on the first cell of a 1M
    sphere this gives 8 levels at vw = 8 and 6 at vw = 16, the fastest measured
    (kernels/knn_radius.cl has the figures)."""
    mu, term, cdf = k / vw, math.exp(-k / vw), 0.0
    for levels in range(15):
        cdf += term
        if levels >= 4 and vw * (1.0 - cdf) <= OVERFLOW_RATE:
            return levels
        term *= mu / (levels + 1)
    return 15


#: candidate chunks knn_radius.cl sorts together and merges into the kept values at once
#: (:func:`merge_network`): at 8 levels 12 min/max per chunk, against 15 inserting each
#: chunk alone (3, 4 and 8 need fewer, 10.3, 9.5 and 8.8, but were slower on the EPYC: the
#: kept values and the batch no longer fit the registers)
KNN_BATCH = 2


def _odd_even_merge(a, b):
    """Comparators (i, j) of Batcher's odd-even merge of the sorted positions ``a`` and
    ``b`` (any sizes; Knuth 5.3.4): after them the positions ``a + b`` hold the values
    sorted."""
    if not a or not b:
        return []
    if len(a) == 1 and len(b) == 1:
        return [(a[0], b[0])]
    out = _odd_even_merge(a[0::2], b[0::2]) + _odd_even_merge(a[1::2], b[1::2])
    seq = a + b
    out += [(seq[i], seq[i + 1]) for i in range(1, len(seq) - 1, 2)]
    return out


def _sorting_network(pos):
    """Comparators sorting the positions ``pos`` (odd-even merge sort)."""
    if len(pos) <= 1:
        return []
    h = len(pos) // 2
    return (_sorting_network(pos[:h]) + _sorting_network(pos[h:])
            + _odd_even_merge(pos[:h], pos[h:]))


def merge_comparators(levels, batch):
    """The comparators that keep, sorted, the ``levels`` smallest of ``levels`` sorted
    values (positions 0 .. levels - 1) and ``batch`` new ones (positions levels ..): the
    batch sorted, then merged, and every comparator pruned whose outputs no kept position
    needs. Each is (i, j, kind), kind "ce" (min to i, max to j), "lo" (only the min, to i)
    or "hi" (only the max, to j)."""
    net = (_sorting_network(list(range(levels, levels + batch)))
           + _odd_even_merge(list(range(levels)), list(range(levels, levels + batch))))
    live, out = set(range(levels)), []
    for i, j in reversed(net):
        kind = ("ce" if i in live and j in live else "lo" if i in live
                else "hi" if j in live else None)
        if kind is not None:
            out.append((i, j, kind))
            live |= {i, j}
    return out[::-1]


def merge_network(levels, batch):
    """knn_radius.cl's KNN_MERGE for :func:`merge_comparators`: the kept values a[], the
    batch b[] (one build option, no spaces)."""
    def name(i):
        return f"a[{i}]" if i < levels else f"b[{i - levels}]"
    return "".join(f"KNN_{kind.upper()}({name(i)},{name(j)})"
                   for i, j, kind in merge_comparators(levels, batch))


def reach(cloud):
    """Each point's extended reach in a walk of ``cloud`` (input order, float64, a bound
    slightly below knn_radius.cl:reach2's): the cell plus the point's distance to the
    nearest face of its own cell, less REACH_SLACK epsilons of the cell, and at least the
    cell. Every point within it lies in the 27 cells of the point's walk."""
    g = cloud.grid
    eps = float(np.finfo(cloud.dtype).eps)
    rel = g.rel.astype(np.float64)                 # input order, within the own cell
    face = np.minimum(rel, g.cell - rel).min(axis=1).clip(0, None)
    return np.maximum(g.cell + face - (REACH_SLACK + 4) * eps * g.cell, g.cell)


def _kth_launch(cloud, k, prev=None, levels=None, extend=False, reach=None):
    """Enqueue and flush knn_radius.cl on ``cloud``: the squared distance to the k-th
    nearest point within the cloud's cell (device precision, the cloud's sorted order; +inf
    where fewer than k points lie within it), or with ``extend`` within each point's reach
    (:func:`reach`). Points with a finite ``prev`` value (sorted order; a host array or a
    device buffer) keep it and are not walked. ``levels`` overrides the d^2 values the
    kernel keeps per vector lane (KNN_LEVELS; tests: 1 sends nearly every point down the
    kernel's counting path, which must give the same values). ``reach`` (at most the cell,
    which it is by default; not with ``extend``) narrows the walk's ball: +inf where fewer
    than k points lie within it. Returns the output buffer for :func:`_kth_fetch`; the
    device works while the host goes on."""
    prg = _program(cloud, k, levels)
    mf, ctx, q = cl.mem_flags, cloud.device.context, cloud.device.queue
    nbytes = cloud.n * np.dtype(cloud.dtype).itemsize
    if prev is None:
        prev_buf = device_buffer(cloud.device, nbytes)
        cl.enqueue_fill_buffer(q, prev_buf, cloud.dtype(np.inf), 0, nbytes)
    elif isinstance(prev, np.ndarray):
        prev_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=prev)
    else:
        prev_buf = prev                             # a device buffer (sorted order)
    out = device_buffer(cloud.device, nbytes)
    launch(cloud.device, prg.kth_distance, cloud.n, cloud.x, cloud.y, cloud.z,
           cloud.cell_of, cloud.ranges, np.uint32(cloud.n),
           cloud.ball(cloud.cell if reach is None else min(float(reach), cloud.cell)), prev_buf,
           out, np.uint32(bool(extend)))
    q.flush()
    return out


def _program(cloud, k, levels=None):
    """knn_radius.cl for ``k`` on ``cloud``'s device: VW the native width on a CPU (16 with
    AVX-512, clcurv.orient.graph.knn_defines), KNN_LEVELS :func:`knn_levels` unless ``levels``."""
    opts = knn_defines(cloud)
    lv = int(knn_levels(k, int(opts["VW"])) if levels is None else levels)
    opts.update(program_defines(k, lv))
    return build(cloud.device, "knn_radius.cl", opts)


def program_defines(k, levels, batch=None):
    """knn_radius.cl's own build options for ``k`` and ``levels`` kept per lane (``batch``:
    :data:`KNN_BATCH` unless given)."""
    batch = KNN_BATCH if batch is None else batch
    return dict(KNN_K=int(k), KNN_LEVELS=int(levels), KNN_BATCH=int(batch),
                KNN_MERGE=merge_network(int(levels), int(batch)), KNN_REACH_SLACK=REACH_SLACK)


def _kth_fetch(cloud, out):
    """The result of :func:`_kth_launch` on the host (waits for the kernel)."""
    host = host_empty(cloud.n, cloud.dtype)         # pooled pages (clcurv._shared.host_memory)
    cl.enqueue_copy(cloud.device.queue, host, out)
    return host


def knn_radii(points, k, *, device=None, precision="float"):
    """The :class:`KnnRadii` of ``points`` for ``k`` (see the module notes)."""
    pts = as_points(points, finite=False)      # checked on the bounding box
    t0 = time.perf_counter()
    k = check_k(k, len(pts))
    lo, hi = box = bounding_box(pts)
    check_finite_box(pts, lo, hi)
    diag = float(np.linalg.norm(hi - lo))
    c, tight = _first_cell(pts, k, lo, hi)
    if tight:
        c *= GROWTH                  # one binning, the operators' too (see the module notes)
    cap = None
    levels = []
    d2_in = None            # device: the k-th d^2 found so far, input order (inf: not yet)
    spec = None
    stages = {"first_cell": time.perf_counter() - t0, "binning": 0.0, "kth": 0.0}
    if not tight and GROWTH * c <= diag:
        spec = _bin_ahead(pts, GROWTH * c, precision, box)
    while True:
        t1 = time.perf_counter()
        binned = spec[1].result() if spec is not None and spec[0] == c else \
            host_binning(pts, c, precision=precision, box=box)
        cloud = DeviceCloud(None, None, binned=binned, device=device)
        if spec is not None and spec[0] <= c:
            spec = None
        t2 = time.perf_counter()
        # the first level reaches up to 1.5 c (reach), its next level binned ahead at 1.5 c
        extend = not levels and spec is not None
        prev = None if d2_in is None else _permute(cloud, d2_in, False)
        if tight and not levels:
            # the first walk within FIRST_REACH c, then the points left within c
            out = _kth_launch(cloud, k, prev, reach=FIRST_REACH * c)
            d2 = _kth_fetch(cloud, out)
            if not np.isfinite(d2).all():
                out = _kth_launch(cloud, k, out)
                d2 = _kth_fetch(cloud, out)
        else:
            out = _kth_launch(cloud, k, prev, extend=extend)
            d2 = _kth_fetch(cloud, out)                             # sorted order
        stages["binning"] += t2 - t1
        stages["kth"] += time.perf_counter() - t2
        if not levels:
            stages["kth_first"] = stages["kth"]
        levels.append(c)
        ok = np.isfinite(d2)
        if cap is None:
            resolved = int(np.count_nonzero(ok))
            # every point resolved and none isolated whatever the percentile: no cap needed
            cap = math.inf if resolved == len(d2) and _none_isolated(d2) else \
                _isolation_cap(d2, resolved, c if extend else math.inf)
        if ok.all() or c > diag or (cap is not None and c >= cap) \
                or len(levels) >= _MAX_LEVELS:
            break
        c = GROWTH * c if cap is None else min(GROWTH * c, max(cap, c))
        if spec is not None and spec[0] != c:
            spec = _drop(spec)
        d2_in = _permute(cloud, out, True)
    if extend and ok.any() and float(d2[ok].max()) >= c * c * (1 - 2.0 ** -10):
        # radii beyond the first cell, found within the reach: the operators' cloud is the
        # one binned ahead at 1.5 c, whose walks hold those balls
        t1 = time.perf_counter()
        cloud, c, out, d2 = _to_level(cloud, spec, device, out, d2)
        ok = np.isfinite(d2)
        levels.append(c)
        stages["binning"] += time.perf_counter() - t1
    spec = _drop(spec)
    # the last level's results: out (device) and d2 (host), its cloud's sorted order
    if ok.all() and (cap is None or not np.sqrt(float(d2.max())) > cap):
        radius, iso_in, cloud, buf = _all_resolved(pts, box, k, cloud, c, out, d2, levels)
    else:
        radius, iso_in, cloud, buf = _some_isolated(pts, box, cloud, c, d2, ok, cap, levels)
    stages["knn_radius"] = time.perf_counter() - t0
    return KnnRadii(k, radius, iso_in, cloud, buf, levels, stages)


def _all_resolved(pts, box, k, cloud, c, out, d2, levels):
    """(radius, isolated, the operators' cloud, its r^2 buffer) when every point has its k-th
    distance ``d2`` within the last cell ``c`` (the usual case): the permutations and r^2 on
    the device. The operators' cloud is the last level's, or binned again at the largest
    radius when ``c`` is much larger (appended to ``levels``)."""
    slack = _slack(c, cloud.dtype)
    top = float(np.sqrt(float(_margin(d2.max(keepdims=True), cloud.dtype, slack)[0])))
    d2_in = _permute(cloud, out, True)
    radius = np.sqrt(_kth_fetch(cloud, d2_in), dtype=np.float64, out=host_empty(cloud.n))
    if c > REBIN_FACTOR * top and top > 1e-3 * c:
        # the operators' walk at the largest radius, not at the last level's cell
        cloud = _rebin(pts, box, top, cloud)
        levels.append(cloud.cell)
        out = _permute(cloud, d2_in, False)
    _warn_round_off(c, slack, radius)
    return radius, np.zeros(cloud.n, bool), cloud, _ball_r2(cloud, k, out, slack)


def _some_isolated(pts, box, cloud, c, d2, ok, cap, levels):
    """:func:`_all_resolved` when some points are isolated (no k-th neighbour within the
    last cell, or one beyond ``cap``): their radius NaN and r^2 0, on the host."""
    order = cloud.grid.order
    radius, iso_in = np.empty(cloud.n), np.zeros(cloud.n, bool)
    d2 = d2.astype(np.float64)
    isolated = ~ok
    if cap is not None:                          # beyond the cap within the last cell
        isolated |= np.sqrt(np.where(ok, d2, 0.0)) > cap
    live = ~isolated
    slack = _slack(c, cloud.dtype)
    r2 = _margin(np.where(isolated, 0.0, d2), cloud.dtype, slack)
    r2[isolated] = 0
    top = float(np.sqrt(r2[live].max())) if live.any() else 0.0
    radius[order] = np.where(isolated, np.nan, np.sqrt(np.where(isolated, 0.0, d2)))
    iso_in[order] = isolated
    _warn_round_off(c, slack, radius)
    if live.any() and c > REBIN_FACTOR * top and top > 1e-3 * c:
        r2_in = np.empty(cloud.n, cloud.dtype)
        r2_in[order] = r2
        cloud = _rebin(pts, box, top, cloud)
        levels.append(cloud.cell)
        r2 = r2_in[cloud.grid.order]
    return radius, iso_in, cloud, upload_point_r2(cloud, r2)


def _rebin(pts, box, cell, cloud):
    """The operators' cloud binned again at ``cell`` (the largest radius), on ``cloud``'s
    device and precision; ``box``: the points' bounding box, known already."""
    return DeviceCloud(None, None, device=cloud.device,
                       binned=host_binning(pts, cell, precision=cloud.precision, box=box))


_HOST = None


def _bin_ahead(pts, c, precision, box):
    """(c, future of :func:`clcurv.grid.cloud.host_binning` at c) on a worker thread: the second
    level's cell is GROWTH times the first in nearly every run (a uniform surface leaves ~5%
    of the points for it), and its binning (numpy, one core) then runs beside the first
    level's instead of after the first walk. Host work only: the OpenCL calls (the upload,
    DeviceCloud(binned=)) stay on the calling thread (a second thread's OpenCL calls crashed
    Oclgrind). An error surfaces where the level is used, as it would have there."""
    global _HOST
    if _HOST is None:
        _HOST = ThreadPoolExecutor(1, thread_name_prefix="clcurv-knn-bin")
    # on one core: the main thread's binning of the first level uses both meanwhile (with
    # its parts on the host pool too, the four threads' GIL hand-offs cost ~6 ms at 1M)
    return c, _HOST.submit(host_binning, pts, c, precision=precision, threads=1, box=box)


def _drop(spec):
    """Wait for an unused binning ahead (so that no work outlives the call); None."""
    if spec is not None:
        spec[1].exception()
    return None


def _to_level(cloud, spec, device, out, d2):
    """(cloud, cell, out, d2) moved to the level binned ahead (``spec``): its DeviceCloud,
    and the k-th d^2 of ``cloud``'s sorted order (``out`` on the device, ``d2`` on the
    host) in its sorted order."""
    wide = DeviceCloud(None, None, binned=spec[1].result(), device=device)
    moved = _permute(wide, _permute(cloud, out, True), False)
    # done before the caller lets go of ``cloud``: a CPU device reads its host arrays in
    # place (its order, USE_HOST_PTR), which go with it
    cloud.device.queue.finish()
    d2_in = np.empty(cloud.n, d2.dtype)
    d2_in[cloud.grid.order] = d2
    return wide, spec[0], moved, d2_in[wide.grid.order]


def _isolation_cap(d2, resolved, below=math.inf):
    """ISOLATION times the 90th percentile of the k-NN radii of all the points
    (numpy.quantile's linear interpolation over the n radii), or None while it is unknown.
    ``d2``: the n squared radii found so far, ``resolved`` of them finite, +inf the others.
    An unresolved point's radius exceeds every resolved one when each level walks its cell
    (it lies beyond the cell that resolved them); with an extended reach (the first level),
    only the radii below ``below``, the cell (the smallest reach), are all resolved. So the
    percentile's two order statistics are the resolved radii's once more than ~90% of the
    points are resolved and both lie below ``below`` (None otherwise; taking the
    percentile of the resolved radii alone instead, as before, understated it: on the
    Autzen tile at k = 30, 96% resolved, 8.65 against 9.57 ft, and 149 points were made
    isolated instead of 91). By
    one numpy.partition at one index and the minimum above it (1.3 ms on 1M float32, where
    numpy.quantile takes 8-12; no copy of the values)."""
    n = len(d2)
    at = (n - 1) * 0.9
    i = int(np.floor(at))
    frac = at - i
    if resolved < i + (2 if frac > 0 else 1):
        return None
    part = np.partition(d2, i)
    a = math.sqrt(float(part[i]))
    b = math.sqrt(float(part[i + 1:].min())) if frac > 0 else a
    if not b < below:
        return None
    return ISOLATION * (a + (b - a) * frac)


def _none_isolated(d2):
    """Whether the n finite squared radii ``d2`` are at most the isolation cap whatever its
    exact value (:func:`_isolation_cap`): when at most i = floor(0.9 (n - 1)) of them lie
    below (max / ISOLATION)^2 (widened by 2^-20 for the float32 compare), the percentile's
    lower order statistic is at least the largest radius over ISOLATION. A count (~1 ms at
    1M) where the percentile's partition takes ~8."""
    n = len(d2)
    i = int(np.floor((n - 1) * 0.9))
    limit = float(d2.max()) / ISOLATION ** 2 * (1 + 2.0 ** -20)
    return int(np.count_nonzero(d2 < limit)) <= i


def _slack(cell, dtype):
    """The absolute widening of every radius on grids of cells at most ``cell``: ROUND_OFF
    epsilons of ``dtype`` times the cell, in ``dtype``."""
    return dtype(ROUND_OFF * np.finfo(dtype).eps * cell)


def _margin(d2, dtype, slack):
    """The balls' r^2 from the k-th d^2 (the operations of knn_radius.cl:ball_r2, in
    ``dtype``): (sqrt(d2) + slack)^2 (1 + MARGIN), at least the smallest normal of
    ``dtype`` (so that coincident points, d2 = 0, pass d^2 < r^2)."""
    d = np.sqrt(np.asarray(d2, dtype=dtype)) + dtype(slack)
    x = np.multiply(d * d, dtype(1 + MARGIN), dtype=dtype)
    return np.maximum(x, np.finfo(dtype).tiny, out=x)


def _warn_round_off(cell, slack, radius):
    """RuntimeWarning when the grid's round-off ``slack`` (:func:`_slack` of ``cell``)
    exceeds ROUND_OFF_WARN of some positive ``radius`` (zeros: coincident points)."""
    # positive radii below slack / ROUND_OFF_WARN (NaN, isolated, compares False); first
    # a bound by one compare (zeros counted too, the limit widened), the usual answer
    if not np.count_nonzero(radius < float(slack) / ROUND_OFF_WARN * (1 + 2.0 ** -20)) \
            > ROUND_OFF_SHARE * len(radius):
        return
    few = int(np.count_nonzero((radius > 0) & (radius * ROUND_OFF_WARN < float(slack))))
    if not few > ROUND_OFF_SHARE * len(radius):
        return
    live = radius[np.isfinite(radius) & (radius > 0)]
    warnings.warn(f"k-NN radius: {few} of {len(radius)} points have a radius below "
                  f"{float(slack) / ROUND_OFF_WARN:.3g} (the smallest {float(live.min()):.3g}), "
                  f"far below the grid's cell {cell:.3g} that the sparsest points set: the "
                  f"float round-off of the grid ({float(slack):.2g}) blurs the edge of their "
                  "balls, which may hold a few more than k points, and enters their radius in "
                  "the constants (2 / r, ...) by over 1e-3; precision='double' resolves it",
                  RuntimeWarning, stacklevel=6)    # the caller of features / curvature


def _permute(cloud, buf, to_input):
    """A one-column device buffer of ``cloud``'s points in the other order (gather.cl):
    sorted to input order (``to_input``), or input to sorted order (padded with PAD zeros)."""
    prg = build(cloud.device, "gather.cl", cloud.defines)
    item = np.dtype(cloud.dtype).itemsize
    out = device_buffer(cloud.device, (cloud.n + (0 if to_input else PAD)) * item)
    launch(cloud.device, prg.to_input if to_input else prg.to_sorted,
           cloud.n + (0 if to_input else PAD), buf, cloud.order, np.uint32(cloud.n), out)
    return out


def _ball_r2(cloud, k, d2_sorted, slack):
    """The per-point r^2 (knn_radius.cl:ball_r2, :func:`_margin` on the device) of the k-th
    d^2 in ``cloud``'s sorted order (a device buffer, no point isolated), ``slack`` the
    grid's round-off (:func:`_slack`): a padded device buffer."""
    prg = _program(cloud, k)
    out = device_buffer(cloud.device, (cloud.n + PAD) * np.dtype(cloud.dtype).itemsize)
    launch(cloud.device, prg.ball_r2, cloud.n + PAD, d2_sorted, np.uint32(cloud.n),
           cloud.dtype(1 + MARGIN), cloud.dtype(slack), out)
    return out
