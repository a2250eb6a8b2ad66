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

import logging
from collections.abc import Mapping, Sequence

import numpy as np

from kbs.errors import ParameterError
from kbs.evaluation.hoover import HooverResult, check_tolerance, hoover, region_normals
from kbs.geometry.pca import principal_axes
from kbs.io.segcomp import FIRST_REGION_LABEL, MAX_REGIONS, NO_REGION, NON_REGION_VALUES

logger = logging.getLogger("kbs.io")  # the SegComp messages kept their logger when they moved here

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
        X, where = _points_on_image(xyz, pixel, gt_flat.size)
        gt_normals = region_normals(X, gt_flat[where], np.unique(gt_flat[gt_flat >= FIRST_REGION_LABEL]))
        if ms_normals is None:
            ms_normals = region_normals(X, ms_flat[where], np.unique(ms_flat[ms_flat >= FIRST_REGION_LABEL]))
    # without 3D points there are no GT normals: hoover() then says the metric was not computed
    return [hoover(ms_flat, gt_flat, tolerance=T, ms_ignore=NON_REGION_VALUES, gt_ignore=NON_REGION_VALUES,
                   gt_adjacency=adjacency, ms_normals=ms_normals, gt_normals=gt_normals) for T in Ts]


def region_labels(
    cluster: np.ndarray, *, min_points: int = 3, max_regions: int = MAX_REGIONS
) -> dict[int, int]:
    """The MS region label of each kbs cluster that becomes a region.

    The clusters kept (at least ``min_points`` points, the ``max_regions`` largest if there are
    more) get the labels 10, 11, ... in increasing cluster-id order, because ``compare`` wants
    the labels consecutive from 10. For a usual ``kbs run`` result (clusters 0 ... K-1, K <= 246,
    none smaller than 3 points) this is simply cluster k -> label 10 + k. Noise (-1) and the
    clusters left out get no label (their pixels are written :data:`NO_REGION`).

    Parameters
    ----------
    cluster : np.ndarray, shape (n,)
        kbs cluster of each point, -1 = noise.
    min_points : int, default 3
        Smaller clusters are left out (a plane's normal needs 3 points).
    max_regions : int, default 246
        At most this many regions (246 fit in labels 10 ... 255).

    Returns
    -------
    dict[int, int]
        cluster id -> region label.
    """
    values = np.asarray(cluster)
    if values.ndim != 1 or values.dtype.kind not in "iu":
        raise ParameterError(f"cluster must be a 1-D integer array, got {values.dtype} {values.shape}")
    if not 1 <= max_regions <= MAX_REGIONS:
        raise ParameterError(f"max_regions must be in [1, {MAX_REGIONS}], got {max_regions}")
    ids, counts = np.unique(values[values >= 0], return_counts=True)
    keep = counts >= min_points
    if np.count_nonzero(~keep):
        logger.warning("%d clusters of fewer than %d points left out of the regions", np.count_nonzero(~keep),
                       min_points)
    ids, counts = ids[keep], counts[keep]
    if ids.size > max_regions:
        order = np.lexsort((ids, -counts))  # largest first, then by id
        dropped = order[max_regions:]
        logger.warning("%d clusters but SegComp labels hold %d regions: the %d smallest (%d points) are left out",
                       ids.size, max_regions, dropped.size, int(counts[dropped].sum()))
        ids = np.sort(ids[order[:max_regions]])
    return {int(k): FIRST_REGION_LABEL + i for i, k in enumerate(ids)}


def segmentation_to_image(
    cluster: np.ndarray,
    pixel: np.ndarray,
    shape: tuple[int, int],
    *,
    min_points: int = 3,
    max_regions: int = MAX_REGIONS,
) -> np.ndarray:
    """The MS labels image of a kbs segmentation of an organised cloud.

    Parameters
    ----------
    cluster : np.ndarray, shape (n,)
        kbs cluster of each point, -1 = noise (the ``cluster`` of a ``kbs run`` result).
    pixel : np.ndarray, shape (n,)
        Row-major pixel index of each point in the grid ``shape`` (the result's ``pixel``).
    shape : tuple[int, int]
        (rows, cols) of the grid, e.g. (512, 512).
    min_points, max_regions : int
        As for :func:`region_labels`, which gives the mapping cluster -> label.

    Returns
    -------
    np.ndarray, shape (rows, cols), uint8
        The region label (10, 11, ...) of each pixel; :data:`NO_REGION` (0) for pixels without a
        point (no data), noise points and clusters left out.

    Raises
    ------
    ParameterError
        Arrays of different lengths or non-integers, a pixel outside the grid, or two points on
        one pixel.
    """
    values = np.asarray(cluster)
    where = np.asarray(pixel)
    if where.ndim != 1 or where.dtype.kind not in "iu" or where.shape != values.shape:
        raise ParameterError(
            f"pixel must be a 1-D integer array as long as cluster ({values.shape}), got {where.dtype} {where.shape}"
        )
    rows, cols = (int(s) for s in shape)
    if rows <= 0 or cols <= 0:
        raise ParameterError(f"shape must be two positive sizes, got {tuple(shape)}")
    if where.size and (where.min() < 0 or where.max() >= rows * cols):
        raise ParameterError(f"pixel indices must be in [0, {rows * cols}) for a {rows} x {cols} grid, "
                             f"got [{where.min()}, {where.max()}]")
    if np.unique(where).size != where.size:
        raise ParameterError("two points share a pixel: pixel indices must be distinct")
    mapping = region_labels(values, min_points=min_points, max_regions=max_regions)
    image = np.full(rows * cols, NO_REGION, dtype=np.uint8)
    image[where] = _map_labels(values, mapping)
    return image.reshape(rows, cols)


def _map_labels(cluster: np.ndarray, mapping: Mapping[int, int]) -> np.ndarray:
    """Vectorised cluster -> label (NO_REGION for ids not in ``mapping``)."""
    out = np.full(cluster.size, NO_REGION, dtype=np.uint8)
    if mapping:
        ids = np.fromiter(mapping.keys(), dtype=np.int64)
        labels = np.fromiter(mapping.values(), dtype=np.int64)
        order = np.argsort(ids)
        ids, labels = ids[order], labels[order]
        pos = np.clip(np.searchsorted(ids, cluster), 0, ids.size - 1)
        hit = ids[pos] == cluster
        out[hit] = labels[pos[hit]]
    return out


def image_region_normals(labels_image: np.ndarray, xyz: np.ndarray, pixel: np.ndarray) -> dict[int, np.ndarray]:
    """The normal of each region of a label image, from its points: the eigenvector of the smallest eigenvalue of
    the region's covariance (its least-squares plane), unit length, turned so that nz >= 0.

    Parameters
    ----------
    labels_image : np.ndarray, shape (rows, cols)
        Region labels (>= 10) per pixel, as from :func:`segmentation_to_image`.
    xyz : np.ndarray, shape (n, 3)
        The points.
    pixel : np.ndarray, shape (n,)
        Row-major pixel index of each point.

    Returns
    -------
    dict[int, np.ndarray]
        label -> normal (3,) float64, for every label >= 10 of the image.

    Raises
    ------
    ParameterError
        Inconsistent arrays, or a region with fewer than 3 points.
    """
    labels = np.asarray(labels_image)
    X, where = _points_on_image(xyz, pixel, labels.size)
    point_label = labels.ravel()[where]
    normals: dict[int, np.ndarray] = {}
    for label in np.unique(labels[labels >= FIRST_REGION_LABEL]):
        P = X[point_label == label]
        if len(P) < 3:
            raise ParameterError(f"region {int(label)} has {len(P)} points; a normal needs at least 3")
        normal = principal_axes(P).normal
        normal = normal / np.linalg.norm(normal)
        normals[int(label)] = -normal if normal[2] < 0 else normal
    return normals


def _points_on_image(xyz, pixel, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``xyz`` (n, 3) as float64 and ``pixel`` (n,) integer indices into an image of ``size``
    pixels, checked (:class:`ParameterError` otherwise)."""
    X = np.asarray(xyz, dtype=np.float64)
    where = np.asarray(pixel)
    if X.ndim != 2 or X.shape[1] != 3 or where.shape != (len(X),) or where.dtype.kind not in "iu":
        raise ParameterError(f"xyz must be (n, 3) and pixel (n,) integers, got {X.shape} and {where.shape}")
    if where.size and (where.min() < 0 or where.max() >= size):
        raise ParameterError(f"pixel indices must be in [0, {size})")
    return X, where
