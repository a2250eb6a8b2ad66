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
    line = [ln for ln in r.stdout.splitlines() if "CAh" in ln][0]
    assert "split in 3 components: " in line and "connexity = 3 components > 1 [outdoor.yaml:" in line
    cid = line.split()[0]
    r = kbs("explain", str(tmp_path / "rocks.json"), "--cluster", cid + ".0")
    assert r.returncode == 0 and line.strip() in r.stdout and "accepted as obstacle" in r.stdout
    assert "FAIL  sheet: flatness = " in r.stdout and "pass  level: ground_angle = " in r.stdout


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


def test_explain_unknown_cluster_suggests_one(rocks_scan, tmp_path):
    scan, _ = rocks_scan
    assert kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path)).returncode == 0
    r = kbs("explain", str(tmp_path / "rocks.json"), "--cluster", "c9.9.9")
    assert r.returncode == 2 and "no cluster 'c9.9.9'" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("name", ["broken", "syntax"])
def test_broken_rule_files_give_the_golden_messages(name):
    r = kbs("rules", "check", f"tests/golden/{name}.yaml", cwd=ROOT)
    assert r.returncode == 4
    assert r.stderr == (GOLDEN / f"{name}.expected").read_text()


def test_run_with_a_broken_rule_file_exits_4(tmp_path):
    r = kbs("run", "--rules", str(GOLDEN / "broken.yaml"), str(EXAMPLE), "--out", str(tmp_path))
    assert r.returncode == 4 and "unknown predicate 'thicknes'" in r.stderr and "Traceback" not in r.stderr


def test_rules_show_and_list_and_check_shipped():
    r = kbs("rules", "show", "outdoor")
    assert r.returncode == 0 and r.stdout == (ROOT / "rules" / "outdoor.yaml").read_text()
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
def test_bad_options_exit_2(args, code, tmp_path):
    base = ["run", "--rules", "outdoor", str(EXAMPLE), "--out", str(tmp_path)]
    r = kbs(*(base + args))
    assert r.returncode == code and "Traceback" not in r.stderr


def test_unreadable_cloud_exits_3(tmp_path):
    r = kbs("run", "--rules", "outdoor", str(tmp_path / "missing.ply"), "--out", str(tmp_path))
    assert r.returncode == 3 and "missing.ply" in r.stderr


def test_bundled_example_runs(tmp_path):
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    v = _ply(tmp_path / "outdoor.ply")
    truth, pred = np.asarray(v["label_in"]) == 0, np.asarray(v["scalar_label"]) == 0  # the scene's own labels stay
    f1 = 2 * (truth & pred).sum() / (truth.sum() + pred.sum())
    assert f1 > 0.9, f1


REAL = [("outdoor", "semantickitti/000001.points.npy"), ("outdoor", "isprs/samp11.txt"),
        ("outdoor", "mosd/learn0.pcd"), ("planar_contest", "mosd/learn0.pcd")]


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
