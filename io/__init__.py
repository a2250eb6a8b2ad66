"""Point-cloud files: read PLY, PCD, LAS/LAZ, E57, text tables, ``.npy`` and KITTI ``.bin``; write
PLY, and LAS/LAZ results (:mod:`kbs.io.las`).

>>> from kbs.io import read_cloud, write_ply
>>> cloud = read_cloud("scan.pcd")              # doctest: +SKIP
>>> cloud.xyz.shape, cloud.fields.keys()        # doctest: +SKIP
((182292, 3), dict_keys(['label', 'rgba']))

A cloud carries the units and CRS its file declares (``cloud.units``, ``cloud.crs``:
:mod:`kbs.units`). Every problem with a file raises :class:`kbs.errors.CloudFileError` (path and problem in one
line); points with a NaN/Inf coordinate are dropped, counted in ``n_dropped`` and logged on the
``kbs.io`` logger at INFO level.

Files are written whole or not at all (a temporary file beside the target, then a rename:
:mod:`kbs.io.atomic`). :mod:`kbs.io.result` owns the result files of ``kbs run`` (the PLY/JSON
pair and its run id).
"""

from __future__ import annotations

from kbs.io.cloud import PointCloud
from kbs.io.ply import write_ply
from kbs.io.readers import SUPPORTED_EXTENSIONS, read_cloud
from kbs.io.result import ResultDoc, read_result, read_result_json

__all__ = ["PointCloud", "read_cloud", "write_ply", "read_result", "read_result_json", "ResultDoc", "SUPPORTED_EXTENSIONS"]
