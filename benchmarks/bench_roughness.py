"""Issue 12 analysis (docs/BENCHMARKS.md, "Session 9: a per-point roughness release"): would releasing
the rough points of kbs's ground help on scans it was not tuned on?

Runs ``rules/outdoor.yaml`` as shipped on the six vehicle scans, then releases every ground point
whose neighbourhood among the ground points within r (at least 8 of them) is thicker than t (the
square root of the smallest eigenvalue of their covariance), and prints ground F1 per scan with
the means of the tune part (SemanticKITTI 000001, GndNet 000000) and of the validation part
(GndNet 000001, SemanticKITTI-seq00 frames 0-2; benchmarks/splits.yaml). Ground of the seq00
frames: the data README's classes, lane markings included.

Usage: python benchmarks/bench_roughness.py   (about 3 minutes)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import kbs

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RADII = (0.5, 0.8)
THICKNESS = (0.04, 0.05, 0.06, 0.08, 0.10)
TUNE = ("SemanticKITTI 000001", "GndNet 000000")
VALIDATE = ("GndNet 000001", "seq00 0", "seq00 1", "seq00 2")


def load(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (n, 3) float64, ground truth, the points that count."""
    if name == "SemanticKITTI 000001":
        X = np.load(DATA / "semantickitti" / "000001.points.npy")[:, :3]
        cls = np.load(DATA / "semantickitti" / "000001.labels.npy").ravel()
        return X.astype(np.float64), np.isin(cls, [9, 10, 11, 12, 17]), cls != 0
    if name.startswith("GndNet"):
        stem = name.split()[1]
        X = np.load(DATA / "gndnet" / f"{stem}.points.npy")[:, :3]
        cls = np.load(DATA / "gndnet" / f"{stem}.labels.npy").ravel()
        return X.astype(np.float64), cls == 0, cls >= 0
    stem = DATA / "semantickitti-seq00" / f"seq00_00000{name[-1]}"
    X = np.fromfile(stem.with_suffix(".bin"), np.float32).reshape(-1, 4)[:, :3]
    cls = np.fromfile(stem.with_suffix(".label"), np.uint32) & 0xFFFF
    return X.astype(np.float64), np.isin(cls, [40, 44, 48, 49, 60, 72]), cls != 0


def f1(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    p, t = pred[valid], truth[valid]
    return float(2 * (p & t).sum() / (p.sum() + t.sum()))


def thickness(P: np.ndarray, radius: float) -> np.ndarray:
    """Per point of ``P``: the thickness of its neighbours within ``radius`` (0 with fewer than 8)."""
    out = np.zeros(len(P))
    for i, idx in enumerate(cKDTree(P).query_ball_point(P, radius, workers=2)):
        if len(idx) >= 8:
            Q = P[idx] - P[idx].mean(axis=0)
            out[i] = np.sqrt(max(np.linalg.eigvalsh(Q.T @ Q / len(idx))[0], 0.0))
    return out


def main() -> None:
    seg = kbs.Segmenter("outdoor")
    rows: dict[str, dict] = {}
    for name in TUNE + VALIDATE:
        X, truth, valid = load(name)
        ground = seg.segment(X).label == 0
        G = np.flatnonzero(ground)
        row = {"shipped": f1(ground, truth, valid)}
        for r in RADII:
            th = thickness(X[G], r)
            for t in THICKNESS:
                pred = ground.copy()
                pred[G[th > t]] = False
                row[f"r {r:g} m, t {t:g} m"] = f1(pred, truth, valid)
        rows[name] = row
    print("| setting | tune mean | validate mean | " + " | ".join(rows) + " |")
    print("|---|---:|---:|" + "---:|" * len(rows))
    for key in rows[TUNE[0]]:
        tune = np.mean([rows[n][key] for n in TUNE])
        val = np.mean([rows[n][key] for n in VALIDATE])
        print(f"| {key} | {tune:.4f} | {val:.4f} | " + " | ".join(f"{rows[n][key]:.4f}" for n in rows) + " |")


if __name__ == "__main__":
    main()
