"""Benchmark: ground filtering with low outliers, kbs against a peer, same run.

Airborne (the default): several ISPRS filter-test samples the shared data do not hold (samp41,
samp71) have low outliers: multipath returns a few metres below the terrain. A filter that takes
the lowest points for ground pulls its surface down under them. This adds N such points to each
shared ISPRS sample (copies of N of its points, 3-15 m lower, kept only where the copy lands at
least 0.5 m below every reference bare-earth point among the 16 nearest in plan: a copy of a tree
top dropped 3 m is still above the ground and is no low outlier; labelled object, as the ISPRS
reference labels them) and prints the total error % of kbs (``rules/airborne.yaml``, one process)
and CSF on the same points, for each N, and how many of the N each labels ground.

``--vehicle``: the six vehicle scans (SemanticKITTI, GndNet, SemanticKITTI seq00) with N echoes
reflected under the road (a wet road, a window: SemanticKITTI labels such points 'outlier'):
copies of N labelled-ground points 1-4 m lower, labelled not ground; ground F1 of kbs
(``rules/outdoor.yaml``) and Patchwork++ on the same points, and how many of the N each labels
ground.

Usage: python benchmarks/bench_outliers.py [--counts 0 10 50] [--seed 0] [--no-csf] [--rules FILE]
       python benchmarks/bench_outliers.py --vehicle [--counts 0 100] [--no-peer] [--rules FILE]
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


def reflections(xyz: np.ndarray, ground: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` copies of points of ``xyz`` labelled ground (``ground``, a mask), each 1-4 m lower:
    echoes a vehicle's lidar receives reflected under the road."""
    pick = rng.choice(np.flatnonzero(ground), n, replace=False)
    return xyz[pick] - np.column_stack([np.zeros((n, 2)), rng.uniform(1.0, 4.0, n)])


def vehicle(args: argparse.Namespace) -> None:
    """The vehicle scans with reflections under the road: ground F1, kbs and Patchwork++."""
    pw = not args.no_peer and not peers.available("pypatchworkpp")
    if not args.no_peer and not pw:
        print(f"> Patchwork++ is not available and is skipped: {peers.available('pypatchworkpp')}")
    seg = kbs.Segmenter(args.rules, jobs=1)
    print(f"| scan | part | reflections | kbs {seg.rule_base.name} ground F1 | of them, kbs ground "
          "| Patchwork++ ground F1 | of them, Patchwork++ ground |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for s in bg.scans(["kitti", "gndnet", "seq00"]):
        rng = np.random.default_rng(args.seed)
        for n in args.counts:
            low = reflections(s.xyz, s.truth & s.valid, n, rng)
            X = np.vstack([s.xyz, low])
            truth = np.concatenate([s.truth, np.zeros(n, bool)]).astype(int)
            valid = np.concatenate([s.valid, np.ones(n, bool)])
            res = seg.segment(X, sensor=s.sensor)
            ground = res.label == res.label_names.index("ground")
            f_kbs = ground_metrics(ground[valid], truth[valid], ground_values=(1,)).f1
            f_pw = o_pw = "-"
            if pw:
                g_pw = np.asarray(peers.patchworkpp(X, s.frame), bool)
                f_pw = f"{ground_metrics(g_pw[valid], truth[valid], ground_values=(1,)).f1:.4f}"
                o_pw = str(int(g_pw[len(s.xyz):].sum()))
            print(f"| {s.name} | {bg.part_of(s)} | {n} | {f_kbs:.4f} | {int(ground[len(s.xyz):].sum())} | {f_pw} | {o_pw} |",
                  flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=None,
                    help="outliers added per scan (default: 0 10 50; with --vehicle 0 100)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-csf", action="store_true")
    ap.add_argument("--vehicle", action="store_true", help="the vehicle scans, reflections under the road")
    ap.add_argument("--no-peer", action="store_true", help="with --vehicle: without Patchwork++")
    ap.add_argument("--rules", default=None, help="the rule base (default: the shipped airborne, or outdoor)")
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bg.DATA}")
    if args.vehicle:
        args.counts = args.counts or [0, 100]
        args.rules = args.rules or "outdoor"
        vehicle(args)
        return
    args.counts = args.counts or [0, 10, 50]
    args.rules = args.rules or "airborne"
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
