"""The tiled run's workspace never lies (clcurv.tiles.workspace, clcurv.tiles.engine): it deletes only
what it made, resumes only the same inputs and options, detects every kind of corrupt file
and recomputes, survives a kill at any stage, and refuses a second run on one output.

Every outcome is checked against a fresh run of the same command: the output files must be
equal byte for byte (LAS, NPZ) or the run refused with a clear message."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.tiles import engine as tiled
from clcurv.tiles import workspace as wsp
from clcurv.io import OutputPathError

laspy = pytest.importorskip("laspy")

R = 1.0
TILE = 8.0                   # about 30 tiles of the 40 m x 30 m scene
ROOT = Path(__file__).resolve().parent.parent


def _scene(n=8000, seed=5):
    s = clcurv.shapes.aerial_scene(n, extent=(40.3, 30.9), seed=seed)
    return np.round(s["points"] * 128) / 128


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("ws")
    pts = _scene()
    np.save(d / "scene.npy", pts)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales, hdr.offsets = [2.0 ** -7] * 3, np.floor(pts.min(axis=0))
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.write(str(d / "scene.laz"))
    return d, pts


def _run(src, dst, **kw):
    kw.setdefault("tile", TILE)
    kw.setdefault("method", "mls1")
    return clcurv.curvature_file(src, dst, R, **kw)


def _same(a, b):
    """Equal outputs: LAS/LAZ point records and header fields, or NPZ arrays, bit for bit."""
    a, b = Path(a), Path(b)
    if a.suffix == ".npz":
        with np.load(a) as x, np.load(b) as y:
            assert sorted(x.files) == sorted(y.files)
            for k in x.files:
                assert np.array_equal(x[k], y[k], equal_nan=True), k
        return
    x, y = laspy.read(str(a)), laspy.read(str(b))
    assert list(x.point_format.dimension_names) == list(y.point_format.dimension_names)
    for name in x.point_format.dimension_names:
        assert np.array_equal(np.asarray(x[name]), np.asarray(y[name]), equal_nan=True), name


@pytest.fixture(scope="module")
def fresh(inputs, tmp_path_factory):
    """Fresh tiled runs, by (input suffix, method, fields): the reference outputs."""
    d, _ = inputs
    out = tmp_path_factory.mktemp("fresh")
    cache = {}

    def get(ext, method="mls1", fields=None, orient="auto", src=None):
        key = (ext, method, tuple(fields or ()), orient, src)
        if key not in cache:
            dst = out / f"ref{len(cache)}.{'laz' if ext == 'laz' else 'npz'}"
            _run(src or d / f"scene.{ext}", dst, method=method, fields=fields, orient=orient)
            cache[key] = dst
        return cache[key]
    return get


def _interrupt(src, dst, after=5, outputs=None, **kw):
    """Run until ``after`` tiles are done, then interrupt (KeyboardInterrupt); the
    workspace left (``outputs``: a catalog's output files)."""
    def stop(done, total, points):
        if done == after:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        _run(src, dst, progress=stop, **kw)
    ws = tiled.workspace(outputs or dst, kw.get("workdir"))
    assert (ws / wsp.TAG).exists() and len(_results(ws)) == after
    return ws


# --------------------------------------------------------------------------- data loss

def test_a_workdir_keeps_everything_the_run_did_not_make(inputs, fresh, tmp_path):
    """workdir= is a folder to work in, not one to own: the input in it, a user's files and
    folders survive an interrupted run, its resume and a failed run; nothing of the run's
    is left at the end."""
    d, _ = inputs
    D = tmp_path / "work"
    D.mkdir()
    src = D / "scene.laz"
    src.write_bytes((d / "scene.laz").read_bytes())
    (D / "notes.txt").write_text("mine")
    (D / "sub").mkdir()
    (D / "sub" / "keep.bin").write_bytes(b"\0" * 10)
    before = sorted(p.relative_to(D) for p in D.rglob("*"))
    out = tmp_path / "out.laz"
    _interrupt(src, out, workdir=D)
    summary = _run(src, out, workdir=D)
    assert summary["skipped"] == 5
    _same(out, fresh("laz"))
    assert sorted(p.relative_to(D) for p in D.rglob("*")) == before
    with pytest.raises(ValueError):                         # bad options: fails, cleans
        _run(src, tmp_path / "bad.laz", workdir=D, fields=["no_such_field"])
    assert sorted(p.relative_to(D) for p in D.rglob("*")) == before
    assert (D / "notes.txt").read_text() == "mine"


def test_a_folder_of_the_workspace_name_that_clcurv_did_not_make_is_refused(inputs, tmp_path):
    d, _ = inputs
    out = tmp_path / "out.laz"
    ws = tiled.workspace(out, None)
    ws.mkdir()
    (ws / "precious.txt").write_text("x")
    with pytest.raises(wsp.WorkspaceError, match="did not make"):
        _run(d / "scene.laz", out)
    assert (ws / "precious.txt").read_text() == "x" and not out.exists()


def test_the_api_refuses_to_write_a_mesh_over_itself(tmp_path):
    """As the CLI: curvature_file(mesh.ply, mesh.ply) would drop the faces."""
    plyfile = pytest.importorskip("plyfile")
    pts = _scene(2000)
    v = np.array([tuple(p) for p in pts], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    f = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    mesh = tmp_path / "mesh.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"),
                     plyfile.PlyElement.describe(f, "face")]).write(str(mesh))
    before = mesh.read_bytes()
    for kw in ({"tile": TILE}, {}):
        with pytest.raises(OutputPathError, match="faces"):
            clcurv.curvature_file(mesh, mesh, R, method="mls1", **kw)
    assert mesh.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["mesh.ply"]


# --------------------------------------------------------------------------- resume keys

CHANGES = {
    "fields": ({"fields": ["mean_curvature", "status"]},
               {"fields": ["neighbours", "status"]}),
    "method": ({"method": "mls1"}, {"method": "variation"}),
    "orient": ({"orient": "auto"}, {"orient": None}),
}


@pytest.mark.parametrize("what", sorted(CHANGES))
def test_a_resume_with_other_options_equals_a_fresh_run(inputs, fresh, tmp_path, what):
    d, _ = inputs
    first, second = CHANGES[what]
    out = tmp_path / "out.npz"
    _interrupt(d / "scene.npy", out, **first)
    summary = _run(d / "scene.npy", out, **second)
    assert summary["skipped"] == 0
    ref = fresh("npy", method=second.get("method", "mls1"), fields=second.get("fields"),
                orient=second.get("orient", "auto"))
    _same(out, ref)
    with np.load(out) as z:
        assert sorted(z.files) == sorted(np.load(ref).files)


def test_an_input_replaced_with_the_same_size_and_mtime_is_not_reused(inputs, fresh,
                                                                       tmp_path):
    """The resume key hashes the content: a file of the same size and mtime whose points
    moved (a re-export) is computed afresh."""
    d, pts = inputs
    src = tmp_path / "in.npy"
    np.save(src, pts)
    out = tmp_path / "out.npz"
    _interrupt(src, out)
    st = os.stat(src)
    other = pts.copy()
    other[:, 2] = other[::-1, 2]                       # same size, other values
    np.save(src, other)
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(src).st_size == st.st_size and os.stat(src).st_mtime_ns == st.st_mtime_ns
    summary = _run(src, out)
    assert summary["skipped"] == 0
    ref_src = tmp_path / "other.npy"
    np.save(ref_src, other)
    _same(out, fresh("npy", src=ref_src))


def test_sampled_hash_of_a_large_input_sees_a_changed_block(tmp_path, monkeypatch):
    """Above WHOLE_HASH_BYTES the hash samples the file: a block changed inside a sample
    changes it (the documented limit: a change between samples does not)."""
    monkeypatch.setattr(wsp, "WHOLE_HASH_BYTES", 1 << 16)
    p = tmp_path / "big.bin"
    data = bytearray(os.urandom(8 << 20))
    p.write_bytes(data)
    h = wsp.file_hash(p)
    mid = int(len(data) * 100.5 / wsp.SAMPLES)
    data[mid] ^= 0xFF
    p.write_bytes(data)
    assert wsp.file_hash(p) != h
    data[mid] ^= 0xFF
    p.write_bytes(data)
    assert wsp.file_hash(p) == h


# --------------------------------------------------------------------------- corrupt files

def _corrupt(path, how, rng):
    data = bytearray(path.read_bytes())
    if how == "delete":
        path.unlink()
    elif how == "truncate":
        path.write_bytes(bytes(data[: max(len(data) - 1 - int(rng.integers(0, 200)), 0)]))
    else:                                              # flip one byte past any header
        i = int(rng.integers(len(data) // 2, len(data)))
        data[i] ^= 0x5A
        path.write_bytes(bytes(data))


def _results(ws):
    """The tiles' result files (not the MST's .halo.npy and .nodes.npy)."""
    return sorted(p for p in (ws / "tiles").glob("*.npy") if p.stem.isdigit())


def _todo_inputs(ws):
    """The input files of the tiles not yet computed (read by the resumed run)."""
    done = {p.stem for p in _results(ws)}
    return sorted(p for p in (ws / "tiles_in").glob("p*/*.bin") if p.stem not in done)


def _buckets_and_split_again(ws):
    (ws / "tiles_in.json").unlink()            # the split runs again: it reads the buckets
    return sorted((ws / "buckets").glob("p*/*.bin"))


KINDS = {
    "manifest": lambda ws: [ws / "manifest.json"],
    "bucket": _buckets_and_split_again,
    "tile input": _todo_inputs,
    "tile inputs' sums": lambda ws: [ws / "tiles_in.json"],
    "tile result": _results,
}


@pytest.mark.parametrize("how", ["flip", "truncate", "delete"])
@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_corrupt_workspace_file_is_detected_and_recomputed(inputs, fresh, tmp_path, kind,
                                                            how):
    """After an interruption, one random file of each kind is damaged (a flipped byte, a
    truncation, a deletion): the resumed run's output equals a fresh run's."""
    d, _ = inputs
    rng = np.random.default_rng(abs(hash((kind, how))) % 2**32)
    out = tmp_path / "out.laz"
    ws = _interrupt(d / "scene.laz", out)
    files = [p for p in KINDS[kind](ws) if p.stat().st_size > 0]
    _corrupt(files[int(rng.integers(len(files)))], how, rng)
    lines = []
    _run(d / "scene.laz", out, out=lines.append)
    _same(out, fresh("laz"))
    assert not ws.exists()
    if kind in ("bucket", "tile input") or kind == "tile result" and how != "delete":
        assert any("fail" in s or "records where" in s or "missing" in s
                   for s in lines), lines


@pytest.mark.parametrize("suffix", [".halo.npy", ".nodes.npy", ".npy"])
def test_corrupt_mst_records_are_recomputed(inputs, fresh, tmp_path, suffix):
    """MST orientation across tiles stores three files per tile; each is checked."""
    d, _ = inputs
    out = tmp_path / "out.npz"
    ws = _interrupt(d / "scene.npy", out, orient="mst")
    victim = sorted((ws / "tiles").glob(f"*[0-9]{suffix}"))[2]
    _corrupt(victim, "flip", np.random.default_rng(1))
    _run(d / "scene.npy", out, orient="mst")
    _same(out, fresh("npy", orient="mst"))


def test_window_ids_out_of_range_are_a_corrupt_workspace(tmp_path):
    from clcurv.tiles.results import Windows
    dt = np.dtype([("id", "<i8"), ("v", "<f8")])
    w = Windows(tmp_path, 10, dt)
    rec = np.zeros(10, dt)
    rec["id"] = np.arange(10)
    rec["id"][3] = -7
    rec.tofile(w.path(0))
    with pytest.raises(wsp.CorruptWorkspace, match="1 missing, 0 more than once, 1 out"):
        w.window(0)


# --------------------------------------------------------------------------- kills

_KILLER = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, {root!r})
    import clcurv
    from clcurv.tiles import buckets, engine as tiled, results as tile_results, workspace
    stage, k = sys.argv[1], int(sys.argv[2])
    calls = [0]

    def tick():
        calls[0] += 1
        if calls[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)

    def wrap_open(folder):
        def opener(path, mode="r", *a, **kw):
            if folder in str(path) and "a" in mode:
                tick()
            return open(path, mode, *a, **kw)
        return opener
    if stage == "bucketing":
        buckets.READ_CHUNK = 400             # many appends (the same bucket files)
        buckets.open = wrap_open("buckets")
    elif stage == "splitting":
        buckets.open = wrap_open("tiles_in")
    elif stage == "tiles":
        save = workspace.save_sealed
        def sealed(path, arr):
            tick()
            save(path, arr)
        workspace.save_sealed = sealed
    elif stage == "merging":                 # the tiles' records gathered by window
        tile_results.open = wrap_open("/out/")
    elif stage == "writing":
        rows = tile_results.Windows.rows
        def rows_then_kill(self, a, b):
            out = rows(self, a, b)
            tick()
            return out
        tile_results.Windows.rows = rows_then_kill
    clcurv.curvature_file(sys.argv[3], sys.argv[4], 1.0, method="mls1", tile=8.0)
    print("finished")
""")


@pytest.mark.parametrize("stage", ["bucketing", "splitting", "tiles", "merging", "writing"])
def test_a_run_killed_at_a_random_point_of_each_stage_resumes_to_a_fresh_output(
        inputs, fresh, tmp_path, stage):
    """SIGKILL (no clean-up at all) at a random write of each stage, then the same
    command: the output equals a fresh run's, and nothing is left behind."""
    d, _ = inputs
    script = tmp_path / "killer.py"
    script.write_text(_KILLER.format(root=str(ROOT)))
    rng = np.random.default_rng(abs(hash(stage)) % 2**32)
    k = {"bucketing": 1 + int(rng.integers(0, 20)), "splitting": 1 + int(rng.integers(0, 20)),
         "tiles": 1 + int(rng.integers(0, 20)), "merging": 1 + int(rng.integers(0, 20)),
         "writing": 1}[stage]
    out = tmp_path / "out.laz"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    r = subprocess.run([sys.executable, str(script), stage, str(k), str(d / "scene.laz"),
                        str(out)], capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == -signal.SIGKILL, (r.returncode, r.stdout, r.stderr[-2000:])
    assert not out.exists()
    _run(d / "scene.laz", out)
    _same(out, fresh("laz"))
    assert sorted(os.listdir(tmp_path)) == ["killer.py", "out.laz"]


# --------------------------------------------------------------------------- two runs

def test_a_second_run_on_the_same_output_is_refused_clearly(inputs, fresh, tmp_path):
    from tests.hostile import run_cli
    d, _ = inputs
    out = tmp_path / "out.laz"
    out.write_bytes(b"previous")
    with wsp.claim(tiled.workspace(out, None), out):           # a run holds it
        r = run_cli("compute", d / "scene.laz", "-o", out, "--radius", "1", "--method",
                    "mls1", "--tile-size", "8", "-q")
        assert r.code == 3, r.stderr
        assert "in use by another clcurv run" in r.stderr and str(out) in r.stderr
        assert f"pid {os.getpid()}" in r.stderr and "Traceback" not in r.stderr
        other = tmp_path / "elsewhere"
        other.mkdir()                             # another workspace: the output's lock
        with pytest.raises(wsp.WorkspaceError, match="in use"):
            _run(d / "scene.laz", out, workdir=other)
    assert out.read_bytes() == b"previous"
    _run(d / "scene.laz", out)                     # released: runs
    _same(out, fresh("laz"))


def test_two_concurrent_runs_give_one_correct_output(inputs, fresh, tmp_path):
    """Two processes started together on one output: every run that finishes leaves the
    fresh output, and any that does not says the output is in use."""
    d, _ = inputs
    out = tmp_path / "out.laz"
    code = (f"import sys; sys.path.insert(0, {str(ROOT)!r}); import clcurv; "
            f"clcurv.curvature_file({str(d / 'scene.laz')!r}, {str(out)!r}, 1.0, "
            "method='mls1', tile=8.0)")
    procs = [subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE,
                              text=True) for _ in range(2)]
    results = [(p.wait(timeout=600), p.stderr.read()) for p in procs]
    assert any(c == 0 for c, _ in results), results
    for c, err in results:
        assert c == 0 or "in use by another clcurv run" in err, err[-2000:]
    _same(out, fresh("laz"))
    assert sorted(os.listdir(tmp_path)) == ["out.laz"]


def test_two_catalogs_into_one_folder_have_their_own_workspaces(inputs, tmp_path):
    d, pts = inputs
    srcs = []
    for name, sel in (("a", pts[:4000]), ("b", pts[4000:]), ("c", pts[::2]), ("e", pts[1::2])):
        np.save(tmp_path / f"{name}.npy", sel)
        srcs.append(tmp_path / f"{name}.npy")
    folder = tmp_path / "out"
    folder.mkdir()
    one, two = [str(p) for p in srcs[:2]], [str(p) for p in srcs[2:]]
    ws_one = tiled.workspace([folder / "a.npz", folder / "b.npz"], None)
    ws_two = tiled.workspace([folder / "c.npz", folder / "e.npz"], None)
    assert ws_one != ws_two
    _interrupt(one, folder, after=3, outputs=[folder / "a.npz", folder / "b.npz"])
    clcurv.curvature_file(two, folder, R, method="mls1", tile=TILE)   # not poisoned
    summary = clcurv.curvature_file(one, folder, R, method="mls1", tile=TILE)
    assert summary["skipped"] == 3
    assert sorted(os.listdir(folder)) == ["a.npz", "b.npz", "c.npz", "e.npz"]


# --------------------------------------------------------------------------- front door

def test_options_fields_and_device_are_refused_before_any_point_is_read(inputs, tmp_path,
                                                                       monkeypatch):
    """Every check that can be made before reading is made then: the input is never
    opened for its points."""
    from clcurv.io import stream
    d, _ = inputs

    def no_reading(*a, **kw):
        raise AssertionError("points read before the options were checked")
    monkeypatch.setattr(stream.LasSource, "chunks", no_reading)
    out = tmp_path / "out.laz"
    bad = [({"fields": ["k1"]}, ValueError, "unknown field"),            # mls1 has no k1
           ({"kernel": "gaussian"}, ValueError, "kernel"),
           ({"weights": "heavy"}, ValueError, "weights"),
           ({"precision": "quad"}, ValueError, "precision"),
           ({"device": 99}, clcurv.NoDeviceError, "99")]
    for kw, exc, msg in bad:
        with pytest.raises(exc, match=msg):
            _run(d / "scene.laz", out, **kw)
    from clcurv.cli.main import main                  # --radius auto reads the cloud: not yet
    for extra, code in ((["--fields", "k1"], 2), (["--kernel", "gaussian"], 2),
                        (["--device", "99"], 4)):
        assert main(["compute", str(d / "scene.laz"), "-o", str(out), "--method", "mls1",
                     "--tile-size", "8", "-q"] + extra) == code, extra
    assert sorted(os.listdir(tmp_path)) == []


def test_an_empty_input_gives_an_empty_output_in_tiles_as_in_memory(tmp_path):
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    laspy.LasData(hdr).write(str(tmp_path / "empty.las"))
    a = clcurv.curvature_file(tmp_path / "empty.las", tmp_path / "a.las", R)
    b = clcurv.curvature_file(tmp_path / "empty.las", tmp_path / "b.las", R, tile=TILE)
    assert not a["tiled"] and b["tiled"] and a["points"] == b["points"] == 0
    _same(tmp_path / "a.las", tmp_path / "b.las")


def test_a_catalog_with_an_empty_file_writes_every_output(inputs, tmp_path):
    d, pts = inputs
    np.save(tmp_path / "full.npy", pts)
    np.save(tmp_path / "empty.npy", np.empty((0, 3)))
    folder = tmp_path / "out"
    folder.mkdir()
    clcurv.curvature_file([str(tmp_path / "full.npy"), str(tmp_path / "empty.npy")], folder,
                          R, method="mls1", orient=None)
    ref = tmp_path / "ref.npz"
    clcurv.curvature_file(tmp_path / "full.npy", ref, R, method="mls1", tile=TILE,
                          orient=None)
    _same(folder / "full.npz", ref)
    with np.load(folder / "empty.npz") as z:
        assert all(len(z[k]) == 0 for k in z.files) and "mean_curvature" in z.files


def test_a_radius_too_small_warns_in_tiles_as_in_memory(inputs, tmp_path):
    d, _ = inputs
    for kw in ({}, {"tile": TILE}):
        with pytest.warns(RuntimeWarning, match="fewer than .* neighbours"):
            clcurv.curvature_file(d / "scene.laz", tmp_path / "x.laz", 0.01, method="mls1",
                                  **kw)


def test_the_tiled_summary_says_status_only_when_known(inputs, tmp_path):
    from tests.hostile import run_cli
    d, _ = inputs
    r = run_cli("compute", d / "scene.laz", "-o", tmp_path / "o.laz", "--radius", "1",
                "--method", "mls1", "--tile-size", "8", "-q", "--fields", "mean_curvature")
    assert r.code == 0, r.stderr
    assert "status ok" in r.stdout and "status ok 0.0%" not in r.stdout
    r = run_cli("compute", d / "scene.laz", "-o", tmp_path / "s.laz", "--radius", "0.01",
                "--method", "mls1", "--tile-size", "8", "-q")
    assert r.code == 0 and "clcurv: warning:" in r.stderr and "too small" in r.stderr


# --------------------------------------------------------------------------- full disk

def test_a_disk_too_small_is_refused_before_reading(inputs, tmp_path, monkeypatch):
    """The workspace's need is estimated from the point count and the fields, and said; a
    disk with less room refuses the run before a point is bucketed."""
    import shutil
    d, _ = inputs
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=100_000))
    out = tmp_path / "out.laz"
    with pytest.raises(OSError, match=r"needs about .* GiB of workspace") as e:
        _run(d / "scene.laz", out)
    assert e.value.errno == 28
    assert sorted(os.listdir(tmp_path)) == []


def test_a_disk_that_fills_during_the_tiles_removes_the_workspace(inputs, tmp_path,
                                                                  monkeypatch):
    """ENOSPC part way: the workspace goes (it cannot be resumed on this disk as it is),
    the error says how much a run needs, and the previous output is intact."""
    import errno
    d, _ = inputs
    out = tmp_path / "out.laz"
    out.write_bytes(b"previous")
    calls = [0]
    save = wsp.save_sealed

    def filling(path, arr):
        calls[0] += 1
        if calls[0] == 4:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        save(path, arr)
    monkeypatch.setattr(wsp, "save_sealed", filling)
    with pytest.raises(OSError, match="no space left .* needs about") as e:
        _run(d / "scene.laz", out)
    assert e.value.errno == errno.ENOSPC
    assert sorted(os.listdir(tmp_path)) == ["out.laz"] and out.read_bytes() == b"previous"


def test_the_command_takes_a_workdir(inputs, fresh, tmp_path):
    """--workdir DIR: the workspace is made in DIR (a missing DIR is refused, exit 3, before
    any point is read) and DIR keeps only what it held."""
    from tests.hostile import run_cli
    d, _ = inputs
    D = tmp_path / "scratch"
    out = tmp_path / "out.laz"
    args = ["compute", d / "scene.laz", "-o", out, "--radius", "1", "--method", "mls1",
            "--tile-size", "8", "-q", "--workdir", D]
    r = run_cli(*args)
    assert r.code == 3 and "does not exist" in r.stderr and not out.exists(), r.stderr
    r = run_cli(*[a for a in args if a not in ("--radius", "1")])           # radius auto
    assert r.code == 3 and "does not exist" in r.stderr and not out.exists(), r.stderr
    D.mkdir()
    (D / "keep.txt").write_text("k")
    r = run_cli(*args)
    assert r.code == 0, r.stderr
    assert sorted(os.listdir(D)) == ["keep.txt"]
    _same(out, fresh("laz"))


@pytest.mark.parametrize("where", ["write_las_piece", "assemble"])
def test_a_disk_that_fills_while_writing_the_output_removes_the_workspace(inputs, tmp_path,
                                                                          monkeypatch, where):
    """The disk fills while a piece of the output is written (a task's) or while the client
    joins the pieces: the previous output stays, and no workspace nor piece is left."""
    import errno
    from clcurv.io import pieces, stream
    d, _ = inputs
    out = tmp_path / "out.laz"
    out.write_bytes(b"previous")

    def full(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(stream if where == "write_las_piece" else pieces, where, full)
    with pytest.raises(OSError, match="no space left .* needs about") as e:
        _run(d / "scene.laz", out)
    assert e.value.errno == errno.ENOSPC
    assert sorted(os.listdir(tmp_path)) == ["out.laz"] and out.read_bytes() == b"previous"
