"""The peers kbs is compared with, behind one interface: ``run(points) -> bool mask of ground``
or region labels. Each peer is an optional dependency (``pip install .[bench]``); a missing one
is reported, never faked.

Parameters are the peers' documented defaults, adapted to each data set where their
documentation says to (sensor height for Patchwork++, cloth resolution for CSF); every adaptation
is written here, next to the call.
"""
from __future__ import annotations

import contextlib
import importlib
import io
import os
from dataclasses import dataclass

import numpy as np


def available(module: str) -> str | None:
    """None when the module imports, else the reason it does not (one line)."""
    try:
        with _quiet():
            importlib.import_module(module)
    except Exception as exc:  # ImportError, or a missing system library (open3d needs libusb)
        return f"{type(exc).__name__}: {exc}".splitlines()[0]
    return None


@contextlib.contextmanager
def _quiet():
    """Silence C++ chatter on stdout (Patchwork++ prints at construction)."""
    fd = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            with contextlib.redirect_stdout(io.StringIO()):
                yield
    finally:
        os.dup2(fd, 1)
        os.close(fd)


@dataclass(frozen=True)
class Frame:
    """How a scan sits: ``up`` maps its points to a z-up frame for the peers that need one;
    ``sensor_height`` is the sensor's height above the ground in that frame."""

    up: np.ndarray  # (3, 3) rotation applied as X @ up.T
    sensor_height: float
    airborne: bool = False


def patchworkpp(X: np.ndarray, frame: Frame) -> np.ndarray:
    """Patchwork++ (Lee et al. 2022), pypatchworkpp with default parameters but the sensor height."""
    import pypatchworkpp

    with _quiet():
        params = pypatchworkpp.Parameters()
        params.verbose = False
        params.sensor_height = frame.sensor_height
        pw = pypatchworkpp.patchworkpp(params)
        Z = X @ frame.up.T
        pw.estimateGround(np.hstack([Z, np.zeros((len(Z), 1))]))
        idx = np.asarray(pw.getGroundIndices(), dtype=np.int64)
    mask = np.zeros(len(X), bool)
    mask[idx] = True
    return mask


def csf(X: np.ndarray, frame: Frame) -> np.ndarray:
    """Cloth Simulation Filter (Zhang et al. 2016). Defaults of the package, but for terrestrial or
    vehicle scans (not airborne) a finer cloth (0.2 m) and slope smoothing off, as its
    documentation advises for flat scenes; airborne: cloth 0.5 m, slope smoothing on."""
    import CSF

    Z = X @ frame.up.T
    with _quiet():
        c = CSF.CSF()
        c.params.bSloopSmooth = frame.airborne
        c.params.cloth_resolution = 0.5 if frame.airborne else 0.2
        c.params.rigidness = 2 if frame.airborne else 3
        c.params.class_threshold = 0.5 if frame.airborne else 0.2
        c.setPointCloud(Z - Z.mean(axis=0))
        ground, non = CSF.VecInt(), CSF.VecInt()
        c.do_filtering(ground, non, False)
    mask = np.zeros(len(X), bool)
    mask[np.asarray(ground, dtype=np.int64)] = True
    return mask


def ransac_ground(X: np.ndarray, frame: Frame, distance: float = 0.2) -> np.ndarray:
    """The plane with most inliers (Open3D ``segment_plane``, 1,000 iterations, fixed seed);
    its inliers are the ground. ``distance`` 0.2 m for vehicle scans, 0.5 m airborne, 1 cm for
    a table top."""
    import open3d as o3d

    o3d.utility.random.seed(0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(X, dtype=np.float64)))  # a writable copy
    _, inliers = pc.segment_plane(distance_threshold=distance, ransac_n=3, num_iterations=1000)
    mask = np.zeros(len(X), bool)
    mask[np.asarray(inliers, dtype=np.int64)] = True
    return mask


def ransac_dbscan_planes(X: np.ndarray, distance: float = 0.01, min_points: int = 200, max_planes: int = 30,
                         eps: float | None = None) -> np.ndarray:
    """Iterative RANSAC plane extraction, each plane's inliers split into connected pieces by
    DBSCAN (the usual Open3D recipe): region labels (n,), -1 for points in no region."""
    import open3d as o3d

    o3d.utility.random.seed(0)
    X = np.array(X, dtype=np.float64)  # Open3D wants a writable array
    labels = np.full(len(X), -1, dtype=np.int64)
    rest = np.arange(len(X))
    nxt = 0
    if eps is None:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X))
        eps = 4.0 * float(np.median(np.asarray(pc.compute_nearest_neighbor_distance())))
    for _ in range(max_planes):
        if rest.size < min_points:
            break
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X[rest]))
        _, inl = pc.segment_plane(distance_threshold=distance, ransac_n=3, num_iterations=1000)
        inl = np.asarray(inl, dtype=np.int64)
        if inl.size < min_points:
            break
        sub = pc.select_by_index(inl)
        parts = np.asarray(sub.cluster_dbscan(eps=eps, min_points=10))
        for p in np.unique(parts[parts >= 0]):
            sel = inl[parts == p]
            if sel.size >= min_points:
                labels[rest[sel]] = nxt
                nxt += 1
        rest = np.delete(rest, inl)
    return labels


def gmm_bic_regions(X: np.ndarray, k_max: int = 15, seed: int = 0) -> np.ndarray:
    """scikit-learn GaussianMixture (full covariance) with K chosen by BIC over 1..k_max (15), fitted
    on at most 20,000 points (a fixed random subset), labels predicted for all."""
    from sklearn.mixture import GaussianMixture

    rng = np.random.default_rng(seed)
    fit = X if len(X) <= 20000 else X[rng.choice(len(X), 20000, replace=False)]
    best, best_bic = None, np.inf
    for k in range(1, k_max + 1):
        gm = GaussianMixture(k, covariance_type="full", random_state=seed).fit(fit)
        bic = gm.bic(fit)
        if bic < best_bic:
            best, best_bic = gm, bic
    return best.predict(X)
