"""clcurv benchmark: every OpenCL device against Open3D, jakteristics and the float64 NumPy reference.

Run from the repository root::

    python -m bench.run                 # 100k and 1M points, ~30 and ~100 neighbours, 3 repeats
    python -m bench.run --quick         # 100k points, ~30 neighbours: smoke run (< 1 min)
    python -m bench.run --sizes 1M --neighbours 30
    python -m bench.run --sizes 1M      # only the 1M rows (orientation also at 100k)
    python -m bench.run --no-open3d --no-jakteristics

The cloud is a uniform sample of the unit sphere (``clcurv.shapes.sphere``) in random order,
plus a spatially sorted copy (k-d tree leaf order); its exact normals are the points. Radii
give ~k neighbours: r = sqrt(4 k / n) (area 4 pi, k = n pi r^2 / (4 pi)). Every timing is the
minimum of ``--repeats`` runs after an untimed warm-up (so program builds are cached), except
where the table says otherwise.

Measured, per device, size and neighbour count, first what a user gets from the default
call: every operator of the registry (``clcurv.ops.registry``) as ``curvature(P, r, method=m)``,
``normals(P, r)`` and the paper's pipeline ``curvature(P, r, method="mls2", scale_space=5)``,
each with its default arguments (orient='auto': signed methods orient their PCA normals on
the device, unsigned ones do not orient), with ``orient=None`` and with the exact normals
(``normals=``), end to end; at sizes >= ``--rss-min-points`` (1M) the peak RSS of each default
call (a fresh process running it once). Then orientation alone at every size and at
``--orient-points`` (100k): ``clcurv.orient.orientation.flip_on_device`` split into the k-NN graph, the
Boruvka rounds and the signs, against the host reference ``flip_by_propagation`` (same
graph) and Open3D ``orient_normals_consistent_tangent_plane(10)`` at 100k, with the outward
fraction of each. Then the detail: the stages of one moments run, each kernel alone
(``cloud.timings``), the operators interleaved with ``normals(orient=None)`` for the time
ratios, the MLS1 scale space (1 iteration; 5 with ``return_stats``). Peers: the NumPy
reference of every operator (timed once on a polar cap of the same cloud, extrapolated
linearly), Open3D ``estimate_normals``/``estimate_covariances`` and jakteristics
``compute_features``; at the largest size, the default variation call on the first device
and Open3D's ``estimate_normals`` interleaved in 5 pairs, whose ratio of minima is the
default-call target's (both sides in the same seconds; the separate blocks' ratio is
listed too). Results are checked against the reference on the cap, with the
tolerances of ``bench/targets.py`` (those the tests assert), and the speed targets of that
module are evaluated (PASS/FAIL).

Each block (reference, clcurv per device and column, Open3D, jakteristics, the pairs,
orientation) runs
between two checks that both cores are free (a PoCL kernel timed with 1 and 2 threads); busy
blocks are measured again, and flagged if still busy. Prints a table, writes
``bench/results/bench-<devicekind>.json`` and ``bench/results/bench.md``.

Modules: ``harness`` (timers, clouds, environment), ``contention`` (the free-cores guard),
``measure`` (clcurv on one device), ``peers`` (reference, Open3D, jakteristics),
``accuracy`` (checks against the reference), ``report`` (ratios, targets, tables, files),
``targets`` (tolerances and targets), ``ops`` (what is timed, from the registry).
"""
from __future__ import annotations

import argparse
import os

import clcurv

from .contention import Guard
from .harness import cap_indices, environment, exact_normals, log, make_clouds, radius_for
from .measure import bench_device
from .peers import (bench_jakteristics, bench_open3d, bench_orientation, bench_reference,
                    bench_variation_pairs, jakteristics_or_reason, jakteristics_version,
                    open3d_or_none)
from .report import report


def parse_size(text):
    """'100k', '1M', '250000' -> int."""
    t = text.strip().lower().replace("_", "").replace(",", "")
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:], 1)
    return int(float(t[:-1] if mult > 1 else t) * mult)


def size_label(n):
    if n >= 1_000_000 and n % 100_000 == 0:
        return f"{n / 1e6:g}M"
    if n >= 1_000 and n % 1_000 == 0:
        return f"{n // 1000}k"
    return str(n)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[100_000, 1_000_000],
                    metavar="N", help="cloud sizes (e.g. 100k 1M; default 100k 1M)")
    ap.add_argument("--n", type=parse_size, default=None, help="one size (same as --sizes N)")
    ap.add_argument("--neighbours", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ref-points", type=int, default=100_000,
                    help="points of the NumPy reference subsample (at most n/4)")
    ap.add_argument("--orient-points", type=parse_size, default=100_000,
                    help="size of the orientation cloud with the host reference and Open3D "
                         "(the device orientation also runs at every --sizes)")
    ap.add_argument("--rss-min-points", type=parse_size, default=1_000_000, metavar="N",
                    help="peak RSS of the default calls (a child process each) at sizes >= N")
    ap.add_argument("--quick", action="store_true",
                    help="100k points, ~30 neighbours, 1 repeat, 20k-point subsamples (< 1 min)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--no-jakteristics", action="store_true")
    ap.add_argument("--wait-quiet", type=float, default=60, metavar="SECONDS",
                    help="before each block, wait up to this long for both cores to be free")
    ap.add_argument("--retries", type=int, default=2,
                    help="measure a block again (up to this many times) when the cores were busy")
    args = ap.parse_args(argv)
    if args.n is not None:
        args.sizes = [args.n]
    if args.quick:
        args.sizes, args.neighbours, args.repeats = [100_000], [30], 1
        args.ref_points, args.orient_points = 20_000, 20_000
        args.wait_quiet, args.retries = min(args.wait_quiet, 15), min(args.retries, 1)
    args.sizes = sorted(set(args.sizes))
    return args


def bench_devices():
    """Every OpenCL device but simulators (Oclgrind, FPGA emulators: ~1000x slower), or
    only the one ``CLCURV_DEVICE`` names (``CLCURV_DEVICE=gpu make bench``)."""
    infos = clcurv.devices()
    if not infos:
        raise SystemExit("no OpenCL device: " + clcurv.runtime.device.APT_HINT)
    if os.environ.get("CLCURV_DEVICE"):
        return [infos[clcurv.get_device().info.index]]
    real = [d for d in infos if not d.simulator]
    if not real:
        raise SystemExit(infos.reason)
    return real


def main(argv=None):
    args = parse_args(argv)
    # the OpenCL platforms first: importing Open3D first hides Intel's CPU runtime (its
    # libraries clash; loaded in this order both work)
    infos = bench_devices()
    env = environment()
    guard = Guard(args.wait_quiet, args.retries)
    o3d = None if args.no_open3d else open3d_or_none()
    jak, jak_note = (None, "--no-jakteristics") if args.no_jakteristics else jakteristics_or_reason()
    if jak is not None:
        env["jakteristics"] = jakteristics_version(jak)
    elif not args.no_jakteristics:
        log(f"jakteristics not available ({jak_note}): skipped (pip install jakteristics)")

    data, cols = {}, []
    for n in args.sizes:
        pts, sorted_pts = make_clouds(n)
        data[n] = {"random": pts, "sorted": sorted_pts, "normals": exact_normals(pts)}
        for k in args.neighbours:
            cols.append({"id": f"{size_label(n)} ~{k}", "n": n, "k": k, "r": radius_for(k, n),
                         "cap": cap_indices(pts, min(args.ref_points, n // 4))})
    refs = {c["id"]: guard.block(f"NumPy reference {c['id']}", lambda c=c: bench_reference(
        data[c["n"]]["random"], c["r"], c["cap"], data[c["n"]]["normals"])) for c in cols}

    devs = [bench_device(info, cols, data, refs, args.repeats, guard, args.rss_min_points)
            for info in infos]

    o3d_res, jak_res = {}, {}
    for c in cols:
        clouds = {"random": data[c["n"]]["random"], "sorted": data[c["n"]]["sorted"]}
        for name, mod, fn, res in (("Open3D", o3d, bench_open3d, o3d_res),
                                   ("jakteristics", jak, bench_jakteristics, jak_res)):
            if mod is not None:
                label = f"{name} {c['id']}"
                res[c["id"]] = guard.block(label, lambda: fn(mod, clouds, c["r"], args.repeats))
                res[c["id"]]["threads"] = guard.gains(label)
    if o3d is not None:             # the default-call target, interleaved with Open3D
        top = max(c["n"] for c in cols)
        for c in cols:
            if c["n"] == top:
                clouds = {"random": data[top]["random"], "sorted": data[top]["sorted"]}
                label = f"variation / Open3D interleaved {c['id']}"
                o3d_res[c["id"]]["paired"] = guard.block(label, lambda: bench_variation_pairs(
                    o3d, clouds, c["r"], infos[0].index))
    oclouds = {n: data[n]["random"] if n in data else make_clouds(n)[0]
               for n in sorted(set(args.sizes) | {args.orient_points})}
    orientation = guard.block("orientation", lambda: bench_orientation(
        o3d, oclouds, args.orient_points, infos[0].index, args.repeats))

    report(args, env, guard, cols, refs, o3d_res, jak_res, jak_note, orientation, devs)


if __name__ == "__main__":
    main()
