"""The result of a run (:class:`Segmentation`) and the kinds of limit that keep a cluster from
being divided (:data:`STOP_KINDS`)."""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kbs.knowledge.explain import NO_LABEL, Explanation


@dataclass(frozen=True)
class Segmentation:
    """The result of a run.

    Attributes
    ----------
    cluster : ndarray (n,) int32
        Output cluster of each point (numbered by decreasing size), -1 = not assigned (noise).
    label : ndarray (n,) int32
        Index into ``label_names``, -1 = none (noise).
    membership : ndarray (n,) float32
        Membership of each point in its cluster (product of the fuzzy memberships along its path
        in the split tree; crisp splits count 1).
    label_names : list of str
    explanation : Explanation
    clusters : list of dict
        One per output cluster: index, ids of the records merged into it, label, size, descriptors.
    seconds : float
    """

    cluster: np.ndarray
    label: np.ndarray
    membership: np.ndarray
    label_names: list[str]
    explanation: Explanation
    clusters: list[dict[str, Any]]
    seconds: float

    @property
    def n_splits(self) -> int:
        return sum(bool(r.children) and r.action != "partition" for r in self.explanation.records.values())

    def limits_by_kind(self) -> dict[str, dict[str, Any]]:
        """The clusters a rule wanted split but that were kept, grouped by what stopped them.

        Keys are the kinds of :data:`STOP_KINDS`, in that order (only those that occurred). Each
        value: ``setting`` (the rule-file key that decides it, e.g. ``'limits.max_depth'``, or None
        when it is not a setting: the split failed, or gave a single cluster), ``value`` (that
        setting's value), ``count``, ``points`` (their points when judged) and ``clusters`` (their
        ids, the largest first).
        """
        return limits_by_kind((r.n_points, r.id, r.limit) for r in self.explanation.records.values()
                              if r.action == "limit")

    def with_set_aside(self, aside: np.ndarray, note: str) -> Segmentation:
        """This result, of the points ``~aside`` of a cloud, as the result of the whole cloud: the
        points ``aside`` (a mask) are noise (no cluster, no label, membership 0), and ``note`` is
        added to the explanation's notes."""
        from dataclasses import replace

        keep = ~np.asarray(aside, dtype=bool)
        cluster = np.full(keep.size, -1, dtype=self.cluster.dtype)
        label = np.full(keep.size, -1, dtype=self.label.dtype)
        membership = np.zeros(keep.size, dtype=self.membership.dtype)
        cluster[keep], label[keep], membership[keep] = self.cluster, self.label, self.membership
        return replace(self, cluster=cluster, label=label, membership=membership,
                       explanation=replace(self.explanation, notes=[*self.explanation.notes, note]))

    def summary(self) -> dict[str, Any]:
        """Counts; ``points_per_label``: each label's points, then ``noise`` (points in no output
        cluster: rejected; ``noise (rejected)`` when the rule base has a label named noise) and,
        when there are, ``no label matched`` (points of output clusters no label's condition held
        for)."""
        counts = {name: int((self.label == i).sum()) for i, name in enumerate(self.label_names)}
        counts["noise (rejected)" if "noise" in counts else "noise"] = int((self.cluster < 0).sum())
        unlabelled = int(((self.label < 0) & (self.cluster >= 0)).sum())
        if unlabelled:
            counts[NO_LABEL] = unlabelled
        return {"points": int(self.cluster.size), "clusters": len(self.clusters), "splits": self.n_splits,
                "limits": sum(r.action == "limit" for r in self.explanation.records.values()),
                "limits_by_kind": self.limits_by_kind(),
                "points_per_label": counts, "seconds": round(self.seconds, 3)}


def limits_by_kind(stopped: Iterable[tuple[int, str, Any]]) -> dict[str, dict[str, Any]]:
    """:meth:`Segmentation.limits_by_kind` of the records a limit stopped, given as (n_points, id,
    limit) (a tiled run's, without a record object each)."""
    out: dict[str, dict[str, Any]] = {}
    for n_points, rid, limit in sorted(stopped, key=lambda s: (-s[0], s[1])):
        lim = limit or {"kind": "other", "setting": None, "value": None}
        e = out.setdefault(lim["kind"], {"setting": lim["setting"], "value": lim["value"], "count": 0,
                                         "points": 0, "clusters": []})
        e["count"] += 1
        e["points"] += n_points
        e["clusters"].append(rid)
    order = list(STOP_KINDS)
    return dict(sorted(out.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))


#: Why a cluster that a rule wanted split was kept (``ClusterRecord.limit['kind']``), and the
#: rule-file setting that decides it (None: not a setting of the file).
STOP_KINDS: dict[str, str | None] = {
    "max_depth": "limits.max_depth",          # the cluster is max_depth splits below the scene
    "min_points": "limits.min_points",        # it has fewer points
    "max_clusters": "limits.max_clusters",    # the whole split tree has that many clusters (optional cap)
    "k_max": "engine.k_max",                  # strategy global: no partition of the scene beyond K = k_max
    "split_failed": None,                     # the engine could not split its points
    "single_cluster": None,                   # the split put all its points in one cluster
    "unpartitioned": None,                    # the scene could not be partitioned (further, for global)
}


#: far outliers: points farther than this many times the largest side of the box of the central 98 %
#: of a cloud beyond that box (see :func:`far_outliers`)
FAR_OUTLIER_FACTOR = 2.0
#: clouds of fewer points are not searched for far outliers (the central 98 % is then most of them)
FAR_OUTLIER_MIN_POINTS = 100
#: the percentiles of a larger cloud are those of every k-th point, about this many
FAR_OUTLIER_SAMPLE = 1_000_000


def far_outliers(X: np.ndarray, factor: float | None = FAR_OUTLIER_FACTOR) -> tuple[np.ndarray, float] | None:
    """The points of ``X`` (n, 3) that lie so far from the rest of the cloud that they are glitches
    (a lidar return kilometres away, a damaged record), and the size that decided it: the box of
    the central 98 % of the points (1st to 99th percentile on each axis, of every k-th point of a
    cloud of more than :data:`FAR_OUTLIER_SAMPLE`) and its largest side E; a
    point more than ``factor`` x E beyond the box, on any axis (the rule base's
    ``scene.far_outliers.factor``, :data:`FAR_OUTLIER_FACTOR` by default). None when there is
    none (or ``factor`` is None: the rule base asks for none to be set aside; or the cloud has
    fewer than :data:`FAR_OUTLIER_MIN_POINTS` points, or E is 0).

    One such point is enough to make UFP-ONC's first partition a single cluster (its new
    prototype takes the outlier alone, which dies): the whole scene would be judged as one
    cluster."""
    if factor is None or X.ndim != 2 or X.shape[0] < FAR_OUTLIER_MIN_POINTS or not np.isfinite(X).all():
        return None
    step = max(1, X.shape[0] // FAR_OUTLIER_SAMPLE)  # the percentiles of a regular sample of a large cloud
    lo, hi = np.percentile(X[::step], [1.0, 99.0], axis=0)
    side = float((hi - lo).max())
    if not side > 0.0:
        return None
    reach = factor * side
    far = ((X < lo - reach) | (X > hi + reach)).any(axis=1)
    return (far, side) if far.any() else None
