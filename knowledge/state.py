"""The run's state as frozen records: what the strategies, actions and post steps take and give.

- :class:`Node`: a cluster of the split tree as index arrays into the cloud (its points, their
  membership in it, their membership along the path from the scene).
- :class:`Leaf`: a node the strategy kept, with its :class:`~kbs.knowledge.predicates.Cluster`
  (the points and their cached measurements) and its explanation record.
- :class:`Judged`: what a strategy hands to labelling: the leaves, the scene (sensor, ground plane),
  the records of the whole tree, the explanation's ground section and notes, the global sweep.
- :class:`PostState`: what the post steps pass along: the leaves (points move between them), the
  local ground surface once built, the groups of leaves a grouping step made.

None of them is changed in place: a step that moves points returns new leaves
(:meth:`Leaf.with_points`) in a new state (``dataclasses.replace``). What is written as the run
goes is the explanation: each leaf's :class:`~kbs.knowledge.explain.ClusterRecord` (an
append-only log of what was decided about it) and the explanation's ``ground`` section.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from kbs.knowledge.explain import ClusterRecord
from kbs.knowledge.predicates import Cluster, Scene


@dataclass(frozen=True)
class Node:
    """A cluster of the split tree: ``idx`` (its points, indices into the cloud), ``weight``
    (their membership in it, from its own split) and ``path`` (their membership along the path
    from the scene: the product of the fuzzy memberships, crisp splits counting 1)."""

    id: str
    parent: str | None
    depth: int
    idx: np.ndarray
    weight: np.ndarray
    path: np.ndarray

    @property
    def size(self) -> int:
        return int(self.idx.size)

    @classmethod
    def root(cls, n: int) -> Node:
        return cls("c", None, 0, np.arange(n), np.ones(n), np.ones(n))

    def children(self, u: np.ndarray) -> list[Node]:
        """Its children from a fuzzy partition of its points (``u``, (n, K) memberships): the hard
        clusters, the largest first, ids path-like under it ('c0.2.1'; the scene's: 'c0', 'c1')."""
        hard = u.argmax(axis=1)
        parts = [np.flatnonzero(hard == j) for j in range(u.shape[1])]
        order = sorted((j for j in range(len(parts)) if parts[j].size), key=lambda j: -parts[j].size)
        return [Node(f"{self.id}.{i}" if self.parent is not None else f"c{i}", self.id, self.depth + 1,
                     self.idx[parts[j]], u[parts[j], j], self.path[parts[j]] * u[parts[j], j])
                for i, j in enumerate(order)]


@dataclass(frozen=True)
class Leaf:
    """A cluster the strategy kept (accepted, or stopped by a limit), with its measurements
    (``cluster``, as judged: post steps that move points do not measure it again) and its
    explanation record."""

    node: Node
    cluster: Cluster
    record: ClusterRecord

    @property
    def id(self) -> str:
        return self.node.id

    @property
    def size(self) -> int:
        return self.node.size

    @property
    def label(self) -> str | None:
        return self.record.label

    def with_points(self, idx: np.ndarray, weight: np.ndarray, path: np.ndarray) -> Leaf:
        """This leaf holding other points (a post step moved some in or out)."""
        return replace(self, node=replace(self.node, idx=idx, weight=weight, path=path))


@dataclass(frozen=True)
class Judged:
    """What a strategy hands on: its leaves, the scene it judged them in, the records of the whole
    split tree (by id), the explanation's ground section and notes, and the global strategy's
    sweep (one entry per K judged; empty for the divisive strategy)."""

    X: np.ndarray
    leaves: tuple[Leaf, ...]
    scene: Scene
    records: dict[str, ClusterRecord]
    ground_info: dict[str, Any]
    notes: tuple[str, ...] = ()
    sweep: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True)
class Surface:
    """The local ground surface a ``ground_model`` step built, and the leaf (its position in
    :attr:`PostState.leaves`) each of its points came from."""

    model: Any  # kbs.knowledge.groundmodel.LocalGround
    owner: np.ndarray
    #: the step that built it (a relabel step builds it again the same way)
    spec: Any = None


@dataclass(frozen=True)
class PostState:
    """What the post steps pass along.

    ``leaves`` keep their positions through the steps (a leaf whose points all left stays, empty,
    and makes no output cluster); ``groups``: leaf positions that form one output cluster, once a
    grouping step (``merge_coplanar``) made them (None: each leaf alone)."""

    leaves: tuple[Leaf, ...]
    scene: Scene
    surface: Surface | None = None
    groups: tuple[tuple[int, ...], ...] | None = None
