"""Benchmark: ground F1 of tiled runs (kbs run --tile) against the untiled run, on the real scans.

Prints markdown: per scan and tile size, the number of tiles, the ground F1 untiled and tiled and
their difference (the target is |difference| <= 0.002), stitched clusters, how many labels changed
and the F1 difference near the inner tile edges (within a buffer) and inside the tiles, and wall times.

With --auto, the tiles are those the rule base's ``limits.tile`` makes of a cloud wider than its
``wider_than`` (tiles of ``limits.tile.size``, the default buffer or --buffer), whatever the scan's
width, and the ground total error (%) is printed beside F1 (the ISPRS measure). The LAS scans in feet
are in metres (bench_ground.scans converts them as ``kbs run`` does).

Usage: python benchmarks/bench_tiles.py [--sets kitti isprs las] [--scans samp11] [--sizes 60 80] [--buffer B] [--auto]
Every run is in process with jobs=1 (the result does not depend on jobs).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_ground import scans  # noqa: E402

from kbs.evaluation import ground_metrics  # noqa: E402
from kbs.knowledge import Segmenter  # noqa: E402
from kbs.tiles import default_buffer, segment_tiled  # noqa: E402

RULES = {"SemanticKITTI": "outdoor", "ISPRS": "airborne", "LAS": "airborne"}


def metrics(scan, seg, where=None):
    pred = seg.label == seg.label_names.index("ground")
    keep = scan.valid if where is None else scan.valid & where
    return ground_metrics(pred[keep], np.where(scan.truth, 1, 0)[keep], ground_values=(1,))


def f1(scan, seg, where=None) -> float:
    return metrics(scan, seg, where).f1


def near_edge(seg, X, size, buffer) -> np.ndarray:
    """Points within ``buffer`` of an inner tile edge (where a seam would show)."""
    from kbs.tiles import TileGrid

    grid = TileGrid.fit(X, size, buffer, seg.rule_base.ground.normal)
    uv = (X @ grid.axes.T - np.asarray(grid.origin)) / size
    d = np.abs(uv - np.round(uv)) * size
    inner = (np.round(uv) > 0) & (np.round(uv) < np.asarray(grid.shape))
    return ((d <= buffer) & inner).any(axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="+", default=["kitti", "isprs"])
    ap.add_argument("--scans", nargs="*", default=None, help="only these scan names (e.g. samp11 000001)")
    ap.add_argument("--sizes", nargs="+", type=float, default=None,
                    help="tile sizes (default: the longer side of the scan / 2.5: 4 to 9 tiles)")
    ap.add_argument("--buffer", type=float, default=None)
    ap.add_argument("--auto", action="store_true",
                    help="the tiles of the rule base's limits.tile (its size), with the ground total error")
    args = ap.parse_args()
    te_head, te_rule = ("total error % untiled | total error % tiled | TE diff | ", "---:|---:|---:|") if args.auto else ("", "")
    print("| data set | scan | points | tile m | buffer m | tiles | F1 untiled | F1 tiled | diff | " + te_head + "stitched | "
          "changed % near edges | changed % inside | F1 diff near edges | F1 diff inside | s untiled | s tiled |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|" + te_rule + "---:|---:|---:|---:|---:|---:|---:|")
    for scan in scans(args.sets):
        if args.scans and scan.name not in args.scans:
            continue
        note = ""
        seg = Segmenter(RULES[scan.dataset], jobs=1, sensor=scan.sensor)
        t0 = time.perf_counter()
        base = seg.segment(scan.xyz)
        t_base = time.perf_counter() - t0
        f_base = f1(scan, base)
        sizes = args.sizes or [round(float(np.ptp(scan.xyz[:, :2], axis=0).max()) / 2.5)]
        if args.auto:
            if seg.rule_base.tile is None:
                print(f"| {scan.dataset} | {scan.name} | rule base '{seg.rule_base.name}' has no limits.tile |")
                continue
            sizes = [seg.rule_base.tile.size]
        for size in sizes:
            t0 = time.perf_counter()
            tiled = segment_tiled(seg, scan.xyz, size, args.buffer)
            dt = time.perf_counter() - t0
            n_tiles = len(tiled.explanation.records["tiles"].children)
            stitched = sum("stitched" in c for c in tiled.clusters)
            buf = args.buffer if args.buffer is not None else default_buffer(seg, size)
            f_t = f1(scan, tiled)
            te = ""
            if args.auto:
                e_base, e_t = 100 * metrics(scan, base).total_error, 100 * metrics(scan, tiled).total_error
                te = f"{e_base:.2f} | {e_t:.2f} | {e_t - e_base:+.2f} | "
            near = near_edge(seg, scan.xyz, size, buf)
            changed = (tiled.label == tiled.label_names.index("ground")) != (base.label == base.label_names.index("ground"))
            print(f"| {scan.dataset} | {scan.name}{note} | {len(scan.xyz):,} | {size:g} | {buf:g} | {n_tiles} | {f_base:.4f} | "
                  f"{f_t:.4f} | {f_t - f_base:+.4f} | {te}{stitched} | {100 * changed[near].mean():.2f} | {100 * changed[~near].mean():.2f} | "
                  f"{f1(scan, tiled, near) - f1(scan, base, near):+.4f} | {f1(scan, tiled, ~near) - f1(scan, base, ~near):+.4f} | {t_base:.1f} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    main()
