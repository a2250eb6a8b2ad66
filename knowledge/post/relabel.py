"""``relabel``: rules applied after labelling: a cluster with label ``from`` whose condition
holds takes label ``to``."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.predicates import Scene
from kbs.knowledge.rulebase import Condition, SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class RelabelRule:
    """A relabel rule: a cluster labelled ``source`` whose condition holds takes label ``target``."""

    name: str
    source: str
    target: str
    condition: Condition
    doc: str
    pos: SourcePos


@dataclass(frozen=True)
class Relabel(PostStep):
    """Rules applied after labelling, in order: a cluster with label 'from' whose condition holds
    takes label 'to' (the first such rule acts). Conditions may use the local ground surface.

    When a rule changed a label and a ground_model step came before, the surface is built again
    from the new labels for the steps after this one.
    """

    key: ClassVar[str] = "relabel"
    schema: ClassVar[dict[str, Any]] = {
        "type": "array",
        "items": {"type": "object", "additionalProperties": False, "required": ["name", "from", "to", "if"],
                  "properties": {"name": {"$ref": "#/$defs/name"}, "doc": {"type": "string"},
                                 "from": {"$ref": "#/$defs/name"}, "to": {"$ref": "#/$defs/name"},
                                 "if": {"$ref": "#/$defs/condition"}}},
    }

    rules: tuple[RelabelRule, ...]
    pos: SourcePos

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> Relabel | None:
        out: list[RelabelRule] = []
        seen = {r.name for s in ctx.earlier if isinstance(s, Relabel) for r in s.rules}
        surface = any(s.key == "ground_model" for s in ctx.earlier)
        for i, spec in enumerate(raw if isinstance(raw, list) else []):
            path = ctx.path + (i,)
            if not isinstance(spec, dict) or not all(isinstance(spec.get(k), str) for k in ("name", "from", "to")):
                continue  # the schema reported it
            if spec["name"] in seen:
                ctx.add(path + ("name",), f"relabel rule '{spec['name']}' is defined twice")
            seen.add(spec["name"])
            ctx.label_ref(path + ("from",), spec["from"])
            ctx.label_ref(path + ("to",), spec["to"])
            if spec["from"] == spec["to"]:
                ctx.add(path + ("to",), f"relabel rule '{spec['name']}' changes nothing: from and to are both "
                        f"'{spec['to']}'")
            cond = ctx.condition(spec.get("if"), path + ("if",)) if "if" in spec else None
            if cond is None:
                continue
            ctx.never(cond, path + ("if",), f"relabel rule '{spec['name']}' can never act")
            if not surface:
                uses = [f.name for f in cond.facts()
                        if f.name in ctx.checks and ctx.checks[f.name].predicate.needs_ground_model]
                if uses:
                    ctx.add(path + ("if",), f"relabel rule '{spec['name']}': check '{uses[0]}' needs the local "
                            "ground surface, but post.ground_model does not declare it")
            out.append(RelabelRule(spec["name"], spec["from"], spec["to"], cond, str(spec.get("doc", "")),
                                   ctx.pos(path)))
        return cls(rules=tuple(out), pos=ctx.pos(ctx.path, key=True))

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        surface = state.surface
        if surface is None and state.ground_facts.local_model is not None:  # a ground_model step was skipped (no ground plane)
            return state
        scene = state.scene
        post_scene = Scene(scene.sensor, scene.ground, scene.unit,
                           ground_model=surface.model if surface is not None else None)
        changed = 0
        leaves = list(state.leaves)
        for i, lf in enumerate(leaves):
            fact = ctx.fact(lf.cluster, post_scene, lf.record)
            for r in self.rules:
                if lf.label != r.source or not r.condition.evaluate(fact):
                    continue
                leaves[i] = lf.with_record(fact.record, label=r.target, relabel={
                    "rule": r.name, "source": r.pos.short, "from": r.source, "to": r.target,
                    "checks": ctx.names(r.condition)})
                changed += 1
                break
            else:
                leaves[i] = lf.with_record(fact.record)  # with the checks measured
        state = replace(state, leaves=tuple(leaves))
        if surface is None:
            return state
        state = replace(state, ground_facts=state.ground_facts.with_local_model(relabelled=changed))
        if not changed:
            return state
        surface = surface.spec.build(state, ctx)
        return replace(state, surface=surface,
                       ground_facts=state.ground_facts.with_local_model(points_after_relabel=surface.model.n_points))
