"""`kbs explain` as a reader who has not read the paper meets it: rules and checks named with
their docs, a condition's terms shown as holding or not (never FAIL for a check that went the way
the rule wanted), the label of a cluster a limit stopped explained, a large tree grouped and folded
(--depth, --cluster unfold it); the result JSON and its explanation carry a format version that
every reader checks."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from kbs.knowledge import PredicateRegistry
from test_cli import EXAMPLE, ROOT


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    """`kbs run --rules outdoor` on the bundled example: its result JSON."""
    out = tmp_path_factory.mktemp("example")
    assert main(["-q", "run", "--rules", "outdoor", "-j", "1", str(EXAMPLE), "--out", str(out)]) == 0
    return out / "outdoor.json"


def _explain(capsys, *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["explain", *map(str, args)])
    got = capsys.readouterr()
    return code, got.out, got.err


# -- 1. names with their docs -------------------------------------------------------------------


def test_the_summary_names_each_rule_label_and_check_with_its_doc(example, capsys):
    code, out, _ = _explain(capsys, example)
    assert code == 0
    assert "  SAh [outdoor.yaml:81] split if not planar and level and sheet: 4 split\n" in out
    assert "      size ambiguity — a wide ground cluster has swallowed small obstacles\n" in out
    assert "  CAh [outdoor.yaml:85] split_components if not planar and not connected: 2 split in components\n" in out
    assert "  ground [outdoor.yaml:91] if planar and level (navigable): 6 clusters" in out
    assert re.search(r"\n  planar +thickness <= 0\.05 m \[outdoor\.yaml:38\]: PAh, planar ambiguity — thin across", out)
    # the tree's lines name the rule that acted and the terms of its condition
    assert ("c1 (6,869 pts) split in 4 by SAh [outdoor.yaml:81]: not planar (thickness = 0.1179 m > 0.05 m), "
            "level (ground_angle = 0.9913 deg <= 22.5 deg), sheet (flatness = 0.03933 <= 0.3)\n") in out


def test_why_shows_each_check_with_its_doc_and_no_fail_for_a_check_that_went_the_rules_way(example, capsys):
    """c1 was split by SAh because it is *not* planar: 'planar' measured no is what the rule asked
    for, and 'tiny' no is what keeps it from being noise. Neither is a failure."""
    code, out, _ = _explain(capsys, example, "--cluster", "c1")
    assert code == 0 and "FAIL" not in out and "pass " not in out
    assert ("    noise [outdoor.yaml:78] reject if tiny: does not hold: tiny does not hold "
            "(point_count = 6,869 pts > 1 pts)\n") in out
    assert ("    SAh [outdoor.yaml:81] split if not planar and level and sheet: holds: not planar "
            "(thickness = 0.1179 m > 0.05 m), level (ground_angle = 0.9913 deg <= 22.5 deg), sheet") in out
    assert "CAh" not in out.split("checks measured")[0].split("SAh [outdoor.yaml:81] split if")[1]  # not evaluated
    assert re.search(r"\n    planar +no +thickness = 0\.1179 m > 0\.05 m +\[outdoor\.yaml:38\] +PAh, planar ambiguity", out)
    assert re.search(r"\n    tiny +no +point_count = 6,869 pts > 1 pts +\[outdoor\.yaml:55\] +a point alone", out)
    assert "tree below c1" in out and "  c1.2.1.1 (128 pts) split in 2 components by CAh" in out


def test_why_of_an_obstacle_says_which_label_conditions_did_not_hold(example, capsys):
    code, out, _ = _explain(capsys, example, "--cluster", "c1.3.0")
    assert code == 0
    assert "c1.3.0 (1,078 pts) accepted as obstacle, not ground: planar does not hold (thickness = 0.06635 m > 0.05 m)" in out
    assert ("    ground [outdoor.yaml:91] if planar and level: does not hold: planar does not hold "
            "(thickness = 0.06635 m > 0.05 m); navigable\n") in out
    assert "    obstacle [outdoor.yaml:94] no condition (the default label)\n" in out
    assert "  post.relabel, the rules for clusters labelled obstacle:\n    low_level [outdoor.yaml:102] obstacle -> ground" in out


# -- 2. a cluster a limit stopped ---------------------------------------------------------------


def test_a_cluster_stopped_by_a_limit_says_which_rule_wanted_a_split_and_how_it_got_its_label(tmp_path, capsys):
    rules = tmp_path / "shallow.yaml"
    rules.write_text(re.sub(r"max_depth: \d+", "max_depth: 1", (ROOT / "rules" / "outdoor.yaml").read_text()))
    assert main(["-q", "run", "--rules", str(rules), "-j", "1", str(EXAMPLE), "--out", str(tmp_path)]) == 0
    code, out, _ = _explain(capsys, tmp_path / "outdoor.json")
    assert code == 0
    assert ("  c1 (6,869 pts) kept as obstacle (limit reached: limits.max_depth = 1): SAh [shallow.yaml:81] would "
            "split it: not planar (thickness = 0.1179 m > 0.05 m), level (ground_angle = 0.9913 deg <= 22.5 deg), "
            "sheet (flatness = 0.03933 <= 0.3); label obstacle, not ground: planar does not hold "
            "(thickness = 0.1179 m > 0.05 m)\n") in out
    assert "    kept by a limit (max_depth): 1 cluster, 6,869 pts: c1 (6,869 pts)\n" in out
    code, out, _ = _explain(capsys, tmp_path / "outdoor.json", "--cluster", "c1")
    assert code == 0
    assert "    the split did not happen (limit reached: limits.max_depth = 1): the cluster is kept as it is and labelled\n" in out
    assert "  labels, in order (the first whose condition holds gives the label):\n    ground [shallow.yaml:91] if planar and level: does not hold: planar does not hold" in out


# -- 3. a large tree, grouped and folded ------------------------------------------------------------


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_explain_of_a_large_scan_is_short_and_unfolds_with_depth_and_cluster(shared_data, tmp_path, capsys):
    """SemanticKITTI: 616 clusters, 618 lines before. The summary and the tree to the depth that
    fits stay under 80 lines; --depth all prints every cluster; --cluster prints one branch."""
    scan = shared_data / "semantickitti" / "000001.points.npy"
    assert main(["-q", "run", "--rules", "outdoor", str(scan), "--out", str(tmp_path)]) == 0
    js = tmp_path / "000001.points.json"
    records = json.loads(js.read_text())["explanation"]["clusters"]
    code, short, _ = _explain(capsys, js)
    assert code == 0 and len(short.splitlines()) < 80 and len(records) > 600
    m = re.search(r"\ntree \(to depth (\d), ([\d,]+) of its ([\d,]+) clusters: --depth N or --depth all unfolds it", short)
    assert m and int(m.group(3).replace(",", "")) == len(records) - 1
    assert int(m.group(2)) == len(short.split(m.group(0))[1].splitlines()) - 2  # the root, and the heading's end
    assert re.search(r"\[\+ \d+ clusters below, ending as ground \d+ \([\d,]+ pts\), obstacle \d+", short)
    code, full, _ = _explain(capsys, js, "--depth", "all")
    tree = full.split("\ntree:\n")[1].splitlines()
    assert code == 0 and [ln.split()[0] for ln in tree] == [r["id"] for r in records]
    code, two, _ = _explain(capsys, js, "--depth", "2")
    tree = two.split("--depth all unfolds it, --cluster ID shows one branch):\n")[1].splitlines()
    depth = {r["id"]: r["depth"] for r in records}
    assert code == 0 and {depth[ln.split()[0]] for ln in tree} == {0, 1, 2}
    deep = max(records, key=lambda r: r["depth"])
    branch = deep["id"].rsplit(".", 3)[0]
    code, one, _ = _explain(capsys, js, "--cluster", branch, "--depth", "all")
    below = one.split(f"tree below {branch}:\n")[1].splitlines()
    assert code == 0 and deep["id"] in {ln.split()[0] for ln in below}
    assert all(ln.split()[0].startswith(branch + ".") for ln in below)


def test_depth_must_be_a_number_of_levels_or_all(example, capsys):
    code, _, err = _explain(capsys, example, "--depth", "-1")
    assert code == 2 and "--depth" in err and "expected a number of levels (0 or more) or 'all'" in err
    code, out, _ = _explain(capsys, example, "--depth", "0")
    assert code == 0 and out.rstrip().splitlines()[-1].startswith("c (26,233 pts) partitioned in 2")
    assert "[+ 16 clusters below, ending as ground 6 (24,702 pts), obstacle 4 (1,531 pts)]" in out


# -- 4. the renderer knows no predicate by name ---------------------------------------------------------


def test_the_renderer_names_no_predicate():
    source = (ROOT / "knowledge" / "explain.py").read_text()
    for p in PredicateRegistry.default():
        assert f'"{p.name}"' not in source and f"'{p.name}'" not in source, p.name


# -- 5. format and version ---------------------------------------------------------------------------


def test_the_result_and_its_explanation_carry_format_and_version(example):
    doc = json.loads(example.read_text())
    assert list(doc)[:2] == ["format", "version"] and (doc["format"], doc["version"]) == ("kbs-result", "1.1")
    e = doc["explanation"]
    assert (e["format"], e["version"]) == ("kbs-explanation", "1.2")  # 1.2: the global strategy's sweep
    assert {c["name"] for c in e["catalogue"]["checks"]} == {"planar", "level", "sheet", "connected", "tiny", "low", "raised", "sunk"}
    assert [r["name"] for r in e["catalogue"]["rules"]] == ["noise", "SAh", "CAh"]


def _copy_pair(example: Path, folder: Path, edit) -> Path:
    folder.mkdir()
    shutil.copy(example.with_suffix(".ply"), folder / "outdoor.ply")
    doc = json.loads(example.read_text())
    edit(doc)
    (folder / "outdoor.json").write_text(json.dumps(doc))
    return folder / "outdoor.json"


@pytest.mark.parametrize("where", ["result", "explanation"])
def test_a_newer_major_version_is_refused_by_every_reader(example, tmp_path, capsys, where):
    def newer(doc):
        (doc if where == "result" else doc["explanation"])["version"] = "2.0"
        doc["label_names"] = doc.pop("label_names")  # unchanged otherwise

    js = _copy_pair(example, tmp_path / "newer", newer)
    code, out, err = _explain(capsys, js)
    kind = "kbs-result" if where == "result" else "kbs-explanation"
    assert code == 3 and out == "" and err.count("\n") == 1
    assert f"written by a newer kbs ({kind} version 2.0; this kbs reads 1.x): upgrade kbs to read it" in err
    if where == "result":  # eval and render read the result JSON through the same check
        assert main(["render", str(js), "--kind", "map", "--out", str(tmp_path / "m.png")]) == 3
        assert "written by a newer kbs (kbs-result version 2.0" in capsys.readouterr().err
        assert main(["eval", str(js.with_suffix(".ply")), "field:label_in", "--ground-values", "0", "--no-hoover"]) == 3
        assert "written by a newer kbs (kbs-result version 2.0" in capsys.readouterr().err
        assert not (tmp_path / "m.png").exists()


@pytest.mark.parametrize("version, problem", [("x", "'version' is 'x'"), (1.1, "'version' is 1.1"),
                                               ("1.1.0", "'version' is '1.1.0'")])
def test_a_malformed_version_is_not_a_result(example, tmp_path, capsys, version, problem):
    js = _copy_pair(example, tmp_path / "bad", lambda doc: doc.update(version=version))
    code, _, err = _explain(capsys, js)
    assert code == 3 and f"not a kbs result file ({problem}: expected \"MAJOR.MINOR\"" in err


def test_another_format_is_not_a_result(example, tmp_path, capsys):
    js = _copy_pair(example, tmp_path / "other", lambda doc: doc.update(format="kbs-map"))
    code, _, err = _explain(capsys, js)
    assert code == 3 and "not a kbs result file ('format' is 'kbs-map', not 'kbs-result')" in err


def test_results_written_before_versions_and_newer_minor_versions_still_read(example, tmp_path, capsys):
    def legacy(doc):  # kbs 0.1: result_format 1, an explanation without format, version or catalogue
        del doc["format"], doc["version"]
        doc["result_format"] = 1
        for key in ("format", "version", "catalogue"):
            del doc["explanation"][key]

    js = _copy_pair(example, tmp_path / "legacy", legacy)
    code, out, _ = _explain(capsys, js)
    assert code == 0 and "c1 (6,869 pts) split in 4 by SAh [outdoor.yaml:81]: thickness = 0.1179 m > 0.05 m" in out
    code, out, _ = _explain(capsys, js, "--cluster", "c1.3.0")
    assert code == 0 and "accepted as obstacle" in out and "FAIL" not in out
    def minor(doc):  # keys a newer 1.x may add, at every level: ignored
        doc.update(version="1.9", extra={"a": 1})
        e = doc["explanation"]
        e.update(version="1.9", extra=1)
        e["catalogue"]["checks"][0]["extra"] = 1
        e["catalogue"]["rules"][0]["extra"] = 1
        e["clusters"][1]["extra"] = 1
        e["clusters"][1]["checks"][0]["extra"] = 1

    newer_minor = _copy_pair(example, tmp_path / "minor", minor)
    code, out, _ = _explain(capsys, newer_minor, "--cluster", "c0")
    assert code == 0 and "c0 (19,364 pts) accepted as ground: planar (thickness = 0.01393 m <= 0.05 m)" in out
    assert main(["render", str(newer_minor), "--kind", "map", "--out", str(tmp_path / "m.png")]) == 0


# -- 6. the HTML report: unlabelled is not noise --------------------------------------------------------


def test_the_report_tells_unlabelled_clusters_from_noise(tmp_path):
    """A rule base whose only label needs a condition: the clusters it does not hold for are in
    the output (cluster >= 0, label -1), and the report calls them unlabelled, not noise."""
    from test_report_html import _data

    text = (ROOT / "rules" / "outdoor.yaml").read_text()
    text, n = re.subn(r"\n  - name: obstacle\n", "\n", text)
    assert n == 1
    text = text.replace("asprs_classes: {ground: 2, obstacle: 1, noise: 7}", "")
    text = re.sub(r"\n  - relabel:\n(      .*\n|        .*\n)+", "\n", text)
    text = re.sub(r"\n  - ground_release:.*\n(      .*\n)+", "\n", text)
    rules = tmp_path / "ground_only.yaml"
    rules.write_text(text)
    assert main(["-q", "run", "--rules", str(rules), "-j", "1", str(EXAMPLE), "--out", str(tmp_path), "--report"]) == 0
    page = (tmp_path / "outdoor.html").read_text()
    data = _data(page)
    import base64

    width = "<i2" if data["int"] == 2 else "<i4"  # the report packs them in 16 bits when they fit
    label = np.frombuffer(base64.b64decode(data["label"]), dtype=width)
    cluster = np.frombuffer(base64.b64decode(data["cluster"]), dtype=width)
    assert data["unlabelled_key"] == -2 and data["unlabelled"] != data["noise"]
    assert (label == -2).any() and (cluster[label == -2] >= 0).all()  # in an output cluster, no label
    assert (cluster[label == -1] < 0).all()  # noise: in no output cluster
    assert '"unlabelled (no label matched)"' in page and "(unlabelled: no label matched)" in page


def test_a_cluster_given_the_default_label_says_why_no_rule_acted(tmp_path, capsys):
    """planar_contest's only label has no condition: what decided is that no rule's condition held."""
    assert main(["-q", "run", "--rules", "planar_contest", "-j", "1", str(EXAMPLE), "--out", str(tmp_path)]) == 0
    code, out, _ = _explain(capsys, tmp_path / "outdoor.json", "--depth", "all")
    accepted = [ln for ln in out.splitlines() if " accepted as plane" in ln]
    assert code == 0 and accepted
    for line in accepted:
        assert re.fullmatch(r" *c[\d.]+ \([\d,]+ pts\) accepted as plane: tiny does not hold \(point_count = [\d,]+ pts "
                            r"> 10 pts\), not planar does not hold \(thickness = [\d.e-]+ m <= 0\.01 m\)", line), line


# -- the README's printed outputs ------------------------------------------------------------------


@pytest.mark.slow
def test_the_readme_run_and_explain_block_is_what_kbs_prints(tmp_path):
    """The README's first example block (`kbs run` on the bundled scene, then `kbs explain` and
    `kbs explain --cluster`): every line it shows, but the elisions (`...`) and the time line, is a
    line of the real output, in the same order."""
    import shlex
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## `kbs run`: segment a scan with a rule base"):]
    block = re.search(r"```\n(.*?)```", section, re.S).group(1)
    commands: list[tuple[str, list[str]]] = []
    for line in block.splitlines():
        if line.startswith("$ "):
            commands.append((line[2:].split("#")[0].strip(), []))
        else:
            commands[-1][1].append(line)
    assert [c.split()[:2] for c, _ in commands] == [["kbs", "run"], ["kbs", "explain"], ["kbs", "explain"]]
    (tmp_path / "examples" / "data").mkdir(parents=True)
    (tmp_path / "examples" / "data" / "outdoor.ply").write_bytes((root / "examples" / "data" / "outdoor.ply").read_bytes())
    for command, shown in commands:
        args = shlex.split(command)[1:]
        r = subprocess.run([sys.executable, "-c", "import sys; from kbs.cli.main import main; sys.exit(main())", *args],
                           capture_output=True, text=True, cwd=tmp_path, timeout=300)
        assert r.returncode == 0, r.stderr
        got = (r.stderr + r.stdout).splitlines() if args[0] == "run" else r.stdout.splitlines()
        at = 0
        for line in shown:
            if line.strip() in ("...", "") or line.startswith("  time: "):
                continue
            assert line in got[at:], f"README line not printed (in order) by `{command}`:\n{line}"
            at = got.index(line, at) + 1


@pytest.mark.slow
def test_the_readme_airborne_outputs_are_what_kbs_prints(shared_data, tmp_path):
    """Two printed outputs of the README's airborne examples, on the shared scans: the tiles line of
    `kbs run --rules airborne --tile 121 samp11.txt`, and the classes of the LAS it writes for
    autzen_trim.las (they had gone stale: 69 clusters stitched and other class counts, from rule
    bases sessions before)."""
    import subprocess
    import sys

    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    tiles = re.search(r"\$ kbs run --rules airborne --tile 121 \.\./shared/data/isprs/samp11\.txt\n\.\.\.\n(  tiles: .*)\n",
                      readme).group(1)
    classes = re.search(r"print\(np\.bincount\(laspy\.read\('out/autzen_trim\.las'\)\.classification\)\)\"\n(\[.*\])\n",
                        readme).group(1)
    run = [sys.executable, "-c", "import sys; from kbs.cli.main import main; sys.exit(main())", "run", "--rules",
           "airborne"]
    r = subprocess.run([*run, "--tile", "121", str(shared_data / "isprs" / "samp11.txt"), "--out", str(tmp_path / "a")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert tiles in (r.stderr + r.stdout).splitlines(), (tiles, r.stderr)
    r = subprocess.run([*run, str(shared_data / "las" / "autzen_trim.las"), "--out", str(tmp_path / "b")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    import laspy

    got = np.bincount(laspy.read(str(tmp_path / "b" / "autzen_trim.las")).classification)
    assert str(got) == classes, (str(got), classes)


# -- 7. the records are frozen ------------------------------------------------------------------------


def test_the_records_of_a_run_and_of_a_result_file_are_frozen(example):
    """Nothing writes a cluster's record in place: the run builds new ones, and a record read back
    from a result file cannot be changed either (its sequences are tuples)."""
    import dataclasses

    from kbs.knowledge import Explanation

    doc = json.loads(example.read_text())
    expl = Explanation.from_dict(doc["explanation"])
    rec = expl["c1"]
    assert isinstance(rec.checks, tuple) and isinstance(rec.children, tuple) and isinstance(rec.notes, tuple)
    for field, value in (("label", "ground"), ("notes", ()), ("output_index", 3), ("action", "reject")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(rec, field, value)
    with pytest.raises(AttributeError):
        rec.notes.append("x")  # type: ignore[attr-defined]
    # a new record instead; the explanation's dictionary form is the file's, unchanged
    assert rec.noted("x").notes == rec.notes + ("x",) and expl["c1"] is rec
    assert expl.to_dict()["clusters"] == doc["explanation"]["clusters"]


def test_a_run_leaves_the_records_it_was_handed_unchanged():
    """Labelling and the post steps give the leaves new records: the strategy's records (what
    ``kbs tune`` labels again) are as the strategy left them."""
    from kbs.knowledge import Interpreter, load_rule_base
    from scenes import ground_and_rocks

    class Keeping(Interpreter):
        judged = None

        def finish(self, judged, t0):
            self.judged = judged  # as the strategy handed it on, not a copy
            return super().finish(judged, t0)

    X, _ = ground_and_rocks()
    it = Keeping(load_rule_base("outdoor"))
    seg = it.run(X)
    judged = it.judged
    assert judged is not None and all(lf.record.label is None for lf in judged.leaves)
    assert all(r.output_index is None for r in judged.records.values())
    final = seg.explanation.records
    assert {lf.id for lf in judged.leaves} <= set(final)
    assert all(final[lf.id].label is not None and final[lf.id].output_index is not None for lf in judged.leaves)
    again = Interpreter(load_rule_base("outdoor")).finish(judged, 0.0)
    assert np.array_equal(again.label, seg.label) and again.explanation.to_dict() == seg.explanation.to_dict()


def test_the_ground_section_is_typed_and_round_trips_through_json(example):
    """The explanation's ground section is frozen records (the search's facts, each candidate's
    verdict, what the local ground surface steps did), written as the same JSON it always was."""
    import dataclasses

    from kbs.knowledge import Explanation
    from kbs.knowledge.groundfacts import GroundCandidate, GroundFacts, LocalModel

    doc = json.loads(example.read_text())
    written = doc["explanation"]["ground"]
    assert {"source", "cluster", "normal", "point", "method", "candidates", "local_model"} <= set(written)
    g = Explanation.from_dict(doc["explanation"]).ground
    assert isinstance(g, GroundFacts) and g.source == written["source"] and g.normal == tuple(written["normal"])
    assert all(isinstance(c, GroundCandidate) for c in g.candidates) and len(g.candidates) == len(written["candidates"])
    assert isinstance(g.local_model, LocalModel) and g.local_model.points == written["local_model"]["points"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.source = "x"  # type: ignore[misc]
    assert g.to_dict() == written and json.loads(json.dumps(g.to_dict())) == written
    assert GroundFacts.from_dict(g.to_dict()) == g
    # a section with keys a newer minor version adds reads, and writes what it knows
    assert GroundFacts.from_dict({**written, "extra": 1}) == g
    # the fallback's facts, a skipped local model, and a tiled run's sections round-trip too
    fallback = GroundFacts(source="fallback", normal=(0.0, 0.0, 1.0), point=(0.0, 0.0, -1.5),
                           note="no cluster ...: the fallback normal [0, 0, 1] is used",
                           local_model=LocalModel(note="no ground plane: post.ground_model skipped"))
    tiled = GroundFacts(source="per tile (fallback)", tiles={"t0_0": fallback, "t0_1": GroundFacts()})
    for facts in (fallback, tiled, GroundFacts()):
        assert GroundFacts.from_dict(json.loads(json.dumps(facts.to_dict()))) == facts
    assert fallback.to_dict()["local_model"] == {"note": "no ground plane: post.ground_model skipped"}
    assert not GroundFacts() and GroundFacts().to_dict() == {}


# -- 8. the result record: read once, versioned, positioned errors ---------------------------------------


def _where(text: str, key: str, value: str, after: str | None = None) -> str:
    """'line:col' (1-based) of ``"key": value`` in ``text`` (the first after the line holding ``after``)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if f'"{after}"' in line) + 1 if after else 0
    pair = f'"{key}": {value}'
    i = next(i for i in range(start, len(lines)) if pair in lines[i])
    return f"{i + 1}:{lines[i].index(pair) + len(key) + 5}"


@pytest.mark.parametrize("where", ["result", "explanation"])
def test_a_result_of_a_future_version_is_refused_at_the_position_of_its_version(example, tmp_path, capsys, where):
    folder = tmp_path / where
    folder.mkdir()
    shutil.copy(example.with_suffix(".ply"), folder / "outdoor.ply")
    doc = json.loads(example.read_text())
    (doc if where == "result" else doc["explanation"])["version"] = "3.1"
    js = folder / "outdoor.json"
    js.write_text(json.dumps(doc, indent=1))  # one key a line: the version is not on line 1
    at = _where(js.read_text(), "version", '"3.1"', after=None if where == "result" else "explanation")
    assert int(at.split(":")[0]) > 1
    code, out, err = _explain(capsys, js)
    kind = "kbs-result" if where == "result" else "kbs-explanation"
    assert code == 3 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert f"error: {js}:{at}: " in err, err
    assert f"written by a newer kbs ({kind} version 3.1; this kbs reads 1.x): upgrade kbs to read it" in err


def test_a_result_field_of_the_wrong_type_is_refused_at_its_position(example, tmp_path, capsys):
    folder = tmp_path / "bad"
    folder.mkdir()
    shutil.copy(example.with_suffix(".ply"), folder / "outdoor.ply")
    doc = json.loads(example.read_text())
    doc["label_names"] = "ground,obstacle"
    js = folder / "outdoor.json"
    js.write_text(json.dumps(doc, indent=1))
    at = _where(js.read_text(), "label_names", '"ground,obstacle"')
    code, out, err = _explain(capsys, js)
    assert code == 3 and out == ""
    assert f"{js}:{at}: not a kbs result file ('label_names' is not a list of names)" in err
    assert main(["eval", str(js.with_suffix(".ply")), "field:label_in", "--ground-values", "0", "--no-hoover"]) == 3
    assert f"{js}:{at}: not a kbs result file ('label_names' is not a list of names)" in capsys.readouterr().err


def test_the_result_record_holds_what_readers_use(example):
    import dataclasses

    from kbs.formats import Version
    from kbs.io import ResultDoc, read_result
    from kbs.knowledge import Explanation

    raw = json.loads(example.read_text())
    doc = read_result(example)
    assert isinstance(doc, ResultDoc) and doc.version == Version(1, 1) and doc.path == example
    assert doc.label_names == ("ground", "obstacle") and doc.rule_base == "outdoor" and doc.input == raw["input"]
    assert doc.run_id == raw["run_id"] and len(doc.clusters) == len(raw["clusters"]) and doc.sensor == (0.0, 0.0, 0.0)
    assert Explanation.from_result(doc).to_dict() == raw["explanation"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        doc.label_names = ()  # type: ignore[misc]
    at = doc.position("explanation", "root")  # compact JSON: on line 1, at the root's id
    col = int(at.rsplit(":", 1)[1])
    assert at.startswith(f"{example}:1:") and example.read_text()[col - 1:col + 2] == '"c"'
    assert doc.position("no such key") == str(example)


def test_a_record_evolved_is_the_record_dataclasses_replace_gives():
    """ClusterRecord.evolve, the run's cheap copy of a record with changes: equal to
    dataclasses.replace field by field, lists kept as tuples, an unknown field refused."""
    from dataclasses import replace

    from kbs.knowledge.explain import ClusterRecord

    r = ClusterRecord(id="c0.1", parent="c0", depth=2, n_points=100, descriptors={"a": 1}, notes=("x",))
    for changes in ({"label": "ground"}, {"notes": ["a", "b"]}, {"checks": [], "decisive": ["planar"]},
                    {"children": ("c0.1.0",), "action": "split"}, {}):
        a, b = replace(r, **changes), r.evolve(**changes)
        assert a == b and a.__dict__ == b.__dict__ and b is not r
        assert all(isinstance(getattr(b, name), tuple) for name in ("checks", "children", "notes", "decisive"))
    assert r.label is None and r.notes == ("x",)  # the original unchanged
    assert r.noted("y").notes == ("x", "y")
    with pytest.raises(TypeError, match="no field 'nope'"):
        r.evolve(nope=1)


def test_a_patch_no_relabel_rule_took_keeps_the_values_that_decided_it():
    """rules/airborne.yaml has two relabel steps: the roof rules (ground -> object), then the rough
    bits (object -> ground). The second forgets the surface checks of the clusters it judges, to
    measure them on its own surface; a ground patch it does not judge keeps what the first step
    measured, so the explanation says which roof check failed, not 'not evaluated' (before session
    42 the second step forgot them on every cluster)."""
    from kbs.knowledge import Interpreter, load_rule_base
    from scenes import airborne_step_and_building

    X, _ = airborne_step_and_building()
    rb = load_rule_base("airborne")
    assert [s.key for s in rb.post].count("relabel") == 2
    seg = Interpreter(rb).run(X)
    roof_checks = {"edge_raised", "raised", "above_terrain"}
    kept = [r for r in seg.explanation.records.values()
            if r.label == "ground" and r.first_label == "ground" and not r.relabel and r.output_index is not None]
    assert kept
    for rec in kept:
        assert roof_checks <= {c.check for c in rec.checks}, rec.id
        why = seg.explanation.why(rec.id)
        lines = why[why.index("post.relabel, the rules for clusters labelled ground"):].splitlines()
        large = next(ln for ln in lines if ln.strip().startswith("large_roofs ["))
        assert "does not hold: edge_raised does not hold (edge_drop = " in large, large
        assert not any("not evaluated" in ln for ln in lines if "ground -> object" in ln), why
