"""PDAL's ``filters.covariancefeatures`` run through the ``pdal`` command, for the bench
(bench.features) and the cross-check tests (tests/test_pdal.py).

PDAL is not a dependency of clcurv and has no wheel on PyPI: it comes with conda-forge's
``pdal``, Homebrew, or a distribution's package (Ubuntu 22.04's ``pdal`` 2.3; Debian 12
has none). The command is ``$CLCURV_PDAL`` when set (split like a shell line, e.g.
``chroot /srv/jammy pdal`` for a PDAL installed in another system's root, which must see
this machine's temporary directory at the same path), else ``pdal`` on the PATH.

The cloud goes to PDAL as a LAS 1.2 file written by laspy (coordinates stored as integers
times a scale: pass points that the scale holds exactly, or compare with the coordinates
PDAL read, which :func:`covariance_features` returns) and its features come back through
``writers.text`` with 17 significant digits, in the input's order.
"""
from __future__ import annotations

import csv
import json
import os
import shlex
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

#: PDAL's feature names (filters.covariancefeatures, 2.3 and later); Density needs the
#: optimal neighbourhood's dimensions and is left out; EigenvalueSum is not in 2.3
PDAL_FEATURES = ("Linearity", "Planarity", "Scattering", "Verticality", "Omnivariance",
                 "Anisotropy", "Eigenentropy", "EigenvalueSum", "SurfaceVariation",
                 "DemantkeVerticality")


def pdal_command():
    """(argv prefix of the pdal command, None) or (None, why it is unavailable)."""
    spec = os.environ.get("CLCURV_PDAL")
    found = shutil.which("pdal")
    cmd = shlex.split(spec) if spec else ([found] if found else None)
    if not cmd:
        return None, ("no pdal command: PDAL is not on the PATH and CLCURV_PDAL is not set "
                      "(PDAL has no PyPI wheel; conda-forge, Homebrew or Ubuntu 22.04's "
                      "package provide it)")
    try:
        out = subprocess.run(cmd + ["--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f"{' '.join(cmd)} --version failed: {exc}"
    if out.returncode:
        return None, f"{' '.join(cmd)} --version failed: {out.stderr.strip()[-200:]}"
    return cmd, None


def pdal_version(cmd):
    """The version string printed by ``pdal --version`` (e.g. '2.3.0')."""
    out = subprocess.run(cmd + ["--version"], capture_output=True, text=True, timeout=60)
    for word in out.stdout.split():
        if word[:1].isdigit() and word.count(".") >= 1:
            return word
    return out.stdout.strip()


def write_las(path, points):
    """``points`` (N, 3) as a LAS 1.2 file (point format 0), offsets at the bounding box's
    lower corner, the scale the power of ten that keeps the extent within int32 (1e-9 for a
    unit sphere); returns the coordinates as stored (float64)."""
    import laspy
    pts = np.asarray(points, dtype=np.float64)
    lo = np.floor(pts.min(axis=0))
    extent = float(np.max(pts.max(axis=0) - lo)) if len(pts) else 1.0
    scale = 10.0 ** np.ceil(np.log10(max(extent, 1e-300) / 2e9))
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.offsets = lo
    header.scales = np.array([scale] * 3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))
    back = laspy.read(str(path))
    return np.c_[back.x, back.y, back.z]


def run_pipeline(cmd, stages, workdir):
    """Run a pipeline (list of stage dicts) with ``cmd``; raises RuntimeError with PDAL's
    message on failure. Returns the wall time in seconds."""
    spec = Path(workdir) / f"pipeline_{time.monotonic_ns()}.json"
    spec.write_text(json.dumps(stages))
    t0 = time.perf_counter()
    out = subprocess.run(cmd + ["pipeline", str(spec)], capture_output=True, text=True,
                         timeout=3600)
    seconds = time.perf_counter() - t0
    if out.returncode:
        raise RuntimeError(f"pdal pipeline failed: {(out.stderr or out.stdout).strip()[-400:]}")
    return seconds


def _filter(las, radius, mode, threads, knn=None):
    opts = {"type": "filters.covariancefeatures", "feature_set": ",".join(PDAL_FEATURES),
            "mode": mode, "threads": int(threads), "min_k": 3}
    if knn is None:
        opts["radius"] = float(radius)
    else:
        opts["knn"] = int(knn)
    return [{"type": "readers.las", "filename": str(las)}, opts]


def covariance_features(cmd, points, radius, mode="Raw", threads=2, workdir=None, knn=None):
    """PDAL's covariance features of ``points`` in balls of ``radius`` (its KD-tree radius
    search, at least 3 points: min_k) or, with ``knn``, of each point's knn + 1 nearest
    points (itself included), ``mode`` 'Raw', 'SQRT' (PDAL's default) or 'Normalized'.
    Returns (coordinates PDAL read (N, 3), {feature: (N,) float64}) in the input's order; a
    point with fewer than 3 neighbours keeps PDAL's 0 in every field."""
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        las = Path(tmp) / "cloud.las"
        write_las(las, points)
        out = Path(tmp) / "features.csv"
        run_pipeline(cmd, _filter(las, radius, mode, threads, knn) + [
            {"type": "writers.text", "filename": str(out), "precision": 17}], tmp)
        with open(out, newline="") as f:
            header = next(csv.reader(f))
        data = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    cols = {name: data[:, i] for i, name in enumerate(header)}
    xyz = np.c_[cols["X"], cols["Y"], cols["Z"]]
    return xyz, {n: cols[n] for n in PDAL_FEATURES if n in cols}


def time_covariance_features(cmd, points, radius, threads=2, repeats=1, workdir=None):
    """Seconds of PDAL's filter on ``points`` (radius search, the features of PDAL_FEATURES
    in Raw mode, ``threads`` threads): the best pipeline time with the filter minus the
    best without it (reading the LAS file, writers.null), and the whole pipeline's."""
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        las = Path(tmp) / "cloud.las"
        write_las(las, points)
        null = [{"type": "writers.null"}]
        read = min(run_pipeline(cmd, [{"type": "readers.las", "filename": str(las)}] + null,
                                tmp) for _ in range(max(1, repeats)))
        full = min(run_pipeline(cmd, _filter(las, radius, "Raw", threads) + null, tmp)
                   for _ in range(max(1, repeats)))
    return {"seconds": full - read, "pipeline_seconds": full, "read_seconds": read}
