"""``relabel``: rules applied after labelling: a cluster with label ``from`` whose condition
holds takes label ``to``; a rule with ``passes`` judges again, against the surface rebuilt without
the clusters it took, those it left; a rule that ``undoes`` an earlier one judges again, against
the surface rebuilt without them, the clusters that rule relabelled."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.knowledge.explain import ClusterRecord
from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.predicates import Scene
from kbs.knowledge.rulebase import Condition, SourcePos
from kbs.knowledge.state import Leaf, PostState, Surface

#: the most passes a rule may ask for (each rebuilds the surface)
MAX_PASSES = 64

#: the 3 x 3 block of cells around a cell
_AROUND = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], dtype=np.int64)


@dataclass(frozen=True)
class RelabelRule:
    """A relabel rule: a cluster labelled ``source`` whose condition holds takes label ``target``.
    With ``passes`` > 1 and no ``undoes``, the clusters still labelled ``source`` that no rule
    relabelled are judged again, against the surface rebuilt from the labels left, for up to
    ``passes`` passes in all. With ``undoes`` (the name of an earlier rule of the same step), it
    judges only the clusters that rule relabelled, against the surface rebuilt from the labels
    left, and gives them their label back (``source``/``target`` are that rule's
    ``target``/``source``), for up to ``passes`` passes."""

    name: str
    source: str
    target: str
    condition: Condition
    doc: str
    pos: SourcePos
    undoes: str | None = None
    passes: int = 1


@dataclass(frozen=True)
class Relabel(PostStep):
    """Rules applied after labelling, in order: a cluster with label 'from' whose condition holds
    takes label 'to' (the first such rule acts). Conditions may use the local ground surface.

    A rule with 'passes: N' that undoes none is judged, after the first rules, again: the surface
    is built again from the labels they left, and each cluster still labelled its 'from' that no
    rule relabelled is judged against it (its checks on the surface measured anew); each pass that
    relabels some builds the surface again, without them, until a pass relabels none or after N
    passes in all (e.g. the inner patches of a large roof, whose neighbours are roof patches, judged
    against the ground left once the outer ones are out).

    A rule with 'undoes: NAME' (an earlier rule of the step) runs after those: the surface
    is built again from the labels they left, and each cluster NAME relabelled is judged against
    it (its checks on the surface measured anew): where the condition holds it takes its label
    back. Each pass that gives some back builds the surface again, with them, and judges the
    others again, until a pass gives none back or after 'passes' passes (default 1): a patch is
    judged against the patches that are not themselves relabelled (e.g. a terrace above a
    terrain step against the terrain left once the roofs are out).

    When a rule changed a label and a ground_model step came before, the surface is built again
    from the new labels for the steps after this one; a later relabel step measures its checks on
    the surface again, against that surface (what an earlier step measured stays in the
    explanation of that step's relabelling).
    """

    key: ClassVar[str] = "relabel"
    schema: ClassVar[dict[str, Any]] = {
        "type": "array",
        "items": {"type": "object", "additionalProperties": False, "required": ["name", "if"],
                  "properties": {"name": {"$ref": "#/$defs/name"}, "doc": {"type": "string"},
                                 "from": {"$ref": "#/$defs/name"}, "to": {"$ref": "#/$defs/name"},
                                 "if": {"$ref": "#/$defs/condition"},
                                 "undoes": {"description": "an earlier rule of this step: the clusters it relabelled "
                                                           "are judged again against the surface rebuilt without "
                                                           "them, and take their label back where the condition "
                                                           "holds ('from'/'to' are that rule's 'to'/'from')",
                                            "$ref": "#/$defs/name"},
                                 "passes": {"description": "at most this many passes in all, each after the surface "
                                                           "was rebuilt from the labels the passes before left "
                                                           "(they stop at the first that changes none); with "
                                                           "'undoes', the clusters that rule relabelled are judged "
                                                           "again, without it the clusters still labelled 'from' "
                                                           "that no rule relabelled",
                                            "type": "integer", "minimum": 1, "maximum": MAX_PASSES}}},
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
            if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
                continue  # the schema reported it
            ok, undone = cls._undone(spec, out, path, ctx)
            if not ok:
                continue
            if undone is None and not all(isinstance(spec.get(k), str) for k in ("from", "to")):
                if not all(k in spec for k in ("from", "to")):
                    ctx.add(path, f"relabel rule '{spec['name']}' needs 'from' and 'to' (or 'undoes', an earlier "
                            "rule of this step)")
                continue  # the schema reported a wrong type
            if spec["name"] in seen:
                ctx.add(path + ("name",), f"relabel rule '{spec['name']}' is defined twice")
            seen.add(spec["name"])
            source = undone.target if undone is not None else spec["from"]
            target = undone.source if undone is not None else spec["to"]
            if undone is None:
                ctx.label_ref(path + ("from",), source)
                ctx.label_ref(path + ("to",), target)
            if source == target:
                ctx.add(path + ("to",), f"relabel rule '{spec['name']}' changes nothing: from and to are both "
                        f"'{target}'")
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
                elif undone is not None:
                    ctx.add(path + ("undoes",), f"relabel rule '{spec['name']}' undoes '{undone.name}' against the "
                            "surface rebuilt without its clusters, but post.ground_model does not declare it",
                            key=True)
            out.append(RelabelRule(spec["name"], source, target, cond, str(spec.get("doc", "")), ctx.pos(path),
                                   undoes=undone.name if undone is not None else None,
                                   passes=int(spec.get("passes", 1)) if isinstance(spec.get("passes"), int) else 1))
        return cls(rules=tuple(out), pos=ctx.pos(ctx.path, key=True))

    @staticmethod
    def _undone(spec: dict, earlier: list[RelabelRule], path: tuple,
                ctx: SpecContext) -> tuple[bool, RelabelRule | None]:
        """(False when a problem was reported, the rule ``spec`` undoes or None)."""
        name = spec["name"]
        if "undoes" not in spec:
            return True, None
        target = spec["undoes"]
        if not isinstance(target, str):
            return False, None  # the schema reported it
        undone = next((r for r in earlier if r.name == target), None)
        if undone is None:
            where = "itself" if target == name else f"'{target}', which is not an earlier rule of this step"
            ctx.add(path + ("undoes",), f"relabel rule '{name}' undoes {where} (it can undo only a rule listed "
                    f"before it in the same relabel step: {', '.join(r.name for r in earlier) or 'none'})")
            return False, None
        if undone.undoes is not None:
            ctx.add(path + ("undoes",), f"relabel rule '{name}' undoes '{target}', which itself undoes "
                    f"'{undone.undoes}': undo the rule that relabels")
            return False, None
        for key, want in (("from", undone.target), ("to", undone.source)):
            if key in spec and spec[key] != want:
                ctx.add(path + (key,), f"relabel rule '{name}' undoes '{target}' ({undone.source} -> "
                        f"{undone.target}): its '{key}' is '{want}', not '{spec[key]}' (or leave it out)")
                return False, None
        return True, undone

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        surface = state.surface
        if surface is None and state.ground_facts.local_model is not None:  # a ground_model step was skipped (no ground plane)
            return state
        before = [lf.label for lf in state.leaves]
        leaves, changed = self._first_rules(state, ctx)
        moved = [i for i, lf in enumerate(leaves) if lf.label != before[i]]
        state = replace(state, leaves=tuple(leaves))
        if surface is None:
            return state
        # from here the state holds the surface, not this frame: a surface built again frees the old
        spec = surface.spec
        del surface
        state = replace(state, ground_facts=state.ground_facts.with_local_model(relabelled=changed))
        built = False  # the surface in the state was built again from labels this step changed
        since = list(moved)  # the leaves whose label changed since the rules were first judged
        for r in self.rules:
            if r.undoes is None and r.passes > 1:
                hand = [state]
                del state
                # judged again on what moved since it was first judged (by the first rules and by
                # the passes of the rules before it), not only on what the last pass moved
                state, changed, passes, took = self._repeat(r, hand.pop(), ctx, changed, since)
                since += took
                built = built or passes > 0
        for r in self.rules:
            if r.undoes is not None:
                hand = [state]
                del state
                state, changed, passes = self._undo(r, hand.pop(), ctx, changed)
                built = built or passes > 0
        if changed:
            state = replace(state, surface=None)  # the old surface freed before the new one is built
            state = replace(state, surface=spec.build(state, ctx))
        elif not built:
            return state
        assert state.surface is not None
        # rebuilt within this step, the surface measured the continuous surfaces the step started
        # from; the steps after this one measure those of the surface they are given
        state.surface.model.measure_regions_on(None)
        return replace(state, ground_facts=state.ground_facts.with_local_model(
            points_after_relabel=state.surface.model.n_points))

    def _first_rules(self, state: PostState, ctx: PostContext) -> tuple[list[Leaf], int]:
        """The leaves after the rules that undo nothing (each leaf's first rule that holds), and how
        many labels they changed; measured against the state's surface."""
        scene, surface = state.scene, state.surface
        post_scene = Scene(scene.sensor, scene.ground, scene.unit,
                           ground_model=surface.model if surface is not None else None)
        changed = 0
        judged = {r.source for r in self.rules}  # a leaf of another label keeps what an earlier step measured
        leaves = [self._fresh(lf, ctx) if lf.label in judged else lf for lf in state.leaves]
        first = [r for r in self.rules if r.undoes is None]
        for i, lf in enumerate(leaves):
            fact = ctx.fact(lf.cluster, post_scene, lf.record)
            for r in first:
                if lf.label != r.source or not r.condition.evaluate(fact):
                    continue
                leaves[i] = lf.with_record(fact.record, label=r.target, relabel={
                    "rule": r.name, "source": r.pos.short, "from": r.source, "to": r.target,
                    "checks": ctx.names(r.condition)})
                changed += 1
                break
            else:
                leaves[i] = lf.with_record(fact.record)  # with the checks measured
        return leaves, changed

    def _undo(self, rule: RelabelRule, state: PostState, ctx: PostContext,
              changed: int) -> tuple[PostState, int, int]:
        """``rule`` (it undoes another) on the clusters that rule relabelled: pass after pass, each
        against the surface built from the labels the passes before left (``changed``: labels
        changed since the state's surface was built). Returns the state, the labels changed since
        its surface was built, and the passes run."""
        assert state.surface is not None
        checks = ctx.rule_base.checks
        fresh = {n for n in ctx.names(rule.condition) if checks[n].predicate.needs_ground_model}
        leaves = list(state.leaves)
        given_back = 0
        passes = 0
        spec = state.surface.spec
        surface: Surface | None = None
        post_scene: Scene | None = None
        while passes < rule.passes:
            todo = [i for i, lf in enumerate(leaves) if lf.record.relabel and lf.record.relabel["rule"] == rule.undoes
                    and lf.label == rule.source]
            if not todo:
                break
            if changed:  # built again from the labels the passes before left
                surface = post_scene = None
                hand = [state]
                del state
                state = self._rebuilt(hand, leaves, spec, ctx)
            surface, changed = state.surface, 0
            assert surface is not None
            passes += 1
            post_scene = self._scene(state)
            for i in todo:
                lf = leaves[i]
                holds, measured = self._judge(rule, lf, post_scene, ctx, fresh)
                step = {"rule": rule.name, "source": rule.pos.short, "pass": passes + 1, "holds": holds,
                        "surface_points": surface.model.n_points, "measured": measured}
                if holds:
                    leaves[i] = lf.with_record(label=rule.target, relabel={
                        "rule": rule.name, "source": rule.pos.short, "from": rule.source, "to": rule.target,
                        "checks": ctx.names(rule.condition), "pass": passes + 1, "measured": measured,
                        "surface_points": surface.model.n_points, "undid": dict(lf.record.relabel or {})})
                    changed += 1
                    given_back += 1
                else:  # still relabelled: the record says it was judged again, and how
                    old = dict(lf.record.relabel or {})
                    old["judged_again"] = [*old.get("judged_again", []), step]
                    leaves[i] = lf.with_record(relabel=old)
            if not changed:
                break
        state = replace(state, leaves=tuple(leaves))
        model = state.ground_facts.local_model
        state = replace(state, ground_facts=state.ground_facts.with_local_model(
            undone=(model.undone or 0) + given_back if model is not None else given_back,
            undo_passes=passes))
        return state, changed, passes

    def _repeat(self, rule: RelabelRule, state: PostState, ctx: PostContext, changed: int,
                moved: list[int]) -> tuple[PostState, int, int, list[int]]:
        """``rule`` (it undoes none) judged again, pass after pass, on the clusters still labelled
        its 'from' that no rule relabelled, each pass against the surface built from the labels the
        passes before left (``changed``: labels changed since the state's surface was built, which
        is built again first if any; ``moved``: the leaves whose label changed since the rule was
        last judged; the passes stop at the first that relabels none). Only the clusters within
        reach of the moved ones are asked (:meth:`_near`): the surface the others' checks read is
        what it was. Returns the state, the labels changed since its surface was built, the passes
        run after the first and the leaves the passes relabelled."""
        assert state.surface is not None
        checks = ctx.rule_base.checks
        fresh = {n for n in ctx.names(rule.condition) if checks[n].predicate.needs_ground_model}
        reach = self._reach(fresh, ctx, state.surface.model)
        spec = state.surface.spec
        leaves = list(state.leaves)
        passes = taken = 0
        took: list[int] = []
        while moved and passes + 1 < rule.passes:
            surface = post_scene = None
            if changed:  # built again from the labels the passes before left
                hand = [state]
                del state
                state = self._rebuilt(hand, leaves, spec, ctx)
            surface, changed = state.surface, 0
            assert surface is not None
            passes += 1
            post_scene = self._scene(state)
            todo = [i for i, lf in enumerate(leaves) if lf.label == rule.source and not lf.record.relabel]
            if reach is not None:
                todo = self._near(todo, moved, leaves, surface.model, reach)
            moved = []
            for i in todo:
                lf = leaves[i]
                holds, measured = self._judge(rule, lf, post_scene, ctx, fresh)
                if holds:
                    leaves[i] = lf.with_record(label=rule.target, relabel={
                        "rule": rule.name, "source": rule.pos.short, "from": rule.source, "to": rule.target,
                        "checks": ctx.names(rule.condition), "pass": passes + 1, "measured": measured,
                        "surface_points": surface.model.n_points})
                    moved.append(i)
            changed = len(moved)
            taken += changed
            took += moved
        state = replace(state, leaves=tuple(leaves))
        model = state.ground_facts.local_model
        if taken and model is not None:
            state = replace(state, ground_facts=state.ground_facts.with_local_model(
                relabelled=(model.relabelled or 0) + taken))
        return state, changed, passes, took

    @staticmethod
    def _rebuilt(hand: list[PostState], leaves: list[Leaf], spec: Any, ctx: PostContext) -> PostState:
        """The state in ``hand`` (taken out: the caller holds no reference to it, nor to its
        surface) with ``leaves`` and the surface built again from their labels by ``spec`` (the
        step that built it), the old surface freed first."""
        before = hand[0].surface
        regions = before.model.regions if before is not None else None  # the step's continuous surfaces
        del before
        state = replace(hand.pop(), leaves=tuple(leaves), surface=None)
        built = spec.build(state, ctx)
        if regions is not None:
            built.model.measure_regions_on(regions)
        return replace(state, surface=built)

    @staticmethod
    def _scene(state: PostState) -> Scene:
        """The scene of ``state`` with its surface, for checks on the surface."""
        scene, surface = state.scene, state.surface
        assert surface is not None
        return Scene(scene.sensor, scene.ground, scene.unit, ground_model=surface.model)

    @staticmethod
    def _reach(names: set[str], ctx: PostContext, model: Any) -> float | None:
        """How far from a cluster's points the surface points its checks ``names`` read may lie
        (the largest of their predicates' reach, those that read nothing the step's moves change
        left out), or None when one does not say."""
        checks = ctx.rule_base.checks
        reach = 0.0
        for n in names:
            pred = checks[n].predicate
            if pred.reach is None:
                return None
            params = {p.name: p.default for p in pred.params.values()} | dict(checks[n].params)
            r = pred.reach(params, model)
            if r == 0.0:  # reads nothing the step's moves change
                continue
            if r is None or not np.isfinite(r) or r <= 0.0:
                return None
            reach = max(reach, float(r))
        return reach if reach > 0.0 else None

    @staticmethod
    def _near(todo: list[int], moved: list[int], leaves: list[Leaf], model: Any, reach: float) -> list[int]:
        """The leaves of ``todo`` with a point within ``reach`` (along the ground plane) of a point
        of the ``moved`` leaves, and possibly a few more: cells of side ``reach`` in the plane, a
        leaf kept when one of its points lies in a cell next to (or in) a cell of a moved point."""
        if not moved or not todo:
            return []

        def cells(i: int) -> np.ndarray:
            return np.floor(((leaves[i].cluster.X - model.point) @ model.basis.T) / reach).astype(np.int64)

        near = np.unique(np.concatenate([cells(i) for i in moved]), axis=0)
        near = np.unique((near[:, None, :] + _AROUND[None, :, :]).reshape(-1, 2), axis=0)
        lo = near.min(axis=0) - 1
        span = near.max(axis=0) - lo + 2
        keys = np.sort((near[:, 0] - lo[0]) * span[1] + (near[:, 1] - lo[1]))
        out = []
        for i in todo:
            c = cells(i) - lo
            inside = (c >= 0).all(axis=1) & (c < span).all(axis=1)
            if inside.any():
                k = c[inside, 0] * span[1] + c[inside, 1]
                pos = np.minimum(np.searchsorted(keys, k), keys.size - 1)
                if (keys[pos] == k).any():
                    out.append(i)
        return out


    @staticmethod
    def _fresh(lf: Leaf, ctx: PostContext) -> Leaf:
        """``lf`` with its checks on the surface forgotten, so that this step measures them against
        its own surface: an earlier relabel step measured them against the surface of its time,
        which it built again if it changed a label. The values an earlier step's relabelling
        decided on stay in that relabel entry's 'measured' (the explanation of that decision).
        Only for the leaves this step judges (its rules' 'from' label): the others keep the values
        an earlier step decided on, relabelled or not (the explanation of a roof patch left ground
        by the airborne rules' first step says which of its checks failed, not 'not evaluated')."""
        checks = ctx.rule_base.checks
        stale = [c for c in lf.record.checks if c.check in checks and checks[c.check].predicate.needs_ground_model]
        if not stale:
            return lf
        gone = {id(c) for c in stale}
        kept = tuple(c for c in lf.record.checks if id(c) not in gone)
        rel = lf.record.relabel
        if rel and "measured" not in rel:
            rel = {**rel, "measured": [dict(vars(c)) for c in stale if c.check in rel.get("checks", ())]}
        return lf.with_record(checks=kept, relabel=rel)

    @staticmethod
    def _judge(rule: RelabelRule, lf: Leaf, scene: Scene, ctx: PostContext,
               fresh: set[str]) -> tuple[bool, list[dict[str, Any]]]:
        """Whether ``rule``'s condition holds on ``lf``, its checks on the surface measured anew
        against ``scene``'s (the others as measured before); the checks measured, as plain data."""
        kept = tuple(c for c in lf.record.checks if c.check not in fresh)
        fact = ctx.fact(lf.cluster, scene, ClusterRecord(lf.id, None, 0, lf.size, checks=kept))
        holds = rule.condition.evaluate(fact)
        return bool(holds), [dict(vars(c)) for c in fact.record.checks[len(kept):]]
