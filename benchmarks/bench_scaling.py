"""Benchmark: how a whole kbs segmentation scales with the number of points, for the outdoor
rules on tiled vehicle scans and the airborne rules on tiled airborne samples: wall time, peak
resident memory, output clusters, splits and limits reached (by kind), from 10^4 to 10^7 points.

Data (real scans of ../shared/data, tiled; nothing is written to the repository):
- outdoor: the SemanticKITTI scan and the two GndNet scans (288,173 points), subsampled with a
  fixed stride below that size, tiled side by side above it (copies shifted 250 m in x);
- airborne: the six ISPRS samples (184,856 points), each moved to its own 600 m cell of a grid
  (8 cells a row), copies added cell after cell, 1 cm of seeded jitter, cut at the size wanted;
  below 184,856 points a fixed stride of the same pool.

Each measurement runs in a fresh child process (its peak RSS is its own; the largest of the
split workers it forks is given beside it). Those two count the pages a forked worker shares with
the child twice, so the physical memory of the whole run is given too: the peak of the summed PSS
(proportional set size: a shared page counted once, split between its sharers) of the child and
its workers, sampled every 0.2 s from ``/proc/PID/smaps_rollup`` (Linux; "n/a" elsewhere), from
the child's start, so building the cloud counts too. Reading and writing files are not included.

Usage: python benchmarks/bench_scaling.py [--sizes 10000 100000 1000000 10000000]
           [--rules outdoor airborne] [--repeats 1] [--jobs -1] [--timeout 1800]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import queue as queue_mod
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _pool(rules: str) -> list[np.ndarray]:
    if rules == "outdoor":
        return [np.load(DATA / "semantickitti" / "000001.points.npy")[:, :3].astype(np.float64),
                np.load(DATA / "gndnet" / "000000.points.npy")[:, :3].astype(np.float64) - [0, 0, 1.73],
                np.load(DATA / "gndnet" / "000001.points.npy")[:, :3].astype(np.float64) - [0, 0, 1.73]]
    from kbs.io import read_cloud

    names = ["samp11.txt", "samp12.txt", "samp21-utm.pcd", "samp31-utm.pcd", "samp51-utm.pcd", "samp61-utm.pcd"]
    out = []
    for f in names:
        X = read_cloud(DATA / "isprs" / f).xyz
        out.append(X - X.min(axis=0))
    return out


def cloud(rules: str, n: int) -> np.ndarray:
    parts = _pool(rules)
    total = sum(len(p) for p in parts)
    if rules == "outdoor":
        pool = np.vstack(parts)
        if n <= total:
            return pool[np.linspace(0, total - 1, n).astype(np.int64)]
        tiles = [pool + [250.0 * i, 0.0, 0.0] for i in range(int(np.ceil(n / total)))]
        return np.vstack(tiles)[:n]
    rng = np.random.default_rng(0)
    if n <= total:
        cells = [p + [600.0 * i, 0.0, 0.0] for i, p in enumerate(parts)]
        pool = np.vstack(cells)
        return pool[np.linspace(0, total - 1, n).astype(np.int64)]
    out, have, i = [], 0, 0
    while have < n:
        p = parts[i % len(parts)]
        out.append(p + [600.0 * (i % 8), 600.0 * (i // 8), 0.0] + rng.normal(scale=0.01, size=p.shape))
        have += len(p)
        i += 1
    return np.vstack(out)[:n]


def _child(rules: str, n: int, q, jobs: int) -> None:
    import kbs

    X = cloud(rules, n)
    seg = kbs.Segmenter(rules, jobs=jobs, sensor=[0.0, 0.0, 0.0] if rules == "outdoor" else None)
    t0 = time.perf_counter()
    out = seg.segment(X)
    dt = time.perf_counter() - t0
    s = out.summary()
    kinds = s.get("limits_by_kind") or {}
    lim = ", ".join(f"{k} {v['count'] if isinstance(v, dict) else v}" for k, v in kinds.items()) or "-"
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    seg.close()  # the split workers end here: their peak RSS is then known
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    q.put((dt, rss, workers, s["clusters"], s["splits"], s["limits"], lim))


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (Linux: /proc/PID/task/TID/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for tid in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (tid / "children").read_text().split()]
        except OSError:  # gone meanwhile, or no /proc
            pass
    return out


def _pss(pid: int) -> int | None:
    """Bytes of PSS of one process (/proc/PID/smaps_rollup), None where it cannot be read."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def tree_pss(pid: int) -> int | None:
    """The summed PSS of ``pid`` and its descendants, None where /proc does not say."""
    values = [_pss(p) for p in _tree(pid)]
    return sum(v for v in values if v is not None) if any(v is not None for v in values) else None


def measure(rules: str, n: int, repeats: int, jobs: int, timeout: float):
    ctx = mp.get_context("spawn")
    runs = []
    for _ in range(repeats):
        q = ctx.Queue()
        p = ctx.Process(target=_child, args=(rules, n, q, jobs))
        p.start()
        assert p.pid is not None
        end = time.monotonic() + timeout
        peak: int | None = None
        while True:  # the result, sampling the process tree's PSS meanwhile
            now = tree_pss(p.pid)
            if now is not None:
                peak = now if peak is None else max(peak, now)
            try:
                got = q.get(timeout=0.2)
                break
            except queue_mod.Empty:
                if not p.is_alive():  # ended without a result: it failed
                    p.join()
                    return f"failed (exit code {p.exitcode})"
                if time.monotonic() > end:
                    p.kill()
                    p.join()
                    return None
        p.join()
        runs.append(got + (peak,))
    peaks = [r[-1] for r in runs if r[-1] is not None]
    return ((statistics.median(r[0] for r in runs), max(r[1] for r in runs), max(r[2] for r in runs))
            + runs[0][3:-1] + (max(peaks) if peaks else None,))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000, 10_000_000])
    ap.add_argument("--rules", nargs="+", default=["outdoor", "airborne"])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=-1, help="kbs split processes (-1: one per core, as kbs run)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds before a measurement is given up")
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {DATA}")
    print(f"whole segmentation (kbs.Segmenter, jobs = {args.jobs}), reading and writing excluded\n")
    print("| rules | points | seconds | s per 10^5 points | peak RSS MB | largest worker MB | whole run PSS MiB | "
          "clusters | splits | limits | limits by kind |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for rules in args.rules:
        for n in args.sizes:
            r = measure(rules, n, args.repeats if n <= 1_000_000 else 1, args.jobs, args.timeout)
            if r is None or isinstance(r, str):
                what = f"> {args.timeout:.0f} (given up)" if r is None else r
                print(f"| {rules} | {n:,} | {what} | | | | | | | | |", flush=True)
                continue
            dt, rss, workers, clusters, splits, limits, kinds, pss = r
            whole = "n/a" if pss is None else f"{pss / 2**20:,.0f}"
            print(f"| {rules} | {n:,} | {dt:.2f} | {dt / n * 1e5:.3f} | {rss / 1e6:.0f} | "
                  f"{workers / 1e6:.0f} | {whole} | {clusters:,} | {splits:,} | {limits:,} | {kinds} |", flush=True)


if __name__ == "__main__":
    main()
