"""The contract between the kernels and the host: constants defined once in Python
(clcurv._shared.constants, the operator registry) and nothing else.

- every upper-case identifier a kernel uses is defined in the kernels themselves (macros,
  types), an OpenCL built-in, or provided by the host as a build option;
- a kernel built without one of the host's constants does not compile (no silent default);
- each registered kernel's record layout fits the record, has no overlapping columns, has
  count and status, and names every COL_* column its kernel source writes.
"""
import re

import numpy as np
import pyopencl as cl
import pytest

from clcurv._shared import constants
from clcurv.ops.registry import OPERATORS, program_variants
from clcurv.runtime.program import kernels_dir

# OpenCL C built-ins and keywords that look like macros
BUILTINS = {"NAN", "INFINITY", "FLT_MAX", "FLT_EPSILON", "FLT_MIN", "DBL_MAX", "DBL_EPSILON",
            "DBL_MIN", "CLK_LOCAL_MEM_FENCE", "CLK_GLOBAL_MEM_FENCE", "OPENCL", "EXTENSION",
            "M_PI", "M_PI_F", "MAXFLOAT", "HUGE_VALF"}
PRECISION = {"REAL_IS_DOUBLE": 0, "VW": 8, "MASKED_SUMS": 1, "PCA_FMA": 1}


def sources():
    return {p.name: p.read_text() for p in sorted(kernels_dir().glob("*.[ch]*"))
            if p.suffix in (".cl", ".h")}


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    return re.sub(r'"[^"\n]*"', " ", text)            # #error messages


TYPE = r"(?:REALV|REAL[234]?|IREALV|IREAL|uint2?|int|uchar|size_t|float|double|eig3_v3_v)"


def defined_in_kernels(texts):
    """Macros #defined in the sources, their parameters, typedef names, and upper-case
    variables (declared after a type, or assigned to)."""
    names = set()
    for t in texts:
        names.update(re.findall(TYPE + r"\s*\*?\s*(?:const\s+)?\*?\s*([A-Z]\w*)", t))
        names.update(re.findall(r"\b([A-Z]\w*)\s*=(?!=)", t))
        for m in re.finditer(r"#define\s+(\w+)(\(([^)]*)\))?", t):
            names.add(m.group(1))
            if m.group(3):
                names.update(a.strip() for a in m.group(3).split(","))
        names.update(re.findall(r"typedef\b[^;]*?\b(\w+)\s*;", t))
    return names


def host_provided():
    names = set(constants.kernel_defines()) | set(PRECISION)
    for _, defines in program_variants(PRECISION):
        names |= set(defines)
    return names


def test_kernels_use_only_constants_the_host_provides():
    texts = [strip_comments(t) for t in sources().values()]
    used = set()
    for t in texts:
        used |= set(re.findall(r"\b([A-Z][A-Z0-9_]*[A-Z0-9])\b", t))
    known = defined_in_kernels(texts) | host_provided() | BUILTINS
    # the three-letter vector types are lower case; what remains must be explained
    unknown = sorted(u for u in used - known if not u.startswith("CL_"))
    assert not unknown, f"kernels use constants the host does not provide: {unknown}"


def test_no_kernel_redefines_a_host_constant():
    texts = [strip_comments(t) for t in sources().values()]
    redefined = defined_in_kernels(texts) & (set(constants.kernel_defines()) | {"MIN_COUNT"})
    assert not redefined, f"host constants #defined in a kernel: {sorted(redefined)}"


@pytest.mark.parametrize("missing", sorted(constants.kernel_defines()))
def test_build_fails_without_each_host_constant(device, missing):
    """A kernel file built without one of clcurv._shared.constants' values must not compile."""
    opts = dict(constants.kernel_defines(), **PRECISION)
    del opts[missing]
    kdir = kernels_dir()
    src = (kdir / "gather.cl").read_text()
    options = ["-I", str(kdir)] + [f"-D{k}={v}" for k, v in opts.items()]
    with pytest.raises(cl.Error):
        cl.Program(device.context, src).build(options=options)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_record_layouts_fit_and_match_their_kernel(name):
    k = OPERATORS[name].kernel
    layouts = [k.layout] + ([k.errors] if k.errors is not None else [])
    for layout in layouts:             # the record, and the error record (uncertainty)
        assert {"count", "status"} <= set(layout)
        cols = []
        for field in layout:
            v = layout[field]
            cols += [v] if isinstance(v, int) else list(range(v.start, v.stop))
        assert len(cols) == len(set(cols)), f"{name}: overlapping record columns"
        assert 0 <= min(cols) and max(cols) < constants.RECORD_WIDTH
    src = strip_comments((kernels_dir() / k.file).read_text())
    written = {c[len("COL_"):].lower() for c in re.findall(r"\bCOL_[A-Z0-9_]+\b", src)}
    named = set(k.layout) | set(k.errors or ())
    assert written <= named, f"{k.file} writes columns {written - named} " \
                             f"that the {name} layouts lack"
    if k.errors is not None:           # the error record's own count and status columns
        assert {"ECOL_COUNT", "ECOL_STATUS"} <= set(re.findall(r"\bECOL_[A-Z]+\b", src))


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_every_output_is_documented_with_a_unit(name):
    op = OPERATORS[name]
    assert op.outputs and all(o.unit and o.doc for o in op.outputs)
    assert "normals" in {o.name for o in op.outputs}
    widths = {o.name: o.width for o in op.outputs}
    for field, v in op.kernel.layout.items():
        if field in widths and field not in ("normals",):
            assert op.kernel.width(field) == widths[field], (name, field)


def test_status_codes_and_minimum_counts_have_one_source():
    from clcurv.reference import operators as reference
    from clcurv.api import result
    assert (result.OK, result.TOO_FEW, result.DEGENERATE, result.SINGULAR) == (
        constants.OK, constants.TOO_FEW, constants.DEGENERATE, constants.SINGULAR)
    assert OPERATORS["mls2"].min_count == constants.MIN_COUNT_MLS2
    assert all(OPERATORS[m].min_count == constants.MIN_COUNT_PCA for m in OPERATORS
               if m != "mls2")
    # the reference decides "too few" with the same numbers (2 neighbours / 5 for MLS2)
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0.01], [5, 5, 5],
                    [5.1, 5, 5]], dtype=float)
    m = reference.moments(pts, 0.5)
    assert list(m["status"]) == [0, 0, 0, 0, constants.TOO_FEW, constants.TOO_FEW]
