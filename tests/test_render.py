"""Pictures: the PNG has the stated size, is not blank, uses a diverging map for signed
fields, subsamples large clouds, and survives an all-NaN field."""
import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib", reason="matplotlib is an optional extra")
from matplotlib.image import imread  # noqa: E402

from clcurv import shapes  # noqa: E402
from clcurv.render import render  # noqa: E402


def pixels(path):
    img = imread(str(path))
    return img[..., :3] if img.ndim == 3 else img


def test_signed_field_png_size_colours_and_content(tmp_path):
    pts = shapes.sphere(20_000, 1.0, seed=1)["points"]
    path = render(pts, pts[:, 2], tmp_path / "signed.png", field="mean_curvature", unit="1/m",
                  dpi=80)
    img = pixels(path)
    assert img.shape[:2] == (round(4.5 * 80), round(12 * 80))          # figsize 12 x 4.5
    nonwhite = np.any(img < 0.95, axis=2)
    assert nonwhite.mean() > 0.15                                       # not blank
    colours = np.unique((img[nonwhite] * 32).astype(int), axis=0)
    assert len(colours) > 50
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert np.count_nonzero((r > 0.6) & (b < 0.4) & (g < 0.5)) > 500   # reddish (positive)
    assert np.count_nonzero((b > 0.6) & (r < 0.4) & (g < 0.6)) > 500   # bluish (negative)


def test_unsigned_field_uses_a_sequential_map(tmp_path):
    pts = shapes.sphere(20_000, 1.0, seed=2)["points"]
    img = pixels(render(pts, np.abs(pts[:, 2]), tmp_path / "unsigned.png",
                        field="surface_variation", unit="", dpi=60))
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert np.count_nonzero((r > 0.6) & (b < 0.4) & (g < 0.5)) < 50     # no diverging reds


def test_large_cloud_is_subsampled_and_all_nan_still_renders(tmp_path):
    pts = np.random.default_rng(3).normal(size=(300_000, 3))
    p = render(pts, pts[:, 0], tmp_path / "big.png", max_points=50_000, dpi=50)
    assert pixels(p).shape[0] == round(4.5 * 50)
    p = render(pts[:1000], np.full(1000, np.nan), tmp_path / "nan.png", dpi=50)
    img = pixels(p)
    assert np.any(img < 0.95, axis=2).mean() > 0.01                     # grey points drawn


def test_bad_input():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        render(np.zeros((5, 2)), np.zeros(5), "/tmp/x.png")
    with pytest.raises(ValueError):
        render(np.zeros((5, 3)), np.zeros(4), "/tmp/x.png")
