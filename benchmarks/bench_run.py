"""Benchmark: the main command end to end, ``kbs run --rules outdoor SCAN``, as a user runs it (a new
process each time: start-up, imports, reading, segmentation, writing the PLY and the JSON).

Prints a markdown table: for each ``--jobs`` value, the median, min and max wall time over the
runs, and the ratio to ``-j 1`` measured in the same run (the machine is shared: compare ratios,
not absolute times across runs). Runs alternate between the settings so that a busy spell hits
both alike.

Usage: python benchmarks/bench_run.py [--scan PATH] [--repeats 5] [--jobs 1 2]
"""
from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def kbs_command() -> list[str]:
    exe = shutil.which("kbs", path=str(Path(sys.executable).parent)) or shutil.which("kbs")
    return [exe] if exe else [sys.executable, "-m", "kbs.cli.main"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path, default=DATA / "semantickitti" / "000001.points.npy")
    ap.add_argument("--rules", default="outdoor")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    if not args.scan.is_file():
        sys.exit(f"no scan at {args.scan}")
    times: dict[int, list[float]] = {j: [] for j in args.jobs}
    with tempfile.TemporaryDirectory() as out:
        for _ in range(args.repeats):
            for j in args.jobs:
                t0 = time.perf_counter()
                r = subprocess.run(kbs_command() + ["-q", "run", "--rules", args.rules, str(args.scan), "--out", out,
                                                    "-j", str(j)], capture_output=True, text=True)
                dt = time.perf_counter() - t0
                if r.returncode != 0:
                    sys.exit(f"kbs run failed ({r.returncode}): {r.stderr}")
                times[j].append(dt)
    base = statistics.median(times[args.jobs[0]])
    print(f"`kbs run --rules {args.rules} {args.scan.name}`, {args.repeats} runs each, wall time of the process\n")
    print(f"| jobs | median s | min s | max s | ratio to -j {args.jobs[0]} |")
    print("|---:|---:|---:|---:|---:|")
    for j in args.jobs:
        med = statistics.median(times[j])
        print(f"| {j} | {med:.2f} | {min(times[j]):.2f} | {max(times[j]):.2f} | {med / base:.2f} |")


if __name__ == "__main__":
    main()
