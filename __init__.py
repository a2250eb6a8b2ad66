"""kbs: knowledge-based partitioning of unorganised 3D point clouds.

The package is laid out as in the seed paper's architecture:

- :mod:`kbs.inference` -- the inference motor (fuzzy c-means, Gath-Geva, UFP-ONC, cluster geometry);
- :mod:`kbs.knowledge` -- rule bases, predicates, interpreter and explanations;
- :mod:`kbs.io` -- point-cloud readers and writers;
- :mod:`kbs.cli` -- the ``kbs`` command.
"""
from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("kbs")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

from kbs.errors import (  # noqa: E402
    CloudFileError,
    ExitCode,
    FitError,
    KbsError,
    ParameterError,
)

__all__ = ["__version__", "KbsError", "CloudFileError", "ParameterError", "FitError", "ExitCode"]
