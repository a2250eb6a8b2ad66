"""One table of engine settings (kbs.inference.settings): ufp_onc, IncrementalSweep, the estimators,
the rule file's engine section (its defaults, its checks, its part of the JSON Schema), kbs cluster's
options, `kbs rules schema --engine` and the README's table all read it.

``python tests/test_settings.py --write`` regenerates the schema's engine part and the README's
table from the table."""
from __future__ import annotations

import inspect
import json
import numbers
import sys
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from kbs.errors import ParameterError
from kbs.inference._validation import Interval, NoneValue, Options
from kbs.inference.estimators import FuzzyCMeans, GathGeva
from kbs.inference.incremental import IncrementalSweep
from kbs.inference.settings import DEFAULTS, ENGINE_SETTINGS, FIT_DEFAULTS, SAME, SETTINGS, rule_file_settings
from kbs.inference.ufp_onc import ENGINE_CONSTRAINTS, ufp_onc
from kbs.knowledge import PredicateRegistry
from kbs.knowledge.engine_settings import engine_schema, render_readme, render_schema, schema_path
from kbs.knowledge.rulebase import parse_rule_base, schema
from test_knowledge import MINIMAL

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"



def _settings_of(fn) -> dict[str, inspect.Parameter]:
    return {k: p for k, p in inspect.signature(fn).parameters.items() if k in SETTINGS}


# --- the generated files ------------------------------------------------------------------------


def test_the_schemas_engine_part_is_generated_from_the_table():
    text = schema_path().read_text(encoding="utf-8")
    assert render_schema(text) == text, "the schema's engine part is out of date: python tests/test_settings.py --write"
    assert schema()["properties"]["engine"] == engine_schema()


def test_the_schema_gives_each_engine_key_its_default_and_doc():
    """Editors (yaml-language-server) show a key's description and default on hover."""
    props = schema()["properties"]["engine"]["properties"]
    assert list(props) == [s.name for s in rule_file_settings()]
    for s in rule_file_settings():
        assert props[s.name]["default"] == s.default and props[s.name]["description"] == s.doc


def test_the_readmes_table_is_the_tables():
    text = README.read_text(encoding="utf-8")
    assert render_readme(text) == text, "the README's engine table is out of date: python tests/test_settings.py --write"


# --- the engine reads the table -----------------------------------------------------------------


@pytest.mark.parametrize("fn", [ufp_onc, IncrementalSweep], ids=["ufp_onc", "IncrementalSweep"])
def test_the_engines_defaults_are_the_tables(fn):
    params = _settings_of(fn)
    assert params and {k: p.default for k, p in params.items()} == {k: DEFAULTS[k] for k in params}


def test_ufp_onc_and_the_sweep_check_every_setting_they_take_with_the_tables_constraint():
    from kbs.inference.incremental import _CONSTRAINTS as sweep_constraints

    params = _settings_of(ufp_onc)
    assert set(ENGINE_CONSTRAINTS) == set(params) == {s.name for s in ENGINE_SETTINGS if s.in_ufp_onc}
    assert set(sweep_constraints) == set(_settings_of(IncrementalSweep))
    for name, allowed in [*ENGINE_CONSTRAINTS.items(), *sweep_constraints.items()]:
        assert allowed == list(SETTINGS[name].allowed)


@pytest.mark.parametrize("est", [FuzzyCMeans, GathGeva])
def test_the_estimators_read_the_table(est):
    """Their constraints are the table's; their defaults are the table's estimator defaults (the
    engine's, except where the table says why not)."""
    params = _settings_of(est)
    assert {k: p.default for k, p in params.items()} == {k: FIT_DEFAULTS[k] for k in params}
    for name in params:
        assert est._constraints[name] == list(SETTINGS[name].allowed)


def test_where_the_estimators_default_differs_the_table_says_why():
    differ = {s.name: (s.default, s.fit_default) for s in ENGINE_SETTINGS if s.estimator_default is not SAME}
    assert differ == {"tol": (1e-3, 1e-4), "max_iter": (100, 300)}  # the documented defaults, kept
    assert all(SETTINGS[n].estimator_note for n in differ)
    assert GathGeva().tol == 1e-4 and GathGeva().max_iter == 300 and FuzzyCMeans().max_iter == 300


def _outside(c: Interval) -> list[float]:
    """Values just outside an interval (below, above)."""
    out = []
    step = 1 if c.kind is numbers.Integral else 0.5
    if c.low is not None:
        out.append(c.low if c.closed in ("right", "neither") else c.low - step)
    if c.high is not None:
        out.append(c.high if c.closed in ("left", "neither") else c.high + step)
    return out


ENGINE_BAD = [(s.name, v, s.allowed) for s in ENGINE_SETTINGS if s.in_ufp_onc
              for c in s.allowed if isinstance(c, Interval) for v in _outside(c)]


@pytest.mark.parametrize("name, value, allowed", ENGINE_BAD, ids=[f"{n}={v}" for n, v, _ in ENGINE_BAD])
def test_ufp_onc_refuses_what_the_table_refuses(name, value, allowed):
    X = np.random.RandomState(0).normal(size=(50, 3))
    with pytest.raises(ParameterError) as exc:
        ufp_onc(X, **{name: value})
    expected = " or ".join(c.describe() for c in allowed)
    assert str(exc.value) == f"The {name!r} parameter of ufp_onc must be {expected}. Got {value!r} instead."


def test_k_max_1_is_an_engine_setting_but_not_a_rule_files():
    """The engine fits K = 1 alone (GathGeva(n_clusters=1)); a rule file's splits need K = 2."""
    X = np.random.RandomState(0).normal(size=(50, 3))
    assert ufp_onc(X, k_max=1).chosen_k == 1
    assert GathGeva(n_clusters=1).fit(X).n_clusters_ == 1
    assert SETTINGS["k_max"].rule_note


# --- the rule file reads the table --------------------------------------------------------------


def test_a_rule_files_engine_defaults_are_the_engines():
    rb = parse_rule_base(MINIMAL, "t.yaml", PredicateRegistry.default())
    assert dict(rb.engine) == {s.name: s.default for s in rule_file_settings()}
    for s in rule_file_settings():
        if s.in_ufp_onc:
            assert rb.engine[s.name] == inspect.signature(ufp_onc).parameters[s.name].default
    # what kbs run has always used when a rule file says nothing (its results must not move)
    assert dict(rb.engine) == {"m": 2.0, "k_max": 10, "initial_k": "first_apd_max", "max_fit_points": 6000,
                               "min_variance": 1e-6, "max_condition": 1e4, "tol": 1e-3, "fcm_tol": 1e-3,
                               "max_iter": 100, "new_prototype": "distance", "split_min_k": 1}


def _rule_file_cases() -> list[tuple[str, object, bool]]:
    """(setting, value, valid) at and beyond each bound a rule file has, from the table."""
    cases: list[tuple[str, object, bool]] = []
    for s in rule_file_settings():
        for c in s.rule_file_allowed:
            if isinstance(c, Interval):
                cases += [(s.name, v, False) for v in _outside(c)]
                if c.low is not None and c.closed in ("both", "left"):
                    cases.append((s.name, c.low, True))
                if c.high is not None and c.closed in ("both", "right"):
                    cases.append((s.name, c.high, True))
            elif isinstance(c, Options):
                cases += [(s.name, v, True) for v in c.values]
        if not any(isinstance(c, NoneValue) for c in s.rule_file_allowed):
            cases.append((s.name, None, False))
    return cases


RULE_CASES = _rule_file_cases()


@pytest.mark.parametrize("name, value, valid", RULE_CASES, ids=[f"{n}={v}" for n, v, _ in RULE_CASES])
def test_kbs_rules_check_takes_what_the_table_allows_in_a_rule_file(tmp_path, capsys, name, value, valid):
    written = json.dumps(value)
    text = MINIMAL + f"engine:\n  {name}: {written}\n"
    if name == "initial_k" and isinstance(value, int) and value > 10:
        text += "  k_max: 50\n"
    path = tmp_path / "t.yaml"
    path.write_text(text, encoding="utf-8")
    code = main(["rules", "check", str(path)])
    err = capsys.readouterr().err
    if valid:
        assert code == 0, err
    else:
        col = len(f"  {name}: ") + 1
        assert code == 4 and f"t.yaml:12:{col}: engine.{name}" in err, err
        assert "Traceback" not in err


def test_kbs_rules_schema_engine_prints_the_table(capsys):
    assert main(["rules", "schema", "--engine"]) == 0
    lines = capsys.readouterr().out.splitlines()[1:]
    assert len(lines) == len(rule_file_settings())
    for line, s in zip(lines, rule_file_settings()):
        assert line.strip().startswith(f"{s.name} = ") and s.doc in line and s.describe(rule_file=True) in line
    assert "k_max = 10: an int in the range [2, 50]. Largest K tried" in "\n".join(lines)
    assert main(["rules", "schema", "--engine", "--json"]) == 2


def test_kbs_rules_show_engine_prints_the_values_a_rule_base_uses(capsys):
    assert main(["rules", "show", "planar_global", "--engine"]) == 0
    out = capsys.readouterr().out
    assert "  k_max: 30 (default 10); an int in the range [2, 50]." in out
    assert "  m: 2; a float in the range (1, inf). Fuzzifier" in out  # a default, said without '(default'


def test_kbs_cluster_options_are_the_tables(capsys):
    assert main(["cluster", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "[default: 10; x>=1]" in out and "[default: 6000; x>=10]" in out and "[default: 2.0; x>1]" in out
    assert "Fuzzifier; with 2" in out


@pytest.mark.parametrize("option, value", [("--m", "1"), ("--k-max", "0"), ("--max-fit-points", "9"),
                                            ("--stop", "never")])
def test_kbs_cluster_refuses_what_the_table_refuses(option, value):
    example = ROOT / "examples" / "data" / "outdoor.ply"
    assert main(["cluster", str(example), option, value]) == 2


# --- regenerate ---------------------------------------------------------------------------------


def _write() -> None:
    for path, render in ((schema_path(), render_schema), (README, render_readme)):
        old = path.read_text(encoding="utf-8")
        new = render(old)
        if new != old:
            path.write_text(new, encoding="utf-8")
            print(f"rewrote {path}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_settings.py --write")
    _write()
