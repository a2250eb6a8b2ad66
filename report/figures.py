"""Static figures of a ``kbs run`` result (matplotlib, headless).

Every function returns a :class:`matplotlib.figure.Figure` built without pyplot (no global
state, no display needed; ``fig.savefig`` renders with Agg):

- :func:`partition_series_figure`: the K-partition series of the seed paper's figure 2 with each
  cluster's eigen-box, from a global run's visited partitions (:func:`panels_from_sweep`) or
  UFP-ONC re-run on the points (:func:`panels_from_ufp_onc`);
- :func:`cah_figure`: a cluster's CAh view (projection, alpha-shape, alpha-opening);
- :func:`obstacle_map_figure`: a top-down grid of ground / obstacle cells, the sensor marked;
- :func:`clusters_figure`: the points coloured by output cluster, each fuzzy centre marked and a
  box along the eigenvectors of the cluster's covariance (half-sides 2 sqrt(eigenvalue)).

:func:`load_result` reads a result (``<stem>.json`` and its sibling ``<stem>.ply``).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kbs.errors import require
from kbs.io.result import ResultDoc
from kbs.geometry.pca import plane_basis, principal_axes
from kbs.report.colors import NOISE_RGB, colors_for
from kbs.report.view import View

if TYPE_CHECKING:
    from kbs.knowledge.explain import Explanation

#: The K of the seed paper's figure 2.
SERIES_K = (2, 4, 5, 6, 8, 10)


@dataclass(frozen=True)
class Result:
    """A ``kbs run`` result read back: the JSON document (:class:`kbs.io.result.ResultDoc`) and the
    per-point arrays of the PLY."""

    doc: ResultDoc
    X: np.ndarray  # (n, 3)
    cluster: np.ndarray  # (n,) int
    label: np.ndarray  # (n,) int
    membership: np.ndarray  # (n,) float

    @property
    def label_names(self) -> list[str]:
        return list(self.doc.label_names or ())

    @property
    def clusters(self) -> list[dict[str, Any]]:
        return list(self.doc.clusters or ())

    @property
    def sensor(self) -> np.ndarray | None:
        s = self.doc.sensor
        return None if s is None else np.asarray(s, dtype=float)

    @functools.cached_property
    def explanation(self) -> Explanation | None:
        """The run's explanation (None: the file has none). Raises CloudFileError for one this kbs
        does not read (a newer major version)."""
        from kbs.knowledge.explain import Explanation

        return None if self.doc.explanation is None else Explanation.from_result(self.doc)


def load_result(path: str | Path) -> Result:
    """Read ``RESULT.json`` and the sibling ``RESULT.ply`` written by ``kbs run``.

    Raises
    ------
    CloudFileError
        Either file is missing or is not a kbs result, or they come from two runs (their run ids
        differ: :func:`kbs.io.result.check_pair`).
    """
    from kbs.io.result import read_result_pair

    path = Path(path)
    # refuses two runs' files, and points without their cluster and label
    doc, pc = read_result_pair(path, require=("clusters", "label_names"), fields=("cluster", "label"))
    n = len(pc)
    return Result(doc=doc, X=np.asarray(pc.xyz, dtype=np.float64),
                  cluster=np.asarray(pc.fields["cluster"]).astype(np.int64),
                  label=np.asarray(pc.fields["label"]).astype(np.int64),
                  membership=np.asarray(pc.fields.get("membership", np.ones(n)), dtype=np.float64))


def decimate(n: int, max_points: int) -> np.ndarray:
    """Indices of a deterministic stride sample of at most ``max_points`` out of ``n``."""
    step = max(1, int(np.ceil(n / max_points)))
    return np.arange(0, n, step)


def _figure(width: float, height: float):
    Figure = require("matplotlib.figure", "render", "drawing figures").Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def _rgb(index: np.ndarray) -> np.ndarray:
    return colors_for(index).astype(float) / 255.0


def obstacle_grid(X: np.ndarray, label: np.ndarray, obstacle: np.ndarray, *, cell: float | None = None,
                  max_cells: int = 400) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Top-down occupancy grid: 0 empty, 1 ground/other only, 2 obstacle (any obstacle point in
    the cell), 3 noise only. ``obstacle`` is a boolean per label index. Returns the grid (ny, nx)
    and ``(x0, y0, cell)``; the cell is 0.25 length units unless the extent would need more than
    ``max_cells`` cells along a side."""
    xy = np.asarray(X, dtype=float)[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    if cell is None:
        cell = max(0.25, float((hi - lo).max()) / max_cells)
    shape = np.maximum(np.ceil((hi - lo) / cell).astype(int), 1)
    ij = np.minimum(((xy - lo) / cell).astype(int), shape - 1)
    flat = ij[:, 1] * shape[0] + ij[:, 0]
    lab = np.asarray(label)
    is_obst = np.zeros(lab.shape, dtype=bool)
    known = lab >= 0
    is_obst[known] = np.asarray(obstacle, dtype=bool)[lab[known]]
    size = int(shape[0] * shape[1])
    any_pt = np.bincount(flat, minlength=size) > 0
    any_known = np.bincount(flat[known], minlength=size) > 0
    any_obst = np.bincount(flat[is_obst], minlength=size) > 0
    grid = np.zeros(size, dtype=np.int8)
    grid[any_pt] = 3
    grid[any_known] = 1
    grid[any_obst] = 2
    return grid.reshape(shape[1], shape[0]), (float(lo[0]), float(lo[1]), float(cell))


def obstacle_map_figure(X: np.ndarray, label: np.ndarray, label_names: list[str], *,
                        sensor: np.ndarray | None = None, ground_label: str = "ground",
                        cell: float | None = None, title: str = "", view: View | None = None) -> Any:
    """Top-down map of ground vs obstacle cells (a cell is an obstacle when any of its points has
    a label other than ``ground_label``; empty cells white, noise-only cells grey), the sensor
    marked with a star when it lies in or near the scan (an airborne or georeferenced scan's
    default sensor, the origin, would shrink the scan to a sliver: it is named in a note instead).
    The map is the plane perpendicular to ``view.up`` (x-y when no view is given): a camera's
    frame, whose up is -y, gets its map in x-z instead of a sliver."""
    require("matplotlib", "render", "drawing figures")
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    view = view or View.from_up([0.0, 0.0, 1.0])
    obstacle = np.array([name != ground_label for name in label_names], dtype=bool)
    grid, (x0, y0, c) = obstacle_grid(view.plan(X), label, obstacle, cell=cell)
    if sensor is not None:
        sensor = np.r_[view.plan(np.asarray(sensor, dtype=float)), 0.0]
    fig = _figure(6.4, 6.0)
    ax = fig.add_subplot(1, 1, 1)
    cmap = ListedColormap(["white", "#b8d8a8", "#c0392b", tuple(v / 255 for v in NOISE_RGB)])
    ny, nx = grid.shape
    ax.imshow(grid, cmap=cmap, vmin=0, vmax=3, origin="lower", interpolation="nearest",
              extent=(x0, x0 + nx * c, y0, y0 + ny * c))
    handles = [Patch(color="#b8d8a8", label=ground_label), Patch(color="#c0392b", label="obstacle"),
               Patch(facecolor="white", edgecolor="0.6", label="no point")]
    if sensor is not None:
        w, h_ = nx * c, ny * c
        near = (x0 - 0.25 * w <= sensor[0] <= x0 + 1.25 * w) and (y0 - 0.25 * h_ <= sensor[1] <= y0 + 1.25 * h_)
        if near:
            h = ax.scatter([sensor[0]], [sensor[1]], marker="*", s=220, c="#1f4e99", edgecolors="k", zorder=3,
                           label="sensor")
            handles.append(h)
        else:
            ax.text(0.01, 0.01, f"sensor at ({sensor[0]:.6g}, {sensor[1]:.6g}), far outside the scan: not drawn",
                    transform=ax.transAxes, fontsize=7, color="0.3")
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_aspect("equal")
    names = view.axis_names()
    ax.set_xlabel(names[0])
    ax.set_ylabel(names[1])
    ax.set_title(title or f"obstacle map (cells {c:.3g})", fontsize=11)
    return fig


def _box_edges(center: np.ndarray, axes: np.ndarray, half: np.ndarray) -> list[np.ndarray]:
    """The 12 edges (each (2, 3)) of the box ``center + sum_i s_i half_i axes[:, i]``, s_i = +-1."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    corners = center + (signs * half) @ axes.T
    edges = []
    for a in range(8):
        for b in range(a + 1, 8):
            if np.count_nonzero(signs[a] != signs[b]) == 1:
                edges.append(corners[[a, b]])
    return edges


def cluster_axes(X: np.ndarray, weights: np.ndarray, normal: np.ndarray | None) -> np.ndarray:
    """Eigenvectors (3, 3), columns e1 e2 e3 by increasing variance, of the weighted covariance of
    a cluster's points; when ``normal`` (the JSON descriptor) is given, e1 is it and e2, e3 are
    the principal directions within its plane."""
    pca = principal_axes(X, weights=weights)
    if normal is None:
        return pca.eigenvectors
    cov = pca.covariance
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    B = plane_basis(n).T  # (3, 2): in-plane directions
    _, vec2 = np.linalg.eigh(B.T @ cov @ B)
    return np.column_stack([n, B @ vec2[:, 0], B @ vec2[:, 1]])


def clusters_figure(X: np.ndarray, cluster: np.ndarray, clusters: list[dict[str, Any]], *,
                    membership: np.ndarray | None = None, max_points: int = 30000, point_size: float = 0.6,
                    elev: float | None = None, azim: float | None = None, title: str = "", max_boxes: int = 30,
                    view: View | None = None) -> Any:
    """Oblique 3-D view: points (decimated) coloured by output cluster and, for the ``max_boxes``
    largest clusters (a scene of thousands stays readable, and fast), the fuzzy centre (a dot)
    and the box along the covariance eigenvectors with half-sides 2 sqrt(eigenvalue) (centre,
    eigenvalues and normal from the JSON descriptors; the in-plane directions from the cluster's
    points weighted by membership). The figure is drawn with ``view.up`` vertical (the
    coordinates turned to right, forward, up; a level scan keeps its own x, y, z), seen from above
    at ``elev`` 35 and ``azim`` -60 degrees by default, a camera's frame from behind the camera
    (``elev`` 20, ``azim`` -90)."""
    view = view or View.from_up([0.0, 0.0, 1.0])
    turn = not (view.level and view.up[2] > 0)
    if elev is None:
        elev = 20.0 if view.camera_frame else 35.0
    if azim is None:
        azim = -90.0 if view.camera_frame else -60.0
    X = np.asarray(X, dtype=float)
    if turn:  # up vertical: the points, centres, normals and axes in the (right, forward, up) frame
        R = view.rotation
        X = X @ R.T
        clusters = [_turned(cl, R) for cl in clusters]
    cluster = np.asarray(cluster)
    fig = _figure(8.0, 6.4)
    ax = fig.add_subplot(1, 1, 1, projection="3d", computed_zorder=False)  # boxes over points
    idx = decimate(len(X), max_points)
    w_all = np.ones(len(X)) if membership is None else np.asarray(membership, dtype=float)
    boxed = sorted(clusters, key=lambda cl: (-int(cl.get("n_points", 0)), cl["index"]))[:max(max_boxes, 0)]
    order = np.argsort(cluster, kind="stable")  # each cluster's points at once, not a pass per cluster
    sorted_ids = cluster[order]
    for cl in boxed:
        d = cl.get("descriptors") or {}
        if "center" not in d or "eigenvalues" not in d:
            continue
        a, b = np.searchsorted(sorted_ids, [cl["index"], cl["index"] + 1])
        sel = order[a:b]
        if sel.size < 3:
            continue
        col = _rgb(np.array([cl["index"]]))[0]
        center = np.asarray(d["center"], dtype=float)
        axes = cluster_axes(X[sel], w_all[sel], d.get("normal"))
        half = 2.0 * np.sqrt(np.maximum(np.asarray(d["eigenvalues"], dtype=float), 0.0))
        for e in _box_edges(center, axes, half):
            ax.plot(e[:, 0], e[:, 1], e[:, 2], color=col * 0.6, linewidth=1.0, zorder=3)
        ax.scatter([center[0]], [center[1]], [center[2]], s=60, c=[col], edgecolors="k", depthshade=False,
                   zorder=4)
        ax.text(center[0], center[1], center[2] + half[0] + 0.05 * float(np.ptp(X[:, 2]) or 1),
                f"{cl['index']} {cl.get('label', '')}", fontsize=7, zorder=5)
    lo, hi = np.percentile(X[idx], [1, 99], axis=0)  # far, sparse returns do not shrink the scene
    pad = 0.05 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    span = hi - lo + 2 * pad
    inside = idx[np.all((X[idx, :2] >= lo[:2] - pad) & (X[idx, :2] <= hi[:2] + pad), axis=1)]
    ax.scatter(X[inside, 0], X[inside, 1], X[inside, 2], c=_rgb(cluster[inside]), s=point_size, linewidths=0,
               depthshade=False, rasterized=True, zorder=1)
    ax.set_box_aspect(np.maximum(span, 0.25 * span.max()))  # flat scenes: heights stay readable
    ax.view_init(elev=elev, azim=azim)
    names = view.axis_names()
    ax.set_xlabel(names[0], fontsize=8)
    ax.set_ylabel(names[1], fontsize=8)
    ax.set_zlabel(names[2], fontsize=8)
    ax.tick_params(labelsize=6)
    boxes = "fuzzy centres and 2-sigma boxes" + (f" of the {len(boxed)} largest" if len(boxed) < len(clusters) else "")
    ax.set_title(title or f"{len(clusters)} output clusters: {boxes}", fontsize=11)
    if len(boxed) < len(clusters) and title:
        ax.text2D(0.01, 0.01, f"boxes: the {len(boxed)} largest of {len(clusters)} clusters", transform=ax.transAxes,
                  fontsize=7, color="0.3")
    return fig


def _turned(cl: dict[str, Any], R: np.ndarray) -> dict[str, Any]:
    """A cluster's JSON descriptor with its centre and normal turned by the rotation ``R`` (3, 3)
    (eigenvalues do not change under a rotation); the caller's dict is not changed."""
    d = dict(cl.get("descriptors") or {})
    for key in ("center", "normal"):
        if d.get(key) is not None:
            d[key] = (R @ np.asarray(d[key], dtype=float)).tolist()
    return {**cl, "descriptors": d}


# -- the K-partition series with eigen-boxes (the seed paper's figure 2) ----------------------------


@dataclass(frozen=True)
class PartitionPanel:
    """One K-partition to draw: its clusters' centres (K, 3), covariance eigenvalues (K, 3) and
    eigenvectors (K, 3, 3) (columns), the hard cluster of each drawn point (or None: the most
    likely cluster of each point under those Gaussians), which clusters a rule wanted split, and
    a title."""

    k: int
    centers: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    title: str
    hard: np.ndarray | None = None
    failing: np.ndarray | None = None  # (K,) bool


def panels_from_sweep(sweep: list[dict[str, Any]], *, max_panels: int = 12) -> list[PartitionPanel]:
    """The panels of the global strategy's visited partitions (``explanation['sweep']`` of a
    result): every K when there are at most ``max_panels``, else the first, the last and K's
    evenly between."""
    steps = list(sweep)
    if len(steps) > max_panels:
        pick = np.unique(np.round(np.linspace(0, len(steps) - 1, max_panels)).astype(int))
        steps = [steps[i] for i in pick]
    out = []
    for st in steps:
        cl = st["clusters"]
        failing = np.array([c["action"] in ("split", "split_components") or
                            (c["action"] == "limit" and bool(c.get("rule"))) for c in cl], dtype=bool)
        what = ("APD's first local maximum" if st is sweep[0] else f"seeded in {st['seeded_in']} of K = {st['k'] - 1}"
                if st.get("seeded_in") else "")
        fails = f"{int(failing.sum())} fail{'s' if failing.sum() == 1 else ''}" if failing.any() else "all pass"
        title = f"K = {st['k']}{' (kept)' if st.get('kept') else ''}: {fails}" + (f"\n{what}" if what else "")
        out.append(PartitionPanel(
            k=int(st["k"]), centers=np.array([c["center"] for c in cl], dtype=float).reshape(-1, 3),
            eigenvalues=np.array([c["eigenvalues"] for c in cl], dtype=float).reshape(-1, 3),
            eigenvectors=np.array([c["eigenvectors"] for c in cl], dtype=float).reshape(-1, 3, 3),
            title=title, failing=failing))
    return out


def panels_from_ufp_onc(X: np.ndarray, ks: tuple[int, ...] = SERIES_K) -> tuple[list[PartitionPanel], Any]:
    """UFP-ONC re-run on ``X`` for K = 1 .. max(ks) (the divisive strategy's initial sweep): one
    panel per K of ``ks`` the sweep reaches, with its exact hard partition and the eigen-boxes of
    its (floored) fuzzy covariances. Returns the panels and the sweep's result."""
    from kbs.inference import ufp_onc

    res = ufp_onc(X, k_max=max(ks), stop="k_max")
    out = []
    for p in res.partitions:
        if p.k not in ks:
            continue
        lam, vec = np.linalg.eigh(p.covariances)
        out.append(PartitionPanel(k=p.k, centers=np.asarray(p.centers), eigenvalues=lam, eigenvectors=vec,
                                  title=f"K = {p.k}" + ("  (chosen by APD)" if p.k == res.chosen_k else "")
                                  + f"   APD {p.apd:.3g}", hard=p.predict(X)))
    return out, res


def most_likely(X: np.ndarray, centers: np.ndarray, eigenvalues: np.ndarray, eigenvectors: np.ndarray,
                floor: float = 1e-3) -> np.ndarray:
    """The cluster of highest Gaussian likelihood (equal priors) of each point (n,), the Gaussians
    given by centres and eigen-decompositions; eigenvalues floored at ``floor`` times the largest
    (a planar cluster's Gaussian is otherwise a sheet no point off it belongs to)."""
    best = np.full(len(X), -np.inf)
    out = np.zeros(len(X), dtype=np.int64)
    for j in range(len(centers)):
        lam = np.maximum(eigenvalues[j], floor * max(float(eigenvalues[j].max()), 1e-300))
        Y = (X - centers[j]) @ eigenvectors[j]
        ll = -0.5 * ((Y * Y) / lam).sum(axis=1) - 0.5 * float(np.log(lam).sum())
        better = ll > best
        best[better], out[better] = ll[better], j
    return out


def partition_series_figure(X: np.ndarray, panels: list[PartitionPanel], *, max_points: int = 30000,
                            point_size: float = 0.5, title: str = "", note: str = "") -> Any:
    """Top-down small multiples of K-partitions: the points (stride-decimated to ``max_points``)
    coloured by cluster, each cluster's fuzzy centre (a cross) and eigen-box (its covariance's three
    axes, half-sides ``2 sqrt(eigenvalue)``, drawn from above) in the cluster's colour; the boxes of
    clusters a rule wanted split dashed in red."""
    X = np.asarray(X, dtype=np.float64)
    idx = decimate(len(X), max_points)
    Xd = X[idx]
    ncol = min(4, max(1, len(panels)))
    nrow = int(np.ceil(len(panels) / ncol)) or 1
    fig = _figure(3.6 * ncol, 3.5 * nrow)
    order = np.argsort(Xd[:, 2])  # higher points drawn last: objects stay visible from above
    lo, hi = np.percentile(Xd[:, :2], [0.5, 99.5], axis=0)
    pad = 0.05 * float((hi - lo).max() or 1.0)
    for i, p in enumerate(panels):
        ax = fig.add_subplot(nrow, ncol, i + 1)
        hard = p.hard[idx] if p.hard is not None and len(p.hard) == len(X) else \
            p.hard if p.hard is not None else most_likely(Xd, p.centers, p.eigenvalues, p.eigenvectors)
        ax.scatter(Xd[order, 0], Xd[order, 1], c=_rgb(hard[order]), s=point_size, linewidths=0, rasterized=True)
        for j in range(len(p.centers)):
            bad = p.failing is not None and bool(p.failing[j])
            col = (1.0, 0.0, 0.0) if bad else tuple(_rgb(np.array([j]))[0] * 0.55)
            half = 2.0 * np.sqrt(np.maximum(p.eigenvalues[j], 0.0))
            for e in _box_edges(p.centers[j], p.eigenvectors[j], half):
                ax.plot(e[:, 0], e[:, 1], color=col, linewidth=1.3 if bad else 0.9, linestyle="--" if bad else "-")
        ax.scatter(p.centers[:, 0], p.centers[:, 1], marker="x", c="k", s=18, linewidths=1.0, zorder=3)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_title(p.title, fontsize=8)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
    fig.suptitle((title or f"K-partitions with eigen-boxes, top view ({len(Xd):,} points)")
                 + (f"\n{note}" if note else ""), fontsize=10)
    return fig


# -- a cluster's CAh view (the seed paper's figures 5-7) ------------------------------------------


def _fill_polygons(ax, polygons, colors, alpha: float = 0.45, edge: str = "k") -> None:
    for poly, col in zip(polygons, colors):
        ax.fill(*poly.exterior.xy, facecolor=col, alpha=alpha, edgecolor=edge, linewidth=0.6)
        for hole in poly.interiors:
            ax.fill(*hole.xy, facecolor="white", edgecolor=edge, linewidth=0.4)


def cah_figure(X: np.ndarray, normal: np.ndarray, center: np.ndarray, *, plane: str, alpha_factor: float = 3.0,
               opening_factor: float = 1.0, min_fraction: float = 0.05, max_points: int = 30000,
               title: str = "") -> Any:
    """A cluster's connexity (CAh) view (:func:`kbs.report.cah.cah_view`): its points ``X`` (n, 3)
    (stride-decimated to ``max_points``) projected on the plane through ``center`` with ``normal``
    (``plane`` names it: 'the ground plane', 'its best approximating plane'); their alpha-shape
    (the union of the Delaunay triangles of circumradius <= alpha, alpha = ``alpha_factor`` times
    the median spacing of the projected points); and its alpha-opening (erosion then dilation by a
    disc of radius ``opening_factor`` alpha), the components coloured, the significant ones (at
    least ``min_fraction`` of the points) numbered, what the opening removed in grey."""
    from kbs.report.cah import cah_view

    X = np.asarray(X, dtype=np.float64)[decimate(len(X), max_points)]
    v = cah_view(X, normal, center, alpha_factor=alpha_factor, opening_factor=opening_factor,
                 min_fraction=min_fraction)
    P = v.points
    fig = _figure(13.5, 4.6)
    axes = [fig.add_subplot(1, 3, i + 1) for i in range(3)]
    ps = max(0.3, min(4.0, 3000.0 / max(len(P), 1)))
    axes[0].scatter(P[:, 0], P[:, 1], s=ps, c="0.25", linewidths=0, rasterized=True)
    axes[0].set_title(f"{len(X):,} points projected on {plane}", fontsize=9)
    _fill_polygons(axes[1], v.shape, ["#6baed6"] * len(v.shape))
    axes[1].scatter(P[:, 0], P[:, 1], s=ps * 0.5, c="0.35", linewidths=0, rasterized=True)
    axes[1].set_title(f"alpha-shape, alpha = {v.alpha:.3g} ({alpha_factor:g} x spacing {v.spacing:.3g}): "
                      f"{len(v.shape)} piece{'s' if len(v.shape) != 1 else ''}", fontsize=9)
    if v.shape:
        _fill_polygons(axes[2], v.shape, ["#dddddd"] * len(v.shape), alpha=0.6, edge="0.7")
    _fill_polygons(axes[2], v.opening, [tuple(c) for c in _rgb(np.arange(len(v.opening)))], alpha=0.65)
    for i, g in enumerate(v.opening[:v.n_significant]):
        c = g.representative_point()
        axes[2].text(c.x, c.y, str(i), fontsize=9, ha="center", va="center", weight="bold")
    n = len(v.opening)
    axes[2].set_title(f"alpha-opening, disc radius {v.radius:.3g}: {n} component{'s' if n != 1 else ''}, "
                      f"{v.n_significant} significant", fontsize=9)
    lo, hi = P.min(axis=0), P.max(axis=0)
    pad = 0.04 * float((hi - lo).max() or 1.0)
    for ax in axes:
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=6)
    fig.suptitle(title or "CAh: projection, alpha-shape, alpha-opening", fontsize=10)
    return fig
