"""Tests of :mod:`kbs.io`: round trips through every format, NaN dropping, bad files, real scans."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pytest
from pypcd4 import Encoding
from pypcd4 import PointCloud as PcdCloud

from kbs.errors import CloudFileError, ParameterError
from kbs.io import SUPPORTED_EXTENSIONS, PointCloud, read_cloud, write_ply

PCD_ENCODINGS = [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED]


def _utm_xyz(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) absolute UTM-like coordinates rounded to the centimetre."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([5e5 + rng.random(n) * 1000, 5e6 + rng.random(n) * 1000, 300 + rng.random(n) * 50])
    return np.round(xyz, 2)


def _write_pcd(
    path: Path,
    columns: dict[str, np.ndarray],
    encoding: Encoding,
    *,
    height: int = 1,
) -> Path:
    """Write ``columns`` (dtypes kept) as a PCD file with pypcd4; ``height > 1`` makes it organised."""
    names = list(columns)
    cloud = PcdCloud.from_points(list(columns.values()), names, [columns[name].dtype for name in names])
    n = len(columns[names[0]])
    cloud.metadata = cloud.metadata.derive(width=n // height, height=height)
    cloud.save(path, encoding=encoding)
    assert f"DATA {encoding.value}".encode() in path.read_bytes()[:500]  # pypcd4 may fall back to binary
    return path


def _write_las(path: Path, xyz: np.ndarray, classification: np.ndarray) -> Path:
    las = laspy.create(point_format=3, file_version="1.2")
    las.header.scales = np.array([0.01, 0.01, 0.01])
    las.header.offsets = np.array([5e5, 5e6, 0.0])
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = classification
    las.intensity = np.arange(len(xyz), dtype=np.uint16)
    las.red = np.full(len(xyz), 65535, dtype=np.uint16)
    las.write(path)
    return path


# --------------------------------------------------------------------------------------------
# PLY


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_round_trip_keeps_values_and_dtypes(tmp_path: Path, binary: bool) -> None:
    xyz = _utm_xyz(40) + np.random.default_rng(1).random((40, 3)) * 1e-3  # full float64 digits
    fields = {
        "label": np.arange(40, dtype=np.int32) - 5,
        "intensity": np.linspace(0, 1, 40, dtype=np.float32),
        "weight": np.linspace(-1, 1, 40),
        "cls": np.arange(40, dtype=np.uint8),
        "ground": np.arange(40) % 3 == 0,
        "segment": np.arange(40, dtype=np.int64) * 1000,
    }
    path = tmp_path / "cloud.ply"
    write_ply(path, xyz, fields, binary=binary, comments=["made by kbs", "frame: UTM 32N"])

    header = path.read_bytes()[:600]
    assert (b"format binary_little_endian" if binary else b"format ascii") in header
    assert b"comment made by kbs\n" in header and b"comment frame: UTM 32N\n" in header
    cloud = read_cloud(path)
    assert cloud.xyz.dtype == np.float64
    np.testing.assert_array_equal(cloud.xyz, xyz)
    assert list(cloud.fields) == list(fields)
    expected_dtypes = {
        "label": "i4",
        "intensity": "f4",
        "weight": "f8",
        "cls": "u1",
        "ground": "u1",
        "segment": "i4",
    }
    assert {name: values.dtype for name, values in cloud.fields.items()} == {
        name: np.dtype(code) for name, code in expected_dtypes.items()
    }
    for name, values in fields.items():
        np.testing.assert_array_equal(cloud.fields[name], values)
    assert (len(cloud), cloud.n_read, cloud.n_dropped, cloud.shape) == (40, 40, 0, None)
    np.testing.assert_array_equal(cloud.index, np.arange(40))
    assert cloud.path == str(path)


def test_write_ply_float32_coordinates_stay_float32(tmp_path: Path) -> None:
    xyz = np.random.default_rng(2).random((10, 3)).astype(np.float32)
    path = tmp_path / "f32.ply"
    write_ply(path, xyz)
    ply = plyfile.PlyData.read(str(path))
    assert [(p.name, p.val_dtype) for p in ply["vertex"].properties] == [
        ("x", "f4"),
        ("y", "f4"),
        ("z", "f4"),
    ]
    np.testing.assert_array_equal(read_cloud(path).xyz, xyz.astype(np.float64))


def test_read_ply_skips_list_properties_and_other_elements(tmp_path: Path) -> None:
    vertex = np.array(
        [(0, 0, 0, 7), (1, 0, 0, 8), (0, 1, 0, 9)],
        dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("id", "u2")],
    )
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    path = tmp_path / "mesh.ply"
    plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")]
    ).write(str(path))
    cloud = read_cloud(path)
    assert len(cloud) == 3 and list(cloud.fields) == ["id"] and cloud.fields["id"].dtype == np.uint16


@pytest.mark.parametrize(
    ("xyz", "fields", "comments", "problem"),
    [
        (np.zeros((4, 2)), None, (), "shape (N, 3)"),
        (np.zeros((4, 3), dtype=complex), None, (), "shape (N, 3)"),
        (np.zeros((4, 3)), {"a": np.zeros(3)}, (), "shape (4,)"),
        (np.zeros((4, 3)), {"a": np.zeros((4, 1))}, (), "shape (4,)"),
        (np.zeros((4, 3)), {"a": np.array(list("abcd"))}, (), "cannot store"),
        (np.zeros((4, 3)), {"a": np.array([0, 1, 2, 2**40])}, (), "outside the int32 range"),
        (np.zeros((4, 3)), {"two words": np.zeros(4)}, (), "one word"),
        (np.zeros((4, 3)), {"x": np.zeros(4)}, (), "clashes"),
        (np.zeros((4, 3)), None, ("line one\nline two",), "one-line ASCII"),
    ],
    ids=[
        "xyz-2-cols",
        "xyz-complex",
        "short-field",
        "2d-field",
        "str-field",
        "int64-overflow",
        "spaced-name",
        "x-name",
        "multiline-comment",
    ],
)
def test_write_ply_rejects_bad_arguments(tmp_path: Path, xyz, fields, comments, problem: str) -> None:
    path = tmp_path / "bad.ply"
    with pytest.raises(ParameterError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        write_ply(path, xyz, fields, comments=comments)
    assert not path.exists()


def test_write_ply_to_missing_folder_is_a_cloud_file_error(tmp_path: Path) -> None:
    path = tmp_path / "no" / "such" / "out.ply"
    with pytest.raises(CloudFileError, match="cannot write") as info:
        write_ply(path, np.zeros((2, 3)))
    assert info.value.path == str(path)


# --------------------------------------------------------------------------------------------
# PCD


@pytest.mark.parametrize("encoding", PCD_ENCODINGS, ids=lambda e: e.value)
def test_pcd_organised_with_nans_keeps_shape_index_and_dtypes(tmp_path: Path, encoding: Encoding) -> None:
    rows, cols = 4, 6
    grid = np.indices((rows, cols)).reshape(2, -1).astype(np.float32)
    x, y, z = grid[1] * 0.5, grid[0] * 0.25, np.ones(rows * cols, dtype=np.float32)
    invalid = np.array([0, 5, 7, 8, 23])
    x[invalid[:2]] = np.nan
    y[invalid[2]] = np.inf
    z[invalid[3:]] = np.nan
    label = np.arange(rows * cols, dtype=np.uint32) + 100
    rgba = np.full(rows * cols, 0xFF102030, dtype=np.uint32)
    path = _write_pcd(
        tmp_path / "organised.pcd",
        {"label": label, "x": x, "y": y, "z": z, "rgba": rgba},
        encoding,
        height=rows,
    )

    cloud = read_cloud(path)
    assert cloud.shape == (rows, cols)
    assert (cloud.n_read, cloud.n_dropped, len(cloud)) == (24, 5, 19)
    expected_index = np.setdiff1d(np.arange(24), invalid)
    assert cloud.index.dtype == np.int64
    np.testing.assert_array_equal(cloud.index, expected_index)
    r, c = np.unravel_index(cloud.index, cloud.shape)
    np.testing.assert_array_equal(cloud.xyz[:, 0], c * 0.5)
    np.testing.assert_array_equal(cloud.xyz[:, 1], r * 0.25)
    assert cloud.fields["label"].dtype == np.uint32 and cloud.fields["rgba"].dtype == np.uint32
    np.testing.assert_array_equal(cloud.fields["label"], label[expected_index])
    assert np.isfinite(cloud.xyz).all()


@pytest.mark.parametrize("encoding", PCD_ENCODINGS, ids=lambda e: e.value)
def test_pcd_unorganised_float64_and_rgb(tmp_path: Path, encoding: Encoding) -> None:
    xyz = _utm_xyz(30)
    xyz[:, 2] = np.arange(30) % 4  # compressible enough for binary_compressed
    rgb = PcdCloud.encode_rgb(np.tile(np.array([[255, 0, 10]], dtype=np.uint8), (30, 1)))
    columns = {
        "x": xyz[:, 0],
        "y": xyz[:, 1],
        "z": xyz[:, 2],
        "rgb": rgb,
        "intensity": np.ones(30, np.float32),
    }
    columns = {name: np.repeat(values, 20) for name, values in columns.items()}
    cloud = read_cloud(_write_pcd(tmp_path / "utm.pcd", columns, encoding))
    assert cloud.shape is None and len(cloud) == 600
    np.testing.assert_allclose(cloud.xyz, np.repeat(xyz, 20, axis=0), rtol=0, atol=1e-6)
    assert cloud.fields["rgb"].dtype == np.float32
    if encoding != Encoding.ASCII:  # pypcd4 writes ascii floats with %.10f, which zeroes a packed rgb
        np.testing.assert_array_equal(PcdCloud.decode_rgb(cloud.fields["rgb"])[0], [255, 0, 10])


# --------------------------------------------------------------------------------------------
# LAS / LAZ


@pytest.mark.parametrize("suffix", [".las", ".laz", ".LAZ"])
def test_las_round_trip_keeps_centimetres_of_absolute_coordinates(tmp_path: Path, suffix: str) -> None:
    xyz = _utm_xyz(500, seed=3)
    classification = (np.arange(500) % 3 == 0).astype(np.uint8) + 1
    path = _write_las(tmp_path / f"utm{suffix}", xyz, classification)
    assert laspy.open(path).header.are_points_compressed == (suffix.lower() == ".laz")

    cloud = read_cloud(path)
    assert cloud.xyz.dtype == np.float64 and len(cloud) == 500
    np.testing.assert_allclose(cloud.xyz, xyz, rtol=0, atol=1e-6)  # float32 would be off by ~0.25 m
    assert np.count_nonzero(cloud.fields["classification"] == 2) == np.count_nonzero(classification == 2)
    assert cloud.fields["classification"].dtype == np.uint8
    assert cloud.fields["intensity"].dtype == np.uint16
    np.testing.assert_array_equal(cloud.fields["intensity"], np.arange(500))
    assert set(cloud.fields) == {
        "classification",
        "intensity",
        "return_number",
        "number_of_returns",
        "red",
        "green",
        "blue",
    }
    assert (cloud.fields["red"] == 65535).all()


def test_las_without_colour_has_no_rgb_fields(tmp_path: Path) -> None:
    las = laspy.create(point_format=1, file_version="1.2")
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    las.write(tmp_path / "grey.las")
    cloud = read_cloud(tmp_path / "grey.las")
    assert "red" not in cloud.fields and "classification" in cloud.fields and len(cloud) == 5


# --------------------------------------------------------------------------------------------
# text tables


def test_xyz_with_spaces_tabs_comments_and_nan(tmp_path: Path) -> None:
    path = tmp_path / "scan.xyz"
    path.write_text(
        "# exported by a scanner\n\n"
        "512743.63 5403547.33 308.68 12 0\n"
        "512743.62\t5403547.33  308.70 13 1\n"
        "nan 5403547.30 308.71 14 0\n"
        "// a comment between points\n"
        "512743.61 5403547.33 308.72 15 1  # a trailing comment\n\n"
    )
    cloud = read_cloud(path)
    assert (cloud.n_read, cloud.n_dropped, len(cloud)) == (4, 1, 3)
    np.testing.assert_array_equal(cloud.xyz[0], [512743.63, 5403547.33, 308.68])
    np.testing.assert_array_equal(cloud.index, [0, 1, 3])
    assert list(cloud.fields) == ["col3", "col4"]
    np.testing.assert_array_equal(cloud.fields["col3"], [12, 13, 15])
    np.testing.assert_array_equal(cloud.fields["col4"], [0, 1, 1])


def test_csv_with_bom_header_and_crlf(tmp_path: Path) -> None:
    path = tmp_path / "points.csv"
    path.write_bytes(b"\xef\xbb\xbfx,y,z,label,intensity\r\n1.5,2,3,4,0.5\r\n5, 6 ,7,8,0.25\r\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1.5, 2, 3], [5, 6, 7]])
    assert list(cloud.fields) == ["label", "intensity"]
    np.testing.assert_array_equal(cloud.fields["label"], [4, 8])


def test_text_header_naming_xyz_out_of_order(tmp_path: Path) -> None:
    path = tmp_path / "points.txt"
    path.write_text("label x y z\n7 1 2 3\n9 4 5 6\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud.fields["label"], [7, 9])


def test_cloudcompare_header_and_pts_count_line(tmp_path: Path) -> None:
    cc = tmp_path / "cc.txt"
    cc.write_text("//X Y Z R G B\n1 2 3 255 0 0\n4 5 6 0 255 0\n")
    assert list(read_cloud(cc).fields) == ["R", "G", "B"]
    pts = tmp_path / "scan.pts"
    pts.write_text("2\n1 2 3 -1200 10 20 30\n4 5 6 -1100 10 20 30\n")
    cloud = read_cloud(pts)
    assert len(cloud) == 2 and list(cloud.fields) == ["col3", "col4", "col5", "col6"]
    np.testing.assert_array_equal(cloud.fields["col3"], [-1200, -1100])


def test_format_override_and_case_insensitive_extension(tmp_path: Path) -> None:
    path = tmp_path / "points.dat"
    path.write_text("1 2 3\n4 5 6\n")
    assert len(read_cloud(path, format="xyz")) == 2
    assert len(read_cloud(path, format=".TXT")) == 2
    upper = tmp_path / "POINTS.XYZ"
    upper.write_text("1 2 3\n")
    assert len(read_cloud(upper)) == 1
    with pytest.raises(ParameterError, match="unknown point-cloud format 'dxf'"):
        read_cloud(path, format="dxf")


# --------------------------------------------------------------------------------------------
# NPY and KITTI .bin


def test_npy_plain_arrays(tmp_path: Path) -> None:
    xyz = np.random.default_rng(4).random((20, 3)).astype(np.float32)
    np.save(tmp_path / "xyz.npy", xyz)
    cloud = read_cloud(tmp_path / "xyz.npy")
    assert cloud.fields == {} and cloud.xyz.dtype == np.float64
    np.testing.assert_array_equal(cloud.xyz, xyz)

    wide = np.column_stack([xyz, np.arange(20), np.arange(20) * 2]).astype(np.float32)
    np.save(tmp_path / "wide.npy", wide)
    cloud = read_cloud(tmp_path / "wide.npy")
    assert list(cloud.fields) == ["intensity", "col4"]
    assert cloud.fields["intensity"].dtype == np.float32
    np.testing.assert_array_equal(cloud.fields["col4"], np.arange(20) * 2)


def test_npy_structured_array(tmp_path: Path) -> None:
    data = np.zeros(6, dtype=[("label", "i2"), ("x", "f8"), ("y", "f8"), ("z", "f8")])
    data["x"] = np.arange(6)
    data["label"] = [1, 2, 3, 4, 5, 6]
    data["z"][2] = np.nan
    np.save(tmp_path / "structured.npy", data)
    cloud = read_cloud(tmp_path / "structured.npy")
    assert (len(cloud), cloud.n_dropped) == (5, 1)
    assert cloud.fields["label"].dtype == np.int16
    np.testing.assert_array_equal(cloud.fields["label"], [1, 2, 4, 5, 6])


def test_kitti_bin_round_trip(tmp_path: Path) -> None:
    scan = np.random.default_rng(5).random((50, 4)).astype(np.float32)
    scan[7, 1] = np.nan
    scan.tofile(tmp_path / "000000.bin")
    cloud = read_cloud(tmp_path / "000000.bin")
    assert (cloud.n_read, cloud.n_dropped) == (50, 1)
    keep = np.arange(50) != 7
    np.testing.assert_array_equal(cloud.xyz, scan[keep, :3].astype(np.float64))
    np.testing.assert_array_equal(cloud.fields["intensity"], scan[keep, 3])


# --------------------------------------------------------------------------------------------
# NaN dropping and the PointCloud type


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_nan_and_inf_points_are_dropped_counted_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, binary: bool
) -> None:
    xyz = np.arange(30, dtype=float).reshape(10, 3)
    xyz[[1, 4], 0] = np.nan
    xyz[6, 2] = -np.inf
    path = tmp_path / "holes.ply"
    write_ply(path, xyz, {"id": np.arange(10, dtype=np.int32)}, binary=binary)
    with caplog.at_level(logging.INFO, logger="kbs.io"):
        cloud = read_cloud(path)
    assert (cloud.n_read, cloud.n_dropped, len(cloud)) == (10, 3, 7)
    np.testing.assert_array_equal(cloud.fields["id"], [0, 2, 3, 5, 7, 8, 9])
    np.testing.assert_array_equal(cloud.index, cloud.fields["id"])
    records = [r for r in caplog.records if r.name == "kbs.io" and r.levelno == logging.INFO]
    assert len(records) == 1 and "dropped 3 of 10" in records[0].getMessage()


def test_no_log_when_nothing_is_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    np.save(tmp_path / "ok.npy", np.ones((3, 3)))
    with caplog.at_level(logging.DEBUG, logger="kbs.io"):
        read_cloud(tmp_path / "ok.npy")
    assert not [r for r in caplog.records if "dropped" in r.getMessage()]


def test_point_cloud_is_frozen_and_validated() -> None:
    source = np.ones((3, 3), dtype=np.float32)
    cloud = PointCloud.from_arrays(source, {"a": np.arange(3)})
    assert len(cloud) == 3 and cloud.path is None and cloud.xyz.dtype == np.float64
    cloud.xyz[0, 0] = 5.0
    assert source[0, 0] == 1.0  # the cloud owns copies
    with pytest.raises(dataclasses.FrozenInstanceError):
        cloud.xyz = np.zeros((3, 3))  # type: ignore[misc]
    with pytest.raises(TypeError):
        cloud.fields["b"] = np.zeros(3)  # type: ignore[index]
    with pytest.raises(ParameterError, match="shape \\(3,\\)"):
        PointCloud.from_arrays(source, {"a": np.arange(4)})
    with pytest.raises(ParameterError, match="all 2 points are NaN/Inf"):
        PointCloud.from_arrays(np.full((2, 3), np.nan))
    with pytest.raises(ParameterError, match="n_read"):
        PointCloud(np.zeros((2, 3)), {}, None, np.arange(2), n_read=3, n_dropped=0)


# --------------------------------------------------------------------------------------------
# bad files: always a one-line CloudFileError naming the file and the problem


def _bin_of(path: Path, floats: int) -> Path:
    """A scan of 400 points in a sensor frame saved as ``floats`` float32 a record (3: x y z; 5:
    nuScenes' x y z intensity ring), which a KITTI reader takes 4 at a time; the byte count is a
    multiple of 16, so only the values can tell."""
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-30, 30, (400, 2)), rng.uniform(-2, 1, 400), rng.uniform(0, 1, 400),
                         np.arange(400) % 32])[:, :floats]
    out = path / f"of{floats}.bin"
    X.astype("<f4").tofile(out)
    return out


def _ordered_scan(floats: int) -> np.ndarray:
    """16 rings of 300 returns in a scanner's order, in map coordinates (every one positive), with
    ``floats`` float32 a record: x y z, then a remission (0-1) and a ring number."""
    ring, step = np.divmod(np.arange(16 * 300), 300)
    angle = 2 * np.pi * step / 300
    r = 8.0 + 1.5 * ring
    return np.column_stack([5000 + r * np.cos(angle), 7000 + r * np.sin(angle), 40.0 - 1.7 + 0.02 * ring,
                            (step % 97) / 97.0, ring % 32]).astype("<f4")[:, :floats]


def _scan_bin_of(path: Path, floats: int) -> Path:
    """An ordered scan of 3 or 5 floats a record with no negative value: the remission's sign cannot
    tell, the order of the points can."""
    out = path / f"scan{floats}.bin"
    _ordered_scan(floats).tofile(out)
    return out


@pytest.mark.parametrize("order", ["scanner", "shuffled"])
def test_a_kitti_bin_in_any_order_is_read_as_its_records(tmp_path, order):
    """A KITTI scan in map coordinates (no negative value), in its scanner's order or shuffled, is
    read 4 floats a record: its byte count (a multiple of 48) allows records of 3 floats too."""
    X = _ordered_scan(4)
    if order == "shuffled":
        X = X[np.random.default_rng(1).permutation(len(X))]
    X.tofile(tmp_path / "k.bin")
    cloud = read_cloud(tmp_path / "k.bin")
    np.testing.assert_array_equal(cloud.xyz, X[:, :3])
    np.testing.assert_array_equal(cloud.fields["intensity"], X[:, 3])


def test_a_kitti_bin_with_remissions_is_read_as_its_records(tmp_path):
    X = np.column_stack([np.random.default_rng(6).uniform(-30, 30, (400, 3)), np.linspace(0, 1, 400)])
    X.astype("<f4").tofile(tmp_path / "k.bin")
    cloud = read_cloud(tmp_path / "k.bin")
    np.testing.assert_array_equal(cloud.xyz, X[:, :3].astype("<f4"))
    np.testing.assert_array_equal(cloud.fields["intensity"], X[:, 3].astype("<f4"))


def _pcd_binary_longer(path: Path) -> Path:
    """A binary PCD whose POINTS (3) understates its data (5 points): read as 3 points before."""
    out = path / "longer.pcd"
    out.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
                    b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary\n" + np.arange(15, dtype="<f4").tobytes())
    return out


def test_a_binary_pcd_with_a_few_bytes_after_its_points_is_read(tmp_path):
    """Fewer bytes than one point after the data (a writer's trailing newline) are not more points:
    read, as PCL reads them."""
    path = _pcd_binary_longer(tmp_path)
    path.write_bytes(path.read_bytes()[:-24] + b"\n")
    np.testing.assert_array_equal(read_cloud(path).xyz, np.arange(9, dtype="<f4").reshape(3, 3))
    # zeros to the end of a page, as PCL's binary writer pads (the shared Bobkov room ends so)
    path.write_bytes(path.read_bytes()[:-1] + bytes(4096 - 36))
    np.testing.assert_array_equal(read_cloud(path).xyz, np.arange(9, dtype="<f4").reshape(3, 3))


def _truncated_binary_ply(tmp_path: Path) -> Path:
    path = tmp_path / "cut.ply"
    write_ply(path, np.random.default_rng(0).random((100, 3)))
    path.write_bytes(path.read_bytes()[:-100])
    return path


def _truncated_pcd(tmp_path: Path, encoding: Encoding, cut: int) -> Path:
    ramp = np.arange(2000, dtype=np.float32) % 10
    path = _write_pcd(tmp_path / f"cut_{encoding.value}.pcd", {"x": ramp, "y": ramp, "z": ramp}, encoding)
    path.write_bytes(path.read_bytes()[:-cut])
    return path


def _truncated_las(tmp_path: Path, suffix: str = ".las") -> Path:
    path = _write_las(tmp_path / f"cut{suffix}", _utm_xyz(100), np.ones(100, dtype=np.uint8))
    path.write_bytes(path.read_bytes()[:-200])
    return path


def _patched_las(tmp_path: Path, offset: int, *values: float) -> Path:
    """A LAS file whose header doubles from byte ``offset`` on are ``values`` (131: the x, y, z
    scales; 179: max x, min x, max y, min y, max z, min z)."""
    import struct

    path = _write_las(tmp_path / "patched.las", _utm_xyz(100), np.ones(100, dtype=np.uint8))
    data = bytearray(path.read_bytes())
    struct.pack_into(f"<{len(values)}d", data, offset, *values)
    path.write_bytes(bytes(data))
    return path


def _write(name: str, content: bytes):
    def make(tmp_path: Path) -> Path:
        path = tmp_path / name
        path.write_bytes(content)
        return path

    return make


def _npy(name: str, array: np.ndarray):
    def make(tmp_path: Path) -> Path:
        np.save(tmp_path / name, array)
        return tmp_path / name

    return make


def _directory(tmp_path: Path) -> Path:
    (tmp_path / "scan.ply").mkdir()
    return tmp_path / "scan.ply"


def _pcd_without_z(tmp_path: Path) -> Path:
    one = np.ones(4, dtype=np.float32)
    return _write_pcd(tmp_path / "noz.pcd", {"x": one, "y": one, "intensity": one}, Encoding.BINARY)


_PLY_XYZ_HEAD = (
    b"ply\nformat ascii 1.0\nelement vertex %d\nproperty float %s\nproperty float y\nproperty float z\n"
)
_GARBAGE = bytes(np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8))

BAD_FILES = {
    "missing": (lambda tmp_path: tmp_path / "nowhere.xyz", "no such file"),
    "directory": (_directory, "is a directory"),
    "unknown-extension": (
        _write("scan.dxf", b"1 2 3\n"),
        "unknown extension '.dxf' (supported: .bin, .csv, .e57, .las",
    ),
    "no-extension": (_write("scan", b"1 2 3\n"), "no file extension (supported:"),
    "empty-xyz": (_write("empty.xyz", b""), "empty file"),
    "blank-xyz": (_write("blank.xyz", b"\n  \n# only a comment\n"), "no data line"),
    "letters": (
        _write("letters.txt", b"1 2 3\n4 5 6\n7 eight 9\n"),
        "line 3: 'eight' is not a number: '7 eight 9'",
    ),
    "letters-first": (_write("letters.csv", b"1,2,abc\n"), "line 1: 'abc' is not a number"),
    "ragged": (
        _write("ragged.xyz", b"# c\n1 2 3 4\n5 6 7 8\n9 10\n"),
        "line 4 has 2 columns, expected 4: '9 10'",
    ),
    "two-columns": (_write("flat.xyz", b"1 2\n3 4\n"), "line 1 has 2 columns; at least 3 (x y z) are needed"),
    "header-mismatch": (
        _write("h.csv", b"x,y,z\n1,2,3,4\n"),
        "header on line 1 names 3 columns but line 2 has 4",
    ),
    "binary-as-text": (_write("bin.xyz", b"\x00\x01\x02" * 100), "binary data, not a text table"),
    "kitti-15-bytes": (_write("scan.bin", b"\x00" * 15), "size 15 bytes is not a multiple of 16"),
    "all-nan-npy": (_npy("nan.npy", np.full((4, 3), np.nan)), "all 4 points are NaN/Inf"),
    "npy-two-columns": (_npy("flat.npy", np.zeros((4, 2))), "expected an (N, 3+) array"),
    "npy-garbage": (_write("junk.npy", _GARBAGE), "not a NPY file (it does not start with '\\x93NUMPY')"),
    "npy-truncated": (
        _write("cut.npy", b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order'"),
        "NPY file",
    ),
    "garbage-ply": (_write("junk.ply", _GARBAGE), "not a PLY file (it does not start with 'ply')"),
    "garbage-pcd": (
        _write("junk.pcd", _GARBAGE),
        "not a PCD file (it does not start with '#', 'VERSION' or 'FIELDS')",
    ),
    "garbage-las": (_write("junk.las", _GARBAGE), "not a LAS file (it does not start with 'LASF')"),
    "garbage-laz": (
        _write("junk.laz", b"LASF" + _GARBAGE),
        "malformed LAZ header: 3090104048 VLRs",
    ),  # laspy alone spins for minutes
    "short-las": (
        _write("short.las", b"LASF" + bytes(100)),
        "truncated LAS file: 104 bytes, shorter than a LAS header",
    ),
    "ply-bad-header": (
        _write("head.ply", b"ply\nformat ascii 1.0\nelement vertex two\nend_header\n"),
        "malformed PLY file",
    ),
    "ply-no-vertex": (
        _write(
            "novert.ply",
            b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
        ),
        "no vertex element",
    ),
    "ply-no-x": (
        _write(
            "nox.ply",
            _PLY_XYZ_HEAD % (1, b"a") + b"end_header\n1 2 3\n",
        ),
        "no x field in the PLY vertex element (it has: a, y, z)",
    ),
    "ply-zero-points": (
        _write(
            "zero.ply",
            _PLY_XYZ_HEAD % (0, b"x") + b"end_header\n",
        ),
        "holds no points",
    ),
    "truncated-binary-ply": (_truncated_binary_ply, "truncated PLY file"),
    "truncated-pcd-binary-partial-record": (
        lambda p: _truncated_pcd(p, Encoding.BINARY, 5),
        "truncated PCD file",
    ),
    "truncated-pcd-binary-whole-records": (
        lambda p: _truncated_pcd(p, Encoding.BINARY, 120),
        "truncated PCD file: the header announces 2000 points, the data holds 1990",
    ),
    "pcd-binary-longer-than-its-header": (
        lambda p: _pcd_binary_longer(p),
        "PCD file longer than its header says: the header announces 3 points (36 bytes of binary data), "
        "and 24 bytes more follow them (room for 2 more points)",
    ),
    "truncated-pcd-compressed": (
        lambda p: _truncated_pcd(p, Encoding.BINARY_COMPRESSED, 10),
        "corrupt or truncated PCD file",
    ),
    "truncated-pcd-ascii": (
        lambda p: _truncated_pcd(p, Encoding.ASCII, 300),
        "malformed PCD file: the dtype passed requires 3 columns but 1 were found at row",
    ),
    "pcd-bad-header": (
        _write("head.pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nDATA ascii\n1 2 3\n"),
        "malformed PCD file: invalid header (size:",
    ),
    "pcd-no-z": (_pcd_without_z, "no z field in the PCD header (it has: x, y, intensity)"),
    "pcd-zero-points": (
        _write(
            "zero.pcd",
            b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            b"WIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA binary\n",
        ),
        "holds no points",
    ),
    "npy-transposed": (_npy("t.npy", np.zeros((3, 500))), "saved transposed?"),
    "bin-of-three-floats": (lambda p: _bin_of(p, 3), "not KITTI's x y z remission layout: the 4th float32 of"),
    "bin-of-five-floats": (lambda p: _bin_of(p, 5), "not KITTI's x y z remission layout"),
    "bin-of-three-positive-floats": (lambda p: _scan_bin_of(p, 3), "not KITTI's x y z remission layout: read 3 "
                                     "float32 a record, consecutive points lie next to each other"),
    "bin-of-five-positive-floats": (lambda p: _scan_bin_of(p, 5), "(records of 5 floats?)"),
    "las-scale-zero": (lambda p: _patched_las(p, 131, 0.0, 0.0, 0.0),
                       "the x, y, z scale factors 0, 0, 0 must be positive numbers"),
    "las-far-outside-its-bounds": (lambda p: _patched_las(p, 179, 5e5 + 10, 5e5, 5e6 + 10, 5e6, 310.0, 300.0),
                                   "lie far outside its header's bounds"),  # a 10 m box for 1 km of points
    "pcd-size-short": (
        _write("size.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
               b"WIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n"),
        "malformed PCD header: SIZE has 2 values for the 3 FIELDS (x y z)",
    ),
    "ply-header-not-ascii": (
        _write("latin.ply", b"ply\nformat ascii 1.0\ncomment cr\xe9\xe9\n" + _PLY_XYZ_HEAD.split(b"\n", 2)[2] % (1, b"x")
               + b"end_header\n1 2 3\n"),
        "malformed PLY header: line 3 holds byte 0xe9 at column 11",
    ),
    "ply-no-end-header": (_write("noend.ply", _PLY_XYZ_HEAD % (1, b"x") + b"1 2 3\n"),
                          "malformed PLY header: no end_header line"),
    "truncated-las": (_truncated_las, "truncated LAS file"),
    "truncated-laz": (lambda p: _truncated_las(p, ".laz"), "truncated LAZ file"),
}


@pytest.mark.parametrize(("make", "problem"), list(BAD_FILES.values()), ids=list(BAD_FILES))
def test_bad_files_raise_cloud_file_error(tmp_path: Path, make, problem: str) -> None:
    path = make(tmp_path)
    with pytest.raises(CloudFileError) as info:
        read_cloud(path)
    error = info.value
    message = str(error)
    assert error.path == str(path)
    assert message.startswith(f"{path}: ")
    assert problem in error.problem, message
    assert "\n" not in message and len(error.problem) < 200


def test_supported_extensions_match_readers() -> None:
    assert SUPPORTED_EXTENSIONS == (
        ".bin",
        ".csv",
        ".e57",
        ".las",
        ".laz",
        ".npy",
        ".pcd",
        ".ply",
        ".pts",
        ".range",
        ".txt",
        ".xyz",
    )


# --------------------------------------------------------------------------------------------
# the real scans of ../shared/data (skipped when absent)


@pytest.mark.parametrize(
    ("name", "n_points"),
    [
        ("isprs/samp21-utm.pcd", 12_960),
        ("isprs/samp31-utm.pcd", 28_862),
        ("isprs/samp51-utm.pcd", 17_845),
        ("isprs/samp61-utm.pcd", 35_060),
    ],
)
def test_real_isprs_pcd_aligns_with_its_labels(shared_data: Path, name: str, n_points: int) -> None:
    cloud = read_cloud(shared_data / name)
    labels = np.loadtxt(shared_data / name.replace(".pcd", ".labels.txt"), dtype=np.int64)
    assert len(cloud) == cloud.n_read == n_points == len(labels)
    assert cloud.xyz.min(axis=0)[0] > 1e5  # absolute UTM, not centred


@pytest.mark.parametrize(
    ("name", "n_points", "first"),
    [
        ("samp11.txt", 38_010, (512743.63, 5403547.33, 308.68)),
        ("samp12.txt", 52_119, (512203.97, 5403685.49, 336.41)),
    ],
)
def test_real_isprs_text(
    shared_data: Path, name: str, n_points: int, first: tuple[float, float, float]
) -> None:
    cloud = read_cloud(shared_data / "isprs" / name)
    assert len(cloud) == n_points and list(cloud.fields) == ["col3"]
    np.testing.assert_array_equal(cloud.xyz[0], first)  # centimetres of absolute coordinates intact
    assert set(np.unique(cloud.fields["col3"])) == {0.0, 1.0}


def test_real_isprs_text_body_is_parsed_in_one_call(shared_data: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The numbers of a real 50k-line table go through one numpy.loadtxt call (its C parser), not
    line by line in Python: only the preamble is read a line at a time, and the slow scan that names
    a bad line never runs on a good file. (How fast that is: a benchmark's business, not a test's.)"""
    from kbs.io import text

    calls: list[int] = []
    real_loadtxt = np.loadtxt

    def loadtxt(*args, **kwargs):  # type: ignore[no-untyped-def]
        out = real_loadtxt(*args, **kwargs)
        calls.append(out.shape[0])
        return out

    def no_scan(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the body was scanned line by line")

    split_calls = []
    real_split = text._split
    monkeypatch.setattr(text.np, "loadtxt", loadtxt)
    monkeypatch.setattr(text, "_find_bad_line", no_scan)
    monkeypatch.setattr(text, "_split", lambda *a: split_calls.append(1) or real_split(*a))
    cloud = read_cloud(shared_data / "isprs" / "samp12.txt")
    assert calls == [len(cloud)] and len(cloud) > 50_000
    assert len(split_calls) < 10  # the preamble's lines only


@pytest.mark.parametrize(
    ("name", "n_points", "fields"),
    [("semantickitti/000001.points.npy", 88_173, []), ("gndnet/000000.points.npy", 100_000, ["intensity"])],
)
def test_real_npy(shared_data: Path, name: str, n_points: int, fields: list[str]) -> None:
    cloud = read_cloud(shared_data / name)
    labels = np.load(shared_data / name.replace(".points.", ".labels."))
    assert len(cloud) == n_points == len(labels) and list(cloud.fields) == fields
    if fields:
        assert cloud.fields["intensity"].dtype == np.float32


def test_real_mosd_organised_cloud_maps_back_to_its_grid(shared_data: Path) -> None:
    path = shared_data / "mosd" / "learn0.pcd"
    cloud = read_cloud(path)
    assert cloud.shape == (480, 640) and cloud.n_read == 307_200
    assert len(cloud) == 182_292 and cloud.n_dropped == 307_200 - 182_292  # README: "about 185k"
    assert list(cloud.fields) == ["label", "rgba"] and cloud.fields["label"].dtype == np.uint32
    raw = PcdCloud.from_path(path).pc_data.reshape(cloud.shape)
    rows, cols = np.unravel_index(cloud.index, cloud.shape)
    np.testing.assert_array_equal(cloud.xyz[:, 2], raw["z"][rows, cols])
    np.testing.assert_array_equal(cloud.fields["label"], raw["label"][rows, cols])
    assert (cloud.fields["label"] > 0).all()  # label 0 marks exactly the invalid pixels
    invalid = np.ones(cloud.shape, dtype=bool)
    invalid[rows, cols] = False
    assert np.isnan(raw["z"][invalid]).all()


def test_real_bobkov_room(shared_data: Path) -> None:
    cloud = read_cloud(shared_data / "bobkov" / "room1_gt_fine.pcd")
    assert len(cloud) == 237_907 and cloud.shape is None
    assert cloud.fields["label"].dtype == np.uint32 and (cloud.fields["label"] == 0).any()


@pytest.mark.parametrize(
    ("name", "n_points", "n_ground"), [("autzen_trim.las", 110_000, 26_107), ("simple.las", 1_065, 276)]
)
def test_real_las(shared_data: Path, name: str, n_points: int, n_ground: int) -> None:
    cloud = read_cloud(shared_data / "las" / name)
    assert len(cloud) == n_points
    assert np.count_nonzero(cloud.fields["classification"] == 2) == n_ground
    assert cloud.xyz[:, 0].min() > 6e5 and {"red", "green", "blue", "intensity"} <= set(cloud.fields)


@pytest.mark.parametrize(
    ("name", "n_valid", "shape"),
    [("table_scene_mug_stereo_textured.pcd", 209_280, (480, 640)), ("room_scan1.pcd", 112_586, None)],
)
def test_real_unlabelled(shared_data: Path, name: str, n_valid: int, shape: tuple[int, int] | None) -> None:
    cloud = read_cloud(shared_data / "unlabelled" / name)
    assert len(cloud) == n_valid and cloud.shape == shape


@pytest.mark.parametrize("encoding", PCD_ENCODINGS)
def test_pcd_version_0_6_reads_as_0_7(tmp_path: Path, encoding: Encoding) -> None:
    """A PCD 0.6 header (no VIEWPOINT line), which PCL still reads, gives the points of the same
    file written as 0.7."""
    xyz = _utm_xyz(50).astype(np.float32) - np.float32([5e5, 5e6, 0])
    new = _write_pcd(tmp_path / "v07.pcd", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, encoding)
    data = new.read_bytes()
    head, body = data.split(b"DATA", 1)
    lines = [line for line in head.split(b"\n") if not line.startswith((b"VIEWPOINT", b"VERSION"))]
    old = tmp_path / "v06.pcd"
    old.write_bytes(b"VERSION .6\n" + b"\n".join(lines) + b"DATA" + body)
    assert b"VIEWPOINT" not in old.read_bytes()[:400]
    a, b = read_cloud(new), read_cloud(old)
    assert np.array_equal(a.xyz, b.xyz) and len(a.xyz) == 50


def test_las_header_bounds_a_little_off_are_accepted(tmp_path: Path) -> None:
    """A header's bounds a little off (a writer's rounding) are accepted: only points far outside
    them are refused."""
    path = _patched_las(tmp_path, 211, 350.5, 299.5)  # z bounds 0.5 m wider than the points' 300-350
    assert read_cloud(path).xyz.shape == (100, 3)
