"""The labelled scene every generator returns, and its PLY export."""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from kbs.synth._params import count
from kbs.synth.raycast import HeightField


def _frozen(a: np.ndarray, dtype) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Face:
    """One planar face of a polyhedral scene, in the sensor frame.

    Attributes
    ----------
    label : int
        The face id (``Scene.labels``); 0 is the ground.
    object : int
        The object it belongs to (``Scene.objects``); 0 is the ground.
    name : str
        ``ground``, or the face's name on its solid (``top``, ``+a``, ``slope-``, ...).
    normal : np.ndarray, shape (3,)
        Outward unit normal (the side the sensor sees).
    offset : float
        The plane is ``normal . x = offset``.
    polygon : np.ndarray, shape (k, 3) or None
        The face's vertices in order around it; None for the unbounded ground.
    """

    label: int
    object: int
    name: str
    normal: np.ndarray
    offset: float
    polygon: np.ndarray | None = None

    def distance(self, X: np.ndarray) -> np.ndarray:
        """Signed distance of points ``X`` (n, 3) to the face's plane (positive: in front)."""
        return np.asarray(X) @ self.normal - self.offset


@dataclass(frozen=True, eq=False)
class Scene:
    """A labelled synthetic point cloud in the sensor frame (metres).

    The sensor is at the origin; z is up (against gravity), x is the horizontal direction the
    sensor looks towards, y points to its left. The ground lies about ``sensor_height`` below.

    Attributes
    ----------
    xyz : np.ndarray, shape (n, 3), float64
        The points.
    labels : np.ndarray, shape (n,), int32
        Ground-truth region of each point: the planar face id for a polyhedral scene (0 the
        ground, 1.. the visible faces of the solids), the object id for an outdoor scene.
    objects : np.ndarray, shape (n,), int32
        Object of each point: 0 the ground, then the solids, rocks or the bin (``object_names``).
    ground : np.ndarray, shape (n,), bool
        Whether the point is on the ground (``objects == 0``).
    kind : str
        ``"polyhedral"`` or ``"outdoor"``.
    seed : int
        The seed the scene was generated from (same seed and options, same arrays).
    description : str
        One ASCII line saying what the scene holds and how it was seen.
    object_names : tuple of str
        Name of each object id (``object_names[0] == "ground"``).
    normals_by_label : Mapping[int, np.ndarray] or None
        Polyhedral scenes: the outward unit normal of each face id present in ``labels``.
    faces : Mapping[int, Face] or None
        Polyhedral scenes: each face id's plane and polygon.
    pixel : np.ndarray, shape (n,), int64, or None
        Row-major index of the pixel each point was seen through, in an image of ``shape``.
    shape : (int, int) or None
        ``(rows, cols)`` of the simulated sensor's image.
    terrain : HeightField or None
        Outdoor scenes: the ground's height ``z = terrain(x, y)``.
    solids : tuple
        The analytic objects, ``solids[i - 1]`` for object id ``i``: :class:`~kbs.synth.polyhedral.Solid`
        (half-spaces, vertices), :class:`~kbs.synth.outdoor.Rock` or :class:`~kbs.synth.outdoor.Bin`.
    params : Mapping[str, Any]
        The generator's arguments.
    """

    xyz: np.ndarray
    labels: np.ndarray
    objects: np.ndarray
    ground: np.ndarray
    kind: str
    seed: int
    description: str
    object_names: tuple[str, ...] = ("ground",)
    normals_by_label: Mapping[int, np.ndarray] | None = None
    faces: Mapping[int, Face] | None = None
    pixel: np.ndarray | None = None
    shape: tuple[int, int] | None = None
    terrain: HeightField | None = None
    solids: tuple[Any, ...] = ()
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.xyz)
        object.__setattr__(self, "xyz", _frozen(self.xyz, np.float64).reshape(n, 3))
        for name, dtype in (("labels", np.int32), ("objects", np.int32), ("ground", bool)):
            a = _frozen(getattr(self, name), dtype)
            if a.shape != (n,):
                raise ValueError(f"Scene.{name} must have shape ({n},), got {a.shape}")
            object.__setattr__(self, name, a)
        if self.pixel is not None:
            object.__setattr__(self, "pixel", _frozen(self.pixel, np.int64))
        for name in ("normals_by_label", "faces", "params"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, MappingProxyType):
                object.__setattr__(self, name, MappingProxyType(dict(value)))

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def n_labels(self) -> int:
        """Number of distinct labels present."""
        return int(np.unique(self.labels).size)

    @property
    def n_objects(self) -> int:
        """Number of distinct objects present (the ground included)."""
        return int(np.unique(self.objects).size)

    def summary(self) -> str:
        """One line: points, faces or objects, ground fraction."""
        ground = float(self.ground.mean()) if len(self) else 0.0
        parts = [f"{self.kind} scene (seed {self.seed}): {len(self):,} points"]
        if self.kind == "polyhedral":
            parts.append(f"{count(self.n_labels, 'face', 'faces')} on {count(self.n_objects, 'object', 'objects')}")
        else:
            parts.append(f"{count(self.n_objects, 'object', 'objects')} ({', '.join(self._present_names())})")
        parts.append(f"ground {100 * ground:.1f}%")
        return ", ".join(parts)

    def _present_names(self) -> list[str]:
        return [self.object_names[i] for i in np.unique(self.objects)]

    def save(self, path: str | os.PathLike[str], *, run_id: str | None = None) -> str:
        """Write the scene as a binary PLY file, whole or not at all; returns its run id.

        Per vertex: ``x y z`` (double), ``label`` and ``object`` (int), ``ground`` (uchar 0/1),
        and ``pixel`` (int) for a scene seen through an image. Header comments: the description,
        the object names, the image shape, and for polyhedral scenes one line per face
        (``face LABEL object OBJ normal NX NY NZ offset D``), then who wrote it and the run id
        (``kbs_run_id <hex>``, default a fresh one: it marks the file as kbs's, :func:`kbs.io.result.is_kbs_output`).

        Raises
        ------
        CloudFileError
            The file cannot be written.
        """
        from kbs.io import write_ply
        from kbs.io.result import new_run_id, result_comments

        fields: dict[str, np.ndarray] = {"label": self.labels, "object": self.objects, "ground": self.ground}
        comments = [f"kbs synth: {self.description}",
                    "objects: " + ", ".join(f"{i} {name}" for i, name in enumerate(self.object_names))]
        if self.pixel is not None and self.shape is not None:
            fields["pixel"] = self.pixel.astype(np.int32)
            comments.append(f"image shape (rows cols): {self.shape[0]} {self.shape[1]}")
        for label, face in (self.faces or {}).items():
            nx, ny, nz = face.normal
            comments.append(f"face {label} object {face.object} normal {nx:.9g} {ny:.9g} {nz:.9g} "
                            f"offset {face.offset:.9g}")
        run_id = run_id or new_run_id()
        write_ply(path, self.xyz, fields, comments=[*comments, *result_comments(run_id)])
        return run_id
