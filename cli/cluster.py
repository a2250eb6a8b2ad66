"""``kbs cluster``: run the inference motor alone and print the per-K table."""
from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from kbs.cli.types import PathArg
from kbs.cli.common import (
    ProgressLines,
    check_writable_folder,
    cloud_argument,
    force_option,
    progress_bar,
    setting_option,
    write_result_ply,
)
from kbs.inference import ufp_onc
from kbs.io import read_cloud
from kbs.io.result import check_output


def format_k_table(result) -> str:
    """The per-K table (K, FHV, PD, APD, iterations, seconds) with the chosen K marked '*'."""
    rows = [f"{'K':>4} {'FHV':>12} {'PD':>12} {'APD':>12} {'iter':>9} {'seconds':>8}"]
    for p in result.partitions:
        mark = "*" if p.k == result.chosen_k else " "
        rows.append(
            f"{p.k:>3}{mark} {p.fhv:>12.5g} {p.pd:>12.5g} {p.apd:>12.5g} "
            f"{f'{p.n_iter_fcm}+{p.n_iter_gg}':>9} {p.seconds:>8.3f}"
        )
    return "\n".join(rows)


@click.command()
@cloud_argument
@setting_option("--k-max", "k_max")
@setting_option("--m", "m")
@setting_option("--stop", "stop")
@setting_option("--max-fit-points", "max_fit_points")
@click.option("--out", type=PathArg(dir_okay=False, path_type=Path),
              help="Write the cloud with per-vertex 'cluster' and 'membership' to this PLY file (never over "
                   "CLOUD; over a file kbs did not write only with --force).")
@force_option
@click.pass_context
def cluster(ctx: click.Context, cloud: Path, k_max: int, m: float, stop: str, max_fit_points: int,
            out: Path | None, force: bool = False) -> None:
    """Run UFP-ONC on CLOUD and print the per-K table; the K chosen (APD's first local maximum)
    is marked '*'."""
    quiet = ctx.obj.get("quiet", False)
    t0 = time.perf_counter()
    if out is not None:  # before any work
        if out.suffix.lower() != ".ply":  # PLY bytes written over a result's .json made it unreadable
            raise click.BadParameter(f"{out}: the clusters are written as PLY: give a .ply file name", param_hint="--out")
        check_output(out, inputs=(cloud,), force=force)
        check_writable_folder(out.parent, create=False, name=out)
    pc = read_cloud(cloud)
    t_read = time.perf_counter() - t0
    lines = ProgressLines(str(cloud), lambda k: f"K = {k} of {k_max}", quiet=quiet, start=t0)

    def step(part) -> None:
        bar.update(1)
        lines()

    with progress_bar(k_max, "UFP-ONC K", quiet) as bar:
        result = ufp_onc(pc.xyz, k_max, m=m, stop=stop, max_fit_points=max_fit_points, progress=step)
    click.echo(f"{cloud}: {len(pc):,} points"
               + (f", fitted on {result.n_fit:,} voxels of {result.voxel_size:.3g}" if result.voxel_size else ""))
    click.echo(format_k_table(result))
    click.echo(f"chosen K = {result.chosen_k} (first local maximum of APD); "
               f"read {t_read:.2f} s, clustering {result.seconds:.2f} s")
    if not quiet:
        for note in result.notes:
            click.echo(f"note: {note}", err=True)
    if out is not None:
        labels = result.memberships.argmax(axis=1)
        write_result_ply(out, pc, {
            "cluster": labels.astype(np.int32),
            "membership": result.memberships[np.arange(len(labels)), labels].astype(np.float32),
        })
        click.echo(f"wrote {out}")
