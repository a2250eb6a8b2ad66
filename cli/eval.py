"""``kbs eval``: compare a ``kbs run`` result with a ground truth (Hoover counts, ground metrics,
adjusted Rand index)."""
from __future__ import annotations

import difflib
import json
import math
from pathlib import Path

import click
import numpy as np

from kbs import __version__
from kbs.errors import CloudFileError, ParameterError
from kbs.evaluation import (
    GroundMetrics,
    HooverResult,
    UnknownFieldError,
    adjusted_rand,
    ground_metrics,
    hoover,
    load_ground_truth,
)
from kbs.evaluation.hoover import check_tolerance
from kbs.io import read_result_json
from kbs.io.result import check_pair, read_result_cloud


def _int_list(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[int, ...] | None:
    if value is None:
        return None
    if value.strip().lower() in ("", "none"):
        return ()
    try:
        return tuple(int(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected integers separated by commas (e.g. 9,10,11), got {value!r}") from None


def _tolerance(ctx: click.Context, param: click.Parameter, value: float) -> float:
    try:
        return check_tolerance(value)
    except ParameterError:
        raise click.BadParameter(f"must be in (0.5, 1], got {value:g}") from None


def _label_names(result: Path) -> tuple[Path, list[str] | None]:
    """The sibling ``<stem>.json`` of a result and its ``label_names`` (None when it is absent);
    a JSON of another run than the PLY's is refused (:func:`kbs.io.result.check_pair`)."""
    js = result.with_suffix(".json")
    if not js.is_file():
        return js, None
    doc = read_result_json(js, require=("label_names",))
    check_pair(result, js, doc)
    names = doc["label_names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise CloudFileError(str(js), "not a kbs result file ('label_names' is not a list of names)")
    return js, names


def _nan_none(x: float) -> float | None:
    return None if isinstance(x, float) and math.isnan(x) else x


def _region_list(ids: tuple[int, ...], width: int = 16) -> str:
    """Comma-separated region labels, cut to ``width`` characters with the number left out."""
    text = ",".join(str(i) for i in ids)
    if len(text) <= width:
        return text
    shown: list[str] = []
    for k, i in enumerate(ids):
        tail = f",+{len(ids) - k} more" if k else f"+{len(ids)} more"
        if len(",".join(shown + [str(i)])) + len(f",+{len(ids) - k - 1} more") > width:
            return ",".join(shown) + tail
        shown.append(str(i))
    return text  # pragma: no cover - the loop returns


def _unclassified(kind: str, side: str, sizes: dict[int, int], show: int = 12) -> list[str]:
    """One line per missed/noise region, the largest first; beyond ``show``, one summary line."""
    if not sizes:
        return []
    order = sorted(sizes, key=lambda r: (-sizes[r], r))
    rows = []
    for r in order[:show]:
        gt, ms = (str(r), "") if side == "GT" else ("", str(r))
        rows.append(f"  {gt:<16} {kind:<8} {ms:<16} ({sizes[r]:,} points)")
    if len(order) > show:
        rest = order[show:]
        rows.append(f"  ... and {len(rest)} more {kind} {side} regions ({sum(sizes[r] for r in rest):,} points; "
                    f"all in --json)")
    return rows


def format_hoover(h: HooverResult) -> str:
    """The Hoover counts, the angle metric and one line per instance and per unclassified region."""
    rows = [f"Hoover et al. (T = {h.tolerance:g}): {h.n_gt_regions} GT regions, {h.n_ms_regions} MS regions",
            f"  {'correct':>7} {'over':>5} {'under':>6} {'missed':>7} {'noise':>6}",
            f"  {h.correct:>7} {h.over:>5} {h.under:>6} {h.missed:>7} {h.noise:>6}"]
    if h.angle_mean is None:
        rows.append(f"  angle error: not computed ({h.angle_note})")
    else:
        rows.append(f"  angle error: {h.angle_mean:.3g} deg mean, {h.angle_std:.3g} std over "
                    f"{len(h.angle_errors)} adjacent pairs of correctly detected GT regions")
    rows.append(f"  {'GT region(s)':<16} {'category':<8} {'MS region(s)':<16} {'GT ratio':>8} {'MS ratio':>8}")
    for i in h.instances:
        rows.append(f"  {_region_list(i.gt):<16} {i.kind:<8} {_region_list(i.ms):<16} "
                    f"{i.gt_ratio:>8.3f} {i.ms_ratio:>8.3f}")
    rows += _unclassified("missed", "GT", {n: h.gt_sizes[n] for n, c in h.gt_class.items() if c == "missed"})
    rows += _unclassified("noise", "MS", {m: h.ms_sizes[m] for m, c in h.ms_class.items() if c == "noise"})
    return "\n".join(rows)


def format_ground(g: GroundMetrics) -> str:
    """Precision, recall, F1, IoU, ISPRS errors and the confusion counts."""
    names = ("precision", "recall", "F1", "IoU", "total error", "type I", "type II")
    values = (g.precision, g.recall, g.f1, g.iou, g.total_error, g.type_i, g.type_ii)
    rows = ["  " + " ".join(f"{n:>11}" for n in names),
            "  " + " ".join(f"{v:>11.4f}" for v in values),
            f"  TP {g.tp:,}  FP {g.fp:,}  FN {g.fn:,}  TN {g.tn:,}  (ignored {g.n_ignored:,})"]
    if g.undefined:
        rows.append(f"  undefined (zero denominator, reported as 0): {', '.join(g.undefined)}")
    return "\n".join(rows)


@click.command("eval")
@click.argument("result", type=click.Path(path_type=Path, readable=False))
@click.argument("ground_truth", metavar="GROUND_TRUTH")
@click.option("--tolerance", type=float, default=0.8, show_default=True, callback=_tolerance,
              help="Hoover tolerance T, in (0.5, 1].")
@click.option("--ground-values", callback=_int_list, metavar="V,V,...",
              help="GT labels that are ground (e.g. 9,10,11,12,17 for SemanticKITTI); gives the ground metrics.")
@click.option("--unlabelled-values", callback=_int_list, metavar="V,V,...",
              help="GT labels whose points are ignored (e.g. 0 for SemanticKITTI and mOSD); default: none.")
@click.option("--ground-label", default="ground", show_default=True, metavar="NAME",
              help="The result's label that means ground (from its <stem>.json label_names).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), metavar="OUT.json",
              help="Also write every number to this JSON file.")
@click.option("--hoover/--no-hoover", "do_hoover", default=True, show_default=True,
              help="Compute the Hoover region classification (MS regions: the result's clusters).")
def eval_(result: Path, ground_truth: str, tolerance: float, ground_values: tuple[int, ...] | None,
          unlabelled_values: tuple[int, ...] | None, ground_label: str, json_out: Path | None,
          do_hoover: bool) -> None:
    """Compare a `kbs run` RESULT (.ply) with GROUND_TRUTH: a label file (.npy, or text with one
    integer per line) or field:NAME, a field of RESULT (e.g. field:label_in, the input's own
    'label').

    Prints the Hoover et al. (1996) counts of the result's clusters against the GT regions,
    the ground metrics (with --ground-values; the ground label is found in RESULT's sibling
    <stem>.json) and the adjusted Rand index, on the points whose GT label is not unlabelled.
    """
    unlabelled = unlabelled_values or ()
    cloud = read_result_cloud(result)
    if "cluster" not in cloud.fields:
        raise CloudFileError(str(result), "not a kbs result: no per-vertex 'cluster' field (write one with kbs run)")
    try:
        gt = load_ground_truth(ground_truth, cloud)
    except UnknownFieldError as exc:
        raise click.BadParameter(str(exc), param_hint="GROUND_TRUTH") from None
    clusters = cloud.fields["cluster"]

    ground = None
    ground_doc = None
    if ground_values is not None:
        if not ground_values:
            raise click.BadParameter("give at least one GT label", param_hint="--ground-values")
        if set(ground_values) & set(unlabelled):
            raise click.BadParameter(f"labels {sorted(set(ground_values) & set(unlabelled))} are also unlabelled",
                                     param_hint="--ground-values")
        js, names = _label_names(result)
        if names is None:
            raise CloudFileError(str(js), "no such file: the result's label names are needed to find "
                                          f"the label '{ground_label}' (--ground-label)")
        if ground_label not in names:
            close = difflib.get_close_matches(ground_label, names, n=1)
            raise click.BadParameter(f"no label {ground_label!r} in {js} (labels: {', '.join(names) or 'none'})"
                                     + (f"; did you mean {close[0]!r}?" if close else ""), param_hint="--ground-label")
        if "label" not in cloud.fields:
            raise CloudFileError(str(result), "not a kbs result: no per-vertex 'label' field")
        index = names.index(ground_label)
        ground = ground_metrics(np.asarray(cloud.fields["label"]) == index, gt, ground_values=ground_values,
                                unlabelled_values=unlabelled)
        ground_doc = {"ground_label": ground_label, "ground_index": index, "ground_values": list(ground_values),
                      **ground.to_dict()}

    h = hoover(clusters, gt, tolerance=tolerance, ms_ignore=(-1,), gt_ignore=unlabelled,
               points=cloud.xyz) if do_hoover else None
    ari = adjusted_rand(clusters, gt, ignore=unlabelled)
    n_labelled = int(np.count_nonzero(~np.isin(gt, np.asarray(unlabelled, dtype=np.int64))))

    n_noise = int(np.count_nonzero(np.asarray(clusters) < 0))
    n_clusters = len(np.unique(clusters[np.asarray(clusters) >= 0]))
    click.echo(f"{result}: {len(cloud):,} points, {n_clusters} clusters, {n_noise:,} noise points")
    click.echo(f"ground truth {ground_truth}: {n_labelled:,} labelled points"
               + (f", {len(gt) - n_labelled:,} unlabelled ({','.join(map(str, unlabelled))}) ignored"
                  if unlabelled else ""))
    if h is not None:
        click.echo(format_hoover(h))
    if ground is not None:
        click.echo(f"ground: label '{ground_label}' (index {ground_doc['ground_index']}) against GT values "
                   f"{','.join(map(str, ground_values))}")
        click.echo(format_ground(ground))
    else:
        click.echo("ground: not computed (give --ground-values)")
    click.echo(f"adjusted Rand index: {ari:.4f} (clusters vs GT labels, on the labelled points)")

    if json_out is not None:
        doc = {"kbs_version": __version__, "result": str(result), "ground_truth": ground_truth,
               "n_points": len(cloud), "n_labelled": n_labelled, "unlabelled_values": list(unlabelled),
               "hoover": None if h is None else h.to_dict(), "ground": ground_doc,
               "adjusted_rand": _nan_none(ari)}
        try:
            json_out.write_text(json.dumps(doc, indent=1))
        except OSError as exc:
            raise CloudFileError(str(json_out), f"cannot write: {exc.strerror or exc}") from exc
        click.echo(f"wrote {json_out}")
