"""Connexity kernel of the CAh heuristic ("connexity ambiguity", ../shared/ALGORITHMS.md section 3).

Obstacles that emerge from the ground and look alike may be gathered in one cluster. Projected
on the cluster's best approximating plane (BAP), such a cluster falls apart into several blobs:
counting the significant connected components of the projection detects the ambiguity, and the
components are the natural split.

Two methods find the components (``method``): ``'graph'`` (the default, and what the shipped
rule bases use), an approximation on the points of the alpha-complex and of its opening, and
``'alpha_opening'``, the paper's alpha-shape opened by a disc (section "The alpha-opening"
below). Steps 1, 2 and 5 are common to both.

Method ``'graph'``
------------------
1. Project the points on the plane through ``center`` with normal ``normal``
   (:func:`project_on_plane`). Exact duplicates (after projection) are merged into one position
   with a multiplicity; every count below still counts input points.
2. ``alpha`` (a length) is ``alpha_factor`` times the *spacing*: the median, over the distinct
   positions, of the distance to the nearest other distinct position (unless ``alpha`` is given).
3. The connected components of the alpha-complex are those of the graph
   ``{(p, q): |p - q| <= 2 alpha}``; they are computed exactly without listing most of that
   graph's edges (a cell grid, see :func:`graph_components`).
4. Morphological opening of that graph, the analogue on the points of the triangulation version
   (remove the triangles touching the boundary, add back those sharing a vertex with what
   remains):

   - *erosion*: the degree of a point is its number of other points within ``2 alpha`` (its
     neighbours in the graph); ``k_min = erosion_fraction * (median degree over all points)``;
     a point stays when its degree is at least ``k_min``. Above 4,096 distinct positions the
     median is taken over 4,096 of them, evenly spread in order of distance to their centroid
     (so it depends neither on the input order nor on a rigid motion).
   - *dilation*: every removed point with a kept point within ``2 alpha`` is added back.

   With the defaults (``alpha = 3`` spacings, ``erosion_fraction = 0.3``) on a regular sampling
   of step h, an interior point has about ``pi (2 alpha)^2 / h^2 ~ 110`` neighbours, a point of
   a straight boundary half of that (it stays), a point of a one-point-wide line of step h
   about ``4 alpha / h = 12`` (0.11 of the median: removed), of a two-point-wide one 0.21
   (removed), of a three-point-wide one 0.32 (stays). So blob shapes survive (what the erosion
   takes from their boundary, sharp corners, the dilation gives back) while bridges one or two
   sampling steps wide are cut: their middle is eroded and the dilation only restores their
   ends. On a random (Poisson) sampling the median nearest-neighbour distance is only about
   half the mean spacing, so a disc of radius ``2 alpha`` holds ~26 points and a line sampled
   at the mean spacing ~6 (0.22: cut), but a line sampled at 0.6 of the mean spacing survives.
   Like any opening, it removes whole components smaller than the structuring element (specks
   of fewer than ``k_min + 1`` points). The reference (the median degree) is global: a part of
   the cluster with 3.5 to 4 times fewer points per unit area than most of it (farther from the
   sensor) is eroded away; lower ``erosion_fraction`` for clouds with strong density gradients.
5. Components are computed on the opened points and numbered by decreasing size (0 = largest;
   ties go to the component holding the lexicographically smallest projected position). A
   component is significant when its size (points, or summed ``sample_weight``) is at least
   ``max(min_points, min_fraction * total)``, ``total`` being the size of the whole cluster.
   Because the test is monotone in the size, the significant components are exactly the labels
   ``0 .. n_significant - 1``.

Points removed by the opening and not restored, and isolated points (no other point within
``2 alpha``), get the label ``-1`` and count in no component's size. A caller that splits the
cluster along its components gives every point the label of its nearest point in a significant
component with :func:`assign_to_nearest` (points of non-significant components too), so the
split partitions the cluster exactly into ``n_significant`` parts.

Cost: the degrees are counted only where a cheap cell-count lower bound does not settle the
erosion, and the components only list edges along gaps; 100,000 points take about 0.15-0.2 s
on one core, with memory linear in the number of points.

The alpha-opening (method ``'alpha_opening'``)
----------------------------------------------
The paper's operators, on the shape rather than on the points:

1. The *alpha-complex* (:func:`alpha_complex`): the triangles of scipy's Delaunay triangulation of
   the distinct projected positions whose circumradius is at most ``alpha`` (their edges are then
   at most ``2 alpha``). The *alpha-shape* (:func:`alpha_shape`) is their union, a shapely
   (Multi)Polygon with holes: the triangles meet edge to edge, so it is a coverage union
   (``shapely.coverage_union_all``), exact and 2-5 times cheaper than a general union. (Building
   it from the boundary edges instead is no better: ``shapely.polygonize`` returns the holes as
   faces too, and ``shapely.build_area``, which sorts them out, costs as much as the coverage
   union and fills holes that touch the outline at a vertex, 21 of 169 real calls;
   ``benchmarks/bench_connexity.py``.) Points that make no triangle (a line of points, a
   strand too sparse for alpha) are no part of the shape.
2. The *opening* by a disc of radius ``rho`` (:func:`alpha_opening`): the alpha-erosion
   ``buffer(-rho)`` keeps the centres of the discs of radius ``rho`` that fit inside the shape;
   the alpha-dilation ``buffer(rho)`` puts the discs back. What is left is the union of the discs
   that fit: a part narrower than ``2 rho`` disappears (a bridge of width ``w`` is cut exactly
   when ``w < 2 rho``), and so do specks smaller than the disc; convex corners are rounded.
   ``rho = opening_factor * alpha`` (default 1), or ``opening_radius`` in length units; 0 (or
   ``opening=False``) counts the components of the alpha-shape itself. The radius is a multiple
   of alpha, not a length in the rule file, because alpha is itself a multiple of the cluster's
   own sampling step: the shape is only resolved to about alpha (the complex bridges gaps up to
   ``2 alpha``), so a fixed length would be a no-op on sparse far clusters of a LiDAR frame and
   too strong on dense near ones, and a multiple keeps the measure independent of the density,
   the unit and the scale, as the rest of this module is. ``Connexity.opening_radius`` records
   the length used.
3. The components are the polygons of the opened shape. A point belongs to the one it lies in,
   or within ``0.2 rho`` of: the opening rounds the convex corners of the outline, whose vertices
   are sample points (a corner of angle ``t`` moves in by ``rho (1 / sin(t / 2) - 1)``, 0.155
   rho at 120 degrees), and GEOS draws the arcs of the dilation with chords and simplifies its
   input by 1 % of rho. Points in removed parts (bridges, spurs, specks) get ``-1``; sizes,
   numbering, significance and :func:`assign_to_nearest` are as in step 5 above. A cluster whose
   shape has no part ``2 rho`` wide has no component at all (``n_significant = 0``).

With the defaults (``alpha = 3`` spacings, ``rho = alpha``) a bridge is cut when narrower than
6 spacings, where the graph's opening cuts 1 or 2 rows of points: nearly touching obstacles are
separated. The price: Delaunay, the union and two buffers cost 3-10 times the graph version per
call (``benchmarks/bench_connexity.py``), and on LiDAR frames, where the median spacing is that
along the scan lines, sparse parts fall out of the shape. Measured with the outdoor rules
(docs/BENCHMARKS.md), it lowers the ground F1 of one GndNet scan by 0.004 and adds about 30 % to
the frame time, so the shipped rule bases keep ``'graph'``.
"""
from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from kbs.arrays import rows
from kbs.errors import FitError, ParameterError
from kbs.geometry.nearest import nearest_label
from kbs.inference import _flags
from kbs.inference.voxel import bounds

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def _kdtree(*args, **kwargs) -> cKDTree:
    """scipy's ``cKDTree``, imported when first needed: importing kbs (``kbs explain``, ``kbs
    rules``) does not load scipy."""
    from scipy.spatial import cKDTree

    return cKDTree(*args, **kwargs)

__all__ = ["METHODS", "Connexity", "alpha_complex", "alpha_opening", "alpha_shape", "assign_to_nearest", "connexity",
           "edge_components", "graph_components", "project_on_plane"]

_OWNER = "connexity"
#: How the components are found: the graph of links ``<= 2 alpha`` opened by neighbour counts
#: (the default), or the paper's alpha-shape opened by a disc.
METHODS = ("graph", "alpha_opening")
#: Most index pairs listed at once (16 bytes each, about 80 MB); larger neighbourhoods are walked
#: in pieces.
_PAIR_BUDGET = 5_000_000

#: Distinct positions on which the median degree (the erosion's reference) is measured.
_MEDIAN_SAMPLE = 4096
#: Half of the cells whose points are all within ``r`` of every point of a cell of side ``r / 5``
#: (itself excluded): ``(|dx| + 1)^2 + (|dy| + 1)^2 <= 25``, 45 cells in all.
_LOWER_OFFSETS = tuple(
    (dx, dy)
    for dx in range(0, 4)
    for dy in range(-3, 4)
    if (dx > 0 or dy > 0) and (abs(dx) + 1) ** 2 + (abs(dy) + 1) ** 2 <= 25
)

#: Offsets (half of the symmetric set) between grid cells of side ``r / (2 sqrt 2)`` whose points
#: are always within ``r`` of each other: the 8-neighbourhood.
_SURE_OFFSETS = ((1, 0), (0, 1), (1, 1), (1, -1))
#: Every other offset at which two points within ``r`` can lie (|dx|, |dy| <= 3), half the set.
_UNSURE_OFFSETS = tuple(
    (dx, dy)
    for dx in range(0, 4)
    for dy in range(-3, 4)
    if (dx > 0 or dy > 0) and (dx, dy) not in _SURE_OFFSETS
)


@dataclass(frozen=True)
class Connexity:
    """Connected components of a cluster projected on its best approximating plane.

    Attributes
    ----------
    n_components : int
        Connected components of the (opened) alpha-complex graph, all sizes.
    n_significant : int
        Components whose size passes the significance test; they are the labels
        ``0 .. n_significant - 1``.
    labels : ndarray (n,) int64
        Component of each input point, numbered by decreasing size (0 = largest); ``-1`` for the
        points in no component (removed by the opening and not restored, or isolated). Points of
        non-significant components keep their label. See :func:`assign_to_nearest`.
    significant : ndarray (n_components,) bool
        Significance of each component, indexed by label.
    sizes : ndarray (n_components,)
        Points per component (int64), or summed ``sample_weight`` (float64) when weights are
        given; points labelled ``-1`` count in none.
    alpha : float
        The alpha actually used, in length units (edges are ``|p - q| <= 2 alpha``; the
        triangles of the alpha-complex have a circumradius ``<= alpha``).
    spacing : float
        Median nearest-neighbour spacing of the projected points, exact duplicates ignored:
        the median over the distinct positions of the distance to the nearest other one (0 when
        all the points project on one position).
    method : str
        ``'graph'`` or ``'alpha_opening'`` (see the module docstring).
    opening_radius : float or None
        With ``'alpha_opening'``: the radius of the disc of the opening actually used, in length
        units (0 without opening); None with ``'graph'``, whose opening counts neighbours.
    """

    n_components: int
    n_significant: int
    labels: np.ndarray
    significant: np.ndarray
    sizes: np.ndarray
    alpha: float
    spacing: float
    method: str = "graph"
    opening_radius: float | None = None


def _check_vector(v, name: str) -> np.ndarray:
    try:
        arr = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{_OWNER}: {name} must be a numeric vector of length 3: {exc}") from exc
    if arr.shape != (3,):
        raise ParameterError(f"{_OWNER}: {name} must have shape (3,); got {arr.shape}.")
    if not np.isfinite(arr).all():
        raise ParameterError(f"{_OWNER}: {name} contains NaN or infinite values: {arr.tolist()}.")
    return arr


def _check_cloud(X) -> np.ndarray:
    try:
        arr = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{_OWNER}: X must be a numeric array of shape (n_points, 3): {exc}") from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ParameterError(f"{_OWNER}: X must have shape (n_points, 3); got {arr.shape}.")
    if arr.shape[0] == 0:
        raise FitError("connexity of an empty cluster")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise ParameterError(
            f"{_OWNER}: X contains NaN or infinite values in {bad} rows; drop them first "
            "(kbs.io.read_cloud does so)."
        )
    return arr


def _check_real(value, name: str, *, low: float, high: float | None = None,
                low_open: bool = False) -> float:
    ok = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    if ok:
        v = float(value)
        ok = not math.isnan(v) and (v > low if low_open else v >= low) and (high is None or v <= high)
    if not ok:
        left = "(" if low_open else "["
        right = "inf)" if high is None else f"{high:g}]"
        raise ParameterError(
            f"The {name!r} parameter of {_OWNER} must be a float in the range {left}{low:g}, {right}. "
            f"Got {value!r} instead."
        )
    return float(value)


def _plane_basis(normal: np.ndarray) -> np.ndarray:
    """Orthonormal basis (2, 3) of the plane with that normal; deterministic."""
    norm = float(np.linalg.norm(normal))
    if not norm > 0.0:
        raise ParameterError(f"{_OWNER}: the plane normal must be a non-zero vector; got {normal.tolist()}.")
    n = normal / norm
    a = np.zeros(3)
    a[int(np.argmin(np.abs(n)))] = 1.0  # the axis least aligned with n
    u = a - (a @ n) * n
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return np.stack([u, v])


def project_on_plane(X, center, normal) -> np.ndarray:
    """In-plane coordinates of points projected on a plane.

    Parameters
    ----------
    X : array-like (n, 3)
        Points.
    center : array-like (3,)
        A point of the plane (the cluster's centre); it becomes the origin.
    normal : array-like (3,)
        Normal of the plane (normalised here; must not be zero).

    Returns
    -------
    ndarray (n, 2)
        Coordinates in an orthonormal basis ``(u, v)`` of the plane: ``u`` is the coordinate axis
        least aligned with the normal, made orthogonal to it, and ``v = normal x u``. Distances
        between projected points are those between the orthogonal projections in 3D.
    """
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ParameterError(f"{_OWNER}: X must have shape (n_points, 3); got {X.shape}.")
    center = _check_vector(center, "center")
    basis = _plane_basis(_check_vector(normal, "normal"))
    D = X - center
    # Column by column rather than a matrix product: no BLAS threads for a (n, 3) x (3, 2) product.
    return np.stack([D[:, 0] * b[0] + D[:, 1] * b[1] + D[:, 2] * b[2] for b in basis], axis=1)


@dataclass(frozen=True)
class _Distinct:
    """The distinct positions of a projected cloud, in a spatially coherent order.

    Input point ``order[i]`` lies at ``points[point_of[i]]``; ``mult`` (m,) counts the input
    points at each of the m distinct positions; ``tree`` is a k-d tree over ``points``,
    ``tree_all`` one over all the input points (the same tree without duplicates), and
    ``spacing`` the median (over distinct positions) distance to the nearest other one (0 when
    m = 1). Visiting the points cell by cell makes the k-d tree queries ~30 % faster than a
    random order. The trees are built when first asked (a vehicle frame's connexity measures,
    answered by the compiled kernels, built 149 of them a frame and asked none).
    """

    points: np.ndarray
    mult: np.ndarray
    order: np.ndarray
    point_of: np.ndarray
    spacing: float
    #: every input point's position, in a spatially coherent order (``points`` when none repeats)
    all_points: np.ndarray
    #: a k-d tree over ``points`` already built (by the search of the nearest distances), or None
    built: cKDTree | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def tree(self) -> cKDTree:
        """The k-d tree over ``points``, built when first asked: the compiled components
        (:func:`_compiled_opening_components`) answer without it."""
        if self.built is not None:
            return self.built
        return _kdtree(self.points, balanced_tree=False, compact_nodes=False)

    @functools.cached_property
    def tree_all(self) -> cKDTree:
        """The k-d tree over every input point (the same tree as :attr:`tree` when no position
        repeats; only counts are asked of it, so its order is moot), built when first asked."""
        if self.all_points is self.points:
            return self.tree
        return _kdtree(self.all_points, balanced_tree=False, compact_nodes=False)


def _nearest_other(S: np.ndarray, side: float) -> tuple[np.ndarray, cKDTree | None]:
    """The distance from each row of ``S`` (n, 2) to its nearest other row: ``tree.query(S,
    k=2)[0][:, 1]`` of a k-d tree over ``S``, the same values bit for bit from the compiled grid
    search (:func:`~kbs.inference._compiled.nearest_other_distances`, cells of ``side``) when the
    kernels are on and the grid fits (about 4x faster on a vehicle frame's connexity calls). Also
    the tree, when one was built (None: the grid answered)."""
    if _flags.JIT and S.dtype == np.float64 and np.isfinite(S).all():
        from kbs.inference import _compiled

        d, ok = _compiled.nearest_other_distances(np.ascontiguousarray(S), float(side))
        if ok:
            return d, None
    tree = _kdtree(S, balanced_tree=False, compact_nodes=False)
    return tree.query(S, k=2)[0][:, 1], tree


def _distinct(P: np.ndarray) -> _Distinct:
    n = P.shape[0]
    lo, hi = bounds(P)
    extent = hi - lo
    area = float(np.prod(np.maximum(extent, extent.max() * 1e-3)))
    side = 4.0 * math.sqrt(area / n)
    if side > 0.0:  # cells of about 16 points, row by row
        ij = np.floor((P - lo) / side)
        key = ij[:, 0] * (float(ij[:, 1].max()) + 1.0) + ij[:, 1]
        order = np.argsort(key, kind="stable")
    else:  # a single position
        order = np.arange(n)
    S = rows(P, order)
    if n < 2:
        return _Distinct(S, np.ones(n, dtype=np.int64), order, np.arange(n), 0.0, S)
    d, tree = _nearest_other(S, side)
    if d.min() > 0.0:  # no duplicate: the common case
        return _Distinct(S, np.ones(n, dtype=np.int64), order, np.arange(n), float(np.median(d)), S, tree)
    # Exact duplicates: merge them (x, y sorted within each cell) and measure again.
    sub = np.lexsort((S[:, 1], S[:, 0], key[order])) if side > 0.0 else np.arange(n)
    order = order[sub]
    S = rows(S, sub)
    first = np.ones(n, dtype=bool)
    first[1:] = (S[1:] != S[:-1]).any(axis=1)
    point_of = np.cumsum(first) - 1
    U = rows(S, first)
    tree = None
    spacing = 0.0
    if U.shape[0] > 1:
        d, tree = _nearest_other(U, side)
        spacing = float(np.median(d))
    return _Distinct(U, np.bincount(point_of), order, point_of, spacing, S, tree)


def edge_components(n: int, i: np.ndarray, j: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the graph on ``n`` nodes with the edges ``(i, j)``, numbered as
    scipy's ``connected_components`` numbers them (compiled when the kernels are on)."""
    if _flags.JIT:
        from kbs.inference import _compiled

        n_comp, comp = _compiled.graph_labels(int(n), np.ascontiguousarray(i, dtype=np.int64),
                                              np.ascontiguousarray(j, dtype=np.int64))
        return int(n_comp), comp
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(i.size, dtype=np.int8), (i, j)), shape=(n, n)).tocsr()
    return connected_components(graph, directed=False)


@dataclass(frozen=True)
class _Grid:
    """Square cells of one side over 2D points.

    ``codes`` (n_cells,) are the sorted codes of the non-empty cells, ``cell`` (m,) the cell of
    each point (an index into ``codes``) and ``width`` the code of one step in x. ``table``, when
    the bounding box holds few enough cells, maps every code to its cell index (-1 for an empty
    cell), so that neighbour look-ups are direct instead of binary searches.
    """

    codes: np.ndarray
    cell: np.ndarray
    width: int
    table: np.ndarray | None

    @classmethod
    def build(cls, P: np.ndarray, side: float) -> _Grid | None:
        """The grid, or None when the extent is absurd for that side (codes would overflow).
        Offsets of up to 4 cells stay inside the code range."""
        ij = np.floor((P - P.min(axis=0)) / side)
        width = float(ij[:, 1].max()) + 9.0
        total = (float(ij[:, 0].max()) + 9.0) * width
        if total >= 2.0**62:
            return None
        ij = ij.astype(np.int64) + 4
        code = ij[:, 0] * int(width) + ij[:, 1]
        if total <= 32.0 * P.shape[0] + 65536.0:  # at most 128 bytes a point
            occupied = np.zeros(int(total), dtype=bool)
            occupied[code] = True
            codes = np.flatnonzero(occupied)
            table = np.full(int(total), -1, dtype=np.int32)
            table[codes] = np.arange(codes.size, dtype=np.int32)
            return cls(codes=codes, cell=table[code], width=int(width), table=table)
        codes, cell = np.unique(code, return_inverse=True)
        return cls(codes=codes, cell=cell.ravel(), width=int(width), table=None)

    def neighbours(self, offsets) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (a, b) of non-empty cells with ``b = a + offset``, for each offset (dx, dy)."""
        src, dst = [], []
        n_cells = self.codes.size
        for dx, dy in offsets:
            target = self.codes + (dx * self.width + dy)
            if self.table is not None:
                pos = self.table[target]
                hit = pos >= 0
            else:
                pos = np.minimum(np.searchsorted(self.codes, target), n_cells - 1)
                hit = self.codes[pos] == target
            src.append(np.flatnonzero(hit))
            dst.append(pos[hit])
        return np.concatenate(src), np.concatenate(dst)


def _pair_pieces(P: np.ndarray, tree: cKDTree, r: float) -> list[tuple[int, int]] | None:
    """How to list the pairs within ``r``: None for one k-d tree pair query (expected to give
    at most ``_PAIR_BUDGET`` pairs), or runs ``(start, stop)`` of consecutive points to query one
    at a time (each expected to give about ``_PAIR_BUDGET / 4`` pairs), so that memory stays
    bounded when the neighbourhoods are large (a dense part of a scan, a large explicit alpha).

    The number of neighbours is measured on every k-th point (about 2,000 of them) and
    interpolated to the runs between them; the plan changes the cost only, never the pairs.
    """
    m = P.shape[0]
    stride = max(1, m // 2048)
    sample = tree.query_ball_point(P[::stride], r, return_length=True).astype(np.float64) * stride
    if sample.sum() <= 2.0 * _PAIR_BUDGET:  # ordered pairs, self included
        return None
    load = np.cumsum(sample)
    step = 0.5 * _PAIR_BUDGET  # ordered pairs of a run: ~24 bytes each while listed
    cuts = np.searchsorted(load, np.arange(step, load[-1], step)) * stride
    bounds = np.unique(np.concatenate(([0], cuts, [m])))
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _pairs(P: np.ndarray, tree: cKDTree, r: float, pieces: list[tuple[int, int]] | None):
    """Yield arrays (k, 2) of the index pairs ``i < j`` with ``|P_i - P_j| <= r``, each pair
    once, following the plan of :func:`_pair_pieces`."""
    if pieces is None:
        yield tree.query_pairs(r, output_type="ndarray")
        return
    for start, stop in pieces:
        near = _kdtree(P[start:stop]).sparse_distance_matrix(tree, r, output_type="ndarray")
        i = near["i"] + start
        j = near["j"]
        keep = i < j
        yield np.stack((i[keep], j[keep]), axis=1)


def graph_components(P: np.ndarray, r: float) -> tuple[int, np.ndarray]:
    """Connected components of the graph ``{(p, q): |p - q| <= r}`` on 2D points.

    Exact, without listing most edges: the points are binned in square cells of side
    ``r / (2 sqrt 2)``; points of a cell and of 8-adjacent cells are always within ``r`` of each
    other, so the components of the cell adjacency ("pieces") are parts of true components.
    Only cells with a non-adjacent neighbour cell (up to 3 cells away) in another piece can hold
    a missing edge: the exact pairs are listed among their points only (k-d tree pair queries),
    which in a dense cloud is a thin band along the gaps.

    Parameters
    ----------
    P : ndarray (m, 2)
        Points (spatially sorted points are fastest).
    r : float
        Link distance (``2 alpha``), > 0.

    Returns
    -------
    n_components : int
    labels : ndarray (m,) int
        Component of each point (arbitrary numbering).
    """
    P = np.asarray(P, dtype=np.float64)
    m = P.shape[0]
    if m == 0:
        return 0, np.zeros(0, dtype=np.int64)
    # A cell side a hair below r / (2 sqrt 2), so that rounding never breaks the "sure" offsets.
    grid = _Grid.build(P, r / (2.0 * math.sqrt(2.0)) * (1.0 - 1e-9))
    if grid is None:  # absurd extent for r: list the pairs
        n_pieces, piece, cell, idx = m, np.arange(m), np.arange(m), np.arange(m)
    else:
        a, b = grid.neighbours(_SURE_OFFSETS)
        n_pieces, piece = edge_components(grid.codes.size, a, b)
        cell = grid.cell
        if n_pieces == 1:
            return 1, np.zeros(m, dtype=np.int64)
        a, b = grid.neighbours(_UNSURE_OFFSETS)
        across = piece[a] != piece[b]
        if not across.any():
            return n_pieces, piece[cell]
        band = np.zeros(grid.codes.size, dtype=bool)
        band[a[across]] = True
        band[b[across]] = True
        idx = np.flatnonzero(band[cell])
    Q = rows(P, idx)
    tree = _kdtree(Q)
    src, dst = [], []
    for pairs in _pairs(Q, tree, r, _pair_pieces(Q, tree, r)):
        pa, pb = piece[cell[idx[pairs[:, 0]]]], piece[cell[idx[pairs[:, 1]]]]
        keep = pa != pb
        src.append(pa[keep])
        dst.append(pb[keep])
    n_comp, comp = edge_components(n_pieces, np.concatenate(src), np.concatenate(dst))
    return n_comp, comp[piece[cell]]


def _median_sample(U: np.ndarray) -> np.ndarray:
    """Indices of the distinct positions on which the median degree is measured: all of them up
    to ``_MEDIAN_SAMPLE``, else that many, evenly spread in order of distance to their centroid
    (a choice that depends on the positions only: not on the input order, nor on a rotation)."""
    m = U.shape[0]
    if m <= _MEDIAN_SAMPLE:
        return np.arange(m)
    c = U - U.mean(axis=0)
    key = np.einsum("ij,ij->i", c, c)
    return np.argsort(key, kind="stable")[(np.arange(_MEDIAN_SAMPLE) * m) // _MEDIAN_SAMPLE]


def _degree_lower_bounds(U: np.ndarray, mult: np.ndarray, r: float) -> np.ndarray:
    """Lower bounds (m,) of the number of other input points within ``r`` of each distinct
    position (``mult`` input points at each).

    Cells of side ``r / 5``: two points in cells ``(dx, dy)`` apart are always within ``r``
    when ``(|dx| + 1)^2 + (|dy| + 1)^2 <= 25`` (45 cells, ~0.57 of the disc), so the points of
    those cells are neighbours for sure."""
    grid = _Grid.build(U, 0.2 * r * (1.0 - 1e-9))
    if grid is None:
        return np.zeros(U.shape[0])
    count = np.bincount(grid.cell, weights=mult, minlength=grid.codes.size)
    a, b = grid.neighbours(_LOWER_OFFSETS)
    block = count + np.bincount(a, weights=count[b], minlength=count.size)
    block += np.bincount(b, weights=count[a], minlength=count.size)
    return block[grid.cell] - 1.0


def _opening(D: _Distinct, r: float, erosion_fraction: float) -> np.ndarray:
    """Mask (m,) of the distinct positions kept by the opening of the graph of link distance r.

    The degree of an input point is its number of other input points within ``r`` (duplicates
    included); ``k_min`` is ``erosion_fraction`` times its median over the input points at the
    positions of :func:`_median_sample`. Erosion keeps the points with ``degree >= k_min``;
    dilation adds back the removed points with a kept point within ``r``.

    Degrees are counted only where needed: on the sample, and where a cheap lower bound does
    not already reach ``k_min`` (near boundaries, in thin or sparse parts).
    """
    U, mult, tree = D.points, D.mult, D.tree
    m = U.shape[0]
    sample = _median_sample(U)
    degree = D.tree_all.query_ball_point(U[sample], r, return_length=True) - 1
    k_min = erosion_fraction * float(np.median(np.repeat(degree, mult[sample])))
    kept = _degree_lower_bounds(U, mult, r) >= k_min
    unsure = np.flatnonzero(~kept)
    kept[unsure] = D.tree_all.query_ball_point(U[unsure], r, return_length=True) - 1 >= k_min
    removed = np.flatnonzero(~kept)
    if removed.size == 0 or removed.size == m:
        return kept
    # Dilation: a removed point comes back when a kept point lies within r.
    bound = np.nextafter(r, np.inf)
    if removed.size * 8 < m:  # few: the nearest kept point among the k nearest of all points
        back = np.zeros(removed.size, dtype=bool)
        todo = np.arange(removed.size)
        k = 8
        while todo.size:
            d, j = tree.query(U[removed[todo]], k=min(k, m), distance_upper_bound=bound)
            near = (d <= r) & kept[np.minimum(j, m - 1)]
            back[todo[near.any(axis=1)]] = True
            # undecided: all k within r and none kept: look further
            todo = todo[~near.any(axis=1) & (d[:, -1] <= r)] if k < m else todo[:0]
            k *= 4
    else:
        d, _ = _kdtree(U[kept]).query(U[removed], k=1, distance_upper_bound=bound)
        back = d <= r
    kept[removed[back]] = True
    return kept


def _compiled_opening_components(D: _Distinct, r: float, erosion_fraction: float, opening: bool):
    """The opening (:func:`_opening`) and the components (:func:`graph_components`) in two
    compiled passes over a grid of cells of side ``r``: ``(idx, comp, n_comp)``, the kept
    positions, their components and how many. A grid of more than ``4 m + 4096`` cells (an
    extent wide for ``r``: a sparse cluster of a dense scan) keeps its occupied cells only; None
    when an axis would hold 1e9 cells or more, where the k-d tree version runs instead. The same
    degrees, ``k_min``, dilation and components as the k-d tree version."""
    from kbs.inference import _compiled

    U, mult = D.points, D.mult
    m = U.shape[0]
    max_cells = 4.0 * m + 4096.0
    dilate = False
    if opening:
        degree = _compiled.connexity_degrees(U, mult, r, max_cells)
        if degree.size == 0:
            return None
        sample = _median_sample(U)
        k_min = erosion_fraction * float(np.median(np.repeat(degree[sample], mult[sample])))
        kept = degree >= k_min
        n_kept = int(np.count_nonzero(kept))
        dilate = 0 < n_kept < m
    else:
        kept = np.ones(m, dtype=bool)
    kept, comp, n_comp = _compiled.connexity_components(U, kept, r, dilate, max_cells)
    if n_comp < 0:
        return None
    idx = np.flatnonzero(kept)
    return idx, comp[idx], int(n_comp)


# -- the alpha-shape method ---------------------------------------------------------------------


def alpha_complex(P, alpha: float) -> np.ndarray:
    """Triangles of the alpha-complex of 2D points: the Delaunay triangles whose circumradius is
    at most ``alpha`` (their edges are then at most ``2 alpha``).

    Parameters
    ----------
    P : array-like (m, 2)
        Distinct points.
    alpha : float
        Alpha radius, > 0.

    Returns
    -------
    ndarray (k, 3) int
        Vertex indices into ``P`` of each triangle; empty (0, 3) when there are fewer than three
        points or they are all collinear (no triangle: an alpha-shape without area).
    """
    from scipy.spatial import Delaunay, QhullError

    P = np.asarray(P, dtype=np.float64)
    if P.shape[0] < 3:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        S = Delaunay(P).simplices
    except QhullError:  # all collinear (or coincident): no triangle
        return np.zeros((0, 3), dtype=np.int64)
    A, B, C = P[S[:, 0]], P[S[:, 1]], P[S[:, 2]]
    ab, bc, ca = B - A, C - B, A - C
    area2 = np.abs(ab[:, 0] * ca[:, 1] - ab[:, 1] * ca[:, 0])  # twice the area
    # circumradius R = |ab| |bc| |ca| / (4 area) <= alpha, without dividing by a zero area
    lengths = np.sqrt(np.einsum("ij,ij->i", ab, ab) * np.einsum("ij,ij->i", bc, bc) * np.einsum("ij,ij->i", ca, ca))
    return S[lengths <= 2.0 * alpha * area2]


def alpha_shape(P, alpha: float):
    """The alpha-shape of 2D points: the union of the triangles of their alpha-complex
    (:func:`alpha_complex`), as a shapely (Multi)Polygon (empty when there is no triangle).

    The triangles of a Delaunay triangulation meet edge to edge, so their union is a coverage
    union (``shapely.coverage_union_all``), much cheaper than a general union.
    """
    import shapely

    P = np.asarray(P, dtype=np.float64)
    T = alpha_complex(P, alpha)
    k = T.shape[0]
    if k == 0:
        return shapely.Polygon()
    # the triangles as closed rings, built in one call (3-4 times faster than shapely.polygons)
    rings = P[T[:, [0, 1, 2, 0]]].reshape(-1, 2)
    offsets = (np.arange(0, 4 * k + 1, 4), np.arange(k + 1))
    return shapely.coverage_union_all(shapely.from_ragged_array(shapely.GeometryType.POLYGON, rings, offsets))


def alpha_opening(shape, radius: float) -> list:
    """Components of the morphological opening of a shape by a disc: erosion by a disc of radius
    ``radius`` (``buffer(-radius)``) then dilation by the same disc (``buffer(radius)``).

    The opening keeps the union of the discs of that radius that fit inside the shape: a part
    narrower than ``2 radius`` (a bridge of width ``w < 2 radius``, a spur, a speck) disappears,
    and so do convex corners (rounded to the disc); a part at least ``2 radius`` wide stays.

    Parameters
    ----------
    shape : shapely geometry
        A (Multi)Polygon, e.g. :func:`alpha_shape`.
    radius : float
        Radius of the disc, >= 0 (0: the shape itself).

    Returns
    -------
    list of shapely Polygon
        The connected components of the opened shape (none when it is empty).
    """
    import shapely

    opened = shape if radius <= 0.0 else shape.buffer(-radius).buffer(radius)
    return [g for g in shapely.get_parts(opened) if not g.is_empty]


#: A point counts in a component of the opened alpha-shape when it lies within this fraction of
#: the opening radius of it: the opening rounds the convex corners of the shape, whose vertices
#: are the sample points of its outline; a corner of angle t moves in by radius (1 / sin(t / 2)
#: - 1), 0.155 radius at 120 degrees; GEOS approximates the arcs of the dilation by chords and
#: simplifies its input by 1 % of the radius.
_NEAR_FRACTION = 0.2


def _alpha_opening_components(D: _Distinct, alpha: float, radius: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The components of the opening of the alpha-shape of the distinct positions, and the
    positions in each: ``(idx, comp, n_comp)``, the positions in a component, their components
    (in no particular order) and how many components hold a position."""
    label = _points_in_parts(D.points, alpha_opening(alpha_shape(D.points, alpha), radius), radius, alpha)
    idx = np.flatnonzero(label >= 0)
    used, comp = np.unique(label[idx], return_inverse=True)  # components holding no position go
    return idx, comp.ravel(), int(used.size)


def _points_in_parts(U: np.ndarray, parts: list, radius: float, alpha: float) -> np.ndarray:
    """The part (index into ``parts``) each point of ``U`` (m, 2) lies in or within
    ``_NEAR_FRACTION * radius`` of, -1 for none (the first such part when there are several)."""
    import shapely

    label = np.full(U.shape[0], -1, dtype=np.int64)
    if not parts:
        return label
    scale = float(np.abs(U).max()) + alpha
    near = _NEAR_FRACTION * radius + 1e-9 * scale  # the outline (and rounding) when radius is 0
    x, y = U[:, 0], U[:, 1]
    boxes = shapely.bounds(parts)
    for i, part in enumerate(parts):
        shapely.prepare(part)
        x0, y0, x1, y1 = boxes[i]
        cand = np.flatnonzero((label < 0) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))
        label[cand[shapely.intersects_xy(part, x[cand], y[cand])]] = i
    for i, part in enumerate(parts):
        x0, y0, x1, y1 = boxes[i]
        cand = np.flatnonzero((label < 0) & (x >= x0 - near) & (x <= x1 + near) & (y >= y0 - near) & (y <= y1 + near))
        if cand.size:
            label[cand[shapely.dwithin(part, shapely.points(U[cand]), near)]] = i
    return label


def _number_by_size(n_comp: int, comp: np.ndarray, size: np.ndarray, Q: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Renumber components by decreasing size; ties go to the component holding the
    lexicographically smallest (x, y) position, so the numbering does not depend on the input
    order.

    Parameters: ``comp`` (k,) the component of each distinct position ``Q`` (k, 2), ``size``
    (k,) their sizes. Returns the old-to-new map (n_comp,) and the sizes (n_comp,) in the new
    order."""
    sizes = np.bincount(comp, weights=size, minlength=n_comp)
    if np.issubdtype(size.dtype, np.integer):
        sizes = np.rint(sizes).astype(np.int64)
    first = np.zeros(n_comp, dtype=np.int64)
    if np.unique(sizes).size < n_comp:
        rank = np.empty(comp.size, dtype=np.int64)
        rank[np.lexsort((Q[:, 1], Q[:, 0]))] = np.arange(comp.size)
        first[:] = comp.size
        np.minimum.at(first, comp, rank)
    order = np.lexsort((first, -sizes))
    new = np.empty(n_comp, dtype=np.int64)
    new[order] = np.arange(n_comp)
    return new, sizes[order]


def connexity(
    X,
    center,
    normal,
    *,
    alpha: float | None = None,
    alpha_factor: float = 3.0,
    opening: bool = True,
    method: str = "graph",
    erosion_fraction: float = 0.3,
    opening_radius: float | None = None,
    opening_factor: float = 1.0,
    min_fraction: float = 0.05,
    min_points: float = 10,
    sample_weight=None,
) -> Connexity:
    """Significant connected components of a cluster projected on its best approximating plane.

    Parameters
    ----------
    X : array-like (n, 3)
        The cluster's points.
    center : array-like (3,)
        A point of the plane (the cluster's centre, e.g. ``ClusterGeometry.center``).
    normal : array-like (3,)
        The plane's normal (e.g. ``ClusterGeometry.normal``); normalised here, must not be zero.
    alpha : float, optional
        Alpha radius in length units (points at most ``2 alpha`` apart are linked). Default:
        ``alpha_factor`` times the median nearest-neighbour spacing of the projected points.
    alpha_factor : float
        Multiple of the spacing used when ``alpha`` is None (> 0).
    opening : bool
        Filter the points with a morphological opening (see the module docstring) before
        counting components, so that thin bridges do not join blobs.
    method : {'graph', 'alpha_opening'}
        ``'graph'``: components of the graph ``|p - q| <= 2 alpha``, opened by counting
        neighbours. ``'alpha_opening'``: components of the alpha-shape (union of the Delaunay
        triangles of circumradius ``<= alpha``) opened by a disc of radius ``opening_radius``.
    erosion_fraction : float in [0, 1]
        ``'graph'`` only. Erosion threshold: a point stays when it has at least
        ``erosion_fraction`` times the median (over all points, or 4,096 of them) number of
        other points within ``2 alpha``.
    opening_radius : float, optional
        ``'alpha_opening'`` only. Radius of the disc of the opening in length units (>= 0): parts
        of the alpha-shape narrower than ``2 opening_radius`` are removed. Default:
        ``opening_factor`` times alpha.
    opening_factor : float
        ``'alpha_opening'`` only: multiple of alpha used when ``opening_radius`` is None (>= 0).
    min_fraction : float in [0, 1]
        A component is significant when its size is at least ``max(min_points, min_fraction *
        total)``.
    min_points : float >= 0
        See ``min_fraction`` (compared with summed weights when ``sample_weight`` is given).
    sample_weight : array-like (n,), optional
        Non-negative weights (e.g. voxel counts): sizes are then summed weights.

    Returns
    -------
    Connexity
        Fewer than 3 points, or points that all project on one position, make one component
        (significant if it passes the size test).

    Raises
    ------
    FitError
        For an empty cluster.
    ParameterError
        For NaN or infinite coordinates, a zero normal, or an invalid parameter.
    """
    X = _check_cloud(X)
    n = X.shape[0]
    if alpha is not None:
        alpha = _check_real(alpha, "alpha", low=0.0, low_open=True)
    alpha_factor = _check_real(alpha_factor, "alpha_factor", low=0.0, low_open=True)
    erosion_fraction = _check_real(erosion_fraction, "erosion_fraction", low=0.0, high=1.0)
    min_fraction = _check_real(min_fraction, "min_fraction", low=0.0, high=1.0)
    min_points = _check_real(min_points, "min_points", low=0.0)
    if method not in METHODS:
        raise ParameterError(f"The 'method' parameter of {_OWNER} must be one of {', '.join(map(repr, METHODS))}. "
                             f"Got {method!r} instead.")
    if opening_radius is not None:
        opening_radius = _check_real(opening_radius, "opening_radius", low=0.0)
    opening_factor = _check_real(opening_factor, "opening_factor", low=0.0)
    if not isinstance(opening, (bool, np.bool_)):
        raise ParameterError(f"The 'opening' parameter of {_OWNER} must be a bool. Got {opening!r} instead.")
    w = None
    if sample_weight is not None:
        w = np.asarray(sample_weight, dtype=np.float64)
        if w.shape != (n,):
            raise ParameterError(f"{_OWNER}: sample_weight must have shape ({n},); got {w.shape}.")
        if not np.isfinite(w).all() or (w < 0).any():
            raise ParameterError(f"{_OWNER}: sample_weight must be finite and non-negative.")

    P = project_on_plane(X, center, normal)
    total = float(n if w is None else w.sum())
    threshold = max(min_points, min_fraction * total)
    D = _distinct(P)
    U, mult, spacing = D.points, D.mult, D.spacing
    if alpha is None:
        alpha = alpha_factor * spacing
    radius = None
    if method == "alpha_opening":
        radius = 0.0 if not opening else opening_factor * alpha if opening_radius is None else opening_radius

    if n < 3 or U.shape[0] == 1:
        # Too few points for a shape, or a single position: one component.
        size = n if w is None else total
        sig = np.array([size >= threshold])
        return Connexity(n_components=1, n_significant=int(sig[0]), labels=np.zeros(n, dtype=np.int64),
                         significant=sig, sizes=np.array([size]), alpha=float(alpha), spacing=spacing,
                         method=method, opening_radius=radius)

    # Size of each distinct position: its multiplicity, or its summed weight.
    size = mult if w is None else np.bincount(D.point_of, weights=w[D.order])
    found = None
    if method == "alpha_opening":
        found = _alpha_opening_components(D, alpha, radius)
    elif _flags.JIT:
        found = _compiled_opening_components(D, 2.0 * alpha, erosion_fraction, opening)
    if found is not None:
        idx, comp, n_comp = found
    else:
        kept = _opening(D, 2.0 * alpha, erosion_fraction) if opening else np.ones(U.shape[0], dtype=bool)
        idx = np.flatnonzero(kept)
        n_comp, comp = graph_components(rows(U, idx), 2.0 * alpha)
    # An isolated point (a component of one point: no other point within 2 alpha) is no component.
    alone = (np.bincount(comp, weights=mult[idx], minlength=n_comp) == 1)[comp]
    if alone.any():
        idx = idx[~alone]
        _, comp = np.unique(comp[~alone], return_inverse=True)
        comp = comp.ravel()
        n_comp = int(comp.max()) + 1 if comp.size else 0
    new, sizes = _number_by_size(n_comp, comp, size[idx], rows(U, idx))
    label_u = np.full(U.shape[0], -1, dtype=np.int64)
    label_u[idx] = new[comp]
    labels = np.empty(n, dtype=np.int64)
    labels[D.order] = label_u[D.point_of]
    significant = sizes >= threshold
    return Connexity(n_components=int(n_comp), n_significant=int(significant.sum()), labels=labels,
                     significant=significant, sizes=sizes, alpha=float(alpha), spacing=spacing,
                     method=method, opening_radius=radius)


def assign_to_nearest(X2d, labels, significant) -> np.ndarray:
    """Give every point the label of its nearest point in a significant component.

    Points of significant components keep their label; points of non-significant components
    and points labelled ``-1`` take the label of the nearest point (Euclidean, in ``X2d``) that
    belongs to a significant component. Splitting a cluster along the result partitions it
    exactly into ``significant.sum()`` parts.

    Parameters
    ----------
    X2d : array-like (n, d)
        Point coordinates, normally the projection :func:`project_on_plane` used by
        :func:`connexity`.
    labels : array-like (n,) int
        ``Connexity.labels``.
    significant : array-like (n_components,) bool
        ``Connexity.significant``.

    Returns
    -------
    ndarray (n,) int64
        Labels, all of significant components (``0 .. n_significant - 1`` for a
        :class:`Connexity`).

    Raises
    ------
    FitError
        When no component is significant (there is nothing to assign the points to).
    """
    P = np.asarray(X2d, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    significant = np.asarray(significant, dtype=bool)
    if P.ndim != 2 or labels.ndim != 1 or P.shape[0] != labels.shape[0]:
        raise ParameterError(
            f"assign_to_nearest: X2d (n, d) and labels (n,) must match; got {P.shape} and {labels.shape}."
        )
    if labels.size and (labels.max() >= significant.size or labels.min() < -1):
        raise ParameterError("assign_to_nearest: labels must lie in [-1, len(significant)).")
    ok = np.zeros(labels.shape, dtype=bool)
    inside = labels >= 0
    ok[inside] = significant[labels[inside]]
    if ok.all():
        return labels.copy()
    if not ok.any():
        raise FitError("no significant component to assign the points to")
    out = labels.copy()
    good = np.flatnonzero(ok)
    out[~ok] = nearest_label(rows(P, ~ok), rows(P, good), labels[good])
    return out
