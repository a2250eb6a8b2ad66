"""SegComp support: Sun rasterfiles, ABW range images, MS/GT segmentations and `kbs segcomp`.

No real ABW data is available: every raster here is written by the test itself.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kbs.cli.main import main
from kbs.errors import CloudFileError, ParameterError
from kbs.evaluation.segcomp import image_region_normals, region_labels, segmentation_to_image
from kbs.io import read_cloud, write_ply
from kbs.io.segcomp import (
    ABW_ALTERNATIVE_CALIBRATION,
    ABW_CALIBRATION,
    abw_image_number,
    range_to_points,
    read_gt_seg,
    read_ms_nor,
    read_range,
    read_sunraster,
    write_ms_nor,
    write_ms_seg,
    write_sunraster,
)
from test_cli import kbs

MAGIC = 0x59A66A95


def _raster(header: tuple[int, ...], body: bytes = b"", order: str = ">") -> bytes:
    return struct.pack(f"{order}8I", *header) + body


def _expected_point(r: int, c: int, v: int, O: float, S: float, F: float, C: float) -> tuple[float, float, float]:
    """The published ABW formula, written out again independently of kbs.io.segcomp."""
    d = v / S + O
    return (c - 255) * d / abs(F), (255 - r) / C * d / abs(F), (255 - v) / S


# --------------------------------------------------------------------------------------------
# Sun rasterfiles


@pytest.mark.parametrize("shape", [(512, 512), (5, 7), (3, 1), (1, 1), (4, 6)])
def test_sunraster_round_trip_pads_odd_rows_to_16_bits(tmp_path, shape):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, size=shape).astype(np.uint8)
    path = tmp_path / "img.ras"
    write_sunraster(path, image)
    data = path.read_bytes()
    height, width = shape
    row = width + width % 2
    assert len(data) == 32 + height * row
    assert struct.unpack(">8I", data[:32]) == (MAGIC, width, height, 8, height * row, 1, 0, 0)
    rows = np.frombuffer(data[32:], dtype=np.uint8).reshape(height, row)
    np.testing.assert_array_equal(rows[:, :width], image)
    if row != width:  # the pad byte ends each row
        assert (rows[:, width:] == 0).all()
    back = read_sunraster(path)
    assert back.dtype == np.uint8 and back.shape == shape
    np.testing.assert_array_equal(back, image)


def test_sunraster_types_old_and_byte_encoded_colour_map_and_little_endian(tmp_path):
    image = np.array([[1, 1, 1, 1], [0x80, 5, 5, 5], [7, 8, 9, 7]], dtype=np.uint8)
    # RT_OLD: ras_length 0, raw rows
    (tmp_path / "old.ras").write_bytes(_raster((MAGIC, 4, 3, 8, 0, 0, 0, 0), image.tobytes()))
    np.testing.assert_array_equal(read_sunraster(tmp_path / "old.ras"), image)
    # RT_BYTE_ENCODED: 0x80 n v = n+1 copies of v, 0x80 0x00 = one 0x80, other bytes literal
    encoded = bytes([0x80, 3, 1, 0x80, 0, 0x80, 2, 5, 7, 8, 9, 7])
    (tmp_path / "rle.ras").write_bytes(_raster((MAGIC, 4, 3, 8, len(encoded), 2, 0, 0), encoded))
    np.testing.assert_array_equal(read_sunraster(tmp_path / "rle.ras"), image)
    # an odd width: the encoded stream holds the padded rows
    odd = np.array([[3, 3, 3], [4, 4, 4]], dtype=np.uint8)
    encoded = bytes([0x80, 2, 3, 0, 0x80, 2, 4, 0])
    (tmp_path / "rle3.ras").write_bytes(_raster((MAGIC, 3, 2, 8, len(encoded), 2, 0, 0), encoded))
    np.testing.assert_array_equal(read_sunraster(tmp_path / "rle3.ras"), odd)
    # a colour map (RMT_EQUAL_RGB, 2 entries) is skipped; the raw indices are returned
    cmap = bytes([0, 255, 0, 255, 0, 255])
    (tmp_path / "cmap.ras").write_bytes(_raster((MAGIC, 4, 3, 8, 12, 1, 1, 6), cmap + image.tobytes()))
    np.testing.assert_array_equal(read_sunraster(tmp_path / "cmap.ras"), image)
    # a header written in x86 byte order
    (tmp_path / "le.ras").write_bytes(_raster((MAGIC, 4, 3, 8, 12, 1, 0, 0), image.tobytes(), order="<"))
    np.testing.assert_array_equal(read_sunraster(tmp_path / "le.ras"), image)


def _bad_rasters(tmp: Path) -> dict[str, tuple[Path, str]]:
    def put(name: str, data: bytes) -> Path:
        (tmp / name).write_bytes(data)
        return tmp / name

    body = bytes(range(12))
    return {
        "bad magic": (put("magic.ras", _raster((0x12345678, 4, 3, 8, 12, 1, 0, 0), body)), "not a Sun rasterfile"),
        "short header": (put("short.ras", _raster((MAGIC, 4, 3, 8, 12, 1, 0, 0))[:20]), "shorter than the 32-byte"),
        "truncated data": (put("trunc.ras", _raster((MAGIC, 4, 3, 8, 12, 1, 0, 0), body[:7])), "truncated"),
        "24-bit": (put("rgb.ras", _raster((MAGIC, 4, 3, 24, 36, 1, 0, 0), body * 3)), "unsupported Sun rasterfile"),
        "type 3": (put("type3.ras", _raster((MAGIC, 4, 3, 8, 12, 3, 0, 0), body)), "unsupported Sun rasterfile type 3"),
        "truncated rle": (put("rle.ras", _raster((MAGIC, 4, 3, 8, 3, 2, 0, 0), bytes([0x80, 3, 1]))), "truncated"),
        "colour map past the end": (put("cmap.ras", _raster((MAGIC, 4, 3, 8, 12, 1, 1, 999), body)), "colour map"),
        "missing": (tmp / "nowhere.ras", "no such file"),
    }


@pytest.mark.parametrize("case", ["bad magic", "short header", "truncated data", "24-bit", "type 3",
                                  "truncated rle", "colour map past the end", "missing"])
def test_bad_sunrasters_are_one_line_cloud_file_errors(tmp_path, case):
    path, needle = _bad_rasters(tmp_path)[case]
    with pytest.raises(CloudFileError) as info:
        read_sunraster(path)
    assert info.value.path == str(path) and needle in info.value.problem
    assert "\n" not in str(info.value)


def test_write_sunraster_rejects_what_8_bits_cannot_hold(tmp_path):
    for image in (np.zeros(5), np.full((2, 2), 256), np.full((2, 2), -1), np.zeros((2, 2)) + 0.5):
        with pytest.raises(ParameterError):
            write_sunraster(tmp_path / "x.ras", image)


# --------------------------------------------------------------------------------------------
# ABW range images to 3D


def _facet_values(normal, v_centre: float, r0: int, c0: int, rows: int, cols: int,
                  cal=ABW_CALIBRATION) -> np.ndarray:
    """Exact (unrounded) range values of the plane with ``normal`` through the 3D point of the
    facet's centre pixel at range ``v_centre``, over the pixels [r0, r0+rows) x [c0, c0+cols).

    The ABW formula is a pinhole camera: with d = v/S + O, a pixel's point is
    d ((c-255)/|F|, (255-r)/(C|F|), -1) + (0, 0, 255/S + O); a plane n.X = h meets that ray at
    d = (h - n_z (255/S + O)) / (n_x (c-255)/|F| + n_y (255-r)/(C|F|) - n_z).
    """
    O, S, F, C = cal.offset, cal.scale, abs(cal.focal), cal.aspect
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    rc, cc = r0 + rows // 2, c0 + cols // 2
    h = n @ np.array(_expected_point(rc, cc, v_centre, O, S, F, C))
    r, c = np.mgrid[r0:r0 + rows, c0:c0 + cols]
    d = (h - n[2] * (255 / S + O)) / (n[0] * (c - 255) / F + n[1] * (255 - r) / (C * F) - n[2])
    return S * (d - O)


def _two_planes() -> tuple[np.ndarray, np.ndarray]:
    """A floor (constant range 180: a plane z = const) over rows 300-399 and a ramp tilted 35 deg
    about the x axis over rows 100-199 (range values rounded, as a scanner quantises them)."""
    image = np.zeros((512, 512), dtype=np.uint8)
    image[300:400, 100:400] = 180
    ramp_normal = (0.0, np.sin(np.radians(35)), np.cos(np.radians(35)))
    image[100:200, 100:400] = np.rint(_facet_values(ramp_normal, 90, 100, 100, 100, 300)).astype(np.uint8)
    return image, np.array(ramp_normal)


def test_two_planes_to_3d_match_the_formula_by_hand():
    image, ramp_normal = _two_planes()
    image[0, 0], image[100, 50], image[300, 400] = 100, 200, 37  # three pixels worked out by hand
    xyz, pixel = range_to_points(image)
    assert xyz.dtype == np.float64 and pixel.dtype == np.int64
    assert np.array_equal(pixel, np.flatnonzero(image))  # only v != 0, in row-major order
    at = {int(p): xyz[i] for i, p in enumerate(pixel)}
    # d = v/0.791686 + 771.016866; x = (c-255) d/1586.072821; y = (255-r)/1.4508 d/1586.072821;
    # z = (255-v)/0.791686
    np.testing.assert_allclose(at[0], [-144.26767643983263, 99.44008577325103, 195.78469241593257], rtol=1e-12)
    np.testing.assert_allclose(at[100 * 512 + 50], [-132.3058208382437, 68.9523769221616, 69.47198763145995],
                               rtol=1e-12)
    np.testing.assert_allclose(at[300 * 512 + 400], [74.75957005992159, -15.99203603574946, 275.36169643015035],
                               rtol=1e-12)
    # the floor is the plane z = (255 - 180)/S, exactly
    rows, cols = np.divmod(pixel, 512)
    floor = xyz[(rows >= 300) & (rows < 400) & (cols >= 100) & (cols < 400)]
    np.testing.assert_allclose(floor[:, 2], 75 / 0.791686, rtol=1e-13)
    assert np.ptp(floor[:, 0]) > 100 and np.ptp(floor[:, 1]) > 30
    # the ramp's points lie on its plane up to the rounding of the range (half a level along the ray)
    ramp = xyz[(rows >= 100) & (rows < 200) & (cols >= 100) & (cols < 400)]
    offset = ramp @ ramp_normal
    assert np.ptp(offset) < 2 * 0.5 / 0.791686 * 1.05
    np.testing.assert_allclose(np.linalg.eigh(np.cov(ramp, rowvar=False))[1][:, 0] @ ramp_normal, 1, atol=1e-4)


def test_the_alternative_calibration_is_chosen_for_test_image_19(tmp_path):
    image = np.zeros((512, 512), dtype=np.uint8)
    image[0, 0] = 100
    alt = _expected_point(0, 0, 100, 785.410786, 0.773545, -1610.981722, 1.4508)
    std = _expected_point(0, 0, 100, 771.016866, 0.791686, -1586.072821, 1.4508)
    np.testing.assert_allclose(alt, [-144.78430288588456, 99.7961834063169, 200.37619013761318], rtol=1e-12)
    np.testing.assert_allclose(range_to_points(image, image_number=19)[0][0], alt, rtol=1e-12)
    np.testing.assert_allclose(range_to_points(image, image_number=1)[0][0], std, rtol=1e-12)
    np.testing.assert_allclose(range_to_points(image)[0][0], std, rtol=1e-12)
    np.testing.assert_allclose(range_to_points(image, ABW_ALTERNATIVE_CALIBRATION)[0][0], alt, rtol=1e-12)
    # from the file name, as the SegComp tools do
    assert abw_image_number("data/abw.test.19.range") == 19 and abw_image_number("abw.test.1.range") == 1
    assert abw_image_number("abw.train.19.range") is None and abw_image_number("scene.range") is None
    for name, expected in (("abw.test.19.range", alt), ("abw.test.1.range", std), ("abw.train.19.range", std)):
        write_sunraster(tmp_path / name, image)
        np.testing.assert_allclose(read_range(tmp_path / name).xyz[0], expected, rtol=1e-12)
    np.testing.assert_allclose(read_range(tmp_path / "abw.test.1.range", image_number=19).xyz[0], alt, rtol=1e-12)
    with pytest.raises(ParameterError):
        range_to_points(image, "perceptron")
    with pytest.raises(ParameterError):
        range_to_points(np.zeros((4, 4), dtype=np.uint8))


def test_range_through_read_cloud_keeps_shape_and_pixel_index(tmp_path):
    image, _ = _two_planes()
    path = tmp_path / "scene.range"
    write_sunraster(path, image)
    cloud = read_cloud(path)
    n = np.count_nonzero(image)
    assert cloud.shape == (512, 512) and len(cloud) == n
    assert cloud.n_read == 512 * 512 and cloud.n_dropped == 512 * 512 - n
    np.testing.assert_array_equal(cloud.index, np.flatnonzero(image))
    rows, cols = np.unravel_index(cloud.index, cloud.shape)
    np.testing.assert_array_equal(cloud.fields["range"], image[rows, cols])
    assert cloud.fields["range"].dtype == np.uint8
    np.testing.assert_array_equal(cloud.xyz, range_to_points(image)[0])
    assert read_cloud(tmp_path / "scene.range", format="range").shape == (512, 512)


@pytest.mark.parametrize("case", ["truncated", "bad magic", "not 512", "no data"])
def test_bad_range_files_give_cloud_file_error(tmp_path, case):
    image, _ = _two_planes()
    path = tmp_path / "bad.range"
    write_sunraster(path, image)
    data = path.read_bytes()
    needle = {"truncated": "truncated", "bad magic": "not a Sun rasterfile", "not 512": "not an ABW range image",
              "no data": "no range data"}[case]
    if case == "truncated":
        path.write_bytes(data[:100_000])
    elif case == "bad magic":
        path.write_bytes(b"P5\n512 512\n255\n" + data[32:])
    elif case == "not 512":
        write_sunraster(path, image[:256])
    else:
        write_sunraster(path, np.zeros((512, 512), dtype=np.uint8))
    with pytest.raises(CloudFileError) as info:
        read_cloud(path)
    assert info.value.path == str(path) and needle in info.value.problem


# --------------------------------------------------------------------------------------------
# GT and MS segmentations


def test_gt_seg_values_and_ms_seg_checks(tmp_path):
    gt = np.zeros((6, 8), dtype=np.uint8)
    gt[:3], gt[3:, :4], gt[5, 7] = 10, 11, 1
    write_sunraster(tmp_path / "x.gt-seg", gt)
    np.testing.assert_array_equal(read_gt_seg(tmp_path / "x.gt-seg"), gt)
    gt[0, 0] = 5
    write_sunraster(tmp_path / "bad.gt-seg", gt)
    with pytest.raises(CloudFileError, match="pixel value 5"):
        read_gt_seg(tmp_path / "bad.gt-seg")

    ms = np.zeros((6, 8), dtype=np.uint8)
    ms[:2], ms[2:4], ms[4:] = 10, 11, 12
    ms[0, 0] = 3
    write_ms_seg(tmp_path / "x.ms-seg", ms)
    np.testing.assert_array_equal(read_sunraster(tmp_path / "x.ms-seg"), ms)
    assert struct.unpack(">8I", (tmp_path / "x.ms-seg").read_bytes()[:32])[5:] == (1, 0, 0)  # compare wants no map
    for bad, message in ((np.where(ms == 11, 13, ms), "11 is missing"), (np.where(ms == 12, 7, ms), "label 7"),
                         (np.zeros((6, 8), dtype=np.uint8), "no region")):
        with pytest.raises(ParameterError, match=message):
            write_ms_seg(tmp_path / "y.ms-seg", bad)


def test_ms_nor_is_the_count_then_label_and_unit_normal_per_line(tmp_path):
    write_ms_nor(tmp_path / "x.ms-nor", {11: [0, 0, -2.0], 10: np.array([3.0, 0, 4.0])})
    assert (tmp_path / "x.ms-nor").read_text() == (
        "2\n10 0.600000000 0.000000000 0.800000000\n11 0.000000000 0.000000000 1.000000000\n"
    )
    back = read_ms_nor(tmp_path / "x.ms-nor")
    assert sorted(back) == [10, 11]
    np.testing.assert_allclose(back[10], [0.6, 0, 0.8])
    for bad in ({9: [0, 0, 1]}, {10: [0, 0, 0]}, {10: [1, 2]}, {10: [np.nan, 0, 1]}):
        with pytest.raises(ParameterError):
            write_ms_nor(tmp_path / "y.ms-nor", bad)
    (tmp_path / "bad.ms-nor").write_text("3\n10 0 0 1\n")
    with pytest.raises(CloudFileError, match="not a SegComp normals file"):
        read_ms_nor(tmp_path / "bad.ms-nor")


def test_clusters_become_consecutive_region_labels():
    cluster = np.array([0, 0, 0, 1, 1, 1, -1, 2, 2, 2, 2, 3])
    pixel = np.array([0, 1, 2, 5, 6, 7, 8, 9, 10, 11, 12, 15])
    image = segmentation_to_image(cluster, pixel, (4, 4))
    assert image.dtype == np.uint8 and image.shape == (4, 4)
    # cluster k -> 10 + k; noise, no-data pixels and the 1-point cluster 3 -> 0
    np.testing.assert_array_equal(image.ravel(), [10, 10, 10, 0, 0, 11, 11, 11, 0, 12, 12, 12, 12, 0, 0, 0])
    # gaps in cluster ids are closed: labels stay consecutive from 10
    assert region_labels(np.array([4, 4, 4, 7, 7, 7, -1])) == {4: 10, 7: 11}
    # more clusters than 246 labels: the largest are kept
    many = np.repeat(np.arange(300), np.r_[np.full(54, 3), np.full(246, 5)])
    kept = region_labels(many)
    assert len(kept) == 246 and min(kept) == 54 and list(kept.values()) == list(range(10, 256))
    with pytest.raises(ParameterError, match="share a pixel"):
        segmentation_to_image(np.array([0, 0, 0]), np.array([1, 1, 2]), (2, 2))
    with pytest.raises(ParameterError, match="pixel indices"):
        segmentation_to_image(np.array([0, 0, 0]), np.array([1, 2, 4]), (2, 2))


def test_region_normals_are_the_planes_normals():
    rng = np.random.default_rng(1)
    u, w = rng.uniform(-10, 10, (2, 200))
    a = np.column_stack([u, w, 0.5 * u + 3])  # normal ~ (-0.5, 0, 1)
    b = np.column_stack([u, w, np.full(200, -4.0)])  # normal (0, 0, 1)
    labels = np.zeros((20, 20), dtype=np.uint8)
    labels.ravel()[:200], labels.ravel()[200:] = 10, 11
    normals = image_region_normals(labels, np.vstack([a, b]), np.arange(400))
    np.testing.assert_allclose(normals[10], np.array([-0.5, 0, 1]) / np.sqrt(1.25), atol=1e-12)
    np.testing.assert_allclose(normals[11], [0, 0, 1], atol=1e-12)


# --------------------------------------------------------------------------------------------
# end to end: a synthetic .range through `kbs run` and `kbs segcomp`

#: (normal, range at the centre, top row, left column) of four 64 x 64 facets: two fronto-parallel
#: (a floor and a box top), a ramp tilted 30 deg about x and a face tilted 40 deg about y.
FACETS = (
    ((0.0, 0.0, 1.0), 200, 120, 120),
    ((0.0, 0.0, 1.0), 110, 120, 280),
    ((0.0, np.sin(np.radians(30)), np.cos(np.radians(30))), 160, 280, 120),
    ((np.sin(np.radians(40)), 0.0, np.cos(np.radians(40))), 60, 280, 280),
)
SIZE = 64


def _facets_image() -> tuple[np.ndarray, np.ndarray]:
    image = np.zeros((512, 512), dtype=np.uint8)
    facet = np.full((512, 512), -1)
    for i, (normal, v, r0, c0) in enumerate(FACETS):
        values = np.rint(_facet_values(normal, v, r0, c0, SIZE, SIZE))
        assert values.min() >= 1 and values.max() <= 255
        image[r0:r0 + SIZE, c0:c0 + SIZE] = values
        facet[r0:r0 + SIZE, c0:c0 + SIZE] = i
    return image, facet


@pytest.mark.slow
def test_segcomp_end_to_end_through_kbs_run(tmp_path):
    image, facet = _facets_image()
    scan = tmp_path / "abw.train.3.range"
    write_sunraster(scan, image)
    # the shipped rule base of the contest on ABW images (thresholds in the calibration's units)
    r = kbs("run", "--rules", "abw", str(scan), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    result = tmp_path / "out" / "abw.train.3.ply"
    r = kbs("segcomp", str(result), "--image", str(scan))
    assert r.returncode == 0, r.stderr
    ms_seg, ms_nor = tmp_path / "out" / "abw.train.3.ms-seg", tmp_path / "out" / "abw.train.3.ms-nor"
    assert f"wrote {ms_seg} and {ms_nor}" in r.stdout

    ms = read_sunraster(ms_seg)
    assert ms.shape == (512, 512)
    assert (ms[image == 0] == 0).all()  # no data, no region
    # every facet got one region label of its own
    facet_label = []
    for i in range(len(FACETS)):
        labels, counts = np.unique(ms[facet == i], return_counts=True)
        best = labels[counts.argmax()]
        assert best >= 10 and counts.max() >= 0.95 * SIZE * SIZE, (i, labels, counts)
        facet_label.append(int(best))
    assert len(set(facet_label)) == len(FACETS)
    # the labels are the clusters: cluster k -> 10 + k, noise -> 0
    vertex = PlyData.read(str(result))["vertex"]
    cluster, pixel = np.asarray(vertex["scalar_cluster"]), np.asarray(vertex["pixel"])
    assert cluster.max() + 1 + 10 <= 256
    np.testing.assert_array_equal(ms.ravel()[pixel], np.where(cluster >= 0, cluster + 10, 0))
    # the normals file gives each facet's plane
    normals = read_ms_nor(ms_nor)
    assert sorted(normals) == list(range(10, 10 + len(normals)))
    assert set(np.unique(ms[ms >= 10])) == set(normals)
    for (normal, *_), label in zip(FACETS, facet_label):
        angle = np.degrees(np.arccos(min(1.0, abs(float(np.dot(normals[label], normal))))))
        assert angle < 1.0, (label, normals[label], normal)
    # the same result against another image of the same size and coverage: refused, not a wrong .ms-seg
    other = tmp_path / "abw.train.4.range"
    write_sunraster(other, np.where(image > 0, np.clip(image.astype(int) + 3, 1, 255), 0).astype(np.uint8))
    r = kbs("segcomp", str(result), "--image", str(other), "--out", str(tmp_path / "other.ms-seg"))
    assert r.returncode == 3 and f"differs from {other}'s at their pixels: the result was not computed from this " \
                                  "image" in r.stderr, r.stderr
    wider = tmp_path / "abw.train.5.range"  # more pixels with data than the result has points
    more = image.copy()
    assert (more[:4, :4] == 0).all()
    more[:4, :4] = 100
    write_sunraster(wider, more)
    r = kbs("segcomp", str(result), "--image", str(wider), "--out", str(tmp_path / "wider.ms-seg"))
    assert r.returncode == 3 and f"has {int(np.count_nonzero(more)):,} pixels with data: the result was not " \
                                  "computed from this image" in r.stderr, r.stderr
    assert not (tmp_path / "other.ms-seg").exists() and not (tmp_path / "wider.ms-seg").exists()


def test_segcomp_errors_are_one_line_with_exit_codes(tmp_path, capsys):
    image, facet = _facets_image()
    scan = tmp_path / "scene.range"
    write_sunraster(scan, image)
    pixel = np.flatnonzero(image)
    xyz = range_to_points(image)[0]
    cluster = facet.ravel()[pixel].astype(np.int32)
    write_ply(tmp_path / "good.ply", xyz, {"cluster": cluster, "pixel": pixel.astype(np.int32)})
    # a result of an unorganised input: no 'pixel'
    write_ply(tmp_path / "flat.ply", xyz, {"cluster": cluster})
    # a result on another image: points where this image has no data
    write_ply(tmp_path / "other.ply", xyz, {"cluster": cluster, "pixel": (pixel + 1).astype(np.int32)})
    write_ply(tmp_path / "noise.ply", xyz, {"cluster": np.full(len(xyz), -1, np.int32),
                                            "pixel": pixel.astype(np.int32)})
    cases = [
        (("flat.ply", "--image", str(scan)), 3, "the input of `kbs run` was not organised"),
        (("other.ply", "--image", str(scan)), 3, "has no data: the result was not computed from this image"),
        (("noise.ply", "--image", str(scan)), 3, "every point is noise"),
        (("good.ply", "--image", str(tmp_path / "missing.range")), 3, "missing.range: no such file"),
        (("good.ply", "--image", str(tmp_path / "good.ply")), 3, "not a Sun rasterfile"),
        (("nowhere.ply", "--image", str(scan)), 3, "nowhere.ply: no such file"),
        (("good.ply", "--image", str(scan), "--out", str(scan)), 3, "is the input"),
        (("good.ply",), 2, "--image"),
    ]
    for (name, *rest), code, needle in cases:  # in-process: the same entry point as the command
        assert main(["segcomp", str(tmp_path / name), *rest]) == code, name
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, err
        if code == 3:
            assert len(err.strip().splitlines()) == 1 and err.startswith("kbs: error: "), err
    # the real command, on a good result written by a fake `kbs run`: --no-normals writes only the image
    r = kbs("segcomp", str(tmp_path / "good.ply"), "--image", str(scan), "--out", str(tmp_path / "g.ms-seg"),
            "--no-normals")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "g.ms-seg").exists() and not (tmp_path / "g.ms-nor").exists()
    np.testing.assert_array_equal(read_sunraster(tmp_path / "g.ms-seg"), np.where(facet >= 0, facet + 10, 0))
    assert kbs("segcomp", str(tmp_path / "flat.ply"), "--image", str(scan)).returncode == 3


def test_segcomp_replaces_no_input_and_no_existing_file_without_force(tmp_path, capsys):
    """--out / --normals over the ground truth or the result's JSON (a later kbs eval then scores
    the wrong files), over each other, or over any existing file: refused before the work, exit 3;
    an existing .ms-seg / .ms-nor (no room for a run id) replaced only with --force."""
    image, facet = _facets_image()
    scan = tmp_path / "scene.range"
    write_sunraster(scan, image)
    pixel = np.flatnonzero(image)
    xyz = range_to_points(image)[0]
    write_ply(tmp_path / "good.ply", xyz, {"cluster": facet.ravel()[pixel].astype(np.int32),
                                           "pixel": pixel.astype(np.int32)})
    (tmp_path / "good.json").write_text('{"kbs_version": "0", "run_id": "x"}')
    gt = tmp_path / "scene.gt-seg"
    write_sunraster(gt, image)
    protected = {p: p.read_bytes() for p in (scan, gt, tmp_path / "good.json", tmp_path / "good.ply")}
    good = str(tmp_path / "good.ply")
    cases = [
        (["--out", str(gt), "--no-normals"], f"{gt}: is the input"),
        (["--out", str(tmp_path / "x.ms-seg"), "--normals", str(tmp_path / "good.json")], "good.json: is the input"),
        (["--out", str(tmp_path / "x.ms-seg"), "--normals", str(tmp_path / "x.ms-seg")],
         "x.ms-seg: is both --out and --normals"),
    ]
    for force in ([], ["--force"]):  # never over an input, even with --force
        for args, needle in cases:
            assert main(["segcomp", good, "--image", str(scan), *args, *force]) == 3, args
            err = capsys.readouterr().err
            assert needle in err and len(err.splitlines()) == 1, err
    assert {p: p.read_bytes() for p in protected} == protected
    assert not (tmp_path / "x.ms-seg").exists()
    mine = tmp_path / "mine.ms-seg"
    mine.write_text("someone else's segmentation")
    assert main(["segcomp", good, "--image", str(scan), "--out", str(mine), "--no-normals"]) == 3
    err = capsys.readouterr().err
    assert f"kbs: error: {mine}: exists, and kbs cannot tell whether it wrote it" in err and "--force" in err
    assert mine.read_text() == "someone else's segmentation"
    assert main(["segcomp", good, "--image", str(scan), "--out", str(mine), "--no-normals", "--force"]) == 0
    np.testing.assert_array_equal(read_sunraster(mine), np.where(facet >= 0, facet + 10, 0))
    # the normals too: a foreign one stops both files before the work
    nor = tmp_path / "other.ms-nor"
    nor.write_text("mine")
    assert main(["segcomp", good, "--image", str(scan), "--out", str(tmp_path / "other.ms-seg")]) == 3
    assert f"{nor}: exists" in capsys.readouterr().err and nor.read_text() == "mine"
    assert not (tmp_path / "other.ms-seg").exists()


# --------------------------------------------------------------------------------------------
# the planar contest on ABW range images, end to end: kbs synth abw -> kbs run --rules abw ->
# kbs segcomp -> kbs eval X.ms-seg X.gt-seg (the paper's Table 1)


@pytest.mark.slow
def test_the_abw_rule_base_ships_and_is_written_in_abw_units():
    r = kbs("rules", "list")
    assert r.returncode == 0 and any(line.startswith("abw ") for line in r.stdout.splitlines()), r.stdout
    r = kbs("rules", "check", "abw")
    assert r.returncode == 0 and "abw: ok" in r.stdout, r.stdout + r.stderr
    import yaml
    from jsonschema import Draft202012Validator

    from kbs.knowledge import load_rule_base, shipped_rule_bases
    from kbs.knowledge.rulebase import schema

    assert "abw" in shipped_rule_bases()
    rb, contest = load_rule_base("abw"), load_rule_base("planar_contest")
    assert rb.text.startswith("# yaml-language-server: $schema=rule-base.schema.json")
    assert not list(Draft202012Validator(schema()).iter_errors(yaml.safe_load(rb.text)))
    assert rb.units == "mm"
    # the paper's contest planarity, 1 length unit, in the calibration's unit (planar_contest: 0.01 m)
    assert rb.checks["planar"].predicate.name == "thickness" and rb.checks["planar"].max == 1.0
    assert contest.checks["planar"].max == 0.01
    # otherwise the contest's rules: PAh alone, no ground merging, the same labels
    assert {r.name: r.action for r in rb.rules} == {r.name: r.action for r in contest.rules} == {
        "noise": "reject", "PAh": "split"}
    assert rb.merge is None and rb.label_names == contest.label_names == ["plane"]


@pytest.mark.slow
def test_synth_abw_writes_a_range_image_whose_points_lie_on_the_gt_faces(tmp_path):
    from kbs.synth.abw import abw_scene

    r = kbs("synth", "abw", "--seed", "3", "--out", str(tmp_path / "abw.synth.3"))
    assert r.returncode == 0, r.stderr
    assert f"wrote {tmp_path / 'abw.synth.3.range'} and {tmp_path / 'abw.synth.3.gt-seg'}" in r.stdout
    image = read_sunraster(tmp_path / "abw.synth.3.range")
    gt = read_gt_seg(tmp_path / "abw.synth.3.gt-seg")
    scene = abw_scene(3)  # same seed, same image
    np.testing.assert_array_equal(image, scene.range_image)
    np.testing.assert_array_equal(gt, scene.gt_image)
    assert image.shape == gt.shape == (512, 512)
    regions = np.unique(gt[gt >= 10])
    assert list(regions) == list(range(10, 10 + regions.size)) and 10 <= regions.size <= 16
    assert (gt[image == 0] == 0).all()
    # read back through the ABW calibration, each GT region is a plane of the generated normal,
    # flat up to the range quantisation (one level = 1/S = 1.26 units along the ray)
    cloud = read_range(tmp_path / "abw.synth.3.range")
    label = gt.ravel()[cloud.index]
    tilted = 0
    for region in regions:
        P = cloud.xyz[label == region]
        normal = scene.normals_by_label[int(region)]
        offset = P @ normal
        assert np.ptp(offset) <= 1.0 / ABW_CALIBRATION.scale * 1.05, (region, np.ptp(offset))
        fitted = np.linalg.eigh(np.cov(P, rowvar=False))[1][:, 0]
        assert abs(fitted @ normal) > np.cos(np.radians(1.0)), region
        tilted += abs(normal[2]) < np.cos(np.radians(10))
    assert tilted >= 4  # sides are seen, not only fronto-parallel tops
    # a bad parameter is a one-line error with exit code 6 / 2
    r = kbs("synth", "abw", "--boxes", "40", "--out", str(tmp_path / "crowded"))
    assert r.returncode == 6 and "could not place" in r.stderr and "Traceback" not in r.stderr
    assert kbs("synth", "abw", "--tilt", "70").returncode == 2


@pytest.mark.slow
def test_abw_contest_end_to_end_synth_run_segcomp_eval(tmp_path):
    prefix = tmp_path / "abw.synth.0"
    assert kbs("synth", "abw", "--seed", "0", "--out", str(prefix)).returncode == 0
    out = tmp_path / "out"
    r = kbs("run", "--rules", "abw", str(prefix) + ".range", "--out", str(out))
    assert r.returncode == 0, r.stderr
    r = kbs("segcomp", str(out / "abw.synth.0.ply"), "--image", str(prefix) + ".range")
    assert r.returncode == 0, r.stderr
    ms_seg = out / "abw.synth.0.ms-seg"
    r = kbs("eval", str(ms_seg), str(prefix) + ".gt-seg", "--json", str(tmp_path / "eval.json"))
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stdout.splitlines()
    # the paper's Table 1: one row per T = 0.51 (Hoover's T must exceed 0.5), 0.6, 0.7, 0.8, 0.9
    head = next(i for i, line in enumerate(lines) if line.startswith("Hoover et al. (1996), Table 1"))
    assert lines[head + 1].split()[:6] == ["T", "correct", "over", "under", "missed", "noise"]
    assert "angle error" in lines[head + 1]
    rows = [line.split() for line in lines[head + 2:head + 7]]
    assert [row[0] for row in rows] == ["0.51", "0.60", "0.70", "0.80", "0.90"]
    doc = json.loads((tmp_path / "eval.json").read_text())
    table = doc["table"]
    assert [t["tolerance"] for t in table] == [0.51, 0.6, 0.7, 0.8, 0.9]
    for row, t in zip(rows, table):  # the JSON carries what is printed
        assert [int(v) for v in row[1:6]] == [t[k] for k in ("correct", "over", "under", "missed", "noise")]
        assert t["n_gt_regions"] == int(read_gt_seg(str(prefix) + ".gt-seg").max()) - 9
    t08 = table[3]
    # Measured on this image (seed 0, 13 GT regions): 12 correct, 1 over-segmented (the table
    # plane split in two), none under, missed or noise at T = 0.8; across seeds 0-5 the abw rules
    # score 9-12 correct of 12-13. The bar leaves one region of slack for platform differences;
    # a rule base in the wrong units (planar_contest's 0.01) over-segments every tilted face and
    # fails it.
    assert t08["correct"] >= 11, table
    assert t08["under"] == 0 and t08["missed"] <= 1
    # correct counts do not grow with T
    assert all(a["correct"] >= b["correct"] for a, b in zip(table, table[1:]))
    # the angle error over adjacent, correctly detected regions: normals from the range image's
    # points (GT) and from the .ms-nor written by kbs segcomp (MS)
    assert t08["angle_pairs"] >= 10 and t08["angle_mean"] < 0.5
    assert doc["segcomp"]["image"] == str(prefix) + ".range"
    assert doc["segcomp"]["ms_normals"] == str(out / "abw.synth.0.ms-nor")
    assert doc["hoover"]["tolerance"] == 0.8 and doc["hoover"]["correct"] == t08["correct"]


def _label_images() -> tuple[np.ndarray, np.ndarray]:
    """A 6 x 8 GT of three regions and an MS that detects 10, over-segments 11 and misses 12."""
    gt = np.zeros((6, 8), dtype=np.uint8)
    gt[:, :4], gt[:3, 4:], gt[3:, 4:] = 10, 11, 12
    ms = np.zeros((6, 8), dtype=np.uint8)
    ms[:, :4] = 10
    ms[:3, 4:6], ms[:3, 6:] = 11, 12
    ms[3:, 4:] = 2  # non-region pixels (a value of 0-3)
    return ms, gt


def test_kbs_eval_segcomp_table_by_hand_and_without_a_range_image(tmp_path):
    from kbs.evaluation.segcomp import grid_adjacency, segcomp_table

    ms, gt = _label_images()
    assert grid_adjacency(gt) == {(10, 11), (10, 12), (11, 12)}
    rows = segcomp_table(ms, gt, (0.6, 0.9))
    assert [(r.correct, r.over, r.under, r.missed, r.noise) for r in rows] == [(1, 1, 0, 1, 0)] * 2
    assert rows[0].angle_mean is None and "not computed" in rows[0].angle_note
    write_sunraster(tmp_path / "x.ms-seg", ms)
    write_sunraster(tmp_path / "x.gt-seg", gt)
    r = kbs("eval", str(tmp_path / "x.ms-seg"), str(tmp_path / "x.gt-seg"), "--tolerances", "0.6,0.9")
    assert r.returncode == 0, r.stderr
    assert "give --image X.range" in r.stdout
    assert "   0.60       1     1      0       1      0  -" in r.stdout, r.stdout
    assert "   0.90       1     1      0       1      0  -" in r.stdout


def test_kbs_eval_segcomp_errors_are_one_line_with_exit_codes(tmp_path, capsys):
    ms, gt = _label_images()
    write_sunraster(tmp_path / "x.ms-seg", ms)
    write_sunraster(tmp_path / "x.gt-seg", gt)
    write_sunraster(tmp_path / "small.gt-seg", gt[:4])
    write_sunraster(tmp_path / "bad.ms-seg", np.where(ms == 12, 5, ms))
    np.save(tmp_path / "labels.npy", np.zeros(48, dtype=np.int64))
    write_sunraster(tmp_path / "abw.range", _facets_image()[0])  # a good range image, of another size
    ms_seg, gt_seg = str(tmp_path / "x.ms-seg"), str(tmp_path / "x.gt-seg")
    cases = [
        ((ms_seg, str(tmp_path / "labels.npy")), 2, "scores X.ms-seg against X.gt-seg"),
        ((ms_seg, gt_seg, "--ground-values", "10"), 2, "not for a SegComp evaluation"),
        ((ms_seg, gt_seg, "--no-hoover"), 2, "not for a SegComp evaluation"),
        ((ms_seg, gt_seg, "--tolerances", "0.5,0.8"), 2, "each T must be in (0.5, 1], got 0.5"),
        ((ms_seg, gt_seg, "--tolerances", "0.8,high"), 2, "expected tolerances separated by commas"),
        ((ms_seg, str(tmp_path / "small.gt-seg")), 3, "not a segmentation of the same image"),
        ((str(tmp_path / "bad.ms-seg"), gt_seg), 3, "pixel value 5"),
        ((str(tmp_path / "none.ms-seg"), gt_seg), 3, "none.ms-seg: no such file"),
        ((ms_seg, gt_seg, "--image", str(tmp_path / "none.range")), 3, "none.range: no such file"),
        ((ms_seg, gt_seg, "--image", gt_seg), 3, "not an ABW range image"),
        ((ms_seg, gt_seg, "--image", str(tmp_path / "abw.range")), 3, "not the image that was segmented"),
    ]
    for args, code, needle in cases:
        assert main(["eval", *args]) == code, args
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (args, err)
    # --image belongs to the SegComp evaluation only
    write_ply(tmp_path / "r.ply", np.zeros((48, 3)), {"cluster": np.zeros(48, np.int32)})
    assert main(["eval", str(tmp_path / "r.ply"), str(tmp_path / "labels.npy"), "--image", "x.range"]) == 2
    assert "--image is for a SegComp evaluation" in capsys.readouterr().err
