"""The map view of `kbs map --report` (kbs.report.mapview): a generated drive mapped through the real
command, the page's grid, objects and trajectory checked against the map's own files, and a click on
an object in headless Chromium showing its frames and the explanation of its cluster in each frame
(checked against `kbs run` on that frame's scan)."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from test_report_html import CHROMIUM, _chromium, _data, _outside_plotly, _page_errors, needs_chromium


@pytest.fixture(scope="module")
def mapped(tmp_path_factory) -> Path:
    """A 5-frame generated drive mapped with `kbs map --report` (the real command)."""
    root = tmp_path_factory.mktemp("mapview")
    assert main(["-q", "synth", "outdoor", "--frames", "5", "--seed", "0", "--out", str(root / "drive")]) == 0
    assert main(["-q", "map", "--rules", "outdoor", str(root / "drive" / "scans"), "--poses",
                 str(root / "drive" / "poses.txt"), "--out", str(root / "map"), "--report", "-j", "1"]) == 0
    return root


@pytest.mark.slow  # a drive mapped through kbs map: pytest --runslow (CI) runs it
def test_kbs_map_report_holds_the_grid_every_object_and_the_trajectory(mapped):
    page_path = mapped / "map" / "map.html"
    doc = json.loads((mapped / "map" / "map.json").read_text())
    assert doc["files"]["report"] == "map.html"
    page = page_path.read_text(encoding="utf-8")
    assert "http://" not in _outside_plotly(page) and "https://" not in _outside_plotly(page)  # nothing fetched
    D = _data(page)
    # the grid: the class band of map.npy (north-up rows) is the page's (rows south to north)
    g = doc["grid"]
    bands = np.load(mapped / "map" / "map.npy")
    cls_npy = bands[g["bands"].index("class")]
    import base64

    G = D["grid"]
    cls_page = np.frombuffer(base64.b64decode(G["cls"]), dtype=np.uint8).reshape(G["ny"], G["nx"])
    assert G["block"] == 1 and (G["nx"], G["ny"]) == (g["shape"]["cols"], g["shape"]["rows"])
    np.testing.assert_array_equal(cls_page, np.flipud(cls_npy).astype(np.uint8))
    assert G["counts"] == g["counts"] and G["counts"]["obstacle"] > 0
    assert (G["x0"], G["y0"]) == pytest.approx((g["bounds"][0], g["bounds"][1]))
    # every object, with its frames and clusters
    assert doc["objects"], "no object tracked"
    assert [o["id"] for o in D["objects"]] == [o["id"] for o in doc["objects"]]
    for o, oj in zip(D["objects"], doc["objects"]):
        assert o["frames"] == oj["frames"] and o["clusters"] == oj["clusters"]
        assert o["centroid"] == pytest.approx(oj["centroid"], abs=1e-3)
        for f, c in o["clusters"]:  # each of its clusters is explained
            e = D["why"][str(f)][str(c)]
            assert e["ids"] and len(e["why"]) == len(e["ids"]) and e["label"] != "ground"
    # the trajectory: the sensor positions of map.json's frames
    P = np.array([f["pose"] for f in doc["frames"]])
    np.testing.assert_allclose(D["trajectory"]["x"], P[:, 0, 3], atol=1e-4)
    np.testing.assert_allclose(D["trajectory"]["y"], P[:, 1, 3], atol=1e-4)
    assert D["trajectory"]["names"] == [f["name"] for f in doc["frames"]]


def test_a_large_grid_is_drawn_in_blocks_and_the_page_says_so():
    from kbs.report.mapview import _blocks

    cls = np.zeros((7, 5), dtype=np.uint8)
    cls[0, 0], cls[6, 4], cls[3, 2] = 2, 1, 1
    out, f = _blocks(cls, 6)
    assert f == 3 and out.shape == (3, 2)
    np.testing.assert_array_equal(out, [[2, 0], [1, 0], [0, 1]])  # a block is an obstacle when any cell is
    same, f1 = _blocks(cls, 35)
    assert f1 == 1 and same is cls


@pytest.mark.slow  # a drive mapped through kbs map: pytest --runslow (CI) runs it
def test_kbs_map_report_without_plotly_stops_before_any_frame(mapped, tmp_path):
    code = ("import sys; sys.modules['plotly'] = None; from kbs.cli.main import main; sys.exit(main())")
    out = tmp_path / "m"
    r = subprocess.run([sys.executable, "-c", code, "map", "--rules", "outdoor", str(mapped / "drive" / "scans"),
                        "--poses", str(mapped / "drive" / "poses.txt"), "--out", str(out), "--report"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert "kbs[report]" in r.stderr and "frame 1/" not in r.stdout + r.stderr and not out.exists()


@pytest.mark.slow  # a drive mapped through kbs map: pytest --runslow (CI) runs it
def test_map_files_are_written_through_the_atomic_writer(mapped, monkeypatch, tmp_path):
    """Every file of the map goes through kbs.io.atomic.replacing (temporary name, then rename)."""
    import kbs.io.atomic as atomic
    from kbs.maps import map_drive
    from kbs.maps.files import write_map
    from kbs.synth.drive import outdoor_drive
    from kbs import Segmenter

    seen: list[str] = []
    real = atomic.replacing

    def recording(*targets):
        seen.extend(Path(t).name for t in targets)
        return real(*targets)

    monkeypatch.setattr(atomic, "replacing", recording)
    d = outdoor_drive(1, n_frames=2, resolution=(60, 100))
    with Segmenter("outdoor", jobs=1) as seg:
        m = map_drive(seg, [f.xyz for f in d.frames], d.poses, explain=True)
    doc = write_map(m, tmp_path / "m", report=True)
    written = {"map.npy", "cloud.ply", "map.json", "map.html"} | {Path(p).name for p in doc["files"].values()}
    written |= {Path(o["mesh"]).name for o in doc["objects"] if o["mesh"]}
    assert written <= set(seen), written - set(seen)
    assert not [p for p in (tmp_path / "m").rglob("*") if ".kbs-tmp-" in p.name]


# -- in a real browser -----------------------------------------------------------------------------

def _clicked(page: Path, tmp: Path, script: str) -> str:
    """The DOM after ``script`` ran once the page was drawn (a copy of the page with it added)."""
    copy = tmp / "clicked.html"
    copy.write_text(page.read_text(encoding="utf-8").replace("</body>", f"""<script>
var t = setInterval(function () {{
  if (document.body.getAttribute("data-kbs-ready") !== "1") return;
  clearInterval(t);
  {script}
}}, 50);
</script>
</body>"""), encoding="utf-8")
    return _chromium(copy, tmp, "--dump-dom").stdout


def _unescape(s: str) -> str:
    return s.replace("&lt;", "<").replace("&gt;", ">").replace("&quot;", '"').replace("&amp;", "&")


@pytest.mark.slow  # a browser: pytest --runslow (CI) runs it
@needs_chromium
def test_the_map_view_renders_and_a_click_on_an_object_shows_its_frames_and_explanations(mapped, tmp_path):
    page = mapped / "map" / "map.html"
    ready, errors = _page_errors(page, tmp_path)
    assert errors == "" and ready
    doc = json.loads((mapped / "map" / "map.json").read_text())
    o = max(doc["objects"], key=lambda x: len(x["frames"]))  # the object seen in the most frames
    k = doc["objects"].index(o)
    dom = _clicked(page, tmp_path, f"""var gd = document.getElementById("map"), n = -1;
  gd.data.forEach(function (tr, i) {{ if (tr.name === "objects") n = i; }});
  gd.emit("plotly_click", {{points: [{{curveNumber: n, pointNumber: {k}, customdata: gd.data[n].customdata[{k}]}}]}});""")
    assert re.search(r'<div id="kbs-errors"[^>]*></div>', dom) and 'data-kbs-ready="1"' in dom
    # every object id is listed, the clicked one selected
    for oj in doc["objects"]:
        assert re.search(rf'<div id="object-{oj["id"]}"[^>]*>.*?object {oj["id"]}: frames ', dom)
    assert re.search(rf'<div id="object-{o["id"]}" class="sel"', dom)
    head = re.search(r'<div id="object-head">(.*?)</div>', dom, re.S).group(1)
    assert head.startswith(f"object {o['id']}: seen in {len(o['frames'])} frame")
    frames = _unescape(re.search(r'<div id="object-frames"[^>]*>(.*?)</div>', dom, re.S).group(1)).splitlines()
    assert [ln.split(":")[0] for ln in frames] == [f"frame {f} ({doc['frames'][f]['name']})" for f, _ in o["clusters"]]
    why = _unescape(re.search(r'<div id="why">(.*?)</div>', dom, re.S).group(1))
    # each frame's explanation, checked against `kbs run` on that frame's scan (the same rule base, the same points)
    f, c = o["clusters"][-1]
    scan = mapped / "drive" / "scans" / doc["frames"][f]["name"]
    run_dir = tmp_path / "run"
    assert main(["-q", "run", "--rules", "outdoor", str(scan), "--out", str(run_dir), "-j", "1"]) == 0
    res = json.loads((run_dir / f"{scan.stem}.json").read_text())
    from kbs.knowledge.explain import Explanation

    expl = Explanation.from_dict(res["explanation"])
    cluster = res["clusters"][c]
    assert f"frame {f} ({scan.name}): cluster {c} ({cluster['label']}), {cluster['n_points']:,} points, from record" in why
    for rid in cluster["ids"]:
        assert expl.why(rid) in why
    for fi, ci in o["clusters"]:
        assert f"frame {fi} ({doc['frames'][fi]['name']}): cluster {ci} (" in why


@pytest.mark.slow  # a browser: pytest --runslow (CI) runs it
@needs_chromium
def test_the_map_view_opens_on_the_object_named_in_its_address(mapped, tmp_path):
    doc = json.loads((mapped / "map" / "map.json").read_text())
    last = doc["objects"][-1]["id"]
    r = subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                        "--virtual-time-budget=5000", f"--user-data-dir={tmp_path / 'p'}", "--dump-dom",
                        (mapped / "map" / "map.html").resolve().as_uri() + f"#object-{last}"],
                       capture_output=True, text=True, timeout=180)
    assert re.search(rf'<div id="object-{last}" class="sel"', r.stdout)
    assert f"object {last}: seen in" in r.stdout



@pytest.mark.slow  # a drive mapped through kbs map: pytest --runslow (CI) runs it
def test_the_map_view_and_map_png_draw_the_grid_in_the_one_set_of_grid_colours(mapped):
    """The grid's class colours (unknown, ground, obstacle) are kbs.report.colors.GRID_HEX in the
    page's colour scale and in the pixels of map.png."""
    import re

    from kbs.report.colors import GRID_HEX

    page = (mapped / "map" / "map.html").read_text(encoding="utf-8")
    scale = re.search(r"colorscale: (\[\[0, .*?\]\]),", page, re.S)
    assert scale is not None
    stops = json.loads(scale.group(1))
    assert [c for _, c in stops] == [GRID_HEX[0], GRID_HEX[0], GRID_HEX[1], GRID_HEX[1], GRID_HEX[2], GRID_HEX[2]]
    png = mapped / "map" / "map.png"
    if not png.exists():
        pytest.skip("no map.png (matplotlib is not installed)")
    import matplotlib.image

    rgb = (matplotlib.image.imread(str(png))[..., :3] * 255).round().astype(int).reshape(-1, 3)
    seen = {f"#{r:02x}{g:02x}{b:02x}" for r, g, b in np.unique(rgb, axis=0)}
    assert {GRID_HEX[0], GRID_HEX[1]} <= seen  # unknown and ground cells (obstacles are shaded by height)
