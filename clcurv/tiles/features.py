"""Covariance features of a file, in tiles when the cloud does not fit the memory budget
(``clcurv features``, :func:`features_file`).

    clcurv.features_file("survey.laz", "out.laz", [1, 2, 4], ["planarity", "linearity"])
    clcurv features survey.laz -o out.laz --radius 1,2,4 --features planarity,linearity

A tiled run computes what the in-memory run (:func:`clcurv.api.features` on the whole cloud)
computes, bit for bit on the same device, with the engine of :mod:`clcurv.tiles.engine`: tiles of
whole cells of the cloud's grid frame, cells of the largest radius (the in-memory call bins
at it too), and a halo of one cell (the features read the points alone: one neighbourhood
pass, however many radii; the optimal neighbourhood's walks all read the same 27 cells).
Not tiled: the k-NN radius (``k=``; its radius is not bounded before the walk, so neither
is a halo), ascii PLY and text formats. Output fields are those of the in-memory file
(:func:`file_fields`): one radius or ``optimal``, the features, ``number_of_neighbors``,
``feature_status`` and the normals in the file's normals slot (``optimal_radius``,
``knn_radius`` with them); several radii, every field suffixed ``_r<radius>``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clcurv import io
from clcurv.api.features import (DEFAULT_FEATURES, as_radii, canonical_names, empty_features,
                                 radius_suffix)
from clcurv.io import stream
from clcurv.tiles.planning import (TILE_BYTES_PER_POINT, TilingError, budget_of,
                                   check_tile_size, fits_memory)
from clcurv._shared.validate import choice

#: host bytes per point and written column beyond a curvature run's (the float64 result
#: column and its copy in the tile's records, or in the in-memory run the output's)
BYTES_PER_COLUMN = 16
#: host bytes per point and radius beyond a curvature run's (the device's 16-column record
#: of the radius, mapped on a CPU device)
BYTES_PER_RADIUS = 64


def file_fields(res, radii=None, extra=None):
    """(fields, normals) that a features file holds for ``res``, the result of
    :func:`clcurv.api.features`: ``radii`` the radius list of a several-radii result (a list;
    every field then named ``<name>_r<radius>``, normals as ``nx_r<radius>``...), else one
    result whose features, number_of_neighbors and feature_status are the fields and whose
    normals (None when not asked for) go to the file's normals slot; ``extra`` names a
    field for the per-point radius of a one-result run (``knn_radius``, ``optimal_radius``)."""
    if radii is not None:
        fields = {}
        for r, f in zip(radii, res):
            fields.update(f.file_fields(radius_suffix(r)))
        return fields, None
    fields = res.file_fields()
    normals = None
    if "normals" in res.values:
        normals = res.values["normals"]
        for a in ("nx", "ny", "nz"):
            del fields[a]
    if extra is not None:
        fields[extra] = res.radius
    return fields, normals


@dataclass
class FeatureParams:
    """What every tile of a features run computes (the interface of clcurv.tiles.engine's
    parameters: radius, halo, orientation, specs, key, bytes_per_point)."""
    radii: tuple
    names: tuple
    ddof: int
    optimal: bool
    device: object
    precision: str
    scale_space: int = 0
    kind = "features"
    #: the features never read the file's normals (a PLY or LAS input with normals crashed
    #: the tiled run on this missing attribute)
    ignore_normals = True

    @property
    def radius(self):
        """The grid's cell: the largest radius (the in-memory call bins at it)."""
        return max(self.radii)

    @property
    def several(self):
        return len(self.radii) > 1 and not self.optimal

    def halo(self, file_normals):
        return 1

    def orientation(self, src, file_normals):
        return None

    def _fields_of(self, res):
        return file_fields(res, list(self.radii) if self.several else None,
                           "optimal_radius" if self.optimal else None)

    def specs(self, wanted=None):
        """(name, width, dtype) of the written fields, in the in-memory file's order."""
        if self.several:
            res = [empty_features(self.names, r, self.ddof) for r in self.radii]
        else:
            res = empty_features(self.names, np.empty(0) if self.optimal else self.radius, self.ddof)
        fields, normals = self._fields_of(res)
        specs = [(name, None, np.float64) for name in fields]
        if normals is not None:
            specs.append(("normals", 3, np.float64))
        return specs

    def columns(self):
        return sum(1 if w is None else w for _, w, _ in self.specs())

    def bytes_per_point(self):
        """Peak host bytes per point of a tile: a curvature tile's, plus the columns and
        the radii of this run."""
        return (TILE_BYTES_PER_POINT + BYTES_PER_COLUMN * self.columns()
                + BYTES_PER_RADIUS * len(self.radii))

    def extra_in_memory(self):
        return BYTES_PER_COLUMN * self.columns() + BYTES_PER_RADIUS * len(self.radii)

    def key(self):
        d = dict(self.__dict__)
        d["radii"] = list(map(float, d["radii"]))
        d["names"] = list(d["names"])
        d["device"] = None if d["device"] is None else str(d["device"])
        d["kind"] = self.kind
        return d

    def tile_fields(self, cloud):
        """The fields (specs' names) of every point of a tile's ``cloud`` (a DeviceCloud in
        the run's frame, cells of the largest radius)."""
        from clcurv.api.features import features
        radius = list(self.radii) if self.several or self.optimal else self.radii[0]
        res = features(cloud, radius, self.names, ddof=self.ddof, optimal=self.optimal)
        fields, normals = self._fields_of(res)
        if normals is not None:
            fields["normals"] = normals
        return fields


def features_file(src, dst, radius=None, features=DEFAULT_FEATURES, *, k=None, ddof=0,
                  optimal=False, memory="auto", tile=None, workdir=None, device=None,
                  precision="float", progress=None, out=None, client=None, workers=None):
    """Covariance features (:func:`clcurv.api.features`) of the cloud of file ``src``, written
    with its points to ``dst``; in tiles when the cloud does not fit the memory budget
    (see the module docstring), with the same output bit for bit.

    Parameters
    ----------
    src : path, or a list of paths (a catalog: LAS/LAZ or NPY files read as one cloud, in
        tiles, one output per input in the folder ``dst``)
    dst : path
        The output: any format :func:`clcurv.io.write` takes in memory; a tiled run writes
        LAS/LAZ (from LAS/LAZ input: header and records kept), NPZ or binary PLY.
    radius : float or list of floats
        Ball radius in the file's unit, or several (one neighbour walk; fields named
        ``<feature>_r<radius>``).
    features, k, ddof, optimal, device, precision
        As :func:`clcurv.api.features`. ``k`` runs in memory only.
    memory, tile, workdir, progress, out, client, workers
        As :func:`clcurv.curvature_file`.

    Returns
    -------
    dict
        ``tiled`` (bool), ``tiles``, ``points``, ``fields`` (names written), ``halo``,
        ``times`` (seconds per stage), ``dst``.
    """
    from clcurv.tiles import engine as tiled
    tile = check_tile_size(tile)                    # before any point is read
    say = out or (lambda s: None)
    choice(ddof, "ddof", (0, 1))
    names = canonical_names(features)
    if not names:
        raise ValueError("features must name at least one feature")
    catalog = isinstance(src, (list, tuple))
    forced = tile is not None or client is not None or bool(workers)
    if k is not None:
        if radius is not None:
            raise ValueError("give either radius or k, not both")
        if optimal:
            raise ValueError("optimal=True chooses among a list of radii, not with k")
        if forced or catalog:
            raise TilingError("k (a k-NN radius) needs the whole cloud in memory: it does "
                              "not run in tiles (a tile size, workers, a scheduler or several "
                              "input files); give a radius to run in tiles")
        dst = io.check_output(dst)
        io.check_not_input(dst, src)
        return _in_memory(src, dst, None, names, k, ddof, False, device, precision)
    if radius is None:
        raise ValueError("features_file needs radius= (a number or a list) or k=")
    radii, _ = as_radii(radius)
    if optimal and len(radii) < 2:
        raise ValueError(f"optimal=True needs a list of at least two radii, got {radius!r}")
    params = FeatureParams(tuple(radii), names, int(ddof), bool(optimal), device, precision)
    for d in ([dst] if not catalog else []):
        if Path(d).suffix.lower() in (".las", ".laz"):     # before any work: LAS's limit
            io.las.check_extra_count(d, params.columns())
    if catalog:
        source = stream.Catalog(src)
        dst = tiled.catalog_outputs(source, dst)
    else:
        dst = io.check_output(dst)
        io.check_not_input(dst, src)
        source = _streamed(src) if not forced else stream.open_source(src)
        if source is None:          # a format the tiles do not read: the in-memory reader
            return _in_memory(src, dst, radii, names, None, ddof, optimal, device, precision)
    budget = budget_of(memory)
    if not catalog and not forced and fits_memory(source.n, budget, params.extra_in_memory()):
        return _in_memory(src, dst, radii, names, None, ddof, optimal, device, precision)
    tiled.check_tiled_outputs(dst if catalog else [dst], source)
    tiled.check_params(params, None, local=client is None and not workers)
    tiled.wsp.check_workdir(workdir)
    budget = tiled.worker_budget(budget, workers, client)
    ws = tiled.workspace(dst, workdir)
    summary = tiled.run_tiles(source, dst, params, budget, tile, ws, None, progress, say,
                              client, workers)
    summary["fields"] = [n for n, _, _ in params.specs()]
    summary.pop("status", None)             # curvature's status field: none here
    return summary


def _streamed(src):
    """The stream source of ``src``, or None when the tiles cannot read it (the in-memory
    reader then reads it, or says what is wrong with it)."""
    if Path(src).suffix.lower() not in stream.STREAM_READS:
        return None
    try:
        return stream.open_source(src)
    except Exception:
        return None


def _in_memory(src, dst, radii, names, k, ddof, optimal, device, precision):
    """The whole cloud read, :func:`clcurv.api.features`, the file written (the summary dict of
    :func:`features_file`)."""
    from clcurv.api.features import features
    t0 = time.perf_counter()
    cloud = io.read(src)
    several = radii is not None and len(radii) > 1 and not optimal
    radius = None if radii is None else radii if several or optimal else radii[0]
    res = features(cloud.points, radius, names, k=k, ddof=ddof, optimal=optimal,
                   device=device, precision=precision)
    extra = "knn_radius" if k is not None else "optimal_radius" if optimal else None
    fields, normals = file_fields(res, radii if several else None, extra)
    path = io.write(dst, cloud.points, fields, normals=normals, like=cloud)
    names_out = list(fields) + ([] if normals is None else ["normals"])
    return {"tiled": False, "tiles": 1, "halo": 0, "points": len(cloud.points),
            "dropped": int(getattr(cloud, "dropped", 0) or 0), "fields": names_out,
            "times": {"in memory": time.perf_counter() - t0}, "dst": path}
