"""``kbs tune``: fit the thresholds marked ``tune:`` in a rule file to labelled scans (grid search,
k-fold cross-validation over the scans) and write the rule file with the chosen values."""
from __future__ import annotations

import json
import time
from pathlib import Path

import click

from kbs.cli.types import FiniteFloatRange, PathArg
import numpy as np

from kbs import __version__
from kbs.cli.common import ProgressLines, progress_interval
from kbs.cli.eval import _int_list
from kbs.cli.run import _jobs, _registry, _vector3, plugin_option
from kbs.errors import CloudFileError, ParameterError
from kbs.evaluation import (
    SEMANTICKITTI_GROUND,
    SEMANTICKITTI_IGNORED,
    UnknownFieldError,
    is_semantickitti_label,
    load_ground_truth,
)
from kbs.evaluation.tune import METRICS, LabelledScan, format_report, tune, tuned_text
from kbs.io import read_cloud
from kbs.io.atomic import replacing
from kbs.io.result import InputFiles, check_output, distinct_outputs, new_run_id
from kbs.knowledge.rulebase import Problem, RuleFileError, SourcePos, load_rule_base, resolve
from kbs.units import UNITS as LENGTH_UNITS, ScanUnits, scale_factors, unit


@click.command("tune")
@click.option("--rules", "rules", required=True, metavar="NAME|FILE",
              help="The rule file whose thresholds marked 'tune:' are fitted (a shipped name or a file).")
@click.argument("pairs", nargs=-1, required=True, metavar="SCAN GT [SCAN GT]...")
@click.option("--out", "out", required=True, type=PathArg(dir_okay=False, path_type=Path), metavar="NEW.yaml",
              help="The tuned rule file to write (never the rule file itself, nor a scan).")
@click.option("--folds", type=click.IntRange(min=2), default=None,
              help="k of the k-fold cross-validation over scans  [default: min(5, number of scans)]")
@click.option("--metric", type=click.Choice(list(METRICS)), default="f1", show_default=True,
              help="Score of the ground label on the labelled points (total_error is minimised).")
@click.option("--select", type=click.Choice(["mean", "median"]), default="mean", show_default=True,
              help="How a setting's scores on the tuning scans are combined to choose it: their mean (as "
                   "scikit-learn's GridSearchCV), or their median, which one much harder scan does not decide.")
@click.option("--max-evals", type=click.IntRange(min=1), default=None, metavar="N",
              help="Evaluate at most N settings of the grid (the file's own values first, then groups sharing a "
                   "split tree in a shuffled order).")
@click.option("--time-limit", type=FiniteFloatRange(min=0, min_open=True), default=None, metavar="S",
              help="Start no new setting after S seconds (the file's own values are always scored).")
@click.option("--ground-values", callback=_int_list, metavar="V,V,...",
              help="GT labels that are ground, for every GT  [default for a SemanticKITTI .label: "
                   + ",".join(map(str, SEMANTICKITTI_GROUND)) + "]")
@click.option("--unlabelled-values", callback=_int_list, metavar="V,V,...",
              help="GT labels whose points are left out  [default: none; "
                   + ",".join(map(str, SEMANTICKITTI_IGNORED)) + " for a .label]")
@click.option("--ground-label", default="ground", show_default=True, metavar="NAME",
              help="The rule base's label that the GT's ground values mean (e.g. table for a table-top rule base).")
@click.option("--sensor", callback=_vector3, metavar="X,Y,Z",
              help="Sensor position for every scan (overrides the rule base's), in the scans' coordinates.")
@click.option("--units", type=click.Choice(list(LENGTH_UNITS)), default=None,
              help="Unit of the scans' coordinates, for files that do not declare one (as kbs run).")
@click.option("--report", "report", type=PathArg(dir_okay=False, path_type=Path), metavar="FILE.json",
              help="Also write the report as JSON (another file than --out).")
@click.option("-j", "--jobs", type=click.IntRange(min=-1), default=-1, show_default=True, callback=_jobs,
              help="Processes computing the UFP-ONC splits (as kbs run).")
@click.option("--force", is_flag=True,
              help="Replace an existing --out / --report file that kbs did not write (never an input), as kbs run.")
@plugin_option
@click.pass_context
def tune_(ctx: click.Context, rules: str, pairs: tuple[str, ...], out: Path, folds: int | None, metric: str,
          select: str, max_evals: int | None, time_limit: float | None, ground_values, unlabelled_values, ground_label: str,
          sensor, units: str | None, report: Path | None, jobs: int, force: bool, plugins: tuple[Path, ...]) -> None:
    """Fit the thresholds marked 'tune:' in a rule file to labelled scans, SCAN GT pairs (GT as
    in kbs eval: a label file .npy / .label / text, or field:NAME of the scan), and write NEW.yaml.

    A threshold is marked beside its value, on a check (`max: 0.05` then
    `tune: {min: 0.02, max: 0.10, steps: 5}`, or `tune: [0.03, 0.05, 0.08]`) or on a post step
    (ground_contact, ground_release: tolerance; merge_coplanar, ground_model: give `field:`).
    kbs run ignores the marks. Every combination of the marked values (the file's own included)
    is scored on every scan; with k folds of scans, each fold's setting is chosen on the other
    folds' scans and scored on its own; the values written are those chosen on all the scans
    (ties: the nearest to the file's). A threshold that only labels (not used by a split rule
    nor the ground candidate) costs no new segmentation: the split tree is labelled again.

    NEW.yaml is the rule file's text, comments kept, with each moved value replaced in place
    and a comment 'kbs tune: old -> new, cross-validated score'. The report (markdown on stdout;
    --report FILE.json too): the score per fold on the held-back scans beside the file's own
    values, the score per scan, the thresholds that moved. Progress lines on stderr as kbs run.
    """
    quiet = ctx.obj.get("quiet", False) if ctx.obj else False
    t0 = time.perf_counter()
    if not quiet:
        progress_interval()
    if len(pairs) % 2:
        raise click.UsageError(f"scan {pairs[-1]} has no ground truth: give SCAN GT pairs "
                               f"({len(pairs)} arguments given)")
    registry = _registry(plugins)
    rb = load_rule_base(rules, registry)
    if not rb.tunables:
        raise RuleFileError([Problem(SourcePos(rb.path, 1, 1), "no threshold is marked 'tune:' for kbs tune to fit "
                                     "(e.g. under a check's 'max: 0.05': 'tune: {min: 0.02, max: 0.10, steps: 5}')")])
    if ground_label not in rb.label_names:
        raise click.BadParameter(f"rule base '{rb.name}' has no label {ground_label!r} "
                                 f"(labels: {', '.join(rb.label_names)})", param_hint="--ground-label")
    scans_in = [Path(p) for p in pairs[0::2]]
    n = len(scans_in)
    if n < 2:
        raise click.UsageError("cross-validation over scans needs at least 2 SCAN GT pairs, got 1")
    if folds is not None and folds > n:
        raise click.BadParameter(f"{folds} folds for {n} scans: at most one fold per scan", param_hint="--folds")
    inputs = {Path(rules).resolve()} | {p.resolve() for p in scans_in}
    inputs |= {Path(g).resolve() for g in pairs[1::2] if not g.startswith("field:")}
    for target, what in ((out, "--out"), (report, "--report")):
        if target is not None and target.resolve() in inputs:
            raise click.BadParameter(f"{target} is an input: write the tuned rule file elsewhere", param_hint=what)
    for target, what in ((out, "--out"), (report, "--report")):
        if target is not None and not target.parent.is_dir():  # before the work, not after it
            raise click.BadParameter(f"no such folder: {target.parent}", param_hint=what)
    distinct_outputs(("--out", out), ("--report", report))  # one would replace the other
    for target, what, suffixes in ((out, "--out", (".yaml", ".yml")), (report, "--report", (".json",))):
        if target is not None and target.suffix.lower() not in suffixes:  # YAML over a result's .json ...
            raise click.BadParameter(f"{target}: give a {' or '.join(suffixes)} file name", param_hint=what)
    sources = InputFiles([rules if Path(rules).is_file() else Path(rb.path), *scans_in,
                          *(g for g in pairs[1::2] if not g.startswith("field:"))])
    for target, what in ((out, "--out"), (report, "--report")):  # before the work, as kbs run: a file kbs did
        if target is not None:                                    # not write only with --force
            check_output(target, inputs=sources, force=force, option=what)
    target_unit = None if rb.units == "scan" else unit(rb.units)
    scans = []
    for cloud, truth in zip(scans_in, pairs[1::2]):
        pc_units = ScanUnits.uniform(units, source="--units") if units else None
        scans.append(_read_pair(cloud, truth, ground_values=ground_values, unlabelled_values=unlabelled_values,
                                units=pc_units, target_unit=target_unit, sensor=sensor))
    if not any(s.truth[s.valid].any() for s in scans):
        raise click.UsageError(f"no scan has a ground point in its ground truth (--ground-values "
                               f"{','.join(map(str, ground_values or ()))}): there is no ground to fit the thresholds "
                               "to; check the values that mean ground")
    if not quiet:
        click.echo(f"kbs: tune: {rb.path}: {len(rb.tunables)} marked threshold(s), "
                   f"{int(np.prod([len(t.values) for t in rb.tunables])):,} settings, {n} scans", err=True)
    n_settings = int(np.prod([len(t.values) for t in rb.tunables]))
    total = min(n_settings, max_evals or n_settings) * n
    lines = ProgressLines("tune", lambda k: f"{k:,} of {total:,} scores (settings x scans)", quiet=quiet, start=t0)
    try:
        result = tune(rb, scans, ground_label=ground_label, folds=folds, metric=metric, jobs=jobs,
                      max_evals=max_evals, time_limit=time_limit, progress=lines, select=select)
    except ParameterError as exc:
        raise click.UsageError(str(exc)) from None
    run_id = new_run_id()
    text = tuned_text(rb, result, resolve(rules)[1])  # its first line '# kbs tune: ...' marks it as kbs's
    targets = (out,) if report is None else (out, report)
    with replacing(*targets) as tmps:  # the rule file and its report together, or neither
        tmps[0].write_text(text, encoding="utf-8")
        if report is not None:
            doc = {"kbs_version": __version__, "run_id": run_id, "rules": rb.path, "out": str(out), **result.to_dict()}
            tmps[1].write_text(json.dumps(doc, indent=1), encoding="utf-8")
    click.echo(format_report(result, rb.path, str(out)))
    if report is not None:
        click.echo(f"wrote {report}")


def _read_pair(cloud: Path, truth: str, *, ground_values, unlabelled_values, units, target_unit, sensor) -> LabelledScan:
    """One SCAN GT pair: the points in the rule base's unit, the GT checked (one label per point)."""
    pc = read_cloud(cloud)
    try:
        gt = load_ground_truth(truth, pc)
    except UnknownFieldError as exc:
        raise click.BadParameter(str(exc), param_hint="GT") from None
    kitti = is_semantickitti_label(truth)
    gv = ground_values if ground_values is not None else SEMANTICKITTI_GROUND if kitti else None
    if gv is None:
        raise click.UsageError(f"{truth}: give --ground-values (the GT labels that are ground); only a "
                               "SemanticKITTI .label has a default")
    ul = unlabelled_values if unlabelled_values is not None else SEMANTICKITTI_IGNORED if kitti else ()
    if set(gv) & set(ul):
        raise click.BadParameter(f"labels {sorted(set(gv) & set(ul))} are also unlabelled",
                                 param_hint="--ground-values")
    valid = ~np.isin(gt, np.asarray(ul, dtype=np.int64))
    if not valid.any():
        raise CloudFileError(truth, f"every one of its {len(gt):,} labels is unlabelled "
                                    f"({','.join(map(str, ul))}): nothing to score")
    f = scale_factors(units if units is not None else pc.units, target_unit)
    X = pc.xyz * f if not np.array_equal(f, np.ones(3)) else pc.xyz
    return LabelledScan(name=str(cloud), X=np.asarray(X, dtype=np.float64),
                        truth=np.isin(gt, np.asarray(gv, dtype=np.int64)), valid=valid,
                        sensor=None if sensor is None else np.asarray(sensor, dtype=np.float64) * f)
