"""The knowledge module as a library: rule files, predicates and their registry, the interpreter,
the explanation tree."""
from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator

from kbs.knowledge import (
    Cluster,
    Explanation,
    Ground,
    Interpreter,
    PredicateError,
    PredicateRegistry,
    RuleFileError,
    Scene,
    load_rule_base,
    predicate,
    shipped_rule_bases,
)
from kbs.knowledge.explain import limit_lines
from kbs.knowledge.rulebase import parse_rule_base, schema
from scenes import anisotropic_blobs, box_on_table, ground_and_rocks, ground_with_small_obstacles

ROOT = Path(__file__).resolve().parents[1]


# --- rule files --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["outdoor", "planar_contest", "airborne"])
def test_shipped_rule_bases_load_and_declare_their_schema(name):
    assert name in shipped_rule_bases()
    rb = load_rule_base(name)
    text = (ROOT / "rules" / f"{name}.yaml").read_text()
    assert text.startswith("# yaml-language-server: $schema=rule-base.schema.json")
    assert not list(Draft202012Validator(schema()).iter_errors(yaml.safe_load(text)))
    assert rb.units == "m"


def test_outdoor_rules_say_what_the_paper_says():
    rb = load_rule_base("outdoor")
    assert rb.checks["planar"].predicate.name == "thickness" and rb.checks["planar"].max == 0.05
    assert rb.checks["level"].predicate.name == "ground_angle" and rb.checks["level"].max == 22.5  # pi/8
    assert {r.name: r.action for r in rb.rules} == {"noise": "reject", "CAh": "split_components", "SAh": "split"}
    assert rb.label_names == ["ground", "obstacle"]
    assert rb.merge is not None and rb.merge.label == "ground"
    assert rb.ground.normal is None and rb.ground.candidate == "planar"


def test_contest_rules_are_pah_alone_at_one_centimetre_without_merge():
    rb = load_rule_base("planar_contest")
    assert rb.checks["planar"].max == 0.01 and rb.units == "m"
    assert [r.action for r in rb.rules if r.name == "PAh"] == ["split"]
    assert rb.merge is None


def _rb(text: str, registry=None):
    return parse_rule_base(textwrap.dedent(text), "t.yaml", registry or PredicateRegistry.default())


MINIMAL = """\
kbs_rules: 1
name: t
units: m
strategy: divisive
checks:
  planar: {predicate: thickness, max: 0.05}
rules:
  - {name: PAh, if: not planar, then: split}
labels:
  - {name: plane}
"""


def test_minimal_rule_file_is_valid():
    rb = _rb(MINIMAL)
    assert rb.engine["k_max"] == 10 and rb.limits["max_depth"] == 8  # documented defaults


@pytest.mark.parametrize(
    "change, expected",
    [
        (("strategy: divisive", "strategy: divisve"), "t.yaml:4:11: strategy must be one of global, divisive; got 'divisve' (did you mean 'divisive'?)"),
        (("predicate: thickness", "predicate: thicknes"), "t.yaml:6:23: unknown predicate 'thicknes' (did you mean 'thickness'?)"),
        (("max: 0.05", "max: -1"), "t.yaml:6:39: threshold max = -1 is outside what 'thickness' can measure [0, inf] (length)"),
        (("max: 0.05", "max: fast"), "t.yaml:6:39: checks.planar.max must be a number; got 'fast'"),
        (("if: not planar", "if: not planr"), "t.yaml:8:21: unknown check 'planr' (did you mean 'planar'?)"),
        (("units: m", "units: m\nunit: m"), "t.yaml:4:1: unknown key 'unit' in the rule base (did you mean 'units'?)"),
        (("then: split", "then: split_components"), "split_components needs a failed connexity check"),
        (("kbs_rules: 1", "kbs_rules: 2"), "t.yaml:1:12: kbs_rules must be 1; got 2"),
        (("name: t\n", ""), "t.yaml:1:1: the rule base is missing the required key 'name'"),
    ],
)
def test_each_problem_has_a_position_and_a_message(change, expected):
    with pytest.raises(RuleFileError) as info:
        _rb(MINIMAL.replace(*change))
    assert expected in str(info.value)


def test_all_problems_are_reported_at_once_with_the_source_line_and_a_caret():
    text = MINIMAL.replace("divisive", "divisve").replace("thickness", "thicknes")
    with pytest.raises(RuleFileError) as info:
        _rb(text)
    assert len(info.value.problems) == 2
    out = str(info.value).splitlines()
    i = next(k for k, ln in enumerate(out) if ln.startswith("t.yaml:6:23:"))
    assert out[i + 1] == "      planar: {predicate: thicknes, max: 0.05}"
    assert out[i + 2].index("^") == out[i + 1].index("thicknes")


def test_yaml_syntax_error_is_positioned():
    with pytest.raises(RuleFileError) as info:
        _rb(MINIMAL.replace("  planar: {predicate: thickness, max: 0.05}", "  planar: {predicate: thickness, max: 0.05"))
    assert str(info.value.problems[0].pos).startswith("t.yaml:7:") and "YAML syntax" in str(info.value)


def test_duplicate_keys_are_errors():
    with pytest.raises(RuleFileError, match="duplicate key 'strategy'"):
        _rb(MINIMAL + "strategy: global\n")


def test_unknown_rule_base_name_suggests_a_shipped_one():
    with pytest.raises(RuleFileError, match="did you mean 'outdoor'"):
        load_rule_base("outdor")


# --- predicates ------------------------------------------------------------------------------------


def _cluster(X) -> Cluster:
    return Cluster("c0", np.asarray(X, float), np.ones(len(X)))


def _scene() -> Scene:
    return Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m")


def test_builtin_predicates_measure_what_they_say():
    reg = PredicateRegistry.default()
    rng = np.random.default_rng(0)
    n = 4000
    plane = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1, 1, n), rng.normal(0, 0.02, n)])
    tilt = np.radians(30)
    R = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    cl = _cluster(plane @ R.T + [0, 0, 1.0])
    sc = _scene()

    def m(name, **params):
        return reg.get(name).measure(cl, sc, params).value

    assert m("thickness") == pytest.approx(0.02, rel=0.05)
    assert m("ground_angle") == pytest.approx(30.0, abs=0.5)
    assert m("point_count") == n
    assert m("extent", axis="largest") == pytest.approx(4.0, rel=0.02)
    assert m("flatness") == pytest.approx(0.02 / (2 / np.sqrt(12)), rel=0.1)  # mu2: 2 m wide
    assert m("height_above_ground", stat="max") == pytest.approx(1.0 + np.sin(tilt) * 1.0, abs=0.06)
    h = cl.X[:, 2]  # the ground is z = 0: heights are z
    for stat, q in (("p90", 90), ("median", 50), ("p10", 10)):
        assert m("height_above_ground", stat=stat) == np.percentile(h, q)
    assert m("height_above_ground", stat="p10") < m("height_above_ground", stat="median") < \
        m("height_above_ground", stat="p90")
    assert m("distance_to_sensor") == pytest.approx(1.0, abs=0.05)
    assert m("connexity") == 1
    X, labels = ground_and_rocks()
    rocks = _cluster(X[labels > 0])
    assert reg.get("connexity").measure(rocks, sc, {}).value == 3


def test_a_predicate_is_checked_when_it_registers():
    def nodoc(cluster, scene):
        return 1.0

    with pytest.raises(PredicateError, match="docstring"):
        predicate(unit="ratio")(nodoc)
    def documented(cluster, scene):
        """doc"""

    with pytest.raises(PredicateError, match="unknown unit"):
        predicate(unit="furlongs")(documented)
    with pytest.raises(PredicateError, match="must be an identifier"):
        predicate(name="two words", unit="count")(documented)

    def positional(cluster, scene, k=3):
        """doc"""

    with pytest.raises(PredicateError, match="keyword-only"):
        predicate(unit="count")(positional)

    def nodefault(cluster, scene, *, k):
        """doc"""

    with pytest.raises(PredicateError, match="needs a default"):
        predicate(unit="count")(nodefault)

    def bad_default(cluster, scene, *, k: float = 5.0):
        """doc"""

    with pytest.raises(PredicateError, match="default of parameter 'k' must be in"):
        predicate(unit="count", bounds={"k": (0.0, 1.0)})(bad_default)

    def two_ways(cluster, scene, *, way: str = "a", width: float = 1.0):
        """doc"""

    with pytest.raises(PredicateError, match="not one of the declared choices"):
        predicate(unit="count", choices={"way": ("a", "b")}, applies_with={"width": ("way", "c")})(two_ways)
    with pytest.raises(PredicateError, match="not one of the declared choices"):
        predicate(unit="count", applies_with={"width": ("way", "b")})(two_ways)
    with pytest.raises(PredicateError, match="unknown parameters \\['depth'\\]"):
        predicate(unit="count", choices={"way": ("a", "b")}, applies_with={"depth": ("way", "b")})(two_ways)
    ok = predicate(unit="count", choices={"way": ("a", "b")}, applies_with={"width": ("way", "b")})(two_ways)
    assert ok.params["width"].check_with({"way": "b"}, ok.params) is None
    assert ok.params["width"].check_with({}, ok.params) == "parameter 'width' applies only with way: b (here way is 'a')"


def test_registry_refuses_a_clash_and_suggests_names():
    reg = PredicateRegistry.default(entry_points_too=False)

    @predicate(name="thickness", unit="length")
    def other(cluster, scene):
        """Another thickness."""
        return 0.0

    with pytest.raises(PredicateError, match="clashes"):
        reg.add(other)
    assert reg.suggest("conexity") == "connexity"


def test_plugin_file_and_entry_points_add_predicates(tmp_path, monkeypatch):
    reg = PredicateRegistry.default(entry_points_too=False)
    assert reg.add_plugin_file(ROOT / "examples" / "plugins" / "elongation.py") == 2
    assert "elongation" in reg and reg.get("elongation").unit == "ratio"
    # an installed package advertising predicates through the entry-point group
    pkg = tmp_path / "kbs_fake_plugin"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        from kbs.knowledge import predicate
        @predicate(unit="points")
        def double_count(cluster, scene):
            """Twice the point count."""
            return 2.0 * cluster.n_points
    '''))
    dist = tmp_path / "kbs_fake_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: kbs-fake-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[kbs.predicates]\nfake = kbs_fake_plugin\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    reg2 = PredicateRegistry.default()
    assert "double_count" in reg2
    assert reg2.get("double_count").measure(_cluster(np.zeros((5, 3))), _scene(), {}).value == 10.0


def test_broken_plugin_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from kbs.knowledge import predicate\n@predicate(unit='count')\ndef f(cluster, scene):\n    return 1\n")
    with pytest.raises(PredicateError, match=r"bad\.py: predicate 'f'.*docstring"):
        PredicateRegistry.default().add_plugin_file(bad)
    with pytest.raises(PredicateError, match="not found"):
        PredicateRegistry.default().add_plugin_file(tmp_path / "nope.py")


# --- the interpreter -------------------------------------------------------------------------------


def _descendants_partition_parents(expl: Explanation) -> None:
    for rec in expl.records.values():
        if rec.children and rec.action != "partition":
            assert sum(expl[c].n_points for c in rec.children) == rec.n_points, rec.id
    root = expl[expl.root]
    assert sum(expl[c].n_points for c in root.children) == root.n_points


def test_rocks_gathered_by_ufp_onc_are_split_by_cah():
    X, labels = ground_and_rocks()
    seg = Interpreter(load_rule_base("outdoor")).run(X)
    expl = seg.explanation
    cah = [r for r in expl.records.values() if r.rule == "CAh"]
    assert len(cah) == 1 and cah[0].action == "split_components" and len(cah[0].children) == 3
    conn = [c for c in cah[0].checks if c.predicate == "connexity"][0]
    assert conn.value == 3 and not conn.passed
    assert "split in 3 components by CAh [outdoor.yaml:" in expl.line(cah[0])
    assert "not connected (connexity = 3 > 1)" in expl.line(cah[0])
    for rock in (1, 2, 3):  # each rock is one obstacle cluster
        got = seg.cluster[labels == rock]
        assert np.bincount(got[got >= 0]).max() / got.size > 0.8
        assert (seg.label[labels == rock] == seg.label_names.index("obstacle")).mean() > 0.8
    _descendants_partition_parents(expl)


def test_ground_swallowing_small_obstacles_is_split_by_sah():
    X, labels = ground_with_small_obstacles()
    rb = load_rule_base("outdoor")
    rb1 = parse_rule_base(rb.text.replace("initial_k: first_apd_max", "initial_k: 1"), "outdoor.yaml",
                          PredicateRegistry.default())
    seg = Interpreter(rb1).run(X)
    first = seg.explanation["c0"]
    assert first.n_points == len(X) and first.rule == "SAh" and first.action == "split"
    by = {c.check: c for c in first.checks}
    assert not by["planar"].passed and by["level"].passed and by["sheet"].passed
    assert first.apd is not None and len(first.children) == first.apd.chosen
    ground = seg.label == seg.label_names.index("ground")
    assert (ground[labels == 0]).mean() > 0.95 and (~ground[labels == 1]).mean() > 0.8


def test_contest_rules_split_a_box_on_a_table_into_its_faces():
    X, faces = box_on_table()
    seg = Interpreter(load_rule_base("planar_contest")).run(X)
    assert (seg.cluster >= 0).all()
    # each region lies on one face: the face of its majority, 98 % of the points over all regions
    owner = {c: np.bincount(faces[seg.cluster == c], minlength=4).argmax() for c in np.unique(seg.cluster)}
    on_own_face = np.array([owner[c] for c in seg.cluster]) == faces
    assert on_own_face.mean() > 0.98
    for f in range(4):  # and every face, box faces included, is made of regions of its own (the
        # edges between faces may go to a sliver region that PAh at 1 cm cannot tell apart)
        assert on_own_face[faces == f].mean() > 0.9, f
    assert len({owner[c] for c in owner}) == 4
    for c in seg.clusters:
        assert c["descriptors"]["thickness"] <= 0.01


def test_the_global_strategy_stops_at_the_first_k_whose_clusters_all_pass():
    """The box on a table: at APD's first local maximum every face is already planar, so the global
    strategy judges that one K and keeps it (tests/test_global.py has a scene where it must go on)."""
    X, faces = box_on_table()
    rb = load_rule_base("planar_contest")
    rbg = parse_rule_base(rb.text.replace("strategy: divisive", "strategy: global"), "g.yaml",
                          PredicateRegistry.default())
    seg = Interpreter(rbg).run(X)
    root = seg.explanation["c"]
    (step,) = seg.explanation.sweep
    assert root.action == "partition" and step["kept"] and step["k"] == root.apd.chosen == len(root.children)
    assert all(seg.explanation[c].action == "accept" for c in root.children)
    assert max(root.apd.ks) == step["k"] + 1  # the sweep went one K further, to see APD's maximum, and came back


def test_the_global_strategy_says_k_max_stopped_it():
    X, _ = box_on_table()
    rb = load_rule_base("planar_contest")
    text = rb.text.replace("strategy: divisive", "strategy: global").replace("k_max: 10", "k_max: 2")
    seg = Interpreter(parse_rule_base(text, "g.yaml", PredicateRegistry.default())).run(X)
    stopped = [r for r in seg.explanation.records.values() if r.action == "limit"]
    assert stopped and all(r.limit == {"kind": "k_max", "setting": "engine.k_max", "value": 2} for r in stopped)
    (line,) = limit_lines(seg.summary()["limits_by_kind"], "g.yaml")
    assert line.startswith("limits: k_max (2) stopped ") and line.endswith("raise engine.k_max in g.yaml, or use "
                                                                            "strategy: divisive")


def test_limits_are_recorded_not_silent():
    X, _ = ground_and_rocks()
    rb = load_rule_base("outdoor")
    tight = parse_rule_base(re.sub(r"max_depth: \d+", "max_depth: 1", rb.text), "o.yaml", PredicateRegistry.default())
    seg = Interpreter(tight).run(X)
    limited = [r for r in seg.explanation.records.values() if r.action == "limit"]
    assert limited and all(any("max_depth = 1" in n for n in r.notes) for r in limited)
    assert all(r.limit == {"kind": "max_depth", "setting": "limits.max_depth", "value": 1} for r in limited)
    assert (seg.cluster[np.isin(seg.cluster, [r.output_index for r in limited])] >= 0).all()
    by_kind = seg.summary()["limits_by_kind"]
    assert list(by_kind) == ["max_depth"] and by_kind["max_depth"]["count"] == len(limited) == seg.summary()["limits"]
    assert sorted(by_kind["max_depth"]["clusters"]) == sorted(r.id for r in limited)
    assert by_kind["max_depth"]["points"] == sum(r.n_points for r in limited)
    sizes = [seg.explanation[c].n_points for c in by_kind["max_depth"]["clusters"]]
    assert sizes == sorted(sizes, reverse=True)  # the largest first


def test_limit_lines_say_which_limit_where_and_what_to_change():
    by_kind = {
        "max_depth": {"setting": "limits.max_depth", "value": 12, "count": 2, "points": 300, "clusters": ["c1.0", "c0.2"]},
        "min_points": {"setting": "limits.min_points", "value": 40, "count": 5, "points": 120,
                       "clusters": ["c0.1", "c1.4", "c1.5", "c2.0", "c2.1"]},
        "single_cluster": {"setting": None, "value": None, "count": 1, "points": 80, "clusters": ["c3.1"]},
    }
    assert limit_lines(by_kind, "outdoor.yaml", result="out/scan.json") == [
        "limits: max_depth (12) stopped 2 clusters, 300 points (c1.0, c0.2): raise limits.max_depth in outdoor.yaml "
        "to split them",
        "limits: min_points (40) stopped 5 clusters, 120 points (c0.1, c1.4, c1.5, ...): lower limits.min_points in "
        "outdoor.yaml to split them",
        "not split: the split gave a single cluster for 1 cluster, 80 points (c3.1): kbs explain out/scan.json "
        "--cluster c3.1 says why",
    ]
    assert limit_lines({}, "outdoor.yaml") == []


def _two_tables() -> np.ndarray:
    """Two boxes on two tables 5 m apart: split once into pieces, some split again."""
    return np.vstack([box_on_table(5)[0], box_on_table(6)[0] + [5.0, 0.0, 0.0]])


def _far_away(n_tables: int) -> np.ndarray:
    """What else a file may hold, 100 km away: a flat patch that needs no split (0), or scenes that
    split into many clusters."""
    if not n_tables:
        rng = np.random.default_rng(0)
        return np.column_stack([rng.uniform(0, 1, 2000), rng.uniform(0, 1, 2000), np.zeros(2000)]) + [1e5, 0.0, 0.0]
    return np.vstack([box_on_table(10 + i)[0] + [1e5 + 20.0 * i, 0.0, 0.0] for i in range(n_tables)])


def _subtree(seg, n_points: int) -> list[tuple]:
    """The records under the scene's first-level cluster of ``n_points`` points, ids relative to it."""
    e = seg.explanation
    (top,) = [c for c in e["c"].children if e[c].n_points == n_points]
    return [(r.id[len(top):], r.n_points, r.action, r.rule, r.label, (r.limit or {}).get("kind"),
             [(c.check, c.value) for c in r.checks]) for r in e.walk(top)]


def _contest(cap: int | None = None):
    """The contest rules (no ground plane), the scene's first partition in two; optionally a
    global max_clusters."""
    text = load_rule_base("planar_contest").text.replace("initial_k: first_apd_max", "initial_k: 2")
    text = re.sub(r"\n *max_clusters: \d+", "", text)
    if cap is not None:
        text = text.replace("limits:\n", f"limits:\n  max_clusters: {cap}\n")
    return parse_rule_base(text, "contest.yaml", PredicateRegistry.default())


def test_a_clusters_subtree_depends_on_its_points_alone():
    """Limits are per cluster: the same points A, beside a patch that needs no split or beside
    three scenes that split into many clusters (far away, so that the scene's first partition puts
    them apart from A), get the same subtree: splits, sizes, measured values, labels, limits."""
    A = _two_tables()
    rb = _contest()
    assert rb.limits["max_clusters"] is None
    alone = Interpreter(rb).run(np.vstack([A, _far_away(0)]))
    crowded = Interpreter(rb).run(np.vstack([_far_away(3), A]))
    assert len(crowded.explanation.records) > 2 * len(alone.explanation.records)
    mine = _subtree(alone, len(A))
    assert sum(a == "split" for _, _, a, *_ in mine) >= 2 and max(i.count(".") for i, *_ in mine) >= 2
    assert _subtree(crowded, len(A)) == mine


def test_a_rule_file_with_max_clusters_still_stops_at_it():
    """max_clusters, when a rule file sets it, caps the clusters of the whole file: the same points
    A are cut short when the file holds more (the reason it is no longer in the shipped rules)."""
    A = _two_tables()
    alone = Interpreter(_contest()).run(np.vstack([A, _far_away(0)]))
    cap = len(alone.explanation.leaves())  # just what A beside the patch needs: not reached there
    rb = _contest(cap)
    assert _subtree(Interpreter(rb).run(np.vstack([A, _far_away(0)])), len(A)) == _subtree(alone, len(A))
    crowded = Interpreter(rb).run(np.vstack([_far_away(3), A]))
    mine = _subtree(crowded, len(A))
    assert mine != _subtree(alone, len(A)) and "max_clusters" in [k for *_, k, _ in mine]
    e = crowded.explanation
    assert len(e.leaves()) < cap + rb.engine["k_max"]  # a split under way when the cap is reached may exceed it
    by_kind = crowded.summary()["limits_by_kind"]
    assert by_kind["max_clusters"]["value"] == cap and by_kind["max_clusters"]["setting"] == "limits.max_clusters"
    stopped = [r for r in e.records.values() if r.limit and r.limit["kind"] == "max_clusters"]
    assert stopped and all(f"limit reached: max_clusters = {cap}" in r.notes for r in stopped)


@pytest.mark.slow
def test_explanation_round_trips_through_json():
    X, _ = ground_and_rocks()
    seg = Interpreter(load_rule_base("outdoor")).run(X)
    d = json.loads(json.dumps(seg.explanation.to_dict()))
    back = Explanation.from_dict(d)
    assert back.render() == seg.explanation.render()
    assert back.why("c1") == seg.explanation.why("c1")
    g = seg.explanation.to_networkx()
    assert g.number_of_nodes() == len(seg.explanation.records) and g.number_of_edges() == len(seg.explanation.records) - 1


@settings(max_examples=12, deadline=None)
@given(st.integers(1, 120), st.integers(0, 10**6), st.sampled_from(["blob", "plane", "line", "same"]))
def test_the_interpreter_terminates_and_assigns_every_point(n, seed, shape):
    rng = np.random.default_rng(seed)
    X = {"blob": lambda: rng.normal(size=(n, 3)),
         "plane": lambda: np.column_stack([rng.uniform(-3, 3, (n, 2)), np.zeros(n)]),
         "line": lambda: np.outer(rng.uniform(-3, 3, n), [1.0, 0.5, 0.2]),
         "same": lambda: np.tile([1.0, 2.0, 3.0], (n, 1))}[shape]()
    seg = Interpreter(load_rule_base("outdoor")).run(X)
    assert seg.cluster.shape == (n,) and seg.label.shape == (n,)
    assert ((seg.cluster >= 0) == (seg.label >= 0)).all()
    assert set(np.unique(seg.cluster[seg.cluster >= 0])) == set(range(len(seg.clusters)))
    assert np.isfinite(seg.membership).all()
    _descendants_partition_parents(seg.explanation)


def test_fixed_initial_k_is_honoured_or_its_shortfall_recorded():
    X, _ = ground_and_rocks()
    rb = load_rule_base("outdoor")
    three = parse_rule_base(rb.text.replace("initial_k: first_apd_max", "initial_k: 3"), "o.yaml",
                            PredicateRegistry.default())
    seg = Interpreter(three).run(X)
    root = seg.explanation["c"]
    assert len(root.children) == 3 and root.apd.chosen == 3
    blobs, _ = anisotropic_blobs()  # three blobs: a new prototype dies before K = 9
    text = re.sub(r"k_max: \d+", "k_max: 10", rb.text)  # K = 9 within the sweep, whatever outdoor's k_max
    far = parse_rule_base(text.replace("initial_k: first_apd_max", "initial_k: 9"), "o.yaml",
                          PredicateRegistry.default())
    seg = Interpreter(far).run(blobs)
    assert any(n.startswith("initial_k = 9 could not be reached") for n in seg.explanation.notes)


# --- splits side by side ---------------------------------------------------------------------------


def test_parallel_splits_give_the_same_segmentation_and_explanation():
    """jobs only changes where the UFP-ONC splits run: arrays and explanation are identical."""
    X, _ = ground_with_small_obstacles()
    rb = load_rule_base("outdoor")
    one, two = Interpreter(rb, jobs=1).run(X), Interpreter(rb, jobs=2).run(X)
    assert one.n_splits > 0
    for a in ("cluster", "label", "membership"):
        assert np.array_equal(getattr(one, a), getattr(two, a)), a
    assert one.explanation.render() == two.explanation.render()
    assert one.clusters == two.clusters


def test_a_split_worker_trims_its_heap_after_a_large_split(monkeypatch):
    """After a split of TRIM_AFTER points or more, the worker gives its free heap back before the
    next split (and only then: trimming after every split slows a frame); the result is unchanged."""
    from kbs.knowledge import interpreter as interp_mod

    interp_mod._trim_heap()  # glibc here; a no-op where malloc_trim is missing
    trims = []
    monkeypatch.setattr(interp_mod, "_trim_heap", lambda: trims.append(interp_mod._last_split))
    monkeypatch.setattr(interp_mod, "_last_split", 0)
    monkeypatch.setattr(interp_mod, "TRIM_AFTER", 2000)
    X, _ = ground_with_small_obstacles()
    kwargs = Interpreter(load_rule_base("outdoor"))._ufp_kwargs("first_max")
    small, large = X[:1500], X[:2500]
    first = interp_mod._worker_split_job(small, kwargs)
    interp_mod._worker_split_job(large, kwargs)
    assert trims == []
    again = interp_mod._worker_split_job(small, kwargs)
    assert trims == [2500]
    interp_mod._worker_split_job(small, kwargs)
    assert trims == [2500]
    assert first[0] == again[0] == "ok" and np.array_equal(first[1].memberships, again[1].memberships)


def test_workers_forked_before_the_first_partition_on_large_clouds(monkeypatch):
    """From EARLY_WORKERS points, the split workers are forked when the run starts (they then hold
    the input only, not the first partition's arrays): before any UFP-ONC fit, and the result is
    that of one process."""
    import kbs.knowledge.run as run_mod
    from kbs.knowledge import interpreter as interp_mod

    X, _ = ground_with_small_obstacles()
    rb = load_rule_base("outdoor")
    one = Interpreter(rb, jobs=1).run(X)
    monkeypatch.setattr(run_mod, "EARLY_WORKERS", X.shape[0])
    two = Interpreter(rb, jobs=2)
    seen = []
    fit = interp_mod.Interpreter._ufp_onc
    monkeypatch.setattr(interp_mod.Interpreter, "_ufp_onc",
                        lambda self, *a, **k: (seen.append(self._pool is not None), fit(self, *a, **k))[1])
    with two:
        res = two.run(X)
        assert seen and seen[0], "the workers were forked before the first partition"
        assert len([p for p in two._pool._processes.values() if p.is_alive()]) == 2
    for a in ("cluster", "label", "membership"):
        assert np.array_equal(getattr(one, a), getattr(res, a)), a
    assert one.explanation.render() == res.explanation.render()


def test_the_root_and_the_first_partition_are_freed_before_labelling(monkeypatch):
    """The root node's (n,) arrays, the points a cluster record gathers for the root and the first
    partition's (n, K) memberships are not held to the end of the run (0.5 GB at 10^7 points, one
    copy of the cloud among them): dead when labelling starts, and the result is unchanged."""
    import weakref

    import kbs.knowledge.run as run_mod
    from kbs.knowledge.state import Node
    from kbs.knowledge.strategies.divisive import Divisive

    X, _ = ground_with_small_obstacles()
    rb = load_rule_base("outdoor")
    before = Interpreter(rb, jobs=1).run(X)
    refs: dict[str, weakref.ref] = {}
    root = Node.root.__func__

    def spy_root(cls, n):
        r = root(cls, n)
        i = len(refs)
        refs[f"root {i} idx"], refs[f"root {i} weight"] = weakref.ref(r.idx), weakref.ref(r.weight)
        return r

    monkeypatch.setattr(Node, "root", classmethod(spy_root))
    record = run_mod.RunContext.record

    def spy_record(self, node):
        cl, draft = record(self, node)
        if node.parent is None:
            refs["root cluster"] = weakref.ref(cl)
        return cl, draft

    monkeypatch.setattr(run_mod.RunContext, "record", spy_record)
    partition = Divisive.partition

    def spy_partition(self, run, X):
        res = partition(self, run, X)
        refs["first memberships"] = weakref.ref(res.memberships)
        return res

    monkeypatch.setattr(Divisive, "partition", spy_partition)
    alive_at_labelling: list[str] = []
    finish = run_mod.finish

    def spy_finish(ctx, judged, t0):
        alive_at_labelling.extend(name for name, ref in refs.items() if ref() is not None)
        return finish(ctx, judged, t0)

    monkeypatch.setattr(run_mod, "finish", spy_finish)
    after = Interpreter(rb, jobs=1).run(X)
    assert {"first memberships", "root cluster"} <= set(refs) and len(refs) >= 4
    assert alive_at_labelling == []
    for a in ("cluster", "label", "membership"):
        assert np.array_equal(getattr(before, a), getattr(after, a)), a


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_parallel_splits_on_semantickitti_stop_at_the_same_limits(shared_data):
    """With a rule file that sets max_clusters (the shipped ones do not), the real scan reaches it:
    the same clusters are stopped whatever jobs is."""
    X = np.load(shared_data / "semantickitti" / "000001.points.npy").astype(np.float64)
    text = re.sub(r"\n *max_clusters: \d+", "", load_rule_base("outdoor").text)
    rb = parse_rule_base(re.sub(r"max_depth: \d+", "max_depth: 12\n  max_clusters: 250", text), "o.yaml",
                         PredicateRegistry.default())
    one, two = Interpreter(rb, jobs=1).run(X), Interpreter(rb, jobs=2).run(X)
    limited = [r.id for r in one.explanation.records.values() if any("max_clusters" in n for n in r.notes)]
    assert limited, "the scan reaches max_clusters"
    assert limited == [r.id for r in two.explanation.records.values() if any("max_clusters" in n for n in r.notes)]
    assert np.array_equal(one.cluster, two.cluster) and np.array_equal(one.label, two.label)


@pytest.mark.parametrize("jobs", [0, -2, 1.5, "2"])
def test_jobs_must_be_a_count(jobs):
    with pytest.raises(ValueError, match="jobs must be"):
        Interpreter(load_rule_base("outdoor"), jobs=jobs)


def test_fcm_tol_is_an_engine_setting_the_splits_use(monkeypatch):
    """engine.fcm_tol (fuzzy c-means' stopping threshold, the start of each K's Gath-Geva fit)
    is validated with its position and reaches every UFP-ONC call of a run."""
    import kbs.knowledge.interpreter as interp_mod

    assert _rb(MINIMAL).engine["fcm_tol"] == 1e-3
    with pytest.raises(RuleFileError) as info:
        _rb(MINIMAL + "engine:\n  fcm_tol: 0\n")
    assert "t.yaml:12:12:" in str(info.value) and "fcm_tol" in str(info.value)
    seen = []
    real = interp_mod.ufp_onc

    def spy(X, **kw):
        seen.append(kw["fcm_tol"])
        return real(X, **kw)

    monkeypatch.setattr(interp_mod, "ufp_onc", spy)
    X, _ = ground_and_rocks(seed=0)
    Interpreter(_rb(MINIMAL + "engine:\n  fcm_tol: 0.02\n")).run(X)
    assert len(seen) > 1 and set(seen) == {0.02}
