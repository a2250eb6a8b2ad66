"""Rule bases: YAML files of application knowledge, loaded into immutable objects with the
source position of every part, and validated with ALL problems reported at once.

Each problem prints as ``file:line:col: message`` (1-based), followed by the offending source
line and a caret under the offending value (after yamllint and strictyaml). Validation is the
JSON Schema shipped in ``rules/rule-base.schema.json`` plus what a schema cannot say: known
predicates ("did you mean"), their parameters, thresholds within the predicate's range,
references between checks, rules and labels, and contradictory settings. Conditions that can
never hold are warnings (:attr:`RuleBase.warnings`), not problems.

The YAML is read within bounds, so that no file can hang the reader or exhaust the memory: a
size (:data:`MAX_RULE_FILE_BYTES`), a nesting depth (:data:`MAX_NESTING`,
:data:`MAX_CONDITION_DEPTH`) and the nodes aliases may repeat (:data:`MAX_ALIAS_NODES`); numbers
must be finite. Each is a problem at its position, as any other.
"""
from __future__ import annotations

import functools
import copy
import hashlib
import json
import os
import math
import reprlib
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
import yaml.cyaml  # noqa: F401 (libyaml when present)

if TYPE_CHECKING:  # imported when a file is first validated (_KnownValid: not for a file validated before)
    from jsonschema import Draft202012Validator

from kbs.errors import ExitCode, KbsError, raise_if_interrupted
from kbs.knowledge.engine_settings import ENGINE_DEFAULTS as _ENGINE_DEFAULTS
from kbs.knowledge.predicates import Predicate, PredicateRegistry, did_you_mean
from kbs.knowledge.segmentation import FAR_OUTLIER_FACTOR

SCHEMA_FILE = "rule-base.schema.json"
ACTIONS = ("split", "split_components", "reject")

#: The engine section's defaults, its allowed values (the schema's engine part) and docs: the
#: engine's table of settings (kbs.inference.settings, read by kbs.knowledge.engine_settings).
ENGINE_DEFAULTS: Mapping[str, Any] = _ENGINE_DEFAULTS
#: Limits are per cluster. max_clusters (None: absent) is an optional cap on the whole split tree,
#: which makes a point's result depend on the rest of the file; no shipped rule base sets it.
LIMIT_DEFAULTS: dict[str, Any] = {"max_depth": 8, "min_points": 30, "max_clusters": None}
GROUND_DEFAULTS: dict[str, Any] = {"normal": "auto", "candidate": None, "min_points": 500, "fallback": [0.0, 0.0, 1.0],
                                   "plane": None, "choose": None, "sensor_above": False}


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
    """A problem of a rule file at a position; a warning does not make the file invalid."""

    pos: SourcePos
    message: str
    source_line: str = ""
    warning: bool = False

    def format(self) -> str:
        out = f"{self.pos}: {'warning: ' if self.warning else ''}{self.message}"
        if self.source_line:
            line, caret = _window(self.source_line, self.pos.col)
            out += f"\n    {line}\n    {' ' * caret}^"
        return out


def _window(line: str, col: int, width: int = 120) -> tuple[str, int]:
    """The part of a source line to quote (at most ``width`` characters around column ``col``,
    '...' where it is cut; a tab shown as a space so that the caret stays under its character)
    and the caret's offset in it."""
    line = line.replace("\t", " ")
    if len(line) <= width:
        return line, col - 1
    start = max(0, min(col - 1 - width // 2, len(line) - width))
    end = start + width
    head, tail = ("..." if start > 0 else ""), ("..." if end < len(line) else "")
    return head + line[start:end] + tail, col - 1 - start + len(head)


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
    """Maps a path in the YAML document (keys and indices) to the position of its value and key.

    The walk goes over the document as the program sees it (an alias stands for the node it
    names), which the loader has bounded (:data:`MAX_ALIAS_NODES`, :data:`MAX_NESTING`); it is
    iterative, whatever the depth."""

    def __init__(self, file: str, text: str, root: yaml.Node | None) -> None:
        self.file = file
        self.lines = text.splitlines()
        self.values: dict[tuple, yaml.Mark] = {}
        self.keys: dict[tuple, yaml.Mark] = {}
        self.duplicates: list[tuple[tuple, yaml.Mark]] = []
        if root is not None:
            self._walk(root)

    def _walk(self, root: yaml.Node) -> None:
        reported: set[int] = set()  # a mapping reached through several aliases reports its duplicates once
        stack: list[tuple[yaml.Node, tuple]] = [(root, ())]
        while stack:
            node, path = stack.pop()
            self.values[path] = node.start_mark
            if isinstance(node, yaml.MappingNode):
                seen = set()
                for k, v in node.value:
                    key = k.value if isinstance(k, yaml.ScalarNode) else id(k)
                    if key in seen and id(k) not in reported:
                        reported.add(id(k))
                        self.duplicates.append((path + (key,), k.start_mark))
                    seen.add(key)
                    self.keys[path + (key,)] = k.start_mark
                    stack.append((v, path + (key,)))
            elif isinstance(node, yaml.SequenceNode):
                stack.extend((v, path + (i,)) for i, v in enumerate(node.value))

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

    def problem(self, path: tuple, message: str, *, key: bool = False, warning: bool = False) -> Problem:
        pos = self.pos(path, key=key)
        return Problem(pos, message, self.line(pos.line), warning)

    def line(self, line: int) -> str:
        """The source line (1-based), '' beyond the text."""
        return self.lines[line - 1] if 0 < line <= len(self.lines) else ""


def _where(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "the rule base"


def _meant_branch(err: Any) -> list:
    """The errors of the one form of a ``oneOf``/``anyOf`` schema error ``err`` that the value's type
    (or constant) fits, when exactly one fits and has errors of its own: what is wrong with the value
    in the form it was written in (e.g. ``far_outliers: {factor: 0}``: the factor's bound, at the
    factor). Empty otherwise (a value of no form's type: the caller names the forms)."""
    branches: dict[Any, list] = {}
    for sub in err.context or ():
        branches.setdefault(sub.relative_schema_path[0] if sub.relative_schema_path else None, []).append(sub)
    root = tuple(err.absolute_path)
    fitting = [errs for errs in branches.values()
               if not any(e.validator in ("type", "const") and tuple(e.absolute_path) == root for e in errs)]
    return fitting[0] if len(fitting) == 1 and len(branches) > 1 else []


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
    items: tuple[Condition, ...] = ()

    def evaluate(self, fact: Callable[[str], bool]) -> bool:
        """Evaluate lazily (checks are measured only when needed)."""
        if self.kind == "fact":
            return fact(self.name) != self.negated
        if self.kind == "all":
            return all(c.evaluate(fact) for c in self.items)
        return any(c.evaluate(fact) for c in self.items)

    def facts(self) -> Iterator[Condition]:
        if self.kind == "fact":
            yield self
        for c in self.items:
            yield from c.facts()

    @functools.cached_property
    def names(self) -> tuple[str, ...]:
        """The checks it names, each once, in order (asked for every cluster a rule or label decides)."""
        return tuple(dict.fromkeys(f.name for f in self.facts()))

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
    #: the action's part (:mod:`kbs.knowledge.actions`, or a plugin's)
    part: Any = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Label:
    name: str
    condition: Condition | None
    doc: str
    pos: SourcePos


@dataclass(frozen=True)
class PlaneSpec:
    """scene.ground.plane: a candidate whose robust plane holds ``min_inlier_share`` of its points
    within ``inlier_distance`` (length units), and whose normal lies within ``max_tilt`` degrees of
    the fallback normal (None: any direction), is a ground plane, even if it fails the candidate check.
    ``planes``: how many robust planes a candidate may give, one after another: when one is refused
    for its direction (``max_tilt``, ``sensor_above``), the next is the robust plane of the points
    the earlier ones do not hold, its share and ``min_points`` counted on those points.
    ``share_of``: the points the share is counted among: 'all', or 'not_above' (those not above
    the plane, on the sensor's side farther than ``inlier_distance``: what stands on the ground
    does not count against it). ``refit``: a candidate that passes the candidate check gives its
    robust plane too (when it holds the share and ``min_points``), not the plane of all its points.
    ``max_thickness`` (length units, None: any): a robust plane whose points spread more than this
    across it (their standard deviation) is a slab cut through a volume, not a surface."""

    inlier_distance: float
    min_inlier_share: float
    max_tilt: float | None
    pos: SourcePos
    planes: int = 1
    share_of: str = "all"
    refit: bool = False
    max_thickness: float | None = None


@dataclass(frozen=True)
class SupportSpec:
    """scene.ground.choose: supporting: of the candidates that give a plane, the ground is the one
    with the most points of the scan standing on it: between ``min_height`` and ``max_height``
    (length units) above its plane, towards the sensor, inside its outline (the convex hull of
    its plane's points). A table holds the objects on it; a large face of one of them holds
    nothing, or only what is stacked on it."""

    min_height: float
    max_height: float
    pos: SourcePos


@dataclass(frozen=True)
class GroundSpec:
    normal: tuple[float, float, float] | None  # None = auto
    candidate: str | None
    min_points: int
    fallback: tuple[float, float, float]
    #: the robust plane test of a candidate (None: only the candidate check finds the ground)
    plane: PlaneSpec | None = None
    #: which plane is the ground: None, the closest to the sensor (the paper's rule); or the one
    #: supporting the most points
    support: SupportSpec | None = None
    #: the sensor sees the ground from above: a candidate plane with the sensor on the side
    #: opposite the fallback normal (seen from underneath: a box's face turned towards a camera
    #: looking down, a ceiling) is not the ground
    sensor_above: bool = False


#: Evenly spaced values a ``tune: {min, max}`` mark tries when it gives no ``steps``.
TUNE_STEPS = 5
#: The most ``steps`` a mark may give (the schema's maximum).
TUNE_MAX_STEPS = 101
#: The most settings the marks of one file may make together (the product of their numbers of
#: values): ``kbs tune`` holds every setting and its scores, and at a second a segmentation a grid
#: this size already takes more than a day per scan.
TUNE_MAX_SETTINGS = 100_000


@dataclass(frozen=True)
class Tunable:
    """A threshold marked ``tune:`` in a rule file: the values ``kbs tune`` tries for it.

    Attributes
    ----------
    path : tuple of str
        Where the value is in the document, e.g. ``("checks", "planar", "max")`` or
        ``("post", "ground_contact", "tolerance")``.
    value : float
        The value the file gives it now.
    values : tuple of float
        The candidates, ascending, the current value among them.
    integer : bool
        Whether the field takes integers (``ground_model.neighbours``).
    pos : SourcePos
        Position of the value in the file (what ``kbs tune`` replaces).
    mark : SourcePos
        Position of the ``tune`` key.
    """

    path: tuple[str, ...]
    value: float
    values: tuple[float, ...]
    integer: bool
    pos: SourcePos
    mark: SourcePos

    @property
    def name(self) -> str:
        """'checks.planar.max', 'post.ground_contact.tolerance'."""
        return ".".join(str(p) for p in self.path if not isinstance(p, int))


@dataclass(frozen=True)
class TileSpec:
    """``limits.tile``: ``kbs run`` segments a cloud wider than ``wider_than`` (along either axis of
    the ground plane, in the rule base's unit) in square tiles of ``size`` with the default buffer,
    as ``--tile size`` does."""

    size: float
    wider_than: float


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
    path: str
    text: str = field(repr=False)
    #: the post steps, in the order they run (:mod:`kbs.knowledge.post`, or a plugin's)
    post: tuple[Any, ...] = ()
    #: ASPRS classification code of each label (and of 'noise', the rejected points) in LAS output.
    asprs_classes: Mapping[str, int] | None = None
    #: spacing: the median point spacing [min, max] the rule base suits (its unit); None: not declared.
    spacing: tuple[float, float] | None = None
    #: far outliers (``scene.far_outliers``): the factor of :func:`~kbs.knowledge.segmentation.far_outliers`
    #: (points that far beyond the box of the cloud's central 98 % are set aside as noise first); None: off
    far_outliers: float | None = FAR_OUTLIER_FACTOR
    #: what is valid but cannot be meant: conditions that can never hold (``kbs rules check``
    #: prints them; they do not make the file invalid)
    warnings: tuple[Problem, ...] = ()
    #: the thresholds marked ``tune:`` (for ``kbs tune``; a run ignores the marks), in file order
    tunables: tuple[Tunable, ...] = ()

    @property
    def label_names(self) -> list[str]:
        return [lb.name for lb in self.labels]

    @property
    def tile(self) -> TileSpec | None:
        """``limits.tile``: the tiles ``kbs run`` cuts a cloud wider than ``wider_than`` into, or None."""
        t = self.limits.get("tile")
        return None if t is None else TileSpec(float(t["size"]), float(t["wider_than"]))

    def step(self, key: str) -> Any:
        """The first post step named ``key``, or None."""
        return next((s for s in self.post if s.key == key), None)

    @property
    def merge(self) -> Any:
        """The merge_coplanar step, or None."""
        return self.step("merge_coplanar")

    @property
    def ground_model(self) -> Any:
        """The (first) ground_model step, or None."""
        return self.step("ground_model")

    @property
    def relabel(self) -> tuple[Any, ...]:
        """The relabel rules of every relabel step, in order."""
        return tuple(r for s in self.post if s.key == "relabel" for r in s.rules)

    @property
    def contact(self) -> Any:
        """The (first) ground_contact step, or None."""
        return self.step("ground_contact")

    @property
    def release(self) -> Any:
        """The (first) ground_release step, or None."""
        return self.step("ground_release")

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


@lru_cache(maxsize=8)
def _schema_validator(actions: tuple[str, ...] = ()) -> Draft202012Validator:
    """A validator of :func:`schema` with its non-recursive definitions ('name', 'vector3')
    written out where they are used: the same schema, validated some 1.5 x faster (a reference
    costs a look-up for each of the thousands of names a large file holds).

    ``actions``: the actions a rule may take (the registry's: plugins add some). ``post`` is
    checked step by step, each against its own part's schema (:meth:`_Validator._post`)."""
    doc = copy.deepcopy(schema())
    if actions:
        doc["properties"]["rules"]["items"]["properties"]["then"] = {"enum": list(actions)}
    doc["properties"]["post"] = {}
    defs = doc.get("$defs", {})
    plain = {f"#/$defs/{k}": v for k, v in defs.items() if "$ref" not in json.dumps(v)}

    def inline(node: Any) -> Any:
        if isinstance(node, dict):
            out = {k: inline(v) for k, v in node.items()}
            target = plain.get(out.get("$ref")) if isinstance(out.get("$ref"), str) else None
            if target is not None:
                del out["$ref"]
                out = {**target, **out}
            return out
        if isinstance(node, list):
            return [inline(v) for v in node]
        return node

    from jsonschema import Draft202012Validator

    return Draft202012Validator(inline(doc))


@lru_cache(maxsize=64)
def _fragment_validator(step: Any) -> Draft202012Validator:
    """A validator of one post step's spec: its schema, with the rule-file schema's definitions."""
    from jsonschema import Draft202012Validator

    return Draft202012Validator({**step.schema, "$defs": schema().get("$defs", {})})


class _KnownValid:
    """The rule files that passed the JSON Schema before, so that a process loading one again
    neither imports jsonschema (about 50 ms) nor runs it (10-20 ms): the SHA-256 of what the schema
    checks decides (the file's data, the schema, the actions and post steps the registry knows,
    plugins' included, and jsonschema's version), kept in ``kbs-valid-rules`` in the compiled
    kernels' state folder (:func:`kbs.inference._flags._state_dir`). Only a file that passed every
    check (the schema and kbs's own) is written; kbs's own checks run every time. Any failure to
    read, hash or write means the schema is run, as without it."""

    FILE = "kbs-valid-rules"
    KEEP = 256  #: the most recent keys kept

    @staticmethod
    def key(data: Any, registry: PredicateRegistry) -> str | None:
        try:
            from importlib.metadata import version

            h = hashlib.sha256()
            h.update(json.dumps(_KnownValid._typed(data), sort_keys=True, default=repr).encode())
            h.update(json.dumps(schema(), sort_keys=True).encode())
            h.update(repr(tuple(registry.actions)).encode())
            h.update(json.dumps({k: getattr(v, "schema", None) for k, v in registry.post_steps.items()},
                                sort_keys=True, default=repr).encode())
            h.update(version("jsonschema").encode())
            return h.hexdigest()
        except Exception:  # noqa: BLE001 - keys of mixed types, a schema that does not dump: validate
            return None

    @staticmethod
    def _typed(node: Any) -> Any:
        """``node`` with each mapping key written with its type (``int:1`` and ``str:'1'`` differ:
        the schema may pass one and refuse the other)."""
        if isinstance(node, dict):
            return {f"{type(k).__name__}:{k!r}": _KnownValid._typed(v) for k, v in node.items()}
        if isinstance(node, list):
            return [_KnownValid._typed(v) for v in node]
        return node

    @classmethod
    def _path(cls) -> Path:
        from kbs.inference import _flags

        return _flags._state_dir() / cls.FILE

    @classmethod
    def known(cls, key: str | None) -> bool:
        if key is None:
            return False
        try:
            return key in cls._path().read_text().split()
        except (OSError, ValueError):
            return False

    @classmethod
    def add(cls, key: str | None) -> None:
        if key is None:
            return
        try:
            path = cls._path()
            try:
                keys = path.read_text().split()
            except FileNotFoundError:
                keys = []
            keys = [k for k in keys if k != key][-(cls.KEEP - 1):] + [key]
            tmp = path.with_name(f"{cls.FILE}.{os.getpid()}.tmp")
            tmp.write_text("\n".join(keys) + "\n")
            os.replace(tmp, path)
        except (OSError, ValueError):
            pass


def _fragment_field(step: Any, field: str) -> dict[str, Any]:
    """The schema of one field of a post step's spec ({} when it has none)."""
    props = step.schema.get("properties", {})
    return props.get(field, {}) if isinstance(props, dict) else {}


class _StepContext:
    """What a part's ``parse``/``validate`` may ask of the file being read
    (:class:`kbs.knowledge.parts.SpecContext`)."""

    def __init__(self, v: _Validator, path: tuple, labels: list[str], checks: Mapping[str, Check],
                 earlier: tuple) -> None:
        self.v, self.path, self.labels, self.checks, self.earlier = v, path, labels, checks, earlier

    def add(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.v.add(path, message, key=key)

    def warn(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.v.warn(path, message, key=key)

    def pos(self, path: tuple, *, key: bool = False) -> SourcePos:
        return self.v.pos.pos(path, key=key)

    def label_ref(self, path: tuple, name: Any) -> None:
        self.v._label_ref(path, name, self.labels)

    def condition(self, raw: Any, path: tuple) -> Condition | None:
        return self.v._condition(raw, path, self.checks)

    def never(self, cond: Condition, path: tuple, what: str) -> None:
        self.v._never(cond, path, self.checks, what)

    def number(self, value: Any, default: float, kind: type = float) -> Any:
        return _number(value, default, kind)


def shipped_rule_bases() -> list[str]:
    """Names of the rule bases shipped with kbs."""
    return sorted(p.name[:-5] for p in resources.files("kbs.rules").iterdir() if p.name.endswith(".yaml"))


def shipped_text(name: str) -> str:
    return resources.files("kbs.rules").joinpath(f"{name}.yaml").read_text(encoding="utf-8")


#: Example rule files are named ``examples/NAME`` (``kbs rules show examples/tabletop``).
EXAMPLES_PREFIX = "examples/"


def examples_folder() -> Path | None:
    """Where the examples are installed (``kbs.examples``: rules/, plugins/, data/), or None."""
    try:
        return Path(str(resources.files("kbs.examples")))
    except ModuleNotFoundError:
        return None


def example_rule_bases() -> list[str]:
    """Names (``examples/tabletop``, ...) of the example rule files installed with kbs."""
    folder = examples_folder()
    if folder is None or not (folder / "rules").is_dir():
        return []
    return sorted(EXAMPLES_PREFIX + p.name[:-5] for p in (folder / "rules").iterdir() if p.name.endswith(".yaml"))


def resolve(name_or_path: str) -> tuple[str, str]:
    """``(display path, text)`` of a rule base given as a path or a shipped name.

    A file larger than :data:`MAX_RULE_FILE_BYTES` is refused before it is read; one that is not
    UTF-8 is refused at the line and column of its first bad byte."""
    p = Path(name_or_path)
    if p.is_file():
        where = SourcePos(str(name_or_path), 1, 1)
        try:
            size = p.stat().st_size
            if size > MAX_RULE_FILE_BYTES:
                raise RuleFileError([Problem(where, _too_large(size))])
            data = p.read_bytes()
        except OSError as exc:
            raise RuleFileError([Problem(where, f"cannot read: {exc.strerror or exc}")]) from exc
        if len(data) > MAX_RULE_FILE_BYTES:  # grew since
            raise RuleFileError([Problem(where, _too_large(len(data)))])
        return str(name_or_path), _decode(data, str(name_or_path))
    if p.exists() and not (p.is_dir() and str(name_or_path) in shipped_rule_bases()):
        # a folder named as a shipped rule base (`abw/` where `--rules abw` is run) is not a rule
        # file: the name means the shipped one
        raise RuleFileError([Problem(SourcePos(str(name_or_path), 1, 1), "not a file")])
    name = p.name[:-5] if p.name.endswith(".yaml") and p.parent == Path(".") else str(name_or_path)
    if name in shipped_rule_bases():
        return f"{name}.yaml", shipped_text(name)
    folder = examples_folder()
    if folder is not None and name in example_rule_bases():  # examples/NAME: an installed example (kbs rules list)
        return f"{name}.yaml", (folder / "rules" / f"{name.removeprefix(EXAMPLES_PREFIX)}.yaml").read_text(encoding="utf-8")
    hint = did_you_mean(name, shipped_rule_bases())
    msg = f"no such file, nor a shipped rule base (shipped: {', '.join(shipped_rule_bases())})"
    if hint:
        msg += f"; did you mean '{hint}'?"
    raise RuleFileError([Problem(SourcePos(str(name_or_path), 1, 1), msg)])


def _too_large(size: int) -> str:
    return (f"the file is {size:,} bytes; a rule file may have at most {MAX_RULE_FILE_BYTES:,} "
            f"(the shipped ones have under 5,000)")


def _decode(data: bytes, file: str) -> str:
    """The text of a UTF-8 file; a byte that is not UTF-8 is a problem at its line and column."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        start = data.rfind(b"\n", 0, exc.start) + 1
        end = data.find(b"\n", exc.start)
        line = data.count(b"\n", 0, exc.start) + 1
        col = len(data[start:exc.start].decode("utf-8", errors="replace")) + 1
        src = data[start:None if end < 0 else end].decode("utf-8", errors="replace").rstrip("\r")
        raise RuleFileError([Problem(SourcePos(file, line, col),
                                     f"not UTF-8: byte 0x{data[exc.start]:02x} cannot be decoded ({exc.reason}); "
                                     "save the file as UTF-8", src)]) from None


def load_rule_base(name_or_path: str, registry: PredicateRegistry | None = None) -> RuleBase:
    """Load and validate a rule base (a path or a shipped name); raises :class:`RuleFileError`
    listing every problem."""
    display, text = resolve(name_or_path)
    return parse_rule_base(text, display, registry or PredicateRegistry.default())


# --- reading YAML within bounds ------------------------------------------------------------------

#: A rule file larger than this is refused before it is read (the shipped ones are ~4 kB; 1 MB is
#: some 7,000 checks).
MAX_RULE_FILE_BYTES = 1_000_000
#: Nodes (scalars, lists, mappings) all the aliases of a document may repeat together. An alias
#: costs nothing in the file and its whole node to every pass over the document: nine levels of
#: nine aliases (a "billion laughs", 1 kB) repeat 9**9 nodes. Reusing a condition or parameters
#: through an anchor repeats tens of nodes.
MAX_ALIAS_NODES = 10_000
#: Nesting of lists and mappings, aliases expanded. Every pass over the document (the schema's
#: among them) recurses, one or a few Python frames per level; 100 levels stay well within
#: Python's default limit of 1,000 frames, and hold conditions nested MAX_CONDITION_DEPTH deep.
MAX_NESTING = 100
#: Nesting of conditions (a list, {all: ...} or {any: ...} inside another). The shipped rule bases
#: nest 1 deep; 32 is beyond anything a reader can follow, and {all: [...]} being two YAML
#: levels, 32 conditions deep sit within MAX_NESTING.
MAX_CONDITION_DEPTH = 32

_FLOAT_TAG = "tag:yaml.org,2002:float"
_INT_TAG = "tag:yaml.org,2002:int"


class _Refused(Exception):
    """What the bounded loader refuses: a position (a yaml Mark) and a message."""

    def __init__(self, mark: yaml.Mark, message: str) -> None:
        super().__init__(message)
        self.mark, self.message = mark, message


class _BoundedComposer(yaml.composer.Composer):
    """PyYAML's composer (events to nodes) with bounds, checked as the nodes come.

    Every node records its size and height with aliases expanded (a sum over its children, each
    counted once: linear in the file). An alias adds the size of the node it names to a running
    total: past :data:`MAX_ALIAS_NODES` it is refused at its position, before anything walks the
    expansion. So is a node deeper than :data:`MAX_NESTING` (an alias counts with the height of
    its node), and an alias inside the node it names (a recursive structure). Numbers that are
    not finite, or too large for a float, are collected in ``self.bad_numbers``.
    """

    def __init__(self) -> None:
        super().__init__()
        self._depth = 0
        self._alias_nodes = 0
        self._size: dict[int, int] = {}  # id(node) -> nodes with aliases expanded; absent while open
        self._height: dict[int, int] = {}
        self.bad_numbers: list[tuple[yaml.Mark, str]] = []

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            target = self.anchors.get(event.anchor)
            if target is not None:  # (an undefined alias: PyYAML's own error)
                size = self._size.get(id(target))
                if size is None:
                    raise _Refused(event.start_mark, f"alias *{event.anchor} is inside the node it names "
                                                     "(a structure that contains itself)")
                self._alias_nodes += size
                if self._alias_nodes > MAX_ALIAS_NODES:
                    raise _Refused(event.start_mark,
                                   f"alias *{event.anchor} repeats {size:,} nodes: the aliases of this file would "
                                   f"repeat more than {MAX_ALIAS_NODES:,} nodes in all (an alias bomb?); write the "
                                   "values out, or use fewer aliases")
                if self._depth + self._height[id(target)] > MAX_NESTING:
                    raise _Refused(event.start_mark, _too_deep())
            return super().compose_node(parent, index)
        if self._depth >= MAX_NESTING:
            raise _Refused(self.peek_event().start_mark, _too_deep())
        self._depth += 1
        node = super().compose_node(parent, index)
        self._depth -= 1
        if isinstance(node, yaml.ScalarNode):
            self._size[id(node)], self._height[id(node)] = 1, 1
            if node.tag in (_FLOAT_TAG, _INT_TAG):
                self._check_number(node)
            return node
        children = ([c for pair in node.value for c in pair] if isinstance(node, yaml.MappingNode)
                    else node.value)
        self._size[id(node)] = 1 + sum(self._size[id(c)] for c in children)
        self._height[id(node)] = 1 + max((self._height[id(c)] for c in children), default=0)
        return node

    def _check_number(self, node: yaml.ScalarNode) -> None:
        text = node.value
        if node.tag == _INT_TAG:
            digits = sum(ch.isdigit() for ch in text)
            if digits > 300:  # beyond any float, and Python refuses to read 4,300 digits
                self.bad_numbers.append((node.start_mark, f"{_clip(text)} ({digits:,} digits) is too large: "
                                                          "a number must be within +-1.8e308"))
            return
        try:
            value = yaml.constructor.SafeConstructor.construct_yaml_float(self, node)
        except ValueError:
            return  # the constructor says what is wrong with it
        if not math.isfinite(value):
            self.bad_numbers.append((node.start_mark, f"{text} is not a finite number: thresholds, positions, "
                                                      "vectors and settings must be finite"
                                     + ("" if text.lstrip("+-").startswith(".") else " (it overflows)")))


def _too_deep() -> str:
    return (f"nested more than {MAX_NESTING} levels deep (lists and mappings); a condition may nest at most "
            f"{MAX_CONDITION_DEPTH} levels")


def _clip(text: str, keep: int = 12) -> str:
    return text if len(text) <= 2 * keep + 3 else f"{text[:keep]}...{text[-keep:]}"


class _ConstructorMixin:
    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep)
        except (ValueError, ArithmeticError) as exc:  # an impossible date, a float that is not one
            raise _Refused(node.start_mark, f"cannot read {_clip(str(node.value), 30)}: {exc}") from exc


class _PyLoader(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser, _BoundedComposer, _ConstructorMixin,
                yaml.constructor.SafeConstructor, yaml.resolver.Resolver):
    """The pure-Python loader, bounded (its messages say what was expected, and what was found)."""

    def __init__(self, stream: str) -> None:
        yaml.reader.Reader.__init__(self, stream)
        yaml.scanner.Scanner.__init__(self)
        yaml.parser.Parser.__init__(self)
        _BoundedComposer.__init__(self)
        yaml.constructor.SafeConstructor.__init__(self)
        yaml.resolver.Resolver.__init__(self)


if getattr(yaml, "__with_libyaml__", False):
    class _CLoader(_BoundedComposer, _ConstructorMixin, yaml.cyaml.CParser, yaml.constructor.SafeConstructor,
                   yaml.resolver.Resolver):
        """The same bounded composer over libyaml's events (the parser in C: 3 x faster)."""

        def __init__(self, stream: str) -> None:
            yaml.cyaml.CParser.__init__(self, stream)
            _BoundedComposer.__init__(self)
            yaml.constructor.SafeConstructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)

    _FAST_LOADER: type = _CLoader
else:  # pragma: no cover - PyYAML without libyaml
    _FAST_LOADER = _PyLoader


def _load(text: str, loader_class: type) -> tuple[yaml.Node | None, Any, list[tuple[yaml.Mark, str]]]:
    """(root node, data, bad numbers) of a YAML document; raises yaml.YAMLError or _Refused."""
    loader = loader_class(text)
    try:
        root = loader.get_single_node()
        if loader.bad_numbers or root is None:
            return root, None, loader.bad_numbers
        return root, _construct(loader, root), []
    finally:
        loader.dispose()


_STR_TAG, _SEQ_TAG, _MAP_TAG = "tag:yaml.org,2002:str", "tag:yaml.org,2002:seq", "tag:yaml.org,2002:map"
_MERGE_TAG = "tag:yaml.org,2002:merge"


def _construct(loader: Any, root: yaml.Node) -> Any:
    """The data of a composed document, as PyYAML's SafeConstructor makes it (an alias is the same
    object as its anchor), 2 x faster: plain strings, lists and mappings are built here, anything
    else (numbers, dates, merge keys, sets, unknown tags) by the constructor. Recursive, at most
    MAX_NESTING deep (the composer saw to it)."""
    done: dict[int, Any] = {}
    scalar = loader.yaml_constructors

    def build(node: yaml.Node) -> Any:
        got = done.get(id(node), done)
        if got is not done:
            return got
        if isinstance(node, yaml.ScalarNode):
            if node.tag == _STR_TAG:
                value = node.value
            else:
                make = scalar.get(node.tag)
                value = make(loader, node) if make is not None else loader.construct_object(node, deep=True)
        elif isinstance(node, yaml.SequenceNode) and node.tag == _SEQ_TAG:
            value = done[id(node)] = []
            value.extend(build(c) for c in node.value)
        elif isinstance(node, yaml.MappingNode) and node.tag == _MAP_TAG \
                and not any(k.tag == _MERGE_TAG for k, _ in node.value):
            value = done[id(node)] = {}
            for k, v in node.value:
                key = build(k)
                try:
                    hash(key)
                except TypeError:
                    raise yaml.constructor.ConstructorError("while constructing a mapping", node.start_mark,
                                                            "found unhashable key", k.start_mark) from None
                value[key] = build(v)
        else:
            value = loader.construct_object(node, deep=True)
        done[id(node)] = value
        return value

    try:
        return build(root)
    except (ValueError, ArithmeticError) as exc:  # from a scalar built here: find which
        bad = next((n for n in _scalars(root) if _fails(loader, n)), root)
        raise _Refused(bad.start_mark, f"cannot read {_clip(str(bad.value), 30)}: {exc}") from exc


def _scalars(root: yaml.Node) -> Iterator[yaml.ScalarNode]:
    seen, stack = set(), [root]
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.ScalarNode):
            yield node
        elif isinstance(node, yaml.MappingNode):
            stack.extend(reversed([c for pair in node.value for c in pair]))
        else:
            stack.extend(reversed(node.value))


def _fails(loader: Any, node: yaml.ScalarNode) -> bool:
    make = loader.yaml_constructors.get(node.tag)
    try:
        make and make(loader, node)
    except (ValueError, ArithmeticError):
        return True
    return False


def _read_yaml(text: str, file: str) -> tuple[yaml.Node | None, Any]:
    """The root node (positions) and the data of a rule file's text, within the bounds; every
    problem is a :class:`RuleFileError` with its position."""
    lines = text.splitlines()

    def problem(line: int, col: int, message: str) -> Problem:
        return Problem(SourcePos(file, line, col), message, lines[line - 1] if 0 < line <= len(lines) else "")

    try:
        try:
            root, data, bad = _load(text, _FAST_LOADER)
        except (yaml.YAMLError, UnicodeError):  # UnicodeError: libyaml cannot encode a lone surrogate
            if _FAST_LOADER is _PyLoader:
                raise
            root, data, bad = _load(text, _PyLoader)  # the same error, said better (what was found)
    except _Refused as exc:
        raise RuleFileError([problem(exc.mark.line + 1, exc.mark.column + 1, exc.message)]) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        msg = f"YAML syntax: {exc.problem}"
        if exc.context and exc.context_mark and exc.context_mark is not mark:
            msg += f" ({exc.context} at line {exc.context_mark.line + 1}, column {exc.context_mark.column + 1})"
        raise RuleFileError([problem(line, col, msg)]) from None
    except yaml.reader.ReaderError as exc:  # a character YAML does not allow: at its line and column
        line = text.count("\n", 0, exc.position) + 1
        col = exc.position - (text.rfind("\n", 0, exc.position) + 1) + 1
        what = f"#x{exc.character:04x}" if isinstance(exc.character, int) else repr(exc.character)
        raise RuleFileError([problem(line, col, f"YAML: unacceptable character {what}: {exc.reason}")]) from None
    except yaml.YAMLError as exc:
        raise RuleFileError([problem(1, 1, f"YAML: {exc}")]) from None
    if bad:
        raise RuleFileError([problem(m.line + 1, m.column + 1, msg) for m, msg in bad])
    return root, data


def parse_rule_base(text: str, file: str, registry: PredicateRegistry) -> RuleBase:
    """Validate the text of a rule file (``file`` is its name in the messages); raises
    :class:`RuleFileError` listing every problem. Warnings (conditions that can never hold) are
    in the result's ``warnings``."""
    size = len(text) if len(text) * 4 <= MAX_RULE_FILE_BYTES else len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_RULE_FILE_BYTES:
        raise RuleFileError([Problem(SourcePos(file, 1, 1), _too_large(size))])
    root, data = _read_yaml(text, file)
    pos = _Positions(file, text, root)
    if not isinstance(data, dict):
        raise RuleFileError([pos.problem((), "a rule base is a mapping of keys (kbs_rules, name, checks, rules, ...)")])
    v = _Validator(data, pos, registry)
    rb = v.run()
    if v.problems:
        raise RuleFileError(v.problems)
    return rb


class _Validator:
    #: Candidate names all the "did you mean" look-ups of one file may compare with: each costs
    #: a string comparison per candidate, and a file with thousands of checks and as many typos
    #: would otherwise take minutes. Beyond it, problems are reported without a suggestion.
    HINT_BUDGET = 200_000

    def __init__(self, data: dict, pos: _Positions, registry: PredicateRegistry) -> None:
        self.data, self.pos, self.registry = data, pos, registry
        self.problems: list[Problem] = []
        self.warnings: list[Problem] = []
        self._hint_budget = self.HINT_BUDGET
        self._valid_key = _KnownValid.key(data, registry)
        self._schema_known = _KnownValid.known(self._valid_key)  # it passed the schema before: not run again

    def add(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.problems.append(self.pos.problem(path, message, key=key))

    def warn(self, path: tuple, message: str, *, key: bool = False) -> None:
        self.warnings.append(self.pos.problem(path, message, key=key, warning=True))

    def hint(self, name: Any, candidates: Any) -> str | None:
        """The closest of ``candidates`` to ``name`` (did you mean), within the file's budget."""
        candidates = [str(c) for c in candidates]
        if len(candidates) > self._hint_budget:
            return None
        self._hint_budget -= len(candidates)
        return did_you_mean(str(name), candidates)

    # -- schema ------------------------------------------------------------------------------

    def schema_problems(self) -> None:
        for path, mark in self.pos.duplicates:
            self.problems.append(Problem(SourcePos(self.pos.file, mark.line + 1, mark.column + 1),
                                         f"duplicate key '{_clip(str(path[-1]), 30)}' in {_where(path[:-1])}",
                                         self.pos.line(mark.line + 1)))
        if not self._schema_known:
            for err in _schema_validator(tuple(self.registry.actions)).iter_errors(self.data):
                self._schema_error(err)
        self._post_shape(self.data.get("post"))

    def _post_shape(self, raw: Any) -> None:
        """``post``: a sequence of one-key mappings naming known steps (or one mapping of them)."""
        known = list(self.registry.post_steps)

        def unknown(path: tuple, key: Any, where: str) -> None:
            hint = self.hint(key, known)
            self.add(path, f"unknown key '{_clip(str(key), 30)}' in {where}"
                     + (f" (did you mean '{hint}'?)" if hint else f"; allowed: {_listing(known)}"), key=True)

        if raw is None or "post" not in self.data:
            return
        if isinstance(raw, dict):
            for k in raw:
                if k not in self.registry.post_steps:
                    unknown(("post", k), k, "post")
        elif isinstance(raw, list):
            for i, item in enumerate(raw):
                if not isinstance(item, dict) or len(item) != 1:
                    self.add(("post", i), f"post[{i}] must be one step: a mapping of one step name to its settings "
                             f"(e.g. '- ground_model: {{label: ground}}'); got {_brief(item)}")
                    continue
                k = next(iter(item))
                if k not in self.registry.post_steps:
                    unknown(("post", i, k), k, f"post[{i}]")
        else:
            self.add(("post",), f"post must be a sequence of steps; got {_brief(raw)}")

    def _schema_error(self, err, prefix: tuple = ()) -> None:
        path = prefix + tuple(err.absolute_path)
        where = _where(path)
        sch, inst, kind = err.schema, err.instance, err.validator
        if kind == "additionalProperties" and isinstance(inst, dict):
            allowed = list(sch.get("properties", {}))
            for k in inst:
                if k not in allowed:
                    hint = self.hint(k, allowed)
                    self.add(path + (k,), f"unknown key '{_clip(str(k), 30)}' in {where}"
                             + (f" (did you mean '{hint}'?)" if hint else f"; allowed: {_listing(allowed)}"), key=True)
        elif kind == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            self.add(path, f"{where} is missing the required key '{missing}'")
        elif kind == "enum":
            hint = self.hint(inst, sch["enum"])
            self.add(path, f"{where} must be one of {', '.join(map(str, sch['enum']))}; got {_brief(inst)}"
                     + (f" (did you mean '{hint}'?)" if hint else ""))
        elif kind == "const":
            self.add(path, f"{where} must be {sch['const']!r}; got {_brief(inst)}")
        elif kind == "type":
            self.add(path, f"{where} must be {_article(sch['type'])}; got {_brief(inst)}" + _as_number_hint(inst))
        elif kind in ("oneOf", "anyOf"):
            meant = _meant_branch(err)
            if path and len(path) == 2 and path[0] == "checks":
                self.add(path, f"check '{path[1]}' needs a threshold: 'max' and/or 'min'")
            elif meant:  # the value has the type of one form only: what is wrong with it in that form, where
                for sub in meant:
                    self._schema_error(sub, prefix)
            else:
                what = str(sch.get("description", "see the schema")).rstrip(". ")  # a sentence: its stop before '; got'
                self.add(path, f"{where} is invalid: {what}; got {_brief(inst)}")
        elif kind == "pattern":
            self.add(path, f"{where}: {_brief(inst)} is not a valid name (letters, digits, '_', not starting with a "
                     "digit)")
        elif kind == "propertyNames":
            self.add(path, f"{where}: invalid name {_brief(err.instance)}")
        else:
            self.add(path, f"{where}: {_clip(err.message, 150)}")

    # -- semantics -----------------------------------------------------------------------------

    def run(self) -> RuleBase | None:
        self.schema_problems()
        d = self.data
        checks = self._checks(d.get("checks"))
        rules = self._rules(d.get("rules"), checks)
        labels = self._labels(d.get("labels"), checks)
        engine = {**ENGINE_DEFAULTS, **(d.get("engine") if isinstance(d.get("engine"), dict) else {})}
        limits = {**LIMIT_DEFAULTS, **(d.get("limits") if isinstance(d.get("limits"), dict) else {})}
        tile = limits.get("tile")
        if isinstance(tile, dict) and all(isinstance(tile.get(k), (int, float)) and not isinstance(tile.get(k), bool)
                                          for k in ("size", "wider_than")) and tile["wider_than"] < tile["size"]:
            self.add(("limits", "tile", "wider_than"), f"wider_than {tile['wider_than']!r} is below the tile size "
                     f"{tile['size']!r}: a cloud narrower than one tile would be cut into tiles")
        if isinstance(engine.get("initial_k"), int) and isinstance(engine.get("k_max"), int) \
                and engine["initial_k"] > engine["k_max"]:
            self.add(("engine", "initial_k"), f"initial_k = {engine['initial_k']} contradicts k_max = {engine['k_max']}")
        scene = d.get("scene") if isinstance(d.get("scene"), dict) else {}
        sensor = scene.get("sensor", [0.0, 0.0, 0.0])
        far = scene.get("far_outliers", {})
        far_factor = None if far is False else float(far.get("factor", FAR_OUTLIER_FACTOR)) if isinstance(far, dict) \
            else FAR_OUTLIER_FACTOR
        ground = self._ground(scene.get("ground") if isinstance(scene.get("ground"), dict) else {}, checks)
        post = self._post(d.get("post"), checks, labels)
        self._model_checks_placed(checks, rules, labels)
        classes = self._asprs_classes(d.get("asprs_classes"), [lb.name for lb in labels])
        tunables = self._tunables(checks)
        spacing = d.get("spacing")
        if isinstance(spacing, list) and len(spacing) == 2 and all(isinstance(x, (int, float)) for x in spacing) \
                and spacing[0] >= spacing[1]:
            self.add(("spacing",), f"spacing is [min, max]: {spacing[0]!r} is not below {spacing[1]!r}")
        if self.problems:
            return None
        if not self._schema_known:
            _KnownValid.add(self._valid_key)
        return RuleBase(
            name=d["name"], description=str(d.get("description", "")).strip(), units=d["units"], engine=engine,
            strategy=d["strategy"], limits=limits, sensor=tuple(float(x) for x in sensor), ground=ground,
            checks=checks, rules=tuple(rules), labels=tuple(labels), path=self.pos.file,
            text="\n".join(self.pos.lines), post=tuple(post), warnings=tuple(sorted(self.warnings, key=lambda p: (p.pos.line, p.pos.col))),
            asprs_classes=classes, spacing=None if spacing is None else (float(spacing[0]), float(spacing[1])),
            tunables=tuple(tunables), far_outliers=far_factor,
        )

    # -- tune marks ------------------------------------------------------------------------------

    def _tunables(self, checks: Mapping[str, Check]) -> list[Tunable]:
        """The ``tune:`` marks of the checks and post steps, validated (positioned problems)."""
        out: list[Tunable] = []
        raw_checks = self.data.get("checks")
        for name, spec in (raw_checks.items() if isinstance(raw_checks, dict) else ()):
            if isinstance(spec, dict) and "tune" in spec:
                fields = tuple(f for f in ("min", "max") if f in spec)
                t = self._tunable(("checks", name), spec, fields, ("min", "max"), checks.get(name))
                if t is not None:
                    out.append(t)
        post = self.data.get("post")
        items = (list(post.items()) if isinstance(post, dict) else
                 [(i, item) for i, item in enumerate(post) if isinstance(item, dict) and len(item) == 1]
                 if isinstance(post, list) else [])
        for where, item in items:
            step, spec = (where, item) if isinstance(where, str) else next(iter(item.items()))
            cls = self.registry.post_steps.get(step) if isinstance(step, str) else None
            if cls is not None and isinstance(spec, dict) and "tune" in spec:
                allowed = cls.tunable
                fields = tuple(f for f in allowed if f in spec)
                base = ("post", step) if isinstance(where, str) else ("post", where, step)
                t = self._tunable(base, spec, fields, allowed, None)
                if t is not None:
                    out.append(t)
        out.sort(key=lambda t: (t.mark.line, t.mark.col))
        total = 1
        for i, t in enumerate(out):
            total *= len(t.values)
            if total > TUNE_MAX_SETTINGS:
                sizes = " x ".join(str(len(u.values)) for u in out)
                self.add(t.path[:-1] + ("tune",),
                         f"the tune marks make {math.prod(len(u.values) for u in out):,} settings together ({sizes} "
                         f"values); kbs tune tries at most {TUNE_MAX_SETTINGS:,}: give fewer steps or values, or mark "
                         "fewer thresholds", key=True)
                return out[:i]
        return out

    def _tunable(self, base: tuple, spec: dict, present: tuple[str, ...], allowed: tuple[str, ...],
                 check: Check | None) -> Tunable | None:
        mark = spec["tune"]
        at = base + ("tune",)
        what = _where(base)
        if isinstance(mark, list):
            mark = {"values": mark}
        if not isinstance(mark, dict):
            return None  # the schema reported it
        field = mark.get("field")
        if field is None:
            if len(present) != 1:
                self.add(at, f"tune on {what}: say which threshold with 'field' ("
                         + (f"it has {', '.join(present)})" if present else f"thresholds: {', '.join(allowed)}; "
                            "none is set)"), key=True)
                return None
            field = present[0]
        elif not isinstance(field, str):
            return None  # the schema reported it
        elif field not in allowed:
            hint = self.hint(field, allowed)
            kind = "not a number" if field in spec else "not a field"
            self.add(at + ("field",), f"tune on {what}: '{_clip(field, 30)}' is {kind} kbs tune can fit "
                     f"(numeric thresholds here: {', '.join(allowed)})" + (f"; did you mean '{hint}'?" if hint else ""))
            return None
        elif field not in present:
            self.add(at + ("field",), f"tune on {what}: {field} is not set; write its current value "
                     f"({what}.{field}) before marking it")
            return None
        current = spec.get(field)
        if isinstance(current, bool) or not isinstance(current, (int, float)):
            return None  # the schema reported it
        integer = base[0] == "post" and _fragment_field(self.registry.post_steps[base[-1]], field).get("type") == "integer"
        has_range = "min" in mark or "max" in mark
        if "values" in mark and (has_range or "steps" in mark):
            self.add(at, f"tune on {what}: give either 'values' or 'min'/'max' (with 'steps'), not both", key=True)
            return None
        if "values" in mark:
            values = mark["values"]
            if not isinstance(values, list) or len(values) < 2 or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
                return None  # the schema reported it (numbers, at least two)
            vpath = at if isinstance(spec["tune"], list) else at + ("values",)
            lo, hi = min(values), max(values)
            if integer and any(float(v) != int(v) for v in values):
                self.add(vpath, f"tune on {what}.{field}: the values must be integers")
                return None
            grid = [float(v) for v in values]
        else:
            lo, hi = mark.get("min"), mark.get("max")
            if lo is None or hi is None:
                self.add(at, f"tune on {what}: give 'min' and 'max' (and 'steps', default {TUNE_STEPS}), or "
                         "'values', or a list of values", key=True)
                return None
            if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in (lo, hi)):
                return None  # the schema reported it
            vpath = at + ("min",)
            if lo > hi:
                self.add(at + ("min",), f"tune on {what}.{field}: min {lo:g} > max {hi:g}")
                return None
            steps = mark.get("steps", TUNE_STEPS)
            if isinstance(steps, bool) or not isinstance(steps, int) or not 2 <= steps <= TUNE_MAX_STEPS:
                return None  # the schema reported it (a grid of 10^9 steps would fill the memory before)
            grid = [float(v) for v in np.linspace(float(lo), float(hi), max(int(steps), 2))]
            if integer:
                grid = [float(round(v)) for v in grid]
        if not lo <= current <= hi:
            self.add(vpath, f"tune on {what}.{field}: the range [{lo:g}, {hi:g}] does not hold the current value "
                     f"{current:g}")
            return None
        bad = self._tune_value_problem(base, field, [*grid, float(current)], check, spec)
        if bad:
            self.add(vpath, f"tune on {what}.{field}: {bad}")
            return None
        values = tuple(sorted({round(v, 12) for v in [*grid, float(current)]}))
        return Tunable(path=tuple(base) + (field,), value=float(current), values=values,
                       integer=integer, pos=self.pos.pos(base + (field,)), mark=self.pos.pos(at, key=True))

    def _tune_value_problem(self, base: tuple, field: str, values: list[float], check: Check | None,
                            spec: dict) -> str | None:
        """Why some candidate cannot be the field's value (what the predicate measures, the
        schema's bounds, a check's other bound), or None."""
        if base[0] == "checks":
            if check is None:
                return None  # the check is broken; reported there
            lo, hi = check.predicate.value_range
            out = [v for v in values if (lo is not None and v < lo) or (hi is not None and v > hi)]
            if out:
                return (f"value {out[0]:g} is outside what '{check.predicate.name}' can measure "
                        f"[{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]")
            other = "max" if field == "min" else "min"
            o = spec.get(other)
            if isinstance(o, (int, float)) and not isinstance(o, bool):
                clash = [v for v in values if (v > o if field == "min" else v < o)]
                if clash:
                    return f"value {clash[0]:g} would make the check never pass ({other} is {o:g})"
            return None
        prop = _fragment_field(self.registry.post_steps[base[-1]], field)
        for v in values:
            if "minimum" in prop and v < prop["minimum"] or "maximum" in prop and v > prop["maximum"]:
                return f"value {v:g} is outside [{prop.get('minimum', '-inf')}, {prop.get('maximum', 'inf')}]"
            if "exclusiveMinimum" in prop and v <= prop["exclusiveMinimum"]:
                return f"value {v:g} must be above {prop['exclusiveMinimum']:g}"
        return None

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
                hint = self.hint(pname, self.registry.names())
                self.add(base + ("predicate",), f"unknown predicate '{_clip(pname, 30)}'"
                         + (f" (did you mean '{hint}'?)" if hint else f"; known: {_listing(self.registry.names())} (a "
                                                               "plugin's predicate needs its file: --plugin FILE)"))
                continue
            pred = self.registry.get(pname)
            params = dict(spec.get("params") or {}) if isinstance(spec.get("params", {}), dict) else {}
            for pkey, pval in params.items():
                if pkey not in pred.params:
                    hint = self.hint(pkey, pred.params)
                    known = _listing(pred.params) or "none"
                    self.add(base + ("params", pkey), f"predicate '{pname}' has no parameter '{_clip(str(pkey), 30)}'"
                             + (f" (did you mean '{hint}'?)" if hint else f"; its parameters: {known}"), key=True)
                    continue
                problem = pred.params[pkey].check(pval) or pred.params[pkey].check_with(params, pred.params)
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

    def _condition(self, raw: Any, path: tuple, checks: Mapping[str, Check], depth: int = 0) -> Condition | None:
        """The condition at ``path`` (a fact, a list, {all: ...} or {any: ...}), or None when it
        is invalid (reported here or by the schema). ``depth``: the groups around it."""
        if isinstance(raw, str):
            words = raw.split()
            negated = len(words) == 2 and words[0] == "not"
            name = words[-1] if words else ""
            if len(words) not in (1, 2) or (len(words) == 2 and not negated):
                return None  # the schema reported it
            known = self._declared
            if name not in checks and name in known:
                return Condition("fact", name, negated)  # the check itself is broken; reported there
            if name not in checks:
                hint = self.hint(name, known)
                self.add(path, f"unknown check '{_clip(name, 30)}'" + (f" (did you mean '{hint}'?)" if hint else
                                                                       f"; checks: {_listing(known)}"))
                return None
            return Condition("fact", name, negated)
        group = isinstance(raw, list) or (isinstance(raw, dict) and len(raw) == 1 and next(iter(raw)) in ("all", "any"))
        if group and depth >= MAX_CONDITION_DEPTH:
            self.add(path, f"condition nested more than {MAX_CONDITION_DEPTH} levels deep (lists, all, any): "
                     "nobody can follow it; split it over several checks or rules")
            return None
        if isinstance(raw, list):
            items = [self._condition(x, path + (i,), checks, depth + 1) for i, x in enumerate(raw)]
            return Condition("all", items=tuple(c for c in items if c)) if all(items) and items else None
        if group:
            kind = next(iter(raw))
            sub = raw[kind] if isinstance(raw[kind], list) else []
            items = [self._condition(x, path + (kind, i), checks, depth + 1) for i, x in enumerate(sub)]
            return Condition(kind, items=tuple(c for c in items if c)) if all(items) and items else None
        return None

    @functools.cached_property
    def _declared(self) -> dict[str, None]:
        """The names under 'checks' (valid or not), in order; empty when 'checks' is not a mapping."""
        raw = self.data.get("checks")
        return {k: None for k in raw if isinstance(k, str)} if isinstance(raw, dict) else {}

    def _never(self, cond: Condition, path: tuple, checks: Mapping[str, Check], what: str) -> None:
        """A warning at ``path`` when ``cond`` can never hold, whatever the clusters measure."""
        why = never_holds(cond, checks)
        if why:
            self.warn(path, f"{what}: its condition can never hold: {why}")

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
            part = self.registry.actions.get(action) if isinstance(action, str) else None
            if cond is None or part is None:
                continue
            self._never(cond, path + ("if",), checks, f"rule '{spec['name']}' can never act")
            rule = Rule(spec["name"], cond, action, str(spec.get("doc", "")), self.pos.pos(path), part)
            part.validate(rule, path, _StepContext(self, path, [], checks, ()))
            out.append(rule)
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
                if cond is not None and default_at is None:
                    self._never(cond, path + ("if",), checks, f"label '{spec['name']}' can never be given")
            else:
                default_at = i
            out.append(Label(spec["name"], cond, str(spec.get("doc", "")), self.pos.pos(path)))
        return out

    def _ground(self, raw: dict, checks: Mapping[str, Check]) -> GroundSpec:
        g = {**GROUND_DEFAULTS, **raw}
        needs = [c for c in checks.values() if c.predicate.needs_ground]
        auto = isinstance(g["normal"], str) and g["normal"] == "auto"
        normal = None if auto else _vector3(g["normal"])  # None too when invalid: the schema said so
        fallback = _vector3(g["fallback"])
        cand = g.get("candidate")
        for key, vec, what in (("normal", normal, "the ground normal"), ("fallback", fallback,
                                                                          "the fallback ground normal")):
            square = sum(x * x for x in vec) if vec is not None else 1.0
            if square == 0:
                self.add(("scene", "ground", key), f"{what} must not be the zero vector")
            elif not math.isfinite(square):  # its length overflows: the engine would divide by inf
                self.add(("scene", "ground", key), f"{what} is too long to be normalised (its squared length "
                         "overflows); a unit vector such as [0, 0, 1] says the same")
        if cand is not None and isinstance(cand, str):
            if cand not in checks and cand not in self._declared:
                hint = self.hint(cand, checks)
                self.add(("scene", "ground", "candidate"), f"unknown check '{cand}'"
                         + (f" (did you mean '{hint}'?)" if hint else ""))
            elif cand in checks and checks[cand].predicate.needs_ground:
                self.add(("scene", "ground", "candidate"), f"check '{cand}' needs the ground itself "
                         f"('{checks[cand].predicate.name}'): it cannot be what finds the ground")
        elif needs and auto and not isinstance(g["plane"], dict):
            first = needs[0]
            self.add(("checks", first.name, "predicate"),
                     f"check '{first.name}' uses the ground ('{first.predicate.name}'), found automatically, but "
                     "scene.ground.candidate does not name the check a ground candidate must pass "
                     "(e.g. 'candidate: planar'), nor does scene.ground.plane ask for a robust plane, "
                     "nor does scene.ground.normal fix it")
        plane = None
        if isinstance(g["plane"], dict):  # its keys, types and ranges: the schema
            tilt = g["plane"].get("max_tilt")
            plane = PlaneSpec(_number(g["plane"].get("inlier_distance"), 0.1),
                              _number(g["plane"].get("min_inlier_share"), 0.5),
                              None if tilt is None else _number(tilt, 90.0),
                              self.pos.pos(("scene", "ground", "plane"), key=True),
                              _number(g["plane"].get("planes"), 1, int),
                              str(g["plane"].get("share_of", "all")),
                              g["plane"].get("refit") is True,
                              None if g["plane"].get("max_thickness") is None else _number(g["plane"]["max_thickness"], 1.0))
            if not auto:
                self.warn(("scene", "ground", "plane"), "scene.ground.plane is not used: scene.ground.normal "
                          "fixes the ground direction (plane only applies with 'normal: auto')", key=True)
        support = None
        choose = g["choose"]
        if isinstance(choose, dict) and isinstance(choose.get("supporting"), dict):  # its shape: the schema
            band = choose["supporting"]
            support = SupportSpec(_number(band.get("min_height"), 0.0), _number(band.get("max_height"), 1.0),
                                  self.pos.pos(("scene", "ground", "choose"), key=True))
            if support.min_height >= support.max_height:
                self.add(("scene", "ground", "choose", "supporting", "max_height"),
                         f"max_height {support.max_height:g} must be greater than min_height {support.min_height:g}"
                         " (the band of heights above a candidate plane whose points it supports)")
            if not auto:
                self.warn(("scene", "ground", "choose"), "scene.ground.choose is not used: scene.ground.normal "
                          "fixes the ground direction (choose only applies with 'normal: auto')", key=True)
        above = g["sensor_above"] is True  # its type: the schema
        if above and not auto:
            self.warn(("scene", "ground", "sensor_above"), "scene.ground.sensor_above is not used: scene.ground.normal "
                      "fixes the ground direction (sensor_above only applies with 'normal: auto')", key=True)
        return GroundSpec(normal=normal, candidate=cand, min_points=_number(g["min_points"], 0, int),
                          fallback=fallback or (0.0, 0.0, 1.0), plane=plane, support=support, sensor_above=above)

    def _label_ref(self, path: tuple, name: Any, names: list[str]) -> None:
        if isinstance(name, str) and name not in names:
            hint = self.hint(name, names)
            self.add(path, f"unknown label '{_clip(name, 30)}'" + (f" (did you mean '{hint}'?)" if hint
                                                                    else f"; labels: {_listing(names)}"))

    def _post(self, raw: Any, checks: Mapping[str, Check], labels: list[Label]) -> list[Any]:
        """The post steps, in the order they run: ``post`` as a sequence of one-key mappings, or,
        as older files write it, one mapping of steps (run in :data:`kbs.knowledge.post.LEGACY_ORDER`,
        then any other step in file order)."""
        from kbs.knowledge.post import LEGACY_ORDER

        steps = self.registry.post_steps
        if isinstance(raw, dict):
            order = [k for k in LEGACY_ORDER if k in raw] + [k for k in raw if k not in LEGACY_ORDER]
            items = [(("post", k), k, raw[k]) for k in order]
        elif isinstance(raw, list):
            items = [(("post", i, k), k, v) for i, item in enumerate(raw) if isinstance(item, dict) and len(item) == 1
                     for k, v in item.items()]
        else:
            return []
        out: list[Any] = []
        names = [lb.name for lb in labels]
        for path, key, spec in items:
            cls = steps.get(key) if isinstance(key, str) else None
            if cls is None:
                continue  # the schema reported it
            before = len(self.problems)
            for err in () if self._schema_known else _fragment_validator(cls).iter_errors(spec):
                self._schema_error(err, prefix=path)
            invalid = len(self.problems) > before
            ctx = _StepContext(self, path, names, checks, tuple(out))
            try:  # read even when invalid (the file is refused anyway): the steps after it see it
                step = cls.parse(spec, ctx)
            except KbsError:
                raise
            except Exception as exc:  # a plugin step's bug: say which step, where
                raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
                if not invalid:
                    self.add(path, f"post step '{key}' failed to read its settings: {type(exc).__name__}: {exc}",
                             key=True)
                continue
            if step is not None:
                out.append(step)
        return out

    def _model_checks_placed(self, checks: Mapping[str, Check], rules: list[Rule], labels: list[Label]) -> None:
        """A check on the local ground surface cannot decide splits or labels: the surface is made
        of the labelled clusters."""
        def bad(cond: Condition | None) -> list[str]:
            return [] if cond is None else [f.name for f in cond.facts()
                                           if f.name in checks and checks[f.name].predicate.needs_ground_model]

        raw_rules = self.data.get("rules") if isinstance(self.data.get("rules"), list) else []
        first: dict[str, Rule] = {}  # by name (a name given twice is reported elsewhere): linear, not a search per rule
        for r in rules:
            first.setdefault(r.name, r)
        for i, spec in enumerate(raw_rules):
            name = spec.get("name") if isinstance(spec, dict) else None
            rule = first.get(name) if isinstance(name, str) else None
            for name in bad(rule.condition if rule else None)[:1]:
                self.add(("rules", i, "if"), f"rule '{rule.name}': check '{name}' measures against the local ground "
                         "surface, which exists only once clusters are labelled; use it in post.relabel")
        raw_labels = self.data.get("labels") if isinstance(self.data.get("labels"), list) else []
        for i, lab in enumerate(labels):
            for name in bad(lab.condition)[:1]:
                if i < len(raw_labels):
                    self.add(("labels", i, "if"), f"label '{lab.name}': check '{name}' measures against the local "
                             "ground surface, which is built from the labels; use it in post.relabel")


def _as_number_hint(value: Any) -> str:
    """For '1e5', which YAML 1.1 reads as text: how to write it as a number."""
    if isinstance(value, str) and len(value) < 40:
        try:
            number = float(value)
        except ValueError:
            return ""
        if not math.isfinite(number) or "e" not in value.lower():
            return ""
        mantissa, exponent = value.strip().lower().split("e", 1)
        mantissa += "" if "." in mantissa else ".0"
        exponent = exponent if exponent[:1] in ("+", "-") else "+" + exponent
        written = f"{mantissa}e{exponent}"
        if yaml.safe_load(written) == number:
            return f" (YAML reads {value} as text; write {written})"
    return ""


def _number(value: Any, default: float, kind: type = float) -> Any:
    """``value`` as a float (or int), ``default`` when it is not a real number (the schema reports
    it; the rule base is then not built)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return default
    return kind(value) if math.isfinite(value) else default


def _vector3(value: Any) -> tuple[float, float, float] | None:
    """Three real numbers as floats, or None (the schema reports what it is instead)."""
    if not isinstance(value, list) or len(value) != 3:
        return None
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in value):
        return None
    return (float(value[0]), float(value[1]), float(value[2]))


def _article(t: Any) -> str:
    if isinstance(t, list):
        return " or ".join(_article(x) for x in t)
    return {"object": "a mapping", "array": "a list", "string": "a string", "number": "a number",
            "integer": "an integer", "boolean": "true or false"}.get(t, str(t))


def _listing(names: Any, show: int = 12) -> str:
    """'a, b, c' or, for many, 'a, b, ..., l (3,000 in all)'."""
    names = [str(n) for n in names]
    if len(names) <= show:
        return ", ".join(names)
    return ", ".join(names[:show - 1]) + f", ..., {names[-1]} ({len(names):,} in all)"


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxlong, _REPR.maxother = 3, 6, 6, 60, 40, 60


def _brief(value: Any) -> str:
    """repr of a value from the file, short whatever its size."""
    return _REPR.repr(value)


# --- conditions that can never hold ---------------------------------------------------------------

#: Alternatives (terms of the condition's disjunctive normal form) a condition is analysed with;
#: a larger one gets no warning (the analysis would cost more than it tells).
MAX_ALTERNATIVES = 256

_Interval = tuple[float, bool, float, bool]  # (low, low included, high, high included)


def never_holds(cond: Condition, checks: Mapping[str, Check]) -> str | None:
    """Why ``cond`` can never hold, whatever the clusters measure, or None when it can (or when
    it is too large to analyse, or names checks that are not valid).

    A check passes when ``min <= value <= max``; its negation when the value is outside. Checks
    on the same measure (predicate and parameters, defaults included) constrain one value: the
    condition can never hold when, in each of its alternatives, some measure's constraints leave
    no value within what the predicate can measure (its declared ``value_range``), or a check and
    its negation meet.
    """
    terms = _alternatives(cond)
    if terms is None:
        return None
    reasons = []
    for term in terms:
        why = _conflict(term, checks)
        if why is None:
            return None
        reasons.append(why)
    if len(reasons) == 1:
        return reasons[0]
    return f"none of its {len(reasons)} alternatives can, e.g. {reasons[0]}"


def _alternatives(cond: Condition) -> list[tuple[tuple[str, bool], ...]] | None:
    """The condition as alternatives (any of), each a tuple of facts (all of), in order; None
    beyond MAX_ALTERNATIVES."""
    if cond.kind == "fact":
        return [((cond.name, cond.negated),)]
    subs = [_alternatives(c) for c in cond.items]
    if any(s is None for s in subs):
        return None
    if cond.kind == "any":
        out = [t for s in subs for t in s]
        return out if len(out) <= MAX_ALTERNATIVES else None
    out = [()]
    for s in subs:
        out = [a + b for a in out for b in s]
        if len(out) > MAX_ALTERNATIVES:
            return None
    return out


def _conflict(term: tuple[tuple[str, bool], ...], checks: Mapping[str, Check]) -> str | None:
    """Why the facts of one alternative cannot all hold, or None when they can."""
    seen: dict[str, bool] = {}
    for name, negated in term:
        if seen.get(name, negated) != negated:
            return f"'{name}' and 'not {name}' cannot both hold"
        seen[name] = negated
    by_measure: dict[tuple, list[tuple[str, bool]]] = {}
    for name, negated in dict.fromkeys(term):
        check = checks.get(name)
        if check is None:
            return None  # a check that is not valid: reported as a problem
        by_measure.setdefault(_measure(check), []).append((name, negated))
    for facts in by_measure.values():
        pred = checks[facts[0][0]].predicate
        allowed: list[_Interval] = [(-math.inf, False, math.inf, False)]
        for name, negated in facts:
            allowed = _intersect(allowed, _passes(checks[name], negated))
        if allowed:
            domain = _intersect(allowed, [_domain(pred)])
            if domain:
                continue
        what = " and ".join(f"'{'not ' if neg else ''}{name}' ({_text(checks[name], neg)})" for name, neg in facts)
        lo, hi = pred.value_range
        if allowed:  # possible values, but not ones the predicate measures
            rng = f"[{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]"
            return f"{what} asks for values {pred.name} never measures (it measures {rng})"
        return f"{what} exclude each other" if len(facts) > 1 else f"{what} is impossible"
    return None


def _measure(check: Check) -> tuple:
    """What a check measures: its predicate and every parameter's value (defaults included)."""
    params = {k: p.default for k, p in check.predicate.params.items()}
    params.update(check.params)
    return (check.predicate.name, tuple(sorted((k, repr(v)) for k, v in params.items())))


def _domain(pred: Predicate) -> _Interval:
    lo, hi = pred.value_range
    return (-math.inf if lo is None else float(lo), lo is not None,
            math.inf if hi is None else float(hi), hi is not None)


def _passes(check: Check, negated: bool) -> list[_Interval]:
    """The values for which the fact holds: [min, max] passes; below min or above max fails."""
    lo = -math.inf if check.min is None else check.min
    hi = math.inf if check.max is None else check.max
    if not negated:
        return [(lo, check.min is not None, hi, check.max is not None)]
    out = []
    if check.min is not None:
        out.append((-math.inf, False, lo, False))
    if check.max is not None:
        out.append((hi, False, math.inf, False))
    return out


def _intersect(a: list[_Interval], b: list[_Interval]) -> list[_Interval]:
    out = []
    for a_lo, a_lin, a_hi, a_hin in a:
        for b_lo, b_lin, b_hi, b_hin in b:
            lo, lin = (a_lo, a_lin) if a_lo > b_lo else (b_lo, b_lin) if b_lo > a_lo else (a_lo, a_lin and b_lin)
            hi, hin = (a_hi, a_hin) if a_hi < b_hi else (b_hi, b_hin) if b_hi < a_hi else (a_hi, a_hin and b_hin)
            if lo < hi or (lo == hi and lin and hin):
                out.append((lo, lin, hi, hin))
    return out


def _text(check: Check, negated: bool) -> str:
    """'thickness <= 0.05', 'not: thickness < 1 or > 2'."""
    p = check.predicate.name
    if not negated:
        if check.min is not None and check.max is not None:
            return f"{check.min:g} <= {p} <= {check.max:g}"
        return f"{p} >= {check.min:g}" if check.min is not None else f"{p} <= {check.max:g}"
    parts = [f"< {check.min:g}"] if check.min is not None else []
    parts += [f"> {check.max:g}"] if check.max is not None else []
    return f"{p} {' or '.join(parts)}"
