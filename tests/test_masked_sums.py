"""The two forms of the PCA sums (kernels/pca.h, MASKED_SUMS; the host's choice,
clcurv.runtime.program.masked_sums): each sum updated only in the mask's lanes (s = m ? s + d : s,
one masked instruction each on AVX-512) or the offsets zeroed outside the mask and added
to every lane (s += m ? d : 0). A lane outside the mask keeps s in the first, adds +0 to
it in the second, so every sum, and so every output, is the same bit for bit (the products
fused alike in both: fma() where the device has one, clcurv.runtime.program.fused_sums): checked by
forcing each form on every device, in float and double, for every operator and call that
sums through pca.h (the moments, MLS2, the scale space, the features at one radius, at
three radii in one walk and at the k-NN radius)."""
import dataclasses

import numpy as np
import pytest

import clcurv
import clcurv.grid.cloud
from clcurv.runtime.program import fused_sums, masked_sums


def _torus():
    return clcurv.shapes.torus(20000, 1.0, 0.3, noise=1e-3, seed=5)["points"]


def _calls(pts, device, precision):
    """name -> a call returning a dict of arrays"""
    kw = {"device": device, "precision": precision}

    def fields(res, names):
        return {n: np.asarray(getattr(res, n)) for n in names}

    def feats(res):
        res = res if isinstance(res, list) else [res]
        return {f"{i}:{n}": v for i, f in enumerate(res)
                for n, v in dict(f.values, count=f.count).items()}

    return {
        "variation": lambda: fields(clcurv.curvature(pts, 0.12, method="variation",
                                                     orient=None, **kw),
                                    ("variation", "normals", "eigenvalues", "count")),
        "mls2": lambda: fields(clcurv.curvature(pts, 0.12, method="mls2", orient=None, **kw),
                               ("mean", "k1", "k2", "dir1", "normals")),
        "scale_space": lambda: {"p": clcurv.scale_space(pts, 0.06, 2, **kw)},
        "features_radii": lambda: feats(clcurv.features(pts, [0.05, 0.085, 0.12], "all",
                                                        **kw)),
        "features_knn": lambda: feats(clcurv.features(pts, k=20, features="all", **kw)),
    }


@pytest.mark.parametrize("precision", ["float", "double"])
def test_both_forms_give_the_same_bits(device, monkeypatch, precision):
    if precision == "double" and not device.info.fp64:
        pytest.skip("device without fp64")
    pts = _torus()
    real = clcurv.grid.cloud.precision_defines
    out = {}
    for form in (0, 1):
        monkeypatch.setattr(clcurv.grid.cloud, "precision_defines",
                            lambda dev, prec, f=form: dict(real(dev, prec), MASKED_SUMS=f))
        out[form] = {name: call() for name, call in _calls(pts, device, precision).items()}
    for name in out[0]:
        a, b = out[0][name], out[1][name]
        assert a.keys() == b.keys()
        for f in a:
            assert np.array_equal(a[f], b[f], equal_nan=True), (name, f)
            assert np.isfinite(a[f]).mean() > 0.9, (name, f)     # the outputs mean something


def test_choice():
    """Masked sums on CPU devices with 512-bit vectors only."""
    base = clcurv.runtime.device.DeviceInfo(0, "d", "p", "v", "cpu", "1", "1.2", True, 1, 1, 1, 1, 1)
    assert masked_sums(dataclasses.replace(base, native_float_width=16)) == 1
    assert masked_sums(dataclasses.replace(base, native_float_width=8)) == 0
    assert masked_sums(dataclasses.replace(base, kind="gpu", native_float_width=16)) == 0
    assert masked_sums(base) == 0


def test_fused_products_follow_the_device_fp_config():
    """pca.h's products are fma(a, b, c) where the precision's CL_FP_FMA is set, so that
    the two forms fuse alike (Intel's runtime, left to contract a * b + c itself, fused
    them differently in float64); a * b + c elsewhere."""
    base = clcurv.runtime.device.DeviceInfo(0, "d", "p", "v", "cpu", "1", "1.2", True, 1, 1, 1, 1, 1)
    fma = dataclasses.replace(base, fma_double=True)
    assert fused_sums(fma, "double") == 1 and fused_sums(fma, "float") == 0
    assert fused_sums(base, "double") == 0
    assert fused_sums(dataclasses.replace(base, fma_float=True), "float") == 1
