"""Poses estimated from the scans themselves, with KISS-ICP (Vizzo et al., RA-L 2023; the
``kiss-icp`` package of the ``map`` extra), for drives that come without poses.

Each frame is registered against KISS-ICP's local map of the frames before it (point-to-point
ICP with an adaptive threshold and a constant-velocity prediction; no deskewing, as the frames
carry no per-point time). The world frame is the first frame's sensor frame.

The residual of a frame is measured here, independently of the registration: the median
distance from its points (a 1-in-``stride`` sample, brought into the world with the estimated
pose) to the nearest point of the previous frame, among the points within ``inlier_distance``;
and the fraction of points within that distance (the overlap). A frame whose overlap falls
below ``min_overlap`` after registration is a failed registration (a :class:`FitError`, exit
code 5): the frames do not see the same scene, or the motion between them is too large.

``kbs map --estimate-poses`` registers each frame once segmented, on its points the segmentation
did not call ground (:class:`Odometry`, ``map_drive(..., odometry=...)``): flat ground sampled
anew in every frame holds a point-to-point ICP near no motion (on the generated drives KISS-ICP
found 0.05-0.2 m a frame for 1 m driven with the ground in; 0.9-1.0 m without it).

Before registering, each frame is checked for a degenerate scene, on what the registration sees
(the registered points, one per voxel of KISS-ICP's voxel size): fewer than ``min_voxels``
occupied voxels (nothing but ground: too little to register on), or less than
``min_constraint`` of their surface facing the horizontal direction they constrain least
(:func:`horizontal_constraint`: a corridor, a single wall), along which ICP slides whatever its
residual says; both are a :class:`FitError` too. Measured off the ground: SemanticKITTI frames
0.25; the street drives of ``kbs synth outdoor --frames N --street`` 0.17-0.33; the rover drives
without a street 0.003-0.19, and some of their frames have almost nothing off the ground (26-40
voxels); a corridor 0.00. The bound 0.03 keeps frames with one elongated rock out. With all the
points (:func:`estimate_poses`), the ground counts too: SemanticKITTI 0.19-0.22, the rover drives
0.001-0.015, the street drives 0.047-0.12.

KISS-ICP is configured for the sensor's range as its own pipeline does: ``max_range`` (default:
the first frame's farthest registered point, at most 100 m) and a voxel of ``max_range / 100``;
no deskewing (the frames carry no per-point time).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kbs.errors import FitError, ParameterError
from kbs.maps.drive import Drive, Frame
from kbs.maps.poses import Poses


@dataclass(frozen=True)
class FrameResidual:
    """How well a frame sits on the previous one: after registration and with no motion at all.

    Attributes
    ----------
    median : float
        Median distance to the previous frame's nearest point, metres (points within the inlier
        distance).
    overlap : float
        Fraction of the frame's points within the inlier distance of the previous frame.
    median_identity, overlap_identity : float
        The same with the frame left where it was (no motion): what registration improved.
    """

    median: float
    overlap: float
    median_identity: float
    overlap_identity: float


def kiss_icp_available() -> bool:
    """Whether KISS-ICP (the ``map`` extra) is installed."""
    try:
        import kiss_icp  # noqa: F401
    except ImportError:
        return False
    return True


def horizontal_constraint(X: np.ndarray, *, k: int = 12, n: int = 5000) -> tuple[float, np.ndarray]:
    """How much the surfaces of a frame constrain a horizontal motion, in its weakest direction.

    The normals of ``n`` sampled points (the least-variance axis of their ``k`` nearest
    neighbours) give ``H = mean(n_xy n_xy^T)``; its smallest eigenvalue is the mean squared
    component of the normals along the horizontal direction they constrain least (0: every
    surface horizontal, as flat ground, along which ICP slides freely; 0.5: walls all round).

    Returns
    -------
    value : float
    direction : np.ndarray (2,)
        The weakest horizontal direction.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    idx = rng.choice(len(X), min(n, len(X)), replace=False)
    _, nb = cKDTree(X).query(X[idx], k=min(k, len(X)))
    P = X[nb] - X[nb].mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", P, P))
    normal = vec[:, :, 0]
    w, v = np.linalg.eigh(normal[:, :2].T @ normal[:, :2] / len(normal))
    return float(w[0]), v[:, 0]


def _residual(points: np.ndarray, tree, inlier_distance: float) -> tuple[float, float]:
    d, _ = tree.query(points, distance_upper_bound=inlier_distance)
    ok = np.isfinite(d)
    return (float(np.median(d[ok])) if ok.any() else float("inf")), float(ok.mean())


def _default_range(X: np.ndarray) -> float:
    """KISS-ICP's ``max_range`` for a sensor whose frame is ``X``: its farthest point, rounded up
    to a metre, at most 100 m (KISS-ICP's default)."""
    far = float(np.sqrt((np.asarray(X, dtype=np.float64) ** 2).sum(axis=1).max())) if len(X) else 100.0
    return float(min(100.0, max(1.0, np.ceil(far))))


class Odometry:
    """Sensor poses estimated frame after frame with KISS-ICP (online: :meth:`register` each frame
    in order, then :meth:`poses`). :func:`estimate_poses` runs it over a drive; ``map_drive(...,
    odometry=Odometry())`` runs it inside the mapping loop, on each frame's points that its
    segmentation did not call ground (``keep``): flat ground, sampled anew in every frame, holds a
    point-to-point ICP near no motion (the generated drives' motion came out 0.05-0.2 m a frame for
    1 m driven with the ground in, 0.9-1.0 m without it).

    Parameters are those of :func:`estimate_poses`, and ``origin`` (4x4, optional): the first
    frame's pose, the world frame's placement (default the identity: the world is the first
    frame's sensor frame).
    """

    def __init__(self, *, voxel_size: float | None = None, max_range: float | None = None, min_range: float = 0.0,
                 inlier_distance: float = 0.3, min_overlap: float = 0.5, stride: int = 10,
                 min_constraint: float = 0.03, min_voxels: int = 30, origin: np.ndarray | None = None) -> None:
        try:
            from kiss_icp.config import load_config
            from kiss_icp.kiss_icp import KissICP
        except ImportError as exc:
            raise ParameterError("estimating poses needs KISS-ICP: pip install 'kbs[map]' (or give --poses)") from exc
        self._load_config, self._kiss = load_config, KissICP
        for name, value in (("voxel_size", voxel_size), ("max_range", max_range), ("inlier_distance", inlier_distance)):
            if value is None and name != "inlier_distance":
                continue
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ParameterError(f"The {name!r} parameter of estimate_poses must be a float in the range (0, inf). "
                                     f"Got {value!r} instead.")
        if not 0 <= min_overlap <= 1:
            raise ParameterError(f"The 'min_overlap' parameter of estimate_poses must be a float in the range [0, 1]. "
                                 f"Got {min_overlap!r} instead.")
        self.voxel_size, self.max_range, self.min_range = voxel_size, max_range, float(min_range)
        self.inlier_distance, self.min_overlap, self.stride = float(inlier_distance), float(min_overlap), int(stride)
        self.min_constraint, self.min_voxels = float(min_constraint), int(min_voxels)
        self.origin = np.eye(4) if origin is None else np.asarray(origin, dtype=np.float64)
        if self.origin.shape != (4, 4) or not np.isfinite(self.origin).all():
            raise ParameterError(f"The 'origin' parameter of Odometry must be a 4x4 matrix. Got {origin!r} instead.")
        self._odometry: Any = None
        self.far, self.voxel = 100.0, 1.0
        self.matrices: list[np.ndarray] = []
        self.residuals: list[FrameResidual] = []
        self.on_ground = False
        self._prev_tree: Any = None

    def register(self, X: np.ndarray, name: str, keep: np.ndarray | None = None) -> np.ndarray:
        """The pose (4x4, sensor to world) of the next frame ``X`` (n, 3), registered on the points
        ``keep`` (a boolean mask; default all).

        Raises
        ------
        FitError
            The frame is degenerate for ICP (too little to register on, or its surfaces leave a
            horizontal direction free), or its registration failed (KISS-ICP's error, a pose
            that is not finite, an overlap with the previous frame below ``min_overlap``).
        """
        from scipy.spatial import cKDTree

        from kbs.maps.objects import voxel_mean

        i = len(self.matrices)
        X = np.asarray(X, dtype=np.float64)
        if keep is not None:
            self.on_ground = True
            X = X[np.asarray(keep, dtype=bool)]
        if self._odometry is None:  # configured for the sensor's range, from the first frame
            self.far = _default_range(X) if self.max_range is None else float(self.max_range)
            self.voxel = self.far / 100.0 if self.voxel_size is None else float(self.voxel_size)
            config = self._load_config(None)
            config.data.deskew = False
            config.data.max_range, config.data.min_range = self.far, self.min_range
            config.mapping.voxel_size = self.voxel
            self._odometry = self._kiss(config)
        what = "points off the ground" if keep is not None else "points"
        r2 = (X ** 2).sum(axis=1)
        seen = voxel_mean(X[(r2 <= self.far ** 2) & (r2 >= self.min_range ** 2)], self.voxel) if len(X) else X
        if len(seen) < self.min_voxels:
            raise FitError(f"frame {i} ({name}) cannot be registered: its {what} fill only {len(seen)} voxels of "
                           f"{self.voxel:g} m within {self.far:g} m (at least {self.min_voxels} needed): too little "
                           f"structure to register on; give the poses (--poses)")
        if self.min_constraint > 0:
            value, direction = horizontal_constraint(seen)
            if value < self.min_constraint:
                raise FitError(f"frame {i} ({name}) cannot be registered reliably: only {value:.1%} of the surface of "
                               f"its {what} faces the horizontal direction ({direction[0]:+.2f}, {direction[1]:+.2f}) "
                               f"(at least {self.min_constraint:.0%} needed, one point per {self.voxel:g} m voxel): "
                               f"ICP slides along that direction; give the poses (--poses)")
        try:
            self._odometry.register_frame(np.array(X, dtype=np.float64, order="C"), np.zeros(len(X)))  # a writable copy
        except Exception as exc:  # noqa: BLE001 - the C++ core's errors, for one frame
            raise FitError(f"registration of frame {i} ({name}) failed in KISS-ICP: {exc}") from exc
        T = self.origin @ np.array(self._odometry.last_pose, dtype=np.float64)
        if not np.isfinite(T).all():
            raise FitError(f"registration of frame {i} ({name}) failed: KISS-ICP returned a pose that is not finite")
        W = X @ T[:3, :3].T + T[:3, 3]
        if self._prev_tree is not None:
            med, overlap = _residual(W[::self.stride], self._prev_tree, self.inlier_distance)
            prev_T = self.matrices[-1]
            still = X[::self.stride] @ prev_T[:3, :3].T + prev_T[:3, 3]  # no motion since the previous frame
            med0, overlap0 = _residual(still, self._prev_tree, self.inlier_distance)
            if overlap < self.min_overlap:
                raise FitError(f"registration of frame {i} ({name}) failed: after it only {overlap:.0%} of the "
                               f"frame's {what} lie within {self.inlier_distance:g} m of frame {i - 1}'s (at least "
                               f"{self.min_overlap:.0%} needed; {overlap0:.0%} with no motion); the frames do not "
                               f"overlap enough: give the poses (--poses)")
            self.residuals.append(FrameResidual(med, overlap, med0, overlap0))
        self._prev_tree = cKDTree(W)
        self.matrices.append(T)
        return T

    def poses(self) -> Poses:
        """The poses registered so far (source ``"estimated"``, with the residuals and a note)."""
        if not self.matrices:
            raise ParameterError("no frame to register")
        P = np.array(self.matrices)
        on = " on the points the segmentation did not call ground" if self.on_ground else ""
        if self.residuals:
            meds = [r.median for r in self.residuals]
            steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
            note = (f"poses estimated with KISS-ICP{on} (range {self.far:g} m, voxel {self.voxel:g} m); residual to "
                    f"the previous frame: median {np.median(meds):.3f} m (worst {max(meds):.3f} m; "
                    f"{np.median([r.median_identity for r in self.residuals]):.3f} m with no motion), overlap at least "
                    f"{min(r.overlap for r in self.residuals):.0%}; motion {np.median(steps):.2f} m per frame (median)")
        else:
            note = "poses estimated with KISS-ICP: one frame, the identity"
        return Poses(P, "estimated", None, note, tuple(self.residuals))


def estimate_poses(frames: Drive | Sequence[Frame] | Sequence[np.ndarray], *, voxel_size: float | None = None,
                   max_range: float | None = None, min_range: float = 0.0, inlier_distance: float = 0.3,
                   min_overlap: float = 0.5, stride: int = 10, min_constraint: float = 0.03,
                   min_voxels: int = 30) -> Poses:
    """Estimate the sensor-to-world pose of every frame with KISS-ICP, on all its points (see
    :class:`Odometry` for registering on the points above the ground).

    Parameters
    ----------
    frames : Drive, sequence of Frame or of (n, 3) arrays
        The frames in order (a Drive's own poses are ignored).
    voxel_size : float, optional
        KISS-ICP's map voxel, metres (default, as KISS-ICP's: ``max_range / 100``).
    max_range : float, optional
        Points farther than this from the sensor are left out of the registration, metres
        (default: the first frame's farthest point, rounded up, at most 100).
    min_range : float
        Points nearer than this are left out.
    inlier_distance : float
        Distance within which a point counts as overlapping the previous frame, metres. 0.3: two
        consecutive SemanticKITTI frames overlap by 94 % after registration, a frame of another
        sequence registered on them by 23 % (at 1 m, 99 % and 56 %: flat roads match anywhere).
    min_overlap : float
        Least overlap of a registered frame with the previous one; below it the registration
        has failed.
    stride : int
        One point in ``stride`` is used to measure the residuals.
    min_constraint : float
        Least :func:`horizontal_constraint` of a frame (0 disables the check).
    min_voxels : int
        Least number of occupied voxels a frame must have to be registered.

    Returns
    -------
    Poses
        Source ``"estimated"``; ``residuals`` holds a :class:`FrameResidual` per frame after the
        first, and ``note`` says how the poses were estimated and the residuals.

    Raises
    ------
    ParameterError
        KISS-ICP is not installed, or a parameter is out of range.
    FitError
        A registration failed (the overlap with the previous frame below ``min_overlap``, or a
        pose that is not finite), or a frame is degenerate for it (``min_constraint``,
        ``min_voxels``).
    """
    odometry = Odometry(voxel_size=voxel_size, max_range=max_range, min_range=min_range,
                        inlier_distance=inlier_distance, min_overlap=min_overlap, stride=stride,
                        min_constraint=min_constraint, min_voxels=min_voxels)
    items = list(frames.frames if isinstance(frames, Drive) else frames)
    if not items:
        raise ParameterError("no frame to register")
    for i, item in enumerate(items):
        X = item.load() if isinstance(item, Frame) else np.asarray(item, dtype=np.float64)
        odometry.register(X, item.name if isinstance(item, Frame) else f"frame {i}")
    return odometry.poses()
