"""COPC files for the tests, written by copc-lib (``copclib``, in the ``test`` extra) from a LAS
file: its points in point format 6/7 given to the nodes of a real octree (``levels`` levels, each
level holding a random share of the points at its cell, the deepest the rest), so a query of a
box reads the coarse levels and the deep nodes that meet it, and the file's point order is the
nodes' order (by level, then key) with each node's points in the LAS file's order."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_copc(source: Path, target: Path, levels: int = 4, seed: int = 0, per_node: int = 256) -> int:
    """Write the points of the LAS ``source`` to the COPC ``target``; returns the nodes written.
    Each node above the deepest level keeps ``per_node`` of its cell's points at most."""
    import copclib
    import laspy

    las = laspy.read(str(source))
    las = laspy.convert(las, point_format_id=7 if las.point_format.id in (2, 3, 5, 7, 8, 10) else 6,
                        file_version="1.4")
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    centre = (lo + hi) / 2.0
    half = float((hi - lo).max()) / 2.0 * 1.001 + 1e-6
    # top down: each occupied cell of a level keeps an eighth of its points (one at least, per_node
    # at most), at random; the deepest level the rest (every node's parent holds points: a real octree)
    rng = np.random.default_rng(seed)
    level = np.full(len(xyz), levels - 1)
    left = np.ones(len(xyz), dtype=bool)
    rank = rng.random(len(xyz))
    for d in range(levels - 1):
        cell = np.floor((xyz - (centre - half)) / (2.0 * half) * 2.0 ** d).astype(np.int64)
        ids = (cell[:, 0] * 2 ** d + cell[:, 1]) * 2 ** d + cell[:, 2]
        rows = np.flatnonzero(left)
        by_cell = rows[np.lexsort((rank[rows], ids[rows]))]
        head = np.concatenate([[True], ids[by_cell][1:] != ids[by_cell][:-1]])
        place = np.arange(len(by_cell)) - np.maximum.accumulate(np.where(head, np.arange(len(by_cell)), 0))
        take = by_cell[head | ((rank[by_cell] < 0.125) & (place < per_node))]
        level[take] = d
        left[take] = False
        rank = rng.random(len(xyz))
    cells = np.floor((xyz - (centre - half)) / (2.0 * half) * (2.0 ** level)[:, None]).astype(np.int64)
    cells = np.clip(cells, 0, (2 ** level)[:, None] - 1)
    keys = np.column_stack([level, cells])
    order = np.lexsort(keys.T[::-1])
    keys = keys[order]
    cut = np.flatnonzero(np.any(np.diff(keys, axis=0) != 0, axis=1)) + 1
    config = copclib.CopcConfigWriter(las.point_format.id, copclib.Vector3(*las.header.scales),
                                      copclib.Vector3(*las.header.offsets))
    header = config.las_header
    header.min, header.max = copclib.Vector3(*lo), copclib.Vector3(*hi)
    info = config.copc_info
    info.center_x, info.center_y, info.center_z = (float(c) for c in centre)
    info.halfsize, info.spacing = half, 2.0 * half / 64.0
    raw = np.asarray(las.points.array)
    writer = copclib.FileWriter(str(target), config)
    groups = np.split(order, cut)
    starts = np.concatenate([[0], cut])
    for start, rows in zip(starts, groups):
        d, i, j, k = (int(v) for v in keys[start])
        data = np.frombuffer(raw[np.sort(rows)].tobytes(), dtype=np.int8)
        writer.AddNode(copclib.VoxelKey(d, i, j, k), copclib.VectorChar(data))
    writer.Close()
    return len(groups)
