"""The compiled kernels (kbs.inference._compiled, numba) against the plain-numpy reference of
the same iterations (kbs.inference.engine with jit=False)."""
from __future__ import annotations

import numpy as np
import pytest

from kbs.inference import _compiled as C
from kbs.inference import _flags
from kbs.inference import ufp_onc
from kbs.inference.engine import fcm_fit, gg_fit, gg_memberships, new_prototype_memberships
from kbs.inference.kernels import Moments, floor_covariances
from kbs.inference.voxel import voxel_reduce


def _blobs(seed: int, n: int = 1500) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n // 3, 3)) * [2.0, 2.0, 0.05]  # a sheet
    b = rng.normal(size=(n // 3, 3)) * 0.4 + [3.0, 1.0, 1.0]  # a blob
    c = rng.normal(size=(n - 2 * (n // 3), 3)) * [0.1, 1.5, 0.1] + [-3.0, 0.0, 0.5]  # a rod
    return np.vstack([a, b, c])


def _moments(X: np.ndarray, weighted: bool) -> Moments:
    if weighted:
        red = voxel_reduce(X - X.mean(axis=0), 0.3)
        return Moments.build(red.centroids, red.weights, red.scatter)
    return Moments.build(X - X.mean(axis=0), np.ones(len(X)))


def _start(mom: Moments, k: int, m: float) -> np.ndarray:
    centers = mom.X[np.linspace(0, mom.n - 1, k - 1).astype(int)]
    d0 = 10.0 * float(np.trace(np.cov(mom.X.T)))
    return new_prototype_memberships(mom.XT, centers, d0, m)


@pytest.mark.slow
def test_exp_row_matches_numpy():
    x = np.concatenate([-np.geomspace(1e-12, 707.0, 5000), [0.0, -0.5, -1e-300]])
    out = np.empty_like(x)
    C._exp_row(x, np.empty(x.size, dtype=np.int64), out)
    ref = np.exp(x)
    assert np.max(np.abs(out - ref) / ref) < 2e-15
    far = np.array([-708.5, -800.0, -1e6])
    out = np.empty(3)
    C._exp_row(far, np.empty(3, dtype=np.int64), out)
    assert np.all(out == 0.0)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("m", [2.0, 1.6])
@pytest.mark.parametrize("k", [2, 4])
def test_fcm_compiled_equals_reference(weighted, m, k):
    mom = _moments(_blobs(1), weighted)
    u0 = _start(mom, k, m)
    kw = dict(m=m, tol=1e-4, max_iter=200, min_mass=4.0)
    a = fcm_fit(mom, u0, jit=True, **kw)
    b = fcm_fit(mom, u0, jit=False, **kw)
    assert a.n_iter == b.n_iter and a.converged == b.converged
    np.testing.assert_allclose(a.memberships, b.memberships, atol=1e-9)
    np.testing.assert_allclose(a.centers, b.centers, atol=1e-9)


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("accelerate", [True, False])
@pytest.mark.parametrize("m,power", [(2.0, 2.0), (2.0, 1.0), (1.7, 1.7)])
def test_gg_compiled_equals_reference(weighted, accelerate, m, power):
    mom = _moments(_blobs(2), weighted)
    u0 = fcm_fit(mom, _start(mom, 3, m), m=m, tol=1e-3, max_iter=100, min_mass=4.0, jit=False).memberships
    kw = dict(m=m, center_power=power, tol=1e-5, max_iter=150, min_variance=1e-6, max_condition=1e4, min_mass=4.0,
              accelerate=accelerate)
    a = gg_fit(mom, u0, jit=True, **kw)
    b = gg_fit(mom, u0, jit=False, **kw)
    assert a.n_iter == b.n_iter and a.converged == b.converged
    np.testing.assert_allclose(a.memberships, b.memberships, atol=1e-8)
    np.testing.assert_allclose(a.maha, b.maha, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(a.centers, b.centers, atol=1e-8)
    np.testing.assert_allclose(a.priors, b.priors, atol=1e-9)
    np.testing.assert_allclose(a.gaussians.covariances, b.gaussians.covariances, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(a.gaussians.logdet, b.gaussians.logdet, rtol=1e-9, atol=1e-9)


def test_a_dying_cluster_is_recorded_as_by_the_reference():
    """The compiled loop hands a drop over to the reference, which records it."""
    mom = _moments(_blobs(3, 600), False)
    u0 = _start(mom, 4, 2.0)
    kw = dict(m=2.0, tol=1e-3, max_iter=100, min_mass=0.3 * mom.n)  # most clusters cannot keep 30 %
    a = fcm_fit(mom, u0, jit=True, **kw)
    b = fcm_fit(mom, u0, jit=False, **kw)
    assert b.dropped and [str(d) for d in a.dropped] == [str(d) for d in b.dropped]
    u1 = _start(mom, 3, 2.0)
    kw = dict(m=2.0, center_power=2.0, tol=1e-3, max_iter=100, min_variance=1e-6, max_condition=1e4,
              min_mass=0.4 * mom.n)
    a = gg_fit(mom, u1, jit=True, **kw)
    b = gg_fit(mom, u1, jit=False, **kw)
    assert b.dropped and [str(d) for d in a.dropped] == [str(d) for d in b.dropped]
    np.testing.assert_allclose(a.memberships, b.memberships, atol=1e-9)


def test_predicted_memberships_match():
    rng = np.random.default_rng(4)
    XT = np.ascontiguousarray(rng.normal(size=(3, 5000)) * 3.0)
    cov = np.stack([np.diag([1.0, 0.5, 1e-9]), np.eye(3) * 4.0, np.diag([0.01, 2.0, 2.0])])
    gauss = floor_covariances(cov, 1e-6, 1e4)
    centers = np.array([[0.0, 0.0, 0.0], [5.0, 1.0, -2.0], [-3.0, 3.0, 0.0]])
    priors = np.array([0.5, 0.3, 0.2])
    for m in (2.0, 1.5):
        a = C.gg_predict(XT, centers, gauss.whitening, gauss.logdet, priors, m)
        from kbs.inference.kernels import gg_memberships_from_maha, mahalanobis_sq

        b = gg_memberships_from_maha(mahalanobis_sq(XT, centers, gauss.whitening), gauss.logdet, np.log(priors), m)
        np.testing.assert_allclose(a, b, atol=1e-12)
        np.testing.assert_allclose(gg_memberships(XT, centers, gauss, priors, m), b, atol=1e-12)


def test_ufp_onc_sweep_same_with_and_without_compiled_kernels(monkeypatch):
    X = _blobs(5, 9000) * [1.0, 1.0, 1.0] + [100.0, -50.0, 3.0]
    a = ufp_onc(X, 6, max_fit_points=2000)
    monkeypatch.setattr(_flags, "JIT", False)
    b = ufp_onc(X, 6, max_fit_points=2000)
    assert a.chosen_k == b.chosen_k and a.stop_reason == b.stop_reason
    assert [(p.n_iter_fcm, p.n_iter_gg) for p in a.partitions] == [(p.n_iter_fcm, p.n_iter_gg) for p in b.partitions]
    np.testing.assert_allclose([p.apd for p in a.partitions], [p.apd for p in b.partitions], rtol=1e-8)
    np.testing.assert_allclose(a.memberships, b.memberships, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_voxel_grids_give_the_reference_fitting_set(monkeypatch, seed):
    """Hash-table voxel counting and reduction: the same voxel size and the same moments as the
    sort-based reference (identical arrays, not merely close)."""
    from kbs.inference.ufp_onc import prepare_fit_set
    from kbs.inference.voxel import auto_voxel_size, count_voxels

    rng = np.random.default_rng(seed)
    X = np.vstack([_blobs(seed, 30000) * 5.0, rng.uniform(-20, 20, size=(5000, 3))]) + [3e5, 5e6, 40.0]
    w = rng.integers(1, 4, size=len(X)).astype(float)
    a = prepare_fit_set(X, w, max_fit_points=2500, voxel_size=None)
    sizes_a = auto_voxel_size(X - X.mean(axis=0), 1000), count_voxels(X, 0.7)
    monkeypatch.setattr(_flags, "JIT", False)
    b = prepare_fit_set(X, w, max_fit_points=2500, voxel_size=None)
    sizes_b = auto_voxel_size(X - X.mean(axis=0), 1000), count_voxels(X, 0.7)
    assert a.voxel_size == b.voxel_size and sizes_a == sizes_b
    assert np.array_equal(a.offset, b.offset)
    assert np.array_equal(a.moments.X, b.moments.X) and np.array_equal(a.moments.w, b.moments.w)
    assert np.array_equal(a.moments.stats, b.moments.stats)


def test_unique_inverse_is_numpys():
    rng = np.random.default_rng(7)
    keys = rng.integers(0, 2**40, size=3000)[rng.integers(0, 3000, size=50000)]
    k, inv = C.unique_inverse(keys)
    k2, inv2 = np.unique(keys, return_inverse=True)
    assert np.array_equal(k, k2) and np.array_equal(inv, inv2)
    lo, hi = C.bounds(np.ascontiguousarray(keys.reshape(-1, 2).astype(float)))
    assert np.array_equal(lo, keys.reshape(-1, 2).min(axis=0)) and np.array_equal(hi, keys.reshape(-1, 2).max(axis=0))


def test_stop_at_drop_names_the_same_first_drop_with_and_without_compiled_kernels():
    mom = _moments(_blobs(3, 600), False)
    u0 = _start(mom, 4, 2.0)
    kw = dict(m=2.0, tol=1e-3, max_iter=100, min_mass=0.3 * mom.n, stop_at_drop=True)
    a = fcm_fit(mom, u0, jit=True, **kw)
    b = fcm_fit(mom, u0, jit=False, **kw)
    full = fcm_fit(mom, u0, jit=False, **{**kw, "stop_at_drop": False})
    assert a.dropped and [str(d) for d in a.dropped] == [str(d) for d in b.dropped]
    assert a.n_iter == b.n_iter == full.dropped[0].iteration  # stopped at the first drop
    u1 = _start(mom, 3, 2.0)
    kw = dict(m=2.0, center_power=2.0, tol=1e-3, max_iter=100, min_variance=1e-6, max_condition=1e4,
              min_mass=0.4 * mom.n, stop_at_drop=True)
    a = gg_fit(mom, u1, jit=True, **kw)
    b = gg_fit(mom, u1, jit=False, **kw)
    assert a.dropped and [str(d) for d in a.dropped] == [str(d) for d in b.dropped]


@pytest.mark.slow
@pytest.mark.parametrize("power", [2.0, 1.0, 1.5])
def test_compiled_cluster_geometry_and_criteria_match_numpy(monkeypatch, power):
    from kbs.inference import cluster_geometry
    from kbs.inference.kernels import validity

    rng = np.random.default_rng(8)
    X = _blobs(8, 3000) + [4e5, 5.4e6, 120.0]
    u, w = rng.random(len(X)), rng.integers(1, 5, len(X)).astype(float)
    a = cluster_geometry(X, u, w, center_power=power)
    maha, uu = rng.random((3, 4000)) * 3, rng.random((3, 4000))
    w4 = rng.random(4000)
    va = validity(uu, w4, maha, np.array([0.1, -2.0, 3.0]))
    monkeypatch.setattr(_flags, "JIT", False)
    b = cluster_geometry(X, u, w, center_power=power)
    vb = validity(uu, w4, maha, np.array([0.1, -2.0, 3.0]))
    np.testing.assert_allclose(a.center, b.center, rtol=1e-12)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a.eigenvalues, b.eigenvalues, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.abs(a.eigenvectors.T @ b.eigenvectors), np.eye(3), atol=1e-8)
    assert a.thickness == pytest.approx(b.thickness, rel=1e-8) and a.mass == pytest.approx(b.mass, rel=1e-12)
    np.testing.assert_allclose(va, vb, rtol=1e-12)


def _connexity_cases():
    rng = np.random.default_rng(7)
    blobs = np.vstack([rng.normal(size=(400, 3)) * [0.3, 0.3, 0.01], rng.normal(size=(400, 3)) * [0.3, 0.3, 0.01] + [3.0, 0, 0]])
    bridge = np.c_[np.linspace(0.5, 2.5, 21), np.zeros(21), np.zeros(21)]
    g = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0)), -1).reshape(-1, 2)
    lattice = np.c_[g, np.zeros(len(g))]  # exact distances, ties at the link distance
    lattice = np.vstack([lattice, lattice[:25]])  # and duplicates
    strip = np.c_[rng.random(600) * 10, rng.random(600) * 0.2, rng.random(600) * 0.01]
    far = np.vstack([rng.random((300, 3)), rng.random((300, 3)) + [1e4, 0, 0]])  # grid too large: k-d tree path
    return {"blobs": blobs, "bridged": np.vstack([blobs, bridge]), "lattice": lattice, "strip": strip, "far": far,
            "scan": _scan_piece()}


def _scan_piece():
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "semantickitti" / "000001.points.npy"
    if not path.exists():  # the synthetic cases still run
        return np.random.default_rng(3).random((2000, 3)) * [8, 8, 0.2]
    X = np.load(path)[:, :3]
    return X[np.argsort(np.linalg.norm(X - X[1234], axis=1))[:6000]]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["blobs", "bridged", "lattice", "strip", "far", "scan"])
@pytest.mark.parametrize("kw", [{}, {"opening": False}, {"erosion_fraction": 0.6}, {"alpha": 0.5}])
def test_compiled_connexity_equals_the_kd_tree_version(monkeypatch, case, kw):
    from kbs.geometry.connexity import connexity

    X = _connexity_cases()[case]
    args = (X, X.mean(axis=0), np.array([0.0, 0.0, 1.0]))
    monkeypatch.setattr(_flags, "JIT", True)
    a = connexity(*args, **kw)
    monkeypatch.setattr(_flags, "JIT", False)
    b = connexity(*args, **kw)
    assert a.n_components == b.n_components and a.n_significant == b.n_significant
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.sizes, b.sizes)
    if case == "bridged" and not kw:
        assert a.n_significant == 2  # the bridge is cut: the case exercises the opening ...
    if case == "bridged" and kw == {"opening": False}:
        assert a.n_significant == 1  # ... and without it the bridge links the blobs


def test_connexity_grid_refuses_only_an_absurd_extent():
    """Past ``max_cells`` the grid keeps its occupied cells (three points 1e6 links apart: three
    components); only an axis of 1e9 cells or more is refused (the k-d tree version answers)."""
    U = np.array([[0.0, 0.0], [1e6, 0.0], [0.0, 1e6]])
    assert C.connexity_degrees(U, np.ones(3, dtype=np.int64), 1.0, 4096.0).tolist() == [0, 0, 0]
    kept, comp, n = C.connexity_components(U, np.ones(3, dtype=bool), 1.0, False, 4096.0)
    assert n == 3 and comp.tolist() == [0, 1, 2]
    V = np.array([[0.0, 0.0], [1e10, 0.0]])
    assert C.connexity_degrees(V, np.ones(2, dtype=np.int64), 1.0, 4096.0).size == 0
    assert C.connexity_components(V, np.ones(2, dtype=bool), 1.0, False, 4096.0)[2] == -1


def test_connexity_occupied_cells_answer_as_the_full_grid_and_the_pairs_do():
    """The same degrees, dilation and components from the full grid (``max_cells`` large) and
    from the occupied cells alone (``max_cells`` small), and as the pairs within ``r`` give them:
    degrees summed over the pairs, components as scipy numbers them by their lowest point."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    U = np.r_[rng.uniform(0, 30, (600, 2)), rng.uniform(200, 203, (300, 2)), [[400.0, 5.0], [400.5, 5.0]]]
    U = np.round(U, 1)  # links exactly at r
    U = np.unique(U, axis=0)[rng.permutation(len(np.unique(U, axis=0)))]
    mult = rng.integers(1, 4, len(U))
    r = 1.0
    pairs = cKDTree(U).query_pairs(r, output_type="ndarray")
    deg = mult - 1 + np.bincount(pairs[:, 0], weights=mult[pairs[:, 1]], minlength=len(U)) \
        + np.bincount(pairs[:, 1], weights=mult[pairs[:, 0]], minlength=len(U))
    kept = deg >= np.median(deg)
    for cells in (1e9, 64.0):
        assert np.array_equal(C.connexity_degrees(U, mult, r, cells), deg)
    full = C.connexity_components(U, kept, r, True, 1e9)
    sparse = C.connexity_components(U, kept, r, True, 64.0)
    for a, b in zip(full, sparse):
        assert np.array_equal(a, b)
    out, comp, n = sparse
    back = ~kept & out  # dilated: a kept position within r
    near = cKDTree(U[kept]).query(U[~kept], k=1)[0] <= r
    assert np.array_equal(back[~kept], near) and back.any()
    idx = np.flatnonzero(out)
    keep = out[pairs[:, 0]] & out[pairs[:, 1]]
    _, ref = connected_components(coo_matrix((np.ones(keep.sum()), (pairs[keep, 0], pairs[keep, 1])),
                                             shape=(len(U), len(U))), directed=False)
    first = {c: i for i, c in reversed(list(enumerate(ref[idx])))}  # the kept positions' components, first seen first
    order = sorted(first, key=first.get)
    assert n == len(order) and np.array_equal(comp[idx], np.array([order.index(c) for c in ref[idx]]))


def test_graph_labels_number_components_as_scipy_does():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(8)
    for _ in range(30):
        n = int(rng.integers(1, 120))
        e = int(rng.integers(0, 150))
        i, j = rng.integers(0, n, e), rng.integers(0, n, e)
        ref = connected_components(coo_matrix((np.ones(e), (i, j)), shape=(n, n)), directed=False)
        got = C.graph_labels(n, i.astype(np.int64), j.astype(np.int64))
        assert got[0] == ref[0] and np.array_equal(got[1], ref[1])


def test_compiled_plane_inlier_counts_are_the_numpy_counts():
    """The RANSAC scoring of the ground-plane search: the compiled counts equal numpy's einsum
    counts exactly, on points whose distances to the hypotheses straddle the threshold."""
    from kbs.geometry.groundplane import _inlier_counts

    rng = np.random.default_rng(3)
    S = rng.normal(size=(3000, 3)) * [20.0, 20.0, 0.05] + [5.0, -3.0, -1.7]
    tri = np.array([rng.choice(S.shape[0], 3, replace=False) for _ in range(200)])
    a = S[tri[:, 0]]
    nrm = np.cross(S[tri[:, 1]] - a, S[tri[:, 2]] - a)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    ref = (np.abs(np.einsum("kij,kj->ki", S[None, :, :] - a[:, None, :], nrm)) <= 0.1).sum(axis=1)
    got = C.plane_inlier_counts(S, a, nrm, 0.1)
    assert ref.min() < got.max() and np.array_equal(got, ref)
    # exactly on the threshold: a point at distance 0.1 along an axis-aligned normal counts
    P = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, -0.1], [0.0, 0.0, 0.1000001]])
    assert C.plane_inlier_counts(P, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 0.1).tolist() == [2]
    assert np.array_equal(_inlier_counts(S, a, nrm, 0.1), ref)


def test_compiled_order_statistics_are_numpys_bit_for_bit():
    """_compiled.quantile_linear (the predicates' p90, p10 and median) against np.percentile and
    np.median: equal bit for bit whenever it says it can (ok), on sizes 1 to 5,000, rounded
    values with ties, repeated draws and zeros; it declines a NaN, an empty array and a picked zero."""
    rng = np.random.default_rng(2)
    taken = 0
    for trial in range(3000):
        n = int(rng.integers(1, 300)) if trial % 10 else int(rng.integers(1, 5000))
        h = rng.normal(size=n) * rng.choice([0.01, 1.0, 100.0])
        if trial % 4 == 0:
            h = np.round(h, 2)
        if trial % 7 == 0:
            h = rng.choice(h, n)
        for q, median, want in ((90 / 100, False, lambda a: np.percentile(a, 90)),
                                (10 / 100, False, lambda a: np.percentile(a, 10)), (0.5, True, np.median)):
            v, ok = C.quantile_linear(h, q, median)
            if ok:
                assert np.float64(v).tobytes() == np.float64(want(h)).tobytes(), (trial, q, median)
                taken += 1
    assert taken > 8000
    assert not C.quantile_linear(np.array([1.0, np.nan]), 0.9, False)[1]
    assert not C.quantile_linear(np.zeros(0), 0.5, True)[1]
    assert not C.quantile_linear(np.array([-0.0, 0.0, 1.0]), 0.5, True)[1]


def test_the_predicates_statistics_are_numpys_with_and_without_compiled_kernels(monkeypatch):
    """The statistics of height_above_local_ground / height_above_slope_surface: the compiled path
    (and its fallback to numpy on zeros, NaN and large arrays) gives numpy's values bit for bit."""
    from kbs.geometry.groundmodel import FAST_STAT_MAX
    from kbs.knowledge import predicates as P

    rng = np.random.default_rng(3)
    arrays = [rng.normal(size=n) for n in (1, 2, 3, 10, 64, 1001)]
    arrays += [np.round(rng.normal(size=50), 1), np.array([0.0, -0.0, 2.0, -1.0]), np.array([np.nan, 1.0, 2.0]),
               rng.normal(size=FAST_STAT_MAX + 3)]
    ref = {"p90": lambda a: np.percentile(a, 90), "p10": lambda a: np.percentile(a, 10), "median": np.median}
    for jit in (True, False):
        monkeypatch.setattr(_flags, "JIT", jit)
        for a in arrays:
            for name, want in ref.items():
                assert np.float64(P._STATS[name](a)).tobytes() == np.float64(want(a)).tobytes(), (jit, name, a.size)


@pytest.mark.parametrize("D", [2, 3])
def test_coarse_counts_from_the_fine_keys_are_numpys(D):
    """The voxel-size search's count of coarse cells, read from the fine keys, is the number of
    distinct rows numpy finds, for grids from as fine as the keys to a handful of cells."""
    from kbs.inference.voxel import _decode, _distinct, _keys

    rng = np.random.default_rng(11 + D)
    X = (_blobs(D, 9000) * 4.0)[:, :D]
    lo = X.min(axis=0)
    keys = C.distinct_keys(C.cell_keys(np.ascontiguousarray(X), lo, float((X.max(axis=0) - lo).max()) / 4096.0))
    cells = _decode(keys, D)
    for factor in [1.0, 1.37, 2.5, *rng.uniform(1.0, 400.0, 12), 5000.0]:
        ref = _distinct(_keys(np.floor(cells / factor).astype(np.int64))).size
        assert C.count_coarse_keys(keys, D, float(factor)) == ref, factor


@pytest.mark.parametrize("n, high", [(0, 1), (5, 1), (3000, 50), (200_000, 1 << 40)])
def test_distinct_keys_in_order_of_first_appearance(n, high):
    """The distinct keys as numpy orders them by first appearance, through tables that grow past
    their first size (200,000 distinct keys against a start of 2^17)."""
    rng = np.random.default_rng(n)
    keys = rng.integers(0, high, n).astype(np.int64)
    _, first = np.unique(keys, return_index=True)
    assert np.array_equal(C.distinct_keys(keys), keys[np.sort(first)])


@pytest.mark.parametrize("D", [2, 3])
def test_compiled_frame_and_reduction_are_numpys_bit_for_bit(monkeypatch, D):
    """HorizontalFrame.to_frame and voxel_reduce compiled: the very same floats as numpy's (no
    fused multiply-adds), zero weights included."""
    from kbs.inference.voxel import HorizontalFrame

    monkeypatch.setattr(_flags, "JIT", True)
    rng = np.random.default_rng(5)
    X = (_blobs(4, 6000) * 3.0 + [2e3, -7e2, 30.0])[:, :D]
    w = rng.integers(0, 3, size=len(X)).astype(float)  # some points weigh nothing
    frame = HorizontalFrame.of(X, w)
    a_frame, a_red = frame.to_frame(X), voxel_reduce(X, 0.37, w)
    monkeypatch.setattr(_flags, "JIT", False)
    b_frame, b_red = frame.to_frame(X), voxel_reduce(X, 0.37, w)
    assert a_frame.tobytes() == b_frame.tobytes()
    for a, b in [(a_red.centroids, b_red.centroids), (a_red.weights, b_red.weights), (a_red.scatter, b_red.scatter)]:
        assert a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("jit", [True, False])
def test_a_single_cluster_s_memberships_are_the_predicted_ones(monkeypatch, jit):
    """ufp_onc gives the memberships of a chosen K = 1 without predicting them: exactly the ones
    the prediction gives, far from the origin too."""
    monkeypatch.setattr(_flags, "JIT", jit)
    rng = np.random.default_rng(9)
    for shift in (0.0, 4e6):
        X = rng.normal(size=(3000, 3)) * [30.0, 20.0, 0.2] + shift
        res = ufp_onc(X, k_max=1)
        assert res.chosen_k == 1
        assert res.memberships.tobytes() == res.best.predict_proba(X).tobytes()


def test_the_compiled_lexicographic_order_is_numpys():
    """The fitting set's canonical order (rows by x, then y, then z; ties in input order): the
    compiled merge sort gives np.lexsort's permutation, ties, zeros of both signs and 1-4
    columns included."""
    rng = np.random.default_rng(21)
    for t in range(60):
        n, D = int(rng.integers(2, 3000)), int(rng.integers(1, 5))
        X = rng.normal(size=(n, D))
        if t % 2:
            X = np.round(X * 2.0) / 2.0  # many ties
            X[rng.random(n) < 0.2] = -0.0
        assert np.array_equal(C.lex_order(X), np.lexsort(X.T[::-1]))


def test_predicted_memberships_by_rows_are_the_chunked_ones(monkeypatch):
    """KPartition.predict_proba compiled over the rows: the very values of the chunked
    transposed path (memberships_in_chunks over gg_memberships), chunk edges included."""
    from kbs.inference.engine import memberships_in_chunks

    monkeypatch.setattr(_flags, "JIT", True)
    X = _blobs(6, 5000) + [1e5, 2e5, 30.0]
    res = ufp_onc(X, k_max=3)
    for p in res.partitions:
        centers = p.centers - p.offset
        ref = memberships_in_chunks(X, p.offset, lambda XT, c=centers, p=p: gg_memberships(XT, c, p.gaussians, p.priors, p.m),
                                    p.k, 777)
        assert p.predict_proba(X, chunk_size=777).tobytes() == ref.tobytes()


@pytest.mark.parametrize("k", [1, 3, 9])
def test_compiled_new_prototype_memberships_are_numpys_bit_for_bit(monkeypatch, k):
    """The start of K + 1's fuzzy c-means (m = 2): the compiled memberships are numpy's, points
    on a centre (a distance floored at TINY) and d0 = 0 included."""
    monkeypatch.setattr(_flags, "JIT", True)
    rng = np.random.default_rng(k)
    XT = np.ascontiguousarray(_blobs(k, 2000).T * 7.0)
    centers = XT[:, rng.integers(0, XT.shape[1], k)].T.copy()
    for d0 in (0.0, 3.5, 1e4):
        a = new_prototype_memberships(XT, centers, d0, 2.0)
        monkeypatch.setattr(_flags, "JIT", False)
        b = new_prototype_memberships(XT, centers, d0, 2.0)
        monkeypatch.setattr(_flags, "JIT", True)
        assert a.tobytes() == b.tobytes()


def test_one_cluster_s_softmax_is_the_exponential_s_ones(monkeypatch):
    """K = 1 (the first fit of every sweep): the memberships written as ones are the ones the
    exponential path gives (the numpy reference's, bit for bit); a row with a non-finite
    argument takes the exponential path, as before."""
    mom = _moments(_blobs(4), True)
    kw = dict(m=2.0, center_power=2.0, tol=1e-4, max_iter=50, min_variance=1e-6, max_condition=1e6, min_mass=4.0)
    a = gg_fit(mom, np.ones((1, mom.n)), jit=True, **kw)
    b = gg_fit(mom, np.ones((1, mom.n)), jit=False, **kw)
    assert a.memberships.tobytes() == b.memberships.tobytes() == np.ones((1, mom.n)).tobytes()
    z = np.array([[-3.5, 0.25, -700.0, 7.0]])
    u = np.empty_like(z)
    C._softmax(z.copy(), z[0].copy(), np.empty(4), np.empty(4, dtype=np.int64), u)
    assert u.tobytes() == np.ones((1, 4)).tobytes()
    bad = np.array([[-3.5, -np.inf]])  # the exponential path, as before (a division by zero)
    with pytest.raises(ZeroDivisionError):
        C._softmax(bad.copy(), bad[0].copy(), np.empty(2), np.empty(2, dtype=np.int64), np.empty_like(bad))


def test_the_plane_search_and_the_spacing_order_points_as_numpy(monkeypatch):
    """The robust plane's order of the points is np.lexsort's, and the spacing check's distinct
    rows are np.unique's and give its spacing (ties and zeros of both signs included; numpy's own
    answer for NaN)."""
    from kbs.geometry.groundplane import _xyz_order
    from kbs.units import _distinct_rows, median_spacing

    monkeypatch.setattr(_flags, "JIT", True)
    rng = np.random.default_rng(5)
    for t in range(40):
        X = rng.normal(size=(int(rng.integers(2, 2000)), 3))
        if t % 2:
            X = np.round(X * 2.0) / 2.0
            X[rng.random(len(X)) < 0.2] = -0.0
        if t % 7 == 3:
            X[0, 1] = np.nan
        assert np.array_equal(_xyz_order(X), np.lexsort((X[:, 2], X[:, 1], X[:, 0])))
        if not np.isnan(X).any():  # the same rows (which zero's sign stands for a row may differ)
            assert np.array_equal(_distinct_rows(X), np.unique(X, axis=0))
            a = median_spacing(X)
            monkeypatch.setattr(_flags, "JIT", False)
            assert median_spacing(X) == a
            monkeypatch.setattr(_flags, "JIT", True)


def test_nearest_other_distances_are_the_kd_tree_s():
    """Connexity's spacing: the compiled grid search gives cKDTree's k = 2 distances bit for bit
    (duplicates, ties on a lattice, a thin strip, far from the origin), and declines a grid it
    cannot lay."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(12)
    for t in range(60):
        n = int(rng.integers(2, 1500))
        S = rng.normal(size=(n, 2)) * rng.uniform(0.01, 50.0, size=2) + rng.uniform(-1e4, 1e4, size=2)
        if t % 3 == 1:
            S = np.round(S * 4.0) / 4.0
        if t % 5 == 2:
            S[:, 1] = S[0, 1] + (S[:, 1] - S[0, 1]) * 1e-6
        ext = S.max(axis=0) - S.min(axis=0)
        side = 4.0 * np.sqrt(np.prod(np.maximum(ext, ext.max() * 1e-3)) / n)
        d, ok = C.nearest_other_distances(np.ascontiguousarray(S), float(side))
        assert ok
        assert d.tobytes() == cKDTree(S).query(S, k=2)[0][:, 1].tobytes()
    assert not C.nearest_other_distances(np.zeros((3, 2)), 0.0)[1]
    assert not C.nearest_other_distances(np.array([[0.0, 0.0], [1e9, 1e9]]), 1.0)[1]


def test_grid_knn_rows_give_the_kd_tree_s_medians():
    """The local ground surface's queries: on the rows the compiled grid search vouches for, the
    medians (all points, or a cluster's own left out) are the k-d tree's bit for bit, and so are
    the nearest points or their owners when asked for (k = 16, 128; within a radius; queries off
    the grid; a lattice full of ties and zero heights); it vouches for most rows."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    for t in range(18):
        m = int(rng.integers(20, 2500))
        T = rng.normal(size=(m, 2)) * rng.uniform(0.5, 30.0, size=2)
        heights = rng.normal(size=m)
        if t % 3 == 1:
            T = np.round(T * 4.0) / 4.0
            heights = np.round(heights)
        owners = rng.integers(0, 4, m)
        Q = np.vstack([T[rng.integers(0, m, 150)] + rng.normal(size=(150, 2)) * 0.3, rng.normal(size=(30, 2)) * 60.0])
        own, k = (-1, 16) if t % 2 else (int(t % 4), 128)
        radius = [3.0, 1.0, 0.2][(t // 2) % 3]
        ext = T.max(axis=0) - T.min(axis=0)
        side = 2.0 * float(np.sqrt(np.prod(np.maximum(ext, ext.max() * 1e-3)) / m))
        *grid, ok = C.plane_grid(np.ascontiguousarray(T), side, 4.0, 1.0)  # duplicates allowed: the ties tested
        assert ok
        first = t % 3  # the nearest point asked for: its position, its owner, nothing
        d, i, rows = C.grid_knn(np.ascontiguousarray(Q), np.ascontiguousarray(T), *grid, k, radius, heights, owners, own,
                                16, first)
        rd, ri = cKDTree(T).query(Q, k=k, distance_upper_bound=radius)
        a = C.local_medians_fast(d[rows], i[rows], heights, owners, own, 16, 0.5)
        b = C.local_medians_fast(rd.reshape(len(Q), k)[rows], ri.reshape(len(Q), k)[rows], heights, owners, own, 16, 0.5)
        assert rows.mean() > (0.3 if t % 3 == 1 else 0.9)  # a lattice: ties at the k-th, zero heights
        assert a[0].tobytes() == b[0].tobytes()
        found = a[1] >= 0
        assert np.array_equal(found, b[1] >= 0)
        if first == 0:
            assert np.array_equal(a[1], b[1])
        elif first == 1:
            assert np.array_equal(owners[a[1][found]], owners[b[1][found]])
    T = rng.normal(size=(1000, 2))
    assert C.plane_grid(T, 0.2)[-1]
    assert not C.plane_grid(np.vstack([T, T[:50]]), 0.2)[-1]  # 5 % of the positions repeated: no grid


def _symmetric(rng, kind: int) -> np.ndarray:
    """A symmetric 3 x 3 matrix of one of the shapes covariances take."""
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if kind == 0:  # any
        M = rng.normal(size=(3, 3))
        return M @ M.T
    if kind == 1:  # a plane: the smallest eigenvalue 1e-14 .. 1e-2 of the others
        lam = [10 ** rng.uniform(-14, -2), rng.uniform(0.5, 2.0), rng.uniform(2.0, 9.0)]
    elif kind == 2:  # two equal eigenvalues
        lo = rng.uniform(0.0, 3.0)
        lam = [lo, lo, 2.0 * lo]
    elif kind == 3:  # a line: rank 1
        lam = [0.0, 0.0, rng.uniform(1.0, 2.0)]
    else:  # far from the origin, large values
        M = rng.normal(size=(3, 3)) * 1e3 + 5e5
        return M @ M.T
    A = Q @ np.diag(lam) @ Q.T
    return 0.5 * (A + A.T)


def test_the_kernels_eigensolver_equals_lapacks_to_rounding():
    """``_eigh3`` (cyclic Jacobi; the kernels' own, so that they need no LAPACK) against numpy's
    ``eigh``: the same eigenvalues to rounding, ascending, orthonormal eigenvectors with a residual
    at rounding level, for matrices of every shape a cluster's covariance takes."""
    rng = np.random.default_rng(7)
    for i in range(3000):
        A = _symmetric(rng, i % 5)
        lam, vec = C._eigh3(A)
        ref, ref_vec = np.linalg.eigh(A)
        scale = max(float(np.abs(ref).max()), 1e-300)
        assert np.all(np.diff(lam) >= 0.0), (A, lam)
        assert np.abs(lam - ref).max() <= 1e-14 * scale, (A, lam, ref)
        assert np.abs(A @ vec - vec * lam).max() <= 1e-14 * scale, A
        assert np.abs(vec.T @ vec - np.eye(3)).max() <= 1e-14, A
        # a simple eigenvalue's eigenvector is LAPACK's up to its sign
        for k in range(3):
            gap = min(abs(ref[k] - ref[j]) for j in range(3) if j != k)
            if gap > 1e-6 * scale:
                assert abs(abs(vec[:, k] @ ref_vec[:, k]) - 1.0) <= 1e-9, (A, k)


def test_the_kernels_eigensolver_on_exact_cases_and_bad_input():
    lam, vec = C._eigh3(np.zeros((3, 3)))
    assert np.array_equal(lam, np.zeros(3)) and np.array_equal(vec, np.eye(3))
    lam, vec = C._eigh3(np.diag([3.0, 1.0, 2.0]))
    assert np.array_equal(lam, [1.0, 2.0, 3.0]) and np.array_equal(vec, np.eye(3)[:, [1, 2, 0]])
    lam, vec = C._eigh3(np.eye(3) * 5.0)  # ties keep their order
    assert np.array_equal(lam, [5.0, 5.0, 5.0]) and np.array_equal(vec, np.eye(3))
    # the lower triangle is read, as LAPACK's eigh (UPLO='L') reads it
    A = np.array([[2.0, 99.0, 99.0], [1.0, 2.0, 99.0], [0.0, 0.5, 1.0]])
    np.testing.assert_allclose(C._eigh3(A)[0], np.linalg.eigh(A)[0], rtol=0, atol=1e-14)
    for bad in (np.nan, np.inf):
        A = np.eye(3)
        A[2, 1] = bad
        with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
            C._eigh3(A)
