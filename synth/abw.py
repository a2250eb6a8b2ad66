"""Polyhedral scenes at the ABW geometry: SegComp range images with their ground truth.

The ABW range images of Hoover et al. (1996) are 512 x 512 8-bit range values of blocks on a
table, seen by a structured-light scanner. Their calibration (:mod:`kbs.io.segcomp`) is a pinhole
camera: pixel (r, c) at range value v is the point ``d u(r, c) + (0, 0, Z)`` with
``d = v / S + O``, ``u = ((c - 255) / |F|, (255 - r) / (C |F|), -1)`` and ``Z = 255 / S + O``.
This module casts those very rays through a tilted table with boxes and wedges on it, quantises
``v = S (d - O)`` to integers as the scanner does, and labels every pixel with the planar face it
sees, so that ``kbs.io.segcomp.read_range`` turns the image back into points on those faces (up
to the quantisation) and the ground truth is exact.

>>> from kbs.synth.abw import abw_scene
>>> scene = abw_scene(seed=0)                          # doctest: +SKIP
>>> scene.save("abw.synth.0")                          # doctest: +SKIP
('abw.synth.0.range', 'abw.synth.0.gt-seg')
"""
from __future__ import annotations

import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from shapely.geometry import box as shapely_box

from kbs.errors import CloudFileError, ParameterError
from kbs.io.atomic import replacing
from kbs.inference import Interval, validate_params
from kbs.io.segcomp import (
    ABW_CALIBRATION,
    ABW_SHAPE,
    FIRST_REGION_LABEL,
    MAX_REGIONS,
    NO_REGION,
    ABWCalibration,
    write_sunraster,
)
from kbs.synth._params import check_pair, count
from kbs.synth.polyhedral import place_solids
from kbs.synth.raycast import ray_convex, ray_plane

#: Least and greatest range value with data (0 is "no data").
_V_MIN, _V_MAX = 1, 255


@dataclass(frozen=True, eq=False)
class ABWScene:
    """A synthetic ABW range image and its SegComp ground truth.

    Attributes
    ----------
    range_image : np.ndarray, shape (512, 512), uint8
        Range values v (0 = no data), as in an ``abw.*.range`` file.
    gt_image : np.ndarray, shape (512, 512), uint8
        Ground truth as in a ``.gt-seg`` file: 10 the table, 11, 12, ... the visible faces of the
        solids (consecutive); 0 for pixels without data and faces seen on fewer than
        ``min_region`` pixels.
    normals_by_label : Mapping[int, np.ndarray]
        Unit normal (3,) of each GT region, in the calibration's frame, turned towards the camera.
    seed : int
    description : str
        One ASCII line saying what the image holds.
    params : Mapping[str, Any]
        The generator's arguments.
    """

    range_image: np.ndarray
    gt_image: np.ndarray
    normals_by_label: Mapping[int, np.ndarray]
    seed: int
    description: str
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("range_image", "gt_image"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.uint8)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        for name in ("normals_by_label", "params"):
            value = getattr(self, name)
            if not isinstance(value, MappingProxyType):
                object.__setattr__(self, name, MappingProxyType(dict(value)))

    @property
    def n_regions(self) -> int:
        """Number of GT regions (labels >= 10)."""
        return int(np.unique(self.gt_image[self.gt_image >= FIRST_REGION_LABEL]).size)

    def summary(self) -> str:
        """One line: pixels with data, GT regions."""
        n_data = int(np.count_nonzero(self.range_image))
        return (f"ABW range image (seed {self.seed}): {n_data:,} pixels with data of {self.range_image.size:,}, "
                f"{count(self.n_regions, 'GT region', 'GT regions')}")

    def save(self, prefix: str | os.PathLike[str]) -> tuple[str, str]:
        """Write ``<prefix>.range`` and ``<prefix>.gt-seg`` (8-bit Sun rasterfiles, as SegComp).

        Returns
        -------
        (str, str)
            The two paths written.

        Raises
        ------
        CloudFileError
            A file cannot be written.
        """
        base = os.fspath(prefix)
        paths = (base + ".range", base + ".gt-seg")
        with replacing(*paths) as temps:  # both whole, or neither
            for path, temp, image in zip(paths, temps, (self.range_image, self.gt_image)):
                try:
                    write_sunraster(temp, image)
                except CloudFileError as exc:  # named where the user looks, not the temporary file
                    raise CloudFileError(path, exc.problem) from exc
        return paths


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _camera_rays(cal: ABWCalibration) -> np.ndarray:
    """(512 * 512, 3) ray directions u(r, c), row-major: the point at depth d is d u + camera."""
    rows, cols = ABW_SHAPE
    r, c = np.divmod(np.arange(rows * cols, dtype=np.float64), cols)
    focal = abs(cal.focal)
    return np.column_stack([(c - 255) / focal, (255 - r) / (cal.aspect * focal), -np.ones(r.size)])


def _project(P: np.ndarray, cal: ABWCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row, column and (unrounded) range value of points ``P`` (n, 3) in the calibration's frame."""
    focal = abs(cal.focal)
    camera_z = 255 / cal.scale + cal.offset
    d = camera_z - P[:, 2]
    c = 255 + focal * P[:, 0] / d
    r = 255 - cal.aspect * focal * P[:, 1] / d
    return r, c, cal.scale * (d - cal.offset)


_ABW_CONSTRAINTS = {
    "seed": [Interval(numbers.Integral, 0, None)],
    "n_boxes": [Interval(numbers.Integral, 0, None)],
    "n_wedges": [Interval(numbers.Integral, 0, None)],
    "tilt_deg": [Interval(numbers.Real, 0, 60, closed="left")],
    "table_range": [Interval(numbers.Real, 20, 250, closed="both")],
    "noise": [Interval(numbers.Real, 0, None)],
    "gap": [Interval(numbers.Real, 0, None)],
    "min_region": [Interval(numbers.Integral, 1, None)],
    "max_tries": [Interval(numbers.Integral, 1, None)],
}


def abw_scene(
    seed: int = 0,
    *,
    n_boxes: int = 3,
    n_wedges: int = 1,
    tilt_deg: float = 30.0,
    table_range: float = 180.0,
    size_range: tuple[float, float] = (45.0, 90.0),
    noise: float = 0.0,
    gap: float = 10.0,
    min_region: int = 100,
    max_tries: int = 500,
    calibration: ABWCalibration = ABW_CALIBRATION,
) -> ABWScene:
    """Boxes and wedges on a tilted table, seen through the ABW camera (512 x 512, 8-bit range).

    The table is a plane through the point of the image centre at range value ``table_range``,
    tilted ``tilt_deg`` about the image's horizontal axis (its far side at the top of the image),
    so that the solids' sides are seen as well as their tops. The solids stand on it at random
    positions and yaws, wholly in the image and between range values 5 and 250 (before
    occlusion), their footprints at least ``gap`` apart. Each pixel keeps its nearest hit; its
    range value is ``rint(S (d - O) + noise * N(0, 1))``, and 0 (no data) outside [1, 255].

    Parameters
    ----------
    seed : int
        Seed of the numpy Generator that places the solids and draws the noise.
    n_boxes, n_wedges : int
        Number of boxes and wedges (as :func:`kbs.synth.polyhedral_scene`).
    tilt_deg : float
        Tilt of the table from fronto-parallel, degrees, in [0, 60).
    table_range : float
        Range value of the table at the image centre, in [20, 250].
    size_range : (float, float)
        Each side of a solid is uniform in this range, in the calibration's units (about 0.59 per
        column at mid range: the default solids span 75 to 150 columns).
    noise : float
        Standard deviation of the range noise, in range levels, added before rounding.
    gap : float
        Least distance between two solids' footprints, calibration units.
    min_region : int
        A face seen on fewer pixels is no GT region (its pixels are 0, as a region too small to
        label).
    max_tries : int
        Random placements tried per solid before giving up.
    calibration : ABWCalibration
        The camera (default: the standard ABW calibration, the one ``kbs run`` uses for a file not
        named ``abw.test.N.range`` with N in 0, 19, 21, 25, 27, 28, 29).

    Returns
    -------
    ABWScene

    Raises
    ------
    ParameterError
        A parameter out of range, or solids that do not fit in the image.
    """
    params = dict(seed=seed, n_boxes=n_boxes, n_wedges=n_wedges, tilt_deg=tilt_deg, table_range=table_range,
                  size_range=size_range, noise=noise, gap=gap, min_region=min_region, max_tries=max_tries)
    validate_params("abw_scene", {k: v for k, v in params.items() if k != "size_range"}, _ABW_CONSTRAINTS)
    size_range = check_pair("abw_scene", "size_range", size_range, numbers.Real, 0, None)
    if size_range[0] > size_range[1]:
        raise ParameterError(f"The 'size_range' parameter of abw_scene must be (low, high) with "
                             f"low <= high. Got {size_range!r} instead.")
    if not isinstance(calibration, ABWCalibration):
        raise ParameterError(f"The 'calibration' parameter of abw_scene must be an ABWCalibration. "
                             f"Got {calibration!r} instead.")
    cal = calibration
    rng = np.random.default_rng(seed)
    camera = np.array([0.0, 0.0, 255 / cal.scale + cal.offset])
    # the table's frame: origin where the central ray meets range value table_range, z its normal
    origin = np.array([0.0, 0.0, (255 - table_range) / cal.scale])
    R = _rotation_x(-np.radians(tilt_deg))  # the far side at the top of the image

    def to_camera_frame(X: np.ndarray) -> np.ndarray:
        return X @ R.T + origin

    def in_view(V: np.ndarray) -> bool:
        r, c, v = _project(to_camera_frame(V), cal)
        return bool((r >= 16).all() and (r <= 495).all() and (c >= 16).all() and (c <= 495).all()
                    and (v >= 5).all() and (v <= 250).all())

    # where a solid's centre may go: the part of the table the image sees (a generous box; the
    # in_view test decides)
    half_w = 255 * (cal.offset + table_range / cal.scale) / abs(cal.focal)
    region = shapely_box(-half_w, -half_w / cal.aspect, half_w, half_w / cal.aspect)
    kinds = ["box"] * n_boxes + ["wedge"] * n_wedges
    local = place_solids(rng, kinds, region, size_range, gap, 0.0, max_tries, in_view)

    # cast the rays from the camera (ray_convex / ray_plane take the ray origin as 0)
    dirs = _camera_rays(cal)
    shift = origin - camera
    up = R @ np.array([0.0, 0.0, 1.0])
    t_best = ray_plane(dirs, -up, -(up @ shift))  # the table, seen from the camera's side
    owner = np.zeros(len(dirs), dtype=np.int64)
    face = np.zeros(len(dirs), dtype=np.int64)
    face_normals: list[np.ndarray] = []
    for s, solid in enumerate(local, start=1):
        normals = solid.normals @ R.T
        offsets = solid.offsets + normals @ shift
        face_normals.append(normals)
        t, f = ray_convex(dirs, normals, offsets)
        nearer = t <= t_best
        t_best = np.where(nearer, t, t_best)
        owner = np.where(nearer, s, owner)
        face = np.where(nearer, f, face)
    v = cal.scale * (t_best - cal.offset)
    if noise > 0:
        v = v + rng.normal(0.0, noise, v.size)
    v = np.where(np.isfinite(v), np.rint(v), 0)
    data = (v >= _V_MIN) & (v <= _V_MAX)
    range_image = np.where(data, v, 0).astype(np.uint8).reshape(ABW_SHAPE)

    # GT: the table 10, then each (solid, face) seen on >= min_region pixels, in order
    max_faces = max((len(n) for n in face_normals), default=1)
    key = np.where(owner == 0, -1, (owner - 1) * max_faces + face)
    key = np.where(data, key, -2)
    keys, sizes = np.unique(key[data], return_counts=True)
    keep = keys[sizes >= min_region]
    if keep.size > MAX_REGIONS:  # pragma: no cover - needs dozens of solids
        raise ParameterError(f"abw_scene: {keep.size} faces are more than the {MAX_REGIONS} regions of a "
                             "SegComp image; ask for fewer solids")
    gt = np.full(key.size, NO_REGION, dtype=np.uint8)
    normals_by_label: dict[int, np.ndarray] = {}
    for i, k in enumerate(keep):
        label = FIRST_REGION_LABEL + i
        gt[key == k] = label
        if k == -1:
            normal = up.copy()
        else:
            s, f = divmod(int(k), max_faces)
            normal = face_normals[s][f].copy()
        normals_by_label[label] = normal
    gt_image = gt.reshape(ABW_SHAPE)

    description = (
        f"ABW-geometry range image, seed {seed}: a table tilted {tilt_deg:g} deg at range value "
        f"{table_range:g}, {count(n_boxes, 'box', 'boxes')}, {count(n_wedges, 'wedge', 'wedges')}; "
        f"512x512 8-bit range values (ABW calibration O={cal.offset:g} S={cal.scale:g}), range noise "
        f"{noise:g} levels; GT: 10 the table, 11.. the faces of at least {min_region} pixels"
    )
    return ABWScene(range_image=range_image, gt_image=gt_image, normals_by_label=normals_by_label, seed=seed,
                    description=description, params=params)
