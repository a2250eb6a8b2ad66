"""``split_components``: the cluster is divided along the connected components of its
alpha-complex, found by the connexity check that failed."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from kbs.errors import FitError
from kbs.knowledge.explain import CheckRecord
from kbs.knowledge.parts import Action, SpecContext
from kbs.knowledge.predicates import Cluster, Measurement
from kbs.knowledge.state import Node


class SplitComponents(Action):
    """One child per significant connected component of the failed connexity check (the others'
    points go to the nearest component, in the cluster's plane); each child's connexity checks of
    the rule hold at the parent's alpha, and are recorded so rather than measured again."""

    key: ClassVar[str] = "split_components"
    divides: ClassVar[bool] = True

    def validate(self, rule: Any, path: tuple, ctx: SpecContext) -> None:
        negated = [f for f in rule.condition.facts() if f.negated and f.name in ctx.checks
                   and ctx.checks[f.name].predicate.name == "connexity"]
        if not negated:
            ctx.add(path + ("then",), f"rule '{rule.name}': split_components needs a failed connexity "
                    "check in its condition (e.g. 'if: not connected'), to know the components")

    def divide(self, engine: Any, node: Node, cluster: Cluster, facts: Mapping[str, Measurement], rule: Any,
               prepared: Any) -> list[Node]:
        from kbs.geometry.connexity import Connexity, assign_to_nearest, project_on_plane

        conn: Connexity | None = None
        for f in rule.condition.facts():  # reuse the components of the failed connexity check
            m = facts.get(f.name)
            if m is not None and isinstance(m.details, Connexity):
                conn = m.details
                break
        if conn is None or conn.n_significant < 2:
            raise FitError("no two significant connected components to split along")
        geo = cluster.geometry
        labels = assign_to_nearest(project_on_plane(cluster.X, geo.center, geo.normal), conn.labels,
                                   conn.significant)
        kids: list[Node] = []
        for i in range(conn.n_significant):
            sel = np.flatnonzero(labels == i)
            if sel.size:
                kids.append(Node(f"{node.id}.{len(kids)}", node.id, node.depth + 1, node.idx[sel],
                                 np.ones(sel.size), node.path[sel]))
        return kids

    def inherit(self, engine: Any, rule: Any, parent: Node) -> list[tuple[CheckRecord, Measurement]]:
        """A child is one component of its parent's alpha-complex: its connexity checks hold at the
        parent's alpha, and are recorded so rather than measured again with a smaller alpha of its
        own (which would cut it again and again along the sampling pattern, e.g. LiDAR rings)."""
        rb = engine.rule_base
        names = {f.name for f in rule.condition.facts() if rb.checks[f.name].predicate.name == "connexity"}
        known = []
        for name in names:
            check = rb.checks[name]
            known.append((CheckRecord(
                check=name, predicate="connexity", value=1.0, unit=check.predicate.unit_label(rb.length_unit),
                min=check.min, max=check.max, passed=check.passes(1.0), source=check.pos.short,
                note=f"one component of {parent.id}, at its alpha"), Measurement(1.0)))
        return known
