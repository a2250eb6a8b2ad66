"""Meshes of a segmentation: a closed convex hull per obstacle cluster, and the ground surface.

Obstacles: :func:`hull_mesh` is scipy's ``ConvexHull`` of the cluster's points with every
triangle turned to face outward (its normal agrees with the hull facet's outward normal), so the
mesh is closed, consistently wound and of positive volume. Clusters with fewer than 4 points, or
whose points are coplanar/collinear (Qhull cannot build a 3-D hull), are skipped and listed;
a degenerate cluster (its points on a line or at one position,
:attr:`kbs.inference.ClusterGeometry.degenerate`) is said to be one.

Ground: :func:`ground_mesh` projects the ground points on their best approximating plane, runs a
2-D Delaunay triangulation there and removes triangles with an edge longer than ``edge_factor``
times the median Delaunay edge (holes under obstacles and gaps between scan lines stay open) and
zero-area triangles (height at most :data:`~kbs.inference.geometry.RANK_TOLERANCE` times the
longest edge: slivers along collinear points). Ground points that lie on a line have no surface.
"""
from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import plyfile

from kbs.errors import CloudFileError
from kbs.geometry.pca import principal_axes
from kbs.io.atomic import sigint_held, temporary_path
from kbs.inference import ClusterGeometry, cluster_geometry
from kbs.inference.geometry import RANK_TOLERANCE


def hull_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed, outward-oriented convex hull of ``points`` (n, 3).

    Returns
    -------
    vertices : ndarray (m, 3) float64
        The hull's vertices (a subset of the points).
    faces : ndarray (f, 3) int32
        Triangles indexing ``vertices``, counter-clockwise seen from outside.

    Raises
    ------
    ValueError
        Fewer than 4 points, or points that span no volume (coplanar, collinear, coincident).
    """
    from scipy.spatial import ConvexHull, QhullError

    P = np.asarray(points, dtype=np.float64)
    if P.shape[0] < 4:
        raise ValueError(f"{P.shape[0]} points (a hull needs at least 4)")
    try:
        hull = ConvexHull(P)
    except QhullError as exc:
        raise ValueError("degenerate points (coplanar or collinear): no 3-D hull") from exc
    scale = float(np.ptp(P, axis=0).max())
    if hull.volume <= 1e-12 * max(scale, 1e-300) ** 3:
        raise ValueError("degenerate points (hull volume ~ 0)")
    tri = hull.simplices.copy()
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", normal, hull.equations[:, :3]) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    used = np.unique(tri)
    remap = np.full(P.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return P[used], remap[tri].astype(np.int32)


def ground_mesh(points: np.ndarray, *, edge_factor: float = 3.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Triangulated ground surface of ``points`` (n, 3).

    Returns
    -------
    vertices : ndarray (n, 3) float64
        The points themselves.
    faces : ndarray (f, 3) int32
        Delaunay triangles of the projection on the best approximating plane, without those
        having an edge longer than ``max_edge``; oriented so their normals point to the same
        side as the plane normal (up when the ground faces +z).
    max_edge : float
        The edge-length threshold used: ``edge_factor`` x the median Delaunay edge length.

    Raises
    ------
    ValueError
        Fewer than 3 points, or points with no surface (on a line, or all at one position).
    """
    from scipy.spatial import Delaunay, QhullError

    P = np.asarray(points, dtype=np.float64)
    if P.shape[0] < 3:
        raise ValueError(f"{P.shape[0]} ground points (a surface needs at least 3)")
    pca = principal_axes(P, ddof=1)
    c, cov, lam, vec = pca.center, pca.covariance, pca.eigenvalues, pca.eigenvectors
    shape = ClusterGeometry(center=c, covariance=cov, eigenvalues=np.maximum(lam, 0.0), eigenvectors=vec,
                            mass=float(P.shape[0]))
    if shape.degenerate:
        raise ValueError(f"degenerate ground points: they {shape.degeneracy.removeprefix('its points ')}: no surface")
    n = vec[:, 0] if vec[2, 0] >= 0 else -vec[:, 0]
    uv = (P - c) @ vec[:, 1:]
    try:
        tri = Delaunay(uv).simplices
    except QhullError as exc:
        raise ValueError("degenerate ground points (collinear): no surface") from exc
    edges = np.stack([np.linalg.norm(P[tri[:, i]] - P[tri[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=1)
    max_edge = float(edge_factor * np.median(edges))
    longest = edges.max(axis=1)
    a, b, cc = P[tri[:, 0]] - c, P[tri[:, 1]] - c, P[tri[:, 2]] - c
    height = np.linalg.norm(np.cross(b - a, cc - a), axis=1) / np.maximum(longest, np.finfo(float).tiny)
    keep = (longest <= max_edge) & (height > RANK_TOLERANCE * longest)  # not too long, not zero-area
    tri = tri[keep]
    if not tri.shape[0]:
        raise ValueError("degenerate ground points: every triangle has zero area or too long an edge: no surface")
    a, b, cc = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    flip = np.cross(b - a, cc - a) @ n < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return P, tri.astype(np.int32), max_edge


def write_mesh_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, *, run_id: str | None = None) -> None:
    """Write a triangle mesh as a binary PLY (``vertex``: x y z double; ``face``: vertex_indices);
    with ``run_id``, header comments saying kbs wrote it (``kbs_run_id <hex>``: :func:`kbs.io.result.is_kbs_output`)."""
    from kbs.io.result import result_comments

    v = np.empty(vertices.shape[0], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    v["x"], v["y"], v["z"] = vertices.T
    f = np.empty(faces.shape[0], dtype=[("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = faces
    data = plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")],
                           comments=result_comments(run_id) if run_id else [])
    try:
        data.write(str(path))
    except OSError as exc:
        raise CloudFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc


@dataclass
class MeshSummary:
    """What :func:`write_meshes` wrote and skipped."""

    directory: Path
    obstacles: list[Path] = field(default_factory=list)
    skipped: list[tuple[int, str]] = field(default_factory=list)  # (cluster index, reason)
    ground: Path | None = None
    ground_note: str = ""

    def describe(self) -> str:
        lines = [f"meshes in {self.directory}: {len(self.obstacles)} obstacle hull"
                 f"{'s' if len(self.obstacles) != 1 else ''}, ground: {self.ground_note}"]
        for idx, why in self.skipped:
            lines.append(f"  skipped cluster {idx}: {why}")
        return "\n".join(lines)


def check_meshes_folder(directory: Path, *, force: bool = False) -> None:
    """Refuse a mesh folder :func:`write_meshes` must not replace (``kbs run`` calls it before any work).

    Raises
    ------
    CloudFileError
        ``directory`` is a file or a link; it holds a file of another name than the meshes'
        (never removed, even with ``force``: move it); or a mesh-named file kbs did not write (no
        ``kbs_run_id`` comment: another program's, or a mesh of kbs before run ids), unless ``force``.
    """
    from kbs.io.result import is_kbs_output

    directory = Path(directory)
    if not (directory.exists() or directory.is_symlink()):
        return
    if not directory.is_dir() or directory.is_symlink():
        raise CloudFileError(str(directory), "exists and is not a folder of meshes kbs wrote; choose another --out")
    names = sorted(p.name for p in directory.iterdir())
    foreign = [n for n in names if not _MESH_NAME.fullmatch(n)]
    if foreign:
        raise CloudFileError(str(directory), f"holds files kbs did not write ({', '.join(foreign[:3])}"
                                             f"{', ...' if len(foreign) > 3 else ''}): move them, or choose another --out")
    if not force:
        unmarked = [n for n in names if not is_kbs_output(directory / n)]
        if unmarked:
            raise CloudFileError(str(directory / unmarked[0]),
                                 "exists and was not written by kbs (it has no kbs run id); give --force to replace "
                                 "the mesh folder, or choose another --out")


def write_meshes(directory: Path, X: np.ndarray, cluster: np.ndarray, label: np.ndarray,
                 label_names: list[str], *, ground_label: str = "ground", run_id: str | None = None,
                 force: bool = False) -> MeshSummary:
    """Write ``directory/obstacle-<index>.ply`` for every output cluster whose label is not
    ``ground_label`` (noise excluded) and ``directory/ground.ply`` for the points labelled
    ``ground_label``.

    The folder appears whole or not at all: the meshes are written into a hidden temporary folder
    beside it, which then takes its place (an earlier run's folder, stale meshes included, goes
    only once the new one is complete; a full disk or Ctrl-C leaves it as it was). An existing
    folder holding other files than kbs's meshes is refused, not replaced, and one holding a mesh
    kbs did not write only with ``force`` (:func:`check_meshes_folder`). Each mesh carries
    ``run_id`` (default: a fresh one) in its header.

    Parameters
    ----------
    X : ndarray (n, 3)
    cluster, label : ndarray (n,) int
        Output cluster and label index of each point (-1 = noise).
    label_names : list of str
    """
    from kbs.io.result import new_run_id

    directory = Path(directory)
    check_meshes_folder(directory, force=force)
    run_id = run_id or new_run_id()
    staging = temporary_path(directory)
    try:
        staging.mkdir(parents=True)
    except OSError as exc:
        raise CloudFileError(str(directory), f"cannot create the mesh directory: {exc.strerror or exc}") from exc
    try:
        out = _write_meshes(staging, directory, X, cluster, label, label_names, ground_label=ground_label,
                            run_id=run_id)
        _swap_in(staging, directory)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


#: The files write_meshes writes; an existing folder holding anything else is not replaced.
_MESH_NAME = re.compile(r"obstacle-\d+\.ply|ground\.ply")


def _swap_in(staging: Path, directory: Path) -> None:
    """Put the complete ``staging`` folder in the place of ``directory`` (whose earlier content
    goes only then), Ctrl-C held back between the two renames."""
    old = temporary_path(directory.with_name(directory.name + "-old")) if directory.exists() else None
    try:
        with sigint_held():
            if old is not None:
                os.replace(directory, old)
            os.replace(staging, directory)
    except OSError as exc:
        raise CloudFileError(str(directory), f"cannot write: {exc.strerror or exc}") from exc
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _put(staging: Path, directory: Path, name: str, V: np.ndarray, F: np.ndarray, run_id: str) -> None:
    """write_mesh_ply into the staging folder; an error names the file where the user looks for it."""
    try:
        write_mesh_ply(staging / name, V, F, run_id=run_id)
    except CloudFileError as exc:
        raise CloudFileError(str(directory / name), exc.problem) from exc


def _write_meshes(staging: Path, directory: Path, X: np.ndarray, cluster: np.ndarray, label: np.ndarray,
                  label_names: list[str], *, ground_label: str, run_id: str) -> MeshSummary:
    """The meshes written into ``staging``, described as they will be in ``directory``."""
    X = np.asarray(X, dtype=np.float64)
    gi = label_names.index(ground_label) if ground_label in label_names else None
    out = MeshSummary(directory)
    for idx in np.unique(cluster[cluster >= 0]):
        sel = cluster == idx
        if gi is not None and np.all(label[sel] == gi):
            continue
        degeneracy = cluster_geometry(X[sel]).degeneracy
        if degeneracy is not None:
            out.skipped.append((int(idx), f"degenerate: {degeneracy}: no hull"))
            continue
        try:
            V, F = hull_mesh(X[sel])
        except ValueError as exc:
            out.skipped.append((int(idx), str(exc)))
            continue
        name = f"obstacle-{int(idx)}.ply"
        _put(staging, directory, name, V, F, run_id)
        out.obstacles.append(directory / name)
    if gi is None:
        out.ground_note = f"none (no label named {ground_label!r})"
    else:
        try:
            V, F, max_edge = ground_mesh(X[label == gi])
        except ValueError as exc:
            out.ground_note = f"not written: {exc}"
        else:
            out.ground = directory / "ground.ply"
            _put(staging, directory, "ground.ply", V, F, run_id)
            out.ground_note = f"{out.ground.name} ({F.shape[0]:,} triangles, edges <= {max_edge:.3g})"
    return out
