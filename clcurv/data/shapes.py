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


def sphere(n, radius=2.0, *, noise=0.0, seed=0, cap=None):
    """Sphere of ``radius`` centred at the origin: k1 = k2 = 1/radius.

    ``cap`` (radians, optional): sample only the cap of that half-angle around +z (uniform
    by area: ``z`` uniform in ``[radius cos(cap), radius]``), a dense patch for small balls."""
    rng = np.random.default_rng(seed)
    if cap is None:
        u = rng.normal(size=(n, 3))
    else:
        u = _cap_directions(rng, n, cap)
    u /= np.linalg.norm(u, axis=1)[:, None]
    k = np.full(n, 1.0 / radius)
    return _finish(rng, radius * u, u, k, k.copy(), noise)


def _cap_directions(rng, n, cap, axis=(0.0, 0.0, 1.0)):
    """``n`` unit vectors uniform on the cap of half-angle ``cap`` around ``axis``."""
    z = rng.uniform(np.cos(cap), 1.0, n)
    t = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    local = np.stack([s * np.cos(t), s * np.sin(t), z], axis=1)
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    e = np.zeros(3)
    e[np.argmin(np.abs(a))] = 1.0
    b1 = np.cross(a, e)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(a, b1)
    return local @ np.stack([b1, b2, a])


def ellipsoid(n, axes=(1.0, 0.8, 0.6), *, noise=0.0, seed=0, cap=None, axis=(0.0, 0.0, 1.0)):
    """Ellipsoid ``x^2/a^2 + y^2/b^2 + z^2/c^2 = 1`` with semi-axes ``axes = (a, b, c)``.

    Uniform by area: unit vectors ``u`` (uniform on the sphere, or on the cap of half-angle
    ``cap`` radians around ``axis`` for a dense patch) are mapped to ``(a u1, b u2, c u3)``
    and kept with probability proportional to the area ratio ``abc |(u1/a, u2/b, u3/c)|``.
    Outward normals ``(x/a^2, y/b^2, z/c^2) / h`` with ``h = |(x/a^2, y/b^2, z/c^2)|``;
    ``K = 1 / (a b c h^2)^2`` and ``H = (a^2 + b^2 + c^2 - |p|^2) / (2 a^2 b^2 c^2 h^3)``
    (positive: convex with outward normals), ``k1,2 = H +- sqrt(H^2 - K)``. Four umbilics
    (k1 = k2) in the plane of the longest and shortest axes."""
    rng = np.random.default_rng(seed)
    ax = np.asarray(axes, dtype=np.float64)
    out = np.empty((0, 3))
    while len(out) < n:
        m = 2 * (n - len(out)) + 16
        if cap is None:
            u = rng.normal(size=(m, 3))
            u /= np.linalg.norm(u, axis=1)[:, None]
        else:
            u = _cap_directions(rng, m, cap, axis)
        g = np.sqrt(((u / ax) ** 2).sum(axis=1)) * ax.min()          # area ratio / its max
        out = np.concatenate([out, u[rng.uniform(0, 1, m) < g]])
    pts = out[:n] * ax
    grad = pts / ax ** 2
    h = np.linalg.norm(grad, axis=1)
    nrm = grad / h[:, None]
    abc2 = np.prod(ax) ** 2
    K = 1.0 / (abc2 * h ** 4)
    H = (np.sum(ax ** 2) - np.einsum("ij,ij->i", pts, pts)) / (2.0 * abc2 * h ** 3)
    d = np.sqrt(np.maximum(H * H - K, 0.0))
    return _finish(rng, pts, nrm, H + d, H - d, noise)


def wave(n, amplitude=0.1, wavelength=1.0, extent=1.0, *, noise=0.0, seed=0):
    """Wave graph ``z = A sin(w x) sin(w y)``, ``w = 2 pi / wavelength``, over the square
    ``|x|, |y| <= extent``, uniform by area (rejection on ``sqrt(1 + zx^2 + zy^2)``).

    Normals point up (+z side): ``(-zx, -zy, 1) / sqrt(1 + zx^2 + zy^2)``. clcurv's sign
    (a surface bending away from its normal is positive): a crest has ``k1 = k2 = A w^2 > 0``
    and a trough ``-A w^2``; elsewhere saddles and umbilic points mix. The curvatures are
    minus the eigenvalues of the graph's shape operator ``I^-1 II``, as for MLS2:
    ``H = -((1 + zy^2) zxx - 2 zx zy zxy + (1 + zx^2) zyy) / (2 W^3)``,
    ``K = (zxx zyy - zxy^2) / W^4``, ``W = sqrt(1 + zx^2 + zy^2)``."""
    rng = np.random.default_rng(seed)
    a, w = float(amplitude), 2.0 * np.pi / float(wavelength)
    gmax = np.sqrt(1.0 + 2.0 * (a * w) ** 2)
    xy = np.empty((0, 2))
    while len(xy) < n:
        m = 2 * (n - len(xy)) + 16
        c = rng.uniform(-extent, extent, size=(m, 2))
        zx = a * w * np.cos(w * c[:, 0]) * np.sin(w * c[:, 1])
        zy = a * w * np.sin(w * c[:, 0]) * np.cos(w * c[:, 1])
        keep = rng.uniform(0, gmax, m) < np.sqrt(1.0 + zx * zx + zy * zy)
        xy = np.concatenate([xy, c[keep]])
    x, y = xy[:n].T
    sx, cx, sy, cy = np.sin(w * x), np.cos(w * x), np.sin(w * y), np.cos(w * y)
    zx, zy = a * w * cx * sy, a * w * sx * cy
    zxx, zyy, zxy = -a * w * w * sx * sy, -a * w * w * sx * sy, a * w * w * cx * cy
    ww = np.sqrt(1.0 + zx * zx + zy * zy)
    H = -((1 + zy * zy) * zxx - 2 * zx * zy * zxy + (1 + zx * zx) * zyy) / (2.0 * ww ** 3)
    K = (zxx * zyy - zxy * zxy) / ww ** 4
    d = np.sqrt(np.maximum(H * H - K, 0.0))
    nrm = np.stack([-zx, -zy, np.ones(n)], axis=1) / ww[:, None]
    pts = np.stack([x, y, a * sx * sy], axis=1)
    return _finish(rng, pts, nrm, H + d, H - d, noise)


def chirp(n, amplitude=0.02, wavelengths=(1.0, 0.3), extent=(2.0, 0.6), power=0.0, *,
          noise=0.0, seed=0):
    """A chirp: the ridged graph ``z = A(x) sin(phi(x))`` whose frequency grows across x,
    over ``0 <= x <= extent[0]``, ``0 <= y <= extent[1]``, uniform by area (rejection on
    ``sqrt(1 + f'^2)``). A surface whose curvature varies by a known factor, for choosing a
    radius per point (issue 51).

    The angular frequency ``w(x) = phi'(x) = w0 exp(b x)`` grows geometrically from
    ``w0 = 2 pi / wavelengths[0]`` at ``x = 0`` to ``w1 = 2 pi / wavelengths[1]`` at
    ``x = extent[0]`` (``b = ln(w1 / w0) / extent[0]``), so ``phi(x) = w0 (exp(b x) - 1) / b``;
    the amplitude ``A(x) = amplitude (w0 / w(x))^power`` (``power = 0``: constant amplitude,
    the crests' curvature grows as ``w^2``; ``power = 1``: constant slope, as ``w``). The
    envelope of ``|H|`` (crests) therefore grows by ``(w1 / w0)^(2 - power)`` between the
    two ends: 11.1x with the defaults (the crests actually sampled are fewer: the first
    lies a quarter period in, so their range is smaller, ~8x with the defaults); H passes
    through 0 on every inflection line ``sin(phi) = 0``.

    Exact derivatives (``A' = -power b A``):
    ``f' = A (w cos(phi) - power b sin(phi))``,
    ``f'' = A ((power^2 b^2 - w^2) sin(phi) + (1 - 2 power) b w cos(phi))``.
    Normals point up (+z side): ``(-f', 0, 1) / W``, ``W = sqrt(1 + f'^2)``. The surface is a
    cylinder over the profile (straight along y): one principal curvature is 0 and the other
    is clcurv's ``kappa = -f'' / W^3`` (bending away from the upward normal is positive, so
    a crest is positive), ``k1 = max(kappa, 0)``, ``k2 = min(kappa, 0)``, ``H = kappa / 2``,
    ``K = 0``; ``dir1`` is the profile's tangent ``(1, 0, f') / W`` where ``kappa >= 0``, else
    ``(0, 1, 0)``.

    Returns the dict of the other samplers plus ``"omega"`` (N,): the local angular
    frequency ``w(x)`` of each sample (noise added along the normal after)."""
    rng = np.random.default_rng(seed)
    lx, ly = (float(e) for e in extent)
    w0, w1 = 2.0 * np.pi / float(wavelengths[0]), 2.0 * np.pi / float(wavelengths[1])
    if not (lx > 0 and ly > 0 and w0 > 0 and w1 > 0):
        raise ValueError(f"extent and wavelengths must be positive, got {extent}, {wavelengths}")
    b = np.log(w1 / w0) / lx
    a0, pw = float(amplitude), float(power)

    def profile(x):
        w = w0 * np.exp(b * x)
        phi = w0 * np.expm1(b * x) / b if b != 0 else w0 * x
        amp = a0 * (w0 / w) ** pw
        s, c = np.sin(phi), np.cos(phi)
        f1 = amp * (w * c - pw * b * s)
        f2 = amp * ((pw * pw * b * b - w * w) * s + (1.0 - 2.0 * pw) * b * w * c)
        return amp * s, f1, f2, w

    grid = np.linspace(0.0, lx, 4097)
    gmax = np.sqrt(1.0 + np.max(np.abs(profile(grid)[1])) ** 2) * 1.01
    xy = np.empty((0, 2))
    while len(xy) < n:
        m = 2 * (n - len(xy)) + 16
        c = rng.uniform(0.0, 1.0, size=(m, 2)) * [lx, ly]
        keep = rng.uniform(0, gmax, m) < np.sqrt(1.0 + profile(c[:, 0])[1] ** 2)
        xy = np.concatenate([xy, c[keep]])
    x, y = xy[:n].T
    f, f1, f2, w = profile(x)
    ww = np.sqrt(1.0 + f1 * f1)
    kappa = -f2 / ww ** 3
    nrm = np.stack([-f1, np.zeros(n), np.ones(n)], axis=1) / ww[:, None]
    tangent = np.stack([np.ones(n), np.zeros(n), f1], axis=1) / ww[:, None]
    dir1 = np.where((kappa >= 0)[:, None], tangent, [0.0, 1.0, 0.0])
    pts = np.stack([x, y, f], axis=1)
    out = _finish(rng, pts, nrm, np.maximum(kappa, 0.0), np.minimum(kappa, 0.0), noise, dir1)
    out["omega"] = w
    return out


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


def _concat(parts):
    """One sample from several: every array concatenated (dir1 only if all have it)."""
    keys = [k for k in parts[0] if all(k in p for p in parts)]
    return {k: np.concatenate([p[k] for p in parts]) for k in keys}


def two_spheres(n, radius=1.0, gap=1.0, *, noise=0.0, seed=0):
    """Two disjoint spheres of ``radius`` on the x axis, ``gap`` apart (n // 2 points each)."""
    parts = [sphere(m, radius, noise=noise, seed=seed + i) for i, m in
             enumerate((n // 2, n - n // 2))]
    for p, sgn in zip(parts, (-1, 1)):
        p["points"] = p["points"] + [sgn * (radius + gap / 2), 0.0, 0.0]
    return _concat(parts)


def hollow_shell(n, outer=1.0, inner=0.7, *, noise=0.0, seed=0):
    """A hollow spherical shell: the solid between two concentric spheres. Its normals
    point out of the solid: away from the centre on the outer wall, towards it on the inner
    wall, whose curvatures are then -1/inner (it bends towards its normal). Points are
    split between the walls in proportion to their areas."""
    m = int(round(n * outer ** 2 / (outer ** 2 + inner ** 2)))
    a = sphere(m, outer, noise=noise, seed=seed)
    b = sphere(n - m, inner, noise=noise, seed=seed + 1)
    for key in ("normals", "k1", "k2", "H"):
        b[key] = -b[key]
    return _concat([a, b])


def thin_box(spacing, thickness, side=1.0, *, seed=0):
    """A closed box ``side`` x ``side`` x ``thickness`` centred at the origin, sampled
    uniformly on its six faces at about one point per ``spacing**2``: a thin plate whose
    two large faces are ``thickness / spacing`` samples apart. Flat faces: k1 = k2 = 0
    (the edges' curvature is not modelled)."""
    rng = np.random.default_rng(seed)
    dims = np.array([side, side, thickness], dtype=np.float64)
    pts, nrm = [], []
    for ax in range(3):
        o = [a for a in range(3) if a != ax]
        m = max(1, int(dims[o[0]] * dims[o[1]] / spacing ** 2))
        for sgn in (-1.0, 1.0):
            q = np.empty((m, 3))
            q[:, o[0]] = rng.uniform(0, dims[o[0]], m)
            q[:, o[1]] = rng.uniform(0, dims[o[1]], m)
            q[:, ax] = dims[ax] if sgn > 0 else 0.0
            nn = np.zeros((m, 3))
            nn[:, ax] = sgn
            pts.append(q - dims / 2)
            nrm.append(nn)
    pts, nrm = np.concatenate(pts), np.concatenate(nrm)
    zero = np.zeros(len(pts))
    return _finish(rng, pts, nrm, zero, zero.copy(), 0.0)


def aerial_scene(n, extent=(97.3, 61.9), *, origin=(481200.25, 4390100.5, 12.0), seed=0):
    """A synthetic aerial LiDAR scene of about ``n`` points (x, y, z in metres, z up): rolling
    terrain, gable-roofed houses with vertical walls, and trees (noisy crowns on trunks),
    over an ``extent`` (x, y) from ``origin`` (a UTM-like offset, so coordinates are large).

    Returns a dict with ``points`` (N, 3) and ``kind`` (N,) uint8: 2 ground, 6 building,
    5 vegetation (the ASPRS LAS classes). No analytic curvature: a scene for the tiled
    engine and the features, not an accuracy test."""
    rng = np.random.default_rng(seed)
    ex, ey = extent
    ox, oy, oz = origin

    def ground(x, y):
        return 1.5 * np.sin(x / 17.0) * np.cos(y / 23.0) + 0.02 * x

    m_ground, m_house, m_tree = int(0.6 * n), int(0.25 * n), n - int(0.6 * n) - int(0.25 * n)
    x, y = rng.uniform(0, ex, m_ground), rng.uniform(0, ey, m_ground)
    parts = [(np.stack([x, y, ground(x, y)], axis=1), 2)]
    houses = max(1, int(ex * ey / 900))
    per = max(1, m_house // houses)
    for _ in range(houses):
        cx, cy = rng.uniform(8, ex - 8), rng.uniform(8, ey - 8)
        w, d, hw, hr = rng.uniform(5, 8), rng.uniform(4, 6), rng.uniform(3, 5), rng.uniform(1, 2.5)
        base = ground(cx, cy)
        k = per // 2
        u, v = rng.uniform(-w, w, k), rng.uniform(-d, d, k)           # gable roof
        roof = np.stack([cx + u, cy + v, base + hw + hr * (1 - np.abs(v) / d)], axis=1)
        t = rng.uniform(0, 4 * (w + d), per - k)                       # four walls
        s = rng.uniform(0, hw, per - k)
        wx = np.where(t < 2 * w, -w + t, np.where(t < 2 * w + 2 * d, w, np.where(
            t < 4 * w + 2 * d, w - (t - 2 * w - 2 * d), -w)))
        wy = np.where(t < 2 * w, -d, np.where(t < 2 * w + 2 * d, -d + (t - 2 * w), np.where(
            t < 4 * w + 2 * d, d, d - (t - 4 * w - 2 * d))))
        walls = np.stack([cx + np.clip(wx, -w, w), cy + np.clip(wy, -d, d), base + s], axis=1)
        parts.append((np.concatenate([roof, walls]), 6))
    trees = max(1, int(ex * ey / 400))
    per = max(1, m_tree // trees)
    for _ in range(trees):
        cx, cy = rng.uniform(2, ex - 2), rng.uniform(2, ey - 2)
        c = rng.normal(size=(per, 3))
        c /= np.linalg.norm(c, axis=1)[:, None]
        c *= rng.uniform(0.6, 1.0, (per, 1)) * np.array([2.5, 2.5, 3.0])
        crown = c + [cx, cy, ground(cx, cy) + 6.0]
        parts.append((crown, 5))
    pts = np.concatenate([p for p, _ in parts])
    kind = np.concatenate([np.full(len(p), k, np.uint8) for p, k in parts])
    perm = rng.permutation(len(pts))                    # scanner order is not spatial
    return {"points": pts[perm] + np.asarray(origin, float), "kind": kind[perm]}
