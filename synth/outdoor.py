"""Outdoor scenes seen by a stereo-like sensor: uneven ground, partly buried rocks and a bin.

As a stereo rig on a rover sees them (the seed paper's outdoor-navigation set-up): one ray per
pixel of a camera looking ahead and slightly down, the nearest surface hit (occlusion), matches
that get rarer with range and depth noise that grows with the square of the range.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from kbs.errors import ParameterError
from kbs.inference import Interval, validate_params
from kbs.synth._params import check_pair, count
from kbs.synth.raycast import (
    HeightField,
    pinhole_rays,
    ray_ellipsoid,
    ray_heightfield,
    ray_rectangle,
    sphere_candidates,
)
from kbs.synth.scene import Scene


@dataclass(frozen=True, eq=False)
class Rock:
    """An irregular rock: the union of a few ellipsoids (lobes), partly below the ground.

    Attributes
    ----------
    centers : np.ndarray, shape (k, 3)
    axes : np.ndarray, shape (k, 3, 3)
        Per lobe, its principal axes as rows.
    radii : np.ndarray, shape (k, 3)
    """

    centers: np.ndarray
    axes: np.ndarray
    radii: np.ndarray

    def cast(self, dirs: np.ndarray) -> np.ndarray:
        """Distance to the rock along each ray, ``inf`` for a miss."""
        t = np.full(len(dirs), np.inf)
        for c, ax, r in zip(self.centers, self.axes, self.radii):
            idx = sphere_candidates(dirs, c, float(r.max()))
            t[idx] = np.minimum(t[idx], ray_ellipsoid(dirs[idx], c, ax, r))
        return t

    def inside(self, X: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Whether points ``X`` (n, 3) are inside a lobe (scaled by ``1 + tol``)."""
        out = np.zeros(len(X), dtype=bool)
        for c, ax, r in zip(self.centers, self.axes, self.radii):
            q = ((X - c) @ ax.T) / r
            out |= np.einsum("ij,ij->i", q, q) <= (1.0 + tol) ** 2
        return out


@dataclass(frozen=True, eq=False)
class Bin:
    """An open box: four vertical walls of zero thickness and a floor, no lid.

    Attributes
    ----------
    center : np.ndarray, shape (2,)
    yaw : float
    size : (float, float, float)
        Length, width, height (above the ground at its centre).
    base : float
        Height of the walls' bottom (a little below the ground everywhere under the bin).
    floor : float
        Height of the floor (a little above the ground everywhere under the bin).
    top : float
        Height of the walls' top.
    """

    center: np.ndarray
    yaw: float
    size: tuple[float, float, float]
    base: float
    floor: float
    top: float

    def rectangles(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float]]:
        """``(center, axis_u, axis_v, half_u, half_v)`` of the four walls and the floor."""
        a = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        b = np.array([-np.sin(self.yaw), np.cos(self.yaw), 0.0])
        z = np.array([0.0, 0.0, 1.0])
        length, width, _ = self.size
        c = np.array([self.center[0], self.center[1], 0.0])
        mid, half_h = (self.base + self.top) / 2, (self.top - self.base) / 2
        rects = []
        for axis, other, half_other, half_along in ((a, b, width / 2, length / 2), (b, a, length / 2, width / 2)):
            for sign in (-1.0, 1.0):
                rects.append((c + sign * half_along * axis + mid * z, other, z, half_other, half_h))
        rects.append((c + self.floor * z, a, b, length / 2, width / 2))
        return rects

    def cast(self, dirs: np.ndarray) -> np.ndarray:
        """Distance to the bin along each ray, ``inf`` for a miss."""
        t = np.full(len(dirs), np.inf)
        length, width, _ = self.size
        centre = np.array([self.center[0], self.center[1], (self.base + self.top) / 2])
        idx = sphere_candidates(dirs, centre, float(np.linalg.norm([length, width, self.top - self.base])) / 2)
        sub = dirs[idx]
        for rect in self.rectangles():
            t[idx] = np.minimum(t[idx], ray_rectangle(sub, *rect))
        return t


def random_terrain(rng: np.random.Generator, sensor_height: float, amplitude: float, n_waves: int = 5) -> HeightField:
    """A smooth random terrain: ``n_waves`` sinusoids of wavelengths 6-30 m, heights within
    ``+- amplitude`` of ``-sensor_height``."""
    wavelength = rng.uniform(6.0, 30.0, n_waves)
    direction = rng.uniform(0.0, 2 * np.pi, n_waves)
    k = (2 * np.pi / wavelength)[:, None] * np.column_stack([np.cos(direction), np.sin(direction)])
    weights = rng.uniform(0.3, 1.0, n_waves)
    return HeightField(base=-float(sensor_height), amplitudes=amplitude * weights / weights.sum(),
                       wavevectors=k, phases=rng.uniform(0.0, 2 * np.pi, n_waves))


def random_rock(
    rng: np.random.Generator, center_xy: np.ndarray, size_range: tuple[float, float], terrain: HeightField
) -> tuple[Rock, float]:
    """A rock of 1-3 lobes at ``center_xy``, its main lobe 35-65 % buried; returns it and the
    radius of a circle holding its footprint."""
    main = np.array([rng.uniform(*size_range), rng.uniform(*size_range), 0.0])
    main[2] = rng.uniform(0.5, 0.9) * main[:2].max()
    ground = float(terrain(center_xy[0], center_xy[1]))
    centers = [np.array([center_xy[0], center_xy[1], ground + main[2] * rng.uniform(-0.3, 0.3)])]
    radii = [main]
    for _ in range(rng.integers(0, 3)):  # 0-2 extra lobes
        offset = np.array([*rng.uniform(-0.6, 0.6, 2) * main[:2], rng.uniform(-0.2, 0.2) * main[2]])
        centers.append(centers[0] + offset)
        radii.append(main * rng.uniform(0.5, 0.8, 3))
    axes = [Rotation.from_euler("zyx", [rng.uniform(0, 2 * np.pi), *rng.uniform(-0.25, 0.25, 2)]).as_matrix().T
            for _ in centers]
    centers, radii = np.array(centers), np.array(radii)
    reach = float((np.linalg.norm(centers[:, :2] - center_xy, axis=1) + radii.max(axis=1)).max())
    return Rock(centers, np.array(axes), radii), reach


def random_bin(
    rng: np.random.Generator, center_xy: np.ndarray, size: tuple[float, float, float], terrain: HeightField
) -> tuple[Bin, float]:
    """A bin at ``center_xy`` with a random yaw; returns it and the radius of its footprint circle."""
    yaw = rng.uniform(0.0, np.pi / 2)
    length, width, height = size
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, 7), np.linspace(-0.5, 0.5, 7))
    x = center_xy[0] + length * u * np.cos(yaw) - width * v * np.sin(yaw)
    y = center_xy[1] + length * u * np.sin(yaw) + width * v * np.cos(yaw)
    g = terrain(x, y)
    ground = float(terrain(center_xy[0], center_xy[1]))
    slack = 0.02 + terrain.max_slope * 0.1  # the ground between samples is no higher than this
    b = Bin(np.asarray(center_xy, dtype=float), float(yaw), (length, width, height),
            base=float(g.min()) - 0.05, floor=float(g.max()) + slack, top=ground + height)
    return b, float(np.hypot(length, width) / 2)


#: The settings of outdoor_scene and their allowed values (outdoor_drive checks the same ones).
OUTDOOR_CONSTRAINTS = {
    "seed": [Interval(numbers.Integral, 0, None)],
    "extent": [Interval(numbers.Real, 5, None)],
    "n_rocks": [Interval(numbers.Integral, 0, None)],
    "noise": [Interval(numbers.Real, 0, None)],
    "sensor_height": [Interval(numbers.Real, 0, None, closed="neither")],
    "tilt_deg": [Interval(numbers.Real, -90, 90, closed="both")],
    "density_r0": [Interval(numbers.Real, 0, None, closed="neither")],
    "ground_amplitude": [Interval(numbers.Real, 0, None)],
    "gap": [Interval(numbers.Real, 0, None)],
    "max_tries": [Interval(numbers.Integral, 1, None)],
}


def outdoor_scene(
    seed: int = 0,
    *,
    extent: float = 25.0,
    n_rocks: int = 3,
    with_bin: bool = True,
    resolution: tuple[int, int] = (360, 640),
    fov_deg: tuple[float, float] = (45.0, 90.0),
    tilt_deg: float = 18.0,
    sensor_height: float = 1.5,
    noise: float = 5e-4,
    density_r0: float = 6.0,
    ground_amplitude: float = 0.15,
    rock_size: tuple[float, float] = (0.3, 0.8),
    bin_size: tuple[float, float, float] = (0.6, 0.6, 1.0),
    gap: float = 0.5,
    max_tries: int = 500,
) -> Scene:
    """Uneven ground, rocks and a bin seen by a stereo-like sensor at the origin.

    The terrain is a sum of five sinusoids (wavelengths 6-30 m) within ``ground_amplitude`` of
    ``z = -sensor_height``. Rocks are unions of one to three ellipsoids, the main one 35-65 %
    buried; the bin is an open box (four walls and a floor) standing on the ground. Objects are
    placed 3.5 m to ``0.6 extent`` ahead, inside the central part of the view, at least ``gap``
    apart. One ray per pixel (through a random position inside it) keeps its nearest hit,
    within ``extent``; as stereo matching gets rarer with range, a hit at range ``r`` is kept
    with probability ``min(1, (density_r0 / r)^2)`` (on top of the pixel footprint growing with
    range), and the range gets Gaussian noise of standard deviation ``noise * r^2``.

    Parameters
    ----------
    seed : int
        Seed of the numpy Generator behind the terrain, the objects, the rays and the noise.
    extent : float
        Farthest range measured, metres (at least 5).
    n_rocks : int
    with_bin : bool
    resolution : (int, int)
        ``(rows, cols)`` of the camera.
    fov_deg : (float, float)
        Vertical and horizontal fields of view, degrees.
    tilt_deg : float
        Depression of the optical axis, degrees.
    sensor_height : float
        Height of the sensor above the terrain's mean level, metres.
    noise : float
        Range noise coefficient, 1/m: standard deviation ``noise * r^2`` at range ``r``.
    density_r0 : float
        Range up to which every hit is kept, metres.
    ground_amplitude : float
        Largest departure of the terrain from its mean level, metres (< sensor_height).
    rock_size : (float, float)
        Range of a rock's horizontal semi-axes, metres.
    bin_size : (float, float, float)
        Length, width and height of the bin, metres.
    gap : float
        Least distance between two objects' footprint circles, metres.
    max_tries : int
        Random placements tried per object before giving up.

    Returns
    -------
    Scene
        ``labels`` and ``objects``: 0 the ground, 1..n_rocks the rocks, n_rocks + 1 the bin;
        ``ground`` is ``labels == 0``; ``terrain`` the height field; ``pixel`` and ``shape``.

    Raises
    ------
    ParameterError
        A parameter out of range, or objects that do not fit in the view.
    """
    params = dict(seed=seed, extent=extent, n_rocks=n_rocks, with_bin=with_bin, resolution=resolution,
                  fov_deg=fov_deg, tilt_deg=tilt_deg, sensor_height=sensor_height, noise=noise,
                  density_r0=density_r0, ground_amplitude=ground_amplitude, rock_size=rock_size,
                  bin_size=bin_size, gap=gap, max_tries=max_tries)
    validate_params("outdoor_scene", params, OUTDOOR_CONSTRAINTS)
    resolution = check_pair("outdoor_scene", "resolution", resolution, numbers.Integral, 0, None)
    fov_deg = check_pair("outdoor_scene", "fov_deg", fov_deg, numbers.Real, 0, 180)
    rock_size = check_pair("outdoor_scene", "rock_size", rock_size, numbers.Real, 0, None)
    if rock_size[0] > rock_size[1]:
        raise ParameterError(f"The 'rock_size' parameter of outdoor_scene must be (low, high) with low <= high. "
                             f"Got {rock_size!r} instead.")
    try:
        bin_size = tuple(float(v) for v in bin_size)
    except (TypeError, ValueError):
        bin_size = ()
    if len(bin_size) != 3 or not all(v > 0 and np.isfinite(v) for v in bin_size):
        raise ParameterError("The 'bin_size' parameter of outdoor_scene must be three positive floats "
                             f"(length, width, height). Got {params['bin_size']!r} instead.")
    if ground_amplitude >= sensor_height:
        raise ParameterError(f"The 'ground_amplitude' parameter of outdoor_scene must be below sensor_height "
                             f"({sensor_height:g}). Got {ground_amplitude!r} instead.")
    rng = np.random.default_rng(seed)
    terrain = random_terrain(rng, sensor_height, ground_amplitude)

    # objects: rocks then the bin, footprint circles apart
    near, far = 3.5, max(3.5, 0.6 * extent)
    half_azimuth = np.radians(fov_deg[1]) / 2 * 0.7
    placed: list[tuple[np.ndarray, float]] = []
    rocks: list[Rock] = []
    bin_: Bin | None = None
    for i in range(n_rocks + int(with_bin)):
        is_bin = i == n_rocks
        for _ in range(max_tries):
            r, az = rng.uniform(near, far), rng.uniform(-half_azimuth, half_azimuth)
            xy = np.array([r * np.cos(az), r * np.sin(az)])
            obj, reach = random_bin(rng, xy, bin_size, terrain) if is_bin else random_rock(rng, xy, rock_size, terrain)
            if all(np.linalg.norm(xy - c) >= reach + rc + gap for c, rc in placed):
                placed.append((xy, reach))
                if is_bin:
                    bin_ = obj
                else:
                    rocks.append(obj)
                break
        else:
            raise ParameterError(
                f"outdoor_scene could not place {'the bin' if is_bin else f'rock {i + 1}'} without touching "
                f"the other objects after {max_tries} tries; ask for fewer or smaller objects, or a larger extent"
            )

    dirs = pinhole_rays(resolution, fov_deg, tilt_deg, rng=rng)
    n_rays = len(dirs)
    t_best = ray_heightfield(dirs, terrain, extent)
    owner = np.zeros(n_rays, dtype=np.int64)
    solids = [rock.cast for rock in rocks] + ([bin_.cast] if bin_ is not None else [])
    for k, cast in enumerate(solids, start=1):
        t = cast(dirs)
        nearer = t < t_best
        t_best = np.where(nearer, t, t_best)
        owner = np.where(nearer, k, owner)
    keep_draw = rng.uniform(size=n_rays)
    noise_draw = rng.normal(size=n_rays)
    hit = t_best <= extent
    with np.errstate(divide="ignore"):
        keep_probability = np.minimum(1.0, (density_r0 / t_best) ** 2)
    hit &= keep_draw < keep_probability
    ranges = t_best[hit] * (1.0 + noise * t_best[hit] * noise_draw[hit])  # sigma = noise r^2
    xyz = dirs[hit] * ranges[:, None]
    owner = owner[hit]

    names = ("ground",) + tuple(f"rock {i}" for i in range(1, len(rocks) + 1)) + (("bin",) if bin_ else ())
    description = (
        f"outdoor scene, seed {seed}: uneven ground (+-{ground_amplitude:g} m), "
        f"{count(len(rocks), 'rock', 'rocks')}"
        f"{', a bin' if bin_ else ''}; stereo-like camera {resolution[0]}x{resolution[1]} px, fov "
        f"{fov_deg[0]:g}x{fov_deg[1]:g} deg, tilt {tilt_deg:g} deg, {sensor_height:g} m above the ground, "
        f"range <= {extent:g} m, density (r0/r)^2 with r0 {density_r0:g} m, range noise {noise:g} r^2; "
        "sensor frame: origin at the sensor, x forward, y left, z up; label 0 ground, 1.."
        f"{len(rocks)} rocks" + (f", {len(rocks) + 1} bin" if bin_ else "")
    )
    return Scene(
        xyz=xyz, labels=owner, objects=owner, ground=owner == 0, kind="outdoor", seed=seed,
        description=description, object_names=names, pixel=np.flatnonzero(hit), shape=tuple(resolution),
        terrain=terrain, solids=tuple(rocks) + ((bin_,) if bin_ is not None else ()), params=params,
    )
