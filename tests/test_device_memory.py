"""Clouds too big for the device run in chunks of sorted points (clcurv.grid.cloud.DeviceCloud.plan),
with results bit-identical to the whole-cloud run; only data that must stay whole on the
device (coordinates, grid, normals, density weights, the scale space's iterates) can make a
cloud fail, and then the error says how many points fit.

The device's memory is limited with clcurv.runtime.limits.DEVICE_MEMORY (the
CLCURV_DEVICE_MEMORY knob), so a 20k-point cloud is split like a 10M-point one on a small
device; the real kernels run (no mocks)."""
import re

import numpy as np
import pyopencl as cl
import pytest

import clcurv
from clcurv.grid import cloud as cloud_mod
from clcurv.runtime import limits
from clcurv.grid.cloud import MIN_CHUNK, DeviceCloud, DeviceMemoryError, upload_sorted

N, R, RADIUS = 20_000, 2.0, 0.2
#: the chunk the tests force: odd (not a multiple of any vector width VW), and 20000 points
#: make 7 chunks, the last one partial (20000 - 6 * 2861 = 2834)
CHUNK = 2861
CHUNKS = 7


@pytest.fixture(scope="module")
def sphere():
    s = clcurv.shapes.sphere(N, R)
    return s["points"], s["normals"]


@pytest.fixture
def budget(monkeypatch):
    """set(bytes): limit the device memory clcurv uses (None: the device's own limits)."""
    monkeypatch.delenv("CLCURV_DEVICE_MEMORY", raising=False)
    return lambda nbytes: monkeypatch.setattr(limits, "DEVICE_MEMORY", nbytes)


def for_chunk(plan, chunk=CHUNK):
    """The budget under which ``plan``'s stage runs in chunks of ``chunk`` points."""
    return plan.held + chunk * plan.per_point


def assert_bit_identical(a, b):
    a, b = (x.arrays() if hasattr(x, "arrays") else {"": x} for x in (a, b))
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)   # NaN == NaN here


def assert_chunked(plan, device):
    assert (plan.count, plan.chunk) == (CHUNKS, CHUNK), plan
    vw = clcurv.runtime.program.precision_defines(device, "float")["VW"]
    assert plan.chunk % vw and plan.n % plan.chunk, "a partial last chunk, chunks not k VW"


CASES = [(m, "uniform") for m in clcurv.METHODS] + [("variation", "density"),
                                                    ("2dcov2", "density"), ("mls2", "density")]


@pytest.mark.parametrize("method,weights", CASES, ids=[f"{m}-{w}" for m, w in CASES])
def test_operators_in_chunks_are_bit_identical(device, sphere, budget, method, weights):
    pts, nrm = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    run = lambda: clcurv.curvature(cloud, RADIUS, method=method, weights=weights, normals=nrm)
    whole = run()
    plan = cloud.plans[f"kernel_{clcurv.ops.registry.OPERATORS[method].kernel.name}"]
    assert plan.count == 1
    budget(for_chunk(plan))
    parts = run()
    assert_chunked(cloud.plans[plan.what], device)
    assert_bit_identical(whole, parts)


def test_double_precision_in_chunks(device, sphere, budget):
    if not device.info.fp64:
        pytest.skip("device without fp64")
    pts, nrm = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device, precision="double")
    run = lambda: clcurv.curvature(cloud, RADIUS, method="mls2", normals=nrm)
    whole = run()
    budget(for_chunk(cloud.plans["kernel_mls2"]))
    parts = run()
    assert_chunked(cloud.plans["kernel_mls2"], device)
    assert_bit_identical(whole, parts)


@pytest.mark.parametrize("orient", [None, "up"])
def test_mls2_without_reference_normals_and_pca_normals_in_chunks(device, sphere, budget,
                                                                  orient):
    pts, _ = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    whole = clcurv.curvature(cloud, RADIUS, method="mls2", orient=orient)
    budget(for_chunk(cloud.plans["kernel_mls2"]))
    parts = clcurv.curvature(cloud, RADIUS, method="mls2", orient=orient)
    assert_chunked(cloud.plans["kernel_mls2"], device)
    assert_bit_identical(whole, parts)


def test_orientation_graph_is_whole_cloud(device, sphere, budget):
    """The MST orientation's graph (k edges per point) is not chunked: under a budget that
    holds only the operators' chunks it is refused by name, never skipped or replaced."""
    pts, _ = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    clcurv.curvature(cloud, RADIUS, method="mls2", orient=None)
    budget(for_chunk(cloud.plans["kernel_mls2"]))
    with pytest.raises(DeviceMemoryError, match="orientation graph"):
        clcurv.curvature(cloud, RADIUS, method="mls2", orient="mst")


@pytest.mark.parametrize("weights", ["uniform", "density"])
def test_normals_in_chunks_are_bit_identical(device, sphere, budget, weights):
    pts, _ = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    whole = clcurv.normals(cloud, RADIUS, weights=weights, orient=None)
    budget(for_chunk(cloud.plans["kernel_moments"]))
    parts = clcurv.normals(cloud, RADIUS, weights=weights, orient=None)
    assert_chunked(cloud.plans["kernel_moments"], device)
    assert_bit_identical(whole, parts)


@pytest.mark.parametrize("weights", ["uniform", "density"])
def test_scale_space_in_chunks_is_bit_identical(device, sphere, budget, weights):
    pts, _ = sphere
    run = lambda: clcurv.scale_space(pts, RADIUS, 3, weights=weights, device=device.info.index,
                                     return_iterates=True, return_stats=True)
    whole, stats = run()
    assert stats["plan"].count == 1
    budget(for_chunk(stats["plan"]))
    parts, stats = run()
    assert_chunked(stats["plan"], device)
    for a, b in zip(whole, parts):
        assert_bit_identical(a, b)


def test_scale_space_in_chunks_with_rebinning(device, budget):
    """Noise of 0.1 r: points drift far enough to re-bin (a new cloud, planned again)."""
    pts = clcurv.shapes.sphere(N, R, noise=0.03, seed=9)["points"]
    run = lambda: clcurv.scale_space(pts, 0.3, 5, device=device.info.index, return_stats=True)
    whole, stats = run()
    budget(for_chunk(stats["plan"]))
    parts, stats = run()
    assert stats["rebins"] >= 1 and stats["plan"].count >= CHUNKS - 1
    assert_bit_identical(whole, parts)


def test_upload_of_normals_in_chunks_of_input_rows(device, sphere, budget):
    """The staging buffer of upload_sorted holds one chunk of input rows at a time."""
    pts, nrm = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)

    def upload():
        cols = [np.empty(N + cloud_mod.PAD, cloud.dtype) for _ in range(3)]
        for col, buf in zip(cols, upload_sorted(cloud, nrm)):
            cl.enqueue_copy(cloud.device.queue, col, buf)
        return cols
    whole = upload()
    assert cloud.plans["upload_normals"].count == 1
    budget(for_chunk(cloud.plans["upload_normals"]))
    parts = upload()
    assert_chunked(cloud.plans["upload_normals"], device)
    for a, b in zip(whole, parts):
        np.testing.assert_array_equal(a, b)


def fitting_points(message):
    m = re.search(r"About (\d+) points", message)
    assert m, message
    return int(m.group(1))


def test_a_cloud_whose_coordinates_do_not_fit_says_what_fits(device, sphere, budget):
    pts, _ = sphere
    need = DeviceCloud(pts, RADIUS, device=device).device_bytes
    budget(need - 1)
    with pytest.raises(DeviceMemoryError) as err:
        clcurv.curvature(pts, RADIUS, method="mls1", orient=None, device=device.info.index)
    msg = str(err.value)
    fit = fitting_points(msg)
    assert 0 < fit < N
    assert "float" in msg and "MiB" in msg and "CLCURV_DEVICE_MEMORY" in msg
    # a cloud of 95% of that size at the same density (a smaller sphere) runs
    k = int(0.95 * fit)
    smaller = clcurv.shapes.sphere(k, R * np.sqrt(k / N))["points"]
    res = clcurv.curvature(smaller, RADIUS, method="mls1", orient=None, device=device.info.index)
    assert len(res) == k and np.count_nonzero(res.valid) > 0.99 * k


def test_density_weights_that_do_not_fit_say_what_fits(device, sphere, budget):
    pts, _ = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    clcurv.normals(cloud, RADIUS, orient=None)
    plan = cloud.plans["kernel_moments"]
    budget(for_chunk(plan, MIN_CHUNK + 100))            # uniform fits in chunks ...
    clcurv.normals(cloud, RADIUS, orient=None)
    assert cloud.plans["kernel_moments"].chunk == MIN_CHUNK + 100
    with pytest.raises(DeviceMemoryError) as err:       # ... the density weights do not
        clcurv.normals(cloud, RADIUS, weights="density", orient=None)
    msg = str(err.value)
    assert "density weights" in msg
    assert 0 < fitting_points(msg) < N


def test_the_environment_variable_limits_device_memory(device, sphere, monkeypatch):
    pts, _ = sphere
    cloud = DeviceCloud(pts, RADIUS, device=device)
    clcurv.normals(cloud, RADIUS, orient=None)
    plan = cloud.plans["kernel_moments"]
    monkeypatch.setattr(limits, "DEVICE_MEMORY", None)
    monkeypatch.setenv("CLCURV_DEVICE_MEMORY", str(for_chunk(plan)))
    clcurv.normals(cloud, RADIUS, orient=None)
    assert cloud.plans["kernel_moments"].chunk == CHUNK
