"""Point-wise metrics: ground segmentation (precision, recall, F1, IoU, ISPRS total error) and the
adjusted Rand index of a partition (``../shared/ALGORITHMS.md`` section 4)."""
from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np
from kbs.errors import ParameterError
from kbs.evaluation.hoover import as_labels


@dataclass(frozen=True)
class GroundMetrics:
    """Ground-class metrics of a per-point ground/not-ground prediction, unlabelled points left
    out.

    Every ratio whose denominator is zero takes the value ``zero_division`` (as scikit-learn's
    ``zero_division`` parameter, without the warning) and its name is listed in ``undefined``.

    Attributes
    ----------
    tp, fp, fn, tn : int
        Ground predicted as ground, object predicted as ground, ground predicted as object,
        object predicted as object; labelled points only.
    n_ignored : int
        Points left out because their GT label is an unlabelled value.
    precision : float
        TP / (TP + FP).
    recall : float
        TP / (TP + FN).
    f1 : float
        2 TP / (2 TP + FP + FN) (the harmonic mean of precision and recall).
    iou : float
        TP / (TP + FP + FN).
    total_error : float
        (FP + FN) / (TP + FP + FN + TN): the ISPRS filter test's total error.
    type_i : float
        FN / (TP + FN): ground rejected (ISPRS type I error).
    type_ii : float
        FP / (FP + TN): object accepted as ground (ISPRS type II error).
    undefined : tuple[str, ...]
        Names of the ratios that hit a zero denominator.
    """

    tp: int
    fp: int
    fn: int
    tn: int
    n_ignored: int
    precision: float
    recall: float
    f1: float
    iou: float
    total_error: float
    type_i: float
    type_ii: float
    undefined: tuple[str, ...] = ()

    @property
    def n_labelled(self) -> int:
        """TP + FP + FN + TN."""
        return self.tp + self.fp + self.fn + self.tn

    def to_dict(self) -> dict:
        """A JSON-ready dict (a NaN ratio becomes None)."""
        d = {k: getattr(self, k) for k in ("tp", "fp", "fn", "tn", "n_ignored", "precision", "recall", "f1",
                                           "iou", "total_error", "type_i", "type_ii")}
        d = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}
        d["undefined"] = list(self.undefined)
        return d


def ground_metrics(
    pred_is_ground: np.ndarray,
    gt_labels: np.ndarray,
    *,
    ground_values: Collection[int],
    unlabelled_values: Collection[int] = (),
    zero_division: float = 0.0,
) -> GroundMetrics:
    """Precision, recall, F1, IoU and ISPRS errors of the ground class.

    Parameters
    ----------
    pred_is_ground : np.ndarray, shape (N,), bool
        True where the segmentation says ground.
    gt_labels : np.ndarray, shape (N,) or (N, 1), int
        Ground-truth label of each point.
    ground_values : collection of int
        GT labels that are ground (e.g. SemanticKITTI {9, 10, 11, 12, 17}, ISPRS {0}).
    unlabelled_values : collection of int, default ()
        GT labels whose points are left out (e.g. SemanticKITTI {0}). Must not meet
        ``ground_values``.
    zero_division : float, default 0.0
        Value of a ratio whose denominator is zero: 0.0, 1.0 or nan, as in scikit-learn.

    Returns
    -------
    GroundMetrics

    Raises
    ------
    ParameterError
        Arrays of different lengths, a non-boolean prediction, ground values that are also
        unlabelled, or a ``zero_division`` other than 0, 1 or nan.
    """
    pred = np.asarray(pred_is_ground)
    if pred.ndim == 2 and pred.shape[1] == 1:
        pred = pred[:, 0]
    if pred.ndim != 1 or pred.dtype != bool:
        raise ParameterError(f"pred_is_ground must be a boolean array of shape (N,), got {pred.dtype} {pred.shape}")
    gt = as_labels(gt_labels, "gt_labels")
    if len(pred) != len(gt):
        raise ParameterError(f"pred_is_ground and gt_labels must have the same length, got {len(pred)} and {len(gt)}")
    ground = {int(v) for v in ground_values}
    unlabelled = {int(v) for v in unlabelled_values}
    if not ground:
        raise ParameterError("ground_values must name at least one GT label")
    if ground & unlabelled:
        raise ParameterError(f"labels {sorted(ground & unlabelled)} are both ground and unlabelled")
    zd = float(zero_division)
    if not (zd in (0.0, 1.0) or math.isnan(zd)):
        raise ParameterError(f"The 'zero_division' parameter must be 0.0, 1.0 or nan. Got {zero_division!r} instead.")
    labelled = ~np.isin(gt, np.fromiter(unlabelled, dtype=np.int64, count=len(unlabelled)))
    truth = np.isin(gt, np.fromiter(ground, dtype=np.int64, count=len(ground)))
    p, t = pred[labelled], truth[labelled]
    tp = int(np.count_nonzero(p & t))
    fp = int(np.count_nonzero(p & ~t))
    fn = int(np.count_nonzero(~p & t))
    tn = int(np.count_nonzero(~p & ~t))
    undefined: list[str] = []

    def ratio(name: str, num: int, den: int) -> float:
        if den == 0:
            undefined.append(name)
            return zd
        return num / den

    return GroundMetrics(
        tp=tp, fp=fp, fn=fn, tn=tn, n_ignored=int(len(gt) - np.count_nonzero(labelled)),
        precision=ratio("precision", tp, tp + fp), recall=ratio("recall", tp, tp + fn),
        f1=ratio("f1", 2 * tp, 2 * tp + fp + fn), iou=ratio("iou", tp, tp + fp + fn),
        total_error=ratio("total_error", fp + fn, tp + fp + fn + tn),
        type_i=ratio("type_i", fn, tp + fn), type_ii=ratio("type_ii", fp, fp + tn),
        undefined=tuple(undefined),
    )


def adjusted_rand(ms_labels: np.ndarray, gt_labels: np.ndarray, *, ignore: Collection[int] = (0,)) -> float:
    """Adjusted Rand index between a segmentation and the ground truth, on the labelled points.

    Computed by :func:`sklearn.metrics.adjusted_rand_score` on the points whose GT label is not
    in ``ignore``. MS noise (e.g. -1) is kept, as one more cluster: a segmentation that leaves
    points unassigned is not rewarded for it.

    Parameters
    ----------
    ms_labels : np.ndarray, shape (N,) or (N, 1), int
    gt_labels : np.ndarray, shape (N,) or (N, 1), int
    ignore : collection of int, default (0,)
        GT labels whose points are left out.

    Returns
    -------
    float
        In [-1, 1] (1: the same partition); nan when no point is labelled.
    """
    from sklearn.metrics import adjusted_rand_score  # lazy: a second on import, for every `kbs` command

    ms = as_labels(ms_labels, "ms_labels")
    gt = as_labels(gt_labels, "gt_labels")
    if len(ms) != len(gt):
        raise ParameterError(f"ms_labels and gt_labels must have the same length, got {len(ms)} and {len(gt)}")
    keep = ~np.isin(gt, np.asarray(list(ignore), dtype=np.int64))
    if not keep.any():
        return float("nan")
    return float(adjusted_rand_score(gt[keep], ms[keep]))
