"""Shared fixtures: the OpenCL devices (real kernels, never mocked) and shapes.

The ``device`` fixture runs a test once per OpenCL device found (pyopencl's
``pytest_generate_tests_for_pyopencl`` idea), simulators excepted: Oclgrind is ~1000x
slower and only ``tests/test_oclgrind.py`` uses it, on tiny clouds. Test ids name the
implementation (``device=1-pocl``, ``device=2-intel``).

The ICDs that ``make intel-opencl`` and ``make oclgrind`` register in
``.venv/etc/OpenCL/vendors`` are read by the loader only when ``OCL_ICD_VENDORS`` names
that folder: ``make test`` sets it, and so does this file, before any platform is
listed, when it is unset, so that a bare ``python -m pytest`` tests the same devices.
"""
import os
import re
from pathlib import Path

import numpy as np
import pytest

from clcurv.runtime.device import venv_vendors

if not os.environ.get("OCL_ICD_VENDORS") and venv_vendors().is_dir():
    os.environ["OCL_ICD_VENDORS"] = str(venv_vendors())

import clcurv  # noqa: E402  (after OCL_ICD_VENDORS: the loader reads it once)


def _found():
    try:
        return clcurv.devices()
    except Exception:  # no platform: every device test fails loudly below
        return []


def _slug(info):
    """'pocl', 'intel', 'oclgrind', ...: the implementation, for test ids."""
    words = f"{info.platform} {info.driver} {info.version}".lower()
    if "pocl" in words:
        return "pocl"
    word = re.match(r"[a-z0-9]*", info.platform.lower()).group()
    return word or "dev"


#: indices of the real OpenCL devices (every test with a ``device`` argument runs on each)
DEVICES = [d.index for d in _found() if not d.simulator]
#: indices of the simulators (Oclgrind): tests/test_oclgrind.py only
SIMULATORS = [d.index for d in _found() if d.simulator]
NAMES = {d.index: f"{d.index}-{_slug(d)}" for d in _found()}


@pytest.fixture(params=DEVICES or [None], ids=lambda i: NAMES.get(i, "none"))
def device(request):
    """Every real OpenCL device present; fails (not skips) when there is none."""
    if request.param is None:
        pytest.fail("no OpenCL device found: " + clcurv.runtime.device.APT_HINT)
    return clcurv.get_device(request.param)


#: the external data sets, made outside the project (../shared/data next to the repository,
#: described by its README): a bare clone has none of them
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: the small ones shipped with the suite, byte-exact copies (tests/data/README.md: sources
#: and licences)
TEST_DATA = Path(__file__).resolve().parent / "data"


def data_path(name):
    """The data file ``name`` (a file name of ../shared/data): the shared copy when present,
    else the one shipped in tests/data, else None (the caller skips, naming the file)."""
    for folder in (SHARED_DATA, TEST_DATA):
        path = folder / name
        if path.is_file():
            return path
    return None


def data_params(names):
    """Parameters for a test run once per data file: one per file found (``data_path``),
    and, when some are not, ONE skipped parameter naming them all (a bare clone reports
    the missing large scans on one line, not one skip per file)."""
    names = list(names)
    absent = [n for n in names if data_path(n) is None]
    params = [pytest.param(n, id=n) for n in names if n not in absent]
    if absent:
        params.append(pytest.param(None, id="absent", marks=pytest.mark.skip(
            reason=f"{len(absent)} data files not present: ../shared/data is absent and they "
                   f"are too large to ship in tests/data: {', '.join(absent)}")))
    return params


def bumpy_surface(n, seed, noise=0.002):
    """A smooth random height field z = 0.2 sin(3x) cos(2y) over [-1, 1]^2 with noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    z = 0.2 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1]) + noise * rng.normal(size=n)
    return np.column_stack([xy, z])


def worst(values, k=5):
    """The k worst entries with their indices, for assertion messages."""
    values = np.asarray(values)
    idx = np.argsort(values)[::-1][:k]
    return ", ".join(f"[{i}]={values[i]:.3g}" for i in idx)


def pytest_configure(config):
    # Tests that build their own kernel sources with pyopencl (test_eig3*.py,
    # test_kernel_contract.py) bypass clcurv.runtime.program.build, which reads the build log and
    # re-raises its warning lines as clcurv.runtime.program.BuildWarning. Intel's CPU runtime logs
    # every build ("Compilation started", vectoriser remarks), and pyopencl turns any
    # non-empty log into this CompilerWarning: it carries no warning of the compiler.
    config.addinivalue_line(
        "filterwarnings", "ignore:Non-empty compiler output encountered:UserWarning")
