"""A hand-edited result JSON read by `kbs explain` (and `kbs render`): every field the readers use
is checked once where the explanation is read (kbs.knowledge.explain_schema), so that a wrong type,
a missing key or a broken cluster tree (a cycle, a dangling or duplicate id) is an input error at
its position (exit 3, one line naming the file, line:col and the JSON path), never an internal
error (exit 1) nor a hang. A fuzzing pass found 103 distinct internal errors and a hang (a cluster
its own child) before the check."""
from __future__ import annotations

import copy
import json
import shutil
import signal
from pathlib import Path

import pytest

from kbs.cli.main import main
from test_cli import EXAMPLE


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("example")
    assert main(["-q", "run", "--rules", "outdoor", "-j", "1", str(EXAMPLE), "--out", str(out)]) == 0
    return out / "outdoor.json"


@pytest.fixture(scope="module")
def raw(example) -> dict:
    return json.loads(example.read_text())


class _Hang(Exception):
    pass


def _run(capsys, *args: str, seconds: int = 30) -> tuple[int, str, str]:
    """kbs ARGS in this process; a run longer than ``seconds`` fails the test (a hang)."""
    def hang(*_):
        raise _Hang(f"kbs {' '.join(args)} ran for more than {seconds} s")

    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(seconds)
    capsys.readouterr()
    try:
        code = main(list(args))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    got = capsys.readouterr()
    return code, got.out, got.err


def _pair(example: Path, folder: Path, doc: dict) -> Path:
    folder.mkdir()
    shutil.copy(example.with_suffix(".ply"), folder / "outdoor.ply")
    js = folder / "outdoor.json"
    js.write_text(json.dumps(doc, indent=1))  # a value a line: positions are not all on line 1
    return js


def _at(js: Path, err: str) -> str:
    """The text of ``js`` at the position the one-line error names (file:line:col: ...)."""
    where = err.split("kbs: error: ", 1)[1].split(": ", 1)[0]
    name, line, col = where.rsplit(":", 2)
    assert name == str(js), err
    return js.read_text().splitlines()[int(line) - 1][int(col) - 1:]


def _leaf(doc: dict) -> int:
    return next(i for i, c in enumerate(doc["explanation"]["clusters"]) if not c["children"])


def _inner(doc: dict) -> int:
    return next(i for i, c in enumerate(doc["explanation"]["clusters"]) if c["children"] and i > 0)


def _set(doc: dict, path: tuple, value) -> None:
    d = doc
    for k in path[:-1]:
        d = d[k]
    if value is _DEL:
        del d[path[-1]]
    else:
        d[path[-1]] = value


_DEL = object()

#: (where, value, the problem said, the text at the position named: the bad value or its object)
WRONG = [
    (("explanation", "label_names", 0), None, "explanation.label_names[0]: expected a string, got null", "null"),
    (("explanation", "label_names", 0), 5, "explanation.label_names[0]: expected a string, got 5", "5"),
    (("explanation", "root"), None, "explanation.root: expected a string, got null", "null"),
    (("explanation", "root"), "zz", "explanation.root: no cluster has the root's id 'zz'", '"zz"'),
    (("explanation", "ground"), "x", "explanation.ground: expected an object or null, got \"x\"", '"x"'),
    (("explanation", "ground", "normal", 0), "x", 'explanation.ground.normal[0]: expected a number, got "x"', '"x"'),
    (("explanation", "ground", "normal"), [1, 2], "explanation.ground.normal: expected 3 numbers, got a list", "["),
    (("explanation", "catalogue", "checks", 0, "predicate"), _DEL,
     "explanation.catalogue.checks[0]: missing key 'predicate'", "{"),
    (("explanation", "catalogue", "labels", 0, "condition"), {"all": ["a"], "any": []},
     "explanation.catalogue.labels[0].condition: expected a condition", "{"),
    (("explanation", "clusters", 0, "apd", "apd", 0), {}, "explanation.clusters[0].apd.apd[0]: expected a number or "
                                                          "null, got an empty object", "{}"),
    (("explanation", "clusters", 0, "depth"), 1e308, "explanation.clusters[0].depth: expected an integer, got 1e+308",
     "1e+308"),
    (("explanation", "clusters", 1, "n_points"), True, "explanation.clusters[1].n_points: expected an integer, got true",
     "true"),
    (("explanation", "clusters", 1, "n_points"), -1, "explanation.clusters[1].n_points: expected 0 or more, got -1",
     "-1"),
    (("explanation", "clusters", 1, "checks", 0, "max"), None,
     "explanation.clusters[1].checks[0]: expected a check with a bound (min or max a number)", "{"),
    (("explanation", "sweep"), None, "explanation.sweep: expected a list, got null", "null"),
    (("explanation", "clusters"), [], "explanation.clusters: expected a list of cluster records, got an empty list",
     "[]"),
]


@pytest.mark.parametrize("path, value, problem, text", WRONG, ids=[f"{'.'.join(map(str, w[0][1:]))}="
                                                                   + ("<deleted>" if w[1] is _DEL else repr(w[1]))
                                                                   for w in WRONG])
def test_a_wrong_field_of_the_explanation_is_an_input_error_at_its_position(example, raw, tmp_path, capsys,
                                                                            path, value, problem, text):
    doc = copy.deepcopy(raw)
    _set(doc, path, value)
    js = _pair(example, tmp_path / "bad", doc)
    code, out, err = _run(capsys, "explain", str(js))
    assert code == 3 and out == "" and err.count("\n") == 1 and "internal error" not in err, err
    assert f"not a kbs result file ({problem}" in err, err
    assert _at(js, err).startswith(text), (err, _at(js, err)[:40])


def _cycle_self(doc):  # the fuzzer's hang: the root listed as its own child
    doc["explanation"]["clusters"][0]["children"][0] = doc["explanation"]["root"]
    return "explanation.clusters[0].children[0]: cluster 'c' is listed as its own child (a cycle)"


def _cycle_below(doc):  # an inner cluster listed again below one of its leaves
    cl = doc["explanation"]["clusters"]
    inner = cl[_inner(doc)]
    leaf = next(i for i, c in enumerate(cl) if c["parent"] == inner["id"] and not c["children"])
    cl[leaf]["children"] = [inner["id"]]
    return (f"explanation.clusters[{leaf}].children[0]: cluster {inner['id']!r} is listed as a child of its "
            f"descendant {cl[leaf]['id']!r} (a cycle)")


def _dangling(doc):
    leaf = _leaf(doc)
    doc["explanation"]["clusters"][leaf]["children"] = ["nope"]
    return f"explanation.clusters[{leaf}].children[0]: no cluster has the id 'nope'"


def _duplicate(doc):
    cl = doc["explanation"]["clusters"]
    leaf, inner = max(_leaf(doc), _inner(doc)), min(_leaf(doc), _inner(doc))
    cl[leaf]["id"] = cl[inner]["id"]
    return f"explanation.clusters[{leaf}].id: cluster id {cl[inner]['id']!r} is also that of clusters[{inner}]"


def _parent(doc):
    leaf = _leaf(doc)
    cl = doc["explanation"]["clusters"]
    cl[leaf]["parent"] = cl[leaf]["id"]  # the parent walk of --cluster would loop
    return f"explanation.clusters[{leaf}].parent: cluster {cl[leaf]['id']!r} is a child of"


def _depth(doc):
    leaf = _leaf(doc)
    doc["explanation"]["clusters"][leaf]["depth"] = 10 ** 12  # indented by 2 x 10^12 spaces
    return f"explanation.clusters[{leaf}].depth: cluster"


def _orphan(doc):
    cl = doc["explanation"]["clusters"]
    cl[0]["children"] = cl[0]["children"][1:]
    return "is not in the tree under the root 'c'"


@pytest.mark.parametrize("edit", [_cycle_self, _cycle_below, _dangling, _duplicate, _parent, _depth, _orphan])
def test_a_broken_cluster_tree_is_an_input_error_not_a_hang(example, raw, tmp_path, capsys, edit):
    doc = copy.deepcopy(raw)
    problem = edit(doc)
    js = _pair(example, tmp_path / "bad", doc)
    for args in (["explain", str(js)], ["explain", str(js), "--cluster", doc["explanation"]["clusters"][-1]["id"]],
                 ["render", str(js), "--kind", "cah", "--cluster", "c0", "--out", str(tmp_path / "c.png")]):
        code, out, err = _run(capsys, *args)
        assert code == 3 and out == "" and "internal error" not in err, (args, err)
        assert problem in err and f"error: {js}:" in err, (args, err)
    assert not (tmp_path / "c.png").exists()


def test_render_reads_the_explanation_through_the_same_check(example, raw, tmp_path, capsys):
    doc = copy.deepcopy(raw)
    doc["explanation"]["ground"]["normal"] = ["up", 0, 1]
    js = _pair(example, tmp_path / "bad", doc)
    code, _, err = _run(capsys, "render", str(js), "--kind", "map", "--out", str(tmp_path / "m.png"))
    assert code == 3 and 'explanation.ground.normal[0]: expected a number, got "up"' in err, err
    assert _at(js, err).startswith('"up"')


def test_every_explanation_kbs_writes_passes_the_check(example, raw, tmp_path):
    """The divisive outdoor run, a global-strategy run and a tiled run: their explanations pass."""
    from kbs.knowledge.explain_schema import check_explanation

    check_explanation(raw["explanation"])
    polyhedral = EXAMPLE.parent / "polyhedral.ply"
    for name, args in [("global", ["--rules", "planar_global", str(polyhedral)]),
                       ("tiled", ["--rules", "outdoor", "--tile", "8", str(EXAMPLE)])]:
        out = tmp_path / name
        assert main(["-q", "run", "-j", "1", *args, "--out", str(out)]) == 0, name
        (js,) = out.glob("*.json")
        expl = json.loads(js.read_text())["explanation"]
        assert name != "global" or expl.get("sweep"), "a global-strategy run records its sweep"
        assert name != "tiled" or any("/" in c["id"] for c in expl["clusters"]), "a tiled run's records"
        check_explanation(expl)


def test_the_check_says_what_jsonschema_says_of_its_schema(raw):
    """SCHEMA is a JSON Schema (draft 2020-12) that uses only the keywords the fast check knows, and
    jsonschema (its integers JSON integers) finds the same documents valid, field by field mutated."""
    from jsonschema import Draft202012Validator, validators

    from kbs.jsoncheck import compile_schema
    from kbs.knowledge.explain_schema import SCHEMA

    Draft202012Validator.check_schema(SCHEMA)
    first_error = compile_schema(SCHEMA)  # refuses a schema with a keyword it does not know
    with pytest.raises(ValueError, match="keywords this check does not know: .'pattern'."):
        compile_schema({"type": "object", "properties": {"a": {"type": "string", "pattern": "^x"}}})
    checker = Draft202012Validator.TYPE_CHECKER.redefine("integer",
                                                         lambda _, v: isinstance(v, int) and not isinstance(v, bool))
    strict = validators.extend(Draft202012Validator, type_checker=checker)(SCHEMA)
    base = raw["explanation"]
    paths: list[tuple] = []

    def walk(v, p):
        paths.append(p)
        if isinstance(v, dict):
            for k in v:
                walk(v[k], (*p, k))
        elif isinstance(v, list) and v:
            walk(v[0], (*p, 0))

    walk(base, ())
    n_bad = 0
    for p in paths[1:]:
        for value in (_DEL, None, "x", -1, [], {}, 1.5, True):
            doc = copy.deepcopy(base)
            _set(doc, p, value)
            ours = first_error(doc)
            assert (ours is None) == strict.is_valid(doc), (p, value, ours)
            n_bad += ours is not None
    assert n_bad > 500


@pytest.mark.parametrize("path, value, problem", [
    (("clusters", 0, "index"), None, "clusters[0].index: expected an integer, got null"),
    (("clusters", 0, "descriptors", "center"), [], "clusters[0].descriptors.center: expected 3 numbers within "
                                                   "+-1e50, got an empty list"),
    (("clusters", 0, "descriptors", "center", 2), 1e308, "clusters[0].descriptors.center[2]: expected 1e+50 or less"),
    (("clusters", 0, "descriptors", "eigenvalues"), None, "clusters[0].descriptors.eigenvalues: expected 3 numbers"),
])
def test_render_refuses_an_output_cluster_of_the_wrong_form_at_its_position(example, raw, tmp_path, capsys,
                                                                            path, value, problem):
    """The result's own `clusters` (kbs render --kind clusters draws their descriptors): were only
    checked to be objects, then crashed the figure (exit 1)."""
    doc = copy.deepcopy(raw)
    _set(doc, path, value)
    js = _pair(example, tmp_path / "bad", doc)
    code, out, err = _run(capsys, "render", str(js), "--kind", "clusters", "--out", str(tmp_path / "c.png"))
    assert code == 3 and "internal error" not in err and f"not a kbs result file ({problem}" in err, err
    assert _at(js, err).startswith(json.dumps(value)[:1])
    assert not (tmp_path / "c.png").exists()
