"""Tolerances and targets, declared once: the bench (bench/run.py, bench/paper.py) and the
tests (``from bench.targets import ...``) import them from here.

Kept out of the package on purpose: an installed clcurv has no use for them. Plain numbers
only (no imports), so that a test can import this module cheaply.

Accuracy tolerances bound float32 kernels against the float64 NumPy reference
(clcurv.reference.operators) on the points whose neighbour counts agree with the reference's (float32
may put a neighbour at distance ~r on the other side of the ball). The tests assert them on
15k-200k-point clouds, mostly on the worst point; the bench, on the polar cap of a
whole-cloud run, on the 99.9th percentile (equal counts do not guarantee equal neighbour
sets there).
"""

# ------------------------------------------------------------------- kernels vs reference
# normals: 1 - |cos| to the reference's PCA normal; float32 sums of ~30-1000 terms give ~1e-7
COS_TOL = 1e-4
# fraction of points with the reference's neighbour count (others: a neighbour at |q - p| ~ r)
AGREE_MIN = 0.998
# lambda_0 and variation: relative error, 99.9th percentile (second-pass lambda_0 keeps digits)
L0_REL_TOL = 1e-3
# surface variation: median relative error over the bench's cap (the bench's view of L0_REL_TOL)
VAR_MEDIAN_TOL = 1e-3
# 2dcov1, 2dcov2, 3dcov: |k1 - k1_ref| / k1_ref (products of float32 sums; ~1e-5 seen)
COV_K1_TOL = 1e-3
# MLS2: |k - k_ref| / max(|k1_ref|, |k2_ref|), k1 and k2 (6x6 float32 solve; ~1e-5 seen)
MLS2_K_TOL = 1e-3
# MLS2 projection: |p'_kernel - p'_ref| / r (p' = Q + a0 v0; a0 from the 6x6 float32 solve)
MLS2_PROJ_TOL = 1e-5
# MLS1 scale space: |position - reference| / r after N steps (displacement kept apart: no growth)
SS_TOL = 1e-5

# ------------------------------------------------------------------- contention guard
# 2-thread / 1-thread speed of a PoCL spin kernel, at least, else cores shared (free: ~2.0)
THREADS_MIN_GAIN = 1.6

# ------------------------------------------------------------------- speed targets (bench)
# the project's goals; the bench evaluates them at its largest size (1M points in a full run)
# curvature(P, r, method="variation") with default arguments (an unsigned method: normals and
# variation, no orientation) end to end / Open3D estimate_normals with the same radius on the
# spatially sorted copy of the same cloud, same run (interleaved pairs: peers.VARIATION_PAIRS),
# at least
DEFAULT_VARIATION_VS_OPEN3D = 10.0
# curvature(P, r, method="mls2", scale_space=5) with default arguments (the scale space, the
# PCA normals, their orientation on the device, MLS2) end to end, seconds at ~30 neighbours, at most
PIPELINE_DEFAULT_MAX_S = 1.5
# orientation alone (clcurv.orient.orientation.flip_on_device: k-NN graph, spanning forest, signs; the
# cloud binned beforehand), M points/s, at least
ORIENT_MPTS = 2.0
# moments kernel alone (lambda_0 refined), M points/s at ~30 neighbours, at least
KERNEL_MPTS_AT_30 = 5.0
# variation end to end / the NumPy reference's moments (extrapolated to n), at least
VS_REFERENCE = 50.0
# binning time / moments kernel time, at most: host binning must not dominate
BINNING_OVER_KERNEL_MAX = 1.0
# orientation alone (flip_on_device, k = 10) / Open3D orient_normals_consistent_tangent_plane(10)
# on the same 100k-point cloud and normals, at least
ORIENT_VS_OPEN3D = 10.0
# MLS2 (normals=) end to end / the NumPy reference's MLS2 (extrapolated to n), at least
MLS2_VS_REFERENCE = 50.0
# MLS2 (normals=) time / clcurv.normals(orient=None) time, at most (interleaved runs)
MLS2_VS_NORMALS = 2.0
# each covariance operator (normals=) time / clcurv.normals time, at most (interleaved runs)
COV_VS_NORMALS = 1.5
# pipeline curvature(method="mls2", scale_space=5, normals=exact) at ~30 neighbours, seconds, below
PIPELINE_MAX_S = 5.0
# one scale-space iteration's points/s / Open3D estimate_normals points/s, at least
SS_VS_OPEN3D = 5.0

# ------------------------------------------------------------------- the paper (Digne & Morel)
# what "reliable", "signed" and "stable" mean in bench/paper.py's verdicts and tests/test_paper.py
# after the scale space, mean H within this fraction of the exact H (and k1 of the exact k1)
PAPER_REL_TOL = 0.1
# after the scale space, MLS2's k2 within this fraction of the exact k1 from the exact k2
PAPER_K2_TOL = 0.1
# after the scale space, MLS2's median principal direction error, degrees, below
PAPER_DIR1_MAX_DEG = 10.0
# iterated MLS2's H std / iterated MLS1's H std from iteration 3 on, at least (paper: ~4)
PAPER_STABILITY_MIN = 2.0
# Table 1's MLS1 iterate k: |mean H x sqrt(R^2 - k r^2 / 2) - 1| (curvature motion; ~0.3% seen)
PAPER_MCM_TOL = 0.02
