"""A point cloud binned once and kept on an OpenCL device.

:class:`DeviceCloud` holds the sorted coordinates, the sparse cell table and the per-cell
neighbour ranges on the device, so several operators can run without re-binning or
re-uploading. Timings of each stage are kept in ``timings`` (seconds).
"""
from __future__ import annotations

import time

import numpy as np

from .device import get_device
from .grid import PAD, bin_points
from .program import build, launch, precision_defines
from .validate import as_points, as_radius


class DeviceMemoryError(MemoryError):
    """The cloud does not fit the device's allocation limits."""


class DeviceCloud:
    """Points binned into cells of size ``cell`` (>= every radius used) on ``device``.

    Parameters
    ----------
    points : (N, 3) array_like, any real dtype
        Coordinates; centred in float64 on the host before the cast to ``precision``.
    cell : float
        Cell size, same length unit as the points; operators accept radii <= cell.
    device : None, int or str
        See :func:`clcurv.device.get_device`.
    precision : {'float', 'double'}
        Device arithmetic; 'double' needs cl_khr_fp64.
    """

    def __init__(self, points, cell, *, device=None, precision="float"):
        import pyopencl as cl
        points = as_points(points)
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
        self.x, self.y, self.z = up(g.x), up(g.y), up(g.z)
        self.cell_of = up(g.cell_of)
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
        q.finish()
        self.timings["cell_ranges"] = time.perf_counter() - t3

    def _check_memory(self):
        info = self.device.info
        item = np.dtype(self.dtype).itemsize
        biggest = max(self.grid.ncells * 9 * 8, 3 * self.n * item)
        total = (3 * item + 8) * self.n + self.grid.ncells * (9 * 8 + 12) + 6 * self.n * item
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

    def empty(self, shape, dtype=None):
        return np.empty(shape, dtype=dtype or self.dtype)


def upload_sorted(cloud, values):
    """Upload per-point ``values`` (N, 3), input order, as three padded SoA buffers in the
    cloud's sorted order and precision."""
    import pyopencl as cl
    rows = np.take(values, cloud.grid.order, axis=0)      # one contiguous row gather
    out = []
    for d in range(3):
        col = np.zeros(cloud.n + PAD, dtype=cloud.dtype)
        col[:cloud.n] = rows[:, d]
        out.append(cl.Buffer(cloud.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                             hostbuf=col))
    return out


RECORD = 16      # REALs per point of a kernel's output record (kernels/common.h RECORD_WIDTH)


def record_buffer(cloud):
    """A device buffer for one output record per point. On a CPU device it is allocated in
    host-visible memory so that :func:`fetch_records` maps it instead of copying it."""
    import pyopencl as cl
    flags = cl.mem_flags.WRITE_ONLY
    if cloud.device.info.kind == "cpu":
        flags |= cl.mem_flags.ALLOC_HOST_PTR
    size = cloud.n * RECORD * np.dtype(cloud.dtype).itemsize
    return cl.Buffer(cloud.device.context, flags, size=max(size, 1))


def fetch_records(cloud, buf):
    """The (N, RECORD) records of ``buf`` in the cloud's precision: mapped (zero-copy) on a
    CPU device, copied otherwise. Views into it stay valid as long as they are referenced."""
    import pyopencl as cl
    shape = (cloud.n, RECORD)
    if cloud.device.info.kind == "cpu":
        rec, ev = cl.enqueue_map_buffer(cloud.device.queue, buf, cl.map_flags.READ, 0, shape,
                                        cloud.dtype)
        ev.wait()
        return rec
    rec = np.empty(shape, cloud.dtype)
    cl.enqueue_copy(cloud.device.queue, rec, buf)
    return rec


def record_fields(rec, layout):
    """Split records into named views: ``layout`` maps a name to a column or a column slice;
    the names 'count' (uint bits) and 'status' (small integer) are decoded."""
    out = {}
    for name, col in layout.items():
        if name == "count":
            out[name] = rec.view(np.uint32 if rec.dtype == np.float32 else np.uint64)[:, col]
        elif name == "status":
            out[name] = rec[:, col].astype(np.uint8)
        else:
            out[name] = rec[:, col]
    return out
