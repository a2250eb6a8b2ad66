"""Cluster geometry: fuzzy centre, fuzzy covariance, its eigen-decomposition, best approximating
plane (BAP) and thickness (ALGORITHMS.md section 2). Used by the knowledge module's predicates.

The covariance here is the raw one (two-pass, no eigenvalue floor): the floor is a numerical
device of the clustering, and must not hide how thin a planar cluster really is.

A cluster is **degenerate** when its covariance has rank < 2: its points lie on a line (or are
all at one position). It has no best approximating plane: any plane through the line fits it, so
its normal, and any angle measured from it, is undefined (:attr:`ClusterGeometry.degenerate`).
The rank is counted up to a relative tolerance on the spreads ``sigma_i = sqrt(mu_i)``:

- ``sigma_2 <= RANK_TOLERANCE * sigma_3`` (1e-5): across the line, less than a hundred-thousandth
  of the spread along it. Rounding leaves less on a straight line: the eigenvalues of the 3 x 3
  covariance are exact to about ``eps * mu_3``, i.e. sigma_2 / sigma_3 ~ 1e-8 in float64; a line
  of length L stored in float32 (KITTI ``.bin``, most PCD and PLY files: one rounding step is
  6e-8 to 1.2e-7 of the coordinate R) gets sigma_2 / sigma_3 ~ 1e-7 R / L, within the tolerance
  up to R ~ 80 L (a 1 m pole 80 m from the origin). The thinnest real cluster judged in the
  quality benchmarks (SemanticKITTI, GndNet, the six ISPRS samples with the outdoor and airborne
  rule bases, the five mOSD scenes: 11,900 clusters) has sigma_2 / sigma_3 = 3.0e-3, 300 times
  the tolerance.
- ``sigma_3 <= COINCIDENT_TOLERANCE * max|centre|`` (1e-12, about 5,000 float64 rounding steps
  of the coordinates): every point at one position.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from kbs.inference import _flags

from kbs.errors import FitError

#: sigma_2 / sigma_3 at or below which a cluster's points lie on a line (see the module's doc)
RANK_TOLERANCE = 1e-5
#: sigma_3 / max|centre| at or below which a cluster's points are all at one position
COINCIDENT_TOLERANCE = 1e-12


@dataclass(frozen=True)
class ClusterGeometry:
    """Shape of one (fuzzy) cluster.

    Attributes
    ----------
    center : ndarray (D,)
        Fuzzy centre ``sum w u^p x / sum w u^p``.
    covariance : ndarray (D, D)
        Fuzzy covariance ``sum w u (x - c)(x - c)^T / sum w u``.
    eigenvalues : ndarray (D,)
        ``mu1 <= mu2 <= mu3`` (clipped at 0).
    eigenvectors : ndarray (D, D)
        Columns ``e1, e2, e3`` matching the eigenvalues.
    mass : float
        Effective size ``sum w u``.
    """

    center: np.ndarray
    covariance: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    mass: float

    @functools.cached_property
    def rank(self) -> int:
        """Rank of the covariance up to :data:`RANK_TOLERANCE` (0: every point at one position,
        1: on a line, 2: on a plane, 3: a volume); computed once (a cluster's records and
        predicates ask for it about four times)."""
        sigma = np.sqrt(self.eigenvalues)
        floor = COINCIDENT_TOLERANCE * float(np.max(np.abs(self.center), initial=0.0))
        if sigma[-1] <= floor:
            return 0
        tol = max(RANK_TOLERANCE * float(sigma[-1]), floor)
        return int(np.count_nonzero(sigma > tol))

    @property
    def degenerate(self) -> bool:
        """Whether it has no best approximating plane (rank < 2: a line, or one position): its
        :attr:`normal` is then an arbitrary direction and no angle can be measured from it."""
        return self.rank < 2

    @property
    def degeneracy(self) -> str | None:
        """What is degenerate about it, in words ('its points lie on a line'), or None."""
        return {0: "its points are all at one position", 1: "its points lie on a line"}.get(self.rank)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal ``e1`` of the best approximating plane (sign: pointing to +z when possible).
        For a :attr:`degenerate` cluster, an arbitrary direction across its line."""
        n = self.eigenvectors[:, 0]
        return -n if n[-1] < 0 else n

    @property
    def thickness(self) -> float:
        """``sqrt(mu1)``: the spread across the best approximating plane, in length units."""
        return float(np.sqrt(self.eigenvalues[0]))

    @property
    def plane(self) -> tuple[np.ndarray, float]:
        """Best approximating plane as ``(n, d)`` with ``n . x + d = 0``, through the centre."""
        n = self.normal
        return n, float(-n @ self.center)

    def distance_to_plane(self, X: np.ndarray) -> np.ndarray:
        """Signed distances (n,) of points to the best approximating plane."""
        n, d = self.plane
        return X @ n + d


def cluster_geometry(
    X: np.ndarray,
    memberships: np.ndarray | None = None,
    sample_weight: np.ndarray | None = None,
    *,
    center_power: float = 2.0,
) -> ClusterGeometry:
    """Geometry of one cluster from its points and (optional) memberships; its arrays are
    read-only (a result).

    Parameters
    ----------
    X : ndarray (n, D)
    memberships : ndarray (n,), optional
        Memberships of the points in the cluster; all ones (a hard cluster) when omitted.
    sample_weight : ndarray (n,), optional
    center_power : float
        Power of the memberships in the centre (Gath-Geva: m = 2).
    """
    X = np.asarray(X, dtype=np.float64)
    n = X.shape[0]
    if X.shape[1] == 3 and _flags.JIT and n:  # compiled: one call, no numpy temporaries
        from kbs.inference._compiled import geometry3

        none = np.zeros(0)
        uc = none if memberships is None else np.ascontiguousarray(memberships, dtype=np.float64)
        wc = none if sample_weight is None else np.ascontiguousarray(sample_weight, dtype=np.float64)
        center, cov, lam, vec, mass = geometry3(np.ascontiguousarray(X), uc, wc, float(center_power))
        if not mass > 0.0:
            raise FitError("cannot describe an empty cluster (no point with a positive membership)")
        return _frozen(center, cov, np.maximum(lam, 0.0), vec, float(mass))
    u = np.ones(n) if memberships is None else np.asarray(memberships, dtype=np.float64)
    w = np.ones(n) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
    uw = u * w
    mass = float(uw.sum())
    if n == 0 or mass <= 0.0:
        raise FitError("cannot describe an empty cluster (no point with a positive membership)")
    upw = (u**center_power) * w
    center = (upw @ X) / upw.sum()
    diff = X - center
    cov = (diff * uw[:, None]).T @ diff / mass
    cov = 0.5 * (cov + cov.T)
    lam, vec = np.linalg.eigh(cov)
    return _frozen(center, cov, np.maximum(lam, 0.0), vec, mass)


def _frozen(center, cov, lam, vec, mass: float) -> ClusterGeometry:
    """A ClusterGeometry over arrays made here, set read-only."""
    for a in (center, cov, lam, vec):
        a.flags.writeable = False
    return ClusterGeometry(center=center, covariance=cov, eigenvalues=lam, eigenvectors=vec, mass=mass)


def angle_between_planes(n1: np.ndarray, n2: np.ndarray) -> float:
    """Angle in radians in [0, pi/2] between two planes given by their normals (0 = parallel)."""
    c = abs(float(np.dot(n1, n2)) / (np.linalg.norm(n1) * np.linalg.norm(n2)))
    return float(np.arccos(min(1.0, c)))
