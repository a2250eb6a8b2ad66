"""Benchmark: this working tree against another revision of kbs, in the same run.

For each scan, a loaded ``kbs.Segmenter`` per side segments the same points frame after frame in
its own process (one warm-up frame not counted, then ``--repeats`` timed frames); the sides take
turns, ``--rounds`` times, so that both see the same load on a shared machine. Prints a markdown
table: the median ms per frame of each side (all rounds pooled), the ratio, and whether the
results are identical (the per-point cluster ids and labels), with the share of points whose label
differs when they are not; a changed result is the signal to run the quality benchmarks
(``bench_ground.py``, ``bench_planar.py``).

The other side is a git revision (``--base``, default ``HEAD``: the last commit, against the
uncommitted changes) extracted with ``git archive`` into a temporary folder and imported from
there (``PYTHONPATH``), with this venv's packages. Both sides run the compiled kernels
(``KBS_JIT=1``); the base's are cached separately, so its warm-up frame of the first round
compiles them (without ``KBS_JIT=1`` it would run the numpy reference, its cache being cold).
When this tree's kernels are built ahead of time (``kbs warmup``, :mod:`kbs.inference._aot`), its
side runs them, as its runs do (``KBS_AOT=0`` keeps numba's); the header says which.

The post steps column is the time of ``Interpreter.finish`` in each frame (labels, the post
steps, the result), median of the same frames.

Usage: python benchmarks/bench_compare.py [--base REV] [--repeats 5] [--rounds 2] [--jobs 1] [--scan NAME ...]
(scans: the five defaults, and the airborne samp11, samp61 and isprs-tile, 131,951 points of the
ISPRS samples side by side, run in tiles by the rules' limits.tile; mosd0-table: mOSD learn0 with
each side's own examples/tabletop rules)
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"

#: name -> (file, rule base, sensor position or None for the rule base's)
SCANS = {
    "semantickitti": (DATA / "semantickitti" / "000001.points.npy", "outdoor", None),
    "gndnet0": (DATA / "gndnet" / "000000.points.npy", "outdoor", [0.0, 0.0, 1.73]),
    "seq00-0": (DATA / "semantickitti-seq00" / "seq00_000000.bin", "outdoor", None),
    "isprs21": (DATA / "isprs" / "samp21-utm.pcd", "airborne", None),
    "mosd0": (DATA / "mosd" / "learn0.pcd", "planar_contest", None),
    "mosd0-table": (DATA / "mosd" / "learn0.pcd", "examples/tabletop", None),  # each side its own example file
    "samp11": (DATA / "isprs" / "samp11.txt", "airborne", None),
    "samp61": (DATA / "isprs" / "samp61-utm.pcd", "airborne", None),
    # ISPRS samples side by side (benchmarks/profile_run.py: make_isprs_tile), made once in the temp folder
    "isprs-tile": (Path(tempfile.gettempdir()) / "kbs-bench" / "isprs-tile-130000.npy", "airborne", None),
}
#: the scans run by default (the others on demand with --scan)
DEFAULT = ["semantickitti", "gndnet0", "seq00-0", "isprs21", "mosd0"]

CHILD = r"""
import hashlib, json, sys, time
import numpy as np
import kbs
from kbs.io import read_cloud
path, rules, sensor, repeats, out = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
X = read_cloud(path).xyz
seg = kbs.Segmenter(rules, jobs=int(sys.argv[6]), sensor=sensor)
from kbs.knowledge.interpreter import Interpreter
post = [0.0]
_finish = Interpreter.finish
def finish(self, *a, **k):  # the post steps' share: labels, post steps, the result
    t = time.perf_counter()
    try:
        return _finish(self, *a, **k)
    finally:
        post[0] += time.perf_counter() - t
Interpreter.finish = finish
res = seg.segment(X)
times, posts = [], []
for _ in range(repeats):
    post[0] = 0.0
    t = time.perf_counter()
    res = seg.segment(X)
    times.append(time.perf_counter() - t)
    posts.append(post[0])
names = np.asarray(res.label_names, dtype=object)
label = names[res.label] if len(names) else res.label
np.save(out, np.stack([res.cluster.astype(np.int64), np.unique(label, return_inverse=True)[1].ravel()]))
print(json.dumps({"times": times, "posts": posts, "kbs": kbs.__file__, "clusters": int(res.cluster.max()) + 1,
                  "labels": sorted(set(map(str, names)))}))
"""


def _this_aot() -> bool:
    """Whether this working tree's kernels are built ahead of time (``kbs warmup``): its side then
    runs them, as its runs do; otherwise numba's, as the base's."""
    if os.environ.get("KBS_AOT", "1") == "0":
        return False
    try:
        from kbs.inference import _aot
    except ImportError:
        return False
    return _aot.ready()


def run_side(pythonpath: str | None, scan: str, repeats: int, out: Path, jobs: int = 1) -> dict:
    path, rules, sensor = SCANS[scan]
    if scan == "isprs-tile" and not path.exists():
        sys.path.insert(0, str(REPO / "benchmarks"))
        from profile_run import make_isprs_tile

        make_isprs_tile(130000, path)
    env = dict(os.environ, KBS_JIT="1")  # compiled on both sides (the base's cache is cold: its warm-up compiles)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    elif _this_aot():  # this tree's kernels as a run takes them: its ahead-of-time module (kbs.inference._aot)
        env["KBS_JIT"] = "auto"
    proc = subprocess.run([sys.executable, "-c", CHILD, str(path), rules, json.dumps(sensor), str(repeats), str(out), str(jobs)],
                          capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    if proc.returncode:
        raise SystemExit(f"{scan}: the child failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision to compare with (default: HEAD)")
    ap.add_argument("--repeats", type=int, default=5, help="timed frames per side and round")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds per scan")
    ap.add_argument("--scan", nargs="*", default=DEFAULT, choices=list(SCANS))
    ap.add_argument("--jobs", type=int, default=1, help="the segmenters' jobs (default 1: one core)")
    a = ap.parse_args()
    import numpy as np

    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", a.base], capture_output=True, text=True,
                         check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True).stdout.strip())
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="kbs-base-") as tmp:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", "--prefix=kbs/", a.base], capture_output=True,
                                 check=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        sides = {"base": tmp, "this": None}
        kernels = "the kernels built ahead of time" if _this_aot() else "numba's kernels"
        print(f"base: {a.base} ({rev}); this: the working tree at {head}{' with uncommitted changes' if dirty else ''}, "
              f"{kernels}; "
              f"{a.repeats} frames x {a.rounds} rounds per side, jobs={a.jobs}, load average {os.getloadavg()[0]:.2f} at the start\n")
        print("| scan | rules | points | base ms | this ms | base / this | post steps, base ms | this ms | result |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---|")
        for scan in a.scan:
            times: dict[str, list[float]] = {"base": [], "this": []}
            posts: dict[str, list[float]] = {"base": [], "this": []}
            info = {}
            for _ in range(a.rounds):
                for side in ("base", "this"):
                    out = Path(tmp) / f"{scan}-{side}.npy"
                    r = run_side(sides[side], scan, a.repeats, out, a.jobs)
                    times[side] += r["times"]
                    posts[side] += r.get("posts", [])
                    info[side] = r
            if Path(info["base"]["kbs"]).resolve().is_relative_to(REPO):
                raise SystemExit("the base side imported this working tree: check PYTHONPATH handling")
            A, B = np.load(Path(tmp) / f"{scan}-base.npy"), np.load(Path(tmp) / f"{scan}-this.npy")
            if A.shape == B.shape and np.array_equal(A, B):
                verdict = "identical"
            else:
                diff = float(np.mean(A[1] != B[1])) if A.shape == B.shape else float("nan")
                verdict = f"differs: {diff:.2%} of labels, clusters {info['base']['clusters']} -> {info['this']['clusters']}"
            mb, mt = statistics.median(times["base"]) * 1e3, statistics.median(times["this"]) * 1e3
            path, rules, _ = SCANS[scan]
            pb, pt = (statistics.median(posts[k]) * 1e3 if posts[k] else float("nan") for k in ("base", "this"))
            print(f"| {scan} | {rules} | {A.shape[1]:,} | {mb:.0f} | {mt:.0f} | {mb / mt:.2f}x | {pb:.0f} | {pt:.0f} | "
                  f"{verdict} |", flush=True)
        print(f"\nload average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
