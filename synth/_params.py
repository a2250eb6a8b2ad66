"""Parameter checks and wording shared by the scene generators."""
from __future__ import annotations

from typing import Any

from kbs.errors import ParameterError
from kbs.inference import Interval


def check_pair(owner: str, name: str, value: Any, kind: type, low: float, high: float | None) -> tuple:
    """Return ``value`` as a pair of numbers of ``kind`` (``numbers.Integral`` or ``numbers.Real``)
    in the open range ``(low, high)`` (``high`` None: no upper bound), or raise
    :class:`ParameterError` in the scikit-learn wording."""
    try:
        pair = tuple(value)
    except TypeError:
        pair = ()
    iv = Interval(kind, low, high, closed="neither")
    if len(pair) != 2 or not all(iv.accepts(v) for v in pair):
        raise ParameterError(f"The {name!r} parameter of {owner} must be a pair of "
                             f"{iv.describe().replace('an int', 'ints').replace('a float', 'floats')}. "
                             f"Got {value!r} instead.")
    return pair


def count(n: int, one: str, many: str) -> str:
    """``"1 box"``, ``"3 boxes"``."""
    return f"{n} {one if n == 1 else many}"
