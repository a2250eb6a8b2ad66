"""Issue 14 part A, through the real command: LAS/LAZ out with ASPRS classes, units and CRS,
fields CloudCompare loads as scalar fields, more readers (ascii PCD with any blanks, E57, standard
input and output), and the Python one-liner."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from kbs.io import read_cloud, write_ply
from scenes import ground_and_rocks
from test_cli import ROOT, kbs

EXAMPLE = ROOT / "examples" / "data" / "outdoor.ply"
OUTDOOR_CLASSES = {0: 2, 1: 1, -1: 7}  # rules/outdoor.yaml asprs_classes: ground 2, obstacle 1, noise 7


def _kbs_without(module: str, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """The kbs command in a Python where ``module`` cannot be imported (as if not installed)."""
    code = f"import sys; sys.modules[{module!r}] = None; from kbs.cli.main import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def rocks() -> tuple[np.ndarray, np.ndarray]:
    return ground_and_rocks()


def _las_scene(path: Path, X: np.ndarray, truth: np.ndarray, *, point_format: int = 3, version: str = "1.2") -> Path:
    """A LAS file of the scene with absolute coordinates, its own VLR, GPS times and a class 5
    everywhere (which the result must replace)."""
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500000.0, 4000000.0, 100.0])
    header.vlrs.append(laspy.VLR(user_id="someone", record_id=42, description="theirs", record_data=b"keep me"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0] + 500000.0, X[:, 1] + 4000000.0, X[:, 2] + 100.0
    las.gps_time = np.arange(len(X), dtype=float) * 0.5
    las.intensity = (truth * 100 + 7).astype(np.uint16)
    las.classification = np.full(len(X), 5, dtype=np.uint8)
    las.write(path)
    return path


# -- 1. LAS/LAZ out ------------------------------------------------------------------------------


@pytest.mark.slow
def test_las_in_las_out_keeps_the_records_and_sets_the_asprs_classes(tmp_path, rocks):
    X, truth = rocks
    scan = _las_scene(tmp_path / "scan.las", X, truth)
    r = kbs("run", "--rules", "outdoor", "--sensor", "500000,4000000,100", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    out = tmp_path / "o" / "scan.las"
    assert r.stdout.splitlines()[-1] == f"wrote {out} and {tmp_path / 'o' / 'scan.json'}"  # LAS in, LAS out
    src, res = laspy.read(scan), laspy.read(out)
    # the input's records, header and VLRs, untouched
    assert (res.header.version, res.header.point_format.id) == (src.header.version, 3)
    np.testing.assert_array_equal(res.header.scales, src.header.scales)
    np.testing.assert_array_equal(res.header.offsets, src.header.offsets)
    for dim in ("X", "Y", "Z", "gps_time", "intensity"):
        np.testing.assert_array_equal(res[dim], src[dim])
    theirs = [v for v in res.header.vlrs if v.user_id == "someone"]
    assert len(theirs) == 1 and theirs[0].record_data == b"keep me"
    # kbs's fields as extra bytes, and the classification from the rule base's asprs_classes
    assert list(res.point_format.extra_dimension_names) == ["cluster", "label", "membership"]
    label = np.asarray(res["label"])
    assert res["cluster"].dtype == np.int32 and label.dtype == np.int32 and res["membership"].dtype == np.float32
    expected = np.vectorize(OUTDOOR_CLASSES.get)(label)
    np.testing.assert_array_equal(np.asarray(res.classification), expected)
    assert set(np.unique(res.classification)) <= {1, 2, 7} and (np.asarray(res.classification) == 2).mean() > 0.5
    ground = np.asarray(res.classification) == 2
    assert ground[truth == 0].mean() > 0.95 and (~ground[truth > 0]).mean() > 0.8
    # the pair: the JSON names its points file and carries the same run id as the VLR
    doc = json.loads((tmp_path / "o" / "scan.json").read_text())
    assert doc["points"] == "scan.las"
    vlr = [v for v in res.header.vlrs if v.user_id == "kbs"]
    assert len(vlr) == 1 and vlr[0].record_data.decode() == doc["run_id"]
    assert res.header.generating_software.startswith("kbs ")


@pytest.mark.slow
def test_laz_out_from_a_ply_with_its_crs(tmp_path, rocks):
    X, truth = rocks
    scan = tmp_path / "rocks.ply"
    write_ply(scan, X + [600000.0, 5000000.0, 0.0], {"truth": truth.astype(np.int32)},
              comments=["units m", "crs EPSG:32633"])
    r = kbs("run", "--rules", "outdoor", "--sensor", "600000,5000000,0", str(scan), "--out", str(tmp_path / "o"),
            "--out-format", "laz")
    assert r.returncode == 0, r.stderr
    res = laspy.read(tmp_path / "o" / "rocks.laz")  # lazrs
    assert res.header.are_points_compressed and res.header.point_format.id == 6 and res.header.version == "1.4"
    assert np.abs(res.xyz - (X + [600000.0, 5000000.0, 0.0])).max() < 1e-6
    np.testing.assert_array_equal(np.asarray(res["truth"]), truth)
    np.testing.assert_array_equal(np.asarray(res.classification), np.vectorize(OUTDOOR_CLASSES.get)(res["label"]))
    assert res.header.parse_crs().to_epsg() == 32633
    doc = json.loads((tmp_path / "o" / "rocks.json").read_text())
    assert doc["points"] == "rocks.laz" and doc["scan_units"]["crs"] == "EPSG:32633"


@pytest.mark.slow
def test_codes_a_legacy_point_format_cannot_hold_are_refused_before_any_work(tmp_path, rocks):
    X, truth = rocks
    scan = _las_scene(tmp_path / "scan.las", X, truth)
    rules = tmp_path / "big.yaml"
    rules.write_text(kbs("rules", "show", "outdoor").stdout.replace("obstacle: 1,", "obstacle: 64,"))
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 6 and "Traceback" not in r.stderr
    assert r.stderr.startswith(f"kbs: error: {scan}: LAS point format 3 holds classification codes 0-31; ")
    assert "obstacle 64" in r.stderr and not (tmp_path / "o" / "scan.las").exists()
    r = kbs("run", "--rules", str(rules), str(scan), "--out", str(tmp_path / "o"), "--out-format", "ply")
    assert r.returncode == 0, r.stderr


@pytest.mark.slow
def test_asprs_classes_are_validated_with_positions(tmp_path):
    text = kbs("rules", "show", "outdoor").stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("asprs_classes: {ground: 2, obstacle: 1, noise: 7}",
                                "asprs_classes: {grund: 2, obstacle: 256, noise: -1}"))
    line = next(i for i, ln in enumerate(bad.read_text().splitlines(), 1) if ln.startswith("asprs_classes"))
    r = kbs("rules", "check", str(bad))
    assert r.returncode == 4
    assert f"{bad}:{line}:17: unknown label 'grund' in asprs_classes (did you mean 'ground'?)" in r.stderr
    assert f"{bad}:{line}:37: asprs_classes.obstacle: 256 is greater than the maximum of 255" in r.stderr
    assert f"{bad}:{line}:49: asprs_classes.noise: -1 is less than the minimum of 0" in r.stderr


@pytest.mark.slow
def test_a_las_result_and_a_json_of_another_run_are_refused(tmp_path, rocks):
    X, truth = rocks
    scan = _las_scene(tmp_path / "scan.las", X, truth)
    for out in ("a", "b"):
        assert kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / out)).returncode == 0
    (tmp_path / "a" / "scan.json").write_bytes((tmp_path / "b" / "scan.json").read_bytes())
    r = kbs("eval", str(tmp_path / "a" / "scan.las"), "field:intensity", "--ground-values", "7")
    assert r.returncode == 3 and "does not belong with scan.las: run id" in r.stderr and "in the LAS" in r.stderr
    r = kbs("eval", str(tmp_path / "b" / "scan.las"), "field:intensity", "--ground-values", "7", "--no-hoover")
    assert r.returncode == 0, r.stderr


# -- 2. units and CRS ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def metres_run(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("m")
    r = kbs("run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out))
    assert r.returncode == 0, r.stderr
    return out / "outdoor.ply", json.loads((out / "outdoor.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize(("unit", "factor", "how"), [("mm", 1000.0, "comment"), ("ft", 1 / 0.3048, "comment"),
                                                     ("mm", 1000.0, "--units"), ("us-ft", 3937 / 1200, "--units")])
def test_the_same_scene_in_m_mm_and_ft_gives_the_same_labels(tmp_path, metres_run, unit, factor, how):
    ref_ply, ref_doc = metres_run
    X = read_cloud(EXAMPLE).xyz * factor
    scan = tmp_path / "scene.ply"
    write_ply(scan, X, comments=[f"units {unit}"] if how == "comment" else [])
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"),
            *(["--units", unit] if how == "--units" else []))
    assert r.returncode == 0, r.stderr
    source = "the PLY header's 'units' comment" if how == "comment" else "--units"
    assert r.stdout.splitlines()[1] == f"  units: {unit} ({source}), scaled to the rule base's m"
    assert "warning" not in r.stderr
    ref, got = PlyData.read(str(ref_ply))["vertex"], PlyData.read(str(tmp_path / "o" / "scene.ply"))["vertex"]
    np.testing.assert_array_equal(got["scalar_label"], ref["scalar_label"])
    np.testing.assert_array_equal(got["scalar_cluster"], ref["scalar_cluster"])
    np.testing.assert_array_equal(got["x"], X[:, 0])  # the output points are the input's
    doc = json.loads((tmp_path / "o" / "scene.json").read_text())
    assert {k: v for k, v in doc["summary"].items() if k != "seconds"} == \
        {k: v for k, v in ref_doc["summary"].items() if k != "seconds"} and doc["units"] == "m"
    assert doc["scan_units"]["horizontal"] == unit and doc["scan_units"]["source"] == source
    # the clusters' descriptors are in the scan's frame and unit; the explanation stays in the rule base's
    for c, c0 in zip(doc["clusters"], ref_doc["clusters"]):
        np.testing.assert_allclose(c["descriptors"]["center"], np.asarray(c0["descriptors"]["center"]) * factor,
                                   rtol=1e-9, atol=1e-9)
        assert c["descriptors"]["thickness"] == pytest.approx(c0["descriptors"]["thickness"] * factor, rel=1e-9)
    for rec, rec0 in zip(doc["explanation"]["clusters"], ref_doc["explanation"]["clusters"]):
        assert rec["id"] == rec0["id"] and rec["action"] == rec0["action"]
        assert rec["descriptors"]["thickness"] == pytest.approx(rec0["descriptors"]["thickness"], rel=1e-9)
    if how == "comment":
        assert f"units {unit}" in PlyData.read(str(tmp_path / "o" / "scene.ply")).comments  # the output says so too


@pytest.mark.slow
def test_an_implausible_spacing_is_a_warning_and_a_note_in_the_json(tmp_path):
    scan = tmp_path / "mm.ply"
    write_ply(scan, read_cloud(EXAMPLE).xyz * 1000.0)  # millimetres, not declared
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    warning = [ln for ln in r.stderr.splitlines() if ln.startswith("kbs: warning:")]
    assert len(warning) == 1 and re.match(rf"kbs: warning: {re.escape(str(scan))}: median point spacing 1\d\.\d m ",
                                          warning[0]), warning  # 18.8 mm exactly, estimated on a sample
    assert "outside 0.0005-2 m, what rule base 'outdoor' expects" in warning[0]
    assert "give its unit with --units" in warning[0] and "(as cm or mm it would fit)" in warning[0]
    doc = json.loads((tmp_path / "o" / "mm.json").read_text())
    assert doc["spacing"]["plausible"] is False and doc["spacing"]["expected"] == [0.0005, 2]
    assert doc["spacing"]["suggested_units"] == ["cm", "mm"] and 10 < doc["spacing"]["median_spacing"] < 20
    assert "scan_units" not in doc  # unknown: taken as the rule base's
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"), "--units", "mm")
    assert r.returncode == 0 and "warning" not in r.stderr
    assert "spacing" not in json.loads((tmp_path / "o" / "mm.json").read_text())


@pytest.mark.slow
def test_spacing_declared_by_a_rule_file_is_validated(tmp_path):
    rules = tmp_path / "r.yaml"
    rules.write_text(kbs("rules", "show", "outdoor").stdout.replace("spacing: [0.0005, 2]", "spacing: [2, 0.0005]"))
    line = next(i for i, ln in enumerate(rules.read_text().splitlines(), 1) if ln.startswith("spacing"))
    r = kbs("rules", "check", str(rules))
    assert r.returncode == 4 and f"{rules}:{line}:10: spacing is [min, max]: 2 is not below 0.0005" in r.stderr


AUTZEN_UNITS = """
import sys
if sys.argv[2] == "hidden":
    sys.modules["pyproj"] = None
from kbs.io import read_cloud
c = read_cloud(sys.argv[1])
print(c.units.horizontal.name, c.units.vertical.name, c.units.source, "|", (c.crs or "")[:22])
"""


@pytest.mark.parametrize("pyproj", ["installed", "hidden"])
def test_las_units_come_from_the_crs_with_or_without_pyproj(shared_data, pyproj):
    for name, expected in (("autzen_trim.las", "ft ft the LAS file's CRS | PROJCS[\"NAD_1983_HARN_"),
                           ("4_6_crop.las", "us-ft us-ft the LAS file's CRS | ")):
        r = subprocess.run([sys.executable, "-c", AUTZEN_UNITS, str(shared_data / "las" / name), pyproj],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        out = r.stdout.strip()
        if name == "4_6_crop.las":  # GeoTIFF keys: EPSG:2903 as text without pyproj, its WKT with it
            crs = "EPSG:2903" if pyproj == "hidden" else 'PROJCRS["NAD83(HARN) /'
            assert out == expected + crs
        else:
            assert out == expected


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_autzen_in_feet_is_segmented_in_metres(shared_data, tmp_path):
    """autzen_trim.las is in international feet (its WKT): the same points written in metres
    (declared so) give the same labels."""
    scan = shared_data / "las" / "autzen_trim.las"
    r = kbs("run", "--rules", "airborne", str(scan), "--out", str(tmp_path / "ft"), "--out-format", "ply")
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[1] == "  units: ft (the LAS file's CRS), scaled to the rule base's m"
    metres = tmp_path / "autzen_m.ply"
    write_ply(metres, read_cloud(scan).xyz * 0.3048, comments=["units m"])
    r = kbs("run", "--rules", "airborne", str(metres), "--out", str(tmp_path / "m"))
    assert r.returncode == 0, r.stderr
    ft = PlyData.read(str(tmp_path / "ft" / "autzen_trim.ply"))["vertex"]
    m = PlyData.read(str(tmp_path / "m" / "autzen_m.ply"))["vertex"]
    assert (np.asarray(ft["scalar_label"]) == np.asarray(m["scalar_label"])).mean() > 0.999
    doc = json.loads((tmp_path / "ft" / "autzen_trim.json").read_text())
    assert doc["scan_units"]["horizontal"] == "ft" and doc["scan_units"]["crs"].startswith("PROJCS[")


@pytest.mark.slow
def test_pcd_comments_declare_units(tmp_path):
    X = read_cloud(EXAMPLE).xyz[:2000] * 100.0
    body = "\n".join(f"{x:.4f}   {y:.4f}\t{z:.4f}" for x, y, z in X)
    scan = tmp_path / "cm.pcd"
    scan.write_text("# .PCD v0.7 - Point Cloud Data file format\n# units cm\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
                    f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(X)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(X)}\n"
                    f"DATA ascii\n{body}\n")
    cloud = read_cloud(scan)
    assert cloud.units.name == "cm" and cloud.units.source == "the PCD header's 'units' comment"
    bad = tmp_path / "bad.ply"
    write_ply(bad, X, comments=["units furlongs"])
    r = kbs("run", "--rules", "outdoor", str(bad), "--out", str(tmp_path / "o"))
    assert r.returncode == 3
    assert r.stderr == (f"kbs: error: {bad}: the PLY header's comment 'units furlongs' names an unknown unit "
                        "(known: m, cm, mm, km, ft, us-ft)\n")


# -- 3. CloudCompare -------------------------------------------------------------------------------


def cloudcompare_scalar_fields(path: Path) -> dict[str, np.ndarray]:
    """The scalar fields CloudCompare's PLY filter loads from a file, following its rules
    (CloudCompare libs/qCC_io/PlyFilter.cpp, PlyFilter::loadFile, the loop over the point-like
    elements' properties): upper-cased names are tried in order against NX/NY/NZ, RED/GREEN/BLUE,
    INTENSITY/GRAY/GREY (a scalar field), then, in a vertex or point element, a name containing
    'SCAL' is a scalar field and a name ending in X/Y/Z a coordinate; anything else stays
    unassigned (the GUI's Scalar = None, dropped by the command line). A loaded field's name loses
    a 'scalar_' prefix and its '_' become spaces."""
    ply = PlyData.read(str(path))
    out: dict[str, np.ndarray] = {}
    taken: set[str] = set()
    for element in ply.elements:
        el = element.name.upper()
        for prop in element.properties:
            name = prop.name.upper()
            rules = [("nx", "NX" in name), ("ny", "NY" in name), ("nz", "NZ" in name),
                     ("r", "RED" in name), ("g", "GREEN" in name), ("b", "BLUE" in name)]
            slot = next((s for s, hit in rules if hit and s not in taken), None)
            if slot is not None:
                taken.add(slot)
                continue
            is_sf = any(w in name for w in ("INTENSITY", "GRAY", "GREY"))
            if not is_sf and ("VERT" in el or "POINT" in el):
                is_sf = "SCAL" in name
                if not is_sf:
                    axis = next((a for a in "XYZ" if name.endswith(a) and a not in taken), None)
                    if axis:
                        taken.add(axis)
                    continue
            elif not is_sf:
                is_sf = "SCAL" in name or "VAL" in name
            if is_sf:
                shown = prop.name[7:].replace("_", " ") if prop.name.startswith("scalar_") and len(prop.name) > 7 \
                    else prop.name
                out[shown] = np.asarray(element[prop.name], dtype=np.float32)  # ScalarType: float
    return out


@pytest.mark.slow
def test_cloudcompare_loads_cluster_label_membership_as_scalar_fields(tmp_path, metres_run):
    ply, doc = metres_run
    fields = cloudcompare_scalar_fields(ply)
    assert {"cluster", "label", "membership"} <= set(fields)
    v = PlyData.read(str(ply))["vertex"]
    np.testing.assert_array_equal(fields["cluster"], np.asarray(v["scalar_cluster"], dtype=np.float32))
    assert int(fields["cluster"].max()) + 1 == len(doc["clusters"])
    assert np.bincount(fields["label"].astype(int) + 1).tolist()[1:] == list(doc["summary"]["points_per_label"].values())[:2]
    # a result as kbs wrote it before (plain names): CloudCompare left the three unassigned
    old = tmp_path / "old.ply"
    write_ply(old, np.column_stack([v["x"], v["y"], v["z"]]),
              {"cluster": np.asarray(v["scalar_cluster"]), "label": np.asarray(v["scalar_label"]),
               "membership": np.asarray(v["scalar_membership"])})
    assert not {"cluster", "label", "membership"} & set(cloudcompare_scalar_fields(old))


@pytest.mark.slow
def test_kbs_reads_old_and_new_field_names(tmp_path, metres_run):
    ply, doc = metres_run
    v = PlyData.read(str(ply))["vertex"]
    old = tmp_path / "old.ply"  # as kbs wrote results before: cluster, label, membership
    write_ply(old, np.column_stack([v["x"], v["y"], v["z"]]),
              {"cluster": np.asarray(v["scalar_cluster"]), "label": np.asarray(v["scalar_label"]),
               "membership": np.asarray(v["scalar_membership"]), "label_in": np.asarray(v["label_in"])})
    outputs = []
    for result in (ply, old):
        r = kbs("eval", str(result), "field:label_in", "--json", str(tmp_path / f"{result.stem}.eval.json"))
        assert r.returncode == 0, r.stderr
        outputs.append([ln for ln in r.stdout.splitlines()[1:] if not ln.startswith("wrote ")])
    assert outputs[0] == outputs[1] and any("correct" in ln for ln in outputs[0])


# -- 4. readers ----------------------------------------------------------------------------------

#: The layout of PCL's tutorials/min_cut_segmentation_tutorial.pcd: an ascii body whose columns are
#: separated by several spaces (pypcd4 accepted only one).
PCL_TUTORIAL_HEADER = """# .PCD v0.7 - Point Cloud Data file format
VERSION 0.7
FIELDS x y z
SIZE 4 4 4
TYPE F F F
COUNT 1 1 1
WIDTH {n}
HEIGHT 1
VIEWPOINT 0 0 0 1 0 0 0
POINTS {n}
DATA ascii
"""


@pytest.mark.slow
def test_ascii_pcd_with_several_spaces_between_columns(tmp_path, rocks):
    X, _ = rocks
    rows = "\n".join(f"{x:.6g}  {y:.6g}    {z:.6g}" if i % 2 else f" {x:.6g}\t{y:.6g}  {z:.6g} "
                     for i, (x, y, z) in enumerate(X))
    scan = tmp_path / "min_cut_layout.pcd"
    scan.write_text(PCL_TUTORIAL_HEADER.format(n=len(X)) + rows + "\n")
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"{scan}: {len(X):,} points, rule base 'outdoor'")
    np.testing.assert_allclose(read_cloud(scan).xyz, X, rtol=1e-5, atol=1e-5)
    short = tmp_path / "short.pcd"
    short.write_text(PCL_TUTORIAL_HEADER.format(n=3) + "1  2  3\n4  5\n7  8  9\n")
    r = kbs("run", "--rules", "outdoor", str(short), "--out", str(tmp_path / "o"))
    assert r.returncode == 3 and r.stderr.startswith(f"kbs: error: {short}: malformed PCD file: ")


def _e57(path: Path, X: np.ndarray, truth: np.ndarray) -> Path:
    import pye57

    e57 = pye57.E57(str(path), mode="w")
    half = len(X) // 2
    for part, shift in ((slice(None, half), 0.0), (slice(half, None), 1.0)):  # two scans, the second moved by a pose
        e57.write_scan_raw({"cartesianX": X[part, 0] - shift, "cartesianY": X[part, 1], "cartesianZ": X[part, 2],
                            "intensity": truth[part].astype(float)}, name="s", translation=np.array([shift, 0.0, 0.0]))
    e57.close()
    return path


@pytest.mark.slow
def test_e57_scans_are_read_with_their_poses(tmp_path, rocks):
    X, truth = rocks
    scan = _e57(tmp_path / "rocks.e57", X, truth)
    cloud = read_cloud(scan)
    np.testing.assert_allclose(cloud.xyz, X, atol=1e-6)  # E57 keeps the coordinates as float32 here
    assert cloud.units.name == "m" and cloud.fields["scan"].max() == 1
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[1] == "  units: m (E57 (metres))"
    r = _kbs_without("pye57", "run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 3
    assert r.stderr == f"kbs: error: {scan}: reading E57 needs the optional package pye57: pip install 'kbs[e57]'\n"


@pytest.mark.slow
def test_standard_input_and_output(tmp_path, rocks):
    X, truth = rocks
    scan = tmp_path / "rocks.ply"
    write_ply(scan, X, {"truth": truth.astype(np.int32)})
    exe = str(Path(sys.executable).parent / "kbs")
    with open(scan, "rb") as stdin:
        r = subprocess.run([exe, "run", "--rules", "outdoor", "-", "--in-format", "ply", "--out", "-",
                            "--out-format", "las"], stdin=stdin, capture_output=True, timeout=300)
    assert r.returncode == 0, r.stderr.decode()
    out = tmp_path / "piped.las"
    out.write_bytes(r.stdout)
    res = laspy.read(out)
    assert len(res.points) == len(X)
    np.testing.assert_array_equal(np.asarray(res.classification), np.vectorize(OUTDOOR_CLASSES.get)(res["label"]))
    err = r.stderr.decode()
    assert err.startswith("<stdin>: 30,") or err.startswith("<stdin>: ")
    assert "wrote the LAS result to standard output" in err
    with open(scan, "rb") as stdin:  # to a folder: <out>/stdin.ply and stdin.json
        r = subprocess.run([exe, "run", "--rules", "outdoor", "-", "--in-format", "ply", "--out", str(tmp_path / "o")],
                           stdin=stdin, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "o" / "stdin.ply").is_file() and json.loads((tmp_path / "o" / "stdin.json").read_text())[
        "input"] == "<stdin>"
    r = kbs("run", "--rules", "outdoor", "-", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "needs --in-format" in r.stderr
    r = kbs("run", "--rules", "outdoor", str(scan), str(EXAMPLE), "--out", "-")
    assert r.returncode == 2 and "--out - writes one scan to standard output; 2 scans given" in r.stderr
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", "-", "--report")
    assert r.returncode == 2 and "--meshes and --report need a folder" in r.stderr


# -- 5. Python -----------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_readme_one_liner_runs():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### One call: `kbs.segment`"):]
    code, shown = re.search(r"```python\n(.*?)```\n\n```\n(.*?)```", section, re.S).groups()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == shown.splitlines()


def test_dir_kbs_lists_the_public_names_only():
    code = "import kbs; print(' '.join(dir(kbs)))"
    names = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout.split()
    assert {"segment", "Segmenter", "KbsError", "__version__", "io", "knowledge"} <= set(names)
    assert not {"annotations", "version", "PackageNotFoundError", "_metadata"} & set(names)


@pytest.mark.slow
def test_knowledge_segment_takes_a_rule_base_name():
    import kbs
    import kbs.knowledge

    X = read_cloud(EXAMPLE).xyz
    a = kbs.knowledge.segment(X, "outdoor")
    b = kbs.segment(str(EXAMPLE), "outdoor")
    np.testing.assert_array_equal(a.label, b.label)
    with pytest.warns(UserWarning, match="median point spacing"):
        kbs.segment(X * 1000.0, "outdoor")
    c = kbs.segment(X * 1000.0, "outdoor", units="mm")
    np.testing.assert_array_equal(c.label, a.label)


COMPOUND_WKT = ('COMPD_CS["UTM 33N + heights in feet",PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",'
                'SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
                'PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",15],PARAMETER["scale_factor",0.9996],'
                'PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1]],'
                'VERT_CS["some height",VERT_DATUM["some datum",2005],UNIT["foot",0.3048]]]')


@pytest.mark.slow
@pytest.mark.parametrize("pyproj", ["installed", "hidden"])
def test_a_compound_crs_with_heights_in_feet_is_scaled_axis_by_axis(tmp_path, rocks, pyproj):
    """x and y in metres, z in feet (a compound WKT CRS): z alone is scaled; the same labels as
    the scene all in metres."""
    from laspy.vlrs.known import WktCoordinateSystemVlr

    X, truth = rocks
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([1e-4, 1e-4, 1e-4]), np.zeros(3)
    header.vlrs.append(WktCoordinateSystemVlr(COMPOUND_WKT))
    header.global_encoding.wkt = True
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2] / 0.3048
    scan = tmp_path / "compound.las"
    las.write(scan)
    ref = tmp_path / "metres.las"
    las.z = X[:, 2]
    las.header.vlrs.clear()
    las.write(ref)
    args = ("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path / "o"))
    r = kbs(*args) if pyproj == "installed" else _kbs_without("pyproj", *args)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[1] == "  units: m (z in ft) (the LAS file's CRS), scaled to the rule base's m"
    assert kbs("run", "--rules", "outdoor", str(ref), "--out", str(tmp_path / "m")).returncode == 0
    got, want = laspy.read(tmp_path / "o" / "compound.las"), laspy.read(tmp_path / "m" / "metres.las")
    assert (np.asarray(got["label"]) == np.asarray(want["label"])).mean() > 0.999
    doc = json.loads((tmp_path / "o" / "compound.json").read_text())
    assert doc["scan_units"]["metres"] == [1.0, 1.0, 0.3048] and "different units" in doc["notes"][0]


@pytest.mark.slow
def test_clusters_no_label_matched_are_unclassified_not_noise(tmp_path, rocks):
    X, truth = rocks
    scan = _las_scene(tmp_path / "scan.las", X, truth)
    rules = tmp_path / "partial.yaml"  # no default label: a level cluster that is not ground gets none
    text = kbs("rules", "show", "outdoor").stdout
    rules.write_text(text.replace("  - name: obstacle\n", "  - name: obstacle\n    if: [not level]\n", 1))
    r = kbs("run", "--rules", str(rules), "--sensor", "500000,4000000,100", str(scan), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    res = laspy.read(tmp_path / "o" / "scan.las")
    label, cluster, code = (np.asarray(res[k]) for k in ("label", "cluster", "classification"))
    unmatched = (label < 0) & (cluster >= 0)
    assert unmatched.any()
    assert (code[unmatched] == 1).all() and (code[cluster < 0] == 7).all() and (code[label == 0] == 2).all()
    assert "no label matched" in r.stdout


# --- optional extras: the report (plotly) and the figures (matplotlib) ------------------------------


@pytest.mark.slow
def test_report_without_plotly_is_a_usage_error_before_any_work(tmp_path):
    """plotly is the `report` extra (64 MB installed, only to inline plotly.js): without it
    `kbs run --report` stops at once, exit 2, naming the extra, and writes nothing."""
    out = tmp_path / "o"
    r = _kbs_without("plotly", "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out), "--report")
    assert r.returncode == 2, r.stderr
    assert "pip install 'kbs[report]'" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists() or not any(out.iterdir())
    # the run itself needs no plotly
    r = _kbs_without("plotly", "-q", "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert (out / "outdoor.ply").is_file() and (out / "outdoor.json").is_file()


@pytest.mark.slow
def test_render_without_matplotlib_names_the_extra(tmp_path):
    out = tmp_path / "o"
    assert kbs("-q", "run", "--rules", "outdoor", str(EXAMPLE), "--out", str(out)).returncode == 0
    r = _kbs_without("matplotlib", "render", str(out / "outdoor.json"), "--kind", "map")
    assert r.returncode == 2, r.stderr
    assert "pip install 'kbs[render]'" in r.stderr and "Traceback" not in r.stderr
    assert not list(out.glob("*.png"))


@pytest.mark.slow
def test_the_core_install_does_not_import_the_figure_libraries():
    """`kbs run` (the main job) imports neither matplotlib nor plotly."""
    code = ("import sys; from kbs.cli.main import main; code = main(['-q', 'run', '--rules', 'outdoor', "
            f"{str(EXAMPLE)!r}, '--out', sys.argv[1]]); "
            "print(sorted(m for m in ('matplotlib', 'plotly') if m in sys.modules)); sys.exit(code)")
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        r = subprocess.run([sys.executable, "-c", code, d], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.slow
def test_rules_show_writes_a_schema_reference_that_works_from_anywhere(tmp_path):
    """`kbs rules show outdoor > my.yaml` in any folder: the editor line points at the installed
    schema (a file URI to a file that exists), and the file checks clean; `kbs rules schema` prints
    that path, `--json` the schema."""
    from urllib.parse import unquote, urlparse

    r = kbs("rules", "show", "outdoor")
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    assert first.startswith("# yaml-language-server: $schema=file://")
    schema = Path(unquote(urlparse(first.split("$schema=", 1)[1]).path))
    assert schema.is_file() and json.loads(schema.read_text())["$schema"].startswith("https://json-schema.org/")
    mine = tmp_path / "elsewhere" / "my.yaml"
    mine.parent.mkdir()
    mine.write_text(r.stdout)
    assert kbs("rules", "check", str(mine)).returncode == 0
    r = kbs("rules", "schema")
    assert r.returncode == 0 and Path(r.stdout.strip()) == schema
    assert json.loads(kbs("rules", "schema", "--json").stdout) == json.loads(schema.read_text())
