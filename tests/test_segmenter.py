"""kbs.Segmenter (a rule base loaded once, clouds segmented frame after frame) and `kbs run` over
several scans with one Segmenter."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kbs
from kbs.errors import ExitCode, ParameterError
from kbs.io import read_cloud
from kbs.io.result import read_result_cloud
from kbs.knowledge import PredicateError, RuleFileError, Segmentation, load_rule_base
from scenes import ground_and_boxes, ground_and_rocks, ground_with_small_obstacles
from test_cli import EXAMPLE, ROOT, kbs as kbs_command

POLYHEDRAL = ROOT / "examples" / "data" / "polyhedral.ply"
PER_POINT = ("cluster", "label", "membership")


def _same(a: Segmentation, b: Segmentation) -> None:
    """Two segmentations are identical: per-point arrays (values and dtypes), labels, output
    clusters and the whole explanation tree."""
    for name in PER_POINT:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.label_names == b.label_names
    assert json.dumps(a.clusters, default=float) == json.dumps(b.clusters, default=float)
    assert json.dumps(a.explanation.to_dict(), default=float) == json.dumps(b.explanation.to_dict(), default=float)


def _equals_written(seg: Segmentation, ply: Path) -> None:
    """``seg`` holds exactly the per-point arrays `kbs run` wrote to ``ply``."""
    written = read_result_cloud(ply)  # scalar_cluster ... read as cluster ...
    for name in PER_POINT:
        values = written.fields[name]
        assert values.dtype == getattr(seg, name).dtype and np.array_equal(values, getattr(seg, name)), name
    assert json.loads(ply.with_suffix(".json").read_text())["label_names"] == seg.label_names


# -- the library ---------------------------------------------------------------------------------


def test_exported_lazily_from_kbs_and_from_kbs_knowledge():
    import kbs.knowledge

    assert kbs.Segmenter is kbs.knowledge.Segmenter and "Segmenter" in kbs.__all__ and "Segmenter" in dir(kbs)
    code = "import sys, kbs; assert 'numpy' not in sys.modules and 'kbs.knowledge' not in sys.modules; kbs.Segmenter"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_attributes_and_repr():
    seg = kbs.Segmenter("outdoor", jobs=2, sensor=[0, 0, 1.73])
    assert seg.rule_base.name == "outdoor" and seg.jobs == 2 and seg.sensor == (0.0, 0.0, 1.73)
    assert seg.label_names == ["ground", "obstacle"]
    assert repr(seg) == ("Segmenter(rule base 'outdoor' from outdoor.yaml, divisive, labels ground/obstacle; "
                         "jobs=2, sensor=(0, 0, 1.73))")
    assert kbs.Segmenter("airborne").sensor == tuple(map(float, load_rule_base("airborne").sensor))


def test_rules_by_name_path_or_loaded_rule_base_give_the_same_result():
    X = ground_and_rocks()[0]
    by_name = kbs.Segmenter("outdoor").segment(X)
    _same(by_name, kbs.Segmenter(load_rule_base("outdoor")).segment(X))
    by_path = kbs.Segmenter(ROOT / "rules" / "outdoor.yaml")
    assert by_path.rule_base.path == str(ROOT / "rules" / "outdoor.yaml")
    for name in PER_POINT:
        assert np.array_equal(getattr(by_name, name), getattr(by_path.segment(X), name))


def test_plugins_are_loaded_before_the_rule_file_is_parsed():
    poles = ROOT / "examples" / "rules" / "poles.yaml"
    with pytest.raises(RuleFileError, match="unknown predicate 'elongation'"):
        kbs.Segmenter(poles)
    seg = kbs.Segmenter(poles, plugins=[ROOT / "examples" / "plugins" / "elongation.py"])
    assert seg.label_names == ["ground", "pole", "obstacle"] and "elongation.py" in repr(seg)
    with pytest.raises(PredicateError, match="plugin file not found"):
        kbs.Segmenter("outdoor", plugins=["no-such-plugin.py"])


def test_one_segmenter_frame_after_frame_equals_a_fresh_one_per_frame():
    frames = [ground_and_rocks()[0], ground_with_small_obstacles()[0], ground_and_boxes()]
    loaded = kbs.Segmenter("outdoor")
    in_a_row = [loaded.segment(X) for X in frames] + [loaded.segment(frames[0])]
    for X, seg in zip(frames + frames[:1], in_a_row):
        _same(seg, kbs.Segmenter("outdoor").segment(X))
    assert len({len(s.clusters) for s in in_a_row[:3]}) > 1  # the frames differ, and so do their results


def test_processes_is_jobs_with_minus_one_resolved_to_the_cores_and_at_most_the_cores():
    cores = kbs.knowledge.interpreter.available_cores()
    assert kbs.Segmenter("outdoor", jobs=-1).processes == cores
    seg = kbs.Segmenter("outdoor", jobs=100_000)  # it forked a hundred thousand split processes
    assert (seg.jobs, seg.processes, seg.with_jobs(-1).processes, seg.with_jobs(1).processes) == (100_000, cores,
                                                                                                    cores, 1)


def test_jobs_2_equals_jobs_1():
    X = read_cloud(EXAMPLE).xyz
    _same(kbs.Segmenter("outdoor", jobs=2).segment(X), kbs.Segmenter("outdoor", jobs=1).segment(X))


def test_worker_processes_are_kept_frame_after_frame_and_closed():
    X = read_cloud(EXAMPLE).xyz
    ref = kbs.Segmenter("outdoor", jobs=1).segment(X)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        first = seg.segment(X)
        pool = seg._interpreter._pool
        assert pool is not None  # the bundled example splits: the workers were started
        pids = set(pool._processes)
        second = seg.segment(X)
        assert seg._interpreter._pool is pool and set(pool._processes) == pids  # not forked again
        _same(first, ref)
        _same(second, ref)
    assert seg._interpreter._pool is None  # closed with the block
    _same(seg.segment(X), ref)  # used again: started again
    seg.close()


def test_a_broken_pool_is_replaced_at_the_next_frame():
    X = read_cloud(EXAMPLE).xyz
    ref = kbs.Segmenter("outdoor", jobs=1).segment(X)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        seg.segment(X)
        pool = seg._interpreter._pool
        for p in list(pool._processes.values()):  # a worker killed between two frames
            p.kill()
            p.join()
        _same(seg.segment(X), ref)
        _same(seg.segment(X), ref)


def _subtree_calls(monkeypatch) -> list[int]:
    """Count the subtrees :class:`kbs.knowledge.interpreter.Subtrees` hands to the workers."""
    from kbs.knowledge.interpreter import Subtrees

    calls: list[int] = []
    real = Subtrees.start
    monkeypatch.setattr(Subtrees, "start", lambda self, wave: calls.append(len(wave)) or real(self, wave))
    return calls


@pytest.mark.parametrize("share", [0, 4, 1000])
def test_jobs_2_divides_the_subtrees_in_the_workers_as_jobs_1_does(monkeypatch, share):
    """With jobs > 1, the subtree below each child of the scene's clusters is judged and divided
    whole in a worker (those holding more than 1 / (SUBTREE_SHARE x jobs) of the cloud split here
    first, a level at a time); the records and leaves come back in the order one process gives
    them."""
    import kbs.knowledge.strategies.divisive as divisive

    X = read_cloud(EXAMPLE).xyz
    ref = kbs.Segmenter("outdoor", jobs=1).segment(X)
    monkeypatch.setattr(divisive, "SUBTREE_SHARE", share)
    calls = _subtree_calls(monkeypatch)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        _same(seg.segment(X), ref)
    assert sum(calls) >= 2 or share == 1000, calls  # subtrees were given to the workers (1000: all split here)
    said: dict[int, list[str]] = {1: [], 2: []}
    for jobs in (1, 2):
        with kbs.Segmenter("outdoor", jobs=jobs) as seg:
            again = seg.segment(X, progress=said[jobs].append)
    assert list(ref.explanation.records) == list(again.explanation.records)  # the queue's order
    assert sorted(said[2]) == sorted(said[1]) and said[1]  # every split said, as the subtrees come back


def test_a_large_cloud_keeps_the_splits_alone_in_the_workers(monkeypatch):
    """From EARLY_WORKERS points on, no subtree is given whole (10^7 airborne points went over
    4 GB with them): the same result, the splits alone in the workers."""
    import kbs.knowledge.run as run_module

    X = read_cloud(EXAMPLE).xyz
    ref = kbs.Segmenter("outdoor", jobs=1).segment(X)
    monkeypatch.setattr(run_module, "EARLY_WORKERS", X.shape[0])
    calls = _subtree_calls(monkeypatch)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        _same(seg.segment(X), ref)
    assert calls == []


def _dies_at_a_subtree(owner_id, node, cl, draft, scene):  # a split worker killed (out of memory, kill -9)
    import os

    os._exit(9)


def test_a_worker_killed_in_a_subtree_leaves_it_to_the_process(monkeypatch):
    import kbs.knowledge.interpreter as interpreter

    X = read_cloud(EXAMPLE).xyz
    ref = kbs.Segmenter("outdoor", jobs=1).segment(X)
    monkeypatch.setattr(interpreter, "_worker_subtree", _dies_at_a_subtree)  # before the workers are forked
    calls = _subtree_calls(monkeypatch)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        _same(seg.segment(X), ref)
        _same(seg.segment(X), ref)  # the broken pool replaced
    assert sum(calls) >= 2, calls


@pytest.mark.parametrize("error", [PredicateError("predicate 'x' failed on a deep cluster"),
                                   kbs.errors.CloudFileError("a.ply", "a problem")])  # its __init__ takes two arguments
def test_an_error_in_a_workers_subtree_is_raised_as_with_one_process(monkeypatch, error):
    """An error raised in a subtree a worker judges is the error of jobs=1, whether or not the
    exception can travel between processes."""
    from kbs.knowledge.run import RunContext

    real = RunContext.judge

    def judge(self, cluster, scene, draft):
        if cluster.id.count(".") >= 2:
            raise error
        return real(self, cluster, scene, draft)

    X = read_cloud(EXAMPLE).xyz
    monkeypatch.setattr(RunContext, "judge", judge)
    calls = _subtree_calls(monkeypatch)
    for jobs in (1, 2):
        with kbs.Segmenter("outdoor", jobs=jobs) as seg, pytest.raises(type(error)) as info:
            seg.segment(X)
        assert str(info.value) == str(error)
    assert sum(calls) >= 1, calls


@pytest.mark.slow
def test_jobs_2_equals_jobs_1_on_a_vehicle_scan():
    """SemanticKITTI 000001 (250 clusters, 11 levels): the same per-point arrays, clusters and
    explanation with the subtrees in two worker processes."""
    path = ROOT.parent / "shared" / "data" / "semantickitti" / "000001.points.npy"
    if not path.is_file():
        pytest.skip(f"{path} not found (../shared is absent)")
    X = np.load(path)[:, :3].astype(np.float64)
    with kbs.Segmenter("outdoor", jobs=2) as seg:
        _same(seg.segment(X), kbs.Segmenter("outdoor", jobs=1).segment(X))


def test_float32_points_are_read_as_float64_and_the_input_is_left_alone():
    X = ground_and_rocks()[0].astype(np.float32)
    before = X.copy()
    seg = kbs.Segmenter("outdoor")
    _same(seg.segment(X), seg.segment(X.astype(np.float64)))
    assert np.array_equal(X, before)


@pytest.mark.parametrize("points, needle", [
    (np.zeros((10, 4)), r"shape \(n_points, 3\), got shape \(10, 4\); keep x y z only"),
    (np.zeros((10, 2)), r"shape \(n_points, 3\), got shape \(10, 2\)"),
    (np.zeros(3), r"shape \(n_points, 3\), got shape \(3,\)"),
    (np.zeros((0, 3)), "holds no point"),
    (np.array([[0.0, 0.0, 0.0], [1.0, np.nan, 0.0], [2.0, 0.0, np.inf]]), "2 of the 3 points have a NaN or infinite"),
    ([[1, 2, 3], [4, 5]], r"\(n_points, 3\) array"),
    (np.array([["a", "b", "c"]]), "real numbers"),
])
def test_bad_points_raise_the_parameter_error(points, needle):
    with pytest.raises(ParameterError, match=needle) as info:
        kbs.Segmenter("outdoor").segment(points)
    assert info.value.exit_code == ExitCode.PARAMETER


@pytest.mark.parametrize("kwargs, needle", [
    ({"jobs": 0}, "'jobs' parameter"), ({"jobs": -2}, "'jobs' parameter"), ({"jobs": 1.5}, "'jobs' parameter"),
    ({"sensor": [1, 2]}, "'sensor' parameter"), ({"sensor": [0, 0, np.nan]}, "'sensor' parameter"),
    ({"plugins": "elongation.py"}, "a list of plugin files"),
])
def test_bad_settings_raise_the_parameter_error(kwargs, needle):
    with pytest.raises(ParameterError, match=needle):
        kbs.Segmenter("outdoor", **kwargs)


def test_bad_rules_raise_the_project_errors():
    with pytest.raises(RuleFileError, match="did you mean 'outdoor'"):
        kbs.Segmenter("outdor")
    with pytest.raises(ParameterError, match="rules must be"):
        kbs.Segmenter(3)
    with pytest.raises(ParameterError, match="already loaded"):
        kbs.Segmenter(load_rule_base("outdoor"), plugins=[ROOT / "examples" / "plugins" / "elongation.py"])


# -- equal to what `kbs run` writes ---------------------------------------------------------------


@pytest.fixture(scope="module")
def two_bundled(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """`kbs run` on the two bundled scenes at once."""
    out = tmp_path_factory.mktemp("two")
    r = kbs_command("run", "--rules", "outdoor", str(EXAMPLE), str(POLYHEDRAL), "--out", str(out))
    return out, r


@pytest.mark.slow
def test_segmenter_equals_kbs_run_on_the_bundled_examples(two_bundled):
    out, r = two_bundled
    assert r.returncode == 0, r.stderr
    seg = kbs.Segmenter("outdoor")
    for scan in (EXAMPLE, POLYHEDRAL):
        _equals_written(seg.segment(read_cloud(scan).xyz), out / f"{scan.stem}.ply")


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_segmenter_equals_kbs_run_on_semantickitti(shared_data, tmp_path):
    scan = shared_data / "semantickitti" / "000001.points.npy"
    r = kbs_command("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    points = np.load(scan)  # float32 (N, 3), as a user has it
    _equals_written(kbs.Segmenter("outdoor", jobs=2).segment(points), tmp_path / "000001.points.ply")


# -- `kbs run` over several scans -----------------------------------------------------------------

SCAN_LINE = re.compile(r"^(?P<path>\S+): [\d,]+ points, rule base 'outdoor' \(divisive\)$")
TIME_ROW = re.compile(r"^(?P<name>\S+) +(?P<points>[\d,]+) +(?P<clusters>\d+) +\d+\.\d\d +\d+\.\d\d +\d+\.\d\d$")


def _table(stdout: str) -> list[str]:
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split() == ["scan", "points", "clusters", "read", "s",
                                                                          "segment", "s", "write", "s"])
    return lines[start:]


@pytest.mark.slow
def test_run_two_files_writes_both_pairs_then_the_time_table(two_bundled):
    out, r = two_bundled
    assert r.returncode == 0, r.stderr
    for scan in (EXAMPLE, POLYHEDRAL):
        assert (out / f"{scan.stem}.ply").is_file() and (out / f"{scan.stem}.json").is_file()
        assert json.loads((out / f"{scan.stem}.json").read_text())["input"] == str(scan)
        assert f"wrote {out / scan.stem}.ply and {out / scan.stem}.json" in r.stdout
    assert [m["path"] for m in map(SCAN_LINE.match, r.stdout.splitlines()) if m] == [str(EXAMPLE), str(POLYHEDRAL)]
    assert r.stdout.count("  time: ") == 2
    table = _table(r.stdout)
    assert len(table) == 4 and len({len(line) for line in table[:3]}) == 1  # aligned
    rows = [TIME_ROW.match(line) for line in table[1:3]]
    assert [m["name"] for m in rows] == ["outdoor.ply", "polyhedral.ply"]
    for m, scan in zip(rows, (EXAMPLE, POLYHEDRAL)):
        doc = json.loads((out / f"{scan.stem}.json").read_text())
        assert int(m["points"].replace(",", "")) == doc["n_points"] and int(m["clusters"]) == len(doc["clusters"])
    assert re.fullmatch(r"2 scans: segment median \d+\.\d\d s, total \d+\.\d\d s(, 2 scans at a time)? \(rule base "
                        r"loaded once, \d+\.\d\d s\)", table[3])


@pytest.mark.slow
def test_run_a_directory_takes_its_point_cloud_files_in_name_order(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(POLYHEDRAL, scans / "b.ply")
    shutil.copy(EXAMPLE, scans / "a.ply")
    (scans / "notes.md").write_text("not a cloud\n")
    (scans / "sub").mkdir()
    out = tmp_path / "out"
    r = kbs_command("run", "--rules", "outdoor", "-j", "1", str(scans), "--out", str(out), "--meshes", "--report")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["a-meshes", "a.html", "a.json", "a.ply",
                                                     "b-meshes", "b.html", "b.json", "b.ply"]
    assert (out / "a-meshes" / "ground.ply").is_file() and (out / "b-meshes" / "ground.ply").is_file()
    assert [m["path"] for m in map(SCAN_LINE.match, r.stdout.splitlines()) if m] == [str(scans / "a.ply"),
                                                                                     str(scans / "b.ply")]
    assert [TIME_ROW.match(line)["name"] for line in _table(r.stdout)[1:3]] == ["a.ply", "b.ply"]
    r = kbs_command("run", "--rules", "outdoor", str(scans / "sub"), "--out", str(out))
    assert r.returncode == 3 and "no point-cloud file in this directory" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("case", ["same stem", "given twice", "directory and file"])
def test_duplicate_stems_exit_2_before_any_work(tmp_path, capsys, case):
    from kbs.cli.main import main  # the same entry point, in-process (each subprocess costs ~1 s)

    other = tmp_path / "outdoor.npy"
    np.save(other, read_cloud(EXAMPLE).xyz)
    args = {"same stem": [str(EXAMPLE), str(other)], "given twice": [str(EXAMPLE), str(EXAMPLE)],
            "directory and file": [str(tmp_path), str(EXAMPLE)]}[case]
    out = tmp_path / "out"
    assert main(["run", "--rules", "outdoor", *args, "--out", str(out)]) == 2
    r = capsys.readouterr()
    assert ("is given twice" if case == "given twice" else "would both write outdoor.ply and outdoor.json") in r.err
    assert not out.exists() and r.out == ""


@pytest.mark.slow
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_one_unreadable_scan_among_good_ones_the_others_are_written_exit_3(tmp_path, jobs):
    """The same with the scans one after the other (-j 1) and side by side (-j 2)."""
    broken = tmp_path / "broken.ply"
    broken.write_bytes(EXAMPLE.read_bytes()[:2000])
    out = tmp_path / "out"
    r = kbs_command("run", "--rules", "outdoor", "-j", jobs, str(broken), str(tmp_path / "missing.xyz"), str(EXAMPLE),
                    "--out", str(out))
    assert r.returncode == 3, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["outdoor.json", "outdoor.ply"]
    errors = r.stderr.strip().splitlines()
    assert len(errors) == 2 and "Traceback" not in r.stderr
    assert errors[0].startswith(f"kbs: error: {broken}") and errors[1] == f"kbs: error: {tmp_path / 'missing.xyz'}: no such file"
    table = _table(r.stdout)
    assert table[1].startswith("broken.ply ") and table[1].endswith("failed: exit code 3")
    assert table[2].startswith("missing.xyz ") and TIME_ROW.match(table[3])["name"] == "outdoor.ply"
    assert table[4].startswith("3 scans (2 failed): segment median ")


def _three_scans(tmp_path: Path) -> Path:
    """A folder of three scans: the two bundled scenes and the first turned and moved (an .npy)."""
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy(EXAMPLE, scans / "a.ply")
    shutil.copy(POLYHEDRAL, scans / "b.ply")
    X = read_cloud(EXAMPLE).xyz
    np.save(scans / "c.npy", X[:, [1, 0, 2]] * [1.0, -1.0, 1.0] + [100.0, -50.0, 2.0])
    return scans


def _written(out: Path, stem: str) -> tuple:
    """What a result pair holds apart from its run id and times: the points' arrays and the JSON's
    clusters and explanation."""
    from plyfile import PlyData

    v = PlyData.read(str(out / f"{stem}.ply"))["vertex"].data
    doc = json.loads((out / f"{stem}.json").read_text())
    return ({k: v[k].tolist() for k in v.dtype.names}, doc["clusters"], doc["explanation"], doc["label_names"])


@pytest.mark.slow
def test_several_scans_side_by_side_write_what_one_after_the_other_writes(tmp_path):
    """-j 2 on a folder of three scans segments two at a time, each in a process of its own: the
    same outputs as -j 1, what each scan prints in scan order, the table saying how many ran at once."""
    scans = _three_scans(tmp_path)
    runs = {j: kbs_command("run", "--rules", "outdoor", "-j", j, str(scans), "--out", str(tmp_path / f"o{j}"))
            for j in ("1", "2")}
    for j, r in runs.items():
        assert r.returncode == 0, (j, r.stderr)
        assert [m["path"] for m in map(SCAN_LINE.match, r.stdout.splitlines()) if m] == [
            str(scans / n) for n in ("a.ply", "b.ply", "c.npy")], r.stdout
        assert [TIME_ROW.match(line)["name"] for line in _table(r.stdout)[1:4]] == ["a.ply", "b.ply", "c.npy"]
        assert r.stdout.count("  time: ") == 3 and "Traceback" not in r.stderr
    assert ", 2 scans at a time (rule base loaded once" in _table(runs["2"].stdout)[4]
    assert "at a time" not in runs["1"].stdout
    for stem in ("a", "b", "c"):
        assert _written(tmp_path / "o1", stem) == _written(tmp_path / "o2", stem), stem


@pytest.mark.slow
def test_a_scan_process_that_dies_leaves_its_scan_to_the_command(tmp_path):
    """A scan process killed (out of memory, kill -9) breaks the pool: the scans it left are
    segmented by the command itself, with the same outputs, exit code 0."""
    scans = _three_scans(tmp_path)
    code = ("import os, sys, kbs.cli.run as r\n"
            "real = r._scan_in_worker\n"
            "def dying(scan, *a):\n"
            "    if scan.name == 'b.ply':\n        os._exit(9)\n"
            "    return real(scan, *a)\n"
            "r._scan_in_worker = dying\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    r = subprocess.run([sys.executable, "-c", code, "run", "--rules", "outdoor", "-j", "2", str(scans), "--out",
                        str(tmp_path / "o2")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    ref = kbs_command("run", "--rules", "outdoor", "-j", "1", str(scans / "b.ply"), "--out", str(tmp_path / "o1"))
    assert ref.returncode == 0, ref.stderr
    assert _written(tmp_path / "o1", "b") == _written(tmp_path / "o2", "b")
    assert sorted(p.name for p in (tmp_path / "o2").iterdir()) == ["a.json", "a.ply", "b.json", "b.ply",
                                                                    "c.json", "c.ply"]


@pytest.mark.slow
def test_a_sigterm_as_a_scan_process_is_forked_ends_it_without_a_traceback(tmp_path):
    """A SIGTERM that reaches a scan process between its fork and its start (which sets its own
    handler) waits, blocked, for that handler, which ends the idle process quietly; without the
    block the command's handler, inherited by fork, raised inside multiprocessing's start-up and
    printed a traceback. The command then segments the scans itself: exit code 0, every output."""
    scans = _three_scans(tmp_path)
    code = ("import multiprocessing.util, os, signal, sys\n"
            "parent = os.getpid()\n"
            "class Hook: pass\n"
            "hook = Hook()\n"
            "def term(_):\n"
            "    if os.getppid() == parent:  # the scan processes, not their split workers\n"
            "        os.kill(os.getpid(), signal.SIGTERM)\n"
            "multiprocessing.util.register_after_fork(hook, term)\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    r = subprocess.run([sys.executable, "-c", code, "run", "--rules", "outdoor", "-j", "2", str(scans), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["a.json", "a.ply", "b.json", "b.ply",
                                                                   "c.json", "c.ply"]


@pytest.mark.slow
def test_a_pool_broken_while_the_scans_are_submitted_leaves_them_to_the_command(tmp_path):
    """A scan process that dies before every scan is submitted (killed at its start) breaks the
    pool under the submissions: the submit itself raises BrokenProcessPool (it was an internal
    error); the scans not submitted are segmented by the command itself, exit code 0."""
    scans = _three_scans(tmp_path)
    code = ("import sys, concurrent.futures as cf\n"
            "from concurrent.futures.process import BrokenProcessPool\n"
            "real = cf.ProcessPoolExecutor.submit\n"
            "n = [0]\n"
            "def submit(self, fn, *a, **k):\n"
            "    n[0] += 1\n"
            "    if n[0] == 3:  # the start's task, the first scan, then the pool breaks\n"
            "        raise BrokenProcessPool('a child process terminated abruptly')\n"
            "    return real(self, fn, *a, **k)\n"
            "cf.ProcessPoolExecutor.submit = submit\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    r = subprocess.run([sys.executable, "-c", code, "run", "--rules", "outdoor", "-j", "2", str(scans), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["a.json", "a.ply", "b.json", "b.ply",
                                                                   "c.json", "c.ply"]


@pytest.mark.slow
def test_sigterm_stops_the_scan_processes_and_leaves_nothing_half_written(tmp_path):
    """SIGTERM to `kbs run -j 2` while two scans are segmented side by side: exit code 143, the scan
    processes end too (none left running), no output and no temporary file in the folder."""
    import os
    import signal
    import time

    scans = _three_scans(tmp_path)
    marks = tmp_path / "marks"
    marks.mkdir()
    code = ("import os, sys, time, pathlib, kbs.knowledge.segmenter as s\n"
            "def slow(self, *a, **k):\n"
            f"    pathlib.Path({str(marks)!r}, str(os.getpid())).write_text('')\n"
            "    time.sleep(120)\n"
            "s.Segmenter.segment = slow\n"
            "from kbs.cli.main import entry; sys.argv = ['kbs', *sys.argv[1:]]; entry()")
    out = tmp_path / "o"
    p = subprocess.Popen([sys.executable, "-c", code, "run", "--rules", "outdoor", "-j", "2", str(scans), "--out",
                          str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while len(list(marks.iterdir())) < 2 and p.poll() is None and time.monotonic() - t0 < 120:
        time.sleep(0.02)
    assert p.poll() is None, p.communicate()[1]
    workers = [int(m.name) for m in marks.iterdir()]
    assert len(workers) == 2 and p.pid not in workers
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143, (p.returncode, err)
    assert err.strip().splitlines()[-1] == "kbs: terminated (SIGTERM)", err
    assert "Traceback" not in err
    for pid in workers:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        else:
            raise AssertionError(f"scan process {pid} still running")
    assert not out.exists() or list(out.iterdir()) == []  # the folder the run created is removed with it


@pytest.mark.slow
def test_one_scan_prints_as_before_without_a_table(tmp_path):
    r = kbs_command("run", "--rules", "outdoor", "examples/data/outdoor.ply", "--out", str(tmp_path), cwd=ROOT)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 5
    assert lines[0] == "examples/data/outdoor.ply: 26,233 points, rule base 'outdoor' (divisive)"
    assert re.fullmatch(r"  \d+ clusters, \d+ splits, \d+ limits reached; points: ground [\d,]+, obstacle [\d,]+, "
                        r"noise [\d,]+", lines[1])
    assert lines[2] == ("  ground: cluster c0, it passes 'planar', 2.25 m from the sensor, normal [0.011, -0.021, 1.000], "
                        "1.3 deg from the fallback normal")
    assert re.fullmatch(r"  time: \d+\.\d\d s \(read \d+\.\d\d, segment \d+\.\d\d, write \d+\.\d\d\)", lines[3])
    assert lines[4] == f"wrote {tmp_path}/outdoor.ply and {tmp_path}/outdoor.json"


@pytest.mark.slow
def test_the_readme_several_scans_table_is_what_kbs_run_prints(tmp_path):
    """The README's `kbs run --rules outdoor examples/data` block: the same rows (scan, points,
    clusters; the times are this machine's) and the same last line but for its times (two scans
    at a time on a machine of two cores or more, as the README's)."""
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### Several scans, one rule base"):]
    shown = re.search(r"```\n\$ kbs run --rules outdoor examples/data --out kbs-out\n(.*?)```", section, re.S)[1]
    r = kbs_command("run", "--rules", "outdoor", "examples/data", "--out", str(tmp_path), cwd=ROOT)
    assert r.returncode == 0, r.stderr
    got, want = _table(r.stdout), _table(shown)
    assert len(got) == len(want) == 4
    for line_got, line_want in zip(got[1:3], want[1:3]):
        assert line_got.split()[:3] == line_want.split()[:3], (line_got, line_want)
    times = re.compile(r"\d+\.\d\d s")
    cores = kbs.knowledge.interpreter.available_cores()
    last = times.sub("T s", got[3]) if cores >= 2 else times.sub("T s", got[3]).replace(" (", ", 2 scans at a time (")
    assert last == times.sub("T s", want[3]), (got[3], want[3])


@pytest.mark.slow
def test_the_readme_python_example_runs():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### Several scans, one rule base"):]
    code, shown = re.search(r"```python\n(.*?)```\n\n```\n(.*?)```", section, re.S).groups()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    out, shown = r.stdout.splitlines(), shown.splitlines()
    assert out[0] == shown[0] and len(out) == len(shown) == 3  # the counts may move with the rules: the shape may not
    for line in out[1:]:
        assert re.fullmatch(r"examples/data/\w+\.ply: \d+ clusters, [\d,]+ ground points, \d+ noise", line), line


NEVER_CLOSED = """
import multiprocessing as mp, sys


def child(path, q):
    import kbs
    from kbs.io import read_cloud

    seg = kbs.Segmenter("outdoor", jobs=2)
    q.put(len(seg.segment(read_cloud(path).xyz).clusters))  # no close(): the process must still end


if __name__ == "__main__":
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=child, args=(sys.argv[1], q))
    p.start()
    print(q.get(timeout=300))
    p.join(120)
    print("exitcode", p.exitcode)
    if p.is_alive():
        p.kill()
"""


@pytest.mark.slow
def test_a_process_that_never_closes_its_segmenter_still_exits(tmp_path):
    """In a multiprocessing child (a benchmark, a Dask worker), multiprocessing joins the child's
    own children before Python's exit handlers stop the pool: idle split workers would be waited
    for for ever. The pool is stopped before that join."""
    script = tmp_path / "never_closed.py"
    script.write_text(NEVER_CLOSED)
    r = subprocess.run([sys.executable, str(script), str(EXAMPLE)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.split()
    assert int(lines[0]) > 1 and r.stdout.strip().endswith("exitcode 0"), r.stdout


def test_ctrl_c_inside_a_compiled_kernel_reaches_the_caller_as_ctrl_c(monkeypatch):
    """A KeyboardInterrupt inside a compiled kernel leaves the kernel's call as a SystemError
    caused by it; the loaded segmenter gives its caller the KeyboardInterrupt, wherever in the
    run it came (here in the engine's Gath-Geva fit, outside any predicate), and stays usable."""
    import importlib

    u = importlib.import_module("kbs.inference.ufp_onc")  # the module (kbs.inference.ufp_onc is also a function's name)

    def gg_fit(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("CPUDispatcher(<function gg_run>) returned a result with an exception set") from exc

    rng = np.random.default_rng(0)
    X = rng.normal(size=(2000, 3)) * [5, 5, 0.05]
    seg = kbs.Segmenter("outdoor", jobs=1)
    original = u.gg_fit
    monkeypatch.setattr(u, "gg_fit", gg_fit)
    with pytest.raises(KeyboardInterrupt):
        seg.segment(X)
    monkeypatch.setattr(u, "gg_fit", original)
    assert seg.segment(X).label.shape == (2000,)


@pytest.mark.parametrize("where", [[1e4, 1e4, 1e4], [0.0, 0.0, -3e3]])
def test_a_far_outlier_is_set_aside_as_noise_and_said(tmp_path, where):
    """One glitch point kilometres away made the first partition a single cluster (its new
    prototype took the outlier alone, which died): the whole scene one obstacle, no ground. It is
    set aside as noise, the explanation and the command say so, and every other point gets the
    result of the cloud without it."""
    X = read_cloud(EXAMPLE).xyz
    seg = kbs.Segmenter("outdoor", jobs=1)
    clean = seg.segment(X)
    dirty = np.vstack([X[:7], [where], X[7:]])
    res = seg.segment(dirty)
    keep = np.ones(len(dirty), bool)
    keep[7] = False
    for name in ("cluster", "label", "membership"):
        assert np.array_equal(getattr(res, name)[keep], getattr(clean, name)), name
    assert res.cluster[7] == -1 and res.label[7] == -1 and res.membership[7] == 0
    assert any(n.startswith("1 point set aside as noise before the partition") for n in res.explanation.notes)
    assert res.summary()["points_per_label"]["ground"] == clean.summary()["points_per_label"]["ground"] > 0
    path = tmp_path / "glitch.npy"
    np.save(path, dirty)
    r = kbs_command("run", "--rules", "outdoor", str(path), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    assert "1 point set aside as noise before the partition" in r.stderr + r.stdout


def test_points_within_reach_are_not_outliers():
    """A point beyond the central 98 % of the cloud by less than twice its extent is a point of
    the scene (a far building, a tree top): nothing is set aside, the result is the plain run's."""
    from kbs.knowledge.segmentation import far_outliers

    X = read_cloud(EXAMPLE).xyz
    lo, hi = np.percentile(X, [1, 99], axis=0)
    near = hi + 1.9 * (hi - lo).max()
    assert far_outliers(np.vstack([X, near])) is None
    assert far_outliers(np.vstack([X, hi + 2.1 * (hi - lo).max()]))[0].sum() == 1


def _outdoor_with(tmp_path, far: str) -> Path:
    """The shipped outdoor rules with ``scene.far_outliers`` set (a YAML value)."""
    text = (ROOT / "rules" / "outdoor.yaml").read_text(encoding="utf-8")
    assert "\nscene:\n" in text
    path = tmp_path / "far.yaml"
    path.write_text(text.replace("\nscene:\n", f"\nscene:\n  far_outliers: {far}\n", 1), encoding="utf-8")
    return path


def test_far_outliers_follow_the_rule_base_s_setting(tmp_path):
    """``scene.far_outliers``: ``false`` sets nothing aside (the glitch stays in the cloud and is
    labelled with the rest), a factor moves the reach (a point 3 x the central box's side beyond it
    is a far outlier at factor 2, not at 4); the default is the factor 2 the shipped rules use."""
    X = read_cloud(EXAMPLE).xyz
    lo, hi = np.percentile(X, [1, 99], axis=0)
    dirty = np.vstack([X, hi + 3.0 * (hi - lo).max()])
    assert load_rule_base("outdoor").far_outliers == 2.0
    off = load_rule_base(_outdoor_with(tmp_path, "false"))
    assert off.far_outliers is None
    res = kbs.Segmenter(off, jobs=1).segment(dirty)
    assert res.label[-1] >= 0 and not any("set aside as noise" in n for n in res.explanation.notes)
    wide = load_rule_base(_outdoor_with(tmp_path, "{factor: 4}"))
    assert wide.far_outliers == 4.0
    from kbs.knowledge.segmentation import far_outliers

    assert far_outliers(dirty, 4.0) is None and far_outliers(dirty, 2.0)[0].sum() == 1
    assert far_outliers(dirty, None) is None


@pytest.mark.parametrize("value, problem", [("{factor: 0}", "factor"), ("{factor: -1}", "factor"),
                                            ("{factor: .nan}", "not a finite number"), ("true", "far_outliers"),
                                            ("{reach: 2}", "reach")])
def test_a_bad_far_outliers_setting_is_a_positioned_rule_file_error(tmp_path, value, problem):
    path = _outdoor_with(tmp_path, value)
    with pytest.raises(RuleFileError) as info:
        load_rule_base(path)
    message = str(info.value)
    line = path.read_text(encoding="utf-8").split("\n").index(f"  far_outliers: {value}") + 1
    assert f"far.yaml:{line}:" in message and problem in message, message


_SIGTERM_AT_FORK = r"""
import multiprocessing.util, os, signal, sys
import kbs
from kbs.cli.main import _on_sigterm
from kbs.knowledge import load_rule_base
from kbs.knowledge.interpreter import Interpreter

signal.signal(signal.SIGTERM, _on_sigterm)  # the kbs command's handler, which a forked worker inherits


class Hook:
    pass


hook = Hook()  # SIGTERM arrives in a worker after the fork, before the pool's initializer runs
multiprocessing.util.register_after_fork(hook, lambda _: os.kill(os.getpid(), signal.SIGTERM))
it = Interpreter(load_rule_base("outdoor"), jobs=2)
it.start_workers()  # the workers die at their start: no pool kept, the splits are done here
print("pool kept:", it._pool is not None)
blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
print("parent blocks SIGTERM:", signal.SIGTERM in blocked, "SIGINT:", signal.SIGINT in blocked)
"""


@pytest.mark.skipif(not hasattr(__import__("signal"), "pthread_sigmask"), reason="no signal masks on this platform")
def test_a_sigterm_between_a_workers_fork_and_its_start_ends_it_without_a_traceback():
    """The split workers are forked with SIGINT and SIGTERM blocked, and unblock them once their
    start has set their own handlers: a SIGTERM that arrives in between (the command being stopped
    while it forks) ends the worker as SIG_DFL does, not through the command's handler inherited by
    fork, which raised inside multiprocessing's start-up and printed a traceback."""
    r = subprocess.run([sys.executable, "-c", _SIGTERM_AT_FORK], capture_output=True, text=True, timeout=120)
    assert "Traceback" not in r.stderr, r.stderr
    assert "Terminated" not in r.stderr, r.stderr
    assert r.returncode == 0, r.stderr
    assert "pool kept: False" in r.stdout, (r.stdout, r.stderr)
    assert "parent blocks SIGTERM: False SIGINT: False" in r.stdout  # the mask is the parent's own again


def test_the_split_workers_run_with_no_signal_blocked():
    from kbs.knowledge.interpreter import Interpreter

    it = Interpreter(load_rule_base("outdoor"), jobs=2)
    if it.jobs < 2:
        pytest.skip("one core: no split workers")
    import signal

    blocked = it._worker_pool().submit(signal.pthread_sigmask, signal.SIG_BLOCK, []).result()
    it.close()
    assert signal.SIGTERM not in blocked and signal.SIGINT not in blocked
