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

Before registering, each frame is checked for a degenerate scene
(:func:`horizontal_constraint`): when less than ``min_constraint`` of its surface faces the
horizontal direction it constrains least (flat ground with few objects, a corridor), ICP slides
along that direction and its motion cannot be trusted whatever its residual; that is a
:class:`FitError` too. SemanticKITTI frames measure about 0.15, the rover drives of
``kbs synth outdoor --frames`` 0.003-0.03 (their motion estimated there was 0.1 m per frame for
1 m driven): the bound 0.05 lies between.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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


def estimate_poses(frames: Drive | Sequence[Frame] | Sequence[np.ndarray], *, voxel_size: float = 1.0,
                   max_range: float = 100.0, min_range: float = 0.0, inlier_distance: float = 0.3,
                   min_overlap: float = 0.5, stride: int = 10, min_constraint: float = 0.05) -> Poses:
    """Estimate the sensor-to-world pose of every frame with KISS-ICP.

    Parameters
    ----------
    frames : Drive, sequence of Frame or of (n, 3) arrays
        The frames in order (a Drive's own poses are ignored).
    voxel_size : float
        KISS-ICP's map voxel, metres (its default: ``max_range / 100``).
    max_range, min_range : float
        Points farther or nearer than these from the sensor are left out of the registration.
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
        pose that is not finite), or a frame is degenerate for it (``min_constraint``).
    """
    try:
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP
    except ImportError as exc:
        raise ParameterError("estimating poses needs KISS-ICP: pip install 'kbs[map]' (or give --poses)") from exc
    from scipy.spatial import cKDTree

    for name, value in (("voxel_size", voxel_size), ("max_range", max_range), ("inlier_distance", inlier_distance)):
        if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
            raise ParameterError(f"The {name!r} parameter of estimate_poses must be a float in the range (0, inf). "
                                 f"Got {value!r} instead.")
    if not 0 <= min_overlap <= 1:
        raise ParameterError(f"The 'min_overlap' parameter of estimate_poses must be a float in the range [0, 1]. "
                             f"Got {min_overlap!r} instead.")
    items = list(frames.frames if isinstance(frames, Drive) else frames)
    if not items:
        raise ParameterError("no frame to register")
    config = load_config(None)
    config.data.deskew = False
    config.data.max_range, config.data.min_range = float(max_range), float(min_range)
    config.mapping.voxel_size = float(voxel_size)
    odometry = KissICP(config)
    poses, residuals = [], []
    prev_tree = None
    for i, item in enumerate(items):
        X = item.load() if isinstance(item, Frame) else np.asarray(item, dtype=np.float64)
        name = item.name if isinstance(item, Frame) else f"frame {i}"
        if min_constraint > 0 and len(X) >= 3:
            value, direction = horizontal_constraint(X)
            if value < min_constraint:
                raise FitError(f"frame {i} ({name}) cannot be registered reliably: only {value:.1%} of its surface "
                               f"faces the horizontal direction ({direction[0]:+.2f}, {direction[1]:+.2f}) (at least "
                               f"{min_constraint:.0%} needed): the scene is mostly flat ground, along which ICP "
                               f"slides; give the poses (--poses)")
        try:
            odometry.register_frame(np.array(X, dtype=np.float64, order="C"), np.zeros(len(X)))  # a writable copy
        except Exception as exc:  # noqa: BLE001 - the C++ core's errors, for one frame
            raise FitError(f"registration of frame {i} ({name}) failed in KISS-ICP: {exc}") from exc
        T = np.array(odometry.last_pose, dtype=np.float64)
        if not np.isfinite(T).all():
            raise FitError(f"registration of frame {i} ({name}) failed: KISS-ICP returned a pose that is not finite")
        W = X @ T[:3, :3].T + T[:3, 3]
        sample = W[::stride]
        if prev_tree is not None:
            med, overlap = _residual(sample, prev_tree, inlier_distance)
            prev_T = poses[-1]
            still = X[::stride] @ prev_T[:3, :3].T + prev_T[:3, 3]  # no motion since the previous frame
            med0, overlap0 = _residual(still, prev_tree, inlier_distance)
            if overlap < min_overlap:
                raise FitError(f"registration of frame {i} ({name}) failed: after it only {overlap:.0%} of the "
                               f"frame's points lie within {inlier_distance:g} m of frame {i - 1} (at least "
                               f"{min_overlap:.0%} needed; {overlap0:.0%} with no motion); the frames do not "
                               f"overlap enough: give the poses (--poses)")
            residuals.append(FrameResidual(med, overlap, med0, overlap0))
        prev_tree = cKDTree(W)
        poses.append(T)
    P = np.array(poses)
    if residuals:
        meds = [r.median for r in residuals]
        steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
        note = (f"poses estimated with KISS-ICP (voxel {voxel_size:g} m); residual to the previous frame: median "
                f"{np.median(meds):.3f} m (worst {max(meds):.3f} m; {np.median([r.median_identity for r in residuals]):.3f}"
                f" m with no motion), overlap at least {min(r.overlap for r in residuals):.0%}; motion "
                f"{np.median(steps):.2f} m per frame (median)")
    else:
        note = "poses estimated with KISS-ICP: one frame, the identity"
    return Poses(P, "estimated", None, note, tuple(residuals))
