"""The in-memory point cloud every reader returns, and the one place non-finite points are dropped.

Readers hand the raw arrays of a file to :meth:`PointCloud.from_arrays`, which drops the points
with a NaN/Inf coordinate (logging how many on the ``kbs.io`` logger), converts the coordinates
to float64 and records where each kept point was in the file.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from kbs.arrays import rows, finite_rows
from kbs.errors import CloudFileError, KbsError, ParameterError
from kbs.units import ScanUnits

logger = logging.getLogger("kbs.io")


def _data_error(path: str | None, problem: str) -> KbsError:
    """A :class:`CloudFileError` for data read from a file, a :class:`ParameterError` otherwise."""
    if path is None:
        return ParameterError(problem)
    return CloudFileError(path, problem)


@dataclass(frozen=True, eq=False)
class PointCloud:
    """A point cloud as read from a file: finite coordinates plus per-point attributes.

    Build one with :meth:`from_arrays` (or get one from :func:`kbs.io.read_cloud`); the plain
    constructor only checks that the parts are consistent.

    Attributes
    ----------
    xyz : np.ndarray, shape (N, 3), float64
        Coordinates of the kept points, all finite, as stored in the file (not centred).
    fields : Mapping[str, np.ndarray]
        Extra per-point attributes (``intensity``, ``label``, ``classification``, ``rgb`` ...),
        each of shape (N,), in the dtype the file stores them in. Read-only mapping.
    shape : tuple[int, int] or None
        ``(rows, cols)`` of an organised cloud (e.g. a PCD with HEIGHT > 1), else None.
    index : np.ndarray, shape (N,), int64
        Position of each kept point in the file's original point order, increasing. For an
        organised cloud, ``np.unravel_index(index, shape)`` gives its (row, col) on the grid.
    n_read : int
        Number of points in the file (kept + dropped).
    n_dropped : int
        Number of points dropped because a coordinate was NaN or Inf.
    path : str or None
        The file the cloud was read from, None for a cloud built from arrays.
    units : ScanUnits or None
        The length units of the coordinates when the file declares them (a LAS/LAZ file's CRS,
        a ``units`` or ``crs`` comment of a PLY or PCD header, E57's metres), else None.
    crs : str or None
        The coordinate reference system the file declares, as text (WKT, ``EPSG:n`` ...), else None.
    source : object or None
        The reading library's own object when a writer needs the file's layout to write it back
        (the ``laspy.LasData`` of a LAS/LAZ file: header, point format, VLRs); None otherwise.
    """

    xyz: np.ndarray
    fields: Mapping[str, np.ndarray]
    shape: tuple[int, int] | None
    index: np.ndarray
    n_read: int
    n_dropped: int
    path: str | None = None
    units: ScanUnits | None = None
    crs: str | None = None
    source: Any = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        xyz = self.xyz
        if not isinstance(xyz, np.ndarray) or xyz.dtype != np.float64 or xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ParameterError(
                f"PointCloud.xyz must be a float64 array of shape (N, 3), got "
                f"{getattr(xyz, 'dtype', type(xyz).__name__)} {getattr(xyz, 'shape', '')}"
            )
        n = len(xyz)
        index = self.index
        if not isinstance(index, np.ndarray) or index.dtype != np.int64 or index.shape != (n,):
            raise ParameterError(f"PointCloud.index must be an int64 array of shape ({n},)")
        for name, values in self.fields.items():
            if not isinstance(name, str) or not isinstance(values, np.ndarray) or values.shape != (n,):
                raise ParameterError(
                    f"PointCloud field {name!r} must be an array of shape ({n},), "
                    f"got {getattr(values, 'shape', type(values).__name__)}"
                )
        if self.n_dropped < 0 or self.n_read != n + self.n_dropped:
            raise ParameterError(
                f"PointCloud.n_read ({self.n_read}) must equal the kept ({n}) plus the dropped "
                f"({self.n_dropped}) points"
            )
        if self.shape is not None and (len(self.shape) != 2 or self.shape[0] * self.shape[1] != self.n_read):
            raise ParameterError(f"PointCloud.shape {self.shape} does not hold n_read = {self.n_read} points")
        if not isinstance(self.fields, MappingProxyType):
            object.__setattr__(self, "fields", MappingProxyType(dict(self.fields)))

    @classmethod
    def from_arrays(
        cls,
        xyz: np.ndarray,
        fields: Mapping[str, np.ndarray] | None = None,
        *,
        shape: tuple[int, int] | None = None,
        path: str | None = None,
        units: ScanUnits | None = None,
        crs: str | None = None,
        source: Any = None,
    ) -> PointCloud:
        """Build a cloud from raw arrays, dropping the points with a NaN/Inf coordinate.

        The arrays are copied (never kept as views of a file buffer or memory map).

        Parameters
        ----------
        xyz : np.ndarray, shape (M, 3)
            Coordinates of every point in file order, any real dtype (converted to float64).
        fields : Mapping[str, np.ndarray], optional
            Extra attributes, each of shape (M,); their dtypes are kept.
        shape : tuple[int, int], optional
            ``(rows, cols)`` of an organised cloud, with ``rows * cols == M``.
        path : str, optional
            The file the arrays come from (used in messages and stored on the cloud).
        units, crs, source : optional
            Stored as they are (see the class).

        Returns
        -------
        PointCloud
            The N <= M finite points, with ``index`` their positions among the M.

        Raises
        ------
        CloudFileError
            ``path`` is given and there is no point, or every point is NaN/Inf.
        ParameterError
            The arrays are inconsistent, or (without ``path``) hold no usable point.
        """
        xyz = np.asarray(xyz)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype.kind not in "fiu":
            raise ParameterError(f"xyz must be a real array of shape (N, 3), got {xyz.dtype} {xyz.shape}")
        n_read = len(xyz)
        fields = {} if fields is None else dict(fields)
        for name, values in fields.items():
            if np.shape(values) != (n_read,):
                raise ParameterError(f"field {name!r} must have shape ({n_read},), got {np.shape(values)}")
        if n_read == 0:
            raise _data_error(path, "the cloud holds no points")
        keep = finite_rows(xyz)
        n_kept = int(np.count_nonzero(keep))
        if n_kept == 0:
            raise _data_error(path, f"all {n_read} points are NaN/Inf")
        n_dropped = n_read - n_kept
        if n_dropped:
            logger.info(
                "%s: dropped %d of %d points with a NaN/Inf coordinate",
                path or "<array>",
                n_dropped,
                n_read,
            )
            index = np.flatnonzero(keep).astype(np.int64, copy=False)
            kept_xyz = rows(xyz, keep).astype(np.float64, copy=False)
            kept_fields = {name: np.asarray(values)[keep] for name, values in fields.items()}
        else:
            index = np.arange(n_read, dtype=np.int64)
            kept_xyz = np.array(xyz, dtype=np.float64, order="C", copy=True)
            kept_fields = {name: np.array(values, copy=True) for name, values in fields.items()}
        return cls(
            xyz=np.ascontiguousarray(kept_xyz),
            fields=kept_fields,
            shape=None if shape is None else (int(shape[0]), int(shape[1])),
            index=index,
            n_read=n_read,
            n_dropped=n_dropped,
            path=None if path is None else str(path),
            units=units,
            crs=crs,
            source=source,
        )

    def __len__(self) -> int:
        """Number of kept (finite) points, N."""
        return len(self.xyz)

    def __repr__(self) -> str:
        organised = f", shape={self.shape}" if self.shape is not None else ""
        units = f", units={self.units.name!r}" if self.units is not None else ""
        return (
            f"PointCloud(n={len(self)}, fields={list(self.fields)}{organised}, "
            f"n_read={self.n_read}, n_dropped={self.n_dropped}{units}, path={self.path!r})"
        )
