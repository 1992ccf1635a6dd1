"""Tests written for the faults of the mutation check (bench/mutants.py, docs/mutants.md) that
the rest of the suite let through: each names the mutant it catches.

- ball-closed, features-ball-closed: every ball is the open ball |q - p| < r. On random
  points a point exactly at distance r has probability zero, so only a lattice whose
  coordinates and offsets are exact in float32 (multiples of 2^-3, cells of r = 2^-2 from a
  corner at the origin) tells < from <=: the 27 lattice points within 2 spacings of an inner
  point (1 + 6 + 12 + 8, not the 6 at exactly 2), the 93 within 3 (not the 30 at exactly 3).
"""
import numpy as np
import pytest

import clcurv

H = 0.125               # the lattice spacing: 2^-3, so every offset and r^2 is exact


def lattice(n=9):
    g = np.arange(n) * H
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    inner = np.all((pts >= 3 * H) & (pts <= (n - 4) * H), axis=1)
    return pts, inner


def lattice_count(m):
    """Lattice points strictly within m spacings of a point (the open ball)."""
    a = np.arange(-m, m + 1)
    i, j, k = np.meshgrid(a, a, a, indexing="ij")
    return int(np.count_nonzero(i * i + j * j + k * k < m * m))


def test_the_ball_is_open_on_a_lattice(device):
    """ball-closed: neighbours at exactly r are outside the ball (the kernels' d^2 < r^2), in
    the operators' walk and the features' largest ball, as in the float64 reference."""
    pts, inner = lattice()
    assert lattice_count(2) == 27 and lattice_count(3) == 93
    for m in (2, 3):
        r = m * H
        got = clcurv.curvature(pts, r, method="variation", device=device)
        ref = clcurv.curvature(pts, r, method="variation", backend="numpy")
        assert np.all(got.count[inner] == lattice_count(m)), np.unique(got.count[inner])
        np.testing.assert_array_equal(got.count, ref.count)


def test_every_ball_of_a_multi_radius_walk_is_open(device):
    """features-ball-closed: the smaller balls of one multi-radius walk (their own mask on
    the kept d^2) are open too, each equal to a call at that radius alone."""
    pts, inner = lattice()
    radii = [2 * H, 3 * H]
    got = clcurv.features(pts, radii, ["eigenvalue_sum"], device=device)
    ref = clcurv.features(pts, radii, ["eigenvalue_sum"], backend="numpy")
    for m, g, f in zip((2, 3), got, ref):
        assert np.all(g.count[inner] == lattice_count(m)), (m, np.unique(g.count[inner]))
        np.testing.assert_array_equal(g.count, f.count)


def test_scale_space_re_bins_when_a_point_drifted_past_the_margin(device):
    """scale-space-drift: the device's drift |x' - B| (B: the positions the grid was binned
    on) decides the re-binning; a drift under-reported lets points leave the cells that hold
    their balls. On a unit sphere at r = 0.6 each MLS1 step moves points by ~0.17 r, well past
    the MARGIN r = 0.1 r allowed between binnings: every step but the last re-bins, as the
    drifts of the float64 iterates say."""
    from clcurv.ops.smoothing import MARGIN
    pts = clcurv.shapes.sphere(4000, 1.0, seed=3)["points"]
    r, steps = 0.6, 3
    its, stats = clcurv.scale_space(pts, r, steps, return_iterates=True, return_stats=True,
                                    device=device)
    binned, want = its[0], 0
    for it in its[1:steps]:                     # the last step never re-bins
        d = np.linalg.norm(it - binned, axis=1).max() / r
        assert not 0.8 * MARGIN < d < 1.25 * MARGIN, d      # clear of the threshold
        if d > MARGIN:
            want, binned = want + 1, it
    assert want == steps - 1
    assert stats["rebins"] == want
