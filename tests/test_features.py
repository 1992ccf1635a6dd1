"""clcurv.features: the covariance feature set against jakteristics' compute_features and
against the float64 reference (clcurv.reference.features), names, status policy."""
from pathlib import Path

import numpy as np
import pytest

import clcurv
from importlib import import_module
F = import_module("clcurv.api.features")   # the module; clcurv.features is the function
from clcurv._shared.constants import DEGENERATE, OK, TOO_FEW
from clcurv.ops.features import layouts
from conftest import data_path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
AUTZEN = data_path("laspy_autzen_trim.laz")      # shipped in tests/data too
BUNNY = DATA / "stanford_bun_zipper.ply"

#: jakteristics 0.6 names, eigenvectors aside (clcurv returns e3 only, as normals)
JAK_NAMES = ["eigenvalue_sum", "omnivariance", "eigenentropy", "anisotropy", "planarity",
             "linearity", "PCA1", "PCA2", "surface_variation", "sphericity", "verticality",
             "nx", "ny", "nz", "number_of_neighbors", "eigenvalue1", "eigenvalue2",
             "eigenvalue3"]
#: features whose value goes through l3 (compared only where l3 is above round-off)
L3_FEATURES = {"omnivariance", "eigenentropy", "surface_variation", "sphericity",
               "eigenvalue3", "anisotropy", "planarity"}
RTOL = 1e-5
#: jakteristics evaluates its formulas in float32 (`cdef float l1, l2, l3`, float32
#: output): a difference of two eigenvalues rounded to float32 (linearity with l1 ~ l2)
#: carries up to a few float32 ulps of the eigenvalues, i.e. an absolute error of about
#: 2^-22 on the [0, 1] ratios: the only absolute floor of the comparison.
ATOL_RATIO = 2.0 ** -22
#: jakteristics matches its eigenvectors to its sorted eigenvalues by |l_i - l_j| < 1e-5,
#: an absolute threshold in the data's units squared (utils.pyx, c_sort_eigenvalues)
JAK_MATCH = 1e-5
#: the most points (fraction of the cloud) that the normals' rules may leave out while
#: jakteristics returns a finite normal there (synthetic scene: 4 of 23000)
MAX_LEFT_OUT = 1e-3


def synthetic_scene(seed=0):
    """A stand-in for the real data: a noisy plane, a cylinder, a sphere and a scatter."""
    rng = np.random.default_rng(seed)
    plane = np.c_[rng.uniform(-2, 2, (8000, 2)), rng.normal(0, 0.003, 8000)]
    cyl = clcurv.shapes.cylinder(6000, 0.5, 2.0, noise=0.002, seed=seed)["points"] + (3, 0, 0)
    sph = clcurv.shapes.sphere(6000, 0.8, noise=0.002, seed=seed)["points"] + (0, 3, 1)
    blob = rng.normal(0, 0.3, (3000, 3)) + (-3, -3, 1)
    return np.vstack([plane, cyl, sph, blob])


def _clouds():
    out = []
    if AUTZEN.exists():      # feet; r = 6 ft (~30 neighbours), float32-exact
        out.append(pytest.param(AUTZEN, 6.0, id="autzen"))
    if BUNNY.exists():       # metres; r = 2^-8 m (~30 neighbours), float32-exact
        out.append(pytest.param(BUNNY, 2.0 ** -8, id="bunny"))
    if not out:
        out.append(pytest.param(None, 0.125, id="synthetic"))
    return out


def _points(path):
    return synthetic_scene() if path is None else clcurv.io.read(path).points


def normals_compared(J, f):
    """The rules of test_against_jakteristics's note 5 for its normals, as two masks: (a)
    jakteristics' normal is its eigenvector of l3, (b) that normal is well posed."""
    l1, l2, l3 = (J[f"eigenvalue{i}"] for i in (1, 2, 3))
    # (a) its matching is unambiguous; widened by 2^-22 l1, the rounding of its float32
    #     outputs
    slack = JAK_MATCH + 2.0 ** -22 * l1
    matched = (l1 - l2 >= slack) & (l2 - l3 >= slack)
    # (b) Davis-Kahan: the angle between the computed and the exact normal is at most
    #     |dC| / (l2 - l3), with |dC| <= n_p 2^-53 l1 for a float64 covariance of n_p points
    #     (both sides compute in float64): compared where that bound is below ATOL_RATIO / 10
    e1, e2, e3 = (f[f"eigenvalue{i}"] for i in (1, 2, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        posed = f.count * 2.0 ** -53 * e1 < 0.1 * ATOL_RATIO * (e2 - e3)
    return matched, posed


@pytest.mark.parametrize("path, radius", _clouds())
def test_against_jakteristics(path, radius, device):
    """Every feature of jakteristics 0.6 at RTOL (+ ATOL_RATIO for the ratios), where both
    are defined (notes 1-6 below). The normals are compared only where (a) jakteristics'
    eigenvector matching is unambiguous, l1 - l2 >= 1e-5 and l2 - l3 >= 1e-5 (its absolute
    threshold; elsewhere its normal is NaN or its middle eigenvector, on any CPU), and (b)
    the normal is well posed, n_p 2^-53 l1 / (l2 - l3) < ATOL_RATIO / 10 (Davis-Kahan for a
    float64 PCA). The test fails if the points so left out, where jakteristics' normal is
    finite, exceed MAX_LEFT_OUT = 0.1% of the cloud, or if one left out by (a) alone is not
    orthogonal to clcurv's normal (|cos| >= 1e-6). Measured (PoCL, AMD EPYC Zen 4): the
    synthetic scene 4 of 23000 left out, all by (a), |cos| <= 9e-9; Autzen and the bunny
    none."""
    jak = pytest.importorskip("jakteristics", reason="jakteristics is not installed: "
                              "pip install jakteristics (the 'test' extra) to run this check")
    if not device.info.fp64:
        pytest.skip("the 1e-5 comparison runs the kernels in float64; no cl_khr_fp64 here")
    pts = _points(path)
    J = jak.compute_features(pts, radius, feature_names=JAK_NAMES, num_threads=2)
    J = {n: J[:, i].astype(np.float64) for i, n in enumerate(JAK_NAMES)}
    # Definitional differences, each handled here:
    # 1. jakteristics divides the covariance by n - 1 (sample covariance): ddof=1.
    # 2. Its ball is closed (scipy's <= r, r cast to float32), clcurv's open (< r): with a
    #    float32-exact radius they differ only by points at exactly r, and the float64
    #    kernels may round a distance within 1 ulp of r the other way: only points whose
    #    neighbour counts agree are compared (> 99.99 % of them).
    # 3. clcurv gives NaN (status 2) for a covariance of rank < 2 (collinear or coincident
    #    points) where jakteristics returns numbers, and jakteristics gives NaN for
    #    eigenentropy when l3 = 0 (0 log 0) where clcurv takes 0 ln 0 = 0: "where both
    #    are defined" = both finite.
    # 4. For an exactly coplanar ball (LAS coordinates quantised to 0.01 ft make flat
    #    ground so) l3 is round-off in both (~1e-16 l1): the features through l3 are
    #    compared only where jakteristics' l3 > 1e-9 l1.
    # 5. jakteristics' normals are cross(e1, e2) of its rows e1, e2, the eigenvectors
    #    matched to its sorted eigenvalues l1 >= l2 >= l3 (LAPACK dsyev, float64): the
    #    sorted l_i takes the vector of the first of dsyev's ascending eigenvalues within
    #    JAK_MATCH = 1e-5 of it, an absolute threshold in the data's units squared. The
    #    normal is compared, up to its sign (arbitrary in both: PCA sign), only where
    #    (a) the matching is unambiguous: l1 - l2 >= 1e-5 and l2 - l3 >= 1e-5 (its
    #        eigenvalues). Elsewhere its normal is not the eigenvector of l3, whatever the
    #        CPU: NaN when e1 = e2 (l1 - l2 < 1e-5; the bunny in metres, l ~ 1e-6 m^2), or
    #        the middle eigenvector when l2 - l3 < 1e-5 <= l1 - l2 (e2 := v3, so e1 x e2 =
    #        +-v2). The synthetic scene has 4 such points (balls of 3 points of the
    #        scatter, l2 ~ 4e-6 to 8e-6, l3 = 0, relative gaps (l2 - l3) / l1 of 1.2e-3 to
    #        2.7e-3: well posed), where jakteristics' normal is orthogonal to clcurv's and
    #        to the float64 reference's; checked below: at every point left out by (a)
    #        where jakteristics' normal is finite and (b) holds, the two are orthogonal;
    #    (b) the normal is well posed: the Davis-Kahan bound n_p 2^-53 l1 / (l2 - l3) on
    #        the angle error of a float64 PCA is below ATOL_RATIO / 10 (normals_compared).
    #    The points left out with a finite normal of jakteristics' are at most
    #    MAX_LEFT_OUT of the cloud.
    # 6. Its formulas run in float32 (see ATOL_RATIO).
    f = clcurv.features(pts, radius, "all", ddof=1, device=device, precision="double")
    same = J["number_of_neighbors"] == f.count
    assert same.mean() > 0.9999
    resolved = J["eigenvalue3"] > 1e-9 * J["eigenvalue1"]
    jn = np.c_[J["nx"], J["ny"], J["nz"]]
    cos = np.einsum("ij,ij->i", f["normals"], jn)
    sign = np.sign(cos)
    matched, posed = normals_compared(J, f)
    normal_ok = matched & posed
    both = same & np.isfinite(cos)
    left_out = both & ~normal_ok
    print(f"\nnormals: {int(left_out.sum())} of {len(pts)} points left out where both are "
          f"finite ({int((both & ~matched).sum())} by (a), "
          f"{int((both & matched & ~posed).sum())} by (b only))")
    assert left_out.sum() <= MAX_LEFT_OUT * len(pts), int(left_out.sum())
    # (a) leaves out only jakteristics' other eigenvectors: orthogonal to ours
    other = both & ~matched & posed
    assert np.all(np.abs(cos[other]) < 1e-6), np.abs(cos[other]).max()
    compared = {}
    for name in JAK_NAMES:
        if name == "number_of_neighbors":
            continue
        ours = f[name] * (sign if name in ("nx", "ny", "nz") else 1.0)
        theirs = J[name]
        m = same & np.isfinite(ours) & np.isfinite(theirs)
        if name in L3_FEATURES:
            m &= resolved
        if name in ("nx", "ny", "nz"):
            m &= normal_ok
        compared[name] = int(m.sum())
        atol = 0.0 if name.startswith("eigenvalue") or name in (
            "omnivariance", "eigenentropy") else ATOL_RATIO
        err = np.abs(ours[m] - theirs[m])
        bad = err > RTOL * np.abs(theirs[m]) + atol
        assert not bad.any(), (name, int(bad.sum()), err[bad][:5], theirs[m][bad][:5])
    # the comparison covered almost every point for every feature but the NaN normals
    assert min(v for k, v in compared.items() if k not in ("nx", "ny", "nz")) > 0.8 * len(pts)
    if path == AUTZEN:
        assert compared["nx"] > 0.99 * len(pts)
    if path is None:        # 250 points of the scatter have fewer than 3 neighbours
        assert compared["nx"] > 0.98 * len(pts), compared["nx"]


#: float32 kernels vs jakteristics (test_against_jakteristics_float32): the error of each
#: feature over its conditioning scale (_scales32). A float32 covariance of n_p centred
#: points (coordinates relative to their cell, terms of the ball's size) carries an error
#: of a few ulps of l1, growing like sqrt(n_p) for rounded sums (about 30 neighbours here):
#: its eigenvalues are then off by c 2^-24 l1 with c of order 10, and so is every ratio;
#: jakteristics' own float32 formulas add ~1 ulp. TOL32 = 2^-17 = 128 x 2^-24. Measured
#: (PoCL, AMD EPYC Zen 4), the largest c: the synthetic scene 17.4, the bundled bunny
#: 17.2, Autzen 21 (eigenvalue_sum): a margin of 6.
TOL32 = 2.0 ** -17
#: float32 distances: a neighbour within a few ulps of r is in one ball and not the other
SAME_COUNT32 = 0.9999
#: a float32 normal is compared where its Davis-Kahan bound TOL32 / gap (gap = (l2 - l3) /
#: l1) is below this: elsewhere the bound says nothing
POSED32 = 0.01


def _clouds32():
    """The synthetic scene and the bundled bunny (clcurv/data/bunny.ply: bun_zipper's
    vertices in float32, metres; r = 2^-8 m, ~30 neighbours) and Autzen (tests/data)."""
    out = [pytest.param(None, 0.125, id="synthetic"),
           pytest.param(clcurv.data.sample_path(), 2.0 ** -8, id="bunny")]
    if AUTZEN.exists():
        out.append(pytest.param(AUTZEN, 6.0, id="autzen"))
    return out


def _scales32(J):
    """Each jakteristics feature's conditioning at eigenvalue errors of up to TOL32 l1:
    the eigenvalues and their sum l1; the ratios 1; omnivariance compared as its cube
    l1 l2 l3, whose error is ~ l1 l1 l2; eigenentropy -sum l_i ln l_i, whose derivative is
    |ln l_i + 1| (|ln d + 1| once l_i is below the error d = TOL32 l1: x ln x near 0);
    the normal and the verticality 1 / gap, gap = (l2 - l3) / l1 (Davis-Kahan)."""
    l1, l2, l3 = (J[f"eigenvalue{i}"] for i in (1, 2, 3))
    d = TOL32 * l1
    with np.errstate(divide="ignore", invalid="ignore"):
        entropy = l1 * sum(np.abs(np.log(np.maximum(x, d)) + 1) for x in (l1, l2, l3))
        turn = l1 / (l2 - l3)
    return dict({n: l1 for n in ("eigenvalue_sum", "eigenvalue1", "eigenvalue2",
                                 "eigenvalue3")},
                omnivariance=l1 * l1 * l2, eigenentropy=entropy,
                **{n: turn for n in ("nx", "ny", "nz", "verticality")})


@pytest.mark.parametrize("path, radius", _clouds32())
def test_against_jakteristics_float32(path, radius, device):
    """The default path (float32 kernels, ``precision`` left out) against jakteristics 0.6:
    every feature within TOL32 = 2^-17 of its conditioning scale (_scales32: l1 for the
    eigenvalues, 1 for the ratios, l1 / (l2 - l3) for the normal), where both are defined.
    The rules of test_against_jakteristics, in float32:
    - its ball is closed, clcurv's open, and float32 distances round a neighbour within a
      few ulps of r either way: points whose counts agree, > 99.99 % of them;
    - both finite (its NaN eigenentropy at l3 = 0, clcurv's NaN for rank < 2);
    - no l3 > 1e-9 l1 rule: the scales are absolute (l3's error is TOL32 l1, whatever l3);
    - normals (and verticality, 1 - |nz|) where (a) its eigenvector matching is
      unambiguous (normals_compared; elsewhere its normal is another eigenvector or NaN:
      the bunny in metres, l ~ 1e-6 m^2 < its 1e-5 threshold, has none) and (b) well posed
      in float32: TOL32 l1 / (l2 - l3) < POSED32; the points left out by (b) alone are at
      most MAX_LEFT_OUT of the cloud.
    Measured (PoCL, AMD EPYC Zen 4): at most 21 x 2^-24 (Autzen's eigenvalue_sum); normals
    at most 6.1 x 2^-24 l1 / (l2 - l3)."""
    jak = pytest.importorskip("jakteristics", reason="jakteristics is not installed: "
                              "pip install jakteristics (the 'test' extra) to run this check")
    pts = _points(path)
    J = jak.compute_features(pts, radius, feature_names=JAK_NAMES, num_threads=2)
    J = {n: J[:, i].astype(np.float64) for i, n in enumerate(JAK_NAMES)}
    f = clcurv.features(pts, radius, "all", ddof=1, device=device)   # float32: the default
    same = J["number_of_neighbors"] == f.count
    assert same.mean() > SAME_COUNT32, same.mean()
    jn = np.c_[J["nx"], J["ny"], J["nz"]]
    sign = np.sign(np.einsum("ij,ij->i", f["normals"], jn))
    matched, _ = normals_compared(J, f)
    scales = _scales32(J)
    with np.errstate(divide="ignore", invalid="ignore"):
        posed = TOL32 * scales["nx"] < POSED32
    both = same & np.isfinite(sign)
    left_out = both & matched & ~posed
    assert left_out.sum() <= MAX_LEFT_OUT * len(pts), int(left_out.sum())
    compared, worst = {}, {}
    for name in JAK_NAMES:
        if name == "number_of_neighbors":
            continue
        ours = f[name] * (sign if name in ("nx", "ny", "nz") else 1.0)
        theirs = J[name]
        if name == "omnivariance":
            ours, theirs = ours ** 3, theirs ** 3
        m = same & np.isfinite(ours) & np.isfinite(theirs)
        if name in ("nx", "ny", "nz", "verticality"):
            m &= matched & posed
        compared[name] = int(m.sum())
        if not m.any():
            continue
        err = np.abs(ours[m] - theirs[m]) / np.broadcast_to(scales.get(name, 1.0), m.shape)[m]
        worst[name] = err.max() / 2.0 ** -24
        bad = err > TOL32
        assert not bad.any(), (name, int(bad.sum()), err[bad][:5], theirs[m][bad][:5])
    print(f"\nfloat32 vs jakteristics, worst error / scale in units of 2^-24: " +
          ", ".join(f"{k} {v:.3g}" for k, v in worst.items()) +
          f"; normals compared at {compared['nx']} of {len(pts)} points")
    assert min(v for k, v in compared.items()
               if k not in ("nx", "ny", "nz", "verticality")) > 0.8 * len(pts)
    if path is None:        # 250 points of the scatter have fewer than 3 neighbours
        assert compared["nx"] > 0.98 * len(pts), compared["nx"]
    if path == AUTZEN:
        assert compared["nx"] > 0.99 * len(pts), compared["nx"]


def _check_reference(pts, radius, device, precision, tol):
    ref = clcurv.features(pts, radius, "all", backend="numpy")
    got = clcurv.features(pts, radius, "all", device=device, precision=precision)
    np.testing.assert_array_equal(got.count, ref.count)
    np.testing.assert_array_equal(got.status, ref.status)
    ok = ref.status == OK
    l1 = ref["eigenvalue1"][ok]
    # the conditioning of each feature: eigenvalue errors are ~tol * l1 absolute; ratios
    # to l1 or to the sum then ~tol; the normal (and so the verticalities) is determined to
    # ~tol * l1 / (l2 - l3)
    gap = (ref["eigenvalue2"] - ref["eigenvalue3"])[ok] / l1
    for name in F.FEATURES:
        a, b = got[name][ok], ref[name][ok]
        if name == "normals":
            a = a * np.sign(np.einsum("ij,ij->i", a, b))[:, None]
        if name == "omnivariance":     # cbrt amplifies l3's absolute error near l3 = 0:
            a, b = a ** 3, b ** 3      # compare l1 l2 l3, conditioned by l1 * l1 * l2
        scale = {"eigenvalue_sum": l1, "eigenvalue1": l1, "eigenvalue2": l1,
                 "eigenvalue3": l1, "density": b,
                 "omnivariance": l1 * l1 * ref["eigenvalue2"][ok],
                 "eigenentropy": np.abs(l1 * np.log(l1)) + l1}.get(name, 1.0)
        if name in ("normals", "verticality", "guinard_verticality"):
            scale = 1.0 / np.maximum(gap, 1e-3)
        scale = np.reshape(scale, (-1, 1)) if np.ndim(a) == 2 else scale
        err = np.abs(a - b) / scale
        assert np.nanmax(err) < tol, (name, np.nanmax(err))
        assert np.isnan(got[name][~ok]).all()


def test_against_reference_float32(device):
    """float32 kernels vs the float64 reference on a curved, noisy scene: errors relative
    to each feature's conditioning (l1 for eigenvalues, 1 for the ratios, l1 / (l2 - l3)
    for the normal), below 2e-5."""
    _check_reference(synthetic_scene(1)[::2], 0.12, device, "float", 2e-5)


def test_against_reference_float64(device):
    if not device.info.fp64:
        pytest.skip("no cl_khr_fp64")
    _check_reference(synthetic_scene(2)[::2], 0.12, device, "double", 1e-9)


@pytest.mark.parametrize("precision,tol", [("float", 2e-5), ("double", 1e-9)])
def test_against_reference_at_the_gpu_vector_width(device, monkeypatch, precision, tol):
    # GPUs build the kernels with VW = 4 (clcurv.runtime.program.precision_defines), whose records
    # are assembled lane by lane (kernels/lanes_records.h), not transposed as at VW = 8
    import clcurv.grid.cloud
    if precision == "double" and not device.info.fp64:
        pytest.skip("the device has no float64")
    real = clcurv.grid.cloud.precision_defines
    monkeypatch.setattr(clcurv.grid.cloud, "precision_defines",
                        lambda dev, prec: dict(real(dev, prec), VW=4))
    _check_reference(synthetic_scene(3)[::2], 0.12, device, precision, tol)


def test_same_eigenvalues_as_moments(device):
    """features.cl shares the moments kernel's PCA (pca.h): the eigenvalues and the
    surface variation's l0 are those of curvature(method='variation'), bit for bit."""
    pts = clcurv.shapes.torus(20000, noise=0.003, seed=4)["points"]
    cloud = clcurv.DeviceCloud(pts, 0.12, device=device)
    v = clcurv.curvature(cloud, 0.12, method="variation", orient=None)
    f = clcurv.features(cloud, 0.12, ["eigenvalue1", "eigenvalue2", "eigenvalue3", "normals",
                                      "surface_variation"])
    np.testing.assert_array_equal(f["surface_variation"], v.variation)
    np.testing.assert_array_equal(f["eigenvalue3"], v.eigenvalues[:, 0])
    np.testing.assert_array_equal(f["eigenvalue2"], v.eigenvalues[:, 1])
    np.testing.assert_array_equal(f["eigenvalue1"], v.eigenvalues[:, 2])
    np.testing.assert_array_equal(f["normals"], v.normals)
    np.testing.assert_array_equal(f.count, v.count)


def test_analytic_plane_line_and_ball(device):
    """Features with known values: a dense plane (planarity ~1, l3 = 0 exactly so
    sphericity = surface variation = 0, verticality = 0 for a horizontal plane, = 1 for a
    vertical one), a line (rank 1: status 2, NaN), an isotropic Gaussian blob (sphericity
    ~1)."""
    g = np.linspace(0, 1, 101)
    X, Y = np.meshgrid(g, g)
    flat = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    f = clcurv.features(flat, 0.055, "all", device=device)
    inner = (np.abs(flat[:, :2] - 0.5) < 0.4).all(1)
    assert (f.status[inner] == OK).all()
    assert np.allclose(f["planarity"][inner], 1.0, atol=1e-6)      # l1 = l2 on the grid
    assert np.all(f["sphericity"][inner] == 0) and np.all(f["verticality"][inner] == 0)
    assert np.allclose(f["guinard_verticality"][inner], 0.0, atol=1e-6)
    wall = flat[:, [0, 2, 1]]
    fw = clcurv.features(wall, 0.055, ["verticality", "Verticality"], device=device)
    assert np.allclose(fw["verticality"][inner], 1.0, atol=1e-6)
    line = np.c_[np.linspace(0, 1, 500), np.zeros(500), np.zeros(500)]
    fl = clcurv.features(line, 0.02, device=device)
    assert (fl.status == DEGENERATE).all() and np.isnan(fl["linearity"]).all()
    blob = np.random.default_rng(5).normal(0, 1, (20000, 3))
    fb = clcurv.features(blob, 1.5, ["sphericity", "density"], device=device)
    centre = np.linalg.norm(blob, axis=1) < 0.2
    assert np.median(fb["sphericity"][centre]) > 0.8
    # density = n / (4/3 pi r^3)
    ok = fb.status == OK             # far outliers of the blob have < 3 neighbours: NaN
    assert ok.mean() > 0.99 and np.isnan(fb["density"][~ok]).all()
    np.testing.assert_allclose(fb["density"][ok], fb.count[ok] / (4 / 3 * np.pi * 1.5 ** 3),
                               rtol=1e-6)


def test_names_and_spellings():
    """jakteristics and PDAL spellings map to one canonical name; PDAL's Verticality
    (Guinard) is not jakteristics' verticality (PDAL's DemantkeVerticality)."""
    c = F.canonical_names
    assert c(["Scattering", "sphericity"]) == ("sphericity",)
    assert c(["DemantkeVerticality"]) == ("verticality",)
    assert c(["Verticality"]) == ("guinard_verticality",)
    assert c(["Sum", "EigenvalueSum", "SurfaceVariation"]) == ("eigenvalue_sum",
                                                               "surface_variation")
    assert c("nx,ny,nz,number_of_neighbors") == ("normals",)
    assert c(["LINEARITY"]) == ("linearity",)           # unique case-insensitive match
    # CloudCompare's scalar-field names (CCCoreLib divides by n, as ddof=0; its
    # Verticality, 1 - |e3_z|, is asked for as "verticality": "Verticality" is PDAL's)
    assert c(["Eigenvalues sum", "Surface variation", "Normal change rate", "PCA1",
              "1st eigenvalue", "2nd eigenvalue", "3rd eigenvalue", "Omnivariance",
              "Eigenentropy", "Anisotropy", "Planarity", "Linearity", "Sphericity"]) == (
        "eigenvalue_sum", "surface_variation", "PCA1", "eigenvalue1", "eigenvalue2",
        "eigenvalue3", "omnivariance", "eigenentropy", "anisotropy", "planarity",
        "linearity", "sphericity")
    assert c(["surface VARIATION"]) == ("surface_variation",)
    assert c("all") == tuple(F.FEATURES)
    with pytest.raises(ValueError, match="unknown feature"):
        c(["curviness"])
    with pytest.raises(TypeError, match="feature names must be strings"):
        c(["planarity", 3])
    with pytest.raises(TypeError, match="features must be a name"):
        c(7)


def test_to_array_in_the_order_asked(device):
    """FeatureResult.to_array: one (N, F) float64 array, a column per name in the order
    asked (any spelling; normals as nx, ny, nz; the count), as jakteristics returns them;
    by default every feature held, in order; a feature not computed is a KeyError."""
    pts = clcurv.shapes.sphere(3000, 1.0, noise=0.01, seed=5)["points"]
    f = clcurv.features(pts, 0.2, ["planarity", "normals", "Scattering"], device=device)
    ask = ["Scattering", "nz", "number_of_neighbors", "planarity"]
    a = f.to_array(ask)
    assert a.shape == (len(pts), 4) and a.dtype == np.float64
    assert f.columns(ask) == ["sphericity", "nz", "number_of_neighbors", "planarity"]
    np.testing.assert_array_equal(a[:, 0], f["sphericity"])
    np.testing.assert_array_equal(a[:, 1], f.values["normals"][:, 2])
    np.testing.assert_array_equal(a[:, 2], f.count)
    np.testing.assert_array_equal(a[:, 3], f["planarity"])
    assert f.columns() == ["planarity", "nx", "ny", "nz", "sphericity"]
    np.testing.assert_array_equal(f.to_array()[:, 1:4], f.values["normals"])
    np.testing.assert_array_equal(f.to_array("planarity, Scattering"),
                                  f.to_array(["planarity", "sphericity"]))
    with pytest.raises(KeyError, match="linearity"):
        f.to_array(["linearity"])
    g = clcurv.features(pts, 0.2, ["planarity"], device=device)
    with pytest.raises(KeyError, match="normals"):
        g.to_array(["nz"])
    with pytest.raises(ValueError, match="unknown feature"):
        f.to_array(["curviness"])
    with pytest.raises(TypeError, match="must be strings"):
        f.to_array([3])


def test_features_none_is_the_default_set(device):
    """features=None asks for DEFAULT_FEATURES, as leaving it out does."""
    pts = clcurv.shapes.sphere(3000, 1.0, seed=4)["points"]
    a = clcurv.features(pts, 0.2, None, device=device)
    b = clcurv.features(pts, 0.2, device=device)
    assert a.names == b.names == F.canonical_names(F.DEFAULT_FEATURES)
    for name in a.names:
        np.testing.assert_array_equal(a[name], b[name])


def test_more_than_one_record(device):
    """"all" needs more columns than one 16-wide record: two launches, same values as
    asking for each half alone."""
    pts = clcurv.shapes.sphere(5000, 1.0, noise=0.01, seed=2)["points"]
    everything = clcurv.features(pts, 0.15, "all", device=device)
    assert len(layouts(tuple(F.FEATURES))) == 2
    for name in ("density", "normals", "eigenvalue3", "planarity"):
        alone = clcurv.features(pts, 0.15, [name], device=device)
        np.testing.assert_array_equal(alone[name], everything[name])


def test_bad_input_and_status(device):
    pts = clcurv.shapes.sphere(2000, 1.0, seed=1)["points"]
    with pytest.raises(ValueError, match="radius"):
        clcurv.features(pts, -1.0, device=device)
    with pytest.raises(ValueError, match="ddof"):
        clcurv.features(pts, 0.2, ddof=2, device=device)
    with pytest.raises(ValueError, match="features"):
        clcurv.features(pts, 0.2, [], device=device)
    empty = clcurv.features(np.empty((0, 3)), 0.2, device=device)
    assert len(empty) == 0 and empty["planarity"].shape == (0,)
    with pytest.warns(RuntimeWarning, match="too small"):
        sparse = clcurv.features(pts, 1e-4, device=device)
    assert (sparse.status == TOO_FEW).all() and np.isnan(sparse["planarity"]).all()
    up = clcurv.features(pts, 0.2, ["normals"], orient="up", device=device)
    assert (up["nz"][up.status == OK] >= 0).all()


def test_cli_features(tmp_path):
    """`clcurv features`: several radii give fields <feature>_r<radius>, equal to the API's
    values; --k adds the per-point radius."""
    from clcurv.cli.main import main
    pts = clcurv.shapes.sphere(4000, 1.0, noise=0.005, seed=8)["points"]
    src = tmp_path / "in.ply"
    clcurv.io.write(src, pts)
    out = tmp_path / "out.ply"
    assert main(["features", str(src), "-o", str(out), "--radius", "0.2,0.3",
                 "--features", "planarity,Scattering,nx"]) == 0
    attrs = clcurv.io.read(out).attributes
    for r in ("0.2", "0.3"):
        for name in ("planarity", "sphericity", "nx", "ny", "nz", "number_of_neighbors",
                     "feature_status"):
            assert f"{name}_r{r}" in attrs
    api = clcurv.features(pts, [0.2, 0.3], ["planarity", "Scattering"])
    np.testing.assert_allclose(attrs["planarity_r0.3"], api[1]["planarity"], rtol=1e-6)
    np.testing.assert_array_equal(attrs["number_of_neighbors_r0.2"], api[0].count)
    knn = tmp_path / "knn.ply"
    assert main(["features", str(src), "-o", str(knn), "--k", "20"]) == 0
    got = clcurv.io.read(knn).attributes
    assert "knn_radius" in got and (got["number_of_neighbors"] >= 20).all()
    alias = tmp_path / "alias.ply"                       # the API's spelling, radius="knn:K"
    assert main(["features", str(src), "-o", str(alias), "--radius", "knn:20"]) == 0
    same = clcurv.io.read(alias).attributes
    for name in ("knn_radius", "number_of_neighbors", "planarity"):
        np.testing.assert_array_equal(same[name], got[name])
    assert main(["features", str(src), "-o", str(knn)]) == 2           # neither --radius nor --k
    assert main(["features", str(src), "-o", str(knn), "--radius", "0.2",
                 "--features", "curviness"]) == 2


def test_radius_suffixes_are_distinct_and_plain():
    """Field suffixes give the radius back: %g's six digits made 300 and 300.0001 one
    field (one radius's results silently overwritten) and 1e6 a name with '+'."""
    from clcurv.api.features import radius_suffix
    assert [radius_suffix(r) for r in (0.5, 2.0, 1e6, 0.0123456789)] == \
        ["_r0.5", "_r2", "_r1000000", "_r0.0123456789"]
    assert radius_suffix(300) != radius_suffix(300.0001)


def test_cli_features_counts_dropped_rows_and_keeps_integer_dimensions(tmp_path):
    """Non-finite rows are dropped and counted in the summary (as `compute` does); a LAS
    input whose own uint8 extra-bytes dimension is named like a feature is not silently
    truncated (planarity stored as 0): the feature replaces it as a float dimension (the
    rule of clcurv.io.las for a clashing extra-bytes dimension)."""
    laspy = pytest.importorskip("laspy")
    from tests.hostile import run_cli
    pts = clcurv.shapes.sphere(3000, 1.0, noise=0.005, seed=8)["points"]
    bad = pts.copy()
    bad[[5, 9, 11]] = [np.nan, 0, 0], [np.inf, 1, 0], [0, 0, -np.inf]
    src = tmp_path / "nan.npy"
    np.save(src, bad)
    r = run_cli("features", src, "-o", tmp_path / "out.ply", "--radius", "0.2", "-q")
    assert r.code == 0 and "2997 points (3 non-finite dropped)" in r.stdout, r.stdout
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [1e-4] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.add_extra_dims([laspy.ExtraBytesParams(name="planarity", type=np.uint8)])
    typed = tmp_path / "typed.las"
    las.write(str(typed))
    out = tmp_path / "typed_f.las"
    r = run_cli("features", typed, "-o", out, "--radius", "0.2", "-q")
    assert r.code == 0, r.stderr
    back = laspy.read(str(out))
    got = np.asarray(back["planarity"])
    assert got.dtype.kind == "f"
    want = clcurv.features(np.column_stack([back.x, back.y, back.z]), 0.2,
                           ["planarity"])["planarity"]
    ok = np.isfinite(want)
    assert ok.mean() > 0.99 and np.allclose(got[ok], want[ok], atol=1e-6)


def test_cli_output_that_is_the_input(tmp_path):
    """-o the input file: refused for a PLY mesh (its faces would be lost),
    by compute and features, exit code 3, the input untouched."""
    from tests.hostile import run_cli
    src = tmp_path / "mesh.ply"
    src.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                   "property float y\nproperty float z\nelement face 1\n"
                   "property list uchar int vertex_indices\nend_header\n"
                   "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n")
    before = src.read_bytes()
    for cmd in (("features", src, "-o", src, "--radius", "2"),
                ("compute", src, "-o", src, "--radius", "2", "--method", "variation")):
        r = run_cli(*cmd, "-q")
        assert r.code == 3 and "the output is the input file" in r.stderr, r.stderr
        assert src.read_bytes() == before


def test_cli_too_many_las_fields_is_refused_before_any_work(tmp_path):
    """20 radii of every feature are 420 fields; a LAS file describes at most 341 extra
    dimensions (a 16-bit ExtraBytes VLR): exit code 3 before reading, no output (before,
    laspy failed after the whole computation with "VLR record_date length ... exceeds")."""
    pytest.importorskip("laspy")
    from tests.hostile import run_cli
    src = tmp_path / "missing.las"          # not even read: the count is known beforehand
    out = tmp_path / "many.las"
    radii = ",".join(str(1 + i) for i in range(20))
    r = run_cli("features", src, "-o", out, "--radius", radii, "--features", "all", "-q")
    assert r.code == 3 and "420 extra-bytes dimensions" in r.stderr, r.stderr
    assert not out.exists()
