"""The engine settings, declared once: for each, what values it takes, its default and a one-line
doc. Everything that takes these settings reads them here: :func:`~kbs.inference.ufp_onc.ufp_onc`,
:class:`~kbs.inference.incremental.IncrementalSweep`, the estimators (their
``_parameter_constraints``), the rule file's ``engine:`` section (its defaults, its checks, and the
part of ``rules/rule-base.schema.json`` generated from this table by
:mod:`kbs.knowledge.engine_settings`), ``kbs rules schema --engine`` and the README's table.

A setting may be narrower in a rule file than in the engine (:attr:`Setting.rule_file`), and the
scikit-learn-style estimators may keep a default of their own (:attr:`Setting.estimator_default`);
both are declared here, each with its reason, not in the places that use them.
"""
from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from kbs.inference._validation import Interval, NoneValue, Options

#: :attr:`Setting.estimator_default` when the estimators default to the engine's own value
SAME = object()

Constraint = Interval | Options | NoneValue


@dataclass(frozen=True)
class Setting:
    """One engine setting.

    Attributes
    ----------
    name : str
        The keyword of :func:`~kbs.inference.ufp_onc.ufp_onc` (and of the estimators), and the key
        in a rule file's ``engine:`` section.
    allowed : tuple of constraints
        The values the engine takes (any one of them).
    default : object
        The engine's default, which is also the rule file's.
    doc : str
        One line: what it does.
    rule_file : tuple of constraints or None
        The values a rule file may give, when narrower than ``allowed`` (``rule_note`` says why);
        None: the same as ``allowed``.
    in_rule_file : bool
        Whether a rule file's ``engine:`` section may set it.
    in_ufp_onc : bool
        Whether it is a keyword of ``ufp_onc`` (``initial_k`` and ``split_min_k`` are read by the
        knowledge layer: how the first K is chosen, the ``min_k`` a split passes).
    estimator_default : object
        The estimators' default when it differs from the engine's (:data:`SAME` otherwise).
    """

    name: str
    allowed: tuple[Constraint, ...]
    default: Any
    doc: str
    rule_file: tuple[Constraint, ...] | None = None
    rule_note: str = ""
    in_rule_file: bool = False
    in_ufp_onc: bool = True
    estimator_default: Any = SAME
    estimator_note: str = ""

    @property
    def rule_file_allowed(self) -> tuple[Constraint, ...]:
        """The values a rule file may give."""
        return self.allowed if self.rule_file is None else self.rule_file

    @property
    def fit_default(self) -> Any:
        """The estimators' default."""
        return self.default if self.estimator_default is SAME else self.estimator_default

    def describe(self, *, rule_file: bool = False) -> str:
        """'a float in the range (1, inf)', or several joined by 'or'."""
        return " or ".join(repr(c.values[0]) if isinstance(c, Options) and len(c.values) == 1 else c.describe()
                           for c in (self.rule_file_allowed if rule_file else self.allowed))

    def line(self, *, rule_file: bool = False) -> str:
        """One line: name, default, constraint, doc (``kbs rules schema --engine``)."""
        return f"{self.name} = {format_default(self.default)}: {self.describe(rule_file=rule_file)}. {self.doc}"


def format_default(value: Any) -> str:
    """A default as a rule file writes it (None as 'null')."""
    if value is None:
        return "null"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _int(low: float | None, high: float | None = None) -> Interval:
    return Interval(numbers.Integral, low, high)


def _real(low: float | None, high: float | None = None, closed: str = "both") -> Interval:
    return Interval(numbers.Real, low, high, closed=closed)


def _positive() -> Interval:
    return _real(0, None, closed="neither")


#: The table, in the order of the rule file's ``engine:`` section (its keys first), then the
#: settings only Python callers give.
ENGINE_SETTINGS: tuple[Setting, ...] = (
    Setting("m", (_real(1, None, closed="neither"),), 2.0,
            "Fuzzifier; with 2 the memberships are the posteriors of a Gaussian mixture.", in_rule_file=True),
    Setting("k_max", (_int(1),), 10, "Largest K tried (the global strategy: the largest K of the scene's partition).",
            rule_file=(_int(2, 50),),
            rule_note="a rule file's K bounds its splits, which need K = 2 (with 1, every split fails), and 50 "
                      "bounds the cost of a sweep the file asks for; the engine takes any K >= 1 (GathGeva with "
                      "n_clusters=1 is a sweep of K = 1)",
            in_rule_file=True),
    Setting("initial_k", (Options(("first_apd_max",)), _int(1)), "first_apd_max",
            "K of the first partition: 'first_apd_max' (APD's first local maximum, the seed paper) or a fixed K.",
            in_rule_file=True, in_ufp_onc=False),
    Setting("max_fit_points", (_int(10), NoneValue()), 6000,
            "Larger clouds are fitted on a voxel grid of at most this many voxels.",
            rule_file=(_int(100),),
            rule_note="a rule file segments scans: at least 100 voxels, and no unreduced fit of a whole scan",
            in_rule_file=True),
    Setting("min_variance", (_positive(),), 1e-6,
            "Absolute eigenvalue floor of the covariances, in squared length units (sensor noise).",
            in_rule_file=True),
    Setting("max_condition", (_real(1),), 1e4,
            "Relative eigenvalue floor: every eigenvalue >= the largest / max_condition.", in_rule_file=True),
    Setting("tol", (_positive(),), 1e-3, "Gath-Geva stops when no membership moves by this much in an update.",
            in_rule_file=True, estimator_default=1e-4,
            estimator_note="one fit, not the hundreds of a segmentation: the estimators' documented default is "
                           "tighter"),
    Setting("fcm_tol", (_positive(),), 1e-3,
            "Fuzzy c-means, which starts each K's Gath-Geva fit, stops when no membership moves by this much in an "
            "update.",
            in_rule_file=True),
    Setting("max_iter", (_int(1),), 100, "Most Gath-Geva updates per K.", in_rule_file=True,
            estimator_default=300,
            estimator_note="one fit, not the hundreds of a segmentation: the estimators' documented default is "
                           "higher (FuzzyCMeans' max_iter too)"),
    Setting("new_prototype", (Options(("distance", "worst")),), "distance",
            "How K's new prototype enters: 'distance' (10 trace(Cov X) from every point) or 'worst' "
            "(the worst-explained point).", in_rule_file=True),
    Setting("split_min_k", (_int(1, 2),), 1,
            "A divisive split takes K at APD's first local maximum among K >= split_min_k; with 1, a split whose "
            "maximum is K = 1 takes K = 2.", in_rule_file=True, in_ufp_onc=False),
    # -- Python callers only ------------------------------------------------------------------------
    Setting("center_power", (_real(1), NoneValue()), None,
            "Power of the memberships in the centre update; None: m (Gath-Geva's), 1: the EM-like centre."),
    Setting("fcm_max_iter", (_int(1),), 100, "Most fuzzy c-means updates per K."),
    Setting("min_cluster_size", (_positive(), NoneValue()), None,
            "A cluster whose effective size sum w u falls below this dies; None: max(D + 1, 0.001 x total weight)."),
    Setting("stop", (Options(("k_max", "first_max")),), "k_max",
            "Compute every K up to k_max, or stop once APD's first local maximum is confirmed."),
    Setting("min_k", (_int(1),), 1, "Smallest K that may be chosen (a split passes split_min_k)."),
    Setting("voxel_size", (_positive(), NoneValue()), None,
            "Voxel edge of the fitting grid; None: sized from max_fit_points."),
    Setting("chunk_size", (_int(1),), 65536, "Rows per chunk when computing the memberships of every point."),
)

#: The settings by name.
SETTINGS: Mapping[str, Setting] = MappingProxyType({s.name: s for s in ENGINE_SETTINGS})

#: The engine's defaults by name (the keyword defaults of ufp_onc and IncrementalSweep).
DEFAULTS: Mapping[str, Any] = MappingProxyType({s.name: s.default for s in ENGINE_SETTINGS})

#: The estimators' defaults by name.
FIT_DEFAULTS: Mapping[str, Any] = MappingProxyType({s.name: s.fit_default for s in ENGINE_SETTINGS})


def constraints(names: Sequence[str] | None = None) -> dict[str, list]:
    """The constraints of ``names`` (every engine setting when None), as
    :func:`~kbs.inference._validation.validate_params` takes them."""
    chosen = ENGINE_SETTINGS if names is None else tuple(SETTINGS[n] for n in names)
    return {s.name: list(s.allowed) for s in chosen}


def rule_file_settings() -> tuple[Setting, ...]:
    """The settings of a rule file's ``engine:`` section, in its order."""
    return tuple(s for s in ENGINE_SETTINGS if s.in_rule_file)


#: The constraints of ufp_onc's keywords (one object: validate_params remembers settings it
#: found valid per constraints object).
UFP_ONC_CONSTRAINTS: dict[str, list] = constraints([s.name for s in ENGINE_SETTINGS if s.in_ufp_onc])
