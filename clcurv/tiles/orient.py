"""Hoppe's MST orientation across tiles (the design of :mod:`clcurv.orient.orientation`, "Tiles").

A tile with ``orient="mst"`` orients its points (owned and halo) by the device's graph and
spanning forest (:mod:`clcurv.orient.graph`, :mod:`clcurv.orient.forest`) on its own: every point gets a
tile component (a *node*: the tile and the component's label) and a normal consistent
within it. The operator then runs with those normals as the orientation reference. What a
tile cannot know is how its components continue in the other tiles, nor which side of a
closed object is out. So each tile also reports

* for its halo points: (id, node, normal) -- the same points are owned by a neighbour tile,
  whose output holds their (owner node, normal);
* per node: the sums of the outward vote of :func:`clcurv.orient.orientation.component_signs` over its
  own points (count, sum of p - o, sum of n, sum of <n, p - o>; o the frame's origin, so
  large coordinates cost no digits).

The client then joins the halo points with their owners (by id windows): each pair of
nodes gets a vote, +1 per shared point whose two normals agree and -1 per one that does
not. A maximum spanning forest over the node graph (strongest votes first, union-find
with parity) gives every node's flip relative to its global component, whose outward
vote is the sum of its nodes' vote sums, flipped. Points of components smaller than
:data:`clcurv.orient.orientation.MIN_COMPONENT` face away from the centroid of all points, as in
memory. The writing pass applies each node's flip to its points' signed fields: normals
and H negated, (k1, k2) -> (-k2, -k1) with their directions swapped; K and the unsigned
fields do not change.

Not reproduced: the nesting step of component_signs (an inner wall of a hollow object
inside another component's solid); a tiled run orients every global component by its own
vote.
"""
from __future__ import annotations

import numpy as np

from clcurv.api.curvature import normals as pca_normals
from clcurv.orient import forest, graph
from clcurv.orient.orientation import MIN_COMPONENT
from clcurv.tiles.workspace import load_sealed, tile_file

#: extra per-point fields of a tile's records when it orients by MST
NODE_FIELDS = [("node", "<i8"), ("nl", "<f4", (3,)), ("pd", "<f8")]
HALO_DTYPE = np.dtype([("id", "<i8"), ("node", "<i8"), ("nl", "<f4", (3,))])
SUMS_DTYPE = np.dtype([("node", "<i8"), ("count", "<i8"), ("sp", "<f8", (3,)),
                       ("sn", "<f8", (3,)), ("snp", "<f8")])


def orient_tile(cloud, radius, k, t):
    """(normals (N, 3) consistent within each tile component, node (N,) int64 (-1 where
    the normal is invalid)) of the points of a tile's DeviceCloud; ``t`` numbers the tile
    among the run's (0 <= t < 2^31: a tile id t = tx + ntx ty, which one far point makes
    larger, would overflow the node ids t << 32)."""
    n = pca_normals(cloud, radius, orient=None)
    ok = np.isfinite(n).all(axis=1)
    u = np.where(ok[:, None], n, 0.0)
    g = graph.knn_graph(cloud, radius, u, k)
    fo = forest.spanning_forest(cloud, g, edges=False)
    valid = ok & (fo.label >= 0)
    sign = np.where(fo.parity, -1.0, 1.0)
    nl = np.where(valid[:, None], u * sign[:, None], np.nan)
    node = np.where(valid, (np.int64(t) << 32) | fo.label.astype(np.int64), -1)
    return nl, node


def node_sums(points, nl, node, origin):
    """Per node: count and the sums of the outward vote (see the module)."""
    keep = node >= 0
    if not keep.any():
        return np.empty(0, SUMS_DTYPE)
    nodes, inv = np.unique(node[keep], return_inverse=True)
    p = points[keep] - np.asarray(origin)
    u = nl[keep].astype(np.float64)
    out = np.zeros(len(nodes), SUMS_DTYPE)
    out["node"] = nodes
    out["count"] = np.bincount(inv, minlength=len(nodes))
    for j in range(3):
        out["sp"][:, j] = np.bincount(inv, weights=p[:, j], minlength=len(nodes))
        out["sn"][:, j] = np.bincount(inv, weights=u[:, j], minlength=len(nodes))
    out["snp"] = np.bincount(inv, weights=np.einsum("ij,ij->i", u, p), minlength=len(nodes))
    return out


def reconcile(node_sums_list, votes):
    """The flip of every node (dict node -> bool) and the global centroid offset (from
    the origin) and small-group set, from the per-tile node sums and the pair votes
    (dict (a, b) -> int)."""
    sums = np.concatenate(node_sums_list) if node_sums_list else np.empty(0, SUMS_DTYPE)
    index = {int(v): i for i, v in enumerate(sums["node"])}
    m = len(sums)
    parent = np.arange(m)
    rel = np.zeros(m, bool)               # parity of each node relative to its parent

    def find(a):
        flip = False
        while parent[a] != a:
            flip ^= rel[a]
            a = parent[a]
        return a, flip

    for (a, b), v in sorted(votes.items(), key=lambda kv: (-abs(kv[1]), kv[0])):
        if v == 0 or a not in index or b not in index:
            continue
        ra, fa = find(index[a])
        rb, fb = find(index[b])
        if ra == rb:
            continue
        # nodes a and b disagree when v < 0: flip(a) ^ flip(b) = (v < 0)
        parent[rb] = ra
        rel[rb] = fa ^ fb ^ (v < 0)
    roots, flips = np.empty(m, np.int64), np.zeros(m, bool)
    for i in range(m):
        roots[i], flips[i] = find(i)
    s = np.where(flips, -1.0, 1.0)
    count = np.bincount(roots, weights=sums["count"], minlength=m)
    sp = np.stack([np.bincount(roots, weights=sums["sp"][:, j], minlength=m)
                   for j in range(3)], axis=1)
    sn = np.stack([np.bincount(roots, weights=sums["sn"][:, j] * s, minlength=m)
                   for j in range(3)], axis=1)
    snp = np.bincount(roots, weights=sums["snp"] * s, minlength=m)
    cen = sp / np.maximum(count, 1)[:, None]
    vote = snp - np.einsum("ij,ij->i", sn, cen)
    group_flip = vote < 0
    final = {int(sums["node"][i]): bool(flips[i] ^ group_flip[roots[i]]) for i in range(m)}
    small = {int(sums["node"][i]) for i in range(m) if count[roots[i]] < MIN_COMPONENT}
    total = max(float(sums["count"].sum()), 1.0)
    centroid = sums["sp"].sum(axis=0) / total
    return final, centroid, small


def flip_mask(rec, flips, centroid, small):
    """Which records' orientation to negate: their node's flip; points of small groups
    face away from the centroid of all points (as clcurv.orient.orientation.orient_components)."""
    node = rec["node"]
    mask = np.zeros(len(rec), bool)
    if not len(rec):
        return mask
    uniq, inv = np.unique(node, return_inverse=True)
    table = np.array([flips.get(int(v), False) for v in uniq], bool)
    mask = table[inv] & (node >= 0)
    if small:
        tiny = np.isin(node, list(small))
        if tiny.any():
            u = rec["nl"][tiny].astype(np.float64)
            d = rec["pd"][tiny] - u @ centroid
            mask[tiny] = d < 0
    return mask


def flip_fields(rec, mask, method):
    """Negate the orientation of the records where ``mask``: normals and H negated, for
    MLS2 (k1, k2) -> (-k2, -k1), dir1 <-> dir2 and their standard errors k1_se <-> k2_se;
    in place."""
    if not mask.any():
        return rec
    names = rec.dtype.names
    if "normals" in names:
        rec["normals"][mask] *= -1
    if "mean_curvature" in names:
        rec["mean_curvature"][mask] *= -1
    if method == "mls2" and "k1" in names and "k2" in names:
        k1, k2 = rec["k1"][mask].copy(), rec["k2"][mask].copy()
        rec["k1"][mask], rec["k2"][mask] = -k2, -k1
        if "k1_se" in names and "k2_se" in names:
            e1, e2 = rec["k1_se"][mask].copy(), rec["k2_se"][mask].copy()
            rec["k1_se"][mask], rec["k2_se"][mask] = e2, e1
        for c in "xyz":
            a, b = f"dir1_{c}", f"dir2_{c}"
            if a in names and b in names:
                x, y = rec[a][mask].copy(), rec[b][mask].copy()
                rec[a][mask], rec[b][mask] = y, x
    return rec


def reconcile_windows(ws, windows, tiles, method):
    """Votes between tile components from the halo points and their owners, window by
    window, and the node sums of ``tiles`` (the ids of the tiles that hold points); sets
    ``windows.transform`` to the final flips (clcurv.tiles.orient)."""
    votes = {}
    for w in range(windows.count):
        hp = windows.halo_path(w)
        if not hp.exists():
            continue
        halo = np.fromfile(hp, HALO_DTYPE)
        own = windows.window(w)[halo["id"] - w * windows.size]
        ok = own["node"] >= 0
        halo, own = halo[ok], own[ok]
        agree = np.einsum("ij,ij->i", halo["nl"].astype(np.float64),
                          own["nl"].astype(np.float64)) >= 0
        a, b = np.minimum(halo["node"], own["node"]), np.maximum(halo["node"], own["node"])
        keys = np.stack([a, b, agree.astype(np.int64)], axis=1)
        uniq, cnt = np.unique(keys, axis=0, return_counts=True)
        for (x, y, g), c in zip(uniq.tolist(), cnt.tolist()):
            if x != y:
                votes[(x, y)] = votes.get((x, y), 0) + (c if g else -c)
    sums = [load_sealed(tile_file(ws, t).with_suffix(".nodes.npy")) for t in tiles]
    flips, centroid, small = reconcile(sums, votes)
    windows.transform = lambda rec: flip_fields(rec, flip_mask(rec, flips, centroid, small),
                                                method)
