"""A drive through one outdoor scene: the stereo-like sensor of :func:`outdoor_scene` carried along
an arc over one generated terrain with rocks and a bin, one ray-cast frame per pose, with the
per-point ground truth, the true poses and the true obstacle layout (to score a map against).

The world frame is the first pose's sensor frame projected on the horizontal: origin below... at
the first sensor position, x its forward direction, z up. The sensor stays level (yaw only) at
``sensor_height`` above the terrain under it; its path is an arc of constant curvature
(``yaw_rate`` degrees per frame, ``step`` metres between frames). Each frame is in its own
sensor frame (as a scanner writes it), like :func:`outdoor_scene`'s scene.
"""
from __future__ import annotations

import json
import numbers
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import CloudFileError, ParameterError
from kbs.inference import Interval, validate_params
from kbs.synth._params import check_pair, count
from kbs.synth.outdoor import OUTDOOR_CONSTRAINTS, Bin, Rock, random_bin, random_rock, random_terrain
from kbs.synth.raycast import HeightField, pinhole_rays, ray_convex, ray_heightfield, sphere_candidates
from kbs.synth.scene import Scene

#: Format of ``truth.json``.
TRUTH_VERSION = 1


def _rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def arc(s: np.ndarray | float, yaw_rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y and heading (rad) at arc length ``s`` along an arc from the origin heading +x that
    turns ``yaw_rate`` radians per metre (left for positive)."""
    s = np.asarray(s, dtype=np.float64)
    if abs(yaw_rate) < 1e-12:
        return s.copy(), np.zeros_like(s), np.zeros_like(s)
    return np.sin(yaw_rate * s) / yaw_rate, (1.0 - np.cos(yaw_rate * s)) / yaw_rate, yaw_rate * s


@dataclass(frozen=True, eq=False)
class Prism:
    """A vertical convex prism: a building's block, a pole, a tree's trunk.

    Attributes
    ----------
    footprint : np.ndarray, shape (k, 2)
        Its convex footprint, counter-clockwise (world or sensor frame).
    base, top : float
        Heights of its bottom (below the terrain under it) and of its top.
    """

    footprint: np.ndarray
    base: float
    top: float

    def _halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(self.footprint, dtype=np.float64)
        e = np.roll(p, -1, axis=0) - p
        n = np.column_stack([e[:, 1], -e[:, 0]]) / np.linalg.norm(e, axis=1)[:, None]  # outward (CCW)
        normals = np.vstack([np.column_stack([n, np.zeros(len(n))]), [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
        offsets = np.concatenate([(n * p).sum(axis=1), [self.top, -self.base]])
        return normals, offsets

    def cast(self, dirs: np.ndarray) -> np.ndarray:
        """Distance to the prism along each ray, ``inf`` for a miss."""
        t = np.full(len(dirs), np.inf)
        p = np.asarray(self.footprint, dtype=np.float64)
        c2 = p.mean(axis=0)
        centre = np.array([c2[0], c2[1], (self.base + self.top) / 2])
        radius = float(np.hypot(np.linalg.norm(p - c2, axis=1).max(), (self.top - self.base) / 2))
        idx = sphere_candidates(dirs, centre, radius)
        if idx.size:
            t[idx] = ray_convex(dirs[idx], *self._halfspaces())[0]
        return t

    def top_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of its top at ``(x, y)``, ``-inf`` outside its footprint."""
        normals, offsets = self._halfspaces()
        inside = np.ones(np.shape(x), dtype=bool)
        for nv, d in zip(normals[:-2], offsets[:-2]):
            inside &= nv[0] * x + nv[1] * y <= d
        return np.where(inside, self.top, -np.inf)

    def moved(self, R: np.ndarray, t: np.ndarray) -> Prism:
        """Expressed in the frame of the pose ``(R, t)`` (yaw-only rotation)."""
        return Prism((np.asarray(self.footprint) - t[:2]) @ R[:2, :2], self.base - t[2], self.top - t[2])


@dataclass(frozen=True, eq=False)
class Tree:
    """A tree: a trunk (an octagonal :class:`Prism`) under an ellipsoidal crown (a one-lobe
    :class:`~kbs.synth.outdoor.Rock`)."""

    trunk: Prism
    crown: Rock

    def cast(self, dirs: np.ndarray) -> np.ndarray:
        return np.minimum(self.trunk.cast(dirs), self.crown.cast(dirs))

    def top_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.maximum(self.trunk.top_at(x, y), _rock_top(self.crown, x, y))

    def moved(self, R: np.ndarray, t: np.ndarray) -> Tree:
        return Tree(self.trunk.moved(R, t), Rock((self.crown.centers - t) @ R, self.crown.axes @ R, self.crown.radii))


def _rock_top(s: Rock, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the top of a rock's lobes at ``(x, y)``, ``-inf`` outside them."""
    top = np.full(np.shape(x), -np.inf)
    for c, ax, r in zip(s.centers, s.axes, s.radii):
        # q = ax (p - c) / r; |q|^2 <= 1 is quadratic in z
        A = ax / r[:, None]  # rows scaled
        d = np.stack([x - c[0], y - c[1], np.zeros_like(x)], axis=-1) @ A.T  # (..., 3) at z = c_z
        a = float(A[:, 2] @ A[:, 2])
        b = 2.0 * (d @ A[:, 2])
        cc = (d * d).sum(-1) - 1.0
        disc = b * b - 4 * a * cc
        with np.errstate(invalid="ignore"):
            zt = c[2] + (-b + np.sqrt(disc)) / (2 * a)
        top = np.where(disc >= 0, np.maximum(top, zt), top)
    return top


def _octagon(center: np.ndarray, radius: float) -> np.ndarray:
    a = (np.arange(8) + 0.5) * np.pi / 4
    return np.column_stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)])


def _in_sensor_frame(obj: Any, T: np.ndarray) -> Any:
    """A rock, bin or terrain expressed in the frame of pose ``T`` (yaw-only rotation)."""
    R, t = T[:3, :3], T[:3, 3]
    if isinstance(obj, HeightField):
        R2 = R[:2, :2]
        return HeightField(base=obj.base - t[2], amplitudes=obj.amplitudes, wavevectors=obj.wavevectors @ R2,
                           phases=obj.phases + obj.wavevectors @ t[:2])
    if isinstance(obj, Rock):
        return Rock((obj.centers - t) @ R, obj.axes @ R, obj.radii)
    if isinstance(obj, (Prism, Tree)):
        return obj.moved(R, t)
    c = (np.array([obj.center[0], obj.center[1], 0.0]) - np.array([t[0], t[1], 0.0])) @ R
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return replace(obj, center=c[:2], yaw=obj.yaw - yaw, base=obj.base - t[2], floor=obj.floor - t[2],
                   top=obj.top - t[2])


@dataclass(frozen=True, eq=False)
class DriveTruth:
    """The true layout of a drive's scene: terrain, obstacles and poses (world frame).

    Attributes
    ----------
    terrain : HeightField
    solids : tuple of Rock and Bin
        ``solids[i - 1]`` is object id ``i``.
    object_names : tuple of str
        ``object_names[0] == "ground"``.
    poses : np.ndarray (n_frames, 4, 4)
        The true sensor-to-world transforms.
    """

    terrain: HeightField
    solids: tuple[Any, ...]
    object_names: tuple[str, ...]
    poses: np.ndarray

    def exposed_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the obstacles above the terrain at world ``(x, y)`` (0 where none)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        g = self.terrain(x, y)
        top = np.full(x.shape, -np.inf)
        for s in self.solids:
            if isinstance(s, Rock):
                top = np.maximum(top, _rock_top(s, x, y))
            elif isinstance(s, (Prism, Tree)):
                top = np.maximum(top, s.top_at(x, y))
            else:  # a bin: its footprint rectangle, up to its top
                ca, sa = np.cos(s.yaw), np.sin(s.yaw)
                u = (x - s.center[0]) * ca + (y - s.center[1]) * sa
                v = -(x - s.center[0]) * sa + (y - s.center[1]) * ca
                inside = (np.abs(u) <= s.size[0] / 2) & (np.abs(v) <= s.size[1] / 2)
                top = np.where(inside, np.maximum(top, s.top), top)
        return np.maximum(top - g, 0.0)

    def object_at(self, x: np.ndarray, y: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
        """The true object id at world ``(x, y)`` (0: none): the obstacle standing above the terrain
        there, or within ``tolerance`` metres of it (the nearest, checked on 8 directions)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        out = np.zeros(x.shape, dtype=np.int64)
        offsets = [(0.0, 0.0)] + ([(tolerance * np.cos(a), tolerance * np.sin(a))
                                   for a in np.arange(8) * np.pi / 4] if tolerance > 0 else [])
        for dx, dy in offsets:
            for i, s in enumerate(self.solids, start=1):
                free = out == 0
                if not free.any():
                    break
                one = DriveTruth(self.terrain, (s,), self.object_names, self.poses)
                out[free & (one.exposed_height(x + dx, y + dy) > 0)] = i
        return out

    def obstacle_fraction(self, origin: tuple[float, float], cell_size: float, shape: tuple[int, int], *,
                          min_height: float = 0.05, subsamples: int = 4) -> np.ndarray:
        """Fraction of each cell (axes ix, iy, as :class:`kbs.maps.grid.GridMap`) where an obstacle
        stands more than ``min_height`` above the terrain (``subsamples^2`` points per cell)."""
        nx, ny = shape
        off = (np.arange(subsamples) + 0.5) / subsamples
        xs = origin[0] + (np.arange(nx)[:, None] + off[None, :]).ravel() * cell_size
        ys = origin[1] + (np.arange(ny)[:, None] + off[None, :]).ravel() * cell_size
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        h = self.exposed_height(X, Y) > min_height
        return h.reshape(nx, subsamples, ny, subsamples).mean(axis=(1, 3))

    def overhang_fraction(self, origin: tuple[float, float], cell_size: float, shape: tuple[int, int], *,
                          subsamples: int = 4) -> np.ndarray:
        """Fraction of each cell (as :meth:`obstacle_fraction`) under a tree's crown and under no
        trunk nor other solid: free at the ground, an obstacle from above; a map is right either
        way there (:func:`kbs.maps.score.score_grid` leaves these cells out)."""
        nx, ny = shape
        off = (np.arange(subsamples) + 0.5) / subsamples
        xs = origin[0] + (np.arange(nx)[:, None] + off[None, :]).ravel() * cell_size
        ys = origin[1] + (np.arange(ny)[:, None] + off[None, :]).ravel() * cell_size
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        crown = np.zeros(X.shape, dtype=bool)
        standing = np.zeros(X.shape, dtype=bool)
        for s in self.solids:
            if isinstance(s, Tree):
                crown |= np.isfinite(_rock_top(s.crown, X, Y))
                standing |= np.isfinite(s.trunk.top_at(X, Y))
            else:
                standing |= DriveTruth(self.terrain, (s,), self.object_names, self.poses).exposed_height(X, Y) > 0
        return (crown & ~standing).reshape(nx, subsamples, ny, subsamples).mean(axis=(1, 3))

    def to_dict(self) -> dict[str, Any]:
        t = self.terrain
        objs = []
        for i, s in enumerate(self.solids, start=1):
            if isinstance(s, Rock):
                objs.append({"id": i, "name": self.object_names[i], "kind": "rock", "centers": s.centers.tolist(),
                             "axes": s.axes.tolist(), "radii": s.radii.tolist()})
            elif isinstance(s, Prism):
                objs.append({"id": i, "name": self.object_names[i], "kind": "prism",
                             "footprint": np.asarray(s.footprint).tolist(), "base": s.base, "top": s.top})
            elif isinstance(s, Tree):
                objs.append({"id": i, "name": self.object_names[i], "kind": "tree",
                             "footprint": np.asarray(s.trunk.footprint).tolist(), "base": s.trunk.base,
                             "top": s.trunk.top, "centers": s.crown.centers.tolist(), "axes": s.crown.axes.tolist(),
                             "radii": s.crown.radii.tolist()})
            else:
                objs.append({"id": i, "name": self.object_names[i], "kind": "bin", "center": list(map(float, s.center)),
                             "yaw": s.yaw, "size": list(s.size), "base": s.base, "floor": s.floor, "top": s.top})
        return {"kbs_drive_truth": TRUTH_VERSION,
                "terrain": {"base": t.base, "amplitudes": t.amplitudes.tolist(), "wavevectors": t.wavevectors.tolist(),
                            "phases": t.phases.tolist()},
                "objects": objs, "poses": self.poses.tolist()}

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> DriveTruth:
        t = doc["terrain"]
        terrain = HeightField(float(t["base"]), np.array(t["amplitudes"]), np.array(t["wavevectors"]),
                              np.array(t["phases"]))
        solids, names = [], ["ground"]
        for o in doc["objects"]:
            names.append(o["name"])
            if o["kind"] == "rock":
                solids.append(Rock(np.array(o["centers"]), np.array(o["axes"]), np.array(o["radii"])))
            elif o["kind"] == "prism":
                solids.append(Prism(np.array(o["footprint"], dtype=np.float64), float(o["base"]), float(o["top"])))
            elif o["kind"] == "tree":
                solids.append(Tree(Prism(np.array(o["footprint"], dtype=np.float64), float(o["base"]), float(o["top"])),
                                   Rock(np.array(o["centers"]), np.array(o["axes"]), np.array(o["radii"]))))
            else:
                solids.append(Bin(np.array(o["center"]), float(o["yaw"]), tuple(o["size"]), float(o["base"]),
                                  float(o["floor"]), float(o["top"])))
        return cls(terrain, tuple(solids), tuple(names), np.array(doc["poses"], dtype=np.float64))


def read_truth(path: str | os.PathLike[str]) -> DriveTruth:
    """Read the ``truth.json`` a drive was saved with.

    Raises
    ------
    CloudFileError
        Missing, not JSON, or not a kbs drive truth file.
    """
    try:
        doc = json.loads(Path(path).read_text())
        if doc.get("kbs_drive_truth") != TRUTH_VERSION:
            raise KeyError("kbs_drive_truth")
        return DriveTruth.from_dict(doc)
    except FileNotFoundError as exc:
        raise CloudFileError(os.fspath(path), "no such file") from exc
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CloudFileError(os.fspath(path), f"not a kbs drive truth file ({type(exc).__name__}: {exc})") from exc


@dataclass(frozen=True, eq=False)
class DriveScene:
    """A generated drive: one :class:`Scene` per frame (sensor frame; ``objects`` ids are the
    drive's, the same object keeps its id in every frame) and the :class:`DriveTruth`."""

    frames: tuple[Scene, ...]
    truth: DriveTruth
    description: str
    params: dict[str, Any]

    @property
    def poses(self) -> np.ndarray:
        return self.truth.poses

    def summary(self) -> str:
        n = sum(len(f) for f in self.frames)
        seen = set().union(*(set(np.unique(f.objects).tolist()) for f in self.frames)) - {0}
        return (f"outdoor drive (seed {self.params['seed']}): {count(len(self.frames), 'frame', 'frames')}, "
                f"{n:,} points, {count(len(seen), 'object', 'objects')} seen of {len(self.truth.solids)}, "
                f"path {self.params['step'] * (len(self.frames) - 1):g} m")

    def save(self, directory: str | os.PathLike[str], *, force: bool = False) -> None:
        """Write ``DIR/scans/NNNNNN.ply`` (each frame as :meth:`Scene.save`), ``DIR/poses.txt``
        (KITTI format: the 3x4 of each sensor-to-world pose; they are LiDAR poses, there is no
        calib.txt) and ``DIR/truth.json`` (the layout and the poses), each whole or not at all.
        One run id marks them as kbs's: in each frame's PLY header and in ``truth.json``, which also
        holds the SHA-256 of ``poses.txt`` (a format with no room for it: :func:`kbs.io.result.listed_by_index`).
        Frames of an earlier, longer drive in ``DIR/scans`` (:func:`stale_frames`) are removed when kbs
        wrote them, or with ``force``: left, they would be read as frames of this drive.

        Raises
        ------
        CloudFileError
            The folder cannot be written.
        """
        from kbs import __version__
        from kbs.io.atomic import replacing
        from kbs.io.result import file_digest, is_kbs_output, new_run_id
        from kbs.maps.poses import write_kitti_poses

        d = Path(directory)
        run_id = new_run_id()
        try:
            (d / "scans").mkdir(parents=True, exist_ok=True)
            for path, f in zip(drive_files(d, len(self.frames))[0], self.frames):
                f.save(path, run_id=run_id)
            for path in stale_frames(d, len(self.frames)):
                if force or is_kbs_output(path):
                    path.unlink()
            with replacing(d / "poses.txt") as (tmp,):
                write_kitti_poses(tmp, self.poses)
                digest = file_digest(tmp)
            doc = {"kbs_version": __version__, "run_id": run_id, "description": self.description,
                   "params": {k: v for k, v in self.params.items()}, **self.truth.to_dict(),
                   "sha256": {"poses.txt": digest}}
            with replacing(d / "truth.json") as (tmp,):
                tmp.write_text(json.dumps(doc, default=_jsonable))
        except OSError as exc:
            raise CloudFileError(str(d), f"cannot write the drive: {exc.strerror or exc}") from exc


def stale_frames(directory: str | os.PathLike[str], n_frames: int) -> list[Path]:
    """The frame files ``DIR/scans/NNNNNN.ply`` numbered ``n_frames`` or more: an earlier, longer
    drive's, which a drive of ``n_frames`` written there would leave behind."""
    scans = Path(directory) / "scans"
    if not scans.is_dir():
        return []
    return sorted(p for p in scans.iterdir()
                  if len(p.name) == 10 and p.name.endswith(".ply") and p.name[:6].isdigit() and int(p.name[:6]) >= n_frames)


def drive_files(directory: str | os.PathLike[str], n_frames: int) -> tuple[list[Path], Path, Path]:
    """The files :meth:`Drive.save` writes in ``directory``: the frames' PLY files, ``poses.txt``
    and ``truth.json``."""
    d = Path(directory)
    return [d / "scans" / f"{i:06d}.ply" for i in range(n_frames)], d / "poses.txt", d / "truth.json"


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, (tuple, np.ndarray)):
        return list(o)
    raise TypeError(type(o).__name__)


_DRIVE_CONSTRAINTS = {
    **OUTDOOR_CONSTRAINTS,  # the scene's own settings, as outdoor_scene checks them
    "n_frames": [Interval(numbers.Integral, 1, None)],
    "step": [Interval(numbers.Real, 0, None, closed="neither")],
    "yaw_rate": [Interval(numbers.Real, -45, 45, closed="both")],
}


def _near(poly: np.ndarray, points: np.ndarray, spacing: float = 0.25) -> np.ndarray:
    """Distance from each of ``points`` (m, 2) to the closed polygon ``poly`` (k, 2)'s outline
    (sampled every ``spacing`` metres)."""
    from scipy.spatial import cKDTree

    edges = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / spacing)) + 1)
        edges.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return cKDTree(np.vstack(edges)).query(points)[0]


def _street(rng: np.random.Generator, terrain: HeightField, w: float, s_lo: float, s_hi: float,
            path_xy: np.ndarray, placed: list[tuple[np.ndarray, float]], gap: float) -> list[tuple[str, Any]]:
    """Buildings, trees and poles along both sides of the path between arc lengths ``s_lo`` and
    ``s_hi``, clear of the path and of the objects already ``placed`` (footprint circles)."""
    out: list[tuple[str, Any]] = []

    def clear(poly: np.ndarray, margin: float) -> bool:
        if _near(poly, path_xy).min() < margin or _inside(poly, path_xy).any():
            return False
        return all(_near(poly, c[None])[0] >= r + gap and not _inside(poly, c[None])[0] for c, r in placed)

    def local(s: float, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        x, y, h = (float(v) for v in arc(s, w))
        return np.column_stack([x + along * np.cos(h) - across * np.sin(h), y + along * np.sin(h) + across * np.cos(h)])

    for side in (1.0, -1.0):
        a = s_lo + rng.uniform(0.0, 4.0)  # buildings: blocks with gaps between them
        while a < s_hi:
            length, depth, setback = rng.uniform(6.0, 12.0), rng.uniform(5.0, 9.0), rng.uniform(7.5, 10.0)
            along = np.array([-0.5, 0.5, 0.5, -0.5]) * length
            across = side * np.array([setback, setback, setback + depth, setback + depth])
            poly = local(a + length / 2, along, across)
            if side < 0:
                poly = poly[::-1]  # counter-clockwise
            g = terrain(poly[:, 0], poly[:, 1])
            height = rng.uniform(4.0, 9.0)
            if clear(poly, 2.0):
                out.append(("building", Prism(poly, float(g.min()) - 0.3, float(g.mean()) + height)))
            a += length + rng.uniform(1.5, 4.0)
        a = s_lo + rng.uniform(0.0, 6.0)  # trees in front of the buildings
        while a < s_hi:
            c = local(a, np.zeros(1), np.array([side * rng.uniform(5.0, 6.5)]))[0]
            r_trunk, h_trunk = rng.uniform(0.15, 0.3), rng.uniform(2.0, 3.0)
            crown = np.array([rng.uniform(1.2, 2.0), 0.0, rng.uniform(1.0, 1.8)])
            crown[1] = crown[0] * rng.uniform(0.8, 1.0)
            ground = float(terrain(c[0], c[1]))
            trunk = Prism(_octagon(c, r_trunk), ground - 0.3, ground + h_trunk + 0.5 * crown[2])
            if clear(_octagon(c, crown[0]), 0.8) and all(np.linalg.norm(c - q) >= crown[0] + r + gap for q, r in placed):
                out.append(("tree", Tree(trunk, Rock(np.array([[c[0], c[1], ground + h_trunk + crown[2]]]),
                                                     np.eye(3)[None], crown[None]))))
                placed.append((c, float(crown[0])))
            a += rng.uniform(6.0, 10.0)
        a = s_lo + rng.uniform(0.0, 4.0)  # poles at the kerb
        while a < s_hi:
            c = local(a, np.zeros(1), np.array([side * rng.uniform(2.5, 4.0)]))[0]
            r_pole = rng.uniform(0.08, 0.15)
            ground = float(terrain(c[0], c[1]))
            pole = Prism(_octagon(c, r_pole), ground - 0.3, ground + rng.uniform(4.0, 7.0))
            if clear(pole.footprint, 1.0) and all(np.linalg.norm(c - q) >= r_pole + r + gap for q, r in placed):
                out.append(("pole", pole))
                placed.append((c, r_pole))
            a += rng.uniform(4.0, 8.0)
    return out


def _inside(poly: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Whether ``points`` (m, 2) lie inside the convex counter-clockwise polygon ``poly``."""
    e = np.roll(poly, -1, axis=0) - poly
    cross = e[None, :, 0] * (points[:, None, 1] - poly[None, :, 1]) - e[None, :, 1] * (points[:, None, 0] - poly[None, :, 0])
    return (cross >= 0).all(axis=1)


def outdoor_drive(
    seed: int = 0,
    *,
    n_frames: int = 20,
    step: float = 1.0,
    yaw_rate: float = 2.0,
    extent: float = 25.0,
    n_rocks: int = 6,
    with_bin: bool = True,
    resolution: tuple[int, int] = (180, 320),
    fov_deg: tuple[float, float] = (45.0, 90.0),
    tilt_deg: float = 18.0,
    sensor_height: float = 1.5,
    noise: float = 5e-4,
    density_r0: float = 6.0,
    ground_amplitude: float = 0.15,
    rock_size: tuple[float, float] = (0.3, 0.8),
    bin_size: tuple[float, float, float] = (0.6, 0.6, 1.0),
    lateral: tuple[float, float] = (1.5, 5.0),
    gap: float = 0.5,
    max_tries: int = 500,
    street: bool = False,
) -> DriveScene:
    """A drive of ``n_frames`` frames through one outdoor scene (see the module's doc).

    Objects stand beside the path: at a random arc length from 4 m to ``0.4 extent`` past the
    last pose, ``lateral`` metres to its left or right, their footprint circles ``gap`` apart.
    Each frame is ray-cast as :func:`outdoor_scene` casts its one view (the same sensor laws:
    density ``(density_r0 / r)^2``, range noise ``noise r^2``), from its pose.

    Parameters
    ----------
    seed : int
    n_frames : int
    step : float
        Metres between consecutive poses.
    yaw_rate : float
        Heading change between consecutive poses, degrees (positive: to the left).
    lateral : (float, float)
        Range of the objects' distance to the path, metres.
    extent, n_rocks, with_bin, resolution, fov_deg, tilt_deg, sensor_height, noise, density_r0,
    ground_amplitude, rock_size, bin_size, gap, max_tries
        As :func:`kbs.synth.outdoor_scene`.
    street : bool
        Also line the path as a street is lined: on each side, buildings (blocks 6-12 m long,
        5-9 m deep, 4-9 m high, 7.5-10 m from the path, 1.5-4 m apart), trees (a trunk under an
        ellipsoidal crown, 5-6.5 m from the path, every 6-10 m) and poles (4-7 m high, 2.5-4 m
        from the path, every 4-8 m), from 8 m behind the first pose to past the last view. They
        are drawn from a generator of their own, so the rocks, the bin and the rays of a drive
        without them are the same. Their faces give a registration (``kbs map
        --estimate-poses``) what flat ground and a few rocks do not: surfaces facing the
        direction of travel.

    Returns
    -------
    DriveScene

    Raises
    ------
    ParameterError
        A parameter out of range, or objects that cannot be placed.
    """
    params = dict(seed=seed, n_frames=n_frames, step=step, yaw_rate=yaw_rate, extent=extent, n_rocks=n_rocks,
                  with_bin=with_bin, resolution=resolution, fov_deg=fov_deg, tilt_deg=tilt_deg,
                  sensor_height=sensor_height, noise=noise, density_r0=density_r0,
                  ground_amplitude=ground_amplitude, rock_size=rock_size, bin_size=bin_size, lateral=lateral, gap=gap,
                  max_tries=max_tries, street=street)
    validate_params("outdoor_drive", params, _DRIVE_CONSTRAINTS)
    if not isinstance(street, (bool, np.bool_)):
        raise ParameterError(f"The 'street' parameter of outdoor_drive must be a bool. Got {street!r} instead.")
    resolution = check_pair("outdoor_drive", "resolution", resolution, numbers.Integral, 0, None)
    fov_deg = check_pair("outdoor_drive", "fov_deg", fov_deg, numbers.Real, 0, 180)
    rock_size = check_pair("outdoor_drive", "rock_size", rock_size, numbers.Real, 0, None)
    lateral = check_pair("outdoor_drive", "lateral", lateral, numbers.Real, 0, None)
    if rock_size[0] > rock_size[1] or lateral[0] > lateral[1]:
        raise ParameterError("The 'rock_size' and 'lateral' parameters of outdoor_drive must be (low, high) with "
                             f"low <= high. Got {rock_size!r} and {lateral!r} instead.")
    if ground_amplitude >= sensor_height:
        raise ParameterError(f"The 'ground_amplitude' parameter of outdoor_drive must be below sensor_height "
                             f"({sensor_height:g}). Got {ground_amplitude!r} instead.")
    bin_size = tuple(float(v) for v in bin_size)
    rng = np.random.default_rng(seed)
    terrain = random_terrain(rng, sensor_height, ground_amplitude)
    w = np.radians(yaw_rate) / step  # rad per metre
    s = np.arange(n_frames) * step
    px, py, heading = arc(s, w)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        poses[i, :3, :3] = _rz(float(heading[i]))
        poses[i, :3, 3] = [px[i], py[i], float(terrain(px[i], py[i])) + sensor_height]

    path_far = s[-1] + 0.4 * extent
    dense = np.linspace(-2.0, path_far + 2.0, int((path_far + 4.0) / 0.25) + 2)
    path_xy = np.column_stack(arc(dense, w)[:2])
    placed: list[tuple[np.ndarray, float]] = []
    solids: list[Any] = []
    names = ["ground"]
    for i in range(n_rocks + int(with_bin)):
        is_bin = i == n_rocks
        for _ in range(max_tries):
            a = rng.uniform(4.0, path_far)
            side = rng.choice([-1.0, 1.0])
            d = rng.uniform(*lateral)
            x, y, h = arc(a, w)
            xy = np.array([float(x) - side * d * np.sin(float(h)), float(y) + side * d * np.cos(float(h))])
            obj, reach = random_bin(rng, xy, bin_size, terrain) if is_bin else random_rock(rng, xy, rock_size, terrain)
            clear_path = np.linalg.norm(path_xy - xy, axis=1).min() >= reach + 0.5
            if clear_path and all(np.linalg.norm(xy - c) >= reach + rc + gap for c, rc in placed):
                placed.append((xy, reach))
                solids.append(obj)
                names.append("bin" if is_bin else f"rock {i + 1}")
                break
        else:
            raise ParameterError(f"outdoor_drive could not place {'the bin' if is_bin else f'rock {i + 1}'} beside "
                                 f"the path after {max_tries} tries; ask for fewer or smaller objects, or a longer drive")
    if street:
        counts: dict[str, int] = {}
        street_s = np.linspace(-12.0, path_far + 8.0, int((path_far + 20.0) / 0.25) + 2)
        street_path = np.column_stack(arc(street_s, w)[:2])
        for kind, obj in _street(np.random.default_rng([seed, 1]), terrain, w, -8.0, path_far + 5.0, street_path,
                                 placed, gap):
            counts[kind] = counts.get(kind, 0) + 1
            solids.append(obj)
            names.append(f"{kind} {counts[kind]}")

    frames = []
    for i in range(n_frames):
        T = poses[i]
        local_terrain = _in_sensor_frame(terrain, T)
        local = [_in_sensor_frame(o, T) for o in solids]
        dirs = pinhole_rays(resolution, fov_deg, tilt_deg, rng=rng)
        n_rays = len(dirs)
        t_best = ray_heightfield(dirs, local_terrain, extent)
        owner = np.zeros(n_rays, dtype=np.int64)
        for k, o in enumerate(local, start=1):
            t = o.cast(dirs)
            nearer = t < t_best
            t_best = np.where(nearer, t, t_best)
            owner = np.where(nearer, k, owner)
        keep_draw = rng.uniform(size=n_rays)
        noise_draw = rng.normal(size=n_rays)
        hit = t_best <= extent
        with np.errstate(divide="ignore"):
            hit &= keep_draw < np.minimum(1.0, (density_r0 / t_best) ** 2)
        ranges = t_best[hit] * (1.0 + noise * t_best[hit] * noise_draw[hit])
        owner = owner[hit]
        frames.append(Scene(
            xyz=dirs[hit] * ranges[:, None], labels=owner, objects=owner, ground=owner == 0, kind="outdoor",
            seed=seed, description=f"outdoor drive, seed {seed}, frame {i} of {n_frames}; sensor frame: origin at the "
            "sensor, x forward, y left, z up; label 0 ground, 1.. the drive's objects",
            object_names=tuple(names), pixel=np.flatnonzero(hit), shape=tuple(resolution), terrain=local_terrain,
            solids=tuple(local), params=params))
    furniture = ""
    if street:
        kinds = [n.rsplit(" ", 1)[0] for n in names[n_rocks + int(with_bin) + 1:]]
        furniture = ", " + ", ".join(count(kinds.count(k), k, k + "s") for k in ("building", "tree", "pole")) + \
            " along the street"
    description = (f"outdoor drive, seed {seed}: {n_frames} frames {step:g} m apart turning {yaw_rate:g} deg per "
                   f"frame, {count(n_rocks, 'rock', 'rocks')}{', a bin' if with_bin else ''} beside the path{furniture}; camera "
                   f"{resolution[0]}x{resolution[1]} px, fov {fov_deg[0]:g}x{fov_deg[1]:g} deg, tilt {tilt_deg:g} deg, "
                   f"{sensor_height:g} m above the ground, range <= {extent:g} m")
    return DriveScene(tuple(frames), DriveTruth(terrain, tuple(solids), tuple(names), poses), description, params)
