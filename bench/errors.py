"""The cost of the error bars and of the radius selection, and their reading on real scans
(issue 51): ``python -m bench.errors [--points 1e6] [--repeats 5]``; writes the tables to
stdout (bench/results/errors.md holds a run).

* Cost, default arguments, a 1M-point noisy sphere at about 30 neighbours: the MLS2 call
  with ``uncertainty=True`` against the same call without (paired rounds, their minima);
  ``select='error'`` among 4 radii of ratio 1.6 (the second the 30-neighbour one: about
  12, 30, 77 and 200 neighbours) against one call at the largest radius; MLS1 with ``uncertainty=True`` against MLS1. Peak RSS of
  each call in a fresh interpreter beside it.
* Real scans (../shared/data, when present; the bundled bunny otherwise): the fraction of
  points whose H (MLS2) is significant, |H| > 2 SE(H), at radii of about 15, 30, 60 and
  120 neighbours, and the median SE and roughness there; the bunny and the Autzen LAZ
  rendered with the not-significant points grey (bench/results/*_significance.png).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import clcurv
from bench.harness import REPO, cpu_model, loadavg, log, paired, run_python

RESULTS = REPO / "bench" / "results"
SHARED = REPO.parent / "shared" / "data"
RATIO = 1.6

# VmHWM, this process's own peak: ru_maxrss would carry the parent's over fork and exec
_RSS = """
import sys, json, numpy as np, clcurv
kw = json.loads(sys.argv[1])
s = clcurv.shapes.sphere(int(kw.pop("n")), 1.0, noise=0.002, seed=0)
clcurv.curvature(s["points"], **kw)
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM:")][0]
print(int(hwm.split()[1]) // 1024)
"""


def peak_mib(n, **kw):
    """Peak RSS (MiB) of one call ``clcurv.curvature(points, **kw)`` in a fresh interpreter
    (the cloud made there too)."""
    return int(run_python(_RSS, json.dumps(dict(kw, n=n))).strip())


def cost(n, repeats):
    s = clcurv.shapes.sphere(n, 1.0, noise=0.002, seed=0)
    p = s["points"]
    r = float(np.sqrt(4.0 * 30 / n))                    # ~30 neighbours on the unit sphere
    radii = [r * RATIO ** j for j in (-1, 0, 1, 2)]
    rows = []
    cases = [("mls2", dict(radius=r, method="mls2"), dict(radius=r, method="mls2",
                                                          uncertainty=True)),
             ("mls2 select, 4 radii", dict(radius=radii[-1], method="mls2"),
              dict(radius=radii, method="mls2", select="error")),
             ("mls1", dict(radius=r, method="mls1"), dict(radius=r, method="mls1",
                                                          uncertainty=True))]
    for name, base, more in cases:
        clcurv.curvature(p, **base)
        clcurv.curvature(p, **more)                     # builds, warm caches
        a, b = paired(lambda: clcurv.curvature(p, **base), lambda: clcurv.curvature(p, **more),
                      repeats)
        rows.append((name, a, b, b / a, peak_mib(n, **base), peak_mib(n, **more), loadavg()))
        log(f"{name}: {a:.3f} s -> {b:.3f} s ({b / a:.2f}x)")
    return r, radii, rows


def _scan(name):
    if name == "bunny":
        path = SHARED / "stanford_bun_zipper.ply"
        path = path if path.exists() else REPO / "clcurv" / "data" / "bunny.ply"
        return path, clcurv.io.read(path).points, 0.00379, "mst"
    path = SHARED / "laspy_autzen_trim.laz"
    if not path.exists():
        return None, None, None, None
    return path, clcurv.io.read(path).points, 6.14, "up"


def scans():
    out = []
    for name in ("bunny", "autzen"):
        path, pts, r30, orient = _scan(name)
        if path is None:
            log(f"{name}: absent")
            continue
        for f in (np.sqrt(0.5), 1.0, np.sqrt(2.0), 2.0):
            r = r30 * f
            res = clcurv.curvature(pts, r, method="mls2", orient=orient, uncertainty=True)
            ok = np.isfinite(res.mean) & np.isfinite(res.mean_se)
            sig = np.abs(res.mean[ok]) > 2 * res.mean_se[ok]
            out.append((name, path.name, len(pts), r, float(np.median(res.count)),
                        float(sig.mean()), float(np.median(res.mean_se[ok])),
                        float(np.median(res.roughness[ok])), int((~ok).sum())))
            log(f"{name} r {r:.4g}: {sig.mean():.1%} significant")
            if f == 1.0:
                png = RESULTS / f"{name}_significance.png"
                clcurv.render.render(pts, res.mean, png, field="mean_curvature", se=res.mean_se,
                                     up="z" if name == "autzen" else "auto",
                                     source=path, title=f"{name}: MLS2 H at r = {r:.4g}, "
                                     "grey where |H| < 2 SE", dpi=60)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=1e6)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--skip-cost", action="store_true")
    a = ap.parse_args(argv)
    n = int(a.points)
    dev = clcurv.get_device()
    print(f"CPU {cpu_model()}; device {dev.info.name}; load {loadavg()}\n")
    if not a.skip_cost:
        r, radii, rows = cost(n, a.repeats)
        print(f"## Cost ({n:,} points, noisy unit sphere, r = {r:.4g}: ~30 neighbours; "
              f"select among {', '.join(f'{x:.4g}' for x in radii)})\n")
        print("| call | without s | with s | ratio | peak RSS without MiB | with MiB | load |")
        print("|---|---:|---:|---:|---:|---:|---|")
        for name, ta, tb, q, ma, mb, ld in rows:
            print(f"| {name} | {ta:.3f} | {tb:.3f} | {q:.2f}x | {ma} | {mb} | {ld} |")
        print()
    print("## Real scans: MLS2 H significant (|H| > 2 SE)\n")
    print("| scan | file | points | radius | median neighbours | significant | median SE(H) "
          "| median roughness | no SE |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, f, n_, r, nb, sig, se, rough, bad in scans():
        print(f"| {name} | {f} | {n_:,} | {r:.4g} | {nb:.0f} | {sig:.1%} | {se:.4g} | "
              f"{rough:.3g} | {bad} |")


if __name__ == "__main__":
    sys.exit(main())
