"""Benchmark: ``kbs tune`` on the tuning part of the shared vehicle scans (benchmarks/splits.yaml),
with examples/rules/outdoor-tune.yaml (outdoor.yaml with four thresholds marked ``tune:``), then
the tuned values and the file's own on the validation part, which the tuning never saw.

Prints markdown: the tune report (score per fold on the held-back scan, the file's values on the
same scan, which thresholds moved), the lines of the tuned rule file that changed, and ground F1
per validation scan for both rule files.

Usage: python benchmarks/bench_tune.py [--rules FILE] [--folds K] [--time-limit S] [--jobs N]
                                      [--no-validate] [--out TUNED.yaml]
"""
from __future__ import annotations

import argparse
import difflib
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_ground  # noqa: E402

from kbs.evaluation.tune import LabelledScan, format_report, scan_metrics, tune, tuned_text  # noqa: E402
from kbs.knowledge import Interpreter, load_rule_base  # noqa: E402
from kbs.knowledge.rulebase import parse_rule_base  # noqa: E402
from kbs.knowledge.tuning import registry_of  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SETS = ["kitti", "gndnet", "seq00"]


def vehicle_scans(part: str) -> list[bench_ground.Scan]:
    """The vehicle scans of one part of benchmarks/splits.yaml, in its order."""
    wanted = bench_ground.splits()["vehicle"][part]
    by_key = {f"{s.dataset}/{s.name}": s for s in bench_ground.scans(SETS)}
    return [by_key[k] for k in wanted]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rules", default=str(ROOT / "examples" / "rules" / "outdoor-tune.yaml"))
    ap.add_argument("--folds", type=int, default=None)
    ap.add_argument("--time-limit", type=float, default=None)
    ap.add_argument("--jobs", type=int, default=-1)
    ap.add_argument("--no-validate", action="store_true")
    ap.add_argument("--out", default=None, help="also write the tuned rule file here")
    args = ap.parse_args()
    if not bench_ground.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bench_ground.DATA}")
    rb = load_rule_base(args.rules)
    tuning = vehicle_scans("tune")
    scans = [LabelledScan(f"{s.dataset}/{s.name}", s.xyz, s.truth, s.valid, s.sensor) for s in tuning]
    print(f"> tuning part: {', '.join(s.name for s in scans)}; validation part: "
          f"{', '.join(bench_ground.splits()['vehicle']['validate'])}\n")
    t0 = time.perf_counter()
    result = tune(rb, scans, ground_label="ground", folds=args.folds, metric="f1", jobs=args.jobs,
                  time_limit=args.time_limit)
    print(format_report(result, str(Path(args.rules).relative_to(ROOT) if Path(args.rules).is_relative_to(ROOT)
                                     else args.rules)))
    text = tuned_text(rb, result, Path(args.rules).read_text())
    if args.out:
        Path(args.out).write_text(text)
    print("\nLines of the tuned rule file that changed:\n\n```")
    old = Path(args.rules).read_text().splitlines()
    for line in difflib.ndiff(old, text.splitlines()):
        if line.startswith("+ "):
            print(line[2:])
    print(f"```\n\n(tuning: {time.perf_counter() - t0:.0f} s)")
    if args.no_validate:
        return
    tuned = parse_rule_base(text, "tuned.yaml", registry_of(rb))
    gi = rb.label_names.index("ground")
    print("\nValidation part (never seen while tuning), ground F1:\n")
    print("| scan | points | file's values | tuned | seconds (both) |")
    print("|---|---:|---:|---:|---:|")
    rows = []
    for s in vehicle_scans("validate"):
        ls = LabelledScan(s.name, s.xyz, s.truth, s.valid, s.sensor)
        t1 = time.perf_counter()
        f1 = []
        for r in (rb, tuned):
            with Interpreter(r, sensor=s.sensor, jobs=args.jobs) as it:
                f1.append(scan_metrics(it.run(s.xyz).label == gi, ls).f1)
        rows.append(f1)
        print(f"| {s.dataset}/{s.name} | {len(s.xyz):,} | {f1[0]:.4f} | {f1[1]:.4f} | {time.perf_counter() - t1:.0f} |",
              flush=True)
    a, b = np.array(rows).T
    print(f"| median | | {statistics.median(a):.4f} | {statistics.median(b):.4f} | |")
    print(f"| mean | | {a.mean():.4f} | {b.mean():.4f} | |")


if __name__ == "__main__":
    main()
