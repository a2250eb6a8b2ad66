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

from kbs.evaluation import ground_metrics
from kbs.io import read_cloud, write_ply
from test_cli import kbs


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
