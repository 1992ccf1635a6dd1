"""Every result array of a broad set of calls, saved, or compared bit for bit with a saved
set: the check that a refactor changed no output.

    python -m bench.golden save  /tmp/before.npz     # on the commit before the change
    python -m bench.golden check /tmp/before.npz     # after it: exit 1 on any difference

The set: every method (and weighting, user normals, k-NN radius, MLS2's options, float64),
the scale space, normals and projections, features at one and three radii and at the k-NN
radius, optimal radii, and tiled runs of curvature_file and features_file (NPZ outputs read
back). Uses the public API only, so it runs unchanged across a reorganisation of the
modules. One device: CLCURV_DEVICE, else the default.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

import clcurv


def _arrays(prefix, obj, out):
    if isinstance(obj, dict):
        for k, v in obj.items():
            _arrays(f"{prefix}.{k}", v, out)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _arrays(f"{prefix}[{i}]", v, out)
    elif hasattr(obj, "__dataclass_fields__") or hasattr(obj, "values") and hasattr(obj, "count"):
        names = getattr(obj, "__dataclass_fields__", None) or vars(obj)
        for k in names:
            if k not in ("info", "timings"):
                _arrays(f"{prefix}.{k}", getattr(obj, k), out)
    elif isinstance(obj, np.ndarray) or np.isscalar(obj) and not isinstance(obj, str):
        out[prefix] = np.asarray(obj)


def results():
    torus = clcurv.shapes.torus(20000, 1.0, 0.3, noise=1e-3, seed=5)
    pts, nrm = torus["points"], torus["normals"]
    scene = clcurv.shapes.aerial_scene(20000)["points"]
    out = {}
    for m in clcurv.METHODS:
        for w in ("uniform", "density"):
            _arrays(f"{m}.{w}", clcurv.curvature(pts, 0.12, method=m, weights=w), out)
        _arrays(f"{m}.user_normals", clcurv.curvature(pts, 0.12, method=m, normals=nrm), out)
        _arrays(f"{m}.knn", clcurv.curvature(pts, method=m, k=30), out)
        _arrays(f"{m}.double", clcurv.curvature(pts, 0.12, method=m, precision="double"), out)
    _arrays("mls2.gauss", clcurv.curvature(pts, 0.12, method="mls2", kernel="gaussian",
                                           h=0.05, projections=2), out)
    _arrays("mls2.scale_space", clcurv.curvature(pts, 0.12, method="mls2", scale_space=2), out)
    _arrays("scene.mls2", clcurv.curvature(scene, 2.0, method="mls2", orient="up"), out)
    _arrays("scene.mst", clcurv.curvature(scene, 2.0, method="mls1", orient="mst"), out)
    _arrays("scale_space", clcurv.scale_space(pts, 0.06, 3), out)
    _arrays("normals", clcurv.normals(pts, 0.12), out)
    _arrays("normals.knn", clcurv.normals(pts, k=20), out)
    _arrays("project", clcurv.project(pts, 0.12), out)
    _arrays("features.1", clcurv.features(pts, 0.12, "all"), out)
    _arrays("features.3", clcurv.features(pts, [0.05, 0.085, 0.12], "all"), out)
    _arrays("features.knn", clcurv.features(pts, k=20, features="all"), out)
    _arrays("features.optimal", clcurv.features(pts, [0.05, 0.085, 0.12], "all",
                                                optimal=True), out)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "scene.npy"
        np.save(src, scene)
        for name, call in (
                ("tiled.mls2", lambda o: clcurv.curvature_file(src, o, 2.0, method="mls2",
                                                               tile=30.0)),
                ("tiled.mst", lambda o: clcurv.curvature_file(src, o, 2.0, method="mls1",
                                                              orient="mst", tile=30.0)),
                ("tiled.scale_space", lambda o: clcurv.curvature_file(
                    src, o, 2.0, method="mls1", scale_space=2, tile=30.0)),
                ("tiled.features", lambda o: clcurv.features_file(src, o, [1.5, 2.5], "all",
                                                                  tile=30.0))):
            dst = Path(tmp) / f"{name}.npz"
            call(dst)
            with np.load(dst) as z:
                _arrays(name, dict(z), out)
    return out


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2 or argv[0] not in ("save", "check"):
        raise SystemExit(__doc__)
    got = results()
    if argv[0] == "save":
        np.savez_compressed(argv[1], **got)
        print(f"{len(got)} arrays saved to {argv[1]}")
        return 0
    want = dict(np.load(argv[1]))
    bad = sorted(k for k in want.keys() | got.keys() if k not in want or k not in got
                 or want[k].shape != got[k].shape
                 or not np.array_equal(want[k], got[k], equal_nan=True))
    for k in bad[:40]:
        print("DIFFERS:", k)
    print(f"{len(want)} arrays saved, {len(got)} now, {len(bad)} differ")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
