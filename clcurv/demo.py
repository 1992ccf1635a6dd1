"""The bundled sample: the Stanford bunny (35,947 points, binary PLY, metres).

``python -m clcurv.demo`` is the same as ``clcurv demo``: it runs the paper's pipeline (MLS1
scale space, then MLS2) on the bunny, writes a PLY with the fields and a PNG, and prints a
summary.
"""
from __future__ import annotations

import sys
from importlib import resources
from pathlib import Path


def sample_path() -> Path:
    """Path of the bundled sample (Stanford bunny ``bun_zipper`` vertices, binary PLY)."""
    return Path(str(resources.files("clcurv.data") / "bunny.ply"))


def load_sample():
    """The bundled sample's points, (N, 3) float64."""
    from .io import read
    return read(sample_path()).points


def main(argv=None):
    from .cli import main as cli_main
    return cli_main(["demo", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
