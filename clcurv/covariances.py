"""Normal-based covariance operators on the device: 2dcov1, 2dcov2, 3dcov (Digne & Morel,
Theorems 1-3). They read the oriented unit normals of the neighbours.

:func:`device_covariances` returns, in input order: ``count``, ``status``, ``eigenvalues``
(descending, count-normalised: weighted covariance / sum of weights), ``k1``, ``k2``
(magnitudes, 1/length, k1 >= k2 >= 0) and unit tangent directions ``dir1``, ``dir2``.
"""
from __future__ import annotations

import time

import numpy as np

from .grid import PAD
from .moments import device_counts
from .program import batches, build, launch

COV_METHODS = {"2dcov1": 1, "2dcov2": 2, "3dcov": 3}


def upload_sorted(cloud, values):
    """Upload per-point ``values`` (N, 3), input order, as three padded SoA buffers in the
    cloud's sorted order and precision."""
    import pyopencl as cl
    out = []
    for d in range(3):
        col = np.zeros(cloud.n + PAD, dtype=cloud.dtype)
        np.take(values[:, d], cloud.grid.order, out=col[:cloud.n])
        out.append(cl.Buffer(cloud.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                             hostbuf=col))
    return out


def weight_buffer(cloud, radius, weights):
    """The density weight buffer, or a placeholder the kernel does not read."""
    return device_counts(cloud, radius)[1] if weights == "density" else cloud.x


def download(cloud, spec):
    """Allocate device outputs from ``spec`` {name: (shape, dtype)}; return (host, buffers)."""
    import pyopencl as cl
    host = {k: np.empty(shape, dtype) for k, (shape, dtype) in spec.items()}
    bufs = {k: cl.Buffer(cloud.device.context, cl.mem_flags.WRITE_ONLY, size=max(v.nbytes, 1))
            for k, v in host.items()}
    return host, bufs


def fetch(cloud, host, bufs):
    import pyopencl as cl
    for k, v in host.items():
        cl.enqueue_copy(cloud.device.queue, v, bufs[k])
    cloud.device.queue.finish()
    return host


def device_covariances(cloud, radius, normals, method, *, weights="uniform"):
    """Run 2dcov1/2dcov2/3dcov with the oriented unit ``normals`` (N, 3), input order."""
    r = cloud.check_radius(radius)
    t0 = time.perf_counter()
    defines = dict(cloud.defines, COV_METHOD=COV_METHODS[method], DENSITY=int(weights == "density"))
    prg = build(cloud.device, "covariances.cl", defines)
    nx, ny, nz = upload_sorted(cloud, normals)
    wbuf = weight_buffer(cloud, r, weights)
    n, ne = cloud.n, 3 if method == "3dcov" else 2
    host, bufs = download(cloud, {"count": (n, np.uint32), "status": (n, np.uint8),
                                  "eigenvalues": ((n, ne), cloud.dtype), "k": ((n, 2), cloud.dtype),
                                  "dir1": ((n, 3), cloud.dtype), "dir2": ((n, 3), cloud.dtype)})
    t1 = time.perf_counter()
    launch(cloud.device, prg.covariance, batches(n, defines), cloud.x, cloud.y, cloud.z, nx, ny, nz, wbuf,
           cloud.cell_of, cloud.ranges, cloud.order, np.uint32(n), cloud.real(r),
           bufs["count"], bufs["status"], bufs["eigenvalues"], bufs["k"], bufs["dir1"], bufs["dir2"])
    cloud.device.queue.finish()
    t2 = time.perf_counter()
    out = fetch(cloud, host, bufs)
    k = out.pop("k")
    out["k1"], out["k2"] = k[:, 0], k[:, 1]
    cloud.timings.update({f"kernel_{method}": t2 - t1, "upload_normals": t1 - t0})
    return out
