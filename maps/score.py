"""Scoring a drive map against the true layout of a generated drive
(:class:`kbs.synth.drive.DriveTruth`): cell accuracy of the grid and the tracked objects against
the true obstacles."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kbs.maps.grid import OBSTACLE, GridMap


@dataclass(frozen=True)
class GridScore:
    """How the grid's cells agree with the true layout, over the cells the drive saw.

    A cell's truth is *obstacle* when at least half of it lies under an obstacle standing more
    than ``min_height`` above the terrain, *ground* when none of it does; cells partly covered
    (less than half) are on an obstacle's rim, where either answer is right, and are left out, as
    are cells under a tree's crown and nothing else (free at the ground, an obstacle from above:
    ``truth.overhang_fraction``, when the truth has one).

    Attributes
    ----------
    cells : int
        Cells scored (seen, not on a rim).
    accuracy : float
        Fraction of scored cells whose class (obstacle or not) is the true one.
    obstacle_precision, obstacle_recall : float
        Of the cells mapped as obstacles, the fraction truly so; of the true obstacle cells, the
        fraction mapped so.
    true_obstacle_cells, mapped_obstacle_cells : int
    """

    cells: int
    accuracy: float
    obstacle_precision: float
    obstacle_recall: float
    true_obstacle_cells: int
    mapped_obstacle_cells: int


def score_grid(grid: GridMap, truth: Any, *, min_height: float = 0.05) -> GridScore:
    """Score ``grid`` against ``truth`` (a :class:`~kbs.synth.drive.DriveTruth`)."""
    frac = truth.obstacle_fraction(grid.origin, grid.cell_size, grid.shape, min_height=min_height)
    scored = (grid.frames_seen > 0) & ~((frac > 0) & (frac < 0.5))
    if hasattr(truth, "overhang_fraction"):
        scored &= ~(truth.overhang_fraction(grid.origin, grid.cell_size, grid.shape) > 0)
    true_o = (frac >= 0.5) & scored
    pred_o = (grid.cls == OBSTACLE) & scored
    tp = int((true_o & pred_o).sum())
    n = int(scored.sum())
    return GridScore(n, float((true_o == pred_o)[scored].mean()) if n else float("nan"),
                     tp / max(int(pred_o.sum()), 1), tp / max(int(true_o.sum()), 1), int(true_o.sum()),
                     int(pred_o.sum()))


@dataclass(frozen=True)
class ObjectScore:
    """Tracked objects against the true obstacles.

    Attributes
    ----------
    true_objects : int
        True obstacles with at least ``min_points`` points in some frame.
    mapped_objects : int
    matched : int
        True obstacles that some mapped object lies on.
    split : int
        True obstacles that more than one mapped object lies on.
    false : int
        Mapped objects that lie on no true obstacle.
    assignment : dict
        Mapped object id -> true object id (0: none).
    """

    true_objects: int
    mapped_objects: int
    matched: int
    split: int
    false: int
    assignment: dict[int, int]


def score_objects(objects: Any, truth: Any, frame_objects: list[np.ndarray], *, min_points: int = 20,
                  tolerance: float = 0.3) -> ObjectScore:
    """Match each mapped object to the true obstacle most of its points lie on (within
    ``tolerance`` metres of its footprint, horizontally), and count.

    Parameters
    ----------
    objects : sequence of :class:`~kbs.maps.build.MapObject`
    truth : DriveTruth
    frame_objects : list of (n_i,) int arrays
        The true object id of every point of every frame (the drive's ``Scene.objects``).
    """
    counts: dict[int, int] = {}
    for ids in frame_objects:
        u, c = np.unique(ids[ids > 0], return_counts=True)
        for k, v in zip(u.tolist(), c.tolist()):
            counts[k] = max(counts.get(k, 0), v)
    visible = {k for k, v in counts.items() if v >= min_points}
    assignment = {}
    for o in objects:
        ids = truth.object_at(o.points[:, 0], o.points[:, 1], tolerance)
        u, c = np.unique(ids, return_counts=True)
        assignment[o.id] = int(u[np.argmax(c)])
    hits: dict[int, int] = {}
    for t in assignment.values():
        if t > 0:
            hits[t] = hits.get(t, 0) + 1
    return ObjectScore(len(visible), len(objects), len(hits), sum(1 for v in hits.values() if v > 1),
                       sum(1 for t in assignment.values() if t == 0), assignment)
