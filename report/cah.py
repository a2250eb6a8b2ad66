"""A cluster's connexity (CAh) view, as data: its points projected on a plane, their alpha-shape
and its alpha-opening (the seed paper's figures 5-7), computed with :mod:`kbs.geometry.connexity`
(the ``alpha_opening`` method of the connexity predicate). Drawn by
:func:`kbs.report.figures.cah_figure` (PNG) and by the HTML report (on click on a cluster)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class CahView:
    """``points`` (n, 2): the projected points; ``shape``: the alpha-shape's polygons (shapely),
    ``opening``: the opening's components, the largest first (the first ``n_significant`` hold at
    least ``min_fraction`` of the points); ``alpha``, ``radius`` (of the opening's disc) and
    ``spacing`` (median nearest-neighbour spacing) in the cloud's length unit."""

    points: np.ndarray
    shape: list[Any]
    opening: list[Any]
    alpha: float
    radius: float
    spacing: float
    n_significant: int
    n_components: int


def cah_view(X: np.ndarray, normal: np.ndarray, center: np.ndarray, *, alpha_factor: float = 3.0,
             opening_factor: float = 1.0, min_fraction: float = 0.05) -> CahView:
    """The CAh view of points ``X`` (n, 3) projected on the plane through ``center`` with ``normal``."""
    from kbs.geometry.connexity import alpha_opening, alpha_shape, connexity, project_on_plane

    X = np.asarray(X, dtype=np.float64)
    conn = connexity(X, center, normal, method="alpha_opening", alpha_factor=alpha_factor,
                     opening_factor=opening_factor, min_fraction=min_fraction)
    P = project_on_plane(X, center, normal)
    shape = alpha_shape(np.unique(P, axis=0), conn.alpha)
    pieces = [g for g in getattr(shape, "geoms", [shape]) if not g.is_empty]
    radius = float(conn.opening_radius or 0.0)
    parts = sorted(alpha_opening(shape, radius), key=lambda g: -g.area)
    return CahView(points=P, shape=pieces, opening=parts, alpha=float(conn.alpha), radius=radius,
                   spacing=float(conn.spacing), n_significant=int(conn.n_significant),
                   n_components=int(conn.n_components))


def rings(polygons: list[Any], tolerance: float = 0.0) -> list[dict[str, Any]]:
    """Each polygon's exterior then its holes as ``{"x": [...], "y": [...], "hole": bool, "part": i}``
    rings (simplified by ``tolerance``), for plotting as filled paths."""
    out = []
    for i, g in enumerate(polygons):
        g = g.simplify(tolerance) if tolerance > 0 else g
        if g.is_empty or not hasattr(g, "exterior"):
            continue
        for j, ring in enumerate([g.exterior, *g.interiors]):
            xy = np.asarray(ring.coords)
            out.append({"x": np.round(xy[:, 0], 5).tolist(), "y": np.round(xy[:, 1], 5).tolist(), "hole": j > 0,
                        "part": i})
    return out
