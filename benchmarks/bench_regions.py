"""Is a region's result the same whether it is run alone or inside a larger file? (issue 9, item 5;
the airborne rule base's ``limits.tile``; docs/BENCHMARKS.md "Regions alone and inside larger files")

Each labelled airborne scan is run with ``rules/airborne.yaml`` alone, and as one copy inside a file
of ``R x R`` copies of itself mirrored (left-right, front-back), so that the terrain is continuous
across the seams and the file is a larger piece of the same kind of land; untiled (the whole file
at once, ``kbs run --no-tile``) and in tiles of each ``--sizes`` (``kbs run --tile T``, default
buffer). Prints the total error % on the scan's own points (ISPRS: the reference labels; LAS: the
provider's class 2 = ground, noise left out) of the original copy, and with ``--repeat`` above 2
the mean, min and max over all copies, and the seconds.

Usage:
    python benchmarks/bench_regions.py                      # tune and validation parts, 2 x 2, T = 100
    python benchmarks/bench_regions.py --repeat 4 --scans samp51 samp61 --sizes 100
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from kbs.io import read_cloud
from kbs.knowledge import Segmenter
from kbs.tiles import segment_tiled

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
TUNE = ["samp11", "samp12", "samp51", "autzen_trim"]     # benchmarks/splits.yaml, airborne
VALIDATE = ["samp21", "samp31", "samp61", "4_6_crop"]    # (sample_c is 83 m wide: one 100 m tile)


def load(name: str, seg: Segmenter) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points in the rule base's unit (moved near the origin), ground truth, the points that count."""
    if name in ("samp11", "samp12"):
        pc = read_cloud(DATA / "isprs" / f"{name}.txt")
        truth, valid = pc.fields["col3"].astype(int) == 0, np.ones(len(pc), bool)
    elif name.startswith("samp") and name[4:].isdigit():  # not sample_c
        pc = read_cloud(DATA / "isprs" / f"{name}-utm.pcd")
        truth = np.loadtxt(DATA / "isprs" / f"{name}-utm.labels.txt")[pc.index].astype(int) == 0
        valid = np.ones(len(pc), bool)
    else:
        pc = read_cloud(DATA / "las" / f"{name}.las")
        cls = pc.fields["classification"].astype(int)
        truth, valid = cls == 2, ~np.isin(cls, (7, 18))
    X = pc.xyz.astype(np.float64) * seg.scale(pc.units)
    return X - np.floor(X.min(axis=0)), truth, valid


def mirrored(X: np.ndarray, repeat: int) -> np.ndarray:
    """``repeat x repeat`` copies of ``X``, each the mirror image of its neighbours (the first is ``X``)."""
    lo, hi = X.min(axis=0), X.max(axis=0)
    copies = []
    for j in range(repeat):
        for i in range(repeat):
            Y = X.copy()
            if i % 2:
                Y[:, 0] = lo[0] + hi[0] - Y[:, 0]
            if j % 2:
                Y[:, 1] = lo[1] + hi[1] - Y[:, 1]
            Y[:, 0] += i * (hi[0] - lo[0])
            Y[:, 1] += j * (hi[1] - lo[1])
            copies.append(Y)
    return np.vstack(copies)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", nargs="+", default=TUNE + VALIDATE)
    ap.add_argument("--sizes", nargs="+", type=float, default=[100.0])
    ap.add_argument("--repeat", type=int, default=2, help="copies along each axis of the larger file (default 2)")
    ap.add_argument("--rules", default="airborne", help="rule base (default: the shipped airborne one)")
    args = ap.parse_args()
    seg = Segmenter(args.rules, jobs=1)
    runs = [("untiled", None)] + [(f"--tile {t:g}", t) for t in args.sizes]
    print(f"rules {args.rules}; the larger file: {args.repeat} x {args.repeat} mirrored copies; total error %, "
          "the original copy's points" + ("; mean (min-max) over the copies" if args.repeat > 2 else ""))
    print()
    print("| scan | part | points | width m | " + " | ".join(f"alone, {n} | in the larger file, {n}" for n, _ in runs)
          + " | seconds |")
    print("|---|---|---:|---:|" + "---:|---:|" * len(runs) + "---|")
    for name in args.scans:
        X, truth, valid = load(name, seg)
        n = len(X)
        big = mirrored(X, args.repeat)
        cells, seconds = [], []
        for _, size in runs:
            for pts in (X, big):
                t0 = time.perf_counter()
                res = seg.segment(pts) if size is None else segment_tiled(seg, pts, size)
                seconds.append(time.perf_counter() - t0)
                errs = [100.0 * ((res.label[k * n:(k + 1) * n] == 0) != truth)[valid].mean()
                        for k in range(len(pts) // n)]
                cells.append(f"{errs[0]:.2f}" if len(errs) == 1 or args.repeat <= 2 else
                             f"{np.mean(errs):.2f} ({min(errs):.2f}-{max(errs):.2f})")
        part = "tune" if name in TUNE else "validate" if name in VALIDATE else "-"
        width = float((X.max(axis=0) - X.min(axis=0))[:2].max())
        print(f"| {name} | {part} | {n:,} | {width:.0f} | " + " | ".join(cells) + " | "
              + " / ".join(f"{s:.0f}" for s in seconds) + " |", flush=True)


if __name__ == "__main__":
    main()
