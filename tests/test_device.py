"""Device choice, program cache and build errors on the real OpenCL runtime."""
import dataclasses
import subprocess
import sys
import uuid
import warnings

import pytest

import clcurv
from clcurv.cli import main as cli
from clcurv.runtime.device import _default
from clcurv.ops.registry import program_variants
from clcurv.runtime.program import (BuildError, BuildWarning, _warn_from_log, build, kernels_dir,
                            log_warnings)

from conftest import DEVICES, SIMULATORS

GRID = {"REAL_IS_DOUBLE": 0, "VW": 8, "MASKED_SUMS": 1, "PCA_FMA": 1}


def test_devices_listed_with_capabilities():
    devs = clcurv.devices()
    assert devs, "no OpenCL device"
    for d in devs:
        assert d.kind in ("cpu", "gpu", "accelerator", "other") and d.max_alloc > 0
        assert d.max_work_group >= 1 and d.name and d.platform
        assert isinstance(d.simulator, bool)
    assert DEVICES, "no real (non-simulator) OpenCL device"


def test_device_selection_by_index_name_and_env(monkeypatch):
    real = clcurv.devices()[DEVICES[0]]
    assert clcurv.get_device(real.index).info.index == real.index
    assert clcurv.get_device(real.name[:6]).info.name == real.name
    assert clcurv.get_device(real.kind).info.kind == real.kind
    monkeypatch.setenv("CLCURV_DEVICE", str(real.index))
    assert clcurv.get_device().info.index == real.index
    monkeypatch.setenv("CLCURV_DEVICE", "definitely-not-a-device")
    with pytest.raises(clcurv.NoDeviceError, match="no OpenCL device matches"):
        clcurv.get_device()
    with pytest.raises(clcurv.NoDeviceError, match="out of range"):
        clcurv.get_device(99)


def test_spec_matches_the_platform_name_and_vendor():
    """'pocl' is PoCL, whose device is 'pthread-<cpu>' and platform 'Portable Computing
    Language' by 'The pocl project'; a platform match wins over a device-name match."""
    devs = clcurv.devices()
    pocl = [d for d in devs if d.platform == "Portable Computing Language"]
    if not pocl:
        pytest.skip("PoCL is not installed here")
    assert clcurv.get_device("pocl").info.index == pocl[0].index
    assert clcurv.get_device("Portable").info.index == pocl[0].index
    for d in devs:           # every platform is reachable by its name
        assert clcurv.get_device(d.platform).info.platform == d.platform


def test_no_match_lists_devices_and_platforms():
    with pytest.raises(clcurv.NoDeviceError) as err:
        clcurv.get_device("no-such-thing")
    for d in clcurv.devices():
        assert d.name in str(err.value) and d.platform in str(err.value)


def _record(index, kind, simulator, name="dev"):
    """A DeviceInfo record (data only: the choice logic reads no OpenCL object)."""
    return clcurv.runtime.device.DeviceInfo(index, name, "platform", "vendor", kind, "1", "1.2", True,
                                    1, 1, 1, 1, 1, simulator=simulator)


def test_default_is_never_a_simulator():
    """A simulator that reports itself as a GPU (Oclgrind sets every type bit) is not the
    default; a real GPU beats a CPU; only simulators: no default, and why."""
    sim, cpu, gpu = _record(0, "gpu", True), _record(1, "cpu", False), _record(2, "gpu", False)
    assert _default([sim, cpu]) == (1, "the first CPU device (no GPU)")
    assert _default([sim, cpu, gpu]) == (2, "the first GPU")
    index, why = _default([sim])
    assert index is None and "only simulators" in why and "apt-get install" in why
    devs = clcurv.devices()
    assert devs.default is not None and not devs[devs.default].simulator
    assert not clcurv.get_device().info.simulator


def test_simulators_only_when_named():
    """Oclgrind (installed by make test): a kind ('gpu', 'cpu') never picks it, its name does."""
    if not SIMULATORS:
        pytest.skip("no simulator installed (make oclgrind)")
    for kind in ("gpu", "cpu", "accelerator"):
        try:
            assert not clcurv.get_device(kind).info.simulator
        except clcurv.NoDeviceError as exc:
            assert f"no OpenCL {kind} device" in str(exc)
    named = clcurv.get_device(clcurv.devices()[SIMULATORS[0]].platform)
    assert named.info.simulator


def test_every_icd_file_loads_a_device():
    """Each .icd file the loader read gave at least one device (the Intel wheel's own
    file names a placeholder path: that is what this catches), and every device's library
    is one an ICD file names."""
    devs = clcurv.devices()
    assert devs.icds, f"no .icd file found in {devs.vendors}"
    dead = [str(i) for i in devs.icds if i.devices == 0]
    assert not dead, "ICD files that load no device: " + "; ".join(dead)
    if sys.platform.startswith("linux"):
        assert all(d.library for d in devs), [(d.name, d.library) for d in devs]
        assert sum(i.devices for i in devs.icds) == len(devs)


def test_devices_command_marks_the_default_and_why():
    lines = []
    cli.devices_cmd(None, out=lines.append)
    devs = clcurv.devices()
    marked = [ln for ln in lines if ln[:2] == "* " and ln[2].isdigit()]
    assert marked == [ln for ln in lines if ln.startswith(f"* {devs.default}: ")]
    assert len(marked) == 1 and f"* = default: {devs.reason}" in lines
    assert sum("simulator: used only when named" in ln for ln in lines) == len(SIMULATORS)
    assert sum(ln.startswith("  /") and ".icd -> " in ln for ln in lines) == len(devs.icds)


def test_build_log_warnings_are_raised_and_remarks_dropped(device):
    """A compiler warning in a build log becomes a BuildWarning naming the file; a
    clean build (whatever the runtime logs: Intel's progress and vectoriser remarks) warns
    nothing."""
    import pyopencl as cl
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        # a fresh source each run: from pyopencl's binary cache (used on Intel) the log
        # holds no compiler message
        prg = cl.Program(device.context, f"// {uuid.uuid4()}\n#warning clcurv-test\n"
                         "__kernel void k(__global float *a) { a[0] = 1.0f; }").build()
    with pytest.warns(BuildWarning, match="x.cl on .*clcurv-test"):
        _warn_from_log(device, "x.cl", prg)
    clcurv.runtime.program._cache.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 8})


#: PoCL's build log of knn.cl on an AVX2 CPU without AVX-512 (AMD EPYC, PoCL 3.1), two of its
#: 20 lines: clang's -Wpsabi notes on 512-bit vectors passed to builtins
ABI_LOG = (
    "warning: /root/.cache/pocl/kcache/tempfile_EHDnz5.cl:63:12 <Spelling=<scratch space>:55:1>"
    ": AVX vector return of type 'ulong8' (vector of 8 'ulong' values) without 'avx512f' "
    "enabled changes the ABI\n"
    "warning: /root/.cache/pocl/kcache/tempfile_EHDnz5.cl:84:12 <Spelling=/lib/x86_64-linux-gnu/"
    "../../share/pocl/include/_builtin_renames.h:839:27>: AVX vector argument of type "
    "'__private ulong16' (vector of 16 'ulong' values) without 'avx512f' enabled changes the "
    "ABI\n")


def test_abi_notes_are_dropped_and_real_warnings_kept():
    """clang's notes on wide vectors (logged by PoCL on every AVX2 CPU) are no BuildWarning;
    a real warning or error beside them still is."""
    assert log_warnings(ABI_LOG) == []
    real = "x.cl:3:2: warning: unused variable 'v'"
    error = "x.cl:9:1: error: AVX vector argument missing"
    assert log_warnings(ABI_LOG + real + "\n" + error + "\n") == [real, error]
    assert log_warnings("Compilation started\nremark: loop not vectorized\n") == []


def test_compiler_diagnostic_counts_do_not_reach_stderr():
    """PoCL's clang writes "N warnings generated." to fd 2 on a compile missing from its
    kernel cache: a build under _stderr_counts_dropped leaves stderr with the other lines
    only (here a line written to fd 2 directly and a Python one), in order."""
    code = (
        "import os, sys, uuid, warnings, pyopencl as cl\n"
        "from clcurv.runtime.program import _stderr_counts_dropped\n"
        "from clcurv.runtime.device import get_device\n"
        "dev = get_device()\n"
        "src = f'#warning clcurv-count-test\\n__kernel void k_{uuid.uuid4().hex}"
        "(__global float *a) {{ a[0] = 1.0f; }}'\n"
        "with warnings.catch_warnings(), _stderr_counts_dropped():\n"
        "    warnings.simplefilter('ignore')\n"
        "    os.write(2, b'2 warnings generated.\\nbefore\\n')\n"
        "    cl.Program(dev.context, src).build()\n"
        "    print('after', file=sys.stderr)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stderr == "before\nafter\n"


def test_program_built_once_per_options(device):
    a = build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 8})
    b = build(device, "grid.cl", {"VW": 8, "REAL_IS_DOUBLE": 0})
    c = build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 4})
    assert a is b and a is not c


def test_build_error_carries_the_log(device):
    with pytest.raises(BuildError, match="VW must be 2, 4, 8 or 16"):
        build(device, "grid.cl", {"REAL_IS_DOUBLE": 0, "VW": 3})


def test_every_kernel_builds_in_both_precisions(device):
    """Every program clcurv builds (clcurv.ops.registry.program_variants), with every optional
    branch on, covers every kernel file and builds in float and (where the device has
    fp64) double."""
    variants = program_variants(GRID)
    assert {f for f, _ in variants} == {p.name for p in kernels_dir().glob("*.cl")}
    for name, defines in variants:
        build(device, name, defines)
    if device.info.fp64:
        for name, defines in program_variants({"REAL_IS_DOUBLE": 1, "VW": 4, "MASKED_SUMS": 0,
                                                "PCA_FMA": 0}):
            build(device, name, defines)


def test_no_platform_gives_the_apt_command(tmp_path):
    """With the ICD loader pointed at an empty vendor directory there is no platform:
    the error names the one apt command that fixes it, and devices() is empty."""
    code = ("import clcurv\nprint(sum(not d.simulator for d in clcurv.devices()))\n"
            "try:\n    clcurv.curvature([[0, 0, 0.0]] * 5, 1.0)\n"
            "except clcurv.NoDeviceError as e:\n    print('ERR', e)\n")
    env = {"OCL_ICD_VENDORS": str(tmp_path), "PATH": "/usr/bin:/bin"}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "0"
    assert "apt-get install -y pocl-opencl-icd ocl-icd-libopencl1" in lines[1]
