"""Public entry points: :func:`curvature`, :func:`normals` and :func:`project` (numpy in,
numpy out, input order preserved)."""
from __future__ import annotations

import contextvars

import numpy as np

from clcurv._shared.constants import TOO_FEW
from clcurv._shared.host_threads import host_pool
from clcurv._shared.options import check, given
from clcurv._shared.validate import (as_count, as_normals, as_points, as_radius, as_viewpoint,
                                     choice, device_radius)
from clcurv.api.inputs import as_radii, check_method, cloud_points, orient_spec, parse_knn
from clcurv.api.result import CurvatureResult, empty_columns, warn_sparse
from clcurv.grid.binning import ExtentError, bin_points, check_pairs
from clcurv.grid.cloud import DeviceCloud
from clcurv.ops.driver import run_kernel
from clcurv.ops.features import run_features
from clcurv.ops.knn_radius import knn_radii
from clcurv.ops.registry import OPERATORS, PCA, PCA_NORMALS_DEFINES
from clcurv.ops.pooling import pool_bias
from clcurv.ops.selection import choose, fit_bias
from clcurv.ops.smoothing import scale_space as smooth
from clcurv.orient import orientation as _orient
from clcurv.reference import operators as reference
from clcurv.reference import pooling as reference_pooling
from clcurv.reference import uncertainty

#: largest ``orient_k`` (the device graph's longest neighbour list, clcurv.orient.graph.KMAX):
#: Hoppe's graph needs about 10; more only costs time and memory
MAX_ORIENT_K = 32


#: PCA normals of several radii from one walk (:func:`_radius_list`): {"cloud", "raws":
#: {radius: raw fields}}, taken by :meth:`_Run.pca_normals` in the calls at those radii
_PCA_GIVEN = contextvars.ContextVar("clcurv_pca_given", default=None)


class _Run:
    """Where a call's operators run: the kernels on one DeviceCloud binned once for every
    pass of the call, or (backend='numpy') the float64 reference on the same points."""

    def __init__(self, backend, points, radius, device, precision, cloud=None, knn=None):
        self.points, self.radius = points, radius
        self.cloud = None
        # the k-NN radius (clcurv.ops.knn_radius.KnnRadii): per-point balls, radius the largest
        self.point_r2 = None if knn is None else knn.r2_sorted
        self.knn_k = None if knn is None else knn.k
        if backend == "opencl":                # DeviceCloud checks the radius and the pairs
            self.cloud = cloud if cloud is not None else DeviceCloud(
                points, radius, device=device, precision=precision)
            self.cloud.check_radius(radius)
        else:                               # the float64 reference: double's range
            device_radius(radius, "double")
            try:
                grid = bin_points(points, radius)
            except ExtentError:             # more cells than keys: far from quadratic
                grid = None
            if grid is not None:
                check_pairs(grid, points, radius)

    def operator(self, op, normals=None, weights="uniform", kernel="ball", h=None,
                 align=None, uncertainty=False):
        """The raw fields of ``op`` (a clcurv.ops.registry.Operator); ``h`` defaults to r / 2
        for ``kernel='gaussian'``; ``align`` (2dcov2, 3dcov): align each neighbour's normal
        with the query point's (None: the kernel's default, the normals as given);
        ``uncertainty``: the kernel's error record too (the reference's errors are
        :meth:`reference_errors`)."""
        if self.cloud is None:
            opts = {"kernel": kernel, "h": h} if "kernel" in op.options else {}
            if align is not None:
                opts["align_normals"] = align
            return op.reference(self.points, self.radius, normals, weights, **opts)
        if kernel == "gaussian" and h is None:
            h = self.radius / 2
        return run_kernel(op.kernel, self.cloud, self.radius, normals=normals, weights=weights,
                          h=h if kernel == "gaussian" else None, fields=op.fields,
                          point_r2=self.point_r2, uncertainty=uncertainty,
                          defines=dict({} if align is None else {"ALIGN_NORMALS": int(align)},
                                       **(op.error_defines if uncertainty else {})))

    def reference_errors(self, op, normals, weights, kernel, h, user=None):
        """backend='numpy': the error outputs of ``op`` from the float64 reference
        (clcurv.reference.uncertainty), ``normals`` the oriented normals the call used
        (MLS2 and MLS1 orient their fits with them), ``user`` the user's (MLS0's n)."""
        pts, r = self.points, self.radius
        if op.normals == "values" and op.name != "mls0" and user is not None:
            return _unknown_errors(op, len(pts))     # your normals: their error unknown
        if op.name == "mls2":
            hh = (r / 2 if h is None else h) if kernel == "gaussian" else None
            ref = uncertainty.mls2_uncertainty(pts, r, normals, weights=weights,
                                               kernel=kernel, h=hh)
        elif op.name in ("mls0", "mls1"):
            ref = uncertainty.mls1_uncertainty(
                pts, r, normals if op.name == "mls1" or user is None else user,
                weights=weights, method=op.name)
        else:
            ref = uncertainty.pca_uncertainty(pts, r, weights=weights)
        return {o.name: ref[o.name] for o in op.errors}

    def mst_flips(self, normals, k):
        """Flip mask of Hoppe's propagation over the ``k``-nearest-neighbour graph within the
        radius: on the device (the same graph and forest), or the float64 reference."""
        if self.cloud is None:              # the reference's own propagation
            return reference.mst_flips(self.points, normals, k=k, radius=self.radius)
        # a k-NN ball of K points holds each point's k < K nearest: the orientation graph
        # walks that ball, not the grid's largest radius
        own = self.point_r2 if self.knn_k is not None and k < self.knn_k else None
        return _orient.flip_on_device(self.cloud, normals, self.radius, k, own)

    def pca_normals(self, weights, uncertainty=False):
        """Unoriented PCA normals (and count, status) only: the orientation pass, and the
        covariance operators' normals (``uncertainty``: with the error record, the
        normal's SE and the plane's roughness; the same normals bit for bit)."""
        if self.cloud is None:
            return reference.moments(self.points, self.radius, weights=weights)
        given = _PCA_GIVEN.get()
        if (given is not None and given["cloud"] is self.cloud and weights == "uniform"
                and self.point_r2 is None and self.radius in given["raws"]
                and not uncertainty):
            return given["raws"][self.radius]
        return run_kernel(PCA, self.cloud, self.radius, weights=weights, fields=("normals",),
                          defines=PCA_NORMALS_DEFINES, point_r2=self.point_r2,
                          uncertainty=uncertainty)


DEFER_MIN = 100_000     # from this size, user normals are checked while the cloud is binned


def _inputs(points, radius, weights, backend, orient, normals, viewpoint, orient_k, unit=True,
            defer=False, signed=True):
    """Validated (points, radius, normals or None (unit if ``unit``), viewpoint or None,
    orientation). With ``defer`` (and a large cloud on the OpenCL backend) the normals come
    as a future of that result, checked on a host thread while the caller bins the cloud;
    :func:`_resolved` gives the array or raises the check's error."""
    check(weights, "weights")
    check(backend, "backend")
    orient = orient_spec(orient)
    as_count(orient_k, "orient_k", MAX_ORIENT_K)
    # on the OpenCL backend the binning checks finiteness on its bounding box (every path
    # bins before it reads a coordinate), with the same message: no extra pass here
    pts = as_points(points, finite=backend != "opencl")
    if radius is None:
        raise ValueError("give radius= (a number, or 'knn:K') or k=")
    r = as_radius(radius)
    ref = None
    if normals is not None:
        if defer and backend == "opencl" and len(pts) >= DEFER_MIN:
            ref = host_pool().submit(as_normals, normals, len(pts), unit)
        else:
            ref = as_normals(normals, len(pts), unit)
    vp = as_viewpoint(viewpoint) if viewpoint is not None else None
    return pts, r, ref, vp, _orientation(orient, ref, vp, signed)


def _resolved(normals):
    """The normals of :func:`_inputs`, waiting for a deferred check."""
    return normals.result() if hasattr(normals, "result") else normals


def _orientation(orient, normals, viewpoint, signed=True):
    """The orientation a call uses: 'auto' is the user's normals, else the viewpoint, else
    'mst' for a signed result and None (no global orientation) for an unsigned one."""
    if isinstance(orient, np.ndarray):
        return orient
    if orient == "auto":
        if normals is not None:
            return "normals"
        if viewpoint is not None:
            return "viewpoint"
        return "mst" if signed else None
    if orient == "normals" and normals is None:
        raise ValueError("orient='normals' needs normals=")
    if orient == "viewpoint" and viewpoint is None:
        raise ValueError("orient='viewpoint' needs viewpoint=")
    return orient


def _flip(run, n, how, normals, viewpoint, k):
    """Flip mask of the normals ``n`` of ``run``'s points for the orientation ``how``."""
    if run.cloud is None:                   # backend='numpy': the reference's own flips
        return reference.orientation_flips(run.points, n, how, normals, viewpoint, k, run.radius)
    if isinstance(how, np.ndarray):
        return _orient.flip_to_reference(n, how)
    if how == "normals":
        return _orient.flip_to_reference(n, normals)
    if how == "viewpoint":
        return _orient.flip_to_viewpoint(run.points, n, viewpoint)
    if how == "mst":
        return run.mst_flips(n, k)
    return np.zeros(len(n), dtype=bool)


def _oriented(run, raw, how, ref_normals, vp, k):
    """The PCA normals of ``raw`` (float64), oriented as ``how`` says."""
    n = np.array(raw["normals"], dtype=np.float64, copy=None)   # the backends' arrays are fresh
    n[_flip(run, n, how, ref_normals, vp, k)] *= -1
    return n


def _result(op, r, weights, count, status, attrs):
    """A CurvatureResult of ``op`` from its finished attributes (float64 arrays)."""
    attrs = {k: (None if v is None else np.asarray(v, dtype=np.float64))
             for k, v in attrs.items()}
    return CurvatureResult(op.name, r, weights, np.asarray(count, dtype=np.int64),
                           np.asarray(status, dtype=np.uint8), attrs.pop("normals"),
                           attrs.pop("eigenvalues", None), attrs.pop("variation", None), **attrs)


def _unknown_errors(op, n):
    """The error outputs of ``op`` as NaN: the covariance operators with your normals,
    whose errors clcurv cannot know."""
    return {o.name: np.full(n, np.nan) for o in op.errors}


def _check_options(op, kernel, h, projections, align_normals=None, uncertainty=False):
    """The method-specific options: given to a method that ignores them, they raise."""
    extra = op.foreign_options(given({"kernel": kernel, "h": h, "projections": projections,
                                      "align_normals": align_normals}))
    if extra:
        takers = next(iter(extra.values()))
        raise ValueError(f"{', '.join(extra)} {'is' if len(extra) == 1 else 'are'} not an "
                         f"option of method={op.name!r} (only of "
                         f"{', '.join(repr(m) for m in takers)})")
    kernel = check("ball" if kernel is None else kernel, "kernel")
    if h is not None:
        if kernel != "gaussian":
            raise ValueError("h is the width of kernel='gaussian'")
        h = float(h)
        if not (h > 0 and np.isfinite(h)):
            raise ValueError(f"h must be a positive finite number, got {h}")
    projections = int(projections)
    if projections < 0:
        raise ValueError(f"projections must be >= 0, got {projections}")
    if align_normals is not None and not isinstance(align_normals, (bool, np.bool_)):
        raise TypeError(f"align_normals must be True, False or None, got {align_normals!r}")
    if not isinstance(uncertainty, (bool, np.bool_)):
        raise TypeError(f"uncertainty must be True or False, got {uncertainty!r}")
    return kernel, h, projections


def curvature(points, radius=None, *, method="mls1", weights="uniform", normals=None,
              orient="auto", viewpoint=None, orient_k=10, kernel=None, h=None, projections=0,
              scale_space=0, device=None, precision="float", backend="opencl", k=None,
              align_normals=None, uncertainty=False, select=None):
    """Differential operators on the ball N_r(p) = {q : |q - p| < radius} of every point.

    Parameters
    ----------
    points : (N, 3) array_like of real numbers, or a DeviceCloud
        The raw cloud. Any finite coordinates; they are stored relative to their grid cell
        (computed in float64), so georeferenced ones lose no precision. A
        :class:`~clcurv.DeviceCloud` (binned once, cell >= radius) is reused as it is, so
        several operators can run on one binning.
    radius : float or sequence of floats
        Ball radius, in the points' length unit (about 30 neighbours is a good start). A
        list of radii (methods 'variation', '2dcov1', '2dcov2', '3dcov') returns a list of
        results, one per radius, each bit-identical to a call at that radius alone on the
        same DeviceCloud: the cloud is binned once at the largest radius, and the PCA of
        every radius comes from one neighbour walk ('variation' is that walk; the
        covariance operators take their normals from it, then run their own pass per
        radius; see :func:`_radius_list`).
    method : str
        One of :data:`clcurv.METHODS` (the registry, :mod:`clcurv.ops.registry`):
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
        normals of the normal-based operators (the PCL/CGAL convention), used as given:
        2dcov2 is then PCL's PrincipalCurvaturesEstimation with these normals (see
        ``align_normals``).
    orient : {'auto', 'mst', 'viewpoint', 'normals', 'up', None} or 3 floats
        How to orient the normals (and so sign H, k1, k2). 'auto' uses ``normals`` when given,
        else ``viewpoint`` when given, else, for a signed method (mls0, mls1, mls2), 'mst',
        and for an unsigned one (variation, 2dcov1, 2dcov2, 3dcov) None: their values do not
        depend on the PCA normals' signs (2dcov2 and 3dcov align each neighbour's PCA normal
        with the query point's inside the kernel, see ``align_normals``), so no global
        orientation is paid for and their ``normals`` keep the PCA sign. 'mst': Hoppe's minimum-spanning-tree propagation
        over the graph of each point's ``orient_k`` nearest neighbours within the radius,
        on the device (:mod:`clcurv.orient.forest`), then each connected component turned outward
        (:func:`clcurv.orient.orientation.component_signs`: closed shapes, nested ones included, come
        out outward). 'up' (or a direction vector): normals make a positive dot product
        with +Z (with the vector): PDAL's ``always_up``, for aerial LiDAR. None keeps the
        PCA sign (arbitrary per point).
    viewpoint : 3 floats, optional
        Scanner position: normals are turned towards it.
    orient_k : int
        Neighbours per point of the 'mst' propagation graph, 1 to 32 (default 10).
    kernel : {'ball', 'gaussian'}, optional
        MLS2 only: neighbour weights uniform in the ball (default), or
        exp(-|q - p|^2 / h^2).
    h : float, optional
        MLS2 with ``kernel='gaussian'`` only: the Gaussian's width, in the points' unit
        (default radius / 2).
    projections : int
        MLS2 only: project the cloud this many times by MLS2 first (neighbourhoods
        recomputed each time, see :func:`project`), then evaluate; values refer to the
        input indices. Default 0.
    scale_space : int
        Run this many MLS1 scale-space steps (:func:`clcurv.scale_space`) at ``radius``
        first and evaluate the operator on the smoothed cloud: the paper's recommended
        pipeline. ``points`` of the result are then the smoothed positions (or the
        operator's projection of them). Default 0.
    device : None, int or str
        OpenCL device (see :func:`clcurv.devices`); default ``CLCURV_DEVICE`` or a GPU or PoCL.
    precision : {'float', 'double'}
        Device arithmetic ('double' needs a device with cl_khr_fp64).
    backend : {'opencl', 'numpy'}
        'numpy' runs the float64 NumPy/SciPy reference instead of the kernels.
    k : int, optional
        Adaptive radius (``radius=None``, or ``radius="knn:K"``): each point's ball radius is
        the distance to its k-th nearest point (the point itself the first), found on the
        device with the grid (:mod:`clcurv.ops.knn_radius`, which documents k > N, duplicates
        and isolated points), and every operator uses that point's radius in its constants
        (H = 4 <p - o, n> / r^2, the 2 / r factors). The paper's analysis is for a fixed r.
        ``result.radius`` is then the (N,) array of radii. Not with weights='density',
        kernel='gaussian', scale_space, projections or backend='numpy'; the MST
        orientation graph uses the largest radius.
    align_normals : bool, optional
        2dcov2 and 3dcov only: align each neighbour's normal with the query point's
        (n_i := -n_i where <n_i, n> < 0) before its covariance, so that only the normals'
        agreement within each ball matters, not their signs. Default (None): aligned where
        clcurv estimates the normals itself (the PCA normals, whatever ``orient``); the
        ``normals`` you pass are used as given. True: yours too (normals of arbitrary
        signs); False: never (the PCA normals as ``orient`` leaves them).
    uncertainty : bool
        Also per-point standard errors (SE), from the same neighbour walk ('mls0' and
        'mls1' add a second walk, MLS2's quadric fit, for the point's own noise):
        ``mean_se`` (mls0, mls1, mls2), ``gaussian_se``, ``k1_se``, ``k2_se`` (mls2),
        ``normal_se`` (radians: of the PCA normal, or of MLS2's fitted normal) and
        ``roughness`` (length: the residual RMS to the fitted quadric for mls2, to the
        regression plane otherwise); the covariance operators have the last two, of
        their PCA normals' pass (NaN with your ``normals``: their error is not known). The model: noise
        independent, along the normal, first order; the operator's bias (which grows
        with the radius) is **not** included, so an SE is an error bar only where the
        radius is small against the curvature's scale (docs/uncertainty.md, with the
        calibration figures). With ``scale_space`` or ``projections`` they are the errors
        of the final operator on the moved cloud. Not with ``k`` (per-point radii).
    select : {None, 'error'}
        Methods 'mls1' and 'mls2', with a list of radii: one result in which each point
        keeps the radius of least predicted error SE(H)^2 + bias^2
        (:func:`_selected`, :mod:`clcurv.ops.selection`), with ``uncertainty`` on;
        ``result.radius`` is the (N,) array of the chosen radii. Each radius is binned at
        its own size; the normals of the largest radius orient the others (one
        orientation for every radius), and each point's outputs are those of a call at
        its chosen radius with those normals.

    Returns
    -------
    CurvatureResult
        Arrays in input order. Sign convention: outward normals, sphere of radius R has
        H = k1 = k2 = +1/R. Points with too few neighbours (status 1: fewer than the
        method's minimum, 3, or 6 for MLS2), a degenerate neighbourhood (2) or a singular
        fit (3) get NaN. MLS2 with 6 to 9 neighbours (``count``) is an interpolation more
        than a fit: it amplifies round-off, and float32 results may differ from float64 by
        up to about 0.4 / r with exactly 6 neighbours, 0.015 / r with 7 to 9, and below
        1e-4 / r from 10 (measured on spheres over several seeds, see
        tests/test_hostile_api.py). Use a radius with ~30 neighbours, or
        ``precision='double'``, where such points matter.

    Examples
    --------
    >>> import numpy as np, clcurv
    >>> p = clcurv.shapes.sphere(20000, 2.0)["points"]
    >>> res = clcurv.curvature(p, 0.3, method="mls2")
    >>> bool(abs(np.nanmedian(res.k2) - 0.5) < 0.01)
    True
    """
    op = OPERATORS[check_method(method)]
    if select is not None:
        return _selected(op, points, radius, select, k, dict(
            weights=weights, normals=normals, orient=orient, viewpoint=viewpoint,
            orient_k=orient_k, kernel=kernel, h=h, projections=projections,
            scale_space=scale_space, device=device, precision=precision, backend=backend,
            align_normals=align_normals))
    if np.ndim(radius) > 0:
        if k is not None:
            raise ValueError("give either radius or k (or radius='knn:K'), not both")
        return _radius_list(op, points, radius, dict(
            weights=weights, normals=normals, orient=orient, viewpoint=viewpoint,
            orient_k=orient_k, kernel=kernel, h=h, projections=projections,
            scale_space=scale_space, device=device, precision=precision, backend=backend,
            align_normals=align_normals, uncertainty=uncertainty))
    kernel, h, projections = _check_options(op, kernel, h, projections, align_normals,
                                            uncertainty)
    uncertainty = bool(uncertainty)
    knn = None
    if k is not None or isinstance(radius, str):
        if uncertainty:
            raise ValueError("uncertainty=True needs one radius for every point, not a k-NN "
                             "radius (k=, radius='knn:K')")
        knn, radius = _knn(points, radius, k, weights, kernel, scale_space, projections, device,
                           precision, backend)
        points = knn.cloud
    points, cloud = cloud_points(points)
    pts, r, ref_normals, vp, how = _inputs(points, radius, weights, backend, orient, normals,
                                           viewpoint, orient_k, unit=op.normals == "values",
                                           defer=True, signed=op.signed)
    scale_space = int(scale_space)
    if scale_space < 0:
        raise ValueError(f"scale_space must be >= 0, got {scale_space}")
    if len(pts) == 0 or scale_space or projections:
        ref_normals = _resolved(ref_normals)
    if len(pts) == 0:
        return _result(op, r, weights, np.empty(0), np.empty(0),
                       empty_columns((o.name, o.width) for o in
                                     op.outputs + (op.errors if uncertainty else ())))
    same = dict(method=method, weights=weights, viewpoint=vp, orient_k=orient_k, device=device,
                precision=precision, backend=backend, align_normals=align_normals,
                uncertainty=uncertainty)
    mls = dict(kernel=kernel if "kernel" in op.options else None, h=h)
    if scale_space:
        smoothed = smooth(pts, r, scale_space, weights=weights, device=device,
                          precision=precision, backend=backend)
        res = curvature(smoothed, r, normals=ref_normals, orient=orient,
                        projections=projections, **same, **mls)
        if res.points is None:
            res.points = smoothed
        res.info["scale_space"] = scale_space
        return res
    if projections:
        moved, fitted = _project(pts, r, projections, weights=weights, normals=ref_normals,
                                 orient=orient, viewpoint=vp, orient_k=orient_k, kernel=kernel,
                                 h=h, device=device, precision=precision, backend=backend)
        # the last projection's fitted normals carry the orientation asked for (the
        # user's normals, viewpoint or MST) to the moved cloud
        res = curvature(moved, r, normals=fitted, orient="normals" if fitted is not None
                        else orient, **same, **mls)
        res.info["projections"] = projections
        return res
    run = _Run(backend, pts, r, device, precision, cloud, knn)  # bins while the normals are checked
    err_raw = None                      # the error record, when not the operator's own
    ref_normals = _resolved(ref_normals)
    if op.kernel.reads_normals:
        # the normal-based operators and MLS2 need only oriented normals: with the user's
        # normals no PCA pass is run at all
        if ref_normals is not None:
            use = ref_normals
        elif how is None and op.normals != "values":
            use = None                      # MLS2 with the solver's sign for v0
        elif op.flip is not None and run.cloud is not None:
            use = "own"                     # orient the fit's own normals afterwards
        else:                               # 2dcov2/3dcov align these per ball
            pca = run.pca_normals(weights, uncertainty and run.cloud is not None)
            use = _oriented(run, pca, how, None, vp, orient_k)
            if op.kernel.errors is None:    # the covariance operators: their normals' errors
                err_raw = pca
        # yours as given, clcurv's own PCA normals aligned (align_normals)
        align = ((ref_normals is None if align_normals is None else bool(align_normals))
                 if "align_normals" in op.options else None)
        # the operator's own error record (the covariance operators have none)
        unc = uncertainty and run.cloud is not None and op.kernel.errors is not None
        if isinstance(use, str):
            raw = run.operator(op, None, weights, kernel, h, uncertainty=unc)
            use = op.flip(raw, _flip(run, raw["normals"], how, None, vp, orient_k))["normals"]
        else:
            raw = run.operator(op, use, weights, kernel, h, align, uncertainty=unc)
    else:
        raw = run.operator(op, weights=weights, uncertainty=uncertainty and run.cloud is not None)
        use = _oriented(run, raw, how, ref_normals, vp, orient_k)
    if knn is not None:                 # each point's own radius in the constants
        r = knn.radius
        raw["status"][knn.isolated] = TOO_FEW
    warn_sparse(raw["status"], r, op.min_count, None if knn is None else knn.k)
    if run.cloud is None:               # backend='numpy': the reference's own finishing
        attrs = reference.finish(op.name, raw, pts, r, use, ref_normals)
        if uncertainty:
            attrs.update(run.reference_errors(op, use, weights, kernel, h, ref_normals))
    else:
        if uncertainty:                 # before finish, which may reuse raw's arrays
            errors = (op.finish_errors(err_raw, r) if err_raw is not None
                      else op.finish_errors(raw, r) if op.kernel.errors is not None
                      else _unknown_errors(op, len(pts)))
        attrs = op.finish(raw, pts, r, use, ref_normals)
        if uncertainty:
            attrs.update(errors)
    if uncertainty:                     # NaN where the operator's own status is not OK
        bad = raw["status"] != 0
        for o in op.errors:
            attrs[o.name] = np.where(bad, np.nan, attrs[o.name])
    res = _result(op, r, weights, raw["count"], raw["status"], attrs)
    res.info["orientation"] = how
    if knn is not None:
        res.info["k"] = knn.k
    return res


def project(points, radius, *, projections=1, method="mls2", weights="uniform", normals=None,
            orient="auto", viewpoint=None, orient_k=10, kernel=None, h=None, device=None,
            precision="float", backend="opencl"):
    """Iterated MLS2 projection: every point is replaced by its MLS2 projection, all together,
    ``projections`` times, neighbourhoods recomputed on the moved cloud each time.

    The other parameters are those of :func:`curvature`. The fit's normals are oriented at
    the first projection as ``orient`` says and then propagated: each projection's PCA
    normals are oriented to agree with the previous one's fitted normals. Points whose fit
    fails (status != 0) stay where they are for that projection. Returns the moved (N, 3)
    float64 points in input order. Iterated MLS2 is not a scale space (Digne & Morel): use
    :func:`clcurv.scale_space` (MLS1) to smooth.
    """
    choice(method, "method", ("mls2",))         # project is MLS2's alone
    points, _ = cloud_points(points)
    projections = int(projections)
    if projections < 0:
        raise ValueError(f"projections must be >= 0, got {projections}")
    return _project(as_points(points), radius, projections, weights=weights, normals=normals,
                    orient=orient, viewpoint=viewpoint, orient_k=orient_k, kernel=kernel, h=h,
                    device=device, precision=precision, backend=backend)[0]


def _project(pts, radius, projections, *, normals, orient, viewpoint, **common):
    """:func:`project` on checked points; returns (moved points, the last projection's
    fitted normals, oriented as asked: the user's normals where a fit failed, None when no
    normals were given and some point never had a valid fit)."""
    pts = pts.copy()
    ref = as_normals(normals, len(pts), unit=False) if normals is not None else None
    how = orient
    for _ in range(projections):
        if len(pts) == 0:
            break
        res = curvature(pts, radius, method="mls2", normals=ref, orient=how,
                        viewpoint=viewpoint, **common)
        ok = res.valid
        pts[ok] = res.points[ok]
        ref = np.where(ok[:, None], res.normals, ref if ref is not None else res.normals)
        if not np.isfinite(ref).all():
            ref = None
        how = "normals" if ref is not None else orient
    return pts, ref


def normals(points, radius=None, *, weights="uniform", normals=None, orient="auto",
            viewpoint=None, orient_k=10, device=None, precision="float", backend="opencl",
            k=None):
    """Unit PCA normals (eigenvector of the smallest covariance eigenvalue of N_r(p)).

    Same parameters as :func:`curvature` (``points`` may be a DeviceCloud), ``k`` (or
    ``radius="knn:K"``) included: each point's ball is then that of its k nearest points
    (PCL's ``setKSearch``, Open3D's ``KDTreeSearchParamKNN``, up to ties), from the k-NN
    radius of :mod:`clcurv.ops.knn_radius`; an isolated point gets NaN. Returns an (N, 3)
    float64 array in input order, oriented as ``orient`` says (outward by default on closed
    shapes), NaN where fewer than 3 neighbours or a degenerate neighbourhood.
    """
    knn = None
    if k is not None or isinstance(radius, str):
        knn, radius = _knn(points, radius, k, weights, None, 0, 0, device, precision, backend)
        points = knn.cloud
    points, cloud = cloud_points(points)
    pts, r, ref_normals, vp, how = _inputs(points, radius, weights, backend, orient, normals,
                                           viewpoint, orient_k, unit=False)  # they only orient
    if len(pts) == 0:
        return np.empty((0, 3))
    run = _Run(backend, pts, r, device, precision, cloud, knn)
    raw = run.pca_normals(weights)
    if knn is not None:     # the warning's radius (isolated points: r^2 = 0, NaN normals)
        r = knn.radius
    warn_sparse(raw["status"], r, PCA.min_count, None if knn is None else knn.k)
    return _oriented(run, raw, how, ref_normals, vp, orient_k)


#: the methods that take a list of radii (their results do not depend on an orientation)
MULTI_RADIUS_METHODS = ("variation", "2dcov1", "2dcov2", "3dcov")


def _radius_list(op, points, radius, kw):
    """:func:`curvature` at every radius of a list: one result per radius, in the order
    given, each bit-identical to a call at that radius alone on the same DeviceCloud. The
    cloud is binned once at the largest radius (unless a DeviceCloud is given). With uniform
    weights, no normals given and no scale space, the PCA of every radius comes from one
    neighbour walk (the features kernel, which shares the moments kernel's PCA): 'variation'
    (with no orientation asked) is that walk's result; the covariance operators take their
    PCA normals from it (built as the moments kernel's normals pass, so the same bits), then
    orient them and run their covariance pass once per radius. Other cases run once per
    radius."""
    if op.name not in MULTI_RADIUS_METHODS:
        raise ValueError(f"a list of radii is for methods {', '.join(MULTI_RADIUS_METHODS)} "
                         f"(and clcurv.features), not {op.name!r}")
    radii, _ = as_radii(radius)
    points, cloud = cloud_points(points)
    if kw["backend"] == "opencl" and cloud is None and len(as_points(points)):
        cloud = DeviceCloud(points, max(radii), device=kw["device"], precision=kw["precision"])
    one_walk = (cloud is not None and kw["weights"] == "uniform" and kw["normals"] is None
                and not kw["scale_space"])
    plain = (one_walk and op.name == "variation" and kw["viewpoint"] is None
             and kw["orient"] in ("auto", None) and not kw["uncertainty"])
    if plain:
        return _variation_list(op, cloud, radii)
    if not one_walk or op.name == "variation":
        return [curvature(points if cloud is None else cloud, r, method=op.name, **kw)
                for r in radii]
    for r in radii:
        cloud.check_radius(r)
    raws = {r: {"normals": v["normals"], "count": c, "status": s}
            for r, (v, c, s) in zip(radii, run_features(cloud, radii, ("normals",),
                                                        anchored=False))}
    token = _PCA_GIVEN.set({"cloud": cloud, "raws": raws})
    try:
        return [curvature(cloud, r, method=op.name, **kw) for r in radii]
    finally:
        _PCA_GIVEN.reset(token)


def _selected(op, points, radius, select, k, kw):
    """:func:`curvature` with ``select='error'``: every radius of ``radius`` with
    ``uncertainty=True``, each binned at its own radius (the largest on ``points`` when it
    is a DeviceCloud), so that each point's outputs are bit for bit those of a call at its
    radius with the largest radius's normals (``orient='normals'``); per point, the radius
    of least predicted error of H (bias ``c r^2``, the leading term of MLS1's and MLS2's
    expansions:
    ``c`` fitted per point, :func:`clcurv.ops.selection.fit_bias`, pooled over the ball of
    the second smallest radius, :func:`clcurv.ops.pooling.pool_bias`, then
    :func:`clcurv.ops.selection.choose`; docs/uncertainty.md). The largest radius
    runs first and its oriented normals orient the others. Each output of the result is
    the chosen radius's; points with no radius of finite H and SE keep the largest's.
    A point without a normal at the largest radius (its status there not OK) has no sign
    for the others: it keeps the largest radius's result (NaN). ``info["select"]``: the
    radii, how often each was chosen, and per point the predicted error
    ``predicted_error`` and the fitted bias coefficient ``bias_coef``."""
    check(select, "select")
    extra = op.foreign_options({"select": True})
    if extra:
        raise ValueError(f"select is not an option of method={op.name!r} (only of "
                         f"{', '.join(repr(m) for m in extra['select'])})")
    if k is not None:
        raise ValueError("select='error' chooses among given radii: give radius=[r1, ...], "
                         "not k")
    radii, multi = as_radii(radius)
    if not multi or len(radii) < 2:
        raise ValueError("select='error' needs at least two radii: radius=[r1, r2, ...]")
    points, cloud = cloud_points(points)
    pts = as_points(points, finite=kw["backend"] != "opencl")
    order = np.argsort(radii)[::-1]                   # the largest first: it orients
    opencl = kw["backend"] == "opencl" and len(pts) > 0
    if opencl and cloud is None:
        cloud = DeviceCloud(pts, max(radii), device=kw["device"], precision=kw["precision"])
    runs, unoriented = {}, None
    for j in order:
        call, where = dict(kw), pts if cloud is None else cloud
        if runs:                    # one orientation: the largest radius's normals
            if unoriented is None:
                ref = runs[order[0]].normals
                unoriented = ~np.all(np.isfinite(ref), axis=1)
                ref = np.where(unoriented[:, None], (0.0, 0.0, 1.0), ref)
            call.update(normals=ref, orient="normals", viewpoint=None)
            # binned at its own radius: the walk scans 27 cells of that radius, not of the
            # largest (a quarter of the largest: 2.3x faster at 1M points)
            where = pts
            if cloud is not None:       # the given DeviceCloud's device and precision
                call["device"] = cloud.device
                call["precision"] = "double" if cloud.dtype == np.float64 else "float"
        runs[j] = curvature(where, radii[j], method=op.name, uncertainty=True, **call)
    up = sorted(range(len(radii)), key=lambda j: radii[j])       # ascending for the fit
    rs = np.array([radii[j] for j in up])
    values = np.stack([runs[j].mean for j in up], axis=1)
    se = np.stack([runs[j].mean_se for j in up], axis=1)
    if unoriented is not None:      # no normal at the largest radius: no sign for the others
        values[unoriented] = np.nan
    # c fitted per point, pooled over the second radius's ball (inverse-variance weights:
    # clcurv.ops.selection's docstring has the measurements), then the choice
    fit = fit_bias(values, se, rs, order=2)
    mean = None if cloud is not None else (
        lambda v, r, w: reference_pooling.ball_mean(pts, v, r, w))
    sel = choose(values, se, rs, *pool_bias(cloud, fit, rs[1], mean=mean), order=2)
    pick = np.where(sel.index >= 0, sel.index, len(up) - 1)      # none usable: the largest
    res = runs[up[-1]]
    for name, v in res.arrays().items():       # the largest's arrays, others' rows put in
        for col, j in enumerate(up[:-1]):
            rows = pick == col
            v[rows] = getattr(runs[j], name)[rows]
    res.radius = rs[pick]
    res.info["select"] = {"radii": rs.tolist(),
                          "chosen": np.bincount(pick, minlength=len(rs)).tolist(),
                          "predicted_error": sel.error, "bias_coef": sel.coef}
    return res


def _variation_list(op, cloud, radii):
    """'variation' at every radius of a list from one walk of the features kernel."""
    names = ("eigenvalue3", "eigenvalue2", "eigenvalue1", "surface_variation", "normals")
    out = []
    for r, (vals, count, status) in zip(radii, run_features(cloud, radii, names)):
        warn_sparse(status, r, op.min_count)
        eig = np.stack([vals[n] for n in names[:3]], axis=1)
        res = _result(op, r, "uniform", count, status,
                      {"normals": vals["normals"], "eigenvalues": eig,
                       "variation": vals["surface_variation"]})
        res.info["orientation"] = None
        out.append(res)
    return out


def _knn(points, radius, k, weights, kernel, scale_space, projections, device, precision,
         backend):
    """(KnnRadii, the largest radius) of a k-NN radius call (radius='knn:K' or k=K)."""
    if isinstance(radius, str):
        k = parse_knn(radius, k)
    elif radius is not None:
        raise ValueError("give either radius or k (or radius='knn:K'), not both")
    for bad, what in ((weights == "density", "weights='density' (every ball holds k points, "
                       "so the weights would be 1/k)"), (kernel == "gaussian",
                      "kernel='gaussian'"), (scale_space, "scale_space"),
                      (projections, "projections"), (backend == "numpy", "backend='numpy'")):
        if bad:
            raise ValueError(f"a k-NN radius does not combine with {what}")
    points, _ = cloud_points(points)
    knn = knn_radii(points, k, device=device, precision=precision)
    return knn, knn.cloud.cell
