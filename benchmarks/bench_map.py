"""Benchmark: `kbs map` on generated drives — the obstacle grid's cell accuracy against the true
layout, the tracked objects against the true obstacles, and what fusing a frame costs beside
segmenting it.

Drives: `kbs synth outdoor --frames N` (kbs.synth.drive.outdoor_drive: the rover's stereo-like
sensor, 1 m between frames, turning 2 degrees a frame, 6 rocks and a bin beside the path), mapped
with the outdoor rule base loaded once (kbs.Segmenter) and the true poses. Scores
(kbs.maps.score): cells seen by the drive, less those on an obstacle's rim (partly covered, less
than half); a cell is truly an obstacle when half of it or more lies under an obstacle standing
5 cm above the terrain. "all ground" is the accuracy of a map that says ground everywhere.

Fusion cost: the time map_drive spends per frame after segmentation (the world transform, the
grid's votes, the tracker and the fused cloud), median over the frames, on a drive whose frames
hold about 100k points (--fusion-resolution).

Estimated poses: the same drives with poses from KISS-ICP (the map extra), the pose error
against the true poses and the map built on them.

Usage: python benchmarks/bench_map.py [--seeds 0 1 2] [--frames 20] [--fusion-frames 5]
       [--jobs N]
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from kbs import Segmenter
from kbs.maps import map_drive
from kbs.maps.score import score_grid, score_objects
from kbs.synth.drive import outdoor_drive


def _estimated(seg, d) -> str:
    """The cells of the estimated-poses table for one drive (KISS-ICP must be installed)."""
    from kbs.errors import FitError
    from kbs.maps.odometry import estimate_poses, kiss_icp_available

    if not kiss_icp_available():
        return "KISS-ICP not installed (pip install 'kbs[map]') |" + " |" * 9
    frames = [f.xyz for f in d.frames]
    try:
        estimate_poses(frames)
        refused = "not refused"
    except FitError as exc:
        refused = str(exc).split(": ", 1)[-1].split(" (at least")[0]
    try:
        est = estimate_poses(frames, min_constraint=0.0, min_overlap=0.0)
    except FitError as exc:
        return f"{refused} | failed: {exc} |" + " |" * 8
    true = np.linalg.inv(d.poses[0])[None] @ d.poses  # in the first pose's frame, as the estimate
    err = np.linalg.norm(est.matrices[:, :3, 3] - true[:, :3, 3], axis=1)
    yaw = np.degrees(np.arctan2(est.matrices[-1, 1, 0], est.matrices[-1, 0, 0]) -
                     np.arctan2(true[-1, 1, 0], true[-1, 0, 0]))
    step = np.median(np.linalg.norm(np.diff(est.matrices[:, :3, 3], axis=0), axis=1))
    # the map on the estimated poses, scored in the true world frame (estimated poses from the true first one)
    m = map_drive(seg, frames, d.poses[0][None] @ est.matrices)
    gs = score_grid(m.grid, d.truth)
    os_ = score_objects(m.objects, d.truth, [f.objects for f in d.frames], min_points=40)
    return (f"{refused} | {step:.2f} | {np.sqrt((err ** 2).mean()):.2f} | {err[-1]:.2f} | {yaw:.1f} | "
            f"{gs.accuracy:.4f} | {gs.obstacle_precision:.3f} | {gs.obstacle_recall:.3f} | {os_.mapped_objects} | "
            f"{os_.false}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--fusion-frames", type=int, default=5)
    ap.add_argument("--fusion-resolution", type=int, nargs=2, default=[300, 530], metavar=("ROWS", "COLS"))
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()

    print(f"### Generated drives: {args.frames} frames, outdoor rule base, true poses\n")
    print("| seed | points/frame | cells scored | accuracy | all ground | obstacle precision | obstacle recall "
          "| true objects | mapped | matched | split | invented | segment s/frame | fuse ms/frame |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with Segmenter("outdoor", jobs=args.jobs) as seg:
        seg.segment(outdoor_drive(0, n_frames=1, resolution=(60, 100)).frames[0].xyz)  # compile before timing
        drives = []
        for seed in args.seeds:
            d = outdoor_drive(seed, n_frames=args.frames)
            m = map_drive(seg, [f.xyz for f in d.frames], d.poses)
            gs = score_grid(m.grid, d.truth)
            os_ = score_objects(m.objects, d.truth, [f.objects for f in d.frames], min_points=40)
            baseline = 1 - gs.true_obstacle_cells / gs.cells
            print(f"| {seed} | {statistics.mean(len(f) for f in d.frames):,.0f} | {gs.cells:,} | {gs.accuracy:.4f} "
                  f"| {baseline:.4f} | {gs.obstacle_precision:.3f} | {gs.obstacle_recall:.3f} | {os_.true_objects} "
                  f"| {os_.mapped_objects} | {os_.matched} | {os_.split} | {os_.false} "
                  f"| {statistics.median(f.segment_seconds for f in m.frames):.2f} | {m.fuse_ms_per_frame:.1f} |")
            drives.append(d)
        print(f"\n### The same drives with poses estimated by KISS-ICP\n")
        print("KISS-ICP (kbs.maps.odometry.estimate_poses, voxel 1 m) refuses these frames as too flat to register; "
              "forced (min_constraint=0), its poses and the map built on them:\n")
        print("| seed | refused because | est. motion m/frame (true 1.0) | position error RMS m | final position error m "
              "| final yaw error deg | accuracy | obstacle precision | obstacle recall | mapped objects | invented |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for seed, d in zip(args.seeds, drives):
            est_row = _estimated(seg, d)
            print(f"| {seed} | {est_row} |")
        rows, cols = args.fusion_resolution
        d = outdoor_drive(0, n_frames=args.fusion_frames, resolution=(rows, cols))
        t0 = time.perf_counter()
        m = map_drive(seg, [f.xyz for f in d.frames], d.poses)
        total = time.perf_counter() - t0
    n = np.median([f.n_points for f in m.frames])
    fuse = m.fuse_ms_per_frame
    segment = 1e3 * statistics.median(f.segment_seconds for f in m.frames)
    print(f"\n### Fusion cost per frame ({args.fusion_frames} frames of {rows}x{cols} rays)\n")
    print("| points/frame (median) | segment ms/frame | fuse ms/frame | fuse / segment | whole map_drive s |")
    print("|---|---|---|---|---|")
    print(f"| {n:,.0f} | {segment:.0f} | {fuse:.1f} | {fuse / segment:.1%} | {total:.1f} |")


if __name__ == "__main__":
    main()
