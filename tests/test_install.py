"""`pip install .` maps the top-level kernels/ into the package: every kernel builds from the
installed copy, run from outside the source tree."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

CHECK = r"""
import sys, pathlib, clcurv
from clcurv.ops.registry import program_variants
from clcurv.runtime.program import kernels_dir, build, precision_defines
kd = kernels_dir()
assert str(kd).startswith(sys.argv[1]), f"kernels found at {kd}, not in the installed copy"
dev = clcurv.get_device()
variants = program_variants(precision_defines(dev, "float"))
names = sorted({name for name, _ in variants})
for name, defines in variants:
    build(dev, name, defines)
res = clcurv.curvature(clcurv.shapes.sphere(20000, 2.0)["points"], 0.3, method="mls1")
import numpy as np
print("OK", len(names), round(float(np.median(res.mean)), 2))
"""


def test_installed_package_finds_and_builds_kernels(tmp_path):
    target = tmp_path / "site"
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                          "--no-build-isolation", "--target", str(target), str(ROOT)],
                         capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr[-2000:]
    installed = sorted(p.name for p in (target / "clcurv" / "kernels").iterdir()
                       if p.suffix in (".cl", ".h"))
    source = sorted(p.name for p in (ROOT / "kernels").iterdir() if p.suffix in (".cl", ".h"))
    assert installed == source, "a kernel file is missing from the wheel"
    env = dict(os.environ, PYTHONPATH=str(target))
    run = subprocess.run([sys.executable, "-c", CHECK, str(target)], cwd="/", env=env,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]
    ok, count, median_h = run.stdout.split()[-3:]
    assert ok == "OK" and int(count) == len([s for s in source if s.endswith(".cl")])
    assert float(median_h) == pytest.approx(0.5, abs=0.02)
