"""The seed paper's figures in `kbs render` (issue 13): the K-partition series with eigen-boxes
(figure 2) and a cluster's CAh view: its projection, alpha-shape and alpha-opening (figures 5-7)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from test_cli import EXAMPLE, ROOT, kbs

pytest.importorskip("matplotlib")

POLYHEDRAL = ROOT / "examples" / "data" / "polyhedral.ply"


def _png(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    assert path.is_file() and 10_000 < path.stat().st_size < 2_000_000, path
    img = imread(str(path))[..., :3]
    assert img.shape[0] >= 300 and img.shape[1] >= 600
    assert img.std() > 0.02, f"{path.name} looks blank"
    return img


def _colours(img: np.ndarray) -> int:
    return len(np.unique((img * 15).round().reshape(-1, 3), axis=0))


def _reddish(img: np.ndarray) -> int:
    """Pixels of the dashed red of the boxes of clusters a rule wanted split."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 0.93) & (g < 0.08) & (b < 0.08)).sum())


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("paper-figures")
    done = {}
    for rules, scan in (("planar_global", POLYHEDRAL), ("outdoor", EXAMPLE)):
        d = out / rules
        r = kbs("run", "--rules", rules, str(scan), "--out", str(d))
        assert r.returncode == 0, r.stderr
        done[rules] = d / f"{scan.stem}.json"
    return done


@pytest.mark.slow
def test_the_series_of_a_global_run_draws_each_visited_k_with_its_eigen_boxes(runs, tmp_path):
    from kbs.report import figures

    result = runs["planar_global"]
    sweep = json.loads(result.read_text())["explanation"]["sweep"]
    panels = figures.panels_from_sweep(sweep)
    assert [p.k for p in panels] == [s["k"] for s in sweep] == list(range(2, 11))
    assert [int(p.failing.sum()) > 0 for p in panels] == [True] * 8 + [False]
    assert panels[0].title.endswith("APD's first local maximum") and panels[-1].title.startswith("K = 10 (kept)")
    fewer = figures.panels_from_sweep(sweep, max_panels=4)  # a long sweep: the first, the last, and between
    assert [p.k for p in fewer] == [2, 5, 7, 10]
    out = tmp_path / "g.png"
    r = kbs("render", str(result), "--kind", "series", "--out", str(out), "--max-points", "8000")
    assert r.returncode == 0, r.stderr
    img = _png(out)
    assert _colours(img) >= 8
    assert _reddish(img) > 200, "no box of a failing cluster drawn"


@pytest.mark.slow
def test_the_series_of_a_divisive_run_is_the_initial_sweep_with_eigen_boxes(runs, tmp_path):
    from kbs.report import figures

    X = np.random.default_rng(0).normal(0, 1, (3000, 3)) * [3.0, 1.0, 0.1]
    X[:1500] += [10, 0, 0]
    panels, res = figures.panels_from_ufp_onc(X, ks=(1, 2))
    assert [p.k for p in panels] == [1, 2] and panels[1].centers.shape == (2, 3)
    # the boxes are the partition's own (floored) covariances, axes as columns
    cov = panels[1].eigenvectors[0] @ np.diag(panels[1].eigenvalues[0]) @ panels[1].eigenvectors[0].T
    np.testing.assert_allclose(cov, res.partition(2).covariances[0], atol=1e-10)
    out = tmp_path / "d.png"
    r = kbs("render", str(runs["outdoor"]), "--kind", "series", "--out", str(out), "--max-points", "6000")
    assert r.returncode == 0, r.stderr
    assert _colours(_png(out)) >= 8
    assert _reddish(_png(out)) < 50  # no rule judged those partitions: no red boxes


@pytest.mark.slow
def test_the_cah_view_of_a_cluster_split_by_cah_shows_its_components(runs, tmp_path):
    result = runs["outdoor"]
    records = json.loads(result.read_text())["explanation"]["clusters"]
    cah = [r for r in records if r["action"] == "split_components"]
    assert cah, "the bundled outdoor scan has a cluster split in components by CAh"
    rid = cah[0]["id"]
    r = kbs("render", str(result), "--kind", "cah", "--cluster", rid, "--max-points", "8000")
    assert r.returncode == 0, r.stderr
    png = result.with_name(f"outdoor-cah-{rid}.png")
    assert _colours(_png(png)) >= 6
    # an output cluster's number works too, and --kind all adds the CAh view when --cluster is given
    r = kbs("render", str(result), "--kind", "all", "--cluster", "0", "--out", str(tmp_path / "f.png"))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in tmp_path.glob("f-*.png")) == ["f-cah-0.png", "f-clusters.png", "f-map.png",
                                                               "f-series.png"]


def test_the_cah_figure_separates_two_discs_joined_by_a_thin_bridge():
    """Figures 5-7 on a known shape: two discs joined by a bridge narrower than the opening's disc;
    the alpha-shape is one piece, the opening two components."""
    from kbs.report import figures

    g = np.mgrid[-3:3:0.02, -1:1:0.02].reshape(2, -1).T
    discs = (np.hypot(g[:, 0] + 1.5, g[:, 1]) < 0.8) | (np.hypot(g[:, 0] - 1.5, g[:, 1]) < 0.8)
    bridge = (np.abs(g[:, 0]) < 1.0) & (np.abs(g[:, 1]) < 0.03)
    P = g[discs | bridge]
    X = np.column_stack([P, np.zeros(len(P))])
    fig = figures.cah_figure(X, np.array([0, 0, 1.0]), X.mean(axis=0), plane="the ground plane")
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[1].endswith(": 1 piece"), titles[1]
    assert "2 components, 2 significant" in titles[2], titles[2]
    fig = figures.cah_figure(X, np.array([0, 0, 1.0]), X.mean(axis=0),
                             plane="the ground plane", opening_factor=0.0)
    assert "1 component, 1 significant" in fig.axes[2].get_title()  # no opening: the bridge holds


@pytest.mark.slow
def test_render_cah_refuses_a_missing_or_unknown_cluster(runs):
    result = runs["outdoor"]
    r = kbs("render", str(result), "--kind", "cah")
    assert r.returncode == 2 and "--cluster ID" in r.stderr and "Traceback" not in r.stderr
    r = kbs("render", str(result), "--kind", "cah", "--cluster", "c1.9.9")
    assert r.returncode == 2 and "no cluster 'c1.9.9'" in r.stderr and "Traceback" not in r.stderr
    r = kbs("render", str(result), "--kind", "cah", "--cluster", "999")
    assert r.returncode == 2 and "output cluster 0 .." in r.stderr
