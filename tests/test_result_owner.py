"""One owner of the result files (the PLY/JSON pair): kbs.io.result. Every command that reads a
result reads it there, and says the same thing of a result cloud without its fields."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from kbs.io.result import read_result_cloud, write_result_cloud

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "data" / "outdoor.ply"

#: The modules outside io/ that parse JSON, each with what it parses (none of them a result file).
#: A new module parsing JSON fails the test below: a result is read through kbs.io.result
#: (read_result_json, read_result_pair); anything else is added here with what it reads.
JSON_READERS = {
    "knowledge/rulebase.py": "the rule files' JSON Schema",
    "inference/_aot.py": "the table of the kernels built ahead of time (kbs.inference._aot writes it)",
    "maps/files.py": "a map's index, map.json (kbs.maps owns the map files)",
    "maps/poses.py": "a poses file",
    "synth/drive.py": "a generated drive's truth.json",
    "tiles/store.py": "a finished tile's document inside the tile store's spill file (not a result pair)",
    "tiles/streamed.py": "a finished tile's document inside the tile store's spill file (not a result pair)",
    "benchmarks/bench_compare.py": "the timing line a child process prints",
    "benchmarks/profile_run.py": "the child process's progress and timing lines, its spec file",
}
#: The literals of the result format that only kbs.io.result (and kbs.formats) may spell.
FORMAT_LITERALS = {"scalar_cluster", "scalar_label", "scalar_membership", "kbs-result", "result_format",
                   "kbs_run_id"}


def _modules() -> list[Path]:
    # build/: the copy of the package a non-editable pip install leaves in the repository (CI makes one)
    skip = {"tests", "kbs.egg-info", "io", "build", "dist"}
    return [p for p in sorted(ROOT.rglob("*.py")) if not skip & set(p.relative_to(ROOT).parts[:1])
            and not p.relative_to(ROOT).parts[0].startswith(".") and "site-packages" not in p.parts]


def test_only_the_listed_modules_parse_json_and_none_of_them_a_result():
    found = set()
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ("load", "loads")
                    and isinstance(node.func.value, ast.Name) and node.func.value.id == "json"):
                found.add(path.relative_to(ROOT).as_posix())
    assert found - set(JSON_READERS) == set(), "read a result JSON through kbs.io.result, or list what this parses"
    assert set(JSON_READERS) - found == set(), "listed but no longer parsing JSON: take it off the list"


def test_no_module_outside_io_spells_the_result_formats_names():
    spelled = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and node.value in FORMAT_LITERALS:
                spelled.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}")
    assert not spelled, "use kbs.io.result's names (PLY_NAMES, RESULT_FORMAT, RUN_ID_COMMENT): " + "; ".join(spelled)


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("result")
    assert main(["-q", "run", "--rules", "outdoor", "-j", "1", str(EXAMPLE), "--out", str(out)]) == 0
    return out / "outdoor.json"


def _without(result: Path, field: str, folder: Path) -> Path:
    """A copy of the pair whose cloud lacks one result field (same run id: still one result)."""
    doc = json.loads(result.read_text())
    cloud = read_result_cloud(result.with_suffix(".ply"))
    fields = {k: np.asarray(v) for k, v in cloud.fields.items() if k != field}
    js = folder / "outdoor.json"
    js.write_text(result.read_text())
    write_result_cloud(folder / "outdoor.ply", cloud.xyz, fields, run_id=doc["run_id"])
    return js


MISSING = "not a kbs result: no per-vertex '{}' field (write one with kbs run)"


def test_render_and_eval_say_the_same_of_a_cloud_without_its_labels(result, tmp_path, capsys):
    js = _without(result, "label", tmp_path)
    capsys.readouterr()
    assert main(["render", str(js), "--kind", "map", "--out", str(tmp_path / "m.png")]) == 3
    err = capsys.readouterr().err
    assert err == f"kbs: error: {js.with_suffix('.ply')}: {MISSING.format('label')}\n"
    assert main(["eval", str(js.with_suffix(".ply")), "field:label_in", "--ground-values", "0", "--no-hoover"]) == 3
    assert capsys.readouterr().err.endswith(f"{js.with_suffix('.ply')}: {MISSING.format('label')}\n")
    assert not (tmp_path / "m.png").exists()


def test_eval_and_segcomp_say_the_same_of_a_cloud_without_its_clusters(result, tmp_path, capsys):
    js = _without(result, "cluster", tmp_path)
    ply = js.with_suffix(".ply")
    capsys.readouterr()
    assert main(["eval", str(ply), "field:label_in", "--ground-values", "0", "--no-hoover"]) == 3
    assert capsys.readouterr().err.endswith(f"{ply}: {MISSING.format('cluster')}\n")
    assert main(["segcomp", str(ply), "--image", str(tmp_path / "scan.range")]) == 3  # refused before the image
    assert capsys.readouterr().err.endswith(f"{ply}: {MISSING.format('cluster')}\n")


@pytest.mark.slow  # a tiled, streamed run with its page and meshes (about 10 s)
def test_a_streamed_result_is_read_back_through_io_for_its_page_and_meshes(tmp_path):
    """A streamed LAS run writes its result in pieces, then reads it back (read_result_json) for
    the page and the meshes: they hold every cluster the JSON does."""
    import laspy

    from scenes import ground_and_rocks

    X, _ = ground_and_rocks()
    scan = tmp_path / "rocks.las"
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(X.min(axis=0)), np.array([1e-4, 1e-4, 1e-4])
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.write(str(scan))
    out = tmp_path / "out"
    assert main(["-q", "run", "--rules", "outdoor", "-j", "1", "--tile", "6", "--buffer", "1.5", "--chunk-points",
                 "4000", "--report", "--meshes", str(scan), "--out", str(out)]) == 0
    doc = json.loads((out / "rocks.json").read_text())
    assert doc["clusters"] and (out / "rocks.html").stat().st_size > 0
    meshes = sorted((out / "rocks-meshes").iterdir())
    assert meshes, "no mesh written"
