"""The arguments that :func:`clcurv.curvature`, :func:`clcurv.normals`,
:func:`clcurv.features` and the command line (:mod:`clcurv.cli.main`) share, checked once
here: the points (or a DeviceCloud), a radius list, ``radius="knn:K"``, ``orient`` and
``method`` (the allowed values of the options' declaration, :mod:`clcurv._shared.options`,
with the registry's methods: :func:`allowed`)."""
from __future__ import annotations

import numpy as np

from clcurv._shared.options import METHODS_OF_REGISTRY, choices
from clcurv._shared.validate import as_radius, choice
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.registry import METHODS

#: the allowed ``orient`` values (or a direction, 3 floats): the options' declaration
ORIENTS = choices("orient")


def allowed(name):
    """The allowed values of compute option ``name`` (:data:`clcurv._shared.options.OPTIONS`),
    the registry's methods for ``method``."""
    found = choices(name)
    return METHODS if found == METHODS_OF_REGISTRY else found


def check_method(method):
    """``method`` if it is one of the registry's methods, else ValueError."""
    return choice(method, "method", allowed("method"))


def cloud_points(points):
    """(points, DeviceCloud or None): a DeviceCloud is accepted for its points and binning."""
    if isinstance(points, DeviceCloud):
        return points.points, points
    return points, None


def as_radii(radius):
    """(list of float radii, multi) from a number or a sequence of numbers."""
    if np.ndim(radius) == 0:
        return [as_radius(radius)], False
    radii = [as_radius(r) for r in np.asarray(radius, dtype=object).reshape(-1)]
    if not radii:
        raise ValueError("radius must be a number or a non-empty list of numbers")
    if len(set(radii)) != len(radii):
        raise ValueError(f"radius lists must not repeat a radius, got {radius!r}")
    return radii, True


def parse_knn(spec, k):
    """K of ``radius="knn:K"`` (``spec``), refused with ``k`` given too."""
    if not spec.startswith("knn:"):
        raise TypeError(f"radius must be a number (or a list of numbers, or 'knn:K'), got "
                        f"{spec!r}")
    if k is not None:
        raise ValueError("give either radius='knn:K' or k=, not both")
    try:
        return int(spec[4:])
    except ValueError:
        raise ValueError(f"radius='knn:K' needs an integer K, got {spec!r}") from None


def orient_spec(orient):
    """``orient`` checked: one of :data:`ORIENTS`, or a direction as a unit float64 (3,)
    array ("up" is (0, 0, 1))."""
    if orient is None or isinstance(orient, str):
        choice(orient, "orient", ORIENTS)
        return np.array([0.0, 0.0, 1.0]) if orient == "up" else orient
    d = np.asarray(orient, dtype=np.float64).reshape(-1)
    if d.shape != (3,) or not np.isfinite(d).all() or not np.any(d):
        raise ValueError(f"orient must be one of {', '.join(map(repr, ORIENTS))} or a "
                         f"nonzero direction of 3 finite numbers, got {orient!r}")
    return d / np.linalg.norm(d)
