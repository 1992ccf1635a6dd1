"""Every compute option, declared once: its name, type, default(s), allowed values, help
text, the methods that take it and its command-line flag.

The table :data:`OPTIONS` feeds

* the API's checks (:func:`allowed`, :func:`check`: the allowed values and the message of a
  bad one) in :mod:`clcurv.api.curvature`, :mod:`clcurv.api.features`,
  :mod:`clcurv.ops.smoothing` and :mod:`clcurv.jobs.job`;
* which methods take a method-specific option (``methods``): the registry's
  ``Operator.options`` (:mod:`clcurv.ops.registry`) are read from it;
* the command line: the arguments of ``clcurv compute`` and ``clcurv features`` and their
  ``--help`` are generated from it (:func:`clcurv.cli.main.add_options`);
* the file job: the defaults of :class:`clcurv.jobs.job.Job` (:func:`job_default`), and the
  tile parameters (:class:`clcurv.tiles.engine.CurvatureParams`) and the mapping of a job
  onto :func:`clcurv.curvature_file` take their names from it;

as a PDAL stage's ``addArgs`` feeds its pipeline and its command line.

Two defaults differ between the API and the file job (the command line,
:class:`~clcurv.jobs.job.Job`, :func:`clcurv.curvature_file`), and the table says both:
``method`` (the API's ``"mls1"``, the file job's ``"mls2"``) and ``radius`` (the API's none,
``clcurv compute``'s ``"auto"``). ``orient`` takes API values and command-line spellings
(``"none"`` for None; :data:`Option.cli_choices`).

Imports only :mod:`clcurv._shared.validate` (floor 0): the methods themselves are the
registry's (``choices=METHODS_OF_REGISTRY`` says so; the layers above resolve it), and the
default features the features table's (``features=None`` is them in the API; the command
line writes them out).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from clcurv._shared.validate import choice

#: ``Option.choices`` of ``method``: the registry's methods (:data:`clcurv.ops.registry.METHODS`),
#: which this floor cannot import; :func:`clcurv.api.inputs.allowed` resolves it
METHODS_OF_REGISTRY = "the registry's methods"
#: ``Option.file_default`` when the file job's default is the API's
SAME = object()


@dataclass(frozen=True)
class Option:
    """One compute option.

    ``name``: the API's keyword (:func:`clcurv.curvature`, :func:`clcurv.features`,
    :func:`clcurv.curvature_file`, ...); ``type``: the command line's converter (None: a
    flag, or a string; a name, "tile size" or "workers", for a converter the command line
    takes from the tiles); ``default``: the API's default; ``file_default``: the file job's
    (``clcurv compute``, :class:`~clcurv.jobs.job.Job`, :func:`clcurv.curvature_file`) when it
    differs, else :data:`SAME`; ``choices``: the allowed values (None: any of the type);
    ``cli_choices``: the command line's spellings -> the API's values, when they differ;
    ``help``: the ``--help`` text; ``methods``: the methods that take it (None: every
    method); ``flag`` (and a ``short`` one), ``metavar``, ``nargs``, ``action``: its
    command-line argument (no flag: not on the command line); ``commands``: the commands
    that take it; ``job``: its :class:`~clcurv.jobs.job.Job` field (None: not a job
    option); ``per_command``: another ``default``, ``help`` or ``metavar`` in a command
    (``{"features": {...}}``).
    """
    name: str
    type: object = None
    default: object = None
    file_default: object = SAME
    choices: tuple | str | None = None
    cli_choices: dict | None = None
    help: str | None = None
    methods: tuple | None = None
    flag: str | None = None
    short: str | None = None
    metavar: object = None
    nargs: object = None
    action: str | None = None
    commands: tuple = ("compute",)
    job: str | None = None
    per_command: dict = field(default_factory=dict)

    @property
    def job_default(self):
        """The default of the file job (:class:`~clcurv.jobs.job.Job`, ``clcurv compute``)."""
        return self.default if self.file_default is SAME else self.file_default

    def cli(self, command):
        """The ``add_argument`` keywords of this option in ``command`` (None: not there)."""
        if self.flag is None or command not in self.commands:
            return None
        kw = {"default": self.job_default, "help": self.help, "metavar": self.metavar}
        if self.action:
            kw["action"] = self.action
        else:
            kw["type"] = self.type
            kw["nargs"] = self.nargs
            choices = self.cli_choices if self.cli_choices is not None else self.choices
            kw["choices"] = (list(choices) if isinstance(choices, (tuple, dict)) else None)
        kw.update(self.per_command.get(command, {}))
        return {k: v for k, v in kw.items() if v is not None or k == "default"}


#: the commands that run on files
FILE_COMMANDS = ("compute", "features")


def _opt(name, **kw):
    return name, Option(name, **kw)


def _both(name, flag, metavar=None, **kw):
    """An option of both file commands, its :class:`~clcurv.jobs.job.Job` field of the same
    name unless ``job=`` says another."""
    kw.setdefault("job", name)
    return _opt(name, flag=flag, metavar=metavar, commands=FILE_COMMANDS, **kw)


#: the table: every compute option once (the order of ``clcurv compute --help``)
OPTIONS = dict([
    _opt("method", default="mls1", file_default="mls2", choices=METHODS_OF_REGISTRY,
         flag="--method", job="method",
         help="the operator (the registry's methods; the API's default is mls1, the file "
         "job's mls2)"),
    _opt("radius", default=None, file_default="auto", flag="--radius", job="radius",
         commands=FILE_COMMANDS,
         help="ball radius in the file's unit, or 'auto' (about 30 neighbours), or knn:K "
         "(the same as --k K)",
         per_command={"features": {"default": None, "help": "ball radius in the file's "
                                   "unit, or several separated by commas (one neighbour "
                                   "walk; fields named <feature>_r<radius>), or knn:K (the "
                                   "same as --k K)"}}),
    _opt("k", type=int, default=None, flag="--k", metavar="K", job="k",
         commands=FILE_COMMANDS,
         help="instead of --radius, each point's radius is the distance to its K-th "
         "nearest point (the point itself the first; a knn_radius field is written); in "
         "memory only, not with --scale-space, --projections, --weights density or --kernel "
         "gaussian",
         per_command={"features": {"metavar": None, "help": "per-point radius: the distance "
                                   "to the k-th nearest point"}}),
    _opt("optimal", default=False, flag="--optimal", action="store_true",
         commands=("features",),
         help="with several radii: each point's features at the radius of least "
         "eigenentropy among them (optimal neighbourhood; one set of fields plus "
         "optimal_radius)"),
    _opt("features", flag="--features", commands=("features",),
         help="comma-separated names (jakteristics or PDAL spellings) or 'all'"),
    _opt("ddof", type=int, default=0, choices=(0, 1), flag="--ddof", commands=("features",),
         help="covariance divided by n - ddof (1: jakteristics)"),
    _opt("scale_space", type=int, default=0, flag="--scale-space", metavar="N",
         job="scale_space",
         help="MLS1 scale-space iterations first (the paper's pipeline)"),
    _opt("weights", default="uniform", choices=("uniform", "density"), flag="--weights",
         job="weights"),
    _opt("kernel", default=None, choices=("ball", "gaussian"), methods=("mls2",),
         flag="--kernel", job="kernel",
         help="MLS2 only: neighbour weights (default ball)"),
    _opt("h", type=float, default=None, methods=("mls2",), flag="--h", metavar="H", job="h",
         help="MLS2 with --kernel gaussian only: Gaussian width in the file's unit (default "
         "radius / 2)"),
    _opt("projections", type=int, default=0, methods=("mls2",), flag="--projections",
         metavar="N", job="projections",
         help="MLS2 only: MLS2 projections of the cloud before evaluation"),
    # 2dcov1 reads p's normal alone: aligning its neighbours' would change nothing
    _opt("align_normals", default=None, choices=(None, True, False),
         methods=("2dcov2", "3dcov")),
    _opt("uncertainty", default=False, flag="--uncertainty", action="store_true",
         job="uncertainty",
         help="also per-point standard errors from the same neighbour walk: "
         "mean_curvature_se (mls0, mls1, mls2), gaussian_curvature_se, k1_se, k2_se "
         "(mls2), normal_se and roughness (every method; docs/uncertainty.md)"),
    _opt("select", default=None, choices=(None, "error"), cli_choices={"error": "error"},
         flag="--select", job="select",
         methods=("mls1", "mls2"),
         help="with several radii (--radius R1,R2,...): each point keeps the radius of "
         "least predicted error SE^2 + bias^2 (the bias fitted per point from how H moves "
         "between the radii); writes the standard errors and selected_radius; in memory "
         "only (docs/uncertainty.md)"),
    _opt("device", default=None, flag="--device", job="device",
         commands=FILE_COMMANDS,
         help="index, 'platform:device' or name substring",
         per_command={"features": {"help": None}}),
    _opt("precision", default="float", choices=("float", "double"), flag="--precision",
         job="precision", commands=FILE_COMMANDS),
    _opt("backend", default="opencl", choices=("opencl", "numpy")),
    _opt("fields", default=None, flag="--fields", nargs="+", job="fields",
         help="fields to write: names (normals, mean_curvature, k1, dir1 for dir1_x "
         "dir1_y dir1_z, ...), 'default' or 'all' (default: the method's curvatures, "
         "neighbours, status and normals; not the principal directions)"),
    _opt("quantize", default=False, flag="--quantize", action="store_true", job="quantize",
         help="LAS/LAZ output: store normals, curvatures and directions as integers with "
         "the extra-bytes descriptor's scale (curvatures to 5e-5 / radius, normals to "
         "5e-5; NaN as no_data): a smaller LAZ"),
    _opt("viewpoint", type=float, default=None, flag="--viewpoint", nargs=3,
         metavar=("X", "Y", "Z"), job="viewpoint",
         help="orient normals towards this scanner position"),
    _opt("orient", default="auto", choices=("auto", "mst", "viewpoint", "normals", "up", None),
         cli_choices={"auto": "auto", "mst": "mst", "up": "up", "none": None},
         flag="--orient", job="orient",
         help="how signed results are oriented: 'auto' (default) uses the file's normals, "
         "else --viewpoint, else 'up' for LAS/LAZ input (normals towards +Z, for aerial "
         "LiDAR) and 'mst' (minimum-spanning-tree propagation, outward on closed shapes) "
         "for the other formats; 'none' keeps the PCA sign"),
    _opt("orient_k", default=10),
    # the API takes normals (an array); the file job uses the file's unless told not to
    _opt("normals", default=None),
    _opt("positions", default="original", choices=("original", "projected"),
         flag="--positions", job="positions",
         help="write the input positions or the smoothed/projected ones"),
    _opt("ignore_normals", default=False, flag="--ignore-normals", action="store_true",
         job="ignore_normals", help="do not use normals stored in the input file"),
    _both("memory", "--memory", "SIZE", default="auto",
          help="host memory budget, e.g. 2GiB (default auto: half the available RAM, at most "
          "512 MiB). LAS/LAZ/NPY input that does not fit runs in tiles with an exact halo "
          "(same results as in memory), output LAS/LAZ/NPZ"),
    _both("tile", "--tile-size", "S", type="tile size", job="tile_size",
          help="run in tiles of S x S (file unit, a finite number > 0) even if the cloud "
          "fits; larger than the cloud: one tile"),
    _both("workers", "--workers", "N", type="workers",
          help="run the tiles on a local Dask cluster of N worker processes "
          '(pip install "clcurv[dask]"), at most the cores this process may use: more are '
          "clamped to them with a warning, unless {force_workers}=1. --memory is the whole "
          "run's: each worker's tiles get SIZE / N. The workers exit with the command, even "
          "if it is killed"),
    _both("scheduler", "--scheduler", "ADDRESS", help="run the tiles on the Dask cluster at "
          "ADDRESS, e.g. tcp://host:8786 (its workers must see the input and the output's "
          "folder at the same paths; --memory is then each worker's). Refused after "
          "{connect_timeout:g} s if no Dask scheduler answers there"),
    _both("workdir", "--workdir", "DIR", help="an existing folder to keep a tiled run's "
          "workspace in (default: beside the output), e.g. on another disk; the run makes "
          "its own folder there and touches nothing else (docs/workspace.md)"),
    _both("quiet", "--quiet", short="-q", action="store_true", default=False,
          help="no progress bars"),
])

#: options that only some methods take (the registry's ``Operator.options``)
METHOD_OPTIONS = tuple(name for name, o in OPTIONS.items() if o.methods is not None)
#: ``--workers`` and ``--scheduler`` exclude each other
EXCLUSIVE = ("workers", "scheduler")


def taken_by(method):
    """The method-specific options that ``method`` takes (its ``Operator.options``), in the
    table's order."""
    return tuple(n for n in METHOD_OPTIONS if method in OPTIONS[n].methods)


def given(values):
    """{name: set?} of method-specific options (``values``: name -> value, the API's): an
    option is set when it is not its declared default (None: not None)."""
    out = {}
    for name, value in values.items():
        default = OPTIONS[name].default
        out[name] = value is not None if default is None else bool(value != default)
    return out


def choices(name):
    """The allowed values of option ``name`` (the API's)."""
    return OPTIONS[name].choices


def check(value, name):
    """``value`` if it is an allowed value of option ``name``, else ValueError
    ``"<name> must be one of ..., got ..."`` (:func:`clcurv._shared.validate.choice`)."""
    return choice(value, name, OPTIONS[name].choices)


def cli_value(name, value):
    """The API value of a command-line spelling of option ``name`` (``--orient none`` is
    None); other values unchanged."""
    spell = OPTIONS[name].cli_choices
    return spell.get(value, value) if spell is not None and isinstance(value, str) else value


def file_orient(orient, z_up, viewpoint, normals):
    """The orientation of a file run: ``orient="auto"`` is ``"up"`` (normals towards +Z,
    PDAL's ``always_up``) for a z-up (LAS/LAZ, :func:`clcurv.io.is_las`) input without
    normals (``normals``: the run uses the file's) or a viewpoint; else ``orient``."""
    if isinstance(orient, str) and orient == "auto" and z_up and viewpoint is None \
            and not normals:
        return "up"
    return orient


def job_default(name):
    """The :class:`~clcurv.jobs.job.Job` default of the option whose job field is ``name``."""
    return next(o.job_default for o in OPTIONS.values() if o.job == name)
