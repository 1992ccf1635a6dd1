"""Out-of-core operators: a cloud larger than memory in tiles with an exact halo.

    clcurv.curvature_file("survey.laz", "out.laz", 3.0, method="mls2", memory="2GiB")
    clcurv compute survey.laz -o out.laz --radius 3 --memory 2GiB [--tile-size 500]

What a tiled run computes is what the in-memory run (:func:`clcurv.curvature` on the whole
cloud) computes, bit for bit on the same device. How:

* **One frame.** Every tile bins its points in the grid frame of the whole cloud
  (:class:`clcurv.grid.Frame`: the origin at the cloud's minimum corner, cells of the
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
  (:mod:`clcurv.tiled_orient`). The result agrees with the in-memory MST on closed shapes
  (tests: a torus and two spheres cut into dozens of tiles, 100% agreement), though not bit
  for bit: a component's propagation tree differs near tile borders.
* **Scale space.** ``scale_space=N`` runs the N MLS1 steps in lock step over tiles
  (:mod:`clcurv.tiled_scale`): bit for bit the in-memory steps, re-binnings included.
* **Not tiled:** ``projections`` (refused with a message), input other than LAS/LAZ/NPY,
  output other than LAS/LAZ/NPZ, radius "auto" (give the radius).

Passes and files. (1) The input is read once in chunks (:mod:`clcurv.io.stream`) and each
point is appended, with its global id, to an on-disk bucket of a coarse 2-D grid (files
opened per write, so their number is not bounded by the open-file limit); the exact
bounds are taken on the way. (2) Each tile gathers its cells and halo from the buckets
that overlap them, runs the operator on a :class:`clcurv.DeviceCloud` in the global frame,
and writes its own points' fields into memory-mapped arrays indexed by global id. (3) The
output is written in input order from those arrays (LAS/LAZ: the input's header, scales,
offsets, VLRs and records kept, the fields as extra bytes), atomically
(:func:`clcurv.io.atomic_output`). The workspace (buckets, arrays, the list of finished
tiles) is a folder beside the output, ``.<output name>.clcurv-tiles``; a run interrupted
or killed is resumed by the same command (finished tiles are skipped), and the folder is
removed at the end.

Memory: peak RSS is about the baseline (interpreter, OpenCL) plus the largest tile (its
core and halo) times :data:`TILE_BYTES_PER_POINT`, whatever the size of the cloud; the
tile size comes from the budget (``memory=``) and the density measured in pass (1).
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import io, tiled_orient
from .grid import Frame
from .io import stream
from .operators import METHODS, OPERATORS
from .validate import as_radius, choice

#: peak host bytes per point of a tile's run (its points with their halo): the records of
#: the buckets, the float64 points, the DeviceCloud's host arrays, the result and its fields
#: (measured on an MLS2 run; see bench/tiled.py)
TILE_BYTES_PER_POINT = 900
#: peak host bytes per point of an in-memory file job (clcurv.job.run), to decide whether a
#: cloud fits memory="auto"
IN_MEMORY_BYTES_PER_POINT = 1300
#: fraction of the available RAM that memory="auto" uses, at most AUTO_CAP bytes: the
#: default run of a large file streams through tiles of at most ~600k points, whose peak
#: memory does not grow with the cloud (bench/tiled.py), and a larger tile is not faster
AUTO_FRACTION = 0.5
AUTO_CAP = 512 << 20
#: points per read chunk of pass (1) and per written chunk of pass (3)
READ_CHUNK = 1 << 18
#: most buckets of pass (1) (a coarse grid; each is a file)
MAX_BUCKETS = 4096
#: tiles per side of a bucket: buckets are this many times smaller than a tile, so a tile
#: reads little more than its own cells and halo
BUCKETS_PER_TILE = 2


class TilingError(ValueError):
    """A tiled run cannot be planned: a budget too small for one tile, a tile smaller than
    its halo, or options a tiled run does not take."""


# --------------------------------------------------------------------------- memory

def parse_memory(memory):
    """Bytes of a budget: an int, or a string like ``"2GiB"``, ``"500MB"``, ``"1.5G"``."""
    if isinstance(memory, (int, np.integer)) and not isinstance(memory, bool):
        value = int(memory)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(i?[bB]?)\s*", str(memory))
        if not m:
            raise ValueError(f"memory must be 'auto', a number of bytes or a size like "
                             f"'2GiB', got {memory!r}")
        unit = m.group(2).upper()
        base = 1024 if m.group(3).lower().startswith("i") or not m.group(3) else 1000
        value = int(float(m.group(1)) * base ** " KMGT".index(unit or " "))
    if value <= 0:
        raise ValueError(f"memory must be positive, got {memory!r}")
    return value


def available_memory():
    """Bytes of RAM available now (Linux MemAvailable; else total / 2)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError):
        return 4 << 30


def budget_of(memory):
    """The byte budget of ``memory`` ('auto': AUTO_FRACTION of the available RAM, at most
    AUTO_CAP)."""
    if memory is None or memory == "auto":
        return int(min(available_memory() * AUTO_FRACTION, AUTO_CAP))
    return parse_memory(memory)


# --------------------------------------------------------------------------- geometry

def halo_cells(method, weights="uniform", file_normals=False):
    """Cells of halo a tile needs for ``method`` so that its own points' results are exact:
    one per neighbourhood pass that feeds the next (see the module docstring)."""
    op = OPERATORS[method]
    passes = 2 if (op.kernel.reads_normals and op.normals == "values"
                   and not file_normals) else 1
    return passes * (2 if weights == "density" else 1)


@dataclass(frozen=True)
class Tiling:
    """Tiles of ``size`` x ``size`` cells (x, y) of ``frame``, each reading ``halo`` more
    cells around; tile t = tx + ntx * ty."""
    frame: Frame
    size: int
    halo: int

    @property
    def shape(self):
        nx, ny, _ = self.frame.dims
        return -(-nx // self.size), -(-ny // self.size)

    @property
    def count(self):
        a, b = self.shape
        return a * b

    def cells(self, t, halo=True):
        """(cx0, cx1, cy0, cy1): the half-open cell ranges of tile t (with its halo)."""
        ntx, _ = self.shape
        tx, ty = t % ntx, t // ntx
        h = self.halo if halo else 0
        return (tx * self.size - h, (tx + 1) * self.size + h,
                ty * self.size - h, (ty + 1) * self.size + h)

    def box(self, t):
        """(lo, hi) x-y coordinates of tile t with its halo (for the bucket search)."""
        cx0, cx1, cy0, cy1 = self.cells(t)
        o, c = self.frame.origin, self.frame.cell
        return (o[0] + cx0 * c, o[1] + cy0 * c), (o[0] + cx1 * c, o[1] + cy1 * c)


def _within(cells, rng):
    cx0, cx1, cy0, cy1 = rng
    return ((cells[:, 0] >= cx0) & (cells[:, 0] < cx1)
            & (cells[:, 1] >= cy0) & (cells[:, 1] < cy1))


# --------------------------------------------------------------------------- buckets

class Buckets:
    """Pass (1): the points, with their global ids (and the file's normals), appended to the
    files of a coarse x-y grid of ``side`` from ``origin`` (indices clamped to the grid, so
    a point outside the expected box still lands in an edge bucket); exact bounds and
    counts taken on the way."""

    def __init__(self, folder, origin, side, shape, normals):
        self.folder = Path(folder)
        self.origin, self.side, self.shape = np.asarray(origin, float), float(side), shape
        fields = [("id", "<i8"), ("p", "<f8", (3,))]
        if normals:
            fields.append(("n", "<f8", (3,)))
        self.dtype = np.dtype(fields)
        self.counts = np.zeros(shape, np.int64)
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.normals_finite = True

    def _index(self, xy):
        ij = np.floor((xy - self.origin) / self.side).astype(np.int64)
        np.clip(ij[:, 0], 0, self.shape[0] - 1, out=ij[:, 0])
        np.clip(ij[:, 1], 0, self.shape[1] - 1, out=ij[:, 1])
        return ij

    def path(self, i, j):
        return self.folder / f"b{i}_{j}.bin"

    def add(self, start, xyz, nrm):
        m = len(xyz)
        self.lo = np.minimum(self.lo, xyz.min(axis=0))
        self.hi = np.maximum(self.hi, xyz.max(axis=0))
        rec = np.empty(m, self.dtype)
        rec["id"] = np.arange(start, start + m)
        rec["p"] = xyz
        if "n" in self.dtype.names:
            rec["n"] = nrm
            self.normals_finite &= bool(np.isfinite(nrm).all())
        ij = self._index(xyz[:, :2])
        flat = ij[:, 0] * self.shape[1] + ij[:, 1]
        order = np.argsort(flat, kind="stable")
        flat, rec = flat[order], rec[order]
        cuts = np.flatnonzero(np.diff(flat)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, m]):
            i, j = divmod(int(flat[a]), self.shape[1])
            with open(self.path(i, j), "ab") as f:
                rec[a:b].tofile(f)
            self.counts[i, j] += b - a

    def overlapping(self, lo, hi):
        """(i, j) of the non-empty buckets that may hold points of the box [lo, hi) (x-y)."""
        ij = self._index(np.array([lo, hi], float))
        for i in range(ij[0, 0], ij[1, 0] + 1):
            for j in range(ij[0, 1], ij[1, 1] + 1):
                if self.counts[i, j]:
                    yield i, j

    def gather(self, tiling, t, block=1 << 18, state=None):
        """The records of the points in tile t's cells and halo, in global-id order.

        ``state`` (a :class:`clcurv.tiled_scale.State`) joins each record with its row of
        the scale space's state and places the points by ``state.key`` (their binned or
        smoothed positions, within ``state.margin`` of the original ones) instead of by
        their original positions."""
        lo, hi = tiling.box(t)
        if state is not None:
            lo, hi = np.subtract(lo, state.margin), np.add(hi, state.margin)
        rng = tiling.cells(t)
        parts = []
        for i, j in self.overlapping(lo, hi):
            rows = state.rows(self, i, j, block) if state is not None else None
            start = 0
            with open(self.path(i, j), "rb") as f:
                while True:
                    rec = np.fromfile(f, self.dtype, count=block)
                    if not len(rec):
                        break
                    if rows is not None:
                        rec = state.join(rec, next(rows), i * self.shape[1] + j, start)
                    start += len(rec)
                    pos = state.key(rec) if state is not None else rec["p"]
                    keep = _within(tiling.frame.cells_of(pos), rng)
                    if keep.any():
                        parts.append(rec[keep])
        if not parts:
            return np.empty(0, self._dtype(state))
        rec = np.concatenate(parts)
        return rec[np.argsort(rec["id"], kind="stable")]

    def _dtype(self, state):
        return self.dtype if state is None else state.joined_dtype(self.dtype)

    def state(self):
        return {"origin": self.origin.tolist(), "side": self.side, "shape": list(self.shape),
                "counts": self.counts.tolist(), "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "normals_finite": self.normals_finite,
                "normals": "n" in self.dtype.names}

    @classmethod
    def from_state(cls, folder, s):
        b = cls(folder, s["origin"], s["side"], tuple(s["shape"]), s["normals"])
        b.counts = np.asarray(s["counts"], np.int64).reshape(b.shape)
        b.lo, b.hi = np.asarray(s["lo"]), np.asarray(s["hi"])
        b.normals_finite = s["normals_finite"]
        return b


def _bucket_grid(src, target_points):
    """(origin, side, shape) of the coarse bucket grid: buckets of about target_points /
    BUCKETS_PER_TILE^2 points over the header's box (LAS) or the exact box (NPY, a cheap
    memory-mapped scan), at most MAX_BUCKETS."""
    box = src.bounds_hint()
    if box is None:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _, xyz, _ in src.chunks(READ_CHUNK * 4):
            lo, hi = np.minimum(lo, xyz.min(axis=0)), np.maximum(hi, xyz.max(axis=0))
        box = (lo, hi) if src.n else (np.zeros(3), np.zeros(3))
    lo, hi = box
    ext = np.maximum(hi[:2] - lo[:2], 1e-300)
    area = float(ext[0] * ext[1])
    per_bucket = max(target_points / BUCKETS_PER_TILE ** 2, 1.0)
    side = math.sqrt(area * per_bucket / max(src.n, 1))
    side = max(side, float(max(ext)) / math.sqrt(MAX_BUCKETS))
    shape = tuple(max(1, min(int(math.ceil(e / side)), MAX_BUCKETS)) for e in ext)
    return lo[:2], side, shape


# --------------------------------------------------------------------------- planning

def plan_tiles(buckets, radius, halo, budget, tile=None, frame=None):
    """The :class:`Tiling` of the whole cloud: its frame from the exact bounds (or
    ``frame``), and tiles of ``tile`` (length) or, from the budget, as large as the
    densest tile allows."""
    frame = frame if frame is not None else Frame.covering(buckets.lo, buckets.hi, radius)
    limit = max(int(budget // TILE_BYTES_PER_POINT), 1)
    if tile is not None:
        size = int(math.floor(float(tile) / frame.cell))
        if size < max(halo, 1):
            raise TilingError(f"tile size {tile} is smaller than the halo: a tile needs at "
                              f"least {halo} cell(s) of the radius {radius:.6g}, i.e. "
                              f"--tile-size >= {max(halo, 1) * frame.cell:.6g}")
        return Tiling(frame, size, halo)
    nx, ny, _ = frame.dims
    size = max(nx, ny)
    while True:
        tiling = Tiling(frame, size, halo)
        worst = _densest(buckets, tiling)
        if worst <= limit:
            return tiling
        if size <= max(halo, 1):
            raise TilingError(
                f"the memory budget ({budget / 2**20:.0f} MiB) is too small for one tile: "
                f"the densest tile of {size} x {size} cells of the radius holds about "
                f"{worst} points with its halo, {TILE_BYTES_PER_POINT} bytes each; give "
                "more memory (--memory) or a smaller radius")
        size = max(max(halo, 1), int(size * min(0.7, math.sqrt(limit / worst))))


def _densest(buckets, tiling):
    """An estimate of the most points a tile of ``tiling`` reads: the buckets' counts
    spread uniformly over their area."""
    b = buckets
    ntx, nty = tiling.shape
    cell = tiling.frame.cell
    reach = (tiling.size + 2 * tiling.halo) * cell
    density = b.counts / (b.side * b.side)
    worst = 0.0
    step = max(1, int(max(ntx, nty) // 256))
    for t in range(0, tiling.count, step if tiling.count > 65536 else 1):
        lo, hi = tiling.box(t)
        est = 0.0
        for i, j in b.overlapping(lo, hi):
            bx0 = b.origin[0] + i * b.side
            by0 = b.origin[1] + j * b.side
            ox = max(0.0, min(hi[0], bx0 + b.side) - max(lo[0], bx0))
            oy = max(0.0, min(hi[1], by0 + b.side) - max(lo[1], by0))
            edge = i in (0, b.shape[0] - 1) or j in (0, b.shape[1] - 1)
            est += b.counts[i, j] if edge and ox * oy > 0 else density[i, j] * ox * oy
        worst = max(worst, est)
        if reach >= 1e300:
            break
    return int(worst)


# --------------------------------------------------------------------------- the run

@dataclass
class _Params:
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
    scale_space: int = 0
    orient_k: int = 10

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
    how = params.orient
    if isinstance(how, str) and how == "auto":
        if source_aerial(src) and params.viewpoint is None and not file_normals:
            return "up"                      # as clcurv.job.orientation: PDAL's always_up
        if file_normals:
            return "auto"
        if params.viewpoint is not None:
            return "auto"
        if not op.signed:
            return "auto"
        how = "mst"
    return how


def source_aerial(src):
    return src.format in ("las", "laz")


def _workspace(dst, workdir):
    dst = Path(dst)
    return Path(workdir) if workdir is not None else dst.parent / f".{dst.name}.clcurv-tiles"


def _source_key(src):
    if isinstance(src, stream.Catalog):
        return [_source_key(p) for p in src.parts]
    st = os.stat(src.path)
    return {"path": str(Path(src.path).resolve()), "size": st.st_size,
            "mtime_ns": st.st_mtime_ns, "n": int(src.n)}


def _field_specs(method, precision, want_normals):
    """(name, width, dtype) of the stored fields, as clcurv.job.result_fields names them."""
    op = OPERATORS[method]
    real = np.float64
    specs = [(name, None, real) for name in op.file_fields()]
    specs += [("neighbours", None, np.int32), ("status", None, np.uint8)]
    if want_normals:
        specs.append(("normals", 3, np.float64))     # as the in-memory run writes them
    return specs


def curvature_file(src, dst, radius, *, method="mls2", weights="uniform", orient="auto",
                   viewpoint=None, kernel=None, h=None, scale_space=0, projections=0,
                   memory="auto", tile=None, workdir=None, fields=None,
                   ignore_normals=False, device=None, precision="float", progress=None,
                   out=None, client=None, workers=None):
    """Run ``method`` on the cloud of file ``src`` and write ``dst``, in tiles when the cloud
    does not fit the memory budget (see the module docstring).

    Parameters
    ----------
    src, dst : path
        Input LAS/LAZ or NPY; output LAS/LAZ (only from LAS/LAZ input: header and records
        kept) or NPZ. Non-tiled runs (the cloud fits) go through :func:`clcurv.job.run` and
        take every format it takes.
    radius : float
        Ball radius in the file's unit.
    method, weights, orient, viewpoint, kernel, h, device, precision
        As :func:`clcurv.curvature`; ``orient='auto'`` of a signed method without normals
        in the file or a viewpoint is MST propagation, which a tiled run refuses (use
        'up' for aerial data).
    memory : 'auto', int or str
        Host memory budget ('auto': half the available RAM). The run tiles when about
        N x IN_MEMORY_BYTES_PER_POINT exceeds it, or when ``tile`` is given.
    tile : float, optional
        Tile side in the file's unit (default: from the budget).
    workdir : path, optional
        Workspace folder (default: beside ``dst``); kept between an interrupted run and
        the same command run again (finished tiles are skipped), removed at the end.
    fields : list of str, optional
        The fields to write (as ``clcurv compute --fields``); default all and the normals.
    progress : callable(done, total, points) or None
        Called after each tile.
    client : dask.distributed.Client, optional
        Run the tiles on this cluster (:mod:`clcurv.cluster`; the workspace must be on a
        file system the workers share).
    workers : int, optional
        Run the tiles on a LocalCluster of this many worker processes.
    out : callable(str) or None
        Receives one line per stage (the CLI prints them).

    Returns
    -------
    dict
        ``tiled`` (bool), ``tiles``, ``points``, ``halo`` (cells), ``times`` (seconds per
        stage), ``status`` counts, ``dst``.
    """
    say = out or (lambda s: None)
    choice(method, "method", METHODS)
    r = as_radius(radius)
    catalog = isinstance(src, (list, tuple))
    if catalog:
        source = stream.Catalog(src)
        dst = _catalog_outputs(source, dst)
    else:
        dst = io.check_output(dst)
        source = stream.open_source(src)
    budget = budget_of(memory)
    if int(projections):
        raise TilingError("a tiled run does not take projections yet (iterated MLS2 moves "
                          "the points across tiles): run them in memory")
    if int(scale_space) < 0:
        raise ValueError(f"scale_space must be >= 0, got {scale_space}")
    for d in (dst if catalog else [dst]):
        ext = d.suffix.lower()
        if ext not in stream.STREAM_WRITES:
            raise TilingError(f"{d}: a tiled run writes {', '.join(stream.STREAM_WRITES)}")
        if ext in (".las", ".laz") and source.format not in ("las", "laz"):
            raise TilingError(f"{d}: a tiled run writes LAS/LAZ from LAS/LAZ input only (it "
                              "keeps the input's header); write .npz")
    params = _Params(method, r, weights, orient, viewpoint, kernel, h, device, precision,
                     bool(ignore_normals), int(scale_space))
    if not catalog and tile is None and fits_memory(source.n, budget) and client is None \
            and not workers:
        return _in_memory(src, dst, params, fields, say)
    ws = _workspace(dst[0].parent / ".catalog" if catalog else dst, workdir)
    return _run(source, dst, params, budget, tile, ws, fields, progress, say, client,
                workers)


def _catalog_outputs(source, dst):
    """The output path of every file of a catalog: ``dst`` (an existing folder) / the
    input's name (an NPY input's as .npz); never an input itself."""
    folder = Path(dst)
    if not folder.is_dir():
        raise TilingError(f"{dst}: the output of a catalog (several input files) is an "
                          "existing folder, one output file per input")
    outs = []
    inputs = {Path(p).resolve() for p in source.paths}
    for p in source.paths:
        p = Path(p)
        out = folder / (p.name if p.suffix.lower() != ".npy" else p.stem + ".npz")
        if out.resolve() in inputs:
            raise TilingError(f"{out} would replace the input file of that name: choose "
                              "another output folder")
        outs.append(io.check_output(out))
    if len({o.resolve() for o in outs}) != len(outs):
        raise TilingError("two input files have the same name: their outputs would collide")
    return outs


def _manifest(ws, source, params, budget, tile):
    return {"version": 1, "source": _source_key(source), "params": params.key(),
            "tile": tile, "budget": budget if tile is None else None}


def _prepare(ws, source, params, budget, tile, say):
    """Pass (1), or its state from an interrupted run with the same manifest."""
    want = _manifest(ws, source, params, budget, tile)
    mf = ws / "manifest.json"
    if mf.exists():
        try:
            have = json.loads(mf.read_text())
        except ValueError:
            have = None
        if have and have.get("key") == want and have.get("buckets"):
            say(f"resuming from {ws}")
            return Buckets.from_state(ws / "buckets", have["buckets"]), have, False
    if ws.exists():
        shutil.rmtree(ws)
    (ws / "buckets").mkdir(parents=True)
    target = max(budget // TILE_BYTES_PER_POINT, 1)
    origin, side, shape = _bucket_grid(source, target)
    b = Buckets(ws / "buckets", origin, side, shape, source.has_normals)
    for start, xyz, nrm in source.chunks(READ_CHUNK):
        b.add(start, xyz, nrm)
    if source.n == 0:
        raise TilingError(f"{source.path}: no points")
    state = {"key": want, "buckets": b.state()}
    _write_json(mf, state)
    return b, state, True


def _write_json(path, obj):
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(obj))
    os.replace(tmp, path)


def _run(source, dst, params, budget, tile, ws, wanted, progress, say, client=None,
         workers=None):
    times = {}
    t0 = time.perf_counter()
    try:
        buckets, state, fresh = _prepare(ws, source, params, budget, tile, say)
        times["bucketing"] = time.perf_counter() - t0
        file_normals = (buckets.normals_finite and "n" in buckets.dtype.names
                        and not params.ignore_normals)
        how = _orientation(params, source, file_normals)
        halo = halo_cells(params.method, params.weights, file_normals)
        specs = _wanted_specs(params, wanted)
        if not params.scale_space:
            tiling = plan_tiles(buckets, params.radius, halo, budget, tile)
    except (io.ReadError, ValueError):
        # bad input or options: the same command cannot succeed, so nothing is kept to
        # resume from (an interruption or a failure while computing keeps the workspace)
        shutil.rmtree(ws, ignore_errors=True)
        raise
    smoothed = None
    if params.scale_space:
        from .tiled_scale import run_steps
        t_s = time.perf_counter()
        smoothed = run_steps(ws, buckets, params, params.scale_space, budget,
                             lambda tasks: _execute(tasks, client, workers, step=True),
                             tile=tile)
        times["scale space"] = time.perf_counter() - t_s
        frame = Frame.covering(*smoothed.box, params.radius)
        tiling = plan_tiles(buckets, params.radius, halo, budget, tile, frame=frame)
    (ws / "tiles").mkdir(exist_ok=True)
    say(f"{source.n} points in {tiling.count} tile(s) of {tiling.size} x {tiling.size} "
        f"cells of {tiling.frame.cell:.6g} (halo {halo} cell(s)), budget "
        f"{budget / 2**20:.0f} MiB")
    todo = [t for t in range(tiling.count) if not _tile_file(ws, t).exists()]
    skipped = tiling.count - len(todo)
    tasks = [TileTask(str(ws), t, tiling, state["buckets"], params, how, file_normals,
                      specs, smoothed) for t in todo]
    t1 = time.perf_counter()
    computed, finished = 0, skipped
    for _, owned in _execute(tasks, client, workers):
        computed += owned
        finished += 1
        _trim()
        if progress is not None:
            progress(finished, tiling.count, computed)
    times["tiles"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    mst = isinstance(how, str) and how == "mst"
    windows = _partition(ws, source.n, tiling.count, specs, mst)
    if mst:
        _reconcile_mst(ws, windows, tiling.count, params.method)
    _trim()
    times["merging"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    _write_output(dst, source, windows, specs)
    times["writing"] = time.perf_counter() - t3
    shutil.rmtree(ws, ignore_errors=True)
    return {"tiled": True, "tiles": tiling.count, "skipped": skipped,
            "tile_cells": tiling.size, "halo": halo,
            "points": source.n, "times": times, "status": windows.status.tolist(),
            "dst": dst}


def _trim():
    """Give the heap's free pages back to the system (glibc keeps them after a tile's
    large temporaries, and the next pass would run on top of them)."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _wanted_specs(params, wanted):
    want_normals = not wanted or "normals" in wanted
    specs = _field_specs(params.method, params.precision, want_normals)
    if wanted:
        names = {s[0] for s in specs} | {"normals"}
        unknown = sorted(set(wanted) - names)
        if unknown:
            raise ValueError(f"unknown field(s) {', '.join(unknown)} for method "
                             f"{params.method}; available: {', '.join(sorted(names))}")
        specs = [s for s in specs if s[0] in wanted]
    return specs


def _tile_file(ws, t):
    return Path(ws) / "tiles" / f"{t}.npy"


#: points per id window of the merge (its records are what the writing pass holds; a
#: multiple of READ_CHUNK, so a written chunk never spans two windows)
WINDOW = 1 << 18


class Windows:
    """The tiles' records regrouped by windows of WINDOW consecutive global ids (one file
    each), read back one window at a time in input order: the writing pass holds one
    window, never the whole cloud's fields (no memory maps either: their pages would stay
    in the resident set)."""

    def __init__(self, folder, n, dtype):
        self.folder, self.n, self.dtype = Path(folder), n, dtype
        self.count = -(-n // WINDOW)
        self.status = np.zeros(4, np.int64)
        self._w, self._rec = -1, None
        self.transform = None           # applied to a copy of the rows given out

    def path(self, w):
        return self.folder / f"w{w}.bin"

    def halo_path(self, w):
        return self.folder / f"h{w}.bin"

    def window(self, w):
        """The records of window w, indexed by id - w * WINDOW; RuntimeError unless every
        id of the window is there exactly once (a bug, never a silently partial output)."""
        if w != self._w:
            lo, hi = w * WINDOW, min(self.n, (w + 1) * WINDOW)
            p = self.path(w)
            rec = np.fromfile(p, self.dtype) if p.exists() else np.empty(0, self.dtype)
            seen = np.bincount(rec["id"] - lo, minlength=hi - lo)
            if len(seen) != hi - lo or not np.all(seen == 1):
                raise RuntimeError(
                    f"the tiles wrote ids {lo}..{hi - 1} wrongly: "
                    f"{int(np.count_nonzero(seen[:hi - lo] == 0))} missing, "
                    f"{int(np.count_nonzero(seen > 1))} more than once")
            out = np.empty(hi - lo, self.dtype)
            out[rec["id"] - lo] = rec
            self._w, self._rec = w, out
        return self._rec

    def rows(self, start, stop):
        """The records of ids start..stop-1 (may span windows)."""
        parts = []
        while start < stop:
            w = start // WINDOW
            rec = self.window(w)
            end = min(stop, (w + 1) * WINDOW)
            parts.append(rec[start - w * WINDOW:end - w * WINDOW])
            start = end
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return self.transform(out.copy()) if self.transform is not None else out


def _to_windows(rec, path_of):
    """Append the records ``rec`` (with an 'id') to the files of their id windows."""
    w = rec["id"] // WINDOW
    order = np.argsort(w, kind="stable")
    w, rec = w[order], rec[order]
    cuts = np.flatnonzero(np.diff(w)) + 1
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(rec)]):
        with open(path_of(int(w[a])), "ab") as f:
            rec[a:b].tofile(f)


def _partition(ws, n, count, specs, mst=False):
    """Pass (3a): the tile files' records appended to the id windows' files (and, for MST
    orientation, the halo records to the windows' halo files)."""
    dtype = _tile_dtype(specs, mst)
    win = Windows(Path(ws) / "windows", n, dtype)
    if win.folder.exists():
        shutil.rmtree(win.folder)
    win.folder.mkdir()
    for t in range(count):
        rec = np.load(_tile_file(ws, t))
        if "status" in rec.dtype.names and len(rec):
            win.status += np.bincount(rec["status"], minlength=4)[:4]
        if len(rec):
            _to_windows(rec, win.path)
        if mst:
            halo = np.load(_tile_file(ws, t).with_suffix(".halo.npy"))
            if len(halo):
                _to_windows(halo, win.halo_path)
    return win


def _reconcile_mst(ws, windows, count, method):
    """Votes between tile components from the halo points and their owners, window by
    window; sets ``windows.transform`` to the final flips (clcurv.tiled_orient)."""
    from .tiled_orient import HALO_DTYPE, flip_fields, flip_mask, reconcile
    votes = {}
    for w in range(windows.count):
        hp = windows.halo_path(w)
        if not hp.exists():
            continue
        halo = np.fromfile(hp, HALO_DTYPE)
        own = windows.window(w)[halo["id"] - w * WINDOW]
        ok = own["node"] >= 0
        halo, own = halo[ok], own[ok]
        agree = np.einsum("ij,ij->i", halo["nl"].astype(np.float64),
                          own["nl"].astype(np.float64)) >= 0
        a, b = np.minimum(halo["node"], own["node"]), np.maximum(halo["node"], own["node"])
        keys = np.stack([a, b, agree.astype(np.int64)], axis=1)
        uniq, cnt = np.unique(keys, axis=0, return_counts=True)
        for (x, y, g), c in zip(uniq.tolist(), cnt.tolist()):
            if x != y:
                votes[(x, y)] = votes.get((x, y), 0) + (c if g else -c)
    sums = [np.load(_tile_file(ws, t).with_suffix(".nodes.npy")) for t in range(count)]
    flips, centroid, small = reconcile(sums, votes)
    windows.transform = lambda rec: flip_fields(rec, flip_mask(rec, flips, centroid, small),
                                                method)


def fits_memory(n, budget):
    """Does an in-memory run of ``n`` points fit ``budget`` bytes?"""
    return n * IN_MEMORY_BYTES_PER_POINT <= budget


def _in_memory(src, dst, params, fields, say):
    """The cloud fits: the in-memory file job (clcurv.job.run)."""
    from .job import Job, run
    orient = params.orient
    if not isinstance(orient, str) and orient is not None:
        raise TilingError("a direction orient= is for tiled runs and the API; the file job "
                          "takes 'auto', 'mst', 'up' or None")
    job = Job(src, dst, method=params.method, radius=params.radius, weights=params.weights,
              kernel=params.kernel, h=params.h, device=params.device,
              precision=params.precision, fields=fields, viewpoint=params.viewpoint,
              orient="none" if orient is None else orient,
              ignore_normals=params.ignore_normals, scale_space=params.scale_space,
              quiet=True)
    t0 = time.perf_counter()
    done = run(job, out=lambda line: None)
    return {"tiled": False, "tiles": 1, "halo": 0, "points": len(done.points),
            "times": {"in memory": time.perf_counter() - t0},
            "status": np.bincount(done.result.status, minlength=4).tolist(), "dst": dst}


@dataclass
class TileTask:
    """What a worker needs to compute one tile (small: no arrays; the worker reads the
    buckets from the workspace, on a file system it shares with the client)."""
    ws: str
    t: int
    tiling: Tiling
    buckets: dict
    params: _Params
    how: object
    file_normals: bool
    specs: list
    smoothed: object = None      # clcurv.tiled_scale.State after a scale space


def compute_tile(task, device=None):
    """Compute tile ``task.t`` and write its own points' fields (with their global ids) to
    the workspace, atomically; returns (t, points owned)."""
    from .api import curvature
    from .cloud import DeviceCloud
    from .job import result_fields
    params, tiling = task.params, task.tiling
    buckets = Buckets.from_state(Path(task.ws) / "buckets", task.buckets)
    rec = buckets.gather(tiling, task.t, state=task.smoothed)
    pos = rec["p"] if task.smoothed is None or not len(rec) else task.smoothed.key(rec)
    cells = tiling.frame.cells_of(pos) if len(rec) else np.empty((0, 3), np.int64)
    own = _within(cells, tiling.cells(task.t, halo=False))
    mst = isinstance(task.how, str) and task.how == "mst"
    out = np.empty(int(own.sum()), _tile_dtype(task.specs, mst))
    if len(out):
        if device is None:
            device = _worker_device(params.device)
        cloud = DeviceCloud(pos, params.radius, device=device,
                            precision=params.precision, frame=tiling.frame)
        normals, how = (rec["n"] if task.file_normals else None), task.how
        if mst:
            nl, node = tiled_orient.orient_tile(cloud, params.radius, params.orient_k,
                                                task.t, tiling.frame.origin)
            normals = np.where(node[:, None] >= 0, nl, (0.0, 0.0, 1.0))
            how = "normals"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # per tile; summed at the end
            res = curvature(cloud, params.radius, method=params.method,
                            weights=params.weights, normals=normals, orient=how,
                            viewpoint=params.viewpoint, kernel=params.kernel, h=params.h)
        f = result_fields(res)
        f["normals"] = res.normals
        out["id"] = rec["id"][own]
        for name, _, _ in task.specs:
            out[name] = f[name][own]
        if mst:
            _mst_records(task, out, own, pos, nl, node, rec["id"])
    elif mst:
        _mst_records(task, out, np.zeros(0, bool), np.empty((0, 3)), np.empty((0, 3)),
                     np.empty(0, np.int64), np.empty(0, np.int64))
    path = _tile_file(task.ws, task.t)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, out)
    os.replace(tmp, path)
    return task.t, len(out)


def _mst_records(task, out, own, pos, nl, node, ids):
    """The MST fields of a tile's own records, its halo records and its node sums."""
    o = np.asarray(task.tiling.frame.origin)
    if len(out):
        out["node"], out["nl"] = node[own], nl[own]
        out["pd"] = np.einsum("ij,ij->i", np.nan_to_num(nl[own]), pos[own] - o)
    halo = ~own & (node >= 0)
    h = np.empty(int(halo.sum()), tiled_orient.HALO_DTYPE)
    h["id"], h["node"], h["nl"] = ids[halo], node[halo], nl[halo]
    base = _tile_file(task.ws, task.t)
    for suffix, arr in ((".halo.npy", h), (".nodes.npy", tiled_orient.node_sums(
            pos[own], nl[own], node[own], o) if len(out) else
            np.empty(0, tiled_orient.SUMS_DTYPE))):
        path = base.with_suffix(suffix)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, arr)
        os.replace(tmp, path)


def _tile_dtype(specs, mst=False):
    from .tiled_orient import NODE_FIELDS
    return np.dtype([("id", "<i8")] + [(name, dtype) if width is None else
                                       (name, dtype, (width,)) for name, width, dtype in specs]
                    + (NODE_FIELDS if mst else []))


_DEVICES = {}


def _worker_device(spec):
    """The device of this process (one OpenCL context per process): the one the Dask
    worker plugin chose (:class:`ClcurvWorker`), else ``spec``."""
    try:
        from distributed import get_worker
        chosen = getattr(get_worker(), "clcurv_device", None)
    except (ImportError, ValueError):
        chosen = None
    key = chosen if chosen is not None else spec
    if key not in _DEVICES:
        from .device import get_device
        _DEVICES[key] = get_device(key)
    return _DEVICES[key]


def _execute(tasks, client, workers, step=False):
    """fn(task) of every task as it finishes (fn: compute_tile, or the scale space's
    step_tile when ``step``): in this process, on a Dask ``client``, or on a LocalCluster
    of ``workers`` processes started (and closed) here."""
    if step:
        from .tiled_scale import step_tile as fn
    else:
        fn = compute_tile
    if client is None and not workers:
        for task in tasks:
            yield fn(task)
        return
    from . import cluster
    yield from cluster.map_tiles(fn, tasks, client=client, workers=workers)


def _write_output(dst, source, windows, specs):
    """Pass (3b): the output in input order, a window at a time, atomically (a catalog:
    one output per input file, each with its own points)."""
    if isinstance(source, stream.Catalog):
        for part, off, d in zip(source.parts, source.offsets, dst):
            rows = (lambda o: lambda a, b: windows.rows(o + a, o + b))(int(off))
            _write_one(d, part, rows, part.n, specs)
        return
    _write_one(dst, source, windows.rows, windows.n, specs)


def _write_one(dst, source, rows, n, specs):
    names = [name for name, _, _ in specs]
    with io.atomic_output(dst) as tmp:
        if dst.suffix.lower() in (".las", ".laz"):
            stream.write_las(tmp, source, names, rows, chunk=READ_CHUNK)
        elif dst.suffix.lower() == ".ply":
            stream.write_ply(tmp, source, names, rows, n,
                             {name: (width, dtype) for name, width, dtype in specs},
                             chunk=READ_CHUNK)
        else:
            stream.write_npz(tmp, source, names, rows, n,
                             {name: (width, dtype) for name, width, dtype in specs},
                             chunk=READ_CHUNK)


# --------------------------------------------------------------------------- the file job

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
    if job.projections or job.positions != "original":
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
    import tempfile
    from scipy.spatial import cKDTree
    with tempfile.TemporaryDirectory(prefix="clcurv-radius-") as tmp:
        target = max((budget or (1 << 28)) // (TILE_BYTES_PER_POINT * 9), 10_000)
        origin, side, shape = _bucket_grid(src, target * BUCKETS_PER_TILE ** 2)
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
                             f"neighbours; give the radius")
        return r


def run_job(job, out=print):
    """The file job ``job`` in tiles (:func:`curvature_file`); prints a summary on ``out``
    and returns the summary dict."""
    from .job import ORIENT_CHOICES, UsageError
    if job.radius == "auto" or job.radius is None:
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
    client = None
    if job.scheduler:
        from .cluster import _import
        client = _import().Client(job.scheduler)
    bar = None
    if not job.quiet:
        from tqdm import tqdm
        bar = tqdm(desc="tiles", unit="tile", file=sys.stderr, leave=True)

    def progress(done, total, points):
        if bar is not None:
            if bar.total != total:
                bar.reset(total=total)
            bar.set_postfix_str(f"{points} points", refresh=False)
            bar.update(done - bar.n)
    try:
        summary = curvature_file(
            job.input, job.output, float(job.radius), method=job.method,
            weights=job.weights, orient=ORIENT_CHOICES.get(job.orient, job.orient),
            viewpoint=job.viewpoint, kernel=job.kernel, h=job.h,
            scale_space=job.scale_space, projections=job.projections, memory=job.memory,
            tile=job.tile_size, fields=job.fields, ignore_normals=job.ignore_normals,
            device=job.device, precision=job.precision, progress=progress,
            out=None if job.quiet else (lambda s: print(s, file=sys.stderr)),
            client=client, workers=job.workers)
    except TilingError as exc:
        raise UsageError(str(exc)) from exc
    finally:
        if bar is not None:
            bar.close()
        if client is not None:
            client.close()
    times = ", ".join(f"{k} {v:.2f} s" for k, v in summary["times"].items())
    st = summary["status"] or []
    ok = st[0] / max(sum(st), 1) if st else float("nan")
    what = (f"{len(job.input)} files" if isinstance(job.input, (list, tuple))
            else job.input)
    out(f"\n{summary['points']} points from {what} in {summary['tiles']} tile(s) "
        f"(halo {summary['halo']} cell(s)); status ok {ok:.1%}")
    out(f"time: {times}")
    out(f"wrote {job.output}")
    return summary
