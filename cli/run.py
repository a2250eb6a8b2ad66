"""``kbs run``, ``kbs explain``, ``kbs rules``, ``kbs predicates``: the knowledge-based system."""
from __future__ import annotations

import dataclasses
import functools
import re
import shutil
import tempfile
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from kbs.cli.types import FiniteFloatRange, PathArg
import numpy as np

from kbs import __version__
from kbs.cli.common import (ProgressLines, check_writable_folder, force_option, progress_interval, remove_if_empty,
                            result_fields)
from kbs.errors import CloudFileError, ExitCode, KbsError, raise_if_interrupted, require
from kbs.io import SUPPORTED_EXTENSIONS, PointCloud, read_cloud, read_result
from kbs.io.atomic import replacing
from kbs.io.las import check_classes_fit, class_codes
from kbs.io.readers import cloud_files_in, why_not_a_scan
from kbs.io.result import RUN_ID_COMMENT, InputFiles, check_output, new_run_id, write_result_pair, write_result_stream
from kbs.io.result import jsonable as _jsonable  # noqa: F401 -- benchmarks/profile_run.py times the JSON with it
from kbs.knowledge import Explanation, PredicateRegistry, Segmenter, load_rule_base
from kbs.knowledge.segmenter import coordinate_problem
from kbs.knowledge.explain import TREE_LINES, limit_lines
from kbs.knowledge.predicates import UNITS, did_you_mean
from kbs.knowledge.rulebase import RuleFileError, resolve, shipped_rule_bases
from kbs.units import UNITS as LENGTH_UNITS, CoordinateWarning, ScanUnits, SpacingWarning

if TYPE_CHECKING:
    from kbs.tiles.stream import SpilledCloud


def _vector3(ctx, param, value):
    if value is None:
        return None
    try:
        v = [float(x) for x in value.split(",")]
    except ValueError:
        v = []
    from kbs.knowledge.segmenter import MAX_COORDINATE

    if len(v) != 3 or not all(np.isfinite(v)) or max(abs(x) for x in v) > MAX_COORDINATE:
        raise click.BadParameter(f"expected X,Y,Z (three finite numbers, each within +-{MAX_COORDINATE:g}), got {value!r}")
    return v


def _jobs(ctx, param, value):
    if value == 0:
        raise click.BadParameter("0 processes: give a positive number, or -1 for one per core")
    from kbs.knowledge.interpreter import available_cores

    cores = available_cores()
    if value > cores and not (ctx.find_root().obj or {}).get("quiet"):  # the processes kbs starts are capped there
        click.echo(f"note: -j {value}: {cores} core{'s' if cores > 1 else ''} available, so at most {cores} "
                   f"process{'es' if cores > 1 else ''} on this machine (more would run no faster)", err=True)
    return value


def _registry(plugins: tuple[Path, ...]) -> PredicateRegistry:
    reg = PredicateRegistry.default()
    for p in plugins:
        reg.add_plugin_file(p)
    return reg


plugin_option = click.option("--plugin", "plugins", multiple=True, type=PathArg(path_type=Path),
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


def _companion_of(path: Path, names: set[str]) -> str | None:
    """``B.labels.npy`` beside ``B.points.npy`` (SemanticKITTI, GndNet): the name of the scan a
    file goes with, or None."""
    parts = path.name.split(".")
    if len(parts) >= 3 and parts[-2] != "points":
        scan = ".".join([*parts[:-2], "points", parts[-1]])
        if scan in names:
            return scan
    return None


def scan_paths(clouds: tuple[Path, ...], *,
               on_skip: Callable[[Path, str], None] | None = None) -> list[Path]:
    """The scans named by CLOUD arguments: a file as given, a directory as every file directly
    inside it with a supported extension (:data:`kbs.io.SUPPORTED_EXTENSIONS`), in name order,
    except the files that are not point clouds: ``B.<anything>.EXT`` beside a ``B.points.EXT``
    (labels, grids), and arrays or text files that cannot hold x y z
    (:func:`kbs.io.readers.why_not_a_scan`); each of those is passed to ``on_skip`` with the reason.
    Two scans with the same stem would write the same result files: a usage error."""
    scans: list[Path] = []
    for arg in clouds:
        if not arg.is_dir():
            scans.append(arg)  # the reader says what is wrong with it, if anything
            continue
        found = cloud_files_in(arg)
        names = {p.name for p in found}
        kept = []
        for p in found:
            scan = _companion_of(p, names)
            problem = None if scan else why_not_a_scan(p)
            if scan is None and problem is None:
                kept.append(p)
            elif on_skip is not None:
                on_skip(p, f"a companion of {scan}, not a scan" if scan else f"not a point cloud ({problem})")
        if not kept:
            skipped = f"; {len(found)} skipped, not point clouds" if found else ""
            raise CloudFileError(str(arg), f"no point-cloud file in this directory (extensions: "
                                 f"{', '.join(SUPPORTED_EXTENSIONS)}{skipped})")
        scans.extend(kept)
    seen: dict[str, Path] = {}
    for path in scans:
        if path.stem in seen:
            first = seen[path.stem]
            what = (f"{path} is given twice" if first.resolve() == path.resolve() else
                    f"{first} and {path} would both write {path.stem}.ply and {path.stem}.json; give scans with "
                    f"different names (or run them apart with different --out)")
            raise click.BadParameter(what, param_hint="CLOUD")
        seen[path.stem] = path
    return scans


@dataclass(frozen=True)
class Tiling:
    """``kbs run --tile``: square tiles of ``size`` with a ``buffer`` (None: the default), run in
    process (``scheduler`` None) or on Dask (``"local"`` or a scheduler address); ``resume``:
    take the tiles an earlier failed run finished."""

    size: float
    buffer: float | None = None
    scheduler: str | None = None
    workers: int | None = None
    resume: bool = False
    #: LAS/LAZ in and out: read (and write) this many points at a time, the tiles spilled to disk
    #: (kbs.tiles.stream); 0: the whole file read into memory
    chunk_points: int = 0


@dataclass(frozen=True)
class TileOptions:
    """``--buffer``, ``--resume`` and ``--chunk-points`` as given (None / False: not given). Without
    ``--tile`` they apply to the tiles of the rule base's ``limits.tile`` as they do to ``--tile``'s."""

    buffer: float | None = None
    resume: bool = False
    chunk_points: int | None = None

    def given(self) -> list[str]:
        """The options given, by name, in the order of ``kbs run --help``."""
        return [name for name, value in (("--buffer", self.buffer), ("--resume", self.resume or None),
                                         ("--chunk-points", self.chunk_points)) if value is not None]


def _not_used(names: list[str]) -> str:
    """'--buffer is not used' / '--buffer and --resume are not used' ('' for no name)."""
    return f"{_listed(names)} {'is' if len(names) == 1 else 'are'} not used" if names else ""


def _listed(names: list[str]) -> str:
    """'--buffer' / '--buffer and --resume' / '--buffer, --resume and --chunk-points'."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def default_out_format(cloud: Path, in_format: str | None = None) -> str:
    """The points format of a result when --out-format is not given: LAS in, LAS out (LAZ in,
    LAZ out); anything else, PLY."""
    ext = (in_format or cloud.suffix).lower().lstrip(".")
    return ext if ext in ("las", "laz") else "ply"


def read_scan(cloud: Path, in_format: str | None = None) -> PointCloud:
    """Read a scan: a file (``in_format`` overrides its extension), or ``-``: standard input,
    whose format ``in_format`` must give. Errors name ``<stdin>`` for standard input."""
    if str(cloud) != "-":
        return read_cloud(cloud, format=in_format)
    if in_format is None:
        raise click.UsageError("reading a scan from standard input ('-') needs --in-format (ply, pcd, las, ...)")
    import tempfile

    with tempfile.TemporaryDirectory(prefix="kbs-") as folder:
        tmp = Path(folder) / f"stdin.{in_format.lower().lstrip('.')}"
        with open(tmp, "wb") as out:
            shutil.copyfileobj(sys.stdin.buffer, out, 1 << 20)
        try:
            return dataclasses.replace(read_cloud(tmp, format=in_format), path="-")
        except CloudFileError as exc:
            raise CloudFileError("<stdin>", exc.problem) from exc


def _scan_units(pc: PointCloud, given: str | None, name: str, quiet: bool) -> ScanUnits | None:
    """The scan's units: --units, else what its file declares, else None (unknown)."""
    if given is None:
        return pc.units
    units = ScanUnits.uniform(given, source="--units")
    if pc.units is not None and pc.units.name != units.name and not quiet:
        click.echo(f"kbs: warning: {name}: --units {given} overrides {pc.units.name}, which {pc.units.source} says",
                   err=True)
    return units


def _scan_frame(clusters: list[dict], f: np.ndarray) -> tuple[list[dict], str | None]:
    """The output clusters with their descriptors (computed in the rule base's unit) back in the
    scan's: centre / f, thickness / f, eigenvalues / f^2 (copies; the explanation keeps the rule
    base's unit). With a different factor for z, only the centre is converted (and a note says so)."""
    if np.array_equal(f, np.ones(3)):
        return clusters, None
    iso = bool(np.all(f == f[0]))
    out = []
    for c in clusters:
        d = dict(c.get("descriptors") or {})
        if "center" in d:
            d["center"] = (np.asarray(d["center"], dtype=float) / f).tolist()
        if iso:
            if "thickness" in d:
                d["thickness"] = float(d["thickness"]) / float(f[0])
            if "eigenvalues" in d:
                d["eigenvalues"] = (np.asarray(d["eigenvalues"], dtype=float) / float(f[0]) ** 2).tolist()
        out.append({**c, "descriptors": d})
    note = None if iso else ("the clusters' thickness and eigenvalues are in the rule base's unit (x, y and z of the "
                             "scan are in different units); their centres are in the scan's")
    return out, note


def _ascii_line(text: str) -> str | None:
    line = " ".join(text.split())
    return line if line.isascii() and line else None


def run_scan(segmenter: Segmenter, cloud: Path, out_dir: Path | None, *, color_by: str = "cluster", meshes: bool = False,
             report: bool = False, quiet: bool = False, t0: float | None = None,
             inputs: InputFiles | tuple[Path, ...] = (),
             force: bool = False, out_format: str | None = None, in_format: str | None = None,
             units: str | None = None, sensor=None, tiling: Tiling | None = None,
             auto_tile: bool = True, auto_scheduler: tuple[str, int | None] | None = None,
             tile_options: TileOptions = TileOptions()) -> ScanResult:
    """Read one scan, segment it, write DIR/<stem>.ply (or .las/.laz) and DIR/<stem>.json (and the
    meshes and the report when asked) and print what was done (nothing on stdout when ``quiet``);
    ``t0`` is when its clock started (default: now). ``out_dir`` None: the points go to standard
    output (``--out -``), no JSON, and the summary to stderr. Without ``tiling``, a cloud wider than
    the rule base's ``limits.tile.wider_than`` is segmented in its tiles (:func:`_auto_tiling`)
    unless ``auto_tile`` is False (``--no-tile``): on Dask when ``auto_scheduler`` is given (the
    scheduler and the number of workers, as :class:`Tiling`'s), with ``tile_options``' buffer and
    resume; a LAS/LAZ written as LAS/LAZ whose header's bounds say it is wider is read in chunks of
    ``tile_options.chunk_points`` (0: read whole), as ``--tile`` reads it (:func:`_header_tiling`).
    An option given that this scan cannot use is named in a note (on stderr), never ignored silently.

    Before reading, each output is checked (:func:`kbs.io.result.check_output`): never ``cloud``
    or one of ``inputs``; an existing file kbs did not write only with ``force``."""
    t0 = time.perf_counter() if t0 is None else t0
    to_stdout = out_dir is None
    say = (lambda *args, **kwargs: None) if quiet else functools.partial(click.echo, err=to_stdout)
    stdin = str(cloud) == "-"
    stem = "stdin" if stdin else cloud.stem
    fmt = out_format or default_out_format(cloud, in_format)
    points = js = html = None
    if not to_stdout:
        points, js = out_dir / f"{stem}.{fmt}", out_dir / f"{stem}.json"
        html = out_dir / f"{stem}.html"
        sources = inputs if isinstance(inputs, InputFiles) else InputFiles((cloud, *inputs))
        for target in (points, js, *([html] if report else [])):
            check_output(target, inputs=sources, force=force)
        if meshes:  # before the work too: a mesh kbs did not write is replaced only with --force
            from kbs.report.meshes import check_meshes_folder

            check_meshes_folder(out_dir / f"{stem}-meshes", force=force)
    spilled: SpilledCloud | None = None  # a LAS/LAZ file read in chunks, or a COPC file by its octree
    why_tiled = None
    if tiling is None and auto_tile and not stdin and not to_stdout and sensor is None:
        tiling, why_tiled = _header_tiling(segmenter, cloud, in_format, fmt, units, auto_scheduler, tile_options)
    if _streams(tiling, cloud, in_format, fmt):
        from kbs.tiles.copc import ENV, copc_reason, read_copc
        from kbs.tiles.stream import las_header, spill_las, streamed_cloud

        assert tiling is not None

        spill_folder = Path(tempfile.mkdtemp(prefix=f".{cloud.stem}.spill-", dir=out_dir))
        try:
            normal = segmenter.rule_base.ground.normal
            not_copc = copc_reason(las_header(cloud), normal)
            if not_copc is None:  # each tile reads its bounds by the octree (kbs.tiles.copc)
                spilled = read_copc(cloud, spill_folder, tiling.size, _buffer(segmenter, tiling), tiling.chunk_points)
            else:
                if not quiet and not_copc not in ("not a COPC file", f"{ENV}=0"):
                    click.echo(f"note: {cloud}: a COPC file read as a plain LAZ file, not by its octree: {not_copc}",
                               err=True)
                spilled = spill_las(cloud, spill_folder, tiling.size, _buffer(segmenter, tiling), normal,
                                    tiling.chunk_points)
        except BaseException:
            shutil.rmtree(spill_folder, ignore_errors=True)
            raise
        spec = segmenter.rule_base.tile
        if why_tiled is not None and spec is not None and not spilled.width > spec.wider_than:
            # the header's bounds said wider, the points do not: read whole, as without the header
            spilled.remove()
            shutil.rmtree(spilled.folder, ignore_errors=True)
            spilled, tiling, why_tiled = None, None, None
    chunk_note = None  # --chunk-points given, this scan read whole: said if it is tiled
    if spilled is None and tile_options.chunk_points:
        chunk_note = ("--chunk-points is not used: it reads a LAS/LAZ file written as LAS/LAZ in chunks; this scan "
                      "is read whole" if not _las_in_and_out(cloud, in_format, fmt) else
                      "--chunk-points is not used: the LAS header's bounds do not give the width across the rule "
                      "base's ground normal, so the scan was read whole for its points to decide")
    pc = read_scan(cloud, in_format) if spilled is None else streamed_cloud(spilled, cloud)
    try:
        return _segment_and_write(segmenter, cloud, pc, spilled, out_dir, t0, stdin=stdin, stem=stem, fmt=fmt,
                                  points=points, js=js, html=html, to_stdout=to_stdout, color_by=color_by,
                                  meshes=meshes, report=report, quiet=quiet, units=units, sensor=sensor,
                                  tiling=tiling, auto_tile=auto_tile, auto_scheduler=auto_scheduler,
                                  why_tiled=why_tiled, say=say, tile_options=tile_options, chunk_note=chunk_note,
                                  force=force)
    finally:
        if spilled is not None:
            spilled.remove()
            shutil.rmtree(spilled.folder, ignore_errors=True)


def _auto_tiling(segmenter: Segmenter, xyz: np.ndarray, scan_units: ScanUnits | None, sensor,
                 to_stdout: bool, scheduler: tuple[str, int | None] | None = None,
                 options: TileOptions = TileOptions()) -> tuple[Tiling | None, str | None]:
    """The rule base's ``limits.tile`` for a scan read whole: its tiling when the cloud is wider
    than ``wider_than`` along either ground axis (the rule base's fixed ground normal, else x-y), with
    the words that say why, its tiles on Dask with ``scheduler`` (address, workers), with
    ``options``' buffer and resume; (None, why not) when it is wider but cannot be tiled (another
    unit, --sensor, --out -: as for --tile); when it is not wider, (None, None), or (None, a note
    that it runs whole) when a ``scheduler`` or ``options`` were given (they are not used)."""
    from kbs.tiles import ground_axes

    spec = segmenter.rule_base.tile
    f = segmenter.scale(scan_units)
    if spec is None or not len(xyz):
        return None, None
    uv = (xyz * f) @ ground_axes(segmenter.rule_base.ground.normal).T
    width = float((uv.max(axis=0) - uv.min(axis=0)).max())
    unit = segmenter.rule_base.length_unit
    u = f" {unit}" if unit else ""
    src = f"{Path(segmenter.rule_base.path).name} limits.tile"
    names = (["--scheduler"] if scheduler is not None else []) + options.given()
    unused = f"; {_not_used(names)}" if names else ""
    if not width > spec.wider_than:
        return None, (None if not names else
                      f"the cloud is {width:.6g}{u} wide, not more than {src}.wider_than ({spec.wider_than:g}{u}): "
                      f"it runs whole{', in this process' if scheduler is not None else ''}{unused}")
    from kbs.tiles import TileGrid

    grid = TileGrid.fit(xyz * f, spec.size, 0.0, segmenter.rule_base.ground.normal)  # the tiles it would get
    sample = uv[::max(1, len(uv) // SPARSE_SAMPLE)]  # fewer occupied tiles counted: a mean only higher
    sparse = _sparse(segmenter, len(uv) / max(1, grid.n_occupied(sample)))
    if sparse is not None:
        return None, (f"the cloud is {width:.6g}{u} wide, more than {src}.wider_than ({spec.wider_than:g}{u}), but "
                      f"its {len(xyz):,} points would average {sparse:.2g} in each tile of {spec.size:g}{u} that holds "
                      f"any, fewer than limits.min_points ({segmenter.rule_base.limits['min_points']}): it runs "
                      f"whole{unused}")
    if sensor is not None or not np.array_equal(f, np.ones(3)) or to_stdout:
        why = ("--sensor" if sensor is not None else "--out -" if to_stdout else
               f"its unit ({scan_units.name if scan_units else '?'}) is not the rule base's")
        return None, (f"the cloud is {width:.6g}{u} wide, more than {src}.wider_than ({spec.wider_than:g}{u}), but it "
                      f"runs whole: tiles need the rule base's own units and sensor and a result folder ({why}); "
                      f"give --tile {spec.size:g} after converting it, or --no-tile to silence this{unused}")
    address, workers = scheduler if scheduler is not None else (None, None)
    return (Tiling(size=spec.size, buffer=options.buffer, scheduler=address, workers=workers, resume=options.resume,
                   chunk_points=0),
            f"{src}: the cloud is {width:.6g}{u} wide, more than {spec.wider_than:g}{u}{_buffer_from(options)}; "
            f"--no-tile runs it whole")


def _sparse(segmenter: Segmenter, per_tile: float) -> float | None:
    """``per_tile``, the points a tile of ``limits.tile`` would hold on average, when fewer than
    ``limits.min_points``: tiles of a point or two (1,065 points over 4.6 km gave 764 tiles) make
    every point noise; None otherwise."""
    return per_tile if per_tile < segmenter.rule_base.limits["min_points"] else None


#: points at most on which :func:`_auto_tiling` counts the tiles that hold points (a sample: a
#: stray point far away still leaves the scan's tiles as full as they were)
SPARSE_SAMPLE = 1_000_000
#: a LAS file of at most this many points whose header's box gives sparse tiles is read whole, and
#: its points decide (:func:`_auto_tiling`); a larger one is tiled in chunks as its header says
SPARSE_HEADER_POINTS = 1_000_000


def _buffer_from(options: TileOptions) -> str:
    """Where an automatic tiling's buffer comes from, when not the default (said on the tiles: line)."""
    return f"; the buffer from --buffer {options.buffer:g}" if options.buffer is not None else ""


def _header_tiling(segmenter: Segmenter, cloud: Path, in_format: str | None, fmt: str, units: str | None,
                   scheduler: tuple[str, int | None] | None,
                   options: TileOptions = TileOptions()) -> tuple[Tiling | None, str | None]:
    """The rule base's ``limits.tile`` for a LAS/LAZ file written as LAS/LAZ, decided from its
    header's bounds before any point is read: a tiling read in chunks (as ``--tile``'s) and the words
    that say why when they are wider than ``wider_than``; (None, None) when the header cannot
    decide (no ``limits.tile``, another format, a ground plane other than x-y, a unit other than
    the rule base's, a header kbs cannot read, ``--chunk-points 0``: the points then decide, read
    whole, as :func:`_auto_tiling` does) or says it is not wider. ``options``: as for ``--tile``."""
    from kbs.tiles import ground_axes
    from kbs.tiles.stream import DEFAULT_CHUNK_POINTS, las_header

    spec = segmenter.rule_base.tile
    if spec is None or not _las_in_and_out(cloud, in_format, fmt) or options.chunk_points == 0:
        return None, None
    if not np.array_equal(ground_axes(segmenter.rule_base.ground.normal), np.eye(3)[:2]):
        return None, None  # the bounds of x and y do not give the width across another normal
    try:
        header = las_header(cloud)
    except CloudFileError:
        return None, None  # the reader says what is wrong with the file
    from kbs.io.readers import las_crs

    scan_units = ScanUnits.uniform(units, source="--units") if units is not None else las_crs(header, cloud)[0]
    if not np.array_equal(segmenter.scale(scan_units), np.ones(3)) or not int(header.point_count):
        return None, None
    lo, hi = np.asarray(header.mins, dtype=float)[:2], np.asarray(header.maxs, dtype=float)[:2]
    width = float((hi - lo).max())
    if not np.isfinite(width) or not width > spec.wider_than:
        return None, None
    n = int(header.point_count)
    area = float(np.prod(np.maximum(hi - lo, spec.size)))  # the header's box: its points decide when sparse
    if n <= SPARSE_HEADER_POINTS and _sparse(segmenter, n * spec.size ** 2 / area) is not None:
        return None, None  # read whole: its points decide (_auto_tiling)
    unit = segmenter.rule_base.length_unit
    u = f" {unit}" if unit else ""
    address, workers = scheduler if scheduler is not None else (None, None)
    chunk_points = DEFAULT_CHUNK_POINTS if options.chunk_points is None else options.chunk_points
    return (Tiling(size=spec.size, buffer=options.buffer, scheduler=address, workers=workers, resume=options.resume,
                   chunk_points=chunk_points),
            f"{Path(segmenter.rule_base.path).name} limits.tile: the cloud is {width:.6g}{u} wide by its LAS header, "
            f"more than {spec.wider_than:g}{u}, read in chunks{_buffer_from(options)}; --no-tile runs it whole")


def _streams(tiling: Tiling | None, cloud: Path, in_format: str | None, fmt: str) -> bool:
    """Whether a tiled run reads (and writes) the LAS/LAZ file in chunks: LAS/LAZ in and out, a
    file (not standard input), --chunk-points not 0."""
    return tiling is not None and tiling.chunk_points > 0 and _las_in_and_out(cloud, in_format, fmt)


def _las_in_and_out(cloud: Path, in_format: str | None, fmt: str) -> bool:
    """A LAS/LAZ file (not standard input) whose result is LAS/LAZ: what can be read in chunks."""
    ext = (in_format or cloud.suffix).lower().lstrip(".")
    return str(cloud) != "-" and ext in ("las", "laz") and fmt in ("las", "laz")


def _buffer(segmenter: Segmenter, tiling: Tiling) -> float:
    from kbs.tiles import default_buffer

    return default_buffer(segmenter, tiling.size) if tiling.buffer is None else tiling.buffer


def _segment_and_write(segmenter, cloud, pc, spilled, out_dir, t0, *, stdin, stem, fmt, points, js, html, to_stdout,
                       color_by, meshes, report, quiet, units, sensor, tiling, auto_tile, auto_scheduler, why_tiled,
                       say, tile_options=TileOptions(), chunk_note=None, force=False) -> ScanResult:
    rb = segmenter.rule_base
    name = "<stdin>" if stdin else str(cloud)
    if fmt != "ply":
        check_classes_fit(pc.source, rb.asprs_classes, name)
    scan_units = _scan_units(pc, units, name, quiet)
    t_read = time.perf_counter() - t0
    # the file's fault (3), said before the work (a spilled file's points were checked as they were read)
    too_big = coordinate_problem(pc.xyz * segmenter.scale(scan_units)) if spilled is None else None
    if too_big is not None:
        raise CloudFileError(name, too_big)
    if tiling is None and auto_tile and rb.tile is not None:
        tiling, why_tiled = _auto_tiling(segmenter, pc.xyz, scan_units, sensor, to_stdout, auto_scheduler,
                                         tile_options)
        if tiling is None and why_tiled and not quiet:
            click.echo(f"note: {name}: {why_tiled}", err=True)
    if tiling is not None and chunk_note is not None and not quiet:
        click.echo(f"note: {name}: {chunk_note}", err=True)
    if tiling is None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", SpacingWarning)
            warnings.simplefilter("always", CoordinateWarning)
            seg = segmenter.segment(pc.xyz, units=scan_units, sensor=sensor,
                                    progress=ProgressLines(name, _splits, quiet=quiet, start=t0))
        spacing = [w.message for w in caught if isinstance(w.message, SpacingWarning)]
        far = [w.message for w in caught if isinstance(w.message, CoordinateWarning)]
        for w in caught:
            if not isinstance(w.message, (SpacingWarning, CoordinateWarning)):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    else:
        if sensor is not None or (scan_units is not None and not np.array_equal(segmenter.scale(scan_units), np.ones(3))):
            raise click.UsageError("--tile runs a scan in the rule base's own units and sensor: --units, a unit "
                                   "other than the rule base's, and --sensor are not supported with --tile yet")
        from kbs.tiles.store import TileStore

        store = TileStore(out_dir / f"{cloud.stem}.tiles", segmenter)
        with warnings.catch_warnings(record=True) as caught:  # the whole cloud's spacing, judged once
            warnings.simplefilter("always", SpacingWarning)
            seg = _segment_tiled(segmenter, pc.xyz, cloud, tiling, quiet=quiet, t0=t0, store=store, spilled=spilled)
        spacing = [w.message for w in caught if isinstance(w.message, SpacingWarning)]
        far = []
        for w in caught:
            if not isinstance(w.message, SpacingWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    t1 = time.perf_counter()
    if not to_stdout:
        check_writable_folder(out_dir, create=True)  # checked by `kbs run` already; here for other callers
    from kbs.report.colors import rgb_fields

    f = segmenter.scale(scan_units)
    clusters, frame_note = _scan_frame(seg.clusters if spilled is None else [], f)  # streamed: written by pieces
    used_sensor = (np.asarray(segmenter.sensor, dtype=float) / f).tolist() if sensor is None else list(sensor)
    results = {"cluster": seg.cluster, "label": seg.label, "membership": seg.membership}
    # streamed (a spilled LAS/LAZ written as LAS/LAZ): the result's columns are files, read a chunk at a time
    fields = {} if spilled is not None else \
        result_fields(pc, {**results, **rgb_fields(seg.cluster if color_by == "cluster" else seg.label)})
    doc = {
        "kbs_version": __version__, "input": name, "n_points": len(pc), "n_dropped": pc.n_dropped,
        "rule_base": rb.name, "rule_file": rb.path, "units": rb.units, "sensor": used_sensor,
        # streamed: the summary too is written by pieces (the limits' ids are read as they are written)
        "label_names": seg.label_names, "summary": seg.summary() if spilled is None else None, "clusters": clusters,
        "explanation": seg.explanation.to_dict() if spilled is None else None,
    }
    if tiling is not None:
        doc["tiling"] = seg.tiling
        # where the tiling came from (the tiles: line says why): --tile, or the rule base's limits.tile
        doc["tiled_by"] = {"from": "--tile" if why_tiled is None else "limits.tile",
                           "buffer_from": "--buffer" if tiling.buffer is not None else "default"}
    if scan_units is not None or pc.crs is not None:
        doc["scan_units"] = {**(scan_units.to_dict() if scan_units is not None else {}),
                             "to_rule_base": f.tolist(), "crs": pc.crs}
    if frame_note:
        doc["notes"] = [frame_note]
    if spacing:
        doc["spacing"] = spacing[0].to_dict()
    comments = [line for line in (f"units {scan_units.name}" if scan_units is not None and
                                  scan_units.horizontal == scan_units.vertical else None,
                                  f"crs {_ascii_line(pc.crs)}" if pc.crs and _ascii_line(pc.crs) else None) if line]
    las = None
    if fmt != "ply":
        classes = rb.asprs_classes
        if spilled is not None:
            from kbs.tiles.streamed import CodesColumn

            codes = CodesColumn(seg.label, seg.cluster, seg.label_names, dict(classes)) if classes else None
        else:
            codes = class_codes(seg.label, seg.cluster, seg.label_names, classes) if classes else None
        if spilled is not None:
            from kbs.tiles.stream import ChunkedLas

            las = functools.partial(ChunkedLas, cloud, results, codes, chunk_points=tiling.chunk_points)
        else:
            las = functools.partial(_build_las, pc, results, codes)
    if to_stdout:
        run_id = write_result_stream(sys.stdout.buffer, f".{fmt}", pc.xyz, fields, run_id=new_run_id(), las=las,
                                     comments=comments)
    else:
        run_id = write_result_pair(points, js, pc.xyz, fields, doc, run_id=new_run_id(), las=las, comments=comments,
                                   pieces={k: v for k, v in seg.pieces().items() if k in doc} if spilled is not None
                                   else None)
        if spilled is not None and (meshes or report):  # the whole result, read back, for the meshes and the page
            written = read_result(js, require=("clusters", "explanation"))
            clusters, doc["explanation"] = list(written.clusters or ()), written.explanation
            seg = dataclasses.replace(seg, columns={k: np.asarray(v) for k, v in seg.columns.items()})
    if tiling is not None:
        store.remove()  # the result is written: the finished tiles are no longer needed
    t_write = time.perf_counter() - t1
    s = seg.summary()
    per_label = ", ".join(f"{k} {v:,}" for k, v in s["points_per_label"].items())
    say(f"{name}: {len(pc):,} points, rule base '{rb.name}' ({rb.strategy})")
    if scan_units is not None and segmenter.length_unit is not None:
        scaled = "" if np.array_equal(f, np.ones(3)) else f", scaled to the rule base's {segmenter.length_unit.name}"
        say(f"  units: {scan_units.name} ({scan_units.source}){scaled}")
    say(f"  {s['clusters']} clusters, {s['splits']} splits, {s['limits']} limits reached; points: {per_label}")
    for line in limit_lines(s["limits_by_kind"], Path(rb.path).name, result=str(js or "the result")):
        say(f"  {line}")
    say(f"  ground: {seg.explanation.ground_line()}")
    if tiling is not None:
        t = seg.tiling
        say(f"  tiles: {len(t['tiles'])} of {t['size']:g} x {t['size']:g} with a {t['buffer']:g} buffer; "
            f"{t['stitched']} clusters stitched across tile edges" + (f" ({why_tiled})" if why_tiled else ""))
    say(f"  time: {time.perf_counter() - t0:.2f} s (read {t_read:.2f}, segment {seg.seconds:.2f}, "
        f"write {t_write:.2f})")
    say(f"wrote {points} and {js}" if not to_stdout else f"wrote the {fmt.upper()} result to standard output")
    if fmt != "ply" and not rb.asprs_classes and not quiet:
        click.echo(f"note: rule base '{rb.name}' maps no label to an ASPRS class (asprs_classes): the classification "
                   "is the input's", err=True)
    if meshes:
        from kbs.report.meshes import write_meshes

        say(write_meshes(out_dir / f"{stem}-meshes", pc.xyz, seg.cluster, seg.label,
                         seg.label_names, run_id=run_id, force=force).describe())
    if report:
        from kbs.report.html import write_report

        try:
            with replacing(html) as (tmp,):
                write_report(tmp, pc.xyz, seg.cluster, seg.label, seg.label_names, doc["explanation"], clusters,
                             title=f"{Path(name).name} — rule base '{rb.name}'",
                             grid=None if pc.shape is None else (pc.shape, pc.index))
                with open(tmp, "a", encoding="utf-8") as stream:  # marks the page as kbs's own (--force)
                    stream.write(f"<!-- {RUN_ID_COMMENT} {run_id} -->\n")
        except OSError as exc:
            raise CloudFileError(str(html), f"cannot write: {exc.strerror or exc}") from exc
        say(f"wrote {html}")
    if not quiet:
        for w in [*far, *spacing]:
            click.echo(f"kbs: warning: {name}: {w}", err=True)
        ground_note = seg.explanation.ground.note
        for note in seg.explanation.notes + ([ground_note] if ground_note is not None else []):
            click.echo(f"note: {note}", err=True)
        if getattr(seg, "read_note", None):
            click.echo(f"note: {name}: {seg.read_note}", err=True)
    return ScanResult(cloud, len(pc), s["clusters"], t_read, seg.seconds, t_write)


def _segment_tiled(segmenter: Segmenter, xyz: np.ndarray, cloud: Path, tiling: Tiling, *, quiet: bool, t0: float,
                   store=None, spilled=None):
    from kbs.tiles import segment_tiled
    from kbs.tiles.run import SchedulerError

    lines = ProgressLines(str(cloud), lambda n: f"{n:,} tile{'s' if n != 1 else ''} done", quiet=quiet, start=t0)
    if tiling.scheduler is not None:  # Dask logs every worker's start and stop at INFO: not kbs's news
        import logging

        logging.getLogger("distributed").setLevel(logging.ERROR)  # and warns of a slow event loop under load

    def progress(message: str) -> None:
        if message.startswith(("Dask dashboard", "resumed")):
            if not quiet:
                click.echo(f"kbs: {message}", err=True)
        else:
            lines()

    try:
        from kbs.tiles.copc import CopcCloud

        if isinstance(spilled, CopcCloud):
            from kbs.tiles.streamed import segment_copc

            return segment_copc(segmenter, spilled, store, scheduler=tiling.scheduler, workers=tiling.workers,
                                progress=progress, resume=tiling.resume)
        if spilled is not None:
            from kbs.tiles.streamed import segment_streamed

            return segment_streamed(segmenter, spilled, store, scheduler=tiling.scheduler, workers=tiling.workers,
                                    progress=progress, resume=tiling.resume)
        return segment_tiled(segmenter, xyz, tiling.size, tiling.buffer, scheduler=tiling.scheduler,
                             workers=tiling.workers, progress=progress, store=store, resume=tiling.resume)
    except SchedulerError as exc:
        raise click.BadParameter(str(exc), param_hint="--scheduler") from exc


def _build_las(pc: PointCloud, results: dict, codes, run_id: str):
    from kbs.io.las import build_las

    return build_las(pc.xyz, pc.fields, results, classification=codes, run_id=run_id, source=pc.source, crs=pc.crs)


def _splits(n: int) -> str:
    return f"{n:,} split{'s' if n != 1 else ''}"


def time_table(results: list[ScanResult | ScanFailure], t_load: float, t_total: float, at_once: int = 1) -> str:
    """The per-scan time table `kbs run` prints after several scans (aligned columns, then the
    median segmentation time and the total, which includes loading the rule base; ``at_once``: how
    many scans were segmented side by side)."""
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
    side = f", {at_once} scans at a time" if at_once > 1 else ""
    lines.append(f"{head}: {median}total {t_total:.2f} s{side} (rule base loaded once, {t_load:.2f} s)")
    return "\n".join(lines)


@click.command()
@click.option("--rules", "rules", required=True, metavar="NAME|FILE",
              help=f"A shipped rule base ({', '.join(shipped_rule_bases())}) or a rule file.")
@click.argument("clouds", nargs=-1, required=True, type=PathArg(path_type=Path, readable=False),
                metavar="CLOUD...")
@click.option("--sensor", callback=_vector3, metavar="X,Y,Z",
              help="Sensor position (overrides the rule base's), in the scan's coordinates and units.")
@click.option("--out", "out_dir", type=PathArg(file_okay=False, path_type=Path, allow_dash=True),
              default=Path("kbs-out"), show_default=True,
              help="Directory for <stem>.ply (or .las/.laz) and <stem>.json (created if needed; checked for writing "
              "before any segmentation). '-': the points to standard output (one scan; no JSON, no meshes, no report; "
              "the summary on stderr).")
@click.option("--out-format", "out_format", type=click.Choice(["ply", "las", "laz"]), default=None,
              help="Format of the result's points: ply, or las/laz (the input's records with the ASPRS classification "
              "the rule base's asprs_classes gives each label, and cluster, label, membership as extra bytes). "
              "Default: the input's for LAS/LAZ input, else ply.")
@click.option("--in-format", "in_format", type=click.Choice([e.lstrip(".") for e in SUPPORTED_EXTENSIONS]),
              default=None, help="Read every CLOUD as this format, whatever its name says; needed for '-' "
              "(standard input).")
@click.option("--units", type=click.Choice(list(LENGTH_UNITS)), default=None,
              help="Unit of the scans' coordinates, for files that do not declare one (LAS/LAZ declare it in their "
              "CRS, PLY/PCD in a 'units' comment); overrides the file's. The points are scaled to the rule base's "
              "unit before segmenting; the output points are the input's.")
@force_option
@plugin_option
@click.option("--color-by", "color_by", type=click.Choice(["cluster", "label"]), default="cluster", show_default=True,
              help="Colour of each vertex (red green blue) in a PLY result: one per output cluster or per label.")
@click.option("--meshes", is_flag=True, help="Also write DIR/<stem>-meshes/: a convex hull per obstacle cluster "
              "(obstacle-<index>.ply) and the ground surface (ground.ply), each with the result's run id; checked "
              "before the work: a folder holding other files is refused, a mesh kbs did not write is replaced only "
              "with --force.")
@click.option("--report", is_flag=True, help="Also write DIR/<stem>.html: a self-contained report (3D view by "
              "cluster or label, centres and eigen-boxes, APD curve, the explanation tree; opens offline).")
@click.option("-j", "--jobs", type=click.IntRange(min=-1), default=-1, show_default=True, callback=_jobs,
              help="Processes computing the UFP-ONC splits side by side; -1: one per available core (and at most "
              "that many). With several "
              "scans (not --tile, --scheduler), up to this many scans are segmented at once instead, each in a process "
              "of its own. The result does not depend on it.")
@click.option("--tile", "tile", type=FiniteFloatRange(min=0, min_open=True), metavar="SIZE",
              help="Segment in square tiles of SIZE (cloud units) in the ground plane, each with a buffer, and "
              "stitch them: clusters crossing a tile edge become one.")
@click.option("--no-tile", "no_tile", is_flag=True,
              help="Run the whole cloud at once even when it is wider than the rule base's limits.tile.wider_than "
              "(which otherwise segments it in tiles of limits.tile.size, as --tile does).")
@click.option("--buffer", "buffer", type=FiniteFloatRange(min=0), metavar="B",
              help="How far each tile reaches beyond its core, with --tile or for the tiles of the rule base's "
              "limits.tile (default: a tenth of the tile size, at least twice the local ground surface's radius).")
@click.option("--scheduler", "scheduler", metavar="ADDRESS|local",
              help="Run the tiles (with --tile, or of the rule base's limits.tile when the cloud is wider than its "
              "wider_than) or the scans (a folder, several scans) as Dask tasks: on the "
              "scheduler at ADDRESS (tcp://host:8786), or on a LocalCluster of -j workers ('local'; -1: one per "
              "core). Needs pip install 'kbs[dask]'. Without it they run one after the other in this process. The "
              "result is the same.")
@click.option("--resume", is_flag=True, help="With --tile, or for the tiles of the rule base's limits.tile: take the "
              "tiles an earlier run that failed kept in DIR/<stem>.tiles/ (same cloud, rule base and grid) and segment "
              "only the others.")
@click.option("--chunk-points", "chunk_points", type=click.IntRange(min=0), metavar="N",
              help="With --tile, or the tiles of the rule base's limits.tile, a LAS/LAZ scan written as LAS/LAZ: "
              "read and write N points at a time, the tiles "
              f"spilled to a temporary folder in DIR (default {1_000_000:,}); 0: read the whole file into memory.")
@click.pass_context
def run(ctx: click.Context, rules: str, clouds: tuple[Path, ...], sensor, out_dir: Path, plugins: tuple[Path, ...],
        color_by: str = "cluster", meshes: bool = False, report: bool = False, jobs: int = -1,
        force: bool = False, out_format: str | None = None, in_format: str | None = None,
        units: str | None = None, tile: float | None = None, buffer: float | None = None,
        scheduler: str | None = None, resume: bool = False, chunk_points: int | None = None,
        no_tile: bool = False) -> None:
    """Segment each CLOUD with a rule base; write DIR/<stem>.ply (per-vertex scalar_cluster,
    scalar_label, scalar_membership) or, with --out-format las|laz (the default for LAS/LAZ input),
    DIR/<stem>.las|.laz (ASPRS classification, cluster, label, membership), and DIR/<stem>.json
    (label names, clusters, the explanation tree).

    A CLOUD that is a directory stands for every point-cloud file directly inside it, in name
    order; '-' is standard input (give --in-format). The rule base is loaded once for all the
    scans; with several, a table of the time each took follows. Several scans are segmented -j at
    a time, each in a process of its own (what each prints comes in scan order); one scan uses the
    -j processes for its splits. A scan that fails is reported and the others go on; the exit code
    is then the first failure's.

    Units: a scan whose unit is known (its file's CRS or 'units' comment, --units) is scaled to
    the rule base's unit before segmenting; a warning says when its point spacing does not fit
    the rule base (wrong units?).

    Outputs: never an input file; an existing file that kbs did not write (no kbs run id) only
    with --force; an earlier kbs result is replaced. Each pair is written whole or not at all.
    On a stderr that is not a terminal, a progress line every 10 s (KBS_PROGRESS_SECONDS); `kbs
    -q run` (the option before the command) prints nothing but errors."""
    quiet = ctx.obj.get("quiet", False)
    t0 = time.perf_counter()
    if not quiet:
        progress_interval()  # a bad KBS_PROGRESS_SECONDS is a usage error before any work
    to_stdout = str(out_dir) == "-"
    if to_stdout and (meshes or report):
        raise click.UsageError("--out - writes the points to standard output: --meshes and --report need a folder")
    if report:  # known before any segmentation
        require("plotly", "report", "--report (the HTML report)")
    if "-" in map(str, clouds) and in_format is None:
        raise click.UsageError("reading a scan from standard input ('-') needs --in-format (ply, pcd, las, ...)")

    def skipped(path: Path, why: str) -> None:
        if not quiet:
            click.echo(f"kbs: skipped {path}: {why}", err=True)

    scans = scan_paths(clouds, on_skip=skipped)
    many = len(scans) > 1 or any(Path(c).is_dir() for c in clouds)
    scan_scheduler = auto_scheduler = None
    if tile is None and scheduler is not None and many:  # the scans themselves as Dask tasks
        _check_scheduler(scheduler)
        scan_scheduler, scheduler = (scheduler, None if jobs == -1 else jobs), None
    if no_tile and tile is not None:
        raise click.UsageError("--no-tile and --tile contradict each other: give one")
    if tile is None and scheduler is not None:  # one scan: the tiles of its rule base's limits.tile on Dask
        if no_tile:
            raise click.UsageError("--scheduler runs the tiles of one scan (or several scans) on Dask; --no-tile runs "
                                   "the scan whole in this process: give one")
        if to_stdout:
            raise click.UsageError("--out - runs the scan whole (tiles write a result folder): --scheduler is not "
                                   "used with --out -")
        _check_scheduler(scheduler)
        auto_scheduler, scheduler = (scheduler, None if jobs == -1 else jobs), None
    tiling = _tiling(tile, buffer, scheduler, jobs, resume, chunk_points)
    tile_options = TileOptions(buffer, resume, chunk_points)
    auto_given = tile_options.given() if tile is None else []  # for the tiles of the rule base's limits.tile
    if chunk_points and out_format == "ply":
        raise click.UsageError("--chunk-points reads and writes a LAS/LAZ scan in chunks: it is not used with "
                               "--out-format ply")
    if auto_given:
        if no_tile:
            raise click.UsageError(f"{_listed(auto_given)} appl{'ies' if len(auto_given) == 1 else 'y'} to the tiles "
                                   f"of the rule base's limits.tile; --no-tile runs the scan whole: give one")
        if to_stdout:
            raise click.UsageError(f"--out - runs the scan whole (tiles write a result folder): "
                                   f"{_not_used(auto_given)} with --out -")
        if sensor is not None:
            raise click.UsageError(f"--sensor runs the scan whole (tiles need the rule base's own sensor, as with "
                                   f"--tile): {_not_used(auto_given)} with --sensor")
    if to_stdout and len(scans) != 1:
        raise click.UsageError(f"--out - writes one scan to standard output; {len(scans)} scans given")
    if to_stdout and tiling is not None:
        raise click.UsageError("--tile writes a result folder: --out - is not supported with --tile")
    split_jobs = 1 if (tiling is not None and tiling.scheduler is not None) or scan_scheduler else jobs  # Dask does the work
    with Segmenter(rules, jobs=split_jobs, plugins=plugins) as segmenter:  # workers kept for all scans
        if auto_scheduler is not None and segmenter.rule_base.tile is None:
            raise click.UsageError(f"--scheduler only applies to a tiled run: give --tile SIZE too (or several scans: a "
                                   f"folder's scans run as Dask tasks); rule base '{segmenter.rule_base.name}' has no "
                                   f"limits.tile to tile a wide cloud by itself")
        if auto_given and segmenter.rule_base.tile is None:
            raise click.UsageError(f"{_listed(auto_given)} only appl{'ies' if len(auto_given) == 1 else 'y'} to a "
                                   f"tiled run: give --tile SIZE too; rule base '{segmenter.rule_base.name}' has no "
                                   f"limits.tile to tile a wide cloud by itself")
        if not quiet:
            for w in segmenter.rule_base.warnings:  # `kbs rules check` quotes the line
                click.echo(f"kbs: warning: {w.pos}: {w.message}", err=True)
        created = [] if to_stdout else check_writable_folder(out_dir, create=True)  # before any segmentation
        try:
            _run_scans(segmenter, scans, None if to_stdout else out_dir, t0, color_by=color_by, meshes=meshes,
                       report=report, quiet=quiet, inputs=InputFiles(scans), force=force, out_format=out_format,
                       in_format=in_format, units=units, sensor=sensor, tiling=tiling, scheduler=scan_scheduler,
                       auto_tile=not no_tile, auto_scheduler=auto_scheduler, tile_options=tile_options)
        except BaseException as exc:
            if not (isinstance(exc, click.exceptions.Exit) and exc.exit_code == 0):
                remove_if_empty(created)  # a failed run leaves no new, empty --out folder
            raise


def _tiling(tile: float | None, buffer: float | None, scheduler: str | None, jobs: int,
            resume: bool = False, chunk_points: int | None = None) -> Tiling | None:
    """The --tile/--buffer/--scheduler/--resume/--chunk-points options, checked together (usage
    errors, exit 2). Without --tile: None (--buffer, --resume and --chunk-points then apply to the
    tiles of the rule base's limits.tile, checked by :func:`run` once the rule base is loaded)."""
    if tile is None:
        if scheduler is not None:
            raise click.UsageError("--scheduler only applies to a tiled run: give --tile SIZE too (or several scans: "
                                   "a folder's scans run as Dask tasks)")
        return None
    if scheduler is not None:
        _check_scheduler(scheduler)
    from kbs.tiles.stream import DEFAULT_CHUNK_POINTS

    return Tiling(size=tile, buffer=buffer, scheduler=scheduler, workers=None if jobs == -1 else jobs, resume=resume,
                  chunk_points=DEFAULT_CHUNK_POINTS if chunk_points is None else chunk_points)


def _check_scheduler(scheduler: str) -> None:
    """--scheduler: an address (or 'local'), and Dask installed (usage errors, exit 2)."""
    if not scheduler.strip():
        raise click.BadParameter("give a Dask scheduler address (tcp://host:8786) or 'local'",
                                 param_hint="--scheduler")
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise click.UsageError(f"--scheduler needs Dask ({exc}): pip install 'kbs[dask]', or leave "
                               f"--scheduler out to run in this process") from exc


def _run_scans(segmenter, scans, out_dir: Path, t0: float, scheduler: tuple[str, int | None] | None = None,
               **options) -> None:
    if len(scans) == 1 and scheduler is None:  # the clock starts with the command: its read time includes loading the rule base
        run_scan(segmenter, scans[0], out_dir, t0=t0, **options)
        return
    t_load = time.perf_counter() - t0
    results: list[ScanResult | ScanFailure] = []
    at_once = 1 if scheduler is not None else scans_at_once(segmenter, scans, out_dir, options)
    if scheduler is not None:
        results = _scans_on_dask(segmenter, scans, out_dir, *scheduler, options)
    elif at_once > 1:
        results = _scans_in_processes(segmenter, scans, out_dir, at_once, options)
    else:
        results = [_one_scan(segmenter, scan, out_dir, options) for scan in scans]
    if not options.get("quiet"):
        click.echo(time_table(results, t_load, time.perf_counter() - t0, at_once=at_once))
    failures = [r.exit_code for r in results if isinstance(r, ScanFailure)]
    if failures:
        raise click.exceptions.Exit(failures[0])


def _one_scan(segmenter: Segmenter, scan: Path, out_dir: Path, options: dict) -> ScanResult | ScanFailure:
    """One scan of several, in this process: a failure is reported as the command would report it
    alone, and the other scans go on."""
    try:
        return run_scan(segmenter, scan, out_dir, **options)
    except KbsError as exc:
        click.echo(f"kbs: error: {exc}", err=True)
        return ScanFailure(scan, int(exc.exit_code))


def scans_at_once(segmenter: Segmenter, scans: list[Path], out_dir: Path | None, options: dict) -> int:
    """How many of several scans ``kbs run`` segments side by side, each in a process of its own:
    as many as the segmenter's ``jobs`` (the split processes it would start otherwise), at most one
    per scan; 1 (one after the other, the splits in ``jobs`` processes) for ``--tile`` (whose tiles
    the split processes share), standard input or output, and where processes cannot be forked."""
    import multiprocessing

    jobs = segmenter.processes  # -1 already resolved to the available cores
    if (len(scans) < 2 or jobs < 2 or out_dir is None or options.get("tiling") is not None
            or any(str(scan) == "-" for scan in scans) or "fork" not in multiprocessing.get_all_start_methods()):
        return 1
    return min(jobs, len(scans))


#: the segmenter of a process that segments whole scans (set by :func:`_scan_worker_start`)
_SCAN_WORKER: dict = {}


def _scan_worker_start(segmenter: Segmenter, jobs: int) -> None:
    """A scan process's start (forked: the rule base is the parent's, not read again): its own
    segmenter with ``jobs`` split processes; Ctrl-C is for the parent, which stops the scan
    processes with SIGTERM; a SIGTERM during a scan ends it as a SIGTERM ends ``kbs run`` (the
    outputs being written are removed), between scans the process just ends."""
    import signal

    from kbs.knowledge.interpreter import unblock_stop_signals

    _SCAN_WORKER["segmenter"] = segmenter.with_jobs(jobs)
    _SCAN_WORKER["busy"] = False
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _scan_worker_sigterm)
    unblock_stop_signals()  # forked with them blocked (start_with_signals_blocked)


def _scan_worker_sigterm(signum: int, frame: object) -> None:
    import os

    from kbs.errors import Terminated

    if _SCAN_WORKER.get("busy"):  # the scan unwinds (its outputs' temporary files removed), then the process ends
        _SCAN_WORKER["stop"] = 128 + signum
        raise Terminated
    os._exit(128 + signum)


def _scan_in_worker(scan: Path, out_dir: Path, options: dict) -> tuple[ScanResult | None, int | None, str, str, str]:
    """One scan in a scan process (:func:`_captured`)."""
    import os

    _SCAN_WORKER["busy"] = True
    try:
        return _captured(_SCAN_WORKER["segmenter"], scan, out_dir, options)
    finally:
        _SCAN_WORKER["busy"] = False
        if _SCAN_WORKER.get("stop"):  # stopped by the parent: no next scan
            os._exit(_SCAN_WORKER["stop"])


def _scans_in_processes(segmenter: Segmenter, scans: list[Path], out_dir: Path, at_once: int,
                        options: dict) -> list[ScanResult | ScanFailure]:
    """Several scans ``at_once`` at a time, each read, segmented and written whole in a forked
    process with its own segmenter (the split processes shared out among them); what each printed
    is printed here in scan order, as one run after the other would print it. The results are those
    of one process (a scan's segmentation does not depend on the others). A scan process that dies
    (killed, out of memory) leaves its scan to this process. Ctrl-C or SIGTERM here stops the scan
    processes (SIGTERM: the outputs they were writing are removed) after printing what the scans
    already finished printed."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    from kbs.knowledge.interpreter import start_with_signals_blocked

    jobs = max(1, segmenter.processes // at_once)
    pool = ProcessPoolExecutor(max_workers=at_once, mp_context=multiprocessing.get_context("fork"),
                               initializer=_scan_worker_start, initargs=(segmenter, jobs))
    start_with_signals_blocked(pool)  # a SIGTERM while they are forked waits for their own handler
    futures: list[Any] = []
    for scan in scans:
        try:
            futures.append(pool.submit(_scan_in_worker, scan, out_dir, options))
        except BrokenProcessPool:  # a scan process died already (killed at its start): the rest here
            futures.append(None)
    results: list[ScanResult | ScanFailure] = []
    try:
        for scan, future in zip(scans, futures):
            try:
                if future is None:
                    raise BrokenProcessPool("not submitted")
                outcome = future.result()
            except BrokenProcessPool:  # its process died: the scan again, here
                results.append(_one_scan(segmenter, scan, out_dir, options))
                continue
            results.append(_reported(scan, outcome))
    except BaseException:  # Ctrl-C, SIGTERM: what finished is said, the rest stopped
        for scan, future in zip(scans[len(results):], futures[len(results):]):
            if future is None or not future.done() or future.cancelled() or future.exception() is not None:
                break
            _reported(scan, future.result())
        for process in list(getattr(pool, "_processes", {}).values()):
            process.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return results


def _captured(segmenter: Segmenter, scan: Path, out_dir: Path,
              options: dict) -> tuple[ScanResult | None, int | None, str, str, str]:
    """One scan in a process other than the command's: what :func:`run_scan` returns (or the exit
    code and message of its KbsError) and what it printed on stdout and stderr, for the command to
    print in scan order (:func:`_reported`)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    result, code, message = None, None, ""
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            result = run_scan(segmenter, scan, out_dir, **options)
        except KbsError as exc:
            code, message = int(exc.exit_code), str(exc)
    return result, code, message, out.getvalue(), err.getvalue()


def _reported(scan: Path, outcome: tuple) -> ScanResult | ScanFailure:
    """Print what a scan run elsewhere printed (:func:`_captured`), and its error if it failed."""
    result, code, message, out, err = outcome
    click.echo(out, nl=False)
    click.echo(err, nl=False, err=True)
    if result is None:
        click.echo(f"kbs: error: {message}", err=True)
        return ScanFailure(scan, code if code is not None else int(ExitCode.INTERNAL))
    return result


def _scan_task(rules: str, sensor: tuple[float, float, float], plugins: tuple[str, ...], scan: Path,
               out_dir: Path, options: dict) -> tuple[ScanResult | None, int | None, str, str, str]:
    """One scan of ``kbs run DIR/ --scheduler`` on a Dask worker (:func:`_captured`)."""
    from kbs.tiles.run import worker_segmenter

    return _captured(worker_segmenter(rules, sensor, plugins), scan, out_dir, options)


def _scans_on_dask(segmenter: Segmenter, scans: list[Path], out_dir: Path, scheduler: str, workers: int | None,
                   options: dict) -> list[ScanResult | ScanFailure]:
    """The scans of ``kbs run DIR/ --scheduler`` as Dask tasks (one per scan, each on a worker's own
    segmenter); what each printed is printed here in scan order, as one run after the other would."""
    import logging
    import os

    from kbs.tiles.run import SchedulerError, dask_client

    logging.getLogger("distributed").setLevel(logging.ERROR)
    try:
        client = dask_client(scheduler, workers)
    except SchedulerError as exc:
        raise click.BadParameter(str(exc), param_hint="--scheduler") from exc
    results: list[ScanResult | ScanFailure] = []
    try:
        if not options.get("quiet"):
            click.echo(f"kbs: Dask dashboard: {client.dashboard_link}", err=True)
        spec = (segmenter.rule_base.path, tuple(segmenter.sensor), tuple(segmenter.plugins))
        futures = [client.submit(_scan_task, *spec, scan, out_dir, options, retries=1, pure=False,
                                 key=f"kbs-scan-{scan.stem}-{os.urandom(6).hex()}") for scan in scans]
        for scan, future in zip(scans, futures):
            try:
                outcome = future.result()
            except Exception as exc:  # noqa: BLE001 - the task died twice (a worker lost), or a bug in it
                raise_if_interrupted(exc)  # Ctrl-C inside a compiled kernel: not this part's failure
                outcome = (None, int(ExitCode.INTERNAL), f"{type(exc).__name__}: {exc}", "", "")
            results.append(_reported(scan, outcome))
    finally:
        cluster = client.cluster if scheduler == "local" else None
        client.close()
        if cluster is not None:
            cluster.close()
    return results


def _depth(ctx, param, value):
    if value is None or value == "all":
        return value
    try:
        depth = int(value)
    except ValueError:
        depth = -1
    if depth < 0:
        raise click.BadParameter(f"expected a number of levels (0 or more) or 'all', got {value!r}")
    return depth


@click.command()
@click.argument("result", type=PathArg(path_type=Path, readable=False))
@click.option("--cluster", "cluster_id", metavar="ID", help="Say why this cluster ended as it did (e.g. c0.2): the "
              "rules and labels evaluated on it, every check, then the tree below it.")
@click.option("--depth", callback=_depth, metavar="N|all",
              help="Show the tree to N levels below the root (or below --cluster); 'all': the whole tree. "
              f"Default: the whole tree when it has at most {TREE_LINES} clusters, else the levels that fit "
              f"in {TREE_LINES} lines.")
def explain(result: Path, cluster_id: str | None, depth: int | str | None) -> None:
    """Print what a `kbs run` RESULT.json did, grouped (rules, labels by outcome, checks with their
    docs), then its explanation tree; or why one cluster ended as it did (--cluster). Deeper
    parts of a large tree are folded into counts: --depth and --cluster unfold them."""
    expl = Explanation.from_result(read_result(result, require=("explanation",)))
    if cluster_id is not None and cluster_id not in expl.records:
        hint = did_you_mean(cluster_id, list(expl.records))
        raise click.BadParameter(f"no cluster {cluster_id!r} in {result}" + (f"; did you mean {hint!r}?" if hint else ""),
                                 param_hint="--cluster")
    start = cluster_id or expl.root
    levels = None if depth == "all" else int(depth) if depth is not None else expl.fitting_depth(start)
    if cluster_id is None:
        click.echo(f"rule base '{expl.rule_base}' ({expl.rule_file}), strategy {expl.strategy}; "
                   f"labels: {', '.join(expl.label_names)}")
        if expl.ground:
            click.echo(expl.ground_text())
        for line in expl.summary():
            click.echo(line)
        if expl.sweep:
            click.echo("global strategy, the K-partitions of the scene judged in turn:")
            for line in expl.sweep_lines():
                click.echo(f"  {line}")
        lines = expl.tree_lines(depth=levels)
    else:
        click.echo(expl.why(cluster_id))
        rec = expl.records[cluster_id]
        if not rec.children:
            return
        lines = expl.tree_lines(cluster_id, levels)[1:]
    shown = len(lines) - (cluster_id is None)  # the clusters below the root or --cluster
    total = sum(1 for _ in expl.walk(start)) - 1
    folded = "" if shown == total else (f" (to depth {levels}, {shown:,} of its {total:,} clusters: --depth N or "
                                         f"--depth all unfolds it, --cluster ID shows one branch)")
    click.echo(f"tree{' below ' + cluster_id if cluster_id else ''}{folded}:")
    for line in lines:
        click.echo(line)


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
        post = f", post {' > '.join(step.key for step in rb.post)}" if rb.post else ""
        click.echo(f"{f}: ok — '{rb.name}', {len(rb.checks)} checks, {len(rb.rules)} rules, "
                   f"labels {', '.join(labels)}, strategy {rb.strategy}{post}"
                   + (f"; {n_warn} warning{'s' if n_warn != 1 else ''}" if n_warn else ""))
        for w in rb.warnings:
            click.echo(w.format(), err=True)
    if bad:
        for problem in bad:
            click.echo(problem.format(), err=True)
        n = sum(len(e.problems) for e in bad)
        click.echo(f"kbs: error: {n} problem{'s' if n != 1 else ''} in {len(bad)} rule file"
                   f"{'s' if len(bad) != 1 else ''}", err=True)
        raise click.exceptions.Exit(int(ExitCode.RULES))


def _schema_path() -> Path:
    from importlib import resources

    from kbs.knowledge.rulebase import SCHEMA_FILE

    return Path(str(resources.files("kbs.rules").joinpath(SCHEMA_FILE))).resolve()


_SCHEMA_LINE = re.compile(r"^(#\s*yaml-language-server:\s*\$schema=)(\S+)(.*)$")


@rules.command("show")
@click.argument("name")
@click.option("--engine", "engine", is_flag=True,
              help="Print the engine settings the rule base uses instead, one a line: value (and the default when "
                   "it differs), allowed values, what it does.")
@plugin_option
def rules_show(name: str, engine: bool, plugins: tuple[Path, ...]) -> None:
    """Print a shipped rule base (or a rule file). Its editor schema line points at the installed
    schema (a file URI), so that `kbs rules show outdoor > my.yaml` keeps completion and checks in
    editors that read it (yaml-language-server). The rule base is validated first (with the
    predicates of --plugin): a file that is not a valid rule file is reported as by `kbs rules
    check` (exit 4) and not printed."""
    rb = load_rule_base(name, _registry(plugins))
    if engine:
        from kbs.knowledge.engine_settings import settings_lines

        click.echo(f"engine settings of '{rb.name}' ({rb.path}):")
        for line in settings_lines(rb.engine):
            click.echo(f"  {line}")
        return
    _, text = resolve(name)
    first, sep, rest = text.partition("\n")
    m = _SCHEMA_LINE.match(first)
    if m and "://" not in m.group(2) and not Path(m.group(2)).is_absolute():
        text = f"{m.group(1)}{_schema_path().as_uri()}{m.group(3)}{sep}{rest}"
    click.echo(text, nl=not text.endswith("\n"))


@rules.command("schema")
@click.option("--json", "as_json", is_flag=True, help="Print the schema itself instead of its path.")
@click.option("--engine", "engine", is_flag=True,
              help="Print the settings of the rule file's engine: section instead, one a line: name, default, "
                   "allowed values, what it does.")
def rules_schema(as_json: bool, engine: bool) -> None:
    """Print the installed path of the rule files' JSON Schema (for editors: yaml-language-server's
    `$schema=` line, VS Code's yaml.schemas)."""
    if as_json and engine:
        raise click.UsageError("--json and --engine exclude each other")
    if engine:
        from kbs.knowledge.engine_settings import settings_lines

        click.echo("engine: section of a rule file (name = default: allowed values. what it does):")
        for line in settings_lines():
            click.echo(f"  {line}")
        return
    path = _schema_path()
    click.echo(path.read_text(encoding="utf-8") if as_json else str(path), nl=not as_json)


@rules.command("list")
def rules_list() -> None:
    """List the shipped rule bases, then the examples installed with kbs (examples/NAME: `kbs rules
    show examples/NAME > NAME.yaml` copies one, `kbs run --rules examples/NAME` runs it)."""
    for name in shipped_rule_bases():
        rb = load_rule_base(name)
        click.echo(f"{name:16} {rb.description.splitlines()[0] if rb.description else ''}")
    _list_examples()


def _list_examples() -> None:
    """The example rule files, with the plugin an example needs at its installed path."""
    import yaml

    from kbs.knowledge.rulebase import example_rule_bases, examples_folder

    folder = examples_folder()
    names = example_rule_bases()
    if folder is None or not names:
        return
    width = max(16, *(len(n) + 1 for n in names))
    for name in names:
        text = resolve(name)[1]
        doc = yaml.safe_load(text) or {}
        line = " ".join(str(doc.get("description", "")).split())
        plugin = re.search(r"--plugin examples/plugins/(\S+\.py)", text)  # the example's own header says which
        if plugin:
            line += f" (with --plugin {folder / 'plugins' / plugin.group(1)})"
        click.echo(f"{name:{width}} {line}")
    click.echo(f"examples installed in {folder} (rules/, plugins/, data/): `kbs rules show examples/NAME > NAME.yaml` "
               "copies one, `kbs run --rules examples/NAME` runs it")


@click.command()
@plugin_option
def predicates(plugins: tuple[Path, ...]) -> None:
    """List every predicate a rule file may use, with unit, parameters and doc."""
    for p in _registry(plugins):
        uses = ("  (uses the local ground surface: post.relabel only)" if p.needs_ground_model
                else "  (uses the ground)" if p.needs_ground else "")
        uses += "  (needs a plane: undefined on a degenerate cluster)" if p.needs_plane else ""
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
