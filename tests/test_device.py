"""Device choice, program cache and build errors on the real OpenCL runtime."""
import subprocess
import sys

import pytest

import clcurv
from clcurv.operators import program_variants
from clcurv.program import BuildError, build, kernels_dir

GRID = {"REAL_IS_DOUBLE": 0, "VW": 8}


def test_devices_listed_with_capabilities():
    devs = clcurv.devices()
    assert devs, "no OpenCL device"
    for d in devs:
        assert d.kind in ("cpu", "gpu", "other") and d.max_alloc > 0 and d.max_work_group >= 1
        assert d.name and d.platform


def test_device_selection_by_index_name_and_env(monkeypatch):
    first = clcurv.devices()[0]
    assert clcurv.get_device(0).info.index == 0
    assert clcurv.get_device(first.name[:6]).info.name == first.name
    assert clcurv.get_device(first.kind).info.kind == first.kind
    monkeypatch.setenv("CLCURV_DEVICE", "0")
    assert clcurv.get_device().info.index == 0
    monkeypatch.setenv("CLCURV_DEVICE", "definitely-not-a-device")
    with pytest.raises(clcurv.NoDeviceError, match="no OpenCL device matches"):
        clcurv.get_device()
    with pytest.raises(clcurv.NoDeviceError, match="out of range"):
        clcurv.get_device(99)


def test_program_built_once_per_options(device):
    a = build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 8})
    b = build(device, "grid.cl", {"VW": 8, "REAL_IS_DOUBLE": 0})
    c = build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 4})
    assert a is b and a is not c


def test_build_error_carries_the_log(device):
    with pytest.raises(BuildError, match="VW must be 2, 4, 8 or 16"):
        build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 3})


def test_every_kernel_builds_in_both_precisions(device):
    """Every program clcurv builds (clcurv.operators.program_variants), with every optional
    branch on, covers every kernel file and builds in float and (where the device has
    fp64) double."""
    variants = program_variants(GRID)
    assert {f for f, _ in variants} == {p.name for p in kernels_dir().glob("*.cl")}
    for name, defines in variants:
        build(device, name, defines)
    if device.info.fp64:
        for name, defines in program_variants({"REAL_IS_DOUBLE": 1, "VW": 4}):
            build(device, name, defines)


def test_no_platform_gives_the_apt_command(tmp_path):
    """With the ICD loader pointed at an empty vendor directory there is no platform:
    the error names the one apt command that fixes it, and devices() is empty."""
    code = ("import clcurv\nprint(len(clcurv.devices()))\n"
            "try:\n    clcurv.curvature([[0, 0, 0.0]] * 5, 1.0)\n"
            "except clcurv.NoDeviceError as e:\n    print('ERR', e)\n")
    env = {"OCL_ICD_VENDORS": str(tmp_path), "PATH": "/usr/bin:/bin"}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "0"
    assert "apt-get install -y pocl-opencl-icd ocl-icd-libopencl1" in lines[1]
