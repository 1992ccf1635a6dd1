"""PCL's own test of PrincipalCurvaturesEstimation, ported: clcurv's 2dcov2, given the normals
and the neighbourhoods of that test, returns PCL's published pc1, pc2 and principal
direction (issue 47: the local alignment of neighbour normals had moved them by 0.05).

The oracle: PCL's ``test/features/test_curvatures_estimation.cpp``, ``TEST (PCL,
PrincipalCurvaturesEstimation)`` (formerly in ``test_features.cpp``; read at PCL commit
0bb69c0c795e852ddd731039cc1b0ac96b11d8ed), on ``bun0.pcd`` (tests/data/pcl_bun0.pcd, 397
points; source and BSD licence in tests/data/README.md). What it runs, and what runs here:

1. Normals: ``NormalEstimation`` with ``setKSearch (10)`` on every index: PCA of the 10
   nearest points (the point itself included), the eigenvector of the smallest eigenvalue,
   flipped towards PCL's default viewpoint (0, 0, 0). Here: ``clcurv.normals(points, k=10,
   viewpoint=(0, 0, 0))`` on the device (the file's stored normals are not used).
2. Curvatures: ``computePointPrincipalCurvatures (*normals, p, indices, ...)`` with
   ``indices`` = every point, then ``compute ()`` with ``setKSearch (indices.size ())``:
   in both, every point's neighbourhood is the whole cloud. Here: a radius of 1.0, larger
   than the cloud's diameter (its box is 0.15 x 0.15 x 0.11), so every ball holds all 397
   points (asserted); clcurv's k-NN radius stops at k = 256.
3. PCL projects the neighbours' normals as given on the tangent plane, (I - n n^T) n_i,
   and returns the two largest eigenvalues of their scatter divided by the count (pc1,
   pc2) and the eigenvector of pc1 (``principal_curvature``): 2dcov2's count-normalised
   eigenvalues (uniform weights) and ``dir1``, with the normals used as given (the
   default for normals one passes; ``align_normals=True`` is not PCL's operator).

Expected values: both of PCL's blocks (``computePointPrincipalCurvatures`` and
``compute ()``, which differ from each other by up to 3.6e-7: summation order), at
points 0, 2, N - 3 and N - 1.

Tolerances (PCL's own test uses 1e-4 on every number):

* pc1, pc2: ``PC_TOL`` = 1e-6 absolute (4e-6 relative). PCL computes in float32: its two
  blocks differ by 3.6e-7; a float32 sum of 397 terms of size ~0.25 carries about
  sqrt(397) * 2^-24 * 0.25 ~ 3e-7. Measured on PoCL (float32 kernels, normals included):
  at most 2.7e-7 from PCL's numbers; float64 kernels and the float64 reference 2.3e-7.
* principal direction, up to its sign (eigen33's sign is arbitrary; PCL's test takes the
  absolute values at point 0): ``DIR_TOL`` = 2e-5 per component. PCL prints 5 decimals
  (rounding <= 5e-6); the eigenvector moves by about (error of the covariance) /
  (pc1 - pc2) ~ 3e-7 / 0.046 ~ 7e-6. Measured: at most 1.2e-5. PCL's y component at N - 1,
  -0.375851, keeps PCL's own 1e-3: with its x and z, that vector is not unit (norm^2
  0.99990); the unit one has y = -0.37599, PCL's own value at N - 3 (the same point of the
  scan).
"""
from pathlib import Path

import numpy as np
import pytest

import clcurv

BUN0 = Path(__file__).resolve().parent / "data" / "pcl_bun0.pcd"
PC_TOL = 1e-6
DIR_TOL = 2e-5
#: where PCL's published number is not self-consistent (see the docstring): PCL's tolerance
LOOSE = {("compute", -1, 1): 1e-3, ("point", -1, 1): 1e-3}
#: point 0 of the bunny: its pc1 when the neighbours' normals are aligned with its own
#: (align_normals=True) differs from PCL's by more than this (measured 5.1e-3)
ALIGNED_OFF = 1e-3

#: PCL's expected values: block -> point -> (pc1, pc2, principal direction); point -1 is
#: indices.size () - 1. Point 0's direction is published as absolute values.
PCL = {
    "point": {      # pc.computePointPrincipalCurvatures (*normals, p, indices, ...)
        0: (0.23997423052787781, 0.19400238990783691, (0.98509, 0.10714, 0.13462)),
        2: (0.27207490801811218, 0.19464978575706482, (0.98079, -0.04019, 0.19086)),
        -3: (0.25900053977966309, 0.17906945943832397, (0.86725, -0.37599, 0.32635)),
        -1: (0.2590005099773407, 0.17906956374645233, (0.86725, -0.375851, 0.32636)),
    },
    "compute": {    # pc.setKSearch (indices_size); pc.compute (*pcs)
        0: (0.23997458815574646, 0.19400238990783691, (0.98509, 0.10713, 0.13462)),
        2: (0.27207502722740173, 0.1946497857570648, (0.98079, -0.04019, 0.19086)),
        -3: (0.2590007483959198, 0.17906941473484039, (0.86725, -0.37599, 0.32636)),
        -1: (0.25900065898895264, 0.17906941473484039, (0.86725, -0.375851, 0.32636)),
    },
}
RADIUS = 1.0        # > the cloud's diameter: every neighbourhood is the whole cloud


def bun0():
    pts = clcurv.io.read(BUN0).points
    assert pts.shape == (397, 3)
    return np.asarray(pts, dtype=np.float64)


def pcl_errors(res):
    """{(block, point, what): |clcurv - PCL|}, what = 'pc1', 'pc2' or a direction component
    0, 1, 2 (direction up to its sign; absolute values at point 0, as PCL compares)."""
    err = {}
    for block, points in PCL.items():
        for p, (pc1, pc2, d) in points.items():
            err[(block, p, "pc1")] = abs(res.eigenvalues[p, 0] - pc1)
            err[(block, p, "pc2")] = abs(res.eigenvalues[p, 1] - pc2)
            ours = res.dir1[p]
            if p == 0:
                ours = np.abs(ours)
            else:
                ours = ours * np.sign(ours @ np.asarray(d))
            for c in range(3):
                err[(block, p, c)] = abs(ours[c] - d[c])
    return err


def check_pcl(res):
    np.testing.assert_array_equal(res.count, 397)     # the whole cloud, as in PCL's test
    assert (res.status == 0).all()
    err = pcl_errors(res)
    for key, e in err.items():
        tol = PC_TOL if key[2] in ("pc1", "pc2") else LOOSE.get(key, DIR_TOL)
        assert e <= tol, f"{key}: clcurv differs from PCL's published value by {e:.3g} " \
                         f"(tolerance {tol:g})"
    return err


def _runs(device):
    out = [("float", "opencl")]
    if device.info.fp64:
        out.append(("double", "opencl"))
    return out + [("double", "numpy")]     # the float64 reference, on the device's normals


def test_2dcov2_reproduces_pcl_principal_curvatures(device):
    pts = bun0()
    for precision, backend in _runs(device):
        nrm = clcurv.normals(pts, k=10, viewpoint=(0.0, 0.0, 0.0), device=device,
                             precision="double" if precision == "double" else "float")
        assert np.isfinite(nrm).all()
        res = clcurv.curvature(pts, RADIUS, method="2dcov2", normals=nrm, device=device,
                               precision=precision, backend=backend)
        err = check_pcl(res)
        pc = max(v for k, v in err.items() if k[2] in ("pc1", "pc2"))
        d = max(v for k, v in err.items() if k[2] not in ("pc1", "pc2") and k not in LOOSE)
        print(f"\n{precision} {backend}: pc1/pc2 max |clcurv - PCL| {pc:.3g}, direction "
              f"{d:.3g}")
        # the option that is not PCL's operator: aligning the neighbours' normals with the
        # query point's changes point 0's pc1 (what issue 47 reported)
        aligned = clcurv.curvature(pts, RADIUS, method="2dcov2", normals=nrm, device=device,
                                   precision=precision, backend=backend, align_normals=True)
        off = abs(aligned.eigenvalues[0, 0] - PCL["point"][0][0])
        assert off > ALIGNED_OFF, off
