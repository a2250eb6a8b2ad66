"""``kbs run``, ``kbs explain``, ``kbs rules``, ``kbs predicates``: the knowledge-based system."""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from kbs import __version__
from kbs.cli.common import write_result_ply
from kbs.errors import CloudFileError, ExitCode, KbsError
from kbs.io import SUPPORTED_EXTENSIONS, read_cloud, read_result_json
from kbs.knowledge import Explanation, PredicateRegistry, Segmenter, load_rule_base
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


@dataclass(frozen=True)
class ScanResult:
    """What `kbs run` did with one scan: its size, cluster count and where the time went (s)."""

    cloud: Path
    points: int
    clusters: int
    read: float
    segment: float
    write: float


@dataclass(frozen=True)
class ScanFailure:
    """A scan `kbs run` could not do (reported on stderr as it happened), and its exit code."""

    cloud: Path
    exit_code: int


def scan_paths(clouds: tuple[Path, ...]) -> list[Path]:
    """The scans named by CLOUD arguments: a file as given, a directory as every file directly
    inside it with a supported extension (:data:`kbs.io.SUPPORTED_EXTENSIONS`), in name order.
    Two scans with the same stem would write the same result files: a usage error."""
    scans: list[Path] = []
    for arg in clouds:
        if not arg.is_dir():
            scans.append(arg)  # the reader says what is wrong with it, if anything
            continue
        try:
            found = sorted((p for p in arg.iterdir() if p.suffix.lower() in SUPPORTED_EXTENSIONS and p.is_file()),
                           key=lambda p: p.name)
        except OSError as exc:
            raise CloudFileError(str(arg), f"cannot list the directory: {exc.strerror or exc}") from exc
        if not found:
            raise CloudFileError(str(arg), f"no point-cloud file in this directory (extensions: "
                                 f"{', '.join(SUPPORTED_EXTENSIONS)})")
        scans.extend(found)
    seen: dict[str, Path] = {}
    for scan in scans:
        if scan.stem in seen:
            first = seen[scan.stem]
            what = (f"{scan} is given twice" if first.resolve() == scan.resolve() else
                    f"{first} and {scan} would both write {scan.stem}.ply and {scan.stem}.json; give scans with "
                    f"different names (or run them apart with different --out)")
            raise click.BadParameter(what, param_hint="CLOUD")
        seen[scan.stem] = scan
    return scans


def run_scan(segmenter: Segmenter, cloud: Path, out_dir: Path, *, color_by: str = "cluster", meshes: bool = False,
             report: bool = False, quiet: bool = False, t0: float | None = None) -> ScanResult:
    """Read one scan, segment it, write DIR/<stem>.ply and DIR/<stem>.json (and the meshes and the
    report when asked) and print what was done; ``t0`` is when its clock started (default: now)."""
    t0 = time.perf_counter() if t0 is None else t0
    rb = segmenter.rule_base
    pc = read_cloud(cloud)
    t_read = time.perf_counter() - t0
    ply, js = out_dir / f"{cloud.stem}.ply", out_dir / f"{cloud.stem}.json"
    if ply.resolve() == cloud.resolve():
        raise CloudFileError(str(ply), "the output would overwrite the input; choose another --out")
    seg = segmenter.segment(pc.xyz)
    t1 = time.perf_counter()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CloudFileError(str(out_dir), f"cannot create the output directory: {exc.strerror or exc}") from exc
    from kbs.report.colors import rgb_fields

    write_result_ply(ply, pc, {"cluster": seg.cluster, "label": seg.label, "membership": seg.membership,
                               **rgb_fields(seg.cluster if color_by == "cluster" else seg.label)})
    doc = {
        "kbs_version": __version__, "input": str(cloud), "n_points": len(pc), "n_dropped": pc.n_dropped,
        "rule_base": rb.name, "rule_file": rb.path, "units": rb.units, "sensor": list(segmenter.sensor),
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
    return ScanResult(cloud, len(pc), s["clusters"], t_read, seg.seconds, t_write)


def time_table(results: list[ScanResult | ScanFailure], t_load: float, t_total: float) -> str:
    """The per-scan time table `kbs run` prints after several scans (aligned columns, then the
    median segmentation time and the total, which includes loading the rule base)."""
    name_w = max([len("scan")] + [len(r.cloud.name) for r in results])
    head = f"{'scan':<{name_w}}  {'points':>10}  {'clusters':>8}  {'read s':>6}  {'segment s':>9}  {'write s':>7}"
    lines = [head]
    for r in results:
        if isinstance(r, ScanResult):
            lines.append(f"{r.cloud.name:<{name_w}}  {r.points:>10,}  {r.clusters:>8,}  {r.read:>6.2f}  "
                         f"{r.segment:>9.2f}  {r.write:>7.2f}")
        else:
            lines.append(f"{r.cloud.name:<{name_w}}  {'-':>10}  {'-':>8}  {'-':>6}  {'-':>9}  {'-':>7}  "
                         f"failed: exit code {r.exit_code}")
    done = [r.segment for r in results if isinstance(r, ScanResult)]
    failed = len(results) - len(done)
    head = f"{len(results)} scans" + (f" ({failed} failed)" if failed else "")
    median = f"segment median {float(np.median(done)):.2f} s, " if done else ""
    lines.append(f"{head}: {median}total {t_total:.2f} s (rule base loaded once, {t_load:.2f} s)")
    return "\n".join(lines)


@click.command()
@click.option("--rules", "rules", required=True, metavar="NAME|FILE",
              help=f"A shipped rule base ({', '.join(shipped_rule_bases())}) or a rule file.")
@click.argument("clouds", nargs=-1, required=True, type=click.Path(path_type=Path), metavar="CLOUD...")
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
def run(ctx: click.Context, rules: str, clouds: tuple[Path, ...], sensor, out_dir: Path, plugins: tuple[Path, ...],
        color_by: str = "cluster", meshes: bool = False, report: bool = False, jobs: int = -1) -> None:
    """Segment each CLOUD with a rule base; write DIR/<stem>.ply (per-vertex cluster, label,
    membership) and DIR/<stem>.json (label names, clusters, the explanation tree).

    A CLOUD that is a directory stands for every point-cloud file directly inside it, in name
    order. The rule base is loaded once for all the scans; with several, a table of the time each
    took follows. A scan that fails is reported and the others go on; the exit code is then the
    first failure's."""
    quiet = ctx.obj.get("quiet", False)
    t0 = time.perf_counter()
    scans = scan_paths(clouds)
    with Segmenter(rules, jobs=jobs, sensor=sensor, plugins=plugins) as segmenter:  # workers kept for all scans
        if not quiet:
            for w in segmenter.rule_base.warnings:  # `kbs rules check` quotes the line
                click.echo(f"kbs: warning: {w.pos}: {w.message}", err=True)
        _run_scans(segmenter, scans, out_dir, t0, color_by=color_by, meshes=meshes, report=report, quiet=quiet)


def _run_scans(segmenter, scans, out_dir: Path, t0: float, **options) -> None:
    if len(scans) == 1:  # the clock starts with the command: its read time includes loading the rule base
        run_scan(segmenter, scans[0], out_dir, t0=t0, **options)
        return
    t_load = time.perf_counter() - t0
    results: list[ScanResult | ScanFailure] = []
    for scan in scans:
        try:
            results.append(run_scan(segmenter, scan, out_dir, **options))
        except KbsError as exc:  # as the command would report it alone; the other scans go on
            click.echo(f"kbs: error: {exc}", err=True)
            results.append(ScanFailure(scan, int(exc.exit_code)))
    click.echo(time_table(results, t_load, time.perf_counter() - t0))
    failures = [r.exit_code for r in results if isinstance(r, ScanFailure)]
    if failures:
        raise click.exceptions.Exit(failures[0])


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
    """Validate rule files (or shipped names); every problem is reported as file:line:col.

    Warnings (a condition that can never hold: a rule that never acts, a label never given) are
    printed on stderr as file:line:col: warning: ...; they do not change the exit code."""
    reg = _registry(plugins)
    bad: list[RuleFileError] = []
    for f in files:
        try:
            rb = load_rule_base(f, reg)
        except RuleFileError as exc:
            bad.append(exc)
            continue
        n_warn = len(rb.warnings)
        labels = rb.label_names if len(rb.label_names) <= 12 else rb.label_names[:11] + ["...", rb.label_names[-1]]
        click.echo(f"{f}: ok — '{rb.name}', {len(rb.checks)} checks, {len(rb.rules)} rules, "
                   f"labels {', '.join(labels)}, strategy {rb.strategy}"
                   + (f"; {n_warn} warning{'s' if n_warn != 1 else ''}" if n_warn else ""))
        for w in rb.warnings:
            click.echo(w.format(), err=True)
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
