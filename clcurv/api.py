"""Public entry points: :func:`curvature` and :func:`normals` (numpy in, numpy out)."""
from __future__ import annotations

import warnings

import numpy as np

from . import orient as _orient
from .result import CurvatureResult, OK, TOO_FEW
from .validate import as_normals, as_points, as_radius, as_viewpoint, choice

MOMENT_METHODS = ("variation", "mls0", "mls1")
METHODS = MOMENT_METHODS
ORIENTS = ("auto", "mst", "viewpoint", "normals", None)


def _raw_moments(points, radius, weights, backend, device, precision, refine):
    if backend == "numpy":
        from .reference import moments
        return moments(points, radius, weights=weights)
    from .cloud import DeviceCloud
    from .moments import device_moments
    cloud = DeviceCloud(points, radius, device=device, precision=precision)
    return device_moments(cloud, radius, weights=weights, refine=refine)


def _empty(method, radius, weights):
    z3 = np.empty((0, 3))
    return CurvatureResult(method, radius, weights, np.empty(0, np.int64), np.empty(0, np.uint8),
                           z3, z3.copy(), np.empty(0), np.empty(0) if method != "variation" else None,
                           z3.copy() if method in ("mls0", "mls1") else None)


def _orientation(orient, normals, viewpoint):
    if orient == "auto":
        return "normals" if normals is not None else "viewpoint" if viewpoint is not None else "mst"
    if orient == "normals" and normals is None:
        raise ValueError("orient='normals' needs normals=")
    if orient == "viewpoint" and viewpoint is None:
        raise ValueError("orient='viewpoint' needs viewpoint=")
    return orient


def _flip(points, n, how, normals, viewpoint, k):
    if how == "normals":
        return _orient.flip_to_reference(n, normals)
    if how == "viewpoint":
        return _orient.flip_to_viewpoint(points, n, viewpoint)
    if how == "mst":
        return _orient.flip_by_propagation(points, n, k=k)
    return np.zeros(len(n), dtype=bool)


def _warn_sparse(status, radius):
    few = np.count_nonzero(status == TOO_FEW)
    if few > len(status) // 2:
        warnings.warn(f"{few} of {len(status)} points have fewer than 3 neighbours within "
                      f"radius {radius}: their outputs are NaN; the radius is probably too small",
                      RuntimeWarning, stacklevel=3)


def curvature(points, radius, *, method="mls1", weights="uniform", normals=None, orient="auto",
              viewpoint=None, orient_k=10, device=None, precision="float", backend="opencl"):
    """Differential operators on the ball N_r(p) = {q : |q - p| < radius} of every point.

    Parameters
    ----------
    points : (N, 3) array_like of real numbers
        The raw cloud. Any finite coordinates; georeferenced ones are centred in float64.
    radius : float
        Ball radius, in the points' length unit (about 30 neighbours is a good start).
    method : {'variation', 'mls0', 'mls1'}
        'variation': surface variation l0/(l0+l1+l2) (Pauly et al.; Theorem 4 of Digne &
        Morel: r^2/16 ((k1^2+k2^2)/2 - k1 k2/3)), unsigned.
        'mls0': barycenter shift o - p; ``mean`` = H = 4 <p - o, n> / r^2 (Lemma 2) with n
        the supplied ``normals`` when given, else the oriented PCA normal (then H equals
        MLS1's); ``points`` = o, the barycenter.
        'mls1': projection on the PCA regression plane; ``mean`` = H = 4 <p - p', n> / r^2
        (Theorem 5); ``points`` = p'.
    weights : {'uniform', 'density'}
        'density' weights each neighbour q by 1/#N_r(q) to compensate irregular sampling.
    normals : (N, 3) array_like, optional
        Reference normals (need not be unit): they orient the PCA normals.
    orient : {'auto', 'mst', 'viewpoint', 'normals', None}
        How to orient the normals (and so sign H). 'auto' uses ``normals`` when given, else
        ``viewpoint`` when given, else 'mst': Hoppe's minimum-spanning-tree propagation over
        the ``orient_k``-nearest-neighbour graph with the outward choice at the point
        farthest from each component's centroid (closed shapes come out outward).
        None leaves the PCA sign as computed (then the sign of H is arbitrary per point).
    viewpoint : 3 floats, optional
        Scanner position: normals are turned towards it.
    device : None, int or str
        OpenCL device (see :func:`clcurv.devices`); default ``CLCURV_DEVICE`` or a GPU or PoCL.
    precision : {'float', 'double'}
        Device arithmetic ('double' needs a device with cl_khr_fp64).
    backend : {'opencl', 'numpy'}
        'numpy' runs the float64 NumPy/SciPy reference instead of the kernels.

    Returns
    -------
    CurvatureResult
        Arrays in input order. Sign convention: outward normals, sphere of radius R has
        H = +1/R. Points with fewer than 3 neighbours (status 1) or collinear/coincident
        neighbours (status 2) get NaN.

    Examples
    --------
    >>> import numpy as np, clcurv
    >>> rng = np.random.default_rng(0)
    >>> p = rng.normal(size=(20000, 3)); p *= 2 / np.linalg.norm(p, axis=1)[:, None]
    >>> res = clcurv.curvature(p, 0.3, method="mls1")
    >>> bool(abs(np.nanmedian(res.mean) - 0.5) < 0.01)
    True
    """
    method = choice(method, "method", METHODS)
    weights = choice(weights, "weights", ("uniform", "density"))
    backend = choice(backend, "backend", ("opencl", "numpy"))
    orient = choice(orient, "orient", ORIENTS)
    pts = as_points(points)
    r = as_radius(radius)
    ref_normals = as_normals(normals, len(pts)) if normals is not None else None
    vp = as_viewpoint(viewpoint) if viewpoint is not None else None
    how = _orientation(orient, ref_normals, vp)
    if len(pts) == 0:
        return _empty(method, r, weights)
    raw = _raw_moments(pts, r, weights, backend, device, precision, refine=True)
    n = raw["normals"].astype(np.float64)
    flip = _flip(pts, n, how, ref_normals, vp, orient_k)
    n[flip] *= -1
    shift = raw["shift"].astype(np.float64)
    status = raw["status"].astype(np.uint8)
    _warn_sparse(status, r)
    res = CurvatureResult(method, r, weights, raw["count"].astype(np.int64), status, n,
                          raw["eigenvalues"].astype(np.float64),
                          raw["variation"].astype(np.float64))
    if method == "mls0":
        nref = ref_normals if ref_normals is not None else n
        res.mean = -4.0 * np.einsum("ij,ij->i", shift, nref) / (r * r)
        res.mean[status != OK] = np.nan
        res.points = pts + shift
    elif method == "mls1":
        along = np.einsum("ij,ij->i", shift, n)
        res.mean = -4.0 * along / (r * r)
        res.points = pts + along[:, None] * n
    res.info["orientation"] = how
    return res


def normals(points, radius, *, weights="uniform", normals=None, orient="auto", viewpoint=None,
            orient_k=10, device=None, precision="float", backend="opencl"):
    """Unit PCA normals (eigenvector of the smallest covariance eigenvalue of N_r(p)).

    Same parameters as :func:`curvature`. Returns an (N, 3) float64 array in input order,
    oriented as ``orient`` says (outward by default on closed shapes), NaN where fewer than
    3 neighbours or a degenerate neighbourhood.
    """
    weights = choice(weights, "weights", ("uniform", "density"))
    backend = choice(backend, "backend", ("opencl", "numpy"))
    orient = choice(orient, "orient", ORIENTS)
    pts = as_points(points)
    r = as_radius(radius)
    ref_normals = as_normals(normals, len(pts)) if normals is not None else None
    vp = as_viewpoint(viewpoint) if viewpoint is not None else None
    how = _orientation(orient, ref_normals, vp)
    if len(pts) == 0:
        return np.empty((0, 3))
    raw = _raw_moments(pts, r, weights, backend, device, precision, refine=False)
    n = raw["normals"].astype(np.float64)
    _warn_sparse(raw["status"], r)
    n[_flip(pts, n, how, ref_normals, vp, orient_k)] *= -1
    return n
