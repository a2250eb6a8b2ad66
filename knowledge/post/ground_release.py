"""``ground_release``: points of the ground clusters standing above the local ground surface join
the nearest cluster of another label."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.post._surface import needs_surface, receive, surface_batches, take
from kbs.knowledge.post.relabel import MAX_PASSES
from kbs.knowledge.rulebase import SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class GroundRelease(PostStep):
    """Points of the ground model's clusters standing more than tolerance above the local ground
    surface (a tuft, the bottom of a bush inside a ground cluster) join the nearest cluster of
    label 'to'.

    The surface is built from the ground clusters' points, the released ones among them: where
    low plants stand in a ground cluster, it lies between the plants and the terrain. With
    'passes: N', after a pass that released points the surface is built again from the ground
    points left and the ground clusters are measured against it again, until a pass releases
    none or after N passes; the last surface built stays for the steps after."""

    key: ClassVar[str] = "ground_release"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["tolerance", "to"],
        "properties": {
            "tolerance": {"description": "length units, along the ground normal", "type": "number",
                          "exclusiveMinimum": 0},
            "to": {"$ref": "#/$defs/name"},
            "passes": {"description": "at most this many passes, each after the surface was built again from the "
                                      "ground points the passes before left (default 1)",
                       "type": "integer", "minimum": 1, "maximum": MAX_PASSES},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("tolerance",)

    tolerance: float
    target: str  #: the label of the clusters released points join
    pos: SourcePos
    passes: int = 1  #: at most this many passes, the surface built again between them

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
        passes = raw.get("passes", 1)
        return cls(float(tol), raw["to"], ctx.pos(ctx.path, key=True),
                   passes if isinstance(passes, int) and not isinstance(passes, bool) else 1)

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        surface = state.surface
        if surface is None or not surface.model.n_points:
            return state
        gl = surface.spec.label
        if not any(lf.label == self.target and lf.size for lf in state.leaves):
            note = f"no {self.target} cluster to take released points"
            return replace(state, ground_facts=state.ground_facts.with_local_model(release_note=note))
        del surface
        total = 0
        asked = None
        for p in range(self.passes):
            if p:  # the surface again, from the ground points the passes before left
                spec = state.surface.spec
                state = replace(state, surface=None)  # the old surface freed before the new one is built
                state = replace(state, surface=spec.build(state, ctx))
                if not state.surface.model.n_points:
                    break
            state, released = self._release(state, ctx, gl, p, asked)
            total += released.size
            if not released.size:
                break
            if p + 1 < self.passes:
                asked = self._near(ctx.X, state.surface.model, released)
        return replace(state, ground_facts=state.ground_facts.with_local_model(released=total))

    @staticmethod
    def _near(X: np.ndarray, model: Any, released: np.ndarray) -> np.ndarray:
        """The points of ``X`` (a mask) whose surface height the release of the points ``released``
        (rows of ``X``) can change: a point's height is the median of its nearest surface points
        within its radius, so a point farther than its radius from every released point keeps its
        nearest points, its height, and its outcome (it stayed). In the plane's coordinates, by
        cells as wide as the largest radius: a released point's cell and the eight around it."""
        if model.per_range > 0.0:
            assert model.sensor is not None
            far = float(np.sqrt(((X - model.sensor) ** 2).sum(axis=1)).max())
            side = model.radius + model.per_range * far
        else:
            side = model.radius
        Q = (X - model.point) @ model.basis.T
        cells = np.floor((Q - Q.min(axis=0)) / side).astype(np.int64)
        width = int(cells[:, 1].max()) + 3
        key = (cells[:, 0] + 1) * width + cells[:, 1] + 1
        near = np.unique(key[released][:, None] + (np.arange(-1, 2)[:, None] * width + np.arange(-1, 2)).ravel())
        return np.isin(key, near)

    def _release(self, state: PostState, ctx: PostContext, gl: str, p: int,
                 asked: np.ndarray | None) -> tuple[PostState, np.ndarray]:
        """One pass against the state's surface (only the points ``asked``, when given): the state
        with the points released, and those points (rows of ``ctx.X``)."""
        from scipy.spatial import cKDTree

        surface = state.surface
        assert surface is not None
        unit = ctx.rule_base.length_unit
        leaves = list(state.leaves)
        targets = [li for li, lf in enumerate(leaves) if lf.label == self.target and lf.size]
        X = ctx.X
        t_idx = np.concatenate([leaves[li].node.idx for li in targets])
        t_owner = np.concatenate([np.full(leaves[li].size, li) for li in targets])
        tree = cKDTree(X[t_idx])
        moved_in: dict[int, list] = {}
        todo = [li for li, lf in enumerate(leaves) if lf.label == gl and lf.size]
        # queries for batches of clusters (points move only after the loop)
        tol = self.tolerance
        above = lambda hp, lo, hi, P: hp - lo > tol  # noqa: E731 (no surface height under it is low enough: stays)
        batches = surface_batches(X, [leaves[li] for li in todo], surface.model, above, nearest_of="none",
                                  asked=asked)
        gone = []
        which = f" (pass {p + 1}: the surface without the points released before)" if p else ""
        for li, (h, _) in zip(todo, batches):
            lf = leaves[li]
            move = np.nan_to_num(h, nan=-np.inf) > tol
            n_move, size = int(move.sum()), lf.size
            if not n_move:
                continue
            _, j = tree.query(X[lf.node.idx[move]], workers=ctx.jobs if n_move >= 4096 else 1)
            taken, dest = take(lf, move, t_owner[j], moved_in)
            gone.append(lf.node.idx[move])
            ids = [leaves[t].id for t in dest]
            leaves[li] = taken.with_record(released=lf.record.released + n_move, notes=(
                f"{n_move:,} of its {size:,} points stand more than {tol:g} {unit} above the "
                f"local ground surface{which} and joined {self.target} cluster{'s' if len(ids) > 1 else ''} "
                f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{self.pos.short} ground_release]",))
        receive(leaves, moved_in, "{n} points released by ground clusters joined it (the nearest "
                f"{self.target} cluster) [{self.pos.short} ground_release]")
        return replace(state, leaves=tuple(leaves)), np.concatenate(gone) if gone else np.zeros(0, dtype=np.int64)
