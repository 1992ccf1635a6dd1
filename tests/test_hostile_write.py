"""Issue 10, hostile output: writes are atomic and output paths are checked before the work.

A full disk is simulated without root by writing in a child process whose file size limit
(``RLIMIT_FSIZE``) is below the output's size, with ``SIGXFSZ`` ignored: a write past the
limit fails with ``EFBIG`` as it would with ``ENOSPC`` on a full disk.
"""
from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import clcurv.io as cio
from clcurv.data import sample_path

from hostile import assert_clean_failure, run_cli

#: the child's file size limit; every output of ``big_cloud`` is larger (LAZ included)
LIMIT = 64 * 1024
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


def fsize_limit(nbytes):
    """preexec_fn: writes past ``nbytes`` fail with EFBIG instead of killing the process."""
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return limit


def listing(folder):
    """name -> bytes of every file in ``folder``."""
    return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir())}


def needs_laspy(ext):
    if ext in (".las", ".laz"):
        laspy = pytest.importorskip("laspy")
        if ext == ".laz" and not laspy.LazBackend.detect_available():
            pytest.skip("no LAZ backend (pip install laspy[lazrs])")


def run_child(code, *args, limit=None):
    """Run Python ``code`` (argv[1:] = args) in a child, optionally under a file size limit;
    return the JSON object it prints last."""
    p = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                       text=True, timeout=120,
                       preexec_fn=None if limit is None else fsize_limit(limit))
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


#: writes a 50,000-point cloud with normals and two fields to argv[1]; prints what it raised
CHILD_WRITE = r"""
import json, sys
import numpy as np
import clcurv.io as cio
rng = np.random.default_rng(1)
n = 50_000
pts = rng.uniform(-10, 10, size=(n, 3))
nrm = rng.normal(size=(n, 3))
fields = {"mean_curvature": rng.normal(size=n), "k1": rng.normal(size=n).astype(np.float32)}
try:
    cio.write(sys.argv[1], pts, fields, normals=nrm)
except BaseException as e:
    print(json.dumps({"type": type(e).__name__, "msg": str(e), "errno": getattr(e, "errno", None),
                      "oserror": isinstance(e, OSError), "writeerror": isinstance(e, cio.WriteError)}))
else:
    print(json.dumps({"type": None}))
"""


# --------------------------------------------------------------------------- io.write

@pytest.mark.parametrize("previous", [True, False], ids=["replace", "new"])
@pytest.mark.parametrize("ext", sorted(cio.WRITE_FORMATS))
def test_write_that_fills_the_disk_leaves_the_previous_file_and_nothing_else(
        tmp_path, ext, previous):
    needs_laspy(ext)
    out = tmp_path / f"cloud{ext}"
    if previous:
        cio.write(out, np.arange(30.0).reshape(10, 3), {"k1": np.ones(10)})
    before = listing(tmp_path)
    got = run_child(CHILD_WRITE, out, limit=LIMIT)
    assert listing(tmp_path) == before  # byte-identical previous file, no temporary left
    assert got["type"] == "WriteFailedError", got
    assert got["oserror"] and got["writeerror"], got  # the CLI maps both to exit 3
    assert got["errno"] == errno.EFBIG, got
    assert got["msg"].startswith(f"{out}: write failed"), got
    assert ".tmp" not in got["msg"], got


def test_cli_compute_in_place_on_a_full_disk_keeps_the_input(tmp_path):
    """``clcurv compute in.ply -o in.ply`` whose output does not fit: exit 3, one line, the
    input byte-identical, no other file."""
    src = tmp_path / "in.ply"
    shutil.copyfile(sample_path(), src)
    before = listing(tmp_path)
    # the result with every field (normals, curvatures, directions: 2.9 MB) does not fit;
    # PoCL's compiler writes files of up to about 1 MB (a kernel build fails under a 0.5 MB
    # limit)
    limit = 2 * 2**20
    outcome = run_cli("compute", src, "-o", src, "-q", "--fields", "all",
                      preexec_fn=fsize_limit(limit))
    assert listing(tmp_path) == before
    assert_clean_failure(outcome, 3, "compute on a full disk")
    assert str(src) in outcome.lines[0] and "write failed" in outcome.lines[0], outcome.lines


def can_mount_a_tmpfs():
    """True when ``unshare -rm`` may mount a tmpfs (a user and mount namespace)."""
    if shutil.which("unshare") is None:
        return False
    p = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                       capture_output=True, timeout=30)
    return p.returncode == 0


@pytest.mark.skipif(not can_mount_a_tmpfs(), reason="cannot mount a tmpfs (unshare -rm)")
def test_cli_compute_in_place_on_a_real_full_disk_keeps_the_input(tmp_path):
    """The issue's case: the bunny on a 2 MB tmpfs, ``clcurv compute b.ply -o b.ply``: the
    write fails with ENOSPC; exit 3, one line, the input byte-identical, nothing else."""
    disk = tmp_path / "disk"
    disk.mkdir()
    src = disk / "b.ply"
    script = (f'mount -t tmpfs -o size=2m tmpfs "{disk}" && cp "{sample_path()}" "{src}" && '
              f'{{ "{sys.executable}" -m clcurv.cli compute "{src}" -o "{src}" -q; '
              f'echo "rc=$?"; ls -A "{disk}"; cmp -s "{src}" "{sample_path()}" && echo same; }}')
    p = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True,
                       timeout=120)
    lines = [l for l in p.stderr.splitlines() if l.strip()]
    assert p.stdout.split("\n")[-4:] == ["rc=3", "b.ply", "same", ""], (p.stdout, p.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"clcurv: error: {src}: write failed: "), lines
    assert "No space left" in lines[0], lines


#: writes a 400,000-point CSV to argv[1]; a watcher thread interrupts the main thread (as
#: Ctrl-C would) as soon as a new or changed non-empty file shows up in the folder
CHILD_INTERRUPT = r"""
import _thread, json, os, sys, threading, time
from pathlib import Path
import numpy as np
import clcurv.io as cio
out = Path(sys.argv[1])
folder = out.parent
def state():
    return {p.name: p.stat().st_size for p in folder.iterdir()}
start = state()
seen = {}
def watch():
    while True:
        try:
            now = state()
        except FileNotFoundError:
            continue
        grown = {k: v for k, v in now.items() if v and start.get(k) != v}
        if grown:
            seen.update(grown)
            _thread.interrupt_main()
            return
        time.sleep(0.0005)
rng = np.random.default_rng(2)
n = 400_000
pts = rng.uniform(-1, 1, size=(n, 3))
fields = {"mean_curvature": rng.normal(size=n)}
threading.Thread(target=watch, daemon=True).start()
try:
    cio.write(out, pts, fields)
except KeyboardInterrupt:
    print(json.dumps({"interrupted": True, "seen": seen}))
else:
    print(json.dumps({"interrupted": False, "seen": seen}))
"""


def test_interrupt_in_the_middle_of_a_write_leaves_the_previous_file(tmp_path):
    """Ctrl-C while the rows are being written: the partial file existed (the watcher saw it
    grow), then the previous file is back byte-identical and the partial one is gone."""
    out = tmp_path / "cloud.csv"
    cio.write(out, np.arange(30.0).reshape(10, 3))
    before = listing(tmp_path)
    got = run_child(CHILD_INTERRUPT, out)
    assert got["interrupted"], got
    assert got["seen"], got  # interrupted mid-write, not before it began
    assert listing(tmp_path) == before


def test_a_writer_refusal_names_the_output_and_leaves_the_previous_file(tmp_path):
    """The LAS writer refuses NaN coordinates after its checks began (inside the atomic
    write): the message names the output, not the temporary file."""
    needs_laspy(".las")
    out = tmp_path / "cloud.las"
    cio.write(out, np.arange(30.0).reshape(10, 3))
    before = listing(tmp_path)
    pts = np.arange(30.0).reshape(10, 3)
    pts[4, 1] = np.nan
    with pytest.raises(cio.WriteError, match="NaN") as e:
        cio.write(out, pts)
    assert str(e.value).startswith(f"{out}: "), str(e.value)
    assert ".tmp" not in str(e.value)
    assert listing(tmp_path) == before


# --------------------------------------------------------------------------- atomic_output

def test_atomic_output_keeps_mode_and_extension_and_cleans_up(tmp_path):
    out = tmp_path / "a.laz"
    out.write_bytes(b"old")
    out.chmod(0o640)
    with cio.atomic_output(out) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".laz" and tmp.name.startswith(".a.laz.")
        assert tmp.exists() and tmp != out
        tmp.write_bytes(b"new")
        assert out.read_bytes() == b"old"  # nothing visible before the end
    assert listing(tmp_path) == {"a.laz": b"new"}
    assert out.stat().st_mode & 0o777 == 0o640

    for exc in (KeyboardInterrupt(), RuntimeError("boom")):
        with pytest.raises(type(exc)):
            with cio.atomic_output(out) as tmp:
                tmp.write_bytes(b"partial")
                raise exc
        assert listing(tmp_path) == {"a.laz": b"new"}


def test_atomic_output_new_file_has_the_usual_mode(tmp_path):
    umask = os.umask(0o022)
    try:
        with cio.atomic_output(tmp_path / "n.ply") as tmp:
            tmp.write_bytes(b"x")
        plain = tmp_path / "plain"
        plain.write_bytes(b"x")
    finally:
        os.umask(umask)
    assert (tmp_path / "n.ply").stat().st_mode & 0o777 == plain.stat().st_mode & 0o777 == 0o644


def test_atomic_output_through_a_symlink_replaces_the_file_it_points_to(tmp_path):
    real = tmp_path / "data" / "real.ply"
    real.parent.mkdir()
    real.write_bytes(b"old")
    link = tmp_path / "link.ply"
    link.symlink_to(real)
    with cio.atomic_output(link) as tmp:
        assert tmp.parent == real.parent
        tmp.write_bytes(b"new")
    assert link.is_symlink() and real.read_bytes() == b"new"


# --------------------------------------------------------------------------- check_output

def test_check_output_accepts_a_writable_path_without_touching_it(tmp_path):
    for ext in cio.WRITE_FORMATS:
        assert cio.check_output(str(tmp_path / f"o{ext.upper()}")) == tmp_path / f"o{ext.upper()}"
    (tmp_path / "old.ply").write_bytes(b"old")
    assert cio.check_output(tmp_path / "old.ply") == tmp_path / "old.ply"
    assert listing(tmp_path) == {"old.ply": b"old"}


def refused_cases(tmp):
    (tmp / "dir.ply").mkdir()
    (tmp / "file.txt").write_text("x")
    return {
        "unknown extension": (tmp / "cloud.e57", r"extension '\.e57'; expected one of .*\.ply"),
        "no extension": (tmp / "cloud", r"extension '\(none\)'; expected one of .*\.las"),
        "read-only format": (tmp / "cloud.pcd", r"'\.pcd'; expected one of"),
        "missing folder": (tmp / "nope" / "cloud.ply", r"folder .*nope does not exist"),
        "parent is a file": (tmp / "file.txt" / "cloud.ply", r"file\.txt is not a folder"),
        "directory": (tmp / "dir.ply", r"is a directory"),
    }


@pytest.mark.parametrize("case", ["unknown extension", "no extension", "read-only format",
                                  "missing folder", "parent is a file", "directory"])
def test_check_output_refuses(tmp_path, case):
    path, pattern = refused_cases(tmp_path)[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(cio.OutputPathError, match=pattern) as e:
        cio.check_output(path)
    assert isinstance(e.value, cio.WriteError) and isinstance(e.value, ValueError)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no folder created
    with pytest.raises(cio.OutputPathError, match=pattern):  # write checks first
        cio.write(path, np.zeros((3, 2)))


def read_only_folder(tmp_path):
    """A folder this process cannot create files in, where ``os.access`` may still say yes:
    a 0o555 folder, or for root (who ignores modes) sysfs."""
    if not IS_ROOT:
        folder = tmp_path / "ro"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    for folder in (Path("/sys"), Path("/proc")):
        probe = folder / ".clcurv-probe.ply"
        try:
            os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except OSError:
            return folder
        os.unlink(probe)
    pytest.skip("running as root without a read-only folder to test with")


def test_check_output_refuses_a_read_only_folder(tmp_path):
    folder = read_only_folder(tmp_path)
    try:
        with pytest.raises(cio.OutputPathError, match=r"not writable|cannot create a file"):
            cio.check_output(folder / "cloud.ply")
    finally:
        if folder.is_relative_to(tmp_path):
            folder.chmod(0o755)


@pytest.mark.skipif(IS_ROOT, reason="root may write read-only files")
def test_check_output_refuses_a_read_only_file(tmp_path):
    out = tmp_path / "old.ply"
    out.write_bytes(b"old")
    out.chmod(0o444)
    with pytest.raises(cio.OutputPathError, match="read-only"):
        cio.check_output(out)
    with pytest.raises(cio.OutputPathError, match="read-only"):
        cio.write(out, np.zeros((3, 3)))
    assert out.read_bytes() == b"old"


def test_check_output_is_fast(tmp_path):
    """No computation: well under a millisecond a call in practice."""
    paths = [tmp_path / "ok.ply", tmp_path / "no" / "x.ply", tmp_path / "x.e57"]
    t = time.perf_counter()
    for _ in range(100):
        for p in paths:
            try:
                cio.check_output(p)
            except cio.OutputPathError:
                pass
    assert (time.perf_counter() - t) / 300 < 0.01
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- render

render_mod = pytest.importorskip("clcurv.render")


def sphere(n=2_000, seed=0):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


@pytest.mark.parametrize("ext", [".ply", ".las", ".npz", ".csv", ".txt", ".e57", ""])
def test_render_refuses_a_non_picture_extension_before_drawing(tmp_path, ext, monkeypatch):
    out = tmp_path / f"a{ext}"
    out.write_bytes(b"the cloud")
    drew = []
    monkeypatch.setattr(render_mod, "_import_matplotlib", lambda: drew.append(1))
    with pytest.raises(cio.OutputPathError, match=r"expected one of \.png, .*\.svg"):
        render_mod.render(sphere(), sphere()[:, 0], out)
    assert not drew
    assert listing(tmp_path) == {out.name: b"the cloud"}


def test_render_refuses_a_missing_folder(tmp_path):
    with pytest.raises(cio.OutputPathError, match="does not exist"):
        render_mod.render(sphere(), sphere()[:, 0], tmp_path / "sub" / "x.png")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(cio.OutputPathError, match="does not exist"):
        render_mod.check_image_output(tmp_path / "sub" / "x.png")


def test_cli_render_onto_the_cloud_is_refused(tmp_path):
    """``clcurv render a.ply -o a.ply``: exit 3 (a WriteError: the output cannot be written,
    like every unwritable output), one line listing the picture extensions, the cloud
    byte-identical."""
    pytest.importorskip("matplotlib")
    src = tmp_path / "a.ply"
    pts = sphere()
    cio.write(src, pts, {"mean_curvature": pts[:, 2]})
    before = listing(tmp_path)
    outcome = run_cli("render", src, "-o", src)
    assert_clean_failure(outcome, 3, "render onto a .ply")
    assert ".png" in outcome.lines[0] and str(src) in outcome.lines[0], outcome.lines
    assert listing(tmp_path) == before


MAGIC = {".png": b"\x89PNG", ".jpg": b"\xff\xd8\xff", ".pdf": b"%PDF", ".svg": b"<?xml",
         ".tiff": b"II*\x00"}


@pytest.mark.parametrize("ext", sorted(MAGIC))
def test_render_writes_the_format_of_the_extension_atomically(tmp_path, ext):
    pytest.importorskip("matplotlib")
    out = tmp_path / f"pic{ext}"
    out.write_bytes(b"old")
    out.chmod(0o640)
    assert render_mod.render(sphere(), sphere()[:, 0], out, dpi=20) == out
    assert out.read_bytes().startswith(MAGIC[ext])
    assert out.stat().st_mode & 0o777 == 0o640
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


CHILD_RENDER = r"""
import json, sys
import numpy as np
from clcurv.render import render
p = np.random.default_rng(0).normal(size=(5_000, 3))
try:
    render(p, p[:, 0], sys.argv[1], dpi=80)
except BaseException as e:
    print(json.dumps({"type": type(e).__name__, "msg": str(e), "oserror": isinstance(e, OSError)}))
else:
    print(json.dumps({"type": None}))
"""


def test_render_that_fills_the_disk_leaves_the_previous_picture(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "pic.png"
    out.write_bytes(b"previous picture")
    got = run_child(CHILD_RENDER, out, limit=16 * 1024)
    assert listing(tmp_path) == {"pic.png": b"previous picture"}
    assert got["type"] == "WriteFailedError" and got["oserror"], got
    assert got["msg"].startswith(f"{out}: write failed"), got
