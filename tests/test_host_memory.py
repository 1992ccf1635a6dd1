"""The host pool of result arrays (clcurv._shared.host_memory): a dropped result's pages are reused,
never while any view of them is alive, within the hold limit; release and CLCURV_POOL=0."""
import os
import pickle

import numpy as np
import pytest

import clcurv
from clcurv._shared import host_memory as hm


def held_bytes():
    """Bytes the pool holds unused."""
    return hm._STATE["held"]


@pytest.fixture
def pool(monkeypatch):
    hm.release()
    monkeypatch.setitem(hm._STATE, "holding", True)
    yield hm
    hm.release()


def test_a_dropped_array_is_reused_and_a_live_one_never(pool):
    a = pool.empty((300_000, 3))                      # 7.2 MB: pooled
    assert a.flags.c_contiguous and a.flags.writeable and a.dtype == np.float64
    assert a.shape == (300_000, 3)
    where, size = a.ctypes.data, pool._bin(a.nbytes)
    a[:] = 1.0
    view = a[::7]                                     # keeps the block alive
    del a
    assert held_bytes() == 0
    b = pool.empty((300_000, 3))
    assert b.ctypes.data != where                     # not the block the view is on
    b[:] = 2.0
    assert (view == 1.0).all()
    del view
    assert held_bytes() == size
    c = pool.empty((300_000, 3))                      # the first block again
    assert c.ctypes.data == where and held_bytes() == 0
    # other dtypes and shapes of the same bin take it too; small arrays are numpy's
    del c
    d = pool.empty(900_000 * 2, np.float32)
    assert d.ctypes.data == where and d.dtype == np.float32 and d.shape == (1_800_000,)
    assert pool.empty(10, np.uint8).flags.owndata


def test_results_survive_pickling_and_the_pool_respects_its_limit(pool, monkeypatch):
    a = pool.empty(500_000, np.int64)
    a[:] = np.arange(500_000)
    b = pickle.loads(pickle.dumps(a))
    np.testing.assert_array_equal(b, np.arange(500_000))
    size = pool._bin(a.nbytes)
    monkeypatch.setattr(pool, "hold_limit", lambda: size)   # room for one block
    c = pool.empty(500_000, np.int64)
    latest = c.ctypes.data
    del a, c                  # the later one returned stays, the earlier one is let go
    assert held_bytes() == size
    d = pool.empty(500_000, np.int64)
    assert d.ctypes.data == latest and held_bytes() == 0
    big = pool.empty(2 * size // 8, np.int64)                 # larger than the limit
    del d, big
    assert held_bytes() == size
    assert pool.release() == size and held_bytes() == 0


def test_a_forked_child_writes_its_own_copy(pool):
    """Pooled pages are private, as numpy's: a child's writes after a fork (multiprocessing)
    do not reach the parent's array."""
    a = pool.empty(300_000)
    a[:] = 1.0
    pid = os.fork()
    if pid == 0:                                      # the child
        a[:] = 2.0
        os._exit(0)
    os.waitpid(pid, 0)
    assert (a == 1.0).all()


def test_pool_off(monkeypatch):
    hm.release()
    monkeypatch.setitem(hm._STATE, "holding", None)
    monkeypatch.setenv("CLCURV_POOL", "0")
    a = hm.empty((400_000, 3))
    assert a.flags.owndata                            # numpy's own array
    assert hm.hold_limit() == 0
    del a
    assert held_bytes() == 0


def test_a_call_reuses_the_pages_of_the_results_it_replaced(pool, device):
    pts = clcurv.shapes.sphere(150_000, 1.0, seed=5)["points"]
    names = ("normals", "eigenvalues", "variation", "count", "status")
    first = clcurv.curvature(pts, 0.03, method="variation", device=device)
    want = {k: np.array(getattr(first, k)) for k in names}
    where = {getattr(first, k).ctypes.data for k in names}
    del first
    held = held_bytes()
    assert held > 150_000 * 7 * 8                     # normals, eigenvalues, variation
    again = clcurv.curvature(pts, 0.03, method="variation", device=device)
    assert held_bytes() < held
    assert {getattr(again, k).ctypes.data for k in names} & where
    for k, v in want.items():                         # the same values in reused pages
        np.testing.assert_array_equal(getattr(again, k), v, err_msg=k)
    assert clcurv.release_memory() >= 0 and held_bytes() == 0


def _vm_flags(address):
    """The VmFlags of the mapping holding ``address`` (/proc/self/smaps), or None."""
    try:
        text = open("/proc/self/smaps").read()
    except OSError:
        return None
    inside = False
    for line in text.splitlines():
        head = line.split()[0] if line else ""
        if "-" in head and ":" not in head:
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= address < hi
        elif inside and line.startswith("VmFlags:"):
            return line.split()[1:]
    return None


def test_new_mappings_do_not_ask_for_huge_pages(pool):
    """The pool's mappings are plain pages (no MADV_HUGEPAGE, 'hg' in smaps' VmFlags): a
    fresh huge page may wait for memory compaction, which made first calls slower and
    erratic (the module docstring), where numpy's own large arrays ask for them."""
    a = pool.empty((1_000_000,))
    a[:] = 0
    flags = _vm_flags(a.ctypes.data)
    if flags is None:
        pytest.skip("no /proc/self/smaps on this system")
    assert "hg" not in flags
