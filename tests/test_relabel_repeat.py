"""post.relabel's rules with 'passes' that undo none: judged again, pass after pass, on the
clusters still labelled 'from' that no rule relabelled, against the surface rebuilt from the labels
the passes before left (issue 12: the inner patches of a large roof, whose neighbours are roof
patches, judged against the ground left once the outer ones are out)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from kbs.io import write_ply
from kbs.knowledge import Interpreter, RuleFileError
from scenes import airborne_large_roof
from test_cli import kbs
from test_relabel_undo import MODEL, RULES, _parse

INNER = """\
      - name: inner_roofs
        from: ground
        to: object
        if: raised
{passes}"""


def _rules(passes: int | None) -> str:
    return RULES.format(model=MODEL) + INNER.format(passes="" if passes is None else f"        passes: {passes}\n")


def _run(passes: int | None):
    X, labels, core = airborne_large_roof()
    rb = _parse(_rules(passes))
    seg = Interpreter(rb).run(X)
    return seg, seg.label == rb.label_names.index("ground"), labels, core


def test_a_rule_with_passes_takes_the_core_of_a_large_roof():
    """Judged once, the roof's core (its neighbours the roof's outer ring, 0.8 m under it) stays
    ground, while 'roofs' takes the ring (it meets the ground). With passes, 'inner_roofs' judges
    the core again against the surface rebuilt without the ring: it stands 8.8 m above the ground
    left, and is taken in pass 2; the bare earth stays ground."""
    seg, ground, labels, core = _run(None)
    ring = (labels == 1) & ~core
    assert ground[core].all() and not ground[ring].any() and ground[labels == 0].all()
    seg, ground, labels, core = _run(8)
    assert not ground[labels == 1].any() and ground[labels == 0].all()
    recs = [r for r in seg.explanation.records.values() if r.relabel]
    inner = [r for r in recs if r.relabel["rule"] == "inner_roofs"]
    assert inner and all(r.label == "object" and r.first_label == "ground" for r in inner)
    assert sum(r.n_points for r in inner) == core.sum()
    rel = inner[0].relabel
    assert rel["pass"] == 2 and rel["from"] == "ground" and rel["to"] == "object" and rel["checks"] == ["raised"]
    (m,) = rel["measured"]
    assert m["check"] == "raised" and m["passed"] and m["value"] > 8.0  # against the ground left
    first = next(c for c in inner[0].checks if c.check == "raised")
    assert not first.passed and first.value < 1.0  # pass 1: against the ring around it
    # the surface of pass 2: the ground clusters left after pass 1, the core among them
    ground_left = sum(r.n_points for r in seg.explanation.leaves() if r.label == "ground") + inner[0].n_points
    assert rel["surface_points"] == ground_left
    assert seg.explanation.ground.local_model.relabelled == len(recs)
    assert all("pass" not in r.relabel for r in recs if r.relabel["rule"] == "roofs")


def test_one_pass_judges_once():
    """'passes: 1' (the default) judges the rule once, with the others: the labels and records of
    a rule without 'passes'."""
    a, *_ = _run(None)
    b, *_ = _run(1)
    assert np.array_equal(a.label, b.label) and np.array_equal(a.cluster, b.cluster)
    assert all("pass" not in r.relabel for r in b.explanation.records.values() if r.relabel)


@pytest.mark.parametrize("passes, expected", [
    (0, "t.yaml:33:17: post[1].relabel[1].passes: 0 is less than the minimum of 1"),
    (65, "t.yaml:33:17: post[1].relabel[1].passes: 65 is greater than the maximum of 64"),
])
def test_bad_passes_are_positioned(passes, expected):
    with pytest.raises(RuleFileError) as err:
        _parse(_rules(passes))
    assert expected in str(err.value), str(err.value)


@pytest.mark.slow
def test_kbs_run_and_explain_say_which_pass_took_it(tmp_path):
    """Through the commands: the result JSON records the pass, and kbs explain says it, in the
    summary, the tree and the cluster's own account."""
    X, _, _ = airborne_large_roof()
    write_ply(tmp_path / "roof.ply", X)
    (tmp_path / "t.yaml").write_text(_rules(8))
    r = kbs("run", "--rules", str(tmp_path / "t.yaml"), str(tmp_path / "roof.ply"), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "o" / "roof.json").read_text())
    taken = next(c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "inner_roofs")
    assert taken["relabel"]["pass"] == 2 and taken["label"] == "object"
    r = kbs("explain", str(tmp_path / "o" / "roof.json"))
    assert "inner_roofs [t.yaml:29] ground -> object if raised: 1 relabelled (in pass 2)" in r.stdout, r.stdout
    assert (f"relabelled object by inner_roofs [t.yaml:29] in pass 2 (against the surface rebuilt without the "
            "clusters relabelled in the passes before): raised (height_above_local_ground = ") in r.stdout
    r = kbs("explain", str(tmp_path / "o" / "roof.json"), "--cluster", taken["id"])
    assert r.returncode == 0, r.stderr
    assert "inner_roofs [t.yaml:29] ground -> object if raised: does not hold" in r.stdout  # pass 1
    assert "post.relabel, judged again by inner_roofs [t.yaml:29] in pass 2 against the surface rebuilt" in r.stdout
    assert "holds, relabelled object: height_above_local_ground = " in r.stdout


def test_a_later_pass_asks_only_the_clusters_within_reach_of_those_that_moved(monkeypatch):
    """Pass 2 asks again only the ground clusters with a point within the surface's radius (5 m,
    the reach of 'raised') of a cluster whose label changed: the others read the same surface
    points. Asking every cluster gives the same labels and records, with more questions."""
    from kbs.knowledge.post.relabel import Relabel

    asked: list[str] = []
    judge = Relabel._judge

    def counting(rule, lf, scene, ctx, fresh):
        asked.append(lf.id)
        return judge(rule, lf, scene, ctx, fresh)

    monkeypatch.setattr(Relabel, "_judge", staticmethod(counting))
    seg, *_ = _run(8)
    near = list(asked)
    asked.clear()
    monkeypatch.setattr(Relabel, "_near", staticmethod(lambda todo, *a: todo))
    every, *_ = _run(8)
    assert np.array_equal(seg.label, every.label)
    assert seg.explanation.to_dict() == every.explanation.to_dict()
    assert 0 < len(near) < len(asked), (len(near), len(asked))
    # the ones asked are those the ring's points come within 5 m of
    X, labels, core = airborne_large_roof()
    recs = seg.explanation.records
    ring = np.vstack([X[seg.cluster == c["index"]] for c in seg.clusters
                      if any(recs[i].relabel and recs[i].relabel["rule"] == "roofs" for i in c["ids"])])
    from scipy.spatial import cKDTree

    tree = cKDTree(ring[:, :2])
    for c in seg.clusters:
        if c["label"] != "ground" or c["ids"][0] in near:
            continue
        d, _ = tree.query(X[seg.cluster == c["index"], :2])
        assert d.min() > 5.0, (c["ids"], d.min())  # not asked: out of reach


def test_a_predicate_without_a_reach_has_every_cluster_asked_again():
    """A plugin predicate on the surface that does not say its reach: every cluster still labelled
    'from' is asked again (the rule cannot know which the surface's change could move)."""
    from kbs.knowledge import PredicateRegistry, predicate
    from kbs.knowledge.predicates import height_above_local_ground
    from kbs.knowledge.post.relabel import Relabel

    @predicate(unit="length", needs_ground_model=True)
    def height_above_surface_p90(cluster, scene) -> float:
        """What 'raised' measures (the built-in's p90 with exclude_self), without a reach."""
        return height_above_local_ground.func(cluster, scene, stat="p90", exclude_self=True)

    assert height_above_surface_p90.reach is None
    reg = PredicateRegistry.default(entry_points_too=False)
    reg.add(height_above_surface_p90)
    from kbs.knowledge.rulebase import parse_rule_base

    text = _rules(8).replace("raised: {predicate: height_above_local_ground, params: {stat: p90, exclude_self: true}",
                             "raised: {predicate: height_above_surface_p90")
    rb = parse_rule_base(text, "t.yaml", reg)
    names = {"raised"}

    class Ctx:
        rule_base = rb

    assert Relabel._reach(names, Ctx, None) is None
    X, labels, core = airborne_large_roof()
    seg = Interpreter(rb).run(X)
    assert not (seg.label[core] == rb.label_names.index("ground")).any()  # taken in pass 2 all the same
    ref, *_ = _run(8)
    assert np.array_equal(seg.label, ref.label)


def test_the_continuous_surface_checks_ask_no_cluster_again():
    """The airborne gates on plateaus (`drops`, `open_surface`, `vast`) measure the continuous
    surfaces the relabel step found, which its passes do not change: their predicates' reach is 0,
    so `inner_roofs` still asks again only the clusters within the surface's radius (5 m) of those
    that moved, and a rule reading nothing else would ask every cluster (None: not known). On a
    quarry pit (the rim a plateau), asking every cluster gives the same labels and records."""
    from kbs.knowledge import load_rule_base
    from kbs.knowledge.post.relabel import Relabel
    from scenes import airborne_pit

    rb = load_rule_base("airborne")

    class Ctx:
        rule_base = rb

    class Model:
        radius, per_range = 5.0, 0.0

    assert Relabel._reach({"well_raised", "drops", "open_surface", "vast"}, Ctx, Model) == 5.0
    assert Relabel._reach({"drops", "open_surface", "vast"}, Ctx, Model) is None
    # 'edge_drop' with 'beside: ground' (session 39) changes where anything left the surface beside
    # any edge of the cluster's surface, however far: with it, every cluster is asked again
    assert Relabel._reach({"well_raised", "edge_raised"}, Ctx, Model) == 5.0
    assert Relabel._reach({"well_raised", "edge_raised_left"}, Ctx, Model) is None
    X, labels = airborne_pit(depth=8.0)
    X = X - X.mean(axis=0)
    sensor = np.array([0.0, 0.0, X[:, 2].min() - 10.0])
    asked: list[str] = []
    judge = Relabel._judge

    def counting(rule, lf, scene, ctx, fresh):
        asked.append(lf.id)
        return judge(rule, lf, scene, ctx, fresh)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Relabel, "_judge", staticmethod(counting))
        seg = Interpreter(rb, sensor=sensor, jobs=1).run(X)
        near = len(asked)
        asked.clear()
        mp.setattr(Relabel, "_near", staticmethod(lambda todo, *a: todo))
        every = Interpreter(rb, sensor=sensor, jobs=1).run(X)
    assert (seg.label[labels == 0] == rb.label_names.index("ground")).mean() > 0.97
    assert np.array_equal(seg.label, every.label) and np.array_equal(seg.cluster, every.cluster)
    assert seg.explanation.to_dict() == every.explanation.to_dict()
    assert 0 < near < len(asked), (near, len(asked))  # later passes ran, asking fewer
