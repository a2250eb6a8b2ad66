"""Which way is up in a result: the view the figures and the HTML report draw.

A lidar scan is z up, and its map is the x-y plane. A camera's frame (stereo, RGB-D) has the
optical axis along z and "up" along -y: drawn in x-y, its scene lies on its side and its map is a
sliver. The up direction is the one the run used for the ground: the ground plane's normal it
found (oriented towards the sensor) or the rule base's ``scene.ground`` normal / fallback, as the
result JSON records it (``explanation.ground.normal``). Without a ground (a rule base that uses
none), z is up.

:func:`view_of` reads it; :class:`View` projects points on the plane perpendicular to up (the
map, the top view); the 3-D views turn the points so that up is vertical, a camera's frame seen
from behind the camera.

>>> v = View.from_up([0, -1, 0])
>>> v.camera_frame, v.right.tolist(), v.forward.tolist()
(True, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from kbs.knowledge.groundfacts import GroundFacts

#: Up within this angle of +z (or -z): the scan's own x-y plane is the map (axes named x and y).
LEVEL_DEGREES = 10.0


@dataclass(frozen=True)
class View:
    """An orthonormal frame (right, forward, up), right = forward x up, and where up came from."""

    up: np.ndarray  # (3,) unit
    forward: np.ndarray  # (3,) unit, perpendicular to up: the optical axis, or y, made level
    right: np.ndarray  # (3,) unit
    source: str

    @classmethod
    def from_up(cls, up: Any, source: str = "given") -> View:
        u = np.asarray(up, dtype=float)
        norm = float(np.linalg.norm(u))
        if u.shape != (3,) or not np.isfinite(norm) or norm == 0:
            u, source = np.array([0.0, 0.0, 1.0]), "z (no usable up direction)"
        else:
            u = u / norm
        if abs(u[2]) >= np.cos(np.radians(LEVEL_DEGREES)):  # a level scan: its own x and y
            s = 1.0 if u[2] > 0 else -1.0
            return cls(up=u, forward=np.array([0.0, s, 0.0]), right=np.array([1.0, 0.0, 0.0]), source=source)
        # a camera's optical axis (z), else y, made perpendicular to up
        cand = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        f = cand - (cand @ u) * u
        f /= np.linalg.norm(f)
        r = np.cross(f, u)
        return cls(up=u, forward=f, right=r / np.linalg.norm(r), source=source)

    @property
    def level(self) -> bool:
        """Up within :data:`LEVEL_DEGREES` of the z axis: the x-y plane is the map."""
        return abs(float(self.up[2])) >= np.cos(np.radians(LEVEL_DEGREES))

    @property
    def camera_frame(self) -> bool:
        """Up closer to the y axis than to z: a camera's frame (optical axis z, up -y)."""
        return abs(float(self.up[1])) > abs(float(self.up[2]))

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rows right, forward, up: ``X @ R.T`` gives coordinates with up as the third."""
        return np.vstack([self.right, self.forward, self.up])

    def plan(self, X: np.ndarray) -> np.ndarray:
        """(n, 2) map coordinates: the points on the plane perpendicular to up (x, y for a level scan)."""
        X = np.asarray(X, dtype=float)
        if self.level and self.up[2] > 0:
            return X[..., :2].copy()
        return np.stack([X @ self.right, X @ self.forward], axis=-1)

    def height(self, X: np.ndarray) -> np.ndarray:
        """(n,) the coordinate along up."""
        return np.asarray(X, dtype=float) @ self.up

    def axis_names(self) -> tuple[str, str, str]:
        """Names of the right, forward and up axes for a figure: x, y, z for a level scan; else the
        directions in the scan's coordinates, e.g. 'x', 'z (forward)', '-y (up)'."""
        if self.level and self.up[2] > 0:
            return "x", "y", "z"
        return _name(self.right, "right"), _name(self.forward, "forward"), _name(self.up, "up")

    def describe(self) -> str:
        """'camera frame, up [0, -1, 0] (the ground plane the run found, cluster c0)'."""
        vec = "[" + ", ".join(f"{c:.3g}" for c in np.round(self.up, 3) + 0.0) + "]"  # + 0.0: no -0
        kind = "camera frame" if self.camera_frame else "level" if self.level else "tilted"
        return f"{kind}, up {vec} ({self.source})"


def _name(v: np.ndarray, what: str) -> str:
    i = int(np.argmax(np.abs(v)))
    if abs(v[i]) > 0.985:  # within 10 degrees of an axis
        return f"{'-' if v[i] < 0 else ''}{'xyz'[i]} ({what})"
    return what


def view_of(ground: GroundFacts | None) -> View:
    """The view of a result from its explanation's ground section: up is the ground normal the
    run recorded, else z."""
    normal = ground.normal if ground is not None else None
    if ground is None or normal is None:
        return View.from_up([0.0, 0.0, 1.0], "z: the run used no ground plane")
    src = ground.source or ""
    what = ("the rule base's fixed ground normal" if src == "fixed" else
            "the rule base's fallback ground normal" if src == "fallback" else f"the ground plane the run found, {src}")
    return View.from_up(normal, what)
