"""Out-of-core operators: a cloud larger than memory in tiles with an exact halo.

    clcurv.curvature_file("survey.laz", "out.laz", 3.0, method="mls2", memory="2GiB")
    clcurv compute survey.laz -o out.laz --radius 3 --memory 2GiB [--tile-size 500]

What a tiled run computes is what the in-memory run (:func:`clcurv.curvature` on the whole
cloud) computes, bit for bit on the same device. How:

* **One frame.** Every tile bins its points in the grid frame of the whole cloud
  (:class:`clcurv.grid.binning.Frame`: the origin at the cloud's minimum corner, cells of the
  radius), so a point's float32 cell-relative coordinates, its cell key and its place
  among the points of its cell are those of the in-memory run; a tile's points are kept in
  input order (global id), as the in-memory run's stable binning keeps them.
* **Tiles are blocks of cells.** A tile is ``size x size`` cells in x and y (all of z), and
  owns the points of its cells: half-open bounds on the global grid, so every point has
  exactly one owner (lidR's chunks are the model; a point on a tile edge belongs to the
  tile whose cell holds it, as in the in-memory binning).
* **An exact halo, in whole cells.** The kernels walk the 27 cells around a point's cell as
  9 runs of consecutive points in a fixed order, several at a time (neighbors.h): the
  floating-point sums are those of the in-memory run only when every one of those cells is
  complete. So a tile reads ``halo`` more cells around its own, ``halo`` = the number of
  neighbourhood passes that feed each other (:func:`halo_cells`): 1 for an operator on the
  points alone, 2 when it reads its neighbours' PCA normals (2dcov1, 2dcov2, 3dcov without
  normals from the file), twice that with density weights (a weight is a neighbour count).
  A distance halo of the radius is not enough: a missing cell two radii away shifts the
  vector lanes of the sums (tests/test_tiled.py shows the difference).
* **Orientation.** Normals from the file, a viewpoint, "up" (or a direction) and no
  orientation are decided point by point, so they are exact in tiles. Hoppe's MST
  propagation (``orient="mst"``, and ``"auto"`` of a signed method on a cloud without
  normals that is not LAS/LAZ) runs per tile with its halo; tiles then agree by votes on
  the points they share and each global component is turned outward by its own vote
  (:mod:`clcurv.tiles.orient`). The result agrees with the in-memory MST on closed shapes
  (tests: a torus and two spheres cut into dozens of tiles, 100% agreement), though not bit
  for bit: a component's propagation tree differs near tile borders.
* **Scale space.** ``scale_space=N`` runs the N MLS1 steps in lock step over tiles
  (:mod:`clcurv.tiles.scale`): bit for bit the in-memory steps, re-binnings included.
* **Features.** :func:`clcurv.features_file` runs the covariance features on this engine
  (:mod:`clcurv.tiles.features`: cells of the largest radius, a halo of one cell).
* **Not tiled:** ``projections`` and the projected positions (refused with a message),
  ascii PLY and the text formats. Input: LAS/LAZ, NPY, binary PLY, or a list of such files
  read as one cloud (a catalog: one output per input file); output: LAS/LAZ (from LAS/LAZ
  input), NPZ, binary PLY. ``radius="auto"`` of the CLI job is estimated from regions
  (:mod:`clcurv.jobs.tiled_job`).

Passes and files. Every pass over the points is a set of tasks (:func:`_execute`: in this
process, or on Dask workers, :mod:`clcurv.tiles.workers`); the client reads only the
files' headers and plans from the tasks' small results. (0) The inputs' content hashes,
for the resume key. (1) The input is cut in parts (:func:`clcurv.io.stream.parts_of`: the
files of a catalog, 4M-point ranges of a LAS/LAZ file), and each part's task reads it and
appends each point, with its global id, to its own on-disk buckets of a coarse 2-D grid
(:mod:`clcurv.tiles.buckets`; files opened per write, so their number is not bounded by
the open-file limit), taking its exact bounds on the way. (1b) Each part's buckets are
split into its share of the tiles' input files: their points and halo, each flagged as
owned or not (the tiles sized from the parts' counts and, where needed, their occupancy
of the cells, counted by a task per part). (2) Each tile reads its files, runs the
operator on a :class:`clcurv.DeviceCloud` in the global frame, and writes its own points'
fields with their global ids to a tile file. (3) The outputs (:mod:`clcurv.tiles.writing`):
a task per catalog file, or per window of whole LAZ chunks of one LAS/LAZ output (pieces
the client joins by byte copies), gathers its points' records from the tiles (every point
checked present once) and writes them in input order (LAS/LAZ: the input's header, scales,
offsets, VLRs and records kept, the fields as extra bytes); NPZ, PLY and MST-oriented
outputs are merged and written by the client, a window of ids at a time; all atomically
(:func:`clcurv.io.atomic_output`). A COPC file skips (1) and (1b): its tiles read their
regions from the octree (:mod:`clcurv.tiles.regions`). The workspace (buckets, tile files,
windows, pieces, the manifest) is a folder the run makes, locks and checks
(:mod:`clcurv.tiles.workspace`, docs/workspace.md): a run interrupted or killed is resumed
by the same command (finished tiles are skipped) only when its inputs' content and options
are the same and every file passes its count and CRC check; the folder is removed at the
end, on bad input and on a full disk.

Memory: peak RSS is about the baseline (interpreter, OpenCL) plus the largest tile (its
core and halo) times :data:`TILE_BYTES_PER_POINT`, whatever the size of the cloud; the
tile size comes from the budget (``memory=``) and the density measured in pass (1).
"""
from __future__ import annotations

import ctypes
import errno
import json
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv import io
from clcurv.api.curvature import curvature
from clcurv.grid.cloud import DeviceCloud
from clcurv.runtime.memory import release_memory
from clcurv.tiles import orient as tiled_orient
from clcurv.tiles import regions
from clcurv.tiles import scale as tiled_scale
from clcurv.tiles import workers as cluster
from clcurv.tiles import workspace as wsp
from clcurv.tiles import writing
from clcurv.tiles.buckets import (BucketTask, Buckets, OccupancyTask, SplitTask,
                                  bucket_grid, bucket_part, merge_sums, occupancy_part,
                                  split_part)
from clcurv.grid.binning import Frame
from clcurv.io import stream
from clcurv.io.copc import UntrustedBounds
from clcurv._shared.constants import TOO_FEW
from clcurv.tiles.results import Windows, partition, tile_dtype
from clcurv.tiles.workers import worker_device
from clcurv.tiles.workspace import load_sealed, tile_file
from clcurv.tiles.planning import (OCCUPANCY_BLOCKS, TILE_BYTES_PER_POINT, Tiling,
                                   TilingError, halo_cells, merge_occupancy, plan_tiles)
from clcurv.ops.registry import OPERATORS
from clcurv._shared.options import OPTIONS, file_orient
from clcurv._shared.validate import device_radius


def worker_budget(budget, workers, client):
    """The budget of one tile: :func:`clcurv.tiles.workers.worker_budget` (a LocalCluster's
    workers share the run's budget; a Dask client's each have it)."""
    if client is None and not workers:
        return budget
    return cluster.worker_budget(budget, workers, client)


# --------------------------------------------------------------------------- the run

@dataclass
class CurvatureParams:
    """What every tile of a curvature run computes (the options of
    :func:`clcurv.curvature_file`, named as the options' declaration names them,
    :data:`clcurv._shared.options.OPTIONS`): its radius, halo, orientation, fields and key."""
    method: str
    radius: float
    weights: str
    orient: object
    viewpoint: object
    kernel: object
    h: object
    device: object
    precision: str
    ignore_normals: bool
    scale_space: int = OPTIONS["scale_space"].default
    quantize: bool = OPTIONS["quantize"].default
    orient_k: int = OPTIONS["orient_k"].default
    uncertainty: bool = OPTIONS["uncertainty"].default
    #: what the tiles compute (clcurv.tiles.features.FeatureParams: "features")
    kind = "curvature"

    def __post_init__(self):
        self.ignore_normals, self.scale_space = bool(self.ignore_normals), int(self.scale_space)
        self.quantize = bool(self.quantize)
        self.uncertainty = bool(self.uncertainty)

    def halo(self, file_normals):
        """Cells of halo of this run's tiles (:func:`halo_cells`)."""
        return halo_cells(self.method, self.weights, file_normals)

    def orientation(self, src, file_normals):
        return _orientation(self, src, file_normals)

    def specs(self, wanted):
        return _wanted_specs(self, wanted)

    def bytes_per_point(self):
        """Peak host bytes per point of a tile (its points with their halo)."""
        return TILE_BYTES_PER_POINT

    def key(self):
        d = dict(self.__dict__)
        d["orient"] = (np.asarray(d["orient"]).tolist()
                       if d["orient"] is not None and not isinstance(d["orient"], str)
                       else d["orient"])
        d["viewpoint"] = None if d["viewpoint"] is None else list(map(float, d["viewpoint"]))
        d["device"] = None if d["device"] is None else str(d["device"])
        return d


def _orientation(params, src, file_normals):
    """The API orient of a tile run, or TilingError for one that needs the whole cloud."""
    op = OPERATORS[params.method]
    how = file_orient(params.orient, io.from_las(src), params.viewpoint, file_normals)
    if isinstance(how, str) and how == "auto":
        if file_normals:
            return "auto"
        if params.viewpoint is not None:
            return "auto"
        if not op.signed:
            return "auto"
        how = "mst"
    return how


def workspace(dst, workdir):
    """The workspace folder of a run writing ``dst`` (a path, or a catalog's list of
    paths): :func:`clcurv.tiles.workspace.folder`."""
    return wsp.folder(dst, workdir)


def _source_key(src, execute=None):
    """The resume key of the input(s): content hashes (each file's by a task of
    ``execute``, when given: on the workers of a Dask run) and point counts."""
    parts = src.parts if isinstance(src, stream.Catalog) else [src]
    hashes = None
    if execute is not None:
        done = dict(execute([wsp.HashTask(k, str(p.path)) for k, p in enumerate(parts)],
                            wsp.hash_task))
        hashes = [done[k] for k in range(len(parts))]
    keys = wsp.source_key([p.path for p in parts], hashes)
    for k, p in zip(keys, parts):
        k["n"] = int(p.n)
    return keys


def curvature_fields(res):
    """The per-point fields of ``res`` (a :class:`~clcurv.api.result.CurvatureResult`) that a
    file holds, name -> (N,) array, named as CloudCompare/MeshLab scalar fields: the
    operator's file fields in the registry's order
    (:meth:`clcurv.ops.registry.Operator.file_fields`; float64, curvatures in 1/length,
    directions as ``dirI_x, _y, _z``), then ``knn_radius`` with a k-NN radius, ``neighbours``
    (int32, #N_r(p), the point itself included) and ``status`` (uint8, 0 ok). The file job
    (:func:`clcurv.jobs.job.result_fields`) and the tiles write these."""
    f = {}
    op = OPERATORS[res.method]
    for name, (attr, col) in op.file_fields(op.has_errors(res)).items():
        a = getattr(res, attr)
        f[name] = a if col is None else a[:, col]
    if np.ndim(res.radius):                  # a k-NN radius, or a selected one: each point's
        name = "selected_radius" if "select" in res.info else "knn_radius"
        f[name] = np.asarray(res.radius, dtype=np.float64)
    f["neighbours"] = res.count.astype(np.int32)
    f["status"] = res.status.astype(np.uint8)
    return f


def _field_specs(method, want_normals, uncertainty=False):
    """(name, width, dtype) of the stored fields, as :func:`curvature_fields` names them."""
    op = OPERATORS[method]
    real = np.float64
    specs = [(name, None, real) for name in op.file_fields(uncertainty)]
    specs += [("neighbours", None, np.int32), ("status", None, np.uint8)]
    if want_normals:
        specs.append(("normals", 3, np.float64))     # as the in-memory run writes them
    return specs


def run(source, dst, params, budget, tile, workdir, fields, progress, say, client=None,
        workers=None):
    """A tiled run of ``params`` (:class:`CurvatureParams`, or
    clcurv.tiles.features.FeatureParams) from the opened ``source`` to ``dst`` (checked: a
    path, or a catalog's list of paths, :func:`check_tiled_outputs`), once the caller chose
    to tile (:mod:`clcurv.jobs.job`, the one place that does): the checks made before any
    point is read (:func:`check_params`, the workspace's folder), then :func:`run_tiles` in
    the workspace of ``dst`` (in ``workdir``), each tile's budget that of a worker
    (:func:`worker_budget`); the summary dict."""
    check_params(params, fields, local=client is None and not workers)
    wsp.check_workdir(workdir)
    budget = worker_budget(budget, workers, client)
    return run_tiles(source, dst, params, budget, tile, workspace(dst, workdir), fields,
                     progress, say, client, workers)


def check_params(params, fields, local=True):
    """Every check of a tiled run's options that can be made before a point is read: the
    field names, the radius for the precision, and the options of the method: the API's
    own checks, run on a small synthetic cloud; on this process's device (a run here: its
    precision and kernels too), else with the NumPy reference (the workers' devices)."""
    params.specs(fields)                                  # unknown field names
    device_radius(params.radius, params.precision)
    if params.kind != "curvature":
        if local:
            worker_device(params.device)
        return
    u = np.random.default_rng(0).normal(size=(64, 3))
    pts = u / np.linalg.norm(u, axis=1)[:, None] * params.radius
    how = params.orient
    if isinstance(how, str) and how == "auto" and params.viewpoint is None:
        how = "up"
    given = isinstance(how, str) and how == "normals"           # the file's, in the run
    where = ({"device": worker_device(params.device)} if local else {"backend": "numpy"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        curvature(pts, params.radius, method=params.method, weights=params.weights,
                  orient=how, viewpoint=params.viewpoint, kernel=params.kernel, h=params.h,
                  precision=params.precision, normals=pts if given else None,
                  uncertainty=params.uncertainty, **where)


def check_tiled_outputs(dsts, source):
    """TilingError unless a tiled run can write every path of ``dsts`` from ``source``."""
    for d in dsts:
        ext = d.suffix.lower()
        if ext not in stream.STREAM_WRITES:
            raise TilingError(f"{d}: a tiled run writes {', '.join(stream.STREAM_WRITES)}")
        if io.is_las(d) and not io.from_las(source):
            raise TilingError(f"{d}: a tiled run writes LAS/LAZ from LAS/LAZ input only (it "
                              "keeps the input's header); write .npz")


def catalog_outputs(source, dst):
    """The output path of every file of a catalog: ``dst`` (an existing folder) / the
    input's name (an NPY input's as .npz, a COPC one's as .laz: the output is a plain LAZ);
    never an input itself."""
    folder = Path(dst)
    if not folder.is_dir():
        raise TilingError(f"{dst}: the output of a catalog (several input files) is an "
                          "existing folder, one output file per input")
    outs = []
    inputs = {Path(p).resolve() for p in source.paths}
    for p in source.paths:
        p = Path(p)
        name = (p.stem + ".npz" if p.suffix.lower() == ".npy"
                else p.name[:-len(".copc.laz")] + ".laz"     # a plain LAZ: not COPC
                if p.name.lower().endswith(".copc.laz") else p.name)
        out = folder / name
        if out.resolve() in inputs:
            raise TilingError(f"{out} would replace the input file of that name: choose "
                              "another output folder")
        outs.append(io.check_output(out))
    if len({o.resolve() for o in outs}) != len(outs):
        raise TilingError("two input files have the same name: their outputs would collide")
    return outs


def _manifest(source, params, budget, tile, wanted, client, workers, execute=None):
    """The resume key: the inputs' content (hashed by the tasks of ``execute``), every
    option that changes a byte of the output (the fields written among them), the code,
    and the device of a local run."""
    device = None
    if client is None and not workers:
        info = worker_device(params.device).info
        device = [info.platform, info.name, info.driver]
    return {"source": _source_key(source, execute), "params": params.key(),
            "fields": sorted(wanted) if wanted else None, "code": wsp.code_key(),
            "tile": None if tile is None else float(tile),
            "budget": budget if tile is None else None, "device": device,
            "dask": bool(client is not None or workers)}


def _prepare(space, want, source, params, budget, say, execute, check_disk=None):
    """Pass (1), or its state from an interrupted run with the same key ``want``
    (``check_disk()`` is called before a fresh pass): each part of the input
    (:func:`clcurv.io.stream.parts_of`) read and filed by a task of ``execute`` (on the
    workers of a Dask run: the client reads no point)."""
    have = space.manifest()
    if have and have.get("key") == want and have.get("buckets"):
        say(f"resuming from {space.path}")
        b = Buckets.from_state(space / "buckets", have["buckets"])
        return b, have, False
    if have is not None or (space / "buckets").exists():
        say(f"{space.path}: left by a run of other inputs or options; starting afresh")
    space.clear()
    if check_disk is not None:
        check_disk()
    (space / "buckets").mkdir()
    target = max(budget // params.bytes_per_point(), 1)
    grid = bucket_grid(source, target)
    tasks = [BucketTask(str(space / "buckets"), k, part, grid)
             for k, part in enumerate(stream.parts_of(source))]
    b = Buckets.merge(space / "buckets", list(execute(tasks, bucket_part)))
    if source.n == 0:
        raise TilingError(f"{source.path}: no points")
    state = {"key": want, "buckets": b.state()}
    space.write_manifest(state)
    return b, state, True


def run_tiles(source, dst, params, budget, tile, ws, wanted, progress, say, client=None,
              workers=None):
    """Passes (1) to (3) of a tiled run of ``params`` (:class:`CurvatureParams`, or
    clcurv.tiles.features.FeatureParams: the tiles' computation, halo, fields and budget per
    point) from ``source`` to ``dst``, in the workspace folder ``ws``
    (:mod:`clcurv.tiles.workspace`: claimed and locked for the run); the summary dict.

    What is left behind: nothing after a success; nothing after bad input or options, or a
    full disk (the same command cannot succeed as it is); the workspace after an
    interruption or any other failure, for the same command to resume. A workspace file
    that fails its check is recomputed: the run starts afresh once."""
    with wsp.claim(ws, dst) as space, cluster.session(client, workers) as dask:
        want = _manifest(source, params, budget, tile, wanted, client, workers,
                         lambda tasks, fn: _execute(tasks, dask, fn))
        try:
            for attempt in (0, 1):
                try:
                    summary = _run_tiles(space, want, source, dst, params, budget, tile,
                                         wanted, progress, say, dask)
                    break
                except wsp.CorruptWorkspace as exc:
                    if attempt:
                        raise wsp.WorkspaceError(
                            f"the workspace {space.path} failed its checks twice ({exc}): "
                            "is another program writing there, or the disk failing?") from exc
                    say(f"{exc}: recomputing from the start")
                    space.clear()
        except Exception as exc:
            if _no_space(exc) and "needs about" in str(exc):
                space.remove()          # the check before the run: says it already
                raise
            if _no_space(exc):
                space.remove()
                raise OSError(errno.ENOSPC, f"no space left on the device of {space.path} "
                              f"or {Path(dst[0] if isinstance(dst, list) else dst).parent}: "
                              f"a tiled run of {source.n} points needs about "
                              f"{_gib(disk_need(source, params, wanted))} GiB of workspace "
                              "besides its output (workdir= puts the workspace on another "
                              "disk)") from exc
            if isinstance(exc, (io.ReadError, ValueError, TilingError)):
                space.remove()      # bad input or options: nothing to resume from
            raise
        space.remove()
    return summary


def _no_space(exc):
    """Is ``exc`` (or what it was raised from) a full disk (ENOSPC, EDQUOT)?"""
    while exc is not None:
        if getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT):
            return True
        exc = exc.__cause__
    return False


def _gib(n):
    return f"{n / 2**30:.2g}"


def disk_need(source, params, wanted):
    """Bytes of workspace a tiled run of ``source`` needs at its peak, about: the buckets
    and the tiles' inputs (the points twice, with a halo), then the tiles' results and
    their windows (the fields twice)."""
    point = 8 + 24 + (24 if source.has_normals else 0)
    fields = 8 + sum(np.dtype(dt).itemsize * (w or 1) for _, w, dt in params.specs(wanted))
    return int(source.n * (point * 2.3 + fields * 2))


def check_disk(space, source, params, wanted, say):
    """OSError (ENOSPC) before the run when the workspace's disk has less room than the run
    needs (:func:`disk_need`); the need said either way."""
    need = disk_need(source, params, wanted)
    free = shutil.disk_usage(space.path).free
    say(f"workspace {space.path}: about {_gib(need)} GiB at its peak ({_gib(free)} GiB free)")
    if free < need:
        raise OSError(errno.ENOSPC, f"{space.path}: a tiled run of {source.n} points needs "
                      f"about {_gib(need)} GiB of workspace, and its disk has {_gib(free)} "
                      "GiB free: free some space, or give workdir= (--workdir) on another "
                      "disk")


def _run_tiles(space, want, source, dst, params, budget, tile, wanted, progress, say,
               client):
    times = {}
    t0 = time.perf_counter()
    ws = space.path
    specs = params.specs(wanted)
    stored = _stored_specs(params, specs)
    if source.n == 0:                   # as the in-memory run: an empty output
        windows = Windows(ws / "windows", 0, tile_dtype(stored))
        writing.write_output(dst, source, windows, specs, _quantize(params))
        return _summary(params, 0, 0, 0, source, times, windows.status, dst)
    def execute(tasks, fn):
        return _execute(tasks, client, fn)
    if regions.applies(source, params):
        try:
            return _run_regions(space, want, source, dst, params, budget, tile, wanted,
                                progress, say, execute, _workers(client))
        except UntrustedBounds as exc:
            say(f"{exc}: reading it as a plain LAZ instead")
            space.clear()
    buckets, state, fresh = _prepare(space, want, source, params, budget, say, execute,
                                     lambda: check_disk(space, source, params, wanted, say))
    times["bucketing"] = time.perf_counter() - t0
    file_normals = (buckets.normals_finite and "n" in buckets.dtype.names
                    and not params.ignore_normals)
    how = params.orientation(source, file_normals)
    halo = params.halo(file_normals)
    smoothed = None
    if params.scale_space:
        t_s = time.perf_counter()
        wsp.remove(ws / "parts")            # an interrupted run's steps: made again
        smoothed = tiled_scale.run_steps(ws, buckets, params, params.scale_space, budget,
                             lambda tasks: execute(tasks, tiled_scale.step_tile),
                             tile=tile)
        times["scale space"] = time.perf_counter() - t_s
        frame = Frame.covering(*smoothed.box, params.radius)
        tiling = plan_tiles(buckets, params.radius, halo, budget, tile, frame=frame)
    else:
        tiling = plan_tiles(buckets, params.radius, halo, budget, tile,
                            bytes_per_point=params.bytes_per_point(),
                            occupy=lambda frame: _occupancy(buckets, frame, execute))
    (ws / "tiles").mkdir(exist_ok=True)
    t_split = time.perf_counter()
    sums = _split(space, buckets, tiling, smoothed, execute)
    times["splitting"] = time.perf_counter() - t_split
    tiles = tiling.occupied(sums)       # never range(tiling.count): see Tiling.occupied
    say(f"{source.n} points in {len(tiles)} tile(s) of {tiling.size} x {tiling.size} "
        f"cells of {tiling.frame.cell:.6g} (halo {halo} cell(s)), budget "
        f"{budget / 2**20:.0f} MiB")
    mst = isinstance(how, str) and how == "mst"
    pieced = writing.writes_pieces(source, dst, mst)
    windows = (writing.piece_windows(source.n, _workers(client)) if pieced else None)
    offsets = tuple(a for a, _ in windows) if pieced else _file_offsets(source)
    todo = [(rank, t) for rank, t in enumerate(tiles) if not _tile_done(ws, t, mst, say)]
    skipped = len(tiles) - len(todo)
    layout = buckets.state([])          # a tile reads its split files, not the buckets
    tasks = [TileTask(str(ws), t, tiling, layout, params, how, file_normals,
                      stored, smoothed, sums.get(str(t)), rank, offsets, source.n)
             for rank, t in todo]
    t1 = time.perf_counter()
    computed, finished = 0, skipped
    info = {}
    for t, owned, about in execute(tasks, compute_tile):
        info[t] = about
        computed += owned
        finished += 1
        _trim()
        if progress is not None:
            progress(finished, len(tiles), computed)
    times["tiles"] = time.perf_counter() - t1
    for t in set(tiles) - set(info):        # a resumed run's tiles, done before
        info[t] = tile_info(load_sealed(tile_file(ws, t)), offsets, params, source.n)
    t2 = time.perf_counter()
    files_of = {t: info[t]["files"] for t in tiles}
    if isinstance(source, stream.Catalog) and not mst:
        status = writing.write_files(ws, source, dst, tiles, files_of, stored, specs,
                                     execute, _quantize(params))
        times["writing"] = time.perf_counter() - t2
        return _finished(params, tiles, skipped, tiling.size, source, times, status, dst,
                         halo, info, specs)
    return _write_one(ws, source, dst, params, tiles, info, windows,
                      stored, specs, execute, mst, times, skipped, tiling.size, halo)


def _write_one(ws, source, dst, params, tiles, info, windows, stored, specs, execute, mst,
               times, skipped, size, halo):
    """Write the one output ``dst`` of a run's ``tiles``: in pieces on the workers
    (``windows`` given: :func:`clcurv.tiles.writing.write_pieces`), else merged
    (:func:`partition`, the orientation's reconciliation with ``mst``) and written by the
    client (NPZ, PLY); then the run's summary dict (:func:`_finished`)."""
    t2 = time.perf_counter()
    if windows is not None:
        status = writing.write_pieces(ws, source, dst, tiles,
                                      {t: info[t]["files"] for t in tiles}, windows, stored,
                                      specs, execute, _quantize(params),
                                      max([info[t]["most"] for t in tiles] + [0]))
        times["writing"] = time.perf_counter() - t2
    else:
        windows = partition(ws, source.n, tiles, stored, mst)
        if mst:
            tiled_orient.reconcile_windows(ws, windows, tiles, params.method)
        _trim()
        times["merging"] = time.perf_counter() - t2
        t3 = time.perf_counter()
        writing.write_output(dst, source, windows, specs, _quantize(params))
        times["writing"] = time.perf_counter() - t3
        status = windows.status
    return _finished(params, tiles, skipped, size, source, times, status, dst, halo, info,
                     specs)


def _finished(params, tiles, skipped, size, source, times, status, dst, halo, info, specs):
    """The summary dict of a run (:func:`_summary`, the values' summary, the fields)."""
    summary = _summary(params, len(tiles), skipped, size, source, times, status, dst, halo)
    summary.update(values_summary([info[t] for t in tiles], params))
    summary["fields"] = [("nx ny nz" if k == "normals" else k)
                         for k, _, _ in sorted(specs, key=lambda s: s[0] != "normals")]
    return summary


def _occupancy(buckets, frame, execute):
    """The points' occupancy of ``frame`` (for planning), each part's counted by a task of
    ``execute`` (at most OCCUPANCY_BLOCKS blocks in all: what the client receives)."""
    limit = max(OCCUPANCY_BLOCKS // len(buckets.parts), 1 << 10)
    tasks = [OccupancyTask(str(buckets.folder), k, buckets.state([k]), frame, limit)
             for k in buckets.parts]
    return merge_occupancy(frame, list(execute(tasks, occupancy_part)))


def _run_regions(space, want, source, dst, params, budget, tile, wanted, progress, say,
                 execute, workers=0):
    """A tiled run of one COPC file whose tiles read their own regions
    (:mod:`clcurv.tiles.regions`): no pass (1) nor (1b); the tiles' results checked
    against the header (UntrustedBounds: the caller starts again through the buckets),
    then written as by :func:`_run_tiles`: a LAS/LAZ output in pieces by the tasks of
    ``execute`` (windows for ``workers`` Dask workers) that the client joins by byte
    copies, an NPZ or PLY output merged and written by the client; the summary dict."""
    times, ws = {}, space.path
    specs = params.specs(wanted)
    stored = _stored_specs(params, specs)
    how, halo = params.orientation(source, False), params.halo(False)
    t0 = time.perf_counter()
    plan = regions.plan(source, params, budget, tile, halo)
    times["planning"] = time.perf_counter() - t0
    state = json.loads(json.dumps({"key": want, "regions": plan.key()}, sort_keys=True))
    if space.manifest() != state:
        space.clear()
        space.write_manifest(state)
    else:
        say(f"resuming from {space.path}")
    (ws / "tiles").mkdir(exist_ok=True)
    tiles, tiling = plan.tiles, plan.tiling
    say(f"{source.n} points in {len(tiles)} tile(s) of {tiling.size} x {tiling.size} "
        f"cells of {tiling.frame.cell:.6g} (halo {halo} cell(s)), read by region from the "
        f"COPC file, budget {budget / 2**20:.0f} MiB")
    pieced = writing.writes_pieces(source, dst, False)
    windows = writing.piece_windows(source.n, workers) if pieced else None
    offsets = tuple(a for a, _ in windows) if pieced else (0,)
    todo = [(rank, t) for rank, t in enumerate(tiles) if not _tile_done(ws, t, False, say)]
    tasks = [TileTask(str(ws), t, tiling, None, params, how, False, stored, rank=rank,
                      offsets=offsets, n=source.n, region=plan.region(t))
             for rank, t in todo]
    t1 = time.perf_counter()
    info, computed = {}, 0
    for t, owned, about in execute(tasks, compute_tile):
        info[t] = about
        computed += owned
        _trim()
        if progress is not None:
            progress(len(tiles) - len(tasks) + len(info), len(tiles), computed)
    times["tiles"] = time.perf_counter() - t1
    for t in set(tiles) - set(info):        # a resumed run's tiles, done before
        info[t] = tile_info(load_sealed(tile_file(ws, t)), offsets, params, source.n)
        info[t]["box"] = load_sealed(regions.box_file(tile_file(ws, t))).tolist()
    regions.check(plan.index, [info[t]["box"] for t in tiles],
                  sum(info[t]["points"] for t in tiles))
    summary = _write_one(ws, source, dst, params, tiles, info, windows,
                         stored, specs, execute, False, times, len(tiles) - len(tasks),
                         tiling.size, halo)
    summary["regions"] = True
    return summary


#: fields that an orientation flip exchanges (clcurv.tiles.orient.flip_fields: MLS2's
#: (k1, k2) -> (-k2, -k1), dir1 <-> dir2): one written, the tiles store both
_FLIP_PAIRS = ([("k1", "k2"), ("k1_se", "k2_se")]
               + [(f"dir1_{c}", f"dir2_{c}") for c in "xyz"])


def _stored_specs(params, specs):
    """The fields the tiles store: those written, the partner of each one that a flip of
    the orientation exchanges with it (:data:`_FLIP_PAIRS`: ``--fields k1`` or ``dir1``
    alone flips as every field does), and a curvature run's status and neighbour count
    always (the summary's counts and the small-radius warning need them)."""
    if params.kind != "curvature":
        return specs
    names = {n for n, _, _ in specs}
    need = {b for pair in _FLIP_PAIRS for a, b in (pair, pair[::-1])
            if a in names and b not in names} | ({"status", "neighbours"} - names)
    return list(specs) + [s for s in _field_specs(params.method, False, params.uncertainty)
                          if s[0] in need]


def _summary(params, tiles, skipped, size, source, times, status, dst, halo=0):
    """The summary dict of a tiled run (``status``: the points by status); warns, as the
    in-memory run does, when most points have too few neighbours."""
    status = np.asarray(status).tolist() if params.kind == "curvature" else None
    if status is not None:
        few, total = status[TOO_FEW], sum(status)
        need = OPERATORS[params.method].min_count
        if few > total // 2:
            warnings.warn(f"{few} of {total} points have fewer than {need} neighbours "
                          f"within radius {params.radius}: their outputs are NaN; the "
                          "radius is probably too small", RuntimeWarning, stacklevel=5)
    return {"tiled": True, "tiles": tiles, "skipped": skipped, "tile_cells": size,
            "halo": halo, "points": source.n, "dropped": int(getattr(source, "dropped", 0)),
            "times": times, "status": status, "dst": dst}


def _tile_done(ws, t, mst, say):
    """Is tile t's result in the workspace and sound (its files pass their checks)? One
    that fails is removed, and computed again."""
    base = tile_file(ws, t)
    paths = [base] + ([base.with_suffix(".halo.npy"), base.with_suffix(".nodes.npy")]
                      if mst else [])
    if not base.exists():
        return False
    if all(wsp.is_sound(p) for p in paths):
        return True
    say(f"{base}: fails its check; computing tile {t} again")
    for p in paths:
        wsp.remove(p)
    return False


def _split(space, buckets, tiling, smoothed, execute):
    """Pass (1b), once per run: the tiles' input files and their sums, each part's by a
    task of ``execute`` (after a scale space, all parts at once here: its state is by
    bucket); a resumed run reuses them when their record of sums, ``tiles_in.json``, is
    sound and of this tiling."""
    record = space / "tiles_in.json"
    key = {"size": tiling.size, "halo": tiling.halo, "count": tiling.count,
           "origin": list(map(float, tiling.frame.origin)), "cell": tiling.frame.cell}
    try:
        have = json.loads(record.read_text())
        if have.get("key") == key and have.get("sum") == wsp.digest(
                json.dumps(have["sums"], sort_keys=True).encode()):
            return have["sums"]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    wsp.remove(record)
    folder = space / "tiles_in"
    wsp.remove(folder)
    if smoothed is not None:
        sums = buckets.split(tiling, folder, state=smoothed)
    else:
        folder.mkdir()
        tasks = [SplitTask(str(buckets.folder), k, buckets.state([k]), tiling, str(folder))
                 for k in buckets.parts]
        sums = {}
        for part in execute(tasks, split_part):
            merge_sums(sums, part)
    wsp.write_text(record, json.dumps({"key": key, "sums": sums, "sum": wsp.digest(
        json.dumps(sums, sort_keys=True).encode())}))
    return sums


def _trim():
    """Give the heap's free pages back to the system (glibc keeps them after a tile's
    large temporaries, and the next pass would run on top of them)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _wanted_specs(params, wanted):
    """The specs of the fields written for the ``fields`` option's value ``wanted`` (None:
    the method's default set; :meth:`clcurv.ops.registry.Operator.chosen_fields`, as the
    run in memory); ValueError for an unknown name."""
    names = OPERATORS[params.method].chosen_fields(wanted, uncertainty=params.uncertainty)
    return [s for s in _field_specs(params.method, "normals" in names, params.uncertainty)
            if s[0] in names]


@dataclass
class TileTask:
    """What a worker needs to compute one tile (small: no arrays; the worker reads the
    buckets from the workspace, on a file system it shares with the client)."""
    ws: str
    t: int
    tiling: Tiling
    buckets: dict
    params: CurvatureParams
    how: object
    file_normals: bool
    specs: list
    smoothed: object = None      # clcurv.tiles.scale.State after a scale space
    expect: object = None        # {file: [count, CRC-32, owned]} of its input files
    rank: int = 0                # its place among the run's tiles (< 2^31: MST node ids)
    offsets: tuple = (0,)        # the first global id of each input file
    n: int = 0                   # the points of the run (its summary's sample)
    region: object = None        # clcurv.io.copc.Region: read from a COPC file, no bucket


def compute_tile(task, device=None):
    """Compute tile ``task.t`` and write its own points' fields (with their global ids) to
    the workspace, atomically; returns (t, points owned, :func:`tile_info`: the input files
    that hold them, their indices in ``task.offsets``, ...; read by region, the owned
    points' box too, ``"box"``). Its points come from its split files, or, with
    ``task.region``, from the COPC file (:func:`clcurv.tiles.regions.read_tile`)."""
    if task.region is not None:
        ids, pos, own = regions.read_tile(task.region, task.tiling, task.t)
        out = tile_records(task, pos, own, ids, None, device)
        box = regions.owned_box(pos, own)       # first: a tile is done when its result is
        wsp.save_sealed(regions.box_file(tile_file(task.ws, task.t)), box)
        wsp.save_sealed(tile_file(task.ws, task.t), out)
        info = tile_info(out, task.offsets, task.params, task.n)
        info["box"] = box.tolist()
        return task.t, len(out), info
    buckets = Buckets.from_state(Path(task.ws) / "buckets", task.buckets)
    rec = buckets.read_tile(Path(task.ws) / "tiles_in", task.t, state=task.smoothed,
                            expect=task.expect)
    pos = rec["p"] if task.smoothed is None or not len(rec) else task.smoothed.key(rec)
    own = rec["own"].astype(bool)
    out = tile_records(task, pos, own, rec["id"], rec["n"] if task.file_normals else None,
                       device)
    wsp.save_sealed(tile_file(task.ws, task.t), out)
    return task.t, len(out), tile_info(out, task.offsets, task.params, task.n)


def tile_records(task, pos, own, ids, file_normals, device=None):
    """The records of tile ``task.t``'s own points: its points ``pos`` (global-id order,
    ``own`` those it owns, ``ids`` their global ids, ``file_normals`` theirs or None) run
    in the global frame (an MST run's records written to the workspace here)."""
    params, tiling = task.params, task.tiling
    mst = isinstance(task.how, str) and task.how == "mst"
    out = np.empty(int(own.sum()), tile_dtype(task.specs, mst))
    if len(out):
        if device is None:
            device = worker_device(params.device)
        cloud = DeviceCloud(pos, params.radius, device=device,
                            precision=params.precision, frame=tiling.frame)
        if params.kind == "features":           # clcurv.tiles.features.FeatureParams
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                f = params.tile_fields(cloud)
        else:
            normals, how = file_normals, task.how
            extra = {}
            if mst:
                nl, node = tiled_orient.orient_tile(cloud, params.radius, params.orient_k,
                                                    task.rank)
                normals = np.where(node[:, None] >= 0, nl, (0.0, 0.0, 1.0))
                how = "normals"
                if "align_normals" in OPERATORS[params.method].options:
                    extra["align_normals"] = True   # clcurv's own normals, as in memory
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)   # per tile; summed at the end
                res = curvature(cloud, params.radius, method=params.method,
                                weights=params.weights, normals=normals, orient=how,
                                viewpoint=params.viewpoint, kernel=params.kernel, h=params.h,
                                uncertainty=params.uncertainty, **extra)
            f = curvature_fields(res)
            f["normals"] = res.normals
        out["id"] = ids[own]
        for name, _, _ in task.specs:
            out[name] = f[name][own]
        del cloud               # its device buffers back to the pool, which lets them go:
        release_memory(device)  # the memory budget sizes tiles as if all were freed
    if mst and len(out):        # the MST records first: a tile is done when its result is
        _mst_records(task, out, own, pos, nl, node, ids)
    elif mst:
        _mst_records(task, out, np.zeros(0, bool), np.empty((0, 3)), np.empty((0, 3)),
                     np.empty(0, np.int64), np.empty(0, np.int64))
    return out


#: points of the sample the summary of a tiled run takes its percentiles from, about
SAMPLE_POINTS = 1 << 15


def _ranged(params):
    """The fields whose ranges a run's summary prints (clcurv.jobs.job.summary_fields)."""
    if params.kind != "curvature":
        return []
    op = OPERATORS[params.method]
    return [o.file for o in op.outputs + (op.errors if params.uncertainty else ())
            if o.file is not None and o.width == 1]


def tile_info(out, offsets, params, n):
    """What the client needs of a tile's records ``out``, small: the input files (or the
    output's windows) that hold its points (their first ids ``offsets``), its largest
    neighbour count (the count type of a LAS output), and for the summary the exact NaN
    counts and neighbour sum, and a systematic sample (the ids that are multiples of
    n / SAMPLE_POINTS) of the summary's fields."""
    step = max(1, int(n) // SAMPLE_POINTS)
    names = [k for k in _ranged(params) + ["neighbours"] if k in out.dtype.names]
    take = out[out["id"] % step == 0]
    return {"files": _files(out["id"], offsets),
            "most": int(out["neighbours"].max()) if "neighbours" in names and len(out) else 0,
            "sample": {k: np.ascontiguousarray(take[k]) for k in names},
            "nan": {k: int(np.count_nonzero(np.isnan(out[k]))) for k in names
                    if out.dtype[k].kind == "f"},
            "neighbours": int(out["neighbours"].sum()) if "neighbours" in names else 0,
            "points": len(out)}


def values_summary(infos, params):
    """The summary's value lines of a tiled run from its tiles' :func:`tile_info`: per
    ranged field (p1, median, p99 of the sample, NaN count), the mean neighbour count (exact)
    and its median (sample), and the sample's size."""
    names = [k for k in _ranged(params) if infos and k in infos[0]["sample"]]
    sample = {k: np.concatenate([np.asarray(i["sample"][k], float) for i in infos])
              for k in names + (["neighbours"] if infos and "neighbours" in
                                infos[0]["sample"] else [])}
    points = sum(i["points"] for i in infos)
    out = {"sample": len(next(iter(sample.values()))) if sample else 0, "ranges": {}}
    for k in names:
        v = sample[k][np.isfinite(sample[k])]
        nan = sum(i["nan"].get(k, 0) for i in infos)
        out["ranges"][k] = (tuple(np.percentile(v, [1, 50, 99]).tolist()) if len(v)
                            else None, nan)
    if "neighbours" in sample and points:
        out["neighbours"] = (sum(i["neighbours"] for i in infos) / points,
                             float(np.median(sample["neighbours"])))
    return out


def _file_offsets(source):
    """The first global id of each input file (a catalog's), as a tuple of ints."""
    if isinstance(source, stream.Catalog):
        return tuple(int(o) for o in source.offsets[:-1])
    return (0,)


def _files(ids, offsets):
    """The indices of the input files (first ids ``offsets``) that hold the ``ids``."""
    if not len(ids):
        return []
    return np.unique(np.searchsorted(np.asarray(offsets), ids, side="right") - 1).tolist()


def _mst_records(task, out, own, pos, nl, node, ids):
    """The MST fields of a tile's own records, its halo records and its node sums."""
    o = np.asarray(task.tiling.frame.origin)
    if len(out):
        out["node"], out["nl"] = node[own], nl[own]
        out["pd"] = np.einsum("ij,ij->i", np.nan_to_num(nl[own]), pos[own] - o)
    halo = ~own & (node >= 0)
    h = np.empty(int(halo.sum()), tiled_orient.HALO_DTYPE)
    h["id"], h["node"], h["nl"] = ids[halo], node[halo], nl[halo]
    base = tile_file(task.ws, task.t)
    for suffix, arr in ((".halo.npy", h), (".nodes.npy", tiled_orient.node_sums(
            pos[own], nl[own], node[own], o) if len(out) else
            np.empty(0, tiled_orient.SUMS_DTYPE))):
        wsp.save_sealed(base.with_suffix(suffix), arr)


def _execute(tasks, client, fn):
    """fn(task) of every task as it finishes (fn: a pass's task, :func:`compute_tile`,
    the scale space's step_tile...): in this process, or on the Dask ``client``."""
    if client is None:
        for task in tasks:
            yield fn(task)
        return
    yield from cluster.map_tiles(fn, tasks, client=client)


def _workers(client):
    """The worker processes of a Dask ``client`` (0 without one)."""
    if client is None:
        return 0
    return len(client.scheduler_info()["workers"])


def _quantize(params):
    """The ``quantize`` of the LAS writers: the run's radius when its fields are written
    quantised (:func:`clcurv.io.las.quantization`), else None."""
    return float(params.radius) if getattr(params, "quantize", False) else None


