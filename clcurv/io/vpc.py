"""Virtual point clouds (``.vpc``): the index of a tiled survey that PDAL wrench
(``build_vpc``) and QGIS write and open as one layer.

A ``.vpc`` is a STAC ItemCollection (a GeoJSON ``FeatureCollection``), one STAC Item per
file, with the pointcloud (``pc:``) and projection (``proj:``) extensions
(github.com/PDAL/wrench, ``vpc-spec.md``):

    {"type": "FeatureCollection", "features": [
      {"type": "Feature", "stac_version": "1.0.0", "id": "tile_1",
       "geometry": {...}, "bbox": [...],                  # WGS 84 (GeoJSON's)
       "properties": {"pc:count": 1000, "proj:wkt2": "...", "proj:epsg": 2056,
                      "proj:bbox": [minx, miny, minz, maxx, maxy, maxz], ...},
       "assets": {"data": {"href": "./tile_1.laz", "roles": ["data"]}}}, ...]}

:func:`read` gives the items in the file's order (:class:`Item`: the data file's path, a
relative href resolved against the ``.vpc``'s folder; the stated point count, native box
and CRS when present). :func:`write` describes LAS/LAZ files from their headers (count,
box, CRS) with relative hrefs, atomically. :func:`header_crs` is the CRS a LAS header
states (its WKT VLR or GeoTIFF keys), read without pyproj.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np

from . import atomic_output, las
from .common import CorruptFileError, MissingFileError, is_las

#: the STAC extensions a written item declares (as wrench writes them)
EXTENSIONS = ("https://stac-extensions.github.io/pointcloud/v1.0.0/schema.json",
              "https://stac-extensions.github.io/projection/v1.1.0/schema.json")
#: the GeoTIFF keys of an EPSG code: ProjectedCSTypeGeoKey, then GeographicTypeGeoKey
_EPSG_KEYS = (3072, 2048)
#: the top-level authority at the end of a WKT1 (AUTHORITY["EPSG","2056"]) or WKT2
#: (ID["EPSG",2056]) string
_WKT_EPSG = re.compile(r'(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]\s*\]\s*$', re.I)


@dataclass(frozen=True)
class Crs:
    """The CRS a file or an item states: its WKT text and/or EPSG code (either may be
    None). ``key`` is what two CRS are compared by: the EPSG code when known, else the
    WKT with its white space removed, else None (no CRS stated)."""
    wkt: str | None = None
    epsg: int | None = None

    @property
    def key(self):
        if self.epsg is not None:
            return f"EPSG:{self.epsg}"
        if self.wkt:
            return "".join(self.wkt.split())
        return None

    def __str__(self):
        if self.epsg is not None:
            return f"EPSG:{self.epsg}"
        if self.wkt:
            return self.wkt if len(self.wkt) <= 80 else self.wkt[:77] + "..."
        return "no CRS"


@dataclass(frozen=True)
class Item:
    """One file of a ``.vpc``: ``path`` (absolute, or as the href gave it), what the item
    states of it: ``count`` (``pc:count``), ``bounds`` ((mins, maxs) of ``proj:bbox``,
    native coordinates; None without it; z as -inf..inf for a 2D box) and ``crs``."""
    path: Path
    count: int | None
    bounds: tuple | None
    crs: Crs


def read(path):
    """The items of the ``.vpc`` ``path``, in its order (a catalog's global ids follow it).

    The data file of an item is its asset with the role ``data``, else its first asset (as
    wrench reads it); relative hrefs and ``file://`` URLs are resolved against the folder
    of ``path``. Overview assets are ignored. CorruptFileError for a file that is not a
    FeatureCollection of items with assets, or a remote href (http, s3...: a run reads
    files on a local or shared file system).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MissingFileError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptFileError(f"{path}: not a virtual point cloud (.vpc is JSON): "
                               f"{exc}") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" \
            or not isinstance(doc.get("features"), list):
        raise CorruptFileError(f"{path}: not a virtual point cloud (a STAC ItemCollection: "
                               "a GeoJSON FeatureCollection with a list of features)")
    return [_item(path, k, f) for k, f in enumerate(doc["features"])]


def _item(path, k, f):
    """The :class:`Item` of feature #k ``f`` of the ``.vpc`` ``path``."""
    where = f"{path}: item #{k}"
    assets = f.get("assets") if isinstance(f, dict) else None
    props = f.get("properties") if isinstance(f, dict) else None
    if not isinstance(assets, dict) or not assets or not isinstance(props, dict):
        raise CorruptFileError(f"{where} is not a STAC item with assets and properties")
    data = [a for a in assets.values() if isinstance(a, dict)
            and "data" in (a.get("roles") or [])]
    asset = data[0] if data else next(iter(assets.values()))
    href = asset.get("href") if isinstance(asset, dict) else None
    if not isinstance(href, str) or not href:
        raise CorruptFileError(f"{where}: its data asset has no href")
    url = urlparse(href)
    if url.scheme == "file":
        href = unquote(url.path)
    elif len(url.scheme) > 1:                # not a Windows drive letter
        raise CorruptFileError(f"{where}: {href} is a remote file; a run reads files on a "
                               "local or shared file system (copy them there)")
    file = Path(href)
    if not file.is_absolute():
        file = path.parent / file
    count = props.get("pc:count")
    if count is not None and (not isinstance(count, int) or count < 0):
        raise CorruptFileError(f"{where}: pc:count {count!r} is not a point count")
    return Item(Path(file), count, _bounds(where, props.get("proj:bbox")), _item_crs(props))


def _bounds(where, box):
    """(mins, maxs) of a 6-value (3D) or 4-value (2D) ``proj:bbox``, or None."""
    if box is None:
        return None
    try:
        box = np.asarray(box, float)
    except (TypeError, ValueError):
        box = np.zeros(0)
    if box.shape == (4,):
        box = np.array([box[0], box[1], -np.inf, box[2], box[3], np.inf])
    if box.shape != (6,):
        raise CorruptFileError(f"{where}: proj:bbox is not 4 or 6 numbers")
    return box[:3], box[3:]


def _item_crs(props):
    """The :class:`Crs` of an item's ``proj:epsg``, ``proj:wkt2`` (``proj:projjson``'s
    ``id`` when only it is given)."""
    wkt = props.get("proj:wkt2") or None
    epsg = props.get("proj:epsg")
    pj = props.get("proj:projjson")
    if epsg is None and isinstance(pj, dict) and isinstance(pj.get("id"), dict) \
            and str(pj["id"].get("authority", "")).upper() == "EPSG":
        epsg = pj["id"].get("code")
    if epsg is None and isinstance(wkt, str):
        m = _WKT_EPSG.search(wkt)
        epsg = m and m.group(1)
    try:
        epsg = None if epsg is None else int(epsg)
    except (TypeError, ValueError):
        epsg = None
    return Crs(wkt if isinstance(wkt, str) else None, epsg)


def header_crs(header):
    """The :class:`Crs` a ``laspy.LasHeader`` states: the WKT of its OGC WKT (E)VLR, and an
    EPSG code from its GeoTIFF keys (a projected CRS first) or the WKT's top-level
    authority."""
    wkt, epsg = None, None
    records = list(header.vlrs) + list(header.evlrs or [])
    for v in records:
        if getattr(v, "user_id", "") != "LASF_Projection":
            continue
        if v.record_id == 2112 and getattr(v, "string", ""):
            wkt = v.string.strip("\0").strip() or None
        elif v.record_id == 34735 and hasattr(v, "geo_keys"):
            codes = {k.id: k.value_offset for k in v.geo_keys if k.tiff_tag_location == 0}
            found = [codes[k] for k in _EPSG_KEYS if 1024 <= codes.get(k, 0) <= 32766]
            epsg = found[0] if found else epsg
    if wkt and epsg is None:
        m = _WKT_EPSG.search(wkt)
        epsg = int(m.group(1)) if m else None
    return Crs(wkt, epsg)


# --------------------------------------------------------------------------- writing

def write(path, files):
    """Write the ``.vpc`` ``path`` describing the LAS/LAZ ``files`` (in that order): per
    file an item with its header's point count, box (``proj:bbox``, ``proj:geometry``) and
    CRS (``proj:wkt2``, ``proj:epsg``), its dimensions (``pc:schemas``), and an href
    relative to the folder of ``path``. The GeoJSON ``geometry`` and ``bbox`` are WGS 84
    when pyproj is installed and the file states a CRS, else the native box (what wrench
    writes when it cannot reproject). Written atomically. Returns ``path``."""
    path = Path(path)
    items, ids = [], set()
    for f in files:
        f = Path(f)
        item = _describe(f, path.parent)
        if item["id"] in ids:                   # x.las and x.laz: ids by name instead
            item["id"] = f.name
        ids.add(item["id"])
        items.append(item)
    text = json.dumps({"type": "FeatureCollection", "features": items}, indent=1) + "\n"
    with atomic_output(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path


def _describe(file, folder):
    """The STAC item of the LAS/LAZ ``file`` (its header only is read)."""
    layout = las.read_layout(file)
    laspy = las.import_laspy(file, layout.compressed)
    with laspy.open(str(file)) as f:
        h = f.header
    crs = header_crs(h)
    lo, hi = np.asarray(h.mins, float), np.asarray(h.maxs, float)
    box = [*map(float, lo), *map(float, hi)]
    geometry = _polygon(lo, hi)
    wgs = _wgs84(crs, lo, hi)
    date = h.creation_date
    props = {
        "datetime": f"{date.isoformat()}T00:00:00Z" if date else "1970-01-01T00:00:00Z",
        "pc:count": int(h.point_count),
        "pc:type": "lidar",
        "pc:encoding": "LASzip" if layout.compressed else "LAS",
        "pc:schemas": [_schema(d) for d in h.point_format.dimensions],
        "proj:wkt2": crs.wkt or "",             # a string, as wrench reads it
        "proj:bbox": box,
        "proj:geometry": geometry,
    }
    if crs.epsg is not None:
        props["proj:epsg"] = crs.epsg
    try:
        href = "./" + Path(file).resolve().relative_to(Path(folder).resolve()).as_posix()
    except ValueError:
        href = str(Path(file).resolve())
    name = Path(file).name
    stem = name[:-len(".copc.laz")] if name.lower().endswith(".copc.laz") else Path(name).stem
    return {"type": "Feature", "stac_version": "1.0.0", "stac_extensions": list(EXTENSIONS),
            "id": stem, "geometry": wgs[0] if wgs else geometry,
            "bbox": wgs[1] if wgs else box, "properties": props, "links": [],
            "assets": {"data": {"href": href, "roles": ["data"]}}}


def _polygon(lo, hi):
    """The GeoJSON polygon of the xy box ``lo``..``hi``."""
    x0, y0, x1, y1 = float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])
    return {"type": "Polygon",
            "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}


def _wgs84(crs, lo, hi):
    """(geometry, bbox) of the box in WGS 84, or None (no CRS, or no pyproj)."""
    if crs.key is None:
        return None
    try:
        import pyproj           # optional: without it, the native box (as wrench's fallback)
        src = pyproj.CRS.from_epsg(crs.epsg) if crs.epsg is not None else \
            pyproj.CRS.from_wkt(crs.wkt)
        to = pyproj.Transformer.from_crs(src, "EPSG:4326", always_xy=True)
        xs, ys = to.transform([lo[0], hi[0], hi[0], lo[0]], [lo[1], lo[1], hi[1], hi[1]])
    except Exception:
        return None
    if not (np.isfinite(xs).all() and np.isfinite(ys).all()):
        return None
    ring = [[float(x), float(y)] for x, y in zip(xs, ys)]
    return ({"type": "Polygon", "coordinates": [ring + ring[:1]]},
            [float(min(xs)), float(min(ys)), float(lo[2]),
             float(max(xs)), float(max(ys)), float(hi[2])])


def _schema(dim):
    """The ``pc:schemas`` entry of a laspy dimension: name, size in bytes (a bit field: 1),
    type (signed, unsigned, floating)."""
    kind = dim.kind.name
    typ = {"SignedInteger": "signed", "FloatingPoint": "floating"}.get(kind, "unsigned")
    return {"name": dim.name, "size": max(int(dim.num_bytes), 1), "type": typ}


def is_vpc(path):
    """Is ``path`` a ``.vpc`` file name (any case)?"""
    return isinstance(path, (str, Path)) and Path(str(path)).suffix.lower() == ".vpc"


def data_files(items):
    """The item paths that are not LAS/LAZ names (a ``.vpc`` of a catalog names LAS/LAZ)."""
    return [it.path for it in items if not is_las(it.path)]
