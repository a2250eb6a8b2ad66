"""``ground_model``: the local ground surface, from the points of the clusters of one label."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.knowledge.groundfacts import LocalModel
from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.rulebase import SourcePos
from kbs.knowledge.state import PostState, Surface


@dataclass(frozen=True)
class GroundModel(PostStep):
    """A local ground surface from the points of the clusters of one label: the ground height under a
    point is the median height of its nearest such points (in the ground plane's coordinates, within
    radius, plus per_range x the point's distance to scene.sensor: a spinning lidar's rings lie
    farther apart with range), or with 'quantile' a lower quantile of their heights (where low
    plants and the feet of obstacles stand among the ground points, the terrain is their lower
    part). Used by predicates such as height_above_local_ground and by ground_contact.

    Later steps measure against it (relabel conditions, ground_release, ground_contact); a relabel
    step that changes labels builds it again from the new labels. Without a ground plane (a rule
    base with no way to orient the ground) it is skipped, and the explanation says so.
    """

    key: ClassVar[str] = "ground_model"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["label"],
        "properties": {
            "label": {"$ref": "#/$defs/name"},
            "neighbours": {"description": "ground points whose median height is the local ground height",
                           "type": "integer", "minimum": 1, "maximum": 64},
            "radius": {"description": "length units; farther ground points do not count", "type": "number",
                       "exclusiveMinimum": 0},
            "per_range": {"description": "length units of radius per length unit of the point's distance to "
                                         "scene.sensor (default 0: a fixed radius)", "type": "number",
                          "minimum": 0, "maximum": 1},
            "quantile": {"description": "the quantile of the neighbours' heights that is the ground height "
                                        "(default 0.5: the median; lower: the terrain under low plants)",
                         "type": "number", "minimum": 0, "maximum": 1},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("neighbours", "radius", "per_range", "quantile")

    label: str
    neighbours: int
    radius: float
    pos: SourcePos
    per_range: float = 0.0  #: radius per unit of distance to the sensor
    quantile: float = 0.5  #: the statistic of the neighbours' heights (0.5: the median)

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> GroundModel | None:
        if not isinstance(raw, dict) or not isinstance(raw.get("label"), str):
            return None  # the schema reported it
        ctx.label_ref(ctx.path + ("label",), raw["label"])
        return cls(label=raw["label"], neighbours=ctx.number(raw.get("neighbours"), 8, int),
                   radius=ctx.number(raw.get("radius"), 3.0), pos=ctx.pos(ctx.path, key=True),
                   per_range=ctx.number(raw.get("per_range"), 0.0), quantile=ctx.number(raw.get("quantile"), 0.5))

    def build(self, state: PostState, ctx: PostContext) -> Surface:
        """The surface from the leaves labelled :attr:`label` now."""
        from kbs.geometry.groundmodel import LocalGround

        leaves, ground = state.leaves, state.scene.ground
        assert ground is not None  # apply() saw to it
        mine = [i for i, lf in enumerate(leaves) if lf.label == self.label]
        index = np.concatenate([leaves[i].node.idx for i in mine]) if mine else np.zeros(0, dtype=np.int64)
        owner = np.concatenate([np.full(leaves[i].size, i) for i in mine]) if mine else np.zeros(0, dtype=np.int64)
        model = LocalGround.build(ctx.X, index, ground.normal, ground.point, neighbours=self.neighbours,
                                  radius=self.radius, owners=np.searchsorted(mine, owner) if mine else owner,
                                  owner_ids=tuple(leaves[i].id for i in mine), workers=ctx.jobs,
                                  per_range=self.per_range, sensor=state.scene.sensor, quantile=self.quantile)
        return Surface(model=model, owner=owner, spec=self)

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        if state.scene.ground is None:  # the rule base has no way to orient the ground: say so, do nothing
            skipped = LocalModel(note="no ground plane: post.ground_model skipped")
            return replace(state, surface=None, ground_facts=replace(state.ground_facts, local_model=skipped))
        state = replace(state, surface=None)  # a surface from an earlier step, freed before this one is built
        surface = self.build(state, ctx)
        built = LocalModel(label=self.label, points=surface.model.n_points, neighbours=self.neighbours,
                           radius=self.radius, per_range=self.per_range or None,
                           quantile=None if self.quantile == 0.5 else self.quantile, source=self.pos.short)
        return replace(state, surface=surface, ground_facts=replace(state.ground_facts, local_model=built))
