"""Hostile input (issue 10): a seeded fuzz of the readers' headers.

Valid small files (PLY ascii/binary, PCD ascii/binary/binary_compressed, LAS, NPZ) have
header bytes, header counts (their digits, or the binary count fields) and their length
mutated; every outcome must be a clean read (a Cloud whose arrays have consistent lengths)
or a :class:`clcurv.io.ReadError`. The reads run in a worker process whose address space
is capped (:data:`WORKER_AS`) and which is killed after :data:`CASE_SECONDS` on one case,
so a MemoryError, a hang or a crash is a failure that prints the seed, the mutation and a
command reproducing it (the mutated file is kept in pytest's tmp directory).

``CLCURV_FUZZ_CASES=<n>`` changes the number of cases per format (default
:data:`CASES`, about 30 s in all on 2 cores).
"""
import json
import os
import re
import select
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv import io as cio
from hostile import lzf_literals

SEED = 20240610
CASES = int(os.environ.get("CLCURV_FUZZ_CASES", "3000"))
#: address space the worker may add to what it uses after its imports
WORKER_AS = 2 << 30
#: wall time for one read before the case counts as a hang
CASE_SECONDS = 10.0

#: number strings put in place of a header count
EXTREMES = [b"0", b"1", b"-1", b"2", b"3", b"255", b"65536", b"999999999", b"1000000000",
            b"2147483648", b"4294967295", b"4294967296", b"10000000000",
            b"9223372036854775807", b"9223372036854775808", b"18446744073709551617",
            b"-9223372036854775809", b"99999999999999999999999999", b"1e9", b"+5", b"0x10",
            b"", b"nan"]
#: integers written over a binary count field (masked to its width)
#: point counts that :func:`_scale` claims (a 32-bit size word must still be able to hold
#: them times the point size)
EXTREMES_INT = [0, 1, 25, 1000, 10 ** 6, 10 ** 7, 5 * 10 ** 7, 10 ** 8]
N_BASE = 24
BIN_EXTREMES = [0, 1, 2, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0x80000000,
                0xFFFFFFFF, 0x7FFFFFFFFFFFFFFF, 0xFFFFFFFFFFFFFFFF]


# ------------------------------------------------------------------ valid base files

def _cloud(n=N_BASE, seed=3):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * 10
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    fields = {"curv": rng.normal(size=n).astype(np.float32),
              "label": rng.integers(0, 9, n).astype(np.uint8)}
    return pts, nrm, fields


def _pcd(data, pts, nrm, fields):
    """PCD with x y z, normals, a packed rgb, a COUNT 2 field and a label."""
    n = len(pts)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("normal_x", "<f4"),
                      ("normal_y", "<f4"), ("normal_z", "<f4"), ("rgb", "<u4"),
                      ("hist", "<f4", (2,)), ("label", "u1")])
    rec = np.zeros(n, dtype)
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["normal_x"], rec["normal_y"], rec["normal_z"] = nrm.T
    rec["rgb"] = np.arange(n) * 65793
    rec["hist"] = np.column_stack([fields["curv"], -fields["curv"]])
    rec["label"] = fields["label"]
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
            "FIELDS x y z normal_x normal_y normal_z rgb hist label\n"
            "SIZE 4 4 4 4 4 4 4 4 1\nTYPE F F F F F F U F U\nCOUNT 1 1 1 1 1 1 1 2 1\n"
            f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
            ).encode()
    if data == "ascii":
        rows = [" ".join(str(v) for name in dtype.names for v in np.atleast_1d(r[name]))
                for r in rec]
        return head, head + ("\n".join(rows) + "\n").encode(), []
    if data == "binary":
        return head, head + rec.tobytes(), []
    soa = b"".join(np.ascontiguousarray(rec[name]).tobytes() for name in dtype.names)
    comp = lzf_literals(soa)
    sizes = [(len(head), 4), (len(head) + 4, 4)]  # compressed, uncompressed size words
    return head, head + struct.pack("<II", len(comp), len(soa)) + comp, sizes


def _ply_text(tmp, pts, nrm, fields, text, face_first, order="<"):
    """PLY with a vertex element and a face element (plyfile writes it)."""
    import plyfile
    v = np.zeros(len(pts), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("nx", "f4"),
                            ("ny", "f4"), ("nz", "f4"), ("curv", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    v["nx"], v["ny"], v["nz"] = nrm.T
    v["curv"] = fields["curv"]
    f = np.zeros(4, [("vertex_indices", "O")])
    for i in range(4):
        f["vertex_indices"][i] = np.array([i, i + 1, i + 2], np.int32)
    els = [plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")]
    path = tmp / "base.ply"
    plyfile.PlyData(els[::-1] if face_first else els, text=text, byte_order=order,
                    comments=["fuzz base"]).write(str(path))
    return path.read_bytes()


def _las_fields(raw):
    """(offset, width) of the LAS header fields holding counts, sizes and offsets."""
    fields = [(94, 2), (96, 4), (100, 4), (104, 1), (105, 2), (107, 4), (111, 4)]
    if raw[24:26] == b"\x01\x04":  # LAS 1.4: EVLRs and 64-bit counts
        fields += [(227, 8), (235, 8), (243, 4), (247, 8), (255, 8)]
    header_size = struct.unpack_from("<H", raw, 94)[0]
    if struct.unpack_from("<I", raw, 100)[0]:  # first VLR: its record length
        fields.append((header_size + 20, 2))
    return fields


def _zip_fields(raw):
    """(offset, width) of the size fields of every zip local and central header."""
    fields = []
    for sig, at in ((b"PK\x03\x04", 18), (b"PK\x01\x02", 20)):
        for m in re.finditer(re.escape(sig), raw):
            fields += [(m.start() + at, 4), (m.start() + at + 4, 4)]
    return fields


def base_file(kind, tmp):
    """(extension, bytes, header length, binary count fields) of a valid file, also
    written to ``tmp/base.<ext>``."""
    pts, nrm, fields = _cloud()
    if kind.startswith("pcd_"):
        head, raw, sizes = _pcd(kind[4:], pts, nrm, fields)
        (tmp / "base.pcd").write_bytes(raw)
        return ".pcd", raw, len(head), sizes
    if kind.startswith("ply_"):
        if kind == "ply_binary":  # clcurv's own writer: vertex only
            cio.write(tmp / "base.ply", pts, fields, nrm)
            raw = (tmp / "base.ply").read_bytes()
        else:
            raw = _ply_text(tmp, pts, nrm, fields, text=kind == "ply_ascii",
                            face_first=kind == "ply_mesh_be", order=">")
        return ".ply", raw, raw.index(b"end_header") + 11, []
    ext = "." + kind
    cio.write(tmp / ("base" + ext), pts, fields, nrm)
    raw = (tmp / ("base" + ext)).read_bytes()
    if kind == "las":
        return ext, raw, struct.unpack_from("<I", raw, 96)[0], _las_fields(raw)
    return ext, raw, len(raw), _zip_fields(raw)


KINDS = ["ply_ascii", "ply_binary", "ply_mesh_be", "pcd_ascii", "pcd_binary",
         "pcd_binary_compressed", "las", "npz"]


# ------------------------------------------------------------------ mutations

def _digits(raw, hlen, rng):
    """Replace one number of the text header by an extreme or a random digit string."""
    nums = list(re.finditer(rb"-?\d+", raw[:hlen]))
    if not nums:
        return raw, None
    m = nums[rng.integers(len(nums))]
    if rng.random() < 0.7:
        new = EXTREMES[rng.integers(len(EXTREMES))]
    else:
        new = str(int(rng.integers(0, 10 ** rng.integers(1, 19)))).encode()
    return raw[:m.start()] + new + raw[m.end():], ("digits", m.start(), m.group(), new)


def _scale(raw, hlen, fields, rng):
    """Put one new point count in every header number equal to the base's (PCD WIDTH and
    POINTS, PLY ``element vertex``) and, in binary_compressed PCD, the matching
    uncompressed size word: a coherent claim of many points over a small body."""
    new = int(EXTREMES_INT[rng.integers(len(EXTREMES_INT))])
    head = re.sub(rb"(?<![\d.-])%d(?![\d.])" % N_BASE, str(new).encode(), raw[:hlen])
    raw = head + raw[hlen:]
    if fields:  # PCD binary_compressed: the size words follow the header
        off = len(head) + 4
        usize = struct.unpack_from("<I", raw, off)[0] // N_BASE * new & 0xFFFFFFFF
        raw = raw[:off] + struct.pack("<I", usize) + raw[off + 4:]
    return raw, ("scale", N_BASE, new)


def _binfield(raw, fields, rng):
    """Write an extreme integer over one binary count field."""
    off, width = fields[rng.integers(len(fields))]
    value = BIN_EXTREMES[rng.integers(len(BIN_EXTREMES))] & ((1 << 8 * width) - 1)
    if rng.random() < 0.3:
        value = int(rng.integers(0, 1 << min(8 * width, 62)))
    new = value.to_bytes(width, "little")
    return raw[:off] + new + raw[off + width:], ("binfield", off, raw[off:off + width], new)


def _bytes(raw, hlen, rng):
    """Set one to four bytes of the header to random values."""
    out = bytearray(raw)
    edits = []
    for _ in range(rng.integers(1, 5)):
        off = int(rng.integers(min(hlen, len(raw))))
        new = int(rng.integers(256))
        edits.append((off, out[off], new))
        out[off] = new
    return bytes(out), ("bytes", edits)


def _truncate(raw, hlen, rng):
    """Cut the file, most often within a few bytes of the end of the header."""
    if rng.random() < 0.5:
        cut = int(rng.integers(max(hlen - 16, 0), min(hlen + 64, len(raw)) + 1))
    else:
        cut = int(rng.integers(len(raw) + 1))
    return raw[:cut], ("truncate", cut)


def mutate(raw, hlen, fields, rng):
    """(mutated bytes, list of mutations): one or two of digits, binfield, bytes, then a
    truncation one case in four."""
    done = []
    ops = ["bytes", "digits"] + (["binfield"] * 2 if fields else [])
    if hlen < len(raw) and not raw.startswith(b"LASF"):  # text headers: PLY and PCD
        ops.append("scale")
    for _ in range(rng.integers(1, 3)):
        op = ops[rng.integers(len(ops))]
        size = len(raw)
        if op == "scale":
            raw, what = _scale(raw, hlen, fields, rng)
        elif op == "digits":
            raw, what = _digits(raw, hlen, rng)
        elif op == "binfield":
            raw, what = _binfield(raw, fields, rng)
        else:
            raw, what = _bytes(raw, hlen, rng)
        hlen += len(raw) - size  # digits and scale change the header's length only
        if what:
            done.append(what)
    if rng.random() < 0.25:
        raw, what = _truncate(raw, hlen, rng)
        done.append(what)
    return raw, done


# ------------------------------------------------------------------ the worker

def check_cloud(c):
    """'' when the Cloud's arrays are consistent, else what is wrong."""
    n = len(c.points)
    if c.points.shape != (n, 3) or c.points.dtype != np.float64:
        return f"points {c.points.shape} {c.points.dtype}"
    if not np.isfinite(c.points).all():
        return "non-finite points"
    if c.normals is not None and c.normals.shape != (n, 3):
        return f"normals {c.normals.shape} for {n} points"
    bad = {k: np.shape(v) for k, v in c.attributes.items() if len(v) != n}
    return f"attributes {bad} for {n} points" if bad else ""


def worker():
    """Read one path per stdin line; answer one JSON line: status ok / error / bad."""
    import resource
    import traceback
    with open("/proc/self/statm") as f:
        used = int(f.read().split()[0]) * resource.getpagesize()
    resource.setrlimit(resource.RLIMIT_AS, (used + WORKER_AS, resource.RLIM_INFINITY))
    for line in sys.stdin:
        try:
            cloud = cio.read(line.strip())
            wrong = check_cloud(cloud)
            out = {"status": "bad" if wrong else "ok", "detail": wrong}
        except cio.ReadError as exc:
            out = {"status": "error", "detail": f"{type(exc).__name__}: {exc}"[:300]}
        except BaseException as exc:  # MemoryError, RecursionError...: a failure
            out = {"status": "bad", "detail": f"{type(exc).__name__}: {exc}\n"
                   + traceback.format_exc()[-1500:]}
        print(json.dumps(out), flush=True)


class Worker:
    """The worker process: :meth:`read` returns its answer, or a hang/crash answer."""

    def __init__(self):
        src = str(Path(clcurv.__file__).resolve().parents[1])
        tests = str(Path(__file__).resolve().parent)
        code = (f"import sys; sys.path[:0] = [{src!r}, {tests!r}]; "
                "import test_hostile_fuzz as t; t.worker()")
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        self.p = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, env=env)

    def read(self, path):
        self.p.stdin.write(f"{path}\n")
        self.p.stdin.flush()
        ready, _, _ = select.select([self.p.stdout], [], [], CASE_SECONDS)
        line = self.p.stdout.readline() if ready else ""
        if line:
            return json.loads(line)
        self.close()
        if not ready:
            return {"status": "bad", "detail": f"hang: no answer after {CASE_SECONDS} s"}
        return {"status": "bad", "detail": f"worker died (exit {self.p.returncode})"}

    def close(self):
        if self.p.poll() is None:
            self.p.kill()
        self.p.wait()


# ------------------------------------------------------------------ the test

def _reproducer(kind, case, path, mutations, detail):
    return (f"fuzz {kind} case {case} (SEED {SEED}): {detail}\n"
            f"  mutations: {mutations!r}\n"
            f"  file kept: {path}\n"
            f"  reproduce: python -c \"from clcurv import io; io.read('{path}')\"\n"
            f"  or rebuild: test_hostile_fuzz.case_bytes({kind!r}, {case}, tmp_dir)")


def case_bytes(kind, case, tmp):
    """The mutated bytes of one case (deterministic from SEED, kind and case)."""
    ext, raw, hlen, fields = base_file(kind, Path(tmp))
    rng = np.random.default_rng([SEED, KINDS.index(kind), case])
    data, mutations = mutate(raw, hlen, fields, rng)
    return ext, data, mutations


@pytest.mark.parametrize("kind", KINDS)
def test_fuzz_headers(tmp_path, kind):
    if kind == "las":
        pytest.importorskip("laspy")
    ext, raw, hlen, fields = base_file(kind, tmp_path)
    assert cio.read(tmp_path / ("base" + ext)).points.shape == (N_BASE, 3)  # the base is valid
    worker, failures, counts = Worker(), [], {}
    try:
        for case in range(CASES):
            rng = np.random.default_rng([SEED, KINDS.index(kind), case])
            data, mutations = mutate(raw, hlen, fields, rng)
            path = tmp_path / f"case{case}{ext}"
            path.write_bytes(data)
            got = worker.read(path)
            counts[got["status"]] = counts.get(got["status"], 0) + 1
            if got["status"] == "bad":
                failures.append(_reproducer(kind, case, path, mutations, got["detail"]))
                if worker.p.poll() is not None:
                    worker = Worker()
            else:
                path.unlink()
    finally:
        worker.close()
    print(f"{kind}: {counts}")
    assert not failures, f"{len(failures)} of {CASES} cases failed:\n" + "\n".join(
        failures[:10])
