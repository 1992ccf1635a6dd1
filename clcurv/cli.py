"""The ``clcurv`` command line: compute, devices, render, demo.

    clcurv compute INPUT -o OUTPUT --method mls2 --radius auto --scale-space 3
    clcurv devices
    clcurv render OUTPUT.ply --field mean_curvature -o picture.png
    clcurv demo

Exit codes: 0 success, 1 unexpected error, 2 bad arguments, 3 unreadable input or
unwritable output, 4 no usable OpenCL device.
"""
from __future__ import annotations

import argparse
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

EXIT_ERROR, EXIT_USAGE, EXIT_IO, EXIT_DEVICE = 1, 2, 3, 4
SIGNED = ("mean_curvature", "gaussian_curvature", "k1", "k2")


class UsageError(Exception):
    """A bad argument value (exit code 2)."""


def auto_radius(points, k=30, sample=5000, seed=0):
    """Radius giving about ``k`` neighbours: the median over a random subsample of the
    distance to the k-th nearest other point."""
    from scipy.spatial import cKDTree
    if len(points) <= k:
        raise UsageError(f"--radius auto needs more than {k} points, the cloud has {len(points)}")
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(points), size=min(sample, len(points)), replace=False)
    d, _ = cKDTree(points).query(points[idx], k=k + 1)
    return float(np.median(d[:, -1]))


class Stages:
    """Times each stage; shows a tqdm bar per stage unless quiet."""

    def __init__(self, quiet):
        self.quiet, self.times = quiet, {}

    @contextmanager
    def stage(self, name, total=1):
        bar = None
        if not self.quiet:
            from tqdm import tqdm
            bar = tqdm(total=total, desc=f"{name:<14}", leave=True, file=sys.stderr,
                       bar_format="{desc} {bar} {n_fmt}/{total_fmt} [{elapsed}]")
        t = time.perf_counter()
        try:
            yield (bar.update if bar is not None else (lambda *a: None))
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t
            if bar is not None:
                bar.n = total
                bar.refresh()
                bar.close()


def result_fields(res, wanted=None):
    """Per-point output fields named as CloudCompare/MeshLab scalar fields."""
    f = {}
    if res.mean is not None:
        f["mean_curvature"] = res.mean
    if res.gaussian is not None:
        f["gaussian_curvature"] = res.gaussian
    if res.k1 is not None:
        f["k1"], f["k2"] = res.k1, res.k2
        for i, a in (("1", res.dir1), ("2", res.dir2)):
            f[f"dir{i}_x"], f[f"dir{i}_y"], f[f"dir{i}_z"] = a.T
    if res.variation is not None:
        f["surface_variation"] = res.variation
    f["neighbours"] = res.count.astype(np.int32)
    f["status"] = res.status.astype(np.uint8)
    if wanted:
        unknown = sorted(set(wanted) - set(f) - {"normals"})
        if unknown:
            raise UsageError(f"unknown field(s) {', '.join(unknown)} for method {res.method}; "
                             f"available: normals, {', '.join(f)}")
        f = {k: v for k, v in f.items() if k in wanted}
    return f


def _range(v):
    ok = np.isfinite(v)
    if not ok.any():
        return "all NaN"
    lo, med, hi = np.percentile(v[ok], [1, 50, 99])
    nan = f", {np.count_nonzero(~ok)} NaN" if not ok.all() else ""
    return f"p1 {lo:.4g}  median {med:.4g}  p99 {hi:.4g}{nan}"


def compute(args, out=print):
    import clcurv
    from clcurv import io
    st = Stages(args.quiet)
    with st.stage("reading"):
        cloud = io.read(args.input)
    pts = cloud.points
    if args.radius == "auto":
        radius = auto_radius(pts)
        out(f"radius auto: {radius:.6g} (median distance to the 30th neighbour)")
    else:
        try:
            radius = float(args.radius)
        except ValueError:
            raise UsageError(f"--radius must be a number or 'auto', got {args.radius!r}") from None
        if not np.isfinite(radius) or radius <= 0:
            raise UsageError(f"--radius must be positive, got {args.radius}")
    dev = clcurv.get_device(args.device)
    normals = cloud.normals if (cloud.normals is not None and np.isfinite(cloud.normals).all()
                                and not args.ignore_normals) else None
    common = dict(weights=args.weights, device=dev, precision=args.precision)
    work = pts
    if args.scale_space:
        with st.stage("scale space", total=args.scale_space) as tick:
            work = clcurv.scale_space(pts, radius, args.scale_space, progress=tick, **common)
    with st.stage(args.method):
        res = clcurv.curvature(work, radius, method=args.method, normals=normals,
                               viewpoint=args.viewpoint, kernel=args.kernel, **common)
    fields = result_fields(res, args.fields)
    write_normals = None if args.fields and "normals" not in args.fields else res.normals
    positions = pts if args.positions == "original" else (res.points if res.points is not None else work)
    with st.stage("writing"):
        io.write(args.output, positions, fields=fields, normals=write_normals, like=cloud)
    out(f"\n{len(pts)} points from {args.input}" + (f" ({cloud.dropped} non-finite dropped)" if cloud.dropped else ""))
    out(f"method {args.method}, radius {radius:.6g}, scale space {args.scale_space} iteration(s), "
        f"weights {args.weights}")
    out(f"mean neighbours {res.count.mean():.1f} (median {np.median(res.count):.0f}); "
        f"status ok {np.mean(res.valid):.1%}")
    out(f"device {dev.info.name} ({dev.info.platform})")
    out("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in st.times.items()))
    for k, v in fields.items():
        if k in SIGNED or k == "surface_variation":
            out(f"  {k:<20} {_range(v)}")
    out(f"wrote {args.output}: {', '.join((['nx ny nz'] if write_normals is not None else []) + list(fields))}")
    res.info["input_points"] = pts
    return res


def render_cmd(args, out=print):
    from clcurv import io
    from clcurv.render import render
    cloud = io.read(args.input)
    values = cloud.attributes.get(args.field)
    if values is None:
        raise UsageError(f"{args.input} has no field {args.field!r}; it has: "
                         f"{', '.join(cloud.attributes) or 'none'}")
    path = render(cloud.points, np.asarray(values, dtype=float), args.output, field=args.field,
                  unit=args.unit)
    out(f"wrote {path}")
    return path


def devices_cmd(args, out=print):
    import clcurv
    devs = clcurv.devices()
    if not devs:
        raise clcurv.NoDeviceError(clcurv.device.APT_HINT)
    default = clcurv.get_device().info.index
    for d in devs:
        mark = "*" if d.index == default else " "
        out(f"{mark} {d.index}: {d.name} | {d.platform} | {d.kind} | driver {d.driver} | "
            f"fp64 {'yes' if d.fp64 else 'no'} | {d.global_mem / 2**30:.1f} GiB")
    out("(* = default; choose with --device or CLCURV_DEVICE)")


def demo_cmd(args, out=print):
    from clcurv.demo import sample_path
    outdir = Path(args.outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    ns = argparse.Namespace(input=str(sample_path()), output=str(outdir / "bunny_mls2.ply"),
                            method="mls2", radius="auto", scale_space=3, weights="uniform",
                            device=args.device, precision="float", fields=None, kernel="ball",
                            viewpoint=None, positions="original", ignore_normals=False,
                            quiet=args.quiet)
    out(f"demo: the bundled Stanford bunny ({ns.input}), the paper's pipeline: "
        "3 MLS1 scale-space iterations, then MLS2")
    res = compute(ns, out)
    try:
        from clcurv.render import render
    except ImportError:
        out("matplotlib is not installed: no picture (pip install matplotlib)")
        return res
    png = render(res.info["input_points"], res.mean, outdir / "bunny_mean_curvature.png",
                 field="mean_curvature", unit="1/m")
    out(f"wrote {png}")
    return res


def build_parser():
    p = argparse.ArgumentParser(prog="clcurv", description="Curvatures of raw point clouds "
                                "(Digne & Morel operators, OpenCL).")
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("compute", help="compute an operator on a point cloud file")
    c.add_argument("input")
    c.add_argument("-o", "--output", required=True, help=".ply, .las/.laz, .npz, .csv, .txt")
    c.add_argument("--method", default="mls2", choices=["variation", "mls0", "mls1", "2dcov1",
                                                         "2dcov2", "3dcov", "mls2"])
    c.add_argument("--radius", default="auto", help="ball radius in the file's unit, or 'auto' "
                   "(about 30 neighbours)")
    c.add_argument("--scale-space", type=int, default=0, metavar="N",
                   help="MLS1 scale-space iterations first (the paper's pipeline)")
    c.add_argument("--weights", default="uniform", choices=["uniform", "density"])
    c.add_argument("--kernel", default="ball", choices=["ball", "gaussian"], help="MLS2 weights")
    c.add_argument("--device", default=None, help="index, 'platform:device' or name substring")
    c.add_argument("--precision", default="float", choices=["float", "double"])
    c.add_argument("--fields", nargs="+", default=None, help="fields to write (default: all)")
    c.add_argument("--viewpoint", nargs=3, type=float, default=None, metavar=("X", "Y", "Z"),
                   help="orient normals towards this scanner position (default: MST propagation)")
    c.add_argument("--positions", default="original", choices=["original", "projected"],
                   help="write the input positions or the smoothed/projected ones")
    c.add_argument("--ignore-normals", action="store_true",
                   help="do not use normals stored in the input file")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub.add_parser("devices", help="list the OpenCL devices")
    r = sub.add_parser("render", help="PNG of a cloud coloured by a field")
    r.add_argument("input")
    r.add_argument("--field", default="mean_curvature")
    r.add_argument("--unit", default="1/length")
    r.add_argument("-o", "--output", required=True)
    d = sub.add_parser("demo", help="run the pipeline on the bundled bunny")
    d.add_argument("--outdir", default="out")
    d.add_argument("--device", default=None)
    d.add_argument("-q", "--quiet", action="store_true")
    return p


def _fail(code, msg):
    print(f"clcurv: error: {msg}", file=sys.stderr)
    return code


def main(argv=None):
    import clcurv
    from clcurv import io
    args = build_parser().parse_args(argv)
    run = {"compute": compute, "devices": devices_cmd, "render": render_cmd, "demo": demo_cmd}
    try:
        run[args.command](args)
    except UsageError as e:
        return _fail(EXIT_USAGE, str(e))
    except (io.ReadError, io.WriteError, OSError) as e:
        return _fail(EXIT_IO, str(e))
    except clcurv.NoDeviceError as e:
        return _fail(EXIT_DEVICE, str(e))
    except clcurv.PrecisionError as e:
        return _fail(EXIT_DEVICE, str(e))
    except (ValueError, TypeError) as e:
        return _fail(EXIT_USAGE, str(e))
    except ImportError as e:
        return _fail(EXIT_ERROR, str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
