"""``limits.tile``: a rule base says how wide a cloud it judges whole; ``kbs run`` segments a wider
cloud in tiles of ``size`` (as ``--tile size`` does), so that a region's labels do not depend on how
much else the file holds; ``--no-tile`` runs it whole. Through ``kbs run`` on a real ISPRS sample."""
from __future__ import annotations

import json
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
