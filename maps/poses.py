"""Sensor poses of a drive: KITTI ``poses.txt`` (with ``calib.txt``), JSON and CSV files of 4x4
matrices, checked line by line.

A pose is the 4x4 rigid transform ``T`` that takes a point from the frame's sensor (LiDAR) frame
to the world frame: ``x_world = R x_sensor + t``. Every problem with a poses file is a
:class:`PoseFileError` that says where (``file:line:col``, 1-based) and exits with code 3 (an
unreadable input file).

KITTI odometry poses are those of the left camera (``cam0``) in the frame of the first camera
pose. With the calibration ``Tr`` (velodyne -> cam0, from the sequence's ``calib.txt``), the LiDAR
pose in the frame of the first LiDAR pose is ``Tr^-1 P Tr`` (the SemanticKITTI convention), so
that the world's z is up as the LiDAR's. Without a ``calib.txt`` the poses are taken as LiDAR
poses, and :attr:`Poses.note` says so.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError

#: Largest departure of R^T R from the identity (and of det R from 1) accepted for a rotation:
#: KITTI's files give 6-7 significant digits.
ROTATION_TOLERANCE = 1e-3


class PoseFileError(CloudFileError):
    """A poses (or calibration) file that cannot be used, with the position of the problem.

    Parameters
    ----------
    path : str
    problem : str
    line, col : int, optional
        1-based position of the problem in the file.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str, line: int | None = None,
                 col: int | None = None) -> None:
        self.line, self.col = line, col
        where = os.fspath(path) + (f":{line}" if line is not None else "") + (f":{col}" if col is not None else "")
        super().__init__(where, problem)


@dataclass(frozen=True, eq=False)
class Poses:
    """One 4x4 sensor-to-world transform per frame, and where they came from.

    Attributes
    ----------
    matrices : np.ndarray, shape (n_frames, 4, 4), float64
        Rigid transforms, last row ``0 0 0 1``. Read-only.
    source : str
        ``"identity"``, ``"kitti"``, ``"json"``, ``"csv"``, ``"estimated"`` or ``"given"``.
    path : str or None
        The file read, if any.
    note : str
        One line for the user: what the poses are taken as.
    residuals : tuple
        Estimated poses: one :class:`kbs.maps.odometry.FrameResidual` per frame after the first.
    """

    matrices: np.ndarray
    source: str
    path: str | None = None
    note: str = ""
    residuals: tuple = ()

    def __post_init__(self) -> None:
        m = np.array(self.matrices, dtype=np.float64)
        if m.ndim != 3 or m.shape[1:] != (4, 4):
            raise ValueError(f"Poses.matrices must have shape (n, 4, 4), got {m.shape}")
        m.setflags(write=False)
        object.__setattr__(self, "matrices", m)

    def __len__(self) -> int:
        return len(self.matrices)

    @classmethod
    def identity(cls, n_frames: int) -> Poses:
        """The poses of scans already in one world frame."""
        return cls(np.broadcast_to(np.eye(4), (n_frames, 4, 4)).copy(), "identity",
                   note="no poses given: the scans are taken as already in one world frame (identity poses)")

    @property
    def positions(self) -> np.ndarray:
        """The sensor positions, shape (n_frames, 3)."""
        return self.matrices[:, :3, 3].copy()


def rigid_problem(m: np.ndarray) -> str | None:
    """Why the 4x4 ``m`` is not a rigid transform, or None if it is (within
    :data:`ROTATION_TOLERANCE`)."""
    if not np.isfinite(m).all():
        return "a NaN or infinite value"
    from kbs.knowledge.segmenter import MAX_COORDINATE

    far = float(m[:3, 3][np.argmax(np.abs(m[:3, 3]))])
    if abs(far) > MAX_COORDINATE:  # as a point's coordinate: the map would be built in a frame it cannot hold
        return f"a translation of {far:g}, beyond +-{MAX_COORDINATE:g} (the bound of a point's coordinates)"
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        return f"last row is {' '.join(f'{v:g}' for v in m[3])}, not 0 0 0 1"
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ROTATION_TOLERANCE:
        return f"the 3x3 part is not a rotation (R^T R departs from the identity by {err:.3g})"
    det = float(np.linalg.det(r))
    if det < 0:
        return "the 3x3 part is a reflection (determinant < 0), not a rotation"
    return None


def _numbers(path: Path, line: str, lineno: int, sep: str | None = None, start_col: int = 1) -> list[float]:
    """The numbers of one line, each checked; a bad token raises with its 1-based column."""
    values = []
    pattern = r"[^\s,]+" if sep == "," else r"\S+"
    for m in re.finditer(pattern, line):
        token = m.group(0)
        try:
            v = float(token)
        except ValueError:
            raise PoseFileError(path, f"{token!r} is not a number", lineno, start_col + m.start()) from None
        if not np.isfinite(v):
            raise PoseFileError(path, f"{token!r} is not a finite number", lineno, start_col + m.start())
        values.append(v)
    return values


def _read_text(path: Path) -> str:
    if not path.exists():
        raise PoseFileError(path, "no such file")
    if path.is_dir():
        raise PoseFileError(path, "is a directory, not a poses file")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise PoseFileError(path, f"not a text file (byte {exc.start} is not UTF-8)") from exc
    except OSError as exc:
        raise PoseFileError(path, f"cannot read: {exc.strerror or exc}") from exc


def _to_matrix(values: list[float]) -> np.ndarray:
    m = np.eye(4)
    m[: len(values) // 4] = np.reshape(values, (-1, 4))
    return m


def _check_rigid(path: Path, m: np.ndarray, lineno: int | None, what: str = "") -> None:
    problem = rigid_problem(m)
    if problem:
        raise PoseFileError(path, f"{what}not a rigid transform: {problem}", lineno, 1 if lineno else None)


def read_kitti_poses(path: str | os.PathLike[str], calib: str | os.PathLike[str] | None = None) -> Poses:
    """Read a KITTI odometry ``poses.txt``: one pose per line, the 12 numbers of its 3x4 matrix
    row by row (16 numbers, a full 4x4, are accepted too). Blank lines and ``#`` comments are
    skipped.

    Parameters
    ----------
    path : path of the poses file.
    calib : path of the sequence's ``calib.txt``, optional. Its ``Tr:`` line (velodyne -> cam0)
        turns the camera poses into LiDAR poses ``Tr^-1 P Tr``. Without it the poses are taken as
        LiDAR poses, and the note says so.

    Raises
    ------
    PoseFileError
        Missing or unreadable file, a token that is not a number (line:col), a line with another
        count of numbers, a matrix that is not rigid, no pose at all; a calib.txt without ``Tr:``.
    """
    path = Path(path)
    text = _read_text(path)
    mats: list[np.ndarray] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0]
        if not line.strip():
            continue
        values = _numbers(path, line, lineno)
        if len(values) not in (12, 16):
            raise PoseFileError(path, f"{len(values)} numbers; a KITTI pose line holds 12 (a 3x4 matrix, row by "
                                f"row) or 16 (4x4)", lineno, 1)
        m = _to_matrix(values)
        _check_rigid(path, m, lineno)
        mats.append(m)
    if not mats:
        raise PoseFileError(path, "no pose in the file (one line of 12 numbers per frame expected)")
    P = np.array(mats)
    if calib is None:
        note = (f"poses from {path} (KITTI format) taken as LiDAR poses: no calib.txt beside them; KITTI "
                "odometry poses are camera poses, give the sequence's calib.txt to convert them")
        return Poses(P, "kitti", str(path), note)
    tr = read_kitti_calib(calib)
    inv = np.linalg.inv(tr)
    lidar = inv[None] @ P @ tr[None]
    return Poses(lidar, "kitti", str(path),
                 f"poses from {path} (KITTI camera poses) turned into LiDAR poses with Tr of {calib}")


def read_kitti_calib(path: str | os.PathLike[str]) -> np.ndarray:
    """The 4x4 velodyne -> cam0 transform ``Tr`` of a KITTI ``calib.txt`` (``Tr: 12 numbers``).

    Raises
    ------
    PoseFileError
        Missing file, no ``Tr:`` line, a bad number (line:col), not a rigid transform.
    """
    path = Path(path)
    text = _read_text(path)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        key, sep, rest = raw.partition(":")
        if not sep or key.strip() not in ("Tr", "Tr_velo_to_cam"):
            continue
        values = _numbers(path, rest, lineno, start_col=len(key) + 2)
        if len(values) != 12:
            raise PoseFileError(path, f"Tr holds {len(values)} numbers; 12 expected (3x4, row by row)", lineno, 1)
        m = _to_matrix(values)
        _check_rigid(path, m, lineno, "Tr is ")
        return m
    raise PoseFileError(path, "no 'Tr:' line (the velodyne -> camera transform of a KITTI calib.txt)")


def read_json_poses(path: str | os.PathLike[str]) -> Poses:
    """Read poses from JSON: a list of 4x4 matrices (lists of 4 rows), or an object whose
    ``"poses"`` key holds that list. The position given for a bad matrix is the line and column
    where that matrix starts in the file."""
    path = Path(path)
    text = _read_text(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PoseFileError(path, f"not JSON: {exc.msg}", exc.lineno, exc.colno) from exc
    except RecursionError as exc:
        raise PoseFileError(path, "its JSON nests deeper than Python's parser can follow") from exc
    items = doc.get("poses") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise PoseFileError(path, "expected a list of 4x4 matrices, or an object with a 'poses' list")
    starts = _list_item_starts(text, bool(isinstance(doc, dict)))
    mats = []
    for i, item in enumerate(items):
        line, col = starts[i] if i < len(starts) else (None, None)
        try:
            m = np.array(item, dtype=np.float64)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise PoseFileError(path, f"pose {i} is not a 4x4 (or 3x4) matrix of numbers", line, col)
        problem = rigid_problem(m)
        if problem:
            raise PoseFileError(path, f"pose {i} is not a rigid transform: {problem}", line, col)
        mats.append(m)
    if not mats:
        raise PoseFileError(path, "no pose in the file")
    return Poses(np.array(mats), "json", str(path), f"poses from {path} (4x4 sensor-to-world matrices)")


def _list_item_starts(text: str, in_object: bool) -> list[tuple[int, int]]:
    """(line, col) where each item of the top-level poses list starts (a light scan of the JSON
    text: brackets at depth 1 of the list; strings skipped)."""
    starts: list[tuple[int, int]] = []
    depth, list_depth, in_str, esc = 0, None, False, False
    line, col = 1, 0
    for ch in text:
        col += 1
        if ch == "\n":
            line, col = line + 1, 0
            continue
        if in_str:
            esc = (ch == "\\") and not esc
            if ch == '"' and not esc:
                in_str = False
            continue
        if ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if list_depth is None and ch == "[" and depth == (2 if in_object else 1):
                list_depth = depth
            elif list_depth is not None and depth == list_depth + 1:
                starts.append((line, col))
        elif ch in "]}":
            if list_depth is not None and depth == list_depth:
                break
            depth -= 1
    return starts


def read_csv_poses(path: str | os.PathLike[str]) -> Poses:
    """Read poses from CSV: one row per frame, 16 numbers (a 4x4 row by row) or 12 (3x4), an
    optional header line first."""
    path = Path(path)
    text = _read_text(path)
    mats: list[np.ndarray] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip() or raw.lstrip().startswith("#"):
            continue
        if not mats and lineno == 1 and re.search(r"[A-DF-Za-df-z_]", raw):  # a header (not 1e-3)
            continue
        values = _numbers(path, raw, lineno, sep=",")
        if len(values) not in (12, 16):
            raise PoseFileError(path, f"{len(values)} numbers; a pose row holds 16 (4x4, row by row) or 12 (3x4)",
                                lineno, 1)
        m = _to_matrix(values)
        _check_rigid(path, m, lineno)
        mats.append(m)
    if not mats:
        raise PoseFileError(path, "no pose in the file")
    return Poses(np.array(mats), "csv", str(path), f"poses from {path} (4x4 sensor-to-world matrices)")


def read_poses(path: str | os.PathLike[str], *, calib: str | os.PathLike[str] | None = None) -> Poses:
    """Read a poses file by its extension: ``.json`` (4x4 lists), ``.csv`` (16 or 12 numbers a
    row), anything else as KITTI ``poses.txt``. For a KITTI file, ``calib`` defaults to a
    ``calib.txt`` beside it when there is one."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return read_json_poses(path)
    if suffix == ".csv":
        return read_csv_poses(path)
    if calib is None and (path.parent / "calib.txt").is_file():
        calib = path.parent / "calib.txt"
    return read_kitti_poses(path, calib)


def write_kitti_poses(path: str | os.PathLike[str], matrices: np.ndarray) -> None:
    """Write poses as KITTI ``poses.txt`` lines (12 numbers, the 3x4 part row by row)."""
    m = np.asarray(matrices, dtype=np.float64)
    lines = [" ".join(f"{v:.9e}" for v in mat[:3].ravel()) for mat in m]
    try:
        Path(path).write_text("\n".join(lines) + "\n")
    except OSError as exc:
        raise CloudFileError(os.fspath(path), f"cannot write: {exc.strerror or exc}") from exc
