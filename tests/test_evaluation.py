"""Tests of kbs.evaluation (Hoover metrics, ground metrics, ARI, ground-truth loading) and of
`kbs eval`. The label arrays are built from blocks ``(ms, gt, count)``: ``count`` points with MS
label ``ms`` and GT label ``gt``; each expected answer is worked out by hand in a comment."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData
from sklearn.metrics import adjusted_rand_score, f1_score, jaccard_score, precision_score, recall_score

from kbs.cli.main import main
from kbs.errors import CloudFileError, ParameterError
from kbs.evaluation import (
    UnknownFieldError,
    adjacent_regions,
    adjusted_rand,
    ground_metrics,
    hoover,
    hoover_average,
    load_ground_truth,
)
from kbs.io import PointCloud, write_ply
from scenes import ground_and_rocks
from test_cli import kbs


def blocks(*spec: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(ms, gt) label arrays from blocks (ms label, gt label, number of points)."""
    ms = np.concatenate([np.full(c, m) for m, _, c in spec])
    gt = np.concatenate([np.full(c, g) for _, g, c in spec])
    return ms, gt


def counts(r) -> tuple[int, int, int, int, int]:
    return r.correct, r.over, r.under, r.missed, r.noise


# --- one test per category -------------------------------------------------------------------

def test_correct_detection():
    # GT 10: 9 pts in MS 1 + 1 pt left as MS noise (-1) -> P_n = 10; MS 1: those 9 + 1 GT-unlabelled
    # pt -> P_m = 10. O = 9: 9/10 >= 0.8 both ways -> correct (0.9, 0.9). GT 20 = MS 2 exactly: (1, 1).
    ms, gt = blocks((1, 10, 9), (-1, 10, 1), (1, 0, 1), (2, 20, 10))
    r = hoover(ms, gt)
    assert counts(r) == (2, 0, 0, 0, 0)
    assert dict(r.gt_class) == {10: "correct", 20: "correct"} and dict(r.ms_class) == {1: "correct", 2: "correct"}
    first = r.instances[0]
    assert (first.kind, first.gt, first.ms, first.gt_ratio, first.ms_ratio) == ("correct", (10,), (1,), 0.9, 0.9)


def test_over_segmentation():
    # GT 10 (11 pts): MS 1 has 6, MS 2 has 4, MS 3 has 1 (MS 3's other pt is GT-unlabelled).
    # MS 1, 2 lie wholly in GT 10 (O/P_m = 1 >= 0.8); MS 3: 1/2 < 0.8, not part of it.
    # Together 10/11 = 0.909 of GT 10 and 10/10 of themselves -> over-segmentation; MS 3 noise.
    ms, gt = blocks((1, 10, 6), (2, 10, 4), (3, 10, 1), (3, 0, 1))
    r = hoover(ms, gt)
    assert counts(r) == (0, 1, 0, 0, 1)
    (inst,) = r.instances
    assert (inst.kind, inst.gt, inst.ms) == ("over", (10,), (1, 2))
    assert inst.gt_ratio == pytest.approx(10 / 11) and inst.ms_ratio == 1.0
    assert dict(r.ms_class) == {1: "over", 2: "over", 3: "noise"}


def test_under_segmentation():
    # MS 1 (11 pts) holds all of GT 10 (6 pts) and GT 20 (4 pts) and 1 pt of GT 30 (GT 30: 2 pts,
    # the other in MS 2). GT 10, 20: O/P_n = 1; GT 30: 1/2 < 0.8, not part of it. Together 10/10 of
    # the GT regions and 10/11 = 0.909 of MS 1 -> under-segmentation; GT 30 missed, MS 2 noise.
    ms, gt = blocks((1, 10, 6), (1, 20, 4), (1, 30, 1), (2, 30, 1))
    r = hoover(ms, gt)
    assert counts(r) == (0, 0, 1, 1, 1)
    (inst,) = r.instances
    assert (inst.kind, inst.gt, inst.ms) == ("under", (10, 20), (1,))
    assert dict(r.gt_class) == {10: "under", 20: "under", 30: "missed"}


def test_missed():
    # GT 10 (10 pts): 5 in MS 1, 5 left as MS noise. 5/10 < 0.8 -> not correct; one MS region only
    # -> no over-segmentation -> missed. MS 1 (5 pts, all in GT 10): 5/10 of GT 10 < 0.8 -> noise.
    ms, gt = blocks((1, 10, 5), (-1, 10, 5))
    r = hoover(ms, gt)
    assert counts(r) == (0, 0, 0, 1, 1) and dict(r.gt_class) == {10: "missed"}


def test_noise():
    # MS 5 lies on GT-unlabelled points only: no GT region at all -> noise; GT 10 = MS 1 -> correct.
    ms, gt = blocks((5, 0, 7), (1, 10, 4))
    r = hoover(ms, gt)
    assert counts(r) == (1, 0, 0, 0, 1) and dict(r.ms_class) == {1: "correct", 5: "noise"}
    assert r.n_gt_regions == 1 and r.n_ms_regions == 2


# --- tolerance boundary, sizes over all points -----------------------------------------------

@pytest.mark.parametrize("o, p, t", [(4, 5, 0.8), (14, 25, 0.56), (55, 100, 0.55), (9, 10, 0.9)])
def test_a_ratio_exactly_t_passes_and_just_above_fails(o, p, t):
    # GT 10 has p pts, o of them in MS 1 (= all of MS 1), the rest MS noise: ratios o/p and 1.
    # o/p == t exactly passes (14/25 at T = 0.56 although 0.56 * 25 = 14.000000000000002 in floats).
    ms, gt = blocks((1, 10, o), (-1, 10, p - o))
    assert counts(hoover(ms, gt, tolerance=t)) == (1, 0, 0, 0, 0)
    assert counts(hoover(ms, gt, tolerance=t + 1e-9)) == (0, 0, 0, 1, 1)


def test_sizes_count_points_unlabelled_on_the_other_side():
    # MS 1 covers all 10 pts of GT 10 plus 3 GT-unlabelled pts: P_m = 13, O/P_m = 10/13 = 0.769
    # < 0.8 -> not correct (it would be, were P_m counted over GT-labelled points only): missed +
    # noise. Mirror: GT 20 = 10 pts of MS 2 + 3 pts of MS noise: P_n = 13 -> missed + noise.
    ms, gt = blocks((1, 10, 10), (1, 0, 3), (2, 20, 10), (-1, 20, 3))
    r = hoover(ms, gt)
    assert counts(r) == (0, 0, 0, 2, 2)
    assert dict(r.ms_sizes) == {1: 13, 2: 10} and dict(r.gt_sizes) == {10: 10, 20: 13}
    assert counts(hoover(ms, gt, tolerance=0.75)) == (2, 0, 0, 0, 0)  # 10/13 = 0.769 >= 0.75


# --- conflict resolution ---------------------------------------------------------------------

def test_over_segmentation_replaces_a_correct_detection_with_a_lower_mean():
    # GT 10 (10 pts): MS 1 has 9, MS 2 has 1. Correct (MS 1, GT 10): (9/10, 9/9), mean 0.95.
    # Over (GT 10; MS 1, 2): (10/10, 10/10), mean 1.0 > 0.95 -> the over-segmentation wins.
    ms, gt = blocks((1, 10, 9), (2, 10, 1))
    r = hoover(ms, gt)
    assert counts(r) == (0, 1, 0, 0, 0)
    ((old, new),) = r.replaced
    assert (old.kind, old.score, new.kind, new.score) == ("correct", 0.95, "over", 1.0)


def test_a_correct_detection_with_a_higher_mean_is_kept():
    # T = 0.51. GT 10 (31 pts): 16 in MS 1, 4 in MS 2, 11 MS noise; MS 2 also has 3 GT-unlabelled.
    # Correct (MS 1, GT 10): (16/31, 16/16) = (0.516, 1), mean 0.7581.
    # MS 2: 4/7 = 0.571 >= 0.51, so over (GT 10; MS 1, 2): (20/31, 20/23) = (0.645, 0.870),
    # mean 0.7574 < 0.7581 -> the correct detection stays; MS 2 ends as noise.
    ms, gt = blocks((1, 10, 16), (2, 10, 4), (2, 0, 3), (-1, 10, 11))
    r = hoover(ms, gt, tolerance=0.51)
    assert counts(r) == (1, 0, 0, 0, 1) and r.replaced == ()
    assert r.instances[0].score == pytest.approx((16 / 31 + 1) / 2)


def test_a_tie_keeps_the_earlier_classification():
    # T = 0.51, as above with 17 pts in MS 1 (GT 10: 32 pts). Correct: (17/32, 1), mean 0.765625;
    # over: (21/32, 21/24) = (0.65625, 0.875), mean 0.765625: an exact tie (binary fractions)
    # -> the correct detection, found first, is kept.
    ms, gt = blocks((1, 10, 17), (2, 10, 4), (2, 0, 3), (-1, 10, 11))
    r = hoover(ms, gt, tolerance=0.51)
    assert counts(r) == (1, 0, 0, 0, 1) and r.replaced == ()
    # over- against under-segmentation, T = 0.8: GT 10 (10 pts) = 8 in MS 1 + 2 in MS 2; MS 1 also
    # holds GT 20 (2 pts). Correct (1, 10): (0.8, 0.8), 0.8; over (10; 1, 2): (10/10, 10/12),
    # 0.9167, replaces it; under (MS 1; 10, 20): (10/12, 10/10), the same mean -> over stays,
    # GT 20 is missed.
    ms, gt = blocks((1, 10, 8), (2, 10, 2), (1, 20, 2))
    r = hoover(ms, gt)
    assert counts(r) == (0, 1, 0, 1, 0)
    assert [(a.kind, b.kind) for a, b in r.replaced] == [("correct", "over")]


def test_under_segmentation_with_a_higher_mean_replaces_an_over_segmentation():
    # T = 0.8. GT 10 (20 pts) = 16 in MS 1 + 4 in MS 2; MS 2 also has 1 GT-unlabelled pt (P = 5);
    # MS 1 also holds all of GT 20 (4 pts), so P_1 = 20.
    # correct (1, 10): (16/20, 16/20) = 0.8; over (10; 1, 2): (20/20, 20/25) = 0.9 replaces it;
    # under (MS 1; 10, 20): (20/24, 20/20) = 0.9167 > 0.9 replaces the over-segmentation whole:
    # MS 2 is left unclassified -> noise.
    ms, gt = blocks((1, 10, 16), (2, 10, 4), (2, 0, 1), (1, 20, 4))
    r = hoover(ms, gt)
    assert counts(r) == (0, 0, 1, 0, 1)
    assert [(a.kind, b.kind) for a, b in r.replaced] == [("correct", "over"), ("over", "under")]
    assert dict(r.ms_class) == {1: "under", 2: "noise"} and dict(r.gt_class) == {10: "under", 20: "under"}


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-1, 4), st.integers(0, 4), st.integers(1, 6)), min_size=1, max_size=12),
       st.sampled_from([0.51, 0.6, 0.8, 1.0]), st.randoms(use_true_random=False))
def test_every_region_ends_in_exactly_one_category_whatever_the_point_order(spec, t, rnd):
    ms, gt = blocks(*spec)
    r = hoover(ms, gt, tolerance=t)
    assert set(r.gt_class) == set(np.unique(gt[gt != 0]).tolist())
    assert set(r.ms_class) == set(np.unique(ms[ms != -1]).tolist())
    for i in r.instances:
        assert {r.gt_class[n] for n in i.gt} == {r.ms_class[m] for m in i.ms} == {i.kind}
        assert i.gt_ratio >= t and i.ms_ratio >= t
    n_gt_in_under = sum(1 for c in r.gt_class.values() if c == "under")
    n_ms_in_over = sum(1 for c in r.ms_class.values() if c == "over")
    assert r.correct + r.over + n_gt_in_under + r.missed == r.n_gt_regions
    assert r.correct + n_ms_in_over + r.under + r.noise == r.n_ms_regions
    perm = np.array(rnd.sample(range(len(ms)), len(ms)))
    assert hoover(ms[perm], gt[perm], tolerance=t).instances == r.instances


def test_bad_parameters_raise_parameter_errors():
    with pytest.raises(ParameterError, match="tolerance"):
        hoover([1, 2], [1, 2], tolerance=0.5)
    with pytest.raises(ParameterError, match="same length"):
        hoover([1, 2], [1, 2, 3])
    with pytest.raises(ParameterError, match="integer"):
        hoover([1.5, 2], [1, 2])


# --- angle metric ----------------------------------------------------------------------------

def box_corner() -> tuple[np.ndarray, np.ndarray]:
    """Three faces of a unit box meeting at the origin (GT 1: x = 0, 2: y = 0, 3: z = 0), on a
    0.05 grid, and a far plane x = 10 (GT 4) parallel to face 1 and adjacent to nothing."""
    c = 0.025 + 0.05 * np.arange(20)
    u, v = (a.ravel() for a in np.meshgrid(c, c))
    z = np.zeros_like(u)
    faces = [np.column_stack(f) for f in ((z, u, v), (u, z, v), (u, v, z), (z + 10, u, v))]
    return np.vstack(faces), np.repeat([1, 2, 3, 4], len(u))


def test_angle_metric_on_a_box_corner_with_one_tilted_normal():
    X, gt = box_corner()
    ms = gt + 100  # every face correctly detected
    t = math.radians(5.0)
    ms_normals = {101: [math.cos(t), 0, math.sin(t)], 102: [0, -1, 0], 103: [0, 0, 2], 104: [1, 0, 0]}
    r = hoover(ms, gt, points=X, ms_normals=ms_normals)
    # adjacent pairs: (1,2), (1,3), (2,3) (GT dihedral 90); the plane 4 is 10 away from all.
    # MS face 1 tilted 5 deg from x towards z: angle to y stays 90 (error 0), to z is 85 (error
    # 5). Errors 0, 5, 0: mean 5/3, population std sqrt(((5/3)^2 * 2 + (10/3)^2) / 3) = sqrt(50/9).
    assert [a.gt for a in r.angle_errors] == [(1, 2), (1, 3), (2, 3)]
    assert [a.gt_angle for a in r.angle_errors] == pytest.approx([90, 90, 90])
    assert [a.error for a in r.angle_errors] == pytest.approx([0, 5, 0], abs=1e-9)
    assert r.angle_mean == pytest.approx(5 / 3) and r.angle_std == pytest.approx(math.sqrt(50 / 9))
    # the same from normals and adjacency given without points
    gt_normals = {1: [1, 0, 0], 2: [0, 1, 0], 3: [0, 0, -1], 4: [1, 0, 0]}
    r2 = hoover(ms, gt, ms_normals=ms_normals, gt_normals=gt_normals, gt_adjacency={(2, 1), (1, 3), (3, 2)})
    assert r2.angle_mean == pytest.approx(r.angle_mean) and len(r2.angle_errors) == 3
    # MS normals computed from the points of the same faces: no error at all
    r3 = hoover(ms, gt, points=X)
    assert r3.angle_mean == pytest.approx(0, abs=1e-9) and len(r3.angle_errors) == 3


def test_angle_metric_is_none_without_points_or_normals_and_skips_missed_regions():
    X, gt = box_corner()
    r = hoover(gt + 100, gt)
    assert r.angle_mean is None and r.angle_std is None and "no points" in r.angle_note
    ms = gt + 100
    ms[gt == 3] = -1  # face 3 missed: only the pair (1, 2) is left
    r = hoover(ms, gt, points=X)
    assert [a.gt for a in r.angle_errors] == [(1, 2)]
    assert adjacent_regions(X, gt) == {(1, 2), (1, 3), (2, 3)}
    assert adjacent_regions(X, gt, distance=0.01) == set()  # the faces' points are 0.035 apart


def test_hoover_average_means_counts_per_scan_and_pools_angles():
    X, gt = box_corner()
    t = math.radians(5.0)
    r1 = hoover(gt + 100, gt, points=X, ms_normals={101: [math.cos(t), 0, math.sin(t)], 102: [0, 1, 0],
                                                      103: [0, 0, 1], 104: [1, 0, 0]})  # 4 correct, errors 0 5 0
    r2 = hoover(*blocks((1, 10, 5), (-1, 10, 5)))  # 1 missed, 1 noise, no angle
    avg = hoover_average([r1, r2])
    assert avg["n_scans"] == 2 and avg["correct"] == 2.0 and avg["missed"] == 0.5 and avg["noise"] == 0.5
    assert avg["angle_pairs"] == 3 and avg["angle_mean"] == pytest.approx(5 / 3)
    assert avg["angle_mean_per_scan"] == pytest.approx(5 / 3)
    with pytest.raises(ParameterError):
        hoover_average([r1, hoover(gt, gt, tolerance=0.9)])


# --- ground metrics, ARI ---------------------------------------------------------------------

def test_ground_metrics_by_hand_and_against_scikit_learn():
    gt = np.array([9, 9, 9, 40, 40, 0, 0, 17])
    pred = np.array([1, 1, 0, 1, 0, 1, 0, 1], dtype=bool)
    # ground = {9, 17}, 0 unlabelled (points 5, 6 ignored). Labelled: 0 1 2 3 4 7.
    # TP: 0 1 7 = 3; FP: 3 = 1; FN: 2 = 1; TN: 4 = 1.
    g = ground_metrics(pred, gt, ground_values={9, 17}, unlabelled_values={0})
    assert (g.tp, g.fp, g.fn, g.tn, g.n_ignored) == (3, 1, 1, 1, 2)
    # precision 3/4, recall 3/4, F1 6/8, IoU 3/5, total error 2/6, type I 1/4, type II 1/2
    assert (g.precision, g.recall, g.f1, g.iou) == (0.75, 0.75, 0.75, 0.6)
    assert (g.total_error, g.type_i, g.type_ii) == (pytest.approx(1 / 3), 0.25, 0.5)
    keep = gt != 0
    truth = np.isin(gt, [9, 17])[keep]
    assert g.precision == precision_score(truth, pred[keep]) and g.recall == recall_score(truth, pred[keep])
    assert g.f1 == pytest.approx(f1_score(truth, pred[keep])) and g.iou == jaccard_score(truth, pred[keep])


def test_ground_metrics_zero_division_follows_scikit_learn_and_is_flagged():
    gt = np.array([1, 1, 2, 2])
    none = np.zeros(4, dtype=bool)
    g = ground_metrics(none, gt, ground_values={1})  # nothing predicted ground: TP = FP = 0
    assert g.precision == 0.0 == precision_score(gt == 1, none, zero_division=0.0)
    assert g.undefined == ("precision",) and g.recall == 0.0 and g.f1 == 0.0
    g = ground_metrics(none, gt, ground_values={1}, zero_division=float("nan"))
    assert math.isnan(g.precision) and g.to_dict()["precision"] is None
    with pytest.raises(ParameterError, match="both ground and unlabelled"):
        ground_metrics(none, gt, ground_values={1}, unlabelled_values={1})


def test_adjusted_rand_ignores_unlabelled_points_only():
    gt = np.array([1, 1, 2, 2, 0, 0])
    ms = np.array([7, 7, 3, 3, 7, 3])  # the same partition on the labelled points, relabelled
    assert adjusted_rand(ms, gt) == 1.0
    assert adjusted_rand(ms, gt, ignore=()) == adjusted_rand_score(gt, ms) < 1.0
    noisy = np.array([7, -1, 3, 3, 9, 9])  # MS noise counts as one more cluster
    assert adjusted_rand(noisy, gt) == adjusted_rand_score(gt[:4], noisy[:4]) < 1.0


# --- ground-truth loading ----------------------------------------------------------------------

def test_load_ground_truth_from_files_and_fields(tmp_path):
    cloud = PointCloud.from_arrays(np.zeros((4, 3)), {"label": np.array([3, 3, 5, 0], np.uint32),
                                                      "col3": np.array([0.0, 1.0, 1.0, 0.0]),
                                                      "intensity": np.array([0.5, 1, 2, 3])})
    np.save(tmp_path / "a.npy", np.array([[1], [2], [3], [4]], np.int32))
    (tmp_path / "a.txt").write_text("1\n2\n3\n4\n")
    assert load_ground_truth(tmp_path / "a.npy", cloud).tolist() == [1, 2, 3, 4]
    assert load_ground_truth(str(tmp_path / "a.txt"), cloud).tolist() == [1, 2, 3, 4]
    assert load_ground_truth("field:label", cloud).tolist() == [3, 3, 5, 0]
    assert load_ground_truth("field:col3", cloud).dtype == np.int64
    with pytest.raises(UnknownFieldError, match="did you mean 'label'"):
        load_ground_truth("field:lable", cloud)
    with pytest.raises(CloudFileError, match="integer labels"):
        load_ground_truth("field:intensity", cloud)
    (tmp_path / "short.txt").write_text("1\n2\n3\n")
    with pytest.raises(CloudFileError, match="3 labels for the 4 points"):
        load_ground_truth(tmp_path / "short.txt", cloud)
    (tmp_path / "bad.txt").write_text("1\n2\nx\n4\n")
    with pytest.raises(CloudFileError, match="line 3: 'x' is not an integer label"):
        load_ground_truth(tmp_path / "bad.txt")
    (tmp_path / "table.txt").write_text("0 0 0 1\n1 1 1 0\n")
    with pytest.raises(CloudFileError, match="line 1 holds 4 values"):
        load_ground_truth(tmp_path / "table.txt")
    with pytest.raises(CloudFileError, match="no such file"):
        load_ground_truth(tmp_path / "absent.npy")


@pytest.mark.parametrize("text, problem", [
    ("1\n12345678901234567890123\n3\n4\n", "line 2: 12345678901234567890123 is beyond the range of a label"),
    ("1\n2\n18446744073709551615\n4\n", "line 3: 18446744073709551615 is beyond the range of a label"),
    ("1\n2\n3\n-9223372036854775809\n", "line 4: -9223372036854775809 is beyond the range of a label"),
])
def test_a_text_label_beyond_int64_is_refused_at_its_line(tmp_path, text, problem):
    """A 23-digit label overflowed (an internal error, exit 1): now the file and the line."""
    (tmp_path / "big.txt").write_text(text)
    with pytest.raises(CloudFileError, match=f"big.txt: {problem}"):
        load_ground_truth(tmp_path / "big.txt")
    (tmp_path / "edge.txt").write_text("-9223372036854775808\n9223372036854775807\n")  # int64's own ends: read
    assert load_ground_truth(tmp_path / "edge.txt").tolist() == [-(2 ** 63), 2 ** 63 - 1]


def test_a_label_beyond_int64_is_never_wrapped_nor_rounded(tmp_path):
    """uint64 2^64-1 became -1 (then an unlabelled value, or another region) without a word; a
    float label of 1e19 became another number: now each is refused with its index."""
    u = np.array([1, 2, 2 ** 64 - 1, 4], np.uint64)
    np.save(tmp_path / "u.npy", u)
    with pytest.raises(CloudFileError, match=r"u.npy: labels\[2\] = 18446744073709551615 is beyond the range"):
        load_ground_truth(tmp_path / "u.npy")
    np.save(tmp_path / "f.npy", np.array([1.0, 1e19, 3.0]))
    with pytest.raises(CloudFileError, match=r"f.npy: labels\[1\] = 1e\+19 is beyond the range"):
        load_ground_truth(tmp_path / "f.npy")
    cloud = PointCloud.from_arrays(np.zeros((4, 3)), {"label": u}, path="c.pcd")
    with pytest.raises(CloudFileError, match=r"c.pcd: field 'label'\[2\] = 18446744073709551615 .* \(point 2\)"):
        load_ground_truth("field:label", cloud)
    fine = np.array([0, 2 ** 63 - 1], np.uint64)  # uint64 labels within int64 read unchanged
    np.save(tmp_path / "ok.npy", fine)
    assert load_ground_truth(tmp_path / "ok.npy").tolist() == [0, 2 ** 63 - 1]


def test_eval_refuses_labels_beyond_int64_with_exit_3(tmp_path, capsys):
    n = 300
    xyz = np.random.default_rng(0).normal(size=(n, 3))
    write_ply(tmp_path / "r.ply", xyz, {"cluster": np.zeros(n, np.int32)})
    (tmp_path / "gt.txt").write_text("0\n" * 10 + "12345678901234567890123\n" + "0\n" * (n - 11))
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "r.ply"), str(tmp_path / "gt.txt")]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "gt.txt: line 11: 12345678901234567890123 is beyond the range of a label" in err
    assert main(["eval", str(tmp_path / "r.ply"), str(tmp_path / "gt.txt"), "--unlabelled-values",
                 "18446744073709551615"]) == 2
    assert "18446744073709551615 is beyond the range of a label" in capsys.readouterr().err


# --- the command -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rocks_result(tmp_path_factory):
    """The rocks scene (0 ground, 1..3 rocks) segmented by `kbs run --rules outdoor`."""
    tmp = tmp_path_factory.mktemp("eval")
    X, truth = ground_and_rocks()
    write_ply(tmp / "rocks.ply", X, {"truth": truth.astype(np.int32)})
    np.save(tmp / "truth.npy", truth.astype(np.int32))
    r = kbs("run", "--rules", "outdoor", str(tmp / "rocks.ply"), "--out", str(tmp / "out"))
    assert r.returncode == 0, r.stderr
    return tmp, tmp / "out" / "rocks.ply", truth


@pytest.mark.slow
def test_kbs_eval_end_to_end(rocks_result, capsys):
    tmp, ply, truth = rocks_result
    out = tmp / "eval.json"
    r = kbs("eval", str(ply), "field:truth", "--ground-values", "0", "--hoover", "--json", str(out))
    assert r.returncode == 0, r.stderr
    assert "correct" in r.stdout and "precision" in r.stdout and "adjusted Rand index" in r.stdout
    doc = json.loads(out.read_text())
    v = PlyData.read(str(ply))["vertex"]
    # the numbers are the library's on the result's own arrays
    g = ground_metrics(np.asarray(v["scalar_label"]) == 0, truth, ground_values={0})
    h = hoover(np.asarray(v["scalar_cluster"]), truth, gt_ignore=(), points=np.column_stack([v["x"], v["y"], v["z"]]))
    assert doc["ground"]["f1"] == g.f1 > 0.95 and doc["ground"]["tp"] == g.tp
    assert [doc["hoover"][k] for k in ("correct", "over", "under", "missed", "noise")] == list(counts(h))
    assert h.correct + h.over >= 3  # the ground and most rocks are found
    # the same from a label file, without the Hoover part (in process: the same entry point)
    assert main(["eval", str(ply), str(tmp / "truth.npy"), "--ground-values", "0", "--no-hoover"]) == 0
    stdout = capsys.readouterr().out
    assert "Hoover" not in stdout and f"{g.f1:.4f}" in stdout


@pytest.mark.slow
def test_a_ground_evaluation_prints_the_ground_table_not_hoover_by_default(rocks_result):
    """--ground-values asks for the ground metrics: their table alone (Hoover's regions table came
    first and took the screen); without --ground-values Hoover is still the default."""
    tmp, ply, truth = rocks_result
    r = kbs("eval", str(ply), "field:truth", "--ground-values", "0", "--json", str(tmp / "g.json"))
    assert r.returncode == 0, r.stderr
    assert "precision" in r.stdout and "F1" in r.stdout and "Hoover et al." not in r.stdout
    assert "Hoover regions: not computed for a ground evaluation (--hoover computes them)" in r.stdout
    assert json.loads((tmp / "g.json").read_text())["hoover"] is None
    r = kbs("eval", str(ply), "field:truth")
    assert r.returncode == 0 and "Hoover et al." in r.stdout and "ground: not computed" in r.stdout


@pytest.mark.slow
def test_kbs_eval_tolerances_print_the_table_1_rows_of_a_result(rocks_result, capsys):
    tmp, ply, truth = rocks_result
    out = tmp / "eval_t.json"
    assert main(["eval", str(ply), "field:truth", "--tolerances", "0.6,0.95", "--json", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "Table 1" in stdout
    v = PlyData.read(str(ply))["vertex"]
    X = np.column_stack([v["x"], v["y"], v["z"]])
    table = json.loads(out.read_text())["table"]
    assert [t["tolerance"] for t in table] == [0.6, 0.95]
    for t in table:  # each row is the library's classification at that T, printed and in the JSON
        h = hoover(np.asarray(v["scalar_cluster"]), truth, tolerance=t["tolerance"], gt_ignore=(), points=X)
        assert [t[k] for k in ("correct", "over", "under", "missed", "noise")] == list(counts(h))
        assert f"{t['tolerance']:>5.2f} {h.correct:>7} {h.over:>5} {h.under:>6} {h.missed:>7} {h.noise:>6}" in stdout
    # without --tolerances a result's evaluation prints no table (unchanged)
    assert main(["eval", str(ply), "field:truth"]) == 0
    assert "Table 1" not in capsys.readouterr().out


def test_kbs_eval_bad_inputs_exit_codes(rocks_result, tmp_path, capsys):
    _, ply, truth = rocks_result
    np.save(tmp_path / "short.npy", truth[:-1])
    cases = [  # (arguments, exit code, text in the message)
        ([str(tmp_path / "absent.ply"), "field:truth"], 3, "no such file"),
        ([str(ply), str(tmp_path / "absent.npy")], 3, "absent.npy: no such file"),
        ([str(ply), str(tmp_path / "short.npy")], 3, f"{len(truth) - 1:,} labels for the {len(truth):,} points"),
        ([str(ply), "field:truht"], 2, "did you mean 'truth'"),
        ([str(ply), "field:truth", "--ground-values", "0", "--ground-label", "grund"], 2, "did you mean 'ground'"),
        ([str(ply), "field:truth", "--tolerance", "0.5"], 2, "(0.5, 1]"),
        ([str(ply), "field:truth", "--ground-values", "a,b"], 2, "integers separated by commas"),
    ]
    for args, code, text in cases:
        assert main(["eval", *args]) == code, args
        err = capsys.readouterr().err
        assert text in err and "Traceback" not in err, (args, err)
        if code == 3:
            assert err.startswith("kbs: error: ") and err.count("\n") == 1
    r = kbs("eval", str(tmp_path / "absent.ply"), "field:truth")  # the real command, too
    assert r.returncode == 3 and r.stderr.startswith("kbs: error: ") and r.stderr.count("\n") == 1


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_kbs_eval_on_semantickitti(shared_data, tmp_path, capsys):
    scan = shared_data / "semantickitti" / "000001.points.npy"
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    labels = shared_data / "semantickitti" / "000001.labels.npy"
    assert main(["eval", str(tmp_path / "000001.points.ply"), str(labels), "--ground-values", "9,10,11,12,17",
                 "--unlabelled-values", "0", "--json", str(tmp_path / "e.json")]) == 0
    assert "F1" in capsys.readouterr().out
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["ground"]["n_ignored"] == int((np.load(shared_data / "semantickitti" / "000001.labels.npy") == 0).sum())
    assert doc["ground"]["f1"] > 0.92 and doc["ground"]["precision"] > 0.9 and doc["ground"]["recall"] > 0.9


@pytest.mark.slow
def test_a_ground_truth_with_no_labelled_point_is_an_input_error(rocks_result):
    """Every label of GROUND_TRUTH an unlabelled value: every metric was printed as 0 ("undefined")
    and the ARI as nan, with exit code 0; now one line naming the file, exit code 3, no JSON."""
    tmp, ply, truth = rocks_result
    np.save(tmp / "none.npy", np.full(truth.size, 7, dtype=np.int32))
    r = kbs("eval", str(ply), str(tmp / "none.npy"), "--unlabelled-values", "7", "--ground-values", "0",
            "--json", str(tmp / "none.json"))
    assert r.returncode == 3, r.stderr
    assert r.stderr.strip() == (f"kbs: error: {tmp / 'none.npy'}: no point is labelled: all {truth.size:,} labels are "
                                "unlabelled values (7), nothing to compare")
    assert not (tmp / "none.json").exists()
