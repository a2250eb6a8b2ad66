"""UFP-ONC (Gath & Geva 1989): unsupervised fuzzy partition with an optimal number of clusters.

K = 1, 2, ..., k_max; each K starts from the K-1 solution plus one new prototype, runs fuzzy
c-means then Gath-Geva, and is scored by the fuzzy hypervolume (FHV), the partition density (PD)
and the average partition density (APD). The K chosen is the first local maximum of APD.

Large clouds are fitted on a voxel-grid reduction (centroids weighted by counts, with their
within-voxel scatter; the grid laid in the cloud's own horizontal frame, so that it turns with the
cloud about the vertical) and memberships are then computed for every point in bounded-memory chunks.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from collections.abc import Callable

import numpy as np

from kbs.arrays import rows, minus
from kbs.errors import FitError, ParameterError
from kbs.inference import _flags
from kbs.inference._validation import check_points, check_weights, validate_params
from kbs.inference.engine import (
    DroppedCluster,
    GGState,
    fcm_fit,
    gg_fit,
    gg_memberships,
    memberships_in_chunks,
    new_prototype_memberships,
    worst_point_memberships,
)
from kbs.inference.kernels import FlooredGaussians, Moments, validity
from kbs.inference.settings import DEFAULTS, UFP_ONC_CONSTRAINTS
from kbs.inference.voxel import HorizontalFrame, auto_voxel_size, bounds, ladder_size, voxel_reduce

#: Allowed values of ufp_onc's settings: the table's (:mod:`kbs.inference.settings`).
ENGINE_CONSTRAINTS: dict[str, list] = UFP_ONC_CONSTRAINTS


@dataclass(frozen=True)
class KPartition:
    """The Gath-Geva partition of one K of the sweep.

    ``centers`` and ``covariances`` are in the input's coordinates; covariances are the floored
    ones the distances used. ``fit_memberships`` are those of the fitting set (the voxel centroids
    when the cloud was reduced); memberships of any points come from :meth:`predict_proba`.
    """

    k: int
    centers: np.ndarray  # (K, D)
    covariances: np.ndarray  # (K, D, D)
    priors: np.ndarray  # (K,)
    fhv: float
    pd: float
    apd: float
    n_iter_fcm: int
    n_iter_gg: int
    converged: bool
    seconds: float
    m: float
    fit_memberships: np.ndarray = field(repr=False)  # (n_fit, K)
    offset: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(3))
    gaussians: FlooredGaussians | None = field(repr=False, default=None)

    @property
    def n_iter(self) -> int:
        return self.n_iter_fcm + self.n_iter_gg

    def predict_proba(self, X: np.ndarray, chunk_size: int = 65536) -> np.ndarray:
        """Memberships (n, K) of points ``X`` (input coordinates), computed in chunks of
        ``chunk_size`` rows: memory is O(n K), never O(n K D^2)."""
        centers = self.centers - self.offset
        X = np.asarray(X)
        if (_flags.JIT and X.ndim == 2 and X.shape[1] == 3 and X.shape[0] and X.dtype == np.float64
                and self.gaussians is not None):  # the same chunks, compiled, no transposed copies
            from kbs.inference import _compiled

            return _compiled.gg_predict_rows(np.ascontiguousarray(X), np.ascontiguousarray(self.offset, dtype=np.float64),
                                             np.ascontiguousarray(centers), self.gaussians.whitening,
                                             self.gaussians.logdet, self.priors, float(self.m), int(chunk_size))
        return memberships_in_chunks(
            np.asarray(X), self.offset, lambda XT: gg_memberships(XT, centers, self.gaussians, self.priors, self.m),
            self.k, chunk_size,
        )

    def predict(self, X: np.ndarray, chunk_size: int = 65536) -> np.ndarray:
        """Index of the cluster of highest membership (n,)."""
        return self.predict_proba(X, chunk_size).argmax(axis=1)


@dataclass(frozen=True)
class UFPONCResult:
    """The whole sweep.

    Attributes
    ----------
    partitions : tuple of KPartition
        One per K computed (K = 1, 2, ...).
    chosen_k : int
        First local maximum of APD over the partitions computed.
    memberships : ndarray (n_samples, chosen_k)
        Memberships of every input point in the chosen partition, in input order.
    offset : ndarray (D,)
        The centring offset subtracted before fitting (bounding-box middle).
    n_fit : int
        Size of the fitting set (voxels, or points when not reduced).
    voxel_size : float or None
        Edge of the reduction grid, None when the points were fitted directly.
    stop_reason : str
        'k_max', 'first_max', or 'no_growth' (a new prototype died; see ``notes``).
    notes : tuple of str
        Events worth telling a user (clusters dropped, layers that hit max_iter).
    """

    partitions: tuple[KPartition, ...]
    chosen_k: int
    memberships: np.ndarray = field(repr=False)
    offset: np.ndarray = field(repr=False)
    n_samples: int = 0
    n_fit: int = 0
    voxel_size: float | None = None
    stop_reason: str = "k_max"
    notes: tuple[str, ...] = ()
    seconds: float = 0.0

    def partition(self, k: int) -> KPartition:
        for p in self.partitions:
            if p.k == k:
                return p
        raise ParameterError(f"no partition with K = {k}; computed K = {[p.k for p in self.partitions]}")

    @property
    def best(self) -> KPartition:
        return self.partition(self.chosen_k)

    @property
    def labels(self) -> np.ndarray:
        """Hard labels (n_samples,) of the chosen partition."""
        return self.memberships.argmax(axis=1)

    @property
    def apd_curve(self) -> np.ndarray:
        """Array (n_partitions, 2) of (K, APD)."""
        return np.array([[p.k, p.apd] for p in self.partitions])


def first_local_max(values: list[float] | np.ndarray) -> int:
    """Index of the first local maximum: ``v[i] > v[i-1]`` (or i = 0) and ``v[i] >= v[i+1]`` (or
    i last)."""
    v = list(values)
    for i in range(len(v)):
        if (i == 0 or v[i] > v[i - 1]) and (i == len(v) - 1 or v[i] >= v[i + 1]):
            return i
    return len(v) - 1  # unreachable for a non-empty list


@dataclass(frozen=True)
class FitSet:
    """The centred, canonically ordered (possibly voxel-reduced) weighted set the engine fits."""

    moments: Moments
    offset: np.ndarray
    voxel_size: float | None


def prepare_fit_set(X: np.ndarray, w: np.ndarray, *, max_fit_points: int | None,
                    voxel_size: float | None) -> FitSet:
    """Centre on the bounding-box middle, reduce on a voxel grid when the cloud is large, and put
    the fitting set in a canonical order (so the result does not depend on the point order).

    The grid is laid in the cloud's own :class:`~kbs.inference.voxel.HorizontalFrame` (its
    centroid and principal horizontal axes), not along x and y: a cloud turned about the vertical
    gets the same voxels, in the same order, turned with it, so the partition does not depend on
    the axes the cloud is given in (a grid along x and y changed 4 % of the labels of a
    SemanticKITTI scan turned by 90 degrees). The reduction is then put back in the centred input
    coordinates. A cloud fitted point by point needs no frame: every step of the fit turns with
    the points (their order, by x, y then z, only changes the rounding of the sums). The voxel
    edge, when not given, is the rung of :func:`~kbs.inference.voxel.ladder_size` above the
    counted one, so that the rounding of a turned file does not move it."""
    lo, hi = bounds(X)
    offset = 0.5 * (lo + hi)
    Xc = minus(X, offset)
    reduce = voxel_size is not None or (max_fit_points is not None and X.shape[0] > max_fit_points)
    if reduce and X.shape[1] <= 3:
        frame = HorizontalFrame.of(Xc, w)
        Y = frame.to_frame(Xc)
        size = voxel_size if voxel_size is not None else ladder_size(auto_voxel_size(Y, max_fit_points))
        expect = max_fit_points if voxel_size is None else None
        red = voxel_reduce(Y, size, w, expect=expect)
        while voxel_size is None and len(red) > max_fit_points:  # the size search counts on a finer grid
            size = ladder_size(size, up=1)
            red = voxel_reduce(Y, size, w, expect=expect)
        red = frame.from_frame(red)
        return FitSet(Moments.build(red.centroids, red.weights, red.scatter), offset, red.voxel_size)
    order = _lex_order(Xc)
    return FitSet(Moments.build(rows(Xc, order), w[order]), offset, None)


def _lex_order(X: np.ndarray) -> np.ndarray:
    """``np.lexsort(X.T[::-1])`` (by the first column, then the next ...; ties in input order),
    compiled when the kernels are on (the same permutation: a stable order is unique)."""
    if _flags.JIT and X.dtype == np.float64 and X.ndim == 2 and X.shape[0] > 1:
        from kbs.inference import _compiled

        return _compiled.lex_order(np.ascontiguousarray(X))
    return np.lexsort(X.T[::-1])


def ufp_onc(
    X: np.ndarray,
    k_max: int = DEFAULTS["k_max"],
    *,
    sample_weight: np.ndarray | None = None,
    m: float = DEFAULTS["m"],
    center_power: float | None = DEFAULTS["center_power"],
    tol: float = DEFAULTS["tol"],
    fcm_tol: float = DEFAULTS["fcm_tol"],
    max_iter: int = DEFAULTS["max_iter"],
    fcm_max_iter: int = DEFAULTS["fcm_max_iter"],
    min_variance: float = DEFAULTS["min_variance"],
    max_condition: float = DEFAULTS["max_condition"],
    min_cluster_size: float | None = DEFAULTS["min_cluster_size"],
    new_prototype: str = DEFAULTS["new_prototype"],
    stop: str = DEFAULTS["stop"],
    min_k: int = DEFAULTS["min_k"],
    max_fit_points: int | None = DEFAULTS["max_fit_points"],
    voxel_size: float | None = DEFAULTS["voxel_size"],
    chunk_size: int = DEFAULTS["chunk_size"],
    progress: Callable[[KPartition], None] | None = None,
) -> UFPONCResult:
    """Run UFP-ONC on points ``X`` (n, D) for K = 1 .. k_max.

    The settings' allowed values, defaults and docs are the table of :mod:`kbs.inference.settings`.

    Parameters
    ----------
    X : array-like (n, D)
        Points; any float dtype; finite.
    k_max : int
        Largest K tried.
    sample_weight : array-like (n,), optional
        Per-point weights (e.g. voxel counts).
    m : float
        Fuzzifier (> 1); the seed paper uses 2, where memberships are Gaussian-mixture posteriors.
    center_power : float, optional
        Power of the memberships in the centre update; ``m`` (Gath-Geva's choice) when None,
        1 for the EM-like centre.
    tol, fcm_tol : float
        Stop each layer when ``max |dU| < tol``.
    max_iter, fcm_max_iter : int
        Iteration limits of Gath-Geva and fuzzy c-means.
    min_variance : float
        Absolute eigenvalue floor of the covariances, in squared length units (sensor noise).
    max_condition : float
        Eigenvalue floor relative to the largest: ``lambda >= lambda_max / max_condition``.
    min_cluster_size : float, optional
        A cluster whose effective size ``sum w u`` falls below this dies; default
        ``max(D + 1, 0.001 * total weight)``.
    new_prototype : {'distance', 'worst'}
        How K's extra prototype enters: a constant squared distance ``10 trace(Cov X)`` to every
        point (Gath-Geva's way V), or the point of lowest maximum membership (way W).
    stop : {'k_max', 'first_max'}
        Compute every K up to k_max, or stop as soon as APD's first local maximum is confirmed.
    min_k : int
        Smallest K that may be chosen: the first local maximum is sought among K >= min_k (a
        divisive split asks for 2). Partitions with smaller K are still computed and returned.
    max_fit_points : int, optional
        Clouds larger than this are fitted on a voxel grid sized to at most this many voxels;
        None fits every point.
    voxel_size : float, optional
        Use this voxel edge instead of the automatic one.
    chunk_size : int
        Rows per chunk when computing memberships of all points.
    progress : callable, optional
        Called with each :class:`KPartition` as it is computed.

    Returns
    -------
    UFPONCResult
    """
    t_start = time.perf_counter()
    params = dict(k_max=k_max, m=m, center_power=center_power, tol=tol, fcm_tol=fcm_tol, max_iter=max_iter,
                  fcm_max_iter=fcm_max_iter, min_variance=min_variance, max_condition=max_condition,
                  min_cluster_size=min_cluster_size, new_prototype=new_prototype, stop=stop, min_k=min_k,
                  max_fit_points=max_fit_points, voxel_size=voxel_size, chunk_size=chunk_size)
    validate_params("ufp_onc", params, ENGINE_CONSTRAINTS)
    X = check_points(X, owner="ufp_onc")
    w = check_weights(sample_weight, X.shape[0], owner="ufp_onc")
    n, D = X.shape
    power = m if center_power is None else float(center_power)
    fit = prepare_fit_set(X, w, max_fit_points=max_fit_points, voxel_size=voxel_size)
    mom = fit.moments
    total = float(mom.w.sum())
    min_mass = float(min_cluster_size) if min_cluster_size is not None else max(D + 1.0, 1e-3 * total)
    if total < min_mass:
        raise FitError(f"the cloud's total weight {total:g} is below the minimum cluster size {min_mass:g}")

    gg_kw = dict(m=m, center_power=power, tol=tol, max_iter=max_iter, min_variance=min_variance,
                 max_condition=max_condition, min_mass=min_mass)
    partitions: list[KPartition] = []
    notes: list[str] = []
    stop_reason = "k_max"
    d0 = None
    prev: GGState | None = None
    for k in range(1, k_max + 1):
        t0 = time.perf_counter()
        n_fcm = 0
        if prev is None:
            state = gg_fit(mom, np.ones((1, mom.n)), **gg_kw)
        else:
            if new_prototype == "distance":
                if d0 is None:
                    cov1 = partitions[0].covariances[0]
                    d0 = max(10.0 * float(np.trace(cov1)), 10.0 * min_variance)  # all points may coincide
                u0 = new_prototype_memberships(mom.XT, prev.centers, d0, m)
            else:
                u0 = worst_point_memberships(mom.X, prev.centers, prev.memberships, m)
            # a cluster that dies ends the sweep: the layers stop at the first drop, which the note names
            fcm = fcm_fit(mom, u0, m=m, tol=fcm_tol, max_iter=fcm_max_iter, min_mass=min_mass, stop_at_drop=True)
            n_fcm = fcm.n_iter
            dropped: tuple[DroppedCluster, ...] = fcm.dropped
            if not dropped:
                state = gg_fit(mom, fcm.memberships, stop_at_drop=True, **gg_kw)
                dropped = state.dropped
            if dropped:
                if len(dropped) == k and k > 2:  # every cluster (identical points, a K past the points' count)
                    masses = [d.mass for d in dropped]
                    said = (f"all {k} clusters fell below the minimum effective size {min_mass:g} in "
                            f"{dropped[0].layer} iteration {dropped[0].iteration} (effective sizes "
                            f"{min(masses):.3g}-{max(masses):.3g})")
                else:
                    said = "; ".join(str(d) for d in dropped)
                notes.append(f"K={k}: {said}; the sweep stopped at K={k - 1}")
                stop_reason = "no_growth"
                break
        if not state.converged:
            notes.append(f"K={k}: Gath-Geva stopped at max_iter={max_iter} before max |dU| < {tol:g}")
        fhv, pd, apd = _validity(state, mom)
        part = KPartition(
            k=state.centers.shape[0], centers=state.centers + fit.offset,
            covariances=state.gaussians.covariances, priors=state.priors, fhv=fhv, pd=pd, apd=apd,
            n_iter_fcm=n_fcm, n_iter_gg=state.n_iter, converged=state.converged,
            seconds=time.perf_counter() - t0, m=m, fit_memberships=state.memberships.T,
            offset=fit.offset, gaussians=state.gaussians,
        )
        partitions.append(part)
        if progress is not None:
            progress(part)
        prev = state
        if (stop == "first_max" and len(partitions) >= 2 and partitions[-2].k >= min_k
                and partitions[-1].apd <= partitions[-2].apd):
            stop_reason = "first_max"
            break
    eligible = [p for p in partitions if p.k >= min_k] or partitions[-1:]
    chosen = eligible[first_local_max([p.apd for p in eligible])]
    memberships = _ones_when_single(chosen, X)
    if memberships is None:
        memberships = chosen.predict_proba(X, chunk_size)
    return UFPONCResult(
        partitions=tuple(partitions), chosen_k=chosen.k, memberships=memberships, offset=fit.offset,
        n_samples=n, n_fit=int(mom.X.shape[0]), voxel_size=fit.voxel_size, stop_reason=stop_reason,
        notes=tuple(notes), seconds=time.perf_counter() - t_start,
    )


def _ones_when_single(part: KPartition, X: np.ndarray) -> np.ndarray | None:
    """The memberships (n, 1) of a partition of one cluster, when they are provably ones: the
    softmax over one cluster is ``exp(0) / exp(0)`` = 1 exactly (compiled or not) wherever the
    squared distance is finite, which holds when the whitening is finite and no whitened
    coordinate can reach 1e150. None otherwise (the caller predicts). The ground chain of a
    vehicle frame, split after split whose sweep prefers K = 1, no longer predicts its K = 1."""
    if part.k != 1 or part.gaussians is None or X.shape[0] == 0:
        return None
    whit = part.gaussians.whitening
    if not np.isfinite(whit).all():
        return None
    lo, hi = bounds(X)
    reach = float(max(np.abs(lo - part.centers[0]).max(), np.abs(hi - part.centers[0]).max()))
    if not reach * float(np.abs(whit).max()) * X.shape[1] < 1e150:
        return None
    return np.ones((X.shape[0], 1))


def _validity(state: GGState, mom: Moments) -> tuple[float, float, float]:
    return validity(state.memberships, mom.w, state.maha, state.gaussians.logdet)
