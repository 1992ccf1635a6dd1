"""Bench of a catalog or COPC run on the workers (issue 50): who reads and writes the points.

    python -m bench.catalog --points 10e6 --files 16 [--workdir /tmp/clcurv-bench-catalog]
    python -m bench.catalog --points 10e6 --copc

Generates (once, in --workdir, not committed) a catalog of ``--files`` LAZ files side by
side (a square grid of blocks of clcurv.shapes.aerial_scene, about 100 points per square
metre), then runs ``clcurv compute <folder> -o <out>/ --radius 0.6 -q`` (default method
and memory) in a child process, in one process and with ``--workers 2``. The child runs
the command's ``main`` and reports, from inside, its own ``/proc/self/io`` (rchar +
wchar: every byte it read or wrote through a system call, files, pipes and sockets alike;
taken when the passes end, before the LocalCluster's worker processes exit, whose I/O the
kernel then adds to their parent's; the .vpc index written after is left out, a few kB)
and its CPU time (``getrusage``: itself, and its reaped children, the workers). A run of a 2,000-point catalog gives the client's fixed cost (the imports of
Python, numpy, OpenCL and Dask), reported apart. Results are appended to
bench/results/tiled.md.

With ``--copc`` the same scene (the same ``--files`` blocks) is written once as one
``.copc.laz`` (:func:`make_copc`, copclib), and the command is ``clcurv compute
<file>.copc.laz -o <out>/out.laz --radius 0.6 -q --workers 2`` (the tiles read by region,
on the workers), and with ``--scheduler``; a single-file COPC run in one process runs in
memory by default and is not measured. One output file is joined by the client from the
workers' pieces (:func:`clcurv.io.pieces.assemble`): the child also reports the bytes it
read and wrote during that join, apart.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.harness import copc_config, cpu_model

REPO = Path(__file__).resolve().parent.parent
RADIUS = 0.6

_CHILD = """
import contextlib, json, resource, sys, time
from clcurv.tiles import workers
from clcurv.cli.main import main

def io():
    return {k: int(v) for k, v in (ln.split(": ") for ln in
            open("/proc/self/io").read().splitlines())}

snap = []
session = workers.session

@contextlib.contextmanager
def measured(client=None, n=None):
    with session(client, n) as c:
        try:
            yield c
        finally:
            snap.append(io())        # before the workers exit: a reaped child's I/O is
                                     # added to its parent's /proc/<pid>/io
workers.session = measured
joined = [0]
from clcurv.io import pieces
_assemble = pieces.assemble

def assemble(*a, **k):
    before = io()
    try:
        return _assemble(*a, **k)
    finally:
        after = io()
        joined[0] += sum(after[f] - before[f] for f in ("rchar", "wchar"))
pieces.assemble = assemble
t = time.perf_counter()
code = main(sys.argv[1:])
wall = time.perf_counter() - t
mine = snap[-1] if snap else io()
me = resource.getrusage(resource.RUSAGE_SELF)
kids = resource.getrusage(resource.RUSAGE_CHILDREN)
print("BENCH " + json.dumps({"code": code, "wall": wall,
      "rchar": mine["rchar"], "wchar": mine["wchar"], "joined": joined[0],
      "cpu": me.ru_utime + me.ru_stime, "cpu_children": kids.ru_utime + kids.ru_stime,
      "rss": me.ru_maxrss * 1024, "rss_children": kids.ru_maxrss * 1024}))
"""


def _blocks(n, files, seed=0, extent=None):
    """The synthetic scene: ``files`` blocks of about n / files points each, a square grid
    (of ``extent`` metres; default: 100 points per square metre); yields (i, j, scene)."""
    from clcurv.data.shapes import aerial_scene
    side = math.ceil(math.sqrt(files))
    per = int(n // files)
    extent = extent or math.sqrt(per / 100.0)
    for b in range(files):
        i, j = divmod(b, side)
        yield i, j, aerial_scene(per, extent=(extent, extent), seed=seed + b,
                                 origin=(480000.0 + extent * i, 4390000.0 + extent * j, 12.0))


def make_catalog(folder, n, files, seed=0, extent=None):
    """``files`` LAZ files of about n / files points each, a square grid of blocks (of
    ``extent`` metres; default: 100 points per square metre)."""
    import laspy
    folder.mkdir(parents=True, exist_ok=True)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.001] * 3
    hdr.offsets = [480000.0, 4390000.0, 0.0]
    total = 0
    for i, j, s in _blocks(n, files, seed, extent):
        path = folder / f"tile_{i:02d}_{j:02d}.laz"
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = s["points"].T
        las.classification = s["kind"]
        las.write(str(path))
        total += len(s["points"])
    return total


def make_copc(path, n, files, seed=0, extent=None, depth=None, node_points=40_000):
    """The scene of :func:`make_catalog` (the same blocks) as one COPC file (point format 6,
    written by copclib, ``pip install copclib``), laid out as a COPC writer does: levels
    0..depth-1 of the octree hold random samples, each about half the density of the next
    (a node of level l about n / 2 / 4^(depth - l) points, flat terrain filling 4^l x-y
    cells), level ``depth`` (default: nodes of about ``node_points``) the rest; each
    node's points in scene order. Returns the number of points."""
    import copclib as copc
    import laspy
    import numpy as np
    scenes = list(_blocks(n, files, seed, extent))
    pts = np.concatenate([s["points"] for _, _, s in scenes])
    kind = np.concatenate([s["kind"] for _, _, s in scenes])
    del scenes
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales = [0.001] * 3
    hdr.offsets = [480000.0, 4390000.0, 0.0]
    rec = laspy.ScaleAwarePointRecord.zeros(len(pts), header=hdr)
    rec.x, rec.y, rec.z = pts[:, 0], pts[:, 1], pts[:, 2]
    rec.classification = kind
    rec.return_number = rec.number_of_returns = np.ones(len(pts), np.uint8)
    xyz = np.stack([np.asarray(rec.x), np.asarray(rec.y), np.asarray(rec.z)], axis=1)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)       # the coordinates as laspy reads them
    span = float((hi - lo).max())
    cfg = copc_config(copc, 6, (0.001,) * 3, (480000.0, 4390000.0, 0.0), lo, hi, 128)
    depth = depth or max(1, round(math.log(max(len(pts) / node_points, 1), 4)))
    rng = np.random.default_rng(seed)
    level = np.full(len(pts), depth, np.int32)
    u = rng.random(len(pts))
    edge = 0.0
    for lev in range(depth):                        # fractions 1/2 4^-(depth-l), l < depth
        share = 0.5 * 4.0 ** (lev - depth)
        level[(u >= edge) & (u < edge + share)] = lev
        edge += share
    records = np.ascontiguousarray(rec.array)
    writer = copc.FileWriter(str(path), cfg)
    for lev in range(depth + 1):
        idx = np.flatnonzero(level == lev)
        cell = np.clip(((xyz[idx] - lo) / (span / 2 ** lev)).astype(np.int64), 0,
                       2 ** lev - 1)
        keys = (cell[:, 0] << 40) | (cell[:, 1] << 20) | cell[:, 2]
        order = np.argsort(keys, kind="stable")
        idx, cell, keys = idx[order], cell[order], keys[order]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(keys)]):
            data = records[idx[a:b]].view(np.int8).ravel()
            writer.AddNode(copc.VoxelKey(lev, *map(int, cell[a])), copc.VectorChar(data))
    writer.Close()
    return len(pts)


def _cpu_tree(proc):
    """CPU seconds of a process and its children (psutil: Dask's dependency)."""
    import psutil
    total = 0.0
    for p in [proc] + proc.children(recursive=True):
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def run_on_scheduler(folder, out, extra=(), name=None):
    """The child's report of the command with ``--scheduler``: a Dask scheduler and two
    single-threaded workers started here, each in its own process (the client process then
    holds the client alone); the workers' CPU read from their processes before they stop."""
    import psutil
    bindir = Path(sys.executable).parent
    # the workers import this checkout's clcurv, as the client does (cwd=REPO), not the
    # one installed in the environment (the `dask` script's path comes first otherwise)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    sched = subprocess.Popen([str(bindir / "dask"), "scheduler", "--port", "0",
                              "--dashboard-address", ":0", "--scheduler-file",
                              str(out.parent / "sched.json")], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(200):
            if (out.parent / "sched.json").exists():
                break
            time.sleep(0.1)
        address = json.loads((out.parent / "sched.json").read_text())["address"]
        workers = [subprocess.Popen([str(bindir / "dask"), "worker", address, "--nthreads",
                                     "1", "--nworkers", "1", "--no-dashboard"], env=env,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                   for _ in range(2)]
        time.sleep(3)
        procs = [psutil.Process(w.pid) for w in workers]
        before = sum(_cpu_tree(p) for p in procs)
        rep = run(folder, out, ("--scheduler", address, *extra), name)
        rep["cpu_children"] = sum(_cpu_tree(p) for p in procs) - before
        rep["cpu_scheduler"] = _cpu_tree(psutil.Process(sched.pid))
        for w in workers:
            w.terminate()
            w.wait(30)
    finally:
        sched.terminate()
        sched.wait(30)
        (out.parent / "sched.json").unlink(missing_ok=True)
    return rep


def run(folder, out, extra=(), name=None):
    """The child's report (dict) of ``clcurv compute folder -o out ...`` (``-o out/name``
    with a ``name``: one output file)."""
    out.mkdir(parents=True, exist_ok=True)
    for f in out.iterdir():
        f.unlink()
    args = ["compute", str(folder), "-o", str(out / name if name else out), "--radius",
            str(RADIUS), "-q", *extra]
    p = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True,
                       text=True, cwd=REPO)
    line = next((ln for ln in p.stdout.splitlines() if ln.startswith("BENCH ")), None)
    if p.returncode or line is None:
        raise RuntimeError(f"clcurv {' '.join(args)} failed: {p.stderr[-3000:]}")
    rep = json.loads(line[6:])
    rep["stages"] = next((ln.split("time: ", 1)[1] for ln in p.stdout.splitlines()
                          if ln.startswith("time: ")), "")
    return rep


def _size(path):
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.iterdir() if p.is_file())


def _inputs(a, wd):
    """(the input, the 2,000-point input of the fixed cost, the points): made once."""
    small = wd / "small"
    if not (small / "done").exists():
        make_catalog(small, 2000, 4, extent=20.0)
        (small / "done").write_text("2000")
    if a.copc:
        src = wd / f"copc_{int(a.points)}_{a.files}.copc.laz"
        done = src.with_name(src.name + ".done")
        if not done.exists():
            done.write_text(str(make_copc(src, a.points, a.files)))
        tiny = wd / "small.copc.laz"
        if not tiny.exists():
            make_copc(tiny, 2000, 4, extent=20.0)
        return src, tiny, int(done.read_text())
    cat = wd / f"cat_{int(a.points)}_{a.files}"
    if not (cat / "done").exists():
        n = make_catalog(cat, a.points, a.files)
        (cat / "done").write_text(str(n))
    # ("done" is not a LAS/LAZ: no input of the catalog)
    return cat, small, int((cat / "done").read_text())


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=float, default=10e6)
    ap.add_argument("--files", type=int, default=16)
    ap.add_argument("--copc", action="store_true",
                    help="the scene as one .copc.laz, written to one output file")
    ap.add_argument("--workdir", default="/tmp/clcurv-bench-catalog")
    a = ap.parse_args(argv)
    wd = Path(a.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    src, small, n = _inputs(a, wd)
    name = "out.laz" if a.copc else None
    runs = (("--workers 2", ("--workers", "2")), ("--scheduler", None))
    if not a.copc:
        runs = (("one process", ()),) + runs
    load0 = open("/proc/loadavg").read().split()[:3]
    rows = []
    for label, extra in runs:
        how = run if extra is not None else run_on_scheduler
        base = how(small, wd / "out_small", extra or (), name)
        rep = how(src, wd / "out", extra or (), name)
        rep["in"], rep["out"] = _size(src), _size(wd / "out")
        rows.append((label, rep, base))
    cpu = cpu_model()
    load = open("/proc/loadavg").read().split()[:3]
    what = "COPC" if a.copc else "Catalog"
    cmd = (f"`clcurv compute <file>.copc.laz -o <folder>/out.laz --radius {RADIUS} -q` "
           f"(the scene of the {a.files}-file catalog as one COPC file, copclib, point "
           f"format 6, {src.stat().st_size / 1e6:.1f} MB)" if a.copc else
           f"`clcurv compute <folder of {a.files} LAZ> -o <folder>/ --radius {RADIUS} -q` "
           f"(input {_size(src) / 1e6:.1f} MB)")
    lines = [f"\n### {what} on the workers, {time.strftime('%Y-%m-%d %H:%M')} — {cpu}, "
             f"load average {' '.join(load0)} before, {' '.join(load)} after\n",
             f"{cmd}, default method and memory, {n:,} points.\n",
             "| run | wall s | client CPU s | workers' CPU s | client CPU / workers' | "
             "client rchar+wchar MB (above its 2,000-point run) | of the point bytes in+out "
             + ("| of which the join of the pieces MB " if a.copc else "")
             + "| peak RSS client / worker MB | output MB | stages |",
             "|---|---:|---:|---:|---:|---:|---:|" + ("---:|" if a.copc else "")
             + "---:|---:|---|"]
    for label, rep, base in rows:
        moved = rep["rchar"] + rep["wchar"]
        above = moved - (base["rchar"] + base["wchar"])
        points = rep["in"] + rep["out"]
        kids = rep["cpu_children"]
        client_cpu = rep["cpu"] - (base["cpu"] if kids else 0)
        ratio = f"{client_cpu / kids:.1%}" if kids else "-"
        join = f"{rep['joined'] / 1e6:.1f} | " if a.copc else ""
        lines.append(
            f"| {label} | {rep['wall']:.1f} | {rep['cpu']:.1f} ({client_cpu:.1f} above "
            f"its 2,000-point run) | {kids:.1f} | {ratio} | {moved / 1e6:.1f} "
            f"({above / 1e6:.1f}) | {above / points:.2%} | {join}{rep['rss'] / 2**20:.0f} / "
            f"{rep['rss_children'] / 2**20:.0f} | {rep['out'] / 1e6:.1f} | {rep['stages']} |")
    text = "\n".join(lines) + "\n"
    print(text)
    with open(REPO / "bench" / "results" / "tiled.md", "a") as f:
        f.write(text)


if __name__ == "__main__":
    main()
