"""``merge_coplanar``: clusters of one label whose planes agree become one output cluster; with
``absorb``, clusters of other labels lying in such a plane take its label and join it."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.geometry.connexity import edge_components
from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.rulebase import SourcePos
from kbs.knowledge.state import PostState


@dataclass(frozen=True)
class MergeCoplanar(PostStep):
    """Merge clusters of one label whose planes agree (the seed paper merges ground planes).

    Two clusters agree when their normals are within max_angle and each centre is within
    max_offset of the other's plane; agreement is transitive. A cluster with no plane (its points
    on a line) and a cluster whose points all left for others take no part. Each merged group
    takes the place of its first member.

    With ``absorb`` (labels), a cluster of one of those labels that agrees with a cluster of
    ``label`` (the same test) takes ``label`` and joins its group: the pieces of a wall that the
    objects in front of it cut off, each too small to be called a wall on its own. Only agreement
    with a cluster of ``label`` counts: two absorbable clusters that agree with each other but
    with none of ``label`` stay as they were, and so does a cluster an earlier step grouped with
    others (a group keeps one label). The explanation records the change as a relabel by this
    step, with the cluster of ``label`` whose plane it lies in (``joined``: its id, the angle
    between the normals and the larger of the two centre-to-plane offsets); ``kbs explain`` says
    "relabelled wall by merge_coplanar [...]: in the plane of c3.0.1.1 (normals 2.95 deg apart <=
    10 deg, each centre 0.109 m off the other's plane <= 0.15 m)".
    """

    key: ClassVar[str] = "merge_coplanar"
    schema: ClassVar[dict[str, Any]] = {
        "type": "object", "additionalProperties": False, "required": ["label"],
        "properties": {
            "label": {"$ref": "#/$defs/name"},
            "absorb": {"description": "labels whose clusters lying in the plane of a cluster of label take it",
                       "type": "array", "items": {"$ref": "#/$defs/name"}},
            "max_angle": {"description": "degrees", "type": "number", "minimum": 0, "maximum": 90},
            "max_offset": {"description": "length units, plane-to-centre distance", "type": "number", "minimum": 0},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("max_angle", "max_offset")

    label: str
    max_angle: float
    max_offset: float
    pos: SourcePos
    absorb: tuple[str, ...] = ()

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> MergeCoplanar | None:
        if not isinstance(raw, dict):
            return None
        ctx.label_ref(ctx.path + ("label",), raw.get("label"))
        absorb = raw.get("absorb") or []
        for i, name in enumerate(absorb if isinstance(absorb, list) else []):
            ctx.label_ref(ctx.path + ("absorb", i), name)
        return cls(label=str(raw.get("label")), max_angle=ctx.number(raw.get("max_angle"), 10.0),
                   max_offset=ctx.number(raw.get("max_offset"), 0.15), pos=ctx.pos(ctx.path, key=True),
                   absorb=tuple(str(a) for a in absorb) if isinstance(absorb, list) else ())

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        leaves = state.leaves
        n = len(leaves)
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        grouped = {i for g in state.groups or () if len(g) > 1 for i in g}
        cand = np.array([i for i, lf in enumerate(leaves)
                         if lf.size and not lf.cluster.geometry.degenerate
                         and (lf.label == self.label or (lf.label in self.absorb and i not in grouped))], dtype=int)
        own = np.array([leaves[i].label == self.label for i in cand], dtype=bool)
        if cand.size > 1:
            geos = [leaves[i].cluster.geometry for i in cand]
            N = np.array([g.normal for g in geos])
            C = np.array([g.center for g in geos])
            cos = np.clip(np.abs(N @ N.T), 0.0, 1.0)
            off = np.abs(np.einsum("id,ijd->ij", N, C[None, :, :] - C[:, None, :]))  # j's centre to i's plane
            ok = (np.degrees(np.arccos(cos)) <= self.max_angle) & (np.maximum(off, off.T) <= self.max_offset)
            ok &= own[:, None] | own[None, :]  # an absorbed cluster joins through a cluster of the label only
            a, b = np.nonzero(ok)
            rows.append(cand[a])
            cols.append(cand[b])
        for g in state.groups or ():  # an earlier grouping step's groups stay together
            rows.append(np.full(len(g) - 1, g[0], dtype=int))
            cols.append(np.asarray(g[1:], dtype=int))
        r = np.concatenate(rows) if rows else np.zeros(0, dtype=int)
        c = np.concatenate(cols) if cols else np.zeros(0, dtype=int)
        _, comp = edge_components(n, r, c)
        out: dict[int, list[int]] = {}
        for i, g in enumerate(comp):  # a group takes the place of its first member (leaf order)
            out.setdefault(int(g), []).append(i)
        if self.absorb and cand.size > 1:
            new = list(leaves)
            both = np.maximum(off, off.T)
            for k in np.flatnonzero(~own):
                mates = np.flatnonzero(ok[k] & own)
                if not mates.size:
                    continue
                j = int(mates[np.argmin(both[k, mates])])  # the cluster of the label whose plane it lies in best
                lf = leaves[cand[k]]
                new[cand[k]] = lf.with_record(label=self.label, relabel={
                    "rule": self.key, "source": self.pos.short, "from": lf.label, "to": self.label, "checks": [],
                    "joined": {"cluster": leaves[cand[j]].id, "angle": float(np.degrees(np.arccos(cos[k, j]))),
                               "offset": float(both[k, j]), "max_angle": float(self.max_angle),
                               "max_offset": float(self.max_offset), "unit": state.scene.unit}})
            state = replace(state, leaves=tuple(new))
        return replace(state, groups=tuple(tuple(m) for m in out.values()))
