"""A point cloud binned once and kept on an OpenCL device.

:class:`DeviceCloud` holds the sorted coordinates, the sparse cell table and the per-cell
neighbour ranges on the device, so several operators can run without re-binning or
re-uploading. Timings of each stage are kept in ``timings`` (seconds).

Device memory: what every point's neighbours read stays whole on the device (coordinates,
grid; per run the reference normals and density weights; the scale space's iterates); what
is per point only (output records, the normals' staging rows, drift) goes through chunks of
points. :meth:`DeviceCloud.plan` sizes the chunks from the device's global memory and max
allocation (queried at every plan, :func:`clcurv.runtime.limits.device_limits`) minus what
the cloud holds, one chunk when everything fits. ``DEVICE_MEMORY`` / ``CLCURV_DEVICE_MEMORY``
(:mod:`clcurv.runtime.limits`) caps the budget.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.cltypes as ct

from clcurv._shared.constants import PAD, RECORD_WIDTH as RECORD, record_selector
from clcurv.runtime.device import get_device
from clcurv._shared.host_threads import host_pool
from clcurv._shared.host_memory import empty as host_empty
from clcurv.runtime.limits import device_limits
from clcurv.runtime.memory import buffer as device_buffer, release_memory
from clcurv.grid.binning import CELLS_PER_ITEM, bin_points, check_pairs, sentinel_keys
from clcurv.runtime.program import build, launch, local_size, precision_defines
from clcurv._shared.validate import as_points, as_radius, device_radius

#: Fewest points of a chunk: a budget that leaves room for fewer is refused.
MIN_CHUNK = 1024
#: Bytes of one row of a cell's 27-cell block (kernels/grid.cl: the index range of the row's
#: points, a uint2), 9 rows per occupied cell, after a header of 8 bytes; as many again for
#: the rows' middle cells once a pruned walk needs them (:meth:`DeviceCloud.with_middles`).
RANGE_BYTES = 8


class DeviceMemoryError(MemoryError):
    """The data that must stay on the device does not fit it (or the DEVICE_MEMORY cap);
    the message says how many points would fit."""


@dataclass(frozen=True)
class Plan:
    """How one stage runs: ``n`` points in chunks of ``chunk`` consecutive points (sorted
    positions; input indices for upload_sorted), the last one partial, ``per_point`` device
    bytes per point of a chunk, while ``held`` bytes stay on the device (the cloud and the
    stage's whole-cloud buffers)."""
    what: str
    n: int
    chunk: int
    per_point: int
    held: int

    @property
    def count(self):
        return -(-self.n // self.chunk)

    def ranges(self):
        """The ranges (first, stop) of the chunks, in order."""
        return [(a, min(a + self.chunk, self.n)) for a in range(0, self.n, self.chunk)]


class DeviceCloud:
    """Points binned into cells of size ``cell`` (>= every radius used) on ``device``.

    Parameters
    ----------
    points : (N, 3) array_like, any real dtype
        Coordinates; made relative to their grid cell in float64 on the host before the
        cast to ``precision`` (clcurv.grid.binning).
    cell : float
        Cell size, same length unit as the points; operators accept radii <= cell.
    device : None, int or str
        See :func:`clcurv.runtime.device.get_device`.
    precision : {'float', 'double'}
        Device arithmetic; 'double' needs cl_khr_fp64.
    frame : clcurv.grid.binning.Frame, optional
        Bin in this frame (of cell size ``cell``) rather than the points' own bounding box:
        a tile binned in the whole cloud's frame, its points in the whole cloud's order,
        gets the same results as the whole cloud's run (clcurv.tiles.engine).

    A DeviceCloud can be passed to :func:`clcurv.curvature` and :func:`clcurv.normals` in
    place of the points: the cloud is then binned once for several operators (at any radius
    <= ``cell``), on its own device and precision. ``points`` keeps the float64 input.

    Device memory: the coordinates, the grid (and per run the reference normals, density
    weights) stay whole on the device; the operators' outputs go through chunks of sorted
    points sized by :meth:`plan` from the device's limits
    (:func:`~clcurv.runtime.limits.device_limits`), so a cloud too big for the device at
    once still runs. :class:`DeviceMemoryError` is raised
    only when the whole-cloud data does not fit; its message says how many points would.
    ``device_bytes`` is what the cloud holds on the device; ``plans`` the last
    :class:`Plan` of every stage run on it.
    """

    def __init__(self, points, cell, *, device=None, precision="float", frame=None,
                 binned=None):
        if binned is not None:                  # host_binning's result: no binning here
            points, cell, precision = binned.points, binned.cell, binned.precision
        # finiteness: checked on the binning's bounding box (grid.bin_points)
        self.points = points = as_points(points, finite=False)
        self.cell = device_radius(as_radius(cell), precision)
        self.device = get_device(device)
        self.defines = precision_defines(self.device, precision)
        self.precision = precision
        self.dtype = np.float64 if precision == "double" else np.float32
        self.n = len(points)
        self.timings = {}
        self.plans = {}
        self.middles = False                # the rows' middle cells: with_middles
        if self.n == 0:
            raise ValueError("DeviceCloud needs at least one point")
        t0 = time.perf_counter()
        if binned is not None:
            self.grid = g = binned.grid
            self.timings["binning"] = binned.seconds
        else:
            self.grid = g = bin_points(points, self.cell, self.dtype, frame)
            check_pairs(g, points, self.cell)   # the walk visits the cells: cell = radius
            self.timings["binning"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        self._check_memory()
        ctx, q = self.device.context, self.device.queue
        mf = cl.mem_flags
        # read-only inputs: a CPU device reads the host's arrays in place (no copy; the
        # Buffer keeps its array alive), other devices get copies
        use = mf.USE_HOST_PTR if self.device.info.kind == "cpu" else mf.COPY_HOST_PTR
        up = lambda a: cl.Buffer(ctx, mf.READ_ONLY | use, hostbuf=a)
        # y, z and the first of x's three copies (neighbors.h) gathered on the device from
        # the input-order rows (gather.cl), the other copies made by grid.cl:expand_x
        m, item = self.n + PAD, np.dtype(self.dtype).itemsize
        self.x = device_buffer(self.device, 3 * m * item)
        self.y, self.z = (device_buffer(self.device, m * item) for _ in range(2))
        for a in (1, 2):                           # the pads of the other copies
            cl.enqueue_fill_buffer(q, self.x, self.dtype(0), (a * m + self.n) * item,
                                   PAD * item)
        rel = up(g.rel)
        self.cell_of = device_buffer(self.device, 4 * self.n)   # by expand_x
        self.order = up(g.order.astype(np.uint32))
        keys = up(sentinel_keys(g.keys))
        # kept: the anchor normals (clcurv.grid.anchor) read the cells' starts too
        self.cell_start = cell_start = up(g.cell_start)
        self.ranges = device_buffer(self.device, 8 + max(g.ncells, 1) * 9 * RANGE_BYTES)
        q.finish()
        t2 = time.perf_counter()
        self.timings["upload"] = t2 - t1
        prg = build(self.device, "grid.cl", self.defines)
        gather = build(self.device, "gather.cl", self.defines).gather_sorted
        t3 = time.perf_counter()
        self.timings["build"] = t3 - t2
        nx, ny, nz = g.dims
        launch(self.device, gather, self.n + PAD, rel, self.order, np.uint32(self.n),
               np.uint32(0), np.uint32(self.n), self.x, self.y, self.z)
        per, items = np.uint32(CELLS_PER_ITEM), -(-g.ncells // CELLS_PER_ITEM)
        self._cell_ranges(keys, False, self.ranges)
        launch(self.device, prg.expand_x, items, keys, np.uint32(g.ncells), cell_start,
               np.int64(nx), per, np.uint32(self.n), self.real(self.cell), self.x,
               self.cell_of)
        q.finish()
        self.timings["cell_ranges"] = time.perf_counter() - t3

    def with_middles(self):
        """The cloud's ranges with the middle cell of every row (kernels/grid.cl), made on
        the first call: a walk with ROW_PRUNE then also leaves out a row's first or last cell
        beyond its ball (kernels/neighbors.h); without them it prunes whole rows only. The
        callers that build a pruned walk call this first (clcurv.ops.driver.row_prune's users,
        clcurv.orient.graph); 72 more bytes per occupied cell on the device."""
        if self.middles:
            return self.ranges
        g = self.grid
        cells = max(g.ncells, 1)
        rows = 9 * RANGE_BYTES * cells
        self._require("the grid's rows and their middle cells", 8 + 2 * rows + 8 * cells, 0,
                      0, 8 + 2 * rows)
        mf = cl.mem_flags
        use = mf.USE_HOST_PTR if self.device.info.kind == "cpu" else mf.COPY_HOST_PTR
        keys = cl.Buffer(self.device.context, mf.READ_ONLY | use,
                         hostbuf=sentinel_keys(g.keys))
        ranges = device_buffer(self.device, 8 + 2 * rows)
        self._cell_ranges(keys, True, ranges)
        self.device.queue.finish()
        self.ranges, self.middles = ranges, True
        self.device_bytes += rows
        return ranges

    def _cell_ranges(self, keys, middles, out):
        """Enqueue grid.cl:cell_ranges: the rows of every cell (and with ``middles`` their
        middle cells) into ``out``; ``keys``: the occupied cells' keys on the device."""
        g = self.grid
        nx, ny, nz = g.dims
        launch(self.device, build(self.device, "grid.cl", self.defines).cell_ranges,
               -(-g.ncells // CELLS_PER_ITEM), keys, np.uint32(g.ncells), self.cell_start,
               np.int64(nx), np.int64(ny), np.int64(nz), np.uint32(CELLS_PER_ITEM),
               np.uint32(middles), out)

    def _check_memory(self):
        """Refuse a cloud whose coordinates and grid, with the binning's temporaries and the
        smallest chunk of an operator, do not fit the device."""
        g, item = self.grid, np.dtype(self.dtype).itemsize
        cells = max(g.ncells, 1)
        # x (3 copies), y, z | cell_of, order | 9 ranges and the start per cell, and once an
        # operator needs them the cells' anchor normals (clcurv.grid.anchor)
        self.device_bytes = (5 * (self.n + PAD) * item + 8 * self.n
                             + (9 * RANGE_BYTES + 4 + 3 * item) * cells)
        # the keys, and the input-order rows gathered to x, y, z (__init__)
        temporary = 8 * cells + 3 * self.n * item
        # and the smallest chunk of the widest operator: a record and as many split fields
        # (record_bytes)
        self._require("the coordinates and the grid", temporary,
                      MIN_CHUNK * (2 * RECORD * item + 5), 0, MIN_CHUNK * RECORD * item)

    def _require(self, what, grows, fixed, reserve, chunk_alloc):
        """Raise DeviceMemoryError unless the cloud, ``reserve`` bytes per point of
        whole-cloud buffers, ``grows`` more bytes that scale with the cloud and ``fixed``
        bytes fit the device, every whole-cloud buffer within the max allocation and a
        chunk buffer of ``chunk_alloc`` bytes too. The message names how many points of
        this cloud's density (cells per point) would fit."""
        lim = device_limits(self.device)
        item = np.dtype(self.dtype).itemsize
        held = self.device_bytes + reserve * (self.n + PAD) + grows
        # the largest whole-cloud buffer: x's 3 copies or the ranges (9 uint2 per cell, 18
        # with the middle cells)
        widest_pp = max(3 * item, (2 if self.middles else 1) * 9 * RANGE_BYTES
                        * max(self.grid.ncells, 1) / self.n)
        widest = widest_pp * (self.n + PAD)
        if held + fixed <= lim.budget and widest <= lim.max_alloc \
                and chunk_alloc <= lim.max_alloc:
            return
        per_point = held / (self.n + PAD)
        fit = min((lim.budget - fixed) / per_point, lim.max_alloc / widest_pp) - PAD
        fit = max(int(fit), 0) if chunk_alloc <= lim.max_alloc else 0
        raise DeviceMemoryError(
            f"{self.n} points do not fit the device: {what} need "
            f"{(held + fixed) / 2**20:.1f} MiB on it at precision {self.precision!r} "
            f"(about {per_point:.0f} bytes per point, largest buffer "
            f"{widest / 2**20:.1f} MiB), but clcurv may use {lim.budget / 2**20:.1f} MiB "
            f"with buffers up to {lim.max_alloc / 2**20:.1f} MiB ({lim.source}). "
            f"About {fit} points of this cloud's density fit: split the cloud into tiles, "
            "or use a larger radius (fewer cells) or a device with more memory")

    def plan(self, what, per_point, *, reserve=0, widest=None, label=None):
        """The :class:`Plan` of stage ``what``: chunks of sorted points of ``per_point``
        device bytes each (``widest`` of them in one buffer; default all), beside the cloud
        and ``reserve`` bytes per point of the stage's whole-cloud buffers (already
        allocated or about to be). One chunk when everything fits; DeviceMemoryError
        (describing the stage as ``label``) when not even MIN_CHUNK points do."""
        lim = device_limits(self.device)
        widest = per_point if widest is None else widest
        held = self.device_bytes + reserve * (self.n + PAD)
        chunk = int(min((lim.budget - held) // per_point, lim.max_alloc // widest, self.n))
        if chunk < self.n:          # short of memory: nothing held for later calls
            release_memory(self.device)
        if chunk < min(self.n, MIN_CHUNK):
            k = min(self.n, MIN_CHUNK)
            self._require(label or what, 0, k * per_point, reserve, k * widest)
        plan = Plan(what, self.n, max(chunk, min(self.n, MIN_CHUNK)), int(per_point), held)
        self.plans[what] = plan
        return plan

    def check_radius(self, radius):
        r = device_radius(as_radius(radius), self.precision)
        if r > self.cell * (1 + 1e-12):
            raise ValueError(f"radius {r} exceeds the cell size {self.cell} of this DeviceCloud")
        return r

    def real(self, value):
        return self.dtype(value)

    def ball(self, radius):
        """The kernels' REAL2 geometry (r^2, cell) (neighbors.h)."""
        make = ct.make_double2 if self.dtype == np.float64 else ct.make_float2
        return make(radius * radius, self.cell)


@dataclass(frozen=True)
class Binned:
    """The host half of a :class:`DeviceCloud`: points binned and checked, no OpenCL call
    (:func:`host_binning`). ``DeviceCloud(None, None, binned=b, device=...)`` uploads it."""
    points: np.ndarray
    cell: float
    precision: str
    grid: object
    seconds: float


def host_binning(points, cell, *, precision="float", frame=None, threads=None, box=None):
    """Bin ``points`` as :class:`DeviceCloud` does, on the host only: safe on a worker
    thread while the main thread drives the device (OpenCL calls stay on one thread; the
    Oclgrind simulator crashes when two threads use one queue). ``threads`` and ``box``: as
    :func:`clcurv.grid.binning.bin_points`."""
    t0 = time.perf_counter()
    points = as_points(points, finite=False)        # checked by bin_points' bounding box
    cell = device_radius(as_radius(cell), precision)
    if len(points) == 0:
        raise ValueError("DeviceCloud needs at least one point")
    dtype = np.float64 if precision == "double" else np.float32
    grid = bin_points(points, cell, dtype, frame, threads, box)
    check_pairs(grid, points, cell)
    return Binned(points, cell, precision, grid, time.perf_counter() - t0)


def upload_sorted(cloud, values):
    """Upload per-point ``values`` (N, 3), input order, as three padded SoA buffers in the
    cloud's sorted order and precision (cast on the host, gathered on the device). The rows
    go through a staging buffer in chunks of input indices when the device lacks room for
    all of them (stage ``upload_normals`` of :meth:`DeviceCloud.plan`)."""
    values = np.asarray(values)
    item = np.dtype(cloud.dtype).itemsize
    plan = cloud.plan("upload_normals", 3 * item, reserve=3 * item,
                      label="the coordinates, the grid and the reference normals")
    q = cloud.device.queue
    size = (cloud.n + PAD) * item
    out = [device_buffer(cloud.device, size) for _ in range(3)]
    prg = build(cloud.device, "gather.cl", cloud.defines)
    staging = device_buffer(cloud.device, plan.chunk * 3 * item)
    for lo, hi in plan.ranges():
        cl.enqueue_copy(q, staging, np.ascontiguousarray(values[lo:hi], dtype=cloud.dtype))
        launch(cloud.device, prg.gather_sorted, cloud.n + PAD, staging, cloud.order,
               np.uint32(cloud.n), np.uint32(lo), np.uint32(hi), *out)
    return out


def record_buffer(cloud, count=None):
    """A device buffer for one output record per point (of ``count`` points; default all)."""
    size = (cloud.n if count is None else count) * RECORD * np.dtype(cloud.dtype).itemsize
    return device_buffer(cloud.device, size)


def record_bytes(cloud, layout):
    """Device bytes per point of a record and its split fields (:func:`split_records`)."""
    item = np.dtype(cloud.dtype).itemsize
    cols = sum(1 if isinstance(v, int) else v.stop - v.start
               for k, v in layout.items() if k not in ("count", "status"))
    return (RECORD + cols) * item + 5


def _host_array(cloud, buf, shape, dtype, mapped=None):
    """``buf`` on the host: mapped (zero-copy) on a CPU device, copied otherwise (``mapped``
    overrides the choice)."""
    q = cloud.device.queue
    if cloud.device.info.kind == "cpu" if mapped is None else mapped:
        arr, ev = cl.enqueue_map_buffer(q, buf, cl.map_flags.READ, 0, shape, dtype)
        ev.wait()
        return arr
    arr = np.empty(shape, dtype)
    cl.enqueue_copy(q, arr, buf)
    return arr


def _fields(layout, n):
    """(name, shape, host dtype) of the fields of ``layout`` for ``n`` points, the real
    fields first (at most 6), then count and status."""
    real = [(k, v) for k, v in layout.items() if k not in ("count", "status")]
    if len(real) > 6:
        raise ValueError("split_records takes at most 6 real fields")
    out = [(k, (n,) if isinstance(v, int) else (n, v.stop - v.start), np.float64)
           for k, v in real]
    return out + [("count", (n,), np.int64), ("status", (n,), np.uint8)]


def _split_program(cloud, layout, real, host, balls=None):
    """records.cl built for ``layout``'s real fields ``real`` (``host``: SPLIT_HOST;
    ``balls``: (NB, REC_BALL, REC_BLOCK), ball REC_BALL's records among those of NB balls
    in blocks of REC_BLOCK points: features.cl's REC_BALLS)."""
    defines = dict(cloud.defines, NF=len(real), COL_COUNT=record_selector(layout["count"]),
                   COL_STATUS=record_selector(layout["status"]), SPLIT_HOST=int(host))
    if balls:
        defines.update(NB=int(balls[0]), REC_BALL=int(balls[1]), REC_BLOCK=int(balls[2]))
    for k, (name, _, _) in enumerate(real):
        col = layout[name]
        a, b = (col, col + 1) if isinstance(col, int) else (col.start, col.stop)
        defines[f"S{k}"], defines[f"W{k}"] = a, b - a
    return build(cloud.device, "records.cl", defines)


def _split_launch(cloud, prg, n, balls, *args):
    """split_records over ``n`` records: 1D, or with ``balls`` (NB, b, block) over
    (block, blocks) work-items, so that x runs along one ball's block of records."""
    if not balls:
        return launch(cloud.device, prg.split_records, n, *args)
    block = int(balls[2])
    ls = min(local_size(cloud.device, prg.split_records), block)
    return prg.split_records(cloud.device.queue, (-(-block // ls) * ls, -(-n // block)),
                             (ls, 1), *args)


def split_records(cloud, rec, layout, n, mapped=None, balls=None):
    """The fields of the first ``n`` records of ``rec`` as host arrays in the device's types
    (REAL, count uint32, status uint8), in the records' order: a list of (name, array). The
    device splits the records into contiguous per-field arrays first (records.cl), so the
    host only casts."""
    fields = _fields(layout, n)
    real = fields[:-2]
    prg = _split_program(cloud, layout, real, False, balls)
    item = np.dtype(cloud.dtype).itemsize
    new = lambda nbytes: device_buffer(cloud.device, nbytes)
    outs = [new(int(np.prod(shape)) * item) for _, shape, _ in real]
    outs += [outs[0] if outs else rec] * (6 - len(outs))       # unused placeholders
    count, status = new(4 * n), new(n)
    _split_launch(cloud, prg, n, balls, rec, np.uint32(n), *outs, count, status)
    host = [(name, _host_array(cloud, buf, shape, cloud.dtype, mapped))
            for (name, shape, _), buf in zip(real, outs)]
    return host + [("count", _host_array(cloud, count, (n,), np.uint32, mapped)),
                   ("status", _host_array(cloud, status, (n,), np.uint8, mapped))]


def empty_fields(layout, n):
    """Host arrays (uninitialised) for the fields of ``layout`` for ``n`` points, in the
    types :func:`place_records` writes (float64, count int64, status uint8); large ones
    from the pool of :mod:`clcurv._shared.host_memory` (the pages of results the caller
    dropped)."""
    return {name: host_empty(shape, dtype) for name, shape, dtype in _fields(layout, n)}


def split_into_host(cloud, rec, layout, out, balls=None):
    """Split the records of every point (``rec``, input order) straight into the host
    arrays ``out`` (:func:`empty_fields`: float64, count int64, status uint8), which the
    device writes in place (USE_HOST_PTR), casting as it goes: one pass instead of the split
    and a cast on the host (6 of the 14 ms of a 1M-point variation call's records on PoCL).
    For CPU devices with cl_khr_fp64 (:func:`splits_into_host`); the same values as
    :func:`split_records` and the host's cast, bit for bit (tests/test_records.py)."""
    fields = _fields(layout, cloud.n)
    real = fields[:-2]
    prg = _split_program(cloud, layout, real, True, balls)
    ctx, q = cloud.device.context, cloud.device.queue
    flags = cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR
    bufs = {name: cl.Buffer(ctx, flags, hostbuf=out[name]) for name, _, _ in fields}
    outs = [bufs[name] for name, _, _ in real]
    outs += [outs[0] if outs else bufs["count"]] * (6 - len(outs))   # unused placeholders
    _split_launch(cloud, prg, cloud.n, balls, rec, np.uint32(cloud.n), *outs,
                  bufs["count"], bufs["status"])
    for name, shape, dtype in fields:       # the host's view is valid once mapped
        view, ev = cl.enqueue_map_buffer(q, bufs[name], cl.map_flags.READ, 0, shape, dtype)
        ev.wait()
        del view
    q.finish()


def splits_into_host(cloud):
    """Does :func:`place_records` split whole-cloud records into the host arrays on the
    device (:func:`split_into_host`)? On CPU devices with cl_khr_fp64."""
    return cloud.device.info.kind == "cpu" and cloud.device.info.fp64


def place_records(cloud, rec, layout, out, first, stop, chunked, mapped=None, balls=None):
    """Split the records of the sorted points [first, stop) in ``rec`` and write them to the
    host arrays ``out`` (:func:`empty_fields`) at their input indices: ``rec`` holds the
    records of every point at its input index (``chunked`` false, then first = 0 and stop =
    N), or those of the chunk at g - first (``chunked``: scattered by ``cloud.grid.order``).
    Whole-cloud records on a CPU device with fp64 go straight into ``out``
    (:func:`split_into_host`) unless ``mapped`` chooses the other ways. ``balls``: (NB, b,
    block), ``rec`` holds NB balls' records, ball b's to split (features.cl: REC_BALLS)."""
    if not chunked and mapped is None and splits_into_host(cloud):
        return split_into_host(cloud, rec, layout, out, balls)
    host = split_records(cloud, rec, layout, stop - first, mapped, balls)
    at = cloud.grid.order[first:stop] if chunked else slice(first, stop)

    def put(h):
        out[h[0]][at] = h[1]          # the cast, and in a chunk the scatter (no GIL held)
    list(host_pool().map(put, host))


def upload_point_r2(cloud, r2_sorted):
    """Per-point squared radii (``cloud``'s sorted order; radius.h's POINT_RADIUS: the k-NN
    radius, the optimal neighbourhood) as a device buffer padded with PAD zeros."""
    host = np.zeros(cloud.n + PAD, cloud.dtype)
    host[:cloud.n] = r2_sorted
    return cl.Buffer(cloud.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                     hostbuf=host)
