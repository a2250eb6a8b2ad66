"""Benchmark: generated forest tiles (issue 12's forest failure kind), kbs against CSF in the same run.

Usage: python benchmarks/bench_forest.py [--part tune|validate|all] [--rules FILE] [--before FILE]
                                         [--density D] [--no-csf] [--seeds FIRST LAST]

The scenes are ``benchmarks/forest_scenes.forest_scene`` (100 m x 100 m of hilly ground under
50-95 % canopy, 1-4 pulses per square metre, up to three returns a pulse; its docstring says what
is drawn and from which ranges), the seeds of each part as benchmarks/splits.yaml's
``airborne-forest-generated`` declares them. ``--density`` replaces every scene's pulse density
(10: the density of a modern survey). kbs runs the rule file (default: the shipped airborne) in
one process (``jobs=1``; the labels do not depend on it), centred as bench_ground.py centres the
airborne scans, with no sensor; CSF as bench_ground.py runs it on airborne scans (cloth 0.5 m,
slope smoothing on). ``--seeds`` runs the seeds FIRST..LAST instead of the parts' (part 'extra':
seeds neither part holds). Prints one markdown row per scene (ground precision, recall, F1, total error
%, seconds) and the medians per part.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_ground as bg  # noqa: E402
import peers  # noqa: E402
from forest_scenes import forest_scene  # noqa: E402

from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402


def scores(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float, float, float]:
    """Ground precision, recall, F1 and total error % of the mask ``pred`` against ``truth``."""
    tp = float((pred & truth).sum())
    fp = float((pred & ~truth).sum())
    fn = float((~pred & truth).sum())
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
    return precision, recall, f1, 100.0 * (fp + fn) / truth.size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=["tune", "validate", "all"], default="all")
    ap.add_argument("--rules", default="airborne", help="the rule file (default: the shipped airborne)")
    ap.add_argument("--before", help="another rule file, scored in the same run (e.g. the one before a change)")
    ap.add_argument("--density", type=float, help="pulses per square metre for every scene (default: each scene's)")
    ap.add_argument("--no-csf", action="store_true", help="kbs only")
    ap.add_argument("--seeds", nargs=2, type=int, metavar=("FIRST", "LAST"),
                    help="the scenes FIRST..LAST instead of the parts' (part 'extra')")
    args = ap.parse_args()
    seeds = dict(bg.splits()["airborne-forest-generated"])
    parts = ["tune", "validate"] if args.part == "all" else [args.part]
    if args.seeds:
        if args.seeds[0] > args.seeds[1]:
            ap.error(f"--seeds: FIRST {args.seeds[0]} is after LAST {args.seeds[1]}")
        parts, seeds["extra_seeds"] = ["extra"], list(args.seeds)
    methods = ([("kbs " + Path(args.before).stem, args.before)] if args.before else []) + [("kbs " + Path(args.rules).stem, args.rules)]
    rbs = {name: load_rule_base(f) for name, f in methods}
    names = [name for name, _ in methods] + ([] if args.no_csf else ["CSF"])
    print(f"density: {'each scene its own' if args.density is None else f'{args.density:g} pulses/m2'}\n")
    print("| part | seed | points | canopy cover | penetration | slope % | method | precision | recall | F1 | "
          "total error % | seconds |")
    print("|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|")
    rows: dict[tuple[str, str], list[tuple[float, ...]]] = {}
    for part in parts:
        lo, hi = seeds[f"{part}_seeds"]
        for seed in range(lo, hi + 1):
            X, labels, drawn = forest_scene(seed, density=args.density)
            X = X - X.mean(axis=0)
            truth = labels == 0
            for name in names:
                t0 = time.perf_counter()
                if name == "CSF":
                    pred = peers.csf(X, peers.Frame(np.eye(3), 0.0, airborne=True))
                else:
                    rb = rbs[name]
                    pred = Interpreter(rb, jobs=1).run(X).label == rb.label_names.index("ground")
                sec = time.perf_counter() - t0
                s = scores(pred, truth)
                rows.setdefault((part, name), []).append((*s, sec))
                print(f"| {part} | {seed} | {len(X):,} | {drawn['cover']:.2f} | {drawn['penetration']:.2f} | "
                      f"{100 * drawn['slope']:.0f} | {name} | {s[0]:.3f} | {s[1]:.3f} | {s[2]:.3f} | {s[3]:.2f} | "
                      f"{sec:.2f} |", flush=True)
    print("\n| part | method | scenes | median precision | median recall | median F1 | median total error % | "
          "worst F1 | median seconds |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for (part, name), rs in rows.items():
        med = [statistics.median(r[i] for r in rs) for i in range(5)]
        print(f"| {part} | {name} | {len(rs)} | {med[0]:.3f} | {med[1]:.3f} | {med[2]:.3f} | {med[3]:.2f} | "
              f"{min(r[2] for r in rs):.3f} | {med[4]:.2f} |")


if __name__ == "__main__":
    main()
