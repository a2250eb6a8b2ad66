"""End-to-end tests of `kbs run`, `kbs explain`, `kbs rules` and `kbs predicates` through the
real command."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.io import write_ply
from scenes import ground_and_rocks
from test_cli import EXAMPLE, ROOT, kbs

GOLDEN = ROOT / "tests" / "golden"


def _ply(path: Path):
    return PlyData.read(str(path))["vertex"]


@pytest.fixture(scope="module")
def rocks_scan(tmp_path_factory) -> tuple[Path, np.ndarray]:
    X, labels = ground_and_rocks()
    path = tmp_path_factory.mktemp("scan") / "rocks.ply"
    write_ply(path, X, {"truth": labels.astype(np.int32)})
    return path, labels


@pytest.mark.slow
def test_run_writes_ply_and_json_and_explains_the_cah_split(rocks_scan, tmp_path):
    scan, labels = rocks_scan
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "clusters" in r.stdout and "splits" in r.stdout and "time:" in r.stdout
    v = _ply(tmp_path / "rocks.ply")
    assert v["scalar_cluster"].dtype == np.int32 and v["scalar_label"].dtype == np.int32 and v["scalar_membership"].dtype == np.float32
    doc = json.loads((tmp_path / "rocks.json").read_text())
    assert doc["label_names"] == ["ground", "obstacle"]
    assert len(doc["clusters"]) == int(v["scalar_cluster"].max()) + 1
    assert {"center", "normal", "thickness", "eigenvalues"} <= set(doc["clusters"][0]["descriptors"])
    ground = v["scalar_label"] == 0
    assert ground[labels == 0].mean() > 0.95 and (~ground[labels > 0]).mean() > 0.8
    # the explanation tree, and why the rocks' cluster was split
    r = kbs("explain", str(tmp_path / "rocks.json"))
    assert r.returncode == 0
    line = [ln for ln in r.stdout.splitlines() if "by CAh" in ln][0]
    assert "split in 3 components by CAh [outdoor.yaml:" in line and "not connected (connexity = 3 > 1)" in line
    cid = line.split()[0]
    r = kbs("explain", str(tmp_path / "rocks.json"), "--cluster", cid + ".0")
    assert r.returncode == 0 and line.strip() in r.stdout and "accepted as obstacle" in r.stdout
    assert re.search(r"\n    sheet +no +flatness = ", r.stdout) and re.search(r"\n    level +yes +ground_angle = ", r.stdout)


@pytest.mark.slow
def test_run_says_which_limit_stopped_which_clusters(rocks_scan, tmp_path):
    scan, _ = rocks_scan
    text = kbs("rules", "show", "outdoor").stdout
    rules = tmp_path / "shallow.yaml"
    rules.write_text(re.sub(r"max_depth: \d+", "max_depth: 1", text))
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    i = [n for n, ln in enumerate(lines) if "limits reached;" in ln][0]
    n_limits = int(lines[i].split(" limits reached;")[0].split()[-1])
    assert n_limits > 0
    assert re.fullmatch(r"  limits: max_depth \(1\) stopped \d+ clusters?, [\d,]+ points \(c\d[^)]*\): "
                        r"raise limits\.max_depth in shallow\.yaml to split them", lines[i + 1]), lines[i + 1]
    by_kind = json.loads((tmp_path / "rocks.json").read_text())["summary"]["limits_by_kind"]
    assert sum(e["count"] for e in by_kind.values()) == n_limits
    assert by_kind["max_depth"]["setting"] == "limits.max_depth" and by_kind["max_depth"]["value"] == 1


@pytest.mark.slow
def test_explain_unknown_cluster_suggests_one(rocks_scan, tmp_path):
    scan, _ = rocks_scan
    assert kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path)).returncode == 0
    r = kbs("explain", str(tmp_path / "rocks.json"), "--cluster", "c9.9.9")
    assert r.returncode == 2 and "no cluster 'c9.9.9'" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("name", ["broken", "syntax"])
def test_broken_rule_files_give_the_golden_messages(name):
    r = kbs("rules", "check", f"tests/golden/{name}.yaml", cwd=ROOT)
    assert r.returncode == 4
    assert r.stderr == (GOLDEN / f"{name}.expected").read_text()


def test_run_with_a_broken_rule_file_exits_4(tmp_path):
    r = kbs("run", "--rules", str(GOLDEN / "broken.yaml"), str(EXAMPLE), "--out", str(tmp_path))
    assert r.returncode == 4 and "unknown predicate 'thicknes'" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_rules_show_and_list_and_check_shipped():
    r = kbs("rules", "show", "outdoor")
    shipped = (ROOT / "rules" / "outdoor.yaml").read_text()
    # the file as shipped, its editor line pointing at the installed schema (test_ecosystem_io)
    assert r.returncode == 0 and r.stdout.partition("\n")[2] == shipped.partition("\n")[2]
    assert r.stdout.startswith("# yaml-language-server: $schema=file://")
    r = kbs("rules", "list")
    assert r.returncode == 0 and "outdoor" in r.stdout and "planar_contest" in r.stdout and "airborne" in r.stdout
    r = kbs("rules", "check", "outdoor", "planar_contest")
    assert r.returncode == 0 and r.stdout.count(": ok") == 2


def test_predicates_lists_builtins_and_plugins():
    r = kbs("predicates", "--plugin", str(ROOT / "examples" / "plugins" / "elongation.py"))
    assert r.returncode == 0
    for name in ("thickness", "ground_angle", "connexity", "point_count", "extent", "height_above_ground",
                 "distance_to_sensor", "flatness", "elongation", "axis_tilt"):
        assert f"\n{name}  [" in "\n" + r.stdout
    assert "param alpha_factor: float in [0.1, 100.0] (default 3.0)" in r.stdout
    assert "param method: one of graph, alpha_opening (default 'graph')" in r.stdout
    assert "param opening_factor: float in [0.0, 10.0] (default 1.0, with method: alpha_opening)" in r.stdout


@pytest.mark.slow
def test_user_rule_file_with_plugin_runs(rocks_scan, tmp_path):
    scan, labels = rocks_scan
    args = ["run", "--rules", str(ROOT / "examples" / "rules" / "poles.yaml"), str(scan), "--out", str(tmp_path)]
    r = kbs(*args)
    assert r.returncode == 4 and "unknown predicate 'elongation'" in r.stderr
    r = kbs(*args, "--plugin", str(ROOT / "examples" / "plugins" / "elongation.py"))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "rocks.json").read_text())
    assert doc["label_names"] == ["ground", "pole", "obstacle"]
    checks = {c["check"] for rec in doc["explanation"]["clusters"] for c in rec["checks"]}
    assert "long" in checks  # the plugin predicate was measured (and 'upright' only where 'long' holds)


@pytest.mark.slow
def test_broken_plugin_exits_7(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("raise RuntimeError('boom')\n")
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--plugin", str(bad), "--out", str(tmp_path))
    assert r.returncode == 7 and "boom" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("args, code", [
    (["--sensor", "1,2"], 2),
    (["--rules"], 2),
    (["--jobs", "0"], 2),
    (["-j", "-3"], 2),
])
@pytest.mark.slow
def test_bad_options_exit_2(args, code, tmp_path):
    base = ["run", "--rules", "outdoor", str(EXAMPLE), "--out", str(tmp_path)]
    r = kbs(*(base + args))
    assert r.returncode == code and "Traceback" not in r.stderr


def test_unreadable_cloud_exits_3(tmp_path):
    r = kbs("run", "--rules", "outdoor", str(tmp_path / "missing.ply"), "--out", str(tmp_path))
    assert r.returncode == 3 and "missing.ply" in r.stderr


@pytest.mark.slow
def test_bundled_example_runs(tmp_path):
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    v = _ply(tmp_path / "outdoor.ply")
    truth, pred = np.asarray(v["label_in"]) == 0, np.asarray(v["scalar_label"]) == 0  # the scene's own labels stay
    f1 = 2 * (truth & pred).sum() / (truth.sum() + pred.sum())
    assert f1 > 0.9, f1


REAL = [("outdoor", "semantickitti/000001.points.npy"), ("outdoor", "isprs/samp11.txt"),
        ("outdoor", "mosd/learn0.pcd"), ("planar_contest", "mosd/learn0.pcd")]


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
@pytest.mark.parametrize("rules, scan", REAL)
def test_runs_on_real_scans(shared_data, tmp_path, rules, scan):
    r = kbs("run", "--rules", rules, str(shared_data / scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    stem = Path(scan).stem
    v = _ply(tmp_path / f"{stem}.ply")
    doc = json.loads((tmp_path / f"{stem}.json").read_text())
    assert len(doc["clusters"]) >= 2 and doc["n_points"] == v.count
    if scan.startswith("semantickitti"):
        gt = np.load(shared_data / "semantickitti" / "000001.labels.npy").ravel()
        valid = gt != 0
        truth = np.isin(gt, [9, 10, 11, 12, 17])[valid]
        pred = (np.asarray(v["scalar_label"]) == 0)[valid]
        tp = (truth & pred).sum()
        f1 = 2 * tp / (truth.sum() + pred.sum())
        assert f1 > 0.85, f1


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_worked_example_tabletop_rule_base_on_mosd(shared_data, tmp_path):
    r = kbs("rules", "check", str(ROOT / "examples" / "rules" / "tabletop.yaml"))
    assert r.returncode == 0, r.stderr
    r = kbs("run", "--rules", str(ROOT / "examples" / "rules" / "tabletop.yaml"),
            str(shared_data / "mosd" / "learn0.pcd"), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    v = _ply(tmp_path / "learn0.ply")
    gt, pred = np.asarray(v["label_in"]), np.asarray(v["scalar_label"])
    for name, index, truth in (("table", 0, (gt >= 1) & (gt <= 9)), ("object", 1, gt >= 20)):
        p = pred == index
        assert (p & truth).sum() / p.sum() > 0.98 and (p & truth).sum() / truth.sum() > 0.95, name


# --- CAh with the paper's alpha-opening (method: alpha_opening) ---------------------------------


def boulders_joined_by_a_ridge(width: float = 0.06, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Flat ground (12 m x 12 m) and two low boulders (1.2 m wide, 0.55 m high, 0.6 m apart) joined
    by a low ridge ``width`` wide, all sampled at about 1,800 points per square metre seen from
    above; sensor frame, 1.5 m above the ground. Labels: 0 ground, 1 and 2 the boulders, 3 the
    ridge."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(-6, 6, 12000), rng.uniform(-6, 6, 12000), rng.normal(0, 0.005, 12000)])
    parts, labels = [ground], [np.zeros(len(ground), int)]
    for i, cx in enumerate((-0.9, 0.9), start=1):
        n = int(1800 * np.pi * 0.36)
        r, t = 0.6 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
        parts.append(np.c_[cx + r * np.cos(t), 3.0 + r * np.sin(t), 0.5 * (1 - r ** 2 / 0.36) + 0.05])
        labels.append(np.full(n, i))
    n = int(1800 * 0.7 * width)
    parts.append(np.c_[rng.uniform(-0.35, 0.35, n), 3.0 + rng.uniform(-width / 2, width / 2, n), rng.uniform(0.1, 0.15, n)])
    labels.append(np.full(n, 3))
    return np.vstack(parts) - [0.0, 0.0, 1.5], np.concatenate(labels)


@pytest.mark.slow
def test_alpha_opening_separates_boulders_that_a_ridge_joins(tmp_path):
    X, labels = boulders_joined_by_a_ridge()
    scan = tmp_path / "boulders.ply"
    write_ply(scan, X, {"truth": labels.astype(np.int32)})
    text = kbs("rules", "show", "outdoor").stdout
    rules = tmp_path / "alpha.yaml"
    rules.write_text(text.replace("params: {alpha_factor: 3.0, min_fraction: 0.05}",
                                  "params: {alpha_factor: 3.0, min_fraction: 0.05, method: alpha_opening}"))
    assert kbs("rules", "check", str(rules)).returncode == 0
    clusters = {}
    for name, rb in (("graph", "outdoor"), ("alpha", str(rules))):
        out = tmp_path / name
        r = kbs("run", "--rules", rb, str(scan), "--out", str(out))
        assert r.returncode == 0, r.stderr
        clusters[name] = np.asarray(_ply(out / "boulders.ply")["scalar_cluster"])
        explained = kbs("explain", str(out / "boulders.json")).stdout
        cah = [ln for ln in explained.splitlines() if "by CAh" in ln]
        if name == "graph":  # the ridge is dense and 6 cm wide: the graph's opening keeps it
            assert not cah, cah
        else:  # the disc of radius alpha does not fit in it: two components, one per boulder
            assert len(cah) == 1 and "split in 2 components by CAh [alpha.yaml:" in cah[0]
            assert "not connected (connexity = 2 > 1)" in cah[0]
    for name, expected in (("graph", 1), ("alpha", 2)):
        c = clusters[name]
        main = [np.bincount(c[labels == k]).argmax() for k in (1, 2)]
        assert len(set(main)) == expected, name
        for k, m in zip((1, 2), main):  # each boulder is (all but its foot on the ground) in one cluster
            assert (c[labels == k] == m).mean() > 0.95


@pytest.mark.slow
def test_connexity_method_and_opening_factor_are_checked_in_the_rule_file(tmp_path):
    text = kbs("rules", "show", "outdoor").stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("params: {alpha_factor: 3.0, min_fraction: 0.05}",
                                "params: {alpha_factor: 3.0, min_fraction: 0.05, method: alpha_openin}")
                   .replace("  tiny:\n", "  connected2:\n    predicate: connexity\n    params: {opening_factor: 1.5}\n"
                            "    max: 1\n  tiny:\n"))
    r = kbs("rules", "check", str(bad))
    assert r.returncode == 4 and "Traceback" not in r.stderr
    line = next(n for n, ln in enumerate(bad.read_text().splitlines(), 1) if "alpha_openin" in ln)
    col = bad.read_text().splitlines()[line - 1].index("alpha_openin") + 1
    assert (f"bad.yaml:{line}:{col}: predicate 'connexity': parameter 'method' must be one of graph, "
            f"alpha_opening, got 'alpha_openin'") in r.stderr
    line = next(n for n, ln in enumerate(bad.read_text().splitlines(), 1) if "opening_factor" in ln)
    col = bad.read_text().splitlines()[line - 1].index("1.5") + 1
    assert (f"bad.yaml:{line}:{col}: predicate 'connexity': parameter 'opening_factor' applies only with "
            f"method: alpha_opening (here method is 'graph')") in r.stderr
    assert "2 problems in 1 rule file" in r.stderr
    good = tmp_path / "good.yaml"
    good.write_text(text.replace("params: {alpha_factor: 3.0, min_fraction: 0.05}",
                                 "params: {alpha_factor: 3.0, min_fraction: 0.05, method: alpha_opening, "
                                 "opening_factor: 1.5}"))
    assert kbs("rules", "check", str(good)).returncode == 0


# --- post.merge_coplanar: ground planes split by the tree come out as one cluster ----------------

MERGE_RULES = """\
kbs_rules: 1
name: merge
units: m
strategy: divisive
scene:
  sensor: [0, 0, 2]
  ground:
    normal: [0, 0, 1]
checks:
  planar: {predicate: thickness, max: 0.05}
  level: {predicate: ground_angle, max: 22.5}
rules:
  - {name: PAh, if: not planar, then: split}
labels:
  - {name: ground, if: [planar, level]}
  - {name: other}
post:
  merge_coplanar: {label: ground, max_angle: 10, max_offset: 0.15}
"""


def ground_patches(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Four planar patches, all labelled ground by MERGE_RULES (thin, within 22.5 deg of
    horizontal): 0 and 1, two halves of one plane z = 0, 4 m apart (coplanar: must merge); 2, a
    platform 0.5 m above that plane (parallel, but offset by more than max_offset: must not
    merge); 3, a ramp tilted 15 deg (more than max_angle: must not merge) in the gap between 0 and
    1, its centre on their plane and its plane through their centres, so that only the angle keeps
    it apart."""
    rng = np.random.default_rng(seed)

    def patch(n, x, y):
        return np.c_[rng.uniform(*x, n), rng.uniform(*y, n), rng.normal(0, 0.005, n)]

    a, b = patch(4000, (-10, -2), (-5, 5)), patch(4000, (2, 10), (-5, 5))
    platform = patch(1500, (-3, 3), (8, 12)) + [0.0, 0.0, 0.5]
    ramp = patch(1500, (-1.5, 1.5), (-3, 3))
    ramp[:, 2] += np.tan(np.radians(15.0)) * ramp[:, 1]
    parts = [a, b, platform, ramp]
    return np.vstack(parts), np.repeat(np.arange(4), [len(p) for p in parts])


@pytest.mark.slow
def test_coplanar_ground_clusters_are_merged_into_one_output_cluster_and_others_are_not(tmp_path):
    X, part = ground_patches()
    scan = tmp_path / "patches.ply"
    write_ply(scan, X, {"truth": part.astype(np.int32)})
    out = {}
    for name, text in (("merge", MERGE_RULES), ("no_merge", MERGE_RULES.split("post:")[0])):
        rules = tmp_path / f"{name}.yaml"
        rules.write_text(text)
        r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / name))
        assert r.returncode == 0, r.stderr
        v = _ply(tmp_path / name / "patches.ply")
        out[name] = (np.asarray(v["scalar_cluster"]), np.asarray(v["scalar_label"]),
                     json.loads((tmp_path / name / "patches.json").read_text()))
    # without the merge, the split tree leaves the plane z = 0 in several ground clusters
    cluster, label, doc = out["no_merge"]
    assert (label == 0).all()  # every patch is ground
    assert len(np.unique(cluster[part <= 1])) >= 2
    # with it, they are one output cluster, made of those leaves; the platform and the ramp are not in it
    cluster, label, doc = out["merge"]
    assert (label == 0).all()
    plane = np.unique(cluster[part <= 1])
    assert len(plane) == 1, plane
    g = int(plane[0])
    entry = doc["clusters"][g]
    assert entry["index"] == g and entry["label"] == "ground" and entry["n_points"] == int((cluster == g).sum())
    assert len(entry["ids"]) == len(np.unique(out["no_merge"][0][part <= 1])) >= 2
    assert entry["n_points"] == int((part <= 1).sum())
    platform, ramp = np.unique(cluster[part == 2]), np.unique(cluster[part == 3])
    assert len(platform) == 1 and len(ramp) == 1 and len({g, int(platform[0]), int(ramp[0])}) == 3
    assert len(doc["clusters"]) == 3
    # and the explanation says so, for each merged leaf
    leaf = entry["ids"][0]
    r = kbs("explain", str(tmp_path / "merge" / "patches.json"), "--cluster", leaf)
    others = len(entry["ids"]) - 1
    assert (f"note: merged with {others} other coplanar ground cluster{'s' if others > 1 else ''} "
            f"into output cluster {g}") in r.stdout
