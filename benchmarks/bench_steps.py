"""Benchmark: kbs airborne alone, total error %, on the airborne scans of benchmarks/splits.yaml,
on generated terrain steps and on generated urban blocks with large roofs, against another rule
file in the same run (issue 12: a terrace above a terrain step taken for a roof; the roofs of
large buildings taken for ground).

Usage: python benchmarks/bench_steps.py [--part tune|validate|all] [--before FILE] [--rules FILE]
                                        [--no-scans] [--no-generated] [--no-roofs]

Prints one markdown row per scan (total error % with each rule file, the difference) and the
median per part. The generated scenes are ``tests/scenes.airborne_step_and_building`` (level
terrain 160 m x 160 m, 1 point per square metre, a terrain step of 1.5, 2, 3, 4 or 5 m with a 2 m
wide bank, a flat-roofed building 7 m up beside it; seeds 9, 1, 2; and, since session 38, steps of
8, 10 and 12 m, seed 9), whole (the upper terrace and its bank one patch) and cropped to their
middle 90 m x 90 m (the bank a patch of its own), and ``tests/scenes.airborne_pit`` (a quarry pit
8 or 12 m deep in 1 % terrain, a building beside it; seeds 3, 4). Steps of 1.5 and 2 m are below
`roofs`' 2.5 m: what `understory` and `low_terraces` decide; from 7 m, and in the pits, the
terrain above the face is a plateau (`drops`, `open_surface`, `vast`). kbs runs
in one process (``jobs=1``: the same labels as any number of processes), as bench_ground.py's
'kbs airborne' rows. The urban blocks are ``benchmarks/roof_scenes.roofs_scene``, the seeds of
each part as benchmarks/splits.yaml's ``airborne-roofs-generated`` declares them (part
'roofs tune' / 'roofs validate').
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
import bench_ground as bg  # noqa: E402
from roof_scenes import roofs_scene  # noqa: E402
from scenes import airborne_pit, airborne_step_and_building  # noqa: E402

from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402


def generated() -> list[bg.Scan]:
    out = []
    for crop in (False, True):
        for step, seed in ((1.5, 9), (2.0, 9), (3.0, 9), (4.0, 9), (5.0, 9), (4.0, 1), (4.0, 2), (8.0, 9), (10.0, 9),
                           (12.0, 9)):
            X, labels = airborne_step_and_building(seed=seed, step=step)
            if crop:
                keep = (np.abs(X[:, 0] - 512000.0) < 45) & (np.abs(X[:, 1] - 5400000.0) < 45)
                X, labels = X[keep], labels[keep]
            X = X - X.mean(axis=0)
            name = f"step {step:g} m, seed {seed}" + (", cropped" if crop else "")
            out.append(bg.Scan("generated", name, X, labels == 0, np.ones(len(X), bool), None,
                               np.array([0.0, 0.0, X[:, 2].min() - 10.0]), 0.5))
    for depth, seed in ((8.0, 3), (12.0, 3), (8.0, 4), (12.0, 4)):
        X, labels = airborne_pit(seed=seed, depth=depth)
        X = X - X.mean(axis=0)
        out.append(bg.Scan("generated", f"pit {depth:g} m, seed {seed}", X, labels == 0, np.ones(len(X), bool), None,
                           np.array([0.0, 0.0, X[:, 2].min() - 10.0]), 0.5))
    return out


def roofs(part: str) -> list[tuple[str, bg.Scan]]:
    """The generated urban blocks of ``part`` ('tune', 'validate' or 'all'): (part, scan)."""
    out = []
    for p in (("tune", "validate") if part == "all" else (part,)):
        lo, hi = bg.splits()["airborne-roofs-generated"][f"{p}_seeds"]
        for seed in range(int(lo), int(hi) + 1):
            X, labels, _ = roofs_scene(seed)
            X = X - X.mean(axis=0)
            out.append((f"roofs {p}", bg.Scan("generated", f"roofs, seed {seed}", X, labels == 0, np.ones(len(X), bool),
                                              None, np.array([0.0, 0.0, X[:, 2].min() - 10.0]), 0.5)))
    return out


def total_error(rules: str, scan: bg.Scan) -> float:
    rb = load_rule_base(rules)
    seg = Interpreter(rb, sensor=scan.sensor, jobs=1).run(scan.xyz)
    pred = (seg.label == rb.label_names.index("ground"))[scan.valid]
    truth = scan.truth[scan.valid]
    return 100.0 * float((pred != truth).sum()) / truth.size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=["tune", "validate", "all"], default="all")
    ap.add_argument("--rules", default="airborne", help="the rule file (default: the shipped airborne)")
    ap.add_argument("--before", help="another rule file, scored in the same run (e.g. the one before a change)")
    ap.add_argument("--no-scans", action="store_true", help="only the generated scenes")
    ap.add_argument("--no-generated", action="store_true", help="no generated terrain steps")
    ap.add_argument("--no-roofs", action="store_true", help="no generated urban blocks")
    args = ap.parse_args()
    files = ([args.before] if args.before else []) + [args.rules]
    todo: list[tuple[str, bg.Scan]] = []
    if not args.no_scans:
        todo += [(bg.part_of(s), s) for s in bg.scans(["isprs", "las"]) if args.part == "all" or bg.part_of(s) == args.part]
    if not args.no_generated:
        todo += [("generated", s) for s in generated()]
    if not args.no_roofs:
        todo += roofs(args.part)
    heads = " | ".join(["before", "after", "after - before"] if args.before else ["total error %"])
    print(f"| data set | scan | part | {heads} |")
    print("|---|---|---|" + "---:|" * (3 if args.before else 1))
    per_part: dict[tuple[str, str], list[list[float]]] = {}
    for part, scan in todo:
        te = [total_error(f, scan) for f in files]
        cells = [f"{v:.2f}" for v in te] + ([f"{te[1] - te[0]:+.2f}"] if args.before else [])
        print(f"| {scan.dataset} | {scan.name} | {part} | {' | '.join(cells)} |", flush=True)
        for key in ((part, scan.dataset), (part, "all")):
            per_part.setdefault(key, []).append(te)
    print("\n| part | data set | scans | " + ("median before | median after" if args.before else "median") + " |")
    print("|---|---|---:|---:|" + ("---:|" if args.before else ""))
    for (part, ds), rows in per_part.items():
        meds = [statistics.median(r[i] for r in rows) for i in range(len(files))]
        print(f"| {part} | {ds} | {len(rows)} | {' | '.join(f'{m:.2f}' for m in meds)} |")


if __name__ == "__main__":
    main()
