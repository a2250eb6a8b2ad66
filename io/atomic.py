"""Files that appear whole or not at all: write to a temporary file beside the target, then rename.

>>> from kbs.io.atomic import replacing
>>> with replacing("out/scan.ply", "out/scan.json") as (ply, js):   # doctest: +SKIP
...     write_the_ply(ply)
...     write_the_json(js)

Inside the block the caller writes the temporary paths (in the targets' own folders, so that the
rename stays on one file system). When the block ends normally the temporary files are flushed to
disk and moved over the targets with :func:`os.replace`, one after the other, with Ctrl-C held
back until the last one is in place. When it ends with any exception (a full disk, a bad value,
``KeyboardInterrupt``) the temporary files are removed and the targets are left as they were: the
previous file, if any, stays intact. A process killed outright (SIGKILL, power loss) leaves at
most a hidden ``.<stem>.kbs-tmp-<hex><suffix>`` file beside the untouched target.
"""
from __future__ import annotations

import contextlib
import errno
import os
import signal
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

from kbs.errors import CloudFileError

#: Marks the temporary files (hidden, beside their target; the target's suffix kept last, so that
#: writers which infer the format from the name, such as matplotlib, still do).
TEMP_MARK = ".kbs-tmp-"


def temporary_path(target: Path) -> Path:
    """A fresh hidden name beside ``target``: ``.<stem>.kbs-tmp-<8 hex><suffix>``."""
    return target.with_name(f".{target.stem}{TEMP_MARK}{uuid.uuid4().hex[:8]}{target.suffix}")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make the renames durable; best effort (some file systems cannot sync a directory)."""
    with contextlib.suppress(OSError, AttributeError):
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def sigint_held() -> Iterator[None]:
    """Hold Ctrl-C back while the renames run (main thread only); re-raise it afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    except (ValueError, OSError):  # pragma: no cover - no signal handling here
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and previous is not signal.SIG_IGN:
            if callable(previous):
                previous(signal.SIGINT, None)  # Python's default handler raises KeyboardInterrupt
            else:
                raise KeyboardInterrupt


@contextlib.contextmanager
def replacing(*targets: str | os.PathLike[str]) -> Iterator[tuple[Path, ...]]:
    """Temporary paths to write, moved over ``targets`` together when the block succeeds.

    Parameters
    ----------
    *targets : str or os.PathLike
        The files to create or replace (their folders must exist).

    Yields
    ------
    tuple of Path
        One temporary path per target, in the same order, in the target's folder. Nothing
        exists at them yet: the caller creates them.

    Raises
    ------
    CloudFileError
        A temporary file cannot be flushed or renamed (the message names the target).
    """
    paths = [Path(os.fspath(t)) for t in targets]
    temps = tuple(temporary_path(p) for p in paths)
    try:
        yield temps
        for target, temp in zip(paths, temps):
            try:
                _fsync_file(temp)
            except FileNotFoundError as exc:  # the caller wrote nothing: a bug, not a user error
                raise RuntimeError(f"nothing was written for {target}") from exc
            except OSError as exc:
                raise CloudFileError(str(target), f"cannot write: {exc.strerror or exc}") from exc
        with sigint_held():
            for target, temp in zip(paths, temps):
                try:
                    os.replace(temp, target)
                except OSError as exc:
                    what = ("is a directory" if exc.errno in (errno.EISDIR, errno.ENOTEMPTY, errno.EEXIST)
                            and target.is_dir() else f"cannot write: {exc.strerror or exc}")
                    raise CloudFileError(str(target), what) from exc
        for folder in {p.parent for p in paths}:
            _fsync_dir(folder)
    finally:
        for temp in temps:
            with contextlib.suppress(OSError):
                os.unlink(temp)  # already renamed (FileNotFoundError) when all went well
