"""Voxel-grid reduction of a large cloud into a small weighted fitting set.

Each occupied voxel becomes one sample at the centroid of its points, weighted by their count
(or total weight), and carrying their scatter matrix ``sum (x - c)(x - c)^T``, so that fuzzy
covariances computed on the reduced set are exact whenever memberships are constant inside a
voxel. The reduced set comes out sorted by voxel key: it does not depend on the input point order.

A grid is aligned with the axes of the coordinates it is given. :class:`HorizontalFrame` gives a
cloud coordinates of its own that turn with it about the vertical (z) axis, so that a grid laid
in them (as the UFP-ONC driver does) does not depend on the axes the cloud happens to be given in.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kbs.inference import _flags

_MAX_AXIS_CELLS = 1 << 20  # 3 axes x 20 bits fit one int64 key

#: Rungs per doubling of the ladder of automatic voxel edges (see :func:`ladder_size`).
LADDER_RUNGS = 16


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


@dataclass(frozen=True)
class HorizontalFrame:
    """A frame of a weighted cloud that turns with the cloud about the vertical (z) axis.

    Origin at the weighted centroid; the first axis is the cloud's principal horizontal axis (from
    the weighted covariance of x and y), pointing to the side where the cloud's third moment along
    it is positive; the second axis completes a right-handed rotation about z; z (and any further
    column) is kept. Rotating the cloud about z (about any vertical line: the origin moves with the
    cloud) gives the same coordinates in its frame, to rounding; for a quarter turn they are
    identical (every operation below maps exactly onto its mirror under x -> -y, y -> x).

    When the horizontal covariance is isotropic (a disc, a square: ``|m2| <= 1e-6 sum w r^2``, m2
    the complex moment ``sum w (x + i y)^2``) the axis comes from the fourth moment (the square's
    axes), and when that is isotropic too, the x axis is kept: such a cloud looks the same whatever
    the turn, up to that precision.

    Attributes
    ----------
    origin : ndarray (D,)
    axis : ndarray (2,)
        The first axis ``(cos t, sin t)`` in the x-y plane.
    """

    origin: np.ndarray
    axis: np.ndarray

    #: below this ratio |m_k| / sum w r^k, the k-th moment gives no axis
    ISOTROPIC = 1e-6

    @classmethod
    def of(cls, X: np.ndarray, w: np.ndarray | None = None) -> HorizontalFrame:
        """The frame of points ``X`` (n, D) with weights ``w`` (n,) (ones when None)."""
        n, D = X.shape
        w = np.ones(n) if w is None else np.asarray(w, dtype=np.float64)
        total = float(w.sum())
        # column by column, as sums of products: each mirrors exactly under a quarter turn
        origin = np.array([float((w * X[:, j]).sum()) / total for j in range(D)]) if total > 0 else np.zeros(D)
        if D < 2 or n == 0 or total <= 0:
            return cls(origin, np.array([1.0, 0.0]))
        dx, dy = X[:, 0] - origin[0], X[:, 1] - origin[1]
        xx, yy, xy = dx * dx, dy * dy, dx * dy
        r2 = float((w * (xx + yy)).sum())
        a, b = float((w * (xx - yy)).sum()), 2.0 * float((w * xy).sum())  # m2 = a + i b
        if np.hypot(a, b) > cls.ISOTROPIC * r2:
            c, s = _half_angle(a, b)
            candidates = [(c, s)]
        else:
            d = xx - yy
            a4, b4 = float((w * (d * d - 4.0 * xy * xy)).sum()), 4.0 * float((w * (xy * d)).sum())  # m4
            if np.hypot(a4, b4) <= cls.ISOTROPIC * float((w * (xx + yy) ** 2).sum()):
                return cls(origin, np.array([1.0, 0.0]))
            c2, s2 = _half_angle(a4, b4)  # 2t, where 4t is the angle of m4
            c, s = _half_angle(c2, s2)
            candidates = [(c, s), (-s, c)]  # the two axes of the square, mod a half turn
        best, score = None, -1.0
        for c, s in candidates:  # the axis (and side) along which the cloud is most skewed
            p = dx * c + dy * s
            k3 = float((w * (p * p * p)).sum())
            if abs(k3) > score:
                best, score = ((c, s) if k3 >= 0 else (-c, -s)), abs(k3)
        return cls(origin, np.array(best))

    def to_frame(self, X: np.ndarray) -> np.ndarray:
        """Coordinates (n, D) of points ``X`` (n, D) in this frame."""
        jit = _jit()
        if jit is not None and X.dtype == np.float64 and X.ndim == 2 and X.shape[0]:
            c, s = self.axis
            return jit.turn_to_frame(np.ascontiguousarray(X), np.ascontiguousarray(self.origin, dtype=np.float64),
                                     float(c), float(s))
        Y = X - self.origin
        if X.shape[1] >= 2:
            c, s = self.axis
            dx, dy = Y[:, 0].copy(), Y[:, 1].copy()
            Y[:, 0] = dx * c + dy * s
            Y[:, 1] = dy * c - dx * s
        return Y

    def from_frame(self, red: VoxelReduction) -> VoxelReduction:
        """A reduction computed in this frame, in the coordinates the frame was taken from."""
        P = red.centroids
        S = red.scatter
        D = P.shape[1]
        Q = np.empty((D, D))
        Q[:] = np.eye(D)
        if D >= 2:
            c, s = self.axis
            Q[:2, :2] = [[c, s], [-s, c]]  # frame coordinates = Q @ (x - origin)
        M = P.shape[0]
        SQ = (S.reshape(M * D, D) @ Q).reshape(M, D, D)  # S Q, then (S Q)^T Q = Q^T S Q (S symmetric)
        back = (SQ.transpose(0, 2, 1).reshape(M * D, D) @ Q).reshape(M, D, D)
        back = 0.5 * (back + back.transpose(0, 2, 1))
        return VoxelReduction(centroids=P @ Q + self.origin, weights=red.weights, scatter=back,
                              voxel_size=red.voxel_size)


def _half_angle(a: float, b: float) -> tuple[float, float]:
    """``(cos t, sin t)`` where ``2 t`` is the angle of the vector ``(a, b)`` (not zero), with no
    cancellation: the larger of the two by a square root, the other by a division. The opposite
    vector ``(-a, -b)`` (the second moment of the cloud turned by a quarter turn) gives exactly
    ``(-sin t, cos t)`` or its opposite."""
    r = float(np.hypot(a, b))
    cos2, sin2 = a / r, b / r
    if a >= 0.0:
        c = float(np.sqrt(0.5 * (1.0 + cos2)))
        return c, sin2 / (2.0 * c)
    s = float(np.sqrt(0.5 * (1.0 - cos2)))
    return sin2 / (2.0 * s), s


def ladder_size(size: float, up: int = 0) -> float:
    """The smallest voxel edge of the ladder ``2^(k / 16)`` (k an integer; in the cloud's length
    unit) that is at least ``size``, or ``up`` rungs above it.

    A size found by counting voxels (:func:`auto_voxel_size`) moves a little with every count, and
    so with any change of the points, however small: a file rounded to float32 after a turn, a
    point moved by a micrometre. A grid of another size is another fitting set, and on a real scan
    another segmentation (SemanticKITTI 000001 turned by 45 degrees and saved as float32: 6 % of the
    cluster ids moved). Taken from a fixed ladder, the size only moves when the count search lands
    within its own noise of a rung.
    """
    k = math.ceil(math.log2(size) * LADDER_RUNGS - 1e-9) + up
    return 2.0 ** (k / LADDER_RUNGS)


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


def _min_size(X: np.ndarray, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> float:
    """The smallest voxel edge whose cells fit the 20-bit keys (``lo``, ``hi``: X's bounds, when
    known)."""
    if lo is None or hi is None:
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
    fine = max(extent / 4096.0, _min_size(X, lo, hi))
    jit = _jit()
    if jit is not None and X.dtype == np.float64:
        fine_keys = jit.cell_keys(np.ascontiguousarray(X), lo, float(fine))
    else:
        fine_keys = _keys(_cells(X, lo, fine))
    # the counts below do not depend on the order of the distinct cells: no sort needed
    D = X.shape[1]
    if jit is not None:  # the compiled count reads the cells from the keys: no decoded array
        fine_distinct = jit.distinct_keys(fine_keys)
        n_fine = fine_distinct.shape[0]
    else:
        fine_cells = _decode(_distinct(fine_keys), D)
        n_fine = fine_cells.shape[0]
    if n_fine <= target:
        return fine

    def occupied(factor: float) -> int:
        if jit is not None:
            return int(jit.count_coarse_keys(fine_distinct, D, float(factor)))
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


def voxel_reduce(X: np.ndarray, size: float, sample_weight: np.ndarray | None = None, *,
                 expect: int | None = None) -> VoxelReduction:
    """Reduce ``X`` (n, D<=3) to voxel centroids with weights and within-voxel scatter.
    ``expect``: about how many voxels there will be, when known (the compiled hash table starts
    at that size; the result does not depend on it)."""
    n, D = X.shape
    lo, hi = bounds(X)
    size = max(float(size), _min_size(X, lo, hi))
    origin = lo
    jit = _jit()
    w = np.ones(n) if sample_weight is None else sample_weight
    if jit is not None and X.dtype == np.float64 and D <= 3:  # the same arrays, compiled, no (n, D) temporaries
        Xc = np.ascontiguousarray(X)
        keys, inverse = jit.unique_inverse(jit.cell_keys(Xc, origin, float(size)), -1 if expect is None else int(expect))
        M = keys.size
        weights, s1, s2, first = jit.voxel_sums(Xc, origin, float(size), inverse,
                                                np.ascontiguousarray(w, dtype=np.float64), M)
        centroids, weights, scatter = jit.voxel_finish(Xc, origin, float(size), weights, s1, s2, first)
        return VoxelReduction(centroids=centroids, weights=weights, scatter=scatter, voxel_size=size)
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
