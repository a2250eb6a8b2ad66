"""Safe outputs and clear input errors, through the real command: result pairs written whole or not
at all (a full disk, Ctrl-C, a kill), a run id that ties the PLY to its JSON, no output over an
input or over another program's file, the output folder checked before any segmentation, strict
JSON, progress lines on a stderr that is not a terminal, symbolic link loops and unreadable inputs,
and the label files beside scans in a folder.

Most tests call the entry point in-process (``kbs.cli.main.main``, as the command does) so that a
writer can be made to fail half-way with ``monkeypatch``; the others start the real command.
"""
from __future__ import annotations

import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import plyfile
import pytest

from kbs.cli.main import main
from kbs.io import read_cloud, write_ply
from test_cli import EXAMPLE, ROOT, kbs

RUN = ["run", "--rules", "outdoor", "-j", "1"]
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _strict_json(text: str):
    def refuse(token: str):
        raise ValueError(f"not strict JSON: {token}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def good_pair(tmp_path_factory) -> Path:
    """A folder holding the result pair of `kbs run` on the bundled example."""
    out = tmp_path_factory.mktemp("good")
    assert main(["-q", *RUN, str(EXAMPLE), "--out", str(out)]) == 0
    return out


@pytest.fixture()
def out(good_pair, tmp_path) -> Path:
    """A fresh copy of the good pair: the previous result a failing run must leave intact."""
    folder = tmp_path / "out"
    shutil.copytree(good_pair, folder)
    return folder


def _half_then(exc: BaseException):
    """A PlyData.write that writes the first half of the file, then raises ``exc``."""
    write = plyfile.PlyData.write

    def half(self, stream):
        import io

        buffer = io.BytesIO()
        write(self, buffer)
        data = buffer.getvalue()
        stream.write(data[: len(data) // 2])
        stream.flush()
        raise exc

    return half


# -- 1. a result appears whole or not at all -------------------------------------------------------


def test_a_full_disk_while_writing_the_ply_leaves_the_previous_pair_intact(out, monkeypatch, capsys):
    before = _snapshot(out)
    monkeypatch.setattr(plyfile.PlyData, "write", _half_then(ENOSPC))
    assert main([*RUN, "--sensor", "0,0,5", str(EXAMPLE), "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert f"kbs: error: {out / 'outdoor.ply'}: cannot write: No space left on device" in err
    assert "Traceback" not in err
    assert _snapshot(out) == before  # the same two files, byte for byte, and no temporary file left


def test_a_full_disk_while_writing_the_json_leaves_the_previous_pair_intact(out, monkeypatch, capsys):
    import kbs.io.result

    def half(stream, data):
        stream.write(data[: len(data) // 2])
        raise ENOSPC

    before = _snapshot(out)
    monkeypatch.setattr(kbs.io.result, "_write_json_bytes", half)
    assert main([*RUN, str(EXAMPLE), "--out", str(out)]) == 3
    assert f"{out / 'outdoor.json'}: cannot write: No space left on device" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_ctrl_c_between_the_two_files_leaves_the_previous_pair(out, monkeypatch, capsys):
    """Ctrl-C once the PLY is written, while the JSON is being made: neither file changes (it
    used to leave the new PLY beside the old JSON, and `kbs render` drew them together)."""
    dumps = json.dumps

    def interrupted(obj, *args, **kwargs):
        if isinstance(obj, dict) and "explanation" in obj:
            raise KeyboardInterrupt
        return dumps(obj, *args, **kwargs)

    before = _snapshot(out)
    monkeypatch.setattr(json, "dumps", interrupted)
    assert main([*RUN, "--color-by", "label", str(EXAMPLE), "--out", str(out)]) == 130  # another PLY
    assert "kbs: aborted" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_an_error_in_the_writer_removes_its_temporary_files_and_keeps_the_old_file(tmp_path, monkeypatch):
    """The library writer alone (write_ply): the same guarantee for any exception."""
    path = tmp_path / "a.ply"
    write_ply(path, np.zeros((10, 3)))
    before = path.read_bytes()
    monkeypatch.setattr(plyfile.PlyData, "write", _half_then(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        write_ply(path, np.ones((1000, 3)))
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["a.ply"]


@pytest.mark.slow
def test_a_kill_during_the_write_leaves_the_previous_pair_intact(out):
    """SIGKILL half-way through the PLY (no cleanup can run): the previous pair is untouched and
    still renders; at most a hidden temporary file is left beside it."""
    before = _snapshot(out)
    script = textwrap.dedent(f"""
        import os, signal, io, plyfile
        from kbs.cli.main import main
        write = plyfile.PlyData.write
        def half(self, stream):
            buffer = io.BytesIO(); write(self, buffer); data = buffer.getvalue()
            stream.write(data[: len(data) // 2]); stream.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        plyfile.PlyData.write = half
        main(["run", "--rules", "outdoor", "-j", "1", {str(EXAMPLE)!r}, "--out", {str(out)!r}])
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    after = _snapshot(out)
    assert {k: v for k, v in after.items() if not k.startswith(".")} == before
    assert all(re.fullmatch(r"\.outdoor\.kbs-tmp-[0-9a-f]{8}\.ply", k) for k in after if k.startswith("."))
    r = kbs("render", str(out / "outdoor.json"), "--kind", "map", "--out", str(out / "map.png"))
    assert r.returncode == 0, r.stderr


def test_the_two_files_of_a_result_carry_the_same_run_id(out):
    doc = json.loads((out / "outdoor.json").read_text())
    header = (out / "outdoor.ply").read_bytes()[:2000].split(b"end_header")[0].decode("ascii")
    assert re.fullmatch(r"[0-9a-f]{32}", doc["run_id"]) and (doc["format"], doc["version"]) == ("kbs-result", "1.1")
    assert f"comment kbs_run_id {doc['run_id']}\n" in header


def test_a_ply_and_a_json_of_two_runs_are_refused_by_render_and_eval(good_pair, tmp_path, capsys):
    """The same command run twice: two runs, two ids. A PLY of one beside the JSON of the other is
    refused (exit 3) by every reader of a pair, saying what is wrong."""
    other = tmp_path / "other"
    assert main(["-q", *RUN, str(EXAMPLE), "--out", str(other)]) == 0
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    shutil.copy(good_pair / "outdoor.ply", mixed / "outdoor.ply")
    shutil.copy(other / "outdoor.json", mixed / "outdoor.json")
    capsys.readouterr()
    assert main(["render", str(mixed / "outdoor.json"), "--kind", "map", "--out", str(tmp_path / "m.png")]) == 3
    err = capsys.readouterr().err
    assert err.startswith(f"kbs: error: {mixed / 'outdoor.json'}: does not belong with outdoor.ply: run id ")
    assert err.count("\n") == 1 and not (tmp_path / "m.png").exists()
    assert main(["eval", str(mixed / "outdoor.ply"), "field:label_in", "--ground-values", "0", "--no-hoover"]) == 3
    assert "does not belong with outdoor.ply" in capsys.readouterr().err
    # each run's own pair still reads
    assert main(["render", str(other / "outdoor.json"), "--kind", "map", "--out", str(tmp_path / "m.png")]) == 0


def test_a_pair_written_before_run_ids_still_reads(good_pair, tmp_path):
    """Files without any run id (kbs before this change): nothing to compare, they are read."""
    from kbs.io.result import read_result_pair

    old = tmp_path / "outdoor.json"
    doc = json.loads((good_pair / "outdoor.json").read_text())
    del doc["run_id"], doc["format"], doc["version"]
    old.write_text(json.dumps(doc))
    cloud = read_cloud(good_pair / "outdoor.ply")
    write_ply(tmp_path / "outdoor.ply", cloud.xyz, dict(cloud.fields))  # no kbs comment
    doc2, pc = read_result_pair(old)
    assert list(doc2.label_names) == doc["label_names"] and len(pc) == len(cloud)


# -- 2. never over an input; over another program's file only with --force -------------------------


@pytest.fixture()
def scene_dir(tmp_path) -> Path:
    folder = tmp_path / "scans"
    folder.mkdir()
    np.save(folder / "scene.npy", read_cloud(EXAMPLE).xyz)
    return folder


def test_run_does_not_replace_a_file_it_did_not_write_unless_forced(scene_dir, capsys):
    mine = scene_dir / "scene.ply"
    mine.write_text("ply\nsomeone else's mesh\n")
    assert main(["-q", *RUN, str(scene_dir / "scene.npy"), "--out", str(scene_dir)]) == 3
    err = capsys.readouterr().err
    assert err == (f"kbs: error: {mine}: exists and was not written by kbs (it has no kbs run id); give --force "
                   f"to replace it, or choose another --out\n")
    assert mine.read_text() == "ply\nsomeone else's mesh\n" and not (scene_dir / "scene.json").exists()
    assert main(["-q", *RUN, "--force", str(scene_dir / "scene.npy"), "--out", str(scene_dir)]) == 0
    assert "scalar_cluster" in read_cloud(mine).fields
    # an earlier kbs result is replaced without --force (as PDAL and GDAL tools replace their own outputs)
    first = json.loads((scene_dir / "scene.json").read_text())["run_id"]
    assert main(["-q", *RUN, str(scene_dir / "scene.npy"), "--out", str(scene_dir)]) == 0
    assert json.loads((scene_dir / "scene.json").read_text())["run_id"] != first


def test_run_refuses_a_foreign_json_and_html_report_too(scene_dir, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "scene.json").write_text('{"mine": 1}')
    assert main(["-q", *RUN, str(scene_dir / "scene.npy"), "--out", str(out)]) == 3
    assert "scene.json: exists and was not written by kbs" in capsys.readouterr().err
    (out / "scene.json").unlink()
    (out / "scene.html").write_text("<html>my page</html>")
    assert main(["-q", *RUN, "--report", str(scene_dir / "scene.npy"), "--out", str(out)]) == 3
    assert "scene.html: exists and was not written by kbs" in capsys.readouterr().err
    assert (out / "scene.html").read_text() == "<html>my page</html>"


@pytest.mark.parametrize("how", ["same path", "through a symbolic link"])
def test_cluster_never_writes_over_its_input_even_with_force(tmp_path, capsys, how):
    scan = tmp_path / "X.ply"
    shutil.copy(EXAMPLE, scan)
    before = scan.read_bytes()
    given = scan
    if how == "through a symbolic link":
        given = tmp_path / "alias.ply"
        given.symlink_to(scan)
    for force in ([], ["--force"]):
        assert main(["cluster", str(given), "--k-max", "2", "--out", str(scan), *force]) == 3
        err = capsys.readouterr().err
        assert "kbs never overwrites its input" in err and err.count("\n") == 1
        assert "K " not in capsys.readouterr().out  # refused before clustering
    assert scan.read_bytes() == before


def test_cluster_replaces_its_own_output_but_not_another_file(tmp_path, capsys):
    target = tmp_path / "c.ply"
    target.write_bytes(b"not mine")
    assert main(["cluster", str(EXAMPLE), "--k-max", "2", "--out", str(target)]) == 3
    assert "c.ply: exists and was not written by kbs" in capsys.readouterr().err and target.read_bytes() == b"not mine"
    assert main(["cluster", str(EXAMPLE), "--k-max", "2", "--out", str(target), "--force"]) == 0
    assert main(["cluster", str(EXAMPLE), "--k-max", "2", "--out", str(target)]) == 0  # its own: replaced


def test_render_never_draws_over_the_result_it_reads(out, capsys):
    (out / "alias.png").symlink_to(out / "outdoor.ply")
    before = _snapshot(out)
    for force in ([], ["--force"]):
        assert main(["render", str(out / "outdoor.json"), "--kind", "map", "--out", str(out / "alias.png"),
                     *force]) == 3
        assert f"alias.png: is the input {out / 'outdoor.ply'}" in capsys.readouterr().err
    # named as the result itself: not a PNG name, refused first (exit 2)
    assert main(["render", str(out / "outdoor.json"), "--kind", "map", "--out", str(out / "outdoor.ply")]) == 2
    assert _snapshot(out) == before
    assert main(["render", str(out / "outdoor.json"), "--kind", "map", "--out", str(out / "figure")]) == 0
    # no suffix: a PNG named as matplotlib's savefig names it (and as kbs render says it wrote)
    assert (out / "figure.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (out / "figure").exists()


def test_render_replaces_its_own_png_but_not_another_file(out, capsys):
    from kbs.io.result import is_kbs_output, png_text

    fig = out / "fig.png"
    fig.write_bytes(b"\x89PNG\r\n\x1a\nsomeone else's picture")
    args = ["render", str(out / "outdoor.json"), "--kind", "map", "--out", str(fig)]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert err == (f"kbs: error: {fig}: exists and was not written by kbs (it has no kbs run id); give --force to "
                   "replace it, or choose another --out\n")
    assert fig.read_bytes().endswith(b"someone else's picture")
    assert main([*args, "--force"]) == 0
    assert is_kbs_output(fig) and len(png_text(fig)["kbs_run_id"]) == 32  # a text chunk marks it as kbs's
    assert main(args) == 0  # its own: replaced without --force


def test_render_refuses_a_format_other_than_png_before_drawing(out, capsys):
    before = _snapshot(out)
    assert main(["render", str(out / "outdoor.json"), "--kind", "map", "--out", str(out / "x.txt")]) == 2
    err = capsys.readouterr().err
    assert "kbs render writes PNG figures" in err and "'.txt'" in err and "Traceback" not in err
    assert _snapshot(out) == before


def test_an_unusable_out_folder_is_reported_before_any_segmentation(tmp_path, monkeypatch, capsys):
    import kbs.knowledge.segmenter

    def segment(*args, **kwargs):
        raise AssertionError("segmented before checking --out")

    monkeypatch.setattr(kbs.knowledge.segmenter.Segmenter, "segment", segment)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main([*RUN, str(EXAMPLE), "--out", str(blocker / "out")]) == 3
    r = capsys.readouterr()
    assert r.err == f"kbs: error: {blocker / 'out'}: cannot create the output directory: Not a directory\n"
    assert r.out == ""


# -- 3. progress lines when stderr is not a terminal ---------------------------------------------------


PROGRESS = re.compile(r"kbs: (?P<scan>.+): (?P<n>[\d,]+) splits?, \d+ s")


def _progress(stderr: str) -> list[re.Match]:
    return [m for m in map(PROGRESS.fullmatch, stderr.splitlines()) if m]


@pytest.mark.slow
def test_run_prints_progress_lines_on_a_stderr_that_is_not_a_terminal(tmp_path):
    env = {**os.environ, "KBS_PROGRESS_SECONDS": "0"}  # a line at every split instead of every 10 s
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent))
    args = [exe, *RUN, str(EXAMPLE), "--out", str(tmp_path)]
    r = subprocess.run(args, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = _progress(r.stderr)
    splits = int(re.search(r"(\d+) splits,", r.stdout).group(1))
    assert [int(m["n"]) for m in lines] == list(range(1, splits + 1)) and lines[0]["scan"] == str(EXAMPLE)
    r = subprocess.run([exe, "-q", *args[1:]], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0 and r.stderr == "" and r.stdout == ""  # -q: neither progress nor summary


@pytest.mark.slow
def test_a_terminal_gets_no_progress_lines(tmp_path):
    import pty

    master, slave = pty.openpty()
    env = {**os.environ, "KBS_PROGRESS_SECONDS": "0"}
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent))
    proc = subprocess.run([exe, *RUN, str(EXAMPLE), "--out", str(tmp_path)], stdout=subprocess.DEVNULL,
                          stderr=slave, env=env, timeout=300)
    os.close(slave)
    chunks = []
    while True:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: nothing more to read
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    assert proc.returncode == 0
    assert not _progress(b"".join(chunks).decode().replace("\r\n", "\n"))


def test_a_bad_progress_interval_is_a_usage_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("KBS_PROGRESS_SECONDS", "soon")
    assert main([*RUN, str(EXAMPLE), "--out", str(tmp_path)]) == 2  # capsys's stderr is not a terminal
    assert "KBS_PROGRESS_SECONDS must be a number of seconds >= 0, got 'soon'" in capsys.readouterr().err


# -- 4. strict JSON --------------------------------------------------------------------------------


PLUGIN = '''
from kbs.knowledge import predicate


@predicate(unit="length", value_range=(0.0, None))
def gap_above(cluster, scene) -> float:
    """Free space above the cluster: infinite when nothing is above it."""
    return float("inf")
'''


def test_an_infinite_measurement_is_written_as_null_in_strict_json(tmp_path, capsys):
    plugin = tmp_path / "gap.py"
    plugin.write_text(PLUGIN)
    rules = tmp_path / "gap.yaml"
    text = (ROOT / "rules" / "outdoor.yaml").read_text()
    text = text.replace("checks:\n", "checks:\n  open: {predicate: gap_above, min: 2.0}\n", 1)
    text, n = re.subn(r"if: \[planar, level\]", "if: [planar, level, open]", text)
    assert n >= 1
    rules.write_text(text)
    out = tmp_path / "out"
    assert main(["-q", "run", "--rules", str(rules), "--plugin", str(plugin), "-j", "1", str(EXAMPLE),
                 "--out", str(out)]) == 0
    doc = _strict_json((out / "outdoor.json").read_text())  # raises on NaN / Infinity
    values = [c["value"] for r in doc["explanation"]["clusters"] for c in r["checks"] if c["check"] == "open"]
    assert values and all(v is None for v in values)
    capsys.readouterr()
    assert main(["explain", str(out / "outdoor.json"), "--cluster", "c0"]) == 0
    assert re.search(r"\n    open +yes +gap_above = not finite \(null in the result file\), passes >= 2 m",
                     capsys.readouterr().out)


def test_strict_json_replaces_every_non_finite_number():
    from kbs.io.result import strict_json

    doc = {"a": float("nan"), "b": [1.5, float("-inf"), np.float32("inf")], "c": {"d": np.array([np.nan, 2.0])},
           "e": np.float64("inf"), "f": (np.int32(3), True, None, "NaN")}
    assert _strict_json(strict_json(doc)) == {"a": None, "b": [1.5, None, None], "c": {"d": [None, 2.0]},
                                              "e": None, "f": [3, True, None, "NaN"]}


# -- 5. inputs that cannot be opened ---------------------------------------------------------------


@pytest.mark.parametrize("command", ["run", "cluster", "render"])
def test_a_symbolic_link_loop_is_named_as_such(tmp_path, capsys, command):
    loop = tmp_path / ("loop.json" if command == "render" else "loop.ply")
    loop.symlink_to(loop.name)
    args = {"run": [*RUN, str(loop), "--out", str(tmp_path / "o")], "cluster": ["cluster", str(loop)],
            "render": ["render", str(loop)]}[command]
    assert main(args) == 3
    assert capsys.readouterr().err == (f"kbs: error: {loop}: symbolic link loop (the link points, directly or "
                                       f"not, to itself)\n")


def test_a_broken_symbolic_link_says_where_it_points(tmp_path, capsys):
    link = tmp_path / "scan.ply"
    link.symlink_to("gone.ply")
    assert main(["cluster", str(link)]) == 3
    assert capsys.readouterr().err == f"kbs: error: {link}: no such file: a broken symbolic link (to gone.ply)\n"


def _unprivileged() -> list[str]:
    """A prefix that runs a command without the right to bypass file permissions: nothing when
    not root; as root, setpriv dropping CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH (the Python of
    this venv may live in root's home, so switching user is not an option)."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root, where chmod 000 does not block reading, and setpriv is absent")
    caps = "-dac_override,-dac_read_search"
    prefix = [setpriv, f"--bounding-set={caps}", f"--inh-caps={caps}"]
    probe = subprocess.run([*prefix, "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"running as root and setpriv cannot drop capabilities here: {probe.stderr.decode().strip()}")
    return prefix


@pytest.mark.slow
@pytest.mark.parametrize("command", ["run", "cluster", "render", "run a folder"])
def test_an_unreadable_input_exits_3_not_2(tmp_path, command):
    prefix = _unprivileged()
    locked = tmp_path / "locked"
    locked.mkdir()
    scan = locked / "scan.ply"
    shutil.copy(EXAMPLE, scan)
    (locked / "scan.json").write_text("{}")
    target = {"run": scan, "cluster": scan, "render": locked / "scan.json", "run a folder": locked}[command]
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent))
    args = [*RUN, str(target), "--out", str(tmp_path / "o")] if command.startswith("run") else [command, str(target)]
    target.chmod(0)
    try:
        r = subprocess.run([*prefix, exe, *args], capture_output=True, text=True, timeout=300,
                           env={**os.environ, "KBS_JIT": "0"})
    finally:
        target.chmod(0o755)
    assert r.returncode == 3, r.stderr
    problem = "cannot list the directory" if command == "run a folder" else "cannot read"
    assert r.stderr == f"kbs: error: {target}: {problem}: Permission denied\n"


# -- 6. a folder of scans with their label files; -q ------------------------------------------------


def test_run_on_a_folder_skips_label_and_grid_files(tmp_path, capsys):
    folder = tmp_path / "kitti"
    folder.mkdir()
    xyz = read_cloud(EXAMPLE).xyz.astype(np.float32)
    np.save(folder / "000001.points.npy", xyz)
    np.save(folder / "000001.labels.npy", np.zeros((len(xyz), 1), np.int32))  # SemanticKITTI's shape
    np.save(folder / "000001.ground_grid.npy", np.zeros((100, 100)))  # GndNet: would read as 100 points
    np.save(folder / "other.labels.npy", np.zeros(len(xyz), np.int8))  # no scan beside it: by content
    (folder / "samp.labels.txt").write_text("0\n1\n1\n")
    out = tmp_path / "out"
    assert main([*RUN, str(folder), "--out", str(out)]) == 0
    r = capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["000001.points.json", "000001.points.ply"]
    assert r.err.splitlines()[:4] == [
        f"kbs: skipped {folder / '000001.ground_grid.npy'}: a companion of 000001.points.npy, not a scan",
        f"kbs: skipped {folder / '000001.labels.npy'}: a companion of 000001.points.npy, not a scan",
        f"kbs: skipped {folder / 'other.labels.npy'}: not a point cloud (an array of int8 of shape "
        f"({len(xyz)},), not (N, 3+) coordinates)",
        f"kbs: skipped {folder / 'samp.labels.txt'}: not a point cloud (1 column of text, not x y z)",
    ]
    assert r.out.startswith(f"{folder / '000001.points.npy'}: 26,233 points")


def test_run_on_a_folder_skips_poses_and_calibration_files(tmp_path, capsys):
    """A KITTI-like folder: its poses.txt and calib.txt by name, a trajectory under another name by
    content (12 numbers a line holding a rotation) are not scans; kbs run segments only the scan
    (a poses file read as text was 12 columns: a 'scan' of one point per pose)."""
    folder = tmp_path / "drive"
    folder.mkdir()
    np.save(folder / "000000.npy", read_cloud(EXAMPLE).xyz.astype(np.float32))
    rows = "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1.5 0 1 0 0.2 0 0 1 0\n"
    (folder / "poses.txt").write_text(rows)
    (folder / "traj.txt").write_text(rows)
    (folder / "calib.txt").write_text("P0: 7.1e+02 0 6.0e+02 0 0 7.1e+02 1.8e+02 0 0 0 1 0\n")
    out = tmp_path / "out"
    assert main([*RUN, str(folder), "--out", str(out)]) == 0
    r = capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["000000.json", "000000.ply"]
    skipped = [line for line in r.err.splitlines() if line.startswith("kbs: skipped")]
    assert skipped == [f"kbs: skipped {folder / 'calib.txt'}: not a point cloud (a KITTI calibration file)",
                       f"kbs: skipped {folder / 'poses.txt'}: not a point cloud (a poses file)",
                       f"kbs: skipped {folder / 'traj.txt'}: not a point cloud (a poses file (12 numbers a line: a "
                       "rotation and a translation, KITTI's poses.txt))"]


def test_quiet_run_prints_nothing(tmp_path, capsys):
    assert main(["-q", *RUN, str(EXAMPLE), str(ROOT / "examples" / "data" / "polyhedral.ply"),
                 "--out", str(tmp_path)]) == 0
    r = capsys.readouterr()
    assert r.out == "" and r.err == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outdoor.json", "outdoor.ply", "polyhedral.json",
                                                          "polyhedral.ply"]


# -- eval --json and the meshes folder: whole or not at all too -----------------------------------------


def _full_disk_on(folder: Path, suffix: str):
    """An ``open`` (for builtins.open and io.open, which pathlib uses) whose files written in
    ``folder`` (its hidden temporaries too) with ``suffix`` take half of what is written, then say the
    disk is full."""
    import io

    real_open = io.open

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            self.f.write(data[: len(data) // 2])
            self.f.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def __getattr__(self, name):
            return getattr(self.f, name)

    def opener(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        path = Path(os.fspath(file)) if isinstance(file, (str, os.PathLike)) else None
        if path is not None and "w" in mode and path.suffix == suffix and path.parent == folder:
            return Full(f)
        return f

    return opener


def test_a_full_disk_while_eval_writes_its_json_leaves_the_previous_file(out, monkeypatch, capsys):
    import builtins
    import io

    truth = out / "truth.npy"
    np.save(truth, np.zeros(len(read_cloud(out / "outdoor.ply").xyz), dtype=np.int32))
    report = out / "eval.json"
    assert main(["eval", str(out / "outdoor.ply"), str(truth), "--ground-values", "0", "--json", str(report)]) == 0
    before = _snapshot(out)
    capsys.readouterr()
    full = _full_disk_on(out, ".json")
    monkeypatch.setattr(builtins, "open", full)
    monkeypatch.setattr(io, "open", full)
    code = main(["eval", str(out / "outdoor.ply"), str(truth), "--ground-values", "0", "--hoover", "--json",
                 str(report)])
    monkeypatch.undo()
    assert code == 3 and f"{report}: cannot write: No space left on device" in capsys.readouterr().err
    assert _snapshot(out) == before  # the previous eval.json whole, no temporary file left


def test_eval_json_is_never_the_results_own_json(out, capsys):
    truth = out / "truth.npy"
    np.save(truth, np.zeros(len(read_cloud(out / "outdoor.ply").xyz), dtype=np.int32))
    before = _snapshot(out)
    code = main(["eval", str(out / "outdoor.ply"), str(truth), "--ground-values", "0", "--json", str(out / "outdoor.json")])
    assert code == 3 and "is the input" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_eval_json_replaces_its_own_file_but_not_another_without_force(out, capsys):
    truth = out / "truth.npy"
    np.save(truth, np.zeros(len(read_cloud(out / "outdoor.ply").xyz), dtype=np.int32))
    report = out / "notes.json"
    report.write_text('{"mine": 1}')
    args = ["eval", str(out / "outdoor.ply"), str(truth), "--ground-values", "0", "--json", str(report)]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert err == (f"kbs: error: {report}: exists and was not written by kbs (it has no kbs run id); give --force "
                   "to replace it, or choose another --json\n")
    assert report.read_text() == '{"mine": 1}'
    assert main([*args, "--force"]) == 0
    doc = json.loads(report.read_text())
    assert doc["kbs_version"] and len(doc["run_id"]) == 32
    assert main(args) == 0  # its own: replaced without --force
    assert json.loads(report.read_text())["run_id"] != doc["run_id"]


def test_run_meshes_never_replaces_a_mesh_it_did_not_write_without_force(tmp_path, monkeypatch, capsys):
    """A foreign ground.ply in <stem>-meshes/ is refused before the scan is read (it was replaced,
    and only after the result pair was written); with --force the folder is replaced."""
    import kbs.knowledge.segmenter

    o = tmp_path / "o"
    folder = o / "outdoor-meshes"
    folder.mkdir(parents=True)
    (folder / "ground.ply").write_text("ply\nmine\n")
    real = kbs.knowledge.segmenter.Segmenter.segment

    def segment(*args, **kwargs):
        raise AssertionError("segmented before checking the meshes folder")

    monkeypatch.setattr(kbs.knowledge.segmenter.Segmenter, "segment", segment)
    assert main(["-q", *RUN, str(EXAMPLE), "--out", str(o), "--meshes"]) == 3
    err = capsys.readouterr().err
    assert err == (f"kbs: error: {folder / 'ground.ply'}: exists and was not written by kbs (it has no kbs run id); "
                   "give --force to replace the mesh folder, or choose another --out\n")
    assert (folder / "ground.ply").read_text() == "ply\nmine\n"
    assert sorted(p.name for p in o.iterdir()) == ["outdoor-meshes"]  # no result pair either
    monkeypatch.setattr(kbs.knowledge.segmenter.Segmenter, "segment", real)
    assert main(["-q", *RUN, str(EXAMPLE), "--out", str(o), "--meshes", "--force"]) == 0
    from kbs.io.result import is_kbs_output, ply_run_id

    run_id = json.loads((o / "outdoor.json").read_text())["run_id"]
    meshes = sorted(folder.iterdir())
    assert meshes and all(is_kbs_output(p) and ply_run_id(p) == run_id for p in meshes)
    assert main(["-q", *RUN, str(EXAMPLE), "--out", str(o), "--meshes"]) == 0  # its own: replaced


@pytest.mark.slow
def test_a_full_disk_while_writing_the_meshes_leaves_the_previous_folder(tmp_path, monkeypatch, capsys):
    """The meshes folder of a scan run again on other points: a failure half-way through leaves the
    earlier folder as it was (it was left half new, half old); a complete run replaces it whole,
    stale meshes of clusters that are gone included; a folder with other files is not replaced."""
    import kbs.report.meshes as meshes

    scan = tmp_path / "scene.ply"
    X = read_cloud(EXAMPLE).xyz
    write_ply(scan, X, {})
    o = tmp_path / "o"
    assert main(["-q", *RUN, str(scan), "--out", str(o), "--meshes"]) == 0
    folder = o / "scene-meshes"
    before = _snapshot(folder)
    assert len(before) >= 3
    write_ply(scan, X * [1.0, 1.0, 1.5], {})  # taller obstacles: other hulls
    real = meshes.write_mesh_ply
    calls = []

    def second_fails(path, V, F, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise CloudFileError(str(path), "cannot write: No space left on device")
        real(path, V, F, **kwargs)

    from kbs.errors import CloudFileError

    monkeypatch.setattr(meshes, "write_mesh_ply", second_fails)
    assert main(["-q", *RUN, str(scan), "--out", str(o), "--meshes", "--force"]) == 3
    err = capsys.readouterr().err
    assert "No space left on device" in err and ".kbs-tmp-" not in err  # named where the user looks
    monkeypatch.undo()
    assert _snapshot(folder) == before
    assert sorted(p.name for p in o.iterdir()) == ["scene-meshes", "scene.json", "scene.ply"]  # no temporary left
    (folder / "obstacle-999.ply").write_bytes(before[next(iter(before))])  # a stale mesh
    assert main(["-q", *RUN, str(scan), "--out", str(o), "--meshes"]) == 0
    after = _snapshot(folder)
    assert "obstacle-999.ply" not in after and after != before
    (folder / "notes.txt").write_text("mine")
    assert main(["-q", *RUN, str(scan), "--out", str(o), "--meshes"]) == 3
    assert "holds files kbs did not write (notes.txt)" in capsys.readouterr().err
    assert (folder / "notes.txt").read_text() == "mine"


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1e80, 1e105])
def test_coordinates_too_large_for_float64_products_are_refused_clearly(tmp_path, scale):
    """Coordinates of 1e80 ran for a minute and printed numpy's 'overflow encountered in multiply'
    (the covariances' norms reach the 4th power, their determinants the 6th); 1e105 crashed in the
    voxel grid with a traceback. Now: refused before the work, the file named, exit 3; the library
    says the same as a ParameterError."""
    from kbs.errors import ParameterError
    from kbs.knowledge import Segmenter

    X = read_cloud(EXAMPLE).xyz[::10] * scale
    scan = tmp_path / "huge.xyz"
    np.savetxt(scan, X)
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3, r.stderr
    assert r.stderr.startswith(f"kbs: error: {scan}: ") and "beyond +-1e+50" in r.stderr and "--units" in r.stderr
    assert "Traceback" not in r.stderr and "RuntimeWarning" not in r.stderr and "overflow encountered" not in r.stderr
    assert not (tmp_path / "o" / "huge.json").exists()
    with pytest.raises(ParameterError, match=r"points: .* beyond \+-1e\+50"):
        Segmenter("outdoor").segment(X)
    # a large but computable scale still runs (the bound is not a unit check)
    with pytest.warns(UserWarning, match="median point spacing"):  # and no overflow (RuntimeWarnings fail the tests)
        assert Segmenter("outdoor").segment(X / scale * 1e40).label.shape == (len(X),)
