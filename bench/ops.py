"""Which operators the bench times, read from the registry (clcurv.operators): a newly
registered operator is timed, checked and tabulated without touching the bench."""
from clcurv.operators import OPERATORS

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
