"""The MLS1 scale space on the device (Digne & Morel, Section 5): N iterations of the MLS1
projection over the whole cloud, neighbourhoods recomputed on the moved points every time.

The cloud stays on the device between iterations (ping-pong buffers). It is binned once
with a cell size h = (1 + 2 MARGIN) r; the candidate cells of a point then contain its
whole ball as long as every point moved less than MARGIN r from where it was binned, which
the device checks at each iteration (a per-block maximum, a few KB downloaded). Only when
the bound is crossed is the cloud brought back and re-binned on the host. The iterates stay
whole on the device; each step runs over chunks of sorted points when the device lacks room
for the drift of all of them (:meth:`clcurv.grid.cloud.DeviceCloud.plan`).
"""
from __future__ import annotations

import time

import numpy as np
import pyopencl as cl

from clcurv.grid.cloud import DeviceCloud
from clcurv._shared.constants import PAD
from clcurv.reference import operators as reference
from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import batches, build, launch
from clcurv._shared.options import check
from clcurv._shared.validate import as_points, as_radius

MARGIN = 0.1        # allowed drift between re-binnings, in units of r
BLOCK = 256         # drift values reduced per work-item


def _buffers(cloud, host_arrays):
    mf = cl.mem_flags
    return [cl.Buffer(cloud.device.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=a)
            for a in host_arrays]


def _copies(cloud, buffers):
    """Device copies of device buffers."""
    out = []
    for b in buffers:
        out.append(device_buffer(cloud.device, b.size))
        cl.enqueue_copy(cloud.device.queue, out[-1], b)
    return out


class DeviceState:
    """One binning of the current positions, with ping-pong and displacement buffers (whole
    cloud, on the device) and the drift of one chunk of sorted points at a time."""

    def __init__(self, base, disp, radius, device, precision, density, frame=None,
                 iterate=None):
        self.cloud = c = DeviceCloud(base + disp, radius * (1 + 2 * MARGIN), device=device,
                                     precision=precision, frame=frame)
        g = c.grid
        item = np.dtype(c.dtype).itemsize
        # ping and pong (x in 3 copies, y, z), the displacement and the density weights
        self.plan = c.plan("scale_space", item + 1,          # drift, and its block maxima
                           reserve=item * (13 + density),
                           label="the coordinates, the grid and the scale space's iterates")
        # c.x, c.y, c.z keep the binned positions B; the iterates live in ping/pong, whose
        # padding is zeroed (vector loads read it, masked, and NaN garbage would leak)
        self.ping = _copies(c, (c.x, c.y, c.z))
        self.pong = _copies(c, (c.x, c.y, c.z))
        d = [np.zeros(g.n + PAD, c.dtype) for _ in range(3)]
        for k in range(3):
            d[k][:g.n] = disp[g.order, k]
        if iterate is not None:             # a tile's state (clcurv.tiles.scale)
            self._load(iterate, d)
        self.disp = _buffers(c, d)
        chunk = self.plan.chunk
        self.drift = device_buffer(c.device, item * chunk)
        self.block_max = device_buffer(c.device, item * -(-chunk // BLOCK))
        self.weights = _buffers(c, [np.zeros(g.n + PAD, c.dtype)])[0] if density else c.x

    def _load(self, iterate, d):
        """Set the iterate from ``iterate`` = (ping (N, 5): x in its 3 alignments, y, z as
        the device holds them, or None for the binned positions; displacement (N, 3)),
        rows in the input order of the cloud; ``d`` gets the displacement."""
        c, g = self.cloud, self.cloud.grid
        ping, disp = iterate
        for k in range(3):
            d[k][:g.n] = disp[g.order, k]
        if ping is None:
            return
        m = g.n + PAD
        x = np.zeros(3 * m, c.dtype)
        for a in range(3):
            x[a * m:a * m + g.n] = ping[g.order, a]
        cols = [x] + [np.zeros(m, c.dtype) for _ in range(2)]
        cols[1][:g.n], cols[2][:g.n] = ping[g.order, 3], ping[g.order, 4]
        for buf, host in zip(self.ping, cols):
            cl.enqueue_copy(c.device.queue, buf, host)

    def iterate(self):
        """(ping (N, 5), displacement (N, 3)) of the current iterate in the device's
        precision, input order: what :meth:`_load` takes back (clcurv.tiles.scale)."""
        c, g = self.cloud, self.cloud.grid
        q, m = c.device.queue, g.n + PAD
        x = np.empty(3 * m, c.dtype)
        cl.enqueue_copy(q, x, self.ping[0])
        ping = np.empty((g.n, 5), c.dtype)
        for a in range(3):
            ping[g.order, a] = x[a * m:a * m + g.n]
        for k, buf in ((3, self.ping[1]), (4, self.ping[2])):
            col = np.empty(m, c.dtype)
            cl.enqueue_copy(q, col, buf)
            ping[g.order, k] = col[:g.n]
        disp = np.empty((g.n, 3), c.dtype)
        for k in range(3):
            col = np.empty(m, c.dtype)
            cl.enqueue_copy(q, col, self.disp[k])
            disp[g.order, k] = col[:g.n]
        return ping, disp

    def displacement(self):
        """Accumulated displacement from the input, (N, 3) float64 in input order."""
        c = self.cloud
        out = np.empty((c.n, 3))
        for k in range(3):
            col = np.empty(c.n + PAD, c.dtype)
            cl.enqueue_copy(c.device.queue, col, self.disp[k])
            out[c.grid.order, k] = col[:c.n]
        return out

    def step(self, radius, density, drifts=None):
        """One MLS1 iteration; returns the largest drift from the binned positions
        (``drifts``, an (N,) array, also gets every point's, input order)."""
        c = self.cloud
        n, r2 = np.uint32(c.n), c.ball(radius)
        defines = dict(c.defines, DENSITY=int(density), GAUSSIAN=0)
        if density:
            m = build(c.device, "density.cl", c.defines)
            launch(c.device, m.count_neighbors, c.n, *self.ping, c.cell_of, c.ranges, n, r2,
                   self.weights)
        prg = build(c.device, "scale_space.cl", defines)
        drift = 0.0
        for first, stop in self.plan.ranges():
            k, nblocks = stop - first, -(-(stop - first) // BLOCK)
            launch(c.device, prg.mls1_step, batches(k, defines), *self.ping, self.weights,
                   c.cell_of, c.ranges, n, r2, c.x, c.y, c.z, *self.pong, *self.disp,
                   np.uint32(first), np.uint32(stop), self.drift)
            launch(c.device, prg.block_max, nblocks, self.drift, np.uint32(k), np.uint32(BLOCK),
                   self.block_max, np.uint32(nblocks))
            bm = np.empty(nblocks, c.dtype)
            cl.enqueue_copy(c.device.queue, bm, self.block_max)
            drift = max(drift, float(bm.max()))
            if drifts is not None:
                each = np.empty(k, c.dtype)
                cl.enqueue_copy(c.device.queue, each, self.drift)
                drifts[c.grid.order[first:stop]] = each
        self.ping, self.pong = self.pong, self.ping
        return drift


def scale_space(points, radius, steps, *, weights="uniform", return_iterates=False,
                return_stats=False, device=None, precision="float", backend="opencl",
                progress=None):
    """MLS1 scale space: ``steps`` MLS1 projections of the whole cloud at ``radius``.

    Each iteration moves every point p to p' = p - <p - o, v0> v0 (o the weighted barycenter
    of its ball N_r(p) = {q : |q - p| < r}, v0 the PCA normal), all points together, the
    neighbourhoods recomputed on the moved cloud. This is a discrete mean curvature motion:
    one step moves a point by about H r^2 / 4 along the inward normal of a convex shape;
    N steps at r act roughly like one at sqrt(N) r. Points with fewer than 3 neighbours
    or a degenerate ball stay where they are for that step.

    Parameters
    ----------
    points : (N, 3) array_like
    radius : float, same length unit as the points
    steps : int >= 0
    weights : {'uniform', 'density'}
    return_iterates : bool
        Return every iterate (a list of steps + 1 arrays, the input first) instead of the
        last.
    return_stats : bool
        Also return a dict of statistics of the device run: ``rebins`` (re-binnings on the
        host because a point drifted more than MARGIN r), ``binning`` and ``steps``
        (seconds), ``plan`` (the :class:`clcurv.grid.cloud.Plan` of the steps: chunks of points
        when the device lacks room for the whole cloud's drift at once); empty for the
        NumPy backend.
    backend : {'opencl', 'numpy'}
        'numpy' runs the float64 reference (clcurv.reference.operators.scale_space).
    progress : callable, optional
        Called with no argument after each step (e.g. a tqdm bar's ``update``).

    Returns
    -------
    (N, 3) float64 smoothed points in input order (or the list of iterates), and the
    stats dict when ``return_stats``.
    """
    pts = as_points(points)
    r = as_radius(radius)
    weights = check(weights, "weights")
    check(backend, "backend")
    steps = int(steps)
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    stats = {}
    done = (lambda out: (out, stats)) if return_stats else (lambda out: out)
    if backend == "numpy":
        its = reference.scale_space(pts, r, steps, weights=weights)
        return done(its if return_iterates else its[-1])
    iterates = [pts.copy()]
    if len(pts) == 0 or steps == 0:
        return done(iterates if return_iterates else pts.copy())
    disp = np.zeros_like(pts)
    density = weights == "density"
    state = DeviceState(pts, disp, r, device, precision, density)
    stats.update(rebins=0, binning=state.cloud.timings["binning"], steps=0.0, plan=state.plan)
    for it in range(steps):
        t = time.perf_counter()
        drift = state.step(r, density)
        stats["steps"] += time.perf_counter() - t
        if progress is not None:
            progress()
        last = it == steps - 1
        if return_iterates or last or drift > MARGIN * r:
            disp = state.displacement()
            if return_iterates:
                iterates.append(pts + disp)
        if not last and drift > MARGIN * r:
            state = None                    # its device memory goes before the next binning
            state = DeviceState(pts, disp, r, device, precision, density)
            stats["rebins"] += 1
            stats["plan"] = state.plan
            stats["binning"] += state.cloud.timings["binning"]
    return done(iterates if return_iterates else pts + disp)
