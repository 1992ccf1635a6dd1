"""A point cloud binned once and kept on an OpenCL device.

:class:`DeviceCloud` holds the sorted coordinates, the sparse cell table and the per-cell
neighbour ranges on the device, so several operators can run without re-binning or
re-uploading. Timings of each stage are kept in ``timings`` (seconds).
"""
from __future__ import annotations

import time

import numpy as np

from .constants import PAD, RECORD_WIDTH as RECORD, record_selector
from .device import get_device
from .grid import bin_points
from .program import build, launch, precision_defines
from .validate import as_points, as_radius


class DeviceMemoryError(MemoryError):
    """The cloud does not fit the device's allocation limits."""


class DeviceCloud:
    """Points binned into cells of size ``cell`` (>= every radius used) on ``device``.

    Parameters
    ----------
    points : (N, 3) array_like, any real dtype
        Coordinates; made relative to their grid cell in float64 on the host before the
        cast to ``precision`` (clcurv.grid).
    cell : float
        Cell size, same length unit as the points; operators accept radii <= cell.
    device : None, int or str
        See :func:`clcurv.device.get_device`.
    precision : {'float', 'double'}
        Device arithmetic; 'double' needs cl_khr_fp64.

    A DeviceCloud can be passed to :func:`clcurv.curvature` and :func:`clcurv.normals` in
    place of the points: the cloud is then binned once for several operators (at any radius
    <= ``cell``), on its own device and precision. ``points`` keeps the float64 input.
    """

    def __init__(self, points, cell, *, device=None, precision="float"):
        import pyopencl as cl
        self.points = points = as_points(points)
        self.cell = as_radius(cell)
        self.device = get_device(device)
        self.defines = precision_defines(self.device, precision)
        self.precision = precision
        self.dtype = np.float64 if precision == "double" else np.float32
        self.n = len(points)
        self.timings = {}
        if self.n == 0:
            raise ValueError("DeviceCloud needs at least one point")
        t0 = time.perf_counter()
        self.grid = g = bin_points(points, self.cell, self.dtype)
        t1 = time.perf_counter()
        self.timings["binning"] = t1 - t0
        self._check_memory()
        ctx, q = self.device.context, self.device.queue
        mf = cl.mem_flags
        up = lambda a: cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
        self.y, self.z = up(g.y), up(g.z)
        # x: the host's copy, then two more made by grid.cl:expand_x (neighbors.h)
        m, item = len(g.x), np.dtype(self.dtype).itemsize
        self.x = cl.Buffer(ctx, mf.READ_WRITE, size=3 * m * item)
        cl.enqueue_copy(q, self.x, g.x)
        for a in (1, 2):                           # the pads of the other copies
            cl.enqueue_fill_buffer(q, self.x, self.dtype(0), (a * m + self.n) * item,
                                   (m - self.n) * item)
        self.cell_of = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=g.cell_of)
        self.order = up(g.order.astype(np.uint32))
        keys = up(g.keys)
        cell_start = up(g.cell_start)
        self.ranges = cl.Buffer(ctx, mf.READ_WRITE, size=max(g.ncells, 1) * 9 * 8)
        q.finish()
        t2 = time.perf_counter()
        self.timings["upload"] = t2 - t1
        prg = build(self.device, "grid.cl", self.defines)
        t3 = time.perf_counter()
        self.timings["build"] = t3 - t2
        nx, ny, nz = g.dims
        launch(self.device, prg.cell_ranges, g.ncells, keys, np.uint32(g.ncells), cell_start,
               np.int64(nx), np.int64(ny), np.int64(nz), self.ranges)
        launch(self.device, prg.expand_x, self.n, keys, np.int64(nx), np.uint32(self.n),
               self.real(self.cell), self.x, self.cell_of)
        q.finish()
        self.timings["cell_ranges"] = time.perf_counter() - t3

    def _check_memory(self):
        info = self.device.info
        item = np.dtype(self.dtype).itemsize
        biggest = max(self.grid.ncells * 9 * 8, 3 * self.n * item, RECORD * self.n * item)
        total = (5 * item + 8) * self.n + self.grid.ncells * (9 * 8 + 12) + RECORD * self.n * item
        if biggest > info.max_alloc or total > info.global_mem:
            raise DeviceMemoryError(
                f"{self.n} points need about {total / 2**20:.0f} MiB on {info.name} "
                f"(max single allocation {info.max_alloc / 2**20:.0f} MiB, global memory "
                f"{info.global_mem / 2**20:.0f} MiB); split the cloud into tiles")

    def check_radius(self, radius):
        r = as_radius(radius)
        if r > self.cell * (1 + 1e-12):
            raise ValueError(f"radius {r} exceeds the cell size {self.cell} of this DeviceCloud")
        return r

    def real(self, value):
        return self.dtype(value)

    def ball(self, radius):
        """The kernels' REAL2 geometry (r^2, cell) (neighbors.h)."""
        import pyopencl.cltypes as ct
        make = ct.make_double2 if self.dtype == np.float64 else ct.make_float2
        return make(radius * radius, self.cell)


def upload_sorted(cloud, values):
    """Upload per-point ``values`` (N, 3), input order, as three padded SoA buffers in the
    cloud's sorted order and precision (cast on the host, gathered on the device)."""
    import pyopencl as cl
    rows = np.ascontiguousarray(values, dtype=cloud.dtype)
    ctx, mf = cloud.device.context, cl.mem_flags
    src = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rows)
    size = (cloud.n + PAD) * np.dtype(cloud.dtype).itemsize
    out = [cl.Buffer(ctx, mf.READ_WRITE, size=size) for _ in range(3)]
    prg = build(cloud.device, "gather.cl", cloud.defines)
    launch(cloud.device, prg.gather_sorted, cloud.n + PAD, src, cloud.order, np.uint32(cloud.n),
           *out)
    return out


def record_buffer(cloud):
    """A device buffer for one output record per point."""
    import pyopencl as cl
    size = cloud.n * RECORD * np.dtype(cloud.dtype).itemsize
    return cl.Buffer(cloud.device.context, cl.mem_flags.READ_WRITE, size=max(size, 1))


def _host_array(cloud, buf, shape, dtype, mapped=None):
    """``buf`` on the host: mapped (zero-copy) on a CPU device, copied otherwise (``mapped``
    overrides the choice)."""
    import pyopencl as cl
    q = cloud.device.queue
    if cloud.device.info.kind == "cpu" if mapped is None else mapped:
        arr, ev = cl.enqueue_map_buffer(q, buf, cl.map_flags.READ, 0, shape, dtype)
        ev.wait()
        return arr
    arr = np.empty(shape, dtype)
    cl.enqueue_copy(q, arr, buf)
    return arr


def fetch_records(cloud, rec, layout, mapped=None):
    """The fields of the records ``rec`` (input order) as host arrays.

    ``layout`` maps a name to a record column or a slice of columns, and must name 'count'
    (stored as uint bits) and 'status' (a small integer). Real fields come back as float64
    (N,) or (N, width) arrays, 'count' as int64 and 'status' as uint8. The device splits the
    records into contiguous per-field arrays first (records.cl), so the host only casts.
    """
    import pyopencl as cl
    n, ctx = cloud.n, cloud.device.context
    real = [(k, v) for k, v in layout.items() if k not in ("count", "status")]
    if len(real) > 6:
        raise ValueError("split_records takes at most 6 real fields")
    defines = dict(cloud.defines, NF=len(real), COL_COUNT=record_selector(layout["count"]),
                   COL_STATUS=record_selector(layout["status"]))
    spans = []
    for k, (name, col) in enumerate(real):
        a, b = (col, col + 1) if isinstance(col, int) else (col.start, col.stop)
        defines[f"S{k}"], defines[f"W{k}"] = a, b - a
        spans.append((name, (n,) if isinstance(col, int) else (n, b - a)))
    prg = build(cloud.device, "records.cl", defines)
    flags = cl.mem_flags.WRITE_ONLY
    if cloud.device.info.kind == "cpu":
        flags |= cl.mem_flags.ALLOC_HOST_PTR
    item = np.dtype(cloud.dtype).itemsize
    new = lambda nbytes: cl.Buffer(ctx, flags, size=max(nbytes, 1))
    outs = [new(int(np.prod(shape)) * item) for _, shape in spans]
    outs += [outs[0] if outs else rec] * (6 - len(outs))       # unused placeholders
    count, status = new(4 * n), new(n)
    launch(cloud.device, prg.split_records, n, rec, np.uint32(n), *outs, count, status)
    host = [(name, _host_array(cloud, buf, shape, cloud.dtype, mapped), np.float64)
            for (name, shape), buf in zip(spans, outs)]
    host += [("count", _host_array(cloud, count, (n,), np.uint32, mapped), np.int64),
             ("status", _host_array(cloud, status, (n,), np.uint8, mapped), np.uint8)]
    # the casts (numpy releases the GIL) run on the host's cores while the device is idle
    casts = host_pool().map(lambda h: h[1].astype(h[2]), host)
    return {h[0]: a for h, a in zip(host, casts)}


_POOL = None


def host_pool():
    """A small thread pool for host-side numpy work (checks, conversions) that can run
    beside other host work (numpy releases the GIL)."""
    global _POOL
    if _POOL is None:
        import os
        from concurrent.futures import ThreadPoolExecutor
        _POOL = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1),
                                   thread_name_prefix="clcurv-host")
    return _POOL
