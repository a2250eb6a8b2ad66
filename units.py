"""Length units of scans and rule bases: names, factors, where a file declares them, the point spacing.

A rule base writes every length threshold in its ``units:`` (``m``, ``cm``, ``mm``, ``km``, ``ft``,
``us-ft``; ``scan``: no unit, the scan's own numbers). A scan's unit comes from its file (the CRS
of a LAS/LAZ file, a ``units`` comment of a PLY or PCD header, E57's metres), from
``kbs run --units``, or is unknown. Before segmentation the points are scaled to the rule base's
unit (:func:`scale_factors`); the output points are the input's, unchanged.

>>> from kbs.units import unit, scale_factors
>>> unit("us-ft").metres                              # doctest: +ELLIPSIS
0.3048006096...
>>> scale_factors(ScanUnits.uniform("mm", source="--units"), unit("m"))
array([0.001, 0.001, 0.001])

The module is pure (numpy, and scipy for :func:`median_spacing` unless given a nearest-point function), so that the readers
(:mod:`kbs.io`) and the knowledge layer can both use it.
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from kbs.errors import ParameterError


@dataclass(frozen=True)
class LengthUnit:
    """A unit of length: a short name and its size in metres."""

    name: str
    metres: float

    def __str__(self) -> str:
        return self.name


#: The units kbs knows by name (``--units``, rule files, ``comment units`` lines).
UNITS: dict[str, LengthUnit] = {
    u.name: u for u in (
        LengthUnit("m", 1.0), LengthUnit("cm", 0.01), LengthUnit("mm", 0.001), LengthUnit("km", 1000.0),
        LengthUnit("ft", 0.3048), LengthUnit("us-ft", 1200.0 / 3937.0),
    )
}
#: Other spellings found in headers and CRS definitions (lower case, spaces and '_' as '-').
_ALIASES = {
    "metre": "m", "meter": "m", "metres": "m", "meters": "m",
    "centimetre": "cm", "centimeter": "cm", "centimetres": "cm", "centimeters": "cm",
    "millimetre": "mm", "millimeter": "mm", "millimetres": "mm", "millimeters": "mm",
    "kilometre": "km", "kilometer": "km", "kilometres": "km", "kilometers": "km",
    "foot": "ft", "feet": "ft", "international-foot": "ft", "international-feet": "ft", "intl-ft": "ft",
    "us-survey-foot": "us-ft", "us-survey-feet": "us-ft", "foot-us": "us-ft", "ftus": "us-ft", "us-foot": "us-ft",
    "survey-foot": "us-ft", "us-ft": "us-ft", "ft-us": "us-ft",
}
#: EPSG codes of linear units (GeoTIFF ProjLinearUnitsGeoKey, VerticalUnitsGeoKey).
EPSG_UNITS = {9001: "m", 9002: "ft", 9003: "us-ft", 9036: "km", 1033: "cm", 1025: "mm"}


def unit(name: str | LengthUnit) -> LengthUnit:
    """The unit named ``name`` (one of :data:`UNITS`, or a usual spelling: ``metre``, ``US survey foot``).

    Raises
    ------
    ParameterError
        An unknown name.
    """
    if isinstance(name, LengthUnit):
        return name
    key = re.sub(r"[\s_]+", "-", str(name).strip().lower())
    key = _ALIASES.get(key, key)
    if key not in UNITS:
        raise ParameterError(f"unknown length unit {name!r} (known: {', '.join(UNITS)})")
    return UNITS[key]


#: The sizes a unit of length may have, in metres: a nanometre to a million kilometres, far beyond
#: any survey's unit, and small enough that squares of coordinates scaled by them stay finite.
UNIT_METRES = (1e-9, 1e9)


def unit_from_metres(metres: float, name: str = "") -> LengthUnit:
    """The known unit of this size (within 1e-9 relative), else a unit named ``name`` of that size.

    Raises
    ------
    ParameterError
        ``metres`` is not a number between :data:`UNIT_METRES` (a CRS declaring a unit of 0, -1 or
        NaN metres: scaling by it would mirror, flatten or blank the cloud; 1e-300 m: its square,
        which scales variances, is 0).
    """
    lo, hi = UNIT_METRES
    if not (isinstance(metres, (int, float)) and lo <= metres <= hi):  # NaN fails both comparisons
        shown = f"'{name}' " if name else ""
        raise ParameterError(f"the unit of length {shown}is {metres!r} m: a unit must be a number of metres "
                             f"between {lo:g} and {hi:g}")
    for u in UNITS.values():
        if math.isclose(u.metres, metres, rel_tol=1e-9):
            return u
    return LengthUnit(name or f"{metres:g} m", float(metres))


@dataclass(frozen=True)
class ScanUnits:
    """The length units of a scan's coordinates.

    Attributes
    ----------
    horizontal : LengthUnit
        The unit of x and y.
    vertical : LengthUnit
        The unit of z (a compound CRS may give heights in another unit than x and y).
    source : str
        Where they come from, for messages and the result JSON ("the LAS file's CRS", "--units" ...).
    """

    horizontal: LengthUnit
    vertical: LengthUnit
    source: str

    @classmethod
    def uniform(cls, name: str | LengthUnit, *, source: str) -> ScanUnits:
        u = unit(name)
        return cls(u, u, source)

    @property
    def name(self) -> str:
        """``ft``, or ``m (z in ft)`` when z differs."""
        if self.vertical == self.horizontal:
            return self.horizontal.name
        return f"{self.horizontal.name} (z in {self.vertical.name})"

    def to_dict(self) -> dict[str, Any]:
        return {"horizontal": self.horizontal.name, "vertical": self.vertical.name,
                "metres": [self.horizontal.metres, self.horizontal.metres, self.vertical.metres], "source": self.source}


def scale_factors(scan: ScanUnits | None, target: LengthUnit | None) -> np.ndarray:
    """Per-axis factors (3,) that turn the scan's coordinates into ``target`` units (ones when
    either is unknown: nothing to convert)."""
    if scan is None or target is None:
        return np.ones(3)
    h, v = scan.horizontal.metres / target.metres, scan.vertical.metres / target.metres
    return np.array([h, h, v])


# -- units declared by files -----------------------------------------------------------------------


def parse_comment(text: str) -> tuple[str, str] | None:
    """``("units", "mm")`` or ``("crs", "EPSG:2992")`` for a header comment ``units mm`` or
    ``crs EPSG:2992`` (the keyword in any case, then the value; a ``:`` or ``=`` after the
    keyword is allowed), else None."""
    m = re.match(r"\s*(units|crs)\s*[:=]?\s+(.+?)\s*$", text, re.IGNORECASE)
    if not m:
        return None
    return m.group(1).lower(), m.group(2)


def units_from_comments(comments: list[str], kind: str) -> tuple[ScanUnits | None, str | None]:
    """The units and CRS a PLY or PCD header declares in its comments (:func:`parse_comment`).

    Returns
    -------
    (ScanUnits or None, str or None)
        The ``units`` comment (or the CRS's units, when it names them), and the ``crs`` text.

    Raises
    ------
    ParameterError
        A ``units`` comment names an unknown unit (the caller adds the file's name).
    """
    units_text: str | None = None
    crs: str | None = None
    for comment in comments:
        parsed = parse_comment(comment)
        if parsed is None:
            continue
        key, value = parsed
        if key == "units" and units_text is None:
            units_text = value
        elif key == "units" and units_text is not None and value.strip().lower() != units_text.strip().lower():
            raise ParameterError(f"the {kind} header's comments declare two units, 'units {units_text}' and "
                                 f"'units {value}': keep one")
        elif key == "crs" and crs is None:
            crs = value
    if units_text is not None:
        try:
            return ScanUnits.uniform(units_text, source=f"the {kind} header's 'units' comment"), crs
        except ParameterError as exc:
            raise ParameterError(f"the {kind} header's comment 'units {units_text}' names an unknown unit "
                                 f"(known: {', '.join(UNITS)})") from exc
    if crs is not None:
        return crs_units(crs, f"the {kind} header's 'crs' comment"), crs
    return None, None


def crs_units(text: str, source: str) -> ScanUnits | None:
    """The length units of a CRS given as text (WKT 1 or 2, ``EPSG:n``, PROJ, PROJJSON): with
    pyproj when it is installed, else from the WKT's UNIT / LENGTHUNIT nodes; None when they cannot
    be told (an EPSG code without pyproj, a geographic CRS in degrees)."""
    try:
        import pyproj
    except ImportError:
        return wkt_units(text, source)
    try:
        crs = pyproj.CRS.from_user_input(text)
    except Exception:  # noqa: BLE001 - pyproj.exceptions.CRSError and friends: not a CRS pyproj reads
        return wkt_units(text, source)
    return pyproj_units(crs, source)


def pyproj_units(crs: Any, source: str) -> ScanUnits | None:
    """The units of a ``pyproj.CRS``'s axes (east/north, then up); None for angular axes."""
    axes = list(crs.axis_info)
    for sub in getattr(crs, "sub_crs_list", None) or []:
        if not axes or len(axes) < 3:
            axes.extend(a for a in sub.axis_info if a not in axes)
    linear = [a for a in axes if (a.unit_name or "").lower() not in ("degree", "radian", "grad", "arc-second")
              and a.unit_conversion_factor is not None and a.direction.lower() not in ("geocentricx",)]
    if len(linear) < 2 or any((a.unit_name or "").lower().startswith(("degree", "radian")) for a in axes[:2]):
        return None
    h = unit_from_metres(linear[0].unit_conversion_factor, linear[0].unit_name)
    up = [a for a in linear if a.direction.lower() in ("up", "down")]
    v = unit_from_metres(up[0].unit_conversion_factor, up[0].unit_name) if up else h
    return ScanUnits(h, v, source)


def _wkt_tree(text: str) -> list[Any]:
    """A WKT string as nested ``[keyword, arg, ...]`` lists (strings unquoted, numbers as str)."""
    tokens = re.findall(r'"(?:[^"]|"")*"|[\[\]\(\),]|[^\[\]\(\),"\s]+', text)
    stack: list[list[Any]] = [["ROOT"]]
    last: Any = None
    for tok in tokens:
        if tok in "[(":
            node = [last]
            stack[-1].pop()  # the keyword was pushed as an argument: it becomes this node
            stack[-1].append(node)
            stack.append(node)
            last = None
        elif tok in "])":
            if len(stack) > 1:
                stack.pop()
        elif tok == ",":
            continue
        else:
            last = tok[1:-1].replace('""', '"') if tok.startswith('"') else tok
            stack[-1].append(last)
    return stack[0]


def _children(node: list[Any], *names: str) -> list[list[Any]]:
    return [c for c in node[1:] if isinstance(c, list) and str(c[0]).upper() in names]


def _unit_of(node: list[Any]) -> LengthUnit | None:
    """The linear unit directly in ``node`` (UNIT / LENGTHUNIT), or in its CS axes (WKT 2)."""
    units = _children(node, "UNIT", "LENGTHUNIT")
    for axis in _children(node, "AXIS"):
        units.extend(_children(axis, "UNIT", "LENGTHUNIT"))
    for u in units:
        try:
            metres = float(u[2])
        except (IndexError, ValueError):  # no factor, or not a number: not a unit node we can read
            continue
        return unit_from_metres(metres, str(u[1]))  # a factor of 0, -1 or NaN raises
    return None


def wkt_units(text: str, source: str) -> ScanUnits | None:
    """The units of a WKT CRS (1 or 2), read without pyproj: the projected CRS's linear unit for
    x and y, the vertical CRS's (if compound) for z; None for a geographic CRS or no WKT."""
    try:
        root = _wkt_tree(text)
    except Exception:  # noqa: BLE001 - anything that is not WKT
        return None
    top = [c for c in root[1:] if isinstance(c, list)]
    if not top:
        return None
    node = top[0]
    horizontal = vertical = None
    parts = _children(node, "PROJCS", "PROJCRS", "PROJECTEDCRS", "VERT_CS", "VERTCRS", "VERTICALCRS", "LOCAL_CS",
                      "ENGCRS", "ENGINEERINGCRS") if str(node[0]).upper() in ("COMPD_CS", "COMPOUNDCRS") else [node]
    for part in parts:
        kind = str(part[0]).upper()
        if kind in ("PROJCS", "PROJCRS", "PROJECTEDCRS", "LOCAL_CS", "ENGCRS", "ENGINEERINGCRS"):
            horizontal = horizontal or _unit_of(part)
        elif kind in ("VERT_CS", "VERTCRS", "VERTICALCRS"):
            vertical = vertical or _unit_of(part)
    if horizontal is None:
        return None
    return ScanUnits(horizontal, vertical or horizontal, source)


def geokey_units(keys: dict[int, int], source: str) -> ScanUnits | None:
    """Units from GeoTIFF keys (a LAS file's GeoKeyDirectory): ProjLinearUnitsGeoKey (3076) for x
    and y, VerticalUnitsGeoKey (4099) for z; None when the keys do not name a known unit."""
    h = EPSG_UNITS.get(keys.get(3076, -1))
    if h is None:
        return None
    v = EPSG_UNITS.get(keys.get(4099, -1), h)
    return ScanUnits(UNITS[h], UNITS[v], source)


# -- the point spacing -----------------------------------------------------------------------------

#: Points the spacing is estimated on: a seeded sample of a larger cloud, whose median
#: nearest-neighbour distance is scaled back by sqrt(sample / n) (a surface sampled n times has a
#: spacing that goes as 1/sqrt(n)). On the real scans of ../shared/data the estimate lies within
#: 0.5-1.05 of the exact median, and costs a few milliseconds: enough for a range that spans
#: orders of magnitude, cheap enough for every frame of a Segmenter.
SPACING_SAMPLE = 10_000
#: Median spacing a rule base accepts when it declares none (``scene.spacing``), in metres:
#: from a Kinect at arm's length (about 1 mm) to sparse airborne lidar (several metres).
DEFAULT_SPACING_METRES = (0.0005, 5.0)


def median_spacing(X: np.ndarray, *, seed: int = 0,
                   nearest_other: Callable[[np.ndarray], np.ndarray] | None = None) -> float | None:
    """An estimate of the median distance from a point to its nearest distinct neighbour (in X's
    units): exact up to :data:`SPACING_SAMPLE` points, from a seeded sample above (see there).
    Duplicated points count once. None when the cloud has fewer than 2 distinct points.

    Parameters
    ----------
    X : ndarray (n, 3)
    nearest_other : callable, optional
        Gives the distance from each row of an (m, 3) array of distinct rows to its nearest other
        row, as ``cKDTree(X).query(X, k=2)[0][:, 1]`` does (the default); the knowledge layer passes
        its compiled twin, :func:`kbs.geometry.nearest.nearest_other_distances` (the same values,
        without importing scipy's spatial package).
    """
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    if n > SPACING_SAMPLE:
        X = X[np.random.default_rng(seed).choice(n, SPACING_SAMPLE, replace=False)]
    X = _distinct_rows(X)
    if len(X) < 2:
        return None
    if nearest_other is None:
        from scipy.spatial import cKDTree

        d = cKDTree(X).query(X, k=2)[0][:, 1]
    else:
        d = nearest_other(X)
    spacing = float(np.median(d))
    if n > SPACING_SAMPLE:
        spacing *= math.sqrt(len(X) / n)
    return spacing


def _distinct_rows(X: np.ndarray) -> np.ndarray:
    """The distinct rows of ``X`` (n, 3), as ``np.unique(X, axis=0)`` (rows equal by value, in the
    order of x, then y, then z; which zero's sign stands for a row may differ): by a lexicographic
    sort and a comparison of neighbours, without np.unique's structured copy (10,000 rows: 5.5 ->
    2 ms). NaN rows: np.unique's own answer."""
    if X.ndim != 2 or X.shape[0] < 2 or not np.isfinite(X).all():
        return np.unique(X, axis=0)
    S = X[np.lexsort(X.T[::-1])]
    first = np.ones(S.shape[0], dtype=bool)
    first[1:] = (S[1:] != S[:-1]).any(axis=1)
    return S[first]


class CoordinateWarning(UserWarning):
    """A scan lies so far from the origin, for its size, that float64 no longer holds the
    precision the engine's sums need (see :func:`kbs.knowledge.segmenter.offset_problem`)."""


class SpacingWarning(UserWarning):
    """The median point spacing of a scan is outside the range its rule base expects: the units
    are probably wrong. Carries the numbers (``spacing``, ``expected``, ``unit``: the rule base's)."""

    def __init__(self, message: str, *, spacing: float, expected: tuple[float, float], unit: str,
                 suggested: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.spacing, self.expected, self.unit, self.suggested = spacing, expected, unit, suggested

    def to_dict(self) -> dict[str, Any]:
        return {"median_spacing": self.spacing, "expected": list(self.expected), "unit": self.unit,
                "plausible": False, "suggested_units": list(self.suggested), "note": str(self)}


def expected_spacing(declared: tuple[float, float] | None, target: LengthUnit) -> tuple[float, float]:
    """The spacing range a rule base expects, in its unit: what it declares, else the default."""
    if declared is not None:
        return declared
    lo, hi = DEFAULT_SPACING_METRES
    return (lo / target.metres, hi / target.metres)


def check_spacing(X: np.ndarray, *, scan: ScanUnits | None, target: LengthUnit, declared: tuple[float, float] | None,
                  rule_base: str, nearest_other: Callable[[np.ndarray], np.ndarray] | None = None) -> SpacingWarning | None:
    """A :class:`SpacingWarning` when the median spacing of ``X`` (already in ``target`` units)
    lies outside the range the rule base expects, else None (``nearest_other``: see
    :func:`median_spacing`)."""
    spacing = median_spacing(X, nearest_other=nearest_other)
    if spacing is None or spacing == 0:
        return None
    lo, hi = expected_spacing(declared, target)
    if lo <= spacing <= hi:
        return None
    raw = spacing / (scan.horizontal.metres / target.metres if scan is not None else 1.0)
    suggested = tuple(u.name for u in UNITS.values() if lo <= raw * u.metres / target.metres <= hi)
    where = "the rule base's spacing" if declared is not None else "kbs's default for rule bases that declare no spacing"
    if scan is None:
        why = (f"the scan declares no unit, so its numbers were taken as {target.name}; give its unit with --units "
               "(or a 'units' comment line in its PLY/PCD header)")
    else:
        why = f"its unit, {scan.name}, comes from {scan.source}; check it, or give --units"
    hint = f" (as {' or '.join(suggested)} it would fit)" if suggested else ""
    message = (f"median point spacing {spacing:.3g} {target.name} is outside {lo:g}-{hi:g} {target.name}, what rule base "
               f"'{rule_base}' expects ({where}): {why}{hint}")
    return SpacingWarning(message, spacing=spacing, expected=(lo, hi), unit=target.name, suggested=suggested)
