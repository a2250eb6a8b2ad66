"""Streamed tiling of a LAS/LAZ file: read in chunks, every point routed to the tiles that hold it.

``kbs run --tile SIZE BIG.laz`` does not read the file into memory as one ``laspy.LasData``. It
reads it in chunks of ``chunk_points`` (laspy's ``chunk_iterator``) twice:

1. the extent of the cloud in the ground plane (the grid's corner and shape, exactly as
   :meth:`~kbs.tiles.grid.TileGrid.fit` finds them from the whole cloud);
2. every point's coordinates into ``xyz.npy`` (a memory-mapped file in the spill folder: pages the
   operating system can drop, not the process's own memory) and its index into the file of every
   tile (core or buffer) that holds it, ``<tile>.idx``.

The tiles are then what :meth:`TileGrid.tiles` gives for the whole cloud, in the same order, with
the same indices, so the tiled result is the in-memory one, byte for byte. The result is written
in chunks too (:func:`write_las_chunked`): the input's records read again chunk by chunk, the
result's dimensions added.

What stays proportional to the cloud in the process that stitches: the per-point result arrays
(cluster, label, membership: 12 bytes a point) and the tiles' index arrays while stitching (8
bytes a point and buffer point). The points themselves stay in the memory-mapped file.
"""
from __future__ import annotations

import copy
import datetime
import functools
import math
import os
import re
import types
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import CloudFileError
from kbs.knowledge.segmenter import coordinate_problem
from kbs.tiles.grid import Tile, TileGrid, grid_shape, ground_axes

#: Points read at a time from a LAS/LAZ file (``kbs run --chunk-points``).
DEFAULT_CHUNK_POINTS = 1_000_000


@dataclass
class SpilledCloud:
    """A LAS/LAZ file cut into tiles on disk (:func:`spill_las`).

    Attributes
    ----------
    xyz : ndarray (n, 3) float64
        The coordinates, memory-mapped from ``folder/xyz.npy``.
    index : ndarray (n,) int64
        0 .. n-1, memory-mapped (``PointCloud.index``).
    grid : TileGrid
    tiles : sequence of Tile
        As ``grid.tiles(xyz)``: a :class:`SpilledTiles` (its numbers in arrays, each tile made when
        asked for).
    header : laspy.LasHeader
        The input's header (point format, VLRs, CRS).
    folder : Path
        The spill folder (removed by :meth:`remove`).
    width : float
        The points' widest extent along the ground axes (``kbs run`` checks ``limits.tile`` with
        it after deciding from the header's bounds).
    """

    xyz: np.ndarray
    index: np.ndarray
    grid: TileGrid
    tiles: Sequence[Tile]
    header: Any
    folder: Path
    width: float = math.nan

    def remove(self) -> None:
        """Delete the spill files (and the folder if nothing else is in it)."""
        for path in self.folder.glob("*"):
            if path.suffix in (".idx", ".core", ".npy", ".npz", ".bin", ".pkl", ".part"):
                path.unlink(missing_ok=True)
        try:
            self.folder.rmdir()
        except OSError:
            pass


def _chunks(path: Path, chunk_points: int):
    import laspy

    from kbs.io.readers import library_noise

    try:
        with library_noise(path):  # the header's warnings, naming the file
            reader = laspy.open(os.fspath(path))
        with reader:
            for chunk in reader.chunk_iterator(chunk_points):
                yield np.column_stack([np.asarray(chunk.x, dtype=np.float64), np.asarray(chunk.y, dtype=np.float64),
                                       np.asarray(chunk.z, dtype=np.float64)])
    except (OSError, ValueError, laspy.errors.LaspyException) as exc:
        raise CloudFileError(str(path), f"cannot read in chunks: {exc}") from exc


def las_header(path: Path) -> Any:
    """The header of a LAS/LAZ file (nothing else read)."""
    import laspy

    from kbs.io.readers import library_noise

    try:
        with library_noise(path), laspy.open(os.fspath(path)) as reader:
            return copy.deepcopy(reader.header)
    except (OSError, ValueError, laspy.errors.LaspyException) as exc:
        raise CloudFileError(str(path), f"cannot read the header: {exc}") from exc


def spill_las(path: str | os.PathLike[str], folder: str | os.PathLike[str], size: float, buffer: float,
              normal: Any = None, chunk_points: int = DEFAULT_CHUNK_POINTS) -> SpilledCloud:
    """Cut the LAS/LAZ file ``path`` into tiles of ``size`` with ``buffer`` in the ground plane
    (across ``normal``; None: x-y), reading ``chunk_points`` points at a time; the spill files go
    to ``folder``.

    Raises
    ------
    CloudFileError
        The file cannot be read, holds no point, or a coordinate the engine cannot take
        (:func:`kbs.knowledge.segmenter.coordinate_problem`, the error of an untiled run).
    ParameterError
        Bad size or buffer (as :meth:`TileGrid.fit`).
    """
    path, folder = Path(os.fspath(path)), Path(os.fspath(folder))
    header = las_header(path)
    n = int(header.point_count)
    if n == 0:
        raise CloudFileError(str(path), "holds no point")
    axes = ground_axes(normal)
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    first, count, start = None, 0, 0
    for X in _chunks(path, chunk_points):  # 1: the extent, and coordinates the engine cannot take
        problem = coordinate_problem(X)
        if problem is not None:
            count += int(problem.split(" points have", 1)[0].replace(",", ""))
            if first is None:  # its row counts from the chunk's start: from the file's
                first = re.sub(r"\(first: row (\d+)", functools.partial(_row_from, start), problem, count=1)
        start += len(X)
        uv = X @ axes.T
        lo = np.minimum(lo, uv.min(axis=0))
        hi = np.maximum(hi, uv.max(axis=0))
    if first is not None:
        raise CloudFileError(str(path), f"{count:,}" + first[first.index(" points have"):])
    grid = _grid(size, buffer, axes, lo, hi)
    folder.mkdir(parents=True, exist_ok=True)
    core_count, tile_count = _Counts(grid.shape), _Counts(grid.shape)
    start = 0
    # written with plain writes, not through a memory map: the pages written do not stay in this
    # process's resident memory (a map's dirty pages would, the whole cloud's)
    with open(folder / "xyz.npy", "wb") as xyz_out, open(folder / "index.npy", "wb") as index_out:
        _npy_header(xyz_out, np.float64, (n, 3))
        _npy_header(index_out, np.int64, (n,))
        for X in _chunks(path, chunk_points):  # 2: the points, and each to its tiles
            m = len(X)
            if start + m > n:
                raise CloudFileError(str(path), f"holds more points than its header's {n:,}")
            xyz_out.write(np.ascontiguousarray(X, dtype="<f8").tobytes())
            gi = np.arange(start, start + m, dtype=np.int64)
            index_out.write(gi.astype("<i8").tobytes())
            uv = X @ grid.axes.T
            ij = grid.cells(uv)
            core_count.add(ij[:, 0], ij[:, 1], 1)
            for (i, j), rows in _tile_rows(grid, uv).items():
                target = folder / f"t{i}_{j}.idx"  # not a dict of paths: one per tile, millions at 10^10 points
                with open(target, "ab") as stream:
                    gi[rows].tofile(stream)
                with open(target.with_suffix(".core"), "ab") as stream:
                    ((ij[rows, 0] == i) & (ij[rows, 1] == j)).tofile(stream)
                tile_count.add(i, j, rows.size)
            start += m
    if start != n:
        raise CloudFileError(str(path), f"holds {start:,} points, its header says {n:,}")
    xyz = np.load(folder / "xyz.npy", mmap_mode="r")
    index = np.load(folder / "index.npy", mmap_mode="r")
    rows, cols = core_count.nonzero()  # row by row, as TileGrid.tiles
    tiles = SpilledTiles(grid, folder, rows, cols, tile_count.at(rows, cols), core_count.at(rows, cols))
    return SpilledCloud(xyz=xyz, index=index, grid=grid, tiles=tiles, header=header, folder=folder,
                        width=float((hi - lo).max()))


class SpilledTile(Tile):
    """A :class:`~kbs.tiles.grid.Tile` of a spilled cloud whose ``index`` and ``in_core`` stay in
    the spill folder (``<name>.idx``, ``<name>.core``), read each time they are asked for: the
    process that plans and stitches holds no per-point array of the tiles.

    Attributes
    ----------
    folder : Path
    n_points, n_core : int
        The tile's points (core and buffer) and its core's.
    """

    folder: Path
    n_points: int
    n_core: int

    def __init__(self, name: str, i: int, j: int, core: tuple[float, float, float, float], folder: Path,
                 n_points: int, n_core: int) -> None:
        for key, value in (("name", name), ("i", i), ("j", j), ("core", core),
                           ("folder", folder if isinstance(folder, Path) else Path(folder)),  # one Path for all tiles
                           ("n_points", n_points), ("n_core", n_core)):
            object.__setattr__(self, key, value)

    @property  # type: ignore[override]
    def index(self) -> np.ndarray:
        return np.fromfile(self.folder / f"{self.name}.idx", dtype=np.int64)

    @property  # type: ignore[override]
    def in_core(self) -> np.ndarray:
        return np.fromfile(self.folder / f"{self.name}.core", dtype=np.bool_)


class MadeWhenAsked(Sequence[Any]):
    """A sequence whose items are made when asked for, by ``_one(k)`` (0 <= k < len): indexing with
    negative indices and slices as a list's, not one object per item held."""

    def __len__(self) -> int:
        raise NotImplementedError

    def _one(self, k: int) -> Any:
        raise NotImplementedError

    def __getitem__(self, k: Any) -> Any:
        if isinstance(k, slice):
            return [self._one(x) for x in range(*k.indices(len(self)))]
        k = int(k)
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        return self._one(k % len(self))


class SpilledTiles(MadeWhenAsked):
    """The tiles of a spilled cloud, row by row: their cells and counts in arrays, each
    :class:`SpilledTile` made when asked for. The process that plans and stitches holds a few
    numbers a tile, not an object (about 430 bytes with its name, its core's tuple and its counts:
    about 1 GB at the 2 million tiles of 10^10 points).

    Parameters
    ----------
    grid : TileGrid
    folder : Path
        The spill folder (the tiles' ``.idx`` and ``.core`` files).
    i, j : array of int
        The tiles' cells, row by row (increasing ``i * grid.shape[1] + j``).
    n_points, n_core : array of int
        Each tile's points (core and buffer) and its core's.
    """

    def __init__(self, grid: TileGrid, folder: Path, i: Any, j: Any, n_points: Any, n_core: Any) -> None:
        self.grid, self.folder = grid, Path(folder)
        self.i = np.asarray(i, dtype=np.int32)
        self.j = np.asarray(j, dtype=np.int32)
        self.n_points = np.asarray(n_points, dtype=np.int64)
        self.n_core = np.asarray(n_core, dtype=np.int64)
        self.cell = self.i.astype(np.int64) * int(grid.shape[1]) + self.j
        if self.cell.size > 1 and not np.all(np.diff(self.cell) > 0):
            raise ValueError("the tiles are not in row order")
        self.names = TileNames(self)

    def __len__(self) -> int:
        return int(self.i.size)

    def _one(self, k: int) -> SpilledTile:
        i, j = int(self.i[k]), int(self.j[k])
        g = self.grid
        u0, v0 = g.origin[0] + i * g.size, g.origin[1] + j * g.size  # as TileGrid.tiles computes them
        return SpilledTile(f"t{i}_{j}", i, j, (u0, v0, u0 + g.size, v0 + g.size), self.folder,
                           int(self.n_points[k]), int(self.n_core[k]))

    def __iter__(self) -> Iterator[SpilledTile]:
        return (self._one(k) for k in range(len(self)))

    def at(self, i: int, j: int) -> int | None:
        """The place of the tile of cell (i, j), None where no tile is."""
        if not (0 <= i < self.grid.shape[0] and 0 <= j < self.grid.shape[1]):
            return None
        key = i * int(self.grid.shape[1]) + j
        k = int(np.searchsorted(self.cell, key))
        return k if k < self.cell.size and int(self.cell[k]) == key else None



class TileNames(MadeWhenAsked):
    """The names of :class:`SpilledTiles` (``t<i>_<j>``), made when asked for; ``index`` finds a
    name's place from its cell."""

    def __init__(self, tiles: SpilledTiles) -> None:
        self.tiles = tiles

    def __len__(self) -> int:
        return len(self.tiles)

    def _one(self, k: int) -> str:
        return f"t{int(self.tiles.i[k])}_{int(self.tiles.j[k])}"

    def __iter__(self) -> Iterator[str]:
        return (f"t{i}_{j}" for i, j in zip(self.tiles.i.tolist(), self.tiles.j.tolist()))

    def index(self, name: Any, start: int = 0, stop: Any = None) -> int:
        m = re.fullmatch(r"t(\d+)_(\d+)", name) if isinstance(name, str) else None
        k = None if m is None else self.tiles.at(int(m.group(1)), int(m.group(2)))
        if k is None or k < start or (stop is not None and k >= stop):
            raise ValueError(f"{name!r} is not a tile")
        return k

    def __contains__(self, name: object) -> bool:
        try:
            self.index(name)
        except ValueError:
            return False
        return True


def _row_from(start: int, m: re.Match[str]) -> str:
    """A chunk's row in :func:`coordinate_problem`'s message, counted from the file's start."""
    return f"(first: row {int(m.group(1)) + start}"


def _npy_header(stream: Any, dtype: Any, shape: tuple[int, ...]) -> None:
    """The header of a ``.npy`` file of ``shape`` and ``dtype`` (little-endian, C order), its data
    to be written after it."""
    np.lib.format.write_array_header_1_0(stream, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype).newbyteorder("<")),
                                                  "fortran_order": False, "shape": shape})


class _Counts:
    """Counts per cell of a grid of ``shape``: an array when the grid has at most :attr:`DENSE`
    cells, else a dict of the cells counted (a cloud with a few far points spans a grid of
    millions of cells, nearly all empty: an array of them all would not fit in memory)."""

    DENSE = 10 ** 7

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.dense = np.zeros(shape, dtype=np.int64) if shape[0] * shape[1] <= self.DENSE else None
        self.sparse: dict[int, int] = {}

    def add(self, i: Any, j: Any, n: int) -> None:
        """Add ``n`` at each cell (i, j) (arrays: once per pair, repeated cells counted each time)."""
        if self.dense is not None:
            np.add.at(self.dense, (i, j), n)
            return
        cells, counts = np.unique(np.asarray(i, np.int64) * self.shape[1] + np.asarray(j, np.int64), return_counts=True)
        for c, k in zip(cells.tolist(), counts.tolist()):
            self.sparse[c] = self.sparse.get(c, 0) + k * n

    def nonzero(self) -> tuple[np.ndarray, np.ndarray]:
        """The cells counted, row by row."""
        if self.dense is not None:
            rows, cols = np.nonzero(self.dense)
            return rows, cols
        cells = np.array(sorted(c for c, k in self.sparse.items() if k), dtype=np.int64)
        return cells // self.shape[1], cells % self.shape[1]

    def at(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        if self.dense is not None:
            return self.dense[i, j]
        return np.array([self.sparse.get(c, 0) for c in (i * self.shape[1] + j).tolist()], dtype=np.int64)


def _grid(size: float, buffer: float, axes: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> TileGrid:
    """The grid :meth:`TileGrid.fit` gives for a cloud of ground extent ``lo`` .. ``hi``."""
    TileGrid.fit(np.zeros((1, 3)), size, buffer)  # its checks of size and buffer
    return TileGrid(float(size), float(buffer), axes, (float(lo[0]), float(lo[1])), grid_shape(lo, hi, float(size)))


def _tile_rows(grid: TileGrid, uv: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """For the points ``uv`` of a chunk: the rows each tile (core widened by the buffer, the grid's
    outer edges reaching everything) holds, by the comparisons of :meth:`TileGrid.tiles`."""
    core = grid.cells(uv)
    # a point lies in the tiles at most this many cells from its core: the buffer reaches
    # floor(buffer / size) cells past the neighbour (a margin for a ratio a rounding away from whole)
    reach = int(math.floor(grid.buffer / grid.size + 1e-9)) + 1
    reach = min(reach, max(grid.shape))  # no tile lies farther: a buffer of 1e9 is the whole grid, not 10^8 steps
    steps = range(-reach, reach + 1)
    # each axis's test alone (the tile holds a point when both hold), made once per axis and step
    inside: list[dict[int, np.ndarray]] = []
    for axis in range(2):
        by_step = {}
        for d in steps:
            c = core[:, axis] + d
            ok = (c >= 0) & (c < grid.shape[axis])
            c0 = np.where(ok, c, 0)
            start = grid.origin[axis] + c0 * grid.size
            lo = np.where(c0 == 0, -np.inf, start - grid.buffer)
            hi = np.where(c0 == grid.shape[axis] - 1, np.inf, start + grid.size + grid.buffer)
            by_step[d] = ok & (uv[:, axis] >= lo) & (uv[:, axis] <= hi)
        inside.append(by_step)
    rows_all, ids_all = [], []
    for di in steps:
        for dj in steps:
            rows = np.flatnonzero(inside[0][di] & inside[1][dj])
            rows_all.append(rows)
            ids_all.append((core[rows, 0] + di) * grid.shape[1] + core[rows, 1] + dj)
    rows = np.concatenate(rows_all)
    ids = np.concatenate(ids_all)
    order = np.argsort(ids * max(1, len(uv)) + rows)  # by tile, then by row (a point is once in a tile)
    rows, ids = rows[order], ids[order]
    cut = np.flatnonzero(np.diff(ids)) + 1
    out = {}
    for r, t in zip(np.split(rows, cut), ids[np.concatenate([[0], cut])] if ids.size else []):
        out[(int(t) // grid.shape[1], int(t) % grid.shape[1])] = r
    return out


class ChunkedLas:
    """A LAS/LAZ result written chunk by chunk: the input's records read again ``chunk_points`` at a
    time, with the result's dimensions (and ASPRS classification) added, as
    :func:`kbs.io.las.build_las` adds them to the whole input. ``write(path)`` as ``LasData``'s."""

    def __init__(self, source: Path, results: Mapping[str, np.ndarray], classification: np.ndarray | None,
                 run_id: str, chunk_points: int) -> None:
        self.source, self.results, self.classification = source, results, classification
        self.run_id, self.chunk_points = run_id, chunk_points

    def header(self) -> Any:
        import laspy

        from kbs.io.las import KBS_DIMENSIONS, run_id_vlr, software_id, without_copc

        header = las_header(self.source)
        kept = set(header.point_format.extra_dimension_names)
        self.renamed = {name: f"{name}_in"[:32] for name in KBS_DIMENSIONS if name in kept}
        if self.renamed:  # an earlier result's field: kept as <name>_in (build_las's order: removed, added last)
            descs = {d.name: d.description for d in header.point_format.extra_dimensions}
            dtypes = {d.name: d.dtype for d in header.point_format.extra_dimensions}
            for name, new in self.renamed.items():
                header.remove_extra_dim(name)
                header.add_extra_dim(laspy.ExtraBytesParams(new, dtypes[name], description=descs[name][:32]))
        without_copc(header)
        header.add_extra_dims([laspy.ExtraBytesParams(name, dtype, description=desc)
                               for name, (dtype, desc) in KBS_DIMENSIONS.items()])
        header.vlrs.append(run_id_vlr(self.run_id))
        header.generating_software = software_id()
        header.creation_date = datetime.date.today()
        return header

    def write(self, path: str) -> None:
        import laspy

        from kbs.io.las import KBS_DIMENSIONS

        header = self.header()
        start, first = 0, None
        with laspy.open(os.fspath(self.source)) as reader, \
                laspy.open(path, mode="w", header=header, do_compress=path.lower().endswith(".laz")) as writer:
            for chunk in reader.chunk_iterator(self.chunk_points):
                m = len(chunk)
                out = laspy.ScaleAwarePointRecord.zeros(m, header=header)
                for name in chunk.point_format.dimension_names:
                    out[self.renamed.get(name, name)] = chunk[name]
                for name, (dtype, _) in KBS_DIMENSIONS.items():
                    out[name] = np.asarray(self.results[name][start:start + m]).astype(dtype)
                if self.classification is not None:
                    out.classification = self.classification[start:start + m]
                writer.write_points(out)
                first = out if first is None else first
                start += m
            extra = writer.header.vlrs.get("ExtraBytesVlr")
            if extra and first is not None:
                # the extra-bytes statistics as LasData.write leaves them for the whole record (laspy
                # 2.x grows them from each record's first point only, so chunks would differ)
                extra[0].partial_reset()
                extra[0].grow(first)


def streamed_cloud(spilled: SpilledCloud, path: Path) -> Any:
    """A :class:`kbs.io.PointCloud` over the spilled coordinates (no copy; no per-point field), its
    ``source`` the header alone (what the LAS checks read)."""
    from kbs.io import PointCloud
    from kbs.io.readers import las_crs

    units, crs = las_crs(spilled.header, path)
    return PointCloud(xyz=spilled.xyz, fields={}, shape=None, index=spilled.index, n_read=len(spilled.xyz),
                      n_dropped=0, path=str(path), units=units, crs=crs,
                      source=types.SimpleNamespace(header=spilled.header))
