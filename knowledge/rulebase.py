"""Rule bases: YAML files of application knowledge, loaded into immutable objects with the
source position of every part, and validated with ALL problems reported at once.

Each problem prints as ``file:line:col: message`` (1-based), followed by the offending source
line and a caret under the offending value (after yamllint and strictyaml). Validation is the
JSON Schema shipped in ``rules/rule-base.schema.json`` plus what a schema cannot say: known
predicates ("did you mean"), their parameters, thresholds within the predicate's range,
references between checks, rules and labels, and contradictory settings.
"""
from __future__ import annotations

import functools

import json
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import yaml
from jsonschema import Draft202012Validator

from kbs.errors import ExitCode, KbsError
from kbs.knowledge.predicates import Predicate, PredicateRegistry, did_you_mean

SCHEMA_FILE = "rule-base.schema.json"
ACTIONS = ("split", "split_components", "reject")

ENGINE_DEFAULTS: dict[str, Any] = {
    "m": 2.0, "k_max": 10, "initial_k": "first_apd_max", "max_fit_points": 6000, "min_variance": 1e-6,
    "max_condition": 1e4, "tol": 1e-3, "max_iter": 100, "new_prototype": "distance", "split_min_k": 1,
}
#: Limits are per cluster. max_clusters (None: absent) is an optional cap on the whole split tree,
#: which makes a point's result depend on the rest of the file; no shipped rule base sets it.
LIMIT_DEFAULTS: dict[str, Any] = {"max_depth": 8, "min_points": 30, "max_clusters": None}
GROUND_DEFAULTS: dict[str, Any] = {"normal": "auto", "candidate": None, "min_points": 500, "fallback": [0.0, 0.0, 1.0]}


# --- positions and problems ------------------------------------------------------------------


@dataclass(frozen=True)
class SourcePos:
    """A 1-based position in a rule file."""

    file: str
    line: int
    col: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.col}"

    @property
    def short(self) -> str:
        """'outdoor.yaml:31' for explanations."""
        return _short(self.file, self.line)


@functools.lru_cache(maxsize=4096)
def _short(file: str, line: int) -> str:
    return f"{Path(file).name}:{line}"


@dataclass(frozen=True)
class Problem:
    pos: SourcePos
    message: str
    source_line: str = ""

    def format(self) -> str:
        out = f"{self.pos}: {self.message}"
        if self.source_line:
            out += f"\n    {self.source_line}\n    {' ' * (self.pos.col - 1)}^"
        return out


class RuleFileError(KbsError):
    """An invalid rule file; carries every problem found."""

    exit_code = ExitCode.RULES

    def __init__(self, problems: list[Problem]) -> None:
        self.problems = sorted(problems, key=lambda p: (p.pos.line, p.pos.col, p.message))
        n = len(self.problems)
        head = f"{n} problem{'s' if n != 1 else ''} in rule file {self.problems[0].pos.file}" if n else "rule file"
        super().__init__(head + ":\n" + "\n".join(p.format() for p in self.problems))

    def format(self) -> str:
        return "\n".join(p.format() for p in self.problems)


class _Positions:
    """Maps a path in the YAML document (keys and indices) to the position of its value and key."""

    def __init__(self, file: str, text: str, root: yaml.Node | None) -> None:
        self.file = file
        self.lines = text.splitlines()
        self.values: dict[tuple, yaml.Mark] = {}
        self.keys: dict[tuple, yaml.Mark] = {}
        self.duplicates: list[tuple[tuple, yaml.Mark]] = []
        if root is not None:
            self._walk(root, ())

    def _walk(self, node: yaml.Node, path: tuple) -> None:
        self.values[path] = node.start_mark
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for k, v in node.value:
                key = k.value
                if key in seen:
                    self.duplicates.append((path + (key,), k.start_mark))
                seen.add(key)
                self.keys[path + (key,)] = k.start_mark
                self._walk(v, path + (key,))
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                self._walk(v, path + (i,))

    def pos(self, path: tuple, *, key: bool = False) -> SourcePos:
        path = tuple(path)
        mark = None
        if key:
            mark = self.keys.get(path)
        while mark is None:
            mark = self.values.get(path)
            if mark is None:
                if not path:
                    return SourcePos(self.file, 1, 1)
                path = path[:-1]
        return SourcePos(self.file, mark.line + 1, mark.column + 1)

    def problem(self, path: tuple, message: str, *, key: bool = False) -> Problem:
        pos = self.pos(path, key=key)
        line = self.lines[pos.line - 1] if 0 < pos.line <= len(self.lines) else ""
        return Problem(pos, message, line)


def _where(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "the rule base"


# --- the model -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    """A named measurement compared with thresholds: passes when min <= value <= max."""

    name: str
    predicate: Predicate
    params: Mapping[str, Any]
    min: float | None
    max: float | None
    doc: str
    pos: SourcePos

    def passes(self, value: float) -> bool:
        return (self.min is None or value >= self.min) and (self.max is None or value <= self.max)

    def threshold_text(self, value: float, unit: str) -> str:
        """'> 1' or '<= 0.05 m': how the value compares with the bound it crossed (or met)."""
        u = f" {unit}" if unit else ""
        if self.max is not None and (value > self.max or self.min is None or value >= self.min):
            return f"{'<=' if value <= self.max else '>'} {self.max:g}{u}"
        return f"{'>=' if value >= self.min else '<'} {self.min:g}{u}"


@dataclass(frozen=True)
class Condition:
    """A boolean expression over check outcomes: a fact (possibly negated), all(...), any(...)."""

    kind: str  # 'fact', 'all', 'any'
    name: str = ""
    negated: bool = False
    items: tuple["Condition", ...] = ()

    def evaluate(self, fact: Callable[[str], bool]) -> bool:
        """Evaluate lazily (checks are measured only when needed)."""
        if self.kind == "fact":
            return fact(self.name) != self.negated
        if self.kind == "all":
            return all(c.evaluate(fact) for c in self.items)
        return any(c.evaluate(fact) for c in self.items)

    def facts(self) -> Iterator["Condition"]:
        if self.kind == "fact":
            yield self
        for c in self.items:
            yield from c.facts()

    def __str__(self) -> str:
        if self.kind == "fact":
            return f"not {self.name}" if self.negated else self.name
        sep = " and " if self.kind == "all" else " or "
        return sep.join(str(c) if c.kind == "fact" else f"({c})" for c in self.items)


@dataclass(frozen=True)
class Rule:
    name: str
    condition: Condition
    action: str
    doc: str
    pos: SourcePos


@dataclass(frozen=True)
class Label:
    name: str
    condition: Condition | None
    doc: str
    pos: SourcePos


@dataclass(frozen=True)
class GroundSpec:
    normal: tuple[float, float, float] | None  # None = auto
    candidate: str | None
    min_points: int
    fallback: tuple[float, float, float]


@dataclass(frozen=True)
class MergeSpec:
    label: str
    max_angle: float
    max_offset: float


@dataclass(frozen=True)
class GroundModelSpec:
    label: str
    neighbours: int
    radius: float
    pos: SourcePos


@dataclass(frozen=True)
class Relabel:
    """A post rule: a cluster labelled ``source`` whose condition holds takes label ``target``."""

    name: str
    source: str
    target: str
    condition: Condition
    doc: str
    pos: SourcePos


@dataclass(frozen=True)
class ContactSpec:
    tolerance: float
    sources: tuple[str, ...]  #: labels whose points may join the ground
    pos: SourcePos
    condition: Condition | None = None  #: only clusters for which it holds give points


@dataclass(frozen=True)
class ReleaseSpec:
    tolerance: float
    target: str  #: the label of the clusters released points join
    pos: SourcePos


@dataclass(frozen=True)
class RuleBase:
    """A validated rule base."""

    name: str
    description: str
    units: str
    engine: Mapping[str, Any]
    strategy: str
    limits: Mapping[str, Any]
    sensor: tuple[float, float, float]
    ground: GroundSpec
    checks: Mapping[str, Check]
    rules: tuple[Rule, ...]
    labels: tuple[Label, ...]
    merge: MergeSpec | None
    path: str
    text: str = field(repr=False)
    ground_model: GroundModelSpec | None = None
    relabel: tuple[Relabel, ...] = ()
    contact: ContactSpec | None = None
    release: ReleaseSpec | None = None
    #: ASPRS classification code of each label (and of 'noise', the rejected points) in LAS output.
    asprs_classes: Mapping[str, int] | None = None
    #: spacing: the median point spacing [min, max] the rule base suits (its unit); None: not declared.
    spacing: tuple[float, float] | None = None

    @property
    def label_names(self) -> list[str]:
        return [lb.name for lb in self.labels]

    @property
    def needs_ground(self) -> bool:
        return any(c.predicate.needs_ground for c in self.checks.values())

    @property
    def length_unit(self) -> str:
        return "" if self.units == "scan" else self.units


# --- loading ---------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def schema() -> dict:
    """The rule-file JSON Schema shipped in ``kbs/rules``."""
    return json.loads(resources.files("kbs.rules").joinpath(SCHEMA_FILE).read_text(encoding="utf-8"))


def shipped_rule_bases() -> list[str]:
    """Names of the rule bases shipped with kbs."""
    return sorted(p.name[:-5] for p in resources.files("kbs.rules").iterdir() if p.name.endswith(".yaml"))


def shipped_text(name: str) -> str:
    return resources.files("kbs.rules").joinpath(f"{name}.yaml").read_text(encoding="utf-8")


def resolve(name_or_path: str) -> tuple[str, str]:
    """``(display path, text)`` of a rule base given as a path or a shipped name."""
    p = Path(name_or_path)
    if p.is_file():
        try:
            return str(name_or_path), p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise RuleFileError([Problem(SourcePos(str(name_or_path), 1, 1), f"cannot read: {exc}")]) from exc
    if p.exists():
        raise RuleFileError([Problem(SourcePos(str(name_or_path), 1, 1), "not a file")])
    name = p.name[:-5] if p.name.endswith(".yaml") and p.parent == Path(".") else str(name_or_path)
    if name in shipped_rule_bases():
        return f"{name}.yaml", shipped_text(name)
    hint = did_you_mean(name, shipped_rule_bases())
    msg = f"no such file, nor a shipped rule base (shipped: {', '.join(shipped_rule_bases())})"
    if hint:
        msg += f"; did you mean '{hint}'?"
    raise RuleFileError([Problem(SourcePos(str(name_or_path), 1, 1), msg)])


def load_rule_base(name_or_path: str, registry: PredicateRegistry | None = None) -> RuleBase:
    """Load and validate a rule base (a path or a shipped name); raises :class:`RuleFileError`
    listing every problem."""
    display, text = resolve(name_or_path)
    return parse_rule_base(text, display, registry or PredicateRegistry.default())


def parse_rule_base(text: str, file: str, registry: PredicateRegistry) -> RuleBase:
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        pos = _Positions(file, text, None)
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        src = pos.lines[line - 1] if 0 < line <= len(pos.lines) else ""
        msg = f"YAML syntax: {exc.problem}"
        if exc.context and exc.context_mark and exc.context_mark is not mark:
            msg += f" ({exc.context} at line {exc.context_mark.line + 1}, column {exc.context_mark.column + 1})"
        raise RuleFileError([Problem(SourcePos(file, line, col), msg, src)]) from exc
    except yaml.YAMLError as exc:
        raise RuleFileError([Problem(SourcePos(file, 1, 1), f"YAML: {exc}")]) from exc
    pos = _Positions(file, text, root)
    if not isinstance(data, dict):
        raise RuleFileError([pos.problem((), "a rule base is a mapping of keys (kbs_rules, name, checks, rules, ...)")])
    v = _Validator(data, pos, registry)
    rb = v.run()
    if v.problems:
        raise RuleFileError(v.problems)
    return rb


class _Validator:
    def __init__(self, data: dict, pos: _Positions, registry: PredicateRegistry) -> None:
        self.data, self.pos, self.registry = data, pos, registry
        self.problems: list[Problem] = []

    def add(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.problems.append(self.pos.problem(path, message, key=key))

    # -- schema ------------------------------------------------------------------------------

    def schema_problems(self) -> None:
        for path, mark in self.pos.duplicates:
            self.problems.append(Problem(SourcePos(self.pos.file, mark.line + 1, mark.column + 1),
                                         f"duplicate key '{path[-1]}' in {_where(path[:-1])}",
                                         self.pos.lines[mark.line]))
        validator = Draft202012Validator(schema())
        for err in validator.iter_errors(self.data):
            self._schema_error(err)

    def _schema_error(self, err) -> None:
        path = tuple(err.absolute_path)
        where = _where(path)
        sch, inst, kind = err.schema, err.instance, err.validator
        if kind == "additionalProperties" and isinstance(inst, dict):
            allowed = list(sch.get("properties", {}))
            for k in inst:
                if k not in allowed:
                    hint = did_you_mean(k, allowed)
                    self.add(path + (k,), f"unknown key '{k}' in {where}"
                             + (f" (did you mean '{hint}'?)" if hint else f"; allowed: {', '.join(allowed)}"), key=True)
        elif kind == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            self.add(path, f"{where} is missing the required key '{missing}'")
        elif kind == "enum":
            hint = did_you_mean(str(inst), [str(x) for x in sch["enum"]])
            self.add(path, f"{where} must be one of {', '.join(map(str, sch['enum']))}; got {inst!r}"
                     + (f" (did you mean '{hint}'?)" if hint else ""))
        elif kind == "const":
            self.add(path, f"{where} must be {sch['const']!r}; got {inst!r}")
        elif kind == "type":
            self.add(path, f"{where} must be {_article(sch['type'])}; got {inst!r}")
        elif kind in ("oneOf", "anyOf"):
            if path and len(path) == 2 and path[0] == "checks":
                self.add(path, f"check '{path[1]}' needs a threshold: 'max' and/or 'min'")
            else:
                self.add(path, f"{where} is invalid: {sch.get('description', 'see the schema')}; got {inst!r}")
        elif kind == "pattern":
            self.add(path, f"{where}: {inst!r} is not a valid name (letters, digits, '_', not starting with a digit)")
        elif kind == "propertyNames":
            self.add(path, f"{where}: invalid name {err.instance!r}")
        else:
            self.add(path, f"{where}: {err.message}")

    # -- semantics -----------------------------------------------------------------------------

    def run(self) -> RuleBase | None:
        self.schema_problems()
        d = self.data
        checks = self._checks(d.get("checks"))
        rules = self._rules(d.get("rules"), checks)
        labels = self._labels(d.get("labels"), checks)
        engine = {**ENGINE_DEFAULTS, **(d.get("engine") if isinstance(d.get("engine"), dict) else {})}
        limits = {**LIMIT_DEFAULTS, **(d.get("limits") if isinstance(d.get("limits"), dict) else {})}
        if isinstance(engine.get("initial_k"), int) and isinstance(engine.get("k_max"), int) \
                and engine["initial_k"] > engine["k_max"]:
            self.add(("engine", "initial_k"), f"initial_k = {engine['initial_k']} contradicts k_max = {engine['k_max']}")
        scene = d.get("scene") if isinstance(d.get("scene"), dict) else {}
        sensor = scene.get("sensor", [0.0, 0.0, 0.0])
        ground = self._ground(scene.get("ground") if isinstance(scene.get("ground"), dict) else {}, checks)
        merge = self._merge(d.get("post"), labels)
        gmodel, relabel, contact, release = self._post(d.get("post"), checks, labels)
        self._model_checks_placed(checks, rules, labels)
        classes = self._asprs_classes(d.get("asprs_classes"), [lb.name for lb in labels])
        spacing = d.get("spacing")
        if isinstance(spacing, list) and len(spacing) == 2 and all(isinstance(x, (int, float)) for x in spacing) \
                and spacing[0] >= spacing[1]:
            self.add(("spacing",), f"spacing is [min, max]: {spacing[0]!r} is not below {spacing[1]!r}")
        if self.problems:
            return None
        return RuleBase(
            name=d["name"], description=str(d.get("description", "")).strip(), units=d["units"], engine=engine,
            strategy=d["strategy"], limits=limits, sensor=tuple(float(x) for x in sensor), ground=ground,
            checks=checks, rules=tuple(rules), labels=tuple(labels), merge=merge, path=self.pos.file,
            text="\n".join(self.pos.lines), ground_model=gmodel, relabel=tuple(relabel), contact=contact,
            release=release, asprs_classes=classes,
            spacing=None if spacing is None else (float(spacing[0]), float(spacing[1])),
        )

    def _asprs_classes(self, raw: Any, names: list[str]) -> dict[str, int] | None:
        """asprs_classes: label -> ASPRS code; the keys must be labels (or 'noise'), the codes
        integers 0-255 (the schema says so)."""
        if not isinstance(raw, dict):
            return None
        for key in raw:
            if key not in names and key != "noise":
                hint = did_you_mean(str(key), [*names, "noise"])
                self.add(("asprs_classes", key), f"unknown label '{key}' in asprs_classes"
                         + (f" (did you mean '{hint}'?)" if hint else f"; labels: {', '.join(names)}, or noise"),
                         key=True)
        return {str(k): int(v) for k, v in raw.items() if isinstance(v, int) and not isinstance(v, bool)}

    def _checks(self, raw: Any) -> dict[str, Check]:
        out: dict[str, Check] = {}
        if not isinstance(raw, dict):
            return out
        for name, spec in raw.items():
            base = ("checks", name)
            if not isinstance(spec, dict) or not isinstance(spec.get("predicate"), str):
                continue  # the schema reported it
            pname = spec["predicate"]
            if pname not in self.registry:
                hint = self.registry.suggest(pname)
                self.add(base + ("predicate",), f"unknown predicate '{pname}'"
                         + (f" (did you mean '{hint}'?)" if hint else f"; known: {', '.join(self.registry.names())}"))
                continue
            pred = self.registry.get(pname)
            params = dict(spec.get("params") or {}) if isinstance(spec.get("params", {}), dict) else {}
            for pkey, pval in params.items():
                if pkey not in pred.params:
                    hint = did_you_mean(pkey, pred.params)
                    known = ", ".join(pred.params) or "none"
                    self.add(base + ("params", pkey), f"predicate '{pname}' has no parameter '{pkey}'"
                             + (f" (did you mean '{hint}'?)" if hint else f"; its parameters: {known}"), key=True)
                    continue
                problem = pred.params[pkey].check(pval)
                if problem:
                    self.add(base + ("params", pkey), f"predicate '{pname}': {problem}")
            lo, hi = pred.value_range
            bounds = {}
            for side in ("min", "max"):
                val = spec.get(side)
                if val is None or isinstance(val, bool) or not isinstance(val, (int, float)):
                    continue
                bounds[side] = float(val)
                if (lo is not None and val < lo) or (hi is not None and val > hi):
                    self.add(base + (side,), f"threshold {side} = {val:g} is outside what '{pname}' can measure "
                             f"[{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]"
                             f" ({pred.unit})")
            if "min" in bounds and "max" in bounds and bounds["min"] > bounds["max"]:
                self.add(base + ("min",), f"check '{name}' can never pass: min {bounds['min']:g} > max {bounds['max']:g}")
            out[name] = Check(name=name, predicate=pred, params={k: v for k, v in params.items() if k in pred.params},
                              min=bounds.get("min"), max=bounds.get("max"), doc=str(spec.get("doc", "")),
                              pos=self.pos.pos(base, key=True))
        return out

    def _condition(self, raw: Any, path: tuple, checks: Mapping[str, Check]) -> Condition | None:
        if isinstance(raw, str):
            words = raw.split()
            negated = len(words) == 2 and words[0] == "not"
            name = words[-1] if words else ""
            if len(words) not in (1, 2) or (len(words) == 2 and not negated):
                return None  # the schema reported it
            if name not in checks and name in (self.data.get("checks") or {}):
                return Condition("fact", name, negated)  # the check itself is broken; reported there
            if name not in checks:
                hint = did_you_mean(name, list(self.data.get("checks") or {}))
                self.add(path, f"unknown check '{name}'" + (f" (did you mean '{hint}'?)" if hint else
                                                              f"; checks: {', '.join(self.data.get('checks') or {})}"))
                return None
            return Condition("fact", name, negated)
        if isinstance(raw, list):
            items = [self._condition(x, path + (i,), checks) for i, x in enumerate(raw)]
            return Condition("all", items=tuple(c for c in items if c)) if all(items) and items else None
        if isinstance(raw, dict) and len(raw) == 1 and next(iter(raw)) in ("all", "any"):
            kind = next(iter(raw))
            sub = raw[kind] if isinstance(raw[kind], list) else []
            items = [self._condition(x, path + (kind, i), checks) for i, x in enumerate(sub)]
            return Condition(kind, items=tuple(c for c in items if c)) if all(items) and items else None
        return None

    def _rules(self, raw: Any, checks: Mapping[str, Check]) -> list[Rule]:
        out: list[Rule] = []
        if not isinstance(raw, list):
            return out
        seen: set[str] = set()
        for i, spec in enumerate(raw):
            if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
                continue
            path = ("rules", i)
            if spec["name"] in seen:
                self.add(path + ("name",), f"rule '{spec['name']}' is defined twice")
            seen.add(spec["name"])
            cond = self._condition(spec.get("if"), path + ("if",), checks) if "if" in spec else None
            action = spec.get("then")
            if cond is None or action not in ACTIONS:
                continue
            if action == "split_components":
                negated = [f for f in cond.facts() if f.negated and f.name in checks
                           and checks[f.name].predicate.name == "connexity"]
                if not negated:
                    self.add(path + ("then",), f"rule '{spec['name']}': split_components needs a failed connexity "
                             "check in its condition (e.g. 'if: not connected'), to know the components")
            out.append(Rule(spec["name"], cond, action, str(spec.get("doc", "")), self.pos.pos(path)))
        return out

    def _labels(self, raw: Any, checks: Mapping[str, Check]) -> list[Label]:
        out: list[Label] = []
        if not isinstance(raw, list):
            return out
        default_at = None
        seen: set[str] = set()
        for i, spec in enumerate(raw):
            if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
                continue
            path = ("labels", i)
            if spec["name"] in seen:
                self.add(path + ("name",), f"label '{spec['name']}' is defined twice")
            seen.add(spec["name"])
            if default_at is not None:
                self.add(path, f"label '{spec['name']}' can never be given: label '{raw[default_at]['name']}' "
                         "before it has no 'if' and takes every cluster")
            cond = None
            if "if" in spec:
                cond = self._condition(spec["if"], path + ("if",), checks)
            else:
                default_at = i
            out.append(Label(spec["name"], cond, str(spec.get("doc", "")), self.pos.pos(path)))
        return out

    def _ground(self, raw: dict, checks: Mapping[str, Check]) -> GroundSpec:
        g = {**GROUND_DEFAULTS, **raw}
        needs = [c for c in checks.values() if c.predicate.needs_ground]
        normal = None if g["normal"] == "auto" else tuple(float(x) for x in g["normal"])
        cand = g.get("candidate")
        if normal is not None and sum(x * x for x in normal) == 0:
            self.add(("scene", "ground", "normal"), "the ground normal must not be the zero vector")
        if sum(float(x) ** 2 for x in g["fallback"]) == 0:
            self.add(("scene", "ground", "fallback"), "the fallback ground normal must not be the zero vector")
        if cand is not None and isinstance(cand, str):
            if cand not in checks and cand not in (self.data.get("checks") or {}):
                hint = did_you_mean(cand, list(checks))
                self.add(("scene", "ground", "candidate"), f"unknown check '{cand}'"
                         + (f" (did you mean '{hint}'?)" if hint else ""))
            elif cand in checks and checks[cand].predicate.needs_ground:
                self.add(("scene", "ground", "candidate"), f"check '{cand}' needs the ground itself "
                         f"('{checks[cand].predicate.name}'): it cannot be what finds the ground")
        elif needs and normal is None:
            first = needs[0]
            self.add(("checks", first.name, "predicate"),
                     f"check '{first.name}' uses the ground ('{first.predicate.name}'), found automatically, but "
                     "scene.ground.candidate does not name the check a ground candidate must pass "
                     "(e.g. 'candidate: planar'), nor does scene.ground.normal fix it")
        return GroundSpec(normal=normal, candidate=cand, min_points=int(g["min_points"]),
                          fallback=tuple(float(x) for x in g["fallback"]))

    def _merge(self, raw: Any, labels: list[Label]) -> MergeSpec | None:
        if not isinstance(raw, dict) or not isinstance(raw.get("merge_coplanar"), dict):
            return None
        m = raw["merge_coplanar"]
        self._label_ref(("post", "merge_coplanar", "label"), m.get("label"), [lb.name for lb in labels])
        return MergeSpec(label=str(m.get("label")), max_angle=float(m.get("max_angle", 10.0)),
                         max_offset=float(m.get("max_offset", 0.15)))

    def _label_ref(self, path: tuple, name: Any, names: list[str]) -> None:
        if isinstance(name, str) and name not in names:
            hint = did_you_mean(name, names)
            self.add(path, f"unknown label '{name}'" + (f" (did you mean '{hint}'?)" if hint else f"; labels: {', '.join(names)}"))

    def _post(self, raw: Any, checks: Mapping[str, Check], labels: list[Label]):
        """post.ground_model, post.relabel, post.ground_contact and post.ground_release."""
        if not isinstance(raw, dict):
            raw = {}
        names = [lb.name for lb in labels]
        gm = raw.get("ground_model")
        model = None
        if isinstance(gm, dict) and isinstance(gm.get("label"), str):
            self._label_ref(("post", "ground_model", "label"), gm["label"], names)
            model = GroundModelSpec(label=gm["label"], neighbours=int(gm.get("neighbours", 8)),
                                    radius=float(gm.get("radius", 3.0)), pos=self.pos.pos(("post", "ground_model"), key=True))
        relabel = self._relabel(raw.get("relabel"), checks, names, model)
        contact = self._contact(raw.get("ground_contact"), checks, names, model)
        release = self._release(raw.get("ground_release"), names, model)
        return model, relabel, contact, release

    def _relabel(self, raw: Any, checks: Mapping[str, Check], names: list[str],
                 model: GroundModelSpec | None) -> list[Relabel]:
        out: list[Relabel] = []
        seen: set[str] = set()
        for i, spec in enumerate(raw if isinstance(raw, list) else []):
            path = ("post", "relabel", i)
            if not isinstance(spec, dict) or not all(isinstance(spec.get(k), str) for k in ("name", "from", "to")):
                continue  # the schema reported it
            if spec["name"] in seen:
                self.add(path + ("name",), f"relabel rule '{spec['name']}' is defined twice")
            seen.add(spec["name"])
            self._label_ref(path + ("from",), spec["from"], names)
            self._label_ref(path + ("to",), spec["to"], names)
            if spec["from"] == spec["to"]:
                self.add(path + ("to",), f"relabel rule '{spec['name']}' changes nothing: from and to are both "
                         f"'{spec['to']}'")
            cond = self._condition(spec.get("if"), path + ("if",), checks) if "if" in spec else None
            if cond is None:
                continue
            if model is None:
                uses = [f.name for f in cond.facts() if f.name in checks and checks[f.name].predicate.needs_ground_model]
                if uses:
                    self.add(path + ("if",), f"relabel rule '{spec['name']}': check '{uses[0]}' needs the local ground "
                             "surface, but post.ground_model does not declare it")
            out.append(Relabel(spec["name"], spec["from"], spec["to"], cond, str(spec.get("doc", "")),
                               self.pos.pos(path)))
        return out

    def _surface_step(self, key: str, raw: Any, model: GroundModelSpec | None) -> bool:
        """Whether post.<key> is there with a numeric tolerance; it needs post.ground_model."""
        tol = raw.get("tolerance") if isinstance(raw, dict) else None
        if not isinstance(tol, (int, float)) or isinstance(tol, bool):
            return False  # absent, or the schema reported it
        if model is None:
            self.add(("post", key), f"{key} needs post.ground_model (the surface points are measured against)",
                     key=True)
        return True

    def _own_label(self, path: tuple, what: str, name: Any, model: GroundModelSpec | None) -> None:
        if model is not None and name == model.label:
            self.add(path, f"{what} '{name}', the ground model's own label, changes nothing")

    def _contact(self, raw: Any, checks: Mapping[str, Check], names: list[str],
                 model: GroundModelSpec | None) -> ContactSpec | None:
        if not self._surface_step("ground_contact", raw, model):
            return None
        src = raw.get("from")
        if isinstance(src, list):
            for j, name in enumerate(src):
                self._label_ref(("post", "ground_contact", "from", j), name, names)
                self._own_label(("post", "ground_contact", "from", j), "ground_contact from", name, model)
            sources = tuple(x for x in src if isinstance(x, str))
        else:
            sources = tuple(n for n in names if model is None or n != model.label)
        cond = self._condition(raw["if"], ("post", "ground_contact", "if"), checks) if "if" in raw else None
        return ContactSpec(float(raw["tolerance"]), sources, self.pos.pos(("post", "ground_contact"), key=True), cond)

    def _release(self, raw: Any, names: list[str], model: GroundModelSpec | None) -> ReleaseSpec | None:
        if not isinstance(raw, dict) or not isinstance(raw.get("to"), str) \
                or not self._surface_step("ground_release", raw, model):
            return None
        self._label_ref(("post", "ground_release", "to"), raw["to"], names)
        self._own_label(("post", "ground_release", "to"), "ground_release to", raw["to"], model)
        return ReleaseSpec(float(raw["tolerance"]), raw["to"], self.pos.pos(("post", "ground_release"), key=True))

    def _model_checks_placed(self, checks: Mapping[str, Check], rules: list[Rule], labels: list[Label]) -> None:
        """A check on the local ground surface cannot decide splits or labels: the surface is made
        of the labelled clusters."""
        def bad(cond: Condition | None) -> list[str]:
            return [] if cond is None else [f.name for f in cond.facts()
                                           if f.name in checks and checks[f.name].predicate.needs_ground_model]

        raw_rules = self.data.get("rules") if isinstance(self.data.get("rules"), list) else []
        for i, spec in enumerate(raw_rules):
            rule = next((r for r in rules if isinstance(spec, dict) and r.name == spec.get("name")), None)
            for name in bad(rule.condition if rule else None)[:1]:
                self.add(("rules", i, "if"), f"rule '{rule.name}': check '{name}' measures against the local ground "
                         "surface, which exists only once clusters are labelled; use it in post.relabel")
        raw_labels = self.data.get("labels") if isinstance(self.data.get("labels"), list) else []
        for i, lab in enumerate(labels):
            for name in bad(lab.condition)[:1]:
                if i < len(raw_labels):
                    self.add(("labels", i, "if"), f"label '{lab.name}': check '{name}' measures against the local "
                             "ground surface, which is built from the labels; use it in post.relabel")


def _article(t: Any) -> str:
    if isinstance(t, list):
        return " or ".join(_article(x) for x in t)
    return {"object": "a mapping", "array": "a list", "string": "a string", "number": "a number",
            "integer": "an integer", "boolean": "true or false"}.get(t, str(t))
