"""Which operators the bench times, read from the registry (clcurv.ops.registry): a newly
registered operator is timed, checked and tabulated without touching the bench; and the
public calls of the bench's lead table (:func:`call`)."""
import clcurv
from clcurv.api.curvature import _orientation
from clcurv.ops.registry import OPERATORS

_ORIENT_NONE = "_orient_none"

#: the operator of the headline figures: normals + surface variation, one moments pass
HEADLINE = "variation"
#: timed end to end from the points alone, orient=None (their kernel reads no normals)
POINT_OPS = tuple(m for m, op in OPERATORS.items() if not op.kernel.reads_normals)
#: timed with the exact normals given (normals=: the operator alone, no PCA pass)
NORMAL_OPS = tuple(m for m, op in OPERATORS.items() if op.kernel.reads_normals)
#: of those, the signed ones (MLS2: signed k1 >= k2) and the unsigned ones (magnitudes: the
#: covariance operators)
SIGNED_NORMAL_OPS = tuple(m for m in NORMAL_OPS if OPERATORS[m].signed)
UNSIGNED_NORMAL_OPS = tuple(m for m in NORMAL_OPS if not OPERATORS[m].signed)
#: of those, the ones that also run with orient=None (only the sign of a normal matters:
#: without normals their kernel takes its solver's own sign); timed as '<name>_orient_none'
SIGN_OPS = tuple(m for m in NORMAL_OPS if OPERATORS[m].normals != "values")
#: every run timed against clcurv.normals in interleaved pairs: NORMAL_OPS with normals=,
#: then SIGN_OPS with orient=None
PAIRED = NORMAL_OPS + tuple(m + _ORIENT_NONE for m in SIGN_OPS)


def orient_none(m):
    """The timing key of operator ``m`` run with orient=None."""
    return m + _ORIENT_NONE


def base(key):
    """The operator of a timing key: 'mls2_orient_none' -> 'mls2'."""
    return key[:-len(_ORIENT_NONE)] if key.endswith(_ORIENT_NONE) else key


def label(key):
    """'mls2_orient_none' -> 'mls2 orient=None'; an operator's name stays."""
    return key if key == base(key) else f"{base(key)} orient=None"


# ----------------------------------------------------------------------------- public calls
SS_ITERATIONS = 5         # scale-space iterations timed (and the paper's pipeline's)
#: the rows of the lead table: every operator, clcurv.normals, and the paper's pipeline
#: curvature(method="mls2", scale_space=SS_ITERATIONS)
CALL_ROWS = tuple(OPERATORS) + ("normals", "pipeline")
#: the arguments each row is called with: the defaults, orient=None, the exact normals
VARIANTS = ("default", "orient_none", "normals")
VARIANT_TEXT = {"default": "", "orient_none": ", orient=None", "normals": ", normals=N"}


def call(row, variant, pts, r, nrm=None, device=None):
    """The public call of a lead-table row, with the arguments of ``variant`` (VARIANTS)."""
    kw = {"device": device}
    if variant == "orient_none":
        kw["orient"] = None
    elif variant == "normals":
        kw["normals"] = nrm
    if row == "normals":
        return lambda: clcurv.normals(pts, r, **kw)
    if row == "pipeline":
        return lambda: clcurv.curvature(pts, r, method="mls2", scale_space=SS_ITERATIONS, **kw)
    return lambda: clcurv.curvature(pts, r, method=row, **kw)


def call_text(row, variant="default"):
    """'curvature(P, r, method="mls2")' and the like."""
    extra = VARIANT_TEXT[variant]
    if row == "normals":
        return f"normals(P, r{extra})"
    if row == "pipeline":
        return f'curvature(P, r, method="mls2", scale_space={SS_ITERATIONS}{extra})'
    return f'curvature(P, r, method="{row}"{extra})'


def default_orientation(row):
    """What the default orient='auto' does for a row given neither normals nor a viewpoint
    (clcurv.api.curvature's own rule): 'mst' (Hoppe's propagation on the device) or None."""
    signed = True if row in ("normals", "pipeline") else OPERATORS[row].signed
    return _orientation("auto", None, None, signed)
