"""Read and write point clouds: PLY, PCD, LAS/LAZ, XYZ/TXT/CSV, NPY and NPZ.

:func:`read` returns a :class:`Cloud` (NumPy arrays in float64), :func:`write` writes points,
normals and per-point fields (curvatures, ...) in a format chosen by the file extension.

Rules common to every format
----------------------------
* Points come out as a C-contiguous ``(N, 3)`` float64 array, in file order. Organised clouds
  (PCD with ``HEIGHT > 1``) are flattened row-major, i.e. in storage order.
* Rows whose x, y or z is NaN or +-Inf are dropped on reading, from the points, the normals and
  every attribute alike; ``Cloud.dropped`` counts them. Non-finite *normals* or attributes
  are kept as they are (PCL writes NaN normals where estimation failed).
* Normals are taken from columns or properties named ``nx, ny, nz`` or
  ``normal_x, normal_y, normal_z`` (case-insensitive), when all three are present.
* Every other per-point value becomes an entry of ``Cloud.attributes`` (name -> array whose
  first dimension is N; a PCD field with ``COUNT > 1`` gives an ``(N, COUNT)`` array).
* :func:`write` never reorders, adds or removes points. With ``like=`` (the Cloud the points
  came from) it keeps what the output format can of the input: a LAS/LAZ input's header and
  dimensions in LAS/LAZ, the attributes (colours, intensity, ...) in PLY, NPZ and text
  (:mod:`clcurv.io.carry`), the normals when none are given.

Errors on reading are subclasses of :class:`ReadError`, and their messages start with the
file name: :class:`MissingFileError` (also a ``FileNotFoundError``),
:class:`UnknownFormatError` and :class:`CorruptFileError` (also ``ValueError``), and
:class:`MissingDependencyError` (also ``ImportError``; an optional package such as ``lazrs``
is needed). Bad arguments to :func:`write` raise :class:`WriteError` (a ``ValueError``).

Writing
-------
:func:`write` is atomic: the file is written under a temporary name in the output's folder,
flushed to disk and renamed onto the output (:func:`atomic_output`, also used by
:func:`clcurv.render.render`). A failed or interrupted write leaves the previous file, if any,
byte for byte, and no temporary file. :func:`check_output` checks an output path (extension,
folder, writability) without writing anything, so that a command can refuse a bad ``-o``
before its computation; it raises :class:`OutputPathError`. A write that fails part way
(disk full...) raises :class:`WriteFailedError`, both a :class:`WriteError` and an
``OSError``. Folders are never created: a missing folder is an error.

Optional packages: ``laspy`` for LAS, ``laspy[lazrs]`` for LAZ, and ``python-lzf`` (module
``lzf``) to speed up binary_compressed PCD (a pure-Python LZF decoder is used without it).

Formats
-------
One module per format, reader and writer together, each documenting what it reads and
writes: :mod:`~clcurv.io.ply`, :mod:`~clcurv.io.pcd`, :mod:`~clcurv.io.las` (LAS and LAZ),
:mod:`~clcurv.io.text` (XYZ/TXT/CSV...), :mod:`~clcurv.io.npy` (NPY and NPZ). Each declares
itself as ``FORMAT = Format(reads={ext: description}, read=..., writes={...}, write=...)``
(:class:`clcurv.io.common.Format`); :data:`FORMATS` lists them, and the extension tables
:data:`READ_FORMATS` and :data:`WRITE_FORMATS` are built from it. Adding a format is one
module and one entry in :data:`FORMATS`.
"""
from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
import warnings
from pathlib import Path

from . import carry, las, npy, pcd, ply, text
from .common import (CatalogError, Cloud, CorruptFileError, MissingDependencyError,
                     MissingFileError, ReadError, UnknownFormatError, WriteError, check_fields,
                     check_normals, check_points, from_las, is_las, refuse_urls, url_message,
                     url_scheme)
from .las import LAZ_HINT  # noqa: F401  (kept importable from clcurv.io)
from .pcd import lzf_decompress  # noqa: F401

__all__ = ["Cloud", "read", "write", "check_output", "atomic_output", "lzf_decompress",
           "ReadError", "MissingFileError", "UnknownFormatError", "CorruptFileError",
           "CatalogError", "MissingDependencyError", "WriteError", "OutputPathError",
           "WriteFailedError", "READ_FORMATS", "WRITE_FORMATS", "is_las", "from_las"]


class OutputPathError(WriteError):
    """The output path cannot be written: its extension, a missing folder, a directory in
    its place, a read-only folder or file (:func:`check_output`). Nothing was written."""


class WriteFailedError(WriteError, OSError):
    """Writing failed part way (disk full, file too large, I/O error...): an ``OSError`` of
    the format's writer, re-raised with the output path in the message and the original
    ``errno`` (``errno.ENOSPC``, ``errno.EFBIG``...). The previous file is untouched and the
    temporary file is removed. Also an ``OSError``."""

for _public in (Cloud, ReadError, MissingFileError, UnknownFormatError, CorruptFileError,
                CatalogError, MissingDependencyError, WriteError, OutputPathError,
                WriteFailedError):
    _public.__module__ = __name__  # shown (and pickled) as clcurv.io.<name>, as before
del _public

#: The registry: every supported format, one entry per format module.
FORMATS = (ply.FORMAT, pcd.FORMAT, las.FORMAT, text.FORMAT, npy.FORMAT)


def _by_extension(kind):
    """Extension -> (description, function) over :data:`FORMATS`; ``kind`` is read/write."""
    table = {}
    for fmt in FORMATS:
        for ext, description in getattr(fmt, kind + "s").items():
            if ext in table:
                raise ImportError(f"clcurv.io: two formats {kind} {ext}")
            table[ext] = (description, getattr(fmt, kind))
    return table


_READERS = _by_extension("read")
_WRITERS = _by_extension("write")
#: extension written -> what it keeps of like='s attributes (Format.carries)
_CARRIES = {ext: fmt.carries for fmt in FORMATS for ext in fmt.writes}
#: Extensions understood by :func:`read` (lower case) and what each one means.
READ_FORMATS = {ext: description for ext, (description, _) in _READERS.items()}
#: Extensions understood by :func:`write`.
WRITE_FORMATS = {ext: description for ext, (description, _) in _WRITERS.items()}


def read(path) -> Cloud:
    """Read a point cloud; the format is chosen by the file extension.

    Parameters
    ----------
    path : str or os.PathLike
        A file whose extension is one of :data:`READ_FORMATS` (case-insensitive).

    Returns
    -------
    Cloud
        Points (float64), normals, attributes, header and the number of dropped rows.

    Raises
    ------
    UnknownFormatError
        The extension is not supported.
    MissingFileError
        The file does not exist, or ``path`` is a URL (``s3://``, ``https://``...: files
        are read by path only).
    CorruptFileError
        The content cannot be parsed as the format of its extension.
    MissingDependencyError
        LAS needs ``laspy``; LAZ needs ``laspy`` with a LAZ backend (``pip install
        "laspy[lazrs]"``).

    Notes
    -----
    What each format reads (fields, normals, attributes, header) is described in the
    docstring of its module: :mod:`clcurv.io.ply`, :mod:`clcurv.io.pcd`,
    :mod:`clcurv.io.las`, :mod:`clcurv.io.text`, :mod:`clcurv.io.npy`.
    """
    refuse_urls(path)
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    if ext not in _READERS:
        raise UnknownFormatError(
            f"{path}: unknown point cloud extension {ext or '(none)'!r}; expected one of "
            f"{', '.join(READ_FORMATS)}")
    kind, reader = _READERS[ext]
    if not path.exists():
        raise MissingFileError(f"{path}: no such file (expected a {kind} point cloud)")
    if not path.is_file():
        raise CorruptFileError(f"{path}: not a regular file (expected a {kind} point cloud)")
    try:
        return reader(path)
    except ReadError:
        raise
    except MemoryError:
        raise
    except Exception as exc:  # parser-specific errors, re-raised with the file name
        raise CorruptFileError(f"{path}: cannot read as {kind}: {type(exc).__name__}: {exc}"
                               ) from exc


def write(path, points, fields=None, normals=None, like=None, quantize=None):
    """Write points, optional normals and per-point fields; the format follows the extension.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; its extension is one of :data:`WRITE_FORMATS`.
    points : (N, 3) array_like
        Coordinates (any real dtype; written from float64).
    fields : dict of str -> (N,) array_like, optional
        Per-point scalars such as ``mean_curvature``, ``gaussian_curvature``, ``k1``, ``k2``,
        ``surface_variation``. Names must match ``[A-Za-z_][A-Za-z0-9_.-]*`` and must not be
        x, y, z, nx, ny, nz or normal_x/y/z (any case). Written in the given order.
    normals : (N, 3) array_like, optional
        Unit normals.
    like : Cloud, optional
        The Cloud (from :func:`read`) that the points come from, with the same number of
        points: what the output keeps of it. LAS/LAZ output from a LAS/LAZ ``like``: its
        header (version, point format, scales, offsets, VLRs and EVLRs but a COPC input's:
        the output is a plain LAS/LAZ, :func:`clcurv.io.las.output_header`) and its
        attributes (classification, intensity, GPS time, extra bytes...; an extra-bytes
        dimension named like a field is replaced by the field's); from another format's
        ``like`` (or without ``like``): a fresh header, each axis scaled to its own extent
        (:func:`clcurv.io.las.fresh_scales`), ``like``'s attributes as extra bytes and
        its 8/16-bit red, green, blue as LAS RGB (:func:`clcurv.io.las.carried_plan`).
        PLY, NPZ and text output: ``like``'s
        attributes (colours, intensity, ...), whatever format it was read from, between
        the normals and the fields (:mod:`clcurv.io.carry` says how: dtypes, names, a
        field replacing an attribute of its name). Every format: ``like``'s normals when
        ``normals`` is None. Anything that is not a Cloud, or a Cloud of another size,
        raises WriteError.
    quantize : float, optional
        LAS/LAZ only (WriteError for another format): the radius of the run (file unit),
        to store clcurv's real fields (normals, curvatures, directions, surface variation)
        as integers with the extra-bytes descriptor's scale, e.g. ``mean_curvature`` as
        int32 with scale 1e-4 / radius, NaN as its ``no_data``
        (:func:`clcurv.io.las.quantization`).

    Returns
    -------
    pathlib.Path
        The file written (``path``).

    Raises
    ------
    OutputPathError
        ``path`` cannot be written (:func:`check_output`): unknown extension, missing folder,
        a directory, read-only folder or file. Checked before anything else.
    WriteError
        Bad shapes or names, NaN coordinates in LAS, coordinates out of the int32 range of
        the scale and offset of a LAS ``like=`` header, or a field that LAS cannot hold.
    WriteFailedError
        The write failed part way (disk full ``ENOSPC``, file size limit ``EFBIG``, I/O
        error): a :class:`WriteError` and an ``OSError`` whose message starts with ``path``.
    MissingDependencyError
        LAS needs ``laspy``, LAZ needs ``laspy[lazrs]``.

    Warns
    -----
    clcurv.io.las.LasPrecisionWarning
        A fresh LAS header cannot keep most points to 1e-6 of their extent on an axis (far
        points): :func:`clcurv.io.las.fresh_scales`. The writer's warnings name ``path``.

    Notes
    -----
    The write is atomic (:func:`atomic_output`): on any error, and on ``KeyboardInterrupt``,
    the previous file at ``path`` is left as it was and no other file remains. An existing
    file keeps its permission bits; a symbolic link stays a link and the file it points to
    is replaced.

    How each format stores points, normals and fields (types, precision, header line,
    LAS scales and extra bytes) is described in the docstring of its module:
    :mod:`clcurv.io.ply`, :mod:`clcurv.io.las`, :mod:`clcurv.io.text`, :mod:`clcurv.io.npy`.
    """
    path = check_output(path)
    if quantize is not None and not is_las(path):
        raise WriteError(f"{path}: quantised fields are LAS/LAZ extra bytes; write .las or "
                         ".laz, or leave quantize out")
    pts = check_points(path, points)
    normals = check_normals(path, normals, len(pts))
    fields = check_fields(path, fields, len(pts))
    kind = _CARRIES[path.suffix.lower()]
    carried = {}
    if kind is not None:
        carried, normals = carry.from_like(path, like, len(pts), fields, normals, kind)
        normals = check_normals(path, normals, len(pts))
    with atomic_output(path) as tmp, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        more = {} if quantize is None else {"quantize": float(quantize)}
        _WRITERS[path.suffix.lower()][1](tmp, pts, fields, normals, like, carried, **more)
    for w in caught:                # the writer's warnings, naming path, not the temporary
        warnings.warn(str(w.message).replace(str(tmp), str(path)), w.category, stacklevel=2)
    return path


def kept_attributes(path, like, fields=()):
    """The names of ``like``'s attributes that :func:`write` to ``path`` with ``like=like``
    and the computed ``fields`` (names) keeps (for summaries): LAS/LAZ from a LAS/LAZ
    ``like`` every dimension, from another format its colours and the attributes it takes
    as extra bytes (:func:`clcurv.io.las.carried_plan`); the other formats those
    :mod:`clcurv.io.carry` carries."""
    if like is None:
        return []
    kind = _CARRIES.get(Path(path).suffix.lower())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # write() warns for what it leaves out
        if kind is None:                       # LAS/LAZ
            if from_las(like):
                return list(like.attributes)
            _, rgb, plan = las.carried_plan(path, like, fields)
            return (rgb or []) + list(dict.fromkeys(c.src for c in plan))
        plan = carry.plan(path, carry.specs_of(like.attributes), list(fields), kind)
    return list(dict.fromkeys(c.src for c in plan))


# --------------------------------------------------------------------------- output paths

def _real_target(path):
    """The file that writing ``path`` replaces: the end of a chain of symbolic links."""
    return Path(os.path.realpath(path)) if os.path.islink(path) else path


def _reason(exc):
    return exc.strerror or str(exc) or type(exc).__name__


def _new_temp(target):
    """Create an empty temporary file next to ``target``, named ``.<name>.<random>.tmp<ext>``
    (the real extension stays last: laspy picks LAZ compression and NumPy its suffix by
    it); its mode is what ``open(target, "w")`` would give (0o666 minus the umask)."""
    name = target.name[:180]
    for _ in range(100):
        tmp = target.with_name(f".{name}.{secrets.token_hex(4)}.tmp{target.suffix}")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(target.parent))


def check_not_input(output, source):
    """OutputPathError when ``output`` is the input file ``source`` and would lose what the
    input holds beyond its points: a PLY with other elements than its vertices (a mesh's
    faces), or a PCD (an organised grid, whose non-finite points are dropped on reading).
    LAS/LAZ outputs keep every record and dimension of their input; the other formats
    hold points and their properties only."""
    try:
        same = Path(output).resolve() == Path(source).resolve()
    except (OSError, RuntimeError, TypeError):
        return
    ext = Path(output).suffix.lower()
    if not same or ext not in (".ply", ".pcd"):
        return
    if ext == ".ply":
        try:
            with open(source, "rb") as f:
                head = f.read(1 << 16).split(b"end_header", 1)[0].decode("ascii", "replace")
        except OSError:
            return
        others = [ln.split() for ln in head.splitlines() if ln.startswith("element ")]
        if not any(len(e) == 3 and e[1] != "vertex" and e[2] != "0" for e in others):
            return
    raise OutputPathError(f"{output}: the output is the input file, which would lose what "
                          "it holds beyond the points (a mesh's faces, an organised grid): "
                          "choose another output")


def check_output(path, formats=None, *, what="point cloud") -> Path:
    """Check that ``path`` can be written, without writing it; return it as a Path.

    Meant to be called before a long computation whose result goes to ``path``. The folder
    is not created (no command of clcurv creates folders) and the file is not touched; a
    temporary file is created in the folder and removed again, since ``os.access`` answers
    "writable" on read-only mounts.

    Parameters
    ----------
    path : str or os.PathLike
        The output file.
    formats : collection of str, optional
        Accepted extensions, lower case with the dot (a mapping's keys); default
        :data:`WRITE_FORMATS`. :func:`clcurv.render.check_image_output` passes
        :data:`clcurv.render.IMAGE_FORMATS`.
    what : str
        What is written, for the messages ("point cloud", "image").

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputPathError
        With one message starting with ``path``: a URL (``s3://``, ``https://``...: files
        are written by path only), the extension is not in ``formats`` (the
        accepted ones are listed), the folder does not exist or is not a folder, ``path``
        is a directory or another non-regular file, the folder is not writable (permissions,
        read-only file system), or the existing file is read-only.
    """
    scheme = url_scheme(path)
    if scheme is not None:
        raise OutputPathError(url_message(path, scheme))
    path = Path(os.fspath(path))
    formats = WRITE_FORMATS if formats is None else formats
    ext = path.suffix.lower()
    if ext not in formats:
        raise OutputPathError(f"{path}: cannot write a {what} with extension "
                              f"{ext or '(none)'!r}; expected one of {', '.join(formats)}")
    target = _real_target(path)
    folder = target.parent
    if not folder.exists():
        raise OutputPathError(f"{path}: folder {folder} does not exist (it is not created)")
    if not folder.is_dir():
        raise OutputPathError(f"{path}: {folder} is not a folder")
    if target.is_dir():
        raise OutputPathError(f"{path}: is a directory")
    if target.exists() and not target.is_file():
        raise OutputPathError(f"{path}: exists and is not a regular file")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"{path}: folder {folder} is not writable")
    if target.exists() and not os.access(target, os.W_OK):
        raise OutputPathError(f"{path}: the existing file is read-only")
    try:
        os.unlink(_new_temp(target))
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot create a file in folder {folder}: "
                              f"{_reason(exc)}") from exc
    return path


def _renamed(exc, tmp, path):
    """``exc`` again with the temporary name replaced by ``path`` in its message, or None
    when the message does not name it or the type cannot be rebuilt from a message."""
    if not (len(exc.args) == 1 and isinstance(exc.args[0], str) and str(tmp) in exc.args[0]):
        return None
    try:
        new = type(exc)(exc.args[0].replace(str(tmp), str(path)))
    except Exception:  # a constructor with other arguments: keep the original
        return None
    return new if str(new) != str(exc) else None


def _discard(tmp):
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def _fsync(path, flags=os.O_RDONLY):
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_output(path):
    """Context manager for writing ``path`` atomically; yields the temporary path to write.

    The body writes the whole file to the yielded path (``.<name>.<random>.tmp<ext>`` in the
    folder of ``path``, created empty; the extension of ``path`` stays last). When the body
    returns, the temporary file is flushed to disk (``fsync``), given the permission bits of
    the file it replaces (if any) and renamed onto ``path`` with ``os.replace`` (atomic on
    one file system), then the folder is flushed. When the body raises (any exception,
    ``KeyboardInterrupt`` included) the temporary file is removed and ``path`` is untouched.

    A symbolic link at ``path`` stays a link: the file it points to is replaced. Hard links
    to the old file keep the old content; the new file belongs to the writing user.

    Raises
    ------
    OutputPathError
        The temporary file cannot be created in the folder.
    WriteFailedError
        An ``OSError`` (disk full, file too large...) in the body, the flush or the rename,
        with ``path`` in the message and the original ``errno``.
    Other exceptions of the body propagate, their message naming ``path`` instead of the
    temporary file.
    """
    path = Path(os.fspath(path))
    target = _real_target(path)
    try:
        tmp = _new_temp(target)
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot create a file in folder {target.parent}: "
                              f"{_reason(exc)}") from exc
    try:
        yield tmp
        _fsync(tmp, os.O_RDWR if os.name == "nt" else os.O_RDONLY)
        try:
            mode = stat.S_IMODE(os.stat(target).st_mode)
        except FileNotFoundError:
            pass
        else:
            os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException as exc:
        _discard(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            err = WriteFailedError(f"{path}: write failed: {_reason(exc)}")
            err.errno = exc.errno
            raise err from exc
        renamed = _renamed(exc, tmp, path) if isinstance(exc, Exception) else None
        if renamed is None:
            raise
        raise renamed from exc
    with contextlib.suppress(OSError):  # the rename itself reaches the disk
        _fsync(target.parent)
