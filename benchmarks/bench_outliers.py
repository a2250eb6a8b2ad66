"""Benchmark: airborne ground filtering with low outliers, kbs airborne against CSF, same run.

Several ISPRS filter-test samples the shared data do not hold (samp41, samp71) have low outliers:
multipath returns a few metres below the terrain. A filter that takes the lowest points for
ground pulls its surface down under them. This adds N such points to each shared ISPRS sample
(copies of N of its points, 3-15 m lower; labelled object, as the ISPRS reference labels them)
and prints the total error % of kbs (``rules/airborne.yaml``, one process) and CSF on the same
points, for each N.

Usage: python benchmarks/bench_outliers.py [--counts 0 10 50] [--seed 0] [--no-csf]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_ground as bg  # noqa: E402
import peers  # noqa: E402

import kbs  # noqa: E402
from kbs.evaluation import ground_metrics  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[0, 10, 50], help="low outliers added per sample")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-csf", action="store_true")
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bg.DATA}")
    csf = not args.no_csf and not peers.available("CSF")
    if not args.no_csf and not csf:
        print(f"> CSF is not available and is skipped: {peers.available('CSF')}")
    seg = kbs.Segmenter("airborne", jobs=1)
    print("| sample | part | low outliers | kbs airborne total error % | CSF total error % |")
    print("|---|---|---:|---:|---:|")
    for s in bg.scans(["isprs"]):
        rng = np.random.default_rng(args.seed)
        for n in args.counts:
            pick = rng.choice(len(s.xyz), n, replace=False)
            low = s.xyz[pick] - np.column_stack([np.zeros((n, 2)), rng.uniform(3.0, 15.0, n)])
            X = np.vstack([s.xyz, low])
            truth = np.concatenate([s.truth, np.zeros(n, bool)]).astype(int)
            res = seg.segment(X)
            ground = res.label == res.label_names.index("ground")
            e_kbs = 100 * ground_metrics(ground, truth, ground_values=(1,)).total_error
            e_csf = (f"{100 * ground_metrics(np.asarray(peers.csf(X, s.frame), bool), truth, ground_values=(1,)).total_error:.2f}"
                     if csf else "-")
            print(f"| {s.name} | {bg.part_of(s)} | {n} | {e_kbs:.2f} | {e_csf} |", flush=True)


if __name__ == "__main__":
    main()
