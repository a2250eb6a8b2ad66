"""Obstacles tracked across the frames of a drive as 3D objects, and their meshes.

Every connected piece of an obstacle cluster of a frame (a segmenter output cluster whose label
is not ground, cut into its 8-connected pieces on the footprint grid, each with at least
``min_points`` points) is a node; its footprint is the set of grid cells its points fall in, in
the world frame. Two nodes of frames at most ``max_gap`` apart (1: consecutive frames)
whose footprints share a cell are the same object (union-find over the links), so an object
is a connected chain of overlapping clusters. Its points are the fused (voxel-downsampled)
points of its clusters, and its mesh an alpha shape of them (:func:`alpha_shape`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kbs.arrays import rows as take_rows

_OFF = np.int64(1 << 20)


def _indices(X: np.ndarray, size: float) -> np.ndarray:
    """Integer cell indices of ``X`` at ``size``, offset to be non-negative (21 bits each)."""
    ij = np.floor(np.asarray(X) / size).astype(np.int64)
    if ij.size and (np.abs(ij).max() >= _OFF):
        from kbs.errors import ParameterError

        raise ParameterError(f"coordinates beyond {int(_OFF) * size:g} m from the world origin at cell or voxel "
                             f"size {size:g}: centre the poses (subtract the first position) or use larger cells")
    return ij + _OFF


def cell_keys(xy: np.ndarray, size: float) -> np.ndarray:
    """One int64 key per 2D cell of side ``size`` (world x, y): ``ix << 21 | iy`` (offset)."""
    ij = _indices(np.asarray(xy)[:, :2], size)
    return (ij[:, 0] << np.int64(21)) | ij[:, 1]


def voxel_keys(xyz: np.ndarray, size: float) -> np.ndarray:
    """One int64 key per 3D voxel of side ``size`` (|coordinate| < 2^20 voxels)."""
    ijk = _indices(xyz, size)
    return (ijk[:, 0] << np.int64(42)) | (ijk[:, 1] << np.int64(21)) | ijk[:, 2]


def voxel_mean(xyz: np.ndarray, size: float) -> np.ndarray:
    """The mean point of each occupied voxel (a voxel-grid downsampling), in key order."""
    keys = voxel_keys(xyz, size)
    uniq, inv = np.unique(keys, return_inverse=True)
    n = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    return np.column_stack([np.bincount(inv, weights=xyz[:, d], minlength=len(uniq)) / n for d in range(3)])


class _UnionFind:
    def __init__(self) -> None:
        self.parent: list[int] = []

    def add(self) -> int:
        self.parent.append(len(self.parent))
        return len(self.parent) - 1

    def find(self, a: int) -> int:
        root = a
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[a] != root:
            self.parent[a], a = root, self.parent[a]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


@dataclass(frozen=True)
class Node:
    """One obstacle cluster of one frame."""

    frame: int
    cluster: int
    n_points: int


class ObjectTracker:
    """Links the obstacle clusters of successive frames into objects (see the module's doc).

    Parameters
    ----------
    cell_size : float
        Side of the footprint cells, metres.
    voxel_size : float
        Voxel side of the points kept per cluster, metres.
    max_gap : int
        Nodes of frames up to this many frames apart are linked when they overlap.
    min_points : int
        Obstacle clusters with fewer points are not tracked (still in the grid).
    """

    def __init__(self, cell_size: float, voxel_size: float, *, max_gap: int = 1, min_points: int = 20) -> None:
        self.cell_size, self.voxel_size, self.max_gap, self.min_points = cell_size, voxel_size, max_gap, min_points
        self.nodes: list[Node] = []
        self.points: list[np.ndarray] = []
        self._uf = _UnionFind()
        self._frames: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, cell keys, node ids)

    def add(self, frame: int, xyz: np.ndarray, cluster: np.ndarray, obstacle: np.ndarray) -> np.ndarray:
        """Add one frame's obstacle clusters; returns the node id of each point (-1: none).

        A cluster is first cut into its connected pieces on the footprint grid (8-connected
        cells): a cluster that gathers look-alike obstacles far apart is several objects. All the
        clusters of the frame are cut at once: the (cluster, cell) pairs are the vertices of a
        graph whose edges join 8-neighbour cells of one cluster, and its connected components
        (scipy.sparse.csgraph) are the pieces.

        Parameters
        ----------
        frame : int
        xyz : np.ndarray (n, 3)
            World coordinates of the frame's points.
        cluster : np.ndarray (n,) int
            Output cluster of each point (-1 noise).
        obstacle : np.ndarray (n,) bool
            Whether each point is labelled an obstacle.
        """
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        node_of_point = np.full(len(xyz), -1, dtype=np.int64)
        sel = np.flatnonzero(obstacle & (cluster >= 0))
        if sel.size:
            big = np.bincount(cluster[sel])[cluster[sel]] >= self.min_points
            sel = sel[big]
        if sel.size == 0:
            self._frames.append((frame, np.zeros(0, np.int64), np.zeros(0, np.int64)))
            return node_of_point
        cl = cluster[sel].astype(np.int64)
        cells = cell_keys(take_rows(xyz, sel), self.cell_size)  # 2D cell keys: 21 bits per axis
        pair, inv = np.unique((cl << np.int64(42)) | cells, return_inverse=True)
        inv = inv.ravel()
        m = len(pair)
        rows, cols = [], []
        for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
            nb = pair + (np.int64(dx) << np.int64(21)) + np.int64(dy)
            pos = np.minimum(np.searchsorted(pair, nb), m - 1)
            hit = pair[pos] == nb
            rows.append(np.flatnonzero(hit))
            cols.append(pos[hit])
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(m, m))
        n_comp, comp = connected_components(graph, directed=False)
        comp_pt = comp[inv]
        size = np.bincount(comp_pt, minlength=n_comp)
        kept = np.flatnonzero(size >= self.min_points)
        if kept.size == 0:
            self._frames.append((frame, np.zeros(0, np.int64), np.zeros(0, np.int64)))
            return node_of_point
        base = len(self.nodes)
        node_of_comp = np.full(n_comp, -1, dtype=np.int64)
        node_of_comp[kept] = base + np.arange(len(kept))
        comp_cluster = np.zeros(n_comp, dtype=np.int64)
        comp_cluster[comp] = pair >> np.int64(42)
        for k in kept:
            self._uf.add()
            self.nodes.append(Node(frame, int(comp_cluster[k]), int(size[k])))
        nodes_pt = node_of_comp[comp_pt]
        node_of_point[sel] = nodes_pt
        # each node's points, voxel-downsampled: the mean of each (node, voxel)
        keep = nodes_pt >= 0
        P, npt = take_rows(take_rows(xyz, sel), keep), nodes_pt[keep]
        vk = voxel_keys(P, self.voxel_size)
        order = np.lexsort((vk, npt))
        npt, vk, P = npt[order], vk[order], take_rows(P, order)
        start = np.flatnonzero(np.r_[True, (np.diff(npt) != 0) | (np.diff(vk) != 0)])
        group = np.cumsum(np.r_[False, (np.diff(npt) != 0) | (np.diff(vk) != 0)])
        cnt = np.bincount(group).astype(np.float64)
        means = np.column_stack([np.bincount(group, weights=P[:, d]) / cnt for d in range(3)])
        gnode = npt[start]
        cuts = np.flatnonzero(np.diff(gnode)) + 1
        self.points.extend(np.split(means, cuts))
        # footprints: the cells of each node
        pk = pair & np.int64((1 << 42) - 1)  # the cell part of each (cluster, cell) key
        pn = node_of_comp[comp]
        nk, nn = pk[pn >= 0], pn[pn >= 0]
        self._link(frame, nk, nn)
        self._frames.append((frame, nk, nn))
        return node_of_point

    def _link(self, frame: int, nk: np.ndarray, nn: np.ndarray) -> None:
        recent = [(k, n) for f, k, n in self._frames if 0 < frame - f <= self.max_gap and len(k)]
        if not recent:
            return
        pk = np.concatenate([k for k, _ in recent])
        pn = np.concatenate([n for _, n in recent])
        order = np.argsort(pk, kind="stable")
        pk, pn = pk[order], pn[order]
        left, right = np.searchsorted(pk, nk, "left"), np.searchsorted(pk, nk, "right")
        counts = right - left
        if not counts.any():
            return
        new = np.repeat(nn, counts)
        idx = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(left, counts)
        pairs = np.unique(np.column_stack([new, pn[idx]]), axis=0)
        for a, b in pairs:
            self._uf.union(int(a), int(b))

    def objects(self) -> tuple[list[list[int]], np.ndarray]:
        """The objects as lists of node ids, ordered by first frame (then first node), and the
        object id of every node."""
        groups: dict[int, list[int]] = {}
        for i in range(len(self.nodes)):
            groups.setdefault(self._uf.find(i), []).append(i)
        ordered = sorted(groups.values(), key=lambda g: (self.nodes[g[0]].frame, g[0]))
        of_node = np.full(len(self.nodes), -1, dtype=np.int64)
        for oid, g in enumerate(ordered):
            of_node[g] = oid
        return ordered, of_node


def alpha_shape(points: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """The alpha shape of ``points``: the boundary of the union of the Delaunay tetrahedra whose
    circumsphere radius is below ``alpha`` (Edelsbrunner & Mücke 1994), as an outward-oriented
    triangle mesh. Unlike a convex hull it follows concavities and gaps wider than ``2 alpha``.

    Parameters
    ----------
    points : np.ndarray (n, 3)
    alpha : float
        Radius, metres (``inf`` gives the convex hull's tetrahedra).

    Returns
    -------
    vertices : np.ndarray (m, 3) float64
        The points used by the faces.
    faces : np.ndarray (f, 3) int32
        Triangles, counter-clockwise seen from outside (normals away from the kept tetrahedra).

    Raises
    ------
    ValueError
        Fewer than 4 points, points spanning no volume, or no tetrahedron below ``alpha``.
    """
    from scipy.spatial import Delaunay, QhullError

    P = np.asarray(points, dtype=np.float64)
    if len(P) < 4:
        raise ValueError(f"{len(P)} points (a 3D shape needs at least 4)")
    c = P.mean(axis=0)
    try:
        tet = Delaunay(P - c, qhull_options="Qbb Qc Qz Q12").simplices
    except QhullError as exc:
        raise ValueError("degenerate points (coplanar or collinear): no 3D shape") from exc
    a, b, cc, d = (P[tet[:, i]] for i in range(4))
    u, v, w = b - a, cc - a, d - a
    vw, wu, uv = np.cross(v, w), np.cross(w, u), np.cross(u, v)
    det = np.einsum("ij,ij->i", u, vw)
    num = (u * u).sum(1)[:, None] * vw + (v * v).sum(1)[:, None] * wu + (w * w).sum(1)[:, None] * uv
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.linalg.norm(num, axis=1) / np.abs(2.0 * det)
    scale = float(np.ptp(P, axis=0).max())
    keep = np.isfinite(radius) & (radius < alpha) & (np.abs(det) > 1e-12 * scale**3)
    tet = tet[keep]
    if len(tet) == 0:
        raise ValueError(f"no tetrahedron with a circumradius below alpha = {alpha:g}")
    # the four faces of each kept tetrahedron, with the opposite vertex; a face on the boundary
    # belongs to exactly one kept tetrahedron
    opp = np.array([[1, 2, 3, 0], [0, 3, 2, 1], [0, 1, 3, 2], [0, 2, 1, 3]])
    faces = np.concatenate([tet[:, o[:3]] for o in opp])
    apex = np.concatenate([tet[:, o[3]] for o in opp])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    faces, apex = faces[once], apex[once]
    fa, fb, fc = P[faces[:, 0]], P[faces[:, 1]], P[faces[:, 2]]
    normal = np.cross(fb - fa, fc - fa)
    inward = np.einsum("ij,ij->i", normal, P[apex] - fa) > 0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    used = np.unique(faces)
    remap = np.full(len(P), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return P[used], remap[faces].astype(np.int32)


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by an outward-oriented triangle mesh (divergence theorem)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def object_mesh(points: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray, str]:
    """The mesh of an object's fused points: their alpha shape, or their convex hull when the
    alpha shape is empty (too sparse for ``alpha``); ``kind`` says which.

    Raises
    ------
    ValueError
        Not even a convex hull (fewer than 4 points, or flat).
    """
    try:
        V, F = alpha_shape(points, alpha)
        return V, F, "alpha shape"
    except ValueError:
        from kbs.report.meshes import hull_mesh

        V, F = hull_mesh(points)
        return V, F, "convex hull (alpha shape empty)"
