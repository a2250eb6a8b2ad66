"""``ground_release``: points of the ground clusters standing above the local ground surface join
the nearest cluster of another label."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.post._surface import needs_surface, receive, surface_batches, take
from kbs.knowledge.rulebase import SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class GroundRelease(PostStep):
    """Points of the ground model's clusters standing more than tolerance above the local ground
    surface (a tuft, the bottom of a bush inside a ground cluster) join the nearest cluster of
    label 'to'."""

    key: ClassVar[str] = "ground_release"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["tolerance", "to"],
        "properties": {
            "tolerance": {"description": "length units, along the ground normal", "type": "number",
                          "exclusiveMinimum": 0},
            "to": {"$ref": "#/$defs/name"},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("tolerance",)

    tolerance: float
    target: str  #: the label of the clusters released points join
    pos: SourcePos

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> GroundRelease | None:
        tol = raw.get("tolerance") if isinstance(raw, dict) else None
        if not isinstance(tol, (int, float)) or isinstance(tol, bool) or not isinstance(raw.get("to"), str):
            return None  # the schema reported it
        needs_surface(cls.key, ctx)
        ctx.label_ref(ctx.path + ("to",), raw["to"])
        model = next((s for s in reversed(ctx.earlier) if s.key == "ground_model"), None)
        if model is not None and raw["to"] == getattr(model, "label", None):
            ctx.add(ctx.path + ("to",), f"ground_release to '{raw['to']}', the ground model's own label, changes nothing")
        return cls(float(tol), raw["to"], ctx.pos(ctx.path, key=True))

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        from scipy.spatial import cKDTree

        surface = state.surface
        if surface is None or not surface.model.n_points:
            return state
        gl = surface.spec.label
        unit = ctx.rule_base.length_unit
        leaves = list(state.leaves)
        targets = [li for li, lf in enumerate(leaves) if lf.label == self.target and lf.size]
        if not targets:
            note = f"no {self.target} cluster to take released points"
            return replace(state, ground_facts=state.ground_facts.with_local_model(release_note=note))
        X = ctx.X
        t_idx = np.concatenate([leaves[li].node.idx for li in targets])
        t_owner = np.concatenate([np.full(leaves[li].size, li) for li in targets])
        tree = cKDTree(X[t_idx])
        moved_in: dict[int, list] = {}
        total = 0
        todo = [li for li, lf in enumerate(leaves) if lf.label == gl and lf.size]
        # queries for batches of clusters (points move only after the loop)
        tol = self.tolerance
        above = lambda hp, lo, hi, P: hp - lo > tol  # noqa: E731 (no surface height under it is low enough: stays)
        batches = surface_batches(X, [leaves[li] for li in todo], surface.model, above, nearest_of="none")
        for li, (h, _) in zip(todo, batches):
            lf = leaves[li]
            move = np.nan_to_num(h, nan=-np.inf) > tol
            n_move, size = int(move.sum()), lf.size
            if not n_move:
                continue
            _, j = tree.query(X[lf.node.idx[move]], workers=ctx.jobs if n_move >= 4096 else 1)
            taken, dest = take(lf, move, t_owner[j], moved_in)
            total += n_move
            ids = [leaves[t].id for t in dest]
            leaves[li] = taken.with_record(released=n_move, notes=(
                f"{n_move:,} of its {size:,} points stand more than {tol:g} {unit} above the "
                f"local ground surface and joined {self.target} cluster{'s' if len(ids) > 1 else ''} "
                f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{self.pos.short} ground_release]",))
        receive(leaves, moved_in, "{n} points released by ground clusters joined it (the nearest "
                f"{self.target} cluster) [{self.pos.short} ground_release]")
        return replace(state, leaves=tuple(leaves), ground_facts=state.ground_facts.with_local_model(released=total))
