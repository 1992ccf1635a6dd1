"""MLS2 on the device (Digne & Morel operator 7): weighted quadric regression in the PCA
frame, giving the projected point, signed principal curvatures k1 >= k2 and directions.

:func:`device_mls2` returns, in input order: ``count``, ``status``, ``shift`` (projection -
p), ``k1``, ``k2`` (signed, 1/length; outward normals, sphere positive), unit ``dir1``,
``dir2`` and the fitted unit ``normals``.
"""
from __future__ import annotations

import time

import numpy as np

from .cloud import fetch_records, record_buffer, upload_sorted
from .moments import weight_buffer
from .program import batches, build, launch

KERNELS = ("ball", "gaussian")
# fields of the MLS2 kernel's output record (kernels/mls2.cl)
LAYOUT = {"shift": slice(0, 3), "k1": 3, "k2": 4, "dir1": slice(5, 8), "dir2": slice(8, 11),
          "normals": slice(11, 14), "count": 14, "status": 15}


def device_mls2(cloud, radius, reference_normals=None, *, weights="uniform", kernel="ball", h=None):
    """MLS2 at ``radius``. ``reference_normals`` (N, 3), input order, orient the PCA normal of
    each point (the fit's height axis); without them the sign of v0 is the solver's.
    ``kernel='gaussian'`` weights neighbours by exp(-|q - p|^2 / h^2), h = radius / 2 by
    default, on top of the density weights."""
    r = cloud.check_radius(radius)
    h = r / 2 if h is None else float(h)
    if not h > 0:
        raise ValueError(f"h must be positive, got {h}")
    t0 = time.perf_counter()
    defines = dict(cloud.defines, DENSITY=int(weights == "density"),
                   GAUSSIAN=int(kernel == "gaussian"))
    prg = build(cloud.device, "mls2.cl", defines)
    use_ref = reference_normals is not None
    nx, ny, nz = upload_sorted(cloud, reference_normals) if use_ref else (cloud.x,) * 3
    wbuf = weight_buffer(cloud, r, weights)
    n = cloud.n
    rec = record_buffer(cloud)
    t1 = time.perf_counter()
    launch(cloud.device, prg.mls2, batches(n, defines), cloud.x, cloud.y, cloud.z, nx, ny, nz, wbuf, cloud.cell_of,
           cloud.ranges, cloud.order, np.uint32(n), cloud.real(r), cloud.ball(r),
           cloud.real(1.0 / (h * h)),
           np.int32(use_ref), rec)
    cloud.device.queue.finish()
    t2 = time.perf_counter()
    out = fetch_records(cloud, rec, LAYOUT)
    cloud.timings.update(kernel_mls2=t2 - t1, upload_normals=t1 - t0)
    return out
