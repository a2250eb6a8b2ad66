"""Degenerate clusters — every point on a line, or at one position — have no best approximating
plane: no normal, no ground angle, no flatness. They get an explicit outcome (the value is
undefined, its check fails, the explanation says why), are never taken for the ground plane, and
the mesh writer skips them and zero-area triangles. Through the real command, then the library."""
from __future__ import annotations

import json
import math
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

import kbs.inference.geometry as geometry
from kbs.inference import cluster_geometry
from kbs.io import write_ply
from kbs.knowledge import Cluster, Ground, Interpreter, Measurement, PredicateError, PredicateRegistry, Scene
from kbs.knowledge import load_rule_base, predicate
from kbs.report.meshes import ground_mesh
from scenes import ground_and_rocks, outdoor_one_release
from test_cli import kbs

LINE_NOTE = "degenerate: its points lie on a line, no plane: normal/ground angle undefined"

#: a rule base that labels every cluster ground (a user's, with no ground-angle check)
ALL_GROUND = """\
kbs_rules: 1
name: allground
units: m
strategy: divisive
checks:
  tiny: {predicate: point_count, max: 15}
rules:
  - {name: noise, if: tiny, then: reject}
labels:
  - {name: ground}
"""


def _no_nan(text: str) -> dict:
    """The result JSON, refusing NaN/Infinity (not JSON; the HTML report refuses them too)."""
    def refuse(name):
        raise AssertionError(f"{name} in the result JSON")
    return json.loads(text, parse_constant=refuse)


def _line(n: int = 2000, dtype=np.float64) -> np.ndarray:
    t = np.linspace(0.0, 10.0, n)
    return np.column_stack([2 + 0.6 * t, 1 + 0.8 * t, 0.3 * t - 1.5]).astype(dtype)


def _triangle_heights(ply: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's height over its longest edge, and that edge."""
    d = PlyData.read(str(ply))
    V = np.column_stack([d["vertex"]["x"], d["vertex"]["y"], d["vertex"]["z"]])
    F = np.stack(d["face"]["vertex_indices"])
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e = np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)]).max(0)
    return np.linalg.norm(np.cross(b - a, c - a), axis=1) / e, e


# --- through kbs run ---------------------------------------------------------------------------------


CLOUDS = {
    "a straight line": (_line(), "its points lie on a line"),
    "a straight line in float32": (_line(dtype=np.float32), "its points lie on a line"),
    "identical points": (np.tile([[3.0, 4.0, -1.5]], (500, 1)), "its points are all at one position"),
    "two distinct points": (np.repeat([[3.0, 4.0, -1.5], [3.5, 4.0, -1.5]], 300, axis=0), "its points lie on a line"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CLOUDS))
def test_a_cloud_with_no_plane_is_not_ground_and_says_why(tmp_path, name):
    X, what = CLOUDS[name]
    scan = tmp_path / "degenerate.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "out"), "--meshes")
    assert r.returncode == 0, r.stderr
    assert f"points: ground 0, obstacle {len(X):,}, noise 0" in r.stdout
    assert f"skipped cluster 0: degenerate: {what}: no hull" in r.stdout
    assert ("passes 'planar' or has a robust plane holding >= 50% of its points within 0.1 m (1 degenerate: no plane): "
            "the fallback normal [0.0, 0.0, 1.0] is used") in r.stderr
    doc = _no_nan((tmp_path / "out" / "degenerate.json").read_text())
    assert doc["explanation"]["ground"]["source"] == "fallback"  # not the plane of a line
    (rec,) = [c for c in doc["explanation"]["clusters"] if c["id"] == "c0"]
    assert rec["label"] == "obstacle"
    assert f"degenerate: {what}, no plane: normal/ground angle undefined" in rec["notes"]
    assert rec["descriptors"]["normal"] is None
    (level,) = [c for c in rec["checks"] if c["check"] == "level"]
    assert level["value"] is None and level["passed"] is False
    assert level["note"] == f"degenerate: {what}, no plane"
    e = kbs("explain", str(tmp_path / "out" / "degenerate.json"), "--cluster", "c0")
    assert e.returncode == 0
    assert f"level   no   ground_angle = undefined  [outdoor.yaml:42]  (degenerate: {what}, no plane)" in e.stdout
    assert f"note: degenerate: {what}, no plane: normal/ground angle undefined" in e.stdout
    e = kbs("explain", str(tmp_path / "out" / "degenerate.json"))
    assert (f"accepted as obstacle, not ground: level does not hold (ground_angle undefined (degenerate: {what}, "
            f"no plane))") in e.stdout


@pytest.mark.slow
def test_meshes_write_no_surface_for_ground_points_on_a_line(tmp_path):
    rules = tmp_path / "allground.yaml"
    rules.write_text(ALL_GROUND)
    scan = tmp_path / "line.ply"
    write_ply(scan, _line(dtype=np.float32))  # float32 rounding: the points are not exactly collinear
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "out"), "--meshes")
    assert r.returncode == 0, r.stderr
    assert "points: ground 2,000, noise 0" in r.stdout
    assert "ground: not written: degenerate ground points: they lie on a line: no surface" in r.stdout
    assert not (tmp_path / "out" / "line-meshes" / "ground.ply").exists()


@pytest.mark.slow
def test_the_ground_mesh_has_no_zero_area_triangle(tmp_path):
    """Two parallel rails of points, 5 cm apart, stored in float32: the triangles along each rail
    are slivers of float32 rounding."""
    rules = tmp_path / "allground.yaml"
    rules.write_text(ALL_GROUND)
    t = np.linspace(0, 3, 1000)
    rail = np.column_stack([10 + t, 20 + 0.37 * t, 0.01 * t])
    scan = tmp_path / "rails.ply"
    write_ply(scan, np.vstack([rail, rail + [-0.37 * 0.05, 0.05, 0.0]]).astype(np.float32))
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "out"), "--meshes")
    assert r.returncode == 0, r.stderr
    assert "ground: ground.ply (" in r.stdout
    height, edge = _triangle_heights(tmp_path / "out" / "rails-meshes" / "ground.ply")
    assert height.size > 1000
    assert (height > geometry.RANK_TOLERANCE * edge).all(), int((height <= geometry.RANK_TOLERANCE * edge).sum())


def _scene_with(line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    X, _ = ground_and_rocks()
    return np.vstack([X, line]), np.r_[np.zeros(len(X), bool), np.ones(len(line), bool)]


def _cable() -> np.ndarray:
    """A straight cable 1 m above the ground (the rocks scene's ground is at z = -1.5)."""
    t = np.linspace(0, 6, 300)
    return np.column_stack([-4 + t, -5 + 0.5 * t, np.full(300, -0.5)])


def _pole() -> np.ndarray:
    """An upright pole of points, 3 m high, standing on the ground."""
    return np.column_stack([np.full(300, -2.0), np.full(300, -3.0), np.linspace(0.0, 3.0, 300) - 1.5])


@pytest.mark.slow
@pytest.mark.parametrize("make_line", [_cable, _pole], ids=["cable", "pole"])
def test_a_line_in_a_scene_is_explained_and_the_other_labels_do_not_move(tmp_path, monkeypatch, make_line):
    line = make_line()
    X, on_line = _scene_with(line)
    scan = tmp_path / "scene.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "out"), "--meshes")
    assert r.returncode == 0, r.stderr
    v = PlyData.read(str(tmp_path / "out" / "scene.ply"))["vertex"]
    label, cluster = np.asarray(v["scalar_label"]), np.asarray(v["scalar_cluster"])
    doc = _no_nan((tmp_path / "out" / "scene.json").read_text())
    ground = doc["label_names"].index("ground")
    # the line's points above its foot are not ground (the cable was labelled ground, level at 0 deg)
    above = on_line & (X[:, 2] > -1.4)
    assert (label[above] != ground).all()
    # the output cluster of most of its points holds the line alone; its record says why it has no ground angle
    index = np.bincount(cluster[on_line & (cluster >= 0)]).argmax()
    (out,) = [c for c in doc["clusters"] if c["index"] == index]
    records = {c["id"]: c for c in doc["explanation"]["clusters"]}
    rec = records[out["ids"][0]]
    assert set(np.flatnonzero(cluster == index)) <= set(np.flatnonzero(on_line))
    assert LINE_NOTE in rec["notes"] and rec["descriptors"]["normal"] is None
    (level,) = [c for c in rec["checks"] if c["check"] == "level"]
    assert level["value"] is None and not level["passed"]
    assert f"skipped cluster {index}: degenerate: its points lie on a line: no hull" in r.stdout
    # every other point is labelled as without the degenerate-cluster outcome (tolerances off)
    monkeypatch.setattr(geometry, "RANK_TOLERANCE", -1.0)
    monkeypatch.setattr(geometry, "COINCIDENT_TOLERANCE", -1.0)
    # ... and without outdoor.yaml's 'raised' relabel rule and its second ground_release (on rough
    # ground, session 42), which now also take a cable 1 m above the ground for an obstacle whatever
    # its plane: the made-up plane alone is what is shown here
    text = outdoor_one_release().text
    rules = tmp_path / "outdoor.yaml"
    rules.write_text(re.sub(r"\n      - name: raised\n(.*\n)*?        if: raised\n", "\n", text))
    rb = load_rule_base(str(rules))
    assert [r.name for r in rb.relabel] == ["low_level"]
    assert [s.rough for s in rb.post if s.key == "ground_release"] == [None]
    with Interpreter(rb) as it:
        before = it.run(X)
    assert not any("degenerate" in n for rec in before.explanation.records.values() for n in rec.notes)
    np.testing.assert_array_equal(label[~on_line], before.label[~on_line])
    if make_line is _cable:  # the made-up plane: a cable taken for level ground
        assert (before.label[on_line] == ground).mean() > 0.9


# --- the library -------------------------------------------------------------------------------------


@pytest.mark.parametrize("X, rank", [
    (_line(), 1),
    (_line(dtype=np.float32).astype(np.float64), 1),
    (_line() + [5e5, 5.4e6, 0.0], 1),  # absolute (UTM-like) coordinates
    (np.repeat([[1.0, 2.0, 3.0], [1.0, 2.5, 3.0]], 4, axis=0), 1),
    (np.zeros((7, 3)), 0),
    (np.tile([[5e5, 5.4e6, 120.0]], (9, 1)), 0),
    (np.tile(np.float32([[3.1, 4.7, -1.3]]), (9, 1)).astype(np.float64), 0),
    (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), 2),
    (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), 3),
])
def test_rank_of_the_covariance(X, rank):
    geo = cluster_geometry(X)
    assert geo.rank == rank
    assert geo.degenerate == (rank < 2)
    assert (geo.degeneracy is None) == (rank >= 2)


def test_a_thin_but_real_cluster_is_not_degenerate():
    """A strip 1,000 times longer than wide (the thinnest real clusters are 300 times wider)."""
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(0, 10, 500), rng.uniform(0, 0.01, 500), np.zeros(500)]) + [40.0, -20.0, -1.7]
    geo = cluster_geometry(X)
    assert 1e-4 < math.sqrt(geo.eigenvalues[1] / geo.eigenvalues[2]) < 1e-2
    assert geo.rank == 2 and not geo.degenerate


def test_geometry_arrays_are_read_only():
    geo = cluster_geometry(_line())
    for a in (geo.center, geo.covariance, geo.eigenvalues, geo.eigenvectors):
        assert not a.flags.writeable


def _measure(name: str, X: np.ndarray, registry: PredicateRegistry | None = None) -> Measurement:
    reg = registry or PredicateRegistry.default(entry_points_too=False)
    scene = Scene(np.zeros(3), Ground(np.array([0.0, 0, 1]), np.zeros(3), "fixed"), "m")
    return reg.get(name).measure(Cluster("c0", np.asarray(X, float), np.ones(len(X))), scene, {})


@pytest.mark.parametrize("X", [_line(), _line(dtype=np.float32), np.tile([[3.0, 4.0, -1.5]], (50, 1))],
                         ids=["line", "float32 line", "one position"])
@pytest.mark.parametrize("name", ["ground_angle", "flatness"])
def test_predicates_that_need_a_plane_are_undefined_on_a_degenerate_cluster(X, name):
    m = _measure(name, X)
    assert not m.defined and math.isnan(m.value) and m.undefined.startswith("degenerate: ")


@pytest.mark.parametrize("name, value", [("thickness", 0.0), ("connexity", 1.0), ("point_count", 2000.0)])
def test_what_a_line_does_have_is_still_measured(name, value):
    m = _measure(name, _line())
    assert m.defined and m.value == pytest.approx(value, abs=1e-6)


def test_connexity_by_alpha_opening_is_undefined_on_a_line_and_by_graph_counts_its_pieces():
    reg = PredicateRegistry.default(entry_points_too=False)
    scene = Scene(np.zeros(3), None, "m")
    line = Cluster("c0", _line(), np.ones(2000))
    m = reg.get("connexity").measure(line, scene, {"method": "alpha_opening"})
    assert not m.defined and m.undefined == "degenerate: its points lie on a line, no plane for an alpha-shape"
    gap = np.vstack([_line()[:900], _line()[1100:]])
    assert reg.get("connexity").measure(Cluster("c1", gap, np.ones(len(gap))), scene, {}).value == 2.0


def test_a_plugin_can_declare_it_needs_a_plane_or_say_a_value_is_undefined(tmp_path):
    @predicate(unit="deg", needs_plane=True)
    def tilt(cluster, scene) -> float:
        """Angle of the plane's normal to z."""
        return math.degrees(math.acos(abs(float(cluster.geometry.normal[2]))))

    @predicate(unit="ratio")
    def sparse(cluster, scene) -> Measurement:
        """Undefined below 10 points."""
        if cluster.n_points < 10:
            return Measurement(math.nan, undefined="fewer than 10 points")
        return Measurement(1.0)

    @predicate(unit="ratio")
    def careless(cluster, scene) -> float:
        """Returns NaN without saying why."""
        return math.nan

    reg = PredicateRegistry([tilt, sparse, careless])
    assert reg.get("tilt").needs_plane and not _measure("tilt", _line(), reg).defined
    assert _measure("tilt", [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], reg).value == pytest.approx(0.0)
    assert _measure("sparse", _line(5), reg).undefined == "fewer than 10 points"
    with pytest.raises(PredicateError, match=r"returned nan for cluster c0, not a number \(when there is none, "
                                             r"return Measurement\(nan, undefined='why'\)\)"):
        _measure("careless", _line(), reg)


def test_ground_mesh_refuses_points_on_a_line():
    with pytest.raises(ValueError, match="degenerate ground points: they lie on a line: no surface"):
        ground_mesh(_line(dtype=np.float32).astype(np.float64))


@pytest.mark.slow
def test_predicates_lists_which_need_a_plane():
    r = kbs("predicates")
    assert r.returncode == 0
    for name in ("ground_angle", "flatness"):
        block = r.stdout.split(f"\n{name}  [", 1)[1].split("\n\n", 1)[0]
        assert "undefined on a degenerate cluster" in block.splitlines()[0], block
    block = r.stdout.split("\nthickness  [", 1)[1]
    assert "degenerate" not in block.splitlines()[0]


def test_an_undefined_value_fails_its_check_and_not_check_holds(tmp_path):
    rb = load_rule_base_text(tmp_path, textwrap.dedent("""\
        kbs_rules: 1
        name: t
        units: m
        strategy: divisive
        scene:
          ground: {normal: [0, 0, 1]}
        checks:
          level: {predicate: ground_angle, max: 90}
          steep: {predicate: ground_angle, min: 0}
        rules: []
        labels:
          - {name: level, if: level}
          - {name: steep, if: steep}
          - {name: not_level, if: not level}
          - {name: other}
        """))
    with Interpreter(rb) as it:
        seg = it.run(_line())
    assert seg.label_names[seg.label[0]] == "not_level"  # neither 'value <= 90' nor 'value >= 0' holds
    rec = seg.explanation.records["c0"]
    assert [(c.check, c.value, c.passed) for c in rec.checks] == [("level", None, False), ("steep", None, False)]


def load_rule_base_text(tmp_path: Path, text: str):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    return load_rule_base(str(path))
