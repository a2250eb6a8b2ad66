"""Benchmark: airborne ground filtering with low outliers, kbs airborne against CSF, same run.

Several ISPRS filter-test samples the shared data do not hold (samp41, samp71) have low outliers:
multipath returns a few metres below the terrain. A filter that takes the lowest points for
ground pulls its surface down under them. This adds N such points to each shared ISPRS sample
(copies of N of its points, 3-15 m lower, kept only where the copy lands at least 0.5 m below
every reference bare-earth point among the 16 nearest in plan: a copy of a tree top dropped 3 m is
still above the ground and is no low outlier; labelled object, as the ISPRS reference labels them)
and prints the total error % of kbs (``rules/airborne.yaml``, one process) and CSF on the same
points, for each N, and how many of the N each labels ground.

Usage: python benchmarks/bench_outliers.py [--counts 0 10 50] [--seed 0] [--no-csf] [--rules FILE]
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


def low_outliers(xyz: np.ndarray, ground: np.ndarray, n: int, rng: np.random.Generator,
                 below: float = 0.5) -> np.ndarray:
    """``n`` copies of points of ``xyz`` lowered by 3-15 m, each at least ``below`` m under every
    bare-earth point (``ground``, a mask) among the 16 nearest to it in plan: candidates are drawn
    (without replacement) until ``n`` of them land under the terrain."""
    from scipy.spatial import cKDTree

    G = xyz[ground]
    tree = cKDTree(G[:, :2])
    out: list[np.ndarray] = []
    order = rng.permutation(len(xyz))
    for start in range(0, len(order), max(4 * n, 64)):
        if sum(len(o) for o in out) >= n:
            break
        pick = order[start:start + max(4 * n, 64)]
        low = xyz[pick] - np.column_stack([np.zeros((pick.size, 2)), rng.uniform(3.0, 15.0, pick.size)])
        _, i = tree.query(low[:, :2], k=min(16, len(G)))
        floor = G[:, 2][i.reshape(pick.size, -1)].min(axis=1)
        out.append(low[low[:, 2] < floor - below])
    low = np.concatenate(out)[:n] if out else np.empty((0, 3))
    if len(low) < n:
        raise SystemExit(f"only {len(low)} of {n} copies land under the terrain")
    return low


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[0, 10, 50], help="low outliers added per sample")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-csf", action="store_true")
    ap.add_argument("--rules", default="airborne", help="the rule base (default: the shipped airborne)")
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bg.DATA}")
    csf = not args.no_csf and not peers.available("CSF")
    if not args.no_csf and not csf:
        print(f"> CSF is not available and is skipped: {peers.available('CSF')}")
    seg = kbs.Segmenter(args.rules, jobs=1)
    print(f"| sample | part | low outliers | kbs {seg.rule_base.name} total error % | of the outliers, kbs ground "
          "| CSF total error % | of the outliers, CSF ground |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for s in bg.scans(["isprs"]):
        rng = np.random.default_rng(args.seed)
        for n in args.counts:
            low = low_outliers(s.xyz, s.truth, n, rng)
            X = np.vstack([s.xyz, low])
            truth = np.concatenate([s.truth, np.zeros(n, bool)]).astype(int)
            res = seg.segment(X)
            ground = res.label == res.label_names.index("ground")
            e_kbs = 100 * ground_metrics(ground, truth, ground_values=(1,)).total_error
            e_csf = o_csf = "-"
            if csf:
                g_csf = np.asarray(peers.csf(X, s.frame), bool)
                e_csf = f"{100 * ground_metrics(g_csf, truth, ground_values=(1,)).total_error:.2f}"
                o_csf = str(int(g_csf[len(s.xyz):].sum()))
            print(f"| {s.name} | {bg.part_of(s)} | {n} | {e_kbs:.2f} | {int(ground[len(s.xyz):].sum())} | {e_csf} | {o_csf} |",
                  flush=True)


if __name__ == "__main__":
    main()
