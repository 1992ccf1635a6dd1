"""Mutation check: plant one fault at a time in a scratch copy of the project, run the test
suite against it, and report which faults survive (issue 48, item 5).

    python -m bench.mutants                  # every mutant (make mutants)
    python -m bench.mutants --list           # the mutants: name, file, kind, what changes
    python -m bench.mutants --only ball-closed --only 'mls2-*'
    python -m bench.mutants --sentinel       # check that the scratch copy is what runs
    python -m bench.mutants --worktree ...   # the working tree's tracked files, not HEAD

A mutant is one exact-text replacement in one file of the project (a kernel, a header or the
host's finishing and orientation code): a sign flipped, a normalisation made wrong, a
centring term dropped, a loop bound off by one, the open ball |q - p| < r made closed, a
step scaled, a neighbour row dropped. Its text must occur exactly once in the file, or the
run stops (so that a mutant that no longer applies is fixed, not silently skipped).

Each mutant runs in its own scratch copy: the files of HEAD (``git archive``; with
--worktree the tracked files of the working tree) in a temporary directory, ``shared`` next
to it linked to the repository's ``../shared`` (the tests' optional data), the mutation
applied, and ``python -m pytest -x -n 2`` run there with the copy first on PYTHONPATH:
``import clcurv`` and its kernel lookup (clcurv/runtime/program.py: kernels_dir) take the copy,
which is checked before the suite runs. The test files run in a fixed order, the fast ones
that compare the kernels with the float64 reference and the analytic values first (FIRST);
-x stops at the first failure, so a caught mutant costs a minute or two and a survivor the
whole suite. The failing test is then run on an unmutated copy: a test that fails there too
(flaky, or broken by work in progress) does not count as a catch; it is deselected and the
mutant runs again. A run that exceeds --timeout (a hang) counts as caught, reported as such.

The report (printed, and bench/results/mutants.md) lists each mutant with the first test
that caught it, or "survived", "timeout"; a survivor is either caught by a new test
(tests/test_mutant_guards.py) or, if no input can tell it from the original, documented as an
equivalent mutant here (``equivalent=``). Results of --only runs are merged into the report
(each row says the commit it ran on). Mutated kernels leave their builds in PoCL's cache
(~/.cache/pocl): a few MB per mutant.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import fnmatch
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REPORT = ROOT / "bench" / "results" / "mutants.md"

#: test files run first, in this order: fast, and between them they compare every kernel
#: family and the host finishing code with the float64 reference or analytic values
FIRST = (
    "tests/test_mutant_guards.py",
    "tests/test_operators.py",
    "tests/test_analytic.py",
    "tests/test_moments.py",
    "tests/test_eig3.py",
    "tests/test_eig3_vector.py",
    "tests/test_forest.py",
    "tests/test_orientation.py",
    "tests/test_reference_ops.py",
    "tests/test_reference_independent.py",
    "tests/test_pcl_oracle.py",
    "tests/test_scale_space.py",
    "tests/test_features.py",
    "tests/test_nan_rows.py",
    "tests/test_local_alignment.py",
    "tests/test_multi_radius.py",
    "tests/test_knn_radius.py",
    "tests/test_row_pruning.py",
)
#: test files run last: the slowest (Oclgrind alone is a quarter of the suite's time)
LAST = (
    "tests/test_hostile_las.py",
    "tests/test_masked_sums.py",
    "tests/test_workspace.py",
    "tests/test_install.py",
    "tests/test_tiled.py",
    "tests/test_oclgrind.py",
)


@dataclasses.dataclass(frozen=True)
class Mutant:
    name: str
    path: str               # file in the repository
    kind: str               # the fault's kind (KINDS)
    old: str                # exact text, found exactly once in the file
    new: str                # its replacement
    what: str               # the fault in words
    equivalent: str = ""    # why no input can tell it from the original (documented survivor)


KINDS = ("sign flip", "normalisation", "centring", "loop bound", "open ball -> closed",
         "step scaled", "dropped row", "eigen order", "weights", "tree")

M = Mutant
MUTANTS = (
    # ---- covariances.cl: 2dcov1, 2dcov2, 3dcov -----------------------------------------
    M("cov-centring", "kernels/covariances.cl", "centring",
      "c[0] = hsum(saa) * iw - ma * ma;", "c[0] = hsum(saa) * iw;",
      "the feature covariance's aa entry not centred (mean square instead of variance)"),
    M("cov-normalisation", "kernels/covariances.cl", "normalisation",
      "const REAL iw = (REAL)1 / COUNT_TOTAL(sw);",
      "const REAL iw = (REAL)1 / (COUNT_TOTAL(sw) - 1);",
      "uniform-weight covariances divided by n - 1 instead of n"),
    M("cov-align-sign", "kernels/covariances.cl", "sign flip",
      "const IREALV flip = isless(qx0 * nrm.x", "const IREALV flip = isgreater(qx0 * nrm.x",
      "ALIGN_NORMALS turns each neighbour's normal away from p's instead of towards it"),
    M("2dcov1-root", "kernels/covariances.cl", "sign flip",
      "const REALV m = (S + sqrt(", "const REALV m = (S - sqrt(",
      "Theorem 1 inverted with the other root m- of m = (k1 + k2)^2"),
    M("cov-dir2-handedness", "kernels/covariances.cl", "sign flip",
      "COV_COLUMN(CIX_DIR2, ny * e1z - nz * e1y)", "COV_COLUMN(CIX_DIR2, -(ny * e1z - nz * e1y))",
      "dir2's x component negated (dir2 no longer n x dir1)"),
    M("3dcov-dir-eigvec", "kernels/covariances.cl", "eigen order",
      "const REALV d = v2.x * nx + v2.y * ny + v2.z * nz;\n"
      "    const REALV tx = v2.x - d * nx, ty = v2.y - d * ny, tz = v2.z - d * nz;",
      "const REALV d = v1.x * nx + v1.y * ny + v1.z * nz;\n"
      "    const REALV tx = v1.x - d * nx, ty = v1.y - d * ny, tz = v1.z - d * nz;",
      "3dcov's dir1 from the middle eigenvector instead of the largest"),
    # ---- mls2.cl: the quadric fit ------------------------------------------------------
    M("mls2-ref-sign", "kernels/mls2.cl", "sign flip",
      "if (s < 0) v0 = -v0;", "if (s > 0) v0 = -v0;",
      "v0 oriented against the reference normal instead of with it"),
    M("mls2-gxx-factor", "kernels/mls2.cl", "normalisation",
      "const REALV gxx = 2 * a[3] * (ir * ir)", "const REALV gxx = a[3] * (ir * ir)",
      "the second derivative g_xx = 2 a3 taken as a3 (shape operator)"),
    M("mls2-dir-eigvec", "kernels/mls2.cl", "eigen order",
      "eigvec2_v(S00, S01, S10, S11, lo, &ex, &ey);",
      "eigvec2_v(S00, S01, S10, S11, hmean + disc, &ex, &ey);",
      "dir1 from the eigenvector of k2 (directions swapped)"),
    M("mls2-height-centring", "kernels/mls2.cl", "centring",
      "dx * v0.x + dy * v0.y + dz * v0.z - cv0, m);", "dx * v0.x + dy * v0.y + dz * v0.z, m);",
      "heights measured from p, not from its projection Q on the regression plane"),
    M("mls2-moment-centring", "kernels/mls2.cl", "centring",
      "const REAL S11 = sw * (dot(t2, C1) + m1 * m2) * ir2;",
      "const REAL S11 = sw * dot(t2, C1) * ir2;",
      "the normal equations' sum w x y without its mean term (centred covariance only)"),
    # ---- pca.h / moments.cl / weights.h: the PCA every operator shares --------------------
    M("pca-centring", "kernels/pca.h", "centring",
      "b->c[5][k] = hsum(szz) * iw - mu.z * mu.z;", "b->c[5][k] = hsum(szz) * iw;",
      "the PCA covariance's zz entry not centred"),
    M("pca-normalisation", "kernels/pca.h", "normalisation",
      "const REAL3 mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw;",
      "const REAL3 mu = (REAL3)(hsum(sx), hsum(sy), hsum(sz)) * iw * (REAL)0.5;",
      "the barycenter offset mu = o - p halved (and the covariance centred on it)"),
    M("variation-normalisation", "kernels/moments.cl", "normalisation",
      "rec.COL_VARIATION = lam.x / (lam.x + lam.y + lam.z);",
      "rec.COL_VARIATION = lam.x / (lam.y + lam.z);",
      "surface variation l0 / (l1 + l2) instead of l0 / (l0 + l1 + l2)"),
    M("anchor-l0-factor", "kernels/pca.h", "normalisation",
      "const REALV l0 = vz * vz * c5 + (REAL)2 * vz * uca + ucu;",
      "const REALV l0 = vz * vz * c5 + vz * uca + ucu;",
      "the anchored lambda0's cross term without its factor 2"),
    M("refine-centring", "kernels/pca.h", "centring",
      "(dz) * (v0).z - (h0);          \\\n        const REALV hm_",
      "(dz) * (v0).z;                 \\\n        const REALV hm_",
      "lambda0's second pass (uniform weights) measures heights from p, not from o"),
    M("density-weights", "kernels/weights.h", "weights",
      "REALV w = VLOADV(0, W + i);", "REALV w = sqrt(VLOADV(0, W + i));",
      "density weights sqrt(1 / #N(q)) instead of 1 / #N(q)"),
    M("gaussian-width", "kernels/weights.h", "step scaled",
      "w *= exp(-(dx * dx + dy * dy + dz * dz) * ih2);",
      "w *= exp(-(dx * dx + dy * dy + dz * dz) * ih2 * (REAL)0.5);",
      "the Gaussian kernel's width scaled by sqrt 2"),
    # ---- eig3.h ------------------------------------------------------------------------
    M("eig3-pair-order", "kernels/eig3.h", "eigen order",
      "const EIG3_I swap = EIG3_FN(eig3_rayleigh)(d, eb) < EIG3_FN(eig3_rayleigh)(d, ea);",
      "const EIG3_I swap = EIG3_FN(eig3_rayleigh)(d, eb) > EIG3_FN(eig3_rayleigh)(d, ea);",
      "the two non-isolated eigenvectors ordered the wrong way"),
    M("eig3-newton-steps", "kernels/eig3.h", "loop bound",
      "for (int it = 0; it < 3; ++it) {", "for (int it = 0; it < 2; ++it) {",
      "two Newton steps on the cubic instead of three"),
    # ---- neighbors.h: the neighbour walk -------------------------------------------------
    M("ball-closed", "kernels/neighbors.h", "open ball -> closed",
      "return live & isless(*d2, (REALV)ball.x);", "return live & islessequal(*d2, (REALV)ball.x);",
      "the ball test |q - p|^2 < r^2 made <= (the closed ball)"),
    M("row-dropped", "kernels/neighbors.h", "dropped row",
      "for (int nb_y = 0; nb_y < 3; ++nb_y) {", "for (int nb_y = 0; nb_y < 3 - (nb_z == 2); ++nb_y) {",
      "the walk skips the last of the 9 rows of cells (dz = dy = +1)"),
    M("lane-off-by-one", "kernels/neighbors.h", "loop bound",
      "const IREALV live = LANES < (IREALV)((IREAL)(end - i));",
      "const IREALV live = LANES <= (IREALV)((IREAL)(end - i));",
      "one lane past each row's end taken as a candidate"),
    M("chunk-loop-bound", "kernels/neighbors.h", "loop bound",
      "(ball).x); i < end; i += VW) {", "(ball).x); i + 1 < end; i += VW) {",
      "a row's last chunk dropped when it holds a single point"),
    # ---- grid.cl -----------------------------------------------------------------------
    M("grid-row-x1", "kernels/grid.cl", "dropped row",
      "x1 = min(ix + 1, nx - 1);", "x1 = min(ix, nx - 1);",
      "every row of the 27-cell block loses its +x cell"),
    # ---- features.cl ---------------------------------------------------------------------
    M("features-ddof", "kernels/features.cl", "normalisation",
      "cnt / (cnt - (REAL)ddof)", "cnt / (cnt + (REAL)ddof)",
      "sample covariance scaled by n / (n + ddof) instead of n / (n - ddof)"),
    M("features-verticality-sign", "kernels/features.cl", "sign flip",
      "FEATURE_COLUMN(CIX_VERTICALITY, 1 - fabs(e3z))", "FEATURE_COLUMN(CIX_VERTICALITY, 1 - e3z)",
      "verticality 1 - e3_z instead of 1 - |e3_z| (the unoriented normal's sign leaks)"),
    M("features-density-volume", "kernels/features.cl", "normalisation",
      "cnt / (FOUR_THIRDS_PI * r2v * sqrt(r2v))", "cnt / (FOUR_THIRDS_PI * r2v)",
      "density divided by 4/3 pi r^2 instead of the ball's volume"),
    M("features-ball-closed", "kernels/features.cl", "open ball -> closed",
      "(CAT(as_, IREALV)(d2) < (IREALV)CAT(as_, IREAL)(r2))",
      "(CAT(as_, IREALV)(d2) <= (IREALV)CAT(as_, IREAL)(r2))",
      "the smaller balls of the multi-radius walk made closed"),
    # ---- knn.cl, knn_radius.cl -----------------------------------------------------------
    M("knn-self-count", "kernels/knn.cl", "loop bound",
      "c[0] -= 1;", "c[0] -= 0;",
      "the orientation graph's bin counts include the point itself (off by one)"),
    M("knn-weight-sign", "kernels/knn.cl", "sign flip",
      "const REALV w = ((REALV)1 - fabs(nn)) + t;", "const REALV w = ((REALV)1 - fabs(nn)) - t;",
      "the edge weight's sheet penalty subtracted in a point's own walk"),
    M("knn-radius-rank", "kernels/knn_radius.cl", "loop bound",
      "d = kth_of_levels(a, lanes, ball.x, KNN_K);", "d = kth_of_levels(a, lanes, ball.x, KNN_K - 1);",
      "the k-NN radius from the (K-1)-th nearest point"),
    M("knn-radius-margin", "kernels/knn_radius.cl", "step scaled",
      "r2[g] = fmax(d * d * grow, REAL_MIN_NORMAL);", "r2[g] = fmax(d * d, REAL_MIN_NORMAL);",
      "the k-NN ball's r^2 without its margin (1 + MARGIN)"),
    # ---- forest.cl: the minimum spanning forest -------------------------------------------
    M("forest-parity-sign", "kernels/forest.cl", "sign flip",
      "NZ[b])) < 0;\n    link[g] = comp[v] << 1", "NZ[b])) > 0;\n    link[g] = comp[v] << 1",
      "a hook's parity from n_u . n_v > 0 instead of < 0 (rounds after the first)"),
    M("forest-lighter", "kernels/forest.cl", "tree",
      "if (w != t->w[h]) return w < t->w[h];", "if (w != t->w[h]) return w > t->w[h];",
      "of two edges between the same components the heavier is kept (not a minimum forest)"),
    M("forest-break-pairs", "kernels/forest.cl", "tree",
      "if (d != g && link[d] >> 1 == g && order[g] < order[d]) {",
      "if (d != g && link[d] >> 1 == g && order[g] > order[d]) {",
      "of two roots that hook onto each other the larger input index stays the root"),
    # ---- scale_space.cl ------------------------------------------------------------------
    M("scale-space-step", "kernels/scale_space.cl", "step scaled",
      "move = dot((REAL3)(pb.mux[k], pb.muy[k], pb.muz[k]), v0) * v0;",
      "move = (REAL)0.5 * dot((REAL3)(pb.mux[k], pb.muy[k], pb.muz[k]), v0) * v0;",
      "each MLS1 step moves half way to the PCA plane"),
    M("scale-space-drift", "kernels/scale_space.cl", "step scaled",
      "drift[g - first] = length(q - (REAL3)(BX[g], BY[g], BZ[g]));",
      "drift[g - first] = (REAL)0.5 * length(q - (REAL3)(BX[g], BY[g], BZ[g]));",
      "the drift since the last binning halved (the re-binning comes late)"),
    # ---- host finishing: clcurv/ops/registry.py -------------------------------------------
    M("mls0-mean-sign", "clcurv/ops/registry.py", "sign flip",
      'mean = -4.0 * np.einsum("ij,ij->i", shift, nref) / (r * r)',
      'mean = 4.0 * np.einsum("ij,ij->i", shift, nref) / (r * r)',
      "MLS0's H = 4 <p - o, n> / r^2 with the sign flipped"),
    M("mls1-mean-normalisation", "clcurv/ops/registry.py", "normalisation",
      "mean=-4.0 * along / (r * r)", "mean=-2.0 * along / (r * r)",
      "MLS1's H = 2 <p - p', n> / r^2 instead of 4 <...> / r^2"),
    M("mls1-projection-sign", "clcurv/ops/registry.py", "sign flip",
      "points=pts + along[:, None] * n)", "points=pts - along[:, None] * n)",
      "MLS1's projection p' moved away from the plane"),
    M("flip-mls2-order", "clcurv/ops/registry.py", "sign flip",
      'raw["k1"][m], raw["k2"][m] = -k2, -k1', 'raw["k1"][m], raw["k2"][m] = -k1, -k2',
      "flipping an MLS2 normal negates k1, k2 without swapping them (k1 < k2)"),
    M("flip-mls2-dirs", "clcurv/ops/registry.py", "sign flip",
      'raw["dir1"][m], raw["dir2"][m] = d2, d1', 'raw["dir1"][m], raw["dir2"][m] = d1, d2',
      "flipping an MLS2 normal keeps dir1, dir2 (not swapped with k1, k2)"),
    M("mls2-mean-normalisation", "clcurv/ops/registry.py", "normalisation",
      '"mean": 0.5 * (k1 + k2)', '"mean": (k1 + k2)',
      "MLS2's mean curvature k1 + k2 instead of (k1 + k2) / 2"),
    # ---- orientation: clcurv/orient/orientation.py -----------------------------------------------------
    M("viewpoint-sign", "clcurv/orient/orientation.py", "sign flip",
      "return _negative(_rowdot(n, v - p))", "return _negative(_rowdot(n, p - v))",
      "normals turned away from the viewpoint"),
    M("reference-sign", "clcurv/orient/orientation.py", "sign flip",
      "return _negative(_rowdot(n, ref))", "return _negative(-_rowdot(n, ref))",
      "normals turned against the reference normals / direction"),
    M("device-vote-sign", "clcurv/orient/orientation.py", "sign flip",
      "flip = fo.parity ^ (_one_vote(cloud.points, n, fo.parity) < 0)",
      "flip = fo.parity ^ (_one_vote(cloud.points, n, fo.parity) > 0)",
      "a single-component MST orientation turned inward"),
    M("components-vote-sign", "clcurv/orient/orientation.py", "sign flip",
      "    flip = vote < 0\n    big = ", "    flip = vote > 0\n    big = ",
      "several components each turned towards their centroid (inward)"),
)

#: mutants that must be caught (build errors, an exception on import): --sentinel checks
#: that the scratch copy, not the repository, is the code under test
SENTINELS = (
    M("sentinel-kernel", "kernels/common.h", "sentinel",
      "#define CAT_(a, b) a##b", '#error "bench.mutants: sentinel"\n#define CAT_(a, b) a##b',
      "every kernel build fails"),
    M("sentinel-host", "clcurv/ops/registry.py", "sentinel",
      "def _finish_mls1(raw, pts, r, n, user):\n",
      "def _finish_mls1(raw, pts, r, n, user):\n    raise RuntimeError('bench.mutants: sentinel')\n",
      "MLS1's finishing step raises"),
)


# ------------------------------------------------------------------------------------------
# scratch copies
# ------------------------------------------------------------------------------------------

def _git(*args):
    return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True).stdout


def head_commit():
    return _git("rev-parse", "--short", "HEAD").decode().strip()


def make_pristine(base, worktree, extra=()):
    """The project's files into base/repo (HEAD, or the working tree's tracked files; plus
    the working tree's ``extra`` files), and base/shared linked to the repository's
    ../shared (the tests' optional data)."""
    repo = base / "repo"
    repo.mkdir(parents=True)
    if worktree:
        for name in _git("ls-files", "-z").decode().split("\0"):
            src = ROOT / name
            if name and src.is_file():
                dst = repo / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst)
    else:
        tar = _git("archive", "--format=tar", "HEAD")
        subprocess.run(["tar", "-x", "-C", str(repo)], input=tar, check=True)
    for name in extra:
        dst = repo / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, dst)
    shared = ROOT.parent / "shared"
    if shared.is_dir():
        (base / "shared").symlink_to(shared)
    return repo


def apply(mutant, repo):
    """Plant ``mutant`` in the copy ``repo``; its text must occur exactly once."""
    f = repo / mutant.path
    text = f.read_text()
    hits = text.count(mutant.old)
    if hits != 1:
        raise SystemExit(f"mutant {mutant.name}: its text occurs {hits} times in "
                         f"{mutant.path} (must be once): update bench/mutants.py\n"
                         f"  text: {mutant.old!r}")
    f.write_text(text.replace(mutant.old, mutant.new))


def check_all_apply(mutants, repo):
    for m in mutants:
        text = (repo / m.path).read_text()
        hits = text.count(m.old)
        if hits != 1:
            raise SystemExit(f"mutant {m.name}: its text occurs {hits} times in {m.path} "
                             f"(must be once): update bench/mutants.py\n  text: {m.old!r}")


def env_for(repo):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo) + (os.pathsep + env["PYTHONPATH"]
                                     if env.get("PYTHONPATH") else "")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env["COLUMNS"] = "400"                  # the summary lines keep their messages
    vendors = ROOT / ".venv" / "etc" / "OpenCL" / "vendors"
    if not env.get("OCL_ICD_VENDORS") and vendors.is_dir():
        env["OCL_ICD_VENDORS"] = str(vendors)
    return env


def check_copy_is_used(repo):
    """``import clcurv`` and its kernels must come from the copy."""
    out = subprocess.run(
        [sys.executable, "-c", "import clcurv, clcurv.runtime.program as p; "
         "print(clcurv.__file__); print(p.kernels_dir())"],
        cwd=repo, env=env_for(repo), capture_output=True, text=True)
    lines = out.stdout.split()
    want = str(repo.resolve())
    if out.returncode or len(lines) != 2 or not all(s.startswith(want) for s in lines):
        raise SystemExit(f"the scratch copy {repo} is not the code under test:\n"
                         f"{out.stdout}{out.stderr}")


def test_files(repo):
    """Every test file, FIRST first, LAST last, the others in between by name."""
    every = sorted(str(p.relative_to(repo)) for p in (repo / "tests").glob("test_*.py"))
    first = [f for f in FIRST if f in every]
    last = [f for f in LAST if f in every and f not in first]
    return first + [f for f in every if f not in first and f not in last] + last


# ------------------------------------------------------------------------------------------
# running the suite
# ------------------------------------------------------------------------------------------

_OUTCOME = re.compile(r"^(FAILED|ERROR) (.+?)(?: - (.*))?$")        # ids may hold spaces


def run_pytest(repo, args, timeout, workers):
    """(returncode or None on timeout, [(FAILED|ERROR, test id, message)], output tail,
    seconds)."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfE",
           "--color=no"]
    if workers:
        cmd += ["-n", str(workers)]
    cmd += args
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=repo, env=env_for(repo), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)          # the suite's process group only
        out, _ = proc.communicate()
        rc = None
    fails = []
    for line in out.splitlines():
        m = _OUTCOME.match(line.strip())
        if m:
            fails.append((m.group(1), m.group(2), (m.group(3) or "")[:160]))
    return rc, fails, "\n".join(out.splitlines()[-25:]), time.monotonic() - t0


class Baseline:
    """Whether a test passes on the unmutated copy (each test id run once)."""

    def __init__(self, repo, timeout):
        self.repo, self.timeout, self.known = repo, timeout, {}

    def passes(self, test_id):
        if test_id not in self.known:
            rc, _, tail, _ = run_pytest(self.repo, [test_id], self.timeout, 0)
            self.known[test_id] = rc == 0
            if rc != 0:
                print(f"    note: {test_id} fails on the unmutated copy too:\n"
                      + "\n".join("      " + s for s in tail.splitlines()[-6:]), flush=True)
        return self.known[test_id]


def run_mutant(mutant, base, pristine, files, baseline, deselected, timeout, workers):
    """Result dict of one mutant: status caught / survived / timeout / build error."""
    mdir = base / f"m-{mutant.name}"
    repo = mdir / "repo"
    shutil.copytree(pristine, repo, symlinks=True)
    if (pristine.parent / "shared").exists():
        (mdir / "shared").symlink_to((pristine.parent / "shared").resolve())
    apply(mutant, repo)
    check_copy_is_used(repo)
    t0 = time.monotonic()
    res = None
    try:
        for _ in range(6):          # a killing test that fails unmutated too: deselect, again
            args = ["-x", *files] + [a for t in sorted(deselected) for a in ("--deselect", t)]
            left = max(60.0, timeout - (time.monotonic() - t0))
            rc, fails, tail, _ = run_pytest(repo, args, left, workers)
            if rc is None:
                res = dict(status="timeout", by=f"no end within {timeout:.0f} s", detail="")
                break
            if rc == 0:
                res = dict(status="survived", by="", detail="")
                break
            if not fails:
                res = dict(status="error", by=f"pytest exit {rc}", detail=tail[-600:])
                break
            real = [f for f in fails if baseline.passes(f[1])]
            if not real:
                deselected.update(f[1] for f in fails)
                continue
            kind, test, msg = real[0]
            build = "BuildError" in msg or "build" in msg.lower() and "error" in msg.lower()
            res = dict(status="build error" if build else "caught", by=test, detail=msg)
            break
        else:
            res = dict(status="error", by="too many tests fail unmutated", detail="")
    finally:
        shutil.rmtree(mdir, ignore_errors=True)
    res.update(name=mutant.name, path=mutant.path, kind=mutant.kind,
               seconds=round(time.monotonic() - t0, 1), commit=RUN["commit"],
               date=RUN["date"], equivalent=mutant.equivalent)
    return res


RUN = {"commit": "", "date": ""}
CAUGHT = ("caught", "timeout", "build error")


# ------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------

_STATE = re.compile(r"<!-- mutants-state\n(.*?)\n-->", re.S)


def load_state(path):
    if not path.is_file():
        return {}
    m = _STATE.search(path.read_text())
    return json.loads(m.group(1)) if m else {}


def summary(rows):
    n = len(rows)
    caught = sum(r["status"] in CAUGHT for r in rows)
    equiv = sum(r["status"] == "survived" and bool(r.get("equivalent")) for r in rows)
    return n, caught, equiv


def render(rows, wall, note):
    n, caught, equiv = summary(rows)
    lines = ["# Mutation check (`python -m bench.mutants`, `make mutants`)", "",
             "Faults planted one at a time in a scratch copy of the kernels and the host's "
             "finishing and orientation code, the test suite run against each (`-x`, the "
             "fast files first; docs/mutants.md). *caught*: the first test that failed "
             "(and passes unmutated); *timeout*: the suite did not end (a hang counts as "
             "caught); *survived*: the whole suite passed.", ""]
    if n:
        lines.append(f"**Caught: {caught} of {n} ({100.0 * caught / n:.1f}%)**"
                     + (f"; {equiv} survivor(s) documented as equivalent: {caught} of "
                        f"{n - equiv} non-equivalent mutants caught "
                        f"({100.0 * caught / max(n - equiv, 1):.1f}%)" if equiv else "")
                     + ".")
    if note:
        lines += ["", note]
    lines += ["", "| mutant | file | fault | result | caught by | s | commit |",
              "|---|---|---|---|---|---:|---|"]
    for r in rows:
        result = r["status"] + (" (equivalent)" if r["status"] == "survived"
                                and r.get("equivalent") else "")
        by = r["by"].replace("|", "\\|")
        lines.append(f"| {r['name']} | {r['path']} | {r['kind']} | {result} | `{by}` | "
                     f"{r['seconds']:.0f} | {r['commit']} |" if by else
                     f"| {r['name']} | {r['path']} | {r['kind']} | {result} | | "
                     f"{r['seconds']:.0f} | {r['commit']} |")
    eq = [r for r in rows if r.get("equivalent")]
    if eq:
        lines += ["", "Equivalent mutants (no input tells them from the original):", ""]
        lines += [f"- **{r['name']}**: {r['equivalent']}" for r in eq]
    what = {m.name: m.what for m in MUTANTS}
    lines += ["", "What each mutant changes:", ""]
    lines += [f"- {r['name']}: {what.get(r['name'], '')}" for r in rows]
    if wall:
        lines += ["", wall]
    return "\n".join(lines) + "\n"


def write_report(path, results, wall):
    state = load_state(path)
    state.update({r["name"]: r for r in results})
    order = [m.name for m in MUTANTS]
    rows = [state[k] for k in order if k in state]
    for r in rows:                          # the documentation is the code's, not the file's
        r["equivalent"] = next(m.equivalent for m in MUTANTS if m.name == r["name"])
    missing = [k for k in order if k not in state]
    note = (f"Not run yet: {', '.join(missing)}." if missing else "")
    text = render(rows, wall, note)
    text += ("\n<!-- mutants-state\n" + json.dumps({r["name"]: r for r in rows}, indent=0)
             + "\n-->\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return rows


# ------------------------------------------------------------------------------------------

def select(names):
    if not names:
        return list(MUTANTS)
    pool = list(MUTANTS) + list(SENTINELS)
    out = []
    for pat in (p for n in names for p in n.split(",")):
        hit = [m for m in pool if fnmatch.fnmatchcase(m.name, pat)]
        if not hit:
            raise SystemExit(f"no mutant matches {pat!r} (see --list)")
        out += [m for m in hit if m not in out]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m bench.mutants", description=__doc__.split(
        "\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--only", action="append", metavar="NAME",
                    help="run these mutants (names or shell patterns; repeat or comma-separate)")
    ap.add_argument("--sentinel", action="store_true",
                    help="run the sentinel mutants (a failing kernel build, a raising host "
                         "step): both must be caught")
    ap.add_argument("--timeout", type=float, default=3600.0,
                    help="seconds per mutant; a suite still running then counts as caught "
                         "(a hang) [3600]")
    ap.add_argument("-n", "--workers", type=int, default=2, help="pytest-xdist workers [2]")
    ap.add_argument("--worktree", action="store_true",
                    help="copy the working tree's tracked files instead of HEAD")
    ap.add_argument("--with", dest="extra", action="append", default=[], metavar="PATH",
                    help="also copy this file of the working tree (e.g. a new test; "
                         "repeatable)")
    ap.add_argument("--tests", nargs="+", metavar="FILE",
                    help="run these test files only (to try a new test on a mutant; the "
                         "report is not written)")
    ap.add_argument("--report", type=Path, default=REPORT,
                    help=f"the report to write or update [{REPORT.relative_to(ROOT)}]")
    ap.add_argument("--no-report", action="store_true", help="print only")
    ap.add_argument("--keep", action="store_true", help="keep the scratch directory")
    ap.add_argument("--deselect", action="append", default=[], metavar="TEST_ID",
                    help="leave this test out (one known to fail unmutated; repeatable)")
    a = ap.parse_args(argv)

    if a.list:
        for m in list(MUTANTS) + list(SENTINELS):
            print(f"{m.name:28s} {m.path:26s} {m.kind:20s} {m.what}")
        print(f"\n{len(MUTANTS)} mutants (+ {len(SENTINELS)} sentinels, --sentinel)")
        return 0
    mutants = list(SENTINELS) if a.sentinel else select(a.only)
    RUN["commit"] = head_commit() + ("+worktree" if a.worktree else "") + (
        "+" + "+".join(Path(p).name for p in a.extra) if a.extra else "")
    RUN["date"] = datetime.date.today().isoformat()
    base = Path(tempfile.mkdtemp(prefix="clcurv-mutants-"))
    t_all = time.monotonic()
    results = []
    try:
        pristine = make_pristine(base, a.worktree, a.extra)
        check_all_apply(list(MUTANTS) + list(SENTINELS), pristine)
        check_copy_is_used(pristine)
        files = a.tests if a.tests else test_files(pristine)
        baseline = Baseline(pristine, a.timeout)
        deselected = set(a.deselect)
        print(f"{len(mutants)} mutant(s) on {RUN['commit']}, scratch {base}; test files in "
              f"order: {' '.join(Path(f).stem for f in files)}", flush=True)
        for i, m in enumerate(mutants, 1):
            print(f"[{i}/{len(mutants)}] {m.name} ({m.path}: {m.kind}) ...", flush=True)
            r = run_mutant(m, base, pristine, files, baseline, deselected, a.timeout,
                           a.workers)
            results.append(r)
            print(f"    {r['status']}" + (f" by {r['by']}" if r["by"] else "")
                  + (f": {r['detail']}" if r["detail"] else "") + f"  ({r['seconds']:.0f} s)",
                  flush=True)
    finally:
        if a.keep:
            print(f"scratch kept: {base}")
        else:
            shutil.rmtree(base, ignore_errors=True)
    wall = time.monotonic() - t_all
    if a.sentinel:
        bad = [r for r in results if r["status"] not in CAUGHT]
        print("sentinels: " + ("all caught" if not bad else
                               f"NOT caught: {', '.join(r['name'] for r in bad)}"))
        return 1 if bad else 0
    n, caught, equiv = summary(results)
    stamp = (f"Last run: {len(results)} mutant(s) in {wall / 60:.1f} min on {RUN['date']} "
             f"(commit {RUN['commit']}, {a.workers} pytest workers)."
             + (f" Tests deselected because they fail unmutated too: "
                f"{', '.join(sorted(deselected))}." if deselected else ""))
    if not a.no_report and not a.tests:
        rows = write_report(a.report, results, stamp)
        print(f"\nreport: {a.report}")
    else:
        rows = results
    print(render(rows, stamp, "").split("\nWhat each mutant changes:")[0])
    survivors = [r for r in results if r["status"] not in CAUGHT and not r.get("equivalent")]
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main())
