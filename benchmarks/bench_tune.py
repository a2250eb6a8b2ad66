"""Benchmark: ``kbs tune`` on the tuning part of the shared vehicle scans (benchmarks/splits.yaml),
with examples/rules/outdoor-tune.yaml (outdoor.yaml with four thresholds marked ``tune:``), then
the tuned values and the file's own on the validation part, which the tuning never saw.
``--kind airborne``: the same on the airborne parts, with examples/rules/airborne-tune.yaml and
ISPRS total error (lower is better) as the score.

Prints markdown: the tune report (score per fold on the held-back scan, the file's values on the
same scan, which thresholds moved), the settings best on the tuning part with their score per
scan (and on how many scans each beats the file's values), the lines of the tuned rule file that
changed, and the score per validation scan for both rule files.

Usage: python benchmarks/bench_tune.py [--kind vehicle|airborne] [--rules FILE] [--folds K]
                                      [--time-limit S] [--jobs N] [--no-validate] [--out TUNED.yaml]
                                      [--top N]
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
#: kind of benchmarks/splits.yaml -> (bench_ground sets, marked rule file, kbs tune metric)
KINDS = {"vehicle": (["kitti", "gndnet", "seq00"], "outdoor-tune.yaml", "f1"),
         "airborne": (["isprs", "las"], "airborne-tune.yaml", "total_error")}
LABEL = {"f1": "ground F1", "total_error": "total error %"}


def part_scans(part: str, kind: str = "vehicle") -> list[bench_ground.Scan]:
    """The scans of one part of benchmarks/splits.yaml's ``kind``, in its order."""
    wanted = bench_ground.splits()[kind][part]
    by_key = {f"{s.dataset}/{s.name}": s for s in bench_ground.scans(KINDS[kind][0])}
    return [by_key[k] for k in wanted]


def vehicle_scans(part: str) -> list[bench_ground.Scan]:
    """The vehicle scans of one part of benchmarks/splits.yaml, in its order."""
    return part_scans(part, "vehicle")


def best_settings(result, top: int) -> str:
    """The ``top`` settings best on the mean over the scans, the file's values first: the score
    per scan, the median, and on how many scans each is better / worse than the file's values."""
    sign = -1 if result.metric == "total_error" else 1
    scores, orig = result.scores, result.original
    ev = sorted(result.evaluated, key=lambda i: -sign * float(np.mean(scores[i])))
    names = [t.name.split(".", 1)[1] for t in result.tunables]
    lines = ["| setting (moved from the file's values) | " + " | ".join(result.scans) + " | median | mean | better / worse |",
             "|---|" + "---:|" * (len(result.scans) + 3)]
    for i in [orig] + [i for i in ev if i != orig][:top]:
        moved = [f"{n} {result.settings[i][t.name]:g}" for n, t in zip(names, result.tunables)
                 if result.settings[i][t.name] != t.value]
        d = sign * (scores[i] - scores[orig])
        x = scores[i] * (100.0 if result.metric == "total_error" else 1.0)
        what = ", ".join(moved) or "(the file's values)"
        lines.append(f"| {what} | " + " | ".join(f"{v:.4f}" for v in x)
                     + f" | {statistics.median(x):.4f} | {float(np.mean(x)):.4f} | "
                     f"{int((d > 1e-9).sum())} / {int((d < -1e-9).sum())} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=list(KINDS), default="vehicle")
    ap.add_argument("--rules", default=None, help="default: examples/rules/outdoor-tune.yaml (airborne: airborne-tune.yaml)")
    ap.add_argument("--folds", type=int, default=None)
    ap.add_argument("--select", choices=["mean", "median"], default="mean",
                    help="how a setting's tuning scores are combined to choose it (kbs tune --select)")
    ap.add_argument("--time-limit", type=float, default=None)
    ap.add_argument("--jobs", type=int, default=-1)
    ap.add_argument("--no-validate", action="store_true")
    ap.add_argument("--out", default=None, help="also write the tuned rule file here")
    ap.add_argument("--top", type=int, default=10, help="settings listed beside the file's values")
    args = ap.parse_args()
    sets, default_rules, metric = KINDS[args.kind]
    args.rules = args.rules or str(ROOT / "examples" / "rules" / default_rules)
    if not bench_ground.DATA.is_dir():
        sys.exit(f"the benchmark needs the real scans in {bench_ground.DATA}")
    rb = load_rule_base(args.rules)
    tuning = part_scans("tune", args.kind)
    scans = [LabelledScan(f"{s.dataset}/{s.name}", s.xyz, s.truth, s.valid, s.sensor) for s in tuning]
    print(f"> tuning part: {', '.join(s.name for s in scans)}; validation part: "
          f"{', '.join(bench_ground.splits()[args.kind]['validate'])}\n")
    t0 = time.perf_counter()
    result = tune(rb, scans, ground_label="ground", folds=args.folds, metric=metric, jobs=args.jobs, select=args.select,
                  time_limit=args.time_limit, progress=lambda m: print(f"\r{m}", end="", file=sys.stderr, flush=True))
    print(file=sys.stderr)
    print(format_report(result, str(Path(args.rules).relative_to(ROOT) if Path(args.rules).is_relative_to(ROOT)
                                     else args.rules)))
    print(f"\nThe {args.top} settings best on the mean over the tuning scans ({LABEL[metric]}, as kbs tune "
          "scores; better / worse: scans on which the setting beats / loses to the file's values):\n")
    print(best_settings(result, args.top))
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
    print(f"\nValidation part (never seen while tuning), {LABEL[metric]}:\n")
    print("| scan | points | file's values | tuned | seconds (both) |")
    print("|---|---:|---:|---:|---:|")
    rows = []
    for s in part_scans("validate", args.kind):
        ls = LabelledScan(s.name, s.xyz, s.truth, s.valid, s.sensor)
        t1 = time.perf_counter()
        f1 = []
        for r in (rb, tuned):
            with Interpreter(r, sensor=s.sensor, jobs=args.jobs) as it:
                m = scan_metrics(it.run(s.xyz).label == gi, ls)
                f1.append(100.0 * m.total_error if metric == "total_error" else m.f1)
        rows.append(f1)
        print(f"| {s.dataset}/{s.name} | {len(s.xyz):,} | {f1[0]:.4f} | {f1[1]:.4f} | {time.perf_counter() - t1:.0f} |",
              flush=True)
    a, b = np.array(rows).T
    print(f"| median | | {statistics.median(a):.4f} | {statistics.median(b):.4f} | |")
    print(f"| mean | | {a.mean():.4f} | {b.mean():.4f} | |")


if __name__ == "__main__":
    main()
