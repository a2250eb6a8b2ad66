"""The self-contained HTML report of a ``kbs run``: one file that opens offline.

:func:`write_report` writes a single HTML page holding

- a 3D scatter of the cloud (plotly) coloured by output cluster or by label, with a toggle between
  the two; noise (rejected points: cluster -1) is grey, and the points of a cluster no label's
  condition held for ("unlabelled (no label matched)": label -1 in a cluster) magenta;
- the fuzzy centre of each output cluster (its ``descriptors.center``) as a marker and its
  eigen-box: a wireframe box centred on the mean of the cluster's points, along the eigenvectors of
  their covariance, with half-sides ``2 sqrt(eigenvalue)``. The result JSON keeps only the
  eigenvalues and the normal of each cluster, not all its eigenvectors, so the box is computed here
  with numpy from the points (all of them, before any decimation) and their ``cluster`` values;
- the APD-per-K curve of the root record (the scene's initial partition), the chosen K marked;
- the explanation tree (one line per record, the sentences of :meth:`Explanation.line`); clicking a
  line, or a point of the 3D plot, shows why its cluster was split or accepted
  (:meth:`Explanation.why`, computed here for every record and embedded as JSON);
- the CAh view of the clicked output cluster (the seed paper's figures 5-7,
  :func:`kbs.report.cah.cah_view`): its points projected on the ground plane (on their best
  approximating plane when the run has none), their alpha-shape and its alpha-opening, computed
  here for the ``cah_clusters`` largest output clusters (each on at most ``cah_points`` of its
  points, a stride sample) and embedded as data; the page says so for the others;
- for the global strategy, the K-partitions it judged (the explanation's ``sweep``): a K slider
  shows each partition's clusters from above, their centres and eigen-box footprints, those a
  rule wanted split in red.

Nothing is fetched: plotly.js is inlined from the installed ``plotly`` package, gzip-compressed
and base64-encoded (4.8 MB of script become 2 MB), as is the page's data (the points as
float32/int16 arrays, the explanations); the page inflates both with the browser's
``DecompressionStream`` (Chrome 80, Firefox 113, Safari 16.4 or later; an older browser gets a
message saying so). Every embedded value goes through :func:`_json` (``<``, ``>``, ``&`` and the
JS line separators escaped) before compression, so a rule or cluster name cannot close the script.

At most ``max_points`` points are drawn (:data:`MAX_POINTS`, 50,000, by default): above it a
deterministic subset (``numpy.random.default_rng(seed)``, without replacement, in the input order)
is drawn and the page says so ("showing 50,000 of 1,234,567 points"); the boxes, centres,
explanations and each cluster's point count (in the hover text) are always those of the whole cloud.
Eigen-boxes are drawn for the :data:`MAX_BOXES` largest clusters (an airborne tile has hundreds);
clicking a point draws its cluster's box, whatever its size.

The colours are :mod:`kbs.report.colors`' palette, the one of the result PLY and of ``kbs render``.
The 3-D view has the run's up direction (:func:`kbs.report.view.view_of`: the ground normal)
vertical: a camera's frame (up -y) is seen upright from behind the camera, not on its side.

The page carries its own error hook (``window.onerror``, unhandled rejections, ``console.error``):
an error is written into a visible ``#kbs-errors`` box and into ``document.title``, and the page
sets ``data-kbs-ready="1"`` on ``<body>`` once everything is drawn, so a headless browser's
``--dump-dom`` tells whether the page rendered and without error (the tests read it that way).

``report.html#c1.0`` opens with the explanation of record ``c1.0`` shown.
"""
from __future__ import annotations

import base64
import functools
import gzip
import html
import json
import re
from pathlib import Path
from collections.abc import Callable, Collection, Sequence
from typing import Any

import numpy as np

from kbs.errors import require
from kbs.geometry.pca import principal_axes
from kbs.knowledge.explain import Explanation
from kbs.knowledge.groundfacts import GroundFacts
from kbs.report.colors import NOISE_HEX, hex_colors
from kbs.report.view import view_of

__all__ = ["write_report", "eigen_boxes"]

#: Points drawn at most by default (a random subset above it; the page says so).
MAX_POINTS = 50_000
#: Eigen-boxes drawn by default: those of the largest clusters (the others on a click).
MAX_BOXES = 30
#: The colour of the points of an output cluster no label's condition held for (label -1 in a
#: cluster): not noise, which they are not (and which a rule base may use as a label's name).
UNLABELLED = "#ff00ff"
#: The label key of those points in the page (noise keeps -1).
_UNLABELLED_KEY = -2


def _json(obj: Any) -> str:
    """JSON safe to put inside ``<script>``: no ``</script>``, ``<!--``, ``&`` or line separators."""
    s = json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_plain)
    return (s.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
            .replace("\u2028", "\\u2028").replace("\u2029", "\\u2029"))


def _plain(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _grid_image(grid: tuple[tuple[int, int], np.ndarray] | None, cluster: np.ndarray) -> dict[str, Any] | None:
    """The output cluster of every pixel of an organised input (-2 where the image has no point,
    -1 noise), row by row, as int32; None without a grid."""
    if grid is None:
        return None
    (rows, cols), index = grid
    image = np.full(int(rows) * int(cols), -2, dtype=np.int32)
    image[np.asarray(index, dtype=np.int64)] = cluster
    return {"rows": int(rows), "cols": int(cols), "cluster": _b64(image, "i4")}


def _b64(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode("ascii")


def eigen_boxes(xyz: np.ndarray, cluster: np.ndarray, n_clusters: int) -> list[dict[str, Any] | None]:
    """For each output cluster 0..n_clusters-1, the box of its points along their covariance axes.

    Parameters
    ----------
    xyz : (n_points, 3) array
    cluster : (n_points,) int array, -1 for noise
    n_clusters : int

    Returns
    -------
    list of dict or None
        ``{"center": (3,), "axes": (3, 3) rows = unit eigenvectors (ascending eigenvalues),
        "half": (3,) = 2 sqrt(eigenvalue), "corners": (8, 3)}``, or None for a cluster with fewer
        than 2 points. The covariance is the population one (``np.cov(..., bias=True)``).
    """
    out: list[dict[str, Any] | None] = []
    cluster = np.asarray(cluster)
    order = np.argsort(cluster, kind="stable")  # group the points once instead of a mask per cluster
    bounds = np.searchsorted(cluster[order], np.arange(n_clusters + 1))
    for i in range(n_clusters):
        P = xyz[order[bounds[i]:bounds[i + 1]]]
        if len(P) < 2:
            out.append(None)
            continue
        pca = principal_axes(P)
        c, w, V = pca.center, pca.eigenvalues, pca.eigenvectors
        half = 2.0 * np.sqrt(np.clip(w, 0.0, None))
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        corners = c + (signs * half) @ V.T
        out.append({"center": c, "axes": V.T, "half": half, "corners": corners})
    return out


#: The 12 edges of a box whose corners are indexed by the bits (x, y, z) of signs as above.
_EDGES = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7))


def _box_lines(boxes: Sequence[dict[str, Any] | None], only: Collection[int] | None = None) -> dict[str, list]:
    xs: list = []
    ys: list = []
    zs: list = []
    text: list = []
    for i, b in enumerate(boxes):
        if b is None or (only is not None and i not in only):
            continue
        for a, e in _EDGES:
            for p in (b["corners"][a], b["corners"][e]):
                xs.append(round(float(p[0]), 5))
                ys.append(round(float(p[1]), 5))
                zs.append(round(float(p[2]), 5))
                text.append(i)
            for column in (xs, ys, zs, text):
                column.append(None)
    return {"x": xs, "y": ys, "z": zs, "cluster": text}


def _gz64(text: str) -> str:
    """``text`` gzip-compressed (mtime 0: the same page for the same inputs) and base64-encoded."""
    return base64.b64encode(gzip.compress(text.encode("utf-8"), compresslevel=9, mtime=0)).decode("ascii")


@functools.lru_cache(maxsize=1)
def _plotly_gz64(get_plotlyjs: Callable[[], str]) -> str:
    """plotly.js compressed once a process (a second or so of gzip)."""
    return _gz64(get_plotlyjs())


def _largest(clusters: Sequence[dict[str, Any]], k: int) -> list[int]:
    """Indices of the ``k`` clusters with the most points (ties: the lower index)."""
    order = sorted(range(len(clusters)), key=lambda i: (-int(clusters[i].get("n_points", 0)), i))
    return sorted(order[:max(k, 0)])


def _camera(ground: GroundFacts) -> dict[str, Any]:
    """The plotly scene camera: up is the run's up direction; a scan not z up is seen from behind
    and above (a camera's frame from behind the camera); a z-up scan keeps plotly's default eye."""
    v = view_of(ground)
    cam: dict[str, Any] = {"up": dict(zip("xyz", np.round(v.up, 6).tolist()))}
    if not (v.level and v.up[2] > 0):
        cam["eye"] = dict(zip("xyz", np.round(-1.6 * v.forward + 0.9 * v.up, 6).tolist()))
    return {"camera": cam, "describe": v.describe(), "level": bool(v.level and v.up[2] > 0)}


def _decimate(n: int, max_points: int, seed: int) -> np.ndarray | None:
    if max_points <= 0 or n <= max_points:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))


def write_report(path: str | Path, xyz: np.ndarray, cluster: np.ndarray, label: np.ndarray,
                 label_names: Sequence[str], explanation_dict: dict[str, Any], clusters: Sequence[dict[str, Any]],
                 *, title: str, max_points: int = MAX_POINTS, seed: int = 0, max_boxes: int = MAX_BOXES,
                 cah_clusters: int = 30, cah_points: int = 2000,
                 grid: tuple[tuple[int, int], np.ndarray] | None = None) -> Path:
    """Write the self-contained HTML report of one segmentation.

    Parameters
    ----------
    path : str or Path
        The HTML file to write (its directory must exist).
    xyz : (n_points, 3) array
        The points.
    cluster : (n_points,) int array
        Output cluster of each point (index into ``clusters``), -1 for noise.
    label : (n_points,) int array
        Label of each point (index into ``label_names``), -1 for noise.
    label_names : sequence of str
    explanation_dict : dict
        ``Explanation.to_dict()`` (the ``explanation`` of a result JSON).
    clusters : sequence of dict
        The ``clusters`` of a result JSON: ``index``, ``ids``, ``label``, ``n_points``, ``descriptors``.
    title : str
        Shown as the page's title and heading.
    max_points : int
        Above this many points, a random subset of this size is shown (the page says so);
        ``<= 0`` shows them all.
    seed : int
        Seed of that subset (the same inputs give the same page).
    max_boxes : int
        Eigen-boxes drawn when the page opens: those of the largest clusters (the page says how
        many of how many); a click on a point draws its cluster's box.
    cah_clusters, cah_points : int
        The CAh view is computed for this many of the largest output clusters, each on at most
        ``cah_points`` of its points.
    grid : ((rows, cols), index), optional
        For an organised input (a range image): its grid and each point's pixel (flat index, as
        ``PointCloud.shape`` / ``.index``); the page then shows the segmentation as an image, one
        colour per output cluster on the pixel grid, beside the 3D view.

    Returns
    -------
    Path
        ``path``.
    """
    get_plotlyjs = require("plotly.offline", "report", "the HTML report").get_plotlyjs

    xyz = np.asarray(xyz, dtype=np.float64)
    cluster = np.asarray(cluster).astype(np.int32, copy=False)
    label = np.asarray(label).astype(np.int32, copy=False)
    n = len(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or cluster.shape != (n,) or label.shape != (n,):
        raise ValueError(f"xyz must be (n_points, 3) and cluster, label (n_points,); got {xyz.shape}, "
                         f"{cluster.shape}, {label.shape}")
    expl = Explanation.from_dict(explanation_dict)
    n_out = len(clusters)
    boxes = eigen_boxes(xyz, cluster, n_out)

    keep = _decimate(n, max_points, seed)
    if keep is None:
        shown, notice = np.arange(n), f"all {n:,} points shown"
    else:
        shown, notice = keep, f"showing {len(keep):,} of {n:,} points (a random subset, seed {seed})"
    origin = xyz.mean(axis=0) if n else np.zeros(3)  # float32 keeps mm precision around the origin

    records = []
    for rec in expl.walk():
        records.append({"id": rec.id, "parent": rec.parent, "depth": rec.depth, "line": expl.line(rec),
                        "why": expl.why(rec.id), "action": rec.action, "label": rec.label,
                        "output_index": rec.output_index})
    root = expl.records[expl.root]
    apd = None if root.apd is None else {"ks": list(root.apd.ks), "apd": list(root.apd.apd), "chosen": root.apd.chosen}
    centres = [c.get("descriptors", {}).get("center") for c in clusters]
    boxed = _largest(clusters, max_boxes)
    small = np.int16 if max(n_out, len(label_names)) < 32000 else np.int32  # the page reads the width
    data = {
        "n": int(n), "shown": int(len(shown)), "notice": notice,
        "origin": origin.tolist(),
        "xyz": _b64((xyz[shown] - origin).astype(np.float32), "f4"),
        "int": np.dtype(small).itemsize,
        "cluster": _b64(cluster[shown], np.dtype(small).str[1:]),
        "label": _b64(np.where((label < 0) & (cluster >= 0), _UNLABELLED_KEY, label)[shown].astype(small),
                      np.dtype(small).str[1:]),
        "label_names": list(label_names),
        "clusters": [{"index": int(c.get("index", i)), "ids": list(c.get("ids", [])), "label": c.get("label"),
                      "n_points": int(c.get("n_points", 0)), "center": centres[i]} for i, c in enumerate(clusters)],
        "boxes": _box_lines(boxes, set(boxed)), "boxed": len(boxed),
        "corners": [None if b is None else np.round(b["corners"], 5).tolist() for b in boxes],
        "records": records, "root": expl.root, "apd": apd,
        "palette": hex_colors(max(n_out, len(label_names), 1)), "noise": NOISE_HEX, "unlabelled": UNLABELLED,
        "unlabelled_key": _UNLABELLED_KEY, "view": _camera(expl.ground),
        "cah": _cah_views(xyz, cluster, clusters, expl.ground, cah_clusters, cah_points),
        "cah_limit": int(cah_clusters),
        "sweep": _sweep_data(expl.sweep),
        "grid": _grid_image(grid, cluster),
        "head": {"rule_base": expl.rule_base, "rule_file": expl.rule_file, "strategy": expl.strategy,
                 "ground": expl.ground_line() if expl.ground else "", "notes": list(expl.notes)},
    }
    fill = {"TITLE": html.escape(title), "NOTICE": html.escape(notice),
            "PLOTLYJS": _plotly_gz64(get_plotlyjs), "DATA": _gz64(_json(data))}
    page = re.sub(r"%%([A-Z]+)%%", lambda mo: fill[mo.group(1)], _TEMPLATE)
    path = Path(path)
    path.write_text(page, encoding="utf-8")
    return path


def _cah_views(xyz: np.ndarray, cluster: np.ndarray, clusters: Sequence[dict[str, Any]], ground: GroundFacts,
               n_views: int, max_points: int) -> dict[str, Any]:
    """Output cluster index (as a string) -> its CAh view as page data, for the ``n_views``
    largest clusters (see :func:`write_report`)."""
    from kbs.report.cah import cah_view, rings

    if n_views <= 0 or not len(clusters):
        return {}
    largest = sorted(range(len(clusters)), key=lambda i: (-int(clusters[i].get("n_points", 0)), i))[:n_views]
    order = np.argsort(cluster, kind="stable")
    ids = cluster[order]
    normal = ground.normal
    out: dict[str, Any] = {}
    for i in largest:
        a, b = np.searchsorted(ids, [i, i + 1])
        sel = order[a:b]
        if sel.size < 3:
            continue
        P = xyz[sel[::max(1, int(np.ceil(sel.size / max_points)))]]
        center = P.mean(axis=0)
        if normal is not None:
            n, plane = np.asarray(normal, dtype=float), "the ground plane"
        else:
            n, plane = principal_axes(P).normal, "its best approximating plane"
        try:
            v = cah_view(P, n, center)
        except (ValueError, ArithmeticError) as exc:  # e.g. every point on one position: no shape
            out[str(i)] = {"note": f"no CAh view: {exc}"}
            continue
        tol = 0.25 * v.alpha
        out[str(i)] = {"plane": plane, "n": int(sel.size), "shown": int(len(P)), "alpha": v.alpha,
                       "radius": v.radius, "spacing": v.spacing, "significant": v.n_significant,
                       "components": len(v.opening), "points": _b64(v.points, "f4"),
                       "shape": rings(v.shape, tol), "opening": rings(v.opening, tol)}
    return out


def _sweep_data(sweep: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The global strategy's partitions for the page: per K, each cluster's centre and the
    footprint (seen from above) of its eigen-box, whether a rule wanted it split."""
    out = []
    for st in sweep:
        cl = []
        for c in st["clusters"]:
            centre = np.asarray(c["center"], dtype=float)
            axes = np.asarray(c["eigenvectors"], dtype=float)
            half = 2.0 * np.sqrt(np.maximum(np.asarray(c["eigenvalues"], dtype=float), 0.0))
            signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
            corners = (centre + (signs * half) @ axes.T)[:, :2]
            hull = _hull2d(corners)
            cl.append({"id": c["id"], "points": int(c["points"]), "center": centre[:2].round(5).tolist(),
                       "box": [hull[:, 0].round(5).tolist(), hull[:, 1].round(5).tolist()],
                       "failing": c["action"] in ("split", "split_components") or
                       (c["action"] == "limit" and bool(c.get("rule")))})
        out.append({"k": int(st["k"]), "kept": bool(st.get("kept")), "seeded_in": st.get("seeded_in"),
                    "clusters": cl})
    return out


def _hull2d(P: np.ndarray) -> np.ndarray:
    """The convex hull of 2D points, closed (the first vertex repeated), by the monotone chain."""
    pts = sorted(map(tuple, np.round(P, 12)))
    if len(pts) < 3:
        return np.array(pts + pts[:1])

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    upper: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    hull = lower[:-1] + upper[:-1]
    return np.array(hull + hull[:1])


#: The page's error hook (first in ``<head>``, before plotly.js, so that its own errors are caught too):
#: every error goes into a visible ``#kbs-errors`` box and into ``document.title`` ("KBS-ERROR: ...").
#: Shared with the map view (:mod:`kbs.report.mapview`).
ERROR_HOOK = r"""<script>
(function () {
  var errors = [];
  function report(msg) {
    errors.push(String(msg));
    document.title = "KBS-ERROR: " + errors.join(" | ");
    var box = document.getElementById("kbs-errors");
    if (box) { box.textContent = errors.join("\n"); box.style.display = "block"; }
  }
  window.kbsErrors = errors;
  window.addEventListener("error", function (e) {
    report("uncaught: " + (e.message || e) + (e.filename ? " (" + e.lineno + ":" + e.colno + ")" : ""));
  });
  window.addEventListener("unhandledrejection", function (e) { report("unhandled rejection: " + e.reason); });
  var ce = console.error;
  console.error = function () {
    report("console.error: " + Array.prototype.map.call(arguments, String).join(" "));
    return ce.apply(console, arguments);
  };
})();
</script>"""

#: ``bytes(b64)`` and ``inflate(id)``: a base64 blob as an ArrayBuffer, and a gzip-compressed blob
#: of the page inflated by the browser (``DecompressionStream``). Shared with the map view.
INFLATE_JS = r"""  function bytes(b64) {
    var s = atob(b64), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return u.buffer;
  }
  // plotly.js and the data are gzip-compressed and base64-encoded (a quarter of their size)
  function inflate(id) {
    if (typeof DecompressionStream === "undefined")
      return Promise.reject(new Error("this browser cannot inflate the report's compressed data (DecompressionStream: " +
                                      "Chrome 80, Firefox 113, Safari 16.4 or later)"));
    var blob = new Blob([bytes(document.getElementById(id).textContent)]);
    return new Response(blob.stream().pipeThrough(new DecompressionStream("gzip"))).text();
  }
"""

# The head and the top of the body that the scan report and the map view share (title, error hook,
# header, error box); each page adds its own styles between them (PAGE_HEAD + styles + PAGE_TOP + body).
PAGE_HEAD = r"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>%%TITLE%%</title>
@@ERROR_HOOK@@
<style>
  body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0; color: #222; }
  header { padding: 6px 12px; border-bottom: 1px solid #ddd; }
  header h1 { font-size: 17px; margin: 0 0 2px 0; }
  header .meta { font-size: 12px; color: #555; }
  #kbs-errors { display: none; background: #fdd; color: #900; padding: 6px 12px; white-space: pre-wrap; font: 12px monospace; }
  main { display: flex; gap: 8px; padding: 6px; height: calc(100vh - 56px); box-sizing: border-box; }
"""
PAGE_TOP = r"""  h2 { font-size: 13px; margin: 2px 0; }
</style>
</head>
<body data-kbs-ready="0">
<header>
  <h1>%%TITLE%%</h1>
  <div class="meta"><span id="meta"></span> &middot; <span id="notice">%%NOTICE%%</span></div>
</header>
<div id="kbs-errors"></div>
<main>
"""

# The end of the page both templates share: the gzip-compressed plotly.js and data, inflated in
# the browser, plotly.js run, then the page's own start(D) with the data (defined after it).
PAGE_BOOT = r"""<script id="kbs-plotly" type="application/gzip">%%PLOTLYJS%%</script>
<script id="kbs-data" type="application/gzip">%%DATA%%</script>
<script>
(function () {
  "use strict";
@@INFLATE_JS@@  inflate("kbs-plotly").then(function (code) {
    var s = document.createElement("script");
    s.textContent = code;  // runs now: defines window.Plotly
    document.head.appendChild(s);
    return inflate("kbs-data");
  }).then(function (text) { start(JSON.parse(text)); });
"""

# The page. Placeholders are filled in one pass (so nothing filled in is re-read as a placeholder). The error hook comes first, before plotly.js, so that its own errors are caught too.
_TEMPLATE = PAGE_HEAD + r"""  #left { flex: 3 1 0; min-width: 0; display: flex; flex-direction: column; }
  #right { flex: 2 1 0; min-width: 280px; display: flex; flex-direction: column; gap: 6px; }
  #scatter { flex: 1 1 auto; min-height: 300px; height: calc(100vh - 100px); }
  #controls { font-size: 13px; padding: 2px 0; }
  #controls button { font-size: 13px; margin-right: 4px; }
  #controls button.on { font-weight: bold; background: #dde8f5; }
  #apd { height: 190px; flex: none; }
  #tree { flex: 1 1 50%; overflow: auto; font: 12px/1.35 monospace; border: 1px solid #ddd; padding: 4px; }
  #tree ul { list-style: none; margin: 0; padding-left: 14px; }
  #tree > ul { padding-left: 0; }
  #tree li > span { cursor: pointer; white-space: nowrap; }
  #tree li > span:hover { background: #eef; }
  #tree li > span.sel { background: #ffe9a8; }
  #tree .accept { color: #1a6b1a; } #tree .reject { color: #888; } #tree .limit { color: #a15c00; }
  #cah { height: 260px; flex: none; border: 1px solid #ddd; font: 12px monospace; color: #666; }
  #sweep { height: 300px; flex: none; border: 1px solid #ddd; }
  #why { flex: 1 1 40%; overflow: auto; font: 12px/1.35 monospace; white-space: pre-wrap; border: 1px solid #ddd; padding: 4px; background: #fafafa; }
""" + PAGE_TOP + r"""  <div id="left">
    <div id="controls">colour by:
      <button id="by-cluster" class="on" type="button">cluster</button><button id="by-label" type="button">label</button>
      <label><input id="show-boxes" type="checkbox" checked> eigen-boxes</label>
      <span style="color:#666">&middot; click a point or a tree line to see why</span>
    </div>
    <div id="scatter"></div>
    <div id="grid-box" style="display:none"><h2>On the range image's pixel grid (one colour per output cluster; white: no data)</h2><div id="grid"></div></div>
    <div id="sweep-box" style="display:none"><h2>The global strategy's K-partitions (top view; red: a rule wanted it split)</h2><div id="sweep"></div></div>
  </div>
  <div id="right">
    <div id="apd"></div>
    <h2>Explanation tree</h2>
    <div id="tree"></div>
    <h2>Why</h2>
    <div id="why">Click a cluster in the 3D view or a line of the tree.</div>
    <h2>CAh view: projection, alpha-shape, alpha-opening</h2>
    <div id="cah">Click a cluster to see its projection, alpha-shape and alpha-opening.</div>
  </div>
</main>
""" + PAGE_BOOT + r"""
function start(D) {
  var Int = D.int === 2 ? Int16Array : Int32Array;
  var xyz = new Float32Array(bytes(D.xyz)), cl = new Int(bytes(D.cluster)), lb = new Int(bytes(D.label));
  var o = D.origin, m = D.shown;
  var recById = {};
  D.records.forEach(function (r) { recById[r.id] = r; });
  function colour(i) { return i === D.unlabelled_key ? D.unlabelled : i < 0 ? D.noise : D.palette[i]; }

  document.getElementById("meta").textContent = "rule base '" + D.head.rule_base + "' (" + D.head.rule_file +
    "), strategy " + D.head.strategy + (D.head.ground ? "; ground: " + D.head.ground : "") +
    "; " + D.clusters.length + " clusters" + (D.view.level ? "" : "; view: " + D.view.describe);

  // One trace per colouring holding every shown point, coloured point by point (hundreds of traces,
  // one per cluster, make plotly several times slower to draw); the legend is made of empty traces.
  var present = function (key) {
    var seen = {};
    for (var i = 0; i < m; i++) seen[key[i]] = true;
    return Object.keys(seen).map(Number).sort(function (a, b) { return (a < 0) - (b < 0) || a - b; });
  };
  var X = new Float64Array(m), Y = new Float64Array(m), Z = new Float64Array(m);
  for (var i = 0; i < m; i++) { X[i] = xyz[3 * i] + o[0]; Y[i] = xyz[3 * i + 1] + o[1]; Z[i] = xyz[3 * i + 2] + o[2]; }
  function cloudTrace(key, nameOf, name, visible) {
    var col = new Array(m), txt = new Array(m);
    for (var i = 0; i < m; i++) { col[i] = colour(key[i]); txt[i] = nameOf(key[i]); }
    return { type: "scatter3d", mode: "markers", name: name, x: X, y: Y, z: Z, visible: visible, showlegend: false,
             marker: { size: 1.5, color: col }, hoverinfo: "text", text: txt };
  }
  function clusterName(k) {
    var c = D.clusters[k];
    return k < 0 ? "noise" : "cluster " + k + (c && c.label ? " (" + c.label + ")" : " (unlabelled: no label matched)") +
      (c ? ", " + c.n_points.toLocaleString("en") + " points" : "");
  }
  function labelName(k) {
    return k === D.unlabelled_key ? "unlabelled (no label matched)" : k < 0 ? "noise" : (D.label_names[k] || "label " + k);
  }
  function legendTrace(k, name, visible) {
    return { type: "scatter3d", mode: "markers", name: name, x: [null], y: [null], z: [null], visible: visible,
             marker: { size: 6, color: colour(k) }, hoverinfo: "skip", showlegend: true };
  }
  var traces = [cloudTrace(cl, clusterName, "clusters", true), cloudTrace(lb, labelName, "labels", false)];
  var byCluster = [0], byLabel = [1];
  var kc = present(cl), manyClusters = kc.length > 30;  // a legend of hundreds of clusters hides the plot
  kc.forEach(function (k) {
    if (manyClusters && k >= 0) return;
    byCluster.push(traces.length);
    traces.push(legendTrace(k, clusterName(k), true));
  });
  present(lb).forEach(function (k) {
    byLabel.push(traces.length);
    traces.push(legendTrace(k, labelName(k), false));
  });
  var cx = [], cy = [], cz = [], ct = [], cc = [];
  D.clusters.forEach(function (c, i) {
    if (!c.center) return;
    cx.push(c.center[0]); cy.push(c.center[1]); cz.push(c.center[2]); cc.push(i);
    ct.push("cluster " + i + (c.label ? " (" + c.label + ")" : " (unlabelled: no label matched)") + ": " + c.ids.join(", "));
  });
  var centreTrace = traces.length;
  traces.push({ type: "scatter3d", mode: "markers", name: "fuzzy centres", x: cx, y: cy, z: cz, text: ct,
                hoverinfo: "text",
                marker: { size: 5, symbol: "diamond", color: "#000", line: { color: "#fff", width: 1 } } });
  var boxTrace = traces.length;
  var nBoxes = D.corners.filter(function (c) { return c; }).length;
  traces.push({ type: "scatter3d", mode: "lines", name: "eigen-boxes (2 sqrt(eigenvalue))" +
                  (D.boxed < nBoxes ? " of the " + D.boxed + " largest of " + D.clusters.length + " clusters" : ""),
                x: D.boxes.x, y: D.boxes.y, z: D.boxes.z, hoverinfo: "skip", connectgaps: false,
                line: { color: "#222", width: 2 } });
  // the box of the cluster clicked last, whatever its size
  var EDGES = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
  var pickTrace = traces.length;
  traces.push({ type: "scatter3d", mode: "lines", name: "the clicked cluster's box", x: [], y: [], z: [],
                hoverinfo: "skip", connectgaps: false, showlegend: false, line: { color: "#d62728", width: 4 } });
  function showBox(i) {
    var c = i >= 0 ? D.corners[i] : null, x = [], y = [], z = [];
    if (c) EDGES.forEach(function (e) {
      x.push(c[e[0]][0], c[e[1]][0], null); y.push(c[e[0]][1], c[e[1]][1], null); z.push(c[e[0]][2], c[e[1]][2], null);
    });
    Plotly.restyle(gd, { x: [x], y: [y], z: [z] }, [pickTrace]);
  }

  var gd = document.getElementById("scatter");
  var layout = { margin: { l: 0, r: 0, t: 0, b: 0 }, height: Math.max(300, gd.clientHeight), legend: { itemsizing: "constant", font: { size: 11 }, x: 0, y: 1, itemclick: false, itemdoubleclick: false,
                           bgcolor: "rgba(255,255,255,0.7)" },
                 scene: { aspectmode: "data", xaxis: { title: { text: "x" } }, yaxis: { title: { text: "y" } },
                          zaxis: { title: { text: "z" } }, camera: D.view.camera },
                 uirevision: "keep" };
  var config = { responsive: true, displaylogo: false };

  function showWhy(ids, heading) {
    document.querySelectorAll("#tree span.sel").forEach(function (e) { e.classList.remove("sel"); });
    var parts = [];
    ids.forEach(function (id) {
      var r = recById[id];
      if (!r) return;
      parts.push(r.why);
      var el = document.getElementById("rec-" + id);
      if (el) { el.classList.add("sel"); el.scrollIntoView({ block: "nearest" }); tree.scrollLeft = 0; }
    });
    document.getElementById("why").textContent = (heading ? heading + "\n\n" : "") +
      (parts.length ? parts.join("\n\n----\n\n") : "no record");
  }
  function drawCah(i) {
    var el = document.getElementById("cah");
    var v = D.cah[String(i)];
    Plotly.purge(el);
    if (!v || v.note) {
      el.textContent = i < 0 ? "noise: no CAh view" : v ? "cluster " + i + ": " + v.note :
        "cluster " + i + ": the CAh view is computed for the " + D.cah_limit + " largest clusters only";
      return;
    }
    el.textContent = "";
    var p = new Float32Array(bytes(v.points)), px = [], py = [];
    for (var j = 0; j < p.length; j += 2) { px.push(p[j]); py.push(p[j + 1]); }
    var tr = [];
    v.shape.forEach(function (r) {
      tr.push({ type: "scatter", mode: "lines", x: r.x, y: r.y, fill: "toself", hoverinfo: "skip", showlegend: false,
                fillcolor: r.hole ? "#ffffff" : "rgba(107,174,214,0.30)", line: { color: "#6baed6", width: 1 } });
    });
    v.opening.forEach(function (r) {
      var c = D.palette[r.part % D.palette.length];
      tr.push({ type: "scatter", mode: "lines", x: r.x, y: r.y, fill: "toself", hoverinfo: "skip", showlegend: false,
                fillcolor: r.hole ? "#ffffff" : c, opacity: 0.55, line: { color: "#222", width: 1 } });
    });
    tr.push({ type: "scatter", mode: "markers", x: px, y: py, hoverinfo: "skip", showlegend: false,
              marker: { size: 2, color: "#333" } });
    var head = "cluster " + i + " on " + v.plane + (v.shown < v.n ? " (" + v.shown + " of " + v.n + " points)" : "") +
      "<br>alpha " + v.alpha.toPrecision(3) + " (blue: alpha-shape), opening disc " + v.radius.toPrecision(3) +
      ": " + v.components + " component" + (v.components === 1 ? "" : "s") + ", " + v.significant + " significant";
    Plotly.newPlot(el, tr, { margin: { l: 40, r: 8, t: 36, b: 24 }, title: { text: head, font: { size: 11 } },
                             xaxis: { zeroline: false }, yaxis: { zeroline: false, scaleanchor: "x" } },
                   { responsive: true, displayModeBar: false });
  }
  function showCluster(i) {
    showBox(i);
    drawCah(i);
    if (i < 0) {
      var rej = D.records.filter(function (r) { return r.action === "reject"; }).map(function (r) { return r.id; });
      showWhy(rej, "noise: points in no output cluster" + (rej.length ? "; rejected records:" : ""));
      return;
    }
    var c = D.clusters[i];
    showWhy(c.ids, "cluster " + i + (c.label ? " (" + c.label + ")" : " (unlabelled: no label matched)") + ", " + c.n_points.toLocaleString("en") +
            " points, from record" + (c.ids.length > 1 ? "s " : " ") + c.ids.join(", ") + ":");
  }

  // the tree: nested lists following parent links, in the records' depth-first order
  var tree = document.getElementById("tree"), lists = {};
  var top = document.createElement("ul"); tree.appendChild(top);
  D.records.forEach(function (r) {
    var parentList = r.parent && lists[r.parent] ? lists[r.parent] : top;
    var li = document.createElement("li"), sp = document.createElement("span");
    sp.id = "rec-" + r.id; sp.textContent = r.line; sp.className = r.action; sp.title = "click: why";
    sp.addEventListener("click", function () {
      showWhy([r.id]);
      if (r.output_index !== null && r.output_index !== undefined) drawCah(r.output_index);
    });
    li.appendChild(sp); parentList.appendChild(li);
    var ul = document.createElement("ul"); li.appendChild(ul); lists[r.id] = ul;
  });

  function setMode(mode) {
    var vis = traces.map(function (t, i) {
      if (byCluster.indexOf(i) >= 0) return mode === "cluster";
      if (byLabel.indexOf(i) >= 0) return mode === "label";
      return i === boxTrace ? document.getElementById("show-boxes").checked : true;
    });
    Plotly.restyle(gd, { visible: vis });
    document.getElementById("by-cluster").classList.toggle("on", mode === "cluster");
    document.getElementById("by-label").classList.toggle("on", mode === "label");
  }
  document.getElementById("by-cluster").addEventListener("click", function () { setMode("cluster"); });
  document.getElementById("by-label").addEventListener("click", function () { setMode("label"); });
  document.getElementById("show-boxes").addEventListener("change", function (e) {
    Plotly.restyle(gd, { visible: e.target.checked }, [boxTrace]);
  });

  var done = [Plotly.newPlot(gd, traces, layout, config).then(function () {
    gd.on("plotly_click", function (ev) {
      if (!ev || !ev.points || !ev.points.length) return;
      var p = ev.points[0];
      if (p.curveNumber === centreTrace) { showCluster(cc[p.pointNumber]); return; }
      if (p.curveNumber <= 1) showCluster(cl[p.pointNumber]);
    });
  })];
  if (D.apd) {
    var ki = D.apd.ks.indexOf(D.apd.chosen);
    done.push(Plotly.newPlot("apd", [
      { type: "scatter", mode: "lines+markers", x: D.apd.ks, y: D.apd.apd, name: "APD", line: { color: "#1f77b4" } },
      { type: "scatter", mode: "markers+text", x: [D.apd.chosen], y: [D.apd.apd[ki]], name: "chosen K",
        text: ["K=" + D.apd.chosen], textposition: "bottom right",
        marker: { size: 12, color: "#d62728", symbol: "star" } }],
      { margin: { l: 60, r: 10, t: 28, b: 36 }, showlegend: false,
        title: { text: "APD per K of the initial partition (" + D.root + ")", font: { size: 12 } },
        xaxis: { title: { text: "K" }, dtick: 1 }, yaxis: { title: { text: "APD" } } },
      { responsive: true, displayModeBar: false }));
  } else {
    document.getElementById("apd").textContent = "no APD curve for the root record";
  }
  if (D.grid) {  // an organised input: the segmentation as an image, clusters in the 3D view's colours
    document.getElementById("grid-box").style.display = "block";
    var gi = new Int32Array(bytes(D.grid.cluster)), z = [], used = {};
    for (var r = 0; r < D.grid.rows; r++) {
      var row = [];
      for (var c = 0; c < D.grid.cols; c++) {
        var v = gi[r * D.grid.cols + c];
        row.push(v === -2 ? null : v);
        if (v !== -2) used[v] = true;
      }
      z.push(row);
    }
    var keys = Object.keys(used).map(Number).sort(function (a, b) { return a - b; });
    var lo = keys.length ? keys[0] : 0, hi = keys.length ? keys[keys.length - 1] : 0, span = Math.max(hi - lo, 1);
    var scale = keys.map(function (k) { return [(k - lo) / span, colour(k)]; });
    if (scale.length < 2) scale = [[0, scale.length ? scale[0][1] : D.noise], [1, scale.length ? scale[0][1] : D.noise]];
    done.push(Plotly.newPlot("grid", [{ type: "heatmap", z: z, zmin: lo, zmax: lo + span, colorscale: scale,
                                        showscale: false, hovertemplate: "row %{y}, column %{x}: cluster %{z}<extra></extra>" }],
      { margin: { l: 40, r: 10, t: 10, b: 30 }, yaxis: { autorange: "reversed", scaleanchor: "x" } },
      { responsive: true, displayModeBar: false }).then(function (gd) {
        gd.on("plotly_click", function (ev) { var k = ev.points[0].z; if (k !== null && k !== undefined) showCluster(k); });
      }));
  }
  if (D.sweep.length) {
    document.getElementById("sweep-box").style.display = "block";
    var sw = [], steps = [], visible0 = D.sweep.length - 1;
    D.sweep.forEach(function (st, s) {
      var idx = [];
      st.clusters.forEach(function (c, j) {
        idx.push(sw.length);
        sw.push({ type: "scatter", mode: "lines", x: c.box[0], y: c.box[1], visible: s === visible0, showlegend: false,
                  line: { color: c.failing ? "#ff0000" : D.palette[j % D.palette.length], width: c.failing ? 2 : 1,
                          dash: c.failing ? "dash" : "solid" },
                  hoverinfo: "text", text: c.id + " (" + c.points + " pts)" + (c.failing ? ": a rule wanted it split" : "") });
      });
      idx.push(sw.length);
      sw.push({ type: "scatter", mode: "markers", visible: s === visible0, showlegend: false, hoverinfo: "text",
                x: st.clusters.map(function (c) { return c.center[0]; }),
                y: st.clusters.map(function (c) { return c.center[1]; }),
                text: st.clusters.map(function (c) { return c.id; }), marker: { size: 6, color: "#000", symbol: "x" } });
      steps.push(idx);
    });
    var sliderSteps = D.sweep.map(function (st, s) {
      var vis = sw.map(function (t, n) { return steps[s].indexOf(n) >= 0; });
      return { label: "K=" + st.k + (st.kept ? " (kept)" : ""), method: "restyle", args: ["visible", vis] };
    });
    done.push(Plotly.newPlot("sweep", sw, {
      margin: { l: 40, r: 10, t: 10, b: 70 }, xaxis: { zeroline: false }, yaxis: { zeroline: false, scaleanchor: "x" },
      sliders: [{ active: visible0, steps: sliderSteps, currentvalue: { prefix: "" }, pad: { t: 30 } }] },
      { responsive: true, displayModeBar: false }));
  }
  // report.html#c1.0 opens with that record's explanation shown
  var want = decodeURIComponent(location.hash.slice(1));
  if (recById[want]) showWhy([want]);
  Promise.all(done).then(function () { document.body.setAttribute("data-kbs-ready", "1"); });
}
})();
</script>
</body>
</html>
"""
_TEMPLATE = _TEMPLATE.replace("@@ERROR_HOOK@@", ERROR_HOOK).replace("@@INFLATE_JS@@", INFLATE_JS)

