"""``ground_contact``: points of other clusters lying on the local ground surface join the ground
cluster under them."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.predicates import Scene
from kbs.knowledge.post._surface import needs_surface, receive, surface_batches, take
from kbs.knowledge.rulebase import Condition, SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class GroundContact(PostStep):
    """Points of clusters of the 'from' labels (default: every other label) lying within tolerance
    of the local ground surface join the ground cluster under them (an obstacle's foot, a kerb's
    top)."""

    key: ClassVar[str] = "ground_contact"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["tolerance"],
        "properties": {
            "tolerance": {"description": "length units, along the ground normal", "type": "number",
                          "exclusiveMinimum": 0},
            "from": {"type": "array", "items": {"$ref": "#/$defs/name"}, "minItems": 1},
            "if": {"$ref": "#/$defs/condition",
                   "description": "Only clusters for which this holds give their points (e.g. things standing on "
                                  "the ground, not sheets lying on it)."},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("tolerance",)

    tolerance: float
    sources: tuple[str, ...]  #: labels whose points may join the ground
    pos: SourcePos
    condition: Condition | None = None  #: only clusters for which it holds give points

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> GroundContact | None:
        tol = raw.get("tolerance") if isinstance(raw, dict) else None
        if not isinstance(tol, (int, float)) or isinstance(tol, bool):
            return None  # the schema reported it
        needs_surface(cls.key, ctx)
        model = next((s for s in reversed(ctx.earlier) if s.key == "ground_model"), None)
        own = getattr(model, "label", None)
        src = raw.get("from")
        if isinstance(src, list):
            for j, name in enumerate(src):
                ctx.label_ref(ctx.path + ("from", j), name)
                if model is not None and name == own:
                    ctx.add(ctx.path + ("from", j), f"ground_contact from '{name}', the ground model's own label, "
                            "changes nothing")
            sources = tuple(x for x in src if isinstance(x, str))
        else:
            sources = tuple(n for n in ctx.labels if model is None or n != own)
        cond = ctx.condition(raw["if"], ctx.path + ("if",)) if "if" in raw else None
        if cond is not None:
            ctx.never(cond, ctx.path + ("if",), "post.ground_contact can never move a point")
        return cls(float(tol), sources, ctx.pos(ctx.path, key=True), cond)

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        surface = state.surface
        if surface is None or not surface.model.n_points:
            return state
        gl = surface.spec.label
        unit = ctx.rule_base.length_unit
        scene = Scene(state.scene.sensor, state.scene.ground, state.scene.unit, ground_model=surface.model)
        leaves = list(state.leaves)
        moved_in: dict[int, list] = {}
        todo = []
        for li, lf in enumerate(leaves):
            if lf.label not in self.sources or lf.label == gl or not lf.size:
                continue
            if self.condition is not None:
                fact = ctx.fact(lf.cluster, scene, lf.record)
                holds = self.condition.evaluate(fact)
                leaves[li] = lf.with_record(fact.record)  # with the checks measured
                if not holds:
                    continue
            todo.append(li)
        # queries for batches of clusters (the surface does not change while points move: they
        # are received after the loop)
        tol = self.tolerance
        # a point whose surface bounds put it farther than the tolerance from any height the
        # surface can have under it does not move: it is not asked for
        near = lambda hp, lo, hi: (hp - hi <= tol) & (hp - lo >= -tol)  # noqa: E731
        batches = surface_batches(ctx.X, [leaves[li] for li in todo], surface.model, near,
                                  nearest_of="owner")  # only the nearest point's cluster is used
        for li, (h, nearest) in zip(todo, batches):
            lf = leaves[li]
            move = np.abs(np.nan_to_num(h, nan=np.inf)) <= tol
            n_move, size = int(move.sum()), lf.size
            if not n_move:
                continue
            taken, dest = take(lf, move, surface.owner[nearest[move]], moved_in)
            ids = [leaves[t].id for t in dest]
            leaves[li] = taken.with_record(contact=n_move, notes=(
                f"{n_move:,} of its {size:,} points lie within {tol:g} {unit} of the local "
                f"ground surface and joined {gl} cluster{'s' if len(ids) > 1 else ''} "
                f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{self.pos.short} ground_contact]",))
        receive(leaves, moved_in, "{n} points of other clusters in contact with it joined it "
                f"[{self.pos.short} ground_contact]")
        return replace(state, leaves=tuple(leaves))
