"""The map view of a drive: one self-contained HTML page (``kbs map ... --report`` writes it as
``DIR/map.html``) that opens offline, as the per-scan report of ``kbs run --report``
(:mod:`kbs.report.html`) does, and is built the same way:

- the obstacle grid seen from above (unknown grey, ground green, obstacle red: the colours of
  ``map.png``), the trajectory (one marker per frame, its name on hover) and every tracked object:
  its footprint (the convex hull of its fused points seen from above) in its colour from the one
  palette (:mod:`kbs.report.colors`, by object id) and its id written on it;
- the list of the objects (a line each: id, frames, points); a click on an object (on the map or in
  the list) draws its footprint in bold, marks the poses of the frames that saw it on the
  trajectory, lists those frames with the cluster it was in each of them, and shows the
  explanation of each of those clusters: why it was split or accepted and labelled so
  (:meth:`kbs.knowledge.explain.Explanation.why` of its records, kept by ``map_drive(...,
  explain=True)``).

plotly.js and the data are embedded gzip-compressed and base64-encoded, with the same error hook
and ``data-kbs-ready="1"`` flag as the per-scan report (the tests open it in headless Chromium).
At most :data:`MAX_CELLS` cells are drawn: a larger grid is drawn in blocks of cells (a block is
an obstacle when any of its cells is, else ground when any is) and the page says so.
``map.html#object-3`` opens with object 3 shown.
"""
from __future__ import annotations

import html
import re
from pathlib import Path
from typing import Any

import numpy as np

from kbs.errors import require
from kbs.report.colors import GRID_HEX, hex_colors
from kbs.report.html import ERROR_HOOK, INFLATE_JS, PAGE_BOOT, PAGE_HEAD, PAGE_TOP, _b64, _gz64, _hull2d, _json, _plotly_gz64

__all__ = ["write_map_report", "map_report_data", "MAX_CELLS"]

#: Grid cells drawn at most (a larger grid is drawn in square blocks of cells; the page says so).
MAX_CELLS = 1_000_000


def _blocks(cls: np.ndarray, max_cells: int) -> tuple[np.ndarray, int]:
    """``cls`` (nx, ny) reduced to at most ``max_cells`` cells by square blocks of ``f`` cells a
    side, each the largest class in it (obstacle 2 > ground 1 > unknown 0); returns it and ``f``."""
    nx, ny = cls.shape
    f = 1
    while (-(-nx // f)) * (-(-ny // f)) > max_cells:
        f += 1
    if f == 1:
        return cls, 1
    px, py = (-nx) % f, (-ny) % f
    padded = np.pad(cls, ((0, px), (0, py)))
    return padded.reshape(padded.shape[0] // f, f, padded.shape[1] // f, f).max(axis=(1, 3)), f


def map_report_data(m: Any, *, max_cells: int = MAX_CELLS) -> dict[str, Any]:
    """What the page draws, as plain data (see the module's doc).

    Parameters
    ----------
    m : kbs.maps.DriveMap
    max_cells : int
        Grid cells drawn at most.
    """
    g = m.grid
    cls, f = _blocks(np.asarray(g.cls, dtype=np.uint8), max_cells)
    x0, y0, _, _ = g.bounds
    nx, ny = cls.shape
    notice = (f"grid {g.shape[0]:,} x {g.shape[1]:,} cells of {g.cell_size:g} m" if f == 1 else
              f"grid {g.shape[0]:,} x {g.shape[1]:,} cells of {g.cell_size:g} m, drawn in blocks of {f} x {f} cells "
              f"({nx:,} x {ny:,}; a block is an obstacle when any of its cells is)")
    n_colours = max((o.id for o in m.objects), default=-1) + 1
    palette = hex_colors(max(n_colours, 1))
    objects = []
    for o in m.objects:
        hull = _hull2d(np.unique(np.round(o.points[:, :2], 3), axis=0))
        c = o.centroid
        objects.append({"id": int(o.id), "frames": [int(i) for i in o.frames],
                        "clusters": [[int(a), int(b)] for a, b in o.clusters], "n_points": int(o.n_points),
                        "centroid": [round(float(v), 4) for v in c],
                        "hull": [hull[:, 0].round(4).tolist(), hull[:, 1].round(4).tolist()],
                        "height": round(float(o.points[:, 2].max() - o.points[:, 2].min()), 3),
                        "mesh": o.mesh_kind, "color": palette[o.id]})
    pos = m.poses.positions
    why: dict[str, dict[str, Any]] = {}
    for r in m.frames:
        if r.explanations:
            why[str(r.index)] = {str(c): e for c, e in sorted(r.explanations.items())}
    return {
        "grid": {"nx": int(nx), "ny": int(ny), "x0": float(x0), "y0": float(y0), "cell": float(g.cell_size * f),
                 "cls": _b64(cls.T, "u1"), "counts": g.counts(), "block": int(f)},
        "notice": notice,
        "trajectory": {"x": pos[:, 0].round(4).tolist(), "y": pos[:, 1].round(4).tolist(),
                       "names": [r.name for r in m.frames]},
        "frames": [{"index": r.index, "name": r.name, "n_points": r.n_points, "clusters": r.clusters,
                    "n_ground": r.n_ground, "n_obstacle": r.n_obstacle} for r in m.frames],
        "objects": objects,
        "why": why,
        "explained": any(r.explanations for r in m.frames),
        "head": {"rule_base": m.rule_base, "rule_file": m.rule_file, "source": m.source,
                 "poses": m.poses.note or m.poses.source, "notes": list(m.notes)},
    }


def write_map_report(m: Any, path: str | Path, *, title: str | None = None, max_cells: int = MAX_CELLS) -> Path:
    """Write the map view of ``m`` (a :class:`kbs.maps.DriveMap`) to ``path`` (one HTML file).

    The explanations shown on a click are those ``map_drive(..., explain=True)`` kept; without
    them the page lists each object's frames and clusters and says that no explanation was kept.

    Raises
    ------
    MissingExtra
        plotly (the ``report`` extra) is not installed.
    """
    get_plotlyjs = require("plotly.offline", "report", "the HTML map view").get_plotlyjs
    data = map_report_data(m, max_cells=max_cells)
    title = title or f"kbs map: {len(m.frames)} frames, {len(m.objects)} objects"
    fill = {"TITLE": html.escape(title), "NOTICE": html.escape(data["notice"]),
            "PLOTLYJS": _plotly_gz64(get_plotlyjs), "DATA": _gz64(_json(data))}
    page = re.sub(r"%%([A-Z]+)%%", lambda mo: fill[mo.group(1)], _TEMPLATE)
    path = Path(path)
    path.write_text(page, encoding="utf-8")
    return path


_TEMPLATE = PAGE_HEAD + r"""  #left { flex: 3 1 0; min-width: 0; }
  #right { flex: 2 1 0; min-width: 300px; display: flex; flex-direction: column; gap: 6px; }
  #map { height: calc(100vh - 80px); min-height: 300px; }
  #objects { flex: 0 1 28%; overflow: auto; font: 12px/1.4 monospace; border: 1px solid #ddd; padding: 4px; }
  #objects div { cursor: pointer; white-space: nowrap; }
  #objects div:hover { background: #eef; }
  #objects div.sel { background: #ffe9a8; }
  #objects span.sw { display: inline-block; width: 10px; height: 10px; margin-right: 5px; }
  #object-head { font-size: 13px; font-weight: bold; }
  #object-frames { flex: 0 1 18%; overflow: auto; font: 12px/1.4 monospace; border: 1px solid #ddd; padding: 4px; }
  #why { flex: 1 1 50%; overflow: auto; font: 12px/1.35 monospace; white-space: pre-wrap; border: 1px solid #ddd; padding: 4px; background: #fafafa; }
""" + PAGE_TOP + r"""  <div id="left"><div id="map"></div></div>
  <div id="right">
    <h2>Objects (click one, here or on the map)</h2>
    <div id="objects"></div>
    <div id="object-head">No object selected.</div>
    <div id="object-frames"></div>
    <h2>Why: the explanation of its cluster in each frame</h2>
    <div id="why">Click an object to see the frames that saw it and why each frame's cluster ended as it did.</div>
  </div>
</main>
""" + PAGE_BOOT + r"""
function start(D) {
  var G = D.grid, cls = new Uint8Array(bytes(G.cls)), z = [];
  for (var j = 0; j < G.ny; j++) {  // rows south to north (the y axis goes up)
    var row = new Array(G.nx);
    for (var i = 0; i < G.nx; i++) row[i] = cls[j * G.nx + i];
    z.push(row);
  }
  var byId = {};
  D.objects.forEach(function (o) { byId[o.id] = o; });
  document.getElementById("meta").textContent = "rule base '" + D.head.rule_base + "' (" + D.head.rule_file + "); " +
    D.frames.length + " frames of " + D.head.source + "; poses: " + D.head.poses + "; cells: obstacle " +
    G.counts.obstacle.toLocaleString("en") + ", ground " + G.counts.ground.toLocaleString("en") + ", unknown " +
    G.counts.unknown.toLocaleString("en") + "; " + D.objects.length + " objects";

  var traces = [{ type: "heatmap", z: z, x0: G.x0 + G.cell / 2, dx: G.cell, y0: G.y0 + G.cell / 2, dy: G.cell,
                  zmin: 0, zmax: 2, showscale: false, zsmooth: false, name: "grid",
                  colorscale: @@GRID_COLOURS@@,
                  hovertemplate: "x %{x:.1f}, y %{y:.1f}<extra></extra>" }];
  D.objects.forEach(function (o) {
    traces.push({ type: "scatter", mode: "lines", x: o.hull[0], y: o.hull[1], fill: "toself", fillcolor: o.color,
                  opacity: 0.75, line: { color: "#222", width: 1 }, hoverinfo: "skip", showlegend: false });
  });
  var objTrace = traces.length;
  traces.push({ type: "scatter", mode: "markers+text", name: "objects", showlegend: false,
                x: D.objects.map(function (o) { return o.centroid[0]; }),
                y: D.objects.map(function (o) { return o.centroid[1]; }),
                text: D.objects.map(function (o) { return String(o.id); }), textposition: "top center",
                textfont: { size: 11, color: "#000" }, customdata: D.objects.map(function (o) { return o.id; }),
                hovertext: D.objects.map(function (o) {
                  return "object " + o.id + ": " + o.frames.length + " frame" + (o.frames.length === 1 ? "" : "s") +
                    ", " + o.n_points.toLocaleString("en") + " points (click: why)"; }),
                hoverinfo: "text",
                marker: { size: 9, color: D.objects.map(function (o) { return o.color; }), line: { color: "#000", width: 1 } } });
  var T = D.trajectory, trajTrace = traces.length;
  traces.push({ type: "scatter", mode: "lines+markers", name: "trajectory", x: T.x, y: T.y,
                text: T.names.map(function (n, k) { return "frame " + k + ": " + n; }), hoverinfo: "text",
                line: { color: "#1565c0", width: 2 }, marker: { size: 5, color: "#1565c0" } });
  var pickTrace = traces.length;
  traces.push({ type: "scatter", mode: "lines", name: "the object clicked", x: [], y: [], hoverinfo: "skip",
                showlegend: false, line: { color: "#000", width: 4 } });
  var seenTrace = traces.length;
  traces.push({ type: "scatter", mode: "markers", name: "poses that saw it", x: [], y: [], hoverinfo: "skip",
                marker: { size: 11, color: "rgba(0,0,0,0)", line: { color: "#ff6f00", width: 3 } } });

  var list = document.getElementById("objects");
  D.objects.forEach(function (o) {
    var el = document.createElement("div"), sw = document.createElement("span");
    el.id = "object-" + o.id;
    sw.className = "sw"; sw.style.background = o.color;
    el.appendChild(sw);
    el.appendChild(document.createTextNode("object " + o.id + ": frames " + o.frames.join(", ") + "; " +
      o.n_points.toLocaleString("en") + " points; " + o.height.toFixed(2) + " m high"));
    el.addEventListener("click", function () { showObject(o.id); });
    list.appendChild(el);
  });
  if (!D.objects.length) list.textContent = "no object tracked";

  var gd = document.getElementById("map");
  function showObject(id) {
    var o = byId[id];
    if (!o) return;
    document.querySelectorAll("#objects div.sel").forEach(function (e) { e.classList.remove("sel"); });
    var el = document.getElementById("object-" + id);
    if (el) { el.classList.add("sel"); el.scrollIntoView({ block: "nearest" }); }
    Plotly.restyle(gd, { x: [o.hull[0]], y: [o.hull[1]] }, [pickTrace]);
    Plotly.restyle(gd, { x: [o.frames.map(function (k) { return T.x[k]; })],
                         y: [o.frames.map(function (k) { return T.y[k]; })] }, [seenTrace]);
    document.getElementById("object-head").textContent = "object " + id + ": seen in " + o.frames.length + " frame" +
      (o.frames.length === 1 ? "" : "s") + ", " + o.n_points.toLocaleString("en") + " points; centre (" +
      o.centroid.map(function (v) { return v.toFixed(2); }).join(", ") + "); mesh: " + o.mesh;
    var lines = [], texts = [];
    o.clusters.forEach(function (fc) {
      var f = D.frames[fc[0]], e = (D.why[String(fc[0])] || {})[String(fc[1])];
      var head = "frame " + fc[0] + " (" + f.name + "): cluster " + fc[1] +
        (e ? (e.label ? " (" + e.label + ")" : " (unlabelled: no label matched)") + ", " +
             e.n_points.toLocaleString("en") + " points" : "");
      lines.push(head);
      if (e) texts.push(head + ", from record" + (e.ids.length > 1 ? "s " : " ") + e.ids.join(", ") + ":\n\n" +
                        e.why.join("\n\n----\n\n"));
      else texts.push(head + ": no explanation kept (map_drive(..., explain=True) keeps them)");
    });
    document.getElementById("object-frames").textContent = lines.join("\n");
    document.getElementById("object-frames").style.whiteSpace = "pre";
    document.getElementById("why").textContent = texts.join("\n\n========\n\n");
  }

  var layout = { margin: { l: 50, r: 10, t: 10, b: 40 }, height: Math.max(300, gd.clientHeight),
                 xaxis: { title: { text: "x (m)" }, zeroline: false, constrain: "domain" },
                 yaxis: { title: { text: "y (m)" }, zeroline: false, scaleanchor: "x" },
                 legend: { x: 0, y: 1, bgcolor: "rgba(255,255,255,0.7)" }, uirevision: "keep" };
  Plotly.newPlot(gd, traces, layout, { responsive: true, displaylogo: false }).then(function () {
    gd.on("plotly_click", function (ev) {
      if (!ev || !ev.points || !ev.points.length) return;
      var p = ev.points[0];
      if (p.curveNumber === objTrace) showObject(p.customdata !== undefined ? p.customdata : D.objects[p.pointNumber].id);
    });
    var want = /^#object-(\d+)$/.exec(location.hash);
    if (want) showObject(Number(want[1]));
    document.body.setAttribute("data-kbs-ready", "1");
  });
}
})();
</script>
</body>
</html>
"""
_TEMPLATE = _TEMPLATE.replace("@@ERROR_HOOK@@", ERROR_HOOK).replace("@@INFLATE_JS@@", INFLATE_JS)
_TEMPLATE = _TEMPLATE.replace("@@GRID_COLOURS@@", '[[0, "{0}"], [0.333, "{0}"], [0.333, "{1}"], [0.667, "{1}"],\n'
                              '                               [0.667, "{2}"], [1, "{2}"]]'.format(*GRID_HEX))
