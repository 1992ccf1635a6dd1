"""Every compute option is declared once (clcurv/_shared/options.py) and the declaration drives
the command line and its --help, the API's checks, the job's defaults, the registry's
per-method options and the tiles' parameters; the LAS/LAZ rules are one function each."""
import argparse
import ast
import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv import io
from clcurv._shared.options import (METHOD_OPTIONS, METHODS_OF_REGISTRY, OPTIONS, SAME, check,
                                    cli_value, file_orient, taken_by)
from clcurv.api.features import DEFAULT_FEATURES
from clcurv.api.inputs import allowed
from clcurv.cli import main as cli
from clcurv.jobs import job
from clcurv.ops.registry import METHODS, OPERATORS
from clcurv.tiles.engine import CurvatureParams

PACKAGE = Path(clcurv.__file__).resolve().parent
COMMANDS = ("compute", "features")


def subparser(command):
    sub = next(a for a in cli.build_parser()._actions
               if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


def actions(command):
    """{dest: action} of ``clcurv <command>``."""
    return {a.dest: a for a in subparser(command)._actions}


def declared(command):
    return [o for o in OPTIONS.values() if o.cli(command) is not None]


def test_every_option_is_complete():
    for name, o in OPTIONS.items():
        assert o.name == name
        if o.flag is not None:
            assert o.flag.startswith("--") and o.commands
        if o.methods is not None:
            assert set(o.methods) <= set(METHODS), name
        if isinstance(o.choices, tuple) and o.default is not None:
            assert o.default in o.choices, name
    assert OPTIONS["method"].choices == METHODS_OF_REGISTRY
    assert allowed("method") == METHODS


@pytest.mark.parametrize("command", COMMANDS)
def test_cli_arguments_are_the_declaration(command):
    """Every declared option of the command is an argument with its flag, default, choices
    (the command line's spellings) and metavar; and the command has no other option."""
    acts = actions(command)
    opts = declared(command)
    for o in opts:
        a = acts[o.flag[2:].replace("-", "_")]
        kw = o.cli(command)
        assert a.option_strings[-1] == o.flag
        want_default = ",".join(DEFAULT_FEATURES) if o.name == "features" else \
            kw["default"]
        assert a.default == want_default, o.name
        if o.choices is not None and o.flag:
            want = METHODS if o.name == "method" else (o.cli_choices or o.choices)
            assert list(a.choices) == list(want), o.name
        assert a.metavar == kw.get("metavar"), o.name
    flags = {a.option_strings[-1] for a in acts.values() if a.option_strings}
    assert flags - {o.flag for o in opts} == {"--help", "--output"}


@pytest.mark.parametrize("command", COMMANDS)
def test_help_lists_every_declared_option(command):
    text = " ".join(subparser(command).format_help().split())
    for o in declared(command):
        assert o.flag in text, o.flag
        kw = o.cli(command)
        if kw.get("help"):
            assert " ".join(kw["help"].split()[:6]) in text, o.name
        if isinstance(kw.get("choices"), list):
            assert "{" + ",".join(map(str, kw["choices"])) + "}" in text, o.name


def test_job_defaults_are_the_declaration():
    fields = {f.name: f.default for f in dataclasses.fields(job.Job)}
    for o in OPTIONS.values():
        if o.job is not None:
            assert fields[o.job] == o.job_default, o.name
    assert set(fields) - {"input", "output"} == {o.job for o in OPTIONS.values() if o.job}
    # the two defaults that differ between the API and the file job, both declared
    assert OPTIONS["method"].default == "mls1" and OPTIONS["method"].job_default == "mls2"
    assert OPTIONS["radius"].default is None and OPTIONS["radius"].job_default == "auto"
    assert [n for n, o in OPTIONS.items() if o.file_default is not SAME] == ["method", "radius"]


@pytest.mark.parametrize("fn", [clcurv.curvature, clcurv.normals, clcurv.project,
                                clcurv.features, clcurv.scale_space, clcurv.curvature_file,
                                clcurv.features_file])
def test_api_defaults_are_the_declaration(fn):
    """The API's keyword defaults are the declared ones (the file functions': the file
    job's, ``radius`` apart: the API's functions take it first); ``features=`` the
    features table's defaults."""
    file_api = fn in (clcurv.curvature_file, clcurv.features_file)
    for name, p in inspect.signature(fn).parameters.items():
        o = OPTIONS.get(name)
        if o is None or p.default is inspect.Parameter.empty or name == "features":
            continue
        if fn is clcurv.project and name in ("method", "projections"):
            continue            # project is MLS2's projection, once by default
        if fn is clcurv.features and name == "orient":
            continue            # the features' orientation: None, 'up' or a direction
        want = o.job_default if file_api and name != "radius" else o.default
        assert p.default == want, (fn.__name__, name)


def test_curvature_params_take_the_declared_names():
    names = [f.name for f in dataclasses.fields(CurvatureParams)]
    assert set(names) <= set(OPTIONS)
    assert CurvatureParams.__dataclass_fields__["orient_k"].default == OPTIONS["orient_k"].default
    j = job.Job("a.las", "b.las", orient="none", tile_size=5.0, workers=2)
    p = CurvatureParams(radius=1.0, **job.options_for(j, CurvatureParams))
    assert p.orient is None and p.method == "mls2" and p.scale_space == 0
    kw = job.options_for(j, clcurv.curvature_file)
    assert kw["tile"] == 5.0 and kw["workers"] == 2 and kw["orient"] is None
    assert "radius" not in kw and "k" not in kw and "quiet" not in kw
    assert set(kw) == {o.name for o in OPTIONS.values() if o.job}.intersection(
        inspect.signature(clcurv.curvature_file).parameters) - {"radius"}


def test_registry_options_are_the_declared_takers():
    for name, op in OPERATORS.items():
        assert op.options == taken_by(name)
    for opt in METHOD_OPTIONS:
        assert [m for m, op in OPERATORS.items() if opt in op.options] == \
            [m for m in METHODS if m in OPTIONS[opt].methods]
    pts = clcurv.shapes.sphere(500, 1.0)["points"]
    with pytest.raises(ValueError, match=r"kernel is not an option of method='mls1' \(only "
                                         r"of 'mls2'\)"):
        clcurv.curvature(pts, 0.3, method="mls1", kernel="ball", backend="numpy")


CHOICE_OPTIONS = [n for n, o in OPTIONS.items()
                  if isinstance(o.choices, tuple) and n != "align_normals"]


def _api_call(name, value):
    """A call of the API with ``name=value`` (a bad value), the rest valid."""
    pts = clcurv.shapes.sphere(500, 1.0)["points"]
    if name == "ddof":
        return lambda: clcurv.features(pts, 0.3, ddof=value)
    if name == "positions":
        return lambda: check(value, "positions")        # the job's, below
    kw = {name: value}
    if name == "kernel":
        kw["method"] = "mls2"
    return lambda: clcurv.curvature(pts, 0.3, **kw)


@pytest.mark.parametrize("name", CHOICE_OPTIONS + ["method"])
def test_a_bad_choice_is_refused_alike_by_the_api_and_the_cli(name, tmp_path, capsys):
    """The API's message names every allowed value, the command line's every spelling."""
    values = allowed(name)
    with pytest.raises(ValueError) as err:
        _api_call(name, "bogus")()
    assert name in str(err.value) and "'bogus'" in str(err.value)
    for v in values:
        assert repr(v) in str(err.value), (name, v)
    o = OPTIONS[name]
    for command in COMMANDS:
        if o.cli(command) is None:
            continue
        bad = "2" if name == "ddof" else "bogus"
        argv = [command, str(tmp_path / "in.ply"), "-o", str(tmp_path / "out.ply"), o.flag,
                bad] + (["--radius", "1"] if command == "features" else [])
        with pytest.raises(SystemExit) as exit_:
            cli.main(argv)
        assert exit_.value.code == 2
        msg = capsys.readouterr().err
        assert f"argument {o.flag}: invalid choice: " in msg
        assert bad in msg.split("invalid choice: ", 1)[1].split("(")[0]
        for v in (o.cli_choices or values):
            assert str(v) in msg.split("choose from", 1)[1], (name, v)


def test_orient_spellings_and_the_job_check():
    assert cli_value("orient", "none") is None and cli_value("orient", "up") == "up"
    assert cli_value("weights", "density") == "density"
    assert set(job.ORIENT_CHOICES.values()) <= set(OPTIONS["orient"].choices)
    cloud = io.Cloud(np.zeros((1, 3)), format="ply")
    with pytest.raises(job.UsageError, match="--orient must be one of auto, mst, up, none"):
        job.orientation(job.Job("a", "b", orient="sideways"), cloud)


def test_las_rules_are_one_function_each():
    for path, las in (("a.las", True), ("A.LAZ", True), ("x/b.copc.laz", True),
                      ("a.ply", False), ("las", False), (Path("d.npz"), False)):
        assert io.is_las(path) is las
    las_cloud = io.Cloud(np.zeros((1, 3)), format="laz")
    ply_cloud = io.Cloud(np.zeros((1, 3)), format="ply")
    assert io.from_las(las_cloud) and not io.from_las(ply_cloud)
    # orient auto is up for LAS/LAZ without normals or viewpoint; the job and tiles agree
    assert file_orient("auto", True, None, False) == "up"
    for args in (("auto", False, None, False), ("auto", True, (0, 0, 1), False),
                 ("auto", True, None, True)):
        assert file_orient(*args) == "auto"
    assert file_orient("mst", True, None, False) == "mst"
    d = np.array([0.0, 1.0, 0.0])
    assert file_orient(d, True, None, False) is d
    j = job.Job("a.las", "b.las")
    assert job.orientation(j, las_cloud) == "up"
    assert job.orientation(j, ply_cloud) == "auto"
    assert job.orientation(job.Job("a", "b", viewpoint=(0, 0, 9)), las_cloud) == "auto"


def _literal_tuples(path):
    """Every tuple or list literal of constants in the module at ``path`` (with line)."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List)) and len(node.elts) >= 2 and all(
                isinstance(e, ast.Constant) for e in node.elts):
            yield node.lineno, tuple(e.value for e in node.elts)


def test_no_module_lists_an_options_values_by_hand():
    """The allowed values of a (string) option are written in the declaration only."""
    sets = {n: frozenset(o.choices) for n, o in OPTIONS.items()
            if isinstance(o.choices, tuple) and all(isinstance(c, str) for c in o.choices)}
    found = []
    for path in PACKAGE.rglob("*.py"):
        if path.name == "options.py" and path.parent.name == "_shared":
            continue
        for line, values in _literal_tuples(path):
            for name, s in sets.items():
                if frozenset(values) == s:
                    found.append(f"{path.relative_to(PACKAGE)}:{line} {name} {values}")
    assert not found, found


def test_no_module_tests_las_extensions_by_hand():
    found = []
    for path in PACKAGE.rglob("*.py"):
        if path.parent.name == "io" and path.name in ("common.py", "las.py"):
            continue                                # the helpers and the format's table
        for line, values in _literal_tuples(path):
            if {".las", ".laz"} <= set(values) or {"las", "laz"} <= set(values):
                found.append(f"{path.relative_to(PACKAGE)}:{line} {values}")
    assert not found, found
