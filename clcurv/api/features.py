"""Covariance ("dimensionality") features of the balls N_r(p): :func:`features`.

The eigenvalue features that LiDAR classification and segmentation compute next to normals
and curvature (jakteristics ``compute_features``, PDAL ``filters.covariancefeatures``,
CloudCompare's geometric features), on the device (``kernels/features.cl``, a sibling of
the moments kernel sharing its PCA), at one radius, several radii in one neighbour walk, or
a per-point k-nearest-neighbour radius.

Eigenvalues and normalisation
-----------------------------
l1 >= l2 >= l3 (length^2) are the eigenvalues of the covariance of the ball,
``sum (q - o)(q - o)^T / (n - ddof)`` with o the ball's barycentre and n its point count
(the point included). ``ddof=0`` (default) is clcurv's count normalisation (the PCA
eigenvalues of :func:`clcurv.curvature`, ascending there); ``ddof=1`` is the sample
covariance that jakteristics (``1 / (n - 1)``) computes. The ratios (anisotropy,
planarity, linearity, PCA1, PCA2, surface_variation, sphericity, the verticalities) do not
depend on ``ddof``; eigenvalue_sum, omnivariance, the eigenvalues and eigenentropy do.

The eigenvalues are **not** normalised by their sum in any feature below except where the
formula says ``/ sum``: jakteristics 0.6 computes eigenentropy and omnivariance from the
raw eigenvalues (its PCA1, PCA2 and surface_variation are the sum-normalised eigenvalues
l_i / sum, which are the "normalised eigenvalues" here too).

PDAL (``filters.covariancefeatures``; 2.3.0 checked by tests/test_pdal.py) divides the
covariance by n - 1 as jakteristics does: its EigenvalueSum, Omnivariance and
Eigenentropy are ``ddof=1``'s. It differs by its ``mode``: by default (``mode="SQRT"``)
it takes the square roots sqrt(l_i) (standard deviations) in Linearity, Planarity,
Scattering, Omnivariance, Eigenentropy, Anisotropy and Verticality; ``mode="Normalized"``
divides them by their sum; ``mode="Raw"`` uses them as they are. In every mode its
EigenvalueSum is the raw sum, and its SurfaceVariation is the transformed l3 over the raw
sum (sqrt(l3) / (l1 + l2 + l3) by default). The PDAL spellings accepted here give PDAL's
``mode="Raw"`` values with ``ddof=1`` (for a sqrt-mode value take e.g. sqrt of
``sphericity`` for Scattering). PDAL rounds the centred offsets to float32 before it sums
their products, so its eigenvalues carry an absolute error of ~2^-24 l1 (on the Autzen
tile its linearity of flat ground, where l1 ~ l2, is up to 1.1e-7 off). PDAL's Density, (k + 1) / ((4 / 3) pi r^3) of its optimal
neighbourhood, evaluates (4 / 3) in integers (= 1) in some versions; ``density`` here is
n / (4/3 pi r^3).

CloudCompare (CCCoreLib ``Neighbourhood::computeFeature``, its "Compute geometric
features") divides the covariance by n (``ddof=0``, the default here) and uses the raw
eigenvalues in every formula above, so its features are those of a default call; its
names ("Eigenvalues sum", "Surface variation", "1st eigenvalue", ...) are accepted, and its
curvature "Normal change rate" is ``surface_variation``. Its "Verticality", 1 - |e3_z|, is
``verticality`` here: the exact spelling ``Verticality`` is PDAL's (Guinard's).

Degenerate neighbourhoods follow clcurv's status policy: fewer than 3 points (status 1) or
a covariance of rank < 2 (collinear or coincident points, status 2) give NaN in every
feature. 0 ln 0 is taken as 0 in eigenentropy (a planar ball, l3 = 0, is defined).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from clcurv._shared.constants import MIN_COUNT_PCA, TOO_FEW
from clcurv._shared.options import check
from clcurv._shared.validate import as_points
from clcurv.api.inputs import as_radii, cloud_points, orient_spec, parse_knn
from clcurv.api.result import empty_columns, warn_sparse
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops import optimal as opt
from clcurv.ops.features import FEATURES, run_features
from clcurv.ops.knn_radius import check_k, knn_radii
from clcurv.reference import features as ref

__all__ = ["features", "FeatureResult", "FEATURES", "DEFAULT_FEATURES", "canonical_names"]


#: jakteristics' per-component names of the normals
_NORMAL_PARTS = {"nx": 0, "ny": 1, "nz": 2}
#: the count is always returned (``FeatureResult.count``); these names ask for it too
_COUNT_NAMES = ("number_of_neighbors", "neighbours", "count")

#: what :func:`features` computes by default: jakteristics' feature list
DEFAULT_FEATURES = ("eigenvalue_sum", "omnivariance", "eigenentropy", "anisotropy",
                    "planarity", "linearity", "PCA1", "PCA2", "surface_variation",
                    "sphericity", "verticality", "normals")

_ALIASES = {a: f.name for f in FEATURES.values() for a in (f.name,) + f.aliases}


def _name_list(names):
    """``names`` (a comma-separated string or a sequence of strings) as a list of strings."""
    if isinstance(names, str):
        return [n.strip() for n in names.split(",") if n.strip()]
    try:
        names = list(names)
    except TypeError:
        raise TypeError(f"features must be a name, a sequence of names or 'all', got "
                        f"{names!r}") from None
    for n in names:
        if not isinstance(n, str):
            raise TypeError(f"feature names must be strings, got {n!r}")
    return names


def canonical_names(names):
    """The canonical feature names of ``names`` (canonical, jakteristics, PDAL or
    CloudCompare spellings; ``nx``/``ny``/``nz`` ask for ``normals``;
    ``number_of_neighbors`` is always returned as ``count``), without repeats, in the order
    given. "all" asks for every feature.

    Exact spellings first (PDAL's ``Verticality`` is not jakteristics' ``verticality``,
    which is CloudCompare's Verticality: ask for that one as ``verticality``), then a
    case-insensitive match when it is unique. Unknown names raise ValueError.
    """
    names = _name_list(names)
    out = []
    lower = {}
    for a, c in _ALIASES.items():
        lower.setdefault(a.lower(), set()).add(c)
    for n in names:
        if n == "all":
            out.extend(FEATURES)
            continue
        if n in _COUNT_NAMES:
            continue
        c = "normals" if n in _NORMAL_PARTS else _ALIASES.get(n)
        if c is None:
            hits = lower.get(n.lower(), set())
            if len(hits) != 1:
                raise ValueError(f"unknown feature {n!r}; known: {', '.join(FEATURES)} (and "
                                 "their jakteristics/PDAL spellings, e.g. 'Scattering', "
                                 "'DemantkeVerticality'), or 'all'")
            c = next(iter(hits))
        out.append(c)
    return tuple(dict.fromkeys(out))


@dataclass
class FeatureResult:
    """The features of one radius (or of the per-point k-NN radii), input order.

    ``values`` maps each canonical feature name to a float64 (N,) array ((N, 3) for
    ``normals``); ``count`` (int64) is the number of points in each ball (the point
    included; jakteristics' number_of_neighbors), ``status`` (uint8) clcurv's status (0 ok,
    1 too few, 2 degenerate); NaN wherever the status is not 0. ``radius`` is the ball
    radius, or with ``k=`` the (N,) per-point radii (NaN for isolated points). ``result[name]``
    accepts any spelling of :func:`canonical_names` and nx, ny, nz.
    """
    radius: float | np.ndarray
    values: dict
    count: np.ndarray
    status: np.ndarray
    ddof: int = 0
    info: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def names(self):
        return tuple(self.values)

    def __len__(self):
        return len(self.count)

    def __getitem__(self, name):
        if name in _NORMAL_PARTS:
            return self.values["normals"][:, _NORMAL_PARTS[name]]
        if name in _COUNT_NAMES:
            return self.count
        return self.values[canonical_names([name])[0]]

    def _columns(self, names):
        """[(label, (N,) array)] of ``names`` (any spelling; normals as nx, ny, nz;
        number_of_neighbors the count, as float64)."""
        cols = []
        for n in list(self.names) if names is None else _name_list(names):
            if n in _COUNT_NAMES:
                cols.append(("number_of_neighbors", self.count.astype(np.float64)))
                continue
            c = "normals" if n in _NORMAL_PARTS else canonical_names([n])[0]
            if c not in self.values:
                raise KeyError(f"{n!r} ({c}) was not computed; this result holds "
                               f"{', '.join(self.names)}")
            parts = [n] if n in _NORMAL_PARTS else ["nx", "ny", "nz"] if c == "normals" else [c]
            cols.extend((part, self[part]) for part in parts)
        return cols

    def columns(self, names=None):
        """The column labels of :meth:`to_array` for ``names``."""
        return [label for label, _ in self._columns(names)]

    def to_array(self, names=None):
        """The features as one (N, F) float64 array, a column per feature in the order of
        ``names`` (any spelling of :func:`canonical_names`, or a comma-separated string;
        ``normals`` gives nx, ny, nz; ``number_of_neighbors`` the count), as jakteristics'
        ``compute_features`` returns them; default every feature held, in :attr:`names`
        order. :meth:`columns` gives the labels. NaN where the status is not 0."""
        cols = self._columns(names)
        out = np.empty((len(self), len(cols)), np.float64)
        for j, (_, v) in enumerate(cols):
            out[:, j] = v
        return out

    def file_fields(self, suffix=""):
        """Per-point scalar fields for a file: every feature (normals as nx, ny, nz), then
        number_of_neighbors and feature_status, each name followed by ``suffix`` (the
        multi-radius calls use ``_r<radius>``)."""
        out = {}
        for k, v in self.values.items():
            if v.ndim == 2:
                for c, a in enumerate("xyz"):
                    out[f"n{a}{suffix}"] = v[:, c]
            else:
                out[f"{k}{suffix}"] = v
        out[f"number_of_neighbors{suffix}"] = self.count.astype(np.float64)
        out[f"feature_status{suffix}"] = self.status.astype(np.float64)
        return out


def radius_suffix(r):
    """The field-name suffix of radius ``r`` in files: ``_r0.5``, ``_r2``, ``_r300.0001``:
    the shortest positional digits that give ``r`` back, so distinct radii never share a
    name (``%g``'s six digits made 300 and 300.0001 one field, and 1e6 a name with '+')."""
    return "_r" + np.format_float_positional(float(r), trim="-")


def features(points, radius=None, features=DEFAULT_FEATURES, *, k=None, ddof=0, orient=None,
             optimal=False, device=None, precision="float", backend="opencl"):
    """Covariance features of the ball N_r(p) = {q : |q - p| < r} of every point.

    Parameters
    ----------
    points : (N, 3) array_like of real numbers, or a DeviceCloud (cell >= every radius)
    radius : float, sequence of floats, or "knn:K"
        Ball radius in the points' unit. A sequence computes every radius in one neighbour
        walk (the cloud is binned at the largest) and returns one result per radius; each
        is bit-identical to a single-radius call on the same DeviceCloud. ``"knn:K"`` is
        ``k=K``.
    features : sequence of str, str or None
        Feature names (:data:`FEATURES`; jakteristics and PDAL spellings accepted, see
        :func:`canonical_names`; "all"). Default (or None) :data:`DEFAULT_FEATURES`.
    k : int, optional
        Adaptive radius: each point's ball radius is the distance to its k-th nearest point
        (the point itself the first), found on the device with the grid
        (:mod:`clcurv.ops.knn_radius`); the ball then holds k points (more on ties). PDAL's
        ``knn=k - 1`` (the point and its k - 1 nearest) is the same neighbourhood.
    ddof : {0, 1}
        The covariance is divided by n - ddof: 0 clcurv's count normalisation, 1 the sample
        covariance of jakteristics.
    orient : None, 'up' or 3 floats
        Orientation of ``normals``: None keeps the PCA sign (arbitrary, as jakteristics);
        'up' or a direction turns them to a positive dot product with it.
    optimal : bool
        With a list of at least two radii: each point's features at the one radius, among
        them, whose ball has the least eigenentropy of its sum-normalised eigenvalues (the
        optimal neighbourhood of Weinmann et al. 2015 and PDAL's
        ``filters.optimalneighborhood``, over radii; :mod:`clcurv.ops.optimal`). One result,
        whose ``radius`` is each point's chosen radius.
    device, precision, backend
        As :func:`clcurv.curvature`; ``backend='numpy'`` runs the float64 reference
        (:mod:`clcurv.reference.features`).

    Returns
    -------
    FeatureResult, or a list of them (one per radius, in the order given) for a sequence
    (one, per-point radii, with ``optimal=True``).

    Examples
    --------
    >>> import numpy as np, clcurv
    >>> p = clcurv.shapes.sphere(20000, 2.0)["points"]
    >>> f = clcurv.features(p, 0.3, ["planarity", "Scattering"])
    >>> bool(np.nanmedian(f["planarity"]) > 0.9)
    True
    """
    check(backend, "backend")
    check(ddof, "ddof")
    names = canonical_names(DEFAULT_FEATURES if features is None else features)
    if not names:
        raise ValueError("features must name at least one feature")
    up = None if orient is None else orient_spec(orient)
    if isinstance(up, str):
        raise ValueError(f"orient must be None, 'up' or a direction, got {orient!r}")
    points, cloud = cloud_points(points)
    # finiteness: the OpenCL path checks it on the binning's bounding box (one pass fewer)
    pts = as_points(points, finite=backend != "opencl")
    if isinstance(radius, str):
        k = parse_knn(radius, k)
        radius = None
    if k is not None:
        if radius is not None:
            raise ValueError("give either radius or k (or radius='knn:K'), not both")
        if optimal:
            raise ValueError("optimal=True chooses among a list of radii, not with k")
        res = _finish(_knn_features(pts, k, names, ddof, device, precision, backend, up),
                      up, backend)
        warn_sparse(res.status, res.radius, MIN_COUNT_PCA, k, "features")
        return res
    if radius is None:
        raise ValueError("features needs radius= (a number, a list of numbers or 'knn:K') "
                         "or k=")
    radii, multi = as_radii(radius)
    if optimal:
        if not multi or len(radii) < 2:
            raise ValueError("optimal=True needs a list of at least two radii to choose from, "
                             f"got radius={radius!r}")
        res = _optimal_features(pts, cloud, sorted(radii), names, ddof, device, precision,
                                backend, up)
        warn_sparse(res.status, res.radius, MIN_COUNT_PCA, None, "features")
        return _finish(res, up, backend)
    if len(pts) == 0:
        out = [empty_features(names, r, ddof) for r in radii]
    elif backend == "numpy":
        out = [FeatureResult(r, *ref.features(pts, r, names, ddof=ddof, up=up), ddof=ddof)
               for r in radii]
    else:
        if cloud is None:
            cloud = DeviceCloud(pts, max(radii), device=device, precision=precision)
        for r in radii:
            cloud.check_radius(r)
        out = [FeatureResult(r, v, c, s, ddof=ddof)
               for r, (v, c, s) in zip(radii, run_features(cloud, radii, names, ddof))]
    out = [_finish(f, up, backend) for f in out]
    for f in out:
        warn_sparse(f.status, f.radius, MIN_COUNT_PCA, None, "features")
    return out if multi else out[0]


def _knn_features(pts, k, names, ddof, device, precision, backend, up):
    if len(pts) == 0:
        return empty_features(names, np.empty(0), ddof)
    check_k(k, len(pts))
    if backend == "numpy":
        r = ref.knn_radii(pts, k)        # the closed ball of radius d_k: k points
        return FeatureResult(r, *ref.features(pts, r * (1 + 1e-12), names, ddof=ddof, up=up),
                             ddof=ddof, info={"k": k})
    radii = knn_radii(pts, k, device=device, precision=precision)
    vals, count, status = run_features(radii.cloud, [radii.cloud.cell], names, ddof,
                                       point_r2=radii.r2_sorted)[0]
    status = np.where(radii.isolated, np.uint8(TOO_FEW), status)
    return FeatureResult(radii.radius, vals, count, status, ddof=ddof,
                         info={"k": k, "timings": radii.timings})


def _optimal_features(pts, cloud, radii, names, ddof, device, precision, backend, up):
    """The FeatureResult of features(optimal=True) (clcurv.ops.optimal) for sorted ``radii``."""
    if len(pts) == 0:
        res = empty_features(names, np.empty(0), ddof)
        res.info.update(radii=radii, optimal_index=np.empty(0, np.intp))
        return res
    if backend == "numpy":
        vals, count, status, radius, idx = opt.reference_optimal_features(pts, radii, names,
                                                                          ddof, up)
    else:
        if cloud is None:
            cloud = DeviceCloud(pts, radii[-1], device=device, precision=precision)
        for r in radii:
            cloud.check_radius(r)
        vals, count, status, radius, idx = opt.optimal_features(cloud, radii, names, ddof)
    return FeatureResult(radius, vals, count, status, ddof=ddof,
                         info={"radii": radii, "optimal_index": idx})


def _finish(res, up, backend):
    """Normals turned towards ``up`` (a unit direction) when asked; the float64 reference
    (backend "numpy") turns its own (clcurv.reference.features), so that this step is
    tested against it, not shared with it."""
    if up is not None and backend != "numpy" and "normals" in res.values:
        n = res.values["normals"]
        n[(n @ up) < 0] *= -1
    return res


def empty_features(names, radius, ddof):
    """The FeatureResult of ``names`` for no points."""
    vals = empty_columns((n, FEATURES[n].width) for n in names)
    return FeatureResult(radius, vals, np.empty(0, np.int64), np.empty(0, np.uint8), ddof)
