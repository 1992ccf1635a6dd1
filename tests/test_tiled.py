"""The tiled engine (clcurv.tiles.engine): tiles equal the in-memory run bit for bit, every point is
written once in input order, a halo too small shows, bad input fails cleanly, and an
interrupted run resumes."""
import os

import numpy as np
import pytest

import clcurv
from tests.hostile import assert_same_las, las_dims
from clcurv.tiles import engine as tiled
from clcurv.jobs import tiled_job
from clcurv.tiles import planning
from clcurv.io.common import CorruptFileError
from conftest import data_path

laspy = pytest.importorskip("laspy")

R = 1.0                    # radius = cell size: tile edges at whole metres from the corner
SCALE = 2.0 ** -7          # LAS scale: coordinates are exact binary fractions


def _scene(n=30_000, seed=3):
    """An aerial scene (terrain, gable roofs, walls, trees) whose extent does not align
    with the tiles, plus points exactly on tile edges and corners and duplicate points."""
    s = clcurv.shapes.aerial_scene(n, extent=(47.3, 38.9), seed=seed)
    p = np.round(s["points"] / SCALE) * SCALE           # on the LAS grid
    lo = p.min(axis=0)
    rng = np.random.default_rng(seed)
    # edges and corners of 8 m tiles: x or y (or both) at lo + 8 k exactly
    k = rng.integers(0, 5, size=(400, 2)) * 8.0
    edge = p[rng.integers(0, len(p), 400)].copy()
    edge[:200, 0] = lo[0] + k[:200, 0]
    edge[200:300, 1] = lo[1] + k[200:300, 1]
    edge[300:, :2] = lo[:2] + k[300:]
    dup = p[rng.integers(0, len(p), 300)]                # duplicates
    pts = np.concatenate([p, edge, dup])
    kind = np.concatenate([s["kind"], np.full(700, 2, np.uint8)])
    perm = rng.permutation(len(pts))
    return pts[perm], kind[perm]


def write_scene(pts, kind, path):
    """A LAS/LAZ file of the scene's points (on the LAS grid of SCALE) and classes."""
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [SCALE] * 3
    hdr.offsets = np.floor(pts.min(axis=0))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.classification = kind
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiled")
    pts, kind = _scene()
    paths = {}
    for ext in ("las", "laz"):
        paths[ext] = write_scene(pts, kind, d / f"scene.{ext}")
    back = laspy.read(str(paths["las"]))
    assert np.array_equal(np.column_stack([back.x, back.y, back.z]), pts)   # exact grid
    return d, paths, pts


_dims, _assert_same = las_dims, assert_same_las


@pytest.mark.parametrize("method", clcurv.METHODS)
def test_tiles_equal_the_in_memory_run_bit_for_bit(scene, method):
    d, paths, pts = scene
    mem = clcurv.curvature_file(paths["laz"], d / f"mem_{method}.laz", R, method=method,
                                memory="64GiB")
    til = clcurv.curvature_file(paths["laz"], d / f"til_{method}.laz", R, method=method,
                                tile=8.0, memory="64GiB")
    assert not mem["tiled"] and til["tiled"] and til["tiles"] >= 20
    assert til["halo"] == tiled.halo_cells(method)
    _assert_same(d / f"mem_{method}.laz", d / f"til_{method}.laz")
    las, dims = _dims(d / f"til_{method}.laz")
    # every point once, in input order, its record as read (X, Y, Z, classification)
    assert np.array_equal(np.column_stack([las.x, las.y, las.z]), pts)
    assert (dims["status"] == 0).mean() > 0.9


@pytest.mark.parametrize("method", clcurv.METHODS)
def test_scale_space_tiles_equal_the_in_memory_run_bit_for_bit(scene, method):
    """Three MLS1 steps in lock step over tiles (clcurv.tiles.scale), then the operator on
    the smoothed cloud: the same bits as the in-memory pipeline, re-binnings included."""
    d, paths, pts = scene
    a, b = d / f"ss_mem_{method}.laz", d / f"ss_til_{method}.laz"
    clcurv.curvature_file(paths["laz"], a, R, method=method, scale_space=3, memory="64GiB")
    til = clcurv.curvature_file(paths["laz"], b, R, method=method, scale_space=3, tile=12.0,
                                memory="64GiB")
    assert til["tiled"] and til["tiles"] >= 9
    _assert_same(a, b)


def _dome(n=30_000, seed=4):
    """A smooth dome on the LAS grid: z = 50 - |xy - c|^2 / 16 over 40 m x 40 m (curvature
    radius ~8 m). Each MLS1 step at r = 1 moves its points by ~0.03 r, so the drift from
    the last binning crosses the bound (0.1 r) after the 4th of 5 steps only."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 40, (n, 2)) + [1000.3, 2000.7]
    z = 50 - ((xy - [1020.3, 2020.7]) ** 2).sum(axis=1) / 16
    return np.round(np.column_stack([xy, z]) / SCALE) * SCALE


def test_the_scale_space_case_re_bins(scene, tmp_path, monkeypatch):
    """The tiled scale space (clcurv.tiles.scale) re-bins after exactly the steps the
    in-memory one (clcurv.ops.smoothing) does, and after every step its smoothed cloud (p + d
    from its state files) is the in-memory iterate, bit for bit. On the dome some steps
    re-bin and some do not; the scene's three steps (test_scale_space_tiles_equal_...)
    re-bin at least once, so that test goes through a re-binning too."""
    from clcurv.ops import smoothing
    from clcurv.tiles import scale as tiled_scale
    _, stats = clcurv.scale_space(scene[2], R, 3, return_stats=True)
    assert stats["rebins"] >= 1
    pts = _dome()
    path = write_scene(pts, np.full(len(pts), 2, np.uint8), tmp_path / "dome.las")
    done, mem_rebins = [0], []

    class Spy(smoothing.DeviceState):      # a new binning after step done[0] - 1
        def __init__(self, *a, **kw):
            if done[0]:
                mem_rebins.append(done[0] - 1)
            super().__init__(*a, **kw)

        def step(self, *a, **kw):
            done[0] += 1
            return super().step(*a, **kw)

    real = smoothing.DeviceState
    monkeypatch.setattr(smoothing, "DeviceState", Spy)
    iterates, stats = clcurv.scale_space(pts, R, 5, return_iterates=True, return_stats=True)
    monkeypatch.setattr(smoothing, "DeviceState", real)    # (the tiles make their own)
    assert done[0] == 5 and len(mem_rebins) == stats["rebins"]
    assert 1 <= len(mem_rebins) < 4                          # some steps re-bin, some not

    til_rebins, smoothed = [], []
    apply = tiled_scale._apply

    def spy(ws, buckets, state, step, rebin, **kw):
        out = apply(ws, buckets, state, step, rebin, **kw)
        if rebin:
            til_rebins.append(step)
        cur = np.full(pts.shape, np.nan)
        for i in range(buckets.shape[0]):
            for j in range(buckets.shape[1]):
                if buckets.counts[i, j]:
                    rec = buckets.read(i, j)
                    st = np.fromfile(state.path(i, j), state.dtype)
                    cur[rec["id"]] = rec["p"] + st["d"].astype(np.float64)
        smoothed.append(cur)
        return out

    monkeypatch.setattr(tiled_scale, "_apply", spy)
    til = clcurv.curvature_file(path, tmp_path / "dome_out.las", R, method="variation",
                                scale_space=5, tile=12.0, memory="64GiB")
    assert til["tiled"] and til["tiles"] >= 9
    assert til_rebins == mem_rebins
    assert len(smoothed) == 5
    for k, cur in enumerate(smoothed):
        np.testing.assert_array_equal(cur, iterates[k + 1], err_msg=f"step {k}")


def test_density_weights_and_las_output_tile_exactly(scene):
    d, paths, _ = scene
    for name, tile in (("mem", None), ("til", 6.0)):
        clcurv.curvature_file(paths["las"], d / f"{name}_dens.las", R, method="2dcov2",
                              weights="density", tile=tile, memory="64GiB")
    assert tiled.halo_cells("2dcov2", "density") == 4
    _assert_same(d / "mem_dens.las", d / "til_dens.las")


def test_npy_with_normals_to_npz(tmp_path):
    s = clcurv.shapes.torus(40_000, 2.0, 0.7, seed=5)
    arr = np.column_stack([s["points"], s["normals"]])     # 6 columns of unit normals
    src = tmp_path / "torus.npy"
    np.save(src, arr)
    out = {}
    for name, tile in (("mem", None), ("til", 1.0)):
        summary = clcurv.curvature_file(src, tmp_path / f"{name}.npz", 0.15, method="3dcov",
                                        tile=tile, memory="64GiB")
        out[name] = np.load(tmp_path / f"{name}.npz")
    assert summary["halo"] == 1          # normals from the file: no PCA pass to feed
    assert sorted(out["mem"].files) == sorted(out["til"].files)
    for k in out["mem"].files:
        assert np.array_equal(out["mem"][k], out["til"][k], equal_nan=True), k
    assert np.array_equal(out["til"]["points"], s["points"])
    # and the file's (outward) normals orient the result
    assert np.all(np.einsum("ij,ij->i", out["til"]["normals"], s["normals"]) > 0)


def test_a_halo_too_small_changes_the_results(scene, monkeypatch):
    """Negative control: with the halo forced to 0 cells (a distance halo of nothing), the
    tiles' border points lose neighbours and their values change."""
    d, paths, _ = scene
    clcurv.curvature_file(paths["laz"], d / "ref_var.laz", R, method="variation",
                          memory="64GiB")
    monkeypatch.setattr(tiled, "halo_cells", lambda *a, **k: 0)
    clcurv.curvature_file(paths["laz"], d / "bad_var.laz", R, method="variation", tile=8.0,
                          memory="64GiB")
    _, a = _dims(d / "ref_var.laz")
    _, b = _dims(d / "bad_var.laz")
    changed = np.mean(a["neighbours"] != b["neighbours"])
    assert changed > 0.05, changed


@pytest.mark.parametrize("shape", ["torus", "two_spheres"])
def test_mst_orientation_across_tiles(tmp_path, shape):
    """Hoppe's MST in tiles (clcurv.tiles.orient): a closed torus (or two disjoint spheres)
    cut into many tiles comes out outward, and agrees with the in-memory MST."""
    s = (clcurv.shapes.torus(60_000, 2.0, 0.7, seed=5) if shape == "torus"
         else clcurv.shapes.two_spheres(60_000, 1.0, 1.0, seed=5))
    src = tmp_path / "c.npy"
    np.save(src, s["points"])                  # no normals: orient='auto' is MST
    r = 0.12 if shape == "torus" else 0.08
    out = {}
    for name, tile in (("mem", None), ("til", 0.9)):
        summary = clcurv.curvature_file(src, tmp_path / f"{name}.npz", r, method="mls2",
                                        tile=tile, memory="64GiB")
        out[name] = np.load(tmp_path / f"{name}.npz")
    assert summary["tiles"] >= 8
    na, nb = out["mem"]["normals"], out["til"]["normals"]
    ok = np.isfinite(na).all(axis=1) & np.isfinite(nb).all(axis=1)
    assert ok.mean() > 0.99
    outward = np.einsum("ij,ij->i", nb[ok], s["normals"][ok]) > 0
    agree = np.einsum("ij,ij->i", na[ok], nb[ok]) > 0
    assert outward.mean() >= 0.999, outward.mean()
    assert agree.mean() >= 0.999, agree.mean()
    # where the orientations agree the signed curvatures are the in-memory ones
    h = np.isfinite(out["mem"]["mean_curvature"])
    assert np.allclose(out["til"]["mean_curvature"][h], out["mem"]["mean_curvature"][h],
                       rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", ["2dcov2", "3dcov"])
def test_mst_normals_of_a_tile_are_aligned_as_in_memory(tmp_path, method, monkeypatch):
    """2dcov2 and 3dcov align clcurv's own normals in every ball (the user's are used as
    given): a tile's MST normals are clcurv's own, so the tiled values are the in-memory
    ones even where a tile's propagation leaves mixed signs (here: a third of the signs
    flipped after each tile's MST)."""
    from clcurv.tiles import orient as tiled_orient
    s = clcurv.shapes.torus(30_000, 2.0, 0.7, noise=0.01, seed=6)
    src = tmp_path / "c.npy"
    np.save(src, s["points"])
    real = tiled_orient.orient_tile

    def mixed(cloud, *a, **kw):
        nl, node = real(cloud, *a, **kw)
        flip = np.random.default_rng(len(nl)).random(len(nl)) < 1 / 3
        return np.where(flip[:, None], -nl, nl), node
    monkeypatch.setattr(tiled_orient, "orient_tile", mixed)
    out = {}
    for name, tile in (("mem", None), ("til", 0.9)):
        clcurv.curvature_file(src, tmp_path / f"{name}.npz", 0.15, method=method,
                              orient="mst", tile=tile, memory="64GiB")
        out[name] = np.load(tmp_path / f"{name}.npz")
    for f in ("k1", "k2"):
        a, b = out["mem"][f], out["til"][f]
        ok = np.isfinite(a)
        assert ok.mean() > 0.99 and np.array_equal(ok, np.isfinite(b))
        assert np.allclose(b[ok], a[ok], rtol=1e-4, atol=1e-4), f


def test_bad_input_fails_cleanly(scene, tmp_path):
    _, paths, _ = scene
    out = tmp_path / "out.laz"
    out.write_bytes(b"previous result")
    # a truncated LAZ (a partial download)
    cut = tmp_path / "cut.laz"
    data = paths["laz"].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(CorruptFileError):
        clcurv.curvature_file(cut, out, R, method="variation", tile=8.0)
    # a tile smaller than its halo
    with pytest.raises(tiled.TilingError, match="smaller than the halo"):
        clcurv.curvature_file(paths["laz"], out, R, method="3dcov", tile=1.5)
    # a budget too small for one tile
    with pytest.raises(tiled.TilingError, match="too small for one tile"):
        clcurv.curvature_file(paths["laz"], out, R, method="variation", memory="200KB")
    assert out.read_bytes() == b"previous result"        # never destroyed
    # no partial output, no temporary, no workspace left behind
    assert sorted(os.listdir(tmp_path)) == ["cut.laz", "out.laz"]


def test_an_interrupted_run_resumes(scene, tmp_path):
    _, paths, _ = scene
    ref = tmp_path / "ref.laz"
    clcurv.curvature_file(paths["laz"], ref, R, method="mls1", memory="64GiB")
    out = tmp_path / "out.laz"

    def stop_after_5(done, total, points):
        if done == 5:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        clcurv.curvature_file(paths["laz"], out, R, method="mls1", tile=8.0,
                              progress=stop_after_5)
    assert not out.exists()
    ws = tiled.workspace(out, None)
    assert len(os.listdir(ws / "tiles")) == 5
    summary = clcurv.curvature_file(paths["laz"], out, R, method="mls1", tile=8.0)
    assert summary["skipped"] == 5
    assert not ws.exists()                                 # cleaned at the end
    _assert_same(ref, out)


def test_memory_budget_decides(tmp_path):
    assert planning.parse_memory("2GiB") == 2 << 30
    assert planning.parse_memory("500MB") == 500_000_000
    assert planning.parse_memory(4096) == 4096
    for bad in ("-1G", "lots", 0):
        with pytest.raises(ValueError):
            planning.parse_memory(bad)
    assert planning.fits_memory(1000, 10 ** 9)
    assert not planning.fits_memory(10 ** 9, 1 << 30)


def test_cli_tiles_equal_the_cli_in_memory(scene, tmp_path):
    from tests.hostile import run_cli
    _, paths, _ = scene
    a, b = tmp_path / "mem.laz", tmp_path / "til.laz"
    r1 = run_cli("compute", paths["laz"], "-o", a, "--radius", "1", "-q")
    r2 = run_cli("compute", paths["laz"], "-o", b, "--radius", "1", "-q", "--tile-size", "8")
    assert r1.code == 0 and r2.code == 0, (r1.stderr, r2.stderr)
    assert "tile(s)" in r2.stdout
    # the summary lines of an in-memory run: its percentiles too, exactly here (30,700
    # points: the tiles' sample of 2^15 is every point), and the fields written
    def lines(text, out):
        keep = [ln for ln in text.splitlines()
                if ln.startswith(("method ", "mean neighbours", "device ", "  "))]
        wrote = [ln for ln in text.splitlines() if ln.startswith("wrote ")]
        assert len(wrote) == 1, text
        return keep + [wrote[0].replace(str(out), "OUT").split(";")[0]]
    got, want = lines(r2.stdout, b), lines(r1.stdout, a)
    assert got == want, (got, want)
    assert sum(ln.startswith("  ") for ln in got) == 4        # H, K, k1, k2
    assert "wrote OUT: nx ny nz, mean_curvature" in got[-1]
    _assert_same(a, b)
    bad = run_cli("compute", paths["laz"], "-o", tmp_path / "x.laz", "--radius", "1", "-q",
                  "--tile-size", "0.5")
    assert bad.code == 2 and "smaller than the halo" in bad.stderr
    assert not (tmp_path / "x.laz").exists()


def test_dask_workers_equal_one_process_and_survive_a_killed_worker(scene, tmp_path):
    """Two LocalCluster workers give the single-process tiled output byte for byte; one of
    them killed while tiles run, the run still completes with the same output."""
    distributed = pytest.importorskip("distributed")
    _, paths, _ = scene
    one, two, killed = (tmp_path / f"{k}.laz" for k in ("one", "two", "killed"))
    clcurv.curvature_file(paths["laz"], one, R, method="mls2", tile=8.0)
    summary = clcurv.curvature_file(paths["laz"], two, R, method="mls2", tile=8.0, workers=2)
    assert summary["tiled"] and summary["tiles"] >= 20
    assert one.read_bytes() == two.read_bytes()

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
    client = distributed.Client(cluster)
    try:
        import signal
        victim = min(client.run(os.getpid).values())        # a worker process
        state = {"killed": False}

        def kill_once(done, total, points):
            if done >= 3 and not state["killed"]:
                state["killed"] = True
                os.kill(victim, signal.SIGKILL)             # its nanny starts another
        clcurv.curvature_file(paths["laz"], killed, R, method="mls2", tile=8.0,
                              client=client, progress=kill_once)
    finally:
        client.close()
        cluster.close()
    assert state["killed"]
    assert one.read_bytes() == killed.read_bytes()


@pytest.mark.parametrize("workers", [None, 2])
def test_a_file_read_in_parts_by_the_workers_equals_the_in_memory_run(scene, tmp_path,
                                                                      monkeypatch, workers):
    """Pass (1) reads a LAS/LAZ file in parts (ranges of points: PART_POINTS made 7,001
    here, so parts start inside a LAZ chunk), each filed in the buckets by its own task
    (on two Dask workers: the client decodes no point), and pass (1b) splits each part
    apart: the output is the in-memory run's, byte for byte."""
    if workers:
        pytest.importorskip("distributed")
    from clcurv.io import stream
    d, paths, pts = scene
    monkeypatch.setattr(stream, "PART_POINTS", 7_001)
    assert len(stream.parts_of(stream.open_source(paths["laz"]))) == 5
    mem = d / "mem_mls2.laz"
    if not mem.exists():
        clcurv.curvature_file(paths["laz"], mem, R, method="mls2", memory="64GiB")
    out = tmp_path / "parts.laz"
    summary = clcurv.curvature_file(paths["laz"], out, R, method="mls2", tile=8.0,
                                    workers=workers)
    assert summary["tiled"] and summary["points"] == len(pts)
    _assert_same(mem, out)


def test_a_laz_written_in_pieces_is_the_in_memory_file_byte_for_byte(tmp_path, monkeypatch):
    """One LAZ output of a tiled run is written in pieces (windows of whole LAZ chunks,
    each compressed by its own task: clcurv.tiles.writing.write_pieces) and joined by the
    client: 110,000 points in three pieces of 50,000, 50,000 and 10,000 points give the
    in-memory writer's file byte for byte (header, extra-bytes statistics, chunk table)."""
    from clcurv.tiles import writing
    s = clcurv.shapes.aerial_scene(110_000, extent=(40.0, 30.0), seed=8)
    pts = np.round(s["points"] / SCALE) * SCALE
    src = write_scene(pts, s["kind"], tmp_path / "big.laz")
    monkeypatch.setattr(writing, "PIECE_POINTS", 50_000)
    assert writing.piece_windows(len(pts)) == [(0, 50_000), (50_000, 100_000),
                                               (100_000, 110_000)]
    mem, til = tmp_path / "mem.laz", tmp_path / "til.laz"
    clcurv.curvature_file(src, mem, R, method="mls1", memory="64GiB")
    summary = clcurv.curvature_file(src, til, R, method="mls1", tile=12.0)
    assert summary["tiled"] and summary["tiles"] >= 4
    assert mem.read_bytes() == til.read_bytes()
    assert not (tmp_path / "til.laz.clcurv").exists() and sorted(
        p.name for p in tmp_path.iterdir()) == ["big.laz", "mem.laz", "til.laz"]


def test_which_file_jobs_tile(scene):
    from clcurv.jobs.job import Job, wants_tiles
    _, paths, _ = scene
    small = Job(paths["laz"], "o.laz", radius=1.0)
    assert not wants_tiles(small)                           # 30k points fit the default budget
    assert wants_tiles(Job(paths["laz"], "o.laz", radius=1.0, memory="4MiB"))
    assert wants_tiles(Job(paths["laz"], "o.laz", radius=1.0, tile_size=8.0))
    assert not wants_tiles(Job(paths["laz"], "o.ply", radius=1.0, memory="4MiB",
                               positions="projected"))   # only in memory, and fits
    assert planning.budget_of("auto") <= planning.AUTO_CAP


def test_auto_radius_in_tiles_estimates_the_in_memory_one(scene):
    """radius 'auto' of a tiled run samples 16 regions (exact k-NN distances inside
    them); it estimates the whole-cloud sample's median to a few per cent."""
    from clcurv.io import stream
    from clcurv.jobs.job import auto_radius
    _, paths, pts = scene
    r_tiled = tiled_job.auto_radius_tiled(stream.open_source(paths["laz"]))
    r_mem = auto_radius(pts)
    assert abs(r_tiled / r_mem - 1) < 0.05, (r_tiled, r_mem)


def test_a_catalog_of_files_equals_one_file(scene, tmp_path):
    """Four LAS/LAZ files side by side (a catalog, lidR's term) run as one cloud: each
    output holds its file's points, bit for bit those of the single file made of the four
    in the same order (tiles cross the files' borders, halos reach into the neighbours)."""
    _, paths, pts = scene
    full = laspy.read(str(paths["las"]))
    mid = np.median(pts[:, :2], axis=0)
    quad = (pts[:, 0] >= mid[0]).astype(int) * 2 + (pts[:, 1] >= mid[1])
    order = np.argsort(quad, kind="stable")
    whole = tmp_path / "whole.las"
    las = laspy.LasData(full.header)
    las.points = full.points[order]
    las.write(str(whole))
    parts = []
    for q in range(4):
        p = tmp_path / f"part{q}.{'laz' if q % 2 else 'las'}"
        sub = laspy.LasData(full.header)
        sub.points = full.points[quad == q]
        sub.write(str(p))
        parts.append(p)
    outdir = tmp_path / "out"
    outdir.mkdir()
    ref = tmp_path / "ref.las"
    clcurv.curvature_file(whole, ref, R, method="mls2", memory="64GiB")
    summary = clcurv.curvature_file(parts, outdir, R, method="mls2", tile=8.0)
    assert summary["tiled"] and summary["points"] == len(pts)
    _, r = _dims(ref)
    start = 0
    for p in parts:
        _, o = _dims(outdir / p.name)
        m = len(o["X"])
        for name, a in o.items():
            assert np.array_equal(a, r[name][start:start + m], equal_nan=True), (p, name)
        start += m
    assert start == len(pts)
    with pytest.raises(tiled.TilingError, match="replace the input"):
        clcurv.curvature_file(parts, tmp_path, R, method="mls2", tile=8.0)


def _cut_catalog(full, pts, folder):
    """Seven files cut from the scene's LAS ``full``: a 3 x 2 grid at unaligned x and y
    (cut at coordinates of points, which then lie exactly on a file border and go to the
    file on their right), 300 points of file 0 repeated in file 4 (overlapping flight
    lines), and an empty file among them; and the single file of the same points in the
    same order."""
    xs = np.sort(pts[:, 0])
    cx = [xs[int(len(xs) * q)] for q in (0.31, 0.67)]
    cy = np.sort(pts[:, 1])[int(len(pts) * 0.45)]
    col = (pts[:, 0] >= cx[0]).astype(int) + (pts[:, 0] >= cx[1])
    cell = col * 2 + (pts[:, 1] >= cy)
    on_border = np.isin(pts[:, 0], cx) | (pts[:, 1] == cy)
    assert on_border.sum() >= 2
    rows = [np.flatnonzero(cell == c) for c in range(6)]
    rows[4] = np.concatenate([rows[4], rows[0][:300]])
    rows.insert(3, np.zeros(0, int))
    paths = []
    for k, r in enumerate(rows):
        p = folder / f"f{k}.{'laz' if k % 2 else 'las'}"
        sub = laspy.LasData(full.header)
        sub.points = full.points[r]
        sub.write(str(p))
        paths.append(p)
    whole = folder / "whole.laz"
    las = laspy.LasData(full.header)
    las.points = full.points[np.concatenate(rows)]
    las.write(str(whole))
    return paths, whole, [len(r) for r in rows]


@pytest.mark.parametrize("workers", [None, 2])
def test_a_catalog_with_borders_duplicates_and_an_empty_file_equals_its_single_file(
        scene, tmp_path, workers):
    """A catalog of 7 files (unaligned extents, points on the borders, duplicates across
    files, one empty file) in tiles: each file read and each output written by its own
    task (on two Dask workers: the client reads and writes no point), every output its
    slice of the in-memory run of the single file they were cut from, bit for bit."""
    if workers:
        pytest.importorskip("distributed")
    _, paths, pts = scene
    full = laspy.read(str(paths["las"]))
    (tmp_path / "in").mkdir()
    files, whole, counts = _cut_catalog(full, pts, tmp_path / "in")
    ref = tmp_path / "ref.laz"
    clcurv.curvature_file(whole, ref, R, method="mls2", memory="64GiB")
    out = tmp_path / "out"
    out.mkdir()
    summary = clcurv.curvature_file(files, out, R, method="mls2", tile=8.0, workers=workers)
    assert summary["tiled"] and summary["points"] == sum(counts)
    assert sum(summary["status"]) == sum(counts)
    _, r = _dims(ref)
    start = 0
    for p, m in zip(files, counts):
        _, o = _dims(out / p.name)
        assert len(o["X"]) == m
        for name, a in o.items():
            assert np.array_equal(a, r[name][start:start + m], equal_nan=True), (p, name)
        start += m
    assert sorted(q.name for q in out.iterdir()) == sorted([p.name for p in files]
                                                          + ["index.vpc"])


def test_binary_ply_in_and_out_byte_for_byte(tmp_path):
    s = clcurv.shapes.torus(30_000, 2.0, 0.7, seed=7)
    src = tmp_path / "t.ply"
    clcurv.io.write(src, s["points"], normals=s["normals"])        # binary PLY
    for name, tile in (("mem", None), ("til", 1.0)):
        clcurv.curvature_file(src, tmp_path / f"{name}.ply", 0.15, method="2dcov2",
                              tile=tile, memory="64GiB")
    assert (tmp_path / "mem.ply").read_bytes() == (tmp_path / "til.ply").read_bytes()
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                         "property float y\nproperty float z\nend_header\n0 0 0\n")
    with pytest.raises(clcurv.io.ReadError, match="binary PLY"):
        clcurv.curvature_file(ascii_ply, tmp_path / "o.ply", 0.1, tile=1.0)


AUTZEN = str(data_path("laspy_autzen_trim.laz"))      # shipped in tests/data too


@pytest.mark.skipif(not os.path.exists(AUTZEN), reason="the Autzen LAZ is not present")
def test_a_real_aerial_scan_tiles_exactly(tmp_path):
    """The Autzen LAZ (110k points, feet, radius 6 for ~30 neighbours), two scale-space
    steps then MLS2 in 100-ft tiles: the in-memory output, bit for bit."""
    a, b = tmp_path / "mem.laz", tmp_path / "til.laz"
    clcurv.curvature_file(AUTZEN, a, 6.0, method="mls2", scale_space=2, memory="64GiB")
    s = clcurv.curvature_file(AUTZEN, b, 6.0, method="mls2", scale_space=2, tile=100.0)
    assert s["tiles"] >= 50
    _assert_same(a, b)


@pytest.mark.parametrize("method", ["mls2", "mls1"])
def test_quantised_tiles_equal_the_in_memory_run_byte_for_byte(scene, method):
    """quantize=True: the tiled LAZ is the in-memory LAZ byte for byte (header, extra-bytes
    descriptors and their statistics included), every field within half its step of the
    float32 run's, the principal directions written on request."""
    d, paths, pts = scene
    kw = dict(method=method, fields=["all"], memory="64GiB")
    plain = clcurv.curvature_file(paths["laz"], d / f"q0_{method}.laz", R, **kw)
    mem = clcurv.curvature_file(paths["laz"], d / f"qm_{method}.laz", R, quantize=True, **kw)
    til = clcurv.curvature_file(paths["laz"], d / f"qt_{method}.laz", R, quantize=True,
                                tile=8.0, **kw)
    assert not plain["tiled"] and not mem["tiled"] and til["tiled"]
    assert (d / f"qm_{method}.laz").read_bytes() == (d / f"qt_{method}.laz").read_bytes()
    _, q = _dims(d / f"qt_{method}.laz")
    _, f = _dims(d / f"q0_{method}.laz")
    assert list(q) == list(f)
    steps = {"nx": 1e-4, "mean_curvature": 1e-4 / R, "surface_variation": 1e-5,
             "gaussian_curvature": 1e-4 / R**2, "k1": 1e-4 / R, "dir2_z": 1e-4}
    checked = 0
    for name, step in steps.items():
        if name not in f:
            continue
        a, b = np.asarray(f[name], np.float64), np.asarray(q[name], np.float64)
        ok = np.isfinite(a)
        # float32 rounding of the plain run's value beside the half step
        assert np.abs(a[ok] - b[ok]).max() <= step / 2 + 1e-7 * np.abs(a[ok]).max(), name
        checked += 1
    assert checked == (5 if method == "mls2" else 3)


def test_a_flipped_tile_flips_the_fields_chosen_alone(tmp_path):
    """MST orientation in tiles flips whole components afterwards: (k1, k2) -> (-k2, -k1)
    and dir1 <-> dir2. ``fields=["k1", "dir1"]`` (or the default set, without the
    directions) stores their partners too, so the values written are those of the run
    with every field."""
    s = clcurv.shapes.torus(20_000, 2.0, 0.7, seed=5)
    src = tmp_path / "c.npy"
    np.save(src, s["points"])                  # no normals: orient='auto' is MST
    out = {}
    for name, fields in (("all", ["all"]), ("some", ["k1", "dir1"])):
        clcurv.curvature_file(src, tmp_path / f"{name}.npz", 0.2, method="mls2", tile=0.9,
                              memory="64GiB", fields=fields)
        out[name] = np.load(tmp_path / f"{name}.npz")
    assert sorted(out["some"].files) == ["dir1_x", "dir1_y", "dir1_z", "k1", "points"]
    for k in out["some"].files:
        assert np.array_equal(out["some"][k], out["all"][k], equal_nan=True), k
