"""Predicates: each MEASURES one number, with a unit, from a cluster and the scene. Rules decide
(they compare the number with a threshold written in the rule file); thresholds never live here.

A predicate is a plain function ``f(cluster, scene, *, param=default, ...) -> float`` (or a
:class:`Measurement` carrying details an action can reuse, such as the connected components),
declared with the :func:`predicate` decorator, which checks it on the spot: name, unit,
docstring, parameters (keyword-only, with defaults of a simple type). A
:class:`PredicateRegistry` collects them: the built-ins, the ``kbs.predicates`` entry-point group,
and plugin files (``kbs run --plugin my_predicates.py``).
"""
from __future__ import annotations

import dataclasses
import difflib
import importlib.util
import inspect
import math
import sys
import traceback
from dataclasses import dataclass
from functools import cached_property
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from kbs.errors import ExitCode, KbsError, raise_if_interrupted
from kbs.inference import ClusterGeometry, angle_between_planes, cluster_geometry
import kbs.geometry.connexity as _connexity

#: Units a predicate may declare. 'length' is the rule base's own length unit.
UNITS: dict[str, str] = {
    "length": "length in the rule base's unit",
    "deg": "degrees",
    "count": "a count",
    "points": "number of points",
    "ratio": "dimensionless",
    "area": "area in the rule base's unit, squared",
}

ENTRY_POINT_GROUP = "kbs.predicates"

_PARAM_TYPES = (bool, int, float, str)


class PredicateError(KbsError):
    """A predicate that does not meet the contract (found when it registers), or that failed."""

    exit_code = ExitCode.PLUGIN


# --- what a predicate sees ------------------------------------------------------------------


def _read_only(a: np.ndarray) -> np.ndarray:
    """A view of ``a`` that cannot be written through (``flags.writeable`` False); ``a`` itself
    stays as it was."""
    v = a.view()
    v.flags.writeable = False
    return v


def _frozen_copy(a: Any) -> np.ndarray:
    """A float64 copy of a small vector that nobody can write into."""
    out = np.array(a, dtype=np.float64)
    out.flags.writeable = False
    return out


@dataclass(eq=False)
class Cluster:
    """One cluster as the interpreter holds it; predicates see it through :meth:`view`.

    Attributes
    ----------
    id : str
        Path-like id ('c0.2').
    X : ndarray (n, 3)
        Its points (hard members).
    weights : ndarray (n,)
        Their memberships in the cluster (fuzzy degrees, 1 for a crisp split).
    """

    id: str
    X: np.ndarray
    weights: np.ndarray

    @property
    def n_points(self) -> int:
        return int(self.X.shape[0])

    @cached_property
    def geometry(self) -> ClusterGeometry:
        """Fuzzy centre, fuzzy covariance and its eigen-decomposition (memberships as weights);
        its arrays are read-only."""
        return cluster_geometry(self.X, self.weights)

    def view(self) -> ClusterView:
        """The read-only view a predicate is given (made once: nothing can be written through it)."""
        seen = self.__dict__.get("_view")
        if seen is None:
            seen = self.__dict__["_view"] = ClusterView(self)
        return seen

    def __getstate__(self) -> dict[str, Any]:
        """What a worker process is sent: not the view (it is made again there when asked)."""
        state = dict(self.__dict__)
        state.pop("_view", None)
        return state


class ClusterView:
    """What a predicate sees of a cluster: ``id``, ``X`` (n, 3), ``weights`` (n,), ``n_points``
    and ``geometry`` (:class:`~kbs.inference.ClusterGeometry`), all read-only. A predicate
    measures; writing into these arrays or assigning an attribute raises, and the run stops with
    a plugin error naming the predicate."""

    __slots__ = ("_cluster", "id", "X", "weights")

    def __init__(self, cluster: Cluster) -> None:
        object.__setattr__(self, "_cluster", cluster)
        object.__setattr__(self, "id", cluster.id)
        object.__setattr__(self, "X", _read_only(np.asarray(cluster.X)))
        object.__setattr__(self, "weights", _read_only(np.asarray(cluster.weights)))

    @property
    def n_points(self) -> int:
        return int(self.X.shape[0])

    @property
    def geometry(self) -> ClusterGeometry:
        return self._cluster.geometry

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"cannot set '{name}': a predicate sees the cluster read-only")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"cannot delete '{name}': a predicate sees the cluster read-only")

    def __repr__(self) -> str:
        return f"ClusterView(id={self.id!r}, n_points={self.n_points})"


@dataclass(frozen=True)
class Ground:
    """The ground plane: unit normal (pointing up, away from the ground) and a point on it (both
    kept as read-only copies)."""

    normal: np.ndarray
    point: np.ndarray
    source: str  #: where it came from ('cluster c0', 'fixed', 'fallback')

    def __post_init__(self) -> None:
        object.__setattr__(self, "normal", _frozen_copy(self.normal))
        object.__setattr__(self, "point", _frozen_copy(self.point))

    def height(self, X: np.ndarray) -> np.ndarray:
        """Signed heights (n,) of points above the ground plane."""
        return (X - self.point) @ self.normal


class _ReadOnlyObject:
    """A read-only stand-in for an object a predicate may query (the local ground surface): its
    methods work, its array attributes come as read-only views, nothing can be assigned."""

    __slots__ = ("_target",)

    def __init__(self, target: Any) -> None:
        object.__setattr__(self, "_target", target)

    def __getattr__(self, name: str) -> Any:
        value = getattr(object.__getattribute__(self, "_target"), name)
        return _read_only(value) if isinstance(value, np.ndarray) else value

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"cannot set '{name}': a predicate sees the scene read-only")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"cannot delete '{name}': a predicate sees the scene read-only")

    def __repr__(self) -> str:
        return f"read-only {object.__getattribute__(self, '_target')!r}"


@dataclass(frozen=True)
class Scene:
    """What predicates may know about the whole scene (read-only: the sensor is a read-only
    copy, the ground plane a frozen :class:`Ground`, the local ground surface a read-only
    stand-in)."""

    sensor: np.ndarray
    ground: Ground | None
    unit: str
    #: the local ground surface (:class:`~kbs.geometry.groundmodel.LocalGround`), built after the
    #: clusters are labelled; only the rule base's ``post.relabel`` conditions can see it
    ground_model: Any = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor", _frozen_copy(self.sensor))
        if self.ground_model is not None and not isinstance(self.ground_model, _ReadOnlyObject):
            object.__setattr__(self, "ground_model", _ReadOnlyObject(self.ground_model))


@dataclass(frozen=True)
class Measurement:
    """A predicate's value with optional details an action can reuse (e.g. the components).

    ``undefined`` says why there is no value (then ``value`` is NaN), e.g. the ground angle of a
    cluster whose points lie on a line: its check fails whatever its thresholds (so ``not CHECK``
    holds), and the explanation gives the reason.
    """

    value: float
    details: Any = None
    undefined: str | None = None

    @property
    def defined(self) -> bool:
        return self.undefined is None


# --- the contract ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Param:
    name: str
    type: type
    default: Any
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    #: (other parameter, value): this parameter only means something when the other one has
    #: that value (e.g. ``opening_factor`` with ``method: alpha_opening``)
    applies_with: tuple[str, str] | None = None

    def describe(self) -> str:
        only = f", with {self.applies_with[0]}: {self.applies_with[1]}" if self.applies_with else ""
        if self.choices:
            return f"{self.name}: one of {', '.join(self.choices)} (default {self.default!r}{only})"
        rng = ""
        if self.low is not None or self.high is not None:
            rng = f" in [{'-inf' if self.low is None else self.low}, {'inf' if self.high is None else self.high}]"
        return f"{self.name}: {self.type.__name__}{rng} (default {self.default!r}{only})"

    def check_with(self, params: Mapping[str, Any], defaults: Mapping[str, Param]) -> str | None:
        """None when the parameters given with this one (``params``, the others at their
        ``defaults``) are those it applies with, else what is wrong."""
        if self.applies_with is None:
            return None
        other, value = self.applies_with
        actual = params.get(other, defaults[other].default)
        if actual == value:
            return None
        return f"parameter '{self.name}' applies only with {other}: {value} (here {other} is {actual!r})"

    def check(self, value: Any) -> str | None:
        """None when ``value`` is acceptable, else what is wrong."""
        ok_type = isinstance(value, self.type) and not (self.type is not bool and isinstance(value, bool))
        if self.type is float and isinstance(value, int) and not isinstance(value, bool):
            ok_type = True
        if not ok_type:
            return f"parameter '{self.name}' must be a {self.type.__name__}, got {_shown(value)}"
        if self.choices and value not in self.choices:
            return f"parameter '{self.name}' must be one of {', '.join(self.choices)}, got {_shown(value)}"
        if self.low is not None and value < self.low or self.high is not None and value > self.high:
            return f"parameter '{self.name}' must be in [{self.low}, {self.high}], got {_shown(value)}"
        return None


def _shown(value: Any, keep: int = 60) -> str:
    """``repr(value)``, cut to about ``keep`` characters (a mapping pasted where a number belongs
    would fill the message)."""
    text = repr(value)
    return text if len(text) <= keep else f"{text[:keep]}... ({type(value).__name__} of {len(text):,} characters)"


@dataclass(frozen=True)
class Predicate:
    """A checked predicate: the function and its declared contract."""

    name: str
    func: Callable[..., float | Measurement]
    unit: str
    doc: str
    params: Mapping[str, Param]
    value_range: tuple[float | None, float | None]
    needs_ground: bool
    #: where it comes from: its module for the built-ins, else its file and line ('my_plugin.py:12')
    origin: str
    needs_ground_model: bool = False
    #: it measures the best approximating plane's orientation, which a degenerate cluster (all its
    #: points on a line or at one position) does not have: the value is then undefined
    needs_plane: bool = False
    #: for a predicate on the local ground surface: ``reach(params, model) -> float | None``, how
    #: far from the cluster's points (along the ground plane) the surface points it reads may lie,
    #: given its parameters (every one, defaults filled in) and the surface (a
    #: :class:`~kbs.geometry.groundmodel.LocalGround`); None: not known. A relabel rule judged again
    #: (``passes``) asks only the clusters within reach of those whose label changed; 0: it reads
    #: nothing the step's moves change.
    reach: Callable[[Mapping[str, Any], Any], float | None] | None = None

    @property
    def builtin(self) -> bool:
        return self.origin == __name__

    @property
    def where(self) -> str:
        """"predicate 'name'" and, for a plugin, its file and line."""
        return f"predicate '{self.name}'" + ("" if self.builtin else f" ({self.origin})")

    def measure(self, cluster: Cluster, scene: Scene, params: Mapping[str, Any]) -> Measurement:
        """Measure ``cluster`` in ``scene``. The predicate is given read-only views of both.

        Raises :class:`PredicateError` when it fails, changes what it is given, exits or returns
        something else than a number; ``KeyboardInterrupt`` goes through (Ctrl-C stops the run).
        """
        if self.needs_plane:
            geo = cluster.geometry
            if geo.degenerate:
                return Measurement(math.nan, undefined=f"degenerate: {geo.degeneracy}, no plane")
        seen = cluster.view() if isinstance(cluster, Cluster) else cluster
        try:
            out = self.func(seen, scene, **params)
        except KeyboardInterrupt:
            raise
        except KbsError as exc:
            if self.builtin:  # e.g. connexity's own parameter errors: as they are
                raise
            raise PredicateError(f"{self.where} failed on cluster {cluster.id} ({cluster.n_points:,} points)"
                                 f"{self._line(exc)}: {type(exc).__name__}: {exc}") from exc
        except SystemExit as exc:
            raise PredicateError(f"{self.where} called sys.exit({exc.code!r}){self._line(exc)} on cluster {cluster.id} "
                                 f"({cluster.n_points:,} points): a predicate returns a number or raises an "
                                 "exception; it must not end the program") from None
        except BaseException as exc:  # its bug: name the predicate, its file and line, and the cluster
            raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
            hint = ("; a predicate must not change the cluster or the scene it is given (they are read-only)"
                    if _is_mutation(exc) else "")
            raise PredicateError(f"{self.where} failed on cluster {cluster.id} ({cluster.n_points:,} points)"
                                 f"{self._line(exc)}: {type(exc).__name__}: {exc}{hint}") from exc
        if isinstance(out, Measurement):
            m = out
        else:
            try:
                m = Measurement(float(out))
            except (TypeError, ValueError):
                m = Measurement(out)
        if not m.defined:
            return Measurement(math.nan, m.details, str(m.undefined))
        if not isinstance(m.value, (int, float, np.floating, np.integer)) or math.isnan(float(m.value)):
            raise PredicateError(f"{self.where} returned {m.value!r} for cluster {cluster.id}, not a number "
                                 "(when there is none, return Measurement(nan, undefined='why'))")
        value = float(m.value)
        lo, hi = self.value_range
        if not self.builtin and ((lo is not None and value < lo) or (hi is not None and value > hi)):
            # a rule file's thresholds were checked against the declared range: a value outside it
            # would be judged by thresholds that were never meant for it
            raise PredicateError(f"{self.where} returned {value:g} for cluster {cluster.id}, outside its declared "
                                 f"value_range [{'-inf' if lo is None else f'{lo:g}'}, "
                                 f"{'inf' if hi is None else f'{hi:g}'}]: fix the predicate or its value_range")
        return Measurement(value, m.details)

    def _line(self, exc: BaseException) -> str:
        """' at my_plugin.py:17': the last line of the predicate's own file the error went
        through ('' for a built-in, or when there is none)."""
        if self.builtin:
            return ""
        code = getattr(inspect.unwrap(self.func), "__code__", None)
        if code is None:
            return ""
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == code.co_filename]
        return f" at {frames[-1].filename}:{frames[-1].lineno}" if frames else ""

    def unit_label(self, length_unit: str) -> str:
        return {"length": length_unit, "deg": "deg", "count": "", "points": "pts", "ratio": "",
                "area": f"{length_unit}²"}[self.unit]

    @property
    def summary(self) -> str:
        return self.doc.strip().splitlines()[0]


def _is_mutation(exc: BaseException) -> bool:
    """Whether ``exc`` is what writing into a read-only view or a frozen object raises."""
    if isinstance(exc, dataclasses.FrozenInstanceError):
        return True
    text = str(exc)
    return (isinstance(exc, ValueError) and "read-only" in text) or \
        (isinstance(exc, AttributeError) and "read-only" in text)


def origin_of(func: Callable) -> str:
    """Where a predicate function is declared: its module for the built-ins (and anything of
    kbs), else its file and line ('my_plugin.py:12', the line of its decorator), else what is
    known (its module's file or name)."""
    module = getattr(func, "__module__", None) or "?"
    if module == "kbs" or module.startswith("kbs."):
        return module
    code = getattr(inspect.unwrap(func), "__code__", None)
    if code is not None:
        return f"{code.co_filename}:{code.co_firstlineno}"
    return getattr(sys.modules.get(module), "__file__", None) or module


def _file_and_line(origin: str) -> tuple[str | None, int | None]:
    """('my_plugin.py', 12) for an origin 'my_plugin.py:12', else (None, None)."""
    file, sep, line = origin.rpartition(":")
    return (file, int(line)) if sep and file and line.isdigit() else (None, None)


def predicate(
    name: str | None = None,
    *,
    unit: str,
    value_range: tuple[float | None, float | None] = (None, None),
    needs_ground: bool = False,
    bounds: Mapping[str, tuple[float | None, float | None]] | None = None,
    choices: Mapping[str, Iterable[str]] | None = None,
    needs_ground_model: bool = False,
    needs_plane: bool = False,
    applies_with: Mapping[str, tuple[str, str]] | None = None,
    reach: Callable[[Mapping[str, Any], Any], float | None] | None = None,
) -> Callable[[Callable], Predicate]:
    """Declare a predicate. The function is checked now, not when it is first called.

    Parameters
    ----------
    name : str, optional
        Its name in rule files (default: the function's name).
    unit : str
        One of :data:`UNITS`.
    value_range : (low, high)
        The values it can return (numbers or None for no bound); thresholds outside are rejected
        when a rule file is loaded, and a plugin's value outside is a :class:`PredicateError`.
    needs_ground : bool
        Whether it uses ``scene.ground``.
    needs_ground_model : bool
        Whether it uses ``scene.ground_model``, the local ground surface built from the clusters
        labelled ground (implies ``needs_ground``). Such a predicate can only be used after the
        labelling: in the conditions of ``post.relabel``.
    needs_plane : bool
        Whether it measures the orientation of the cluster's best approximating plane (its
        normal, the ratio of its spreads). A degenerate cluster (``cluster.geometry.degenerate``:
        its points on a line or at one position) has none: the predicate is not called, its
        value is undefined, its check fails and the explanation says why.
    bounds, choices : mapping
        Allowed ranges of numeric parameters, allowed values of string parameters.
    applies_with : mapping
        Parameters that only mean something when another (string) parameter has one value:
        ``{"opening_factor": ("method", "alpha_opening")}``. A rule file that gives such a
        parameter without that value is refused when it is loaded.
    reach : callable, optional
        With ``needs_ground_model``: ``reach(params, model)``, the largest distance along the ground
        plane between a cluster's point and a surface point the measure reads (None when not
        known). A ``post.relabel`` rule judged again with ``passes`` then asks only the clusters
        within reach of those whose label changed: the others would measure the same. Without it
        every cluster is asked again. 0: the measure reads nothing a relabel step's moves change
        (the continuous surfaces, fixed within a step): it asks no cluster again by itself.
    """

    def wrap(func: Callable) -> Predicate:
        return make_predicate(func, name=name or getattr(func, "__name__", ""), unit=unit, value_range=value_range,
                              needs_ground=needs_ground or needs_ground_model, bounds=bounds or {},
                              choices=choices or {}, origin=origin_of(func),
                              needs_ground_model=needs_ground_model, needs_plane=needs_plane,
                              applies_with=applies_with or {}, reach=reach)

    return wrap


def make_predicate(func: Callable, *, name: str, unit: str, value_range, needs_ground: bool, bounds, choices,
                   origin: str, needs_ground_model: bool = False, needs_plane: bool = False,
                   applies_with: Mapping[str, tuple[str, str]] | None = None,
                   reach: Callable[[Mapping[str, Any], Any], float | None] | None = None) -> Predicate:
    """Check a function against the predicate contract and wrap it (raises PredicateError)."""
    file, line = _file_and_line(origin)
    where = f"{file}: predicate '{name}' (line {line})" if file else f"predicate '{name}' ({origin})"
    if not isinstance(name, str) or not name.isidentifier():
        raise PredicateError(f"{where}: the name must be an identifier")
    if not callable(func):
        raise PredicateError(f"{where}: not callable")
    if unit not in UNITS:
        raise PredicateError(f"{where}: unknown unit {unit!r}; use one of {', '.join(UNITS)}")
    doc = inspect.getdoc(func) or ""
    if not doc.strip():
        raise PredicateError(f"{where}: a docstring saying what it measures is required")
    try:
        lo, hi = value_range
        lo, hi = (None if lo is None else float(lo)), (None if hi is None else float(hi))
    except (TypeError, ValueError):
        raise PredicateError(f"{where}: value_range must be (low, high), numbers or None, got {value_range!r}") from None
    if any(b is not None and math.isnan(b) for b in (lo, hi)):
        raise PredicateError(f"{where}: value_range {value_range} has a NaN bound (use None for no bound)")
    if lo is not None and hi is not None and lo > hi:
        raise PredicateError(f"{where}: empty value range {value_range}")
    sig = inspect.signature(func)
    ps = list(sig.parameters.values())
    if len(ps) < 2 or any(p.kind not in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in ps[:2]):
        raise PredicateError(f"{where}: must take (cluster, scene) as its first two positional parameters")
    params: dict[str, Param] = {}
    for p in ps[2:]:
        if p.kind is not p.KEYWORD_ONLY:
            raise PredicateError(f"{where}: parameter '{p.name}' must be keyword-only (after '*')")
        if p.default is p.empty or type(p.default) not in _PARAM_TYPES:
            raise PredicateError(f"{where}: parameter '{p.name}' needs a default of type bool, int, float or str")
        b = (bounds or {}).get(p.name, (None, None))
        c = tuple((choices or {}).get(p.name, ())) or None
        w = (applies_with or {}).get(p.name)
        params[p.name] = Param(p.name, type(p.default), p.default, b[0], b[1], c, None if w is None else tuple(w))
        problem = params[p.name].check(p.default)
        if problem:
            raise PredicateError(f"{where}: default of {problem}")
    unknown = set(bounds or {}) | set(choices or {}) | set(applies_with or {})
    unknown -= set(params)
    if unknown:
        raise PredicateError(f"{where}: bounds, choices or applies_with given for unknown parameters {sorted(unknown)}")
    for pname, param in params.items():
        if param.applies_with is None:
            continue
        other, value = param.applies_with
        if other not in params or not params[other].choices or value not in params[other].choices:
            raise PredicateError(f"{where}: parameter '{pname}' applies with {other}: {value!r}, which is not one of "
                                 f"the declared choices of a parameter '{other}'")
    return Predicate(name=name, func=func, unit=unit, doc=doc, params=params, value_range=(lo, hi),
                     needs_ground=needs_ground or needs_ground_model, origin=origin,
                     needs_ground_model=needs_ground_model, needs_plane=bool(needs_plane),
                     reach=reach if needs_ground_model else None)


# --- the registry ---------------------------------------------------------------------------


class PredicateRegistry:
    """Name -> :class:`Predicate`, and the other parts a rule file may name: the post steps
    (``post_steps``, key -> class) and the actions (``actions``, key -> instance). Build one with
    :meth:`default`, then add plugins (a plugin file may declare all three kinds)."""

    def __init__(self, predicates: Iterable[Predicate] = ()) -> None:
        from kbs.knowledge.actions import ACTIONS
        from kbs.knowledge.post import STEPS

        self._items: dict[str, Predicate] = {}
        self.post_steps: dict[str, Any] = dict(STEPS)
        self.actions: dict[str, Any] = {k: cls() for k, cls in ACTIONS.items()}
        self._origins: dict[tuple[str, str], str] = {}
        for p in predicates:
            self.add(p)

    @classmethod
    def default(cls, *, entry_points_too: bool = True) -> PredicateRegistry:
        """The built-ins, plus the predicates of installed packages' ``kbs.predicates`` entry points."""
        reg = cls(BUILTINS)
        if entry_points_too:
            for ep in entry_points(group=ENTRY_POINT_GROUP):
                try:
                    obj = ep.load()
                except KeyboardInterrupt:
                    raise
                except BaseException as exc:  # a broken third-party package must say who it is (sys.exit too)
                    raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
                    what = f"called sys.exit({exc.code!r})" if isinstance(exc, SystemExit) else f"failed to load: {exc}"
                    raise PredicateError(f"entry point '{ep.name}' ({ep.value}) {what}") from exc
                reg.add_object(obj, origin=f"entry point {ep.name}")
        return reg

    def add(self, pred: Predicate) -> None:
        if not isinstance(pred, Predicate):
            raise PredicateError(f"{pred!r} is not a predicate; declare it with @kbs.knowledge.predicate(...)")
        if pred.name in self._items and self._items[pred.name] is not pred:
            raise PredicateError(
                f"predicate '{pred.name}' from {pred.origin} clashes with the one from {self._items[pred.name].origin}"
            )
        self._items[pred.name] = pred

    def add_part(self, cls: Any, origin: str) -> None:
        """Add a post step or action class (:mod:`kbs.knowledge.parts`) after checking its
        contract; a key that clashes with another part of its kind is an error."""
        from kbs.knowledge.parts import check_part

        kind = check_part(cls, origin)
        table: dict[str, Any] = self.post_steps if kind == "post step" else self.actions
        if kind not in ("post step", "action"):
            raise PredicateError(f"{origin}: a plugin may add post steps and actions, not a {kind} ({cls.key})")
        if cls.key in table or (kind == "action" and cls.key == "accept"):
            known = self._origins.get((kind, cls.key), "kbs")
            raise PredicateError(f"{kind} '{cls.key}' from {origin} clashes with the one from {known}")
        table[cls.key] = cls if kind == "post step" else cls()
        self._origins[(kind, cls.key)] = origin

    def add_object(self, obj: Any, origin: str) -> int:
        """Add a Predicate, or every Predicate, post step and action class a module declares
        (defined in it, not imported); returns how many."""
        from kbs.knowledge.parts import Action, PostStep, Strategy

        if isinstance(obj, Predicate):
            self.add(obj)
            return 1
        if isinstance(obj, ModuleType):
            found = [v for v in vars(obj).values() if isinstance(v, Predicate)]
            parts = [v for v in vars(obj).values() if isinstance(v, type) and issubclass(v, (PostStep, Action, Strategy))
                     and v.__module__ == obj.__name__]
            if not found and not parts:
                raise PredicateError(f"{origin}: no predicate found (declare them with @kbs.knowledge.predicate; "
                                     "post steps and actions as subclasses of kbs.knowledge.PostStep / Action)")
            for p in found:
                self.add(p)
            for cls in parts:
                self.add_part(cls, origin)
            return len(found) + len(parts)
        raise PredicateError(f"{origin}: expected a predicate or a module of predicates, got {type(obj).__name__}")

    def add_plugin_file(self, path: str | Path) -> int:
        """Import a Python file and add the predicates it declares.

        Every problem is a :class:`PredicateError` naming the file (and the line where known):
        a missing file, an import that fails or exits (``sys.exit``), a predicate that breaks the
        contract. ``KeyboardInterrupt`` goes through.
        """
        path = Path(path)
        if not path.is_file():
            raise PredicateError(f"{path}: plugin file not found")
        mod_name = f"kbs_plugin_{abs(hash(str(path.resolve())))}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise PredicateError(f"{path}: not an importable Python file")
        module = importlib.util.module_from_spec(spec)
        try:
            source = path.read_bytes()
        except OSError as exc:
            raise PredicateError(f"{path}: cannot read the plugin file: {exc.strerror or exc}") from exc
        sys.modules[mod_name] = module
        try:
            # compiled under the path as the user gave it, so that every message (the predicates'
            # origins, the lines of errors) names the file they know
            exec(compile(source, str(path), "exec"), module.__dict__)
        except PredicateError as exc:
            raise PredicateError(str(exc) if str(exc).startswith(f"{path}:") else f"{path}: {exc}") from exc
        except KeyboardInterrupt:
            raise
        except SystemExit as exc:
            raise PredicateError(f"{_at_line(path, exc)}: the plugin called sys.exit({exc.code!r}) while being "
                                 "imported: a plugin file declares predicates; it must not end the program") from None
        except BaseException as exc:
            raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
            raise PredicateError(f"{_at_line(path, exc)}: the plugin failed to import: "
                                 f"{type(exc).__name__}: {exc}") from exc
        return self.add_object(module, origin=str(path))

    def get(self, name: str) -> Predicate:
        return self._items[name]

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def names(self) -> list[str]:
        return sorted(self._items)

    def __iter__(self):
        return iter(self._items[n] for n in self.names())

    def suggest(self, name: str) -> str | None:
        """The closest known name, for 'did you mean'."""
        return did_you_mean(name, self.names())


def _at_line(path: Path, exc: BaseException) -> str:
    """'my_plugin.py:7': the file and the last line of it that ``exc`` went through ('my_plugin.py'
    alone when unknown)."""
    line = getattr(exc, "lineno", None) if isinstance(exc, SyntaxError) else None
    if line is None:
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == str(path)]
        line = frames[-1].lineno if frames else None
    return f"{path}:{line}" if line else str(path)


def did_you_mean(name: str, candidates: Iterable[str]) -> str | None:
    hits = difflib.get_close_matches(str(name), list(candidates), n=1, cutoff=0.6)
    return hits[0] if hits else None


# --- built-in predicates --------------------------------------------------------------------


@predicate(unit="length", value_range=(0.0, None))
def thickness(cluster: Cluster, scene: Scene) -> float:
    """Spread across the best approximating plane: sqrt(mu1), the square root of the smallest
    eigenvalue of the fuzzy covariance (PAh measures this)."""
    return cluster.geometry.thickness


@predicate(unit="ratio", value_range=(0.0, 1.0), needs_plane=True)
def flatness(cluster: Cluster, scene: Scene) -> float:
    """sqrt(mu1 / mu2): the spread across the best approximating plane relative to the smaller
    spread along it; 0 for a sheet, 1 when the cluster is as thick as it is wide (a blob).
    Undefined when its points lie on a line (0 / 0)."""
    mu = cluster.geometry.eigenvalues
    return float(np.sqrt(mu[0] / mu[1])) if mu[1] > 0 else 0.0


@predicate(unit="deg", value_range=(0.0, 90.0), needs_ground=True, needs_plane=True)
def ground_angle(cluster: Cluster, scene: Scene) -> float:
    """Angle in degrees between the cluster's best approximating plane and the ground plane
    (0 = parallel). Undefined when its points lie on a line: no plane."""
    return math.degrees(angle_between_planes(cluster.geometry.normal, scene.ground.normal))


@predicate(unit="count", value_range=(0.0, None),
           bounds={"alpha_factor": (0.1, 100.0), "min_fraction": (0.0, 1.0), "min_points": (1, None),
                   "opening_factor": (0.0, 10.0)},
           choices={"method": _connexity.METHODS},
           applies_with={"opening_factor": ("method", "alpha_opening")})
def connexity(cluster: Cluster, scene: Scene, *, alpha_factor: float = 3.0, min_fraction: float = 0.05,
              min_points: int = 10, opening: bool = True, method: str = "graph",
              opening_factor: float = 1.0) -> Measurement:
    """Number of significant connected components of the cluster projected on its best
    approximating plane (alpha-complex with alpha = alpha_factor x the median nearest-neighbour
    spacing, filtered by a morphological opening; a component is significant with at least
    max(min_points, min_fraction x size) points). CAh measures this; the components are the
    natural split. method 'graph': the components of the links <= 2 alpha, opened by counting
    neighbours; 'alpha_opening' (the paper's): the alpha-shape (Delaunay triangles of
    circumradius <= alpha) opened by a disc of radius opening_factor x alpha, which removes the
    parts narrower than twice that radius."""
    geo = cluster.geometry
    if method == "alpha_opening" and geo.degenerate:  # an alpha-shape of points on a line has no area
        return Measurement(math.nan, undefined=f"degenerate: {geo.degeneracy}, no plane for an alpha-shape")
    res = _connexity.connexity(cluster.X, geo.center, geo.normal, alpha_factor=alpha_factor,
                               min_fraction=min_fraction, min_points=min_points, opening=opening,
                               method=method, opening_factor=opening_factor)
    return Measurement(float(res.n_significant), res)


@predicate(unit="points", value_range=(0.0, None))
def point_count(cluster: Cluster, scene: Scene) -> float:
    """Number of points in the cluster."""
    return float(cluster.n_points)


@predicate(unit="length", value_range=(0.0, None), choices={"axis": ("largest", "middle", "smallest")})
def extent(cluster: Cluster, scene: Scene, *, axis: str = "largest") -> float:
    """Extent of the cluster (max - min of its points' projections) along one of the
    eigenvectors of its fuzzy covariance: 'largest' (e3), 'middle' (e2) or 'smallest' (e1)."""
    geo = cluster.geometry
    e = geo.eigenvectors[:, {"smallest": 0, "middle": 1, "largest": 2}[axis]]
    proj = cluster.X @ e
    return float(proj.max() - proj.min())


@predicate(unit="length", value_range=(0.0, None), choices={"stat": ("median", "max", "mean", "min")})
def point_spacing(cluster: Cluster, scene: Scene, *, stat: str = "median") -> float | Measurement:
    """Distance from each point of the cluster to its nearest other point of the cluster (in 3D):
    their median, max, mean or min. A piece of a surface measures about the scan's sampling (0.65-1.5
    m in the ISPRS airborne samples); stray points that a partition gathered, such as low outliers
    metres apart under the terrain, measure several times that. Undefined for a cluster of one
    point (its check fails)."""
    if cluster.n_points < 2:
        return Measurement(math.nan, undefined="one point: no spacing")
    from kbs.geometry.nearest import nearest_other_distances

    d = nearest_other_distances(np.array(cluster.X, dtype=np.float64))  # a writeable copy: the kernel built ahead of time takes those
    return float({"median": np.median, "max": np.max, "mean": np.mean, "min": np.min}[stat](d))


def _order_stat(q: float, median: bool, reference: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray], Any]:
    """``reference``, computed by :func:`kbs.geometry.groundmodel.order_statistic` (the same value,
    compiled where it can be; imported when first used: the commands that do not segment load no
    numba)."""
    def stat(h: np.ndarray) -> Any:
        from kbs.geometry.groundmodel import order_statistic

        return order_statistic(h, q, median, reference)
    return stat


_STATS = {"max": np.max, "p90": _order_stat(90 / 100, False, lambda h: np.percentile(h, 90)),
          "p75": _order_stat(75 / 100, False, lambda h: np.percentile(h, 75)), "mean": np.mean,
          "median": _order_stat(0.5, True, np.median),
          "p25": _order_stat(25 / 100, False, lambda h: np.percentile(h, 25)),
          "p10": _order_stat(10 / 100, False, lambda h: np.percentile(h, 10)), "min": np.min}


@predicate(unit="length", needs_ground=True, choices={"stat": tuple(_STATS)})
def height_above_ground(cluster: Cluster, scene: Scene, *, stat: str = "max") -> float:
    """Height of the cluster's points above the ground plane (signed, along the ground normal):
    their max, 90th or 75th percentile, mean, median, 25th or 10th percentile, or min."""
    h = scene.ground.height(cluster.X)
    return float(_STATS[stat](h))


@predicate(unit="length", value_range=(0.0, None), choices={"to": ("center", "nearest")})
def distance_to_sensor(cluster: Cluster, scene: Scene, *, to: str = "center") -> float:
    """Distance from the sensor to the cluster's fuzzy centre ('center') or to its nearest point
    ('nearest')."""
    if to == "center":
        return float(np.linalg.norm(cluster.geometry.center - scene.sensor))
    return float(np.sqrt(((cluster.X - scene.sensor) ** 2).sum(axis=1).min()))


def _surface_reach(params: Mapping[str, Any], model: Any) -> float | None:
    """The surface's own radius (its neighbours are looked for within it), when it is fixed."""
    return None if model.per_range > 0.0 else float(model.radius)


@predicate(unit="length", needs_ground_model=True, choices={"stat": tuple(_STATS)}, bounds={"max_points": (0, None)},
           reach=_surface_reach)
def height_above_local_ground(cluster: Cluster, scene: Scene, *, stat: str = "p90", exclude_self: bool = False,
                              max_points: int = 0) -> float:
    """Height of the cluster's points above the local ground surface (the median height of the
    nearest points of the clusters labelled ground, see post.ground_model), along the ground
    normal: their max, 90th or 75th percentile, mean, median, 25th or 10th percentile, or min, over the points
    with ground within the model's radius (above the ground plane when none has). With
    exclude_self, the cluster's own points are not part of the surface: a ground cluster is
    compared with the ground around it (a roof stands high above it); a point counts then only if
    other clusters' points are among its (8 x the model's neighbours) nearest surface points. With
    max_points (0: all), the statistic is taken over at most that many of the cluster's points,
    evenly spaced in its point order: a bound on the cost for large clusters (with exclude_self each
    point asks the surface for 8 x neighbours points). Usable in post.relabel conditions only (the
    surface exists once clusters are labelled)."""
    P = cluster.X
    if 0 < max_points < P.shape[0]:
        P = P[np.linspace(0, P.shape[0] - 1, max_points).astype(np.int64)]
    h = scene.ground_model.height(P, cluster.id if exclude_self else None)
    known = ~np.isnan(h)
    h = h[known] if known.any() else scene.ground.height(P)
    return float(_STATS[stat](h))


@predicate(unit="length", needs_ground_model=True, choices={"stat": tuple(_STATS)},
           bounds={"slope": (0.0, 89.0), "radius": (0.0, None), "max_points": (1, None)},
           reach=lambda params, model: float(params["radius"]))
def height_above_slope_surface(cluster: Cluster, scene: Scene, *, slope: float = 30.0, radius: float = 20.0,
                               stat: str = "median", max_points: int = 64) -> float | Measurement:
    """Height of the cluster above the lowest terrain the ground around it allows, the terrain
    being no steeper than slope degrees (a slope-based filter): for each point, its height above
    min over the surface points of other clusters within radius (along the ground plane) of
    (their height + tan(slope) x their distance). Ground on a hillside no steeper than slope
    measures 0 or less, a roof its height less the slope's rise to the ground beside the building,
    however many roof patches surround it. The stat (max, 90th or 75th percentile, mean, median, 25th or 10th
    percentile or min) over up to max_points of its points, evenly taken; points with no surface
    within radius are left out, and the value is undefined when none has (no ground around it says
    nothing of its height above the terrain: its check fails). Usable in post.relabel conditions
    only."""
    X = cluster.X
    if X.shape[0] > max_points:
        X = X[np.linspace(0, X.shape[0] - 1, max_points).astype(np.int64)]
    h = scene.ground_model.height_above_slope(X, slope, radius, cluster.id)
    h = h[~np.isnan(h)]
    if not h.size:
        return Measurement(math.nan, undefined=f"no ground of other clusters within {radius:g} of its points")
    return float(_STATS[stat](h))


def _step_regions(params: Mapping[str, Any], model: Any) -> float:
    """0: the continuous surfaces are those the relabel step found (LocalGround.regions), whatever
    its passes move."""
    return 0.0


def _edge_drop_reach(params: Mapping[str, Any], model: Any) -> float | None:
    """0 (the step's surfaces, :func:`_step_regions`), but None with beside: ground: what left the
    surface beside any edge of the cluster's surface, however far from the cluster, moves it."""
    return None if params.get("beside") == "ground" else 0.0


def _surfaces_of(cluster: Cluster, scene: Scene, gap: float, slope: float, step: float):
    """(the surfaces' regions, their :class:`~kbs.geometry.groundmodel.SurfaceEdges`, the
    cluster's owner index), or (regions, None, None) for a cluster not part of the surface."""
    regions = scene.ground_model.regions
    k = regions.owner_index.get(cluster.id)
    if k is None:
        return regions, None, None
    return regions, regions.edges(gap, slope, step), k


@predicate(unit="length", needs_ground_model=True,
           choices={"stat": tuple(_STATS), "over": ("surface", "cluster"), "beside": ("all", "ground")},
           applies_with={"beside": ("over", "surface")},
           bounds={"gap": (0.0, None), "slope": (0.0, 89.0), "step": (0.0, None)}, reach=_edge_drop_reach)
def edge_drop(cluster: Cluster, scene: Scene, *, gap: float = 3.0, slope: float = 45.0, step: float = 0.5,
              stat: str = "median", over: str = "surface", beside: str = "all") -> Measurement:
    """How far the continuous ground surface the cluster is part of stands above the surfaces
    beside its edges: the local ground surface's points (post.ground_model) are joined into
    continuous surfaces (a point and one of its 8 nearest within gap, along the ground plane, whose
    heights differ by at most tan(slope) x their distance or step); a point of one with points of
    others within gap stands at its edge, by its height less the lowest terrain those allow
    (their height + tan(slope) x the distance). The stat (max, 90th or 75th percentile, mean, median, 25th or 10th
    percentile or min) over the edge points of the surface holding most of the cluster's points: a
    roof's surface drops by about the building's height at every edge, however large the roof and
    however far the cluster lies from its edge; terrain beside buildings rises at its edges. The
    value is undefined for a cluster that is not part of the surface (not labelled as the surface
    is) and for a surface that meets no other within gap. With over: cluster, the stat is over the
    cluster's own points that stand at an edge of their surface (how far the cluster itself stands
    above the surfaces beside it), undefined when none does. Rules judged again (passes) measure
    the surfaces the relabel step started from; with beside: ground, only those of their points
    still labelled as the surface is count beside its edges (the clusters the rules took in earlier
    passes are out): a low roof between taller ones, which rises to them, drops at its edges once
    they are taken for roofs. Usable in post.relabel conditions only."""
    regions, edges, k = _surfaces_of(cluster, scene, gap, slope, step)
    if edges is None:
        return Measurement(math.nan, undefined="not part of the local ground surface")
    alive = scene.ground_model.owners_alive() if beside == "ground" else None
    r = int(edges.owner_region[k])
    if (alive is not None and r >= 0 and not alive.all()  # a later pass: some left the surface, beside this one's
            and regions.touched(gap, slope, step, alive)[r]):
        d = regions.drops_beside(gap, slope, step, r, alive)
        if not d.size:
            return Measurement(math.nan, undefined=f"its continuous surface ({edges.size_of(r):,} points) meets no "
                                                   f"other still labelled as the surface within {gap:g}")
        return Measurement(float(_STATS[stat](d)), details={"surface_points": edges.size_of(r),
                                                            "edge_points": int(d.size)})
    if over == "cluster":
        d = edges.drop[regions.points_of(k)]
        d = d[~np.isnan(d)]
        if not d.size:
            return Measurement(math.nan, undefined=f"none of its points meets another continuous surface within {gap:g}")
        return Measurement(float(_STATS[stat](d)), details={"edge_points": int(d.size)})
    r = int(edges.owner_region[k])
    d = edges.drops_of(r)
    if not d.size:
        return Measurement(math.nan, undefined=f"its continuous surface ({edges.size_of(r):,} points) meets no "
                                               f"other within {gap:g}")
    return Measurement(edges.stat_of(r, stat, _STATS[stat]), details={"surface_points": edges.size_of(r),
                                                                       "edge_points": int(d.size)})


def _surface_region(cluster: Cluster, scene: Scene, gap: float, slope: float, step: float):
    """(the continuous surfaces, the one holding most of the cluster's points) or (None, a reason)."""
    _, edges, k = _surfaces_of(cluster, scene, gap, slope, step)
    if edges is None:
        return None, "not part of the local ground surface"
    return edges, int(edges.owner_region[k])


@predicate(unit="ratio", value_range=(0.0, 1.0), needs_ground_model=True,
           bounds={"gap": (0.0, None), "slope": (0.0, 89.0), "step": (0.0, None), "min_drop": (0.0, None)},
           reach=_step_regions)
def surface_enclosure(cluster: Cluster, scene: Scene, *, gap: float = 3.0, slope: float = 45.0, step: float = 0.5,
                      min_drop: float = 5.0) -> Measurement:
    """How far the continuous ground surface the cluster is part of (as edge_drop joins them) is
    enclosed by the surfaces it drops to: the share of its points inside the convex hull, along
    the ground plane, of the points beside its edges that allow the lowest terrain under each edge
    point dropping by min_drop or more. A roof drops to the street on every side and the street
    around it encloses it (1; a quarter to a half where the scan cuts the building with two walls
    in view); the upper terrace of a terrain step drops on one side only (0), and the rim of a pit
    drops to a floor that lies inside the rim, not around it (0). Undefined for a cluster not part
    of the surface and for a surface with no edge dropping by min_drop. Rules judged again (passes)
    measure the surfaces the relabel step started from. Usable in post.relabel conditions only."""
    edges, r = _surface_region(cluster, scene, gap, slope, step)
    if edges is None:
        return Measurement(math.nan, undefined=r)
    share, n_edge = edges.enclosure(r, min_drop)
    if not n_edge:
        return Measurement(math.nan, undefined=f"its continuous surface ({edges.size_of(r):,} points) has no edge "
                                               f"dropping by {min_drop:g} or more")
    return Measurement(share, details={"surface_points": edges.size_of(r), "dropping_edge_points": n_edge})


@predicate(unit="area", value_range=(0.0, None), needs_ground_model=True,
           bounds={"gap": (0.0, None), "slope": (0.0, 89.0), "step": (0.0, None), "cell": (0.0, None)},
           reach=_step_regions)
def surface_area(cluster: Cluster, scene: Scene, *, gap: float = 3.0, slope: float = 45.0, step: float = 0.5,
                 cell: float = 3.0) -> Measurement:
    """The area the continuous ground surface the cluster is part of (as edge_drop joins them)
    covers along the ground plane: its occupied square cells of side cell, times cell squared. A
    building's roof covers what its footprint does; terrain reaches as far as the scan. Undefined
    for a cluster not part of the surface. Rules judged again (passes) measure the surfaces the
    relabel step started from. Usable in post.relabel conditions only."""
    edges, r = _surface_region(cluster, scene, gap, slope, step)
    if edges is None:
        return Measurement(math.nan, undefined=r)
    return Measurement(float(edges.areas(cell)[r]), details={"surface_points": edges.size_of(r)})


BUILTINS: tuple[Predicate, ...] = (thickness, flatness, ground_angle, connexity, point_count, point_spacing, extent,
                                   height_above_ground,
                                   distance_to_sensor, height_above_local_ground, height_above_slope_surface, edge_drop,
                                   surface_enclosure, surface_area)
