"""The device side of the covariance features (:func:`clcurv.features`, whose module
:mod:`clcurv.api.features` documents them): the :data:`FEATURES` table, the record layouts
of kernels/features.cl, its build options and :func:`run_features`, the host side of the
kernel (at one radius, up to four radii per neighbour walk, or per-point radii), whose
launches are the operators' driver loop (:func:`clcurv.ops.driver.walk_chunks`). Used by
the API (:mod:`clcurv.api.features`, :mod:`clcurv.api.curvature`'s radius lists), the
optimal radius (:mod:`clcurv.ops.optimal`) and the registry's list of programs
(:func:`clcurv.ops.registry.program_variants`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyopencl.cltypes as ct

from clcurv._shared.constants import MIN_COUNT_PCA, RECORD_WIDTH
from clcurv.grid.anchor import cell_normals
from clcurv.grid.cloud import (empty_fields, place_records, record_buffer, record_bytes,
                               splits_into_host)
from clcurv.ops.driver import row_prune, walk_chunks
from clcurv.runtime.program import build


@dataclass(frozen=True)
class Feature:
    """One feature: canonical ``name``, its width (3 for normals), unit, formula, the other
    spellings accepted (jakteristics, PDAL), and where the definition comes from."""
    name: str
    width: int
    unit: str
    formula: str
    aliases: tuple = ()
    source: str = ""


#: The features, canonical names first (jakteristics' spelling), PDAL's and CloudCompare's
#: as aliases.
FEATURES = {f.name: f for f in (
    Feature("eigenvalue_sum", 1, "length^2", "l1 + l2 + l3",
            ("Sum", "EigenvalueSum", "Eigenvalues sum"),
            "jakteristics eigenvalue_sum, PDAL Sum, CloudCompare"),
    Feature("omnivariance", 1, "length^2", "(l1 l2 l3)^(1/3)", ("Omnivariance",),
            "jakteristics, PDAL (Raw mode)"),
    Feature("eigenentropy", 1, "1", "-(l1 ln l1 + l2 ln l2 + l3 ln l3), raw eigenvalues "
            "(depends on the length unit), 0 ln 0 = 0", ("Eigenentropy",),
            "jakteristics, PDAL (Raw mode)"),
    Feature("anisotropy", 1, "1", "(l1 - l3) / l1", ("Anisotropy",), "jakteristics, PDAL"),
    Feature("planarity", 1, "1", "(l2 - l3) / l1", ("Planarity",), "jakteristics, PDAL"),
    Feature("linearity", 1, "1", "(l1 - l2) / l1", ("Linearity",), "jakteristics, PDAL"),
    Feature("PCA1", 1, "1", "l1 / (l1 + l2 + l3), the first normalised eigenvalue",
            ("pca1", "normalized_eigenvalue1"), "jakteristics"),
    Feature("PCA2", 1, "1", "l2 / (l1 + l2 + l3), the second normalised eigenvalue",
            ("pca2", "normalized_eigenvalue2"), "jakteristics"),
    Feature("surface_variation", 1, "1", "l3 / (l1 + l2 + l3), the third normalised "
            "eigenvalue (Pauly's surface variation)",
            ("SurfaceVariation", "change_of_curvature", "normalized_eigenvalue3",
             "Surface variation", "Normal change rate"),
            "jakteristics, PDAL, CloudCompare (also its curvature 'Normal change rate'), "
            "clcurv method='variation'"),
    Feature("sphericity", 1, "1", "l3 / l1", ("Scattering",), "jakteristics; PDAL "
            "Scattering"),
    Feature("verticality", 1, "1", "1 - |e3_z|, e3 the unit normal (eigenvector of l3)",
            ("DemantkeVerticality",), "jakteristics verticality, PDAL DemantkeVerticality"),
    Feature("guinard_verticality", 1, "1", "|u_z| / |u|, u = l1 |e1| + l2 |e2| + l3 |e3| "
            "(componentwise absolute values)", ("Verticality",),
            "PDAL Verticality (Guinard & Landrieu 2017)"),
    Feature("eigenvalue1", 1, "length^2", "l1, the largest eigenvalue", ("1st eigenvalue",),
            "jakteristics, CloudCompare"),
    Feature("eigenvalue2", 1, "length^2", "l2", ("2nd eigenvalue",),
            "jakteristics, CloudCompare"),
    Feature("eigenvalue3", 1, "length^2", "l3, the smallest eigenvalue", ("3rd eigenvalue",),
            "jakteristics, CloudCompare"),
    Feature("density", 1, "1/length^3", "n / (4/3 pi r^3)", ("Density",),
            "PDAL Density (see the module notes)"),
    Feature("normals", 3, "1", "e3, the unit PCA normal (sign arbitrary unless `orient`)",
            ("normal",), "jakteristics nx, ny, nz"),
)}

#: the real columns of one record (count and status take the last two)
_COLUMNS = RECORD_WIDTH - 2
#: radii walked at once by one launch (features.cl: NR <= 4)
MAX_RADII_PER_WALK = 4


def layouts(names):
    """The record layouts of ``names``: groups of at most 14 real columns (one launch each),
    as (feature -> first column) dicts. Wide features (normals) come first in a group, so
    that they lie in one 4-column block of the split (:func:`_split_layout`) and reach the
    host as a view, not a copy."""
    groups, cur, used = [], {}, 0
    for n in sorted(names, key=lambda n: -FEATURES[n].width):
        w = FEATURES[n].width
        if used + w > _COLUMNS:
            groups.append(cur)
            cur, used = {}, 0
        cur[n] = used
        used += w
    groups.append(cur)
    return groups


def _split_layout(used):
    """The record split in blocks of at most 4 columns (clcurv.grid.cloud.split_records takes
    fields of width 1-4) for ``used`` real columns, plus count and status."""
    out = {f"b{b}": slice(a, min(a + 4, used)) for b, a in enumerate(range(0, used, 4))}
    return dict(out, count=_COLUMNS, status=_COLUMNS + 1)


#: several radii on a CPU device: the balls' records in one buffer, in blocks of this many
#: points (features.cl: REC_BALLS): a point's records of its balls lie close together, so
#: that the kernel's scattered stores cost less, and each ball's block is long enough for
#: the split to read it as one run
REC_BLOCK = 128


def program_defines(group, nr, point_radius=False, row_prune=0, anchored=True,
                    one_buffer=False):
    """Build options of features.cl for one record layout ``group`` and ``nr`` radii
    (``row_prune``: clcurv.ops.driver.row_prune of the walk's largest radius): each feature's
    first record column (CIX_<FEATURE>), count's and status's, and REC_USED the mask of
    the columns written (kernels/lanes_records.h). ``anchored`` false builds the plain PCA
    (REFINE_L0=0: no anchor frame, no lambda0 refinement), whose sums, eigenvectors and
    status are those of the moments kernel built so (clcurv.api.curvature's PCA normals pass).
    ``one_buffer``: the ``nr`` radii's records in one buffer, in blocks of
    :data:`REC_BLOCK` points (REC_BALLS), else one buffer per radius."""
    cols = {f"CIX_{n.upper()}": c for n, c in group.items()}
    used = (1 << _COLUMNS) | (1 << (_COLUMNS + 1))
    for n, c in group.items():
        used |= ((1 << FEATURES[n].width) - 1) << c
    return dict(cols, CIX_COUNT=_COLUMNS, CIX_STATUS=_COLUMNS + 1, REC_USED=hex(used), NR=nr,
                REFINE_L0=int(anchored), MIN_COUNT=MIN_COUNT_PCA, DENSITY=0, GAUSSIAN=0,
                REF_NORMALS=0, POINT_RADIUS=int(point_radius), ROW_PRUNE=int(row_prune),
                REC_BALLS=nr if one_buffer else 0, REC_BLOCK=REC_BLOCK)


def run_features(cloud, radii, names, ddof=0, point_r2=None, anchored=True):
    """Run features.cl on ``cloud`` for ``radii`` (<= its cell), at most 4 radii per walk.

    ``point_r2`` (device buffer, sorted order): per-point squared radii (one radius, the
    k-NN radius) instead of ``radii``; ``anchored`` false: the plain PCA of the moments
    kernel's normals pass (:func:`program_defines`). Returns, per radius, (values, count,
    status) in input order: values float64 by canonical name. Stage times go to
    ``cloud.timings`` (build_features, kernel_features, download).
    """
    out = []
    groups = layouts(names)
    make4 = ct.make_double4 if cloud.dtype == np.float64 else ct.make_float4
    t_build = t_run = t_fetch = 0.0
    for w0 in range(0, len(radii), MAX_RADII_PER_WALK):
        walk = radii[w0:w0 + MAX_RADII_PER_WALK]
        nr = len(walk)
        r2 = [cloud.dtype(r * r) for r in walk] + [cloud.dtype(0)] * (4 - nr)
        res = [({}, None, None) for _ in walk]
        for group in groups:
            used = sum(FEATURES[n].width for n in group)
            layout = _split_layout(used)
            plan = cloud.plan("kernel_features", nr * record_bytes(cloud, layout),
                              widest=RECORD_WIDTH * np.dtype(cloud.dtype).itemsize,
                              label="the coordinates, the grid")
            chunked = plan.count > 1
            # several radii on a CPU device: their records in one buffer (REC_BLOCK)
            one = nr > 1 and not chunked and splits_into_host(cloud)
            t0 = time.perf_counter()
            opts = dict(cloud.defines, **program_defines(
                group, nr, point_r2 is not None,
                row_prune(cloud, max(walk), point_r2 is not None), anchored, one))
            prg = build(cloud.device, "features.cl", opts)
            ranges = cloud.with_middles() if opts["ROW_PRUNE"] else cloud.ranges
            t_build += time.perf_counter() - t0
            if one:
                blocks = -(-plan.chunk // REC_BLOCK)
                recs = [record_buffer(cloud, blocks * REC_BLOCK * nr)] * 4
            else:
                recs = [record_buffer(cloud, plan.chunk) for _ in walk]
                recs += [recs[0]] * (4 - nr)
            fields = [empty_fields(layout, cloud.n) for _ in walk]
            wbuf = point_r2 if point_r2 is not None else cloud.x
            anchors = cell_normals(cloud) if opts.get("REFINE_L0") else cloud.x
            par = make4(max(walk), 0.0, float(ddof), 0.0)    # (r, 1/h^2, ddof, 0)
            def place(first, stop, chunked):
                for j in range(nr):
                    place_records(cloud, recs[j], layout, fields[j], first, stop, chunked,
                                  balls=(nr, j, REC_BLOCK) if one else None)

            run, fetch = walk_chunks(
                cloud, prg.features, opts, plan, (cloud.x, cloud.x, cloud.x, wbuf, anchors),
                ranges, max(walk), par, (recs[0], make4(*r2), recs[1], recs[2], recs[3]), place)
            t_run, t_fetch = t_run + run, t_fetch + fetch
            for j in range(nr):
                vals = res[j][0]
                blocks = fields[j]
                for n, c in group.items():       # views of the (N, <= 4) float64 blocks
                    w, b, o = FEATURES[n].width, c // 4, c % 4
                    if o + w <= 4:
                        vals[n] = blocks[f"b{b}"][:, o] if w == 1 else blocks[f"b{b}"][:, o:o + w]
                    else:
                        vals[n] = np.stack([blocks[f"b{(c + i) // 4}"][:, (c + i) % 4]
                                            for i in range(w)], axis=1)
                res[j] = (vals, blocks["count"], blocks["status"])
            del recs
        out.extend(({n: r[0][n] for n in names}, r[1], r[2]) for r in res)
    cloud.timings.update(build_features=t_build, kernel_features=t_run, download=t_fetch)
    return out
