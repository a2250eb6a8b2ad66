"""A rule file's ``engine:`` section, read from the engine's table of settings
(:mod:`kbs.inference.settings`): its defaults, its part of the JSON Schema, its lines in
``kbs rules schema --engine`` and in the README.

The schema's ``engine`` part and the README's table are generated from the table and committed
(editors read the schema file): ``python tests/test_settings.py --write`` rewrites them, and
tests/test_settings.py fails when they are out of date. The rest of the schema is written by hand.
"""
from __future__ import annotations

import json
import numbers
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from kbs.inference import Interval, NoneValue, Options
from kbs.inference.settings import Constraint, Setting, format_default, rule_file_settings

#: The defaults of a rule file's engine section (those of the engine), in the section's order.
ENGINE_DEFAULTS: Mapping[str, Any] = {s.name: s.default for s in rule_file_settings()}

#: The rule-file settings that are keywords of ufp_onc (the interpreter passes them on).
UFP_ONC_RULE_SETTINGS: tuple[Setting, ...] = tuple(s for s in rule_file_settings() if s.in_ufp_onc)

#: What the schema says of the engine section as a whole.
SECTION_DESCRIPTION = "Settings of the inference motor (UFP-ONC)."


def constraint_schema(c: Constraint) -> dict[str, Any]:
    """The JSON Schema of one constraint."""
    if isinstance(c, Interval):
        out: dict[str, Any] = {"type": "integer" if c.kind is numbers.Integral else "number"}
        if c.low is not None:
            out["minimum" if c.closed in ("both", "left") else "exclusiveMinimum"] = c.low
        if c.high is not None:
            out["maximum" if c.closed in ("both", "right") else "exclusiveMaximum"] = c.high
        return out
    if isinstance(c, Options):
        return {"const": c.values[0]} if len(c.values) == 1 else {"enum": list(c.values)}
    if isinstance(c, NoneValue):
        return {"type": "null"}
    raise TypeError(f"no JSON Schema for {c!r}")


def setting_schema(s: Setting) -> dict[str, Any]:
    """The JSON Schema of one setting of the engine section: its doc, its default, its values."""
    allowed = s.rule_file_allowed
    out: dict[str, Any] = {"description": s.doc, "default": s.default}
    if len(allowed) == 1:
        out.update(constraint_schema(allowed[0]))
    else:
        out["oneOf"] = [constraint_schema(c) for c in allowed]
    return out


def engine_schema() -> dict[str, Any]:
    """The JSON Schema of a rule file's ``engine:`` section."""
    return {"description": SECTION_DESCRIPTION, "type": "object", "additionalProperties": False,
            "properties": {s.name: setting_schema(s) for s in rule_file_settings()}}


_ENGINE_START = re.compile(r'^(?P<indent> *)"engine": \{$', re.M)


def render_schema(text: str) -> str:
    """The schema file's text with its ``engine`` part replaced by :func:`engine_schema` (the rest
    of the file, written by hand, left as it is)."""
    m = _ENGINE_START.search(text)
    if m is None:
        raise ValueError('no "engine": { line in the schema')
    indent = m.group("indent")
    end = re.compile(rf"^{indent}\}}", re.M).search(text, m.end())
    if end is None:
        raise ValueError("the schema's engine part does not end")
    body = json.dumps(engine_schema(), indent=2, ensure_ascii=False).replace("\n", "\n" + indent)
    return text[: m.start()] + f'{indent}"engine": ' + body + text[end.end():]


def schema_path() -> Path:
    """The rule-file schema in this source tree."""
    from kbs.knowledge.rulebase import SCHEMA_FILE

    return Path(__file__).resolve().parents[1] / "rules" / SCHEMA_FILE


def settings_lines(values: Mapping[str, Any] | None = None) -> list[str]:
    """One line per setting of the engine section: name, default, allowed values, doc. With
    ``values`` (a rule base's engine), each line starts with the value it uses."""
    out = []
    for s in rule_file_settings():
        line = s.line(rule_file=True)
        if values is not None:
            v = values.get(s.name, s.default)
            line = f"{s.name}: {format_default(v)}{'' if v == s.default else ' (default ' + format_default(s.default) + ')'}" \
                   f"; {s.describe(rule_file=True)}. {s.doc}"
        out.append(line)
    return out


def readme_table() -> str:
    """The README's table of the engine section (markdown)."""
    rows = ["| setting | default | values | what it does |", "|---|---|---|---|"]
    for s in rule_file_settings():
        values = s.describe(rule_file=True).replace("|", "\\|")
        rows.append(f"| `{s.name}` | `{format_default(s.default)}` | {values} | {s.doc} |")
    return "\n".join(rows) + "\n"


README_START = "<!-- engine-settings: generated from kbs.inference.settings by python tests/test_settings.py --write -->\n"
README_END = "<!-- /engine-settings -->\n"


def render_readme(text: str) -> str:
    """The README's text with the table between its markers regenerated."""
    a = text.index(README_START) + len(README_START)
    b = text.index(README_END, a)
    return text[:a] + readme_table() + text[b:]
