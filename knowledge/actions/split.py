"""``split``: the cluster is partitioned again by UFP-ONC on its own points."""
from __future__ import annotations

from typing import Any, ClassVar

from kbs.arrays import rows
from kbs.errors import FitError
from collections.abc import Mapping

from kbs.knowledge.explain import APDCurve
from kbs.knowledge.parts import Action
from kbs.knowledge.predicates import Cluster, Measurement
from kbs.knowledge.state import Division, Node


class Split(Action):
    """UFP-ONC on the cluster's own points, K by APD's first local maximum among K >= split_min_k
    (at least 2); its children are the hard clusters of that partition, the largest first."""

    key: ClassVar[str] = "split"
    divides: ClassVar[bool] = True

    def prepare(self, engine: Any, cluster: Cluster) -> Any:
        """The split starts as soon as the cluster is judged (in a worker when jobs > 1)."""
        return engine.submit_split(cluster.X)  # the cluster's points, X[node.idx]: no second copy

    def divide(self, engine: Any, node: Node, cluster: Cluster, facts: Mapping[str, Measurement], rule: Any,
               prepared: Any) -> Division:
        # the cluster's points are X[node.idx] (the interpreter's Cluster): no second copy
        X = cluster.X if cluster.X.shape[0] == node.size else rows(engine.X, node.idx)
        res = prepared.result() if prepared is not None else \
            engine.ufp_onc(X, "first_max", min_k=engine.rule_base.engine["split_min_k"])
        k = res.chosen_k
        if k < 2:
            if len(res.partitions) < 2:
                raise FitError("UFP-ONC found no second cluster")
            k = 2
        apd = APDCurve(tuple(p.k for p in res.partitions), tuple(p.apd for p in res.partitions), k)
        u = res.memberships if k == res.chosen_k else res.partition(k).predict_proba(X)
        return Division(tuple(node.children(u)), apd)
