"""Stitching the results of the tiles of one cloud into one result.

Each point takes the result of the tile whose core holds it. A cluster that crosses a tile edge
is segmented twice near that edge, once by each tile (core and buffer); the two are one cluster
when they share enough buffer points with the same label: at least :data:`MIN_SHARED_POINTS`,
and half of the points either has in the region both tiles hold (or half of the smaller one's
there, when that region holds at least 5 % of its cluster: a tile may give a few points of an
object to its neighbour, which must not merge the two objects). Such clusters are merged, transitively,
into one output cluster with one id, and the explanation says so: its ``clusters`` entry has
``stitched`` (the tiles and tile clusters it was made of) and every tile record merged into it a
note.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kbs.arrays import rows
from kbs.knowledge.explain import ClusterRecord, Explanation
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.interpreter import Segmentation
from kbs.tiles.grid import Tile, TileGrid

#: Two clusters of neighbouring tiles are one when they share at least this many points ...
MIN_SHARED_POINTS = 10
#: ... and at least this fraction of the points either has in the region both tiles hold (or of the
#: smaller one's there, when they are at least MIN_SHARED_OF_CLUSTER of its whole cluster).
MIN_SHARED_FRACTION = 0.5
MIN_SHARED_OF_CLUSTER = 0.05
#: The record at the top of a tiled explanation; its children are the roots of the tiles.
ROOT = "tiles"


@dataclass(frozen=True)
class TiledSegmentation(Segmentation):
    """A :class:`~kbs.knowledge.interpreter.Segmentation` stitched from tiles, with ``tiling``:
    the grid (``size``, ``buffer``, ``axes``, ``origin``, ``shape``), ``stitched`` (output clusters
    made of several tile clusters) and ``tiles`` (each one's ``name``, ``core`` bounds
    ``[u_min, v_min, u_max, v_max]``, ``points`` with its buffer and ``core_points``)."""

    tiling: dict[str, Any] = field(default_factory=dict)


class _Union:
    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)

    def find(self, a: int) -> int:
        p = self.parent
        while p[a] != a:
            p[a] = p[p[a]]
            a = p[a]
        return int(a)

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)  # the smaller node (earlier tile) stays the root

    def roots(self) -> np.ndarray:
        """Every node's root (what :meth:`find` gives each), by pointer jumping over the whole
        array: no Python object per node."""
        p = self.parent
        while True:
            q = p[p]
            if np.array_equal(q, p):
                return q
            p = q


def _links(a: Tile, ra: Segmentation, b: Tile, rb: Segmentation) -> list[tuple[int, int, int]]:
    """(cluster of a, cluster of b, shared points) for the clusters of two tiles that are one."""
    size_a = np.bincount(ra.cluster[ra.cluster >= 0], minlength=len(ra.clusters))
    size_b = np.bincount(rb.cluster[rb.cluster >= 0], minlength=len(rb.clusters))
    return pair_links(a.index, ra.cluster, ra.label, size_a, b.index, rb.cluster, rb.label, size_b)


def pair_links(index_a: np.ndarray, cluster_a: np.ndarray, label_a: np.ndarray, size_a: np.ndarray,
               index_b: np.ndarray, cluster_b: np.ndarray, label_b: np.ndarray,
               size_b: np.ndarray) -> list[tuple[int, int, int]]:
    """:func:`_links` from the points of two tiles that the other may hold: ``index_a`` (increasing
    indices into the cloud) with their ``cluster_a`` and ``label_a``, and ``size_a``, the points of
    each cluster of tile a in the whole tile (likewise for b). Any superset of the points both tiles
    hold gives the same links (a streamed run passes the points near the tiles' edges alone)."""
    _, ia, ib = np.intersect1d(index_a, index_b, assume_unique=True, return_indices=True)
    if ia.size == 0:
        return []
    ca, cb = cluster_a[ia].astype(np.int64), cluster_b[ib].astype(np.int64)
    na = np.bincount(ca[ca >= 0], minlength=len(size_a))
    nb = np.bincount(cb[cb >= 0], minlength=len(size_b))
    both = (ca >= 0) & (cb >= 0) & (label_a[ia] == label_b[ib])
    pairs, counts = np.unique(np.stack([ca[both], cb[both]], axis=1), axis=0, return_counts=True)
    out = []
    for (x, y), k in zip(pairs.tolist(), counts.tolist()):
        if k < MIN_SHARED_POINTS:
            continue
        if k >= MIN_SHARED_FRACTION * max(na[x], nb[y]):  # most of each one's shared points are the other's
            out.append((x, y, k))
            continue
        # one lies mostly inside the other there (a cluster one tile split and the other did not),
        # and is not a sliver of a cluster that lies elsewhere (points a tile gave the wrong object)
        small, size = (na[x], size_a[x]) if na[x] <= nb[y] else (nb[y], size_b[y])
        if k >= MIN_SHARED_FRACTION * small and small >= MIN_SHARED_OF_CLUSTER * size:
            out.append((x, y, k))
    return out


#: The neighbours of a tile (i + di, j + dj) its links are looked for with: each neighbouring pair once.
NEIGHBOURS = ((0, 1), (1, -1), (1, 0), (1, 1))


def stitch(X: np.ndarray, grid: TileGrid, tiles: Sequence[Tile], results: Sequence[Segmentation], *,
           seconds: float, notes: Sequence[str] = (), ground: GroundFacts | None = None) -> TiledSegmentation:
    """One result for the cloud ``X`` from the results of its tiles.

    Parameters
    ----------
    X : ndarray (n_points, 3)
        The whole cloud.
    grid : TileGrid
        The grid of the tiles.
    tiles : sequence of Tile
        The tiles (:meth:`~kbs.tiles.grid.TileGrid.tiles`); their cores partition the points.
    results : sequence of Segmentation
        The result of each tile, segmented with ``X[tile.index]``, same order as ``tiles``.
    seconds : float
        The wall time of the whole run (the result's ``seconds``).
    notes : sequence of str
        Added to the explanation's notes.
    ground : GroundFacts, optional
        The whole cloud's ground plane every tile was given (its explanation, as
        :func:`kbs.tiles.run.scene_ground` returns it): the explanation's ``ground``, with each
        tile's own (its local ground surface) under ``tiles``. None: the tiles found their own.

    Returns
    -------
    TiledSegmentation
        Per point ``cluster`` (output clusters numbered by decreasing size, -1 noise), ``label``,
        ``membership`` as in the tile whose core holds the point; ``clusters`` with ``stitched``
        for the clusters made of several tile clusters; an explanation whose root, ``tiles``, has
        the tiles' trees as children (record ids prefixed with the tile name: ``t0_1/c1.0``).
    """
    from kbs.inference import cluster_geometry

    n = X.shape[0]
    offsets = np.concatenate([[0], np.cumsum([len(r.clusters) for r in results])]).astype(np.int64)
    uf = _Union(int(offsets[-1]))
    shared: dict[int, list[str]] = {}
    by_cell = {(t.i, t.j): k for k, t in enumerate(tiles)}
    for ka, a in enumerate(tiles):
        for di, dj in NEIGHBOURS:
            kb = by_cell.get((a.i + di, a.j + dj))
            if kb is None:
                continue
            b = tiles[kb]
            for x, y, k in _links(a, results[ka], b, results[kb]):
                uf.union(int(offsets[ka] + x), int(offsets[kb] + y))
                shared.setdefault(int(offsets[ka] + x), []).append(f"{b.name} cluster {y} ({k:,} shared points)")
                shared.setdefault(int(offsets[kb] + y), []).append(f"{a.name} cluster {x} ({k:,} shared points)")

    cluster = np.full(n, -1, dtype=np.int32)
    label = np.full(n, -1, dtype=np.int32)
    membership = np.zeros(n, dtype=np.float32)
    node = np.full(n, -1, dtype=np.int64)  # the tile cluster (global node number) of each point
    for k, (t, r) in enumerate(zip(tiles, results)):
        core = t.index[t.in_core]
        local = r.cluster[t.in_core].astype(np.int64)
        label[core] = r.label[t.in_core]
        membership[core] = r.membership[t.in_core]
        node[core] = np.where(local >= 0, offsets[k] + local, -1)
    roots = uf.roots()
    kept = node >= 0
    point_root = np.full(n, -1, dtype=np.int64)
    point_root[kept] = roots[node[kept]]
    sizes = np.bincount(point_root[kept], minlength=int(offsets[-1]))
    alive = np.flatnonzero(sizes)  # components holding at least one output point
    order = alive[np.lexsort((alive, -sizes[alive]))]  # by decreasing size, then earliest tile
    out_of_root = np.full(int(offsets[-1]) + 1, -1, dtype=np.int64)
    out_of_root[order] = np.arange(order.size)
    cluster[kept] = out_of_root[point_root[kept]].astype(np.int32)

    tile_of = np.searchsorted(offsets, np.arange(int(offsets[-1])), side="right") - 1
    members: dict[int, list[int]] = {}
    for g in range(int(offsets[-1])):
        members.setdefault(int(roots[g]), []).append(g)
    weights = membership.astype(np.float64)
    point_order = np.argsort(cluster, kind="stable")
    starts = np.searchsorted(cluster[point_order], np.arange(order.size + 1))
    out_clusters: list[dict[str, Any]] = []
    for gi, root in enumerate(order.tolist()):
        idx = point_order[starts[gi]:starts[gi + 1]]
        parts = []
        for g in members[root]:
            k = int(tile_of[g])
            c = int(g - offsets[k])
            entry = results[k].clusters[c]
            in_core = int(np.count_nonzero(node[idx] == g))
            if in_core:  # a tile cluster only in a buffer gave its points to the neighbour's core
                parts.append({"tile": tiles[k].name, "cluster": c, "label": entry["label"], "core_points": in_core,
                              "ids": [f"{tiles[k].name}/{i}" for i in entry["ids"]]})
        geo = cluster_geometry(rows(X, idx), weights[idx])
        item = {"index": gi, "ids": [i for p in parts for i in p["ids"]], "label": parts[0]["label"],
                "n_points": int(idx.size),
                "descriptors": {"center": geo.center.tolist(), "normal": geo.normal.tolist(),
                                "thickness": geo.thickness, "eigenvalues": geo.eigenvalues.tolist(),
                                "mass": geo.mass}}
        if len(parts) > 1:
            item["stitched"] = parts
        out_clusters.append(item)

    n_stitched = sum("stitched" in c for c in out_clusters)
    stitched = {c["index"] for c in out_clusters if "stitched" in c}
    expl = _explanation(tiles, results, offsets, roots, out_of_root, shared, stitched, n, notes, ground)
    tiling = {"size": grid.size, "buffer": grid.buffer, "axes": grid.axes.tolist(), "origin": list(grid.origin),
              "shape": list(grid.shape), "stitched": n_stitched,
              "tiles": [{"name": t.name, "core": list(t.core), "points": int(t.index.size),
                         "core_points": int(np.count_nonzero(t.in_core))} for t in tiles]}
    return TiledSegmentation(cluster=cluster, label=label, membership=membership,
                             label_names=list(results[0].label_names), explanation=expl, clusters=out_clusters,
                             seconds=seconds, tiling=tiling)


def _explanation(tiles, results, offsets, roots, out_of_root, shared, stitched, n, notes, given) -> Explanation:
    first = results[0].explanation
    records: dict[str, ClusterRecord] = {}
    children = []
    grounds = {}
    for k, (t, r) in enumerate(zip(tiles, results)):
        e = r.explanation
        grounds[t.name] = e.ground
        children.append(f"{t.name}/{e.root}")
        for rec in tile_records(t.name, e, int(offsets[k]), roots, out_of_root, shared, stitched):
            records[rec.id] = rec
    records[ROOT] = ClusterRecord(id=ROOT, parent=None, depth=0, n_points=n, action="partition",
                                  children=tuple(children),
                                  notes=(f"{len(tiles)} tiles: " + ", ".join(t.bounds_text() for t in tiles),))
    sources = sorted({str(g.source or "not used") for g in grounds.values()})
    if given is not None and given:
        ground = dataclasses.replace(given, tiles=grounds)
    else:
        ground = GroundFacts(source=f"per tile ({', '.join(sources)})", tiles=grounds)
    tile_notes = [f"{t.name}: {note}" for t, r in zip(tiles, results) for note in r.explanation.notes]
    k = len(stitched)
    summary = f"{len(tiles)} tiles; {k} output cluster{'s' if k != 1 else ''} stitched across tile edges"
    return Explanation(rule_base=first.rule_base, rule_file=first.rule_file, strategy=first.strategy,
                       label_names=list(first.label_names), records=records, root=ROOT, ground=ground,
                       notes=[summary, *notes, *tile_notes], catalogue=first.catalogue)


def tile_records(name: str, e: Explanation, offset: int, roots: np.ndarray, out_of_root: np.ndarray,
                 shared: Mapping[int, list[str]], stitched: Container[int]) -> Iterator[ClusterRecord]:
    """The records of one tile's explanation ``e`` as the stitched explanation holds them, in its
    order: ids prefixed with the tile's ``name``, the output cluster each became, notes on the
    stitched ones and on those only in the buffer (``offset``: the tile's first node number)."""
    for rec in e.walk():
        d = dict(vars(rec))
        d["notes"] = list(rec.notes)
        yield ClusterRecord(**stitched_record(d, name, offset, roots, out_of_root, shared, stitched))


def stitched_record(d: dict[str, Any], name: str, offset: int, roots: np.ndarray, out_of_root: np.ndarray,
                    shared: Mapping[int, list[str]], stitched: Container[int]) -> dict[str, Any]:
    """One record of a tile (its fields ``d``, changed in place and returned) as the stitched
    explanation holds it (:func:`tile_records`)."""
    output_index = d["output_index"]
    renamed(d, name)
    if output_index is not None:
        g = offset + output_index
        out = int(out_of_root[roots[g]])
        d["output_index"] = out if out >= 0 else None
        note = stitch_note(name, g, out, shared, stitched)
        if note is not None:
            d["notes"].append(note)
    return d


def renamed(d: dict[str, Any], name: str) -> dict[str, Any]:
    """What :func:`stitched_record` changes in a record ``d`` of tile ``name`` that does not depend
    on the other tiles: its id, parent and children prefixed with the tile, one level deeper."""
    rid, parent = d["id"], d["parent"]
    d["id"] = f"{name}/{rid}"
    d["parent"] = f"{name}/{parent}" if parent else ROOT
    d["depth"] = d["depth"] + 1
    d["children"] = [f"{name}/{c}" for c in d["children"]]
    return d


def stitch_note(name: str, g: int, out: int, shared: Mapping[int, list[str]], stitched: Container[int]) -> str | None:
    """The note :func:`stitched_record` adds to a record of tile ``name`` that became tile cluster
    node ``g`` and output cluster ``out`` (-1: none, its points in other tiles' cores), or None."""
    if out < 0:
        return f"only in the buffer of tile {name}: its points are in the cores of other tiles, which took them"
    if out in stitched:
        links = f": shares buffer points with {'; '.join(shared[g])}" if g in shared else ""
        return f"stitched across tile edges into output cluster {out}{links}"
    return None
