"""Rule files a user (or an attacker) can write that used to hang, blow the memory, crash with a
traceback or pass unnoticed: alias bombs, non-finite numbers, deep nesting, huge files, bytes that
are not UTF-8, conditions that can never hold. Each is refused (or warned about) with its position,
through the real command."""
from __future__ import annotations

import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kbs.cli.main import main
from kbs.knowledge import PredicateRegistry, RuleFileError
from kbs.knowledge.rulebase import (
    MAX_ALIAS_NODES,
    MAX_CONDITION_DEPTH,
    MAX_NESTING,
    MAX_RULE_FILE_BYTES,
    parse_rule_base,
)

ROOT = Path(__file__).resolve().parents[1]
OUTDOOR = (ROOT / "rules" / "outdoor.yaml").read_text(encoding="utf-8")
EXAMPLE = ROOT / "examples" / "data" / "outdoor.ply"

MINIMAL = """\
kbs_rules: 1
name: t
units: m
strategy: divisive
checks:
  planar: {predicate: thickness, max: 0.05}
rules:
  - name: PAh
    if: not planar
    then: split
labels:
  - {name: plane}
"""


def check(capsys, *files: Path | str) -> tuple[int, str, str]:
    """`kbs rules check FILES` through the real entry point, in-process: (exit code, stdout, stderr)."""
    code = main(["rules", "check", *map(str, files)])
    out = capsys.readouterr()
    return code, out.out, out.err


def write(tmp_path: Path, text: str, name: str = "t.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def line_col(text: str, needle: str, nth: int = 0) -> str:
    """'line:col' (1-based) of the nth occurrence of needle in text."""
    i = -1
    for _ in range(nth + 1):
        i = text.index(needle, i + 1)
    line = text.count("\n", 0, i) + 1
    return f"{line}:{i - (text.rfind(chr(10), 0, i) + 1) + 1}"


# --- 1. alias bombs ------------------------------------------------------------------------------


def billion_laughs(levels: int = 9, width: int = 9) -> str:
    """~1 KB of YAML whose aliases expand to width**levels nodes."""
    out = [f"a0: &a0 [{', '.join(['lol'] * width)}]"]
    for i in range(1, levels):
        out.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(out) + "\n"


def _limited() -> None:  # in the child: 1.5 GB of address space at most (the bomb wanted > 5 GB)
    resource.setrlimit(resource.RLIMIT_AS, (3 << 29, 3 << 29))


def kbs_limited(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """The real command in a child with a memory limit and a timeout: a regression fails the test
    (MemoryError: exit 1; a hang: TimeoutExpired) instead of taking the machine down."""
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert exe, "the kbs command is not installed"
    env = {**os.environ, "KBS_JIT": "0"}  # no compiled kernels needed to refuse a rule file
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=timeout, preexec_fn=_limited,
                          env=env)


def billion_laughs_inline(levels: int = 9, width: int = 9) -> str:
    """The same, as one flow list: every level anchored inside it."""
    out = [f"&a0 [{', '.join(['lol'] * width)}]"]
    for i in range(1, levels):
        out.append(f"&a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "[" + ", ".join(out) + "]"


def first_alias_past_the_bound(levels: int = 9, width: int = 9) -> tuple[int, int]:
    """(level k, index j): the j-th alias *a{k-1} is the first whose expansion crosses the bound;
    every *aK repeats (width**(K+2) - 1) / (width - 1) nodes."""
    sizes, total = [(width ** (k + 2) - 1) // (width - 1) for k in range(levels)], 0
    for k in range(1, levels):
        for j in range(width):
            total += sizes[k - 1]
            if total > MAX_ALIAS_NODES:
                return k, j
    raise AssertionError("the bomb is too small")


@pytest.mark.slow
@pytest.mark.parametrize("where", ["top", "inline"])
def test_an_alias_bomb_is_refused_at_the_alias_that_crosses_the_bound(tmp_path, where):
    if where == "top":  # unknown keys: the old code walked the expanded tree to position them
        bomb = billion_laughs()
        text = OUTDOOR + bomb
    else:  # a check's doc, which the schema wants a string: the old message quoted the expansion
        bomb = billion_laughs_inline()
        text = OUTDOOR.replace("doc: a point alone in a cluster of its own, neither ground nor an obstacle", f"doc: {bomb}")
    assert len(bomb) < 1100 and bomb in text
    path = write(tmp_path, text, "bomb.yaml")
    k, j = first_alias_past_the_bound()
    expected = f"bomb.yaml:{line_col(text, f'*a{k - 1}', j)}: alias *a{k - 1} "
    for args in (["rules", "check", str(path)],
                 ["run", "--rules", str(path), "-j", "1", str(EXAMPLE), "--out", str(tmp_path / "out")]):
        t0 = time.perf_counter()
        r = kbs_limited(*args)
        assert r.returncode == 4, r.stderr[-2000:]
        assert "Traceback" not in r.stderr
        assert expected in r.stderr and f"more than {MAX_ALIAS_NODES:,} nodes" in r.stderr, r.stderr
        assert time.perf_counter() - t0 < 60  # in practice the time Python takes to start (it never ended)
    assert not (tmp_path / "out").exists()


def test_aliases_within_the_bound_still_load_as_written_out():
    """An anchor reused for a condition or parameters is ordinary YAML: it loads as if written out."""
    aliased = (OUTDOOR.replace("params: {alpha_factor: 3.0, min_fraction: 0.05}",
                               "params: &conn {alpha_factor: 3.0, min_fraction: 0.05}")
               .replace("  tiny:\n", "  also_connected: {predicate: connexity, params: *conn, max: 1}\n  tiny:\n")
               .replace("    if: [planar, level]", "    if: &flat [planar, level]")
               .replace("  - name: obstacle", "  - name: obstacle\n    if: {any: [*flat, not planar]}"))
    assert aliased.count("*conn") == aliased.count("*flat") == 1
    reg = PredicateRegistry.default()
    a = parse_rule_base(aliased, "a.yaml", reg)
    assert a.checks["also_connected"].params == a.checks["connected"].params == {"alpha_factor": 3.0,
                                                                                 "min_fraction": 0.05}
    assert str(a.labels[0].condition) == "planar and level"
    assert str(a.labels[1].condition) == "(planar and level) or not planar"


def test_a_recursive_alias_is_refused_with_its_position(tmp_path, capsys):
    text = MINIMAL.replace("  - {name: plane}", "  - &me {name: plane, doc: [*me]}")
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err
    assert f"t.yaml:{line_col(text, '*me')}: alias *me is inside the node it names" in err


# --- 2. non-finite numbers -----------------------------------------------------------------------


@pytest.mark.parametrize("old, new, value", [
    ("max: 0.05                  # m", "max: .nan", ".nan"),
    ("max: 22.5                  # degrees", "max: .inf", ".inf"),
    ("max: 1                     # not 15", "max: -.inf  # not 15", "-.inf"),
    ("sensor: [0, 0, 0]", "sensor: [.inf, 0, 0]", ".inf"),
    ("fallback: [0, 0, 1]", "fallback: [0, 0, .NaN]", ".NaN"),
    ("normal: auto ", "normal: [0, 0, -.Inf]", "-.Inf"),
    ("max_offset: 0.15", "max_offset: .nan", ".nan"),
    ("tolerance: 0.10", "tolerance: .inf", ".inf"),
    ("radius: 3.0", "radius: 1.0e+999", "1.0e+999"),  # overflows to inf
    ("m: 2.0", "m: .nan", ".nan"),
])
def test_non_finite_numbers_are_refused_with_their_position(tmp_path, capsys, old, new, value):
    assert old in OUTDOOR
    text = OUTDOOR.replace(old, new, 1)
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err, err
    assert f"t.yaml:{line_col(text, value)}: {value} is not a finite number" in err


def test_non_finite_numbers_are_all_reported_and_no_run_starts(tmp_path, capsys):
    text = OUTDOOR.replace("max: 0.05                  # m", "max: .nan").replace("sensor: [0, 0, 0]",
                                                                                  "sensor: [0, .inf, 0]")
    path = write(tmp_path, text)
    code, out, err = check(capsys, path)
    assert code == 4 and err.count("is not a finite number") == 2
    assert main(["run", "--rules", str(path), "-j", "1", str(EXAMPLE), "--out", str(tmp_path / "out")]) == 4
    assert not (tmp_path / "out").exists()


def test_an_integer_too_large_for_a_float_is_refused(tmp_path, capsys):
    digits = "9" * 400
    text = OUTDOOR.replace("max: 1                     # not 15", f"max: {digits}  # not 15")
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err
    assert f"t.yaml:{line_col(text, digits)}: 999999999999...999999999999 (400 digits) is too large" in err


# --- 3. deep nesting, huge files, linear validation -----------------------------------------------


def nested(levels: int, form: str) -> str:
    cond = "planar"
    for _ in range(levels):
        cond = f"{{all: [{cond}]}}" if form == "dict" else f"[{cond}]"
    return cond


@pytest.mark.parametrize("form", ["dict", "list"])
def test_a_condition_nested_150_levels_deep_is_a_positioned_error(tmp_path, capsys, form):
    text = MINIMAL.replace("if: not planar", f"if: {nested(150, form)}")
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err and "RecursionError" not in err
    # the first node beyond the bound: the 'if' value is at depth 4 (rule base > rules > rule >
    # if), each opener one level deeper; in {all: [...]}, the key 'all' is one level below its '{'
    base = text.index("if: ")
    openers = [j for j in range(base, len(text)) if text[j] in "{["]
    i = openers[MAX_NESTING - 3] if form == "list" else openers[MAX_NESTING - 4] + 1
    assert f"t.yaml:9:{i - text.rfind(chr(10), 0, i)}: nested more than {MAX_NESTING} levels deep" in err, err


@pytest.mark.parametrize("form", ["dict", "list"])
def test_conditions_may_nest_32_levels_not_33(tmp_path, capsys, form):
    assert MAX_CONDITION_DEPTH == 32
    ok = write(tmp_path, MINIMAL.replace("if: not planar", f"if: {nested(32, form)}"), "ok.yaml")
    code, out, err = check(capsys, ok)
    assert code == 0, err
    text = MINIMAL.replace("if: not planar", f"if: {nested(33, form)}")
    code, out, err = check(capsys, write(tmp_path, text, "deep.yaml"))
    assert code == 4 and "Traceback" not in err
    i = [j for j in range(text.index("if: "), len(text)) if text[j] == ("{" if form == "dict" else "[")][32]
    assert f"deep.yaml:9:{i - text.rfind(chr(10), 0, i)}: condition nested more than 32 levels deep" in err, err


def test_a_rule_file_over_1_mb_is_refused_before_it_is_read(tmp_path, capsys):
    path = write(tmp_path, MINIMAL + "# " + "x" * MAX_RULE_FILE_BYTES + "\n", "huge.yaml")
    code, out, err = check(capsys, path)
    assert code == 4 and "Traceback" not in err
    assert f"huge.yaml:1:1: the file is {path.stat().st_size:,} bytes; a rule file may have at most " \
           f"{MAX_RULE_FILE_BYTES:,}" in err
    with pytest.raises(RuleFileError, match="a rule file may have at most"):  # the library, given the text
        parse_rule_base(path.read_text(), "huge.yaml", PredicateRegistry.default())


def many_rules(n: int) -> str:
    """A valid rule file with n rules (the old code looked each one up in the list of rules)."""
    out = ["kbs_rules: 1", "name: big", "units: m", "strategy: divisive", "checks:",
           "  c: {predicate: thickness, max: 0.05}", "rules:"]
    out += [f"  - {{name: r{i}, if: c, then: split}}" for i in range(n)]
    return "\n".join(out + ["labels:", "  - {name: other}"]) + "\n"


@pytest.mark.slow
def test_validation_time_grows_linearly_with_the_rule_file(monkeypatch):
    """8 x the rules takes about 8 to 12 x the CPU time (it took 44 x, 74 s for 20,000 rules).
    Best of three runs each (CPU time: other processes on the machine count less), a wide margin,
    and the large file is not timed again once it took too long. Every run validates in full: the
    files known to pass the schema are not remembered here (the small file's second and third runs
    skipped the schema, the large file's first did not, and CI once measured 26 x that way)."""
    from kbs.knowledge.rulebase import _KnownValid

    monkeypatch.setattr(_KnownValid, "known", classmethod(lambda cls, key: False))
    monkeypatch.setattr(_KnownValid, "add", classmethod(lambda cls, key: None))
    reg = PredicateRegistry.default()

    def cpu(text: str) -> float:
        t0 = time.process_time()
        parse_rule_base(text, "big.yaml", reg)
        return time.process_time() - t0

    small, large = many_rules(2500), many_rules(20000)
    assert len(large.encode()) < MAX_RULE_FILE_BYTES
    t_small = min(cpu(small) for _ in range(3))
    t_large = cpu(large)
    if t_large < 20 * t_small:
        t_large = min(t_large, cpu(large))
    assert t_large / t_small < 20, (t_small, t_large)


# --- 4. bytes that are not UTF-8, characters YAML refuses -----------------------------------------


def test_a_byte_that_is_not_utf8_is_located_by_line_and_column(tmp_path, capsys):
    path = tmp_path / "latin1.yaml"
    text = MINIMAL.replace("units: m", "description: Régles de l'été\nunits: m")
    path.write_bytes(text.encode("latin-1"))
    code, out, err = check(capsys, path)
    assert code == 4 and "Traceback" not in err
    assert "latin1.yaml:3:15: not UTF-8: byte 0xe9 cannot be decoded" in err, err
    assert "description: R\ufffdgles de l'\ufffdt\ufffd\n" + " " * (4 + 14) + "^" in err  # the line, a caret under it


def test_a_character_yaml_refuses_is_located_by_line_and_column(tmp_path, capsys):
    text = MINIMAL.replace("units: m", "units: m\ndescription: a\x07b")
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err
    assert "t.yaml:4:15: YAML: unacceptable character #x0007" in err, err


def test_an_impossible_date_is_a_positioned_error(tmp_path, capsys):
    text = MINIMAL.replace("units: m", "units: m\ndescription: 2021-02-30")
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err
    assert "t.yaml:4:14: cannot read 2021-02-30: day is out of range for month" in err, err


# --- 5. conditions that can never hold; clusters no label matched -------------------------------

WARN_BASE = """\
kbs_rules: 1
name: t
units: m
strategy: divisive
scene: {ground: {normal: [0, 0, 1]}}
checks:
  planar: {predicate: thickness, max: 0.05}
  thick: {predicate: thickness, min: 5}
  thin: {predicate: thickness, max: 3}
  anything: {predicate: thickness, min: 0}
  level: {predicate: ground_angle, max: 22.5}
  upright: {predicate: ground_angle, min: 90}
  one_piece: {predicate: connexity, max: 1}
  pieces: {predicate: connexity, params: {alpha_factor: 3.0}, min: 2}
  pieces_coarse: {predicate: connexity, params: {alpha_factor: 5.0}, min: 2}
  just_one: {predicate: connexity, min: 1, max: 1}
  some: {predicate: connexity, min: 1}
rules:
  - {name: R, if: COND, then: split}
labels:
  - {name: plane}
"""


@pytest.mark.parametrize("cond, why", [
    ("[thick, thin]", "'thick' (thickness >= 5) and 'thin' (thickness <= 3) exclude each other"),
    ("not anything", "'not anything' (thickness < 0) asks for values thickness never measures (it measures [0, inf])"),
    ("[planar, not planar]", "'planar' and 'not planar' cannot both hold"),
    ("[one_piece, pieces]", "'one_piece' (connexity <= 1) and 'pieces' (connexity >= 2) exclude each other"),  # a default
    ("{any: [[thick, thin], [level, not level]]}", "none of its 2 alternatives can, e.g. 'thick' (thickness >= 5) "
                                                   "and 'thin' (thickness <= 3) exclude each other"),
    ("[level, {all: [not level, planar]}]", "'level' and 'not level' cannot both hold"),
    # bounds that meet: one side includes the value, the other not
    ("[just_one, not one_piece]", "'just_one' (1 <= connexity <= 1) and 'not one_piece' (connexity > 1) exclude each other"),
    ("[just_one, not some]", "'just_one' (1 <= connexity <= 1) and 'not some' (connexity < 1) exclude each other"),
])
def test_rules_check_warns_about_a_condition_that_can_never_hold(tmp_path, capsys, cond, why):
    text = WARN_BASE.replace("COND", cond)
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 0, err
    assert out.strip().endswith("strategy divisive; 1 warning")
    assert f"t.yaml:{line_col(text, cond)}: warning: rule 'R' can never act: its condition can never hold: {why}\n" \
           f"      - {{name: R, if: {cond}, then: split}}\n" in err, err


@pytest.mark.parametrize("cond", ["[thick, not thin]", "[upright, not level]", "[one_piece, pieces_coarse]",
                                  "[just_one, some, one_piece]", "[not just_one, some, not pieces]",
                                  "{any: [[thick, thin], planar]}", "[not upright, level]", "[planar, thin]"])
def test_a_condition_that_can_hold_gets_no_warning(tmp_path, capsys, cond):
    code, out, err = check(capsys, write(tmp_path, WARN_BASE.replace("COND", cond)))
    assert code == 0 and err == "" and "warning" not in out


def test_labels_relabel_rules_and_ground_contact_are_checked_too(tmp_path, capsys):
    text = (OUTDOOR.replace("    if: [planar, level]", "    if: [planar, level, not sheet, sheet]")
            .replace("      if: [level, low, not sunk]", "      if: [level, low, not sunk, not level]")
            .replace("if: {any: [not level, not sheet]}", "if: {any: [[level, not level], [sheet, not sheet]]}"))
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 0 and out.strip().endswith("; 3 warnings"), err
    lines = [ln for ln in err.splitlines() if ": warning: " in ln]
    assert [ln.split(": warning: ")[1].split(":")[0] for ln in lines] == [
        "label 'ground' can never be given", "relabel rule 'low_level' can never act",
        "post.ground_contact can never move a point"]


@pytest.mark.slow
def test_kbs_run_prints_the_warnings_and_runs(tmp_path, capsys):
    text = OUTDOOR.replace("    if: [not planar, not connected]", "    if: [not planar, not connected, planar]")
    path = write(tmp_path, text)
    assert main(["run", "--rules", str(path), "-j", "1", str(EXAMPLE), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert f"kbs: warning: {path}:{line_col(text, '[not planar, not connected, planar]')}: rule 'CAh' can never act: " \
           "its condition can never hold: 'planar' and 'not planar' cannot both hold" in err
    assert main(["-q", "run", "--rules", str(path), "-j", "1", str(EXAMPLE), "--out", str(tmp_path / "out")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_the_shipped_rule_bases_and_examples_have_no_warning(capsys):
    files = ["outdoor", "airborne", "planar_contest", ROOT / "examples" / "rules" / "tabletop.yaml"]
    code, out, err = check(capsys, *files)
    assert code == 0 and err == "" and "warning" not in out


@pytest.mark.slow
@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.data())
def test_never_holds_agrees_with_trying_every_value(data):
    """Against brute force: thresholds are small integers (few, so that bounds often meet), so
    the values k/2 in [-1, 6] meet every region of the line; a condition can hold iff some values
    of its two measures satisfy it."""
    reg = PredicateRegistry.default()
    bound = st.one_of(st.none(), st.integers(0, 2))
    specs = {}
    for i in range(4):
        lo, hi = data.draw(bound), data.draw(bound)
        if lo is None and hi is None:
            hi = 2
        if lo is not None and hi is not None and lo > hi:
            lo, hi = hi, lo
        pred = "flatness" if i == 3 else "thickness"  # flatness measures [0, 1]
        specs[f"c{i}"] = {"predicate": pred, **({} if lo is None else {"min": min(lo, 1) if i == 3 else lo}),
                          **({} if hi is None else {"max": min(hi, 1) if i == 3 else hi})}
    names = list(specs)
    fact = st.builds(lambda n, neg: f"not {n}" if neg else n, st.sampled_from(names), st.booleans())
    cond_st = st.recursive(fact, lambda sub: st.one_of(st.lists(sub, min_size=1, max_size=3),
                                                         st.builds(lambda k, xs: {k: xs}, st.sampled_from(["all", "any"]),
                                                                   st.lists(sub, min_size=1, max_size=3))),
                           max_leaves=6)
    cond = data.draw(cond_st)
    import yaml as _yaml

    doc = {"kbs_rules": 1, "name": "t", "units": "m", "strategy": "divisive", "checks": specs,
           "rules": [{"name": "R", "if": cond, "then": "split"}], "labels": [{"name": "x"}]}
    rb = parse_rule_base(_yaml.safe_dump(doc), "t.yaml", reg)
    grid = [k / 2 for k in range(-2, 13)]

    def holds(values: dict[str, float]) -> bool:
        def fact_value(name: str) -> bool:
            c = rb.checks[name]
            v = values[c.predicate.name]
            return c.passes(v)
        return rb.rules[0].condition.evaluate(fact_value)

    possible = any(holds({"thickness": t, "flatness": f}) for t in grid if t >= 0 for f in grid if 0 <= f <= 1)
    warned = [w for w in rb.warnings if "rule 'R' can never act" in w.message]
    assert bool(warned) == (not possible), (cond, specs, [w.message for w in rb.warnings])


def test_clusters_no_label_matched_are_not_called_noise(tmp_path, capsys):
    """A rule base without a default label, with a label of its own named noise: the clusters no
    label's condition holds for say so in the summary and the explanation; the label noise keeps
    its own count (it was overwritten by the count of unlabelled points)."""
    text = OUTDOOR.replace("  - name: obstacle\n", "  - name: obstacle\n    if: not level\n  - name: noise\n"
                                                   "    if: tiny\n")
    path = write(tmp_path, text, "nolabel.yaml")
    out_dir = tmp_path / "out"
    assert main(["run", "--rules", str(path), "-j", "1", str(EXAMPLE), "--out", str(out_dir)]) == 0
    out = capsys.readouterr().out
    doc = json.loads((out_dir / "outdoor.json").read_text())
    counts = doc["summary"]["points_per_label"]
    unlabelled = [c for c in doc["clusters"] if c["label"] is None]
    assert unlabelled, "the scene must have a cluster no label matched"
    n_unlabelled = sum(c["n_points"] for c in unlabelled)
    assert counts["no label matched"] == n_unlabelled
    assert counts["noise"] == 0 and counts["noise (rejected)"] == 0  # the label, and the rejected points
    assert sum(counts.values()) == doc["n_points"]
    assert f"no label matched {n_unlabelled:,}" in out
    assert main(["explain", str(out_dir / "outdoor.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    cid = unlabelled[0]["ids"][0]
    line = next(ln for ln in lines if ln.strip().startswith(f"{cid} ("))
    assert "accepted, no label matched: " in line and not re.search(r"(accepted|rejected) as noise", line)
    assert "; not noise: " in line  # the label 'noise' is named as one whose condition did not hold
    assert main(["explain", str(out_dir / "outdoor.json"), "--cluster", cid]) == 0
    assert f"{cid}: {unlabelled[0]['n_points']:,} points, action accept, no label matched" in capsys.readouterr().out


# --- what the fuzz tests found --------------------------------------------------------------------


@pytest.mark.parametrize("old, new, at, message", [
    ("fallback: [0, 0, 1]", "fallback: [0, 0, up]", "up]", "scene.ground.fallback[2] must be a number; got 'up'"),
    ("min_points: 500", "min_points: ~", "~", "scene.ground.min_points must be an integer; got None"),
    ("max_angle: 10", "max_angle: ten", "ten", "post[5].merge_coplanar.max_angle must be a number; got 'ten'"),
    ("neighbours: 16", "neighbours: [16]", "[16]", "post[0].ground_model.neighbours must be an integer; got [16]"),
    ("radius: 3.0                # m", "radius: 3 m", "3 m", "post[0].ground_model.radius must be a number; got '3 m'"),
    ("normal: auto ", "normal: [1.0e+200, 1.0e+200, 0]", "[1.0e+200", "the ground normal is too long to be normalised"),
    ("max: 0.25                  # m", "max: 25e-2", "25e-2", "checks.low.max must be a number; got '25e-2' "
                                                              "(YAML reads 25e-2 as text; write 25.0e-2)"),
])
def test_values_the_schema_refuses_are_not_converted_anyway(tmp_path, capsys, old, new, at, message):
    """Found by the fuzz tests: the validator went on converting values the schema had refused
    (ValueError, TypeError tracebacks), and a normal too long to normalise reached scipy."""
    assert old in OUTDOOR
    text = OUTDOOR.replace(old, new, 1)
    code, out, err = check(capsys, write(tmp_path, text))
    assert code == 4 and "Traceback" not in err, err
    assert f"t.yaml:{line_col(text, at)}: {message}" in err, err


def test_a_folder_named_as_a_shipped_rule_base_does_not_hide_it(tmp_path, monkeypatch):
    """`kbs rules check abw` run where a folder `abw/` happens to be (a SegComp data set, say):
    the folder is not a rule file, the name means the shipped rule base; any other folder given as
    rules is still refused as not a file."""
    from kbs.cli.main import main

    (tmp_path / "abw").mkdir()
    (tmp_path / "mine").mkdir()
    monkeypatch.chdir(tmp_path)
    assert main(["rules", "check", "abw"]) == 0
    assert main(["rules", "check", "mine"]) == 4


def test_rules_check_summary_lists_the_post_steps_in_order(tmp_path, capsys):
    from kbs.knowledge import load_rule_base

    code, out, _ = check(capsys, "outdoor", "planar_contest")
    assert code == 0
    lines = out.splitlines()
    steps = [s.key for s in load_rule_base("outdoor").post]
    assert len(steps) >= 2 and lines[0].endswith(f", strategy divisive, post {' > '.join(steps)}"), lines[0]
    assert lines[1].endswith(", strategy divisive") and "post" not in lines[1]  # a file without post steps
    path = write(tmp_path, MINIMAL + "post:\n  - merge_coplanar: {label: plane}\n  - merge_coplanar: {label: plane}\n")
    code, out, _ = check(capsys, path)
    assert code == 0 and out.rstrip().endswith("strategy divisive, post merge_coplanar > merge_coplanar"), out


def test_a_setting_with_two_forms_says_what_it_takes_in_one_sentence(tmp_path, capsys):
    """A value of neither form's type (a misspelt name for ``initial_k``) is told both forms in one
    sentence, at the value."""
    text = MINIMAL.replace("strategy: divisive", "strategy: divisive\nengine: {initial_k: firstmax}")
    path = write(tmp_path, text)
    code, _, err = check(capsys, path)
    at = line_col(text, "firstmax}")
    assert code == 4
    assert (f"{path}:{at}: engine.initial_k is invalid: K of the first partition: 'first_apd_max' (APD's first "
            "local maximum, the seed paper) or a fixed K; got 'firstmax'\n") in err, err


@pytest.mark.parametrize("setting, at, message", [
    ("engine: {initial_k: 0}", "0}", "engine.initial_k: 0 is less than the minimum of 1"),
    ("scene: {far_outliers: {factor: 0}}", "0}}", "scene.far_outliers.factor: 0 is less than or equal to the minimum of 0"),
    ("scene: {far_outliers: {fator: 2}}", "fator", "unknown key 'fator' in scene.far_outliers (did you mean 'factor'?)"),
    ("scene: {ground: {normal: [0, 1]}}", "[0, 1]", "scene.ground.normal: [0, 1] is too short"),
])
def test_a_value_of_one_form_s_type_is_told_what_is_wrong_in_that_form_where(tmp_path, capsys, setting, at, message):
    """A value written in one of a setting's forms (a number for ``initial_k``, a mapping for
    ``far_outliers``, a vector for ``normal``) is told what is wrong with it in that form, at the
    part that is wrong, not the whole setting's description at the setting."""
    text = MINIMAL.replace("strategy: divisive", f"strategy: divisive\n{setting}")
    path = write(tmp_path, text)
    code, _, err = check(capsys, path)
    assert code == 4
    assert f"{path}:{line_col(text, at)}: {message}\n" in err, err
    assert "is invalid" not in err, err


def test_a_parameter_given_a_whole_mapping_is_named_briefly():
    """A mapping pasted where a parameter's number belongs (found by the fuzz test: a rule base's
    whole text under ``slope``) is refused at its position with the value cut short, not a
    message of thousands of characters."""
    from kbs.knowledge import PredicateRegistry, load_rule_base
    from kbs.knowledge.rulebase import RuleFileError, parse_rule_base

    big = "{" + ", ".join(f"k{i}: {i}" for i in range(500)) + "}"
    text = load_rule_base("outdoor").text.replace("params: {stat: p90, max_points: 300}",
                                                  f"params: {{stat: p90, max_points: {big}}}")
    assert big in text
    with pytest.raises(RuleFileError) as err:
        parse_rule_base(text, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    message = err.value.format()
    assert "parameter 'max_points' must be a int, got {'k0': 0" in message and "characters)" in message
    assert all(len(p.format()) < 2000 for p in err.value.problems), message[:300]
