"""Principal components of a point set: the one place kbs computes "the PCA of these points" and
the basis of a plane.

Convention (every caller):

- the centre is the mean of the points (or their weighted mean), and the points are centred
  before the covariance is formed;
- the covariance is ``np.cov`` of the centred points with ``ddof=0`` (the population covariance,
  divided by ``n``: the default) or ``ddof=1`` (the sample covariance, divided by ``n - 1``) where
  a caller's numbers were defined with it; with ``weights`` it is the weighted population
  covariance ``sum_i w_i (x_i - c)(x_i - c)^T`` with the weights scaled to sum 1;
- eigenpairs come sorted by increasing eigenvalue (:func:`numpy.linalg.eigh`'s order): column 0
  of the eigenvectors is the normal of the best approximating plane, columns 1 and 2 span it.

The divisor scales the covariance by ``n / (n - 1)``: the eigenvectors are the same (a scaled
symmetric matrix has the same eigenvectors, and ``eigh`` of ``s * C`` returns them in the same
order), the eigenvalues, spreads and thickness are not. A caller that uses only directions may
take either; one that reads eigenvalues keeps the divisor its numbers were defined with.

The engine's fuzzy cluster descriptor (:func:`kbs.inference.cluster_geometry`: membership
weights, a compiled twin) and the batched or compiled kernels keep their own code.

Pure numpy; no kbs import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Principal:
    """The principal components of a point set.

    Attributes
    ----------
    center : ndarray (3,)
    covariance : ndarray (3, 3)
    eigenvalues : ndarray (3,)
        Increasing (as returned by ``eigh``; not floored: may be -1e-17 on a line).
    eigenvectors : ndarray (3, 3)
        Columns, in the order of the eigenvalues.
    """

    center: np.ndarray
    covariance: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        """Unit normal (3,) of the best approximating plane (the least-variance direction)."""
        return self.eigenvectors[:, 0]

    @property
    def in_plane(self) -> np.ndarray:
        """(3, 2): the two principal directions within the plane, by increasing variance."""
        return self.eigenvectors[:, 1:]

    @property
    def thickness(self) -> float:
        """Spread across the plane: ``sqrt`` of the smallest eigenvalue (0 when rounding makes it
        negative)."""
        return float(np.sqrt(max(float(self.eigenvalues[0]), 0.0)))


def covariance(P: np.ndarray, *, ddof: int = 0, weights: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Centre (D,) and covariance (D, D) of points ``P`` (n, D) by the module's convention.

    Parameters
    ----------
    P : ndarray (n, D)
    ddof : {0, 1}
        Divide by ``n - ddof`` (ignored with ``weights``).
    weights : ndarray (n,), optional
        Non-negative; scaled to sum 1 (all equal when they sum to 0).
    """
    P = np.asarray(P, dtype=np.float64)
    if weights is None:
        c = P.mean(axis=0)
        return c, np.cov(P - c, rowvar=False, ddof=ddof)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum() if w.sum() > 0 else np.full(len(P), 1.0 / len(P))
    c = w @ P
    return c, (P - c).T @ ((P - c) * w[:, None])


def principal_axes(P: np.ndarray, *, ddof: int = 0, weights: np.ndarray | None = None) -> Principal:
    """The principal components of points ``P`` (n, 3): centre, covariance (see
    :func:`covariance`), eigenvalues increasing and their eigenvectors as columns."""
    c, cov = covariance(P, ddof=ddof, weights=weights)
    lam, vec = np.linalg.eigh(cov)
    return Principal(center=c, covariance=cov, eigenvalues=lam, eigenvectors=vec)


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Two orthonormal vectors (2, 3) spanning the plane of unit ``normal``: ``e1 = n x a`` with
    ``a`` the axis least aligned with ``n``, ``e2 = n x e1``; deterministic."""
    n = np.asarray(normal, dtype=np.float64)
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])
