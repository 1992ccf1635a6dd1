"""Row pruning of the neighbour walk (kernels/neighbors.h, ROW_PRUNE; the host turns it on
for radii below clcurv.ops.driver.PRUNE_BELOW cells and for per-point radii): the rows of the
27-cell block whose slab lies beyond the ball's radius in y and z are skipped, and of a row
whose first (last) cell lies beyond it in x as well the whole chunks of that first cell
(the last cell) are left out, from the rows' middle cells (grid.cl, DeviceCloud.with_middles).
No lane so skipped can pass the walk's strict ball test (row_gap2 and x_gaps2 keep a slack
of a few ulps of the cell), and the chunks walked keep their lanes, so every sum, and so
every output, is the same bit for bit as the full walk of all 9 rows: checked with
pruning forced on and off for every operator kernel, both weightings, a radius equal to the
cell and one well below it (where most rows are pruned), float and double, and for the
features kernel at three radii in one walk."""
import importlib

import numpy as np
import pytest

import clcurv
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import run_kernel
from clcurv.ops.registry import OPERATORS

features_mod = importlib.import_module("clcurv.ops.features")


def _torus():
    t = clcurv.shapes.torus(20000, 1.0, 0.3, noise=1e-3, seed=3)
    return t["points"], t["normals"]


def _same(a, b, what):
    for f in a:
        assert np.array_equal(a[f], b[f], equal_nan=True), (what, f)


@pytest.mark.parametrize("precision", ["float", "double"])
def test_operators_identical_with_and_without_pruning(device, precision):
    if precision == "double" and not device.info.fp64:
        pytest.skip("device without fp64")
    pts, nrm = _torus()
    cloud = DeviceCloud(pts, 0.12, device=device, precision=precision)
    for r in (0.12, 0.05):
        for kernel in {op.kernel.name: op.kernel for op in OPERATORS.values()}.values():
            kw = {"normals": nrm} if kernel.reads_normals else {}
            for w in ("uniform", "density"):
                full = run_kernel(kernel, cloud, r, weights=w, defines={"ROW_PRUNE": 0}, **kw)
                pruned = run_kernel(kernel, cloud, r, weights=w, defines={"ROW_PRUNE": 1},
                                    **kw)
                _same(full, pruned, (kernel.name, r, w))
                assert (pruned["status"] == 0).mean() > 0.9


def test_features_identical_with_and_without_pruning(device, monkeypatch):
    pts, _ = _torus()
    cloud = DeviceCloud(pts, 0.12, device=device)
    radii = [0.05, 0.085, 0.12]
    orig = features_mod.program_defines
    runs = []
    for prune in (1, 0):
        monkeypatch.setattr(features_mod, "program_defines",
                            lambda *a, p=prune, **k: dict(orig(*a, **k), ROW_PRUNE=p))
        runs.append(clcurv.features(cloud, radii, "all"))
    pruned, full = runs
    for p, f in zip(pruned, full):
        assert np.array_equal(p.count, f.count)
        for name in p.names:
            assert np.array_equal(p[name], f[name], equal_nan=True), name
