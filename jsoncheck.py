"""A fast check of a JSON document against a JSON Schema of the few keywords kbs's document
schemas use (:data:`KEYWORDS`), with the first problem's JSON path and a sentence: what a reader of
a file kbs wrote (a result JSON, its explanation) runs once, where it reads the file, so that a
hand-edited field of the wrong type is an input error at its position, not a crash later.

jsonschema says the same of these keywords (tests/test_explain_schema.py checks it) but is some
15 times slower: a result of a large scan has hundreds of thousands of records. Differences from
JSON Schema: an ``integer`` is a JSON integer (not ``1.0``, not ``true``), a NaN (which
Python's json reads, and strict JSON has not) is outside any ``minimum``/``maximum``, and a node's
``x-expected`` (an annotation, which JSON Schema ignores) gives the words of "expected ...".
"""
from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from typing import Any

#: A JSON path: object keys and array indices from the document's top.
JsonPath = tuple[str | int, ...]


def dotted(path: Sequence[str | int]) -> str:
    """``('explanation', 'label_names', 0)`` as ``explanation.label_names[0]``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


#: The JSON Schema keywords this check knows (:func:`compile_schema` refuses a schema with another).
KEYWORDS = frozenset({"$schema", "title", "type", "const", "minimum", "maximum", "required", "dependentRequired",
                      "minProperties", "maxProperties", "properties", "additionalProperties", "minItems",
                      "maxItems", "items", "allOf", "anyOf", "if", "then", "$ref", "$defs", "x-expected"})

_TYPE_WORDS = {"string": "a string", "number": "a number", "integer": "an integer", "boolean": "true or false",
               "array": "a list", "object": "an object", "null": "null"}


#: The Python types json.loads gives for each JSON Schema type (an integer: int, never bool).
_PY_TYPES: dict[str, tuple[type, ...]] = {"string": (str,), "integer": (int,), "number": (int, float),
                                          "boolean": (bool,), "array": (list,), "object": (dict,),
                                          "null": (type(None),)}


def _is(value: Any, kind: str) -> bool:
    """JSON Schema's types, except that an integer is a JSON integer (not 1.0, not true)."""
    if kind == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind == "string":
        return isinstance(value, str)
    if kind == "boolean":
        return isinstance(value, bool)
    if kind == "array":
        return isinstance(value, list)
    if kind == "object":
        return isinstance(value, dict)
    return value is None  # "null"


def describe(value: Any) -> str:
    """A JSON value in a few words: 'null', '5', '"x"', 'a list', 'an object'."""
    if isinstance(value, list):
        return "an empty list" if not value else "a list"
    if isinstance(value, dict):
        return "an empty object" if not value else "an object"
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _expected(sch: Mapping[str, Any], value: Any) -> str:
    words = sch.get("x-expected")
    if words is None:
        t = sch.get("type", ())
        words = " or ".join(_TYPE_WORDS[k] for k in ([t] if isinstance(t, str) else t)) or "another value"
    return f"expected {words}, got {describe(value)}"


#: A compiled schema node: value -> None, or (the path to the problem, innermost first; the problem).
Check = Callable[[Any], "tuple[list[str | int], str] | None"]


def _compile(sch: Mapping[str, Any], defs: dict[str, Check]) -> Check:
    """``sch`` (a schema node; ``defs``: its schema's definitions, compiled) as a function that
    checks a value against it."""
    ref = sch.get("$ref")
    if ref is not None:
        name = ref.removeprefix("#/$defs/")
        return lambda v: defs[name](v)  # compiled later: the definitions may refer to themselves
    steps: list[Check] = []
    t = sch.get("type")
    if t is not None:
        kinds = [t] if isinstance(t, str) else list(t)
        exact = frozenset(c for k in kinds for c in _PY_TYPES[k])  # what json.loads gives: a set lookup
        steps.append(lambda v: None if type(v) in exact or any(_is(v, k) for k in kinds) else ([], _expected(sch, v)))
    if "const" in sch:
        const = sch["const"]
        steps.append(lambda v: None if v == const else ([], f"expected {json.dumps(const)}, got {describe(v)}"))
    if "minimum" in sch:
        low = sch["minimum"]
        steps.append(lambda v: ([], f"expected {low:g} or more, got {describe(v)}")
                     if _is(v, "number") and not v >= low else None)  # NaN too
    if "maximum" in sch:
        high = sch["maximum"]
        steps.append(lambda v: ([], f"expected {high:g} or less, got {describe(v)}")
                     if _is(v, "number") and not v <= high else None)
    required = tuple(sch.get("required", ()))
    depends = dict(sch.get("dependentRequired", {}))
    n_props = (sch.get("minProperties", 0), sch.get("maxProperties", float("inf")))
    props = {k: _compile(x, defs) for k, x in sch.get("properties", {}).items()}
    more = sch.get("additionalProperties", True)
    more_check = None if isinstance(more, bool) else _compile(more, defs)
    if required or depends or n_props != (0, float("inf")) or props or more is not True:
        def obj(v: Any) -> tuple[list[str | int], str] | None:
            if not isinstance(v, dict):
                return None
            for key in required:
                if key not in v:
                    return [], f"missing key {key!r}"
            for key, needs in depends.items():
                missing = [k for k in needs if k not in v]
                if key in v and missing:
                    return [], f"missing key {missing[0]!r} (which {key!r} needs)"
            if not n_props[0] <= len(v) <= n_props[1]:
                return [], _expected(sch, v)
            for key, item in v.items():
                check = props.get(key)
                if check is None:
                    if more is False:
                        return [key], f"unexpected key {key!r}"
                    check = more_check
                err = None if check is None else check(item)
                if err is not None:
                    err[0].append(key)
                    return err
            return None
        steps.append(obj)
    n_items = (sch.get("minItems", 0), sch.get("maxItems", float("inf")))
    items = None if "items" not in sch else _compile(sch["items"], defs)
    if items is not None or n_items != (0, float("inf")):
        def arr(v: Any) -> tuple[list[str | int], str] | None:
            if not isinstance(v, list):
                return None
            if not n_items[0] <= len(v) <= n_items[1]:
                return [], _expected(sch, v)
            if items is not None:
                for i, item in enumerate(v):
                    err = items(item)
                    if err is not None:
                        err[0].append(i)
                        return err
            return None
        steps.append(arr)
    steps += [_compile(sub, defs) for sub in sch.get("allOf", ())]
    if "anyOf" in sch:
        options = [_compile(sub, defs) for sub in sch["anyOf"]]
        steps.append(lambda v: None if any(o(v) is None for o in options) else ([], _expected(sch, v)))
    if "if" in sch and "then" in sch:
        cond, then = _compile(sch["if"], defs), _compile(sch["then"], defs)
        steps.append(lambda v: then(v) if cond(v) is None else None)
    if len(steps) == 1:
        return steps[0]

    def node(v: Any) -> tuple[list[str | int], str] | None:
        for step in steps:
            err = step(v)
            if err is not None:
                return err
        return None
    return node


def compile_schema(schema: Mapping[str, Any]) -> Callable[[Any], tuple[JsonPath, str] | None]:
    """A check of documents against ``schema`` (its ``$ref`` are to its own ``$defs``): the check
    gives the first place (in the document's order) where a document does not follow the schema,
    and what is wrong there (``(path, problem)``); None when it follows it.

    Raises
    ------
    ValueError
        The schema uses a keyword this check does not know (it would be ignored silently).
    """
    unknown = set(_keywords(schema)) - KEYWORDS
    if unknown:
        raise ValueError(f"keywords this check does not know: {sorted(unknown)}")
    defs: dict[str, Check] = {}
    defs.update({name: _compile(sub, defs) for name, sub in schema.get("$defs", {}).items()})
    top = _compile(schema, defs)

    def check(value: Any) -> tuple[JsonPath, str] | None:
        err = top(value)
        return None if err is None else (tuple(reversed(err[0])), err[1])
    return check


def _keywords(node: Any) -> list[str]:
    """The keywords of a schema node and of every node below it."""
    if not isinstance(node, Mapping):
        return []
    out = list(node)
    for key, value in node.items():
        if key in ("properties", "$defs"):
            for sub in value.values():
                out += _keywords(sub)
        elif key in ("items", "additionalProperties", "if", "then"):
            out += _keywords(value)
        elif key in ("allOf", "anyOf"):
            for sub in value:
                out += _keywords(sub)
    return out


