"""The one exception family for errors a user can cause, and the CLI exit codes.

Every error a user can trigger (a bad file, a bad parameter, a cloud the engine cannot fit) is a
:class:`KbsError`; the command line prints its message on one line and exits with its
:attr:`KbsError.exit_code`. Anything else escaping to the top is a bug.
"""
from __future__ import annotations

import enum
from collections.abc import Iterator


class ExitCode(enum.IntEnum):
    """Documented exit codes of the ``kbs`` command."""

    OK = 0
    INTERNAL = 1  #: a bug: an unexpected exception
    USAGE = 2  #: bad command-line usage or option value (click's own code for usage errors)
    CLOUD = 3  #: unreadable, malformed, empty or all-invalid input file (a cloud, a result)
    RULES = 4  #: invalid rule file
    FIT = 5  #: the engine could not fit the data (degenerate input)
    PARAMETER = 6  #: an invalid parameter value given through the library
    PLUGIN = 7  #: a predicate plugin that breaks the contract or fails
    MEMORY = 8  #: the machine ran out of memory (not a bug: a smaller tile, fewer jobs)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, a batch scheduler's notice) received by the ``kbs`` command: stops the
    run as Ctrl-C does (nothing half-written, the workers stopped), with exit code 143."""


def exception_chain(exc: BaseException | None) -> Iterator[BaseException]:
    """``exc``, then what caused it or was being handled when it arose, and so on (each once)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def interrupted(exc: BaseException | None) -> bool:
    """Whether ``exc`` is, or was caused by, a KeyboardInterrupt (Ctrl-C). A Ctrl-C that arrives while
    a compiled kernel runs comes out of the kernel's call as a SystemError ("returned a result with
    an exception set") whose cause is the KeyboardInterrupt: a wrapper that names a failed part must
    not report it as that part's failure, and a tiled run must not go on to the next tile."""
    return any(isinstance(e, KeyboardInterrupt) for e in exception_chain(exc))


def raise_if_interrupted(exc: BaseException) -> None:
    """Raise a KeyboardInterrupt (from ``exc``) when ``exc`` is a Ctrl-C (:func:`interrupted`): for a
    wrapper about to report ``exc`` as the failure of the part it wraps."""
    if interrupted(exc):
        raise KeyboardInterrupt from exc


class KbsError(Exception):
    """Base class of every error a user can cause."""

    exit_code: ExitCode = ExitCode.INTERNAL


class MissingExtra(KbsError, ImportError):
    """A feature needs an optional package that is not installed (``pip install 'kbs[EXTRA]'``);
    the command exits with the usage code, before any work."""

    exit_code = ExitCode.USAGE


def require(module: str, extra: str, feature: str):
    """Import ``module`` for ``feature``, or raise :class:`MissingExtra` naming the extra that
    installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(f"{feature} needs {module.split('.')[0]}, which is not installed: "
                           f"pip install 'kbs[{extra}]'") from exc


class ParameterError(KbsError, ValueError):
    """An invalid parameter value (also a ``ValueError``, as scikit-learn users expect)."""

    exit_code = ExitCode.PARAMETER


class CloudFileError(KbsError):
    """A point-cloud file that cannot be read, or holds no usable point.

    Parameters
    ----------
    path : str
        The file concerned.
    problem : str
        What is wrong with it, in a few words.
    """

    exit_code = ExitCode.CLOUD

    def __init__(self, path: str, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class FitError(KbsError, ArithmeticError, ValueError):
    """The engine could not fit the data (e.g. fewer distinct points than needed, every cluster
    died). The message says what to change. Also a ``ValueError``, as scikit-learn users expect
    for data an estimator cannot fit."""

    exit_code = ExitCode.FIT
