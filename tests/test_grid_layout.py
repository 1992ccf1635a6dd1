"""Host binning (clcurv/grid/binning.py) and the device cell ranges (kernels/grid.cl) against a
brute-force numpy construction."""
import numpy as np
import pyopencl as cl
import pytest

from clcurv.grid import binning as G
from clcurv.grid.cloud import DeviceCloud


def clouds():
    rng = np.random.default_rng(7)
    sphere = rng.normal(size=(30_000, 3))
    sphere /= np.linalg.norm(sphere, axis=1)[:, None]
    blob = rng.uniform(-1, 1, (5_000, 3)) * [3.0, 1.0, 0.2] + 1e6     # offset, flat
    line = np.stack([np.linspace(0, 1, 2_000)] + [np.zeros(2_000)] * 2, 1)   # nx only
    dup = np.repeat(rng.uniform(size=(50, 3)), 20, axis=0)              # coincident points
    far = np.vstack([rng.normal(0, 0.1, (300, 3)), rng.normal(1.5e5, 0.1, (300, 3))])
    return {"sphere": (sphere, 0.05), "blob": (blob, 0.1), "line": (line, 0.01),
            "dup": (dup, 0.2), "far": (far, 0.1)}     # far: 2^61 cells, key and index unpacked


@pytest.mark.parametrize("name", list(clouds()))
def test_bin_points_layout(name):
    pts, cell = clouds()[name]
    g = G.bin_points(pts, cell)
    lo = pts.min(0)
    ijk = np.floor((pts - lo) / cell).astype(np.int64)
    nx, ny, nz = g.dims
    key = (ijk[:, 2] * ny + ijk[:, 1]) * nx + ijk[:, 0]
    assert np.array_equal(g.order, np.argsort(key, kind="stable"))      # stable sort
    assert np.array_equal(g.keys, np.unique(key))
    assert np.array_equal(g.keys[g.cell_of], key[g.order])
    assert np.array_equal(g.cell_start[:-1], np.searchsorted(key[g.order], g.keys))
    assert g.cell_start[-1] == len(pts)
    # coordinates relative to the corner of the point's cell (float64, then cast)
    n = len(pts)
    rel = ((pts - lo) - ijk * cell)[g.order]
    for d, c in enumerate((g.x, g.y, g.z)):
        np.testing.assert_allclose(c[:n], rel[:, d], rtol=0, atol=2e-7 * cell)
        assert not c[n:].any() and len(c) == n + G.PAD
    assert rel.min() >= -1e-9 * cell and rel.max() <= cell * (1 + 1e-9)
    assert np.array_equal(g.cell_index(), ijk[g.order])
    np.testing.assert_allclose(g.positions(), pts[g.order], rtol=0, atol=1e-6 * cell)


@pytest.mark.parametrize("fits", [True, False], ids=["packed", "fallback"])
def test_sort_cells_packed_and_fallback(fits):
    """_sort_cells: keys with the point index packed below them (one plain sort), or the
    stable argsort when key and index do not fit 63 bits; cells spanning several blocks."""
    rng = np.random.default_rng(5)
    key = rng.integers(0, 40, 9 * G.BLOCK + 7)                  # several blocks
    key[::997] = 41 if fits else 2 ** 60
    bits = G._index_bits(len(key), 42.0 if fits else float(2 ** 61))
    assert (bits > 0) == fits
    packed = key << bits | np.arange(len(key)) if bits else key.copy()
    order, keys, start = G._sort_cells(packed, bits)
    want = np.argsort(key, kind="stable")
    assert np.array_equal(order, want)
    assert np.array_equal(keys, np.unique(key))
    assert np.array_equal(start[:-1], np.searchsorted(key[want], keys))
    assert start[-1] == len(key)
    assert np.array_equal(np.repeat(keys, np.diff(start)), key[want])


@pytest.mark.parametrize("top", [40, 2 ** 16 - 1, 2 ** 16, 2 ** 32 - 1, 2 ** 32, 2 ** 60])
def test_stable_order_is_the_stable_argsort(top):
    """_stable_order: by one or two radix passes on 16-bit digits (keys below 2^16, 2^32),
    else numpy's stable argsort: the stable argsort of the keys, ties in input order, on
    keys crowding both ends of the range; empty input too."""
    rng = np.random.default_rng(7)
    key = np.concatenate([rng.integers(0, 50, 3000), rng.integers(max(top - 50, 0), top + 1, 3000),
                          rng.integers(0, top + 1, 3000)])
    key = key[rng.permutation(len(key))]
    assert np.array_equal(G._stable_order(key), np.argsort(key, kind="stable"))
    assert len(G._stable_order(np.empty(0, np.int64))) == 0


def test_radix_and_packed_binnings_are_the_same(monkeypatch):
    """bin_points sorts the keys by radix passes (up to RADIX_POINTS points, keys below
    2^32) or packs the point index below them: the same grid either way."""
    rng = np.random.default_rng(8)
    pts = rng.normal(size=(3 * G.MIN_PARALLEL, 3))
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    got = []
    for points in (G.RADIX_POINTS, 0):
        monkeypatch.setattr(G, "RADIX_POINTS", points)
        got.append(G.bin_points(pts, 0.05))
    a, b = got
    for name in ("order", "keys", "cell_start", "rel"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_sort_distinct_in_parts_matches_sort():
    """_sort_distinct: a selection, then parts sorted on threads, sorts as np.sort."""
    rng = np.random.default_rng(4)
    for n in (10, G.MIN_PARALLEL - 1, 3 * G.MIN_PARALLEL + 5):
        a = rng.choice(2 ** 40, size=n, replace=False).astype(np.int64)
        b = a.copy()
        G._sort_distinct(b)
        assert np.array_equal(b, np.sort(a))


def test_bounding_box_matches_min_max():
    rng = np.random.default_rng(3)
    for n in (1, 5, 1023, 1024, 1025, 5000, G.MIN_PARALLEL + 1001):    # last: in parts
        p = rng.normal(size=(n, 3))
        lo, hi = G.bounding_box(p)
        assert np.array_equal(lo, p.min(0)) and np.array_equal(hi, p.max(0))


@pytest.mark.parametrize("name", list(clouds()))
def test_cell_ranges_brute_force(name, device):
    pts, cell = clouds()[name]
    c = DeviceCloud(pts, cell, device=device)
    g = c.grid
    head = np.empty(2, np.uint32)
    cl.enqueue_copy(c.device.queue, head, c.ranges)
    c.device.queue.finish()
    assert tuple(head) == (g.ncells, 0) and not c.middles    # rows only, until a pruned walk
    rows_only = c.ranges
    flat = np.empty(2 + g.ncells * 36, np.uint32)      # header, the rows, their middles
    cl.enqueue_copy(c.device.queue, flat, c.with_middles())
    c.device.queue.finish()
    assert tuple(flat[:2]) == (g.ncells, 1) and c.middles and c.ranges is not rows_only
    assert c.with_middles() is c.ranges                  # made once
    rows = flat[2:2 + 18 * g.ncells].reshape(g.ncells, 9, 2)
    mids = flat[2 + 18 * g.ncells:].reshape(g.ncells, 9, 2)
    nx, ny, nz = g.dims
    ix = g.keys % nx
    iy = (g.keys // nx) % ny
    iz = g.keys // (nx * ny)
    for ci in range(g.ncells):
        want = []
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                y, z = iy[ci] + dy, iz[ci] + dz
                if not (0 <= y < ny and 0 <= z < nz):
                    want.append((0, 0, 0, 0))
                    continue
                row = (z * ny + y) * nx
                a = np.searchsorted(g.keys, row + max(ix[ci] - 1, 0))
                b = np.searchsorted(g.keys, row + min(ix[ci] + 1, nx - 1) + 1)
                # the middle cell (ix, y, z): its points, or none where it begins
                m0 = np.searchsorted(g.keys, row + ix[ci])
                m1 = np.searchsorted(g.keys, row + ix[ci] + 1)
                want.append((g.cell_start[a], g.cell_start[m0], g.cell_start[m1], g.cell_start[b])
                            if b > a else (0, 0, 0, 0))
        want = np.array(want, np.uint32)
        assert np.array_equal(rows[ci], want[:, [0, 3]]), ci
        assert np.array_equal(mids[ci], want[:, [1, 2]]), ci


@pytest.mark.parametrize("name", list(clouds()))
def test_device_x_copies_and_row_alignment(name, device):
    """grid.cl:expand_x: copy a of x is relative to the point's 3-cell block starting at an
    index = a mod 3; cell_of's top bits hold the alignment (ix - 1) mod 3 of its rows."""
    pts, cell = clouds()[name]
    c = DeviceCloud(pts, cell, device=device)
    g, n, m = c.grid, len(pts), len(pts) + G.PAD
    x = np.empty(3 * m, np.float32)
    co = np.empty(n, np.uint32)
    cl.enqueue_copy(c.device.queue, x, c.x)
    cl.enqueue_copy(c.device.queue, co, c.cell_of)
    ix = g.cell_index()[:, 0]
    assert np.array_equal(co & G.CELL_MASK, g.cell_of)
    assert np.array_equal(co >> G.CELL_BITS, (ix - 1) % 3)
    x0 = g.positions()[:, 0] - g.origin[0]
    for a in range(3):
        block = (ix - a) // 3 * 3 + a
        np.testing.assert_allclose(x[a * m:a * m + n], x0 - block * cell, rtol=0,
                                   atol=4e-7 * cell)
        assert not x[a * m + n:(a + 1) * m].any()
