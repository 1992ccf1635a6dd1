"""The workspace of a tiled run (:mod:`clcurv.tiles.engine`): a folder the run creates, locks and
verifies, so that a run resumed after an interruption never reuses what it cannot trust.

* **Its own folder.** ``.<output name>.<hash>.clcurv-tiles`` beside the output (or in
  ``workdir``), the hash being that of the output's absolute path(s): two runs meet in one
  workspace only when they write the same output(s). The run marks it with :data:`TAG` and
  removes only the entries it makes (:data:`ENTRIES`); a folder of that name without the tag
  is refused, never emptied.
* **A lock.** ``flock(2)`` on the workspace folder and on a lock file beside each output
  (``.<output name>.clcurv-lock``, removed at the end): a second run on the same output or
  workspace is refused at once with a message naming the run that holds it. On file systems
  where ``flock`` is not shared between machines (some NFS mounts), runs from two machines
  are not excluded.
* **A key.** The manifest holds the key of the run: a content hash of every input
  (:func:`source_key`: its size, its mtime and a BLAKE2 hash of the whole file up to
  :data:`WHOLE_HASH_BYTES`, else of its head, its tail and :data:`SAMPLES` blocks spread
  over it), every option that changes a byte of output, the clcurv version and a hash of
  the kernels' sources. Another key: the workspace is emptied and the run starts afresh.
* **Sums.** Every file the run reuses across runs carries its record count and a CRC-32:
  the buckets and the tiles' input files in the manifest, the tiles' results in a footer of
  their own (:func:`save_sealed`). A file that fails its check raises
  :class:`CorruptWorkspace`; the run then recomputes (:mod:`clcurv.tiles.engine`). The merge's
  windows and the scale space's state are made afresh by every run and checked by their
  record ids.
"""
from __future__ import annotations

import errno
import fcntl
import glob
import hashlib
import io as _io
import json
import os
import re
import shutil
import socket
import struct
import time
import zlib
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv._shared.version import __version__
from clcurv.runtime.program import kernels_dir

#: the file that marks a folder as a clcurv workspace
TAG = "CLCURV-WORKSPACE"
#: what a run makes in its workspace (and removes; nothing else is touched)
ENTRIES = (TAG, "manifest.json", "manifest.tmp", "buckets", "tiles_in", "tiles_in.json",
           "tiles", "windows", "state", "parts", "owner.json")
#: inputs up to this size are hashed whole for the resume key; larger ones are sampled
WHOLE_HASH_BYTES = 256 << 20
#: blocks hashed in a larger input (besides its first and last MiB), of SAMPLE_BYTES each
SAMPLES = 256
SAMPLE_BYTES = 1 << 16
#: the version of the workspace's layout: another one is never resumed
LAYOUT = 3

_FOOTER = struct.Struct("<8sQI4x")
_MAGIC = b"CLCVSUM1"


class CorruptWorkspace(Exception):
    """A workspace file fails its check (count, CRC, footer): the run recomputes."""

    def __init__(self, path, why="corrupt"):
        super().__init__(str(path), why)          # (args: pickled through Dask intact)
        self.path, self.why = Path(path), why

    def __str__(self):
        return f"{self.path}: {self.why}"


class WorkspaceError(RuntimeError):
    """A workspace that cannot be used: locked by another run, or a folder of its name that
    clcurv did not make."""


# --------------------------------------------------------------------------- place and lock

def folder(dsts, workdir=None):
    """The workspace folder of a run writing ``dsts`` (a path, or the list of a catalog)."""
    dsts = [Path(d) for d in (dsts if isinstance(dsts, (list, tuple)) else [dsts])]
    key = hashlib.blake2b("\0".join(str(d.resolve()) for d in dsts).encode(),
                          digest_size=5).hexdigest()
    name = dsts[0].name if len(dsts) == 1 else f"catalog-{len(dsts)}"
    parent = Path(workdir) if workdir is not None else dsts[0].parent
    return parent / f".{name}.{key}.clcurv-tiles"


def check_workdir(workdir):
    """WorkspaceError unless ``workdir`` (None: beside the output) is an existing folder."""
    if workdir is not None and not Path(workdir).is_dir():
        raise WorkspaceError(f"{workdir}: the workspace's folder does not exist (give an "
                             "existing folder; clcurv makes its own folder inside it)")


def _lock_fd(fd, what):
    """flock ``fd`` without waiting, or WorkspaceError naming ``what``."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
            return True         # no locks on this file system: the documented limit
        raise
    return True


@contextmanager
def _locked_path(path, make, what):
    """Hold an exclusive flock on ``path`` (made by ``make(path)`` when missing), checked to
    be the path's current inode (a run that removed it as we opened it: try again)."""
    for _ in range(50):
        make(path)
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            if not _lock_fd(fd, what):
                raise WorkspaceError(f"{what} is in use by another clcurv run"
                                     f"{_owner_text(path)}: wait for it to finish, or stop "
                                     "it; two runs on one output would spoil each other")
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                try:
                    yield
                finally:
                    fcntl.flock(fd, fcntl.LOCK_UN)
                return
        finally:
            os.close(fd)
    raise WorkspaceError(f"{what}: could not take its lock")


def _owner_text(path):
    """Who holds the lock of ``path``: the owner.json of a workspace folder, or the lock
    file's own text."""
    p = Path(path)
    try:
        o = json.loads((p / "owner.json" if p.is_dir() else p).read_text())
    except (OSError, ValueError):
        o = None
    if not o:
        return ""
    return f" (pid {o.get('pid')} on {o.get('host')}, since {o.get('started')})"


def _make_dir(path):
    Path(path).mkdir(parents=False, exist_ok=True)


def _make_file(path):
    try:
        os.close(os.open(path, os.O_CREAT | os.O_WRONLY, 0o644))
    except FileExistsError:
        pass


@contextmanager
def claim(ws, dsts):
    """Create (or take over) the workspace ``ws`` and lock it and the outputs ``dsts`` for
    this run; yields the :class:`Workspace`. Refuses a folder that clcurv did not make."""
    ws = Path(ws)
    if ws.exists() and not ws.is_dir():
        raise WorkspaceError(f"{ws}: the workspace's name is taken by a file; remove it or "
                             "give another workdir")
    if ws.is_dir() and any(ws.iterdir()) and not (ws / TAG).exists():
        raise WorkspaceError(f"{ws}: a folder of the workspace's name that clcurv did not "
                             "make; it is left as it is: remove it or give another workdir")
    if not ws.parent.is_dir():
        raise WorkspaceError(f"{ws.parent}: the workspace's folder does not exist")
    dsts = [Path(d) for d in (dsts if isinstance(dsts, (list, tuple)) else [dsts])]
    owner = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                        "started": time.strftime("%Y-%m-%d %H:%M:%S")})
    with ExitStack() as stack:
        for d in sorted(set(dsts), key=str):
            lock = d.parent / f".{d.name}.clcurv-lock"
            stack.enter_context(_locked_path(lock, _make_file, f"the output {d}"))
            stack.callback(_unlink, lock)
            Path(lock).write_text(owner)
            _remove_stale_temps(d)
        stack.enter_context(_locked_path(ws, _make_dir, f"the workspace {ws}"))
        (ws / TAG).touch()
        write_text(ws / "owner.json", owner)
        yield Workspace(ws)


def _remove_stale_temps(dst):
    """Remove the temporary files of ``dst`` that a killed run left (clcurv.io.atomic_output
    names them ``.<name>.<8 hex digits>.tmp<ext>``); called with ``dst``'s lock held."""
    pattern = re.compile(re.escape(f".{dst.name[:180]}.") + r"[0-9a-f]{8}\.tmp"
                         + re.escape(dst.suffix) + "$")
    for p in dst.parent.glob(f".{glob.escape(dst.name[:180])}.*.tmp*"):
        if pattern.match(p.name) and p.is_file():
            _unlink(p)


def _unlink(path):
    try:
        os.unlink(path)
    except OSError:
        pass


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (a temporary file renamed onto it)."""
    tmp = Path(path).with_name(f".{Path(path).name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class Workspace:
    """A claimed workspace folder (:func:`claim`): its manifest, and removal of what the
    run made."""

    def __init__(self, path):
        self.path = Path(path)

    def __truediv__(self, name):
        return self.path / name

    def clear(self):
        """Remove what runs make here (the tag, lock and owner stay while it is held)."""
        for name in ENTRIES:
            if name in (TAG, "owner.json"):
                continue
            remove(self.path / name)
        for p in self.path.glob(".*.tmp"):
            remove(p)

    def remove(self):
        """Remove what runs make here, then the folder when nothing else is left in it."""
        self.clear()
        for name in (TAG, "owner.json"):
            remove(self.path / name)
        try:
            self.path.rmdir()
        except OSError:
            pass                # something clcurv did not make: left where it is

    def manifest(self):
        """The manifest dict, or None when missing or failing its own sum."""
        try:
            doc = json.loads((self.path / "manifest.json").read_text())
            body = doc["body"]
            ok = doc["sum"] == digest(json.dumps(body, sort_keys=True).encode())
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return body if ok else None

    def write_manifest(self, body):
        text = json.dumps(body, sort_keys=True)
        write_text(self.path / "manifest.json",
                   json.dumps({"body": json.loads(text), "sum": digest(text.encode())}))


def tile_file(ws, t):
    """The result file of tile ``t`` in the workspace folder ``ws``."""
    return Path(ws) / "tiles" / f"{t}.npy"


def remove(p):
    """Remove the file or folder ``p`` (and what it holds), if there."""
    p = Path(p)
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        _unlink(p)


def digest(data):
    return hashlib.blake2b(data, digest_size=16).hexdigest()


# --------------------------------------------------------------------------- the key

def file_hash(path):
    """A BLAKE2 hash of the file ``path``: of all of it up to WHOLE_HASH_BYTES, else of its
    first and last MiB and SAMPLES blocks spread evenly between (with its size)."""
    size = os.path.getsize(path)
    h = hashlib.blake2b(digest_size=16)
    h.update(str(size).encode())
    with open(path, "rb") as f:
        if size <= WHOLE_HASH_BYTES:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        else:
            offsets = [0, max(size - (1 << 20), 0)]
            offsets += [int(size * (k + 0.5) / SAMPLES) for k in range(SAMPLES)]
            for off in sorted(offsets):
                f.seek(off)
                h.update(f.read(1 << 20 if off in offsets[:2] else SAMPLE_BYTES))
    return h.hexdigest()


def source_key(paths, hashes=None):
    """The resume key of the input files ``paths``: path, size, mtime and content hash
    (:func:`file_hash`; ``hashes``: theirs, computed elsewhere, e.g. by the workers)."""
    out = []
    hashes = hashes if hashes is not None else [file_hash(p) for p in paths]
    for p, h in zip(paths, hashes):
        st = os.stat(p)
        out.append({"path": str(Path(p).resolve()), "size": st.st_size,
                    "mtime_ns": st.st_mtime_ns, "hash": h})
    return out


@dataclass
class HashTask:
    """The :func:`file_hash` of input file number ``t`` (:func:`hash_task`)."""
    t: int
    path: str


def hash_task(task):
    """The content hash of one input file, on a worker (the client reads no input)."""
    return task.t, file_hash(task.path)


_CODE = []


def code_key():
    """The clcurv version and a hash of the kernels' sources: results of other code are
    never resumed."""
    if not _CODE:
        h = hashlib.blake2b(digest_size=16)
        for p in sorted(kernels_dir().glob("*")):
            if p.suffix in (".cl", ".h"):
                h.update(p.name.encode() + p.read_bytes())
        _CODE.append({"clcurv": __version__, "kernels": h.hexdigest(), "layout": LAYOUT})
    return _CODE[0]


# --------------------------------------------------------------------------- sums

class Crc:
    """Record counts and CRC-32s of files written by appends, keyed by name."""

    def __init__(self, state=None):
        self.sums = {k: list(v) for k, v in (state or {}).items()}

    def add(self, key, rec):
        """Account for the records ``rec`` appended to the file ``key``."""
        n, c = self.sums.get(key, (0, 0))
        self.sums[key] = [n + len(rec), zlib.crc32(memoryview(np.ascontiguousarray(rec))
                                                   .cast("B"), c)]

    def state(self):
        return {k: list(v) for k, v in self.sums.items()}


def check_records(path, rec, expect):
    """CorruptWorkspace unless the records ``rec`` read from ``path`` have the count and the
    CRC of ``expect`` ((count, crc), or None: the file must be empty or absent)."""
    n, c = expect if expect is not None else (0, 0)
    if len(rec) != n:
        raise CorruptWorkspace(path, f"{len(rec)} records where {n} were written")
    got = zlib.crc32(memoryview(np.ascontiguousarray(rec)).cast("B")) if len(rec) else 0
    if got != c:
        raise CorruptWorkspace(path, "its records fail their CRC-32 (changed on disk)")


def save_sealed(path, arr):
    """Write the array ``arr`` to ``path`` atomically, as .npy followed by a footer with its
    length and the CRC-32 of the .npy bytes (:func:`load_sealed` checks both)."""
    path = Path(path)
    buf = _io.BytesIO()
    np.save(buf, arr)
    body = buf.getvalue()
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(body)
        f.write(_FOOTER.pack(_MAGIC, len(arr), zlib.crc32(body)))
    os.replace(tmp, path)


def load_sealed(path):
    """The array of a file written by :func:`save_sealed`, or CorruptWorkspace."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CorruptWorkspace(path, "missing") from None
    if len(data) < _FOOTER.size:
        raise CorruptWorkspace(path, "truncated")
    magic, n, crc = _FOOTER.unpack(data[-_FOOTER.size:])
    body = memoryview(data)[:-_FOOTER.size]
    if magic != _MAGIC or zlib.crc32(body) != crc:
        raise CorruptWorkspace(path, "fails its CRC-32 (truncated or changed on disk)")
    try:
        arr = np.load(_io.BytesIO(body))
    except (ValueError, OSError, EOFError) as exc:
        raise CorruptWorkspace(path, f"unreadable ({exc})") from None
    if len(arr) != n:
        raise CorruptWorkspace(path, f"{len(arr)} records where {n} were written")
    return arr


def is_sound(path):
    """Does ``path`` pass :func:`load_sealed`?"""
    try:
        load_sealed(path)
    except CorruptWorkspace:
        return False
    return True
