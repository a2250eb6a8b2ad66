"""kbs.geometry.pca: the one PCA of a point set, against independent references, and the
conventions its callers rely on."""
from __future__ import annotations

import numpy as np
import pytest

from kbs.geometry.pca import covariance, plane_basis, principal_axes


def _cloud(seed: int = 0, n: int = 500) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return (rng.normal(size=(n, 3)) * [3.0, 1.0, 0.05]) @ R.T + [100.0, -40.0, 7.0]


@pytest.mark.parametrize("ddof", [0, 1])
def test_covariance_is_numpys_of_the_points(ddof):
    P = _cloud()
    c, C = covariance(P, ddof=ddof)
    np.testing.assert_allclose(c, P.mean(axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(C, np.cov(P, rowvar=False, ddof=ddof), rtol=1e-10, atol=1e-14)
    brute = sum(np.outer(p - c, p - c) for p in P) / (len(P) - ddof)
    np.testing.assert_allclose(C, brute, rtol=1e-10, atol=1e-14)


def test_weighted_covariance_is_the_weighted_population_one():
    P = _cloud(1, 200)
    w = np.random.default_rng(2).random(len(P))
    c, C = covariance(P, weights=w)
    np.testing.assert_allclose(c, np.average(P, axis=0, weights=w), rtol=0, atol=1e-12)
    np.testing.assert_allclose(C, np.cov(P, rowvar=False, aweights=w, bias=True), rtol=1e-10, atol=1e-14)
    c0, _ = covariance(P, weights=np.zeros(len(P)))  # no weight: all points count alike
    np.testing.assert_allclose(c0, P.mean(axis=0), atol=1e-12)


def test_eigenpairs_sorted_normal_and_thickness():
    P = _cloud(3)
    pca = principal_axes(P)
    assert np.all(np.diff(pca.eigenvalues) > 0)
    np.testing.assert_allclose(pca.covariance @ pca.eigenvectors, pca.eigenvectors * pca.eigenvalues, atol=1e-10)
    d = (P - pca.center) @ pca.normal  # the thinnest direction: the spread across the plane
    assert pca.thickness == pytest.approx(np.sqrt(np.mean(d**2)), rel=1e-9)
    assert pca.in_plane.shape == (3, 2)
    np.testing.assert_allclose(pca.in_plane.T @ pca.normal, 0.0, atol=1e-12)


def test_the_divisor_moves_eigenvalues_not_eigenvectors():
    """Why callers that read only directions may take either divisor, and those that read the
    thickness must keep theirs: n / (n - 1) scales the eigenvalues, the eigenvectors stay."""
    P = _cloud(4, 50)
    a, b = principal_axes(P, ddof=0), principal_axes(P, ddof=1)
    np.testing.assert_allclose(b.eigenvalues, a.eigenvalues * 50 / 49, rtol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(a.eigenvectors * b.eigenvectors, axis=0)), 1.0, atol=1e-12)
    assert b.thickness > a.thickness


def test_same_numbers_as_the_formulas_it_replaced():
    """Bit for bit where a caller's numbers are stored (the robust plane's thickness, the report's
    eigen-boxes and ground mesh, the weighted figure axes); the normal to rounding where the points
    were not centred first (evaluation, render, SegComp normals)."""
    P = _cloud(5, 1000)
    c = P.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((P - c).T))  # groundplane, report/meshes: ddof=1
    b = principal_axes(P, ddof=1)
    assert np.array_equal(b.center, c) and np.array_equal(b.eigenvalues, w) and np.array_equal(b.eigenvectors, v)
    w0, v0 = np.linalg.eigh(np.cov(P - c, rowvar=False, bias=True))  # report/html eigen-boxes
    a = principal_axes(P)
    assert np.array_equal(a.eigenvalues, w0) and np.array_equal(a.eigenvectors, v0)
    wt = np.random.default_rng(6).random(len(P))  # report/figures cluster_axes
    ws = wt / wt.sum()
    cw = ws @ P
    assert np.array_equal(principal_axes(P, weights=wt).covariance, (P - cw).T @ ((P - cw) * ws[:, None]))
    n_old = np.linalg.eigh(np.cov(P.T))[1][:, 0]  # not centred first
    assert abs(float(n_old @ a.normal)) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("normal", [[0, 0, 1], [1, 0, 0], [0.3, -0.5, 0.8], [1e-9, 1, 0]])
def test_plane_basis_is_orthonormal_and_spans_the_plane(normal):
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    B = plane_basis(n)
    np.testing.assert_allclose(B @ B.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(B @ n, 0.0, atol=1e-12)
    assert np.linalg.det(np.vstack([B, n])) == pytest.approx(1.0)  # right-handed (e1, e2, n)
