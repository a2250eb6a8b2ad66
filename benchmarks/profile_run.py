"""Profile: where the time of ``kbs run`` goes, stage by stage, on real scans.

For each scan, prints a markdown table of the stages of ``kbs run`` (seconds, median over the
repeats, and % of the total): process start-up and imports, loading the rule base, reading the
file, the initial UFP-ONC partition of the scene, the UFP-ONC splits (voxel reduction / fit-set
preparation, fuzzy c-means, Gath-Geva, validity criteria, memberships of all points), the
predicates (connexity apart), the local ground surface and the post steps, writing the PLY and
the JSON; then the counts behind them (UFP-ONC calls, fit-set points, FCM and GG iterations, K
values tried, predicate measures) and the hottest functions of one run under cProfile.

How a stage is measured: the library runs in-process as ``kbs run -j 1`` runs it (``read_cloud``,
``load_rule_base``, ``Interpreter(rb, jobs=1).run(xyz)``, the writers of ``cli/run.py``), with
the functions of :data:`STAGES` wrapped by a timer. A stage's time is the cumulative time of its
functions (what cProfile calls cumtime), minus the time of any other stage function called inside
them, so nothing is counted twice (a connexity measure inside a predicate counts as connexity, not
as predicate; FCM inside a split counts as FCM, not as the split's "other"). Predicates and
cluster descriptors measured during the post steps count as the post step that asked for them.
The wrappers cost about a microsecond per call; the cProfile run (``--cprofile``, one extra
run) is only for the function table, its times are inflated by the profiler. Each run is a fresh
process (so lazy imports fall where ``kbs run`` pays them), and so is each start-up measurement.

Functions are looked up by name (module and qualified name, with alternatives): a stage whose
functions are all absent prints "n/a", and the run goes on.

Usage:
    python benchmarks/profile_run.py                       # the default set of scans
    python benchmarks/profile_run.py --scan ../shared/data/isprs/samp21-utm.pcd --rules airborne
    python benchmarks/profile_run.py --scan isprs-tile:130000 --rules airborne --repeats 1
A scan ``isprs-tile:N`` is an airborne tile of at least N points made from the ISPRS samples
(see :func:`make_isprs_tile`), written once as a .npy under ``--tile-dir``.
"""
from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

DEFAULT_SCANS = [
    (DATA / "semantickitti" / "000001.points.npy", "outdoor"),
    (DATA / "semantickitti-seq00" / "seq00_000000.bin", "outdoor"),
    ("isprs-tile:500000", "airborne"),
    (DATA / "mosd" / "learn0.pcd", "planar_contest"),
]

# -- stages ------------------------------------------------------------------------------------

#: stage key -> (group, row label, candidate functions "module:qualname"). Every candidate found
#: is wrapped; nested calls of the same stage are charged once. Keys under "ufp." are the parts of
#: a UFP-ONC call: they are charged to "initial." or "split." according to the call they run in.
STAGES: dict[str, tuple[str, str, list[str]]] = {
    "rules": ("io", "load the rule base", ["kbs.knowledge.rulebase:load_rule_base", "kbs.knowledge:load_rule_base"]),
    "read": ("io", "read the file", ["kbs.io.readers:read_cloud", "kbs.io:read_cloud"]),
    "ufp": ("ufp", "UFP-ONC, other (checks, new prototypes, bookkeeping)",
            ["kbs.inference.ufp_onc:ufp_onc", "kbs.inference:ufp_onc"]),
    "ufp.fitset": ("ufp", "voxel reduction / fit-set preparation",
                   ["kbs.inference.ufp_onc:prepare_fit_set", "kbs.inference.voxel:voxel_reduce",
                    "kbs.inference.voxel:auto_voxel_size", "kbs.inference.kernels:Moments.build"]),
    "ufp.fcm": ("ufp", "fuzzy c-means iterations", ["kbs.inference.engine:fcm_fit"]),
    "ufp.gg": ("ufp", "Gath-Geva iterations", ["kbs.inference.engine:gg_fit"]),
    "ufp.validity": ("ufp", "validity criteria (FHV, PD, APD)",
                     ["kbs.inference.ufp_onc:_validity", "kbs.inference.kernels:validity"]),
    "ufp.members": ("ufp", "memberships of all points",
                    ["kbs.inference.ufp_onc:KPartition.predict_proba", "kbs.inference.engine:memberships_in_chunks"]),
    "split_side": ("interp", "splits, interpreter side (children, split along components)",
                   ["kbs.knowledge.actions.split:Split.divide", "kbs.knowledge.actions.split_components:SplitComponents.divide"]),
    "descriptors": ("interp", "cluster descriptors (fuzzy covariance, eigenvectors)",
                    ["kbs.inference.geometry:cluster_geometry"]),
    "connexity": ("pred", "predicates: connexity", ["kbs.knowledge.connexity:connexity"]),
    "predicates": ("pred", "predicates: the rest", ["kbs.knowledge.predicates:Predicate.measure"]),
    "post.model": ("post", "ground_model (local ground surface built)",
                   ["kbs.knowledge.post.ground_model:GroundModel.build", "kbs.knowledge.groundmodel:LocalGround.build"]),
    "post.relabel": ("post", "relabel (its measures against the surface)",
                     ["kbs.knowledge.post.relabel:Relabel.apply"]),
    "post.release": ("post", "ground_release", ["kbs.knowledge.post.ground_release:GroundRelease.apply"]),
    "post.contact": ("post", "ground_contact", ["kbs.knowledge.post.ground_contact:GroundContact.apply"]),
    "post.merge": ("post", "merge_coplanar (and merged descriptors)",
                   ["kbs.knowledge.post.merge_coplanar:MergeCoplanar.apply", "kbs.knowledge.run:group_descriptors"]),
    "interp": ("interp", "interpreter, other (records, judging, labels, output arrays)",
               ["kbs.knowledge.interpreter:Interpreter.run", "kbs.knowledge:Interpreter.run"]),
    "ply": ("io", "write the PLY", ["kbs.cli.common:write_result_ply", "kbs.report.colors:rgb_fields"]),
    "json": ("io", "write the JSON", []),  # the harness's own write_json (cli/run.py's code)
}
#: stages absorbed by an enclosing post step (their time counts as that step)
ABSORBED_IN_POST = {"predicates", "descriptors"}
UFP_PARTS = ["fitset", "fcm", "gg", "validity", "members", "other"]


class StageTimer:
    """Exclusive wall time per stage: a stack of open stage calls; a call's time minus the time
    of the stage calls nested in it is charged to its stage."""

    def __init__(self) -> None:
        self.acc: dict[str, float] = defaultdict(float)
        self.calls: Counter = Counter()
        self.stack: list[list] = []  # [stage, nested seconds]
        self.ufp_calls: list[dict] = []
        self.measures: Counter = Counter()
        self.connexity_points = 0
        self.n_scene = -1
        self.splits_started = False
        self.progress_file: str | None = None
        self.t_segment = None
        self.found: dict[str, list[str]] = {}

    # the stage a call of `key` is charged to, or None when an enclosing stage absorbs it
    def resolve(self, key: str) -> str | None:
        if key in ABSORBED_IN_POST and any(s.startswith("post.") for s, _ in self.stack):
            return None
        if key.startswith("ufp."):
            kind = self._ufp_kind()
            return f"{kind}.{key[4:]}"
        return key

    def _ufp_kind(self) -> str:
        for s, _ in reversed(self.stack):
            if s == "initial.other":
                return "initial"
            if s == "split.other":
                return "split"
        return "split" if self.splits_started else "initial"

    def push(self, stage: str) -> None:
        self.stack.append([stage, 0.0])

    def pop(self, dt: float) -> None:
        stage, inner = self.stack.pop()
        self.acc[stage] += dt - inner
        if not self.stack or self.stack[-1][0] != stage:  # a call nested in its own stage is not another call
            self.calls[stage] += 1
        if self.stack:
            self.stack[-1][1] += dt

    def timed(self, stage: str, fn, *a, **k):
        t0 = time.perf_counter()
        self.push(stage)
        try:
            return fn(*a, **k)
        finally:
            self.pop(time.perf_counter() - t0)

    def wrap(self, key: str, fn):
        timer = self

        @functools.wraps(fn)
        def stage_wrapper(*a, **k):  # noqa: ANN202
            if key == "ufp":
                return timer._ufp(fn, a, k)
            if key == "predicates" and a:
                timer.measures[getattr(a[0], "name", "?")] += 1
            if key == "connexity" and a:
                try:
                    timer.connexity_points += len(a[0])
                except TypeError:
                    pass
            stage = timer.resolve(key)
            if stage is None:
                return fn(*a, **k)
            return timer.timed(stage, fn, *a, **k)

        stage_wrapper.profile_stage = key
        return stage_wrapper

    def _ufp(self, fn, a, k):
        X = a[0] if a else k.get("X")
        n = len(X) if X is not None else -1
        initial = not self.ufp_calls and n == self.n_scene
        kind = "initial" if initial else "split"
        if not initial:
            self.splits_started = True
        t0 = time.perf_counter()
        res = None
        try:
            res = self.timed(f"{kind}.other", fn, *a, **k)
            return res
        finally:
            dt = time.perf_counter() - t0
            rec = {"kind": kind, "n": n, "seconds": dt}
            if res is not None:
                parts = getattr(res, "partitions", ()) or ()
                rec.update(n_fit=getattr(res, "n_fit", None), chosen_k=getattr(res, "chosen_k", None),
                           ks=[getattr(p, "k", None) for p in parts],
                           fcm=sum(getattr(p, "n_iter_fcm", 0) or 0 for p in parts),
                           gg=sum(getattr(p, "n_iter_gg", 0) or 0 for p in parts))
            self.ufp_calls.append(rec)
            self._progress()

    def _progress(self) -> None:
        if not self.progress_file:
            return
        snap = {"elapsed_segment": time.perf_counter() - self.t_segment if self.t_segment else None,
                "ufp_calls": len(self.ufp_calls), "split_points": sum(c["n"] for c in self.ufp_calls if c["kind"] == "split"),
                "stages": dict(self.acc), "measures": sum(self.measures.values())}
        with open(self.progress_file, "a") as f:
            f.write(json.dumps(snap) + "\n")


def _lookup(spec: str):
    """(owner, attribute name, object) for "module:qualname", or None when absent."""
    mod_name, qual = spec.split(":")
    try:
        owner = importlib.import_module(mod_name)
    except ImportError:
        return None
    parts = qual.split(".")
    for p in parts[:-1]:
        owner = getattr(owner, p, None)
        if owner is None:
            return None
    name = parts[-1]
    if isinstance(owner, type):
        raw = None
        for klass in owner.__mro__:  # the raw attribute (staticmethod / classmethod objects)
            if name in vars(klass):
                raw = vars(klass)[name]
                break
        return None if raw is None else (owner, name, raw)
    obj = getattr(owner, name, None)
    return None if obj is None or not callable(obj) else (owner, name, obj)


def install(timer: StageTimer) -> None:
    """Wrap every stage function found (in its class, or in every kbs module that holds it)."""
    for key, (_, _, specs) in STAGES.items():
        timer.found[key] = []
        done: set[int] = set()
        for spec in specs:
            hit = _lookup(spec)
            if hit is None:
                continue
            owner, name, raw = hit
            if hasattr(getattr(raw, "__func__", raw), "profile_stage") or id(raw) in done:
                continue  # already wrapped (found under another name)
            done.add(id(raw))
            timer.found[key].append(spec)
            if isinstance(owner, type):
                if isinstance(raw, staticmethod):
                    setattr(owner, name, staticmethod(timer.wrap(key, raw.__func__)))
                elif isinstance(raw, classmethod):
                    setattr(owner, name, classmethod(timer.wrap(key, raw.__func__)))
                elif callable(raw):
                    setattr(owner, name, timer.wrap(key, raw))
                continue
            wrapped = timer.wrap(key, raw)
            for mod in list(sys.modules.values()):
                if getattr(mod, "__name__", "").split(".")[0] != "kbs":
                    continue
                for attr, val in list(vars(mod).items()):
                    if val is raw:
                        setattr(mod, attr, wrapped)


# -- the child: one run, in-process ---------------------------------------------------------------


def child(spec: dict) -> dict:
    t_start = time.perf_counter()
    import numpy as np  # noqa: F401  (imported by kbs anyway)

    import kbs.cli.run  # noqa: F401  what `kbs run` has imported before it starts working
    import kbs.inference  # noqa: F401
    import kbs.knowledge  # noqa: F401
    t_imports = time.perf_counter() - t_start
    for m in ("kbs.inference.ufp_onc", "kbs.inference.engine", "kbs.inference.voxel", "kbs.inference.kernels",
              "kbs.inference.geometry", "kbs.knowledge.connexity", "kbs.knowledge.groundmodel",
              "kbs.knowledge.predicates", "kbs.knowledge.interpreter", "kbs.cli.common", "kbs.report.colors",
              "kbs.io.readers"):
        try:
            importlib.import_module(m)
        except ImportError:
            pass
    timer = StageTimer()
    timer.progress_file = spec.get("progress")
    install(timer)

    from kbs.io import read_cloud
    from kbs.knowledge import Interpreter, load_rule_base

    prof = None
    if spec.get("cprofile"):
        import cProfile

        prof = cProfile.Profile()
        prof.enable()
    t0 = time.perf_counter()
    rb = load_rule_base(spec["rules"])
    pc = read_cloud(spec["scan"])
    timer.n_scene = len(pc.xyz)
    timer.t_segment = time.perf_counter()
    try:
        interp = Interpreter(rb, jobs=1)
    except TypeError:  # a version without the jobs parameter
        interp = Interpreter(rb)
    seg = interp.run(pc.xyz)
    t_seg = time.perf_counter() - timer.t_segment
    out = Path(spec["out"])
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(spec["scan"]).stem
    problems = []
    for key, fn, path in (("ply", write_ply, out / f"{stem}.ply"), ("json", write_json, out / f"{stem}.json")):
        try:
            timer.timed(key, fn, path, spec, rb, pc, seg)
        except Exception as exc:  # a later version's writer that this harness does not know: say so, go on
            problems.append(f"writing {path.name} failed in the harness: {type(exc).__name__}: {exc}")
    total = time.perf_counter() - t0
    if prof is not None:
        prof.disable()
    summary = seg.summary() if hasattr(seg, "summary") else {}
    result = {
        "scan": spec["scan"], "rules": spec["rules"], "n_points": len(pc.xyz), "imports_in_child": t_imports,
        "total": total, "segment": t_seg, "stages": dict(timer.acc), "calls": dict(timer.calls),
        "unattributed": total - sum(timer.acc.values()), "ufp_calls": timer.ufp_calls,
        "measures": dict(timer.measures), "connexity_points": timer.connexity_points,
        "found": timer.found, "summary": summary, "problems": problems,
    }
    if prof is not None:
        result["cprofile"] = cprofile_table(prof, spec.get("top", 20), timer)
    return result


def write_ply(path: Path, spec: dict, rb, pc, seg) -> None:
    """What cli/run.py writes: the cloud with cluster, label, membership and colours."""
    try:
        from kbs.cli.common import write_result_ply
    except ImportError:
        return
    try:
        from kbs.report.colors import rgb_fields
        colours = rgb_fields(seg.cluster)
    except ImportError:
        colours = {}
    write_result_ply(path, pc, {"cluster": seg.cluster, "label": seg.label, "membership": seg.membership, **colours})


def write_json(path: Path, spec: dict, rb, pc, seg) -> None:
    """What cli/run.py writes: label names, summary, clusters and the explanation tree."""
    from kbs import __version__

    from kbs.cli.run import _jsonable
    doc = {
        "kbs_version": __version__, "input": spec["scan"], "n_points": len(pc), "n_dropped": getattr(pc, "n_dropped", 0),
        "rule_base": rb.name, "rule_file": rb.path, "units": rb.units, "sensor": list(map(float, rb.sensor)),
        "label_names": seg.label_names, "summary": seg.summary(), "clusters": seg.clusters,
        "explanation": seg.explanation.to_dict(),
    }
    path.write_text(json.dumps(doc, separators=(",", ":"), default=_jsonable))


def cprofile_table(prof, top: int, timer: StageTimer) -> dict:
    """The hottest functions by own time, and cProfile's cumulative time of each stage function."""
    import pstats

    st = pstats.Stats(prof)
    here = Path(__file__).name
    rows = []
    for (file, line, name), (cc, nc, tt, ct, _) in st.stats.items():
        if Path(file).name == here:
            continue
        short = file
        for marker in ("/site-packages/", "/kbs/", "/wt-prof/", "/main/"):
            if marker in file:
                short = file.split(marker, 1)[1]
                break
        if file.startswith("~"):
            short = "built-in"
        rows.append({"func": f"{short}:{line}({name})", "ncalls": nc, "tottime": tt, "cumtime": ct})
    rows.sort(key=lambda r: -r["tottime"])
    total = sum(r["tottime"] for r in rows)
    # cumulative time (cProfile's own) of each stage function found
    stage_funcs = []
    for key, specs in timer.found.items():
        for spec in specs:
            mod, qual = spec.split(":")
            name = qual.split(".")[-1]
            for (file, line, fname), (cc, nc, tt, ct, _) in st.stats.items():
                if fname == name and Path(file).name != here and Path(file).stem == mod.split(".")[-1]:
                    stage_funcs.append({"stage": key, "func": spec, "ncalls": nc, "cumtime": ct})
    imports = [v[3] for k, v in st.stats.items() if k[2] == "_find_and_load"]
    return {"top": rows[:top], "total_tottime": total, "stage_funcs": stage_funcs,
            "imports": imports[0] if imports else None}


# -- the parent ---------------------------------------------------------------------------------


def make_isprs_tile(n: int, path: Path, spacing: float = 2000.0, jitter: float = 0.01, seed: int = 0) -> int:
    """An airborne tile of at least ``n`` points: whole copies of the ISPRS samples (samp11, samp12
    text; samp21, 31, 51, 61 PCD), in that order and again, each moved so that its own x/y minimum
    sits at (``spacing`` x i, 0) (heights kept), side by side ``spacing`` m apart in x so that no
    two overlap, with Gaussian jitter of ``jitter`` m on every coordinate (seeded) so that no two
    copies are identical. Written as a float64 (N, 3) .npy; returns N."""
    import numpy as np

    from kbs.io import read_cloud

    files = [DATA / "isprs" / f for f in ("samp11.txt", "samp12.txt", "samp21-utm.pcd", "samp31-utm.pcd",
                                          "samp51-utm.pcd", "samp61-utm.pcd")]
    clouds = [read_cloud(f).xyz for f in files]
    rng = np.random.default_rng(seed)
    parts, total, i = [], 0, 0
    while total < n:
        xyz = np.array(clouds[i % len(clouds)], dtype=np.float64)
        xyz[:, :2] -= xyz[:, :2].min(axis=0)
        xyz[:, 0] += spacing * i
        xyz += rng.normal(0.0, jitter, xyz.shape)
        parts.append(xyz)
        total += len(xyz)
        i += 1
    tile = np.vstack(parts)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, tile)
    return len(tile)


def kbs_command() -> list[str]:
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    return [exe] if exe else [sys.executable, "-m", "kbs.cli.main"]


def wall(cmd: list[str], timeout: float | None = None) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, timeout=timeout)
    return time.perf_counter() - t0


def startup(repeats: int) -> dict[str, list[float]]:
    py = sys.executable
    cmds = {
        "python -c pass": [py, "-c", "pass"],
        'python -c "import kbs.cli.main"': [py, "-c", "import kbs.cli.main"],
        'python -c "import kbs.cli.main, kbs.cli.run"': [py, "-c", "import kbs.cli.main, kbs.cli.run"],
        "kbs --help": kbs_command() + ["--help"],
    }
    out: dict[str, list[float]] = {k: [] for k in cmds}
    for _ in range(repeats):  # interleaved, so that a busy spell hits all alike
        for k, c in cmds.items():
            out[k].append(wall(c))
    return out


def run_child(spec: dict, timeout: float | None) -> dict:
    """One run in a fresh process; on timeout, what the progress file says it got to."""
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        json.dump(spec, f)
        spec_file = f.name
    t0 = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, __file__, "--child", spec_file], capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired:
        last = None
        if spec.get("progress") and os.path.exists(spec["progress"]):
            lines = Path(spec["progress"]).read_text().splitlines()
            last = json.loads(lines[-1]) if lines else None
        return {"timeout": timeout, "wall": time.perf_counter() - t0, "progress": last}
    finally:
        os.unlink(spec_file)
    if r.returncode != 0:
        raise SystemExit(f"the profiled run failed ({r.returncode}):\n{r.stderr[-3000:]}")
    res = json.loads(r.stdout.strip().splitlines()[-1])
    res["wall"] = time.perf_counter() - t0
    return res


def med(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def fmt_s(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def report(scan: str, rules: str, runs: list[dict], start: dict[str, list[float]], process_runs: list[float],
           prof: dict | None, load: str = "") -> str:
    lines = []
    n = runs[0]["n_points"]
    found = runs[0]["found"]
    lines.append(f"### `{Path(scan).name}` ({n:,} points), rules `{rules}`\n")
    lines.append(f"{len(runs)} in-process run(s) with `Interpreter(rb, jobs=1)`, each in a fresh process; "
                 "seconds are medians over the runs (range in brackets), % of the total; calls: outermost calls "
                 f"of the stage's functions in one run. Load average before / after this scan: {load}.\n")

    def stage_vals(key: str) -> list[float]:
        return [r["stages"].get(key, 0.0) for r in runs]

    def present(key: str) -> bool:
        base = key.split(".", 1)[1] if key.startswith(("initial.", "split.")) else key
        base = "ufp" if base == "other" else ("ufp." + base if key.startswith(("initial.", "split.")) else base)
        return base == "json" or bool(found.get(base))

    rows: list[tuple[str, float | None, str, int | None, bool]] = []  # label, median, range, calls, counted
    st_key = 'python -c "import kbs.cli.main, kbs.cli.run"'
    st = start.get(st_key, [])
    rows.append((f"process start-up and imports (`{st_key}`, a fresh process)", med(st) if st else None,
                 f"{min(st):.2f}–{max(st):.2f}" if st else "", None, True))
    for k in ("python -c pass", 'python -c "import kbs.cli.main"', "kbs --help"):
        v = start.get(k, [])
        rows.append((f"&nbsp;&nbsp;for reference, not in the total: `{k}` process", med(v) if v else None,
                     f"{min(v):.2f}–{max(v):.2f}" if v else "", None, False))

    def add(label: str, key: str | list[str], indent: int = 0, counted: bool = True, calls_of: str | None = None) -> None:
        keys = [key] if isinstance(key, str) else key
        if not any(present(k) for k in keys):
            rows.append(("&nbsp;&nbsp;" * indent + label, None, "", None, counted))
            return
        per_run = [sum(r["stages"].get(k, 0.0) for k in keys) for r in runs]
        calls = None if calls_of == "" else sum(runs[0]["calls"].get(k, 0) for k in ([calls_of] if calls_of else keys))
        rows.append(("&nbsp;&nbsp;" * indent + label, med(per_run), f"{min(per_run):.2f}–{max(per_run):.2f}",
                     calls, counted))

    add("load the rule base", "rules")
    add("read the file", "read")
    for kind, title in (("initial", "initial UFP-ONC partition of the scene"), ("split", "UFP-ONC splits")):
        keys = [f"{kind}.{p}" for p in UFP_PARTS]
        add(f"**{title}** (total; calls: UFP-ONC runs)", keys, counted=False, calls_of=f"{kind}.other")
        for p in UFP_PARTS:
            label = STAGES["ufp" if p == "other" else f"ufp.{p}"][1]
            add(label, f"{kind}.{p}", indent=1)
    add(STAGES["split_side"][1], "split_side")
    add(STAGES["descriptors"][1], "descriptors")
    add(STAGES["connexity"][1], "connexity")
    add(STAGES["predicates"][1], "predicates")
    post = ["post.model", "post.relabel", "post.release", "post.contact", "post.merge"]
    add("**ground surface and post steps** (total)", post, counted=False, calls_of="")
    for k in post:
        add(STAGES[k][1], k, indent=1)
    add(STAGES["interp"][1], "interp")
    add("write the PLY", "ply")
    add("write the JSON", "json")
    un = [r["unattributed"] for r in runs]
    rows.append(("harness, between stages (unattributed)", med(un), f"{min(un):.2f}–{max(un):.2f}", None, True))
    total = sum(v for _, v, _, _, c in rows if c and v is not None)

    lines.append("| stage | seconds | % of total | calls |")
    lines.append("|---|---:|---:|---:|")
    for label, v, rng, calls, counted in rows:
        pct = f"{100 * v / total:.1f}" if (v is not None and total > 0) else ""
        if not counted and v is not None and not label.startswith("**"):
            pct = f"({100 * v / total:.1f})"
        vs = "n/a" if v is None else f"{v:.3f}" + (f" [{rng}]" if rng and len(runs) > 1 or "process" in label else "")
        lines.append(f"| {label} | {vs} | {pct} | {'' if calls is None else f'{calls:,}'} |")
    lines.append(f"| **total** (start-up + the rows with a %) | **{total:.3f}** | 100 | |")
    seg = [r["segment"] for r in runs]
    lines.append("")
    lines.append(f"In-process: median {med([r['total'] for r in runs]):.3f} s from loading the rules to the JSON "
                 f"written, of which `Interpreter.run` {med(seg):.3f} s.")
    if process_runs:
        lines.append(f"For comparison, the wall time of the whole `kbs -q run -j 1 --rules {rules}` process: median "
                     f"{med(process_runs):.2f} s over {len(process_runs)} run(s) "
                     f"[{min(process_runs):.2f}–{max(process_runs):.2f}].")
    lines.append("")

    # counts (from the first run: the runs are deterministic)
    r0 = runs[0]
    calls = r0["ufp_calls"]
    splits = [c for c in calls if c["kind"] == "split"]
    init = [c for c in calls if c["kind"] == "initial"]
    lines.append("Counts (deterministic, from one run):\n")
    for name, cs in (("initial partition", init), ("splits", splits)):
        if not cs:
            lines.append(f"- UFP-ONC {name}: none")
            continue
        ks_tried = Counter(len(c.get("ks") or []) for c in cs)
        chosen = Counter(c.get("chosen_k") for c in cs)
        n_fit = sum(c.get("n_fit") or 0 for c in cs)
        fits = sum(len(c.get("ks") or []) for c in cs)
        lines.append(
            f"- UFP-ONC {name}: {len(cs):,} call(s), {sum(c['n'] for c in cs):,} points in, "
            f"{n_fit:,} fit-set points in all ({n_fit / len(cs):,.0f} per call), {fits:,} K-fits "
            f"(K values tried per call: {', '.join(f'{k}: {v}' for k, v in sorted(ks_tried.items()))} calls), "
            f"FCM iterations {sum(c.get('fcm', 0) for c in cs):,}, GG iterations {sum(c.get('gg', 0) for c in cs):,}; "
            f"chosen K: {', '.join(f'K={k}: {v}' for k, v in sorted(chosen.items(), key=lambda kv: (kv[0] is None, kv[0])))}")
        if name == "splits":
            sizes = sorted(c["n"] for c in cs)
            reduced = sum(1 for c in cs if (c.get("n_fit") or 0) < c["n"])
            lines.append(f"  - split sizes: median {statistics.median(sizes):,.0f} points, largest {sizes[-1]:,}; "
                         f"{reduced} of {len(cs)} fitted on a voxel reduction, the others on every point")
    m = r0["measures"]
    lines.append(f"- predicate measures: {sum(m.values()):,} ({', '.join(f'{k} {v:,}' for k, v in sorted(m.items(), key=lambda kv: -kv[1]))}); "
                 f"connexity on {r0['connexity_points']:,} points in all")
    s = r0.get("summary") or {}
    if s:
        lines.append(f"- result: {s.get('clusters')} clusters, {s.get('splits')} splits, {s.get('limits')} limits reached")
    for prob in r0.get("problems", []):
        lines.append(f"- {prob}")
    missing = [k for k, v in found.items() if not v and STAGES[k][2]]
    if missing:
        lines.append(f"- stage functions not found in this version (n/a): {', '.join(missing)}")
    lines.append("")
    if prof:
        p = prof["cprofile"]
        lines.append(f"Hottest functions by own time, one run under cProfile (in-process total {prof['total']:.2f} s "
                     f"under the profiler; own times add up to {p['total_tottime']:.2f} s"
                     + (f"; modules imported lazily during the run, within the stages above: "
                        f"{p['imports']:.2f} s" if p.get("imports") is not None else "") + "):\n")
        lines.append("| function | calls | own s | % own | cumulative s |")
        lines.append("|---|---:|---:|---:|---:|")
        for row in p["top"]:
            lines.append(f"| `{row['func']}` | {row['ncalls']:,} | {row['tottime']:.3f} | "
                         f"{100 * row['tottime'] / p['total_tottime']:.1f} | {row['cumtime']:.3f} |")
        lines.append("")
        if p.get("stage_funcs"):
            lines.append("cProfile's own cumulative time of each stage function in that run (inclusive: nested "
                         "stage functions are counted again here, not in the table above):\n")
            lines.append("| stage | function | calls | cumulative s |")
            lines.append("|---|---|---:|---:|")
            for row in p["stage_funcs"]:
                lines.append(f"| {row['stage']} | `{row['func']}` | {row['ncalls']:,} | {row['cumtime']:.3f} |")
            lines.append("")
    return "\n".join(lines)


def parse_scans(args) -> list[tuple[str, str]]:
    if not args.scan:
        return [(str(s), r) for s, r in DEFAULT_SCANS]
    rules = args.rules or []
    if len(rules) not in (0, 1, len(args.scan)):
        raise SystemExit("give one --rules per --scan (or one for all)")
    if not rules:
        rules = ["outdoor"]
    if len(rules) == 1:
        rules = rules * len(args.scan)
    return list(zip(args.scan, rules))


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        spec = json.loads(Path(sys.argv[2]).read_text())
        print(json.dumps(child(spec)))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", action="append", help="a scan (repeatable), or isprs-tile:N")
    ap.add_argument("--rules", action="append", help="its rule base (one per --scan, or one for all)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per scan (fresh processes)")
    ap.add_argument("--startup-repeats", type=int, default=7)
    ap.add_argument("--process-runs", type=int, default=None,
                    help="whole `kbs run -j 1` processes per scan, for comparison (default: --repeats)")
    ap.add_argument("--no-cprofile", action="store_true", help="skip the extra run under cProfile")
    ap.add_argument("--top", type=int, default=20, help="functions in the cProfile table")
    ap.add_argument("--timeout", type=float, default=None, help="seconds per run; a run past it reports how far it got")
    ap.add_argument("--tile-dir", type=Path, default=Path(tempfile.gettempdir()) / "kbs-profile-tiles")
    args = ap.parse_args()
    scans = parse_scans(args)
    process_runs = args.repeats if args.process_runs is None else args.process_runs

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"load average at start {', '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    start = startup(args.startup_repeats)
    print(f"Start-up, {args.startup_repeats} fresh processes each (median [min–max] s): " + "; ".join(
        f"`{k}` {med(v):.3f} [{min(v):.3f}–{max(v):.3f}]" for k, v in start.items()) + "\n")
    for scan, rules in scans:
        if scan.startswith("isprs-tile:"):
            want = int(scan.split(":", 1)[1])
            path = args.tile_dir / f"isprs-tile-{want}.npy"
            if not path.exists():
                got = make_isprs_tile(want, path)
                print(f"made {path}: {got:,} points\n")
            scan = str(path)
        if not Path(scan).exists():
            print(f"### `{scan}`: not found, skipped\n")
            continue
        load_before = ", ".join(f"{x:.2f}" for x in os.getloadavg())
        with tempfile.TemporaryDirectory() as out:
            runs, proc, timed_out = [], [], None
            for i in range(args.repeats):
                progress = os.path.join(out, f"progress-{i}.jsonl")
                r = run_child({"scan": scan, "rules": rules, "out": os.path.join(out, f"run-{i}"), "progress": progress},
                              args.timeout)
                if "timeout" in r:
                    timed_out = r
                    break
                runs.append(r)
                if i < process_runs:
                    try:
                        proc.append(wall(kbs_command() + ["-q", "run", "-j", "1", "--rules", rules, scan, "--out",
                                                          os.path.join(out, f"process-{i}")], args.timeout))
                    except subprocess.TimeoutExpired:
                        pass
            if timed_out is not None:
                print(f"### `{Path(scan).name}`, rules `{rules}`: stopped after {timed_out['timeout']:.0f} s\n")
                p = timed_out.get("progress")
                if p:
                    st = p.get("stages", {})
                    print(f"How far it got (the last progress record, after a UFP-ONC call): {p['ufp_calls']} UFP-ONC "
                          f"call(s) done ({p['split_points']:,} points split), {p['measures']:,} predicate measures, "
                          f"{p['elapsed_segment']:.0f} s into `Interpreter.run`. Stage seconds so far: "
                          + ", ".join(f"{k} {v:.1f}" for k, v in sorted(st.items(), key=lambda kv: -kv[1])) + "\n")
                else:
                    print("No progress record: it did not finish its initial partition.\n")
                if not runs:
                    continue
            prof = None
            if not args.no_cprofile:
                prof = run_child({"scan": scan, "rules": rules, "out": os.path.join(out, "cprofile"), "cprofile": True, "top": args.top},
                                 args.timeout)
                if "timeout" in prof:
                    prof = None
            load = f"{load_before} / {', '.join(f'{x:.2f}' for x in os.getloadavg())}"
            print(report(scan, rules, runs, start, proc, prof, load), flush=True)


if __name__ == "__main__":
    main()
