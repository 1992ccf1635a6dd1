"""The one host driver: runs any operator kernel of the registry (:mod:`clcurv.operators`)
on a :class:`~clcurv.cloud.DeviceCloud` and brings its records back as input-order arrays.

Every operator kernel has the same arguments (``OPERATOR_ARGS`` in kernels/common.h) and
writes one record per point whose columns its :class:`~clcurv.operators.Kernel` spec
declares, so running an operator is the same recipe for all of them: build with the spec's
defines, upload the reference normals (sorted, device precision), the density weights if
asked for, launch one work-item per VW points, split and fetch the records.
"""
from __future__ import annotations

import time

import numpy as np

from .cloud import fetch_records, record_buffer, upload_sorted
from .program import batches, build, launch


def device_counts(cloud, radius):
    """#N_r(p) (point itself included) in *sorted* order, and the buffer of the density
    weights 1/#N_r(p) (sorted, device precision), both on the device."""
    import pyopencl as cl
    ctx = cloud.device.context
    prg = build(cloud.device, "density.cl", cloud.defines)
    counts = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=4 * cloud.n)
    weights = cl.Buffer(ctx, cl.mem_flags.READ_WRITE,
                        size=np.dtype(cloud.dtype).itemsize * (cloud.n + 16))
    launch(cloud.device, prg.count_neighbors, cloud.n, cloud.x, cloud.y, cloud.z, cloud.cell_of,
           cloud.ranges, np.uint32(cloud.n), cloud.ball(radius), counts, weights)
    return counts, weights


def _par(cloud, r, h):
    """The kernels' REAL4 ``par`` = (r, 1 / h^2 or 0, 0, 0)."""
    import pyopencl.cltypes as ct
    make = ct.make_double4 if cloud.dtype == np.float64 else ct.make_float4
    return make(r, 0.0 if h is None else 1.0 / (h * h), 0.0, 0.0)


def run_kernel(kernel, cloud, radius, *, normals=None, weights="uniform", h=None,
               fields=None, defines=None):
    """Run the operator kernel ``kernel`` (a :class:`clcurv.operators.Kernel`) on ``cloud``.

    Parameters
    ----------
    kernel : clcurv.operators.Kernel
    cloud : clcurv.cloud.DeviceCloud
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

    Returns
    -------
    dict of input-order host arrays: real fields as float64 (N,) or (N, w), ``count``
    int64, ``status`` uint8; rows whose status is not 0 hold NaN. Stage times go to
    ``cloud.timings`` (build_<name>, upload_normals, density, kernel_<name>, download).
    """
    r = cloud.check_radius(radius)
    if normals is not None and not kernel.reads_normals:
        raise ValueError(f"the {kernel.name} kernel takes no normals")
    opts = dict(cloud.defines, **kernel.build_defines())
    opts.update(defines or {}, DENSITY=int(weights == "density"), GAUSSIAN=int(h is not None),
                REF_NORMALS=int(normals is not None))
    t = [time.perf_counter()]
    prg = build(cloud.device, kernel.file, opts)
    t.append(time.perf_counter())
    nx, ny, nz = upload_sorted(cloud, normals) if normals is not None else (cloud.x,) * 3
    cloud.device.queue.finish()
    t.append(time.perf_counter())
    wbuf = device_counts(cloud, r)[1] if weights == "density" else cloud.x
    rec = record_buffer(cloud)
    cloud.device.queue.finish()
    t.append(time.perf_counter())
    launch(cloud.device, getattr(prg, kernel.entry), batches(cloud.n, opts), cloud.x, cloud.y,
           cloud.z, nx, ny, nz, wbuf, cloud.cell_of, cloud.ranges, cloud.order,
           np.uint32(cloud.n), cloud.ball(r), _par(cloud, r, h), rec)
    cloud.device.queue.finish()
    t.append(time.perf_counter())
    keep = set(kernel.layout) if fields is None else set(fields) | {"count", "status"}
    out = fetch_records(cloud, rec, {k: v for k, v in kernel.layout.items() if k in keep})
    t.append(time.perf_counter())
    names = (f"build_{kernel.name}", "upload_normals", "density", f"kernel_{kernel.name}",
             "download")
    cloud.timings.update({k: b - a for k, a, b in zip(names, t, t[1:])})
    return out
