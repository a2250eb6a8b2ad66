"""The knowledge module: rule bases, predicates, the interpreter and explanations.

Application knowledge lives in YAML rule files (``kbs/rules``), separate from the inference
motor; predicates measure, rules decide, and every decision is recorded.
"""
from __future__ import annotations

from kbs.knowledge.explain import APDCurve, CheckRecord, ClusterRecord, Explanation
from kbs.knowledge.interpreter import Interpreter, Segmentation
from kbs.knowledge.parts import Action, PostStep
from kbs.knowledge.predicates import (
    Cluster,
    Ground,
    Measurement,
    Predicate,
    PredicateError,
    PredicateRegistry,
    Scene,
    predicate,
)
from kbs.knowledge.rulebase import RuleBase, RuleFileError, load_rule_base, shipped_rule_bases
from kbs.knowledge.segmenter import Segmenter, segment

__all__ = [
    "APDCurve", "CheckRecord", "ClusterRecord", "Explanation", "Interpreter", "Segmentation", "segment",
    "Cluster", "Ground", "Measurement", "Predicate", "PredicateError", "PredicateRegistry", "Scene", "predicate",
    "RuleBase", "RuleFileError", "load_rule_base", "shipped_rule_bases", "Segmenter", "PostStep", "Action",
]
