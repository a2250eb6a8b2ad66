"""``global``: the seed paper's strategy, the whole scene's K-partition for growing K."""
from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from kbs.inference import first_local_max
from kbs.inference.incremental import IncrementalSweep
from kbs.knowledge.explain import APDCurve
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.parts import Strategy
from kbs.knowledge.state import Draft, Judged, Node


class GlobalSweep(Strategy):
    """The seed paper's strategy: the whole scene's K-partition, K from APD's first local maximum;
    while a rule wants some cluster divided (a heuristic fails on it), the (K+1)-partition of the
    whole scene, seeded from the K-partition with the new prototype in the largest failing cluster
    (its prototype split in two along its largest axis; when that cluster's new prototype dies, the
    next failing cluster, then UFP-ONC's own way V), until no rule wants a division or K = k_max.
    Every K visited is recorded in the explanation's ``sweep``: its clusters with centre, axes and
    outcome, the cluster its new prototype was seeded in.
    """

    key: ClassVar[str] = "global"

    def partition(self, run: Any, X: np.ndarray) -> IncrementalSweep:
        """The whole scene's incremental sweep, at K = 1. A cluster dies under the engine's own
        minimum size (0.1 % of the points) or limits.min_points, whichever is smaller: a K + 1
        sought for a small thick cluster must not kill the small planar clusters beside it (on the
        generated polyhedral scenes, the engine's 0.1 % stopped the sweep before every face was
        found)."""
        e = run.rule_base.engine
        return IncrementalSweep(X, m=e["m"], tol=e["tol"], fcm_tol=e["fcm_tol"], max_iter=e["max_iter"],
                                min_variance=e["min_variance"],
                                max_condition=e["max_condition"], max_fit_points=e["max_fit_points"],
                                min_cluster_size=min(float(run.rule_base.limits["min_points"]),
                                                     max(4.0, 1e-3 * len(X))))

    @staticmethod
    def first_k(run: Any, sweep: IncrementalSweep, notes: list[str]) -> tuple[int, list[tuple[int, float]]]:
        """Grow the sweep with UFP-ONC's own incremental init (way V) up to APD's first local
        maximum (or the rule file's fixed initial_k), then go back to that K."""
        e = run.rule_base.engine
        ik = e["initial_k"]
        while sweep.k < e["k_max"]:
            parts = sweep.partitions
            if isinstance(ik, int) and sweep.k >= ik:
                break
            if not isinstance(ik, int) and len(parts) >= 3 and parts[-1].apd <= parts[-2].apd:
                break  # the first local maximum (among K >= 2) is confirmed
            if sweep.grow() is None:
                break
        eligible = [p for p in sweep.partitions if p.k >= 2] or sweep.partitions
        if isinstance(ik, int):
            k0 = min(ik, sweep.k)
            if k0 < ik:
                notes.append(f"initial_k = {ik} could not be reached (the sweep stopped at K = {k0}); K = {k0} is used")
        else:
            k0 = eligible[first_local_max([p.apd for p in eligible])].k
        first = [(p.k, p.apd) for p in sweep.partitions]
        sweep.back_to(k0)
        return k0, first

    @staticmethod
    def clusters(X: np.ndarray, root: Node, sweep: IncrementalSweep) -> list[tuple[Node, int]]:
        """The clusters of the sweep's last partition (ids c0, c1, ... by decreasing size), each with
        its column in the partition."""
        u = sweep.memberships(X)
        hard = u.argmax(axis=1)
        parts = [np.flatnonzero(hard == j) for j in range(u.shape[1])]
        order = sorted((j for j in range(len(parts)) if parts[j].size), key=lambda j: -parts[j].size)
        return [(Node(f"c{i}", root.id, 1, root.idx[parts[j]], u[parts[j], j], u[parts[j], j]), j)
                for i, j in enumerate(order)]

    def run(self, run: Any, X: np.ndarray, root: Node, records: dict[str, Draft],
            sweep: IncrementalSweep) -> Judged:
        rb = run.rule_base
        k_max = rb.engine["k_max"]
        min_points = rb.limits["min_points"]
        notes: list[str] = []
        steps: list[dict[str, Any]] = []
        ground_facts = GroundFacts()
        k0, first = self.first_k(run, sweep, notes)
        scene = None
        seeded: str | None = None
        while True:
            kids = self.clusters(X, root, sweep)
            judged = [(node, j, *run.record(node)) for node, j in kids]
            if scene is None:  # the ground plane from the first partition judged, as the divisive strategy does
                ground, ground_facts = run.ground([(cl, rec) for _, _, cl, rec in judged])
                scene = run.scene(ground)
            failing = []
            for node, j, cl, rec in judged:
                action, _rule = run.judge(cl, scene, rec)
                rec.set(action=action.key)
                if action.divides:
                    if node.size < min_points:
                        run.stop(rec, "min_points", f"limit reached: {node.size} points < min_points = {min_points}")
                    else:
                        failing.append((node, j))
            steps.append(self.step_record(sweep, judged, seeded))
            if not failing or sweep.k >= k_max:
                break
            grown = None
            for node, j in failing:  # the largest first (ids are by decreasing size)
                if sweep.grow(target=j, name=f"{node.id} of K={sweep.k}") is not None:
                    grown = node.id
                    break
            if grown is None and sweep.grow() is None:
                break
            seeded = grown or "anywhere (way V)"
            steps[-1]["next"] = seeded
        k = sweep.k
        for st in steps:
            st["kept"] = st["k"] == k
        curve = sorted(dict(first + [(p.k, p.apd) for p in sweep.partitions]).items())  # every K computed
        records["c"].set(children=tuple(node.id for node, _, _, _ in judged),
                         apd=APDCurve(tuple(kk for kk, _ in curve), tuple(a for _, a in curve), chosen=k))
        records["c"].note(f"global strategy: K = {k0} (APD's first local maximum) to K = {k} "
                          f"({len(steps)} partitions judged); K = {k} kept")
        notes.extend(sweep.notes)
        actions = {r.part.key: r.part for r in rb.rules}
        leaves = []
        for node, _, cl, rec in judged:
            records[node.id] = rec
            act = actions.get(rec.record.action)
            if act is not None and act.divides:
                if k >= k_max:
                    run.stop(rec, "k_max", f"limit reached: no partition of the scene beyond K = {k} "
                                           f"(k_max = {k_max})")
                else:
                    run.stop(rec, "unpartitioned", f"it cannot be split: no partition of the scene beyond K = {k} "
                                                   "(every new prototype died)")
            elif act is not None and not act.keeps:  # reject: its points are noise
                continue
            leaves.append((node, cl, rec))
        return Judged.of(X, leaves, scene, records, ground_facts, tuple(notes), tuple(steps))

    @staticmethod
    def step_record(sweep: IncrementalSweep, judged: list, seeded: str | None) -> dict[str, Any]:
        """One K, as data: its clusters (id, points, centre, covariance axes, what the rules decided
        and the checks that failed)."""
        part = sweep.partitions[-1]
        clusters = []
        for node, j, cl, draft in judged:
            geo, rec = cl.geometry, draft.record
            decisive = [{"check": c.check, "predicate": c.predicate, "value": c.value, "unit": c.unit, "min": c.min,
                         "max": c.max, "passed": c.passed, "source": c.source} for c in rec.decisive_checks()]
            clusters.append({"id": node.id, "column": int(j), "points": int(node.size),
                             "center": geo.center.tolist(), "eigenvalues": geo.eigenvalues.tolist(),
                             "eigenvectors": geo.eigenvectors.tolist(), "action": rec.action,
                             "rule": rec.rule, "rule_source": rec.rule_source, "decisive": decisive,
                             "limit": rec.limit})
        return {"k": part.k, "apd": part.apd, "seeded_in": seeded, "clusters": clusters}
