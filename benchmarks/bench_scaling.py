"""Benchmark: how kbs scales. Wall time and peak memory of a whole `kbs run` segmentation
(outdoor rules, reading and writing excluded) and of the inference motor alone
(`ufp_onc`, K = 1 .. 10), at 10^4, 10^5, 10^6 and 3 x 10^6 points.

Data: the SemanticKITTI scan and the two GndNet scans of ../shared/data (288,173 real points),
subsampled (a fixed stride) below that size and tiled side by side (copies shifted 250 m in x)
above it. Each measurement runs in a fresh child process; its peak RSS is its own, and the
largest of the split workers it forks (``--jobs``, default one per core as ``kbs run``) is given
beside it.

Usage: python benchmarks/bench_scaling.py [--sizes 10000 100000 1000000 3000000] [--repeats 3]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def cloud(n: int) -> np.ndarray:
    pool = np.vstack([np.load(DATA / "semantickitti" / "000001.points.npy")[:, :3],
                      np.load(DATA / "gndnet" / "000000.points.npy")[:, :3] - [0, 0, 1.73],
                      np.load(DATA / "gndnet" / "000001.points.npy")[:, :3] - [0, 0, 1.73]]).astype(np.float64)
    if n <= len(pool):
        return pool[np.linspace(0, len(pool) - 1, n).astype(np.int64)]
    tiles = [pool + [250.0 * i, 0.0, 0.0] for i in range(int(np.ceil(n / len(pool))))]
    return np.vstack(tiles)[:n]


def _child(kind: str, n: int, queue, jobs: int) -> None:
    X = cloud(n)
    if kind == "kbs run":
        from kbs.knowledge import Interpreter, load_rule_base

        it = Interpreter(load_rule_base("outdoor"), jobs=jobs)
        call = lambda: it.run(X)  # noqa: E731
    else:
        from kbs.inference import ufp_onc

        call = lambda: ufp_onc(X, 10)  # noqa: E731
    t0 = time.perf_counter()
    out = call()
    dt = time.perf_counter() - t0
    extra = (f"{len(out.clusters)} clusters, {out.n_splits} splits" if kind == "kbs run"
             else f"K = {out.chosen_k}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # the largest split worker
    queue.put((dt, rss, extra, workers))


def measure(kind: str, n: int, repeats: int, jobs: int) -> tuple[float, float, str, float]:
    ctx = mp.get_context("spawn")
    runs = []
    for _ in range(repeats):
        q = ctx.Queue()
        p = ctx.Process(target=_child, args=(kind, n, q, jobs))
        p.start()
        runs.append(q.get())
        p.join()
    return statistics.median(r[0] for r in runs), max(r[1] for r in runs), runs[0][2], max(r[3] for r in runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000, 3_000_000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=-1, help="kbs split processes (-1: one per core, as kbs run)")
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {DATA}")
    print(f"kbs run with jobs = {args.jobs}\n")
    print("| points | what | median s (runs) | peak RSS MB | largest worker MB | result |")
    print("|---:|---|---:|---:|---:|---|")
    for n in args.sizes:
        for kind in ("ufp_onc", "kbs run"):
            reps = args.repeats if n <= 1_000_000 else 1
            dt, rss, extra, workers = measure(kind, n, reps, args.jobs)
            w = f"{workers / 1e6:.0f}" if kind == "kbs run" and workers else "-"
            print(f"| {n:,} | {kind} | {dt:.2f} ({reps}) | {rss / 1e6:.0f} | {w} | {extra} |", flush=True)


if __name__ == "__main__":
    main()
