"""The device buffer pool (clcurv/runtime/memory.py): buffers a call frees are reused by the next
call, so no kernel may rely on fresh (zeroed) memory; release_memory gives them back."""
import os
import subprocess
import sys

import numpy as np
import pytest

import clcurv
from clcurv.runtime import memory
from clcurv.data.shapes import sphere

from conftest import bumpy_surface


def held_bytes(device):
    """Bytes the pool of ``device`` holds unused (0 for a simulator)."""
    pool = memory._pool(device)
    return 0 if pool is None else int(pool.managed_bytes - pool.active_bytes)


def test_results_do_not_depend_on_reused_memory(device, monkeypatch):
    """Every operator gives the same bits on fresh buffers and on buffers full of NaN
    (memory.FILL: pads, records, the grid and the orientation graph included)."""
    pts = bumpy_surface(20000, 3)
    r = 0.06
    memory.release_memory(device)
    first = {m: clcurv.curvature(pts, r, method=m, device=device) for m in ("variation", "mls2")}
    nrm = clcurv.normals(pts, r, device=device)
    feats = clcurv.features(pts, [r / 2, r], device=device)
    space = clcurv.curvature(pts, r, method="mls2", scale_space=2, device=device)
    knn = clcurv.features(pts, "knn:20", device=device)
    assert held_bytes(device) > 0
    monkeypatch.setattr(memory, "FILL", np.nan)
    for m, res in first.items():
        again = clcurv.curvature(pts, r, method=m, device=device)
        ref = res.arrays()
        for name, arr in again.arrays().items():
            np.testing.assert_array_equal(arr, ref[name], err_msg=f"{m} {name}")
    np.testing.assert_array_equal(clcurv.normals(pts, r, device=device), nrm)
    for a, b in zip(clcurv.features(pts, [r / 2, r], device=device), feats):
        for name in a.values:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    again = clcurv.curvature(pts, r, method="mls2", scale_space=2, device=device)
    for name, arr in again.arrays().items():
        np.testing.assert_array_equal(arr, space.arrays()[name], err_msg=f"scale space {name}")
    again = clcurv.features(pts, "knn:20", device=device)
    for name in knn.values:
        np.testing.assert_array_equal(again[name], knn[name], err_msg=f"knn {name}")


def test_release_memory_frees_what_the_pool_holds(device):
    pts = sphere(30000, 1.0)["points"]
    clcurv.curvature(pts, 0.05, method="variation", device=device)
    held = held_bytes(device)
    # the call's buffers (coordinates 5 x 4 bytes, records 64 bytes per point, ...) came back
    assert held >= 80 * len(pts)
    assert clcurv.release_memory(device) >= held
    assert held_bytes(device) == 0


def test_pool_off_holds_nothing():
    """CLCURV_POOL=0: every buffer is freed when its call ends."""
    code = ("import clcurv, clcurv.runtime.memory as m;"
            "p = clcurv.shapes.sphere(20000, 1.0)['points'];"
            "clcurv.curvature(p, 0.05, method='variation');"
            "pool = m._pool(clcurv.get_device());"
            "print(0 if pool is None else pool.managed_bytes - pool.active_bytes)")
    env = dict(os.environ, CLCURV_POOL="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.split()[-1]) == 0


@pytest.mark.parametrize("scale_space", [0, 2])
def test_tiled_runs_hold_no_memory_between_tiles(tmp_path, scale_space):
    """A tiled run's memory budget sizes tiles as if every buffer were freed: the pool lets
    a tile's buffers go when the tile is done (clcurv.tiles.engine.compute_tile, tiled_scale)."""
    dev = clcurv.get_device()
    pts = clcurv.shapes.aerial_scene(30000, extent=(30.0, 30.0), seed=1)["points"]
    src = tmp_path / "scene.npy"
    np.save(src, pts)
    clcurv.release_memory(dev)
    out = clcurv.curvature_file(src, tmp_path / "out.npz", 1.0, method="variation",
                                scale_space=scale_space, tile=8.0, memory="64GiB")
    assert out["tiled"] and out["tiles"] >= 9
    assert held_bytes(dev) == 0
