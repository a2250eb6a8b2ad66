"""What the steps on the local ground surface share: moving points between leaves, and asking
the surface for batches of leaves at once."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from kbs.knowledge.state import Leaf

#: points per batch of surface queries
SURFACE_BATCH = 1 << 18


def needs_surface(key: str, ctx) -> None:
    """Report a step on the local ground surface that no ground_model step comes before."""
    if not any(s.key == "ground_model" for s in ctx.earlier):
        ctx.add(ctx.path, f"{key} needs post.ground_model (the surface points are measured against)", key=True)


def take(leaf: Leaf, move: np.ndarray, targets: np.ndarray, moved_in: dict) -> tuple[Leaf, list[int]]:
    """Take the points ``move`` (mask) out of ``leaf``, bound for the leaves at positions
    ``targets``; returns the leaf without them and the destination positions."""
    node = leaf.node
    dest = np.unique(targets)
    pos = np.flatnonzero(move)
    for t in dest:
        sel = pos[targets == t]
        moved_in.setdefault(int(t), []).append((node.idx[sel], node.weight[sel], node.path[sel]))
    keep = ~move
    return leaf.with_points(node.idx[keep], node.weight[keep], node.path[keep]), [int(t) for t in dest]


def receive(leaves: list[Leaf], moved_in: dict, note: str) -> None:
    """Append moved points (idx, weight, path) to their destination leaves, with a note."""
    for t, parts in moved_in.items():
        lf = leaves[t]
        n_in = sum(p[0].size for p in parts)
        leaves[t] = lf.with_points(np.concatenate([lf.node.idx] + [p[0] for p in parts]),
                                   np.concatenate([lf.node.weight] + [p[1] for p in parts]),
                                   np.concatenate([lf.node.path] + [p[2] for p in parts]))
        lf.record.notes.append(note.format(n=f"{n_in:,}"))


def surface_batches(X: np.ndarray, todo: Sequence[Leaf], model,
                    may_matter: Callable | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """For each leaf of ``todo`` in order: (heights above the local surface, positions of the
    nearest surface points) of its points, asked for batches of leaves of about
    :data:`SURFACE_BATCH` points together (few small queries, bounded temporaries).

    ``may_matter(hp, lo, hi)``: which points the caller needs, from their heights above the
    ground plane and the bounds of the surface under them (:meth:`LocalGround.height_bounds`);
    the others are not asked for and come back as NaN (height) and -1 (nearest). The caller
    promises that their outcome is the same either way (the bounds decide it)."""
    batch: list[Leaf] = []
    size = 0
    for i, lf in enumerate(todo):
        batch.append(lf)
        size += lf.size
        if size < SURFACE_BATCH and i + 1 < len(todo):
            continue
        P = X[np.concatenate([b.node.idx for b in batch])]
        hp = (P - model.point) @ model.normal
        bounds = model.height_bounds(P) if may_matter is not None else None
        if bounds is None or may_matter is None:
            ground, nearest = model.query(P)
            h = hp - ground
        else:
            ask = np.flatnonzero(may_matter(hp, *bounds))
            h = np.full(P.shape[0], np.nan)
            nearest = np.full(P.shape[0], -1, dtype=np.int64)
            ground, nearest[ask] = model.query(P[ask])
            h[ask] = hp[ask] - ground
        stop = 0
        for b in batch:
            start, stop = stop, stop + b.size
            yield h[start:stop], nearest[start:stop]
        batch, size = [], 0


class Nearest:
    """The nearest of points ``T`` (m, d) to queries, as ``cKDTree(T).query(x)[1]`` gives them,
    on a tree that is cheaper to build (unbalanced, not compacted: 2-3x faster for 40k points).
    Trees of other shapes may differ only where two points are at the same distance from a query
    (which one comes first is the tree's choice): the cheaper tree is asked for the two nearest,
    and a query whose two are not apart by more than a margin (squared: 1e-12 (1 + c^2), c the
    largest coordinate; the trees' pruning rounds squared distances to their cells by a few
    units of 2e-16 c^2 per step of a descent) is asked again on ``cKDTree(T)``, built then. On
    SemanticKITTI 000001 no released point needs it."""

    def __init__(self, T: np.ndarray) -> None:
        self.T = T
        self._fast: Any = None
        self._exact: Any = None

    def query(self, x: np.ndarray, workers: int = 1) -> np.ndarray:
        """Positions in ``T`` (q,) of the nearest point to each row of ``x`` (q, d)."""
        from scipy.spatial import cKDTree

        if self.T.shape[0] < 2:
            return self._exact_tree().query(x, workers=workers)[1]
        if self._fast is None:
            self._fast = cKDTree(self.T, balanced_tree=False, compact_nodes=False)
        d, j = self._fast.query(x, k=2, workers=workers)
        c = max(float(np.abs(self._fast.mins).max()), float(np.abs(self._fast.maxes).max()),
                float(np.abs(x).max()) if x.size else 0.0)
        unsure = ~(d[:, 0] * d[:, 0] < d[:, 1] * d[:, 1] - 1e-12 * (1.0 + c * c))
        out = j[:, 0].copy()
        if unsure.any():
            out[unsure] = self._exact_tree().query(x[unsure], workers=workers)[1]
        return out

    def _exact_tree(self) -> Any:
        from scipy.spatial import cKDTree

        if self._exact is None:
            self._exact = cKDTree(self.T)
        return self._exact
