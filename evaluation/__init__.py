"""Evaluation of segmentations: Hoover et al. (1996) region metrics, ground-segmentation metrics, ground-truth loading.

>>> from kbs.evaluation import hoover, ground_metrics, adjusted_rand, load_ground_truth
>>> r = hoover(ms_labels, gt_labels, tolerance=0.8, points=xyz)      # doctest: +SKIP
>>> r.correct, r.over, r.under, r.missed, r.noise, r.angle_mean      # doctest: +SKIP
>>> g = ground_metrics(label == 0, gt, ground_values={9, 10, 11, 12, 17}, unlabelled_values={0})  # doctest: +SKIP
>>> g.precision, g.recall, g.f1, g.iou, g.total_error                # doctest: +SKIP

See ``../shared/ALGORITHMS.md`` section 4 for the definitions; :mod:`kbs.evaluation.hoover`
says which conflict-resolution order is followed and why.
"""
from __future__ import annotations

from kbs.evaluation.groundtruth import (
    FIELD_PREFIX,
    SEMANTICKITTI_GROUND,
    SEMANTICKITTI_IGNORED,
    UnknownFieldError,
    is_semantickitti_label,
    load_ground_truth,
)
from kbs.evaluation.hoover import (
    AngleError,
    HooverInstance,
    HooverResult,
    adjacent_regions,
    folded_angle,
    hoover,
    hoover_average,
    median_spacing,
    region_normals,
)
from kbs.evaluation.metrics import GroundMetrics, adjusted_rand, ground_metrics

__all__ = [
    "AngleError", "FIELD_PREFIX", "GroundMetrics", "HooverInstance", "HooverResult", "SEMANTICKITTI_GROUND",
    "SEMANTICKITTI_IGNORED", "UnknownFieldError",
    "adjacent_regions", "adjusted_rand", "folded_angle", "ground_metrics", "hoover", "hoover_average",
    "is_semantickitti_label", "load_ground_truth", "median_spacing", "region_normals",
]
