"""Moment operators on the device: neighbour counts, PCA normals, eigenvalues, surface
variation (Pauly) and the barycenter shift used by MLS0 and MLS1.

:func:`device_moments` returns the raw per-point quantities in input order; the public
API (:mod:`clcurv.api`) orients normals and turns them into curvatures.
"""
from __future__ import annotations

import time

import numpy as np

from .cloud import fetch_records, record_buffer
from .program import batches, build, launch

# fields of the moments kernel's output record (kernels/moments.cl)
LAYOUT = {"normals": slice(0, 3), "eigenvalues": slice(3, 6), "variation": 6,
          "shift": slice(7, 10), "count": 10, "status": 11}


def _launch(cloud, kernel, *args):
    """Enqueue ``kernel`` over the cloud's points."""
    launch(cloud.device, kernel, cloud.n, *args)


def device_counts(cloud, radius):
    """#N_r(p) (point itself included) in *sorted* order, and the buffer of weights 1/#N_r."""
    import pyopencl as cl
    r = cloud.check_radius(radius)
    ctx = cloud.device.context
    prg = build(cloud.device, "moments.cl", cloud.defines)
    counts = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=4 * cloud.n)
    weights = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=np.dtype(cloud.dtype).itemsize * (cloud.n + 16))
    _launch(cloud, prg.count_neighbors, cloud.x, cloud.y, cloud.z, cloud.cell_of, cloud.ranges,
            np.uint32(cloud.n), cloud.ball(r), counts, weights)
    return counts, weights


def weight_buffer(cloud, radius, weights):
    """The density weight buffer, or a placeholder the kernel does not read."""
    return device_counts(cloud, radius)[1] if weights == "density" else cloud.x


def device_moments(cloud, radius, *, weights="uniform", refine=True, fields=None):
    """Raw moments of N_r(p) for every point, in input order.

    Returns a dict: ``count`` (N,) int64, ``status`` (N,) uint8, ``normals`` (N, 3) unit,
    unoriented, ``eigenvalues`` (N, 3) ascending, of the weighted covariance
    sum w (q - o)(q - o)^T / sum w, ``variation`` (N,), ``shift`` (N, 3) = o - p, computed in
    the cloud's precision and returned as float64; rows with status != 0 are NaN. ``refine`` recomputes lambda0 in a
    second pass (needed for ``variation`` and ``eigenvalues`` in float32). ``fields``, a
    subset of the names, limits what is brought back to the host (``count`` and ``status``
    always are).
    """
    r = cloud.check_radius(radius)
    density = weights == "density"
    t0 = time.perf_counter()
    defines = dict(cloud.defines, DENSITY=int(density), REFINE_L0=int(refine))
    prg = build(cloud.device, "moments.cl", defines)
    q, n = cloud.device.queue, cloud.n
    t1 = time.perf_counter()
    wbuf = device_counts(cloud, r)[1] if density else cloud.x
    rec = record_buffer(cloud)
    # one work-item per VW consecutive points (the eigen decompositions run VW lanes at once)
    launch(cloud.device, prg.moments, batches(n, defines), cloud.x, cloud.y, cloud.z, wbuf,
           cloud.cell_of, cloud.ranges, cloud.order, np.uint32(n), cloud.ball(r), rec)
    q.finish()
    t2 = time.perf_counter()
    keep = set(LAYOUT) if fields is None else set(fields) | {"count", "status"}
    out = fetch_records(cloud, rec, {k: v for k, v in LAYOUT.items() if k in keep})
    t3 = time.perf_counter()
    cloud.timings.update(build_moments=t1 - t0, kernel_moments=t2 - t1, download=t3 - t2)
    return out
