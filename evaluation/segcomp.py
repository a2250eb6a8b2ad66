"""Hoover et al. (1996) on SegComp label images: a machine segmentation (``.ms-seg``) against its
ground truth (``.gt-seg``), pixel by pixel as SegComp's ``compare`` counts, at a series of
tolerances (the paper's Table 1 format).

>>> from kbs.evaluation.segcomp import segcomp_table, DEFAULT_TOLERANCES
>>> rows = segcomp_table(ms_image, gt_image, DEFAULT_TOLERANCES, xyz=xyz, pixel=pixel)  # doctest: +SKIP
>>> [(r.tolerance, r.correct, r.angle_mean) for r in rows]                              # doctest: +SKIP

Regions are the labels >= 10 of each image; 0-3 are non-region pixels (:mod:`kbs.io.segcomp`).
Region sizes are counted over the whole image, as ``compare`` counts them. Two GT regions are
adjacent when two of their pixels are 4-neighbours in the image. Normals: the least-squares
plane of each region's 3D points (from the range image), or the MS normals of an ``.ms-nor``
file when given.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kbs.errors import ParameterError
from kbs.evaluation.hoover import HooverResult, check_tolerance, hoover, region_normals
from kbs.io.segcomp import FIRST_REGION_LABEL, NON_REGION_VALUES

#: The tolerances of the Table 1 rows: Hoover's T must exceed 0.5, so 0.51 stands for "0.5" as
#: in the paper's plots (T from 0.51 to 0.95).
DEFAULT_TOLERANCES = (0.51, 0.6, 0.7, 0.8, 0.9)


def grid_adjacency(labels_image: np.ndarray) -> set[tuple[int, int]]:
    """Pairs (a, b), a < b, of region labels (>= 10) that touch as 4-neighbours in the image.

    Parameters
    ----------
    labels_image : np.ndarray, shape (rows, cols)

    Returns
    -------
    set of (int, int)
    """
    L = np.asarray(labels_image).astype(np.int64)
    pairs: set[tuple[int, int]] = set()
    for a, b in ((L[:, :-1], L[:, 1:]), (L[:-1, :], L[1:, :])):
        touch = (a != b) & (a >= FIRST_REGION_LABEL) & (b >= FIRST_REGION_LABEL)
        if touch.any():
            lo, hi = np.minimum(a[touch], b[touch]), np.maximum(a[touch], b[touch])
            pairs.update(zip(*np.unique(np.stack([lo, hi]), axis=1).tolist()))
    return {(int(a), int(b)) for a, b in pairs}


def segcomp_table(
    ms_image: np.ndarray,
    gt_image: np.ndarray,
    tolerances: Sequence[float] = DEFAULT_TOLERANCES,
    *,
    xyz: np.ndarray | None = None,
    pixel: np.ndarray | None = None,
    ms_normals: Mapping[int, np.ndarray] | None = None,
) -> list[HooverResult]:
    """The Hoover classification of an MS label image against a GT label image at each tolerance.

    Parameters
    ----------
    ms_image, gt_image : np.ndarray, shape (rows, cols)
        SegComp label images (regions >= 10; 0-3 non-region), of the same shape.
    tolerances : sequence of float
        Each T in (0.5, 1].
    xyz : np.ndarray, shape (n, 3), optional
        The 3D points of the range image's pixels with data, for the angle metric.
    pixel : np.ndarray, shape (n,), optional
        Row-major pixel index of each point of ``xyz``.
    ms_normals : Mapping[int, np.ndarray], optional
        MS region -> normal (an ``.ms-nor`` file); default: from ``xyz``.

    Returns
    -------
    list of HooverResult
        One per tolerance, in the given order. Without ``xyz`` the angle metric is not computed
        (``angle_note`` says so).

    Raises
    ------
    ParameterError
        Images of different shapes, a tolerance out of (0.5, 1], or ``xyz`` / ``pixel`` that do
        not fit the images.
    """
    ms, gt = np.asarray(ms_image), np.asarray(gt_image)
    if ms.shape != gt.shape or ms.ndim != 2:
        raise ParameterError(f"the MS and GT images must have the same 2-D shape, got {ms.shape} and {gt.shape}")
    Ts = [check_tolerance(t) for t in tolerances]
    if not Ts:
        raise ParameterError("give at least one tolerance")
    ms_flat, gt_flat = ms.ravel().astype(np.int64), gt.ravel().astype(np.int64)
    adjacency = grid_adjacency(gt)
    gt_normals: Mapping[int, np.ndarray] | None = None
    if xyz is not None:
        X = np.asarray(xyz, dtype=np.float64)
        where = np.asarray(pixel)
        if X.ndim != 2 or X.shape[1] != 3 or where.shape != (len(X),) or where.dtype.kind not in "iu":
            raise ParameterError(f"xyz must be (n, 3) and pixel (n,) integers, got {X.shape} and {where.shape}")
        if where.size and (where.min() < 0 or where.max() >= gt_flat.size):
            raise ParameterError(f"pixel indices must be in [0, {gt_flat.size})")
        gt_normals = region_normals(X, gt_flat[where], np.unique(gt_flat[gt_flat >= FIRST_REGION_LABEL]))
        if ms_normals is None:
            ms_normals = region_normals(X, ms_flat[where], np.unique(ms_flat[ms_flat >= FIRST_REGION_LABEL]))
    # without 3D points there are no GT normals: hoover() then says the metric was not computed
    return [hoover(ms_flat, gt_flat, tolerance=T, ms_ignore=NON_REGION_VALUES, gt_ignore=NON_REGION_VALUES,
                   gt_adjacency=adjacency, ms_normals=ms_normals, gt_normals=gt_normals) for T in Ts]
