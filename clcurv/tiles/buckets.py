"""Pass (1) of a tiled run (:mod:`clcurv.tiles.engine`): the points, with their global ids, filed
in on-disk buckets of a coarse x-y grid, and read back per tile."""
from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv.io import stream
from clcurv.tiles.planning import occupancy, within
from clcurv.tiles.workspace import Crc, CorruptWorkspace, check_records

#: points per read chunk of pass (1) and per written chunk of pass (3)
READ_CHUNK = 1 << 18


#: most buckets of pass (1) (a coarse grid; each is a file)
MAX_BUCKETS = 4096


#: tiles per side of a bucket: buckets are this many times smaller than a tile, so a tile
#: reads little more than its own cells and halo
BUCKETS_PER_TILE = 2


class Buckets:
    """Pass (1): the points, with their global ids (and the file's normals), appended to the
    files of a coarse x-y grid of ``side`` from ``origin`` (indices clamped to the grid, so
    a point outside the expected box still lands in an edge bucket); exact bounds and
    counts taken on the way.

    The points come in *parts* (:func:`clcurv.io.stream.parts_of`: the files of a catalog,
    ranges of a large file), each filed by its own writer (a worker, :func:`bucket_part`)
    in its own folder ``p<k>``; :meth:`merge` joins their states. A bucket's records are
    read part after part (:meth:`blocks`): parts are in global-id order, so they come in
    the order one writer of the whole cloud would have appended them."""

    def __init__(self, folder, origin, side, shape, normals, part=0):
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
        self.part = int(part)        # the part this writer files (:meth:`add`)
        self.parts = [self.part]     # the parts read, in order
        self.crc = Crc()             # count and CRC-32 of every bucket file, "k/i_j"

    def _index(self, xy):
        ij = np.floor((xy - self.origin) / self.side).astype(np.int64)
        np.clip(ij[:, 0], 0, self.shape[0] - 1, out=ij[:, 0])
        np.clip(ij[:, 1], 0, self.shape[1] - 1, out=ij[:, 1])
        return ij

    def path(self, i, j, part=None):
        k = self.part if part is None else part
        return self.folder / f"p{k}" / f"b{i}_{j}.bin"

    @staticmethod
    def _key(k, i, j):
        return f"{k}/{i}_{j}"

    def _parts_of(self, i, j):
        """The parts that filed points in bucket (i, j), in order."""
        return [k for k in self.parts if self._key(k, i, j) in self.crc.sums]

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
        self.path(0, 0).parent.mkdir(parents=True, exist_ok=True)
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, m]):
            i, j = divmod(int(flat[a]), self.shape[1])
            with open(self.path(i, j), "ab") as f:
                rec[a:b].tofile(f)
            self.counts[i, j] += b - a
            self.crc.add(self._key(self.part, i, j), rec[a:b])

    def overlapping(self, lo, hi):
        """(i, j) of the non-empty buckets that may hold points of the box [lo, hi) (x-y)."""
        ij = self._index(np.array([lo, hi], float))
        i0, j0 = int(ij[0, 0]), int(ij[0, 1])
        for i, j in np.argwhere(self.counts[i0:ij[1, 0] + 1, j0:ij[1, 1] + 1] > 0):
            yield i0 + int(i), j0 + int(j)

    def nonempty(self):
        """(i, j) of the non-empty buckets, in order (their number, not the grid's, is what
        a loop over the buckets costs)."""
        for i, j in np.argwhere(self.counts > 0):
            yield int(i), int(j)

    def gather(self, tiling, t, block=1 << 18, state=None):
        """The records of the points in tile t's cells and halo, in global-id order.

        ``state`` (a :class:`clcurv.tiles.scale.State`) joins each record with its row of
        the scale space's state and places the points by ``state.key`` (their binned or
        smoothed positions, within ``state.margin`` of the original ones) instead of by
        their original positions."""
        lo, hi = tiling.box(t)
        if state is not None:
            lo, hi = np.subtract(lo, state.margin), np.add(hi, state.margin)
        rng = tiling.cells(t)
        parts = []
        for i, j in self.overlapping(lo, hi):
            for rec, pos in self.blocks(i, j, state, block):
                keep = within(tiling.frame.cells_of(pos), rng)
                if keep.any():
                    parts.append(rec[keep])
        if not parts:
            return np.empty(0, self._dtype(state))
        rec = np.concatenate(parts)
        return rec[np.argsort(rec["id"], kind="stable")]

    def blocks(self, i, j, state=None, block=1 << 18):
        """The records of bucket (i, j) in blocks of ``block``, with their positions: the
        original ones, or (``state``) joined with their state rows and placed by
        ``state.key``. Part after part, each file checked against its count and CRC."""
        rows = _Rows(state.rows(self, i, j, block)) if state is not None else None
        start = 0
        for k in self._parts_of(i, j):
            path = self.path(i, j, k)
            check = Crc()
            if not path.exists():
                raise CorruptWorkspace(path, "missing")
            with open(path, "rb") as f:
                while True:
                    rec = np.fromfile(f, self.dtype, count=block)
                    check.add("", rec)
                    if not len(rec):
                        self._verify(i, j, k, check)
                        break
                    if rows is not None:
                        rec = state.join(rec, rows.take(len(rec)), i * self.shape[1] + j,
                                         start)
                    start += len(rec)
                    yield rec, (state.key(rec) if state is not None else rec["p"])

    def split(self, tiling, folder, state=None, block=1 << 18, part=None):
        """Pass (1b): every point appended to the input file of each tile whose cells or
        halo hold it (records of :meth:`tile_dtype` with ``own`` = 1 in the tile that owns
        it), so a tile then reads exactly its points: the points of each part apart, in
        ``folder``/p<k>/<t>.bin (``part``: that part only, the task of one worker), or,
        with a scale-space ``state`` (as in :meth:`gather`; its rows are those of whole
        buckets), all parts together in ``folder``/s/<t>.bin.

        Returns {tile: {file key: [count, CRC-32, points owned]}} of the files written:
        its keys are the tiles that hold points (:meth:`clcurv.tiles.planning.Tiling.occupied`),
        a pass that costs O(points) whatever the number of tiles of the frame (tile ids are
        int64: one far point makes them large)."""
        folder = Path(folder)
        if state is not None:
            return self._split(tiling, folder, "s", self.parts, state, block)
        sums = {}
        for k in (self.parts if part is None else [part]):
            merge_sums(sums, self._split(tiling, folder, f"p{k}", [k], None, block))
        return sums

    def _split(self, tiling, folder, key, parts, state, block):
        out = folder / key
        out.mkdir(parents=True, exist_ok=True)
        size, h = tiling.size, tiling.halo
        ntx, nty = tiling.shape
        dtype = self.tile_dtype(state)
        crc, owned = Crc(), {}
        view = self if parts == self.parts else self._only(parts)
        for i, j in view.nonempty():
            for rec, pos in view.blocks(i, j, state, block):
                self._scatter(rec, tiling.frame.cells_xy(pos), size, h, ntx, nty,
                              dtype, out, crc, owned)
        return {t: {key: v + [owned.get(t, 0)]} for t, v in crc.state().items()}

    def _only(self, parts):
        """This grid restricted to ``parts`` (its counts those of the parts' files)."""
        b = Buckets.from_state(self.folder, self.state())
        b.parts = list(parts)
        b.counts = np.zeros(self.shape, np.int64)
        for key, (n, _) in self.crc.sums.items():
            k, ij = key.split("/")
            if int(k) in b.parts:
                i, j = map(int, ij.split("_"))
                b.counts[i, j] += n
        return b

    @staticmethod
    def _scatter(rec, c, size, h, ntx, nty, dtype, folder, crc=None, owned=None):
        """Append the records ``rec`` (x-y cells ``c``) to the files of the tiles whose
        reach [t size - h, (t + 1) size + h) holds them: the owner and, within h cells of
        its edges, its neighbours (h <= size)."""
        own_t = c // size
        local = c - own_t * size                  # cell within the owner tile, 0..size-1
        side = {-1: local < h, 0: None, 1: local >= size - h}   # near which edges
        ts = [own_t[:, 0] + ntx * own_t[:, 1]]
        sels = [np.arange(len(c))]
        owns = [np.ones(len(c), np.uint8)]
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx == dy == 0:
                    continue
                near = [m for m in ((side[dx][:, 0] if dx else None),
                                    (side[dy][:, 1] if dy else None)) if m is not None]
                sel = np.flatnonzero(near[0] & near[1] if len(near) == 2 else near[0])
                tx, ty = own_t[sel, 0] + dx, own_t[sel, 1] + dy
                ok = (tx >= 0) & (tx < ntx) & (ty >= 0) & (ty < nty)
                ts.append((tx + ntx * ty)[ok])
                sels.append(sel[ok])
                owns.append(np.zeros(int(ok.sum()), np.uint8))
        t, sel, own = np.concatenate(ts), np.concatenate(sels), np.concatenate(owns)
        order = np.argsort(t, kind="stable")
        t, sel, own = t[order], sel[order], own[order]
        out = np.empty(len(sel), dtype)
        for name in rec.dtype.names:
            out[name] = rec[name][sel]
        out["own"] = own
        cuts = np.flatnonzero(np.diff(t)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
            with open(folder / f"{int(t[a])}.bin", "ab") as f:
                out[a:b].tofile(f)
            if crc is not None:
                crc.add(str(int(t[a])), out[a:b])
            if owned is not None:
                key = str(int(t[a]))
                owned[key] = owned.get(key, 0) + int(own[a:b].sum())

    def read(self, i, j):
        """The records of bucket (i, j), checked against the sums taken when written."""
        parts = [rec for rec, _ in self.blocks(i, j, block=-1)]
        return np.concatenate(parts) if parts else np.empty(0, self.dtype)

    def _verify(self, i, j, k, check):
        """CorruptWorkspace unless the count and CRC in ``check`` (a :class:`Crc` of the
        whole file of part k read) are those written."""
        have = check.sums.get("", [0, 0])
        want = self.crc.sums.get(self._key(k, i, j), [0, 0])
        if list(have) != list(want):
            raise CorruptWorkspace(self.path(i, j, k), f"{have[0]} records where {want[0]} "
                                   "were written, or their CRC-32 differs (changed on disk)")

    def tile_dtype(self, state=None):
        """The records of a tile's input file (:meth:`split`)."""
        return np.dtype(self._dtype(state).descr + [("own", "u1")])

    def read_tile(self, folder, t, state=None, expect=None):
        """The records of tile t's input files in global-id order (none: empty), each
        checked against ``expect`` ({file key: [count, CRC-32, ...]} taken by
        :meth:`split`; CorruptWorkspace)."""
        dt = self.tile_dtype(state)
        parts = []
        for key, want in sorted((expect or {}).items()):
            path = Path(folder) / key / f"{t}.bin"
            rec = np.fromfile(path, dt) if path.exists() else np.empty(0, dt)
            check_records(path, rec, want[:2])
            parts.append(rec)
        if not parts:
            return np.empty(0, dt)
        rec = np.concatenate(parts) if len(parts) > 1 else parts[0]
        return rec[np.argsort(rec["id"], kind="stable")]

    def _dtype(self, state):
        return self.dtype if state is None else state.joined_dtype(self.dtype)

    def state(self, parts=None):
        """The picklable state (:meth:`from_state`); ``parts``: of those parts only (their
        files' sums: a task's, which reads no other part's files; [] for none)."""
        crc = self.crc.state()
        if parts is not None:
            keep = {str(k) for k in parts}
            crc = {key: v for key, v in crc.items() if key.split("/")[0] in keep}
        return {"origin": self.origin.tolist(), "side": self.side, "shape": list(self.shape),
                "counts": self.counts.tolist(), "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "normals_finite": self.normals_finite,
                "normals": "n" in self.dtype.names, "crc": crc,
                "part": self.part, "parts": list(self.parts if parts is None else parts)}

    @classmethod
    def from_state(cls, folder, s):
        b = cls(folder, s["origin"], s["side"], tuple(s["shape"]), s["normals"],
                s.get("part", 0))
        b.counts = np.asarray(s["counts"], np.int64).reshape(b.shape)
        b.lo, b.hi = np.asarray(s["lo"]), np.asarray(s["hi"])
        b.normals_finite = s["normals_finite"]
        b.crc = Crc(s.get("crc"))
        b.parts = list(s.get("parts", [b.part]))
        return b

    @classmethod
    def merge(cls, folder, states):
        """The buckets of every part, from the states of their writers (in any order)."""
        states = sorted(states, key=lambda s: s["part"])
        b = cls.from_state(folder, states[0])
        for s in states[1:]:
            b.counts += np.asarray(s["counts"], np.int64).reshape(b.shape)
            b.lo, b.hi = np.minimum(b.lo, s["lo"]), np.maximum(b.hi, s["hi"])
            b.normals_finite = b.normals_finite and s["normals_finite"]
            b.crc.sums.update(Crc(s["crc"]).sums)
        b.parts = [s["part"] for s in states]
        return b


class _Rows:
    """Rows taken from the blocks of an iterator ``it`` a given number at a time (a
    bucket's state rows, whose blocks do not end where its parts' files end)."""

    def __init__(self, it):
        self.it, self.buf = it, None

    def take(self, m):
        out = []
        while m > 0:
            if self.buf is None or not len(self.buf):
                self.buf = next(self.it, None)
                if self.buf is None:
                    break
            out.append(self.buf[:m])
            self.buf = self.buf[m:]
            m -= len(out[-1])
        return out[0] if len(out) == 1 else (np.concatenate(out) if out else np.empty(0))


def merge_sums(into, sums):
    """Add the split sums ``sums`` ({tile: {file key: [...]}}) to ``into``."""
    for t, files in sums.items():
        into.setdefault(t, {}).update(files)
    return into


def bucket_part(task):
    """Pass (1) of one part, on a worker: read ``task.part`` (a
    :class:`clcurv.io.stream.Part`) from its file and file its points in the buckets of
    ``task.grid`` ((origin, side, shape)) under ``task.folder``; returns the writer's
    state (for :meth:`Buckets.merge`)."""
    origin, side, shape = task.grid
    b = Buckets(task.folder, origin, side, tuple(shape), task.part.normals, task.t)
    shutil.rmtree(b.path(0, 0).parent, ignore_errors=True)     # a retried task's files
    for start, xyz, nrm in stream.read_part(task.part, READ_CHUNK):
        b.add(start, xyz, nrm)
    return b.state()


@dataclass
class BucketTask:
    """Pass (1) of part number ``t`` (:func:`bucket_part`)."""
    folder: str
    t: int
    part: object
    grid: tuple


@dataclass
class SplitTask:
    """Pass (1b) of part number ``t`` (:func:`split_part`)."""
    folder: str
    t: int
    buckets: dict
    tiling: object
    out: str


@dataclass
class OccupancyTask:
    """The occupancy of part number ``t`` (:func:`occupancy_part`)."""
    folder: str
    t: int
    buckets: dict
    frame: object
    limit: int


def occupancy_part(task):
    """The :class:`clcurv.tiles.planning.Occupancy` of one part's points, on a worker (at
    most ``task.limit`` blocks: clcurv.tiles.planning.merge_occupancy joins them)."""
    b = Buckets.from_state(task.folder, task.buckets)._only([task.t])
    return occupancy(b, task.frame, limit=task.limit)


def split_part(task):
    """Pass (1b) of one part, on a worker (:meth:`Buckets.split`); returns its sums."""
    b = Buckets.from_state(task.folder, task.buckets)
    shutil.rmtree(Path(task.out) / f"p{task.t}", ignore_errors=True)   # a retried task's
    return b.split(task.tiling, task.out, part=task.t)


def bucket_grid(src, target_points):
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
