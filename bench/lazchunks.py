"""LAZ output from pieces (clcurv.io.pieces, issue 50) against laspy's one-process write.

    python -m bench.lazchunks [--points 5000000] [--pieces 2] [--folder /tmp] [--json out.json]

The cloud: point format 6 with 13 float32 extra-bytes fields (a clcurv curvature output:
smooth functions of the coordinates plus noise), made in each process block by block from
seeds, so that workers get no arrays from the client. Timed: laspy writing the whole cloud
in one process (backends Lazrs and LazrsParallel); ``--pieces`` worker processes each
writing its window (:func:`windows`) with :func:`write_piece` (the slowest worker's wall
and CPU time, and the wall time of the phase with the points' generation); :func:`assemble`
with and without the CRC check, against a plain copy of the output file (with and without
fsync: assemble fsyncs, being atomic). The load average is recorded before and after: on
shared cores, compare CPU times. Each run checks that the assembled file holds laspy's
points, and whether it is laspy's file byte for byte (it is, with aligned windows).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

from clcurv.io.pieces import CHUNK_SIZE, assemble, windows, write_piece

FIELDS = 13


def header():
    h = laspy.LasHeader(point_format=6, version="1.4")
    h.add_extra_dims([laspy.ExtraBytesParams(f"f{i}", np.float32) for i in range(FIELDS)])
    h.scales = np.array([0.001, 0.001, 0.001])
    h.offsets = np.array([481200.0, 4390100.0, 0.0])
    return h


def cloud(h, start, stop, n, seed=0):
    """Points start..stop-1 of an n-point aerial-like cloud, made block by block (blocks of
    CHUNK_SIZE points, each from its own seed): the windows of :func:`windows` give the
    same points as the whole."""
    blocks = [_block(h, a, min(a + CHUNK_SIZE, stop), n, seed)
              for a in range(start, stop, CHUNK_SIZE)]
    arr = np.concatenate([b.array for b in blocks]) if blocks else \
        np.zeros(0, h.point_format.dtype())
    return laspy.ScaleAwarePointRecord(arr, h.point_format, h.scales, h.offsets)


def _block(h, start, stop, n, seed):
    m = stop - start
    rng = np.random.default_rng([seed, start])
    rec = laspy.ScaleAwarePointRecord.zeros(m, header=h)
    side = int(np.sqrt(n)) + 1
    i = np.arange(start, stop)
    x = (i % side) * 0.5 + rng.uniform(0, 0.5, m)
    y = (i // side) * 0.5 + rng.uniform(0, 0.5, m)
    rec.x, rec.y = 481200.0 + x, 4390100.0 + y
    rec.z = 12 + 3 * np.sin(x / 7) * np.cos(y / 11) + rng.normal(0, 0.05, m)
    rec.intensity = rng.integers(0, 4000, m)
    rec.return_number = rec.number_of_returns = np.ones(m, np.uint8)
    rec.classification = np.full(m, 2, np.uint8)
    rec.gps_time = 3e8 + i * 1e-5
    for k in range(FIELDS):
        rec[f"f{k}"] = (np.sin(x / (3 + k)) * np.cos(y / (5 + k))
                        + rng.normal(0, 0.01, m)).astype(np.float32)
    return rec


def _worker(args):
    path, start, stop, n = args
    h = header()
    rec = cloud(h, start, stop, n)
    t0, c0 = time.perf_counter(), time.process_time()
    write_piece(path, h, rec)
    return time.perf_counter() - t0, time.process_time() - c0


def best_of(f, repeat, cpu=None):
    """The best wall time of ``repeat`` calls of ``f``; with a dict ``cpu``, its ``"cpu"``
    entry is the best CPU time of this process."""
    times, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        f()
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    if cpu is not None:
        cpu["cpu"] = min(cpus)
    return min(times)


def copy_and_sync(src, dst):
    shutil.copyfile(src, dst)
    fd = os.open(dst, os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=5_000_000)
    ap.add_argument("--pieces", type=int, default=2)
    ap.add_argument("--folder", default=None)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    n = a.points
    folder = Path(tempfile.mkdtemp(prefix="lazchunks-", dir=a.folder))
    res = {"points": n, "pieces": a.pieces, "fields": FIELDS, "cores": os.cpu_count(),
           "load_before": round(os.getloadavg()[0], 2)}
    try:
        h = header()
        rec = cloud(h, 0, n, n)
        ref = folder / "ref.laz"
        for name, backend in (("laspy_lazrs", laspy.LazBackend.Lazrs),
                              ("laspy_lazrs_parallel", laspy.LazBackend.LazrsParallel)):
            las = laspy.LasData(header(), points=rec)
            cpu = {}
            res[name] = best_of(lambda: las.write(str(ref), laz_backend=backend), a.repeat, cpu)
            res[name + "_cpu"] = cpu["cpu"]
        del las, rec
        paths = [folder / f"p{i}.lazpiece" for i in range(a.pieces)]
        bounds = windows(n, a.pieces)
        with concurrent.futures.ProcessPoolExecutor(a.pieces) as pool:
            pool.submit(int, 0).result()                 # processes started
            walls, slowest, cpus = [], [], []
            for _ in range(a.repeat):
                t0 = time.perf_counter()
                worker = list(pool.map(_worker, [(str(p), s, e, n)
                                                 for p, (s, e) in zip(paths, bounds)]))
                walls.append(time.perf_counter() - t0)
                slowest.append(max(w for w, _ in worker))
                cpus.append(max(c for _, c in worker))
        res["pieces_write_slowest_worker"] = min(slowest)
        res["pieces_write_slowest_worker_cpu"] = min(cpus)
        res["pieces_phase_wall_incl_generation"] = min(walls)
        out = folder / "out.laz"
        res["assemble_verify"] = best_of(lambda: assemble(out, h, paths), a.repeat)
        res["assemble_no_verify"] = best_of(lambda: assemble(out, h, paths, verify=False),
                                            a.repeat)
        res["plain_copy"] = best_of(lambda: shutil.copyfile(out, folder / "copy.laz"),
                                    a.repeat)
        res["plain_copy_fsync"] = best_of(lambda: copy_and_sync(out, folder / "copy2.laz"),
                                          a.repeat)
        res["bytes_assembled"] = out.stat().st_size
        res["bytes_laspy"] = ref.stat().st_size
        res["bytes_pieces"] = sum(p.stat().st_size for p in paths)
        got, want = laspy.read(str(out)), laspy.read(str(ref))
        res["same_points"] = bool(np.array_equal(got.points.array.view(np.uint8),
                                                 want.points.array.view(np.uint8)))
        res["same_bytes_as_laspy"] = out.read_bytes() == ref.read_bytes()
    finally:
        shutil.rmtree(folder)
    res["load_after"] = round(os.getloadavg()[0], 2)
    rows = [(k, f"{v:.3f} s" if isinstance(v, float) and not k.startswith("load") else
             str(v)) for k, v in res.items()]
    print("| measure | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
