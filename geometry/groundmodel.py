"""A local ground surface built from the points of the clusters that earned the ground label.

One global plane (the scene's ``Ground``) cannot say whether a patch of grass beside a cambered
road, or a strip of pavement at the foot of a wall, lies *on* the ground: the terrain bends and
steps. The local model answers it the way a height map does, without gridding: the ground height
under a point is the median height of its ``neighbours`` nearest ground points, found in the ground
plane's own 2D coordinates within ``radius`` (or a lower ``quantile`` of them: where low plants
or the feet of obstacles stand among the ground points, the terrain is the lower part of them).
Heights are measured along the ground normal.

The radius may grow with the distance to the sensor (``per_range``): a spinning lidar's rings
lie farther apart the farther they are (metres apart at 30 m for a 64-beam sensor), so a fixed
radius that holds a near surface leaves far ground without one.

Where no ground point lies within ``radius`` the local height is unknown (NaN in
:meth:`LocalGround.height`); callers decide what that means (the predicate falls back to the
global plane, the ground-contact step leaves such points alone).
"""
from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kbs.arrays import rows, minus
from kbs.geometry.pca import plane_basis
from kbs.inference import _compiled, _flags
from kbs.inference.voxel import bounds


#: arrays up to this size take the compiled order statistics (a sort), larger ones numpy's (a partition)
FAST_STAT_MAX = 1 << 16


def order_statistic(h: np.ndarray, q: float, median: bool, reference: Callable[[np.ndarray], Any]) -> Any:
    """A statistic of heights ``h``: ``reference(h)`` (``np.percentile`` at ``100 q`` or
    ``np.median``), the same value bit for bit from the compiled
    :func:`~kbs.inference._compiled.quantile_linear` where it can say so (numpy's per-call
    overhead was about 0.1 ms, a tenth of an airborne frame's post steps); numpy answers for NaN,
    zeros picked, empty or large arrays and ``KBS_JIT=0``."""
    if _flags.JIT and isinstance(h, np.ndarray) and h.ndim == 1 and h.dtype == np.float64 \
            and 0 < h.size <= FAST_STAT_MAX:
        v, ok = _compiled.quantile_linear(h, q, median)
        if ok:
            return v
    return reference(h)


def _slide(A: np.ndarray, reach: int, op) -> np.ndarray:
    """``op`` (minimum, maximum or add) of ``A`` (2D) over the (2 reach + 1)^2 block around each
    cell, one axis after the other (cells beyond the edges do not count)."""
    out = A
    for axis in (0, 1):
        src_all, res = out, out.copy()
        n = out.shape[axis]
        for d in range(1, reach + 1):
            for lo_src, lo_dst in ((d, 0), (0, d)):  # the cell d after, then the cell d before
                src = [slice(None)] * 2
                dst = [slice(None)] * 2
                src[axis] = slice(lo_src, n - lo_dst)
                dst[axis] = slice(lo_dst, n - lo_src)
                op(res[tuple(dst)], src_all[tuple(src)], out=res[tuple(dst)])
        out = res
    return out


@dataclass(frozen=True)
class SurfaceEdges:
    """The surface's points grouped into continuous surfaces, and how far the points at the edge of
    each stand above the surfaces beside it (:meth:`LocalGround.edges`).

    Two surface points are continuous when one is among the other's :attr:`NEIGHBOURS` nearest
    (in the plane) within ``gap`` and their heights differ by at most ``max(step, tan(slope) d)``
    (``d`` their distance in the plane): terrain no steeper than ``slope``, or a step no higher
    than ``step``. A continuous surface (a *region*) is a connected set of such links. A point has
    a *drop* when points of other regions lie within ``gap`` of it: its height less the lowest
    terrain those allow, ``min_j (h_j + tan(slope) d_ij)``; a roof's edge above the street beside
    the building drops by about its height, terrain beside a building rises (negative).
    """

    #: the nearest surface points a point's continuity is judged with
    NEIGHBOURS = 8
    #: points whose pairs within ``gap`` are found at once (about 70 pairs a point at 2.5 points
    #: a square metre and a 3 m gap: 16 bytes each)
    CHUNK = 1 << 14

    #: (m,) the region of each surface point
    region: np.ndarray
    #: (m,) each point's drop (NaN where no other region lies within ``gap``)
    drop: np.ndarray
    n_regions: int
    #: (number of owners,) the region holding most of each owner's points (-1: none)
    owner_region: np.ndarray
    #: (n_regions,) the surface points each region holds
    sizes: np.ndarray
    #: the points with a drop, ordered by region, and where each region's run starts and ends
    _edge_order: np.ndarray
    _starts: np.ndarray
    _ends: np.ndarray
    #: (m, 2) the surface points in the plane, and (m,) for each point with a drop the point of
    #: another region that allows the lowest terrain under it (-1: no drop)
    plane: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    partner: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def build(cls, plane: np.ndarray, heights: np.ndarray, owners: np.ndarray | None, n_owners: int,
              tree: Any, gap: float, slope: float, step: float) -> SurfaceEdges:
        """The regions and drops of the surface points ``plane`` (m, 2) with ``heights`` (m,),
        ``owners`` (m,) (indices below ``n_owners``), ``tree`` a k-d tree over ``plane``."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        m = int(heights.size)
        rise = float(np.tan(np.radians(slope)))
        if m == 0:
            empty = np.zeros(0, dtype=np.int64)
            return cls(empty, np.zeros(0), 0, np.full(n_owners, -1, dtype=np.int64), empty, empty, empty, empty,
                       np.zeros((0, 2)), empty)
        k = min(cls.NEIGHBOURS + 1, m)
        d, j = tree.query(plane, k=k, distance_upper_bound=gap)
        d, j = np.asarray(d).reshape(m, k), np.asarray(j).reshape(m, k)
        i = np.broadcast_to(np.arange(m)[:, None], (m, k))
        ok = (j < m) & (j != i)
        jj = np.where(ok, j, 0)
        dd = np.where(ok, d, 0.0)
        linked = ok & (np.abs(heights[i] - heights[jj]) <= np.maximum(step, rise * dd))
        graph = coo_matrix((np.ones(int(linked.sum()), dtype=np.int8), (i[linked], jj[linked])), shape=(m, m))
        n, region = connected_components(graph, directed=False)
        region = region.astype(np.int64)
        lowest = np.full(m, np.inf)
        partner = np.full(m, -1, dtype=np.int64)
        near = cls._near_other_regions(plane, region, gap)
        for s in range(0, near.size, cls.CHUNK):  # their pairs within gap, a chunk at a time (bounded memory)
            at = near[s:s + cls.CHUNK]
            part = cKDTree(plane[at], balanced_tree=False, compact_nodes=False)
            pairs = part.sparse_distance_matrix(tree, gap, output_type="ndarray")
            a, b = at[pairs["i"]], pairs["j"].astype(np.int64)
            other = region[a] != region[b]
            a, b, low = a[other], b[other], heights[b[other]] + rise * pairs["v"][other]
            np.minimum.at(lowest, a, low)
            # the partner realising each point's lowest: the pairs in the order (point, value, partner)
            # (a point's pairs all fall in one chunk), the first of each point's run
            best = np.lexsort((b, low, a))
            a, b, low = a[best], b[best], low[best]
            head = np.r_[True, a[1:] != a[:-1]] if a.size else np.zeros(0, dtype=bool)
            partner[a[head]] = b[head]
        edge = np.isfinite(lowest)
        drop = np.full(m, np.nan)
        drop[edge] = heights[edge] - lowest[edge]
        at = np.flatnonzero(edge)
        order = at[np.argsort(region[at], kind="stable")]
        runs = region[order]
        starts = np.flatnonzero(np.r_[True, runs[1:] != runs[:-1]]) if runs.size else np.zeros(0, dtype=np.int64)
        first = np.full(n, -1, dtype=np.int64)
        last = np.full(n, -1, dtype=np.int64)
        if runs.size:
            first[runs[starts]] = starts
            last[runs[starts]] = np.r_[starts[1:], runs.size]
        owner_region = np.full(n_owners, -1, dtype=np.int64)
        if owners is not None and n_owners:
            pair, count = np.unique(np.asarray(owners, dtype=np.int64) * n + region, return_counts=True)
            po, pr = pair // n, pair % n
            best = np.lexsort((pr, -count, po))  # per owner: the most points, then the lowest region
            po, pr = po[best], pr[best]
            head = np.r_[True, po[1:] != po[:-1]]
            owner_region[po[head]] = pr[head]
        return cls(region, drop, int(n), owner_region, np.bincount(region, minlength=n), order, first, last,
                   plane, partner)

    @classmethod
    def _near_other_regions(cls, plane: np.ndarray, region: np.ndarray, gap: float) -> np.ndarray:
        """The points (indices, ascending) that may have a point of another region within ``gap``:
        those whose 3 x 3 block of square cells of side ``gap`` holds more than one region (the
        block holds every point within ``gap``); all points when such a grid would be too large."""
        m = region.size
        lo, hi = bounds(plane)
        if not gap > 0.0:
            return np.arange(m)
        origin = lo - gap
        shape = np.floor((hi - origin) / gap).astype(np.int64) + 2
        if float(shape[0]) * float(shape[1]) > 4.0 * m + 4096:
            return np.arange(m)
        ij = np.floor((plane - origin) / gap).astype(np.int64)
        cell = ij[:, 0] * shape[1] + ij[:, 1]
        size = int(shape[0] * shape[1])
        low = np.full(size, np.iinfo(np.int64).max)
        high = np.full(size, -1, dtype=np.int64)
        np.minimum.at(low, cell, region)
        np.maximum.at(high, cell, region)
        shape2 = (int(shape[0]), int(shape[1]))
        low_b = _slide(low.reshape(shape2), 1, np.minimum).ravel()
        high_b = _slide(high.reshape(shape2), 1, np.maximum).ravel()
        return np.flatnonzero(low_b[cell] != high_b[cell])

    def drops_of(self, r: int) -> np.ndarray:
        """The drops of region ``r``'s edge points (empty when it meets no other region)."""
        if r < 0 or self._starts[r] < 0:
            return np.zeros(0)
        return self.drop[self._edge_order[self._starts[r]:self._ends[r]]]

    def stat_of(self, r: int, name: str, stat: Callable[[np.ndarray], Any]) -> float:
        """``stat`` (called ``name``) of region ``r``'s drops (non-empty), computed once per region:
        every cluster of a large surface asks for the same value."""
        key = ("stat", int(r), name)
        got = self._cache.get(key)
        if got is None:
            got = float(stat(self.drops_of(r)))
            self._cache[key] = got
        return got

    def size_of(self, r: int) -> int:
        """How many surface points region ``r`` holds (0 for -1, no region)."""
        return int(self.sizes[r]) if r >= 0 else 0

    def areas(self, cell: float) -> np.ndarray:
        """(n_regions,) the area each region covers: its occupied square cells of side ``cell`` in
        the plane, times ``cell`` squared (an outline traced at that resolution, holes and all)."""
        key = ("area", float(cell))
        got = self._cache.get(key)
        if got is None:
            if not self.region.size:
                got = np.zeros(self.n_regions)
            else:
                ij = np.floor((self.plane - self.plane.min(axis=0)) / cell).astype(np.int64)
                cells = (int(ij[:, 0].max()) + 1) * (int(ij[:, 1].max()) + 1)
                pair = np.unique(self.region * cells + ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1])
                got = np.bincount(pair // cells, minlength=self.n_regions) * (cell * cell)
            self._cache[key] = got
        return got

    def enclosure(self, r: int, min_drop: float) -> tuple[float, int]:
        """How far region ``r`` is enclosed by the surfaces it drops to: the share of its points
        inside the convex hull (in the plane) of the points that allow the lowest terrain under its
        edge points dropping by ``min_drop`` or more, and how many such edge points it has (0: the
        share is NaN). A roof drops to the street on every side: the street's points around it
        enclose it (1), a quarter to a half of it where the scan cuts the building with two walls
        in view; the
        upper terrace of a terrain step drops on one side only, the street beside it lies along a
        line (0), as does the rim of a pit, whose floor lies inside the rim, not around it."""
        key = ("enclosure", int(r), float(min_drop))
        got = self._cache.get(key)
        if got is None:
            got = self._enclosure(r, min_drop)
            self._cache[key] = got
        return got

    def _enclosure(self, r: int, min_drop: float) -> tuple[float, int]:
        import shapely

        if r < 0 or self._starts[r] < 0:
            return math.nan, 0
        at = self._edge_order[self._starts[r]:self._ends[r]]
        at = at[self.drop[at] >= min_drop]
        if not at.size:
            return math.nan, 0
        lows = self.plane[np.unique(self.partner[at])]
        mine = self.plane[self.region == r]
        hull = shapely.MultiPoint(lows).convex_hull
        if hull.area <= 0.0:  # the lower points on a line (or one point): nothing inside
            return 0.0, int(at.size)
        inside = shapely.intersects_xy(hull, mine[:, 0], mine[:, 1])
        return float(inside.mean()), int(at.size)


@dataclass(frozen=True)
class SurfaceRegions:
    """The points the continuous surfaces of a ground surface are built from (its plane
    coordinates, heights and owners, shared with it, not copied), and the :class:`SurfaceEdges`
    built on them, by parameters. Held apart from the :class:`LocalGround` so that a surface
    rebuilt within a relabel step can measure on its predecessor's without keeping it whole."""

    plane: np.ndarray
    heights: np.ndarray
    owners: np.ndarray | None
    owner_ids: tuple[str, ...]
    tree_: Any = None
    _edges: dict = field(default_factory=dict, repr=False, compare=False)

    @functools.cached_property
    def owner_index(self) -> dict[str, int]:
        """Each owner id's index in :attr:`owner_ids`."""
        return {oid: k for k, oid in enumerate(self.owner_ids)}

    @functools.cached_property
    def _by_owner(self) -> tuple[np.ndarray, np.ndarray]:
        """The points ordered by owner, and where each owner's run starts (n_owners + 1,)."""
        n = len(self.owner_ids)
        if self.owners is None:
            return np.arange(self.heights.size), np.r_[0, np.full(n, self.heights.size)]
        order = np.argsort(self.owners, kind="stable")
        return order, np.searchsorted(self.owners[order], np.arange(n + 1))

    def points_of(self, k: int) -> np.ndarray:
        """The points (indices) of owner ``k``."""
        order, starts = self._by_owner
        return order[starts[k]:starts[k + 1]]

    def edges(self, gap: float, slope: float, step: float) -> SurfaceEdges:
        """The :class:`SurfaceEdges` for these parameters, built at the first call."""
        key = (float(gap), float(slope), float(step))
        got = self._edges.get(key)
        if got is None:
            got = SurfaceEdges.build(self.plane, self.heights, self.owners, len(self.owner_ids), self._tree(),
                                     float(gap), float(slope), float(step))
            self._edges[key] = got
        return got

    def drops_beside(self, gap: float, slope: float, step: float, r: int, alive: np.ndarray) -> np.ndarray:
        """The drops of region ``r``'s edge points (:meth:`edges`) when only the points of the
        owners ``alive`` (bool, one per owner) may lie beside them: an edge point whose surfaces
        beside it all belong to owners no longer alive is no longer at an edge (left out). With
        every owner alive, the drops of :meth:`SurfaceEdges.drops_of`. A low roof between taller
        ones drops to the street and rises to them; once they are taken for roofs, it drops."""
        edges = self.edges(gap, slope, step)
        if r < 0 or edges._starts[r] < 0:
            return np.zeros(0)
        if not self.touched(gap, slope, step, alive)[r]:  # no point that left lies beside it
            return edges.drops_of(r)
        key = ("beside", float(gap), float(slope), float(step), int(r), alive.tobytes())
        got = self._edges.get(key)
        if got is None:
            from scipy.spatial import cKDTree

            # an edge point's partners may only be fewer: its pairs are among those of the points
            # that stood at an edge with every owner alive
            at = edges._edge_order[edges._starts[r]:edges._ends[r]]
            pairs = cKDTree(self.plane[at], balanced_tree=False, compact_nodes=False).sparse_distance_matrix(
                self._tree(), gap, output_type="ndarray")
            a, b = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
            keep = edges.region[b] != r
            if self.owners is not None:
                keep &= alive[self.owners[b]]
            lowest = np.full(at.size, np.inf)
            np.minimum.at(lowest, a[keep], self.heights[b[keep]] + float(np.tan(np.radians(slope))) * pairs["v"][keep])
            edge = np.isfinite(lowest)
            got = self.heights[at[edge]] - lowest[edge]
            self._edges[key] = got
        return got

    def touched(self, gap: float, slope: float, step: float, alive: np.ndarray) -> np.ndarray:
        """(regions,) bool: the regions (:meth:`edges`) with a point of an owner no longer alive
        (``alive``: bool, one per owner) beside them, within ``gap``: those whose drops
        :meth:`drops_beside` measures anew; computed once per ``alive``."""
        edges = self.edges(gap, slope, step)
        key = ("touched", float(gap), float(slope), float(step), alive.tobytes())
        got = self._edges.get(key)
        if got is None:
            got = np.zeros(edges.n_regions, dtype=bool)
            gone = np.flatnonzero(~alive[self.owners]) if self.owners is not None else np.zeros(0, np.int64)
            if gone.size:
                from scipy.spatial import cKDTree

                pairs = cKDTree(self.plane[gone], balanced_tree=False, compact_nodes=False).sparse_distance_matrix(
                    self._tree(), gap, output_type="ndarray")
                a, b = gone[pairs["i"]], pairs["j"].astype(np.int64)
                other = edges.region[a] != edges.region[b]
                got[edges.region[b[other]]] = True
            self._edges[key] = got
        return got

    def _tree(self) -> Any:
        """A k-d tree over :attr:`plane`: the surface's own, when a query built it, else one built
        as LocalGround.tree builds it (the same neighbours, ties and all), kept."""
        if self.tree_ is None:
            from scipy.spatial import cKDTree

            object.__setattr__(self, "tree_", cKDTree(self.plane, balanced_tree=False, compact_nodes=False))
        return self.tree_


@dataclass(frozen=True)
class _BlockGrid:
    """Square cells of ``side`` over the plane from ``origin``: ``blocks`` = (lowest height,
    highest height, surface points of the 3 x 3 block) per cell, arrays of ``shape``."""

    origin: np.ndarray
    side: float
    shape: tuple[int, int]
    blocks: tuple[np.ndarray, np.ndarray, np.ndarray]

    def cells_of(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows of ``Q`` (q, 2) inside the grid, their cell rows, their cell columns)."""
        with np.errstate(invalid="ignore"):
            ij = np.floor((Q - self.origin) / self.side)
        inside = np.isfinite(ij).all(axis=1) & (ij >= 0).all(axis=1) & (ij[:, 0] < self.shape[0]) & \
            (ij[:, 1] < self.shape[1])
        k = np.flatnonzero(inside)
        c = ij[k].astype(np.int64)
        return k, c[:, 0], c[:, 1]


@dataclass(frozen=True)
class LocalGround:
    """The ground points, indexed for "which ground is under this point" queries.

    Attributes
    ----------
    normal, point : ndarray (3,)
        The scene's ground plane (heights are along ``normal``, from ``point``).
    index : ndarray (m,) int
        Which points of the scene the model was built from (indices into the scene's cloud).
    heights : ndarray (m,)
        Their heights above the ground plane.
    neighbours : int
    radius : float
        Farther ground points do not count (plus ``per_range`` x the query point's distance to
        ``sensor``).
    owners : ndarray (m,) int
        Which cluster each point came from (an index into ``owner_ids``), so that a cluster can be
        compared with the ground *around* it, its own points left out.
    owner_ids : tuple of str
    per_range : float
        How much the radius grows per unit of a query point's distance to ``sensor`` (0: a fixed
        radius).
    sensor : ndarray (3,) or None
        Where distances are measured from (needed when ``per_range`` > 0).
    quantile : float
        The statistic of the neighbours' heights that is the ground height: 0.5 the median, a
        lower value a lower quantile (linear between the two heights around it).
    """

    normal: np.ndarray
    point: np.ndarray
    index: np.ndarray
    heights: np.ndarray
    neighbours: int
    radius: float
    basis: np.ndarray
    #: the ground points' plane coordinates (m, 2), float64, C-contiguous: what :attr:`tree` holds
    plane: np.ndarray
    owners: np.ndarray | None = None
    owner_ids: tuple[str, ...] = ()
    #: threads of the k-d tree queries (scipy's ``workers``): the answers do not depend on it
    workers: int = 1
    per_range: float = 0.0
    sensor: np.ndarray | None = None
    quantile: float = 0.5
    #: the heights :meth:`height` gave, by ``exclude`` and the points' bytes: the checks of a relabel
    #: measure the same cluster on the same surface with several statistics (airborne: `raised`,
    #: `stands_up`, `joins`), each asking for the same heights
    _heights: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    #: how many more neighbours are fetched when a cluster's own points are left out
    EXCLUDE_FACTOR = 8
    #: the grid search answers while it leaves at most this share of its rows to the k-d tree
    #: (duplicated plane positions, as in GndNet's scans, tie many distances: each row left is asked
    #: twice), judged once it has been asked this many rows; the answers are the same either way
    GRID_MAX_LEFT = 0.1
    GRID_TRIAL = 2000
    #: neighbours fetched per k-d tree query call (16 bytes each): queries go in chunks of
    #: ``QUERY_BUDGET // k`` points
    QUERY_BUDGET = 1 << 20

    @classmethod
    def build(cls, X: np.ndarray, index: np.ndarray, normal: np.ndarray, point: np.ndarray, *,
              neighbours: int = 8, radius: float = 3.0, owners: np.ndarray | None = None,
              owner_ids: tuple[str, ...] = (), workers: int = 1, per_range: float = 0.0,
              sensor: np.ndarray | None = None, quantile: float = 0.5) -> LocalGround:
        """A model from the points ``X[index]`` (the scene ``X`` (n, 3)) over the plane (normal,
        point); ``owners``/``owner_ids`` say which cluster each point came from; ``workers``
        threads answer large queries (the same answers); the radius of a query at distance ``r``
        from ``sensor`` is ``radius + per_range r``; ``quantile`` of the neighbours' heights is the
        ground height (0.5: the median)."""
        normal = np.asarray(normal, dtype=np.float64)
        point = np.asarray(point, dtype=np.float64)
        basis = plane_basis(normal)
        if per_range < 0.0 or not np.isfinite(per_range):
            raise ValueError(f"per_range must be a finite number >= 0, got {per_range}")
        if per_range > 0.0 and sensor is None:
            raise ValueError("a radius growing with range (per_range > 0) needs the sensor's position")
        if not 0.0 <= quantile <= 1.0:
            raise ValueError(f"quantile must be within [0, 1], got {quantile}")
        G = rows(X, index) - point
        return cls(normal=normal, point=point, index=np.asarray(index), heights=G @ normal,
                   neighbours=int(neighbours), radius=float(radius), basis=basis,
                   plane=np.ascontiguousarray(G @ basis.T, dtype=np.float64),
                   owners=None if owners is None else np.asarray(owners), owner_ids=tuple(owner_ids),
                   workers=max(1, int(workers)), per_range=float(per_range),
                   sensor=None if sensor is None else np.asarray(sensor, dtype=np.float64).reshape(3),
                   quantile=float(quantile))

    @property
    def n_points(self) -> int:
        return int(self.index.size)

    @functools.cached_property
    def tree(self) -> Any:
        """A ``scipy.spatial.cKDTree`` over :attr:`plane`, built at its first use: with the compiled
        kernels most surfaces are asked only through their grids (the rows a grid leaves, and the
        reference path without the kernels, ask the tree; the same answers either way)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.plane, balanced_tree=False, compact_nodes=False)

    @functools.cached_property
    def _plane_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The lowest and highest plane coordinates of the surface points (what a k-d tree over
        them holds as its ``mins`` and ``maxes``)."""
        return bounds(self.plane)

    def radii(self, P: np.ndarray) -> np.ndarray | None:
        """The radius of each query point ``P`` (q, 3): ``radius + per_range`` x its distance to
        ``sensor``; None when the radius is fixed (``per_range`` 0)."""
        if not self.per_range > 0.0:
            return None
        assert self.sensor is not None  # build() saw to it
        return self.radius + self.per_range * np.sqrt(((np.asarray(P, dtype=np.float64) - self.sensor) ** 2).sum(axis=1))

    def query(self, P: np.ndarray, exclude: str | None = None, *,
              nearest_of: str = "point", found: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """For points ``P`` (q, 3): the local ground height under each (NaN where no ground point
        lies within ``radius``, see :meth:`radii`) and the position in :attr:`index` of its nearest ground point (-1
        where none). With ``exclude`` (a cluster id), that cluster's own points are left out: among
        the ``EXCLUDE_FACTOR x neighbours`` nearest, the nearest ``neighbours`` of other clusters
        count. ``nearest_of``: what the caller uses of the nearest surface point, its position
        (``'point'``), only its cluster (``'owner'``: of points at the same distance, any one of the
        same cluster may be given) or nothing (``'none'``: any one of them). ``found``: a (q,
        k) int64 array (k the neighbours fetched: :attr:`neighbours`, times :attr:`EXCLUDE_FACTOR`
        with ``exclude``) that receives the positions in :attr:`index` of the surface points each
        height was taken among (:attr:`n_points` where fewer were found; with a radius growing with
        range, some may lie beyond a point's own radius)."""
        first = {"point": 0, "owner": 1, "none": 2}[nearest_of]
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        q = P.shape[0]
        ground = np.full(q, np.nan)
        nearest = np.full(q, -1, dtype=np.int64)
        if q == 0 or self.n_points == 0:
            return ground, nearest
        own = -1
        if exclude is not None and self.owners is not None and exclude in self.owner_ids:
            own = self.owner_ids.index(exclude)
        k = min(self.neighbours * (self.EXCLUDE_FACTOR if own >= 0 else 1), self.n_points)
        Q = np.empty((q, 2))
        for s in range(0, q, 1 << 16):  # plane coordinates, without a (q, 3) temporary
            Q[s:s + (1 << 16)] = minus(P[s:s + (1 << 16)], self.point) @ self.basis.T
        order = self._spatial_order(Q)
        if order is None:
            order = np.arange(q)
        radii = self.radii(P)
        # in chunks of the spatial order: the same answers, asked in an order that keeps the
        # tree's nodes in cache, with the (chunk, k) temporaries bounded whatever q
        step = max(1, self.QUERY_BUDGET // k)
        for s in range(0, q, step):
            sel = order[s:s + step]
            if radii is None:
                d, i = self._knn(rows(Q, sel), k, own, first)
            else:  # the neighbours within the chunk's largest radius, then each point's own
                r = radii[sel]
                d, i = self._knn(rows(Q, sel), k, own, first, float(r.max()))
                d = np.where(d.reshape(sel.size, k) <= r[:, None], d.reshape(sel.size, k), np.inf)
            ground[sel], nearest[sel] = self._medians(d.reshape(sel.size, k), i.reshape(sel.size, k), own)
            if found is not None:
                found[sel] = i.reshape(sel.size, k)
        return ground, nearest

    def _knn(self, Q: np.ndarray, k: int, own: int, first: int = 0,
             radius: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``tree.query(Q, k, distance_upper_bound=radius)`` (default :attr:`radius`) as (q, k) arrays, or the compiled grid
        search's answer (:func:`~kbs.inference._compiled.grid_knn`) for the rows where
        :meth:`_medians` (``own``) gives both the same outputs (the nearest point's position, its
        cluster or nothing: ``first`` 0, 1, 2, see :meth:`query`): the same distances, and the same
        indices up to the order of equal distances where that order changes nothing; the k-d tree
        answers the other rows, and all when the kernels are off or the grid left it more than
        :attr:`GRID_MAX_LEFT` of the rows so far."""
        radius = self.radius if radius is None else radius
        tally = self._knn_tally  # rows asked of the grid, rows it left to the tree
        useful = tally[0] < self.GRID_TRIAL or tally[1] <= self.GRID_MAX_LEFT * tally[0]
        grid = self._grid if _flags.JIT and useful and np.isfinite(Q).all() else None
        if grid is None:
            d, i = self.tree.query(Q, k=k, distance_upper_bound=radius,  # type: ignore[attr-defined]
                                   workers=self.workers if Q.shape[0] >= 4096 else 1)
            return d.reshape(Q.shape[0], k), i.reshape(Q.shape[0], k)
        Q = np.ascontiguousarray(Q)
        T = self.plane
        owners = np.ascontiguousarray(self.owners if self.owners is not None else np.zeros(0), dtype=np.int64)
        rest = (float(radius), self.heights, owners, int(own), int(self.neighbours), int(first))
        if self.workers > 1 and Q.shape[0] >= 4096:  # the kernel releases the GIL: rows in threads, the same answers
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(self.workers) as pool:
                parts = list(pool.map(lambda rows: _compiled.grid_knn(Q[rows], T, *grid, k, *rest),  # type: ignore[call-arg]
                                      np.array_split(np.arange(Q.shape[0]), self.workers)))
            d, i, ok = (np.concatenate([p[j] for p in parts]) for j in range(3))
        else:
            d, i, ok = _compiled.grid_knn(Q, T, *grid, k, *rest)  # type: ignore[call-arg]
        redo = np.flatnonzero(~ok)
        tally[0] += Q.shape[0]
        tally[1] += redo.size
        if redo.size:
            rd, ri = self.tree.query(Q[redo], k=k, distance_upper_bound=radius,  # type: ignore[attr-defined]
                                     workers=self.workers if redo.size >= 4096 else 1)
            d[redo], i[redo] = rd.reshape(redo.size, k), ri.reshape(redo.size, k)
        return d, i

    @functools.cached_property
    def _knn_tally(self) -> list[int]:
        """[rows asked of the grid search, rows it left to the k-d tree] (see :meth:`_knn`)."""
        return [0, 0]

    @functools.cached_property
    def _grid(self) -> tuple | None:
        """The compiled search's grid over the surface's plane coordinates (built once, at the
        first query), or None when none fits."""
        T = self.plane
        if T.shape[0] < 2 or not np.isfinite(T).all():
            return None
        lo, hi = self._plane_bounds
        extent = hi - lo
        area = float(np.prod(np.maximum(extent, extent.max() * 1e-3)))
        *grid, ok = _compiled.plane_grid(np.ascontiguousarray(T), 2.0 * float(np.sqrt(area / T.shape[0])))
        return tuple(grid) if ok else None

    def _medians(self, d: np.ndarray, i: np.ndarray, own: int) -> tuple[np.ndarray, np.ndarray]:
        """The median heights (:attr:`quantile`) and nearest positions of a k-nearest query (``d``,
        ``i`` (q, k), nearest first), ``own`` the owner left out (-1: none)."""
        q = d.shape[0]
        if _flags.JIT:  # the same medians, compiled: one pass over the rows, no (q, k) temporaries
            owners = self.owners if self.owners is not None else np.zeros(0, dtype=np.int64)
            return _compiled.local_medians_fast(np.ascontiguousarray(d), np.ascontiguousarray(i, dtype=np.int64),
                                           self.heights, np.ascontiguousarray(owners, dtype=np.int64), own,
                                           self.neighbours, self.quantile)
        ground = np.full(q, np.nan)
        nearest = np.full(q, -1, dtype=np.int64)
        if own >= 0:  # leave the cluster's own points out, keep the nearest `neighbours` others
            ok = np.isfinite(d)
            ok[ok] = self.owners[i[ok]] != own
            ok &= np.cumsum(ok, axis=1) <= self.neighbours
            order = np.argsort(~ok, axis=1, kind="stable")  # kept ones first, still nearest first
            d = np.where(ok, d, np.inf)
            d, i = np.take_along_axis(d, order, axis=1), np.take_along_axis(i, order, axis=1)
        nf = np.isfinite(d).sum(axis=1)  # neighbours found, nearest first
        some = nf > 0
        if some.any():  # the median of the found heights: sort with the missing ones last
            hs = np.where(np.isfinite(d[some]), self.heights[np.minimum(i[some], self.n_points - 1)], np.inf)
            hs.sort(axis=1)
            r = np.arange(hs.shape[0])
            m = nf[some]
            if self.quantile == 0.5:
                ground[some] = 0.5 * (hs[r, (m - 1) // 2] + hs[r, m // 2])
            else:  # as _compiled.sorted_quantile: linear between the ranks around (m - 1) q, within them
                pos = (m - 1) * self.quantile
                lo = np.floor(pos).astype(np.int64)
                a, b = hs[r, lo], hs[r, np.minimum(lo + 1, m - 1)]
                ground[some] = np.minimum(np.maximum(a + (b - a) * (pos - lo), a), b)
        nearest[some] = i[some, 0]
        return ground, nearest

    def _spatial_order(self, Q: np.ndarray) -> np.ndarray | None:
        """An order of the query points (q, 2) cell by cell (cells of about 16 ground points),
        or None for few queries: k-d tree queries in a spatially coherent order run 1.2-2.5x
        faster than in scan order, with the same answers."""
        q = Q.shape[0]
        if q < 2048:
            return None
        lo, hi = self._plane_bounds
        extent = hi - lo
        area = float(np.prod(np.maximum(extent, extent.max() * 1e-3)))
        side = 4.0 * np.sqrt(area / self.n_points)
        if not side > 0.0:
            return None
        ij = np.floor((Q - Q.min(axis=0)) / side)
        if not np.isfinite(ij).all() or ij.max() >= 2.0**30:
            return None
        key = ij[:, 0] * (ij[:, 1].max() + 1.0) + ij[:, 1]
        return np.argsort(key, kind="stable")

    def height_above_slope(self, P: np.ndarray, slope: float, radius: float, exclude: str | None = None) -> np.ndarray:
        """Heights (q,) of points ``P`` above the lowest terrain that the surface's points within
        ``radius`` (plane distance) allow when the terrain is no steeper than ``slope`` degrees:
        ``h(p) - min_j (h(j) + tan(slope) d(p, j))`` (a slope-based filter: a point on terrain no
        steeper than ``slope`` is at most 0; a roof stands its height less the slope's rise over
        the distance to the ground beside the building). NaN where no surface point lies within
        ``radius``; ``exclude``: a cluster whose own points do not count."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        out = np.full(P.shape[0], np.nan)
        if P.shape[0] == 0 or self.n_points == 0:
            return out
        own = -1
        if exclude is not None and self.owners is not None and exclude in self.owner_ids:
            own = self.owner_ids.index(exclude)
        G = P - self.point
        Q, hp = G @ self.basis.T, G @ self.normal
        rise = float(np.tan(np.radians(slope)))
        cells = self._slope_cells(radius) if _flags.JIT and self.PRUNE else None
        grid = self._slope_grid(radius) if _flags.JIT and cells is None else None
        if cells is not None:  # compiled, on finer cells, lowest bound first: the same minimum, fewer points
            owners = self.owners if own >= 0 else np.zeros(0, dtype=np.int64)
            ny, start, order, lo, side, hmin, box = cells
            lowest = _compiled.slope_lowest_pruned(np.ascontiguousarray(Q), self.plane,
                                                   self.heights, np.asarray(owners, dtype=np.int64), own, ny, start,
                                                   order, lo, side, hmin, box, rise, float(radius), float(radius) ** 2)
            reached = np.isfinite(lowest)
            out[reached] = hp[reached] - lowest[reached]
            return out
        if grid is not None:  # compiled: the same minimum over the same points, without the lists
            owners = self.owners if own >= 0 else np.zeros(0, dtype=np.int64)
            ny, start, order, lo, side = grid
            T = self.plane
            lowest = _compiled.slope_lowest(np.ascontiguousarray(Q), T, self.heights, np.asarray(owners, dtype=np.int64),
                                            own, ny, start, order, lo, side, rise, float(radius) ** 2)
            reached = np.isfinite(lowest)
            out[reached] = hp[reached] - lowest[reached]
            return out
        found = self.tree.query_ball_point(Q, r=radius)  # type: ignore[attr-defined]
        sizes = np.fromiter((len(f) for f in found), dtype=np.int64, count=len(found))
        if not sizes.sum():
            return out
        j = np.concatenate([np.asarray(f, dtype=np.int64) for f in found])
        k = np.repeat(np.arange(P.shape[0]), sizes)
        if own >= 0:
            keep = self.owners[j] != own
            j, k = j[keep], k[keep]
        d = np.sqrt(((self.plane[j] - Q[k]) ** 2).sum(axis=1))
        lowest = np.full(P.shape[0], np.inf)
        np.minimum.at(lowest, k, self.heights[j] + rise * d)
        reached = np.isfinite(lowest)
        out[reached] = hp[reached] - lowest[reached]
        return out

    #: surface points a neighbourhood of :meth:`thickness_within` needs (fewer: no thickness)
    THICKNESS_MIN_POINTS = 8

    def thickness_within(self, P: np.ndarray, radius: float) -> np.ndarray:
        """How rough the surface is around points ``P`` (q, 3): the thickness of the surface's
        points within ``radius`` of each (plane distance), as the ``thickness`` predicate measures
        a cluster (the square root of the smallest eigenvalue of their covariance, their heights
        along :attr:`normal`): a few millimetres on a road, a kerb's step spread over the radius, a
        few centimetres in grass and low plants. NaN where fewer than
        :attr:`THICKNESS_MIN_POINTS` surface points lie within ``radius``."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        out = np.full(P.shape[0], np.nan)
        if P.shape[0] == 0 or self.n_points == 0:
            return out
        G = P - self.point
        Q, hq = np.ascontiguousarray(G @ self.basis.T), np.ascontiguousarray(G @ self.normal)
        grid = self._ball_grid(radius) if _flags.JIT else None
        if grid is not None:  # compiled: the same points, summed in the grid's order
            ny, start, S, lo, side, reach = grid
            rest = (S, ny, start, lo, side, reach, float(radius) ** 2, self.THICKNESS_MIN_POINTS)
            order = self._spatial_order(Q)  # neighbouring queries read the same cells (the same answers)
            if order is not None:
                Q, hq = rows(Q, order), hq[order]
            if self.workers > 1 and Q.shape[0] >= 4096:  # the kernel releases the GIL: rows in threads, the same answers
                from concurrent.futures import ThreadPoolExecutor

                parts = np.array_split(np.arange(Q.shape[0]), self.workers)
                with ThreadPoolExecutor(self.workers) as pool:
                    got = np.concatenate(list(pool.map(
                        lambda part: _compiled.ball_thickness(Q[part], hq[part], *rest), parts)))
            else:
                got = _compiled.ball_thickness(Q, hq, *rest)
            if order is None:
                return got
            out[order] = got
            return out
        found = self.tree.query_ball_point(Q, r=radius)  # type: ignore[attr-defined]
        sizes = np.fromiter((len(f) for f in found), dtype=np.int64, count=len(found))
        some = np.flatnonzero(sizes >= self.THICKNESS_MIN_POINTS)
        if not some.size:
            return out
        j = np.concatenate([np.asarray(found[s], dtype=np.int64) for s in some])
        k = np.repeat(np.arange(some.size), sizes[some])
        D = np.column_stack([self.plane[j] - Q[some][k], self.heights[j] - hq[some][k]])
        n = sizes[some].astype(np.float64)
        m = np.stack([np.bincount(k, D[:, a], minlength=some.size) for a in range(3)], axis=1) / n[:, None]
        S = np.stack([np.bincount(k, D[:, a] * D[:, b], minlength=some.size) for a in range(3) for b in range(3)],
                     axis=1).reshape(-1, 3, 3) / n[:, None, None]
        lam = np.linalg.eigvalsh(S - m[:, :, None] * m[:, None, :])[:, 0]
        out[some] = np.sqrt(np.maximum(lam, 0.0))
        return out

    #: cells of :meth:`_ball_grid` per radius
    BALL_CELLS = 3
    #: at most this many cells in the finer grid of :meth:`_ball_grid` (32 MB of offsets)
    BALL_MAX_CELLS = 1 << 22

    def _ball_grid(self, radius: float) -> tuple | None:
        """The surface points for the compiled :meth:`thickness_within`: ``(ny, start, S, lo,
        side, reach)``, the points (plane coordinates and height, ``S``) in the order of square
        cells of ``side`` a third of ``radius`` (just over), ``reach`` cells around a query's
        holding its disc; built once per radius. Cells as wide as the radius (``reach`` 1) when
        the finer grid would have more than :attr:`BOUND_CELLS_PER_POINT` cells per surface point;
        None when that one would too (the k-d tree answers then). The finer grid may have as many
        cells per surface point as the cells of the radius have in a 3 x 3 block (9 x), up to
        :attr:`BALL_MAX_CELLS`. A third of the radius: on the tiered release's queries of GndNet
        000000, 101 -> 53 ms against a 3 x 3 block of cells as wide as the radius
        (docs/PERFORMANCE.md, session 44)."""
        grids = self._slope_grids
        key = ("ball", radius)
        if key not in grids:
            grids[key] = None
            T = self.plane
            coarse = float(self.BOUND_CELLS_PER_POINT * T.shape[0] + 4096)
            for cells, most in ((self.BALL_CELLS, min(coarse * self.BALL_CELLS ** 2, float(self.BALL_MAX_CELLS))),
                                (1, coarse)):
                side = float(radius) * 1.001 / cells  # ``cells`` of them hold the radius, rounding aside
                if not (side > 0.0 and np.isfinite(side)):
                    break
                ny, start, order, lo = _compiled.surface_grid(T, side, most)
                if ny >= 0:
                    S = np.ascontiguousarray(np.column_stack([rows(T, order), self.heights[order]]))
                    grids[key] = (int(ny), start, S, lo, side, cells)
                    break
        return grids[key]

    def spread_within(self, P: np.ndarray, radius: float) -> np.ndarray | None:
        """For points ``P`` (q, 3): a bound of twice :meth:`thickness_within` (``radius``) without
        finding the surface points within ``radius`` of each: how far apart the points of the
        3 x 3 block of cells of side just over ``radius`` around its cell (which holds them) lie
        across a plane, highest less lowest; -inf where the block holds none. Compiled: across the
        block's least-squares plane (:func:`~kbs.inference._compiled.block_plane_spread`: a tilted
        road measures its noise); otherwise across the horizontal (the spread of the heights).
        None when the grid would have too many cells (see :meth:`height_bounds`)."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        grids = self._spread_grids
        if radius not in grids:
            grids[radius] = self._spread_grid(float(radius) * 1.001) if self.n_points else None
        grid = grids[radius]
        if grid is None:
            return None
        origin, side, spread = grid
        Q = (P - self.point) @ self.basis.T
        out = np.full(P.shape[0], -np.inf)
        with np.errstate(invalid="ignore"):
            ij = np.floor((Q - origin) / side)
        inside = np.isfinite(ij).all(axis=1) & (ij >= 0).all(axis=1) & (ij[:, 0] < spread.shape[0]) & \
            (ij[:, 1] < spread.shape[1])
        k = np.flatnonzero(inside)
        c = ij[k].astype(np.int64)
        out[k] = spread[c[:, 0], c[:, 1]]
        return out

    def _spread_grid(self, side: float) -> tuple[np.ndarray, float, np.ndarray] | None:
        """(origin, side, per cell the spread of its 3 x 3 block) for :meth:`spread_within`."""
        if _flags.JIT:
            laid = self._cells(side, 2)  # as the 3 x 3 blocks of _block_grid
            if laid is None:
                return None
            origin, (nx, ny) = laid
            return origin, side, _compiled.block_plane_spread(self.plane, self.heights, origin, float(side), nx, ny)
        grid = self._block_grid(side, reach=1)
        if grid is None:
            return None
        lo_b, hi_b, _ = grid.blocks
        return grid.origin, grid.side, hi_b - lo_b

    @functools.cached_property
    def _spread_grids(self) -> dict:
        return {}

    def _slope_grid(self, radius: float) -> tuple | None:
        """The surface points in cells of side just over ``radius`` for the compiled
        :meth:`height_above_slope` (``(ny, start, order, lo, side)``, built once per radius), or
        None when the grid would have more than :attr:`BOUND_CELLS_PER_POINT` cells per surface
        point (the k-d tree answers then)."""
        grids = self._slope_grids
        if radius not in grids:
            side = float(radius) * 1.001  # the 3 x 3 block holds the disc of radius, rounding aside
            T = self.plane
            grids[radius] = None
            if side > 0.0 and np.isfinite(side):
                ny, start, order, lo = _compiled.surface_grid(T, side, float(self.BOUND_CELLS_PER_POINT * T.shape[0] + 4096))
                if ny >= 0:
                    grids[radius] = (int(ny), start, order, lo, side)
        return grids[radius]

    @functools.cached_property
    def _slope_grids(self) -> dict:
        return {}

    #: cells of :meth:`_slope_cells` per radius (side ``radius / SLOPE_CELLS``)
    SLOPE_CELLS = 4
    #: whether :meth:`height_above_slope` visits the finer cells lowest bound first (the tests
    #: switch it off to compare with the plain grid)
    PRUNE = True
    #: the finer cells are built when there are at most this many per surface point: a tile's
    #: ground covers its bounding box (the ISPRS and PDAL samples: 0.07-1.15 cells per ground
    #: point at a 10 m radius); a cloud whose box is mostly empty (samples 600 m apart) would fill
    #: memory with empty cells (48 bytes each), and gets the plain grid, which gives the same bits
    SLOPE_CELLS_PER_POINT = 2

    def _slope_cells(self, radius: float) -> tuple | None:
        """The surface points in cells of side ``radius / SLOPE_CELLS`` with each cell's lowest
        height and bounding box, for :func:`~kbs.inference._compiled.slope_lowest_pruned`
        (``(ny, start, order, lo, side, hmin, box)``, built once per radius), or None when the
        grid would have more than :attr:`SLOPE_CELLS_PER_POINT` cells per surface point (the plain
        grid of :meth:`_slope_grid` answers then, with the same bits)."""
        grids = self._slope_grids
        key = ("cells", radius)
        if key not in grids:
            side = float(radius) / self.SLOPE_CELLS
            T = self.plane
            grids[key] = None
            if side > 0.0 and np.isfinite(side):
                ny, start, order, lo, hmin, box = _compiled.slope_cells(
                    T, self.heights, side, float(self.SLOPE_CELLS_PER_POINT * T.shape[0] + 4096))
                if ny >= 0:
                    grids[key] = (int(ny), start, order, lo, side, hmin, box)
        return grids[key]

    #: the block grid of :meth:`height_bounds` is skipped when it would have more cells than this
    #: many per surface point (an extent absurd for the radius)
    BOUND_CELLS_PER_POINT = 4

    def height_bounds(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """For points ``P`` (q, 3): bounds ``(lo, hi)`` of the local ground height :meth:`query`
        can give under each, without a k-d tree query. Two grids of square cells in the plane:

        - cells of side just above ``radius``: the 3 x 3 block around a point's cell holds every
          surface point within ``radius`` of it, so the lowest and highest of them bound any
          median of the heights found; where that block is empty, ``lo`` is +inf and ``hi`` -inf
          (the query finds nothing there);
        - cells of side ``radius / 6``: where the 3 x 3 block around a point's cell holds at least
          ``neighbours`` surface points, its nearest ``neighbours`` are within ``2 sqrt(2)`` cells,
          inside the 7 x 7 block, whose lowest and highest points bound their median more tightly.

        Exact in floating point: a median of heights between ``lo`` and ``hi`` is between them, so
        ``fl(h_p - hi) <= fl(h_p - ground) <= fl(h_p - lo)``: a caller may skip the query of a
        point whose bounds already decide its outcome. None when the coarse grid would be absurdly
        large for the surface (the fine grid is then skipped alone), and when the radius grows with
        range (``per_range``: the coarse grid's cells are one radius wide)."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        if self.n_points == 0 or not self.radius > 0.0 or self.per_range > 0.0:
            return None
        coarse, fine = self._bound_grids
        if coarse is None:
            return None
        q = P.shape[0]
        lo, hi = np.full(q, np.inf), np.full(q, -np.inf)
        need = min(self.neighbours, self.n_points)
        for s in range(0, q, 1 << 16):  # plane coordinates as query() computes them
            Q = (P[s:s + (1 << 16)] - self.point) @ self.basis.T
            if _flags.JIT:  # the same bounds, compiled: no (q,) temporaries per grid
                lo_s, hi_s = lo[s:s + (1 << 16)], hi[s:s + (1 << 16)]
                for grid, narrow in ((coarse, False), (fine, True)):
                    if grid is not None:
                        _compiled.surface_bounds(np.ascontiguousarray(Q), lo_s, hi_s, grid.origin, grid.side,
                                                 *grid.blocks, need, narrow)
                continue
            at, (lo_b, hi_b, _) = coarse.cells_of(Q), coarse.blocks
            lo[s + at[0]], hi[s + at[0]] = lo_b[at[1], at[2]], hi_b[at[1], at[2]]
            if fine is not None:
                at, (lo_b, hi_b, n3) = fine.cells_of(Q), fine.blocks
                ok = n3[at[1], at[2]] >= need
                j, a, b = at[0][ok], at[1][ok], at[2][ok]
                lo[s + j] = np.maximum(lo[s + j], lo_b[a, b])
                hi[s + j] = np.minimum(hi[s + j], hi_b[a, b])
        return lo, hi

    @functools.cached_property
    def _bound_grids(self) -> tuple[_BlockGrid | None, _BlockGrid | None]:
        """The two grids of :meth:`height_bounds` (built once per surface: the post steps ask twice)."""
        coarse = self._block_grid(self.radius * 1.001, reach=1)
        return coarse, None if coarse is None else self._block_grid(self.radius / 6.0, reach=3)

    def _cells(self, side: float, pad: int) -> tuple[np.ndarray, tuple[int, int]] | None:
        """(origin, (nx, ny)) of a grid of cells of ``side`` over the surface's plane coordinates
        with ``pad`` empty rings of cells around them; None when ``side`` is not positive or there
        would be more than :attr:`BOUND_CELLS_PER_POINT` cells per surface point."""
        if not side > 0.0:
            return None
        lo, hi = self._plane_bounds
        origin = lo - pad * side
        cells = np.floor((hi - origin) / side) + pad + 1  # floats: may be huge
        if float(cells[0]) * float(cells[1]) > self.BOUND_CELLS_PER_POINT * self.plane.shape[0] + 4096:
            return None
        return origin, (int(cells[0]), int(cells[1]))

    def _block_grid(self, side: float, reach: int) -> _BlockGrid | None:
        """The surface on cells of ``side``: per cell, the lowest and highest height over the
        (2 reach + 1)^2 block around it and the number of surface points of the 3 x 3 block; None
        when there would be more than :attr:`BOUND_CELLS_PER_POINT` cells per surface point."""
        T = self.plane  # the surface points' plane coordinates
        laid = self._cells(side, reach + 1)
        if laid is None:
            return None
        origin, shape2 = laid
        shape = np.array(shape2, dtype=np.int64)
        if _flags.JIT:  # the same arrays, compiled: one pass over the points, no sort
            blocks = _compiled.surface_blocks(T, self.heights, origin, float(side), shape2[0], shape2[1], reach)
            return _BlockGrid(origin, side, shape2, blocks)
        ij = np.floor((T - origin) / side).astype(np.int64)
        cell = ij[:, 0] * shape[1] + ij[:, 1]
        size = int(shape[0] * shape[1])
        lo_c, hi_c = np.full(size, np.inf), np.full(size, -np.inf)
        order = np.argsort(cell, kind="stable")  # per occupied cell: a run of the sorted cells
        cs, hs = cell[order], self.heights[order]
        starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
        lo_c[cs[starts]] = np.minimum.reduceat(hs, starts)
        hi_c[cs[starts]] = np.maximum.reduceat(hs, starts)
        n_c = np.bincount(cell, minlength=size).astype(np.float64)
        blocks = (_slide(lo_c.reshape(shape2), reach, np.minimum), _slide(hi_c.reshape(shape2), reach, np.maximum),
                  _slide(n_c.reshape(shape2), 1, np.add))
        return _BlockGrid(origin, side, shape2, blocks)

    @functools.cached_property
    def regions(self) -> SurfaceRegions:
        """Where the continuous surfaces (:meth:`edges`) are measured: this surface's points, or
        those of the surface a relabel step started from (:meth:`measure_regions_on`)."""
        # the surface's k-d tree if a query built it (held by reference: not the whole surface);
        # otherwise the regions build the same tree when their edges are first asked for
        return SurfaceRegions(self.plane, self.heights, self.owners, self.owner_ids, self.__dict__.get("tree"))

    def measure_regions_on(self, regions: SurfaceRegions | None) -> None:
        """Measure the continuous surfaces on ``regions`` (those of an earlier surface) instead of
        this surface's points: a relabel step judging its rules again on a surface rebuilt without
        the clusters it moved keeps the surfaces as the step found them (a roof whose outer patches
        were taken is still the roof whose streets enclose it, not the patch left). None: on this
        surface's own points again (the step is over; a later step finds its own surfaces)."""
        if regions is None:
            self.__dict__.pop("regions", None)
        else:
            self.__dict__["regions"] = regions

    def owners_alive(self) -> np.ndarray:
        """(owners of :attr:`regions`,) bool: which of the owners the continuous surfaces are
        measured on are owners of this surface (all, unless it measures on an earlier surface's
        regions and some clusters left it since); computed once."""
        regions = self.regions
        got = self.__dict__.get("_owners_alive")
        if got is None or got[0] is not regions:
            alive = np.zeros(len(regions.owner_ids), dtype=bool)
            index = regions.owner_index
            for oid in self.owner_ids:
                k = index.get(oid)
                if k is not None:
                    alive[k] = True
            got = (regions, alive)
            self.__dict__["_owners_alive"] = got
        return got[1]

    def edges(self, gap: float, slope: float, step: float) -> SurfaceEdges:
        """The surface's points grouped into continuous surfaces and their edges' drops (see
        :class:`SurfaceEdges`), built at the first call for these parameters (on :attr:`regions`)."""
        return self.regions.edges(gap, slope, step)

    def height(self, P: np.ndarray, exclude: str | None = None) -> np.ndarray:
        """Heights (q,) of points ``P`` above the local ground surface (NaN where it is unknown);
        ``exclude``: a cluster whose own points do not count (see :meth:`query`). Read-only: the
        same points asked again get the same array."""
        P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 3)
        key = (exclude, hashlib.blake2b(P.tobytes(), digest_size=16).digest())
        h = self._heights.get(key)
        if h is None:
            ground, _ = self.query(P, exclude, nearest_of="none")
            h = (P - self.point) @ self.normal - ground
            h.flags.writeable = False  # shared by the callers that ask again
            self._heights[key] = h
        return h
