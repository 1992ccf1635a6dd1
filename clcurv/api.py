"""Public entry points: :func:`curvature`, :func:`normals` and :func:`project` (numpy in,
numpy out, input order preserved)."""
from __future__ import annotations

import warnings

import numpy as np

from . import orient as _orient
from .result import CurvatureResult, OK, TOO_FEW
from .validate import as_normals, as_points, as_radius, as_viewpoint, choice

MOMENT_METHODS = ("variation", "mls0", "mls1")
COVARIANCE_METHODS = ("2dcov1", "2dcov2", "3dcov")
METHODS = MOMENT_METHODS + COVARIANCE_METHODS + ("mls2",)
ORIENTS = ("auto", "mst", "viewpoint", "normals", None)
MLS_KERNELS = ("ball", "gaussian")


class _OpenCL:
    """The kernels, on one DeviceCloud binned once for every pass of a call."""

    def __init__(self, points, radius, device, precision):
        from .cloud import DeviceCloud
        self.cloud = DeviceCloud(points, radius, device=device, precision=precision)
        self.radius = radius

    def moments(self, weights, refine, fields=None):
        from .moments import device_moments
        return device_moments(self.cloud, self.radius, weights=weights, refine=refine,
                              fields=fields)

    def covariances(self, normals, method, weights):
        from .covariances import device_covariances
        return device_covariances(self.cloud, self.radius, normals, method, weights=weights)

    def mls2(self, normals, weights, kernel, h):
        from .mls import device_mls2
        return device_mls2(self.cloud, self.radius, normals, weights=weights, kernel=kernel, h=h)


class _NumPy:
    """The float64 reference (clcurv.reference), same interface as :class:`_OpenCL`."""

    def __init__(self, points, radius):
        from . import reference
        self.ref, self.points, self.radius = reference, points, radius

    def moments(self, weights, refine, fields=None):
        return self.ref.moments(self.points, self.radius, weights=weights)

    def covariances(self, normals, method, weights):
        return self.ref.covariance_ops(self.points, self.radius, normals, method, weights=weights)

    def mls2(self, normals, weights, kernel, h):
        if normals is None:
            raise ValueError("backend='numpy' MLS2 needs oriented normals (orient must not be None)")
        out = self.ref.mls2(self.points, self.radius, normals, weights=weights, kernel=kernel, h=h)
        out["shift"] = out.pop("points") - self.points
        return out


def _backend(backend, points, radius, device, precision):
    if backend == "numpy":
        return _NumPy(points, radius)
    return _OpenCL(points, radius, device, precision)


DEFER_MIN = 100_000     # from this size, user normals are checked while the cloud is binned


def _inputs(points, radius, weights, backend, orient, normals, viewpoint, unit=True,
            defer=False):
    """Validated (points, radius, normals or None (unit if ``unit``), viewpoint or None,
    orientation). With ``defer`` (and a large cloud on the OpenCL backend) the normals come
    as a future of that result, checked on a host thread while the caller bins the cloud;
    :func:`_resolved` gives the array or raises the check's error."""
    choice(weights, "weights", ("uniform", "density"))
    choice(backend, "backend", ("opencl", "numpy"))
    choice(orient, "orient", ORIENTS)
    pts = as_points(points)
    r = as_radius(radius)
    ref = None
    if normals is not None:
        if defer and backend == "opencl" and len(pts) >= DEFER_MIN:
            from .cloud import host_pool
            ref = host_pool().submit(as_normals, normals, len(pts), unit)
        else:
            ref = as_normals(normals, len(pts), unit)
    vp = as_viewpoint(viewpoint) if viewpoint is not None else None
    return pts, r, ref, vp, _orientation(orient, ref, vp)


def _resolved(normals):
    """The normals of :func:`_inputs`, waiting for a deferred check."""
    return normals.result() if hasattr(normals, "result") else normals


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


def _warn_sparse(status, radius, need=3):
    few = np.count_nonzero(status == TOO_FEW)
    if few > len(status) // 2:
        warnings.warn(f"{few} of {len(status)} points have fewer than {need} neighbours within "
                      f"radius {radius}: their outputs are NaN; the radius is probably too small",
                      RuntimeWarning, stacklevel=3)


def _f64(a):
    return None if a is None else np.asarray(a, dtype=np.float64)


def _empty(method, radius, weights):
    z, z3 = np.empty(0), np.empty((0, 3))
    res = CurvatureResult(method, radius, weights, np.empty(0, np.int64), np.empty(0, np.uint8),
                          z3, z3.copy(), z.copy())
    if method in ("mls0", "mls1", "mls2"):
        res.mean, res.points = z.copy(), z3.copy()
    if method in COVARIANCE_METHODS + ("mls2",):
        res.k1, res.k2, res.dir1, res.dir2 = z.copy(), z.copy(), z3.copy(), z3.copy()
        res.variation = None
        res.eigenvalues = None if method == "mls2" else np.empty((0, 3 if method == "3dcov" else 2))
    if method == "mls2":
        res.gaussian = z.copy()
    return res


def _moment_result(method, r, weights, pts, raw, n, ref_normals):
    status = raw["status"].astype(np.uint8)
    res = CurvatureResult(method, r, weights, raw["count"].astype(np.int64), status, n,
                          _f64(raw["eigenvalues"]), _f64(raw["variation"]))
    shift = _f64(raw["shift"])
    if method == "mls0":
        nref = ref_normals if ref_normals is not None else n
        res.mean = -4.0 * np.einsum("ij,ij->i", shift, nref) / (r * r)
        res.mean[status != OK] = np.nan
        res.points = pts + shift
    elif method == "mls1":
        along = np.einsum("ij,ij->i", shift, n)
        res.mean = -4.0 * along / (r * r)
        res.points = pts + along[:, None] * n
    return res


def _oriented(pts, raw, how, ref_normals, vp, k):
    """The PCA normals of ``raw`` (float64), oriented as ``how`` says."""
    n = np.array(raw["normals"], dtype=np.float64, copy=None)   # the backends' arrays are fresh
    n[_flip(pts, n, how, ref_normals, vp, k)] *= -1
    return n


def _operator_result(method, r, weights, pts, raw, n):
    res = CurvatureResult(method, r, weights, raw["count"].astype(np.int64),
                          raw["status"].astype(np.uint8), n, None, None)
    res.k1, res.k2 = _f64(raw["k1"]), _f64(raw["k2"])
    res.dir1, res.dir2 = _f64(raw["dir1"]), _f64(raw["dir2"])
    if method == "mls2":
        res.normals = _f64(raw["normals"])
        res.points = np.add(pts, raw["shift"], out=raw["shift"])      # a fresh float64 array
        res.mean = 0.5 * (res.k1 + res.k2)
        res.gaussian = res.k1 * res.k2
    else:
        res.eigenvalues = _f64(raw["eigenvalues"])
    return res


def curvature(points, radius, *, method="mls1", weights="uniform", normals=None, orient="auto",
              viewpoint=None, orient_k=10, kernel="ball", h=None, iterations=0, scale_space=0,
              device=None, precision="float", backend="opencl"):
    """Differential operators on the ball N_r(p) = {q : |q - p| < radius} of every point.

    Parameters
    ----------
    points : (N, 3) array_like of real numbers
        The raw cloud. Any finite coordinates; they are stored relative to their grid cell
        (computed in float64), so georeferenced ones lose no precision.
    radius : float
        Ball radius, in the points' length unit (about 30 neighbours is a good start).
    method : str
        'variation': surface variation l0/(l0+l1+l2) (Pauly et al.; Theorem 4 of Digne &
        Morel: r^2/16 ((k1^2+k2^2)/2 - k1 k2/3)), unsigned.
        'mls0': barycenter shift o - p; ``mean`` = H = 4 <p - o, n> / r^2 (Lemma 2) with n
        the supplied ``normals`` when given, else the oriented PCA normal (then H equals
        MLS1's); ``points`` = o, the barycenter.
        'mls1': projection on the PCA regression plane; ``mean`` = H = 4 <p - p', n> / r^2
        (Theorem 5); ``points`` = p'.
        '2dcov1', '2dcov2', '3dcov': covariances of normal-based quantities (Theorems 1-3);
        ``k1 >= k2 >= 0`` are curvature MAGNITUDES (unsigned), ``dir1``, ``dir2`` principal
        directions, ``eigenvalues`` the count-normalised covariance eigenvalues (descending).
        They use ``normals`` when given (normalised), else the oriented PCA normals.
        'mls2': weighted quadric fit in the PCA frame (operator 7): signed ``k1 >= k2``,
        ``dir1``, ``dir2``, ``mean`` H, ``gaussian`` K, fitted ``normals``, ``points`` the
        MLS2 projection (fourth-order accurate).
    weights : {'uniform', 'density'}
        'density' weights each neighbour q by 1/#N_r(q) to compensate irregular sampling.
    normals : (N, 3) array_like, optional
        Normals of the points (need not be unit). They orient the PCA normals and are the
        normals of the normal-based operators (the PCL/CGAL convention).
    orient : {'auto', 'mst', 'viewpoint', 'normals', None}
        How to orient the normals (and so sign H, k1, k2). 'auto' uses ``normals`` when given,
        else ``viewpoint`` when given, else 'mst': Hoppe's minimum-spanning-tree propagation
        over the ``orient_k``-nearest-neighbour graph with the outward choice at the point
        farthest from each component's centroid (closed shapes come out outward).
        None keeps the PCA sign (arbitrary per point; not allowed for the 2dcov/3dcov methods,
        which need consistent normals).
    viewpoint : 3 floats, optional
        Scanner position: normals are turned towards it.
    kernel : {'ball', 'gaussian'}
        MLS2 weights: uniform in the ball, or exp(-|q - p|^2 / h^2) (h = radius/2 by default).
    iterations : int
        MLS2 only: project the cloud this many times by MLS2 first (neighbourhoods recomputed
        each time, see :func:`project`), then evaluate; values refer to the input indices.
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
        H = k1 = k2 = +1/R. Points with too few neighbours (status 1: < 3, or < 6 for MLS2),
        a degenerate neighbourhood (2) or a singular fit (3) get NaN.

    Examples
    --------
    >>> import numpy as np, clcurv
    >>> p = clcurv.shapes.sphere(20000, 2.0)["points"]
    >>> res = clcurv.curvature(p, 0.3, method="mls2")
    >>> bool(abs(np.nanmedian(res.k2) - 0.5) < 0.01)
    True
    """
    method = choice(method, "method", METHODS)
    kernel = choice(kernel, "kernel", MLS_KERNELS)
    # the normal-based operators and MLS0 use the normals' values; the others only their sign
    unit = method in COVARIANCE_METHODS + ("mls0",)
    pts, r, ref_normals, vp, how = _inputs(points, radius, weights, backend, orient, normals,
                                           viewpoint, unit, defer=True)
    if method in COVARIANCE_METHODS and how is None and ref_normals is None:
        raise ValueError(f"{method} needs consistently oriented normals: pass normals= or an orient")
    iterations = int(iterations)
    if iterations < 0 or (iterations and method != "mls2"):
        raise ValueError("iterations must be >= 0 and is for method='mls2' "
                         "(use clcurv.scale_space for MLS1)")
    scale_space = int(scale_space)
    if scale_space < 0:
        raise ValueError(f"scale_space must be >= 0, got {scale_space}")
    if len(pts) == 0 or scale_space or iterations:
        ref_normals = _resolved(ref_normals)
    if len(pts) == 0:
        return _empty(method, r, weights)
    if scale_space:
        from .scale_space import scale_space as _smooth
        smoothed = _smooth(pts, r, scale_space, weights=weights, device=device,
                           precision=precision, backend=backend)
        res = curvature(smoothed, r, method=method, weights=weights, normals=ref_normals,
                        orient=orient, viewpoint=vp, orient_k=orient_k, kernel=kernel, h=h,
                        iterations=iterations, device=device, precision=precision, backend=backend)
        if res.points is None:
            res.points = smoothed
        res.info["scale_space"] = scale_space
        return res
    if iterations:
        moved = project(pts, r, iterations=iterations, weights=weights, normals=ref_normals,
                        orient=orient, viewpoint=vp, orient_k=orient_k, kernel=kernel, h=h,
                        device=device, precision=precision, backend=backend)
        res = curvature(moved, r, method=method, weights=weights, orient=orient if orient != "normals" else "mst",
                        viewpoint=vp, orient_k=orient_k, kernel=kernel, h=h, device=device,
                        precision=precision, backend=backend)
        res.info["iterations"] = iterations
        return res
    be = _backend(backend, pts, r, device, precision)      # bins while the normals are checked
    ref_normals = _resolved(ref_normals)
    if method in MOMENT_METHODS:
        raw = be.moments(weights, refine=True)
        n = _oriented(pts, raw, how, ref_normals, vp, orient_k)
        _warn_sparse(raw["status"], r)
        res = _moment_result(method, r, weights, pts, raw, n, ref_normals)
    else:
        # the normal-based operators and MLS2 need only oriented normals: with the user's
        # normals no PCA pass is run at all
        if ref_normals is not None:
            use = ref_normals
        elif how is None:
            use = None                      # MLS2 with the solver's sign for v0
        else:
            use = _oriented(pts, be.moments(weights, refine=False, fields=("normals",)), how,
                            None, vp, orient_k)
        if method in COVARIANCE_METHODS:
            op = be.covariances(use, method, weights)
        else:
            op = be.mls2(use, weights, kernel, h)
        _warn_sparse(op["status"], r, need=6 if method == "mls2" else 3)
        res = _operator_result(method, r, weights, pts, op, use)
    res.info["orientation"] = how
    return res


def project(points, radius, *, iterations=1, method="mls2", weights="uniform", normals=None,
            orient="auto", viewpoint=None, orient_k=10, kernel="ball", h=None, device=None,
            precision="float", backend="opencl"):
    """Iterated MLS2 projection: every point is replaced by its MLS2 projection, all together,
    ``iterations`` times, neighbourhoods recomputed on the moved cloud each time.

    The fit's normals are oriented at the first iteration as ``orient`` says and then
    propagated: each iteration's PCA normals are oriented to agree with the previous
    iteration's fitted normals. Points whose fit fails (status != 0) stay where they are for
    that iteration. Returns the moved (N, 3) float64 points in input order. Iterated MLS2 is
    not a scale space (Digne & Morel): use :func:`clcurv.scale_space` (MLS1) to smooth.
    """
    choice(method, "method", ("mls2",))
    pts = as_points(points).copy()
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    ref = as_normals(normals, len(pts), unit=False) if normals is not None else None
    how = orient
    for _ in range(iterations):
        if len(pts) == 0:
            break
        res = curvature(pts, radius, method="mls2", weights=weights, normals=ref, orient=how,
                        viewpoint=viewpoint, orient_k=orient_k, kernel=kernel, h=h,
                        device=device, precision=precision, backend=backend)
        ok = res.valid
        pts[ok] = res.points[ok]
        ref = np.where(ok[:, None], res.normals, ref if ref is not None else res.normals)
        if not np.isfinite(ref).all():
            ref = None
        how = "normals" if ref is not None else orient
    return pts


def normals(points, radius, *, weights="uniform", normals=None, orient="auto", viewpoint=None,
            orient_k=10, device=None, precision="float", backend="opencl"):
    """Unit PCA normals (eigenvector of the smallest covariance eigenvalue of N_r(p)).

    Same parameters as :func:`curvature`. Returns an (N, 3) float64 array in input order,
    oriented as ``orient`` says (outward by default on closed shapes), NaN where fewer than
    3 neighbours or a degenerate neighbourhood.
    """
    pts, r, ref_normals, vp, how = _inputs(points, radius, weights, backend, orient, normals,
                                           viewpoint, unit=False)     # they only orient
    if len(pts) == 0:
        return np.empty((0, 3))
    raw = _backend(backend, pts, r, device, precision).moments(weights, refine=False,
                                                               fields=("normals",))
    n = np.array(raw["normals"], dtype=np.float64, copy=None)   # the backends' arrays are fresh
    _warn_sparse(raw["status"], r)
    n[_flip(pts, n, how, ref_normals, vp, orient_k)] *= -1
    return n
