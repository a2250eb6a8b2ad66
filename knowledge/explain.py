"""Explanations are data: a tree of records, one per cluster, saying what was measured, which rule
acted, with what result. Only the renderers here turn them into sentences.

Like hdbscan's ``CondensedTree``: a first-class object with exporters (:meth:`Explanation.to_dict`,
:meth:`Explanation.to_networkx`) and renderers (:meth:`Explanation.render`,
:meth:`Explanation.why`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Iterator


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
        it, ('>=', min) or ('<', min) for a lower bound."""
        if self.max is not None and (self.value > self.max or self.min is None or self.value >= self.min):
            return ("<=" if self.value <= self.max else ">"), self.max
        return (">=" if self.value >= self.min else "<"), self.min

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
        u = f" {self.unit}" if self.unit else ""
        return f"{self.value:.4g}{u} {op} {b:g}{u}"

    def sentence(self) -> str:
        """'connexity = 3 components > 1', 'thickness = 0.12 m > 0.05 m', 'ground_angle undefined
        (degenerate: its points lie on a line, no plane)'."""
        if self.value is None:
            return f"{self.predicate} undefined ({self.note})" if self.note else f"{self.predicate} = {self._unknown()}"
        op, b = self.bound()
        u = f" {self.unit}" if self.unit else ""
        if self.predicate == "connexity":
            n = int(round(self.value))
            return f"connexity = {n} component{'s' if n != 1 else ''} {op} {b:g}"
        if self.predicate == "point_count":
            return f"point_count = {int(self.value):,} {op} {b:g}"
        return f"{self.predicate} = {self.value:.4g}{u} {op} {b:g}{u}"


@dataclass(frozen=True)
class APDCurve:
    """The APD values of the UFP-ONC sweep that chose K for a split."""

    ks: tuple[int, ...]
    apd: tuple[float, ...]
    chosen: int

    def text(self) -> str:
        return ", ".join(f"K={k}{'*' if k == self.chosen else ''}: {'null' if a is None else f'{a:.4g}'}"
                         for k, a in zip(self.ks, self.apd))


@dataclass
class ClusterRecord:
    """Everything decided about one cluster.

    ``action`` is one of 'accept', 'split' (UFP-ONC), 'split_components', 'reject' (noise),
    'limit' (it should have been split but a limit stopped it; it is kept as it is), 'partition'
    (the root: the scene's initial partition).
    """

    id: str
    parent: str | None
    depth: int
    n_points: int
    descriptors: dict[str, Any] = field(default_factory=dict)
    checks: list[CheckRecord] = field(default_factory=list)
    action: str = "accept"
    rule: str | None = None
    rule_source: str | None = None
    children: list[str] = field(default_factory=list)
    label: str | None = None
    apd: APDCurve | None = None
    notes: list[str] = field(default_factory=list)
    output_index: int | None = None  #: value of the per-point 'cluster' property, None if none
    decisive: list[str] = field(default_factory=list)  #: checks of the condition that decided
    #: set when a post.relabel rule changed the label: {rule, source, from, to, checks}
    relabel: dict[str, Any] | None = None
    contact: int = 0  #: points that left it for the ground (post.ground_contact)
    released: int = 0  #: points that left this ground cluster, standing above the surface (post.ground_release)
    #: set when action is 'limit': what stopped the split, {kind, setting, value}, e.g.
    #: {'kind': 'max_depth', 'setting': 'limits.max_depth', 'value': 12} (kinds: interpreter.STOP_KINDS)
    limit: dict[str, Any] | None = None

    def decisive_checks(self) -> list[CheckRecord]:
        names = set(self.decisive)
        return [c for c in self.checks if c.check in names]

    def failing_checks(self) -> list[CheckRecord]:
        return [c for c in self.checks if not c.passed]


@dataclass
class Explanation:
    """The tree of cluster records of one run."""

    rule_base: str
    rule_file: str
    strategy: str
    label_names: list[str]
    records: dict[str, ClusterRecord]
    root: str
    ground: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

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
        return {
            "rule_base": self.rule_base, "rule_file": self.rule_file, "strategy": self.strategy,
            "label_names": list(self.label_names), "root": self.root, "ground": self.ground,
            "notes": list(self.notes), "clusters": [_record_dict(r) for r in self.walk()],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Explanation":
        records = {}
        for r in d["clusters"]:
            r = dict(r)
            r["checks"] = [CheckRecord(**c) for c in r.get("checks", [])]
            if r.get("apd"):
                a = r["apd"]
                r["apd"] = APDCurve(tuple(a["ks"]), tuple(a["apd"]), a["chosen"])
            records[r["id"]] = ClusterRecord(**r)
        return cls(rule_base=d["rule_base"], rule_file=d["rule_file"], strategy=d["strategy"],
                   label_names=list(d["label_names"]), records=records, root=d["root"], ground=d.get("ground", {}),
                   notes=list(d.get("notes", [])))

    def to_networkx(self):
        """A ``networkx.DiGraph`` parent -> child with each record's fields as node attributes."""
        import networkx as nx

        g = nx.DiGraph()
        for r in self.walk():
            g.add_node(r.id, **{k: v for k, v in asdict(r).items() if k != "children"})
            if r.parent is not None:
                g.add_edge(r.parent, r.id)
        return g

    # -- renderers -------------------------------------------------------------------------

    def line(self, rec: ClusterRecord) -> str:
        """One line: 'c0.2 (1,204 pts) split in 3: connexity = 3 components > 1 [outdoor.yaml:31 CAh]'."""
        head = f"{rec.id} ({rec.n_points:,} pts)"
        src = f" [{rec.rule_source} {rec.rule}]" if rec.rule_source else ""
        why = "; ".join(c.sentence() for c in rec.decisive_checks())
        if rec.action == "partition":
            k = len(rec.children)
            chosen = f" (APD first local maximum: {rec.apd.text()})" if rec.apd else ""
            return f"{head} partitioned in {k}{chosen}"
        if rec.action in ("split", "split_components"):
            how = "" if rec.action == "split" else " components"
            return f"{head} split in {len(rec.children)}{how}: {why}{src}"
        if rec.action == "reject":
            return f"{head} rejected as noise: {why}{src}"
        if rec.action == "limit":
            kept = rec.label or f"it is, {NO_LABEL}"
            return f"{head} kept as {kept} ({'; '.join(rec.notes)}): {why}{src}{self._relabel_text(rec)}"
        label = f" as {rec.label}" if rec.label else f", {NO_LABEL}"
        if rec.relabel:
            return f"{head} accepted as {rec.relabel['from']}{self._relabel_text(rec)}"
        why = why or "; ".join(c.sentence() for c in rec.checks) or "no check measured"
        return f"{head} accepted{label}: {why}"

    @staticmethod
    def _relabel_text(rec: ClusterRecord) -> str:
        """', relabelled ground: height_above_local_ground = 0.08 m <= 0.25 m [outdoor.yaml:95 low_sheet]'."""
        if not rec.relabel:
            return ""
        r = rec.relabel
        names = set(r["checks"])
        why = "; ".join(c.sentence() for c in rec.checks if c.check in names)
        return f", relabelled {r['to']}: {why} [{r['source']} {r['rule']}]"

    def render(self, start: str | None = None) -> str:
        """The tree as indented text."""
        base = self.records[start or self.root].depth
        lines = []
        for rec in self.walk(start):
            lines.append("  " * (rec.depth - base) + self.line(rec))
        return "\n".join(lines)

    def ground_line(self) -> str:
        """The ground plane in one line: where it came from and how it was found, e.g. 'cluster c0,
        its robust plane (77 % of its 44,197 points within 0.1), normal [-0.019, 0.038, 0.999],
        2.4 deg from the fallback normal'."""
        g = self.ground
        if not g or "source" not in g:
            return "not used"
        parts = [str(g["source"])]
        method = g.get("method")
        if method == "robust plane":
            parts.append(f"its robust plane ({g['inlier_share']:.0%} of its points, {g['inliers']:,}, on it)")
        elif method:
            parts.append(f"it passes {method.removeprefix('check ')}")
        if g.get("normal") is not None:
            parts.append("normal [" + ", ".join(f"{x:.3f}".replace("-0.000", "0.000") for x in g["normal"]) + "]")
        if g.get("angle_to_fallback") is not None:
            parts.append(f"{g['angle_to_fallback']:.1f} deg from the fallback normal")
        return ", ".join(parts)

    def ground_text(self) -> str:
        """The ground plane, then every ground candidate's verdict and the fallback's reason."""
        out = [f"ground: {self.ground_line()}"]
        unit = f" {self.ground['unit']}" if self.ground.get("unit") else ""
        for v in self.ground.get("candidates", []):
            what = [f"{v['points']:,} points"]
            if v.get("inlier_share") is not None:
                what.append(f"{v['inlier_share']:.0%} on its robust plane")
            if v.get("distance_to_sensor") is not None:
                what.append(f"{v['distance_to_sensor']:.2f}{unit} from the sensor")
            method = v.get("method")
            verdict = v["why"] if v.get("why") else "no plane" if not method else \
                "a plane: it passes " + method.removeprefix("check ") if method.startswith("check ") else f"a plane: its {method}"
            out.append(f"  candidate {v['cluster']}: {', '.join(what)}: {verdict}")
        if "note" in self.ground:
            out.append(f"  note: {self.ground['note']}")
        return "\n".join(out)

    def why(self, cluster_id: str) -> str:
        """Why one cluster ended as it did: its ancestry, its decision, every check with values."""
        if cluster_id not in self.records:
            raise KeyError(cluster_id)
        chain = []
        rec: ClusterRecord | None = self.records[cluster_id]
        while rec is not None:
            chain.append(rec)
            rec = self.records[rec.parent] if rec.parent else None
        out = [self.line(r) for r in reversed(chain)]
        rec = chain[0]
        out.append("")
        out.append(f"{rec.id}: {rec.n_points:,} points, action {rec.action}"
                   + (f", label {rec.label}" if rec.label else f", {NO_LABEL}" if _is_leaf(rec) else ""))
        for c in rec.checks:
            out.append(f"  {'pass' if c.passed else 'FAIL'}  {c.check}: {c.predicate} = {c.comparison()}  [{c.source}]"
                       + (f"  ({c.note})" if c.note else ""))
        for k, v in rec.descriptors.items():
            out.append(f"  {k}: {_fmt(v)}")
        for n in rec.notes:
            out.append(f"  note: {n}")
        if rec.apd:
            out.append(f"  APD: {rec.apd.text()}")
        return "\n".join(out)


#: What an accepted cluster no label's condition holds for is called (its points have label -1,
#: as rejected ones do, but they are in an output cluster): never 'noise', which a rule base may
#: use as one of its labels.
NO_LABEL = "no label matched"


def _is_leaf(rec: ClusterRecord) -> bool:
    """An output cluster's record: accepted, or kept by a limit (rejected ones are noise)."""
    return rec.action in ("accept", "limit") and not rec.children


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _record_dict(r: ClusterRecord) -> dict[str, Any]:
    """A record as plain data (what ``dataclasses.asdict`` gives, without its deep copies)."""
    d = dict(vars(r))
    d["checks"] = [dict(vars(c)) for c in r.checks]
    d["apd"] = None if r.apd is None else {"ks": list(r.apd.ks), "apd": list(r.apd.apd), "chosen": r.apd.chosen}
    d["children"], d["notes"], d["decisive"] = list(r.children), list(r.notes), list(r.decisive)
    d["limit"] = None if r.limit is None else dict(r.limit)
    return d


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
