"""Readers of the supported point-cloud formats, dispatched on the file extension.

Each format has one small function ``path -> PointCloud`` that extracts the coordinates and the
per-point attributes with the ecosystem's library and hands them to
:meth:`~kbs.io.cloud.PointCloud.from_arrays`. Every failure a bad file can cause, including the
libraries' own exceptions, becomes a :class:`~kbs.errors.CloudFileError` naming the file and the
problem in one line.
"""

from __future__ import annotations

import errno
import io
import logging
import os
import stat
import struct
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, KbsError, ParameterError
from kbs.io.cloud import PointCloud
from kbs.io.segcomp import read_range
from kbs.io.text import TableError, parse_table
from kbs.units import ScanUnits, geokey_units, pyproj_units, units_from_comments, wkt_units

logger = logging.getLogger("kbs.io")

#: LAS attributes kept as fields when the point format has them.
LAS_FIELDS = ("classification", "intensity", "return_number", "number_of_returns", "red", "green", "blue")
#: pypcd4 renames the padding fields ``_`` of a PCD header to this prefix plus random letters.
_PCD_PADDING_PREFIX = "#$%&~~"
#: Fragments of library messages that reveal damaged data, and what they mean.
_DAMAGE_HINTS = {
    "early end-of-file": "truncated",  # plyfile
    "multiple of element size": "truncated",  # numpy.frombuffer in pypcd4 and laspy
    "unpack requires a buffer": "truncated",  # struct, reading a PCD compressed-block header
    "failed to fill whole buffer": "truncated",  # lazrs
    "error in compressed data": "corrupt or truncated",  # lzf, PCD binary_compressed
}
#: KITTI Velodyne records: little-endian float32 x y z intensity.
_KITTI_RECORD = np.dtype("<f4")
_KITTI_COLUMNS = 4
#: Sizes in the LAS public header (LAS 1.0-1.4 specifications).
_LAS_MIN_HEADER = 227
_LAS_VLR_HEADER = 54
_LAS_EVLR_HEADER = 60
#: The LAS versions read (1.0 to 1.4, the published specifications) and point data formats.
_LAS_MAX_MINOR = 4
_LAS_POINT_FORMATS = range(11)


def _one_line(exc: BaseException) -> str:
    """A short one-line description of a library exception."""
    errors = getattr(exc, "errors", None)
    if callable(errors):  # pydantic.ValidationError (pypcd4's header model)
        try:
            details = [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors()[:3]]
        except Exception:  # noqa: BLE001 - fall back to the message below
            details = []
        if details:
            return "invalid header (" + "; ".join(details) + ")"
    lines = str(exc).strip().splitlines()
    text = lines[0].split("; use `usecols`")[0] if lines else type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


@contextmanager
def _library_errors(path: Path, kind: str) -> Iterator[None]:
    """Turn any exception a parsing library raises on a bad file into a CloudFileError.

    Parameters
    ----------
    path : Path
        The file being read.
    kind : str
        Its format, for the message (``"PLY"``, ``"PCD"``, ...).
    """
    try:
        yield
    except KbsError:
        raise
    except OSError as exc:
        raise CloudFileError(
            str(path), f"cannot read the {kind} file: {exc.strerror or _one_line(exc)}"
        ) from exc
    except Exception as exc:
        detail = _one_line(exc)
        state = next((state for hint, state in _DAMAGE_HINTS.items() if hint in detail), "malformed")
        raise CloudFileError(str(path), f"{state} {kind} file: {detail}") from exc


def _check_magic(path: Path, magic: tuple[bytes, ...], kind: str) -> None:
    """Raise unless the file starts with one of ``magic`` (after blank space)."""
    with open(path, "rb") as fp:
        head = fp.read(64).lstrip()
    if not head.startswith(magic):
        signatures = [f"'{m.decode('ascii', 'backslashreplace')}'" for m in magic]
        expected = " or ".join(
            [", ".join(signatures[:-1]), signatures[-1]] if len(signatures) > 1 else signatures
        )
        raise CloudFileError(str(path), f"not a {kind} file (it does not start with {expected})")


def _require_xyz(path: Path, names: tuple[str, ...], where: str) -> None:
    missing = [axis for axis in ("x", "y", "z") if axis not in names]
    if missing:
        raise CloudFileError(
            str(path), f"no {'/'.join(missing)} field in {where} (it has: {', '.join(names) or 'nothing'})"
        )


def _check_count(path: Path, kind: str, expected: int, found: int) -> None:
    if found < expected:
        raise CloudFileError(
            str(path),
            f"truncated {kind} file: the header announces {expected} points, the data holds {found}",
        )
    if found > expected:
        raise CloudFileError(
            str(path),
            f"{kind} file longer than its header says: the header announces {expected} points, the data "
            f"holds {found}",
        )


def _from_structured(
    path: Path,
    data: np.ndarray,
    *,
    skip: Callable[[str], bool] = lambda name: False,
    shape: tuple[int, int] | None = None,
    units: ScanUnits | None = None,
    crs: str | None = None,
) -> PointCloud:
    """A cloud from a structured array with x, y, z fields; every other 1-D field is kept."""
    names = tuple(name for name in data.dtype.names if not skip(name))
    for axis in ("x", "y", "z"):
        kind = data.dtype[axis]
        if kind.shape:
            raise CloudFileError(str(path), f"field {axis!r} holds {int(np.prod(kind.shape))} values a point "
                                 f"({kind.base} of shape {kind.shape}): x, y and z must be one number each")
        if kind.kind not in "fiu":
            raise CloudFileError(str(path), f"field {axis!r} is of type {kind}, not numbers: x, y and z must be "
                                 "integer or floating-point fields")
    fields: dict[str, np.ndarray] = {}
    for name in names:
        if name in ("x", "y", "z"):
            continue
        if data.dtype[name].shape:
            logger.debug("%s: field %r has shape %s per point; not kept", path, name, data.dtype[name].shape)
            continue
        fields[name] = data[name]
    xyz = np.column_stack([data["x"], data["y"], data["z"]]) if len(data) else np.empty((0, 3))
    return PointCloud.from_arrays(xyz, fields, shape=shape, path=str(path), units=units, crs=crs)


#: bytes at most of a PLY header (its lines up to end_header)
_PLY_MAX_HEADER = 1 << 20


def _check_ply_header(path: Path) -> tuple[bool, int]:
    """Say what is wrong with a PLY header that plyfile would only call undecodable: a line that is
    not ASCII (a comment written in another encoding), or no ``end_header`` line. Return whether
    its ``format`` line says ascii, and its number of lines (``end_header`` included)."""
    with open(path, "rb") as fp:
        head = fp.read(_PLY_MAX_HEADER)
    end, end_marker = -1, b""
    for marker in (b"\nend_header\n", b"\nend_header\r\n", b"\rend_header\r"):
        at = head.find(marker)
        if at >= 0 and (end < 0 or at < end):
            end, end_marker = at, marker
    if end < 0:
        raise CloudFileError(str(path), "malformed PLY header: no end_header line"
                             + (f" in its first {_PLY_MAX_HEADER:,} bytes" if len(head) == _PLY_MAX_HEADER else ""))
    for number, line in enumerate(head[:end].split(b"\n"), 1):
        bad = next((i for i, byte in enumerate(line) if byte > 127), None)
        if bad is not None:
            raise CloudFileError(str(path), f"malformed PLY header: line {number} holds byte 0x{line[bad]:02x} at "
                                 f"column {bad + 1}: a PLY header is ASCII ({line[:60].decode('latin-1')!r})")
    lines = head[:end + len(end_marker)].splitlines()
    text = any(line.split()[:2] == [b"format", b"ascii"] for line in lines)
    return text, len(lines)


#: bytes at most of blank space after a PLY file's last element that are read to check they are
#: blank (more than this, blank or not, is data the header does not declare)
_PLY_MAX_TRAILER = 1 << 16


def _ply_elements(ply) -> str:
    return ", ".join(f"{element.count:,} {element.name}" for element in ply.elements)


def _check_ply_end_binary(path: Path, ply, end: int) -> None:
    """Refuse a binary PLY with data after its last element: an element count (the vertex count,
    most often) that understates the data would drop points silently. Blank space is allowed."""
    extra = path.stat().st_size - end
    if extra <= 0:
        return
    with open(path, "rb") as fp:
        fp.seek(end)
        if extra <= _PLY_MAX_TRAILER and not fp.read(extra).strip():
            return
    import plyfile

    last = ply.elements[-1] if ply.elements else None
    record = (last.data.dtype.itemsize if last is not None
              and not any(isinstance(p, plyfile.PlyListProperty) for p in last.properties) else 0)
    room = f" (room for {extra // record:,} more {last.name} records)" if record and extra >= record else ""
    raise CloudFileError(
        str(path),
        f"PLY file longer than its header says: its elements ({_ply_elements(ply)}) end at byte {end:,}, and "
        f"{extra:,} bytes more follow them{room}: an element count understates the data",
    )


def _check_ply_end_ascii(path: Path, ply, stream, header_lines: int) -> None:
    """Refuse an ascii PLY with lines after its last element (blank lines allowed): ``stream`` is
    where plyfile stopped, one line an element after the ``header_lines`` of the header."""
    consumed = header_lines + sum(element.count for element in ply.elements)
    first, more = 0, 0
    for number, line in enumerate(stream, consumed + 1):
        if line.strip():
            first = first or number
            more += 1
    if more:
        raise CloudFileError(
            str(path),
            f"PLY file longer than its header says: its elements ({_ply_elements(ply)}) end on line "
            f"{consumed:,}, and {more:,} more lines follow them (from line {first:,}): an element count "
            "understates the data",
        )


def read_ply(path: Path) -> PointCloud:
    """Read the ``vertex`` element of an ascii or binary PLY file (plyfile); list properties are skipped.

    Data after the last element the header declares (but blank space) is an error, as it is in a
    PCD file: an element count that understates the data would otherwise drop points silently."""
    _check_magic(path, (b"ply",), "PLY")
    text, header_lines = _check_ply_header(path)
    import plyfile  # each format's library is imported when a file of that format is read

    with _library_errors(path, "PLY"), open(path, "rb") as raw:
        if text:  # read as plyfile reads it, through a text layer, and see where it stopped
            stream = io.TextIOWrapper(raw, "ascii")
            ply = plyfile.PlyData.read(stream)
            _check_ply_end_ascii(path, ply, stream, header_lines)
        else:
            ply = plyfile.PlyData.read(raw)  # memory-mapped when it can be; from_arrays copies
            _check_ply_end_binary(path, ply, raw.tell())
    elements = {element.name: element for element in ply.elements}
    if "vertex" not in elements:
        raise CloudFileError(str(path), f"no vertex element (it has: {', '.join(elements) or 'nothing'})")
    vertex = elements["vertex"]
    scalars = tuple(p.name for p in vertex.properties if not isinstance(p, plyfile.PlyListProperty))
    _require_xyz(path, scalars, "the PLY vertex element")
    if not text:
        _check_ply_byte_order(path, vertex.data, ply.byte_order)
    units, crs = _declared_units(path, [*ply.comments, *ply.obj_info], "PLY")
    return _from_structured(path, vertex.data, skip=lambda name: name not in scalars, units=units, crs=crs)


#: a coordinate is implausible when not finite or beyond this magnitude (in any unit a scan is
#: given in), or non-zero below :data:`_TINY`: what floats read in the wrong byte order look like
_HUGE, _TINY = 1e12, 1e-30


def _implausible(v: np.ndarray) -> float:
    """The share of ``v`` (floats) that is not finite, beyond :data:`_HUGE` or non-zero below :data:`_TINY`."""
    a = np.abs(v.astype(np.float64))
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(a) | (a > _HUGE) | ((a > 0.0) & (a < _TINY))
    return float(bad.mean()) if a.size else 0.0


def _check_ply_byte_order(path: Path, data: np.ndarray, declared: str) -> None:
    """A binary PLY whose header names the wrong byte order reads as coordinates like 1e38 and NaN;
    the bytes cannot say which order is right, but when at least a tenth of x, y and z read
    implausible in the declared order and almost none (under 0.1 %) in the other, the header is
    wrong: an error naming both orders, not a segmentation of nonsense."""
    if declared not in "<>" or data.size < 16:
        return
    names = [n for n in ("x", "y", "z") if data.dtype[n].kind == "f" and data.dtype[n].itemsize > 1]
    if len(names) < 3:
        return
    order = {"<": "binary_little_endian", ">": "binary_big_endian"}
    given = max(_implausible(data[n]) for n in names)
    if given < 0.1:
        return
    other = max(_implausible(data[n].view(data.dtype[n].newbyteorder())) for n in names)
    if other < 0.001:
        raise CloudFileError(str(path), f"the header says 'format {order[declared]}', but its x, y, z read as "
                                        f"{order['<' if declared == '>' else '>']} ({given:.0%} of one coordinate's values are NaN, "
                                        f"infinite or beyond {_HUGE:.0e} as declared, {other:.1%} in the other "
                                        f"order); correct the header's format line")


def _declared_units(path: Path, comments: list[str], kind: str) -> tuple[ScanUnits | None, str | None]:
    """The ``units`` and ``crs`` a header's comment lines declare (:func:`kbs.units.units_from_comments`)."""
    try:
        return units_from_comments(comments, kind)
    except ParameterError as exc:
        raise CloudFileError(str(path), str(exc)) from exc


#: PCD header lines at most before DATA (a header has 10 keywords, plus comments).
_PCD_MAX_HEADER_LINES = 1000


def _pcd_header(path: Path) -> tuple[list[str], list[str], int]:
    """The keyword lines and the ``#`` comment lines (without the ``#``) of a PCD header, and the
    byte offset of its data."""
    lines: list[str] = []
    comments: list[str] = []
    offset = 0
    with open(path, "rb") as fp:
        for _ in range(_PCD_MAX_HEADER_LINES):
            raw = fp.readline()
            if not raw:
                break
            offset += len(raw)
            line = raw.decode("utf-8", errors="replace").strip()
            if line.startswith("#"):
                comments.append(line[1:].strip())
            elif line:
                lines.append(line)
                if line.upper().startswith("DATA"):
                    return lines, comments, offset
    raise CloudFileError(str(path), "malformed PCD header: no DATA line")


def _pcd_header_as_v07(path: Path, lines: list[str]) -> tuple[list[str], bool]:
    """The keyword lines of a PCD header checked (FIELDS, SIZE, TYPE and COUNT of one length) and
    written as version 0.7 where they are of 0.5 or 0.6, as PCL reads those (no VIEWPOINT: the
    identity; no COUNT: one value a field); and whether they changed."""
    keys = {line.split()[0].upper(): i for i, line in enumerate(lines) if line.split()}
    fields = lines[keys["FIELDS"]].split()[1:] if "FIELDS" in keys else None
    if fields is not None:
        for key in ("SIZE", "TYPE", "COUNT"):
            if key in keys and len(lines[keys[key]].split()) - 1 != len(fields):
                raise CloudFileError(str(path), f"malformed PCD header: {key} has {len(lines[keys[key]].split()) - 1} "
                                     f"values for the {len(fields)} FIELDS ({' '.join(fields)})")
    version = lines[keys["VERSION"]].split()[1:2] if "VERSION" in keys else []
    if version not in (["0.5"], [".5"], ["0.6"], [".6"]):
        return lines, False
    out = list(lines)
    out[keys["VERSION"]] = "VERSION 0.7"
    data = keys.get("DATA", len(out) - 1)
    extra = []
    if "COUNT" not in keys and fields is not None:
        extra.append("COUNT " + " ".join("1" for _ in fields))
    if "VIEWPOINT" not in keys:
        extra.append("VIEWPOINT 0 0 0 1 0 0 0")
    return out[:data] + extra + out[data:], True


def read_pcd(path: Path) -> PointCloud:
    """Read an ascii, binary or binary_compressed PCD file (pypcd4); HEIGHT > 1 gives an organised cloud.

    The ascii body is read with numpy, columns separated by any run of spaces or tabs (as PCL and
    Open3D read it; pypcd4 itself accepts only single spaces). ``# units mm`` and ``# crs ...``
    comment lines of the header declare the coordinates' units and CRS."""
    _check_magic(path, (b"#", b"VERSION", b"FIELDS"), "PCD")
    import pypcd4

    lines, comments, offset = _pcd_header(path)
    lines, changed = _pcd_header_as_v07(path, lines)
    with _library_errors(path, "PCD"):
        meta = pypcd4.MetaData.parse_header(lines)
    _check_pcd_header(path, meta, offset)
    with _library_errors(path, "PCD"):
        if lines[-1].split()[1:2] == ["ascii"]:
            with open(path, "rb") as fp:
                fp.seek(offset)
                data = _pcd_ascii(path, fp, meta.build_dtype(), meta.points)
        elif changed:  # an older header (PCD 0.5/0.6): pypcd4 reads 0.7 only, given the same body
            with open(path, "rb") as fp:
                fp.seek(offset)
                pcd = pypcd4.PointCloud.from_fileobj(io.BufferedReader(io.BytesIO(
                    ("\n".join(lines) + "\n").encode() + fp.read())))  # type: ignore[arg-type]
            meta, data = pcd.metadata, np.atleast_1d(pcd.pc_data)
        else:
            pcd = pypcd4.PointCloud.from_path(path)
            meta, data = pcd.metadata, np.atleast_1d(pcd.pc_data)
    _check_count(path, "PCD", meta.points, len(data))
    if lines[-1].split()[1:2] == ["binary"]:  # PCL reads the POINTS it is told and ignores the rest
        record = data.dtype.itemsize
        extra = path.stat().st_size - offset - meta.points * record
        if extra >= record and not _zero_padding(path, extra):
            raise CloudFileError(
                str(path),
                f"PCD file longer than its header says: the header announces {meta.points:,} points "
                f"({meta.points * record:,} bytes of binary data), and {extra:,} bytes more follow them "
                f"(room for {extra // record:,} more points): POINTS, WIDTH or HEIGHT understates the data",
            )
    names = tuple(name for name in data.dtype.names if not name.startswith(_PCD_PADDING_PREFIX))
    _require_xyz(path, names, "the PCD header")
    shape = (meta.height, meta.width) if meta.height > 1 else None
    units, crs = _declared_units(path, comments, "PCD")
    return _from_structured(path, data, skip=lambda name: name.startswith(_PCD_PADDING_PREFIX), shape=shape,
                            units=units, crs=crs)


#: The SIZE of each PCD TYPE that PCL and pypcd4 read (bytes a value).
_PCD_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_PCD_SIZES_TEXT = "TYPE F has SIZE 4 or 8; I and U have 1, 2, 4 or 8"


def _check_pcd_header(path: Path, meta, offset: int) -> None:
    """Refuse what pypcd4 would only name cryptically or try to allocate: a field of a SIZE its TYPE
    does not have, WIDTH x HEIGHT other than POINTS (HEIGHT is 1 for an unorganised cloud, as the
    PCD specification and PCL require), or a binary body shorter than POINTS records."""
    for column, (name, kind, size) in enumerate(zip(meta.fields, meta.type, meta.size), 1):
        if size not in _PCD_SIZES.get(kind, ()):
            raise CloudFileError(str(path), f"malformed PCD header: field {name!r} (column {column} of FIELDS) has "
                                 f"TYPE {kind} and SIZE {size}, a pair that is not supported ({_PCD_SIZES_TEXT})")
    if meta.width * meta.height != meta.points:
        raise CloudFileError(
            str(path),
            f"malformed PCD header: WIDTH {meta.width} x HEIGHT {meta.height} != POINTS {meta.points} "
            "(an unorganised cloud has HEIGHT 1 and WIDTH = POINTS)",
        )
    if meta.data.value == "binary":
        record = sum(size * count for size, count in zip(meta.size, meta.count))
        held = path.stat().st_size - offset
        if meta.points * record > held:
            raise CloudFileError(
                str(path),
                f"truncated PCD file: the header announces {meta.points} points, the data holds {held // record} "
                f"({meta.points * record:,} bytes of binary data announced, {held:,} bytes after the header)",
            )


def _zero_padding(path: Path, extra: int) -> bool:
    """Whether the last ``extra`` bytes of the file are zeros, less than a few pages of them: PCL's
    binary writer pads its files to the page size with zeros (the shared Bobkov room: 3,910 bytes)."""
    if extra > 1 << 16:
        return False
    with open(path, "rb") as fp:
        fp.seek(-extra, io.SEEK_END)
        return not fp.read(extra).strip(b"\0")


def _pcd_ascii(path: Path, fp, dtype: np.dtype, n_points: int) -> np.ndarray:
    """The body of an ascii PCD: one point a line, values separated by blanks (any number)."""
    if n_points == 0:
        return np.empty(0, dtype)
    try:
        return np.atleast_1d(np.loadtxt(fp, dtype=dtype, ndmin=1, comments="#"))
    except ValueError as exc:
        raise CloudFileError(str(path), f"malformed PCD file: {_one_line(exc)}") from exc


def _check_las_layout(path: Path, kind: str) -> None:
    """Check that the header's sizes and record counts fit in the file.

    laspy loops over the header's VLR and EVLR counts without checking for the end of the file,
    so a damaged header (say 3 billion VLRs) would make it spin for minutes.
    """
    size = path.stat().st_size
    with open(path, "rb") as fp:
        head = fp.read(_LAS_MIN_HEADER + 24)
    if len(head) < _LAS_MIN_HEADER:
        raise CloudFileError(str(path), f"truncated {kind} file: {size} bytes, shorter than a LAS header")
    major, minor = head[24], head[25]
    header_size, offset_to_points, n_vlrs = struct.unpack_from("<HII", head, 94)
    if (
        not header_size <= offset_to_points <= size
        or header_size + n_vlrs * _LAS_VLR_HEADER > offset_to_points
    ):
        raise CloudFileError(
            str(path),
            f"malformed {kind} header: {n_vlrs} VLRs and point data at byte {offset_to_points} "
            f"do not fit a {size}-byte file",
        )
    if major != 1 or minor > _LAS_MAX_MINOR:  # laspy would read its fields at the wrong places
        raise CloudFileError(str(path), f"unsupported {kind} version {major}.{minor} (header bytes 24-25): "
                             f"LAS 1.0 to 1.{_LAS_MAX_MINOR} are read")
    point_format = head[104]
    if point_format & 0x3F not in _LAS_POINT_FORMATS:  # bits 7 and 6 mark compressed (LAZ) points
        raise CloudFileError(str(path), f"malformed {kind} header: unknown point data format {point_format} "
                             f"(header byte 104; LAS defines formats 0 to {max(_LAS_POINT_FORMATS)}, "
                             "plus 128 when compressed)")
    if minor >= 4 and len(head) >= 247:
        start_of_evlrs, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and start_of_evlrs + n_evlrs * _LAS_EVLR_HEADER > size:
            raise CloudFileError(
                str(path), f"malformed {kind} header: {n_evlrs} extended VLRs do not fit a {size}-byte file"
            )


def _check_las_length(path: Path, kind: str, point_count: int) -> None:
    """Refuse an uncompressed LAS file whose point data region holds more whole records than its
    header's point count: laspy reads the count it is told, and the points after it would be dropped
    silently. The region runs from the offset to point data to the end of the file, or to the start
    of the extended VLRs (LAS 1.4) or of internal waveform data (LAS 1.3+) when these follow it."""
    size = path.stat().st_size
    with open(path, "rb") as fp:
        head = fp.read(_LAS_MIN_HEADER + 28)
    if head[104] & 0x80:  # compressed (LAZ): the records' size says nothing of their number
        return
    minor = head[25]
    offset_to_points, = struct.unpack_from("<I", head, 96)
    record, = struct.unpack_from("<H", head, 105)
    end = size
    if minor >= 3 and len(head) >= 235:
        waveform, = struct.unpack_from("<Q", head, 227)
        if offset_to_points < waveform < end:
            end = waveform
    if minor >= 4 and len(head) >= 247:
        start_of_evlrs, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and offset_to_points < start_of_evlrs < end:
            end = start_of_evlrs
    if not record:
        return
    room = (end - offset_to_points) // record
    if room > point_count:
        extra = end - offset_to_points - point_count * record
        raise CloudFileError(
            str(path),
            f"{kind} file longer than its header says: the header announces {point_count:,} points "
            f"({point_count * record:,} bytes of point records from byte {offset_to_points:,}), and {extra:,} "
            f"bytes more follow them (room for {room - point_count:,} more points): its point count understates "
            "the data",
        )


def _check_las_bounds(path: Path, kind: str, header, xyz: np.ndarray) -> None:
    """Refuse a file whose points lie far outside the bounds its header declares: farther than the
    bounds' own largest side (and than 1,000 scale steps), beyond what a writer's rounding or a
    stale header gives. Points decoded from a damaged LAZ land kilometres away. A header that
    declares no bounds (all zeros, or minima above maxima) is not checked."""
    lo = np.asarray(header.mins, dtype=np.float64)
    hi = np.asarray(header.maxs, dtype=np.float64)
    if not xyz.shape[0] or not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (lo > hi).any() \
            or not (lo.any() or hi.any()):
        return
    slack = max(float((hi - lo).max()), 1000.0 * float(np.max(header.scales)))
    far = ((xyz < lo - slack) | (xyz > hi + slack)).any(axis=1)
    n = int(far.sum())
    if n:
        i = int(np.flatnonzero(far)[0])
        raise CloudFileError(
            str(path),
            f"{n:,} of its {xyz.shape[0]:,} points lie far outside its header's bounds (point {i:,} at "
            f"{xyz[i, 0]:.9g}, {xyz[i, 1]:.9g}, {xyz[i, 2]:.9g}; z {lo[2]:.9g}..{hi[2]:.9g}): damaged, or a wrong header",
        )


def read_las(path: Path) -> PointCloud:
    """Read a LAS or LAZ file (laspy, lazrs backend): scaled float64 xyz, the LAS_FIELDS present and
    every extra-bytes dimension; the CRS and its units (:func:`las_crs`); the ``laspy.LasData`` kept
    as the cloud's ``source`` (LAS output writes the file's own records back)."""
    kind = "LAZ" if path.suffix.lower() == ".laz" else "LAS"
    _check_magic(path, (b"LASF",), kind)
    _check_las_layout(path, kind)
    import laspy

    with _library_errors(path, kind):
        las = laspy.read(path)
        _check_count(path, kind, las.header.point_count, len(las.points))
        _check_las_length(path, kind, las.header.point_count)
        scales = np.asarray(las.header.scales, dtype=np.float64)
        if not (np.isfinite(scales).all() and (scales > 0).all()):
            raise CloudFileError(str(path), f"malformed {kind} header: the x, y, z scale factors "
                                 f"{', '.join(f'{v:g}' for v in scales)} must be positive numbers")
        xyz = np.column_stack(
            [
                np.asarray(las.x, dtype=np.float64),
                np.asarray(las.y, dtype=np.float64),
                np.asarray(las.z, dtype=np.float64),
            ]
        )
        _check_las_bounds(path, kind, las.header, xyz)
        present = set(las.point_format.dimension_names)
        fields = {name: np.asarray(las[name]) for name in LAS_FIELDS if name in present}
        for name in las.point_format.extra_dimension_names:
            values = np.asarray(las[name])
            if values.ndim == 1 and name not in fields:
                fields[name] = values
    units, crs = las_crs(las.header, path)
    return PointCloud.from_arrays(xyz, fields, path=str(path), units=units, crs=crs, source=las)


def las_crs(header, path: str | os.PathLike[str] | None = None) -> tuple[ScanUnits | None, str | None]:
    """The units and the CRS text of a LAS header (of the file ``path``: a CRS whose unit is no
    length, 0 or NaN metres, is then a CloudFileError naming it; without ``path`` a ParameterError).

    With pyproj (``pip install 'kbs[crs]'``), laspy's ``parse_crs`` reads the WKT or GeoTIFF
    records and the text is the CRS's WKT. Without it, the WKT record's text is kept as it is and
    its UNIT nodes give the units; GeoTIFF keys give them through ProjLinearUnitsGeoKey /
    VerticalUnitsGeoKey (the CRS text is then ``EPSG:<ProjectedCSTypeGeoKey>``)."""
    try:
        return _las_crs(header)
    except ParameterError as exc:
        if path is None:
            raise
        raise CloudFileError(os.fspath(path), f"its CRS: {exc}") from exc


def _las_crs(header) -> tuple[ScanUnits | None, str | None]:
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    source = "the LAS file's CRS"
    vlrs = list(header.vlrs) + list(header.evlrs or [])
    wkt = next((v.string for v in vlrs if isinstance(v, WktCoordinateSystemVlr) and v.string.strip()), None)
    keys: dict[int, int] = {}
    for v in vlrs:
        if isinstance(v, GeoKeyDirectoryVlr):
            keys.update({k.id: k.value_offset for k in v.geo_keys if k.tiff_tag_location == 0})
    try:
        crs = header.parse_crs()
    except ImportError:  # no pyproj: the text as it is
        crs = None
    except Exception:  # noqa: BLE001 - a CRS pyproj cannot read: fall back on the text
        logger.debug("laspy could not parse the CRS", exc_info=True)
        crs = None
    if crs is not None:
        units = pyproj_units(crs, source) or (wkt_units(wkt, source) if wkt else geokey_units(keys, source))
        return units, wkt or crs.to_wkt()
    if wkt:
        return wkt_units(wkt, source) or geokey_units(keys, source), wkt
    epsg = keys.get(3072)
    text = f"EPSG:{epsg}" if epsg not in (None, 0, 32767) else None
    return geokey_units(keys, source), text


def read_e57(path: Path) -> PointCloud:
    """Read every scan of an E57 file (pye57, ``pip install 'kbs[e57]'``), each placed by its pose,
    with intensity and colours where present; coordinates are metres (the E57 standard)."""
    _check_magic(path, (b"ASTM-E57",), "E57")
    try:
        import pye57
    except ImportError as exc:
        raise CloudFileError(str(path), "reading E57 needs the optional package pye57: pip install 'kbs[e57]'") from exc
    from kbs.units import ScanUnits as _Units

    with _library_errors(path, "E57"):
        e57 = pye57.E57(str(path))
        try:
            scans = [e57.read_scan(i, ignore_missing_fields=True, intensity=True, colors=True, transform=True)
                     for i in range(e57.scan_count)]
        finally:
            close = getattr(e57, "close", None)
            if callable(close):
                close()
    if not scans:
        raise CloudFileError(str(path), "the E57 file holds no scan")
    xyz = np.concatenate([np.column_stack([s["cartesianX"], s["cartesianY"], s["cartesianZ"]]) for s in scans])
    fields: dict[str, np.ndarray] = {}
    names = {"intensity": "intensity", "colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
    for key, name in names.items():
        if all(key in s and len(s[key]) == len(s["cartesianX"]) for s in scans):
            fields[name] = np.concatenate([np.asarray(s[key]) for s in scans])
    if len(scans) > 1:
        fields["scan"] = np.concatenate([np.full(len(s["cartesianX"]), i, dtype=np.int32) for i, s in enumerate(scans)])
    return PointCloud.from_arrays(xyz, fields, path=str(path), units=_Units.uniform("m", source="E57 (metres)"))


def read_text(path: Path) -> PointCloud:
    """Read a whitespace- or comma-separated table: x y z, then extra columns kept as float64 fields.

    Extra columns are named from the header line if there is one, else ``col3``, ``col4`` ... by
    their 0-based position. A header naming ``x``, ``y`` and ``z`` (any case) picks those columns;
    one naming none of them leaves x, y, z the first three; one naming some but not all, or a
    column twice, is an error. A point count line (a ``.pts`` file's first line) must match the
    number of data lines.
    """
    text = path.read_bytes().decode("utf-8-sig", errors="replace")
    try:
        table = parse_table(text)
    except TableError as exc:
        raise CloudFileError(str(path), str(exc)) from exc
    values, names = table.values, table.names
    n_columns = values.shape[1]
    kind = "PTS" if path.suffix.lower() == ".pts" else "text"
    if table.count is not None and table.count != values.shape[0]:
        state = f"truncated {kind} file" if table.count > values.shape[0] else f"{kind} file longer than its point count says"
        raise CloudFileError(str(path), f"{state}: the point count on line {table.count_line} announces "
                             f"{table.count:,} points, the data holds {values.shape[0]:,} lines")
    lowered = [name.lower() for name in names] if names else []
    if names:
        _check_text_header(path, names, table.header_line)
    if all(axis in lowered for axis in ("x", "y", "z")):
        xyz_columns = [lowered.index(axis) for axis in ("x", "y", "z")]
    else:
        xyz_columns = [0, 1, 2]
    fields: dict[str, np.ndarray] = {}
    for column in range(n_columns):
        if column in xyz_columns:
            continue
        name = names[column] if names else f"col{column}"
        if name in fields:
            raise CloudFileError(str(path), f"the header names two columns {name!r}")
        fields[name] = values[:, column]
    return PointCloud.from_arrays(values[:, xyz_columns], fields, path=str(path))


def _check_text_header(path: Path, names: tuple[str, ...], line: int | None) -> None:
    """Refuse a text header that names a column twice (x, y and z in any case, as they are picked),
    or some of x, y, z but not all: its columns would be taken silently for others."""
    where = f"the header on line {line}"
    seen: dict[str, int] = {}
    for column, name in enumerate(names, 1):
        key = name.lower() if name.lower() in ("x", "y", "z") else name
        if key in seen:
            raise CloudFileError(str(path), f"{where} names {key!r} twice (columns {seen[key]} and {column}: "
                                 f"{' '.join(names)[:80]})")
        seen[key] = column
    named = [axis for axis in ("x", "y", "z") if axis in seen]
    if named and len(named) < 3:
        missing = [axis for axis in ("x", "y", "z") if axis not in seen]
        raise CloudFileError(str(path), f"{where} names {', '.join(named)} but no {'/'.join(missing)} column "
                             f"({' '.join(names)[:80]})")


#: an .npy array with more columns than this and than rows is taken for a transposed cloud
_NPY_MAX_COLUMNS = 64


def read_npy(path: Path) -> PointCloud:
    """Read a ``.npy`` array: (N, 3+) numbers (x y z, then ``intensity``, ``col4`` ...) or a structured
    array with x, y, z fields (a 2-D structured array is an organised cloud)."""
    _check_magic(path, (b"\x93NUMPY",), "NPY")
    with _library_errors(path, "NPY"):
        array = np.load(path, allow_pickle=False)
    if not isinstance(array, np.ndarray):
        raise CloudFileError(str(path), "not a single .npy array")
    if array.dtype.names is not None:
        _require_xyz(path, array.dtype.names, "the structured array")
        if array.ndim not in (1, 2):
            raise CloudFileError(
                str(path), f"a structured array of shape {array.shape}; expected (N,) or (rows, cols)"
            )
        shape = (array.shape[0], array.shape[1]) if array.ndim == 2 else None
        return _from_structured(path, array.reshape(-1), shape=shape)
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise CloudFileError(
            str(path),
            f"expected an (N, 3+) array of numbers or x/y/z fields, got {array.dtype} {array.shape}",
        )
    if array.shape[1] > max(_NPY_MAX_COLUMNS, array.shape[0]):
        raise CloudFileError(
            str(path),
            f"an array of {array.shape[0]} rows and {array.shape[1]} columns: a cloud is one point per row "
            f"(x, y, z, then its attributes); saved transposed? (np.save(path, points.T))",
        )
    fields = {
        ("intensity" if column == 3 else f"col{column}"): array[:, column]
        for column in range(3, array.shape[1])
    }
    return PointCloud.from_arrays(array[:, :3], fields, path=str(path))


#: the share of a KITTI .bin's records whose 4th float (the remission, 0 to 1 in KITTI's scans) may
#: be negative before the file is taken for another layout read 4 floats at a time
_KITTI_MAX_NEGATIVE_REMISSION = 0.01


#: bytes at the start of a .bin that are looked at to tell a text file from float32 records
_TEXT_SAMPLE = 4096
#: the bytes of text (:func:`_looks_like_text`): printable ASCII, space, tab, CR, LF
_TEXT_BYTES = frozenset(range(0x20, 0x7F)) | frozenset(b"\t\r\n")


def _looks_like_text(path: Path) -> bool:
    """Whether the file's first :data:`_TEXT_SAMPLE` bytes (all of it, if shorter) are printable
    ASCII characters, spaces, tabs and line breaks, with at least one line break: a text table.
    Float32 records do not pass: 98 of the 256 byte values are text; a negative value's last byte
    is 0x80 or more, the low bytes of a round value are 0x00 and those of any other are close to
    random (the chance that 4 KiB of them pass is far below 0.4**1000)."""
    with open(path, "rb") as fp:
        head = fp.read(_TEXT_SAMPLE)
    return bool(head) and (b"\n" in head or b"\r" in head) and set(head) <= _TEXT_BYTES


def read_kitti_bin(path: Path) -> PointCloud:
    """Read a KITTI Velodyne ``.bin`` scan: little-endian float32 records x y z intensity.

    A file whose start is text (:func:`_looks_like_text`) is refused: read 4 bytes at a time its
    characters would make points far from anything."""
    record = _KITTI_COLUMNS * _KITTI_RECORD.itemsize
    with open(path, "rb") as fp:
        magic = fp.read(6)
    if magic == b"\x93NUMPY":  # its header would be read as points, and the rows shifted
        raise CloudFileError(str(path), "an .npy array, not float32 records: give --in-format npy")
    if _looks_like_text(path):
        raise CloudFileError(
            str(path),
            f"looks like text, not float32 records (its first {min(path.stat().st_size, _TEXT_SAMPLE):,} bytes "
            "are printable ASCII and line breaks): give --in-format xyz (or csv)",
        )
    size = path.stat().st_size
    if size % record:
        raise CloudFileError(
            str(path),
            f"size {size} bytes is not a multiple of {record} "
            "(KITTI .bin records are float32 x y z intensity)",
        )
    array = np.fromfile(path, dtype=_KITTI_RECORD).reshape(-1, _KITTI_COLUMNS)
    xyz = array[:, :3]
    tiny = int(np.count_nonzero((xyz != 0) & (np.abs(xyz) < np.finfo(np.float32).tiny)))
    if tiny > 0.5 * xyz.size:  # integers (labels, counts) read as float32 are subnormal: no scanner measures 1e-40 m
        raise CloudFileError(
            str(path),
            f"not float32 coordinates: {tiny:,} of its {xyz.size:,} x, y, z values are subnormal (below "
            f"{np.finfo(np.float32).tiny:.3g}), as integers read as float32 are (a .label file?)",
        )
    negative = int(np.count_nonzero(array[:, 3] < 0))
    if negative > _KITTI_MAX_NEGATIVE_REMISSION * array.shape[0]:
        # a remission is never negative; coordinates are, about half the time in a sensor frame:
        # records of 3 or 5 floats (nuScenes' x y z intensity ring) read 4 at a time put them there
        raise CloudFileError(
            str(path),
            f"not KITTI's x y z remission layout: the 4th float32 of {negative:,} of {array.shape[0]:,} "
            f"records is negative, as no remission is (records of 3 or 5 floats?); save them as .npy",
        )
    smoother = _smoother_layout(path, array)
    if smoother is not None:
        raise CloudFileError(
            str(path),
            f"not KITTI's x y z remission layout: read {smoother} float32 a record, consecutive points lie "
            f"next to each other as a scanner's do, and read 4 at a time they do not (records of {smoother} "
            f"floats?); save them as .npy",
        )
    return PointCloud.from_arrays(array[:, :3], {"intensity": array[:, 3]}, path=str(path))


#: consecutive records per run on which the order of a scan is judged
_STEP_WINDOW = 2048
#: a scan whose consecutive points lie this much closer (relative to its size) when its floats are
#: read 3 or 5 to a record than when read 4 to one is taken for records of 3 or 5 floats
_KITTI_SMOOTHER_BY = 10.0


def _step_ratio(xyz: np.ndarray) -> float:
    """The median distance between consecutive points over the cloud's size (the median distance to
    its median point): about 0.01 for a scanner's points in the order it took them, about 1 for
    points in no order, or for floats read in the wrong layout."""
    n = xyz.shape[0]
    if n > 4 * _STEP_WINDOW:  # four runs of consecutive points, spread over the file
        xyz = np.stack([xyz[s:s + _STEP_WINDOW] for s in np.linspace(0, n - _STEP_WINDOW, 4).astype(int)])
    else:
        xyz = xyz[None]
    xyz = xyz.astype(np.float64)
    steps = np.sqrt((np.diff(xyz, axis=1) ** 2).sum(axis=2)).ravel()
    pts = xyz.reshape(-1, 3)
    good = np.isfinite(pts).all(axis=1)
    steps = steps[np.isfinite(steps)]
    if good.sum() < 16 or steps.size < 16:
        return float("nan")
    pts = pts[good]
    size = float(np.median(np.sqrt(((pts - np.median(pts, axis=0)) ** 2).sum(axis=1))))
    return float(np.median(steps)) / size if size > 0.0 else float("nan")


def _smoother_layout(path: Path, array: np.ndarray) -> int | None:
    """3 or 5 when the file's floats read that many to a record make a scan in a scanner's order
    (consecutive points close) and read 4 to one do not (:data:`_KITTI_SMOOTHER_BY`): the layout a
    KITTI reader cannot tell by the byte count (a multiple of 16 and of 12 or 20) nor, with no
    negative coordinate, by the remissions' sign. None otherwise (a KITTI scan in any order)."""
    if array.shape[0] < 64:
        return None
    as4 = _step_ratio(array[:, :3])
    flat = array.reshape(-1)
    for floats in (3, 5):
        if flat.size % floats:
            continue
        other = _step_ratio(flat.reshape(-1, floats)[:, :3])
        if other * _KITTI_SMOOTHER_BY < as4:
            return floats
    return None


#: Reader of each supported extension (lower case, with the dot).
READERS: Mapping[str, Callable[[Path], PointCloud]] = {
    ".ply": read_ply,
    ".pcd": read_pcd,
    ".las": read_las,
    ".laz": read_las,
    ".e57": read_e57,
    ".xyz": read_text,
    ".txt": read_text,
    ".csv": read_text,
    ".pts": read_text,
    ".npy": read_npy,
    ".bin": read_kitti_bin,
    ".range": read_range,  # ABW range images of the SegComp contest (kbs.io.segcomp)
}

#: The file extensions :func:`read_cloud` understands.
SUPPORTED_EXTENSIONS: tuple[str, ...] = tuple(sorted(READERS))


def cloud_files_in(folder: Path) -> list[Path]:
    """The point-cloud files directly inside ``folder`` (by extension), in name order.

    Raises
    ------
    CloudFileError
        When the folder cannot be listed.
    """
    try:
        # every entry but folders: a broken link or a FIFO is a scan the reader refuses, and says so
        return sorted((p for p in folder.iterdir() if p.suffix.lower() in SUPPORTED_EXTENSIONS and not p.is_dir()),
                      key=lambda p: p.name)
    except OSError as exc:
        raise CloudFileError(str(folder), f"cannot list the directory: {exc.strerror or exc}") from exc


def _stat_problem(file: Path) -> str | None:
    """Why ``file`` cannot be opened at all (missing, a symbolic link loop, a broken link, a
    folder on the way that cannot be searched), or None."""
    try:
        file.stat()
    except FileNotFoundError:
        if file.is_symlink():
            return f"no such file: a broken symbolic link (to {os.readlink(file)})"
        return "no such file"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "symbolic link loop (the link points, directly or not, to itself)"
        return f"cannot read: {exc.strerror or exc}"
    return None


#: Files of a drive's folder that are never scans, by name: a KITTI sequence's (and ``kbs synth
#: --frames``') poses, the KITTI calibration and timestamps (text of 12, 2 x 12 or 1 columns).
NOT_SCANS = {"poses.txt": "a poses file", "calib.txt": "a KITTI calibration file",
             "times.txt": "a KITTI timestamps file"}


def _is_pose_row(row: list[str]) -> bool:
    """Whether 12 text numbers are a KITTI pose: a 3x4 matrix, row by row, whose 3x3 part is a
    rotation."""
    try:
        m = np.array([float(v) for v in row]).reshape(3, 4)
    except ValueError:
        return False
    r = m[:, :3]
    return bool(np.isfinite(r).all() and np.abs(r.T @ r - np.eye(3)).max() < 1e-3)


def why_not_a_scan(path: Path) -> str | None:
    """Why a file found in a scanned directory is not a point cloud: by its name (:data:`NOT_SCANS`),
    or judged from its first bytes (a label or grid ``.npy`` array, a one-column text file of
    labels); None when it may be one (the reader will tell). Never raises."""
    extension = path.suffix.lower()
    if path.name.lower() in NOT_SCANS:
        return NOT_SCANS[path.name.lower()]
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # a FIFO or device is not opened (it could block): the reader says
            return None
        if extension == ".npy":
            with open(path, "rb") as stream:
                version = np.lib.format.read_magic(stream)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(stream)
            if dtype.names is not None:
                return None if {"x", "y", "z"} <= set(dtype.names) else "a structured array without x/y/z fields"
            if len(shape) != 2 or shape[1] < 3 or dtype.kind not in "fiu":
                return f"an array of {dtype} of shape {shape}, not (N, 3+) coordinates"
        elif READERS.get(extension) is read_text:
            with open(path, "rb") as stream:
                data = stream.read(8192)
            lines = data.decode("utf-8-sig", errors="replace").splitlines()
            if len(data) == 8192:
                lines = lines[:-1]  # maybe cut short
            rows = [line.replace(",", " ").split() for line in lines[:20] if line.strip() and line[:1] not in "#/%"]
            widest = max(map(len, rows), default=3)
            if widest < 3:
                return f"{widest} column{'s' if widest > 1 else ''} of text, not x y z"
            if rows and all(len(r) == 12 for r in rows) and all(_is_pose_row(r) for r in rows):
                return "a poses file (12 numbers a line: a rotation and a translation, KITTI's poses.txt)"
    except (OSError, ValueError):
        return None
    return None


def read_cloud(path: str | os.PathLike[str], *, format: str | None = None) -> PointCloud:  # noqa: A002
    """Read a point cloud file.

    Parameters
    ----------
    path : str or os.PathLike
        The file. Its extension (case-insensitive) selects the reader, one of
        :data:`SUPPORTED_EXTENSIONS`.
    format : str, optional
        Read the file as this format instead (an extension, with or without the dot: ``"ply"``).

    Returns
    -------
    PointCloud
        The N finite points, as float64 (N, 3) coordinates in the file's frame (not centred),
        with their attributes; points with a NaN/Inf coordinate are dropped and counted.

    Raises
    ------
    CloudFileError
        The file is missing (or a broken link, or a symbolic link loop), unreadable, a directory,
        of an unknown extension, empty, truncated or malformed, or holds no finite point.
    ParameterError
        ``format`` is not a supported format.
    """
    file = Path(os.fspath(path))
    supported = ", ".join(SUPPORTED_EXTENSIONS)
    if format is not None:
        extension = "." + format.lower().lstrip(".")
        if extension not in READERS:
            raise ParameterError(f"unknown point-cloud format {format!r} (supported: {supported})")
    else:
        extension = file.suffix.lower()
    problem = _stat_problem(file)
    if problem:
        raise CloudFileError(str(file), problem)
    if file.is_dir():
        raise CloudFileError(str(file), "is a directory, not a point-cloud file")
    if extension not in READERS:
        what = f"unknown extension {file.suffix!r}" if file.suffix else "no file extension"
        raise CloudFileError(str(file), f"{what} (supported: {supported})")
    try:
        status = file.stat()
        if not stat.S_ISREG(status.st_mode):  # not opened: reading a FIFO would block
            raise CloudFileError(str(file), f"not a regular file but {_file_type(status.st_mode)}: a cloud is "
                                 "read from a file (`kbs run - --in-format FORMAT` reads one from standard input)")
        if status.st_size == 0:
            raise CloudFileError(str(file), "empty file (0 bytes)")
        with library_noise(file):
            return READERS[extension](file)
    except OSError as exc:
        raise CloudFileError(str(file), f"cannot read: {exc.strerror or exc}") from exc


def _file_type(mode: int) -> str:
    """What a file that is not a regular file is, from its ``st_mode``."""
    kinds = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
             (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))
    return next((what for test, what in kinds if test(mode)), "a special file")


#: loggers of the reading libraries whose records a failed read discards (laspy logs each LAZ
#: backend's failure at ERROR level, then raises the last one)
_LIBRARY_LOGGERS = ("laspy",)


#: the library log lines already given out by :func:`library_noise` (each once a process, as
#: Python's warnings are)
_GIVEN: set[tuple[str, str]] = set()


class _Held(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.NOTSET)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextmanager
def library_noise(file: Path) -> Iterator[None]:
    """Hold back the warnings and the log records of the reading libraries while a reader runs:
    when the reader fails, its own one-line error says what is wrong and they are dropped (plyfile's
    ``UserWarning: loadtxt: input contained no data``, laspy's ``IoError: failed to fill whole
    buffer``); when it succeeds they are given out as they would have been, their message prefixed
    with ``file`` (laspy's "There is an ExtraByteVlr but ..." does not say which file). (As
    :class:`warnings.catch_warnings`, not meant for readers run in several threads at once.)"""
    held = _Held()
    loggers = [logging.getLogger(name) for name in _LIBRARY_LOGGERS]
    propagate = [logger_.propagate for logger_ in loggers]
    for logger_ in loggers:
        logger_.addHandler(held)
        logger_.propagate = False
    failed = True
    try:
        with warnings.catch_warnings(record=True) as caught:
            yield
        failed = False
    finally:
        for logger_, was in zip(loggers, propagate):
            logger_.removeHandler(held)
            logger_.propagate = was
        if not failed:
            for warning in caught:
                warnings.warn_explicit(f"{file}: {warning.message}", warning.category, warning.filename,
                                       warning.lineno, source=warning.source)
            for record in held.records:
                record.msg, record.args = f"{file}: {record.getMessage()}", None
                if (record.name, record.msg) not in _GIVEN:  # a file's header read again says it again
                    _GIVEN.add((record.name, record.msg))
                    logging.getLogger(record.name).handle(record)
