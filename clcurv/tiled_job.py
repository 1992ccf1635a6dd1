"""``clcurv compute`` on clouds that do not fit the memory budget: the file job in tiles
(:func:`clcurv.tiled.curvature_file`), and ``radius="auto"`` without the whole cloud."""
from __future__ import annotations

import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .buckets import BUCKETS_PER_TILE, READ_CHUNK, Buckets, bucket_grid
from .io import stream
from .operators import OPERATORS
from .tiled import curvature_file
from .tiling import (AUTO_FRACTION, TILE_BYTES_PER_POINT, TilingError, available_memory,
                     budget_of, fits_memory)

def wants_tiles(job):
    """Does the file job ``job`` (clcurv.job.Job) run tiled: a tile size was given, or its
    LAS/LAZ/NPY input does not fit the memory budget (its point count from the header)."""
    if job.tile_size is not None or job.workers or job.scheduler:
        return True
    if Path(job.input).suffix.lower() not in stream.STREAM_READS:
        return False
    try:
        n = stream.open_source(job.input).n
    except Exception:                       # the in-memory reader reports it
        return False
    if job.projections or job.positions != "original" or job.k is not None:
        # options only the in-memory job has: tiles only when it cannot fit at all (the
        # tiled run then says which option it lacks)
        return not fits_memory(n, int(available_memory() * AUTO_FRACTION))
    return not fits_memory(n, budget_of(job.memory))


def auto_radius_tiled(src, k=30, regions=16, sample=5000, seed=0, budget=None):
    """``radius="auto"`` of a cloud too large for memory: the median, over about
    ``sample`` points drawn from ``regions`` random buckets (seeded, weighted by their
    counts), of the distance to the k-th nearest other point, each bucket read with the
    ring of buckets around it and only points whose k-th neighbour lies inside that
    region kept (so each distance is the whole cloud's). It estimates the in-memory
    auto radius (clcurv.job.auto_radius, a sample of the whole cloud) to a few per cent,
    not to the bit: pass the radius for reproducible runs."""
    from scipy.spatial import cKDTree
    with tempfile.TemporaryDirectory(prefix="clcurv-radius-") as tmp:
        target = max((budget or (1 << 28)) // (TILE_BYTES_PER_POINT * 9), 10_000)
        origin, side, shape = bucket_grid(src, target * BUCKETS_PER_TILE ** 2)
        b = Buckets(tmp, origin, side, shape, False)
        for start, xyz, _ in src.chunks(READ_CHUNK):
            b.add(start, xyz, None)
        rng = np.random.default_rng(seed)
        flat = b.counts.ravel().astype(float)
        if flat.sum() <= k:
            raise ValueError(f"radius auto needs more than {k} points")
        picks = rng.choice(len(flat), size=min(regions, int((flat > 0).sum())),
                           replace=False, p=flat / flat.sum())
        dists = []
        for f in picks:
            i, j = divmod(int(f), shape[1])
            pts, centre = [], None
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    a, c = i + di, j + dj
                    if 0 <= a < shape[0] and 0 <= c < shape[1] and b.counts[a, c]:
                        rec = np.fromfile(b.path(a, c), b.dtype)
                        pts.append(rec["p"])
                        if (di, dj) == (0, 0):
                            centre = rec["p"]
            cloud = np.concatenate(pts)
            q = centre[rng.choice(len(centre), size=min(len(centre), -(-sample // len(picks))),
                                  replace=False)]
            kk = min(k + 1, len(cloud))
            d, _ = cKDTree(cloud).query(q, k=kk)
            d = d.reshape(len(q), -1)[:, -1]
            # room to the region's sides that have buckets beyond them (the others are
            # the grid's own sides, beyond which there is nothing)
            lo = np.asarray(origin) + np.array([i - 1, j - 1]) * side
            hi = lo + 3 * side
            lo = np.where([i - 1 < 0, j - 1 < 0], -np.inf, lo)
            hi = np.where([i + 1 >= shape[0], j + 1 >= shape[1]], np.inf, hi)
            room = np.min(np.concatenate([q[:, :2] - lo, hi - q[:, :2]], axis=1), axis=1)
            keep = d <= room
            dists.append(d[keep] if keep.any() else d)
        r = float(np.median(np.concatenate(dists)))
        if not r > 0:
            raise ValueError("radius auto: the sampled points have duplicates for "
                             "neighbours; give the radius")
        return r


@contextmanager
def tile_session(quiet, scheduler=None):
    """(progress, client) of a tiled CLI run: a tqdm bar of the tiles on stderr, made at
    the first tile's report (none when ``quiet``, and none for a run that turns out to fit
    in memory, which reports no tile) and a Dask client of ``scheduler`` (None without);
    both closed at the end. A scheduler that does not answer within
    clcurv.cluster.CONNECT_TIMEOUT seconds raises clcurv.cluster.SchedulerError (a
    ConnectionError: nothing listening there, or not a Dask scheduler), never a hang."""
    client = None
    if scheduler:
        from .cluster import connect
        client = connect(scheduler)
    bars = []
    started = [None]

    def progress(done, total, points):
        if not quiet and not bars:
            from tqdm import tqdm
            bars.append(tqdm(desc="tiles", unit="tile", total=total, file=sys.stderr,
                             leave=True))
        bar = bars[0] if bars else None
        if bar is not None:
            if bar.total != total:
                bar.reset(total=total)
            now = time.perf_counter()
            started[0] = started[0] or now
            rate = points / max(now - started[0], 1e-9) / 1e6 if points else 0.0
            bar.set_postfix_str(f"{points} points, {rate:.2f} M points/s", refresh=False)
            bar.update(done - bar.n)
    try:
        yield progress, client
    finally:
        for bar in bars:
            bar.close()
        if client is not None:
            client.close()


def _check_before_reading(job):
    """The checks of :func:`clcurv.tiled.check_params` before ``radius="auto"`` reads the
    cloud to estimate the radius (made with a radius of 1; the run checks the real one)."""
    from .job import ORIENT_CHOICES
    from .tiled import _Params, check_params
    from .validate import choice
    choice(job.method, "method", tuple(OPERATORS))
    params = _Params(job.method, 1.0, job.weights, ORIENT_CHOICES.get(job.orient, job.orient),
                     job.viewpoint, job.kernel, job.h, job.device, job.precision,
                     bool(job.ignore_normals), int(job.scale_space))
    check_params(params, job.fields, local=not (job.workers or job.scheduler))
    from .workspace import check_workdir
    check_workdir(job.workdir)


def run_job(job, out=print):
    """The file job ``job`` in tiles (:func:`curvature_file`); prints a summary on ``out``
    and returns the summary dict."""
    from .job import ORIENT_CHOICES, UsageError
    if job.k is not None:
        raise UsageError("--k (a k-NN radius) needs the whole cloud in memory: it does not "
                         "run in tiles (--tile-size, --workers, --scheduler, several input "
                         "files, or a cloud larger than this machine's memory); give --radius "
                         "to run in tiles")
    if job.radius == "auto" or job.radius is None:
        _check_before_reading(job)
        src = (stream.Catalog(job.input) if isinstance(job.input, (list, tuple))
               else stream.open_source(job.input))
        job.radius = auto_radius_tiled(src,
                                       budget=budget_of(job.memory))
        out(f"radius auto: {job.radius:.6g} (median distance to the 30th neighbour, "
            "sampled in 16 regions of the cloud)")
    if job.positions != "original":
        raise UsageError("a tiled run writes the original positions (--positions original)")
    if job.workers is not None and job.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {job.workers}")
    try:
        with tile_session(job.quiet, job.scheduler) as (progress, client):
            summary = curvature_file(
                job.input, job.output, float(job.radius), method=job.method,
                weights=job.weights, orient=ORIENT_CHOICES.get(job.orient, job.orient),
                viewpoint=job.viewpoint, kernel=job.kernel, h=job.h,
                scale_space=job.scale_space, projections=job.projections, memory=job.memory,
                tile=job.tile_size, fields=job.fields, ignore_normals=job.ignore_normals,
                device=job.device, precision=job.precision, progress=progress,
                out=None if job.quiet else (lambda s: print(s, file=sys.stderr)),
                client=client, workers=job.workers, workdir=job.workdir)
    except TilingError as exc:
        raise UsageError(str(exc)) from exc
    times = ", ".join(f"{k} {v:.2f} s" for k, v in summary["times"].items())
    st = summary["status"]
    ok = f"; status ok {st[0] / sum(st):.1%}" if st and sum(st) else ""
    what = (f"{len(job.input)} files" if isinstance(job.input, (list, tuple))
            else job.input)
    dropped = summary.get("dropped", 0)
    dropped = f" ({dropped} non-finite dropped)" if dropped else ""
    out(f"\n{summary['points']} points from {what}{dropped} in {summary['tiles']} tile(s) "
        f"(halo {summary['halo']} cell(s)){ok}")
    out(f"time: {times}")
    out(f"wrote {job.output}")
    return summary
