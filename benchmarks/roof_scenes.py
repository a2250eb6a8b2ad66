"""Generated airborne scans of urban blocks with large roofs, labelled (0 bare earth, 1 building,
2 vegetation), z up, absolute-looking coordinates.

Issue 12, item 4: the roofs of large buildings (many roof patches, each compared with the roof
patches around it, not with the ground) are taken for ground. These scenes draw the conditions
behind it from physical ranges, not from any scan:

- a 200 m x 200 m tile of gently sloping ground (up to 2 %), 1-4 points per square metre (one
  density per scene), 5 cm of range noise;
- a grid of streets 10-20 m wide around blocks 40-150 m on a side; each block is built over, by
  1-3 adjoining buildings 5-30 m tall (one height each), flat roofs (in sections up to 1.5 m apart:
  parapets, levels, plant rooms) or gabled ones (15-35 deg, the ridge along the longer side); one
  block in three keeps a courtyard (bare earth enclosed by its buildings);
- the ground is seen only in the streets and courtyards; the walls get a few points (a twentieth of
  the density over their area);
- a few trees (crowns 3-8 m wide, 5-15 m tall) in the streets and courtyards: most returns from
  the crown, some from the ground under it.

``benchmarks/bench_steps.py`` runs them (the seeds of each part in benchmarks/splits.yaml,
``airborne-roofs-generated``) beside the airborne scans; ``tests/test_groundmodel.py`` runs one
through ``kbs run``.
"""
from __future__ import annotations

import numpy as np

ORIGIN = np.array([512000.0, 5400000.0, 250.0])
SIZE = 200.0  # m, the side of the tile


def _cuts(rng: np.random.Generator) -> list[tuple[float, float]]:
    """Blocks along one axis of the tile: (start, end) in [0, SIZE], streets between them."""
    out, x = [], -rng.uniform(0.0, 60.0)  # the first block may start outside the tile
    while x < SIZE:
        x += rng.uniform(10.0, 20.0)  # a street
        w = rng.uniform(40.0, 150.0)
        if x < SIZE:
            out.append((max(x, 0.0), min(x + w, SIZE)))
        x += w
    return [(a, b) for a, b in out if b - a > 5.0]


def roofs_scene(seed: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """One scene: points (n, 3), labels (n,) (0 bare earth, 1 building, 2 vegetation), and what was
    drawn (a dict: density, buildings as (x0, x1, y0, y1, height, roof kind), trees)."""
    rng = np.random.default_rng(seed)
    density = rng.uniform(1.0, 4.0)
    grade = rng.uniform(0.0, 0.02) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])

    def terrain(xy: np.ndarray) -> np.ndarray:
        return xy @ grade

    buildings = []  # x0, x1, y0, y1, height, kind, pitch/levels
    courts = []
    for bx in _cuts(rng):
        for by in _cuts(rng):
            # 1-3 buildings side by side along the block's longer side
            along = 0 if bx[1] - bx[0] >= by[1] - by[0] else 1
            lo, hi = (bx if along == 0 else by)
            n = int(rng.integers(1, 4))
            edges = np.sort(rng.uniform(lo, hi, n - 1)) if n > 1 else np.zeros(0)
            edges = np.r_[lo, edges, hi]
            for a, b in zip(edges[:-1], edges[1:]):
                if b - a < 8.0:
                    continue
                box = (a, b, by[0], by[1]) if along == 0 else (bx[0], bx[1], a, b)
                kind = "gabled" if rng.uniform() < 0.4 else "flat"
                buildings.append({"box": box, "height": rng.uniform(5.0, 30.0), "kind": kind,
                                  "pitch": rng.uniform(15.0, 35.0), "levels": rng.choice([0.0, 0.5, 1.0, 1.5], 9),
                                  "ridge_x": (box[1] - box[0]) >= (box[3] - box[2])})
            if rng.uniform() < 1 / 3 and min(bx[1] - bx[0], by[1] - by[0]) > 50.0:
                m = rng.uniform(0.2, 0.35)  # the courtyard leaves this fraction of each side built
                courts.append((bx[0] + m * (bx[1] - bx[0]), bx[1] - m * (bx[1] - bx[0]),
                               by[0] + m * (by[1] - by[0]), by[1] - m * (by[1] - by[0])))
    trees = []
    for _ in range(int(rng.integers(5, 25))):
        trees.append((rng.uniform(0, SIZE), rng.uniform(0, SIZE), rng.uniform(1.5, 4.0), rng.uniform(5.0, 15.0)))

    n = int(density * SIZE * SIZE)
    xy = rng.uniform(0.0, SIZE, (n, 2))
    z = terrain(xy)
    label = np.zeros(n, dtype=np.int64)
    in_court = np.zeros(n, bool)
    for c in courts:
        in_court |= (xy[:, 0] > c[0]) & (xy[:, 0] < c[1]) & (xy[:, 1] > c[2]) & (xy[:, 1] < c[3])
    walls = []
    for b in buildings:
        x0, x1, y0, y1 = b["box"]
        inside = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1) & ~in_court
        base = terrain(np.array([[(x0 + x1) / 2, (y0 + y1) / 2]]))[0]
        P = xy[inside]
        if b["kind"] == "flat":  # 3 x 3 sections at levels up to 1.5 m apart
            i = np.minimum(((P[:, 0] - x0) / (x1 - x0) * 3).astype(int), 2)
            j = np.minimum(((P[:, 1] - y0) / (y1 - y0) * 3).astype(int), 2)
            roof = b["height"] + b["levels"][3 * i + j]
        else:  # a gable: rising from the eaves to the ridge along the longer side, at most 12 m
            u = np.abs(P[:, 1] - (y0 + y1) / 2) if b["ridge_x"] else np.abs(P[:, 0] - (x0 + x1) / 2)
            half = (y1 - y0) / 2 if b["ridge_x"] else (x1 - x0) / 2
            rise = min(np.tan(np.radians(b["pitch"])) * half, 12.0)
            roof = b["height"] + rise * (1.0 - u / half)
        z[inside] = base + roof
        label[inside] = 1
        # a few points on the walls, a twentieth of the density (the scanner sees them at a grazing angle)
        perim = 2 * ((x1 - x0) + (y1 - y0))
        m = int(rng.poisson(density / 20.0 * perim * b["height"]))
        t = rng.uniform(0.0, perim, m)
        wx = np.where(t < x1 - x0, x0 + t, np.where(t < (x1 - x0) + (y1 - y0), x1,
                      np.where(t < 2 * (x1 - x0) + (y1 - y0), x1 - (t - (x1 - x0) - (y1 - y0)), x0)))
        wy = np.where(t < x1 - x0, y0, np.where(t < (x1 - x0) + (y1 - y0), y0 + (t - (x1 - x0)),
                      np.where(t < 2 * (x1 - x0) + (y1 - y0), y1, y1 - (t - 2 * (x1 - x0) - (y1 - y0)))))
        walls.append(np.column_stack([wx, wy, base + rng.uniform(0.3, b["height"], m)]))
    # trees where there is no building: most returns from the crown (an ellipsoid cap)
    for tx, ty, r, h in trees:
        d = np.hypot(xy[:, 0] - tx, xy[:, 1] - ty)
        under = (d < r) & (label == 0) & (rng.uniform(size=n) < 0.8)
        cap = np.sqrt(np.clip(1.0 - (d[under] / r) ** 2, 0.0, 1.0))
        z[under] = terrain(xy[under]) + h - 0.4 * h * (1.0 - cap) + rng.normal(0, 0.3, under.sum())
        label[under] = 2
    z = z + rng.normal(0.0, 0.05, n)
    W = np.vstack(walls) if walls else np.zeros((0, 3))
    X = np.vstack([np.column_stack([xy, z]), W]) + ORIGIN
    labels = np.r_[label, np.ones(len(W), dtype=np.int64)]
    drawn = {"density": density, "buildings": [(*b["box"], b["height"], b["kind"]) for b in buildings],
             "courts": courts, "trees": trees}
    return X, labels, drawn
