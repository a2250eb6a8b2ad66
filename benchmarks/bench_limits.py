"""Benchmark: the limits of the shipped rule bases on the real scans — which limits stop how many
clusters (per kind, as ``kbs run`` prints them), the quality and the time, and optionally the same
at other ``max_depth`` values (to choose one: the quality of the rule bases depends on where the
splitting stops).

Scans and set-ups are those of bench_ground.py (outdoor: SemanticKITTI, GndNet, ISPRS, mOSD;
airborne: ISPRS; tabletop: mOSD) and bench_planar.py (planar_contest: mOSD and 5 generated
polyhedral scenes). Quality: ground F1 and ISPRS total error for the ground rule bases, Hoover
correct detections (T = 0.8) for planar_contest.

Usage: python benchmarks/bench_limits.py [--rules outdoor airborne tabletop planar_contest]
       [--depths 10 11 12 14 16 20 24] [--sets kitti gndnet isprs mosd] [--jobs N]
"""
from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_ground  # noqa: E402
import bench_planar  # noqa: E402

from kbs.evaluation import ground_metrics, hoover  # noqa: E402
from kbs.knowledge import Interpreter, PredicateRegistry, load_rule_base  # noqa: E402
from kbs.knowledge.rulebase import parse_rule_base  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"outdoor": "outdoor", "airborne": "airborne", "planar_contest": "planar_contest",
           "tabletop": str(ROOT / "examples" / "rules" / "tabletop.yaml")}
GROUND = {"outdoor": ("ground", None), "airborne": ("ground", "ISPRS"), "tabletop": ("table", "mOSD table")}
SHORT = {"max_depth": "depth", "min_points": "min_points", "max_clusters": "max_clusters", "k_max": "k_max",
         "split_failed": "failed", "single_cluster": "single", "unpartitioned": "unpartitioned"}


def with_depth(name: str, depth: int | None):
    rb = load_rule_base(SOURCES[name])
    if depth is None:
        return rb
    text = re.sub(r"max_depth: \d+", f"max_depth: {depth}", rb.text)
    return parse_rule_base(text, Path(rb.path).name, PredicateRegistry.default())


def items(name: str, sets: list[str], ground_scans):
    """(data set, scan, points, sensor, scorer) for the scans a rule base is run on."""
    if name == "planar_contest":
        for group, scene, X, gt, ignore in bench_planar.scenes(5, "mosd" in sets):
            def score(seg, gt=gt, ignore=ignore, X=X):
                h = hoover(seg.cluster.astype(np.int64), gt, tolerance=0.8, ms_ignore=(-1,), gt_ignore=ignore, points=X)
                return {"correct": h.correct}
            yield group, scene, X, None, score
        return
    label, only = GROUND[name]
    for scan in ground_scans:
        if only is not None and scan.dataset != only:
            continue
        def score(seg, scan=scan):
            pred = seg.label == seg.label_names.index(label)
            m = ground_metrics(pred[scan.valid], np.where(scan.truth, 1, 0)[scan.valid], ground_values=(1,))
            return {"F1": m.f1, "total error %": 100 * m.total_error}
        yield scan.dataset, scan.name, scan.xyz, scan.sensor, score


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rules", nargs="+", default=list(SOURCES))
    ap.add_argument("--sets", nargs="+", default=["kitti", "gndnet", "isprs", "mosd"])
    ap.add_argument("--depths", nargs="*", type=int, default=[], help="max_depth values to try besides the shipped one")
    ap.add_argument("--jobs", type=int, default=-1, help="kbs split processes (-1: one per core)")
    args = ap.parse_args()
    if not bench_ground.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bench_ground.DATA}")
    ground_scans = bench_ground.scans(args.sets)
    print("| rule base | max_depth | data set | scan | clusters | splits | stopped, by kind | deepest | quality | seconds |")
    print("|---|---:|---|---|---:|---:|---|---:|---|---:|")
    medians = []
    for name in args.rules:
        for depth in [None, *args.depths]:
            rb = with_depth(name, depth)
            errors = []
            for dataset, scan, X, sensor, score in items(name, args.sets, ground_scans):
                t0 = time.perf_counter()
                seg = Interpreter(rb, sensor=sensor, jobs=args.jobs).run(X)
                dt = time.perf_counter() - t0
                s = seg.summary()
                kinds = ", ".join(f"{SHORT.get(k, k)} {v['count']}" for k, v in s["limits_by_kind"].items()) or "-"
                q = score(seg)
                if dataset == "ISPRS":
                    errors.append(q["total error %"])
                quality = ", ".join(f"{k} {v:.4f}" if k == "F1" else f"{k} {v:.2f}" if isinstance(v, float) else
                                    f"{k} {v}" for k, v in q.items())
                deepest = max(r.depth for r in seg.explanation.records.values())
                print(f"| {name} | {rb.limits['max_depth']}{'' if depth is None else ' (tried)'} | {dataset} | {scan} | "
                      f"{s['clusters']} | {s['splits']} | {kinds} | {deepest} | {quality} | {dt:.2f} |", flush=True)
            if errors:
                medians.append((name, rb.limits["max_depth"], statistics.median(errors)))
    if medians:
        print("\nISPRS median total error:\n")
        print("| rule base | max_depth | median total error % |")
        print("|---|---:|---:|")
        for name, depth, med in medians:
            print(f"| {name} | {depth} | {med:.2f} |")


if __name__ == "__main__":
    main()
