"""Rule files that passed the JSON Schema before are not run through it again
(kbs.knowledge.rulebase._KnownValid): a process loading a known file neither imports jsonschema nor
runs it; anything else (a new or changed file, one that failed, another schema or plugin set) is
validated as before."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import kbs.knowledge.rulebase as rb_module
from kbs.inference import _flags
from kbs.knowledge import RuleFileError, load_rule_base

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def schema_runs(tmp_path, monkeypatch):
    """The state folder in tmp_path; counts the schema validators built and run."""
    monkeypatch.setattr(_flags, "_state_dir", lambda: tmp_path)
    calls = []
    real = rb_module._schema_validator

    def counted(actions=()):
        calls.append(actions)
        return real(actions)

    monkeypatch.setattr(rb_module, "_schema_validator", counted)
    return calls


def _copy(tmp_path: Path, name: str = "mine.yaml", edit=None) -> Path:
    text = (ROOT / "rules" / "outdoor.yaml").read_text()
    if edit:
        text = edit(text)
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_valid_file_is_checked_against_the_schema_once(tmp_path, schema_runs):
    path = _copy(tmp_path)
    first = load_rule_base(str(path))
    assert len(schema_runs) == 1
    second = load_rule_base(str(path))
    assert len(schema_runs) == 1  # known: not run again
    assert second.checks == first.checks and second.rules == first.rules and second.post == first.post
    assert (tmp_path / "kbs-valid-rules").read_text().split() == [rb_module._KnownValid.key(
        rb_module.yaml.safe_load(path.read_text()), rb_module.PredicateRegistry.default())]


def test_a_changed_file_is_checked_again(tmp_path, schema_runs):
    load_rule_base(str(_copy(tmp_path)))
    load_rule_base(str(_copy(tmp_path, edit=lambda t: t.replace("max: 0.05", "max: 0.06", 1))))
    assert len(schema_runs) == 2


def test_a_file_that_fails_the_schema_is_never_known_and_says_so_each_time(tmp_path, schema_runs):
    path = _copy(tmp_path, edit=lambda t: t.replace("  max_depth: 11", "  max_depth: eleven", 1))
    for n in (1, 2):
        with pytest.raises(RuleFileError) as err:
            load_rule_base(str(path))
        assert "max_depth" in str(err.value) and f"{path}:" in str(err.value)
        assert len(schema_runs) == n
    assert not (tmp_path / "kbs-valid-rules").exists()


def test_a_file_that_passes_the_schema_but_not_kbss_checks_is_not_known(tmp_path, schema_runs):
    path = _copy(tmp_path, edit=lambda t: t.replace("if: tiny\n", "if: tinyy\n", 1))
    for n in (1, 2):
        with pytest.raises(RuleFileError, match="tinyy"):
            load_rule_base(str(path))
        assert len(schema_runs) == n


def test_an_unreadable_state_folder_means_the_schema_runs(tmp_path, monkeypatch, schema_runs):
    def nowhere():
        raise OSError("read-only")

    monkeypatch.setattr(_flags, "_state_dir", nowhere)
    path = _copy(tmp_path)
    load_rule_base(str(path))
    load_rule_base(str(path))
    assert len(schema_runs) == 2


def test_a_process_loading_a_known_rule_base_does_not_import_jsonschema(tmp_path):
    code = ("import sys\nfrom kbs.knowledge import load_rule_base\nload_rule_base('outdoor')\n"
            "print('jsonschema' in sys.modules)")
    env = {**os.environ, "KBS_CACHE_DIR": str(tmp_path)}
    out = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
           for _ in range(2)]
    assert all(r.returncode == 0 for r in out), [r.stderr for r in out]
    assert [r.stdout.strip() for r in out] == ["True", "False"]


def test_a_key_of_another_type_is_another_file(tmp_path, schema_runs):
    """A mapping key 1 and a key '1' hash differently (the schema may refuse one and pass the other)."""
    from kbs.knowledge.predicates import PredicateRegistry

    reg = PredicateRegistry.default()
    assert rb_module._KnownValid.key({"a": {1: 2}}, reg) != rb_module._KnownValid.key({"a": {"1": 2}}, reg)
    assert rb_module._KnownValid.key({"a": [1]}, reg) != rb_module._KnownValid.key({"a": [1.0]}, reg)
    assert rb_module._KnownValid.key({"a": True}, reg) != rb_module._KnownValid.key({"a": 1}, reg)
