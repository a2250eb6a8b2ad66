"""The nearest point: scipy's k-d tree answers (``cKDTree(T).query(Q, k=1)`` and the distance to the
nearest other point), from compiled kernels.

A run asks for the nearest point in a few places (a cluster's points given back to the nearest
significant component, released ground points joining the nearest obstacle cluster, the median
spacing of a scan). Building a k-d tree for those is cheap; importing scipy's spatial package to
build it is not (0.25-0.33 s in a fresh process, most of it scipy.sparse's array-API layer), and on
most scans these are the only k-d trees a run needs. The compiled k-d tree
(:func:`kbs.inference._compiled.kdtree_build`) gives the same distances bit for bit and the same
answer wherever the order of equal distances cannot change it; the rows it cannot settle (points of
two labels at the same distance) go to scipy's tree, and so does everything when the kernels are
off (``KBS_JIT=0``).
"""
from __future__ import annotations

import numpy as np

from kbs.inference import _flags

__all__ = ["NearestIndex", "nearest", "nearest_label", "nearest_other_distances"]

def _tree(T: np.ndarray):
    from scipy.spatial import cKDTree

    return cKDTree(T)


class NearestIndex:
    """The points ``T`` (m > 0, D), ready to answer nearest-point queries as ``cKDTree(T).query(Q,
    k=1)`` does, with ``labels`` (m,) int when the caller uses only the nearest point's label (then
    queries whose nearest points at one distance carry several labels are answered by scipy's
    tree, whose order among equal distances is its own). The compiled tree
    (:func:`kbs.inference._compiled.kdtree_build`) is built at once; scipy's only if a query needs
    it."""

    def __init__(self, T: np.ndarray, labels: np.ndarray | None = None) -> None:
        self.T = np.ascontiguousarray(T, dtype=np.float64)
        if self.T.ndim != 2 or self.T.shape[0] == 0:
            raise ValueError(f"NearestIndex needs (m > 0, D) points, got shape {self.T.shape}")
        self.labels = None if labels is None else np.ascontiguousarray(labels, dtype=np.int64)
        self._compiled = None
        if _flags.JIT and np.isfinite(self.T).all():
            from kbs.inference import _compiled

            self._compiled = _compiled.kdtree_build(self.T)
        self._kdtree = None

    @property
    def tree(self):
        """scipy's k-d tree over the points, built (and scipy imported) when first asked."""
        if self._kdtree is None:
            self._kdtree = _tree(self.T)
        return self._kdtree

    def query(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The distance from each row of ``Q`` (q, D) to its nearest point, and that point's row."""
        Q = np.ascontiguousarray(Q, dtype=np.float64).reshape(-1, self.T.shape[1])
        if Q.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        if self._compiled is None or not np.isfinite(Q).all():
            d, i = self.tree.query(Q, k=1)
            return np.asarray(d, dtype=np.float64), np.asarray(i, dtype=np.int64)
        from kbs.inference import _compiled

        lab = np.zeros(0, dtype=np.int64) if self.labels is None else self.labels
        d, i, ok = _compiled.kdtree_nearest(Q, self.T, *self._compiled, lab)  # type: ignore[call-arg]
        redo = np.flatnonzero(~ok)
        if redo.size:
            d[redo], i[redo] = self.tree.query(Q[redo], k=1)
        return d, i

    def label(self, Q: np.ndarray) -> np.ndarray:
        """The label of each row of ``Q``'s nearest point (the k-d tree's, where labels tie)."""
        assert self.labels is not None, "NearestIndex built without labels"
        return self.labels[self.query(Q)[1]]


def nearest(Q: np.ndarray, T: np.ndarray, labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``cKDTree(T).query(Q, k=1)``: the distance from each row of ``Q`` (q, D) to its nearest row
    of ``T`` (m > 0, D), and that row. With ``labels`` (m,) int, the row given is one of the
    k-d tree's label wherever points of several labels lie at the nearest distance (the tree's
    own row for those queries); without, any row at the nearest distance."""
    return NearestIndex(T, labels).query(Q)


def nearest_label(Q: np.ndarray, T: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The label (``labels`` (m,) int, of the rows of ``T``) of each row of ``Q``'s nearest row of
    ``T``: ``labels[cKDTree(T).query(Q, k=1)[1]]``."""
    return NearestIndex(T, labels).label(Q)


def nearest_other_distances(X: np.ndarray) -> np.ndarray:
    """The distance from each row of ``X`` (n >= 2, D >= 2) to its nearest other row:
    ``cKDTree(X).query(X, k=2)[0][:, 1]`` (0 where a row is repeated), bit for bit. Compiled: a
    grid over the first two columns (:func:`kbs.inference._compiled.nearest_other_distances`,
    cells of about 16 points), the k-d tree when that grid does not fit."""
    X = np.asarray(X, dtype=np.float64)
    n = X.shape[0]
    if _flags.JIT and n >= 2 and X.ndim == 2 and X.shape[1] >= 2 and np.isfinite(X).all():
        from kbs.inference import _compiled

        extent = np.ptp(X[:, :2], axis=0)
        area = float(np.prod(np.maximum(extent, extent.max() * 1e-3)))
        d, ok = _compiled.nearest_other_distances(np.ascontiguousarray(X), 4.0 * float(np.sqrt(area / n)))
        if ok:
            return d
    return np.asarray(_tree(X).query(X, k=2)[0][:, 1], dtype=np.float64)
