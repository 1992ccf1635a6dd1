"""The demo (``clcurv demo``, ``make demo``): the paper's pipeline on the bundled bunny.

:func:`run` reads the Stanford bunny (:func:`clcurv.data.sample_path`, 35,947 points,
metres), picks the radius for about 30 neighbours, runs 3 MLS1 scale-space steps then MLS2
(Digne & Morel's recommended pipeline), and writes into ``outdir``:

* ``bunny_mls2.ply``: the input positions and order, the fitted normals (``nx ny nz``) and
  every field (``--fields all``: the principal directions too, which the paper's pipeline
  estimates) ``mean_curvature`` (H, 1/m), ``gaussian_curvature`` (K, 1/m^2), ``k1 >= k2``
  (signed, 1/m), ``dir1_*``, ``dir2_*``, ``neighbours``, ``status``;
* ``bunny_mean_curvature.png``: the cloud coloured by H (needs matplotlib).

Outward normals: convex parts of the bunny have H > 0.
"""
from __future__ import annotations

from pathlib import Path

from clcurv.data import sample_path
from clcurv.jobs.job import Job, run as run_job
from clcurv.render import MissingMatplotlibError, render

__all__ = ["run", "PLY_NAME", "PNG_NAME", "SCALE_SPACE_STEPS"]

PLY_NAME = "bunny_mls2.ply"
PNG_NAME = "bunny_mean_curvature.png"
#: MLS1 scale-space steps before MLS2
SCALE_SPACE_STEPS = 3


def run(outdir="out", device=None, quiet=False, out=print):
    """Run the demo into ``outdir`` (created), printing on ``out``; return the
    :class:`clcurv.jobs.job.Done` of the MLS2 job. ``device``: as for :func:`clcurv.get_device`;
    ``quiet``: no progress bars."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    job = Job(sample_path(), outdir / PLY_NAME, method="mls2", radius="auto",
              scale_space=SCALE_SPACE_STEPS, fields=["all"], device=device, quiet=quiet)
    out(f"demo: the bundled Stanford bunny ({job.input}), the paper's pipeline: "
        f"{SCALE_SPACE_STEPS} MLS1 scale-space iterations, then MLS2")
    done = run_job(job, out)
    try:
        png = render(done.points, done.result.mean, outdir / PNG_NAME,
                     field="mean_curvature", unit="1/m")
    except MissingMatplotlibError:
        out("matplotlib is not installed: no picture (pip install matplotlib)")
    else:
        out(f"wrote {png}")
    return done
