"""The result object returned by :func:`clcurv.curvature`, and what the results of
:func:`clcurv.curvature`, :func:`clcurv.normals` and :func:`clcurv.features` share: the
warning of sparse balls, the columns of an empty cloud."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields

import numpy as np

from clcurv._shared.constants import DEGENERATE, OK, SINGULAR, TOO_FEW   # noqa: F401 (the status codes)


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
    normals : (N, 3) float64 unit normals: the PCA normals ('variation', 'mls0', 'mls1'),
        the normals the operator used (covariance methods), the fitted normals (MLS2).
    eigenvalues : float64 or None, per method (clcurv.ops.registry lists them):
        'variation', 'mls0', 'mls1': (N, 3), ascending l0 <= l1 <= l2, of the weighted PCA
        covariance sum w (q - o)(q - o)^T / sum w (length^2);
        '2dcov1': (N, 2), descending, of the count-normalised covariance of
        <d, n>(<d, t1>, <d, t2>) (length^4); '2dcov2': (N, 2), descending, of the tangent
        projections of the neighbours' unit normals (unitless); '3dcov': (N, 3),
        descending, of the neighbours' unit normals (unitless); 'mls2': None.
    variation : (N,) float64 or None, surface variation l0 / (l0 + l1 + l2), in [0, 1/3]
        (the PCA methods).
    mean : (N,) float64 or None, signed mean curvature H (1/length).
    points : (N, 3) float64 or None, the projected positions (MLS0 barycenter, MLS1 point
        projected on the regression plane, MLS2 projection).
    k1, k2 : (N,) float64 or None, principal curvatures, k1 >= k2 (1/length): signed for
        MLS2, magnitudes (>= 0) for 2dcov1, 2dcov2 and 3dcov.
    dir1, dir2 : (N, 3) float64 or None, unit principal directions (tangent, orthogonal).
    gaussian : (N,) float64 or None, Gaussian curvature K = k1 k2 (1/length^2), MLS2.
    mean_se, gaussian_se, k1_se, k2_se : (N,) float64 or None, ``uncertainty=True``: the
        standard errors of ``mean`` (mls0, mls1, mls2), ``gaussian``, ``k1`` and ``k2``
        (mls2), same units; noise only, the operator's bias not included
        (docs/uncertainty.md).
    normal_se : (N,) float64 or None, ``uncertainty=True``: the angular standard error
        (radians, RMS angle) of ``normals`` (PCA or MLS2's fitted normals).
    roughness : (N,) float64 or None, ``uncertainty=True``: the residual RMS (length) to
        the fitted quadric (mls2) or regression plane (the PCA methods).
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
    mean_se: np.ndarray | None = None
    gaussian_se: np.ndarray | None = None
    k1_se: np.ndarray | None = None
    k2_se: np.ndarray | None = None
    normal_se: np.ndarray | None = None
    roughness: np.ndarray | None = None
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


def warn_sparse(status, radius, need, k=None, what="outputs"):
    """RuntimeWarning when most points have fewer than ``need`` neighbours (``status``
    TOO_FEW) within ``radius`` (a number; an array: each point's own radius) or the k-NN
    radius of ``k``; ``what``: the results that are then NaN. The warning names the caller
    of this function's caller (the user's call of a public function)."""
    few = int(np.count_nonzero(status == TOO_FEW))
    if few > len(status) // 2:
        where = (f"radius {radius}: their {what} are NaN; the radius is probably too small"
                 if np.ndim(radius) == 0 else
                 f"their own radius (per point): their {what} are NaN" if k is None else
                 f"their k-NN radius (k = {k}): their {what} are NaN; k must be at least "
                 f"{need}")
        warnings.warn(f"{few} of {len(status)} points have fewer than {need} neighbours within "
                      f"{where}", RuntimeWarning, stacklevel=3)


def empty_columns(widths):
    """{name: empty float64 array} for (name, width) pairs: (0,) for width 1, else
    (0, width): the values of a result of no points."""
    return {name: np.empty((0,) if width == 1 else (0, width)) for name, width in widths}
