"""Tiled runs of a COPC file (kbs.tiles.copc): each tile reads its buffered bounds by a query of
the file's octree, no pass routes the points to the tiles, and the bytes written are those of the
same file read as a plain LAZ file by the spill path (KBS_COPC=0). The COPC files are written in
the test from a shared airborne LAS by copc-lib (tests/copc_files.py), with an octree of 4 levels."""
from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from test_cli import kbs as kbs_cmd
from test_tiles_streamed import _normalised

copclib = pytest.importorskip("copclib", reason="copc-lib's bindings are not installed: pip install copclib "
                                                "(it is in kbs[test])")


@pytest.fixture
def copc_file(shared_data, tmp_path) -> Path:
    from copc_files import write_copc

    path = tmp_path / "sample_c.copc.laz"
    assert write_copc(shared_data / "las" / "sample_c.las", path, levels=4) > 20  # a real octree: many nodes
    return path


def _kbs_env(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    import shutil
    import sys

    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    assert exe
    full = {k: v for k, v in os.environ.items() if k != "COLUMNS"} | env
    return subprocess.run([exe, *args], capture_output=True, text=True, env=full, timeout=300)


def test_a_tile_read_by_the_octree_holds_the_points_and_order_of_the_grid_s_tile(copc_file, tmp_path):
    """read_tile: the rows, core and coordinates of each tile are those TileGrid.tiles gives on the
    whole file read as LAZ, and no tile decompresses the whole file."""
    import laspy

    from kbs.tiles import TileGrid
    from kbs.tiles.copc import copc_nodes, read_tile, tile_box, CopcCloud

    las = laspy.read(str(copc_file))
    X = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    xyz = tmp_path / "xyz.npy"  # the coordinates in file order, as read_copc writes them
    np.save(xyz, X)
    table, bounds, header = copc_nodes(copc_file)
    assert int(table[:, 6].sum()) == len(X) and len(np.unique(table[:, 0])) == 4
    cloud = CopcCloud(xyz=X, index=np.arange(len(X)), grid=None, tiles=[], header=header, folder=Path("."),
                      nodes=table, bounds=bounds)
    for size, buffer in ((30.0, 10.0), (20.0, 3.0)):
        grid = TileGrid.fit(X, size, buffer)
        expected = {t.name: t for t in grid.tiles(X)}
        for i in range(grid.shape[0]):
            for j in range(grid.shape[1]):
                rows, core, pts, read = read_tile(str(copc_file), cloud.nodes_of(*tile_box(grid, i, j)), grid, i, j)
                again = read_tile(str(copc_file), cloud.nodes_of(*tile_box(grid, i, j)), grid, i, j, str(xyz))
                assert all(np.array_equal(a, b) for a, b in zip((rows, core, pts, read), again))
                t = expected.get(f"t{i}_{j}")
                if t is None:
                    assert not core.any()
                    continue
                assert np.array_equal(rows, t.index) and np.array_equal(core, t.in_core)
                assert np.array_equal(pts, X[t.index])
                if grid.shape[0] > 2 and grid.shape[1] > 2 and 0 < i < grid.shape[0] - 1 and 0 < j < grid.shape[1] - 1:
                    assert read < len(X)  # an inner tile reads part of the file


@pytest.mark.slow  # three whole tiled runs, one on a LocalCluster of 2 workers
def test_a_copc_file_tiled_by_its_octree_gives_the_bytes_of_the_spill_path(copc_file, tmp_path):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    args = ["run", "--rules", "airborne", "--tile", "30", str(copc_file)]
    plain = _kbs_env("-q", *args, "-j", "1", "--out", str(tmp_path / "plain"), env={"KBS_COPC": "0"})
    assert plain.returncode == 0, plain.stderr
    here = kbs_cmd(*args, "-j", "1", "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr
    m = re.search(r"a COPC file: each of its (\d+) tiles read the nodes of its octree that meet its buffered bounds "
                  r"\(at most ([\d,]+) of its ([\d,]+) points for one tile", here.stderr)
    assert m, here.stderr
    assert int(m.group(2).replace(",", "")) < int(m.group(3).replace(",", "")) == 14408
    assert "read by its octree" not in plain.stderr and "a COPC file" not in plain.stderr
    names = ("sample_c.copc.laz", "sample_c.copc.json")
    for name in names:
        assert _normalised(tmp_path / "here" / name) == _normalised(tmp_path / "plain" / name), name
    assert '"stitched":[' in (tmp_path / "here" / names[1]).read_text()
    dask = kbs_cmd("-q", *args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    for name in names:
        assert _normalised(tmp_path / "dask" / name) == _normalised(tmp_path / "plain" / name), name
    for out in ("plain", "here", "dask"):  # the spill folder and the tile files are gone
        assert sorted(p.name for p in (tmp_path / out).iterdir()) == sorted(names)


@pytest.mark.slow  # a whole tiled run
def test_a_copc_file_is_never_spilled_nor_routed_by_a_pass_over_its_chunks(copc_file, tmp_path, monkeypatch):
    """In process, with the spill path's chunked reader and spill_las made to fail: the run reads
    the file by its octree; every tile reads the rows of its nodes, less than the whole file."""
    from click.testing import CliRunner

    from kbs.cli.main import cli
    from kbs.tiles import copc, stream

    def forbidden(*args, **kwargs):
        raise AssertionError("the file was read by the spill path")

    monkeypatch.setattr(stream, "_chunks", forbidden)
    monkeypatch.setattr(stream, "spill_las", forbidden)
    reads = []
    original = copc.read_tile

    def spy(path, nodes, grid, i, j, xyz=None):
        out = original(path, nodes, grid, i, j, xyz)
        reads.append(out[3])
        return out

    monkeypatch.setattr(copc, "read_tile", spy)
    r = CliRunner().invoke(cli, ["-q", "run", "--rules", "airborne", "--tile", "30", "-j", "1", str(copc_file),
                                 "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, (r.output, r.exception)
    assert len(reads) == 9 and all(0 < k < 14408 for k in reads), reads
    assert sum(reads) > 14408  # the coarse levels are read by every tile: a tile is its nodes, not a slice


@pytest.mark.slow  # subprocesses
@pytest.mark.parametrize("damage", ["truncated", "hierarchy cut", "count", "garbled node"])
def test_a_damaged_copc_file_is_a_positioned_file_error(copc_file, tmp_path, damage):
    data = bytearray(copc_file.read_bytes())
    bad = tmp_path / "bad.copc.laz"
    if damage == "truncated":  # the file cut in its points: the hierarchy (at its end) is gone
        bad.write_bytes(bytes(data[: len(data) // 2]))
        expected = r"is truncated: its COPC hierarchy \(bytes [\d,]+ to [\d,]+\) reaches past the end of the file"
    elif damage == "hierarchy cut":  # the last bytes cut: the last entry of the hierarchy is gone
        bad.write_bytes(bytes(data[:-10]))
        expected = r"is truncated: its COPC hierarchy"
    elif damage == "garbled node":  # bytes of the points (after the header and VLRs) overwritten
        data[5000:9000] = np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes()
        bad.write_bytes(bytes(data))
        expected = r"cannot decompress COPC octree node \d+-\d+-\d+-\d+ \(bytes [\d,]+ to [\d,]+\): "
    else:  # the header's point count changed (LAS 1.4: 64 bits at byte 247)
        data[247:255] = (int.from_bytes(data[247:255], "little") + 5).to_bytes(8, "little")
        bad.write_bytes(bytes(data))
        expected = r"its COPC octree's nodes hold 14,408 points, its header says 14,413"
    r = kbs_cmd("run", "--rules", "airborne", "--tile", "30", "-j", "1", str(bad), "--out", str(tmp_path / "out"))
    assert r.returncode == 3, r.stderr
    assert re.search(expected, r.stderr) and str(bad) in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.slow  # a whole run
def test_a_copc_file_run_whole_is_written_as_plain_laz_without_its_copc_records(copc_file, tmp_path):
    """laspy cannot write a COPC file's records: the result drops them (it is not ordered by an octree)."""
    import laspy

    r = kbs_cmd("-q", "run", "--rules", "airborne", "-j", "1", str(copc_file), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    out = laspy.read(str(tmp_path / "out" / copc_file.name))
    assert len(out.points) == 14408 and "cluster" in out.point_format.extra_dimension_names
    assert not [v for v in [*out.header.vlrs, *(out.header.evlrs or [])] if v.user_id == "copc"]


@pytest.mark.slow  # two tiled runs
def test_a_copc_file_with_a_stray_point_reads_only_the_tiles_holding_points(shared_data, tmp_path):
    """A COPC file with one stray point 3,000 km away: tiles of 30 m make a grid of 10^10 cells.
    Every cell was a tile to read (an array of 10^10 tiles: out of memory); now, past 10^7 cells,
    only the cells holding points are, and the bytes are those of the file read as a plain LAZ
    (the spill path, whose counts per cell went sparse too)."""
    import laspy

    from copc_files import write_copc

    las = laspy.read(str(shared_data / "las" / "sample_c.las"))
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    xyz = np.vstack([xyz, xyz.max(axis=0) + [3e6, 3e6, 0.0]])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(xyz.min(axis=0)), np.array([0.01, 0.01, 0.01])
    crs = las.header.parse_crs()
    if crs is not None:
        header.add_crs(crs)
    out = laspy.LasData(header)
    out.x, out.y, out.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out.write(str(tmp_path / "stray.las"))
    path = tmp_path / "stray.copc.laz"
    assert write_copc(tmp_path / "stray.las", path, levels=4) > 5
    args = ["run", "--rules", "airborne", "--tile", "30", "-j", "1", str(path)]
    plain = _kbs_env("-q", *args, "--out", str(tmp_path / "plain"), env={"KBS_COPC": "0"})
    assert plain.returncode == 0, plain.stderr
    here = kbs_cmd(*args, "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr
    assert "a COPC file: each of its" in here.stderr
    for name in ("stray.copc.laz", "stray.copc.json"):
        assert _normalised(tmp_path / "here" / name) == _normalised(tmp_path / "plain" / name), name
