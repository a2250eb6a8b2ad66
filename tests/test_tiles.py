"""Tiled runs (`kbs run --tile`, kbs.segment_tiled): the tile geometry, stitching across tile
edges, the command's options, and Dask (a LocalCluster gives the bytes of the in-process run)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

import kbs
from kbs.errors import ParameterError
from kbs.io import write_ply
from kbs.tiles import TileGrid, ground_axes, segment_tiled
from scenes import ground_and_rocks
from test_cli import ROOT
from test_cli import kbs as kbs_cmd


def _vertex(path: Path):
    return PlyData.read(str(path))["vertex"]


# -- 1. the tiles ----------------------------------------------------------------------------------


@pytest.mark.parametrize("size, buffer", [(10.0, 0.0), (7.5, 2.0), (3.0, 5.0), (1000.0, 1.0)])
def test_cores_partition_the_points_and_each_tile_holds_its_core_widened_by_the_buffer(size, buffer):
    X = np.random.default_rng(4).uniform([-20, 5, 0], [13, 31, 4], (3000, 3))
    grid = TileGrid.fit(X, size, buffer)
    tiles = grid.tiles(X)
    owners = np.zeros(len(X), int)
    for t in tiles:
        owners[t.index[t.in_core]] += 1
        u0, v0, u1, v1 = t.core
        # brute force: inside the core widened by the buffer (the grid's outer edges reach everything)
        lo_u = -np.inf if t.i == 0 else u0 - buffer
        hi_u = np.inf if t.i == grid.shape[0] - 1 else u1 + buffer
        lo_v = -np.inf if t.j == 0 else v0 - buffer
        hi_v = np.inf if t.j == grid.shape[1] - 1 else v1 + buffer
        inside = np.flatnonzero((X[:, 0] >= lo_u) & (X[:, 0] <= hi_u) & (X[:, 1] >= lo_v) & (X[:, 1] <= hi_v))
        np.testing.assert_array_equal(t.index, inside)
        core = X[t.index[t.in_core]]
        assert (core[:, 0] >= u0).all() and (core[:, 1] >= v0).all()
        assert ((core[:, 0] < u1) | (t.i == grid.shape[0] - 1)).all()
    assert (owners == 1).all()
    assert grid.shape == (int(np.ceil(np.ptp(X[:, 0]) / size)), int(np.ceil(np.ptp(X[:, 1]) / size)))


def test_a_tile_whose_core_holds_no_point_is_left_out():
    X = np.array([[0.0, 0, 0], [1, 1, 0], [25, 25, 0], [29, 29, 1]])
    tiles = TileGrid.fit(X, 10.0, 1.0).tiles(X)
    assert [t.name for t in tiles] == ["t0_0", "t2_2"]


def test_the_ground_plane_axes_are_orthonormal_and_across_the_normal():
    np.testing.assert_array_equal(ground_axes(None), [[1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(ground_axes((0, 0, 2.0)), [[1, 0, 0], [0, 1, 0]])
    for n in ([0, -1, 0], [1, 0, 0], [0.3, 0.2, 0.9]):
        A = ground_axes(n)
        np.testing.assert_allclose(A @ A.T, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(A @ (np.asarray(n) / np.linalg.norm(n)), 0, atol=1e-12)


@pytest.mark.parametrize("size, buffer, message", [
    (0.0, 1.0, "The 'tile size' parameter must be a positive length. Got 0.0 instead."),
    (float("nan"), 1.0, "The 'tile size' parameter must be a positive length. Got nan instead."),
    (10.0, -1.0, "The 'buffer' parameter must be a length >= 0. Got -1.0 instead."),
    (1.0, 4.6, "tiles of 1 with a buffer of 4.6: each tile would be segmented over 104 times its own area, every "
               "point as many times; the buffer may be at most 4.5 tiles wide: give tiles of at least 1.02, or a "
               "smaller buffer"),
    (5.0, 1e300, "tiles of 5 with a buffer of 1e+300: each tile would be segmented over inf times its own area"),
])
def test_bad_tile_size_or_buffer_is_a_parameter_error(size, buffer, message):
    with pytest.raises(ParameterError, match=re.escape(message)):
        TileGrid.fit(np.zeros((3, 3)), size, buffer)


def test_a_buffer_of_at_most_4_5_tiles_is_a_grid():
    assert TileGrid.fit(np.zeros((3, 3)), 1.0, 4.5).buffer == 4.5


def test_tiles_far_below_the_buffer_are_refused_by_the_command_before_any_tile(tmp_path):
    """`kbs run --tile 0.0001` on the 26k-point example made about 26,000 one-point tiles, each
    segmented with the 6 m buffer (twice the ground surface's radius) around it: minutes of work
    with no warning. Now a parameter error (exit 6) saying how small the tiles may be."""
    r = kbs_cmd("run", "--rules", "outdoor", "--tile", "0.0001", str(ROOT / "examples" / "data" / "outdoor.ply"),
                "--out", str(tmp_path / "o"), "-j", "1")
    assert r.returncode == 6, r.stderr
    assert "kbs: error: tiles of 0.0001 with a buffer of 6: each tile would be segmented over 1.44e+10 times its " \
           "own area" in r.stderr and "give tiles of at least 1.33, or a smaller buffer" in r.stderr, r.stderr
    assert not list((tmp_path / "o").glob("*.ply"))


# -- 2. stitching, through the command -----------------------------------------------------------


@pytest.fixture(scope="module")
def rocks(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """Three rocks on flat ground 12 m x 12 m; tiles of 6 m put an edge through the middle rock."""
    X, labels = ground_and_rocks()
    path = tmp_path_factory.mktemp("scan") / "rocks.ply"
    write_ply(path, X, {"truth": labels.astype(np.int32)})
    return path, labels


@pytest.mark.slow
def test_a_rock_across_a_tile_edge_is_one_stitched_cluster_and_its_neighbours_stay_apart(rocks, tmp_path):
    scan, truth = rocks
    r = kbs_cmd("run", "--rules", "outdoor", "-j", "1", "--tile", "6", "--buffer", "1.5", str(scan),
                "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "tiles: 4 of 6 x 6 with a 1.5 buffer; 2 clusters stitched across tile edges" in r.stdout
    v = _vertex(tmp_path / "rocks.ply")
    doc = json.loads((tmp_path / "rocks.json").read_text())
    cluster, label = np.asarray(v["scalar_cluster"]), np.asarray(v["scalar_label"])
    assert len(doc["clusters"]) == cluster.max() + 1
    assert [c["index"] for c in doc["clusters"]] == list(range(len(doc["clusters"])))
    sizes = [c["n_points"] for c in doc["clusters"]]
    assert sizes == sorted(sizes, reverse=True) and sizes == np.bincount(cluster[cluster >= 0]).tolist()
    rock = lambda i: np.bincount(cluster[(truth == i) & (label == 1)]).argmax()  # noqa: E731
    middle = doc["clusters"][rock(2)]
    assert [(p["tile"], p["label"]) for p in middle["stitched"]] == [("t0_1", "obstacle"), ("t1_1", "obstacle")]
    assert np.mean(cluster[(truth == 2) & (label == 1)] == rock(2)) > 0.97  # both halves: one id
    assert len({rock(1), rock(2), rock(3)}) == 3  # the rocks beside it are not merged into it
    assert "stitched" not in doc["clusters"][rock(1)] and "stitched" not in doc["clusters"][rock(3)]
    assert doc["tiling"]["size"] == 6.0 and [t["name"] for t in doc["tiling"]["tiles"]] == [
        "t0_0", "t0_1", "t1_0", "t1_1"]
    assert sum(t["core_points"] for t in doc["tiling"]["tiles"]) == len(cluster)
    # the explanation says it was stitched, from which tiles and clusters
    part = middle["stitched"][0]["ids"][0]
    r = kbs_cmd("explain", str(tmp_path / "rocks.json"), "--cluster", part)
    assert r.returncode == 0, r.stderr
    assert f"note: stitched across tile edges into output cluster {rock(2)}: shares buffer points with t1_1 cluster" \
        in r.stdout
    r = kbs_cmd("explain", str(tmp_path / "rocks.json"))
    tree = r.stdout.split("\ntree:\n")[1].splitlines()
    assert r.returncode == 0 and tree[0].startswith("tiles (") and "partitioned in 4" in r.stdout


@pytest.mark.slow
def test_the_python_api_gives_what_the_command_writes(rocks, tmp_path):
    scan, truth = rocks
    X = np.column_stack([_vertex(scan)[k] for k in "xyz"]).astype(np.float64)
    with kbs.Segmenter("outdoor", jobs=1) as seg:
        out = kbs.segment_tiled(seg, X, 6.0, 1.5)
    assert kbs.segment_tiled is segment_tiled
    assert kbs_cmd("-q", "run", "--rules", "outdoor", "-j", "1", "--tile", "6", "--buffer", "1.5", str(scan),
                   "--out", str(tmp_path)).returncode == 0
    v = _vertex(tmp_path / "rocks.ply")
    np.testing.assert_array_equal(out.cluster, v["scalar_cluster"])
    np.testing.assert_array_equal(out.label, v["scalar_label"])
    assert out.tiling == json.loads((tmp_path / "rocks.json").read_text())["tiling"]


@pytest.mark.parametrize("args, message", [
    (["--buffer", "2"], "--buffer only applies to a tiled run: give --tile SIZE too"),
    (["--scheduler", "local"], "--scheduler only applies to a tiled run: give --tile SIZE too"),
    (["--tile", "0"], "Invalid value for '--tile': 0.0 is not in the range x>0."),
    (["--tile", "6", "--buffer", "-1"], "Invalid value for '--buffer': -1.0 is not in the range x>=0."),
    (["--tile", "6", "--scheduler", " "], "Invalid value for --scheduler: give a Dask scheduler address"),
])
@pytest.mark.slow
def test_bad_tiling_options_are_usage_errors(rocks, tmp_path, args, message):
    r = kbs_cmd("run", "--rules", "outdoor", "-j", "1", *args, str(rocks[0]), "--out", str(tmp_path))
    assert r.returncode == 2, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "rocks.ply").exists()


FAILING_PLUGIN = '''
from kbs.knowledge import predicate


@predicate(unit="length")
def east(cluster, scene) -> float:
    """x of the centre; fails east of x = 3 m (to make the tiles there fail)."""
    x = float(cluster.geometry.center[0])
    if x > 3.0:
        raise RuntimeError("no measurement east of 3 m")
    return x
'''


def east_rules(tmp_path: Path, plugin_text: str) -> list[str]:
    """``--rules``/``--plugin`` arguments: the outdoor rules with a check ``west`` measured by the
    plugin ``plugin_text`` (a predicate ``east`` that fails, or kills its worker, east of 3 m)."""
    plugin = tmp_path / "east.py"
    plugin.write_text(plugin_text)
    rules = tmp_path / "east.yaml"
    text = kbs_cmd("rules", "show", "outdoor").stdout
    text = text.replace("checks:\n", "checks:\n  west: {predicate: east, max: 100.0}\n", 1)
    text, n = re.subn(r"if: \[planar, level\]", "if: [planar, level, west]", text)
    assert n >= 1, "the outdoor rules no longer have 'if: [planar, level]'"
    rules.write_text(text)
    return ["--rules", str(rules), "--plugin", str(plugin)]


@pytest.mark.slow
def test_a_failing_tile_is_named_with_its_bounds_and_the_run_exits_with_its_code(rocks, tmp_path):
    r = kbs_cmd("run", *east_rules(tmp_path, FAILING_PLUGIN), "-j", "1", "--tile", "6", "--buffer", "1.5",
                str(rocks[0]), "--out", str(tmp_path / "out"))
    assert r.returncode == 7, r.stderr
    assert re.search(r"kbs: error: tile t1_1 \[0\.000\d+, 6\.000\d+\] x \[0\.001\d+, 6\.001\d*\] \(7,700 points\): ",
                     r.stderr), r.stderr
    assert "predicate 'east' (" in r.stderr and "failed on cluster c0" in r.stderr and "no measurement east of 3 m" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out" / "rocks.ply").exists()


# -- 3. Dask: a LocalCluster of 2 workers gives the bytes of the in-process run ---------------------


def _normalised(folder: Path, stem: str) -> tuple[bytes, dict]:
    """The PLY bytes without the run id comment, and the JSON without run id and timing."""
    ply = re.sub(rb"comment kbs_run_id [0-9a-f]+\n", b"", (folder / f"{stem}.ply").read_bytes())
    doc = json.loads((folder / f"{stem}.json").read_text())
    assert doc.pop("run_id") and doc["summary"].pop("seconds") >= 0
    return ply, doc


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_tiles_on_a_local_dask_cluster_of_2_workers_give_the_in_process_bytes(shared_data, tmp_path):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    scan = shared_data / "isprs" / "samp21-utm.pcd"  # airborne, 124 m x 115 m: 9 tiles of 50 m
    args = ["-q", "run", "--rules", "airborne", "--tile", "50", str(scan)]
    here = kbs_cmd(*args, "-j", "1", "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr
    dask = kbs_cmd(*args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    assert dask.stderr == ""  # -q: no Dask log lines
    ply_here, doc_here = _normalised(tmp_path / "here", "samp21-utm")
    ply_dask, doc_dask = _normalised(tmp_path / "dask", "samp21-utm")
    assert len(doc_here["tiling"]["tiles"]) == 9
    assert ply_dask == ply_here
    assert doc_dask == doc_here
    # and the labels of the untiled run, within the tolerance measured on this scan: 5.0 % changed
    # before the airborne rules' `understory` (session 18), 8.1 % with it (a level patch is judged
    # against the patches around it, which tiles of 50 m cut otherwise; tiles of 100 m: 3.7 %)
    whole = kbs_cmd(*args[:4], str(scan), "-j", "1", "--out", str(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    tiled, untiled = _vertex(tmp_path / "here" / "samp21-utm.ply"), _vertex(tmp_path / "whole" / "samp21-utm.ply")
    assert np.mean(np.asarray(tiled["scalar_label"]) == np.asarray(untiled["scalar_label"])) > 0.9


@pytest.mark.slow
def test_an_unreachable_scheduler_is_a_usage_error(rocks, tmp_path):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    r = kbs_cmd("run", "--rules", "outdoor", "--tile", "6", "--scheduler", "tcp://127.0.0.1:9", str(rocks[0]),
                "--out", str(tmp_path))
    assert r.returncode == 2, r.stderr
    assert "Invalid value for --scheduler: no Dask scheduler answers at 'tcp://127.0.0.1:9'" in r.stderr
    assert "Traceback" not in r.stderr


FLAKY_PLUGIN = FAILING_PLUGIN.replace('if x > 3.0:', 'if x > 3.0 and os.environ.get("KBS_TEST_FAIL_EAST"):').replace(
    "from kbs.knowledge import predicate", "import os\n\nfrom kbs.knowledge import predicate")


@pytest.mark.slow
def test_finished_tiles_are_kept_and_resume_segments_only_the_failed_ones(rocks, tmp_path, monkeypatch):
    args = ["run", *east_rules(tmp_path, FLAKY_PLUGIN), "-j", "1", "--tile", "6", "--buffer", "1.5",
            str(rocks[0])]
    out, kept = tmp_path / "out", tmp_path / "out" / "rocks.tiles"
    monkeypatch.setenv("KBS_TEST_FAIL_EAST", "1")  # tile t1_1 fails, the three others are done and kept
    r = kbs_cmd(*args, "--out", str(out))
    assert r.returncode == 7, r.stderr
    assert f"; the finished tiles are kept in {kept}: run again with --resume (resume=True) to segment only the " \
           f"failed ones" in r.stderr
    assert sorted(p.name for p in kept.iterdir()) == ["t0_0.npz", "t0_1.npz", "t1_0.npz"]
    assert not (out / "rocks.ply").exists()
    monkeypatch.delenv("KBS_TEST_FAIL_EAST")
    r = kbs_cmd(*args, "--resume", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"kbs: resumed 3 of 4 tiles from {kept}" in r.stderr
    assert not kept.exists()  # the result is written: the tiles are removed
    fresh = kbs_cmd(*args, "--out", str(tmp_path / "fresh"))
    assert fresh.returncode == 0, fresh.stderr
    assert _normalised(out, "rocks") == _normalised(tmp_path / "fresh", "rocks")


@pytest.mark.slow
def test_resume_takes_no_tile_of_another_grid(rocks, tmp_path, monkeypatch):
    """A tile file whose points differ (another buffer) is segmented again, not taken."""
    out, kept = tmp_path / "out", tmp_path / "out" / "rocks.tiles"
    from kbs.tiles import plan_tiles
    from kbs.tiles.store import TileStore

    X = np.column_stack([_vertex(rocks[0])[k] for k in "xyz"]).astype(np.float64)
    with kbs.Segmenter("outdoor", jobs=1) as seg:
        store = TileStore(kept, seg)
        _, tiles = plan_tiles(seg, X, 6.0, 1.0)  # --buffer 1, the run below uses 1.5
        store.save(tiles[0], store.key(tiles[0], X), seg.segment(X[tiles[0].index]))
    r = kbs_cmd("run", "--rules", "outdoor", "-j", "1", "--tile", "6", "--buffer", "1.5", "--resume",
                str(rocks[0]), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"kbs: resumed 0 of 4 tiles from {kept}" in r.stderr


def test_resume_needs_tile(rocks, tmp_path):
    r = kbs_cmd("run", "--rules", "outdoor", "--resume", str(rocks[0]), "--out", str(tmp_path))
    assert r.returncode == 2 and "--resume only applies to a tiled run: give --tile SIZE too" in r.stderr


KILLING_PLUGIN = '''
import os
from pathlib import Path

from kbs.knowledge import predicate


@predicate(unit="length")
def east(cluster, scene) -> float:
    """x of the centre; the first Dask worker to measure one east of 3 m dies (once)."""
    x = float(cluster.geometry.center[0])
    marker = os.environ.get("KBS_TEST_KILL_MARKER")
    if x > 3.0 and marker and not os.path.exists(marker):
        try:
            from distributed import get_worker

            get_worker()
        except (ImportError, ValueError):
            return x  # not on a Dask worker
        Path(marker).write_text("killed")
        os._exit(1)
    return x
'''


@pytest.mark.slow
def test_a_dask_worker_killed_mid_run_gives_the_same_output(rocks, tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    args = ["-q", "run", *east_rules(tmp_path, KILLING_PLUGIN), "--tile", "6", "--buffer", "1.5", str(rocks[0])]
    assert kbs_cmd(*args, "-j", "1", "--out", str(tmp_path / "here")).returncode == 0
    marker = tmp_path / "killed"
    monkeypatch.setenv("KBS_TEST_KILL_MARKER", str(marker))
    r = kbs_cmd(*args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert r.returncode == 0, r.stderr
    assert marker.read_text() == "killed"  # a worker died in a tile; Dask ran the tile again on another
    assert _normalised(tmp_path / "dask", "rocks") == _normalised(tmp_path / "here", "rocks")


def test_a_tiled_cloud_in_the_wrong_unit_is_warned_of_once_not_once_per_tile(rocks):
    """The spacing of a tiled cloud is judged once, on the whole cloud (a cloud in mm read as m
    used to warn once per tile: 764 warnings for PDAL's simple.las)."""
    import warnings

    from kbs.units import SpacingWarning

    X = np.column_stack([_vertex(rocks[0])[k] for k in "xyz"]).astype(np.float64) * 1000.0  # m written as mm
    with kbs.Segmenter("outdoor", jobs=1) as seg, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = segment_tiled(seg, X, 6000.0, 1500.0)
    spacing = [w.message for w in caught if isinstance(w.message, SpacingWarning)]
    assert len(out.tiling["tiles"]) == 4
    assert len(spacing) == 1, [str(w.message) for w in caught]
    assert spacing[0].spacing > 2.0 and "mm" in spacing[0].suggested


def test_a_tiles_spacing_is_not_measured_and_the_segmenter_measures_again_after(rocks, monkeypatch):
    """The tiles' spacing would be ignored: it is not measured (a k-d tree over each tile). The
    whole cloud's is, once; and the segmenter judges its next cloud's again."""
    import kbs.units

    calls = []
    real = kbs.units.median_spacing
    monkeypatch.setattr(kbs.units, "median_spacing", lambda X, **kw: calls.append(len(X)) or real(X, **kw))
    X = np.column_stack([_vertex(rocks[0])[k] for k in "xyz"]).astype(np.float64)
    with kbs.Segmenter("outdoor", jobs=1) as seg:
        out = segment_tiled(seg, X, 6.0, 1.5)
        assert len(out.tiling["tiles"]) == 4 and calls == [len(X)]
        seg.segment(X[:2000])
    assert calls == [len(X), 2000]


@pytest.mark.filterwarnings("ignore:median point spacing")
def test_the_whole_cloud_ground_is_found_without_a_partition_only_when_the_rule_file_fixes_its_normal(monkeypatch):
    """A tiled run finds the ground plane once on the whole cloud (Interpreter.find_ground). With a
    normal fixed by the rule file (airborne) the plane is the fixed normal through the 5 % height
    quantile, and the initial partition the candidates come from is not computed (it was, on up to
    2,000,000 points: the client's largest memory); the result is what the run itself would find.
    With a normal found from the data (outdoor) the partition is computed."""
    from kbs.knowledge.ground import plane_from_normal
    from kbs.knowledge.interpreter import Interpreter

    X, _ = ground_and_rocks()
    X = X + np.array([1000.0, 2000.0, 50.0])
    calls = []
    original = Interpreter._ufp_onc
    monkeypatch.setattr(Interpreter, "_ufp_onc", lambda self, *a, **k: calls.append(1) or original(self, *a, **k))
    airborne = kbs.Segmenter("airborne", jobs=1)
    ground, facts = airborne._interpreter.find_ground(X)
    assert calls == []
    expected, expected_facts = plane_from_normal(X, np.array([0.0, 0.0, 1.0]), "fixed", type(facts)())
    assert np.array_equal(ground.normal, expected.normal) and np.array_equal(ground.point, expected.point)
    assert facts == expected_facts and facts.source == "fixed"
    run = airborne.segment(X)  # the untiled run finds the same plane
    assert run.explanation.ground.normal == facts.normal and run.explanation.ground.point == facts.point
    calls.clear()
    kbs.Segmenter("outdoor", jobs=1)._interpreter.find_ground(X - np.array([1000.0, 2000.0, 50.0]))
    assert calls == [1]


def test_the_union_find_gives_every_node_its_root_at_once():
    from kbs.tiles.stitch import _Union

    rng = np.random.default_rng(3)
    for n in (0, 1, 50, 2000):
        uf = _Union(n)
        for a, b in rng.integers(0, max(n, 1), size=(n // 2, 2)) if n else ():
            uf.union(int(a), int(b))
        roots = uf.roots()
        assert roots.dtype == np.int64 and roots.tolist() == [uf.find(i) for i in range(n)]
        assert all(roots[i] <= i for i in range(n))  # the smaller node stays the root


# -- Ctrl-C: a tiled run stops at once, keeps its finished tiles, and --resume ends it ---------------


@pytest.mark.slow  # a real scan, three kbs processes: pytest --runslow (CI) runs it
def test_ctrl_c_stops_a_tiled_run_at_once_keeping_its_tiles_and_resume_ends_it(shared_data, tmp_path):
    """SIGINT to `kbs run --tile` once a few tiles are saved: exit code 130, one line saying the run
    was aborted and where its finished tiles are, no result written; `--resume` then gives the bytes of
    an uninterrupted run. Before, a Ctrl-C that fell inside a compiled kernel came out as a
    SystemError, which the tile's predicate wrapper reported as the predicate's failure (exit 7)
    after segmenting every other tile."""
    import shutil
    import signal
    import subprocess
    import sys
    import time

    from test_cli import kbs as run_kbs

    scan = shared_data / "isprs" / "samp31-utm.pcd"  # 81 tiles of 20 m
    args = ["run", "--rules", "airborne", "--tile", "20", "-j", "1", str(scan)]
    out = tmp_path / "cut"
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert exe, "the kbs command is not installed"
    # SIGINT's default action in the child: a shell starting a job in the background (CI may) makes it
    # ignored, and Python then installs no KeyboardInterrupt for it
    p = subprocess.Popen([exe, *args, "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    store = out / "samp31-utm.tiles"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 240 and p.poll() is None and len(list(store.glob("*.npz"))) < 3:
        time.sleep(0.02)
    assert p.poll() is None, "the run ended before it could be interrupted"
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    kept = len(list(store.glob("*.npz")))
    assert p.returncode == 130, err
    assert err.strip().splitlines()[-1] == (f"kbs: aborted; the finished tiles are kept in {store}: run again with "
                                            "--resume (resume=True) to segment only the others"), err
    assert "Traceback" not in err and "error" not in err
    assert 3 <= kept < 81, kept  # it stopped: not every tile was segmented after the signal
    assert not (out / "samp31-utm.ply").exists() and not (out / "samp31-utm.json").exists()
    resumed = run_kbs("-q", *args, "--resume", "--out", str(out))
    assert resumed.returncode == 0, resumed.stderr
    whole = run_kbs("-q", *args, "--out", str(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    assert _normalised(out, "samp31-utm") == _normalised(tmp_path / "whole", "samp31-utm")
