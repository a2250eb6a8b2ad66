"""Ground-truth labels: a per-point label file (``.npy``, or text with one integer per line), or a
field of the evaluated cloud (``field:NAME``)."""
from __future__ import annotations

import difflib
import os
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, KbsError, ParameterError
from kbs.evaluation.hoover import as_labels
from kbs.io import PointCloud

#: Prefix of a ground-truth spec naming a field of the cloud.
FIELD_PREFIX = "field:"


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
        ``.npy`` of shape (N,) or (N, 1), or any other extension read as text with one integer
        label per line (e.g. ``samp21-utm.labels.txt``).
    cloud : PointCloud, optional
        The evaluated cloud: required for ``field:``; when given, the labels must have one
        entry per point of it.

    Returns
    -------
    np.ndarray, shape (N,), int64

    Raises
    ------
    CloudFileError
        The file is missing, unreadable, malformed, not integer labels, or does not have one
        label per point of ``cloud`` (exit code 3 on the command line).
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
        except ParameterError as exc:
            raise CloudFileError(where, f"field {name!r} does not hold integer labels "
                                        f"({cloud.fields[name].dtype})") from exc
    path = Path(text)
    labels = _read_npy(path) if path.suffix.lower() == ".npy" else _read_text(path)
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
    except KbsError as exc:
        raise CloudFileError(str(path), f"expected integer labels of shape (N,) or (N, 1), "
                                        f"got {a.dtype} {a.shape}") from exc


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
        except ValueError:
            pass
    for i, line in enumerate(lines, start=1):  # find the first bad line for the message
        parts = line.split()
        if len(parts) != 1:
            what = "is empty" if not parts else f"holds {len(parts)} values"
            raise CloudFileError(str(path), f"line {i} {what}; a label file holds one integer per line "
                                            f"(for a column of a cloud, use field:NAME with the cloud)")
        try:
            int(parts[0])
        except ValueError:
            raise CloudFileError(str(path), f"line {i}: {parts[0]!r} is not an integer label") from None
    raise CloudFileError(str(path), "malformed label file")  # pragma: no cover - every case is caught above
