"""Pass (3) of a tiled run (:mod:`clcurv.tiles.engine`): the output files, from the tiles'
results (one file per tile: its own points' fields with their global ids).

* **A catalog** (several input files): one task per input file (:func:`write_file`, on a
  Dask worker in a Dask run) gathers its points' records from the tiles that own them and
  writes its output; each output is written under a hidden name beside its destination
  and renamed once all are written (:func:`write_files`).
* **One LAS/LAZ output** of one LAS/LAZ input: one task per window of consecutive points
  (:func:`write_piece`, windows that are whole LAZ chunks, :func:`clcurv.io.pieces.windows`)
  writes that window's records, compressed, to a piece file; the client joins the pieces
  (:func:`clcurv.io.pieces.assemble`: a header, a byte copy of each piece and a chunk
  table), the header's extra-bytes statistics merged from the tasks'
  (:func:`write_pieces`). The file is the one the in-memory writer writes, byte for byte.
* **Otherwise** (NPZ and PLY outputs, and MST orientation, whose flips are decided from
  every tile): the client merges the tiles' records by windows of ids
  (:func:`clcurv.tiles.results.partition`) and writes the output a window at a time
  (:func:`write_output`).

Every record is checked present exactly once before it is written
(:class:`clcurv.tiles.results.Windows`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv import io
from clcurv.io import pieces, stream
from clcurv.tiles import workspace as wsp
from clcurv.tiles.buckets import READ_CHUNK
from clcurv.tiles.results import Windows, tile_dtype, to_windows
from clcurv.tiles.workspace import load_sealed, tile_file


def _gather(ws, key, tiles, stored, lo, n):
    """The :class:`Windows` (in ``ws``/out/``key``) of the records of ids lo..lo+n-1 of the
    results of ``tiles``, their ids made lo-based, and their counts by status."""
    folder = Path(ws) / "out" / str(key)
    wsp.remove(folder)
    folder.mkdir(parents=True)
    win = Windows(folder, n, tile_dtype(stored))
    hi = lo + n
    for t in tiles:
        rec = load_sealed(tile_file(ws, t))          # CorruptWorkspace: recomputed
        rec = rec[(rec["id"] >= lo) & (rec["id"] < hi)]
        rec["id"] -= lo
        if "status" in rec.dtype.names and len(rec):
            win.status += np.bincount(rec["status"], minlength=4)[:4]
        to_windows(rec, win.path, win.size)
    return win


@dataclass
class WriteTask:
    """The output of input file number ``t`` of a catalog (:func:`write_file`)."""
    ws: str
    t: int
    path: str           # the input file
    dst: str            # where the worker writes it (renamed by the client at the end)
    offset: int         # its first global id
    n: int
    tiles: list         # the tiles that own its points
    stored: list        # the fields of the tiles' records
    specs: list         # the fields written
    quantize: float = None   # the LAS writers' quantize (clcurv.tiles.engine.quantize_of)


def write_file(task):
    """One input file's output, on a worker: its points' records gathered from the tiles
    that own them (each id checked present once), written in input order from its own
    input file; returns (t, points by status)."""
    src = stream.open_source(Path(task.path))
    win = _gather(task.ws, task.t, task.tiles, task.stored, task.offset, task.n)
    write_one(Path(task.dst), src, win.rows, task.n, task.specs, win.size, task.quantize)
    wsp.remove(win.folder)
    return task.t, win.status.tolist()


def write_files(ws, source, dst, tiles, files_of, stored, specs, execute, quantize=None):
    """A catalog's outputs, each by a task of ``execute`` (:func:`write_file`), under a
    hidden name beside its destination; once every one is written, each is renamed to its
    destination (a failure leaves no output of the run and no earlier file replaced).
    ``files_of[t]``: the input files that tile t owns points of. Returns the points by
    status."""
    token = os.urandom(4).hex()
    hidden = [Path(d).with_name(f".clcurv-{token}-{Path(d).name}") for d in dst]
    tasks = []
    for k, (part, off, tmp) in enumerate(zip(source.parts, source.offsets, hidden)):
        mine = [t for t in tiles if k in files_of[t]]
        tasks.append(WriteTask(str(ws), k, str(part.path), str(tmp), int(off), int(part.n),
                               mine, stored, specs, quantize))
    status = np.zeros(4, np.int64)
    try:
        for _, counts in execute(tasks, write_file):
            status += counts
        for tmp, d in zip(hidden, dst):
            os.replace(tmp, d)
    finally:
        for tmp in hidden:
            wsp.remove(tmp)
        wsp.remove(Path(ws) / "out")
    return status


# --------------------------------------------------------------------------- pieces

#: points of a piece of one LAS/LAZ output, about (whole LAZ chunks)
PIECE_POINTS = 4_000_000


def piece_windows(n, workers=0):
    """The windows (start, stop) of the pieces of an output of ``n`` points: about
    PIECE_POINTS each, at least two per worker, whole LAZ chunks but the last
    (:func:`clcurv.io.pieces.windows`)."""
    parts = max(-(-n // PIECE_POINTS), 2 * workers, 1)
    return [w for w in pieces.windows(n, parts) if w[1] > w[0]] or [(0, n)]


def writes_pieces(source, dst, mst):
    """Is the output of this run written in pieces (:func:`write_pieces`)?"""
    return (not isinstance(source, stream.Catalog) and io.is_las(dst)
            and io.from_las(source) and not mst)


@dataclass
class PieceTask:
    """Window ``t`` (points first..stop-1) of a LAS/LAZ output (:func:`write_piece`)."""
    ws: str
    t: int
    path: str           # the input file
    piece: str          # the piece file written
    first: int
    stop: int
    tiles: list         # the tiles that own its points
    stored: list
    plan: object        # clcurv.io.stream.LasPlan: the output's header and fields


def write_piece(task):
    """One window's piece, on a worker; returns (t, points by status, extra-bytes
    statistics)."""
    n = task.stop - task.first
    win = _gather(task.ws, f"w{task.t}", task.tiles, task.stored, task.first, n)
    stats = stream.write_las_piece(task.piece, task.plan, task.path, task.first, task.stop,
                                   win.rows, chunk=win.size)
    wsp.remove(win.folder)
    return task.t, win.status.tolist(), stats


def write_pieces(ws, source, dst, tiles, files_of, windows, stored, specs, execute,
                 quantize=None, most_count=0):
    """One LAS/LAZ output in pieces: a task per window of ``windows`` (:func:`write_piece`;
    ``files_of[t]``: the windows that tile t owns points of), joined by the client
    (:func:`clcurv.io.pieces.assemble`, atomically) with the extra-bytes statistics of
    every point. ``most_count``: the largest neighbour count of the run (the count type,
    as the in-memory writer chooses it from the whole column). Returns the points by
    status."""
    names = [name for name, _, _ in specs]
    first = np.zeros(1, tile_dtype(specs))
    if "neighbours" in first.dtype.names:
        first["neighbours"] = most_count
    plan = stream.LasPlan.make(dst, source, names, first, quantize)
    folder = Path(ws) / "pieces"
    wsp.remove(folder)
    folder.mkdir()
    tasks = [PieceTask(str(ws), k, str(source.path), str(folder / f"{k}.piece"), a, b,
                       [t for t in tiles if k in files_of[t]], stored, plan)
             for k, (a, b) in enumerate(windows)]
    status = np.zeros(4, np.int64)
    stats = io.las.ExtraStats(plan.header)
    try:
        for _, counts, piece_stats in execute(tasks, write_piece):
            status += counts
            stats.merge(piece_stats)
        pieces.assemble(dst, plan.header, [t.piece for t in tasks], finish=stats.put)
    finally:
        wsp.remove(folder)
        wsp.remove(Path(ws) / "out")
    return status


# --------------------------------------------------------------------------- the client

def write_output(dst, source, windows, specs, quantize=None):
    """The output in input order, a window at a time, atomically, from the client's
    windows (:func:`clcurv.tiles.results.partition`; a catalog: one output per input file,
    each with its own points)."""
    if isinstance(source, stream.Catalog):
        for part, off, d in zip(source.parts, source.offsets, dst):
            rows = (lambda o: lambda a, b: windows.rows(o + a, o + b))(int(off))
            write_one(d, part, rows, part.n, specs, windows.size, quantize)
        return
    write_one(dst, source, windows.rows, windows.n, specs, windows.size, quantize)


def write_one(dst, source, rows, n, specs, chunk=READ_CHUNK, quantize=None):
    """One output file, ``chunk`` points at a time (a window's: wide records, fewer)."""
    names = [name for name, _, _ in specs]
    with io.atomic_output(dst) as tmp:
        if io.is_las(dst):
            stream.write_las(tmp, source, names, rows, chunk=chunk, quantize=quantize)
        elif dst.suffix.lower() == ".ply":
            stream.write_ply(tmp, source, names, rows, n,
                             {name: (width, dtype) for name, width, dtype in specs},
                             chunk=chunk)
        else:
            stream.write_npz(tmp, source, names, rows, n,
                             {name: (width, dtype) for name, width, dtype in specs},
                             chunk=chunk)
