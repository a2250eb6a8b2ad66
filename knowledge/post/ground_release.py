"""``ground_release``: points of the ground clusters standing above the local ground surface join
the nearest cluster of another label."""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from kbs.arrays import rows as take_rows
from kbs.geometry.nearest import NearestIndex
from kbs.knowledge.parts import PostContext, PostStep, SpecContext
from kbs.knowledge.post._surface import needs_surface, receive, surface_batches, take
from kbs.knowledge.post.relabel import MAX_PASSES
from kbs.knowledge.rulebase import SourcePos
from kbs.knowledge.state import PostState


#: one tier of 'rough': where the surface within radius is thicker than min, points more than
#: tolerance (default the step's) above it are released
_ROUGH_TIER: dict[str, Any] = {
    "type": "object", "additionalProperties": False, "required": ["radius", "min"],
    "properties": {"radius": {"type": "number", "exclusiveMinimum": 0},
                   "min": {"type": "number", "minimum": 0},
                   "tolerance": {"description": "length units, along the ground normal (default: the step's)",
                                 "type": "number", "exclusiveMinimum": 0}}}


@dataclass(frozen=True)
class GroundRelease(PostStep):
    """Points of the ground model's clusters standing more than tolerance above the local ground
    surface (a tuft, the bottom of a bush inside a ground cluster) join the nearest cluster of
    label 'to'.

    The surface is built from the ground clusters' points, the released ones among them: where
    low plants stand in a ground cluster, it lies between the plants and the terrain. With
    'passes: N', after a pass that released points the surface is built again from the ground
    points left and the ground clusters are measured against it again, until a pass releases
    none or after N passes; the last surface built stays for the steps after.

    With 'quantile' or 'neighbours', the step measures against a surface of its own, built from
    the ground points as they are when it starts (and again between its passes), the ground
    model's but for that statistic of that many neighbours (a low quantile: the lowest ground
    around a point, under the plants that stand among the ground points); the steps after it
    find the ground model's surface as they would have. With 'rough: {radius: R, min: T}', only
    the points where that surface within R of them is thicker than T are released
    (:meth:`~kbs.geometry.groundmodel.LocalGround.thickness_within`: grass and low plants, not a
    smooth pavement a kerb raises above the road). 'rough' may be a list of such tiers, each
    with a tolerance of its own (default: the step's): a point is released when one holds (the
    rougher the ground, the less a plant need stand above it), in one pass against one surface."""

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
            "quantile": {"description": "the quantile of the neighbours' heights the step measures against, on a "
                                        "surface of its own (default: the ground model's)",
                         "type": "number", "minimum": 0, "maximum": 1},
            "neighbours": {"description": "ground points whose heights give the surface the step measures against, "
                                          "on a surface of its own (default: the ground model's)",
                           "type": "integer", "minimum": 1},
            "rough": {"description": "release only the points where the surface is rough: thicker than min "
                                     "within radius of them (length units; at least 8 surface points there); a "
                                     "list: tiers, each with a tolerance of its own (default the step's), a point "
                                     "released when one holds",
                      "oneOf": [_ROUGH_TIER,
                                {"type": "array", "minItems": 1, "items": _ROUGH_TIER}]},
            "tune": {"$ref": "#/$defs/tune"},
        },
    }
    tunable: ClassVar[tuple[str, ...]] = ("tolerance",)

    tolerance: float
    target: str  #: the label of the clusters released points join
    pos: SourcePos
    passes: int = 1  #: at most this many passes, the surface built again between them
    #: tiers (radius, min, tolerance): only points where the surface within radius is thicker than
    #: min and that stand more than that tolerance above it are released (one tier holding is enough)
    rough: tuple[tuple[float, float, float], ...] | None = None
    quantile: float | None = None  #: the statistic of a surface of its own (None: the ground model's)
    neighbours: int | None = None  #: the neighbours of a surface of its own (None: the ground model's)

    @property
    def own_surface(self) -> bool:
        """Whether the step measures against a surface of its own ('quantile' or 'neighbours')."""
        return self.quantile is not None or self.neighbours is not None

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
        rough = raw.get("rough")
        tiers = [rough] if isinstance(rough, dict) else rough if isinstance(rough, list) else []
        parsed = tuple((ctx.number(t.get("radius"), 1.0), ctx.number(t.get("min"), 0.0),
                        ctx.number(t.get("tolerance", tol), float(tol))) for t in tiers if isinstance(t, dict))
        q, k = raw.get("quantile"), raw.get("neighbours")
        return cls(float(tol), raw["to"], ctx.pos(ctx.path, key=True), ctx.number(raw.get("passes"), 1, int),
                   parsed or None, None if q is None else ctx.number(q, 0.5),
                   None if k is None else ctx.number(k, 8, int))

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        surface = state.surface
        if surface is None or not surface.model.n_points:
            return state
        gl = surface.spec.label
        if not any(lf.label == self.target and lf.size for lf in state.leaves):
            note = f"no {self.target} cluster to take released points"
            return replace(state, ground_facts=state.ground_facts.with_local_model(release_note=note))
        kept = None  # with a surface of its own: the one the steps after find
        if self.own_surface:
            kept = surface
            spec = replace(surface.spec, **{f: v for f, v in (("quantile", self.quantile),
                                                               ("neighbours", self.neighbours)) if v is not None})
            state = replace(state, surface=spec.build(state, ctx))
        del surface
        # a point's roughness may change with any point released within its radius, which the
        # passes' record of each point's nearest does not follow: with 'rough', every pass asks all
        passes = _Passes(ctx.X) if self.passes > 1 and self.rough is None else None
        total = 0
        for p in range(self.passes):
            if p:  # the surface again, from the ground points the passes before left
                assert state.surface is not None
                spec = state.surface.spec
                state = replace(state, surface=None)  # the old surface freed before the new one is built
                built = spec.build(state, ctx)
                state = replace(state, surface=built)
                if not built.model.n_points:
                    break
            state, released = self._release(state, ctx, gl, p, passes)
            total += released.size
            if not released.size:
                break
        if kept is not None:
            state = replace(state, surface=kept)
        before = state.ground_facts.local_model.released if state.ground_facts.local_model is not None else None
        return replace(state, ground_facts=state.ground_facts.with_local_model(released=(before or 0) + total))

    @staticmethod
    def _near(X: np.ndarray, model: Any, released: np.ndarray) -> np.ndarray:
        """The points of the surface ``model`` (rows of ``X``) within the radius of one of the points
        ``released`` (rows of ``X``, points of the surface), and more: in the plane's coordinates,
        by cells as wide as the largest radius, a released point's cell and the eight around it."""
        if model.per_range > 0.0:
            assert model.sensor is not None
            far = float(np.sqrt(((take_rows(X, model.index) - model.sensor) ** 2).sum(axis=1)).max())
            side = model.radius + model.per_range * far
        else:
            side = model.radius
        cells = np.floor((model.plane - model.plane.min(axis=0)) / side).astype(np.int64)
        width = int(cells[:, 1].max()) + 3
        key = (cells[:, 0] + 1) * width + cells[:, 1] + 1
        at = np.zeros(X.shape[0], dtype=bool)
        at[released] = True
        mine = at[model.index]  # the released points among the surface's
        near = np.unique(key[mine][:, None] + (np.arange(-1, 2)[:, None] * width + np.arange(-1, 2)).ravel())
        return model.index[np.isin(key, near)]

    def _release(self, state: PostState, ctx: PostContext, gl: str, p: int,
                 passes: _Passes | None) -> tuple[PostState, np.ndarray]:
        """One pass against the state's surface (with ``passes``, only the points the pass before
        can have changed): the state with the points released, and those points (rows of
        ``ctx.X``)."""
        surface = state.surface
        assert surface is not None
        unit = ctx.rule_base.length_unit
        leaves = list(state.leaves)
        X = ctx.X
        moved_in: dict[int, list] = {}
        todo = [li for li, lf in enumerate(leaves) if lf.label == gl and lf.size]
        # queries for batches of clusters (points move only after the loop)
        tol = self.tolerance
        above = lambda hp, lo, hi, P, at: hp - lo > tol  # noqa: E731 (no surface height under it is low enough: stays)
        thickness = None if self.rough is None else _Thickness(surface.model, X, self.rough)
        if thickness is not None:  # nor where the surface is too smooth for each tier it may stand high enough for
            above = thickness.may_hold
        batches = surface_batches(X, [leaves[li] for li in todo], surface.model, above, nearest_of="none",
                                  asked=None if passes is None else passes.asked,
                                  found=None if passes is None or p + 1 == self.passes else
                                  functools.partial(passes.found, surface.model))
        nearest = _Nearest(X, leaves, self.target)  # of this pass's clusters (with the points received before)
        gone = []
        parts = [f"the {surface.spec.quantile:g} quantile of the heights of {surface.spec.neighbours} ground points "
                 "around each"] if self.own_surface else []
        if p:
            parts.append(f"pass {p + 1}: the surface without the points released before")
        which = f" ({', '.join(parts)})" if parts else ""
        stand = f"stand more than {tol:g} {unit} above the local ground surface{which}"
        if self.rough is not None:
            tiers = [f"where it is thicker than {t_min:g} {unit} within {radius:g} {unit}"
                     for radius, t_min, _ in self.rough]
            if len(self.rough) == 1:
                stand = f"stand more than {self.rough[0][2]:g} {unit} above the local ground surface{which} {tiers[0]}"
            else:
                stand = f"stand above the local ground surface{which} " + ", or ".join(
                    f"more than {t[2]:g} {unit} {where}" for t, where in zip(self.rough, tiers))
        low = tol if self.rough is None else min(t[2] for t in self.rough)  # no tier releases a point lower
        for li, (h, _) in zip(todo, batches):
            lf = leaves[li]
            height = np.nan_to_num(h, nan=-np.inf)
            move = height > low
            if thickness is not None and move.any():  # of those, the points where the surface is rough enough
                move[move] = thickness.holds(lf.node.idx[move], height[move])
            n_move, size = int(move.sum()), lf.size
            if not n_move:
                continue
            taken, dest = take(lf, move, nearest.owners(lf.node.idx[move]), moved_in)
            gone.append(lf.node.idx[move])
            ids = [leaves[t].id for t in dest]
            leaves[li] = taken.with_record(released=lf.record.released + n_move, notes=(
                f"{n_move:,} of its {size:,} points {stand} and joined {self.target} "
                f"cluster{'s' if len(ids) > 1 else ''} "
                f"{', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''} [{self.pos.short} ground_release]",))
        receive(leaves, moved_in, "{n} points released by ground clusters joined it (the nearest "
                f"{self.target} cluster) [{self.pos.short} ground_release]")
        released = np.concatenate(gone) if gone else np.zeros(0, dtype=np.int64)
        if passes is not None and p + 1 < self.passes and released.size:  # what the next pass asks
            passes.after(surface.model, released, keep=p + 2 < self.passes)
        return replace(state, leaves=tuple(leaves)), released


class _Thickness:
    """The tiers of 'rough' (radius, min, tolerance) against the surface ``model``, and the
    thickness of that surface within a radius around points of ``X`` (by row; -inf where too few
    surface points are near), each measured once in a pass: the check of which points to ask
    (:meth:`may_hold`) and the release of the points asked (:meth:`holds`) need the same values
    (the release measured them a second time before session 44: about a tenth of the step on
    SemanticKITTI 000001)."""

    def __init__(self, model: Any, X: np.ndarray, tiers: tuple[tuple[float, float, float], ...]) -> None:
        self.model = model
        self.X = X
        self.tiers = tiers
        self.known: dict[float, np.ndarray] = {}  # by radius, one per row of X (NaN: not measured)

    def at(self, radius: float, rows: np.ndarray, P: np.ndarray | None = None) -> np.ndarray:
        """The thickness within ``radius`` around the points of ``X`` at ``rows`` (``P``: those
        points, when the caller has them)."""
        known = self.known.get(radius)
        if known is None:
            known = self.known[radius] = np.full(self.X.shape[0], np.nan)
        got = known[rows]
        todo = np.flatnonzero(np.isnan(got))
        if todo.size:
            Q = take_rows(self.X, rows[todo]) if P is None else take_rows(P, todo)
            got[todo] = np.nan_to_num(self.model.thickness_within(Q, radius), nan=-np.inf)
            known[rows[todo]] = got[todo]
        return got

    def holds(self, rows: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """Which of the points of ``X`` at ``rows``, standing ``heights`` above the surface, a tier
        releases: more than its tolerance up where the surface is thicker than its min."""
        held = np.zeros(rows.size, dtype=bool)
        for radius, t_min, t_tol in self.tiers:  # (measured while the heights were asked, most of them)
            held |= (heights > t_tol) & (self.at(radius, rows) > t_min)
        return held

    def may_hold(self, hp: np.ndarray, lo: np.ndarray, hi: np.ndarray, P: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Which points ``P`` (the rows ``at`` of ``X``; heights ``hp`` above the ground plane, ``lo``
        the lowest surface height under each, :meth:`~kbs.geometry.groundmodel.LocalGround.height_bounds`)
        a tier may release: more than its tolerance above the lowest surface under them, where the
        surface is thicker than its min (the others' outcome is known without their height: they
        stay; :func:`~kbs.knowledge.post._surface.surface_batches`' ``may_matter``). Where half the
        spread of the surface's heights around a point
        (:meth:`~kbs.geometry.groundmodel.LocalGround.spread_within`, a bound of the thickness) is
        no more than a tier's min, the thickness is not measured: a smooth road's."""
        up = hp - lo
        keep = np.zeros(up.shape, dtype=bool)
        for radius, t_min, t_tol in self.tiers:
            ask = (up > t_tol) & ~keep
            if ask.any():
                spread = self.model.spread_within(take_rows(P, np.flatnonzero(ask)), radius)
                if spread is not None:  # with room for rounding (a flat surface's thickness is not exactly 0)
                    ask[ask] = 0.5 * spread * (1.0 + 1e-6) + 1e-6 * radius > t_min
            if not ask.any():
                continue
            sel = np.flatnonzero(ask)
            keep[sel] = self.at(radius, at[sel], take_rows(P, sel)) > t_min
        return keep


class _Nearest:
    """The cluster of label ``target`` nearest to points: an index over the points of the leaves
    of that label (their positions in ``leaves``)."""

    def __init__(self, X: np.ndarray, leaves, target: str) -> None:
        targets = [li for li, lf in enumerate(leaves) if lf.label == target and lf.size]
        self.X = X
        self.index = NearestIndex(take_rows(X, np.concatenate([leaves[li].node.idx for li in targets])),
                                  np.concatenate([np.full(leaves[li].size, li) for li in targets]))

    def owners(self, idx: np.ndarray) -> np.ndarray:
        """The position (in the leaves) of the cluster nearest to each point ``idx`` (a k-d tree's
        answer, :class:`~kbs.geometry.nearest.NearestIndex`)."""
        return self.index.label(take_rows(self.X, idx))


class _Passes:
    """What a release of several passes keeps from one pass to the next: which points the next
    pass asks.

    A point's height is the median of its nearest surface points (within its radius). The surface
    of a pass is that of the pass before without the points it released (R): a point whose nearest
    surface points, when its height was computed, held none of the points released since, keeps
    them, its height and its outcome (it stayed); so does a point whose height was never computed
    (the surface's bounds decided it) if no point of R is within its radius. The next pass asks
    the others: the points whose nearest held one of R (in any pass that computed their height: a
    superset of the last), and the points never queried within the radius of one of R
    (:meth:`GroundRelease._near`; the bounds decide most of them again). The labels are those of
    asking every point every pass (tested). Kept: per point queried, the rows of its nearest
    surface points (int32: 64 bytes a point for 16 neighbours)."""

    def __init__(self, X: np.ndarray) -> None:
        self.X = X
        self.asked: np.ndarray | None = None  # the next pass asks these (None: all)
        self.queried = np.zeros(X.shape[0], dtype=bool)
        self.dtype = np.int32 if X.shape[0] < 2**31 - 1 else np.int64
        #: (points queried, the rows of X their heights were taken among; -1: none found)
        self.sets: list[tuple[np.ndarray, np.ndarray]] = []

    def found(self, model: Any, rows: np.ndarray, positions: np.ndarray) -> None:
        """The points ``rows`` were queried on the surface ``model``, their heights taken among its
        points at ``positions`` (:meth:`LocalGround.query`'s ``found``)."""
        index = np.append(model.index, -1).astype(self.dtype)
        self.sets.append((rows.astype(self.dtype), index[np.minimum(positions, model.n_points)]))
        self.queried[rows] = True

    def after(self, model: Any, released: np.ndarray, keep: bool = True) -> None:
        """Record a pass against the surface ``model`` that released the points ``released``
        (``keep``: a pass after the next one will ask which points to query)."""
        gone = np.zeros(self.X.shape[0] + 1, dtype=bool)  # the last entry: "none found" (-1)
        gone[released] = True
        asked = np.zeros(self.X.shape[0], dtype=bool)
        for rows, sets in self.sets:
            asked[rows[gone[sets].any(axis=1)]] = True
        if not keep:  # no later pass asks: the nearest sets are freed before the next surface is built
            self.sets = []
        near = GroundRelease._near(self.X, model, released)
        asked[near[~self.queried[near]]] = True
        asked[released] = False
        self.asked = asked
