"""Polyhedral scenes seen by a simulated range sensor: a ground plane, boxes and wedges.

In the spirit of the range images of Hoover et al. (1996): planar-faced objects on a plane, one
range measurement per pixel, every point labelled with the planar face it lies on.
"""
from __future__ import annotations

import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from shapely.geometry import MultiPoint, Polygon

from kbs.errors import ParameterError
from kbs.inference import Interval, validate_params
from kbs.synth._params import check_pair, count
from kbs.synth.raycast import pinhole_rays, ray_convex, ray_plane
from kbs.synth.scene import Face, Scene

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Solid:
    """A convex solid standing on the ground: the intersection of half-spaces ``normals @ x <= offsets``.

    Attributes
    ----------
    kind : str
        ``"box"`` or ``"wedge"``.
    normals : np.ndarray, shape (k, 3)
        Outward unit normals of its faces.
    offsets : np.ndarray, shape (k,)
    face_names : tuple of str
        One name per face.
    vertices : np.ndarray, shape (v, 3)
    """

    kind: str
    normals: np.ndarray
    offsets: np.ndarray
    face_names: tuple[str, ...]
    vertices: np.ndarray

    def footprint(self) -> Polygon:
        """Its outline on the ground (the convex hull of its vertices seen from above)."""
        return MultiPoint(self.vertices[:, :2]).convex_hull

    def polygon(self, face: int, tol: float = 1e-9) -> np.ndarray:
        """Vertices (k, 3) of one face, in order around it."""
        n, d = self.normals[face], self.offsets[face]
        V = self.vertices[np.abs(self.vertices @ n - d) <= tol * max(1.0, abs(d))]
        centre = V.mean(axis=0)
        a = np.cross(n, _UP if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0]))
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        angle = np.arctan2((V - centre) @ b, (V - centre) @ a)
        return V[np.argsort(angle)]

    def contains(self, X: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether points ``X`` (n, 3) are inside, at least ``margin`` from every face."""
        return (np.asarray(X) @ self.normals.T <= self.offsets - margin).all(axis=1)


def _frame(center_xy: Sequence[float], yaw: float, z0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    b = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    origin = np.array([center_xy[0], center_xy[1], z0])
    return origin, a, b


def box(center_xy: Sequence[float], size: Sequence[float], yaw: float, z0: float) -> Solid:
    """A box of ``size = (length, width, height)`` standing on the ground ``z = z0``, centred on
    ``center_xy``, its length along the direction ``a`` at angle ``yaw`` (radians from +x), its
    width along ``b`` (a turned 90 degrees left). Faces: ``+a``, ``-a``, ``+b``, ``-b``, ``top``,
    ``bottom``."""
    length, width, height = size
    o, a, b = _frame(center_xy, yaw, z0)
    normals = np.array([a, -a, b, -b, _UP, -_UP])
    offsets = np.array([a @ o + length / 2, -(a @ o) + length / 2, b @ o + width / 2, -(b @ o) + width / 2,
                        z0 + height, -z0])
    corners = np.array([[sa, sb, sz] for sa in (-1, 1) for sb in (-1, 1) for sz in (0, 1)], dtype=float)
    vertices = o + (corners[:, :1] * length / 2) * a + (corners[:, 1:2] * width / 2) * b + corners[:, 2:] * height * _UP
    return Solid("box", normals, offsets, ("+a", "-a", "+b", "-b", "top", "bottom"), vertices)


def wedge(center_xy: Sequence[float], size: Sequence[float], yaw: float, z0: float, apex: float) -> Solid:
    """A triangular prism standing on the ground ``z = z0``: a triangle of base ``length`` and
    height ``height`` in the vertical plane along ``yaw``, its apex at fraction ``apex`` of the
    base (0: a right-angled wedge whose back is vertical, 0.5: a symmetric roof), extruded over
    ``width``. Faces: ``slope-`` (on the -a side; vertical when ``apex`` is 0), ``slope+``, the
    triangular ends ``+b`` and ``-b``, ``bottom``."""
    length, width, height = size
    o, a, b = _frame(center_xy, yaw, z0)
    p = -length / 2 + apex * length  # apex position along a
    # in the (a, z) plane: the face from (-L/2, 0) to (p, H) and the one from (p, H) to (L/2, 0)
    n1 = np.array([-height, p + length / 2])
    n2 = np.array([height, length / 2 - p])
    n1, n2 = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
    N1 = n1[0] * a + n1[1] * _UP
    N2 = n2[0] * a + n2[1] * _UP
    normals = np.array([N1, N2, b, -b, -_UP])
    offsets = np.array([N1 @ o + n1[0] * -length / 2, N2 @ o + n2[0] * length / 2,
                        b @ o + width / 2, -(b @ o) + width / 2, -z0])
    profile = [(-length / 2, 0.0), (p, height), (length / 2, 0.0)]
    vertices = np.array([o + s * a + z * _UP + sb * width / 2 * b for s, z in profile for sb in (-1, 1)])
    return Solid("wedge", normals, offsets, ("slope-", "slope+", "+b", "-b", "bottom"), vertices)


def _view_region(fov_deg: tuple[float, float], tilt_deg: float, sensor_height: float, max_range: float) -> Polygon:
    """Where the image sees the ground within ``max_range``, as a polygon on the ground."""
    dirs = pinhole_rays((24, 24), fov_deg, tilt_deg)
    t = ray_plane(dirs, _UP, -sensor_height)
    ok = t <= max_range
    if ok.sum() < 3:
        return Polygon()
    return MultiPoint((dirs[ok] * t[ok, None])[:, :2]).convex_hull


def _in_view(X: np.ndarray, fov_deg: tuple[float, float], tilt_deg: float, inner: float, max_range: float) -> bool:
    """Whether every point of ``X`` (n, 3) projects inside the central ``inner`` part of the image
    and lies within ``max_range``."""
    tilt = np.radians(tilt_deg)
    depth = X @ np.array([np.cos(tilt), 0.0, -np.sin(tilt)])
    if (depth <= 0).any() or (np.linalg.norm(X, axis=1) > max_range).any():
        return False
    u = -X[:, 1] / depth
    v = (X @ np.array([np.sin(tilt), 0.0, np.cos(tilt)])) / depth
    return bool((np.abs(u) <= inner * np.tan(np.radians(fov_deg[1]) / 2)).all()
                and (np.abs(v) <= inner * np.tan(np.radians(fov_deg[0]) / 2)).all())


def place_solids(
    rng: np.random.Generator, kinds: list[str], region: Polygon, size_range: tuple[float, float], gap: float,
    z0: float, max_tries: int, in_view: Callable[[np.ndarray], bool],
) -> list[Solid]:
    """Solids of the given kinds at random positions and yaws, wholly in view (``in_view`` of
    their vertices), their footprints at least ``gap`` apart."""
    solids: list[Solid] = []
    footprints: list[Polygon] = []
    x0, y0, x1, y1 = region.bounds if not region.is_empty else (0.0, 0.0, 0.0, 0.0)
    for i, kind in enumerate(kinds):
        for _ in range(max_tries):
            center = (rng.uniform(x0, x1), rng.uniform(y0, y1))
            size = tuple(rng.uniform(*size_range, size=3))
            yaw = rng.uniform(0.0, np.pi)
            if kind == "box":
                solid = box(center, size, yaw, z0)
            else:
                apex = 0.0 if rng.uniform() < 0.5 else rng.uniform(0.3, 0.7)
                solid = wedge(center, size, yaw, z0, apex)
            if not in_view(solid.vertices):
                continue
            fp = solid.footprint()
            if all(fp.distance(other) >= gap for other in footprints):
                solids.append(solid)
                footprints.append(fp)
                break
        else:
            raise ParameterError(
                f"polyhedral_scene could not place solid {i + 1} of {len(kinds)} ({kind}) wholly in the "
                f"field of view without touching the others after {max_tries} tries; ask for fewer or "
                "smaller solids, or a wider field of view"
            )
    return solids


_POLY_CONSTRAINTS = {
    "seed": [Interval(numbers.Integral, 0, None)],
    "n_boxes": [Interval(numbers.Integral, 0, None)],
    "n_wedges": [Interval(numbers.Integral, 0, None)],
    "noise": [Interval(numbers.Real, 0, None)],
    "sensor_height": [Interval(numbers.Real, 0, None, closed="neither")],
    "tilt_deg": [Interval(numbers.Real, 0, 90, closed="right")],
    "max_range": [Interval(numbers.Real, 0, None, closed="neither")],
    "gap": [Interval(numbers.Real, 0, None)],
    "max_tries": [Interval(numbers.Integral, 1, None)],
}


def polyhedral_scene(
    seed: int = 0,
    *,
    n_boxes: int = 3,
    n_wedges: int = 1,
    resolution: tuple[int, int] = (240, 320),
    fov_deg: tuple[float, float] = (45.0, 60.0),
    noise: float = 0.002,
    sensor_height: float = 1.2,
    tilt_deg: float = 50.0,
    size_range: tuple[float, float] = (0.15, 0.45),
    max_range: float = 10.0,
    gap: float = 0.05,
    max_tries: int = 500,
) -> Scene:
    """A ground plane with boxes and wedges, seen by a range sensor looking down at them.

    One ray per pixel of a pinhole sensor at the origin, its optical axis ``tilt_deg`` below the
    horizontal, ``sensor_height`` above the ground plane ``z = -sensor_height``. The solids stand
    on the ground at random positions and yaws, wholly inside the image (before occlusion), their
    footprints at least ``gap`` apart (so they never intersect). Each ray keeps its nearest hit
    (occlusion), within ``max_range``; Gaussian noise of standard deviation ``noise`` is added to
    the range along the ray. Rays that hit nothing within ``max_range`` give no point.

    Parameters
    ----------
    seed : int
        Seed of the numpy Generator that places the solids and draws the noise.
    n_boxes, n_wedges : int
        Number of boxes and of wedges (triangular prisms, half right-angled, half roof-like).
    resolution : (int, int)
        ``(rows, cols)`` of the range image.
    fov_deg : (float, float)
        Vertical and horizontal fields of view, degrees.
    noise : float
        Standard deviation of the range noise, metres.
    sensor_height : float
        Height of the sensor above the ground, metres.
    tilt_deg : float
        Depression of the optical axis, degrees (90: looking straight down).
    size_range : (float, float)
        Each side (length, width, height) of a solid is uniform in this range, metres.
    max_range : float
        Farthest measurable range, metres.
    gap : float
        Least distance between two solids' footprints, metres.
    max_tries : int
        Random placements tried per solid before giving up.

    Returns
    -------
    Scene
        ``labels``: face ids, 0 the ground, then the visible faces of each solid in object
        order; ``objects``: 0 the ground, 1..n_boxes the boxes, then the wedges;
        ``normals_by_label`` and ``faces`` for every face id present; ``pixel`` and ``shape``.

    Raises
    ------
    ParameterError
        A parameter out of range, or solids that do not fit in the view.
    """
    params = dict(seed=seed, n_boxes=n_boxes, n_wedges=n_wedges, resolution=resolution, fov_deg=fov_deg,
                  noise=noise, sensor_height=sensor_height, tilt_deg=tilt_deg, size_range=size_range,
                  max_range=max_range, gap=gap, max_tries=max_tries)
    validate_params("polyhedral_scene", params, _POLY_CONSTRAINTS)
    resolution = check_pair("polyhedral_scene", "resolution", resolution, numbers.Integral, 0, None)
    fov_deg = check_pair("polyhedral_scene", "fov_deg", fov_deg, numbers.Real, 0, 180)
    size_range = check_pair("polyhedral_scene", "size_range", size_range, numbers.Real, 0, None)
    if size_range[0] > size_range[1]:
        raise ParameterError(f"The 'size_range' parameter of polyhedral_scene must be (low, high) with "
                             f"low <= high. Got {size_range!r} instead.")
    rng = np.random.default_rng(seed)
    z0 = -float(sensor_height)

    region = _view_region(fov_deg, tilt_deg, sensor_height, max_range)
    kinds = ["box"] * n_boxes + ["wedge"] * n_wedges
    solids = place_solids(rng, kinds, region, size_range, gap, z0, max_tries,
                    lambda X: _in_view(X, fov_deg, tilt_deg, 0.95, max_range))

    dirs = pinhole_rays(resolution, fov_deg, tilt_deg)
    n_rays = len(dirs)
    t_best = ray_plane(dirs, _UP, z0)
    owner = np.zeros(n_rays, dtype=np.int64)  # 0 ground, s + 1 solid s
    face = np.zeros(n_rays, dtype=np.int64)
    for s, solid in enumerate(solids, start=1):
        t, f = ray_convex(dirs, solid.normals, solid.offsets)
        nearer = t <= t_best  # a tie at a base edge goes to the solid
        t_best = np.where(nearer, t, t_best)
        owner = np.where(nearer, s, owner)
        face = np.where(nearer, f, face)
    ranges = t_best + rng.normal(0.0, noise, n_rays) if noise > 0 else t_best
    hit = np.isfinite(t_best) & (t_best <= max_range)
    pixel = np.flatnonzero(hit)
    xyz = dirs[hit] * ranges[hit, None]
    owner, face = owner[hit], face[hit]

    # face ids: 0 the ground, then every (solid, face) pair that was seen, in order
    max_faces = max((len(s.normals) for s in solids), default=1)
    key = np.where(owner == 0, -1, (owner - 1) * max_faces + face)
    seen, labels = np.unique(key, return_inverse=True)
    if seen[0] != -1:  # no ground point: ids still start with the ground
        seen, labels = np.concatenate([[-1], seen]), labels + 1
    faces = {0: Face(0, 0, "ground", _UP.copy(), z0)}
    for label, k in enumerate(seen[1:], start=1):
        s, f = divmod(int(k), max_faces)
        solid = solids[s]
        faces[label] = Face(label, s + 1, solid.face_names[f], solid.normals[f].copy(), float(solid.offsets[f]),
                            solid.polygon(f))
    present = set(np.unique(labels).tolist())
    faces = {k: v for k, v in faces.items() if k in present}

    names = ("ground",) + tuple(f"{s.kind} {i + 1}" for i, s in enumerate(solids[:n_boxes])) \
        + tuple(f"{s.kind} {i + 1}" for i, s in enumerate(solids[n_boxes:]))
    description = (
        f"polyhedral scene, seed {seed}: ground plane, {count(n_boxes, 'box', 'boxes')}, "
        f"{count(n_wedges, 'wedge', 'wedges')}; range sensor "
        f"{resolution[0]}x{resolution[1]} px, fov {fov_deg[0]:g}x{fov_deg[1]:g} deg, tilt {tilt_deg:g} deg, "
        f"{sensor_height:g} m above the ground, range noise {noise:g} m; sensor frame: origin at the sensor, "
        "x forward, y left, z up; label = face id (0 ground)"
    )
    return Scene(
        xyz=xyz, labels=labels, objects=owner, ground=owner == 0, kind="polyhedral", seed=seed,
        description=description, object_names=names,
        normals_by_label={k: f.normal for k, f in faces.items()}, faces=faces,
        pixel=pixel, shape=tuple(resolution), solids=tuple(solids), params=params,
    )
