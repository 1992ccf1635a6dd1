"""Bundled sample data.

``bunny.ply``: the Stanford bunny (``bun_zipper.ply`` vertices, Stanford 3D Scanning
Repository), 35,947 points, binary little-endian PLY with float32 ``x y z`` only (no
normals, no faces). Coordinates are in metres, y up; the bunny is about 0.16 m wide, so
its curvatures are in 1/m (of order 10 to 100 on the body).
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["sample_path", "SAMPLE_POINTS"]

#: number of points of the bundled sample
SAMPLE_POINTS = 35_947


def sample_path() -> Path:
    """Path of the bundled sample ``bunny.ply`` (read it with :func:`clcurv.io.read`)."""
    return Path(str(resources.files(__name__) / "bunny.ply"))
