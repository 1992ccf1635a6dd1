"""The runs from files to files, and the one place that decides whether a run is made in
memory or in tiles (:func:`in_tiles`); the tiles (:mod:`clcurv.tiles`) never decide, and
never call back here.

* :class:`Job` and :func:`run`, the file job behind ``clcurv compute`` and ``clcurv demo``:
  read a cloud, pick the radius, smooth it by the MLS1 scale space, run one operator, write
  the fields, print a summary; in tiles (:func:`run_tiled`) when :func:`wants_tiles` says.
* :func:`curvature_file` and :func:`features_file` (``clcurv.curvature_file``,
  ``clcurv.features_file``, ``clcurv features``): an operator or the covariance features of
  a file, in memory when the cloud fits the memory budget, else in tiles.

    from clcurv.jobs.job import Job, run
    done = run(Job("in.ply", "out.ply", method="mls2", scale_space=3))
    done.result.mean                        # (N,) float64, 1/length

Units and conventions are those of :mod:`clcurv.ops.registry`: radius and positions in the
file's length unit, curvatures in 1/length (Gaussian curvature in 1/length^2), outward
normals, a sphere of radius R has H = k1 = k2 = +1/R. Output fields are named as
CloudCompare/MeshLab scalar fields (:func:`result_fields`). The input order of the points
is kept in every file written.

Bad option values raise :class:`UsageError` (the command's exit code 2); the other errors
(:mod:`clcurv.io` errors, ``NoDeviceError``, ``ValueError`` of the API) propagate.
"""
from __future__ import annotations

import inspect
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from clcurv import io
from clcurv.api.curvature import curvature
from clcurv.api.features import DEFAULT_FEATURES, canonical_names
from clcurv.api.inputs import as_radii, check_method
from clcurv.api.features import features as compute_features
from clcurv.api.result import CurvatureResult
from clcurv.io import stream, vpc
from clcurv.jobs.tiled_job import auto_radius_tiled, tile_session
from clcurv.ops.registry import OPERATORS
from clcurv.ops.smoothing import scale_space
from clcurv.runtime.device import get_device
from clcurv.tiles import engine as tiled
from clcurv.tiles.engine import CurvatureParams, curvature_fields
from clcurv.tiles.features import FeatureParams, file_fields
from clcurv.tiles.planning import (UNCERTAINTY_BYTES, TilingError, budget_of, fit_budget,
                                   check_tile_size, fits_memory)
from clcurv._shared.options import (METHOD_OPTIONS, OPTIONS, check, cli_value, file_orient,
                                    given, job_default)
from clcurv._shared.validate import as_radius

__all__ = ["Job", "Done", "UsageError", "run", "auto_radius", "result_fields",
           "curvature_file", "features_file"]

#: neighbours aimed at by ``radius="auto"``
AUTO_NEIGHBOURS = 30


class UsageError(Exception):
    """A bad option value (the command's exit code 2)."""


@dataclass
class Job:
    """One file job; the fields are the options of ``clcurv compute``, their defaults the
    file job's of the options' declaration (:data:`clcurv._shared.options.OPTIONS`).

    ``radius``: the ball radius in the file's length unit, or ``"auto"`` (about 30
    neighbours, :func:`auto_radius`). ``scale_space``: MLS1 scale-space steps at that
    radius before the operator. ``kernel``, ``h`` (length unit) and ``projections``: the
    options of the methods that take them (MLS2). ``fields``: the fields to write
    (``"normals"`` and the names of :func:`result_fields`, ``"all"``; None: the method's
    default set, :func:`chosen_fields`). ``quantize``: LAS/LAZ output, the real fields as
    quantised extra bytes (:func:`clcurv.io.las.quantization`). ``positions``:
    write the ``"original"`` positions or the ``"projected"`` ones (the operator's
    projection, else the smoothed cloud). ``k``: instead of ``radius``, each point's radius
    is the distance to its k-th nearest point (:mod:`clcurv.ops.knn_radius`; in memory only).
    ``uncertainty``: also the standard errors and roughness (:func:`clcurv.curvature`'s
    ``uncertainty``), written by default. ``select="error"``: ``radius`` is several radii
    (a list, or numbers separated by commas) and each point keeps the one of least
    predicted error (:func:`clcurv.curvature`'s ``select``; in memory only), written as
    ``selected_radius`` with the standard errors.
    """
    input: str | Path
    output: str | Path
    method: str = job_default("method")
    radius: float | str = job_default("radius")
    scale_space: int = job_default("scale_space")
    weights: str = job_default("weights")
    kernel: str | None = job_default("kernel")
    h: float | None = job_default("h")
    projections: int = job_default("projections")
    device: int | str | None = job_default("device")
    precision: str = job_default("precision")
    fields: Sequence[str] | None = job_default("fields")
    quantize: bool = job_default("quantize")
    viewpoint: Sequence[float] | None = job_default("viewpoint")
    orient: str = job_default("orient")
    positions: str = job_default("positions")
    ignore_normals: bool = job_default("ignore_normals")
    quiet: bool = job_default("quiet")
    memory: str | int | None = job_default("memory")
    tile_size: float | None = job_default("tile_size")
    workers: int | None = job_default("workers")
    scheduler: str | None = job_default("scheduler")
    workdir: str | Path | None = job_default("workdir")
    k: int | None = job_default("k")
    uncertainty: bool = job_default("uncertainty")
    select: str | None = job_default("select")

    @classmethod
    def from_args(cls, args):
        """The job of an ``argparse.Namespace`` with the same attribute names."""
        kw = {f.name: getattr(args, f.name) for f in fields(cls) if hasattr(args, f.name)}
        if isinstance(kw.get("input"), list) and len(kw["input"]) == 1:
            kw["input"] = kw["input"][0]            # several, a folder, a .vpc: a catalog
        return cls(**kw)


@dataclass
class Done:
    """What a job did: the input points ((N, 3) float64, file order), the radius used
    (with ``k``: each point's, NaN where isolated), the
    :class:`~clcurv.api.result.CurvatureResult` and the fields written."""
    points: np.ndarray
    radius: float | np.ndarray
    result: CurvatureResult
    fields: dict


class Stages:
    """Times each stage (seconds, in ``times``); a tqdm bar per stage unless quiet."""

    def __init__(self, quiet):
        self.quiet, self.times = quiet, {}

    @contextmanager
    def stage(self, name, total=1):
        """Context yielding ``tick()``, to be called once per unit of work done."""
        bar = None if self.quiet else _bar(name, total)
        t = time.perf_counter()
        try:
            yield (bar.update if bar is not None else (lambda *a: None))
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t
            if bar is not None:
                bar.n = total
                bar.refresh()
                bar.close()


def _bar(name, total):
    return tqdm(total=total, desc=f"{name:<14}", leave=True, file=sys.stderr,
                bar_format="{desc} {bar} {n_fmt}/{total_fmt} [{elapsed}]")


def auto_radius(points, k=AUTO_NEIGHBOURS, sample=5000, seed=0):
    """Radius (points' length unit) giving about ``k`` neighbours: the median, over a
    random subsample of ``sample`` points (``seed``), of the distance to the k-th nearest
    other point. When that median is 0 (most points have k exact duplicates), the same
    over the distinct positions; UsageError when there are at most ``k`` of them."""
    if len(points) <= k:
        raise UsageError(f"--radius auto needs more than {k} points, the cloud has {len(points)}")
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(points), size=min(sample, len(points)), replace=False)
    d, _ = cKDTree(points).query(points[idx], k=k + 1)
    r = float(np.median(d[:, -1]))
    if r > 0:
        return r
    distinct = np.unique(points, axis=0)        # most sampled points have k duplicates
    if len(distinct) <= k:
        raise UsageError(f"--radius auto: the {len(points)} points have only {len(distinct)} "
                         f"distinct positions (duplicates); give --radius explicitly")
    return auto_radius(distinct, k, sample, seed)


def radius_list(radius):
    """Several radii (``--select error``): a list of numbers or a string of numbers
    separated by commas, as positive floats; UsageError otherwise."""
    items = radius.split(",") if isinstance(radius, str) else list(np.ravel(radius))
    try:
        radii = [float(r) for r in items]
    except (TypeError, ValueError):
        raise UsageError(f"--select error needs --radius R1,R2[,...] (numbers separated by "
                         f"commas), got {radius!r}") from None
    if len(radii) < 2 or not all(np.isfinite(r) and r > 0 for r in radii):
        raise UsageError(f"--select error needs at least two positive radii, got {radius!r}")
    return radii


def resolve_radius(radius, points, out=print):
    """The radius as a positive float: ``"auto"`` (said on ``out``) or a number."""
    if radius == "auto":
        r = auto_radius(points)
        out(f"radius auto: {r:.6g} (median distance to the {AUTO_NEIGHBOURS}th neighbour)")
        return r
    try:
        r = float(radius)
    except ValueError:
        raise UsageError(f"--radius must be a number or 'auto', got {radius!r}") from None
    if not np.isfinite(r) or r <= 0:
        raise UsageError(f"--radius must be positive, got {radius}")
    return r


def check_options(job):
    """Refuse ``kernel``, ``h`` or ``projections`` for a method that does not take them
    (before any work is done)."""
    op = OPERATORS.get(job.method)
    if op is None:
        return                                  # the API names the methods
    extra = op.foreign_options(given({n: getattr(job, OPTIONS[n].job) for n in METHOD_OPTIONS
                                      if OPTIONS[n].job is not None}))
    for name, takers in extra.items():
        raise UsageError(f"{OPTIONS[name].flag} is an option of --method {' or '.join(takers)} "
                         f"only, not of {job.method}")
    if job.quantize:
        outs = job.output if isinstance(job.output, (list, tuple)) else [job.output]
        if isinstance(job.input, (list, tuple)):
            outs = []                       # a catalog's outputs are LAS/LAZ, like its inputs
        if not all(io.is_las(o) for o in outs):
            raise UsageError("--quantize stores LAS/LAZ extra bytes: write .las or .laz")
        if job.k is not None:
            raise UsageError("--quantize scales the curvatures by the radius: give --radius, "
                             "not --k")
    if job.select is not None:
        if job.select != "error":
            raise UsageError(f"--select must be 'error', got {job.select!r}")
        radius_list(job.radius)
        for name, on in (("--k", job.k is not None), ("--quantize", job.quantize),
                         ("--tile-size", job.tile_size is not None),
                         ("--workers", bool(job.workers)), ("--scheduler", job.scheduler)):
            if on:
                raise UsageError(f"--select error runs in memory on one radius scale: not "
                                 f"with {name}")
    if job.k is not None:
        if job.radius != "auto":
            raise UsageError("give --radius or --k, not both")
        for name, on in (("--scale-space", job.scale_space), ("--projections", job.projections),
                         ("--weights density", job.weights == "density"),
                         ("--kernel gaussian", job.kernel == "gaussian")):
            if on:
                raise UsageError(f"{name} does not combine with --k (a k-NN radius)")


def chosen_fields(res, wanted=None):
    """The names of the fields a file of ``res`` gets for the ``fields`` option's value
    ``wanted`` (None: the method's default set; ``"all"``; names: :meth:`clcurv.ops.registry.
    Operator.chosen_fields`), ``"normals"`` among them when they are written; UsageError
    for an unknown name."""
    extra = ((("selected_radius",) if "select" in res.info else ("knn_radius",))
             if np.ndim(res.radius) else ())
    op = OPERATORS[res.method]
    try:
        return op.chosen_fields(wanted, extra, op.has_errors(res))
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def result_fields(res, wanted=None):
    """The per-point fields of ``res`` to write, name -> (N,) array, named as
    CloudCompare/MeshLab scalar fields (:func:`clcurv.tiles.engine.curvature_fields`: the
    operator's file fields in the registry's order, then ``neighbours`` and ``status``).
    ``wanted``: the ``fields`` option (None: the method's default set, :func:`chosen_fields`;
    ``"all"``: every one; ``"normals"`` is allowed and written apart); UsageError for an
    unknown name."""
    names = chosen_fields(res, wanted)
    return {k: v for k, v in curvature_fields(res).items() if k in names}


def summary_fields(method, uncertainty=False):
    """The file fields whose ranges the summary prints: the method's width-1 file fields
    (its curvatures, or the surface variation; with ``uncertainty`` its errors too)."""
    op = OPERATORS[method]
    return [o.file for o in op.outputs + (op.errors if uncertainty else ())
            if o.file is not None and o.width == 1]


def _range(v):
    ok = np.isfinite(v)
    if not ok.any():
        return "all NaN"
    lo, med, hi = np.percentile(v[ok], [1, 50, 99])
    nan = f", {np.count_nonzero(~ok)} NaN" if not ok.all() else ""
    return f"p1 {lo:.4g}  median {med:.4g}  p99 {hi:.4g}{nan}"


def _input_normals(job, cloud):
    """The file's normals when usable (all finite) and not ignored, else None."""
    n = cloud.normals
    if job.ignore_normals or n is None or not np.isfinite(n).all():
        return None
    return n


def _evaluate(job, cloud, radius, device, st):
    """Scale space then operator; returns (result, the cloud the operator saw)."""
    common = dict(weights=job.weights, device=device, precision=job.precision)
    work = cloud.points
    if job.scale_space:
        with st.stage("scale space", total=job.scale_space) as tick:
            work = scale_space(work, radius, job.scale_space, progress=tick, **common)
    with st.stage(job.method):
        res = curvature(work, radius, k=job.k, method=job.method,
                        normals=_input_normals(job, cloud),
                        viewpoint=job.viewpoint, orient=orientation(job, cloud),
                        kernel=job.kernel, h=job.h, projections=job.projections,
                        uncertainty=job.uncertainty and job.select is None, select=job.select,
                        **common)
    return res, work


#: ``--orient`` values and the API's ``orient`` they stand for (the options' declaration)
ORIENT_CHOICES = OPTIONS["orient"].cli_choices


def orientation(job, cloud):
    """The API ``orient`` of a job: ``--orient auto`` is "up" (normals towards +Z, PDAL's
    ``always_up``) for LAS/LAZ input without normals or a viewpoint
    (:func:`clcurv._shared.options.file_orient`, the tiles' rule too), else the API's
    "auto" (the file's normals, the viewpoint, else MST propagation)."""
    if job.orient not in ORIENT_CHOICES:
        raise UsageError(f"--orient must be one of {', '.join(ORIENT_CHOICES)}, got "
                         f"{job.orient!r}")
    return file_orient(ORIENT_CHOICES[job.orient], io.from_las(cloud), job.viewpoint,
                       _input_normals(job, cloud) is not None)


def _positions(job, cloud, res, work):
    if job.positions == "original":
        return cloud.points
    return res.points if res.points is not None else work


def _radius_text(job, radius):
    """The summary's radius: the number, or with ``--k`` the per-point radii's median, p99
    and isolated count."""
    if not np.ndim(radius):
        return f"radius {radius:.6g}"
    if job.select is not None:
        radii = sorted(set(np.asarray(radius)[np.isfinite(radius)].tolist()))
        counts = ", ".join(f"{r:.6g}: {np.mean(radius == r):.0%}" for r in radii)
        return f"radius selected per point by predicted error ({counts})"
    iso = int(np.count_nonzero(np.isnan(radius)))
    if iso == len(radius):
        return f"radius the distance to the k-th nearest point, k = {job.k} (every point isolated)"
    more = f", {iso} isolated" if iso else ""
    return (f"radius the distance to the k-th nearest point, k = {job.k} (median "
            f"{np.nanmedian(radius):.6g}, p99 {np.nanpercentile(radius, 99):.6g}{more})")


def _summary(job, cloud, done, device, times, normals_written):
    """The summary lines printed after a job."""
    res, pts = done.result, done.points
    dropped = f" ({cloud.dropped} non-finite dropped)" if cloud.dropped else ""
    yield f"\n{len(pts)} points from {job.input}{dropped}"
    yield (f"method {job.method}, {_radius_text(job, done.radius)}, scale space "
           f"{job.scale_space} iteration(s), weights {job.weights}")
    if len(pts):
        yield (f"mean neighbours {res.count.mean():.1f} (median {np.median(res.count):.0f}); "
               f"status ok {np.mean(res.valid):.1%}")
    yield f"device {device.info.name} ({device.info.platform})"
    yield "time: " + ", ".join(f"{k} {v:.2f} s" for k, v in times.items())
    ranged = summary_fields(job.method, job.uncertainty or job.select is not None)
    for k, v in done.fields.items():
        if k in ranged:
            yield f"  {k:<20} {_range(v)}"
    names = (["nx ny nz"] if normals_written else []) + list(done.fields)
    kept = io.kept_attributes(job.output, cloud, done.fields)
    more = f"; kept from the input: {', '.join(kept)}" if kept else ""
    yield f"wrote {job.output}: {', '.join(names)}{more}"


def run(job, out=print):
    """Run ``job`` (a :class:`Job`), print its summary on ``out``; return a :class:`Done`
    (in tiles, :func:`run_tiled`: the summary dict)."""
    check_options(job)
    if stream.is_catalog(job.input):                # a catalog: always in tiles
        return run_tiled(job, out)
    io.check_output(job.output)             # before any work: extension, folder, rights
    io.check_not_input(job.output, job.input)
    if wants_tiles(job):
        return run_tiled(job, out)
    return _run_in_memory(job, out)


def _run_in_memory(job, out):
    """The job in memory (its options checked, its output path too)."""
    st = Stages(job.quiet)
    with st.stage("reading"):
        cloud = io.read(job.input)
    radius = (None if job.k is not None else radius_list(job.radius) if job.select
              else resolve_radius(job.radius, cloud.points, out))
    device = get_device(job.device)
    res, work = _evaluate(job, cloud, radius, device, st)
    done = Done(cloud.points, res.radius if job.k is not None or job.select else radius, res,
                result_fields(res, job.fields))
    normals = res.normals if "normals" in chosen_fields(res, job.fields) else None
    with st.stage("writing"):
        io.write(job.output, _positions(job, cloud, res, work), fields=done.fields,
                 normals=normals, like=cloud, quantize=radius if job.quantize else None)
    for line in _summary(job, cloud, done, device, st.times, normals is not None):
        out(line)
    return done


# --------------------------------------------------------------------------- in tiles, or not

def error_bytes(uncertainty):
    """Host bytes more per point of an in-memory run with ``uncertainty``
    (:data:`clcurv.tiles.planning.UNCERTAINTY_BYTES`), else 0."""
    return UNCERTAINTY_BYTES if uncertainty else 0


def in_tiles(n, budget, forced=False, extra=0, method=None, source=None):
    """The decision between a run in memory and one in tiles, for every entry point here: in
    tiles when it is ``forced`` (a tile size, workers or a Dask scheduler or client, several
    input files) or when ``n`` points do not fit ``budget`` bytes (the estimate of
    ``method`` and of the LAS records of ``source``, ``extra`` bytes more per point:
    :func:`clcurv.tiles.planning.fits_memory`)."""
    layout = getattr(source, "layout", None)
    return forced or not fits_memory(n, budget, extra, method,
                                     getattr(layout, "record_length", None))


def wants_tiles(job):
    """Does the file job ``job`` (a :class:`Job`) run tiled: a tile size was given, or its
    LAS/LAZ/NPY input does not fit the memory budget (its point count from the header)."""
    if job.tile_size is not None or job.workers or job.scheduler:      # forced
        return True
    if Path(job.input).suffix.lower() not in stream.STREAM_READS:
        return False
    try:
        src = stream.open_source(job.input)
    except Exception:                       # the in-memory reader reports it
        return False
    if (job.projections or job.positions != "original" or job.k is not None
            or job.select is not None):
        # options only the in-memory job has: tiles only when it cannot fit at all (the
        # tiled run then says which option it lacks)
        return in_tiles(src.n, fit_budget("auto"), extra=error_bytes(job.uncertainty),
                        method=job.method, source=src)
    return in_tiles(src.n, fit_budget(job.memory), extra=error_bytes(job.uncertainty),
                    method=job.method, source=src)


def options_for(job, takes):
    """The options of ``job`` (a :class:`Job`) that ``takes`` (a function or a class) takes,
    by the names the options' declaration gives them (``tile_size`` is ``tile``), ``--orient``
    spellings as the API's values (``"none"`` is None); the radius apart."""
    names = inspect.signature(takes).parameters
    return {o.name: cli_value(o.name, getattr(job, o.job)) for o in OPTIONS.values()
            if o.job is not None and o.name in names and o.name != "radius"}


def _check_before_reading(job):
    """The checks of :func:`clcurv.tiles.engine.check_params` before ``radius="auto"`` reads the
    cloud to estimate the radius (made with a radius of 1; the run checks the real one)."""
    check_method(job.method)
    params = CurvatureParams(radius=1.0, **options_for(job, CurvatureParams))
    tiled.check_params(params, job.fields, local=not (job.workers or job.scheduler))
    tiled.wsp.check_workdir(job.workdir)


def run_tiled(job, out=print):
    """The file job ``job`` in tiles (:func:`curvature_file`); prints a summary on ``out``
    and returns the summary dict."""
    if job.select is not None:
        raise UsageError("--select error needs the whole cloud in memory: it does not run in "
                         "tiles (a cloud larger than this machine's memory, several input "
                         "files); give one --radius to run in tiles")
    if job.k is not None:
        raise UsageError("--k (a k-NN radius) needs the whole cloud in memory: it does not "
                         "run in tiles (--tile-size, --workers, --scheduler, several input "
                         "files, or a cloud larger than this machine's memory); give --radius "
                         "to run in tiles")
    if job.radius == "auto" or job.radius is None:
        _check_before_reading(job)
        src = (stream.Catalog(job.input) if stream.is_catalog(job.input)
               else stream.open_source(job.input))
        job.radius = auto_radius_tiled(src,
                                       budget=budget_of(job.memory))
        out(f"radius auto: {job.radius:.6g} (median distance to the 30th neighbour, "
            "sampled in regions spread over the cloud)")
    if job.positions != "original":
        raise UsageError("a tiled run writes the original positions (--positions original)")
    if job.workers is not None and job.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {job.workers}")
    try:
        with tile_session(job.quiet, job.scheduler) as (progress, client):
            summary = curvature_file(
                job.input, job.output, float(job.radius), progress=progress,
                out=None if job.quiet else (lambda s: print(s, file=sys.stderr)),
                client=client, **options_for(job, curvature_file))
    except TilingError as exc:
        raise UsageError(str(exc)) from exc
    for line in _tiled_summary(job, summary):
        out(line)
    return summary


def _tiled_summary(job, summary):
    """The summary lines of a tiled run: those of the in-memory run (:func:`_summary`),
    the percentiles from the systematic sample of the tiles (:func:`clcurv.tiles.engine.
    values_summary`; the mean neighbour count and the NaN counts exact)."""
    times = ", ".join(f"{k} {v:.2f} s" for k, v in summary["times"].items())
    st = summary["status"]
    what = job.input
    if "files" in summary:
        what = f"{summary['files']} files" + ("" if isinstance(what, (list, tuple))
                                               else f" of {what}")
    dropped = summary.get("dropped", 0)
    dropped = f" ({dropped} non-finite dropped)" if dropped else ""
    n = summary["points"]
    yield (f"\n{n} points from {what}{dropped} in {summary['tiles']} tile(s) "
           f"(halo {summary['halo']} cell(s))")
    yield (f"method {job.method}, {_radius_text(job, float(job.radius))}, scale space "
           f"{job.scale_space} iteration(s), weights {job.weights}")
    if "neighbours" in summary and st and sum(st):
        mean, med = summary["neighbours"]
        yield (f"mean neighbours {mean:.1f} (median {med:.0f}); status ok "
               f"{st[0] / sum(st):.1%}")
    if job.workers or job.scheduler:
        yield "device: each worker's own (--device, else its default)"
    else:
        device = get_device(job.device)
        yield f"device {device.info.name} ({device.info.platform})"
    yield f"time: {times}"
    for k, (q, nan) in summary.get("ranges", {}).items():
        text = ("all NaN" if q is None else
                f"p1 {q[0]:.4g}  median {q[1]:.4g}  p99 {q[2]:.4g}"
                + (f", {nan} NaN" if nan else ""))
        yield f"  {k:<20} {text}"
    if summary.get("ranges") and summary.get("sample", n) < n:
        yield (f"  (median and percentiles of a systematic sample of {summary['sample']} "
               "points)")
    names = summary.get("fields")
    index = f"; and the index {summary['index']}" if summary.get("index") else ""
    yield f"wrote {job.output}" + (f": {', '.join(names)}" if names else "") + index


def curvature_file(src, dst, radius, *, method="mls2", weights="uniform", orient="auto",
                   viewpoint=None, kernel=None, h=None, scale_space=0, projections=0,
                   memory="auto", tile=None, workdir=None, fields=None, quantize=False,
                   ignore_normals=False, device=None, precision="float", progress=None,
                   out=None, client=None, workers=None, uncertainty=False):
    """Run ``method`` on the cloud of file ``src`` and write ``dst``, in tiles when the cloud
    does not fit the memory budget (:mod:`clcurv.tiles.engine`: the same output bit for
    bit).

    Parameters
    ----------
    src, dst : path
        Input LAS/LAZ or NPY; output LAS/LAZ (only from LAS/LAZ input: header and records
        kept) or NPZ. Non-tiled runs (the cloud fits) are the file job (:class:`Job`) in
        memory and take every format it takes. ``src`` may be a catalog, always run in
        tiles: a list of LAS/LAZ (or NPY) paths, a folder (its ``*.las``, ``*.laz``,
        ``*.copc.laz`` in sorted name order) or a ``.vpc`` (its items' order), read as one
        cloud (:class:`clcurv.io.stream.Catalog`, which says what is checked and refused);
        ``dst`` is then an existing folder that gets one output per input file, named as
        the input (``x.copc.laz`` as ``x.laz``, ``x.npy`` as ``x.npz``), and for LAS/LAZ a
        ``.vpc`` index of them (:mod:`clcurv.io.vpc`): ``dst/<the input .vpc's name>``,
        else ``dst/index.vpc``.
    radius : float
        Ball radius in the file's unit.
    method, weights, orient, viewpoint, kernel, h, device, precision
        As :func:`clcurv.curvature`; ``orient='auto'`` of a signed method without normals
        in the file or a viewpoint is MST propagation, which a tiled run refuses (use
        'up' for aerial data).
    memory : 'auto', int or str
        Host memory budget ('auto': half the available RAM). The run tiles when about
        N x clcurv.tiles.planning.in_memory_bytes (by method and input) exceeds it, or
        when ``tile`` is given.
    tile : float, optional
        Tile side in the file's unit (default: from the budget).
    workdir : path, optional
        Workspace folder (default: beside ``dst``); kept between an interrupted run and
        the same command run again (finished tiles are skipped), removed at the end.
    fields : list of str or 'all', optional
        The fields to write (as ``clcurv compute --fields``; ``"normals"`` among them):
        default the method's default set (its curvatures, ``neighbours``, ``status`` and
        the normals; not the principal directions), ``"all"`` every one
        (:meth:`clcurv.ops.registry.Operator.chosen_fields`).
    quantize : bool
        LAS/LAZ output: clcurv's real fields as integers with the extra-bytes descriptor's
        scale (:func:`clcurv.io.las.quantization`: curvatures to 5e-5 / radius, normals to
        5e-5, NaN as ``no_data``); ValueError for another output format.
    uncertainty : bool
        Also the standard errors and roughness (as :func:`clcurv.curvature`), among the
        default fields: ``mean_curvature_se``, ``gaussian_curvature_se``, ``k1_se``,
        ``k2_se``, ``normal_se``, ``roughness`` (those of the method).
    progress : callable(done, total, points) or None
        Called after each tile.
    client : dask.distributed.Client, optional
        Run the tiles on this cluster (:mod:`clcurv.tiles.workers`; the workspace must be on a
        file system the workers share).
    workers : int, optional
        Run the tiles on a LocalCluster of this many worker processes.
    out : callable(str) or None
        Receives one line per stage (the CLI prints them).

    Returns
    -------
    dict
        ``tiled`` (bool), ``tiles``, ``points``, ``halo`` (cells), ``times`` (seconds per
        stage), ``status`` counts, ``dst``; a catalog's ``files`` (count) and ``index``
        (the ``.vpc`` written, LAS/LAZ only).
    """
    say = out or (lambda s: None)
    check_method(method)
    r = as_radius(radius)
    catalog = stream.is_catalog(src)
    if catalog:
        source, dst, index = _catalog(src, dst)
    else:
        index = None
        dst = io.check_output(dst)
        io.check_not_input(dst, src)        # as the CLI: a mesh's faces are never lost
        source = stream.open_source(src)
    tile = check_tile_size(tile)                    # before any point is read
    budget = budget_of(memory)
    if int(projections):
        raise TilingError("a tiled run does not take projections yet (iterated MLS2 moves "
                          "the points across tiles): run them in memory")
    if int(scale_space) < 0:
        raise ValueError(f"scale_space must be >= 0, got {scale_space}")
    tiled.check_tiled_outputs(dst if catalog else [dst], source)
    uncertainty = bool(uncertainty)
    # the names, in the resume key too
    fields = OPERATORS[method].chosen_fields(fields, uncertainty=uncertainty)
    if quantize and not all(io.is_las(d) for d in (dst if catalog else [dst])):
        raise ValueError("quantize stores LAS/LAZ extra bytes: write .las or .laz")
    params = CurvatureParams(method=method, radius=r, weights=weights, orient=orient,
                             viewpoint=viewpoint, kernel=kernel, h=h, device=device,
                             precision=precision, ignore_normals=ignore_normals,
                             scale_space=scale_space, quantize=quantize,
                             uncertainty=uncertainty)
    forced = catalog or tile is not None or client is not None or bool(workers)
    if not in_tiles(source.n, fit_budget(memory), forced, error_bytes(uncertainty),
                    method=method, source=source):
        summary = _curvature_in_memory(src, dst, params, fields)
        summary["dropped"] = int(getattr(source, "dropped", 0))
        return summary
    summary = tiled.run(source, dst, params, budget, tile, workdir, fields, progress, say,
                        client, workers)
    return _indexed(summary, source, dst, index) if catalog else summary


def _catalog(src, dst):
    """(the :class:`clcurv.io.stream.Catalog` of ``src``: several paths, a folder or a
    ``.vpc``; its output paths in the folder ``dst``; the path of the ``.vpc`` index of
    the outputs, or None): checked before any point is read. The index of LAS/LAZ outputs
    is ``dst/<the input .vpc's name>``, else ``dst/index.vpc``; it never replaces the
    input ``.vpc``."""
    source = stream.Catalog(src)
    dsts = tiled.catalog_outputs(source, dst)
    if not io.from_las(source):
        return source, dsts, None
    index = Path(dst) / (source.vpc.name if source.vpc is not None else "index.vpc")
    if source.vpc is not None and index.resolve() == source.vpc.resolve():
        raise TilingError(f"{index} would replace the input .vpc: choose another output "
                          "folder")
    io.check_output(index, {".vpc": "virtual point cloud"}, what="virtual point cloud")
    return source, dsts, index


def _indexed(summary, source, dsts, index):
    """The summary of a catalog run, its ``.vpc`` index of the outputs written."""
    summary["files"] = len(source.parts)
    if index is not None:
        summary["index"] = vpc.write(index, dsts)
    return summary


def _curvature_in_memory(src, dst, params, fields):
    """The cloud fits: the file job in memory."""
    orient = params.orient
    if not isinstance(orient, str) and orient is not None:
        raise TilingError("a direction orient= is for tiled runs and the API; the file job "
                          "takes 'auto', 'mst', 'up' or None")
    job = Job(src, dst, method=params.method, radius=params.radius, weights=params.weights,
              kernel=params.kernel, h=params.h, device=params.device,
              precision=params.precision, fields=fields, viewpoint=params.viewpoint,
              orient="none" if orient is None else orient,
              ignore_normals=params.ignore_normals, scale_space=params.scale_space,
              quantize=params.quantize, uncertainty=params.uncertainty, quiet=True)
    t0 = time.perf_counter()
    check_options(job)
    done = _run_in_memory(job, out=lambda line: None)
    return {"tiled": False, "tiles": 1, "halo": 0, "points": len(done.points),
            "times": {"in memory": time.perf_counter() - t0},
            "status": np.bincount(done.result.status, minlength=4).tolist(), "dst": dst}


def features_file(src, dst, radius=None, features=DEFAULT_FEATURES, *, k=None, ddof=0,
                  optimal=False, memory="auto", tile=None, workdir=None, device=None,
                  precision="float", progress=None, out=None, client=None, workers=None):
    """Covariance features (:func:`clcurv.api.features`) of the cloud of file ``src``, written
    with its points to ``dst``; in tiles when the cloud does not fit the memory budget
    (:mod:`clcurv.tiles.features`), with the same output bit for bit.

    Parameters
    ----------
    src : path, or a catalog (a list of paths, a folder or a ``.vpc``: files read as one
        cloud, in tiles, one output per input and a ``.vpc`` index in the folder ``dst``,
        as :func:`clcurv.curvature_file`)
    dst : path
        The output: any format :func:`clcurv.io.write` takes in memory; a tiled run writes
        LAS/LAZ (from LAS/LAZ input: header and records kept), NPZ or binary PLY.
    radius : float or list of floats
        Ball radius in the file's unit, or several (one neighbour walk; fields named
        ``<feature>_r<radius>``).
    features, k, ddof, optimal, device, precision
        As :func:`clcurv.api.features`. ``k`` runs in memory only.
    memory, tile, workdir, progress, out, client, workers
        As :func:`clcurv.curvature_file`.

    Returns
    -------
    dict
        ``tiled`` (bool), ``tiles``, ``points``, ``fields`` (names written), ``halo``,
        ``times`` (seconds per stage), ``dst``.
    """
    tile = check_tile_size(tile)                    # before any point is read
    say = out or (lambda s: None)
    check(ddof, "ddof")
    names = canonical_names(features)
    if not names:
        raise ValueError("features must name at least one feature")
    catalog = stream.is_catalog(src)
    forced = tile is not None or client is not None or bool(workers)
    if k is not None:
        if radius is not None:
            raise ValueError("give either radius or k, not both")
        if optimal:
            raise ValueError("optimal=True chooses among a list of radii, not with k")
        if forced or catalog:
            raise TilingError("k (a k-NN radius) needs the whole cloud in memory: it does "
                              "not run in tiles (a tile size, workers, a scheduler or several "
                              "input files); give a radius to run in tiles")
        dst = io.check_output(dst)
        io.check_not_input(dst, src)
        return _features_in_memory(src, dst, None, names, k, ddof, False, device,
                                   precision)
    if radius is None:
        raise ValueError("features_file needs radius= (a number or a list) or k=")
    radii, _ = as_radii(radius)
    if optimal and len(radii) < 2:
        raise ValueError(f"optimal=True needs a list of at least two radii, got {radius!r}")
    params = FeatureParams(tuple(radii), names, int(ddof), bool(optimal), device, precision)
    for d in ([dst] if not catalog else []):
        if io.is_las(d):                        # before any work: LAS's limit
            io.las.check_extra_count(d, params.columns())
    if catalog:
        source, dst, index = _catalog(src, dst)
    else:
        index = None
        dst = io.check_output(dst)
        io.check_not_input(dst, src)
        source = _streamed(src) if not forced else stream.open_source(src)
        if source is None:          # a format the tiles do not read: the in-memory reader
            return _features_in_memory(src, dst, radii, names, None, ddof, optimal, device,
                                       precision)
    budget = budget_of(memory)
    if not in_tiles(source.n, fit_budget(memory), forced or catalog, params.extra_in_memory(),
                    method="features", source=source):
        return _features_in_memory(src, dst, radii, names, None, ddof, optimal, device,
                                   precision)
    tiled.check_tiled_outputs(dst if catalog else [dst], source)
    summary = tiled.run(source, dst, params, budget, tile, workdir, None, progress, say,
                        client, workers)
    summary["fields"] = [n for n, _, _ in params.specs()]
    summary.pop("status", None)             # curvature's status field: none here
    return _indexed(summary, source, dst, index) if catalog else summary


def _streamed(src):
    """The stream source of ``src``, or None when the tiles cannot read it (the in-memory
    reader then reads it, or says what is wrong with it)."""
    if Path(src).suffix.lower() not in stream.STREAM_READS:
        return None
    try:
        return stream.open_source(src)
    except Exception:
        return None


def _features_in_memory(src, dst, radii, names, k, ddof, optimal, device, precision):
    """The whole cloud read, :func:`clcurv.api.features`, the file written (the summary dict
    of :func:`features_file`)."""
    t0 = time.perf_counter()
    cloud = io.read(src)
    several = radii is not None and len(radii) > 1 and not optimal
    radius = None if radii is None else radii if several or optimal else radii[0]
    res = compute_features(cloud.points, radius, names, k=k, ddof=ddof, optimal=optimal,
                           device=device, precision=precision)
    extra = "knn_radius" if k is not None else "optimal_radius" if optimal else None
    fields, normals = file_fields(res, radii if several else None, extra)
    path = io.write(dst, cloud.points, fields, normals=normals, like=cloud)
    names_out = list(fields) + ([] if normals is None else ["normals"])
    return {"tiled": False, "tiles": 1, "halo": 0, "points": len(cloud.points),
            "dropped": int(getattr(cloud, "dropped", 0) or 0), "fields": names_out,
            "times": {"in memory": time.perf_counter() - t0}, "dst": path}
