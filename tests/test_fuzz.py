"""Fuzzing: mutated rule files and small, degenerate clouds, through the library and the real
command. Every case must end in a result or a KbsError (the command: exit 0 or 2-7), never another
exception (a traceback, exit 1), never a hang (each case runs under an alarm).

Reproducible (derandomize=True) and short (max_examples per test): the whole file runs in well
under a minute once the compiled kernels are cached (`kbs warmup`).
"""
from __future__ import annotations

import contextlib
import copy
import math
import signal
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kbs.cli.main import main
from kbs.errors import KbsError
from kbs.knowledge import PredicateRegistry, RuleFileError, Segmenter
from kbs.knowledge.rulebase import parse_rule_base, shipped_rule_bases, shipped_text

#: Seconds a case may take; beyond, it counts as a hang (the alarm interrupts it).
CASE_SECONDS = 30

REGISTRY = PredicateRegistry.default()
SHIPPED = {name: yaml.safe_load(shipped_text(name)) for name in shipped_rule_bases()}
FUZZ = settings(derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])  # capsys: read after each case


class Hang(Exception):
    """A case that took longer than CASE_SECONDS."""


@contextlib.contextmanager
def bounded(seconds: int = CASE_SECONDS) -> Iterator[None]:
    def alarm(signum, frame):
        raise Hang(f"the case took more than {seconds} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# --- rule files -------------------------------------------------------------------------------------


def _paths(node: Any, path: tuple = ()) -> Iterator[tuple]:
    yield path
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, path + (i,))


def _get(node: Any, path: tuple) -> Any:
    for p in path:
        node = node[p]
    return node


def _nest(value: Any, levels: int, form: str) -> Any:
    for _ in range(levels):
        value = [value] if form == "list" else {"all": [value]}
    return value


extreme_numbers = st.sampled_from([0, -1, 1, 2, 0.5, -0.0, 1e-300, 5e-324, 1e300, -1e300, 1.7976931348623157e308,
                                   2**31, 2**63, -(2**63), 10**30, math.nan, math.inf, -math.inf])
wrong_types = st.one_of(st.none(), st.booleans(), st.text(max_size=12), st.lists(st.integers(-3, 3), max_size=4),
                        st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
                        st.builds(dict), st.builds(list),  # fresh each draw: st.just({}) is one object, and a
                        st.just("not planar"), st.just("auto"))  # later 'add' mutation into it leaked into the next case
names = st.sampled_from(["planar", "level", "sheet", "connected", "tiny", "low", "ground", "obstacle", "noise",
                         "thickness", "thicknes", "no_such_check", "not planar", "all", "any", "_x", "9lives"])
predicates = st.sampled_from(["thickness", "flatness", "ground_angle", "connexity", "point_count", "extent",
                              "height_above_ground", "distance_to_sensor", "height_above_local_ground", "unknown",
                              "Thickness", "", "elongation"])


@st.composite
def mutated_rule_base(draw) -> tuple[str, str]:
    """(name of the shipped rule base, the YAML text of a mutation of it)."""
    name = draw(st.sampled_from(sorted(SHIPPED)))
    data = copy.deepcopy(SHIPPED[name])
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(data))
        path = draw(st.sampled_from(paths))
        kind = draw(st.sampled_from(["value", "number", "delete", "add", "nest", "predicate", "rename", "swap"]))
        parent = _get(data, path[:-1]) if path else None
        if kind == "value" and path:
            parent[path[-1]] = draw(wrong_types)
        elif kind == "number" and path:
            parent[path[-1]] = draw(extreme_numbers)
        elif kind == "delete" and path:
            del parent[path[-1]]
        elif kind == "add":
            target = _get(data, path)
            if isinstance(target, dict):
                target[draw(names)] = draw(st.one_of(wrong_types, extreme_numbers, names))
            elif isinstance(target, list):
                target.append(draw(st.one_of(wrong_types, names)))
        elif kind == "nest" and path:
            parent[path[-1]] = _nest(parent[path[-1]], draw(st.integers(1, 140)), draw(st.sampled_from(["list", "all"])))
        elif kind == "predicate" and isinstance(data.get("checks"), dict) and data["checks"]:
            check = draw(st.sampled_from(sorted(data["checks"])))
            if isinstance(data["checks"][check], dict):
                data["checks"][check]["predicate"] = draw(predicates)
        elif kind == "rename" and isinstance(data.get("checks"), dict) and data["checks"]:
            old = draw(st.sampled_from(sorted(data["checks"])))
            data["checks"][draw(names)] = data["checks"].pop(old)
        elif kind == "swap" and path and isinstance(parent, (dict, list)):
            other = draw(st.sampled_from(paths))
            try:
                parent[path[-1]] = copy.deepcopy(_get(data, other))
            except (KeyError, IndexError, TypeError):
                pass
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True, width=100)
    edit = draw(st.sampled_from(["none", "none", "none", "truncate", "insert", "drop_line", "indent"]))
    if edit != "none" and text:
        at = draw(st.integers(0, len(text) - 1))
        if edit == "truncate":
            text = text[:at]
        elif edit == "insert":
            text = text[:at] + draw(st.sampled_from(["\x00", "\t", ":", "- ", "{", "]", "&a ", "*a", "\ufeff", "é",
                                                      "\u2028", "!!python/object ", "? ", "'", '"', "#"])) + text[at:]
        else:
            lines = text.splitlines(keepends=True)
            i = at % len(lines)
            lines[i] = "" if edit == "drop_line" else "  " + lines[i]
            text = "".join(lines)
    return name, text


def _check_outcome(text: str) -> Any:
    """Parse; a RuleFileError must carry positioned problems."""
    try:
        return parse_rule_base(text, "fuzz.yaml", REGISTRY)
    except RuleFileError as exc:
        assert exc.problems
        for p in exc.problems:
            assert p.pos.line >= 1 and p.pos.col >= 1 and p.message, p
            assert len(p.format()) < 2000, p.format()[:300]
        return exc


@pytest.mark.slow
@settings(FUZZ, max_examples=300)
@given(mutated_rule_base())
def test_a_mutated_rule_file_loads_or_is_a_positioned_rule_file_error(case):
    name, text = case
    with bounded():
        _check_outcome(text)  # any other exception fails the test with its traceback


@settings(FUZZ, max_examples=25)
@given(mutated_rule_base())
def test_kbs_rules_check_on_a_mutated_rule_file_exits_0_or_4(tmp_path_factory, capsys, case):
    name, text = case
    path = tmp_path_factory.mktemp("rules") / "fuzz.yaml"
    path.write_text(text, encoding="utf-8")
    with bounded():
        code = main(["rules", "check", str(path)])
    err = capsys.readouterr().err
    assert code in (0, 4) and "Traceback" not in err, (code, err[-2000:])


yaml_junk = st.text(st.sampled_from(list("ab:-[]{},&*!|>'\"#%@` \n\t.0123456789eE+~?") + ["\x00", "\ufeff", "é",
                                                                                      "\u2028", "\ud800"]),
                    max_size=200)


@settings(FUZZ, max_examples=200)
@given(st.one_of(yaml_junk, st.text(max_size=200)))
def test_any_text_loads_or_is_a_positioned_rule_file_error(text):
    with bounded():
        _check_outcome(text)


@settings(FUZZ, max_examples=15)
@given(st.binary(max_size=300), st.sampled_from(sorted(SHIPPED)), st.integers(0, 4000))
def test_kbs_rules_check_on_bytes_exits_4(tmp_path_factory, capsys, junk, name, at):
    """Random bytes, alone or inside a shipped rule file."""
    path = tmp_path_factory.mktemp("rules") / "junk.yaml"
    base = shipped_text(name).encode()
    path.write_bytes(base[:at] + junk + base[at:] if at % 2 else junk)
    with bounded():
        code = main(["rules", "check", str(path)])
    err = capsys.readouterr().err
    assert code in (0, 4) and "Traceback" not in err, (code, err[-2000:])


@settings(FUZZ, max_examples=12)
@given(mutated_rule_base())
def test_a_valid_mutation_segments_a_small_scene_or_says_why(case):
    name, text = case
    rb = _check_outcome(text)
    if isinstance(rb, RuleFileError):
        return
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-5, 5, (300, 2)), rng.normal(0, 0.01, 300)]
    box = rng.uniform(-0.5, 0.5, (80, 3)) + [2, 2, 1]
    with bounded():
        try:
            with Segmenter(rb, jobs=1) as seg:
                out = seg.segment(np.vstack([ground, box]))
        except KbsError:
            return
    assert out.cluster.shape == out.label.shape == (380,)


# --- small clouds -------------------------------------------------------------------------------------


@st.composite
def small_cloud(draw) -> np.ndarray:
    kind = draw(st.sampled_from(["random", "identical", "collinear", "coplanar", "few", "huge", "tiny", "grid"]))
    n = draw(st.integers(1, 10)) if kind == "few" else draw(st.integers(1, 120))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    if kind == "identical":
        X = np.tile(rng.uniform(-5, 5, 3), (n, 1))
    elif kind == "collinear":
        X = rng.uniform(-5, 5, 3) + np.outer(rng.uniform(-5, 5, n), rng.normal(size=3))
    elif kind == "coplanar":
        X = np.c_[rng.uniform(-5, 5, (n, 2)), np.zeros(n)]
    elif kind == "huge":
        X = rng.uniform(-1, 1, (n, 3)) * draw(st.sampled_from([1e8, 1e15, 1e100, 1e150])) + draw(
            st.sampled_from([0.0, 1e12, -1e15]))
    elif kind == "tiny":
        X = rng.uniform(-1, 1, (n, 3)) * draw(st.sampled_from([1e-9, 1e-150, 5e-324]))
    elif kind == "grid":
        side = max(1, int(round(n ** (1 / 3))))
        X = np.stack(np.meshgrid(*[np.arange(side)] * 3), axis=-1).reshape(-1, 3).astype(float)
    else:
        X = rng.uniform(-5, 5, (n, 3))
    return X


@settings(FUZZ, max_examples=40)
@given(small_cloud(), st.sampled_from(sorted(SHIPPED)))
def test_a_small_or_degenerate_cloud_segments_or_is_a_kbs_error(X, name):
    with bounded():
        try:
            with Segmenter(name, jobs=1) as seg:
                out = seg.segment(X)
        except KbsError:
            return
    n = X.shape[0]
    assert out.cluster.shape == out.label.shape == out.membership.shape == (n,)
    assert ((out.cluster >= -1) & (out.cluster < max(1, len(out.clusters)))).all()


@settings(FUZZ, max_examples=12)
@given(small_cloud(), st.sampled_from(sorted(SHIPPED)), st.integers(0, 3))
def test_kbs_run_on_a_small_cloud_with_nan_rows_exits_0_or_2_to_7(tmp_path_factory, capsys, X, name, nan_rows):
    d = tmp_path_factory.mktemp("cloud")
    rows = [" ".join(repr(float(v)) for v in p) for p in X] + ["nan nan nan"] * nan_rows + ["1 inf 2"] * (nan_rows > 1)
    (d / "scan.xyz").write_text("\n".join(rows) + "\n")
    with bounded():
        code = main(["-q", "run", "--rules", name, "-j", "1", str(d / "scan.xyz"), "--out", str(d / "out")])
    err = capsys.readouterr().err
    assert code == 0 or 2 <= code <= 7, (code, err[-2000:])
    assert "Traceback" not in err
    if code == 0:
        assert (d / "out" / "scan.json").is_file()
