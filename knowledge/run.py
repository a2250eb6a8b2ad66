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

from kbs.errors import FitError, KbsError
from kbs.inference import UFPONCResult
from kbs.knowledge import ground as ground_search
from kbs.knowledge.actions import DEFAULT
from kbs.knowledge.explain import Catalogue, CheckRecord, ClusterRecord, Explanation
from kbs.knowledge.parts import Action
from kbs.knowledge.predicates import Cluster, Ground, PredicateError, Scene
from kbs.knowledge.rulebase import Condition, RuleBase
from kbs.knowledge.segmentation import STOP_KINDS, Segmentation
from kbs.knowledge.state import Judged, Leaf, Node, PostState
from kbs.knowledge.strategies import STRATEGIES

_ACCEPT = DEFAULT()


def run(interpreter: Any, X: np.ndarray) -> Segmentation:
    """Segment points ``X`` (n, 3) with the interpreter's rule base."""
    t0 = time.perf_counter()
    X = np.ascontiguousarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] == 0:
        raise FitError(f"expected a non-empty (n, 3) cloud, got shape {X.shape}")
    ctx = RunContext(interpreter, X)
    root = Node.root(X.shape[0])
    _, root_rec = ctx.record(root)  # its descriptors; the cluster itself (a copy of X) is not kept
    root_rec.action = "partition"
    records: dict[str, ClusterRecord] = {"c": root_rec}
    strategy = STRATEGIES[ctx.rule_base.strategy]()
    try:
        first = strategy.partition(ctx, X)  # 1. partition
    except FitError as exc:  # too few or degenerate points: the scene is one cluster
        judged = unpartitioned(ctx, root, records, exc)
    else:
        judged = strategy.run(ctx, X, root, records, first)  # 2. strategy
    return interpreter.finish(judged, t0)


def finish(ctx: RunContext, judged: Judged, t0: float) -> Segmentation:
    """3. label the leaves, 4. run the post steps, 5. the result."""
    rb = ctx.rule_base
    for lf in judged.leaves:
        ctx.label(lf.cluster, judged.scene, lf.record)
    state = PostState(leaves=judged.leaves, scene=judged.scene)
    if state.leaves:
        post = PostContext(judged.X, rb, ctx.jobs, judged.ground_info, ctx.fact, ctx.names)
        for step in rb.post:
            state = step.apply(state, post)
    return result(judged, state, rb, t0)


def result(judged: Judged, state: PostState, rb: RuleBase, t0: float) -> Segmentation:
    """The per-point arrays, the output clusters (groups of leaves, the largest first) and the
    explanation."""
    X, leaves = judged.X, state.leaves
    for lf in leaves:
        if not lf.size:
            lf.record.notes.append("every point of it left for other clusters: no output cluster")
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
            node, rec = leaves[i].node, leaves[i].record
            cluster[node.idx] = gi
            label[node.idx] = li
            membership[node.idx] = node.path
            rec.output_index = gi
            size += node.size
            if len(members) > 1:
                rec.notes.append(f"merged with {len(members) - 1} other coplanar {lab} cluster"
                                 f"{'s' if len(members) > 2 else ''} into output cluster {gi}")
        out_clusters.append({"index": gi, "ids": ids, "label": lab, "n_points": int(size),
                             "descriptors": leaves[members[0]].record.descriptors if len(members) == 1 else
                             group_descriptors(X, [leaves[i].node for i in members])})
    expl = Explanation(rule_base=rb.name, rule_file=rb.path, strategy=rb.strategy, label_names=rb.label_names,
                       records=judged.records, root="c", ground=judged.ground_info, notes=list(judged.notes),
                       catalogue=Catalogue.of(rb), sweep=list(judged.sweep))
    return Segmentation(cluster=cluster, label=label, membership=membership, label_names=rb.label_names,
                        explanation=expl, clusters=out_clusters, seconds=time.perf_counter() - t0)


def group_descriptors(X: np.ndarray, nodes: list[Node]) -> dict[str, Any]:
    """The descriptors of merged leaves: the geometry of all their points."""
    from kbs.inference import cluster_geometry

    idx = np.concatenate([nd.idx for nd in nodes])
    geo = cluster_geometry(X[idx], np.concatenate([nd.weight for nd in nodes]))
    return {"center": geo.center.tolist(), "normal": geo.normal.tolist(), "thickness": geo.thickness,
            "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass}


def unpartitioned(ctx: RunContext, root: Node, records: dict[str, ClusterRecord], exc: Exception) -> Judged:
    """A scene the engine could not partition: one cluster, judged, and kept whatever the rules
    say (unless rejected)."""
    root_rec = records["c"]
    root_rec.notes.append(f"the scene was not partitioned: {exc}")
    child = Node("c0", "c", 1, root.idx, root.weight, root.path)
    root_rec.children = ["c0"]
    cl, rec = ctx.record(child)
    records["c0"] = rec
    info: dict[str, Any] = {}
    scene = ctx.scene(ctx.ground([(cl, rec)], info))
    action, _ = ctx.judge(cl, scene, rec)
    if action.divides:
        ctx.stop(rec, "unpartitioned", "it cannot be split: the engine could not partition these points")
    else:
        rec.action = action.key
    leaves = (Leaf(child, cl, rec),) if action.divides or action.keeps else ()  # not kept: noise
    return Judged(ctx.X, leaves, scene, records, info)


@dataclass(frozen=True)
class PostContext:
    """What a post step's ``apply`` may use (:class:`kbs.knowledge.parts.PostContext`)."""

    X: np.ndarray
    rule_base: RuleBase
    jobs: int
    ground_info: dict[str, Any]
    fact: Callable[[Cluster, Scene, ClusterRecord], Callable[[str], bool]]
    names: Callable[[Condition | None], list[str]]


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
    def given_ground(self) -> tuple[Ground | None, dict[str, Any]] | None:
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

    def fact(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> Callable[[str], bool]:
        """The outcome of a check on ``cluster``, measured once (recorded in ``rec``)."""
        rb = self.rule_base
        done: dict[str, bool] = {c.check: c.passed for c in rec.checks}  # measured before: reuse

        def fact(name: str) -> bool:
            if name not in done:
                check = rb.checks[name]
                if check.predicate.needs_ground and scene.ground is None:
                    raise FitError(f"check '{name}' needs the ground plane, which is not known yet")
                try:
                    m = check.predicate.measure(cluster, scene, check.params)
                except KbsError:
                    raise
                except Exception as exc:  # a predicate's bug must name the predicate and cluster
                    raise PredicateError(f"predicate '{check.predicate.name}' failed on cluster {cluster.id} "
                                         f"({cluster.n_points} points): {type(exc).__name__}: {exc}") from exc
                done[name] = m.defined and check.passes(m.value)  # an undefined value fails its check
                cluster.cache[name] = m
                rec.checks.append(CheckRecord(
                    check=name, predicate=check.predicate.name, value=m.value if m.defined else None,
                    unit=check.predicate.unit_label(rb.length_unit), min=check.min, max=check.max,
                    passed=done[name], source=check.pos.short, note=m.undefined or ""))
            return done[name]

        return fact

    @staticmethod
    def names(cond: Condition | None) -> list[str]:
        return [] if cond is None else list(dict.fromkeys(f.name for f in cond.facts()))

    def judge(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> tuple[Action, Any]:
        """The first rule whose condition holds: its action and the rule (accept and None when no
        rule acts)."""
        fact = self.fact(cluster, scene, rec)
        for rule in self.rule_base.rules:
            if rule.condition.evaluate(fact):
                rec.rule, rec.rule_source = rule.name, rule.pos.short
                rec.decisive = self.names(rule.condition)
                return rule.part, rule
        return _ACCEPT, None

    def label(self, cluster: Cluster, scene: Scene, rec: ClusterRecord) -> None:
        """The first label whose condition holds."""
        fact = self.fact(cluster, scene, rec)
        for lab in self.rule_base.labels:
            if lab.condition is None or lab.condition.evaluate(fact):
                rec.label = lab.name
                if rec.action == "accept":
                    rec.decisive = self.names(lab.condition)
                return
        rec.notes.append("no label's condition holds")

    # -- clusters, the scene, limits -------------------------------------------------------------

    def record(self, node: Node) -> tuple[Cluster, ClusterRecord]:
        """The cluster of a node and its new record (with its descriptors)."""
        cl = Cluster(node.id, self.X[node.idx], node.weight)
        rec = ClusterRecord(id=node.id, parent=node.parent, depth=node.depth, n_points=node.size)
        if node.size:
            geo = cl.geometry
            rec.descriptors = {
                "center": geo.center.tolist(), "normal": None if geo.degenerate else geo.normal.tolist(),
                "thickness": geo.thickness, "eigenvalues": geo.eigenvalues.tolist(), "mass": geo.mass,
            }
            if geo.degenerate:
                rec.notes.append(f"degenerate: {geo.degeneracy}, no plane: normal/ground angle undefined")
        return cl, rec

    def ground(self, candidates: list[tuple[Cluster, ClusterRecord]], info: dict[str, Any]) -> Ground | None:
        """The ground plane, from the first partition's clusters (:func:`kbs.knowledge.ground.find`)."""
        return ground_search.find(self, self.X, candidates, info)

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

    def stop(self, rec: ClusterRecord, kind: str, note: str) -> None:
        """Keep a cluster a rule wanted divided, saying what stopped it."""
        setting = STOP_KINDS[kind]
        value = None
        if setting is not None:
            section, key = setting.split(".")
            value = (self.rule_base.limits if section == "limits" else self.rule_base.engine).get(key)
        rec.action = "limit"
        rec.limit = {"kind": kind, "setting": setting, "value": value}
        rec.notes.append(note)
