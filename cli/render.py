"""``kbs render``: static figures (PNG) of a ``kbs run`` result."""
from __future__ import annotations

import time
from pathlib import Path

import click

from kbs.errors import CloudFileError, require
from kbs.io.atomic import replacing
from kbs.io.result import InputFiles, check_output

KINDS = ("series", "map", "clusters")


def _outputs(result: Path, out: Path | None, kind: str) -> dict[str, Path]:
    """kind -> PNG path. One kind: ``--out`` as given (default ``<stem>-<kind>.png`` next to the
    result). ``all``: three files, ``<out stem>-series.png``, ``-map.png``, ``-clusters.png``
    (default ``<result stem>-...`` next to the result)."""
    kinds = KINDS if kind == "all" else (kind,)
    if out is not None and kind != "all":  # no suffix: a PNG, as matplotlib's savefig names it
        return {kind: out if out.suffix else out.with_name(out.name + ".png")}
    base = (out.with_suffix("") if out is not None else result.with_suffix(""))
    return {k: base.with_name(f"{base.name}-{k}.png") for k in kinds}


@click.command()
@click.argument("result", type=click.Path(path_type=Path, readable=False))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG to write (default: <stem>-<kind>.png next to RESULT). With --kind all, three "
                   "files: <out stem>-series.png, -map.png, -clusters.png.")
@click.option("--kind", type=click.Choice([*KINDS, "all"]), default="all", show_default=True,
              help="series: UFP-ONC partitions for K = 2,4,5,6,8,10 (seed paper's figure 2); map: top-down "
                   "obstacle map; clusters: points, fuzzy centres and covariance boxes.")
@click.option("--max-points", type=click.IntRange(100, None), default=30000, show_default=True,
              help="Points drawn (and clustered for the series), a deterministic stride sample.")
@click.option("--dpi", type=click.IntRange(30, 600), default=100, show_default=True)
@click.option("--ground-label", default="ground", show_default=True, metavar="NAME",
              help="The map's ground: cells whose points all have this label (from RESULT's label_names).")
def render(result: Path, out: Path | None, kind: str, max_points: int, dpi: int, ground_label: str) -> None:
    """Draw figures of a `kbs run` RESULT.json (its points are read from the sibling RESULT.ply;
    the two must be the same run's)."""
    matplotlib = require("matplotlib", "render", "kbs render")
    matplotlib.use("Agg")  # headless whatever MPLBACKEND says
    from kbs.report import figures

    t0 = time.perf_counter()
    outputs = _outputs(result, out, kind)
    sources = InputFiles((result, result.with_suffix(".ply")))
    for path in outputs.values():  # a figure never replaces the result it is drawn from
        check_output(path, inputs=sources, force=True)
    res = figures.load_result(result)
    if "map" in outputs and ground_label not in res.label_names:
        raise click.BadParameter(f"no label {ground_label!r} in this result (labels: {', '.join(res.label_names) or 'none'}): "
                                 "the map draws that label against the others", param_hint="--ground-label")
    stem = result.stem
    view = _view(res, outputs)
    for k, path in outputs.items():
        t = time.perf_counter()
        if k == "series":
            fig = figures.series_figure(res.X, max_points=max_points, title=f"{stem}: UFP-ONC partitions, top view",
                                        view=view)
        elif k == "map":
            fig = figures.obstacle_map_figure(res.X, res.label, res.label_names, sensor=res.sensor,
                                              ground_label=ground_label, title=f"{stem}: obstacle map", view=view)
        else:
            fig = figures.clusters_figure(res.X, res.cluster, res.doc["clusters"], membership=res.membership,
                                          max_points=max_points, title=f"{stem}: output clusters", view=view)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with replacing(path) as (tmp,):  # whole or not at all; the temporary name keeps the suffix
                fig.savefig(tmp, dpi=dpi, format=path.suffix[1:].lower() or "png")
        except OSError as exc:
            raise CloudFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc
        click.echo(f"wrote {path} ({time.perf_counter() - t:.2f} s)")
    click.echo(f"time: {time.perf_counter() - t0:.2f} s", err=True)


def _view(res, outputs: dict[str, Path]):
    """Which way is up (the ground normal the run recorded, else z), said on stderr when it is not
    the scan's z: a camera's frame is drawn upright, its map on the plane perpendicular to up."""
    from kbs.report.view import view_of

    view = view_of(res.doc)
    if not (view.level and view.up[2] > 0):
        what = [f"{k}: up vertical, seen from behind the camera" if k == "clusters" and view.camera_frame else
                f"{k}: up vertical" if k == "clusters" else f"{k}: the plane perpendicular to up" for k in outputs]
        click.echo(f"view: {view.describe()}; {', '.join(what)}", err=True)
    return view
