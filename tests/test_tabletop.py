"""The table as the largest supporting plane under the objects (``scene.ground.choose:
supporting``, examples/rules/tabletop.yaml; issue 12): a large box face near the camera is not the
table, through ``kbs run`` on generated Kinect-like scenes (benchmarks/tabletop_scenes.py); the
count of supported points against a brute-force reference; bad values refused at their position."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import MultiPoint, Point

from kbs.cli.main import main
from kbs.evaluation import ground_metrics
from kbs.io import write_ply
from kbs.knowledge import load_rule_base
from kbs.geometry.groundplane import supported_points
from test_cli import kbs

ROOT = Path(__file__).resolve().parents[1]
TABLETOP = (ROOT / "examples" / "rules" / "tabletop.yaml").read_text(encoding="utf-8")
sys.path.insert(0, str(ROOT / "benchmarks"))
from tabletop_scenes import tabletop_scene  # noqa: E402


def run_scene(tmp_path: Path, seed: int, rules: str = str(ROOT / "examples" / "rules" / "tabletop.yaml")):
    X, lab, _ = tabletop_scene(seed)
    scan = tmp_path / f"table{seed}.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", rules, "-j", "1", str(scan), "--out", str(tmp_path / "out"), "--force")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "out" / f"table{seed}.json").read_text())
    from kbs.io import read_cloud

    out = read_cloud(tmp_path / "out" / f"table{seed}.ply")
    table = doc["label_names"].index("table") if "label_names" in doc else None
    pred = out.fields["scalar_label"].astype(int) == table
    f1 = ground_metrics(pred, np.where(lab == 1, 1, 0), ground_values=(1,)).f1
    return r, doc, X, lab, f1


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 11])
def test_a_large_box_face_is_not_the_table(tmp_path, seed):
    """A large box in the front half of the table: its top face (seed 1: 39,000 points, more than
    the table's 34,000; seed 11: the table's cluster holds objects and fails 'planar', the box top
    passes) was the closest planar candidate and became the table (F1 0.64 / 0.84 before); the
    plane supporting the most points is the table."""
    r, doc, X, lab, f1 = run_scene(tmp_path, seed)
    g = doc["explanation"]["ground"]
    n, p = np.array(g["normal"]), np.array(g["point"])
    on = np.abs((X - p) @ n) < 0.01
    assert (lab[on] == 1).mean() > 0.95, g  # the plane found is the table's
    assert f1 > 0.99, (f1, g)
    cands = [v for v in g["candidates"] if v.get("supported") is not None]
    assert len(cands) >= 2 and g["supported"] == max(v["supported"] for v in cands)
    assert "points standing on it" in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("seed, share", [(4047, 0.4995), (5095, 0.4265)])
def test_a_table_plane_under_half_of_its_cluster_is_a_candidate(tmp_path, seed, share):
    """Fresh generated scenes (session 44): a large box shares the table's cluster (with its sides
    and the objects); the table's robust plane holds under half of that cluster, and with
    ``min_inlier_share: 0.5`` the cluster was no candidate: the box's top, planar and supporting
    nothing, was the only one and became the table (F1 0). With 0.4 the table's plane is a
    candidate and supports the objects: it is the table."""
    r, doc, X, lab, f1 = run_scene(tmp_path, seed)
    g = doc["explanation"]["ground"]
    assert f1 > 0.99, (f1, g)
    chosen = [v for v in g["candidates"] if v["cluster"] == g["cluster"]][0]
    assert chosen["inlier_share"] > 0.9 and g["supported"] > 0  # of the points not above it (share_of)
    of_all = tmp_path / "all.yaml"
    of_all.write_text(_share_of_all(TABLETOP), encoding="utf-8")
    (tmp_path / "all").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "all", seed, str(of_all))
    g = doc["explanation"]["ground"]
    assert f1 > 0.99, (f1, g)
    chosen = [v for v in g["candidates"] if v["cluster"] == g["cluster"]][0]
    assert chosen["inlier_share"] == pytest.approx(share, abs=1e-4) and g["supported"] > 0
    strict = tmp_path / "strict.yaml"
    strict.write_text(_share_of_all(TABLETOP).replace("min_inlier_share: 0.4", "min_inlier_share: 0.5"), encoding="utf-8")
    r, doc, X, lab, f1 = run_scene(tmp_path, seed, str(strict))
    assert f1 < 0.1 and doc["explanation"]["ground"]["supported"] == 0  # the box's top


@pytest.mark.slow
def test_a_planar_table_cluster_gives_its_robust_plane(tmp_path):
    """Fresh generated scene 8027 (session 45): the table's largest piece (15,077 points) passes
    'planar' with a slice of a box's foot in it, which tilts the plane of all its points 4 deg
    from the table's; against that plane the table's other piece stood a few cm up, 'on the
    table', an object (F1 0.70). With ``refit`` the piece gives its robust plane, the table's."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 8027)
    g = doc["explanation"]["ground"]
    assert f1 > 0.98, (f1, g)
    assert g["method"] == "check 'planar'" and g["inliers"] > 4000 and g["inlier_share"] > 0.9, g
    assert "it passes 'planar', its robust plane (" in r.stdout, r.stdout
    n = np.array(g["normal"])
    truth = np.linalg.svd(X[lab == 1] - X[lab == 1].mean(axis=0))[2][2]
    assert np.degrees(np.arccos(min(1.0, abs(float(n @ truth))))) < 0.5  # the table's plane
    off = tmp_path / "off.yaml"
    off.write_text(TABLETOP.replace("refit: true", "refit: false"), encoding="utf-8")
    (tmp_path / "off").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "off", 8027, str(off))
    g = doc["explanation"]["ground"]
    assert 0.5 < f1 < 0.8 and "inliers" not in g, (f1, g)
    assert np.degrees(np.arccos(min(1.0, abs(float(np.array(g["normal"]) @ truth))))) > 3


@pytest.mark.slow
def test_a_plane_cut_through_a_blob_is_no_table(tmp_path):
    """Fresh generated scene 8067 (session 45): a cluster of objects and the table's edge has a
    robust plane whose 7,590 points fill the 1 cm band (spread 5 mm across it, a table's 1-2 mm):
    counted among the points not above it, 82 % held it, and its plane, 3 deg off the table's,
    supported the most points (F1 0.975 against 0.995). ``max_thickness`` 3.5 mm (the Kinect's
    depth noise at 1.5 m) refuses it."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 8067)
    g = doc["explanation"]["ground"]
    assert f1 > 0.99, (f1, g)
    slab = [v for v in g["candidates"] if "a slab through a volume" in (v.get("why") or "")]
    assert len(slab) == 1 and slab[0]["plane_thickness"] > 0.0035 and slab[0]["cluster"] != g["cluster"], g
    loose = tmp_path / "loose.yaml"
    text = "\n".join(line for line in TABLETOP.splitlines() if "max_thickness: 0.0035" not in line)
    assert text != TABLETOP
    loose.write_text(text, encoding="utf-8")
    (tmp_path / "loose").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "loose", 8067, str(loose))
    assert f1 < 0.98 and doc["explanation"]["ground"]["cluster"] == slab[0]["cluster"], f1


def _share_of_all(text: str) -> str:
    """The table-top rules with the robust plane's share counted among all a candidate's points."""
    out = text.replace("share_of: not_above", "share_of: all", 1)
    assert out != text
    return out


@pytest.mark.slow
def test_what_stands_on_the_table_does_not_count_against_its_plane(tmp_path):
    """Fresh generated scene 7039 (session 45): the table's cluster (27,273 points) holds the
    objects and a box standing on it; the table's robust plane holds 39 % of them, under
    ``min_inlier_share: 0.4``, and the box's top, supporting nothing, became the table (F1 0).
    Counted among the points not above the plane (``share_of: not_above``) it holds all of them:
    the cluster is a candidate, and its plane supports the objects."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 7039)
    g = doc["explanation"]["ground"]
    assert f1 > 0.99, (f1, g)
    assert g["share_of"] == "not_above" and g["inlier_share"] == 1.0 and g["supported"] > 0, g
    assert "of its points not above it, " in r.stdout, r.stdout
    n, p = np.array(g["normal"]), np.array(g["point"])
    assert (lab[np.abs((X - p) @ n) < 0.01] == 1).mean() > 0.95  # the plane found is the table's
    out = kbs("explain", str(tmp_path / "out" / "table7039.json"))
    assert out.returncode == 0 and "100% of those not above it on its robust plane" in out.stdout, out.stdout
    of_all = tmp_path / "all.yaml"
    of_all.write_text(_share_of_all(TABLETOP), encoding="utf-8")
    (tmp_path / "all").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "all", 7039, str(of_all))
    g = doc["explanation"]["ground"]
    assert f1 < 0.1 and g["supported"] == 0 and "share_of" not in g  # the box's top
    mine = [v for v in g["candidates"] if v.get("inlier_share") is not None][0]
    assert mine["inlier_share"] == pytest.approx(0.3899, abs=1e-4) and "< 40%" in mine["why"], mine


@pytest.mark.slow
def test_a_table_cut_into_clusters_under_5000_points_is_found(tmp_path):
    """Fresh generated scene 5063 (session 44; 1021 in session 36 was the same kind): the camera
    0.84 m above a small table, whose 8,944 points the first partition cut into clusters of 4,562
    points and fewer; with ``min_points: 5000`` no cluster was a candidate and the fallback normal
    left no table (F1 0). With 4000 (1500 since session 45) the table's largest piece is one and
    gives the table's plane."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 5063)
    g = doc["explanation"]["ground"]
    assert f1 > 0.99, (f1, g)
    assert g["source"].startswith("cluster") and max(v["points"] for v in g["candidates"]) < 5000
    strict = tmp_path / "strict.yaml"
    strict.write_text(TABLETOP.replace("min_points: 1500", "min_points: 5000"), encoding="utf-8")
    r, doc, X, lab, f1 = run_scene(tmp_path, 5063, str(strict))
    assert f1 == 0.0 and doc["explanation"]["ground"]["source"] == "fallback"


@pytest.mark.slow
def test_a_table_a_large_box_hides_is_found(tmp_path):
    """Fresh generated scene 9175 (session 45): a box holds 98 % of the view, the table 1,735 of
    the 76,745 points, a cluster of its own; with ``min_points: 4000`` it was no candidate and the
    box's top, supporting nothing, became the table (F1 0.07). With 1500 the table is one, and
    supports the box."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 9175)
    g = doc["explanation"]["ground"]
    assert f1 > 0.99 and g["supported"] > 0, (f1, g)
    assert 1500 <= [v for v in g["candidates"] if v["cluster"] == g["cluster"]][0]["points"] < 4000
    strict = tmp_path / "strict.yaml"
    strict.write_text(TABLETOP.replace("min_points: 1500", "min_points: 4000"), encoding="utf-8")
    (tmp_path / "strict").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "strict", 9175, str(strict))
    assert f1 < 0.1 and doc["explanation"]["ground"]["supported"] == 0  # the box's top


@pytest.mark.slow
def test_a_table_under_a_refused_box_face_in_its_cluster_is_its_second_plane(tmp_path):
    """Fresh generated scene 6029 (session 45): the table's cluster (33,584 points, the table's
    9,749 among them) holds a larger plane, the face of a box turned to the camera (15,542 points
    within 1 cm), which is its robust plane and is refused (the camera under it: sensor_above);
    the box's top, supporting nothing, was the only candidate left and became the table (F1 0).
    With ``planes: 2`` the cluster's next robust plane, among the points the face does not hold,
    is the table's: it supports the objects and is the ground."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 6029)
    g = doc["explanation"]["ground"]
    assert f1 > 0.98, (f1, g)
    assert g["method"] == "robust plane" and g["plane"] == 2 and g["supported"] > 0, g
    mine = [v for v in g["candidates"] if v["cluster"] == g["cluster"]]
    assert [v.get("plane") for v in mine] == [None, 2], mine
    assert "(sensor_above)" in mine[0]["why"] and mine[1]["points"] == mine[0]["points"] - mine[0]["inliers"]
    n, p = np.array(g["normal"]), np.array(g["point"])
    assert (lab[np.abs((X - p) @ n) < 0.01] == 1).mean() > 0.9  # the plane found is the table's (94.5 %: the feet of objects within 1 cm)
    out = kbs("explain", str(tmp_path / "out" / "table6029.json"))
    assert out.returncode == 0 and f"{g['cluster']}, its robust plane 2 (" in out.stdout, out.stdout
    assert f"candidate {g['cluster']}: robust plane 2, among {mine[1]['points']:,} points" in out.stdout, out.stdout
    one = tmp_path / "one.yaml"
    one.write_text(TABLETOP.replace("planes: 2", "planes: 1"), encoding="utf-8")
    (tmp_path / "one").mkdir()
    r, doc, X, lab, f1 = run_scene(tmp_path / "one", 6029, str(one))
    assert f1 < 0.1 and doc["explanation"]["ground"]["supported"] == 0  # the box's top
    assert [v.get("plane") for v in doc["explanation"]["ground"]["candidates"]] == [None, None]


@pytest.mark.parametrize("old, new, says", [
    ("max_thickness: 0.0035", "max_thickness: 0", "max_thickness"),
    ("refit: true", "refit: yes please", "refit"),
    ("share_of: not_above", "share_of: above", "not_above"),
    *[("planes: 2", f"planes: {value}", "planes") for value in ("0", "2.5", "true", "6")],
])
def test_a_bad_plane_setting_is_refused_at_its_line(tmp_path, capsys, old, new, says):
    """scene.ground.plane's settings of session 45: max_thickness a positive length, refit a
    boolean, share_of all or not_above, planes a count from 1 to 5."""
    text = TABLETOP.replace(old, new, 1)
    assert text != TABLETOP
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    line = text[:text.index(new)].count("\n") + 1
    assert main(["rules", "check", str(rules)]) == 4
    err = capsys.readouterr().err
    assert f"t.yaml:{line}:" in err and says in err and "Traceback" not in err, err


def test_planes_defaults_to_one():
    assert load_rule_base(str(ROOT / "examples" / "rules" / "tabletop.yaml")).ground.plane.planes == 2
    assert load_rule_base("outdoor").ground.plane.planes == 1
    assert load_rule_base("outdoor").ground.plane.share_of == "all"
    assert not load_rule_base("outdoor").ground.plane.refit
    assert load_rule_base("outdoor").ground.plane.max_thickness is None


@pytest.mark.slow
def test_a_table_cluster_holding_a_large_box_is_split(tmp_path):
    """The table's cluster swallowed a large box: not planar, and too blobby for SAh's 'sheet', it
    stayed one cluster, labelled background (1,791 of the table's 11,004 points, F1 0.911 before;
    other scenes lost all their table). Partly at the table's height (10th percentile of its heights
    within 1 cm) yet not planar, it is split ('table_and_object')."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 35)
    assert f1 > 0.99, f1
    split = [c for c in doc["explanation"]["clusters"] if c.get("rule") == "table_and_object"]
    assert split, "the rule split the table's cluster"


@pytest.mark.slow
def test_a_box_cluster_holding_part_of_the_table_is_split(tmp_path):
    """Generated scene 101 (validation part): 2,927 of the table's 14,757 points stayed in one
    cluster with a large box. Its median height is above 1 cm, so the rule as first written
    ('at_table_height' by the median) left it whole, labelled background: table F1 0.887. A tenth
    of its points or more lie on the table plane (its 10th percentile height within 1 cm): split."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 101)
    assert f1 > 0.99, f1
    split = [c for c in doc["explanation"]["clusters"] if c.get("rule") == "table_and_object"]
    assert split, "the rule split the box's cluster"
    median_rules = tmp_path / "median.yaml"
    median_rules.write_text(TABLETOP.replace("params: {stat: p10}", "params: {stat: median}"), encoding="utf-8")
    assert "params: {stat: median}" in median_rules.read_text(encoding="utf-8")
    (tmp_path / "m").mkdir()
    _, _, _, _, f1_median = run_scene(tmp_path / "m", 101, str(median_rules))
    assert f1_median < 0.9, f1_median


@pytest.mark.slow
def test_closest_keeps_the_papers_choice(tmp_path):
    """Without 'choose' (the paper's rule, 'closest'), the same scene takes the box face: the
    choice, not anything else in the rule file, makes the difference."""
    rules = tmp_path / "closest.yaml"
    text = TABLETOP
    start, end = text.index("    choose:"), text.index("    fallback:")
    rules.write_text(text[:start] + text[end:], encoding="utf-8")
    assert load_rule_base(str(rules)).ground.support is None
    _, doc, X, lab, f1 = run_scene(tmp_path, 1, str(rules))
    assert f1 < 0.7


def test_supported_points_match_a_brute_force_count():
    rng = np.random.default_rng(3)
    normal = np.array([0.0, -0.8, -0.6])
    u = np.array([1.0, 0.0, 0.0])
    v = np.cross(normal, u)
    point = np.array([0.1, 0.2, 0.9])
    uv = rng.uniform(-0.4, 0.4, (3000, 2)) * [1.0, 0.6]
    on = point + uv[:, :1] * u + uv[:, 1:] * v
    X = point + rng.uniform(-0.7, 0.7, (5000, 1)) * u + rng.uniform(-0.5, 0.5, (5000, 1)) * v \
        + rng.uniform(-0.2, 0.8, (5000, 1)) * normal
    got = supported_points(X, normal, point, on, 0.01, 0.5)
    hull = MultiPoint([tuple(q) for q in uv]).convex_hull
    h = (X - point) @ normal
    ref = sum(1 for x, hh in zip(X, h) if 0.01 <= hh <= 0.5
              and hull.covers(Point(float((x - point) @ u), float((x - point) @ v))))
    assert got == ref and 0 < got < len(X)
    assert supported_points(X, normal, point, on[:2], 0.01, 0.5) == 0  # no outline
    assert supported_points(X, normal, point, on, 5.0, 6.0) == 0  # nothing in the band


@pytest.mark.parametrize("old, new, at, message", [
    ("max_height: 0.5 ", "max_height: 0.005 ", "0.005",
     "max_height 0.005 must be greater than min_height 0.01"),
    ("min_height: 0.01 ", "min_height: -0.01 ", "-0.01",
     "scene.ground.choose.supporting.min_height: -0.01 is less than the minimum of 0"),
    ("max_height: 0.5 ", "max_height: 50 cm ", "50 cm", "must be a number"),
    ("      supporting:", "      supportin:", "supportin:", "unknown key 'supportin' in scene.ground.choose (did you mean 'supporting'?)"),
])
def test_a_bad_choice_is_refused_at_its_position(tmp_path, capsys, old, new, at, message):
    assert old in TABLETOP
    text = TABLETOP.replace(old, new, 1)
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    line = text[:text.index(at)].count("\n") + 1
    col = text.index(at) - text.rfind("\n", 0, text.index(at))
    scan = tmp_path / "s.ply"
    write_ply(scan, tabletop_scene(0, resolution=(60, 80))[0])
    assert main(["run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "out")]) == 4
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"t.yaml:{line}:" in err and message in err, err
    if message.startswith("max_height"):
        assert f"t.yaml:{line}:{col}: " in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("key", ["choose", "sensor_above"])
def test_a_ground_search_setting_with_a_fixed_normal_is_a_warning(tmp_path, capsys, key):
    text = TABLETOP.replace("normal: auto", "normal: [0, -1, 0]", 1)
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    assert main(["rules", "check", str(rules)]) == 0
    err = capsys.readouterr().err
    line = text[:text.index(f"    {key}:")].count("\n") + 1
    assert f"t.yaml:{line}:5: warning: scene.ground.{key} is not used" in err, err


@pytest.mark.slow
def test_a_face_seen_from_underneath_is_not_the_table(tmp_path):
    """Generated scene 1007 (outside both parts; found on fresh seeds): the table came out of the
    first partition in five pieces, and the face of a large box turned towards the camera, which
    looks down at 54 deg, supported more points (9,751) than any of them: every point was taken
    from the table (F1 0.001). The camera is below that face's plane (on the side opposite the
    fallback normal, camera up): with ``sensor_above`` it is refused, and a piece of the table,
    seen from above, is the ground."""
    r, doc, X, lab, f1 = run_scene(tmp_path, 1007)
    assert f1 > 0.99, f1
    g = doc["explanation"]["ground"]
    refused = [v for v in g["candidates"] if "below its plane" in v.get("why", "")]
    assert refused and "(sensor_above)" in refused[0]["why"], g["candidates"]
    depth = float(refused[0]["why"].split("the sensor lies ")[1].split(" m below")[0])
    assert 0.0 < depth < 1.0, refused[0]["why"]  # a distance: the camera 0.27 m under the box face's plane
    assert refused[0]["cluster"] != g["cluster"]
    n, p = np.array(g["normal"]), np.array(g["point"])
    assert (lab[np.abs((X - p) @ n) < 0.01] == 1).mean() > 0.95  # the plane found is the table's
    assert n @ -p > 0 and "note" not in g  # the camera above it: no note that the frame is wrong
    rules = tmp_path / "without.yaml"
    text = TABLETOP.replace("    sensor_above: true", "    sensor_above: false", 1)
    assert text != TABLETOP
    rules.write_text(text, encoding="utf-8")
    (tmp_path / "w").mkdir()
    _, doc_without, _, _, f1_without = run_scene(tmp_path / "w", 1007, str(rules))
    assert f1_without < 0.1, f1_without
    assert doc_without["explanation"]["ground"]["cluster"] == refused[0]["cluster"]


def test_sensor_above_falls_back_when_every_plane_is_seen_from_underneath():
    """A ceiling over the camera is the only plane: refused, the fallback normal is used, and the
    note says why."""
    from kbs.knowledge import Interpreter

    rng = np.random.default_rng(0)
    ceiling = np.column_stack([rng.uniform(-1, 1, 8000), np.full(8000, -0.8), rng.uniform(0.5, 2.0, 8000)])
    rb = load_rule_base(str(ROOT / "examples" / "rules" / "tabletop.yaml"))
    assert rb.ground.sensor_above
    facts = Interpreter(rb, sensor=np.zeros(3), jobs=1).run(ceiling).explanation.ground
    assert facts.source == "fallback" and facts.cluster is None, facts
    assert "with the sensor above it" in facts.note and "fallback normal [0.0, -1.0, 0.0] is used" in facts.note, facts.note
    assert any("below its plane" in (c.why or "") for c in facts.candidates)


def test_sensor_above_must_be_a_boolean(tmp_path, capsys):
    text = TABLETOP.replace("sensor_above: true", "sensor_above: 1", 1)
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    line = text[:text.index("sensor_above: 1")].count("\n") + 1
    assert main(["rules", "check", str(rules)]) == 4
    err = capsys.readouterr().err
    assert f"t.yaml:{line}:" in err and "sensor_above" in err and "Traceback" not in err, err
