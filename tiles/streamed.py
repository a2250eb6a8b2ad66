"""A tiled run of a spilled LAS/LAZ file with the memory of the stitching process bounded by the
tile size, not the cloud (``kbs run --tile`` on a LAS/LAZ file read in chunks).

:func:`segment_streamed` gives the result :func:`kbs.tiles.run.segment_tiled` and
:func:`kbs.tiles.stitch.stitch` give, byte for byte once written, without holding the tiles'
results:

1. each tile is segmented (in this process or as a Dask task) from its points read from the spill
   folder (the task gets file paths, not arrays); its whole result goes to its tile file
   (:class:`~kbs.tiles.store.TileStore`), the cluster and label of the points near the tile's
   edges (the only ones a neighbour may hold) to a file in the spill folder, its summary
   (:class:`TileSummary`: each cluster's size, label and ids, its limits, the counts of the
   summary) to another, its explanation's records as the stitched JSON's texts with stand-ins for
   what stitching decides (:func:`write_record_texts`) to a third, and what comes back is a few
   numbers (:class:`TileBrief`);
2. the summaries are read back once and gathered in files (:func:`_gather`); the clusters crossing
   tile edges are merged from the edge points alone, two rows of tiles read at a time
   (:func:`kbs.tiles.stitch.pair_links`);
3. the per-point result (cluster, label, membership) is written to files in the spill folder,
   reading the tile files in turn; the output clusters' descriptors are summed over those files
   in chunks (the sums of :func:`kbs.inference.cluster_geometry`, in its order: the same numbers);
4. the JSON's clusters and explanation are written piece by piece (:meth:`StreamedResult.pieces`:
   one tile's record texts at a time, their stand-ins replaced, not decoded and encoded again) and
   the LAS/LAZ chunk by chunk (:class:`FileColumn`).

What the stitching process holds while the tiles run is a few numbers per tile in arrays: its
cell and counts (:class:`~kbs.tiles.stream.SpilledTiles`, each tile and its job made when asked
for) and its brief's numbers (:class:`TileBriefs`; its notes where it has any, one head for all). The arrays per tile cluster and per output
cluster (sizes, labels, ids, roots, members, descriptors) are in files and mapped when read.
The summary's limits are made from those files too, their ids read when written
(:class:`LimitIds`), and so are the links of the stitched clusters, their notes made when
written (:class:`_Links`). What still grows with the cloud in memory: the union-find over the tile
clusters while stitching (8 bytes each, and a few such arrays while they are made), the order of
the limited records while the summary is written (8 bytes each), the numbers per tile above (about
100 bytes a tile), and, while the JSON is made, the explanation root's children and the tiling's
list (an entry per tile, as the JSON holds them).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import os
import pickle
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kbs.arrays import rows as take_rows
from kbs.errors import KbsError, ParameterError
from kbs.knowledge.explain import ClusterRecord, Explanation
from kbs.knowledge.groundfacts import GroundFacts
from kbs.knowledge.interpreter import NO_LABEL, Segmentation
from kbs.knowledge.segmentation import STOP_KINDS
from kbs.tiles.grid import Tile, TileGrid
from kbs.tiles.stitch import NEIGHBOURS, ROOT, _Union, pair_links, stitched_record
from kbs.tiles.store import TileStore
from kbs.tiles.stream import MadeWhenAsked

#: Points summed (and written) at a time when the output is computed from the files.
CHUNK_POINTS = 1_000_000
#: Output clusters whose descriptors are computed at a time (their sums in files).
DESCRIPTOR_STEP = 1 << 16
#: Tiles whose per-point results are written into the output columns' maps between two write-backs.
COLUMN_FLUSH_TILES = 256


@dataclass(frozen=True)
class Texts:
    """Strings packed in one: the ``i``-th is ``text[ends[i - 1]:ends[i]]``. A tile's record ids
    held this way cost their characters and 8 bytes each, not a Python string and a list slot
    each (about 60 bytes): what the stitching process holds per tile while the others run."""

    text: str
    ends: np.ndarray  # (n,) int64

    @classmethod
    def of(cls, items: Sequence[str]) -> Texts:
        return cls("".join(items), np.cumsum([len(t) for t in items], dtype=np.int64))

    def __len__(self) -> int:
        return int(self.ends.size)

    def slice(self, a: int, b: int) -> list[str]:
        """Strings ``a`` .. ``b - 1``."""
        if b <= a:
            return []
        bounds = [int(self.ends[a - 1]) if a else 0, *self.ends[a:b].tolist()]
        return [self.text[s:e] for s, e in zip(bounds, bounds[1:])]


def _codes(values: Sequence[Any]) -> tuple[tuple[Any, ...], np.ndarray]:
    """The distinct values (by equality, in order of first appearance) and each value's position
    among them: a few labels or limit kinds stand for a tile's many clusters and records."""
    table = _Table()
    codes = table.codes(values, np.arange(len(values)))
    return tuple(table.values), codes


@dataclass(frozen=True)
class TileSummary:
    """What stitching needs of one tile's result (its whole result is in its tile file), in a few
    arrays; written by the tile's task to a file of the spill folder (:func:`save_summary`).

    Attributes
    ----------
    name : str
    sizes, core_sizes : ndarray (K,) int64
        The points of each of the tile's K clusters, in the whole tile and in its core.
    labels, label_codes : tuple and ndarray (K,) int32
        The distinct labels of the clusters, and each cluster's (:meth:`cluster`).
    ids, id_start : Texts and ndarray (K + 1,) int64
        The clusters' explanation record ids, those of cluster c being ``id_start[c]`` ..
        ``id_start[c + 1] - 1`` (:meth:`cluster`).
    label_counts : ndarray (L + 2,) int64
        Core points per label, then core points in no cluster, then core points of a cluster
        with no label.
    n_splits : int
    limit_points, limit_ids, limit_kinds, limit_codes
        The records a limit stopped: their points, ids (without the tile's name), the distinct
        ``limit`` values and each record's (:meth:`limits`).
    root : str
        The id of the tile explanation's root.
    ground, notes, head
        The explanation's ground and notes; ``head``: rule_base, rule_file, strategy,
        label_names, catalogue (the same for every tile: the process that stitches keeps one,
        :func:`_dispatch`).
    """

    name: str
    sizes: np.ndarray
    core_sizes: np.ndarray
    labels: tuple[Any, ...]
    label_codes: np.ndarray
    ids: Texts
    id_start: np.ndarray
    label_counts: np.ndarray
    n_splits: int
    limit_points: np.ndarray
    limit_ids: Texts
    limit_kinds: tuple[Any, ...]
    limit_codes: np.ndarray
    root: str
    ground: GroundFacts
    notes: list[str]
    head: dict[str, Any] = field(default_factory=dict)

    def cluster(self, c: int) -> tuple[Any, list[str]]:
        """Cluster ``c``'s label and record ids."""
        return self.labels[int(self.label_codes[c])], self.ids.slice(int(self.id_start[c]), int(self.id_start[c + 1]))

    def limits(self) -> list[tuple[int, str, Any]]:
        """The records a limit stopped: (n_points, id prefixed with the tile's name, limit)."""
        ids = self.limit_ids.slice(0, len(self.limit_ids))
        return [(int(p), f"{self.name}/{i}", self.limit_kinds[int(c)])
                for p, i, c in zip(self.limit_points.tolist(), ids, self.limit_codes)]


@dataclass(frozen=True)
class TileBrief:
    """What the stitching process holds of a finished tile while the others run: a few numbers;
    the tile's :class:`TileSummary` is in the file ``path`` (spill folder), read back once when
    stitching (:func:`_tables`). ``head`` as the summary's (one kept for all tiles)."""

    name: str
    path: str
    n_clusters: int
    n_ids: int
    n_limits: int
    n_splits: int
    label_counts: np.ndarray
    root: str
    notes: list[str]
    head: dict[str, Any] = field(default_factory=dict)


def save_summary(summary: TileSummary, path: Path) -> TileBrief:
    """Write ``summary`` to ``path`` (pickled: a file of this run's spill folder, read by this
    run) and give back its :class:`TileBrief`."""
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as stream:
        pickle.dump(summary, stream, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)
    return TileBrief(name=summary.name, path=str(path), n_clusters=len(summary.sizes), n_ids=len(summary.ids),
                     n_limits=len(summary.limit_points), n_splits=summary.n_splits, label_counts=summary.label_counts,
                     root=summary.root, notes=summary.notes, head=summary.head)


def load_summary(brief: TileBrief) -> TileSummary:
    with open(brief.path, "rb") as stream:
        summary = pickle.load(stream)
    if not isinstance(summary, TileSummary) or summary.name != brief.name:
        raise KbsError(f"{brief.path} is not the summary of tile {brief.name}")
    return summary


class TileBriefs(MadeWhenAsked):
    """What the stitching process keeps of the finished tiles' :class:`TileBrief`, as they come
    back: their numbers in arrays, their root ids and notes only where they differ from the first
    tile's / are not empty, their summary files' paths only where not ``<folder>/<name>.summary.pkl``,
    one head for all (the tiles' heads are equal). About 60 bytes a tile, not a brief object of
    about 570 (about 1.2 GB at the 2 million tiles of 10^10 points). ``self[k]`` makes the k-th
    brief again.

    Parameters
    ----------
    names : sequence of str
        The tiles' names (a :class:`~kbs.tiles.stream.TileNames`).
    folder : Path
        The spill folder, where the summaries are.
    """

    def __init__(self, names: Sequence[str], folder: Path) -> None:
        n = len(names)
        self.names, self.folder = names, Path(folder)
        self.done = np.zeros(n, dtype=bool)
        self.numbers = np.zeros((n, 4), dtype=np.int64)  # n_clusters, n_ids, n_limits, n_splits
        self.label_counts: np.ndarray | None = None
        self.head: dict[str, Any] | None = None
        self.root: str | None = None
        self.roots: dict[int, str] = {}
        self.notes: dict[int, list[str]] = {}
        self.paths: dict[int, str] = {}

    def add(self, k: int, brief: TileBrief) -> None:
        """Keep tile ``k``'s brief."""
        if brief.name != self.names[k]:
            raise KbsError(f"the brief of tile {brief.name} came back as tile {self.names[k]}'s")
        self.numbers[k] = (brief.n_clusters, brief.n_ids, brief.n_limits, brief.n_splits)
        counts = np.asarray(brief.label_counts, dtype=np.int64)
        if self.label_counts is None:
            self.label_counts = np.zeros((len(self.done), counts.size), dtype=np.int64)
        self.label_counts[k] = counts
        if self.head is None:
            self.head = brief.head
        if self.root is None:
            self.root = brief.root
        if brief.root != self.root:
            self.roots[k] = brief.root
        if brief.notes:
            self.notes[k] = list(brief.notes)
        if brief.path != self._path(k):
            self.paths[k] = brief.path
        self.done[k] = True

    def _path(self, k: int) -> str:
        return str(self.folder / f"{self.names[k]}.summary.pkl")

    @property
    def n_clusters(self) -> np.ndarray:
        return self.numbers[:, 0]

    @property
    def n_splits(self) -> np.ndarray:
        return self.numbers[:, 3]

    def root_of(self, k: int) -> str:
        return self.roots.get(k, self.root or "")

    def path_of(self, k: int) -> str:
        return self.paths.get(k) or self._path(k)

    def take(self, keep: Any, names: Sequence[str]) -> TileBriefs:
        """The briefs of the tiles at the places ``keep`` (increasing), named ``names``."""
        keep = [int(k) for k in keep]
        out = TileBriefs(names, self.folder)
        out.done, out.numbers = self.done[keep], self.numbers[keep]
        out.label_counts = None if self.label_counts is None else self.label_counts[keep]
        out.head, out.root = self.head, self.root
        new = {k: x for x, k in enumerate(keep)}
        out.roots = {new[k]: v for k, v in self.roots.items() if k in new}
        out.notes = {new[k]: v for k, v in self.notes.items() if k in new}
        out.paths = {new[k]: v for k, v in self.paths.items() if k in new}
        return out

    def __len__(self) -> int:
        return len(self.done)

    def _one(self, k: int) -> TileBrief:
        if not self.done[k]:
            raise KbsError(f"tile {self.names[k]} has no brief: it was not finished")
        n_clusters, n_ids, n_limits, n_splits = (int(x) for x in self.numbers[k])
        assert self.label_counts is not None
        return TileBrief(name=self.names[k], path=self.path_of(k), n_clusters=n_clusters, n_ids=n_ids,
                         n_limits=n_limits, n_splits=n_splits, label_counts=self.label_counts[k].copy(),
                         root=self.root_of(k), notes=list(self.notes.get(k, [])), head=self.head or {})



def summary_path(job: Any) -> Path:
    """The file of the tile's summary: in the spill folder, beside its edge points."""
    return Path(job.xyz).with_name(f"{job.tile.name}.summary.pkl")


def summarize(tile: Tile, grid: TileGrid, index: np.ndarray, in_core: np.ndarray, points: np.ndarray,
              seg: Segmentation, edges: Path | None = None) -> TileSummary:
    """The :class:`TileSummary` of ``tile``'s result ``seg`` (its ``points`` (n, 3) at ``index``);
    the tile's edge points (those a neighbouring tile may hold: their indices into the cloud,
    increasing, and their cluster and label here) go to the file ``edges``."""
    cl = np.asarray(seg.cluster)
    k = len(seg.clusters)
    sizes = np.bincount(cl[cl >= 0], minlength=k).astype(np.int64)
    cc = cl[in_core]
    core_sizes = np.bincount(cc[cc >= 0], minlength=k).astype(np.int64)
    lab = np.asarray(seg.label)[in_core]
    counts = [np.count_nonzero(lab == i) for i in range(len(seg.label_names))]
    counts += [np.count_nonzero(cc < 0), np.count_nonzero((lab < 0) & (cc >= 0))]
    if edges is not None:
        edge = _edge_mask(grid, tile, points @ grid.axes.T)
        with open(edges, "wb") as stream:
            np.savez(stream, index=np.asarray(index)[edge], cluster=cl[edge], label=np.asarray(seg.label)[edge])
    e = seg.explanation
    records = e.records.values()
    labels, label_codes = _codes([c["label"] for c in seg.clusters])
    ids = [list(c["ids"]) for c in seg.clusters]
    stopped = [r for r in records if r.action == "limit"]
    limit_kinds, limit_codes = _codes([r.limit for r in stopped])
    return TileSummary(
        name=tile.name, sizes=sizes, core_sizes=core_sizes, labels=labels, label_codes=label_codes,
        ids=Texts.of([i for c in ids for i in c]), id_start=np.cumsum([0] + [len(c) for c in ids], dtype=np.int64),
        label_counts=np.array(counts, dtype=np.int64),
        n_splits=sum(r.action in ("split", "split_components") for r in records),
        limit_points=np.array([r.n_points for r in stopped], dtype=np.int64),
        limit_ids=Texts.of([r.id for r in stopped]), limit_kinds=limit_kinds, limit_codes=limit_codes,
        root=e.root, ground=e.ground, notes=list(e.notes),
        head={"rule_base": e.rule_base, "rule_file": e.rule_file, "strategy": e.strategy,
              "label_names": list(e.label_names), "catalogue": e.catalogue})


def _edge_mask(grid: TileGrid, tile: Tile, uv: np.ndarray) -> np.ndarray:
    """The points of a tile (ground coordinates ``uv``) that a neighbouring tile may hold: within
    the buffer (and a rounding margin) of an edge of its core. A superset is harmless."""
    near = np.zeros(len(uv), dtype=bool)
    for axis, c in ((0, tile.i), (1, tile.j)):
        start = grid.origin[axis] + c * grid.size
        slack = 1e-6 * grid.size + 1e-9 * (abs(start) + grid.size)
        near |= uv[:, axis] <= start + grid.buffer + slack
        near |= uv[:, axis] >= start + grid.size - grid.buffer - slack
    return near


# -- the tiles: each segmented from the spill folder, its result to its tile file ---------------------


@dataclass(frozen=True)
class TileJob:
    """What a task needs to segment one tile of a spilled cloud: paths and small values only."""

    xyz: str
    tile: Tile
    grid: TileGrid
    store: str
    base: bytes
    resume: bool


def read_rows(path: str | os.PathLike[str], index: np.ndarray) -> np.ndarray:
    """Rows ``index`` of the ``.npy`` file ``path`` (a copy; the file's map is dropped on return,
    so its pages do not stay in this process's memory)."""
    mm = np.load(os.fspath(path), mmap_mode="r")
    try:
        return np.array(mm[index])
    finally:
        del mm


def run_job(segment: Callable[[np.ndarray], Segmentation], job: TileJob,
            given: tuple[Any, GroundFacts]) -> tuple[TileBrief, bool]:
    """Segment ``job``'s tile with ``segment`` (points -> result), or take its file when resuming
    and the file is this tile's; save it and its summary (:func:`summary_path`), return the
    summary's brief and whether it was resumed."""
    try:
        index, in_core = job.tile.index, job.tile.in_core
        points = read_rows(job.xyz, index)
    except OSError as exc:
        raise _no_shared_folder(exc) from exc
    return _run_points(segment, job, given, index, in_core, points)


def _no_shared_folder(exc: OSError) -> ParameterError:
    return ParameterError(f"this worker cannot read the tile's points ({exc.strerror or exc}: {exc.filename}): "
                          f"the workers of a Dask scheduler read the tiles from, and write their results to, "
                          f"the output folder: give them a shared file system that holds it at the same path, "
                          f"or run with 'local' or in process")


def _run_points(segment: Callable[[np.ndarray], Segmentation], job: Any, given: tuple[Any, GroundFacts],
                index: np.ndarray, in_core: np.ndarray, points: np.ndarray) -> tuple[TileBrief, bool]:
    store = TileStore.at(job.store, job.base)
    key = store.key_of(index, points, given)
    seg = store.load(job.tile, key) if job.resume else None
    resumed = seg is not None
    if seg is None:
        seg = segment(points)
        store.save(job.tile, key, seg)
    summary = summarize(job.tile, job.grid, index, in_core, points, seg, edges_path(job))
    write_record_texts(seg.explanation, job.tile.name, records_path(job))
    return save_summary(summary, summary_path(job)), resumed


#: Stand-ins, in a record's JSON text written by its tile's task, for what stitching decides: a
#: note it may add to the record's notes, and the output cluster the record became.
NOTE_MARK, OUT_MARK = json.dumps("\x00kbs note\x00"), json.dumps("\x00kbs output index\x00")


def records_path(job: Any) -> Path:
    """The file of the tile's records as JSON texts (:func:`write_record_texts`): in the spill
    folder, beside its edge points."""
    return Path(job.xyz).with_name(f"{job.tile.name}.records.npz")


def write_record_texts(e: Explanation, name: str, path: Path) -> None:
    """The records of tile ``name``'s explanation ``e`` as the stitched JSON writes them, in its
    order, to ``path``: each one's text with what does not depend on the other tiles done
    (:func:`kbs.tiles.stitch.renamed`), and where it became an output cluster of the tile, the
    stand-ins :data:`NOTE_MARK` (the last of its notes) and :data:`OUT_MARK` (its output index),
    with that index (-1: none). Stitching then writes each text with the stand-ins replaced
    (:meth:`StreamedResult.record_texts`), not the records read and encoded again."""
    from kbs.io.result import strict_json
    from kbs.tiles.stitch import renamed

    texts, outs = [], []
    for rec in e.walk():
        d = renamed(rec.to_dict(), name)
        out = d["output_index"]
        if out is not None:
            d["notes"].append(json.loads(NOTE_MARK))
            d["output_index"] = json.loads(OUT_MARK)
        texts.append(strict_json(d))
        outs.append(-1 if out is None else int(out))
    data = "\n".join(texts).encode("utf-8")  # a JSON text holds no raw line break
    with open(path, "wb") as stream:
        np.savez(stream, text=np.frombuffer(data, dtype=np.uint8), out=np.array(outs, dtype=np.int64))


def edges_path(job: Any) -> Path:
    """The file of the tile's edge points: in the spill folder, beside the coordinates."""
    return Path(job.xyz).with_name(f"{job.tile.name}.edges.npz")


class _Edges:
    """The tiles' edge points read from their files, two rows of the grid at a time (the links of
    row i are with rows i and i + 1): what stitching holds is bounded by two rows of tiles."""

    def __init__(self, jobs: Sequence[Any]) -> None:  # TileJob or kbs.tiles.copc.CopcJob, made when asked for
        self.jobs = jobs
        self.cache: dict[int, tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}  # k: (row, edges)

    def get(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if k not in self.cache:
            job = self.jobs[k]
            row = job.tile.i
            for old in [c for c, (r, _) in self.cache.items() if r < row - 1]:
                del self.cache[old]
            with np.load(edges_path(job)) as f:
                self.cache[k] = (row, (f["index"], f["cluster"], f["label"]))
        return self.cache[k][1]


def _task(runner: Callable[..., Any], rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...],
          job: Any, given: tuple[Any, GroundFacts]) -> Any:
    """One tile on a Dask worker: ``runner`` (:func:`run_job`, or :func:`run_copc_job` for a tile
    of a COPC file) with the worker's segmenter; a KbsError is returned, not raised (see
    :func:`kbs.tiles.run.segment_task`)."""
    from kbs.tiles.run import _segment_tile, worker_segmenter

    segmenter = worker_segmenter(rules, sensor, plugins)
    try:
        return runner(lambda X: _segment_tile(segmenter, X, given), job, given)
    except KbsError as exc:
        return exc


def _dispatch(segmenter: Any, runner: Callable[..., Any], names: Sequence[str], job_of: Callable[[int], Any],
              given: tuple[Any, GroundFacts], keep: Callable[[int, Any], bool], scheduler: str | None,
              workers: int | None, progress: Callable[[str], None] | None,
              kept: Path | None = None) -> tuple[dict[int, BaseException], int]:
    """Run ``runner`` on the job of each tile (``job_of(k)``, made when it is run or submitted): in
    this process one after the other, or as Dask tasks on ``scheduler``. Each tile's output goes to
    ``keep(k, out)`` as it comes (which keeps what it needs of it and says whether it was resumed):
    not held here. Returns the failures by tile and how many outputs were resumed. Interrupted
    (Ctrl-C) once a tile is finished, the KeyboardInterrupt says that the finished tiles are kept in
    ``kept`` (the store's folder)."""
    from kbs.tiles.run import _segment_tile, noting_kept_tiles

    failures: dict[int, BaseException] = {}
    n_resumed = 0
    n_kept = 0

    def finished(k: int, out: Any, done: int) -> None:
        nonlocal n_resumed, n_kept
        if isinstance(out, BaseException):
            failures[k] = out
            return
        resumed = keep(k, out)
        n_resumed += resumed
        n_kept += 1
        if progress is not None and not resumed:
            progress(f"{names[k]} ({done}/{len(names)} tiles)")

    with noting_kept_tiles(kept, lambda: n_kept > 0):
        if scheduler is None:
            for done, k in enumerate(range(len(names)), start=1):
                try:
                    out: Any = runner(lambda X: _segment_tile(segmenter, X, given), job_of(k), given)
                except KbsError as exc:
                    out = exc
                finished(k, out, done)
        else:
            from kbs.tiles.run import submit_all

            spec = (segmenter.rule_base.path, segmenter.sensor, segmenter.plugins)
            submit_all(scheduler, workers, progress, finished, range(len(names)),
                       lambda k: (_task, runner, *spec, job_of(k), given), names)
    return failures, n_resumed


class _Lazy(MadeWhenAsked):
    """``make(k)`` for k < n, made when asked for (the tiles' jobs: not one object per tile held)."""

    def __init__(self, n: int, make: Callable[[int], Any]) -> None:
        self.n, self.make = n, make

    def __len__(self) -> int:
        return self.n

    def _one(self, k: int) -> Any:
        return self.make(k)


def segment_streamed(segmenter: Any, spilled: Any, store: TileStore, *, scheduler: str | None = None,
                     workers: int | None = None, progress: Callable[[str], None] | None = None,
                     resume: bool = False) -> StreamedResult:
    """Segment the tiles of a spilled LAS/LAZ file (:func:`kbs.tiles.stream.spill_las`) and stitch
    them with bounded memory: each tile's result goes to ``store``, the output to files in the
    spill folder. Arguments and errors as :func:`kbs.tiles.run.segment_tiled`'s."""
    from kbs.tiles.run import TileError, warn_spacing

    t0 = time.perf_counter()
    warn_spacing(segmenter, spilled.xyz)
    tiles, grid = spilled.tiles, spilled.grid
    xyz_path = str(spilled.folder / "xyz.npy")
    n = int(spilled.xyz.shape[0])
    given = _ground(segmenter, xyz_path, n)
    release_free_memory()  # what the spill's chunks and the ground's sample left
    store_folder = str(store.folder)  # one string for every job
    names = getattr(tiles, "names", None) or [t.name for t in tiles]
    jobs = _Lazy(len(tiles), lambda k: TileJob(xyz_path, tiles[k], grid, store_folder, store._base, resume))
    briefs = TileBriefs(names, spilled.folder)

    def keep(k: int, out: tuple[TileBrief, bool]) -> bool:
        briefs.add(k, out[0])
        return bool(out[1])

    failures, n_resumed = _dispatch(segmenter, run_job, names, jobs.__getitem__, given, keep, scheduler, workers,
                                    progress, store.folder)
    if resume and progress is not None:
        progress(f"resumed {n_resumed} of {len(tiles)} tiles from {store.folder}")
    if failures:
        first = min(failures)
        raise TileError(tiles[first], _n_points(tiles[first]), failures[first],
                        failed=[tiles[k] for k in sorted(failures)], total=len(tiles),
                        kept=store.folder if len(failures) < len(tiles) else None)
    return _stitch(spilled, grid, tiles, briefs, _Edges(jobs), store, given[1], t0)


def run_copc_job(segment: Callable[[np.ndarray], Segmentation], job: Any,
                 given: tuple[Any, GroundFacts]) -> tuple[TileBrief | None, bool, Any, int]:
    """Read ``job``'s tile (a :class:`kbs.tiles.copc.CopcJob`) from its COPC file by its nodes,
    write its rows beside the spill folder's coordinates and segment it as :func:`run_job` does;
    returns its summary (None: no point in its core, nothing segmented), whether it was resumed,
    the tile with its counts, and the points decompressed."""
    from kbs.tiles.copc import read_tile
    from kbs.tiles.stream import SpilledTile

    try:  # the nodes' rows of the coordinates the client wrote (decompressed once, there)
        index, in_core, points, read = read_tile(job.path, job.nodes, job.grid, job.tile.i, job.tile.j, job.xyz)
    except OSError as exc:
        raise _no_shared_folder(exc) from exc
    t = job.tile
    tile = SpilledTile(t.name, t.i, t.j, t.core, t.folder, int(index.size), int(np.count_nonzero(in_core)))
    if not tile.n_core:
        return None, False, tile, read
    try:
        index.tofile(tile.folder / f"{tile.name}.idx")
        in_core.tofile(tile.folder / f"{tile.name}.core")
    except OSError as exc:
        raise _no_shared_folder(exc) from exc
    summary, resumed = _run_points(segment, dataclasses.replace(job, tile=tile), given, index, in_core, points)
    return summary, resumed, tile, read


def segment_copc(segmenter: Any, cloud: Any, store: TileStore, *, scheduler: str | None = None,
                 workers: int | None = None, progress: Callable[[str], None] | None = None,
                 resume: bool = False) -> StreamedResult:
    """Segment the tiles of a COPC file (:func:`kbs.tiles.copc.read_copc`), each read by the
    nodes of its octree that meet its buffered bounds (in this process or in its Dask task), and
    stitch them as :func:`segment_streamed` does: the same result, byte for byte."""
    from kbs.errors import CloudFileError
    from kbs.tiles.copc import CopcJob, tile_box, tiles_of
    from kbs.tiles.stream import SpilledTiles
    from kbs.tiles.run import TileError, sample_ground, warn_spacing

    t0 = time.perf_counter()
    warn_spacing(segmenter, cloud.xyz)
    grid = cloud.grid
    n = int(cloud.xyz.shape[0])
    given = sample_ground(segmenter, cloud.sample, n)
    release_free_memory()
    cells = tiles_of(cloud)
    xyz_path = str(cloud.folder / "xyz.npy")

    def job_of(k: int) -> CopcJob:  # made when submitted: the client holds the nodes of the tiles in flight
        t = cells[k]
        return CopcJob(str(cloud.path), cloud.nodes_of(*tile_box(grid, t.i, t.j)), xyz_path, t, grid,
                       str(store.folder), store._base, resume)

    briefs = TileBriefs(cells.names, cloud.folder)
    n_points, n_core = np.zeros(len(cells), np.int64), np.zeros(len(cells), np.int64)
    read = np.zeros(len(cells), np.int64)

    def keep(k: int, out: tuple[TileBrief | None, bool, Any, int]) -> bool:
        brief, resumed, tile, n_read = out
        if brief is not None:
            briefs.add(k, brief)
        n_points[k], n_core[k], read[k] = tile.n_points, tile.n_core, n_read
        return bool(resumed)

    failures, n_resumed = _dispatch(segmenter, run_copc_job, cells.names, job_of, given, keep, scheduler, workers,
                                    progress, store.folder)
    if resume and progress is not None:
        progress(f"resumed {n_resumed} of {int(np.count_nonzero(briefs.done))} tiles from {store.folder}")
    if failures:
        first = min(failures)
        raise TileError(cells[first], 0, failures[first], failed=[cells[k] for k in sorted(failures)],
                        total=len(cells), kept=store.folder if len(failures) < len(cells) else None)
    kept = np.flatnonzero(briefs.done)
    tiles = SpilledTiles(grid, cloud.folder, cells.i[kept], cells.j[kept], n_points[kept], n_core[kept])
    cloud.tiles = tiles
    cloud.read_by_tiles = read
    held = int(tiles.n_core.sum())
    if held != n:  # a point outside the bounds of its node: no tile read it
        raise CloudFileError(str(cloud.path), f"the bounds of its COPC octree's nodes do not hold their points: the "
                                              f"tiles read by them hold {held:,} of its {n:,} points")
    no_nodes = np.zeros((0, 8), dtype=np.int64)  # what stitching asks of a job: its tile and folder
    jobs = _Lazy(len(tiles), lambda x: CopcJob(str(cloud.path), no_nodes, xyz_path, tiles[x], grid,
                                               str(store.folder), store._base, resume))
    out = _stitch(cloud, grid, tiles, briefs.take(kept, tiles.names), _Edges(jobs), store, given[1], t0)
    top = int(read.max())
    out.read_note = (f"a COPC file: each of its {len(cells)} tiles read the nodes of its octree that meet its "
                     f"buffered bounds (at most {top:,} of its {n:,} points for one tile; {len(tiles)} hold points), "
                     f"no pass routed the points to the tiles")
    return out


def _n_points(tile: Tile) -> int:
    return int(getattr(tile, "n_points", None) or tile.index.size)


def _ground(segmenter: Any, xyz_path: str, n: int) -> tuple[Any, GroundFacts]:
    """:func:`kbs.tiles.run.scene_ground` of the spilled cloud: its sample read from the file (at
    most :data:`kbs.tiles.run.GROUND_SAMPLE_POINTS` points in memory)."""
    from kbs.tiles.run import ground_step, sample_ground

    mm = np.load(xyz_path, mmap_mode="r")
    try:
        sample = np.array(mm[::ground_step(n)])
    finally:
        del mm
    return sample_ground(segmenter, sample, n)


# -- stitching from the summaries ---------------------------------------------------------------------


def _mapped(path: Path, dtype: Any) -> np.ndarray:
    """The raw file ``path`` mapped read-only as an array of ``dtype`` (an empty array when the
    file is: a map cannot be empty)."""
    if path.stat().st_size == 0:
        return np.zeros(0, dtype=dtype)
    return np.memmap(path, dtype=dtype, mode="r")


@dataclass(frozen=True)
class FileTexts:
    """:class:`Texts` in a file: the strings' UTF-8 bytes one after the other (``data``, mapped)
    and each one's end offset in bytes (``ends``)."""

    data: np.ndarray  # (bytes,) uint8
    ends: np.ndarray  # (n,) int64

    def __len__(self) -> int:
        return int(self.ends.size)

    def slice(self, a: int, b: int) -> list[str]:
        """Strings ``a`` .. ``b - 1``."""
        if b <= a:
            return []
        s0 = int(self.ends[a - 1]) if a else 0
        bounds = [s0, *self.ends[a:b].tolist()]
        raw = bytes(self.data[s0:bounds[-1]])
        return [raw[x - s0:y - s0].decode("utf-8") for x, y in zip(bounds, bounds[1:])]


class _Table:
    """Distinct values (by equality and type; labels, limit dicts: few, not all hashable) and a
    code each, over all tiles."""

    def __init__(self) -> None:
        self.values: list[Any] = []

    def codes(self, values: Sequence[Any], codes: np.ndarray) -> np.ndarray:
        """The global codes of a tile's ``values`` table, for its ``codes`` into it."""
        out = []
        for v in values:
            for i, t in enumerate(self.values):
                if t == v and type(t) is type(v):
                    out.append(i)
                    break
            else:
                out.append(len(self.values))
                self.values.append(v)
        return np.asarray(out, dtype=np.int32)[codes] if len(codes) else np.zeros(0, dtype=np.int32)


def _utf8(texts: Texts) -> tuple[bytes, np.ndarray]:
    """``texts`` as UTF-8 bytes and each string's end in them."""
    data = texts.text.encode("utf-8")
    if len(data) == len(texts.text):  # ASCII (the record ids kbs makes): the same offsets
        return data, texts.ends
    return data, np.cumsum([len(t.encode("utf-8")) for t in texts.slice(0, len(texts))], dtype=np.int64)


@dataclass(frozen=True)
class _Tables:
    """The tiles' summaries gathered, in files of the spill folder (:func:`_gather`, one pass over
    the summary files): per tile cluster (numbered ``offsets[k] + c`` over the tiles) its points
    (``sizes``), core points, label code and record ids; per record a limit stopped, its points,
    tile, limit code and id. What stitching and writing read of the summaries, mapped, not held."""

    sizes: np.ndarray
    core_sizes: np.ndarray
    labels: tuple[Any, ...]
    label_codes: np.ndarray
    id_start: np.ndarray  # (total + 1,)
    ids: FileTexts
    limit_points: np.ndarray
    limit_tiles: np.ndarray
    limit_kinds: tuple[Any, ...]
    limit_codes: np.ndarray
    limit_ids: FileTexts
    limit_ranks: np.ndarray  # each limited record's place among its tile's in the order of their ids
    grounds: FileTexts
    ground_sources: tuple[str, ...]

    def cluster(self, g: int) -> tuple[Any, list[str]]:
        """Tile cluster ``g``'s label and record ids (without the tile's name)."""
        return self.labels[int(self.label_codes[g])], self.ids.slice(int(self.id_start[g]), int(self.id_start[g + 1]))

    def limits(self, names: Sequence[str]) -> list[tuple[int, str, Any]]:
        """The records a limit stopped, tile by tile: (n_points, id prefixed with its tile's name
        from ``names``, limit)."""
        ids = self.limit_ids.slice(0, len(self.limit_ids))
        return [(p, f"{names[k]}/{i}", self.limit_kinds[c]) for p, k, i, c in
                zip(self.limit_points.tolist(), self.limit_tiles.tolist(), ids, self.limit_codes.tolist())]


    def limits_by_kind(self, names: Sequence[str]) -> dict[str, dict[str, Any]]:
        """:func:`kbs.knowledge.segmentation.limits_by_kind` of :meth:`limits`, the same dict
        (``==``, the same JSON), made from the arrays: each kind's ``clusters`` is a
        :class:`LimitIds`, the ids read from the file when asked for, not a list of strings.

        The order is limits_by_kind's, the fewest points last and equal points by their ids
        (``tile/id``): a tile's name holds no '/', so the ids of two tiles compare as their names
        followed by '/', and those of one tile as the tile's ids (``limit_ranks``)."""
        m = int(self.limit_points.size)
        if m == 0:
            return {}
        by_name = sorted(range(len(names)), key=lambda k: names[k] + "/")
        name_rank = np.empty(len(names), dtype=np.int64)
        name_rank[by_name] = np.arange(len(names))
        tiles = np.asarray(self.limit_tiles, dtype=np.int64)
        points = np.asarray(self.limit_points, dtype=np.int64)
        order = np.lexsort((np.asarray(self.limit_ranks), name_rank[tiles], -points))
        del tiles
        kinds = [(lim or {"kind": "other", "setting": None, "value": None}) for lim in self.limit_kinds]
        names_of_kinds = [k["kind"] for k in kinds]
        group_of_code = np.array([names_of_kinds.index(k) for k in names_of_kinds], dtype=np.int64)
        codes = np.asarray(self.limit_codes, dtype=np.int64)[order]
        grouped = group_of_code[codes]  # the kind of each record, in the order
        out: dict[str, dict[str, Any]] = {}
        groups, firsts = np.unique(grouped, return_index=True)
        for g, first in sorted(zip(groups.tolist(), firsts.tolist()), key=lambda t: t[1]):  # as first met
            rows = order[grouped == g]
            lim = kinds[int(codes[first])]  # the setting and value of the kind's first record
            out[lim["kind"]] = {"setting": lim["setting"], "value": lim["value"], "count": int(rows.size),
                                "points": int(points[rows].sum()), "clusters": LimitIds(rows, self, names)}
        stops = list(STOP_KINDS)
        return dict(sorted(out.items(), key=lambda kv: stops.index(kv[0]) if kv[0] in stops else len(stops)))


class LimitIds(Sequence[str]):
    """The ids (``tile/id``) of some limited records of a streamed result, in a given order, read
    from the gathered file when asked for (``limits_by_kind``'s ``clusters`` of a streamed result:
    a list of every id would be held while the result is written). Equal to the list of them."""

    def __init__(self, rows: np.ndarray, tables: _Tables, names: Sequence[str]) -> None:
        self.rows, self.tables, self.names = rows, tables, names

    def __len__(self) -> int:
        return int(self.rows.size)

    def _one(self, r: int) -> str:
        return f"{self.names[int(self.tables.limit_tiles[r])]}/{self.tables.limit_ids.slice(r, r + 1)[0]}"

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, slice):
            return [self._one(r) for r in self.rows[key].tolist()]
        return self._one(int(self.rows[key]))

    def __iter__(self) -> Iterator[str]:
        for r in self.rows.tolist():
            yield self._one(r)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, LimitIds | list | tuple):
            return len(self) == len(other) and all(a == b for a, b in zip(self, other))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"LimitIds({list(self[:3])}{', ...' if len(self) > 3 else ''}; {len(self)})"


def _gather(folder: Path, briefs: Sequence[TileBrief]) -> _Tables:
    """Read each tile's summary file once and write what :class:`_Tables` holds to ``folder``."""
    from kbs.io.result import strict_json

    names = ("sizes", "core_sizes", "label_codes", "id_start", "ids", "id_ends", "limit_points", "limit_tiles",
             "limit_codes", "limit_ids", "limit_id_ends", "limit_ranks", "grounds", "ground_ends")
    paths = {name: folder / f"tables-{name}.bin" for name in names}
    labels, kinds = _Table(), _Table()
    n_ids = n_bytes = n_limit_bytes = n_ground_bytes = 0
    sources: set[str] = set()
    streams = {name: open(path, "wb") for name, path in paths.items()}
    try:
        for k, brief in enumerate(briefs):
            s = load_summary(brief)
            streams["sizes"].write(s.sizes.astype("<i8").tobytes())
            streams["core_sizes"].write(s.core_sizes.astype("<i8").tobytes())
            streams["label_codes"].write(labels.codes(s.labels, s.label_codes).astype("<i4").tobytes())
            streams["id_start"].write((s.id_start[:-1] + n_ids).astype("<i8").tobytes())
            data, ends = _utf8(s.ids)
            streams["ids"].write(data)
            streams["id_ends"].write((ends + n_bytes).astype("<i8").tobytes())
            n_ids += len(s.ids)
            n_bytes += len(data)
            streams["limit_points"].write(s.limit_points.astype("<i8").tobytes())
            streams["limit_tiles"].write(np.full(len(s.limit_points), k, dtype="<i4").tobytes())
            streams["limit_codes"].write(kinds.codes(s.limit_kinds, s.limit_codes).astype("<i4").tobytes())
            data, ends = _utf8(s.limit_ids)
            rids = s.limit_ids.slice(0, len(s.limit_ids))
            rank = np.empty(len(rids), dtype="<i4")  # each id's place among the tile's in string order
            rank[sorted(range(len(rids)), key=rids.__getitem__)] = np.arange(len(rids), dtype="<i4")
            streams["limit_ranks"].write(rank.tobytes())
            streams["limit_ids"].write(data)
            streams["limit_id_ends"].write((ends + n_limit_bytes).astype("<i8").tobytes())
            n_limit_bytes += len(data)
            data = strict_json(s.ground.to_dict()).encode("utf-8")  # as the explanation's JSON holds it
            streams["grounds"].write(data)
            n_ground_bytes += len(data)
            streams["ground_ends"].write(np.array([n_ground_bytes], dtype="<i8").tobytes())
            sources.add(str(s.ground.source or "not used"))
        streams["id_start"].write(np.array([n_ids], dtype="<i8").tobytes())
    finally:
        for stream in streams.values():
            stream.close()
    i8, i4, u1 = np.dtype("<i8"), np.dtype("<i4"), np.dtype(np.uint8)
    return _Tables(sizes=_mapped(paths["sizes"], i8), core_sizes=_mapped(paths["core_sizes"], i8),
                   labels=tuple(labels.values), label_codes=_mapped(paths["label_codes"], i4),
                   id_start=_mapped(paths["id_start"], i8),
                   ids=FileTexts(_mapped(paths["ids"], u1), _mapped(paths["id_ends"], i8)),
                   limit_points=_mapped(paths["limit_points"], i8), limit_tiles=_mapped(paths["limit_tiles"], i4),
                   limit_kinds=tuple(kinds.values), limit_codes=_mapped(paths["limit_codes"], i4),
                   limit_ids=FileTexts(_mapped(paths["limit_ids"], u1), _mapped(paths["limit_id_ends"], i8)),
                   limit_ranks=_mapped(paths["limit_ranks"], i4), grounds=FileTexts(_mapped(paths["grounds"], u1), _mapped(paths["ground_ends"], i8)),
                   ground_sources=tuple(sorted(sources)))


class _GroundTiles(Mapping[str, GroundFacts]):
    """The tiles' ground facts by tile name (``GroundFacts.tiles`` of a streamed result), read
    from their JSON text in a file when asked for: not held per tile (:meth:`StreamedResult.pieces`
    writes the texts as they are)."""

    def __init__(self, names: Sequence[str], texts: FileTexts) -> None:
        self.names = names  # a TileNames finds a name's place from its cell: no dict of the names
        self.texts = texts
        self._at: dict[str, int] | None = None

    def text(self, k: int) -> str:
        return self.texts.slice(k, k + 1)[0]

    def __getitem__(self, name: str) -> GroundFacts:
        from kbs.tiles.stream import TileNames

        if isinstance(self.names, TileNames):
            try:
                k = self.names.index(name)
            except ValueError:
                raise KeyError(name) from None
        else:
            if self._at is None:
                self._at = {n: k for k, n in enumerate(self.names)}
            k = self._at[name]
        return GroundFacts.from_dict(json.loads(self.text(k)))

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)



def _stitch(spilled: Any, grid: TileGrid, tiles: Any, briefs: TileBriefs, edges: _Edges,
            store: TileStore, given: GroundFacts, t0: float) -> StreamedResult:
    """``tiles``: a :class:`~kbs.tiles.stream.SpilledTiles`; ``briefs``: theirs, all finished."""
    folder = Path(spilled.folder)
    names = tiles.names
    tables = _gather(folder, briefs)
    offsets = np.concatenate([[0], np.cumsum(briefs.n_clusters)]).astype(np.int64)
    total = int(offsets[-1])
    uf = _Union(total)
    with open(folder / "stitch-links.bin", "wb") as log:  # each link, from each side, as it is found
        for ka, a in enumerate(tiles):
            size_a = np.asarray(tables.sizes[offsets[ka]:offsets[ka + 1]])
            for di, dj in NEIGHBOURS:
                kb = tiles.at(a.i + di, a.j + dj)
                if kb is None:
                    continue
                (ia, ca, la), (ib, cb, lb) = edges.get(ka), edges.get(kb)
                found = pair_links(ia, ca, la, size_a, ib, cb, lb, np.asarray(tables.sizes[offsets[kb]:offsets[kb + 1]]))
                for x, y, _ in found:
                    uf.union(int(offsets[ka] + x), int(offsets[kb] + y))
                if found:
                    xyk = np.array(found, dtype=np.int64).reshape(-1, 3)
                    rows = np.empty((2 * len(xyk), 4), dtype=np.int64)
                    rows[0::2] = np.column_stack([offsets[ka] + xyk[:, 0], np.full(len(xyk), kb), xyk[:, 1], xyk[:, 2]])
                    rows[1::2] = np.column_stack([offsets[kb] + xyk[:, 1], np.full(len(xyk), ka), xyk[:, 0], xyk[:, 2]])
                    log.write(rows.tobytes())
    shared = _Links.gather(folder, names)
    roots = uf.roots()
    del uf
    release_free_memory()
    core_sizes = np.asarray(tables.core_sizes) if total else np.zeros(0, dtype=np.int64)
    sizes = np.bincount(roots, weights=core_sizes, minlength=total).astype(np.int64) if total else \
        np.zeros(0, dtype=np.int64)
    alive = np.flatnonzero(sizes)
    order = alive[np.lexsort((alive, -sizes[alive]))]
    del alive
    out_of_root = np.full(total + 1, -1, dtype=np.int64)
    out_of_root[order] = np.arange(order.size)
    out_of_node = out_of_root[roots] if total else np.zeros(0, dtype=np.int64)

    n = int(spilled.xyz.shape[0])
    columns = {name: _new_column(folder / f"out-{name}.npy", dtype, n)
               for name, dtype in (("cluster", np.int32), ("label", np.int32), ("membership", np.float32))}
    # each point takes the result of the tile whose core holds it; the columns' maps are opened
    # once and, every COLUMN_FLUSH_TILES tiles, written back and dropped from this process's
    # resident pages (not opened, flushed and closed for every tile: 3 maps of the whole cloud
    # each time)
    maps = {name: np.load(column.path, mmap_mode="r+") for name, column in columns.items()}
    for k, t in enumerate(tiles):
        with np.load(store.path(t), allow_pickle=False) as f:
            local = f["cluster"].astype(np.int64)
            label, membership = f["label"], f["membership"]
        in_core = t.in_core
        core = t.index[in_core]
        local = local[in_core]
        cluster = np.full(local.shape, -1, dtype=np.int64)  # noise stays -1; only the tile's clusters are looked up
        clustered = local >= 0  # (a tile of noise alone, the last one, has no cluster at offsets[k] == total)
        cluster[clustered] = out_of_node[local[clustered] + offsets[k]]
        values = {"cluster": cluster,
                  "label": label[in_core], "membership": membership[in_core]}
        for name, mm in maps.items():
            mm[core] = values[name]
        if (k + 1) % COLUMN_FLUSH_TILES == 0 or k + 1 == len(tiles):
            for mm in maps.values():
                _write_back(mm)
    del maps, out_of_node
    release_free_memory()
    geometry = _descriptors(folder / "xyz.npy", columns["cluster"], columns["membership"], order.size, folder)
    release_free_memory()

    # the tile clusters of each root, in increasing order: members[start[r]:start[r + 1]]; these
    # arrays (a few per tile cluster) go to files: the JSON is written from them, not held
    members = np.argsort(roots, kind="stable") if total else np.zeros(0, dtype=np.int64)
    member_start = np.searchsorted(roots[members], np.arange(total + 1)) if total else np.zeros(1, dtype=np.int64)
    in_core_parts = np.bincount(roots, weights=core_sizes > 0, minlength=total) if total else np.zeros(0)
    stitched = _Marked(_in_files(folder, {"stitched": in_core_parts[order] > 1}, prefix="stitch")["stitched"])
    del in_core_parts, core_sizes
    head = briefs.head or {}
    label_names = list(head["label_names"])
    grounds = _GroundTiles(names, tables.grounds)
    k_st = len(stitched)
    notes = [f"{len(tiles)} tiles; {k_st} output cluster{'s' if k_st != 1 else ''} stitched across tile edges",
             *[f"{names[k]}: {note}" for k in sorted(briefs.notes) for note in briefs.notes[k]]]
    root_record = ClusterRecord(id=ROOT, parent=None, depth=0, n_points=n, action="partition",
                                children=tuple(f"{name}/{briefs.root_of(k)}" for k, name in enumerate(names)),
                                notes=(f"{len(tiles)} tiles: " + ", ".join(t.bounds_text() for t in tiles),))
    ground = dataclasses.replace(given, tiles=grounds) if given else \
        GroundFacts(source=f"per tile ({', '.join(tables.ground_sources)})", tiles=grounds)
    explanation = Explanation(rule_base=head["rule_base"], rule_file=head["rule_file"], strategy=head["strategy"],
                              label_names=label_names, records={ROOT: root_record}, root=ROOT, ground=ground,
                              notes=notes, catalogue=head["catalogue"])
    assert briefs.label_counts is not None
    counts = briefs.label_counts.sum(axis=0)
    per_label = {name: int(counts[i]) for i, name in enumerate(label_names)}
    per_label["noise (rejected)" if "noise" in per_label else "noise"] = int(counts[len(label_names)])
    if counts[len(label_names) + 1]:
        per_label[NO_LABEL] = int(counts[len(label_names) + 1])
    tiling = {"size": grid.size, "buffer": grid.buffer, "axes": grid.axes.tolist(), "origin": list(grid.origin),
              "shape": list(grid.shape), "stitched": k_st, "tiles": TilingEntries(tiles)}
    mapped = _in_files(folder, {"roots": roots, "out_of_root": out_of_root, "order": order, "members": members,
                                "member_start": member_start, "sizes": sizes}, prefix="stitch")
    n_out = int(order.size)
    del roots, out_of_root, order, members, member_start, sizes
    release_free_memory()
    return StreamedResult(
        n=n, columns=columns, label_names=label_names, explanation=explanation, tiling=tiling,
        seconds=time.perf_counter() - t0, n_clusters=n_out, n_splits=int(briefs.n_splits.sum()),
        points_per_label=per_label,
        _tiles=tiles, _tables=tables, _store=store, _offsets=offsets,
        _roots=mapped["roots"], _out_of_root=mapped["out_of_root"], _order=mapped["order"], _members=mapped["members"],
        _member_start=mapped["member_start"], _shared=shared, _stitched=stitched, _geometry=geometry,
        _sizes=mapped["sizes"], _folder=folder)


class TilingEntries(MadeWhenAsked):
    """The ``tiles`` of a streamed result's ``tiling``: each tile's entry (name, core, points, core
    points) made when asked for, from the :class:`~kbs.tiles.stream.SpilledTiles`' arrays, and
    written to the JSON one at a time (:meth:`StreamedResult.pieces`): not a list of dicts."""

    def __init__(self, tiles: Any) -> None:
        self.tiles = tiles

    def __len__(self) -> int:
        return len(self.tiles)

    def _one(self, k: int) -> dict[str, Any]:
        t = self.tiles[k]
        return {"name": t.name, "core": list(t.core), "points": int(t.n_points), "core_points": int(t.n_core)}


    def __eq__(self, other: object) -> bool:
        return isinstance(other, (list, tuple, TilingEntries)) and len(other) == len(self) and \
            all(a == b for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]


class _Links(Mapping[int, list[str]]):
    """The links of the stitched tile clusters (``shared`` of :func:`kbs.tiles.stitch.stitch`: for
    a tile cluster's node, the notes naming the clusters of neighbouring tiles it shares buffer
    points with, in the order they were found), from a file of rows (node, other tile, its
    cluster, shared points) sorted by node: each note made when asked for, not held."""

    def __init__(self, rows: np.ndarray, names: Sequence[str]) -> None:
        self.rows, self.names = np.asarray(rows), names  # a plain view of the map: cheaper to index
        self.nodes = self.rows[:, 0] if len(rows) else np.zeros(0, dtype=np.int64)

    @classmethod
    def gather(cls, folder: Path, names: Sequence[str]) -> _Links:
        """The links logged in ``folder/stitch-links.bin`` (rows of 4 int64 in the order found),
        sorted by node (stably: each node's links in that order) into ``stitch-links.npy``."""
        log = folder / "stitch-links.bin"
        found = _mapped(log, np.int64).reshape(-1, 4)
        order = np.argsort(found[:, 0], kind="stable")
        rows = _in_files(folder, {"links": np.asarray(found[order]) if len(order) else np.zeros((0, 4), np.int64)},
                         prefix="stitch")["links"]
        del found, order
        log.unlink()
        return cls(rows, names)

    def _span(self, g: int) -> tuple[int, int]:
        return int(np.searchsorted(self.nodes, g, "left")), int(np.searchsorted(self.nodes, g, "right"))

    def __contains__(self, g: object) -> bool:
        if not isinstance(g, (int, np.integer)):
            return False
        a, b = self._span(int(g))
        return b > a

    def __getitem__(self, g: int) -> list[str]:
        a, b = self._span(int(g))
        if a == b:
            raise KeyError(g)
        return [f"{self.names[t]} cluster {c} ({k:,} shared points)" for _, t, c, k in self.rows[a:b].tolist()]

    def __iter__(self) -> Iterator[int]:
        return iter(np.unique(self.nodes).tolist())

    def __len__(self) -> int:
        return int(np.unique(self.nodes).size)


class _Marked:
    """The output clusters stitched across tile edges (``out in marked``), from a mapped array of
    flags, one per output cluster (not a set of Python integers)."""

    def __init__(self, flags: np.ndarray) -> None:
        self.flags = np.asarray(flags)  # a plain view of the map: cheaper to index

    def __contains__(self, i: object) -> bool:
        return isinstance(i, (int, np.integer)) and 0 <= int(i) < len(self.flags) and bool(self.flags[int(i)])

    def __len__(self) -> int:
        return int(np.count_nonzero(self.flags))


# -- the per-point output, in files ---------------------------------------------------------------------


@dataclass(frozen=True)
class FileColumn:
    """A per-point array in a ``.npy`` file, read by slices (``column[a:b]``: a copy of those rows,
    nothing kept mapped) or whole (``np.asarray(column)``)."""

    path: Path
    dtype: Any
    shape: tuple[int, ...]

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __getitem__(self, key: slice) -> np.ndarray:
        mm = np.load(self.path, mmap_mode="r")
        try:
            return np.array(mm[key])
        finally:
            del mm

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = np.load(self.path)
        return out if dtype is None else out.astype(dtype)

    def chunks(self, size: int = CHUNK_POINTS) -> Iterator[tuple[int, np.ndarray]]:
        for start in range(0, self.shape[0], size):
            yield start, self[start:start + size]


@functools.lru_cache(maxsize=1)
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        import ctypes

        return ctypes.CDLL(None).malloc_trim  # glibc (Linux); not on macOS, Windows or musl
    except (AttributeError, OSError, TypeError):
        return None


def release_free_memory() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``; nothing where
    there is none). The stitching process allocates and frees arrays of tens of MB (per tile
    cluster, per chunk of points) between its steps; the C allocator keeps what they leave
    free, and its resident memory then counts what it no longer holds: 284 of 435 MB at the
    start of a 10^8-point run's tiles, 177 of 705 MB while its JSON was written (measured by
    calling it in the running process). Called between the steps."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _write_back(mm: np.memmap) -> None:
    """Write a map's changed pages to its file and drop its pages from this process's resident
    memory (they stay in the page cache): what a map written tile by tile holds stays bounded."""
    import mmap

    mm.flush()
    raw = getattr(mm, "_mmap", None)
    if raw is not None and hasattr(mmap, "MADV_DONTNEED"):
        raw.madvise(mmap.MADV_DONTNEED)


def _new_column(path: Path, dtype: Any, n: int) -> FileColumn:
    from kbs.tiles.stream import _npy_header

    with open(path, "wb") as stream:
        _npy_header(stream, dtype, (n,))
        stream.truncate(stream.tell() + n * np.dtype(dtype).itemsize)  # every point is written once, by its core
    return FileColumn(path, np.dtype(dtype), (n,))


@dataclass(frozen=True)
class CodesColumn:
    """The ASPRS codes of :func:`kbs.io.las.class_codes`, computed a slice at a time."""

    label: FileColumn
    cluster: FileColumn
    label_names: list[str]
    classes: dict[str, int]

    def __getitem__(self, key: slice) -> np.ndarray:
        from kbs.io.las import class_codes

        return class_codes(self.label[key], self.cluster[key], self.label_names, self.classes)


def _in_files(folder: Path, arrays: dict[str, np.ndarray], prefix: str = "out") -> dict[str, np.ndarray]:
    """``arrays`` written to ``folder/<prefix>-<name>.npy`` and given back mapped from there (read
    only; an empty array as it is): arrays per tile cluster or output cluster that stitching and
    the JSON read, not held."""
    out = {}
    for name, a in arrays.items():
        path = folder / f"{prefix}-{name}.npy"
        np.save(path, a)
        out[name] = np.load(path, mmap_mode="r") if a.size else a
    return out


def _descriptors(xyz_path: Path, cluster: FileColumn, membership: FileColumn, k: int,
                 folder: Path | None = None) -> dict[str, np.ndarray]:
    """Centre, covariance, eigenvalues, eigenvectors and mass of each of the ``k`` output clusters,
    from the files in chunks: the sums of :func:`kbs.inference._compiled.geometry3`, in its order
    (each cluster's points by increasing index), so the same numbers as ``cluster_geometry`` on
    the cluster's points and memberships. With ``folder``, the arrays (the sums and the
    descriptors, a few hundred bytes per output cluster) are files there (``out-<name>.npy``, as
    :func:`_in_files` writes them), filled in place and given back mapped read-only: not held."""
    from kbs.inference import _flags

    if not _flags.JIT:  # the numpy reference sums in another order: its numbers need each cluster whole
        out = _descriptors_reference(xyz_path, cluster, membership, k)
        return out if folder is None else _in_files(folder, out)
    if folder is not None and k == 0:
        return _in_files(folder, _descriptors(xyz_path, cluster, membership, k))
    from kbs.inference import _compiled
    from kbs.tiles._sums import centre_sums, covariance_sums

    def array(name: str, shape: tuple[int, ...]) -> np.ndarray:
        if folder is None:
            return np.zeros(shape)
        return np.lib.format.open_memmap(folder / f"out-{name}.npy", mode="w+", dtype=np.float64, shape=shape)

    den, mass, c = array("sum-den", (k,)), array("mass", (k,)), array("sum-c", (k, 3))
    xyz = FileColumn(xyz_path, np.dtype(np.float64), (len(cluster), 3))
    for start, cl in cluster.chunks():
        stop = start + len(cl)
        centre_sums(xyz[start:stop], cl, membership[start:stop].astype(np.float64), *map(np.asarray, (den, mass, c)))
    centre, s = array("center", (k, 3)), array("sum-s", (k, 6))
    step = DESCRIPTOR_STEP  # clusters at a time: each one's numbers depend on its sums alone
    for a in range(0, k, step):
        b = min(k, a + step)
        ok = (den[a:b] > 0.0) & (mass[a:b] > 0.0)
        part = np.zeros((b - a, 3))
        part[ok] = c[a:b][ok] / den[a:b][ok, None]
        centre[a:b] = part
    for start, cl in cluster.chunks():
        stop = start + len(cl)
        covariance_sums(xyz[start:stop], cl, membership[start:stop].astype(np.float64), np.asarray(centre), np.asarray(s))
    cov, lam, vec = array("covariance", (k, 3, 3)), array("eigenvalues", (k, 3)), array("eigenvectors", (k, 3, 3))
    for a in range(0, k, step):
        b = min(k, a + step)
        ok = (den[a:b] > 0.0) & (mass[a:b] > 0.0)
        cov[a:b], lam[a:b], vec[a:b] = _compiled.covariance_eigen(np.ascontiguousarray(s[a:b]),
                                                                  np.ascontiguousarray(mass[a:b]), ok)
    out = {"center": centre, "covariance": cov, "eigenvalues": lam, "eigenvectors": vec, "mass": mass}
    if folder is None:
        return out
    for a_ in (den, c, s, *out.values()):
        a_.flush()  # type: ignore[attr-defined]
    del den, c, s, out, centre, cov, lam, vec, mass
    for name in ("sum-den", "sum-c", "sum-s"):
        (folder / f"out-{name}.npy").unlink()
    return {name: np.load(folder / f"out-{name}.npy", mmap_mode="r")
            for name in ("center", "covariance", "eigenvalues", "eigenvectors", "mass")}


def _descriptors_reference(xyz_path: Path, cluster: FileColumn, membership: FileColumn,
                           k: int) -> dict[str, np.ndarray]:
    """:func:`_descriptors` without the compiled kernels (``KBS_JIT=0``, or before they are
    compiled): ``cluster_geometry`` on each cluster's points, as :func:`stitch` computes them (the
    per-point arrays in memory then)."""
    from kbs.inference import cluster_geometry

    cl = np.asarray(cluster)
    weights = np.asarray(membership).astype(np.float64)
    X = np.load(xyz_path, mmap_mode="r")
    point_order = np.argsort(cl, kind="stable")
    starts = np.searchsorted(cl[point_order], np.arange(k + 1))
    out = {"center": np.zeros((k, 3)), "covariance": np.zeros((k, 3, 3)), "eigenvalues": np.zeros((k, 3)),
           "eigenvectors": np.zeros((k, 3, 3)), "mass": np.zeros(k)}
    for gi in range(k):
        idx = point_order[starts[gi]:starts[gi + 1]]
        geo = cluster_geometry(take_rows(X, idx), weights[idx])
        for name, value in (("center", geo.center), ("covariance", geo.covariance), ("eigenvalues", geo.eigenvalues),
                            ("eigenvectors", geo.eigenvectors), ("mass", geo.mass)):
            out[name][gi] = value
    del X
    return out


# -- the result ---------------------------------------------------------------------------------------


@dataclass
class StreamedResult:
    """A stitched tiled result whose per-point arrays (``cluster``, ``label``, ``membership``:
    :class:`FileColumn`) are in files and whose clusters and explanation are written piece by piece
    (:meth:`pieces`). ``explanation`` holds the root record alone (its ground, notes and the tiles
    as children)."""

    n: int
    columns: dict[str, FileColumn]
    label_names: list[str]
    explanation: Explanation
    tiling: dict[str, Any]
    seconds: float
    n_clusters: int
    n_splits: int
    points_per_label: dict[str, int]
    _tiles: Any  # a kbs.tiles.stream.SpilledTiles
    _tables: _Tables
    _store: TileStore
    _offsets: np.ndarray
    _roots: np.ndarray
    _out_of_root: np.ndarray
    _order: np.ndarray
    _members: np.ndarray
    _member_start: np.ndarray
    _shared: Mapping[int, list[str]]
    _stitched: _Marked
    _geometry: dict[str, np.ndarray]
    _sizes: np.ndarray
    #: The spill folder (the tiles' record texts, :func:`write_record_texts`).
    _folder: Path | None = None
    #: How the tiles were read, said in a note (not in the result: the same result either way).
    read_note: str | None = None

    @property
    def cluster(self) -> FileColumn:
        return self.columns["cluster"]

    @property
    def label(self) -> FileColumn:
        return self.columns["label"]

    @property
    def membership(self) -> FileColumn:
        return self.columns["membership"]

    @property
    def limits(self) -> list[tuple[int, str, Any]]:
        """The records a limit stopped, tile by tile: (n_points, id, limit); made when asked for."""
        return self._tables.limits(self._tiles.names)

    def summary(self) -> dict[str, Any]:
        """As :meth:`Segmentation.summary` (equal to it: the same JSON), with the limits' ids read
        from the spill folder when asked for (:class:`LimitIds`)."""
        return {"points": self.n, "clusters": self.n_clusters, "splits": self.n_splits,
                "limits": int(self._tables.limit_points.size),
                "limits_by_kind": self._tables.limits_by_kind(self._tiles.names),
                "points_per_label": dict(self.points_per_label), "seconds": round(self.seconds, 3)}

    def cluster_items(self) -> Iterator[dict[str, Any]]:
        """The output clusters (``clusters`` of a result), one at a time, as :func:`stitch` makes them."""
        from kbs.inference.geometry import ClusterGeometry

        # plain views of the mapped files: a memmap's indexing makes a memmap object each time
        geo_all = {name: np.asarray(a) for name, a in self._geometry.items()}
        members, member_start = np.asarray(self._members), np.asarray(self._member_start)
        core_sizes, sizes = np.asarray(self._tables.core_sizes), np.asarray(self._sizes)
        for gi, root in enumerate(np.asarray(self._order).tolist()):
            parts = []
            for g in members[member_start[root]:member_start[root + 1]].tolist():
                k = int(np.searchsorted(self._offsets, g, side="right")) - 1
                c = int(g - self._offsets[k])
                in_core = int(core_sizes[g])
                if in_core:
                    label, ids = self._tables.cluster(g)
                    name = self._tiles.names[k]
                    parts.append({"tile": name, "cluster": c, "label": label, "core_points": in_core,
                                  "ids": [f"{name}/{i}" for i in ids]})
            geo = ClusterGeometry(center=geo_all["center"][gi].copy(), covariance=geo_all["covariance"][gi].copy(),
                                  eigenvalues=geo_all["eigenvalues"][gi].copy(),
                                  eigenvectors=geo_all["eigenvectors"][gi].copy(), mass=float(geo_all["mass"][gi]))
            item = {"index": gi, "ids": [i for p in parts for i in p["ids"]], "label": parts[0]["label"],
                    "n_points": int(sizes[root]),
                    "descriptors": {"center": geo.center.tolist(), "normal": geo.normal.tolist(),
                                    "thickness": geo.thickness, "eigenvalues": geo.eigenvalues.tolist(),
                                    "mass": geo.mass}}
            if len(parts) > 1:
                item["stitched"] = parts
            yield item

    def records(self) -> Iterator[dict[str, Any]]:
        """The explanation's records in its order, as plain data (``to_dict``'s): the root, then
        each tile's, read from its file (:func:`kbs.tiles.stitch.stitched_record`)."""
        yield self.explanation.records[ROOT].to_dict()
        for k, t in enumerate(self._tiles):
            with np.load(self._store.path(t), allow_pickle=False) as f:
                doc = json.loads(bytes(f["doc"]).decode("utf-8"))
            for d in doc["explanation"]["clusters"]:  # to_dict's records: depth-first from the root
                yield stitched_record(d, t.name, int(self._offsets[k]), self._roots, self._out_of_root, self._shared,
                                      self._stitched)

    def record_texts(self) -> Iterator[str]:
        """:meth:`records` as their JSON texts (``strict_json`` of each, the same text), from the
        tiles' record texts (:func:`write_record_texts`): the stand-ins replaced, nothing decoded."""
        from kbs.io.result import strict_json
        from kbs.tiles.stitch import stitch_note

        yield strict_json(self.explanation.records[ROOT].to_dict())
        assert self._folder is not None
        for k, t in enumerate(self._tiles):
            with np.load(self._folder / f"{t.name}.records.npz", allow_pickle=False) as f:
                texts = bytes(f["text"]).decode("utf-8").split("\n")
                local = f["out"]
            g = int(self._offsets[k]) + local
            outs = np.full(local.shape, -1, dtype=np.int64)
            held = local >= 0  # a record of a tile cluster (none at all when every point was noise)
            outs[held] = np.asarray(self._out_of_root)[np.asarray(self._roots)[g[held]]]
            for text, lo, gi, out in zip(texts, local.tolist(), g.tolist(), outs.tolist()):
                if lo < 0:
                    yield text
                    continue
                note = stitch_note(t.name, gi, out, self._shared, self._stitched)
                if note is not None:
                    text = text.replace(NOTE_MARK, json.dumps(note), 1)
                elif "," + NOTE_MARK in text:
                    text = text.replace("," + NOTE_MARK, "", 1)
                else:
                    text = text.replace(NOTE_MARK, "", 1)
                yield text.replace(OUT_MARK, str(out) if out >= 0 else "null", 1)

    def pieces(self) -> dict[str, Callable[[], Iterator[str]]]:
        """The JSON text of ``clusters`` and ``explanation``, piece by piece (for
        :func:`kbs.io.result.write_result_pair`'s ``pieces``)."""
        from kbs.io.result import strict_json

        def clusters() -> Iterator[str]:
            yield "["
            for k, item in enumerate(self.cluster_items()):
                yield ("," if k else "") + strict_json(item)
            release_free_memory()
            yield "]"

        def records() -> Iterator[str]:
            yield "["
            for k, text in enumerate(self.record_texts() if self._folder is not None else
                                     map(strict_json, self.records())):
                yield ("," if k else "") + text
            release_free_memory()
            yield "]"

        def ground_tiles(tiles: _GroundTiles) -> Iterator[str]:  # GroundFacts.to_dict's "tiles", text as kept
            yield "{"
            for k, name in enumerate(tiles.names):
                yield ("," if k else "") + json.dumps(name) + ":" + tiles.text(k)
            yield "}"

        def explanation() -> Iterator[str]:
            alone = ClusterRecord(id=ROOT, parent=None, depth=0, n_points=self.n)  # its records are written here
            e, tiles = self.explanation, self.explanation.ground.tiles
            lazy = tiles if isinstance(tiles, _GroundTiles) else None
            d = dataclasses.replace(e, records={ROOT: alone}, ground=e.ground if lazy is None else
                                    dataclasses.replace(e.ground, tiles=None)).to_dict()
            markers: dict[str, Callable[[], Iterator[str]]] = {"\x00kbs records\x00": records}
            d["clusters"] = "\x00kbs records\x00"
            if lazy is not None:  # "tiles" where GroundFacts.to_dict puts it: after the other facts, before local_model
                markers["\x00kbs ground tiles\x00"] = functools.partial(ground_tiles, lazy)
                facts = d["ground"]
                d["ground"] = {k: v for k, v in facts.items() if k != "local_model"}
                d["ground"]["tiles"] = "\x00kbs ground tiles\x00"
                if "local_model" in facts:
                    d["ground"]["local_model"] = facts["local_model"]
            text = strict_json(d)
            while markers:  # each marker's pieces where it is, in the order they come
                at, marker = min((text.index(json.dumps(m)), m) for m in markers)
                yield text[:at]
                yield from markers.pop(marker)()
                text = text[at + len(json.dumps(marker)):]
            yield text

        def summary() -> Iterator[str]:  # the limits' ids written as they are read, not held as a list
            d = self.summary()
            ids = {f"\x00kbs limit ids {kind}\x00": e["clusters"] for kind, e in d["limits_by_kind"].items()}
            for marker, (kind, e) in zip(ids, list(d["limits_by_kind"].items())):
                d["limits_by_kind"][kind] = {**e, "clusters": marker}
            text = strict_json(d)
            for marker, seq in ids.items():
                at = text.index(json.dumps(marker))
                yield text[:at] + "["
                for k, rid in enumerate(seq):
                    yield ("," if k else "") + json.dumps(rid)
                yield "]"
                text = text[at + len(json.dumps(marker)):]
            yield text

        def tiling() -> Iterator[str]:  # the tiling's entries written one by one, not made as a list
            d = dict(self.tiling)
            entries = d["tiles"]
            d["tiles"] = "\x00kbs tiling tiles\x00"
            text = strict_json(d)
            at = text.index(json.dumps(d["tiles"]))
            yield text[:at] + "["
            for k, entry in enumerate(entries):
                yield ("," if k else "") + strict_json(entry)
            yield "]" + text[at + len(json.dumps(d["tiles"])):]

        return {"clusters": clusters, "explanation": explanation, "summary": summary, "tiling": tiling}
