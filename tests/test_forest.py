"""The device orientation graph and its minimum spanning forest (clcurv.orient.forest), against host
references on the same data: a cKDTree k-NN, float64 weights, and a Kruskal forest (SciPy) on
the graph the device built, with the same strict edge order."""
import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from clcurv.orient import forest
from clcurv import shapes
from clcurv.orient.graph import KMAX, knn_graph
from clcurv.grid.cloud import DeviceCloud

from conftest import bumpy_surface

K = 10
#: distances that differ by less than this (x radius) are treated as ties (float32 offsets)
TIE = 1e-5
#: device (float32) weights against float64 ones computed on the host
WEIGHT_TOL = 2e-5


def random_signs(normals, seed):
    rng = np.random.default_rng(seed)
    return normals * np.where(rng.random(len(normals)) < 0.5, -1.0, 1.0)[:, None]


def run(points, normals, radius, device, k=K):
    cloud = DeviceCloud(points, radius, device=device)
    graph = knn_graph(cloud, radius, normals, k)
    return cloud, graph, forest.spanning_forest(cloud, graph)


def valid_rows(normals):
    return np.isfinite(normals).all(axis=1) & (normals != 0).any(axis=1)


def check_knn(points, normals, radius, graph, k=K):
    """Every list equals the cKDTree's k nearest valid others within the radius (ordered by
    distance, then input index), up to distances within TIE * radius of each other."""
    nb = graph.neighbors()
    ok = valid_rows(normals)
    assert (nb[~ok] == -1).all(), "a point with an invalid normal has neighbours"
    idx = np.flatnonzero(ok)
    tree = cKDTree(points[idx])
    d, j = tree.query(points[idx], k=k + 2, distance_upper_bound=radius)
    tol = TIE * radius
    clean = 0
    for row, i in enumerate(idx):
        have = np.isfinite(d[row]) & (idx[np.minimum(j[row], len(idx) - 1)] != i)
        rd, rj = d[row][have], idx[j[row][have]]
        o = np.lexsort((rj, rd))
        rd, rj = rd[o][:k], rj[o][:k]
        dev = nb[i][nb[i] >= 0]
        assert ok[dev].all() and (dev != i).all()
        dd = np.linalg.norm(points[dev] - points[i], axis=1)
        assert (dd < radius + tol).all()
        assert (np.diff(dd) > -tol).all(), f"list of {i} not ordered by distance"
        more = d[row][have][o][k:]          # the first ball point beyond the k-th, if any
        edge = np.concatenate([rd, more[:1], [radius]])
        if (np.diff(np.sort(edge)) > tol).all():
            clean += 1
            assert np.array_equal(dev, rj), (i, dev, rj)
        else:                                # a near tie: same distances up to tol
            assert abs(len(dev) - len(rj)) <= 1
            m = min(len(dev), len(rj))
            assert np.allclose(dd[:m], rd[:m], atol=tol), (i, dd, rd)
    assert clean >= 0.95 * len(idx)


def check_weights(points, normals, graph):
    nb, w = graph.neighbors(), graph.weights()
    i, s = np.nonzero(nb >= 0)
    j = nb[i, s]
    ni = normals[i] / np.linalg.norm(normals[i], axis=1)[:, None]
    nj = normals[j] / np.linalg.norm(normals[j], axis=1)[:, None]
    e = points[j] - points[i]
    ln = np.linalg.norm(e, axis=1)
    e = np.divide(e, ln[:, None], out=np.zeros_like(e), where=ln[:, None] > 0)
    ref = 1 - np.abs(np.sum(ni * nj, 1)) + np.abs(np.sum(e * ni, 1)) * np.abs(np.sum(e * nj, 1))
    assert (w[i, s] >= 0).all() and not np.signbit(w[i, s]).any()
    assert np.allclose(w[i, s], ref, atol=WEIGHT_TOL), np.abs(w[i, s] - ref).max()
    assert np.isnan(w[nb < 0]).all()


def kruskal(n, lo, hi, w):
    """The minimum spanning forest under the order (w, lo, hi): Kruskal with the edges'
    ranks in that order as (distinct) weights. (M, 2) lo < hi, sorted rows."""
    o = np.lexsort((hi, lo, w))
    rank = np.empty(len(o))
    rank[o] = np.arange(1, len(o) + 1)
    t = minimum_spanning_tree(csr_matrix((rank, (lo, hi)), shape=(n, n))).tocoo()
    return sorted_edges(np.stack([t.row, t.col], axis=1))


def sorted_edges(e):
    e = np.sort(np.asarray(e, np.int64), axis=1)
    return e[np.lexsort((e[:, 1], e[:, 0]))]


def dot32(normals, a, b):
    """n_a . n_b as the device computes it in float32: fma(z, z', fma(y, y', x x')) (a
    product of float32 values is exact in float64; the sum is rounded to float64 first,
    which keeps its sign)."""
    n = normals.astype(np.float32)
    x, y = n[a].astype(np.float64), n[b].astype(np.float64)
    s = (x[:, 0] * y[:, 0]).astype(np.float32)
    s = (x[:, 1] * y[:, 1] + s).astype(np.float32)
    return (x[:, 2] * y[:, 2] + s).astype(np.float32)


def check_forest(normals, graph, fo):
    n = len(normals)
    lo, hi, w = graph.edges()
    assert (lo < hi).all()
    got = sorted_edges(fo.edges)
    assert len(np.unique(got, axis=0)) == len(got), "an edge twice in the forest"
    assert np.array_equal(got, kruskal(n, lo, hi, w))
    ok = valid_rows(normals)
    # components: those of the graph; one label each, the root's input index
    ncomp, comp = connected_components(csr_matrix((np.ones(len(lo)), (lo, hi)), shape=(n, n)),
                                       directed=False)
    assert len(fo.edges) == ok.sum() - len(np.unique(comp[ok]))
    assert (fo.label[~ok] == -1).all() and not fo.parity[~ok].any()
    lab = fo.label[ok]
    assert (fo.label[lab] == lab).all() and not fo.parity[lab].any(), "a root is not its own"
    assert fo.components == len(np.unique(lab))
    pairs = np.unique(np.stack([comp[ok], lab], axis=1), axis=0)
    assert len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1]))
    # parity along the tree
    u, v = fo.edges[:, 0], fo.edges[:, 1]
    neg = dot32(normals, u, v) < 0
    assert np.array_equal(fo.parity[u] ^ fo.parity[v], neg)
    s = np.where(fo.parity, -1.0, 1.0).astype(np.float32)[:, None]
    flipped = normals.astype(np.float32) * s
    assert (dot32(flipped, u, v) >= 0).all()
    assert (fo.label[u] == fo.label[v]).all()


def check_all(points, normals, radius, device, knn=True):
    cloud, graph, fo = run(points, normals, radius, device)
    if knn:
        check_knn(points, normals, radius, graph)
    check_weights(points, normals, graph)
    check_forest(normals, graph, fo)
    return cloud, graph, fo


def two_spheres(n):
    a = shapes.sphere(n // 2, 1.0, seed=3)
    b = shapes.sphere(n - n // 2, 0.5, seed=4)
    return (np.concatenate([a["points"], b["points"] + [3.0, 0, 0]]),
            np.concatenate([a["normals"], b["normals"]]))


def noisy_bumpy(n):
    p = bumpy_surface(n, seed=5, noise=0.004)
    x, y = p[:, 0], p[:, 1]
    nrm = np.stack([-0.6 * np.cos(3 * x) * np.cos(2 * y), 0.4 * np.sin(3 * x) * np.sin(2 * y),
                    np.ones(n)], axis=1)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    rng = np.random.default_rng(6)
    nrm += rng.normal(scale=0.05, size=nrm.shape)          # normals of a noisy estimate
    return p, nrm / np.linalg.norm(nrm, axis=1)[:, None]


CASES = {
    "sphere": (lambda: (lambda s: (s["points"], s["normals"]))(shapes.sphere(20000, 1.0, seed=1)),
               0.06),
    "torus": (lambda: (lambda s: (s["points"], s["normals"]))(
        shapes.torus(30000, 2.0, 0.5, seed=2)), 0.08),
    "noisy_bumpy": (lambda: noisy_bumpy(20000), 0.04),
    "two_spheres": (lambda: two_spheres(20000), 0.07),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_forest_equals_kruskal(device, name):
    make, r = CASES[name]
    p, nrm = make()
    nrm = random_signs(nrm, 7)
    _, _, fo = check_all(p, nrm, r, device, knn=name in ("sphere", "noisy_bumpy"))
    ncomp = len(np.unique(fo.label))
    if name == "two_spheres":
        assert ncomp == 2
    elif name in ("sphere", "torus"):
        assert ncomp == 1


def test_invalid_normals_and_isolated_points(device):
    s = shapes.sphere(10000, 1.0, seed=8)
    p, nrm = s["points"].copy(), random_signs(s["normals"], 9)
    rng = np.random.default_rng(10)
    bad = rng.choice(len(p), 500, replace=False)
    nrm[bad[:200]] = np.nan
    nrm[bad[200:300], 1] = np.inf
    nrm[bad[300:400]] = 0.0
    # isolated points: far from everything, two of them close together (one edge)
    far = np.array([[5.0, 5, 5], [-5, 5, 5], [5, -5, 5], [5, 5, -5], [5.01, 5, -5]])
    p = np.concatenate([p, far])
    nrm = np.concatenate([nrm, [[0, 0, 1.0], [0, 1, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1]]])
    cloud, graph, fo = check_all(p, nrm, 0.08, device)
    m = len(s["points"])
    assert list(fo.label[m:m + 3]) == [m, m + 1, m + 2]
    assert list(fo.parity[m:]) == [False] * 4 + [True]
    assert fo.label[m + 3] == fo.label[m + 4] == m + 3 and fo.parity[m + 4]
    assert (graph.neighbors()[bad[:400]] == -1).all()


def test_thin_plate_edges_stay_on_their_sheet(device):
    """Two parallel sheets 0.3 r apart with opposite normals: edges within a sheet weigh 0
    and edges across weigh |e . n|^2 > 0 (with 1 - |n_i . n_j| alone they would weigh 0
    too), so the forest crosses only to join pieces that a sheet's own edges leave apart."""
    rng = np.random.default_rng(11)
    n = 20000
    xy = rng.uniform(-1, 1, (n, 2))
    z = np.where(np.arange(n) < n // 2, 0.0, 0.012)
    p = np.column_stack([xy, z])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    nrm[n // 2:] *= -1                       # outward normals of a plate
    nrm = random_signs(nrm, 12)
    _, graph, fo = check_all(p, nrm, 0.04, device, knn=False)
    lo, hi, w = graph.edges()
    side = np.arange(n) < n // 2
    across = side[lo] != side[hi]
    assert across.sum() > n and (w[across] > 0).all() and (w[~across] == 0).all()

    def pieces(keep):
        return connected_components(csr_matrix((np.ones(keep.sum()), (lo[keep], hi[keep])),
                                               shape=(n, n)), directed=False)[0]
    u, v = fo.edges[:, 0], fo.edges[:, 1]
    assert (side[u] != side[v]).sum() == pieces(~across) - pieces(across | ~across)


def test_deterministic_and_independent_of_blocking_and_chasing(device, monkeypatch):
    p, nrm = noisy_bumpy(20000)
    nrm = random_signs(nrm, 13)
    nrm[::97] = np.nan
    cloud, g1, f1 = run(p, nrm, 0.04, device)
    g2 = knn_graph(cloud, 0.04, nrm, K)
    f2 = forest.spanning_forest(cloud, g2)
    monkeypatch.setattr(forest, "BLOCK", 7)
    monkeypatch.setattr(forest, "CHASE", 1)          # pointer jumping finishes the chains
    f3 = forest.spanning_forest(cloud, g2)
    f4 = forest.spanning_forest(cloud, g2, edges=False)    # what orienting asks for
    assert f4.edges is None
    assert np.array_equal(g1.neighbors(), g2.neighbors())
    assert g1.weights().tobytes() == g2.weights().tobytes()
    for f in (f2, f3, f4):
        assert np.array_equal(f1.label, f.label)
        assert np.array_equal(f1.parity, f.parity)
    assert np.array_equal(f1.edges, f2.edges)
    assert np.array_equal(sorted_edges(f1.edges), sorted_edges(f3.edges))


def test_the_gpu_block_size_gives_the_same_forest(device, monkeypatch):
    """Devices other than CPUs use blocks of forest.GPU_BLOCK points (enough work-items for
    a GPU): the same labels, parities and edges as the CPU's blocks, here on every device."""
    p, nrm = noisy_bumpy(20000)
    nrm = random_signs(nrm, 17)
    cloud, g, f_cpu = run(p, nrm, 0.04, device)
    monkeypatch.setattr(forest, "block_size", lambda dev: forest.GPU_BLOCK)
    f_gpu = forest.spanning_forest(cloud, g)
    assert forest.GPU_BLOCK < forest.BLOCK
    assert np.array_equal(f_cpu.label, f_gpu.label)
    assert np.array_equal(f_cpu.parity, f_gpu.parity)
    assert np.array_equal(sorted_edges(f_cpu.edges), sorted_edges(f_gpu.edges))


def test_k_and_shapes_checked(device):
    s = shapes.sphere(2000, 1.0, seed=14)
    cloud = DeviceCloud(s["points"], 0.1, device=device)
    with pytest.raises(ValueError, match="k must be"):
        knn_graph(cloud, 0.1, s["normals"], KMAX + 1)
    with pytest.raises(ValueError, match="normals must have shape"):
        knn_graph(cloud, 0.1, s["normals"][:10], 5)
    with pytest.raises(ValueError, match="exceeds the cell size"):
        knn_graph(cloud, 0.2, s["normals"], 5)
    g = knn_graph(cloud, 0.1, s["normals"], KMAX)
    check_knn(s["points"], s["normals"], 0.1, g, KMAX)


def test_graph_that_does_not_fit_names_what_fits(device, monkeypatch):
    from clcurv.grid import cloud as cloud_mod
    from clcurv.runtime import limits
    s = shapes.sphere(20000, 1.0, seed=15)
    cloud = DeviceCloud(s["points"], 0.05, device=device)
    monkeypatch.setattr(limits, "DEVICE_MEMORY", cloud.device_bytes + 20000 * 200)
    with pytest.raises(cloud_mod.DeviceMemoryError, match=r"about \d+ points of this cloud fit"):
        knn_graph(cloud, 0.05, s["normals"], 10)


def test_double_precision(device):
    if not device.info.fp64:
        pytest.skip(f"{device.info.name} has no float64")
    s = shapes.sphere(20000, 1.0, seed=1)
    p, nrm = s["points"], random_signs(s["normals"], 3)
    cloud = DeviceCloud(p, 0.06, device=device, precision="double")
    graph = knn_graph(cloud, 0.06, nrm, K)
    fo = forest.spanning_forest(cloud, graph)
    check_knn(p, nrm, 0.06, graph)
    check_weights(p, nrm, graph)
    lo, hi, w = graph.edges()
    assert np.array_equal(sorted_edges(fo.edges), kruskal(len(p), lo, hi, w))
    u, v = fo.edges[:, 0], fo.edges[:, 1]
    assert np.array_equal(fo.parity[u] ^ fo.parity[v], np.sum(nrm[u] * nrm[v], 1) < 0)


def test_coincident_points_and_dense_balls(device):
    """Balls with more close candidates than the ranked collection holds (knn.cl: MCAP): 60
    copies of some points (their lists: the other copies by input index), and a blob of
    3000 points in a tiny ball (more than 255 chunks of candidates: the packed bin counters
    are emptied on the way); lists, weights (off the blob) and forest against the host
    references."""
    s = shapes.sphere(8000, 1.0, seed=16)
    p, nrm = s["points"], random_signs(s["normals"], 17)
    rng = np.random.default_rng(18)
    src = rng.choice(len(p), 20, replace=False)
    copies = np.repeat(src, 60)
    blob = p[0] + rng.normal(scale=1e-3, size=(3000, 3))
    pts = np.concatenate([p, p[copies], blob])
    nr = np.concatenate([nrm, nrm[copies], np.tile(nrm[0], (3000, 1))])
    nr[-3000:] += rng.normal(scale=0.1, size=(3000, 3))
    nr /= np.linalg.norm(nr, axis=1)[:, None]
    cloud, graph, fo = run(pts, nr, 0.06, device)
    check_forest(nr, graph, fo)
    nb = graph.neighbors()
    # weights away from the blob (in it, float32 offsets of ~1e-4 carry ~1e-4 of the weight)
    m = len(p) + len(copies)
    i, s = np.nonzero((nb[:m] >= 0) & (nb[:m] < m))
    j = nb[i, s]
    w = graph.weights()
    assert (w[nb >= 0] >= 0).all() and not np.signbit(w[nb >= 0]).any()
    e = pts[j] - pts[i]
    ln = np.linalg.norm(e, axis=1)
    e = np.divide(e, ln[:, None], out=np.zeros_like(e), where=ln[:, None] > 0)
    ref = (1 - np.abs(np.sum(nr[i] * nr[j], 1))
           + np.abs(np.sum(e * nr[i], 1)) * np.abs(np.sum(e * nr[j], 1)))
    assert np.allclose(w[i, s], ref, atol=WEIGHT_TOL)
    for c in range(len(src)):
        same = np.concatenate([[src[c]], len(p) + np.arange(60 * c, 60 * c + 60)])
        for i in same[::7]:
            assert np.array_equal(nb[i], same[same != i][:K]), (i, nb[i])
    # the blob: exact distances, no ties to speak of
    idx = np.arange(len(pts) - 3000, len(pts))
    tree = cKDTree(pts)
    d, j = tree.query(pts[idx[::50]], k=K + 1)
    for row, i in enumerate(idx[::50]):
        dd = np.linalg.norm(pts[nb[i]] - pts[i], axis=1)
        assert np.allclose(dd, d[row][1:], rtol=1e-3, atol=1e-9), (i, dd, d[row][1:])


def test_weights_symmetric_to_the_bit(device):
    """An edge in both lists carries the same weight bits in both (forest.cl takes a point's
    lightest edge from its own list, whichever copy it holds)."""
    p, nrm = noisy_bumpy(20000)
    cloud = DeviceCloud(p, 0.04, device=device)
    graph = knn_graph(cloud, 0.04, random_signs(nrm, 19), K)
    nb, w = graph.neighbors(), graph.weights().view(np.uint32)
    i, s = np.nonzero(nb >= 0)
    j = nb[i, s]
    pos = {(a, b): x for a, b, x in zip(i.tolist(), j.tolist(), w[i, s].tolist())}
    both = [(x, pos[(b, a)]) for (a, b), x in pos.items() if (b, a) in pos]
    assert len(both) > 0.5 * len(pos)
    a, b = np.array(both).T
    assert np.array_equal(a, b)


@pytest.mark.parametrize("precision", ["float", "double"])
def test_exact_ties_ordered_by_input_index(device, precision):
    """Exactly equal distances, in the ranked path (fewer than MCAP candidates): a plane grid
    of dyadic spacing (the offsets and squared distances are exact in float32, so the 4 or 8
    points of a grid ring are at bit-equal distances) and 2 extra copies of every 7th point
    in shuffled input order (distance 0). Every list equals the exact order (distance, then
    input index): dropping the index from the rank gives equal ranks and wrong lists."""
    if precision == "double" and not device.info.fp64:
        pytest.skip(f"{device.info.name} has no float64")
    g = np.arange(-24, 25) / 16.0
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = np.column_stack([xy, np.zeros(len(xy))])
    pts = np.concatenate([pts, pts[::7], pts[::7]])
    pts = pts[np.random.default_rng(3).permutation(len(pts))]
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    radius = 0.25                        # 4 grid steps, dyadic (the cell too): ~50 per ball
    cloud = DeviceCloud(pts, radius, device=device, precision=precision)
    nb = knn_graph(cloud, radius, nrm, K).neighbors()
    d2 = np.sum((pts[:, None, :] - pts[None, :, :]) ** 2, axis=2)    # exact: dyadic
    idx = np.arange(len(pts))
    for i in range(0, len(pts), 3):
        inside = (d2[i] < radius ** 2) & (idx != i)
        j = idx[inside][np.lexsort((idx[inside], d2[i][inside]))][:K]
        assert np.array_equal(nb[i], j), (i, nb[i], j)
