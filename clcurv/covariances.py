"""Normal-based covariance operators on the device: 2dcov1, 2dcov2, 3dcov (Digne & Morel,
Theorems 1-3). They read the oriented unit normals of the neighbours.

:func:`device_covariances` returns, in input order: ``count``, ``status``, ``eigenvalues``
(descending, count-normalised: weighted covariance / sum of weights), ``k1``, ``k2``
(magnitudes, 1/length, k1 >= k2 >= 0) and unit tangent directions ``dir1``, ``dir2``.
"""
from __future__ import annotations

import time

import numpy as np

from .cloud import fetch_records, record_buffer, upload_sorted
from .moments import weight_buffer
from .program import batches, build, launch

COV_METHODS = {"2dcov1": 1, "2dcov2": 2, "3dcov": 3}
# fields of the covariance kernel's output record (kernels/covariances.cl)
LAYOUT = {"k1": 3, "k2": 4, "dir1": slice(5, 8), "dir2": slice(8, 11), "count": 11, "status": 12}


def device_covariances(cloud, radius, normals, method, *, weights="uniform"):
    """Run 2dcov1/2dcov2/3dcov with the oriented unit ``normals`` (N, 3), input order."""
    r = cloud.check_radius(radius)
    t0 = time.perf_counter()
    defines = dict(cloud.defines, COV_METHOD=COV_METHODS[method], DENSITY=int(weights == "density"))
    prg = build(cloud.device, "covariances.cl", defines)
    nx, ny, nz = upload_sorted(cloud, normals)
    wbuf = weight_buffer(cloud, r, weights)
    n, ne = cloud.n, 3 if method == "3dcov" else 2
    rec = record_buffer(cloud)
    t1 = time.perf_counter()
    launch(cloud.device, prg.covariance, batches(n, defines), cloud.x, cloud.y, cloud.z, nx, ny, nz, wbuf,
           cloud.cell_of, cloud.ranges, cloud.order, np.uint32(n), cloud.real(r), cloud.ball(r),
           rec)
    cloud.device.queue.finish()
    t2 = time.perf_counter()
    out = fetch_records(cloud, rec, dict(LAYOUT, eigenvalues=slice(0, ne)))
    cloud.timings.update({f"kernel_{method}": t2 - t1, "upload_normals": t1 - t0})
    return out
