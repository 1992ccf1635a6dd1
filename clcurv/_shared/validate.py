"""Checks at the API boundary: clear errors instead of crashes in a kernel."""
from __future__ import annotations

import math

import numpy as np


def as_points(points, name="points", finite=True):
    """Return ``points`` as a C-contiguous float64 (N, 3) array, or raise.

    Raises TypeError for non-real dtypes and ValueError for a wrong shape or non-finite
    coordinates (the message gives how many rows are bad and the first of them). With
    ``finite=False`` the caller checks finiteness itself (the binning's bounding box,
    :func:`check_finite_box`), saving a pass over the points.
    """
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not finite or np.isfinite(arr).all():      # fast path: one pass, no per-row mask
        return arr
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} has {int(bad.sum())} row(s) with NaN or Inf "
                         f"(first at index {first}); drop them first, e.g. "
                         f"{name}[np.isfinite({name}).all(axis=1)]")
    return arr


def check_finite_box(points, lo, hi, name="points"):
    """Raise as :func:`as_points` does when the per-column minima ``lo`` and maxima ``hi``
    of ``points`` are not all finite (a NaN or an infinity among the points)."""
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        as_points(points, name)
        raise ValueError(f"{name} has NaN or Inf")      # (as_points raised already)


def as_number(value, name, convert, kind):
    """``convert(value)`` (float or int), or TypeError naming ``name`` and the ``kind`` it
    must be; a bool is refused: ``radius=True`` is a slip, not 1.0."""
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be {kind}, got {value!r}")
    try:
        return convert(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be {kind}, got {value!r}") from None


def as_radius(radius):
    """Return ``radius`` as a positive finite float, or raise ValueError (TypeError for a
    value that is not a number, a bool among them: ``radius=True`` is a slip, not 1.0)."""
    r = as_number(radius, "radius", float, "a number")
    if not math.isfinite(r) or r <= 0:
        raise ValueError(f"radius must be a positive finite number, got {radius!r}")
    return r


def as_normals(normals, n, unit=True):
    """Float64 (n, 3) normals from user input; zero or non-finite rows raise ValueError.

    With ``unit=False`` (the caller only uses their direction's sign) rows are left at
    their length unless a length is outside [1e-15, 1e15], where the whole array is
    normalised so that a cast to float32 cannot overflow or underflow.
    """
    arr = as_points(normals, "normals")
    if len(arr) != n:
        raise ValueError(f"normals must have one row per point: {len(arr)} rows for {n} points")
    if not n:
        return arr
    norm = np.sqrt(np.einsum("ij,ij->i", arr, arr))
    lo, hi = norm.min(), norm.max()
    if not lo > 0:
        raise ValueError(f"normals has {int((norm <= 0).sum())} zero-length row(s)")
    if unit or lo < 1e-15 or hi > 1e15:
        arr = arr * (1.0 / norm)[:, None]
    return arr


def as_viewpoint(viewpoint):
    vp = np.asarray(viewpoint, dtype=np.float64).reshape(-1)
    if vp.shape != (3,) or not np.isfinite(vp).all():
        raise ValueError(f"viewpoint must be 3 finite numbers, got {viewpoint!r}")
    return vp


def choice(value, name, allowed):
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value


#: Radii (points' unit) the kernels compute with, per device precision. Inside, every
#: operator's outputs scale with the cloud bit for bit under power-of-two scalings
#: (tests/test_hostile_api.py), so no intermediate over- or underflows; outside, some do
#: (2dcov1's 256 / r^6 in float32 beyond about 2^20), and the call is refused.
DEVICE_RADIUS_RANGE = {"float": (2.0 ** -20, 2.0 ** 26), "double": (2.0 ** -140, 2.0 ** 140)}


def device_radius(radius, precision):
    """``radius`` (a checked float) if the kernels of ``precision`` represent it, else a
    ValueError naming the range and what to do."""
    lo, hi = DEVICE_RADIUS_RANGE[choice(precision, "precision", tuple(DEVICE_RADIUS_RANGE))]
    if lo <= radius <= hi:
        return radius
    raise ValueError(f"radius {radius:.6g} is outside [{lo:.3g}, {hi:.3g}], the radii that "
                     f"precision={precision!r} kernels compute with in the points' unit: "
                     f"express the points in another unit (e.g. mm instead of m)"
                     + (" or double precision" if precision == "float" else ""))


def as_count(value, name, most):
    """``value`` as an int in [1, most], or TypeError / ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if not 1 <= value <= most:
        raise ValueError(f"{name} must be in [1, {most}], got {value}")
    return int(value)
