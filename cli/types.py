"""Click parameter types of the commands' options (no import beyond click: the commands' modules
are imported when they run, and this one with them)."""
from __future__ import annotations

import math
import os
from typing import Any

import click


class FiniteFloatRange(click.FloatRange):
    """``click.FloatRange`` for finite numbers only: NaN passes every comparison of a range (``nan
    > 0`` is False, so ``min_open`` does not catch it) and ``inf`` passes an open upper end, and
    either would run on as a silently wrong setting (a scene of infinite noise, no time limit)."""

    name = "float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):  # said before the range: 'inf is not in the range 0<=x<=10' hides why
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(value, param, ctx)


class PathArg(click.Path):
    """``click.Path`` that refuses an empty value: ``''`` is no file name (``pathlib.Path('')`` is
    the current folder, so ``kbs run ''`` would segment every scan there, and ``--out ''`` write
    into it); and, where a file is asked, a value ending with '/' (``pathlib`` drops the slash:
    ``synth abw --out sy/`` wrote ./sy.range)."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and not value.strip():
            self.fail(f"{value!r} is an empty path: give a file or folder name ('.' for the current folder).",
                      param, ctx)
        if isinstance(value, str) and not self.dir_okay and value.endswith(("/", os.sep)):  # 'out/' is no file name
            self.fail(f"{value!r} names a folder (it ends with '/'): give a file name.", param, ctx)
        return super().convert(value, param, ctx)
