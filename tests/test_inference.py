"""The inference motor against independent references (np.cov, scikit-learn's GaussianMixture),
on data that breaks the naive formulas, and for the invariants UFP-ONC promises."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import solve_triangular
from sklearn.mixture import GaussianMixture

from kbs.errors import FitError, ParameterError
from kbs.inference import (
    FuzzyCMeans,
    GathGeva,
    angle_between_planes,
    auto_voxel_size,
    cluster_geometry,
    first_local_max,
    ufp_onc,
    voxel_reduce,
)
from kbs.inference.kernels import Moments, fuzzy_covariances
from kbs.inference.ufp_onc import prepare_fit_set
from kbs.inference.voxel import HorizontalFrame, ladder_size
from scenes import anisotropic_blobs, ground_and_boxes, rz, turn


def gmm_with(centers, covariances, priors) -> GaussianMixture:
    """A scikit-learn GaussianMixture carrying exactly the given parameters."""
    gm = GaussianMixture(n_components=len(priors), covariance_type="full")
    gm.weights_, gm.means_, gm.covariances_ = priors, centers, covariances
    eye = np.eye(centers.shape[1])
    gm.precisions_cholesky_ = np.stack(
        [solve_triangular(np.linalg.cholesky(c), eye, lower=True).T for c in covariances]
    )
    return gm


def match_columns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Permutation p such that columns b[:, p] best match a (clusters are unordered)."""
    from scipy.optimize import linear_sum_assignment

    cost = -(a.T @ b)
    return linear_sum_assignment(cost)[1]


# --- references -----------------------------------------------------------------------------


def test_memberships_equal_gaussian_mixture_posteriors_at_m2():
    X, _ = anisotropic_blobs()
    gg = GathGeva(n_clusters=3).fit(X)
    ref = gmm_with(gg.centers_, gg.covariances_, gg.priors_).predict_proba(X)
    np.testing.assert_allclose(gg.memberships_, ref, rtol=0, atol=1e-9)
    Y = np.random.default_rng(5).normal(0, 10, (500, 3))
    np.testing.assert_allclose(gg.predict_proba(Y), gmm_with(gg.centers_, gg.covariances_, gg.priors_).predict_proba(Y),
                               rtol=0, atol=1e-9)


def test_memberships_equal_gmm_posteriors_for_the_ufp_onc_partition():
    X = ground_and_boxes(4000, 800)
    res = ufp_onc(X, 5, max_fit_points=None)
    for part in res.partitions[1:]:
        ref = gmm_with(part.centers, part.covariances, part.priors).predict_proba(X)
        np.testing.assert_allclose(part.predict_proba(X), ref, rtol=0, atol=1e-9)


def test_memberships_differ_from_gmm_when_m_is_not_2():
    X = np.random.default_rng(4).normal(0, 1, (600, 3)) * [3, 1, 1]
    gg = GathGeva(n_clusters=2, m=1.5).fit(X)
    ref = gmm_with(gg.centers_, gg.covariances_, gg.priors_).predict_proba(X)
    # exponent 1/(m-1) = 2: memberships are sharper than the posteriors, yet sum to one
    assert np.abs(gg.memberships_ - ref).max() > 1e-3
    np.testing.assert_allclose(gg.memberships_.sum(axis=1), 1.0, atol=1e-12)


def test_hard_memberships_give_numpy_covariance():
    X, labels = anisotropic_blobs(300)
    X = X + [100.0, -50.0, 7.0]
    u = np.stack([(labels == k).astype(float) for k in range(3)])  # (K, n)
    mom = Moments.build(X, np.ones(len(X)))
    centers = mom.centers(u, 2.0)
    cov, mass = fuzzy_covariances(mom, u, centers)
    for k in range(3):
        np.testing.assert_allclose(centers[k], X[labels == k].mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(cov[k], np.cov(X[labels == k].T, bias=True), rtol=1e-9, atol=1e-12)
        geo = cluster_geometry(X, (labels == k).astype(float))
        np.testing.assert_allclose(geo.covariance, np.cov(X[labels == k].T, bias=True), rtol=1e-12, atol=1e-14)
    assert mass.tolist() == [300.0, 300.0, 300.0]


def test_weighted_covariance_matches_numpy_aweights():
    X, _ = anisotropic_blobs(200)
    w = np.random.default_rng(2).uniform(0.1, 3.0, len(X))
    geo = cluster_geometry(X, None, w)
    np.testing.assert_allclose(geo.covariance, np.cov(X.T, aweights=w, bias=True), rtol=1e-12)


def test_sample_weight_equals_repeating_points():
    X, _ = anisotropic_blobs(150)
    w = np.random.default_rng(3).integers(1, 4, len(X))
    a = GathGeva(3).fit(X, sample_weight=w.astype(float))
    b = GathGeva(3).fit(np.repeat(X, w, axis=0))
    p = match_columns(a.centers_.T, b.centers_.T)
    np.testing.assert_allclose(a.centers_, b.centers_[p], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(a.covariances_, b.covariances_[p], rtol=1e-5, atol=1e-7)


# --- numerics ------------------------------------------------------------------------------


def _hard_cases() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    far = np.vstack([rng.normal(0, 1, (200, 3)), rng.normal(0, 1, (200, 3)) + 1e4, rng.normal(0, 1, (200, 3)) - 1e4])
    plane = np.column_stack([rng.uniform(-5, 5, 400), rng.uniform(-5, 5, 400), np.zeros(400)])
    line = np.outer(rng.uniform(-5, 5, 300), [1.0, 2.0, -0.5]) + [10.0, 0.0, 0.0]
    planar_and_linear = np.vstack([plane, line])
    dup = np.vstack([np.repeat([[1.0, 2.0, 3.0]], 300, axis=0), np.repeat([[-4.0, 0.0, 1.0]], 300, axis=0),
                     rng.normal(0, 0.5, (300, 3))])
    return {"1e4 apart": far, "planar + collinear": planar_and_linear, "duplicated points": dup}


@pytest.mark.parametrize("name", list(_hard_cases()))
def test_memberships_finite_where_naive_formula_overflows(name):
    X = _hard_cases()[name]
    res = ufp_onc(X, 6, max_fit_points=None)
    for part in res.partitions:
        u = part.predict_proba(X)
        assert np.isfinite(u).all()
        np.testing.assert_allclose(u.sum(axis=1), 1.0, atol=1e-12)
        assert np.isfinite([part.fhv, part.pd, part.apd]).all()
    assert np.isfinite(res.memberships).all()


def test_naive_exponential_distance_really_overflows_on_far_points():
    # guards the test above: the plain formula is not usable on this data
    X = _hard_cases()["1e4 apart"]
    gg = GathGeva(3).fit(X)
    k = int(np.argmin(np.linalg.det(gg.covariances_)))  # the tightest cluster
    diff = X - gg.centers_[k]
    maha = np.einsum("ni,ij,nj->n", diff, np.linalg.inv(gg.covariances_[k]), diff)
    with np.errstate(over="ignore"):
        assert np.isinf(np.exp(maha / 2)).any()


def test_perfect_plane_is_floored_and_thickness_is_zero():
    X = _hard_cases()["planar + collinear"][:400]
    gg = GathGeva(1, max_condition=1e4).fit(X)
    lam = np.linalg.eigvalsh(gg.covariances_[0])
    assert lam[0] == pytest.approx(lam[-1] / 1e4, rel=1e-9)  # floored, not zero
    geo = cluster_geometry(X)
    assert geo.thickness < 1e-12  # the descriptor uses the raw covariance
    np.testing.assert_allclose(abs(geo.normal @ [0, 0, 1.0]), 1.0, atol=1e-12)


def test_absolute_coordinates_give_the_same_partition_as_centred_ones():
    X = ground_and_boxes(3000, 600)
    a = ufp_onc(X, 4, max_fit_points=None)
    b = ufp_onc(X + [512743.0, 5403547.0, 308.0], 4, max_fit_points=None)
    assert a.chosen_k == b.chosen_k
    np.testing.assert_allclose([p.apd for p in a.partitions], [p.apd for p in b.partitions], rtol=1e-6)
    np.testing.assert_allclose(a.memberships, b.memberships, atol=1e-6)


# --- UFP-ONC ---------------------------------------------------------------------------------


def test_ufp_onc_finds_three_blobs_and_apd_peaks_there():
    X, labels = anisotropic_blobs()
    res = ufp_onc(X, 8)
    apd = {p.k: p.apd for p in res.partitions}
    assert res.chosen_k == 3
    assert apd[3] > apd[2] and apd[3] > apd.get(4, -np.inf)
    assert max(apd, key=apd.get) == 3
    # and the clusters are the blobs
    from sklearn.metrics import adjusted_rand_score

    assert adjusted_rand_score(labels, res.labels) > 0.99


def test_first_max_stop_computes_one_past_the_peak():
    X, _ = anisotropic_blobs()
    res = ufp_onc(X, 8, stop="first_max")
    assert [p.k for p in res.partitions] == [1, 2, 3, 4]
    assert res.stop_reason == "first_max" and res.chosen_k == 3


def test_first_local_max():
    assert first_local_max([1.0]) == 0
    assert first_local_max([1.0, 3.0, 2.0, 5.0]) == 1
    assert first_local_max([3.0, 1.0, 5.0]) == 0
    assert first_local_max([1.0, 2.0, 3.0]) == 2
    assert first_local_max([1.0, 2.0, 2.0, 3.0]) == 1


def test_dead_prototype_is_reported_and_stops_the_sweep():
    X, _ = anisotropic_blobs()
    res = ufp_onc(X, 10)
    assert res.stop_reason == "no_growth"
    assert any("dropped" in note for note in res.notes)
    assert res.partitions[-1].k == len(res.partitions) < 10


def test_too_few_points_is_a_fit_error():
    with pytest.raises(FitError, match="minimum cluster size"):
        ufp_onc(np.zeros((3, 3)), 2)


def test_voxel_reduction_keeps_weights_and_moments():
    X = ground_and_boxes(5000, 500)
    red = voxel_reduce(X, 0.5)
    assert red.weights.sum() == len(X)
    np.testing.assert_allclose((red.centroids * red.weights[:, None]).sum(0) / len(X), X.mean(0), rtol=1e-9)
    # total scatter = between-voxel + within-voxel scatter
    between = ((red.centroids - X.mean(0)).T * red.weights) @ (red.centroids - X.mean(0))
    np.testing.assert_allclose((between + red.scatter.sum(0)) / len(X), np.cov(X.T, bias=True), rtol=1e-9, atol=1e-12)
    size = auto_voxel_size(X, 2000)
    assert len(voxel_reduce(X, size)) <= 2000 < len(voxel_reduce(X, size / 1.25))


def _weights(n: int) -> np.ndarray:
    return np.random.default_rng(2).integers(1, 4, n).astype(float)


@pytest.mark.parametrize("degrees", [90, 180, 270])
def test_quarter_turned_cloud_gets_exactly_the_quarter_turned_fit_set(degrees):
    X = ground_and_boxes(6000, 800)
    w = _weights(len(X))
    a = prepare_fit_set(X, w, max_fit_points=1500, voxel_size=None)
    b = prepare_fit_set(turn(X, degrees), w, max_fit_points=1500, voxel_size=None)
    assert a.voxel_size is not None and a.voxel_size == b.voxel_size
    # the same voxels in the same order, to the last bit
    assert np.array_equal(turn(a.moments.X, degrees), b.moments.X)
    assert np.array_equal(a.moments.w, b.moments.w)
    R = rz(degrees)
    np.testing.assert_allclose(R @ a.moments.scatter @ R.T, b.moments.scatter, rtol=0, atol=1e-12)


@pytest.mark.parametrize("degrees", [33.7, 45.0, 123.4])
def test_cloud_turned_about_the_vertical_and_shifted_gets_the_same_fit_set_turned(degrees):
    X = ground_and_boxes(6000, 800)
    w = _weights(len(X))
    shift = [250.0, -1300.0, 7.5]
    a = prepare_fit_set(X, w, max_fit_points=1500, voxel_size=None)
    b = prepare_fit_set(turn(X, degrees, shift), w, max_fit_points=1500, voxel_size=None)
    assert b.voxel_size == pytest.approx(a.voxel_size, rel=1e-12)
    assert b.moments.n == a.moments.n and np.array_equal(a.moments.w, b.moments.w)
    np.testing.assert_allclose(turn(a.moments.X + a.offset, degrees, shift), b.moments.X + b.offset, rtol=0, atol=1e-9)
    R = rz(degrees)
    np.testing.assert_allclose(R @ a.moments.scatter @ R.T, b.moments.scatter, rtol=0, atol=1e-9)


@pytest.mark.parametrize("degrees", [45.0, 123.4])
def test_voxel_edge_stays_when_a_turned_cloud_is_rounded_to_float32(degrees):
    """A turned scan is saved rounded to float32: its points move by a micrometre. The voxel edge,
    taken from a ladder, stays, and so does every voxel (counted to the voxel, the edge moved with
    the counts: on SemanticKITTI 000001 turned by 45 degrees, 6 % of the cluster ids changed)."""
    X = ground_and_boxes(6000, 800)
    w = _weights(len(X))
    shift = [25.0, -13.0, 1.5]
    a = prepare_fit_set(X, w, max_fit_points=1500, voxel_size=None)
    rounded = turn(X, degrees, shift).astype(np.float32).astype(np.float64)
    b = prepare_fit_set(rounded, w, max_fit_points=1500, voxel_size=None)
    assert b.voxel_size == a.voxel_size
    assert np.array_equal(a.moments.w, b.moments.w)  # no point changed voxel
    np.testing.assert_allclose(turn(a.moments.X + a.offset, degrees, shift), b.moments.X + b.offset, rtol=0, atol=1e-5)


def test_ladder_size_takes_the_rung_at_or_above():
    rung = 2.0 ** (1 / 16)
    assert ladder_size(1.0) == 1.0 and ladder_size(2.0 ** (5 / 16)) == 2.0 ** (5 / 16)  # a rung stays
    assert ladder_size(1.0 + 1e-9) == rung
    assert ladder_size(0.3) == 2.0 ** (-27 / 16) and 0.3 > 2.0 ** (-28 / 16)
    assert ladder_size(0.3, up=1) == 2.0 ** (-26 / 16)
    X = ground_and_boxes(6000, 800)
    fit = prepare_fit_set(X, np.ones(len(X)), max_fit_points=1500, voxel_size=None)
    assert fit.moments.n <= 1500 and ladder_size(fit.voxel_size) == fit.voxel_size


def test_fit_set_from_the_cloud_frame_keeps_the_cloud_moments():
    """The reduction is computed in the cloud's own frame and put back: its weights, mean and total
    scatter (between voxels + within voxels) are still those of the points."""
    X = turn(ground_and_boxes(6000, 800), 21.0, [3.0, -4.0, 1.0])
    w = _weights(len(X))
    fit = prepare_fit_set(X, w, max_fit_points=1500, voxel_size=None)
    mom = fit.moments
    assert fit.voxel_size is not None and mom.n <= 1500
    np.testing.assert_allclose(mom.w.sum(), w.sum())
    mean = np.average(X - fit.offset, axis=0, weights=w)
    np.testing.assert_allclose(mom.wX.sum(axis=0) / mom.w.sum(), mean, rtol=0, atol=1e-9)
    D = mom.X - mean
    total = (D.T * mom.w) @ D + mom.scatter.sum(axis=0)
    np.testing.assert_allclose(total / w.sum(), np.cov(X.T, aweights=w, bias=True), rtol=1e-9, atol=1e-12)


def test_horizontal_frame_of_a_square_lattice_turns_with_it():
    """A square lattice has no principal horizontal axis (its covariance is isotropic): the frame
    takes its axes from the fourth moment, and gives the same coordinates whatever the turn (up to
    the lattice's own quarter-turn symmetry)."""
    g = np.arange(-10.0, 11.0)
    S = np.array([[x, y, 0.1 * (x * x + y * y)] for x in g for y in g])
    ref = None
    for degrees in (0.0, 17.0, 90.0, 241.5):
        P = turn(S, degrees, [5.0, 7.0, 0.0])
        Y = HorizontalFrame.of(P).to_frame(P)
        key = np.sort(np.round(Y, 9).view([("u", float), ("v", float), ("z", float)]).ravel(), order=["z", "u", "v"])
        if ref is None:
            ref = key
        assert np.array_equal(key, ref), degrees


@pytest.mark.parametrize("degrees", [90.0, 33.7])
def test_ufp_onc_partition_does_not_depend_on_the_axes_of_the_cloud(degrees):
    X = ground_and_boxes(8000, 1000)
    shift = [40.0, -25.0, 3.0]
    a = ufp_onc(X, 6, max_fit_points=2000)
    b = ufp_onc(turn(X, degrees, shift), 6, max_fit_points=2000)
    assert a.voxel_size is not None
    assert [p.k for p in a.partitions] == [p.k for p in b.partitions] and a.chosen_k == b.chosen_k
    np.testing.assert_allclose([p.apd for p in a.partitions], [p.apd for p in b.partitions], rtol=1e-6)
    np.testing.assert_allclose(turn(a.best.centers, degrees, shift), b.best.centers, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.memberships, b.memberships, rtol=0, atol=1e-6)


def test_weighted_fit_on_voxel_reduction_matches_full_fit():
    X = ground_and_boxes()
    full = ufp_onc(X, 6, max_fit_points=None)
    red = ufp_onc(X, 6, max_fit_points=3000)
    assert red.n_fit <= 3000 and red.voxel_size is not None
    assert full.chosen_k == red.chosen_k
    p = match_columns(full.memberships, red.memberships)
    extent = np.ptp(X, axis=0).max()
    np.testing.assert_allclose(full.best.centers, red.best.centers[p], atol=0.01 * extent)
    np.testing.assert_allclose(full.best.priors, red.best.priors[p], atol=0.01)
    relabel = np.argsort(p)  # reduced cluster j is full cluster relabel[j]
    assert (relabel[red.labels] == full.labels).mean() > 0.98


@pytest.mark.parametrize("max_fit_points", [None, 2000])
def test_point_order_does_not_change_the_result(max_fit_points):
    X = ground_and_boxes(6000, 800)
    perm = np.random.default_rng(11).permutation(len(X))
    a = ufp_onc(X, 6, max_fit_points=max_fit_points)
    b = ufp_onc(X[perm], 6, max_fit_points=max_fit_points)
    assert [p.k for p in a.partitions] == [p.k for p in b.partitions]
    np.testing.assert_allclose([p.apd for p in a.partitions], [p.apd for p in b.partitions], rtol=1e-9)
    np.testing.assert_allclose(a.memberships[perm], b.memberships, atol=1e-9)


def test_chunked_memberships_equal_one_shot():
    X = ground_and_boxes(3000, 300)
    part = ufp_onc(X, 4, max_fit_points=None).best
    np.testing.assert_array_equal(part.predict_proba(X, chunk_size=97), part.predict_proba(X, chunk_size=10**6))


def test_memory_grows_linearly_without_n_k_d_d_temporaries():
    X = ground_and_boxes(200000, 20000, seed=4)
    tracemalloc.start()
    res = ufp_onc(X, 10, max_fit_points=4000)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    n, K = len(X), res.chosen_k
    # the output (n K float64) plus a few n-sized arrays; an (n, K, 3, 3) temporary alone would
    # be 72 K bytes a point
    assert peak < n * (8 * K + 200), f"peak {peak / 1e6:.0f} MB for {n} points"


@settings(max_examples=25, deadline=None)
@given(st.integers(20, 200), st.integers(1, 5), st.integers(0, 10**6), st.floats(1e-3, 1e3))
def test_memberships_always_sum_to_one(n, k, seed, scale):
    X = np.random.default_rng(seed).normal(0, scale, (n, 3))
    res = ufp_onc(X, k, max_fit_points=None)
    for part in res.partitions:
        u = part.predict_proba(X)
        assert np.isfinite(u).all() and (u >= 0).all()
        np.testing.assert_allclose(u.sum(axis=1), 1.0, atol=1e-12)


# --- estimators ----------------------------------------------------------------------------


def test_estimators_follow_the_sklearn_contract():
    X, labels = anisotropic_blobs()
    for est in (FuzzyCMeans(3), GathGeva(3), GathGeva(3, init="fcm", random_state=0),
                FuzzyCMeans(3, init="k-means++", random_state=0)):
        assert est.fit(X) is est
        assert est.memberships_.shape == (len(X), 3)
        np.testing.assert_array_equal(est.predict(X), est.labels_)
        np.testing.assert_allclose(est.predict_proba(X), est.memberships_, atol=1e-12)
        assert est.get_params()["n_clusters"] == 3
        assert isinstance(est.n_iter_, int) and isinstance(est.converged_, bool)
    from sklearn.base import clone

    assert clone(GathGeva(4, m=1.7)).get_params()["m"] == 1.7


def test_fcm_memberships_follow_the_formula():
    X, _ = anisotropic_blobs(100)
    f = FuzzyCMeans(3, m=2.5).fit(X)
    d2 = ((X[:, None, :] - f.centers_[None]) ** 2).sum(-1)
    ref = 1.0 / ((d2[:, :, None] / d2[:, None, :]) ** (1 / 1.5)).sum(axis=2)
    np.testing.assert_allclose(f.memberships_, ref, rtol=1e-10)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"tol": -1}, "The 'tol' parameter of GathGeva must be a float in the range (0, inf). Got -1 instead."),
        ({"m": 1}, "The 'm' parameter of GathGeva must be a float in the range (1, inf). Got 1 instead."),
        ({"init": "random"}, "The 'init' parameter of GathGeva must be a str among {'incremental', 'fcm'}"),
        ({"n_clusters": 0}, "The 'n_clusters' parameter of GathGeva must be an int in the range [1, inf). Got 0"),
    ],
)
def test_bad_parameters_say_what_was_expected(kwargs, message):
    X, _ = anisotropic_blobs(50)
    with pytest.raises(ParameterError) as info:
        GathGeva(**kwargs).fit(X)
    assert message in str(info.value)


def test_nan_points_are_refused():
    X, _ = anisotropic_blobs(50)
    X[3, 1] = np.nan
    with pytest.raises(ParameterError, match="NaN or infinite values in 1 rows"):
        ufp_onc(X)
    with pytest.raises(ValueError):  # also a ValueError, as scikit-learn users expect
        GathGeva(2).fit(X)


def test_unfitted_estimator_says_so():
    with pytest.raises(ParameterError, match="not fitted"):
        GathGeva(2).predict(np.zeros((3, 3)))


# --- geometry ------------------------------------------------------------------------------


def test_geometry_of_a_noisy_tilted_plane():
    rng = np.random.default_rng(9)
    n = 5000
    P = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-1, 1, n), rng.normal(0, 0.02, n)])
    rot = np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    geo = cluster_geometry(P @ rot.T + [5, 5, 1])
    assert geo.thickness == pytest.approx(0.02, rel=0.05)
    assert angle_between_planes(geo.normal, [0, 0, 1]) == pytest.approx(0.3, abs=0.01)
    assert np.all(np.diff(geo.eigenvalues) >= 0)
    assert np.abs(geo.distance_to_plane(P @ rot.T + [5, 5, 1])).mean() < 0.03


def test_angle_between_planes_is_folded():
    assert angle_between_planes(np.array([0, 0, 1.0]), np.array([0, 0, -1.0])) == 0.0
    assert angle_between_planes(np.array([0, 0, 1.0]), np.array([1.0, 0, 0])) == pytest.approx(np.pi / 2)


def test_min_k_seeks_the_first_apd_maximum_among_larger_k():
    X = np.random.default_rng(12).normal(0, 1, (2000, 3)) * [3.0, 1.0, 0.3]  # one blob: K = 1
    one = ufp_onc(X, 6, stop="first_max")
    assert one.chosen_k == 1 and [p.k for p in one.partitions] == [1, 2]
    two = ufp_onc(X, 6, stop="first_max", min_k=2)
    eligible = [p for p in two.partitions if p.k >= 2]
    assert two.chosen_k >= 2
    assert two.chosen_k == eligible[first_local_max([p.apd for p in eligible])].k
    assert two.partitions[0].apd > two.best.apd  # K = 1 would have won


@pytest.mark.parametrize("jit", [True, False])
def test_a_sweep_in_which_every_cluster_dies_stops_at_the_k_before(jit, monkeypatch):
    """1,000 identical points swept to K = 1,000: at K = 251 every cluster's effective size (1000 /
    251 < 4) falls below the minimum at once. A sweep that stops at its first drop stopped at
    K - 1 when some clusters died, but raised a FitError when all did (`kbs cluster --k-max 1000`
    failed where `--k-max 2` succeeded); now it stops at K = 250 either way, with one note, on the
    compiled kernels and on numpy alike."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", jit)
    X = np.ones((1000, 3))
    res = ufp_onc(X, k_max=1000, stop="k_max")
    assert [p.k for p in res.partitions] == list(range(1, 251)) and res.stop_reason == "no_growth"
    assert res.notes[-1] == ("K=251: all 251 clusters fell below the minimum effective size 4 in fcm iteration 1 "
                             "(effective sizes 3.98-3.98); the sweep stopped at K=250")
    with pytest.raises(FitError, match="every cluster fell below"):  # outside a sweep, still an error
        from kbs.inference.engine import fcm_fit

        fcm_fit(Moments.build(X, np.ones(1000)), np.full((300, 1000), 1 / 300), m=2.0, tol=1e-3, max_iter=10,
                min_mass=4.0)
