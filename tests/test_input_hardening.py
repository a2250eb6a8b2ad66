"""Bad inputs found by a fuzzing pass (session 31) that reached a traceback (exit 1) or gave a
silently wrong result: units declared as 0, -1, NaN or 1e-300 metres, two contradicting units
comments, JSON nested deeper than Python's parser follows, result files whose cluster or label
values kbs cannot have written, a result PLY beside another run's JSON in a Hoover-only
evaluation. Each goes through the real command (or the reader it calls) and asserts the exit code
and the message."""
from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from kbs.errors import ParameterError
from kbs.io import write_ply
from kbs.maps.poses import PoseFileError, read_json_poses
from kbs.units import unit_from_metres, wkt_units
from scenes import ground_and_rocks
from test_cli import kbs

EXAMPLE_PLY = Path(__file__).parent.parent / "examples" / "data" / "outdoor.ply"
PROJ = ('PROJCS["local",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
        'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
        'PARAMETER["central_meridian",15],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],'
        'PARAMETER["false_northing",0],UNIT["{name}",{factor}]]')


@pytest.mark.parametrize("factor", [0.0, -1.0, math.nan, 1e-300, 1e300])
def test_a_unit_that_is_not_a_plausible_length_is_refused(factor):
    with pytest.raises(ParameterError, match=r"a unit must be a number of metres between 1e-09 and 1e\+09"):
        unit_from_metres(factor, "odd")
    with pytest.raises(ParameterError, match="the unit of length 'odd' is"):
        wkt_units(PROJ.format(name="odd", factor=factor), "a test")


def test_usual_units_are_still_read():
    assert unit_from_metres(0.3048).name == "ft" and unit_from_metres(1.0).name == "m"
    assert wkt_units(PROJ.format(name="foot", factor=0.3048), "a test").horizontal.name == "ft"
    assert unit_from_metres(201.168, "furlong").metres == 201.168


def _ply(path: Path, comments: list[str]) -> Path:
    X, _ = ground_and_rocks(seed=3)
    write_ply(path, X[::4], comments=comments)
    return path


@pytest.mark.parametrize("factor", ["0", "-1", "nan"])
def test_kbs_run_refuses_a_ply_whose_crs_comment_declares_a_unit_of_no_length(tmp_path, factor):
    scan = _ply(tmp_path / "odd.ply", [f"crs {PROJ.format(name='u', factor=factor)}"])
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3, r.stderr
    assert f"{scan}: the unit of length 'u' is" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_two_units_comments_that_disagree_are_refused(tmp_path):
    scan = _ply(tmp_path / "two.ply", ["units mm", "units m"])
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3
    assert f"{scan}: the PLY header's comments declare two units, 'units mm' and 'units m': keep one" in r.stderr
    same = _ply(tmp_path / "same.ply", ["units m", "units M"])  # the same unit twice is one declaration
    assert kbs("run", "--rules", "outdoor", str(same), "--out", str(tmp_path / "o2")).returncode == 0


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> Path:
    """A kbs result pair (result.ply, result.json) and its ground truth (gt.npy)."""
    folder = tmp_path_factory.mktemp("result")
    X, truth = ground_and_rocks(seed=3)
    (folder / "scan").mkdir()
    write_ply(folder / "scan" / "result_in.ply", X[::4])
    np.save(folder / "gt.npy", truth[::4].astype(np.int64))
    r = kbs("run", "--rules", "outdoor", str(folder / "scan" / "result_in.ply"), "--out", str(folder))
    assert r.returncode == 0, r.stderr
    return folder


def _copy(result: Path, tmp_path: Path, name: str = "res") -> Path:
    shutil.copy(result / "result_in.ply", tmp_path / f"{name}.ply")
    shutil.copy(result / "result_in.json", tmp_path / f"{name}.json")
    return tmp_path / f"{name}.ply"


def _set_field(ply: Path, field: str, values: np.ndarray) -> None:
    data = PlyData.read(str(ply))
    vertex = data["vertex"].data.copy()
    vertex[field][: len(values)] = values
    PlyData([PlyElement.describe(vertex, "vertex")], text=data.text, byte_order=data.byte_order,
            comments=data.comments).write(str(ply))


def test_a_result_json_nested_too_deep_is_an_unreadable_file_not_a_crash(result, tmp_path):
    res = _copy(result, tmp_path)
    js = res.with_suffix(".json")
    doc = js.read_text()
    js.write_text(doc[:-1].rstrip() + ', "zz": ' + "[" * 100_000 + "]" * 100_000 + "}")
    for args in (("explain", str(js)), ("eval", str(res), str(result / "gt.npy"), "--ground-values", "0")):
        r = kbs(*args)
        assert r.returncode == 3, (args, r.stderr)
        assert f"{js}: not a kbs result file (its JSON nests deeper than Python's parser can follow)" in r.stderr


def test_poses_nested_too_deep_are_a_pose_file_error(tmp_path):
    poses = tmp_path / "poses.json"
    poses.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(PoseFileError, match="nests deeper than Python's parser can follow"):
        read_json_poses(poses)


def test_eval_refuses_cluster_values_kbs_cannot_have_written(result, tmp_path):
    res = _copy(result, tmp_path)
    _set_field(res, "scalar_cluster", np.array([5, -7, -7]))
    r = kbs("eval", str(res), str(result / "gt.npy"))
    assert r.returncode == 3
    assert (f"{res}: not a kbs result: its per-vertex 'cluster' holds -7 at vertex 1 (2 such): kbs writes "
            "integers from -1 up") in r.stderr


def test_eval_refuses_a_label_beyond_the_json_label_names(result, tmp_path):
    res = _copy(result, tmp_path)
    names = json.loads(res.with_suffix(".json").read_text())["label_names"]
    _set_field(res, "scalar_label", np.array([len(names) + 5]))
    r = kbs("eval", str(res), str(result / "gt.npy"), "--ground-values", "0")
    assert r.returncode == 3
    assert (f"{res}: its per-vertex 'label' holds {len(names) + 5}, but {res.with_suffix('.json')} names "
            f"{len(names)} labels") in r.stderr


def test_a_hoover_only_eval_refuses_the_json_of_another_run_too(result, tmp_path):
    res = _copy(result, tmp_path)
    js = res.with_suffix(".json")
    doc = json.loads(js.read_text())
    doc["run_id"] = "deadbeef"
    js.write_text(json.dumps(doc))
    r = kbs("eval", str(res), str(result / "gt.npy"))
    assert r.returncode == 3 and f"{js}: does not belong with {res.name}: run id deadbeef in the JSON" in r.stderr
    assert kbs("eval", str(_copy(result, tmp_path, "good")), str(result / "gt.npy")).returncode == 0


@pytest.mark.parametrize("args", [("run", "--rules", "outdoor", ""), ("run", "--rules", "outdoor", "x.ply", "--out", ""),
                                  ("eval", "", "gt.npy"), ("map", "--rules", "outdoor", "", "--poses", "p.txt")])
def test_an_empty_path_is_a_usage_error_not_the_current_folder(tmp_path, args):
    r = kbs(*args, cwd=tmp_path)
    assert r.returncode == 2 and "'' is an empty path: give a file or folder name" in r.stderr, r.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("factor", ["0", "nan", "-0.3048"])
def test_kbs_run_refuses_a_las_whose_crs_declares_a_unit_of_no_length(tmp_path, factor):
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    X, _ = ground_and_rocks(seed=3)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([1e-3, 1e-3, 1e-3]), np.zeros(3)
    header.vlrs.append(WktCoordinateSystemVlr(PROJ.format(name="odd", factor=factor)))
    header.global_encoding.wkt = True
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[::4, 0], X[::4, 1], X[::4, 2]
    scan = tmp_path / "odd.las"
    las.write(scan)
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3, r.stderr
    assert f"{scan}: its CRS: the unit of length 'odd' is" in r.stderr and "Traceback" not in r.stderr
    assert r.stderr.count("\n") == 1, r.stderr  # one line: no numpy warning before it


def test_a_folder_reports_its_broken_links_and_fifos_instead_of_skipping_them(tmp_path):
    import os

    folder = tmp_path / "scans"
    folder.mkdir()
    _ply(folder / "a.ply", [])
    (folder / "b.ply").symlink_to(tmp_path / "gone.ply")
    os.mkfifo(folder / "c.ply")  # never opened: reading it would wait for a writer
    r = kbs("run", "--rules", "outdoor", str(folder), "--out", str(tmp_path / "o"))
    assert r.returncode == 3, r.stderr
    assert f"{folder / 'b.ply'}: no such file: a broken symbolic link" in r.stderr
    assert f"{folder / 'c.ply'}: not a regular file but a FIFO (named pipe)" in r.stderr
    assert (tmp_path / "o" / "a.ply").is_file()  # the good scan is segmented all the same


def test_jobs_beyond_the_cores_start_no_more_processes_than_cores(tmp_path):
    """`kbs run -j 100000` forked a hundred thousand split processes (the machine ground to a halt);
    the processes are capped at the available cores, with a note, and the result is the same."""
    from kbs.knowledge.interpreter import available_cores

    cores = available_cores()
    scan = _ply(tmp_path / "a.ply", [])
    r = kbs("run", "--rules", "outdoor", "-j", "100000", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    assert f"note: -j 100000: {cores} core{'s' if cores > 1 else ''} available, so at most {cores}" in r.stderr
    assert "note: -j" not in kbs("-q", "run", "--rules", "outdoor", "-j", "100000", str(scan), "--out",
                                 str(tmp_path / "q")).stderr


# -- the other commands (a second fuzzing pass) ----------------------------------------------------

def test_a_name_too_long_for_the_file_system_is_exit_3_naming_it(tmp_path):
    long = tmp_path / ("x" * 300 + ".yaml")
    r = kbs("run", "--rules", str(long), str(EXAMPLE_PLY), "--out", str(tmp_path / "o"))
    assert r.returncode == 3 and r.stderr.startswith(f"kbs: error: {long}: File name too long"), r.stderr


@pytest.mark.parametrize("args, message", [
    (("synth", "outdoor", "--resolution", "20000x20000"), "20,000 x 20,000 = 400,000,000 rays, more than the 4,000,000"),
    (("synth", "abw", "--boxes", "99999999999999999999"), "'--boxes': 99999999999999999999 is not in the range 0<=x<=1000"),
    (("synth", "outdoor", "--frames", "3", "--step", "1e300"), "'--step': 1e+300 is not in the range 0<x<=100"),
    (("synth", "outdoor", "--noise", "inf"), "'--noise': 'inf' is not a finite number"),
    (("synth", "outdoor", "--out", "scene.json"), "scene.json: the scene is written as PLY: give a .ply file name"),
    (("cluster", "EXAMPLE", "--out", "clusters.json"), "clusters.json: the clusters are written as PLY"),
])
def test_sizes_that_would_exhaust_the_machine_or_crash_are_usage_errors(tmp_path, args, message):
    args = tuple(str(EXAMPLE_PLY) if a == "EXAMPLE" else a for a in args)
    if "--out" not in args:
        args += ("--out", str(tmp_path / ("d" if "--frames" in args else "s.ply")))
    r = kbs(*args, cwd=tmp_path)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not any(tmp_path.iterdir())


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("drive") / "d"
    r = kbs("-q", "synth", "outdoor", "--frames", "2", "--resolution", "60x120", "--out", str(d))
    assert r.returncode == 0, r.stderr
    return d


def test_a_map_of_more_cells_than_memory_holds_is_refused_before_it_is_allocated(drive, tmp_path):
    r = kbs("-q", "map", "--rules", "outdoor", str(drive / "scans"), "--poses", str(drive / "poses.txt"),
            "--out", str(tmp_path / "m"), "--cell-size", "0.001")
    assert r.returncode == 6 and "GiB of layers, more than the 4 GiB a map may take: give a larger --cell-size" in r.stderr


def test_map_refuses_its_scans_folder_as_output_and_a_frame_given_twice(drive, tmp_path):
    scans = drive / "scans"
    before = sorted(p.name for p in scans.iterdir())
    r = kbs("-q", "map", "--rules", "outdoor", str(scans), "--poses", str(drive / "poses.txt"), "--out", str(scans))
    assert r.returncode == 2 and "is a folder of the drive's scans: write the map elsewhere" in r.stderr
    assert sorted(p.name for p in scans.iterdir()) == before
    r = kbs("-q", "map", "--rules", "outdoor", str(scans), str(scans / "000000.ply"), "--out", str(tmp_path / "m"))
    assert r.returncode == 2 and f"{scans / '000000.ply'} is given twice: give each frame once" in r.stderr


def _tune_inputs(tmp_path: Path) -> list[str]:
    X, truth = ground_and_rocks(seed=3)
    args = []
    for i in range(2):
        write_ply(tmp_path / f"s{i}.ply", X[i::8])
        np.save(tmp_path / f"g{i}.npy", truth[i::8].astype(np.int64))
        args += [str(tmp_path / f"s{i}.ply"), str(tmp_path / f"g{i}.npy")]
    return args


def test_tune_refuses_wrong_output_kinds_missing_folders_and_a_truth_without_ground(tmp_path):
    rules = str(Path(__file__).parent.parent / "examples" / "rules" / "outdoor-tune.yaml")
    pairs = _tune_inputs(tmp_path)
    base = ("tune", "--rules", rules, *pairs, "--max-evals", "2")
    r = kbs(*base, "--ground-values", "0", "--out", str(tmp_path / "new.json"))
    assert r.returncode == 2 and "new.json: give a .yaml or .yml file name" in r.stderr
    r = kbs(*base, "--ground-values", "0", "--out", str(tmp_path / "new.yaml"), "--report", str(tmp_path / "no" / "r.json"))
    assert r.returncode == 2 and f"no such folder: {tmp_path / 'no'}" in r.stderr
    r = kbs(*base, "--ground-values", "7", "--out", str(tmp_path / "new.yaml"))
    assert r.returncode == 2 and "no scan has a ground point in its ground truth (--ground-values 7)" in r.stderr
    assert not (tmp_path / "new.yaml").exists() and not (tmp_path / "new.json").exists()


@pytest.mark.parametrize("mark, message", [
    ("[]", "checks.planar.tune: [] is too short"),  # it crashed: min() of an empty list
    ("[0.05, 0.05, 0.05]", "checks.planar.tune: [0.05, 0.05, 0.05] has non-unique elements"),  # 3 "settings"
])
def test_a_tune_mark_of_fewer_than_two_values_or_repeated_ones_is_a_rule_file_error(tmp_path, mark, message):
    text = (Path(__file__).parent.parent / "examples" / "rules" / "outdoor-tune.yaml").read_text()
    rules = tmp_path / "r.yaml"
    rules.write_text(text.replace("tune: [0.04, 0.05, 0.07]", f"tune: {mark}", 1))
    r = kbs("rules", "check", str(rules))
    assert r.returncode == 4 and f"{rules}:46:11: {message}" in r.stderr, r.stderr


def test_a_bin_that_is_an_npy_array_or_integer_labels_is_refused(tmp_path):
    X, _ = ground_and_rocks(seed=3)
    npy = tmp_path / "points.npy"
    np.save(npy, X[:4000].astype(np.float32))
    r = kbs("run", "--rules", "outdoor", "--in-format", "bin", str(npy), "--out", str(tmp_path / "o"))
    assert r.returncode == 3 and f"{npy}: an .npy array, not float32 records: give --in-format npy" in r.stderr
    labels = tmp_path / "scan.label"
    np.arange(4000, dtype=np.uint32).tofile(labels)  # SemanticKITTI's labels: one uint32 a point
    r = kbs("run", "--rules", "outdoor", "--in-format", "bin", str(labels), "--out", str(tmp_path / "o"))
    assert r.returncode == 3 and "x, y, z values are subnormal" in r.stderr and "(a .label file?)" in r.stderr


@pytest.mark.parametrize("key, value, message", [
    ("n_points", 5, "'n_points' is 5 and res.ply holds"),
    ("n_points", -5, "('n_points' is not a number of points)"),
    ("sensor", [0.0, float("nan"), 1.0], "('sensor' is not 3 finite numbers)"),
    ("label_names", ["ground", "ground"], "('label_names' is not a list of distinct names)"),
    ("label_names", ["sky", "sea"], ": 'ground' is not one of its label_names)"),
])
def test_a_result_json_that_contradicts_its_points_or_itself_is_refused(result, tmp_path, key, value, message):
    from kbs.errors import CloudFileError
    from kbs.io.result import read_result_pair

    res = _copy(result, tmp_path)
    js = res.with_suffix(".json")
    doc = json.loads(js.read_text())
    doc[key] = value
    js.write_text(json.dumps(doc))
    with pytest.raises(CloudFileError, match=re.escape(message)):
        read_result_pair(js)


def test_a_file_option_given_a_folder_name_ending_with_a_slash_is_a_usage_error(tmp_path):
    r = kbs("synth", "abw", "--out", "sy/", cwd=tmp_path)  # it wrote ./sy.range and ./sy.gt-seg
    assert r.returncode == 2 and "'sy/' names a folder (it ends with '/'): give a file name." in r.stderr
    assert not any(tmp_path.iterdir())


def test_a_wide_cloud_too_sparse_for_its_tiles_runs_whole_with_a_note(tmp_path):
    """simple.las (1,065 points over 4.6 km) was cut into 764 tiles of about one point by the
    airborne rules' limits.tile, and every point came out noise."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(0, 5000, 2000), rng.uniform(0, 5000, 2000), rng.normal(100, 0.5, 2000)]
    scan = tmp_path / "sparse.ply"
    write_ply(scan, X, comments=["units m"])
    r = kbs("run", "--rules", "airborne", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    assert ("but its 2,000 points would average 1.5 in each tile of 100 m that holds any, fewer than "
            "limits.min_points (30): it runs whole") in r.stderr
    assert "tiles:" not in r.stdout


# --- session 32: what the fuzzing passes found and session 31 left -------------------------------

ROOT = Path(__file__).parent.parent


def test_rules_show_validates_what_it_prints_and_loads_the_plugins(tmp_path):
    """`kbs rules show FILE` printed any file (/etc/passwd, a half-written rule file) as if it were
    a rule base, and ignored --plugin; it now validates first: exit 4 with the positioned problems,
    nothing on standard output; a plugin's predicates are known with --plugin."""
    notes = tmp_path / "notes.txt"
    notes.write_text("root:x:0:0:root:/root:/bin/bash\n")
    r = kbs("rules", "show", str(notes))
    assert r.returncode == 4 and r.stdout == "", r.stdout
    assert f"{notes}:1:1: a rule base is a mapping" in r.stderr and "Traceback" not in r.stderr
    poles, plugin = ROOT / "examples" / "rules" / "poles.yaml", ROOT / "examples" / "plugins" / "elongation.py"
    r = kbs("rules", "show", str(poles))
    assert r.returncode == 4 and r.stdout == ""
    assert "unknown predicate 'elongation'" in r.stderr and "--plugin FILE" in r.stderr
    r = kbs("rules", "show", str(poles), "--plugin", str(plugin))
    assert r.returncode == 0, r.stderr
    assert r.stdout.rstrip("\n").splitlines()[1:] == poles.read_text(encoding="utf-8").rstrip("\n").splitlines()[1:]
    r = kbs("rules", "show", str(poles), "--engine", "--plugin", str(plugin))
    assert r.returncode == 0 and r.stdout.startswith("engine settings of 'poles'"), r.stderr


def test_a_failed_run_leaves_no_new_output_folder_and_keeps_what_it_wrote(tmp_path):
    """A `kbs run` that failed used to leave the --out folder it had created, empty. The folders it
    created are removed when nothing was written in them; a folder that was there stays, and so
    do the results of the scans that succeeded beside a failed one."""
    bad = tmp_path / "bad.xyz"
    bad.write_text("garbage\n")
    r = kbs("run", "--rules", "outdoor", str(bad), "--out", str(tmp_path / "a" / "b" / "c"))
    assert r.returncode == 3 and "bad.xyz" in r.stderr
    assert not (tmp_path / "a").exists()
    (tmp_path / "there").mkdir()
    r = kbs("run", "--rules", "outdoor", str(bad), "--out", str(tmp_path / "there"))
    assert r.returncode == 3 and (tmp_path / "there").is_dir() and not any((tmp_path / "there").iterdir())
    r = kbs("-q", "run", "--rules", "outdoor", str(bad), str(EXAMPLE_PLY), "--out", str(tmp_path / "d"))
    assert r.returncode == 3
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == ["outdoor.json", "outdoor.ply"]


def test_a_library_warning_on_a_file_that_reads_names_the_file_once(tmp_path):
    """laspy's "There is an ExtraByteVlr but ..." (a LAS file whose extra-bytes VLR describes no
    bytes), from a read that succeeds, printed without the file's name, once for each time the
    header was read. It now names the file, once."""
    laspy = pytest.importorskip("laspy")
    X, _ = ground_and_rocks(seed=3)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = np.array([0.001] * 3), X.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.vlrs.append(laspy.VLR(user_id="LASF_Spec", record_id=4, record_data=bytes(range(192))))
    scan = tmp_path / "extra.las"
    las.write(str(scan))
    for rules in ("outdoor", "airborne"):  # airborne reads the header first, for its tiles
        r = kbs("-q", "run", "--rules", rules, str(scan), "--out", str(tmp_path / rules))
        assert r.returncode == 0, r.stderr
        lines = [x for x in r.stderr.splitlines() if "ExtraByteVlr" in x]
        assert lines == [f"kbs: {scan}: There is an ExtraByteVlr but the header.point_size matches the point size "
                         "without extra bytes. The extra bytes vlr info will be ignored"], r.stderr


def _raw_ply(path: Path, declared: str, X: np.ndarray) -> Path:
    """A binary PLY of float x, y, z whose header says ``declared`` whatever order ``X``'s bytes are in."""
    head = (f"ply\nformat {declared} 1.0\nelement vertex {len(X)}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    path.write_bytes(head + X.tobytes())
    return path


@pytest.mark.parametrize("declared, written", [("binary_big_endian", "<f4"), ("binary_little_endian", ">f4")])
def test_a_ply_whose_header_names_the_wrong_byte_order_is_refused(tmp_path, declared, written):
    X = ground_and_rocks(seed=3)[0].astype(written)
    scan = _raw_ply(tmp_path / "swapped.ply", declared, X)
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3, r.stderr
    assert f"{scan}: the header says 'format {declared}', but its x, y, z read as binary_" in r.stderr
    assert "correct the header's format line" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("declared, written", [("binary_big_endian", ">f4"), ("binary_little_endian", "<f4")])
def test_a_ply_in_either_byte_order_it_declares_is_read(tmp_path, declared, written):
    from kbs.io import read_cloud

    X = ground_and_rocks(seed=3)[0]
    pc = read_cloud(_raw_ply(tmp_path / "fine.ply", declared, X.astype(written)))
    assert np.array_equal(pc.xyz, X.astype(np.float32).astype(np.float64))


def test_a_ply_of_far_coordinates_in_its_declared_order_is_read(tmp_path):
    """Coordinates beyond the plausible in the declared order but no better in the other (a
    damaged file, not a swapped one) are read; what reads them says what is wrong."""
    from kbs.io import read_cloud

    X = np.full((100, 3), 3e38, dtype=">f4")
    X[:50] = 1.0
    pc = read_cloud(_raw_ply(tmp_path / "far.ply", "binary_big_endian", X))
    assert pc.xyz.shape == (100, 3)
