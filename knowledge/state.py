"""The run's state as frozen records: what the strategies, actions and post steps take and give.

- :class:`Node`: a cluster of the split tree as index arrays into the cloud (its points, their
  membership in it, their membership along the path from the scene).
- :class:`Leaf`: a node the strategy kept, with its :class:`~kbs.knowledge.predicates.Cluster`
  (the points and their geometry, computed once) and its explanation record.
- :class:`Judged`: what a strategy hands to labelling: the leaves, the scene (sensor, ground plane),
  the records of the whole tree, the explanation's ground section and notes, the global sweep.
- :class:`PostState`: what the post steps pass along: the leaves (points move between them), the
  explanation's ground section (:class:`~kbs.knowledge.groundfacts.GroundFacts`), the local
  ground surface once built, the groups of leaves a grouping step made.
- :class:`Draft`: a cluster's record while the strategy decides about it, with the measurements
  of its checks; :class:`Division`: what an action that divides a cluster gives.

None of them is changed in place: a step that moves points returns new leaves
(:meth:`Leaf.with_points`) in a new state (``dataclasses.replace``), and a step that decides more
about a leaf gives it a new frozen :class:`~kbs.knowledge.explain.ClusterRecord`
(:meth:`Leaf.with_record`). While a strategy decides about a cluster, its record is built by a
:class:`Draft` and frozen once into the ``records`` of :class:`Judged`.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from kbs.knowledge.explain import APDCurve, CheckRecord, ClusterRecord
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.predicates import Cluster, Measurement, Scene


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
        kids = []
        for i, j in enumerate(order):
            uj = u[:, j][parts[j]]  # gathered once (from the column: faster than u[parts[j], j], the same values): the weight, and a factor of the path
            kids.append(Node(f"{self.id}.{i}" if self.parent is not None else f"c{i}", self.id, self.depth + 1,
                             self.idx[parts[j]], uj, self.path[parts[j]] * uj))
        return kids


@dataclass(frozen=True)
class Division:
    """What an action that divides a cluster gives (:meth:`kbs.knowledge.parts.Action.divide`):
    its children, and the APD curve of the sweep that chose their number when one did."""

    children: tuple[Node, ...]
    apd: APDCurve | None = None

    @classmethod
    def of(cls, out: Division | Sequence[Node]) -> Division:
        """An action's ``divide`` may return a :class:`Division` or its children alone."""
        return out if isinstance(out, Division) else cls(tuple(out))


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
        n = self.node
        return Leaf(Node(n.id, n.parent, n.depth, idx, weight, path), self.cluster, self.record)

    def with_record(self, record: ClusterRecord | None = None, *, notes: tuple[str, ...] = (),
                    **changes: Any) -> Leaf:
        """This leaf with a new record: ``record`` (default: its own) with ``changes`` to its
        fields (``dataclasses.replace``) and ``notes`` added to its notes."""
        rec = record if record is not None else self.record
        if notes:
            changes["notes"] = rec.notes + tuple(notes)
        return Leaf(self.node, self.cluster, rec.evolve(**changes) if changes else rec)


class Draft:
    """The record of a cluster while the strategy decides about it: each change makes a new
    frozen :class:`ClusterRecord` (:attr:`record`), and the measurements of its checks are kept
    beside it (:attr:`facts`: what an action that divides it may use, e.g. the components of a
    failed connexity check). Labelling and the post steps start one from a leaf's record."""

    __slots__ = ("_record", "_changes", "_checks", "_facts")

    def __init__(self, record: ClusterRecord) -> None:
        self._record = record
        self._changes: dict[str, Any] = {}  # decided since the record was last made
        self._checks: list[CheckRecord] = []  # measured since then, in order
        self._facts: dict[str, Measurement] = {}

    @property
    def record(self) -> ClusterRecord:
        """The frozen record with every change so far: made when asked for (one
        ``dataclasses.replace`` for the changes since the last time, not one per check)."""
        if self._changes or self._checks:
            changes = self._changes
            if self._checks:
                changes["checks"] = self._record.checks + tuple(self._checks)
            self._record = self._record.evolve(**changes)
            self._changes, self._checks = {}, []
        return self._record

    def set(self, **changes: Any) -> None:
        """Fields of the record decided (as ``dataclasses.replace``, in order)."""
        if "checks" in changes and self._checks:
            self.record  # noqa: B018 (the checks measured before these come first)
        self._changes.update(changes)

    def note(self, text: str) -> None:
        self._record = self.record.noted(text)

    def check(self, check: CheckRecord, measured: Measurement) -> None:
        """A check measured (or known without measuring) on the cluster."""
        if "checks" in self._changes:
            self.record  # noqa: B018 (a set(checks=...) before it comes first)
        self._checks.append(check)
        self._facts[check.check] = measured

    @property
    def facts(self) -> Mapping[str, Measurement]:
        """The measurements of the checks judged on the cluster so far, by check name (a read-only copy)."""
        return MappingProxyType(dict(self._facts))


@dataclass(frozen=True)
class Judged:
    """What a strategy hands on: its leaves, the scene it judged them in, the records of the whole
    split tree (by id), the explanation's ground section and notes, and the global strategy's
    sweep (one entry per K judged; empty for the divisive strategy)."""

    X: np.ndarray
    leaves: tuple[Leaf, ...]
    scene: Scene
    records: Mapping[str, ClusterRecord]
    ground_facts: GroundFacts
    notes: tuple[str, ...] = ()
    sweep: tuple[dict[str, Any], ...] = ()

    @classmethod
    def of(cls, X: np.ndarray, kept: list[tuple[Node, Cluster, Draft]], scene: Scene, drafts: Mapping[str, Draft],
           ground_facts: GroundFacts, notes: tuple[str, ...] = (), sweep: tuple[dict[str, Any], ...] = ()) -> Judged:
        """What a strategy hands on, its records frozen: the leaves ``kept`` (node, cluster, draft
        of its record, in order), the scene, the drafts of the whole tree's records by id."""
        return cls(X, tuple(Leaf(node, cl, d.record) for node, cl, d in kept), scene,
                   {k: d.record for k, d in drafts.items()}, ground_facts, notes, sweep)


@dataclass(frozen=True)
class Surface:
    """The local ground surface a ``ground_model`` step built, and the leaf (its position in
    :attr:`PostState.leaves`) each of its points came from."""

    model: Any  # kbs.geometry.groundmodel.LocalGround
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
    #: the explanation's ground section: the ground search's facts, and what the steps on the
    #: local ground surface did (:attr:`GroundFacts.local_model`)
    ground_facts: GroundFacts = GroundFacts()
    surface: Surface | None = None
    groups: tuple[tuple[int, ...], ...] | None = None
