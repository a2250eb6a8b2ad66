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
from kbs.cli.types import PathArg
from kbs.errors import CloudFileError, ParameterError
from kbs.evaluation import (
    SEMANTICKITTI_GROUND,
    SEMANTICKITTI_IGNORED,
    GroundMetrics,
    HooverResult,
    UnknownFieldError,
    adjusted_rand,
    ground_metrics,
    hoover,
    is_semantickitti_label,
    load_ground_truth,
)
from kbs.evaluation.hoover import LABEL_MAX, LABEL_MIN, check_tolerance
from kbs.evaluation.segcomp import DEFAULT_TOLERANCES, segcomp_table
from kbs.io.segcomp import FIRST_REGION_LABEL, NON_REGION_VALUES, read_gt_seg, read_ms_nor, read_range, read_sunraster
from kbs.io.atomic import replacing
from kbs.cli.common import force_option
from kbs.io.result import (
    InputFiles,
    check_output,
    check_pair,
    new_run_id,
    read_result,
    read_result_cloud,
    require_fields,
)


def _int_list(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[int, ...] | None:
    if value is None:
        return None
    if value.strip().lower() in ("", "none"):
        return ()
    try:
        values = tuple(int(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected integers separated by commas (e.g. 9,10,11), got {value!r}") from None
    beyond = next((v for v in values if not LABEL_MIN <= v <= LABEL_MAX), None)
    if beyond is not None:  # no GT label can be it (labels are int64): a typo, not a value to compare
        raise click.BadParameter(f"{beyond} is beyond the range of a label (a 64-bit signed integer, "
                                 f"{LABEL_MIN} .. {LABEL_MAX})")
    return values


def _tolerance(ctx: click.Context, param: click.Parameter, value: float) -> float:
    try:
        return check_tolerance(value)
    except ParameterError:
        raise click.BadParameter(f"must be in (0.5, 1], got {value:g}") from None


def _tolerances(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[float, ...] | None:
    if value is None:
        return None
    try:
        values = tuple(float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected tolerances separated by commas (e.g. 0.51,0.6,0.7,0.8,0.9), "
                                 f"got {value!r}") from None
    bad = [v for v in values if not 0.5 < v <= 1.0]
    if bad:
        raise click.BadParameter(f"each T must be in (0.5, 1], got {bad[0]:g}")
    return values


def _label_names(result: Path) -> tuple[Path, list[str] | None]:
    """The sibling ``<stem>.json`` of a result and its ``label_names`` (None when it is absent);
    a JSON of another run than the PLY's is refused (:func:`kbs.io.result.check_pair`)."""
    js = result.with_suffix(".json")
    if not js.is_file():
        return js, None
    doc = read_result(js, require=("label_names",))
    check_pair(result, js, doc)
    return js, list(doc.label_names or ())


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


def table_rows(results: list[HooverResult]) -> list[dict]:
    """The rows of the paper's Table 1, one per tolerance, as JSON-ready dicts."""
    return [{"tolerance": h.tolerance, "n_gt_regions": h.n_gt_regions, "n_ms_regions": h.n_ms_regions,
             **dict(h.counts), "angle_mean": h.angle_mean, "angle_std": h.angle_std,
             "angle_pairs": len(h.angle_errors)} for h in results]


def format_table(results: list[HooverResult]) -> str:
    """The paper's Table 1 format: one row per tolerance T, correct / over / under / missed / noise
    and the mean (std) angle error over the adjacent pairs of correctly detected GT regions."""
    first = results[0]
    rows = [f"Hoover et al. (1996), Table 1: {first.n_gt_regions} GT regions, {first.n_ms_regions} MS regions",
            f"  {'T':>5} {'correct':>7} {'over':>5} {'under':>6} {'missed':>7} {'noise':>6}  angle error (std), deg"]
    for h in results:
        angle = "-" if h.angle_mean is None else f"{h.angle_mean:.3g} ({h.angle_std:.3g}), {len(h.angle_errors)} pairs"
        rows.append(f"  {h.tolerance:>5.2f} {h.correct:>7} {h.over:>5} {h.under:>6} {h.missed:>7} {h.noise:>6}  {angle}")
    if first.angle_mean is None:
        rows.append(f"  angle error: {first.angle_note}")
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
@click.argument("result", type=PathArg(path_type=Path, readable=False))
@click.argument("ground_truth", metavar="GROUND_TRUTH")
@click.option("--tolerance", type=float, default=0.8, show_default=True, callback=_tolerance,
              help="Hoover tolerance T, in (0.5, 1].")
@click.option("--ground-values", callback=_int_list, metavar="V,V,...",
              help="GT labels that are ground (e.g. 9,10,11,12,17 for SemanticKITTI's learning ids); gives the ground "
                   "metrics. Default for a .label GT: " + ",".join(map(str, SEMANTICKITTI_GROUND)) + ".")
@click.option("--unlabelled-values", callback=_int_list, metavar="V,V,...",
              help="GT labels whose points are ignored (e.g. 0 for SemanticKITTI and mOSD); default: none ("
                   + ",".join(map(str, SEMANTICKITTI_IGNORED)) + " for a .label GT).")
@click.option("--ground-label", default="ground", show_default=True, metavar="NAME",
              help="The result's label that means ground (from its <stem>.json label_names).")
@click.option("--json", "json_out", type=PathArg(dir_okay=False, path_type=Path), metavar="OUT.json",
              help="Also write every number to this JSON file (never over an input; over an existing file kbs "
                   "did not write only with --force; an earlier kbs eval JSON is replaced).")
@click.option("--hoover/--no-hoover", "do_hoover", default=None,
              help="Compute the Hoover region classification (MS regions: the result's clusters). Default: yes, "
                   "except for a ground evaluation (--ground-values, or a .label GT), which prints the ground "
                   "metrics table alone.")
@click.option("--tolerances", callback=_tolerances, metavar="T,T,...",
              help="Also print the paper's Table 1: one row of Hoover counts and angle error per T "
                   "[default for X.ms-seg: 0.51,0.6,0.7,0.8,0.9].")
@click.option("--image", "image_path", type=PathArg(dir_okay=False, path_type=Path), metavar="X.range",
              help="SegComp only: the range image, for the angle error [default: GROUND_TRUTH's X.range beside it].")
@force_option
def eval_(result: Path, ground_truth: str, tolerance: float, ground_values: tuple[int, ...] | None,
          unlabelled_values: tuple[int, ...] | None, ground_label: str, json_out: Path | None,
          do_hoover: bool | None, tolerances: tuple[float, ...] | None, image_path: Path | None,
          force: bool = False) -> None:
    """Compare a `kbs run` RESULT (.ply) with GROUND_TRUTH: a label file (.npy, a SemanticKITTI
    .label, or text with one integer per line) or field:NAME, a field of RESULT (e.g.
    field:label_in, the input's own 'label').

    SemanticKITTI: a .label file (uint32 per point, the raw class id in the low 16 bits) is read
    as the class ids; unless given otherwise, ground is road 40, parking 44, sidewalk 48,
    other-ground 49, lane-marking 60 and terrain 72 (terrain counts, as in the learning-id scans
    9,10,11,12,17 of the benchmarks), and unlabelled 0 and outlier 1 are ignored. Its size must
    be a multiple of 4 bytes, match the KITTI .bin of the same name beside it, and hold one label
    per point of RESULT (exit code 3 otherwise).

    Prints the Hoover et al. (1996) counts of the result's clusters against the GT regions (not
    for a ground evaluation unless --hoover), the ground metrics (with --ground-values; the ground
    label is found in RESULT's sibling <stem>.json) and the adjusted Rand index, on the points
    whose GT label is not unlabelled.

    SegComp (the planar contest): RESULT X.ms-seg (written by `kbs segcomp`) against GROUND_TRUTH
    X.gt-seg, pixel by pixel as SegComp's compare; prints the paper's Table 1 (one row per
    tolerance) and the regions at --tolerance. The angle error needs the range image (--image);
    the MS normals come from X.ms-nor beside X.ms-seg when it exists.
    """
    inputs: list[str | Path] = [result, result.with_suffix(".json"), ground_truth]
    if _is_seg(str(result), ".ms-seg"):  # the normals beside X.ms-seg and the range image are read too
        inputs.append(result.with_name(result.name[:-len(".ms-seg")] + ".ms-nor"))
    if image_path is not None:
        inputs.append(image_path)
    elif _is_seg(ground_truth, ".gt-seg"):
        inputs.append(ground_truth[:-len(".gt-seg")] + ".range")
    _check_json_out(json_out, *inputs, force=force)
    if _is_seg(str(result), ".ms-seg") or _is_seg(ground_truth, ".gt-seg"):
        given = [name for name, value in (("--ground-values", ground_values),
                                          ("--unlabelled-values", unlabelled_values)) if value is not None]
        if do_hoover is False:
            given.append("--no-hoover")
        if given:
            raise click.UsageError(f"{', '.join(given)}: not for a SegComp evaluation (X.ms-seg against X.gt-seg)")
        _eval_segcomp(result, Path(ground_truth), image_path, tolerances or DEFAULT_TOLERANCES, tolerance, json_out)
        return
    if image_path is not None:
        raise click.UsageError("--image is for a SegComp evaluation (RESULT X.ms-seg, GROUND_TRUTH X.gt-seg)")
    kitti = is_semantickitti_label(ground_truth)
    if kitti and ground_values is None:
        ground_values = SEMANTICKITTI_GROUND
    if kitti and unlabelled_values is None:
        unlabelled_values = SEMANTICKITTI_IGNORED
    unlabelled = unlabelled_values or ()
    hoover_said = do_hoover is not None
    if do_hoover is None:  # a ground evaluation asks for the ground table; the regions on request
        do_hoover = ground_values is None
    cloud = read_result_cloud(result, require=("cluster",))
    if ground_values is None:  # the label names are not needed; a JSON beside the points must still be theirs
        _label_names(result)
    try:
        gt = load_ground_truth(ground_truth, cloud)
    except UnknownFieldError as exc:
        raise click.BadParameter(str(exc), param_hint="GROUND_TRUTH") from None
    clusters = cloud.fields["cluster"]
    if len(gt) and not np.count_nonzero(~np.isin(gt, np.asarray(unlabelled, dtype=np.int64))):
        raise CloudFileError(str(ground_truth), f"no point is labelled: all {len(gt):,} labels are unlabelled values "
                                                f"({','.join(map(str, unlabelled))}), nothing to compare")

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
        require_fields(cloud, result, ("label",))
        top = int(np.max(cloud.fields["label"])) if len(cloud) else -1
        if top >= len(names):
            raise CloudFileError(str(result), f"its per-vertex 'label' holds {top}, but {js} names "
                                              f"{len(names)} labels (0 to {len(names) - 1}): not this result's JSON")
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
    elif not hoover_said:
        click.echo("Hoover regions: not computed for a ground evaluation (--hoover computes them)")
    table = None
    if tolerances is not None:
        table = [hoover(clusters, gt, tolerance=t, ms_ignore=(-1,), gt_ignore=unlabelled, points=cloud.xyz)
                 for t in tolerances]
        click.echo(format_table(table))
    if ground is not None:
        click.echo(f"ground: label '{ground_label}' (index {ground_doc['ground_index']}) against GT values "
                   f"{','.join(map(str, ground_values))}")
        click.echo(format_ground(ground))
    else:
        click.echo("ground: not computed (give --ground-values)")
    click.echo(f"adjusted Rand index: {ari:.4f} (clusters vs GT labels, on the labelled points)")

    if json_out is not None:
        doc = {"kbs_version": __version__, "run_id": new_run_id(), "result": str(result), "ground_truth": ground_truth,
               "n_points": len(cloud), "n_labelled": n_labelled, "unlabelled_values": list(unlabelled),
               "hoover": None if h is None else h.to_dict(), "ground": ground_doc,
               "adjusted_rand": _nan_none(ari)}
        if table is not None:
            doc["table"] = table_rows(table)
        _write_json(json_out, doc)


def _write_json(json_out: Path, doc: dict) -> None:
    """Write ``doc`` to ``json_out``, whole or not at all (a full disk leaves the previous file), and
    say so."""
    text = json.dumps(doc, indent=1)
    try:
        with replacing(json_out) as (tmp,):
            with open(tmp, "w", encoding="utf-8") as stream:
                stream.write(text)
    except OSError as exc:
        raise CloudFileError(str(json_out), f"cannot write: {exc.strerror or exc}") from exc
    click.echo(f"wrote {json_out}")


def _check_json_out(json_out: Path | None, *inputs: str | Path, force: bool) -> None:
    """Before the work: --json is never one of the inputs (the result's own JSON included), nor an
    existing file kbs did not write unless ``force`` (the JSON eval writes carries ``kbs_version``
    and a ``run_id``: an earlier one is replaced)."""
    if json_out is not None:
        files = [p for p in inputs if not str(p).startswith("field:")]
        check_output(json_out, inputs=InputFiles(files), force=force, option="--json")


def _is_seg(name: str, suffix: str) -> bool:
    return name.lower().endswith(suffix)


def _eval_segcomp(ms_path: Path, gt_path: Path, image_path: Path | None, tolerances: tuple[float, ...],
                  tolerance: float, json_out: Path | None) -> None:
    """``kbs eval X.ms-seg X.gt-seg``: the paper's Table 1 and the regions at ``tolerance``."""
    if not _is_seg(str(ms_path), ".ms-seg") or not _is_seg(str(gt_path), ".gt-seg"):
        raise click.UsageError(
            f"a SegComp evaluation scores X.ms-seg against X.gt-seg, got {ms_path.name} and {gt_path.name} "
            "(write the .ms-seg of a `kbs run` result with `kbs segcomp RESULT.ply --image X.range`)")
    ms = read_sunraster(ms_path)
    bad = np.unique(ms[(ms > NON_REGION_VALUES[-1]) & (ms < FIRST_REGION_LABEL)])
    if bad.size:
        raise CloudFileError(str(ms_path), f"not a SegComp segmentation: pixel value {int(bad[0])} "
                                           "(0-3 mark non-region pixels, regions are 10 and up, 4-9 are undefined)")
    gt = read_gt_seg(gt_path)
    if ms.shape != gt.shape:
        raise CloudFileError(str(ms_path), f"{ms.shape[0]} x {ms.shape[1]} pixels, but {gt_path} has "
                                           f"{gt.shape[0]} x {gt.shape[1]}: not a segmentation of the same image")
    explicit_image = image_path is not None
    if image_path is None:
        image_path = gt_path.with_name(gt_path.name[:-len(".gt-seg")] + ".range")
    xyz = pixel = None
    if explicit_image or image_path.is_file():
        cloud = read_range(image_path)
        if cloud.shape != ms.shape:
            raise CloudFileError(str(image_path), f"{cloud.shape[0]} x {cloud.shape[1]} pixels, but {ms_path} has "
                                                  f"{ms.shape[0]} x {ms.shape[1]}: not the image that was segmented")
        xyz, pixel = cloud.xyz, cloud.index
    nor_path = ms_path.with_name(ms_path.name[:-len(".ms-seg")] + ".ms-nor")
    ms_normals = read_ms_nor(nor_path) if nor_path.is_file() else None
    rows = segcomp_table(ms, gt, tolerances, xyz=xyz, pixel=pixel, ms_normals=ms_normals)
    detail = next((h for h in rows if h.tolerance == tolerance), None)
    if detail is None:
        detail = segcomp_table(ms, gt, (tolerance,), xyz=xyz, pixel=pixel, ms_normals=ms_normals)[0]

    if xyz is None:
        normals = f"angle error not computed: no range image (give --image X.range; {image_path} does not exist)"
    else:
        normals = (f"normals: GT from the points of {image_path}, MS from "
                   + (str(nor_path) if ms_normals is not None else "the same points"))
    click.echo(f"{ms_path} against {gt_path}: {ms.shape[0]} x {ms.shape[1]} pixels, SegComp regions (labels >= 10; "
               "0-3 non-region), sizes over the whole image, GT adjacency: 4-neighbour pixels")
    click.echo(normals)
    click.echo(format_table(rows))
    click.echo(format_hoover(detail))
    if json_out is not None:
        doc = {"kbs_version": __version__, "run_id": new_run_id(), "result": str(ms_path), "ground_truth": str(gt_path),
               "segcomp": {"image": None if xyz is None else str(image_path),
                           "ms_normals": str(nor_path) if ms_normals is not None else None,
                           "n_pixels": int(ms.size)},
               "table": table_rows(rows), "hoover": detail.to_dict()}
        _write_json(json_out, doc)
