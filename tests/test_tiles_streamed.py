"""Tiled runs of a LAS/LAZ file with the stitching process's memory bounded by the tile size
(kbs.tiles.streamed): the tiles' results stay in their files, the links come from the points near
the tiles' edges, the output is computed and written from files in chunks, and the bytes written
are those of the in-memory path (--chunk-points 0)."""
from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import laspy
import numpy as np
import pytest

from kbs.errors import KbsError
from kbs.inference import cluster_geometry
from kbs.tiles import streamed
from kbs.tiles import TileGrid
from kbs.tiles.stream import spill_las
from kbs.tiles.streamed import TileJob, Texts, _descriptors, _edge_mask, _new_column
from scenes import ground_and_rocks, outdoor_rejecting_fragments
from test_cli import kbs as kbs_cmd


def _normalised(path: Path) -> bytes:
    """A result file's bytes with its run id (32 hex digits) and the JSON's timing blanked."""
    data = re.sub(rb"[0-9a-f]{32}", b"0" * 32, path.read_bytes())
    return re.sub(rb'"seconds":[0-9.e+-]+', b'"seconds":0', data)


# -- the parts --------------------------------------------------------------------------------------


@pytest.mark.parametrize("size, buffer", [(10.0, 0.5), (7.5, 2.0), (3.0, 5.0), (6.0, 1.5)])
def test_every_point_a_tile_shares_with_another_is_in_its_edge_points(size, buffer):
    """The links are computed from each tile's edge points alone: every point two tiles hold
    must be among the edge points of both (else a crossing cluster would not be stitched)."""
    X = np.random.default_rng(9).uniform([-20, 5, 0], [13, 31, 4], (4000, 3))
    grid = TileGrid.fit(X, size, buffer)
    tiles = grid.tiles(X)
    edges = {t.name: set(t.index[_edge_mask(grid, t, X[t.index] @ grid.axes.T)].tolist()) for t in tiles}
    held = {}
    for t in tiles:
        for i in t.index.tolist():
            held.setdefault(i, []).append(t.name)
    shared = {i: names for i, names in held.items() if len(names) > 1}
    assert shared  # the case is tested
    for i, names in shared.items():
        for name in names:
            assert i in edges[name], (i, name)
    interior = sum(len(t.index) - len(edges[t.name]) for t in tiles)
    assert size < 2 * buffer or interior > 0  # and the edge points are not simply every point


@pytest.mark.slow
@pytest.mark.parametrize("jit", [True, False])
def test_the_descriptors_summed_in_chunks_are_cluster_geometry_to_the_last_bit(tmp_path, monkeypatch, jit):
    from kbs.inference import _flags
    from kbs.tiles import streamed

    monkeypatch.setattr(_flags, "JIT", jit)
    monkeypatch.setattr(streamed, "CHUNK_POINTS", 777)  # clusters spread over many chunks
    rng = np.random.default_rng(2)
    n, k = 5000, 7
    X = rng.normal(0, 1, (n, 3)) * [30, 20, 2] + [4.5e5, 5.4e6, 80]
    cl = rng.integers(-1, k, n).astype(np.int32)
    u = rng.uniform(0.05, 1, n).astype(np.float32)
    np.save(tmp_path / "xyz.npy", X)
    cols = {}
    for name, values in (("cluster", cl), ("membership", u)):
        cols[name] = _new_column(tmp_path / f"{name}.npy", values.dtype, n)
        mm = np.load(cols[name].path, mmap_mode="r+")
        mm[:] = values
        del mm
    got = _descriptors(tmp_path / "xyz.npy", cols["cluster"], cols["membership"], k)
    for c in range(k):
        idx = np.flatnonzero(cl == c)
        want = cluster_geometry(X[idx], u.astype(np.float64)[idx])
        assert got["center"][c].tobytes() == want.center.tobytes()
        assert got["eigenvalues"][c].tobytes() == want.eigenvalues.tobytes()
        assert got["eigenvectors"][c].tobytes() == want.eigenvectors.tobytes()
        assert got["mass"][c] == want.mass
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setattr(streamed, "DESCRIPTOR_STEP", 3)  # clusters over several steps
    in_files = _descriptors(tmp_path / "xyz.npy", cols["cluster"], cols["membership"], k, out)
    for name, a in got.items():  # the same numbers, filled in files and mapped back
        assert isinstance(in_files[name], np.memmap) and in_files[name].tobytes() == np.asarray(a).tobytes()
    assert sorted(p.name for p in out.iterdir()) == sorted(f"out-{name}.npy" for name in got)


def test_a_tile_task_carries_paths_not_points(tmp_path):
    """What is sent to a Dask worker for a tile is a few hundred bytes, whatever its points."""
    rng = np.random.default_rng(1)
    X = rng.uniform([0, 0, 0], [100, 100, 5], (60_000, 3))
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.write(str(tmp_path / "a.las"))
    spilled = spill_las(tmp_path / "a.las", tmp_path / "spill", 50.0, 5.0)
    tile = spilled.tiles[0]
    assert tile.index.size > 15_000
    job = TileJob(str(spilled.folder / "xyz.npy"), tile, spilled.grid, str(tmp_path / "store"), b"x" * 32, False)
    assert len(pickle.dumps(job)) < 2_000
    spilled.remove()


def test_a_worker_that_cannot_read_the_spill_folder_says_it_needs_a_shared_file_system(tmp_path):
    from kbs.errors import ParameterError
    from kbs.tiles.stream import SpilledTile
    from kbs.tiles.streamed import run_job

    tile = SpilledTile("t0_0", 0, 0, (0.0, 0.0, 10.0, 10.0), tmp_path / "elsewhere", 10, 10)
    job = TileJob(str(tmp_path / "elsewhere" / "xyz.npy"), tile, TileGrid.fit(np.zeros((1, 3)), 10.0, 1.0),
                  str(tmp_path / "store"), b"x" * 32, False)
    with pytest.raises(ParameterError, match=r"this worker cannot read the tile's points \(No such file or directory: "
                                             r".*elsewhere/t0_0.idx\): the workers of a Dask scheduler read the tiles"):
        run_job(lambda X: None, job, (None, {}))


# -- through the command: the bytes of the in-memory path ---------------------------------------------


@pytest.mark.slow  # a whole real scan three times, once on Dask: pytest --runslow (CI) runs it
def test_a_real_airborne_las_tiled_and_streamed_gives_the_bytes_of_the_in_memory_run(shared_data, tmp_path):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    scan = shared_data / "las" / "sample_c.las"  # airborne, an urban block 83 m x 75 m: 12 tiles of 25 m
    args = ["-q", "run", "--rules", "airborne", "--tile", "25", "--buffer", "6", str(scan)]
    whole = kbs_cmd(*args, "-j", "1", "--chunk-points", "0", "--out", str(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    here = kbs_cmd(*args, "-j", "1", "--chunk-points", "5000", "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr
    dask = kbs_cmd(*args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert dask.returncode == 0, dask.stderr
    doc = (tmp_path / "whole" / "sample_c.json").read_text()
    assert '"tiles":[{"name":"t0_0"' in doc and doc.count('"core_points"') >= 9
    assert '"stitched":[' in doc  # clusters crossing tile edges were merged
    # both notes stitching adds to a tile's records (the streamed runs write them into the tasks' texts)
    assert "stitched across tile edges into output cluster" in doc and "only in the buffer of tile" in doc
    for name in ("sample_c.las", "sample_c.json"):
        assert _normalised(tmp_path / "here" / name) == _normalised(tmp_path / "whole" / name), name
        assert _normalised(tmp_path / "dask" / name) == _normalised(tmp_path / "whole" / name), name
    for out in ("here", "dask"):  # the spill folder and the tile files are gone
        assert sorted(p.name for p in (tmp_path / out).iterdir()) == ["sample_c.json", "sample_c.las"]


def test_a_streamed_run_on_a_scan_with_too_large_coordinates_names_the_row_and_counts_them_all(tmp_path):
    X, _ = ground_and_rocks()
    X = X[:3000].copy()
    X[[2500, 2900], 0] = 2e50
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.offsets, header.scales = np.zeros(3), np.array([1e44, 1e-3, 1e-3])
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.write(str(tmp_path / "big.las"))
    base = ["run", "--rules", "outdoor", "-j", "1", "--tile", "6", str(tmp_path / "big.las")]
    streamed = kbs_cmd(*base, "--chunk-points", "1000", "--out", str(tmp_path / "a"))
    whole = kbs_cmd(*base, "--chunk-points", "0", "--out", str(tmp_path / "b"))
    assert streamed.returncode == whole.returncode == 3, (streamed.stderr, whole.stderr)
    assert "2 points have a coordinate beyond" in whole.stderr and "first: row 2500" in whole.stderr
    assert streamed.stderr == whole.stderr and "Traceback" not in streamed.stderr


def test_a_streamed_run_whose_last_tile_holds_only_noise_is_the_run_in_memory(tmp_path):
    """The last tile in row order holds a few points alone, rejected as noise: it has no cluster,
    and its points' output cluster is -1 (the stitching looked up a cluster past the last one: an
    IndexError, found at 20 m tiles of the 2x10^5-point bench cloud). The outdoor rules as before
    session 41, which rejected clusters of 15 points or fewer (now only a point alone)."""
    X, _ = ground_and_rocks()
    far = X[:5].copy()
    far[:, 0] = X[:, 0].max() + 20.0 + np.arange(5) * 0.3  # a row of tiles of its own, beyond every buffer
    X = np.vstack([X, far])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(X.min(axis=0)), np.array([1e-4, 1e-4, 1e-4])
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.write(str(tmp_path / "lone.las"))
    base = ["run", "--rules", outdoor_rejecting_fragments(tmp_path), "-j", "1", "--tile", "6", "--buffer", "1",
            str(tmp_path / "lone.las")]
    streamed = kbs_cmd(*base, "--chunk-points", "1000", "--out", str(tmp_path / "a"))
    whole = kbs_cmd(*base, "--chunk-points", "0", "--out", str(tmp_path / "b"))
    assert streamed.returncode == whole.returncode == 0, (streamed.stderr, whole.stderr)
    cluster = laspy.read(tmp_path / "a" / "lone.las")["cluster"]
    assert (cluster[-5:] == -1).all() and (cluster[:-5] >= 0).any()
    doc = json.loads((tmp_path / "a" / "lone.json").read_text())
    last = doc["tiling"]["tiles"][-1]
    assert 0 < last["points"] == last["core_points"] <= 5  # far points alone, no buffer point
    for name in ("lone.las", "lone.json"):
        assert _normalised(tmp_path / "a" / name) == _normalised(tmp_path / "b" / name), name


# -- faults: a tile that fails, a worker that dies ------------------------------------------------------


@pytest.fixture(scope="module")
def rocks_las(tmp_path_factory) -> Path:
    X, _ = ground_and_rocks()
    path = tmp_path_factory.mktemp("las") / "rocks.las"
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(X.min(axis=0)), np.array([1e-4, 1e-4, 1e-4])
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    las.write(str(path))
    return path


@pytest.mark.slow
def test_a_streamed_run_keeps_its_finished_tiles_and_resume_segments_only_the_failed_one(rocks_las, tmp_path,
                                                                                          monkeypatch):
    from test_tiles import FLAKY_PLUGIN, east_rules

    args = ["run", *east_rules(tmp_path, FLAKY_PLUGIN), "-j", "1", "--tile", "6", "--buffer", "1.5",
            "--chunk-points", "4000", str(rocks_las)]
    out, kept = tmp_path / "out", tmp_path / "out" / "rocks.tiles"
    monkeypatch.setenv("KBS_TEST_FAIL_EAST", "1")  # tile t1_1 fails, the three others are done and kept
    r = kbs_cmd(*args, "--out", str(out))
    assert r.returncode == 7, r.stderr
    assert "tile t1_1 [" in r.stderr and f"the finished tiles are kept in {kept}: run again with --resume" in r.stderr
    assert sorted(p.name for p in kept.iterdir()) == ["t0_0.npz", "t0_1.npz", "t1_0.npz"]
    assert sorted(p.name for p in out.iterdir()) == ["rocks.tiles"]  # no result, no spill folder left
    monkeypatch.delenv("KBS_TEST_FAIL_EAST")
    r = kbs_cmd(*args, "--resume", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"kbs: resumed 3 of 4 tiles from {kept}" in r.stderr
    assert not kept.exists()
    fresh = kbs_cmd(*args, "--out", str(tmp_path / "fresh"))
    assert fresh.returncode == 0, fresh.stderr
    for name in ("rocks.las", "rocks.json"):
        assert _normalised(out / name) == _normalised(tmp_path / "fresh" / name)


@pytest.mark.slow
def test_a_dask_worker_killed_in_a_streamed_run_gives_the_same_bytes(rocks_las, tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="Dask is not installed: pip install 'kbs[dask]' (it is in [test])")
    from test_tiles import KILLING_PLUGIN, east_rules

    args = ["-q", "run", *east_rules(tmp_path, KILLING_PLUGIN), "--tile", "6", "--buffer", "1.5", str(rocks_las)]
    assert kbs_cmd(*args, "-j", "1", "--out", str(tmp_path / "here")).returncode == 0
    marker = tmp_path / "killed"
    monkeypatch.setenv("KBS_TEST_KILL_MARKER", str(marker))
    r = kbs_cmd(*args, "-j", "2", "--scheduler", "local", "--out", str(tmp_path / "dask"))
    assert r.returncode == 0, r.stderr
    assert marker.read_text() == "killed"  # a worker died in a tile; Dask ran the tile again on another
    for name in ("rocks.las", "rocks.json"):
        assert _normalised(tmp_path / "dask" / name) == _normalised(tmp_path / "here" / name)


def test_packed_texts_give_back_each_string():
    texts = Texts.of(["c0", "", "c0.1.2", "t1_2/c3"])
    assert len(texts) == 4
    assert texts.slice(0, 4) == ["c0", "", "c0.1.2", "t1_2/c3"]
    assert texts.slice(2, 3) == ["c0.1.2"]
    assert texts.slice(1, 2) == [""]
    assert texts.slice(3, 3) == [] and Texts.of([]).slice(0, 0) == []


def test_packed_texts_in_a_file_give_back_each_string(tmp_path):
    from kbs.tiles.streamed import FileTexts, _mapped, _utf8

    for items in (["c0", "", "c0.1.2", "t1_2/c3"], ["sol", "", "sous-bois à 2 m", "c1"]):
        data, ends = _utf8(Texts.of(items))
        (tmp_path / "ids.bin").write_bytes(data)
        texts = FileTexts(_mapped(tmp_path / "ids.bin", np.uint8), ends)
        assert len(texts) == 4 and texts.slice(0, 4) == items
        assert texts.slice(2, 3) == [items[2]] and texts.slice(1, 2) == [""] and texts.slice(3, 3) == []
    (tmp_path / "none.bin").write_bytes(b"")
    assert FileTexts(_mapped(tmp_path / "none.bin", np.uint8), np.zeros(0, dtype=np.int64)).slice(0, 0) == []


def _anonymous_kb() -> int:
    return int(re.search(r"RssAnon:\s+(\d+) kB", Path("/proc/self/status").read_text()).group(1))


def test_the_free_heap_pages_the_stitching_process_leaves_go_back_to_the_system():
    """Arrays freed in the middle of the C heap stay resident until malloc_trim gives their
    pages back: release_free_memory does (glibc only; elsewhere it does nothing)."""
    from kbs.tiles.streamed import _malloc_trim, release_free_memory

    if not Path("/proc/self/status").exists() or _malloc_trim() is None:
        pytest.skip("needs Linux's /proc and glibc's malloc_trim")
    release_free_memory()
    blocks = [np.ones(8192) for _ in range(3000)]  # 64 KB each (under the heap's map threshold): 196 MB
    pin = np.ones(8192)  # above them: the heap's top cannot shrink past it
    del blocks
    before = _anonymous_kb()
    release_free_memory()
    after = _anonymous_kb()
    assert before - after > 100_000, (before, after)
    del pin


def test_the_links_logged_to_a_file_are_the_notes_of_the_dict_in_the_order_found(tmp_path):
    from kbs.tiles.streamed import _Links, _Marked

    rng = np.random.default_rng(3)
    names = [f"t{i}_{j}" for i in range(4) for j in range(5)]
    found = rng.integers(0, [300, len(names), 40, 5000], size=(2000, 4))  # node, other tile, its cluster, points
    found[::7, 0] = 17  # one node with many links: their order is the order found
    expected: dict[int, list[str]] = {}
    for g, t, c, k in found.tolist():
        expected.setdefault(g, []).append(f"{names[t]} cluster {c} ({k:,} shared points)")
    (tmp_path / "stitch-links.bin").write_bytes(found.astype(np.int64).tobytes())
    links = _Links.gather(tmp_path, names)
    assert not (tmp_path / "stitch-links.bin").exists()
    assert dict(links) == expected and len(links) == len(expected)
    assert all(g in links for g in expected) and 300 not in links and -1 not in links and "17" not in links
    with pytest.raises(KeyError):
        links[300]
    (tmp_path / "stitch-links.bin").write_bytes(b"")  # no link at all
    assert dict(_Links.gather(tmp_path, names)) == {}
    marked = _Marked(np.array([False, True, True, False]))
    assert [i in marked for i in range(-1, 5)] == [False, False, True, True, False, False] and len(marked) == 2


def test_a_tile_summary_gives_back_every_cluster_label_and_id_and_every_limit(rocks_las, tmp_path, monkeypatch):
    """The summary a tile sends back holds its clusters' labels and ids and its limits in a few
    arrays (one label table, one string of ids); what it gives back is the result's own, and the
    tiles' summaries kept for stitching share one head."""
    import kbs
    from kbs.tiles import streamed
    from kbs.tiles.store import TileStore

    rules = Path(kbs.__file__).parent / "rules" / "outdoor.yaml"
    text = rules.read_text()
    assert re.search(r"max_depth: \d+ ", text)
    shallow = tmp_path / "shallow.yaml"  # a limit stops some clusters
    shallow.write_text(re.sub(r"max_depth: \d+ ", "max_depth: 1 ", text))
    seg = kbs.Segmenter(str(shallow), jobs=1)
    whole = spill_las(rocks_las, tmp_path / "whole", 30.0, 1.0)  # one tile: the ground and the rocks
    tile = whole.tiles[0]
    points = np.asarray(whole.xyz)[tile.index]
    result = seg.segment(points)
    summary = streamed.summarize(tile, whole.grid, tile.index, tile.in_core, points, result)
    assert len(result.clusters) >= 2 and len({c["label"] for c in result.clusters}) >= 2
    for c, cluster in enumerate(result.clusters):
        assert summary.cluster(c) == (cluster["label"], list(cluster["ids"]))
    stopped = [r for r in result.explanation.records.values() if r.action == "limit"]
    assert stopped
    assert summary.limits() == [(r.n_points, f"{tile.name}/{r.id}", r.limit) for r in stopped]
    assert len(summary.labels) <= len(result.label_names) + 1  # a table of labels, not one per cluster
    assert isinstance(summary.ids.text, str) and len(summary.ids) == sum(len(c["ids"]) for c in result.clusters)

    whole.remove()

    spilled = spill_las(rocks_las, tmp_path / "spill", 6.0, 1.0)
    assert len(spilled.tiles) >= 4
    kept, held = [], []
    stitch = streamed._stitch
    monkeypatch.setattr(streamed, "_stitch", lambda sp, grid, tiles, briefs, *a: held.append(briefs) or
                        kept.extend(briefs) or stitch(sp, grid, tiles, briefs, *a))
    out = streamed.segment_streamed(seg, spilled, TileStore(tmp_path / "store", seg))
    assert len(kept) == len(spilled.tiles)
    # what the stitching process held of each tile while the others ran: numbers in arrays, its
    # summary in a file; no object per tile (the briefs are made again when asked for)
    (briefs,) = held
    assert isinstance(briefs, streamed.TileBriefs) and briefs.done.all()
    assert not briefs.paths and not briefs.roots  # the files' paths and the roots follow from the names
    assert set(briefs.notes) == {k for k, b in enumerate(kept) if b.notes}
    assert [b.name for b in kept] == [t.name for t in spilled.tiles]
    assert all(isinstance(b, streamed.TileBrief) and b.head is kept[0].head for b in kept)
    assert all(Path(b.path).parent == spilled.folder for b in kept)
    assert out.summary()["limits"] == sum(b.n_limits for b in kept) > 0
    # the summaries gathered in files give back each tile's clusters and limits
    tables, limits = out._tables, []
    for k, b in enumerate(kept):
        s = streamed.load_summary(b)
        assert len(s.sizes) == b.n_clusters and len(s.ids) == b.n_ids
        for c in range(b.n_clusters):
            g = int(out._offsets[k]) + c
            assert tables.cluster(g) == s.cluster(c)
            assert tables.sizes[g] == s.sizes[c] and tables.core_sizes[g] == s.core_sizes[c]
        limits += s.limits()
        assert out.explanation.ground.tiles[b.name] == s.ground  # read from the gathered file when asked
    assert out.limits == limits
    assert not any(hasattr(b, "ground") for b in kept)
    # the records' texts the tasks wrote, their stand-ins replaced, are the records read and encoded again
    from kbs.io.result import strict_json

    texts = list(out.record_texts())
    assert texts == [strict_json(r) for r in out.records()]
    assert sum(',"stitched across tile edges into' in t for t in texts) > 0  # a note added after others
    assert not any(m in t for t in texts for m in (streamed.NOTE_MARK, streamed.OUT_MARK))
    spilled.remove()
    assert not spilled.folder.exists()  # the summaries and tables went with the spill files


def test_the_limits_by_kind_of_the_gathered_summaries_are_those_of_the_records(tmp_path):
    """limits_by_kind made from the gathered arrays (its ids read when asked for) is the dict the
    reference function makes from (points, id, limit) triples: equal, and the same JSON; equal
    points ordered by 'tile/id', whatever the tiles' names and the ids' order within a tile."""
    from kbs.io.result import strict_json
    from kbs.knowledge.groundfacts import GroundFacts
    from kbs.knowledge.segmentation import limits_by_kind
    from kbs.tiles import streamed

    rng = np.random.default_rng(7)
    depth = {"kind": "max_depth", "setting": "limits.max_depth", "value": 12}
    small = {"kind": "min_points", "setting": "limits.min_points", "value": 30}
    small2 = {"kind": "min_points", "setting": "limits.min_points", "value": 40}  # the same kind, another value
    failed = {"kind": "split_failed", "setting": None, "value": None}
    names = ["t1_23", "t1_2", "t10_2", "t1_3", "t2_1"]
    briefs, triples = [], []
    for name in names:
        n = int(rng.integers(0, 9))
        points = rng.integers(30, 34, size=n)  # many equal counts: the ids decide
        ids = [f"c{rng.integers(0, 3)}." + ".".join(map(str, rng.integers(0, 3, size=rng.integers(1, 4)))) + f"x{j}"
               for j in range(n)]
        kinds = [[depth, small, small2, failed, None][int(k)] for k in rng.integers(0, 5, size=n)]
        table, codes = streamed._codes(kinds)
        summary = streamed.TileSummary(
            name=name, sizes=np.zeros(0, dtype=np.int64), core_sizes=np.zeros(0, dtype=np.int64), labels=(),
            label_codes=np.zeros(0, dtype=np.int32), ids=Texts.of([]), id_start=np.zeros(1, dtype=np.int64),
            label_counts=np.zeros(3, dtype=np.int64), n_splits=0, limit_points=points.astype(np.int64),
            limit_ids=Texts.of(ids), limit_kinds=table, limit_codes=codes, root="c", ground=GroundFacts(), notes=[])
        briefs.append(streamed.save_summary(summary, tmp_path / f"{name}.summary.pkl"))
        triples += summary.limits()
    tables = streamed._gather(tmp_path, briefs)
    got, want = tables.limits_by_kind(names), limits_by_kind(triples)
    assert got == want and list(got) == list(want)
    assert strict_json({k: {**e, "clusters": list(e["clusters"])} for k, e in got.items()}) == strict_json(want)
    for e in got.values():
        assert isinstance(e["clusters"], streamed.LimitIds)
        assert e["clusters"][:2] == e["clusters"][0:2] and (not len(e["clusters"]) or e["clusters"][-1] == list(e["clusters"])[-1])
    assert streamed._gather(tmp_path, []).limits_by_kind([]) == {}


def test_the_briefs_kept_as_arrays_give_back_each_brief(tmp_path):
    """TileBriefs: what the stitching process keeps of each finished tile; each brief made again
    from it is the brief that came back (notes, a root or a path out of the common case included)."""
    names = ["t0_0", "t0_1", "t1_0", "t2_3"]
    head = {"label_names": ["ground", "obstacle"]}

    def brief(k, **kw):
        base = dict(name=names[k], path=str(tmp_path / f"{names[k]}.summary.pkl"), n_clusters=3 + k, n_ids=7 * k,
                    n_limits=k, n_splits=2 * k + 1, label_counts=np.array([k, 10, 0, 1]), root="root", notes=[],
                    head=dict(head))
        base.update(kw)
        return streamed.TileBrief(**base)

    given = [brief(0), brief(1, notes=["a note", "another"]), brief(2, root="r2", path="/elsewhere/t1_0.summary.pkl"),
             brief(3)]
    briefs = streamed.TileBriefs(names, tmp_path)
    for k in (3, 0, 2, 1):  # as the tiles finish
        briefs.add(k, given[k])
    assert briefs.roots == {2: "r2"} and set(briefs.notes) == {1} and set(briefs.paths) == {2}
    for k, b in enumerate(briefs):
        want = given[k]
        assert (b.name, b.path, b.n_clusters, b.n_ids, b.n_limits, b.n_splits, b.root, b.notes, b.head) == \
               (want.name, want.path, want.n_clusters, want.n_ids, want.n_limits, want.n_splits, want.root, want.notes,
                want.head)
        np.testing.assert_array_equal(b.label_counts, want.label_counts)
    np.testing.assert_array_equal(briefs.label_counts.sum(axis=0), np.sum([b.label_counts for b in given], axis=0))
    part = briefs.take([1, 2], names[1:3])
    assert [b.notes for b in part] == [given[1].notes, []] and part[1].root == "r2" and part[1].path == given[2].path
    with pytest.raises(KbsError, match="t0_1"):  # a brief under another tile's place
        streamed.TileBriefs(names, tmp_path).add(1, given[0])
    with pytest.raises(KbsError, match="not finished"):
        streamed.TileBriefs(names, tmp_path)[0]
