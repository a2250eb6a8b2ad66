"""A tiled run of a COPC file: each tile reads its buffered bounds by a query of the file's octree.

A COPC file (https://copc.io) is a LAZ 1.4 file whose LAZ chunks are the nodes of an octree, and
whose hierarchy (every node's key, file offset, size and point count) is in the file. A point's
row in the file is the points of the nodes stored before its node (by offset) plus its place in
its node, so a tile that reads the nodes meeting its bounds knows its points' rows without any
routing pass: ``kbs run --tile`` on a COPC file (:func:`kbs.cli.run.run_scan`) then

1. reads the header and the whole hierarchy (:func:`copc_nodes`: checked against the file's size
   and the header's point count), and reads every node once, in file order
   (:func:`read_copc`): the coordinates to ``xyz.npy`` (the stitching sums each cluster's points
   in row order, and ``--meshes`` and ``--report`` draw them), the sample of every k-th point the
   ground plane is found on, the extent the grid is planned from and the coordinates the engine
   cannot take: what the spill pass of :func:`kbs.tiles.stream.spill_las` finds, without its
   second pass nor routing a point to its tiles;
2. each tile (in process, or in its Dask task) selects the nodes whose bounds meet its buffered
   bounds and reads their rows of ``xyz.npy`` (one slice a node: decompressed once, in 1; the
   tiles decompressing their nodes again was measured slower than the spill path, each tile
   decoding the octree's coarse levels anew) (:func:`read_tile`), keeps the points the tile
   holds, by the comparisons of
   :meth:`~kbs.tiles.grid.TileGrid.tiles`, in row order, and writes their rows to the spill
   folder, so the tile's points, their order and the stitching are those of the spill path: the
   result is the same, byte for byte.

Only a ground plane of x and y is read this way (a node's bounds are a box of x, y and z; tiles
across another ground normal are squares in another plane): :func:`copc_reason` says when the
spill path reads the file instead.
"""
from __future__ import annotations

import functools
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kbs.arrays import rows as take_rows
from kbs.errors import CloudFileError
from kbs.knowledge.segmenter import coordinate_problem
from kbs.tiles.grid import TileGrid, ground_axes
from kbs.tiles.stream import (DEFAULT_CHUNK_POINTS, SpilledCloud, SpilledTile, SpilledTiles, _Counts, _grid, _npy_header,
                             _row_from)

#: ``KBS_COPC=0`` reads a COPC file as a plain LAZ file (the spill path), e.g. to compare.
ENV = "KBS_COPC"
#: A node's bounds are widened by this share of its side when tiles select the nodes they read
#: (a point on a node's face; reading one node more costs time, not a result).
NODE_SLACK = 1e-3

#: The columns of a node table (:attr:`CopcCloud.nodes`): the key (level, x, y, z), the LAZ
#: chunk's offset and size in bytes, its points, its first row in the file.
LEVEL, KX, KY, KZ, OFFSET, SIZE, COUNT, FIRST = range(8)


def is_copc(header: Any) -> bool:
    """Whether a LAS header (``laspy.LasHeader``) is a COPC file's: its COPC info VLR."""
    return any(getattr(v, "user_id", "") == "copc" and getattr(v, "record_id", None) == 1 for v in header.vlrs)


def copc_reason(header: Any, normal: Any) -> str | None:
    """Why a tiled run does not read a file by its COPC octree (None: it does): not a COPC
    file, ``KBS_COPC=0``, or a ground plane other than x-y."""
    if not is_copc(header):
        return "not a COPC file"
    if os.environ.get(ENV, "1").strip() == "0":
        return f"{ENV}=0"
    if not np.array_equal(ground_axes(normal), np.eye(3)[:2]):
        return ("the rule base's ground plane is not x-y: its tiles are squares across its ground normal, the "
                "octree's nodes boxes of x, y and z")
    return None


def _selection() -> Any:
    import laspy

    return laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z


def _key(row: np.ndarray) -> str:
    return "-".join(str(int(v)) for v in row[:4])


def copc_nodes(path: Path) -> tuple[np.ndarray, np.ndarray, Any]:
    """The nodes of a COPC file's octree holding points, in file order (a table of
    :data:`LEVEL` .. :data:`FIRST`, int64), their x-y bounds ``(x0, y0, x1, y1)`` and the header.

    Raises
    ------
    CloudFileError
        The file cannot be read as COPC, its hierarchy or a node lies past its end, nodes
        overlap, or their points are not the header's count.
    """
    import laspy
    from laspy.copc import load_octree_for_query

    size = path.stat().st_size if path.exists() else 0
    try:
        with laspy.CopcReader.open(os.fspath(path), decompression_selection=_selection()) as reader:
            info = reader.copc_info
            end = info.hierarchy_root_offset + info.hierarchy_root_size
            if end > size:
                raise CloudFileError(str(path), f"is truncated: its COPC hierarchy (bytes {info.hierarchy_root_offset:,}"
                                                f" to {end:,}) reaches past the end of the file ({size:,} bytes)")
            octree = load_octree_for_query(reader.source, info, reader.root_page)
            header = reader.header
    except CloudFileError:
        raise
    except (OSError, ValueError, struct_error(), laspy.errors.LaspyException) as exc:
        raise CloudFileError(str(path), f"cannot read its COPC header and hierarchy: {exc}") from exc
    nodes = [n for n in octree if n.point_count > 0]
    table = np.array([[n.key.level, n.key.x, n.key.y, n.key.z, n.offset, n.byte_size, n.point_count, 0] for n in nodes],
                     dtype=np.int64).reshape(-1, 8)
    bounds = np.array([[n.bounds.mins[0], n.bounds.mins[1], n.bounds.maxs[0], n.bounds.maxs[1]] for n in nodes],
                      dtype=np.float64).reshape(-1, 4)
    order = np.argsort(table[:, OFFSET], kind="stable")
    table, bounds = table[order], bounds[order]
    table[:, FIRST] = np.concatenate([[0], np.cumsum(table[:, COUNT])[:-1]]) if len(table) else []
    ends = table[:, OFFSET] + table[:, SIZE]
    for k in range(len(table)):
        if ends[k] > size:
            raise CloudFileError(str(path), f"is truncated: COPC octree node {_key(table[k])} (bytes "
                                            f"{int(table[k, OFFSET]):,} to {int(ends[k]):,}) reaches past the end of "
                                            f"the file ({size:,} bytes)")
        if k + 1 < len(table) and ends[k] > table[k + 1, OFFSET]:
            raise CloudFileError(str(path), f"COPC octree nodes {_key(table[k])} and {_key(table[k + 1])} overlap "
                                            f"(bytes {int(table[k, OFFSET]):,} to {int(ends[k]):,} and from "
                                            f"{int(table[k + 1, OFFSET]):,})")
    total = int(table[:, COUNT].sum())
    if total != int(header.point_count):
        raise CloudFileError(str(path), f"its COPC octree's nodes hold {total:,} points, its header says "
                                        f"{int(header.point_count):,}")
    return table, bounds, header


def struct_error() -> type[Exception]:
    import struct

    return struct.error


def decompress(path: str, table: np.ndarray, reader: Any = None) -> np.ndarray:
    """The coordinates (m, 3) float64 of the nodes ``table`` (rows of a node table, in file order),
    their points in file order (node after node)."""
    import laspy
    from laspy.copc import OctreeNode

    if not len(table):
        return np.zeros((0, 3))
    own = reader is None
    try:
        if own:
            reader = laspy.CopcReader.open(path, decompression_selection=_selection())
        nodes = []
        for row in table:
            node = OctreeNode()
            node.key.level, node.key.x, node.key.y, node.key.z = (int(v) for v in row[:4])
            node.offset, node.byte_size, node.point_count = int(row[OFFSET]), int(row[SIZE]), int(row[COUNT])
            nodes.append(node)
        points = reader._fetch_and_decompress_points_of_nodes(nodes)  # sorted by offset: file order
        return np.column_stack([np.asarray(points.x, dtype=np.float64), np.asarray(points.y, dtype=np.float64),
                                np.asarray(points.z, dtype=np.float64)])
    except (OSError, ValueError, RuntimeError, struct_error(), laspy.errors.LaspyException) as exc:
        if len(table) > 1:  # the node at fault, named alone
            for k in range(len(table)):
                decompress(path, table[k:k + 1], reader)
        first, last = table[0], table[-1]
        raise CloudFileError(path, f"cannot decompress COPC octree node{'s' if len(table) > 1 else ''} "
                                   f"{_key(first)}{' .. ' + _key(last) if len(table) > 1 else ''} (bytes "
                                   f"{int(first[OFFSET]):,} to {int(last[OFFSET] + last[SIZE]):,}): {exc}") from exc
    finally:
        if own and reader is not None:
            reader.source.close()


@dataclass
class CopcCloud(SpilledCloud):
    """A COPC file read for a tiled run (:func:`read_copc`): ``xyz``, ``index``, ``grid``,
    ``header``, ``folder`` and ``width`` as a :class:`~kbs.tiles.stream.SpilledCloud`'s, ``tiles``
    empty until the tiles are read (:func:`kbs.tiles.streamed.segment_copc`).

    Attributes
    ----------
    path : Path
        The COPC file.
    nodes, bounds : ndarray
        Its node table and the nodes' x-y bounds (:func:`copc_nodes`).
    sample : ndarray (m, 3)
        Every :func:`kbs.tiles.run.ground_step`-th point, in file order.
    read_by_tiles : list of int
        The points each tile decompressed (filled as the tiles are read).
    """

    path: Path = Path()
    nodes: np.ndarray = field(default_factory=lambda: np.zeros((0, 8), dtype=np.int64))
    bounds: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    sample: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    read_by_tiles: list[int] = field(default_factory=list)

    def nodes_of(self, lo: tuple[float, float], hi: tuple[float, float]) -> np.ndarray:
        """The rows of the node table whose x-y bounds (widened by :data:`NODE_SLACK`) meet the box
        ``lo`` .. ``hi`` (infinite sides allowed)."""
        b = self.bounds
        slack = NODE_SLACK * (b[:, 2] - b[:, 0])
        keep = (b[:, 2] + slack >= lo[0]) & (b[:, 0] - slack <= hi[0]) & \
            (b[:, 3] + slack >= lo[1]) & (b[:, 1] - slack <= hi[1])
        return self.nodes[keep]


def read_copc(path: str | os.PathLike[str], folder: str | os.PathLike[str], size: float, buffer: float,
              chunk_points: int = DEFAULT_CHUNK_POINTS) -> CopcCloud:
    """Read the COPC file ``path`` for tiles of ``size`` with ``buffer`` in the x-y plane: its
    hierarchy, then each node once in file order (``chunk_points`` points at a time, about) for the
    coordinates (``folder/xyz.npy``), the ground sample and the extent. The tiles are read later,
    each by its own octree query.

    Raises
    ------
    CloudFileError
        As :func:`copc_nodes`, a node that cannot be decompressed, no point, or a coordinate the
        engine cannot take (the error :func:`kbs.tiles.stream.spill_las` gives, the same row).
    ParameterError
        Bad size or buffer.
    """
    import laspy

    from kbs.tiles.run import ground_step

    path, folder = Path(os.fspath(path)), Path(os.fspath(folder))
    table, bounds, header = copc_nodes(path)
    n = int(header.point_count)
    if n == 0:
        raise CloudFileError(str(path), "holds no point")
    axes = ground_axes(None)
    step = ground_step(n)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    first, count, start = None, 0, 0
    samples = []
    folder.mkdir(parents=True, exist_ok=True)
    groups, group, held = [], [], 0  # nodes of about chunk_points points at a time, in file order
    for k in range(len(table)):
        group.append(k)
        held += int(table[k, COUNT])
        if held >= chunk_points:
            groups.append(group)
            group, held = [], 0
    if group:
        groups.append(group)
    try:
        reader = laspy.CopcReader.open(os.fspath(path), decompression_selection=_selection())
    except (OSError, ValueError, laspy.errors.LaspyException) as exc:
        raise CloudFileError(str(path), f"cannot read its COPC header: {exc}") from exc
    try:
        with open(folder / "xyz.npy", "wb") as xyz_out, open(folder / "index.npy", "wb") as index_out:
            _npy_header(xyz_out, np.float64, (n, 3))
            _npy_header(index_out, np.int64, (n,))
            for g in groups:
                X = decompress(str(path), table[g], reader)
                problem = coordinate_problem(X)
                if problem is not None:
                    count += int(problem.split(" points have", 1)[0].replace(",", ""))
                    if first is None:
                        first = re.sub(r"\(first: row (\d+)", functools.partial(_row_from, start), problem, count=1)
                m = len(X)
                xyz_out.write(np.ascontiguousarray(X, dtype="<f8").tobytes())
                index_out.write(np.arange(start, start + m, dtype="<i8").tobytes())
                rows = np.arange(-start % step, m, step)
                samples.append(take_rows(X, rows))
                uv = X @ axes.T
                lo, hi = np.minimum(lo, uv.min(axis=0)), np.maximum(hi, uv.max(axis=0))
                start += m
    finally:
        reader.source.close()
    if first is not None:
        raise CloudFileError(str(path), f"{count:,}" + first[first.index(" points have"):])
    grid = _grid(size, buffer, axes, lo, hi)
    return CopcCloud(xyz=np.load(folder / "xyz.npy", mmap_mode="r"), index=np.load(folder / "index.npy", mmap_mode="r"),
                     grid=grid, tiles=[], header=header, folder=folder, width=float((hi - lo).max()), path=path,
                     nodes=table, bounds=bounds, sample=np.concatenate(samples), read_by_tiles=[])


def tile_box(grid: TileGrid, i: int, j: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """The x-y box of tile (i, j) widened by the buffer, infinite beyond the grid's outer edges
    (:meth:`TileGrid.tiles`' comparisons)."""
    lo, hi = [0.0, 0.0], [0.0, 0.0]
    for axis, c in ((0, i), (1, j)):
        start = grid.origin[axis] + c * grid.size
        lo[axis] = -np.inf if c == 0 else start - grid.buffer
        hi[axis] = np.inf if c == grid.shape[axis] - 1 else start + grid.size + grid.buffer
    return (lo[0], lo[1]), (hi[0], hi[1])


def read_tile(path: str, nodes: np.ndarray, grid: TileGrid, i: int, j: int,
              xyz: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The points of tile (i, j) of a COPC file read from its ``nodes`` (those meeting its box):
    their rows in the file (increasing), which the core holds, their coordinates, and the points
    read. The nodes' points are decompressed from the file, or with ``xyz`` (the coordinates
    :func:`read_copc` wrote, in file order) read from there: each node's rows are one slice."""
    if xyz is None:
        X = decompress(path, nodes)
    else:
        mm = np.load(xyz, mmap_mode="r")
        try:
            X = np.concatenate([np.array(mm[f:f + c]) for f, c in zip(nodes[:, FIRST], nodes[:, COUNT])]) \
                if len(nodes) else np.zeros((0, 3))
        finally:
            del mm
    rows = np.concatenate([np.arange(f, f + c, dtype=np.int64) for f, c in zip(nodes[:, FIRST], nodes[:, COUNT])]) \
        if len(nodes) else np.zeros(0, dtype=np.int64)
    order = np.argsort(rows, kind="stable")
    rows, X = rows[order], take_rows(X, order)
    uv = X @ grid.axes.T
    (lo_u, lo_v), (hi_u, hi_v) = tile_box(grid, i, j)
    keep = (uv[:, 0] >= lo_u) & (uv[:, 0] <= hi_u) & (uv[:, 1] >= lo_v) & (uv[:, 1] <= hi_v)
    ij = grid.cells(uv[keep])
    return rows[keep], (ij[:, 0] == i) & (ij[:, 1] == j), take_rows(X, keep), len(X)


@dataclass(frozen=True)
class CopcJob:
    """What a task needs to read and segment one tile of a COPC file: its path, the nodes the tile
    reads, paths and small values (``xyz``: the spill folder's coordinates file, beside which the
    tile's rows and edge points go)."""

    path: str
    nodes: np.ndarray
    xyz: str
    tile: SpilledTile
    grid: TileGrid
    store: str
    base: bytes
    resume: bool


def tiles_of(cloud: CopcCloud, chunk_points: int = DEFAULT_CHUNK_POINTS) -> SpilledTiles:
    """Every cell of the grid as a tile to read (which hold points is known once they are read);
    on a grid of more than :attr:`~kbs.tiles.stream._Counts.DENSE` cells (a few far points
    stretching it), only the cells whose core holds points, from one pass over the coordinates
    :func:`read_copc` wrote (a tile whose core holds none gives nothing either way)."""
    grid = cloud.grid
    if grid.shape[0] * grid.shape[1] <= _Counts.DENSE:
        i, j = np.indices(grid.shape).reshape(2, -1)
    else:
        held = np.zeros(0, dtype=np.int64)
        for s in range(0, cloud.xyz.shape[0], chunk_points):
            ij = grid.cells(np.asarray(cloud.xyz[s:s + chunk_points]) @ grid.axes.T)
            held = np.union1d(held, ij[:, 0] * grid.shape[1] + ij[:, 1])
        i, j = held // grid.shape[1], held % grid.shape[1]
    return SpilledTiles(grid, cloud.folder, i, j, np.zeros(i.size, np.int64), np.zeros(i.size, np.int64))
