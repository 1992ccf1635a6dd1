"""Seeded samples of analytic surfaces with their exact normals and curvatures.

Every sampler draws points uniformly with respect to surface area and returns a dict:
``points`` (N, 3), ``normals`` (N, 3) outward unit normals, ``k1``, ``k2`` (N,) signed
principal curvatures in clcurv's convention (outward normals, sphere positive, k1 >= k2),
``H`` = (k1 + k2)/2, ``K`` = k1 k2 and, where defined, ``dir1`` (N, 3) the direction of k1.
Optional ``noise`` adds Gaussian noise of that standard deviation along the normal.
"""
from __future__ import annotations

import numpy as np


def _finish(rng, pts, nrm, k1, k2, noise, dir1=None):
    if noise:
        pts = pts + rng.normal(scale=noise, size=(len(pts), 1)) * nrm
    out = {"points": pts, "normals": nrm, "k1": k1, "k2": k2, "H": 0.5 * (k1 + k2), "K": k1 * k2}
    if dir1 is not None:
        out["dir1"] = dir1
    return out


def sphere(n, radius=2.0, *, noise=0.0, seed=0):
    """Sphere of ``radius`` centred at the origin: k1 = k2 = 1/radius."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    k = np.full(n, 1.0 / radius)
    return _finish(rng, radius * u, u, k, k.copy(), noise)


def cylinder(n, radius=1.0, length=4.0, *, noise=0.0, seed=0):
    """Open cylinder around the z axis, z in [-length/2, length/2]: k1 = 1/radius, k2 = 0."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(-length / 2, length / 2, n)
    nrm = np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)
    pts = np.stack([radius * nrm[:, 0], radius * nrm[:, 1], z], axis=1)
    dir1 = np.stack([-np.sin(t), np.cos(t), np.zeros(n)], axis=1)
    return _finish(rng, pts, nrm, np.full(n, 1.0 / radius), np.zeros(n), noise, dir1)


def torus(n, major=2.0, minor=0.5, *, noise=0.0, seed=0):
    """Torus around the z axis. With phi the angle around the tube (0 outside):
    the meridian curvature is 1/minor and the parallel one cos(phi)/(major + minor cos(phi))."""
    rng = np.random.default_rng(seed)
    phi = np.empty(0)
    while len(phi) < n:  # area density proportional to major + minor cos(phi)
        c = rng.uniform(0, 2 * np.pi, 2 * n)
        keep = rng.uniform(0, major + minor, 2 * n) < major + minor * np.cos(c)
        phi = np.concatenate([phi, c[keep]])
    phi = phi[:n]
    th = rng.uniform(0, 2 * np.pi, n)
    ring = major + minor * np.cos(phi)
    pts = np.stack([ring * np.cos(th), ring * np.sin(th), minor * np.sin(phi)], axis=1)
    nrm = np.stack([np.cos(phi) * np.cos(th), np.cos(phi) * np.sin(th), np.sin(phi)], axis=1)
    km = np.full(n, 1.0 / minor)
    kp = np.cos(phi) / ring
    meridian = np.stack([-np.sin(phi) * np.cos(th), -np.sin(phi) * np.sin(th), np.cos(phi)], axis=1)
    parallel = np.stack([-np.sin(th), np.cos(th), np.zeros(n)], axis=1)
    # 1/minor >= cos(phi)/ring always, so the meridian carries k1
    return _finish(rng, pts, nrm, km, kp, noise, meridian) | {"dir2": parallel}


def saddle(n, c=1.0, extent=1.0, *, noise=0.0, seed=0):
    """Graph z = (x^2 - y^2) / (2c) over the disc x^2 + y^2 <= extent^2, normal towards -z
    side chosen so that the curvature at the origin is (k1, k2) = (1/c, -1/c)."""
    rng = np.random.default_rng(seed)
    pts = np.empty((0, 2))
    while len(pts) < n:
        xy = rng.uniform(-extent, extent, size=(2 * n, 2))
        xy = xy[(xy ** 2).sum(1) <= extent ** 2]
        g = np.sqrt(1 + (xy[:, 0] ** 2 + xy[:, 1] ** 2) / c ** 2)   # area element
        g_max = np.sqrt(1 + extent ** 2 / c ** 2)
        pts = np.concatenate([pts, xy[rng.uniform(0, g_max, len(xy)) < g]])
    x, y = pts[:n].T
    zx, zy = x / c, -y / c
    w = np.sqrt(1 + zx ** 2 + zy ** 2)
    # normal -(grad, -1)/w = (-zx, -zy, 1)/w points to +z; the height along it is +z, and
    # clcurv's k = -(second derivative along n) gives k(x-dir) = -1/c: take n towards -z.
    nrm = np.stack([zx, zy, -np.ones(n)], axis=1) / w[:, None]
    # principal curvatures of the graph: eigenvalues of the shape operator
    fxx, fyy, fxy = 1 / c, -1 / c, 0.0
    E, F, G = 1 + zx ** 2, zx * zy, 1 + zy ** 2
    L, M, N = fxx / w, fxy / w, fyy / w
    det = E * G - F ** 2
    Hn = (E * N + G * L - 2 * F * M) / (2 * det)
    Kn = (L * N - M ** 2) / det
    disc = np.sqrt(np.maximum(Hn ** 2 - Kn, 0))
    # with the normal towards -z, clcurv's k = -(d2 of -z) = the +z shape operator's eigenvalues
    k1, k2 = Hn + disc, Hn - disc
    pts3 = np.stack([x, y, (x ** 2 - y ** 2) / (2 * c)], axis=1)
    return _finish(rng, pts3, nrm, k1, k2, noise)
