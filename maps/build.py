"""Mapping a drive: every frame segmented with one loaded :class:`kbs.Segmenter`, brought into the
world frame with its pose, and fused into the obstacle grid, the tracked objects and a
voxel-downsampled labelled cloud.

>>> from kbs import Segmenter
>>> from kbs.maps import read_drive, map_drive
>>> drive = read_drive(["drive/scans"], "drive/poses.txt")        # doctest: +SKIP
>>> with Segmenter("outdoor") as seg:                              # doctest: +SKIP
...     m = map_drive(seg, drive, cell_size=0.2)
>>> m.grid.counts(), len(m.objects)                                # doctest: +SKIP
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kbs.errors import FitError, ParameterError
from kbs.maps.drive import Drive, as_poses
from kbs.maps.grid import FusionParams, GridAccumulator, GridMap
from kbs.maps.objects import ObjectTracker, object_mesh, voxel_keys, voxel_mean
from kbs.maps.poses import Poses


@dataclass(frozen=True)
class FrameRecord:
    """What was done with one frame."""

    index: int
    name: str
    path: str | None
    pose: np.ndarray
    n_points: int
    n_ground: int
    n_obstacle: int
    n_noise: int
    clusters: int
    objects: dict[int, list[int]]  #: output cluster id -> its objects (tracked obstacle clusters only)
    segment_seconds: float
    fuse_seconds: float
    #: with ``map_drive(..., explain=True)``: output cluster id -> ``label``, ``n_points``, ``ids``
    #: (its records) and ``why`` (each record's :meth:`~kbs.knowledge.explain.Explanation.why`
    #: text), for the clusters of tracked objects (``objects``' keys)
    explanations: dict[int, dict[str, Any]] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class MapObject:
    """An obstacle tracked across frames.

    Attributes
    ----------
    id : int
    frames : tuple of int
        The frames it was seen in.
    clusters : tuple of (int, int)
        (frame, output cluster id) of each of its clusters.
    n_points : int
        Points of its clusters, over every frame.
    points : np.ndarray (m, 3)
        Its fused points (world frame, voxel-downsampled).
    vertices, faces : np.ndarray or None
        Its mesh (None when not even a hull could be built: ``mesh_kind`` says why).
    mesh_kind : str
    """

    id: int
    frames: tuple[int, ...]
    clusters: tuple[tuple[int, int], ...]
    n_points: int
    points: np.ndarray
    vertices: np.ndarray | None
    faces: np.ndarray | None
    mesh_kind: str

    @property
    def centroid(self) -> np.ndarray:
        return self.points.mean(axis=0)

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)


@dataclass(frozen=True, eq=False)
class FusedCloud:
    """The drive's points in the world frame, one per occupied voxel.

    Attributes
    ----------
    xyz : np.ndarray (n, 3)
        Mean point of each voxel.
    label : np.ndarray (n,) int32
        The label most of the voxel's points got (index into ``label_names``, -1 noise only).
    obstacle : np.ndarray (n,) bool
        More obstacle points than ground points in the voxel.
    object : np.ndarray (n,) int32
        The tracked object of the voxel's obstacle points (-1 none).
    frames : np.ndarray (n,) int32
        Frames with a point in the voxel.
    count : np.ndarray (n,) int32
        Points in the voxel, over every frame.
    """

    xyz: np.ndarray
    label: np.ndarray
    obstacle: np.ndarray
    object: np.ndarray
    frames: np.ndarray
    count: np.ndarray


@dataclass(frozen=True, eq=False)
class DriveMap:
    """The map of a drive: the grid, the objects, the fused cloud and a record per frame."""

    grid: GridMap
    objects: tuple[MapObject, ...]
    cloud: FusedCloud
    frames: tuple[FrameRecord, ...]
    poses: Poses
    label_names: list[str]
    rule_base: str
    rule_file: str
    params: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    notes: tuple[str, ...] = ()

    @property
    def fuse_ms_per_frame(self) -> float:
        """Median time spent fusing a frame (grid, tracking, cloud), milliseconds."""
        return 1e3 * float(np.median([f.fuse_seconds for f in self.frames]))


class _CloudAccumulator:
    """Per frame, the points reduced to voxels (sums and counts); reduced again at the end."""

    def __init__(self, voxel_size: float, n_labels: int) -> None:
        self.voxel_size, self.n_labels = voxel_size, n_labels
        self.parts: list[tuple[np.ndarray, ...]] = []

    def add(self, xyz: np.ndarray, label: np.ndarray, node: np.ndarray) -> None:
        keys = voxel_keys(xyz, self.voxel_size)
        uniq, inv = np.unique(keys, return_inverse=True)
        m = len(uniq)
        sums = np.column_stack([np.bincount(inv, weights=xyz[:, d], minlength=m) for d in range(3)])
        lab = np.where(label < 0, self.n_labels, label)  # noise counted in the last column
        per_label = np.bincount(inv * (self.n_labels + 1) + lab, minlength=m * (self.n_labels + 1))
        nodes = np.full(m, -1, dtype=np.int64)
        np.maximum.at(nodes, inv, node)
        self.parts.append((uniq, sums, per_label.reshape(m, self.n_labels + 1), nodes))

    def result(self, ground_index: int | None, object_of_node: np.ndarray) -> FusedCloud:
        keys = np.concatenate([p[0] for p in self.parts])
        uniq, inv = np.unique(keys, return_inverse=True)
        m = len(uniq)
        sums = np.concatenate([p[1] for p in self.parts])
        per_label = np.concatenate([p[2] for p in self.parts])
        nodes = np.concatenate([p[3] for p in self.parts])
        count = np.bincount(inv, weights=per_label.sum(axis=1), minlength=m)
        xyz = np.column_stack([np.bincount(inv, weights=sums[:, d], minlength=m) / count for d in range(3)])
        lab = np.zeros((m, self.n_labels + 1))
        for j in range(self.n_labels + 1):
            lab[:, j] = np.bincount(inv, weights=per_label[:, j], minlength=m)
        label = np.argmax(lab[:, : self.n_labels], axis=1).astype(np.int32)
        label[lab[:, : self.n_labels].sum(axis=1) == 0] = -1
        if ground_index is None:
            obstacle = label >= 0
        else:
            n_ground = lab[:, ground_index]
            n_obst = lab[:, : self.n_labels].sum(axis=1) - n_ground
            obstacle = n_obst > n_ground
        obj_entry = np.where(nodes >= 0, object_of_node[np.maximum(nodes, 0)] if len(object_of_node) else -1, -1)
        obj = np.full(m, -1, dtype=np.int64)
        np.maximum.at(obj, inv, obj_entry)
        frames = np.bincount(inv, minlength=m)
        return FusedCloud(xyz, label, obstacle, np.where(obstacle, obj, -1).astype(np.int32),
                          frames.astype(np.int32), count.astype(np.int32))


def to_world(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``X`` (n, 3) moved by the 4x4 ``T``: ``R x + t`` per point (column by column: a 3x3
    matrix product through BLAS costs more in thread start-up than in arithmetic)."""
    W = np.empty_like(X, dtype=np.float64)
    for k in range(3):
        W[:, k] = X[:, 0] * T[k, 0] + X[:, 1] * T[k, 1] + X[:, 2] * T[k, 2] + T[k, 3]
    return W


def _check(name: str, value: Any, low: float, integer: bool = False, low_open: bool = True) -> Any:
    ok = isinstance(value, (int, np.integer)) if integer else isinstance(value, (int, float, np.floating, np.integer))
    ok = ok and not isinstance(value, bool) and np.isfinite(value) and (value > low if low_open else value >= low)
    if not ok:
        what = "an int" if integer else "a float"
        raise ParameterError(f"The {name!r} parameter of map_drive must be {what} in the range "
                             f"{'(' if low_open else '['}{low:g}, inf). Got {value!r} instead.")
    return value


def map_drive(segmenter: Any, drive: Drive | Iterable[np.ndarray], poses: Poses | np.ndarray | None = None, *,
              cell_size: float = 0.2, voxel_size: float = 0.1, min_obstacle_points: int = 1,
              l_obstacle: float = 0.85, l_ground: float = -0.4, l_clamp: float = 3.5, max_gap: int = 1,
              min_object_points: int = 40, alpha: float | None = None, explain: bool = False,
              odometry: Any = None, progress: Callable[[FrameRecord], None] | None = None,
              scheduler: str | None = None, workers: int | None = None) -> DriveMap:
    """Segment every frame of a drive with ``segmenter`` and fuse the frames into a map.

    Parameters
    ----------
    segmenter : kbs.Segmenter
        The loaded rule base (built once; every frame is segmented in its own sensor frame). Its
        label ``"ground"`` is the navigable ground; every other label is an obstacle.
    drive : Drive or iterable of (n, 3) arrays
        The frames (a :class:`Drive` carries its poses; arrays take ``poses``).
    poses : Poses or array (n_frames, 4, 4), optional
        Sensor-to-world transforms of array frames (None: identity). Not allowed with a Drive.
    cell_size : float
        Side of a grid cell, metres.
    voxel_size : float
        Voxel side of the fused cloud and of the objects' points, metres.
    min_obstacle_points, l_obstacle, l_ground, l_clamp
        The grid's votes (:class:`kbs.maps.grid.FusionParams`).
    max_gap : int
        Obstacle clusters of frames up to this many frames apart that overlap are one object.
    min_object_points : int
        Pieces of obstacle clusters with fewer points are not tracked as objects (they still vote
        in the grid). 40, the outdoor rule base's ``limits.min_points``: below it the rule base
        does not split a cluster any more, and a piece that small is mostly a fragment of an
        object seen better in another frame (on the generated 20-frame drive of
        docs/BENCHMARKS.md, 20 gave 3 true objects split in two, 40 none).
    alpha : float, optional
        Alpha-shape radius of the objects' meshes, metres (default ``3 voxel_size``).
    explain : bool
        Keep, in each :class:`FrameRecord`'s ``explanations``, why each cluster of a tracked
        object ended as it did (the map view of the HTML report shows it on a click).
    odometry : kbs.maps.odometry.Odometry, optional
        Estimate the poses instead of taking the drive's: each frame, once segmented, is
        registered with KISS-ICP on its points the segmentation did not call ground (the map's
        ``poses`` are then the estimated ones, with their residuals). Its errors (a frame that
        cannot be registered) are :class:`FitError`.
    progress : callable, optional
        Called with each frame's :class:`FrameRecord` once it is fused.
    scheduler : str, optional
        Segment the frames as Dask tasks: ``"local"`` (a ``LocalCluster`` of ``workers`` processes,
        default one per core, started for this call) or the address of a running scheduler (its
        workers load the rule file and plugins from the same paths). Each worker segments with its
        own loaded copy of ``segmenter``'s rule base; the frames are fused here, in their order, as
        their segmentations arrive, so the map is the one of the in-process run (None).
    workers : int, optional
        The number of workers of a ``"local"`` scheduler.

    Returns
    -------
    DriveMap

    Raises
    ------
    ParameterError
        A parameter out of range, no frame, poses that are not rigid or not one per frame.
    CloudFileError
        A scan file that cannot be read.
    FitError
        The segmenter could not fit a frame.
    """
    for name, value in (("cell_size", cell_size), ("voxel_size", voxel_size), ("l_obstacle", l_obstacle),
                        ("l_clamp", l_clamp)):
        _check(name, value, 0.0)
    if isinstance(l_ground, bool) or not isinstance(l_ground, (int, float, np.floating, np.integer)) or \
            not np.isfinite(l_ground) or l_ground >= 0:
        raise ParameterError(f"The 'l_ground' parameter of map_drive must be a float in the range (-inf, 0). "
                             f"Got {l_ground!r} instead.")
    _check("min_obstacle_points", min_obstacle_points, 1, integer=True, low_open=False)
    _check("max_gap", max_gap, 1, integer=True, low_open=False)
    _check("min_object_points", min_object_points, 1, integer=True, low_open=False)
    alpha = 3.0 * voxel_size if alpha is None else _check("alpha", alpha, 0.0)
    if isinstance(drive, Drive):
        if poses is not None:
            raise ParameterError("a Drive carries its poses: pass poses=None (or arrays as frames)")
    else:
        frames = list(drive)
        drive = Drive.from_arrays(frames, as_poses(poses, len(frames)))
    names = list(segmenter.label_names)
    gi = names.index("ground") if "ground" in names else None
    notes = [] if gi is not None else [f"the rule base has no label 'ground' (labels: {', '.join(names)}): every "
                                       "labelled point counts as an obstacle"]
    if drive.poses.note and odometry is None:
        notes.insert(0, drive.poses.note)
    fparams = FusionParams(cell_size, l_obstacle, l_ground, l_clamp, min_obstacle_points)
    grid = GridAccumulator(fparams)
    tracker = ObjectTracker(cell_size, voxel_size, max_gap=max_gap, min_points=min_object_points)
    cloud = _CloudAccumulator(voxel_size, len(names))
    records: list[FrameRecord] = []
    framed = list(zip(drive.frames, drive.poses.matrices))

    def fuse_frame(i: int, X: np.ndarray, seg: Any) -> None:
        frame, T = framed[i]
        if isinstance(seg, FitError):
            raise FitError(f"frame {i} ({frame.name}): {seg}") from seg
        if isinstance(seg, BaseException):  # another KbsError of a Dask worker's segmenter, or its task lost twice
            raise seg
        ground = seg.label == gi if gi is not None else np.zeros(len(X), dtype=bool)
        if odometry is not None:
            T = odometry.register(X, frame.name, keep=~ground)
        t0 = time.perf_counter()
        W = to_world(X, T)
        labelled = seg.label >= 0
        obstacle = labelled & ~ground
        grid.add(W, ground, obstacle)
        node = tracker.add(i, W, seg.cluster, obstacle)
        cloud.add(W, seg.label, node)
        has = node >= 0
        pairs = np.unique((seg.cluster[has].astype(np.int64) << np.int64(32)) | node[has])
        mapping: dict[int, list[int]] = {}
        for key in pairs.tolist():
            mapping.setdefault(key >> 32, []).append(key & 0xFFFFFFFF)
        fuse = time.perf_counter() - t0
        why: dict[int, dict[str, Any]] = {}
        if explain:
            for c in mapping:
                info = seg.clusters[c]
                why[c] = {"label": info["label"], "n_points": int(info["n_points"]), "ids": list(info["ids"]),
                          "why": [seg.explanation.why(r) for r in info["ids"]]}
        rec = FrameRecord(i, frame.name, frame.path, T.copy(), len(X), int(ground.sum()), int(obstacle.sum()),
                          int((~labelled).sum()), len(seg.clusters), dict(mapping), seg.seconds, fuse, why)
        records.append(rec)
        if progress is not None:
            progress(rec)

    if scheduler is None:
        for i, (frame, _) in enumerate(framed):
            X = frame.load()
            try:
                seg = segmenter.segment(X)
            except FitError as exc:
                seg = exc
            fuse_frame(i, X, seg)
    else:
        _segment_on_dask(segmenter, [f for f, _ in framed], scheduler, workers, fuse_frame)
    groups, of_node = tracker.objects()
    objects = []
    for oid, g in enumerate(groups):
        pts = voxel_mean(np.concatenate([tracker.points[n] for n in g]), voxel_size)
        try:
            V, F, kind = object_mesh(pts, alpha)
        except ValueError as exc:
            V = F = None
            kind = f"none: {exc}"
        nodes = [tracker.nodes[n] for n in g]
        objects.append(MapObject(oid, tuple(sorted({n.frame for n in nodes})),
                                 tuple(sorted({(n.frame, n.cluster) for n in nodes})), sum(n.n_points for n in nodes),
                                 pts, V, F, kind))
    records = [FrameRecord(**{**r.__dict__, "objects": {c: sorted({int(of_node[n]) for n in ns})
                                                        for c, ns in r.objects.items()}})
               for r in records]
    params = {"cell_size": cell_size, "voxel_size": voxel_size, "min_obstacle_points": min_obstacle_points,
              "l_obstacle": l_obstacle, "l_ground": l_ground, "l_clamp": l_clamp, "max_gap": max_gap,
              "min_object_points": min_object_points, "alpha": alpha}
    rb = segmenter.rule_base
    poses_used = drive.poses
    if odometry is not None:
        poses_used = odometry.poses()
        notes.insert(0, poses_used.note)
    return DriveMap(grid.result(), tuple(objects), cloud.result(gi, of_node), tuple(records), poses_used, names,
                    rb.name, rb.path, params, drive.source, tuple(notes))


def _segment_on_dask(segmenter: Any, frames: list[Any], scheduler: str, workers: int | None,
                     fuse_frame: Callable[[int, np.ndarray, Any], None]) -> None:
    """Segment ``frames`` as Dask tasks (:func:`kbs.tiles.run.submit_all`: a bounded number in
    flight, a task lost with its worker run again once) and hand each to ``fuse_frame(i, X,
    segmentation or error)`` in frame order: a frame that ends before an earlier one waits (with its
    points) until that one is fused."""
    import logging

    from kbs.errors import KbsError
    from kbs.tiles.run import segment_task, submit_all

    logging.getLogger("distributed").setLevel(logging.ERROR)  # a worker's start and stop are not kbs's news
    spec = (segmenter.rule_base.path, tuple(segmenter.sensor), tuple(segmenter.plugins))
    loaded: dict[int, np.ndarray] = {}
    arrived: dict[int, Any] = {}
    next_frame = 0

    def task_of(k: int) -> tuple[Any, ...]:
        loaded[k] = frames[k].load()  # read here: the fusion needs the points too
        return (segment_task, *spec, loaded[k], None)

    def finished(k: int, out: Any, done: int) -> None:
        nonlocal next_frame
        if isinstance(out, BaseException) and not isinstance(out, KbsError):
            out = FitError(f"its Dask task failed twice ({type(out).__name__}: {out})")
        arrived[k] = out
        while next_frame in arrived:
            fuse_frame(next_frame, loaded.pop(next_frame), arrived.pop(next_frame))
            next_frame += 1

    submit_all(scheduler, workers, None, finished, range(len(frames)), task_of, [f.name for f in frames])
