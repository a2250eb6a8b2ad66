"""Declarative parameter checks with one message template (after scikit-learn's
``_param_validation``): allowed values are data, the message says what was expected."""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Any

import numpy as np

from kbs.errors import ParameterError


@dataclass(frozen=True)
class Interval:
    """A real or integral range; ``closed`` is one of 'both', 'left', 'right', 'neither'."""

    kind: type  # numbers.Integral or numbers.Real
    low: float | None
    high: float | None
    closed: str = "both"

    def describe(self) -> str:
        what = "an int" if self.kind is numbers.Integral else "a float"
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        left = "[" if self.closed in ("both", "left") and self.low is not None else "("
        right = "]" if self.closed in ("both", "right") and self.high is not None else ")"
        return f"{what} in the range {left}{lo}, {hi}{right}"

    def accepts(self, value: Any) -> bool:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, self.kind):
            return False
        if isinstance(value, numbers.Real) and math.isnan(float(value)):
            return False
        if self.low is not None:
            if value < self.low or (value == self.low and self.closed in ("right", "neither")):
                return False
        if self.high is not None:
            if value > self.high or (value == self.high and self.closed in ("left", "neither")):
                return False
        return True


@dataclass(frozen=True)
class Options:
    """One of a fixed set of strings."""

    values: tuple[str, ...]

    def describe(self) -> str:
        return "a str among {" + ", ".join(repr(v) for v in self.values) + "}"

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str) and value in self.values


class ArrayLike:
    """Any array-like (checked further by the caller)."""

    def describe(self) -> str:
        return "an array-like"

    def accepts(self, value: Any) -> bool:
        return isinstance(value, (np.ndarray, list, tuple))


class RandomStateLike:
    """A ``numpy.random.RandomState`` instance."""

    def describe(self) -> str:
        return "a numpy RandomState"

    def accepts(self, value: Any) -> bool:
        return isinstance(value, np.random.RandomState)


class NoneValue:
    def describe(self) -> str:
        return "None"

    def accepts(self, value: Any) -> bool:
        return value is None


def validate_params(owner: str, params: Mapping[str, Any], constraints: Mapping[str, list]) -> None:
    """Raise :class:`ParameterError` for the first parameter that fits none of its constraints.

    The message reads: "The 'tol' parameter of GathGeva must be a float in the range [0, inf).
    Got -1 instead."
    """
    try:  # the same settings again (a split tree calls ufp_onc hundreds of times): checked once
        key = (owner, id(constraints), tuple((k, type(v), v) for k, v in params.items()))
        if key in _VALID:
            return
    except TypeError:  # an unhashable value: check it every time
        key = None
    for name, allowed in constraints.items():
        value = params[name]
        if any(c.accepts(value) for c in allowed):
            continue
        expected = " or ".join(c.describe() for c in allowed)
        raise ParameterError(f"The {name!r} parameter of {owner} must be {expected}. Got {value!r} instead.")
    if key is not None and len(_VALID) < 1024:
        _VALID.add(key)


#: settings already found valid (owner, constraints, values with their types)
_VALID: set = set()


def check_points(X: Any, *, owner: str, min_samples: int = 1) -> np.ndarray:
    """Return ``X`` as a C-contiguous float64 array of shape (n_samples, n_features).

    Raises :class:`ParameterError` for a wrong shape, too few points, or non-finite values.
    """
    try:
        arr = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{owner}: X must be a numeric array of shape (n_samples, n_features): {exc}") from exc
    if arr.ndim != 2:
        raise ParameterError(f"{owner}: X must be 2-D (n_samples, n_features); got shape {arr.shape}.")
    if arr.shape[0] < min_samples:
        raise ParameterError(f"{owner}: needs at least {min_samples} samples; got {arr.shape[0]}.")
    if arr.shape[1] < 1:
        raise ParameterError(f"{owner}: X has no feature column.")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise ParameterError(
            f"{owner}: X contains NaN or infinite values in {bad} rows; drop them first "
            "(kbs.io.read_cloud does so)."
        )
    return np.ascontiguousarray(arr)


def check_weights(sample_weight: Any, n_samples: int, *, owner: str) -> np.ndarray:
    """Return per-sample weights as float64 (n_samples,), all ones when ``None``."""
    if sample_weight is None:
        return np.ones(n_samples)
    w = np.asarray(sample_weight, dtype=np.float64)
    if w.shape != (n_samples,):
        raise ParameterError(f"{owner}: sample_weight must have shape ({n_samples},); got {w.shape}.")
    if not np.isfinite(w).all() or (w < 0).any():
        raise ParameterError(f"{owner}: sample_weight must be finite and non-negative.")
    if w.sum() <= 0:
        raise ParameterError(f"{owner}: sample_weight sums to zero.")
    return w
