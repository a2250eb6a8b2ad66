"""What the steps on the local ground surface share: moving points between leaves, and asking
the surface for batches of leaves at once."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

from kbs.arrays import rows as take_rows
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
        leaves[t] = leaves[t].with_record(notes=(note.format(n=f"{n_in:,}"),))


def surface_batches(X: np.ndarray, todo: Sequence[Leaf], model, may_matter: Callable | None = None,
                    nearest_of: str = "point", asked: np.ndarray | None = None,
                    found: Callable | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """For each leaf of ``todo`` in order: (heights above the local surface, positions of the
    nearest surface points) of its points, asked for batches of leaves of about
    :data:`SURFACE_BATCH` points together (few small queries, bounded temporaries).

    ``may_matter(hp, lo, hi, P, at)``: which points ``P`` (the rows ``at`` of ``X``) the caller
    needs, from their heights above the ground plane and the bounds of the surface under them
    (:meth:`LocalGround.height_bounds`);
    the others are not asked for and come back as NaN (height) and -1 (nearest). The caller
    promises that their outcome is the same either way (the bounds decide it). ``nearest_of``:
    what the caller uses of the nearest surface points (:meth:`LocalGround.query`). ``asked``
    (bool, one per row of ``X``): only those points may be asked, the others come back as not
    asked (the caller knows their outcome). ``found(rows, positions)``: called for each batch with
    the rows of ``X`` queried and the surface positions their heights were taken among
    (:meth:`LocalGround.query`'s ``found``)."""
    batch: list[Leaf] = []
    size = 0
    for i, lf in enumerate(todo):
        batch.append(lf)
        size += lf.size
        if size < SURFACE_BATCH and i + 1 < len(todo):
            continue
        idx = np.concatenate([b.node.idx for b in batch])
        rows = None if asked is None else np.flatnonzero(asked[idx])  # the points that may be asked
        at = idx if rows is None else idx[rows]
        P = take_rows(X, at)
        hp = (P - model.point) @ model.normal
        bounds = model.height_bounds(P) if may_matter is not None and P.shape[0] else None
        ask = None if bounds is None or may_matter is None else np.flatnonzero(may_matter(hp, *bounds, P, at))
        if rows is None and ask is None and found is None:
            ground, nearest = model.query(P, nearest_of=nearest_of)
            h = hp - ground
        else:
            ask = np.arange(P.shape[0]) if ask is None else ask
            at = ask if rows is None else rows[ask]  # their positions in the batch
            h = np.full(idx.size, np.nan)
            nearest = np.full(idx.size, -1, dtype=np.int64)
            among = None if found is None else np.empty((ask.size, min(model.neighbours, model.n_points)),
                                                        dtype=np.int64)
            ground, nearest[at] = model.query(take_rows(P, ask), nearest_of=nearest_of, found=among)
            h[at] = hp[ask] - ground
            if found is not None:
                found(idx[at], among)
        stop = 0
        for b in batch:
            start, stop = stop, stop + b.size
            yield h[start:stop], nearest[start:stop]
        batch, size = [], 0
