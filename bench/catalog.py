"""Bench of a catalog run on the workers (issue 50): who reads and writes the points.

    python -m bench.catalog --points 10e6 --files 16 [--workdir /tmp/clcurv-bench-catalog]

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
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

from bench.harness import cpu_model

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
t = time.perf_counter()
code = main(sys.argv[1:])
wall = time.perf_counter() - t
mine = snap[-1] if snap else io()
me = resource.getrusage(resource.RUSAGE_SELF)
kids = resource.getrusage(resource.RUSAGE_CHILDREN)
print("BENCH " + json.dumps({"code": code, "wall": wall,
      "rchar": mine["rchar"], "wchar": mine["wchar"],
      "cpu": me.ru_utime + me.ru_stime, "cpu_children": kids.ru_utime + kids.ru_stime,
      "rss": me.ru_maxrss * 1024, "rss_children": kids.ru_maxrss * 1024}))
"""


def make_catalog(folder, n, files, seed=0, extent=None):
    """``files`` LAZ files of about n / files points each, a square grid of blocks (of
    ``extent`` metres; default: 100 points per square metre)."""
    import laspy
    from clcurv.data.shapes import aerial_scene
    folder.mkdir(parents=True, exist_ok=True)
    side = math.ceil(math.sqrt(files))
    per = int(n // files)
    extent = extent or math.sqrt(per / 100.0)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.001] * 3
    hdr.offsets = [480000.0, 4390000.0, 0.0]
    total = 0
    for b in range(files):
        i, j = divmod(b, side)
        path = folder / f"tile_{i:02d}_{j:02d}.laz"
        s = aerial_scene(per, extent=(extent, extent), seed=seed + b,
                         origin=(480000.0 + extent * i, 4390000.0 + extent * j, 12.0))
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = s["points"].T
        las.classification = s["kind"]
        las.write(str(path))
        total += len(s["points"])
    return total


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


def run_on_scheduler(folder, out, extra=()):
    """The child's report of the command with ``--scheduler``: a Dask scheduler and two
    single-threaded workers started here, each in its own process (the client process then
    holds the client alone); the workers' CPU read from their processes before they stop."""
    import psutil
    bindir = Path(sys.executable).parent
    sched = subprocess.Popen([str(bindir / "dask"), "scheduler", "--port", "0",
                              "--dashboard-address", ":0", "--scheduler-file",
                              str(out.parent / "sched.json")],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(200):
            if (out.parent / "sched.json").exists():
                break
            time.sleep(0.1)
        address = json.loads((out.parent / "sched.json").read_text())["address"]
        workers = [subprocess.Popen([str(bindir / "dask"), "worker", address, "--nthreads",
                                     "1", "--nworkers", "1", "--no-dashboard"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                   for _ in range(2)]
        time.sleep(3)
        procs = [psutil.Process(w.pid) for w in workers]
        before = sum(_cpu_tree(p) for p in procs)
        rep = run(folder, out, ("--scheduler", address, *extra))
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


def run(folder, out, extra=()):
    """The child's report (dict) of ``clcurv compute folder -o out ...``."""
    out.mkdir(parents=True, exist_ok=True)
    for f in out.iterdir():
        f.unlink()
    args = ["compute", str(folder), "-o", str(out), "--radius", str(RADIUS), "-q", *extra]
    p = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True,
                       text=True, cwd=REPO)
    line = next((ln for ln in p.stdout.splitlines() if ln.startswith("BENCH ")), None)
    if p.returncode or line is None:
        raise RuntimeError(f"clcurv {' '.join(args)} failed: {p.stderr[-3000:]}")
    rep = json.loads(line[6:])
    rep["stages"] = next((ln.split("time: ", 1)[1] for ln in p.stdout.splitlines()
                          if ln.startswith("time: ")), "")
    return rep


def _size(folder):
    return sum(p.stat().st_size for p in Path(folder).iterdir() if p.is_file())


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=float, default=10e6)
    ap.add_argument("--files", type=int, default=16)
    ap.add_argument("--workdir", default="/tmp/clcurv-bench-catalog")
    a = ap.parse_args(argv)
    wd = Path(a.workdir)
    cat = wd / f"cat_{int(a.points)}_{a.files}"
    if not (cat / "done").exists():
        n = make_catalog(cat, a.points, a.files)
        (cat / "done").write_text(str(n))
    n = int((cat / "done").read_text())
    small = wd / "small"
    if not (small / "done").exists():
        make_catalog(small, 2000, 4, extent=20.0)
        (small / "done").write_text("2000")
    rows = []                       # ("done" is not a LAS/LAZ: no input of the catalog)
    for label, extra in (("one process", ()), ("--workers 2", ("--workers", "2")),
                         ("--scheduler", None)):
        how = run if extra is not None else run_on_scheduler
        base = how(small, wd / "out_small", extra or ())
        rep = how(cat, wd / "out", extra or ())
        rep["in"], rep["out"] = _size(cat), _size(wd / "out")
        rows.append((label, rep, base))
    cpu = cpu_model()
    load = open("/proc/loadavg").read().split()[:3]
    lines = [f"\n### Catalog on the workers, {time.strftime('%Y-%m-%d %H:%M')} — {cpu}, "
             f"load average {' '.join(load)}\n",
             f"`clcurv compute <folder of {a.files} LAZ> -o <folder>/ --radius {RADIUS} -q` "
             f"(default method and memory), {n:,} points; input {_size(cat) / 1e6:.1f} MB.\n",
             "| run | wall s | client CPU s | workers' CPU s | client CPU / workers' | "
             "client rchar+wchar MB (above its 2,000-point run) | of the point bytes in+out "
             "| peak RSS client / worker MB | output MB | stages |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for label, rep, base in rows:
        moved = rep["rchar"] + rep["wchar"]
        above = moved - (base["rchar"] + base["wchar"])
        points = rep["in"] + rep["out"]
        kids = rep["cpu_children"]
        client_cpu = rep["cpu"] - (base["cpu"] if kids else 0)
        ratio = f"{client_cpu / kids:.1%}" if kids else "-"
        lines.append(
            f"| {label} | {rep['wall']:.1f} | {rep['cpu']:.1f} ({client_cpu:.1f} above "
            f"its 2,000-point run) | {kids:.1f} | {ratio} | {moved / 1e6:.1f} "
            f"({above / 1e6:.1f}) | {above / points:.2%} | {rep['rss'] / 2**20:.0f} / "
            f"{rep['rss_children'] / 2**20:.0f} | {rep['out'] / 1e6:.1f} | {rep['stages']} |")
    text = "\n".join(lines) + "\n"
    print(text)
    with open(REPO / "bench" / "results" / "tiled.md", "a") as f:
        f.write(text)


if __name__ == "__main__":
    main()
