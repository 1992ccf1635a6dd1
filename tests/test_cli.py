"""The clcurv command line end to end on the bundled sample and a LAS file; bad input gives
a non-zero exit and a one-line message, never a traceback."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clcurv.cli import main as cli
from clcurv import io
from clcurv.jobs import job
from clcurv.data import sample_path
from conftest import data_path

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def run(*args):
    return subprocess.run([sys.executable, "-m", "clcurv.cli.main", *map(str, args)],
                          capture_output=True, text=True)


def test_compute_on_bundled_sample_writes_fields(tmp_path):
    out = tmp_path / "bunny.ply"
    p = run("compute", sample_path(), "-o", out, "--method", "mls2", "--scale-space", "2", "-q")
    assert p.returncode == 0, p.stderr
    assert "radius auto" in p.stdout and "mean neighbours" in p.stdout
    cloud = io.read(out)
    src = io.read(sample_path())
    np.testing.assert_array_equal(cloud.points, src.points)           # order and points kept
    # the default fields: MLS2's curvatures, counts, statuses and normals, no directions
    assert list(cloud.attributes) == ["mean_curvature", "gaussian_curvature", "k1", "k2",
                                      "neighbours", "status"]
    ok = cloud.attributes["status"] == 0
    assert ok.mean() > 0.98
    assert np.isfinite(cloud.attributes["mean_curvature"][ok]).all()
    assert np.isnan(cloud.attributes["mean_curvature"][~ok]).all()
    assert np.all(cloud.attributes["k1"][ok] >= cloud.attributes["k2"][ok])
    assert np.allclose(np.linalg.norm(cloud.normals[ok], axis=1), 1, atol=1e-5)
    assert 0 < np.median(cloud.attributes["mean_curvature"][ok]) < 200     # bunny ~ 5 cm: H > 0


def test_compute_on_las_keeps_header_and_adds_extra_bytes(tmp_path):
    src = data_path("laspy_simple.las")         # shared, else shipped in tests/data
    if src is None:
        pytest.skip("laspy_simple.las not present (../shared/data, tests/data)")
    out = tmp_path / "simple.las"
    p = run("compute", src, "-o", out, "--method", "mls1", "--radius", "400",
            "--fields", "mean_curvature", "surface_variation", "-q")
    assert p.returncode == 0, p.stderr
    import laspy
    a, b = laspy.read(src), laspy.read(out)
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert tuple(b.header.scales) == tuple(a.header.scales)
    assert tuple(b.header.offsets) == tuple(a.header.offsets)
    assert {"mean_curvature", "surface_variation"} <= set(b.point_format.extra_dimension_names)
    v = np.asarray(b["surface_variation"])
    assert np.isfinite(v).mean() > 0.95 and np.nanmax(v) <= 1 / 3 + 1e-6


def test_devices_lists_the_default():
    p = run("devices")
    assert p.returncode == 0 and "*" in p.stdout and "fp64" in p.stdout


def test_compute_with_a_knn_radius(tmp_path):
    """`compute --k 30`: each point's radius is the distance to its 30th nearest point (the
    k-d tree's), written as knn_radius; every ball holds 30 points (more only on ties), the
    same values as the API call."""
    from scipy.spatial import cKDTree
    import clcurv
    out = tmp_path / "bunny_k.ply"
    p = run("compute", sample_path(), "-o", out, "--method", "variation", "--k", 30, "-q")
    assert p.returncode == 0, p.stderr
    assert "the distance to the k-th nearest point, k = 30" in p.stdout
    assert "radius auto" not in p.stdout
    a = io.read(out).attributes
    pts = io.read(sample_path()).points
    d = cKDTree(pts).query(pts, 30)[0][:, -1]
    np.testing.assert_allclose(a["knn_radius"], d, rtol=4e-6)
    assert (a["neighbours"] >= 30).all() and (a["neighbours"] == 30).mean() > 0.99
    api = clcurv.curvature(pts, method="variation", k=30)
    np.testing.assert_array_equal(a["surface_variation"], api.variation)
    # --radius knn:30, the API's spelling, is --k 30
    alias = tmp_path / "bunny_knn.ply"
    p = run("compute", sample_path(), "-o", alias, "--method", "variation", "--radius",
            "knn:30", "-q")
    assert p.returncode == 0, p.stderr
    b = io.read(alias).attributes
    for name in ("knn_radius", "surface_variation", "neighbours"):
        np.testing.assert_array_equal(b[name], a[name])


@pytest.mark.parametrize("args,code,msg", [
    (["compute", "/no/such/file.ply", "-o", "x.ply"], 3, "no/such/file.ply"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--radius", "-1"], 2, "--radius must be positive"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--radius", "big"], 2, "number or 'auto'"),
    (["compute", "{sample}", "-o", "{tmp}/x.unknown"], 3, "x.unknown"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--fields", "nonsense"], 2, "unknown field"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--quantize"], 2,
     "--quantize stores LAS/LAZ extra bytes"),
    (["compute", "{sample}", "-o", "{tmp}/x.las", "--quantize", "--k", "30"], 2,
     "give --radius, not --k"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--device", "no-such-gpu"], 4, "no OpenCL device"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--method", "mls9"], 2, "invalid choice"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--method", "3dcov", "--kernel", "gaussian"],
     2, "--kernel is an option of --method mls2 only"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--method", "mls1", "--projections", "1"],
     2, "--projections is an option of --method mls2 only"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--method", "mls2", "--h", "0.01"],
     2, "kernel='gaussian'"),
    # no abbreviated options (--k, before compute had it, was taken for --kernel)
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--proj", "1"], 2,
     "unrecognized arguments: --proj"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--scale", "2"], 2,
     "unrecognized arguments: --scale"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--k", "30", "--radius", "0.01"], 2,
     "give --radius or --k, not both"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--k", "30", "--scale-space", "2"], 2,
     "--scale-space does not combine with --k"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--k", "30", "--weights", "density"], 2,
     "--weights density does not combine with --k"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--k", "30", "--tile-size", "0.05"], 2,
     "does not run in tiles"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--k", "0"], 2, "k must be"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--radius", "knn:many"], 2,
     "--radius knn:K needs an integer K"),
    (["compute", "{sample}", "-o", "{tmp}/x.ply", "--radius", "knn:30", "--k", "30"], 2,
     "give --radius knn:K or --k K, not both"),
    (["features", "{sample}", "-o", "{tmp}/x.ply", "--radius", "knn:30", "--k", "20"], 2,
     "give --radius knn:K or --k K, not both"),
])
def test_bad_arguments_exit_codes(tmp_path, args, code, msg):
    args = [a.format(sample=sample_path(), tmp=tmp_path) for a in args]
    p = run(*args)
    assert p.returncode == code, (p.returncode, p.stderr)
    assert msg in p.stderr and "Traceback" not in p.stderr


def test_no_opencl_platform_names_the_apt_command(tmp_path):
    import os
    env = dict(os.environ, OCL_ICD_VENDORS=str(tmp_path))
    p = subprocess.run([sys.executable, "-m", "clcurv.cli.main", "devices"], capture_output=True,
                       text=True, env=env)
    assert p.returncode == 4 and "apt-get install -y pocl-opencl-icd" in p.stderr
    assert "Traceback" not in p.stderr


def test_auto_radius_gives_about_30_neighbours():
    pts = io.read(sample_path()).points
    r = job.auto_radius(pts)
    from scipy.spatial import cKDTree
    counts = np.array([len(x) for x in cKDTree(pts).query_ball_point(pts[::50], r)])
    assert 26 <= np.median(counts) <= 34


def test_render_command_on_a_computed_file(tmp_path):
    ply, png = tmp_path / "b.ply", tmp_path / "b.png"
    assert run("compute", sample_path(), "-o", ply, "--method", "mls1", "-q").returncode == 0
    p = run("render", ply, "--field", "mean_curvature", "--unit", "1/m", "-o", png)
    assert p.returncode == 0, p.stderr
    from matplotlib.image import imread
    img = imread(str(png))
    assert img.shape[0] > 300 and np.any(img[..., :3] < 0.9, axis=2).mean() > 0.1
    p = run("render", ply, "--field", "no_such_field", "-o", png)
    assert p.returncode == 2 and "no field 'no_such_field'" in p.stderr


#: the file fields of each method, in the order ``clcurv compute`` wrote them before the
#: operator registry (the registry's output order must keep it)
DIRS = [f"dir{i}_{a}" for i in "12" for a in "xyz"]
FILE_FIELDS = {
    "variation": ["surface_variation"],
    "mls0": ["mean_curvature", "surface_variation"],
    "mls1": ["mean_curvature", "surface_variation"],
    "2dcov1": ["k1", "k2", *DIRS], "2dcov2": ["k1", "k2", *DIRS], "3dcov": ["k1", "k2", *DIRS],
    "mls2": ["mean_curvature", "gaussian_curvature", "k1", "k2", *DIRS],
}


@pytest.fixture(scope="module")
def sphere_points():
    import clcurv
    return clcurv.shapes.sphere(3000, 1.0)["points"]


@pytest.mark.parametrize("method", sorted(FILE_FIELDS))
def test_result_fields_names_order_and_dtypes(sphere_points, method):
    import clcurv
    res = clcurv.curvature(sphere_points, 0.35, method=method)
    f = job.result_fields(res, "all")
    assert list(f) == FILE_FIELDS[method] + ["neighbours", "status"]
    # the default set: all but the principal directions, and the normals
    assert list(job.result_fields(res)) == \
        [k for k in FILE_FIELDS[method] if k not in DIRS] + ["neighbours", "status"]
    assert job.chosen_fields(res)[-1] == "normals"
    assert job.result_fields(res, ["all"]).keys() == f.keys()
    assert f["neighbours"].dtype == np.int32 and f["status"].dtype == np.uint8
    assert all(f[k].dtype == np.float64 and f[k].shape == (len(res),) for k in FILE_FIELDS[method])
    if res.k1 is not None:
        np.testing.assert_array_equal(f["dir2_y"], res.dir2[:, 1])
    assert list(job.result_fields(res, ["status", "normals", FILE_FIELDS[method][0]])) == \
        [FILE_FIELDS[method][0], "status"]
    with pytest.raises(job.UsageError, match="unknown field"):
        job.result_fields(res, ["nonsense"])


def test_fields_words_default_all_and_stems(sphere_points):
    """``fields=``: "default" and "all" stand for those sets, a width-3 field's stem for its
    three components, in file order whatever the order given."""
    import clcurv
    res = clcurv.curvature(sphere_points, 0.35, method="mls2")
    assert job.chosen_fields(res, ["dir2", "default"]) == [
        "mean_curvature", "gaussian_curvature", "k1", "k2", "dir2_x", "dir2_y", "dir2_z",
        "neighbours", "status", "normals"]
    assert job.chosen_fields(res, ["status", "k2"]) == ["k2", "status"]
    assert job.chosen_fields(res, "all") == FILE_FIELDS["mls2"] + ["neighbours", "status",
                                                                   "normals"]


def test_compute_fields_all_writes_the_directions(tmp_path):
    out = tmp_path / "bunny.npz"
    p = run("compute", sample_path(), "-o", out, "--method", "2dcov1", "--fields", "all", "-q")
    assert p.returncode == 0, p.stderr
    cloud = io.read(out)
    assert list(cloud.attributes) == FILE_FIELDS["2dcov1"] + ["neighbours", "status"]
    assert cloud.normals is not None


def test_summary_prints_the_ranges_of_the_width_1_fields(tmp_path, sphere_points):
    src, lines = tmp_path / "s.npy", []
    np.save(src, sphere_points)
    job.run(job.Job(src, tmp_path / "s.ply", method="mls1", radius=0.35, quiet=True),
            lines.append)
    ranged = [ln.split()[0] for ln in lines if ln.startswith("  ")]
    assert ranged == ["mean_curvature", "surface_variation"]
    h = next(ln for ln in lines if ln.startswith("  mean_curvature"))
    assert 0.9 < float(h.split("median")[1].split()[0]) < 1.1         # unit sphere: H = 1


def test_mls2_gaussian_kernel_and_projections_options(tmp_path):
    """--kernel, --h and --projections reach clcurv.curvature: the file's fields are the
    API's with the same options (float32 fields: its values rounded to them, the same
    kernels on the same device), and each option changes them: the API's result without
    it differs on most points."""
    import clcurv
    out = tmp_path / "g.ply"
    r, h = 0.004, 0.0012
    p = run("compute", sample_path(), "-o", out, "--method", "mls2", "--radius", r,
            "--kernel", "gaussian", "--h", h, "--projections", "1", "-q")
    assert p.returncode == 0, p.stderr
    got = io.read(out)
    pts = io.read(sample_path()).points
    np.testing.assert_array_equal(got.points, pts)                    # positions original
    opts = dict(kernel="gaussian", h=h, projections=1)
    want = clcurv.curvature(pts, r, method="mls2", **opts)
    assert want.valid.mean() > 0.98
    np.testing.assert_array_equal(got.attributes["status"], want.status)
    fields = {"mean_curvature": want.mean, "gaussian_curvature": want.gaussian,
              "k1": want.k1, "k2": want.k2}
    for name, v in fields.items():
        np.testing.assert_array_equal(got.attributes[name], v.astype(np.float32), err_msg=name)
    for dropped in ("kernel", "h", "projections"):
        kw = {k: v for k, v in opts.items() if k != dropped and not (dropped == "kernel" and
                                                                      k == "h")}
        other = clcurv.curvature(pts, r, method="mls2", **kw)
        ok = want.valid & other.valid
        changed = np.abs(other.mean[ok] - want.mean[ok]) > 1e-3 * np.abs(want.mean[ok])
        assert changed.mean() > 0.5, (dropped, changed.mean())


def test_render_up_takes_a_negative_axis_as_written():
    """`--up -z` (docs/methods.md's spelling) is the axis -z, not an unknown option -z."""
    from clcurv.cli.main import _glue_negative_axes, build_parser
    argv = ["render", "a.ply", "--field", "f", "--up", "-z", "-o", "a.png"]
    assert build_parser().parse_args(_glue_negative_axes(argv)).up == "-z"
    argv = ["render", "a.ply", "--field", "f", "--up", "y", "-o", "a.png"]
    assert build_parser().parse_args(_glue_negative_axes(argv)).up == "y"
