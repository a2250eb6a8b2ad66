"""Ground-truth labels: a per-point label file (``.npy``, a SemanticKITTI ``.label``, or text with
one integer per line), or a field of the evaluated cloud (``field:NAME``)."""
from __future__ import annotations

import difflib
import os
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, KbsError, ParameterError
from kbs.evaluation.hoover import LABEL_MAX, LABEL_MIN, LabelRangeError, as_labels
from kbs.io import PointCloud

#: Prefix of a ground-truth spec naming a field of the cloud.
FIELD_PREFIX = "field:"

#: SemanticKITTI raw class ids (the low 16 bits of a ``.label`` entry) that are ground, as the
#: dataset's own benchmark maps them to its learning classes road (40 road, 60 lane-marking),
#: parking (44), sidewalk (48), other-ground (49) and terrain (72): the same set as the learning
#: ids 9, 10, 11, 12, 17 of the ``semantickitti/*.labels.npy`` scans (benchmarks/bench_ground.py).
SEMANTICKITTI_GROUND = (40, 44, 48, 49, 60, 72)
#: SemanticKITTI raw classes whose points are ignored: 0 unlabelled, 1 outlier.
SEMANTICKITTI_IGNORED = (0, 1)
#: Bytes per entry of a SemanticKITTI ``.label`` file (uint32: class id low 16 bits, instance high 16).
LABEL_BYTES = 4
#: Bytes per point of a KITTI ``.bin`` scan (float32 x y z remission).
KITTI_BIN_BYTES = 16


def is_semantickitti_label(spec: str | os.PathLike[str]) -> bool:
    """Whether a ground-truth spec is a SemanticKITTI ``.label`` file (by its extension)."""
    text = os.fspath(spec)
    return not text.startswith(FIELD_PREFIX) and Path(text).suffix.lower() == ".label"


class UnknownFieldError(ParameterError):
    """A ``field:NAME`` ground truth naming a field the cloud does not have.

    Attributes
    ----------
    name : str
        The field asked for.
    available : tuple[str, ...]
        The cloud's fields.
    suggestion : str or None
        The closest field name, if one is close.
    """

    def __init__(self, name: str, available: tuple[str, ...], where: str) -> None:
        self.name = name
        self.available = available
        close = difflib.get_close_matches(name, available, n=1, cutoff=0.6)
        self.suggestion = close[0] if close else None
        hint = f"; did you mean {self.suggestion!r}?" if self.suggestion else ""
        fields = ", ".join(available) if available else "none"
        super().__init__(f"{where} has no field {name!r} (fields: {fields}){hint}")


def load_ground_truth(spec: str | os.PathLike[str], cloud: PointCloud | None = None) -> np.ndarray:
    """Per-point ground-truth labels from a label file or a field of ``cloud``.

    Parameters
    ----------
    spec : str or path
        ``field:NAME``: the field NAME of ``cloud`` (e.g. ``field:label`` of a PCD,
        ``field:classification`` of a LAS file, ``field:col3`` of a text table,
        ``field:label_in`` of a ``kbs run`` result made from a labelled cloud); or a file:
        ``.npy`` of shape (N,) or (N, 1); ``.label``, SemanticKITTI's binary format (one uint32
        per point, the semantic class in the low 16 bits, the instance in the high 16: the class
        is returned, see :data:`SEMANTICKITTI_GROUND`); or any other extension read as text with
        one integer label per line (e.g. ``samp21-utm.labels.txt``).
    cloud : PointCloud, optional
        The evaluated cloud: required for ``field:``; when given, the labels must have one
        entry per point of it.

    Returns
    -------
    np.ndarray, shape (N,), int64

    Raises
    ------
    CloudFileError
        The file is missing, unreadable, malformed, not integer labels, holds a label beyond
        int64 (refused, never wrapped: its line, or its index), or does not have one label per
        point of ``cloud`` (exit code 3 on the command line).
    UnknownFieldError
        ``field:NAME`` names a field ``cloud`` does not have.
    ParameterError
        ``field:`` without a cloud.
    """
    text = os.fspath(spec)
    where = (cloud.path if cloud is not None and cloud.path else "the cloud")
    if text.startswith(FIELD_PREFIX):
        name = text[len(FIELD_PREFIX):]
        if cloud is None:
            raise ParameterError(f"ground truth {text!r} names a field, but no cloud was given")
        if name not in cloud.fields:
            raise UnknownFieldError(name, tuple(cloud.fields), where)
        try:
            return as_labels(cloud.fields[name], f"field {name!r}")
        except LabelRangeError as exc:
            raise CloudFileError(where, f"{exc} (point {exc.index})") from exc
        except ParameterError as exc:
            raise CloudFileError(where, f"field {name!r} does not hold integer labels "
                                        f"({cloud.fields[name].dtype})") from exc
    path = Path(text)
    suffix = path.suffix.lower()
    labels = (_read_npy(path) if suffix == ".npy" else _read_semantickitti(path) if suffix == ".label"
              else _read_text(path))
    if cloud is not None and len(labels) != len(cloud):
        raise CloudFileError(str(path), f"{len(labels):,} labels for the {len(cloud):,} points of {where}")
    return labels


def _check_file(path: Path) -> None:
    if not path.exists():
        raise CloudFileError(str(path), "no such file")
    if path.is_dir():
        raise CloudFileError(str(path), "is a directory, not a label file")


def _read_npy(path: Path) -> np.ndarray:
    _check_file(path)
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise CloudFileError(str(path), f"cannot read the NPY label file: {exc}") from exc
    if not isinstance(a, np.ndarray):
        raise CloudFileError(str(path), "not a single NPY array")
    try:
        return as_labels(a, "labels")
    except LabelRangeError as exc:
        raise CloudFileError(str(path), str(exc)) from exc
    except KbsError as exc:
        raise CloudFileError(str(path), f"expected integer labels of shape (N,) or (N, 1), "
                                        f"got {a.dtype} {a.shape}") from exc


def _read_semantickitti(path: Path) -> np.ndarray:
    """The semantic classes of a SemanticKITTI ``.label`` file (uint32 little-endian per point,
    class in the low 16 bits). The file's size must be a whole number of entries, and match the
    KITTI ``.bin`` scan of the same name beside it when there is one."""
    _check_file(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CloudFileError(str(path), f"cannot read: {exc.strerror or exc}") from exc
    if not data:
        raise CloudFileError(str(path), "the label file is empty (0 bytes)")
    if len(data) % LABEL_BYTES:
        raise CloudFileError(str(path), f"size {len(data):,} bytes is not a multiple of {LABEL_BYTES}: not a "
                                        f"SemanticKITTI .label file (one uint32 per point); the last "
                                        f"{len(data) % LABEL_BYTES} byte(s), from byte offset "
                                        f"{len(data) - len(data) % LABEL_BYTES:,}, are not a whole label")
    n = len(data) // LABEL_BYTES
    scan = path.with_suffix(".bin")
    if scan.is_file():
        size = scan.stat().st_size
        if size % KITTI_BIN_BYTES == 0 and size // KITTI_BIN_BYTES != n:
            raise CloudFileError(str(path), f"{n:,} labels ({len(data):,} bytes), but the scan {scan} beside it has "
                                            f"{size // KITTI_BIN_BYTES:,} points ({size:,} bytes of "
                                            f"{KITTI_BIN_BYTES}): not the labels of that scan")
    raw = np.frombuffer(data, dtype="<u4")
    return (raw & 0xFFFF).astype(np.int64)


def _read_text(path: Path) -> np.ndarray:
    _check_file(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise CloudFileError(str(path), "not a text label file (not UTF-8 text; "
                                        "a binary label file must be .npy)") from exc
    except OSError as exc:
        raise CloudFileError(str(path), f"cannot read: {exc.strerror or exc}") from exc
    lines = text.rstrip().splitlines()
    if not lines:
        raise CloudFileError(str(path), "the label file is empty")
    tokens = text.split()
    if len(tokens) == len(lines):
        try:
            return np.array(tokens, dtype=np.int64)
        except (ValueError, OverflowError):  # not an integer, or beyond int64: the line, below
            pass
    for i, line in enumerate(lines, start=1):  # find the first bad line for the message
        parts = line.split()
        if len(parts) != 1:
            what = "is empty" if not parts else f"holds {len(parts)} values"
            raise CloudFileError(str(path), f"line {i} {what}; a label file holds one integer per line "
                                            f"(for a column of a cloud, use field:NAME with the cloud)")
        try:
            value = int(parts[0])
        except ValueError:
            raise CloudFileError(str(path), f"line {i}: {parts[0]!r} is not an integer label") from None
        if not LABEL_MIN <= value <= LABEL_MAX:
            raise CloudFileError(str(path), f"line {i}: {parts[0]} is beyond the range of a label (a 64-bit "
                                            f"signed integer, {LABEL_MIN} .. {LABEL_MAX})")
    raise CloudFileError(str(path), "malformed label file")  # pragma: no cover - every case is caught above
