"""Tiles on a Dask cluster (optional: ``pip install "clcurv[dask]"``).

    clcurv.curvature_file("survey.laz", "out.laz", 3.0, client=Client("tcp://host:8786"))
    clcurv compute survey.laz -o out.laz --radius 3 --workers 4      # a LocalCluster
    clcurv compute survey.laz -o out.laz --radius 3 --scheduler tcp://host:8786

Tasks carry tile specifications (:class:`clcurv.tiled.TileTask`: a tile number, the grid,
the options), never arrays: each worker reads its tile's points from the workspace's
buckets and writes its fields there, so **the workspace must be on a file system that
every worker sees at the same path** (one machine, or NFS/Lustre/... mounted alike; put it
there with ``workdir=`` / the output's folder). The client writes the output at the end.

Each worker process gets :class:`ClcurvWorker` (a Dask ``WorkerPlugin``) before its first
task: it caps the threads of PoCL, lazrs (rayon) and BLAS to the host's cores divided by
the workers on that host (unless already set in the environment), and picks the OpenCL
device: the one asked for, else, when the host has several GPUs, GPU ``ordinal mod count``
(ordinal: the worker's rank among that host's workers), so each GPU gets its own workers;
one OpenCL context per worker process. At most ``2 x workers`` tiles are in flight; a task
whose worker fails is retried (``RETRIES``) and one whose worker dies is re-run by Dask
elsewhere.
"""
from __future__ import annotations

import os

#: retries of a tile whose task raised (a worker that dies is handled by Dask itself)
RETRIES = 2
#: tiles in flight per worker
IN_FLIGHT = 2
THREAD_VARIABLES = ("POCL_CPU_MAX_CU_COUNT", "POCL_MAX_PTHREAD_COUNT", "RAYON_NUM_THREADS",
                    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _import():
    try:
        import distributed
    except ImportError:
        raise ImportError('running tiles on Dask needs dask.distributed: pip install '
                          '"clcurv[dask]"') from None
    return distributed


def worker_plugin(device=None):
    """A :class:`ClcurvWorker` plugin instance (defined lazily: Dask is optional)."""
    distributed = _import()

    class ClcurvWorker(distributed.WorkerPlugin):
        """Thread caps and the OpenCL device of one worker process (see the module)."""
        name = "clcurv"

        def __init__(self, device=None):
            self.device = device

        def setup(self, worker):
            host = worker.address.rsplit(":", 1)[0]
            peers = sorted(a for a in worker.scheduler_info()["workers"]
                           if a.rsplit(":", 1)[0] == host) if hasattr(
                worker, "scheduler_info") else [worker.address]
            peers = peers or [worker.address]
            ordinal = peers.index(worker.address) if worker.address in peers else 0
            per = max(1, (os.cpu_count() or 1) // len(peers))
            for var in THREAD_VARIABLES:
                os.environ.setdefault(var, str(per))
            worker.clcurv_device = self.device if self.device is not None else \
                _gpu_by_ordinal(ordinal)

    return ClcurvWorker(device)


def _gpu_by_ordinal(ordinal):
    """The device index of GPU ``ordinal mod count`` when this host has several GPUs
    (simulators excluded), else None (the default device)."""
    from .device import devices
    gpus = [d for d in devices() if d.kind == "gpu" and not getattr(d, "simulator", False)]
    return gpus[ordinal % len(gpus)].index if len(gpus) > 1 else None


def local_cluster(workers):
    """A LocalCluster of ``workers`` single-threaded worker processes and its client."""
    distributed = _import()
    cluster = distributed.LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                       processes=True, dashboard_address=None)
    return cluster, distributed.Client(cluster)


def map_tiles(fn, tasks, *, client=None, workers=None, device=None):
    """Yield ``fn(task)`` of every task as it finishes, on ``client`` or on a LocalCluster of
    ``workers`` processes started and closed here; at most IN_FLIGHT tiles per worker are
    submitted at once."""
    distributed = _import()
    cluster = None
    if client is None:
        cluster, client = local_cluster(workers)
    try:
        _register(client, worker_plugin(device))
        nworkers = max(1, len(client.scheduler_info()["workers"]))
        pending = iter(tasks)
        running = distributed.as_completed()

        def submit_next():
            task = next(pending, None)
            if task is not None:
                running.add(client.submit(fn, task, retries=RETRIES, pure=False,
                                          key=f"clcurv-tile-{task.t}-{os.urandom(4).hex()}"))
        for _ in range(IN_FLIGHT * nworkers):
            submit_next()
        for fut in running:
            yield fut.result()
            submit_next()
    finally:
        if cluster is not None:
            client.close()
            cluster.close()


def _register(client, plugin):
    if hasattr(client, "register_plugin"):
        client.register_plugin(plugin, name=plugin.name)
    else:                                               # older distributed
        client.register_worker_plugin(plugin, name=plugin.name)
