"""Small synthetic scenes for the tests (deterministic, generated, never stored)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def anisotropic_blobs(n_per: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Three well-separated, elongated, rotated Gaussian blobs; returns (X (3 n_per, 3), labels)."""
    rng = np.random.default_rng(seed)
    specs = [
        ((0.0, 0.0, 0.0), (3.0, 1.0, 0.2), (10, 20, 30)),
        ((20.0, 0.0, 0.0), (0.3, 2.0, 1.0), (40, 0, 70)),
        ((0.0, 20.0, 5.0), (1.0, 1.0, 4.0), (0, 60, 0)),
    ]
    parts, labels = [], []
    for i, (c, s, angles) in enumerate(specs):
        rot = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
        parts.append(rng.normal(size=(n_per, 3)) * s @ rot.T + c)
        labels.append(np.full(n_per, i))
    return np.vstack(parts), np.concatenate(labels)


def ground_and_boxes(n_ground: int = 20000, n_box: int = 3000, seed: int = 1, noise: float = 0.01) -> np.ndarray:
    """A flat noisy ground (40 m x 40 m) and two boxes' surfaces standing on it, well apart."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(-20, 20, n_ground), rng.uniform(-20, 20, n_ground),
                              rng.normal(0, noise, n_ground)])
    boxes = []
    for cx, cy, h in ((8.0, 8.0, 3.0), (-9.0, -6.0, 2.0)):
        P = rng.uniform(-1, 1, (n_box, 3))
        face = rng.integers(0, 3, n_box)
        P[np.arange(n_box), face] = np.sign(rng.uniform(-1, 1, n_box))
        P = P * [1.5, 1.5, h / 2] + [cx, cy, h / 2 + 0.3]
        boxes.append(P + rng.normal(0, noise, P.shape))
    return np.vstack([ground] + boxes)


def _ground(rng: np.random.Generator, n: int, half: float, noise: float) -> np.ndarray:
    return np.column_stack([rng.uniform(-half, half, n), rng.uniform(-half, half, n), rng.normal(0, noise, n)])


def _dome(rng: np.random.Generator, n: int, center, radii) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2])
    return d * radii + center


def ground_and_rocks(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Flat ground (12 m x 12 m) and three look-alike rocks (domes 0.6 m high) 4 m apart, in a
    sensor frame with the sensor 1.5 m above the ground. Labels: 0 ground, 1..3 rocks."""
    rng = np.random.default_rng(seed)
    parts, labels = [_ground(rng, 12000, 6.0, 0.005)], [np.zeros(12000, int)]
    for i, cx in enumerate((-4.0, 0.0, 4.0), start=1):
        parts.append(_dome(rng, 1500, (cx, 3.0, 0.0), (0.6, 0.6, 0.6)))
        labels.append(np.full(1500, i))
    X = np.vstack(parts) - [0.0, 0.0, 1.5]
    return X, np.concatenate(labels)


def ground_with_small_obstacles(seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Dense flat ground with small sparse obstacles (cubes of 0.4 m) standing on it. Labels:
    0 ground, 1 obstacles. The sensor is 1.5 m above the ground."""
    rng = np.random.default_rng(seed)
    g = _ground(rng, 15000, 5.0, 0.005)
    obs = []
    for cx, cy in ((-2.5, -2.0), (1.5, 2.5), (3.0, -3.0), (-1.0, 3.5), (0.5, -0.5), (-3.5, 1.0)):
        P = rng.uniform(-1, 1, (400, 3))
        face = rng.integers(0, 3, 400)
        P[np.arange(400), face] = np.sign(rng.uniform(-1, 1, 400))
        P = P * 0.2 + [cx, cy, 0.2]
        obs.append(P[P[:, 2] > 0.01])
    O = np.vstack(obs)
    X = np.vstack([g, O]) - [0.0, 0.0, 1.5]
    return X, np.concatenate([np.zeros(len(g), int), np.ones(len(O), int)])


def box_on_table(seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A range sensor's view of a box on a table (metres): the table top (1.2 m x 0.8 m) and the
    three faces of the box it sees (top, front, side), 1 mm depth noise. Labels: 0 table,
    1 box top, 2 box front, 3 box side."""
    rng = np.random.default_rng(seed)
    L, W, H = 0.30, 0.20, 0.15
    table = np.column_stack([rng.uniform(-0.6, 0.6, 20000), rng.uniform(-0.4, 0.4, 20000), np.zeros(20000)])
    under = (np.abs(table[:, 0]) < L / 2) & (np.abs(table[:, 1]) < W / 2)
    table = table[~under]
    top = np.column_stack([rng.uniform(-L / 2, L / 2, 3000), rng.uniform(-W / 2, W / 2, 3000), np.full(3000, H)])
    front = np.column_stack([np.full(2500, L / 2), rng.uniform(-W / 2, W / 2, 2500), rng.uniform(0, H, 2500)])
    side = np.column_stack([rng.uniform(-L / 2, L / 2, 2500), np.full(2500, W / 2), rng.uniform(0, H, 2500)])
    parts = [table, top, front, side]
    X = np.vstack(parts)
    X = X + rng.normal(0, 0.001, X.shape)
    labels = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
    return X, labels


def turn(X: np.ndarray, degrees: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``X`` (n, 3) turned about the vertical (z) axis by ``degrees``, then shifted. Multiples of
    90 degrees are exact (coordinates swapped and negated), as a scan saved in other axes would be."""
    P = np.array(X, dtype=np.float64)
    if degrees % 90 == 0:
        for _ in range(int(degrees // 90) % 4):
            P = np.column_stack([-P[:, 1], P[:, 0], P[:, 2]])
    else:
        P = P @ rz(degrees).T
    return P + np.asarray(shift, dtype=np.float64)


def rz(degrees: float) -> np.ndarray:
    """The rotation matrix of a turn by ``degrees`` about the z axis."""
    t = np.radians(degrees)
    return np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])



def ground_and_parked_cars(seed: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Flat ground (20 m x 20 m) and a row of parked cars seen from a vehicle 5 m away: three cars
    bumper to bumper (12.6 m x 1.8 m) whose roofs, 1.45 m up, make one level sheet as thin as the
    road, and their near sides (sparse: the beams graze them). The sensor is 1.73 m above the
    ground. Labels: 0 ground, 1 the roofs, 2 the sides."""
    rng = np.random.default_rng(seed)
    g = _ground(rng, 20000, 10.0, 0.005)
    g = g[~((np.abs(g[:, 0]) < 6.3) & (np.abs(g[:, 1] - 6.0) < 0.9))]  # under the cars: hidden
    roof = np.column_stack([rng.uniform(-6.3, 6.3, 4000), rng.uniform(5.1, 6.9, 4000), rng.normal(1.45, 0.005, 4000)])
    side = np.column_stack([rng.uniform(-6.3, 6.3, 300), np.full(300, 5.1) + rng.normal(0, 0.005, 300),
                            rng.uniform(0.15, 1.45, 300)])
    X = np.vstack([g, roof, side]) - [0.0, 0.0, 1.73]
    return X, np.concatenate([np.zeros(len(g), int), np.ones(len(roof), int), np.full(len(side), 2)])


def airborne_large_building(seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """An airborne scan (z up, about 1 point per square metre, absolute-looking coordinates) of
    gently sloping ground, 160 m x 160 m rising 5 m across, and a large flat-roofed building,
    70 m x 50 m, its roof 18-19.2 m above the ground (six storeys) in sections of three levels, with a few
    points on its walls. Labels: 0 bare earth, 1 the building."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-80, 80, (25600, 2))
    inside = (np.abs(xy[:, 0]) < 35) & (np.abs(xy[:, 1]) < 25)
    z = 0.03125 * xy[:, 0] + rng.normal(0, 0.05, len(xy))
    # the roof in 5 x 5 sections (14 m x 10 m) at 18, 18.6 or 19.2 m: parapets, skylights, levels
    section = (np.floor((xy[inside, 0] + 35) / 14) * 5 + np.floor((xy[inside, 1] + 25) / 10)).astype(int)
    z[inside] += 18.0 + rng.choice([0.0, 0.6, 1.2], 25)[section]
    wall = np.column_stack([rng.uniform(-35, 35, 200), np.full(200, -25.0), rng.uniform(0.5, 17.5, 200)])
    wall[:, 2] += 0.03125 * wall[:, 0]
    X = np.vstack([np.column_stack([xy, z]), wall]) + [512000.0, 5400000.0, 250.0]
    return X, np.r_[inside.astype(int), np.ones(len(wall), int)]


def airborne_step_and_building(seed: int = 9, step: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """An airborne scan (z up, about 1 point per square metre) of level terrain, 160 m x 160 m, with
    a terrain step of ``step`` metres across it (the upper terrace x > 10 m; the step's face a 2 m
    wide bank), and beside the step, on the lower terrace, a flat-roofed building 24 m x 16 m, its
    roof 7 m up, with a few points on its walls. Labels: 0 bare earth (both terraces and the bank),
    1 the building."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-80, 80, (25600, 2))
    z = step * np.clip((xy[:, 0] - 10.0) / 2.0, 0.0, 1.0) + rng.normal(0, 0.05, len(xy))
    inside = (np.abs(xy[:, 0] + 12.0) < 12) & (np.abs(xy[:, 1]) < 8)  # x in [-24, 0]: 10 m from the bank
    z[inside] += 7.0
    wall = np.column_stack([rng.uniform(-24, 0, 120), np.full(120, -8.0), rng.uniform(0.5, 6.5, 120)])
    X = np.vstack([np.column_stack([xy, z]), wall]) + [512000.0, 5400000.0, 250.0]
    return X, np.r_[inside.astype(int), np.ones(len(wall), int)]


def airborne_pit(seed: int = 3, depth: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """An airborne scan (z up, about 1 point per square metre) of gently sloping terrain (1 %),
    160 m x 160 m, with a pit ``depth`` metres deep, 60 m x 40 m (a quarry: its walls 2 m wide,
    76 deg for 8 m), and beside it a flat-roofed building 24 m x 16 m, its roof 7 m up, with a few
    points on a wall. Labels: 0 bare earth (the terrain, the pit's floor and walls), 1 the
    building."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-80, 80, (25600, 2))
    inside = np.minimum(30.0 - np.abs(xy[:, 0] - 20.0), 20.0 - np.abs(xy[:, 1]))  # metres inside the pit's rim
    z = -depth * np.clip(inside / 2.0, 0.0, 1.0) + 0.01 * xy[:, 0] + rng.normal(0, 0.05, len(xy))
    building = (np.abs(xy[:, 0] + 45.0) < 12) & (np.abs(xy[:, 1] - 40.0) < 8)
    z[building] += 7.0
    wall = np.column_stack([rng.uniform(-57, -33, 120), np.full(120, 32.0), rng.uniform(0.5, 6.5, 120)])
    X = np.vstack([np.column_stack([xy, z]), wall]) + [512000.0, 5400000.0, 250.0]
    return X, np.r_[building.astype(int), np.ones(len(wall), int)]


def airborne_large_roof(seed: int = 9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An airborne scan (z up, 1 point per square metre) of level ground, 120 m x 120 m, with a
    building 50 m x 50 m whose flat roof, 8 m up, has a raised core 26 m x 26 m (0.8 m higher) in
    its middle: the core's neighbours are the roof's outer ring, 12 m wide, not the ground. Labels:
    0 bare earth, 1 the building; and the mask of the core's points."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-60, 60, (14400, 2))
    z = rng.normal(0, 0.05, len(xy))
    building = (np.abs(xy[:, 0]) < 25) & (np.abs(xy[:, 1]) < 25)
    core = (np.abs(xy[:, 0]) < 13) & (np.abs(xy[:, 1]) < 13)
    z[building] += 8.0
    z[core] += 0.8
    X = np.column_stack([xy, z]) + [512000.0, 5400000.0, 250.0]
    return X, building.astype(int), core


def airborne_without(folder, rules: tuple[str, ...], checks: tuple[str, ...] = ()) -> str:
    """rules/airborne.yaml without the relabel rules ``rules`` and the checks ``checks``, written in
    ``folder``: the rule base as it was before those rules, to show what each one does."""
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[1]
    doc = yaml.safe_load((root / "rules" / "airborne.yaml").read_text())
    steps = [step for step in doc["post"] if "relabel" in step]
    names = [r["name"] for step in steps for r in step["relabel"]]
    assert set(rules) <= set(names), (rules, names)
    for step in steps:
        step["relabel"] = [r for r in step["relabel"] if r["name"] not in rules]
    doc["post"] = [step for step in doc["post"] if "relabel" not in step or step["relabel"]]
    for name in checks:
        del doc["checks"][name]
    path = Path(folder) / ("airborne-without-" + "-".join(rules) + ".yaml")
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(path)


def outdoor_rejecting_fragments(folder) -> str:
    """The path of a copy of the shipped outdoor rules (written in ``folder``) whose noise rule
    rejects every cluster of 15 points or fewer, as it did before session 41 (now only a point
    alone): for runs that need tiles with no cluster at all."""
    import re
    from pathlib import Path

    from kbs.knowledge.rulebase import shipped_text

    text, n = re.subn(r"(  tiny:\n(?:    [^\n]*\n)*?    max: )1\b[^\n]*\n", r"\g<1>15\n", shipped_text("outdoor"))
    assert n == 1
    path = Path(folder) / "outdoor-fragments-rejected.yaml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def outdoor_one_release(rb=None):
    """The outdoor rule base (``rb``, default the shipped one) parsed again without its second
    ground_release (on rough ground, session 42): the rules the tests of the first release, of a
    post mapping (one step of each kind) and of the degenerate-cluster outcome were written on."""
    from pathlib import Path

    from kbs.knowledge import PredicateRegistry, load_rule_base
    from kbs.knowledge.rulebase import parse_rule_base

    rb = load_rule_base("outdoor") if rb is None else rb
    lines = rb.text.split("\n")
    second = [i for i, ln in enumerate(lines) if ln.startswith("  - ground_release:")][1]
    end = next(i for i in range(second + 1, len(lines)) if not lines[i].startswith("      "))
    return parse_rule_base("\n".join(lines[:second] + lines[end:]), Path(rb.path).name,
                           PredicateRegistry.default(entry_points_too=False))
