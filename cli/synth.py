"""``kbs synth``: generate a labelled synthetic scene (polyhedral range image, outdoor stereo, or an ABW
range image with its SegComp ground truth)."""
from __future__ import annotations

import time
from pathlib import Path

import click

from kbs.cli.common import check_writable_folder
from kbs.cli.types import FiniteFloatRange, PathArg
from kbs.io.result import check_output, listed_by_index

from kbs.synth import Scene, outdoor_scene, polyhedral_scene


def _resolution(ctx, param, value):
    if value is None:
        return None
    try:
        rows, cols = (int(v) for v in value.lower().split("x"))
    except ValueError:
        rows = cols = 0
    if rows <= 0 or cols <= 0:
        raise click.BadParameter(f"expected ROWSxCOLS (two positive integers), got {value!r}")
    if rows * cols > MAX_RAYS:  # 20000x20000 rays took all 24 GiB of a machine before the kernel killed it
        raise click.BadParameter(f"{rows:,} x {cols:,} = {rows * cols:,} rays, more than the {MAX_RAYS:,} a scene "
                                 "may cast (4,000,000 take about 0.7 GB)")
    return rows, cols


#: Rays a synthetic scan may cast (rows x columns; a 128-beam lidar's frame is about 260,000).
MAX_RAYS = 4_000_000
#: Objects a synthetic scene may hold, of each kind.
MAX_OBJECTS = 1000


seed_option = click.option("--seed", type=click.IntRange(0, None), default=0, show_default=True,
                           help="Seed of the random generator (same seed and options, same scene).")
out_option = click.option("--out", type=PathArg(dir_okay=False, path_type=Path),
                          help="Write the scene to this PLY file (per-vertex label, object, ground, pixel; a kbs run "
                               "id in its header).")
force_option = click.option("--force", is_flag=True,
                            help="Replace existing output files that kbs did not write (checked before the scene is "
                                 "made).")


def _check_out(out: Path | None, force: bool, *, ply: bool = True) -> None:
    """Before the work: a PLY file name when ``ply`` (PLY bytes written over a result's .json made
    both unreadable), a file kbs did not write only with ``force``; the folder must accept files."""
    if out is not None:
        if ply and out.suffix.lower() != ".ply":
            raise click.BadParameter(f"{out}: the scene is written as PLY: give a .ply file name", param_hint="--out")
        check_output(out, force=force)
        check_writable_folder(out.parent, create=False, name=out)


resolution_option = click.option("--resolution", callback=_resolution, metavar="ROWSxCOLS",
                                  help="Image size of the simulated sensor.")


def _finish(scene: Scene, out: Path | None, seconds: float) -> None:
    line = f"{scene.summary()}; {seconds:.2f} s"
    if out is not None:
        scene.save(out)
        line += f"; wrote {out}"
    click.echo(line)


@click.group()
def synth() -> None:
    """Generate a labelled synthetic scene (sensor frame: origin at the sensor, z up)."""


@synth.command("polyhedral")
@seed_option
@out_option
@force_option
@click.option("--boxes", "n_boxes", type=click.IntRange(0, MAX_OBJECTS), default=3, show_default=True)
@click.option("--wedges", "n_wedges", type=click.IntRange(0, MAX_OBJECTS), default=1, show_default=True)
@resolution_option
@click.option("--noise", type=FiniteFloatRange(0, 10), default=0.002, show_default=True,
              help="Range noise (standard deviation), metres.")
@click.option("--sensor-height", type=FiniteFloatRange(0, 1000, min_open=True), default=1.2, show_default=True,
              help="Metres above the ground.")
@click.option("--tilt", "tilt_deg", type=FiniteFloatRange(0, 90, min_open=True), default=50.0, show_default=True,
              help="Depression of the optical axis, degrees.")
def synth_polyhedral(seed: int, out: Path | None, resolution, force: bool = False, **options) -> None:
    """Boxes and wedges on a ground plane, seen by a range sensor; label = planar face id."""
    _check_out(out, force)
    if resolution is not None:
        options["resolution"] = resolution
    t0 = time.perf_counter()
    scene = polyhedral_scene(seed, **options)
    _finish(scene, out, time.perf_counter() - t0)


@synth.command("outdoor")
@seed_option
@click.option("--out", type=PathArg(path_type=Path),
              help="Write the scene to this PLY file (per-vertex label, object, ground, pixel); with --frames, the "
              "drive to this folder (scans/NNNNNN.ply, poses.txt, truth.json: each marked as kbs's by a run id, "
              "poses.txt by its digest in truth.json).")
@force_option
@click.option("--frames", "n_frames", type=click.IntRange(1, 10_000), default=None,
              help="Ray-cast a drive of this many frames through one scene instead of one view: the sensor moves "
              "--step metres and turns --yaw-rate degrees between frames; objects stand beside the path.")
@click.option("--step", type=FiniteFloatRange(0, 100, min_open=True), default=1.0, show_default=True,
              help="With --frames: metres between consecutive poses.")
@click.option("--yaw-rate", type=FiniteFloatRange(-45, 45), default=2.0, show_default=True,
              help="With --frames: heading change between consecutive poses, degrees (positive: left).")
@click.option("--street", is_flag=True,
              help="With --frames: line the path as a street (buildings, trees and poles on both sides), which "
              "also gives `kbs map --estimate-poses` surfaces to register on.")
@click.option("--extent", type=FiniteFloatRange(5, 10_000), default=25.0, show_default=True,
              help="Farthest range measured, metres.")
@click.option("--rocks", "n_rocks", type=click.IntRange(0, MAX_OBJECTS), default=None,
              help="Rocks in the scene  [default: 3; 6 with --frames]")
@click.option("--bin/--no-bin", "with_bin", default=True, show_default=True, help="Put a bin (open box) in the scene.")
@resolution_option
@click.option("--noise", type=FiniteFloatRange(0, 10), default=5e-4, show_default=True,
              help="Range noise coefficient: standard deviation noise * range^2.")
@click.option("--sensor-height", type=FiniteFloatRange(0, 1000, min_open=True), default=1.5, show_default=True,
              help="Metres above the ground's mean level.")
def synth_outdoor(seed: int, out: Path | None, resolution, n_frames: int | None, step: float, yaw_rate: float,
                  street: bool, n_rocks: int | None, force: bool = False, **options) -> None:
    """Uneven ground, rocks and a bin, seen by a stereo-like sensor; label 0 ground, 1.. objects.

    With --frames N: a drive of N frames through one such scene (each frame in its sensor frame,
    with the true poses and the true obstacle layout), written to the --out folder for `kbs map`;
    with --street too, along a street lined with buildings, trees and poles."""
    if resolution is not None:
        options["resolution"] = resolution
    t0 = time.perf_counter()
    if n_frames is not None:
        from kbs.synth.drive import drive_files, outdoor_drive, stale_frames

        if out is not None:  # before the work: each file the drive would replace
            if out.exists() and not out.is_dir():
                raise click.BadParameter(f"{out} is a file; give a folder for the drive (--frames)",
                                         param_hint="--out")
            scans, poses, truth = drive_files(out, n_frames)
            for target in (*scans, truth, *stale_frames(out, n_frames)):  # an earlier drive's extra frames go
                check_output(target, force=force)
            check_output(poses, force=force, own=listed_by_index(poses, truth))

        drive = outdoor_drive(seed, n_frames=n_frames, step=step, yaw_rate=yaw_rate, street=street,
                              n_rocks=6 if n_rocks is None else n_rocks, **options)
        line = f"{drive.summary()}; {time.perf_counter() - t0:.2f} s"
        if out is not None:
            drive.save(out, force=force)
            line += f"; wrote {out / 'scans'} ({n_frames} PLY), {out / 'poses.txt'} and {out / 'truth.json'}"
        click.echo(line)
        return
    if street:
        raise click.UsageError("--street is for a drive: give --frames N too")
    if out is not None and out.is_dir():
        raise click.BadParameter(f"{out} is a directory; give a PLY file name (a folder is for --frames)",
                                 param_hint="--out")
    _check_out(out, force)
    options["n_rocks"] = 3 if n_rocks is None else n_rocks
    scene = outdoor_scene(seed, **options)
    _finish(scene, out, time.perf_counter() - t0)


@synth.command("abw")
@seed_option
@click.option("--out", "prefix", type=PathArg(dir_okay=False, path_type=Path), metavar="PREFIX",
              help="Write PREFIX.range (the range image) and PREFIX.gt-seg (its ground truth), as SegComp. These "
                   "8-bit rasterfiles have no room for a kbs run id: existing ones are replaced only with --force.")
@click.option("--force", is_flag=True, help="Replace an existing PREFIX.range / PREFIX.gt-seg (checked before the "
                                            "scene is made).")
@click.option("--boxes", "n_boxes", type=click.IntRange(0, MAX_OBJECTS), default=3, show_default=True)
@click.option("--wedges", "n_wedges", type=click.IntRange(0, MAX_OBJECTS), default=1, show_default=True)
@click.option("--tilt", "tilt_deg", type=FiniteFloatRange(0, 60, max_open=True), default=30.0, show_default=True,
              help="Tilt of the table from fronto-parallel, degrees.")
@click.option("--noise", type=FiniteFloatRange(0, 255), default=0.0, show_default=True,
              help="Range noise (standard deviation) in range levels, before the rounding to 8 bits.")
def synth_abw(seed: int, prefix: Path | None, force: bool = False, **options) -> None:
    """Boxes and wedges on a tilted table seen through the ABW camera: a 512 x 512 8-bit SegComp
    range image (.range) and its ground truth (.gt-seg: 10 the table, 11.. the faces).

    For the planar contest: kbs run --rules abw PREFIX.range, then kbs segcomp and kbs eval."""
    from kbs.synth.abw import abw_scene

    t0 = time.perf_counter()
    if prefix is not None:
        if prefix.suffix.lower() in (".range", ".gt-seg"):
            prefix = prefix.with_suffix("")
        for target in (Path(f"{prefix}.range"), Path(f"{prefix}.gt-seg")):
            _check_out(target, force, ply=False)
    scene = abw_scene(seed, **options)
    line = f"{scene.summary()}; {time.perf_counter() - t0:.2f} s"
    if prefix is not None:
        range_path, gt_path = scene.save(prefix)
        line += f"; wrote {range_path} and {gt_path}"
    click.echo(line)
