"""Consistent orientation of unoriented (e.g. PCA) normals, on the host.

Every function returns a boolean **flip mask** ``flip`` of shape ``(N,)``:
``True`` where the normal must be negated. Inputs are never modified; use
:func:`apply_flip` (or ``n[flip] *= -1`` on a copy) to apply it.

Conventions
-----------
* ``points`` is an ``(N, 3)`` array in any length unit; ``normals`` is
  ``(N, 3)`` and need not be unit length (only directions matter).
* A normal is *invalid* when any of its components is not finite (the NaN
  rows the moment operators output for status != 0) or it is the zero vector;
  invalid normals always get ``flip = False``.
* clcurv orients normals **outward** (away from the solid): a sphere of
  radius ``R`` with outward normals has mean curvature ``H = +1/R``.
* A normal ``n`` that is exactly perpendicular to the reference direction
  (dot product 0) is not flipped.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import (breadth_first_order, connected_components,
                                  minimum_spanning_tree)
from scipy.spatial import cKDTree

__all__ = [
    "flip_to_reference",
    "flip_to_viewpoint",
    "flip_by_propagation",
    "apply_flip",
]

#: Added to every edge weight ``1 - |n_i . n_j|`` so that parallel normals
#: still give a stored (non-zero) edge in the sparse graph.
EDGE_EPS = 1e-6
#: Connected components smaller than this are not propagated over; each of
#: their points is oriented on its own, away from the centroid of all valid
#: points.
MIN_COMPONENT = 3


def _as_vectors(a, name):
    """Return ``a`` as a float64 ``(N, 3)`` array (no copy if possible)."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    return arr


def _rowdot(a, b):
    """Row-wise dot products of two ``(N, 3)`` arrays."""
    return np.einsum("ij,ij->i", a, b)


def _negative(dots):
    """``dots < 0`` with NaN treated as not negative (no warning)."""
    with np.errstate(invalid="ignore"):
        return dots < 0.0


def flip_to_reference(normals, reference):
    """Flip mask orienting ``normals`` like user-supplied reference normals.

    Parameters
    ----------
    normals : array_like, shape (N, 3)
        Normals to orient (any length; NaN rows allowed).
    reference : array_like, shape (N, 3) or (3,)
        Reference normals (any length), e.g. the normals the user gave with
        the cloud, or one direction for all points.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
        ``True`` where ``dot(n, reference) < 0``; ``False`` where either
        vector is invalid (NaN) or the dot product is 0.
    """
    n = _as_vectors(normals, "normals")
    ref = np.broadcast_to(np.asarray(reference, dtype=np.float64), n.shape)
    return _negative(_rowdot(n, ref))


def flip_to_viewpoint(points, normals, viewpoint):
    """Flip mask making normals point towards a viewpoint (scanner position).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Point coordinates (length unit ``L``).
    normals : array_like, shape (N, 3)
        Normals to orient (any length; NaN rows allowed).
    viewpoint : array_like, shape (3,) or (N, 3)
        Viewpoint position(s) in unit ``L``.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
        ``True`` where ``dot(n, viewpoint - p) < 0``.
    """
    p = _as_vectors(points, "points")
    n = _as_vectors(normals, "normals")
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} differ")
    v = np.asarray(viewpoint, dtype=np.float64)
    if v.shape not in ((3,), p.shape):
        raise ValueError(f"viewpoint must have shape (3,) or {p.shape}, "
                         f"got {v.shape}")
    return _negative(_rowdot(n, v - p))


# --------------------------------------------------------------------------
# Hoppe et al. 1992 propagation
# --------------------------------------------------------------------------
def _valid_rows(points, normals):
    """Rows with finite point, finite and non-zero normal."""
    ok = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(normals),
                                                       axis=1)
    ok[ok] = np.any(normals[ok] != 0.0, axis=1)
    return ok


def _spatial_order(p):
    """Permutation putting points in k-d tree (spatially coherent) order.

    Working in this order makes the neighbour queries and every later gather
    cache friendly (about 25% faster on 10^5 points).
    """
    return cKDTree(p, balanced_tree=False).indices


def _knn_graph(p, u, k):
    """kNN graph with Hoppe weights ``1 - |u_i . u_j| + EDGE_EPS``.

    Returned as an ``(M, M)`` CSR matrix holding the directed kNN edges; the
    spanning-tree routine treats every stored entry as an undirected edge
    (with the smaller weight of ``(i, j)`` and ``(j, i)``, here equal), which
    symmetrises the graph.
    """
    m = len(p)
    kk = min(k, m - 1)
    _, nb = cKDTree(p, balanced_tree=False).query(p, k=kk + 1, workers=-1)
    w = 1.0 - np.abs(np.einsum("ijk,ik->ij", u[nb], u)) + EDGE_EPS
    if np.array_equal(nb[:, 0], np.arange(m)):
        # usual case: the self match comes first; build the CSR directly
        return csr_matrix((w[:, 1:].ravel(), nb[:, 1:].ravel(),
                           np.arange(0, kk * m + 1, kk)), shape=(m, m))
    rows = np.repeat(np.arange(m), kk + 1)
    cols = nb.ravel()
    keep = cols != rows  # duplicate points: drop self wherever it landed
    return csr_matrix((w.ravel()[keep], (rows[keep], cols[keep])),
                      shape=(m, m))


def _component_roots(p, labels, ncomp):
    """Centroid of each component and its point farthest from it."""
    size = np.bincount(labels, minlength=ncomp).astype(np.float64)
    cen = np.stack([np.bincount(labels, weights=p[:, j], minlength=ncomp)
                    for j in range(3)], axis=1) / size[:, None]
    d2 = np.sum((p - cen[labels]) ** 2, axis=1)
    order = np.lexsort((-d2, labels))  # by label, then farthest first
    first = np.searchsorted(labels[order], np.arange(ncomp))
    return cen, order[first]


def _xor_to_root(edge_flip, parent, root):
    """XOR of ``edge_flip`` along every node's path to ``root``.

    Pointer jumping: after iteration ``t``, ``f[i]`` is the XOR over the
    ``2^t`` edges above ``i`` (or up to ``root``) and ``a[i]`` the ancestor
    ``2^t`` levels up. ``root`` is its own parent with ``edge_flip = False``.
    Vectorised, ``ceil(log2(depth))`` iterations.
    """
    f = edge_flip.copy()
    a = parent.copy()
    while np.any(a != root):
        f = f ^ f[a]
        a = a[a]
    return f


def flip_by_propagation(points, normals, k=10):
    """Flip mask for a consistent, globally outward orientation (Hoppe 1992).

    Algorithm:

    1. Build the k-nearest-neighbour graph of the valid points (symmetrised:
       every kNN pair is an undirected edge) with weights
       ``1 - |n_i . n_j| + 1e-6`` (the epsilon keeps parallel pairs as edges).
    2. Take its minimum spanning forest (Kruskal,
       :func:`scipy.sparse.csgraph.minimum_spanning_tree`).
    3. In every connected component, the root is the point farthest from the
       component's centroid; its normal is oriented away from the centroid.
    4. Propagate along the tree from the root: a node is flipped relative to
       its already-oriented parent when their normals disagree (dot < 0).
       All components are processed at once by hanging their roots under a
       virtual super-root, doing one breadth-first search and accumulating
       the flips along root paths by vectorised pointer jumping.
    5. Global outward choice: a component is flipped as a whole when the sum
       over its points of <n, p - centroid> is negative (closed shapes, open
       cylinders and most single-view scans get outward normals).

    Components with fewer than 3 points (only possible when there are at most
    ``k`` valid points in a region) are not propagated: each of their points
    is oriented on its own, away from the centroid of all valid points.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Point coordinates (length unit ``L``).
    normals : array_like, shape (N, 3)
        Unoriented normals (any non-zero length); rows with a non-finite
        component (or zero rows) are invalid: they are left out of the graph
        and get ``flip = False``.
    k : int, optional
        Number of nearest neighbours per point in the graph (default 10).

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
        ``True`` where the normal must be negated.

    Notes
    -----
    The outward vote assumes that on the whole the centroid lies on the inner
    side of the surface: true for closed surfaces (sphere, capsule, torus...)
    and for most object scans; for terrain (aerial LiDAR) use a viewpoint.
    """
    p_all = _as_vectors(points, "points")
    n_all = _as_vectors(normals, "normals")
    if p_all.shape != n_all.shape:
        raise ValueError(f"points {p_all.shape} and normals {n_all.shape} "
                         f"differ")
    k = int(k)
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    flip = np.zeros(len(p_all), dtype=bool)
    idx = np.flatnonzero(_valid_rows(p_all, n_all))
    if len(idx) == 0:
        return flip
    if len(idx) >= MIN_COMPONENT:
        idx = idx[_spatial_order(p_all[idx])]
    p = p_all[idx]
    u = n_all[idx] / np.linalg.norm(n_all[idx], axis=1)[:, None]
    flip[idx] = _propagate(p, u, k)
    return flip


def _super_rooted_parents(tree, roots):
    """BFS parent of every node of a spanning forest hung under a super-root.

    The super-root is node ``m`` (``m`` = number of tree nodes), linked to
    every component root; it is its own parent in the returned ``(m + 1,)``
    array.
    """
    m, ncomp = tree.shape[0], len(roots)
    t = tree.tocoo()
    rows = np.concatenate([t.row, t.col, np.full(ncomp, m)])
    cols = np.concatenate([t.col, t.row, roots])
    graph = csr_matrix((np.ones(len(rows)), (rows, cols)),
                       shape=(m + 1, m + 1))
    _, parent = breadth_first_order(graph, m, directed=True,
                                    return_predecessors=True)
    parent[m] = m
    return parent


def _propagate(p, u, k):
    """Flip mask of valid points ``p`` with unit normals ``u`` (Hoppe 1992)."""
    m = len(p)
    global_out = _negative(_rowdot(u, p - p.mean(axis=0)))
    if m < MIN_COMPONENT:
        return global_out

    tree = minimum_spanning_tree(_knn_graph(p, u, k), overwrite=True)
    ncomp, labels = connected_components(tree, directed=False)
    cen, roots = _component_roots(p, labels, ncomp)
    parent = _super_rooted_parents(tree, roots)

    edge_flip = np.zeros(m + 1, dtype=bool)
    child = np.flatnonzero(parent[:m] != m)
    edge_flip[child] = _negative(_rowdot(u[child], u[parent[child]]))
    edge_flip[roots] = _negative(_rowdot(u[roots], p[roots] - cen))
    f = _xor_to_root(edge_flip, parent, m)[:m]
    # global outward choice by a vote of the whole component rather than of its root (the
    # root's normal can be poor at a scan's rim): flip a component whose oriented normals
    # point on the whole towards its centroid
    vote = np.bincount(labels, weights=np.where(f, -1.0, 1.0) * _rowdot(u, p - cen[labels]),
                       minlength=ncomp)
    f ^= (vote < 0)[labels]

    small = np.bincount(labels, minlength=ncomp)[labels] < MIN_COMPONENT
    f[small] = global_out[small]
    return f


def apply_flip(flip, *arrays):
    """Negate the rows of arrays where ``flip`` is True.

    Parameters
    ----------
    flip : array_like of bool, shape (N,)
        Flip mask, e.g. from :func:`flip_by_propagation`.
    *arrays : array_like, shape (N, ...)
        Arrays to flip row-wise (normals, signed curvatures, shifts...).

    Returns
    -------
    numpy.ndarray or tuple of numpy.ndarray
        New arrays (inputs untouched) with ``out[i] = -a[i]`` where
        ``flip[i]``; a single array when one was given, else a tuple in the
        input order.
    """
    fl = np.asarray(flip, dtype=bool)
    out = []
    for a in arrays:
        arr = np.array(a, copy=True)
        if arr.shape[:1] != fl.shape:
            raise ValueError(f"array of shape {arr.shape} does not match "
                             f"flip mask of shape {fl.shape}")
        arr[fl] = -arr[fl]
        out.append(arr)
    return out[0] if len(out) == 1 else tuple(out)
