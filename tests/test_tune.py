"""``kbs tune`` (thresholds marked ``tune:`` fitted by cross-validation over labelled scans), the
``tune:`` marks in rule files, and SemanticKITTI ``.label`` ground truth in ``kbs eval``.

The end-to-end tests run the real command on small generated outdoor scenes (``kbs synth
outdoor``) whose truth was made by kbs itself with known threshold values: ``kbs tune`` must find
those values again from a file holding others."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from kbs.evaluation import SEMANTICKITTI_GROUND, load_ground_truth
from kbs.io import read_cloud
from kbs.io.result import read_result_cloud
from kbs.knowledge import Interpreter, load_rule_base
from kbs.knowledge.rulebase import RuleFileError, parse_rule_base, shipped_text
from kbs.knowledge.predicates import PredicateRegistry
from kbs.knowledge.tuning import SplitTree, grid, split_relevant, with_values

OUTDOOR = shipped_text("outdoor")


def run_kbs(capsys, *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def marked(tmp_path: Path, name: str = "marked.yaml", **edits: str) -> Path:
    """outdoor.yaml with lines replaced (old line -> new line(s)), written to tmp_path/name."""
    text = OUTDOOR
    for old, new in edits.values():
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / name
    path.write_text(text)
    return path


PLANAR = "    max: 0.05                  # m\n"
CONTACT = "      tolerance: 0.05            # m\n"
LOW = "    max: 0.25                  # m\n"
#: outdoor.yaml's 'raised' check and relabel rule, to take out (old -> new)
WITHOUT_RAISED = {"c": (re.search(r"\n(  raised:\n(    .*\n)+)", OUTDOOR)[1], ""),
                  "d": (re.search(r"\n(      - name: raised\n(        .*\n)+)", OUTDOOR)[1], "")}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[Path]:
    """Three small outdoor scenes (about 9,400 points each), made by the command."""
    folder = tmp_path_factory.mktemp("scenes")
    out = []
    for seed in (1, 2, 3):
        path = folder / f"scene{seed}.ply"
        assert main(["synth", "outdoor", "--seed", str(seed), "--resolution", "90x160", "--out", str(path)]) == 0
        out.append(path)
    return out


# --- the tune: marks ---------------------------------------------------------------------------


def problems(text: str) -> list[str]:
    with pytest.raises(RuleFileError) as exc:
        parse_rule_base(text, "t.yaml", PredicateRegistry.default())
    return [f"{p.pos.line}:{p.pos.col}: {p.message}" for p in exc.value.problems]


def test_tune_marks_are_read_with_their_values_and_positions():
    text = OUTDOOR.replace(PLANAR, PLANAR + "    tune: {min: 0.02, max: 0.1, steps: 5}\n", 1)
    text = text.replace(CONTACT, CONTACT + "      tune: [0.02, 0.1]\n", 1)
    rb = parse_rule_base(text, "t.yaml", PredicateRegistry.default())
    planar, contact = rb.tunables
    assert planar.name == "checks.planar.max" and planar.value == 0.05
    assert planar.values == (0.02, 0.04, 0.05, 0.06, 0.08, 0.1)  # the file's value joins the grid
    line = text.splitlines()[planar.pos.line - 1]
    assert line[planar.pos.col - 1:].startswith("0.05") and "max:" in line
    assert contact.name == "post.ground_contact.tolerance" and contact.values == (0.02, 0.05, 0.1)
    assert split_relevant(rb, planar) and not split_relevant(rb, contact)


@pytest.mark.parametrize("mark, message", [
    ("    tune: {min: 0.06, max: 0.1}\n", "the range [0.06, 0.1] does not hold the current value 0.05"),
    ("    tune: {min: 0.1, max: 0.02}\n", "min 0.1 > max 0.02"),
    ("    tune: [0.01, 0.02]\n", "does not hold the current value 0.05"),
    ("    tune: {field: predicate, min: 0.01, max: 0.1}\n", "'predicate' is not a number kbs tune can fit"),
    ("    tune: {field: min, min: 0.01, max: 0.1}\n", "min is not set"),
    ("    tune: {min: -1, max: 0.1}\n", "outside what 'thickness' can measure"),
    ("    tune: {steps: 3}\n", "give 'min' and 'max'"),
    ("    tune: {values: [0.01, 0.1], min: 0, max: 1}\n", "either 'values' or 'min'/'max'"),
    ("    tune: fine\n", "checks.planar.tune is invalid"),
])
def test_bad_tune_marks_are_positioned_problems(mark, message):
    text = OUTDOOR.replace(PLANAR, PLANAR + mark, 1)
    line = text.splitlines().index(mark.rstrip("\n")) + 1
    found = problems(text)
    assert any(p.startswith(f"{line}:") and message in p for p in found), found


def test_bad_tune_marks_on_post_steps():
    text = OUTDOOR.replace("      max_offset: 0.15\n", "      max_offset: 0.15\n      tune: [0.1, 0.2]\n", 1)
    assert any("say which threshold with 'field'" in p for p in problems(text))
    text = OUTDOOR.replace("      max_offset: 0.15\n", "      max_offset: 0.15\n      tune: {field: label, values: [1, 2]}\n")
    assert any("'label' is not a number kbs tune can fit (numeric thresholds here: max_angle, max_offset)" in p
               for p in problems(text))
    text = OUTDOOR.replace(CONTACT, CONTACT + "      tune: [0.0, 0.05]\n", 1)
    assert any("value 0 must be above 0" in p for p in problems(text))


def test_the_per_range_settings_can_be_marked_for_kbs_tune():
    """post.ground_model.per_range and post.ground_contact.per_range are thresholds kbs tune can fit
    (labels only: the split tree does not depend on them), written back in place; a value the
    schema refuses is a positioned problem."""
    radius = "      radius: 3.0                # m\n"
    text = OUTDOOR.replace(radius, radius + "      per_range: 0.0\n      tune: {field: per_range, values: [0, 0.1, 0.2]}\n", 1)
    text = text.replace(CONTACT, CONTACT + "      per_range: 0.0\n      tune: {field: per_range, values: [0, 0.002, 0.005]}\n", 1)
    rb = parse_rule_base(text, "t.yaml", PredicateRegistry.default())
    model, contact = rb.tunables
    assert (model.name, model.values) == ("post.ground_model.per_range", (0.0, 0.1, 0.2))
    assert (contact.name, contact.values) == ("post.ground_contact.per_range", (0.0, 0.002, 0.005))
    assert not split_relevant(rb, model) and not split_relevant(rb, contact)
    new_text, other = with_values(rb, {model.name: 0.2, contact.name: 0.005})
    assert other.ground_model.per_range == 0.2 and other.contact.per_range == 0.005
    assert "      per_range: 0.2\n" in new_text and "      per_range: 0.005\n" in new_text
    bad = text.replace("values: [0, 0.002, 0.005]", "values: [0, 0.002, 2]")
    assert any("tune on post[3].ground_contact.per_range: value 2 is outside [0, 1]" in p for p in problems(bad))


def test_a_bad_tune_mark_exits_4_from_kbs_tune_with_its_position(tmp_path, capsys, scenes):
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: {min: 0.1, max: 0.02}\n"))
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), "field:ground", str(scenes[1]),
                           "field:ground", "--ground-values", "1", "--out", str(tmp_path / "new.yaml"))
    assert code == 4
    assert f"{rules}:42:17:" in err and "min 0.1 > max 0.02" in err


def test_kbs_run_ignores_the_tune_marks(tmp_path, capsys, scenes):
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: [0.03, 0.1]\n"), b=(CONTACT, CONTACT + "      tune: [0.01, 0.2]\n"))
    for name, r in (("plain", "outdoor"), ("marked", str(rules))):
        assert main(["-q", "run", "--rules", r, str(scenes[0]), "--out", str(tmp_path / name), "-j", "1"]) == 0
    a = read_result_cloud(tmp_path / "plain" / "scene1.ply").fields
    b = read_result_cloud(tmp_path / "marked" / "scene1.ply").fields
    np.testing.assert_array_equal(a["label"], b["label"])
    np.testing.assert_array_equal(a["cluster"], b["cluster"])


# --- labelling a split tree again ----------------------------------------------------------------


def test_labelling_the_split_tree_again_gives_a_full_runs_result(tmp_path, scenes):
    """Every label-only setting, by the split tree labelled again, against a full run of the
    same rule base (the reference)."""
    rules = marked(tmp_path, a=(LOW, LOW + "    tune: [0.1, 0.25, 0.5]\n"),
                   b=(CONTACT, CONTACT + "      tune: [0.02, 0.05, 0.14]\n"),
                   c=("      tolerance: 0.10            # m\n", "      tolerance: 0.10            # m\n      tune: [0.05, 0.3]\n"),
                   d=("      max_offset: 0.15\n", "      max_offset: 0.15\n      tune: {field: max_angle, values: [2, 10]}\n"))
    rb = load_rule_base(str(rules))
    assert not any(split_relevant(rb, t) for t in rb.tunables)
    X = read_cloud(scenes[1]).xyz
    tree = SplitTree.grow(rb, X)
    seen = set()
    for setting in grid(rb.tunables)[::5]:
        other = with_values(rb, setting)[1]
        again = tree.label(other)
        full = Interpreter(other).run(X)
        np.testing.assert_array_equal(again.label, full.label)
        np.testing.assert_array_equal(again.cluster, full.cluster)
        np.testing.assert_array_equal(again.membership, full.membership)
        seen.add(int((full.label == 0).sum()))
    assert len(seen) > 3  # the settings do change the labels


def test_labelling_again_keeps_the_far_outliers_aside(tmp_path, scenes):
    """A cloud with a far outlier: the split tree labelled again gives a full run's result, the
    outlier noise in both (the per-point arrays have the cloud's length)."""
    rules = marked(tmp_path, a=(LOW, LOW + "    tune: [0.1, 0.5]\n"))
    rb = load_rule_base(str(rules))
    X = read_cloud(scenes[1]).xyz
    X = np.vstack([X, X.max(axis=0) + 100 * (X.max(axis=0) - X.min(axis=0))])
    tree = SplitTree.grow(rb, X)
    for setting in grid(rb.tunables):
        other = with_values(rb, setting)[1]
        again, full = tree.label(other), Interpreter(other).run(X)
        assert again.label.shape == (len(X),) and again.label[-1] == -1 and again.cluster[-1] == -1
        np.testing.assert_array_equal(again.label, full.label)
        np.testing.assert_array_equal(again.cluster, full.cluster)
        assert again.explanation.notes[-1] == full.explanation.notes[-1]


# --- kbs tune end to end --------------------------------------------------------------------------


def truth_from_known_values(tmp_path: Path, scenes: list[Path], planar: str, contact: str,
                            without_raised: bool = False) -> list[Path]:
    """Ground truth made by kbs run with checks.planar.max = planar and
    post.ground_contact.tolerance = contact (and without the 'raised' rule if asked): one .npy of
    0/1 (1 ground) per scene."""
    tmp_path.mkdir(exist_ok=True)
    rules = marked(tmp_path, "truth.yaml", a=(PLANAR, f"    max: {planar}\n"), b=(CONTACT, f"      tolerance: {contact}\n"),
                   **(WITHOUT_RAISED if without_raised else {}))
    out = []
    for scene in scenes:
        assert main(["-q", "run", "--rules", str(rules), str(scene), "--out", str(tmp_path / "truth"), "-j", "1"]) == 0
        label = read_result_cloud(tmp_path / "truth" / f"{scene.stem}.ply").fields["label"]
        path = tmp_path / f"{scene.stem}.truth.npy"
        np.save(path, (label == 0).astype(np.int32))
        out.append(path)
    return out


@pytest.mark.slow
def test_kbs_tune_recovers_the_thresholds_the_truth_was_made_with(tmp_path, capsys, scenes):
    """Truth made with planar.max 0.15 and ground_contact.tolerance 0.14; the file says 0.05 and
    0.05. On these scenes planar 0.05 and 0.15 give other labels on scenes 2 and 3 (not 1), so
    every fold's two training scenes tell them apart. Without outdoor.yaml's 'raised' rule, in
    the truth and the tuned file alike: it relabels what planar 0.15 lets through on scene 2, so
    that there 0.05 and 0.15 agree, and no fold could tell them apart."""
    truths = truth_from_known_values(tmp_path, scenes, "0.15", "0.14", without_raised=True)
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: [0.03, 0.05, 0.15]\n"),
                   b=(CONTACT, CONTACT + "      tune: {min: 0.02, max: 0.2, steps: 4}  # 0.02 0.08 0.14 0.2\n"),
                   **WITHOUT_RAISED)
    out, report = tmp_path / "tuned.yaml", tmp_path / "report.json"
    pairs = [str(p) for pair in zip(scenes, truths) for p in pair]
    code, stdout, err = run_kbs(capsys, "tune", "--rules", str(rules), *pairs, "--ground-values", "1", "--folds", "3",
                                "--out", str(out), "--report", str(report), "-j", "1")
    assert code == 0, err
    doc = json.loads(report.read_text())
    truth = {"checks.planar.max": 0.15, "post.ground_contact.tolerance": 0.14}
    assert doc["chosen_on_all_scans"]["setting"] == truth
    # held back, chosen on the other two scenes: the truth's values each time, and a perfect score
    assert [f["chosen"] for f in doc["folds"]] == [truth] * 3
    assert [f["score"] for f in doc["folds"]] == [1.0, 1.0, 1.0]
    assert all(f["original_score"] < 1.0 for f in doc["folds"])
    assert {m["name"] for m in doc["moved"]} == {"checks.planar.max", "post.ground_contact.tolerance"}
    # the planar values need a segmentation each, the contact tolerances none: 3 values x 3 scans
    assert doc["grid"] == {"settings": 3 * 5, "evaluated": 15, "segmentations": 9, "seconds": doc["grid"]["seconds"],
                           "stopped": None}
    # the new file: the old text, comments kept, the two values replaced in place, commented
    old, new = rules.read_text().splitlines(), out.read_text().splitlines()
    assert new[0].startswith("# kbs tune: 2 of 2 marked thresholds moved on 3 scans (3 folds)")
    changed = [(a, b) for a, b in zip(old, new[1:]) if a != b]
    assert len(new) == len(old) + 1 and len(changed) == 2
    cv = f"cross-validated ground F1 1.0000 (file's values: {doc['cv_original_score']:.4f})"
    assert changed[0][1] == f"    max: 0.15                  # m  # kbs tune: 0.05 -> 0.15, {cv}"
    assert changed[1][1] == f"      tolerance: 0.14            # m  # kbs tune: 0.05 -> 0.14, {cv}"
    assert out.read_text().endswith("\n")
    assert load_rule_base(str(out)).checks["planar"].max == 0.15
    # the markdown report on stdout
    assert "| 3 | " in stdout and f"| mean | | | 1.0000 | {doc['cv_original_score']:.4f} |" in stdout
    assert "Moved: checks.planar.max 0.05 -> 0.15; post.ground_contact.tolerance 0.05 -> 0.14" in stdout
    # the tuned file scores the truth exactly
    assert main(["-q", "run", "--rules", str(out), str(scenes[2]), "--out", str(tmp_path / "check"), "-j", "1"]) == 0
    label = read_result_cloud(tmp_path / "check" / "scene3.ply").fields["label"]
    np.testing.assert_array_equal(label == 0, np.load(truths[2]) == 1)


def test_kbs_tune_keeps_the_files_values_when_they_made_the_truth(tmp_path, capsys, scenes):
    truths = truth_from_known_values(tmp_path, scenes[:2], "0.05", "0.05")
    rules = marked(tmp_path, b=(CONTACT, CONTACT + "      tune: [0.02, 0.14, 0.2]\n"))
    out = tmp_path / "tuned.yaml"
    pairs = [str(p) for pair in zip(scenes[:2], truths) for p in pair]
    code, stdout, err = run_kbs(capsys, "tune", "--rules", str(rules), *pairs, "--ground-values", "1",
                                "--out", str(out), "--metric", "total_error", "-j", "1")
    assert code == 0, err
    assert "No threshold moved" in stdout and "ground total error (lower is better)" in stdout
    assert out.read_text().splitlines()[1:] == rules.read_text().splitlines()


def test_kbs_tune_does_not_replace_a_file_it_did_not_write(tmp_path, capsys, scenes):
    """--out and --report as kbs run's outputs: an existing file kbs did not write is refused before
    the work (exit 3, as kbs run), replaced with --force; kbs tune's own output is replaced."""
    truths = truth_from_known_values(tmp_path, scenes[:2], "0.05", "0.05")
    rules = marked(tmp_path, b=(CONTACT, CONTACT + "      tune: [0.02, 0.14]\n"))
    pairs = [str(p) for pair in zip(scenes[:2], truths) for p in pair]
    out, report = tmp_path / "notes.yaml", tmp_path / "notes.json"
    out.write_text("my notes\n")
    args = ["tune", "--rules", str(rules), *pairs, "--ground-values", "1", "--out", str(out), "-j", "1"]
    code, stdout, err = run_kbs(capsys, *args)
    assert code == 3 and f"{out}: exists and was not written by kbs" in err and "give --force" in err, err
    assert "marked threshold" not in err and out.read_text() == "my notes\n"  # refused before any work
    report.write_text("{}")
    code, _, err = run_kbs(capsys, *args, "--force", "--report", str(report))
    assert code == 0, err
    assert out.read_text().startswith("# kbs tune:") and json.loads(report.read_text())["run_id"]
    code, _, err = run_kbs(capsys, *args, "--report", str(report))  # its own files: replaced
    assert code == 0, err


def test_kbs_tune_bounds_the_evaluations(tmp_path, capsys, scenes):
    truths = truth_from_known_values(tmp_path, scenes[:2], "0.05", "0.05")
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: [0.03, 0.05, 0.1]\n"))
    report = tmp_path / "r.json"
    pairs = [str(p) for pair in zip(scenes[:2], truths) for p in pair]
    code, stdout, err = run_kbs(capsys, "tune", "--rules", str(rules), *pairs, "--ground-values", "1", "--max-evals",
                                "2", "--out", str(tmp_path / "t.yaml"), "--report", str(report), "-j", "1",
                                "--select", "median")
    assert code == 0, err
    doc = json.loads(report.read_text())
    assert doc["grid"]["evaluated"] == 2 and doc["grid"]["stopped"] == "--max-evals 2"
    assert "stopped at --max-evals 2" in stdout
    assert doc["select"] == "median" and "chosen by its median score over the tuning scans" in stdout
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), *pairs, "--ground-values", "1", "--select", "max",
                           "--out", str(tmp_path / "u.yaml"), "-j", "1")
    assert code == 2 and "'max' is not one of 'mean', 'median'" in err


def test_kbs_tune_time_limit_and_progress(tmp_path, capsys, scenes, monkeypatch):
    truths = truth_from_known_values(tmp_path, scenes[:2], "0.05", "0.05")
    rules = marked(tmp_path, b=(CONTACT, CONTACT + "      tune: [0.02, 0.14, 0.2]\n"))
    report = tmp_path / "r.json"
    pairs = [str(p) for pair in zip(scenes[:2], truths) for p in pair]
    monkeypatch.setenv("KBS_PROGRESS_SECONDS", "0")
    code, stdout, err = run_kbs(capsys, "tune", "--rules", str(rules), *pairs, "--ground-values", "1", "--time-limit",
                                "0.001", "--out", str(tmp_path / "t.yaml"), "--report", str(report), "-j", "1")
    assert code == 0, err
    doc = json.loads(report.read_text())
    # the file's own values are scored on every scan whatever the limit; nothing else was started in time
    assert doc["grid"]["evaluated"] == 1 and doc["grid"]["stopped"] == "--time-limit 0.001 s"
    assert doc["per_scan"][0]["original"] == 1.0 and not doc["moved"]
    assert "kbs: tune: 1 of 8 scores (settings x scans)" in err and "kbs: tune: 2 of 8 scores" in err


def test_kbs_tune_bad_inputs(tmp_path, capsys, scenes):
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: [0.03, 0.1]\n"))
    truth = tmp_path / "t.npy"
    np.save(truth, np.zeros(len(read_cloud(scenes[0]).xyz), dtype=np.int32))
    short = tmp_path / "short.npy"
    np.save(short, np.zeros(10, dtype=np.int32))
    out = str(tmp_path / "new.yaml")
    # no tune marks: the rule file is the problem (4)
    code, _, err = run_kbs(capsys, "tune", "--rules", "outdoor", str(scenes[0]), str(truth), str(scenes[0]),
                           str(truth), "--ground-values", "1", "--out", out)
    assert code == 4 and "outdoor.yaml:1:1: no threshold is marked 'tune:'" in err
    # a scan without its truth (2)
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[1]),
                           "--ground-values", "1", "--out", out)
    assert code == 2 and f"scan {scenes[1]} has no ground truth" in err
    # labels not one per point (3)
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[1]),
                           str(short), "--ground-values", "1", "--out", out)
    assert code == 3 and f"{short}: 10 labels for the 9,394 points of {scenes[1]}" in err
    # one scan: no cross-validation (2); more folds than scans (2); the rule file as output (2)
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), "--ground-values", "1",
                           "--out", out)
    assert code == 2 and "at least 2 SCAN GT pairs" in err
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[0]),
                           str(truth), "--ground-values", "1", "--folds", "3", "--out", out)
    assert code == 2 and "3 folds for 2 scans" in err
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[0]),
                           str(truth), "--ground-values", "1", "--out", str(rules))
    assert code == 2 and "is an input" in err
    # no ground values for a GT that has no default (2); an unknown ground label (2)
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[0]),
                           str(truth), "--out", out)
    assert code == 2 and "give --ground-values" in err
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[0]),
                           str(truth), "--ground-values", "1", "--ground-label", "table", "--out", out)
    assert code == 2 and "has no label 'table'" in err
    assert not Path(out).exists()


def test_kbs_tune_refuses_one_file_for_out_and_report(tmp_path, capsys, scenes):
    """--out X --report X: one replaced the other (the tuned rule file lost); refused before the work."""
    rules = marked(tmp_path, a=(PLANAR, PLANAR + "    tune: [0.03, 0.1]\n"))
    truth = tmp_path / "t.npy"
    np.save(truth, np.zeros(len(read_cloud(scenes[0]).xyz), dtype=np.int32))
    same = tmp_path / "same.yaml"
    (tmp_path / "link").symlink_to(tmp_path, target_is_directory=True)
    for other in (same, tmp_path / "link" / "same.yaml"):
        code, out, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[1]),
                                 str(truth), "--ground-values", "1", "--out", str(same), "--report", str(other))
        assert code == 3 and err == (f"kbs: error: {other}: is both --out and --report: one file cannot hold both; "
                                     "give them two different paths\n"), err
        assert not same.exists() and out == ""
    report = tmp_path / "notes.json"
    report.write_text("mine")
    code, _, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(truth), str(scenes[1]),
                           str(truth), "--ground-values", "1", "--out", str(same), "--report", str(report))
    assert code == 3 and "or choose another --report" in err and report.read_text() == "mine"


# --- SemanticKITTI .label in kbs eval ------------------------------------------------------------


def kitti_pair(tmp_path: Path, scene: Path) -> tuple[Path, Path, np.ndarray]:
    """A scene as a KITTI .bin with a SemanticKITTI .label: ground 40 (road) or 72 (terrain) by
    the side of the scene, objects 50 (building), some points 0 (unlabelled) and 1 (outlier);
    instance ids in the high 16 bits."""
    pc = read_cloud(scene)
    n = len(pc.xyz)
    ground = pc.fields["ground"].astype(bool)
    cls = np.where(ground, np.where(pc.xyz[:, 1] > 0, 40, 72), 50).astype(np.uint32)
    cls[::50] = 0
    cls[1::97] = 1
    raw = cls | (np.arange(n, dtype=np.uint32) % 7 << 16)
    stem = tmp_path / "000007"
    np.hstack([pc.xyz, np.zeros((n, 1))]).astype(np.float32).tofile(stem.with_suffix(".bin"))
    raw.astype("<u4").tofile(stem.with_suffix(".label"))
    return stem.with_suffix(".bin"), stem.with_suffix(".label"), cls


def test_kbs_eval_reads_a_semantickitti_label_file(tmp_path, capsys, scenes):
    scan, label, cls = kitti_pair(tmp_path, scenes[0])
    assert main(["-q", "run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "out"), "-j", "1"]) == 0
    result = tmp_path / "out" / "000007.ply"
    code, out, err = run_kbs(capsys, "eval", str(result), str(label), "--no-hoover", "--json", str(tmp_path / "e.json"))
    assert code == 0, err
    ignored = int(np.isin(cls, (0, 1)).sum())
    assert f"{len(cls) - ignored:,} labelled points, {ignored:,} unlabelled (0,1) ignored" in out
    assert "against GT values 40,44,48,49,60,72" in out
    doc = json.loads((tmp_path / "e.json").read_text())["ground"]
    pred = read_result_cloud(result).fields["label"] == 0
    keep = ~np.isin(cls, (0, 1))
    truth = np.isin(cls, (40, 72))
    assert doc["tp"] == int((pred & truth & keep).sum()) and doc["fn"] == int((~pred & truth & keep).sum())
    assert doc["fp"] == int((pred & ~truth & keep).sum())
    # terrain (72) counts as ground by default: without it the recall is another
    code, out2, _ = run_kbs(capsys, "eval", str(result), str(label), "--no-hoover", "--ground-values", "40,44,48,49,60")
    assert code == 0 and out2 != out


def test_kbs_eval_semantickitti_label_errors(tmp_path, capsys, scenes):
    scan, label, _ = kitti_pair(tmp_path, scenes[0])
    assert main(["-q", "run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "out"), "-j", "1"]) == 0
    result = str(tmp_path / "out" / "000007.ply")
    data = label.read_bytes()
    odd = tmp_path / "odd.label"
    odd.write_bytes(data[:-2])
    code, _, err = run_kbs(capsys, "eval", result, str(odd))
    assert code == 3 and f"{odd}: size {len(data) - 2:,} bytes is not a multiple of 4" in err
    label.write_bytes(data[:-4])  # one label short of the .bin beside it
    code, _, err = run_kbs(capsys, "eval", result, str(label))
    n = len(data) // 4
    assert code == 3 and f"{n - 1:,} labels ({len(data) - 4:,} bytes), but the scan {scan} beside it has {n:,} points" in err
    other = tmp_path / "other.label"  # no .bin beside it: the result's count is what differs
    other.write_bytes(data[:-4])
    code, _, err = run_kbs(capsys, "eval", result, str(other))
    assert code == 3 and f"{other}: {n - 1:,} labels for the {n:,} points of" in err
    empty = tmp_path / "empty.label"
    empty.write_bytes(b"")
    code, _, err = run_kbs(capsys, "eval", result, str(empty))
    assert code == 3 and "the label file is empty" in err


def test_the_shared_semantickitti_labels_read_as_the_data_readme_counts(shared_data):
    """seq00 frame 0: 124,668 points; ground {40,44,48,49,60,72}: 67,873 points (data README)."""
    folder = shared_data / "semantickitti-seq00"
    cloud = read_cloud(folder / "seq00_000000.bin")
    cls = load_ground_truth(folder / "seq00_000000.label", cloud)
    assert len(cls) == 124_668 and int(np.isin(cls, SEMANTICKITTI_GROUND).sum()) == 67_873
    assert 1_500 < int(np.isin(cls, (0, 1)).sum()) < 2_500
    assert cls.max() < 1 << 16


# --- the example and the split --------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def test_the_marked_outdoor_example_is_the_shipped_rule_base_plus_marks():
    """examples/rules/outdoor-tune.yaml: outdoor.yaml with its header and 'tune:' lines; drop them
    and the text is the shipped file's, so it segments as the shipped rule base does."""
    example = (ROOT / "examples" / "rules" / "outdoor-tune.yaml").read_text().splitlines()
    body = [ln for ln in example if not ln.lstrip().startswith("tune:")]
    first = body.index("# Outdoor navigation (Loménie et al.): navigable ground versus obstacles.")
    assert body[first:] == OUTDOOR.splitlines()[1:]
    rb = load_rule_base(str(ROOT / "examples" / "rules" / "outdoor-tune.yaml"))
    assert [t.name for t in rb.tunables] == ["checks.planar.max", "checks.low.max", "post.ground_release.tolerance",
                                             "post.ground_contact.tolerance"]
    assert [split_relevant(rb, t) for t in rb.tunables] == [True, False, False, False]


def test_the_marked_airborne_example_is_the_shipped_rule_base_plus_marks():
    """examples/rules/airborne-tune.yaml: airborne.yaml with its header and 'tune:' lines; drop them
    and the text is the shipped file's (bench_tune.py --kind airborne tunes it)."""
    example = (ROOT / "examples" / "rules" / "airborne-tune.yaml").read_text().splitlines()
    body = [ln for ln in example if not ln.lstrip().startswith("tune:")]
    first = body.index("# Airborne laser scanning: bare earth versus objects (buildings, vegetation) seen from above.")
    assert body[first:] == shipped_text("airborne").splitlines()[1:]
    rb = load_rule_base(str(ROOT / "examples" / "rules" / "airborne-tune.yaml"))
    assert [split_relevant(rb, t) for t in rb.tunables] == [t.name == "checks.planar.max" for t in rb.tunables]


def test_the_split_puts_each_shared_scan_in_one_part(shared_data):
    import yaml

    doc = yaml.safe_load((ROOT / "benchmarks" / "splits.yaml").read_text())
    seen: dict[str, str] = {}
    for kind in ("vehicle", "airborne", "table-top"):
        assert doc[kind]["tune"] and doc[kind]["validate"]
        for part in ("tune", "validate"):
            for key in doc[kind][part]:
                assert key not in seen, f"{key} is in {seen[key]} and {kind}.{part}"
                seen[key] = f"{kind}.{part}"
    frames = [k for k in seen if k.startswith("SemanticKITTI-seq00/")]
    assert len(frames) == 3 and len({seen[k] for k in frames}) == 1  # one drive: one part
    # every labelled scan of the data README is placed (simple.las, 1,065 points of Autzen: not)
    assert len(seen) == 6 + 6 + 3 + 5
    assert (shared_data / "semantickitti-seq00" / "seq00_000002.label").is_file()


def test_kbs_tune_says_when_the_held_back_scans_do_not_support_the_move(tmp_path, capsys, scenes):
    """Two scans whose truths were made with contact tolerances on either side of the file's value:
    each fold's choice (the other scan's value) scores worse on its held-back scan than the
    file's value, and the report and the new file say so."""
    a = truth_from_known_values(tmp_path / "a", scenes[:1], "0.05", "0.14")
    b = truth_from_known_values(tmp_path / "b", scenes[1:2], "0.05", "0.02")
    rules = marked(tmp_path, b=(CONTACT, CONTACT + "      tune: [0.02, 0.14]\n"))
    out, report = tmp_path / "tuned.yaml", tmp_path / "r.json"
    code, stdout, err = run_kbs(capsys, "tune", "--rules", str(rules), str(scenes[0]), str(a[0]), str(scenes[1]),
                                str(b[0]), "--ground-values", "1", "--out", str(out), "--report", str(report), "-j", "1")
    assert code == 0, err
    doc = json.loads(report.read_text())
    assert [f["chosen"]["post.ground_contact.tolerance"] for f in doc["folds"]] == [0.02, 0.14]
    first, second = doc["folds"]
    assert first["score"] <= first["original_score"] and second["score"] < second["original_score"]
    assert doc["cv_score"] < doc["cv_original_score"]
    assert "note: on the held-back scans, the values chosen on the other scans score worse than the file's own" in stdout
    assert out.read_text().splitlines()[1] == ("# kbs tune: held back, the tuned values scored worse than the file's: "
                                               "see the report")


def test_a_setting_is_chosen_by_the_mean_or_the_median_of_its_tuning_scores():
    """kbs tune --select: by the mean (GridSearchCV's choice) one scan much harder than the others
    decides; by the median the setting better on most scans wins. Ties go to the nearest setting."""
    from kbs.evaluation.tune import best_setting

    # total error (lower is better, sign -1) of settings 0 (the file's), 1 and 2 on three scans
    scores = np.array([[0.20, 0.20, 1.00],
                       [0.10, 0.10, 0.90],    # mean 0.367: best by the mean
                       [0.05, 0.06, 1.20]])   # median 0.06: best by the median (mean 0.437)
    near = [[0.0], [1.0], [2.0]]
    assert best_setting(scores, [0, 1, 2], [0, 1, 2], -1.0, near, "mean") == 1
    assert best_setting(scores, [0, 1, 2], [0, 1, 2], -1.0, near, "median") == 2
    assert best_setting(scores, [0, 1], [0, 1, 2], -1.0, near, "median") == 1  # among those evaluated
    assert best_setting(scores, [0, 1, 2], [2], 1.0, near, "median") == 2  # higher is better
    tied = np.array([[0.5, 0.5], [0.5, 0.5]])
    assert best_setting(tied, [1, 0], [0, 1], 1.0, [[0.0], [1.0]], "median") == 0
