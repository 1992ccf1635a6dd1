"""clcurv.features against PDAL's filters.covariancefeatures, where a ``pdal`` command is
available (bench/pdal_cli.py: ``$CLCURV_PDAL`` or ``pdal`` on the PATH).

PDAL has no wheel on PyPI and no package in Debian 12, so on the CI machine these tests
skip and say so; they ran with PDAL 2.3.0 (Ubuntu 22.04's package, in a chroot:
``CLCURV_PDAL="chroot /srv/jammy pdal"``, /tmp bind-mounted) when they were written. They
check what clcurv.features documents about PDAL: its spellings give PDAL's ``mode="Raw"``
values with ``ddof=1``, and how its default ``mode="SQRT"`` and ``mode="Normalized"``
differ.
"""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import clcurv
from bench.pdal_cli import covariance_features, pdal_command, pdal_version
from clcurv._shared.constants import OK
from test_features import AUTZEN, BUNNY, synthetic_scene

CMD, WHY = pdal_command()
if CMD is None:     # one report line for the module (a skip per test said the same 4-6 times)
    pytest.skip("PDAL oracle NOT RUN, the whole module (clcurv.features vs PDAL's "
                f"filters.covariancefeatures): PDAL cannot be run here: {WHY}",
                allow_module_level=True)

#: PDAL's name -> clcurv's canonical name (clcurv.api.features.FEATURES' aliases)
NAMES = {"Linearity": "linearity", "Planarity": "planarity", "Scattering": "sphericity",
         "Verticality": "guinard_verticality", "Omnivariance": "omnivariance",
         "Anisotropy": "anisotropy", "Eigenentropy": "eigenentropy",
         "EigenvalueSum": "eigenvalue_sum", "SurfaceVariation": "surface_variation",
         "DemantkeVerticality": "verticality"}
#: features that go through l3 (compared only where l3 is above round-off)
L3 = {"Scattering", "Omnivariance", "Eigenentropy", "SurfaceVariation", "Anisotropy",
      "Planarity"}
RTOL = 1e-5
#: PDAL rounds the centred offsets to float32 before it sums their products
#: (pdal::math::computeCovariance, ``static_cast<float>``): its covariance, and so its
#: eigenvalues, carry an absolute error of up to ~2^-24 l1 (l1 ~ 9 ft^2 on Autzen: its
#: linearity of a ground disc, l1 ~ l2, is off by up to 1.1e-7 where clcurv's float64
#: kernels agree with the float64 reference to 7e-14). EPS_L is that error with a margin
#: of 4, as a fraction of l1, propagated into each feature by _atol.
EPS_L = 2.0 ** -22


def _clouds():
    out = [pytest.param(None, 0.125, id="synthetic")]
    if AUTZEN.exists():      # feet, r = 6 ft (~30 neighbours)
        out.append(pytest.param(AUTZEN, 6.0, id="autzen"))
    if BUNNY.exists():       # metres, r = 2^-8 m
        out.append(pytest.param(BUNNY, 2.0 ** -8, id="bunny"))
    return out


def _unambiguous(pts, radius):
    """Points with no neighbour within 1e-9 r of the sphere of radius r: PDAL's KD-tree
    takes a closed ball (d <= r), clcurv an open one (d < r), and the two sides compute d^2
    with different round-off."""
    tree = cKDTree(pts)
    lo = tree.query_ball_point(pts, radius * (1 - 1e-9), return_length=True)
    hi = tree.query_ball_point(pts, radius * (1 + 1e-9), return_length=True)
    return lo == hi


def _eigen(f):
    return f["eigenvalue1"], f["eigenvalue2"], f["eigenvalue3"]


def _atol(name, f):
    """The absolute error of PDAL's ``name`` from eigenvalue errors of EPS_L l1 (per
    point): the ratios of eigenvalues to l1 or to their sum ~EPS_L (a few, bounded by the
    margin), the sum 3 EPS_L l1, omnivariance its relative derivative, eigenentropy the
    derivative sum |ln l_i + 1| of -sum l_i ln l_i."""
    l1, l2, l3 = _eigen(f)
    d = EPS_L * l1
    if name == "EigenvalueSum":
        return 3 * d
    if name == "Omnivariance":
        with np.errstate(divide="ignore", invalid="ignore"):    # l3 = 0: not compared
            return np.cbrt(l1 * l2 * l3) * d * (1 / l1 + 1 / l2 + 1 / l3) / 3
    if name == "Eigenentropy":
        return d * sum(np.abs(np.log(np.maximum(x, 1e-300)) + 1) for x in (l1, l2, l3))
    return np.full(len(l1), EPS_L)


def _need_fp64(device):
    if not device.info.fp64:
        pytest.skip("PDAL oracle NOT RUN on this device: the comparison runs the kernels "
                    "in float64; no cl_khr_fp64 here")


def _assert_raw_agrees(theirs, f, base, min_fraction):
    """Every PDAL Raw-mode feature in ``theirs`` equals clcurv's (FeatureResult ``f``) to
    RTOL plus _atol at the points of ``base`` where both are finite (the features through
    l3 only where l3 > 1e-9 l1), and such points are more than ``min_fraction`` of all."""
    l1, _, l3 = _eigen(f)
    for name, values in theirs.items():
        ours = f[NAMES[name]]
        m = base & np.isfinite(ours) & np.isfinite(values)
        if name in L3:
            m &= l3 > 1e-9 * l1
        assert m.sum() > min_fraction * len(f.count), (name, int(m.sum()))
        err = np.abs(ours[m] - values[m])
        bad = err > RTOL * np.abs(values[m]) + _atol(name, f)[m]
        assert not bad.any(), (name, int(bad.sum()), err[bad][:5], values[m][bad][:5])


@pytest.mark.parametrize("path, radius", _clouds())
def test_raw_mode(path, radius, device):
    """PDAL's Raw-mode features = clcurv's under PDAL's spellings with ddof=1, to 1e-5
    relative where both are defined.

    Definitional differences, each handled here:
    1. PDAL divides the covariance by n - 1 (a sample covariance, as jakteristics): ddof=1
       (Omnivariance, Eigenentropy and EigenvalueSum depend on it, the ratios do not).
    2. PDAL's ball is closed, clcurv's open: points with a neighbour at r (to 1e-9 r) are
       left out (_unambiguous).
    3. PDAL gives a point with fewer than 3 neighbours (min_k) no features (its fields stay
       0) and returns numbers for a covariance of rank < 2, where clcurv's status is 1 or 2
       and its features NaN: only status-OK points are compared, where both are finite
       (PDAL's Eigenentropy is NaN where l3 = 0: 0 log 0; clcurv takes 0).
    4. l3 of a coplanar ball is round-off on both sides: the features through l3 only
       where l3 > 1e-9 l1.
    5. PDAL's offsets are rounded to float32 (EPS_L): every feature is compared to
       1e-5 relative plus that rounding propagated (_atol).
    """
    _need_fp64(device)
    pts = synthetic_scene() if path is None else clcurv.io.read(path).points
    xyz, theirs = covariance_features(CMD, pts, radius, mode="Raw")
    # PDAL read the LAS coordinates (pts rounded to the file's scale) in the same order
    np.testing.assert_allclose(xyz, pts, rtol=0, atol=1e-6 * np.ptp(pts))
    assert set(theirs) >= set(NAMES) - {"EigenvalueSum"}
    f = clcurv.features(xyz, radius, "all", ddof=1, device=device, precision="double")
    base = (f.status == OK) & _unambiguous(xyz, radius)
    assert base.mean() > 0.9
    _assert_raw_agrees(theirs, f, base, 0.8)


@pytest.mark.parametrize("mode", ["SQRT", "Normalized"])
def test_other_modes(mode, device):
    """What clcurv.features documents about PDAL's other modes: its default SQRT takes the
    eigenvalues' square roots, Normalized divides them by their sum, in every feature but
    DemantkeVerticality and EigenvalueSum (the raw sum); SurfaceVariation divides the
    transformed l3 by the raw sum. Checked against formulas on clcurv's eigenvalues."""
    _need_fp64(device)
    pts = synthetic_scene()
    xyz, theirs = covariance_features(CMD, pts, 0.125, mode=mode)
    f = clcurv.features(xyz, 0.125, "all", ddof=1, device=device, precision="double")
    l1, l2, l3 = _eigen(f)
    s = l1 + l2 + l3
    a, b, c = (np.sqrt(l1), np.sqrt(l2), np.sqrt(l3)) if mode == "SQRT" else (l1 / s, l2 / s,
                                                                             l3 / s)
    with np.errstate(divide="ignore", invalid="ignore"):     # l3 = 0: NaN, left out
        eigenentropy = -(a * np.log(a) + b * np.log(b) + c * np.log(c))
    expect = {"Linearity": (a - b) / a, "Planarity": (b - c) / a, "Scattering": c / a,
              "Omnivariance": np.cbrt(a * b * c), "Anisotropy": (a - c) / a,
              "Eigenentropy": eigenentropy,
              "EigenvalueSum": s, "SurfaceVariation": c / s,
              "DemantkeVerticality": f["verticality"]}
    m0 = (f.status == OK) & _unambiguous(xyz, 0.125) & (l3 > 1e-9 * l1)
    for name, want in expect.items():
        if name not in theirs:
            continue
        m = m0 & np.isfinite(want) & np.isfinite(theirs[name])
        assert m.sum() > 0.8 * len(xyz), name
        err = np.abs(theirs[name][m] - want[m])
        bad = err > RTOL * np.abs(want[m]) + EPS_L
        assert not bad.any(), (mode, name, pdal_version(CMD), err[bad][:5], want[m][bad][:5])


def test_knn_mode(device):
    """clcurv's k nearest (the point itself the first) are PDAL's knn = k - 1 nearest plus
    the point: ``features(P, k=30, ddof=1)`` against PDAL's ``knn=29`` in Raw mode, on a
    sphere whose density varies 10x (random doubles: no ties at the k-th distance), with
    the tolerances of test_raw_mode."""
    _need_fp64(device)
    pts = clcurv.shapes.sphere(20000, 1.0, noise=0.002, seed=7)["points"]
    pts = pts[np.random.default_rng(7).random(len(pts)) < 0.1 + 0.9 * (pts[:, 2] + 1) / 2]
    xyz, theirs = covariance_features(CMD, pts, None, mode="Raw", knn=29)
    f = clcurv.features(xyz, k=30, features="all", ddof=1, device=device, precision="double")
    assert (f.count == 30).mean() > 0.999
    _assert_raw_agrees(theirs, f, (f.status == OK) & (f.count == 30), 0.9)
