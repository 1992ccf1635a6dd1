"""Render a point cloud coloured by a per-point field to a picture (matplotlib, Agg, no display).

:func:`render` draws orthographic projections of the cloud from two or three viewpoints side
by side, with one colorbar and a caption giving the point, drawn-point and NaN counts::

    import clcurv
    from clcurv.render import render
    res = clcurv.curvature(pts, 0.01, method="mls1")
    render(pts, res.mean, "bunny_H.png", field="mean_curvature", unit="1/m")

Views follow the usual scanned-object convention (y up, as in the Stanford models):

========  ===================  ==================  ===============
name      seen from            screen right, up    nearer points
========  ===================  ==================  ===============
front     +z                   +x, +y              larger z
back      -z                   -x, +y              smaller z
side      +x  (alias "right")  -z, +y              larger x
left      -x                   +z, +y              smaller x
top       +y                   +x, -z              larger y
bottom    -y                   +x, +z              smaller y
iso       (+1, +1, +1)         oblique, y up       larger x+y+z
oblique   40 deg above +z      +x, tilted up       towards +z and up
========  ===================  ==================  ===============

The table is in the frame where the cloud's up axis is +y. ``up`` names the cloud's up axis
(:func:`up_axis`): ``"auto"`` takes +Z for LAS/LAZ input (``source``), else the axis of
smallest extent of a flat cloud (terrain in any format), else +Y (scanned objects); or
``"x"``, ``"-z"``, ... or three numbers. The cloud is turned so that up becomes +y before the
views, so with up = +Z the top view shows x to the right and y up, as a map. Terrain (a
cloud whose extent along up is under a quarter of its horizontal extents,
:func:`default_views`) leads with the top view and an oblique view; other clouds get
front, side and top. All views of one figure share the same scale.

Points are sorted by depth so that near points are drawn last (over far ones); points whose
value is NaN are drawn first, beneath every valued point, so that they never hide one.
Signed fields use a diverging colormap centred on 0 ("RdBu_r", symmetric limits); unsigned
ones "viridis". Colour limits are robust percentiles of the finite values; NaN values are
drawn light grey. With standard errors (``se``: ``clcurv compute --uncertainty``'s
``mean_curvature_se`` for ``mean_curvature``...), the values not significant at about 95%,
``|value| < 2 se``, are drawn mid grey: the view that tells a ridge from noise. The colour bar's label is kept inside the picture (the figure is widened,
or the label's font reduced, when it would not fit).

The picture format follows the extension of the output (:data:`IMAGE_FORMATS`: PNG, JPEG,
PDF, SVG, TIFF, WebP); any other extension, a point cloud's included, is refused before
drawing by :func:`check_image_output`, which a command can also call before its computation.
The picture is written atomically (:func:`clcurv.io.atomic_output`): a failed write leaves
the previous file as it was. Folders are not created.

matplotlib is imported inside :func:`render` only; without it :class:`MissingMatplotlibError`
(an ``ImportError``) says how to install it.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from clcurv.ops.features import FEATURES
from clcurv.io import atomic_output, check_output, is_las
from clcurv.ops.registry import OPERATORS, signed_file_fields

__all__ = ["render", "figure", "check_image_output", "MissingMatplotlibError", "VIEWS",
           "SIGNED_FIELDS", "IMAGE_FORMATS", "up_axis", "default_views", "field_unit"]

#: Extensions :func:`render` writes (lower case) -> the format given to matplotlib's
#: ``savefig`` (Agg canvas; JPEG, TIFF and WebP through Pillow, a matplotlib dependency).
IMAGE_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".pdf": "pdf",
                 ".svg": "svg", ".tif": "tiff", ".tiff": "tiff", ".webp": "webp"}

#: Field names treated as signed (diverging colormap) when ``signed=None`` and the values
#: take both signs: the file fields and result attributes of the registry's signed outputs
#: (``mean_curvature``/``mean`` H, ``gaussian_curvature``/``gaussian`` K, ``k1``, ``k2``)
#: and the usual symbols ``h`` and ``k`` of H and K.
SIGNED_FIELDS = frozenset(signed_file_fields()
                          | {o.name for op in OPERATORS.values() for o in op.outputs if o.signed}
                          | {"h", "k"})

#: The unit of every other field clcurv writes (besides the operators' outputs and the
#: covariance features, which carry theirs): counts and statuses have none.
_OTHER_UNITS = {"neighbours": "", "status": "", "number_of_neighbors": "",
                "feature_status": "", "nx": "", "ny": "", "nz": "",
                "knn_radius": "length", "optimal_radius": "length"}
_RADIUS_SUFFIX = re.compile(r"^(.+)_r[0-9.eE+-]+$")


def field_unit(name):
    """The unit of a field that clcurv writes, for the colour-bar label: the registry's
    (:mod:`clcurv.ops.registry` outputs, e.g. ``"1/length"`` for ``mean_curvature``,
    ``"1/length^2"`` for ``gaussian_curvature``; :data:`clcurv.api.features.FEATURES`, also with
    a ``_r<radius>`` suffix, e.g. ``"length^2"`` for ``eigenvalue_sum``), ``""`` for a
    dimensionless field (planarity, directions, counts, statuses), None for a name clcurv
    does not write (a field of another tool: its unit is unknown)."""
    for op in OPERATORS.values():
        for o in op.outputs:
            if name in o.file_fields() or name == o.name:
                return "" if o.unit == "1" else o.unit
    m = _RADIUS_SUFFIX.match(name)
    for base in (name, m.group(1) if m else None):
        if base in FEATURES:
            unit = FEATURES[base].unit
            return "" if unit == "1" else unit
        if base in _OTHER_UNITS:
            return _OTHER_UNITS[base]
    return None


_S3 = 1.0 / np.sqrt(3.0)
_S2 = 1.0 / np.sqrt(2.0)
_S6 = 1.0 / np.sqrt(6.0)

#: name -> (screen right, screen up, towards the viewer), each a unit 3-vector.
VIEWS = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "back": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "side": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "right": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "left": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
    "top": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "bottom": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "iso": ((_S2, 0, -_S2), (-_S6, 2 * _S6, -_S6), (_S3, _S3, _S3)),
    "oblique": ((1, 0, 0), (0, np.cos(np.radians(40)), -np.sin(np.radians(40))),
                (0, np.sin(np.radians(40)), np.cos(np.radians(40)))),
}
#: a cloud whose extent along up is below this fraction of its horizontal extents is terrain
TERRAIN_RATIO = 0.25
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}

_AXIS_NAMES = {(1, 0, 0): "x", (0, 1, 0): "y", (0, 0, 1): "z"}
_NAN_GREY = "#c8c8c8"
#: the colour of values not significant (|value| < SIGNIFICANCE * se)
_NOT_SIGNIFICANT_GREY = "#8c8c8c"
#: significance at about 95% (two standard errors)
SIGNIFICANCE = 2.0


class MissingMatplotlibError(ImportError):
    """matplotlib is not installed; ``pip install matplotlib`` (or ``clcurv[render]``)."""


def _import_matplotlib():
    try:   # here, not at the top: matplotlib is an optional extra (clcurv[render])
        import matplotlib  # noqa: F401
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - exercised only without matplotlib
        raise MissingMatplotlibError(
            "clcurv.render needs matplotlib: pip install matplotlib "
            '(or pip install "clcurv[render]")') from exc
    return matplotlib, Figure, FigureCanvasAgg


def _axis_label(vec):
    """'+x', '-z', or '' for an oblique direction."""
    v = tuple(int(round(c)) for c in vec)
    if sum(abs(c) for c in v) != 1 or not np.allclose(vec, v):
        return ""
    sign = "-" if min(v) < 0 else "+"
    return sign + _AXIS_NAMES[tuple(abs(c) for c in v)]


def _is_signed(signed, field, lo, hi, finite):
    if signed is not None:
        return bool(signed)
    if finite.size == 0:
        return False
    if lo < 0 < hi:
        return True
    vmin, vmax = float(finite.min()), float(finite.max())
    return str(field).lower() in SIGNED_FIELDS and vmin < 0 < vmax


def _fmt_count(n):
    return f"{n:,}"


def _point_diameter_px(u, v, scale_px, n_drawn):
    """Marker diameter (pixels) so that the projected points roughly tile the silhouette.

    The silhouette area is estimated on a coarse occupancy grid; about half of the points are
    assumed on the visible side of a closed surface. The density used is the lower of that
    average and the 25th percentile of the local densities on a finer grid (about 25 points a
    cell), so that sparsely sampled parts (the middle of a projected sphere) are also closed.
    """
    if u.size == 0:
        return 2.0
    du = max(float(np.ptp(u)), 1e-300) * scale_px
    dv = max(float(np.ptp(v)), 1e-300) * scale_px
    bins = 48
    h, _, _ = np.histogram2d(u, v, bins=bins)
    area_px = max(np.count_nonzero(h) / (bins * bins) * du * dv, 1.0)
    rho = 0.5 * n_drawn / area_px  # visible points per pixel
    cell = np.sqrt(25.0 / rho) if rho > 0 else max(du, dv)
    nu = int(np.clip(du / cell, 1, 512))
    nv = int(np.clip(dv / cell, 1, 512))
    if nu * nv >= 16:
        h, _, _ = np.histogram2d(u, v, bins=(nu, nv))
        counts = h[h > 0]
        local = 0.5 * np.percentile(counts, 25) / (du * dv / (nu * nv))
        rho = min(rho, max(local, 0.3 * rho))
    d = 2.5 * np.sqrt(1.0 / max(rho, 1e-12))
    return float(np.clip(d, 0.9, 9.0))


def up_axis(up="auto", points=None, source=None):
    """The cloud's up direction as a unit float64 3-vector.

    ``up``: "auto" (+Z when ``source``, a file name, is LAS/LAZ; else the axis of smallest
    extent when ``points`` are flat: that extent under :data:`TERRAIN_RATIO` times the
    middle one; else +Y), an axis name "x", "+y", "-z", or three numbers.
    """
    if up is None or (isinstance(up, str) and up == "auto"):
        if source is not None and is_las(source):     # z-up (ASPRS: Z is elevation)
            return np.array(_AXES["z"])
        if points is not None and len(points):
            pts = np.asarray(points, dtype=np.float64)
            ext = np.ptp(pts[np.isfinite(pts).all(axis=1)], axis=0) if len(pts) else None
            if ext is not None and ext.size:
                order = np.argsort(ext)
                if ext[order[0]] < TERRAIN_RATIO * ext[order[1]]:
                    return np.eye(3)[order[0]]
        return np.array(_AXES["y"])
    if isinstance(up, str):
        s = up.strip().lower()
        sign = -1.0 if s.startswith("-") else 1.0
        axis = _AXES.get(s.lstrip("+-"))
        if axis is None:
            raise ValueError(f"up must be 'auto', an axis (x, y, z, -z, ...) or 3 numbers, "
                             f"got {up!r}")
        return sign * np.array(axis)
    v = np.asarray(up, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all() or not np.any(v):
        raise ValueError(f"up must be 'auto', an axis or 3 finite numbers, got {up!r}")
    return v / np.linalg.norm(v)


def _frame(up):
    """Rows (x', y' = up, z' = x' x y'): the rotation that makes ``up`` the +y of the view
    table (x' the first of x, y, z not along up, made orthogonal to it)."""
    ex = next(np.array(a) for a in _AXES.values() if abs(np.dot(a, up)) < 0.9)
    ex = ex - np.dot(ex, up) * up
    ex /= np.linalg.norm(ex)
    return np.array([ex, up, np.cross(ex, up)])


def is_terrain(points, up):
    """True when the extent of ``points`` along ``up`` is below TERRAIN_RATIO times both
    horizontal extents (in the frame of :func:`_frame`)."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        return False
    ext = np.ptp(pts @ _frame(up).T, axis=0)
    return bool(ext[1] < TERRAIN_RATIO * min(ext[0], ext[2]))


def default_views(points, up):
    """("top", "oblique") for terrain (:func:`is_terrain`), else ("front", "side", "top")."""
    return ("top", "oblique") if is_terrain(points, up) else ("front", "side", "top")


def check_image_output(path) -> Path:
    """Check that :func:`render` can write ``path``, without drawing or writing; return it.

    The extension must be one of :data:`IMAGE_FORMATS` (so ``-o cloud.ply`` cannot replace a
    point cloud with a picture), the folder must exist (it is not created) and be writable,
    and ``path`` must not be a directory or a read-only file: :func:`clcurv.io.check_output`
    with the picture formats.

    Raises
    ------
    clcurv.io.OutputPathError
        A :class:`clcurv.io.WriteError` (a ``ValueError``) whose message starts with ``path``
        and, for a bad extension, lists the accepted ones.
    """
    return check_output(path, IMAGE_FORMATS, what="picture")


def render(points, values, path, *, field="mean_curvature", unit="auto",
           signed=None, views=None, up="auto", source=None, max_points=200_000,
           percentiles=(2, 98), title=None, dpi=110, seed=0, se=None) -> Path:
    """Write a picture of ``points`` coloured by ``values`` seen from ``views``; return its path.

    Parameters
    ----------
    points : (N, 3) array_like
        Positions. Rows with a non-finite coordinate are not drawn (counted in the caption).
    values : (N,) array_like
        The per-point field (NaN allowed: drawn light grey and counted in the caption).
    path : str or Path
        Output picture; its extension gives the format, one of :data:`IMAGE_FORMATS`
        (``.png``, ``.jpg``, ``.pdf``, ``.svg``...). The folder must exist. Written
        atomically: on failure the previous file is kept and nothing else is left.
    field, unit : str
        Colorbar label ``"field [unit]"`` (``unit`` may be empty or None: ``"field"``).
        ``unit="auto"``: :func:`field_unit` of ``field`` (none for a dimensionless field
        or a name clcurv does not write).
    signed : bool or None
        Diverging colormap centred on 0 (True) or sequential (False). None: signed when the
        robust range contains both signs, or when ``field`` is a curvature name
        (:data:`SIGNED_FIELDS`) and the values take both signs.
    views : sequence of str, optional
        1 to 6 names from :data:`VIEWS`, drawn left to right at a common scale. Default
        :func:`default_views`: top and oblique for terrain, else front, side and top.
    up : "auto", axis name or 3 numbers
        The cloud's up axis (:func:`up_axis`; "auto": +Z for LAS/LAZ ``source``, the thin
        axis of a flat cloud, else +Y).
    source : str or Path, optional
        The file the points come from (its extension decides "auto" for LAS/LAZ).
    max_points : int
        Draw at most this many points, a uniform random subsample (``seed``) when N is larger.
    percentiles : (lo, hi)
        Colour limits from these percentiles of the finite values (symmetric ``+-max(|lo|,
        |hi|)`` when signed); values beyond are clipped to the colormap ends.
    title : str or None
        First line of the caption (default: the field name).
    dpi : int
        A raster picture is ``figsize * dpi`` pixels; the figure is ``(3.7 * len(views) + 0.9) x 4.5``
        inches (12 x 4.5 for three views).
    seed : int
        Seed of the subsample.
    se : (N,) array_like, optional
        Standard errors of ``values`` (same unit): points whose ``|value| < 2 se`` (not
        significant at about 95%) are drawn mid grey and counted in the caption; a NaN ``se`` leaves its point coloured. The colour range is that of
        every finite value.

    Raises
    ------
    clcurv.io.OutputPathError
        ``path`` cannot be written (:func:`check_image_output`): not a picture extension,
        missing folder, a directory, read-only folder or file. Checked before drawing.
    clcurv.io.WriteFailedError
        Writing failed part way (disk full...); also an ``OSError``. The previous file is kept.
    ValueError
        ``points`` not (N, 3), ``values`` not of length N, bad ``views``, ``percentiles``,
        ``max_points`` or ``dpi``.
    MissingMatplotlibError
        matplotlib is not installed (an ``ImportError``).
    """
    path = check_image_output(path)
    fig, _ = figure(points, values, field=field, unit=unit, signed=signed, views=views, up=up,
                    source=source, max_points=max_points, percentiles=percentiles, title=title,
                    dpi=dpi, seed=seed, se=se)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=IMAGE_FORMATS[path.suffix.lower()], facecolor="white")
    return path


def figure(points, values, *, field="mean_curvature", unit="auto", signed=None,
           views=None, up="auto", source=None, max_points=200_000, percentiles=(2, 98),
           title=None, dpi=110, seed=0, se=None):
    """The matplotlib Figure that :func:`render` writes (same parameters, no path), and a
    dict: ``views``, ``up`` (unit vector), ``terrain``, ``label`` (the colour-bar label),
    ``label_bbox`` (its (x0, y0, x1, y1) in pixels of the written picture, origin bottom
    left) and
    ``size`` (width, height) in pixels, ``not_significant``: how many points have
    ``|value| < 2 se`` (0 without ``se``)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {pts.shape}")
    n = pts.shape[0]
    vals = np.asarray(values, dtype=np.float64)
    if vals.ndim == 2 and vals.shape[1] == 1:
        vals = vals[:, 0]
    if vals.ndim != 1 or vals.shape[0] != n:
        raise ValueError(f"values must have one entry per point ({n}), got shape {vals.shape}")
    if se is not None:
        se = np.asarray(se, dtype=np.float64)
        if se.shape != vals.shape:
            raise ValueError(f"se must have one entry per point ({n}), got shape {se.shape}")
        with np.errstate(invalid="ignore"):
            insignificant = np.abs(vals) < SIGNIFICANCE * se       # False where NaN
    else:
        insignificant = np.zeros(n, dtype=bool)
    n_insig = int(np.count_nonzero(insignificant))
    upv = up_axis(up, pts if pts.ndim == 2 and pts.shape[-1] == 3 else None, source)
    if views is None:
        views = default_views(pts, upv)
    if isinstance(views, str):
        views = (views,)
    views = tuple(views)
    if not 1 <= len(views) <= 6:
        raise ValueError(f"views must name 1 to 6 viewpoints, got {len(views)}")
    for name in views:
        if name not in VIEWS:
            raise ValueError(f"unknown view {name!r}; choose from {', '.join(VIEWS)}")
    try:
        p_lo, p_hi = (float(p) for p in percentiles)
    except (TypeError, ValueError):
        raise ValueError(f"percentiles must be a pair (lo, hi), got {percentiles!r}") from None
    if not 0.0 <= p_lo < p_hi <= 100.0:
        raise ValueError(f"percentiles must satisfy 0 <= lo < hi <= 100, got {percentiles!r}")
    if int(max_points) < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    if dpi <= 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    max_points = int(max_points)

    matplotlib, Figure, FigureCanvasAgg = _import_matplotlib()
    from matplotlib.colors import Normalize, to_rgba   # the optional extra, found above
    from matplotlib.cm import ScalarMappable

    # --- colour scale from all finite values (before subsampling) ---------------------------
    finite_mask = np.isfinite(vals)
    finite = vals[finite_mask]
    n_nan = int(n - finite.size)
    if finite.size:
        lo, hi = (float(x) for x in np.percentile(finite, [p_lo, p_hi]))
    else:
        lo, hi = 0.0, 1.0
    is_signed = _is_signed(signed, field, lo, hi, finite)
    if is_signed:
        m = max(abs(lo), abs(hi))
        if not m > 0:
            m = float(np.max(np.abs(finite))) if finite.size else 0.0
        if not m > 0:
            m = 1.0
        vmin, vmax = -m, m
        cmap_name = "RdBu_r"
    else:
        vmin, vmax = lo, hi
        if not vmax > vmin:
            pad = abs(vmin) * 0.05 if vmin != 0 else 0.5
            vmin, vmax = vmin - pad, vmax + pad
        cmap_name = "viridis"
    cmap = matplotlib.colormaps[cmap_name].with_extremes(bad=_NAN_GREY)
    norm = Normalize(vmin=vmin, vmax=vmax)
    below = finite.size and float(finite.min()) < vmin
    above = finite.size and float(finite.max()) > vmax
    extend = {(True, True): "both", (True, False): "min",
              (False, True): "max"}.get((bool(below), bool(above)), "neither")

    # --- subsample, drop non-finite positions -----------------------------------------------
    if n > max_points:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(n, size=max_points, replace=False))
    else:
        idx = np.arange(n)
    n_shown = idx.size
    good = np.all(np.isfinite(pts[idx]), axis=1)
    n_bad_pos = int(n_shown - np.count_nonzero(good))
    idx = idx[good]
    sp = pts[idx]
    sv = vals[idx]
    s_insig = insignificant[idx]
    center = 0.5 * (sp.min(axis=0) + sp.max(axis=0)) if sp.size else np.zeros(3)
    frame = _frame(upv)
    sp = (sp - center) @ frame.T          # up is +y of the view table

    # --- layout (inches): panels side by side, colorbar at the right ------------------------
    nv = len(views)
    panel_w, fig_h = 3.7, 4.5
    left_pad, cbar_w = 0.1, 0.9
    fig_w = panel_w * nv + cbar_w
    top_pad, bottom_pad = 0.75, 0.1
    panel_h = fig_h - top_pad - bottom_pad
    inner_w, inner_h = panel_w - 2 * left_pad, panel_h - 0.25  # room for the view label

    fig = Figure(figsize=(fig_w, fig_h), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    placed = []                           # (axes, rect in inches): re-placed if widened

    def add_axes(rect_in):
        ax = fig.add_axes((rect_in[0] / fig_w, rect_in[1] / fig_h, rect_in[2] / fig_w,
                           rect_in[3] / fig_h))
        placed.append((ax, rect_in))
        return ax

    projections = []
    for name in views:
        r, up, toward = (np.asarray(a, dtype=np.float64) for a in VIEWS[name])
        projections.append((sp @ r, sp @ up, sp @ toward))
    # common scale: data units per inch that fits every view in its panel
    need = 1e-300
    for u, v, _ in projections:
        if u.size:
            need = max(need, np.ptp(u) / inner_w, np.ptp(v) / inner_h)
    units_per_inch = need * 1.08
    if not np.isfinite(units_per_inch) or units_per_inch <= 1e-300:
        units_per_inch = 1.0
    scale_px = dpi / units_per_inch  # pixels per data unit

    for k, (name, (u, v, depth)) in enumerate(zip(views, projections)):
        ax = add_axes((k * panel_w + left_pad, bottom_pad, inner_w, inner_h))
        ax.set_facecolor("white")
        ax.set_xticks([])
        ax.set_yticks([])
        for s in ax.spines.values():
            s.set_visible(False)
        cu = 0.5 * (u.min() + u.max()) if u.size else 0.0
        cv = 0.5 * (v.min() + v.max()) if v.size else 0.0
        half_w = 0.5 * inner_w * units_per_inch
        half_h = 0.5 * inner_h * units_per_inch
        ax.set_xlim(cu - half_w, cu + half_w)
        ax.set_ylim(cv - half_h, cv + half_h)
        ax.set_aspect("equal", adjustable="box")
        r, vu, _ = VIEWS[name]              # screen directions, back in the cloud's axes
        lr, lu = _axis_label(frame.T @ np.asarray(r)), _axis_label(frame.T @ np.asarray(vu))
        label = f"{name}  ({lr} \u2192, {lu} \u2191)" if lr and lu else name
        ax.set_title(label, fontsize=9, color="#555555", pad=4)
        if u.size == 0:
            continue
        d_px = _point_diameter_px(u, v, scale_px, u.size)
        size_pt2 = (d_px * 72.0 / dpi) ** 2
        valued = np.isfinite(sv)
        # NaN points first (beneath), then the valued ones, those not significant in grey
        # among them; each far first, near last
        for part in (~valued, valued):
            sel = np.flatnonzero(part)
            if sel.size == 0:
                continue
            sel = sel[np.argsort(depth[sel], kind="stable")]
            if part is valued and s_insig[sel].any():
                rgba = cmap(norm(sv[sel]))
                rgba[s_insig[sel]] = to_rgba(_NOT_SIGNIFICANT_GREY)
                colour = dict(color=rgba)
            else:
                colour = dict(c=sv[sel], cmap=cmap, norm=norm, plotnonfinite=True)
            ax.scatter(u[sel], v[sel], s=size_pt2, marker="o", linewidths=0,
                       edgecolors="none", rasterized=True, **colour)

    # --- colorbar (and a grey "NaN" key when some values are NaN) --------------------------
    cb_x = fig_w - cbar_w + 0.12
    cb_w = 0.16
    cb_y0, cb_h = bottom_pad + 0.6, panel_h - 1.1
    if unit == "auto":
        unit = field_unit(field)
    label = f"{field} [{unit}]" if unit else f"{field}"
    cax = add_axes((cb_x, cb_y0, cb_w, cb_h))
    if finite.size:
        sm = ScalarMappable(norm=norm, cmap=cmap)
        sm.set_array(np.array([]))
        cb = fig.colorbar(sm, cax=cax, extend=extend)
        cb.set_label(label, fontsize=9)
        label_artist = cb.ax.yaxis.label
        cb.ax.tick_params(labelsize=8)
        cb.formatter.set_powerlimits((-3, 4))
        cb.update_ticks()
    else:
        cax.set_facecolor(_NAN_GREY)
        cax.set_xticks([])
        cax.set_yticks([])
        cax.yaxis.set_label_position("right")
        cax.set_ylabel(f"{label}: all NaN", fontsize=9)
        label_artist = cax.yaxis.label
    if 0 < n_nan < n:
        kax = add_axes((cb_x, bottom_pad + 0.1, cb_w, 0.16))
        kax.set_facecolor(_NAN_GREY)
        kax.set_xticks([])
        kax.set_yticks([])
        kax.text(1.6, 0.5, "NaN", transform=kax.transAxes, fontsize=8, va="center")
    if n_insig:
        gax = add_axes((cb_x, bottom_pad + 0.36, cb_w, 0.16))
        gax.set_facecolor(_NOT_SIGNIFICANT_GREY)
        gax.set_xticks([])
        gax.set_yticks([])
        gax.text(1.6, 0.5, "< 2 SE", transform=gax.transAxes, fontsize=8, va="center")

    # --- caption -------------------------------------------------------------------------
    head = title if title is not None else field
    parts = [f"{_fmt_count(n)} points"]
    if n_shown < n:
        parts = [f"showing {_fmt_count(n_shown)} of {_fmt_count(n)} points "
                 f"(uniform random subsample, seed {seed})"]
    if n == 0:
        parts = ["no points"]
    elif n_nan == n:
        parts.append(f"all {_fmt_count(n)} values are NaN (drawn grey)")
    elif n_nan:
        parts.append(f"{_fmt_count(n_nan)} NaN (grey)")
    else:
        parts.append("no NaN")
    if se is not None and n:
        parts.append(f"{_fmt_count(n_insig)} ({n_insig / n:.0%}) not significant, |value| "
                     f"< 2 SE (dark grey)")
    if n_bad_pos:
        parts.append(f"{_fmt_count(n_bad_pos)} with non-finite coordinates not drawn")
    if finite.size:
        scale = "signed, centred on 0" if is_signed else "sequential"
        parts.append(f"colour range {vmin:.3g} .. {vmax:.3g} "
                     f"(p{p_lo:g}-p{p_hi:g}, {scale})")
    fig.text(0.5, 1 - 0.18 / fig_h, head, ha="center", va="top", fontsize=12,
             fontweight="bold")
    fig.text(0.5, 1 - 0.45 / fig_h, _wrapped(parts, fig_w), ha="center", va="top",
             fontsize=9 if len(views) > 2 else 8, color="#333333")

    bbox = _fit_label(fig, placed, cax, label_artist, fig_h)
    w_px, h_px = (int(round(x * dpi)) for x in fig.get_size_inches())
    return fig, {"views": views, "up": upv, "terrain": is_terrain(pts, upv) if n else False,
                 "label_bbox": bbox, "label": label, "size": (w_px, h_px),
                 "not_significant": n_insig}


def _wrapped(parts, fig_w, chars_per_inch=15):
    """The caption's parts joined by middle dots, on two lines when one would be wider
    than the figure (about ``chars_per_inch`` characters of 9-point text an inch)."""
    line = "  \u00b7  ".join(parts)
    if len(line) <= fig_w * chars_per_inch or len(parts) < 2:
        return line
    cut = max(1, len(parts) // 2)
    return "  \u00b7  ".join(parts[:cut]) + "\n" + "  \u00b7  ".join(parts[cut:])


def _right_edge(cax, label, renderer):
    """The right edge (pixels) of the colour bar with its ticks and label."""
    return max(cax.get_tightbbox(renderer).x1, label.get_window_extent(renderer).x1)


def _fit_label(fig, placed, cax, label, fig_h, margin=0.04, max_shift=0.3):
    """Keep the colour bar's label (and its ticks) inside the figure: a label taller than
    the figure gets a smaller font, one past the right edge widens the figure (every axes
    keeps its place in inches; up to ``max_shift`` inches the colour bar moves left into the
    last panel's margin instead). Returns the label's bbox (x0, y0, x1, y1) in pixels."""
    renderer = fig.canvas.get_renderer()
    cax_x = next(r[0] for ax, r in placed if ax is cax)
    dpi = fig.dpi
    for _ in range(8):                               # height: shrink the font
        bb = label.get_window_extent(renderer)
        if bb.height <= (fig_h - 2 * margin) * dpi or label.get_fontsize() < 4:
            break
        label.set_fontsize(label.get_fontsize() * 0.85)
    right = _right_edge(cax, label, renderer) / dpi
    fig_w = fig.get_size_inches()[0]
    over = right + margin - fig_w
    if over > 0:
        # a little: move the colour bar (and its NaN key) left into the last panel's margin;
        # more: widen the figure, every axes keeping its place in inches
        shift = over if over <= max_shift else 0.0
        if shift == 0.0:
            fig_w = right + margin
            fig.set_size_inches(fig_w, fig_h)
        for ax, (x, y, w, h) in placed:
            x = x - shift if x >= cax_x - 1e-9 else x
            ax.set_position((x / fig_w, y / fig_h, w / fig_w, h / fig_h))
    renderer = fig.canvas.get_renderer()
    _right_edge(cax, label, renderer)                # places the label beside the ticks
    bb = label.get_window_extent(renderer)
    return (float(bb.x0), float(bb.y0), float(bb.x1), float(bb.y1))
