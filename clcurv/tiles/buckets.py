"""Pass (1) of a tiled run (:mod:`clcurv.tiles.engine`): the points, with their global ids, filed
in on-disk buckets of a coarse x-y grid, and read back per tile."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from clcurv.tiles.planning import within
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
        self.crc = Crc()             # count and CRC-32 of every bucket file

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
            self.crc.add(f"{i}_{j}", rec[a:b])

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
        ``state.key``."""
        rows = state.rows(self, i, j, block) if state is not None else None
        start = 0
        check = Crc()
        if not self.path(i, j).exists():
            raise CorruptWorkspace(self.path(i, j), "missing")
        with open(self.path(i, j), "rb") as f:
            while True:
                rec = np.fromfile(f, self.dtype, count=block)
                check.add("", rec)
                if not len(rec):
                    self._verify(i, j, check)
                    return
                if rows is not None:
                    rec = state.join(rec, next(rows), i * self.shape[1] + j, start)
                start += len(rec)
                yield rec, (state.key(rec) if state is not None else rec["p"])

    def split(self, tiling, folder, state=None, block=1 << 18):
        """Pass (1b): every point appended to the input file of each tile whose cells or
        halo hold it (``folder``/<t>.bin, records of :meth:`tile_dtype` with ``own`` = 1 in
        the tile that owns it), so a tile then reads exactly its points. ``state`` as in
        :meth:`gather`. Returns the (count, CRC-32) of every file written, by tile: their
        keys are the tiles that hold points (:meth:`clcurv.tiles.planning.Tiling.occupied`), a pass
        that costs O(points) whatever the number of tiles of the frame (tile ids are int64:
        one far point makes them large)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        size, h = tiling.size, tiling.halo
        ntx, nty = tiling.shape
        dtype = self.tile_dtype(state)
        crc = Crc()
        for i, j in self.nonempty():
            for rec, pos in self.blocks(i, j, state, block):
                self._scatter(rec, tiling.frame.cells_xy(pos), size, h, ntx, nty,
                              dtype, folder, crc)
        return crc.state()

    @staticmethod
    def _scatter(rec, c, size, h, ntx, nty, dtype, folder, crc=None):
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

    def read(self, i, j):
        """The records of bucket (i, j), checked against the sums taken when written."""
        path = self.path(i, j)
        rec = np.fromfile(path, self.dtype) if path.exists() else np.empty(0, self.dtype)
        check_records(path, rec, self.crc.sums.get(f"{i}_{j}"))
        return rec

    def _verify(self, i, j, check):
        """CorruptWorkspace unless the count and CRC in ``check`` (a :class:`Crc` of the
        whole file read) are those written."""
        have = check.sums.get("", [0, 0])
        want = self.crc.sums.get(f"{i}_{j}", [0, 0])
        if list(have) != list(want):
            raise CorruptWorkspace(self.path(i, j), f"{have[0]} records where {want[0]} "
                                   "were written, or their CRC-32 differs (changed on disk)")

    def tile_dtype(self, state=None):
        """The records of a tile's input file (:meth:`split`)."""
        return np.dtype(self._dtype(state).descr + [("own", "u1")])

    def read_tile(self, folder, t, state=None, expect=None):
        """The records of tile t's input file in global-id order (none: empty), checked
        against ``expect`` ((count, CRC-32) taken by :meth:`split`; CorruptWorkspace)."""
        path = Path(folder) / f"{t}.bin"
        dt = self.tile_dtype(state)
        rec = np.fromfile(path, dt) if path.exists() else np.empty(0, dt)
        check_records(path, rec, expect)
        return rec[np.argsort(rec["id"], kind="stable")]

    def _dtype(self, state):
        return self.dtype if state is None else state.joined_dtype(self.dtype)

    def state(self):
        return {"origin": self.origin.tolist(), "side": self.side, "shape": list(self.shape),
                "counts": self.counts.tolist(), "lo": self.lo.tolist(),
                "hi": self.hi.tolist(), "normals_finite": self.normals_finite,
                "normals": "n" in self.dtype.names, "crc": self.crc.state()}

    @classmethod
    def from_state(cls, folder, s):
        b = cls(folder, s["origin"], s["side"], tuple(s["shape"]), s["normals"])
        b.counts = np.asarray(s["counts"], np.int64).reshape(b.shape)
        b.lo, b.hi = np.asarray(s["lo"]), np.asarray(s["hi"])
        b.normals_finite = s["normals_finite"]
        b.crc = Crc(s.get("crc"))
        return b


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
