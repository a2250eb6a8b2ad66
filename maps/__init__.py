"""Drives, not just scans: segment every frame of a sequence with one loaded segmenter and fuse
them into an obstacle map (a 2D grid in log-odds), tracked 3D objects with meshes, and a fused
labelled cloud.

>>> from kbs import Segmenter
>>> from kbs.maps import read_drive, map_drive, write_map
>>> drive = read_drive(["drive/scans"], "drive/poses.txt")        # doctest: +SKIP
>>> with Segmenter("outdoor") as seg:                              # doctest: +SKIP
...     m = map_drive(seg, drive, cell_size=0.2)
>>> write_map(m, "map-out")                                        # doctest: +SKIP
"""
from __future__ import annotations

from kbs.maps.build import DriveMap, FrameRecord, FusedCloud, MapObject, map_drive
from kbs.maps.drive import Drive, Frame, read_drive
from kbs.maps.grid import BANDS, FusionParams, GridMap
from kbs.maps.poses import PoseFileError, Poses, read_poses

__all__ = ["Drive", "Frame", "read_drive", "Poses", "PoseFileError", "read_poses", "map_drive", "DriveMap",
           "FrameRecord", "MapObject", "FusedCloud", "GridMap", "FusionParams", "BANDS", "write_map"]


def __getattr__(name: str):
    if name == "write_map":  # the writers import matplotlib (and rasterio when installed)
        from kbs.maps.files import write_map

        return write_map
    raise AttributeError(f"module 'kbs.maps' has no attribute {name!r}")
