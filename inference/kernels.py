"""Pure numerical kernels of the inference motor (arrays in, arrays out; no state).

Every quantity that can overflow is handled in the log domain (see ALGORITHMS.md section 1):
memberships are a softmax over clusters of ``-log d / (m - 1)``, log-determinants come from the
(floored) eigenvalues, Mahalanobis distances from a whitening matrix.

Layout: inside the engine, per-point-per-cluster arrays are stored **clusters first**, (K, n),
so that every reduction over clusters is an element-wise operation between contiguous rows
(several times faster than reducing a short last axis). Shapes: ``X`` (n, D) points and
``XT`` (D, n) the same transposed, ``w`` (n,) weights, ``u`` (K, n) memberships,
``centers`` (K, D), ``cov`` (K, D, D). Public results are transposed back to (n, K).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from kbs.inference import _flags

#: the smallest positive normal float64: squared distances are clamped here, so that a point
#: sitting exactly on a prototype gets a finite (dominant) membership instead of a division by 0.
TINY = float(np.finfo(np.float64).tiny)


def gg_memberships_from_maha(maha: np.ndarray, logdet: np.ndarray, log_priors: np.ndarray, m: float) -> np.ndarray:
    """Gath-Geva memberships (K, n) from squared Mahalanobis distances (K, n): the softmax over
    clusters of ``-log d_e2 / (m - 1)`` with ``log d_e2 = logdet/2 - log P + maha/2``, fused into
    as few passes as possible (this is the hot loop). ``maha`` is not modified."""
    a = -0.5 / (m - 1.0)
    z = maha * a
    z -= ((0.5 * logdet - log_priors) / (m - 1.0))[:, None]
    z -= z.max(axis=0)
    np.exp(z, out=z)
    z /= z.sum(axis=0)
    return z


def memberships_from_sq_dist(d2: np.ndarray, m: float) -> np.ndarray:
    """Memberships (K, n) from squared distances (K, n) without logarithms: with
    ``r_k = (d_min / d_k)^(1/(m-1))`` in (0, 1], ``u_k = r_k / sum r``. ``d2`` is overwritten."""
    d2 = np.maximum(d2, TINY, out=d2)
    r = np.divide(d2.min(axis=0), d2, out=d2)
    if m != 2.0:
        r **= 1.0 / (m - 1.0)
    r /= r.sum(axis=0)
    return r


def sq_euclidean(XT: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances (K, n) from points ``XT`` (D, n), by explicit differences (no
    cancellation, unlike the expanded |x|^2 - 2 x.c + |c|^2)."""
    d = XT[None, :, :] - centers[:, :, None]
    d *= d
    return d.sum(axis=1)


def powered(u: np.ndarray, power: float) -> np.ndarray:
    """``u ** power`` with the common powers done by multiplication (much faster than pow)."""
    if power == 1.0:
        return u
    if power == 2.0:
        return u * u
    return u**power


@dataclass(frozen=True)
class Moments:
    """Per-sample sufficient statistics of a (possibly voxel-reduced) fitting set.

    ``stats`` holds, per sample, ``[w, w x, w x x^T + scatter]`` (1 + D + D*D columns; the
    within-voxel scatter is added when the set is a voxel reduction), so that centres and fuzzy
    covariances are one matrix product per iteration each, whatever the number of clusters.
    ``rows`` is the same for 3D points as (10, n) rows, the layout of the compiled kernels. Both
    are computed when first used. ``X`` should be centred (the driver does it) to keep the moment
    formula exact.
    """

    X: np.ndarray  # (n, D)
    XT: np.ndarray  # (D, n)
    w: np.ndarray  # (n,)
    scatter: np.ndarray | None = None  # (n, D, D)

    @classmethod
    def build(cls, X: np.ndarray, w: np.ndarray, scatter: np.ndarray | None = None) -> Moments:
        X = np.ascontiguousarray(X, dtype=np.float64)
        w = np.ascontiguousarray(w, dtype=np.float64)
        return cls(X=X, XT=np.ascontiguousarray(X.T), w=w, scatter=scatter)

    @cached_property
    def first(self) -> np.ndarray:
        """(n, 1 + D): ``[w, w x]``."""
        return np.column_stack([self.w, self.X * self.w[:, None]])

    @cached_property
    def stats(self) -> np.ndarray:
        """(n, 1 + D + D*D): ``[w, w x, w x x^T + scatter]``."""
        n, D = self.X.shape
        X, w = self.X, self.w
        second = (w[:, None, None] * (X[:, :, None] * X[:, None, :])).reshape(n, D * D)
        if self.scatter is not None:
            second = second + self.scatter.reshape(n, D * D)
        return np.ascontiguousarray(np.column_stack([self.first, second]))

    @cached_property
    def rows(self) -> np.ndarray:
        """The moments as (10, n) rows ``[w, w x (3), w x x^T + scatter (6: xx xy xz yy yz zz)]``
        for 3D points: the layout of the compiled kernels."""
        XT, w = self.XT, self.w
        R = np.empty((10, self.n))
        R[0] = w
        np.multiply(XT, w, out=R[1:4])
        for r, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), start=4):
            np.multiply(R[1 + a], XT[b], out=R[r])
            if self.scatter is not None:
                R[r] += self.scatter[:, a, b]
        return R

    @property
    def n(self) -> int:
        return int(self.X.shape[0])

    @property
    def wX(self) -> np.ndarray:
        return self.first[:, 1:]

    def centers(self, u: np.ndarray, power: float) -> np.ndarray:
        """Centres ``sum w u^p x / sum w u^p`` (K, D) for memberships ``u`` (K, n)."""
        S = powered(u, power) @ self.first
        return S[:, 1:] / np.maximum(S[:, :1], TINY)


def fuzzy_covariances(mom: Moments, u: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fuzzy covariances ``F_i = sum_j w_j u_ij (x_j - v_i)(x_j - v_i)^T / sum_j w_j u_ij``.

    Memberships ``u`` (K, n) enter with power 1 (Gath-Geva); ``centers`` may have been computed
    with another power. Returns ``(cov (K, D, D), mass (K,))`` with ``mass_i = sum_j w_j u_ij``.
    """
    K, D = centers.shape
    S = u @ mom.stats
    mass, s1, s2 = S[:, 0], S[:, 1 : 1 + D], S[:, 1 + D :].reshape(K, D, D)
    # sum u w (x - v)(x - v)^T = S2 - v s1^T - s1 v^T + mass v v^T
    vs1 = centers[:, :, None] * s1[:, None, :]
    cov = s2 - vs1 - vs1.transpose(0, 2, 1) + mass[:, None, None] * (centers[:, :, None] * centers[:, None, :])
    cov /= np.maximum(mass, TINY)[:, None, None]
    return 0.5 * (cov + cov.transpose(0, 2, 1)), mass


@dataclass(frozen=True)
class FlooredGaussians:
    """Covariances with floored eigenvalues, and what the distances need from them."""

    eigenvalues: np.ndarray  # (K, D) ascending, floored
    eigenvectors: np.ndarray  # (K, D, D) columns
    whitening: np.ndarray  # (K, D, D): maha = |(x - v) @ W|^2
    logdet: np.ndarray  # (K,)

    @property
    def covariances(self) -> np.ndarray:
        """The floored covariances ``V diag(lambda) V^T`` (K, D, D)."""
        V = self.eigenvectors
        return np.einsum("kij,kj,klj->kil", V, self.eigenvalues, V)

    def subset(self, keep: np.ndarray) -> FlooredGaussians:
        return FlooredGaussians(self.eigenvalues[keep], self.eigenvectors[keep], self.whitening[keep],
                                self.logdet[keep])


def floor_covariances(cov: np.ndarray, min_variance: float, max_condition: float) -> FlooredGaussians:
    """Floor the eigenvalues of each covariance at ``max(min_variance, lambda_max / max_condition)``.

    Planar and linear clusters make ``F`` singular; the same floored ``F`` must then be used in the
    distance, the log-determinant and the validity criteria.
    """
    lam, vec = np.linalg.eigh(cov)
    floor = np.maximum(min_variance, lam[:, -1:] / max_condition)
    lam = np.maximum(lam, floor)
    whitening = vec / np.sqrt(lam)[:, None, :]
    return FlooredGaussians(
        eigenvalues=lam, eigenvectors=vec, whitening=whitening, logdet=np.log(lam).sum(axis=1)
    )


def mahalanobis_sq(XT: np.ndarray, centers: np.ndarray, whitening: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances (K, n) of points ``XT`` (D, n), one matrix product for all
    clusters: ``|W_k^T (x - v_k)|^2``."""
    K, D = centers.shape
    WT = whitening.transpose(0, 2, 1).reshape(K * D, D)  # rows: W_k^T
    Y = WT @ XT  # (K*D, n)
    Y -= np.einsum("kde,kd->ke", whitening, centers).reshape(K * D, 1)
    Y *= Y
    return Y.reshape(K, D, -1).sum(axis=1)


def validity(u: np.ndarray, w: np.ndarray, maha: np.ndarray, logdet: np.ndarray) -> tuple[float, float, float]:
    """Gath-Geva validity criteria ``(FHV, PD, APD)`` of one partition (``u``, ``maha`` (K, n)).

    Central members of cluster i are the points with squared Mahalanobis distance < 1;
    ``S_i`` is the sum of their (weighted) memberships.
    FHV = sum_i sqrt(det F_i); PD = sum_i S_i / FHV; APD = mean_i S_i / sqrt(det F_i).
    """
    if _flags.JIT and u.flags.c_contiguous and maha.flags.c_contiguous:
        from kbs.inference._compiled import central_sums

        central = central_sums(u, np.ascontiguousarray(w), maha)
    else:
        central = np.where(maha < 1.0, u, 0.0) @ w
    sqrt_det = np.exp(0.5 * logdet)
    fhv = float(sqrt_det.sum())
    pd = float(central.sum() / fhv)
    apd = float(np.mean(central / sqrt_det))
    return fhv, pd, apd
