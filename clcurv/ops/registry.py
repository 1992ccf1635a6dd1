"""The operator registry: one spec per method of :func:`clcurv.curvature`, declared once.

A spec (:class:`Operator`) holds everything the rest of the package needs to know about a
method: its kernel (:class:`Kernel`: file, entry point, defines, record layout, minimum
neighbour count), how it uses normals, its outputs (:class:`Output`: result attribute,
file field names, unit, sign), its float64 reference and the host step that turns the
kernel's raw fields into the result. :mod:`clcurv.api.curvature`, :mod:`clcurv.cli.main`,
:mod:`clcurv.render`, the bench, the tests and the README's methods table
(tests/test_registry.py) iterate :data:`OPERATORS`; :func:`clcurv.ops.driver.run_kernel`
runs any kernel.

Adding an operator: one kernel (``kernels/``, taking ``OPERATOR_ARGS`` and writing its
record columns ``COL_*``), one reference function (:mod:`clcurv.reference.operators`), one
:class:`Operator` below, and its analytic test.

Conventions of every output: lengths in the points' unit, curvatures in 1/length, normals
outward when an orientation was asked for, a surface bending away from its normal has
positive curvature (a sphere of radius R: k1 = k2 = H = +1/R), k1 >= k2.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from clcurv._shared.constants import MIN_COUNT_MLS2, MIN_COUNT_PCA, OK, record_selector
from clcurv._shared.options import taken_by
from clcurv.ops.features import FEATURES, layouts, program_defines
from clcurv.ops.knn_radius import knn_levels, program_defines as knn_program_defines
from clcurv.reference import operators as reference
from clcurv.runtime.program import build, local_size, precision_defines


# ------------------------------------------------------------------------------------------
# spec types
# ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Kernel:
    """One operator kernel: an entry point of a ``kernels/*.cl`` file and its record.

    ``layout`` maps a raw field to its record column (an int) or columns (a slice); it
    reaches the kernel as ``-D COL_<FIELD>=<REAL16 selector>`` (``s012``), and
    :func:`clcurv.grid.cloud.split_records` reads the record with the same table. Every layout
    has ``count`` and ``status``.
    """
    name: str
    file: str
    entry: str
    layout: Mapping[str, int | slice]
    min_count: int
    defines: Mapping[str, int] = field(default_factory=dict)
    reads_normals: bool = False
    #: the error record's layout (``uncertainty=True``: standard errors from the same walk,
    #: a second record per point in the kernel's argument after ``OPERATOR_ARGS``), or None
    errors: Mapping[str, int | slice] | None = None

    def build_defines(self):
        """The kernel's build options: its defines, MIN_COUNT and the record columns."""
        cols = {f"COL_{k.upper()}": record_selector(v) for k, v in self.layout.items()}
        # the columns' numbers and the mask of those written, for the kernels that store
        # records from column vectors (kernels/lanes_records.h)
        cix, used = {}, 0
        for k, v in self.layout.items():
            first, width = (v, 1) if isinstance(v, int) else (v.start, v.stop - v.start)
            cix[f"CIX_{k.upper()}"] = first
            used |= ((1 << width) - 1) << first
        return dict(self.defines, MIN_COUNT=self.min_count, **cols, **cix, REC_USED=hex(used))

    def width(self, name):
        v = self.layout[name]
        return 1 if isinstance(v, int) else v.stop - v.start

    def error_defines(self):
        """The build options of the error record (``UNCERTAINTY=1``): ``COL_<FIELD>`` of its
        real fields, ``ECOL_COUNT`` and ``ECOL_STATUS``."""
        if self.errors is None:
            raise ValueError(f"the {self.name} kernel has no error record")
        out = {"UNCERTAINTY": 1}
        for k, v in self.errors.items():
            prefix = "ECOL" if k in ("count", "status") else "COL"
            out[f"{prefix}_{k.upper()}"] = record_selector(v)
        return out


@dataclass(frozen=True)
class Output:
    """One per-point output of a method: the :class:`~clcurv.api.result.CurvatureResult`
    attribute ``name`` ((N,) or (N, width) float64), its unit, whether it is signed, its
    field name in files (``None``: not written; a width-3 field gets _x, _y, _z) and whether
    a file gets it by default (``by_default``; else only when asked, ``fields=``:
    :meth:`Operator.chosen_fields`)."""
    name: str
    width: int
    unit: str
    doc: str
    signed: bool = False
    file: str | None = None
    by_default: bool = True

    def file_fields(self):
        if self.file is None:
            return []
        return [self.file] if self.width == 1 else [f"{self.file}_{a}" for a in "xyz"]


@dataclass(frozen=True)
class Operator:
    """One method of :func:`clcurv.curvature`.

    ``normals``: how the operator uses normals --
      'none'   it needs none (its ``normals`` output is oriented only if asked);
      'sign'   their sign only (orientation of the PCA normal; signed outputs);
      'values' their values: the normals you pass (normalised), else the PCA normals,
               oriented when the method is signed (MLS0 alone falls back on its PCA
               normal). 2dcov2 and 3dcov (option ``align_normals``, the kernel's
               ALIGN_NORMALS) align each neighbour's normal with the query point's where
               clcurv estimated the normals itself, so that their values do not depend on
               the PCA signs; the normals you pass are used as given (then 2dcov2 is
               PCL's PrincipalCurvaturesEstimation), unless ``align_normals=True``.
    ``options``: the keyword arguments of :func:`clcurv.curvature` it takes beyond the
    common ones (others given raise), read from the options' declaration
    (:func:`clcurv._shared.options.taken_by`: each option names its methods).
    ``reference(points, r, normals, weights, **options)`` returns the same raw fields as
    the kernel (float64); ``finish(raw, points, r,
    normals_used, user_normals)`` turns raw fields into result attributes. ``flip(raw,
    mask)``, for a 'sign' method, turns the raw fields of a run without reference normals
    into those of the opposite normal where ``mask`` is True, so that the orientation can
    use the method's own normals afterwards instead of a PCA pass first. ``fields``: the
    kernel's record fields that ``finish`` reads (None: all), the only ones brought back
    from the device. ``errors``: the outputs of ``uncertainty=True`` (standard errors and
    roughness, :class:`Output` s; empty: the method has none), which
    ``finish_errors(raw, r)`` forms from the kernel's error record, built with
    ``error_defines`` (the covariance operators, whose kernel has none: from the error
    record of their PCA normals' pass, :data:`PCA_NORMALS_DEFINES`).
    """
    name: str
    title: str
    formula: str
    kernel: Kernel
    outputs: tuple
    normals: str
    finish: Callable
    reference: Callable
    flip: Callable | None = None
    fields: tuple | None = None
    errors: tuple = ()
    finish_errors: Callable | None = None
    #: build options of the error record (``NOISE_WALK=0``: no quadric walk where no
    #: output needs the point's own noise)
    error_defines: Mapping[str, int] = field(default_factory=dict)

    @property
    def signed(self):
        """True when some output carries the sign of curvature (needs oriented normals)."""
        return any(o.signed for o in self.outputs)

    @property
    def options(self):
        """The method-specific options it takes (:func:`clcurv._shared.options.taken_by`)."""
        return taken_by(self.name)

    @property
    def min_count(self):
        return self.kernel.min_count

    def foreign_options(self, given):
        """The names among ``given`` (option name -> whether the caller set it) that this
        method does not take, each with the methods that do take it."""
        return {k: [m for m, op in OPERATORS.items() if k in op.options]
                for k, v in given.items() if v and k not in self.options}

    def has_errors(self, res):
        """Does the result ``res`` (a CurvatureResult of this method) hold the error
        outputs (``uncertainty=True``)?"""
        return bool(self.errors) and getattr(res, self.errors[0].name) is not None

    def file_fields(self, uncertainty=False):
        """File field name -> (output name, column or None), in the output order (then the
        error outputs with ``uncertainty``)."""
        out = {}
        for o in self.outputs + (self.errors if uncertainty else ()):
            names = o.file_fields()
            for c, f in enumerate(names):
                out[f] = (o.name, c if len(names) > 1 else None)
        return out

    def chosen_fields(self, wanted=None, extra=(), uncertainty=False):
        """The names of the file fields to write, in file order (:meth:`file_fields`, then
        ``extra``, e.g. ``knn_radius``, then :data:`COMMON_FILE_FIELDS`, then ``"normals"``),
        for the ``fields`` option's value ``wanted``:

        * None (the default) or ``"default"``: :meth:`default_fields`;
        * ``"all"``: every field;
        * names, among which ``"all"`` and ``"default"`` stand for those sets and the stem
          of a width-3 field (``"dir1"``) for its three components (``dir1_x, _y, _z``).

        With ``uncertainty`` the error outputs' fields (:attr:`errors`) are among them, and
        among the default ones.

        ValueError naming the unknown names and the available ones."""
        every = (list(self.file_fields(uncertainty)) + list(extra) + list(COMMON_FILE_FIELDS)
                 + ["normals"])
        if wanted is None:
            wanted = [DEFAULT_FIELDS]
        elif isinstance(wanted, str):
            wanted = [wanted]
        stems = {o.file: o.file_fields() for o in self.outputs
                 if o.file is not None and o.width > 1}
        take, unknown = set(), []
        for w in wanted:
            if w == ALL_FIELDS:
                take.update(every)
            elif w == DEFAULT_FIELDS:
                take.update(self.default_fields(extra, uncertainty))
            elif w in stems:
                take.update(stems[w])
            elif w in every:
                take.add(w)
            else:
                unknown.append(w)
        if unknown:
            raise ValueError(f"unknown field(s) {', '.join(sorted(unknown))} for method "
                             f"{self.name}; available: {ALL_FIELDS}, {DEFAULT_FIELDS}, "
                             f"{', '.join(every)}")
        return [f for f in every if f in take]

    def default_fields(self, extra=(), uncertainty=False):
        """The file fields written unless ``fields=`` says otherwise: the operator's outputs
        marked ``by_default`` (its curvatures or surface variation; not the principal
        directions, 6 of MLS2's 13 real fields, which few LiDAR uses need), ``extra`` (the
        ``knn_radius`` of a k-NN radius), ``neighbours``, ``status`` and ``normals``; with
        ``uncertainty`` the error outputs too (asked for, so written)."""
        outs = self.outputs + (self.errors if uncertainty else ())
        own = [f for o in outs if o.by_default for f in o.file_fields()]
        return own + list(extra) + list(COMMON_FILE_FIELDS) + ["normals"]


# ------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------

#: the moments kernel's error record (kernels/moments.cl, UNCERTAINTY): the PCA normal's
#: angular SE, the plane's roughness, the quadric's noise sigma_hat, and the weights of the
#: point's own noise and of its neighbours' in MLS0/MLS1's H (:func:`_finish_h_errors`)
PCA_ERRORS = {"normal_se": 0, "roughness": 1, "sigma": 2, "own": 3, "others": 4, "count": 5,
              "status": 6}

#: the build options of the PCA normals' pass (the orientation, the covariance operators'
#: normals): one-pass sums (no anchor: the normals' bits as the features walk gives them),
#: and with its error record no quadric walk
PCA_NORMALS_DEFINES = {"REFINE_L0": 0, "NOISE_WALK": 0}

#: the moments kernel: PCA normal, eigenvalues, surface variation, barycenter shift o - p
PCA = Kernel("moments", "moments.cl", "moments",
             {"normals": slice(0, 3), "eigenvalues": slice(3, 6), "variation": 6,
              "shift": slice(7, 10), "count": 10, "status": 11},
             MIN_COUNT_PCA, {"REFINE_L0": 1}, errors=PCA_ERRORS)


def _cov_kernel(name, code):
    ne = 3 if code == 3 else 2
    # ALIGN_NORMALS: 0 uses the neighbours' normals as given, 1 aligns each with the query
    # point's (kernels/covariances.cl); the host sets it per call (clcurv.api.curvature)
    return Kernel(name, "covariances.cl", "covariance",
                  {"eigenvalues": slice(0, ne), "k1": 3, "k2": 4, "dir1": slice(5, 8),
                   "dir2": slice(8, 11), "count": 11, "status": 12},
                  MIN_COUNT_PCA, {"COV_METHOD": code, "ALIGN_NORMALS": 0},
                  reads_normals=True)


#: MLS2's error record (kernels/mls2.cl, UNCERTAINTY): the standard errors of H, K, k1, k2
#: and of the fitted normal's angle, and the roughness (clcurv/reference/uncertainty.py)
MLS2_ERRORS = {"mean_se": 0, "gaussian_se": 1, "k1_se": 2, "k2_se": 3, "normal_se": 4,
               "roughness": 5, "count": 6, "status": 7}

MLS2 = Kernel("mls2", "mls2.cl", "mls2",
              {"shift": slice(0, 3), "k1": 3, "k2": 4, "dir1": slice(5, 8),
               "dir2": slice(8, 11), "normals": slice(11, 14), "count": 14, "status": 15},
              MIN_COUNT_MLS2, reads_normals=True, errors=MLS2_ERRORS)


# ------------------------------------------------------------------------------------------
# outputs
# ------------------------------------------------------------------------------------------

_NORMALS_PCA = Output("normals", 3, "1", "unit PCA normals (eigenvector of the smallest "
                      "eigenvalue), oriented as `orient` says")
_EIG_PCA = Output("eigenvalues", 3, "length^2", "eigenvalues l0 <= l1 <= l2 (ascending) of "
                  "the weighted covariance sum w (q - o)(q - o)^T / sum w")
_VARIATION = Output("variation", 1, "1", "surface variation l0 / (l0 + l1 + l2), in [0, 1/3]",
                    file="surface_variation")
_MEAN = Output("mean", 1, "1/length", "signed mean curvature H", signed=True,
               file="mean_curvature")


# the error outputs of uncertainty=True (the model, its assumptions and every formula:
# clcurv/reference/uncertainty.py; docs/uncertainty.md)
_SE_MEAN = Output("mean_se", 1, "1/length", "standard error of H (noise along the normal, "
                  "first order; the operator's bias not included)", file="mean_curvature_se")
_SE_NORMAL_PCA = Output("normal_se", 1, "rad", "angular standard error of the PCA normal "
                        "(first-order perturbation of the eigenvector)", file="normal_se")
_ROUGH_PLANE = Output("roughness", 1, "length", "residual RMS to the regression plane, "
                      "sqrt(l0 n_eff / (n_eff - 3)) (noise and the curvature's spread)",
                      file="roughness")
_PCA_ERRORS = (_SE_NORMAL_PCA, _ROUGH_PLANE)
_MLS2_ERRORS = (
    _SE_MEAN,
    Output("gaussian_se", 1, "1/length^2", "standard error of K", file="gaussian_curvature_se"),
    Output("k1_se", 1, "1/length", "standard error of k1 (below its coverage at umbilics, "
           "docs/uncertainty.md)", file="k1_se"),
    Output("k2_se", 1, "1/length", "standard error of k2", file="k2_se"),
    Output("normal_se", 1, "rad", "angular standard error of the fitted normal",
           file="normal_se"),
    Output("roughness", 1, "length", "residual RMS to the fitted quadric, sigma_hat = "
           "sqrt(RSS / nu) (degrees of freedom corrected)", file="roughness"))


def _magnitudes(unit_eig):
    return (Output("k1", 1, "1/length", "larger curvature magnitude k1 >= k2 >= 0", file="k1"),
            Output("k2", 1, "1/length", "smaller curvature magnitude", file="k2"),
            Output("dir1", 3, "1", "unit principal direction of k1 (tangent)", file="dir1",
                   by_default=False),
            Output("dir2", 3, "1", "unit principal direction of k2 = normal x dir1",
                   file="dir2", by_default=False),
            Output("eigenvalues", unit_eig[0], unit_eig[1], unit_eig[2]),
            Output("normals", 3, "1", "the unit normals the operator used (yours, "
                   "normalised, else the oriented PCA normals)"))


# ------------------------------------------------------------------------------------------
# host finishing steps (raw kernel or reference fields -> result attributes, float64)
# ------------------------------------------------------------------------------------------

def _pca_common(raw, n):
    return {"normals": n, "eigenvalues": raw["eigenvalues"], "variation": raw["variation"]}


def _finish_variation(raw, pts, r, n, user):
    return _pca_common(raw, n)


def _finish_mls0(raw, pts, r, n, user):
    shift = raw["shift"]
    nref = user if user is not None else n
    mean = -4.0 * np.einsum("ij,ij->i", shift, nref) / (r * r)
    mean[raw["status"] != OK] = np.nan
    return dict(_pca_common(raw, n), mean=mean, points=pts + shift)


def _finish_mls1(raw, pts, r, n, user):
    along = np.einsum("ij,ij->i", raw["shift"], n)
    return dict(_pca_common(raw, n), mean=-4.0 * along / (r * r),
                points=pts + along[:, None] * n)


def _finish_pca_errors(raw, r):
    return {"normal_se": raw["normal_se"], "roughness": raw["roughness"]}


def _finish_h_errors(raw, r):
    """MLS0/MLS1: SE(H) = 4 / r^2 sqrt(sigma_p^2 (1 - w_p / W)^2 + s^2 (W2 - w_p^2) / W^2),
    sigma_p the quadric's noise (``sigma``), s the plane's roughness, ``own`` and ``others``
    the two weights (kernels/moments.cl)."""
    se = 4.0 / (r * r) * np.sqrt(raw["sigma"] ** 2 * raw["own"]
                                 + raw["roughness"] ** 2 * raw["others"])
    return dict(_finish_pca_errors(raw, r), mean_se=se)


def _finish_mls2_errors(raw, r):
    return {k: raw[k] for k in ("mean_se", "gaussian_se", "k1_se", "k2_se", "normal_se",
                                "roughness")}


def _finish_cov(raw, pts, r, n, user):
    return {k: raw[k] for k in ("k1", "k2", "dir1", "dir2", "eigenvalues")} | {"normals": n}


def _flip_mls2(raw, mask):
    """MLS2's raw fields for the opposite normal where ``mask``: n -> -n, (k1, k2) ->
    (-k2, -k1) and dir1 <-> dir2 (so that (dir1, dir2, n) stays right-handed: with
    n x dir1 = dir2, (-n) x dir2 = dir1); the shift (the projection) is unchanged."""
    m = np.flatnonzero(mask)
    raw["normals"][m] *= -1
    k1, k2 = raw["k1"][m], raw["k2"][m]
    raw["k1"][m], raw["k2"][m] = -k2, -k1
    d1, d2 = raw["dir1"][m], raw["dir2"][m]
    raw["dir1"][m], raw["dir2"][m] = d2, d1
    if "k1_se" in raw:                  # uncertainty=True: SE(k1) goes with k1
        e1, e2 = raw["k1_se"][m], raw["k2_se"][m]
        raw["k1_se"][m], raw["k2_se"][m] = e2, e1
    return raw


def _finish_mls2(raw, pts, r, n, user):
    k1, k2 = raw["k1"], raw["k2"]
    return {"k1": k1, "k2": k2, "dir1": raw["dir1"], "dir2": raw["dir2"],
            "normals": raw["normals"], "points": np.add(pts, raw["shift"], out=raw["shift"]),
            "mean": 0.5 * (k1 + k2), "gaussian": k1 * k2}


# ------------------------------------------------------------------------------------------
# reference adapters (clcurv.reference.operators -> the kernel's raw fields)
# ------------------------------------------------------------------------------------------

def _ref_moments(points, r, normals, weights):
    return reference.moments(points, r, weights=weights)


def _ref_cov(method):
    def run(points, r, normals, weights, align_normals=False):
        return reference.covariance_ops(points, r, normals, method, weights=weights,
                                        align=align_normals)
    run.__name__ = f"_ref_{method}"
    return run


def _ref_mls2(points, r, normals, weights, kernel="ball", h=None):
    if normals is None:
        raise ValueError("backend='numpy' MLS2 needs oriented normals (orient must not be None)")
    out = reference.mls2(points, r, normals, weights=weights, kernel=kernel, h=h)
    out["shift"] = out.pop("points") - points
    return out


# ------------------------------------------------------------------------------------------
# the registry
# ------------------------------------------------------------------------------------------

def _cov(name, code, title, formula, eig_unit, eig_doc):
    k = _cov_kernel(name, code)
    return Operator(name, title, formula, k, _magnitudes((k.width("eigenvalues"), eig_unit,
                                                         eig_doc)),
                    "values", _finish_cov, _ref_cov(name), errors=_PCA_ERRORS,
                    finish_errors=_finish_pca_errors)


OPERATORS = {op.name: op for op in (
    Operator("variation", "surface variation l0/(l0+l1+l2) (Pauly)",
             "Theorem 4: r^2/16((k1^2+k2^2)/2 - k1k2/3)", PCA,
             (_VARIATION, _NORMALS_PCA, _EIG_PCA), "none", _finish_variation, _ref_moments,
             fields=("normals", "eigenvalues", "variation"), errors=_PCA_ERRORS,
             finish_errors=_finish_pca_errors, error_defines={"NOISE_WALK": 0}),
    Operator("mls0", "barycenter shift", "H = 4<p - o, n>/r^2 (Lemma 2)", PCA,
             (_MEAN, Output("points", 3, "length", "the barycenter o of the ball"),
              _VARIATION, _NORMALS_PCA, _EIG_PCA), "values", _finish_mls0, _ref_moments,
             errors=(_SE_MEAN,) + _PCA_ERRORS, finish_errors=_finish_h_errors),
    Operator("mls1", "projection on the PCA plane", "H = 4<p - p', n>/r^2 (Theorem 5)", PCA,
             (_MEAN, Output("points", 3, "length", "p', p projected on the PCA regression "
                            "plane"), _VARIATION, _NORMALS_PCA, _EIG_PCA),
             "sign", _finish_mls1, _ref_moments, errors=(_SE_MEAN,) + _PCA_ERRORS,
             finish_errors=_finish_h_errors),
    _cov("2dcov1", 1, "covariance of <d, n>(<d, t1>, <d, t2>) (Berkmann & Caelli)",
         "Theorem 1", "length^4", "eigenvalues (descending) of the count-normalised "
         "covariance of <d, n>(<d, t1>, <d, t2>), d = q - p"),
    _cov("2dcov2", 2, "covariance of the neighbours' normals projected on the tangent plane "
         "(PCL)", "Theorem 2", "1", "eigenvalues (descending) of the count-normalised "
         "covariance of the neighbours' unit normals projected on the tangent plane (PCL's "
         "pc1, pc2)"),
    _cov("3dcov", 3, "covariance of the neighbours' normals", "Theorem 3", "1",
         "eigenvalues (descending) of the count-normalised covariance of the neighbours' "
         "unit normals"),
    Operator("mls2", "weighted quadric fit in the PCA frame; shape operator",
             "operator 7, a fourth-order projection", MLS2,
             (_MEAN, Output("gaussian", 1, "1/length^2", "Gaussian curvature K = k1 k2",
                            signed=True, file="gaussian_curvature"),
              Output("k1", 1, "1/length", "signed principal curvature, k1 >= k2", signed=True,
                     file="k1"),
              Output("k2", 1, "1/length", "signed principal curvature", signed=True,
                     file="k2"),
              Output("dir1", 3, "1", "unit principal direction of k1 (tangent)", file="dir1",
                     by_default=False),
              Output("dir2", 3, "1", "unit principal direction of k2 = normal x dir1",
                     file="dir2", by_default=False),
              Output("normals", 3, "1", "unit normals of the fitted quadric at the "
                     "projection, oriented as `orient` says"),
              Output("points", 3, "length", "the MLS2 projection of p")),
             "sign", _finish_mls2, _ref_mls2, flip=_flip_mls2, errors=_MLS2_ERRORS,
             finish_errors=_finish_mls2_errors),
)}

#: the method names, in the registry's order
METHODS = tuple(OPERATORS)

#: per-point fields every result has, beside the operator's outputs
COMMON_FILE_FIELDS = ("neighbours", "status")
#: the ``fields`` values (and ``--fields`` words) that stand for every file field and for
#: the default ones (:meth:`Operator.chosen_fields`)
ALL_FIELDS, DEFAULT_FIELDS = "all", "default"


def signed_file_fields():
    """File field names that some operator writes signed (a diverging colour map)."""
    return frozenset(f for op in OPERATORS.values() for o in op.outputs if o.signed
                     for f in o.file_fields())


def program_variants(precision_defines):
    """(file, defines) of every program clcurv builds on a device with
    ``precision_defines`` (clcurv.runtime.program.precision_defines): each operator kernel (with
    every optional branch switched on) and the support kernels. The tests build them all."""
    base = dict(precision_defines)
    out = [(f, base) for f in ("grid.cl", "density.cl", "gather.cl", "knn.cl", "forest.cl",
                               "anchor.cl")]
    out.append(("scale_space.cl", dict(base, DENSITY=1, GAUSSIAN=0)))
    out += [("ball_mean.cl", dict(base, WEIGHTED=w, ROW_PRUNE=1)) for w in (0, 1)]
    layout = MLS2.build_defines()
    split = dict(base, NF=6, COL_COUNT=layout["COL_COUNT"], COL_STATUS=layout["COL_STATUS"],
                 **{f"{a}{k}": 1 for k in range(6) for a in "SW"})
    out.append(("records.cl", dict(split, SPLIT_HOST=0)))
    balls = dict(NB=4, REC_BALL=3, REC_BLOCK=128)     # features.cl's REC_BALLS
    out.append(("records.cl", dict(split, SPLIT_HOST=0, **balls)))
    if base.get("REAL_IS_DOUBLE"):      # the split into float64 host arrays needs fp64
        out.append(("records.cl", dict(split, SPLIT_HOST=1)))
        out.append(("records.cl", dict(split, SPLIT_HOST=1, **balls)))
    for k in {op.kernel.name: op.kernel for op in OPERATORS.values()}.values():
        gaussian = any("kernel" in op.options for op in OPERATORS.values() if op.kernel is k)
        on = {d: 1 for d in ("ALIGN_NORMALS",) if d in k.defines}
        out.append((k.file, dict(base, **k.build_defines(), DENSITY=1, GAUSSIAN=int(gaussian),
                                 REF_NORMALS=int(k.reads_normals), POINT_RADIUS=0,
                                 ROW_PRUNE=1) | on))
        if k.errors is not None:        # uncertainty=True: the error record, both weightings
            for density in (0, 1):
                out.append((k.file, dict(base, **k.build_defines(), **k.error_defines(),
                                         DENSITY=density, GAUSSIAN=int(gaussian) * (1 - density),
                                         REF_NORMALS=int(k.reads_normals), POINT_RADIUS=0,
                                         ROW_PRUNE=1) | on))
        # the k-NN radius (kernels/radius.h): per-point balls, which exclude DENSITY
        out.append((k.file, dict(base, **k.build_defines(), DENSITY=0, GAUSSIAN=0,
                                 REF_NORMALS=int(k.reads_normals), POINT_RADIUS=1)))
    for group in layouts(tuple(FEATURES)):               # clcurv.features: every column
        out.append(("features.cl", dict(base, **program_defines(group, 4))))
        out.append(("features.cl", dict(base, **program_defines(group, 4,
                                                                one_buffer=True))))
        out.append(("features.cl", dict(base, **program_defines(group, 1, True))))
    # the covariance operators' PCA normals of several radii (clcurv.api.curvature._radius_list)
    out.append(("features.cl", dict(base, **program_defines(layouts(("normals",))[0], 4,
                                                             anchored=False))))
    out.append(("knn_radius.cl",
                dict(base, **knn_program_defines(30, knn_levels(30, int(base["VW"]))))))
    return out


def tuning(device, precision="float"):
    """The device-dependent choices clcurv makes on ``device``, for reports: ``VW`` (points
    per work-item: 8 on CPU devices, whose compilers vectorise a work-item's explicit
    vectors, else 4; from the device type query), ``MASKED_SUMS``
    (:func:`clcurv.runtime.program.masked_sums`), ``PCA_FMA``
    (:func:`~clcurv.runtime.program.fused_sums`), ``FEATURES_BUF``
    (:func:`~clcurv.runtime.program.features_buffer`) and ``work_group``, the work-group
    size :func:`~clcurv.runtime.program.local_size` gives every kernel of
    :func:`program_variants` (queried: the kernel's maximum and preferred multiple on this
    device, capped at launch's default 128). Some calls pass a smaller cap
    (clcurv.orient.graph.CPU_GROUP: knn_graph on CPU devices)."""
    base = precision_defines(device, precision)
    sizes = {}
    for file, defines in program_variants(base):
        for k in build(device, file, defines).program.all_kernels():
            sizes[k.function_name] = local_size(device, k)
    return {"VW": base["VW"], "MASKED_SUMS": base["MASKED_SUMS"], "PCA_FMA": base["PCA_FMA"],
            "FEATURES_BUF": base["FEATURES_BUF"], "work_group": sizes}
