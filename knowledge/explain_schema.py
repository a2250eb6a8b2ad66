"""The check of an explanation read from a file (the ``explanation`` of a result JSON, format
``kbs-explanation``), before any of it is used: :func:`check_explanation`.

A result JSON may have been edited by hand, truncated or written by another program: every field
the readers use (``kbs explain``, ``kbs render``, the report) is checked once, where the file is
read (:meth:`kbs.knowledge.explain.Explanation.from_result`), so that a bad one is an input error
at its position (``file:line:col``, and its JSON path, e.g. ``explanation.label_names[0]:
expected a string, got null``) instead of a crash, a hang or a wrong text later.

Two parts:

- :data:`SCHEMA`, a JSON Schema (draft 2020-12) of the fields the readers use, with their types
  (an integer is a JSON integer: ``1.0`` and ``true`` are not counts). Keys it does not name are
  allowed: a newer minor version of the format may add keys, which readers ignore. A schema node's
  ``x-expected`` says, in words, what its value must be (the error message's "expected ...").
- The tree (:func:`_tree_problem`), which a schema cannot say: cluster ids unique, the root one of
  them, every child id a cluster listed once, under one parent, whose ``parent`` and ``depth``
  agree (the root at depth 0 without a parent), every cluster under the root. A cycle (a cluster
  its own descendant) or a dangling id is refused here: the readers walk the tree without
  guarding against either.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import cache
from typing import Any

from kbs.jsoncheck import JsonPath, compile_schema, describe, dotted

Path = JsonPath


class ExplanationError(ValueError):
    """A field of an explanation that readers cannot use: ``path`` (keys and indices from the
    explanation's top) and what is wrong (``problem``)."""

    def __init__(self, path: Path, problem: str) -> None:
        self.path = tuple(path)
        self.problem = problem
        super().__init__(f"{dotted(('explanation', *path))}: {problem}")


_STR = {"type": "string"}
_STR_OR_NULL = {"type": ["string", "null"]}
_NUM_OR_NULL = {"type": ["number", "null"]}  # a non-finite number is written as null
_COUNT = {"type": "integer", "minimum": 0}
_COUNT_OR_NULL = {"type": ["integer", "null"], "minimum": 0}
_STRS = {"type": "array", "items": _STR}
_VEC3 = {"type": "array", "items": _NUM_OR_NULL, "minItems": 3, "maxItems": 3, "x-expected": "3 numbers"}
#: A direction printed digit by digit (the ground normal): 3 numbers, none of them null.
_DIRECTION = {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3, "maxItems": 3,
              "x-expected": "3 numbers"}

_A_CONDITION = 'a condition (a check name, "not NAME", {"all": [...]} or {"any": [...]})'
#: A rule's, label's or relabel rule's condition: a check name, 'not NAME', {"all": [...]}, {"any": [...]}.
_CONDITION: dict[str, Any] = {
    "x-expected": _A_CONDITION,
    "anyOf": [
        {"type": "string"},
        {"type": "object", "minProperties": 1, "maxProperties": 1,
         "properties": {"all": {"$ref": "#/$defs/conditions"}, "any": {"$ref": "#/$defs/conditions"}},
         "additionalProperties": False},
    ],
}

#: A check measured on a cluster (CheckRecord): its value within or beyond a bound, min or max.
_CHECK = {
    "type": "object",
    "required": ["check", "predicate", "value", "unit", "min", "max", "passed", "source"],
    "properties": {"check": _STR, "predicate": _STR, "value": _NUM_OR_NULL, "unit": _STR, "min": _NUM_OR_NULL,
                   "max": _NUM_OR_NULL, "passed": {"type": "boolean"}, "source": _STR, "note": _STR},
    # a measured value is compared with a bound: one of them is a number
    "if": {"properties": {"value": {"type": "number"}}, "required": ["value"]},
    "then": {"anyOf": [{"properties": {"min": {"type": "number"}}}, {"properties": {"max": {"type": "number"}}}],
             "x-expected": "a check with a bound (min or max a number)"},
}

_GROUND_CANDIDATE = {
    "type": "object",
    "required": ["cluster", "points"],
    "properties": {"cluster": _STR, "points": _COUNT, "thickness": _NUM_OR_NULL, "why": _STR_OR_NULL,
                   "inliers": _COUNT_OR_NULL, "inlier_share": _NUM_OR_NULL, "plane_thickness": _NUM_OR_NULL,
                   "method": _STR_OR_NULL, "angle_to_fallback": _NUM_OR_NULL, "distance": _NUM_OR_NULL,
                   "supported": _COUNT_OR_NULL, "plane": _COUNT_OR_NULL},
}

_LOCAL_MODEL = {
    "type": ["object", "null"],
    "properties": {"label": _STR_OR_NULL, "points": _COUNT_OR_NULL, "neighbours": _COUNT_OR_NULL,
                   "radius": _NUM_OR_NULL, "per_range": _NUM_OR_NULL, "quantile": _NUM_OR_NULL, "source": _STR_OR_NULL, "note": _STR_OR_NULL,
                   "relabelled": _COUNT_OR_NULL, "points_after_relabel": _COUNT_OR_NULL,
                   "released": _COUNT_OR_NULL, "release_note": _STR_OR_NULL, "undone": _COUNT_OR_NULL,
                   "undo_passes": _COUNT_OR_NULL},
}

#: The ground section (GroundFacts): every key optional; a tiled run's per-tile facts under 'tiles'.
_GROUND = {
    "type": ["object", "null"],
    "properties": {
        "source": _STR_OR_NULL, "cluster": _STR_OR_NULL, "normal": _DIRECTION,
        "point": {**_VEC3, "type": ["array", "null"]}, "distance_to_sensor": _NUM_OR_NULL, "thickness": _NUM_OR_NULL,
        "distance": _NUM_OR_NULL, "unit": _STR_OR_NULL, "method": _STR_OR_NULL, "supported": _COUNT_OR_NULL,
        "candidates": {"type": ["array", "null"], "items": _GROUND_CANDIDATE},
        "support_band": {"type": ["array", "null"], "items": _NUM_OR_NULL, "minItems": 2, "maxItems": 2,
                         "x-expected": "2 numbers"},
        "angle_to_fallback": _NUM_OR_NULL, "inliers": _COUNT_OR_NULL, "inlier_share": _NUM_OR_NULL,
        "plane": _COUNT_OR_NULL, "share_of": _STR_OR_NULL, "note": _STR_OR_NULL, "scope": _STR_OR_NULL,
        "tiles": {"type": ["object", "null"], "additionalProperties": {"$ref": "#/$defs/ground"}},
        "local_model": _LOCAL_MODEL,
    },
    # a plane found as a cluster's robust plane is said with its inliers
    "if": {"properties": {"method": {"const": "robust plane"}}, "required": ["method"]},
    "then": {"required": ["inliers", "inlier_share"],
             "properties": {"inliers": _COUNT, "inlier_share": {"type": "number"}}},
}

#: A pass of a relabel rule that undoes another, on a cluster it did not give back.
_JUDGED = {
    "type": "object",
    "required": ["rule", "source", "pass"],
    "properties": {"rule": _STR, "source": _STR, "pass": _COUNT, "holds": {"type": "boolean"},
                   "surface_points": _COUNT, "measured": {"type": "array", "items": _CHECK}},
}

#: What a post.relabel rule did to a cluster (its 'undid': the relabelling it undid, the same form).
_RELABEL = {
    "type": ["object", "null"],
    "if": {"type": "object", "minProperties": 1},  # {} and null: not relabelled
    "then": {"required": ["rule", "source", "from", "to", "checks"]},
    "dependentRequired": {"undid": ["pass"]},
    "properties": {"rule": _STR, "source": _STR, "from": _STR, "to": _STR, "checks": _STRS, "pass": _COUNT,
                   "measured": {"type": ["array", "null"], "items": _CHECK}, "surface_points": _COUNT,
                   "undid": {"$ref": "#/$defs/relabel"}, "judged_again": {"type": "array", "items": _JUDGED},
                   # post.merge_coplanar's absorb: the cluster of the label whose plane it lies in
                   "joined": {"type": "object", "required": ["cluster", "angle", "offset"],
                              "properties": {"cluster": _STR, "angle": {"type": "number"}, "offset": {"type": "number"},
                                             "max_angle": {"type": "number"}, "max_offset": {"type": "number"},
                                             "unit": _STR}}},
}

_LIMIT = {
    "type": ["object", "null"],
    "properties": {"kind": _STR, "setting": _STR_OR_NULL},
    "allOf": [
        # a limit that is a setting of the rule file is said with its value
        {"if": {"properties": {"setting": {"type": "string"}}, "required": ["setting"]}, "then": {"required": ["value"]}},
        {"if": {"properties": {"kind": {"const": "min_points"}}, "required": ["kind"]},
         "then": {"required": ["setting", "value"], "properties": {"setting": _STR}}},
    ],
}

#: One cluster's record (ClusterRecord).
_RECORD = {
    "type": "object",
    "required": ["id", "parent", "depth", "n_points"],
    "properties": {
        "id": _STR, "parent": _STR_OR_NULL, "depth": _COUNT, "n_points": _COUNT,
        "descriptors": {"type": "object"}, "checks": {"type": "array", "items": _CHECK}, "action": _STR,
        "rule": _STR_OR_NULL, "rule_source": _STR_OR_NULL, "children": _STRS, "label": _STR_OR_NULL,
        "apd": {"type": ["object", "null"], "required": ["ks", "apd", "chosen"],
                "properties": {"ks": {"type": "array", "items": {"type": "integer"}},
                               "apd": {"type": "array", "items": _NUM_OR_NULL}, "chosen": {"type": "integer"}}},
        "notes": _STRS, "output_index": _COUNT_OR_NULL, "decisive": _STRS, "relabel": {"$ref": "#/$defs/relabel"},
        "contact": _COUNT, "released": _COUNT, "limit": _LIMIT,
    },
}

_CHECK_INFO = {
    "type": "object",
    "required": ["name", "predicate", "unit", "min", "max", "doc", "source"],
    "properties": {"name": _STR, "predicate": _STR, "unit": _STR, "min": _NUM_OR_NULL, "max": _NUM_OR_NULL,
                   "doc": _STR, "source": _STR},
}

_RULE_INFO = {
    "type": "object",
    "required": ["name", "condition", "doc", "source"],
    "properties": {"name": _STR, "condition": {"anyOf": [{"type": "null"}, {"$ref": "#/$defs/condition"}],
                                               "x-expected": _A_CONDITION + " or null"},
                   "doc": _STR, "source": _STR, "action": _STR},
}

#: A cluster of one K-partition of the global strategy's sweep.
_STEP_CLUSTER = {
    "type": "object",
    "required": ["id", "points", "center", "eigenvalues", "eigenvectors", "action"],
    "properties": {
        "id": _STR, "points": _COUNT, "center": _VEC3, "eigenvalues": _VEC3,
        "eigenvectors": {"type": "array", "items": _VEC3, "minItems": 3, "maxItems": 3, "x-expected": "3 x 3 numbers"},
        "action": _STR, "rule": _STR_OR_NULL, "rule_source": _STR_OR_NULL,
        "decisive": {"type": "array", "items": _CHECK},
        "limit": _LIMIT,
    },
}

_STEP = {
    "type": "object",
    "required": ["k", "clusters"],
    "properties": {"k": {"type": "integer"}, "apd": _NUM_OR_NULL, "seeded_in": _STR_OR_NULL, "next": _STR_OR_NULL,
                   "kept": {"type": ["boolean", "null"]}, "clusters": {"type": "array", "items": _STEP_CLUSTER}},
}

#: The explanation's dictionary form (Explanation.to_dict), as far as its readers use it.
SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "kbs-explanation",
    "type": "object",
    "required": ["rule_base", "rule_file", "strategy", "label_names", "root", "clusters"],
    "properties": {
        "rule_base": _STR, "rule_file": _STR, "strategy": _STR, "label_names": _STRS, "root": _STR,
        "ground": {"$ref": "#/$defs/ground"}, "notes": _STRS,
        "catalogue": {
            "type": ["object", "null"],
            "properties": {"checks": {"type": "array", "items": _CHECK_INFO},
                           "rules": {"type": "array", "items": _RULE_INFO},
                           "labels": {"type": "array", "items": _RULE_INFO},
                           "relabel": {"type": "array", "items": _RULE_INFO}},
        },
        "clusters": {"type": "array", "items": _RECORD, "minItems": 1, "x-expected": "a list of cluster records"},
        "sweep": {"type": "array", "items": _STEP},
    },
    "$defs": {
        "condition": _CONDITION,
        "conditions": {"type": "array", "items": {"$ref": "#/$defs/condition"}},
        "ground": _GROUND,
        "relabel": _RELABEL,
    },
}


@cache
def _schema_check() -> Callable[[Any], tuple[Path, str] | None]:
    return compile_schema(SCHEMA)


def check_explanation(d: Any) -> None:
    """Refuse an explanation (its dictionary form, read from a file) that readers cannot use.

    Raises
    ------
    ExplanationError
        The first field that is wrong (its path and the problem), or the tree's first problem.
    """
    problem = _schema_check()(d) or _tree_problem(d["clusters"], d["root"])
    if problem is not None:
        raise ExplanationError(*problem)


def _tree_problem(records: Sequence[Mapping[str, Any]], root: str) -> tuple[Path, str] | None:
    """The first problem of the cluster tree (the records schema-checked), or None."""
    at: dict[str, int] = {}
    for i, r in enumerate(records):
        if r["id"] in at:
            return ("clusters", i, "id"), f"cluster id {r['id']!r} is also that of clusters[{at[r['id']]}]"
        at[r["id"]] = i
    if root not in at:
        return ("root",), f"no cluster has the root's id {root!r}"
    top = records[at[root]]
    if top["parent"] is not None:
        return ("clusters", at[root], "parent"), f"the root {root!r} has a parent ({top['parent']!r}), expected null"
    if top["depth"] != 0:
        return ("clusters", at[root], "depth"), f"the root {root!r} is at depth {top['depth']}, expected 0"
    parent_of: dict[str, str] = {root: ""}
    stack = [root]
    while stack:
        pid = stack.pop()
        i = at[pid]
        rec = records[i]
        for j, cid in enumerate(rec.get("children", ())):
            where = ("clusters", i, "children", j)
            if cid not in at:
                return where, f"no cluster has the id {cid!r} (a child of {pid!r})"
            if cid in parent_of:
                if cid == pid:
                    return where, f"cluster {cid!r} is listed as its own child (a cycle)"
                if _ancestor(cid, pid, parent_of):
                    return where, f"cluster {cid!r} is listed as a child of its descendant {pid!r} (a cycle)"
                return where, f"cluster {cid!r} is listed again (already a child of {parent_of[cid]!r})"
            child = records[at[cid]]
            if child["parent"] != pid:
                return ("clusters", at[cid], "parent"), (f"cluster {cid!r} is a child of {pid!r} but its parent is "
                                                         f"{describe(child['parent'])}")
            if child["depth"] != rec["depth"] + 1:
                return ("clusters", at[cid], "depth"), (f"cluster {cid!r} is at depth {child['depth']}, its parent "
                                                        f"{pid!r} at {rec['depth']}: expected {rec['depth'] + 1}")
            parent_of[cid] = pid
            stack.append(cid)
    for i, r in enumerate(records):
        if r["id"] not in parent_of:
            return ("clusters", i, "id"), f"cluster {r['id']!r} is not in the tree under the root {root!r}"
    return None


def _ancestor(cid: str, of: str, parent_of: Mapping[str, str]) -> bool:
    """Whether ``cid`` is ``of`` or one of its ancestors (``parent_of``: the tree walked so far)."""
    cur = of
    while cur:
        if cur == cid:
            return True
        cur = parent_of.get(cur, "")
    return False
