"""Timings of the float64 host code: the reference's moments (clcurv.reference.operators.moments) and
the two host orientations, clcurv.orient.orientation.flip_by_propagation (the device forest's host
twin) and clcurv.reference.operators.mst_flips (the numpy backend's own), on a sphere and on the
shapes of tests/test_reference.py's orientation cases.

Run from the repository root::

    python -m bench.reference_speed                # 100k sphere points, r = 0.1
    python -m bench.reference_speed --points 20000 --repeats 3

Prints one row per step: wall time (the minimum of ``--repeats`` runs after one untimed
warm-up), points per second, and for the orientations the fraction of normals oriented
outward (the exact normals are known). Nothing is asserted here: the tests check the
results (tests/test_reference.py, tests/test_reference_independent.py), this module only
measures them, on whatever else the machine is doing.
"""
from __future__ import annotations

import argparse

import numpy as np

from clcurv.orient import orientation as orient
from clcurv.reference import operators as reference
from clcurv import shapes

from .harness import timeit

#: the orientation shapes of tests/test_reference.py (name: sampler, radius)
SHAPES = {
    "sphere": (lambda n: shapes.sphere(n, 2.0, seed=7), 0.2),
    "torus": (lambda n: shapes.torus(n, 2.0, 0.5, seed=9), 0.12),
    "open cylinder": (lambda n: shapes.cylinder(n, 1.0, 4.0, seed=10), 0.15),
    "hollow shell": (lambda n: shapes.hollow_shell(n, 2.0, 1.5, seed=8), 0.15),
}


def _outward(flip, normals, truth):
    out = np.where(flip[:, None], -normals, normals)
    return float(np.mean(np.einsum("ij,ij->i", out, truth) > 0))


def run(points=100_000, radius=0.1, shape_points=20_000, repeats=1):
    """The rows (name, points, seconds, outward fraction or None) of the report."""
    rows = []
    s = shapes.sphere(points, 2.0, seed=12)
    m = reference.moments(s["points"], radius)
    rows.append((f"reference.moments, sphere r = {radius:g} (mean count "
                 f"{np.nanmean(m['count']):.0f})", points,
                 timeit(lambda: reference.moments(s["points"], radius), repeats), None))
    for name, fn in (("orient.flip_by_propagation", orient.flip_by_propagation),
                     ("reference.mst_flips", reference.mst_flips)):
        t = timeit(lambda: fn(s["points"], m["normals"], 10), repeats)
        rows.append((f"{name}, sphere", points, t,
                     _outward(fn(s["points"], m["normals"], 10), m["normals"], s["normals"])))
    for shape, (make, r) in SHAPES.items():
        sh = make(shape_points)
        sign = np.random.default_rng(len(shape)).choice([-1.0, 1.0], (shape_points, 1))
        n = reference.moments(sh["points"], r)["normals"] * sign
        for name, fn in (("orient.flip_by_propagation", orient.flip_by_propagation),
                         ("reference.mst_flips", reference.mst_flips)):
            t = timeit(lambda: fn(sh["points"], n, 10, r), repeats)
            rows.append((f"{name}, {shape} r = {r:g}", shape_points, t,
                         _outward(fn(sh["points"], n, 10, r), n, sh["normals"])))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=100_000, help="sphere points (100000)")
    ap.add_argument("--radius", type=float, default=0.1, help="ball radius on the R = 2 "
                    "sphere (0.1: ~25 neighbours)")
    ap.add_argument("--shape-points", type=int, default=20_000,
                    help="points of each orientation shape (20000)")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args(argv)
    rows = run(args.points, args.radius, args.shape_points, args.repeats)
    width = max(len(r[0]) for r in rows)
    print(f"{'step':<{width}}  {'points':>8}  {'s':>7}  {'M pts/s':>7}  outward")
    for name, n, t, out in rows:
        frac = "" if out is None else f"{out:.5%}"
        print(f"{name:<{width}}  {n:>8}  {t:>7.3f}  {n / t / 1e6:>7.3f}  {frac}")
    return rows


if __name__ == "__main__":
    main()
