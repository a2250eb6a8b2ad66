"""Explanations are data: a tree of records, one per cluster, saying what was measured, which rule
acted, with what result. Only the renderers here turn them into sentences.

Like hdbscan's ``CondensedTree``: a first-class object with exporters (:meth:`Explanation.to_dict`,
:meth:`Explanation.to_networkx`) and renderers (:meth:`Explanation.summary`,
:meth:`Explanation.render`, :meth:`Explanation.why`).

The explanation carries the rule base's vocabulary it was made with (:class:`Catalogue`: each
check's predicate, bounds and ``doc``, each rule's, label's and relabel rule's condition and
``doc``), so that a result file explains itself without its rule file, which may have changed
since. The renderers evaluate those conditions again over the recorded check outcomes to say which
terms decided (``not planar (thickness = 0.12 m > 0.05 m)``); they know no predicate by name.

Its dictionary form (:meth:`Explanation.to_dict`, the ``explanation`` of a result JSON) is the
format ``kbs-explanation`` (:data:`EXPLANATION_FORMAT`, version :data:`EXPLANATION_VERSION`;
:mod:`kbs.formats`). Version 1.0 (no ``version`` key) has no catalogue: its explanations name
rules and checks without their docs.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

from kbs.errors import CloudFileError
from kbs.formats import FormatVersionError, Version, document_version
from kbs.knowledge.explain_schema import ExplanationError, check_explanation
from kbs.knowledge.groundfacts import GroundFacts

if TYPE_CHECKING:
    from kbs.io.result import ResultDoc
    from kbs.knowledge.rulebase import Condition, RuleBase

#: The ``format`` of an explanation's dictionary form, and the version this kbs writes.
EXPLANATION_FORMAT = "kbs-explanation"
EXPLANATION_VERSION = Version(1, 2)


def _known(cls: type, d: Mapping[str, Any]) -> dict[str, Any]:
    """The keys of ``d`` that are fields of the dataclass ``cls``: a newer minor version of the
    format may add keys, which this reader ignores."""
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in d.items() if k in names}


def _number(value: float, unit: str) -> str:
    """'0.1179 m', '6,874 pts', '2': integral values as integers with thousands separators (counts
    of points or components), others with 4 significant digits."""
    u = f" {unit}" if unit else ""
    if float(value).is_integer() and abs(value) < 1e15:
        return f"{int(value):,}{u}"
    return f"{value:.4g}{u}"


@dataclass(frozen=True)
class CheckRecord:
    """One check measured on one cluster."""

    check: str
    predicate: str
    #: None: undefined (e.g. the ground angle of a cluster with no plane; ``note`` says why), or, read
    #: back from a result file, not finite (a result JSON writes NaN and infinities as null)
    value: float | None
    unit: str
    min: float | None
    max: float | None
    passed: bool
    source: str  #: 'outdoor.yaml:31'
    note: str = ""  #: e.g. where a value was measured when not on the cluster itself

    def bound(self) -> tuple[str, float]:
        """The comparison that decided: ('<=', max) when within the upper bound, ('>', max) above
        it, ('>=', min) or ('<', min) for a lower bound (the value must be known)."""
        v = self.value
        assert v is not None, "bound() of an undefined value"
        if self.max is not None and (v > self.max or self.min is None or v >= self.min):
            return ("<=" if v <= self.max else ">"), self.max
        assert self.min is not None, "a check has a bound"
        return (">=" if v >= self.min else "<"), self.min

    def _unknown(self) -> str:
        """For a value read back as null (a result JSON writes NaN and infinities so): what is known."""
        u = f" {self.unit}" if self.unit else ""
        bounds = " and ".join(f"{op} {b:g}{u}" for op, b in ((">=", self.min), ("<=", self.max)) if b is not None)
        return f"not finite (null in the result file), {'passes' if self.passed else 'fails'} {bounds}"

    def comparison(self) -> str:
        """'0.021 m <= 0.05 m' ('undefined' when there is no value)."""
        if self.value is None:
            return "undefined" if self.note else self._unknown()
        op, b = self.bound()
        return f"{_number(self.value, self.unit)} {op} {_number(b, self.unit)}"

    def sentence(self) -> str:
        """'connexity = 3 > 1', 'thickness = 0.12 m > 0.05 m', 'ground_angle undefined
        (degenerate: its points lie on a line, no plane)'."""
        if self.value is None:
            return f"{self.predicate} undefined ({self.note})" if self.note else f"{self.predicate} = {self._unknown()}"
        return f"{self.predicate} = {self.comparison()}"

    def verdict(self) -> str:
        """'yes' when the value is within the check's bounds, 'no' otherwise (which is what a
        condition ``not NAME`` asks for: 'no' is not a failure of the cluster)."""
        return "yes" if self.passed else "no"


# -- the rule base's vocabulary ------------------------------------------------------------------


@dataclass(frozen=True)
class CheckInfo:
    """A check of the rule base: ``predicate`` compared with ``min``/``max`` (in ``unit``)."""

    name: str
    predicate: str
    unit: str
    min: float | None
    max: float | None
    doc: str
    source: str

    def bounds_text(self) -> str:
        """'thickness <= 0.05 m', '1 cm <= height >= 50 cm'."""
        parts = [f"{_number(self.min, self.unit)} <="] if self.min is not None else []
        parts.append(self.predicate)
        if self.max is not None:
            parts.append(f"<= {_number(self.max, self.unit)}")
        return " ".join(parts)


@dataclass(frozen=True)
class RuleInfo:
    """A rule, label or relabel rule of the rule base.

    ``condition`` is plain data in the rule file's own terms: a check name, ``"not NAME"``,
    ``{"all": [...]}`` or ``{"any": [...]}``; None: always holds (a default label). ``action``:
    a rule's action (``reject``, ``split``, ``split_components``), a relabel rule's
    ``"FROM -> TO"``, '' for a label.
    """

    name: str
    condition: Any
    doc: str
    source: str
    action: str = ""

    def condition_text(self) -> str:
        return "always" if self.condition is None else _condition_text(self.condition)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "condition": self.condition, "doc": self.doc, "source": self.source,
                "action": self.action}


def _condition_data(cond: Condition | None) -> Any:
    if cond is None:
        return None
    if cond.kind == "fact":
        return f"not {cond.name}" if cond.negated else cond.name
    return {cond.kind: [_condition_data(c) for c in cond.items]}


def _condition_text(cond: Any, top: bool = True) -> str:
    if isinstance(cond, str):
        return cond
    ((kind, items),) = cond.items()
    text = (" and " if kind == "all" else " or ").join(_condition_text(c, False) for c in items)
    return text if top or len(items) < 2 else f"({text})"


#: One term of a condition as evaluated: (check name, negated, holds: None when not measured).
Term = tuple[str, bool, "bool | None"]


def evaluate(cond: Any, outcome: Mapping[str, bool]) -> tuple[bool | None, list[Term]]:
    """Evaluate a condition (:class:`RuleInfo` form) over check outcomes, as the interpreter does
    (in order, lazily): whether it holds (None: a check it needed was not measured) and the terms
    that decided it (all of an ``all`` that holds, the first that fails of one that fails; the
    first that holds of an ``any`` that holds, all of one that fails)."""
    if cond is None:
        return True, []
    if isinstance(cond, str):
        negated = cond.startswith("not ")
        name = cond[4:].strip() if negated else cond
        passed = outcome.get(name)
        holds = None if passed is None else passed != negated
        return holds, [(name, negated, holds)]
    ((kind, items),) = cond.items()
    terms: list[Term] = []
    for item in items:
        holds, t = evaluate(item, outcome)
        if holds is None:
            return None, terms + t
        if holds != (kind == "all"):  # decided: a failing term of 'all', a holding one of 'any'
            return holds, t
        terms += t
    return kind == "all", terms


@dataclass(frozen=True)
class Catalogue:
    """What the rule base of a run said: its checks, rules, labels and relabel rules, in order."""

    checks: Mapping[str, CheckInfo]
    rules: tuple[RuleInfo, ...]
    labels: tuple[RuleInfo, ...]
    relabel: tuple[RuleInfo, ...] = ()

    @classmethod
    def of(cls, rb: RuleBase) -> Catalogue:
        """The catalogue of a validated rule base."""
        checks = {name: CheckInfo(name, c.predicate.name, c.predicate.unit_label(rb.length_unit), c.min, c.max,
                                  c.doc.strip(), c.pos.short) for name, c in rb.checks.items()}
        rules = tuple(RuleInfo(r.name, _condition_data(r.condition), r.doc.strip(), r.pos.short, r.action)
                      for r in rb.rules)
        labels = tuple(RuleInfo(lb.name, _condition_data(lb.condition), lb.doc.strip(), lb.pos.short)
                       for lb in rb.labels)
        relabel = tuple(RuleInfo(r.name, _condition_data(r.condition), " ".join(r.doc.split()), r.pos.short,
                                 f"{r.source} -> {r.target}") for r in rb.relabel)
        return cls(checks, rules, labels, relabel)

    def rule(self, name: str | None) -> RuleInfo | None:
        return next((r for r in self.rules if r.name == name), None)

    def to_dict(self) -> dict[str, Any]:
        return {"checks": [asdict(c) for c in self.checks.values()], "rules": [r.to_dict() for r in self.rules],
                "labels": [r.to_dict() for r in self.labels], "relabel": [r.to_dict() for r in self.relabel]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Catalogue:
        return cls(checks={c["name"]: CheckInfo(**_known(CheckInfo, c)) for c in d.get("checks", [])},
                   rules=tuple(RuleInfo(**_known(RuleInfo, r)) for r in d.get("rules", [])),
                   labels=tuple(RuleInfo(**_known(RuleInfo, r)) for r in d.get("labels", [])),
                   relabel=tuple(RuleInfo(**_known(RuleInfo, r)) for r in d.get("relabel", [])))


@dataclass(frozen=True)
class APDCurve:
    """The APD values of the UFP-ONC sweep that chose K for a split."""

    ks: tuple[int, ...]
    apd: tuple[float, ...]
    chosen: int

    def text(self) -> str:
        return ", ".join(f"K={k}{'*' if k == self.chosen else ''}: {'null' if a is None else f'{a:.4g}'}"
                         for k, a in zip(self.ks, self.apd))


@dataclass(frozen=True)
class ClusterRecord:
    """Everything decided about one cluster (frozen: the run builds a new record with
    ``dataclasses.replace`` or :meth:`noted` where it decides more; lists given for the sequence
    fields are kept as tuples).

    ``action`` is one of 'accept', 'split' (UFP-ONC), 'split_components', 'reject' (noise),
    'limit' (it should have been split but a limit stopped it; it is kept as it is), 'partition'
    (the root: the scene's initial partition).
    """

    id: str
    parent: str | None
    depth: int
    n_points: int
    descriptors: Mapping[str, Any] = field(default_factory=dict)
    checks: tuple[CheckRecord, ...] = ()
    action: str = "accept"
    rule: str | None = None
    rule_source: str | None = None
    children: tuple[str, ...] = ()
    label: str | None = None
    apd: APDCurve | None = None
    notes: tuple[str, ...] = ()
    output_index: int | None = None  #: value of the per-point 'cluster' property, None if none
    decisive: tuple[str, ...] = ()  #: checks of the condition that decided
    #: set when a post.relabel rule changed the label: {rule, source, from, to, checks}
    relabel: Mapping[str, Any] | None = None
    contact: int = 0  #: points that left it for the ground (post.ground_contact)
    released: int = 0  #: points that left this ground cluster, standing above the surface (post.ground_release)
    #: set when action is 'limit': what stopped the split, {kind, setting, value}, e.g.
    #: {'kind': 'max_depth', 'setting': 'limits.max_depth', 'value': 12} (kinds: interpreter.STOP_KINDS)
    limit: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        for name in _SEQUENCES:
            value = getattr(self, name)
            if not isinstance(value, tuple):
                object.__setattr__(self, name, tuple(value))

    def noted(self, *notes: str) -> ClusterRecord:
        """This record with ``notes`` added at the end of its notes."""
        return self.evolve(notes=self.notes + notes)

    def evolve(self, **changes: Any) -> ClusterRecord:
        """``dataclasses.replace(self, **changes)``, the same record, without running ``__init__``
        (about 5 us a call in ``replace``, a few thousand calls a vehicle frame): the fields copied,
        the changed ones set, sequences given as lists kept as tuples as ``__post_init__`` does."""
        unknown = changes.keys() - _RECORD_FIELDS
        if unknown:
            raise TypeError(f"ClusterRecord has no field {sorted(unknown)[0]!r}")
        new = object.__new__(ClusterRecord)
        state = new.__dict__
        state.update(self.__dict__)
        for name, value in changes.items():
            state[name] = tuple(value) if name in _SEQUENCES and not isinstance(value, tuple) else value
        return new

    def decisive_checks(self) -> list[CheckRecord]:
        names = set(self.decisive)
        return [c for c in self.checks if c.check in names]

    def failing_checks(self) -> list[CheckRecord]:
        return [c for c in self.checks if not c.passed]

    @property
    def first_label(self) -> str | None:
        """The label its labels' conditions gave it, before any relabel rule (a rule that undid
        another gave back the label that rule took: ``relabel['undid']``)."""
        r = self.relabel
        while r and r.get("undid"):
            r = r["undid"]
        return r["from"] if r else self.label

    def to_dict(self) -> dict[str, Any]:
        """The record as plain data (what ``dataclasses.asdict`` gives, with lists for its
        sequences, without its deep copies): one of the ``clusters`` of an explanation's
        dictionary form."""
        d = dict(vars(self))
        d["checks"] = [dict(vars(c)) for c in self.checks]
        d["apd"] = None if self.apd is None else {"ks": list(self.apd.ks), "apd": list(self.apd.apd),
                                                  "chosen": self.apd.chosen}
        d["children"], d["notes"], d["decisive"] = list(self.children), list(self.notes), list(self.decisive)
        d["descriptors"] = dict(self.descriptors)
        d["relabel"] = None if self.relabel is None else dict(self.relabel)
        d["limit"] = None if self.limit is None else dict(self.limit)
        return d


#: The fields of a :class:`ClusterRecord` that are sequences (tuples).
_SEQUENCES = ("checks", "children", "notes", "decisive")
_RECORD_FIELDS = frozenset(f.name for f in fields(ClusterRecord))


#: How many records a tree may have to be printed whole by default (``kbs explain`` without
#: ``--depth``); above it, the tree is cut at the deepest level that keeps it within this many lines.
TREE_LINES = 40


@dataclass
class Explanation:
    """The tree of cluster records of one run."""

    rule_base: str
    rule_file: str
    strategy: str
    label_names: list[str]
    records: dict[str, ClusterRecord]
    root: str
    #: how the ground plane was found, and what the steps on the local ground surface did
    ground: GroundFacts = field(default_factory=GroundFacts)
    notes: list[str] = field(default_factory=list)
    #: the rule base's checks, rules and labels (None: an explanation read from a version 1.0 file)
    catalogue: Catalogue | None = None
    #: strategy global: every K-partition of the scene judged, in order (version 1.2): ``k``,
    #: ``apd``, ``seeded_in`` (the cluster of the K-1 partition the new prototype was seeded in),
    #: ``next`` (that of the next K), ``kept``, and ``clusters``: each with ``id``, ``points``,
    #: ``center``, ``eigenvalues``, ``eigenvectors`` (columns), ``action``, ``rule``,
    #: ``rule_source``, ``decisive`` (the checks of the rule's condition: check, predicate, value,
    #: unit, min, max, passed, source) and ``limit``
    sweep: list[dict[str, Any]] = field(default_factory=list)

    # -- access ----------------------------------------------------------------------------

    def __getitem__(self, cluster_id: str) -> ClusterRecord:
        return self.records[cluster_id]

    def walk(self, start: str | None = None) -> Iterator[ClusterRecord]:
        """Records depth-first, children in order."""
        stack = [start or self.root]
        while stack:
            rec = self.records[stack.pop()]
            yield rec
            stack.extend(reversed(rec.children))

    def leaves(self) -> list[ClusterRecord]:
        return [r for r in self.walk() if not r.children]

    # -- export ----------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"format": EXPLANATION_FORMAT, "version": str(EXPLANATION_VERSION)}
        d.update({
            "rule_base": self.rule_base, "rule_file": self.rule_file, "strategy": self.strategy,
            "label_names": list(self.label_names), "root": self.root, "ground": self.ground.to_dict(),
            "notes": list(self.notes),
        })
        if self.catalogue is not None:
            d["catalogue"] = self.catalogue.to_dict()
        d["clusters"] = [r.to_dict() for r in self.walk()]
        if self.sweep:
            d["sweep"] = self.sweep
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Explanation:
        """Read :meth:`to_dict`'s form back.

        Raises
        ------
        kbs.formats.FormatVersionError
            Another format, or a newer major version (a ValueError).
        KeyError, TypeError
            Not an explanation.
        """
        document_version(d, format=EXPLANATION_FORMAT, reads=EXPLANATION_VERSION)
        records = {}
        for r in d["clusters"]:
            r = _known(ClusterRecord, r)
            r["checks"] = [CheckRecord(**_known(CheckRecord, c)) for c in r.get("checks", [])]
            if r.get("apd"):
                a = r["apd"]
                r["apd"] = APDCurve(tuple(a["ks"]), tuple(a["apd"]), a["chosen"])
            records[r["id"]] = ClusterRecord(**r)
        cat = d.get("catalogue")
        return cls(rule_base=d["rule_base"], rule_file=d["rule_file"], strategy=d["strategy"],
                   label_names=list(d["label_names"]), records=records, root=d["root"], ground=GroundFacts.from_dict(d.get("ground")),
                   notes=list(d.get("notes", [])), catalogue=None if cat is None else Catalogue.from_dict(cat),
                   sweep=list(d.get("sweep", [])))

    @classmethod
    def from_result(cls, doc: ResultDoc) -> Explanation:
        """The explanation of a result file read back (:func:`kbs.io.result.read_result`).

        Raises
        ------
        kbs.errors.CloudFileError
            It has none, or not one this kbs reads: a newer major version, a field of the wrong
            type or missing, a cluster tree with a cycle or a dangling id
            (:func:`kbs.knowledge.explain_schema.check_explanation`), at its position.
        """
        if doc.explanation is None:
            raise CloudFileError(str(doc.path), "not a kbs result file (it has no explanation)")
        d = dict(doc.explanation)
        try:
            document_version(d, format=EXPLANATION_FORMAT, reads=EXPLANATION_VERSION)
            check_explanation(d)  # every field the readers use, and the tree: nothing below can fail on the file
        except FormatVersionError as exc:
            raise CloudFileError(doc.position("explanation", "version"), f"its explanation: {exc}") from exc
        except ExplanationError as exc:
            raise CloudFileError(doc.position("explanation", *exc.path), f"not a kbs result file ({exc})") from exc
        return cls.from_dict(d)

    def to_networkx(self):
        """A ``networkx.DiGraph`` parent -> child with each record's fields as node attributes."""
        import networkx as nx

        g = nx.DiGraph()
        for r in self.walk():
            g.add_node(r.id, **{k: v for k, v in asdict(r).items() if k != "children"})
            if r.parent is not None:
                g.add_edge(r.parent, r.id)
        return g

    # -- the words of one decision ----------------------------------------------------------------

    @staticmethod
    def _terms_text(rec: ClusterRecord, terms: list[Term]) -> str:
        """'not planar (thickness = 0.12 m > 0.05 m), level (ground_angle = 2 deg <= 22.5 deg)'."""
        by_name = {c.check: c for c in rec.checks}
        out = []
        for name, negated, holds in terms:
            term = f"not {name}" if negated else name
            c = by_name.get(name)
            if holds is None or c is None:
                out.append(f"{term} (not measured)")
            else:
                out.append(f"{term} ({c.sentence()})" if holds else f"{term} does not hold ({c.sentence()})")
        return ", ".join(out)

    def _rule_why(self, rec: ClusterRecord) -> str:
        """Why the rule of ``rec`` held: its terms, or (without a catalogue) its decisive checks."""
        info = self.catalogue.rule(rec.rule) if self.catalogue else None
        if info is None:
            return "; ".join(c.sentence() for c in rec.decisive_checks())
        _, terms = evaluate(info.condition, {c.check: c.passed for c in rec.checks})
        return self._terms_text(rec, terms)

    def _rule_name(self, rec: ClusterRecord) -> str:
        return f"{rec.rule} [{rec.rule_source}]" if rec.rule_source else str(rec.rule)

    def _label_why(self, rec: ClusterRecord) -> str:
        """How a leaf got its label: 'as ground: planar (...), level (...)', 'as obstacle, not
        ground: planar does not hold (...)', ', no label matched: not ground: ...'."""
        given = rec.first_label
        if self.catalogue is None or not self.catalogue.labels:
            why = "; ".join(c.sentence() for c in (rec.decisive_checks() if rec.action == "accept" else []))
            head = f"as {given}" if given else f", {NO_LABEL}"
            return f"{head}: {why}" if why else head
        outcome = {c.check: c.passed for c in rec.checks}
        rejected: list[str] = []
        for lab in self.catalogue.labels:
            holds, terms = evaluate(lab.condition, outcome)
            if lab.name == given:
                why = self._terms_text(rec, terms)
                head = f"as {given}" + "".join(f", not {r}" for r in rejected)
                return f"{head}: {why}" if why else head
            rejected.append(f"{lab.name}: {self._terms_text(rec, terms)}" if terms else lab.name)
        if given is None:
            return f", {NO_LABEL}: " + "; ".join(f"not {r}" for r in rejected)
        return f"as {given}"

    def _relabel_text(self, rec: ClusterRecord) -> str:
        """', relabelled ground by low_level [outdoor.yaml:102]: level (...), low (...)'."""
        if not rec.relabel:
            return ""
        r = rec.relabel
        info = next((x for x in self.catalogue.relabel if x.name == r["rule"]), None) if self.catalogue else None
        if r.get("measured") is not None:  # judged again by a rule that undoes another: its own measurements
            rec = replace(rec, checks=tuple(CheckRecord(**_known(CheckRecord, c)) for c in r["measured"])
                          + tuple(c for c in rec.checks if c.check not in {m["check"] for m in r["measured"]}))
        if r.get("joined"):  # post.merge_coplanar's absorb: no checks, a plane it lies in
            j = r["joined"]
            unit = f" {j['unit']}" if j.get("unit") else ""
            why = (f"in the plane of {j['cluster']} (normals {j['angle']:.3g} deg apart"
                   + (f" <= {j['max_angle']:g} deg" if "max_angle" in j else "")
                   + f", each centre {j['offset']:.3g}{unit} off the other's plane"
                   + (f" <= {j['max_offset']:g}{unit}" if "max_offset" in j else "") + ")")
        elif info is None:
            names = set(r["checks"])
            why = "; ".join(c.sentence() for c in rec.checks if c.check in names)
        else:
            why = self._terms_text(rec, evaluate(info.condition, {c.check: c.passed for c in rec.checks})[1])
        text = f", relabelled {r['to']} by {r['rule']} [{r['source']}]"
        if not r.get("undid") and r.get("pass", 1) > 1:  # a rule with passes, judged again
            text += (f" in pass {r['pass']} (against the surface rebuilt without the clusters relabelled in the "
                     "passes before)")
        if r.get("undid"):
            u = r["undid"]
            text = (f", relabelled {u['to']} by {u['rule']} [{u['source']}], given back {r['to']} by {r['rule']} "
                    f"[{r['source']}] in pass {r['pass']} (against the surface rebuilt without the clusters "
                    f"{u['rule']} relabelled)")
        elif r.get("judged_again"):
            last = r["judged_again"][-1]
            text += (f"; judged again by {last['rule']} [{last['source']}] in pass {last['pass']}, which did "
                     "not give it back")
        return f"{text}: {why}"

    # -- renderers -------------------------------------------------------------------------

    def line(self, rec: ClusterRecord) -> str:
        """One line: 'c0.2 (1,204 pts) split in 3 components by CAh [outdoor.yaml:31]: not planar
        (thickness = 0.12 m > 0.05 m), not connected (connexity = 3 > 1)'."""
        head = f"{rec.id} ({rec.n_points:,} pts)"
        if rec.action == "partition":
            k = len(rec.children)
            if self.sweep:
                first = self.sweep[0]["k"]
                how = (f" by the global strategy: K = {first} (APD's first local maximum) to K = {self.sweep[-1]['k']}, "
                       f"{len(self.sweep)} partition{'s' if len(self.sweep) != 1 else ''} judged, K = {k} kept")
                return f"{head} partitioned in {k}{how}" + (f" (APD: {rec.apd.text()})" if rec.apd else "")
            chosen = f" (APD first local maximum: {rec.apd.text()})" if rec.apd else ""
            return f"{head} partitioned in {k}{chosen}"
        if rec.action in ("split", "split_components"):
            how = "" if rec.action == "split" else " components"
            return f"{head} split in {len(rec.children)}{how} by {self._rule_name(rec)}: {self._rule_why(rec)}"
        if rec.action == "reject":
            return f"{head} rejected as noise by {self._rule_name(rec)}: {self._rule_why(rec)}"
        label = self._label_why(rec)
        if rec.action == "limit":
            kept = rec.label or f"it is, {NO_LABEL}"
            wanted = f"{self._rule_name(rec)} would split it: {self._rule_why(rec)}; " if rec.rule else ""
            label = label[2:] if label.startswith(", ") else label.removeprefix("as ")
            return f"{head} kept as {kept} ({_stop_text(rec)}): {wanted}label {label}{self._relabel_text(rec)}"
        if self.catalogue is None and not rec.decisive and not rec.relabel:  # a version 1.0 file
            sep = " " if rec.label else ""
            why = "; ".join(c.sentence() for c in rec.checks) or "no check measured"
            return f"{head} accepted{sep}{label}: {why}"
        if self.catalogue is not None and ":" not in label:  # a label without a condition: why no rule acted
            label += f": {self._no_rule_why(rec)}" if self.catalogue.rules else ""
        return f"{head} accepted{' ' if rec.label or rec.relabel else ''}{label}{self._relabel_text(rec)}"

    def _no_rule_why(self, rec: ClusterRecord) -> str:
        """For a cluster no rule acted on: the terms that kept each rule's condition from holding."""
        assert self.catalogue is not None
        outcome = {c.check: c.passed for c in rec.checks}
        terms: list[Term] = []
        for rule in self.catalogue.rules:
            terms += [t for t in evaluate(rule.condition, outcome)[1] if t not in terms]
        return self._terms_text(rec, terms) or "no rule acted"

    def _subtree(self, rec: ClusterRecord) -> list[ClusterRecord]:
        return list(self.walk(rec.id))[1:]

    def _fold(self, records: list[ClusterRecord]) -> str:
        """'37 clusters below: ground 20 (5,021 pts), obstacle 15 (1,200 pts), noise 2 (12 pts)'."""
        groups: dict[str, list[int]] = {}
        for r in records:
            if r.children:
                continue
            key = "noise" if r.action == "reject" else (r.label or NO_LABEL)
            g = groups.setdefault(key, [0, 0])
            g[0] += 1
            g[1] += r.n_points
        order = {name: i for i, name in enumerate([*self.label_names, NO_LABEL, "noise"])}
        parts = ", ".join(f"{k} {n} ({p:,} pts)" for k, (n, p) in sorted(groups.items(), key=lambda kv: order.get(kv[0], -1)))
        return f"{len(records)} cluster{'s' if len(records) != 1 else ''} below, ending as {parts}"

    def tree_lines(self, start: str | None = None, depth: int | None = None) -> list[str]:
        """The tree as indented lines, to ``depth`` levels below ``start`` (None: all); a cluster
        whose children are not shown ends with '[+ N clusters below: ground 20 (5,021 pts), ...]'."""
        base = self.records[start or self.root].depth
        lines = []
        stack = [start or self.root]
        while stack:
            rec = self.records[stack.pop()]
            line = "  " * (rec.depth - base) + self.line(rec)
            if rec.children and depth is not None and rec.depth - base >= depth:
                line += f"  [+ {self._fold(self._subtree(rec))}]"
            else:
                stack.extend(reversed(rec.children))
            lines.append(line)
        return lines

    def render(self, start: str | None = None, depth: int | None = None) -> str:
        """The tree as indented text (to ``depth`` levels below ``start``; None: all)."""
        return "\n".join(self.tree_lines(start, depth))

    def fitting_depth(self, start: str | None = None, lines: int = TREE_LINES) -> int | None:
        """The deepest level to which the tree below ``start`` prints in at most ``lines`` lines
        (at least 1); None when the whole of it does."""
        base = self.records[start or self.root].depth
        per_depth: dict[int, int] = {}
        for r in self.walk(start):
            per_depth[r.depth - base] = per_depth.get(r.depth - base, 0) + 1
        if sum(per_depth.values()) <= lines:
            return None
        total, d = 0, 0
        for level in sorted(per_depth):
            total += per_depth[level]
            if total > lines:
                break
            d = level
        return max(d, 1)

    def summary(self, show: int = 3) -> list[str]:
        """What the run did, grouped and counted: each rule with how often it acted, each label
        with its clusters by outcome (the ``show`` largest named), the checks with their docs."""
        recs = [r for r in self.records.values() if r.action != "partition"]
        leaves = [r for r in recs if not r.children and r.action in ("accept", "limit")]
        rejected = [r for r in recs if r.action == "reject"]
        outputs = {r.output_index for r in leaves if r.output_index is not None}
        depth = max((r.depth for r in recs), default=0)
        splits = sum(r.action in ("split", "split_components") for r in recs)
        out = [f"{len(recs):,} clusters judged, {splits:,} split, {len(leaves):,} kept, {len(rejected):,} rejected "
               f"(tree depth {depth}); {len(outputs):,} output clusters"]

        def largest(group: list[ClusterRecord]) -> str:
            top = sorted(group, key=lambda r: (-r.n_points, r.id))[:show]
            more = ", ..." if len(group) > show else ""
            return ", ".join(f"{r.id} ({r.n_points:,} pts)" for r in top) + more

        def counted(group: list[ClusterRecord]) -> str:
            n = len(group)
            return f"{n:,} cluster{'s' if n != 1 else ''}, {sum(r.n_points for r in group):,} pts"

        cat = self.catalogue
        if cat is not None and cat.rules:
            out.append("rules, in order (the first whose condition holds acts):")
            for rule in cat.rules:
                acted = [r for r in recs if r.rule == rule.name and r.action != "accept"]
                done = [r for r in acted if r.action != "limit"]
                stopped = [r for r in acted if r.action == "limit"]
                what = {"reject": "rejected", "split": "split", "split_components": "split in components"}.get(
                    rule.action, rule.action)
                count = f"{len(done):,} {what}" + (f", {len(stopped):,} kept by a limit" if stopped else "")
                out.append(f"  {rule.name} [{rule.source}] {rule.action} if {rule.condition_text()}: {count}")
                if rule.doc:
                    out.append(f"      {rule.doc}")
        out.append("clusters kept, by label and outcome (points when judged; the largest first):")
        groups: dict[tuple[str, str], list[ClusterRecord]] = {}
        for r in leaves:
            how = "accepted" if r.action == "accept" else f"kept by a limit ({(r.limit or {}).get('kind', 'limit')})"
            if r.relabel and r.relabel.get("undid"):
                how += (f", relabelled {r.relabel['undid']['to']} by {r.relabel['undid']['rule']} and given back by "
                        f"{r.relabel['rule']}")
            elif r.relabel:
                how += f", relabelled from {r.relabel['from']} by {r.relabel['rule']}"
            groups.setdefault((r.label or NO_LABEL, how), []).append(r)
        order = {name: i for i, name in enumerate(self.label_names)}
        labels = {lab.name: lab for lab in cat.labels} if cat else {}
        shown_label = None
        for (label, how), group in sorted(groups.items(), key=lambda kv: (order.get(kv[0][0], len(order)), kv[0][1])):
            if label != shown_label:
                shown_label = label
                info = labels.get(label)
                total = [r for (lb, _), g in groups.items() if lb == label for r in g]
                cond = (f" [{info.source}] if {info.condition_text()}" if info and info.condition is not None
                        else " (the default label)" if info else "")
                doc = f" ({info.doc})" if info and info.doc else ""
                out.append(f"  {label}{cond}{doc}: {counted(total)}")
            out.append(f"    {how}: {counted(group)}: {largest(group)}")
        if rejected:
            out.append(f"  noise (rejected, in no output cluster): {counted(rejected)}: {largest(rejected)}")
        if cat is not None and cat.relabel:
            out.append("post.relabel:")
            for rl in cat.relabel:
                n = sum(1 for r in leaves if r.relabel and r.relabel["rule"] == rl.name)
                back = [r.relabel for r in leaves if r.relabel and (r.relabel.get("undid") or {}).get("rule") == rl.name]
                undoes = {r.relabel["undid"]["rule"] for r in leaves
                          if r.relabel and r.relabel["rule"] == rl.name and r.relabel.get("undid")}
                in_passes = sorted({r.relabel.get("pass", 1) for r in leaves if r.relabel and r.relabel["rule"] == rl.name})
                what = (f"{n:,} given back (undoing {', '.join(sorted(undoes))}, in passes "
                        f"{', '.join(map(str, in_passes))})"
                        if undoes else f"{n:,} relabelled"
                        + (f" (in pass{'es' if len(in_passes) > 1 else ''} {', '.join(map(str, in_passes))})"
                           if any(p > 1 for p in in_passes) else "")
                        + (f", {len(back):,} more given back by {', '.join(sorted({b['rule'] for b in back}))}"
                           if back else ""))
                out.append(f"  {rl.name} [{rl.source}] {rl.action} if {rl.condition_text()}: {what}")
                if rl.doc:
                    out.append(f"      {rl.doc}")
        if cat is not None and cat.checks:
            out.append("checks:")
            w = max(len(c.name) for c in cat.checks.values())
            for c in cat.checks.values():
                out.append(f"  {c.name:<{w}}  {c.bounds_text()} [{c.source}]" + (f": {c.doc}" if c.doc else ""))
        return out

    def sweep_lines(self) -> list[str]:
        """The global strategy's K steps, one line each: the K, which rule wanted which clusters
        split and why (the checks of its condition), where the next K's prototype was seeded; the
        K kept marked. Empty for the divisive strategy."""
        out = []
        for st in self.sweep:
            n = len(st["clusters"])
            head = f"K={st['k']}{' (kept)' if st.get('kept') else ''}: {n} cluster{'s' if n != 1 else ''}"
            if st.get("seeded_in"):
                head += f", its new prototype seeded in {st['seeded_in']} of K={st['k'] - 1}"
            wanted = [c for c in st["clusters"] if c["action"] in ("split", "split_components")
                      or (c["action"] == "limit" and c.get("rule"))]
            rejected = [c for c in st["clusters"] if c["action"] == "reject"]
            if not wanted:
                head += "; no rule wants a cluster split" + (f" ({len(rejected)} rejected as noise)" if rejected else "")
                out.append(head)
                continue
            by_rule: dict[str, list[str]] = {}
            for c in wanted:
                why = ", ".join(_step_check_text(d) for d in c.get("decisive", []))
                rule = f"{c['rule']} [{c['rule_source']}]" if c.get("rule_source") else str(c.get("rule"))
                kept = " (kept: min_points)" if (c.get("limit") or {}).get("kind") == "min_points" else ""
                by_rule.setdefault(rule, []).append(f"{c['id']} ({c['points']:,} pts{': ' + why if why else ''}){kept}")
            head += "; " + "; ".join(f"{rule} fails on {len(ids)}: {', '.join(ids)}" for rule, ids in by_rule.items())
            if st.get("next"):
                head += f"; next K seeded in {st['next']}"
            out.append(head)
        return out

    def ground_line(self) -> str:
        """The ground plane in one line: where it came from, how it was found and how far from the
        sensor (the nearest point of its plane: the nearest candidate wins), e.g. 'cluster c0, its
        robust plane (77 % of its 44,197 points within 0.1), 4.09 m from the sensor, normal
        [-0.019, 0.038, 0.999], 2.4 deg from the fallback normal'."""
        g = self.ground
        if g.source is None:
            return "not used"
        parts = [str(g.source)]
        if g.method == "robust plane":
            of = "its points" if g.plane is None else "the points its earlier planes did not hold"
            if g.share_of == "not_above":
                of += " not above it"
            parts.append(f"its robust plane{'' if g.plane is None else f' {g.plane}'} ({g.inlier_share:.0%} of {of}, "
                         f"{g.inliers:,}, on it)")
        elif g.method:
            parts.append(f"it passes {g.method.removeprefix('check ')}")
            if g.inliers is not None and g.inlier_share is not None:  # refit: its robust plane is the ground's
                of = "its points not above it" if g.share_of == "not_above" else "its points"
                parts.append(f"its robust plane ({g.inlier_share:.0%} of {of}, {g.inliers:,}, on it)")
        if g.supported is not None:  # scene.ground.choose supporting: why this cluster won
            parts.append(f"{g.supported:,} points standing on it")
        if g.distance is not None:  # of the nearest point of its plane: why this cluster won
            unit = f" {g.unit}" if g.unit else ""
            parts.append(f"{g.distance:.2f}{unit} from the sensor")
        if g.normal is not None:
            parts.append("normal [" + ", ".join(f"{x:.3f}".replace("-0.000", "0.000") for x in g.normal) + "]")
        if g.angle_to_fallback is not None:
            parts.append(f"{g.angle_to_fallback:.1f} deg from the fallback normal")
        return ", ".join(parts)

    def ground_text(self) -> str:
        """The ground plane, then every ground candidate's verdict and the fallback's reason."""
        out = [f"ground: {self.ground_line()}"]
        unit = f" {self.ground.unit}" if self.ground.unit else ""
        for v in self.ground.candidates or ():
            what = [f"{v.points:,} points" if v.plane is None else f"robust plane {v.plane}, among {v.points:,} points"]
            if v.inlier_share is not None:
                what.append(f"{v.inlier_share:.0%}{' of those not above it' if self.ground.share_of == 'not_above' else ''}"
                            f" on {'its robust plane' if v.plane is None else 'it'}")
            if v.distance is not None:
                what.append(f"{v.distance:.2f}{unit} from the sensor")
            if v.supported is not None:
                what.append(f"{v.supported:,} points standing on it")
            method = v.method
            verdict = v.why if v.why else "no plane" if not method else \
                "a plane: it passes " + method.removeprefix("check ") if method.startswith("check ") else f"a plane: its {method}"
            out.append(f"  candidate {v.cluster}: {', '.join(what)}: {verdict}")
        if self.ground.note is not None:
            out.append(f"  note: {self.ground.note}")
        return "\n".join(out)

    def why(self, cluster_id: str) -> str:
        """Why one cluster ended as it did: its ancestry, the rules and labels evaluated on it,
        every check with its value, its docs."""
        if cluster_id not in self.records:
            raise KeyError(cluster_id)
        chain = []
        cur: ClusterRecord | None = self.records[cluster_id]
        while cur is not None:
            chain.append(cur)
            cur = self.records[cur.parent] if cur.parent else None
        out = [self.line(r) for r in reversed(chain)]
        rec = chain[0]
        out.append("")
        where = f" (output cluster {rec.output_index})" if rec.output_index is not None else ""
        out.append(f"{rec.id}: {rec.n_points:,} points, action {rec.action}"
                   + (f", label {rec.label}" if rec.label else f", {NO_LABEL}" if _is_leaf(rec) else "") + where)
        out += self._why_decisions(rec)
        if rec.checks:
            out.append("  checks measured (yes: the value is within the check's bounds; 'not NAME' asks for no):")
            docs = self.catalogue.checks if self.catalogue else {}
            w = max(len(c.check) for c in rec.checks)
            for c in rec.checks:
                info = docs.get(c.check)
                doc = f"  {info.doc}" if info and info.doc else ""
                note = f"  ({c.note})" if c.note else ""
                out.append(f"    {c.check:<{w}}  {c.verdict():<3}  {c.predicate} = {c.comparison()}  [{c.source}]"
                           f"{note}{doc}")
        for k, v in rec.descriptors.items():
            out.append(f"  {k}: {_fmt(v)}")
        for n in rec.notes:
            out.append(f"  note: {n}")
        if rec.apd:
            out.append(f"  APD: {rec.apd.text()}")
        return "\n".join(out)

    def _outcome_text(self, rec: ClusterRecord, holds: bool | None, terms) -> str:
        """'holds' / 'does not hold' / 'not evaluated', and the terms that decided it."""
        verdict = "holds" if holds else "does not hold" if holds is False else "not evaluated"
        return verdict + (f": {self._terms_text(rec, terms)}" if terms and holds is not None else "")

    def _why_decisions(self, rec: ClusterRecord) -> list[str]:
        """The rules, labels and relabel rules evaluated on ``rec``, in order, with their outcome."""
        cat = self.catalogue
        if cat is None or rec.action == "partition":
            return []
        outcome = {c.check: c.passed for c in rec.checks}
        out = ["  rules, in order (the first whose condition holds acts):"]
        for rule in cat.rules:
            holds, terms = evaluate(rule.condition, outcome)
            out.append(f"    {rule.name} [{rule.source}] {rule.action} if {rule.condition_text()}: "
                       + self._outcome_text(rec, holds, terms))
            if rule.doc:
                out.append(f"        {rule.doc}")
            if holds:
                break
        else:
            out.append("    no rule acted: the cluster is accepted")
        if rec.action == "limit":
            out.append(f"    the split did not happen ({_stop_text(rec)}): the cluster is kept as it is and labelled")
        if not _is_leaf(rec):
            return out
        out.append("  labels, in order (the first whose condition holds gives the label):")
        for lab in cat.labels:
            holds, terms = evaluate(lab.condition, outcome)
            if lab.condition is None:
                verdict = "no condition (the default label)"
            else:
                verdict = f"if {lab.condition_text()}: " + self._outcome_text(rec, holds, terms)
            out.append(f"    {lab.name} [{lab.source}] {verdict}" + (f"; {lab.doc}" if lab.doc else ""))
            if holds:
                break
        else:
            out.append(f"    {NO_LABEL}")
        given = rec.first_label
        relabel = [r for r in cat.relabel if r.action.split(" -> ")[0] == given]
        if relabel:
            out.append(f"  post.relabel, the rules for clusters labelled {given}:")
            for rl in relabel:
                holds, terms = evaluate(rl.condition, outcome)
                if (rec.relabel and rec.relabel["rule"] == rl.name
                        and (rec.relabel.get("undid") or rec.relabel.get("pass", 1) == 1)):
                    holds = True  # (a rule with passes that took it later says so below)
                out.append(f"    {rl.name} [{rl.source}] {rl.action} if {rl.condition_text()}: "
                           + self._outcome_text(rec, holds, terms))
                if rl.doc:
                    out.append(f"        {rl.doc}")
                if holds:
                    break
        r = rec.relabel
        if r and not r.get("undid") and r.get("pass", 1) > 1:  # taken by a rule with passes, judged again
            checks = tuple(CheckRecord(**_known(CheckRecord, c)) for c in r.get("measured") or [])
            out.append(f"  post.relabel, judged again by {r['rule']} [{r['source']}] in pass {r['pass']} against the "
                       f"surface rebuilt without the clusters relabelled in the passes before "
                       f"({r.get('surface_points', 0):,} surface points): holds, relabelled {r['to']}: "
                       + "; ".join(c.sentence() for c in checks))
        again = _judged_again(rec)
        if again:
            out.append(f"  post.relabel, judged again (relabelled by {again[0][0]}) against the surface rebuilt from the "
                       "labels the passes before left:")
            for _, step in again:
                checks = tuple(CheckRecord(**_known(CheckRecord, c)) for c in step.get("measured", []))
                why = "; ".join(c.sentence() for c in checks)
                verdict = "holds, its label given back" if step.get("holds", True) else "does not hold"
                out.append(f"    {step['rule']} [{step['source']}] pass {step['pass']} "
                           f"({step.get('surface_points', 0):,} surface points): {verdict}: {why}")
        return out


def _judged_again(rec: ClusterRecord) -> list[tuple[str, Mapping[str, Any]]]:
    """The passes of a rule that undoes another on ``rec``: (the undone rule, the pass's record),
    in order (empty for a cluster no such rule judged)."""
    r = rec.relabel
    if not r:
        return []
    if r.get("undid"):
        u = r["undid"]
        return [(u["rule"], s) for s in u.get("judged_again", [])] + [(u["rule"], r)]
    return [(r["rule"], s) for s in r.get("judged_again", [])]


#: What an accepted cluster no label's condition holds for is called (its points have label -1,
#: as rejected ones do, but they are in an output cluster): never 'noise', which a rule base may
#: use as one of its labels.
NO_LABEL = "no label matched"


def _stop_text(rec: ClusterRecord) -> str:
    """What kept a cluster a rule wanted split: 'limit reached: limits.max_depth = 11', 'limit
    reached: 30 points < limits.min_points = 40', 'the split failed'."""
    lim = rec.limit
    if lim is None:  # a version 1.0 file without the limit's kind: its notes say it
        return "; ".join(rec.notes)
    if lim.get("kind") == "min_points":
        return f"limit reached: {rec.n_points:,} points < {lim['setting']} = {lim['value']}"
    if lim.get("setting"):
        return f"limit reached: {lim['setting']} = {lim['value']}"
    return _NOT_SPLIT_TEXT.get(lim.get("kind", ""), str(lim.get("kind")))


def _step_check_text(d: Mapping[str, Any]) -> str:
    """A check of a global-strategy step (:attr:`Explanation.sweep`) in words: 'not planar
    (thickness = 0.08 m > 0.01 m)'."""
    c = CheckRecord(**_known(CheckRecord, {"note": "", **d}))
    return f"{'' if c.passed else 'not '}{c.check} ({c.sentence()})"


def _is_leaf(rec: ClusterRecord) -> bool:
    """An output cluster's record: accepted, or kept by a limit (rejected ones are noise)."""
    return rec.action in ("accept", "limit") and not rec.children


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


#: For each kind of stop (``Segmentation.limits_by_kind``): the words of its summary line.
_STOP_TEXT: dict[str, str] = {
    "max_depth": "raise {setting} in {file} to split them",
    "min_points": "lower {setting} in {file} to split them",
    "max_clusters": "raise or remove {setting} in {file} (a cap on the whole file: results depend on its size)",
    "k_max": "raise {setting} in {file}, or use strategy: divisive",
}
_NOT_SPLIT_TEXT: dict[str, str] = {
    "split_failed": "the split failed",
    "single_cluster": "the split gave a single cluster",
    "unpartitioned": "the engine could not partition the scene",
}


def limit_lines(limits_by_kind: dict[str, dict[str, Any]], rule_file: str, *, result: str | None = None,
                show: int = 3) -> list[str]:
    """One line per kind of stop, for the summary of a run (``Segmentation.summary()['limits_by_kind']``):

    'limits: min_points (40) stopped 17 clusters, 512 points (c0.1.2.3, c1.4, c1.0.2, ...): lower
    limits.min_points in outdoor.yaml to split them'; the cases that are not settings of the file
    (the split failed, or gave a single cluster) say so: 'not split: the split failed for 3 clusters,
    ...: kbs explain RESULT --cluster c1.2 says why' (``result``: the result file, when there is one).
    """
    out = []
    for kind, e in limits_by_kind.items():
        n, ids = e["count"], e["clusters"]
        where = ", ".join(ids[:show]) + (", ..." if len(ids) > show else "")
        what = f"{n:,} cluster{'s' if n != 1 else ''}, {e['points']:,} points ({where})"
        if kind in _STOP_TEXT:
            todo = _STOP_TEXT[kind].format(setting=e["setting"], file=rule_file)
            out.append(f"limits: {kind} ({e['value']}) stopped {what}: {todo}")
        else:
            why = (f"kbs explain {result} --cluster {ids[0]} says why" if result else
                   f"the explanation of {ids[0]} says why")
            out.append(f"not split: {_NOT_SPLIT_TEXT.get(kind, kind)} for {what}: {why}")
    return out
