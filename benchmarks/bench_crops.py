"""Does a region's result depend on where the scan is cut? (issue 12: every airborne scan is a cut
of the land, and the unseen ISPRS samples are cuts of their sites.)

Each airborne scan (the labelled ISPRS and LAS scans of benchmarks/splits.yaml, and the generated
urban blocks of ``airborne-roofs-generated``, ``benchmarks/roof_scenes.py``) is run whole, then cut
into its four corner crops, each ``--frac`` of the scan's width and of its depth (0.6: each crop
holds 36 % of the box and overlaps its neighbours), and each crop is run alone. For each crop the
total error % of its points is printed twice: from the crop's own run ("alone") and from the whole
scan's run ("inside"); a crop where less than ``--min-ground`` of the points are ground (a crop
inside one roof) is left out: with no ground in view nothing tells a roof from the ground. Where
they differ, the result of those points depends on what lies beyond
the cut: a building cut by the scan edge with one wall in view, a terrace whose upper side is cut
off. A crop "fails" when its error alone exceeds its error inside by more than ``--fail`` points.

Total error % as bench_steps.py scores it: the ISPRS reference labels; LAS: the provider's class 2 =
ground, noise left out; generated blocks: their drawn labels. The rule file is the shipped
airborne one unless ``--rules``; ``--before FILE`` adds the same columns for another rule file in
the same run (e.g. the rule file before a change).

Usage:
    python benchmarks/bench_crops.py                           # real scans and the blocks of both parts
    python benchmarks/bench_crops.py --scans samp11 --blocks tune --frac 0.5
    python benchmarks/bench_crops.py --no-scans --blocks tune --before /tmp/airborne-before.yaml
    python benchmarks/bench_crops.py --no-scans --blocks --seeds 800 819   # fresh seeds, part 'extra'
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_ground as bg  # noqa: E402
import roof_scenes  # noqa: E402
from bench_regions import TUNE, VALIDATE, load  # noqa: E402

from kbs.knowledge import Segmenter  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def corner_crops(X: np.ndarray, frac: float) -> list[tuple[str, np.ndarray]]:
    """The four corner crops of ``X``'s box in the plane, each ``frac`` of its width and depth:
    (name, mask), names 'SW', 'NW', 'SE', 'NE' (x grows east, y north)."""
    lo, hi = X[:, :2].min(axis=0), X[:, :2].max(axis=0)
    span = hi - lo
    out = []
    for ix, ew in ((0, "W"), (1, "E")):
        for iy, ns in ((0, "S"), (1, "N")):
            x0 = lo[0] + ix * (1.0 - frac) * span[0]
            y0 = lo[1] + iy * (1.0 - frac) * span[1]
            m = ((X[:, 0] >= x0) & (X[:, 0] <= x0 + frac * span[0])
                 & (X[:, 1] >= y0) & (X[:, 1] <= y0 + frac * span[1]))
            out.append((ns + ew, m))
    return out


def scans(names: list[str], blocks: list[str],
          seeds: tuple[int, int] | None = None) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, part, points, truth, valid) of the real scans named, the generated blocks of the parts
    named, and those of ``seeds`` (first, last; part 'extra': seeds neither part holds)."""
    seg = Segmenter("airborne", jobs=1)  # only for the file's unit (metres)
    out = []
    for name in names:
        X, truth, valid = load(name, seg)
        out.append((name, "tune" if name in TUNE else "validate" if name in (*VALIDATE, "sample_c") else "-",
                    X, truth, valid))
    for part in blocks:
        first, last = bg.splits()["airborne-roofs-generated"][f"{part}_seeds"]
        for seed in range(first, last + 1):
            X, labels, _ = roof_scenes.roofs_scene(seed)
            X = X - np.floor(X.min(axis=0))
            out.append((f"block {seed}", part, X, labels == 0, np.ones(len(X), bool)))
    for seed in range(seeds[0], seeds[1] + 1) if seeds else ():
        X, labels, _ = roof_scenes.roofs_scene(seed)
        X = X - np.floor(X.min(axis=0))
        out.append((f"block {seed}", "extra", X, labels == 0, np.ones(len(X), bool)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scans", nargs="+", default=[*TUNE, *VALIDATE, "sample_c"],
                    help="real airborne scans (default: both parts of benchmarks/splits.yaml)")
    ap.add_argument("--no-scans", action="store_true", help="the generated blocks only")
    ap.add_argument("--blocks", nargs="*", choices=["tune", "validate"], default=["tune", "validate"],
                    help="parts of the generated urban blocks to run (none: --blocks with no value)")
    ap.add_argument("--seeds", nargs=2, type=int, metavar=("FIRST", "LAST"), default=None,
                    help="also the generated blocks of these seeds (part 'extra': neither part's)")
    ap.add_argument("--frac", type=float, default=0.6, help="a crop's share of the scan's width and depth")
    ap.add_argument("--fail", type=float, default=5.0, help="points of total error a crop alone may lose before it fails")
    ap.add_argument("--min-ground", type=float, default=0.1,
                    help="share of ground a crop must hold to count (default 0.1)")
    ap.add_argument("--rules", default="airborne", help="rule base (default: the shipped airborne one)")
    ap.add_argument("--before", default=None, help="another rule file, the same columns in the same run")
    args = ap.parse_args()
    if not 0.0 < args.frac < 1.0:
        ap.error("--frac must lie between 0 and 1")
    variants = [("", args.rules)] + ([("before ", args.before)] if args.before else [])
    segs = [(label, Segmenter(rules, jobs=1)) for label, rules in variants]
    print(f"rules {args.rules}" + (f"; before: {args.before}" if args.before else "") +
          f"; corner crops {args.frac:g} x {args.frac:g} of the box; total error % of a crop's points, "
          "run alone / inside the whole scan's run")
    print()
    head = "| scan | part | points | "
    for label, _ in segs:
        head += f"{label}whole | {label}crops SW, NW, SE, NE alone / inside | "
    print(head + "seconds |")
    print("|---|---|---:|" + "---:|---|" * len(segs) + "---:|")
    diffs: dict[tuple[str, str], list[float]] = {}
    for name, part, X, truth, valid in scans([] if args.no_scans else args.scans, args.blocks, args.seeds):
        t0 = time.perf_counter()
        cells = []
        for label, seg in segs:
            whole = seg.segment(X).label == 0
            cell = []
            for _, m in corner_crops(X, args.frac):
                share = float(truth[m][valid[m]].mean()) if valid[m].any() else 0.0
                if share < args.min_ground:
                    cell.append(f"left out ({100.0 * share:.0f} % ground)")
                    continue
                alone = seg.segment(X[m]).label == 0
                v = valid[m]
                e_alone = 100.0 * (alone != truth[m])[v].mean()
                e_inside = 100.0 * (whole[m] != truth[m])[v].mean()
                diffs.setdefault((label, part), []).append(e_alone - e_inside)
                mark = " **fails**" if e_alone - e_inside > args.fail else ""
                cell.append(f"{e_alone:.2f} / {e_inside:.2f}{mark}")
            cells.append(f"{100.0 * (whole != truth)[valid].mean():.2f} | " + ", ".join(cell))
        print(f"| {name} | {part} | {len(X):,} | " + " | ".join(cells) + f" | {time.perf_counter() - t0:.0f} |",
              flush=True)
    print()
    print(f"| rules | part | crops | alone - inside, mean | median | worst | crops failing (> {args.fail:g} points) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for (label, part), d in diffs.items():
        a = np.asarray(d)
        print(f"| {label.strip() or 'this'} | {part} | {a.size} | {a.mean():+.2f} | {np.median(a):+.2f} | "
              f"{a.max():+.2f} | {int((a > args.fail).sum())} |")


if __name__ == "__main__":
    main()
