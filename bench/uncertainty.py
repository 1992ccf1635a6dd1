"""Calibration of the float64 reference's standard errors (issue 51).

    python -m bench.uncertainty            # the full study (a few minutes, one core)
    python -m bench.uncertainty --quick    # fewer seeds

For every case a dense patch of a shape with known curvature (clcurv.data.shapes: a sphere
cap, an ellipsoid patch, the wave ``z = A sin(wx) sin(wy)``), sized so that a ball of radius
``r`` holds about NB neighbours, with Gaussian noise of ``sigma = c r`` along the true normal.
On the interior points (balls inside the patch) the z-score ``(estimate - truth) / SE`` of
MLS2's H and k1 and of MLS1's H (clcurv.reference.uncertainty) is summarised: its mean, its
standard deviation (``std``), its RMS and the fraction with ``|z| < 1.96``. The issue's
targets: ``std`` in [0.85, 1.2] and 92-97.5% within 1.96.

**Radius choice.** The bias is the error the estimator makes on the *noise-free* patch (same
sample positions: the geometric ``O(r^2)`` term and, for MLS1, the position sampling's
share); it is measured per case, and the calibration radius is the largest of a grid (``k r``
with ``k`` the largest |k| of the patch) whose ``RMS(bias) <= 0.1 RMS(SE)``. The sweep at
``c = 1%`` shows the z-scores as ``r`` grows past it, where the bias takes over.

Writes bench/results/uncertainty.md and uncertainty.json.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clcurv.data import shapes
from clcurv.reference import uncertainty as unc

RESULTS = Path(__file__).resolve().parent / "results"
#: neighbours per ball (about)
NB = 40
#: points per patch
POINTS = 10_000
#: noise levels, sigma / r
NOISE = (0.005, 0.01, 0.02)
#: the grid of k_max r
KR = (0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64)
#: the issue's targets
STD_RANGE, COVER_RANGE = (0.85, 1.2), (0.92, 0.975)
#: the shapes: largest |k| of the patch (for the radius grid)
KMAX = {"sphere": 1.0, "ellipsoid": 2.3, "wave": 0.1 * (2 * np.pi) ** 2}
#: areas of the closed shapes (the ellipsoid's by Thomsen's formula)
FULL_AREA = {"sphere": 4 * np.pi, "ellipsoid": 7.98}
#: area of the shape over the area of the unit sphere near the patch's axis
AREA_ELEMENT = {"sphere": 1.0, "ellipsoid": 0.62}
#: at least this many interior points per case (more seeds where the patches are small)
MIN_POINTS = 8000
ESTIMATORS = ("mls2 H", "mls2 k1", "mls2 K", "mls1 H", "mls1 H, plane noise",
              "mls2 k1 debiased")
#: the normals: RMS of angle / SE (1 if calibrated) and the fraction of angles below
#: sqrt(-2 ln 0.05) / sqrt(2) SE = 1.73 SE (95% for an isotropic 2D Gaussian of variance SE^2)
NORMALS = ("mls1 (PCA) normal", "mls2 normal")
ANGLE_95 = float(np.sqrt(-np.log(0.05)))


def patch(shape, r, c, points=POINTS, nb=NB, seed=0, noise=True):
    """A patch of ``shape`` for balls of radius ``r`` (about ``nb`` neighbours) with noise
    ``c r`` along the true normal; also the interior mask (balls 2 r inside the patch)."""
    area = points * np.pi * r * r / nb
    sig = c * r if noise else 0.0
    # a patch wider than a cap of 1.2 rad: the whole closed shape (no border), as many
    # points as give ``nb`` neighbours
    full = shape in FULL_AREA and area > 2 * np.pi * (1 - np.cos(1.2)) * AREA_ELEMENT[shape]
    if full:
        points = int(FULL_AREA[shape] * nb / (np.pi * r * r))
    if shape == "sphere":
        cap = None if full else np.arccos(1.0 - area / (2 * np.pi))
        s = shapes.sphere(points, 1.0, noise=sig, seed=seed, cap=cap)
        clean = shapes.sphere(points, 1.0, seed=seed, cap=cap)["points"]
        inner = (np.ones(points, dtype=bool) if full else
                 np.arccos(np.clip(clean[:, 2], -1, 1)) < cap - 2 * r)
    elif shape == "ellipsoid":
        axes, axis = np.array([1.0, 0.8, 0.6]), np.array([0.0, 1.0, 0.3]) / np.hypot(1, 0.3)
        # a cap of the parametric sphere around ``axis`` with about the wanted area (the
        # area element is ~0.62 of the sphere's there)
        cap = None if full else np.arccos(1.0 - area / (2 * np.pi * AREA_ELEMENT[shape]))
        s = shapes.ellipsoid(points, axes, noise=sig, seed=seed, cap=cap, axis=axis)
        clean = shapes.ellipsoid(points, axes, seed=seed, cap=cap, axis=axis)["points"]
        u = clean / axes
        u /= np.linalg.norm(u, axis=1)[:, None]
        inner = (np.ones(points, dtype=bool) if full else
                 np.arccos(np.clip(u @ axis, -1, 1)) < cap - 2 * r / 0.6)
    elif shape == "wave":
        ext = 0.5 * np.sqrt(area / 1.25)
        s = shapes.wave(points, 0.1, 1.0, ext, noise=sig, seed=seed)
        clean = shapes.wave(points, 0.1, 1.0, ext, seed=seed)["points"]
        inner = np.all(np.abs(clean[:, :2]) < ext - 2 * r, axis=1)
    else:
        raise ValueError(shape)
    s["inner"] = inner
    s["clean"] = clean
    return s


def estimates(s, r):
    """{estimator: (estimate, SE)} on the patch ``s``."""
    m2 = unc.mls2_uncertainty(s["points"], r, s["normals"])
    m1 = unc.mls1_uncertainty(s["points"], r, s["normals"])
    m1p = unc.mls1_uncertainty(s["points"], r, s["normals"], noise="plane")
    return {"mls2 H": (m2["mean"], m2["mean_se"]), "mls2 k1": (m2["k1"], m2["k1_se"]),
            "mls2 K": (m2["gaussian"], m2["gaussian_se"]),
            "mls2 k1 debiased": (m2["k1_debiased"], m2["k1_se"]),
            "mls1 H": (m1["mean"], m1["mean_se"]),
            "mls1 H, plane noise": (m1p["mean"], m1p["mean_se"]),
            "mls1 (PCA) normal": (m1["normals"], m1["normal_se"]),
            "mls2 normal": (m2["normals"], m2["normal_se"]),
            "_": (m2["count"], m2["roughness"])}


def truth(s, est):
    return {"k1": s["k1"], "K": s["K"]}.get(est.split()[1], s["H"])


def zstats(z):
    z = z[np.isfinite(z)]
    return {"n": int(len(z)), "mean": float(z.mean()), "std": float(z.std()),
            "rms": float(np.sqrt(np.mean(z * z))), "cover": float(np.mean(np.abs(z) < 1.96))}


def run_case(shape, r, c, seeds):
    """z-scores and bias ratio of every estimator, pooled over ``seeds``."""
    zs = {e: [] for e in ESTIMATORS + NORMALS}
    bias, se_all, counts, rough = ({e: [] for e in ESTIMATORS}, {e: [] for e in ESTIMATORS},
                                   [], [])
    first = patch(shape, r, c, seed=seeds[0])
    more = int(np.ceil(MIN_POINTS / max(1, first["inner"].sum())))
    seeds = tuple(seeds) + tuple(range(100, 100 + max(0, more - len(seeds))))
    for seed in seeds:
        noisy = first if seed == seeds[0] else patch(shape, r, c, seed=seed)
        clean = dict(noisy, points=noisy["clean"])
        got, ref = estimates(noisy, r), estimates(clean, r)
        inner = noisy["inner"]
        for e in ESTIMATORS:
            t = truth(noisy, e)[inner]
            est, se = got[e][0][inner], got[e][1][inner]
            zs[e].append((est - t) / se)
            bias[e].append(ref[e][0][inner] - t)
            se_all[e].append(se)
        for e in NORMALS:
            cos = np.einsum("ij,ij->i", got[e][0][inner], noisy["normals"][inner])
            zs[e].append(np.arccos(np.clip(cos, -1.0, 1.0)) / got[e][1][inner])
        counts.append(got["_"][0][inner])
        rough.append(got["_"][1][inner] / (c * r))
    out = {"shape": shape, "r": r, "kr": r * KMAX[shape], "c": c,
           "neighbours": float(np.mean(np.concatenate(counts))),
           "roughness_over_sigma": float(np.nanmedian(np.concatenate(rough)))}
    for e in NORMALS:
        a = np.concatenate(zs[e])
        a = a[np.isfinite(a)]
        out[e] = {"rms": float(np.sqrt(np.mean(a * a))), "cover": float(np.mean(a < ANGLE_95))}
    for e in ESTIMATORS:
        b, se = np.concatenate(bias[e]), np.concatenate(se_all[e])
        ok = np.isfinite(b) & np.isfinite(se)
        out[e] = zstats(np.concatenate(zs[e])) | {
            "bias_over_se": float(np.sqrt(np.mean(b[ok] ** 2)) / np.sqrt(np.mean(se[ok] ** 2)))}
    return out


def met(stats):
    return (STD_RANGE[0] <= stats["std"] <= STD_RANGE[1]
            and COVER_RANGE[0] <= stats["cover"] <= COVER_RANGE[1])


def choose_radius(rows, est):
    """The largest radius of the sweep rows whose bias/SE <= 0.1 (None if none)."""
    ok = [row for row in rows if row[est]["bias_over_se"] <= 0.1]
    return max(ok, key=lambda row: row["r"]) if ok else None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--report", action="store_true",
                    help="only rewrite uncertainty.md from uncertainty.json")
    args = ap.parse_args(argv)
    if args.report:
        saved = json.loads((RESULTS / "uncertainty.json").read_text())
        write_markdown(saved["sweep"], saved["chosen"], saved["seconds"], saved["seeds"])
        return
    sweep_seeds = (0,) if args.quick else (0, 1)
    t0 = time.time()
    sweep = []
    for shape in KMAX:
        for c in NOISE:
            for kr in KR:
                row = run_case(shape, kr / KMAX[shape], c, sweep_seeds)
                sweep.append(row)
                print(f"{shape:9s} c={c:.3f} kr={kr:.3f} n={row['neighbours']:.0f} "
                      + " ".join(f"{e}: {row[e]['std']:.2f}/{row[e]['cover']:.3f}"
                                 f"/b{row[e]['bias_over_se']:.2f}" for e in ESTIMATORS),
                      flush=True)
    chosen = []
    for shape in KMAX:
        for c in NOISE:
            rows = [row for row in sweep if row["shape"] == shape and row["c"] == c]
            for e in ESTIMATORS:
                row = choose_radius(rows, e)
                if row is not None:
                    chosen.append({"shape": shape, "c": c, "estimator": e, "r": row["r"],
                                   "kr": row["kr"], "neighbours": row["neighbours"]}
                                  | row[e])
    elapsed = time.time() - t0
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "uncertainty.json").write_text(json.dumps(
        {"sweep": sweep, "chosen": chosen, "seconds": elapsed, "points": POINTS,
         "neighbours": NB, "seeds": len(sweep_seeds)}, indent=1))
    write_markdown(sweep, chosen, elapsed, len(sweep_seeds))


NOTES = """
## What the numbers say

* **MLS2 H** is calibrated at every calibration radius (std z 1.02-1.05, 94-95% within
  1.96). Its t-like tails (about 35 residual dof: a t-distribution with 35 dof has std
  1.03) put the std a few % above 1.
* **MLS2 k1** is calibrated on the ellipsoid and the wave. On the **sphere** (every point an
  umbilic, k1 = k2) coverage is about 90%, below the 92% target, with std z ~0.91 and mean z
  ~+0.8: k1 = H + D with D = sqrt(H^2 - K) >= 0 is the larger of two noisy eigenvalues, so
  where the true D is 0 the estimate's D is a Rayleigh-like variable of mean ~1.25 SE(D), an
  order-statistic bias that no first-order SE contains (simulated: with Var(H) = 2 s^2 and
  the deviator's two components of variance s^2 each, z = (N(0, 2) + Rayleigh(1)) / sqrt(3)
  has mean 0.72, std 0.90 and 91.3% within 1.96, close to the measured values). A wider
  SE trades std for coverage: only 3-6% wider meets both targets at an exact umbilic
  (simulated: SE^2 = 3.2-3.36 s^2 instead of 3 s^2 gives std 0.87-0.85 and 92.3-93.1%), a
  fit to the targets rather than a model, so it is not done. The cure belongs to the
  estimator: **'mls2 k1 debiased'** (clcurv.reference.uncertainty.debiased_principal, a
  proposal) is H + sqrt(max(D^2 - T, 0)) with T = SE(H)^2 - (cov(L, N) - var M) / w^2 the
  second-order excess of E[D^2], scored with the same k1_se: it meets both targets on the
  sphere and stays within them on the ellipsoid and the wave (its mean z moves from about
  +0.1..+0.3 to -0.1..-0.2 there). H and K are smooth at umbilics and unaffected. Where
  |k1 - k2| is several SE(k1) (most points of the ellipsoid and the wave) the shift
  vanishes.
* **MLS2 K** (not an issue target) is calibrated at the calibration radii but for the
  ellipsoid at sigma = 2% r (std 1.20, 91%). K is a product of two noisy curvatures: its
  first-order SE holds only where SE(k) is small against |k|, i.e. where K is
  significant. At small k r (the sweep's first rows, where SE(H) is of the order of H) the
  z-scores are too narrow (std 0.6) or too wide (1.3): the delta method is not enough there.
  (An exact second-order variance term, K being quadratic in the second derivatives, was
  tried: it fixes neither side, because the plug-in gradient is itself noisy.)
* **MLS1 H**: the estimate 4 <p - o, n> / r^2 holds the point's own noise with weight
  1 - 1/n, so its SE is ~4 sigma / r^2 and does not fall as 1/sqrt(n). With the point's
  own noise taken from the quadric's residuals (the default) it is calibrated everywhere
  (std 1.00, 95%), even far beyond the calibration radius: its bias is small against
  that large SE (on a sphere MLS0/MLS1 are unbiased: the ball cuts a cap whose heights are
  uniform). With the plane's residual (`noise="plane"`, the issue's first rule) the SE
  also counts the curvature's spread of heights about the plane, k^2 r^4 / 48 on a sphere:
  conservative once k r passes ~4 sigma / r (std z 0.66 at k r = 0.08, sigma = 1% r), so it
  misses the 97.5% ceiling in 3 of the 9 cases even at the calibration radius.
* The **bias** column is RMS(noise-free error) / RMS(SE) on the same sample positions. For
  MLS1 the noise-free error is mostly the random position sampling of the neighbours, which
  MLS1's SE covers (its neighbours' term), so the 0.1 rule is conservative for MLS1.
* **Where calibration breaks**: MLS2 at k r >= 0.32 (sigma = 0.5% r: 73% within 1.96 on
  the sphere, 89% on the wave; k r = 0.64: 0-77%) as the O(r^2) bias passes the SE; the
  smaller the noise, the earlier (the SE shrinks with sigma, the bias does not). The
  roughness (the quadric's residual RMS) then grows above sigma (wave, k r = 0.64: 3.2
  sigma) because the quadric no longer fits: a usable warning sign. MLS1 on the wave loses
  calibration in the other direction first (std 0.81 at k r = 0.64, sigma = 0.5% r: the
  quadric's misfit inflates its noise estimate), then by bias (k r = 1.28: std 1.23,
  90%).
* **Normals** (not an issue target): RMS(angle / SE) and the fraction of angles under
  1.73 SE (95% for an isotropic 2D Gaussian). Both the PCA normal's SE and the fitted
  (MLS2) normal's are calibrated at small k r (RMS 1.01-1.05, 93-95%). The PCA normal's
  own bias (its tilt where the curvature varies across the ball) shows first on the wave:
  RMS 1.20 and 88% at k r = 0.04 with sigma = 0.5% r; the fitted normal holds to about
  k r = 0.08-0.16, then its bias (the quadric's misfit of the slope) dominates.
"""


def write_markdown(sweep, chosen, elapsed, seeds):
    lines = []
    lines += ["# Calibration of the standard errors (issue 51, float64 reference)", "",
              f"Generated by `python -m bench.uncertainty` in {elapsed:.0f} s "
              f"({POINTS} points per patch, about {NB} neighbours per ball, at least "
              f"{seeds} seed(s) and {MIN_POINTS} interior points per case). Shapes: a unit "
              "sphere (cap), an ellipsoid with semi-axes (1, 0.8, 0.6) around the direction "
              "(0, 1, 0.3), the wave z = 0.1 sin(2 pi x) sin(2 pi y); noise sigma = c r along "
              "the true normal; z = (estimate - truth) / SE on the interior points. "
              "'mls1 H' uses the default noise='quadric'.", "",
              "## At the calibration radius (bias <= 0.1 SE)", "",
              "The largest k_max r of the grid " + ", ".join(f"{k:g}" for k in KR)
              + " whose RMS(noise-free error) <= 0.1 RMS(SE), per shape, noise and "
              "estimator.", "",
              "| shape | sigma / r | estimator | k_max r | neighbours | points | mean z | "
              "std z | RMS z | within 1.96 | bias / SE | targets met |",
              "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for row in chosen:
        lines.append(f"| {row['shape']} | {row['c']:.3f} | {row['estimator']} | {row['kr']:.3f} "
                     f"| {row['neighbours']:.0f} | {row['n']} | {row['mean']:+.2f} | "
                     f"{row['std']:.2f} | {row['rms']:.2f} | {100 * row['cover']:.1f}% | "
                     f"{row['bias_over_se']:.3f} | {'yes' if met(row) else 'NO'} |")
    lines += NOTES.splitlines()
    lines += ["", "## The sweep: std z / within 1.96 / bias over SE, as r grows", ""]
    for c in NOISE:
        lines += [f"### sigma = {100 * c:g}% of r", "",
                  "| shape | k_max r | " + " | ".join(ESTIMATORS) + " | roughness / sigma | "
                  + " | ".join(f"{e}: RMS angle/SE, < 1.73 SE" for e in NORMALS) + " |",
                  "|---|---:|" + "---|" * len(ESTIMATORS) + "---:|" + "---|" * len(NORMALS)]
        for row in sweep:
            if row["c"] != c:
                continue
            cells = [f"{row[e]['std']:.2f} / {100 * row[e]['cover']:.0f}% / "
                     f"{row[e]['bias_over_se']:.2f}" for e in ESTIMATORS]
            cells += [f"{row['roughness_over_sigma']:.2f}"]
            cells += [f"{row[e]['rms']:.2f} / {100 * row[e]['cover']:.0f}%" for e in NORMALS]
            lines.append(f"| {row['shape']} | {row['kr']:.3f} | " + " | ".join(cells) + " |")
        lines.append("")
    (RESULTS / "uncertainty.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
