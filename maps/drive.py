"""A drive: the frames of a sequence (read one at a time, in order) and one pose per frame.

Where drives come from:

- scan files and folders of scans (every point-cloud file directly inside, in name order), as
  ``kbs run`` takes them;
- a KITTI sequence folder: ``velodyne/*.bin`` in name order, with ``poses.txt`` (and
  ``calib.txt``) beside ``velodyne/`` when present;
- arrays in memory (:meth:`Drive.from_arrays`).

Poses come from a file (:func:`kbs.maps.poses.read_poses`), from the KITTI folder, or are the
identity (the scans are already in one world frame).
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, ParameterError
from kbs.maps.poses import PoseFileError, Poses, read_kitti_poses, read_poses, rigid_problem


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a drive: a scan file, or points already in memory (sensor frame).

    Attributes
    ----------
    name : str
        The scan's file name, or ``frame-<i>``.
    path : str or None
    points : np.ndarray, shape (n, 3), or None
        The points, when given as an array (then ``path`` is None).
    """

    name: str
    path: str | None = None
    points: np.ndarray | None = None

    def load(self) -> np.ndarray:
        """The frame's finite points, (n, 3) float64, in its sensor frame.

        Raises
        ------
        CloudFileError
            The scan file cannot be read (see :func:`kbs.io.read_cloud`).
        """
        if self.points is not None:
            return self.points
        from kbs.io import read_cloud

        return read_cloud(self.path).xyz


@dataclass(frozen=True, eq=False)
class Drive:
    """Frames in order and their poses (``len(poses) == len(frames)``).

    Attributes
    ----------
    frames : tuple of Frame
    poses : Poses
    source : str
        One line: where the frames came from.
    """

    frames: tuple[Frame, ...]
    poses: Poses
    source: str = ""

    def __post_init__(self) -> None:
        if len(self.frames) == 0:
            raise ParameterError("a drive needs at least one frame")
        if len(self.poses) != len(self.frames):
            if self.poses.path is not None:
                raise PoseFileError(self.poses.path, f"{len(self.poses)} poses for {len(self.frames)} frames: give "
                                    "one pose per frame, in the frames' order")
            raise ParameterError(f"{len(self.poses)} poses for {len(self.frames)} frames: give one per frame")

    def __len__(self) -> int:
        return len(self.frames)

    @classmethod
    def from_arrays(cls, frames: Iterable[np.ndarray], poses: Poses | np.ndarray | None = None) -> Drive:
        """A drive from point arrays ((n, 3) each, sensor frame) and poses ((n_frames, 4, 4)
        sensor-to-world matrices, a :class:`Poses`, or None for identity).

        Raises
        ------
        ParameterError
            No frame, a pose that is not a rigid 4x4 transform, a count mismatch.
        """
        from kbs.knowledge.segmenter import as_points

        fr = tuple(Frame(f"frame-{i:06d}", None, as_points(p)) for i, p in enumerate(frames))
        return cls(fr, as_poses(poses, len(fr)), f"{len(fr)} arrays")


def as_poses(poses: Poses | np.ndarray | Sequence | None, n_frames: int) -> Poses:
    """``poses`` as :class:`Poses`: None gives identity poses; an (n, 4, 4) array-like is checked
    (rigid transforms).

    Raises
    ------
    ParameterError
        Not (n, 4, 4) numbers, or a matrix that is not a rigid transform.
    """
    if poses is None:
        return Poses.identity(n_frames)
    if isinstance(poses, Poses):
        return poses
    try:
        m = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"poses must be an (n_frames, 4, 4) array of numbers: {exc}") from exc
    if m.ndim != 3 or m.shape[1:] != (4, 4):
        raise ParameterError(f"poses must have shape (n_frames, 4, 4), got {m.shape}")
    for i, mat in enumerate(m):
        problem = rigid_problem(mat)
        if problem:
            raise ParameterError(f"pose {i} is not a rigid transform: {problem}")
    return Poses(m, "given", None, "poses given as arrays (sensor-to-world)")


def is_kitti_sequence(path: Path) -> bool:
    """Whether ``path`` is a folder holding a ``velodyne/`` folder (a KITTI sequence)."""
    return path.is_dir() and (path / "velodyne").is_dir()


def scan_files(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """The scans named by ``paths``: a file as given, a folder as every point-cloud file directly
    inside it (extensions :data:`kbs.io.SUPPORTED_EXTENSIONS`), in name order, except the files
    that are not scans (a ``poses.txt``, a label file: :func:`kbs.io.readers.why_not_a_scan`).

    Raises
    ------
    CloudFileError
        A missing file or one of an unknown extension; a folder without any point-cloud file, or
        that cannot be listed.
    """
    from kbs.io import SUPPORTED_EXTENSIONS
    from kbs.io.readers import cloud_files_in, why_not_a_scan

    out: list[Path] = []
    for arg in map(Path, paths):
        if not arg.is_dir():
            # checked before any frame is segmented: a drive fails at once, not after minutes
            if not arg.exists():
                raise CloudFileError(str(arg), "no such file")
            if arg.suffix.lower() not in SUPPORTED_EXTENSIONS:
                raise CloudFileError(str(arg), f"unknown extension {arg.suffix!r} (supported: "
                                     f"{', '.join(SUPPORTED_EXTENSIONS)})" if arg.suffix else "no file extension")
            out.append(arg)
            continue
        found = cloud_files_in(arg)
        skipped = {p.name: why for p in found if (why := why_not_a_scan(p)) is not None}
        kept = [p for p in found if p.name not in skipped]
        if not kept:
            what = "; ".join(f"{name}: {why}" for name, why in skipped.items())
            hint = (f"; its scans are in {arg / 'scans'}: kbs map {arg / 'scans'} --poses {arg / 'poses.txt'}"
                    if (arg / "scans").is_dir() and "poses.txt" in skipped else "")
            raise CloudFileError(str(arg), f"no point-cloud file in this directory (extensions: "
                                 f"{', '.join(SUPPORTED_EXTENSIONS)}" + (f"; skipped {what}" if what else "")
                                 + f"){hint}")
        out.extend(kept)
    return out


def read_drive(scans: Sequence[str | os.PathLike[str]], poses: str | os.PathLike[str] | None = None, *,
               calib: str | os.PathLike[str] | None = None, topic: str | None = None) -> Drive:
    """The drive named by ``scans`` (files and folders of scans, or one KITTI sequence folder)
    with its poses.

    Parameters
    ----------
    scans : sequence of paths
        Scan files and folders of scans, in order; or a single KITTI sequence folder (holding
        ``velodyne/``), whose ``poses.txt`` and ``calib.txt`` are used when present.
    poses : path, optional
        A poses file (KITTI ``.txt``, ``.json``, ``.csv``; see :func:`kbs.maps.poses.read_poses`);
        one pose per frame. Without it (and without a KITTI ``poses.txt``) the poses are the
        identity.
    calib : path, optional
        A KITTI ``calib.txt`` for a KITTI poses file (default: the one beside it, if any).
    topic : str, optional
        For a ROS bag (a single ``scans`` entry, see :mod:`kbs.maps.bags`): the PointCloud2
        topic (default: the bag's only one).

    Raises
    ------
    CloudFileError
        No scan, a folder without scans; :class:`PoseFileError` (a CloudFileError) for a bad
        poses file or a count that differs from the frames'.
    """
    paths = [Path(s) for s in scans]
    if not paths:
        raise ParameterError("no scan given")
    from kbs.maps.bags import is_bag

    if topic is not None and not (len(paths) == 1 and is_bag(paths[0])):
        from kbs.maps.bags import TopicError

        raise TopicError("a topic is for a ROS bag: give one bag (a .bag, .db3 or .mcap file, or a rosbag2 folder)")
    if len(paths) == 1 and is_bag(paths[0]):
        from kbs.maps.bags import read_bag

        frames, topic = read_bag(paths[0], topic)
        p = read_poses(poses, calib=calib) if poses is not None else None
        return Drive(tuple(frames), p if p is not None else Poses.identity(len(frames)),
                     f"ROS bag {paths[0]}, topic {topic} ({len(frames)} point clouds)")
    if len(paths) == 1 and is_kitti_sequence(paths[0]):
        seq = paths[0]
        files = sorted((p for p in (seq / "velodyne").iterdir() if p.suffix.lower() == ".bin" and p.is_file()),
                       key=lambda p: p.name)
        if not files:
            raise CloudFileError(str(seq / "velodyne"), "no .bin scan in this KITTI velodyne folder")
        source = f"KITTI sequence {seq} ({len(files)} velodyne scans)"
        if calib is None and (seq / "calib.txt").is_file():
            calib = seq / "calib.txt"
        if poses is None and (seq / "poses.txt").is_file():
            p = read_kitti_poses(seq / "poses.txt", calib)
        else:
            p = None
    else:
        files = scan_files(paths)
        source = f"{len(files)} scan{'s' if len(files) != 1 else ''} in name order" if any(
            s.is_dir() for s in paths) else f"{len(files)} scan{'s' if len(files) != 1 else ''}"
        p = None
    if poses is not None:
        p = read_poses(poses, calib=calib)
    frames = tuple(Frame(f.name, str(f)) for f in files)
    return Drive(frames, p if p is not None else Poses.identity(len(frames)), source)
