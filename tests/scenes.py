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
