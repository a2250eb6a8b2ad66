"""The explanation's ``ground`` section as frozen records: how the ground plane was found
(:class:`GroundFacts`, written by the ground search, :mod:`kbs.knowledge.ground`), every ground
candidate's verdict (:class:`GroundCandidate`), and what the steps on the local ground surface did
(:class:`LocalModel`, written by ``post.ground_model`` and the steps after it).

They travel explicitly: the strategy hands the search's facts on in
:class:`~kbs.knowledge.state.Judged`, the post steps pass them along in
:class:`~kbs.knowledge.state.PostState` (a step returns new facts in its new state), and the result
puts them in the :class:`~kbs.knowledge.explain.Explanation`.

Their dictionary form (:meth:`GroundFacts.to_dict`, the ``ground`` of an explanation's JSON) has
the keys of the fields that are set (None: not set), with the values the free-form dictionary of
earlier versions had: files written before read back the same (:meth:`GroundFacts.from_dict`
ignores keys a newer minor version may add).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any


def _set(obj: Any) -> dict[str, Any]:
    """The fields of a record that are set (not None), in their order."""
    return {f.name: getattr(obj, f.name) for f in fields(obj) if getattr(obj, f.name) is not None}


def _known(cls: type, d: Mapping[str, Any]) -> dict[str, Any]:
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in d.items() if k in names}


@dataclass(frozen=True)
class GroundCandidate:
    """One cluster of the first partition considered for the ground plane, and its verdict."""

    cluster: str
    points: int  #: its points (a later plane: the points its earlier planes did not hold)
    thickness: float | None = None  #: of its points (its fuzzy covariance)
    why: str | None = None  #: why it gives no plane, or was refused (its tilt, the sensor under it) (None: it gives one)
    inliers: int | None = None  #: points within the inlier distance of its robust plane
    inlier_share: float | None = None
    plane_thickness: float | None = None  #: of its robust plane's inliers
    method: str | None = None  #: how it gives a plane: "check 'NAME'" or "robust plane"
    angle_to_fallback: float | None = None  #: degrees between its plane's normal and the fallback normal
    distance: float | None = None  #: to the sensor, of its plane's nearest point
    supported: int | None = None  #: (choose: supporting) points standing on its plane
    #: which of its robust planes (2, 3 ...: scene.ground.plane.planes, sought among the points the
    #: earlier ones, refused, did not hold); not set for its first
    plane: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return _set(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GroundCandidate:
        return cls(**_known(cls, d))


@dataclass(frozen=True)
class LocalModel:
    """What the steps on the local ground surface did: ``post.ground_model`` built it (``label``,
    ``points``, ``neighbours``, ``radius``, ``per_range``, ``quantile`` (when not the median), ``source``) or was skipped (``note``); a relabel step
    after it counted the labels it changed (``relabelled``), the labels a rule that undoes another
    gave back (``undone``) in how many passes (``undo_passes``), and built it again
    (``points_after_relabel``); ``ground_release`` counted the points it released (``released``)
    or said why none could be (``release_note``)."""

    label: str | None = None
    points: int | None = None
    neighbours: int | None = None
    radius: float | None = None
    per_range: float | None = None  #: the radius grows by this per unit of distance to the sensor
    quantile: float | None = None  #: the quantile of the neighbours' heights, when not the median
    source: str | None = None
    note: str | None = None
    relabelled: int | None = None
    points_after_relabel: int | None = None
    released: int | None = None
    release_note: str | None = None
    undone: int | None = None
    undo_passes: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return _set(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LocalModel:
        return cls(**_known(cls, d))


@dataclass(frozen=True)
class GroundFacts:
    """How the scene's ground plane was found (every field None when not known or not used):

    ``source`` ('cluster c0', 'fixed', 'fallback', 'per tile (...)'), ``normal`` and ``point`` of
    the plane; for a plane found from a cluster: ``cluster``, ``distance_to_sensor`` and
    ``distance`` (of its plane's nearest point), ``thickness``, ``unit``, ``method`` (a check it
    passes or its robust plane), ``inliers``/``inlier_share`` (robust plane), ``supported``
    (choose: supporting), ``angle_to_fallback``; ``candidates``: every candidate's verdict;
    ``support_band``; ``note``: why the fallback normal is used; ``scope`` and ``tiles``: a tiled
    run's whole-cloud search and per-tile facts by tile name; ``local_model``: what the steps on the local ground surface did.
    """

    source: str | None = None
    cluster: str | None = None
    normal: tuple[float, ...] | None = None
    point: tuple[float, ...] | None = None
    distance_to_sensor: float | None = None
    thickness: float | None = None
    distance: float | None = None
    unit: str | None = None
    method: str | None = None
    supported: int | None = None
    candidates: tuple[GroundCandidate, ...] | None = None
    support_band: tuple[float, float] | None = None
    angle_to_fallback: float | None = None
    inliers: int | None = None
    inlier_share: float | None = None
    plane: int | None = None  #: which of the cluster's robust planes (not set: its first)
    #: the points the robust planes' shares are counted among, when not all of a candidate's:
    #: 'not_above' (scene.ground.plane.share_of)
    share_of: str | None = None
    note: str | None = None
    #: (a tiled run) how much of the whole cloud the plane every tile was given was found on
    scope: str | None = None
    tiles: Mapping[str, GroundFacts] | None = None
    local_model: LocalModel | None = None

    def __bool__(self) -> bool:
        """False when nothing is known (a rule base that uses no ground plane)."""
        return bool(self.to_dict())

    def with_local_model(self, **changes: Any) -> GroundFacts:
        """These facts with :attr:`local_model` changed (``changes`` to its fields)."""
        return replace(self, local_model=replace(self.local_model or LocalModel(), **changes))

    def to_dict(self) -> dict[str, Any]:
        d = _set(self)
        for key in ("normal", "point", "support_band"):
            if key in d:
                d[key] = list(d[key])
        if self.candidates is not None:
            d["candidates"] = [c.to_dict() for c in self.candidates]
        if self.tiles is not None:
            d["tiles"] = {name: t.to_dict() for name, t in self.tiles.items()}
        if self.local_model is not None:
            d["local_model"] = self.local_model.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> GroundFacts:
        """Read :meth:`to_dict`'s form back (an empty or missing section: no facts; keys a newer
        minor version may add are ignored)."""
        if not d:
            return cls()
        known = _known(cls, d)
        for key in ("normal", "point", "support_band"):
            if known.get(key) is not None:
                known[key] = tuple(known[key])
        if known.get("candidates") is not None:
            known["candidates"] = tuple(GroundCandidate.from_dict(c) for c in known["candidates"])
        if known.get("tiles") is not None:
            known["tiles"] = {name: cls.from_dict(t) for name, t in known["tiles"].items()}
        if known.get("local_model") is not None:
            known["local_model"] = LocalModel.from_dict(known["local_model"])
        return cls(**known)
