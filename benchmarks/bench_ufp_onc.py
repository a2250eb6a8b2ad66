"""Benchmark: UFP-ONC (k_max = 10) against scikit-learn's GaussianMixture sweep, on real scans.

Prints a markdown table: for 100k, 300k and 1M points, the median wall time and peak memory of
``kbs.inference.ufp_onc(X, k_max=10)`` next to ``GaussianMixture(K, covariance_type='full')``
fitted for K = 1 .. 10 on the same data in the same run, and their ratio.

Data: the SemanticKITTI scan and the two GndNet scans of ../shared/data (288,173 real points),
tiled side by side (each copy shifted 250 m in x) up to the size wanted.

Usage: python benchmarks/bench_ufp_onc.py [--sizes 100000 300000 1000000] [--repeats 5]
       [--gmm-repeats 1] [--no-gmm]
Each measurement runs in a fresh child process, so its peak RSS is its own.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import platform
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def real_cloud(n: int) -> np.ndarray:
    parts = [np.load(DATA / "semantickitti" / "000001.points.npy")[:, :3],
             np.load(DATA / "gndnet" / "000000.points.npy")[:, :3],
             np.load(DATA / "gndnet" / "000001.points.npy")[:, :3]]
    pool = np.vstack(parts).astype(np.float64)
    tiles = [pool + [250.0 * i, 0.0, 0.0] for i in range(int(np.ceil(n / len(pool))))]
    return np.vstack(tiles)[:n]


def _run(kind: str, n: int, trace: bool, queue) -> None:
    X = real_cloud(n)
    if kind == "ufp_onc":
        from kbs.inference import ufp_onc

        call = lambda: ufp_onc(X, k_max=10)  # noqa: E731
    else:
        from sklearn.mixture import GaussianMixture

        def call():
            for k in range(1, 11):
                GaussianMixture(k, covariance_type="full", random_state=0).fit(X)

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    out = call()
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] if trace else 0
    if trace:
        tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    queue.put({"seconds": dt, "traced_peak": peak, "rss_peak": rss * 1024, "rss_before": rss0 * 1024,
               "k": getattr(out, "chosen_k", None)})


def measure(kind: str, n: int, repeats: int) -> dict:
    ctx = mp.get_context("spawn")
    runs = []
    for r in range(repeats + 1):  # the last run traces allocations (slower, not timed)
        q = ctx.Queue()
        p = ctx.Process(target=_run, args=(kind, n, r == repeats, q))
        p.start()
        res = q.get()
        p.join()
        runs.append(res)
    timed = runs[:-1]
    return {"median": statistics.median(r["seconds"] for r in timed), "runs": len(timed),
            "traced_peak": runs[-1]["traced_peak"], "rss_peak": max(r["rss_peak"] for r in timed),
            "rss_before": max(r["rss_before"] for r in timed), "k": timed[0]["k"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000, 1_000_000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--gmm-repeats", type=int, default=1)
    ap.add_argument("--no-gmm", action="store_true")
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"benchmark needs the real scans in {DATA}")
    import sklearn

    print(f"machine: {platform.machine()}, {mp.cpu_count()} cores, Python {platform.python_version()}, "
          f"numpy {np.__version__}, scikit-learn {sklearn.__version__}\n")
    print("| points | ufp_onc median s (runs) | ufp_onc peak alloc MB | ufp_onc peak RSS MB | chosen K "
          "| GMM sweep median s (runs) | GMM peak RSS MB | GMM / ufp_onc |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.sizes:
        u = measure("ufp_onc", n, args.repeats)
        g = None if args.no_gmm else measure("gmm", n, args.gmm_repeats)
        gcol = (f"{g['median']:.2f} ({g['runs']}) | {g['rss_peak'] / 1e6:.0f} | {g['median'] / u['median']:.1f}x"
                if g else "not run | | ")
        print(f"| {n:,} | {u['median']:.3f} ({u['runs']}) | {u['traced_peak'] / 1e6:.0f} | "
              f"{u['rss_peak'] / 1e6:.0f} | {u['k']} | {gcol} |", flush=True)
    print("\npeak alloc: numpy/Python allocations traced during the call (tracemalloc, one extra run); "
          "peak RSS: the child process's maximum resident set, interpreter and data included.")


if __name__ == "__main__":
    main()
