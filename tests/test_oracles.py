"""External oracles through the OpenCL kernels, in the default precision (float32), on the
small files of tests/data (sources and licences in tests/data/README.md): a bare clone runs
them. PCL's PrincipalCurvaturesEstimation is tests/test_pcl_oracle.py; jakteristics'
features in float32 are tests/test_features.py::test_against_jakteristics_float32.

CGAL jet fitting (MLS2)
-----------------------
The oracle: CGAL's Jet_fitting_3 package, ``Monge_via_jet_fitting`` on
``data/in_points_d4.txt`` (tests/data/cgal_jet_fitting_in_points_d4.txt, 17 points sampled
on z = 0.1 x^2 + 0.2 y^2, "in_points are sampled on 0.1(x²+2y²)" says the example's README;
the first point, the origin, is where the fit is evaluated). The example
``examples/Jet_fitting_3/Single_estimation.cpp`` prints the Monge form of that point
(``./Single_estimation data/in_points_d4.txt 4 4``); CGAL publishes no output file for it,
but its test ``test/Jet_fitting_3/blind_1pt.cpp`` runs the same fit (degree 4, Monge degree
4) on the same file and asserts the published numbers: after
``comply_wrt_given_normal (-normal)`` the principal curvatures (k1, k2) are (0.4, 0.2) or
(-0.2, -0.4) (the two orientations of the fit's normal), each within 0.01 (its
``precision``). Those are the exact quadric's curvatures at its vertex: 2 x 0.2 = 0.4
along y and 2 x 0.1 = 0.2 along x, normal z.

Sign conventions. CGAL's Monge form is z = (k1 x^2 + k2 y^2) / 2 in its basis (d1, d2, n):
a surface that bends towards n has positive curvatures. clcurv's are outward (a sphere
with outward normals has k = +1/R): the opposite sign for the same normal. So clcurv's
(k1, k2) with normal n are CGAL's (k1, k2) with normal -n, and both orientations are
checked here: viewpoint above (normal +z) gives (-0.2, -0.4), dir1 = x; viewpoint below
(normal -z) gives (0.4, 0.2), dir1 = y (CGAL's maximal direction d1 of k1 = 0.4).

Why MLS2 must give the same numbers, and the tolerance. CGAL: a PCA of the 17 points gives
the fitting basis (z = the eigenvector of the smallest eigenvalue), a least-squares jet of
degree d in that basis with origin p, then the Monge form at the projection of p on the jet.
MLS2 (kernels/mls2.cl): a PCA of the ball (a radius of 4 > the farthest point, 3.07: all 17
points, asserted), a least-squares quadric of the heights in the PCA frame at the projection
of p on the regression plane, with uniform ball weights, then the curvatures of that
quadric's graph at the origin. The point set is symmetric under x -> -x and y -> -y, so its
covariance is diagonal and both PCA normals are exactly z; the 17 points lie exactly on a
quadric in that frame, so CGAL's jet (degree 2 or its test's 4: 17 >= 15 coefficients) and
MLS2's weighted quadric both reproduce z = 0.1 x^2 + 0.2 y^2 exactly (weights and the
origin's height do not matter for an exact fit), and the two differ by round-off only.
MLS2 solves its 6x6 normal equations in float32 with (x, y) scaled by 1/r: their condition
number is 131 here (numpy), so the coefficients carry a relative error of about
131 x 2^-24 = 7.8e-6, i.e. 3.1e-6 on k1 = 0.4. ``K_TOL`` = 1e-5 (a margin of 3); the
principal directions move by the error over the gap k1 - k2 = 0.2: ``DIR_TOL`` = 5e-5.
Measured (PoCL, AMD EPYC): 2.4e-8 on the curvatures, 1.8e-8 on the directions. CGAL's own
tolerance, 0.01, is asserted too (it allows a fitting error; there is none here).

Open3D normals
--------------
``PointCloud.estimate_normals`` (Open3D's PCA normal, float64) with a radius search and a
hybrid search (radius and max_nn >= the cloud's size: the same neighbours) of the radius
clcurv gets, on PCL's bun0.pcd (397 points, tests/data). Open3D is an optional dependency
(the ``bench`` extra, open3d-cpu on PyPI): the test skips, saying so, without it. Both take
the ball of the points at distance < r (nanoflann's radius search is strict, clcurv's ball
open) and return the eigenvector of the smallest eigenvalue of the ball's covariance, with
an arbitrary sign: compared up to sign, as the angle's sine |n_clcurv x n_open3d|.

Which points (the rule): those whose normal is well posed, where the relative eigen-gap
g = (l1 - l0) / (l0 + l1 + l2) of the ball's covariance (float64 numpy, l0 <= l1 <= l2) is at
least ``GAP_MIN`` = 1e-3, with at least 3 points (Open3D returns (0, 0, 1) below 3), and no
neighbour within 1e-5 r of the sphere of radius r (clcurv's float32 distances may take such
a point in or out). The tolerance (Davis-Kahan): the float32 covariance of the kernels
carries an error of about c 2^-24 (l0 + l1 + l2) (coordinates relative to their cell, so the
sums' terms are of the ball's size), which turns the normal by at most that over l1 - l0:
sin(angle) <= ``C_NORMAL`` 2^-24 / g with C_NORMAL = 8; measured (PoCL, AMD EPYC) c <= 1.45 on
bun0 at radii 0.01 to 0.05 (1.39 at 0.02: sin(angle) <= 4.3e-7), so 8 is a margin of 5.5.
At r = 0.02 (6 to 27 neighbours, median 18) every point of bun0 is compared (the smallest
gap is 0.037: a bound of 1.3e-5).
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import clcurv

DATA = Path(__file__).resolve().parent / "data"
CGAL_POINTS = DATA / "cgal_jet_fitting_in_points_d4.txt"
BUN0 = DATA / "pcl_bun0.pcd"

# ------------------------------------------------------------------ CGAL jet fitting

#: CGAL's published (blind_1pt.cpp) principal curvatures, per orientation of the normal:
#: CGAL normal +z -> (0.4, 0.2); -z -> (-0.2, -0.4); and its tolerance
CGAL_K = {+1: (0.4, 0.2), -1: (-0.2, -0.4)}
CGAL_PRECISION = 0.01
#: the exact quadric z = 0.1 x^2 + 0.2 y^2 at the origin: k = 2 * 0.2 along y, 2 * 0.1 along x
K_MAX, K_MIN = 0.4, 0.2
K_TOL = 1e-5
DIR_TOL = 5e-5
#: larger than the farthest point from the origin (sqrt(8 + 1.44) = 3.07): the whole file
CGAL_RADIUS = 4.0

X, Y, Z = np.eye(3)


def cgal_points():
    pts = clcurv.io.read(CGAL_POINTS).points.astype(np.float64)
    assert pts.shape == (17, 3) and not pts[0].any()         # the fitting point: the origin
    assert np.allclose(pts[:, 2], 0.1 * pts[:, 0] ** 2 + 0.2 * pts[:, 1] ** 2)
    return pts


def _up_to_sign(v, axis):
    return np.abs(np.asarray(v) - np.sign(np.dot(v, axis)) * axis).max()


@pytest.mark.parametrize("side", [+1, -1], ids=["normal+z", "normal-z"])
def test_mls2_is_cgal_jet_fitting(device, side):
    """clcurv's MLS2 (float32 kernels) at the origin of CGAL's in_points_d4.txt: CGAL's
    published k1, k2 within CGAL's 0.01, and the exact quadric's curvatures, directions,
    normal and projection within the float32 tolerances of the module docstring."""
    pts = cgal_points()
    res = clcurv.curvature(pts, CGAL_RADIUS, method="mls2", viewpoint=(0.0, 0.0, 10.0 * side),
                           device=device)
    assert res.count[0] == 17 and res.status[0] == 0
    k1, k2 = res.k1[0], res.k2[0]
    # clcurv's curvatures with normal n are CGAL's with normal -n (module docstring)
    cgal_k1, cgal_k2 = CGAL_K[-side]
    print(f"\nnormal {side:+d}z: clcurv k1 {k1:.9g} k2 {k2:.9g}; CGAL (normal {-side:+d}z) "
          f"{cgal_k1} {cgal_k2}")
    assert abs(k1 - cgal_k1) <= CGAL_PRECISION and abs(k2 - cgal_k2) <= CGAL_PRECISION
    # the exact quadric: normal +z bends towards the normal, so negative (clcurv's sign)
    want_k1, want_k2 = (-K_MIN, -K_MAX) if side > 0 else (K_MAX, K_MIN)
    assert abs(k1 - want_k1) <= K_TOL, (k1, want_k1)
    assert abs(k2 - want_k2) <= K_TOL, (k2, want_k2)
    assert abs(res.mean[0] - (k1 + k2) / 2) <= K_TOL
    assert abs(res.gaussian[0] - want_k1 * want_k2) <= K_TOL
    # dir1 goes with k1: x for normal +z (k1 = -0.2), y for normal -z (k1 = 0.4: CGAL's d1)
    d1, d2 = (X, Y) if side > 0 else (Y, X)
    assert _up_to_sign(res.dir1[0], d1) <= DIR_TOL, res.dir1[0]
    assert _up_to_sign(res.dir2[0], d2) <= DIR_TOL, res.dir2[0]
    np.testing.assert_allclose(res.normals[0], side * Z, atol=DIR_TOL)
    # the MLS2 projection of a point on the quadric is the point itself (r = 4: 4 K_TOL)
    assert np.abs(res.points[0]).max() <= CGAL_RADIUS * K_TOL, res.points[0]


# ------------------------------------------------------------------ Open3D normals

O3D_RADIUS = 0.02
GAP_MIN = 1e-3
C_NORMAL = 8.0
EPS32 = 2.0 ** -24
#: distances within this fraction of r of the sphere are ambiguous in float32
SHELL = 1e-5


def open3d_or_skip():
    try:
        import open3d
    except ModuleNotFoundError:
        pytest.skip("Open3D's normals oracle: open3d is not installed (optional: pip install "
                    "open3d-cpu, or the 'bench' extra)")
    except ImportError as e:        # e.g. the wheel needs libusb-1.0.so.0
        pytest.skip(f"Open3D's normals oracle: open3d is installed but does not load ({e})")
    return open3d


def ball_spectra(pts, r):
    """Per point: the count of the open ball, its covariance eigenvalues (ascending,
    float64) and whether a neighbour lies within SHELL r of its sphere."""
    tree = cKDTree(pts)
    balls = tree.query_ball_point(pts, r * (1 - SHELL))
    outer = tree.query_ball_point(pts, r * (1 + SHELL), return_length=True)
    count = np.array([len(b) for b in balls])
    lam = np.full((len(pts), 3), np.nan)
    for i, b in enumerate(balls):
        if len(b) >= 3:
            q = pts[b] - pts[b].mean(axis=0)
            lam[i] = np.linalg.eigvalsh(q.T @ q / len(b))
    return count, lam, count == outer


def test_normals_are_open3d_normals(device):
    """clcurv.normals (float32 kernels) vs Open3D's estimate_normals with a radius search
    and a hybrid search of the same radius, up to sign, where the normal is well posed
    (relative eigen-gap >= GAP_MIN): sin(angle) <= C_NORMAL 2^-24 / gap (module docstring)."""
    o3d = open3d_or_skip()
    pts = clcurv.io.read(BUN0).points.astype(np.float64)
    assert pts.shape == (397, 3)
    theirs = {}
    for name, search in (("radius", o3d.geometry.KDTreeSearchParamRadius(O3D_RADIUS)),
                         ("hybrid", o3d.geometry.KDTreeSearchParamHybrid(O3D_RADIUS,
                                                                          len(pts)))):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        cloud.estimate_normals(search)
        theirs[name] = np.asarray(cloud.normals).copy()
    ours = clcurv.normals(pts, O3D_RADIUS, orient=None, device=device)
    count, lam, clear = ball_spectra(pts, O3D_RADIUS)
    with np.errstate(invalid="ignore", divide="ignore"):
        gap = (lam[:, 1] - lam[:, 0]) / lam.sum(axis=1)
    compared = (count >= 3) & clear & (gap >= GAP_MIN)
    # the rule leaves nothing out on this cloud at this radius: every point is checked
    assert compared.all(), int((~compared).sum())
    assert np.isfinite(ours).all()
    bound = C_NORMAL * EPS32 / gap
    for name, n in theirs.items():
        sin = np.linalg.norm(np.cross(ours, n), axis=1)
        worst = np.argmax(sin / bound)
        print(f"\nOpen3D {name}: max sin(angle) {sin[compared].max():.3g}, max ratio to the "
              f"bound {(sin / bound)[compared].max():.3g} (point {worst}, gap {gap[worst]:.3g},"
              f" {count[worst]} neighbours)")
        bad = compared & (sin > bound)
        assert not bad.any(), (name, np.flatnonzero(bad)[:5], sin[bad][:5], bound[bad][:5])
