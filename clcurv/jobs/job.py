"""The file job behind ``clcurv compute`` and ``clcurv demo``: read a cloud, pick the radius,
smooth it by the MLS1 scale space, run one operator, write the fields, print a summary.

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

import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Sequence

import numpy as np

from clcurv import io
from clcurv.api.curvature import curvature
from clcurv.runtime.device import get_device
from clcurv.ops.registry import OPERATORS
from clcurv.api.result import CurvatureResult
from clcurv.ops.smoothing import scale_space

__all__ = ["Job", "Done", "UsageError", "run", "auto_radius", "result_fields"]

#: neighbours aimed at by ``radius="auto"``
AUTO_NEIGHBOURS = 30


class UsageError(Exception):
    """A bad option value (the command's exit code 2)."""


@dataclass
class Job:
    """One file job; the fields are the options of ``clcurv compute``.

    ``radius``: the ball radius in the file's length unit, or ``"auto"`` (about 30
    neighbours, :func:`auto_radius`). ``scale_space``: MLS1 scale-space steps at that
    radius before the operator. ``kernel``, ``h`` (length unit) and ``projections``: the
    options of the methods that take them (MLS2). ``fields``: the fields to write
    (``"normals"`` and the names of :func:`result_fields`; None: all). ``positions``:
    write the ``"original"`` positions or the ``"projected"`` ones (the operator's
    projection, else the smoothed cloud). ``k``: instead of ``radius``, each point's radius
    is the distance to its k-th nearest point (:mod:`clcurv.ops.knn_radius`; in memory only).
    """
    input: str | Path
    output: str | Path
    method: str = "mls2"
    radius: float | str = "auto"
    scale_space: int = 0
    weights: str = "uniform"
    kernel: str | None = None
    h: float | None = None
    projections: int = 0
    device: int | str | None = None
    precision: str = "float"
    fields: Sequence[str] | None = None
    viewpoint: Sequence[float] | None = None
    orient: str = "auto"
    positions: str = "original"
    ignore_normals: bool = False
    quiet: bool = False
    memory: str | int | None = "auto"
    tile_size: float | None = None
    workers: int | None = None
    scheduler: str | None = None
    workdir: str | Path | None = None
    k: int | None = None

    @classmethod
    def from_args(cls, args):
        """The job of an ``argparse.Namespace`` with the same attribute names."""
        kw = {f.name: getattr(args, f.name) for f in fields(cls) if hasattr(args, f.name)}
        if isinstance(kw.get("input"), list) and len(kw["input"]) == 1:
            kw["input"] = kw["input"][0]            # several: a catalog (clcurv.tiles.engine)
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
    from tqdm import tqdm
    return tqdm(total=total, desc=f"{name:<14}", leave=True, file=sys.stderr,
                bar_format="{desc} {bar} {n_fmt}/{total_fmt} [{elapsed}]")


def auto_radius(points, k=AUTO_NEIGHBOURS, sample=5000, seed=0):
    """Radius (points' length unit) giving about ``k`` neighbours: the median, over a
    random subsample of ``sample`` points (``seed``), of the distance to the k-th nearest
    other point. When that median is 0 (most points have k exact duplicates), the same
    over the distinct positions; UsageError when there are at most ``k`` of them."""
    from scipy.spatial import cKDTree
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
    extra = op.foreign_options({"kernel": job.kernel is not None, "h": job.h is not None,
                                "projections": bool(job.projections)})
    for name, takers in extra.items():
        raise UsageError(f"--{name} is an option of --method {' or '.join(takers)} only, "
                         f"not of {job.method}")
    if job.k is not None:
        if job.radius != "auto":
            raise UsageError("give --radius or --k, not both")
        for name, on in (("--scale-space", job.scale_space), ("--projections", job.projections),
                         ("--weights density", job.weights == "density"),
                         ("--kernel gaussian", job.kernel == "gaussian")):
            if on:
                raise UsageError(f"{name} does not combine with --k (a k-NN radius)")


def result_fields(res, wanted=None):
    """The per-point fields of ``res`` to write, name -> (N,) array, named as
    CloudCompare/MeshLab scalar fields: the operator's file fields in the registry's order
    (:meth:`clcurv.ops.registry.Operator.file_fields`; float64, curvatures in 1/length,
    directions as ``dirI_x, _y, _z``), then ``neighbours`` (int32, #N_r(p), the point
    itself included) and ``status`` (uint8, 0 ok). ``wanted``: keep only these names
    (``"normals"`` is allowed and written apart)."""
    f = {}
    for name, (attr, col) in OPERATORS[res.method].file_fields().items():
        a = getattr(res, attr)
        f[name] = a if col is None else a[:, col]
    if np.ndim(res.radius):                  # a k-NN radius: each point's
        f["knn_radius"] = np.asarray(res.radius, dtype=np.float64)
    f["neighbours"] = res.count.astype(np.int32)
    f["status"] = res.status.astype(np.uint8)
    if not wanted:
        return f
    unknown = sorted(set(wanted) - set(f) - {"normals"})
    if unknown:
        raise UsageError(f"unknown field(s) {', '.join(unknown)} for method {res.method}; "
                         f"available: normals, {', '.join(f)}")
    return {k: v for k, v in f.items() if k in wanted}


def summary_fields(method):
    """The file fields whose ranges the summary prints: the method's width-1 file fields
    (its curvatures, or the surface variation)."""
    return [o.file for o in OPERATORS[method].outputs if o.file is not None and o.width == 1]


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
                        kernel=job.kernel, h=job.h, projections=job.projections, **common)
    return res, work


#: ``--orient`` values and the API's ``orient`` they stand for
ORIENT_CHOICES = {"auto": "auto", "mst": "mst", "up": "up", "none": None}


def orientation(job, cloud):
    """The API ``orient`` of a job: ``--orient auto`` is "up" (normals towards +Z, PDAL's
    ``always_up``) for LAS/LAZ input without normals or a viewpoint, else the API's
    "auto" (the file's normals, the viewpoint, else MST propagation)."""
    if job.orient not in ORIENT_CHOICES:
        raise UsageError(f"--orient must be one of {', '.join(ORIENT_CHOICES)}, got "
                         f"{job.orient!r}")
    aerial = cloud.format in ("las", "laz") and job.viewpoint is None
    if job.orient == "auto" and aerial and _input_normals(job, cloud) is None:
        return "up"
    return ORIENT_CHOICES[job.orient]


def _positions(job, cloud, res, work):
    if job.positions == "original":
        return cloud.points
    return res.points if res.points is not None else work


def _radius_text(job, radius):
    """The summary's radius: the number, or with ``--k`` the per-point radii's median, p99
    and isolated count."""
    if not np.ndim(radius):
        return f"radius {radius:.6g}"
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
    ranged = summary_fields(job.method)
    for k, v in done.fields.items():
        if k in ranged:
            yield f"  {k:<20} {_range(v)}"
    names = (["nx ny nz"] if normals_written else []) + list(done.fields)
    kept = io.kept_attributes(job.output, cloud, done.fields)
    more = f"; kept from the input: {', '.join(kept)}" if kept else ""
    yield f"wrote {job.output}: {', '.join(names)}{more}"


def run(job, out=print):
    """Run ``job`` (a :class:`Job`), print its summary on ``out``; return a :class:`Done`."""
    check_options(job)
    from clcurv.jobs import tiled_job
    if isinstance(job.input, (list, tuple)):        # a catalog: always in tiles
        return tiled_job.run_job(job, out)
    io.check_output(job.output)             # before any work: extension, folder, rights
    io.check_not_input(job.output, job.input)
    if tiled_job.wants_tiles(job):
        return tiled_job.run_job(job, out)
    st = Stages(job.quiet)
    with st.stage("reading"):
        cloud = io.read(job.input)
    radius = None if job.k is not None else resolve_radius(job.radius, cloud.points, out)
    device = get_device(job.device)
    res, work = _evaluate(job, cloud, radius, device, st)
    done = Done(cloud.points, res.radius if job.k is not None else radius, res,
                result_fields(res, job.fields))
    normals = None if job.fields and "normals" not in job.fields else res.normals
    with st.stage("writing"):
        io.write(job.output, _positions(job, cloud, res, work), fields=done.fields,
                 normals=normals, like=cloud)
    for line in _summary(job, cloud, done, device, st.times, normals is not None):
        out(line)
    return done
