"""The host steps that decide a result's sign and values after the operator: finishing
(MLS0/MLS1 H and points, MLS2 H and K), MLS2's flip of its own normals, and orientation.

``backend="numpy"`` runs the reference's own versions (clcurv.reference.operators: ``finish``,
``orientation_flips``, ``mst_flips``), the OpenCL backend the kernel path's
(clcurv.ops.registry ``_finish_*`` and ``_flip_mls2``, clcurv.orient.orientation). A test comparing the
two backends therefore sees a fault of either. Both are also checked here against exact
values, so that a fault shared by the definitions would show too:

* shapes with known signed curvatures and outward normals: a sphere (R = 2), an open
  cylinder (R = 1: k1 = 1, k2 = 0), an elliptic paraboloid z = (x^2 + 0.4 y^2) / 2 (open:
  outward is away from its centroid, so towards -z, k1 > k2 > 0; with orient='up' the
  opposite), a hollow shell (the inner wall faces its cavity: H = -1/1.5), a sphere seen
  from its centre (viewpoint: H = -1/R), a sphere with the user's normals reversed, and
  for MLS2 a saddle (oriented by a direction); each through both backends. Tolerances (measured, both backends the same to 1e-3):
  outward normals and the sign of H (and of K) at every interior point; the median error
  of MLS0/MLS1 H <= 0.1 |H|max (the barycenter's sampling noise and O(r^2) bias); MLS2
  k1, k2 and H within 0.03 |k|max at p99 (the shell's inner wall at r = 0.3 R: 0.024)
  and k1 >= k2 everywhere; K = k1 k2 within 0.06 |K|max (the shell: 0.049), or
  0.01 |k|max^2 where K = 0.
  The sign of H is checked where |H| > 0.3 |H|max (the saddle's H crosses 0);
* the finishing formulas on hand-made fields (exact numbers);
* ``_flip_mls2`` against the reference fit with the opposite normals (round-off), and
  the device's own-normals MLS2 path (fit, then flip) against the numpy backend.
"""
import numpy as np
import pytest

import clcurv
from clcurv.orient import orientation as orient
from clcurv.reference import operators as reference
from clcurv import shapes
from clcurv.ops.registry import OPERATORS, _flip_mls2

SIGNED = ("mls0", "mls1", "mls2")


def rowdot(a, b):
    return np.einsum("ij,ij->i", a, b)


def paraboloid(n, a=1.0, b=0.4, extent=1.0, seed=0):
    """z = (a x^2 + b y^2) / 2 over the disc of ``extent``; outward (away from the
    centroid) is towards -z, where the surface bends away from its normal: k > 0."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-extent, extent, (3 * n, 2))
    x, y = xy[(xy ** 2).sum(axis=1) <= extent ** 2][:n].T
    fx, fy = a * x, b * y
    w = np.sqrt(1 + fx ** 2 + fy ** 2)
    nrm = np.stack([fx, fy, -np.ones(len(x))], axis=1) / w[:, None]
    e, f, g = 1 + fx ** 2, fx * fy, 1 + fy ** 2          # first fundamental form
    ll, nn = a / w, b / w                                 # second (fxy = 0)
    det = e * g - f * f
    h = (e * nn + g * ll) / (2 * det)
    k = ll * nn / det
    d = np.sqrt(np.maximum(h * h - k, 0.0))
    return {"points": np.stack([x, y, (a * x * x + b * y * y) / 2], axis=1), "normals": nrm,
            "k1": h + d, "k2": h - d, "H": h, "K": k,
            "inner": np.hypot(x, y) < extent - 0.3}


def _case(name):
    """(shape dict with an ``inner`` mask, radius, curvature keywords); the shape's
    ``normals``, ``k1``, ``k2``, ``H``, ``K`` are those the call must give."""
    if name == "sphere":
        s, r, kw = shapes.sphere(8000, 2.0, seed=7), 0.45, {}
    elif name == "cylinder":
        s, r, kw = shapes.cylinder(8000, 1.0, 4.0, seed=10), 0.3, {}
        s["inner"] = np.abs(s["points"][:, 2]) < 2.0 - 1.5 * r
    elif name == "paraboloid":
        s, r, kw = paraboloid(8000), 0.2, {}
    elif name == "paraboloid, up":
        s, r, kw = _reversed(paraboloid(8000, seed=1)), 0.2, {"orient": "up"}
    elif name == "hollow shell":
        s, r, kw = shapes.hollow_shell(12000, 2.0, 1.5, seed=4), 0.45, {}
    elif name == "saddle":
        s, r, kw = shapes.saddle(8000, 1.0, 1.0, seed=5), 0.2, {"orient": (0, 0, -1)}
        s["inner"] = np.hypot(*s["points"][:, :2].T) < 0.7
    elif name == "sphere from its centre":
        s, r = shapes.sphere(8000, 2.0, seed=8), 0.45
        kw = {"orient": "viewpoint", "viewpoint": (0.0, 0.0, 0.0)}
        s = _reversed(s)
    elif name == "reversed user normals":
        s, r = shapes.sphere(8000, 2.0, seed=9), 0.45
        s = _reversed(s)
        kw = {"normals": s["normals"] * 3.0}              # any length: normalised
    else:
        raise KeyError(name)
    s.setdefault("inner", np.ones(len(s["points"]), dtype=bool))
    return s, r, kw


def _reversed(s):
    """The shape with its normals reversed: k -> -k, the order of k1 and k2 swapped."""
    return dict(s, normals=-s["normals"], k1=-s["k2"], k2=-s["k1"], H=-s["H"])


CASES = ["sphere", "cylinder", "paraboloid", "paraboloid, up", "hollow shell",
         "sphere from its centre", "reversed user normals"]
#: (shape, method) pairs: the saddle's H is small beside MLS0's and MLS1's noise
PAIRS = [(c, m) for c in CASES for m in SIGNED] + [("saddle", "mls2")]


def check_against_exact(res, s, method):
    ok = s["inner"] & res.valid
    assert ok.mean() > 0.99 * s["inner"].mean(), f"{ok.mean():.3f} valid"
    # outward normals (clcurv's convention), whichever way the call oriented them
    assert np.all(rowdot(res.normals[ok], s["normals"][ok]) > 0.5)
    h = s["H"][ok]
    scale = np.abs(h).max()
    clear = np.abs(h) > 0.3 * scale                # (the saddle's H crosses 0)
    assert np.all(np.sign(res.mean[ok][clear]) == np.sign(h[clear])), "sign of H"
    if method in ("mls0", "mls1"):
        assert np.median(np.abs(res.mean[ok] - h)) <= 0.1 * scale
        # the points: MLS0 the barycenter, MLS1 p projected on the PCA plane, both inside
        # the surface's side of p, a distance ~ |H| r^2 / 4 away
        move = rowdot(res.points[ok] - res.points_input[ok], s["normals"][ok])
        assert np.all(np.sign(move) == -np.sign(h))
        return
    k1, k2 = s["k1"][ok], s["k2"][ok]
    kmax = np.maximum(np.abs(k1), np.abs(k2)).max()
    assert np.all(res.k1[ok] >= res.k2[ok])
    for got, want in ((res.k1, k1), (res.k2, k2), (res.mean, h)):
        assert np.quantile(np.abs(got[ok] - want), 0.99) <= 0.03 * kmax
    kk = s["K"][ok]
    if np.abs(kk).max() > 0:
        assert np.all(np.sign(res.gaussian[ok]) == np.sign(kk)), "sign of K"
        assert np.quantile(np.abs(res.gaussian[ok] - kk), 0.99) <= 0.06 * np.abs(kk).max()
    else:
        assert np.abs(res.gaussian[ok]).max() <= 0.01 * kmax ** 2
    # (dir1, dir2, normal) right-handed: dir2 = normal x dir1
    np.testing.assert_allclose(np.cross(res.normals[ok], res.dir1[ok]), res.dir2[ok],
                               atol=1e-5)


def _run(name, method, **backend):
    s, r, kw = _case(name)
    res = clcurv.curvature(s["points"], r, method=method, **kw, **backend)
    res.points_input = s["points"]
    return res, s


@pytest.mark.parametrize("name, method", PAIRS)
def test_numpy_backend_against_exact_values(name, method):
    """The reference's finishing and orientation (no kernel, no clcurv.ops.registry
    finishing step, no clcurv.orient.orientation)."""
    res, s = _run(name, method, backend="numpy")
    check_against_exact(res, s, method)


@pytest.mark.parametrize("name, method", PAIRS)
def test_kernel_path_against_exact_values(name, method, device):
    """The kernel path's host steps: the operators' finishing, MLS2's own normals flipped
    afterwards (_flip_mls2), the device orientation and its signs (clcurv.orient.orientation)."""
    res, s = _run(name, method, device=device)
    check_against_exact(res, s, method)


# --------------------------------------------------------------------------- finishing

def _fields(status, **kw):
    return {"status": np.asarray(status, dtype=np.uint8),
            **{k: np.asarray(v, dtype=np.float64) for k, v in kw.items()}}


@pytest.mark.parametrize("side", ["reference", "kernel path"])
def test_finishing_formulas_by_hand(side):
    """r = 0.2, p = 0, normal +z. MLS0: barycenter o = (0.03, 0, -0.01), H = 4 <p - o, n> /
    r^2 = 1, points = o; with the user's normal -z, H = -1. MLS1: p' = (0, 0, -0.01) (p
    projected on the plane through o), H = 4 <p - p', n> / r^2 = 1. MLS2: the fit's k1 = 3,
    k2 = -1 give H = 1, K = -3. A status != 0 row is NaN."""
    pts = np.zeros((2, 3))
    n = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    pca = dict(eigenvalues=[[1e-4, 1e-2, 1e-2]] * 2, variation=[1e-4 / 0.0201] * 2,
               shift=[[0.03, 0, -0.01]] * 2)

    def fin(method, raw, user=None):
        if side == "reference":
            return reference.finish(method, raw, pts, 0.2, n, user)
        return OPERATORS[method].finish(raw, pts, 0.2, n, user)

    out = fin("mls0", _fields([0, 1], **pca))
    np.testing.assert_allclose(out["mean"][0], 1.0, rtol=1e-12)
    np.testing.assert_allclose(out["points"][0], [0.03, 0, -0.01], rtol=1e-12)
    assert np.isnan(out["mean"][1])
    out = fin("mls0", _fields([0, 0], **pca), user=-n)
    np.testing.assert_allclose(out["mean"], -1.0, rtol=1e-12)
    out = fin("mls1", _fields([0, 0], **pca))
    np.testing.assert_allclose(out["mean"], 1.0, rtol=1e-12)
    np.testing.assert_allclose(out["points"], [[0, 0, -0.01]] * 2, atol=1e-15)
    np.testing.assert_array_equal(out["normals"], n)
    mls2 = _fields([0, 3], k1=[3.0, np.nan], k2=[-1.0, np.nan], dir1=[[1, 0, 0.0]] * 2,
                   dir2=[[0, 1, 0.0]] * 2, normals=n, shift=[[0, 0, 0.002]] * 2,
                   mean=[1.0, np.nan], gaussian=[-3.0, np.nan])
    out = fin("mls2", mls2)
    np.testing.assert_allclose(out["mean"][0], 1.0, rtol=1e-12)
    np.testing.assert_allclose(out["gaussian"][0], -3.0, rtol=1e-12)
    np.testing.assert_allclose(out["points"][0], [0, 0, 0.002], rtol=1e-12)
    assert np.isnan(out["mean"][1]) and np.isnan(out["gaussian"][1])


@pytest.mark.parametrize("method", list(OPERATORS))
def test_both_finishing_steps_agree_on_reference_fields(method):
    """The reference's finish and the kernel path's on the same fields (a torus, oriented
    normals): equal to round-off. MLS2's H and K come from the shape operator's trace and
    determinant on one side, (k1 + k2) / 2 and k1 k2 on the other."""
    s = shapes.torus(6000, 2.0, 0.5, seed=2)
    pts, r, n = s["points"], 0.25, s["normals"]
    op = OPERATORS[method]
    raw = op.reference(pts, r, n if op.kernel.reads_normals else None, "uniform")
    use = n if op.normals == "values" or op.kernel.reads_normals else \
        np.where(rowdot(raw["normals"], n)[:, None] < 0, -raw["normals"], raw["normals"])
    a = reference.finish(method, {k: v.copy() for k, v in raw.items()}, pts, r, use,
                         n if op.normals == "values" else None)
    b = op.finish({k: v.copy() for k, v in raw.items()}, pts, r, use,
                  n if op.normals == "values" else None)
    assert sorted(a) == sorted(b)
    ok = raw["status"] == 0
    assert ok.mean() > 0.99
    for k in a:
        scale = np.nanmax(np.abs(b[k]))
        np.testing.assert_allclose(a[k][ok], b[k][ok], rtol=0, atol=1e-9 * scale, err_msg=k)
        assert np.isnan(a[k][~ok]).all() == np.isnan(b[k][~ok]).all(), k


# --------------------------------------------------------------------------- MLS2's flip

def test_mls2_flip_is_the_fit_with_the_opposite_normals():
    """_flip_mls2 (the kernel path's: its fit's own normals, flipped afterwards) against
    the reference fit with the opposite normals: n -> -n, (k1, k2) -> (-k2, -k1), dir1 and
    dir2 swapped (up to sign) with (dir1, dir2, n) right-handed, the projection kept."""
    s = paraboloid(6000, seed=3)
    pts, r = s["points"], 0.2
    plus = reference.mls2(pts, r, s["normals"])
    minus = reference.mls2(pts, r, -s["normals"])
    raw = {k: v.copy() for k, v in plus.items()}
    raw["shift"] = raw.pop("points") - pts
    mask = np.zeros(len(pts), dtype=bool)
    mask[::2] = True                                   # half flipped, half kept
    got = _flip_mls2(raw, mask)
    ok = (plus["status"] == 0) & s["inner"]
    assert ok.mean() > 0.4
    want = {k: np.where(mask[:, None] if v.ndim == 2 else mask, minus[k], plus[k])
            for k, v in plus.items() if k in ("k1", "k2", "normals")}
    for k in ("k1", "k2", "normals"):
        np.testing.assert_allclose(got[k][ok], want[k][ok], atol=1e-9, err_msg=k)
    np.testing.assert_allclose((pts + got["shift"])[ok], minus["points"][ok], atol=1e-12)
    sep = ok & (np.abs(plus["k1"] - plus["k2"]) > 0.05)
    for k in ("dir1", "dir2"):
        ref = np.where(mask[:, None], minus[k], plus[k])
        assert np.all(np.abs(rowdot(got[k][sep], ref[sep])) > 1 - 1e-9), k
    hand = rowdot(np.cross(got["dir1"][ok], got["dir2"][ok]), got["normals"][ok])
    np.testing.assert_allclose(hand, 1.0, atol=1e-9)


@pytest.mark.parametrize("how", ["mst", "viewpoint", "direction"])
def test_mls2_own_normals_path_equals_the_numpy_backend(device, how):
    """Without normals, the OpenCL backend fits MLS2 first and flips its fit's normals
    (_flip_mls2); the numpy backend orients the PCA normals first and fits with them. On a
    torus (k1 != k2 almost everywhere), they agree in every sign and value."""
    s = shapes.torus(20000, 2.0, 0.5, seed=6)
    pts, r = s["points"], 0.15
    kw = {"mst": {}, "viewpoint": {"orient": "viewpoint", "viewpoint": (0.0, 0.0, 5.0)},
          "direction": {"orient": (1.0, 2.0, 3.0)}}[how]
    got = clcurv.curvature(pts, r, method="mls2", device=device, **kw)
    ref = clcurv.curvature(pts, r, method="mls2", backend="numpy", **kw)
    ok = got.valid & ref.valid & (got.count == ref.count)
    assert ok.mean() > 0.99
    # where the reference direction is nearly tangent (within ~6 degrees), the fit's normal
    # and the PCA normal may fall on either side of it: a coin toss orients those points
    to = {"mst": s["normals"], "viewpoint": np.array([0.0, 0.0, 5.0]) - pts,
          "direction": np.array([1.0, 2.0, 3.0])}[how]
    to = np.broadcast_to(to, pts.shape)
    ok &= np.abs(rowdot(s["normals"], to)) > 0.1 * np.linalg.norm(to, axis=1)
    assert np.all(rowdot(got.normals[ok], ref.normals[ok]) > 1 - 1e-4)
    for k in ("k1", "k2", "mean", "gaussian"):
        a, b = getattr(got, k)[ok], getattr(ref, k)[ok]
        assert np.abs(a - b).max() <= 2e-3 * np.abs(b).max(), k
    sep = ok & (np.abs(ref.k1 - ref.k2) > 0.1 * np.abs(ref.k1))
    for k in ("dir1", "dir2"):
        assert np.all(np.abs(rowdot(getattr(got, k)[sep], getattr(ref, k)[sep])) > 1 - 1e-4)


# --------------------------------------------------------------------------- orientation

def test_orientation_flips_by_hand_and_as_the_orient_helpers():
    n = np.array([[0, 0, 1.0], [0, 0, -2.0], [1, 0, 0], [np.nan] * 3, [0, 1, 0]])
    ref = np.array([[0, 0, 3.0], [0, 0, 1.0], [-1, 1, 0], [0, 0, 1], [1, 0, 0]])
    p = np.array([[0, 0, 0.0], [0, 0, 0], [2, 0, 0], [0, 0, 0], [0, 3, 0]])
    of = reference.orientation_flips
    assert of(p, n, "normals", reference=ref).tolist() == [False, True, True, False, False]
    assert of(p, n, np.array([0, 0, 1.0])).tolist() == [False, True, False, False, False]
    assert of(p, n, "viewpoint", viewpoint=np.array([1.0, 1, 1])).tolist() == \
        [False, True, True, False, True]
    assert not of(p, n, None).any()
    # as clcurv.orient.orientation's (the kernel path's) on random input, zero products included
    rng = np.random.default_rng(0)
    pts, nrm, rr = rng.normal(size=(3, 500, 3))
    nrm[::50] = np.nan
    rr[1::50] = np.cross(nrm[1::50], [1.0, 0, 0])        # perpendicular: not flipped
    vp = rng.normal(size=3)
    np.testing.assert_array_equal(of(pts, nrm, "normals", reference=rr),
                                  orient.flip_to_reference(nrm, rr))
    np.testing.assert_array_equal(of(pts, nrm, "viewpoint", viewpoint=vp),
                                  orient.flip_to_viewpoint(pts, nrm, vp))


def _signed(s, seed):
    """Unit normals of the shape with random signs and lengths."""
    rng = np.random.default_rng(seed)
    return s["normals"] * rng.choice([-1.0, 1.0], (len(s["normals"]), 1)) \
        * rng.uniform(0.5, 2.0, (len(s["normals"]), 1))


def _shell_and_ball():
    """A hollow shell (outer R = 2, inner 1.5) and a ball (R = 1) in its cavity: the inner
    wall faces the cavity, the ball outward."""
    shell = shapes.hollow_shell(16000, 2.0, 1.5, seed=1)
    ball = shapes.sphere(3000, 1.0, seed=2)
    return {k: np.concatenate([shell[k], ball[k]]) for k in ("points", "normals")}


MST = {
    "sphere": (lambda: shapes.sphere(10000, 2.0, seed=3), 0.25),
    "torus": (lambda: shapes.torus(15000, 2.0, 0.5, seed=4), 0.15),
    "open cylinder": (lambda: shapes.cylinder(10000, 1.0, 4.0, seed=5), 0.2),
    "paraboloid": (lambda: paraboloid(8000, seed=6), 0.1),
    "two spheres": (lambda: shapes.two_spheres(10000, seed=7), 0.2),
    "hollow shell": (lambda: shapes.hollow_shell(16000, 2.0, 1.5, seed=8), 0.25),
    "shell and ball": (_shell_and_ball, 0.2),
}


@pytest.mark.parametrize("name", list(MST))
def test_mst_flips_face_outward(name):
    """The reference's Hoppe propagation on exact normals of random signs and lengths:
    every normal outward (a cavity's wall towards the cavity, a ball inside it outward),
    as clcurv.orient.orientation's host propagation (the device's twin) decides too."""
    make, r = MST[name]
    s = make()
    n = _signed(s, seed=len(name))
    flip = reference.mst_flips(s["points"], n, k=10, radius=r)
    out = np.where(flip[:, None], -n, n)
    assert np.all(rowdot(out, s["normals"]) > 0)
    np.testing.assert_array_equal(flip, orient.flip_by_propagation(s["points"], n, 10, r))


def test_mst_flips_invalid_rows_duplicates_and_tiny_inputs():
    s = shapes.sphere(3000, 1.0, seed=13)
    pts = np.vstack([s["points"]] * 3)                   # every point three times
    truth = np.vstack([s["normals"]] * 3)
    n = truth * np.random.default_rng(13).choice([-1.0, 1.0], (len(pts), 1))
    n[::97] = np.nan
    n[5] = 0.0
    flip = reference.mst_flips(pts, n, k=10)
    bad = ~np.isfinite(n).all(axis=1) | (np.abs(np.nan_to_num(n)).sum(axis=1) == 0)
    assert not flip[bad].any()
    assert np.all(rowdot(np.where(flip[:, None], -n, n)[~bad], truth[~bad]) > 0)
    assert reference.mst_flips(np.empty((0, 3)), np.empty((0, 3))).shape == (0,)
    p = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    # fewer than 3 points: each away from the centroid of the valid points
    assert reference.mst_flips(p, [[-1.0, 0, 0], [-1.0, 0, 0]]).tolist() == [True, False]
    assert reference.mst_flips(p, [[np.nan] * 3, [-1.0, 0, 0]]).tolist() == [False, False]


@pytest.mark.parametrize("name", ["hollow shell", "shell and ball"])
def test_normals_of_both_backends_face_outward(name, device):
    """clcurv.normals: the device orientation (clcurv.orient.orientation.flip_on_device) and the
    numpy backend's own (reference.mst_flips), against the exact outward normals."""
    make, r = MST[name]
    s = make()
    for kw in ({"device": device}, {"backend": "numpy"}):
        n = clcurv.normals(s["points"], r, **kw)
        ok = np.isfinite(n).all(axis=1)
        assert ok.mean() > 0.999
        assert np.all(rowdot(n[ok], s["normals"][ok]) > 0.9), kw


@pytest.mark.parametrize("how", ["radius", "three radii", "k", "optimal"])
def test_features_up_is_turned_by_the_reference_itself(device, how):
    """features(orient="up"): the float64 reference turns its normals towards +z with its
    own code (clcurv.reference.features, up=), the kernel path with the API's step; both
    give n_z >= 0 and the same normals (|1 - n_ref . n_cl| < 1e-4 where both are valid, the
    normal well-posed, l2 > 1.5 l3, and its sign too: |n_z| > 1e-3, walls left out)."""
    pts = shapes.aerial_scene(6000, extent=(30.0, 20.0), seed=4)["points"]
    kw = {"radius": dict(radius=1.5), "three radii": dict(radius=[1.0, 1.5, 2.0]),
          "k": dict(k=30), "optimal": dict(radius=[1.0, 1.5, 2.0], optimal=True)}[how]
    names = ["normals", "eigenvalue2", "eigenvalue3"]
    ref = clcurv.features(pts, features=names, orient="up", backend="numpy", **kw)
    got = clcurv.features(pts, features=names, orient="up", device=device,
                          precision="double", **kw)
    for r, g in zip(ref if isinstance(ref, list) else [ref], got if isinstance(got, list)
                    else [got]):
        nr, ng = r.values["normals"], g.values["normals"]
        ok = ((r.status == 0) & (g.status == 0)
              & (r.values["eigenvalue2"] > 1.5 * r.values["eigenvalue3"])
              & (np.abs(nr[:, 2]) > 1e-3))
        assert ok.mean() > 0.5
        assert np.all(nr[r.status == 0, 2] >= 0) and np.all(ng[g.status == 0, 2] >= 0)
        dots = np.einsum("ij,ij->i", nr[ok], ng[ok])
        assert np.all(np.abs(1 - dots) < 1e-4), np.sort(dots)[:5]
