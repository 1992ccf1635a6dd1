"""Covariance features in tiles (clcurv.tiles.features, `clcurv features --tile-size`): the
output of a tiled run is the in-memory run's, bit for bit (same fields, same order, every
point once in input order), for one radius, several radii and the optimal neighbourhood;
the memory budget decides and grows with the fields; what a tiled run cannot do is refused
before any output is written."""
import os

import numpy as np
import pytest

import clcurv
from clcurv.tiles import features as tiled_features
from clcurv.api.features import canonical_names
from clcurv.tiles.planning import TILE_BYTES_PER_POINT
from tests.hostile import run_cli
from tests.test_tiled import AUTZEN, _assert_same, _dims, _scene, write_scene

laspy = pytest.importorskip("laspy")

RADII = [0.6, 1.0, 1.4]             # the scene's terrain: ~11 to ~60 neighbours


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiled_features")
    pts, kind = _scene(20_000, seed=5)
    return d, write_scene(pts, kind, d / "scene.laz"), pts


CASES = {
    "one radius, all features": dict(radius=1.0, features="all"),
    "three radii": dict(radius=RADII),
    "optimal among three": dict(radius=RADII, optimal=True,
                                features=["planarity", "linearity", "normals"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_tiles_equal_the_in_memory_features_bit_for_bit(scene, case):
    d, path, pts = scene
    kw = CASES[case]
    tag = case.replace(" ", "_").replace(",", "")
    mem = clcurv.features_file(path, d / f"mem_{tag}.laz", memory="64GiB", **kw)
    til = clcurv.features_file(path, d / f"til_{tag}.laz", tile=6.0, **kw)
    assert not mem["tiled"] and til["tiled"] and til["tiles"] >= 25
    assert til["halo"] == 1 and til["fields"] == mem["fields"]
    _assert_same(d / f"mem_{tag}.laz", d / f"til_{tag}.laz")
    dims = _dims(d / f"til_{tag}.laz")[1]
    las = laspy.read(str(d / f"til_{tag}.laz"))
    assert np.array_equal(np.column_stack([las.x, las.y, las.z]), pts)   # input order
    status = [k for k in dims if k.startswith("feature_status")]
    assert status and all((dims[k] == 0).mean() > 0.9 for k in status)
    # the values are the API's on the whole cloud (not only the file job's)
    api = clcurv.features(pts, **kw)
    first = api[0] if isinstance(api, list) else api
    suffix = "_r0.6" if isinstance(api, list) else ""
    np.testing.assert_array_equal(dims[f"planarity{suffix}"], first["planarity"])
    np.testing.assert_array_equal(dims[f"number_of_neighbors{suffix}"], first.count)


def test_the_budget_decides_and_grows_with_the_fields(scene, tmp_path):
    """A budget too small for the whole cloud in memory tiles without a tile size, with the
    same output; a tile's bytes per point grow with the fields and radii written."""
    d, path, _ = scene
    one = tiled_features.FeatureParams((1.0,), ("planarity",), 0, False, None, "float")
    many = tiled_features.FeatureParams(tuple(RADII), canonical_names("all"), 0, False, None,
                                        "float")
    assert one.bytes_per_point() == TILE_BYTES_PER_POINT + 16 * 3 + 64
    # 17 features, normals 3 wide, count and status: 21 columns a radius
    assert many.columns() == 3 * 21
    assert many.bytes_per_point() == TILE_BYTES_PER_POINT + 16 * 63 + 3 * 64
    a = clcurv.features_file(path, tmp_path / "mem.laz", RADII, memory="64GiB")
    # 20,700 points: in memory ~27 MB with these 63 columns (90 + 1,008 + 192 bytes a
    # point, planning.fits_memory); a tile takes 2,100 bytes a point: 20 MiB takes tiles
    b = clcurv.features_file(path, tmp_path / "small.laz", RADII, memory="20MiB")
    assert not a["tiled"] and b["tiled"]
    _assert_same(tmp_path / "mem.laz", tmp_path / "small.laz")


def test_cli_tiles_equal_the_cli_in_memory(scene, tmp_path):
    _, path, _ = scene
    a, b = tmp_path / "mem.laz", tmp_path / "til.laz"
    r1 = run_cli("features", path, "-o", a, "--radius", "0.6,1", "-q")
    r2 = run_cli("features", path, "-o", b, "--radius", "0.6,1", "-q", "--tile-size", "6")
    assert r1.code == 0 and r2.code == 0, (r1.stderr, r2.stderr)
    assert "tile(s)" in r2.stdout and "tile(s)" not in r1.stdout
    _assert_same(a, b)
    # what a tiled run cannot do: refused before any output, exit code 2
    for args, msg in (
            (("--k", "30", "--tile-size", "6"), "whole cloud in memory"),
            (("--radius", "1", "--tile-size", "0.5"), "smaller than the halo"),
            (("--radius", "1", "--tile-size", "6", "--workers", "0"), "--workers")):
        out = tmp_path / "x.laz"
        r = run_cli("features", path, "-o", out, "-q", *args)
        assert r.code == 2 and msg in r.stderr, (args, r.stderr)
        assert not out.exists()
    r = run_cli("features", path, "-o", tmp_path / "x.xyz", "--radius", "1", "-q",
                "--tile-size", "6")
    assert r.code == 2 and "a tiled run writes" in r.stderr
    assert not (tmp_path / "x.xyz").exists()


def test_progress_bar_only_for_a_tiled_run(scene, tmp_path):
    """Without -q a tiled run draws a bar of its tiles on stderr, up to all of them; a run
    in memory draws none (it drew an empty "tiles: 0tile" bar before)."""
    _, path, _ = scene
    mem = run_cli("features", path, "-o", tmp_path / "mem.laz", "--radius", "1")
    til = run_cli("features", path, "-o", tmp_path / "til.laz", "--radius", "1",
                  "--tile-size", "6")
    assert mem.code == 0 and til.code == 0, (mem.stderr, til.stderr)
    assert "tiles:" not in mem.stderr and "tile/s" not in mem.stderr, mem.stderr
    n = int(til.stdout.split(" in ")[-1].split(" tile")[0])
    assert n > 1 and f"tiles: 100%" in til.stderr and f"{n}/{n}" in til.stderr, til.stderr


def test_dask_workers_equal_one_process(scene, tmp_path):
    pytest.importorskip("distributed")
    _, path, _ = scene
    one, two = tmp_path / "one.laz", tmp_path / "two.laz"
    clcurv.features_file(path, one, RADII, tile=6.0)
    s = clcurv.features_file(path, two, RADII, tile=6.0, workers=2)
    assert s["tiled"] and s["tiles"] >= 25
    assert one.read_bytes() == two.read_bytes()


def test_a_real_aerial_scan_tiles_exactly(tmp_path):
    """The Autzen LAZ (110k points, feet), features at 4, 6 and 9 ft in 100-ft tiles: the
    in-memory output, bit for bit."""
    if not os.path.exists(AUTZEN):
        pytest.skip("the shared Autzen LAZ is not present")
    a, b = tmp_path / "mem.laz", tmp_path / "til.laz"
    clcurv.features_file(AUTZEN, a, [4.0, 6.0, 9.0], "all", memory="64GiB")
    s = clcurv.features_file(AUTZEN, b, [4.0, 6.0, 9.0], "all", tile=100.0)
    assert s["tiles"] >= 50
    _assert_same(a, b)


def test_a_catalog_of_files_equals_one_file(scene, tmp_path):
    """Two LAS/LAZ files side by side run as one cloud (`clcurv features a.las b.laz -o
    dir/`): each output holds its file's points with the features, bit for bit those of
    the single file made of the two in the same order."""
    d, path, pts = scene
    full = laspy.read(str(path))
    west = pts[:, 0] < np.median(pts[:, 0])
    order = np.argsort(~west, kind="stable")
    whole = tmp_path / "whole.las"
    las = laspy.LasData(full.header)
    las.points = full.points[order]
    las.write(str(whole))
    parts = []
    for name, keep in (("west.las", west), ("east.laz", ~west)):
        sub = laspy.LasData(full.header)
        sub.points = full.points[keep]
        sub.write(str(tmp_path / name))
        parts.append(tmp_path / name)
    outdir = tmp_path / "out"
    outdir.mkdir()
    clcurv.features_file(whole, tmp_path / "ref.las", RADII, memory="64GiB")
    r = run_cli("features", *parts, "-o", outdir, "--radius", ",".join(map(str, RADII)),
                "--tile-size", "6", "-q")
    assert r.code == 0, r.stderr
    ref = _dims(tmp_path / "ref.las")[1]
    start = 0
    for p in parts:
        out = _dims(outdir / p.name)[1]
        m = len(out["X"])
        for name, a in out.items():
            assert np.array_equal(a, ref[name][start:start + m], equal_nan=True), (p, name)
        start += m
    assert start == len(pts)
