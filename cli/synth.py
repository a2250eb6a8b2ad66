"""``kbs synth``: generate a labelled synthetic scene (polyhedral range image or outdoor stereo)."""
from __future__ import annotations

import time
from pathlib import Path

import click

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
    return rows, cols


seed_option = click.option("--seed", type=click.IntRange(0, None), default=0, show_default=True,
                           help="Seed of the random generator (same seed and options, same scene).")
out_option = click.option("--out", type=click.Path(dir_okay=False, path_type=Path),
                          help="Write the scene to this PLY file (per-vertex label, object, ground, pixel).")
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
@click.option("--boxes", "n_boxes", type=click.IntRange(0, None), default=3, show_default=True)
@click.option("--wedges", "n_wedges", type=click.IntRange(0, None), default=1, show_default=True)
@resolution_option
@click.option("--noise", type=click.FloatRange(0, None), default=0.002, show_default=True,
              help="Range noise (standard deviation), metres.")
@click.option("--sensor-height", type=click.FloatRange(0, None, min_open=True), default=1.2, show_default=True,
              help="Metres above the ground.")
@click.option("--tilt", "tilt_deg", type=click.FloatRange(0, 90, min_open=True), default=50.0, show_default=True,
              help="Depression of the optical axis, degrees.")
def synth_polyhedral(seed: int, out: Path | None, resolution, **options) -> None:
    """Boxes and wedges on a ground plane, seen by a range sensor; label = planar face id."""
    if resolution is not None:
        options["resolution"] = resolution
    t0 = time.perf_counter()
    scene = polyhedral_scene(seed, **options)
    _finish(scene, out, time.perf_counter() - t0)


@synth.command("outdoor")
@seed_option
@out_option
@click.option("--extent", type=click.FloatRange(5, None), default=25.0, show_default=True,
              help="Farthest range measured, metres.")
@click.option("--rocks", "n_rocks", type=click.IntRange(0, None), default=3, show_default=True)
@click.option("--bin/--no-bin", "with_bin", default=True, show_default=True, help="Put a bin (open box) in the scene.")
@resolution_option
@click.option("--noise", type=click.FloatRange(0, None), default=5e-4, show_default=True,
              help="Range noise coefficient: standard deviation noise * range^2.")
@click.option("--sensor-height", type=click.FloatRange(0, None, min_open=True), default=1.5, show_default=True,
              help="Metres above the ground's mean level.")
def synth_outdoor(seed: int, out: Path | None, resolution, **options) -> None:
    """Uneven ground, rocks and a bin, seen by a stereo-like sensor; label 0 ground, 1.. objects."""
    if resolution is not None:
        options["resolution"] = resolution
    t0 = time.perf_counter()
    scene = outdoor_scene(seed, **options)
    _finish(scene, out, time.perf_counter() - t0)
