"""Benchmark: the table plane of table-top scenes, kbs with examples/rules/tabletop.yaml against a
RANSAC plane (Open3D, 1 cm), on the mOSD scans of ../shared/data and on generated scenes
(benchmarks/tabletop_scenes.py), tuning and validation parts of benchmarks/splits.yaml apart.

Prints markdown: one row per scene (table F1 per method), then per part and method the mean and
the lowest F1 and the scenes that fail (table F1 below 0.9). Every method runs in this process on
the same points.

Usage: python benchmarks/bench_tabletop.py [--rules FILE] [--before FILE] [--sets mosd generated]
                                           [--part tune|validate|all] [--seeds FIRST LAST]
``--before`` adds the rows of another rule file (e.g. the one before a change, from
``git show REV:examples/rules/tabletop.yaml``) in the same run. ``--seeds`` runs the generated
scenes FIRST..LAST instead of the parts' (part 'extra': seeds neither part holds, to see how the
rules hold on scenes nobody chose anything on; not the mOSD scans).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402
from bench_ground import CAMERA_Y_DOWN, DATA, ROOT, splits  # noqa: E402
from tabletop_scenes import tabletop_scene  # noqa: E402

from kbs.evaluation import ground_metrics  # noqa: E402
from kbs.io import read_cloud  # noqa: E402
from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402

FAIL = 0.9  # a scene whose table F1 is below this has failed


def seeds(part: str) -> list[int]:
    lo, hi = splits()["table-top-generated"][f"{part}_seeds"]
    return list(range(int(lo), int(hi) + 1))


def scenes(sets: list[str], part: str, extra: tuple[int, int] | None = None):
    """(name, part, points (n, 3), truth: table (n,) bool, valid (n,) bool); with ``extra``
    (first, last), the generated seeds first..last alone, as part 'extra'."""
    if extra is not None:
        for s in range(extra[0], extra[1] + 1):
            X, lab, _ = tabletop_scene(s)
            yield f"generated {s}", "extra", X, lab == 1, np.ones(len(X), bool)
        return
    parts = ["tune", "validate"] if part == "all" else [part]
    if "mosd" in sets:
        kind = splits()["table-top"]
        for p in parts:
            for key in kind[p]:
                name = key.split("/")[-1]
                pc = read_cloud(DATA / "mosd" / f"{name}.pcd")
                lab = pc.fields["label"].astype(int)
                yield f"mOSD {name}", p, pc.xyz, (lab >= 1) & (lab <= 9), lab != 0
    if "generated" in sets:
        for p in parts:
            for s in seeds(p):
                X, lab, _ = tabletop_scene(s)
                yield f"generated {s}", p, X, lab == 1, np.ones(len(X), bool)


def kbs_table(rules: str):
    def run(X: np.ndarray) -> np.ndarray:
        rb = load_rule_base(rules)
        seg = Interpreter(rb, sensor=np.zeros(3), jobs=1).run(X)
        return seg.label == rb.label_names.index("table")
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rules", default=str(ROOT / "examples" / "rules" / "tabletop.yaml"))
    ap.add_argument("--before", help="another rule file, run in the same process (rows 'kbs before')")
    ap.add_argument("--sets", nargs="+", default=["mosd", "generated"])
    ap.add_argument("--part", choices=["tune", "validate", "all"], default="all")
    ap.add_argument("--seeds", nargs=2, type=int, metavar=("FIRST", "LAST"),
                    help="generated scenes FIRST..LAST instead of the parts' (part 'extra')")
    args = ap.parse_args()
    if args.seeds and args.seeds[0] > args.seeds[1]:
        ap.error(f"--seeds: FIRST {args.seeds[0]} is after LAST {args.seeds[1]}")
    methods = {"kbs tabletop": kbs_table(args.rules)}
    if args.before:
        methods = {"kbs before": kbs_table(args.before), **methods}
    why = peers.available("open3d")
    if why:
        print(f"> RANSAC plane is not available and is skipped: {why}")
    else:
        methods["RANSAC plane"] = lambda X: peers.ransac_ground(X, peers.Frame(CAMERA_Y_DOWN, 0.12), 0.01)
    names = list(methods)
    print("| scene | part | points | " + " | ".join(f"{m} F1" for m in names) + " |")
    print("|---|---|---:|" + "---:|" * len(names))
    scores: dict[tuple[str, str], list[tuple[str, float]]] = {}
    seconds: dict[str, float] = dict.fromkeys(names, 0.0)
    for name, part, X, truth, valid in scenes(args.sets, args.part, tuple(args.seeds) if args.seeds else None):
        row = []
        for m, fn in methods.items():
            t0 = time.perf_counter()
            pred = fn(X)
            seconds[m] += time.perf_counter() - t0
            f1 = ground_metrics(pred[valid], np.where(truth, 1, 0)[valid], ground_values=(1,)).f1
            scores.setdefault((part, m), []).append((name, f1))
            row.append(f"{f1:.4f}")
        print(f"| {name} | {part} | {len(X):,} | " + " | ".join(row) + " |", flush=True)
    print("\n| part | method | scenes | mean F1 | lowest F1 | failed (F1 < 0.9) |")
    print("|---|---|---:|---:|---:|---|")
    for (part, m), vals in scores.items():
        failed = [f"{n} ({f:.3f})" for n, f in vals if f < FAIL]
        print(f"| {part} | {m} | {len(vals)} | {statistics.mean(f for _, f in vals):.4f} | "
              f"{min(f for _, f in vals):.4f} | {len(failed)}{': ' + ', '.join(failed) if failed else ''} |")
    print("\nseconds per method, all scenes: " + ", ".join(f"{m} {s:.1f}" for m, s in seconds.items()))


if __name__ == "__main__":
    main()
