"""The results of a tiled run (:mod:`clcurv.tiles.engine`): one file per tile (its own points'
fields with their global ids), regrouped by windows of consecutive ids so that the output
is written in input order one window at a time."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from clcurv.tiles.orient import NODE_FIELDS
from clcurv.tiles.workspace import CorruptWorkspace, load_sealed, tile_file

#: points per id window of the merge, at most (its records are what the writing pass
#: holds; a multiple of READ_CHUNK, so a written chunk never spans two windows)
WINDOW = 1 << 18
#: bytes of one window's records, at most: wide records (a features run's dozens of
#: columns) get windows of fewer points (:func:`window_points`), so that the writing pass,
#: which holds a window twice while it loads, stays within a tile's budget
WINDOW_BYTES = 32 << 20


def window_points(dtype):
    """Points per window for records of ``dtype``: WINDOW, or the power of two that keeps
    a window within WINDOW_BYTES (at least 4096)."""
    fit = max(WINDOW_BYTES // max(np.dtype(dtype).itemsize, 1), 1)
    return int(min(WINDOW, max(1 << 12, 1 << (fit.bit_length() - 1))))


class Windows:
    """The tiles' records regrouped by windows of WINDOW consecutive global ids (one file
    each), read back one window at a time in input order: the writing pass holds one
    window, never the whole cloud's fields (no memory maps either: their pages would stay
    in the resident set)."""

    def __init__(self, folder, n, dtype):
        self.folder, self.n, self.dtype = Path(folder), n, dtype
        self.size = window_points(dtype)          # points per window
        self.count = -(-n // self.size)
        self.status = np.zeros(4, np.int64)
        self._w, self._rec = -1, None
        self.transform = None           # applied to a copy of the rows given out

    def path(self, w):
        return self.folder / f"w{w}.bin"

    def halo_path(self, w):
        return self.folder / f"h{w}.bin"

    def window(self, w):
        """The records of window w, indexed by id - w * size; CorruptWorkspace unless every
        id of the window is there exactly once (never a silently partial output: the run
        recomputes, :mod:`clcurv.tiles.engine`)."""
        if w != self._w:
            lo, hi = w * self.size, min(self.n, (w + 1) * self.size)
            p = self.path(w)
            rec = np.fromfile(p, self.dtype) if p.exists() else np.empty(0, self.dtype)
            rel = rec["id"] - lo
            inside = (rel >= 0) & (rel < hi - lo)
            seen = np.bincount(rel[inside], minlength=hi - lo)
            if not inside.all() or not np.all(seen == 1):
                raise CorruptWorkspace(
                    p, f"the tiles wrote ids {lo}..{hi - 1} wrongly: "
                    f"{int(np.count_nonzero(seen == 0))} missing, "
                    f"{int(np.count_nonzero(seen > 1))} more than once, "
                    f"{int(np.count_nonzero(~inside))} out of range")
            out = np.empty(hi - lo, self.dtype)
            out[rec["id"] - lo] = rec
            self._w, self._rec = w, out
        return self._rec

    def rows(self, start, stop):
        """The records of ids start..stop-1 (may span windows; none: empty)."""
        parts = [np.empty(0, self.dtype)] if start >= stop else []
        while start < stop:
            w = start // self.size
            rec = self.window(w)
            end = min(stop, (w + 1) * self.size)
            parts.append(rec[start - w * self.size:end - w * self.size])
            start = end
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return self.transform(out.copy()) if self.transform is not None else out


def to_windows(rec, path_of, size=WINDOW):
    """Append the records ``rec`` (with an 'id') to the files of their id windows of
    ``size`` points."""
    w = rec["id"] // size
    order = np.argsort(w, kind="stable")
    w, rec = w[order], rec[order]
    cuts = np.flatnonzero(np.diff(w)) + 1
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(rec)]):
        with open(path_of(int(w[a])), "ab") as f:
            rec[a:b].tofile(f)


def partition(ws, n, tiles, specs, mst=False):
    """Pass (3a): the records of the files of ``tiles`` (the ids of the tiles that hold
    points) appended to the id windows' files (and, for MST orientation, the halo records
    to the windows' halo files)."""
    dtype = tile_dtype(specs, mst)
    win = Windows(Path(ws) / "windows", n, dtype)
    if win.folder.exists():
        shutil.rmtree(win.folder)
    win.folder.mkdir()
    for t in tiles:
        rec = load_sealed(tile_file(ws, t))             # CorruptWorkspace: recomputed
        if "status" in rec.dtype.names and len(rec):
            win.status += np.bincount(rec["status"], minlength=4)[:4]
        if len(rec):
            to_windows(rec, win.path, win.size)
        if mst:
            halo = load_sealed(tile_file(ws, t).with_suffix(".halo.npy"))
            if len(halo):
                to_windows(halo, win.halo_path, win.size)
    return win


def tile_dtype(specs, mst=False):
    return np.dtype([("id", "<i8")] + [(name, dtype) if width is None else
                                       (name, dtype, (width,)) for name, width, dtype in specs]
                    + (NODE_FIELDS if mst else []))
