"""``ground_contact``: points of other clusters lying on the local ground surface join the ground
cluster under them."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.arrays import rows
from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.predicates import Scene
from kbs.knowledge.post._surface import needs_surface, receive, surface_batches, take
from kbs.knowledge.rulebase import Condition, SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class GroundContact(PostStep):
    """Points of clusters of the 'from' labels (default: every other label) lying within tolerance
    of the local ground surface join the ground cluster under them (an obstacle's foot, a kerb's
    top). With per_range, the tolerance grows by that much per unit of a point's distance to
    scene.sensor: far from a spinning lidar the surface is interpolated from points metres away, and
    its height under a point is known less closely."""

    key: ClassVar[str] = "ground_contact"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["tolerance"],
        "properties": {
            "tolerance": {"description": "length units, along the ground normal", "type": "number",
                          "exclusiveMinimum": 0},
            "per_range": {"description": "length units of tolerance per length unit of the point's distance to "
                                         "scene.sensor (default 0: a fixed tolerance)", "type": "number",
                          "minimum": 0, "maximum": 1},
            "from": {"type": "array", "items": {"$ref": "#/$defs/name"}, "minItems": 1},
            "if": {"$ref": "#/$defs/condition",
                   "description": "Only clusters for which this holds give their points (e.g. things standing on "
                                  "the ground, not sheets lying on it)."},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("tolerance", "per_range")

    tolerance: float
    sources: tuple[str, ...]  #: labels whose points may join the ground
    pos: SourcePos
    condition: Condition | None = None  #: only clusters for which it holds give points
    per_range: float = 0.0  #: tolerance per unit of distance to the sensor

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
        return cls(float(tol), sources, ctx.pos(ctx.path, key=True), cond, ctx.number(raw.get("per_range"), 0.0))

    def tolerances(self, P: np.ndarray, sensor: np.ndarray) -> np.ndarray | float:
        """The tolerance of each point ``P`` (q, 3): :attr:`tolerance` plus :attr:`per_range` x its
        distance to ``sensor`` (a float when per_range is 0)."""
        if not self.per_range > 0.0:
            return self.tolerance
        return self.tolerance + self.per_range * np.sqrt(((P - np.asarray(sensor, dtype=np.float64)) ** 2).sum(axis=1))

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
        tol, sensor = self.tolerance, state.scene.sensor
        # a point whose surface bounds put it farther than the tolerance from any height the
        # surface can have under it does not move: it is not asked for
        def near(hp: np.ndarray, lo: np.ndarray, hi: np.ndarray, P: np.ndarray, _at: np.ndarray) -> np.ndarray:
            t = self.tolerances(P, sensor)
            return (hp - hi <= t) & (hp - lo >= -t)

        batches = surface_batches(ctx.X, [leaves[li] for li in todo], surface.model, near,
                                  nearest_of="owner")  # only the nearest point's cluster is used
        within = f" + {self.per_range:g} x range" if self.per_range > 0.0 else ""
        for li, (h, nearest) in zip(todo, batches):
            lf = leaves[li]
            move = np.abs(np.nan_to_num(h, nan=np.inf)) <= self.tolerances(rows(ctx.X, lf.node.idx), sensor)
            n_move, size = int(move.sum()), lf.size
            if not n_move:
                continue
            taken, dest = take(lf, move, surface.owner[nearest[move]], moved_in)
            ids = [leaves[t].id for t in dest]
            leaves[li] = taken.with_record(contact=n_move, notes=(
                f"{n_move:,} of its {size:,} points lie within {tol:g} {unit}{within} of the local "
                f"ground surface and joined {gl} cluster{'s' if len(ids) > 1 else ''} "
                f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{self.pos.short} ground_contact]",))
        receive(leaves, moved_in, "{n} points of other clusters in contact with it joined it "
                f"[{self.pos.short} ground_contact]")
        return replace(state, leaves=tuple(leaves))
