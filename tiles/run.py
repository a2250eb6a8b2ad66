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

import contextlib
import dataclasses
import functools
import itertools
import logging
import os
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import ExitCode, KbsError, ParameterError, raise_if_interrupted
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.interpreter import Segmentation, available_cores
from kbs.knowledge.segmenter import Segmenter, as_points
from kbs.tiles.grid import Tile, TileGrid
from kbs.tiles.stitch import TiledSegmentation, stitch
from kbs.tiles.store import TileStore

#: The ground plane of a tiled run is found once, on the whole cloud, or on every k-th point of it
#: when it holds more than this many points (the same plane for every tile: no tile finds its own).
GROUND_SAMPLE_POINTS = 2_000_000
#: Tiles submitted to Dask at a time, per worker (more are submitted as these finish).
IN_FLIGHT_PER_WORKER = 2
#: The buffer, when none is given, is this fraction of the tile size ...
BUFFER_FRACTION = 0.1
#: ... and at least this many times the radius of the rule base's local ground surface.
BUFFER_GROUND_RADII = 2.0


class TileError(KbsError):
    """Tiles could not be segmented; the message names the first with its bounds, and how many
    failed. The exit code is the cause's (a :class:`~kbs.errors.FitError` in a tile exits 5, as it
    would untiled).

    Attributes
    ----------
    tile : Tile
        The first tile that failed (in tile order).
    cause : BaseException
        Its error.
    failed : list of Tile
        Every tile that failed.
    kept : Path or None
        The folder holding the tiles that were finished (a :class:`~kbs.tiles.store.TileStore`'s).
    """

    def __init__(self, tile: Tile, n_points: int, cause: BaseException, *, failed: Sequence[Tile] = (),
                 kept: Path | None = None, total: int | None = None) -> None:
        self.tile, self.cause = tile, cause
        self.failed, self.kept = list(failed) or [tile], kept
        self.exit_code = getattr(cause, "exit_code", ExitCode.INTERNAL)
        what = str(cause) if isinstance(cause, KbsError) else f"{type(cause).__name__}: {cause}"
        more = ""
        if len(self.failed) > 1:
            more = (f"; {len(self.failed)} of {total} tiles failed: "
                    f"{', '.join(t.bounds_text() for t in self.failed)}")
        kept_text = ""
        if kept is not None:
            kept_text = (f"; the finished tiles are kept in {kept}: run again with --resume (resume=True) to "
                         f"segment only the failed ones")
        super().__init__(f"tile {tile.bounds_text()} ({n_points:,} points): {what}{more}{kept_text}")


@contextlib.contextmanager
def noting_kept_tiles(folder: Path | None, any_kept: Callable[[], bool]) -> Iterator[None]:
    """Interrupted (Ctrl-C, SIGTERM) inside the block once a tile is saved (``any_kept()``), the
    KeyboardInterrupt says where the finished tiles are kept (``folder``, the store's)."""
    try:
        yield
    except KeyboardInterrupt as exc:
        if folder is not None and any_kept():
            exc.add_note(f"the finished tiles are kept in {folder}: run again with --resume (resume=True) to "
                         "segment only the others")
        raise


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


def scene_ground(segmenter: Segmenter, X: np.ndarray) -> tuple[Any, GroundFacts]:
    """The ground plane of the whole cloud ``X`` and its explanation (``ground`` of a result), as an
    untiled run finds it (:meth:`~kbs.knowledge.interpreter.Interpreter.find_ground`); on every k-th
    point when ``X`` holds more than :data:`GROUND_SAMPLE_POINTS`. Every tile takes it."""
    n = X.shape[0]
    step = ground_step(n)
    return sample_ground(segmenter, X[::step] if step > 1 else X, n)


def ground_step(n: int) -> int:
    """Every how many points of a cloud of ``n`` the ground plane is found on (:func:`scene_ground`)."""
    return max(1, -(-n // GROUND_SAMPLE_POINTS))


def sample_ground(segmenter: Segmenter, sample: np.ndarray, n: int) -> tuple[Any, GroundFacts]:
    """:func:`scene_ground` of a cloud of ``n`` points from its ``sample`` (every
    :func:`ground_step`-th point of it)."""
    step = ground_step(n)
    ground, facts = segmenter._interpreter.find_ground(sample)
    scope = (f"found once on the whole cloud ({n:,} points)" if step == 1 else
             f"found once on every {step}th point of the whole cloud ({-(-n // step):,} of {n:,})") + \
        ", the same for every tile"
    source = f"whole cloud: {facts.source}" if facts.source is not None else None
    return ground, dataclasses.replace(facts, source=source, scope=scope)


def segment_tiled(segmenter: Segmenter, points: Any, size: float, buffer: float | None = None, *,
                  scheduler: str | None = None, workers: int | None = None,
                  progress: Callable[[str], None] | None = None, store: TileStore | None = None,
                  resume: bool = False, plan: tuple[TileGrid, list[Tile]] | None = None) -> TiledSegmentation:
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
    store : TileStore, optional
        Where each finished tile is saved as soon as it is done (kept when others fail).
    resume : bool, default False
        Take the tiles ``store`` holds for these points, rule base and sensor instead of
        segmenting them again; segment only the others.
    plan : (TileGrid, list of Tile), optional
        The grid and tiles of ``points`` when they are known already (a streamed LAS/LAZ file:
        :func:`kbs.tiles.stream.spill_las`); default :func:`plan_tiles`.

    Returns
    -------
    TiledSegmentation
        As :meth:`Segmenter.segment`, stitched (:func:`kbs.tiles.stitch.stitch`), with ``tiling``.

    Raises
    ------
    ParameterError
        Bad points, size, buffer or workers; Dask missing for a scheduler.
    TileError
        Tiles failed (the first one's bounds in the message, the cause's exit code), after every
        other tile was segmented (and saved in ``store``).
    """
    t0 = time.perf_counter()
    X = points if plan is not None else as_points(points)
    warn_spacing(segmenter, X)
    grid, tiles = plan if plan is not None else plan_tiles(segmenter, X, size, buffer)
    given = scene_ground(segmenter, X)
    keys = [store.key(t, X, given) for t in tiles] if store is not None else [None] * len(tiles)
    results: list[Segmentation | None] = [None] * len(tiles)
    if resume and store is not None:
        for k, t in enumerate(tiles):
            results[k] = store.load(t, keys[k])
        if progress is not None:
            progress(f"resumed {sum(r is not None for r in results)} of {len(tiles)} tiles from {store.folder}")
    todo = [k for k, r in enumerate(results) if r is None]
    failures: dict[int, BaseException] = {}

    def finished(k: int, out: Segmentation | BaseException, done: int) -> None:
        if isinstance(out, BaseException):
            failures[k] = out
            return
        results[k] = out
        if store is not None:
            store.save(tiles[k], keys[k], out)
        if progress is not None:
            progress(f"{tiles[k].name} ({done}/{len(todo)} tiles)")

    with noting_kept_tiles(store.folder if store is not None else None, lambda: any(r is not None for r in results)):
        if scheduler is None:
            for done, k in enumerate(todo, start=1):
                try:
                    out: Segmentation | BaseException = _segment_tile(segmenter, X[tiles[k].index], given)
                except KbsError as exc:
                    out = exc
                finished(k, out, done)
        elif todo:
            _segment_on_dask(segmenter, X, tiles, todo, scheduler, workers, progress, finished, given)
    if failures:
        first = min(failures)
        raise TileError(tiles[first], tiles[first].index.size, failures[first],
                        failed=[tiles[k] for k in sorted(failures)], total=len(tiles),
                        kept=store.folder if store is not None and len(failures) < len(tiles) else None)
    return stitch(X, grid, tiles, results, seconds=time.perf_counter() - t0, ground=given[1])


@functools.lru_cache(maxsize=4)
def worker_segmenter(rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...]) -> Segmenter:
    """The segmenter of a Dask worker process: loaded at its first tile, kept for the next ones."""
    return Segmenter(rules, jobs=1, sensor=sensor, plugins=plugins)


def warn_spacing(segmenter: Segmenter, X: np.ndarray) -> None:
    """Warn once, for the whole cloud, when its point spacing does not fit the rule base (a
    :class:`kbs.units.SpacingWarning`, as :meth:`Segmenter.segment` warns of an untiled cloud). The
    tiles do not warn: a tile at the cloud's edge may be sparse where the cloud is not, and a cloud
    in the wrong unit would warn once per tile."""
    from kbs.geometry.nearest import nearest_other_distances
    from kbs.units import check_spacing

    target = segmenter.length_unit
    if target is None or len(X) == 0:
        return
    rb = segmenter.rule_base
    problem = check_spacing(X, scan=None, target=target, declared=rb.spacing, rule_base=rb.name,
                            nearest_other=nearest_other_distances)
    if problem is not None:
        warnings.warn(problem, stacklevel=3)


def _segment_tile(segmenter: Segmenter, points: np.ndarray, given: tuple[Any, GroundFacts]) -> Segmentation:
    """One tile, with the whole cloud's ground plane ``given`` (:func:`scene_ground`); its
    spacing is not judged (:func:`warn_spacing` judged the whole cloud's)."""
    from kbs.units import SpacingWarning

    interpreter = segmenter._interpreter
    interpreter.given_ground = given
    segmenter._judge_spacing = False  # not measured: its warning would be ignored
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SpacingWarning)
            return segmenter.segment(points)
    finally:
        interpreter.given_ground = None
        segmenter._judge_spacing = True


def segment_task(rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...],
                 points: np.ndarray, given: tuple[Any, GroundFacts]) -> Segmentation | KbsError:
    """One tile on a Dask worker. A KbsError is returned, not raised: Dask retries what raises
    (a worker lost), and a bad tile would fail the same way again."""
    try:
        return _segment_tile(worker_segmenter(rules, sensor, plugins), points, given)
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
        n = min(n, available_cores())  # a local cluster of more workers than cores runs no faster
        # silence_logs: the workers' own log lines (a heartbeat missed while the cluster shuts down,
        # with its traceback) are not the user's news; a failed tile comes back as its error
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=logging.CRITICAL)
        return Client(cluster)
    try:
        return Client(scheduler, timeout="5s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(f"no Dask scheduler answers at {scheduler!r} ({type(exc).__name__}: {exc}); start one "
                             f"(dask scheduler) or give 'local' for a LocalCluster on this machine") from exc


def _segment_on_dask(segmenter: Segmenter, X: np.ndarray, tiles: Sequence[Tile], todo: Sequence[int],
                     scheduler: str, workers: int | None, progress: Callable[[str], None] | None,
                     finished: Callable[[int, Any, int], None], given: tuple[Any, GroundFacts]) -> None:
    spec = (segmenter.rule_base.path, segmenter.sensor, segmenter.plugins)
    submit_all(scheduler, workers, progress, finished, todo,
                lambda k: (segment_task, *spec, X[tiles[k].index], given), [t.name for t in tiles])


def submit_all(scheduler: str, workers: int | None, progress: Callable[[str], None] | None,
               finished: Callable[[int, Any, int], None], todo: Sequence[int],
               task_of: Callable[[int], tuple[Any, ...]], names: Sequence[str]) -> None:
    """Run the tasks ``task_of(k)`` (a function and its arguments) for ``k`` in ``todo`` on Dask,
    a bounded number in flight; ``finished(k, result or exception, done)`` as each ends."""
    from distributed import as_completed

    client = dask_client(scheduler, workers)
    try:
        if progress is not None:
            progress(f"Dask dashboard: {client.dashboard_link}")

        def submit(k: int) -> Any:
            fn, *args = task_of(k)
            future = client.submit(fn, *args, retries=1, pure=False, key=f"kbs-tile-{names[k]}-{os.urandom(6).hex()}")
            futures[future] = k
            return future

        # a bounded number of tiles in flight (a task's arguments are made when it is submitted):
        # the client holds those of these tiles, not of the whole cloud
        n_workers = max(len(client.scheduler_info().get("workers", {})), workers or 1 if scheduler == "local" else 1)
        window = max(2, IN_FLIGHT_PER_WORKER * n_workers)
        futures: dict[Any, int] = {}
        queue = iter(todo)  # not a list popped from its front: that moved the whole list at each task
        pending = as_completed([submit(k) for k in itertools.islice(queue, window)])
        for done, future in enumerate(pending, start=1):
            try:
                out = future.result()
            except Exception as exc:  # the task died twice (a worker lost), or a bug in it
                raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
                out = exc
            k = futures.pop(future)
            future.release()
            following = next(queue, None)
            if following is not None:
                pending.add(submit(following))
            finished(k, out, done)
    finally:
        cluster = client.cluster if scheduler == "local" else None
        client.close()
        if cluster is not None:
            cluster.close()
