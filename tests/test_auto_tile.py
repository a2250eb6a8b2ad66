"""``limits.tile``: a rule base says how wide a cloud it judges whole; ``kbs run`` segments a wider
cloud in tiles of ``size`` (as ``--tile size`` does), so that a region's labels do not depend on how
much else the file holds; ``--no-tile`` runs it whole. Through ``kbs run`` on a real ISPRS sample."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.io import read_cloud, write_ply
from test_cli import kbs

ROOT = Path(__file__).resolve().parents[1]
AIRBORNE = (ROOT / "rules" / "airborne.yaml").read_text(encoding="utf-8")
SHIPPED_TILE = "  tile:                        # a cloud wider"


def rules_with_tile(tmp_path: Path, tile: str) -> Path:
    """airborne.yaml with its limits.tile replaced by ``tile`` (the lines under 'limits:')."""
    lines = AIRBORNE.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.startswith(SHIPPED_TILE))
    path = tmp_path / "airborne_tiled.yaml"
    path.write_text("\n".join(lines[:at] + tile.splitlines() + lines[at + 3:]) + "\n", encoding="utf-8")
    return path


def labels(folder: Path, stem: str) -> np.ndarray:
    return np.asarray(PlyData.read(str(folder / f"{stem}.ply"))["vertex"]["scalar_label"])


def run(*args: str):
    r = kbs("run", "-j", "1", *args)
    assert r.returncode == 0, r.stderr
    return r


def test_the_shipped_airborne_rules_tile_clouds_wider_than_the_isprs_samples():
    from kbs.knowledge import load_rule_base

    spec = load_rule_base("airborne").tile
    assert spec is not None and spec.size == 100.0 and spec.wider_than == 600.0
    assert load_rule_base("outdoor").tile is None


@pytest.mark.slow
def test_a_cloud_wider_than_limits_tile_runs_in_tiles_and_no_tile_runs_it_whole(shared_data, tmp_path):
    """ISPRS samp21 is 124 m wide: with limits.tile {size: 60, wider_than: 100} kbs run cuts it into
    tiles of 60 m, the same result as --tile 60, and says why; --no-tile gives the untiled result;
    wider_than 200 leaves it whole, without a word."""
    scan = shared_data / "isprs" / "samp21-utm.pcd"
    tiled = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")
    r = run("--rules", str(tiled), str(scan), "--out", str(tmp_path / "auto"))
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("  tiles: "))
    assert line.startswith("  tiles: 6 of 60 x 60 with a 10 buffer; ") and line.endswith(
        "(airborne_tiled.yaml limits.tile: the cloud is 123.781 m wide, more than 100 m; --no-tile runs it whole)"), line
    doc = json.loads((tmp_path / "auto" / "samp21-utm.json").read_text())
    assert doc["tiling"]["size"] == 60.0 and len(doc["tiling"]["tiles"]) == 6
    run("--rules", "airborne", "--tile", "60", str(scan), "--out", str(tmp_path / "explicit"))
    np.testing.assert_array_equal(labels(tmp_path / "auto", "samp21-utm"), labels(tmp_path / "explicit", "samp21-utm"))

    r = run("--rules", str(tiled), "--no-tile", str(scan), "--out", str(tmp_path / "whole"))
    assert "tiles:" not in r.stdout and "tiling" not in json.loads((tmp_path / "whole" / "samp21-utm.json").read_text())
    run("--rules", "airborne", str(scan), "--out", str(tmp_path / "shipped"))
    np.testing.assert_array_equal(labels(tmp_path / "whole", "samp21-utm"), labels(tmp_path / "shipped", "samp21-utm"))

    narrow = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 200}")
    r = run("--rules", str(narrow), str(scan), "--out", str(tmp_path / "narrow"))
    assert "tiles:" not in r.stdout and "limits.tile" not in r.stderr, r.stderr
    np.testing.assert_array_equal(labels(tmp_path / "narrow", "samp21-utm"), labels(tmp_path / "shipped", "samp21-utm"))


@pytest.mark.slow
def test_a_wide_cloud_in_another_unit_runs_whole_and_says_why(shared_data, tmp_path):
    """Tiles run a scan in the rule base's own unit (as --tile): a wide scan in centimetres is
    scaled and run whole, and a note says so and what to do."""
    pc = read_cloud(shared_data / "isprs" / "samp21-utm.pcd")
    X = (pc.xyz - np.floor(pc.xyz.min(axis=0))) * 100.0
    scan = tmp_path / "cm.ply"
    write_ply(scan, X, comments=["units cm"])
    tiled = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")
    r = run("--rules", str(tiled), str(scan), "--out", str(tmp_path / "o"))
    assert "tiles:" not in r.stdout
    note = [ln for ln in r.stderr.splitlines() if "limits.tile" in ln]
    assert len(note) == 1 and note[0].startswith(f"note: {scan}: the cloud is 123.781") and \
        "runs whole" in note[0] and "its unit (cm) is not the rule base's" in note[0] and "--no-tile" in note[0], r.stderr


@pytest.mark.parametrize("tile, at, message", [
    ("  tile: {size: 100, wider_than: 50}", "wider_than", "wider_than 50 is below the tile size 100"),
    ("  tile: {size: 0, wider_than: 50}", "size", "0"),
    ("  tile: {size: 100}", "tile", "wider_than"),
    ("  tile: {size: 100, wider_than: 600, buffer: 5}", "buffer", "buffer"),
])
def test_a_bad_limits_tile_is_refused_at_its_position(tmp_path, tile, at, message):
    path = rules_with_tile(tmp_path, tile)
    r = kbs("rules", "check", str(path))
    assert r.returncode == 4, r.stdout + r.stderr
    line = next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if ln.startswith("  tile:"))
    err = r.stdout + r.stderr
    assert f"{path}:{line}:" in err and message in err, err


def test_no_tile_with_tile_is_a_usage_error(tmp_path):
    r = kbs("run", "--rules", "airborne", "--tile", "100", "--no-tile", str(tmp_path / "x.ply"))
    assert r.returncode == 2 and "--no-tile and --tile contradict each other" in r.stderr, r.stderr


# -- issue 16: automatic tiles on Dask, and an automatically tiled LAS read in chunks --------------

def _normalised(path: Path) -> bytes:
    """A result file's bytes with its run id (32 hex digits) and the JSON's timing blanked."""
    data = re.sub(rb"[0-9a-f]{32}", b"0" * 32, path.read_bytes())
    return re.sub(rb'"seconds":[0-9.e+-]+', b'"seconds":0', data)


def _same_files(a: Path, b: Path, *names: str) -> None:
    for name in names:
        assert _normalised(a / name) == _normalised(b / name), name


def _tiled_by(path: Path) -> tuple[dict, dict]:
    """A result JSON's ``tiled_by`` and the rest of it (run id and timing blanked)."""
    doc = json.loads(_normalised(path))
    return doc.pop("tiled_by"), doc


def _invoke(*args: str, monkeypatch=None, forbid_whole_read: bool = False):
    """``kbs ARGS`` in this process (click's CliRunner), so that a spy can watch the reader:
    with ``forbid_whole_read``, reading the scan whole (:func:`kbs.cli.run.read_scan`) fails."""
    from click.testing import CliRunner

    from kbs.cli import run as run_module
    from kbs.cli.main import cli

    read = []
    if monkeypatch is not None:
        original = run_module.read_scan

        def spy(cloud, in_format=None):
            read.append(cloud)
            assert not forbid_whole_read, f"{cloud} was read whole"
            return original(cloud, in_format)

        monkeypatch.setattr(run_module, "read_scan", spy)
    r = CliRunner().invoke(cli, list(args))
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    return r, read


@pytest.mark.slow  # a LocalCluster of 2 workers started for the run
def test_automatic_tiles_on_a_local_dask_cluster_give_the_bytes_of_the_in_process_run(shared_data, tmp_path):
    """--scheduler local -j 2 without --tile: the tiles limits.tile makes run as Dask tasks, and the
    result is the in-process automatic run's, byte for byte (run id and timing apart)."""
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    scan = shared_data / "isprs" / "samp21-utm.pcd"
    tiled = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")
    here = run("--rules", str(tiled), str(scan), "--out", str(tmp_path / "here"))
    dask = kbs("run", "-j", "2", "--scheduler", "local", "--rules", str(tiled), str(scan), "--out",
               str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    assert "kbs: Dask dashboard: http" in dask.stderr and "kbs: Dask dashboard" not in here.stderr
    tiles = [ln for ln in dask.stdout.splitlines() if ln.startswith("  tiles: ")]
    assert len(tiles) == 1 and tiles[0].startswith("  tiles: 6 of 60 x 60") and "limits.tile" in tiles[0], dask.stdout
    _same_files(tmp_path / "here", tmp_path / "dask", "samp21-utm.ply", "samp21-utm.json")
    assert len(json.loads((tmp_path / "dask" / "samp21-utm.json").read_text())["tiling"]["tiles"]) == 6


@pytest.mark.slow  # the scan three times, once on a LocalCluster of 2 workers
def test_an_automatically_tiled_las_is_read_in_chunks_as_tile_reads_it(shared_data, tmp_path, monkeypatch):
    """A LAS whose header's bounds are wider than limits.tile.wider_than is never read whole: it is
    spilled in chunks, as --tile SIZE spills it, and its result is --tile SIZE's, byte for byte; in
    process and with its tiles on Dask."""
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    scan = shared_data / "las" / "sample_c.las"  # 83 m x 75 m, no CRS: the rule base's metres
    tiled = rules_with_tile(tmp_path, "  tile: {size: 30, wider_than: 50}")
    r, read = _invoke("run", "-j", "1", "--rules", str(tiled), str(scan), "--out", str(tmp_path / "auto"),
                      monkeypatch=monkeypatch, forbid_whole_read=True)
    assert r.exit_code == 0, r.output
    assert read == []
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("  tiles: "))
    assert line.startswith("  tiles: 8 of 30 x 30 with a 10 buffer; ") and line.endswith(
        "(airborne_tiled.yaml limits.tile: the cloud is 83.4 m wide by its LAS header, more than 50 m, read in chunks; "
        "--no-tile runs it whole)"), line
    assert sorted(p.name for p in (tmp_path / "auto").iterdir()) == ["sample_c.json", "sample_c.las"]  # spill gone
    run("--rules", str(tiled), "--tile", "30", str(scan), "--out", str(tmp_path / "explicit"))
    _same_files(tmp_path / "auto", tmp_path / "explicit", "sample_c.las")
    by_auto, doc_auto = _tiled_by(tmp_path / "auto" / "sample_c.json")
    by_explicit, doc_explicit = _tiled_by(tmp_path / "explicit" / "sample_c.json")
    assert doc_auto == doc_explicit  # all but where the tiling came from
    assert by_auto == {"from": "limits.tile", "buffer_from": "default"}
    assert by_explicit == {"from": "--tile", "buffer_from": "default"}
    dask = kbs("run", "-j", "2", "--scheduler", "local", "--rules", str(tiled), str(scan), "--out",
               str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    assert "kbs: Dask dashboard: http" in dask.stderr and "by its LAS header" in dask.stdout
    _same_files(tmp_path / "auto", tmp_path / "dask", "sample_c.las", "sample_c.json")


def _tilted(tmp_path: Path, normal: str) -> Path:
    """airborne_tiled.yaml (tiles of 30 beyond 50 m) with its fixed ground normal replaced."""
    path = rules_with_tile(tmp_path, "  tile: {size: 30, wider_than: 50}")
    text = path.read_text(encoding="utf-8")
    assert text.count("normal: [0, 0, 1]") == 1
    path.write_text(text.replace("normal: [0, 0, 1]", f"normal: {normal}"), encoding="utf-8")
    return path


def test_a_las_whose_header_cannot_decide_is_read_whole_as_before(shared_data, tmp_path, monkeypatch):
    """The header's x and y bounds do not give the width across a ground normal other than z: the
    scan is read whole and its points decide, as before."""
    scan = shared_data / "las" / "sample_c.las"
    tilted = _tilted(tmp_path, "[0, 0.6, 0.8]")
    r, read = _invoke("run", "-j", "1", "--rules", str(tilted), str(scan), "--out", str(tmp_path / "o"),
                      monkeypatch=monkeypatch)
    assert r.exit_code == 0, r.output
    assert read == [scan]  # read whole
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("  tiles: "))
    assert "by its LAS header" not in line and "limits.tile: the cloud is" in line, line


def test_a_las_header_wider_than_its_points_does_not_tile_them(shared_data, tmp_path, monkeypatch):
    """A header whose bounds say wider than the points are (written by a careless tool): the spill's
    own extent overrules it; the scan is read whole and runs whole, as its points say."""
    import laspy

    scan = tmp_path / "stale.las"
    las = laspy.read(shared_data / "las" / "sample_c.las")
    las.write(str(scan))
    with laspy.open(str(scan)) as reader:
        lo = float(reader.header.mins[0])
    data = bytearray(scan.read_bytes())
    data[179:187] = np.float64(lo + 1000.0).tobytes()  # the header's max x (LAS 1.x, offset 179)
    scan.write_bytes(bytes(data))
    with laspy.open(str(scan)) as reader:
        assert float(reader.header.maxs[0]) == lo + 1000.0
    narrow = rules_with_tile(tmp_path, "  tile: {size: 30, wider_than: 100}")  # the points: 83.4 m
    r, read = _invoke("run", "-j", "1", "--rules", str(narrow), str(scan), "--out", str(tmp_path / "o"),
                      monkeypatch=monkeypatch)
    assert r.exit_code == 0, r.output
    assert read == [scan] and "tiles:" not in r.stdout, r.stdout
    assert "tiling" not in json.loads((tmp_path / "o" / "stale.json").read_text())
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["stale.json", "stale.las"]  # no spill left


def test_scheduler_on_a_cloud_narrower_than_limits_tile_runs_it_whole_with_a_note(shared_data, tmp_path):
    """--scheduler with a cloud not wider than limits.tile.wider_than: one note says it runs whole
    in this process (no Dask started), and the result is the plain run's."""
    scan = shared_data / "isprs" / "samp21-utm.pcd"  # 124 m
    narrow = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 200}")
    r = kbs("run", "-j", "1", "--scheduler", "local", "--rules", str(narrow), str(scan), "--out", str(tmp_path / "s"))
    assert r.returncode == 0, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if "limits.tile" in ln]
    assert notes == [f"note: {scan}: the cloud is 123.781 m wide, not more than airborne_tiled.yaml "
                     f"limits.tile.wider_than (200 m): it runs whole, in this process; --scheduler is not used"], r.stderr
    assert "Dask dashboard" not in r.stderr and "tiles:" not in r.stdout
    run("--rules", str(narrow), str(scan), "--out", str(tmp_path / "plain"))
    _same_files(tmp_path / "s", tmp_path / "plain", "samp21-utm.ply", "samp21-utm.json")


@pytest.mark.parametrize("rules, extra, message", [
    ("outdoor", (), "rule base 'outdoor' has no limits.tile to tile a wide cloud by itself"),
    ("airborne", ("--no-tile",), "--no-tile runs the scan whole in this process: give one"),
    ("airborne", ("--out", "-"), "--scheduler is not used with --out -"),
])
def test_scheduler_with_one_scan_that_cannot_tile_is_a_usage_error(shared_data, tmp_path, rules, extra, message):
    scan = shared_data / "las" / "sample_c.las"
    out = () if "--out" in extra else ("--out", str(tmp_path / "o"))
    r = kbs("run", "--rules", rules, "--scheduler", "local", str(scan), *extra, *out)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


# -- session 11: --buffer, --resume and --chunk-points for the tiles of limits.tile ----------------

def test_the_tiles_line_and_the_json_say_where_the_tiling_and_its_buffer_came_from():
    """The words a tiled run prints and writes, from the functions that decide them (the whole
    runs are in the slow tests below)."""
    from kbs.cli.run import TileOptions, _auto_tiling
    from kbs.knowledge import Segmenter

    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 130, 500), rng.uniform(0, 40, 500), rng.uniform(0, 1, 500)])
    xyz[0, 0], xyz[1, 0] = 0.0, 130.0  # 130 m wide
    seg = Segmenter("airborne", jobs=1)  # the shipped rules: tiles of 100 m beyond 600 m
    tiling, why = _auto_tiling(seg, xyz, None, None, False, None, TileOptions(buffer=5.0))
    assert tiling is None and why == ("the cloud is 130 m wide, not more than airborne.yaml limits.tile.wider_than "
                                      "(600 m): it runs whole; --buffer is not used"), why
    tiling, why = _auto_tiling(seg, xyz, None, None, False, ("local", 2), TileOptions(resume=True, chunk_points=9))
    assert tiling is None and why.endswith("; --scheduler, --resume and --chunk-points are not used"), why
    assert _auto_tiling(seg, xyz, None, None, False, None, TileOptions()) == (None, None)  # nothing given: no word
    wide = xyz * [10, 1, 1]
    tiling, why = _auto_tiling(seg, wide, None, None, False, None, TileOptions(buffer=5.0, resume=True))
    assert tiling is not None and (tiling.size, tiling.buffer, tiling.resume) == (100.0, 5.0, True)
    assert why.endswith("more than 600 m; the buffer from --buffer 5; --no-tile runs it whole"), why
    tiling, why = _auto_tiling(seg, wide, None, None, False, None, TileOptions())
    assert tiling is not None and tiling.buffer is None and not tiling.resume and "--buffer" not in why


@pytest.mark.parametrize("rules, extra, message", [
    ("outdoor", ("--buffer", "5"), "--buffer only applies to a tiled run: give --tile SIZE too; rule base 'outdoor' "
     "has no limits.tile to tile a wide cloud by itself"),
    ("outdoor", ("--resume", "--chunk-points", "10"), "--resume and --chunk-points only apply to a tiled run"),
    ("airborne", ("--buffer", "5", "--no-tile"), "--buffer applies to the tiles of the rule base's limits.tile; "
     "--no-tile runs the scan whole: give one"),
    ("airborne", ("--resume", "--out", "-"), "--out - runs the scan whole (tiles write a result folder): --resume is "
     "not used with --out -"),
    ("airborne", ("--buffer", "5", "--resume", "--sensor", "0,0,0"), "--sensor runs the scan whole (tiles need the "
     "rule base's own sensor, as with --tile): --buffer and --resume are not used with --sensor"),
    ("airborne", ("--chunk-points", "100", "--out-format", "ply"), "--chunk-points reads and writes a LAS/LAZ scan in "
     "chunks: it is not used with --out-format ply"),
    ("airborne", ("--tile", "30", "--chunk-points", "100", "--out-format", "ply"), "--chunk-points reads and writes"),
])
def test_tile_options_that_cannot_apply_to_the_automatic_tiles_are_usage_errors(shared_data, tmp_path, rules, extra,
                                                                                  message):
    scan = shared_data / "las" / "sample_c.las"
    out = () if "--out" in extra else ("--out", str(tmp_path / "o"))
    r = kbs("run", "--rules", rules, str(scan), *extra, *out)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


@pytest.mark.slow
def test_buffer_sets_the_buffer_of_the_automatic_tiles_as_it_does_for_tile(shared_data, tmp_path):
    """--buffer 7 without --tile: the tiles of limits.tile reach 7 m beyond their cores (the tiles:
    line and the JSON say so, and that it came from --buffer), the labels of --tile 60 --buffer 7;
    a cloud that is not wider runs whole and a note says --buffer is not used."""
    scan = shared_data / "isprs" / "samp21-utm.pcd"
    tiled = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")
    r = run("--rules", str(tiled), "--buffer", "7", str(scan), "--out", str(tmp_path / "auto"))
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("  tiles: "))
    assert line.startswith("  tiles: 6 of 60 x 60 with a 7 buffer; ") and line.endswith(
        "(airborne_tiled.yaml limits.tile: the cloud is 123.781 m wide, more than 100 m; the buffer from --buffer 7; "
        "--no-tile runs it whole)"), line
    by, doc = _tiled_by(tmp_path / "auto" / "samp21-utm.json")
    assert doc["tiling"]["buffer"] == 7.0 and by == {"from": "limits.tile", "buffer_from": "--buffer"}
    default = run("--rules", str(tiled), str(scan), "--out", str(tmp_path / "default"))
    assert "with a 10 buffer; " in default.stdout
    by, doc_default = _tiled_by(tmp_path / "default" / "samp21-utm.json")
    assert doc_default["tiling"]["buffer"] == 10.0 and by == {"from": "limits.tile", "buffer_from": "default"}
    # the buffer reaches the tiles: their points differ from the default's
    assert [t["points"] for t in doc["tiling"]["tiles"]] != [t["points"] for t in doc_default["tiling"]["tiles"]]
    run("--rules", str(tiled), "--tile", "60", "--buffer", "7", str(scan), "--out", str(tmp_path / "explicit"))
    _same_files(tmp_path / "auto", tmp_path / "explicit", "samp21-utm.ply")
    assert _tiled_by(tmp_path / "explicit" / "samp21-utm.json")[1] == doc

    narrow = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 200}")
    r = run("--rules", str(narrow), "--buffer", "7", str(scan), "--out", str(tmp_path / "narrow"))
    assert "tiles:" not in r.stdout
    notes = [ln for ln in r.stderr.splitlines() if "limits.tile" in ln]
    assert notes == [f"note: {scan}: the cloud is 123.781 m wide, not more than airborne_tiled.yaml "
                     f"limits.tile.wider_than (200 m): it runs whole; --buffer is not used"], r.stderr


@pytest.mark.slow  # sample_c three times, and once on a LocalCluster of 2 workers
def test_chunk_points_on_an_automatically_tiled_las_gives_the_bytes_of_the_unchunked_run(shared_data, tmp_path):
    """--chunk-points 4000 (4 chunks) on a LAS tiled by limits.tile: the LAS and JSON of --chunk-points
    0 (read whole, the points decide) and of the default chunks, byte for byte (run id and timing
    apart); with --buffer too, in process and on Dask. A PCD scan cannot be read in chunks: a note says so."""
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    scan = shared_data / "las" / "sample_c.las"  # 14,408 points
    tiled = rules_with_tile(tmp_path, "  tile: {size: 30, wider_than: 50}")
    names = ("sample_c.las", "sample_c.json")
    chunked = run("--rules", str(tiled), "--chunk-points", "4000", str(scan), "--out", str(tmp_path / "chunked"))
    assert "by its LAS header, more than 50 m, read in chunks" in chunked.stdout
    whole = run("--rules", str(tiled), "--chunk-points", "0", str(scan), "--out", str(tmp_path / "whole"))
    line = next(ln for ln in whole.stdout.splitlines() if ln.startswith("  tiles: "))
    assert line.startswith("  tiles: 8 of 30 x 30 with a 10 buffer; ") and "by its LAS header" not in line, line
    assert "the cloud is 83.4 m wide, more than 50 m" in line
    _same_files(tmp_path / "chunked", tmp_path / "whole", *names)
    run("--rules", str(tiled), str(scan), "--out", str(tmp_path / "default"))
    _same_files(tmp_path / "chunked", tmp_path / "default", *names)

    args = ("--rules", str(tiled), "--buffer", "4", "--chunk-points", "4000", str(scan))
    here = run(*args, "--out", str(tmp_path / "here"))
    assert "with a 4 buffer; " in here.stdout and "the buffer from --buffer 4" in here.stdout
    dask = kbs("run", "-j", "2", "--scheduler", "local", *args, "--out", str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    assert "kbs: Dask dashboard: http" in dask.stderr and "with a 4 buffer; " in dask.stdout
    _same_files(tmp_path / "here", tmp_path / "dask", *names)
    assert json.loads((tmp_path / "dask" / "sample_c.json").read_text())["tiling"]["buffer"] == 4.0

    pcd = shared_data / "isprs" / "samp21-utm.pcd"
    r = run("--rules", str(rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")), "--chunk-points", "4000",
            str(pcd), "--out", str(tmp_path / "pcd"))
    assert "  tiles: 6 of 60 x 60" in r.stdout
    assert f"note: {pcd}: --chunk-points is not used: it reads a LAS/LAZ file written as LAS/LAZ in chunks; this " \
           f"scan is read whole" in r.stderr, r.stderr


EAST_PLUGIN = '''
import os

from kbs.knowledge import predicate


@predicate(unit="length")
def east(cluster, scene) -> float:
    """x of the centre; fails east of KBS_TEST_FAIL_EAST_OF (when set), to make the tiles there fail."""
    x = float(cluster.geometry.center[0])
    if x > float(os.environ.get("KBS_TEST_FAIL_EAST_OF", "inf")):
        raise RuntimeError("no measurement that far east")
    return x
'''


@pytest.mark.slow  # samp21 four times, once on a LocalCluster of 2 workers
def test_resume_after_a_failed_automatic_run_redoes_only_the_missing_tiles(shared_data, tmp_path, monkeypatch):
    """limits.tile cuts samp21 into 6 tiles; a plugin check fails east of x = 513,620 m, so the tiles
    there fail: the run exits 7 with the others kept; --resume (in process, then on Dask) segments
    only the failed ones and gives the bytes of a fresh run."""
    plugin = tmp_path / "east.py"
    plugin.write_text(EAST_PLUGIN)
    rules = rules_with_tile(tmp_path, "  tile: {size: 60, wider_than: 100}")
    text = rules.read_text(encoding="utf-8")
    assert text.count("checks:\n") == 1 and text.count("    if: [planar, gentle, not tiny]") == 1
    text = text.replace("checks:\n", "checks:\n  west: {predicate: east, max: 1.0e+9}\n").replace(
        "    if: [planar, gentle, not tiny]", "    if: [planar, gentle, not tiny, west]")
    rules.write_text(text, encoding="utf-8")
    scan = shared_data / "isprs" / "samp21-utm.pcd"
    args = ["--rules", str(rules), "--plugin", str(plugin), "--buffer", "8", str(scan)]
    for out in ("out", "dask"):
        monkeypatch.setenv("KBS_TEST_FAIL_EAST_OF", "513620")
        r = kbs("run", "-j", "1", *args, "--out", str(tmp_path / out))
        assert r.returncode == 7, r.stderr
        kept = tmp_path / out / "samp21-utm.tiles"
        assert re.search(r"kbs: error: tile t\d_\d \[", r.stderr) and "no measurement that far east" in r.stderr
        assert f"the finished tiles are kept in {kept}: run again with --resume" in r.stderr and "Traceback" not in r.stderr
        done = sorted(p.name for p in kept.iterdir())
        assert 0 < len(done) < 6 and "t0_0.npz" in done, done
        assert not (tmp_path / out / "samp21-utm.ply").exists()
        monkeypatch.delenv("KBS_TEST_FAIL_EAST_OF")
        extra = ("-j", "1") if out == "out" else ("-j", "2", "--scheduler", "local")
        r = kbs("run", *extra, *args, "--resume", "--out", str(tmp_path / out))
        assert r.returncode == 0, r.stderr
        assert f"kbs: resumed {len(done)} of 6 tiles from {kept}" in r.stderr, r.stderr
        assert "with a 8 buffer; " in r.stdout and "limits.tile" in r.stdout
        assert not kept.exists()
    run(*args, "--out", str(tmp_path / "fresh"))
    _same_files(tmp_path / "out", tmp_path / "fresh", "samp21-utm.ply", "samp21-utm.json")
    _same_files(tmp_path / "dask", tmp_path / "fresh", "samp21-utm.ply", "samp21-utm.json")
