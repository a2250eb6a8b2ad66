"""Tiled runs beyond one cloud in memory: the whole cloud's ground plane given to every tile, LAS/LAZ
read and written in chunks (kbs run --tile --chunk-points), folders of scans on Dask."""
from __future__ import annotations

import json
import re
from pathlib import Path

import laspy
import numpy as np
import pytest

from kbs.errors import ParameterError
from kbs.tiles import TileGrid
from kbs.tiles.grid import MAX_BUFFER_TILES
from kbs.tiles.stream import SpilledTiles, spill_las
from scenes import ground_and_rocks, outdoor_rejecting_fragments
from test_cli import kbs as kbs_cmd


def _write_las(path: Path, X: np.ndarray, *, extra: dict[str, np.ndarray] | None = None, scale: float = 1e-4) -> None:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(X.min(axis=0)), np.array([scale, scale, scale])
    for name, values in (extra or {}).items():
        header.add_extra_dim(laspy.ExtraBytesParams(name, values.dtype, description=f"input {name}"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.intensity = np.arange(len(X), dtype=np.uint16)
    las.classification = np.ones(len(X), dtype=np.uint8)
    for name, values in (extra or {}).items():
        las[name] = values
    las.write(str(path))


def _without_run_id(path: Path) -> bytes:
    """The file's bytes with the run id (32 hex digits in the kbs VLR) blanked."""
    data = path.read_bytes()
    return re.sub(rb"[0-9a-f]{32}", b"0" * 32, data, count=1)


# -- the tiles of a file read in chunks are the tiles of the cloud in memory ------------------------


@pytest.mark.parametrize("size, buffer, chunk", [(3.0, 0.5, 700), (2.5, 3.0, 1000), (100.0, 1.0, 333), (4.0, 0.0, 5000),
                                                        # a buffer of whole tiles, and a rounding short of one
                                                        (2.0, 4.0, 900), (2.0, 2.0, 900), (3.0, 2.9999999999999, 900)])
def test_the_tiles_of_a_las_spilled_in_chunks_are_the_tiles_of_the_cloud_in_memory(tmp_path, size, buffer, chunk):
    rng = np.random.default_rng(5)
    X = rng.uniform([-7, 2, 0], [6, 11, 3], (4000, 3)).round(4)
    _write_las(tmp_path / "a.las", X)
    X = laspy.read(tmp_path / "a.las").xyz.astype(np.float64)
    spilled = spill_las(tmp_path / "a.las", tmp_path / "spill", size, buffer, chunk_points=chunk)
    grid = TileGrid.fit(X, size, buffer)
    expected = grid.tiles(X)
    assert (spilled.grid.origin, spilled.grid.shape) == (grid.origin, grid.shape)
    assert [t.name for t in spilled.tiles] == [t.name for t in expected]
    for got, want in zip(spilled.tiles, expected):
        np.testing.assert_array_equal(got.index, want.index)
        np.testing.assert_array_equal(got.in_core, want.in_core)
        assert got.core == want.core
    np.testing.assert_array_equal(spilled.xyz, X)
    # the tiles are held as arrays (SpilledTiles), each tile made when asked for: its counts, its
    # place by cell and by name, as the list of tiles gives them
    tiles = spilled.tiles
    assert isinstance(tiles, SpilledTiles) and tiles.i.dtype == np.int32
    assert list(tiles.names) == [t.name for t in expected] and tiles.names[-1] == expected[-1].name
    assert [t.name for t in tiles[1::2]] == [t.name for t in expected[1::2]]
    for k, t in enumerate(expected):
        assert tiles.at(t.i, t.j) == k == tiles.names.index(t.name) and t.name in tiles.names
        assert (tiles[k].n_points, tiles[k].n_core) == (t.index.size, int(np.count_nonzero(t.in_core)))
    held = {(t.i, t.j) for t in expected}
    empty = [(i, j) for i in range(-1, grid.shape[0] + 1) for j in range(-1, grid.shape[1] + 1) if (i, j) not in held]
    assert all(tiles.at(i, j) is None for i, j in empty)
    assert "t999_0" not in tiles.names and "x" not in tiles.names
    with pytest.raises(ValueError):
        tiles.names.index(f"t{empty[0][0]}_{empty[0][1]}")
    with pytest.raises(IndexError):
        tiles[len(tiles)]
    spilled.remove()
    assert not (tmp_path / "spill").exists()


# -- through the command ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rocks_las(tmp_path_factory) -> Path:
    """The rocks scene as LAS 1.4 with an intensity, and an extra dimension named like a result
    ('cluster': kept as cluster_in), 16,500 points."""
    X, labels = ground_and_rocks()
    path = tmp_path_factory.mktemp("las") / "rocks.las"
    _write_las(path, X, extra={"cluster": labels.astype(np.int32)})
    return path


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_las_read_and_written_in_chunks_gives_the_bytes_of_the_in_memory_run(rocks_las, tmp_path, suffix):
    scan = rocks_las
    if suffix == ".laz":
        scan = tmp_path / "rocks.laz"
        laspy.read(rocks_las).write(str(scan))
    args = ["-q", "run", "--rules", "outdoor", "-j", "1", "--tile", "6", "--buffer", "1.5", str(scan)]
    streamed = kbs_cmd(*args, "--chunk-points", "4000", "--out", str(tmp_path / "streamed"))  # 5 chunks
    assert streamed.returncode == 0, streamed.stderr
    whole = kbs_cmd(*args, "--chunk-points", "0", "--out", str(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    a, b = tmp_path / "streamed" / f"rocks{suffix}", tmp_path / "whole" / f"rocks{suffix}"
    if suffix == ".las":
        assert _without_run_id(a) == _without_run_id(b)
    las_a, las_b = laspy.read(a), laspy.read(b)
    assert las_a.points.array.tobytes() == las_b.points.array.tobytes()
    assert "cluster_in" in las_a.point_format.extra_dimension_names
    np.testing.assert_array_equal(las_a["cluster_in"], laspy.read(rocks_las)["cluster"])
    doc_a = json.loads((tmp_path / "streamed" / "rocks.json").read_text())
    doc_b = json.loads((tmp_path / "whole" / "rocks.json").read_text())
    for doc in (doc_a, doc_b):
        doc.pop("run_id")
        doc["summary"].pop("seconds")
    assert doc_a == doc_b
    assert sorted(p.name for p in (tmp_path / "streamed").iterdir()) == ["rocks.json", f"rocks{suffix}"]  # spill gone


def test_chunk_points_needs_tile(rocks_las, tmp_path):
    r = kbs_cmd("run", "--rules", "outdoor", "--chunk-points", "1000", str(rocks_las), "--out", str(tmp_path))
    assert r.returncode == 2 and "--chunk-points only applies to a tiled run: give --tile SIZE too" in r.stderr


@pytest.mark.slow
def test_every_tile_takes_the_ground_plane_of_the_whole_cloud(tmp_path):
    """The rocks scene tilted 3 degrees: the untiled run's ground plane is the one every tile of
    the tiled run is given (none finds its own), and the explanation says so."""
    from kbs.io import write_ply

    X, _ = ground_and_rocks()
    t = np.radians(3.0)
    R = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    path = tmp_path / "tilted.ply"
    write_ply(path, X @ R.T, {})
    base = ["-q", "run", "--rules", "outdoor", "-j", "1", str(path)]
    assert kbs_cmd(*base, "--out", str(tmp_path / "whole")).returncode == 0
    r = kbs_cmd(*base, "--tile", "6", "--buffer", "1.5", "--out", str(tmp_path / "tiled"))
    assert r.returncode == 0, r.stderr
    whole = json.loads((tmp_path / "whole" / "tilted.json").read_text())["explanation"]["ground"]
    tiled = json.loads((tmp_path / "tiled" / "tilted.json").read_text())["explanation"]["ground"]
    assert tiled["normal"] == whole["normal"] and tiled["point"] == whole["point"]
    assert tiled["source"] == f"whole cloud: {whole['source']}"
    assert tiled["scope"] == "found once on the whole cloud (16,500 points), the same for every tile"
    assert len(tiled["tiles"]) == 4
    for ground in tiled["tiles"].values():
        assert ground["normal"] == whole["normal"] and ground["source"] == tiled["source"]
    r = kbs_cmd("run", "--rules", "outdoor", "-j", "1", str(path), "--tile", "6", "--buffer", "1.5",
                "--out", str(tmp_path / "tiled2"))
    assert f"ground: whole cloud: {whole['source']}" in r.stdout


# -- a folder of scans on Dask ------------------------------------------------------------------------


def _normalised_folder(folder: Path) -> dict[str, object]:
    out: dict[str, object] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix == ".json":
            doc = json.loads(path.read_text())
            assert doc.pop("run_id") and doc["summary"].pop("seconds") >= 0
            out[path.name] = doc
        else:
            out[path.name] = re.sub(rb"comment kbs_run_id [0-9a-f]+\n", b"", path.read_bytes())
    return out


@pytest.mark.slow
def test_a_folder_of_scans_on_a_local_dask_cluster_gives_the_outputs_of_one_process(tmp_path):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    from kbs.io import write_ply

    scans = tmp_path / "scans"
    scans.mkdir()
    for seed in (3, 4, 5):
        X, _ = ground_and_rocks(seed)
        write_ply(scans / f"rocks{seed}.ply", X[::2], {})
    (scans / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    args = ["run", "--rules", "outdoor", str(scans)]
    here = kbs_cmd(*args, "-j", "1", "--out", str(tmp_path / "here"))
    dask = kbs_cmd(*args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert here.returncode == dask.returncode == 3, (here.stderr, dask.stderr)  # the broken scan's code
    assert _normalised_folder(tmp_path / "dask") == _normalised_folder(tmp_path / "here")
    assert len(_normalised_folder(tmp_path / "here")) == 6
    assert "kbs: Dask dashboard: http" in dask.stderr
    error = [line for line in here.stderr.splitlines() if line.startswith("kbs: error:")]
    assert len(error) == 1 and error[0] in dask.stderr.splitlines()
    # the same lines per scan, in scan order, then the time table
    assert [line.split(":")[0] for line in dask.stdout.splitlines() if line.startswith(str(scans))] == \
        [line.split(":")[0] for line in here.stdout.splitlines() if line.startswith(str(scans))]
    assert "4 scans (1 failed)" in dask.stdout


def test_scheduler_for_one_untiled_scan_is_a_usage_error(rocks_las, tmp_path):
    r = kbs_cmd("run", "--rules", "outdoor", "--scheduler", "local", str(rocks_las), "--out", str(tmp_path))
    assert r.returncode == 2
    assert "--scheduler only applies to a tiled run: give --tile SIZE too (or several scans: a folder's scans run " \
           "as Dask tasks); rule base 'outdoor' has no limits.tile" in r.stderr


# -- a few far points: a grid of millions of cells, nearly all empty --------------------------------


def _tiles_by_definition(X: np.ndarray, grid: TileGrid) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """What each tile holds, from the definition: the cells holding a point's core, and for each the
    points inside its core widened by the buffer (the grid's outer edges reaching everything)."""
    uv = X @ grid.axes.T
    ij = grid.cells(uv)
    out = {}
    for i, j in sorted({(int(a), int(b)) for a, b in ij}):
        lo = [grid.origin[k] + c * grid.size - grid.buffer for k, c in ((0, i), (1, j))]
        hi = [grid.origin[k] + (c + 1) * grid.size + grid.buffer for k, c in ((0, i), (1, j))]
        lo = [-np.inf if c == 0 else v for c, v in zip((i, j), lo)]
        hi = [np.inf if c == grid.shape[k] - 1 else v for k, (c, v) in enumerate(zip((i, j), hi))]
        index = np.flatnonzero((uv[:, 0] >= lo[0]) & (uv[:, 0] <= hi[0]) & (uv[:, 1] >= lo[1]) & (uv[:, 1] <= hi[1]))
        out[f"t{i}_{j}"] = (index, (ij[index, 0] == i) & (ij[index, 1] == j))
    return out


@pytest.mark.parametrize("dense", [True, False])
def test_far_points_make_a_huge_sparse_grid_whose_tiles_are_those_holding_points(tmp_path, dense, monkeypatch):
    """A cloud of 500 points in 30 m and three points thousands of km away: tiles of 10 m make a grid
    of 2.5 x 10^11 cells. Before, TileGrid.tiles visited every cell (an airborne scan with a stray
    point ran for ever) and the spill held a count per cell (MemoryError); now both visit only the
    cells holding points, and give the tiles of the definition. ``dense=False`` also puts a grid of
    a few cells through the spill's sparse counts, which must agree with its array."""
    from kbs.tiles import stream

    rng = np.random.default_rng(3)
    X = np.vstack([rng.uniform([0, 0, 0], [30, 30, 2], (500, 3)),
                   [[5e6, 5e6, 1.0], [5e6 + 3, 5e6 + 4, 1.0], [1e3, 4.9e6, 0.0]]]).round(3)
    _write_las(tmp_path / "far.las", X, scale=1e-2)
    X = laspy.read(tmp_path / "far.las").xyz.astype(np.float64)
    grid = TileGrid.fit(X, 10.0, 2.0)
    assert grid.shape[0] * grid.shape[1] > 10 ** 11
    want = _tiles_by_definition(X, grid)
    got = grid.tiles(X)
    assert [t.name for t in got] == list(want)  # row by row
    for t in got:
        np.testing.assert_array_equal(t.index, want[t.name][0])
        np.testing.assert_array_equal(t.in_core, want[t.name][1])
    if not dense:
        monkeypatch.setattr(stream._Counts, "DENSE", 0)
        _write_las(tmp_path / "near.las", X[:500], scale=1e-2)
        near = laspy.read(tmp_path / "near.las").xyz.astype(np.float64)
        spilled_near = spill_las(tmp_path / "near.las", tmp_path / "spill-near", 10.0, 2.0, chunk_points=97)
        expected = TileGrid.fit(near, 10.0, 2.0).tiles(near)
        assert [t.name for t in spilled_near.tiles] == [t.name for t in expected]
        for got_t, want_t in zip(spilled_near.tiles, expected):
            assert (got_t.n_points, got_t.n_core) == (want_t.index.size, int(np.count_nonzero(want_t.in_core)))
            np.testing.assert_array_equal(got_t.index, want_t.index)
    spilled = spill_las(tmp_path / "far.las", tmp_path / "spill", 10.0, 2.0, chunk_points=97)
    assert spilled.grid.shape == grid.shape
    assert [t.name for t in spilled.tiles] == list(want)
    for t in spilled.tiles:
        np.testing.assert_array_equal(t.index, want[t.name][0])
        np.testing.assert_array_equal(t.in_core, want[t.name][1])


def test_a_tile_size_whose_grid_a_number_cannot_index_is_a_parameter_error():
    from kbs.errors import ParameterError

    X = np.array([[0.0, 0.0, 0.0], [1e15, 1e15, 0.0]])
    with pytest.raises(ParameterError, match=r"tiles of 1e-05 over a cloud 1e\+15 x 1e\+15 wide would make .* more "
                                             r"than a tile's number can index \(2\^62\): a larger tile size"):
        TileGrid.fit(X, 1e-5, 0.0)


@pytest.mark.slow  # a real scan, four kbs processes: pytest --runslow (CI) runs it
@pytest.mark.parametrize("form", ["las", "npy"])
def test_a_stray_point_thousands_of_km_away_leaves_the_scan_s_labels_as_they_were(shared_data, tmp_path, form):
    """An airborne scan with one stray point 3,000 km away (a bad GPS fix): its rule base tiles it
    (wider than limits.tile.wider_than), over a grid of 9 x 10^8 cells. Before, the run never ended
    (the in-memory tiles visited every cell) or ran out of memory (the spill's counts per cell);
    now it takes the time of the scan, the stray point is noise, and every point of the scan has
    the label of the scan run alone in the same tiles."""
    from kbs.io import read_cloud

    X = read_cloud(shared_data / "isprs" / "samp21-utm.pcd").xyz.astype(np.float64)
    stray = X.max(axis=0) + [3e6, 3e6, 0.0]  # beyond the scan: the grid's origin is the scan's
    both = np.vstack([X, stray])
    alone, far = tmp_path / f"alone.{form}", tmp_path / f"far.{form}"
    if form == "las":
        _write_las(alone, X, scale=1e-2)
        _write_las(far, both, scale=1e-2)
    else:
        np.save(alone, X)
        np.save(far, both)
    r = kbs_cmd("-q", "run", "--rules", "airborne", "-j", "1", str(far), "--out", str(tmp_path / "o"), "--out-format", "ply")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "o" / "far.json").read_text())
    assert doc["tiled_by"]["from"] == "limits.tile" and doc["tiling"]["shape"][0] * doc["tiling"]["shape"][1] > 10 ** 8
    ref = kbs_cmd("-q", "run", "--rules", "airborne", "-j", "1", "--tile", "100", str(alone), "--out", str(tmp_path / "r"),
                  "--out-format", "ply")
    assert ref.returncode == 0, ref.stderr
    from plyfile import PlyData

    got = np.asarray(PlyData.read(str(tmp_path / "o" / "far.ply"))["vertex"]["scalar_label"])
    want = np.asarray(PlyData.read(str(tmp_path / "r" / "alone.ply"))["vertex"]["scalar_label"])
    np.testing.assert_array_equal(got[:-1], want)
    assert got[-1] == -1  # the stray point: noise


def test_a_streamed_run_with_no_cluster_at_all_writes_what_the_in_memory_run_writes(tmp_path):
    """Ten points 50 m apart, tiled: every point is noise and no tile has a cluster (the outdoor
    rules as before session 41, rejecting clusters of 15 points or fewer). The streamed LAS run
    crashed writing the explanation (IndexError in record_texts: an empty array of roots indexed;
    the shipped simple.las with the airborne rules did it too); now its JSON is the PLY run's."""
    rng = np.random.default_rng(0)
    _write_las(tmp_path / "ten.las", rng.uniform(0, 50, (10, 3)), scale=1e-3)
    rules = outdoor_rejecting_fragments(tmp_path)
    for fmt in ("las", "ply"):
        r = kbs_cmd("-q", "run", "--rules", rules, "--tile", "100", "--out-format", fmt, str(tmp_path / "ten.las"),
                    "--out", str(tmp_path / fmt))
        assert r.returncode == 0, r.stderr
    docs = []
    for fmt in ("las", "ply"):
        doc = json.loads((tmp_path / fmt / "ten.json").read_text())
        docs.append((doc["summary"]["points_per_label"], doc["clusters"], doc["explanation"]))
    assert docs[0] == docs[1] and docs[0][1] == [] and docs[0][0]["noise"] == 10


def test_a_buffer_far_wider_than_the_grid_gives_every_tile_every_point(tmp_path):
    """A buffer reaching past the whole grid: the spill looped over buffer / size cells each way
    for every chunk (--buffer 1e9 on tiles of 20 m: 5 x 10^7, a hang, memory growing); the reach is
    now the grid's, and each tile holds the whole cloud. A buffer wider than MAX_BUFFER_TILES tiles
    (--buffer 1e9 on tiles of 20) is refused before any chunk is read."""
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 100, (1010, 3)).round(3)
    _write_las(tmp_path / "k.las", X, scale=1e-3)
    buffer = MAX_BUFFER_TILES * 20.0  # 90 m: past every edge of a 100 m cloud from any tile
    spilled = spill_las(tmp_path / "k.las", tmp_path / "spill", 20.0, buffer, chunk_points=300)
    X = laspy.read(tmp_path / "k.las").xyz.astype(np.float64)
    expected = TileGrid.fit(X, 20.0, buffer).tiles(X)
    assert [t.name for t in spilled.tiles] == [t.name for t in expected]
    assert all(t.n_points == len(X) for t in spilled.tiles)
    with pytest.raises(ParameterError, match=r"tiles of 20 with a buffer of 1e\+09: .* give tiles of at least "
                                             r"2\.22e\+08, or a smaller buffer"):
        spill_las(tmp_path / "k.las", tmp_path / "spill2", 20.0, 1e9, chunk_points=300)
    assert not (tmp_path / "spill2").exists() or not any((tmp_path / "spill2").iterdir())
