"""The 2D obstacle grid of a drive: per cell, ground/obstacle evidence fused over the frames in
log-odds, the obstacle's height above the ground and the number of frames that saw the cell.

Each frame casts at most one vote per cell it has points in (the frame's points are labelled by
the segmenter): *obstacle* when at least ``min_obstacle_points`` of them are obstacle points,
else *ground* when some are ground points. A vote adds ``l_obstacle`` (> 0) or ``l_ground``
(< 0) to the cell's log-odds ``L = log(p / (1 - p))``, clamped to ``[-l_clamp, l_clamp]`` (the
standard occupancy-grid update, Thrun et al., *Probabilistic Robotics* ch. 9, with the per-frame
labels as the inverse sensor model). With the defaults (0.85 and -0.4, i.e. p = 0.7 and 0.4), a
cell seen as ground in three frames and as obstacle in one ends at L = -0.35: not an obstacle.
A cell is an obstacle when ``L > 0``, ground when ``L < 0``, unknown when never seen or ``L = 0``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kbs.errors import ParameterError

#: Values of the ``class`` band.
UNKNOWN, GROUND, OBSTACLE = 0, 1, 2
CLASS_NAMES = ("unknown", "ground", "obstacle")

#: The bands of the GeoTIFF and of ``map.npy``, in order (all float32; NaN = no value).
BANDS = ("class", "p_obstacle", "log_odds", "obstacle_height", "ground_z", "frames_seen", "frames_obstacle")


@dataclass(frozen=True)
class FusionParams:
    """How frames vote in the grid (see the module's doc).

    Attributes
    ----------
    cell_size : float
        Side of a cell, metres.
    l_obstacle : float
        Log-odds added by a frame that sees the cell as an obstacle (> 0).
    l_ground : float
        Log-odds added by a frame that sees the cell as ground (< 0).
    l_clamp : float
        Bound of the cell's log-odds (keeps a cell able to change its mind).
    min_obstacle_points : int
        Obstacle points a frame needs in a cell to vote obstacle there.
    """

    cell_size: float = 0.2
    l_obstacle: float = 0.85
    l_ground: float = -0.4
    l_clamp: float = 3.5
    min_obstacle_points: int = 1


#: The most memory the layers of a map may take (bytes): about 8 km x 8 km at 0.2 m, far beyond a
#: drive's extent at its usual cell size; a cell size of a millimetre would ask for tens of GiB.
MAX_MAP_BYTES = 4 * 2**30


class GridAccumulator:
    """Accumulates the frames' votes in a dense grid that grows as the drive goes.

    Array axes are (ix, iy): cell ``(ix, iy)`` of the arrays covers
    ``[(ix0 + ix) s, (ix0 + ix + 1) s) x [(iy0 + iy) s, ...)`` in world metres.
    """

    _LAYERS = {"log_odds": np.float64, "frames_seen": np.int32, "frames_obstacle": np.int32,
               "frames_ground": np.int32, "n_ground": np.int64, "n_obstacle": np.int64, "ground_zsum": np.float64,
               "obstacle_zmax": np.float64}

    def __init__(self, params: FusionParams) -> None:
        self.params = params
        self.ix0 = self.iy0 = 0
        self.layers: dict[str, np.ndarray] = {k: np.zeros((0, 0), dtype=t) for k, t in self._LAYERS.items()}
        self.layers["obstacle_zmax"][:] = -np.inf

    @property
    def shape(self) -> tuple[int, int]:
        return self.layers["log_odds"].shape

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the arrays so that cells ``lo..hi`` (inclusive, world cell indices) fit."""
        nx, ny = self.shape
        if nx and lo[0] >= self.ix0 and lo[1] >= self.iy0 and hi[0] < self.ix0 + nx and hi[1] < self.iy0 + ny:
            return
        margin = 64  # cells: a drive grows a little at a time, do not reallocate every frame
        if nx:
            nlo = np.minimum(lo - margin, [self.ix0, self.iy0]) if (lo < [self.ix0, self.iy0]).any() else \
                np.array([self.ix0, self.iy0])
            nhi = np.maximum(hi + margin, [self.ix0 + nx - 1, self.iy0 + ny - 1]) if \
                (hi >= [self.ix0 + nx, self.iy0 + ny]).any() else np.array([self.ix0 + nx - 1, self.iy0 + ny - 1])
        else:
            nlo, nhi = lo - margin, hi + margin
        shape = (int(nhi[0] - nlo[0] + 1), int(nhi[1] - nlo[1] + 1))
        cell_bytes = sum(np.dtype(t).itemsize for t in self._LAYERS.values())
        if shape[0] * shape[1] * cell_bytes > MAX_MAP_BYTES:  # refused before it is allocated (or swapped)
            s = self.params.cell_size
            raise ParameterError(
                f"the map would be {shape[0]:,} x {shape[1]:,} cells of {s:g} m ({shape[0] * s:,.0f} m x "
                f"{shape[1] * s:,.0f} m), {shape[0] * shape[1] * cell_bytes / 2**30:,.1f} GiB of layers, more than "
                f"the {MAX_MAP_BYTES / 2**30:g} GiB a map may take: give a larger --cell-size")
        ox, oy = int(self.ix0 - nlo[0]), int(self.iy0 - nlo[1])
        for k, old in self.layers.items():
            new = np.full(shape, -np.inf if k == "obstacle_zmax" else 0, dtype=old.dtype)
            new[ox:ox + nx, oy:oy + ny] = old
            self.layers[k] = new
        self.ix0, self.iy0 = int(nlo[0]), int(nlo[1])

    def add(self, xyz: np.ndarray, ground: np.ndarray, obstacle: np.ndarray) -> None:
        """Add one frame's votes.

        Parameters
        ----------
        xyz : np.ndarray, shape (n, 3)
            The frame's points in the world frame.
        ground, obstacle : np.ndarray, shape (n,), bool
            Which points the segmenter labelled ground, obstacle (neither: noise).
        """
        p = self.params
        ij = np.floor(xyz[:, :2] / p.cell_size).astype(np.int64)
        self._ensure(ij.min(axis=0), ij.max(axis=0))
        ny = self.shape[1]
        # the frame's cells (sorted unique flat indices into the grid): the cost follows the
        # points, not the frame's extent (a 120 m wide LiDAR frame spans 360,000 cells)
        cells, inv = np.unique((ij[:, 0] - self.ix0) * ny + (ij[:, 1] - self.iy0), return_inverse=True)
        m = len(cells)
        n_g = np.bincount(inv[ground], minlength=m)
        n_o = np.bincount(inv[obstacle], minlength=m)
        zsum = np.bincount(inv[ground], weights=xyz[ground, 2], minlength=m)
        zmax = np.full(m, -np.inf)
        np.maximum.at(zmax, inv[obstacle], xyz[obstacle, 2])
        votes_o = n_o >= p.min_obstacle_points
        votes_g = ~votes_o & (n_g > 0)
        delta = np.where(votes_o, p.l_obstacle, np.where(votes_g, p.l_ground, 0.0))
        L = {k: v.reshape(-1) for k, v in self.layers.items()}  # views of the C-contiguous arrays
        L["log_odds"][cells] = np.clip(L["log_odds"][cells] + delta, -p.l_clamp, p.l_clamp)
        L["frames_seen"][cells] += 1
        L["frames_obstacle"][cells] += votes_o
        L["frames_ground"][cells] += votes_g
        L["n_ground"][cells] += n_g
        L["n_obstacle"][cells] += n_o
        L["ground_zsum"][cells] += zsum
        L["obstacle_zmax"][cells] = np.maximum(L["obstacle_zmax"][cells], zmax)

    def result(self) -> GridMap:
        """The fused grid, cropped to the cells seen (plus nothing)."""
        seen = self.layers["frames_seen"] > 0
        if not seen.any():
            raise ValueError("no frame added")
        xs, ys = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
        crop = (slice(xs[0], xs[-1] + 1), slice(ys[0], ys[-1] + 1))
        L = {k: v[crop].copy() for k, v in self.layers.items()}
        return GridMap.from_layers(L, self.params, self.ix0 + int(xs[0]), self.iy0 + int(ys[0]))


@dataclass(frozen=True, eq=False)
class GridMap:
    """The fused grid of a drive. Arrays have axes (ix, iy): x grows with the first index, y with
    the second; :meth:`raster` turns a layer north-up (row 0 = largest y) for an image or GeoTIFF.

    Attributes
    ----------
    cell_size : float
    origin : (float, float)
        World x, y of the corner of cell (0, 0) (its smallest x and y).
    log_odds, p_obstacle : np.ndarray (nx, ny) float64
    cls : np.ndarray (nx, ny) uint8
        :data:`UNKNOWN`, :data:`GROUND` or :data:`OBSTACLE`.
    obstacle_height : np.ndarray (nx, ny) float64
        Highest obstacle point above the cell's ground level, NaN where no obstacle point.
    ground_z : np.ndarray (nx, ny) float64
        Mean height of the cell's ground points, NaN where none.
    frames_seen, frames_obstacle, frames_ground : np.ndarray (nx, ny) int32
    n_ground, n_obstacle : np.ndarray (nx, ny) int64
        Points counted over every frame.
    params : FusionParams
    """

    cell_size: float
    origin: tuple[float, float]
    log_odds: np.ndarray
    p_obstacle: np.ndarray
    cls: np.ndarray
    obstacle_height: np.ndarray
    ground_z: np.ndarray
    frames_seen: np.ndarray
    frames_obstacle: np.ndarray
    frames_ground: np.ndarray
    n_ground: np.ndarray
    n_obstacle: np.ndarray
    params: FusionParams

    @classmethod
    def from_layers(cls, L: dict[str, np.ndarray], params: FusionParams, ix0: int, iy0: int) -> GridMap:
        lo = L["log_odds"]
        seen = L["frames_seen"] > 0
        c = np.full(lo.shape, UNKNOWN, dtype=np.uint8)
        c[seen & (lo > 0)] = OBSTACLE
        c[seen & (lo < 0)] = GROUND
        with np.errstate(invalid="ignore", divide="ignore"):
            gz = np.where(L["n_ground"] > 0, L["ground_zsum"] / L["n_ground"], np.nan)
        level = _fill_nearest(gz)
        zmax = L["obstacle_zmax"]
        height = np.where(np.isfinite(zmax), zmax - level, np.nan)
        p = 1.0 / (1.0 + np.exp(-lo))
        return cls(params.cell_size, (ix0 * params.cell_size, iy0 * params.cell_size), lo, np.where(seen, p, np.nan),
                   c, height, gz, L["frames_seen"], L["frames_obstacle"], L["frames_ground"], L["n_ground"],
                   L["n_obstacle"], params)

    @property
    def shape(self) -> tuple[int, int]:
        """(nx, ny)."""
        return self.cls.shape

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in world metres."""
        x0, y0 = self.origin
        return x0, y0, x0 + self.shape[0] * self.cell_size, y0 + self.shape[1] * self.cell_size

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(ix, iy) array indices of world points ``xy`` (n, 2) (may fall outside the grid)."""
        return np.floor((np.asarray(xy)[:, :2] - np.asarray(self.origin)) / self.cell_size).astype(np.int64)

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World x (nx, ny) and y (nx, ny) of every cell centre."""
        nx, ny = self.shape
        x = self.origin[0] + (np.arange(nx) + 0.5) * self.cell_size
        y = self.origin[1] + (np.arange(ny) + 0.5) * self.cell_size
        return np.meshgrid(x, y, indexing="ij")

    @staticmethod
    def raster(layer: np.ndarray) -> np.ndarray:
        """A (nx, ny) layer as a north-up image (rows = y from the largest, columns = x)."""
        return np.flipud(np.asarray(layer).T)

    def bands(self) -> np.ndarray:
        """Every layer of :data:`BANDS` as a north-up float32 stack, shape (bands, ny, nx)."""
        layers = {"class": self.cls, "p_obstacle": self.p_obstacle, "log_odds": self.log_odds,
                  "obstacle_height": self.obstacle_height, "ground_z": self.ground_z,
                  "frames_seen": self.frames_seen, "frames_obstacle": self.frames_obstacle}
        return np.stack([self.raster(layers[b]).astype(np.float32) for b in BANDS])

    def counts(self) -> dict[str, int]:
        """Cells per class."""
        return {name: int((self.cls == i).sum()) for i, name in enumerate(CLASS_NAMES)}


def _fill_nearest(a: np.ndarray) -> np.ndarray:
    """``a`` with its NaNs replaced by the nearest finite value (all NaN: unchanged)."""
    from scipy.ndimage import distance_transform_edt

    missing = ~np.isfinite(a)
    if not missing.any() or missing.all():
        return a
    idx = distance_transform_edt(missing, return_distances=False, return_indices=True)
    return a[tuple(idx)]
