"""Which way is up in the figures and the HTML report (issue 14, item 7), the report's size and
boxes, and the one palette of the PLY, the figures and the report, through the real commands.

A camera's frame (stereo, RGB-D) has its optical axis along z and up along -y: drawn in x-y as a
lidar scan is, the scene lay on its side and the obstacle map was a sliver. The scene here is the
bundled outdoor example turned into that convention, segmented with the outdoor rule base whose
ground fallback says so (``[0, -1, 0]``, as ``examples/rules/tabletop.yaml`` does for a Kinect).
"""
from __future__ import annotations

import base64
import gzip
import json
import re
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from test_cli import EXAMPLE, kbs

ROOT = Path(__file__).resolve().parents[1]
#: z up (x forward, y left) -> a camera's frame: x right (-y), y down (-z), z forward (x); det +1
TO_CAMERA = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _data(page: Path) -> dict:
    m = re.search(r'<script id="kbs-data" type="application/gzip">(.*?)</script>', page.read_text(encoding="utf-8"), re.S)
    assert m, "no embedded data"
    return json.loads(gzip.decompress(base64.b64decode(m.group(1))))


@pytest.fixture(scope="module")
def camera_run(tmp_path_factory) -> Path:
    """``kbs run --report`` on the example in a camera's frame; returns the output folder."""
    from kbs.io import read_cloud, write_ply

    tmp = tmp_path_factory.mktemp("camera")
    write_ply(tmp / "cam.ply", read_cloud(EXAMPLE).xyz @ TO_CAMERA.T, {})
    rules = (ROOT / "rules" / "outdoor.yaml").read_text(encoding="utf-8")
    assert "fallback: [0, 0, 1]" in rules
    (tmp / "camera.yaml").write_text(rules.replace("fallback: [0, 0, 1]", "fallback: [0, -1, 0]"), encoding="utf-8")
    r = kbs("run", "--rules", str(tmp / "camera.yaml"), str(tmp / "cam.ply"), "--out", str(tmp / "o"), "--report")
    assert r.returncode == 0, r.stderr
    assert "normal [0.0" in r.stdout and "-1.000" in r.stdout  # the run found the ground with up -y
    return tmp / "o"


def _map_fill(png: Path) -> float:
    """Share of the image's pixels that are map cells (the ground green or the obstacle red)."""
    from matplotlib.image import imread

    img = (imread(str(png))[..., :3] * 255).round().astype(int)
    ground = np.all(np.abs(img - [0xB8, 0xD8, 0xA8]) <= 3, axis=-1)
    obstacle = np.all(np.abs(img - [0xC0, 0x39, 0x2B]) <= 3, axis=-1)
    return float((ground | obstacle).mean())


@pytest.mark.slow
def test_render_map_of_a_camera_frame_is_the_ground_seen_from_above_not_a_sliver(camera_run, tmp_path):
    r = kbs("render", str(camera_run / "cam.json"), "--kind", "map", "--out", str(tmp_path / "cam.png"))
    assert r.returncode == 0, r.stderr
    assert "view: camera frame, up [0.0" in r.stderr and "map: the plane perpendicular to up" in r.stderr
    # the same scene z up, as a lidar gives it: the map kbs has always drawn
    level = tmp_path / "level"
    assert kbs("run", "--rules", "outdoor", str(EXAMPLE), "--out", str(level)).returncode == 0
    r2 = kbs("render", str(level / "outdoor.json"), "--kind", "map", "--out", str(tmp_path / "level.png"))
    assert r2.returncode == 0 and "view:" not in r2.stderr
    cam, lvl = _map_fill(tmp_path / "cam.png"), _map_fill(tmp_path / "level.png")
    assert lvl > 0.05, lvl
    assert cam > 0.6 * lvl, (cam, lvl)  # drawn in x-y, the camera's map filled 0.01 of the image (0.11 now)


def test_render_clusters_of_a_camera_frame_stand_upright():
    """The 3-D figure turns the points so that up (-y here) is the vertical axis."""
    import matplotlib

    matplotlib.use("Agg")
    from kbs.report import figures
    from kbs.report.view import View

    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-5, 5, 4000), np.full(4000, 1.5), rng.uniform(2, 20, 4000)])  # y down
    pole = np.column_stack([rng.normal(0, 0.05, 500), rng.uniform(-1.0, 1.5, 500), rng.normal(8, 0.05, 500)])
    X = np.vstack([ground, pole])
    cluster = np.r_[np.zeros(4000, int), np.ones(500, int)]
    clusters = [{"index": i, "label": lab, "n_points": int((cluster == i).sum()),
                 "descriptors": {"center": X[cluster == i].mean(axis=0).tolist(),
                                 "eigenvalues": np.linalg.eigvalsh(np.cov(X[cluster == i].T)).tolist(),
                                 "normal": None}} for i, lab in enumerate(("ground", "obstacle"))]
    fig = figures.clusters_figure(X, cluster, clusters, view=View.from_up([0.0, -1.0, 0.0]))
    ax = fig.axes[0]
    assert ax.get_zlabel() == "-y (up)" and ax.get_xlabel() == "x (right)" and ax.get_ylabel() == "z (forward)"
    lo, hi = ax.get_zlim()
    assert lo <= -1.5 and hi >= 1.0  # the vertical axis spans the pole's height, from the ground (y = 1.5) up
    assert clusters[1]["descriptors"]["center"][1] < 1.0  # the caller's descriptors are not turned in place


@pytest.mark.slow
def test_report_of_a_camera_frame_has_up_vertical(camera_run):
    d = _data(camera_run / "cam.html")
    doc = json.loads((camera_run / "cam.json").read_text())
    normal = doc["explanation"]["ground"]["normal"]
    cam = d["view"]["camera"]
    np.testing.assert_allclose([cam["up"][k] for k in "xyz"], normal, atol=1e-6)
    assert cam["up"]["y"] < -0.99 and "eye" in cam and not d["view"]["level"]
    eye = np.array([cam["eye"][k] for k in "xyz"])
    assert eye @ np.array(normal) > 0 and eye[2] < 0  # above the ground, behind the camera (z forward)


@pytest.fixture(scope="module")
def many_run(tmp_path_factory) -> Path:
    """A ground and 40 boxes: 48 output clusters with the outdoor rule base; `kbs run --report`."""
    tmp = tmp_path_factory.mktemp("many")
    rng = np.random.default_rng(0)
    parts = [np.column_stack([rng.uniform(0, 40, 20000), rng.uniform(-20, 20, 20000), rng.normal(-1.5, 0.005, 20000)])]
    for i in range(40):
        c = np.array([4 + (i % 8) * 4.5, -16 + (i // 8) * 8, -1.0])
        s = 0.3 + 0.05 * (i % 5)
        parts.append(rng.uniform(c - [s, s, 0.5], c + [s, s, 0.5 + 0.1 * (i % 7)], (150 + 20 * i, 3)))
    np.savetxt(tmp / "many.xyz", np.vstack(parts), fmt="%.4f")
    r = kbs("run", "--rules", "outdoor", str(tmp / "many.xyz"), "--out", str(tmp / "o"), "--report")
    assert r.returncode == 0, r.stderr
    return tmp / "o"


@pytest.mark.slow
def test_report_colours_are_the_ply_colours_past_cluster_nine(many_run):
    """One palette: the report's colour of each cluster (12 included) is the PLY's red/green/blue."""
    d = _data(many_run / "many.html")
    v = PlyData.read(str(many_run / "many.ply"))["vertex"]
    cl = np.asarray(v["scalar_cluster"])
    rgb = np.column_stack([v["red"], v["green"], v["blue"]])
    n = len(json.loads((many_run / "many.json").read_text())["clusters"])
    assert n > 30
    for k in (0, 9, 10, 12, n - 1):
        r, g, b = rgb[np.flatnonzero(cl == k)[0]]
        assert d["palette"][k] == f"#{r:02x}{g:02x}{b:02x}", k
    if (cl < 0).any():
        r, g, b = rgb[np.flatnonzero(cl < 0)[0]]
        assert d["noise"] == f"#{r:02x}{g:02x}{b:02x}"


@pytest.mark.slow
def test_report_boxes_only_the_largest_clusters_and_states_each_count(many_run):
    d = _data(many_run / "many.html")
    clusters = json.loads((many_run / "many.json").read_text())["clusters"]
    boxed = {c for c in d["boxes"]["cluster"] if c is not None}
    largest = sorted(range(len(clusters)), key=lambda i: (-clusters[i]["n_points"], i))[:30]
    assert len(clusters) > 30 and boxed == set(largest) and d["boxed"] == 30
    assert sum(c is not None for c in d["corners"]) > 30  # every box on demand (a click on a point)
    assert [c["n_points"] for c in d["clusters"]] == [c["n_points"] for c in clusters]  # exact, not the drawn ones
