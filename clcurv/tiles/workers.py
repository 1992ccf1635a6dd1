"""Tiles on a Dask cluster (optional: ``pip install "clcurv[dask]"``).

    clcurv.curvature_file("survey.laz", "out.laz", 3.0, client=Client("tcp://host:8786"))
    clcurv compute survey.laz -o out.laz --radius 3 --workers 4      # a LocalCluster
    clcurv compute survey.laz -o out.laz --radius 3 --scheduler tcp://host:8786

Tasks carry tile specifications (:class:`clcurv.tiles.engine.TileTask`: a tile number, the grid,
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

Bounds, so that a run on a shared machine cannot run away:

* **Workers.** ``workers=N`` (``--workers N``) starts at most the cores this process may run
  on (``os.sched_getaffinity``): more are clamped to them, with a warning (each worker holds
  an OpenCL context and a tile; more processes than cores only add memory), unless the
  environment sets ``CLCURV_FORCE_WORKERS=1``.
* **Memory.** :func:`worker_budget` is what each worker's tiles may take of a run's
  budget (``memory=``, ``--memory``): budget / N on a LocalCluster of N workers, as N tiles
  run at once; on a cluster of your own (``client=``, ``--scheduler``) the whole budget,
  which is then each worker process's: give a machine's budget divided by the workers it
  runs.
* **Connection.** :func:`connect` (``--scheduler ADDRESS``) gives up after
  :data:`CONNECT_TIMEOUT` seconds with :class:`SchedulerError` when nothing at ADDRESS
  completes Dask's handshake (nothing listening, or a server that is not a Dask scheduler:
  ``distributed.Client`` alone waits for its handshake forever).
* **No orphans.** The worker processes of a LocalCluster are children of the client's
  process, each watching a pipe from it (distributed's ``AsyncProcess``): they exit at once
  when it dies, even by SIGKILL (the kernel's OOM killer); and they give up on a scheduler
  they lose after :data:`DEATH_TIMEOUT` seconds.
"""
from __future__ import annotations

import asyncio
import os
import threading
import warnings
from contextlib import contextmanager

import numpy as np

from clcurv.runtime.device import devices, get_device

#: retries of a tile whose task raised (a worker that dies is handled by Dask itself)
RETRIES = 2
#: tiles in flight per worker
IN_FLIGHT = 2
THREAD_VARIABLES = ("POCL_CPU_MAX_CU_COUNT", "POCL_MAX_PTHREAD_COUNT", "RAYON_NUM_THREADS",
                    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: seconds to reach a Dask scheduler (:func:`connect`): its TCP connection and handshake
CONNECT_TIMEOUT = 10.0
#: seconds a LocalCluster worker outlives a scheduler it lost (the client's process)
DEATH_TIMEOUT = 10.0
#: the environment variable that lets ``workers`` exceed the usable cores ("1")
FORCE_WORKERS = "CLCURV_FORCE_WORKERS"


class SchedulerError(ConnectionError):
    """No Dask scheduler answered at an address in time (:func:`connect`)."""


def _import():
    try:
        import distributed          # here: Dask is an optional extra (clcurv[dask])
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
            per = max(1, usable_cores() // len(peers))
            for var in THREAD_VARIABLES:
                os.environ.setdefault(var, str(per))
            worker.clcurv_device = self.device if self.device is not None else \
                _gpu_by_ordinal(ordinal)

    return ClcurvWorker(device)


def _gpu_by_ordinal(ordinal):
    """The device index of GPU ``ordinal mod count`` when this host has several GPUs
    (simulators excluded), else None (the default device)."""
    gpus = [d for d in devices() if d.kind == "gpu" and not getattr(d, "simulator", False)]
    return gpus[ordinal % len(gpus)].index if len(gpus) > 1 else None


_DEVICES = {}


def worker_device(spec):
    """The device of this process (one OpenCL context per process): the one the Dask
    worker plugin chose (:class:`ClcurvWorker`), else ``spec``."""
    try:
        from distributed import get_worker          # Dask: optional
        chosen = getattr(get_worker(), "clcurv_device", None)
    except (ImportError, ValueError):
        chosen = None
    key = chosen if chosen is not None else spec
    if key not in _DEVICES:
        _DEVICES[key] = get_device(key)
    return _DEVICES[key]


def usable_cores():
    """The cores this process may run on (its CPU affinity; else the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def bound_workers(workers):
    """The worker processes to start for ``workers``: an int >= 1 (ValueError otherwise),
    at most :func:`usable_cores`; more are clamped to them with a RuntimeWarning, unless
    the environment sets ``CLCURV_FORCE_WORKERS=1``."""
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) \
            or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    cores = usable_cores()
    if workers > cores and os.environ.get(FORCE_WORKERS, "") != "1":
        warnings.warn(f"{workers} workers asked for, but this process may run on "
                      f"{cores} core(s): starting {cores} (set {FORCE_WORKERS}=1 to start "
                      f"{workers})", RuntimeWarning, stacklevel=2)
        return cores
    return int(workers)


def worker_budget(budget, workers=None, client=None):
    """The bytes each worker's tiles may take of a run's ``budget``: budget / N on a
    LocalCluster of ``workers`` (N = :func:`bound_workers`: its N tiles run at once); the
    whole budget in one process, or on a ``client``'s cluster (the budget is then each
    worker process's, see the module docstring)."""
    if client is not None or not workers:
        return int(budget)
    return max(int(budget) // bound_workers(workers), 1)


def local_cluster(workers):
    """A LocalCluster of ``workers`` single-threaded worker processes (at most the usable
    cores, :func:`bound_workers`) and its client. Its workers die with this process."""
    distributed = _import()
    cluster = distributed.LocalCluster(n_workers=bound_workers(workers), threads_per_worker=1,
                                       processes=True, dashboard_address=None,
                                       death_timeout=DEATH_TIMEOUT)
    return cluster, distributed.Client(cluster)


@contextmanager
def session(client=None, workers=None):
    """The Dask client of a run: ``client`` as it is, a LocalCluster of ``workers``
    processes started here for the whole run (all its passes) and closed after it, or
    None (one process)."""
    if client is not None or not workers:
        yield client
        return
    cluster, client = local_cluster(workers)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def connect(address, timeout=None):
    """A Dask client of the scheduler at ``address`` (``--scheduler``), or
    :class:`SchedulerError` after ``timeout`` seconds (default :data:`CONNECT_TIMEOUT`)
    when none answers there: nothing listening, or a server that is not a Dask scheduler
    (``distributed.Client`` bounds the TCP connection by its ``timeout=``, but then waits
    for Dask's handshake forever; a TCP address is probed first, the handshake included)."""
    distributed = _import()
    timeout = CONNECT_TIMEOUT if timeout is None else float(timeout)
    scheme = str(address).split("://", 1)[0] if "://" in str(address) else "tcp"
    if scheme == "tcp":
        _probe(address, timeout)
    try:
        return distributed.Client(address, timeout=timeout)
    except Exception as exc:            # OSError: "Timed out trying to connect", ...
        raise SchedulerError(_unreachable(address, timeout, exc)) from None


def _unreachable(address, timeout, why):
    return (f"no Dask scheduler answered at {address} within {timeout:g} s ({why}): is "
            "the scheduler running there (e.g. `dask scheduler`, tcp://host:8786)?")


def _probe(address, timeout):
    """SchedulerError unless something at ``address`` completes Dask's handshake within
    ``timeout`` seconds (on its own thread and event loop: none of the caller's is used)."""
    from distributed.comm import connect as dask_connect      # Dask: optional
    outcome = []

    async def hello():
        comm = await asyncio.wait_for(dask_connect(address, timeout=timeout), timeout)
        await comm.close()

    def run():
        try:
            asyncio.run(hello())
            outcome.append(None)
        except BaseException as exc:        # noqa: B036 (reported to the caller)
            outcome.append(exc)

    thread = threading.Thread(target=run, name="clcurv-scheduler-probe", daemon=True)
    thread.start()
    thread.join(timeout + 2.0)
    if not outcome:
        raise SchedulerError(_unreachable(address, timeout, "no handshake"))
    if outcome[0] is not None:
        exc = outcome[0]
        why = "no handshake" if isinstance(exc, (asyncio.TimeoutError, TimeoutError)) \
            else " ".join(str(exc).split()) or type(exc).__name__
        raise SchedulerError(_unreachable(address, timeout, why))


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
                key = f"clcurv-{fn.__name__}-{task.t}-{os.urandom(4).hex()}"
                running.add(client.submit(fn, task, retries=RETRIES, pure=False, key=key))
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
