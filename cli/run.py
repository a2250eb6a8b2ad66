"""``kbs run``, ``kbs explain``, ``kbs rules``, ``kbs predicates``: the knowledge-based system."""
from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from kbs import __version__
from kbs.cli.common import cloud_argument, write_result_ply
from kbs.errors import CloudFileError, ExitCode
from kbs.io import read_cloud, read_result_json
from kbs.knowledge import Explanation, Interpreter, PredicateRegistry, load_rule_base
from kbs.knowledge.explain import limit_lines
from kbs.knowledge.predicates import UNITS, did_you_mean
from kbs.knowledge.rulebase import RuleFileError, resolve, shipped_rule_bases


def _vector3(ctx, param, value):
    if value is None:
        return None
    try:
        v = [float(x) for x in value.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(np.isfinite(v)):
        raise click.BadParameter(f"expected X,Y,Z (three numbers), got {value!r}")
    return v


def _jobs(ctx, param, value):
    if value == 0:
        raise click.BadParameter("0 processes: give a positive number, or -1 for one per core")
    return value


def _registry(plugins: tuple[Path, ...]) -> PredicateRegistry:
    reg = PredicateRegistry.default()
    for p in plugins:
        reg.add_plugin_file(p)
    return reg


plugin_option = click.option("--plugin", "plugins", multiple=True, type=click.Path(path_type=Path),
                             help="A Python file declaring extra predicates (repeatable).")


@click.command()
@click.option("--rules", "rules", required=True, metavar="NAME|FILE",
              help=f"A shipped rule base ({', '.join(shipped_rule_bases())}) or a rule file.")
@cloud_argument
@click.option("--sensor", callback=_vector3, metavar="X,Y,Z", help="Sensor position (overrides the rule base's).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("kbs-out"),
              show_default=True, help="Directory for <stem>.ply and <stem>.json.")
@plugin_option
@click.option("--color-by", "color_by", type=click.Choice(["cluster", "label"]), default="cluster", show_default=True,
              help="Colour of each vertex (red green blue) in <stem>.ply: one per output cluster or per label.")
@click.option("--meshes", is_flag=True, help="Also write DIR/<stem>-meshes/: a convex hull per obstacle cluster "
              "(obstacle-<index>.ply) and the ground surface (ground.ply).")
@click.option("--report", is_flag=True, help="Also write DIR/<stem>.html: a self-contained report (3D view by "
              "cluster or label, centres and eigen-boxes, APD curve, the explanation tree; opens offline).")
@click.option("-j", "--jobs", type=click.IntRange(min=-1), default=-1, show_default=True, callback=_jobs,
              help="Processes computing the UFP-ONC splits side by side; -1: one per available core. The result "
              "does not depend on it.")
@click.pass_context
def run(ctx: click.Context, rules: str, cloud: Path, sensor, out_dir: Path, plugins: tuple[Path, ...],
        color_by: str = "cluster", meshes: bool = False, report: bool = False, jobs: int = -1) -> None:
    """Segment CLOUD with a rule base; write DIR/<stem>.ply (per-vertex cluster, label, membership)
    and DIR/<stem>.json (label names, clusters, the explanation tree)."""
    quiet = ctx.obj.get("quiet", False)
    t0 = time.perf_counter()
    rb = load_rule_base(rules, _registry(plugins))
    pc = read_cloud(cloud)
    t_read = time.perf_counter() - t0
    seg = Interpreter(rb, sensor=sensor, jobs=jobs).run(pc.xyz)
    t1 = time.perf_counter()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CloudFileError(str(out_dir), f"cannot create the output directory: {exc.strerror or exc}") from exc
    ply, js = out_dir / f"{cloud.stem}.ply", out_dir / f"{cloud.stem}.json"
    if ply.resolve() == cloud.resolve():
        raise CloudFileError(str(ply), "the output would overwrite the input; choose another --out")
    from kbs.report.colors import rgb_fields

    write_result_ply(ply, pc, {"cluster": seg.cluster, "label": seg.label, "membership": seg.membership,
                               **rgb_fields(seg.cluster if color_by == "cluster" else seg.label)})
    doc = {
        "kbs_version": __version__, "input": str(cloud), "n_points": len(pc), "n_dropped": pc.n_dropped,
        "rule_base": rb.name, "rule_file": rb.path, "units": rb.units, "sensor": list(map(float, sensor or rb.sensor)),
        "label_names": seg.label_names, "summary": seg.summary(), "clusters": seg.clusters,
        "explanation": seg.explanation.to_dict(),
    }
    try:
        js.write_text(json.dumps(doc, separators=(",", ":"), default=_jsonable))
    except OSError as exc:
        raise CloudFileError(str(js), f"cannot write: {exc.strerror or exc}") from exc
    t_write = time.perf_counter() - t1
    s = seg.summary()
    per_label = ", ".join(f"{k} {v:,}" for k, v in s["points_per_label"].items())
    click.echo(f"{cloud}: {len(pc):,} points, rule base '{rb.name}' ({rb.strategy})")
    click.echo(f"  {s['clusters']} clusters, {s['splits']} splits, {s['limits']} limits reached; points: {per_label}")
    for line in limit_lines(s["limits_by_kind"], Path(rb.path).name, result=str(js)):
        click.echo(f"  {line}")
    click.echo(f"  ground: {seg.explanation.ground.get('source', 'not used')}")
    click.echo(f"  time: {time.perf_counter() - t0:.2f} s (read {t_read:.2f}, segment {seg.seconds:.2f}, "
               f"write {t_write:.2f})")
    click.echo(f"wrote {ply} and {js}")
    if meshes:
        from kbs.report.meshes import write_meshes

        click.echo(write_meshes(out_dir / f"{cloud.stem}-meshes", pc.xyz, seg.cluster, seg.label,
                                seg.label_names).describe())
    if report:
        from kbs.report.html import write_report

        html = out_dir / f"{cloud.stem}.html"
        try:
            write_report(html, pc.xyz, seg.cluster, seg.label, seg.label_names, doc["explanation"], seg.clusters,
                         title=f"{cloud.name} — rule base '{rb.name}'")
        except OSError as exc:
            raise CloudFileError(str(html), f"cannot write: {exc.strerror or exc}") from exc
        click.echo(f"wrote {html}")
    if not quiet:
        for note in seg.explanation.notes + ([seg.explanation.ground["note"]] if "note" in seg.explanation.ground else []):
            click.echo(f"note: {note}", err=True)


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


@click.command()
@click.argument("result", type=click.Path(path_type=Path))
@click.option("--cluster", "cluster_id", metavar="ID", help="Say why this cluster ended as it did (e.g. c0.2).")
def explain(result: Path, cluster_id: str | None) -> None:
    """Print the explanation tree of a `kbs run` RESULT.json, or why one cluster ended as it did."""
    doc = read_result_json(result, require=("explanation",))
    try:
        expl = Explanation.from_dict(doc["explanation"])
    except (KeyError, TypeError) as exc:
        raise CloudFileError(str(result), f"not a kbs result file ({type(exc).__name__}: {exc})") from exc
    if cluster_id is None:
        click.echo(f"rule base '{expl.rule_base}' ({expl.rule_file}), strategy {expl.strategy}; "
                   f"labels: {', '.join(expl.label_names)}")
        if expl.ground:
            click.echo(f"ground: {expl.ground.get('source')}")
        click.echo(expl.render())
        return
    if cluster_id not in expl.records:
        hint = did_you_mean(cluster_id, list(expl.records))
        raise click.BadParameter(f"no cluster {cluster_id!r} in {result}" + (f"; did you mean {hint!r}?" if hint else ""),
                                 param_hint="--cluster")
    click.echo(expl.why(cluster_id))


@click.group()
def rules() -> None:
    """Check, show and list rule bases."""


@rules.command("check")
@click.argument("files", nargs=-1, required=True)
@plugin_option
def rules_check(files: tuple[str, ...], plugins: tuple[Path, ...]) -> None:
    """Validate rule files (or shipped names); every problem is reported as file:line:col."""
    reg = _registry(plugins)
    bad: list[RuleFileError] = []
    for f in files:
        try:
            rb = load_rule_base(f, reg)
        except RuleFileError as exc:
            bad.append(exc)
            continue
        click.echo(f"{f}: ok — '{rb.name}', {len(rb.checks)} checks, {len(rb.rules)} rules, "
                   f"labels {', '.join(rb.label_names)}, strategy {rb.strategy}")
    if bad:
        for exc in bad:
            click.echo(exc.format(), err=True)
        n = sum(len(e.problems) for e in bad)
        click.echo(f"kbs: error: {n} problem{'s' if n != 1 else ''} in {len(bad)} rule file"
                   f"{'s' if len(bad) != 1 else ''}", err=True)
        raise click.exceptions.Exit(int(ExitCode.RULES))


@rules.command("show")
@click.argument("name")
def rules_show(name: str) -> None:
    """Print a shipped rule base (or a rule file)."""
    _, text = resolve(name)
    click.echo(text, nl=not text.endswith("\n"))


@rules.command("list")
def rules_list() -> None:
    """List the shipped rule bases."""
    for name in shipped_rule_bases():
        rb = load_rule_base(name)
        click.echo(f"{name:16} {rb.description.splitlines()[0] if rb.description else ''}")


@click.command()
@plugin_option
def predicates(plugins: tuple[Path, ...]) -> None:
    """List every predicate a rule file may use, with unit, parameters and doc."""
    for p in _registry(plugins):
        uses = ("  (uses the local ground surface: post.relabel only)" if p.needs_ground_model
                else "  (uses the ground)" if p.needs_ground else "")
        click.echo(f"{p.name}  [{p.unit}: {UNITS[p.unit]}]{uses}")
        lo, hi = p.value_range
        if lo is not None or hi is not None:
            click.echo(f"    values in [{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]")
        for prm in p.params.values():
            click.echo(f"    param {prm.describe()}")
        for line in p.doc.splitlines():
            click.echo(f"    {line}")
        if p.origin != "kbs.knowledge.predicates":
            click.echo(f"    from {p.origin}")
