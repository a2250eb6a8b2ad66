"""Writing point clouds (coordinates plus per-point attributes) as PLY files with plyfile."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
import plyfile

from kbs.errors import CloudFileError, ParameterError
from kbs.io.atomic import replacing

#: The scalar types PLY can store (int8 ... float64); 64-bit integers are not among them.
PLY_SCALAR_DTYPES = frozenset(np.dtype(code) for code in ("i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"))
_NARROWED = {np.dtype("i8"): np.dtype("i4"), np.dtype("u8"): np.dtype("u4")}
#: printf formats that give back the exact value, for the ascii body.
_TEXT_FORMATS = {np.dtype("f4"): "%.9g", np.dtype("f8"): "%.17g"}


def _ply_dtype(name: str, values: np.ndarray) -> np.dtype:
    """The PLY property type that stores ``values`` exactly (native byte order).

    bool becomes ``u1``, float16 ``f4``; int64/uint64 become ``i4``/``u4`` when every value fits.
    """
    dtype = values.dtype.newbyteorder("=")
    if dtype in PLY_SCALAR_DTYPES:
        return dtype
    if dtype.kind == "b":
        return np.dtype("u1")
    if dtype == np.float16:
        return np.dtype("f4")
    if dtype in _NARROWED:
        narrow = _NARROWED[dtype]
        info = np.iinfo(narrow)
        if values.size and (values.min() < info.min or values.max() > info.max):
            raise ParameterError(
                f"field {name!r} has {dtype} values outside the {narrow} range a PLY property can store"
            )
        return narrow
    raise ParameterError(f"field {name!r} has dtype {values.dtype}, which a PLY property cannot store")


def _check_text(what: str, text: object) -> str:
    """A header word or line: ASCII, one line; property names also without spaces."""
    if not isinstance(text, str) or not text.isascii() or "\n" in text or "\r" in text:
        raise ParameterError(f"{what} must be a one-line ASCII string, got {text!r}")
    return text


def write_ply(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    fields: Mapping[str, np.ndarray] | None = None,
    *,
    binary: bool = True,
    comments: Sequence[str] = (),
) -> None:
    """Write points and their attributes as the ``vertex`` element of a PLY file.

    The file appears whole or not at all: it is written to a temporary file in the same folder,
    then renamed over ``path`` (:func:`kbs.io.atomic.replacing`); if writing fails, an existing
    file at ``path`` is left as it was.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create (replaced if it exists).
    xyz : np.ndarray, shape (N, 3)
        Coordinates; stored as float32 (``float``) if given as float32, else as float64 (``double``).
    fields : Mapping[str, np.ndarray], optional
        One scalar property per entry, each of shape (N,), written after x y z with its dtype
        kept (``int32`` -> ``int``, ``uint8`` -> ``uchar``, ``float64`` -> ``double`` ...). bool is
        stored as ``uchar``; int64/uint64 (which PLY lacks) as int32/uint32 when the values fit.
    binary : bool, default True
        Binary little-endian if True, ascii otherwise.
    comments : Sequence[str], default ()
        Header comment lines (one-line ASCII strings).

    Raises
    ------
    ParameterError
        ``xyz`` is not (N, 3) real numbers; a field is not 1-D of length N, has an unstorable
        dtype or a bad name (empty, spaces, non-ASCII, or ``x``/``y``/``z``); a comment is not
        one ASCII line.
    CloudFileError
        The file cannot be written (missing folder, no permission, full disk ...).
    """
    built = build_ply(xyz, fields, binary=binary, comments=comments)
    try:
        with replacing(path) as (temp,):
            write_built_ply(built, temp, target=path)
    except OSError as exc:  # creating the temporary file beside path
        raise CloudFileError(os.fspath(path), f"cannot write: {exc.strerror or exc}") from exc


class BuiltPly(NamedTuple):
    """A PLY document checked and laid out by :func:`build_ply`, ready to be written."""

    ply: plyfile.PlyData
    vertex: np.ndarray
    formats: list[str] | None  # printf formats of the ascii body; None for binary


def build_ply(
    xyz: np.ndarray,
    fields: Mapping[str, np.ndarray] | None = None,
    *,
    binary: bool = True,
    comments: Sequence[str] = (),
) -> BuiltPly:
    """Check the arguments of :func:`write_ply` and lay the vertex table out (raises the same
    ParameterError); nothing is written."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype.kind not in "fiu":
        raise ParameterError(f"xyz must be a real array of shape (N, 3), got {xyz.dtype} {xyz.shape}")
    n = len(xyz)
    coordinate = np.dtype("f4") if xyz.dtype == np.float32 else np.dtype("f8")
    columns: dict[str, tuple[np.ndarray, np.dtype]] = {
        axis: (xyz[:, i], coordinate) for i, axis in enumerate("xyz")
    }
    for name, values in (fields or {}).items():
        _check_text("a field name", name)
        if not name or name.split() != [name]:
            raise ParameterError(f"a field name must be one word without spaces, got {name!r}")
        if name in columns:
            raise ParameterError(f"field name {name!r} clashes with a coordinate or another field")
        values = np.asarray(values)
        if values.shape != (n,):
            raise ParameterError(f"field {name!r} must have shape ({n},) like xyz, got {values.shape}")
        columns[name] = (values, _ply_dtype(name, values))
    header_comments = [_check_text("a PLY comment", comment) for comment in comments]

    vertex = np.empty(n, dtype=[(name, dtype) for name, (_, dtype) in columns.items()])
    for name, (values, _) in columns.items():
        vertex[name] = values
    element = plyfile.PlyElement.describe(vertex, "vertex")
    ply = plyfile.PlyData([element], text=not binary, byte_order="<", comments=header_comments)
    formats = None if binary else [_TEXT_FORMATS.get(dtype, "%d") for _, dtype in columns.values()]
    return BuiltPly(ply, vertex, formats)


def write_built_ply(built: BuiltPly, path: str | os.PathLike[str], *,
                    target: str | os.PathLike[str] | None = None) -> None:
    """Write a :class:`BuiltPly` to ``path`` as it is (no temporary file: callers that want one use
    :func:`kbs.io.atomic.replacing`); errors name ``target`` (default ``path``)."""
    try:
        with open(path, "wb") as stream:
            if built.formats is None:
                built.ply.write(stream)
            else:  # plyfile formats ascii rows one by one in Python (~20 us each): one savetxt instead
                stream.write(built.ply.header.encode("ascii") + b"\n")
                np.savetxt(stream, built.vertex, fmt=built.formats, delimiter=" ")
    except OSError as exc:
        raise CloudFileError(os.fspath(target if target is not None else path),
                             f"cannot write: {exc.strerror or exc}") from exc
