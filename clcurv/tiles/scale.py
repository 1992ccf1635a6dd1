"""The MLS1 scale space in tiles, step by step, equal to the in-memory run bit for bit.

The in-memory scale space (:mod:`clcurv.ops.smoothing`) keeps on the device, for every point,
the iterate (x in its three alignments, y, z, as float cell-relative numbers of the cell it
was binned in), the accumulated displacement ``d`` from the input, and the binned position
``pb`` of the last binning; the whole cloud is binned again (in the frame of the moved
cloud's bounding box) only when some point drifted more than ``MARGIN r`` from ``pb``.
Both the iterate's rounding and that decision depend on the whole cloud, so a tile cannot
run several steps on its own and agree with it. Instead the tiled engine runs the steps
in lock step over all tiles:

* the state of every point (``pb`` float64, the iterate and ``d`` in the device
  precision) is kept on disk beside the buckets of :mod:`clcurv.tiles.engine`, a file per bucket
  with the bucket's row order;
* each step is a pass over tiles of the binning's cells (cell h = (1 + 2 MARGIN) r, halo
  1 cell, 2 with density weights): a tile loads the exact state of its points and halo,
  rebuilds the device state (the binning of ``pb`` in the frame of the whole cloud, the
  iterate as stored), runs one step and writes its own points' new rows;
* between steps the client merges the rows, takes the largest drift of all points, and
  re-bins (``pb = p + d`` in float64, the frame of their bounding box) exactly when the
  in-memory run would.

The halo is one cell per step, never (N + 1) r: the state of every point is exact at the
start of each step, so nothing is certified after the fact. Points are found in the
buckets of their original position within ``margin`` = the largest displacement so far.
After the last step the operator runs in tiles of the smoothed positions ``p + d``.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv.grid.binning import Frame
from clcurv.ops.smoothing import MARGIN, DeviceState
from clcurv.runtime.memory import release_memory
from clcurv.tiles.buckets import Buckets
from clcurv.tiles.planning import covering, occupied_tiles, plan_tiles, within
from clcurv.tiles.workers import worker_device


def state_dtype(real):
    """One row of state: the binned position, the iterate (x in 3 alignments, y, z) and
    the displacement, in the device's precision ``real``."""
    return np.dtype([("pb", "<f8", (3,)), ("it", real, (5,)), ("d", real, (3,))])


@dataclass
class State:
    """The scale space's state files of a workspace, as :meth:`Buckets.gather` reads them:
    ``key`` is 'pb' (place points by their binned positions) or 'smoothed' (p + d)."""
    folder: str
    real: str
    key_name: str
    margin: float
    box: tuple = None          # bounding box of the smoothed positions (after the steps)

    @property
    def dtype(self):
        return state_dtype(np.dtype(self.real))

    def path(self, i, j):
        return Path(self.folder) / f"s{i}_{j}.bin"

    def rows(self, buckets, i, j, block):
        """The state rows of bucket (i, j), in blocks of ``block`` (as its records)."""
        with open(self.path(i, j), "rb") as f:
            while True:
                st = np.fromfile(f, self.dtype, count=block)
                if not len(st):
                    return
                yield st

    def joined_dtype(self, rec_dtype):
        return np.dtype(rec_dtype.descr + [("b", "<i8"), ("row", "<i8")] + self.dtype.descr)

    def join(self, rec, st, b, start):
        """The records ``rec`` of bucket ``b`` (rows start..) with their state rows ``st``."""
        if len(st) != len(rec):
            raise RuntimeError(f"the state of bucket {b} is out of step with its records")
        out = np.empty(len(rec), self.joined_dtype(rec.dtype))
        for name in rec.dtype.names:
            out[name] = rec[name]
        for name in st.dtype.names:
            out[name] = st[name]
        out["b"] = b
        out["row"] = np.arange(start, start + len(rec))
        return out

    def key(self, rec):
        if self.key_name == "pb":
            return rec["pb"]
        return rec["p"] + rec["d"].astype(np.float64)


def init_state(buckets, folder, real, block=1 << 18):
    """The state before the first step: pb = p, d = 0 (the iterate is the binning's)."""
    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    dt = state_dtype(np.dtype(real))
    for i in range(buckets.shape[0]):
        for j in range(buckets.shape[1]):
            if not buckets.counts[i, j]:
                continue
            with open(folder / f"s{i}_{j}.bin", "wb") as out:
                for rec, _ in buckets.blocks(i, j, block=block):    # checked
                    st = np.zeros(len(rec), dt)
                    st["pb"] = rec["p"]
                    st.tofile(out)


@dataclass
class StepTask:
    """One tile of one step (no arrays: the worker reads the workspace)."""
    ws: str
    t: int
    step: int
    tiling: object
    buckets: dict
    state: State
    fresh: bool
    radius: float
    precision: str
    device: object
    density: bool
    #: the step's tiles' input files (Buckets.split) and this tile's sums, when the
    #: buckets are too coarse for each tile to gather its points (:func:`run_steps`)
    split: str = None
    expect: list = None


#: a step splits the buckets into tile files (one pass) instead of letting each tile gather
#: its points from the buckets around it, when the gathers would read more than this many
#: times the points: buckets far larger than the tiles (one far point stretched the bucket
#: grid), which every tile would read whole
GATHER_FACTOR = 4


def _parts(ws, step):
    return Path(ws) / "parts" / str(step)


def step_tile(task):
    """One scale-space step of tile ``task.t``: its own points' new state rows go to part
    files (one per bucket they belong to); returns (t, largest drift of its points)."""
    buckets = Buckets.from_state(Path(task.ws) / "buckets", task.buckets)
    state = State(task.state.folder, task.state.real, "pb", task.state.margin)
    tiling = task.tiling
    if task.split is not None:
        rec = buckets.read_tile(task.split, task.t, state=state, expect=task.expect)
        own = rec["own"].astype(bool)
    else:
        rec = buckets.gather(tiling, task.t, state=state)
        own = within(tiling.frame.cells_of(rec["pb"]), tiling.cells(task.t, halo=False))
    out_dir = _parts(task.ws, task.step)
    if not len(rec):
        return task.t, 0.0
    drift = 0.0
    if own.any():
        device = worker_device(task.device)
        ping = None if task.fresh else rec["it"]
        st = DeviceState(rec["pb"], np.zeros_like(rec["pb"]), task.radius, device,
                         task.precision, task.density, frame=tiling.frame,
                         iterate=(ping, rec["d"]))
        drifts = np.zeros(len(rec))
        st.step(task.radius, task.density, drifts)
        it, d = st.iterate()
        mine = np.flatnonzero(own)
        drift = float(drifts[mine].max())
        dt = np.dtype([("row", "<i8"), ("it", it.dtype, (5,)), ("d", d.dtype, (3,))])
        b = rec["b"][mine]
        order = np.argsort(b, kind="stable")
        mine, b = mine[order], b[order]
        cuts = np.flatnonzero(np.diff(b)) + 1
        for a, e in zip(np.r_[0, cuts], np.r_[cuts, len(mine)]):
            sel = mine[a:e]
            part = np.empty(len(sel), dt)
            part["row"], part["it"], part["d"] = rec["row"][sel], it[sel], d[sel]
            path = out_dir / f"b{int(b[a])}.t{task.t}.bin"
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            part.tofile(tmp)
            os.replace(tmp, path)
        del st                  # as clcurv.tiles.engine.compute_tile: the budget holds per tile
        release_memory(device)
    return task.t, drift


def run_steps(ws, buckets, params, steps, budget, execute, progress=None, tile=None):
    """The ``steps`` scale-space steps over tiles (see the module docstring); leaves the
    final state in ``ws/state`` and returns the State to read smoothed positions from."""
    real = "<f4" if params.precision == "float" else "<f8"
    folder = Path(ws) / "state"
    r = params.radius
    h = r * (1 + 2 * MARGIN)
    # an extent too large for a grid key: the in-memory run's refusal (its first binning is
    # at h), then the operator's at r, before any step
    covering(buckets, h)
    covering(buckets, r)
    init_state(buckets, folder, real)
    density = params.weights == "density"
    halo = 2 if density else 1
    lo, hi = buckets.lo.copy(), buckets.hi.copy()
    moved = dmax = 0.0
    fresh = True
    for step in range(steps):
        frame = Frame.covering(lo, hi, h)
        state = State(str(folder), real, "pb", moved)
        tiling = plan_tiles(buckets, h, halo, budget, tile, frame=frame, state=state)
        _parts(ws, step).mkdir(parents=True, exist_ok=True)
        # the tiles that own points (one pass), never range(tiling.count): one far point
        # makes the frame's tiles astronomically many
        tiles = occupied_tiles(buckets, tiling, state)
        split, sums = None, {}
        if _gathered(buckets, tiling, tiles, state) > GATHER_FACTOR * buckets.counts.sum():
            split = _parts(ws, step) / ".tiles_in"           # (a dot: not a part file)
            sums = buckets.split(tiling, split, state=state)
        tasks = [StepTask(str(ws), int(t), step, tiling, buckets.state(), state, fresh, r,
                          params.precision, params.device, density,
                          None if split is None else str(split), sums.get(str(int(t))))
                 for t in tiles]
        drift = 0.0
        for _, most in execute(tasks):
            drift = max(drift, most)
        rebin = step < steps - 1 and drift > MARGIN * r      # as smoothing.scale_space
        lo, hi, moved, dmax, box = _apply(ws, buckets, state, step, rebin)
        fresh = rebin
        shutil.rmtree(_parts(ws, step), ignore_errors=True)
        if progress is not None:
            progress(step + 1, steps)
    return State(str(folder), real, "smoothed", dmax, box)


def _gathered(buckets, tiling, tiles, state):
    """The records the ``tiles`` would read in all, each gathering its points from the
    buckets that overlap it (:meth:`Buckets.gather`)."""
    total = 0
    for t in tiles:
        lo, hi = tiling.box(int(t))
        lo, hi = np.subtract(lo, state.margin), np.add(hi, state.margin)
        total += sum(int(buckets.counts[i, j]) for i, j in buckets.overlapping(lo, hi))
    return total


def _apply(ws, buckets, state, step, rebin):
    """Merge the parts of ``step`` into the state files (and re-bin: pb = p + d); returns
    the bounding box of pb, the largest |pb - p| and the largest |d| (for the margins), and
    the bounding box of the smoothed positions p + d."""
    parts = _parts(ws, step)
    by_bucket = {}
    for f in parts.iterdir():
        if not f.name.startswith("."):
            by_bucket.setdefault(int(f.name.split(".")[0][1:]), []).append(f)
    sdt = state.dtype
    pdt = np.dtype([("row", "<i8"), ("it", sdt["it"].base, (5,)), ("d", sdt["d"].base, (3,))])
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    slo, shi = lo.copy(), hi.copy()
    moved = dmax = 0.0
    for i in range(buckets.shape[0]):
        for j in range(buckets.shape[1]):
            if not buckets.counts[i, j]:
                continue
            b = i * buckets.shape[1] + j
            path = state.path(i, j)
            st = np.fromfile(path, sdt)
            for f in by_bucket.get(b, []):
                part = np.fromfile(f, pdt)
                st["it"][part["row"]] = part["it"]
                st["d"][part["row"]] = part["d"]
            rec = buckets.read(i, j)                    # checked against its sums
            d64 = st["d"].astype(np.float64)
            if rebin:
                st["pb"] = rec["p"] + d64
            smoothed = rec["p"] + d64
            slo = np.minimum(slo, smoothed.min(axis=0))
            shi = np.maximum(shi, smoothed.max(axis=0))
            lo = np.minimum(lo, st["pb"].min(axis=0))
            hi = np.maximum(hi, st["pb"].max(axis=0))
            moved = max(moved, float(np.abs(st["pb"] - rec["p"]).max()))
            dmax = max(dmax, float(np.abs(d64).max()))
            tmp = path.with_suffix(".tmp")
            st.tofile(tmp)
            os.replace(tmp, path)
    # margins in x-y: a point is searched within this distance of its original position
    return lo, hi, moved * 1.001 + 1e-12, dmax * 1.001 + 1e-12, (slo, shi)
