"""Bench of the tiled engine (clcurv.tiles.engine) on a synthetic aerial LAZ scene.

    python -m bench.tiled --points 10e6 --memory 1GiB [--points 40e6 ...] [--in-memory]

Generates (once, in --workdir, not committed) a LAZ survey of the given size: blocks of
clcurv.shapes.aerial_scene (terrain, gable roofs, walls, trees) side by side, about 100
points per square metre, written in chunks. Each run is ``clcurv compute`` in a child
process with ``-q`` (its default method, mls2, with the default orientation of LAS, 'up');
wall time and peak RSS (``/usr/bin/time``'s maximum resident set) are recorded, with the
stage split the command prints. ``--in-memory`` also runs the same cloud without tiles
(``--memory`` large) for the throughput ratio. Results are appended as a Markdown table to
bench/results/tiled.md.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
BLOCK = 1_000_000            # points per generated block (100 m x 100 m)
RADIUS = 0.6                 # about 30 neighbours at ~100 points / m^2 on the terrain


def make_scene(path, n, seed=0):
    """Write a LAZ of about ``n`` points (blocks of aerial_scene side by side)."""
    import laspy
    from clcurv.data.shapes import aerial_scene
    blocks = max(1, round(n / BLOCK))
    side = math.ceil(math.sqrt(blocks))
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.001] * 3
    hdr.offsets = [480000.0, 4390000.0, 0.0]
    count = 0
    with laspy.open(str(path), mode="w", header=hdr) as w:
        for b in range(blocks):
            i, j = divmod(b, side)
            s = aerial_scene(BLOCK, extent=(100.0, 100.0), seed=seed + b,
                             origin=(480000.0 + 100.0 * i, 4390000.0 + 100.0 * j, 12.0))
            rec = laspy.ScaleAwarePointRecord.zeros(len(s["points"]), header=hdr)
            rec.x, rec.y, rec.z = s["points"].T
            rec.classification = s["kind"]
            w.write_points(rec)
            count += len(s["points"])
    return count


def run_cli(args):
    """(wall seconds, peak RSS bytes, stdout) of ``clcurv`` ``args`` in a child process."""
    cmd = ["/usr/bin/time", "-f", "MAXRSS %M", sys.executable, "-m", "clcurv.cli.main", *args]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode:
        raise RuntimeError(f"clcurv {' '.join(args)} failed: {p.stderr[-2000:]}")
    rss = int(re.search(r"MAXRSS (\d+)", p.stderr).group(1)) * 1024
    return wall, rss, p.stdout


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=float, action="append", required=True)
    ap.add_argument("--memory", default="1GiB")
    ap.add_argument("--workdir", default="/tmp/clcurv-bench-tiled")
    ap.add_argument("--in-memory", action="store_true")
    ap.add_argument("--workers", type=int, default=None)
    a = ap.parse_args(argv)
    wd = Path(a.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    rows = []
    for n in a.points:
        n = int(n)
        src = wd / f"scene_{n}.laz"
        if not src.exists():
            t = time.perf_counter()
            got = make_scene(src, n)
            print(f"generated {src} ({got} points) in {time.perf_counter() - t:.0f} s",
                  flush=True)
        runs = [("tiled", ["--memory", a.memory])]
        if a.workers:
            runs.append((f"tiled, {a.workers} workers",
                         ["--memory", a.memory, "--workers", str(a.workers)]))
        if a.in_memory:
            runs.append(("in memory", ["--memory", "1000GiB"]))
        for label, extra in runs:
            out = wd / "out.laz"
            wall, rss, text = run_cli(["compute", str(src), "-o", str(out), "--radius",
                                       str(RADIUS), "-q", *extra])
            m = re.search(r"^(\d+) points", text, re.M)
            pts = int(m.group(1)) if m else n
            stages = re.search(r"^time: (.*)$", text, re.M)
            tiles = re.search(r"in (\d+) tile", text)
            row = (f"| {pts:,} | {label} | {' '.join(extra)} | "
                   f"{tiles.group(1) if tiles else 1} | {wall:.1f} | {pts / wall / 1e6:.2f} | "
                   f"{rss / 2**20:.0f} | {rss / pts:.0f} | "
                   f"{stages.group(1) if stages else ''} |")
            print(row, flush=True)
            rows.append(row)
            out.unlink(missing_ok=True)
    res = REPO / "bench" / "results" / "tiled.md"
    new = not res.exists()
    with open(res, "a") as f:
        if new:
            f.write("# Tiled engine (bench/tiled.py)\n\n`clcurv compute scene.laz -o out.laz "
                    f"--radius {RADIUS} -q` (mls2, orient 'up'; synthetic aerial LAZ, about "
                    "100 points/m^2, ~30 neighbours), one child process per row; peak RSS "
                    "from /usr/bin/time.\n")
        f.write(f"\n{time.strftime('%Y-%m-%d %H:%M')} — {cpu}, {os.cpu_count()} logical "
                "CPUs\n\n| points | run | options | tiles | wall s | M pts/s | peak RSS MiB "
                "| bytes/point | stages |\n|---:|---|---|---:|---:|---:|---:|---:|---|\n")
        f.write("\n".join(rows) + "\n")
    print(f"appended to {res}")


if __name__ == "__main__":
    main()
