"""I/O bench (issue 50, faster I/O): bytes written, laspy's time to read them back, the LAZ
codec, and the end-to-end time of the default CLI call against its compute stage.

    python -m bench.io --points 5e6 [--points 10e6] [--repeat 3]

For each size, on a synthetic aerial LAZ (``bench.tiled.make_scene``: blocks of
``clcurv.shapes.aerial_scene``, ~100 points/m^2, generated once in --workdir):

1. ``clcurv compute in.laz -o out.laz --method mls2 --radius 1`` in a child process (the
   default fields and memory), then with ``--fields all`` and with ``--quantize``, each
   --cli-repeat times (the fastest kept): wall time and peak RSS (``/usr/bin/time -v``), the
   stage split the command prints, and the ratio of the wall time to the compute stage
   (``mls2``).
2. Each output: bytes, bytes per point, and ``laspy.read`` of it (best of --repeat).
3. The LAZ codec: ``laspy.read`` of the default output and its write (the same header and
   records) with lazrs sequential (``LazBackend.Lazrs``) and parallel
   (``LazBackend.LazrsParallel``, rayon's threads), best of --repeat each.

The CPU (``lscpu``), the load average before and after each measurement (other processes
share the cores) are recorded. Writes bench/results/io.md and io.json (replacing them).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench.tiled import make_scene          # noqa: E402

RADIUS = 1.0
#: io.md: the text above this line is kept (the summary), the tables below are rewritten
MARKER = "<!-- the tables below are written by bench/io.py -->"
RUNS = (("default fields", []), ("--fields all", ["--fields", "all"]),
        ("--quantize", ["--quantize"]))


def load():
    return os.getloadavg()[0]


def cpu_name():
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return re.search(r"Model name:\s*(.+)", out).group(1).strip()
    except (OSError, AttributeError):
        return "unknown"


def run_cli(args, log):
    """(wall s, peak RSS bytes, stdout) of ``clcurv`` ``args``: a child process of the
    worktree's clcurv, timed by /usr/bin/time -v."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = ["/usr/bin/time", "-v", "-o", str(log), sys.executable, "-m", "clcurv.cli.main",
           *map(str, args)]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env)
    wall = time.perf_counter() - t
    if p.returncode:
        raise RuntimeError(f"clcurv {' '.join(map(str, args))} failed: {p.stderr[-2000:]}")
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)",
                        log.read_text()).group(1)) * 1024
    return wall, rss, p.stdout


def stages(text):
    m = re.search(r"^time: (.*)$", text, re.M)
    return {k.strip(): float(v) for k, v in re.findall(r"([\w ]+?) ([\d.]+) s", m.group(1))} if m else {}


def best(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def codec(path, repeat, wd):
    """Best seconds of laspy.read of ``path`` and of its write (batches of 2^20 points, as
    the in-memory writer's, and of 2^18, a tiled run's windows), lazrs sequential against
    parallel; the two alternate in each repeat, the order swapped every time, so that a
    change of the load hits both."""
    import laspy
    b = laspy.LazBackend
    las = laspy.read(str(path))
    dst = wd / "codec.laz"
    backends = (("sequential (Lazrs)", b.Lazrs), ("parallel (LazrsParallel)", b.LazrsParallel))
    out = {name: {"read_s": [], "write_2^20_s": [], "write_2^18_s": [], "load": []}
           for name, _ in backends}
    for i in range(repeat):
        for name, backend in (backends if i % 2 == 0 else backends[::-1]):
            o = out[name]
            o["load"].append(load())
            o["read_s"].append(best(lambda: laspy.read(str(path), laz_backend=backend), 1))
            for batch in (20, 18):
                def write():
                    with laspy.open(str(dst), mode="w", header=las.header, do_compress=True,
                                    laz_backend=backend) as w:
                        for a in range(0, len(las.points), 1 << batch):
                            w.write_points(las.points[a:a + (1 << batch)])
                o[f"write_2^{batch}_s"].append(best(write, 1))
    dst.unlink(missing_ok=True)
    for name, o in out.items():
        for k in ("read_s", "write_2^20_s", "write_2^18_s"):
            o[k] = min(o[k])
        o["load"] = [min(o["load"]), max(o["load"])]
        print(f"  codec {name}: read {o['read_s']:.2f} s, write {o['write_2^20_s']:.2f} s "
              f"(2^20) {o['write_2^18_s']:.2f} s (2^18), load {o['load']}", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=float, action="append", required=True)
    ap.add_argument("--workdir", default="/tmp/clcurv-bench-io")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cli-repeat", type=int, default=2,
                    help="runs of each command: the fastest is reported")
    a = ap.parse_args(argv)
    import laspy
    wd = Path(a.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    report = {"cpu": cpu_name(), "cores": os.cpu_count(), "date": time.strftime("%Y-%m-%d %H:%M"),
              "rayon_threads": os.environ.get("RAYON_NUM_THREADS"), "sizes": []}
    for n in a.points:
        n = int(n)
        src = wd / f"scene_{n}.laz"
        if not src.exists():
            make_scene(src, n)
        size = {"points": n, "input_bytes": src.stat().st_size, "runs": []}
        for label, extra in RUNS:
            dst = wd / f"out_{n}_{len(size['runs'])}.laz"
            la = load()
            wall, rss, text = min(
                (run_cli(["compute", src, "-o", dst, "--method", "mls2", "--radius", RADIUS,
                          *extra], wd / "time.log") for _ in range(a.cli_repeat)),
                key=lambda r: r[0])
            pts = int(re.search(r"^(\d+) points", text, re.M).group(1))
            st = stages(text)
            read = best(lambda: laspy.read(str(dst)), a.repeat)
            rec = laspy.open(str(dst)).header.point_format.size
            row = {"run": label, "args": extra, "points": pts, "wall_s": wall, "rss": rss,
                   "stages": st, "ratio": wall / st["mls2"], "bytes": dst.stat().st_size,
                   "record": rec, "read_s": read, "load": [la, load()]}
            size["runs"].append(row)
            print(f"{n} {label}: wall {wall:.1f} s ({row['ratio']:.2f}x mls2 {st['mls2']:.2f} s), "
                  f"RSS {rss / 2**20:.0f} MiB, {row['bytes'] / pts:.1f} B/pt, read {read:.2f} s, "
                  f"load {la:.2f}->{row['load'][1]:.2f}; {st}", flush=True)
        size["codec"] = codec(wd / f"out_{n}_0.laz", a.repeat, wd)
        report["sizes"].append(size)
        for i in range(len(RUNS)):
            (wd / f"out_{n}_{i}.laz").unlink(missing_ok=True)
    res = REPO / "bench" / "results"
    (res / "io.json").write_text(json.dumps(report, indent=1))
    md = res / "io.md"
    kept = md.read_text().split(MARKER)[0] if md.exists() and MARKER in md.read_text() else ""
    md.write_text(kept + MARKER + "\n" + markdown(report))
    print(f"wrote {res / 'io.json'} and io.md")


def markdown(report):
    """The tables of ``report`` (bench/results/io.md)."""
    out = [f"## Measurements\n",
           f"Measured {report['date']} on {report['cpu']} ({report['cores']} cores, lscpu), "
           "PoCL CPU device, laspy 2.7 with lazrs; other processes shared the cores: the load "
           "average (1 min) is given beside each row. Synthetic aerial LAZ "
           "(`bench.tiled.make_scene`, ~100 points/m^2, point format 3, 6.3 bytes a point); "
           f"`clcurv compute in.laz -o out.laz --method mls2 --radius {RADIUS:g}` with default "
           "arguments (memory 'auto': in memory), then with `--fields all` and `--quantize`. "
           "Wall time and peak RSS from `/usr/bin/time -v`; stages as the command prints "
           "them (the fastest of the runs of each command); ratio = wall / compute stage "
           "(mls2); read back = best `laspy.read` of the output.\n"]
    for size in report["sizes"]:
        n = size["points"]
        out.append(f"\n### {n / 1e6:g}M points (input {size['input_bytes'] / 1e6:.1f} MB, "
                   f"{size['input_bytes'] / n:.1f} bytes a point)\n")
        out.append("| run | record bytes | output MB | bytes/point | laspy read back s | "
                   "wall s | reading s | mls2 s | writing s | wall / mls2 | peak RSS MiB "
                   "| load |")
        out.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
        for r in size["runs"]:
            st = r["stages"]
            out.append(f"| {r['run']} | {r['record']} | {r['bytes'] / 1e6:.1f} | "
                       f"{r['bytes'] / r['points']:.1f} | {r['read_s']:.2f} | "
                       f"{r['wall_s']:.1f} | {st.get('reading', 0):.2f} | "
                       f"{st.get('mls2', 0):.2f} | {st.get('writing', 0):.2f} | "
                       f"{r['ratio']:.2f}x | {r['rss'] / 2**20:.0f} | "
                       f"{r['load'][0]:.1f}-{r['load'][1]:.1f} |")
        out.append("\nLAZ codec on the default output (best of the repeats, sequential and "
                   "parallel alternating; the read all at once, the write in batches of "
                   "2^20 points, the in-memory writer's, or 2^18, a tiled run's windows):\n")
        out.append("| lazrs | laspy.read s | write, 2^20 batches s | write, 2^18 batches s "
                   "| load |")
        out.append("|---|---:|---:|---:|---|")
        for name, c in size["codec"].items():
            out.append(f"| {name} | {c['read_s']:.2f} | {c['write_2^20_s']:.2f} | "
                       f"{c['write_2^18_s']:.2f} | {c['load'][0]:.1f}-{c['load'][1]:.1f} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    main()
