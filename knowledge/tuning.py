"""What ``kbs tune`` needs of the knowledge module: rule bases with other values for the thresholds
marked ``tune:``, which of those thresholds change the split tree, and labelling a split tree
again under other label-only thresholds without splitting anything again.

A threshold is *split-relevant* when the split tree can depend on it: a check named in a rule's
condition (rules decide splits and rejections) or the check the ground candidate must pass (the
ground plane every later check measures against). Every other marked threshold (a check used only
by labels, post.relabel or post.ground_contact's condition, and the post steps' own numbers) acts
only in the interpreter's last stage, where leaves are labelled, relabelled against the local
ground surface and merged. :class:`SplitTree` keeps a run's leaves as they were before that stage,
and :meth:`SplitTree.label` runs the stage again with another rule base: the result is the one a
full run of that rule base gives (the tests compare both).

>>> tree = SplitTree.grow(rule_base, X, sensor=(0, 0, 0))                    # doctest: +SKIP
>>> other = with_values(rule_base, {"post.ground_contact.tolerance": 0.08})  # doctest: +SKIP
>>> tree.label(other).label                                                   # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import math
import re
import time
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Mapping

import numpy as np

from kbs.knowledge.interpreter import Interpreter, Segmentation
from kbs.knowledge.predicates import PredicateRegistry
from kbs.knowledge.rulebase import RuleBase, Tunable, parse_rule_base
from kbs.knowledge.segmentation import far_outliers
from kbs.knowledge.state import Judged

# a plain YAML scalar (a number, as the validation made sure) from its first character: up to a
# space, a comment, or the end of a flow collection's item
_SCALAR = re.compile(r"[^\s,\]}#]+")


def split_relevant(rule_base: RuleBase, tunable: Tunable) -> bool:
    """Whether the split tree can depend on ``tunable`` (see the module's docstring)."""
    if tunable.path[0] != "checks":
        return False
    name = tunable.path[1]
    if rule_base.ground.candidate == name:
        return True
    return any(f.name == name for rule in rule_base.rules for f in rule.condition.facts())


def yaml_number(value: float, integer: bool = False) -> str:
    """``value`` as YAML reads it back as the same number: '0.05', '12', '1.0e-05' (YAML 1.1
    reads '1e-05' as text)."""
    if integer:
        return str(int(round(value)))
    text = format(float(value), ".12g")
    if "e" in text:
        mantissa, exponent = text.split("e")
        mantissa += "" if "." in mantissa else ".0"
        text = f"{mantissa}e{exponent if exponent[:1] in '+-' else '+' + exponent}"
    return text


def substitute(text: str, edits: Mapping[Tunable, str], comments: Mapping[Tunable, str] | None = None) -> str:
    """The rule file's ``text`` with the value of each tunable replaced in place by ``edits``'
    text (everything else, comments included, as it was), and ``comments[t]`` appended to the
    line of ``t`` as a YAML comment."""
    lines = text.split("\n")
    by_line: dict[int, list[Tunable]] = {}
    for t in edits:
        by_line.setdefault(t.pos.line, []).append(t)
    for line_no, ts in by_line.items():
        line = lines[line_no - 1]
        for t in sorted(ts, key=lambda t: -t.pos.col):  # right to left: columns stay valid
            start = t.pos.col - 1
            m = _SCALAR.match(line, start)
            if m is None:  # pragma: no cover - the validation saw a number here
                raise ValueError(f"no value at {t.pos}")
            new, rest = edits[t], line[m.end():]
            gap = len(rest) - len(rest.lstrip(" "))
            if gap and rest[gap:].startswith("#"):  # keep an aligned comment where it was
                shift = len(new) - (m.end() - start)
                rest = " " * max(1, gap - shift) + rest[gap:]
            line = line[:start] + new + rest
        notes = [comments[t] for t in ts if comments and comments.get(t)]
        if notes:
            cr = "\r" if line.endswith("\r") else ""
            line = line.rstrip() + "  # " + "; ".join(notes) + cr
        lines[line_no - 1] = line
    return "\n".join(lines)


def with_values(rule_base: RuleBase, values: Mapping[str, float], registry: PredicateRegistry | None = None,
                comments: Mapping[str, str] | None = None, text: str | None = None) -> tuple[str, RuleBase]:
    """(text, rule base) of ``rule_base`` with the marked thresholds named in ``values``
    (:attr:`Tunable.name`) set to those values; the text is validated again as any rule file.
    ``text``: the file's own text, byte for byte (line ends, last newline), when the caller has
    it; default: ``rule_base.text``. ``comments``: by name, appended to the value's line.

    Raises
    ------
    KeyError
        A name that is not a marked threshold.
    """
    marks = {t.name: t for t in rule_base.tunables}
    edits = {marks[name]: yaml_number(v, marks[name].integer) for name, v in values.items()}
    notes = {marks[name]: c for name, c in (comments or {}).items()}
    text = substitute(rule_base.text if text is None else text, edits, notes)
    registry = registry or registry_of(rule_base)
    return text, parse_rule_base(text, rule_base.path, registry)


def registry_of(rule_base: RuleBase) -> PredicateRegistry:
    """A registry holding the rule base's predicates (plugins included)."""
    reg = PredicateRegistry.default()
    for check in rule_base.checks.values():
        if check.predicate.name not in reg:
            reg.add(check.predicate)
    return reg


class _Recorder(Interpreter):
    """An interpreter that keeps what its last run had before labelling."""

    state: Judged | None = None

    def finish(self, judged: Judged, t0: float) -> Segmentation:
        self.state = judged  # frozen: labelling and the post steps give new records and ground facts
        return super().finish(judged, t0)


@dataclass
class SplitTree:
    """A run's leaves before labelling, to be labelled again under other label-only thresholds.

    Attributes
    ----------
    rule_base : RuleBase
        The rule base the tree was grown with.
    segmentation : Segmentation
        That run's own result.
    seconds : float
        Time the run took.
    """

    rule_base: RuleBase
    segmentation: Segmentation
    seconds: float
    _state: Judged | None = dataclasses.field(repr=False, default=None)
    _sensor: np.ndarray | None = dataclasses.field(repr=False, default=None)
    #: the far outliers the run set aside (:func:`~kbs.knowledge.segmentation.far_outliers`) and its
    #: note, given back to every labelling
    _aside: tuple[np.ndarray, str] | None = dataclasses.field(repr=False, default=None)

    @classmethod
    def grow(cls, rule_base: RuleBase, X: np.ndarray, *, sensor: Any = None, jobs: int = 1,
             progress: Callable[[str], None] | None = None, interpreter: _Recorder | None = None) -> SplitTree:
        """Segment ``X`` (n, 3) with ``rule_base`` and keep its leaves. ``interpreter``: a
        :class:`_Recorder` to reuse (its worker processes), from :func:`recorder`."""
        rec = interpreter if interpreter is not None else recorder(rule_base, sensor=sensor, jobs=jobs)
        rec.rb = rule_base
        rec.sensor = np.asarray(rule_base.sensor if sensor is None else sensor, dtype=np.float64)
        rec.progress = progress
        t0 = time.perf_counter()
        try:
            seg = rec.run(X)
        finally:
            rec.progress = None
            if interpreter is None:
                rec.close()
        assert rec.state is not None  # set by the run's finish
        far = far_outliers(np.asarray(X), rule_base.far_outliers)
        aside = None if far is None else (far[0], seg.explanation.notes[-1])
        return cls(rule_base, seg, time.perf_counter() - t0, rec.state, rec.sensor.copy(), aside)

    def label(self, rule_base: RuleBase) -> Segmentation:
        """The result of ``rule_base`` on the same points, by labelling this tree's leaves again.
        ``rule_base`` must differ from the tree's only in thresholds that are not split-relevant
        (:func:`split_relevant`); the caller sees to it."""
        if rule_base is self.rule_base:
            return self.segmentation
        assert self._state is not None
        it = Interpreter(rule_base, sensor=self._sensor, jobs=1)
        seg = it.finish(self._state, time.perf_counter())
        return seg if self._aside is None else seg.with_set_aside(*self._aside)


def recorder(rule_base: RuleBase, *, sensor: Any = None, jobs: int = 1) -> _Recorder:
    """An interpreter for :meth:`SplitTree.grow` to reuse over several rule bases and scans
    (close it when done)."""
    return _Recorder(rule_base, sensor=sensor, jobs=jobs)


def grid(tunables: tuple[Tunable, ...]) -> list[dict[str, float]]:
    """Every combination of the tunables' values, as {name: value}."""
    out: list[dict[str, float]] = [{}]
    for t in tunables:
        out = [{**c, t.name: v} for c in out for v in t.values]
    return out


def distance(setting: Mapping[str, float], tunables: tuple[Tunable, ...]) -> tuple[int, float]:
    """(thresholds moved, sum of their moves relative to each one's range): how far a setting is
    from the file's values, to break ties in favour of the nearest."""
    moved, total = 0, 0.0
    for t in tunables:
        v = setting.get(t.name, t.value)
        if not math.isclose(v, t.value, rel_tol=1e-12, abs_tol=1e-15):
            moved += 1
            span = (t.values[-1] - t.values[0]) or 1.0
            total += abs(v - t.value) / span
    return moved, total
