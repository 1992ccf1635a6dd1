"""Covariance features of a file in tiles, when the cloud does not fit the memory budget
(``clcurv features``, :func:`clcurv.features_file`, which decides: :mod:`clcurv.jobs.job`).

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

from dataclasses import dataclass

import numpy as np

from clcurv.api.features import empty_features, features, radius_suffix
from clcurv.tiles.planning import TILE_BYTES_PER_POINT

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
        radius = list(self.radii) if self.several or self.optimal else self.radii[0]
        res = features(cloud, radius, self.names, ddof=self.ddof, optimal=self.optimal)
        fields, normals = self._fields_of(res)
        if normals is not None:
            fields["normals"] = normals
        return fields
