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

import difflib
import importlib.util
import inspect
import math
import sys
from dataclasses import dataclass, field
from functools import cached_property
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from kbs.errors import ExitCode, KbsError
from kbs.inference import ClusterGeometry, angle_between_planes, cluster_geometry
import kbs.knowledge.connexity as _connexity

#: Units a predicate may declare. 'length' is the rule base's own length unit.
UNITS: dict[str, str] = {
    "length": "length in the rule base's unit",
    "deg": "degrees",
    "count": "a count",
    "points": "number of points",
    "ratio": "dimensionless",
}

ENTRY_POINT_GROUP = "kbs.predicates"

_PARAM_TYPES = (bool, int, float, str)


class PredicateError(KbsError):
    """A predicate that does not meet the contract (found when it registers), or that failed."""

    exit_code = ExitCode.PLUGIN


# --- what a predicate sees ------------------------------------------------------------------


@dataclass(eq=False)
class Cluster:
    """One cluster as the predicates see it.

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
    cache: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def n_points(self) -> int:
        return int(self.X.shape[0])

    @cached_property
    def geometry(self) -> ClusterGeometry:
        """Fuzzy centre, fuzzy covariance and its eigen-decomposition (memberships as weights)."""
        return cluster_geometry(self.X, self.weights)


@dataclass(frozen=True)
class Ground:
    """The ground plane: unit normal (pointing up, away from the ground) and a point on it."""

    normal: np.ndarray
    point: np.ndarray
    source: str  #: where it came from ('cluster c0', 'fixed', 'fallback')

    def height(self, X: np.ndarray) -> np.ndarray:
        """Signed heights (n,) of points above the ground plane."""
        return (X - self.point) @ self.normal


@dataclass(frozen=True)
class Scene:
    """What predicates may know about the whole scene."""

    sensor: np.ndarray
    ground: Ground | None
    unit: str
    #: the local ground surface (:class:`~kbs.knowledge.groundmodel.LocalGround`), built after the
    #: clusters are labelled; only the rule base's ``post.relabel`` conditions can see it
    ground_model: Any = None


@dataclass(frozen=True)
class Measurement:
    """A predicate's value with optional details an action can reuse (e.g. the components)."""

    value: float
    details: Any = None


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

    def check_with(self, params: Mapping[str, Any], defaults: Mapping[str, "Param"]) -> str | None:
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
            return f"parameter '{self.name}' must be a {self.type.__name__}, got {value!r}"
        if self.choices and value not in self.choices:
            return f"parameter '{self.name}' must be one of {', '.join(self.choices)}, got {value!r}"
        if self.low is not None and value < self.low or self.high is not None and value > self.high:
            return f"parameter '{self.name}' must be in [{self.low}, {self.high}], got {value!r}"
        return None


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
    origin: str
    needs_ground_model: bool = False

    def measure(self, cluster: Cluster, scene: Scene, params: Mapping[str, Any]) -> Measurement:
        out = self.func(cluster, scene, **params)
        m = out if isinstance(out, Measurement) else Measurement(float(out))
        if not isinstance(m.value, (int, float, np.floating, np.integer)) or math.isnan(float(m.value)):
            raise PredicateError(f"predicate '{self.name}' returned {m.value!r} for cluster {cluster.id}, not a number")
        return Measurement(float(m.value), m.details)

    def unit_label(self, length_unit: str) -> str:
        return {"length": length_unit, "deg": "deg", "count": "", "points": "pts", "ratio": ""}[self.unit]

    @property
    def summary(self) -> str:
        return self.doc.strip().splitlines()[0]


def predicate(
    name: str | None = None,
    *,
    unit: str,
    value_range: tuple[float | None, float | None] = (None, None),
    needs_ground: bool = False,
    bounds: Mapping[str, tuple[float | None, float | None]] | None = None,
    choices: Mapping[str, Iterable[str]] | None = None,
    needs_ground_model: bool = False,
    applies_with: Mapping[str, tuple[str, str]] | None = None,
) -> Callable[[Callable], Predicate]:
    """Declare a predicate. The function is checked now, not when it is first called.

    Parameters
    ----------
    name : str, optional
        Its name in rule files (default: the function's name).
    unit : str
        One of :data:`UNITS`.
    value_range : (low, high)
        The values it can return; thresholds outside are rejected when a rule file is loaded.
    needs_ground : bool
        Whether it uses ``scene.ground``.
    needs_ground_model : bool
        Whether it uses ``scene.ground_model``, the local ground surface built from the clusters
        labelled ground (implies ``needs_ground``). Such a predicate can only be used after the
        labelling: in the conditions of ``post.relabel``.
    bounds, choices : mapping
        Allowed ranges of numeric parameters, allowed values of string parameters.
    applies_with : mapping
        Parameters that only mean something when another (string) parameter has one value:
        ``{"opening_factor": ("method", "alpha_opening")}``. A rule file that gives such a
        parameter without that value is refused when it is loaded.
    """

    def wrap(func: Callable) -> Predicate:
        return make_predicate(func, name=name or getattr(func, "__name__", ""), unit=unit, value_range=value_range,
                              needs_ground=needs_ground or needs_ground_model, bounds=bounds or {},
                              choices=choices or {}, origin=getattr(func, "__module__", "?"),
                              needs_ground_model=needs_ground_model, applies_with=applies_with or {})

    return wrap


def make_predicate(func: Callable, *, name: str, unit: str, value_range, needs_ground: bool, bounds, choices,
                   origin: str, needs_ground_model: bool = False,
                   applies_with: Mapping[str, tuple[str, str]] | None = None) -> Predicate:
    """Check a function against the predicate contract and wrap it (raises PredicateError)."""
    where = f"predicate '{name}' ({origin})"
    if not isinstance(name, str) or not name.isidentifier():
        raise PredicateError(f"{where}: the name must be an identifier")
    if not callable(func):
        raise PredicateError(f"{where}: not callable")
    if unit not in UNITS:
        raise PredicateError(f"{where}: unknown unit {unit!r}; use one of {', '.join(UNITS)}")
    doc = inspect.getdoc(func) or ""
    if not doc.strip():
        raise PredicateError(f"{where}: a docstring saying what it measures is required")
    lo, hi = value_range
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
                     needs_ground_model=needs_ground_model)


# --- the registry ---------------------------------------------------------------------------


class PredicateRegistry:
    """Name -> :class:`Predicate`. Build one with :meth:`default`, then add plugins."""

    def __init__(self, predicates: Iterable[Predicate] = ()) -> None:
        self._items: dict[str, Predicate] = {}
        for p in predicates:
            self.add(p)

    @classmethod
    def default(cls, *, entry_points_too: bool = True) -> "PredicateRegistry":
        """The built-ins, plus the predicates of installed packages' ``kbs.predicates`` entry points."""
        reg = cls(BUILTINS)
        if entry_points_too:
            for ep in entry_points(group=ENTRY_POINT_GROUP):
                try:
                    obj = ep.load()
                except Exception as exc:  # a broken third-party package must say who it is
                    raise PredicateError(f"entry point '{ep.name}' ({ep.value}) failed to load: {exc}") from exc
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

    def add_object(self, obj: Any, origin: str) -> int:
        """Add a Predicate, or every Predicate found in a module; returns how many."""
        if isinstance(obj, Predicate):
            self.add(obj)
            return 1
        if isinstance(obj, ModuleType):
            found = [v for v in vars(obj).values() if isinstance(v, Predicate)]
            if not found:
                raise PredicateError(f"{origin}: no predicate found (declare them with @kbs.knowledge.predicate)")
            for p in found:
                self.add(p)
            return len(found)
        raise PredicateError(f"{origin}: expected a predicate or a module of predicates, got {type(obj).__name__}")

    def add_plugin_file(self, path: str | Path) -> int:
        """Import a Python file and add the predicates it declares."""
        path = Path(path)
        if not path.is_file():
            raise PredicateError(f"{path}: plugin file not found")
        mod_name = f"kbs_plugin_{abs(hash(str(path.resolve())))}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise PredicateError(f"{path}: not an importable Python file")
        module = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = module
        try:
            spec.loader.exec_module(module)
        except PredicateError as exc:
            raise PredicateError(f"{path}: {exc}") from exc
        except Exception as exc:
            raise PredicateError(f"{path}: the plugin failed to import: {type(exc).__name__}: {exc}") from exc
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


def did_you_mean(name: str, candidates: Iterable[str]) -> str | None:
    hits = difflib.get_close_matches(str(name), list(candidates), n=1, cutoff=0.6)
    return hits[0] if hits else None


# --- built-in predicates --------------------------------------------------------------------


@predicate(unit="length", value_range=(0.0, None))
def thickness(cluster: Cluster, scene: Scene) -> float:
    """Spread across the best approximating plane: sqrt(mu1), the square root of the smallest
    eigenvalue of the fuzzy covariance (PAh measures this)."""
    return cluster.geometry.thickness


@predicate(unit="ratio", value_range=(0.0, 1.0))
def flatness(cluster: Cluster, scene: Scene) -> float:
    """sqrt(mu1 / mu2): the spread across the best approximating plane relative to the smaller
    spread along it; 0 for a sheet, 1 when the cluster is as thick as it is wide (a blob)."""
    mu = cluster.geometry.eigenvalues
    return float(np.sqrt(mu[0] / mu[1])) if mu[1] > 0 else 0.0


@predicate(unit="deg", value_range=(0.0, 90.0), needs_ground=True)
def ground_angle(cluster: Cluster, scene: Scene) -> float:
    """Angle in degrees between the cluster's best approximating plane and the ground plane
    (0 = parallel)."""
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


@predicate(unit="length", needs_ground=True, choices={"stat": ("max", "mean", "median", "min")})
def height_above_ground(cluster: Cluster, scene: Scene, *, stat: str = "max") -> float:
    """Height of the cluster's points above the ground plane (signed, along the ground normal):
    their max, mean, median or min."""
    h = scene.ground.height(cluster.X)
    return float({"max": np.max, "mean": np.mean, "median": np.median, "min": np.min}[stat](h))


@predicate(unit="length", value_range=(0.0, None), choices={"to": ("center", "nearest")})
def distance_to_sensor(cluster: Cluster, scene: Scene, *, to: str = "center") -> float:
    """Distance from the sensor to the cluster's fuzzy centre ('center') or to its nearest point
    ('nearest')."""
    if to == "center":
        return float(np.linalg.norm(cluster.geometry.center - scene.sensor))
    return float(np.sqrt(((cluster.X - scene.sensor) ** 2).sum(axis=1).min()))


_STATS = {"max": np.max, "p90": lambda h: np.percentile(h, 90), "mean": np.mean, "median": np.median,
          "p10": lambda h: np.percentile(h, 10), "min": np.min}


@predicate(unit="length", needs_ground_model=True, choices={"stat": tuple(_STATS)})
def height_above_local_ground(cluster: Cluster, scene: Scene, *, stat: str = "p90", exclude_self: bool = False) -> float:
    """Height of the cluster's points above the local ground surface (the median height of the
    nearest points of the clusters labelled ground, see post.ground_model), along the ground
    normal: their max, 90th percentile, mean, median, 10th percentile or min, over the points
    with ground within the model's radius (above the ground plane when none has). With
    exclude_self, the cluster's own points are not part of the surface: a ground cluster is
    compared with the ground around it (a roof stands high above it); a point counts then only if
    other clusters' points are among its (8 x the model's neighbours) nearest surface points. Usable in post.relabel
    conditions only (the surface exists once clusters are labelled)."""
    h = scene.ground_model.height(cluster.X, cluster.id if exclude_self else None)
    known = ~np.isnan(h)
    h = h[known] if known.any() else scene.ground.height(cluster.X)
    return float(_STATS[stat](h))


BUILTINS: tuple[Predicate, ...] = (thickness, flatness, ground_angle, connexity, point_count, extent, height_above_ground,
                                   distance_to_sensor, height_above_local_ground)
