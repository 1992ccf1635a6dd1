"""The ``clcurv`` command line: compute, features, devices, render, demo.

    clcurv compute INPUT -o OUTPUT --method mls2 --radius auto --scale-space 3
    clcurv compute tiles/ -o out/ --method mls2 --radius 1     # a catalog: folder, .vpc, files
    clcurv features INPUT -o OUTPUT --radius 0.5,1,2 --features planarity,Scattering
    clcurv devices
    clcurv render OUTPUT.ply --field mean_curvature -o picture.png [--up z]
    clcurv demo

This module parses the arguments and maps errors to exit codes; the work is done by
:mod:`clcurv.jobs.job` (compute), :mod:`clcurv.cli.demo` and :mod:`clcurv.render`. Radii and ``--h``
are in the file's length unit, curvatures in 1/length (see :mod:`clcurv.ops.registry`).

Exit codes: 0 success, 1 unexpected error, 2 bad arguments (including a radius the data
cannot take: a far outlier, a ball holding most of the cloud), 3 unreadable input or
unwritable output, 4 no usable OpenCL device, 5 out of memory (host or device), 130
interrupted. Every failure is one ``clcurv: error: ...`` line on stderr, and every warning
one ``clcurv: warning: ...`` line.
"""
from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

from clcurv._shared.options import EXCLUSIVE, OPTIONS
from clcurv.cli import demo
from clcurv import io
from clcurv.jobs import job
from clcurv.runtime.device import APT_HINT, NoDeviceError, devices
from clcurv.jobs.job import UsageError
from clcurv.api.features import DEFAULT_FEATURES as FEATURE_NAMES
from clcurv.api.inputs import parse_knn
from clcurv.ops.registry import METHODS
from clcurv.runtime.program import BuildError, PrecisionError
from clcurv.jobs.tiled_job import tile_session
from clcurv.render import check_image_output, render
from clcurv.jobs.job import features_file
from clcurv.io.stream import is_catalog
from clcurv.tiles.planning import TilingError, check_tile_size
from clcurv.tiles.workers import CONNECT_TIMEOUT, FORCE_WORKERS
from clcurv.tiles.workspace import WorkspaceError

EXIT_ERROR, EXIT_USAGE, EXIT_IO, EXIT_DEVICE, EXIT_MEMORY = 1, 2, 3, 4, 5
EXIT_INTERRUPTED = 130


def _knn_alias(args, default):
    """``--radius knn:K``, the API's spelling (``radius="knn:K"``), as ``--k K``: args.k set,
    args.radius back to ``default``."""
    spec = args.radius
    if not (isinstance(spec, str) and spec.strip().lower().startswith("knn:")):
        return
    if args.k is not None:
        raise UsageError("give --radius knn:K or --k K, not both")
    try:
        args.k = parse_knn(spec.strip().lower(), None)
    except ValueError:
        raise UsageError(f"--radius knn:K needs an integer K, got {spec!r}") from None
    args.radius = default


def compute(args, out=print):
    """``clcurv compute``: run the file job of ``args``; return its :class:`clcurv.jobs.job.Done`."""
    _knn_alias(args, "auto")
    return job.run(job.Job.from_args(args), out)


def render_cmd(args, out=print):
    """``clcurv render``: PNG of a file's points coloured by one of its fields."""
    check_image_output(args.output)         # before reading: never a picture over a cloud
    cloud = io.read(args.input)
    values = cloud.attributes.get(args.field)
    if values is None:
        raise UsageError(f"{args.input} has no field {args.field!r}; it has: "
                         f"{', '.join(cloud.attributes) or 'none'}")
    se = None
    if args.se != "none":
        name = f"{args.field}_se" if args.se == "auto" else args.se
        se = cloud.attributes.get(name)
        if se is None and args.se != "auto":
            raise UsageError(f"{args.input} has no field {name!r} (--se); it has: "
                             f"{', '.join(cloud.attributes) or 'none'}")
    path = render(cloud.points, np.asarray(values, dtype=float), args.output, field=args.field,
                  unit=args.unit, up=args.up, source=args.input,
                  se=None if se is None else np.asarray(se, dtype=float))
    out(f"wrote {path}")
    return path


def features_cmd(args, out=print):
    """``clcurv features``: covariance features (:func:`clcurv.features_file`) of a file's
    points at one radius, several (fields named ``<feature>_r<radius>``), a k-NN radius
    (plus a ``knn_radius`` field) or each point's optimal radius among several
    (``--optimal``, plus an ``optimal_radius`` field), written with the input's points
    (LAS/LAZ: header kept); in tiles when the cloud does not fit ``--memory`` (or with
    ``--tile-size``, ``--workers``, ``--scheduler``), with the same output."""
    inputs = args.input if len(args.input) > 1 else args.input[0]
    _knn_alias(args, None)
    if (args.radius is None) == (args.k is None):
        raise UsageError("give --radius R[,R2,...] or --k K")
    try:
        radius = None if args.radius is None else [float(r) for r in args.radius.split(",")]
    except ValueError:
        raise UsageError(f"--radius takes numbers separated by commas, got {args.radius!r}")
    if args.optimal and (radius is None or len(radius) < 2):
        raise UsageError("--optimal chooses among radii: give --radius R1,R2[,...]")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if radius is not None and len(radius) == 1:
        radius = radius[0]
    try:
        with tile_session(args.quiet, args.scheduler) as (progress, client):
            done = features_file(
                inputs, args.output, radius, args.features, k=args.k, ddof=args.ddof,
                optimal=args.optimal, memory=args.memory, tile=args.tile_size,
                device=args.device, precision=args.precision, progress=progress,
                out=None if args.quiet else (lambda s: print(s, file=sys.stderr)),
                client=client, workers=args.workers, workdir=args.workdir)
    except TilingError as exc:
        raise UsageError(str(exc)) from exc
    nf = len(done["fields"]) - ("normals" in done["fields"])
    tiles = f" in {done['tiles']} tile(s)" if done["tiled"] else ""
    dropped = done.get("dropped", 0)
    dropped = f" ({dropped} non-finite dropped)" if dropped else ""
    index = f" and the index {done['index']}" if done.get("index") else ""
    out(f"wrote {args.output if is_catalog(inputs) else done['dst']}: {done['points']} "
        f"points{dropped}, {nf} fields{tiles}{index}")
    return done["dst"]


def devices_cmd(args, out=print):
    """``clcurv devices``: one line per OpenCL device, the default marked ``*`` and why,
    simulators marked, then the ICD files the loader read."""
    devs = devices()
    if not devs:
        raise NoDeviceError(APT_HINT + "; ICD folders read: " + ", ".join(devs.vendors))
    for d in devs:
        mark = "*" if d.index == devs.default else " "
        sim = " | simulator: used only when named" if d.simulator else ""
        out(f"{mark} {d.index}: {d.name} | {d.platform} | {d.kind} | driver {d.driver} | "
            f"fp64 {'yes' if d.fp64 else 'no'} | {d.global_mem / 2**30:.1f} GiB{sim}")
    out(f"* = default: {devs.reason}" if devs.default is not None
        else f"no default device: {devs.reason}")
    out("choose with --device (index, 'platform:device', kind, or platform/device name) "
        "or CLCURV_DEVICE")
    out("ICD files read (OCL_ICD_VENDORS, else /etc/OpenCL/vendors; and pyopencl's own):")
    for icd in devs.icds:
        out(f"  {icd}")
    idle = devs.idle_venv_icds
    if idle:
        out(f"  not read: {len(idle)} ICD file(s) in {idle[0].rsplit('/', 1)[0]} "
            f"(export OCL_ICD_VENDORS={idle[0].rsplit('/', 1)[0]} to use them)")


def demo_cmd(args, out=print):
    """``clcurv demo``: :func:`clcurv.cli.demo.run`."""
    return demo.run(args.outdir, device=args.device, quiet=args.quiet, out=out)


def _tile_size(text):
    """``--tile-size``: a finite length > 0, refused before any work."""
    try:
        return check_tile_size(text)
    except TilingError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _workers(text):
    """``--workers``: an integer >= 1."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return n


#: the command line's converters of the declaration's named types, and what the
#: declaration leaves to the layers above it: the registry's methods, the default features
_CONVERTERS = {"tile size": _tile_size, "workers": _workers}
_RESOLVED = {"method": {"choices": list(METHODS)},
             "features": {"default": ",".join(FEATURE_NAMES)}}
_HELP_VALUES = {"force_workers": FORCE_WORKERS, "connect_timeout": CONNECT_TIMEOUT}


def add_options(c, command):
    """The arguments of ``command`` ("compute" or "features") from the options' declaration
    (:data:`clcurv._shared.options.OPTIONS`): flag, type, default, choices, metavar and
    help; ``--workers`` and ``--scheduler`` exclusive."""
    group = c.add_mutually_exclusive_group() if command in ("compute", "features") else None
    for opt in OPTIONS.values():
        kw = opt.cli(command)
        if kw is None:
            continue
        kw.update(_RESOLVED.get(opt.name, {}))
        kw["type"] = _CONVERTERS.get(kw.get("type"), kw.get("type"))
        if kw.get("type") is None:
            kw.pop("type", None)
        if kw.get("help"):
            kw["help"] = kw["help"].format(**_HELP_VALUES)
        flags = [f for f in (opt.short, opt.flag) if f]
        (group if opt.name in EXCLUSIVE else c).add_argument(*flags, **kw)


def _compute_parser(sub):
    c = sub.add_parser("compute", help="compute an operator on a point cloud file",
                       allow_abbrev=False)
    _file_arguments(c)
    add_options(c, "compute")


def _file_arguments(c):
    """input (one file, or several as one cloud) and -o: the file commands' arguments."""
    c.add_argument("input", nargs="+", help="a point cloud file; several LAS/LAZ (or NPY) "
                   "files, a folder of LAS/LAZ files (sorted by name) or a .vpc are one "
                   "cloud (a catalog), run in tiles: one output per input file and an "
                   "index .vpc in the folder -o")
    c.add_argument("-o", "--output", required=True, help=".ply, .las/.laz, .npz, .csv, .txt "
                   "(a folder for a catalog)")


def build_parser():
    # no abbreviations: a prefix is taken for the one option it begins (`--k 30` was taken
    # for --kernel before compute had --k)
    p = argparse.ArgumentParser(prog="clcurv", allow_abbrev=False,
                                description="Curvatures of raw point clouds "
                                "(Digne & Morel operators, OpenCL).")
    sub = p.add_subparsers(dest="command", required=True)
    _compute_parser(sub)
    sub.add_parser("devices", help="list the OpenCL devices", allow_abbrev=False)
    r = sub.add_parser("render", help="PNG of a cloud coloured by a field", allow_abbrev=False)
    r.add_argument("input")
    r.add_argument("--field", default="mean_curvature")
    r.add_argument("--unit", default="auto", help="the colour bar's unit (default: the "
                   "field's own when clcurv wrote it: 1/length for curvatures, none for "
                   "planarity...; none for other fields)")
    r.add_argument("--up", default="auto", help="the cloud's up axis: auto (default: z for "
                   "LAS/LAZ, the thin axis of a flat cloud, else y), x, y, z, -z, ...; "
                   "terrain is drawn from the top and obliquely")
    r.add_argument("--se", default="auto", metavar="FIELD", help="standard errors of the "
                   "field: its points with |value| < 2 SE (not significant) are drawn grey. "
                   "auto (default): the field <field>_se when the file has it (clcurv compute "
                   "--uncertainty writes them); none: colour every point")
    r.add_argument("-o", "--output", required=True)
    f = sub.add_parser("features", help="covariance features (planarity, linearity, ...)",
                       allow_abbrev=False)
    _file_arguments(f)
    add_options(f, "features")
    d = sub.add_parser("demo", help="run the pipeline on the bundled bunny", allow_abbrev=False)
    d.add_argument("--outdir", default="out")
    d.add_argument("--device", default=None)
    d.add_argument("-q", "--quiet", action="store_true")
    return p


#: exception types -> exit code, the first match wins (io errors are also ValueError or
#: ImportError)
_EXIT_CODES = ((MemoryError, EXIT_MEMORY), (UsageError, EXIT_USAGE), (io.ReadError, EXIT_IO),
               (io.WriteError, EXIT_IO), (WorkspaceError, EXIT_IO),
               (OSError, EXIT_IO), (NoDeviceError, EXIT_DEVICE), (PrecisionError, EXIT_DEVICE),
               (BuildError, EXIT_DEVICE),
               (ValueError, EXIT_USAGE), (TypeError, EXIT_USAGE), (ImportError, EXIT_ERROR))


def _fail(code, msg):
    print(f"clcurv: error: {msg}", file=sys.stderr)
    return code


def _message(e):
    """The one-line message of ``e`` (a bare MemoryError has none)."""
    text = " ".join(str(e).split())
    if isinstance(e, MemoryError) and text:
        return f"out of memory: {text}"        # DeviceMemoryError says what fits
    if isinstance(e, MemoryError):
        return ("out of memory (the cloud and its outputs do not fit this machine's RAM; "
                "use a machine with more memory, or split the cloud into tiles)")
    return text or type(e).__name__


def _warn_line(message, category, filename, lineno, file=None, line=None):
    """``warnings.showwarning`` of the command: one line, no Python file or source text."""
    print(f"clcurv: warning: {' '.join(str(message).split())}", file=sys.stderr)


def _glue_negative_axes(argv):
    """``--up -z`` as ``--up=-z``: argparse takes a value starting with '-' for an option
    (docs/methods.md spells the axes x, y, z, -x, -y, -z)."""
    out = []
    for a in argv:
        if out and out[-1] == "--up" and a in ("-x", "-y", "-z"):
            out[-1] = f"--up={a}"
        else:
            out.append(a)
    return out


def main(argv=None):
    """Entry point of the ``clcurv`` command; returns the exit code."""
    argv = _glue_negative_axes(sys.argv[1:] if argv is None else [str(a) for a in argv])
    args = build_parser().parse_args(argv)
    run = {"compute": compute, "devices": devices_cmd, "render": render_cmd, "demo": demo_cmd,
           "features": features_cmd}
    with warnings.catch_warnings():
        warnings.showwarning = _warn_line
        try:
            run[args.command](args)
        except tuple(t for t, _ in _EXIT_CODES) as e:
            return _fail(next(c for t, c in _EXIT_CODES if isinstance(e, t)), _message(e))
        except KeyboardInterrupt:
            return _fail(EXIT_INTERRUPTED, "interrupted")
    return 0


if __name__ == "__main__":
    sys.exit(main())
