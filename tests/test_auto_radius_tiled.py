"""radius 'auto' of a tiled run (clcurv.jobs.tiled_job.auto_radius_tiled) beside one far "no data"
point (issue 47 item 4): the point at (0, 0, 0) stretches the LAS header's box, so the bucket
grid puts the whole survey in one bucket, which the estimate used to read whole (its memory
grew with the cloud: a tree of all 200000 points here). Its regions now hold a bounded
number of points whatever the grid, and the estimate still agrees with the in-memory one
(clcurv.jobs.job.auto_radius).

The points held are measured by the k-d trees it builds (cKDTree wrapped with monkeypatch,
the size of each tree recorded), never by timing: a tree is built per region, and the
regions are read together, so the largest tree is the most points of one region and the
sum of the trees the most points held at once."""
import numpy as np
import pytest
import scipy.spatial

from clcurv.jobs import tiled_job
from clcurv.io import stream
from clcurv.jobs.job import auto_radius

laspy = pytest.importorskip("laspy")

N = 200_000
#: the memory budget of the runs: the regions together hold at most 64 MiB /
#: TILE_BYTES_PER_POINT = 74565 points, and one region at most 1553 (48 regions of at least
#: 50 (k + 1) points: tiled_job._radius_budget)
BUDGET = 64 << 20
HELD = BUDGET // 900
FAR = (0.0, 0.0, 0.0)


def _survey(n=N, seed=5):
    """A 2.5-D survey of ``n`` points near (500000, 4000000): rolling terrain over
    400 m x 300 m, denser in a few swaths (flight-line overlap), on the LAS grid of 0.01."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2)) * [400.0, 300.0]
    swath = rng.uniform(0, 1, n) < 0.3      # overlap: a 60 m strip about 4 times as dense
    xy[swath, 0] = 100 + 60 * rng.uniform(0, 1, swath.sum())
    z = 20 * np.sin(xy[:, 0] / 37) * np.cos(xy[:, 1] / 23) + rng.normal(0, 0.05, n)
    pts = np.column_stack([xy[:, 0] + 500_000.0, xy[:, 1] + 4_000_000.0, z + 120.0])
    return np.round(pts / 0.01) * 0.01


def _write(path, pts):
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.01] * 3
    hdr.offsets = [0.0, 0.0, 0.0]
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.write(str(path))
    back = laspy.read(str(path))
    return np.column_stack([back.x, back.y, back.z])


def _trees(monkeypatch):
    """The sizes of the cKDTrees that auto_radius_tiled builds from now on (its
    scipy.spatial.cKDTree wrapped)."""
    sizes = []
    real = scipy.spatial.cKDTree

    def recorded(data, *args, **kwargs):
        sizes.append(len(data))
        return real(data, *args, **kwargs)

    monkeypatch.setattr(tiled_job, "cKDTree", recorded)
    return sizes


def _bounds(budget=BUDGET):
    """(points of one region, of all regions together) for ``budget``."""
    per, count = tiled_job._radius_budget(budget)
    return per, per * count


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    d = tmp_path_factory.mktemp("radius")
    pts = _survey()
    near = _write(d / "survey.las", pts)
    far = _write(d / "far.las", np.concatenate([pts, [FAR]]))
    assert np.array_equal(far[:-1], near) and np.array_equal(far[-1], FAR)
    return d, near, auto_radius(near)


def test_the_bound_is_the_budget():
    """The stated bound: 48 regions of at most 1553 points, together at most 64 MiB /
    TILE_BYTES_PER_POINT points (far fewer than the 200k points of the cloud); whatever the
    budget, at most 2^21 points together."""
    per, held = _bounds()
    assert (per, held) == (1553, 74544) and held <= HELD
    assert _bounds(1 << 40)[1] <= tiled_job._RADIUS_POINTS


def test_one_far_point_bounds_the_regions(survey, monkeypatch):
    """200k points near (500000, 4000000) and one at (0, 0, 0): the estimate is within 5%
    of the in-memory radius of the survey alone, no tree holds more than a region's bound
    (1553 points) and all the trees together no more than the budget's (74544 points; the
    estimate used to build one tree of the 200000 points of the bucket holding the survey),
    and a second run with the same seed gives the same radius."""
    d, _, r_mem = survey
    src = stream.open_source(d / "far.las")
    sizes = _trees(monkeypatch)
    r = tiled_job.auto_radius_tiled(src, budget=BUDGET)
    per, held = _bounds()
    assert abs(r / r_mem - 1) < 0.05, (r, r_mem)
    assert sizes and max(sizes) <= per, (max(sizes), per)
    assert sum(sizes) <= held < N / 2, (sum(sizes), held)
    assert tiled_job.auto_radius_tiled(stream.open_source(d / "far.las"), budget=BUDGET) == r


def test_without_the_far_point_it_agrees(survey, monkeypatch):
    """The same survey without the far point: the same agreement and bound; and without a
    budget (256 MiB: 192 regions of at most 1553 points, 298176 together)."""
    d, _, r_mem = survey
    sizes = _trees(monkeypatch)
    r = tiled_job.auto_radius_tiled(stream.open_source(d / "survey.las"), budget=BUDGET)
    per, held = _bounds()
    assert abs(r / r_mem - 1) < 0.05, (r, r_mem)
    assert max(sizes) <= per and sum(sizes) <= held
    sizes.clear()
    r = tiled_job.auto_radius_tiled(stream.open_source(d / "survey.las"))
    assert abs(r / r_mem - 1) < 0.05, (r, r_mem)
    per, held = _bounds(None)
    assert max(sizes) <= per and sum(sizes) <= held


def test_blocks_too_full_are_counted_again_finer(survey, monkeypatch):
    """An occupancy too coarse for the budget (a few blocks of thousands of points each, as
    a dense spot of a huge cloud makes them): the picked blocks are counted again in finer
    blocks until their regions fit, with the far point, and the estimate still agrees."""
    d, _, r_mem = survey
    monkeypatch.setattr(tiled_job, "_RADIUS_BLOCKS", 16)
    counted = []
    real = tiled_job._count_regions

    def recorded(b, frame, occ, blocks, finer):
        counted.append(len(blocks))
        return real(b, frame, occ, blocks, finer)

    monkeypatch.setattr(tiled_job, "_count_regions", recorded)
    sizes = _trees(monkeypatch)
    r = tiled_job.auto_radius_tiled(stream.open_source(d / "far.las"), budget=BUDGET)
    per, held = _bounds()
    assert counted, "no block was counted again"
    assert abs(r / r_mem - 1) < 0.05, (r, r_mem)
    assert max(sizes) <= per and sum(sizes) <= held


def test_stacks_at_one_position_are_read_alone(tmp_path, monkeypatch):
    """Two stacks of 2500 points, each at one x-y position (vertical profiles 1 m apart:
    no block of x-y cells splits them, and the region of one holds more than a region's
    bound): each is read alone, in the largest region around it within the regions' total
    (here both stacks: a stack's 30th neighbours are in both), and the radius is the
    in-memory one."""
    z = np.arange(2500.0) * 0.5
    pts = np.concatenate([np.column_stack([np.full(2500, x), np.full(2500, 4.0), z])
                          for x in (3.0, 4.0)])
    path = tmp_path / "stacks.npy"
    np.save(path, pts)
    sizes = _trees(monkeypatch)
    r = tiled_job.auto_radius_tiled(stream.open_source(path), budget=BUDGET)
    per, held = _bounds()
    assert sizes == [5000, 5000] and per < 2500 and 5000 <= held
    monkeypatch.undo()
    assert r == pytest.approx(auto_radius(pts), rel=0.05)
