"""The nearest point without scipy's k-d tree (:mod:`kbs.geometry.nearest`): the compiled tree gives
scipy's distances bit for bit and its answers wherever the order of equal distances cannot change
them; rows it cannot settle go to scipy's tree; with the kernels off, scipy answers everything."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kbs.geometry import nearest as module
from kbs.geometry.nearest import NearestIndex, nearest, nearest_label, nearest_other_distances
from kbs.inference import _flags

ROOT = Path(__file__).resolve().parents[1]
SCAN = ROOT.parent / "shared" / "data" / "semantickitti" / "000001.points.npy"


def _clouds(rng, D):
    """Scattered points, points on a coarse lattice (many equal distances), repeated rows."""
    T = rng.normal(size=(3000, D)) * [30.0, 20.0, 1.0][:D]
    yield T, T[rng.choice(3000, 800)] + rng.normal(0, 0.3, (800, D))
    L = np.round(T, 0)
    yield L, np.round(L[rng.choice(3000, 800)] + rng.normal(0, 1.0, (800, D)), 0) + 0.5
    yield np.r_[T[:500], T[:500]], T[rng.choice(500, 300)]


@pytest.mark.parametrize("jit", [True, False])
@pytest.mark.parametrize("D", [2, 3])
def test_nearest_gives_the_k_d_tree_s_distances_and_labels(monkeypatch, D, jit):
    monkeypatch.setattr(_flags, "JIT", jit)
    rng = np.random.default_rng(D)
    for T, Q in _clouds(rng, D):
        labels = rng.integers(0, 4, len(T))
        d_ref, i_ref = cKDTree(T).query(Q, k=1)
        d, i = nearest(Q, T, labels)
        assert np.array_equal(d, d_ref)
        assert np.array_equal(labels[i], labels[i_ref])
        assert np.array_equal(nearest_label(Q, T, labels), labels[i_ref])
        d2, i2 = nearest(Q, T)  # no labels: a row at the nearest distance
        assert np.array_equal(d2, d_ref) and np.array_equal(((T[i2] - Q) ** 2).sum(axis=1), ((T[i_ref] - Q) ** 2).sum(axis=1))


def test_equal_distances_of_two_labels_go_to_scipy_s_tree(monkeypatch):
    """A query midway between two points of different labels: the compiled tree cannot know which
    the k-d tree gives, so scipy's tree answers that row (and only rows like it)."""
    monkeypatch.setattr(_flags, "JIT", True)
    T = np.array([[0.0, 0.0], [2.0, 0.0], [10.0, 10.0]])
    labels = np.array([0, 1, 2])
    asked = []
    real = module._tree
    monkeypatch.setattr(module, "_tree", lambda T: asked.append(len(T)) or real(T))
    index = NearestIndex(T, labels)
    assert index.label(np.array([[9.0, 9.5]])).tolist() == [2] and asked == []
    Q = np.array([[1.0, 0.0], [9.0, 9.5]])
    assert np.array_equal(index.label(Q), labels[cKDTree(T).query(Q)[1]]) and asked == [3]
    same = NearestIndex(T, np.array([0, 0, 2]))  # the same label either way: no tree
    asked.clear()
    assert same.label(Q).tolist() == [0, 2] and asked == []


@pytest.mark.parametrize("D", [2, 3])
def test_nearest_other_distances_are_the_k_d_tree_s(D):
    rng = np.random.default_rng(10 + D)
    for T, _ in _clouds(rng, D):
        assert np.array_equal(nearest_other_distances(T), cKDTree(T).query(T, k=2)[0][:, 1])
    # a thin cloud (a line of points): the grid's cells adapt, or the tree answers
    line = np.c_[np.linspace(0, 1000, 2000), np.zeros(2000), rng.normal(0, 0.01, 2000)][:, :D]
    assert np.array_equal(nearest_other_distances(line), cKDTree(line).query(line, k=2)[0][:, 1])


def test_nearest_index_refuses_an_empty_set():
    with pytest.raises(ValueError, match="m > 0"):
        NearestIndex(np.zeros((0, 3)))


@pytest.mark.slow
@pytest.mark.skipif(not SCAN.exists(), reason="../shared/data/semantickitti/000001.points.npy is absent")
def test_a_vehicle_frame_is_segmented_without_importing_scipy_spatial():
    """On SemanticKITTI 000001 the outdoor rules need no scipy k-d tree, so a fresh process does not
    pay for importing scipy's spatial and sparse packages (0.25-0.33 s)."""
    code = ("import sys, numpy as np, kbs; "
            f"X = np.load({str(SCAN)!r})[:, :3].astype(float); "
            "r = kbs.Segmenter('outdoor', jobs=1).segment(X); "
            "print(sorted(m for m in sys.modules if m.startswith(('scipy.spatial', 'scipy.sparse')))); "
            "print(int((r.label == r.label_names.index('ground')).sum()))")
    env = dict(os.environ, KBS_JIT="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    imported, ground = out.stdout.split("\n")[:2]
    assert imported == "[]", imported
    assert int(ground) > 40000
