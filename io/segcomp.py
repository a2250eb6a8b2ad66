"""SegComp (Hoover et al. 1996) files: Sun rasterfiles, ABW range images, GT and MS segmentations.

The range-segmentation contest of Hoover et al. (the "SegComp" package of the University of South
Florida) ships its images as 8-bit Sun rasterfiles and scores a machine segmentation (MS) with a
program called ``compare``. This module reads and writes what that program reads, and turns an
ABW range image into 3D points for ``kbs run``:

>>> from kbs.io.segcomp import read_range, read_gt_seg, write_ms_seg, write_ms_nor
>>> cloud = read_range("abw.test.19.range")        # doctest: +SKIP
>>> cloud.shape, cloud.fields["range"].dtype       # doctest: +SKIP
((512, 512), dtype('uint8'))

What each format is, and where it was established
-------------------------------------------------
**Sun rasterfile** (``.range``, ``.gt-seg``, ``.ms-seg``). Source: the SunOS ``rasterfile(4)``
manual page (mirrored at https://hwiegman.home.xs4all.nl/fileformats/R/ras/ras.html) and J.
Zawinski's note "The Sun Rasterfile Format" (http://steve.hollasch.net/cgindex/formats/sunraster.html,
also https://www.fileformat.info/format/sunraster/). A header of 8 big-endian 32-bit integers:
``ras_magic`` (0x59a66a95), ``ras_width``, ``ras_height``, ``ras_depth`` (bits per pixel: 1, 8,
24, 32), ``ras_length`` (bytes of image data, header and colour map excluded; often 0 in old
files), ``ras_type`` (0 RT_OLD, 1 RT_STANDARD, 2 RT_BYTE_ENCODED, 3 RT_FORMAT_RGB, ...),
``ras_maptype`` (0 RMT_NONE, 1 RMT_EQUAL_RGB, 2 RMT_RAW) and ``ras_maplength`` (bytes of colour
map). The colour map follows the header, then the pixels one row at a time, top row first, each
row padded to a multiple of 16 bits (an 8-bit image of odd width has one pad byte per row).
RT_OLD and RT_STANDARD store the rows raw. RT_BYTE_ENCODED is a run-length code of that padded
byte stream: a byte other than 0x80 is itself; ``0x80 0x00`` is one 0x80; ``0x80 n v`` is n + 1
copies of v (Zawinski's note quoting Sun-Spots 6/84; Pillow's ``SunRleDecode.c`` does the same).
Here only 8-bit images are read, of types 0, 1 and 2; a colour map is skipped and the raw pixel
values (the indices) are returned, since range values and labels are what the files hold. A
header written in little-endian order (its magic reads 0x956aa659), as some x86 ports of the
SegComp tools write, is accepted too. Files are written big-endian, RT_STANDARD, no colour map.

**ABW range image** (``abw.*.range``): a 512 x 512 8-bit rasterfile; the pixel value v is the
quantised range, 0 = no data. Pixel (row r, column c, value v) to 3D, with (O, S, F, C) the
calibration: x = (c - 255)(v/S + O)/|F|, y = (255 - r)/C (v/S + O)/|F|, z = (255 - v)/S.
(O, S, F, C) = (771.016866, 0.791686, -1586.072821, 1.4508), except for the test images 0, 19,
21, 25, 27, 28 and 29: (785.410786, 0.773545, -1610.981722, 1.4508). Source:
``ConvertABWRangeToCartesian`` in ``src/segcomp/rangetocoords.cpp`` of the GitHub repository
fkie/structure_coloring_fkie, "a port of ftp://figment.csee.usf.edu/pub/segmentation-comparison/
range-to-coords.c"; its ``src/segcomp/rangeimageio.cpp`` picks the second calibration when the
file name contains ``abw.test.N.range`` with N in that list (same rule here). The geometry is a
pinhole camera: with d = v/S + O, z = (255/S + O) - d, so d is the depth from the camera and
x, y grow with it.

*Units.* None of these sources states the unit of x, y, z; the coordinates are returned in the
formula's own unit. Its scale (one column is about 0.59 units wide at mid range, the image about
300 units wide, one range level 1/S = 1.26 units deep) fits millimetres for a tabletop
structured-light scanner, which is likely but not confirmed. So the shipped ``planar_contest``
rule base (thresholds in metres: a 1 cm thickness bound of 0.01) does not suit these raw
coordinates: 0.01 unit is a hundredth of one range level. The shipped ``abw`` rule base is
the contest in these units (``units: mm``, a thickness bound of 1, of the order of the
quantisation).

**Ground truth** (``.gt-seg``) **and machine segmentation** (``.ms-seg``): 8-bit rasterfiles of
the image's size holding one label per pixel. Source: ``LoadFiles`` and ``ClassifyRegions`` of
the ``compare`` program, ``src/compare/compare.c`` in fkie/structure_coloring_fkie (a modified
copy of the USF tool: it adds ``-noNormals`` and pixel counts). Values 0 to 3 are the
non-region values (its ``NOISE_DEFINED`` table; the meaning of each of the four is not given
there, and was not found elsewhere), values 4 to 9 make ``compare`` stop ("badly defined pixel
value"), regions are labelled 10, 11, ... consecutively ("region labels not consecutive from 10
upward" is an error), so at most 246 regions; an image with no region at all is refused. The
program requires ``ras_maplength == 0`` and the same width and height as the ground truth, and
reads ``rows x cols`` bytes after the header (so it ignores the row padding, harmless for the
512-wide ABW images). A pixel an MS leaves out of every region is written 0, as the fkie
segmenter does (``StructureColoring::writeSegments``: every pixel 0, region ids from 10).

**Machine-segmentation normals** (``.ms-nor``): text, read by ``compare``'s ``LoadFiles`` with
``fscanf``: first the number of regions N (``%d``), then N records ``label nx ny nz`` (``%d``
then three ``%lf``), whitespace-separated; the normal of region ``label`` is stored at that
label. ``compare`` flips a normal with nz < 0 and measures angles with |cos|, so a normal's sign
does not matter. The fkie ``writeMSNormals`` writes exactly this, one region per line. This is
the format of that (modified) copy of ``compare``; the original USF source was not found, so
that its normals reader is unchanged is likely but not verified.
"""
from __future__ import annotations

import logging
import os
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, ParameterError
from kbs.io.cloud import PointCloud

logger = logging.getLogger("kbs.io")

#: ``ras_magic`` of every Sun rasterfile.
RAS_MAGIC = 0x59A66A95
#: ``ras_type`` values: raw pixels (old and standard), and run-length byte encoding.
RT_OLD, RT_STANDARD, RT_BYTE_ENCODED = 0, 1, 2
#: ``ras_maptype`` values.
RMT_NONE, RMT_EQUAL_RGB, RMT_RAW = 0, 1, 2
_HEADER_SIZE = 32
_RLE_ESCAPE = 0x80
#: Largest expansion of the byte encoding: 3 bytes give at most 256 pixels.
_RLE_MAX_RATIO = 256 / 3

#: Size of every ABW range image (rows, columns); the calibration's centre 255 assumes it.
ABW_SHAPE = (512, 512)
#: Pixel values of a SegComp segmentation: 0-3 mark non-region pixels, regions start at 10.
NON_REGION_VALUES = (0, 1, 2, 3)
FIRST_REGION_LABEL = 10
#: Labels 10 ... 255 fit in 8 bits: at most 246 regions (``compare``'s MAX_REGIONS).
MAX_REGIONS = 256 - FIRST_REGION_LABEL
#: The value written for a pixel in no region (no data, noise, or a cluster left out).
NO_REGION = 0


@dataclass(frozen=True)
class ABWCalibration:
    """Constants of the ABW range-to-3D formula (module docstring).

    Attributes
    ----------
    offset : float
        O, added to v / S to give the depth d.
    scale : float
        S, range levels per unit of depth.
    focal : float
        F; only |F| enters the formula (the published value is negative).
    aspect : float
        C, the vertical-to-horizontal pixel ratio.
    """

    offset: float
    scale: float
    focal: float
    aspect: float


#: The calibration of the ABW images ...
ABW_CALIBRATION = ABWCalibration(771.016866, 0.791686, -1586.072821, 1.4508)
#: ... and the one of the test images in :data:`ABW_ALTERNATIVE_TEST_IMAGES`.
ABW_ALTERNATIVE_CALIBRATION = ABWCalibration(785.410786, 0.773545, -1610.981722, 1.4508)
#: ABW *test* images taken with the alternative calibration.
ABW_ALTERNATIVE_TEST_IMAGES = frozenset({0, 19, 21, 25, 27, 28, 29})
_ABW_TEST_NAME = re.compile(r"abw\.test\.(\d+)(?:\.|$)", re.IGNORECASE)


# --- Sun rasterfiles ----------------------------------------------------------------------------


def _row_bytes(width: int) -> int:
    """Bytes of one stored row of an 8-bit image: the width rounded up to 16 bits."""
    return width + (width & 1)


def _decode_byte_encoding(encoded: bytes, size: int) -> bytes | None:
    """Undo RT_BYTE_ENCODED up to ``size`` bytes; None if the data ends first."""
    out = bytearray()
    i, n = 0, len(encoded)
    while len(out) < size:
        if i >= n:
            return None
        byte = encoded[i]
        if byte != _RLE_ESCAPE:
            # copy the literal bytes up to the next escape in one go
            j = encoded.find(_RLE_ESCAPE, i)
            j = n if j < 0 else j
            out += encoded[i:j]
            i = j
        elif i + 1 >= n:
            return None
        elif encoded[i + 1] == 0:
            out.append(_RLE_ESCAPE)
            i += 2
        elif i + 2 >= n:
            return None
        else:
            out += bytes((encoded[i + 2],)) * (encoded[i + 1] + 1)
            i += 3
    return bytes(out[:size])


def _parse_sunraster(data: bytes, path: str) -> np.ndarray:
    """The (H, W) uint8 image of a rasterfile's bytes (see the module docstring)."""
    if len(data) >= 4 and data[:4] == RAS_MAGIC.to_bytes(4, "big"):
        order = ">"
    elif len(data) >= 4 and data[:4] == RAS_MAGIC.to_bytes(4, "little"):
        order = "<"
    else:
        raise CloudFileError(path, "not a Sun rasterfile (it does not start with the magic number 0x59a66a95)")
    if len(data) < _HEADER_SIZE:
        raise CloudFileError(path, f"truncated Sun rasterfile: {len(data)} bytes, shorter than the 32-byte header")
    _, width, height, depth, length, ras_type, maptype, maplength = struct.unpack_from(f"{order}8I", data)
    if depth != 8:
        raise CloudFileError(path, f"unsupported Sun rasterfile depth: {depth} bits per pixel (only 8-bit images)")
    if ras_type not in (RT_OLD, RT_STANDARD, RT_BYTE_ENCODED):
        raise CloudFileError(
            path, f"unsupported Sun rasterfile type {ras_type} (only 0 old, 1 standard and 2 byte-encoded)"
        )
    if width == 0 or height == 0 or width > 1 << 20 or height > 1 << 20:
        raise CloudFileError(path, f"malformed Sun rasterfile header: {width} x {height} pixels")
    if maptype not in (RMT_NONE, RMT_EQUAL_RGB, RMT_RAW):
        raise CloudFileError(path, f"malformed Sun rasterfile header: unknown colour-map type {maptype}")
    start = _HEADER_SIZE + maplength
    if start > len(data):
        raise CloudFileError(
            path, f"truncated Sun rasterfile: a {maplength}-byte colour map announced, {len(data) - 32} bytes follow"
        )
    body = data[start:]
    row = _row_bytes(width)
    need = height * row
    if ras_type == RT_BYTE_ENCODED:
        if length > len(body):
            raise CloudFileError(
                path, f"truncated Sun rasterfile: {length} bytes of encoded data announced, {len(body)} present"
            )
        encoded = body[:length] if length else body
        pixels = None if need > _RLE_MAX_RATIO * len(encoded) + 2 else _decode_byte_encoding(encoded, need)
        if pixels is None:
            raise CloudFileError(
                path, f"truncated Sun rasterfile: the byte-encoded data ends before the {width} x {height} pixels"
            )
    elif len(body) >= need:
        pixels = body[:need]
    elif width % 2 and length == width * height and len(body) >= length:
        # a writer that ignored the 16-bit row padding (the SegComp tools do, for even widths
        # this makes no difference): its ras_length says so
        logger.debug("%s: rows of odd width %d stored without padding", path, width)
        row, pixels = width, body[:length]
    else:
        raise CloudFileError(
            path,
            f"truncated Sun rasterfile: {width} x {height} 8-bit pixels need {need} bytes, "
            f"{len(body)} follow the header",
        )
    return np.frombuffer(pixels, dtype=np.uint8).reshape(height, row)[:, :width].copy()


def _read_bytes(path: str | os.PathLike[str], kind: str) -> tuple[bytes, str]:
    file = os.fspath(path)
    try:
        return Path(file).read_bytes(), file
    except FileNotFoundError as exc:
        raise CloudFileError(file, "no such file") from exc
    except IsADirectoryError as exc:
        raise CloudFileError(file, f"is a directory, not a {kind}") from exc
    except OSError as exc:
        raise CloudFileError(file, f"cannot read: {exc.strerror or exc}") from exc


def read_sunraster(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an 8-bit Sun rasterfile.

    Parameters
    ----------
    path : str or os.PathLike
        The file (types RT_OLD, RT_STANDARD or RT_BYTE_ENCODED; a colour map is skipped).

    Returns
    -------
    np.ndarray, shape (H, W), uint8
        The pixel values, row 0 at the top (the row padding removed).

    Raises
    ------
    CloudFileError
        Missing or unreadable file, bad magic number, a depth other than 8, an unsupported type,
        a malformed header, or fewer pixel bytes than the header announces.
    """
    data, file = _read_bytes(path, "Sun rasterfile")
    return _parse_sunraster(data, file)


def _as_uint8_image(image: object, what: str) -> np.ndarray:
    array = np.asarray(image)
    if array.ndim != 2 or array.shape[0] == 0 or array.shape[1] == 0:
        raise ParameterError(f"{what} must be a non-empty 2-D array (rows, cols), got shape {array.shape}")
    if array.dtype.kind not in "ui" and array.dtype != np.bool_:
        raise ParameterError(f"{what} must hold integers in [0, 255], got dtype {array.dtype}")
    if array.size and array.dtype.kind in "ui" and (array.min() < 0 or array.max() > 255):
        raise ParameterError(
            f"{what} must hold integers in [0, 255], got values in [{array.min()}, {array.max()}]"
        )
    return array.astype(np.uint8)


def write_sunraster(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write an 8-bit Sun rasterfile: big-endian header, RT_STANDARD, no colour map, every row
    padded to 16 bits (one zero byte after each row when the width is odd).

    Parameters
    ----------
    path : str or os.PathLike
        The file to create (overwritten if it exists).
    image : np.ndarray, shape (H, W)
        Integers in [0, 255] (stored as uint8), row 0 at the top.

    Raises
    ------
    ParameterError
        ``image`` is not a non-empty 2-D array of integers in [0, 255].
    CloudFileError
        The file cannot be written.
    """
    pixels = _as_uint8_image(image, "the image")
    height, width = pixels.shape
    row = _row_bytes(width)
    if row != width:
        pixels = np.pad(pixels, ((0, 0), (0, row - width)))
    header = struct.pack(">8I", RAS_MAGIC, width, height, 8, height * row, RT_STANDARD, RMT_NONE, 0)
    try:
        with open(path, "wb") as stream:
            stream.write(header)
            stream.write(np.ascontiguousarray(pixels).tobytes())
    except OSError as exc:
        raise CloudFileError(os.fspath(path), f"cannot write: {exc.strerror or exc}") from exc


# --- ABW range images ---------------------------------------------------------------------------


def abw_image_number(name: str | os.PathLike[str]) -> int | None:
    """The N of an ABW *test* image from its file name (``abw.test.N.range``, any folder), else None."""
    match = _ABW_TEST_NAME.search(Path(os.fspath(name)).name)
    return int(match.group(1)) if match else None


def abw_calibration(image_number: int | None = None) -> ABWCalibration:
    """The calibration of ABW test image ``image_number``: the alternative one for the test images
    0, 19, 21, 25, 27, 28 and 29, the standard one otherwise (and for None)."""
    if image_number is not None and int(image_number) in ABW_ALTERNATIVE_TEST_IMAGES:
        return ABW_ALTERNATIVE_CALIBRATION
    return ABW_CALIBRATION


def range_to_points(
    image: np.ndarray,
    calibration: str | ABWCalibration = "abw",
    image_number: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """3D points of the pixels with data (v != 0) of an ABW range image.

    Parameters
    ----------
    image : np.ndarray, shape (512, 512)
        The range values v, integers in [0, 255]; 0 = no data.
    calibration : "abw" or ABWCalibration, default "abw"
        ``"abw"`` picks the published constants for ``image_number`` (:func:`abw_calibration`);
        an :class:`ABWCalibration` is used as given.
    image_number : int, optional
        Number of the ABW *test* image (``abw.test.N``), to choose the calibration.

    Returns
    -------
    xyz : np.ndarray, shape (n, 3), float64
        x = (c - 255)(v/S + O)/|F|, y = (255 - r)/C (v/S + O)/|F|, z = (255 - v)/S, in the
        formula's own unit (see the module docstring: likely millimetres, not confirmed).
    pixel : np.ndarray, shape (n,), int64
        Row-major index r * 512 + c of each point, increasing.

    Raises
    ------
    ParameterError
        ``image`` is not 512 x 512 integers in [0, 255], or ``calibration`` is unknown.
    """
    values = _as_uint8_image(image, "the range image")
    if values.shape != ABW_SHAPE:
        raise ParameterError(f"an ABW range image is 512 x 512 pixels, got {values.shape[0]} x {values.shape[1]}")
    if isinstance(calibration, ABWCalibration):
        cal = calibration
    elif calibration == "abw":
        cal = abw_calibration(image_number)
    else:
        raise ParameterError(f"unknown calibration {calibration!r} (use 'abw' or an ABWCalibration)")
    flat = values.ravel()
    pixel = np.flatnonzero(flat).astype(np.int64)
    rows, cols = np.divmod(pixel, ABW_SHAPE[1])
    v = flat[pixel].astype(np.float64)
    depth = v / cal.scale + cal.offset
    focal = abs(cal.focal)
    xyz = np.empty((pixel.size, 3))
    xyz[:, 0] = (cols - 255) * depth / focal
    xyz[:, 1] = (255 - rows) / cal.aspect * depth / focal
    xyz[:, 2] = (255 - v) / cal.scale
    return xyz, pixel


def read_range(
    path: str | os.PathLike[str],
    *,
    calibration: str | ABWCalibration = "abw",
    image_number: int | None = None,
) -> PointCloud:
    """Read an ABW range image (``.range``) as an organised point cloud.

    Parameters
    ----------
    path : str or os.PathLike
        A 512 x 512 8-bit Sun rasterfile of range values.
    calibration : "abw" or ABWCalibration, default "abw"
        As for :func:`range_to_points`.
    image_number : int, optional
        ABW test-image number; by default parsed from a name like ``abw.test.19.range``.

    Returns
    -------
    PointCloud
        The pixels with data (v != 0) as points (see :func:`range_to_points`), ``shape``
        (512, 512), ``index`` their row-major pixel index, field ``range`` (uint8) the raw value;
        the pixels without data count as dropped (``n_dropped``).

    Raises
    ------
    CloudFileError
        Not a readable 8-bit rasterfile, not 512 x 512, or no pixel with data.
    """
    file = os.fspath(path)
    _check_raster_length(file)
    image = read_sunraster(file)
    if image.shape != ABW_SHAPE:
        raise CloudFileError(
            file, f"not an ABW range image: {image.shape[0]} x {image.shape[1]} pixels, ABW images are 512 x 512"
        )
    number = abw_image_number(file) if image_number is None else image_number
    xyz, pixel = range_to_points(image, calibration, number)
    if pixel.size == 0:
        raise CloudFileError(file, "no range data: every pixel is 0 (no data)")
    which = "given" if isinstance(calibration, ABWCalibration) else (
        "alternative" if abw_calibration(number) is ABW_ALTERNATIVE_CALIBRATION else "standard")
    logger.info("%s: ABW range image, %d pixels with data (%d without), %s calibration",
                file, pixel.size, image.size - pixel.size, which)
    return PointCloud(
        xyz=xyz,
        fields={"range": image.ravel()[pixel]},
        shape=ABW_SHAPE,
        index=pixel,
        n_read=image.size,
        n_dropped=image.size - pixel.size,
        path=file,
    )


def _check_raster_length(path: str) -> None:
    """Refuse a Sun rasterfile with a row or more of bytes after the image its header describes:
    a wrong width or height would read the pixels on a wrong grid, and the rest be dropped silently.
    Fewer bytes than a row (a writer's trailing padding) are allowed. Other problems are left to
    the rasterfile reader, which names them."""
    try:
        with open(path, "rb") as fp:
            head = fp.read(32)
        size = os.path.getsize(path)
    except OSError:  # missing, unreadable: read_sunraster says so
        return
    orders = {RAS_MAGIC.to_bytes(4, "big"): ">", RAS_MAGIC.to_bytes(4, "little"): "<"}
    if len(head) < 32 or head[:4] not in orders:
        return
    _, width, height, depth, length, ras_type, _, maplength = struct.unpack(f"{orders[head[:4]]}8I", head)
    if depth != 8 or not 0 < width <= 1 << 20 or not 0 < height <= 1 << 20:
        return
    body = size - 32 - maplength
    row = width + (width & 1)  # rows are padded to 16 bits
    if ras_type in (RT_OLD, RT_STANDARD):
        need = height * row
        if body < need and width % 2 and length == width * height:
            need, row = length, width  # a writer that left the rows of odd width unpadded
    elif ras_type == RT_BYTE_ENCODED and length:
        need = length
    else:
        return
    extra = body - need
    if extra >= row:
        raise CloudFileError(
            path,
            f"Sun rasterfile longer than its header says: {width} x {height} 8-bit pixels take {need:,} bytes, "
            f"and {extra:,} bytes more follow them (room for {extra // row:,} more rows): a wrong width or height?",
        )


# --- segmentations ------------------------------------------------------------------------------


def read_gt_seg(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a SegComp ground-truth segmentation (``.gt-seg``).

    Returns
    -------
    np.ndarray, shape (H, W), uint8
        One label per pixel: 10, 11, ... are regions, 0-3 non-region pixels.

    Raises
    ------
    CloudFileError
        Not a readable 8-bit rasterfile, or a pixel value 4-9 (undefined in SegComp).
    """
    file = os.fspath(path)
    image = read_sunraster(file)
    bad = np.unique(image[(image > NON_REGION_VALUES[-1]) & (image < FIRST_REGION_LABEL)])
    if bad.size:
        raise CloudFileError(
            file, f"not a SegComp segmentation: pixel value {int(bad[0])} (0-3 mark non-region pixels, "
                  "regions are 10 and up, 4-9 are undefined)"
        )
    return image


def _check_ms_labels(labels_image: np.ndarray) -> np.ndarray:
    labels = _as_uint8_image(labels_image, "the labels image")
    present = np.unique(labels)
    bad = present[(present > NON_REGION_VALUES[-1]) & (present < FIRST_REGION_LABEL)]
    if bad.size:
        raise ParameterError(f"label {int(bad[0])} is not allowed: 0-3 mark non-region pixels, regions are 10 and up")
    regions = present[present >= FIRST_REGION_LABEL]
    if regions.size == 0:
        raise ParameterError("the labels image has no region (no label >= 10); compare refuses such an image")
    expected = np.arange(FIRST_REGION_LABEL, FIRST_REGION_LABEL + regions.size)
    if not np.array_equal(regions, expected):
        gap = int(expected[np.flatnonzero(regions != expected)[0]])
        raise ParameterError(f"region labels must run consecutively from 10 (compare requires it); {gap} is missing")
    return labels


def write_ms_seg(path: str | os.PathLike[str], labels_image: np.ndarray) -> None:
    """Write a machine segmentation (``.ms-seg``) as ``compare`` reads it.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create, usually ``<prefix>.ms-seg`` beside ``<prefix>.gt-seg``.
    labels_image : np.ndarray, shape (H, W)
        Regions labelled 10, 11, ... consecutively (at least one); 0-3 for pixels in no region
        (:data:`NO_REGION` = 0 is what :func:`kbs.evaluation.segcomp.segmentation_to_image` writes).

    Raises
    ------
    ParameterError
        A label 4-9 or above 255, region labels not consecutive from 10, or no region.
    CloudFileError
        The file cannot be written.
    """
    write_sunraster(path, _check_ms_labels(labels_image))


def write_ms_nor(path: str | os.PathLike[str], normals_by_region: Mapping[int, np.ndarray]) -> None:
    """Write the normals of a machine segmentation's regions (``.ms-nor``) as ``compare`` reads them.

    The file is text: the number of regions N on the first line, then one line
    ``label nx ny nz`` per region in increasing label order, each normal of unit length and
    turned so that nz >= 0 (``compare`` does the same on reading).

    Parameters
    ----------
    path : str or os.PathLike
        The file to create, usually ``<prefix>.ms-nor``.
    normals_by_region : Mapping[int, array-like of 3 floats]
        The normal of each region label (10 ... 255); any non-zero length.

    Raises
    ------
    ParameterError
        A label outside 10 ... 255, or a normal that is not 3 finite numbers of non-zero length.
    CloudFileError
        The file cannot be written.
    """
    lines = [f"{len(normals_by_region)}"]
    for label in sorted(normals_by_region):
        if isinstance(label, bool) or not isinstance(label, (int, np.integer)) or not (
            FIRST_REGION_LABEL <= label <= 255
        ):
            raise ParameterError(f"a region label must be an integer in [10, 255], got {label!r}")
        normal = np.asarray(normals_by_region[label], dtype=np.float64)
        length = float(np.linalg.norm(normal)) if normal.shape == (3,) else 0.0
        if normal.shape != (3,) or not np.isfinite(normal).all() or length == 0.0:
            raise ParameterError(f"the normal of region {label} must be 3 finite numbers, not all 0; got {normal}")
        normal = normal / length
        if normal[2] < 0:
            normal = -normal
        normal = normal + 0.0  # no '-0.000000000'
        lines.append(f"{int(label)} {normal[0]:.9f} {normal[1]:.9f} {normal[2]:.9f}")
    try:
        Path(path).write_text("\n".join(lines) + "\n", encoding="ascii")
    except OSError as exc:
        raise CloudFileError(os.fspath(path), f"cannot write: {exc.strerror or exc}") from exc


def read_ms_nor(path: str | os.PathLike[str]) -> dict[int, np.ndarray]:
    """Read a normals file written by :func:`write_ms_nor` (or any ``compare`` input of that format).

    Returns
    -------
    dict[int, np.ndarray]
        The normal (3,) float64 of each region label, as stored.

    Raises
    ------
    CloudFileError
        Unreadable, or not "N, then N records label nx ny nz".
    """
    data, file = _read_bytes(path, "normals file")
    words = data.decode("ascii", errors="replace").split()
    try:
        count = int(words[0])
        records = words[1:1 + 4 * count]
        if count < 0 or len(records) != 4 * count:
            raise ValueError(f"{count} regions announced, {len(words[1:]) // 4} records present")
        return {int(records[i]): np.array([float(w) for w in records[i + 1:i + 4]]) for i in range(0, len(records), 4)}
    except (IndexError, ValueError) as exc:
        raise CloudFileError(file, f"not a SegComp normals file: {exc}") from exc
