"""Hoover et al. (1996) region metrics: correct detection, over- and under-segmentation, missed,
noise, and the angle metric (``../shared/ALGORITHMS.md`` section 4).

The classification follows the paper (A. Hoover, G. Jean-Baptiste, X. Jiang, P. J. Flynn,
H. Bunke, D. Goldgof, K. Bowyer, D. Eggert, A. Fitzgibbon, R. Fisher, *An experimental comparison
of range image segmentation algorithms*, IEEE PAMI 18(7), 1996) and the order in which its
reference tool, SegComp's ``compare`` (function ``ClassifyRegions``), considers the candidates:

1. every correct detection, GT regions in increasing label order (with T > 0.5 two correct
   detections can never share a region, so this order changes nothing);
2. then, GT regions in increasing label order, each over-segmentation;
3. then, MS regions in increasing label order, each under-segmentation;
4. GT regions left unclassified are missed, MS regions left unclassified are noise.

A candidate of steps 2-3 that shares a region with an instance already recorded replaces it only
when the mean of its two ratios is *strictly* higher (a tie keeps the earlier). With T > 0.5 the
only possible rival of an over-segmentation of GT n is the instance GT n is in, and the only
rival of an under-segmentation of MS m is the instance MS m is in, so this is exactly
``compare``'s test. One deliberate difference: when an under-segmentation replaces an
over-segmentation, ``compare`` leaves the other MS regions of the replaced instance marked
"over" although their GT region is now "under" (they are then counted nowhere); here a replaced
instance is removed whole, so those regions are left unclassified and end as noise. Every region
therefore ends in exactly one category.

Sizes P_m and P_n are counted over all points, as ``compare`` counts them over the whole image:
an MS region's points that are unlabelled in the GT count in its size (and lower its ratios),
and a GT region's points left as MS noise count in its size. A ratio is compared with T as the
quotient ``O / P >= T`` (as ``compare`` does), so a ratio exactly equal to T passes even when
``T * P`` rounds above ``O`` in floating point (e.g. 14 of 25 points at T = 0.56).
"""
from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from kbs.errors import ParameterError
from kbs.geometry.pca import principal_axes

Kind = Literal["correct", "over", "under"]

#: Minimum number of points for a region normal (a plane through fewer is not defined).
MIN_NORMAL_POINTS = 3


@dataclass(frozen=True)
class HooverInstance:
    """One classification instance: which GT and MS regions it binds, and its two ratios.

    Attributes
    ----------
    kind : {"correct", "over", "under"}
        Correct detection (one GT, one MS region), over-segmentation (one GT region, >= 2 MS
        regions) or under-segmentation (>= 2 GT regions, one MS region).
    gt, ms : tuple[int, ...]
        The GT and MS region labels, increasing.
    gt_ratio : float
        Overlap / total size of the GT side (``compare``'s measure 1).
    ms_ratio : float
        Overlap / total size of the MS side (``compare``'s measure 2).
    """

    kind: Kind
    gt: tuple[int, ...]
    ms: tuple[int, ...]
    gt_ratio: float
    ms_ratio: float

    @property
    def score(self) -> float:
        """Mean of the two ratios: the metric compared when two instances conflict."""
        return (self.gt_ratio + self.ms_ratio) / 2.0

    def to_dict(self) -> dict:
        """A JSON-ready dict."""
        return {"kind": self.kind, "gt": list(self.gt), "ms": list(self.ms),
                "gt_ratio": self.gt_ratio, "ms_ratio": self.ms_ratio}


@dataclass(frozen=True)
class AngleError:
    """The angle metric of one pair of adjacent, correctly detected GT regions (degrees).

    Attributes
    ----------
    gt : tuple[int, int]
        The two GT regions.
    ms : tuple[int, int]
        The MS regions matched to them by correct detection.
    gt_angle, ms_angle : float
        Angle between the GT normals and between the MS normals, folded to [0, 90].
    error : float
        ``|gt_angle - ms_angle|``.
    """

    gt: tuple[int, int]
    ms: tuple[int, int]
    gt_angle: float
    ms_angle: float
    error: float

    def to_dict(self) -> dict:
        """A JSON-ready dict."""
        return {"gt": list(self.gt), "ms": list(self.ms), "gt_angle": self.gt_angle,
                "ms_angle": self.ms_angle, "error": self.error}


@dataclass(frozen=True)
class HooverResult:
    """Hoover et al. (1996) classification of one segmentation against its ground truth.

    Attributes
    ----------
    tolerance : float
        T, in (0.5, 1].
    n_gt_regions, n_ms_regions : int
        Number of GT regions (labels not in ``gt_ignore``) and MS regions (not in ``ms_ignore``).
    correct : int
        Correct detections (= GT regions classified correct = MS regions classified correct).
    over : int
        Over-segmentations, counted in GT regions.
    under : int
        Under-segmentations, counted in MS regions.
    missed : int
        GT regions left unclassified.
    noise : int
        MS regions left unclassified.
    instances : tuple[HooverInstance, ...]
        The final instances: correct, then over, then under, each in increasing region order.
    gt_class, ms_class : Mapping[int, str]
        Category of every GT region ("correct", "over", "under", "missed") and of every MS
        region ("correct", "over", "under", "noise").
    gt_sizes, ms_sizes : Mapping[int, int]
        P_n and P_m, in points (over all points).
    replaced : tuple[tuple[HooverInstance, HooverInstance], ...]
        (old, new) for every instance replaced by one with a strictly higher mean ratio, in the
        order it happened.
    angle_mean, angle_std : float or None
        Mean and (population) standard deviation of the angle errors, degrees; None when the
        metric was not computed or no pair qualified (``angle_note`` says which).
    angle_errors : tuple[AngleError, ...]
        One entry per adjacent pair of correctly detected GT regions with both normals known.
    angle_note : str
        How the angle metric was obtained, or why it was not.
    """

    tolerance: float
    n_gt_regions: int
    n_ms_regions: int
    correct: int
    over: int
    under: int
    missed: int
    noise: int
    instances: tuple[HooverInstance, ...]
    gt_class: Mapping[int, str]
    ms_class: Mapping[int, str]
    gt_sizes: Mapping[int, int]
    ms_sizes: Mapping[int, int]
    replaced: tuple[tuple[HooverInstance, HooverInstance], ...] = ()
    angle_mean: float | None = None
    angle_std: float | None = None
    angle_errors: tuple[AngleError, ...] = ()
    angle_note: str = "not computed"
    counts: Mapping[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("gt_class", "ms_class", "gt_sizes", "ms_sizes"):
            value = getattr(self, name)
            if not isinstance(value, MappingProxyType):
                object.__setattr__(self, name, MappingProxyType(dict(value)))
        object.__setattr__(self, "counts", MappingProxyType({
            "correct": self.correct, "over": self.over, "under": self.under,
            "missed": self.missed, "noise": self.noise}))

    def to_dict(self) -> dict:
        """A JSON-ready dict (region labels as strings in the per-region mappings)."""
        return {
            "tolerance": self.tolerance, "n_gt_regions": self.n_gt_regions,
            "n_ms_regions": self.n_ms_regions, **dict(self.counts),
            "instances": [i.to_dict() for i in self.instances],
            "gt_class": {str(k): v for k, v in self.gt_class.items()},
            "ms_class": {str(k): v for k, v in self.ms_class.items()},
            "gt_sizes": {str(k): v for k, v in self.gt_sizes.items()},
            "ms_sizes": {str(k): v for k, v in self.ms_sizes.items()},
            "replaced": [{"old": a.to_dict(), "new": b.to_dict()} for a, b in self.replaced],
            "angle_mean": self.angle_mean, "angle_std": self.angle_std,
            "angle_pairs": len(self.angle_errors),
            "angle_errors": [a.to_dict() for a in self.angle_errors], "angle_note": self.angle_note,
        }


def as_labels(values: object, name: str) -> np.ndarray:
    """Per-point integer labels as an int64 array of shape (N,).

    Parameters
    ----------
    values : array-like, shape (N,) or (N, 1)
        Integers, booleans, or floats holding integers.
    name : str
        The parameter's name, for messages.

    Returns
    -------
    np.ndarray, shape (N,), int64

    Raises
    ------
    ParameterError
        Another shape, or values that are not integers.
    """
    a = np.asarray(values)
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1:
        raise ParameterError(f"{name} must have shape (N,) or (N, 1), got {a.shape}")
    if a.dtype.kind in "iub":
        if a.dtype.kind == "u" and a.dtype.itemsize >= 8 and a.size:  # beyond int64: it would wrap
            _refuse_beyond_int64(a, a > np.uint64(LABEL_MAX), name)
        return a.astype(np.int64, copy=False)
    if a.dtype.kind == "f":
        if not np.isfinite(a).all() or not (a == np.round(a)).all():
            raise ParameterError(f"{name} must hold integer labels, got non-integer values")
        if a.size:  # 2^63 and beyond (as a float) has no int64: the cast would give another number
            _refuse_beyond_int64(a, (a < -2.0 ** 63) | (a >= 2.0 ** 63), name)
        return a.astype(np.int64)
    raise ParameterError(f"{name} must hold integer labels, got dtype {a.dtype}")


#: The range of a label (int64): a label outside it is refused, never wrapped or rounded.
LABEL_MIN, LABEL_MAX = -(2 ** 63), 2 ** 63 - 1


class LabelRangeError(ParameterError):
    """A label beyond :data:`LABEL_MIN` .. :data:`LABEL_MAX`: ``index`` (0-based) and ``value``."""

    def __init__(self, name: str, index: int, value: object) -> None:
        self.index, self.value = index, value
        super().__init__(f"{name}[{index}] = {value} is beyond the range of a label (a 64-bit signed integer, "
                         f"{LABEL_MIN} .. {LABEL_MAX})")


def _refuse_beyond_int64(a: np.ndarray, beyond: np.ndarray, name: str) -> None:
    bad = np.flatnonzero(beyond)
    if bad.size:
        i = int(bad[0])
        value = a[i].item()
        raise LabelRangeError(name, i, f"{value:g}" if isinstance(value, float) else value)


def check_tolerance(tolerance: float) -> float:
    """Validate T (0.5 < T <= 1) and return it as a float."""
    t = float(tolerance)
    if not 0.5 < t <= 1.0:
        raise ParameterError(f"The 'tolerance' parameter must be a float in the range (0.5, 1]. "
                             f"Got {tolerance!r} instead.")
    return t


def median_spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest distinct neighbour.

    Parameters
    ----------
    points : np.ndarray, shape (N, 3)

    Returns
    -------
    float
        The median over points having a neighbour at a non-zero distance (duplicates are
        skipped); 0.0 when there is none.
    """
    X = np.asarray(points, dtype=np.float64)
    if len(X) < 2:
        return 0.0
    tree = cKDTree(X)
    d, _ = tree.query(X, k=2)
    d = d[:, 1]
    d = d[d > 0]
    if d.size == 0:
        return 0.0
    return float(np.median(d))


def region_normals(points: np.ndarray, labels: np.ndarray,
                   regions: Iterable[int] | None = None) -> dict[int, np.ndarray]:
    """Unit normal of each region: the eigenvector of its point covariance with the smallest
    eigenvalue.

    Parameters
    ----------
    points : np.ndarray, shape (N, 3)
    labels : np.ndarray, shape (N,), int
    regions : iterable of int, optional
        The labels to compute (default: every label present).

    Returns
    -------
    dict[int, np.ndarray]
        Label -> normal, shape (3,). Regions with fewer than :data:`MIN_NORMAL_POINTS` points
        have no normal and are left out.
    """
    X = _points(points, len(labels))
    labels = as_labels(labels, "labels")
    wanted = np.unique(labels) if regions is None else np.asarray(sorted(set(int(r) for r in regions)), dtype=np.int64)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    out: dict[int, np.ndarray] = {}
    for r in wanted:
        lo, hi = np.searchsorted(sorted_labels, r, side="left"), np.searchsorted(sorted_labels, r, side="right")
        if hi - lo < MIN_NORMAL_POINTS:
            continue
        P = X[order[lo:hi]]
        out[int(r)] = principal_axes(P).normal
    return out


def adjacent_regions(points: np.ndarray, labels: np.ndarray, *, distance: float | None = None,
                     regions: Iterable[int] | None = None) -> set[tuple[int, int]]:
    """Pairs of regions that have points within ``distance`` of each other.

    Parameters
    ----------
    points : np.ndarray, shape (N, 3)
    labels : np.ndarray, shape (N,), int
    distance : float, optional
        Default: 3 x :func:`median_spacing` of ``points`` (all of them).
    regions : iterable of int, optional
        Only pairs among these labels are tested (default: every label present).

    Returns
    -------
    set[tuple[int, int]]
        ``(a, b)`` with ``a < b``.
    """
    X = _points(points, len(labels))
    labels = as_labels(labels, "labels")
    d = 3.0 * median_spacing(X) if distance is None else float(distance)
    if not d >= 0 or not math.isfinite(d):
        raise ParameterError(f"The 'distance' parameter must be a finite float >= 0. Got {distance!r} instead.")
    wanted = sorted(set(np.unique(labels).tolist()) if regions is None else {int(r) for r in regions})
    pts = {r: X[labels == r] for r in wanted}
    pts = {r: p for r, p in pts.items() if len(p)}
    boxes = {r: (p.min(axis=0), p.max(axis=0)) for r, p in pts.items()}
    trees: dict[int, cKDTree] = {}
    bound = np.nextafter(d, np.inf)  # cKDTree keeps neighbours strictly closer than the bound
    out: set[tuple[int, int]] = set()
    keys = sorted(pts)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            (lo_a, hi_a), (lo_b, hi_b) = boxes[a], boxes[b]
            if (lo_a - hi_b > d).any() or (lo_b - hi_a > d).any():
                continue  # the bounding boxes are farther apart than d along an axis
            small, big = (a, b) if len(pts[a]) <= len(pts[b]) else (b, a)
            if big not in trees:
                trees[big] = cKDTree(pts[big])
            dist, _ = trees[big].query(pts[small], k=1, distance_upper_bound=bound)
            if np.isfinite(dist).any():
                out.add((a, b))
    return out


def _points(points: object, n: int) -> np.ndarray:
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) != n:
        raise ParameterError(f"points must have shape ({n}, 3), got {X.shape}")
    if not np.isfinite(X).all():
        raise ParameterError("points must be finite")
    return X


def folded_angle(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two normals in degrees, folded to [0, 90] (orientation ignored)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu == 0 or nv == 0 or not (np.isfinite(nu) and np.isfinite(nv)):
        raise ParameterError("a normal must be a finite non-zero vector")
    c = abs(float(np.dot(u, v)) / (nu * nv))
    return math.degrees(math.acos(min(1.0, c)))


class _Book:
    """The instances recorded so far, indexed by region on both sides."""

    def __init__(self) -> None:
        self.gt: dict[int, HooverInstance] = {}
        self.ms: dict[int, HooverInstance] = {}
        self.replaced: list[tuple[HooverInstance, HooverInstance]] = []

    def offer(self, cand: HooverInstance) -> bool:
        rivals: dict[int, HooverInstance] = {}
        for n in cand.gt:
            if n in self.gt:
                rivals[id(self.gt[n])] = self.gt[n]
        for m in cand.ms:
            if m in self.ms:
                rivals[id(self.ms[m])] = self.ms[m]
        if any(cand.score <= r.score for r in rivals.values()):
            return False  # a tie keeps the earlier instance
        for r in rivals.values():
            for n in r.gt:
                del self.gt[n]
            for m in r.ms:
                del self.ms[m]
            self.replaced.append((r, cand))
        for n in cand.gt:
            self.gt[n] = cand
        for m in cand.ms:
            self.ms[m] = cand
        return True


def hoover(
    ms_labels: np.ndarray,
    gt_labels: np.ndarray,
    *,
    tolerance: float = 0.8,
    ms_ignore: Collection[int] = (-1,),
    gt_ignore: Collection[int] = (0,),
    points: np.ndarray | None = None,
    ms_normals: Mapping[int, np.ndarray] | None = None,
    gt_normals: Mapping[int, np.ndarray] | None = None,
    gt_adjacency: Iterable[tuple[int, int]] | None = None,
    adjacency_distance: float | None = None,
) -> HooverResult:
    """Classify the regions of a machine segmentation (MS) against a ground truth (GT).

    Each label value not ignored is a region (not necessarily connected). With O_mn the points
    of MS region m in GT region n, and P_m, P_n the region sizes counted over ALL points:

    - correct detection of (m, n): O_mn >= T P_m and O_mn >= T P_n;
    - over-segmentation of GT n: the MS regions with O_mn >= T P_m, if there are >= 2 of them
      and together sum(O) >= T P_n and sum(O) >= T sum(P_m);
    - under-segmentation of MS m: the mirror image;
    - missed: GT regions left unclassified; noise: MS regions left unclassified.

    Conflicts are resolved as in Hoover et al. (1996) and SegComp's ``compare``: correct
    detections first, then over-segmentations (GT regions in increasing label order), then
    under-segmentations (MS regions in increasing label order), each replacing the instance it
    conflicts with only when the mean of its two ratios is strictly higher. See the module
    docstring for the details and the one difference with ``compare``.

    Angle metric: for each pair of adjacent GT regions that are both correctly detected,
    ``|angle(GT normals) - angle(matched MS normals)|`` in degrees, both angles folded to
    [0, 90]; mean and population standard deviation (as ``compare``). Normals and adjacency are
    taken from ``ms_normals``, ``gt_normals`` and ``gt_adjacency`` when given, else computed from
    ``points`` (normal: smallest-eigenvalue eigenvector of the region's covariance; adjacency:
    points of the two GT regions within ``adjacency_distance``). When something needed is
    neither given nor computable, the metric is None and ``angle_note`` says why.

    Parameters
    ----------
    ms_labels : np.ndarray, shape (N,) or (N, 1), int
        Machine segmentation, one region label per point.
    gt_labels : np.ndarray, shape (N,) or (N, 1), int
        Ground truth, one region label per point.
    tolerance : float, default 0.8
        T, in (0.5, 1].
    ms_ignore : collection of int, default (-1,)
        MS labels that are not regions (noise, unassigned).
    gt_ignore : collection of int, default (0,)
        GT labels that are not regions (unlabelled, invalid).
    points : np.ndarray, shape (N, 3), optional
        Coordinates, to compute the normals and the GT adjacency that are not given.
    ms_normals, gt_normals : Mapping[int, np.ndarray], optional
        Region label -> normal, shape (3,), any length and orientation.
    gt_adjacency : iterable of (int, int), optional
        Pairs of adjacent GT regions (either order).
    adjacency_distance : float, optional
        Distance for the computed adjacency; default 3 x the median nearest-neighbour spacing of
        ``points``.

    Returns
    -------
    HooverResult

    Raises
    ------
    ParameterError
        Labels of different lengths or not integers, T out of (0.5, 1], bad ``points``.
    """
    ms = as_labels(ms_labels, "ms_labels")
    gt = as_labels(gt_labels, "gt_labels")
    if ms.shape != gt.shape:
        raise ParameterError(f"ms_labels and gt_labels must have the same length, got {len(ms)} and {len(gt)}")
    T = check_tolerance(tolerance)
    ms_ids, ms_inv, ms_cnt = np.unique(ms, return_inverse=True, return_counts=True)
    gt_ids, gt_inv, gt_cnt = np.unique(gt, return_inverse=True, return_counts=True)
    ms_region = ~np.isin(ms_ids, np.asarray(list(ms_ignore), dtype=np.int64))
    gt_region = ~np.isin(gt_ids, np.asarray(list(gt_ignore), dtype=np.int64))
    ms_size = {int(ms_ids[i]): int(ms_cnt[i]) for i in np.flatnonzero(ms_region)}
    gt_size = {int(gt_ids[i]): int(gt_cnt[i]) for i in np.flatnonzero(gt_region)}

    # sparse overlap table: the (m, n) pairs that share points, both regions
    key = ms_inv.astype(np.int64).ravel() * len(gt_ids) + gt_inv.astype(np.int64).ravel()
    pair_key, pair_o = np.unique(key, return_counts=True)
    pm, pn = np.divmod(pair_key, len(gt_ids))
    keep = ms_region[pm] & gt_region[pn]
    pairs = [(int(ms_ids[m]), int(gt_ids[n]), int(o)) for m, n, o in zip(pm[keep], pn[keep], pair_o[keep])]

    book = _Book()
    # 1. correct detections (GT n outer, MS m inner, as compare)
    for m, n, o in sorted(pairs, key=lambda p: (p[1], p[0])):
        if o / ms_size[m] >= T and o / gt_size[n] >= T:
            book.offer(HooverInstance("correct", (n,), (m,), o / gt_size[n], o / ms_size[m]))
    # 2. over-segmentations of each GT region
    by_gt: dict[int, list[tuple[int, int]]] = {}
    by_ms: dict[int, list[tuple[int, int]]] = {}
    for m, n, o in pairs:
        by_gt.setdefault(n, []).append((m, o))
        by_ms.setdefault(m, []).append((n, o))
    for n in sorted(by_gt):
        parts = sorted((m, o) for m, o in by_gt[n] if o / ms_size[m] >= T)
        if len(parts) < 2:
            continue
        total_o = sum(o for _, o in parts)
        r_gt, r_ms = total_o / gt_size[n], total_o / sum(ms_size[m] for m, _ in parts)
        if r_gt >= T and r_ms >= T:
            book.offer(HooverInstance("over", (n,), tuple(m for m, _ in parts), r_gt, r_ms))
    # 3. under-segmentations of each MS region
    for m in sorted(by_ms):
        parts = sorted((n, o) for n, o in by_ms[m] if o / gt_size[n] >= T)
        if len(parts) < 2:
            continue
        total_o = sum(o for _, o in parts)
        r_gt, r_ms = total_o / sum(gt_size[n] for n, _ in parts), total_o / ms_size[m]
        if r_gt >= T and r_ms >= T:
            book.offer(HooverInstance("under", tuple(n for n, _ in parts), (m,), r_gt, r_ms))

    # 4. missed and noise
    gt_class = {n: (book.gt[n].kind if n in book.gt else "missed") for n in sorted(gt_size)}
    ms_class = {m: (book.ms[m].kind if m in book.ms else "noise") for m in sorted(ms_size)}
    unique = {id(i): i for i in list(book.gt.values()) + list(book.ms.values())}.values()
    rank = {"correct": 0, "over": 1, "under": 2}
    instances = tuple(sorted(unique, key=lambda i: (rank[i.kind], i.gt, i.ms)))
    values = list(gt_class.values())
    n_under_ms = sum(1 for v in ms_class.values() if v == "under")

    angle_mean, angle_std, errors, note = _angle_metric(
        instances, ms, gt, points, ms_normals, gt_normals, gt_adjacency, adjacency_distance)
    return HooverResult(
        tolerance=T, n_gt_regions=len(gt_size), n_ms_regions=len(ms_size),
        correct=values.count("correct"), over=values.count("over"), under=n_under_ms,
        missed=values.count("missed"), noise=sum(1 for v in ms_class.values() if v == "noise"),
        instances=instances, gt_class=gt_class, ms_class=ms_class, gt_sizes=gt_size, ms_sizes=ms_size,
        replaced=tuple(book.replaced), angle_mean=angle_mean, angle_std=angle_std,
        angle_errors=errors, angle_note=note,
    )


def _angle_metric(instances, ms, gt, points, ms_normals, gt_normals, gt_adjacency, adjacency_distance):
    """(mean, std, errors, note) of the angle metric; None, None, (), why when not computed."""
    match = {i.gt[0]: i.ms[0] for i in instances if i.kind == "correct"}
    X = None if points is None else _points(points, len(gt))
    missing = [name for name, given in (("ms_normals", ms_normals), ("gt_normals", gt_normals),
                                        ("gt_adjacency", gt_adjacency)) if given is None]
    if missing and X is None:
        return None, None, (), f"not computed: no points and no {', '.join(missing)}"
    sources = []
    if gt_adjacency is None:
        adjacency = adjacent_regions(X, gt, distance=adjacency_distance, regions=match)
        sources.append("GT adjacency from points (within "
                       + (f"{adjacency_distance:g}" if adjacency_distance is not None else "3 x median spacing") + ")")
    else:
        adjacency = {(min(int(a), int(b)), max(int(a), int(b))) for a, b in gt_adjacency if int(a) != int(b)}
    if gt_normals is None:
        gt_normals = region_normals(X, gt, match.keys())
        sources.append("GT normals from points")
    if ms_normals is None:
        ms_normals = region_normals(X, ms, match.values())
        sources.append("MS normals from points")
    errors = []
    for a, b in sorted(adjacency):
        if a not in match or b not in match:
            continue
        ma, mb = match[a], match[b]
        if a not in gt_normals or b not in gt_normals or ma not in ms_normals or mb not in ms_normals:
            continue  # a region too small for a normal
        g = folded_angle(gt_normals[a], gt_normals[b])
        s = folded_angle(ms_normals[ma], ms_normals[mb])
        errors.append(AngleError((a, b), (ma, mb), g, s, abs(g - s)))
    how = "; ".join(sources) if sources else "normals and adjacency given"
    if not errors:
        return None, None, (), f"no adjacent pair of correctly detected GT regions; {how}"
    e = np.array([x.error for x in errors])
    return float(e.mean()), float(e.std()), tuple(errors), how


def hoover_average(results: Iterable[HooverResult]) -> dict[str, float | int | None]:
    """Average Hoover counts per scan over a set of scans.

    Parameters
    ----------
    results : iterable of HooverResult
        One per scan, all at the same tolerance.

    Returns
    -------
    dict
        ``n_scans``, ``tolerance``; the per-scan means of ``n_gt_regions``, ``n_ms_regions``,
        ``correct``, ``over``, ``under``, ``missed``, ``noise``; ``angle_pairs`` (total);
        ``angle_mean`` and ``angle_std`` pooled over all pairs of all scans (None when there is
        no pair); ``angle_mean_per_scan``, the mean of the per-scan means over the scans with at
        least one pair (how SegComp's ``compare`` averages an image sequence).

    Raises
    ------
    ParameterError
        No result, or results at different tolerances.
    """
    res = list(results)
    if not res:
        raise ParameterError("hoover_average needs at least one result")
    tolerances = {r.tolerance for r in res}
    if len(tolerances) > 1:
        raise ParameterError(f"cannot average results at different tolerances: {sorted(tolerances)}")
    out: dict[str, float | int | None] = {"n_scans": len(res), "tolerance": res[0].tolerance}
    for name in ("n_gt_regions", "n_ms_regions", "correct", "over", "under", "missed", "noise"):
        out[name] = float(np.mean([getattr(r, name) for r in res]))
    errors = np.array([e.error for r in res for e in r.angle_errors])
    out["angle_pairs"] = int(errors.size)
    out["angle_mean"] = float(errors.mean()) if errors.size else None
    out["angle_std"] = float(errors.std()) if errors.size else None
    per_scan = [r.angle_mean for r in res if r.angle_mean is not None]
    out["angle_mean_per_scan"] = float(np.mean(per_scan)) if per_scan else None
    return out
