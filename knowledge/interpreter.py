"""The interpreter: applies a rule base to clouds, frame after frame, keeping what a run may reuse
(the rule base, the sensor, the worker processes that compute UFP-ONC splits side by side).

What one run does is :mod:`kbs.knowledge.run` (partition, strategy, label, post steps, result);
the parts it is made of are tables of modules: :mod:`kbs.knowledge.strategies`,
:mod:`kbs.knowledge.actions`, :mod:`kbs.knowledge.post` (ARCHITECTURE.md).
"""
from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any, Self

import numpy as np

from kbs.arrays import rows
from kbs.errors import FitError, KbsError
from kbs.inference import UFPONCResult, ufp_onc
from kbs.knowledge.engine_settings import UFP_ONC_RULE_SETTINGS
from kbs.knowledge.explain import NO_LABEL, ClusterRecord
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.predicates import Cluster, Ground, Scene
from kbs.knowledge.rulebase import RuleBase
from kbs.knowledge.segmentation import STOP_KINDS, Segmentation, far_outliers
from kbs.knowledge.state import Draft, Judged, Node

__all__ = ["Interpreter", "Segmentation", "STOP_KINDS", "NO_LABEL", "segment", "available_cores"]


class Interpreter:
    """Applies a :class:`RuleBase` to clouds.

    Parameters
    ----------
    rule_base : RuleBase
    sensor : array-like (3,), optional
        Overrides the rule base's sensor position.
    progress : callable, optional
        Called with a short message after each decision.
    jobs : int
        Processes computing UFP-ONC splits (1: all in this process; -1: one per available core; at
        most one per available core: more would run no faster, and ``jobs=100000`` forked a
        hundred thousand processes). The splits of the first partition's clusters run side by
        side in them, then the whole subtree below each of those clusters' children (judged and
        divided) in one of them: a subtree depends on its points and the scene alone, so the
        result is identical whatever ``jobs`` is.
    """

    #: A ground plane found beforehand, with its explanation (:meth:`find_ground`): when set, every
    #: run takes it instead of finding its own (a tile takes the whole cloud's).
    given_ground: tuple[Ground | None, GroundFacts] | None = None

    def __init__(self, rule_base: RuleBase, *, sensor: Any = None,
                 progress: Callable[[str], None] | None = None, jobs: int = 1) -> None:
        self.rb = rule_base
        self.sensor = np.asarray(rule_base.sensor if sensor is None else sensor, dtype=np.float64)
        self.progress = progress
        if not isinstance(jobs, (int, np.integer)) or jobs == 0 or jobs < -1:
            raise ValueError(f"jobs must be a positive number of processes or -1 (one per core), got {jobs!r}")
        self.jobs = available_cores() if jobs == -1 else min(int(jobs), available_cores())
        self._pool: Any = None  # the ProcessPoolExecutor of the split workers, once started
        self._pool_finalizer: Any = None

    # -- worker processes ------------------------------------------------------------------------

    def _worker_pool(self):
        """The pool of split workers (``jobs`` > 1), started when first needed and kept until
        :meth:`close`, so that frame after frame reuses it."""
        pool = self._pool
        if pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from multiprocessing.util import Finalize

            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
            # the workers leave Ctrl-C to this process, which stops them (a worker interrupted
            # inside a compiled kernel or numba's finalizers printed its own traceback)
            _OWNERS[id(self)] = self  # what a forked worker finds this interpreter by (Subtrees)
            pool = self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx, initializer=_ignore_sigint)
            start_with_signals_blocked(pool)
            # stopped when this interpreter is collected or the process exits, before
            # multiprocessing joins its children (in a process that is itself a multiprocessing
            # child, that join comes first and would wait for ever on idle workers)
            self._pool_finalizer = Finalize(self, _shutdown_pool, args=(pool,), exitpriority=10)
        return pool

    @property
    def forks(self) -> bool:
        """Whether the worker processes are forked (they then hold this interpreter and can be
        given whole subtrees: :class:`Subtrees`); where they cannot be, they are given the splits
        alone."""
        import multiprocessing

        return "fork" in multiprocessing.get_all_start_methods()

    def start_workers(self) -> None:
        """Fork the split workers now (``jobs`` > 1), if they are not running: a run on a large
        cloud starts them before its first partition, so that they inherit the input only and
        not the partition's working arrays (which this process frees, but a worker forked after
        them would keep as its own: 0.65 GB per worker on 10^7 points)."""
        if self.jobs > 1 and self._pool is None:
            from concurrent.futures.process import BrokenProcessPool

            try:
                self._worker_pool().submit(int).result()  # forked workers start together, at the first task
            except BrokenProcessPool:  # one died at its start (killed): the splits are done here, a fresh pool later
                self.close()

    def close(self) -> None:
        """Stop the worker processes, if any were started (they start again when needed)."""
        fin = getattr(self, "_pool_finalizer", None)
        self._pool, self._pool_finalizer = None, None
        if fin is not None:
            fin()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- engine --------------------------------------------------------------------------------

    def _ufp_kwargs(self, stop: str, min_k: int = 1) -> dict[str, Any]:
        """ufp_onc's keywords: the rule file's engine settings that are ufp_onc's (the table of
        kbs.inference.settings says which), and the caller's ``stop`` and ``min_k``."""
        e = self.rb.engine
        return {**{s.name: e[s.name] for s in UFP_ONC_RULE_SETTINGS}, "stop": stop, "min_k": min_k}

    def _ufp_onc(self, X: np.ndarray, stop: str, min_k: int = 1) -> UFPONCResult:
        return ufp_onc(X, **self._ufp_kwargs(stop, min_k))

    # -- a run ---------------------------------------------------------------------------------

    def run(self, X: np.ndarray) -> Segmentation:
        """Segment points ``X`` (n, 3) (:func:`kbs.knowledge.run.run`). Far outliers
        (:func:`~kbs.knowledge.segmentation.far_outliers`) are set aside as noise first, and the
        explanation says so."""
        from kbs.knowledge import run

        X = np.asarray(X)
        far = far_outliers(X, self.rb.far_outliers)
        if far is None:
            return run.run(self, X)
        aside, side = far
        n, unit = int(aside.sum()), self.rb.length_unit
        first = X[np.flatnonzero(aside)[0]]
        note = (f"{n:,} point{'s' if n > 1 else ''} set aside as noise before the partition: more than "
                f"{self.rb.far_outliers:g} x {side:.4g} {unit} (the largest side of the box of the central 98 % of the "
                f"cloud) beyond that box, e.g. at {first[0]:.6g}, {first[1]:.6g}, {first[2]:.6g} (far outliers: "
                f"a glitch, a damaged record)")
        return run.run(self, rows(X, ~aside)).with_set_aside(aside, note)

    def finish(self, judged: Judged, t0: float) -> Segmentation:
        """Label the strategy's leaves, run the post steps, make the result
        (:func:`kbs.knowledge.run.finish`). ``kbs tune`` keeps ``judged`` to label it again."""
        from kbs.knowledge import run

        return run.finish(run.RunContext(self, judged.X), judged, t0)

    def find_ground(self, X: np.ndarray) -> tuple[Ground | None, GroundFacts]:
        """The ground plane a run on ``X`` (n, 3) finds, and its explanation's ``ground``, without
        the rest of the run: the root's UFP-ONC partition and the ground among its clusters (as
        :meth:`run` does, its far outliers set aside). A tiled run finds it once on the whole cloud
        and gives it to every tile (:attr:`given_ground`)."""
        from kbs.knowledge.ground import needs_candidates
        from kbs.knowledge.run import RunContext

        X = np.ascontiguousarray(X, dtype=np.float64)
        far = far_outliers(X, self.rb.far_outliers)
        if far is not None:  # as a run sets them aside
            X = np.ascontiguousarray(X[~far[0]])
        ctx = RunContext(self, X)
        if not needs_candidates(ctx):  # a fixed normal (airborne rules), or no ground: no partition to make
            return ctx.ground([])
        root = Node.root(X.shape[0])
        try:
            fixed_k = isinstance(self.rb.engine["initial_k"], int)
            res = self._ufp_onc(X, "k_max" if self.rb.strategy == "global" or fixed_k else "first_max")
        except FitError:
            child = Node("c0", "c", 1, root.idx, root.weight, root.path)
            return ctx.ground([ctx.record(child)])
        k0 = ctx.initial_k(res, [])
        u = res.memberships if k0 == res.chosen_k else res.partition(k0).predict_proba(X)
        del res
        return ctx.ground([ctx.record(c) for c in root.children(u)])


def segment(X: np.ndarray, rule_base: RuleBase, *, sensor: Any = None, jobs: int = 1) -> Segmentation:
    """Segment points ``X`` (n, 3) with a rule base (see :class:`Interpreter`)."""
    return Interpreter(rule_base, sensor=sensor, jobs=jobs).run(X)


# -- running the splits of a wave side by side -------------------------------------------------------


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, where the system tells)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _ignore_sigint() -> None:
    """A split worker's start: Ctrl-C is for the process that started it, and SIGTERM ends the worker
    (not the ``kbs`` command's handler, inherited through fork)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    unblock_stop_signals()  # a SIGTERM that came since the fork ends it now


#: the signals a worker is forked with blocked (:func:`start_with_signals_blocked`)
_STOP_SIGNALS = ("SIGINT", "SIGTERM")


def unblock_stop_signals() -> None:
    """The end of a worker's start (its own handlers set): SIGINT and SIGTERM, blocked while it was
    forked (:func:`start_with_signals_blocked`), are delivered again, one that came since at once."""
    import signal

    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [getattr(signal, s) for s in _STOP_SIGNALS])


def start_with_signals_blocked(pool) -> None:
    """Start ``pool``'s workers now (a pool of forked processes forks them all at its first task),
    with SIGINT and SIGTERM blocked while they are forked. A forked worker inherits this process's
    handlers (the ``kbs`` command's SIGTERM handler raises) until its start sets its own and calls
    :func:`unblock_stop_signals`: a SIGTERM in between raised inside multiprocessing's start-up
    and printed a traceback. Blocked, it waits for the worker's own handler, which ends the worker
    quietly; this process gets its signals once the workers are forked (microseconds later)."""
    import signal

    if not hasattr(signal, "pthread_sigmask"):
        pool.submit(int)
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, [getattr(signal, s) for s in _STOP_SIGNALS])
    try:
        pool.submit(int)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _shutdown_pool(pool) -> None:
    pool.shutdown(wait=True, cancel_futures=True)


_malloc_trim: Any = None


def _trim_heap() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``; nothing elsewhere)."""
    global _malloc_trim
    if _malloc_trim is None:
        import ctypes
        import ctypes.util

        try:
            _malloc_trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
            _malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError, TypeError):
            _malloc_trim = False
    if _malloc_trim:
        _malloc_trim(0)


#: a split worker trims its heap (:func:`_trim_heap`) before a split when its previous split had at
#: least this many points
TRIM_AFTER = 50_000
_last_split = 0  # in a worker: the points of its previous split


def _worker_split_job(X: np.ndarray, kwargs: dict[str, Any]) -> tuple[str, Any]:
    """:func:`_split_job` in a split worker. The arrays of a large split, freed, would stay in the
    worker's heap, kept for the next small splits (40-60 MB per worker on 10^7 airborne points), so the
    heap is trimmed after one; after every split, trimming cost a vehicle frame 5 % with -j 2 (the
    next split's arrays are taken from the system again)."""
    global _last_split
    if _last_split >= TRIM_AFTER:
        _trim_heap()
    _last_split = X.shape[0]
    return _split_job(X, kwargs)


def _split_job(X: np.ndarray, kwargs: dict[str, Any]) -> tuple[str, Any]:
    """In a worker: UFP-ONC on one cluster's points; a FitError travels back as its message."""
    try:
        return "ok", ufp_onc(X, **kwargs)
    except FitError as exc:
        return "error", str(exc)


class _Job:
    """A split under way: in a worker process (``future``) or not started yet (computed here, on
    demand, when ``jobs`` is 1)."""

    def __init__(self, X: np.ndarray, kwargs: dict[str, Any], future=None) -> None:
        self.X: np.ndarray | None = X
        self.kwargs, self.future = kwargs, future

    def result(self) -> UFPONCResult:
        X = self.X
        assert X is not None, "a split's result is taken once"
        if self.future is None:
            status, value = _split_job(X, self.kwargs)
        else:  # concurrent.futures.process imported only with workers (-j 1 does not load multiprocessing)
            from concurrent.futures.process import BrokenProcessPool

            try:
                status, value = self.future.result()
            except BrokenProcessPool:  # a worker died (killed, out of memory): do this split here
                status, value = _split_job(X, self.kwargs)
        self.X = self.future = None  # the points and the result are the caller's now: nothing kept here
        if status == "error":
            raise FitError(value)
        return value


#: the interpreters that started a pool of workers, by id: a forked worker holds a copy of this
#: table, so a task names its interpreter (rule base, engine settings) by the id alone
_OWNERS: weakref.WeakValueDictionary[int, Interpreter] = weakref.WeakValueDictionary()


class Subtrees:
    """The whole split trees below clusters (each judged, divided, its children judged ..., as
    :meth:`Divisive.waves <kbs.knowledge.strategies.divisive.Divisive.waves>` does), each in one
    of the interpreter's worker processes (:meth:`start`), then (:meth:`results`), per cluster in
    the order started, ``(node, records, kept)``: the records of its subtree by id (its own
    first), and the leaves it keeps, their nodes' ``idx`` into ``node``'s points. A subtree
    depends on the cluster's points and the scene alone (no max_clusters), so it is the same in
    any process. A worker that dies, or a subtree that fails in one, leaves it to this process.
    Leaving the block on an error cancels the subtrees not started, and on an interruption stops
    the workers."""

    def __init__(self, owner: Interpreter, scene: Scene) -> None:
        self.owner, self.scene = owner, scene
        self.started: list[tuple[Node, tuple, Any]] = []

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            for _, _, future in self.started:
                if future is not None:
                    future.cancel()
            if exc_type is not FitError and not issubclass(exc_type, KbsError):  # do not leave them running
                self.owner.close()

    def start(self, wave: list[tuple[Node, Cluster, Draft]]) -> None:
        from concurrent.futures.process import BrokenProcessPool

        for node, cl, draft in wave:
            task = (Node(node.id, node.parent, node.depth, np.arange(node.size), node.weight, node.path), cl, draft,
                    self.scene)
            try:
                future = self.owner._worker_pool().submit(_worker_subtree, id(self.owner), *task)
            except BrokenProcessPool:  # a worker died in an earlier wave or run: this process, fresh pool next
                self.owner.close()
                future = None
            self.started.append((node, task, future))

    def results(self) -> list[tuple[Node, list[tuple[str, ClusterRecord]], list[tuple[Node, Cluster, ClusterRecord]]]]:
        from concurrent.futures import as_completed
        from concurrent.futures.process import BrokenProcessPool

        trees: list[Any] = [None] * len(self.started)
        slot = {future: i for i, (_, _, future) in enumerate(self.started) if future is not None}
        for future in as_completed(slot):  # as they come: the progress of a long run is said as it goes
            i = slot[future]
            try:
                trees[i] = future.result()
            except BrokenProcessPool:  # a worker died (killed, out of memory): this process does it below
                continue
            if trees[i] is not None:
                self._said(trees[i][2])
                node = self.started[i][0]
                self.started[i] = (node, (), None)  # its cluster's points let go (240 MB in all at 10^7 points)
        out = []
        for i, (node, task, _) in enumerate(self.started):
            if trees[i] is None:  # not started, failed in the worker, or the worker died: this process does it
                trees[i] = _subtree(self.owner, *task)
                self._said(trees[i][2])
            records, kept, _ = trees[i]
            out.append((node, records, kept))
            trees[i] = None
        self.started = []
        return out

    def _said(self, messages: list[str]) -> None:
        if self.owner.progress:
            for message in messages:
                self.owner.progress(message)


def _worker_subtree(owner_id: int, node: Node, cl: Cluster, draft: Draft, scene: Scene):
    """:func:`_subtree` in a worker process (forked: the interpreter is its copy of the one that
    started the pool); None when it raised (a plugin's predicate failing, say): the subtree is
    then done again in the process that asked, which raises the same error itself (an exception
    does not always survive the trip back: one whose constructor takes other arguments than its
    message does not)."""
    try:
        return _subtree(_OWNERS[owner_id], node, cl, draft, scene)
    except Exception:  # noqa: BLE001 - raised again where it is done again
        return None


def _subtree(owner: Interpreter, node: Node, cl: Cluster, draft: Draft, scene: Scene):
    """The split tree below one cluster, in this process: (records, kept leaves, progress messages)."""
    from kbs.knowledge.run import RunContext
    from kbs.knowledge.strategies.divisive import Divisive

    said: list[str] = []

    class Subtree(RunContext):
        @property
        def progress(self) -> Callable[[str], None] | None:
            return said.append

    run = Subtree(owner, cl.X)
    records: dict[str, Draft] = {}
    kept: list[tuple[Node, Cluster, Draft]] = []
    with _Splitter(owner, owner._ufp_kwargs("first_max", owner.rb.engine["split_min_k"]), jobs=1) as splitter:
        run.splitter = splitter
        Divisive.waves(run, [(node, cl, draft)], scene, records, kept, n_clusters=0)
    return [(rid, d.record) for rid, d in records.items()], [(n, c, d.record) for n, c, d in kept], said


class _Splitter:
    """Starts the UFP-ONC splits of a wave: in the interpreter's pool of ``jobs`` worker
    processes (forked, so nothing is imported again; started at the first split and kept for
    the next runs, so a loaded segmenter does not fork again frame after frame), or lazily in
    this process when ``jobs`` is 1."""

    def __init__(self, owner: Interpreter, kwargs: dict[str, Any], jobs: int | None = None) -> None:
        self.owner, self.jobs, self.kwargs = owner, owner.jobs if jobs is None else jobs, kwargs
        self.jobs_started: list[_Job] = []

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:  # interrupted or failed: do not leave splits running for the next run
            for job in self.jobs_started:
                if job.future is not None:
                    job.future.cancel()
            if exc_type is not FitError and not issubclass(exc_type, KbsError):
                self.owner.close()

    def submit(self, X: np.ndarray) -> _Job:
        if self.jobs <= 1:
            return _Job(X, self.kwargs)
        from concurrent.futures.process import BrokenProcessPool

        try:
            future = self.owner._worker_pool().submit(_worker_split_job, X, self.kwargs)
        except BrokenProcessPool:  # a worker died in an earlier wave or run: split here, fresh pool next run
            self.owner.close()
            return _Job(X, self.kwargs)
        job = _Job(X, self.kwargs, future)
        self.jobs_started.append(job)
        return job
