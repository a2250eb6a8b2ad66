"""``kbs segcomp``: turn a ``kbs run`` result on a range image into the SegComp ``compare`` inputs."""
from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from kbs.cli.types import PathArg
from kbs.cli.common import check_writable_folder
from kbs.errors import CloudFileError
from kbs.evaluation.segcomp import image_region_normals, segmentation_to_image
from kbs.io import PointCloud
from kbs.io.atomic import replacing
from kbs.io.result import InputFiles, check_output, distinct_outputs, read_result_cloud, require_fields
from kbs.io.segcomp import FIRST_REGION_LABEL, read_sunraster, write_ms_nor, write_ms_seg


def _result_arrays(result: Path, cloud: PointCloud) -> tuple[np.ndarray, np.ndarray]:
    """The result's per-point ``cluster`` and ``pixel``, or a one-line error saying what is missing."""
    require_fields(cloud, result, ("cluster",))
    if "pixel" not in cloud.fields:
        raise CloudFileError(
            str(result),
            "no 'pixel' field: the input of `kbs run` was not organised (run it on a range image, e.g. IMAGE.range)",
        )
    cluster, pixel = cloud.fields["cluster"], cloud.fields["pixel"]
    if cluster.dtype.kind not in "iu" or pixel.dtype.kind not in "iu":
        raise CloudFileError(
            str(result), f"'cluster' and 'pixel' must be integers, got {cluster.dtype} and {pixel.dtype}"
        )
    return cluster.astype(np.int64), pixel.astype(np.int64)


def _check_against_image(result: Path, image_path: Path, image: np.ndarray, pixel: np.ndarray) -> None:
    """Every point must sit on a pixel of the image that holds data."""
    rows, cols = image.shape
    outside = (pixel < 0) | (pixel >= image.size)
    if outside.any():
        raise CloudFileError(
            str(result), f"pixel {int(pixel[outside][0])} is outside the {rows} x {cols} grid of {image_path}: "
                         "the result was not computed from this image"
        )
    empty = image.ravel()[pixel] == 0
    if empty.any():
        raise CloudFileError(
            str(result), f"{int(empty.sum())} points sit on pixels where {image_path} has no data: "
                         "the result was not computed from this image"
        )
    if np.unique(pixel).size != pixel.size:
        raise CloudFileError(str(result), "two points share a pixel: not a `kbs run` result on a range image")
    with_data = int(np.count_nonzero(image))
    if pixel.size != with_data:  # kbs run keeps every point of a range image (noise included)
        raise CloudFileError(
            str(result), f"{pixel.size:,} points, but {image_path} has {with_data:,} pixels with data: the result "
                         "was not computed from this image")


def _check_ranges(result: Path, image_path: Path, image: np.ndarray, cloud: PointCloud, pixel: np.ndarray) -> None:
    """A result of a range image keeps each point's 'range' value (kbs.io.segcomp.read_range): it must
    be the image's at the point's pixel (another image of the same size and coverage has other values)."""
    ranges = cloud.fields.get("range")
    if ranges is None:
        return
    differ = np.asarray(ranges).astype(np.int64) != image.ravel()[pixel].astype(np.int64)
    if differ.any():
        raise CloudFileError(
            str(result), f"the 'range' of {int(differ.sum()):,} of its {pixel.size:,} points differs from "
                         f"{image_path}'s at their pixels: the result was not computed from this image")


def _prefix(path: Path, suffix: str) -> Path:
    """``path`` without ``suffix`` (any case) when it ends with it, else without its last suffix."""
    if path.name.lower().endswith(suffix):
        return path.with_name(path.name[:-len(suffix)])
    return path.with_suffix("")


def _check_outputs(result: Path, image_path: Path, out: Path, normals: Path | None, force: bool) -> None:
    """Before the work: the outputs are two files, never an input (RESULT, its <stem>.json, the
    image, the ground truth <prefix>.gt-seg beside the image or beside --out), and an existing one
    only with ``force`` (kbs cannot tell its own .ms-seg / .ms-nor from another program's)."""
    distinct_outputs(("--out", out), ("--normals", normals))
    sources = InputFiles([result, result.with_suffix(".json"), image_path,
                          _prefix(image_path, ".range").with_name(_prefix(image_path, ".range").name + ".gt-seg"),
                          _prefix(out, ".ms-seg").with_name(_prefix(out, ".ms-seg").name + ".gt-seg")])
    for path, what in ((out, "--out"), (normals, "--normals")):
        if path is None:
            continue
        check_output(path, inputs=sources, force=force, option=what)
        check_writable_folder(path.parent, create=False, name=path)


@click.command()
@click.argument("result", type=PathArg(path_type=Path))
@click.option("--image", "image_path", required=True, type=PathArg(path_type=Path), metavar="IMAGE.range",
              help="The range image the result was computed from (gives the grid).")
@click.option("--out", type=PathArg(dir_okay=False, path_type=Path), metavar="X.ms-seg",
              help="Machine-segmentation image to write [default: RESULT with the suffix .ms-seg].")
@click.option("--normals", type=PathArg(dir_okay=False, path_type=Path), metavar="X.ms-nor",
              help="Region normals file to write [default: the --out path with the suffix .ms-nor].")
@click.option("--no-normals", is_flag=True, help="Do not write the normals file (for compare -noNormals).")
@click.option("--force", is_flag=True,
              help="Replace an existing --out / --normals file. The SegComp formats have no room for a kbs run "
                   "id, so kbs cannot tell its own earlier .ms-seg / .ms-nor from another program's: an existing "
                   "one is replaced only with --force. Never an input (RESULT, its .json, the image, a .gt-seg).")
@click.pass_context
def segcomp(ctx: click.Context, result: Path, image_path: Path, out: Path | None, normals: Path | None,
            no_normals: bool, force: bool = False) -> None:
    """Write the SegComp machine segmentation of a `kbs run` RESULT.ply on a range image.

    Cluster k becomes region 10 + k (labels consecutive from 10, at most 246 regions); noise and
    pixels without data are 0. The normals file holds each region's least-squares plane normal.
    Name the outputs <prefix>.ms-seg / <prefix>.ms-nor beside <prefix>.gt-seg for `compare`.
    Existing output files are replaced only with --force (checked before any work).
    """
    quiet = ctx.obj.get("quiet", False)
    if no_normals and normals is not None:
        raise click.UsageError("--normals and --no-normals exclude each other")
    out = out if out is not None else result.with_suffix(".ms-seg")
    normals = None if no_normals else (normals if normals is not None else out.with_suffix(".ms-nor"))
    _check_outputs(result, image_path, out, normals, force)
    cloud = read_result_cloud(result)
    cluster, pixel = _result_arrays(result, cloud)
    image = read_sunraster(image_path)
    _check_against_image(result, image_path, image, pixel)
    _check_ranges(result, image_path, image, cloud, pixel)
    labels = segmentation_to_image(cluster, pixel, image.shape)
    n_regions = int(np.unique(labels[labels >= FIRST_REGION_LABEL]).size)
    if n_regions == 0:
        raise CloudFileError(str(result), "no cluster of at least 3 points: nothing to segment (every point is noise)")
    region_normal = image_region_normals(labels, cloud.xyz, pixel) if normals is not None else None
    targets = (out,) if normals is None else (out, normals)
    with replacing(*targets) as temps:  # both whole, or neither
        for target, temp in zip(targets, temps):
            try:
                if target == out:
                    write_ms_seg(temp, labels)
                else:
                    assert region_normal is not None
                    write_ms_nor(temp, region_normal)
            except CloudFileError as exc:  # named where the user looks, not the temporary file
                raise CloudFileError(str(target), exc.problem) from exc
    n_clusters = np.unique(cluster[cluster >= 0]).size
    labelled = int(np.count_nonzero(labels >= FIRST_REGION_LABEL))
    click.echo(f"{result}: {len(cluster):,} points, {n_clusters} clusters -> {n_regions} regions "
               f"(labels {FIRST_REGION_LABEL}..{FIRST_REGION_LABEL + n_regions - 1}); "
               f"{labelled:,} of the image's {int(np.count_nonzero(image)):,} pixels with data in a region")
    click.echo(f"wrote {out}" + (f" and {normals}" if normals is not None else ""))
    if not quiet and n_regions < n_clusters:
        click.echo(f"note: {n_clusters - n_regions} clusters left out of the regions (see the warnings above)",
                   err=True)
