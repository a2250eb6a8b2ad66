"""kbs: knowledge-based partitioning of unorganised 3D point clouds.

The package is laid out as in the seed paper's architecture:

- :mod:`kbs.inference` -- the inference motor (fuzzy c-means, Gath-Geva, UFP-ONC, cluster geometry);
- :mod:`kbs.knowledge` -- rule bases, predicates, interpreter and explanations;
- :mod:`kbs.io` -- point-cloud readers and writers;
- :mod:`kbs.cli` -- the ``kbs`` command.

:class:`kbs.Segmenter` (from :mod:`kbs.knowledge`) segments clouds with a rule base loaded once;
:func:`kbs.segment_tiled` (from :mod:`kbs.tiles`) segments a large one tile by tile. Both are
imported on first use, so ``import kbs`` stays cheap.
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

__all__ = ["__version__", "KbsError", "CloudFileError", "ParameterError", "FitError", "ExitCode", "Segmenter", "segment_tiled"]


def __getattr__(name: str):
    """``kbs.Segmenter`` is imported when first used (it pulls in the engine: numpy, scipy, ...)."""
    if name == "Segmenter":
        from kbs.knowledge.segmenter import Segmenter

        return Segmenter
    if name == "segment_tiled":
        from kbs.tiles import segment_tiled

        return segment_tiled
    raise AttributeError(f"module 'kbs' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | {"Segmenter", "segment_tiled"})
