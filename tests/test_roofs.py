"""Issue 12, item 4: the roofs of large buildings taken for ground in airborne scans, on generated
urban blocks (benchmarks/roof_scenes.py), through ``kbs run --rules airborne``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from plyfile import PlyData

from kbs.io import write_ply
from scenes import airborne_without
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


def _total_error(tmp_path, seed: int, rules: str = "airborne") -> tuple[float, np.ndarray, np.ndarray, dict]:
    X, labels, _ = roofs_scene(seed)
    path = tmp_path / f"roofs{seed}.ply"
    write_ply(path, X)
    out = tmp_path / Path(rules).stem
    r = kbs("run", "--rules", rules, str(path), "--out", str(out))
    assert r.returncode == 0, r.stderr
    ground = np.asarray(PlyData.read(str(out / f"roofs{seed}.ply"))["vertex"]["scalar_label"]) == 0
    doc = json.loads((out / f"roofs{seed}.json").read_text())
    return 100.0 * float((ground != (labels == 0)).mean()), ground, labels, doc


def _without_inner_roofs(tmp_path) -> str:
    """rules/airborne.yaml without the rule 'inner_roofs' (and its check): the rule base before
    session 24."""
    return airborne_without(tmp_path, ("inner_roofs",), ("well_raised",))


@pytest.mark.slow
def test_airborne_rules_take_every_roof_of_a_large_block_for_an_object(tmp_path):
    """Generated block, seed 0 (tuning part): buildings up to 37 m tall, 54 m x 116 m roofs of
    many patches. The roof patches inside a large roof stand at the height of the roof patches
    around them, so neither 'raised' nor 'above_terrain' takes them, and 'inner_roofs' finds none
    standing 5 m above the ground left once the outer ones are out: they hold each other up.
    'large_roofs' (session 37) takes every patch of a continuous surface whose edges drop 5 m or
    more to the surfaces beside it. (Before session 37 the walls given to the ground by 'terrain'
    were the ground 'inner_roofs' measured the inner patches against: 1.15 %.)"""
    te, ground, labels, doc = _total_error(tmp_path, 0)
    assert te < 0.5, te  # 0.14 measured
    large = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "large_roofs"]
    assert large and all(c["label"] == "object" for c in large)
    cluster = np.asarray(PlyData.read(str(tmp_path / "airborne" / "roofs0.ply"))["vertex"]["scalar_cluster"])
    taken = np.isin(cluster, [c["output_index"] for c in large])
    assert taken.sum() > 20000 and (labels[taken] == 1).mean() > 0.99, ((labels[taken] == 1).mean(), taken.sum())
    # without 'large_roofs' (and the condition session 38 put on 'terraces'), the roof of the 37 m
    # building stays ground: its outer patches are taken by 'roofs', but given back by 'terraces'
    # against the inner ones, which only roof patches surround ('inner_roofs' finds none standing
    # 5 m above the ground left)
    import yaml

    path = Path(airborne_without(tmp_path, ("large_roofs", "low_roofs"), ("edge_raised", "edge_raised_left")))
    doc = yaml.safe_load(path.read_text())
    for step in doc["post"]:
        for rule in step.get("relabel", []):
            if rule["name"] == "terraces":
                assert rule["if"][2] == {"any": ["not drops", "not enclosed"]}, rule["if"]
                rule["if"] = rule["if"][:2]
    path = tmp_path / "airborne-before-session-37.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    without, ground_without, _, _ = _total_error(tmp_path, 0, str(path))
    assert without > 10.0, without  # 26.8 measured
    assert ground_without[taken].mean() > 0.25, ground_without[taken].mean()
    # without 'large_roofs' alone, 'terraces' no longer gives the outer patches back (their surface
    # drops to streets that enclose it): most of the roof is an object, the ridge patches not
    (tmp_path / "alone").mkdir()
    alone, _, _, _ = _total_error(tmp_path / "alone", 0, airborne_without(tmp_path, ("large_roofs", "low_roofs"),
                                                                          ("edge_raised", "edge_raised_left")))
    assert 0.5 < alone < without, (alone, without)  # 4.12 measured
    r = kbs("explain", str(tmp_path / "airborne" / "roofs0.json"))
    assert (f"ground -> object if edge_raised and (not drops or not vast or not open_surface): {len(large)} "
            "relabelled") in r.stdout, r.stdout


@pytest.mark.slow
def test_terraces_do_not_give_back_a_low_roof_beside_a_taller_one(tmp_path):
    """Generated block, seed 705 (drawn after session 37, looked at in session 38): `roofs` takes
    the roof of a low building beside a taller one, but `terraces` gave it back: judged against
    the ground left, it meets the taller roof's patches still there ('joins') and lies on the
    terrain they allow. Its continuous surface drops 2.5 m or more at a quarter of its edges, to
    streets that enclose three quarters of it or more (`drops`, `enclosed`): a roof, kept. Without
    that condition, the block scores as before (8.70 %)."""
    te, ground, labels, doc = _total_error(tmp_path, 705)
    assert te < 2.0, te  # 1.03 measured
    text = (Path(__file__).resolve().parents[1] / "rules" / "airborne.yaml").read_text()
    cond = ", {any: [not drops, not enclosed]}]"
    start = text.index("      - name: terraces")
    at = text.index(cond, start)
    before = tmp_path / "terraces-before.yaml"
    before.write_text(text[:at] + "]" + text[at + len(cond):])
    te_before, ground_before, _, _ = _total_error(tmp_path, 705, str(before))
    assert te_before > 6.0, te_before  # 8.70 measured
    assert (ground_before & (labels == 1)).sum() > (ground & (labels == 1)).sum() + 3000


@pytest.mark.slow
def test_airborne_rules_do_not_give_a_wall_to_the_ground(tmp_path):
    """Generated block, seed 7 (tuning part): the walls get a few points each, and pieces of them
    are planar clusters; 'terrain' gave such a piece to the ground when it was 'low' (the 90th
    percentile of its heights above the local surface at most 0.5 m: far *below* it, near a
    building whose roof still counted), and the later passes of the roof rules then judged the roofs
    against it. Two things keep walls out now: a near-vertical plane spreading a storey or more along
    its second axis ('wall' and 'storey', session 37) is not earth, and 'terrain' runs in a relabel
    step of its own once the roofs are out of the surface (session 40). 0.18 % total error and no
    building point given by 'terrain' measured; with 'terrain' as before both (`if: low`, in the
    roofs' step before 'terraces'), 0.92 % and 871 building points (11.4 % before session 37, without
    'large_roofs' either)."""
    te, ground, labels, doc = _total_error(tmp_path, 7)
    assert te < 1.0, te
    # the rule file with 'terrain' as before: walls become ground, and the building's roof with them
    doc_before = yaml.safe_load((ROOT / "rules" / "airborne.yaml").read_text())
    steps = [step for step in doc_before["post"] if "relabel" in step]
    assert [r["name"] for r in steps[1]["relabel"]] == ["terrain", "specks"]
    terrain = dict(steps[1]["relabel"].pop(0), **{"if": "low"})  # 'specks' (session 41) stays in its step
    names = [r["name"] for r in steps[0]["relabel"]]
    steps[0]["relabel"].insert(names.index("terraces"), terrain)
    path = tmp_path / "airborne-terrain-before.yaml"
    path.write_text(yaml.safe_dump(doc_before, sort_keys=False))
    before, _, _, doc_b = _total_error(tmp_path, 7, str(path))
    assert before > te + 0.5, (before, te)

    def walls_given(out: str, result: dict) -> int:
        """Building points in the clusters 'terrain' gave to the ground."""
        given = [c["output_index"] for c in result["explanation"]["clusters"]
                 if c["relabel"] and c["relabel"]["rule"] == "terrain"]
        cluster = np.asarray(PlyData.read(str(tmp_path / out / "roofs7.ply"))["vertex"]["scalar_cluster"])
        return int((np.isin(cluster, given) & (labels == 1)).sum())

    assert walls_given("airborne-terrain-before", doc_b) > 5 * max(walls_given("airborne", doc), 10)


@pytest.mark.slow
def test_airborne_rules_take_the_large_roof_of_a_real_urban_block(shared_data, tmp_path):
    """PDAL's sample_c.las, an urban block mostly built over (its provider's classes: 1,368 ground,
    12,525 building points): the largest roof patch (8,601 points) has only other roof patches
    within reach, all labelled ground, so 'roofs' leaves it ground (59.9 % total error without
    'inner_roofs'). Judged again once the roof patches beside the ground strip are out, it
    stands 27 m above the ground left and is taken in pass 2."""
    import laspy

    scan = shared_data / "las" / "sample_c.las"
    truth = np.asarray(laspy.read(scan).classification) == 2

    def error(rules: str) -> tuple[float, np.ndarray, Path]:
        out = tmp_path / Path(rules).stem
        r = kbs("run", "--rules", rules, str(scan), "--out", str(out))
        assert r.returncode == 0, r.stderr
        ground = np.asarray(laspy.read(out / "sample_c.las").classification) == 2
        return 100.0 * float((ground != truth).mean()), ground, out

    te, ground, out = error("airborne")
    assert te < 1.0 and ground[truth].mean() > 0.99, te
    before, *_ = error(_without_inner_roofs(tmp_path))
    assert before > 50.0, before
    r = kbs("explain", str(out / "sample_c.json"))
    assert "ground -> object if well_raised and (not drops or not vast or not open_surface): 1 relabelled (in pass 2)" \
        in r.stdout, r.stdout
