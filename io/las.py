"""LAS/LAZ output: the input's points and fields with an ASPRS ``classification`` and kbs's fields.

A result written as LAS or LAZ (``kbs run --out-format las|laz``) holds:

- from a LAS/LAZ input, the input's own records: every dimension, the header's version, point
  format, scales and offsets, its VLRs (the CRS among them) and extra-bytes dimensions; only
  ``classification`` changes. From another format, a LAS 1.4 file, point format 6 (7 when the
  input has ``red green blue``), scales fine enough for the coordinates' extent, the input's
  other fields as extra-bytes dimensions, and the CRS the input declared (a WKT record).
- ``classification``: the ASPRS code the rule base gives each label (``asprs_classes``; ``noise``:
  the rejected points); labels it does not list, and clusters no label matched, get 1 (unclassified). Without ``asprs_classes`` the input's classification
  stays (0 for an input without one).
- extra-bytes dimensions ``cluster`` (int32, -1 noise), ``label`` (int32, index into the rule
  base's labels, -1 noise) and ``membership`` (float32). An input extra dimension of one of
  these names is kept as ``<name>_in``.
- the run id in a VLR (user id ``kbs``, record id 1), as the PLY's header comment: readers of a
  result pair compare it with the JSON's (:func:`kbs.io.result.check_pair`).

Reading a result back is reading a LAS file (:func:`kbs.io.read_cloud` keeps the extra dimensions).
"""
from __future__ import annotations

import copy
import datetime
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import CloudFileError, ParameterError

#: The VLR that carries a result's run id.
RUN_ID_USER_ID = "kbs"
RUN_ID_RECORD_ID = 1
#: Classification codes a point format 0-5 record can hold (5 bits).
LEGACY_MAX_CLASS = 31
#: ASPRS code of the points of a label that ``asprs_classes`` does not list: unclassified.
UNCLASSIFIED = 1
#: The kbs fields written as extra-bytes dimensions, with their types and descriptions.
KBS_DIMENSIONS = {
    "cluster": (np.int32, "kbs output cluster, -1 noise"),
    "label": (np.int32, "kbs label index, -1 noise"),
    "membership": (np.float32, "kbs membership in its cluster"),
}
_EXTRA_DTYPES = frozenset(np.dtype(c) for c in ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8"))


def class_codes(label: np.ndarray, cluster: np.ndarray, label_names: list[str], classes: Mapping[str, int]) -> np.ndarray:
    """The ASPRS code of each point (uint8): ``classes[label name]``; ``classes['noise']`` for the
    rejected points (cluster -1); 1 (unclassified) for a label ``classes`` does not list and for
    the points of a cluster no label's condition held for (label -1 in a cluster)."""
    table = np.array([classes.get(name, UNCLASSIFIED) for name in label_names] + [UNCLASSIFIED], dtype=np.uint8)
    codes = table[np.asarray(label, dtype=np.int64)]  # -1 picks the last entry: unclassified
    codes[np.asarray(cluster) < 0] = classes.get("noise", UNCLASSIFIED)
    return codes


def check_classes_fit(source: Any, classes: Mapping[str, int] | None, path: str) -> None:
    """Refuse, before any work, codes a LAS input's point format cannot hold (formats 0-5: 0-31).

    Raises
    ------
    ParameterError
        A code above 31 for a point format below 6 (the message names the labels and the remedies).
    """
    if source is None or not classes:
        return
    point_format = source.header.point_format.id
    big = {name: code for name, code in classes.items() if code > LEGACY_MAX_CLASS}
    if point_format < 6 and big:
        listed = ", ".join(f"{name} {code}" for name, code in big.items())
        raise ParameterError(f"{path}: LAS point format {point_format} holds classification codes 0-{LEGACY_MAX_CLASS}; "
                             f"the rule base's asprs_classes has {listed}. Write PLY (--out-format ply), map those "
                             "labels to codes up to 31, or convert the input to point format 6 or more (LAS 1.4)")


def _extra_dtype(name: str, values: np.ndarray) -> np.dtype | None:
    dtype = values.dtype.newbyteorder("=")
    if dtype.kind == "b":
        return np.dtype("u1")
    if dtype == np.float16:
        return np.dtype("f4")
    return dtype if dtype in _EXTRA_DTYPES else None


def without_run_id(vlrs: list[Any]) -> list[Any]:
    """The VLRs but kbs's run-id record (a LAS written by kbs carries one, replaced when rewritten)
    and a COPC file's records (the result is written as plain LAS/LAZ: not ordered by an octree)."""
    return [v for v in vlrs if not (v.user_id == RUN_ID_USER_ID and v.record_id == RUN_ID_RECORD_ID)
            and v.user_id != "copc"]


def without_copc(header: Any) -> None:
    """Drop a COPC file's records from ``header`` (laspy cannot write them: its result is plain LAS/LAZ)."""
    header.vlrs = without_run_id(list(header.vlrs))
    if getattr(header, "evlrs", None):
        header.evlrs = [v for v in header.evlrs if v.user_id != "copc"]


def run_id_vlr(run_id: str) -> Any:
    """The VLR that carries a kbs run id."""
    from laspy.vlrs.vlr import VLR

    return VLR(user_id=RUN_ID_USER_ID, record_id=RUN_ID_RECORD_ID, description="kbs run id",
               record_data=run_id.encode("ascii"))


def software_id() -> str:
    """The LAS header's generating software: ``kbs VERSION`` (32 characters at most)."""
    from kbs import __version__

    return f"kbs {__version__}"[:32]


def build_las(xyz: np.ndarray, fields: Mapping[str, np.ndarray], kbs_fields: Mapping[str, np.ndarray], *,
              classification: np.ndarray | None, run_id: str, source: Any = None, crs: str | None = None) -> Any:
    """The ``laspy.LasData`` of a result (nothing written).

    Parameters
    ----------
    xyz : ndarray (n, 3)
        The points (for a LAS ``source``: its own, in its order; the records are copied from it).
    fields : mapping
        The input's own per-point fields (used when there is no LAS ``source``).
    kbs_fields : mapping
        ``cluster``, ``label``, ``membership`` (n,).
    classification : ndarray (n,) uint8 or None
        The ASPRS codes; None keeps the input's (0 without a LAS source).
    run_id : str
    source : laspy.LasData, optional
        The LAS/LAZ input (:attr:`kbs.io.PointCloud.source`).
    crs : str, optional
        The CRS text to record when there is no LAS source (WKT, or anything pyproj reads).
    """
    import laspy

    n = len(xyz)
    if source is not None:
        if len(source.points) != n:
            raise ParameterError(f"the LAS source has {len(source.points)} points, the result {n}")
        out = laspy.LasData(header=copy.deepcopy(source.header), points=source.points.copy())
        kept = set(out.point_format.extra_dimension_names)
        for name in KBS_DIMENSIONS:
            if name in kept:  # an earlier result's field: kept as <name>_in
                old = np.array(out[name])
                desc = next((d.description for d in out.point_format.extra_dimensions if d.name == name), "")
                out.remove_extra_dim(name)
                out.add_extra_dim(laspy.ExtraBytesParams(f"{name}_in"[:32], old.dtype, description=desc[:32]))
                out[f"{name}_in"[:32]] = old
        without_copc(out.header)
    else:
        rgb = all(c in fields for c in ("red", "green", "blue"))
        header = laspy.LasHeader(point_format=7 if rgb else 6, version="1.4")
        header.offsets, header.scales = _offsets_scales(xyz)
        extras = []
        standard = {"intensity", *(("red", "green", "blue") if rgb else ())}
        for name, values in fields.items():
            values = np.asarray(values)
            if name in standard and values.dtype.kind in "uib" and _fits(values, np.uint16):
                continue
            safe = name if name not in KBS_DIMENSIONS and name != "classification" else f"{name}_in"
            dtype = _extra_dtype(name, values)
            if dtype is not None and values.ndim == 1 and len(safe) <= 32:
                extras.append((safe, dtype, values))
        header.add_extra_dims([laspy.ExtraBytesParams(name, dtype) for name, dtype, _ in extras])
        if crs:
            _add_crs(header, crs)
        out = laspy.LasData(header)
        out.x, out.y, out.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        for name in standard:
            if name in fields and name not in {e[0] for e in extras}:
                values = np.asarray(fields[name])
                if name != "intensity" and values.max(initial=0) <= 255:  # 8-bit colours to LAS's 16 bits
                    values = values.astype(np.uint16) * 257
                out[name] = values.astype(np.uint16)
        for name, dtype, values in extras:
            out[name] = values.astype(dtype)
    out.add_extra_dims([laspy.ExtraBytesParams(name, dtype, description=desc)
                        for name, (dtype, desc) in KBS_DIMENSIONS.items()])
    for name, (dtype, _) in KBS_DIMENSIONS.items():
        out[name] = np.asarray(kbs_fields[name]).astype(dtype)
    if classification is not None:
        out.classification = classification
    out.header.vlrs.append(run_id_vlr(run_id))
    out.header.generating_software = software_id()
    out.header.creation_date = datetime.date.today()
    return out


def _fits(values: np.ndarray, dtype: type) -> bool:
    info = np.iinfo(dtype)
    return values.size == 0 or (values.min() >= info.min and values.max() <= info.max)


def _offsets_scales(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (the minimum, rounded down) and per-axis power-of-ten scales, the finest that keeps
    the extent within LAS's 32-bit integers (at most 1e-7 of a unit is lost from float32 data)."""
    lo = np.floor(xyz.min(axis=0))
    extent = np.maximum(xyz.max(axis=0) - lo, 1e-300)
    scales = np.array([10.0 ** max(-7, math.ceil(math.log10(e / 2.0e9))) for e in extent])
    return lo, scales


def _add_crs(header: Any, text: str) -> None:
    """Record ``text`` as the header's CRS: through pyproj when installed, else as a WKT record
    when it is WKT (an EPSG code without pyproj cannot be written: left out)."""
    try:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(text))
        return
    except ImportError:
        pass
    except Exception:  # noqa: BLE001 - pyproj cannot read it: the text as it is, if WKT
        pass
    if "[" in text:
        from laspy.vlrs.known import WktCoordinateSystemVlr

        header.vlrs.append(WktCoordinateSystemVlr(text))
        header.global_encoding.wkt = True


def write_las(path: Path, las: Any, *, target: str | os.PathLike[str] | None = None) -> None:
    """Write a LasData to ``path`` (LAZ when its suffix is ``.laz``, lazrs); errors name ``target``."""
    try:
        las.write(str(path))
    except OSError as exc:
        raise CloudFileError(os.fspath(target or path), f"cannot write: {exc.strerror or exc}") from exc


def las_run_id(path: str | os.PathLike[str]) -> str | None:
    """The run id a LAS/LAZ result carries (its ``kbs`` VLR), None if it has none or is not LAS."""
    try:
        with open(path, "rb") as stream:
            if stream.read(4) != b"LASF":
                return None
        import laspy

        from kbs.io.readers import library_noise

        with library_noise(Path(path)), laspy.open(os.fspath(path)) as reader:
            for vlr in reader.header.vlrs:
                if vlr.user_id == RUN_ID_USER_ID and vlr.record_id == RUN_ID_RECORD_ID:
                    data = getattr(vlr, "record_data", b"")
                    text = bytes(data).decode("ascii", "replace").strip("\x00 ")
                    return text or None
    except Exception:  # noqa: BLE001 - unreadable or not LAS: no run id
        return None
    return None
