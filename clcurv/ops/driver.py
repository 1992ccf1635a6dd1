"""The one host driver: runs any operator kernel of the registry (:mod:`clcurv.ops.registry`)
on a :class:`~clcurv.grid.cloud.DeviceCloud` and brings its records back as input-order arrays.

Every operator kernel has the same arguments (``OPERATOR_ARGS`` in kernels/common.h) and
writes one record per point whose columns its :class:`~clcurv.ops.registry.Kernel` spec
declares, so running an operator is the same recipe for all of them: build with the spec's
defines, upload the reference normals (sorted, device precision), the density weights if
asked for, launch one work-item per VW points, split and fetch the records.

The records go through chunks of sorted points when the device lacks room for all of them
(:meth:`clcurv.grid.cloud.DeviceCloud.plan`): the kernel runs on the sorted points [first,
stop) of each chunk and writes their records at g - first in a chunk-sized buffer, which is
split and scattered on the host by ``order``. With one chunk (the cloud fits) the records
go straight to their input index, as the host wants them. The kernels, and so the results,
are the same either way, bit for bit. That launch loop, :func:`walk_chunks`, also runs the
features kernel (:func:`clcurv.ops.features.run_features`: its layouts and radii, the same
arguments).
"""
from __future__ import annotations

import time

import numpy as np
import pyopencl.cltypes as ct

from clcurv.grid.anchor import cell_normals
from clcurv.grid.cloud import (empty_fields, place_records, record_buffer, record_bytes,
                               upload_sorted)
from clcurv._shared.constants import PAD, RECORD_WIDTH
from clcurv.runtime.memory import buffer as device_buffer
from clcurv.runtime.program import batches, build, launch


def device_counts(cloud, radius):
    """The density weights 1/#N_r(p) (#N_r(p): the point itself included) of every point,
    sorted order, device precision, padded: a device buffer."""
    prg = build(cloud.device, "density.cl", cloud.defines)
    weights = device_buffer(cloud.device, np.dtype(cloud.dtype).itemsize * (cloud.n + PAD))
    launch(cloud.device, prg.count_neighbors, cloud.n, cloud.x, cloud.y, cloud.z, cloud.cell_of,
           cloud.ranges, np.uint32(cloud.n), cloud.ball(radius), weights)
    return weights


#: The neighbour walk skips the rows of the 27-cell block beyond the radius
#: (kernels/neighbors.h, ROW_PRUNE) when the radius is below this fraction of the cell.
#: The test costs more than the rows it skips save unless the ball is small against the
#: cell: the moments kernel at 1M points (sphere, kernels on one cloud, pruned / full, ms,
#: minima of 7 interleaved; Zen 4 EPYC, 2 cores) at 0.1, 0.2, 0.3, 0.5, 0.7 cell: PoCL
#: 41.7/48.5, 48.9/49.7, 54.1/50.5, 59.8/49.7, 70.9/49.2; Intel's runtime 42.1/46.5,
#: 49.4/47.8, 55.0/48.8, 60.8/48.2, 71.0/48.2; Intel's runtime built for AVX2 50.1/63.5,
#: 57.0/64.8, 63.6/65.5, 71.5/64.9, 84.6/65.3 (end to end at 0.7 cell the features,
#: 2dcov1 and MLS2 calls 20-33 ms faster unpruned). Per-point radii (a k-NN radius) prune
#: always (about even there). The sums are the same either way (tests/test_row_pruning.py).
PRUNE_BELOW = 0.25


def row_prune(cloud, r, per_point=False):
    """The ROW_PRUNE build option for a walk at radius ``r`` on ``cloud`` (``per_point``:
    each point's own radius, at most ``r``, which the walk's row test then takes: on,
    since the grid's cell is the largest radius and most balls are smaller)."""
    return int(per_point or r < PRUNE_BELOW * cloud.cell)


def _par(cloud, r, h):
    """The kernels' REAL4 ``par`` = (r, 1 / h^2 or 0, 0, 0)."""
    make = ct.make_double4 if cloud.dtype == np.float64 else ct.make_float4
    return make(r, 0.0 if h is None else 1.0 / (h * h), 0.0, 0.0)


def walk_chunks(cloud, entry, opts, plan, inputs, ranges, r, par, outputs, place):
    """The one launch loop of the kernels that take ``OPERATOR_ARGS`` (kernels/common.h):
    the operators (:func:`run_kernel`) and the features (:func:`clcurv.ops.features.run_features`).
    ``entry`` runs on each chunk [first, stop) of sorted points of ``plan`` (one work-item
    per VW points) with ``inputs`` (nx, ny, nz, the weights or per-point radii, the anchors),
    the cell ``ranges``, the ball of ``r``, ``par`` and ``outputs`` (the record buffer and the
    kernel's further arguments); then ``place(first, stop, chunked)`` takes its records.
    Returns (seconds in the kernel, seconds placing)."""
    chunked = plan.count > 1
    run, fetch = 0.0, 0.0
    for first, stop in plan.ranges():
        t0 = time.perf_counter()
        launch(cloud.device, entry, batches(stop - first, opts), cloud.x, cloud.y, cloud.z,
               *inputs, cloud.cell_of, ranges, cloud.order, np.uint32(cloud.n), cloud.ball(r),
               par, np.uint32(first), np.uint32(stop), np.uint32(chunked), *outputs)
        cloud.device.queue.finish()
        t1 = time.perf_counter()
        place(first, stop, chunked)
        run, fetch = run + t1 - t0, fetch + time.perf_counter() - t1
    return run, fetch


def run_kernel(kernel, cloud, radius, *, normals=None, weights="uniform", h=None,
               fields=None, defines=None, point_r2=None, uncertainty=False):
    """Run the operator kernel ``kernel`` (a :class:`clcurv.ops.registry.Kernel`) on ``cloud``.

    Parameters
    ----------
    kernel : clcurv.ops.registry.Kernel
    cloud : clcurv.grid.cloud.DeviceCloud
    radius : float
        Ball radius (<= the cloud's cell size), in the points' unit.
    normals : (N, 3) array_like, optional
        Reference normals in input order (unit for the kernels that use their values); only
        for kernels whose spec reads normals.
    weights : {'uniform', 'density'}
    h : float, optional
        Gaussian kernel width: neighbours weighted by exp(-|q - p|^2 / h^2) (MLS2).
    fields : iterable of str, optional
        The record fields to bring back (``count`` and ``status`` always are).
    defines : dict, optional
        Extra build options (e.g. ``REFINE_L0=0``).
    point_r2 : pyopencl.Buffer, optional
        Per-point squared radii in the cloud's sorted order (the k-NN radius,
        :mod:`clcurv.ops.knn_radius`): each point's ball (kernels/radius.h); ``radius`` is then
        the largest. Not with ``weights='density'``.
    uncertainty : bool
        Also the kernel's error record (``kernel.errors``: standard errors and roughness,
        kernels/mls2.cl's UNCERTAINTY), from the same walk; its real fields join the
        result under their own names.

    Returns
    -------
    dict of input-order host arrays: real fields as float64 (N,) or (N, w), ``count``
    int64, ``status`` uint8; rows whose status is not 0 hold NaN. Stage times go to
    ``cloud.timings`` (build_<name>, upload_normals, density, anchors (clcurv.grid.anchor, the
    first time on a cloud), kernel_<name>, download).
    """
    r = cloud.check_radius(radius)
    if normals is not None and not kernel.reads_normals:
        raise ValueError(f"the {kernel.name} kernel takes no normals")
    opts = dict(cloud.defines, **kernel.build_defines(),
                ROW_PRUNE=row_prune(cloud, r, point_r2 is not None))
    if point_r2 is not None and weights == "density":
        raise ValueError("per-point radii and density weights exclude each other")
    opts.update(defines or {}, DENSITY=int(weights == "density"), GAUSSIAN=int(h is not None),
                REF_NORMALS=int(normals is not None), POINT_RADIUS=int(point_r2 is not None))
    if uncertainty:
        opts.update(kernel.error_defines())
    keep = set(kernel.layout) if fields is None else set(fields) | {"count", "status"}
    layout = {k: v for k, v in kernel.layout.items() if k in keep}
    elayout = dict(kernel.errors) if uncertainty else None
    item = np.dtype(cloud.dtype).itemsize
    ranges = cloud.with_middles() if opts["ROW_PRUNE"] else cloud.ranges
    what = [w for w, on in (("the reference normals", normals is not None),
                            ("the density weights", weights == "density")) if on]
    per_point = record_bytes(cloud, layout) + (record_bytes(cloud, elayout) if uncertainty else 0)
    plan = cloud.plan(f"kernel_{kernel.name}", per_point,
                      reserve=item * (3 * (normals is not None) + (weights == "density")),
                      widest=RECORD_WIDTH * item, label=", ".join(["the coordinates, the grid"] + what))
    t = [time.perf_counter()]
    prg = build(cloud.device, kernel.file, opts)
    t.append(time.perf_counter())
    nx, ny, nz = upload_sorted(cloud, normals) if normals is not None else (cloud.x,) * 3
    cloud.device.queue.finish()
    t.append(time.perf_counter())
    wbuf = device_counts(cloud, r) if weights == "density" else cloud.x
    wbuf = point_r2 if point_r2 is not None else wbuf
    cloud.device.queue.finish()
    t.append(time.perf_counter())
    anchors = cell_normals(cloud) if opts.get("REFINE_L0") else cloud.x
    rec = record_buffer(cloud, plan.chunk)
    out = empty_fields(layout, cloud.n)
    outputs = (rec,)
    if kernel.errors is not None:       # the error record's argument (unused without it)
        outputs = (rec, record_buffer(cloud, plan.chunk) if uncertainty else rec)
        eout = empty_fields(elayout, cloud.n) if uncertainty else None
    cloud.device.queue.finish()
    t.append(time.perf_counter())

    def place(first, stop, chunked):
        place_records(cloud, rec, layout, out, first, stop, chunked)
        if uncertainty:
            place_records(cloud, outputs[1], elayout, eout, first, stop, chunked)
    run, fetch = walk_chunks(
        cloud, getattr(prg, kernel.entry), opts, plan, (nx, ny, nz, wbuf, anchors), ranges, r,
        _par(cloud, r, h), outputs, place)
    if uncertainty:
        out.update({k: v for k, v in eout.items() if k not in ("count", "status")})
    names = (f"build_{kernel.name}", "upload_normals", "density", "anchors")
    cloud.timings.update({k: b - a for k, a, b in zip(names, t, t[1:])})
    cloud.timings.update({f"kernel_{kernel.name}": run, "download": fetch})
    return out
