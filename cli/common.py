"""Pieces shared by the commands: the cloud argument, progress, the output checks, result files."""
from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import time
from pathlib import Path
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, TextIO

import click

from kbs.cli.types import FiniteFloatRange, PathArg
import numpy as np

from kbs.errors import CloudFileError
from kbs.io import PointCloud
from kbs.io.atomic import temporary_path
from kbs.io.result import PLY_NAMES, write_result_cloud

if TYPE_CHECKING:
    from tqdm import tqdm

#: The CLOUD argument: existence and readability are checked by the reader, which says what is
#: wrong in one line with the file's name and exit code 3 (click's own checks, ``readable`` among
#: them, would exit with 2 and call a symbolic link loop a missing file).
cloud_argument = click.argument("cloud", type=PathArg(path_type=Path, readable=False))

#: Seconds between two progress lines on a stderr that is not a terminal (KBS_PROGRESS_SECONDS).
PROGRESS_SECONDS = 10.0

force_option = click.option("--force", is_flag=True,
                            help="Replace existing output files that kbs did not write (never an input file).")


def progress_interval() -> float:
    """Seconds between progress lines: ``KBS_PROGRESS_SECONDS`` if set, else :data:`PROGRESS_SECONDS`."""
    raw = os.environ.get("KBS_PROGRESS_SECONDS")
    if raw is None:
        return PROGRESS_SECONDS
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not value >= 0 or math.isinf(value):
        raise click.UsageError(f"KBS_PROGRESS_SECONDS must be a number of seconds >= 0, got {raw!r}")
    return value


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


class ProgressLines:
    """Progress for logs and pipes: called once per step, it prints ``kbs: NAME: STEPS, 56 s`` on
    stderr at most every :func:`progress_interval` seconds, when stderr is not a terminal and the
    command is not quiet (a terminal keeps its own display, if any).

    Parameters
    ----------
    name : str
        What is being worked on (the scan as given).
    steps : callable
        The count of steps so far -> its text (``lambda n: f"{n:,} splits"``).
    quiet : bool
        ``kbs -q``: print nothing.
    start : float, optional
        ``time.perf_counter()`` when the work started (default: now).
    """

    def __init__(self, name: str, steps: Callable[[int], str], *, quiet: bool, start: float | None = None,
                 stream: TextIO | None = None) -> None:
        self.name, self.steps = name, steps
        self.stream = sys.stderr if stream is None else stream
        self.enabled = not quiet and not _is_terminal(self.stream)
        self.interval = progress_interval() if self.enabled else math.inf
        self.start = time.perf_counter() if start is None else start
        self.last = self.start
        self.count = 0

    def __call__(self, *_: object) -> None:
        self.count += 1
        if not self.enabled:
            return
        now = time.perf_counter()
        if now - self.last >= self.interval:
            self.last = now
            print(f"kbs: {self.name}: {self.steps(self.count)}, {now - self.start:.0f} s", file=self.stream, flush=True)


@contextlib.contextmanager
def progress_bar(total: int, desc: str, quiet: bool) -> Iterator[tqdm]:
    """A tqdm bar on stderr, shown only on a terminal and when not quiet (tqdm is imported here:
    only `kbs cluster` draws one)."""
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, file=sys.stderr, disable=True if quiet else None, leave=False)
    try:
        yield bar
    finally:
        bar.close()


def check_writable_folder(folder: Path, *, create: bool, name: Path | None = None) -> list[Path]:
    """Make sure files can be created in ``folder`` before any work: create it if asked, then
    create and remove a probe file in it. Returns the folders it created, deepest first (for
    :func:`remove_if_empty` when the work fails).

    Raises
    ------
    CloudFileError
        Naming ``name`` (default ``folder``): the folder cannot be created, is a file, or does
        not accept new files (permission, read-only file system ...). Exit code 3.
    """
    what = folder if name is None else name
    created: list[Path] = []
    if create:
        missing = folder
        while not missing.exists() and not missing.is_symlink() and missing != missing.parent:
            created.append(missing)
            missing = missing.parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except FileExistsError as exc:
            raise CloudFileError(str(what), "cannot create the output directory: a file is in the way") from exc
        except OSError as exc:
            raise CloudFileError(str(what), f"cannot create the output directory: {exc.strerror or exc}") from exc
    probe = temporary_path(folder / "write-test")
    try:
        with open(probe, "xb"):
            pass
    except OSError as exc:
        where = " in the output directory" if name is None else ""
        raise CloudFileError(str(what), f"cannot write{where}: {exc.strerror or exc}") from exc
    finally:
        with contextlib.suppress(OSError):
            os.unlink(probe)
    return created


def remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders a failed command created (:func:`check_writable_folder`), deepest
    first, as long as they are empty: a run that wrote nothing leaves nothing behind, and one that
    wrote some results keeps them."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty (a result, another process's file), or gone
            return


def result_fields(cloud: PointCloud, results: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The per-vertex properties of a result PLY: the cloud's own fields under PLY-safe names
    (an input field named like a result is kept with the suffix '_in'), then ``results`` (the
    result fields ``cluster``, ``label``, ``membership`` under their PLY names ``scalar_cluster``
    ... that CloudCompare loads as scalar fields: :data:`kbs.io.result.PLY_NAMES`), then, for an
    organised input (a range image, an organised PCD), ``pixel`` (int32): each point's position
    in the row-major grid of ``cloud.shape``."""
    named = {PLY_NAMES.get(name, name): values for name, values in results.items()}
    taken = set(results) | set(named)
    fields = {}
    for name, values in cloud.fields.items():  # the input's own fields, under PLY-safe names
        safe = re.sub(r"\W", "_", name)
        if safe in taken:  # the input's own 'label' stays, as 'label_in'
            safe += "_in"
        if safe and safe not in taken and np.asarray(values).ndim == 1:
            fields[safe] = values
    fields.update(named)
    if cloud.shape is not None and "pixel" not in fields:  # organised input: where each point sits
        fields["pixel"] = cloud.index.astype(np.int32)
    return fields


def write_result_ply(path: Path, cloud: PointCloud, results: Mapping[str, np.ndarray], *,
                     run_id: str | None = None) -> str:
    """Write the cloud's points with its own fields and the per-point ``results`` to a PLY file
    (:func:`result_fields`), whole or not at all, with a kbs run id (returned) in its header."""
    return write_result_cloud(path, cloud.xyz, result_fields(cloud, results), run_id=run_id)


def setting_type(name: str) -> click.ParamType:
    """The click type of an engine setting, from its first allowed value kind in the table of
    :mod:`kbs.inference.settings` (an option cannot say None: a setting whose None means 'automatic'
    takes its other kind)."""
    import numbers

    from kbs.inference import Interval, Options
    from kbs.inference.settings import SETTINGS

    c = SETTINGS[name].allowed[0]
    if isinstance(c, Options):
        return click.Choice(list(c.values))
    if not isinstance(c, Interval):
        raise TypeError(f"no click type for {c!r}")
    lo_open, hi_open = c.closed in ("right", "neither"), c.closed in ("left", "neither")
    if c.kind is numbers.Integral:
        return click.IntRange(None if c.low is None else int(c.low), None if c.high is None else int(c.high),
                              min_open=lo_open, max_open=hi_open)
    return FiniteFloatRange(c.low, c.high, min_open=lo_open, max_open=hi_open)


def setting_option(flag: str, name: str, **kw: Any):
    """A click option for the engine setting ``name``: its type, default and help from the table."""
    from kbs.inference.settings import SETTINGS

    s = SETTINGS[name]
    return click.option(flag, name, type=setting_type(name), default=s.default, show_default=True, help=s.doc, **kw)
