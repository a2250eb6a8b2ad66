"""post.merge_coplanar's ``absorb``: clusters of other labels lying in the plane of a cluster of
the step's label take that label and join its output cluster (the pieces of a wall that objects
in front of it cut off); nothing else moves."""
from __future__ import annotations

import numpy as np
import pytest

from kbs.knowledge import Segmenter
from kbs.knowledge.rulebase import RuleFileError, parse_rule_base
from kbs.knowledge import PredicateRegistry

RULES = """\
kbs_rules: 1
name: absorb
units: m
strategy: divisive
scene:
  sensor: [0, 0, 5]
  ground:
    normal: [0, 0, 1]
checks:
  planar: {predicate: thickness, max: 0.05}
  level: {predicate: ground_angle, max: 22.5}
  large: {predicate: point_count, min: 1000}
rules:
  - {name: PAh, if: not planar, then: split}
labels:
  - {name: big, if: [planar, level, large]}
  - {name: small}
"""
POST = """post:
  - merge_coplanar: {label: big, absorb: [small], max_angle: 10, max_offset: 0.15}
"""


def patches(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """0: a large level patch on z = 0; 1: a small patch on the same plane, 6 m away (must be
    absorbed); 2: a small patch 0.5 m above that plane (parallel, offset: must not be); 3 and 4:
    two small patches on the plane z = 1.5, coplanar with each other but with no large patch
    (must stay small)."""
    rng = np.random.default_rng(seed)

    def patch(n, x, y, z):
        return np.c_[rng.uniform(*x, n), rng.uniform(*y, n), z + rng.normal(0, 0.005, n)]

    parts = [patch(4000, (-10, -2), (-5, 5), 0.0), patch(400, (4, 7), (-1.5, 1.5), 0.0),
             patch(400, (-3, 0), (8, 11), 0.5), patch(400, (12, 15), (8, 11), 1.5),
             patch(400, (18, 21), (8, 11), 1.5)]
    return np.vstack(parts), np.repeat(np.arange(len(parts)), [len(p) for p in parts])


def _run(text: str):
    X, part = patches()
    res = Segmenter(parse_rule_base(text, "absorb.yaml", PredicateRegistry.default()), jobs=1).segment(X)
    names = list(res.label_names)
    return part, np.array(names)[res.label], res


def test_a_small_patch_in_the_plane_of_a_large_one_takes_its_label_and_joins_it():
    part, before, _ = _run(RULES)
    # without the step the labels follow the sizes: the small patches are 'small'
    assert (before[part == 0] == "big").all() and (before[part != 0] == "small").all()
    part, label, res = _run(RULES + POST)
    assert (label[part == 0] == "big").all()
    assert (label[part == 1] == "big").all(), "the small patch on the large one's plane was not absorbed"
    assert (label[part == 2] == "small").all(), "a parallel patch 0.5 m off the plane was absorbed"
    assert (label[part >= 3] == "small").all(), "patches coplanar only with each other were absorbed"
    # the absorbed patch is in the large patch's output cluster
    assert set(np.unique(res.cluster[part == 1])) <= set(np.unique(res.cluster[part == 0]))
    # and the output clusters the other patches fell in hold none of the large patch's points
    assert not set(np.unique(res.cluster[part >= 2])) & set(np.unique(res.cluster[part == 0]))
    # the explanation says which step moved which cluster
    moved = [r for r in res.explanation.records.values() if r.relabel and r.relabel.get("rule") == "merge_coplanar"]
    assert moved and all(r.relabel["from"] == "small" and r.relabel["to"] == "big" and r.label == "big" for r in moved)
    assert sum(r.n_points for r in moved) == int((part == 1).sum())
    # and in which cluster's plane it lies: a cluster of the label, within the step's bounds
    big = {r.id for r in res.explanation.records.values() if r.label == "big" and not r.relabel and not r.children}
    for r in moved:
        j = r.relabel["joined"]
        assert j["cluster"] in big and j["angle"] <= 10 and j["offset"] <= 0.15 and j["unit"] == "m"
        assert (f"relabelled big by merge_coplanar [absorb.yaml:19]: in the plane of {j['cluster']} (normals "
                in res.explanation.line(r)), res.explanation.line(r)
        assert "m off the other's plane <= 0.15 m)" in res.explanation.line(r)


def test_absorb_names_only_labels_of_the_rule_base():
    with pytest.raises(RuleFileError) as e:
        parse_rule_base(RULES + POST.replace("absorb: [small]", "absorb: [smal]"), "absorb.yaml",
                        PredicateRegistry.default())
    assert "absorb.yaml:19:43: unknown label 'smal'" in str(e.value)  # line and column of the name


def test_a_cluster_an_earlier_step_grouped_is_not_absorbed():
    """An earlier merge_coplanar groups the small patches of the plane z = 1.5 (3 and 4) and, with a
    wide offset, the small patch on the large one's plane (1) with nothing; a later absorbing
    step must not give one member of a group another label than its group-mates: the grouped
    patches keep theirs, the ungrouped one is absorbed as before."""
    grouping = """post:
  - merge_coplanar: {label: small, max_angle: 10, max_offset: 0.15}
  - merge_coplanar: {label: big, absorb: [small], max_angle: 10, max_offset: 0.15}
"""
    X, part = patches()
    # a sixth patch: small, on the large one's plane like patch 1, and coplanar with patch 1
    rng = np.random.default_rng(1)
    extra = np.c_[rng.uniform(12, 15, 400), rng.uniform(-1.5, 1.5, 400), rng.normal(0, 0.005, 400)]
    X, part = np.vstack([X, extra]), np.r_[part, np.full(400, 5)]
    res = Segmenter(parse_rule_base(RULES + grouping, "absorb.yaml", PredicateRegistry.default()), jobs=1).segment(X)
    label = np.array(res.label_names)[res.label]
    # 1 and 5 lie on the large patch's plane, but the first step grouped them: both stay small,
    # and every output cluster holds one label
    assert (label[part == 1] == "small").all() and (label[part == 5] == "small").all()
    assert (label[part == 0] == "big").all()
    for c in np.unique(res.cluster[res.cluster >= 0]):
        assert len(set(label[res.cluster == c])) == 1
