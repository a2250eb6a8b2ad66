"""One run of a rule base over a cloud, top to bottom:

1. **partition**: the strategy's first partition of the scene (UFP-ONC, K by APD's first local
   maximum); a scene the engine cannot partition is one cluster;
2. **strategy**: the strategy judges clusters by the rules and divides those a rule wants divided
   (``divisive``: each on its own; ``global``: the next K of the whole scene), finding the ground
   plane from the first partition (:mod:`kbs.knowledge.ground`);
3. **label**: every leaf takes the first label whose condition holds;
4. **post steps**: the rule file's ``post`` sequence, in order (:mod:`kbs.knowledge.post`);
5. **result**: per-point cluster, label and membership, the output clusters and the explanation
   (:class:`~kbs.knowledge.segmentation.Segmentation`).

:class:`RunContext` is what the strategies, actions and post steps may use of the run: the cloud,
the rule base, measuring checks, judging a cluster by the rules, recording a cluster, limits.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kbs.arrays import rows
from kbs.errors import FitError, KbsError, raise_if_interrupted
from kbs.inference import UFPONCResult
from kbs.knowledge import ground as ground_search
from kbs.knowledge.actions import DEFAULT
from kbs.knowledge.explain import Catalogue, CheckRecord, ClusterRecord, Explanation
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.parts import Action
from kbs.knowledge.predicates import Cluster, Ground, PredicateError, Scene
from kbs.knowledge.rulebase import Condition, RuleBase
from kbs.knowledge.segmentation import STOP_KINDS, Segmentation
from kbs.knowledge.state import Draft, Judged, Leaf, Node, PostState
from kbs.knowledge.strategies import STRATEGIES

_ACCEPT = DEFAULT()


#: from this many points, the split workers (jobs > 1) are forked before the first partition, not at
#: the first split: they then hold the input only (docs/PERFORMANCE.md, session 20); on smaller
#: clouds, forked later, they inherit the compiled kernels loaded by the first partition instead of
#: loading them again (about 0.4 s each)
EARLY_WORKERS = 500_000


def run(interpreter: Any, X: np.ndarray) -> Segmentation:
    """Segment points ``X`` (n, 3) with the interpreter's rule base."""
    t0 = time.perf_counter()
    X = np.ascontiguousarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] == 0:
        raise FitError(f"expected a non-empty (n, 3) cloud, got shape {X.shape}")
    if X.shape[0] >= EARLY_WORKERS:
        interpreter.start_workers()
    ctx = RunContext(interpreter, X)
    n = X.shape[0]
    root_draft = ctx.record(Node.root(n))[1]  # its descriptors; neither the root nor its cluster is kept
    root_draft.set(action="partition")
    records: dict[str, Draft] = {"c": root_draft}
    strategy = STRATEGIES[ctx.rule_base.strategy]()
    try:
        first = strategy.partition(ctx, X)  # 1. partition
    except FitError as exc:  # too few or degenerate points: the scene is one cluster
        judged = unpartitioned(ctx, Node.root(n), records, exc)
    else:
        # 2. strategy. The root (three (n,) arrays) and the first partition (its (n, K) memberships)
        # are handed over with no reference left in this frame, so a strategy that is done with
        # them frees them (the divisive one does once the first clusters are made): held here,
        # they stayed until the end of the run, 0.5 GB at 10^7 points (docs/PERFORMANCE.md)
        hand = [first]
        del first
        judged = strategy.run(ctx, X, Node.root(n), records, hand.pop())
    return interpreter.finish(judged, t0)


def finish(ctx: RunContext, judged: Judged, t0: float) -> Segmentation:
    """3. label the leaves, 4. run the post steps, 5. the result."""
    rb = ctx.rule_base
    leaves = tuple(ctx.label(lf, judged.scene) for lf in judged.leaves)
    state = PostState(leaves=leaves, scene=judged.scene, ground_facts=judged.ground_facts)
    if state.leaves:
        post = PostContext(judged.X, rb, ctx.jobs, ctx.measure, ctx.names)
        for step in rb.post:
            # handed over, not held here: a step that builds a new ground surface frees the old one
            # with the state it came in (docs/PERFORMANCE.md, session 21)
            hand = [state]
            del state
            state = step.apply(hand.pop(), post)
    return result(judged, state, rb, t0)


def result(judged: Judged, state: PostState, rb: RuleBase, t0: float) -> Segmentation:
    """The per-point arrays, the output clusters (groups of leaves, the largest first) and the
    explanation."""
    X = judged.X
    leaves = [lf if lf.size else lf.with_record(notes=("every point of it left for other clusters: no output cluster",))
              for lf in state.leaves]
    groups = [[i for i in g if leaves[i].size] for g in (state.groups or [(i,) for i in range(len(leaves))])]
    groups = [g for g in groups if g]
    n = X.shape[0]
    cluster = np.full(n, -1, dtype=np.int32)
    label = np.full(n, -1, dtype=np.int32)
    membership = np.zeros(n, dtype=np.float32)
    groups.sort(key=lambda g: -sum(leaves[i].size for i in g))
    out_clusters = []
    for gi, members in enumerate(groups):
        ids = [leaves[i].id for i in members]
        lab = leaves[members[0]].label
        li = rb.label_names.index(lab) if lab in rb.label_names else -1
        size = 0
        for i in members:
            node = leaves[i].node
            cluster[node.idx] = gi
            label[node.idx] = li
            membership[node.idx] = node.path
            size += node.size
            merged = (f"merged with {len(members) - 1} other coplanar {lab} cluster"
                      f"{'s' if len(members) > 2 else ''} into output cluster {gi}",) if len(members) > 1 else ()
            leaves[i] = leaves[i].with_record(output_index=gi, notes=merged)
        out_clusters.append({"index": gi, "ids": ids, "label": lab, "n_points": int(size),
                             "descriptors": leaves[members[0]].record.descriptors if len(members) == 1 else
                             group_descriptors(X, [leaves[i].node for i in members])})
    records = dict(judged.records)
    records.update((lf.id, lf.record) for lf in leaves)  # the leaves' records as labelling and the steps left them
    expl = Explanation(rule_base=rb.name, rule_file=rb.path, strategy=rb.strategy, label_names=rb.label_names,
                       records=records, root="c", ground=state.ground_facts, notes=list(judged.notes),
                       catalogue=Catalogue.of(rb), sweep=list(judged.sweep))
    return Segmentation(cluster=cluster, label=label, membership=membership, label_names=rb.label_names,
                        explanation=expl, clusters=out_clusters, seconds=time.perf_counter() - t0)


def group_descriptors(X: np.ndarray, nodes: list[Node]) -> dict[str, Any]:
    """The descriptors of merged leaves: the geometry of all their points."""
    from kbs.inference import cluster_geometry

    idx = np.concatenate([nd.idx for nd in nodes])
    geo = cluster_geometry(rows(X, idx), np.concatenate([nd.weight for nd in nodes]))
    return {"center": geo.center.tolist(), "normal": geo.normal.tolist(), "thickness": geo.thickness,
            "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass}


def unpartitioned(ctx: RunContext, root: Node, records: dict[str, Draft], exc: Exception) -> Judged:
    """A scene the engine could not partition: one cluster, judged, and kept whatever the rules
    say (unless rejected)."""
    root_draft = records["c"]
    root_draft.note(f"the scene was not partitioned: {exc}")
    child = Node("c0", "c", 1, root.idx, root.weight, root.path)
    root_draft.set(children=("c0",))
    cl, draft = ctx.record(child)
    records["c0"] = draft
    ground, facts = ctx.ground([(cl, draft)])
    scene = ctx.scene(ground)
    action, _ = ctx.judge(cl, scene, draft)
    if action.divides:
        ctx.stop(draft, "unpartitioned", "it cannot be split: the engine could not partition these points")
    else:
        draft.set(action=action.key)
    kept = [(child, cl, draft)] if action.divides or action.keeps else []  # not kept: noise
    return Judged.of(ctx.X, kept, scene, records, facts)


class Measuring:
    """The outcome of the checks on one cluster, each measured once and recorded in its draft
    (``Measuring(name) -> bool``; :attr:`record`: the record with the checks measured so far)."""

    def __init__(self, rule_base: RuleBase, cluster: Cluster, scene: Scene, draft: Draft) -> None:
        self.rule_base, self.cluster, self.scene, self.draft = rule_base, cluster, scene, draft
        self.done: dict[str, bool] = {c.check: c.passed for c in draft.record.checks}  # measured before: reuse

    @property
    def record(self) -> ClusterRecord:
        return self.draft.record

    def __call__(self, name: str) -> bool:
        if name not in self.done:
            rb, cluster, scene = self.rule_base, self.cluster, self.scene
            check = rb.checks[name]
            if check.predicate.needs_ground and scene.ground is None:
                raise FitError(f"check '{name}' needs the ground plane, which is not known yet")
            try:
                m = check.predicate.measure(cluster, scene, check.params)
            except KbsError:
                raise
            except Exception as exc:  # a predicate's bug must name the predicate and cluster
                raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
                raise PredicateError(f"predicate '{check.predicate.name}' failed on cluster {cluster.id} "
                                     f"({cluster.n_points} points): {type(exc).__name__}: {exc}") from exc
            self.done[name] = m.defined and check.passes(m.value)  # an undefined value fails its check
            self.draft.check(CheckRecord(
                check=name, predicate=check.predicate.name, value=m.value if m.defined else None,
                unit=check.predicate.unit_label(rb.length_unit), min=check.min, max=check.max,
                passed=self.done[name], source=check.pos.short, note=m.undefined or ""), m)
        return self.done[name]


@dataclass(frozen=True)
class PostContext:
    """What a post step's ``apply`` may use (:class:`kbs.knowledge.parts.PostContext`)."""

    X: np.ndarray
    rule_base: RuleBase
    jobs: int
    measure: Callable[[Cluster, Scene, ClusterRecord], Measuring]
    names: Callable[[Condition | None], list[str]]

    def fact(self, cluster: Cluster, scene: Scene, record: ClusterRecord) -> Measuring:
        """The outcome of the checks on a leaf's cluster: ``fact(name) -> bool``, each measured
        once; ``fact.record`` is ``record`` with the checks measured so far (the step gives it to
        the leaf: :meth:`~kbs.knowledge.state.Leaf.with_record`)."""
        return self.measure(cluster, scene, record)


@dataclass
class RunContext:
    """What the strategies and actions may use of one run (the interpreter's settings, the cloud)."""

    interpreter: Any
    X: np.ndarray
    #: the splits under way (set by a strategy while it divides: :meth:`submit_split`)
    splitter: Any = field(default=None, repr=False)

    @property
    def rule_base(self) -> RuleBase:
        return self.interpreter.rb

    @property
    def sensor(self) -> np.ndarray:
        return self.interpreter.sensor

    @property
    def jobs(self) -> int:
        return self.interpreter.jobs

    @property
    def progress(self) -> Callable[[str], None] | None:
        return self.interpreter.progress

    @property
    def given_ground(self) -> tuple[Ground | None, GroundFacts] | None:
        return self.interpreter.given_ground

    # -- the engine ----------------------------------------------------------------------------

    def ufp_kwargs(self, stop: str, min_k: int = 1) -> dict[str, Any]:
        return self.interpreter._ufp_kwargs(stop, min_k)

    def ufp_onc(self, X: np.ndarray, stop: str, min_k: int = 1) -> UFPONCResult:
        return self.interpreter._ufp_onc(X, stop, min_k)

    def initial_k(self, res: UFPONCResult, notes: list[str]) -> int:
        """The K of the scene's first partition: the rule file's fixed initial_k, or APD's choice."""
        ik = self.rule_base.engine["initial_k"]
        if isinstance(ik, int):
            ks = [p.k for p in res.partitions]
            if ik not in ks:
                notes.append(f"initial_k = {ik} could not be reached (the sweep stopped at K = {ks[-1]}: "
                             f"{res.stop_reason}); K = {ks[-1]} is used")
                return ks[-1]
            return ik
        return res.chosen_k

    def submit_split(self, X: np.ndarray) -> Any:
        """Start UFP-ONC on a cluster's points (in a worker when jobs > 1); ``.result()`` waits."""
        return self.splitter.submit(X)

    # -- facts and rules -----------------------------------------------------------------------

    def fact(self, cluster: Cluster, scene: Scene, draft: Draft) -> Measuring:
        """The outcome of a check on ``cluster``, measured once (recorded in ``draft``)."""
        return Measuring(self.rule_base, cluster, scene, draft)

    def measure(self, cluster: Cluster, scene: Scene, record: ClusterRecord) -> Measuring:
        """:meth:`fact` on a frozen record (labelling, the post steps): ``.record`` gives it back
        with the checks measured."""
        return Measuring(self.rule_base, cluster, scene, Draft(record))

    @staticmethod
    def names(cond: Condition | None) -> list[str]:
        return [] if cond is None else list(cond.names)

    def judge(self, cluster: Cluster, scene: Scene, draft: Draft) -> tuple[Action, Any]:
        """The first rule whose condition holds: its action and the rule (accept and None when no
        rule acts)."""
        fact = self.fact(cluster, scene, draft)
        for rule in self.rule_base.rules:
            if rule.condition.evaluate(fact):
                draft.set(rule=rule.name, rule_source=rule.pos.short, decisive=tuple(self.names(rule.condition)))
                return rule.part, rule
        return _ACCEPT, None

    def label(self, leaf: Leaf, scene: Scene) -> Leaf:
        """The leaf with the first label whose condition holds."""
        fact = self.measure(leaf.cluster, scene, leaf.record)
        for lab in self.rule_base.labels:
            if lab.condition is None or lab.condition.evaluate(fact):
                decisive = tuple(self.names(lab.condition)) if fact.record.action == "accept" else fact.record.decisive
                return leaf.with_record(fact.record, label=lab.name, decisive=decisive)
        return leaf.with_record(fact.record, notes=("no label's condition holds",))

    # -- clusters, the scene, limits -------------------------------------------------------------

    def record(self, node: Node) -> tuple[Cluster, Draft]:
        """The cluster of a node and the draft of its new record (with its descriptors)."""
        # the root's points are the cloud (the same values as X[arange(n)], without the copy)
        cl = Cluster(node.id, self.X if node.parent is None and node.size == self.X.shape[0] else rows(self.X, node.idx),
                     node.weight)
        descriptors: dict[str, Any] = {}
        notes: tuple[str, ...] = ()
        if node.size:
            geo = cl.geometry
            descriptors = {
                "center": geo.center.tolist(), "normal": None if geo.degenerate else geo.normal.tolist(),
                "thickness": geo.thickness, "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass,
            }
            if geo.degenerate:
                notes = (f"degenerate: {geo.degeneracy}, no plane: normal/ground angle undefined",)
        return cl, Draft(ClusterRecord(id=node.id, parent=node.parent, depth=node.depth, n_points=node.size,
                                       descriptors=descriptors, notes=notes))

    def ground(self, candidates: list[tuple[Cluster, Draft]]) -> tuple[Ground | None, GroundFacts]:
        """The ground plane, from the first partition's clusters, and the explanation's facts of it
        (:func:`kbs.knowledge.ground.find`)."""
        return ground_search.find(self, self.X, candidates)

    def scene(self, ground: Ground | None) -> Scene:
        return Scene(self.sensor, ground, self.rule_base.units)

    def cannot_split(self, node: Node, n_clusters: int) -> tuple[str, str] | None:
        """(kind, note) of the limit that keeps ``node`` from being split, or None. ``n_clusters``
        counts the clusters of the whole tree so far; only the optional max_clusters uses it."""
        lim = self.rule_base.limits
        if node.depth >= lim["max_depth"]:
            return "max_depth", f"limit reached: max_depth = {lim['max_depth']}"
        if node.size < lim["min_points"]:
            return "min_points", f"limit reached: {node.size} points < min_points = {lim['min_points']}"
        cap = lim.get("max_clusters")
        if cap is not None and n_clusters >= cap:
            return "max_clusters", f"limit reached: max_clusters = {cap}"
        return None

    def stop(self, draft: Draft, kind: str, note: str) -> None:
        """Keep a cluster a rule wanted divided, saying what stopped it."""
        setting = STOP_KINDS[kind]
        value = None
        if setting is not None:
            section, key = setting.split(".")
            value = (self.rule_base.limits if section == "limits" else self.rule_base.engine).get(key)
        draft.set(action="limit", limit={"kind": kind, "setting": setting, "value": value},
                  notes=draft.record.notes + (note,))
