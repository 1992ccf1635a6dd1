"""What the file job needs to run in tiles (:func:`clcurv.jobs.job.run_tiled`):
``radius="auto"`` without the whole cloud (:func:`auto_radius_tiled`), and the progress bar
and Dask client of a tiled run (:func:`tile_session`)."""
from __future__ import annotations

import math
import sys
import tempfile
import time
from contextlib import contextmanager

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from clcurv.grid.binning import Frame
from clcurv.tiles.buckets import BUCKETS_PER_TILE, READ_CHUNK, Buckets, bucket_grid
from clcurv.tiles.planning import TILE_BYTES_PER_POINT, occupancy
from clcurv.tiles.workers import connect

#: most points :func:`auto_radius_tiled` holds at once (its regions together), whatever the
#: budget: more would not make the estimate better, only slower
_RADIUS_POINTS = 1 << 21
#: most blocks of the occupancy that :func:`auto_radius_tiled` counts in its first pass
#: (:func:`clcurv.tiles.planning.occupancy` doubles them until they fit; its OCCUPANCY_BLOCKS)
_RADIUS_BLOCKS = 1 << 18
#: a block whose region is too full is counted again in 2^_REFINE x 2^_REFINE sub-blocks
_REFINE = 4


def auto_radius_tiled(src, k=30, regions=None, sample=5000, seed=0, budget=None):
    """``radius="auto"`` of a cloud too large for memory: the median, over about
    ``sample`` points drawn uniformly from the cloud (seeded) in ``regions`` draws of a
    region (None: as many as the budget holds, :func:`_radius_budget`; at least 16), of
    the distance to the k-th nearest other point, each computed from the points of its
    region and kept only when that neighbour lies inside the region (so each distance is
    the whole cloud's). It estimates the in-memory auto radius (clcurv.jobs.job.auto_radius, a
    sample of the whole cloud) to a few per cent, not to the bit: pass the radius for
    reproducible runs.

    Its memory is bounded whatever the cloud's extent (one far "no data" point stretches
    the header's box: the bucket grid then puts the whole survey in one bucket, which was
    read whole): the regions together hold at most about min(``budget`` /
    TILE_BYTES_PER_POINT, 2^21) points (256 MiB without a budget), each at most
    :func:`_radius_budget`'s ``per`` (a stack of points at one x-y position, which no
    block splits, is read alone, up to the same total). A region is a block of x-y cells
    of a fine frame with a margin of one block on each side. The occupied blocks are
    counted in one pass (:func:`clcurv.tiles.planning.occupancy`); each point's region is the
    largest block around it whose region fits (counted again, finer, where even the
    finest is too full); regions
    are drawn in proportion to their points, systematically along the Z order (spread
    over the cloud as its points are; a region drawn twice gives twice the samples), and
    read in one pass over the buckets, a block of records at a time, keeping only the
    points inside them. Many small regions, not a few large ones: a cloud of uneven
    density (flight-line overlaps) is then sampled as a uniform sample of its points."""
    per, count = _radius_budget(budget, k, sample, regions)
    with tempfile.TemporaryDirectory(prefix="clcurv-radius-") as tmp:
        target = max((budget or (1 << 28)) // (TILE_BYTES_PER_POINT * 9), 10_000)
        origin, side, shape = bucket_grid(src, target * BUCKETS_PER_TILE ** 2)
        b = Buckets(tmp, origin, side, shape, False)
        for start, xyz, _ in src.chunks(READ_CHUNK):
            b.add(start, xyz, None)
        if b.counts.sum() <= k:
            raise ValueError(f"radius auto needs more than {k} points")
        frame = _radius_frame(b)
        occ = occupancy(b, frame, g=1, limit=_RADIUS_BLOCKS)
        rng = np.random.default_rng(seed)
        picks, crowded = _pick_regions(b, frame, occ, per, count, per * count, rng)
        if not picks:
            raise ValueError("radius auto: the points crowd into too few x-y positions "
                             "(stacks of points) to be sampled within the memory budget; "
                             "give the radius")
        each = -(-sample // count)
        dists = []
        # the regions together in one pass, then each crowded one alone
        for group in [sorted(set(picks) - crowded)] + [[blk] for blk in sorted(crowded)]:
            centres = np.array(group, np.int64).reshape(-1, 3)
            regions = np.array([picks[c][1] for c in group], np.int64).reshape(-1, 3)
            dists += _region_distances(frame, centres, regions,
                                       _gather_regions(b, frame, occ, regions),
                                       [picks[c][0] * each for c in group], k, rng, cKDTree)
        if not dists:
            raise ValueError(f"radius auto needs more than {k} points")
        r = float(np.median(np.concatenate(dists)))
        if not r > 0:
            raise ValueError("radius auto: the sampled points have duplicates for "
                             "neighbours; give the radius")
        return r


def _region_distances(frame, centres, regions, clouds, samples, k, rng, tree):
    """The k-th neighbour distances of ``samples`` points (at most all) drawn in each
    centre block (``centres`` (s, x, y)) among the points ``clouds`` of the region of its
    block of ``regions``: those whose k-th neighbour lies inside the region (d no more
    than the room to the region's sides that have points beyond them), or all of a
    region's when none does."""
    nx, ny = frame.dims[:2]
    o, cell = np.asarray(frame.origin[:2]), frame.cell
    dists = []
    for (s, x, y), (rs, rx, ry), cloud, want in zip(centres.tolist(), regions.tolist(),
                                                    clouds, samples):
        if len(cloud) <= k:
            continue
        c = frame.cells_xy(cloud) // s
        centre = cloud[(c[:, 0] == x) & (c[:, 1] == y)]
        q = centre[rng.choice(len(centre), size=min(len(centre), want), replace=False)]
        d, _ = tree(cloud).query(q, k=k + 1)
        d = d.reshape(len(q), -1)[:, -1]
        # the sides at or beyond the cloud's bounds have no points beyond them
        c0, c1 = np.array([rx - 1, ry - 1]) * rs, np.array([rx + 2, ry + 2]) * rs
        lo = np.where(c0 <= 0, -np.inf, o + c0 * cell)
        hi = np.where(c1 >= [nx, ny], np.inf, o + c1 * cell)
        room = np.min(np.concatenate([q[:, :2] - lo, hi - q[:, :2]], axis=1), axis=1)
        keep = d <= room
        dists.append(d[keep] if keep.any() else d)
    return dists


def _radius_budget(budget, k=30, sample=5000, regions=None):
    """(per, count): the most points of one region of :func:`auto_radius_tiled` and the
    regions it draws. All together they hold at most ``budget`` / TILE_BYTES_PER_POINT
    points (256 MiB without a budget), at most _RADIUS_POINTS; a region at least
    50 (k + 1) points (a region holds more than a quarter of ``per``, else its parent
    block's would fit: its centre block is then 2 to 4 times wider than the k-th
    neighbour's distance where the density is even). ``regions`` None: as many as that
    allows (at least 16, at most ``sample`` / 4)."""
    held = min(max(int(budget or (1 << 28)) // TILE_BYTES_PER_POINT, 1), _RADIUS_POINTS)
    least = 50 * (k + 1)
    count = int(regions) if regions else max(16, min(held // least, max(sample // 4, 1)))
    return max(held // max(count, 1), least), max(count, 1)


def _radius_frame(b):
    """A frame of x-y cells over the exact bounds of the points of ``b``, as fine as int64
    keys allow (at most 2^30 + 1 cells a side; a power of two: blocks nest exactly)."""
    lo, hi = np.asarray(b.lo, float), np.asarray(b.hi, float)
    ext = float(np.max(hi[:2] - lo[:2]))
    if not np.isfinite(ext):
        raise ValueError("radius auto: the cloud's extent overflows; give the radius")
    cell = 2.0 ** math.ceil(math.log2(ext / 2 ** 30)) if ext > 2.0 ** -900 else 1.0
    top = ((hi[:2] - lo[:2]) * (1.0 / cell)).astype(np.int64) + 1
    return Frame(tuple(float(v) for v in lo), cell, (int(top[0]), int(top[1]), 1))


def _region_levels(bx, by, n, per, top=None):
    """For each block (``bx``, ``by``) of a level (``n`` points each; every occupied block
    of the area that matters): the largest m <= ``top`` (None: until one block is left)
    such that its block of 2^m blocks a side, with one such block around it, holds at
    most ``per`` points; -1 when not even m = 0 does. The region of a block grows with m,
    so the blocks it gives partition the points. The levels at which every region fits
    are skipped by bisection (a fine frame has many), the others made each from the one
    below (the cost follows the blocks)."""
    best = np.full(len(n), -1)
    if not len(n):
        return best
    n = n.astype(float)
    lo = -1                                     # (at level hi, one block)
    hi = int(max(bx.max(), by.max())).bit_length() if top is None else int(top)
    while lo < hi:                              # the last level where all regions fit
        mid = (lo + hi + 1) // 2
        u, inv = np.unique(((bx >> mid) << 32) + (by >> mid), return_inverse=True)
        if _region_counts(u, np.bincount(inv.ravel(), weights=n)).max() <= per:
            lo = mid
        else:
            hi = mid - 1
    m = max(lo, 0)
    best[:] = lo
    keys, cnt = ((bx >> m) << 32) + (by >> m), n
    up = np.arange(len(n))                      # each block's block of the level m
    while True:
        u, inv = np.unique(keys, return_inverse=True)
        inv = inv.ravel()
        cnt = np.bincount(inv, weights=cnt)
        up = inv[up]
        fits = _region_counts(u, cnt) <= per
        if not fits.any():
            return best
        best[fits[up]] = m
        if len(u) == 1 or (top is not None and m >= top):
            return best
        keys = ((u >> 33) << 32) + ((u & 0xFFFFFFFF) >> 1)
        m += 1


def _region_counts(u, cnt):
    """The points of the region (the block with the 8 around it) of each block of the
    sorted keys ``u`` ((x << 32) + y) holding ``cnt`` points each."""
    reg = np.zeros(len(u))
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            want = u + ((dx << 32) + dy)
            at = np.minimum(np.searchsorted(u, want), len(u) - 1)
            reg += np.where(u[at] == want, cnt[at], 0.0)
    return reg


def _candidates(bx, by, n, s, best, lift=None):
    """The regions of the blocks (``bx``, ``by``) of ``s`` cells with their
    :func:`_region_levels` ``best``: (sides, x, y, points, kind, regions) of the distinct
    blocks, kind 0 for a block whose region fits, 1 for one too full (its own block of
    ``s`` cells: it needs a finer count), 2 for a block of one cell too full (a stack of
    points at one x-y position, which no block splits): its samples are taken in it, but
    its region is that of its block ``lift`` levels up (the :func:`_region_levels` of a
    larger bound: the stack is read alone, with a margin that holds its neighbours; left
    out when even its own region is beyond that bound). ``regions``: (R, 3) the block
    (side, x, y) whose region each reads (itself, but for kind 2)."""
    ok = np.flatnonzero(best >= 0)
    m = best[ok]
    cx, cy = (bx[ok] >> m) << m, (by[ok] >> m) << m      # corners: one block per corner
    u, first, inv = np.unique((cx << 32) + cy, return_index=True, return_inverse=True)
    cnt = np.bincount(inv.ravel(), weights=n[ok].astype(float), minlength=len(u))
    m = m[first]
    no = np.flatnonzero(best < 0)
    up = np.zeros(len(no), np.int64)
    if s == 1 and len(no):
        no = no[lift[no] >= 0]
        up = lift[no]
    sides = np.concatenate([np.int64(s) << m, np.full(len(no), s, np.int64)])
    xs = np.concatenate([cx[first] >> m, bx[no]])
    ys = np.concatenate([cy[first] >> m, by[no]])
    regions = np.stack([sides, xs, ys], axis=1)
    regions[len(u):] = np.stack([np.int64(s) << up, bx[no] >> up, by[no] >> up], axis=1)
    return (sides, xs, ys, np.concatenate([cnt, n[no].astype(float)]),
            np.concatenate([np.zeros(len(u), np.int8),
                            np.full(len(no), 1 if s > 1 else 2, np.int8)]), regions)


def _pick_regions(b, frame, occ, per, count, held, rng):
    """({(s, x, y): (times drawn, region)}, crowded) of the regions of
    :func:`auto_radius_tiled`: ``count`` draws weighted by their points, each the block
    (x, y) of s cells of ``frame`` in which its samples are taken, and the block whose
    region (the block with one block around it) is read: itself, holding at most ``per``
    points. The draws are systematic over the blocks in Z order (:func:`_draw`): spread
    over the cloud as its points are, so a cloud of uneven density is sampled as a uniform
    sample of its points would be. A drawn block too full even at the occupancy ``occ``'s
    finest level is counted again in finer blocks (one pass over the buckets for all such
    draws) and its draws made among those, until they fit. ``crowded``: the drawn blocks
    of one cell too full (stacks of points at one x-y position): each is read alone, in
    the largest region around it that holds at most ``held`` points."""
    best = _region_levels(occ.bx, occ.by, occ.count, per)
    lift = (_region_levels(occ.bx, occ.by, occ.count, held)
            if occ.g == 1 and (best < 0).any() else None)
    first = _candidates(occ.bx, occ.by, occ.count, occ.g, best, lift)
    picks, crowded, pending = {}, set(), {}

    def add(s, x, y, n, kind, regions, times, into_pending):
        for a in _draw(s, x, y, n, times, rng):
            blk = (int(s[a]), int(x[a]), int(y[a]))
            if kind[a] == 1:
                into_pending[blk] = into_pending.get(blk, 0) + 1
                continue
            picks[blk] = (picks[blk][0] + 1 if blk in picks else 1,
                          tuple(int(v) for v in regions[a]))
            if kind[a] == 2:
                crowded.add(blk)

    if len(first[3]):
        add(*first, count, pending)
    while pending:
        todo = sorted(pending)
        blocks = np.array(todo, np.int64).reshape(-1, 3)
        finer = np.maximum(blocks[:, 0] >> _REFINE, 1)
        counted = _count_regions(b, frame, occ, blocks, finer)
        again = {}
        for blk, fs, (cx, cy, cn) in zip(todo, finer.tolist(), counted):
            r = blk[0] // fs
            best = _region_levels(cx, cy, cn, per, top=r.bit_length() - 2)
            inside = (cx // r == blk[1]) & (cy // r == blk[2])
            lift = (_region_levels(cx, cy, cn, held, top=r.bit_length() - 1)[inside]
                    if fs == 1 and (best[inside] < 0).any() else None)
            cand = _candidates(cx[inside], cy[inside], cn[inside], fs, best[inside], lift)
            if len(cand[3]):
                add(*cand, pending[blk], again)
        pending = again
    return picks, crowded


def _draw(s, x, y, n, count, rng):
    """``count`` indices of the blocks (x, y) of ``s`` cells holding ``n`` points each,
    drawn systematically with probabilities proportional to ``n`` (one random start, then
    steps of sum(n) / count along the blocks in Z order): each block drawn n count /
    sum(n) times on average, and the draws spread over space."""
    order = np.argsort(_z_order(x * s, y * s), kind="stable")
    cum = np.cumsum(n[order].astype(float))
    at = (rng.uniform() + np.arange(count)) * (cum[-1] / count)
    return order[np.minimum(np.searchsorted(cum, at, side="right"), len(cum) - 1)]


def _z_order(x, y):
    """The Morton keys of the cells (x, y) (non-negative ints below 2^31)."""
    def spread(v):
        v = v.astype(np.uint64) & np.uint64(0x7FFFFFFF)
        for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF),
                            (4, 0x0F0F0F0F0F0F0F0F), (2, 0x3333333333333333),
                            (1, 0x5555555555555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v
    return spread(np.asarray(x)) | (spread(np.asarray(y)) << np.uint64(1))


def _memberships(c, blocks):
    """(rows, regions): every pair of a row of ``c`` ((N, 2) x-y cells) and a row of
    ``blocks`` ((R, 3) distinct s, x, y) whose region (the block with one block around
    it) holds that cell."""
    rows, regs = [], []
    for s in np.unique(blocks[:, 0]).tolist():
        idx = np.flatnonzero(blocks[:, 0] == s)
        keys = (blocks[idx, 1] << 32) + blocks[idx, 2]
        order = np.argsort(keys)
        keys, idx = keys[order], idx[order]
        a = c // s
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                want = ((a[:, 0] - dx) << 32) + (a[:, 1] - dy)
                at = np.minimum(np.searchsorted(keys, want), len(keys) - 1)
                hit = np.flatnonzero(keys[at] == want)
                rows.append(hit)
                regs.append(idx[at[hit]])
    if not rows:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    return np.concatenate(rows), np.concatenate(regs)


def _fine_keys(occ, blocks):
    """The sorted keys (bx << 32) + by of the blocks of the occupancy ``occ`` (of occ.g
    cells) that share cells with the region of a block of ``blocks`` (s, x, y): a pass
    tests its points' block in these first (one search), and only those against the
    regions."""
    g = occ.g
    keys = []
    big = blocks[blocks[:, 0] >= g]            # their regions are whole blocks of g cells
    if len(big):
        rows, _ = _memberships(np.stack([occ.bx, occ.by], axis=1) * g, big)
        keys.append((occ.bx[rows] << 32) + occ.by[rows])
    for s, x, y in blocks[blocks[:, 0] < g].tolist():   # within a few blocks of g cells
        gx = np.arange((x - 1) * s // g, ((x + 2) * s - 1) // g + 1)
        gy = np.arange((y - 1) * s // g, ((y + 2) * s - 1) // g + 1)
        keys.append(((gx[:, None] << 32) + gy[None, :]).ravel())
    return np.unique(np.concatenate(keys)) if keys else np.empty(0, np.int64)


def _region_points(b, frame, occ, blocks):
    """Yields (positions, cells, regions) of the points of the buckets in the regions of
    ``blocks`` (R, 3): a row per pair of a point and a region that holds it, read a block
    of records at a time from the buckets that may hold them, in bucket order."""
    fine = _fine_keys(occ, blocks)
    if not len(fine):
        return
    o, cell = np.asarray(frame.origin[:2]), frame.cell
    buckets = set()
    for s, x, y in blocks.tolist():
        lo = o + np.array([x - 1, y - 1], float) * s * cell
        hi = o + np.array([x + 2, y + 2], float) * s * cell
        buckets.update(b.overlapping(lo, hi))
    for i, j in sorted(buckets):
        for _, pos in b.blocks(i, j):
            c = frame.cells_xy(pos)
            f = c // occ.g
            want = (f[:, 0] << 32) + f[:, 1]
            at = np.minimum(np.searchsorted(fine, want), len(fine) - 1)
            near = np.flatnonzero(fine[at] == want)
            if len(near):
                rows, regs = _memberships(c[near], blocks)
                if len(rows):
                    yield pos[near[rows]], c[near[rows]], regs


def _count_regions(b, frame, occ, blocks, finer):
    """For each block (s, x, y) of ``blocks``: (bx, by, count) of the occupied blocks of
    ``finer`` cells (its row of that array) in its region, in one pass over the buckets
    (memory: a count for each of the (3 s / finer)^2 finer blocks of each region)."""
    ratio = blocks[:, 0] // finer
    span = 3 * int(ratio.max())                 # finer blocks a side of a region
    base = (blocks[:, 1:] - 1) * ratio[:, None]
    counts = np.zeros(len(blocks) * span * span, np.int64)
    for _, c, regs in _region_points(b, frame, occ, blocks):
        rel = c // finer[regs, None] - base[regs]
        counts += np.bincount((regs * span + rel[:, 0]) * span + rel[:, 1],
                              minlength=len(counts))
    out = []
    for r, grid in enumerate(counts.reshape(len(blocks), span, span)):
        rx, ry = np.nonzero(grid)
        out.append((rx + base[r, 0], ry + base[r, 1], grid[rx, ry]))
    return out


def _gather_regions(b, frame, occ, blocks):
    """The points (float64 x, y, z) of the region of each block (s, x, y) of ``blocks``,
    in one pass over the buckets that may hold them (in bucket order: deterministic)."""
    pos, regs = [], []
    for p, _, r in _region_points(b, frame, occ, blocks):
        pos.append(p)
        regs.append(r)
    if not regs:
        return [np.empty((0, 3)) for _ in blocks]
    pos, regs = np.concatenate(pos), np.concatenate(regs)
    order = np.argsort(regs, kind="stable")
    cuts = np.searchsorted(regs[order], np.arange(len(blocks) + 1))
    return [pos[order[a:e]] for a, e in zip(cuts[:-1], cuts[1:])]


@contextmanager
def tile_session(quiet, scheduler=None):
    """(progress, client) of a tiled CLI run: a tqdm bar of the tiles on stderr, made at
    the first tile's report (none when ``quiet``, and none for a run that turns out to fit
    in memory, which reports no tile) and a Dask client of ``scheduler`` (None without);
    both closed at the end. A scheduler that does not answer within
    clcurv.tiles.workers.CONNECT_TIMEOUT seconds raises clcurv.tiles.workers.SchedulerError (a
    ConnectionError: nothing listening there, or not a Dask scheduler), never a hang."""
    client = None
    if scheduler:
        client = connect(scheduler)
    bars = []
    started = [None]

    def progress(done, total, points):
        if not quiet and not bars:
            bars.append(tqdm(desc="tiles", unit="tile", total=total, file=sys.stderr,
                             leave=True))
        bar = bars[0] if bars else None
        if bar is not None:
            if bar.total != total:
                bar.reset(total=total)
            now = time.perf_counter()
            started[0] = started[0] or now
            rate = points / max(now - started[0], 1e-9) / 1e6 if points else 0.0
            bar.set_postfix_str(f"{points} points, {rate:.2f} M points/s", refresh=False)
            bar.update(done - bar.n)
    try:
        yield progress, client
    finally:
        for bar in bars:
            bar.close()
        if client is not None:
            client.close()
