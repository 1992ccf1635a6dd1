"""``clcurv demo`` end to end on the bundled bunny (real kernels), the sample accessor, and
the package's import surface (``import clcurv`` alone gives io, render, data)."""
import contextlib
import io as stdio
import struct
import subprocess
import sys

import numpy as np
import pytest

import clcurv
from clcurv.cli import main as cli, demo
from clcurv import io
from clcurv.data import SAMPLE_POINTS, sample_path

DIRS = [f"dir{i}_{a}" for i in "12" for a in "xyz"]
FIELDS = ["mean_curvature", "gaussian_curvature", "k1", "k2", *DIRS, "neighbours", "status"]
#: median mean curvature (1/m) of the bunny after 3 MLS1 steps, MLS2, radius auto
#: (0.003804 m, ~31 neighbours): measured 23.23 on PoCL (float); outward normals make the
#: mostly convex bunny positive. The tolerance leaves room for other devices' rounding.
MEDIAN_H, MEDIAN_H_TOL = 23.23, 1.5


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    outdir = tmp_path_factory.mktemp("demo")
    printed = stdio.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli.main(["demo", "--outdir", str(outdir), "-q"])
    return code, outdir, printed.getvalue()


def test_demo_exits_0_and_prints_the_summary(demo_run):
    code, outdir, text = demo_run
    assert code == 0, text
    assert "radius auto: 0.0038" in text
    assert "method mls2, radius 0.0038" in text and "scale space 3 iteration(s)" in text
    assert "status ok 100.0%" in text
    for name in ("mean_curvature", "gaussian_curvature", "k1", "k2"):
        assert f"\n  {name} " in text, name
    assert f"wrote {outdir / demo.PLY_NAME}: nx ny nz, {', '.join(FIELDS)}" in text
    assert f"wrote {outdir / demo.PNG_NAME}" in text


def test_demo_ply_fields_and_numbers(demo_run):
    _, outdir, _ = demo_run
    cloud = io.read(outdir / demo.PLY_NAME)
    assert cloud.points.shape == (SAMPLE_POINTS, 3) == (35_947, 3)
    np.testing.assert_array_equal(cloud.points, io.read(sample_path()).points)   # input kept
    assert list(cloud.attributes) == FIELDS
    a = cloud.attributes
    ok = a["status"] == 0
    assert ok.mean() > 0.999
    assert 28 <= np.median(a["neighbours"]) <= 34
    h, k1, k2 = (a[k][ok].astype(float) for k in ("mean_curvature", "k1", "k2"))
    assert abs(np.median(h) - MEDIAN_H) < MEDIAN_H_TOL, np.median(h)
    assert np.all(k1 >= k2)
    np.testing.assert_allclose(h, 0.5 * (k1 + k2), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(a["gaussian_curvature"][ok], k1 * k2, rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(np.linalg.norm(cloud.normals[ok], axis=1), 1, atol=1e-5)


def test_demo_png_is_a_valid_picture(demo_run):
    pytest.importorskip("matplotlib")
    _, outdir, _ = demo_run
    data = (outdir / demo.PNG_NAME).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    assert (width, height) == (1320, 495)         # (3.7 * 3 + 0.9) x 4.5 in at 110 dpi
    assert len(data) > 50_000                     # a coloured bunny, not a blank figure


def test_sample_path():
    p = sample_path()
    assert p.is_file() and p.name == "bunny.ply" and p == clcurv.data.sample_path()
    assert b"element vertex 35947" in p.read_bytes()[:400]


def _python(code):
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return p.stdout


def test_plain_import_clcurv_gives_io_render_data(tmp_path):
    pytest.importorskip("matplotlib")
    out = _python(
        "import clcurv; clcurv.io.read; clcurv.render.render\n"
        "c = clcurv.io.read(clcurv.data.sample_path())\n"
        f"p = clcurv.render.render(c.points, c.points[:, 1], {str(tmp_path / 'y.png')!r}, dpi=20)\n"
        "print(len(c.points), p.is_file())")
    assert out.split() == ["35947", "True"]


def test_demo_does_not_import_the_cli():
    out = _python("import sys, clcurv.cli.demo; print('clcurv.cli.main' in sys.modules)")
    assert out.strip() == "False"
