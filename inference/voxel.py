"""Voxel-grid reduction of a large cloud into a small weighted fitting set.

Each occupied voxel becomes one sample at the centroid of its points, weighted by their count
(or total weight), and carrying their scatter matrix ``sum (x - c)(x - c)^T``, so that fuzzy
covariances computed on the reduced set are exact whenever memberships are constant inside a
voxel. The reduced set comes out sorted by voxel key: it does not depend on the input point order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kbs.inference import _flags

_MAX_AXIS_CELLS = 1 << 20  # 3 axes x 20 bits fit one int64 key


@dataclass(frozen=True)
class VoxelReduction:
    """A weighted reduction of ``n`` points into ``M`` voxels.

    Attributes
    ----------
    centroids : ndarray (M, D)
    weights : ndarray (M,)
        Point count (or summed sample weight) of each voxel.
    scatter : ndarray (M, D, D)
        Weighted within-voxel scatter ``sum_j w_j (x_j - c)(x_j - c)^T``.
    voxel_size : float
    """

    centroids: np.ndarray
    weights: np.ndarray
    scatter: np.ndarray
    voxel_size: float

    def __len__(self) -> int:
        return int(self.weights.shape[0])


def _cells(X: np.ndarray, origin: np.ndarray, size: float) -> np.ndarray:
    return np.floor((X - origin) / size).astype(np.int64)


def _keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per cell row (cells are non-negative and < 2**20 on each of <= 3 axes)."""
    key = np.zeros(cells.shape[0], dtype=np.int64)
    for j in range(cells.shape[1]):
        key = (key << 20) | cells[:, j]
    return key


def _jit():
    """The compiled voxel kernels, or None when ``KBS_JIT=0`` (see :func:`kbs.inference.engine.jit_enabled`)."""
    if not _flags.JIT:
        return None
    from kbs.inference import _compiled

    return _compiled


def bounds(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column ``(min, max)`` of ``X`` (n, D): one compiled pass (numpy's axis-0 reductions
    over a C-ordered (n, 3) array are strided and were a tenth of a split's time)."""
    jit = _jit()
    if jit is not None and X.shape[0] and X.dtype == np.float64:
        return jit.bounds(np.ascontiguousarray(X))
    return X.min(axis=0), X.max(axis=0)


def _distinct(keys: np.ndarray) -> np.ndarray:
    """The distinct keys, sorted: what ``np.unique`` returns, by a plain sort and a mask (several
    times faster than ``np.unique`` on int64 keys here, and faster than the hash table when most
    keys are distinct)."""
    s = np.sort(keys)
    if s.size < 2:
        return s
    keep = np.empty(s.size, dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def _decode(keys: np.ndarray, D: int) -> np.ndarray:
    """Inverse of :func:`_keys`."""
    mask = (1 << 20) - 1
    return np.stack([(keys >> (20 * (D - 1 - j))) & mask for j in range(D)], axis=1)


def _min_size(X: np.ndarray) -> float:
    lo, hi = bounds(X)
    extent = float((hi - lo).max())
    return max(extent / (_MAX_AXIS_CELLS - 2), np.finfo(np.float64).tiny)


def count_voxels(X: np.ndarray, size: float) -> int:
    """Number of occupied voxels of edge ``size``."""
    size = max(size, _min_size(X))
    return int(_distinct(_keys(_cells(X, bounds(X)[0], size))).size)


def auto_voxel_size(X: np.ndarray, target: int) -> float:
    """A voxel edge whose grid has at most ``target`` occupied voxels, and at least about 90 % of
    that (the coarsest grid that fits, within ~6 % in edge length).

    Deterministic: depends on the set of points only. The cloud is gridded once, finely; coarser
    grids are counted on its distinct cells, with a secant search in log-log space (the number of
    occupied voxels of a surface falls about as the square of the edge).
    """
    if X.shape[1] > 3:
        raise ValueError("voxel reduction supports at most 3 dimensions")
    lo, hi = bounds(X)
    extent = float((hi - lo).max())
    if extent == 0.0:
        return 1.0
    fine = max(extent / 4096.0, _min_size(X))
    jit = _jit()
    if jit is not None and X.dtype == np.float64:
        fine_keys = jit.cell_keys(np.ascontiguousarray(X), lo, float(fine))
    else:
        fine_keys = _keys(_cells(X, lo, fine))
    # the counts below do not depend on the order of the distinct cells: no sort needed
    fine_cells = _decode(jit.distinct_keys(fine_keys) if jit is not None else _distinct(fine_keys), X.shape[1])
    n_fine = fine_cells.shape[0]
    if n_fine <= target:
        return fine


    def occupied(factor: float) -> int:
        if jit is not None:
            return int(jit.count_coarse_cells(fine_cells, float(factor)))
        return int(_distinct(_keys(np.floor(fine_cells / factor).astype(np.int64))).size)

    f0, n0 = 1.0, n_fine
    f = float(np.sqrt(n_fine / target))
    n = occupied(f)
    for _ in range(6):
        if 0.9 * target <= n <= target:
            return fine * f
        slope = np.log(n / n0) / np.log(f / f0) if n != n0 and f != f0 else -2.0
        slope = min(slope, -0.5)  # more voxels for a finer grid, whatever the local shape
        f0, n0 = f, n
        f = max(f * (0.95 * target / n) ** (1.0 / slope), 1.0)
        n = occupied(f)
    while n > target:  # did not settle: make sure of the bound
        f *= 1.1
        n = occupied(f)
    return fine * f


def voxel_reduce(X: np.ndarray, size: float, sample_weight: np.ndarray | None = None) -> VoxelReduction:
    """Reduce ``X`` (n, D<=3) to voxel centroids with weights and within-voxel scatter."""
    n, D = X.shape
    size = max(float(size), _min_size(X))
    origin = bounds(X)[0]
    jit = _jit()
    w = np.ones(n) if sample_weight is None else sample_weight
    if jit is not None and X.dtype == np.float64 and D <= 3:  # the same arrays, compiled, no (n, D) temporaries
        Xc = np.ascontiguousarray(X)
        keys, inverse = jit.unique_inverse(jit.cell_keys(Xc, origin, float(size)))
        M = keys.size
        weights, s1, s2, first = jit.voxel_sums(Xc, origin, float(size), inverse,
                                                np.ascontiguousarray(w, dtype=np.float64), M)
        safe = np.where(weights > 0, weights, 1.0)
        mean_local = s1 / safe[:, None]
        scatter = np.empty((M, D, D))
        for a in range(D):
            for b in range(a, D):
                scatter[:, a, b] = scatter[:, b, a] = s2[:, a, b] - weights * mean_local[:, a] * mean_local[:, b]
        corner = origin + _cells(X[first], origin, size) * size
    else:
        cells = _cells(X, origin, size)
        keys, inverse = np.unique(_keys(cells), return_inverse=True)
        M = keys.size
        weights = np.bincount(inverse, weights=w, minlength=M)
        # moments of coordinates local to each voxel corner: small numbers, no cancellation
        local = X - (origin + cells * size)
        s1 = np.stack([np.bincount(inverse, weights=w * local[:, a], minlength=M) for a in range(D)], axis=1)
        safe = np.where(weights > 0, weights, 1.0)
        mean_local = s1 / safe[:, None]
        scatter = np.empty((M, D, D))
        for a in range(D):
            for b in range(a, D):
                s2 = np.bincount(inverse, weights=w * local[:, a] * local[:, b], minlength=M)
                scatter[:, a, b] = scatter[:, b, a] = s2 - weights * mean_local[:, a] * mean_local[:, b]
        corner = np.empty((M, D))
        first = np.zeros(M, dtype=np.int64)
        first[inverse[::-1]] = np.arange(n - 1, -1, -1)  # any member gives the voxel's corner
        corner[:] = origin + cells[first] * size
    keep = weights > 0
    return VoxelReduction(
        centroids=(corner + mean_local)[keep],
        weights=weights[keep],
        scatter=scatter[keep],
        voxel_size=size,
    )
