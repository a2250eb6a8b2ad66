"""Issue 12: airborne scans with low outliers (multipath returns, a few metres below the terrain),
a condition of several ISPRS samples the shared ones do not show (samp41, samp71 in the filter
test). A filter that takes the lowest points for ground pulls its surface down under them, and
the ground around them then stands "raised" above it. Through the real ``kbs run``, on the
shared ISPRS sample 21 (validation part) with 50 points copied 3-15 m below themselves."""
from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial import cKDTree

import sys
from pathlib import Path

from kbs.evaluation import ground_metrics
from kbs.io import read_cloud, write_ply
from kbs.knowledge import Segmenter
from kbs.knowledge.predicates import Cluster, Scene, point_spacing
from test_cli import kbs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_outliers import low_outliers  # noqa: E402


@pytest.mark.slow
def test_low_outliers_are_not_ground_and_do_not_pull_the_ground_down(tmp_path, shared_data):
    pc = read_cloud(shared_data / "isprs" / "samp21-utm.pcd")
    truth = np.loadtxt(shared_data / "isprs" / "samp21-utm.labels.txt")[pc.index].astype(int) == 0
    X = pc.xyz
    rng = np.random.default_rng(0)
    n_out = 50
    pick = rng.choice(len(X), n_out, replace=False)
    below = X[pick] - np.column_stack([np.zeros((n_out, 2)), rng.uniform(3.0, 15.0, n_out)])
    scans = {"clean": (X, truth),
             "outliers": (np.vstack([X, below]), np.concatenate([truth, np.zeros(n_out, bool)]))}
    err, ground = {}, {}
    for name, (P, t) in scans.items():
        write_ply(tmp_path / f"{name}.ply", P)
        r = kbs("run", "--rules", "airborne", str(tmp_path / f"{name}.ply"), "--out", str(tmp_path / name), "-j", "1")
        assert r.returncode == 0, r.stderr
        v = PlyData.read(str(tmp_path / name / f"{name}.ply"))["vertex"]
        assert np.array_equal(np.column_stack([v["x"], v["y"], v["z"]]), P)  # the points in their order
        ground[name] = np.asarray(v["scalar_label"]) == 0  # label 0: ground (-1: noise)
        err[name] = 100 * ground_metrics(ground[name], t.astype(int), ground_values=(1,)).total_error
    # no outlier below the terrain is ground. A point copied down from a tall object can land at
    # the terrain's own height, among the ground (3 of the 50 here: one of them, from a tree 5 m up,
    # 0.8 m above the lowest ground within 5 m, lies in a patch of 93 ground points): it is no low
    # outlier, and ground is a right answer for it (session 22: `low_terraces` gives that patch back)
    G = X[truth]
    near = cKDTree(G[:, :2]).query_ball_point(below[:, :2], 5.0)
    under = below[:, 2] < np.array([G[i, 2].min() if i else np.inf for i in near]) - 1.0
    assert under.sum() == 47
    assert not ground["outliers"][-n_out:][under].any()
    # the ground of the scan itself moves by no more than the fits' own noise (about 1 point of
    # total error from any small change of the input: docs/BENCHMARKS.md, session 19)
    assert err["outliers"] <= err["clean"] + 1.0, err
    assert err["clean"] < 5.0, err  # samp21 with the airborne rules: 2.76 % (CSF 2.17 %)


@pytest.mark.slow
def test_scattered_low_outliers_are_not_given_to_the_ground(shared_data):
    """benchmarks/bench_outliers.py's draw (seed 0: 50 copies landing at least 0.5 m below every
    bare-earth point among the 16 nearest in plan) on ISPRS samp31 (validation part). With the
    airborne rules of session 39, the outliers' clusters (points 9-13 m apart, gathered by the
    partition and kept whole by `limits.min_points`) were given to the ground by `terrain` (`low`
    has no lower bound) in the relabel step of the roof rules, whose later passes then took the
    terrain around them, 5-13 m "above the ground left", for roofs: 52.52 % total error, 30 of the
    50 outliers ground (clean: 2.73 %). Now `terrain` leaves scattered clusters alone and runs in a
    relabel step of its own, after the roofs are settled: 4.11 %, 8 outliers ground (a cluster of
    9 ground points and 8 outliers, 3.65 m apart in the median: `terrain` gives it back)."""
    pc = read_cloud(shared_data / "isprs" / "samp31-utm.pcd")
    truth = np.loadtxt(shared_data / "isprs" / "samp31-utm.labels.txt")[pc.index].astype(int) == 0
    low = low_outliers(pc.xyz, truth, 50, np.random.default_rng(0))
    seg = Segmenter("airborne", jobs=1)
    err, n_ground = {}, {}
    for name, P, t in [("clean", pc.xyz, truth),
                       ("outliers", np.vstack([pc.xyz, low]), np.concatenate([truth, np.zeros(50, bool)]))]:
        r = seg.segment(P)
        g = r.label == r.label_names.index("ground")
        err[name] = 100 * ground_metrics(g, t.astype(int), ground_values=(1,)).total_error
        n_ground[name] = int(g[len(pc.xyz):].sum())
    assert err["clean"] < 4.0, err  # 2.55 % (2.73 % before)
    assert n_ground["outliers"] <= 10, n_ground  # 8 of 50 (30 before)
    assert err["outliers"] <= err["clean"] + 2.5, err  # 4.11 % (52.52 % before)


def test_point_spacing_tells_stray_points_from_a_surface():
    rng = np.random.default_rng(3)
    scene = Scene(np.zeros(3), None, "m")
    # a patch of terrain sampled at about a point per square metre
    g = np.mgrid[0:6, 0:5].reshape(2, -1).T.astype(float)
    patch = np.column_stack([g + rng.uniform(-0.2, 0.2, g.shape), rng.normal(0, 0.1, len(g))])
    # 15 low outliers scattered over 100 m x 100 m
    stray = np.column_stack([rng.uniform(0, 100, (15, 2)), rng.uniform(-12, -4, 15)])
    d_patch = point_spacing.measure(Cluster("p", patch, np.ones(len(patch))), scene, {}).value
    d_stray = point_spacing.measure(Cluster("s", stray, np.ones(15)), scene, {}).value
    assert 0.5 < d_patch < 1.5
    assert d_stray > 8.0
    from scipy.spatial import cKDTree

    ref = cKDTree(stray).query(stray, k=2)[0][:, 1]
    assert d_stray == pytest.approx(float(np.median(ref)), rel=1e-12)
    assert point_spacing.measure(Cluster("s", stray, np.ones(15)), scene, {"stat": "max"}).value == pytest.approx(ref.max(), rel=1e-12)
    one = point_spacing.measure(Cluster("o", stray[:1], np.ones(1)), scene, {})
    assert not one.defined and "one point" in one.undefined
