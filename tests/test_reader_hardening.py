"""Bad input files found by fuzzing the readers: each is a one-line CloudFileError (exit code 3)
naming the file and, where one applies, the line, byte or header field; never a silently wrong
cloud, a traceback, another exit code or a library's warning on stderr. Good files of the same
shapes still read."""
from __future__ import annotations

import os
import struct
from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.vlrs.vlrlist import VLRList

from kbs.errors import CloudFileError
from kbs.io import read_cloud
from kbs.io.segcomp import read_range, write_sunraster
from test_cli import kbs

RNG = np.random.default_rng(31)
POINTS = RNG.normal(size=(40, 3)).astype("<f4")


def _problem(path: Path, **kwargs) -> str:
    """The problem read_cloud reports for ``path``, checked to be one line naming the file."""
    with pytest.raises(CloudFileError) as info:
        read_cloud(path, **kwargs)
    assert info.value.path == str(path) and str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)
    return info.value.problem


def _run(path: Path, tmp_path: Path, *extra: str) -> str:
    """``kbs run`` on ``path``: exit code 3 and one error line naming the file; that line."""
    r = kbs("run", "--rules", "outdoor", str(path), "--out", str(tmp_path / "out"), "--force", *extra)
    assert r.returncode == 3, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("kbs: error: ") and str(path) in lines[0], r.stderr
    return lines[0]


def _ply_head(fmt: str, n: int, extra: str = "") -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
            f"{extra}end_header\n").encode()


def _ascii_rows(xyz: np.ndarray) -> bytes:
    return "".join(" ".join(f"{v:.6g}" for v in row) + "\n" for row in xyz).encode()


# -- 1. a header count below the data -------------------------------------------------------------

def test_ascii_ply_with_more_lines_than_its_vertex_count(tmp_path):
    path = tmp_path / "more.ply"
    path.write_bytes(_ply_head("ascii", 20) + _ascii_rows(POINTS))  # 40 rows for 20 vertices
    problem = _problem(path)
    assert problem.startswith("PLY file longer than its header says: its elements (20 vertex) end on line 27, "
                              "and 20 more lines follow them (from line 28)"), problem


def test_binary_ply_with_more_records_than_its_vertex_count(tmp_path):
    path = tmp_path / "more.ply"
    path.write_bytes(_ply_head("binary_little_endian", 20) + POINTS.tobytes())
    head = len(_ply_head("binary_little_endian", 20))
    problem = _problem(path)
    assert problem.startswith(f"PLY file longer than its header says: its elements (20 vertex) end at byte "
                              f"{head + 240}, and 240 bytes more follow them (room for 20 more vertex records)"), problem


def test_ply_with_faces_after_its_vertices_and_a_trailing_newline_still_reads(tmp_path):
    """Data after the vertex element that a later element declares is not extra, nor blank space."""
    faces = "element face 2\nproperty list uchar int vertex_indices\n"
    binary = tmp_path / "faces.ply"
    records = np.array([(3, 0, 1, 2), (3, 1, 2, 3)], dtype=[("n", "u1"), ("a", "<i4"), ("b", "<i4"), ("c", "<i4")])
    binary.write_bytes(_ply_head("binary_little_endian", 40, faces) + POINTS.tobytes() + records.tobytes() + b"\n")
    text = tmp_path / "faces_ascii.ply"
    text.write_bytes(_ply_head("ascii", 40, faces) + _ascii_rows(POINTS) + b"3 0 1 2\n3 1 2 3\n\n  \n")
    for path in (binary, text):
        cloud = read_cloud(path)
        np.testing.assert_allclose(cloud.xyz, POINTS, rtol=1e-5)


def _las(path: Path, n: int = 100, version: str = "1.2") -> Path:
    las = laspy.create(point_format=3, file_version=version)
    xyz = RNG.uniform(0, 50, size=(n, 3))
    las.header.scales = [0.01, 0.01, 0.01]
    las.header.offsets = [0.0, 0.0, 0.0]
    las.x, las.y, las.z = xyz.T
    if version == "1.4":
        las.evlrs = VLRList([laspy.VLR("kbs_test", 1, "an extended VLR after the points", b"x" * 100)])
    las.write(path)
    return path


def test_las_with_more_records_than_its_point_count(tmp_path):
    path = _las(tmp_path / "less.las")
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, 60)  # the legacy point count, 100 records present
    path.write_bytes(bytes(data))
    problem = _problem(path)
    assert problem.startswith("LAS file longer than its header says: the header announces 60 points "
                              "(2,040 bytes of point records from byte 227), and 1,360 bytes more follow them "
                              "(room for 40 more points)"), problem


def test_las_with_fewer_records_than_its_point_count_is_truncated(tmp_path):
    path = _las(tmp_path / "more.las")
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 107, 150)
    path.write_bytes(bytes(data))
    assert _problem(path) == "truncated LAS file: the header announces 150 points, the data holds 100"


def test_las_1_4_with_extended_vlrs_after_its_points_still_reads(tmp_path):
    path = _las(tmp_path / "evlr.las", version="1.4")
    assert len(read_cloud(path)) == 100


@pytest.mark.parametrize(("count", "state"), [(80, "truncated PTS file"),
                                               (5, "PTS file longer than its point count says")])
def test_pts_count_line_that_disagrees_with_its_data(tmp_path, count, state):
    path = tmp_path / "scan.pts"
    path.write_bytes(f"{count}\n".encode() + _ascii_rows(POINTS))
    assert _problem(path) == f"{state}: the point count on line 1 announces {count} points, the data holds 40 lines"
    path.write_bytes(b"40\n" + _ascii_rows(POINTS))
    assert len(read_cloud(path)) == 40


def test_pts_count_line_that_is_not_a_whole_number(tmp_path):
    path = tmp_path / "scan.pts"
    path.write_bytes(b"40.5\n" + _ascii_rows(POINTS))
    assert _problem(path) == "line 1: a lone number before the data is a point count, and '40.5' is not a whole number: '40.5'"


def _range_image(path: Path) -> Path:
    image = np.zeros((512, 512), dtype=np.uint8)
    image[100:400, 100:400] = RNG.integers(50, 200, size=(300, 300))
    write_sunraster(path, image)
    return path


def test_range_image_with_bytes_after_its_pixels(tmp_path):
    path = _range_image(tmp_path / "abw.test.1.range")
    assert len(read_cloud(path)) == 300 * 300
    path.write_bytes(path.read_bytes() + bytes(RNG.integers(0, 256, 5000, dtype=np.uint8)))
    problem = _problem(path)
    assert problem.startswith("Sun rasterfile longer than its header says: 512 x 512 8-bit pixels take 262,144 bytes, "
                              "and 5,000 bytes more follow them (room for 9 more rows)"), problem
    with pytest.raises(CloudFileError, match="Sun rasterfile longer than its header says"):
        read_range(path)  # what kbs eval --image reads: the same check


# -- 2. garbage accepted -------------------------------------------------------------------------

def test_kitti_bin_that_is_text(tmp_path):
    path = tmp_path / "scan.bin"
    path.write_bytes(b"1 2 3 4\n" * 2000)
    problem = _problem(path)
    assert problem.startswith("looks like text, not float32 records (its first 4,096 bytes") and \
        "--in-format xyz (or csv)" in problem, problem
    assert len(read_cloud(path, format="xyz")) == 2000


def test_kitti_bin_of_small_positive_floats_is_not_text(tmp_path):
    """Float32 records of values whose bytes are often printable are still records."""
    path = tmp_path / "scan.bin"
    records = np.column_stack([RNG.uniform(1, 60, size=(500, 3)), RNG.uniform(0, 1, 500)]).astype("<f4")
    path.write_bytes(records.tobytes())
    np.testing.assert_array_equal(read_cloud(path).xyz, records[:, :3])


def test_text_table_with_an_absurd_number_of_columns(tmp_path):
    path = tmp_path / "long.xyz"
    path.write_bytes(b"# one long line\n" + b"1 " * 100_000 + b"\n")
    problem = _problem(path)
    assert problem.startswith("line 2 has 100,000 columns, more than the 64 of a point table"), problem
    path.write_bytes(b"1 " * 64 + b"\n" + b"2 " * 64 + b"\n")  # 64 columns: the bound itself reads
    assert read_cloud(path).fields.keys() == {f"col{c}" for c in range(3, 64)}


def _pcd(header: dict[str, str], body: bytes) -> bytes:
    keys = {"VERSION": "0.7", "FIELDS": "x y z", "SIZE": "4 4 4", "TYPE": "F F F", "COUNT": "1 1 1",
            "WIDTH": "40", "HEIGHT": "1", "VIEWPOINT": "0 0 0 1 0 0 0", "POINTS": "40", "DATA": "binary"}
    keys.update(header)
    return "".join(f"{k} {v}\n" for k, v in keys.items()).encode() + body


def test_pcd_whose_width_times_height_is_not_points(tmp_path):
    path = tmp_path / "h0.pcd"
    path.write_bytes(_pcd({"HEIGHT": "0"}, POINTS.tobytes()))
    assert _problem(path) == ("malformed PCD header: WIDTH 40 x HEIGHT 0 != POINTS 40 "
                              "(an unorganised cloud has HEIGHT 1 and WIDTH = POINTS)")


@pytest.mark.parametrize(("header", "names"), [("x x z", "'x' twice (columns 1 and 2: x x z)"),
                                                ("X x y z", "'x' twice (columns 1 and 2: X x y z)"),
                                                ("x y q", "x, y but no z column (x y q)")])
def test_text_header_naming_a_column_twice_or_not_all_of_x_y_z(tmp_path, header, names):
    path = tmp_path / "scan.xyz"
    columns = len(header.split())
    path.write_bytes(header.encode() + b"\n" + _ascii_rows(RNG.normal(size=(10, columns))))
    assert _problem(path) == f"the header on line 1 names {names}"


def test_text_header_clash_is_exit_code_3_naming_file_and_line(tmp_path):
    """Before, `X x y z` was read, then `kbs run` failed writing its result with exit code 6."""
    path = tmp_path / "clash.xyz"
    path.write_bytes(b"X x y z\n" + _ascii_rows(np.column_stack([RNG.normal(size=(600, 3)), np.ones(600)])))
    assert "the header on line 1 names 'x' twice" in _run(path, tmp_path)


# -- 3. wrong exit code ---------------------------------------------------------------------------

@pytest.mark.parametrize(("dtype", "problem"), [
    ([("x", "U5"), ("y", "f4"), ("z", "f4")], "field 'x' is of type <U5, not numbers"),
    ([("x", "f4", (2,)), ("y", "f4"), ("z", "f4")], "field 'x' holds 2 values a point (float32 of shape (2,))"),
])
def test_structured_npy_whose_x_is_not_one_number(tmp_path, dtype, problem):
    path = tmp_path / "struct.npy"
    np.save(path, np.zeros(600, dtype=dtype))
    assert problem in _run(path, tmp_path)


# -- 4. messages that say what is wrong -----------------------------------------------------------

@pytest.mark.parametrize(("size", "field", "column"), [("16 16 16", "x", 1), ("2 2 2", "x", 1), ("4 4 3", "z", 3)])
def test_pcd_field_of_a_size_its_type_has_not(tmp_path, size, field, column):
    path = tmp_path / "size.pcd"
    path.write_bytes(_pcd({"SIZE": size}, bytes(40 * 48)))
    kind = size.split()[column - 1]
    assert _problem(path) == (f"malformed PCD header: field '{field}' (column {column} of FIELDS) has TYPE F and SIZE "
                              f"{kind}, a pair that is not supported (TYPE F has SIZE 4 or 8; I and U have 1, 2, 4 or 8)")


def test_pcd_announcing_more_binary_points_than_the_file_holds_is_not_allocated(tmp_path):
    path = tmp_path / "huge.pcd"
    path.write_bytes(_pcd({"WIDTH": str(10**12), "POINTS": str(10**12)}, POINTS.tobytes()))
    assert _problem(path) == ("truncated PCD file: the header announces 1000000000000 points, the data holds 40 "
                              "(12,000,000,000,000 bytes of binary data announced, 480 bytes after the header)")


def test_ascii_pcd_with_more_lines_than_its_points_is_longer_not_truncated(tmp_path):
    path = tmp_path / "more.pcd"
    path.write_bytes(_pcd({"WIDTH": "20", "POINTS": "20", "DATA": "ascii"}, _ascii_rows(POINTS)))
    assert _problem(path) == "PCD file longer than its header says: the header announces 20 points, the data holds 40"


def _patched(path: Path, offset: int, fmt: str, *values: int) -> Path:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))
    return path


def test_las_of_an_unknown_point_format(tmp_path):
    path = _patched(_las(tmp_path / "fmt.las"), 104, "<B", 77)
    assert _problem(path) == ("malformed LAS header: unknown point data format 77 (header byte 104; LAS defines "
                              "formats 0 to 10, plus 128 when compressed)")


def test_las_of_an_unknown_version(tmp_path):
    path = _patched(_las(tmp_path / "version.las"), 24, "<BB", 9, 9)
    assert _problem(path) == "unsupported LAS version 9.9 (header bytes 24-25): LAS 1.0 to 1.4 are read"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_a_fifo_is_not_a_regular_file_and_is_not_opened(tmp_path):
    fifo = tmp_path / "scan.xyz"
    os.mkfifo(fifo)  # opening it for reading would block this test: it must not be opened
    assert _problem(fifo).startswith("not a regular file but a FIFO (named pipe)")


def test_semicolon_separated_table_names_its_line_and_the_separator(tmp_path):
    path = tmp_path / "scan.csv"
    path.write_bytes(b"# from a spreadsheet\n" + b"1.5;2.5;3.5\n" * 10)
    assert _problem(path) == ("no data line (expected rows of at least 3 numbers: x y z ...): line 2 holds "
                              "'1.5;2.5;3.5' (columns separated by ';'? they are read separated by blanks or by "
                              "commas)")


def test_a_header_and_no_data_names_the_line(tmp_path):
    path = tmp_path / "scan.xyz"
    path.write_bytes(b"x y z\nnot numbers at all\n")
    assert _problem(path) == ("no data line (expected rows of at least 3 numbers: x y z ...): line 2 is not a row "
                              "of numbers: 'not numbers at all'")


# -- 5. no library noise on stderr before the error ----------------------------------------------

def test_ply_whose_x_is_a_list_prints_no_plyfile_warning(tmp_path):
    path = tmp_path / "xlist.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty list uchar float x\nproperty float y\n"
                     b"property float z\nend_header\n2 1 2 3 4\n1 5 6 7\n0 8 9\n")
    assert "no x field in the PLY vertex element (it has: y, z)" in _run(path, tmp_path)


def test_truncated_laz_prints_no_laspy_log_lines(tmp_path):
    pytest.importorskip("lazrs")
    good = _las(tmp_path / "good.las", n=3000)
    path = tmp_path / "cut.laz"
    laspy.read(good).write(path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert "truncated LAZ file" in _run(path, tmp_path)


def test_warnings_of_a_successful_read_are_still_given(tmp_path, recwarn, monkeypatch):
    """Only a failed read drops the libraries' warnings; a read that succeeds passes them on."""
    import kbs.io.readers as readers

    def warn_then_read(path: Path):
        import warnings

        warnings.warn("a library's own warning", UserWarning, stacklevel=1)
        return readers.read_text(path)

    path = tmp_path / "ok.xyz"
    path.write_bytes(_ascii_rows(POINTS))
    monkeypatch.setitem(readers.READERS, ".xyz", warn_then_read)
    assert len(read_cloud(path)) == 40
    assert [str(w.message) for w in recwarn.list] == [f"{path}: a library's own warning"]  # naming the file
