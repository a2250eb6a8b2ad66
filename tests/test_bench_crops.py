"""benchmarks/bench_crops.py: a scan cut into its four corner crops, each run alone (issue 12: does a
region's result depend on where the scan is cut?), and the known failure kind it found."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_crops import corner_crops  # noqa: E402
from roof_scenes import roofs_scene  # noqa: E402

from kbs.knowledge import Segmenter  # noqa: E402
from scenes import airborne_without  # noqa: E402


def test_corner_crops_are_the_four_corners_of_the_box():
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(10, 110, 5000), rng.uniform(-50, 150, 5000), rng.normal(0, 1, 5000)])
    crops = corner_crops(X, 0.6)
    lo, span = X[:, :2].min(axis=0), X[:, :2].max(axis=0) - X[:, :2].min(axis=0)  # about 100 m x 200 m
    assert [name for name, _ in crops] == ["SW", "NW", "SE", "NE"]
    for name, m in crops:
        P = X[m]
        x0 = lo[0] + (0.0 if name[1] == "W" else 0.4 * span[0])
        y0 = lo[1] + (0.0 if name[0] == "S" else 0.4 * span[1])
        w, d = 0.6 * span
        # within its box (60 % of the width and of the depth), and every point of that box taken
        assert P[:, 0].min() >= x0 - 1e-9 and P[:, 0].max() <= x0 + w + 1e-9
        assert P[:, 1].min() >= y0 - 1e-9 and P[:, 1].max() <= y0 + d + 1e-9
        box = (X[:, 0] >= x0 + 0.1) & (X[:, 0] <= x0 + w - 0.1) & (X[:, 1] >= y0 + 0.1) & (X[:, 1] <= y0 + d - 0.1)
        assert m[box].all()
        assert 0.3 < m.mean() < 0.42  # about 36 % of the points
    # with crops wider than half the box they cover it, and overlap
    assert np.logical_or.reduce([m for _, m in crops]).all()
    assert (np.sum([m for _, m in crops], axis=0) > 1).any()


def test_bench_regions_reads_sample_c_as_a_las_file(shared_data):
    """'sample_c' starts with 'samp' like the ISPRS samples, and was looked for as an ISPRS file."""
    from bench_regions import load

    X, truth, valid = load("sample_c", Segmenter("airborne", jobs=1))
    assert len(X) == len(truth) == len(valid) == 14_408
    assert 0.05 < truth[valid].mean() < 0.2  # mostly buildings (its provider's class 2: 1,368 points)


def _crop_error(seed: int, corner: str, rules: str = "airborne") -> float:
    """Total error % of a generated block's corner crop (60 %) run alone with ``rules``."""
    X, labels, _ = roofs_scene(seed)
    X = X - np.floor(X.min(axis=0))
    mask = dict(corner_crops(X, 0.6))[corner]
    ground = Segmenter(rules, jobs=1).segment(X[mask]).label == 0
    return 100.0 * float((ground != (labels[mask] == 0)).mean())


@pytest.mark.slow
def test_a_low_roof_cut_by_the_scan_between_taller_ones_is_a_roof(tmp_path):
    """Generated block, seed 2 (tuning part), its south-west corner crop: a low building (7.7 m,
    a flat roof) between two taller ones (17.8 and 17.9 m), cut by the scan's edge, the street
    along its front only. Its continuous surface rises to the taller roofs at most of its edges,
    so 'large_roofs' left it to the ground (7.61 % alone, 0.27 % inside the whole block). Judged
    again once the taller roofs are taken, with only the surfaces beside it still ground
    ('low_roofs': 'edge_drop' with 'beside: ground', in passes), it drops to the street: a roof
    (0.09 % measured)."""
    assert _crop_error(2, "SW") < 1.0
    before = airborne_without(tmp_path, ("low_roofs",), ("edge_raised_left",))
    assert _crop_error(2, "SW", before) > 5.0  # 7.61 measured


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known failure kind (issue 12, session 39): a large low roof cut by the "
                   "scan with one wall in view is taken for the terrace above a terrain step (a plateau)")
def test_a_large_low_roof_cut_by_the_scan_with_one_wall_in_view_is_a_roof():
    """Generated block, seed 7 (tuning part), its north-west corner crop (60 % of the tile's width
    and depth): two low buildings (roofs 7.3 and 8.9 m up, 50 m x 65 m and 70 m x 65 m in view) cut
    by the crop on two sides, a street along the third, the fourth against each other. Whole, the
    block scores 0.22 % and these points 0.13 %; the crop alone 52.29 %: each roof is a continuous
    surface of 2,500 m^2 or more that drops at its edges to surfaces that do not enclose it, which
    is what the rules call a plateau (session 38), so no roof rule takes it. The same crop with the
    rules before session 38: 0.23 %. Geometry inside the crop does not tell it from the terrace of a
    cropped terrain step (raising `vast` to 10,000 m^2 brings this crop to 0.23 % and the cropped
    8-12 m steps of bench_steps.py from 1.8 % to 39 %): see docs/BENCHMARKS.md, session 39."""
    assert _crop_error(7, "NW") < 1.0
