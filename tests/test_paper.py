"""bench/paper.py: the paper's experiments (Digne & Morel 2013, Section 6) in the small setting.

Runs ``bench.paper.main(['--small', ...])`` once in-process (real OpenCL kernels on PoCL,
< 60 s) and checks the numbers of the returned tables against the paper's conclusions that
must hold even at this low density, plus the markdown output.
"""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

import clcurv

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the repo root: bench/
from bench import paper  # noqa: E402


@pytest.fixture(scope="module")
def res(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper") / "paper.md"
    r = paper.main(["--small", "--quiet", "--out", str(out), "--seed", "0"])
    r["_out"] = out
    return r


def test_markdown_has_every_table(res):
    md = res["_out"].read_text()
    assert md == res["markdown"]
    for t in range(1, 9):
        assert f"## Table {t}:" in md, f"Table {t} missing"
    for section in ("### Table 1b", "## Assumptions", "## Verdicts"):
        assert section in md
    for k in (1, 2, 3, 4):
        assert f"\n{k}. **" in md, f"verdict {k} missing"
        assert res["verdicts"][k]["verdict"] in ("holds", "partly", "fails")
    # the paper's numbers are printed beside ours
    assert "2.8609" in md and "0.0749" in md and "276 s" in md


def test_table1_mls1_iteration_more_stable_than_mls2(res):
    t1 = res["table1"]
    # the radius calibration reproduces the paper's iteration-0 std
    assert abs(t1["mls1"][0]["std"] / 2.8609 - 1) < 0.1, t1["mls1"][0]
    for k in (3, 4, 5):
        a, b = t1["mls1"][k]["std"], t1["mls2"][k]["std"]
        assert a < b / 2, f"iteration {k}: MLS1 std {a:.4f}, MLS2 std {b:.4f}"


def test_table1_mls1_mean_and_shrinking(res):
    m = res["table1"]["mls1"]
    assert abs(m[5]["mean"] - 0.5) < 0.05 * 0.5, m[5]
    # a mean curvature motion shrinks the sphere: H grows with the iterations
    assert m[3]["mean"] < m[5]["mean"] < m[10]["mean"]
    # the std reading of the paper's "variance" fits its MLS1 column far better
    chk = res["table1_noise_check"]
    assert chk["std"]["misfit"] < 0.02 < chk["variance"]["misfit"]


def test_calibration_reaches_the_target(res):
    for shape in paper.SHAPES:
        c = res["calibration"][shape]
        for m in paper.METHODS:
            ratio = c["rows"][m]["H"]["std"] / c["target"]
            # MLS1's std jumps with single stray points at this density
            tol = 1.35 if m == "mls1" else 1.1
            assert 1 / tol < ratio < tol, (shape, m, c["rows"][m]["evaluations"])


def test_calibrated_mls1_mean_on_sphere(res):
    row = res["calibration"]["sphere"]["rows"]["mls1"]
    assert abs(row["H"]["mean"] - 0.5) < 0.05 * 0.5, row["H"]
    assert row["N"] == 5 and math.isclose(row["r_eq"], math.sqrt(5) * row["r"])


def test_calibrated_covariances_close_and_mls2_needs_larger_radius(res):
    for shape in paper.SHAPES:
        rows = res["calibration"][shape]["rows"]
        r2, r3 = rows["2dcov2"]["r"], rows["3dcov"]["r"]
        assert abs(r2 / r3 - 1) < 0.1, (shape, r2, r3)
        assert abs(rows["2dcov2"]["H"]["snr"] / rows["3dcov"]["H"]["snr"] - 1) < 0.1
        assert 1.3 < rows["mls2"]["r"] / max(r2, r3) < 2.8, (shape, rows["mls2"]["r"], r2)
        # MLS1's processing radius is the smallest of all
        assert rows["mls1"]["r"] < min(r2, r3, rows["mls2"]["r"])


def test_scale_space_first_beats_the_raw_cloud_at_the_same_radius(res):
    for shape in paper.SHAPES:
        s = res["scale_space"][shape]
        assert s["r"] == res["calibration"][shape]["rows"]["mls1"]["r"]
        for m in paper.OPERATORS:
            a, raw = s["rows"][m]["ss"]["H"], s["rows"][m]["raw"]["H"]
            assert a["std"] < raw["std"] / 3, (shape, m, a["std"], raw["std"])
            assert a["snr"] > raw["snr"]


def test_scale_space_then_mls2_gives_signed_curvatures(res):
    cyl = res["scale_space"]["cylinder"]["rows"]["mls2"]["ss"]
    assert abs(cyl["k1"]["mean"] - 1.0) < 0.1 and abs(cyl["k2"]["mean"]) < 0.1, cyl
    assert cyl["dir1_deg"] < 10
    tor = res["scale_space"]["torus"]["rows"]["mls2"]["ss"]
    assert abs(tor["k1"]["mean"] - 2.0) < 0.2 and abs(tor["k2"]["mean"] - 0.4) < 0.1, tor
    assert tor["dir1_deg"] < 10


def test_table8_times(res):
    t8 = res["table8"]
    for m in paper.OPERATORS:
        row = t8["rows"][m]
        assert row["without"] > 0 and row["with"] > 0
        assert row["r_with"] < row["r_without"]


def test_mls2_iteration_is_clcurv_project():
    s = clcurv.shapes.sphere(4000, 1.0, noise=0.01, seed=5)
    _, iterates = paper.mls2_iterates(s["points"], 0.3, 2, s["normals"])
    ref = clcurv.project(s["points"], 0.3, projections=2, normals=s["normals"])
    np.testing.assert_allclose(iterates[2], ref, rtol=0, atol=1e-12)
    assert np.abs(iterates[2] - s["points"]).max() > 0   # the projection moved the points


def test_secant_radius_finds_a_power_law_root():
    f = lambda r: {"r": r, "H": {"std": 0.01 * r ** -2.7}}
    best, hist = paper.secant_radius(f, 0.05, 0.1, 8, 0.01)
    assert abs(best["H"]["std"] / 0.05 - 1) < 0.01 and len(hist) <= 4
