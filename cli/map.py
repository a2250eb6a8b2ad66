"""``kbs map``: segment every frame of a drive with one rule base and fuse them into an obstacle map."""
from __future__ import annotations

import time
from pathlib import Path

import click

from kbs.cli.types import FiniteFloatRange, PathArg
import numpy as np

from kbs.cli.common import check_writable_folder, force_option
from kbs.cli.run import _check_scheduler, _jobs, _vector3, plugin_option
from kbs.knowledge import Segmenter
from kbs.knowledge.rulebase import shipped_rule_bases


def _crs(ctx, param, value):
    if value is None:
        return None
    from kbs.errors import ParameterError
    from kbs.maps.files import check_crs

    try:
        check_crs(value)  # before any frame is segmented
    except ParameterError as exc:
        raise click.BadParameter(str(exc)) from exc
    return value


@click.command("map")
@click.option("--rules", "rules", required=True, metavar="NAME|FILE",
              help=f"A shipped rule base ({', '.join(shipped_rule_bases())}) or a rule file; its label 'ground' is "
              "the navigable ground, every other label an obstacle.")
@click.argument("scans", nargs=-1, required=True, type=PathArg(path_type=Path), metavar="SCANS...")
@click.option("--poses", type=PathArg(path_type=Path), metavar="FILE",
              help="One pose per frame (sensor to world): KITTI poses.txt (12 numbers a line; a calib.txt beside it "
              "turns camera poses into LiDAR poses), .json (a list of 4x4) or .csv (16 numbers a row). Default: a "
              "KITTI folder's poses.txt, else identity (scans already in one world frame).")
@click.option("--topic", metavar="TOPIC", help="For a ROS 1/2 bag: the sensor_msgs/PointCloud2 topic (default: the "
              "bag's only one).")
@click.option("--estimate-poses", is_flag=True,
              help="Estimate the poses from the scans with KISS-ICP (the map extra) instead of reading them, frame "
              "by frame on the points the segmentation did not call ground; the motion and residual of each frame "
              "against the previous one are printed and kept in map.json.")
@click.option("--calib", type=PathArg(path_type=Path), metavar="FILE",
              help="The KITTI calib.txt of a KITTI poses file (default: the one beside it, if any).")
@click.option("--out", "out_dir", type=PathArg(file_okay=False, path_type=Path), default=Path("kbs-map"),
              show_default=True, help="Directory for map.tif, map.npy, map.png, cloud.ply, objects/ and map.json "
              "(checked before any frame is segmented: a file there kbs did not write is replaced only with --force).")
@force_option
@click.option("--cell-size", type=FiniteFloatRange(0, None, min_open=True), default=0.2, show_default=True,
              help="Side of a grid cell, metres.")
@click.option("--voxel-size", type=FiniteFloatRange(0, None, min_open=True), default=0.1, show_default=True,
              help="Voxel side of the fused cloud and of the objects' points, metres.")
@click.option("--max-gap", type=click.IntRange(1, None), default=1, show_default=True,
              help="Obstacle clusters of frames up to this many frames apart that overlap are one object.")
@click.option("--report", is_flag=True,
              help="Also write DIR/map.html: the map view (grid, trajectory, objects with their ids; a click on an "
              "object lists the frames that saw it and explains its cluster in each). Needs plotly (the report extra).")
@click.option("--crs", metavar="CRS", callback=_crs, help="The CRS the poses are in (e.g. EPSG:32632), for the GeoTIFF. Default: "
              "the drive's local frame, written as a local engineering CRS.")
@click.option("--sensor", callback=_vector3, metavar="X,Y,Z", help="Sensor position in each frame (overrides the "
              "rule base's).")
@plugin_option
@click.option("--scheduler", "scheduler", metavar="ADDRESS|local",
              help="Segment the frames as Dask tasks: on the scheduler at ADDRESS (tcp://host:8786; its workers "
              "need the rule file, the plugins and kbs at the same paths), or on a LocalCluster of -j workers "
              "('local'; -1: one per core); the frames are fused here, in order, as they arrive. Needs pip install "
              "'kbs[dask]'. The map is the same as without it.")
@click.option("-j", "--jobs", type=click.IntRange(min=-1), default=-1, show_default=True, callback=_jobs,
              help="Processes computing the UFP-ONC splits (with --scheduler local: the Dask workers); -1: one per "
              "available core.")
@click.pass_context
def map_(ctx: click.Context, rules: str, scans: tuple[Path, ...], poses: Path | None, topic: str | None,
         estimate_poses: bool,
         calib: Path | None,
         out_dir: Path, cell_size: float, voxel_size: float, max_gap: int, report: bool, crs: str | None, sensor,
         plugins: tuple[Path, ...], scheduler: str | None, jobs: int, force: bool = False) -> None:
    """Segment every frame of a drive (SCANS: scan files and folders of scans in name order, without
    the files that are not scans: poses.txt and other poses files, calib.txt, labels; one
    KITTI sequence folder holding velodyne/*.bin and poses.txt, or one ROS 1/2 bag) with one rule base, bring each into
    the world frame with its pose and fuse them into DIR/: an obstacle grid in log-odds (map.tif,
    map.npy, map.png), the obstacles tracked across frames with a mesh each (objects/), a fused
    labelled cloud (cloud.ply) and an index of frames, objects and cells (map.json); with --report,
    the map view (map.html)."""
    from kbs.maps import map_drive, read_drive
    from kbs.maps.files import check_map_outputs, write_map

    quiet = ctx.obj.get("quiet", False)
    t0 = time.perf_counter()
    if estimate_poses and poses is not None:
        raise click.UsageError("--estimate-poses and --poses: give one of them")
    if scheduler is not None:
        _check_scheduler(scheduler)
    if report:  # known before any frame is segmented
        from kbs.errors import require

        require("plotly", "report", "--report (the HTML map view)")
    from kbs.maps.bags import TopicError

    try:
        drive = read_drive(scans, poses, calib=calib, topic=topic)
    except TopicError as exc:
        raise click.BadParameter(str(exc), param_hint="--topic") from exc
    inputs = [*scans, *(p for p in (poses, calib, drive.poses.path) if p is not None),
              *(f.path for f in drive.frames if f.path is not None)]
    seen: dict[Path, Path] = {}
    for f in drive.frames:  # a frame given twice (a folder twice, a scan and its folder) is fused twice
        if f.path is not None:
            key = Path(f.path).resolve()
            if key in seen:
                same = "is given twice" if Path(f.path) == seen[key] else f"and {seen[key]} are one file"
                raise click.BadParameter(f"{f.path} {same}: give each frame once", param_hint="SCANS")
            seen[key] = Path(f.path)
    scan_folders = {key.parent for key in seen}  # the folders that hold frames (not a KITTI sequence's root)
    if out_dir.resolve() in scan_folders:  # its cloud.ply would be a frame of the next run over the folder
        raise click.BadParameter(f"{out_dir} is a folder of the drive's scans: write the map elsewhere",
                                 param_hint="--out")
    check_map_outputs(out_dir, inputs=inputs, force=force, report=report)  # before any frame is segmented
    if out_dir.is_dir():  # a folder that does not exist yet is made with the map, not before a frame can fail
        check_writable_folder(out_dir, create=False)
    odometry = None
    if estimate_poses:
        from kbs.maps.odometry import Odometry

        odometry = Odometry()  # before any frame: KISS-ICP missing is known now
        click.echo(f"drive: {drive.source}; poses: estimated with KISS-ICP frame by frame, on the points the "
                   "segmentation did not call ground")
    else:
        click.echo(f"drive: {drive.source}; poses: {drive.poses.source}")
        if drive.poses.note and not quiet:
            click.echo(f"note: {drive.poses.note}", err=True)
    n = len(drive)

    def progress(r) -> None:
        click.echo(f"  frame {r.index + 1}/{n} {r.name}: {r.n_points:,} points, {r.clusters} clusters (ground "
                   f"{r.n_ground:,}, obstacle {r.n_obstacle:,}); segment {r.segment_seconds:.2f} s, fuse "
                   f"{1e3 * r.fuse_seconds:.1f} ms")
        if odometry is not None and r.index > 0:
            step = odometry.matrices[r.index][:3, 3] - odometry.matrices[r.index - 1][:3, 3]
            e = odometry.residuals[r.index - 1]
            click.echo(f"    moved {np.linalg.norm(step):.2f} m ({', '.join(f'{v:+.2f}' for v in step)}); residual "
                       f"median {e.median:.3f} m, overlap {e.overlap:.0%} (no motion: {e.median_identity:.3f} m, "
                       f"{e.overlap_identity:.0%})")

    from kbs.tiles.run import SchedulerError

    # with a scheduler the workers segment, each with its own loaded rule base: this one only reads the rules
    with Segmenter(rules, jobs=1 if scheduler else jobs, sensor=sensor, plugins=plugins) as segmenter:
        try:
            m = map_drive(segmenter, drive, cell_size=cell_size, voxel_size=voxel_size, max_gap=max_gap,
                          explain=report, odometry=odometry, progress=progress, scheduler=scheduler,
                          workers=None if jobs == -1 else jobs)
        except SchedulerError as exc:
            raise click.BadParameter(str(exc), param_hint="--scheduler") from exc
    doc = write_map(m, out_dir, crs=crs, report=report, force=force)
    g = m.grid
    c = g.counts()
    kinds: dict[str, int] = {}
    for o in m.objects:
        kinds[o.mesh_kind] = kinds.get(o.mesh_kind, 0) + 1
    meshes = ", ".join(f"{v} {k}" for k, v in kinds.items()) or "none"
    click.echo(f"map: {g.shape[0]} x {g.shape[1]} cells of {g.cell_size:g} m; obstacle {c['obstacle']:,}, ground "
               f"{c['ground']:,}, unknown {c['unknown']:,}")
    click.echo(f"objects: {len(m.objects)} tracked across frames (meshes: {meshes})")
    seg_s = sorted(r.segment_seconds for r in m.frames)[len(m.frames) // 2]
    click.echo(f"time: {time.perf_counter() - t0:.2f} s; per frame (median) segment {seg_s:.2f} s, fuse "
               f"{m.fuse_ms_per_frame:.1f} ms")
    written = [doc["files"][k] for k in ("geotiff", "npy", "png", "cloud", "report") if k in doc["files"]]
    click.echo(f"wrote {', '.join(str(out_dir / f) for f in written)}, {sum(1 for o in doc['objects'] if o['mesh'])} object meshes in "
               f"{out_dir / 'objects'} and {out_dir / 'map.json'}")
    if not quiet:
        shown = 1 if drive.poses.note and odometry is None else 0  # printed before the frames
        for note in m.notes[shown:] + tuple(doc["notes"][len(m.notes):]):
            click.echo(f"note: {note}", err=True)
