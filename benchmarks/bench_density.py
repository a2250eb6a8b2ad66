"""Benchmark: the outdoor rule base at another point density than the scan's, against Patchwork++
in the same run (issue 12: thresholds read at one density must hold at another).

The full-resolution SemanticKITTI frames (``semantickitti-seq00``, about 124k points) are thinned
by a voxel grid to the density of the SemanticKITTI-style scan the project was given (000001:
"voxel-downsampled, about 6 cm", 88k points) and coarser (10 cm): one point per occupied voxel,
the first in the file's order. 000001 itself is thinned to 10 cm. Ground F1 of kbs outdoor
(a loaded ``kbs.Segmenter``, one process) and of Patchwork++ (bench_ground.py's settings) on the
points kept, each scan's own ground truth.

Usage: python benchmarks/bench_density.py [--voxels 0 0.06 0.1] [--rules outdoor]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_ground as bg  # noqa: E402
import peers  # noqa: E402

from kbs.knowledge import Segmenter, load_rule_base  # noqa: E402


def thin(X: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied voxel of edge ``voxel`` (the first in the file), sorted;
    all points when ``voxel`` is 0."""
    if voxel <= 0:
        return np.arange(len(X))
    _, first = np.unique(np.floor(X / voxel).astype(np.int64), axis=0, return_index=True)
    return np.sort(first)


def f1(pred: np.ndarray, scan: bg.Scan, keep: np.ndarray) -> float:
    valid = scan.valid[keep]
    p, t = pred[valid], scan.truth[keep][valid]
    return float(2 * (p & t).sum() / max(p.sum() + t.sum(), 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxels", type=float, nargs="+", default=[0.0, 0.06, 0.1], help="voxel edges, m (0: the scan as it is)")
    ap.add_argument("--rules", default="outdoor")
    args = ap.parse_args()
    if not bg.DATA.is_dir():
        sys.exit(f"no {bg.DATA}: the shared scans are needed")
    ground = load_rule_base(args.rules).label_names.index("ground")
    seg = Segmenter(args.rules, jobs=1)
    print("| scan | part | voxel m | points | kbs F1 | Patchwork++ F1 | kbs - Patchwork++ |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for scan in bg.scans(["kitti", "seq00"]):
        for voxel in args.voxels:
            if scan.dataset == "SemanticKITTI" and 0 < voxel <= 0.06:
                continue  # already thinned to about 6 cm
            keep = thin(scan.xyz, voxel)
            X = scan.xyz[keep]
            k = f1(seg.segment(X).label == ground, scan, keep)
            p = f1(peers.patchworkpp(X, scan.frame), scan, keep)
            print(f"| {scan.name} | {bg.part_of(scan)} | {voxel:g} | {len(keep):,} | {k:.4f} | {p:.4f} | {k - p:+.4f} |",
                  flush=True)


if __name__ == "__main__":
    main()
