"""Constants shared by the host and the OpenCL kernels, defined once here.

Every program is built with :func:`kernel_defines` as ``-D`` options (clcurv.runtime.program), and
``kernels/common.h`` refuses to compile without them, so the kernels never carry a copy.
The per-operator record layouts and minimum neighbour counts live in the operator
registry (:mod:`clcurv.ops.registry`) and reach their kernel the same way.
"""
from __future__ import annotations

#: Zero padding (elements) after every per-point device array: the widest vector load
#: (16 lanes) may read past the last point.
PAD = 16
#: REALs per point of an operator kernel's output record (one 64-byte line in float32).
RECORD_WIDTH = 16
#: ``cell_of`` = alignment << CELL_BITS | occupied-cell id (clcurv.grid.binning, kernels/neighbors.h).
CELL_BITS = 30
CELL_MASK = (1 << CELL_BITS) - 1

# Per-point status codes of every operator (and of the reference).
OK = 0
TOO_FEW = 1        # fewer neighbours than the operator needs (MIN_COUNT_*)
DEGENERATE = 2     # covariance of rank < 2: collinear or coincident neighbours
SINGULAR = 3       # a least-squares system could not be solved

#: Minimum neighbour count (point included) of a PCA (3 points span a plane).
MIN_COUNT_PCA = 3
#: Minimum neighbour count of the 6-coefficient MLS2 quadric fit.
MIN_COUNT_MLS2 = 6


def record_selector(columns):
    """The REAL16 component selector of record ``columns`` (an int or a slice), the form in
    which a record layout reaches a kernel: 10 -> 'sa', slice(0, 3) -> 's012'."""
    cols = [columns] if isinstance(columns, int) else range(columns.start, columns.stop)
    if not cols or min(cols) < 0 or max(cols) >= RECORD_WIDTH or len(cols) not in (1, 2, 3, 4):
        raise ValueError(f"record columns {columns!r} do not fit a {RECORD_WIDTH}-wide record")
    return "s" + "".join(f"{c:x}" for c in cols)


def kernel_defines():
    """The constants above as ``-D`` build options (name -> value)."""
    return {"PAD": PAD, "RECORD_WIDTH": RECORD_WIDTH, "CELL_BITS": CELL_BITS,
            "CELL_MASK": f"{CELL_MASK:#x}u", "ST_OK": OK, "ST_TOO_FEW": TOO_FEW,
            "ST_DEGENERATE": DEGENERATE, "ST_SINGULAR": SINGULAR,
            "MIN_COUNT_PCA": MIN_COUNT_PCA, "MIN_COUNT_MLS2": MIN_COUNT_MLS2}
