"""Generate the bundled example scene ``examples/data/outdoor.ply``.

An outdoor scene as a stereo rig on a rover would see it: gently uneven ground, three rocks and a
bin standing on it, point density falling with the distance to the sensor (at the origin, 1.5 m
above the ground). Per-vertex ``label``: 0 ground, 1-3 rocks, 4 bin. Deterministic (seeded).

Usage: python examples/make_scenes.py [OUT.ply]
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from kbs.io import write_ply

SENSOR_HEIGHT = 1.5


def _keep_by_range(rng: np.random.Generator, P: np.ndarray, r0: float = 4.0) -> np.ndarray:
    """Stereo-like density: keep a point with probability min(1, (r0 / range)^2)."""
    r = np.linalg.norm(P - [0.0, 0.0, SENSOR_HEIGHT], axis=1)
    return rng.uniform(size=len(P)) < np.minimum(1.0, (r0 / r) ** 2)


def outdoor_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)

    def ground_z(x, y):
        return 0.05 * np.sin(0.3 * x) + 0.04 * np.cos(0.25 * y) + 0.01 * x

    n = 120_000
    g = np.column_stack([rng.uniform(1, 25, n), rng.uniform(-10, 10, n)])
    ground = np.column_stack([g, ground_z(g[:, 0], g[:, 1]) + rng.normal(0, 0.01, n)])
    parts, labels = [ground], [np.zeros(n, dtype=np.int32)]
    for i, (cx, cy, radii) in enumerate([(7.0, -2.0, (0.5, 0.4, 0.35)), (9.0, 2.5, (0.6, 0.5, 0.45)),
                                         (14.0, -4.0, (0.7, 0.6, 0.5))], start=1):
        d = rng.normal(size=(6000, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[d[:, 2] > -0.3]  # the buried part is not seen
        rock = d * radii * rng.uniform(0.9, 1.1, (len(d), 1)) + [cx, cy, ground_z(cx, cy) + 0.3 * radii[2]]
        parts.append(rock)
        labels.append(np.full(len(rock), i, dtype=np.int32))
    # a bin: open box 0.6 x 0.6 x 1.0, its four walls
    m = 8000
    u, h = rng.uniform(-0.3, 0.3, m), rng.uniform(0, 1.0, m)
    side = rng.integers(0, 4, m)
    bx = np.where(side == 0, -0.3, np.where(side == 1, 0.3, u))
    by = np.where(side == 2, -0.3, np.where(side == 3, 0.3, u))
    bin_ = np.column_stack([bx + 11.0, by - 0.5, h + ground_z(11.0, -0.5)])
    parts.append(bin_)
    labels.append(np.full(m, 4, dtype=np.int32))
    P, L = np.vstack(parts), np.concatenate(labels)
    P = P + rng.normal(0, 0.005, P.shape)
    keep = _keep_by_range(rng, P)
    P, L = P[keep], L[keep]
    P[:, 2] -= SENSOR_HEIGHT  # sensor frame: sensor at the origin
    return P, L


def main(argv: list[str]) -> None:
    out = Path(argv[0]) if argv else Path(__file__).resolve().parent / "data" / "outdoor.ply"
    out.parent.mkdir(parents=True, exist_ok=True)
    P, L = outdoor_scene()
    write_ply(out, P.astype(np.float32), {"label": L},
              comments=["kbs example: outdoor scene, sensor at the origin; label 0 ground, 1-3 rocks, 4 bin"])
    print(f"wrote {out}: {len(P):,} points")


if __name__ == "__main__":
    main(sys.argv[1:])
