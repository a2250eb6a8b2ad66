"""The ground direction found from the data (``scene.ground``): the closest large plane to the
sensor, a candidate of the initial partition that passes the candidate check or whose robust plane
holds most of its points (``scene.ground.plane``); the fallback normal only when the scene has no
such plane, and then the output says why. Through ``kbs run`` on generated scenes and on the real
vehicle scans rotated about a horizontal axis through the sensor, then the robust plane alone."""
from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from kbs.cli.main import main
from kbs.evaluation import ground_metrics
from kbs.io import write_ply
from kbs.knowledge import Interpreter, load_rule_base
from kbs.geometry.groundplane import hypotheses_needed, robust_plane
from test_cli import kbs

ROOT = Path(__file__).resolve().parents[1]
OUTDOOR = (ROOT / "rules" / "outdoor.yaml").read_text(encoding="utf-8")
UP = np.array([0.0, 0.0, 1.0])


def angle(a, b) -> float:
    """Degrees between two plane normals (unsigned)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(min(1.0, abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))))


def rotation_x(deg: float) -> np.ndarray:
    """Rotation about the sensor's x axis (horizontal, through the sensor at the origin)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def run(tmp_path: Path, X: np.ndarray, *extra: str, name: str = "scene") -> tuple[object, dict]:
    scan = tmp_path / f"{name}.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", "outdoor", "-j", "1", str(scan), "--out", str(tmp_path / "out"), *extra)
    assert r.returncode == 0, r.stderr
    return r, json.loads((tmp_path / "out" / f"{name}.json").read_text())


# --- (b) two planes: the near ground, not the farther plane ------------------------------------------


def two_planes(*, cluttered: bool, seed: int = 0, tilt: float = 15.0) -> tuple[np.ndarray, int]:
    """A near ground 1.7 m below the sensor (12 m x 12 m, 2 to 14 m ahead), with small blocks
    standing on it when ``cluttered`` (then it is 12 cm thick: it fails 'planar'), and a larger,
    clean plane farther away (21 to 39 m ahead), tilted ``tilt`` degrees: it passes 'planar'.
    Returns the points and how many of them (the first) are the near ground and its blocks."""
    rng = np.random.default_rng(seed)
    n = 12000
    near = [np.column_stack([rng.uniform(2, 14, n), rng.uniform(-6, 6, n), rng.normal(-1.7, 0.01, n)])]
    if cluttered:
        for cx, cy in rng.uniform([3, -5], [13, 5], (12, 2)):
            near.append(rng.uniform([-0.4, -0.4, 0], [0.4, 0.4, rng.uniform(0.3, 0.6)], (350, 3)) + [cx, cy, -1.7])
    t = np.radians(tilt)
    m = 20000
    u, v = rng.uniform(-9, 9, m), rng.uniform(-9, 9, m)
    far = np.column_stack([30 + u * np.cos(t), v, 1.3 + u * np.sin(t)])
    far += rng.normal(0, 0.01, (m, 1)) * [-np.sin(t), 0, np.cos(t)]
    near_pts = np.vstack(near)
    return np.vstack([near_pts, far]), len(near_pts)


@pytest.mark.slow
@pytest.mark.parametrize("cluttered", [True, False], ids=["near ground cluttered", "near ground clean"])
def test_the_near_ground_is_the_ground_not_the_farther_larger_plane(tmp_path, cluttered):
    """The farther plane is larger and clean (it passes 'planar'); the near ground, cluttered, does
    not pass it, but its robust plane holds 80 % of its points: the closest plane is the near one.
    Before scene.ground.plane, the farther plane was the ground (15 deg off) in the cluttered case."""
    X, n_near = two_planes(cluttered=cluttered)
    r, doc = run(tmp_path, X)
    g = doc["explanation"]["ground"]
    assert angle(g["normal"], UP) < 1.0, g  # the near ground's normal; the farther plane's is 15 deg off
    assert abs(g["point"][2] + 1.7) < 0.05, g
    assert g["normal"][2] > 0  # pointing up, towards the sensor
    chosen = g["cluster"]
    verdicts = {v["cluster"]: v for v in g["candidates"]}
    far = [v for c, v in verdicts.items() if c != chosen and v.get("method")]
    assert far, "the farther plane is a candidate that gives a plane too"
    assert all(abs(v["angle_to_fallback"] - 15.0) < 1.0 and v["distance"] > g["distance_to_sensor"] + 15
               for v in far), verdicts
    assert g["method"] == ("robust plane" if cluttered else "check 'planar'")
    how = "its robust plane (" if cluttered else "it passes 'planar'"
    assert f"  ground: cluster {chosen}, {how}" in r.stdout
    # the ground cluster's points are the near ground's
    records = {c["id"]: c for c in doc["explanation"]["clusters"]}
    assert records[chosen]["descriptors"]["center"][0] < 15


@pytest.mark.slow
def test_the_ground_is_explained(tmp_path):
    X, _ = two_planes(cluttered=True)
    scan = tmp_path / "two.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", "outdoor", "-j", "1", str(scan), "--out", str(tmp_path / "out"), "--report")
    assert r.returncode == 0, r.stderr
    from test_report_html import _data  # the report's data is embedded gzip-compressed

    page = (tmp_path / "out" / "two.html").read_text(encoding="utf-8")
    assert _data(page)["head"]["ground"].startswith("cluster c0, its robust plane (80% of its points")  # its header line
    e = kbs("explain", str(tmp_path / "out" / "two.json"))
    assert e.returncode == 0, e.stderr
    lines = e.stdout.splitlines()
    assert lines[1].startswith("ground: cluster c") and "its robust plane (" in lines[1] and "deg from the fallback normal" in lines[1]
    cands = [ln for ln in lines[2:] if ln.startswith("  candidate ")]
    assert any("on its robust plane" in ln and ln.endswith("a plane: its robust plane") for ln in cands), cands
    assert any(ln.endswith("a plane: it passes 'planar'") for ln in cands), cands


# --- (c) no plane: the fallback, and why -----------------------------------------------------------


@pytest.mark.slow
def test_a_scene_with_no_plane_uses_the_fallback_and_says_why(tmp_path):
    rng = np.random.default_rng(4)
    X = np.vstack([rng.normal(c, 1.5, (6000, 3)) for c in ([8, 0, 0], [0, 9, 1], [-7, -5, 2])])  # three blobs
    r, doc = run(tmp_path, X, name="blobs")
    g = doc["explanation"]["ground"]
    assert g["source"] == "fallback" and g["normal"] == [0.0, 0.0, 1.0]
    assert all(v["inlier_share"] < 0.5 and "why" in v for v in g["candidates"]), g["candidates"]
    assert "  ground: fallback, normal [0.000, 0.000, 1.000]" in r.stdout
    note = [ln for ln in r.stderr.splitlines() if ln.startswith("note: no cluster of the initial partition")]
    assert len(note) == 1, r.stderr
    assert ("passes 'planar' or has a robust plane holding >= 50% of its points within 0.1 m (the share of their "
            "points on their robust planes: c0 ") in note[0]
    assert note[0].endswith(": the fallback normal [0.0, 0.0, 1.0] is used")


@pytest.mark.slow
def test_a_wall_is_not_the_ground_beyond_max_tilt(tmp_path):
    """Only a rough wall (8 cm thick: not 'planar', but its robust plane holds 79 % of its points;
    90 deg from the fallback): beyond plane.max_tilt, the fallback is used, and the note says the
    wall's plane was tilted more."""
    rng = np.random.default_rng(5)
    n = 18000
    wall = np.column_stack([rng.normal(6.0, 0.08, n), rng.uniform(-6, 6, n), rng.uniform(-1.7, 4, n)])
    r, doc = run(tmp_path, wall, name="wall")
    g = doc["explanation"]["ground"]
    assert g["source"] == "fallback", g
    tilted = [v for v in g["candidates"] if "max_tilt 30 deg" in v.get("why", "")]
    assert tilted and all(v["angle_to_fallback"] > 80 for v in tilted), g["candidates"]
    assert "within max_tilt 30 deg of the fallback (the robust plane of " in r.stderr


# --- (a) the real vehicle scans, rotated ----------------------------------------------------------


def _vehicle(shared: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points in the sensor frame, ground truth, labelled) of a shared vehicle scan."""
    if name == "SemanticKITTI 000001":
        X = np.load(shared / "semantickitti" / "000001.points.npy").astype(np.float64)
        lab = np.load(shared / "semantickitti" / "000001.labels.npy").ravel()
        return X, np.isin(lab, [9, 10, 11, 12, 17]), lab != 0
    if name == "GndNet 000000":
        lab = np.load(shared / "gndnet" / "000000.labels.npy")
        X = np.load(shared / "gndnet" / "000000.points.npy")[:, :3].astype(np.float64) - [0, 0, 1.73]
        return X, lab == 0, lab >= 0
    X = np.fromfile(shared / "semantickitti-seq00" / "seq00_000000.bin", np.float32).reshape(-1, 4)[:, :3]
    lab = np.fromfile(shared / "semantickitti-seq00" / "seq00_000000.label", np.uint32) & 0xFFFF
    return X.astype(np.float64), np.isin(lab, [40, 44, 48, 49, 60, 72]), lab != 0


def _true_ground_normal(X: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The normal of the labelled ground within 20 m (principal components): 1.5-2.5 deg from the
    sensor's z on these scans (the sensor is not mounted exactly level)."""
    Q = X[truth & (np.linalg.norm(X[:, :2], axis=1) < 20)]
    w, v = np.linalg.eigh(np.cov((Q - Q.mean(axis=0)).T))
    return v[:, 0] if v[2, 0] > 0 else -v[:, 0]


VEHICLE = ["SemanticKITTI 000001", "GndNet 000000", "seq00 000000"]


@pytest.fixture(scope="module")
def level_f1(shared_data) -> dict[str, float]:
    """The ground F1 of each vehicle scan as it is (not rotated)."""
    out = {}
    rb = load_rule_base("outdoor")
    for name in VEHICLE:
        X, truth, valid = _vehicle(shared_data, name)
        seg = Interpreter(rb).run(X)
        out[name] = ground_metrics((seg.label == 0)[valid], truth[valid].astype(int), ground_values=(1,)).f1
    return out


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
@pytest.mark.parametrize("degrees", [10, 20])
@pytest.mark.parametrize("name", VEHICLE)
def test_a_tilted_vehicle_scan_finds_its_ground(shared_data, level_f1, name, degrees):
    """Rotated about the sensor's x axis: the ground normal found is the rotated true ground normal
    (within 1 deg; 0.1-0.25 measured), and the ground F1 stays within 0.01 of the level scan's
    (measured, level -> 10 deg and 20 deg: SemanticKITTI 0.9489 -> 0.9497 and 0.9504, GndNet 0.9737
    -> 0.9741 and 0.9746, seq00 0.9760 -> 0.9761 and 0.9733). With the fallback [0, 0, 1] (before
    scene.ground.plane) the normal was 8 and 18 deg off and the F1 fell at 20 deg: SemanticKITTI
    0.9484 -> 0.9404, GndNet 0.9732 -> 0.9535, seq00 0.9760 -> 0.9593."""
    X, truth, valid = _vehicle(shared_data, name)
    R = rotation_x(degrees)
    seg = Interpreter(load_rule_base("outdoor")).run(X @ R.T)
    g = seg.explanation.ground
    assert g.source.startswith("cluster ") and g.method == "robust plane", g.note
    assert angle(g.normal, R @ _true_ground_normal(X, truth)) < 1.0
    assert abs(g.angle_to_fallback - degrees) < 3.0
    f1 = ground_metrics((seg.label == 0)[valid], truth[valid].astype(int), ground_values=(1,)).f1
    assert f1 > level_f1[name] - 0.01, (f1, level_f1[name])


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_a_tilted_scan_through_kbs_run(shared_data, tmp_path):
    """SemanticKITTI 000001 pitched 20 deg (about the sensor's y axis), through kbs run: the summary
    and the JSON say which cluster, how it was found, its normal and its angle to the fallback."""
    X, truth, valid = _vehicle(shared_data, "SemanticKITTI 000001")
    a = np.radians(20)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    r, doc = run(tmp_path, X @ R.T, name="kitti20")
    g = doc["explanation"]["ground"]
    assert g["method"] == "robust plane" and g["inlier_share"] >= 0.5 and g["unit"] == "m"
    assert angle(g["normal"], R @ _true_ground_normal(X, truth)) < 1.0
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("  ground: "))
    assert line.startswith(f"  ground: cluster {g['cluster']}, its robust plane (") and line.endswith(
        f"{g['angle_to_fallback']:.1f} deg from the fallback normal")
    assert "fallback normal [0.0, 0.0, 1.0] is used" not in r.stderr


# --- the rule file ----------------------------------------------------------------------------


PLANE = """\
    plane:                     #   or one whose robust plane holds most of its points (the feet of cars,
      inlier_distance: 0.10    #   kerbs and low plants make a real ground cluster thicker than 5 cm):
      min_inlier_share: 0.5    #   m; at least half of its points within 10 cm of its plane,
      max_tilt: 30 """


def test_the_shipped_outdoor_rules_declare_the_robust_plane():
    assert PLANE in OUTDOOR
    spec = load_rule_base("outdoor").ground
    assert (spec.plane.inlier_distance, spec.plane.min_inlier_share, spec.plane.max_tilt) == (0.1, 0.5, 30.0)
    assert spec.candidate == "planar" and spec.normal is None


@pytest.mark.slow
@pytest.mark.parametrize("old, new, at, message", [
    ("inlier_distance: 0.10", "inlier_distance: -0.1", "-0.1", "scene.ground.plane.inlier_distance: -0.1 is less than or "
                                                               "equal to the minimum of 0"),
    ("inlier_distance: 0.10", "inlier_distance: 10 cm", "10 cm", "scene.ground.plane.inlier_distance must be a number"),
    ("min_inlier_share: 0.5", "min_inlier_share: 50", "50", "scene.ground.plane.min_inlier_share: 50 is greater than "
                                                          "the maximum of 1"),
    ("max_tilt: 30", "max_tilt: 120", "120", "scene.ground.plane.max_tilt: 120 is greater than the maximum of 90"),
    ("min_inlier_share: 0.5", "min_share: 0.5", "min_share", "unknown key 'min_share' in scene.ground.plane "
                                                             "(did you mean 'min_inlier_share'?)"),
    ("      inlier_distance: 0.10", "      inlier_distanc: 0.10", "inlier_distanc", "unknown key 'inlier_distanc'"),
])
def test_a_bad_plane_setting_is_refused_at_its_position(tmp_path, old, new, at, message):
    assert old in OUTDOOR
    text = OUTDOOR.replace(old, new, 1)
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    line = text[:text.index(at)].count("\n") + 1
    col = text.index(at) - text.rfind("\n", 0, text.index(at))
    scan = tmp_path / "s.ply"
    write_ply(scan, two_planes(cluttered=False)[0][:2000])
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "out"))
    assert r.returncode == 4 and "Traceback" not in r.stderr, r.stderr
    assert f"t.yaml:{line}:{col}: {message}" in r.stderr, r.stderr


def test_a_plane_with_a_fixed_normal_is_a_warning(tmp_path, capsys):
    text = OUTDOOR.replace("normal: auto ", "normal: [0, 0, 1]", 1)
    rules = tmp_path / "t.yaml"
    rules.write_text(text, encoding="utf-8")
    assert main(["rules", "check", str(rules)]) == 0
    err = capsys.readouterr().err
    line = text[:text.index("    plane:")].count("\n") + 1
    assert f"t.yaml:{line}:5: warning: scene.ground.plane is not used: scene.ground.normal fixes the ground" in err, err


@pytest.mark.slow
def test_the_robust_plane_alone_finds_the_ground_for_ground_angle_checks(tmp_path):
    """A rule base whose ground-angle checks have no candidate check, only scene.ground.plane: it is
    valid (before, it needed 'candidate') and finds the cluttered near ground."""
    rules = tmp_path / "plane_only.yaml"
    rules.write_text(textwrap.dedent("""\
        kbs_rules: 1
        name: plane_only
        units: m
        strategy: divisive
        scene:
          ground:
            plane: {inlier_distance: 0.1, min_inlier_share: 0.5}
        checks:
          level: {predicate: ground_angle, max: 20}
        rules: []
        labels:
          - {name: ground, if: level}
          - {name: other}
        """), encoding="utf-8")
    X, _ = two_planes(cluttered=True)
    scan = tmp_path / "two.ply"
    write_ply(scan, X)
    r = kbs("run", "--rules", str(rules), "-j", "1", str(scan), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    g = json.loads((tmp_path / "out" / "two.json").read_text())["explanation"]["ground"]
    assert g["method"] == "robust plane" and angle(g["normal"], UP) < 1.0


# --- the robust plane ------------------------------------------------------------------------------


def _plane_with_outliers(seed: int = 0, share: float = 0.6):
    rng = np.random.default_rng(seed)
    n = 5000
    k = int(share * n)
    normal = np.array([0.2, -0.3, 0.93])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    on = rng.uniform(-5, 5, (k, 1)) * e1 + rng.uniform(-5, 5, (k, 1)) * e2 + rng.normal(0, 0.01, (k, 1)) * normal
    off = rng.uniform(-5, 5, (n - k, 3)) + 3 * normal  # a cloud above the plane
    return np.vstack([on, off]) + [1.0, 2.0, 3.0], normal, k


def test_the_robust_plane_is_the_generated_one():
    X, normal, k = _plane_with_outliers()
    rp = robust_plane(X, 0.05, 0.5)
    assert angle(rp.normal, normal) < 0.2
    assert abs((rp.point - [1.0, 2.0, 3.0]) @ normal) < 0.01
    truth = np.arange(len(X)) < k
    off_plane_near = np.abs((X[~truth] - [1.0, 2.0, 3.0]) @ normal) <= 0.05  # outliers that happen to be on it
    assert np.array_equal(rp.inliers[truth], np.ones(k, bool))
    assert abs(int(rp.inliers[~truth].sum()) - int(off_plane_near.sum())) <= 3  # the plane found is not exactly the true one
    assert abs(rp.share - rp.inliers.mean()) < 1e-12
    assert rp.thickness == pytest.approx(0.01, rel=0.1)


def test_the_robust_plane_does_not_depend_on_the_order_of_the_points():
    X, _, _ = _plane_with_outliers(seed=1, share=0.55)
    perm = np.random.default_rng(7).permutation(len(X))
    a, b = robust_plane(X, 0.05, 0.5), robust_plane(X[perm], 0.05, 0.5)
    assert np.allclose(a.normal * np.sign(a.normal[2]), b.normal * np.sign(b.normal[2]))
    assert np.array_equal(a.inliers[perm], b.inliers)


def test_the_robust_plane_is_fitted_to_the_points_it_holds_once(monkeypatch):
    """The refinement stops when the plane fitted to its inliers holds the same points: that fit is
    the plane returned, not fitted a second time on the same points (a third of the cost on a
    153k-point table, the same bits)."""
    import kbs.geometry.groundplane as gp

    fits: list[np.ndarray] = []
    real = gp._principal_plane

    def counted(Q):
        fits.append(Q.copy())
        return real(Q)

    monkeypatch.setattr(gp, "_principal_plane", counted)
    for seed in range(4):
        X, _, _ = _plane_with_outliers(seed=seed, share=0.6)
        fits.clear()
        rp = robust_plane(X, 0.05, 0.5)
        assert all(not np.array_equal(a, b) for a, b in zip(fits, fits[1:])), seed  # no fit repeated
        P = X[gp._xyz_order(X)]
        n, c, t = real(P[rp.inliers[gp._xyz_order(X)]])
        assert np.array_equal(n, rp.normal) and np.array_equal(c, rp.point) and t == rp.thickness
        assert np.array_equal(rp.inliers, np.abs((X - rp.point) @ rp.normal) <= 0.05)


def test_no_robust_plane_through_a_line_or_two_points():
    t = np.linspace(0, 1, 100)[:, None]
    assert robust_plane(t * [1.0, 2.0, 3.0], 0.1, 0.5) is None
    assert robust_plane(np.array([[0.0, 0, 0], [1, 1, 1]]), 0.1, 0.5) is None


def test_enough_hypotheses_to_find_the_plane():
    """(1 - w^3)^k <= 1e-9: a plane holding a share w of the points is missed at most once in 10^9."""
    for w in (0.3, 0.5, 0.8):
        k = hypotheses_needed(w)
        assert (1 - w ** 3) ** k <= 1e-9 < (1 - w ** 3) ** (k - 1) or k == 20
    assert hypotheses_needed(1.0) == 20 and hypotheses_needed(0.01) == 2000


# --- (e) a scan not in the sensor's frame: the normal still points up, and the output says why ------


@pytest.mark.slow
@pytest.mark.parametrize("shift, said, same", [
    ((0.0, 0.0, 1000.0), "lies 99", True),                       # an elevation: the sensor (the origin) 1 km below
    ((5e5, 4e6, -20.0), "from the scan's bounding box", False),  # survey coordinates: the origin 4,000 km away
])
def test_a_scan_in_map_coordinates_keeps_its_ground_up_and_says_the_sensor_does_not_fit(tmp_path, shift, said, same):
    """A scan whose coordinates are not the sensor's frame, read with the rule base's sensor (the
    origin): the ground normal pointed towards the origin, down for a scan 1 km above it, so every
    height above the ground changed sign and 12 % more of SemanticKITTI 000001 became ground. The
    normal now keeps the fallback normal's side, and a note says what does not fit and how to give
    the sensor (--sensor). With the sensor only below, the labels are those of the scan at the
    origin; with the sensor thousands of km away, "the closest plane to the sensor" is not this
    scene's (here the farther of two planes), which the note says; given the sensor, the labels
    are those of the scan at the origin."""
    X, _ = two_planes(cluttered=True)
    r0, doc0 = run(tmp_path, X, name="here")
    r, doc = run(tmp_path, X + np.array(shift), name="there")
    g = doc["explanation"]["ground"]
    assert g["normal"][2] > 0.9 and doc0["explanation"]["ground"]["normal"][2] > 0.9
    from plyfile import PlyData

    def labels(name):
        return np.asarray(PlyData.read(str(tmp_path / "out" / f"{name}.ply"))["vertex"]["scalar_label"])

    if same:
        np.testing.assert_array_equal(labels("there"), labels("here"))
    note = [ln for ln in r.stderr.splitlines() if ln.startswith("note: the sensor [0, 0, 0] ")]
    assert len(note) == 1 and said in note[0] and "--sensor X,Y,Z" in note[0], r.stderr
    assert g["note"] == note[0].removeprefix("note: ")
    assert not [ln for ln in r0.stderr.splitlines() if ln.startswith("note: the sensor")], r0.stderr
    # given the sensor where it is, nothing to say
    r2, _ = run(tmp_path, X + np.array(shift), "--sensor", ",".join(f"{v:.17g}" for v in shift), name="given")
    assert not [ln for ln in r2.stderr.splitlines() if ln.startswith("note: the sensor")], r2.stderr
    np.testing.assert_array_equal(labels("given"), labels("here"))


def test_points_far_from_the_origin_for_their_size_are_warned_about(tmp_path):
    """1e12 m from the origin (6e9 times SemanticKITTI's extent) float64 holds a coordinate to
    0.1 mm and a cluster's sums to centimetres: 12 % of the ground was lost without a word. Now a
    CoordinateWarning (kbs run: 'kbs: warning:'); survey coordinates (4e6 m) are not warned about."""
    import warnings

    from kbs.knowledge import Segmenter
    from kbs.units import CoordinateWarning

    X, _ = two_planes(cluttered=False)
    X = X[::4]
    seg = Segmenter("outdoor")
    with pytest.warns(CoordinateWarning, match=r"lie 1e\+12 m from the origin, .* times their extent .*subtract the offset"):
        seg.segment(X + 1e12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CoordinateWarning)
        seg.segment(X + np.array([5e5, 4e6, 0.0]))
    scan = tmp_path / "far.ply"
    write_ply(scan, X + 1e12)
    r = kbs("run", "--rules", "outdoor", "-j", "1", str(scan), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    assert f"kbs: warning: {scan}: the points lie 1e+12 m from the origin" in r.stderr
    assert "Traceback" not in r.stderr and "CoordinateWarning" not in r.stderr
