"""Square tiles in the ground plane, each with a buffer: pure geometry over arrays.

A cloud is cut along two axes of its ground plane (x-y, or the plane across a fixed ground
normal) into square cores of side ``size``; a point belongs to exactly one core. Each tile is its
core widened by ``buffer`` on every side: the points a tile is segmented with.

>>> import numpy as np
>>> X = np.random.default_rng(0).uniform(0, 100, (1000, 3))
>>> grid = TileGrid.fit(X, size=50.0, buffer=5.0)
>>> [t.name for t in grid.tiles(X)]
['t0_0', 't0_1', 't1_0', 't1_1']
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kbs.errors import ParameterError

_Z_UP = np.array([0.0, 0.0, 1.0])


def ground_axes(normal: np.ndarray | None) -> np.ndarray:
    """Two orthonormal axes of the ground plane, shape (2, 3).

    ``normal`` None or z up: x and y themselves (tile bounds read as map coordinates). Otherwise
    the axes across the normal, the first one the projection of x (or of y, x being along it).
    """
    if normal is None:
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    if np.allclose(n, _Z_UP) or np.allclose(n, -_Z_UP):
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


#: The most cells a grid may have: a cell's number ``i * columns + j`` is an int64.
MAX_CELLS = 2 ** 62


def _count(n: int) -> str:
    return f"{n:,}" if n < 10 ** 12 else f"{float(n):.3g}"


def grid_shape(lo: np.ndarray, hi: np.ndarray, size: float) -> tuple[int, int]:
    """Rows and columns of tiles of ``size`` over the ground extent ``lo`` .. ``hi``.

    Raises
    ------
    ParameterError
        More cells than :data:`MAX_CELLS` (a tile size far too small for the cloud's extent).
    """
    shape = tuple(max(1, math.ceil((float(hi[k]) - float(lo[k])) / size)) for k in range(2))
    if shape[0] * shape[1] > MAX_CELLS:
        raise ParameterError(f"tiles of {size:g} over a cloud {float(hi[0] - lo[0]):.6g} x {float(hi[1] - lo[1]):.6g} "
                             f"wide would make {_count(shape[0])} x {_count(shape[1])} tiles, more than a tile's number can index "
                             "(2^62): a larger tile size")
    return int(shape[0]), int(shape[1])


@dataclass(frozen=True, eq=False)
class Tile:
    """One tile of a :class:`TileGrid`.

    Attributes
    ----------
    name : str
        ``t<i>_<j>``: row i along the first ground axis, column j along the second.
    i, j : int
    core : tuple of 4 float
        ``(u_min, v_min, u_max, v_max)`` of the core in ground-plane coordinates.
    index : ndarray (n_tile,) int64
        The points of the tile (core and buffer), increasing indices into the cloud.
    in_core : ndarray (n_tile,) bool
        Which of them the core holds (the tile's result is kept for those).
    """

    name: str
    i: int
    j: int
    core: tuple[float, float, float, float]
    index: np.ndarray
    in_core: np.ndarray

    def bounds_text(self) -> str:
        u0, v0, u1, v1 = self.core
        return f"{self.name} [{u0:.6g}, {u1:.6g}] x [{v0:.6g}, {v1:.6g}]"


#: The widest buffer, in tile sizes: a tile with its buffer then covers at most (1 + 2 x 4.5)^2 = 100
#: times its core's area. (A tile of 0.0001 m with the outdoor rules' 6 m buffer made 26,000 tiles
#: of one point each, every one segmented with the 12 m wide neighbourhood around it.)
MAX_BUFFER_TILES = 4.5


@dataclass(frozen=True)
class TileGrid:
    """Square tiles of side ``size`` with a ``buffer``, from ``origin`` along ``axes``.

    Attributes
    ----------
    size, buffer : float
    axes : ndarray (2, 3)
        The ground plane's axes (:func:`ground_axes`).
    origin : tuple of 2 float
        Ground-plane coordinates of the corner of tile t0_0.
    shape : tuple of 2 int
        Rows and columns of the grid.
    """

    size: float
    buffer: float
    axes: np.ndarray
    origin: tuple[float, float]
    shape: tuple[int, int]

    @classmethod
    def fit(cls, X: np.ndarray, size: float, buffer: float, normal: np.ndarray | None = None) -> TileGrid:
        """The grid covering ``X`` (n_points, 3): its corner at the smallest ground coordinates.

        Raises
        ------
        ParameterError
            ``size`` not a positive finite number, ``buffer`` negative or not finite, or wider
            than :data:`MAX_BUFFER_TILES` tiles.
        """
        if isinstance(size, bool) or not isinstance(size, (int, float, np.number)) or not math.isfinite(size) \
                or size <= 0:
            raise ParameterError(f"The 'tile size' parameter must be a positive length. Got {size!r} instead.")
        if isinstance(buffer, bool) or not isinstance(buffer, (int, float, np.number)) \
                or not math.isfinite(buffer) or buffer < 0:
            raise ParameterError(f"The 'buffer' parameter must be a length >= 0. Got {buffer!r} instead.")
        if buffer > MAX_BUFFER_TILES * size:
            reach = (1.0 + 2.0 * (buffer / size)) ** 2 if buffer / size < 1e150 else math.inf  # no overflow
            raise ParameterError(f"tiles of {size:g} with a buffer of {buffer:g}: each tile would be segmented over "
                                 f"{reach:.3g} times its own area, every point as many times; the buffer may be at "
                                 f"most {MAX_BUFFER_TILES:g} tiles wide: give tiles of at least "
                                 f"{buffer / MAX_BUFFER_TILES:.3g}, or a smaller buffer")
        axes = ground_axes(normal)
        uv = X @ axes.T
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        return cls(float(size), float(buffer), axes, (float(lo[0]), float(lo[1])), grid_shape(lo, hi, float(size)))

    def cells(self, uv: np.ndarray) -> np.ndarray:
        """The (i, j) core of each point, shape (n_points, 2) int64 (points outside the grid go
        to the nearest edge tile)."""
        ij = np.floor((uv - np.asarray(self.origin)) / self.size).astype(np.int64)
        return np.clip(ij, 0, np.asarray(self.shape) - 1)

    def _occupied(self, ij: np.ndarray) -> np.ndarray:
        """The keys ``i * shape[1] + j`` of the cores holding a point, from their cells ``ij``, sorted
        (row by row)."""
        return np.unique(ij[:, 0] * self.shape[1] + ij[:, 1])

    def n_occupied(self, uv: np.ndarray) -> int:
        """How many tiles' cores hold at least one of the points ``uv`` (ground coordinates)."""
        return int(self._occupied(self.cells(uv)).size)

    def tiles(self, X: np.ndarray) -> list[Tile]:
        """The tiles whose core holds at least one point of ``X``, row by row. Only the cells that
        hold points are visited: a few far points (a grid of millions of empty cells) cost nothing."""
        uv = X @ self.axes.T
        ij = self.cells(uv)
        out = []
        order = np.argsort(uv[:, 0], kind="stable")
        u_sorted = uv[order, 0]
        occupied = self._occupied(ij)  # row by row
        occ_i, occ_j = occupied // self.shape[1], occupied % self.shape[1]
        cut = np.flatnonzero(np.diff(occ_i)) + 1
        for cols in np.split(np.arange(occupied.size), cut):
            i = int(occ_i[cols[0]])
            u0 = self.origin[0] + i * self.size
            lo_u = -np.inf if i == 0 else u0 - self.buffer
            hi_u = np.inf if i == self.shape[0] - 1 else u0 + self.size + self.buffer
            row = np.sort(order[np.searchsorted(u_sorted, lo_u, "left"):np.searchsorted(u_sorted, hi_u, "right")])
            for j in (int(c) for c in occ_j[cols]):
                v0 = self.origin[1] + j * self.size
                lo_v = -np.inf if j == 0 else v0 - self.buffer
                hi_v = np.inf if j == self.shape[1] - 1 else v0 + self.size + self.buffer
                v = uv[row, 1]
                index = row[(v >= lo_v) & (v <= hi_v)]
                in_core = (ij[index, 0] == i) & (ij[index, 1] == j)
                if not in_core.any():
                    continue
                out.append(Tile(f"t{i}_{j}", i, j, (u0, v0, u0 + self.size, v0 + self.size), index, in_core))
        return out
