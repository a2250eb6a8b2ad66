"""Segmenting a cloud tile by tile: in this process, or as Dask tasks on a cluster.

>>> from kbs import Segmenter, segment_tiled
>>> seg = Segmenter("airborne", jobs=1)                                   # doctest: +SKIP
>>> out = segment_tiled(seg, X, size=60.0)                                # doctest: +SKIP
>>> out = segment_tiled(seg, X, size=60.0, scheduler="local", workers=2)  # doctest: +SKIP

Every tile is segmented alone (its core and its buffer) with the same rule base and sensor, so
its result does not depend on where or in which order it ran: the stitched result is the same,
byte for byte, in process and on any number of Dask workers.
"""
from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from kbs.errors import ExitCode, KbsError, ParameterError
from kbs.knowledge.interpreter import Segmentation
from kbs.knowledge.segmenter import Segmenter, as_points
from kbs.tiles.grid import Tile, TileGrid
from kbs.tiles.stitch import TiledSegmentation, stitch

#: The buffer, when none is given, is this fraction of the tile size ...
BUFFER_FRACTION = 0.1
#: ... and at least this many times the radius of the rule base's local ground surface.
BUFFER_GROUND_RADII = 2.0


class TileError(KbsError):
    """A tile could not be segmented; the message names it with its bounds. The exit code is the
    cause's (a :class:`~kbs.errors.FitError` in a tile exits 5, as it would untiled)."""

    def __init__(self, tile: Tile, n_points: int, cause: BaseException) -> None:
        self.tile = tile
        self.exit_code = getattr(cause, "exit_code", ExitCode.INTERNAL)
        what = str(cause) if isinstance(cause, KbsError) else f"{type(cause).__name__}: {cause}"
        super().__init__(f"tile {tile.bounds_text()} ({n_points:,} points): {what}")


class SchedulerError(ParameterError):
    """No Dask scheduler answers at the address given."""


def default_buffer(segmenter: Segmenter, size: float) -> float:
    """The buffer used when none is given: a tenth of the tile, and at least twice the radius of
    the local ground surface (``post.ground_model.radius``) so that the surface near a tile edge
    is built from the ground on both sides of it."""
    gm = segmenter.rule_base.ground_model
    return max(BUFFER_FRACTION * size, BUFFER_GROUND_RADII * gm.radius if gm is not None else 0.0)


def plan_tiles(segmenter: Segmenter, X: np.ndarray, size: float,
               buffer: float | None = None) -> tuple[TileGrid, list[Tile]]:
    """The grid and the tiles of ``X`` (n_points, 3): square in the ground plane (across the rule
    base's fixed ground normal, else x-y)."""
    buffer = default_buffer(segmenter, size) if buffer is None else buffer
    grid = TileGrid.fit(X, size, buffer, segmenter.rule_base.ground.normal)
    return grid, grid.tiles(X)


def segment_tiled(segmenter: Segmenter, points: Any, size: float, buffer: float | None = None, *,
                  scheduler: str | None = None, workers: int | None = None,
                  progress: Callable[[str], None] | None = None) -> TiledSegmentation:
    """Segment a cloud tile by tile and stitch the tiles' results into one.

    Parameters
    ----------
    segmenter : Segmenter
        The loaded rule base (and sensor) every tile is segmented with.
    points : array-like, shape (n_points, 3)
    size : float
        Side of the square tiles, in the cloud's units.
    buffer : float, optional
        How far beyond its core each tile reaches (default :func:`default_buffer`).
    scheduler : str, optional
        None: the tiles one after the other in this process (the segmenter's ``jobs`` compute the
        splits). ``"local"``: a Dask ``LocalCluster`` of ``workers`` processes (default one per
        core) started for this call. Anything else: the address of a running Dask scheduler
        (``tcp://host:8786``); its workers need kbs installed and the rule file (and plugins) at
        the same path.
    workers : int, optional
        Workers of the ``"local"`` cluster.
    progress : callable, optional
        Called with ``"t0_1 (1/9 tiles)"`` as each tile is done.

    Returns
    -------
    TiledSegmentation
        As :meth:`Segmenter.segment`, stitched (:func:`kbs.tiles.stitch.stitch`), with ``tiling``.

    Raises
    ------
    ParameterError
        Bad points, size, buffer or workers; Dask missing for a scheduler.
    TileError
        A tile failed (its bounds in the message, the cause's exit code).
    """
    t0 = time.perf_counter()
    X = as_points(points)
    grid, tiles = plan_tiles(segmenter, X, size, buffer)
    if scheduler is None:
        results = []
        for k, t in enumerate(tiles):
            results.append(_segment_here(segmenter, X, t))
            if progress is not None:
                progress(f"{t.name} ({k + 1}/{len(tiles)} tiles)")
    else:
        results = _segment_on_dask(segmenter, X, tiles, scheduler, workers, progress)
    return stitch(X, grid, tiles, results, seconds=time.perf_counter() - t0)


def _segment_here(segmenter: Segmenter, X: np.ndarray, t: Tile) -> Segmentation:
    try:
        return segmenter.segment(X[t.index])
    except KbsError as exc:
        raise TileError(t, t.index.size, exc) from exc


@functools.lru_cache(maxsize=4)
def _worker_segmenter(rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...]) -> Segmenter:
    """The segmenter of a Dask worker process: loaded at its first tile, kept for the next ones."""
    return Segmenter(rules, jobs=1, sensor=sensor, plugins=plugins)


def _segment_task(rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...],
                  points: np.ndarray) -> Segmentation | KbsError:
    """One tile on a Dask worker. A KbsError is returned, not raised: Dask retries what raises
    (a worker lost), and a bad tile would fail the same way again."""
    try:
        return _worker_segmenter(rules, sensor, plugins).segment(points)
    except KbsError as exc:
        return exc


def dask_client(scheduler: str, workers: int | None = None):
    """A ``distributed.Client``: on a new ``LocalCluster`` (``"local"``) or at an address.

    Raises
    ------
    ParameterError
        Dask is not installed, or ``workers`` is not positive.
    SchedulerError
        No scheduler answers at the address.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ParameterError(f"a Dask scheduler needs dask.distributed ({exc}); install it with "
                             f"pip install 'kbs[dask]', or run in process without a scheduler") from exc
    if scheduler == "local":
        n = workers if workers is not None else (os.cpu_count() or 1)
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ParameterError(f"The 'workers' parameter must be a positive number of processes. Got {n!r} instead.")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0")
        return Client(cluster)
    try:
        return Client(scheduler, timeout="5s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(f"no Dask scheduler answers at {scheduler!r} ({type(exc).__name__}: {exc}); start one "
                             f"(dask scheduler) or give 'local' for a LocalCluster on this machine") from exc


def _segment_on_dask(segmenter: Segmenter, X: np.ndarray, tiles: Sequence[Tile], scheduler: str,
                     workers: int | None, progress: Callable[[str], None] | None) -> list[Segmentation]:
    from distributed import as_completed

    client = dask_client(scheduler, workers)
    try:
        if progress is not None:
            progress(f"Dask dashboard: {client.dashboard_link}")
        spec = (segmenter.rule_base.path, segmenter.sensor, segmenter.plugins)
        futures = [client.submit(_segment_task, *spec, X[t.index], key=f"kbs-tile-{t.name}-{os.urandom(6).hex()}",
                                 retries=1, pure=False) for t in tiles]
        position = {f.key: k for k, f in enumerate(futures)}
        results: list[Any] = [None] * len(tiles)
        for done, future in enumerate(as_completed(futures), start=1):
            k = position[future.key]
            try:
                out = future.result()
            except Exception as exc:  # the task died twice (a worker lost), or a bug in it
                raise TileError(tiles[k], tiles[k].index.size, exc) from exc
            if isinstance(out, KbsError):
                raise TileError(tiles[k], tiles[k].index.size, out)
            results[k] = out
            if progress is not None:
                progress(f"{tiles[k].name} ({done}/{len(tiles)} tiles)")
        return results
    finally:
        cluster = client.cluster if scheduler == "local" else None
        client.close()
        if cluster is not None:
            cluster.close()
