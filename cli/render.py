"""``kbs render``: static figures (PNG) of a ``kbs run`` result."""
from __future__ import annotations

import time
from pathlib import Path

import click

from kbs.cli.types import PathArg
from kbs.cli.common import force_option
from kbs.errors import CloudFileError, require
from kbs.io.atomic import replacing
from kbs.io.result import InputFiles, check_output, distinct_outputs, new_run_id, png_metadata

KINDS = ("series", "map", "clusters", "cah")
#: What ``--kind all`` draws (``cah`` too when ``--cluster`` is given).
ALL = ("series", "map", "clusters")


def _outputs(result: Path, out: Path | None, kind: str, cluster: str | None = None) -> dict[str, Path]:
    """kind -> PNG path. One kind: ``--out`` as given (default ``<stem>-<kind>.png`` next to the
    result, ``<stem>-cah-<ID>.png`` for the CAh view). ``all``: three files, ``<out stem>-series.png``,
    ``-map.png``, ``-clusters.png`` (default ``<result stem>-...`` next to the result), and
    ``-cah-<ID>.png`` with ``--cluster``."""
    kinds = ALL if kind == "all" else (kind,)
    if out is not None and kind != "all":  # no suffix: a PNG, as matplotlib's savefig names it
        return {kind: out if out.suffix else out.with_name(out.name + ".png")}
    if kind == "all" and cluster is not None:
        kinds = (*kinds, "cah")
    base = (out.with_suffix("") if out is not None else result.with_suffix(""))
    return {k: base.with_name(f"{base.name}-{k}{'-' + str(cluster) if k == 'cah' else ''}.png") for k in kinds}


@click.command()
@click.argument("result", type=PathArg(path_type=Path, readable=False))
@click.option("--out", type=PathArg(dir_okay=False, path_type=Path), default=None,
              help="PNG to write (default: <stem>-<kind>.png next to RESULT; the only format: .png, or no suffix). "
                   "With --kind all, three files: <out stem>-series.png, -map.png, -clusters.png. Never over the "
                   "result; over an existing file kbs did not write only with --force (kbs marks its PNGs with a "
                   "run id, and replaces them).")
@click.option("--kind", type=click.Choice([*KINDS, "all"]), default="all", show_default=True,
              help="series: the K-partitions with each cluster's eigen-box (seed paper's figure 2): those the "
                   "global strategy judged, or for the divisive strategy UFP-ONC's sweep re-run for K = 2,4,5,6,8,10; "
                   "map: top-down obstacle map; clusters: points, fuzzy centres and covariance boxes; cah: one "
                   "cluster's projection on the ground plane, its alpha-shape and alpha-opening (figures 5-7; "
                   "needs --cluster).")
@click.option("--cluster", "cluster_id", metavar="ID", default=None,
              help="The cluster of --kind cah: a record of the explanation (e.g. c1.0, as kbs explain names them; "
                   "a cluster that was split shows all its points) or an output cluster's number.")
@click.option("--max-points", type=click.IntRange(100, None), default=30000, show_default=True,
              help="Points drawn (and clustered for the series), a deterministic stride sample.")
@click.option("--dpi", type=click.IntRange(30, 600), default=100, show_default=True)
@click.option("--ground-label", default="ground", show_default=True, metavar="NAME",
              help="The map's ground: cells whose points all have this label (from RESULT's label_names).")
@force_option
def render(result: Path, out: Path | None, kind: str, cluster_id: str | None, max_points: int, dpi: int,
           ground_label: str, force: bool = False) -> None:
    """Draw figures of a `kbs run` RESULT.json (its points are read from the sibling RESULT.ply;
    the two must be the same run's)."""
    if kind == "cah" and cluster_id is None:
        raise click.UsageError("--kind cah draws one cluster: give it with --cluster ID (kbs explain RESULT lists them)")
    outputs = _outputs(result, out, kind, cluster_id)
    for path in outputs.values():  # before any work: matplotlib would refuse it after the drawing
        if path.suffix.lower() != ".png":
            raise click.BadParameter(f"{path}: kbs render writes PNG figures: give a name ending with .png (or no "
                                     f"suffix), not {path.suffix!r}", param_hint="--out")
    matplotlib = require("matplotlib", "render", "kbs render")
    matplotlib.use("Agg")  # headless whatever MPLBACKEND says
    from kbs.report import figures

    t0 = time.perf_counter()
    sources = InputFiles((result, result.with_suffix(".ply"), result.with_suffix(".las"), result.with_suffix(".laz")))
    distinct_outputs(*((f"the {k} figure", p) for k, p in outputs.items()))
    for path in outputs.values():  # a figure never replaces the result it is drawn from, nor another program's file
        check_output(path, inputs=sources, force=force)
    run_id = new_run_id()
    res = figures.load_result(result)
    if "map" in outputs and ground_label not in res.label_names:
        raise click.BadParameter(f"no label {ground_label!r} in this result (labels: {', '.join(res.label_names) or 'none'}): "
                                 "the map draws that label against the others", param_hint="--ground-label")
    stem = result.stem
    view = _view(res, outputs)
    cah = _cah_points(res, cluster_id, result) if "cah" in outputs and cluster_id is not None else None
    for k, path in outputs.items():
        t = time.perf_counter()
        if k == "series":
            fig = _series(res, stem, max_points, view)
        elif k == "cah":
            assert cah is not None
            sel, normal, center, plane, what = cah
            fig = figures.cah_figure(res.X[sel], normal, center, plane=plane, max_points=max_points,
                                     title=f"{stem}: {what}, CAh view")
        elif k == "map":
            fig = figures.obstacle_map_figure(res.X, res.label, res.label_names, sensor=res.sensor,
                                              ground_label=ground_label, title=f"{stem}: obstacle map", view=view)
        else:
            fig = figures.clusters_figure(res.X, res.cluster, res.clusters, membership=res.membership,
                                          max_points=max_points, title=f"{stem}: output clusters", view=view)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with replacing(path) as (tmp,):  # whole or not at all; the temporary name keeps the suffix
                fig.savefig(tmp, dpi=dpi, format="png", metadata=png_metadata(run_id))  # the run id marks it as kbs's
        except OSError as exc:
            raise CloudFileError(str(path), f"cannot write: {exc.strerror or exc}") from exc
        click.echo(f"wrote {path} ({time.perf_counter() - t:.2f} s)")
    click.echo(f"time: {time.perf_counter() - t0:.2f} s", err=True)


def _view(res, outputs: dict[str, Path]):
    """Which way is up (the ground normal the run recorded, else z), said on stderr when it is not
    the scan's z: a camera's frame is drawn upright, its map on the plane perpendicular to up."""
    from kbs.report.view import view_of

    view = view_of(res.explanation.ground if res.explanation is not None else None)
    if not (view.level and view.up[2] > 0):
        what = [f"{k}: up vertical, seen from behind the camera" if k == "clusters" and view.camera_frame else
                f"{k}: up vertical" if k == "clusters" else f"{k}: the plane perpendicular to up" for k in outputs]
        click.echo(f"view: {view.describe()}; {', '.join(what)}", err=True)
    return view


def _series(res, stem: str, max_points: int, view):
    """The K-partition series: the global strategy's visited partitions from the explanation, or
    (divisive) UFP-ONC re-run on the points; drawn on the plane perpendicular to ``view``'s up
    (points, centres and eigen-axes turned so that up is the third axis when it is not z)."""
    import dataclasses

    from kbs.report import figures

    turn = None if (view.level and view.up[2] > 0) else view.rotation
    X = res.X if turn is None else res.X @ turn.T
    sweep = res.explanation.sweep if res.explanation is not None else []
    if sweep:
        panels = figures.panels_from_sweep(sweep)
        if turn is not None:
            panels = [dataclasses.replace(p, centers=p.centers @ turn.T, eigenvectors=turn @ p.eigenvectors)
                      for p in panels]
        shown = "" if len(panels) == len(sweep) else f" ({len(panels)} of {len(sweep)} shown)"
        note = ("points coloured by the most likely cluster of each K (its centre and covariance); red dashed "
                "boxes: clusters a rule wanted split")
        return figures.partition_series_figure(X, panels, max_points=max_points, note=note,
                                               title=f"{stem}: the global strategy's K-partitions{shown}, top view")
    Xd = X[figures.decimate(len(X), max_points)]
    panels, ufp = figures.panels_from_ufp_onc(Xd)
    note = "" if panels and panels[-1].k == max(figures.SERIES_K) else \
        f"the sweep stopped at K = {ufp.partitions[-1].k} ({ufp.stop_reason})"
    return figures.partition_series_figure(Xd, panels, max_points=max_points, note=note,
                                           title=f"{stem}: UFP-ONC's initial sweep re-run on {len(Xd):,} points, "
                                                 "with eigen-boxes, top view")


def _cah_points(res, cluster_id: str, result: Path):
    """(point indices, normal, centre, plane name, what) of ``--cluster``: a record of the
    explanation (the points of the output clusters of the leaves below it) or an output cluster's
    number; the plane is the run's ground plane when it has one, else the cluster's best
    approximating plane."""
    import numpy as np

    from kbs.geometry.pca import principal_axes
    from kbs.knowledge.predicates import did_you_mean

    records = res.explanation.records if res.explanation is not None else {}
    n_out = len(res.clusters)
    if cluster_id in records:
        below, stack = [], [cluster_id]
        while stack:
            r = records[stack.pop()]
            stack.extend(r.children)
            if not r.children and r.output_index is not None:
                below.append(int(r.output_index))
        what = f"cluster {cluster_id}"
        if not below:
            raise click.BadParameter(f"cluster {cluster_id!r} of {result} has no points in an output cluster "
                                     f"(action {records[cluster_id].action}: rejected as noise)",
                                     param_hint="--cluster")
    elif cluster_id.isdigit() and int(cluster_id) < n_out:
        below, what = [int(cluster_id)], f"output cluster {cluster_id}"
    else:
        hint = did_you_mean(cluster_id, list(records))
        raise click.BadParameter(f"no cluster {cluster_id!r} in {result} (a record id such as c0.1, or an output "
                                 f"cluster 0 .. {n_out - 1})" + (f"; did you mean {hint!r}?" if hint else ""),
                                 param_hint="--cluster")
    sel = np.flatnonzero(np.isin(res.cluster, below))
    if sel.size < 3:
        raise click.BadParameter(f"{what} of {result} has {sel.size} points: too few to project", param_hint="--cluster")
    P = res.X[sel]
    center = P.mean(axis=0)
    normal = res.explanation.ground.normal if res.explanation is not None else None
    if normal is not None:
        return sel, np.asarray(normal, float), center, "the ground plane", what
    return sel, principal_axes(P).normal, center, "its best approximating plane (no ground plane in this run)", what
