"""kbs: knowledge-based partitioning of unorganised 3D point clouds.

The package is laid out as in the seed paper's architecture:

- :mod:`kbs.inference` -- the inference motor (fuzzy c-means, Gath-Geva, UFP-ONC, cluster geometry);
- :mod:`kbs.knowledge` -- rule bases, predicates, interpreter and explanations;
- :mod:`kbs.io` -- point-cloud readers and writers;
- :mod:`kbs.cli` -- the ``kbs`` command.

:func:`kbs.segment` segments one cloud (a file, a :class:`~kbs.io.PointCloud` or an array) with a
rule base in one call; :class:`kbs.Segmenter` (from :mod:`kbs.knowledge`) segments clouds with a
rule base loaded once; :func:`kbs.segment_tiled` (from :mod:`kbs.tiles`) segments a
large one tile by tile. They are imported on first use, so ``import kbs`` stays cheap.

>>> import kbs
>>> out = kbs.segment("examples/data/outdoor.ply", "outdoor")     # doctest: +SKIP
>>> out.label_names, out.label, out.cluster                        # doctest: +SKIP
"""
from __future__ import annotations

from kbs.errors import (
    CloudFileError,
    ExitCode,
    FitError,
    KbsError,
    ParameterError,
)

__all__ = ["__version__", "segment", "Segmenter", "KbsError", "CloudFileError", "ParameterError", "FitError",
           "ExitCode", "segment_tiled"]
#: The sub-packages, importable as ``kbs.<name>`` (listed by ``dir(kbs)``).
_SUBPACKAGES = ("inference", "knowledge", "io", "cli", "evaluation", "synth", "report", "rules", "units", "errors", "maps", "tiles")


def __getattr__(name: str):
    """``kbs.segment`` and ``kbs.Segmenter`` are imported when first used (they pull in the
    engine: numpy, scipy, numba ...); ``kbs.__version__`` is read when first asked."""
    if name == "__version__":  # the package's metadata, read when first asked: importlib.metadata
        # costs 25-30 ms to import, a third of `kbs --help` (issue 9)
        import importlib.metadata

        try:
            version = importlib.metadata.version("kbs")
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover - running from a source tree
            version = "0+unknown"
        globals()["__version__"] = version
        return version
    if name in ("Segmenter", "segment"):
        from kbs.knowledge import segmenter

        return getattr(segmenter, name)
    if name == "segment_tiled":
        from kbs.tiles import segment_tiled

        return segment_tiled
    raise AttributeError(f"module 'kbs' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public names and the sub-packages: not what the package's own imports left behind."""
    return sorted({*__all__, *_SUBPACKAGES})
