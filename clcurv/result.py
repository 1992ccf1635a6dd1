"""The result object returned by :func:`clcurv.curvature`."""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

# Per-point status codes (mirrored in kernels/common.h).
OK = 0
TOO_FEW = 1        # fewer neighbours than the operator needs (3 for PCA, 6 for MLS2)
DEGENERATE = 2     # covariance of rank < 2: collinear or coincident neighbours
SINGULAR = 3       # a least-squares system could not be solved
STATUS_NAMES = {OK: "ok", TOO_FEW: "too few neighbours", DEGENERATE: "degenerate neighbourhood",
                SINGULAR: "singular fit"}


@dataclass
class CurvatureResult:
    """Per-point outputs of one operator, in the input's point order.

    Conventions: normals are unit vectors oriented outward (away from the solid) when an
    orientation was requested; a surface bending away from its normal has positive
    curvature (a sphere of radius R has H = 1/R). Lengths are in the points' unit, so
    curvatures are in 1/length. Points whose ``status`` is not 0 hold NaN in every
    floating-point output.

    Attributes
    ----------
    method, radius, weights : the call's parameters.
    count : (N,) int64, #N_r(p), the point itself included.
    status : (N,) uint8, 0 ok, 1 too few neighbours, 2 degenerate, 3 singular fit.
    normals : (N, 3) float64 unit PCA normals (or fitted normals for MLS2).
    eigenvalues : (N, 3) float64, ascending, of the weighted covariance of N_r(p)
        (area^2 units, count-normalised).
    variation : (N,) float64, surface variation l0 / (l0 + l1 + l2), in [0, 1/3].
    mean : (N,) float64 or None, signed mean curvature H (1/length).
    points : (N, 3) float64 or None, the projected positions (MLS0 barycenter, MLS1 point
        projected on the regression plane, MLS2 projection).
    k1, k2 : (N,) float64 or None, principal curvatures, k1 >= k2 (1/length): signed for
        MLS2, magnitudes (>= 0) for 2dcov1, 2dcov2 and 3dcov.
    dir1, dir2 : (N, 3) float64 or None, unit principal directions (tangent, orthogonal).
    gaussian : (N,) float64 or None, Gaussian curvature K = k1 k2 (1/length^2), MLS2.

    For the covariance methods ``eigenvalues`` are those of the operator's covariance
    (descending, count-normalised); for the PCA methods those of the PCA covariance
    (ascending); MLS2 has none. ``variation`` is given by the PCA methods only.
    """
    method: str
    radius: float
    weights: str
    count: np.ndarray
    status: np.ndarray
    normals: np.ndarray
    eigenvalues: np.ndarray | None
    variation: np.ndarray | None
    mean: np.ndarray | None = None
    points: np.ndarray | None = None
    k1: np.ndarray | None = None
    k2: np.ndarray | None = None
    dir1: np.ndarray | None = None
    dir2: np.ndarray | None = None
    gaussian: np.ndarray | None = None
    info: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self):
        return len(self.count)

    @property
    def valid(self):
        """Boolean mask of the points whose status is 0."""
        return self.status == OK

    def arrays(self):
        """The per-point arrays that are present, by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)}
