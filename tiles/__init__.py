"""Tiled segmentation: a cloud cut into square tiles with a buffer, each tile segmented alone (in
this process or as Dask tasks), the results stitched into one.

- :mod:`kbs.tiles.grid` -- the tiles: pure geometry over arrays;
- :mod:`kbs.tiles.stitch` -- one result from the tiles' results (clusters crossing an edge merged);
- :mod:`kbs.tiles.run` -- :func:`segment_tiled`, in process or on Dask.
"""
from __future__ import annotations

from kbs.tiles.grid import Tile, TileGrid, ground_axes
from kbs.tiles.run import TileError, default_buffer, plan_tiles, segment_tiled
from kbs.tiles.stitch import TiledSegmentation, stitch

__all__ = ["Tile", "TileGrid", "ground_axes", "TileError", "default_buffer", "plan_tiles", "segment_tiled", "stitch",
           "TiledSegmentation"]
