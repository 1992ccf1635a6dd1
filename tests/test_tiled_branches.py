"""Branches of the tiled engine that no other test runs (issue 48, item 4), end to end on
small clouds: a tiled run with ``viewpoint=``, ``precision="double"`` and MLS2's
``kernel="gaussian"`` equals the in-memory run bit for bit (as clcurv.tiles.engine promises); an
interrupted features_file resumes to the fresh run's output; on Dask, the scale space's
steps (step_tile) give the one-process output, and a tile task that fails once is retried
(clcurv.tiles.workers.RETRIES) with the same output.

Each option is also checked to change the result (a run that ignored it would not pass)."""
import os
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.tiles import engine as tiled, scale as tiled_scale

R = 1.0
TILE = 8.0                  # about 20 tiles of the 40 m x 31 m scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """An aerial scene of ~8,000 points on a 1/128 grid, as NPY."""
    d = tmp_path_factory.mktemp("branches")
    s = clcurv.shapes.aerial_scene(8000, extent=(40.3, 30.9), seed=7)
    pts = np.round(s["points"] * 128) / 128
    np.save(d / "scene.npy", pts)
    return d / "scene.npy", pts


def _load(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _same(a, b):
    """The NPZ outputs ``a`` and ``b`` hold the same arrays, bit for bit."""
    x, y = _load(a), _load(b)
    assert sorted(x) == sorted(y)
    diff = [k for k in x if not np.array_equal(x[k], y[k], equal_nan=True)]
    assert diff == [], f"the outputs differ in {diff}"


def _differ(a, b, name):
    x, y = _load(a)[name], _load(b)[name]
    assert not np.array_equal(x, y, equal_nan=True), f"{name}: the option changed nothing"


def _mem_and_tiles(src, tmp_path, tag, **kw):
    """The in-memory and the tiled output of curvature_file with ``kw``."""
    mem, til = tmp_path / f"mem_{tag}.npz", tmp_path / f"til_{tag}.npz"
    a = clcurv.curvature_file(src, mem, R, memory="64GiB", **kw)
    b = clcurv.curvature_file(src, til, R, tile=TILE, **kw)
    assert not a["tiled"] and b["tiled"] and b["tiles"] >= 12
    return mem, til


# --------------------------------------------------------------------------- options


def test_a_viewpoint_tiles_exactly(scene, tmp_path):
    """viewpoint= below the ground: every normal of the tiled run faces it (down, where
    'up' would point them up) and the output is the in-memory one bit for bit."""
    src, pts = scene
    vp = (pts[:, 0].mean(), pts[:, 1].mean(), pts[:, 2].min() - 50.0)
    mem, til = _mem_and_tiles(src, tmp_path, "vp", method="mls2", viewpoint=vp)
    _same(mem, til)
    n = _load(til)["normals"]
    ok = np.isfinite(n).all(axis=1)
    assert ok.mean() > 0.9
    assert np.all(np.einsum("ij,ij->i", n[ok], np.asarray(vp) - pts[ok]) > 0)
    clcurv.curvature_file(src, tmp_path / "up.npz", R, method="mls2", orient="up",
                          tile=TILE)
    _differ(til, tmp_path / "up.npz", "mean_curvature")


def test_double_precision_tiles_exactly(scene, tmp_path):
    """precision='double' in tiles: the in-memory double run bit for bit, and not the
    float run's values."""
    info = clcurv.get_device().info
    if not info.fp64:
        pytest.skip(f"the default device ({info.name}) has no fp64: precision='double' "
                    "cannot run on it")
    src, _ = scene
    mem, til = _mem_and_tiles(src, tmp_path, "f64", method="mls2", orient="up",
                              precision="double")
    _same(mem, til)
    clcurv.curvature_file(src, tmp_path / "f32.npz", R, method="mls2", orient="up",
                          tile=TILE)
    for name in ("mean_curvature", "k1", "normals"):
        _differ(til, tmp_path / "f32.npz", name)


@pytest.mark.parametrize("h", [None, 0.4])
def test_the_gaussian_kernel_of_mls2_tiles_exactly(scene, tmp_path, h):
    """MLS2 with kernel='gaussian' (its default width, and h = 0.4) in tiles: the
    in-memory run bit for bit, and not the ball kernel's values."""
    src, _ = scene
    tag = f"g{h}"
    mem, til = _mem_and_tiles(src, tmp_path, tag, method="mls2", orient="up",
                              kernel="gaussian", h=h)
    _same(mem, til)
    clcurv.curvature_file(src, tmp_path / "ball.npz", R, method="mls2", orient="up",
                          tile=TILE)
    for name in ("mean_curvature", "gaussian_curvature"):
        _differ(til, tmp_path / "ball.npz", name)


# --------------------------------------------------------------------------- resume


def test_an_interrupted_features_run_resumes_to_the_fresh_output(scene, tmp_path):
    """features_file interrupted after 3 tiles (KeyboardInterrupt from progress): the
    workspace keeps the 3 tiles, the same call skips them and writes the fresh run's
    output bit for bit, then removes the workspace."""
    src, _ = scene
    kw = dict(radius=[0.6, 1.0], features=["planarity", "linearity", "normals"], tile=6.0)
    fresh = clcurv.features_file(src, tmp_path / "fresh.npz", **kw)
    assert fresh["tiled"] and fresh["tiles"] > 3
    out = tmp_path / "out.npz"

    def stop(done, total, points):
        if done == 3:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        clcurv.features_file(src, out, progress=stop, **kw)
    assert not out.exists()
    ws = tiled.workspace(out, None)
    assert len(list((ws / "tiles").glob("*.npy"))) == 3
    again = clcurv.features_file(src, out, **kw)
    assert again["skipped"] == 3 and again["tiles"] == fresh["tiles"]
    assert not ws.exists()
    _same(tmp_path / "fresh.npz", out)


# --------------------------------------------------------------------------- Dask

_REAL_COMPUTE = tiled.compute_tile
_REAL_STEP = tiled_scale.step_tile


def _fail_once(task, name):
    """RuntimeError the first time a task named ``name`` runs (a marker file beside the
    workspace, made atomically, says it did): in any worker process."""
    folder = Path(task.ws).parent / "planted"
    folder.mkdir(exist_ok=True)
    try:
        os.close(os.open(folder / name, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return
    raise RuntimeError(f"planted failure of {name}")


def flaky_compute_tile(task, device=None):
    """clcurv.tiles.engine.compute_tile, failing once per tile (the workers import it here)."""
    _fail_once(task, f"tile-{task.t}")
    return _REAL_COMPUTE(task, device)


def flaky_step_tile(task):
    """clcurv.tiles.scale.step_tile, failing once per tile of each step."""
    _fail_once(task, f"step{task.step}-{task.t}")
    return _REAL_STEP(task)


SCALE = dict(method="mls1", orient="up", scale_space=2, tile=TILE)


@pytest.fixture(scope="module")
def one_process(scene, tmp_path_factory):
    """The one-process tiled run of SCALE (the scale space's steps, then MLS1)."""
    src, _ = scene
    dst = tmp_path_factory.mktemp("one") / "one.npz"
    summary = clcurv.curvature_file(src, dst, R, **SCALE)
    assert summary["tiled"] and summary["tiles"] >= 12
    return dst


def test_scale_space_steps_on_dask_equal_one_process(scene, one_process, tmp_path,
                                                     monkeypatch):
    """Two LocalCluster workers run the steps (step_tile) and the operator's tiles: the
    one-process output bit for bit."""
    pytest.importorskip("distributed")
    monkeypatch.setenv("CLCURV_FORCE_WORKERS", "1")
    src, _ = scene
    dst = tmp_path / "two.npz"
    summary = clcurv.curvature_file(src, dst, R, workers=2, **SCALE)
    assert summary["tiled"]
    _same(one_process, dst)


def test_a_tile_task_that_fails_once_is_retried_on_dask(scene, one_process, tmp_path,
                                                       monkeypatch):
    """Every step task and every tile task raises the first time it runs (on a worker):
    cluster.map_tiles's retries run each again, and the output is the one-process run's.
    (tests/test_tiled_units.py shows the failure reaching the caller with RETRIES = 0.)"""
    pytest.importorskip("distributed")
    from clcurv.tiles import workers as cluster
    assert cluster.RETRIES >= 1
    monkeypatch.setenv("CLCURV_FORCE_WORKERS", "1")
    monkeypatch.setattr(tiled, "compute_tile", flaky_compute_tile)
    monkeypatch.setattr(tiled_scale, "step_tile", flaky_step_tile)
    src, _ = scene
    (tmp_path / "run").mkdir()
    dst = tmp_path / "run" / "retried.npz"
    summary = clcurv.curvature_file(src, dst, R, workers=2, **SCALE)
    _same(one_process, dst)
    planted = sorted(p.name for p in (tmp_path / "run" / "planted").iterdir())
    tiles = [p for p in planted if p.startswith("tile-")]
    assert len(tiles) == summary["tiles"]                  # each tile failed, then ran
    for step in range(SCALE["scale_space"]):
        assert any(p.startswith(f"step{step}-") for p in planted), planted
