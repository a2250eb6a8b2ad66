"""The shapes of the knowledge layer's parts, beside predicates: post steps, actions, strategies.

Each part is one class in one module, found through a table (:data:`kbs.knowledge.post.STEPS`,
:data:`kbs.knowledge.actions.ACTIONS`, :data:`kbs.knowledge.strategies.STRATEGIES`), as
yamllint's rules are. A plugin file adds post steps and actions as it adds predicates: it defines
subclasses of :class:`PostStep` or :class:`Action`, and ``--plugin FILE`` registers them after the
same checks (:func:`check_part`).

**A post step** (``post:`` in a rule file, a sequence run in order after labelling):

- ``key``: its name in the rule file; ``schema``: the JSON Schema of its spec (may refer to
  ``#/$defs/name``, ``#/$defs/condition``, ``#/$defs/tune`` of the rule-file schema); the class
  docstring is its doc;
- ``tunable``: its numeric fields ``kbs tune`` may fit (``tune:`` marks);
- ``parse(raw, ctx)``: a frozen spec from the rule file's mapping, every problem reported with its
  position through ``ctx`` (:class:`SpecContext`); None when it cannot be built;
- ``apply(state, ctx)``: a new :class:`~kbs.knowledge.state.PostState` from the old one
  (:class:`PostContext` gives the cloud, the rule base and the measuring of checks). The leaves'
  records are frozen: a step that decides more about a leaf gives it a new record
  (``leaf.with_record(label=..., notes=(...,))``) in the new state's leaves.

**An action** (``then:`` of a rule): ``divides`` (it wants the cluster split: the divisive
strategy calls ``divide`` for its children; the global strategy goes on to the next K), or not:
``keeps`` (the cluster is a leaf) or not (its points are noise). ``validate(rule, ctx)`` checks a
rule that uses it; ``prepare`` may start work when the cluster is judged (the UFP-ONC split runs
in a worker while the rest of the wave is judged); ``divide(engine, node, cluster, facts, rule,
prepared)`` gets the measurements of the checks judged on the cluster (``facts``, a read-only
mapping by check name, e.g. the components of a failed connexity check) and returns the children
(or a :class:`~kbs.knowledge.state.Division`, with the APD curve that chose their number);
``inherit`` gives the checks the children know without measuring.

**A strategy** (``strategy:``): ``partition(engine, X)`` the scene's first partition, then
``run(engine, X, root, records, first)`` gives the leaves and the scene
(:class:`~kbs.knowledge.state.Judged`); ``records`` are the drafts of the tree's records
(:class:`~kbs.knowledge.state.Draft`), frozen into the ``Judged``.
"""
from __future__ import annotations

import inspect
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from kbs.knowledge.predicates import PredicateError

if TYPE_CHECKING:
    import numpy as np

    from kbs.knowledge.explain import CheckRecord, ClusterRecord
    from kbs.knowledge.predicates import Cluster, Measurement, Scene
    from kbs.knowledge.rulebase import Check, Condition, RuleBase, SourcePos
    from kbs.knowledge.state import Division, Draft, Judged, Node, PostState

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class SpecContext(Protocol):
    """What a part's ``parse``/``validate`` may ask of the rule file being read (the validator of
    :mod:`kbs.knowledge.rulebase` implements it)."""

    #: where the spec is in the document, e.g. ('post', 2, 'ground_contact') or, in a file that
    #: writes post as a mapping, ('post', 'ground_contact')
    path: tuple
    #: the label names, in order
    labels: list[str]
    #: the checks, by name
    checks: Mapping[str, Check]
    #: the post steps before this one, in order
    earlier: tuple[PostStep, ...]

    def add(self, path: tuple, message: str, *, key: bool = False) -> None:
        """Report a problem at ``path`` (the key itself with ``key``)."""

    def warn(self, path: tuple, message: str, *, key: bool = False) -> None:
        """A warning: valid, but cannot be meant."""

    def pos(self, path: tuple, *, key: bool = False) -> SourcePos:
        """The position of ``path`` in the file."""

    def label_ref(self, path: tuple, name: Any) -> None:
        """Report ``name`` at ``path`` if it is not a label."""

    def condition(self, raw: Any, path: tuple) -> Condition | None:
        """A condition over the checks (problems reported), None when invalid."""

    def never(self, cond: Condition, path: tuple, what: str) -> None:
        """Report a condition that can never hold."""

    def number(self, value: Any, default: float, kind: type = float) -> Any:
        """``value`` as a number (the schema checked its type), ``default`` when absent."""


class Facts(Protocol):
    """The outcome of the checks on one cluster (``facts(name) -> bool``, each measured once), and
    its record with the checks measured so far."""

    record: ClusterRecord

    def __call__(self, name: str) -> bool:
        """Whether the check ``name`` holds on the cluster."""


class PostContext(Protocol):
    """What a post step's ``apply`` may use."""

    X: np.ndarray
    rule_base: RuleBase
    #: processes the step may use (k-d tree queries)
    jobs: int

    def fact(self, cluster: Cluster, scene: Scene, record: ClusterRecord) -> Facts:
        """The outcome of a check on a cluster, measured once; ``.record`` is ``record`` with the
        checks measured so far (give it to the leaf: ``leaf.with_record(fact.record, ...)``)."""

    def names(self, cond: Condition | None) -> list[str]:
        """The checks a condition names, in order, once each."""


class PostStep:
    """Base of the post steps. Subclasses are frozen dataclasses (their fields: the spec)."""

    key: ClassVar[str]
    schema: ClassVar[dict[str, Any]]
    tunable: ClassVar[tuple[str, ...]] = ()
    #: the position of the step in the rule file (every spec has one)
    pos: SourcePos

    @classmethod
    def parse(cls, raw: Any, ctx: SpecContext) -> PostStep | None:
        raise NotImplementedError

    def apply(self, state: PostState, ctx: PostContext) -> PostState:
        raise NotImplementedError

    @classmethod
    def doc(cls) -> str:
        return " ".join((cls.__doc__ or "").split("\n\n")[0].split())


class Action:
    """Base of the actions a rule may take (``then:``)."""

    key: ClassVar[str]
    #: the action wants the cluster divided (``divide`` gives its children)
    divides: ClassVar[bool] = False
    #: (an action that does not divide) the cluster is kept as a leaf; False: its points are noise
    keeps: ClassVar[bool] = True

    def validate(self, rule: Any, path: tuple, ctx: SpecContext) -> None:
        """Problems of a rule (name, condition, action) that takes this action; ``path`` is the
        rule's in the file."""

    def prepare(self, engine: Any, cluster: Cluster) -> Any:
        """Work to start as soon as the cluster is judged (None: nothing)."""
        return None

    def divide(self, engine: Any, node: Node, cluster: Cluster, facts: Mapping[str, Measurement], rule: Any,
               prepared: Any) -> list[Node] | Division:
        """The children of ``node`` (two or more; raise :class:`~kbs.errors.FitError` when it
        cannot be divided: the cluster is kept, the explanation says why). ``facts``: the
        measurements of the checks judged on the cluster, by check name (read-only)."""
        raise NotImplementedError

    def inherit(self, engine: Any, rule: Any, parent: Node) -> list[tuple[CheckRecord, Measurement]]:
        """Checks the children of a division of ``parent`` know without measuring (each recorded
        in every child's record, as if measured)."""
        return []

    @classmethod
    def doc(cls) -> str:
        return " ".join((cls.__doc__ or "").split("\n\n")[0].split())


class Strategy:
    """Base of the strategies (``strategy:``)."""

    key: ClassVar[str]

    def partition(self, engine: Any, X: np.ndarray) -> Any:
        """The scene's first partition (raise :class:`~kbs.errors.FitError` when the engine cannot
        partition it: the run makes the scene one cluster)."""
        raise NotImplementedError

    def run(self, engine: Any, X: np.ndarray, root: Node, records: dict[str, Draft], first: Any) -> Judged:
        """Judge and divide from the first partition: the leaves, the scene, the records."""
        raise NotImplementedError

    @classmethod
    def doc(cls) -> str:
        return " ".join((cls.__doc__ or "").split("\n\n")[0].split())


_KINDS: dict[type, tuple[str, tuple[str, ...]]] = {
    PostStep: ("post step", ("parse", "apply")),
    Action: ("action", ()),
    Strategy: ("strategy", ("partition", "run")),
}


def check_part(cls: Any, origin: str) -> str:
    """Check a part's contract when it is registered (not when a rule file first uses it);
    returns its kind. Raises :class:`~kbs.knowledge.predicates.PredicateError` naming the part."""
    base = next((b for b in _KINDS if isinstance(cls, type) and issubclass(cls, b) and cls is not b), None)
    if base is None:
        raise PredicateError(f"{origin}: {cls!r} is not a post step, action or strategy class")
    kind, methods = _KINDS[base]
    key = getattr(cls, "key", None)
    if not isinstance(key, str) or not _NAME.match(key):
        raise PredicateError(f"{origin}: {kind} {cls.__name__} needs a 'key' (a name: letters, digits, '_'), "
                             f"got {key!r}")
    if not (cls.__doc__ or "").strip():
        raise PredicateError(f"{origin}: {kind} '{key}' needs a docstring (its doc in explanations and listings)")
    for m in methods:
        if getattr(cls, m) is getattr(base, m):
            raise PredicateError(f"{origin}: {kind} '{key}' must define {m}()")
    if base is PostStep:
        schema = getattr(cls, "schema", None)
        if not isinstance(schema, dict) or schema.get("type") not in ("object", "array"):
            raise PredicateError(f"{origin}: post step '{key}' needs a 'schema': a JSON Schema dict of type "
                                 "object or array")
        tun = cls.tunable
        if not isinstance(tun, tuple) or not all(isinstance(t, str) for t in tun):
            raise PredicateError(f"{origin}: post step '{key}': 'tunable' must be a tuple of field names")
        if not inspect.isclass(cls) or "pos" not in getattr(cls, "__dataclass_fields__", {}):
            raise PredicateError(f"{origin}: post step '{key}' must be a frozen dataclass with a 'pos' field "
                                 "(its position in the rule file)")
    if base is Action:
        if cls.divides and cls.divide is Action.divide:
            raise PredicateError(f"{origin}: action '{key}' divides: it must define divide()")
    return kind


def post_schema(steps: Mapping[str, type[PostStep]]) -> dict[str, Any]:
    """The JSON Schema of a rule file's ``post``: a sequence of one-key mappings, one step each,
    run in order (or, as rule files written before the sequence, one mapping of the steps, run in
    the order of :data:`kbs.knowledge.post.LEGACY_ORDER`)."""
    item = {"type": "object", "minProperties": 1, "maxProperties": 1, "additionalProperties": False,
            "properties": {k: {"description": s.doc(), **s.schema} for k, s in steps.items()}}
    return {
        "description": "What is done after labelling, in order: a sequence of steps, each a mapping of one step "
                       "name to its settings (a mapping of step names, as older files write it, runs them in "
                       "the fixed order ground_model, relabel, ground_release, ground_contact, merge_coplanar).",
        "anyOf": [{"type": "array", "items": item},
                  {"type": "object", "additionalProperties": False, "properties": item["properties"]}],
    }
