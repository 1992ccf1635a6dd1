"""PCD (``.pcd``, Point Cloud Library): ascii, binary and binary_compressed; read only.

Reading
-------
Fields ``x y z`` are the points and ``normal_x normal_y normal_z`` (or ``nx ny nz``) the
normals. Packed ``rgb``/``rgba`` (4 bytes, COUNT 1) become ``red``, ``green``, ``blue`` (and
``alpha``) uint8 attributes; in ascii files the packed value may be PCL's uint32 form or the
float itself. ``_`` padding fields are skipped; every other field (``curvature``...) is an
attribute, ``(N, COUNT)`` when ``COUNT > 1``; repeated field names get a ``__<index>``
suffix. Organised clouds (``HEIGHT > 1``) are flattened in storage order. ``Cloud.header``
is the PCD header as a dict (``version``, ``fields``, ``size``, ``type``, ``count``,
``width``, ``height``, ``viewpoint``, ``points``, ``data``).

binary_compressed data is LZF (liblzf format) holding the fields one after the other;
:func:`lzf_decompress` uses the C extension ``lzf`` (PyPI ``python-lzf``) when installed,
else a pure-Python decoder.
"""
from __future__ import annotations

import io
import struct

import numpy as np

from .common import (CorruptFileError, Format, check_claim, native, quiet, split_named,
                     struct_columns)

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2",
          ("U", 4): "<u4", ("U", 8): "<u8", ("I", 1): "i1", ("I", 2): "<i2",
          ("I", 4): "<i4", ("I", 8): "<i8"}
#: LZF's largest expansion: a 3-byte back reference copies at most 264 bytes
LZF_MAX_RATIO = 88


# --------------------------------------------------------------------------- header

def _header_keys(raw, path):
    """The header lines up to DATA as {KEY: [values]}, and the offset of the first data byte."""
    hdr, pos = {}, 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > 1 << 20:
            raise CorruptFileError(f"{path}: PCD header has no DATA line (expected "
                                   "'DATA ascii|binary|binary_compressed')")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        hdr[key.upper()] = vals
        if key.upper() == "DATA":
            return hdr, pos


def _header_values(hdr, path):
    """(fields, sizes, types, counts, width, height, points, data) from the header keys."""
    try:
        fields = hdr["FIELDS"]
        sizes = [int(s) for s in hdr["SIZE"]]
        types = [t.upper() for t in hdr["TYPE"]]
        counts = [int(c) for c in hdr.get("COUNT", ["1"] * len(fields))]
        width = int(hdr["WIDTH"][0]) if "WIDTH" in hdr else None
        height = int(hdr["HEIGHT"][0]) if "HEIGHT" in hdr else 1
        npts = int(hdr["POINTS"][0]) if "POINTS" in hdr else width * height
        width = npts if width is None else width
        data = hdr["DATA"][0].lower()
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise CorruptFileError(f"{path}: bad PCD header ({type(exc).__name__}: {exc}); "
                               "expected FIELDS, SIZE, TYPE, WIDTH/POINTS and DATA") from None
    return fields, sizes, types, counts, width, height, npts, data


def _check_header(path, fields, sizes, types, counts, data):
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise CorruptFileError(f"{path}: PCD header has {len(fields)} FIELDS but "
                               f"{len(sizes)} SIZE, {len(types)} TYPE, {len(counts)} COUNT")
    if any(c < 1 for c in counts):
        raise CorruptFileError(f"{path}: PCD COUNT {counts} must be >= 1 for every field")
    bad = [(t, s) for t, s in zip(types, sizes) if (t, s) not in _TYPES]
    if bad:
        raise CorruptFileError(f"{path}: unsupported PCD TYPE/SIZE {bad}")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise CorruptFileError(f"{path}: unknown PCD DATA {data!r}; expected ascii, binary "
                               "or binary_compressed")


def _check_shape(path, width, height, npts):
    """WIDTH, HEIGHT and POINTS are >= 0 and POINTS = WIDTH x HEIGHT (as PCL requires)."""
    for key, value in (("WIDTH", width), ("HEIGHT", height), ("POINTS", npts)):
        if value < 0:
            raise CorruptFileError(f"{path}: PCD {key} {value} is negative")
    if width * height != npts:
        raise CorruptFileError(f"{path}: PCD WIDTH {width} x HEIGHT {height} = "
                               f"{width * height} points, but POINTS {npts}")


def _unique_names(fields):
    """Field names made unique for a structured dtype (a repeat gets ``__<index>``)."""
    names, seen = [], set()
    for i, f in enumerate(fields):
        name = f if f not in seen else f"{f}__{i}"
        seen.add(name)
        names.append(name)
    return names


def _parse_header(raw, path):
    """Parse the PCD header; return (dict, offset of the first data byte)."""
    hdr, pos = _header_keys(raw, path)
    fields, sizes, types, counts, width, height, npts, data = _header_values(hdr, path)
    _check_header(path, fields, sizes, types, counts, data)
    _check_shape(path, width, height, npts)
    info = {"version": (hdr.get("VERSION") or [None])[0], "fields": fields, "size": sizes,
            "type": types, "count": counts, "width": width, "height": height,
            "viewpoint": [float(v) for v in hdr.get("VIEWPOINT", [])], "points": npts,
            "data": data, "_names": _unique_names(fields)}
    return info, pos


# --------------------------------------------------------------------------- body

def _ascii_packed_color(a):
    """Packed rgb/rgba from ascii PCD as uint32.

    PCL writes ``rgb`` (TYPE F) in ascii as the uint32 of its bits (e.g. 4286611584); older
    writers print the float itself (a tiny denormal-like number). Integral values in
    [0, 2**32) are taken as the uint32, anything else as the float32 whose bits are kept.
    """
    a = np.asarray(a, dtype=np.float64)
    fin = np.isfinite(a)
    v = a[fin]
    if np.all((v == np.floor(v)) & (v >= 0) & (v < 2.0 ** 32)):
        return np.where(fin, a, 0).astype(np.uint32)
    return a.astype(np.float32).view(np.uint32)


def _ascii_columns(raw, pos, h, specs, dtype, path):
    npts = h["points"]
    packed = {n for n, f, s, c in zip(h["_names"], h["fields"], h["size"], h["count"])
              if f in ("rgb", "rgba") and s == 4 and c == 1}
    text_dtype = np.dtype([(n, "f8") if n in packed else (n, dtype[n]) for n in dtype.names])
    with quiet():  # loadtxt warns on an empty body
        text = raw[pos:].decode("ascii", errors="replace")  # '#' comments may be latin-1
        rows = np.loadtxt(io.StringIO(text), dtype=text_dtype,
                          comments="#", ndmin=1, max_rows=npts)
    if len(rows) != npts:
        raise CorruptFileError(f"{path}: PCD header says POINTS {npts} but the ascii "
                               f"data has {len(rows)} rows")
    end = raw[pos:].rstrip(b" \t")
    if npts and end and not end.endswith((b"\n", b"\r")):
        # a file cut inside its last row read a shortened last number (0.01566753 as 0.015)
        raise CorruptFileError(f"{path}: the ascii PCD data ends inside its last line "
                               "(truncated?): the last point may be cut short; if "
                               "the file is whole, end it with a newline")
    return {n: _ascii_packed_color(rows[n]) if n in packed else native(rows[n])
            for n, _, _ in specs}


def _binary_columns(raw, pos, h, specs, dtype, path):
    npts = h["points"]
    return struct_columns(np.frombuffer(raw, dtype=dtype, count=npts, offset=pos))


def _lzf_payload(raw, pos, npts, itemsize, path):
    """The decompressed bytes of a binary_compressed body: two uint32 sizes, then LZF data."""
    if len(raw) - pos < 8:
        raise CorruptFileError(f"{path}: binary_compressed PCD has no size words")
    csize, usize = struct.unpack_from("<II", raw, pos)
    need = npts * itemsize
    if usize != need:
        raise CorruptFileError(f"{path}: binary_compressed PCD uncompressed size {usize} != "
                               f"{need} expected for POINTS {npts} of {itemsize} bytes")
    comp = raw[pos + 8:pos + 8 + csize]
    check_claim(path, f"{csize} bytes of LZF data", csize, len(comp))
    check_claim(path, f"POINTS {npts} = {usize} bytes compressed by LZF (at most "
                f"{LZF_MAX_RATIO}:1)", -(-usize // LZF_MAX_RATIO), csize, exact=False)
    try:
        return lzf_decompress(comp, usize)
    except ValueError as exc:
        raise CorruptFileError(f"{path}: corrupt LZF data in binary_compressed PCD: {exc}"
                               ) from None


def _compressed_columns(raw, pos, h, specs, dtype, path):
    """Fields stored one after the other (SoA) in the LZF payload."""
    npts = h["points"]
    buf = _lzf_payload(raw, pos, npts, dtype.itemsize, path)
    out, off = {}, 0
    for n, t, c in specs:
        dt = np.dtype(t) if c == 1 else np.dtype((t, (c,)))
        out[n] = native(np.frombuffer(buf, dtype=dt, count=npts, offset=off))
        off += npts * dt.itemsize
    return out


_BODIES = {"ascii": _ascii_columns, "binary": _binary_columns,
           "binary_compressed": _compressed_columns}


def _check_body(raw, pos, h, path):
    """CorruptFileError unless the body can hold POINTS points (before any allocation):
    binary takes POINTS x the point size, ascii two bytes per value (a digit and a
    separator), binary_compressed two size words and 1 byte per 88 of the point data."""
    npts, have = h["points"], len(raw) - pos
    values = sum(h["count"])
    itemsize = sum(s * c for s, c in zip(h["size"], h["count"]))
    point = (f"POINTS {npts} of {itemsize} bytes (SIZE {' '.join(map(str, h['size']))} x "
             f"COUNT {' '.join(map(str, h['count']))})")
    if h["data"] == "ascii":
        check_claim(path, f"POINTS {npts} of {values} values (COUNT "
                    f"{' '.join(map(str, h['count']))})", 2 * npts * values - 1, have,
                    exact=False)
    elif h["data"] == "binary":
        check_claim(path, point, npts * itemsize, have)
    else:
        check_claim(path, f"{point} = {npts * itemsize} bytes compressed by LZF (at most "
                    f"{LZF_MAX_RATIO}:1)", 8 + -(-npts * itemsize // LZF_MAX_RATIO), have,
                    exact=False)


def _columns(raw, pos, h, path):
    """Per-field arrays (N,) or (N, COUNT) from the PCD body."""
    _check_body(raw, pos, h, path)
    specs = [(n, _TYPES[(t, s)], c) for n, t, s, c in
             zip(h["_names"], h["type"], h["size"], h["count"])]
    dtype = np.dtype([(n, t) if c == 1 else (n, t, (c,)) for n, t, c in specs])
    return _BODIES[h["data"]](raw, pos, h, specs, dtype, path)


def _unpack_color(a, alpha):
    """red, green, blue (and alpha) uint8 arrays from packed 4-byte colours."""
    v = a.view(np.uint32)
    out = {"red": ((v >> 16) & 255).astype(np.uint8),
           "green": ((v >> 8) & 255).astype(np.uint8),
           "blue": (v & 255).astype(np.uint8)}
    if alpha:
        out["alpha"] = ((v >> 24) & 255).astype(np.uint8)
    return out


def read(path):
    raw = path.read_bytes()
    h, pos = _parse_header(raw, path)
    cols = _columns(raw, pos, h, path)
    columns = {}
    for name, field_name in zip(h["_names"], h["fields"]):
        a = cols[name]
        if field_name == "_":
            continue  # padding
        if field_name in ("rgb", "rgba") and a.ndim == 1 and a.dtype.itemsize == 4:
            columns.update(_unpack_color(a, field_name == "rgba"))
            continue
        columns[name] = a
    header = {k: v for k, v in h.items() if not k.startswith("_")}
    return split_named(path, "pcd", columns, header)


# --------------------------------------------------------------------------- LZF

def lzf_decompress(data, size):
    """Decompress LZF ``data`` (liblzf format, as in PCD binary_compressed) to ``size`` bytes.

    Uses the C extension ``lzf`` (PyPI ``python-lzf``) when installed, else a pure-Python
    decoder (about 0.6 s for 5 MB of output).

    Parameters
    ----------
    data : bytes-like
        Compressed bytes.
    size : int
        Exact size of the decompressed data.

    Returns
    -------
    bytes

    Raises
    ------
    ValueError
        The data is corrupt or does not decompress to exactly ``size`` bytes, or ``size``
        is more than LZF can expand ``data`` to (checked before allocating the output).
    """
    _check_expansion(data, size)
    if size == 0:
        if len(data):
            raise ValueError(f"{len(data)} compressed bytes for an empty output")
        return b""
    try:
        import lzf          # optional (python-lzf): the pure-Python decoder without it
    except ImportError:
        return lzf_decompress_py(data, size)
    out = lzf.decompress(bytes(data), size)
    if out is None or len(out) != size:
        raise ValueError(f"LZF data does not decompress to {size} bytes")
    return out


def _check_expansion(data, size):
    """ValueError when ``size`` exceeds what ``data`` can expand to (or is negative)."""
    if size < 0 or size > LZF_MAX_RATIO * len(data):
        raise ValueError(f"{len(data)} bytes of LZF data cannot decompress to {size} bytes "
                         f"(LZF expands {LZF_MAX_RATIO}:1 at most)")


def lzf_decompress_py(data, size):
    """Pure-Python LZF decoder (see :func:`lzf_decompress`)."""
    _check_expansion(data, size)
    src = bytes(data)
    out = bytearray(size)
    ip = op = 0
    n = len(src)
    try:
        while ip < n:
            ctrl = src[ip]
            ip += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                ctrl += 1
                if ip + ctrl > n or op + ctrl > size:
                    raise ValueError(f"literal run overflows at input byte {ip - 1}")
                out[op:op + ctrl] = src[ip:ip + ctrl]
                ip += ctrl
                op += ctrl
                continue
            length = ctrl >> 5  # back reference
            if length == 7:
                length += src[ip]
                ip += 1
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                raise ValueError(f"back reference out of range at input byte {ip - 1}")
            dist = op - ref
            if dist >= length:
                out[op:op + length] = out[ref:ref + length]
            else:  # overlapping copy repeats the last `dist` bytes
                out[op:op + length] = (out[ref:op] * (length // dist + 1))[:length]
            op += length
    except IndexError:
        raise ValueError("LZF data is truncated") from None
    if op != size:
        raise ValueError(f"LZF data decompresses to {op} bytes, expected {size}")
    return bytes(out)


FORMAT = Format(reads={".pcd": "PCD (ascii, binary or binary_compressed)"}, read=read)
