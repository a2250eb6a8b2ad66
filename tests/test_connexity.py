"""The connexity kernel of CAh (ALGORITHMS.md section 3) on scenes whose answer is known, against
brute-force references (dense distance matrices), and for its invariants."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation
from sklearn.metrics import adjusted_rand_score
from sklearn.neighbors import NearestNeighbors

from kbs.errors import FitError, ParameterError
from kbs.inference import cluster_geometry
from kbs.geometry.connexity import (
    Connexity,
    assign_to_nearest,
    connexity,
    graph_components,
    project_on_plane,
)

UP = np.array([0.0, 0.0, 1.0])
SPACING = 0.05


def disk(center, radius: float = 1.0, rng=None) -> np.ndarray:
    """Points (k, 2) of a disk: a 5 cm grid with 1 cm jitter (no exact distance ties)."""
    rng = np.random.default_rng(0) if rng is None else rng
    t = np.arange(-radius, radius + SPACING / 2, SPACING)
    g = np.stack(np.meshgrid(t, t), axis=-1).reshape(-1, 2)
    g = g[np.hypot(g[:, 0], g[:, 1]) <= radius]
    return g + np.asarray(center) + rng.uniform(-0.01, 0.01, g.shape)


def on_ground(parts, rng=None) -> tuple[np.ndarray, np.ndarray]:
    """3D points on the plane z = 0 (1 cm of noise) and the part of each point."""
    rng = np.random.default_rng(1) if rng is None else rng
    P = np.concatenate(parts)
    y = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    return np.c_[P, rng.normal(0.0, 0.01, len(P))], y


def three_rocks() -> tuple[np.ndarray, np.ndarray]:
    """Three disks of distinct sizes (radius 1, 0.9, 0.8 m), centres 5 m apart."""
    rng = np.random.default_rng(2)
    return on_ground([disk((0, 0), 1.0, rng), disk((5, 0), 0.9, rng), disk((2.5, 4.33), 0.8, rng)])


def reference(P: np.ndarray, alpha: float, erosion_fraction: float = 0.3, opening: bool = True,
              sample: np.ndarray | None = None):
    """The documented rule, written naively with a dense distance matrix: (n_components,
    partition of the kept points as a label array with -1 for the others). The median degree
    is taken over the points ``sample`` (all by default)."""
    D = cdist(P, P)
    keep = np.ones(len(P), dtype=bool)
    linked = D <= 2 * alpha
    if opening:
        degree = linked.sum(axis=1) - 1
        eroded = degree >= erosion_fraction * np.median(degree if sample is None else degree[sample])
        keep = eroded | (linked & eroded[None, :]).any(axis=1)
    idx = np.flatnonzero(keep)
    n, comp = connected_components(linked[np.ix_(idx, idx)].astype(np.int8), directed=False)
    counts = np.bincount(comp, minlength=n)
    labels = np.full(len(P), -1)
    labels[idx] = np.where(counts[comp] > 1, comp, -1)
    return int((counts > 1).sum()), labels


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.array_equal(a < 0, b < 0) and adjusted_rand_score(a[a >= 0], b[b >= 0]) == 1.0)


# --- scenes with a known answer -------------------------------------------------------------


def test_three_rocks_are_three_significant_components_matching_the_blobs():
    X, y = three_rocks()
    c = connexity(X, X.mean(axis=0), UP)
    assert isinstance(c, Connexity)
    assert (c.n_components, c.n_significant) == (3, 3)
    assert c.significant.tolist() == [True, True, True]
    assert c.sizes.tolist() == sorted(c.sizes.tolist(), reverse=True)
    # numbered by decreasing size: the biggest rock is 0, the smallest 2
    assert np.array_equal(c.labels[c.labels >= 0], y[c.labels >= 0])
    split = assign_to_nearest(project_on_plane(X, X.mean(axis=0), UP), c.labels, c.significant)
    assert adjusted_rand_score(y, split) == 1.0


def test_one_disk_is_one_component():
    X, _ = on_ground([disk((0, 0), 1.5)])
    c = connexity(X, X.mean(axis=0), UP)
    assert (c.n_components, c.n_significant) == (1, 1)
    assert (c.labels == 0).all()  # the opening restores the whole boundary of a disk


def test_a_one_point_wide_bridge_is_cut_by_the_opening_only():
    xs = np.arange(1.0 + SPACING, 4.0 - SPACING / 2, SPACING)
    bridge = np.c_[xs, np.zeros(len(xs))]
    X, y = on_ground([disk((0, 0)), disk((5, 0), 0.9), bridge])
    opened = connexity(X, X.mean(axis=0), UP)
    raw = connexity(X, X.mean(axis=0), UP, opening=False)
    assert (opened.n_significant, opened.n_components) == (2, 2)
    assert (raw.n_significant, raw.n_components) == (1, 1)
    # the disks are kept whole; the middle of the bridge is removed, and reassigned by distance
    assert np.array_equal(opened.labels[y < 2], y[y < 2])
    assert (opened.labels[(y == 2) & (np.abs(X[:, 0] - 2.5) < 0.5)] == -1).all()
    split = assign_to_nearest(project_on_plane(X, X.mean(axis=0), UP), opened.labels, opened.significant)
    far = (y == 2) & (np.abs(X[:, 0] - 2.5) > 0.3)  # (the exact middle is a tie)
    assert np.array_equal(split[far], (X[far, 0] > 2.5).astype(int))


@pytest.mark.parametrize(("width", "cut"), [(1, True), (2, True), (3, False)])
def test_the_opening_cuts_bridges_up_to_two_points_wide(width, cut):
    xs = np.arange(1.0 + SPACING, 4.0 - SPACING / 2, SPACING)
    bridge = np.concatenate([np.c_[xs, np.full(len(xs), k * SPACING)] for k in range(width)])
    rng = np.random.default_rng(9)
    X, _ = on_ground([disk((0, 0), 1.0, rng), disk((5, 0), 0.9, rng), bridge + rng.uniform(-0.01, 0.01, bridge.shape)])
    assert connexity(X, X.mean(axis=0), UP).n_significant == (2 if cut else 1)


def test_a_speck_of_five_points_is_a_component_but_not_a_significant_one():
    speck = np.array([[3.0, 0.0], [3.05, 0.0], [3.0, 0.05], [2.95, 0.0], [3.0, -0.05]])
    X, y = on_ground([disk((0, 0)), speck])
    c = connexity(X, X.mean(axis=0), UP, opening=False)
    assert (c.n_components, c.n_significant) == (2, 1)
    assert c.significant.tolist() == [True, False]
    assert c.sizes[1] == 5 and (c.labels[y == 1] == 1).all()
    # the opening removes a component smaller than its structuring element altogether
    o = connexity(X, X.mean(axis=0), UP)
    assert (o.n_components, o.n_significant) == (1, 1)
    assert (o.labels[y == 1] == -1).all()
    split = assign_to_nearest(project_on_plane(X, X.mean(axis=0), UP), o.labels, o.significant)
    assert (split == 0).all()


def test_sample_weight_changes_significance():
    speck = np.array([[3.0, 0.0], [3.05, 0.0], [3.0, 0.05], [2.95, 0.0], [3.0, -0.05]])
    X, y = on_ground([disk((0, 0)), speck])
    w = np.where(y == 1, 100.0, 1.0)
    c = connexity(X, X.mean(axis=0), UP, opening=False, sample_weight=w)
    assert c.n_significant == 2
    assert c.sizes.dtype == np.float64
    assert c.sizes[c.labels[y == 1][0]] == pytest.approx(500.0)
    # a tiny weight on the disk makes it the non-significant part
    c = connexity(X, X.mean(axis=0), UP, opening=False, sample_weight=np.where(y == 1, 100.0, 0.01))
    assert c.significant[c.labels[y == 0][0]] == np.False_ and c.n_significant == 1


def test_tilted_plane_from_cluster_geometry():
    X2, y = three_rocks()
    rot = Rotation.from_euler("xy", [40, -25], degrees=True)
    X = rot.apply(X2) + np.array([10.0, -3.0, 2.0])
    geom = cluster_geometry(X)
    assert abs(geom.normal[2]) < 0.9  # really tilted
    c = connexity(X, geom.center, geom.normal)
    assert (c.n_components, c.n_significant) == (3, 3)
    split = assign_to_nearest(project_on_plane(X, geom.center, geom.normal), c.labels, c.significant)
    assert adjusted_rand_score(y, split) == 1.0


def test_rotation_and_translation_of_cloud_and_plane_change_nothing():
    X, _ = three_rocks()
    center, normal = X.mean(axis=0), UP
    base = connexity(X, center, normal)
    rot = Rotation.random(random_state=3)
    shift = np.array([100.0, -50.0, 7.0])
    moved = connexity(rot.apply(X) + shift, rot.apply(center) + shift, rot.apply(normal))
    assert moved.n_components == base.n_components == 3
    assert np.array_equal(moved.labels, base.labels)
    assert moved.spacing == pytest.approx(base.spacing, rel=1e-9)


def test_point_order_does_not_matter():
    X, _ = three_rocks()
    base = connexity(X, X.mean(axis=0), UP)
    perm = np.random.default_rng(4).permutation(len(X))
    shuffled = connexity(X[perm], X.mean(axis=0), UP)
    back = np.empty_like(shuffled.labels)
    back[perm] = shuffled.labels
    assert np.array_equal(back, base.labels)


def test_numbering_of_equal_sizes_does_not_depend_on_point_order():
    P = np.concatenate([disk((0, 0), 0.5, np.random.default_rng(5)) + o for o in ([0, 0], [3, 0])])
    X = np.c_[P, np.zeros(len(P))]
    base = connexity(X, X.mean(axis=0), UP)
    assert base.sizes[0] == base.sizes[1]  # the same disk twice
    assert (base.labels[X[:, 0] < 1.5] == 0).all()  # tie: the component with the smallest (x, y)
    perm = np.random.default_rng(6).permutation(len(X))
    back = np.empty_like(base.labels)
    back[perm] = connexity(X[perm], X.mean(axis=0), UP).labels
    assert np.array_equal(back, base.labels)


# --- alpha and spacing ----------------------------------------------------------------------


def test_alpha_is_alpha_factor_times_the_median_nearest_neighbour_spacing():
    X, _ = three_rocks()
    P = project_on_plane(X, X.mean(axis=0), UP)
    d, _ = NearestNeighbors(n_neighbors=2, algorithm="brute").fit(P).kneighbors(P)
    c = connexity(X, X.mean(axis=0), UP, alpha_factor=2.5)
    assert c.spacing == pytest.approx(np.median(d[:, 1]), rel=1e-9)
    assert c.alpha == pytest.approx(2.5 * c.spacing, rel=1e-12)
    assert 0.03 < c.spacing < SPACING


def test_explicit_alpha_is_honoured():
    rng = np.random.default_rng(8)
    X, _ = on_ground([disk(c, 0.4, rng) for c in ([0, 0], [5, 0], [2.5, 4.33])])  # gaps of 4.2 m
    wide = connexity(X, X.mean(axis=0), UP, alpha=2.2)  # 2 alpha = 4.4 m > every gap
    assert wide.alpha == 2.2 and wide.n_components == 1
    narrow = connexity(X, X.mean(axis=0), UP, alpha=2.0)  # 4.0 m < every gap
    assert narrow.alpha == 2.0 and narrow.n_components == 3


def test_duplicates_do_not_make_the_spacing_zero():
    X, _ = three_rocks()
    once = connexity(X, X.mean(axis=0), UP)
    twice = connexity(np.vstack([X, X]), X.mean(axis=0), UP)
    assert twice.spacing == pytest.approx(once.spacing, rel=1e-12) and twice.spacing > 0
    assert twice.n_components == 3
    n = len(X)
    assert np.array_equal(twice.labels[:n], once.labels)
    assert np.array_equal(twice.labels[n:], once.labels)
    assert np.array_equal(twice.sizes, 2 * once.sizes)
    weighted = connexity(np.vstack([X, X]), X.mean(axis=0), UP, sample_weight=np.full(2 * n, 0.5))
    assert np.array_equal(weighted.labels, twice.labels)
    np.testing.assert_allclose(weighted.sizes, once.sizes)


def test_all_duplicates_are_one_component():
    c = connexity(np.tile([1.0, 2.0, 3.0], (20, 1)), [1.0, 2.0, 3.0], UP)
    assert (c.n_components, c.n_significant, c.spacing) == (1, 1, 0.0)
    assert (c.labels == 0).all()


# --- against brute-force references ---------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_kernel_matches_a_dense_brute_force_reference(seed):
    rng = np.random.default_rng(seed)
    parts = [rng.normal(rng.uniform(-3, 3, 2), rng.uniform(0.2, 0.8), (rng.integers(20, 150), 2))
             for _ in range(rng.integers(1, 5))]
    parts.append(np.c_[np.linspace(-3, 3, 40), rng.uniform(-3, 3) + np.zeros(40)])  # a bridge
    X, _ = on_ground(parts, rng)
    if seed % 2:  # exact duplicates (after projection): the multiplicity path
        copies = X[rng.choice(len(X), len(X) // 3)]
        X = np.vstack([X, copies + [0.0, 0.0, 0.5]])
    P = project_on_plane(X, X.mean(axis=0), UP)
    for opening in (True, False):
        c = connexity(X, X.mean(axis=0), UP, opening=opening)
        n, labels = reference(P, c.alpha, opening=opening)
        assert c.n_components == n
        assert same_partition(c.labels, labels)
        ref_sizes = np.bincount(labels[labels >= 0])
        assert np.array_equal(c.sizes, np.sort(ref_sizes[ref_sizes > 0])[::-1])


def test_median_degree_on_a_sample_of_a_large_cluster(monkeypatch):
    import kbs.geometry.connexity as module

    monkeypatch.setattr(module, "_MEDIAN_SAMPLE", 97)
    rng = np.random.default_rng(10)
    xs = np.arange(1.0 + SPACING, 4.0 - SPACING / 2, SPACING)
    X, _ = on_ground([disk((0, 0), 0.8, rng), disk((5, 0), 0.6, rng), np.c_[xs, np.zeros(len(xs))]])
    P = project_on_plane(X, X.mean(axis=0), UP)
    distinct = module._distinct(P)
    sample = distinct.order[module._median_sample(distinct.points)]
    assert len(sample) == 97
    c = connexity(X, X.mean(axis=0), UP)
    n, labels = reference(P, c.alpha, sample=sample)
    assert c.n_components == n == 2 and same_partition(c.labels, labels)
    # the sample depends on the positions only: the same points, whatever their order or pose
    perm = rng.permutation(len(P))
    d2 = module._distinct(P[perm])
    assert set(perm[d2.order[module._median_sample(d2.points)]]) == set(sample)
    rot = Rotation.from_euler("z", 33, degrees=True).as_matrix()[:2, :2]
    d3 = module._distinct(P @ rot.T + 7.0)
    assert set(d3.order[module._median_sample(d3.points)]) == set(sample)


def test_dilation_looks_past_removed_nearest_points():
    # a tight knot of 10 points 13 cm from a disk: eroded (9 + a couple of neighbours within
    # 2 alpha = 20 cm, against ~50 inside the disk), all its nearest points are removed too,
    # yet a kept point of the disk lies within 2 alpha: the dilation must bring it back
    rng = np.random.default_rng(11)
    knot = np.array([1.13, 0.0]) + rng.uniform(-5e-4, 5e-4, (10, 2))
    X, y = on_ground([disk((0, 0), 1.0, rng), knot])
    c = connexity(X, X.mean(axis=0), UP, alpha=0.1)
    n, labels = reference(project_on_plane(X, X.mean(axis=0), UP), 0.1)
    assert c.n_components == n == 1 and same_partition(c.labels, labels)
    assert (c.labels[y == 1] == 0).all()


def test_degree_lower_bounds_are_exact_at_the_edge_of_the_sure_cells():
    import kbs.geometry.connexity as module

    # cells of side r / 5: (0, 0) and (3, 2) cells apart are within r only up to their far corners
    r = 1.0
    for excess in (1e-6, 1e-4):
        U = np.array([[0.0, 0.0], [0.8 * r * (1 + excess), 0.6 * r * (1 + excess)]])
        assert module._degree_lower_bounds(U, np.ones(2), r).tolist() == [0.0, 0.0]
    U = np.array([[0.0, 0.0], [0.79 * r, 0.59 * r]])
    assert module._degree_lower_bounds(U, np.ones(2), r).tolist() == [1.0, 1.0]
    assert module._degree_lower_bounds(U, np.array([3, 2]), r).tolist() == [4.0, 4.0]


@settings(max_examples=100, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 80), st.just(2)),
              elements=st.floats(0, 5).map(lambda v: round(v, 2))),
       st.floats(0.05, 2.0))
def test_degree_lower_bounds_never_exceed_the_degree(P, r):
    import kbs.geometry.connexity as module

    U = np.unique(P, axis=0)
    degree = (cdist(U, U) <= r).sum(axis=1) - 1
    assert (module._degree_lower_bounds(U, np.ones(len(U), dtype=np.int64), r) <= degree).all()


@pytest.mark.parametrize("seed", range(8))
def test_graph_components_match_dense_components(seed):
    rng = np.random.default_rng(seed)
    P = rng.uniform(0, rng.uniform(1, 20), (rng.integers(1, 300), 2))
    if seed % 2:
        P = np.round(P)  # distance ties and duplicates
    r = float(rng.uniform(0.3, 3.0))
    n, comp = graph_components(P, r)
    n_ref, ref = connected_components((cdist(P, P) <= r).astype(np.int8), directed=False)
    assert n == n_ref and adjusted_rand_score(ref, comp) == 1.0


@pytest.mark.parametrize("angle", np.linspace(0.0, np.pi, 23))
def test_graph_components_link_exactly_up_to_r_in_every_direction(angle):
    r = 0.7
    u = np.array([np.cos(angle), np.sin(angle)])
    for start in np.random.default_rng(int(angle * 100)).uniform(-5, 5, (20, 2)):
        assert graph_components(np.stack([start, start + u * r * (1 - 1e-9)]), r)[0] == 1
        assert graph_components(np.stack([start, start + u * r * (1 + 1e-9)]), r)[0] == 2


def test_graph_components_do_not_link_across_a_cell_diagonal_beyond_r():
    # the cells are r / (2 sqrt 2) wide: two points a hair over r apart along the diagonal sit in
    # cells two apart, never in 8-adjacent ones (which are linked without measuring)
    r = 1.0
    for excess in (1e-6, 1e-4, 1e-2):
        d = r / np.sqrt(2.0) * (1.0 + excess)
        assert graph_components(np.array([[0.0, 0.0], [d, d]]), r)[0] == 2
        assert graph_components(np.array([[0.0, 0.0], [d, d]]) / (1.0 + 2 * excess), r)[0] == 1


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 40), st.just(2)), elements=st.floats(0, 10)),
       st.floats(0.05, 5.0))
def test_graph_components_property_against_dense_components(P, r):
    n, comp = graph_components(P, r)
    n_ref, ref = connected_components((cdist(P, P) <= r).astype(np.int8), directed=False)
    assert n == n_ref and adjusted_rand_score(ref, comp) == 1.0


def test_large_neighbourhoods_are_walked_in_pieces_with_the_same_result(monkeypatch):
    import kbs.geometry.connexity as module

    X, _ = three_rocks()
    base = connexity(X, X.mean(axis=0), UP, alpha=0.3)
    monkeypatch.setattr(module, "_PAIR_BUDGET", 5000)
    pieces = connexity(X, X.mean(axis=0), UP, alpha=0.3)
    assert np.array_equal(pieces.labels, base.labels)
    P = project_on_plane(X, X.mean(axis=0), UP)
    tree = cKDTree(P)
    plan = module._pair_pieces(P, tree, 0.3)
    assert plan is not None and len(plan) > 10
    pieces_of_pairs = list(module._pairs(P, tree, 0.3, plan))
    assert len(pieces_of_pairs) > 10
    pairs = np.concatenate(pieces_of_pairs)
    ref = cKDTree(P).query_pairs(0.3, output_type="ndarray")
    codes = np.sort(pairs[:, 0] * len(P) + pairs[:, 1])
    assert (pairs[:, 0] < pairs[:, 1]).all()
    assert np.array_equal(codes, np.sort(ref.min(axis=1) * len(P) + ref.max(axis=1)))


# --- small clusters and errors --------------------------------------------------------------


def test_fewer_than_three_points_are_one_component():
    one = connexity([[0.0, 0.0, 0.0]], [0, 0, 0], UP)
    assert (one.n_components, one.n_significant, one.labels.tolist()) == (1, 0, [0])
    two = connexity([[0.0, 0.0, 0.0], [9.0, 0.0, 0.0]], [0, 0, 0], UP, min_points=1, alpha=0.1)
    assert (two.n_components, two.n_significant, two.labels.tolist()) == (1, 1, [0, 0])


def test_empty_cluster_is_a_fit_error():
    with pytest.raises(FitError, match="connexity of an empty cluster"):
        connexity(np.empty((0, 3)), [0, 0, 0], UP)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_points_are_a_parameter_error(bad):
    X, _ = three_rocks()
    X[7, 1] = bad
    with pytest.raises(ParameterError, match="NaN or infinite"):
        connexity(X, [0, 0, 0], UP)


def test_normal_is_normalised_and_a_zero_normal_refused():
    X, _ = three_rocks()
    c = connexity(X, X.mean(axis=0), [0.0, 0.0, 7.5])
    assert np.array_equal(c.labels, connexity(X, X.mean(axis=0), UP).labels)
    np.testing.assert_allclose(project_on_plane(X, X.mean(axis=0), [0, 0, 7.5]),
                               project_on_plane(X, X.mean(axis=0), UP))
    with pytest.raises(ParameterError, match="non-zero"):
        connexity(X, X.mean(axis=0), [0.0, 0.0, 0.0])


@pytest.mark.parametrize("kwargs", [dict(alpha=0.0), dict(alpha=-1.0), dict(alpha_factor=0.0),
                                    dict(erosion_fraction=1.5), dict(min_fraction=-0.1),
                                    dict(opening="yes"), dict(sample_weight=np.ones(3))])
def test_bad_parameters_are_parameter_errors(kwargs):
    X, _ = three_rocks()
    with pytest.raises(ParameterError):
        connexity(X, X.mean(axis=0), UP, **kwargs)


def test_projection_is_an_isometry_of_the_plane():
    rng = np.random.default_rng(7)
    normal = rng.normal(size=3)
    n = normal / np.linalg.norm(normal)
    X = rng.normal(size=(50, 3))
    Y = X - np.outer(X @ n, n)  # orthogonal projections in 3D
    P = project_on_plane(X, [1.0, 2.0, 3.0], normal)
    np.testing.assert_allclose(cdist(P, P), cdist(Y, Y), atol=1e-12)


def test_assign_to_nearest_without_a_significant_component_is_a_fit_error():
    with pytest.raises(FitError, match="no significant component"):
        assign_to_nearest(np.zeros((3, 2)), np.array([0, -1, 0]), np.array([False]))


# --- property -------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 60), st.just(3)),
              elements=st.floats(-10, 10, allow_nan=False).map(lambda v: round(v, 1))),
       st.booleans())
def test_assign_to_nearest_gives_every_point_a_significant_label(X, opening):
    c = connexity(X, X.mean(axis=0), UP, opening=opening, min_points=1, min_fraction=0.0)
    assert c.n_significant >= 1
    split = assign_to_nearest(project_on_plane(X, X.mean(axis=0), UP), c.labels, c.significant)
    assert split.shape == (len(X),)
    assert ((split >= 0) & (split < c.n_significant)).all()
    assert c.significant[split].all()
    inside = c.labels >= 0
    assert np.array_equal(split[inside], c.labels[inside])  # every component significant here


# --- the alpha-shape method: alpha-complex, alpha-shape, opening by a disc -------------------


def two_discs_and_bridge(width: float, radius: float = 1.0, gap: float = 1.5):
    """Exact shapes: two discs of ``radius`` whose rims are ``gap`` apart along x, joined by a
    rectangular bridge of ``width`` (it reaches 0.1 into each disc)."""
    import shapely

    a = shapely.Point(0.0, 0.0).buffer(radius, quad_segs=64)
    b = shapely.Point(2 * radius + gap, 0.0).buffer(radius, quad_segs=64)
    bridge = shapely.box(radius - 0.1, -width / 2, radius + gap + 0.1, width / 2)
    return shapely.union_all([a, b, bridge])


@pytest.mark.parametrize("ratio", [0.5, 0.9, 0.98])
def test_the_opening_removes_a_bridge_narrower_than_twice_its_radius(ratio):
    # erosion by a disc of radius rho keeps the centres of the discs that fit inside the shape:
    # none fits in a bridge of width w < 2 rho, so the bridge disappears and the dilation, which
    # only grows what is left, cannot bring it back
    from kbs.geometry.connexity import alpha_opening

    rho = 0.2
    parts = alpha_opening(two_discs_and_bridge(ratio * 2 * rho), rho)
    assert len(parts) == 2
    assert sorted(round(p.centroid.x, 1) for p in parts) == [0.0, 3.5]
    assert all(p.area == pytest.approx(np.pi, rel=0.02) for p in parts)  # the discs are kept whole


@pytest.mark.parametrize("ratio", [1.02, 1.1, 2.0])
def test_the_opening_keeps_a_bridge_wider_than_twice_its_radius(ratio):
    from kbs.geometry.connexity import alpha_opening

    rho = 0.2
    shape = two_discs_and_bridge(ratio * 2 * rho)
    parts = alpha_opening(shape, rho)
    assert len(parts) == 1
    # the bridge comes back whole: only the concave and convex corners where it meets the discs change
    assert parts[0].area == pytest.approx(shape.area, rel=0.01)


def test_opening_with_a_zero_radius_is_the_shape_and_an_empty_shape_has_no_component():
    import shapely

    from kbs.geometry.connexity import alpha_opening

    shape = two_discs_and_bridge(0.01)
    assert [p.equals(shape) for p in alpha_opening(shape, 0.0)] == [True]
    assert alpha_opening(shapely.Polygon(), 0.3) == []
    assert alpha_opening(shapely.Point(0, 0).buffer(0.25), 0.3) == []  # smaller than the disc


def test_alpha_complex_against_circumradii_computed_from_the_circumcentres():
    from scipy.spatial import Delaunay

    from kbs.geometry.connexity import alpha_complex, alpha_shape

    rng = np.random.default_rng(12)
    P = rng.uniform(0, 4, (400, 2))
    tri = Delaunay(P).simplices
    for alpha in (0.05, 0.15, 0.4, 1.0):
        T = alpha_complex(P, alpha)
        # reference: the circumcentre solves |c - a|^2 = |c - b|^2 = |c - d|^2
        ref = []
        for t in tri:
            a, b, d = P[t]
            M = 2 * np.array([b - a, d - a])
            c = np.linalg.solve(M, [b @ b - a @ a, d @ d - a @ a])
            if np.linalg.norm(c - a) <= alpha:
                ref.append(tuple(sorted(t)))
        assert sorted(tuple(sorted(t)) for t in T) == sorted(ref)
        # the alpha-shape is their union: its area is the sum of theirs (they never overlap)
        A = P[T]
        u, v = A[:, 1] - A[:, 0], A[:, 2] - A[:, 0]
        area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum()
        assert alpha_shape(P, alpha).area == pytest.approx(area, rel=1e-9, abs=1e-12)


def test_alpha_complex_of_collinear_or_too_few_points_is_empty():
    from kbs.geometry.connexity import alpha_complex, alpha_shape

    line = np.c_[np.linspace(0, 1, 20), np.zeros(20)]
    assert alpha_complex(line, 1.0).shape == (0, 3) and alpha_shape(line, 1.0).is_empty
    assert alpha_complex(line[:2], 1.0).shape == (0, 3)


def sampled_discs_and_bridge(rows: int, rng=None) -> tuple[np.ndarray, np.ndarray]:
    """Two sampled disks (radius 1 and 0.9 m, 5 cm grid, 1 cm jitter) 3 m apart, joined by a
    sampled bridge of ``rows`` rows 5 cm apart (its outline is (rows - 1) x 5 cm wide)."""
    rng = np.random.default_rng(9) if rng is None else rng
    xs = np.arange(1.0 + SPACING, 4.1 - SPACING / 2, SPACING)
    ys = (np.arange(rows) - (rows - 1) / 2) * SPACING
    bridge = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    bridge = bridge + rng.uniform(-0.005, 0.005, bridge.shape)
    return on_ground([disk((0, 0), 1.0, rng), disk((5, 0), 0.9, rng), bridge], rng)


@pytest.mark.parametrize(("rows", "parts"), [(1, 2), (3, 2), (5, 2), (9, 1), (13, 1)])
def test_alpha_opening_of_sampled_discs_cuts_a_bridge_narrower_than_twice_the_radius(rows, parts):
    # alpha = 0.1 m (2 spacings: the sampled bridge is filled with triangles), rho = 0.15 m: the
    # bridge is cut when (rows - 1) x 5 cm < 2 rho = 0.3 m, that is up to 6 rows
    X, y = sampled_discs_and_bridge(rows)
    c = connexity(X, X.mean(axis=0), UP, method="alpha_opening", alpha=0.1, opening_radius=0.15)
    assert (c.method, c.alpha, c.opening_radius) == ("alpha_opening", 0.1, 0.15)
    assert c.n_significant == c.n_components == parts
    if parts == 2:
        # the disks are the components, with their outline points (but the odd point sticking out
        # of it, whose corner the disc rounds off); the bridge's middle is in none, and goes to
        # the nearer disk in the split
        on_disk = c.labels[y < 2]
        assert ((on_disk == y[y < 2]) | (on_disk == -1)).all() and (on_disk == -1).sum() <= 3
        middle = (y == 2) & (np.abs(X[:, 0] - 2.5) < 1.0)
        assert (c.labels[middle] == -1).all()
        split = assign_to_nearest(project_on_plane(X, X.mean(axis=0), UP), c.labels, c.significant)
        far = (y == 2) & (np.abs(X[:, 0] - 2.5) > 0.1)
        assert np.array_equal(split[far], (X[far, 0] > 2.5).astype(int))
    else:
        assert (c.labels == 0).all()
    # without the opening, the alpha-shape holds the bridge (unless one row wide: no triangle)
    raw = connexity(X, X.mean(axis=0), UP, method="alpha_opening", alpha=0.1, opening=False)
    assert raw.opening_radius == 0.0 and raw.n_components == (2 if rows == 1 else 1)


def test_alpha_opening_with_the_defaults_separates_what_the_graph_opening_keeps_joined():
    # the graph opening cuts bridges up to 2 sampling steps wide (see above); the disc of radius
    # alpha = 3 spacings also cuts a bridge 5 rows (20 cm) wide, and keeps 9 rows (40 cm)
    X, y = sampled_discs_and_bridge(5)
    assert connexity(X, X.mean(axis=0), UP).n_significant == 1
    c = connexity(X, X.mean(axis=0), UP, method="alpha_opening")
    assert c.n_significant == 2 and c.opening_radius == pytest.approx(c.alpha) and 0.1 < c.alpha < 0.15
    assert np.array_equal(c.labels[y < 2], y[y < 2])
    X, y = sampled_discs_and_bridge(9)
    assert connexity(X, X.mean(axis=0), UP, method="alpha_opening").n_significant == 1
    assert connexity(X, X.mean(axis=0), UP, method="alpha_opening", opening_factor=2.0).n_significant == 2


def test_alpha_opening_three_rocks_and_the_invariances():
    X, y = three_rocks()
    c = connexity(X, X.mean(axis=0), UP, method="alpha_opening")
    assert (c.n_components, c.n_significant) == (3, 3)
    assert np.array_equal(c.labels, y)  # every point, outline included, in its rock
    # point order, rigid motion, scale (alpha and the radius follow the spacing), duplicates
    perm = np.random.default_rng(4).permutation(len(X))
    back = np.empty_like(c.labels)
    back[perm] = connexity(X[perm], X.mean(axis=0), UP, method="alpha_opening").labels
    assert np.array_equal(back, c.labels)
    rot, shift = Rotation.random(random_state=3), np.array([100.0, -50.0, 7.0])
    moved = connexity(rot.apply(X) + shift, rot.apply(X.mean(axis=0)) + shift, rot.apply(UP), method="alpha_opening")
    assert np.array_equal(moved.labels, c.labels)
    scaled = connexity(X * 100.0, X.mean(axis=0) * 100.0, UP, method="alpha_opening")
    assert np.array_equal(scaled.labels, c.labels) and scaled.opening_radius == pytest.approx(100 * c.opening_radius)
    twice = connexity(np.vstack([X, X]), X.mean(axis=0), UP, method="alpha_opening")
    assert np.array_equal(twice.labels, np.concatenate([c.labels, c.labels]))
    assert np.array_equal(twice.sizes, 2 * c.sizes)


def test_alpha_opening_of_a_speck_and_of_a_line():
    speck = np.array([[3.0, 0.0], [3.05, 0.0], [3.0, 0.05], [2.95, 0.0], [3.0, -0.05]])
    X, y = on_ground([disk((0, 0)), speck])
    c = connexity(X, X.mean(axis=0), UP, method="alpha_opening")
    assert (c.n_components, c.n_significant) == (1, 1) and (c.labels[y == 1] == -1).all()
    # a cluster with no area at all (collinear once projected) has no component
    line = np.c_[np.linspace(0, 5, 50), np.zeros(50), np.linspace(0, 1, 50)]
    c = connexity(line, line.mean(axis=0), [0.0, 1.0, 0.0], method="alpha_opening")
    assert (c.n_components, c.n_significant) == (0, 0) and (c.labels == -1).all()
    # fewer than three points, or all on one position: one component, as with the graph
    assert connexity(line[:2], line[0], UP, method="alpha_opening", min_points=1).n_significant == 1
    assert connexity(np.tile([1.0, 2.0, 3.0], (20, 1)), [1.0, 2.0, 3.0], UP, method="alpha_opening").n_significant == 1


def test_alpha_opening_against_a_raster_opening():
    # independent reference: the opening of a fine raster of the alpha-shape by a digital disc
    # (scipy.ndimage), on random blobs, bridges and specks; components and area agree
    from scipy import ndimage

    from kbs.geometry.connexity import alpha_opening, alpha_shape

    rng = np.random.default_rng(13)
    for seed in range(3):
        parts = [rng.normal(rng.uniform(-2, 2, 2), rng.uniform(0.3, 0.7), (400, 2)) for _ in range(3)]
        parts.append(np.c_[np.linspace(-2, 2, 80), rng.uniform(-2, 2) + rng.normal(0, 0.05, 80)])
        P = np.unique(np.concatenate(parts), axis=0)
        shape = alpha_shape(P, 0.25)
        rho = 0.12
        opened = alpha_opening(shape, rho)
        h = 0.01
        x0, y0, x1, y1 = shape.bounds
        gx, gy = np.meshgrid(np.arange(x0 - 0.05, x1 + 0.05, h), np.arange(y0 - 0.05, y1 + 0.05, h))
        import shapely

        inside = shapely.contains_xy(shape, gx, gy)
        r = int(round(rho / h))
        disc = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= r
        ref = ndimage.binary_dilation(ndimage.binary_erosion(inside, disc), disc)
        n_ref = ndimage.label(ref, structure=np.ones((3, 3)))[1]
        big = [p for p in opened if p.area > 4 * h * h * 100]  # raster specks aside
        assert len(opened) == n_ref or len(big) == n_ref, seed
        assert sum(p.area for p in opened) == pytest.approx(ref.sum() * h * h, rel=0.05), seed


@pytest.mark.parametrize("kwargs", [dict(method="alpha"), dict(method="alpha_opening", opening_radius=-0.1),
                                    dict(method="alpha_opening", opening_factor=-1.0),
                                    dict(method="alpha_opening", opening_factor=float("nan"))])
def test_bad_alpha_opening_parameters_are_parameter_errors(kwargs):
    X, _ = three_rocks()
    with pytest.raises(ParameterError, match="method|opening_radius|opening_factor"):
        connexity(X, X.mean(axis=0), UP, **kwargs)


def test_the_compiled_measure_builds_no_k_d_tree_and_answers_as_the_trees_do(monkeypatch):
    """With the compiled kernels, the graph measure answers from its grids: no k-d tree is built
    (a vehicle frame's 100 measures built 149 and asked none); with them off, the trees answer,
    and the components are the same. A cloud with repeated positions too (the spacing of its
    distinct positions from the compiled grid as well)."""
    import kbs.geometry.connexity as module
    from kbs.inference import _flags

    rng = np.random.default_rng(12)
    X, _ = on_ground([disk((0, 0), 1.0, rng), disk((3, 0), 0.7, rng)])
    Xd = np.r_[X, X[:50]]  # 50 positions twice
    built = []
    real = module._kdtree
    monkeypatch.setattr(module, "_kdtree", lambda *a, **k: built.append(len(a[0])) or real(*a, **k))
    for cloud in (X, Xd):
        built.clear()
        monkeypatch.setattr(_flags, "JIT", True)
        fast = connexity(cloud, cloud.mean(axis=0), UP)
        trees_fast = len(built)
        monkeypatch.setattr(_flags, "JIT", False)
        slow = connexity(cloud, cloud.mean(axis=0), UP)
        assert fast.n_components == slow.n_components == 2 and fast.n_significant == slow.n_significant == 2
        np.testing.assert_array_equal(fast.labels, slow.labels)
        assert fast.spacing == slow.spacing
        assert len(built) > trees_fast  # the reference path asks its trees
        # the duplicates' spacing too comes from the compiled grid (the tree's distances)
        assert trees_fast == 0
