"""Issue 12, item 4: the roofs of large buildings taken for ground in airborne scans, on generated
urban blocks (benchmarks/roof_scenes.py), through ``kbs run --rules airborne``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.io import write_ply
from test_cli import kbs

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from roof_scenes import ORIGIN, roofs_scene  # noqa: E402


def test_roof_scenes_are_seeded_and_labelled():
    """The same seed gives the same scene; the labels are what was drawn: the buildings' points
    stand at least 5 m above the terrain (roofs) or on their walls, the bare earth lies on the
    terrain (a grade of at most 2 %), and the tile is mostly built over."""
    X, labels, drawn = roofs_scene(7)
    X2, labels2, _ = roofs_scene(7)
    assert np.array_equal(X, X2) and np.array_equal(labels, labels2)
    assert not np.array_equal(roofs_scene(8)[0][:100], X[:100])
    P = X - ORIGIN
    assert 1.0 <= drawn["density"] <= 4.0
    assert abs(len(X) - drawn["density"] * 200 * 200) < 0.1 * len(X)
    assert set(np.unique(labels)) <= {0, 1, 2}
    assert 0.5 < (labels == 1).mean() < 0.95
    assert np.abs(P[labels == 0, 2]).max() < 0.02 * 200 * np.sqrt(2) + 0.5
    for x0, x1, y0, y1, h, kind in drawn["buildings"]:
        assert 5.0 <= h <= 30.0 and kind in ("flat", "gabled")
        inside = (P[:, 0] > x0 + 1) & (P[:, 0] < x1 - 1) & (P[:, 1] > y0 + 1) & (P[:, 1] < y1 - 1) & (labels == 0)
        # bare earth inside a footprint only in a courtyard
        assert all(any(c[0] <= p[0] <= c[1] and c[2] <= p[1] <= c[3] for c in drawn["courts"]) for p in P[inside][:50])


def _total_error(tmp_path, seed: int) -> tuple[float, np.ndarray, np.ndarray, dict]:
    X, labels, _ = roofs_scene(seed)
    path = tmp_path / f"roofs{seed}.ply"
    write_ply(path, X)
    r = kbs("run", "--rules", "airborne", str(path), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    ground = np.asarray(PlyData.read(str(tmp_path / "o" / f"roofs{seed}.ply"))["vertex"]["scalar_label"]) == 0
    doc = json.loads((tmp_path / "o" / f"roofs{seed}.json").read_text())
    return 100.0 * float((ground != (labels == 0)).mean()), ground, labels, doc


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 12: the inner patches of a large roof, judged against the roof patches "
                   "around them (all labelled ground), stay ground: 5.1 % total error on seed 0 (6.1 % before session 23; docs/BENCHMARKS.md, "
                   "'Session 10: large roofs')")
def test_airborne_rules_take_every_roof_of_a_large_block_for_an_object(tmp_path):
    """Generated block, seed 0 (tuning part): buildings up to 37 m tall, 54 m x 116 m roofs of
    many patches. The roof patches inside a large roof stand at the height of the roof patches
    around them, so neither 'raised' nor 'above_terrain' takes them. A rule base that judged them
    against the surface of the lowest patches (not their neighbours) would pass this."""
    te, ground, labels, _ = _total_error(tmp_path, 0)
    assert te < 5.0, te
