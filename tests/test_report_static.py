"""Coloured result clouds, ``kbs render`` figures and ``--meshes``, through the real command."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.report.colors import NOISE_RGB, colors_for, palette
from kbs.report.meshes import hull_mesh

from test_cli import EXAMPLE, kbs


@pytest.fixture(scope="module")
def outdoor_run(tmp_path_factory) -> Path:
    """``kbs run --rules outdoor --meshes`` on the bundled example; returns the output directory."""
    out = tmp_path_factory.mktemp("run")
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out), "--meshes")
    assert r.returncode == 0, r.stderr
    assert "meshes in" in r.stdout
    return out


def _rgb(v) -> np.ndarray:
    return np.column_stack([v["red"], v["green"], v["blue"]])


def test_palette_of_very_many_clusters_is_fast_distinct_and_never_grey():
    """An airborne tile ends in thousands of clusters: the palette must stay O(n) (the nudging of
    golden-ratio hues alone took minutes past ~5,000) and keep every colour distinct."""
    p = palette(20000)  # the quadratic version did not finish in minutes
    assert len({tuple(int(c) for c in r) for r in p}) == 20000
    assert not ((p[:, 0] == p[:, 1]) & (p[:, 1] == p[:, 2])).any()
    assert np.array_equal(palette(1500), p[:1500])


def test_palette_distinct_deterministic_never_grey():
    p = palette(60)
    assert p.dtype == np.uint8 and p.shape == (60, 3)
    assert len({tuple(c) for c in p}) == 60
    assert NOISE_RGB not in {tuple(int(x) for x in c) for c in p}
    assert np.array_equal(palette(60), p) and np.array_equal(palette(7), p[:7])
    assert tuple(colors_for(np.array([-1]))[0]) == NOISE_RGB


@pytest.mark.slow
def test_run_ply_colours_by_cluster(outdoor_run):
    v = PlyData.read(str(outdoor_run / "outdoor.ply"))["vertex"]
    names = [p.name for p in v.properties]
    assert {"scalar_cluster", "scalar_label", "scalar_membership", "red", "green", "blue"} <= set(names)
    assert all(v[c].dtype == np.uint8 for c in ("red", "green", "blue"))
    rgb, cl = _rgb(v), np.asarray(v["scalar_cluster"])
    seen = {}
    for c in np.unique(cl):
        colours = np.unique(rgb[cl == c], axis=0)
        assert len(colours) == 1, f"cluster {c} has {len(colours)} colours"
        seen[int(c)] = tuple(colours[0])
    assert len(set(seen.values())) == len(seen) >= 2
    assert all(col != NOISE_RGB for c, col in seen.items() if c >= 0)


@pytest.mark.slow
def test_run_colour_by_label_and_noise_grey(tmp_path):
    # a scene with a far, sparse handful of points the outdoor rules reject as noise
    rng = np.random.default_rng(0)
    g = np.column_stack([rng.uniform(0, 10, 3000), rng.uniform(-5, 5, 3000), rng.normal(-1.5, 0.005, 3000)])
    box = rng.uniform([4, -0.5, -1.5], [5, 0.5, -0.5], (600, 3))
    stray = rng.normal([30, 30, 5], 0.05, (6, 3))
    cloud = tmp_path / "scene.xyz"
    np.savetxt(cloud, np.vstack([g, box, stray]))
    r = kbs("run", "--rules", "outdoor", str(cloud), "--out", str(tmp_path / "o"), "--color-by", "label")
    assert r.returncode == 0, r.stderr
    v = PlyData.read(str(tmp_path / "o" / "scene.ply"))["vertex"]
    rgb, lab = _rgb(v), np.asarray(v["scalar_label"])
    for k in np.unique(lab):
        assert len(np.unique(rgb[lab == k], axis=0)) == 1
    assert (lab < 0).any(), "the scene should leave some noise"
    assert (rgb[lab < 0] == NOISE_RGB).all()
    assert not (rgb[lab >= 0] == NOISE_RGB).all(axis=1).any()
    assert len({tuple(rgb[lab == k][0]) for k in np.unique(lab)}) == len(np.unique(lab))


@pytest.mark.slow
def test_render_all_writes_three_nonblank_pngs(outdoor_run, tmp_path):
    from matplotlib.image import imread

    out = tmp_path / "fig.png"
    r = kbs("render", str(outdoor_run / "outdoor.json"), "--out", str(out), "--kind", "all", "--max-points", "8000")
    assert r.returncode == 0, r.stderr
    for kind in ("series", "map", "clusters"):
        png = tmp_path / f"fig-{kind}.png"
        assert png.is_file() and 5_000 < png.stat().st_size < 2_000_000, kind
        img = imread(str(png))
        assert img.shape[0] >= 300 and img.shape[1] >= 300
        assert img[..., :3].std() > 0.02, f"{kind} looks blank"
        # several distinct colours: points coloured by cluster / cell class, not a single ink
        assert len(np.unique((img[..., :3] * 15).round().reshape(-1, 3), axis=0)) >= 4


@pytest.mark.slow
def test_render_missing_files_exit_3(outdoor_run, tmp_path):
    r = kbs("render", str(tmp_path / "nope.json"))
    assert r.returncode == 3 and r.stderr.count("\n") == 1 and "nope.json" in r.stderr
    lone = tmp_path / "lone.json"
    lone.write_text((outdoor_run / "outdoor.json").read_text())
    r = kbs("render", str(lone), "--kind", "map")
    assert r.returncode == 3 and "lone.ply" in r.stderr and "Traceback" not in r.stderr


def test_obstacle_meshes_are_closed_and_contain_their_points(outdoor_run):
    import trimesh

    doc = json.loads((outdoor_run / "outdoor.json").read_text())
    v = PlyData.read(str(outdoor_run / "outdoor.ply"))["vertex"]
    X = np.column_stack([v["x"], v["y"], v["z"]])
    cl = np.asarray(v["scalar_cluster"])
    mdir = outdoor_run / "outdoor-meshes"
    obstacles = [c["index"] for c in doc["clusters"] if c["label"] != "ground"]
    assert obstacles
    for i in obstacles:
        m = trimesh.load(str(mdir / f"obstacle-{i}.ply"), process=False)
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume > 0
        P = X[cl == i]
        # inside or on the hull: behind every face's plane (faces outward, hull convex)
        V, F = np.asarray(m.vertices), np.asarray(m.faces)
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        out_dist = (P @ n.T - np.einsum("ij,ij->i", n, V[F[:, 0]])).max()
        assert out_dist <= 1e-9 * max(1.0, float(np.abs(P).max()))
    g = PlyData.read(str(mdir / "ground.ply"))
    assert g["face"].count > 0 and g["vertex"].count > 3
    assert not (mdir / "obstacle-0.ply").exists()  # cluster 0 is the ground


def test_hull_skips_degenerate_clusters():
    rng = np.random.default_rng(1)
    with pytest.raises(ValueError, match="at least 4"):
        hull_mesh(rng.normal(size=(3, 3)))
    flat = np.column_stack([rng.normal(size=(50, 2)), np.zeros(50)])
    with pytest.raises(ValueError, match="degenerate"):
        hull_mesh(flat)
    V, F = hull_mesh(rng.normal(size=(200, 3)))
    # outward: every face normal points away from the centroid
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    assert (np.einsum("ij,ij->i", n, V[F].mean(axis=1) - V.mean(axis=0)) > 0).all()


@pytest.mark.slow
def test_render_map_of_georeferenced_data_keeps_the_scan_in_view_and_names_the_png(tmp_path):
    """UTM-like coordinates with the sensor left at the origin: the map's axes cover the scan,
    not the origin (the scan was an invisible sliver); `--out fig` writes fig.png and says so; a
    result without a 'ground' label is refused for the map unless --ground-label names one."""
    import matplotlib

    matplotlib.use("Agg")
    from kbs.cli.main import main
    from kbs.io import read_cloud, write_ply
    from kbs.report import figures

    root = Path(__file__).resolve().parents[1]
    X = read_cloud(root / "examples" / "data" / "outdoor.ply").xyz + [600000.0, 5000000.0, 0.0]
    scan = tmp_path / "utm.ply"
    write_ply(scan, X, {})
    out = tmp_path / "o"
    assert main(["-q", "run", "--rules", "outdoor", "--sensor", "0,0,0", str(scan), "--out", str(out)]) in (0, None)
    res = figures.load_result(out / "utm.json")
    fig = figures.obstacle_map_figure(res.X, res.label, res.label_names, sensor=np.zeros(3))
    x0, x1 = fig.axes[0].get_xlim()
    assert x0 > 599000.0 and x1 - x0 < 200.0, (x0, x1)
    assert any("far outside the scan" in t.get_text() for t in fig.axes[0].texts)
    r = subprocess.run([sys.executable, "-c", "import sys; from kbs.cli.main import main; sys.exit(main())",
                        "render", str(out / "utm.json"), "--kind", "map", "--out", str(tmp_path / "fig")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "fig").exists()
    assert f"wrote {tmp_path / 'fig.png'}" in r.stdout
    r = subprocess.run([sys.executable, "-c", "import sys; from kbs.cli.main import main; sys.exit(main())",
                        "render", str(out / "utm.json"), "--kind", "map", "--ground-label", "road"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "no label 'road' in this result (labels: ground, obstacle)" in r.stderr


@pytest.mark.slow
def test_clusters_figure_boxes_the_largest_clusters_only():
    """Thousands of clusters (an airborne tile): boxes and labels for the 30 largest, said in the
    figure; every point is still drawn in its cluster's colour."""
    import matplotlib

    matplotlib.use("Agg")
    from kbs.report import figures

    rng = np.random.default_rng(0)
    n, k = 200_000, 2_000
    cluster = rng.integers(0, k, n)
    X = rng.uniform(0, 100, (n, 3))
    sizes = np.bincount(cluster, minlength=k)
    clusters = [{"index": i, "label": "object", "n_points": int(sizes[i]),
                 "descriptors": {"center": X[cluster == i].mean(axis=0).tolist(), "eigenvalues": [1.0, 0.5, 0.1],
                                 "normal": [0.0, 0.0, 1.0]}} for i in range(k)]
    fig = figures.clusters_figure(X, cluster, clusters, title="tile")
    ax = fig.axes[0]
    assert len(ax.lines) == 30 * 12  # 12 edges a box
    assert sum(t.get_text()[0].isdigit() for t in ax.texts) == 30
    assert any("the 30 largest of 2000 clusters" in t.get_text() for t in ax.texts)
    largest = {c["index"] for c in sorted(clusters, key=lambda c: -c["n_points"])[:30]}
    assert {int(t.get_text().split()[0]) for t in ax.texts if t.get_text()[0].isdigit()} == largest
