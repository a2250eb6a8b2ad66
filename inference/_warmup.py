"""Compile and cache every compiled kernel (numba) by calling each the way kbs calls it, on small
data, then write the marker that tells later processes the cache is warm (see
:mod:`kbs.inference._flags`). Started in the background by the first kbs process that finds the
cache cold; ``python -m kbs.inference._warmup`` runs it by hand (in the foreground)."""
from __future__ import annotations

import sys
from pathlib import Path


def warm() -> None:
    import numpy as np

    from kbs.inference import _flags

    _flags.JIT = True
    from kbs.inference import _numba_kernels as C
    from kbs.inference import cluster_geometry, ufp_onc

    rng = np.random.default_rng(0)
    X = np.vstack([rng.normal(size=(3000, 3)) * [4.0, 4.0, 0.05], rng.normal(size=(1500, 3)) * 0.5 + [6, 0, 1],
                   rng.normal(size=(1500, 3)) * [0.2, 2.0, 0.2] + [-6, 0, 0.5]])
    ufp_onc(X, 6, max_fit_points=2000)  # voxel grids, both layers, memberships, criteria
    ufp_onc(X[:900], 4, stop="first_max")  # a split: no reduction
    cluster_geometry(X, rng.random(len(X)))
    d = np.sort(rng.random((50, 16)), axis=1)
    d[:, -3:] = np.inf
    idx = rng.integers(0, 100, (50, 16)).astype(np.int64)
    C.local_medians(d, idx, rng.random(100), rng.integers(0, 3, 100).astype(np.int64), 1, 8, 0.5)
    C.local_medians(d, idx, rng.random(100), np.zeros(0, dtype=np.int64), -1, 8, 0.25)
    C.local_medians_fast(d, idx, rng.random(100), rng.integers(0, 3, 100).astype(np.int64), 1, 8, 0.5)
    C.local_medians_fast(d, idx, rng.random(100), np.zeros(0, dtype=np.int64), -1, 8, 0.25)
    U = np.ascontiguousarray(X[:3000, :2])  # the connexity kernels (kbs.geometry.connexity)
    degree = C.connexity_degrees(U, np.ones(len(U), dtype=np.int64), 0.5, 4.0 * len(U) + 4096.0)
    C.connexity_components(U, degree >= np.median(degree) * 0.3, 0.5, True, 4.0 * len(U) + 4096.0)
    C.geometry3(X, np.zeros(0), np.zeros(0), 2.0)
    # the streamed tiles' descriptors (kbs.tiles.streamed): covariances from their sums
    C.covariance_eigen(np.ascontiguousarray(rng.random((4, 6))), np.ones(4), np.array([True, True, False, True]))
    ny, start, order, lo = C.surface_grid(U, 1.0, 4.0 * len(U) + 4096.0)  # the slope surface
    C.slope_lowest(U[:50].copy(), U, X[:3000, 2].copy(), np.zeros(3000, dtype=np.int64), 0, ny, start, order, lo,
                   1.0, 0.8, 1.0)
    S = np.ascontiguousarray(np.column_stack([U[order], X[:3000, 2][order]]))  # the thickness's grid
    C.ball_thickness(U[:50].copy(), X[:50, 2].copy(), S, ny, start, lo, 1.0, 1, 1.0, 8)
    ny, start, order, lo, hmin, box = C.slope_cells(U, X[:3000, 2].copy(), 0.25, 4.0 * len(U) + 4096.0)
    C.slope_lowest_pruned(U[:50].copy(), U, X[:3000, 2].copy(), np.zeros(3000, dtype=np.int64), 0, ny, start, order,
                          lo, 0.25, hmin, box, 0.8, 1.0, 1.0)
    for q, median in ((0.9, False), (0.5, True)):  # the predicates' order statistics
        C.quantile_linear(X[:100, 2].copy(), q, median)
    nx, ny = int((U[:, 0].max() - lo[0]) / 0.5) + 5, int((U[:, 1].max() - lo[1]) / 0.5) + 5  # the surface's bounds
    b_lo, b_hi, n3 = C.surface_blocks(U, X[:3000, 2].copy(), lo - 2.0, 0.5, nx, ny, 3)
    C.block_plane_spread(U, X[:3000, 2].copy(), lo - 2.0, 0.5, nx, ny)  # a thickness bound (ground_release's tiers)
    for narrow in (False, True):
        C.surface_bounds(U[:50].copy(), np.full(50, np.inf), np.full(50, -np.inf), lo - 2.0, 0.5, b_lo, b_hi, n3, 8,
                         narrow)
    # the surface's k nearest (kbs.geometry.groundmodel.LocalGround), its own cluster left out or not
    T = np.ascontiguousarray(X[:3000, :2])
    *grid, ok = C.plane_grid(T, 2.0 * float(np.sqrt(np.prod(T.max(axis=0) - T.min(axis=0)) / len(T))))
    heights = np.ascontiguousarray(X[:3000, 2])
    owners = (np.arange(3000) % 7).astype(np.int64)
    for k, own in ((8, -1), (64, 2)):
        C.grid_knn(np.ascontiguousarray(T[:50] + 0.01), T, *grid, k, 3.0, heights, owners, own, 8, 0)  # type: ignore[call-arg]
    # the nearest point and the nearest other (kbs.geometry.nearest), components (connexity, merge)
    tree = C.kdtree_build(np.ascontiguousarray(X[:2000]))
    C.kdtree_nearest(np.ascontiguousarray(X[2000:2100]), np.ascontiguousarray(X[:2000]), *tree, owners[:2000].copy())  # type: ignore[call-arg]
    C.nearest_other_distances(np.ascontiguousarray(X[:2000]), 1.0)
    C.graph_labels(10, np.arange(5, dtype=np.int64), np.arange(1, 6, dtype=np.int64))
    # the ground plane's RANSAC scores (kbs.geometry.groundplane)
    nrm = np.tile([[0.0, 0.0, 1.0]], (4, 1))
    C.plane_inlier_counts(np.ascontiguousarray(X[:500]), np.ascontiguousarray(X[:4]), nrm, 0.1)
    from kbs.inference import GathGeva  # the estimator's predict_proba (engine.gg_memberships)

    GathGeva(n_clusters=2, random_state=0).fit(X[2700:3300]).predict_proba(X[:50])
    _flags.marker().write_text(_flags._stamp())


def main() -> None:
    lock = Path(sys.argv[1]) if len(sys.argv) > 1 else None
    try:
        from kbs.inference import _aot

        warm()  # loads the cached kernels when they are: their signatures are what _aot exports
        if _aot.wanted() and not _aot.ready() and not _aot.failed():
            try:
                _aot.build()
            except Exception:  # noqa: BLE001 - no C compiler, pycc gone: numba's kernels it is (the note says why)
                pass
    finally:
        if lock is not None:
            try:
                lock.unlink()
            except OSError:
                pass


if __name__ == "__main__":
    main()
