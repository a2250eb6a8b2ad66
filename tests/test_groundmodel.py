"""The local ground surface (post.ground_model) and what uses it: the height_above_local_ground
predicate, post.relabel and post.ground_contact — as a library, in rule files, and through the
real command on the SemanticKITTI scan."""
from __future__ import annotations

import json
from pathlib import Path
import re
import textwrap

import numpy as np
import pytest
from plyfile import PlyData

from kbs.io import write_ply
from kbs.knowledge import Interpreter, PredicateRegistry, RuleFileError, load_rule_base
from kbs.geometry.groundmodel import LocalGround
from kbs.geometry.pca import plane_basis
from kbs.knowledge.rulebase import parse_rule_base
from scenes import (airborne_large_building, airborne_pit, airborne_step_and_building, airborne_without, ground_and_parked_cars,
                    ground_and_rocks, outdoor_one_release)
from test_cli import kbs

# --- the surface ---------------------------------------------------------------------------------


def _tilted(rng, n=4000, size=10.0):
    """A gently tilted, gently curved terrain z = 0.05 x + 0.01 y^2 with 1 cm noise."""
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    z = 0.05 * xy[:, 0] + 0.01 * xy[:, 1] ** 2 + rng.normal(0, 0.01, n)
    return np.column_stack([xy, z])


def test_plane_basis_is_orthonormal_and_spans_the_plane():
    for n in ([0, 0, 1], [1, 0, 0], [0.3, -0.4, 0.866]):
        n = np.asarray(n, float) / np.linalg.norm(n)
        B = plane_basis(n)
        assert np.allclose(B @ B.T, np.eye(2)) and np.allclose(B @ n, 0)


def test_local_height_follows_a_curved_terrain_where_one_plane_cannot():
    rng = np.random.default_rng(0)
    G = _tilted(rng)
    model = LocalGround.build(G, np.arange(len(G)), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=1.0)
    probe = _tilted(rng, 200, 8.0)
    probe[:, 2] += 0.3  # 30 cm above the terrain
    h = model.height(probe)
    assert np.all(np.abs(h - 0.3) < 0.05), np.abs(h - 0.3).max()
    # the plane through the terrain is off by up to ~0.2 m at the edges: the local model is not
    assert np.abs(probe[:, 2] - 0.3).max() > 0.15


def test_unknown_beyond_the_radius_and_median_of_the_neighbours_found():
    G = np.array([[0.0, 0, 0.0], [0.1, 0, 0.2], [0.2, 0, 0.4], [5.0, 0, 1.0]])
    model = LocalGround.build(G, np.array([0, 1, 2, 3]), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=0.5)
    ground, nearest = model.query(np.array([[0.1, 0, 1.0], [2.5, 0, 0.0], [5.0, 0.1, 3.0]]))
    assert ground[0] == pytest.approx(0.2)  # median of the three found within 0.5, not of 8
    assert np.isnan(ground[1]) and nearest[1] == -1  # nothing within the radius
    assert ground[2] == pytest.approx(1.0) and nearest[2] == 3
    # brute force on random data: the median of the found neighbours' heights
    rng = np.random.default_rng(1)
    G = rng.uniform(0, 4, (300, 3))
    model = LocalGround.build(G, np.arange(300), np.array([0, 0, 1.0]), np.zeros(3), neighbours=5, radius=0.3)
    P = rng.uniform(-0.5, 4.5, (200, 3))
    ground, _ = model.query(P)
    for p, g in zip(P, ground):
        d = np.hypot(*(G[:, :2] - p[:2]).T)
        near = np.argsort(d, kind="stable")[:5]
        near = near[d[near] <= 0.3]
        assert (np.isnan(g) and near.size == 0) or g == pytest.approx(np.median(G[near, 2]))


@pytest.mark.parametrize("jit", [True, False])
def test_a_radius_growing_with_range_reaches_far_sparse_ground(monkeypatch, jit):
    """per_range: the radius of a query is radius + per_range x its distance to the sensor. Far
    ground a spinning lidar leaves metres apart gets a surface that a fixed radius leaves it
    without; near the sensor the radius hardly grows. Checked against brute force."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", jit)
    G = np.array([[40.0, 0, -1.5], [40.0, 0.5, -1.5], [3.0, 0, -1.7]])  # two far points, one near
    P = np.array([[45.0, 0, -1.4], [7.5, 0, -1.6]])  # 5 m from the far pair at 45 m; 4.5 m from the near one at 7.5 m
    fixed = LocalGround.build(G, np.arange(3), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=3.0)
    grows = LocalGround.build(G, np.arange(3), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=3.0,
                              per_range=0.1, sensor=np.zeros(3))  # about 7.5 m at 45 m, 3.77 m at 7.5 m
    assert np.isnan(fixed.height(P)).all()
    h = grows.height(P)
    assert h[0] == pytest.approx(0.1) and np.isnan(h[1])
    np.testing.assert_allclose(grows.radii(P), 3.0 + 0.1 * np.linalg.norm(P, axis=1))  # 3-d distances
    assert fixed.radii(P) is None and grows.height_bounds(P) is None  # the bounds assume one radius
    # brute force on random data, with and without a cluster left out
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-30, 30, (900, 2)), rng.normal(0, 0.1, 900)])
    owners = (X[:, 0] > 0).astype(np.int64)
    sensor = np.array([0.0, 0.0, 1.7])
    model = LocalGround.build(X, np.arange(900), np.array([0, 0, 1.0]), np.zeros(3), neighbours=6, radius=0.5,
                              owners=owners, owner_ids=("c0", "c1"), per_range=0.05, sensor=sensor)
    Q = np.column_stack([rng.uniform(-35, 35, (300, 2)), rng.normal(0, 0.1, 300)])
    for exclude, own in ((None, -1), ("c1", 1)):
        ground, _ = model.query(Q, exclude)
        for p, g in zip(Q, ground):
            r = 0.5 + 0.05 * np.linalg.norm(p - sensor)
            d = np.hypot(*(X[:, :2] - p[:2]).T)
            near = [j for j in np.argsort(d, kind="stable") if owners[j] != own][:6]
            near = [j for j in near if d[j] <= r]
            assert (np.isnan(g) and not near) or g == pytest.approx(np.median(X[near, 2]))
    with pytest.raises(ValueError, match="needs the sensor"):
        LocalGround.build(G, np.arange(3), np.array([0, 0, 1.0]), np.zeros(3), per_range=0.1)


def test_a_cluster_can_be_compared_with_the_ground_around_it():
    """exclude: the cluster's own points leave the surface; a raised flat roof among ground patches
    is then high above the ground around it, and a ground patch is not."""
    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(0, 20, (3000, 2)), rng.normal(0, 0.02, 3000)])
    ground = ground[~((np.abs(ground[:, 0] - 10) < 3) & (np.abs(ground[:, 1] - 10) < 3))]  # the house
    roof = np.column_stack([rng.uniform(7, 13, (400, 2)), 5 + rng.normal(0, 0.02, 400)])
    X = np.vstack([ground, roof])
    owners = np.r_[np.zeros(len(ground), int), np.ones(len(roof), int)]
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=5.0,
                              owners=owners, owner_ids=("c0", "c1"))
    assert np.nanmedian(model.height(roof)) == pytest.approx(0, abs=0.05)  # the roof is its own surface
    h = model.height(roof, exclude="c1")
    known = ~np.isnan(h)
    assert known.any() and not known.all()  # mid-roof, the 64 nearest surface points are all its own
    assert np.all(np.abs(h[known] - 5) < 0.1)
    g = model.height(ground[:200], exclude="c0")  # the ground without the ground: only the roof is left
    assert np.all(np.isnan(g) | (g < -4.5))
    assert np.allclose(model.height(ground[:50], exclude="nobody"), model.height(ground[:50]))


def test_max_points_bounds_the_points_a_cluster_asks_the_surface_for(monkeypatch):
    """height_above_local_ground's max_points: a large roof asks the surface for that many of its
    points, evenly spread, and measures about the same height as with all of them; 0 asks for all."""
    from kbs.knowledge import Cluster, Scene
    from kbs.geometry.groundmodel import LocalGround as LG
    from kbs.knowledge.predicates import Ground, height_above_local_ground

    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(0, 30, (6000, 2)), rng.normal(0, 0.02, 6000)])
    ground = ground[~((np.abs(ground[:, 0] - 15) < 4) & (np.abs(ground[:, 1] - 15) < 4))]
    roof = np.column_stack([rng.uniform(11, 19, (5000, 2)), 3 + rng.normal(0, 0.02, 5000)])
    X = np.vstack([ground, roof])
    owners = np.r_[np.zeros(len(ground), int), np.ones(len(roof), int)]
    model = LG.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=5.0,
                     owners=owners, owner_ids=("c0", "c1"))
    scene = Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=model)
    asked = []
    real = LG.height
    monkeypatch.setattr(LG, "height", lambda self, P, exclude=None: asked.append(len(P)) or real(self, P, exclude))
    cl = Cluster("c1", roof, np.ones(len(roof)))
    full = height_above_local_ground.func(cl, scene, stat="median", exclude_self=True)
    some = height_above_local_ground.func(cl, scene, stat="median", exclude_self=True, max_points=500)
    assert asked == [5000, 500]
    assert full == pytest.approx(3.0, abs=0.1) and some == pytest.approx(full, abs=0.05)
    assert height_above_local_ground.func(cl, scene, stat="median", exclude_self=True, max_points=0) == full
    _parse(post=POST_OK)  # the base is valid; a negative bound is not
    with pytest.raises(RuleFileError, match="max_points"):
        parse_rule_base(BASE.format(rule_if="not planar", label_if="planar", post=POST_OK).replace(
            "max: 0.2}", "max: 0.2, params: {max_points: -1}}"), "t.yaml", PredicateRegistry.default(entry_points_too=False))


# --- rule files ------------------------------------------------------------------------------------

BASE = textwrap.dedent("""\
    kbs_rules: 1
    name: t
    units: m
    strategy: divisive
    scene:
      ground: {{normal: [0, 0, 1]}}
    checks:
      planar: {{predicate: thickness, max: 0.05}}
      low: {{predicate: height_above_local_ground, max: 0.2}}
    rules:
      - name: r
        if: {rule_if}
        then: split
    labels:
      - name: ground
        if: {label_if}
      - name: obstacle
    post:
    {post}
    """)


def _parse(rule_if="not planar", label_if="planar", post="  merge_coplanar: {label: ground}"):
    return parse_rule_base(BASE.format(rule_if=rule_if, label_if=label_if, post=post), "t.yaml",
                           PredicateRegistry.default(entry_points_too=False))


POST_OK = """\
  ground_model: {label: ground}
  relabel:
    - {name: low_obstacles, from: obstacle, to: ground, if: low}
  ground_contact: {tolerance: 0.05}"""


@pytest.mark.parametrize("exclude", [None, "c1", "c9"])
def test_compiled_medians_equal_the_numpy_reference(monkeypatch, exclude):
    from kbs.inference import _flags

    rng = np.random.default_rng(11)
    X = np.column_stack([rng.uniform(0, 40, 6000), rng.uniform(0, 40, 6000), rng.normal(0, 0.2, 6000)])
    owners = (X[:, 0] // 10).astype(int)  # four strips: c0 .. c3
    model = LocalGround.build(X, np.arange(0, 6000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=7,
                              radius=2.5, owners=owners[::2], owner_ids=("c0", "c1", "c2", "c3"))
    P = np.vstack([X[1::2], [[100.0, 100.0, 0.0], [20.0, 20.0, 5.0]]])
    g1, n1 = model.query(P, exclude)
    monkeypatch.setattr(_flags, "JIT", False)
    g0, n0 = model.query(P, exclude)
    assert np.array_equal(np.isnan(g1), np.isnan(g0)) and np.isnan(g1[-2])
    np.testing.assert_array_equal(g1[~np.isnan(g1)], g0[~np.isnan(g0)])
    np.testing.assert_array_equal(n1, n0)


@pytest.mark.parametrize("jit", [True, False])
@pytest.mark.parametrize("exclude", [None, "c2"])
def test_queries_in_chunks_give_the_answers_of_one_query(monkeypatch, jit, exclude):
    """Queries go in spatial order and in chunks (bounded temporaries); neither may change an
    answer: a budget of 64 neighbours per call (chunks of 8 or 1 points) against one call."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", jit)
    rng = np.random.default_rng(12)
    X = np.column_stack([rng.uniform(0, 40, 9000), rng.uniform(0, 40, 9000), rng.normal(0, 0.2, 9000)])
    owners = (X[:, 0] // 10).astype(int)
    model = LocalGround.build(X, np.arange(0, 9000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=8,
                              radius=2.5, owners=owners[::2], owner_ids=("c0", "c1", "c2", "c3"))
    P = X[1::2]  # 4,500 queries: enough for the spatial order
    assert model._spatial_order(P[:, :2]) is not None
    g1, n1 = model.query(P, exclude)
    monkeypatch.setattr(LocalGround, "QUERY_BUDGET", 64)
    g0, n0 = model.query(P, exclude)
    np.testing.assert_array_equal(g1, g0)
    np.testing.assert_array_equal(n1, n0)
    assert np.isfinite(g1).mean() > (0.99 if exclude is None else 0.8)  # c2's interior: its own points only
    # two query threads (kbs run -j 2 gives the surface its jobs): the same answers
    threaded = LocalGround.build(X, np.arange(0, 9000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=8,
                                 radius=2.5, owners=owners[::2], owner_ids=("c0", "c1", "c2", "c3"), workers=2)
    monkeypatch.setattr(LocalGround, "QUERY_BUDGET", 1 << 20)
    g2, n2 = threaded.query(P, exclude)
    np.testing.assert_array_equal(g1, g2)
    np.testing.assert_array_equal(n1, n2)


def _median_rows(d, idx, heights, owners, own, neighbours, quantile=0.5):
    """Both compiled median kernels on one query; their outputs, bit for bit."""
    from kbs.inference import _compiled as C

    args = (np.ascontiguousarray(d), np.ascontiguousarray(idx, dtype=np.int64), heights,
            np.ascontiguousarray(owners, dtype=np.int64), own, neighbours, quantile)
    (g0, n0), (g1, n1) = C.local_medians(*args), C.local_medians_fast(*args)
    return g0.view(np.int64), g1.view(np.int64), n0, n1


@pytest.mark.parametrize("own", [-1, 0, 1])
def test_median_kernel_without_a_sort_per_row_is_the_old_one_at_ties(own):
    """local_medians_fast (insertion into one buffer) against local_medians (np.sort per row), bit
    for bit: equal heights, +0.0 and -0.0 at the median positions, NaN, duplicate positions (equal
    distances), rows with fewer points than neighbours (the radius reached) and none."""
    rng = np.random.default_rng(21)
    m, q, k = 300, 2000, 48
    heights = rng.choice(np.array([-0.0, 0.0, 0.0, -0.0, 0.1, -0.1, 0.2, 1.5, 0.1]), m)  # signed zeros, repeats
    heights[::37] = np.nan  # never on a surface (its tree refuses them), but the kernels agree there too
    owners = rng.integers(0, 3, m)
    d = np.sort(rng.choice(np.array([0.0, 0.5, 0.5, 1.0, 2.0, 3.0]), (q, k)), axis=1)  # distance ties
    d[rng.random((q, k)) < 0.2] = np.inf
    d.sort(axis=1)  # the missing ones last, as the tree gives them
    idx = np.where(np.isfinite(d), rng.integers(0, m, (q, k)), m)
    for nb in (1, 2, 7, 16):
        g0, g1, n0, n1 = _median_rows(d, idx, heights, owners if own >= 0 else np.zeros(0), own, nb)
        np.testing.assert_array_equal(g0, g1)
        np.testing.assert_array_equal(n0, n1)
    zero_rows = np.isin(np.abs(heights[np.minimum(idx[:, :2], m - 1)]), [0.0]).all(axis=1)
    assert zero_rows.any()  # the signed-zero case was met


@pytest.mark.parametrize("exclude", [None, True])
def test_surface_medians_on_a_semantickitti_piece_are_the_old_kernel_s(shared_data, monkeypatch, exclude):
    """The surface's queries on the real scan's ground (owners: 5 m strips, as clusters), with
    and without a cluster left out, through LocalGround.query: the compiled path (the new kernel)
    gives the numpy reference's answers and the old kernel's, bit for bit."""
    from kbs.inference import _flags

    X = np.load(shared_data / "semantickitti" / "000001.points.npy")[:, :3].astype(np.float64)
    labels = np.load(shared_data / "semantickitti" / "000001.labels.npy").ravel()
    ground = np.flatnonzero(np.isin(labels, [9, 10, 11, 12, 17]))  # road, parking, sidewalk, other-ground, terrain
    owners = np.floor(X[ground, 0] / 5.0).astype(np.int64)
    owners -= owners.min()
    ids = tuple(f"c{i}" for i in range(owners.max() + 1))
    model = LocalGround.build(X, ground, np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16, radius=3.0,
                              owners=owners, owner_ids=ids)
    P = X[::9]
    ex = ids[int(np.bincount(owners).argmax())] if exclude else None  # the strip with most ground
    monkeypatch.setattr(_flags, "JIT", True)
    g1, n1 = model.query(P, ex)
    monkeypatch.setattr(_flags, "JIT", False)
    g0, n0 = model.query(P, ex)
    assert np.isfinite(g1).mean() > 0.5
    np.testing.assert_array_equal(g1, g0)
    np.testing.assert_array_equal(n1, n0)
    Q = (P - model.point) @ model.basis.T
    k = 128 if exclude else 16
    d, i = model.tree.query(Q, k=k, distance_upper_bound=model.radius)
    g0, g1, n0, n1 = _median_rows(d, i, model.heights, owners, ids.index(ex) if ex else -1, 16)
    np.testing.assert_array_equal(g0, g1)
    np.testing.assert_array_equal(n0, n1)


def test_the_surface_builds_its_k_d_tree_only_when_a_query_needs_it(monkeypatch):
    """With the compiled kernels a surface answers from its grids and builds no k-d tree (the
    build was 18 ms a surface of 96k points, several surfaces a frame); a query the grid cannot
    answer alone (duplicated positions tie the distances, or the kernels are off) builds it
    then, and the answers are the same either way."""
    from kbs.inference import _flags

    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(0.0, 60.0, (5000, 2)), rng.normal(0.0, 0.05, 5000)]
    P = np.c_[rng.uniform(5.0, 55.0, (400, 2)), np.zeros(400)]
    owners = (X[:, 0] // 10.0).astype(np.int64)
    ids = tuple(f"c{i}" for i in range(owners.max() + 1))

    def surface():
        return LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=8,
                                 radius=5.0, owners=owners, owner_ids=ids)

    monkeypatch.setattr(_flags, "JIT", True)
    model = surface()
    h1, h2 = model.height(P), model.height(P, "c2")
    s1 = model.height_above_slope(P, 40.0, 10.0, "c2")
    assert model.height_bounds(P) is not None
    assert "tree" not in model.__dict__  # answered from the grids alone
    monkeypatch.setattr(_flags, "JIT", False)
    ref = surface()
    np.testing.assert_array_equal(h1, ref.height(P))
    np.testing.assert_array_equal(h2, ref.height(P, "c2"))
    np.testing.assert_array_equal(s1, ref.height_above_slope(P, 40.0, 10.0, "c2"))
    assert "tree" in ref.__dict__  # the reference path asks the tree
    np.testing.assert_array_equal(ref.tree.data, ref.plane)


def test_post_steps_parse_with_defaults():
    rb = _parse(post=POST_OK)
    assert rb.ground_model.label == "ground" and rb.ground_model.neighbours == 8 and rb.ground_model.radius == 3.0
    assert [(r.name, r.source, r.target) for r in rb.relabel] == [("low_obstacles", "obstacle", "ground")]
    assert rb.contact.tolerance == 0.05 and rb.contact.sources == ("obstacle",)


@pytest.mark.parametrize("kw, expected", [
    (dict(rule_if="low"), "t.yaml:12:9: rule 'r': check 'low' measures against the local ground surface"),
    (dict(label_if="[planar, low]"), "t.yaml:16:9: label 'ground': check 'low' measures against the local ground"),
    (dict(post="  relabel:\n    - {name: x, from: obstacle, to: ground, if: low}"),
     "relabel rule 'x': check 'low' needs the local ground surface, but post.ground_model does not declare it"),
    (dict(post="  ground_contact: {tolerance: 0.1}"), "ground_contact needs post.ground_model"),
    (dict(post="  ground_model: {label: grund}"), "unknown label 'grund' (did you mean 'ground'?)"),
    (dict(post=POST_OK.replace("to: ground", "to: obstacle")), "changes nothing: from and to are both 'obstacle'"),
    (dict(post=POST_OK.replace("tolerance: 0.05", "tolerance: -1")), "post.ground_contact.tolerance"),
    (dict(post=POST_OK.replace("radius", "x").replace("{label: ground}", "{label: ground, radus: 2}")),
     "unknown key 'radus' in post.ground_model (did you mean 'radius'?)"),
    (dict(post="  ground_release: {tolerance: 0.1, to: obstacle}"), "ground_release needs post.ground_model"),
    (dict(post=POST_OK + "\n  ground_release: {tolerance: 0.1, to: obstacel}"),
     "unknown label 'obstacel' (did you mean 'obstacle'?)"),
    (dict(post=POST_OK + "\n  ground_release: {tolerance: 0.1, to: ground}"), "the ground model's own label, changes nothing"),
    (dict(post=POST_OK + "\n  ground_release: {tolerance: 0.1}"), "post.ground_release is missing the required key 'to'"),
    (dict(post=POST_OK.replace("{tolerance: 0.05}", "{tolerance: 0.05, if: [not planr]}")),
     "t.yaml:22:42: unknown check 'planr' (did you mean 'planar'?)"),
])
def test_post_step_problems_are_positioned(kw, expected):
    with pytest.raises(RuleFileError) as err:
        _parse(**kw)
    assert expected in str(err.value), str(err.value)


def test_per_range_settings_parse_and_bad_values_are_positioned():
    """post.ground_model.per_range and post.ground_contact.per_range: 0 when absent; a negative, a
    word or more than 1 is a positioned problem."""
    rb = _parse(post=POST_OK)
    assert rb.ground_model.per_range == 0.0 and rb.contact.per_range == 0.0
    rb = _parse(post=POST_OK.replace("{label: ground}", "{label: ground, per_range: 0.2}")
                .replace("{tolerance: 0.05}", "{tolerance: 0.05, per_range: 0.005}"))
    assert rb.ground_model.per_range == 0.2 and rb.contact.per_range == 0.005
    for post, expected in (
            (POST_OK.replace("{label: ground}", "{label: ground, per_range: -0.1}"),
             "t.yaml:19:44: post.ground_model.per_range: -0.1 is less than the minimum of 0"),
            (POST_OK.replace("{label: ground}", "{label: ground, per_range: far}"),
             "t.yaml:19:44: post.ground_model.per_range must be a number; got 'far'"),
            (POST_OK.replace("{tolerance: 0.05}", "{tolerance: 0.05, per_range: 2}"),
             "t.yaml:22:48: post.ground_contact.per_range: 2 is greater than the maximum of 1")):
        with pytest.raises(RuleFileError) as err:
            _parse(post=post)
        assert expected in str(err.value), str(err.value)


# --- the interpreter -------------------------------------------------------------------------------


def test_ground_contact_moves_only_points_on_the_surface_and_says_so():
    """The rocks stand on flat ground (z = -1.5, 5 mm noise): the lowest points of their clusters
    lie on the ground surface and join it. Against the same rules without ground_contact, exactly
    the points the records count changed, all to the ground, all within the tolerance."""
    X, _ = ground_and_rocks()
    rb = load_rule_base("outdoor")
    lines = rb.text.splitlines()
    start = lines.index(next(line for line in lines if line.startswith("  - ground_contact:")))
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].startswith("      ")), len(lines))
    text = "\n".join(lines[:start] + lines[end:])  # the same rules without post.ground_contact
    rb_off = parse_rule_base(text, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    assert rb_off.contact is None and rb.contact is not None
    seg, seg_off = Interpreter(rb).run(X), Interpreter(rb_off).run(X)
    recs = seg.explanation.records
    moved = sum(r.contact for r in recs.values())
    changed = seg.label != seg_off.label
    assert moved > 0 and changed.sum() == moved
    assert np.all(seg.label[changed] == 0) and np.all(seg_off.label[changed] == 1)
    g = seg.explanation.ground
    surface = LocalGround.build(X, np.flatnonzero(seg_off.label == 0), np.array(g.normal), np.array(g.point),
                                neighbours=rb.ground_model.neighbours, radius=rb.ground_model.radius)
    assert np.all(np.abs(surface.height(X[changed])) <= rb.contact.tolerance)
    assert np.all(np.abs(X[changed, 2] + 1.5) < 0.12)  # the rocks' feet, not their tops (0.6 m)
    donors = [r for r in recs.values() if r.contact]
    assert all(any("within 0.05 m of the local ground surface" in n for n in r.notes) for r in donors)
    # sizes add up: every point is in exactly one output cluster
    for c in seg.clusters:
        assert c["n_points"] == (seg.cluster == c["index"]).sum()
    assert sum(c["n_points"] for c in seg.clusters) == (seg.cluster >= 0).sum() == (seg_off.cluster >= 0).sum()
    # the surface was built from the ground clusters before they received the contact points
    assert seg.explanation.ground.local_model.points == (seg.label == 0).sum() - moved


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_relabel_and_contact_on_semantickitti_through_the_command(shared_data, tmp_path):
    scan = shared_data / "semantickitti" / "000001.points.npy"
    r = kbs("run", "--rules", "outdoor", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "000001.points.json").read_text())
    records = doc["explanation"]["clusters"]
    relabelled = [c for c in records if c["relabel"] and c["relabel"]["rule"] == "low_level"]
    assert relabelled, "the verges and the rough terrain of this scan are relabelled ground"
    raised = [c for c in records if c["relabel"] and c["relabel"]["rule"] == "raised"]
    assert raised and all(c["label"] == "obstacle" for c in raised)  # level patches of hedges and walls standing high
    for c in relabelled:
        checks = {k["check"]: k for k in c["checks"]}
        assert c["label"] == "ground" and checks["low"]["passed"] and checks["level"]["passed"]
        assert checks["low"]["value"] <= 0.25 and c["relabel"]["rule"] == "low_level"
    one = relabelled[0]["id"]
    r = kbs("explain", str(tmp_path / "000001.points.json"), "--cluster", one)
    assert r.returncode == 0, r.stderr
    assert "relabelled ground by low_level [outdoor.yaml:" in r.stdout and "low (height_above_local_ground = " in r.stdout
    assert re.search(r"\n    low +yes +height_above_local_ground = ", r.stdout)
    assert doc["explanation"]["ground"]["local_model"]["relabelled"] == len(relabelled) + len(raised)
    assert sum(c["contact"] for c in records) > 0
    # the measured benefit holds: ground F1 0.948, well above what the rules give without the
    # surface (0.917; benchmarks/bench_rotations.py and docs/PERFORMANCE.md have both)
    v = PlyData.read(str(tmp_path / "000001.points.ply"))["vertex"]
    gt = np.load(shared_data / "semantickitti" / "000001.labels.npy").ravel()
    valid = gt != 0
    truth, pred = np.isin(gt, [9, 10, 11, 12, 17])[valid], (np.asarray(v["scalar_label"]) == 0)[valid]
    f1 = 2 * (truth & pred).sum() / (truth.sum() + pred.sum())
    assert f1 > 0.94, f1


def test_predicates_command_lists_the_local_surface_predicate():
    r = kbs("predicates")
    assert r.returncode == 0, r.stderr
    assert "height_above_local_ground  [length" in r.stdout and "post.relabel only" in r.stdout


@pytest.mark.slow
def test_user_rule_file_with_the_post_steps_runs(tmp_path):
    """A user's rule base with a fixed ground normal and all three post steps, through the command."""
    X, _ = ground_and_rocks()
    path = tmp_path / "s.ply"
    write_ply(path, X)
    rules = tmp_path / "r.yaml"
    rules.write_text(BASE.format(rule_if="not planar", label_if="planar", post=POST_OK))
    r = kbs("rules", "check", str(rules))
    assert r.returncode == 0, r.stderr
    r = kbs("run", "--rules", str(rules), str(path), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "o" / "s.json").read_text())
    model = doc["explanation"]["ground"]["local_model"]
    assert model["label"] == "ground" and model["points"] > 10000 and model["source"] == "r.yaml:19"


def test_no_ground_cluster_leaves_the_surface_empty_and_the_run_whole():
    """A rule base whose ground label no cluster earns: the surface has no point, ground contact
    moves nothing; with a relabel rule, the local-height check falls back to the ground plane and
    the clusters it relabels make the surface for the contact step."""
    X, _ = ground_and_rocks()
    never = "[planar, not planar]"  # 'ground' can never hold
    rb = _parse(label_if=never, post=POST_OK.replace(
        "  relabel:\n    - {name: low_obstacles, from: obstacle, to: ground, if: low}\n", ""))
    assert not rb.relabel and rb.contact is not None
    seg = Interpreter(rb).run(X)
    assert seg.explanation.ground.local_model.points == 0
    assert sum(r.contact for r in seg.explanation.records.values()) == 0 and not (seg.label == 0).any()
    seg = Interpreter(_parse(label_if=never, post=POST_OK)).run(X)
    model = seg.explanation.ground.local_model
    low = [c for r in seg.explanation.records.values() for c in r.checks if c.check == "low"]
    assert model.points == 0 and low and model.relabelled == sum(c.passed for c in low) > 0
    assert model.points_after_relabel > 0


def test_a_worker_that_dies_does_not_lose_the_split(monkeypatch):
    """If the worker pool breaks (a worker killed, out of memory), the split is done in process."""
    from concurrent.futures.process import BrokenProcessPool

    import kbs.knowledge.interpreter as interp

    class Broken:
        def result(self):
            raise BrokenProcessPool("a worker died")

    X, _ = ground_and_rocks()
    job = interp._Job(X[:3000], Interpreter(load_rule_base("outdoor"))._ufp_kwargs("first_max"), Broken())
    res = job.result()
    assert res.n_samples == 3000 and res.chosen_k >= 1


@pytest.mark.slow  # whole real scans / a browser: pytest --runslow (CI) runs it
def test_airborne_rules_tell_roofs_from_the_ground_on_isprs(shared_data, tmp_path):
    """The shipped airborne rule base on ISPRS sample 21 (absolute UTM coordinates), through the
    command: total error against the reference, and the roofs relabelled with their reason."""
    from kbs.io import read_cloud

    scan = shared_data / "isprs" / "samp21-utm.pcd"
    r = kbs("run", "--rules", "airborne", str(scan), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    v = PlyData.read(str(tmp_path / "samp21-utm.ply"))["vertex"]
    pc = read_cloud(scan)
    truth = np.loadtxt(shared_data / "isprs" / "samp21-utm.labels.txt")[pc.index] == 0
    pred = np.asarray(v["scalar_label"]) == 0
    total_error = ((pred & ~truth).sum() + (~pred & truth).sum()) / truth.size
    assert total_error < 0.05, total_error  # measured 3.7 %; CSF 2.2 %
    doc = json.loads((tmp_path / "samp21-utm.json").read_text())
    roofs = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "roofs"]
    assert roofs and all(c["label"] == "object" for c in roofs)
    r = kbs("explain", str(tmp_path / "samp21-utm.json"), "--cluster", roofs[0]["id"])
    assert "relabelled object by roofs [airborne.yaml:" in r.stdout and "height_above_local_ground = " in r.stdout


def test_ground_contact_only_from_the_clusters_its_condition_admits():
    """post.ground_contact.if: a condition no cluster meets moves no point; the shipped outdoor
    rules admit things standing on the ground (not level, or not a sheet) and say which."""
    X, _ = ground_and_rocks()
    never = _parse(post=POST_OK.replace("{tolerance: 0.05}", "{tolerance: 0.05, if: [planar, not planar]}"))
    assert never.contact.condition is not None
    seg = Interpreter(never).run(X)
    assert sum(r.contact for r in seg.explanation.records.values()) == 0
    rb = load_rule_base("outdoor")
    assert str(rb.contact.condition) == "not level or not sheet"
    seg = Interpreter(rb).run(X)
    for r in seg.explanation.records.values():
        if r.contact:
            checks = {c.check: c.passed for c in r.checks}
            assert not checks["level"] or not checks["sheet"]


def test_a_contact_tolerance_growing_with_range_takes_more_of_far_obstacles():
    """post.ground_contact.per_range: the rocks seen from 30 m away take 0.05 m + 0.002 x range
    (about 0.12 m) of contact: more of their feet join the ground than with 0.05 m, each within its
    own tolerance of the ground (flat, at z = -1.5), and the records say so; nothing else changed."""
    X, _ = ground_and_rocks()
    sensor = np.array([0.0, -30.0, 0.0])
    rb = load_rule_base("outdoor")
    contact = "      tolerance: 0.05            # m\n"
    assert contact in rb.text
    on = parse_rule_base(rb.text.replace(contact, contact + "      per_range: 0.002\n"), "outdoor.yaml",
                         PredicateRegistry.default(entry_points_too=False))
    assert on.contact.per_range == 0.002
    seg_off, seg = Interpreter(rb, sensor=sensor).run(X), Interpreter(on, sensor=sensor).run(X)
    off_moved = sum(r.contact for r in seg_off.explanation.records.values())
    moved = sum(r.contact for r in seg.explanation.records.values())
    changed = seg.label != seg_off.label
    assert moved > off_moved + 100 and changed.sum() == moved - off_moved
    assert np.all(seg.label[changed] == 0) and np.all(seg_off.label[changed] == 1)
    # against the surface the step measured with (the ground before contact: the rules without it)
    lines = rb.text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("  - ground_contact:"))
    end = next(i for i in range(start + 1, len(lines)) if not lines[i].startswith("      "))
    no_contact = parse_rule_base("\n".join(lines[:start] + lines[end:]), "outdoor.yaml",
                                 PredicateRegistry.default(entry_points_too=False))
    before = Interpreter(no_contact, sensor=sensor).run(X)
    g = seg.explanation.ground
    surface = LocalGround.build(X, np.flatnonzero(before.label == 0), np.array(g.normal), np.array(g.point),
                                neighbours=on.ground_model.neighbours, radius=on.ground_model.radius,
                                quantile=on.ground_model.quantile)
    h = np.abs(surface.height(X[changed]))
    tol = 0.05 + 0.002 * np.linalg.norm(X[changed] - sensor, axis=1)
    assert np.all(h <= tol) and np.all(h > 0.05 - 1e-12)  # beyond the fixed 0.05 m, within the grown one
    donors = [r for r in seg.explanation.records.values() if r.contact]
    assert all(any("within 0.05 m + 0.002 x range of the local ground surface" in n for n in r.notes) for r in donors)


@pytest.mark.slow
def test_ground_release_moves_raised_ground_points_to_the_nearest_obstacle(shared_data):
    """The SemanticKITTI scan with the shipped outdoor rules, against the same rules without
    post.ground_release: exactly the counted points changed, from ground to obstacle, each standing
    more than the tolerance above the surface the ground clusters made; the ground F1 rises."""
    data = shared_data / "semantickitti"
    X = np.load(data / "000001.points.npy").astype(np.float64)
    gt = np.load(data / "000001.labels.npy").ravel()
    rb = _with_release_passes(outdoor_one_release(), 1)  # one pass: against the surface before any release
    lines = rb.text.splitlines()
    start = lines.index(next(line for line in lines if line.startswith("  - ground_release:")))
    end = next(i for i in range(start + 1, len(lines)) if not lines[i].startswith("      "))
    rb_off = parse_rule_base("\n".join(lines[:start] + lines[end:]), "outdoor.yaml",
                             PredicateRegistry.default(entry_points_too=False))
    assert rb_off.release is None and rb.release.tolerance == 0.10 and rb.release.target == "obstacle"
    seg, seg_off = Interpreter(rb, jobs=2).run(X), Interpreter(rb_off, jobs=2).run(X)
    released = sum(r.released for r in seg.explanation.records.values())
    assert released > 0 and seg.explanation.ground.local_model.released == released
    changed = seg.label != seg_off.label
    # released points went ground -> obstacle; contact may differ only through them
    to_obstacle = (seg_off.label == 0) & (seg.label == 1)
    assert to_obstacle.sum() == released and changed.sum() == released
    # the surface both steps measured against: the ground clusters before either moved a point
    start = lines.index(next(line for line in lines if line.startswith("  - ground_contact:")))
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].startswith("      ")), len(lines))
    no_moves = [line for line in lines[:start] + lines[end:]]
    s0 = no_moves.index(next(line for line in no_moves if line.startswith("  - ground_release:")))
    e0 = next(i for i in range(s0 + 1, len(no_moves)) if not no_moves[i].startswith("      "))
    no_moves = no_moves[:s0] + no_moves[e0:]
    rb_none = parse_rule_base("\n".join(no_moves), "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    assert rb_none.release is None and rb_none.contact is None
    before = Interpreter(rb_none, jobs=2).run(X)
    g = seg.explanation.ground
    surface = LocalGround.build(X, np.flatnonzero(before.label == 0), np.array(g.normal), np.array(g.point),
                                neighbours=rb.ground_model.neighbours, radius=rb.ground_model.radius,
                                quantile=rb.ground_model.quantile)
    assert np.all(surface.height(X[to_obstacle]) > rb.release.tolerance)
    valid = gt != 0
    truth = np.isin(gt, [9, 10, 11, 12, 17])[valid]

    def f1(label):
        p = (label == 0)[valid]
        return 2 * (p & truth).sum() / (p.sum() + truth.sum())

    assert f1(seg.label) > f1(seg_off.label)
    for c in seg.clusters:
        assert c["n_points"] == (seg.cluster == c["index"]).sum()


def _with_release_passes(rb, passes: int, *without: str):
    """The rule base ``rb`` with ``passes`` on its ground_release step (and without the post steps
    ``without``)."""
    rb = _without_post_steps(rb, *without) if without else rb
    text = re.sub(r"(  - ground_release:.*\n(?:      .*\n)*?)      passes: .*\n", r"\g<1>", rb.text)
    text = re.sub(r"(  - ground_release:.*\n(?:      .*\n)*?      to: \w+\n)", rf"\g<1>      passes: {passes}\n", text)
    assert text.count("passes: ") == rb.text.count("passes: ") + (rb.release.passes == 1)
    return parse_rule_base(text, Path(rb.path).name, PredicateRegistry.default(entry_points_too=False))


@pytest.mark.slow
def test_ground_release_passes_release_what_the_surface_left_shows(shared_data, monkeypatch):
    """With 'passes', each pass measures the ground clusters against the surface built from the
    ground points the passes before left: the points a second pass releases are exactly those
    standing more than the tolerance above the surface of the ground left after the first; a pass
    asks only the points a release can have changed (the same labels as asking all of them); the
    passes end when one releases nothing; on SemanticKITTI 000001 (vegetation at terrain height
    inside the ground clusters) the ground F1 rises."""
    import kbs.knowledge.post.ground_release as gr_mod

    data = shared_data / "semantickitti"
    X = np.load(data / "000001.points.npy").astype(np.float64)
    gt = np.load(data / "000001.labels.npy").ravel()
    rb = outdoor_one_release()
    one, two = (_with_release_passes(rb, n, "ground_contact") for n in (1, 2))
    assert one.release.passes == 1 and two.release.passes == 2
    seg1, seg2 = Interpreter(one).run(X), Interpreter(two).run(X)
    moved = seg1.label != seg2.label
    assert moved.any() and np.all(seg1.label[moved] == 0) and np.all(seg2.label[moved] == 1)
    g = seg1.explanation.ground
    left = LocalGround.build(X, np.flatnonzero(seg1.label == 0), np.array(g.normal), np.array(g.point),
                             neighbours=rb.ground_model.neighbours, radius=rb.ground_model.radius,
                             quantile=rb.ground_model.quantile)
    h = left.height(X[seg1.label == 0])
    assert np.array_equal(np.nan_to_num(h, nan=-np.inf) > rb.release.tolerance, moved[seg1.label == 0])
    released = [r.released for r in seg2.explanation.records.values()]
    assert seg2.explanation.ground.local_model.released == sum(released)
    assert any("(pass 2: the surface without the points released before)" in n
               for r in seg2.explanation.records.values() for n in r.notes)
    # a pass asks only the points near those the pass before released: the same labels as all
    many = _with_release_passes(rb, 8)
    seg8 = Interpreter(many).run(X)
    after = gr_mod._Passes.after

    def ask_all(self, *args, **kwargs):
        after(self, *args, **kwargs)
        self.asked = None

    monkeypatch.setattr(gr_mod._Passes, "after", ask_all)
    seg8_all = Interpreter(many).run(X)
    assert np.array_equal(seg8.label, seg8_all.label) and np.array_equal(seg8.cluster, seg8_all.cluster)
    assert seg8.explanation.render() == seg8_all.explanation.render()
    valid = gt != 0
    truth = np.isin(gt, [9, 10, 11, 12, 17])[valid]

    def f1(label):
        p = (label == 0)[valid]
        return 2 * (p & truth).sum() / (p.sum() + truth.sum())

    assert f1(seg8.label) > f1(Interpreter(_with_release_passes(rb, 1)).run(X).label) + 0.003


def test_a_quantile_surface_is_that_quantile_of_the_neighbours_heights(monkeypatch):
    """ground_model.quantile: the ground height under a point is that quantile of its neighbours'
    heights (linear between the two ranks around it, as numpy's default), the median at 0.5;
    compiled and numpy paths give the same bits; height_bounds still bound every answer;
    another cluster's own points are left out as with the median."""
    from kbs.inference import _flags

    rng = np.random.default_rng(12)
    heights = rng.permutation(np.arange(16.0)) * 0.01  # 0 .. 0.15 m, one place
    X = np.column_stack([rng.normal(0, 0.01, 16), rng.normal(0, 0.01, 16), heights])
    for q, want in ((0.5, 0.075), (0.25, 0.0375), (0.0, 0.0), (1.0, 0.15), (0.3, 0.045)):
        model = LocalGround.build(X, np.arange(16), np.array([0, 0, 1.0]), np.zeros(3), neighbours=16, radius=1.0,
                                  quantile=q)
        g, _ = model.query(np.zeros((1, 3)))
        np.testing.assert_allclose(g, np.percentile(heights, 100 * q), atol=1e-15)
        np.testing.assert_allclose(g, want, atol=1e-15)
    with pytest.raises(ValueError, match="quantile"):
        LocalGround.build(X, np.arange(16), np.array([0, 0, 1.0]), np.zeros(3), quantile=1.5)
    # a random slope: both paths, the bounds, a cluster left out
    R = np.column_stack([rng.uniform(0, 40, 6000), rng.uniform(0, 40, 6000), rng.normal(0, 0.2, 6000)])
    R[:, 2] += 0.1 * R[:, 0]
    owners = (R[:, 0] // 10).astype(np.int64)
    P = R[1::2] + [0.0, 0.0, 0.3]
    out = {}
    for jit in (True, False):
        monkeypatch.setattr(_flags, "JIT", jit)
        model = LocalGround.build(R, np.arange(0, 6000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16,
                                  radius=3.0, owners=owners[::2], owner_ids=("a", "b", "c", "d"), quantile=0.25)
        median = LocalGround.build(R, np.arange(0, 6000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16,
                                   radius=3.0, owners=owners[::2], owner_ids=("a", "b", "c", "d"))
        g, near = model.query(P)
        gx, _ = model.query(P, exclude="b")
        lo, hi = model.height_bounds(P)
        assert np.all(lo <= g) and np.all(g <= hi)
        gm, near_m = median.query(P)
        assert np.array_equal(near, near_m)  # the same neighbours, another statistic of them
        assert np.mean(g < gm) > 0.95  # the lower quartile lies below the median almost everywhere
        out[jit] = (g.tobytes(), gx.tobytes(), near.tobytes())
    assert out[True] == out[False]


def _lower_quartile(text: str, tolerance: str = "0.18") -> str:
    """outdoor.yaml's text with its ground model's surface the lower quartile and its release
    tolerance ``tolerance`` (the variant measured in session 28, not shipped)."""
    out = text.replace("      radius: 3.0                # m\n  - relabel:",
                       "      radius: 3.0                # m\n      quantile: 0.25\n  - relabel:")
    out = out.replace("      tolerance: 0.10            # m\n      to: obstacle",
                      f"      tolerance: {tolerance}            # m\n      to: obstacle")
    assert out.count("quantile: 0.25") == 1 and out.count(f"tolerance: {tolerance} ") == 1
    return out


def test_the_ground_model_quantile_is_checked_with_positions_and_said_in_the_explanation():
    shipped = load_rule_base("outdoor")
    assert shipped.ground_model.quantile == 0.5  # the median
    text = _lower_quartile(shipped.text)
    rb = parse_rule_base(text, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    assert rb.ground_model.quantile == 0.25 and rb.release.tolerance == 0.18
    for bad, why in (("1.5", "greater than the maximum of 1"), ("-0.1", "less than the minimum of 0"),
                     ("half", "must be a number"), (".nan", "not a finite number")):
        wrong = text.replace("      quantile: 0.25\n", f"      quantile: {bad}\n")
        assert wrong != text
        with pytest.raises(RuleFileError) as err:
            parse_rule_base(wrong, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
        line = next(i for i, t in enumerate(wrong.splitlines(), 1) if t.startswith(f"      quantile: {bad}"))
        assert re.search(rf"outdoor\.yaml:{line}:\d+: .*{why}", err.value.format()), err.value.format()
    X, _ = ground_and_rocks()
    lm = Interpreter(rb).run(X).explanation.ground.local_model
    assert lm.quantile == 0.25 and lm.to_dict()["quantile"] == 0.25
    lm = Interpreter(shipped).run(X).explanation.ground.local_model
    assert lm.quantile is None and "quantile" not in lm.to_dict()  # the median: as before
    # kbs tune may fit it: a mark on the step names the field
    from kbs.knowledge.tuning import with_values

    marked = text.replace("      quantile: 0.25\n", "      quantile: 0.25\n      tune: {field: quantile, values: [0.25, 0.5]}\n")
    rb_t = parse_rule_base(marked, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    assert [t.name for t in rb_t.tunables] == ["post.ground_model.quantile"]
    assert with_values(rb_t, {"post.ground_model.quantile": 0.5})[1].ground_model.quantile == 0.5


@pytest.mark.slow
def test_the_lower_quartile_surface_raises_f1_on_semantickitti(shared_data):
    """SemanticKITTI 000001 (tuning part): vegetation 0.15-0.5 m above the labelled terrain inside
    the ground clusters, under the median surface of the ground clusters' points. The lower-quartile
    surface and an 18 cm release against the median and 10 cm (the rules without their second
    release, session 42): 0.9561 -> 0.9583 measured,
    less of the vegetation is ground (not shipped: the validation part does not confirm it,
    docs/BENCHMARKS.md "Session 28")."""
    data = shared_data / "semantickitti"
    X = np.load(data / "000001.points.npy").astype(np.float64)
    gt = np.load(data / "000001.labels.npy").ravel()
    rb_old = outdoor_one_release()
    rb = parse_rule_base(_lower_quartile(rb_old.text), "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    new, before = Interpreter(rb).run(X).label == 0, Interpreter(rb_old).run(X).label == 0
    valid = gt != 0
    truth = np.isin(gt, [9, 10, 11, 12, 17])

    def f1(p):
        p, t = p[valid], truth[valid]
        return 2 * (p & t).sum() / (p.sum() + t.sum())

    assert f1(new) > f1(before) + 0.0015, (f1(new), f1(before))
    vegetation = (gt == 15) & valid
    assert (new & vegetation).sum() < 0.9 * (before & vegetation).sum()  # 2,363 -> 2,004 measured


def test_ground_release_passes_are_checked_with_positions():
    text = re.sub(r"      passes: 2 .*\n", "      passes: 0\n", load_rule_base("outdoor").text)
    assert "passes: 0" in text
    with pytest.raises(RuleFileError) as err:
        parse_rule_base(text, "outdoor.yaml", PredicateRegistry.default(entry_points_too=False))
    assert re.search(r"outdoor\.yaml:\d+:\d+: .*passes", err.value.format()), err.value.format()


def _without_post_steps(rb, *keys: str):
    """The rule base ``rb`` parsed again without its post steps ``keys`` (their lines cut)."""
    lines = rb.text.splitlines()
    for key in keys:
        start = lines.index(next(line for line in lines if line.startswith(f"  - {key}:")))
        end = next((i for i in range(start + 1, len(lines)) if not lines[i].startswith("      ")), len(lines))
        lines = lines[:start] + lines[end:]
    return parse_rule_base("\n".join(lines), Path(rb.path).name, PredicateRegistry.default(entry_points_too=False))


def _isprs_centred(shared_data, name: str):
    """An ISPRS sample of the PCL data (``samp31``, ...): its scan path, its points centred and its
    reference bare-earth mask."""
    from kbs.io import read_cloud

    scan = shared_data / "isprs" / f"{name}-utm.pcd"
    pc = read_cloud(scan)
    truth = np.loadtxt(shared_data / "isprs" / f"{name}-utm.labels.txt")[pc.index] == 0
    return scan, pc.xyz - pc.xyz.mean(axis=0), truth



@pytest.mark.slow  # whole real scans: pytest --runslow (CI) runs it
def test_airborne_rules_release_the_points_standing_on_a_ground_patch(shared_data, tmp_path):
    """Session 23: rules/airborne.yaml ends with post.ground_release (0.7 m). On ISPRS sample 31
    (the validation part), against the same rules without the step: only ground -> object
    changes, exactly the counted points, each more than 0.7 m above the final surface; most of them
    are objects by the reference, and the total error falls (4.50 -> 3.72 %). Through the command,
    the explanation says where they went."""
    scan, X, truth = _isprs_centred(shared_data, "samp31")
    rb = load_rule_base("airborne")
    assert rb.release is not None and rb.release.tolerance == 0.7 and rb.release.target == "object"
    rb_off = _without_post_steps(rb, "ground_release")
    assert rb_off.release is None
    seg, off = Interpreter(rb, jobs=1).run(X), Interpreter(rb_off, jobs=1).run(X)
    released = seg.explanation.ground.local_model.released
    assert released == sum(r.released for r in seg.explanation.records.values()) > 100
    moved = seg.label != off.label
    assert moved.sum() == released and np.all(off.label[moved] == 0) and np.all(seg.label[moved] == 1)
    g = off.explanation.ground
    surface = LocalGround.build(X, np.flatnonzero(off.label == 0), np.array(g.normal), np.array(g.point),
                                neighbours=rb.ground_model.neighbours, radius=rb.ground_model.radius)
    # samp31's y is quantised to 0.5 m: neighbours at equal distances abound, and which of them is
    # the 8th depends on the order the surface's points are given in (the step gives them cluster by
    # cluster, this rebuild in index order): a few medians differ by a few centimetres
    h = surface.height(X[moved])
    assert np.all(h > 0.6) and np.mean(h > 0.7 - 1e-4) > 0.98, np.sort(h)[:5]
    assert (~truth[moved]).sum() > 0.9 * released  # measured: 228 of 232 are objects

    def total_error(label):
        return np.mean((label == 0) != truth)

    assert total_error(seg.label) < total_error(off.label) - 0.005  # measured 3.72 % against 4.50 %
    r = kbs("run", "--rules", "airborne", str(scan), "--out", str(tmp_path), "-j", "1")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "samp31-utm.json").read_text())
    one = next(c for c in doc["explanation"]["clusters"] if c.get("released"))
    r = kbs("explain", str(tmp_path / "samp31-utm.json"), "--cluster", one["id"])
    assert re.search(r"stand more than 0\.7 m above the local ground surface and joined object cluster", r.stdout), r.stdout


@pytest.mark.slow  # whole real scans: pytest --runslow (CI) runs it
def test_airborne_rules_give_the_foot_of_rough_objects_to_the_ground(shared_data):
    """Session 23: rules/airborne.yaml's post.ground_contact (0.5 m, if not planar). On ISPRS sample
    61 (the validation part), against the same rules without the step: only object -> ground
    changes, exactly the counted points, each near the surface, only from clusters that are not
    planar; most are bare earth by the reference and the total error falls (8.35 -> 7.46 %)."""
    _, X, truth = _isprs_centred(shared_data, "samp61")
    rb = load_rule_base("airborne")
    assert rb.contact is not None and rb.contact.tolerance == 0.5
    rb_off = _without_post_steps(rb, "ground_contact")
    assert rb_off.contact is None
    seg, off = Interpreter(rb, jobs=1).run(X), Interpreter(rb_off, jobs=1).run(X)
    moved = seg.label != off.label
    contact = [r for r in seg.explanation.records.values() if r.contact]
    assert moved.sum() == sum(r.contact for r in contact) > 100
    assert np.all(off.label[moved] == 1) and np.all(seg.label[moved] == 0)
    assert all(next(c for c in r.checks if c.check == "planar").value > 0.25 for r in contact)  # not planar
    # the surface both post steps measure against: the ground before ground_release moved a point
    rb_none = _without_post_steps(rb, "ground_release", "ground_contact")
    assert rb_none.release is None and rb_none.contact is None
    g = off.explanation.ground
    surface = LocalGround.build(X, np.flatnonzero(Interpreter(rb_none, jobs=1).run(X).label == 0), np.array(g.normal),
                                np.array(g.point), neighbours=rb.ground_model.neighbours, radius=rb.ground_model.radius)
    h = np.abs(surface.height(X[moved]))  # (the order of equal distances aside, see the test above)
    assert np.mean(h <= 0.5 + 1e-4) > 0.98, np.sort(h)[-5:]
    assert truth[moved].mean() > 0.8

    def total_error(label):
        return np.mean((label == 0) != truth)

    assert total_error(seg.label) < total_error(off.label) - 0.005  # measured 7.46 % against 8.35 %

def _ground_of_run(tmp_path, X, rules: str, name: str):
    """``kbs run --rules RULES`` on the points ``X`` written as NAME.ply: (label 0 per point, the result JSON)."""
    path = tmp_path / f"{name}.ply"
    write_ply(path, X)
    r = kbs("run", "--rules", rules, str(path), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr
    v = PlyData.read(str(tmp_path / "o" / f"{name}.ply"))["vertex"]
    return np.asarray(v["scalar_label"]) == 0, json.loads((tmp_path / "o" / f"{name}.json").read_text())


@pytest.mark.slow
def test_outdoor_rules_take_a_row_of_parked_cars_roofs_for_obstacles_not_ground(tmp_path):
    """Issue 12: parked cars became ground. Their roofs are as planar and as level as the road, so
    PAh and the ground angle pass them; what tells them from the ground is where they stand: 1.45 m
    above the ground around them, more than any kerb (outdoor.yaml's 'raised' relabel rule)."""
    X, labels = ground_and_parked_cars()
    ground, doc = _ground_of_run(tmp_path, X, "outdoor", "cars")
    assert ground[labels == 0].mean() > 0.99 and not ground[labels > 0].any()  # 1.0 of the roofs before
    raised = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "raised"]
    assert raised and all(c["label"] == "obstacle" for c in raised)
    r = kbs("explain", str(tmp_path / "o" / "cars.json"), "--cluster", raised[0]["id"])
    assert "relabelled obstacle by raised [outdoor.yaml:" in r.stdout and "raised (height_above_local_ground = 1.4" in r.stdout


@pytest.mark.slow
def test_airborne_rules_take_a_large_buildings_inner_roof_for_an_object(tmp_path):
    """Issue 12: the roofs of large buildings became ground, each roof patch judged against the
    roof patches around it. airborne.yaml's 'above_terrain' judges it against the lowest terrain
    the ground within 30 m allows, no steeper than 40 deg: a six-storey roof 70 m x 50 m, in
    sections of three levels, had 21 % of its points taken for ground (the inner sections); those
    within the slope's reach of the ground beside it became objects. Since session 37
    'large_roofs' takes every patch of a continuous surface whose edges drop 5 m or more (the roof
    sections' surface, 3 m apart at most), before 'roofs' is asked."""
    X, labels = airborne_large_building()
    ground, doc = _ground_of_run(tmp_path, X, "airborne", "block")
    assert ground[labels == 0].mean() > 0.99
    assert ground[labels == 1].mean() < 0.1, ground[labels == 1].mean()  # 0.207 before 'above_terrain'
    large = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "large_roofs"]
    assert large and all(c["label"] == "object" for c in large)
    r = kbs("explain", str(tmp_path / "o" / "block.json"), "--cluster", large[0]["id"])
    assert r.returncode == 0, r.stderr
    assert "relabelled object by large_roofs [airborne.yaml:" in r.stdout and "edge_raised (edge_drop = " in r.stdout
    # the rule base without 'large_roofs' (nor 'low_roofs', judged again on its evidence):
    # 'above_terrain' takes inner sections 'raised' does not
    before = airborne_without(tmp_path, ("large_roofs", "low_roofs"), ("edge_raised", "edge_raised_left"))
    ground, doc = _ground_of_run(tmp_path, X, before, "block")
    assert ground[labels == 1].mean() < 0.1, ground[labels == 1].mean()  # 0.062 measured
    # (what 'roofs' measured is in its relabel entry: 'terrain', a later relabel step, measures
    # the surface's checks again against its own surface)
    roofs = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "roofs"
             and not next(k for k in c["relabel"]["measured"] if k["check"] == "raised")["passed"]]
    assert roofs, "inner roof patches: not raised above their neighbours, above the terrain the slope allows"
    r = kbs("explain", str(tmp_path / "o" / "block.json"), "--cluster", roofs[0]["id"])
    assert r.returncode == 0, r.stderr
    assert "relabelled object by roofs [airborne-without-large_roofs-low_roofs.yaml:" in r.stdout
    assert "above_terrain (height_above_slope_surface = " in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("step", [3.0, 4.0, 5.0])
def test_airborne_rules_keep_a_terrain_step_as_ground_and_the_building_beside_it_an_object(tmp_path, step):
    """Issue 12: the level terrace above a 3-5 m terrain step became an object ('raised': its edge
    stands high above the lower terrace; 44 % of the bare earth lost), while the roof of the
    building beside the step is rightly an object. airborne.yaml's 'terraces' undoes 'roofs' for a
    patch that meets the ground left once the roofs are out and lies on its terrain: the terrace is
    given back in pass 2, the roof judged again and kept an object."""
    X, labels = airborne_step_and_building(step=step)
    ground, doc = _ground_of_run(tmp_path, X, "airborne", "step")
    roof = (labels == 1) & (X[:, 2] - 250.0 > 6.5)
    assert ground[roof].mean() < 0.05, ground[roof].mean()
    assert ground[labels == 0].mean() > 0.995, ground[labels == 0].mean()  # 0.56 before 'terraces'
    back = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "terraces"]
    assert back and all(c["label"] == "ground" and c["relabel"]["undid"]["rule"] == "roofs" for c in back)
    assert doc["explanation"]["ground"]["local_model"]["undone"] == len(back)
    r = kbs("explain", str(tmp_path / "o" / "step.json"), "--cluster", back[0]["id"])
    assert r.returncode == 0, r.stderr
    assert "relabelled object by roofs [airborne.yaml:" in r.stdout and "given back ground by terraces [airborne.yaml:" in r.stdout
    assert re.search(r"terraces \[airborne\.yaml:\d+\] pass 2 \([\d,]+ surface points\): holds", r.stdout), r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("step", [1.5, 2.0])
def test_airborne_rules_keep_a_low_terrace_as_ground(tmp_path, step):
    """A terrain step of 1.5-2 m, below `roofs`' 2.5 m: the upper terrace's edge stands half a metre
    or more above the patches below it, so `understory` took the whole terrace (11,000 points, 43 %
    total error, session 22); `low_terraces` judges it again against the ground left and gives it
    back, the bank's ground patches leading up to it by a gentle rise. The same rule file without
    `low_terraces` loses the terrace again."""
    X, labels = airborne_step_and_building(step=step)
    ground, doc = _ground_of_run(tmp_path, X, "airborne", "low")
    assert ground[labels == 0].mean() > 0.99, ground[labels == 0].mean()
    back = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "low_terraces"]
    assert back and all(c["label"] == "ground" and c["relabel"]["undid"]["rule"] == "understory" for c in back)
    assert sum(c["n_points"] for c in back) > 10000
    text = (Path(__file__).resolve().parents[1] / "rules" / "airborne.yaml").read_text()
    start, end = text.index("      - name: low_terraces"), text.index("      - name: terrain")
    without = tmp_path / "without.yaml"
    without.write_text(text[:start] + text[end:])
    (tmp_path / "w").mkdir()
    ground_without, _ = _ground_of_run(tmp_path / "w", X, str(without), "low")
    assert ground_without[labels == 0].mean() < 0.7, ground_without[labels == 0].mean()


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["step", "pit"])
def test_airborne_rules_keep_a_plateau_above_a_high_step_or_a_pit(tmp_path, scene):
    """A terrain step of 10 m (its face 2 m wide, 79 deg) and a quarry pit 8 m deep: the terrain
    above the face stands 8-10 m above the ground below it, so `roofs` (and `large_roofs`) took all
    of it, 43 % and 90 % total error (session 37). Its continuous surface drops on one side only
    (`open_surface`: none of it inside the hull of the surfaces it drops to) and covers more than a
    large building (`vast`), and the patches standing above another surface stand at its edge
    (`drops`): a plateau, kept as ground, while the building's roof beside it is still an object.
    With `vast` never holding, the rule file loses the plateau again."""
    X, labels = airborne_step_and_building(step=10.0) if scene == "step" else airborne_pit(depth=8.0)
    ground, doc = _ground_of_run(tmp_path, X, "airborne", scene)
    roof = (labels == 1) & (X[:, 2] - 250.0 > 6.5)
    assert ground[roof].mean() < 0.05, ground[roof].mean()
    assert ground[labels == 0].mean() > 0.97, ground[labels == 0].mean()
    text = (Path(__file__).resolve().parents[1] / "rules" / "airborne.yaml").read_text()
    start = text.index("  vast:")
    at = text.index("    min: 2500", start)
    never = tmp_path / "never-vast.yaml"
    never.write_text(text[:at] + "    min: 1.0e+12" + text[at + len("    min: 2500"):])
    (tmp_path / "n").mkdir()
    ground_never, _ = _ground_of_run(tmp_path / "n", X, str(never), scene)
    assert ground_never[labels == 0].mean() < 0.7, ground_never[labels == 0].mean()


@pytest.mark.slow
def test_airborne_rules_keep_a_terrace_whose_bank_is_a_patch_of_its_own(tmp_path):
    """The middle 90 m x 90 m of the 4 m step: the bank (63 deg, not gentle) is split from the
    upper terrace, which then meets no ground at its own height ('joins' fails: its lowest point
    stands 3.7 m above the lower terrace); 'bank' finds it reached from the lower terrace by terrain
    no steeper than 65 deg, which no wall allows: given back (bare earth kept 0.58 before 'bank'),
    the roof still an object, the bank itself an object (steeper than 'gentle')."""
    X, labels = airborne_step_and_building(step=4.0)
    keep = (np.abs(X[:, 0] - 512000.0) < 45) & (np.abs(X[:, 1] - 5400000.0) < 45)
    X, labels = X[keep], labels[keep]
    ground, doc = _ground_of_run(tmp_path, X, "airborne", "crop")
    roof = (labels == 1) & (X[:, 2] - 250.0 > 6.5)
    assert ground[roof].mean() < 0.05, ground[roof].mean()
    assert ground[labels == 0].mean() > 0.97, ground[labels == 0].mean()  # 0.980 measured
    back = [c for c in doc["explanation"]["clusters"] if c["relabel"] and c["relabel"]["rule"] == "terraces"]
    assert len(back) == 1
    measured = {m["check"]: m["passed"] for m in back[0]["relabel"]["measured"]}
    assert measured == {"joins": False, "bank": True, "on_terrain": True, "drops": False}, measured


def test_height_above_slope_is_at_most_zero_on_terrain_no_steeper_than_the_slope():
    """LocalGround.height_above_slope on a 30 deg hillside: 0 or less when 40 deg is allowed,
    positive when only 20 deg is; a point 5 m above the hill, 10 m from its nearest surface point
    measures 5 - tan(40 deg) x 10 with that point's own cluster left out."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (3000, 2))
    X = np.column_stack([xy, np.tan(np.radians(30)) * xy[:, 0]])
    model = LocalGround.build(X, np.arange(3000), np.array([0.0, 0.0, 1.0]), np.zeros(3), owners=np.zeros(3000, int),
                              owner_ids=("hill",))
    P = X[:200]
    assert np.nanmax(model.height_above_slope(P, 40.0, 10.0)) <= 1e-9
    assert np.nanmin(model.height_above_slope(P[np.abs(P[:, 0]) < 10], 20.0, 10.0)) >= 0.0
    assert np.nanmedian(model.height_above_slope(P[np.abs(P[:, 0]) < 10], 20.0, 10.0)) > 0.5
    # its own points left out, nothing is within reach: NaN
    assert np.isnan(model.height_above_slope(P[:5], 40.0, 10.0, exclude="hill")).all()
    flat = LocalGround.build(np.array([[10.0, 0.0, 0.0]]), np.arange(1), np.array([0.0, 0.0, 1.0]), np.zeros(3))
    h = flat.height_above_slope(np.array([[0.0, 0.0, 5.0]]), 40.0, 30.0)
    assert h[0] == pytest.approx(5.0 - np.tan(np.radians(40)) * 10.0)


def test_height_above_slope_surface_is_undefined_with_no_ground_within_its_radius():
    """A cluster with no ground of other clusters within the radius says nothing of its height
    above the terrain: the predicate's value is undefined (its check fails, a 'max' check as
    'on_terrain' included, and says why), where it measured 0 and passed every 'max' check."""
    from kbs.knowledge.predicates import Cluster, Ground, Scene

    rng = np.random.default_rng(1)
    far = np.column_stack([rng.uniform(0, 10, (300, 2)), rng.normal(0, 0.02, 300)])  # ground 60 m away
    roof = np.column_stack([rng.uniform(60, 70, (200, 2)), 8 + rng.normal(0, 0.02, 200)])
    X = np.vstack([far, roof])
    owners = np.r_[np.zeros(len(far), int), np.ones(len(roof), int)]
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), neighbours=8, radius=5.0,
                              owners=owners, owner_ids=("c0", "c1"))
    scene = Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=model)
    pred = PredicateRegistry.default(entry_points_too=False).get("height_above_slope_surface")
    cl = Cluster("c1", roof, np.ones(len(roof)))
    m = pred.measure(cl, scene, {"slope": 40.0, "radius": 30.0})
    assert not m.defined and np.isnan(m.value) and "within 30" in m.undefined
    near = pred.measure(cl, scene, {"slope": 10.0, "radius": 80.0})  # the ground in reach: a height
    assert near.defined and near.value < 8 - np.tan(np.radians(10)) * 50  # at least 50 m from the ground



def _street_block_and_terrace(seed: int = 0):
    """Surface points at 1 a square metre of a 100 m x 100 m street level (z 0, a 1 % grade) around a
    40 m x 40 m roof 10 m up in two sections 0.3 m apart (c1, c2), and a terrace 4 m up (c3) that a
    20 deg ramp (c4) joins to the street on one side; owners c0 (street) to c4."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50, 50, (10000, 2))
    x, y = xy[:, 0], xy[:, 1]
    roof = (np.abs(x) < 20) & (np.abs(y) < 20)
    terrace = (x > 30) & (np.abs(y) < 10)
    ramp = (x > 19) & (x <= 30) & (np.abs(y) < 10)  # rises 4 m over 11 m: 20 deg
    z = 0.01 * x + rng.normal(0, 0.03, x.size)
    z[roof] = 10.0 + 0.3 * (x[roof] > 0) + rng.normal(0, 0.03, roof.sum())
    z[terrace] = 0.01 * x[terrace] + 4.0
    z[ramp] = 0.01 * x[ramp] + 4.0 * (x[ramp] - 19) / 11
    owner = np.zeros(x.size, dtype=np.int64)
    owner[roof & (x <= 0)], owner[roof & (x > 0)], owner[terrace], owner[ramp] = 1, 2, 3, 4
    return np.column_stack([xy, z]), owner


def test_edges_join_a_roofs_sections_and_measure_the_drop_at_its_walls():
    """LocalGround.edges: the roof's two sections (0.3 m apart, under the 0.5 m step) are one
    continuous surface, which drops about 10 m at its edges, less a 45 deg slope's rise over the
    metre or so to the street beside it; the street, the ramp and the terrace are one surface
    (no steeper than 45 deg between neighbours), which rises at the roof's walls; the same answer
    whatever the order of the points."""
    X, owner = _street_block_and_terrace()
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner,
                              owner_ids=("c0", "c1", "c2", "c3", "c4"))
    edges = model.edges(3.0, 45.0, 0.5)
    assert model.edges(3.0, 45.0, 0.5) is edges  # built once per surface and parameters
    r = edges.owner_region
    assert r[1] == r[2] and r[0] == r[3] == r[4] and r[0] != r[1]
    roof_drop = np.median(edges.drops_of(int(r[1])))
    assert 7.0 < roof_drop < 10.0, roof_drop
    assert np.median(edges.drops_of(int(r[0]))) < -7.0
    assert edges.size_of(int(r[1])) == np.isin(owner, [1, 2]).sum()
    # the points in another order: the same surfaces and drops
    perm = np.random.default_rng(1).permutation(len(X))
    again = LocalGround.build(X[perm], np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner[perm],
                              owner_ids=("c0", "c1", "c2", "c3", "c4")).edges(3.0, 45.0, 0.5)
    assert np.median(again.drops_of(int(again.owner_region[1]))) == roof_drop
    assert np.array_equal(np.isnan(again.drop), np.isnan(edges.drop[perm]))
    assert np.allclose(again.drop[~np.isnan(again.drop)], edges.drop[perm][~np.isnan(edges.drop[perm])])
    # a 1 m step still keeps the roof apart from the street (its walls are 10 m high)
    assert model.edges(3.0, 45.0, 1.0).owner_region[1] != model.edges(3.0, 45.0, 1.0).owner_region[0]
    # without the ramp, the terrace is a surface of its own that drops 4 m less the slope's rise
    keep = owner != 4
    alone = LocalGround.build(X[keep], np.arange(keep.sum()), np.array([0, 0, 1.0]), np.zeros(3),
                              owners=owner[keep], owner_ids=("c0", "c1", "c2", "c3", "c4")).edges(3.0, 45.0, 0.5)
    assert alone.owner_region[3] != alone.owner_region[0] and alone.owner_region[4] == -1
    assert 1.0 < np.median(alone.drops_of(int(alone.owner_region[3]))) < 4.0


def test_edge_drop_predicate_measures_the_surface_a_cluster_is_part_of():
    """The predicate 'edge_drop': a roof section's value is its whole roof's (however far it lies
    from the walls); a cluster not part of the surface, and a surface with no other within the
    gap, have no value (the check fails and says why)."""
    from kbs.knowledge.predicates import Cluster, Ground, Scene

    X, owner = _street_block_and_terrace()
    ids = ("c0", "c1", "c2", "c3", "c4")
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner, owner_ids=ids)
    scene = Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=model)
    pred = PredicateRegistry.default(entry_points_too=False).get("edge_drop")
    params = {"gap": 3.0, "slope": 45.0, "step": 0.5, "stat": "median"}
    one, two = (pred.measure(Cluster(c, X[owner == k], np.ones((owner == k).sum())), scene, params)
                for k, c in ((1, "c1"), (2, "c2")))
    assert one.defined and one.value == two.value and one.value > 5.0
    assert one.details["surface_points"] == np.isin(owner, [1, 2]).sum()
    street = pred.measure(Cluster("c0", X[owner == 0], np.ones((owner == 0).sum())), scene, params)
    assert street.defined and street.value < 0.0
    other = pred.measure(Cluster("c9", X[:10], np.ones(10)), scene, params)
    assert not other.defined and "not part of the local ground surface" in other.undefined
    lone = LocalGround.build(X[owner == 1], np.arange((owner == 1).sum()), np.array([0, 0, 1.0]), np.zeros(3),
                             owners=np.zeros((owner == 1).sum(), int), owner_ids=("c1",))
    m = pred.measure(Cluster("c1", X[owner == 1], np.ones((owner == 1).sum())),
                     Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=lone),
                     params)
    assert not m.defined and "meets no other within 3" in m.undefined


def _low_roof_between_taller_ones(seed: int = 0):
    """Surface points at 1 a square metre of a 100 m x 100 m street level (z 0) with a block 40 m deep
    (y > 10) of three buildings side by side: a low roof 8 m up (c1, x in [-10, 10]) between two
    taller ones 18 m up (c2, c3); the street (c0) along the block's front only (the scan ends at the
    block's back). Owners c0 to c3."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-50, 50, (10000, 2))
    x, y = xy[:, 0], xy[:, 1]
    block = y > 10
    low = block & (np.abs(x) <= 10)
    z = rng.normal(0, 0.03, x.size)
    z[block] += 18.0
    z[low] -= 10.0
    owner = np.zeros(x.size, dtype=np.int64)
    owner[low], owner[block & (x < -10)], owner[block & (x > 10)] = 1, 2, 3
    return np.column_stack([xy, z]), owner


def test_drops_beside_the_surfaces_still_ground():
    """SurfaceRegions.drops_beside: with every owner alive, the drops of SurfaceEdges.drops_of; the
    low roof between two taller ones rises to them at most of its edges (median below 0), and drops
    by about its height to the street once they are out (their points no longer beside its edges)."""
    X, owner = _low_roof_between_taller_ones()
    ids = ("c0", "c1", "c2", "c3")
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner, owner_ids=ids)
    regions = model.regions
    edges = regions.edges(3.0, 45.0, 0.5)
    r = int(edges.owner_region[1])
    every = regions.drops_beside(3.0, 45.0, 0.5, r, np.ones(4, bool))
    assert np.allclose(np.sort(every), np.sort(edges.drops_of(r)))
    assert np.median(every) < -5.0 and every.max() > 5.0  # rises to the taller roofs, drops to the street
    street_only = regions.drops_beside(3.0, 45.0, 0.5, r, np.array([True, True, False, False]))
    assert 0 < street_only.size < every.size
    assert street_only.min() > 5.0 and np.median(street_only) > 6.0  # 8 m less a 45 deg slope's rise
    assert regions.drops_beside(3.0, 45.0, 0.5, r, np.array([True, True, False, False])) is street_only  # cached
    assert regions.drops_beside(3.0, 45.0, 0.5, r, np.array([False, True, False, False])).size == 0


def test_edge_drop_beside_ground_in_a_later_pass():
    """The predicate 'edge_drop' with beside: ground: on the surface the relabel step started from,
    the same value as without; on a surface rebuilt without the taller roofs (a later pass, the
    step's surfaces kept), the low roof drops at its edges; a rule file giving 'beside' with
    over: cluster is refused where it says so."""
    from kbs.knowledge.predicates import Cluster, Ground, Scene

    X, owner = _low_roof_between_taller_ones()
    ids = ("c0", "c1", "c2", "c3")
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner, owner_ids=ids)
    ground = Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed")
    pred = PredicateRegistry.default(entry_points_too=False).get("edge_drop")
    params = {"gap": 3.0, "slope": 45.0, "step": 0.5, "stat": "median"}
    low = Cluster("c1", X[owner == 1], np.ones((owner == 1).sum()))
    first = pred.measure(low, Scene(np.zeros(3), ground, "m", ground_model=model), params)
    same = pred.measure(low, Scene(np.zeros(3), ground, "m", ground_model=model), {**params, "beside": "ground"})
    assert first.value == same.value < -5.0
    keep = owner <= 1  # the taller roofs taken: the surface rebuilt without them, the step's surfaces kept
    later = LocalGround.build(X[keep], np.arange(keep.sum()), np.array([0, 0, 1.0]), np.zeros(3), owners=owner[keep],
                              owner_ids=("c0", "c1"))
    later.measure_regions_on(model.regions)
    scene = Scene(np.zeros(3), ground, "m", ground_model=later)
    assert pred.measure(low, scene, params).value == first.value  # 'all': the step's surfaces as they were
    m = pred.measure(low, scene, {**params, "beside": "ground"})
    assert m.defined and m.value > 6.0 and m.details["edge_points"] < first.details["edge_points"]
    later.measure_regions_on(None)  # its own points again
    assert later.regions is not model.regions and later.regions.owner_ids == ("c0", "c1")


def test_edge_drop_beside_applies_over_the_surface_only(tmp_path):
    import yaml

    doc = yaml.safe_load((Path(__file__).resolve().parents[1] / "rules" / "airborne.yaml").read_text())
    doc["checks"]["edge_raised"]["params"].update({"over": "cluster", "beside": "ground"})
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(RuleFileError) as exc:
        load_rule_base(str(path))
    assert "parameter 'beside' applies only with over: surface" in str(exc.value)
    assert "bad.yaml:" in str(exc.value)


def _street_roof_corner_and_step(seed: int = 0):
    """Surface points at 1 a square metre of a 120 m x 120 m street level (z 0, a 1 % grade) with a
    30 m x 30 m roof 9 m up in its middle (c1), a building 30 m x 30 m, 12 m up, cut by the scan's
    corner (two walls in view, c2), and the upper terrace of an 8 m terrain step across the scan
    (x > 35, a vertical face; c3); owners c0 (street) to c3."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-60, 60, (14400, 2))
    x, y = xy[:, 0], xy[:, 1]
    roof = (np.abs(x + 10) < 15) & (np.abs(y) < 15)
    corner = (x < -45) & (y > 45)
    step = x > 35
    z = 0.01 * y + rng.normal(0, 0.03, x.size)
    z[roof] += 9.0
    z[corner] += 12.0
    z[step] += 8.0
    owner = np.zeros(x.size, dtype=np.int64)
    owner[roof], owner[corner], owner[step] = 1, 2, 3
    return np.column_stack([xy, z]), owner


def test_surface_enclosure_tells_a_roof_from_the_upper_terrace_of_a_step():
    """SurfaceEdges.enclosure: the street encloses the roof in its middle (all of its points lie
    within the hull of the street points it drops to), half of the building cut by the scan's corner
    (two walls in view: a quarter to a half), none of the terrace above a step (it drops along one line); each drop's
    partner is the point of another surface that allows the lowest terrain under it; the areas are
    the surfaces' footprints traced on 3 m cells; the same answers whatever the order of the
    points."""
    X, owner = _street_roof_corner_and_step()
    ids = ("c0", "c1", "c2", "c3")
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner, owner_ids=ids)
    edges = model.edges(3.0, 45.0, 0.5)
    r = edges.owner_region
    assert len({int(v) for v in r}) == 4
    roof, n_roof = edges.enclosure(int(r[1]), 2.5)
    corner, _ = edges.enclosure(int(r[2]), 2.5)
    step, n_step = edges.enclosure(int(r[3]), 2.5)
    assert roof > 0.99 and n_roof > 50, (roof, n_roof)
    assert 0.2 < corner < 0.7, corner
    assert step < 0.02 and n_step > 50, (step, n_step)
    assert edges.enclosure(int(r[1]), 2.5) is edges.enclosure(int(r[1]), 2.5)  # computed once
    # the street drops nowhere by 2.5 m: no share
    share, n_street = edges.enclosure(int(r[0]), 2.5)
    assert np.isnan(share) and n_street == 0
    # partners: in another region, realising the lowest terrain under each edge point
    at = np.flatnonzero(~np.isnan(edges.drop))
    p = edges.partner[at]
    assert (p >= 0).all() and (edges.region[p] != edges.region[at]).all()
    d = np.hypot(*(X[p, :2] - X[at, :2]).T)
    assert np.allclose(edges.drop[at], X[at, 2] - (X[p, 2] + d), atol=1e-9)
    assert (edges.partner[np.isnan(edges.drop)] == -1).all()
    # areas, on 3 m cells: each footprint and a margin of up to a cell around it
    area = edges.areas(3.0)
    assert 900 <= area[r[1]] < 900 * 1.5 and 225 <= area[r[2]] < 225 * 1.7 and 3000 <= area[r[3]] < 3000 * 1.3, area[r]
    assert edges.areas(3.0) is area
    assert area.sum() >= 120 * 120 * 0.95
    perm = np.random.default_rng(2).permutation(len(X))
    again = LocalGround.build(X[perm], np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner[perm],
                              owner_ids=ids).edges(3.0, 45.0, 0.5)
    for k in (1, 2, 3):
        assert again.enclosure(int(again.owner_region[k]), 2.5) == edges.enclosure(int(r[k]), 2.5)
        assert again.areas(3.0)[again.owner_region[k]] == area[r[k]]


def test_surface_enclosure_and_area_predicates():
    """The predicates 'surface_enclosure' and 'surface_area' measure the continuous surface a
    cluster is part of; undefined (the check fails and says why) off the surface, and for the
    enclosure where the surface drops nowhere by min_drop."""
    from kbs.knowledge.predicates import Cluster, Ground, Scene

    X, owner = _street_roof_corner_and_step()
    ids = ("c0", "c1", "c2", "c3")
    model = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3), owners=owner, owner_ids=ids)
    scene = Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=model)
    registry = PredicateRegistry.default(entry_points_too=False)
    enclosure, area = registry.get("surface_enclosure"), registry.get("surface_area")
    assert enclosure.unit == "ratio" and area.unit == "area" and area.unit_label("m") == "m²"
    ep = {"gap": 3.0, "slope": 45.0, "step": 0.5, "min_drop": 2.5}
    ap = {"gap": 3.0, "slope": 45.0, "step": 0.5, "cell": 3.0}

    def of(k, pred, params):
        return pred.measure(Cluster(ids[k], X[owner == k], np.ones((owner == k).sum())), scene, params)

    assert of(1, enclosure, ep).value > 0.99 and of(3, enclosure, ep).value < 0.02
    assert of(3, enclosure, ep).details["dropping_edge_points"] > 50
    street = of(0, enclosure, ep)
    assert not street.defined and "has no edge dropping by 2.5 or more" in street.undefined
    assert 3000 <= of(3, area, ap).value < 3000 * 1.3 and of(0, area, ap).value > 8000
    off = enclosure.measure(Cluster("c9", X[:10], np.ones(10)), scene, ep)
    assert not off.defined and "not part of the local ground surface" in off.undefined
    assert not area.measure(Cluster("c9", X[:10], np.ones(10)), scene, ap).defined
    # edge_drop over the cluster's own edge points: the terrace's rim stands above the street below
    # it; the street rises to the roof, the terrace and the cut building; a cluster none of whose
    # points meets another surface has no value
    drop = registry.get("edge_drop")
    dp = {"gap": 3.0, "slope": 45.0, "step": 0.5, "stat": "p90", "over": "cluster"}
    assert of(3, drop, dp).value > 5.0 and of(0, drop, dp).value < -5.0
    inner = (owner == 3) & (X[:, 0] > 45)
    lone = drop.measure(Cluster("c3", X[inner], np.ones(inner.sum())), scene, dp)
    assert lone.defined  # measured on the cluster's points in the surface (c3's), not on the points given
    split = LocalGround.build(X, np.arange(len(X)), np.array([0, 0, 1.0]), np.zeros(3),
                              owners=np.where(inner, 4, owner), owner_ids=ids + ("c4",))
    far = drop.measure(Cluster("c4", X[inner], np.ones(inner.sum())),
                       Scene(np.zeros(3), Ground(np.array([0, 0, 1.0]), np.zeros(3), "fixed"), "m", ground_model=split), dp)
    assert not far.defined and "none of its points meets another continuous surface within 3" in far.undefined


@pytest.mark.parametrize("exclude", [None, "c1"])
def test_compiled_slope_surface_equals_the_k_d_tree_reference(monkeypatch, exclude):
    """LocalGround.height_above_slope, compiled (a grid of cells of side just over the radius)
    against the k-d tree reference (query_ball_point): equal values, bit for bit, on a lattice
    where many surface points lie exactly at the radius (3-4-5 triangles) and duplicates of one
    position carry other heights, with queries far outside the surface and on its edges."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", True)
    monkeypatch.setattr(LocalGround, "PRUNE", False)  # the plain grid (the pruned one: the test below)
    rng = np.random.default_rng(21)
    g = np.arange(0.0, 40.0, 1.0)
    xy = np.array([(a, b) for a in g for b in g])
    xy = np.vstack([xy, xy[::7]])  # duplicated positions, other heights
    X = np.column_stack([xy, rng.normal(0, 1.0, len(xy))])
    owners = (X[:, 0] // 10).astype(int)
    model = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=8,
                              radius=2.5, owners=owners, owner_ids=("c0", "c1", "c2", "c3"))
    P = np.vstack([X[::3] + [0.0, 0.0, 3.0], [[200.0, 200.0, 0.0], [-5.0, 20.0, 1.0], [44.0, 39.0, 0.0],
                                                [np.nextafter(-5.0, 0.0), 0.0, 0.0]]])
    for radius in (5.0, 2.5, 30.0):
        got = model.height_above_slope(P, 40.0, radius, exclude)
        assert model._slope_grid(radius) is not None  # the compiled path ran
        monkeypatch.setattr(_flags, "JIT", False)
        want = model.height_above_slope(P, 40.0, radius, exclude)
        monkeypatch.setattr(_flags, "JIT", True)
        np.testing.assert_array_equal(got, want)
        assert np.isnan(got[-4]) and np.isfinite(got[:-4]).mean() > 0.5
    # an extent absurd for the radius: no grid, the k-d tree answers
    far = LocalGround.build(np.array([[0.0, 0, 0], [1e7, 0, 0], [0, 1e7, 0]]), np.arange(3), np.array([0.0, 0, 1]),
                            np.zeros(3), radius=1.0)
    assert far._slope_grid(1.0) is None
    assert far.height_above_slope(np.array([[0.5, 0.0, 2.0]]), 40.0, 1.0)[0] == pytest.approx(2.0 - np.tan(np.radians(40)) * 0.5)


@pytest.mark.parametrize("exclude", [None, "c1"])
def test_pruned_slope_surface_equals_the_plain_grid_and_the_k_d_tree(monkeypatch, exclude):
    """LocalGround.height_above_slope visiting finer cells lowest bound first (the default, the
    airborne rules' above_terrain/on_terrain/bank) against the plain grid and against the k-d
    tree reference: equal bit for bit, on a lattice with points exactly at the radius,
    duplicated positions of other heights, equal heights and zeros of either sign, queries far
    outside and on the edges, a steep and a zero slope."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", True)
    rng = np.random.default_rng(5)
    g = np.arange(0.0, 60.0, 1.0)
    xy = np.array([(a, b) for a in g for b in g])
    xy = np.vstack([xy, xy[::5], rng.random((500, 2)) * 60.0])
    z = np.round(rng.normal(0, 2.0, len(xy)), 1)  # equal heights, zeros
    z[::11] = -0.0
    X = np.column_stack([xy, z])
    owners = (X[:, 0] // 15).astype(int)
    model = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3), owners=owners,
                              owner_ids=("c0", "c1", "c2", "c3"))
    P = np.vstack([X[::4] + [0.3, -0.2, 4.0], rng.random((300, 3)) * [100, 100, 10] - [20, 20, 0],
                   [[500.0, 500.0, 0.0], [-31.0, 10.0, 0.0]]])
    visited = 0
    for radius in (30.0, 10.0, 2.5, 1.0):
        for slope in (40.0, 65.0, 0.0):
            got = model.height_above_slope(P, slope, radius, exclude)
            visited += model._slope_cells(radius) is not None
            monkeypatch.setattr(LocalGround, "PRUNE", False)
            plain = model.height_above_slope(P, slope, radius, exclude)
            monkeypatch.setattr(_flags, "JIT", False)
            want = model.height_above_slope(P, slope, radius, exclude)
            monkeypatch.setattr(_flags, "JIT", True)
            monkeypatch.setattr(LocalGround, "PRUNE", True)
            assert got.tobytes() == plain.tobytes() == want.tobytes(), (radius, slope)
            assert np.isfinite(got).mean() > 0.3
    assert visited >= 9  # the pruned kernel ran (the finest grid may be refused as too large)


def test_a_surface_whose_box_is_mostly_empty_gets_the_plain_grid_with_the_same_bits(monkeypatch):
    """Two patches of ground 2 km apart (airborne samples side by side): the finer cells of the
    pruned slope surface would be mostly empty, more than SLOPE_CELLS_PER_POINT per surface
    point, so the plain grid answers; the values are those of the pruned path (the cap raised)
    and of the k-d tree, bit for bit."""
    from kbs.inference import _flags

    monkeypatch.setattr(_flags, "JIT", True)
    rng = np.random.default_rng(9)
    patch = rng.random((2000, 2)) * 60.0
    xy = np.vstack([patch, patch + [2000.0, 0.0]])
    X = np.column_stack([xy, np.round(rng.normal(0, 2.0, len(xy)), 2)])
    model = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3))
    P = np.vstack([X[::7] + [0.2, -0.1, 3.0], [[1000.0, 30.0, 0.0]]])
    got = model.height_above_slope(P, 40.0, 10.0)
    assert model._slope_cells(10.0) is None and model._slope_grid(10.0) is not None  # 4,000 points, 824 x 24 cells of 2.5 m
    monkeypatch.setattr(LocalGround, "SLOPE_CELLS_PER_POINT", 1000)
    fresh = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3))
    pruned = fresh.height_above_slope(P, 40.0, 10.0)
    assert fresh._slope_cells(10.0) is not None
    monkeypatch.setattr(_flags, "JIT", False)
    want = fresh.height_above_slope(P, 40.0, 10.0)
    assert got.tobytes() == pruned.tobytes() == want.tobytes()
    assert np.isnan(got[-1]) and np.isfinite(got[:-1]).all()


def test_pruned_slope_kernel_equals_the_plain_kernel_on_random_surfaces():
    """_compiled.slope_lowest_pruned against slope_lowest: the same minimum bit for bit, on
    random surfaces (continuous and rounded positions, zero heights), radii, slopes and owners."""
    from kbs.inference import _compiled as C

    rng = np.random.default_rng(1)
    checked = 0
    for trial in range(24):
        m = int(rng.integers(1, 4000))
        T = rng.random((m, 2)) * rng.choice([10.0, 100.0, 400.0])
        if trial % 3 == 0:
            T = np.round(T)
        h = rng.normal(size=m) * rng.choice([0.1, 3.0, 30.0])
        h[:: 1 + trial % 7] = 0.0
        owners = rng.integers(0, 20, m).astype(np.int64)
        Q = np.vstack([T[rng.integers(0, m, 200)] + rng.normal(size=(200, 2)), rng.random((50, 2)) * 500 - 50])
        for r in (3.0, 10.0, 30.0):
            ny2, st2, o2, lo2, hm, box = C.slope_cells(T, h, r / 4, 4.0 * m + 4096)
            if ny2 < 0:
                continue
            ny, st, o, lo = C.surface_grid(T, r * 1.001, 4.0 * m + 4096)
            for rise in (0.0, 0.84, 2.14):
                for own in (-1, 3):
                    ow = owners if own >= 0 else np.zeros(0, np.int64)
                    a = C.slope_lowest(Q, T, h, ow, own, ny, st, o, lo, r * 1.001, rise, r * r)
                    b = C.slope_lowest_pruned(Q, T, h, ow, own, ny2, st2, o2, lo2, r / 4, hm, box, rise, r, r * r)
                    assert a.tobytes() == b.tobytes(), (trial, r, rise, own)
                    checked += 1
    assert checked > 200


def test_height_bounds_hold_every_answer_of_the_query():
    """LocalGround.height_bounds: the surface height a query gives under a point lies within the
    bounds of its cell block; where no surface point lies within the radius, both say so."""
    rng = np.random.default_rng(8)
    X = np.column_stack([rng.uniform(0, 60, 8000), rng.uniform(0, 60, 8000), rng.normal(0, 0.3, 8000)])
    X[:, 2] += 0.05 * X[:, 0]  # a slope: the bounds must follow it
    model = LocalGround.build(X, np.arange(0, 8000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16,
                              radius=3.0)
    P = np.vstack([X[1::2], [[200.0, 200.0, 0.0], [-3.5, 30.0, 0.0], [63.2, 10.0, 1.0]]])  # far, near the edges
    lo, hi = model.height_bounds(P)
    ground, _ = model.query(P)
    known = ~np.isnan(ground)
    assert known.sum() > 3900 and np.all(lo[known] <= ground[known]) and np.all(ground[known] <= hi[known])
    assert lo[-3] == np.inf and hi[-3] == -np.inf and np.isnan(ground[-3])
    assert (hi - lo)[known].max() < 0.05 * 12 + 3.0  # a block, not the whole surface
    # a dense surface: the fine cells (radius / 6) hold the neighbours, and bound more tightly
    D = np.column_stack([rng.uniform(0, 20, 20000), rng.uniform(0, 20, 20000), rng.normal(0, 0.05, 20000)])
    D[:, 2] += 0.2 * D[:, 0]
    dense = LocalGround.build(D, np.arange(0, 20000, 2), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16,
                              radius=3.0)
    lo, hi = dense.height_bounds(D[1::2])
    ground, _ = dense.query(D[1::2])
    assert np.all(lo <= ground) and np.all(ground <= hi)
    assert np.median(hi - lo) < 1.2  # a 7 x 7 block of 0.5 m cells (3.5 m of slope: 0.7 m), not 9 m (1.8 m)
    # an extent absurd for the radius: no grid, the callers ask the surface for every point
    far = LocalGround.build(np.array([[0.0, 0, 0], [1e7, 0, 0], [0, 1e7, 0]]), np.arange(3), np.array([0.0, 0, 1]),
                            np.zeros(3), radius=1.0)
    assert far.height_bounds(P) is None


def _bound_surfaces(shared_data):
    """Surfaces for the bounds' tests: a tilted random one, three points, points on cell edges
    (a lattice of the fine cells' side), and the SemanticKITTI scan's ground."""
    rng = np.random.default_rng(31)
    X = np.column_stack([rng.uniform(0, 60, 8000), rng.uniform(0, 60, 8000), rng.normal(0, 0.3, 8000)])
    X[:, 2] += 0.05 * X[:, 0]
    g = np.arange(0.0, 12.0, 0.5)  # on the edges of cells of radius / 6 = 0.5
    L = np.column_stack([np.repeat(g, g.size), np.tile(g, g.size), rng.choice([-0.0, 0.0, 0.2], g.size ** 2)])
    K = np.load(shared_data / "semantickitti" / "000001.points.npy")[:, :3].astype(np.float64)
    labels = np.load(shared_data / "semantickitti" / "000001.labels.npy").ravel()
    return {"random": X, "three": X[:3] * [0.03, 0.03, 1.0], "lattice": L, "semantickitti": K[np.isin(labels, [9, 10, 11, 12, 17])]}


@pytest.mark.parametrize("surface", ["random", "three", "lattice", "semantickitti"])
def test_compiled_bound_grids_and_bounds_are_the_numpy_ones(shared_data, monkeypatch, surface):
    """LocalGround.height_bounds compiled (surface_blocks: one pass over the points, no sort;
    surface_bounds: no temporaries) against the numpy reference: the same block grids and the
    same bounds, for points inside, on cell edges, outside the grid and NaN."""
    from kbs.inference import _compiled, _flags

    X = _bound_surfaces(shared_data)[surface]
    model = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16, radius=3.0)
    T = model.tree.data
    assert np.array_equal(model.plane, T)  # the plane coordinates the grids use are the tree's
    lo, hi = model._plane_bounds
    assert np.array_equal(model.tree.mins, lo) and np.array_equal(model.tree.maxes, hi)
    monkeypatch.setattr(_flags, "JIT", False)
    for side, reach in ((3.0 * 1.001, 1), (0.5, 3)):
        ref = model._block_grid(side, reach)
        got = _compiled.surface_blocks(T, model.heights, ref.origin, side, *ref.shape, reach)
        for a, b in zip(ref.blocks, got):
            np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(32)
    lo_xy, hi_xy = X[:, :2].min(axis=0) - 5.0, X[:, :2].max(axis=0) + 5.0
    P = np.vstack([X[::3], np.column_stack([rng.uniform(lo_xy, hi_xy, (3000, 2)), rng.normal(0, 1, 3000)]),
                   [[np.nan, 0.0, 0.0], [1e12, 0.0, 0.0], [X[0, 0] + 0.5, X[0, 1], 0.0]]])
    ref = model.height_bounds(P)
    monkeypatch.setattr(_flags, "JIT", True)
    model2 = LocalGround.build(X, np.arange(len(X)), np.array([0.0, 0.0, 1.0]), np.zeros(3), neighbours=16, radius=3.0)
    got = model2.height_bounds(P)
    np.testing.assert_array_equal(ref[0], got[0])
    np.testing.assert_array_equal(ref[1], got[1])
    assert np.isfinite(got[0]).sum() > len(X[::3]) * 0.9


@pytest.mark.parametrize("reach", [1, 3])
def test_block_reductions_are_those_of_every_block(reach):
    """The separable block minimum, maximum and sum of the bounds' grids equal a direct loop over
    each cell's (2 reach + 1)^2 block (cells beyond the edges left out)."""
    from kbs.geometry.groundmodel import _slide

    rng = np.random.default_rng(reach)
    A = rng.normal(size=(9, 13))
    A[rng.random(A.shape) < 0.3] = np.inf
    for op, red in ((np.minimum, np.min), (np.maximum, np.max), (np.add, np.sum)):
        B = np.where(np.isinf(A), 0.0, A) if op is np.add else A
        want = np.array([[red(B[max(i - reach, 0):i + reach + 1, max(j - reach, 0):j + reach + 1])
                          for j in range(A.shape[1])] for i in range(A.shape[0])])
        np.testing.assert_allclose(_slide(B, reach, op), want)


@pytest.mark.slow
def test_post_steps_ask_only_for_the_points_the_bounds_leave_open(monkeypatch, shared_data):
    """ground_contact and ground_release skip the surface query of points whose bounds decide
    their outcome: the result is the same as asking for every point (SemanticKITTI, outdoor)."""
    X = np.load(shared_data / "semantickitti" / "000001.points.npy")[:, :3].astype(np.float64)
    rb = load_rule_base("outdoor")
    asked = []
    real = LocalGround.query
    monkeypatch.setattr(LocalGround, "query", lambda self, P, exclude=None, **kw: asked.append(len(P)) or real(self, P, exclude, **kw))
    fast = Interpreter(rb).run(X)
    n_fast = sum(asked)
    asked.clear()
    monkeypatch.setattr(LocalGround, "height_bounds", lambda self, P: None)
    full = Interpreter(rb).run(X)
    assert n_fast < 0.9 * sum(asked)
    np.testing.assert_array_equal(fast.cluster, full.cluster)
    np.testing.assert_array_equal(fast.label, full.label)
    assert sum(r.contact for r in full.explanation.records.values()) > 0
    assert [r.released for r in fast.explanation.records.values()] == [r.released for r in full.explanation.records.values()]
