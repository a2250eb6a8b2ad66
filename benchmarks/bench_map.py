"""Benchmark: `kbs map` on generated drives — the obstacle grid's cell accuracy against the true
layout, the tracked objects against the true obstacles, with the true poses and with poses
estimated by KISS-ICP (their error against the true ones), and what fusing a frame costs beside
segmenting it.

Drives: `kbs synth outdoor --frames N` (kbs.synth.drive.outdoor_drive: the rover's stereo-like
sensor, 1 m between frames, turning 2 degrees a frame, 6 rocks and a bin beside the path), and the
same with `--street` (buildings, trees and poles along both sides), mapped with the outdoor rule
base loaded once (kbs.Segmenter). Scores (kbs.maps.score): cells seen by the drive, less those on
an obstacle's rim (partly covered, less than half); a cell is truly an obstacle when half of it or
more lies under an obstacle standing 5 cm above the terrain. "all ground" is the accuracy of a map
that says ground everywhere.

Estimated poses: `map_drive(..., odometry=Odometry(origin=first true pose))`, as `kbs map
--estimate-poses` runs it (KISS-ICP frame by frame on the points the segmentation did not call
ground), the map scored in the true world frame. Pose error: ATE, the RMS over the frames of the
distance between the estimated and the true sensor positions (both start at the first true pose,
no other alignment); per-frame translation error, the median and the largest distance between
the estimated and the true frame-to-frame motions; the yaw error of the last frame.

Fusion cost: the time map_drive spends per frame after segmentation (the world transform, the
grid's votes, the tracker and the fused cloud), median over the frames, on a drive whose frames
hold about 100k points (--fusion-resolution).

Usage: python benchmarks/bench_map.py [--seeds 0 1 2] [--frames 20] [--fusion-frames 5] [--jobs N]
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


def _pose_errors(est: np.ndarray, true: np.ndarray) -> tuple[float, float, float, float]:
    """(ATE RMS m, per-frame translation error median and max m, final yaw error deg)."""
    ate = float(np.sqrt((np.linalg.norm(est[:, :3, 3] - true[:, :3, 3], axis=1) ** 2).mean()))
    d_est = np.linalg.inv(est[:-1]) @ est[1:]
    d_true = np.linalg.inv(true[:-1]) @ true[1:]
    rpe = np.linalg.norm(d_est[:, :3, 3] - d_true[:, :3, 3], axis=1)
    yaw = np.degrees(np.arctan2(est[-1, 1, 0], est[-1, 0, 0]) - np.arctan2(true[-1, 1, 0], true[-1, 0, 0]))
    return ate, float(np.median(rpe)), float(rpe.max()), float((yaw + 180) % 360 - 180)


def _row(kind: str, seed: int, poses: str, d, m, extra: str) -> str:
    gs = score_grid(m.grid, d.truth)
    os_ = score_objects(m.objects, d.truth, [f.objects for f in d.frames], min_points=40)
    baseline = 1 - gs.true_obstacle_cells / gs.cells
    return (f"| {kind} | {seed} | {poses} | {extra} | {gs.cells:,} | {gs.accuracy:.4f} | {baseline:.4f} "
            f"| {gs.obstacle_precision:.3f} | {gs.obstacle_recall:.3f} | {os_.true_objects} | {os_.mapped_objects} "
            f"| {os_.matched} | {os_.split} | {os_.false} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--fusion-frames", type=int, default=5)
    ap.add_argument("--fusion-resolution", type=int, nargs=2, default=[300, 530], metavar=("ROWS", "COLS"))
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()

    from kbs.errors import FitError
    from kbs.maps.odometry import Odometry, kiss_icp_available

    print(f"### Generated drives: {args.frames} frames, outdoor rule base, true and estimated poses\n")
    print("| drive | seed | poses | pose error: ATE m / per-frame translation m (median, max) / final yaw deg "
          "| cells scored | accuracy | all ground | obstacle precision | obstacle recall | true objects | mapped "
          "| matched | split | invented |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    times = []
    with Segmenter("outdoor", jobs=args.jobs) as seg:
        seg.segment(outdoor_drive(0, n_frames=1, resolution=(60, 100)).frames[0].xyz)  # compile before timing
        for street in (False, True):
            kind = "street" if street else "rover"
            for seed in args.seeds:
                d = outdoor_drive(seed, n_frames=args.frames, street=street)
                frames = [f.xyz for f in d.frames]
                m = map_drive(seg, frames, d.poses)
                times.append((statistics.median(f.segment_seconds for f in m.frames), m.fuse_ms_per_frame))
                print(_row(kind, seed, "true", d, m, "-"),
                      flush=True)
                if not kiss_icp_available():
                    print(f"| {kind} | {seed} | estimated | KISS-ICP not installed (pip install 'kbs[map]') |" +
                          " |" * 10)
                    continue
                try:
                    m = map_drive(seg, frames, d.poses, odometry=Odometry(origin=d.poses[0]))
                except FitError as exc:
                    print(f"| {kind} | {seed} | estimated | refused: {exc} |" + " |" * 10)
                    continue
                ate, rpe_med, rpe_max, yaw = _pose_errors(m.poses.matrices, d.poses)
                print(_row(kind, seed, "estimated", d, m, f"{ate:.2f} / {rpe_med:.3f}, {rpe_max:.3f} / {yaw:+.1f}"),
                      flush=True)
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
    print(f"\nOn the drives above (true poses): segment {min(t[0] for t in times):.2f}-{max(t[0] for t in times):.2f} "
          f"s/frame, fuse {min(t[1] for t in times):.1f}-{max(t[1] for t in times):.1f} ms/frame (medians per drive)")


if __name__ == "__main__":
    main()
