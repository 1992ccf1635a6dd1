"""The float64 reference (clcurv.reference.operators) and host orientation (clcurv.orient.orientation).

The reference is the oracle the OpenCL kernels are checked against, so it is itself checked
here against brute force, the paper's asymptotic limits (Digne & Morel 2013, Theorem 4 and
Lemma 2, valid for dense uniform-in-area sampling) and the status rules. Fixed seeds, no
OpenCL, no timings (those are ``python -m bench.reference_speed``).
"""
import numpy as np
import pytest

from clcurv.orient import orientation as orient
from clcurv.reference import operators as reference
from clcurv import shapes

GOLDEN = (1 + 5 ** 0.5) / 2


def fibonacci_sphere(n, radius):
    """Deterministic, uniform-in-area (Fibonacci lattice) sample of a sphere and its normals."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = 2 * np.pi * i / GOLDEN
    s = np.sqrt(1 - z * z)
    u = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    return radius * u, u


def capsule(n, radius=1.0, length=2.0, seed=0):
    """Closed capsule (cylinder of ``length`` along z with hemispherical caps), uniform in
    area, with its outward normals."""
    rng = np.random.default_rng(seed)
    a_cyl, a_cap = 2 * np.pi * radius * length, 4 * np.pi * radius ** 2
    on_cyl = rng.uniform(0, a_cyl + a_cap, n) < a_cyl
    u = rng.normal(size=(n, 3))
    cap_z = np.sign(u[:, 2]) * length / 2        # cap points: centre of their hemisphere
    u[on_cyl, 2] = 0                             # side points: radial normal
    u /= np.linalg.norm(u, axis=1)[:, None]
    pts = radius * u
    pts[:, 2] += np.where(on_cyl, rng.uniform(-length / 2, length / 2, n), cap_z)
    return pts, u


def rowdot(a, b):
    return np.einsum("ij,ij->i", a, b)


def mean_curvature_mls0(m, normals_out, r):
    """H = 4 <p - o, n_out> / r^2 (PAPER.md operator 5, clcurv sign)."""
    return 4 * rowdot(-m["shift"], normals_out) / r ** 2


def brute_moments(points, r, weights):
    """Direct per-point loop: the definition, for a small cloud."""
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    nb = d < r
    count = nb.sum(1)
    out = []
    for i in range(len(points)):
        q = points[nb[i]] - points[i]
        w = np.ones(len(q)) if weights == "uniform" else 1.0 / count[nb[i]]
        o = w @ q / w.sum()
        c = (w[:, None] * (q - o)).T @ (q - o) / w.sum()
        lam, vec = np.linalg.eigh(c)
        out.append((o, lam, vec[:, 0]))
    return count, out


# ---------------------------------------------------------------------------------------
# neighbourhoods
# ---------------------------------------------------------------------------------------
def test_strict_ball_excludes_exact_distance():
    # integer grid: neighbours at distance exactly 1 (and sqrt 2) are representable
    g = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), [0.0]), -1).reshape(-1, 3)
    assert reference.neighbor_counts(g, 1.0).tolist() == [1] * 16
    inner = 1 * 4 + 1  # grid point (1, 1): 4 neighbours at distance 1, 4 at sqrt 2
    assert reference.neighbor_counts(g, np.nextafter(1.0, 2))[inner] == 5
    assert reference.neighbor_counts(g, 1.5)[inner] == 9
    assert reference.ball_neighbors(g, 1.5)[inner] == [0, 1, 2, 4, 5, 6, 8, 9, 10]
    assert reference.moments(g, 1.0)["count"].tolist() == [1] * 16
    assert reference.moments(g, 1.5)["count"][inner] == 9


def test_counts_agree_between_entry_points():
    rng = np.random.default_rng(1)
    pts = np.round(rng.uniform(0, 6, (3000, 3)))  # many exact ties at integer distances
    pts += rng.uniform(0, 1, (3000, 3)) * (rng.uniform(size=(3000, 1)) < 0.5)
    for r in (1.0, 1.5, 2.0):
        lists = reference.ball_neighbors(pts, r)
        c = np.array([len(x) for x in lists])
        assert all(i in x for i, x in enumerate(lists))
        np.testing.assert_array_equal(c, reference.neighbor_counts(pts, r))
        np.testing.assert_array_equal(c, reference.moments(pts, r)["count"])


# ---------------------------------------------------------------------------------------
# moments: against brute force
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("weights", ["uniform", "density"])
def test_moments_match_brute_force(weights):
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 1, (400, 3)) * [1, 1, 0.1]
    r = 0.2
    m = reference.moments(pts, r, weights)
    count, out = brute_moments(pts, r, weights)
    np.testing.assert_array_equal(m["count"], count)
    assert np.all(m["status"] == 0)
    for i, (o, lam, v0) in enumerate(out):
        np.testing.assert_allclose(m["shift"][i], o, rtol=0, atol=1e-15)
        np.testing.assert_allclose(m["eigenvalues"][i], lam, rtol=0, atol=1e-14 * lam[2])
        assert abs(abs(m["normals"][i] @ v0) - 1) < 1e-10
        assert m["variation"][i] == pytest.approx(lam[0] / lam.sum(), rel=1e-9)


def test_moments_translation_invariant():
    # the sums are taken relative to the query point: a 1e6 offset loses no digits
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (2000, 3)) * [1, 1, 0.05]
    a = reference.moments(pts, 0.2)
    b = reference.moments(pts + [1e6, -2e6, 3e5], 0.2)
    np.testing.assert_array_equal(a["count"], b["count"])
    np.testing.assert_allclose(b["shift"], a["shift"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b["eigenvalues"], a["eigenvalues"], rtol=1e-6, atol=1e-14)
    np.testing.assert_allclose(b["variation"], a["variation"], rtol=1e-6)
    assert np.all(np.abs(rowdot(a["normals"], b["normals"])) > 1 - 1e-9)


def test_output_types_and_units():
    pts, _ = fibonacci_sphere(2000, 2.0)
    m = reference.moments(pts, 0.4)
    assert m["count"].dtype == np.int32 and m["status"].dtype == np.uint8
    for key in ("eigenvalues", "normals", "variation", "shift"):
        assert m[key].dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(m["normals"], axis=1), 1, atol=1e-12)
    assert np.all(np.diff(m["eigenvalues"], axis=1) >= 0)
    assert np.all((m["variation"] >= 0) & (m["variation"] <= 1 / 3))
    # scaling the cloud by s scales eigenvalues by s^2, shift by s, variation unchanged
    m2 = reference.moments(3 * pts, 1.2)
    np.testing.assert_allclose(m2["eigenvalues"], 9 * m["eigenvalues"], rtol=1e-9)
    np.testing.assert_allclose(m2["shift"], 3 * m["shift"], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(m2["variation"], m["variation"], rtol=1e-8)


def test_bad_weights_and_empty_cloud():
    with pytest.raises(ValueError):
        reference.moments(np.zeros((3, 3)), 1.0, weights="inverse")
    m = reference.moments(np.empty((0, 3)), 1.0)
    assert m["count"].shape == (0,) and m["normals"].shape == (0, 3)


# ---------------------------------------------------------------------------------------
# status rules
# ---------------------------------------------------------------------------------------
def _assert_nan(m, rows):
    for key in ("eigenvalues", "normals", "variation", "shift"):
        assert np.all(np.isnan(m[key][rows])), key


def test_status_too_few_neighbours():
    rng = np.random.default_rng(4)
    patch = rng.uniform(0, 1, (200, 3)) * [1, 1, 0.01]
    pair = np.array([[10.0, 10, 10], [10.05, 10, 10]])
    pts = np.vstack([patch, [[5.0, 5, 5]], pair])  # an isolated point, an isolated pair
    m = reference.moments(pts, 0.2)
    assert m["count"][200:].tolist() == [1, 2, 2]
    assert m["status"][200:].tolist() == [1, 1, 1]
    _assert_nan(m, slice(200, None))
    assert np.all(m["status"][:200] == 0)
    assert np.all(np.isfinite(m["normals"][:200]))


def test_status_degenerate_collinear_and_coincident():
    t = np.linspace(0, 1, 30)
    line = np.stack([t, 2 * t, -t], axis=1) + [1e3, 0, 0]   # collinear
    dup = np.full((5, 3), 7.0)                            # coincident: C = 0
    m = reference.moments(np.vstack([line, dup]), 0.2)
    assert np.all(m["count"] >= 3)
    assert m["status"].tolist() == [2] * 35
    _assert_nan(m, slice(None))


# ---------------------------------------------------------------------------------------
# moments: the paper's limits (uniform area sampling)
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fib_sphere():
    R, r = 2.0, 0.2
    pts, nrm = fibonacci_sphere(20_000, R)
    return R, r, pts, nrm, reference.moments(pts, r)


def test_sphere_variation_theorem4(fib_sphere):
    R, r, _, _, m = fib_sphere
    assert np.all(m["status"] == 0)
    ratio = np.mean(m["variation"]) / (r ** 2 / 24 / R ** 2)
    assert abs(ratio - 1) <= 0.05, ratio


def test_sphere_mls0_mean_curvature(fib_sphere):
    R, r, _, nrm, m = fib_sphere
    H = mean_curvature_mls0(m, nrm, r)
    assert abs(np.mean(H) * R - 1) <= 0.03, np.mean(H) * R
    assert np.median(np.abs(H * R - 1)) <= 0.05
    # PCA normals are accurate on the noise-free sphere
    assert np.min(np.abs(rowdot(m["normals"], nrm))) > 0.999


def test_cylinder_variation_and_mls0():
    R, r = 1.0, 0.2
    s = shapes.cylinder(20_000, R, 4.0, seed=5)
    m = reference.moments(s["points"], r)
    inner = np.abs(s["points"][:, 2]) < 2.0 - r  # away from the open ends
    ratio = np.mean(m["variation"][inner]) / (r ** 2 / 32 / R ** 2)
    assert abs(ratio - 1) <= 0.05, ratio
    H = mean_curvature_mls0(m, s["normals"], r)[inner]
    assert abs(np.mean(H) / (0.5 / R) - 1) <= 0.03, np.mean(H)


def test_density_weights_neutral_on_uniform_sampling(fib_sphere):
    R, r, pts, nrm, mu = fib_sphere
    md = reference.moments(pts, r, weights="density")
    assert abs(np.mean(md["variation"]) / np.mean(mu["variation"]) - 1) <= 0.01
    assert np.median(np.abs(md["variation"] / mu["variation"] - 1)) <= 0.01
    Hu, Hd = mean_curvature_mls0(mu, nrm, r), mean_curvature_mls0(md, nrm, r)
    assert abs(np.mean(Hd) / np.mean(Hu) - 1) <= 0.01


def test_density_weights_cancel_sampling_gradient():
    # sphere R = 2 sampled with density growing linearly along x (ratio 4 across):
    # relative gradient at x = 0 is g = (3/(2R)) / 2.5 = 0.3 per unit length, so the
    # uniform-weight barycenter drifts tangentially by about g r^2 / 4 = 0.015 r;
    # density weights remove the drift.
    R, r = 2.0, 0.2
    rng = np.random.default_rng(6)
    s = shapes.sphere(80_000, R, seed=6)["points"]
    keep = rng.uniform(0, 4, len(s)) < 1 + 1.5 * (s[:, 0] / R + 1)
    pts = s[keep][:30_000]
    nrm = pts / R
    gx = np.array([1.0, 0, 0]) - nrm[:, :1] * nrm  # tangent direction of the gradient
    eq = np.abs(pts[:, 0]) < 0.5
    drift = {}
    for w in ("uniform", "density"):
        m = reference.moments(pts, r, weights=w)
        drift[w] = np.mean(rowdot(m["shift"], gx)[eq]) / r
    assert 0.012 <= drift["uniform"] <= 0.018, drift
    assert abs(drift["density"]) <= 0.002, drift


# ---------------------------------------------------------------------------------------
# orientation
# ---------------------------------------------------------------------------------------
def test_flip_to_reference_and_viewpoint_exact():
    n = np.array([[0, 0, 1.0], [0, 0, -2.0], [1, 0, 0], [np.nan] * 3, [0, 1, 0]])
    ref = np.array([[0, 0, 3.0], [0, 0, 1.0], [-1, 1, 0], [0, 0, 1], [1, 0, 0]])
    assert orient.flip_to_reference(n, ref).tolist() == [False, True, True, False, False]
    assert orient.flip_to_reference(n, [0, 0, 1]).tolist() == [False, True, False, False,
                                                               False]
    p = np.array([[0, 0, 0.0], [0, 0, 0], [2, 0, 0], [0, 0, 0], [0, 3, 0]])
    vp = np.array([1.0, 1.0, 1.0])
    assert orient.flip_to_viewpoint(p, n, vp).tolist() == [False, True, True, False, True]
    # a sphere seen from its centre: every outward normal flips
    pts, nrm = fibonacci_sphere(500, 1.0)
    assert orient.flip_to_viewpoint(pts, nrm, [0, 0, 0]).all()
    assert not orient.flip_to_viewpoint(pts, nrm, pts + nrm).any()


def test_apply_flip_returns_new_arrays():
    a = np.arange(6.0).reshape(3, 2)
    b = np.array([1.0, 2.0, 3.0])
    flip = np.array([True, False, True])
    fa, fb = orient.apply_flip(flip, a, b)
    assert fa.tolist() == [[-0.0, -1.0], [2.0, 3.0], [-4.0, -5.0]]
    assert fb.tolist() == [-1.0, 2.0, -3.0]
    assert a[0, 1] == 1.0 and b[0] == 1.0  # inputs untouched
    assert orient.apply_flip(flip, b).tolist() == [-1.0, 2.0, -3.0]


def _pca_normals_randomly_signed(points, r, seed):
    m = reference.moments(points, r)
    assert np.all(m["status"] == 0)
    sign = np.random.default_rng(seed).choice([-1.0, 1.0], size=(len(points), 1))
    return m["normals"] * sign


def _outward_fraction(points, normals, truth):
    flip = orient.flip_by_propagation(points, normals, k=10)
    oriented = orient.apply_flip(flip, normals)
    return np.mean(rowdot(oriented, truth) > 0)


ORIENT_CASES = {
    "sphere": (lambda: (lambda s: (s["points"], s["normals"]))(shapes.sphere(20_000, 2.0,
                                                                             seed=7)), 0.2),
    "capsule": (lambda: capsule(20_000, 1.0, 2.0, seed=8), 0.15),
    "torus": (lambda: (lambda s: (s["points"], s["normals"]))(shapes.torus(30_000, 2.0, 0.5,
                                                                           seed=9)), 0.12),
    "open cylinder": (lambda: (lambda s: (s["points"], s["normals"]))(
        shapes.cylinder(20_000, 1.0, 4.0, seed=10)), 0.15),
}


@pytest.mark.parametrize("name", list(ORIENT_CASES))
def test_flip_by_propagation_outward(name):
    make, r = ORIENT_CASES[name]
    pts, truth = make()
    n = _pca_normals_randomly_signed(pts, r, seed=len(name))
    assert 0.4 < np.mean(rowdot(n, truth) > 0) < 0.6
    frac = _outward_fraction(pts, n, truth)
    assert frac >= 0.999, f"{name}: {frac:.4%} outward"


def test_flip_by_propagation_components_and_invalid_rows():
    # two separate spheres: each component gets its own outward choice
    a, na = fibonacci_sphere(3000, 1.0)
    b, nb = fibonacci_sphere(2000, 0.5)
    pts = np.vstack([a, b + [5.0, 0, 0]])
    truth = np.vstack([na, nb])
    rng = np.random.default_rng(11)
    n = truth * rng.choice([-1.0, 1.0], size=(len(pts), 1)) * rng.uniform(0.5, 2, (len(pts), 1))
    n[::97] = np.nan
    invalid = np.isnan(n[:, 0])
    flip = orient.flip_by_propagation(pts, n)
    assert not flip[invalid].any()
    out = orient.apply_flip(flip, n)
    assert np.all(rowdot(out[~invalid], truth[~invalid]) > 0)
    # the unflipped-NaN rows stay NaN, inputs are untouched
    assert np.isnan(out[invalid]).all() and np.isnan(n[invalid]).all()


def test_flip_by_propagation_duplicate_points():
    # every point three times: the kNN self match is not always first
    s = shapes.sphere(5000, 2.0, seed=13)
    pts, truth = np.vstack([s["points"]] * 3), np.vstack([s["normals"]] * 3)
    n = truth * np.random.default_rng(13).choice([-1.0, 1.0], size=(len(pts), 1))
    out = orient.apply_flip(orient.flip_by_propagation(pts, n), n)
    assert np.all(rowdot(out, truth) > 0)


def test_flip_by_propagation_tiny_inputs():
    assert orient.flip_by_propagation(np.empty((0, 3)), np.empty((0, 3))).shape == (0,)
    p = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    n = np.array([[-1.0, 0, 0], [-1.0, 0, 0]])
    # fewer than 3 points: each away from the centroid of the valid points
    assert orient.flip_by_propagation(p, n).tolist() == [True, False]
    n_nan = np.array([[np.nan] * 3, [-1.0, 0, 0]])
    assert orient.flip_by_propagation(p, n_nan).tolist() == [False, False]
