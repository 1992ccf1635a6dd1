"""The per-point data movers of kernels/records.cl against numpy: output records split into
input-order fields (mapped and copied host transfers, float and double), and the gather of
input-order rows to the sorted, padded device columns."""
import numpy as np
import pyopencl as cl
import pytest

from clcurv.grid.cloud import RECORD, DeviceCloud, empty_fields, place_records, upload_sorted
from clcurv.grid.binning import PAD

LAYOUT = {"a": slice(0, 3), "b": 3, "c": slice(4, 6), "count": 9, "status": 10}


def fetch_records(cloud, rec, layout, mapped=None):
    """The fields of the records ``rec`` (one per point, input order) as host arrays, as
    the operators' driver brings them back (clcurv.grid.cloud.place_records, one chunk).

    ``layout`` maps a name to a record column or a slice of columns, and must name 'count'
    (stored as uint bits) and 'status' (a small integer). Real fields come back as float64
    (N,) or (N, width) arrays, 'count' as int64 and 'status' as uint8.
    """
    out = empty_fields(layout, cloud.n)
    place_records(cloud, rec, layout, out, 0, cloud.n, False, mapped)
    return out


def cloud_and_records(device, precision, n=5000):
    rng = np.random.default_rng(11)
    cloud = DeviceCloud(rng.normal(size=(n, 3)), 0.3, device=device, precision=precision)
    rec = rng.normal(size=(n, RECORD)).astype(cloud.dtype)
    tiny = np.finfo(cloud.dtype).tiny
    rec[:8, 0] = [np.nan, np.inf, -np.inf, -0.0, tiny / 4, -tiny, 3.4e38, 1e-30]
    counts = rng.integers(0, 2 ** 31, n, dtype=np.int64)
    bits = rec.view(np.uint32 if cloud.dtype == np.float32 else np.uint64)
    bits[:, 9] = counts
    rec[:, 10] = rng.integers(0, 4, n)
    buf = cl.Buffer(cloud.device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                    hostbuf=rec)
    return cloud, rec, buf, counts


@pytest.mark.parametrize("precision", ["float", "double"])
@pytest.mark.parametrize("mapped", [True, False, None])
def test_fetch_records_splits_fields_exactly(device, precision, mapped):
    """mapped=None: the default, on a CPU device with fp64 the split straight into the host
    arrays (clcurv.grid.cloud.split_into_host); NaN, infinities, -0 and subnormals included."""
    if precision == "double" and not device.info.fp64:
        pytest.skip("device without fp64")
    cloud, rec, buf, counts = cloud_and_records(device, precision)
    out = fetch_records(cloud, buf, LAYOUT, mapped=mapped)
    assert set(out) == set(LAYOUT)
    for name in ("a", "b", "c"):
        assert out[name].dtype == np.float64 and out[name].flags.c_contiguous
        np.testing.assert_array_equal(out[name], rec[:, LAYOUT[name]].astype(np.float64))
        assert np.array_equal(np.signbit(out[name]), np.signbit(rec[:, LAYOUT[name]]))
    assert out["count"].dtype == np.int64 and np.array_equal(out["count"], counts)
    assert out["status"].dtype == np.uint8
    np.testing.assert_array_equal(out["status"], rec[:, 10].astype(np.uint8))


def test_upload_sorted_gathers_rows_in_cell_order(device):
    rng = np.random.default_rng(12)
    pts = rng.normal(size=(3000, 3))
    cloud = DeviceCloud(pts, 0.2, device=device)
    values = rng.normal(size=(3000, 3))
    want = values[cloud.grid.order].astype(np.float32)
    for d, buf in enumerate(upload_sorted(cloud, values)):
        col = np.empty(len(pts) + PAD, np.float32)
        cl.enqueue_copy(cloud.device.queue, col, buf)
        np.testing.assert_array_equal(col[:len(pts)], want[:, d])
        assert not col[len(pts):].any()
