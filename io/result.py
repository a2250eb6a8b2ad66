"""The result files kbs writes, read back and told apart from other files.

``kbs run`` writes one result as a pair, ``<stem>.ply`` (the points with per-vertex
``scalar_cluster``, ``scalar_label``, ``scalar_membership``) or ``<stem>.las``/``.laz``
(:mod:`kbs.io.las`), and ``<stem>.json`` (label names, clusters, explanation tree; its key
``points`` names the cloud file); ``kbs cluster --out`` writes a single PLY. This module owns that
format:

- **Field names.** The PLY properties of the result fields are ``scalar_cluster``,
  ``scalar_label``, ``scalar_membership`` (:data:`PLY_NAMES`): CloudCompare's PLY filter loads a
  vertex property as a scalar field when its name contains "scal" (and strips a ``scalar_``
  prefix), and leaves any other unassigned. kbs's readers (:func:`read_result_cloud`) read them,
  and the plain ``cluster``, ``label``, ``membership`` of results written before, under the plain names;
  a cloud without the fields a command needs is refused in one way (:func:`require_fields`), by
  ``kbs render``, ``kbs eval``, ``kbs segcomp`` and the report alike. No module outside ``kbs.io``
  spells these names or parses a result JSON itself (tests/test_result_owner.py).

- **Writing.** :func:`write_result_pair` writes both files to temporary files beside them and
  moves them into place together (:func:`kbs.io.atomic.replacing`): if anything fails (a full
  disk, Ctrl-C) the temporary files are removed and the previous pair stays as it was.
- **Run id.** Every result carries a run id (a uuid4 hex), the same in both files of a pair: the
  PLY header comment ``kbs_run_id <hex>`` (in a LAS/LAZ result, a VLR of user id ``kbs``) and the
  JSON key ``run_id``. :func:`check_pair`, which
  every reader of a pair goes through (:func:`read_result_pair`, ``kbs render``, ``kbs eval``),
  refuses a PLY and a JSON whose ids differ: left by a run interrupted between its two renames,
  or mixed by hand. The id is also how kbs knows a file is its own (:func:`is_kbs_output`).
- **Strict JSON.** The JSON is strict (RFC 8259): a non-finite number (NaN, +-Infinity, e.g. an
  infinite measurement of a plugin predicate) is written as ``null``.
- **Format version.** The JSON's first keys ``"format": "kbs-result"`` and ``"version":
  "MAJOR.MINOR"`` (:data:`RESULT_FORMAT`, :data:`RESULT_VERSION`; :mod:`kbs.formats`): a reader
  reads every minor version of its major one and refuses a newer major version, saying to upgrade
  kbs, at the position of its version in the file (``file:line:col``).
- **Reading.** :func:`read_result` gives a frozen :class:`ResultDoc`: the format version and the
  fields readers use (run id, input, rule base, label names, clusters, summary, the explanation's
  dictionary form) as attributes, each checked for its type (a wrong one is an error at its
  position); the output clusters' fields the readers use are checked against
  :data:`CLUSTERS_SCHEMA`, and the explanation, when a reader turns it into records, against
  its own (:mod:`kbs.knowledge.explain_schema`): a hand-edited field of the wrong type is an
  input error naming its position and JSON path (``clusters[0].index: expected an integer, got
  null``). ``kbs explain``, ``kbs eval``, ``kbs render``, the report and ``kbs run``'s read-back
  of a streamed result read it; none of them indexes the JSON's keys. Results written before read as version 1.0: those with the integer
  ``result_format`` key of kbs 0.1 (its value is the major version), and those without any
  (kbs before run ids), which have no run id to check either. Version 1.1 added the
  explanation's own ``format``/``version`` and its catalogue of the rule base's checks, rules and
  labels with their docs (:class:`kbs.knowledge.explain.Catalogue`).
"""
from __future__ import annotations

import dataclasses
import errno
import json
import math
import os
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import CloudFileError
from kbs.formats import FormatVersionError, NewerVersionError, Version, document_version
from kbs.io.atomic import replacing
from kbs.io.cloud import PointCloud
from kbs.io.ply import build_ply, write_built_ply
from kbs.io.readers import read_cloud
from kbs.jsoncheck import JsonPath, compile_schema, dotted

#: The ``format`` of a result JSON, and the version this kbs writes (it reads every 1.x).
RESULT_FORMAT = "kbs-result"
RESULT_VERSION = Version(1, 1)
#: The key that held the major version before ``format``/``version`` (kbs 0.1 wrote 1).
LEGACY_VERSION_KEY = "result_format"
#: The PLY header comment word before a result's run id (``comment kbs_run_id <hex>``); also the
#: marker kbs appends to its HTML report.
RUN_ID_COMMENT = "kbs_run_id"
#: The first bytes of a rule file written by ``kbs tune`` (the header of evaluation.tune.tuned_text).
TUNED_MARK = b"# kbs tune:"
#: Bytes of a PLY header read at most when looking for the run id.
_MAX_HEADER = 1 << 20
#: The per-point fields of a result, and their PLY property names (see the module's docstring).
RESULT_FIELDS = ("cluster", "label", "membership")
PLY_NAMES = {name: f"scalar_{name}" for name in RESULT_FIELDS}
#: The formats a result's points can be written in.
CLOUD_FORMATS = ("ply", "las", "laz")


def new_run_id() -> str:
    """A fresh run id: 32 lowercase hex digits (uuid4)."""
    return uuid.uuid4().hex


# -- writing -----------------------------------------------------------------------------------


def jsonable(o: Any) -> Any:
    """``json.dumps`` ``default``: numpy scalars and arrays as Python numbers and lists."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _finite_or_none(o: Any) -> Any:
    """A copy of ``o`` with every non-finite float (NaN, +-inf) replaced by None."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, Mapping):
        return {k: _finite_or_none(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_none(v) for v in o]
    if isinstance(o, (np.generic, np.ndarray)):
        return _finite_or_none(jsonable(o))
    return o


def strict_json(doc: Any) -> str:
    """``doc`` as compact strict JSON: no NaN/Infinity tokens (non-finite numbers become null)."""
    try:
        return json.dumps(doc, separators=(",", ":"), default=jsonable, allow_nan=False)
    except ValueError:  # a NaN or an infinity somewhere (rare): the walk that replaces them
        return json.dumps(_finite_or_none(doc), separators=(",", ":"), default=jsonable, allow_nan=False)


def _write_json_bytes(stream: Any, data: bytes | Iterable[bytes]) -> None:
    if isinstance(data, bytes):
        stream.write(data)
        return
    for part in data:
        stream.write(part)


def _json_pieces(doc: Mapping[str, Any], run_id: str, points: str | None,
                 pieces: Mapping[str, Callable[[], Iterable[str]]]) -> Iterator[bytes]:
    """:func:`_json_bytes`, the values of ``pieces``' keys written from their pieces of text."""
    marks = {key: f"\x00kbs piece {key}\x00" for key in pieces}
    text = _json_bytes({**doc, **marks}, run_id, points).decode("utf-8")
    cuts = sorted((text.index(json.dumps(mark)), key) for key, mark in marks.items())
    at = 0
    for where, key in cuts:
        yield text[at:where].encode("utf-8")
        for part in pieces[key]():
            yield part.encode("utf-8")
        at = where + len(json.dumps(marks[key]))
    yield text[at:].encode("utf-8")


def _write_json_file(path: Path, data: bytes | Iterable[bytes], target: Path) -> None:
    try:
        with open(path, "wb") as stream:
            _write_json_bytes(stream, data)
    except OSError as exc:
        raise CloudFileError(str(target), f"cannot write: {exc.strerror or exc}") from exc


def result_comments(run_id: str) -> list[str]:
    """The PLY header comments of a result: who wrote it and its run id."""
    from kbs import __version__

    return [f"written by kbs {__version__}", f"{RUN_ID_COMMENT} {run_id}"]


def write_result_pair(points: str | os.PathLike[str], js: str | os.PathLike[str], xyz: np.ndarray,
                      fields: Mapping[str, np.ndarray], doc: Mapping[str, Any], *,
                      run_id: str | None = None, las: Callable[[str], Any] | None = None,
                      comments: Iterable[str] = (),
                      pieces: Mapping[str, Callable[[], Iterable[str]]] | None = None) -> str:
    """Write one result, the points file and ``js``, as a whole: both or neither.

    Parameters
    ----------
    points, js : path
        The points file (PLY, or LAS/LAZ with ``las``) and the JSON to create or replace.
    xyz : ndarray, shape (n_points, 3)
    fields : mapping of str to ndarray, each (n_points,)
        The per-vertex properties of a PLY (see :func:`kbs.io.write_ply`).
    doc : mapping
        The JSON document; ``format``, ``version`` (:data:`RESULT_FORMAT`, :data:`RESULT_VERSION`),
        ``run_id`` and ``points`` (the points file's name) are added after ``kbs_version``.
    run_id : str, optional
        Default: a fresh one (:func:`new_run_id`).
    las : callable, optional
        ``run_id -> laspy.LasData``: write the points as LAS (LAZ when ``points`` ends with .laz)
        instead of PLY (:func:`kbs.io.las.build_las`).
    comments : iterable of str
        More PLY header comments (``units mm``, ``crs ...``), after the run id.
    pieces : mapping of str to callable, optional
        Keys of ``doc`` whose value is written from ``pieces[key]()``: pieces of JSON text (a
        tiled result's clusters and explanation, never whole in memory); ``doc[key]`` is ignored.

    Returns
    -------
    str
        The run id written in both files.

    Raises
    ------
    ParameterError
        Bad points or fields (nothing is written).
    CloudFileError
        A file cannot be written; the files that were there before are left as they were.
    """
    points, js = Path(os.fspath(points)), Path(os.fspath(js))
    run_id = run_id or new_run_id()
    built = build_ply(xyz, fields, comments=[*result_comments(run_id), *comments]) if las is None else las(run_id)
    data = _json_bytes(doc, run_id, points.name) if not pieces else _json_pieces(doc, run_id, points.name, pieces)
    try:
        with replacing(points, js) as (tmp_points, tmp_js):
            if las is None:
                write_built_ply(built, tmp_points, target=points)
            else:
                from kbs.io.las import write_las

                write_las(tmp_points, built, target=points)
            _write_json_file(tmp_js, data, js)
    except OSError as exc:  # creating a temporary file beside the target
        raise CloudFileError(str(exc.filename or points), f"cannot write: {exc.strerror or exc}") from exc
    return run_id


def _json_bytes(doc: Mapping[str, Any], run_id: str, points: str | None) -> bytes:
    head = {k: doc[k] for k in ("kbs_version",) if k in doc}
    where = {} if points is None else {"points": points}
    version = {"format": RESULT_FORMAT, "version": str(RESULT_VERSION)}
    return strict_json({**version, **head, "run_id": run_id, **where, **doc}).encode("utf-8")


def write_result_stream(stream: Any, suffix: str, xyz: np.ndarray, fields: Mapping[str, np.ndarray], *,
                        run_id: str | None = None, las: Callable[[str], Any] | None = None,
                        comments: Iterable[str] = ()) -> str:
    """Write a result's points alone to a binary ``stream`` (``kbs run --out -``): built whole in
    a temporary file first, so that nothing reaches the stream unless all of it can.

    ``suffix`` is ``.ply``, ``.las`` or ``.laz``; returns the run id."""
    import shutil
    import tempfile

    run_id = run_id or new_run_id()
    built = build_ply(xyz, fields, comments=[*result_comments(run_id), *comments]) if las is None else las(run_id)
    with tempfile.TemporaryDirectory(prefix="kbs-") as folder:
        tmp = Path(folder) / f"result{suffix}"
        if las is None:
            write_built_ply(built, tmp, target="<stdout>")
        else:
            from kbs.io.las import write_las

            write_las(tmp, built, target="<stdout>")
        with open(tmp, "rb") as source:
            shutil.copyfileobj(source, stream, 1 << 20)
    stream.flush()
    return run_id


def write_result_cloud(path: str | os.PathLike[str], xyz: np.ndarray, fields: Mapping[str, np.ndarray], *,
                       run_id: str | None = None) -> str:
    """Write a result PLY alone (``kbs cluster --out``), whole or not at all, with a run id
    (returned) that marks it as kbs's own."""
    path = Path(os.fspath(path))
    run_id = run_id or new_run_id()
    built = build_ply(xyz, fields, comments=result_comments(run_id))
    try:
        with replacing(path) as (tmp,):
            write_built_ply(built, tmp, target=path)
    except OSError as exc:
        raise CloudFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc
    return run_id


# -- reading -----------------------------------------------------------------------------------


def _os_problem(exc: OSError, what: str) -> str:
    if isinstance(exc, FileNotFoundError):
        return "no such file"
    if exc.errno == errno.ELOOP:
        return "symbolic link loop (the link points, directly or not, to itself)"
    if isinstance(exc, IsADirectoryError):
        return f"is a directory, not {what}"
    return f"cannot read: {exc.strerror or exc}"


def ply_comments(path: str | os.PathLike[str]) -> list[str]:
    """The ``comment`` and ``obj_info`` lines of a PLY header (without the keyword); [] when the
    file is not a PLY file or its header cannot be read."""
    try:
        with open(path, "rb") as stream:
            head = stream.read(4)
            if head[:3] != b"ply":
                return []
            chunks = [head]
            while sum(map(len, chunks)) < _MAX_HEADER:
                chunk = stream.read(65536)
                if not chunk:
                    break
                chunks.append(chunk)
                if b"end_header" in b"".join(chunks[-2:]):  # also when split between two reads
                    break
    except OSError:
        return []
    header = b"".join(chunks).split(b"end_header", 1)[0].decode("ascii", "replace")
    out = []
    for line in header.splitlines():
        word, _, rest = line.strip().partition(" ")
        if word in ("comment", "obj_info"):
            out.append(rest.strip())
    return out


def ply_run_id(path: str | os.PathLike[str]) -> str | None:
    """The run id in a PLY header (``comment kbs_run_id <hex>``), None if there is none."""
    for comment in ply_comments(path):
        word, _, value = comment.partition(" ")
        if word == RUN_ID_COMMENT and value.strip():
            return value.strip()
    return None


def cloud_run_id(path: str | os.PathLike[str]) -> str | None:
    """The run id in a result's points file: a PLY header comment or a LAS/LAZ VLR; None if none."""
    try:
        with open(path, "rb") as stream:
            magic = stream.read(4)
    except OSError:
        return None
    if magic == b"LASF":
        from kbs.io.las import las_run_id

        return las_run_id(path)
    return ply_run_id(path)


def read_result_json(path: str | os.PathLike[str], *, require: Iterable[str] = ()) -> dict[str, Any]:
    """The parsed result document, as raw JSON; every way it can be unreadable is a one-line
    CloudFileError (a bad ``format`` or ``version`` names its position, ``file:line:col``).
    Commands read :func:`read_result` (a :class:`ResultDoc`) instead.

    Parameters
    ----------
    path : path of the JSON file.
    require : keys the document must have (e.g. ``("explanation",)``).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(doc, dict):
            raise TypeError(f"a JSON {type(doc).__name__}, not an object")
        # the version first: a newer file may lack a key this kbs requires
        document_version(doc, format=RESULT_FORMAT, reads=RESULT_VERSION, legacy_key=LEGACY_VERSION_KEY)
        for key in require:
            doc[key]  # noqa: B018 -- a KeyError says which key is missing
    except OSError as exc:
        raise CloudFileError(str(path), _os_problem(exc, "a result file")) from exc
    except NewerVersionError as exc:
        raise CloudFileError(json_position(path, _version_key(doc)), str(exc)) from exc
    except FormatVersionError as exc:
        raise CloudFileError(json_position(path, _version_key(doc)), f"not a kbs result file ({exc})") from exc
    except RecursionError as exc:  # arrays or objects nested deeper than the parser's stack
        raise CloudFileError(str(path), "not a kbs result file (its JSON nests deeper than Python's parser "
                                        "can follow)") from exc
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise CloudFileError(str(path), f"not a kbs result file ({type(exc).__name__}: {exc})") from exc
    return doc


def _version_key(doc: Mapping[str, Any]) -> str:
    """The key of a result document that :func:`kbs.formats.document_version` refused."""
    if doc.get("format", RESULT_FORMAT) != RESULT_FORMAT:
        return "format"
    return "version" if "version" in doc or LEGACY_VERSION_KEY not in doc else LEGACY_VERSION_KEY


def json_position(path: str | os.PathLike[str], *keys: str | int) -> str:
    """``'file:line:col'`` (1-based) of the value at ``keys`` (object keys and array indices from
    the top) in the JSON file ``path``; the file's name alone when it cannot be found there (only
    read when a problem is reported)."""
    where = os.fspath(path)
    try:
        text = Path(where).read_text(encoding="utf-8")
        at = _value_at(text, keys)
    except (OSError, UnicodeDecodeError, ValueError, IndexError):
        return where
    if at is None:
        return where
    line = text.count("\n", 0, at) + 1
    return f"{where}:{line}:{at - (text.rfind(chr(10), 0, at) + 1) + 1}"


def _value_at(text: str, keys: Sequence[str | int]) -> int | None:
    """The offset in the JSON ``text`` of the value at ``keys`` (an int: an array's index), None
    when there is none."""
    decoder = json.JSONDecoder()
    ws = " \t\n\r"

    def skip(i: int) -> int:
        while i < len(text) and text[i] in ws:
            i += 1
        return i

    i = skip(0)
    for key in keys:
        if isinstance(key, int):
            if text[i] != "[":
                return None
            i = skip(i + 1)
            for _ in range(key):
                if text[i] == "]":
                    return None
                _, i = decoder.raw_decode(text, i)
                i = skip(i)
                if text[i] != ",":
                    return None
                i = skip(i + 1)
            if text[i] == "]":
                return None
            continue
        if text[i] != "{":
            return None
        i = skip(i + 1)
        while text[i] != "}":
            name, i = decoder.raw_decode(text, i)
            i = skip(i)
            if text[i] != ":":
                return None
            i = skip(i + 1)
            if name == key:
                break
            _, i = decoder.raw_decode(text, i)
            i = skip(i)
            if text[i] == ",":
                i = skip(i + 1)
        else:
            return None
    return i


#: A coordinate or a variance of a cluster's descriptors: within what a cloud's coordinates may be
#: (kbs.knowledge.segmenter.MAX_COORDINATE, 1e50) and its square.
_COORD = {"type": "number", "minimum": -1e50, "maximum": 1e50}
_VEC3 = {"type": "array", "items": _COORD, "minItems": 3, "maxItems": 3, "x-expected": "3 numbers within +-1e50"}

#: The JSON Schema (kbs.jsoncheck's keywords) of a result's output clusters, as far as their readers
#: (kbs render, the report) use them; other keys are allowed (a newer minor version may add some).
CLUSTERS_SCHEMA: dict[str, Any] = {
    "type": "array",
    "items": {
        "type": "object",
        "required": ["index"],
        "properties": {
            "index": {"type": "integer", "minimum": 0}, "n_points": {"type": "integer", "minimum": 0},
            "label": {"type": ["string", "null"]}, "ids": {"type": "array", "items": {"type": "string"}},
            "descriptors": {"type": ["object", "null"], "properties": {
                "center": _VEC3, "normal": {**_VEC3, "type": ["array", "null"]},
                "eigenvalues": {**_VEC3, "items": {"type": "number", "minimum": -1e100, "maximum": 1e100},
                                "x-expected": "3 numbers within +-1e100"}}},
        },
    },
}


@cache
def _clusters_check() -> Callable[[Any], tuple[JsonPath, str] | None]:
    return compile_schema(CLUSTERS_SCHEMA)


@dataclass(frozen=True)
class ResultDoc:
    """A result JSON (format ``kbs-result``) read back: what its readers use, as attributes.

    Every field is None when the file does not have it (a result of an older kbs; ``kbs run
    --tile`` with a streamed output writes the explanation by pieces, but writes it). ``raw`` is
    the whole document, for what has no attribute here.

    Attributes
    ----------
    path : Path
        The JSON file.
    version : Version
        Its format version (files without one read as 1.0).
    run_id, kbs_version, input, points : str or None
        The run id (the same in the points file: :func:`check_pair`), the kbs that wrote it, the
        input cloud's name, the points file's name.
    rule_base, rule_file, units : str or None
    n_points : int or None
    sensor : tuple of 3 floats, or None
    label_names : tuple of str, or None
        Index = the per-point ``label``.
    clusters : tuple of dict, or None
        The output clusters (index, ids, label, n_points, descriptors, ...).
    summary : dict or None
    explanation : dict or None
        The explanation's dictionary form (:meth:`kbs.knowledge.Explanation.from_result` reads it).
    """

    path: Path
    version: Version
    raw: Mapping[str, Any] = field(repr=False)
    run_id: str | None = None
    kbs_version: str | None = None
    input: str | None = None
    points: str | None = None
    rule_base: str | None = None
    rule_file: str | None = None
    units: str | None = None
    n_points: int | None = None
    sensor: tuple[float, ...] | None = None
    label_names: tuple[str, ...] | None = None
    clusters: tuple[dict[str, Any], ...] | None = None
    summary: Mapping[str, Any] | None = None
    explanation: Mapping[str, Any] | None = None

    @classmethod
    def of(cls, doc: Mapping[str, Any], path: str | os.PathLike[str]) -> ResultDoc:
        """The record of a parsed result document (:func:`read_result_json`'s), its fields
        checked: a field of the wrong type is a CloudFileError naming it and its position."""
        path = Path(os.fspath(path))
        version = document_version(doc, format=RESULT_FORMAT, reads=RESULT_VERSION, legacy_key=LEGACY_VERSION_KEY)

        def bad(key: str, what: str) -> CloudFileError:
            return CloudFileError(json_position(path, key), f"not a kbs result file ({key!r} is not {what})")

        def text(key: str) -> str | None:
            v = doc.get(key)
            if v is not None and not isinstance(v, str):
                raise bad(key, "a string")
            return v

        def mapping(key: str) -> Mapping[str, Any] | None:
            v = doc.get(key)
            if v is not None and not isinstance(v, Mapping):
                raise bad(key, "an object")
            return v

        names = doc.get("label_names")
        if names is not None and (not isinstance(names, list) or not all(isinstance(n, str) for n in names)):
            raise bad("label_names", "a list of names")
        if names is not None and len(set(names)) != len(names):
            raise bad("label_names", "a list of distinct names")
        clusters = doc.get("clusters")
        if clusters is not None and (not isinstance(clusters, list) or not all(isinstance(c, dict) for c in clusters)):
            raise bad("clusters", "a list of objects")
        if clusters is not None:
            problem = _clusters_check()(clusters)
            if problem is not None:
                at, what = problem
                raise CloudFileError(json_position(path, "clusters", *at),
                                     f"not a kbs result file ({dotted(('clusters', *at))}: {what})")
        if clusters is not None and names is not None:  # a cluster's label is one of the result's label names
            for i, c in enumerate(clusters):
                label = c.get("label")
                if label is not None and label not in names:
                    raise CloudFileError(json_position(path, "clusters", i, "label"),
                                         f"not a kbs result file ({dotted(('clusters', i, 'label'))}: "
                                         f"{str(label)[:40]!r} is not one of its label_names)")
        sensor = doc.get("sensor")
        if sensor is not None and (not isinstance(sensor, list) or len(sensor) != 3
                                   or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                              and math.isfinite(v) for v in sensor)):
            raise bad("sensor", "3 finite numbers")
        n = doc.get("n_points")
        if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 0):
            raise bad("n_points", "a number of points")
        return cls(path=path, version=version, raw=doc, run_id=text("run_id"), kbs_version=text("kbs_version"),
                   input=text("input"), points=text("points"), rule_base=text("rule_base"),
                   rule_file=text("rule_file"), units=text("units"), n_points=n,
                   sensor=None if sensor is None else tuple(float(v) for v in sensor),
                   label_names=None if names is None else tuple(names),
                   clusters=None if clusters is None else tuple(clusters), summary=mapping("summary"),
                   explanation=mapping("explanation"))

    def position(self, *keys: str | int) -> str:
        """``'file:line:col'`` of the value at ``keys`` (object keys, array indices) in the file (the
        file alone when not found)."""
        return json_position(self.path, *keys)


def read_result(path: str | os.PathLike[str], *, require: Iterable[str] = ()) -> ResultDoc:
    """A result JSON read and checked (:func:`read_result_json`; ``require``: keys it must have),
    as a :class:`ResultDoc`.

    Raises
    ------
    CloudFileError
        Unreadable, not a result, a newer major version (at the position of its version), or a
        field of the wrong type.
    """
    return ResultDoc.of(read_result_json(path, require=require), path)


def check_pair(ply: str | os.PathLike[str], js: str | os.PathLike[str], doc: ResultDoc | Mapping[str, Any]) -> None:
    """Refuse a points file (PLY, LAS, LAZ) and a JSON that are not the two files of one result.

    Parameters
    ----------
    ply, js : path
        The two files (``ply``: the points, whatever their format); ``doc`` is ``js`` read.

    Raises
    ------
    CloudFileError
        Their run ids differ, or one has a run id and the other none. Two files without a run id
        (written by kbs before run ids) pass: there is nothing to compare.
    """
    json_id = doc.run_id if isinstance(doc, ResultDoc) else doc.get("run_id")
    ply_id = cloud_run_id(ply)
    if json_id is None and ply_id is None:
        return
    if json_id != ply_id:
        ply_name = Path(os.fspath(ply)).name
        kind = ply_name.rsplit(".", 1)[-1].upper() if "." in ply_name else "points file"
        raise CloudFileError(
            str(js), f"does not belong with {ply_name}: run id {json_id or 'none'} in the JSON, "
                     f"{ply_id or 'none'} in the {kind} (a run stopped between writing the two, or files of two "
                     f"runs were put together); run kbs run again to write a matching pair")


def points_file(js: Path, doc: ResultDoc) -> Path:
    """The points file of a result JSON: ``<stem>.ply``, or ``.las``/``.laz`` when its ``points``
    key names a file of that format (the stem is the JSON's: a pair renamed together stays a pair)."""
    name = doc.points
    suffix = Path(name).suffix.lower() if isinstance(name, str) else ""
    return js.with_suffix(suffix if suffix in (".ply", ".las", ".laz") else ".ply")


def read_result_cloud(path: str | os.PathLike[str], *, require: Iterable[str] = ()) -> PointCloud:
    """A result's points file (PLY, LAS, LAZ) read with :func:`kbs.io.read_cloud`, its result
    fields under their plain names: ``scalar_cluster`` read as ``cluster`` (and so on for
    :data:`RESULT_FIELDS`) when there is no plain one.

    ``require``: result fields (of :data:`RESULT_FIELDS`) the file must have
    (:func:`require_fields`)."""
    cloud = read_cloud(path)
    renamed = {PLY_NAMES[k]: k for k in RESULT_FIELDS if PLY_NAMES[k] in cloud.fields and k not in cloud.fields}
    if renamed:
        fields = {renamed.get(name, name): values for name, values in cloud.fields.items()}
        cloud = dataclasses.replace(cloud, fields=fields)
    require_fields(cloud, path, require)
    for name in ("cluster", "label"):  # kbs writes integers from -1 (noise, no label) up
        values = cloud.fields.get(name)
        if values is None or not len(values):
            continue
        v = np.asarray(values)
        bad = ~np.isfinite(v) | (v < -1) | (v != np.round(v)) if v.dtype.kind == "f" else v < -1
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CloudFileError(os.fspath(path), f"not a kbs result: its per-vertex {name!r} holds {v[i].item()!r} at "
                                                  f"vertex {i:,} ({int(bad.sum()):,} such): kbs writes integers "
                                                  "from -1 up")
    return cloud


def require_fields(cloud: PointCloud, path: str | os.PathLike[str], names: Iterable[str]) -> None:
    """Refuse a result cloud without the result fields ``names`` (per-vertex ``cluster``,
    ``label``, ``membership``): one CloudFileError naming what is missing."""
    missing = [n for n in names if n not in cloud.fields]
    if missing:
        what = " and ".join(repr(n) for n in missing)
        raise CloudFileError(os.fspath(path), f"not a kbs result: no per-vertex {what} field"
                                              f"{'s' if len(missing) > 1 else ''} (write one with kbs run)")


def read_result_pair(path: str | os.PathLike[str], *, require: Iterable[str] = (),
                     fields: Iterable[str] = ()) -> tuple[ResultDoc, PointCloud]:
    """Read a result: ``RESULT.json`` and its points file (``RESULT.ply``, or the LAS/LAZ file its
    ``points`` key names), checked to be one result. ``require``: keys the JSON must have;
    ``fields``: result fields the points must have.

    Returns
    -------
    (ResultDoc, PointCloud)
        The JSON document and the points with their fields (:func:`read_result_cloud`).

    Raises
    ------
    CloudFileError
        Either file is missing or unreadable, or they are not the same run's (:func:`check_pair`).
    """
    js = Path(os.fspath(path))
    doc = read_result(js, require=require)
    points = points_file(js, doc)
    if not points.is_file():
        raise CloudFileError(str(points), "no such file (the points of the result, written next to its .json)")
    check_pair(points, js, doc)
    cloud = read_result_cloud(points, require=fields)
    if doc.n_points is not None and doc.n_points != len(cloud):
        raise CloudFileError(doc.position("n_points"), f"not a kbs result file: 'n_points' is {doc.n_points:,} and "
                                                       f"{points.name} holds {len(cloud):,} points")
    return doc, cloud


# -- telling kbs's own files from others -----------------------------------------------------------


#: Suffixes of files whose format has no room for a run id (SegComp's 8-bit Sun rasterfiles and
#: normals text, read by its ``compare`` program): kbs cannot tell its own from another's, so an
#: existing one is replaced only with ``--force``.
UNMARKED_SUFFIXES = (".ms-seg", ".ms-nor", ".gt-seg", ".range")
#: The GeoTIFF tag holding the run id of a ``kbs map`` grid (``map.tif``).
GEOTIFF_RUN_ID_TAG = "KBS_RUN_ID"


def png_text(path: str | os.PathLike[str]) -> dict[str, str]:
    """The uncompressed text chunks (``tEXt``, ``iTXt``) of a PNG file, keyword -> text; {} when
    the file is not a PNG. Only the chunk headers are read, the image data is skipped."""
    out: dict[str, str] = {}
    with open(path, "rb") as stream:
        if stream.read(8) != b"\x89PNG\r\n\x1a\n":
            return out
        while True:
            head = stream.read(8)
            if len(head) < 8:
                return out
            length, kind = int.from_bytes(head[:4], "big"), head[4:]
            if kind == b"IEND":
                return out
            if kind in (b"tEXt", b"iTXt") and length <= 65536:
                data = stream.read(length)
                key, _, rest = data.partition(b"\0")
                if kind == b"iTXt":  # compression flag, method, language\0, translated keyword\0, text
                    if rest[:1] != b"\0":
                        stream.seek(4, os.SEEK_CUR)
                        continue
                    rest = rest[2:].split(b"\0", 2)[-1]
                out[key.decode("latin-1")] = rest.decode("latin-1" if kind == b"tEXt" else "utf-8", "replace")
                stream.seek(4, os.SEEK_CUR)  # the CRC
            else:
                stream.seek(length + 4, os.SEEK_CUR)


def png_metadata(run_id: str) -> dict[str, str]:
    """The PNG text chunks of a figure kbs writes (matplotlib's ``savefig(metadata=...)``): who
    wrote it and its run id (:func:`is_kbs_output` reads it)."""
    from kbs import __version__

    return {"Software": f"kbs {__version__}", RUN_ID_COMMENT: run_id}


def _geotiff_run_id(path: Path) -> str | None:
    try:
        import rasterio
    except ImportError:  # kbs writes no GeoTIFF without rasterio
        return None
    try:
        with rasterio.open(path) as src:
            return src.tags().get(GEOTIFF_RUN_ID_TAG)
    except Exception:  # noqa: BLE001 -- any file rasterio cannot read is not kbs's GeoTIFF
        return None


def file_digest(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes (hex): how an index kbs writes (``map.json``, a drive's
    ``truth.json``) names a file of a format that cannot carry a run id (``map.npy``, ``poses.txt``)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def listed_by_index(target: str | os.PathLike[str], index: str | os.PathLike[str]) -> bool:
    """True when ``index`` is a JSON kbs wrote (:func:`is_kbs_output`) whose ``sha256`` object
    gives ``target``'s name (its path relative to the index's folder) the digest of ``target``'s
    bytes as they are now: a file without room for a run id that kbs wrote beside its index and
    nobody changed since."""
    target, index = Path(os.fspath(target)), Path(os.fspath(index))
    if not target.is_file() or not is_kbs_output(index):
        return False
    try:
        digests = json.loads(index.read_bytes()).get("sha256")
        name = os.path.relpath(target, index.parent).replace(os.sep, "/")
        return isinstance(digests, dict) and digests.get(name) == file_digest(target)
    except (OSError, ValueError, RecursionError):
        return False


def is_kbs_output(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` is a file kbs wrote with a run id: a PLY whose header has the
    ``kbs_run_id`` comment, a LAS/LAZ file with the run id VLR, a JSON object with ``kbs_version`` and ``run_id``, a rule
    file ``kbs tune`` wrote (its first line ``# kbs tune: ...``), a PNG with a ``kbs_run_id`` text chunk
    (:func:`png_metadata`), a GeoTIFF with the ``KBS_RUN_ID`` tag, any other file (the HTML report) ending with the
    ``kbs_run_id`` marker. Never a file of :data:`UNMARKED_SUFFIXES` (nothing in them can say so)."""
    path = Path(os.fspath(path))
    if not path.is_file():
        return False
    suffix = path.suffix.lower()
    if path.name.lower().endswith(UNMARKED_SUFFIXES):
        return False
    try:
        if suffix == ".png":
            return bool(png_text(path).get(RUN_ID_COMMENT))
        if suffix in (".tif", ".tiff"):
            return _geotiff_run_id(path) is not None
        if suffix == ".ply":
            return ply_run_id(path) is not None
        if suffix in (".las", ".laz"):
            return cloud_run_id(path) is not None
        if suffix == ".json":
            doc = json.loads(path.read_bytes())
            return isinstance(doc, dict) and "kbs_version" in doc and isinstance(doc.get("run_id"), str)
        if suffix in (".yaml", ".yml"):
            with open(path, "rb") as stream:
                return stream.read(len(TUNED_MARK)) == TUNED_MARK
        with open(path, "rb") as stream:
            stream.seek(max(0, path.stat().st_size - 256))
            return RUN_ID_COMMENT.encode("ascii") in stream.read()
    except (OSError, ValueError, RecursionError):  # RecursionError: a JSON nested too deep to be kbs's
        return False


class InputFiles:
    """A command's input files, known by identity (device and inode: links and ``..`` do not
    hide one), so that each output is compared with all of them in one ``stat``."""

    def __init__(self, paths: Iterable[str | os.PathLike[str]]) -> None:
        self._ids: dict[tuple[int, int], str] = {}
        for path in paths:
            try:
                st = os.stat(path)
            except OSError:  # missing or unreadable: the reader will say so
                continue
            self._ids.setdefault((st.st_dev, st.st_ino), os.fspath(path))

    def match(self, target: str | os.PathLike[str]) -> str | None:
        """The input that ``target`` is (the same file), or None."""
        try:
            st = os.stat(target)
        except OSError:
            return None
        return self._ids.get((st.st_dev, st.st_ino))


def _file_key(path: str | os.PathLike[str]) -> tuple[Any, ...]:
    try:
        st = os.stat(path)
    except OSError:
        return ("path", os.path.normcase(os.path.realpath(path)))
    return ("file", st.st_dev, st.st_ino)


def distinct_outputs(*targets: tuple[str, str | os.PathLike[str] | None]) -> None:
    """Refuse two outputs of one command that are one file (the same path, or links to one file).

    Parameters
    ----------
    *targets : (str, path or None)
        What each output is (``"--out"``) and its path; None is left out.

    Raises
    ------
    CloudFileError
        Naming the second path and both options (exit code 3), before any work.
    """
    seen: dict[tuple[Any, ...], str] = {}
    for what, target in targets:
        if target is None:
            continue
        key = _file_key(target)
        if key in seen:
            raise CloudFileError(os.fspath(target), f"is both {seen[key]} and {what}: one file cannot hold both; "
                                                    "give them two different paths")
        seen[key] = what


def check_output(target: str | os.PathLike[str], *,
                 inputs: InputFiles | Iterable[str | os.PathLike[str]] = (), force: bool = False,
                 own: bool = False, option: str = "--out") -> None:
    """Refuse to write ``target`` where that would destroy something that is not kbs's.

    Parameters
    ----------
    target : path
        A file a command is about to write.
    inputs : InputFiles or iterable of path
        The command's input files: never overwritten, even with ``force``.
    force : bool
        Replace an existing file that kbs did not write (``--force``).
    own : bool
        The caller knows ``target`` is kbs's own by other means (:func:`listed_by_index`).
    option : str
        The option the messages tell to change (``--json``, ``--report`` ...).

    Raises
    ------
    CloudFileError
        ``target`` is one of ``inputs`` (the same file, whatever the path: links, ``..``), a
        directory, or an existing file without a kbs run id while ``force`` is False. An
        earlier kbs result (it has a run id) is replaced without ``force``.
    """
    target = Path(os.fspath(target))
    source = (inputs if isinstance(inputs, InputFiles) else InputFiles(inputs)).match(target)
    if source is not None:
        named = "" if os.path.normpath(source) == os.path.normpath(target) else f" {source}"
        raise CloudFileError(str(target), f"is the input{named}: kbs never overwrites its input; choose another {option}")
    if target.is_dir():
        raise CloudFileError(str(target), f"is a directory; choose another {option}")
    if not force and not own and os.path.lexists(target) and not is_kbs_output(target):
        if target.name.lower().endswith(UNMARKED_SUFFIXES):
            raise CloudFileError(str(target), "exists, and kbs cannot tell whether it wrote it (this format has no "
                                              f"room for a kbs run id); give --force to replace it, or choose another "
                                              f"{option}")
        raise CloudFileError(str(target), "exists and was not written by kbs (it has no kbs run id); give --force "
                                          f"to replace it, or choose another {option}")
