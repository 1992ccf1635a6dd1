"""clcurv.render: PNGs of a cloud coloured by a field (matplotlib, Agg)."""
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib", reason='rendering needs matplotlib: pip install "clcurv[render]"')

from matplotlib.image import imread  # noqa: E402

from clcurv.render import MissingMatplotlibError, render  # noqa: E402

DPI = 60  # small pictures keep the tests fast; the size check is figsize * dpi all the same


def sphere(n, seed=0, radius=1.0):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


@pytest.fixture
def captions(monkeypatch):
    """Every string passed to Figure.text during the test (the title and the caption)."""
    import matplotlib.figure

    texts = []
    orig = matplotlib.figure.Figure.text

    def spy(self, x, y, s, *a, **k):
        texts.append(s)
        return orig(self, x, y, s, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "text", spy)
    return texts


def load_rgb(path):
    img = imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    rgb = img[..., :3]
    if rgb.dtype != np.uint8:
        rgb = np.round(rgb * 255).astype(np.uint8)
    return rgb


def check_picture(path, n_views=3, dpi=DPI):
    path = Path(path)
    assert path.is_file() and path.stat().st_size > 0
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rgb = load_rgb(path)
    w_in, h_in = 3.7 * n_views + 0.9, 4.5
    assert rgb.shape[:2] == (round(h_in * dpi), round(w_in * dpi))
    non_white = np.any(rgb < 245, axis=2).mean()
    assert non_white > 0.15, f"only {non_white:.1%} non-white pixels"
    colours = np.unique(rgb.reshape(-1, 3), axis=0).shape[0]
    return rgb, non_white, colours


def reddish(rgb):
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return np.count_nonzero((r > 150) & (r - np.maximum(g, b) > 70))


def bluish(rgb):
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return np.count_nonzero((b > 120) & (b - np.maximum(r, g) > 40))


def test_signed_sphere_has_red_and_blue(tmp_path):
    p = sphere(20_000)
    out = render(p, p[:, 2], tmp_path / "z.png", field="z", unit="m", dpi=DPI)
    assert isinstance(out, Path) and out == tmp_path / "z.png"
    rgb, non_white, colours = check_picture(out)
    assert colours > 200, colours
    assert reddish(rgb) > 500 and bluish(rgb) > 500, (reddish(rgb), bluish(rgb))


def test_signed_autodetected_for_curvature_names(tmp_path):
    p = sphere(5_000, seed=1)
    v = 0.5 + p[:, 0]  # mostly positive: robust range may not straddle 0, name says signed
    out = render(p, v, tmp_path / "h.png", field="mean_curvature", dpi=DPI)
    rgb, _, _ = check_picture(out)
    assert reddish(rgb) > 200 and bluish(rgb) > 50


def test_unsigned_sphere_is_sequential(tmp_path):
    p = sphere(20_000, seed=2)
    out = render(p, np.abs(p[:, 2]), tmp_path / "absz.png", field="|z|", unit="m", dpi=DPI)
    rgb, _, colours = check_picture(out)
    assert colours > 200, colours
    # viridis: dark purple to yellow, no red-dominated pixels
    assert reddish(rgb) < 50, reddish(rgb)
    # signed=False forces a sequential map even for values of both signs
    out2 = render(p, p[:, 2], tmp_path / "z_seq.png", field="z", signed=False, dpi=DPI)
    assert reddish(check_picture(out2)[0]) < 50


def test_large_cloud_is_subsampled(tmp_path, captions):
    rng = np.random.default_rng(3)
    p = sphere(300_000, seed=3) * rng.uniform(0.98, 1.02, (300_000, 1))
    v = p[:, 0] * p[:, 1]
    out = render(p, v, tmp_path / "big.png", field="k1", max_points=200_000, dpi=DPI,
                 views=("front", "iso"))
    rgb, _, colours = check_picture(out, n_views=2)
    assert colours > 200
    assert "showing 200,000 of 300,000 points" in " ".join(captions), captions


def test_subsample_caption_and_determinism(tmp_path, captions):
    p = sphere(3_000, seed=4)
    v = p[:, 2].copy()
    v[:7] = np.nan
    a = render(p, v, tmp_path / "a.png", max_points=1_000, dpi=DPI, seed=5)
    caption = " ".join(captions)
    assert "showing 1,000 of 3,000 points" in caption, caption
    assert "7 NaN" in caption, caption
    b = render(p, v, tmp_path / "b.png", max_points=1_000, dpi=DPI, seed=5)
    assert np.array_equal(load_rgb(a), load_rgb(b))


def test_all_nan_still_renders_grey(tmp_path, captions):
    p = sphere(4_000, seed=6)
    out = render(p, np.full(len(p), np.nan), tmp_path / "nan.png", dpi=DPI)
    assert out.is_file()
    rgb = load_rgb(out)
    grey = np.all(np.abs(rgb.astype(int) - 200) <= 3, axis=2).mean()
    assert grey > 0.05, grey
    assert "all 4,000 values are NaN" in " ".join(captions)


def test_nan_points_and_bad_coordinates(tmp_path):
    p = sphere(5_000, seed=7)
    v = p[:, 1].copy()
    v[::3] = np.nan
    p[:10] = np.nan
    check_picture(render(p, v, tmp_path / "mixed.png", dpi=DPI, views=("front", "side"),
                         unit=None), n_views=2)


@pytest.mark.parametrize("points, values", [
    (np.zeros((10, 2)), np.zeros(10)),
    (np.zeros(30), np.zeros(10)),
    (np.zeros((10, 3)), np.zeros(9)),
    (np.zeros((10, 3)), np.zeros((10, 2))),
])
def test_bad_shapes(tmp_path, points, values):
    with pytest.raises(ValueError):
        render(points, values, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def test_signed_fields_come_from_the_registry():
    from clcurv.ops.registry import signed_file_fields
    from clcurv.render import SIGNED_FIELDS
    assert signed_file_fields() == {"mean_curvature", "gaussian_curvature", "k1", "k2"}
    assert SIGNED_FIELDS == signed_file_fields() | {"mean", "gaussian", "k1", "k2", "h", "k"}
    assert "surface_variation" not in SIGNED_FIELDS


def test_bad_options(tmp_path):
    p = sphere(100)
    with pytest.raises(ValueError, match="unknown view"):
        render(p, p[:, 0], tmp_path / "x.png", views=("front", "diagonal"))
    with pytest.raises(ValueError, match="percentiles"):
        render(p, p[:, 0], tmp_path / "x.png", percentiles=(98, 2))


def test_missing_matplotlib_message(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_mpl(name, *a, **k):
        if name == "matplotlib" or name.startswith("matplotlib."):
            raise ImportError("No module named 'matplotlib'")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_mpl)
    p = sphere(100)
    with pytest.raises(ImportError, match="pip install matplotlib") as exc:
        render(p, p[:, 0], tmp_path / "x.png")
    assert isinstance(exc.value, MissingMatplotlibError)
    assert "clcurv[render]" in str(exc.value)


def test_bunny_sample(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    from clcurv.data import sample_path
    v = plyfile.PlyData.read(str(sample_path()))["vertex"]
    p = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    out = render(p, p[:, 2], tmp_path / "bunny_z.png", field="z", unit="m", dpi=DPI)
    rgb, non_white, colours = check_picture(out)
    assert reddish(rgb) > 500 and bluish(rgb) > 500


# --- up axis, terrain views, colour-bar label, NaN beneath (issue 14) -------------------------

from clcurv import render as R  # noqa: E402
from clcurv.render import figure  # noqa: E402
from conftest import data_path  # noqa: E402

AUTZEN = data_path("laspy_autzen_trim.laz")      # shipped in tests/data too


def tile():
    """A LAS tile's points: the Autzen LAZ (tests/data)."""
    import clcurv
    return clcurv.io.read(AUTZEN).points


def test_las_tile_leads_with_top_and_oblique_views():
    """A LAS/LAZ tile is z-up: the picture is the top view (x right, y up, as a map) and an
    oblique view, not two edge-on sections."""
    p = tile()
    fig, info = figure(p, p[:, 2], field="z", unit="ft", source="tile.laz", dpi=DPI)
    assert np.array_equal(info["up"], [0, 0, 1]) and info["terrain"]
    assert info["views"] == ("top", "oblique")
    titles = [ax.get_title() for ax in fig.axes[:2]]
    assert titles[0] == "top  (+x \u2192, +y \u2191)" and titles[1] == "oblique"
    # auto also finds z for terrain in another format (the thin axis), and --up overrides
    assert np.array_equal(R.up_axis("auto", p), [0, 0, 1])
    assert np.array_equal(R.up_axis("-y"), [0, -1, 0])
    with pytest.raises(ValueError, match="up must be"):
        R.up_axis("w")


def test_scanned_objects_keep_y_up_and_three_views():
    p = sphere(3_000, seed=2)
    _, info = figure(p, p[:, 0], dpi=DPI)
    assert np.array_equal(info["up"], [0, 1, 0]) and info["views"] == ("front", "side", "top")
    # a z-up object (not flat) given --up z: the front view then shows x right, z up
    fig, info = figure(p * (1, 1, 2), p[:, 0], up="z", dpi=DPI)
    assert fig.axes[0].get_title() == "front  (+x \u2192, +z \u2191)"


@pytest.mark.parametrize("field, unit", [("z", "m"),
                                         ("a_rather_long_field_name_r0.125", "1/length unit"),
                                         ("x" * 60, "y" * 30)])
def test_colourbar_label_inside_the_picture(tmp_path, field, unit):
    """The colour-bar label's box lies inside the written picture (moved, widened or a
    smaller font when needed), for short, long and absurd labels."""
    p = tile()[::10]
    fig, info = figure(p, p[:, 2], field=field, unit=unit, source="t.laz", dpi=DPI)
    x0, y0, x1, y1 = info["label_bbox"]
    w, h = info["size"]
    assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h, (info["label_bbox"], info["size"])
    out = R.render(p, p[:, 2], tmp_path / "t.png", field=field, unit=unit, source="t.laz",
                   dpi=DPI)
    assert load_rgb(out).shape[:2] == (h, w)


def test_nan_points_are_drawn_beneath(tmp_path):
    """A valued ground grid with NaN points just above it (nearer to a top view): the valued
    points hide the NaN ones, so no NaN grey shows inside the ground."""
    g = np.linspace(0, 1, 120)
    X, Y = np.meshgrid(g, g)
    ground = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    above = ground + (0, 0, 0.01)
    pts = np.vstack([ground, above])
    vals = np.r_[np.linspace(0, 1, len(ground)), np.full(len(above), np.nan)]
    out = R.render(pts, vals, tmp_path / "n.png", up="z", views=("top",), dpi=DPI,
                   field="v", unit=None)
    rgb = load_rgb(out)
    h, w = rgb.shape[:2]
    inner = rgb[int(0.4 * h):int(0.7 * h), int(0.1 * w):int(0.5 * w)]
    grey = np.all(np.abs(inner.astype(int) - 200) <= 3, axis=2).mean()
    assert grey < 0.01, grey


def test_cli_render_las_and_up(tmp_path):
    """`clcurv render` on a LAS/LAZ file draws two views (top, oblique); --up y on the same
    file draws the three object views. The Autzen LAZ (tests/data)."""
    tile = AUTZEN
    from clcurv.cli.main import main
    attrs = __import__("clcurv").io.read(tile).attributes
    field = "intensity" if "intensity" in attrs else next(iter(attrs))
    out = tmp_path / "a.png"
    assert main(["render", str(tile), "--field", field, "-o", str(out)]) == 0
    assert load_rgb(out).shape[1] == round((3.7 * 2 + 0.9) * 110)
    assert main(["render", str(tile), "--field", field, "--up", "y", "-o", str(out)]) == 0
    assert load_rgb(out).shape[1] == round((3.7 * 3 + 0.9) * 110)


@pytest.mark.parametrize("name, unit", [
    ("mean_curvature", "1/length"), ("k2", "1/length"), ("gaussian_curvature", "1/length^2"),
    ("dir1_x", ""), ("surface_variation", ""), ("planarity", ""), ("planarity_r0.5", ""),
    ("eigenvalue_sum_r4", "length^2"), ("eigenvalue3", "length^2"), ("density", "1/length^3"),
    ("nx_r2", ""), ("number_of_neighbors", ""), ("neighbours", ""), ("status", ""),
    ("knn_radius", "length"), ("optimal_radius", "length"), ("intensity", None),
    ("planarity_rx", None)])
def test_field_units(name, unit):
    """The unit of each field clcurv writes, from the registries (operators' outputs,
    covariance features with or without a radius suffix): "" when dimensionless, None for
    a field of another tool."""
    assert R.field_unit(name) == unit


def test_colourbar_unit_follows_the_field(tmp_path):
    """The label's unit is the field's own by default (a feature is dimensionless, a
    curvature 1/length, an unknown field has none); --unit overrides it."""
    p = sphere(2_000, seed=4)
    v = p[:, 0]
    for field, label in (("planarity_r0.5", "planarity_r0.5"),
                         ("mean_curvature", "mean_curvature [1/length]"),
                         ("eigenvalue_sum", "eigenvalue_sum [length^2]"),
                         ("intensity", "intensity")):
        assert figure(p, v, field=field, dpi=DPI)[1]["label"] == label
    assert figure(p, v, field="mean_curvature", unit="1/mm", dpi=DPI)[1]["label"] == \
        "mean_curvature [1/mm]"
    from clcurv.cli.main import build_parser
    args = build_parser().parse_args(["render", "in.ply", "-o", "o.png"])
    assert args.unit == "auto"


def greyish(rgb, level=0x8c, tol=6):
    """Pixels of the 'not significant' grey (#8c8c8c)."""
    d = np.abs(rgb[..., :3].astype(int) - level)
    return np.count_nonzero(d.max(axis=-1) <= tol)


def test_not_significant_points_are_grey(tmp_path, captions):
    """|value| < 2 se is drawn #8c8c8c and counted: z on a sphere with se = 0.25 greys the
    band |z| < 0.5 of the unit sphere, half its area (Archimedes: 10,000 of 20,000)."""
    p = sphere(20_000, seed=4)
    v = p[:, 2]
    se = np.full(len(p), 0.25)
    se[:10] = np.nan                                     # NaN se: coloured
    fig, info = figure(p, v, field="z", se=se, dpi=DPI)
    want = int(np.count_nonzero(np.abs(v[10:]) < 0.5))
    assert info["not_significant"] == want and 9500 < want < 10500
    assert any(f"{want:,} (" in t and "not significant" in t for t in captions)
    out = render(p, v, tmp_path / "sig.png", field="z", se=se, dpi=DPI)
    rgb, _, _ = check_picture(out)
    plain = check_picture(render(p, v, tmp_path / "plain.png", field="z", dpi=DPI))[0]
    assert greyish(rgb) > 20 * max(greyish(plain), 1) and greyish(rgb) > 1000
    assert reddish(rgb) > 300 and bluish(rgb) > 300          # |z| > 0.5 stays coloured
    with pytest.raises(ValueError, match="se must have one entry per point"):
        render(p, v, tmp_path / "bad.png", se=se[:5])


def test_cli_render_takes_the_field_se(tmp_path):
    """clcurv render greys by <field>_se when the file has it (--se auto), or the field
    named, and refuses a missing one."""
    from clcurv import io
    from clcurv.cli.main import main
    p = sphere(3000, seed=5)
    src = tmp_path / "c.ply"
    io.write(src, p, fields={"mean_curvature": p[:, 2], "mean_curvature_se": np.full(3000, 0.25)})
    assert main(["render", str(src), "-o", str(tmp_path / "a.png")]) == 0
    assert main(["render", str(src), "--se", "none", "-o", str(tmp_path / "b.png")]) == 0
    a = check_picture(tmp_path / "a.png", dpi=110)[0]       # the command's dpi
    b = check_picture(tmp_path / "b.png", dpi=110)[0]
    assert greyish(a) > 20 * max(greyish(b), 1)
    assert main(["render", str(src), "--se", "k1_se", "-o", str(tmp_path / "c.png")]) == 2
    assert not (tmp_path / "c.png").exists()
