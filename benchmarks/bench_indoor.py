"""The indoor rule base (rules/indoor.yaml) on Bobkov et al.'s room1 (../shared/data/bobkov): the
F1 of structure (floor, wall, ceiling) against GT label 0 and of furniture against GT > 0, on the
whole room and on its two halves, x < 0 (where `tall` was set) and x >= 0 (not looked at when it
was), and each label's share of GT structure. Prints a markdown table (docs/BENCHMARKS.md, Indoor).

    .venv/bin/python benchmarks/bench_indoor.py > indoor.md
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kbs.io import read_cloud
from kbs.knowledge import Segmenter

SCAN = Path(__file__).resolve().parents[2] / "shared" / "data" / "bobkov" / "room1_gt_fine.pcd"


def f1(pred: np.ndarray, truth: np.ndarray) -> float:
    return float(2 * (pred & truth).sum() / max(pred.sum() + truth.sum(), 1))


def main() -> None:
    if not SCAN.is_file():
        sys.exit(f"no {SCAN}")
    pc = read_cloud(SCAN)
    gt = np.asarray(pc.fields["label"]).astype(int) == 0
    t = time.perf_counter()
    seg = Segmenter("indoor").segment(pc.xyz, units=pc.units)
    seconds = time.perf_counter() - t
    names = list(seg.label_names)
    structure = np.isin(seg.label, [names.index(n) for n in ("floor", "wall", "ceiling")])
    x = pc.xyz[:, 0]
    print(f"room1_gt_fine: {len(gt):,} points, GT structure (label 0) {gt.mean():.1%}; segmented in {seconds:.1f} s\n")
    print("| part | points | structure F1 | furniture F1 | accuracy |")
    print("|---|---:|---:|---:|---:|")
    for part, m in (("whole room", np.ones(len(x), bool)), ("x < 0 (tuning part)", x < 0),
                    ("x >= 0 (validation part)", x >= 0)):
        print(f"| {part} | {m.sum():,} | {f1(structure[m], gt[m]):.3f} | {f1(~structure[m], ~gt[m]):.3f} | "
              f"{(structure[m] == gt[m]).mean():.3f} |")
    print("\n| label | points | GT structure among them |")
    print("|---|---:|---:|")
    for k, name in enumerate([*names, "noise"]):
        m = seg.label == (k if name != "noise" else -1)
        print(f"| {name} | {m.sum():,} | {gt[m].mean() if m.any() else float('nan'):.2f} |")


if __name__ == "__main__":
    main()
