"""A segmenter that stays loaded: the rule base parsed and validated once, the interpreter built
once, then any number of clouds segmented with it, frame after frame.

>>> import numpy as np
>>> from kbs import Segmenter
>>> seg = Segmenter("outdoor")                       # doctest: +SKIP
>>> result = seg.segment(np.load("000001.points.npy"))  # doctest: +SKIP
>>> result.cluster, result.label, result.membership, result.label_names  # doctest: +SKIP

The result of :meth:`Segmenter.segment` is the :class:`~kbs.knowledge.interpreter.Segmentation`
``kbs run`` writes: the same arrays for the same points, whatever was segmented before.
"""
from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from kbs.arrays import finite_rows
from kbs.errors import ParameterError, raise_if_interrupted
from kbs.geometry.nearest import nearest_other_distances
from kbs.inference.voxel import bounds
from kbs.knowledge.interpreter import Interpreter, Segmentation
from kbs.knowledge.predicates import PredicateRegistry
from kbs.knowledge.rulebase import RuleBase, load_rule_base
from kbs.units import CoordinateWarning, LengthUnit, ScanUnits, check_spacing, scale_factors, unit


class Segmenter:
    """Segments point clouds with one rule base, loaded once and reused for every cloud.

    Parameters
    ----------
    rules : str, os.PathLike or RuleBase
        A shipped rule base name (``"outdoor"``, ``"airborne"``, ``"planar_contest"``; see
        :func:`~kbs.knowledge.rulebase.shipped_rule_bases`), the path of a rule file, or a rule
        base already loaded with :func:`~kbs.knowledge.rulebase.load_rule_base`.
    jobs : int, default 1
        Processes computing the UFP-ONC splits (1: everything in this process; -1: one per
        available core), as :class:`~kbs.knowledge.interpreter.Interpreter`. The result does not
        depend on it.
    sensor : array-like (3,), optional
        The sensor position, overriding the rule base's.
    plugins : iterable of str or os.PathLike, default ()
        Python files declaring extra predicates (as ``kbs run --plugin``), added to the default
        registry before the rule file is parsed. Only meaningful when ``rules`` is a name or a
        path: a loaded ``RuleBase`` already holds its predicates.

    Attributes
    ----------
    rule_base : RuleBase
        The validated rule base every cloud is segmented with.
    jobs : int
        As given (-1 stays -1).
    processes : int
        The number of processes ``jobs`` stands for: -1 resolved to the cores available, and at most
        that many.
    sensor : tuple of 3 float
        The sensor position used: ``sensor`` if given, else the rule base's.
    plugins : tuple of str
        The plugin files loaded.

    Raises
    ------
    RuleFileError
        The rule file is missing or invalid (every problem, positioned).
    PredicateError
        A plugin file is missing, fails to import or breaks the predicate contract.
    ParameterError
        ``jobs``, ``sensor``, ``rules`` or ``plugins`` is not a valid value.

    Examples
    --------
    >>> seg = Segmenter("outdoor", jobs=2)               # doctest: +SKIP
    >>> for frame in frames:                             # doctest: +SKIP
    ...     out = seg.segment(frame)                     # (n, 3) points
    ...     ground = frame[out.label == out.label_names.index("ground")]
    """

    def __init__(self, rules: str | os.PathLike[str] | RuleBase, *, jobs: int = 1, sensor: Any = None,
                 plugins: Iterable[str | os.PathLike[str]] = ()) -> None:
        self.jobs = _check_jobs(jobs)
        if isinstance(plugins, (str, os.PathLike)):
            raise ParameterError(f"plugins must be a list of plugin files, got the single path {plugins!r}; "
                                 f"pass [{os.fspath(plugins)!r}]")
        self.plugins: tuple[str, ...] = tuple(os.fspath(p) for p in plugins)
        if isinstance(rules, RuleBase):
            if self.plugins:
                raise ParameterError("plugins are used when a rule file is parsed; this rule base is already "
                                     "loaded: pass the rule file's name or path instead, or load it with "
                                     "load_rule_base(path, registry) using a registry holding the plugins")
            self.rule_base = rules
        elif isinstance(rules, (str, os.PathLike)):
            registry = PredicateRegistry.default()
            for p in self.plugins:
                registry.add_plugin_file(Path(p))
            self.rule_base = load_rule_base(os.fspath(rules), registry)
        else:
            raise ParameterError(f"rules must be a shipped rule base name, a rule file path or a RuleBase, "
                                 f"got {type(rules).__name__}")
        self.sensor: tuple[float, float, float] = (
            tuple(map(float, self.rule_base.sensor)) if sensor is None else _check_sensor(sensor))
        self._interpreter = Interpreter(self.rule_base, sensor=self.sensor, jobs=self.jobs)
        #: False while the tiles of a tiled run are segmented: the whole cloud's spacing was judged
        #: once, and a tile's is not (:func:`kbs.tiles.run.warn_spacing`), so it is not measured.
        self._judge_spacing = True

    @property
    def processes(self) -> int:
        """The number of processes ``jobs`` stands for: -1 resolved to the cores available, and at
        most that many."""
        return self._interpreter.jobs

    @property
    def label_names(self) -> list[str]:
        """The rule base's labels: ``label`` values index this list (-1 is noise)."""
        return self.rule_base.label_names

    @property
    def length_unit(self) -> LengthUnit | None:
        """The rule base's unit of length (``units:``), None for ``units: scan`` (no unit)."""
        return None if self.rule_base.units == "scan" else unit(self.rule_base.units)

    def scale(self, units: Any) -> np.ndarray:
        """Per-axis factors (3,) that turn coordinates in ``units`` into the rule base's unit
        (ones when either is unknown). ``units``: as :meth:`segment` takes it."""
        return scale_factors(as_scan_units(units), self.length_unit)

    def segment(self, points: Any, *, units: Any = None, sensor: Any = None,
                progress: Callable[[str], None] | None = None) -> Segmentation:
        """Segment one cloud.

        Parameters
        ----------
        points : array-like, shape (n_points, 3)
            Finite x y z coordinates, any real dtype (float32 and float64 give the same result
            once float32 is read as float64, as ``kbs run`` does). Drop other columns first
            (``points[:, :3]``) and non-finite points (``kbs.io.read_cloud`` does).
        units : str, LengthUnit or ScanUnits, optional
            The unit of ``points`` (``"mm"``, ``"ft"``; ``read_cloud(...).units`` where the file
            declares one). The points are scaled to the rule base's unit before segmenting (the
            arrays returned are per point, whatever the unit). None: the rule base's unit.
        sensor : array-like (3,), optional
            The sensor position for this cloud, in ``units`` and the cloud's frame; default: the
            segmenter's (in the rule base's unit).
        progress : callable, optional
            Called with a short message (``"c1.0 split in 3"``) after each split of this cloud,
            as :class:`~kbs.knowledge.interpreter.Interpreter`'s ``progress``.

        Returns
        -------
        Segmentation
            Per point ``cluster`` (n_points,) int32, ``label`` (n_points,) int32 (index into
            ``label_names``; -1 = noise) and ``membership`` (n_points,) float32, plus
            ``label_names``, the output ``clusters`` and the ``explanation`` tree (their lengths
            and positions in the rule base's unit).

        Warns
        -----
        SpacingWarning
            The median point spacing, in the rule base's unit, lies outside the range the rule
            base expects (its ``spacing``, or 0.5 mm to 5 m): the units are probably wrong.

        Raises
        ------
        ParameterError
            ``points`` is not a non-empty (n_points, 3) array of finite real numbers, or has a
            coordinate beyond :data:`MAX_COORDINATE` (once in the rule base's unit); an unknown unit.
        FitError
            The engine could not fit the data.
        KeyboardInterrupt
            Ctrl-C, wherever it arrived (inside a compiled kernel too).
        """
        X = as_points(points)
        scan_units = as_scan_units(units)
        f = scale_factors(scan_units, self.length_unit)
        if not np.array_equal(f, np.ones(3)):
            X = X * f
        problem = coordinate_problem(X)
        if problem is not None:
            raise ParameterError(f"points: {problem}")
        far = offset_problem(X, self.rule_base.length_unit or "")
        if far is not None:
            warnings.warn(CoordinateWarning(far), stacklevel=2)
        target = self.length_unit
        if target is not None and self._judge_spacing:
            problem = check_spacing(X, scan=scan_units, target=target, declared=self.rule_base.spacing,
                                    rule_base=self.rule_base.name, nearest_other=nearest_other_distances)
            if problem is not None:
                warnings.warn(problem, stacklevel=2)
        self._interpreter.progress = progress
        if sensor is not None:
            self._interpreter.sensor = np.asarray(_check_sensor(sensor), dtype=np.float64) * f
        try:
            return self._interpreter.run(X)
        except Exception as exc:
            raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
            raise
        finally:
            self._interpreter.progress = None
            self._interpreter.sensor = np.asarray(self.sensor, dtype=np.float64)

    def with_jobs(self, jobs: int) -> Segmenter:
        """A segmenter of the same rule base, sensor and plugins (nothing read again) with ``jobs``
        split processes of its own; this one is unchanged. ``kbs run`` gives one to each process
        that segments whole scans side by side."""
        other = object.__new__(Segmenter)
        other.jobs = _check_jobs(jobs)
        other.plugins, other.rule_base, other.sensor = self.plugins, self.rule_base, self.sensor
        other._interpreter = Interpreter(self.rule_base, sensor=self.sensor, jobs=other.jobs)
        other._judge_spacing = self._judge_spacing
        return other

    def close(self) -> None:
        """Stop the split worker processes (``jobs`` > 1); they are started once, at the first
        split, and kept frame after frame until then. Using the segmenter again restarts them."""
        self._interpreter.close()

    def __enter__(self) -> Segmenter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        rb = self.rule_base
        sensor = ", ".join(f"{v:g}" for v in self.sensor)
        plugins = f", plugins={list(self.plugins)}" if self.plugins else ""
        return (f"Segmenter(rule base '{rb.name}' from {rb.path}, {rb.strategy}, labels "
                f"{'/'.join(rb.label_names)}; jobs={self.jobs}, sensor=({sensor}){plugins})")


#: The largest coordinate magnitude (in the rule base's unit) the engine computes with. Its
#: covariances square the coordinates, and the norms and determinants of those reach their 6th
#: power: past about 1e51, float64 (at most 1.8e308) overflows there (a numpy overflow warning, then
#: infinite or undefined validity values, at 1e105 a crash in the voxel grid). 1e50 keeps each of
#: those products finite; no real scan comes near it (the Earth-centred frame is 6.4e6 m).
MAX_COORDINATE = 1e50


def coordinate_problem(X: np.ndarray) -> str | None:
    """Why the engine cannot segment points ``X`` (n, 3) (already in the rule base's unit): a
    coordinate beyond :data:`MAX_COORDINATE`; None when it can."""
    big = np.abs(X) > MAX_COORDINATE
    if not big.any():
        return None
    row = int(np.argmax(big.any(axis=1)))
    return (f"{int(big.any(axis=1).sum()):,} points have a coordinate beyond +-{MAX_COORDINATE:g} (first: row {row}, "
            f"{', '.join(f'{v:.3g}' for v in X[row])}): the engine's covariances square the coordinates and their "
            "determinants reach the 6th power, which overflows past that; check the file's scale and units (--units)")


#: A cloud farther from the origin than this many times its own extent is warned about: float64
#: keeps about 16 significant digits, so there a coordinate is known to 1e-16 of its size and the
#: sums of a cluster's coordinates (its centre, then its covariance around that centre) to about
#: sqrt(n) times that, which reaches the thickness of a plane. Measured on SemanticKITTI 000001
#: (extent 160 m) moved by 1e8, 1e9, 1e10 m along each axis: the labels of the scan at the
#: origin; moved by 1e11 m (6e8 times its extent), other trees; by 1e12 m, 12 % of the ground lost.
MAX_OFFSET_RATIO = 1e8


def offset_problem(X: np.ndarray, unit: str = "") -> str | None:
    """Why points ``X`` (n, 3) may not segment as they would near the origin: they lie more than
    :data:`MAX_OFFSET_RATIO` times their extent from it (None when they do not, or have no extent).
    A warning, not an error: the result is computed, with less precision than the file's."""
    if not X.shape[0]:
        return None
    lo, hi = bounds(X)
    extent = float((hi - lo).max())
    far = float(np.maximum(np.abs(lo), np.abs(hi)).max())
    if not extent > 0.0 or far <= MAX_OFFSET_RATIO * extent:
        return None
    u = f" {unit}" if unit else ""
    return (f"the points lie {far:.3g}{u} from the origin, {far / extent:.2g} times their extent ({extent:.3g}{u}): "
            f"there float64 holds a coordinate to about {far * 2.0 ** -52:.1g}{u} and the sums of a cluster's coordinates to "
            "less, so the result can differ from that of the same scan near the origin; subtract the offset first")


def as_scan_units(units: Any) -> ScanUnits | None:
    """``units`` (None, a unit name, a LengthUnit or ScanUnits) as ScanUnits, or None."""
    if units is None or isinstance(units, ScanUnits):
        return units
    if isinstance(units, (str, LengthUnit)):
        return ScanUnits.uniform(units, source="the units given")
    raise ParameterError(f"The 'units' parameter must be a unit name ('m', 'mm', 'ft', ...), a LengthUnit or "
                         f"ScanUnits. Got {units!r} instead.")


def segment(cloud: Any, rules: str | os.PathLike[str] | RuleBase, *, units: Any = None, sensor: Any = None,
            jobs: int = 1, plugins: Iterable[str | os.PathLike[str]] = (), format: str | None = None,  # noqa: A002
            progress: Callable[[str], None] | None = None) -> Segmentation:
    """Segment one cloud with a rule base, in one call.

    >>> import kbs
    >>> out = kbs.segment("examples/data/outdoor.ply", "outdoor")        # doctest: +SKIP
    >>> out.label_names, out.label, out.cluster                           # doctest: +SKIP

    Parameters
    ----------
    cloud : path, PointCloud or array-like (n_points, 3)
        A point-cloud file (any format :func:`kbs.io.read_cloud` reads), a cloud it returned, or
        the coordinates.
    rules : str, os.PathLike or RuleBase
        A shipped rule base name, a rule file, or a loaded rule base (as :class:`Segmenter`).
    units : optional
        The unit of the coordinates (as :meth:`Segmenter.segment`); default: the one the file
        declares (``PointCloud.units``), else the rule base's.
    sensor, jobs, plugins :
        As :class:`Segmenter` (``sensor`` in the cloud's units).
    format : str, optional
        Read ``cloud`` as this format (as ``read_cloud``).
    progress : callable, optional
        As :meth:`Segmenter.segment`.

    Returns
    -------
    Segmentation
        One value per point of the cloud (for a file: per point read, NaN/Inf points dropped).
    """
    if isinstance(cloud, (str, os.PathLike)):
        from kbs.io import read_cloud

        cloud = read_cloud(cloud, format=format)
    if hasattr(cloud, "xyz") and hasattr(cloud, "units"):
        points, units = cloud.xyz, units if units is not None else cloud.units
    else:
        points = cloud
    with Segmenter(rules, jobs=jobs, plugins=plugins) as segmenter:
        return segmenter.segment(points, units=units, sensor=sensor, progress=progress)


def as_points(points: Any) -> np.ndarray:
    """``points`` as a C-contiguous float64 (n_points, 3) array, checked.

    Parameters
    ----------
    points : array-like, shape (n_points, 3)

    Returns
    -------
    ndarray, shape (n_points, 3), float64
        ``points`` itself when it already is one (never modified), else a converted copy.

    Raises
    ------
    ParameterError
        Not a 2-D array of real numbers with 3 columns, no point, or a NaN/Inf coordinate.
    """
    try:
        X = np.asarray(points)
    except (ValueError, TypeError) as exc:
        raise ParameterError(f"points must be an (n_points, 3) array of coordinates: {exc}") from exc
    if X.dtype.kind not in "fiu":
        raise ParameterError(f"points must be real numbers (float32, float64, integers), got dtype {X.dtype}")
    if X.ndim != 2 or X.shape[1] != 3:
        hint = "; keep x y z only (points[:, :3])" if X.ndim == 2 and X.shape[1] > 3 else ""
        raise ParameterError(f"points must be an array of shape (n_points, 3), got shape {X.shape}{hint}")
    if X.shape[0] == 0:
        raise ParameterError("points holds no point: shape (0, 3)")
    X = np.ascontiguousarray(X, dtype=np.float64)
    finite = finite_rows(X)
    if not finite.all():
        bad = int(X.shape[0] - np.count_nonzero(finite))
        raise ParameterError(f"{bad:,} of the {X.shape[0]:,} points have a NaN or infinite coordinate (first: row "
                             f"{int(np.argmin(finite))}); drop them first: points[np.isfinite(points).all(axis=1)]")
    return X


def _check_jobs(jobs: Any) -> int:
    if isinstance(jobs, bool) or not isinstance(jobs, (int, np.integer)) or jobs == 0 or jobs < -1:
        raise ParameterError(f"The 'jobs' parameter of Segmenter must be a positive number of processes or -1 "
                             f"(one per available core). Got {jobs!r} instead.")
    return int(jobs)


def _check_sensor(sensor: Any) -> tuple[float, float, float]:
    try:
        v = np.asarray(sensor, dtype=np.float64)
    except (ValueError, TypeError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all() or (np.abs(v) > MAX_COORDINATE).any():
        raise ParameterError(f"The 'sensor' parameter of Segmenter must be three finite numbers (x, y, z), each within "
                             f"+-{MAX_COORDINATE:g} as the points are. Got {sensor!r} instead.")
    return (float(v[0]), float(v[1]), float(v[2]))
