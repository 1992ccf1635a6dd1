"""A catalog given as paths, a folder or a .vpc (clcurv.io.stream.Catalog, clcurv.io.vpc):
the same outputs bit for bit, a .vpc index of the outputs that reads back with their counts,
boxes and CRS, mixed point formats and scales merged, and every bad catalog refused before a
point is read, with no output and no workspace left."""
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import clcurv
from clcurv.io import stream, vpc
from clcurv.tiles.planning import TilingError
from clcurv.io.common import CatalogError, CorruptFileError, MissingFileError, \
    UnknownFormatError
from tests.hostile import assert_clean_failure, assert_same_las, run_cli

laspy = pytest.importorskip("laspy")
from laspy.vlrs.known import (GeoKeyDirectoryVlr, GeoKeyEntryStruct,  # noqa: E402
                              WktCoordinateSystemVlr)

R = 1.0
SCALE = 2.0 ** -7            # coordinates on a binary grid: exact at 2^-7 and at 2^-9
NAMES = ("t1.las", "t2.laz", "t3.laz")
METHOD = "mls1"


def _wkt(epsg, name):
    return (f'PROJCS["{name}",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
            f'298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
            f'PROJECTION["Transverse_Mercator"],UNIT["metre",1],'
            f'AUTHORITY["EPSG","{epsg}"]]')


WKT = _wkt(32632, "WGS 84 / UTM zone 32N")
OTHER_WKT = _wkt(32633, "WGS 84 / UTM zone 33N")


def _header(fmt=6, version="1.4", scale=SCALE, wkt=WKT, epsg=None, offsets=None):
    """A LAS header with the CRS as an OGC WKT VLR (``wkt``) or GeoTIFF keys (``epsg``)."""
    h = laspy.LasHeader(point_format=fmt, version=version)
    h.scales = [scale] * 3
    h.offsets = offsets
    if wkt is not None:
        h.vlrs.append(WktCoordinateSystemVlr(wkt))
        if version == "1.4":
            h.global_encoding.wkt = True
    if epsg is not None:
        keys = GeoKeyDirectoryVlr()
        keys.geo_keys = [GeoKeyEntryStruct(1024, 0, 1, 1),         # model type: projected
                         GeoKeyEntryStruct(3072, 0, 1, epsg)]
        keys.geo_keys_header.number_of_keys = 2
        h.vlrs.append(keys)
    return h


def _write(path, pts, kind, **kw):
    las = laspy.LasData(_header(offsets=np.floor(pts.min(axis=0)) if len(pts) else
                                np.zeros(3), **kw))
    las.x, las.y, las.z = pts.T
    las.classification = kind
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three strips of an aerial scene cut at unaligned x (points exactly on the cuts), as
    t1.las, t2.laz, t3.laz in tiles/; the same points in that order in whole.las and its
    in-memory output ref.las."""
    d = tmp_path_factory.mktemp("catalog")
    s = clcurv.shapes.aerial_scene(4000, extent=(31.3, 17.9), seed=5)
    pts = np.round(s["points"] / SCALE) * SCALE
    cuts = np.round((pts[:, 0].min() + np.array([10.3, 20.7])) / SCALE) * SCALE
    pts[:40, 0] = cuts[0]                                   # on a border
    strip = np.searchsorted(cuts, pts[:, 0], side="right")
    order = np.argsort(strip, kind="stable")
    pts, kind, strip = pts[order], s["kind"][order], strip[order]
    (d / "tiles").mkdir()
    parts = [_write(d / "tiles" / name, pts[strip == k], kind[strip == k])
             for k, name in enumerate(NAMES)]
    _write(d / "whole.las", pts, kind)
    clcurv.curvature_file(d / "whole.las", d / "ref.las", R, method=METHOD, memory="64GiB")
    return d, parts, pts, kind, strip


def _fields(path):
    """{name: values} of the fields clcurv writes (the extra dimensions) and x, y, z."""
    las = laspy.read(str(path))
    out = {n: np.asarray(las[n]) for n in las.point_format.extra_dimension_names}
    out.update(x=np.asarray(las.x), y=np.asarray(las.y), z=np.asarray(las.z))
    return out


def _assert_reference(d, folder, names=NAMES):
    """Each output holds its file's rows of the in-memory run of the whole file, bit for
    bit."""
    ref, start = _fields(d / "ref.las"), 0
    for name in names:
        out = _fields(folder / name)
        m = len(out["x"])
        assert m and sorted(out) == sorted(ref)
        for k, a in out.items():
            assert np.array_equal(a, ref[k][start:start + m], equal_nan=True), (name, k)
        start += m
    assert start == len(ref["x"])


def _wrench_vpc(path, files, counts=None):
    """A .vpc as PDAL wrench's build_vpc writes it: relative "./" hrefs, pc:count,
    proj:bbox and proj:wkt2 from each header."""
    feats = []
    for k, f in enumerate(files):
        h = laspy.open(str(f)).header if os.path.exists(f) else None
        box = [*h.mins, *h.maxs] if h is not None else [0, 0, 0, 1, 1, 1]
        count = counts[k] if counts else h.point_count if h is not None else 0
        feats.append({
            "type": "Feature", "stac_version": "1.0.0", "id": f.stem,
            "stac_extensions": list(vpc.EXTENSIONS),
            "geometry": {"type": "Polygon", "coordinates": [[[box[0], box[1]],
                                                             [box[3], box[1]],
                                                             [box[3], box[4]],
                                                             [box[0], box[1]]]]},
            "bbox": box,
            "properties": {"datetime": "2024-01-01T00:00:00Z", "pc:count": int(count),
                           "pc:type": "lidar", "pc:encoding": "?", "pc:schemas": [],
                           "proj:wkt2": WKT, "proj:bbox": [float(b) for b in box]},
            "links": [],
            "assets": {"data": {"href": "./" + os.path.relpath(f, path.parent),
                                "roles": ["data"]}}})
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return path


def _folder(tmp_path, name):
    f = tmp_path / name
    f.mkdir()
    return f


# --------------------------------------------------------------------------- the three forms

def test_a_folder_and_a_vpc_are_the_listed_paths_bit_for_bit(scene, tmp_path):
    d, parts, _, _, _ = scene
    survey = _wrench_vpc(d / "tiles" / "survey.vpc", parts)
    outs = {}
    for form, src in (("paths", [str(p) for p in parts]), ("folder", d / "tiles"),
                      ("vpc", survey)):
        outs[form] = _folder(tmp_path, form)
        s = clcurv.curvature_file(src, outs[form], R, method=METHOD)
        assert s["tiled"] and s["files"] == 3 and s["points"] == len(scene[2])
    assert sorted(os.listdir(outs["paths"])) == sorted(os.listdir(outs["folder"])) == \
        ["index.vpc", *NAMES]
    assert sorted(os.listdir(outs["vpc"])) == ["survey.vpc", *NAMES]
    for name in NAMES:
        assert_same_las(outs["paths"] / name, outs["folder"] / name)
        assert_same_las(outs["paths"] / name, outs["vpc"] / name)
    _assert_reference(d, outs["vpc"])
    # features too, from the .vpc
    feat = _folder(tmp_path, "features")
    s = clcurv.features_file(survey, feat, R, ["planarity"])
    assert s["files"] == 3 and s["index"] == feat / "survey.vpc"
    assert sum(laspy.open(str(feat / n)).header.point_count for n in NAMES) == len(scene[2])


def test_the_index_reads_back_with_the_outputs_counts_boxes_and_crs(scene, tmp_path):
    d, parts, pts, _, strip = scene
    out = _folder(tmp_path, "out")
    s = clcurv.curvature_file(d / "tiles", out, R, method=METHOD)
    assert s["index"] == out / "index.vpc"
    items = vpc.read(out / "index.vpc")
    assert [it.path.resolve() for it in items] == [(out / n).resolve() for n in NAMES]
    for k, (it, name) in enumerate(zip(items, NAMES)):
        mine = pts[strip == k]
        h = laspy.open(str(out / name)).header
        assert it.count == h.point_count == len(mine) > 0
        assert np.array_equal(it.bounds[0], mine.min(axis=0))      # the grid: exact
        assert np.array_equal(it.bounds[1], mine.max(axis=0))
        assert it.crs.wkt == WKT and it.crs.epsg == 32632
    doc = json.loads((out / "index.vpc").read_text())
    assert [f["assets"]["data"]["href"] for f in doc["features"]] == \
        [f"./{n}" for n in NAMES]
    assert all(f["stac_version"] == "1.0.0" and f["properties"]["proj:epsg"] == 32632
               for f in doc["features"])
    # the index is a catalog itself: the same cloud again
    again = stream.Catalog(out / "index.vpc")
    assert again.n == len(pts) and [p.name for p in again.paths] == list(NAMES)


def test_a_folder_is_read_in_sorted_name_order(scene, tmp_path):
    """Python's string order of the names: upper case first, t10 before t2."""
    _, parts, _, _, _ = scene
    f = _folder(tmp_path, "f")
    for src, name in zip(parts, ("t2.laz", "T9.LAS", "t10.laz")):
        shutil.copy(src, f / name)
    (f / "notes.txt").write_text("not a cloud")
    (f / "sub.las").mkdir()                                 # a folder: not a file
    cat = stream.Catalog(f)
    assert [p.name for p in cat.paths] == ["T9.LAS", "t10.laz", "t2.laz"]
    counts = [laspy.open(str(f / n)).header.point_count for n in ("T9.LAS", "t10.laz")]
    assert list(cat.offsets[1:3]) == list(np.cumsum(counts))


def test_other_point_formats_and_scales_merge_each_output_keeping_its_header(scene,
                                                                             tmp_path):
    """t2 as LAS 1.2 point format 1 at a 4x finer scale, its CRS as GeoTIFF keys (the
    same EPSG code as the others' WKT): one cloud, the in-memory run's numbers, each
    output in its own input's format and scale."""
    d, _, pts, kind, strip = scene
    f = _folder(tmp_path, "mixed")
    for k, name in enumerate(NAMES):
        kw = (dict(fmt=1, version="1.2", scale=SCALE / 4, wkt=None, epsg=32632) if k == 1
              else {})
        _write(f / name, pts[strip == k], kind[strip == k], **kw)
    out = _folder(tmp_path, "out")
    clcurv.curvature_file(f, out, R, method=METHOD)
    _assert_reference(d, out)
    h = laspy.open(str(out / "t2.laz")).header
    assert h.point_format.id == 1 and str(h.version) == "1.2"
    assert np.array_equal(h.scales, [SCALE / 4] * 3)
    assert laspy.open(str(out / "t1.las")).header.point_format.id == 6
    assert [it.crs.epsg for it in vpc.read(out / "index.vpc")] == [32632] * 3


# --------------------------------------------------------------------------- bad catalogs

def _two_crs(d, tmp_path):
    f = _folder(tmp_path, "crs")
    for p in ("t1.las", "t2.laz"):
        shutil.copy(d / "tiles" / p, f / p)
    las = laspy.read(str(d / "tiles" / "t3.laz"))
    _write(f / "t3.laz", np.column_stack([las.x, las.y, las.z]), las.classification,
           wkt=OTHER_WKT)
    return f


def _truncated(d, tmp_path):
    f = _folder(tmp_path, "cut")
    for p in NAMES:
        shutil.copy(d / "tiles" / p, f / p)
    data = (f / "t2.laz").read_bytes()
    (f / "t2.laz").write_bytes(data[:len(data) // 2])
    return f


def _no_las(d, tmp_path):
    f = _folder(tmp_path, "nolas")
    (f / "notes.txt").write_text("x")
    np.save(f / "a.npy", np.zeros((5, 3)))
    return f


def _mixed_kinds(d, tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((5, 3)))
    return [d / "tiles" / "t1.las", tmp_path / "a.npy"]


def _empty_vpc(d, tmp_path):
    p = tmp_path / "none.vpc"
    p.write_text('{"type": "FeatureCollection", "features": []}')
    return p


BAD = {
    "vpc naming missing files": (
        lambda d, t: _wrench_vpc(t / "s.vpc", [d / "tiles" / "t1.las", t / "gone.laz",
                                               t / "nope.las"]),
        MissingFileError, r"s\.vpc: names 2 missing file\(s\): .*gone\.laz, .*nope\.las"),
    "vpc stating other counts": (
        lambda d, t: _wrench_vpc(t / "s.vpc", [d / "tiles" / n for n in NAMES],
                                 counts=[1, 2, 3]),
        CatalogError, r"s\.vpc: states 1 points for .*t1\.las, whose header has \d+"),
    "vpc with zero items": (_empty_vpc, CatalogError, r"none\.vpc: .* has no items"),
    "vpc not json": (lambda d, t: (t / "x.vpc").write_text("{nope") and t / "x.vpc",
                     CorruptFileError, r"x\.vpc: not a virtual point cloud"),
    "truncated LAZ": (_truncated, CorruptFileError, r"cut/t2\.laz: .*(truncated|corrupt)"),
    "two CRS": (lambda d, t: _two_crs(d, t), CatalogError,
                r"one CRS: .*t1\.las has EPSG:32632, .*t3\.laz has EPSG:32633"),
    "empty folder": (lambda d, t: _folder(t, "empty"), CatalogError,
                     r"empty: no LAS/LAZ file .*\(it is empty\)"),
    "folder without LAS": (_no_las, CatalogError,
                           r"nolas: no LAS/LAZ file .*\(it holds a\.npy, notes\.txt\)"),
    "NPY with LAS": (_mixed_kinds, UnknownFormatError,
                     r"a\.npy: a catalog is all LAS/LAZ or all NPY files, not NPY with LAS"),
}


@pytest.mark.parametrize("case", list(BAD))
@pytest.mark.parametrize("api", ["curvature_file", "features_file"])
def test_a_bad_catalog_fails_before_any_output(scene, tmp_path, case, api):
    d, _, _, _, _ = scene
    make, error, message = BAD[case]
    src = make(d, tmp_path)
    out = _folder(tmp_path, "out")
    run = getattr(clcurv, api)
    with pytest.raises(error, match=message):
        run(src, out, R, **({"method": METHOD} if api == "curvature_file" else {}))
    assert os.listdir(out) == []                # no output, no index, no workspace


def test_the_command_takes_a_folder_and_a_vpc(scene, tmp_path):
    d, parts, _, _, _ = scene
    out = _folder(tmp_path, "out")
    r = run_cli("compute", d / "tiles", "-o", out, "--radius", "1", "--method", METHOD, "-q")
    assert r.code == 0, r.stderr
    assert f"{len(scene[2])} points from 3 files of {d / 'tiles'}" in r.stdout
    assert f"and the index {out / 'index.vpc'}" in r.stdout
    _assert_reference(d, out)
    survey = _wrench_vpc(tmp_path / "survey.vpc", parts)
    feat = _folder(tmp_path, "feat")
    r = run_cli("features", survey, "-o", feat, "--radius", "1", "-q")
    assert r.code == 0, r.stderr
    assert sorted(os.listdir(feat)) == ["survey.vpc", *NAMES]
    bad = _wrench_vpc(tmp_path / "bad.vpc", [parts[0], tmp_path / "gone.laz"])
    r = run_cli("compute", bad, "-o", _folder(tmp_path, "o2"), "--radius", "1")
    assert r.code == 3 and "missing file(s)" in r.stderr and "gone.laz" in r.stderr
    assert os.listdir(tmp_path / "o2") == []


def test_the_output_index_never_replaces_the_input_vpc(scene, tmp_path):
    d, parts, _, _, _ = scene
    f = _folder(tmp_path, "in")
    survey = _wrench_vpc(f / "survey.vpc", [Path(shutil.copy(p, tmp_path / p.name))
                                            for p in parts])
    before = survey.read_bytes()
    with pytest.raises(TilingError, match="replace the input .vpc"):
        clcurv.curvature_file(survey, f, R, method=METHOD)
    assert survey.read_bytes() == before and os.listdir(f) == ["survey.vpc"]


def test_an_index_of_files_without_crs_and_of_one_stem(scene, tmp_path):
    """No CRS: ``proj:wkt2`` an empty string (wrench reads a string), no ``proj:epsg``, the
    native box as the GeoJSON bbox; x.las and x.laz get their names as ids."""
    _, _, pts, kind, strip = scene
    files = [_write(tmp_path / name, pts[strip == k], kind[strip == k], wkt=None)
             for k, name in enumerate(("x.las", "x.laz"))]
    index = vpc.write(tmp_path / "i.vpc", files)
    doc = json.loads(index.read_text())
    props = [f["properties"] for f in doc["features"]]
    assert [f["id"] for f in doc["features"]] == ["x", "x.laz"]
    assert [p["proj:wkt2"] for p in props] == ["", ""]
    assert all("proj:epsg" not in p for p in props)
    assert doc["features"][0]["bbox"] == props[0]["proj:bbox"]
    items = vpc.read(index)
    assert [it.crs.key for it in items] == [None, None]
    assert [it.count for it in items] == [int(np.sum(strip == k)) for k in range(2)]
    assert np.array_equal(items[1].bounds[1], pts[strip == 1].max(axis=0))
    assert [p.name for p in stream.Catalog(index).paths] == ["x.las", "x.laz"]


@pytest.mark.parametrize("workers", [None, 2])
def test_a_file_whose_points_do_not_decode_fails_the_run_on_the_workers(scene, tmp_path,
                                                                        workers):
    """A LAZ of the catalog whose header and chunk table are sound but whose compressed
    points are damaged (200 zero bytes in the middle) passes the checks made before the
    run; the worker that decodes it (pass (1), on a Dask worker with ``workers=2``) fails,
    its retries too, and the run stops with a CorruptFileError naming the file: no
    output, no index, no workspace."""
    if workers:
        pytest.importorskip("distributed")
    d, _, _, _, _ = scene
    f = _folder(tmp_path, "cat")
    for p in NAMES:
        shutil.copy(d / "tiles" / p, f / p)
    data = bytearray((f / "t2.laz").read_bytes())
    start = int.from_bytes(data[96:100], "little") + 300       # the points' first chunk
    data[start:start + 200] = bytes(200)
    (f / "t2.laz").write_bytes(bytes(data))
    out = _folder(tmp_path, "out")
    with pytest.raises(CorruptFileError, match=r"t2\.laz: cannot decode the points"):
        clcurv.curvature_file(f, out, R, method=METHOD, workers=workers)
    assert os.listdir(out) == []


@pytest.mark.parametrize("args", [["s3://survey/t1.laz"], ["https://example.org/t1.copc.laz"],
                                  ["t1.laz", "s3://survey/t2.laz"], ["gs://survey/tiles/"]])
def test_a_url_input_is_refused_as_a_url(tmp_path, args):
    """clcurv reads files by path only (no fsspec, HTTP or S3): a URL as the input, alone or
    in a catalog's list, is one error line that says it is a URL, and nothing is written."""
    pts = np.round(clcurv.shapes.aerial_scene(400, extent=(20.0, 20.0), seed=1)["points"]
                   / SCALE) * SCALE
    _write(tmp_path / "t1.laz", pts, np.full(len(pts), 2, np.uint8))
    args = [str(tmp_path / a) if "://" not in a else a for a in args]
    out = tmp_path / "out"
    out.mkdir()
    r = run_cli("compute", *args, "-o", out / "x.laz" if len(args) == 1 else out,
                "--radius", "1", "-q")
    assert_clean_failure(r, 3, "a URL")
    url = next(a for a in args if "://" in a)
    assert f"{url}: a URL ({url.split(':')[0]}://)" in r.lines[0], r.lines
    assert "same path" in r.lines[0], r.lines
    assert list(out.iterdir()) == []
    with pytest.raises(MissingFileError, match="a URL"):
        clcurv.curvature_file(args if len(args) > 1 else args[0],
                              out / "x.laz" if len(args) == 1 else out, R)


def test_a_url_output_and_a_file_url_and_a_local_name_like_a_url(tmp_path, monkeypatch):
    """-o s3://... is refused as a URL; a file: URL is told to give the path; a local path
    that only looks like a URL (a folder named ``s3:``) is read."""
    from clcurv import io as cio
    pts = np.round(clcurv.shapes.aerial_scene(400, extent=(20.0, 20.0), seed=1)["points"]
                   / SCALE) * SCALE
    src = tmp_path / "t1.laz"
    _write(src, pts, np.full(len(pts), 2, np.uint8))
    r = run_cli("compute", src, "-o", "s3://survey/out.laz", "--radius", "1", "-q")
    assert_clean_failure(r, 3, "a URL output")
    assert "s3://survey/out.laz: a URL (s3://)" in r.lines[0], r.lines
    with pytest.raises(cio.OutputPathError, match="a URL"):
        cio.check_output("https://example.org/out.laz")
    with pytest.raises(MissingFileError, match="give the file's path itself"):
        cio.read(f"file://{src}")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s3:").mkdir()
    np.save(tmp_path / "s3:" / "p.npy", pts)
    assert len(cio.read("s3://p.npy").points) == len(pts)
