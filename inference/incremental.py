"""UFP-ONC's incremental K sweep, one K at a time, for a caller that decides after each K whether
to go on (the seed paper's global strategy: K + 1 while a heuristic fails on some cluster).

:func:`~kbs.inference.ufp_onc.ufp_onc` runs the whole sweep (K = 1 .. k_max, or up to APD's first
local maximum) in one call; :class:`IncrementalSweep` is the same scheme (same fitting set, same
layers, same K = 1 start) opened up: :meth:`IncrementalSweep.grow` computes the (K+1)-partition
from the K-partition, with the new prototype entering where the caller says.

- ``grow()`` is UFP-ONC's own incremental init (Gath-Geva's way (V)): the new prototype gets the
  constant squared distance ``d0 = 10 trace(Cov X)`` to every point, so that it takes the points
  the K prototypes explain badly, wherever they are; fuzzy c-means then Gath-Geva. The partitions
  it gives are those of ``ufp_onc`` (tested).
- ``grow(target=j)`` seeds the new prototype in cluster ``j`` of the K-partition (the cluster a
  heuristic rejected): the K memberships are kept, and cluster ``j``'s are shared between two
  clusters by the side of its best approximating plane each point lies on (a cluster made of two
  faces meeting at an edge has its plane across the edge, so each side holds mostly one face);
  Gath-Geva then runs from those K + 1 memberships over the whole scene. Fuzzy c-means is skipped:
  its Euclidean distances would pull the two halves back into round blobs. The partition stays
  global: every cluster may move, not only ``j``'s halves.

A (K+1)-partition in which a cluster dies (its effective size falls under the minimum) is not
kept: ``grow`` returns None and the sweep stays at K (the caller may try another target).
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from kbs.errors import FitError
from kbs.inference._validation import check_points, validate_params
from kbs.inference.engine import GGState, fcm_fit, gg_fit, new_prototype_memberships
from kbs.inference.kernels import validity
from kbs.inference.settings import DEFAULTS, constraints
from kbs.inference.ufp_onc import KPartition, prepare_fit_set

#: the table's constraints of the settings IncrementalSweep takes (:mod:`kbs.inference.settings`)
_CONSTRAINTS = constraints(("m", "center_power", "tol", "fcm_tol", "max_iter", "fcm_max_iter", "min_variance",
                            "max_condition", "min_cluster_size", "max_fit_points", "voxel_size", "chunk_size"))


class IncrementalSweep:
    """The K-partitions of points ``X`` (n, 3), computed one K at a time.

    Parameters are those of :func:`~kbs.inference.ufp_onc.ufp_onc` (``m``, ``tol``, ``max_iter``,
    ``min_variance``, ``max_condition``, ``max_fit_points``, ...); the fitting set (voxel reduction
    of a large cloud) is the one ``ufp_onc`` would fit. The K = 1 partition is computed at once.

    Attributes
    ----------
    partitions : list of KPartition
        The partitions kept, K = 1, 2, ... (each from the one before).
    notes : list of str
        Events worth telling a user (layers that hit max_iter, prototypes that died).
    """

    def __init__(self, X: np.ndarray, *, m: float = DEFAULTS["m"], center_power: float | None = DEFAULTS["center_power"],
                 tol: float = DEFAULTS["tol"], fcm_tol: float = DEFAULTS["fcm_tol"], max_iter: int = DEFAULTS["max_iter"],
                 fcm_max_iter: int = DEFAULTS["fcm_max_iter"], min_variance: float = DEFAULTS["min_variance"],
                 max_condition: float = DEFAULTS["max_condition"],
                 min_cluster_size: float | None = DEFAULTS["min_cluster_size"],
                 max_fit_points: int | None = DEFAULTS["max_fit_points"], voxel_size: float | None = DEFAULTS["voxel_size"],
                 chunk_size: int = DEFAULTS["chunk_size"]) -> None:
        params = dict(m=m, center_power=center_power, tol=tol, fcm_tol=fcm_tol, max_iter=max_iter,
                      fcm_max_iter=fcm_max_iter, min_variance=min_variance, max_condition=max_condition,
                      min_cluster_size=min_cluster_size, max_fit_points=max_fit_points, voxel_size=voxel_size,
                      chunk_size=chunk_size)
        validate_params("IncrementalSweep", params, _CONSTRAINTS)
        X = check_points(X, owner="IncrementalSweep")
        w = np.ones(X.shape[0])
        self.fit = prepare_fit_set(X, w, max_fit_points=max_fit_points, voxel_size=voxel_size)
        mom = self.fit.moments
        total = float(mom.w.sum())
        D = X.shape[1]
        self.min_mass = float(min_cluster_size) if min_cluster_size is not None else max(D + 1.0, 1e-3 * total)
        if total < self.min_mass:
            raise FitError(f"the cloud's total weight {total:g} is below the minimum cluster size {self.min_mass:g}")
        self.m, self.fcm_tol, self.fcm_max_iter, self.max_iter, self.tol = m, fcm_tol, fcm_max_iter, max_iter, tol
        self.chunk_size = chunk_size
        self._gg_kw: dict[str, Any] = dict(m=m, center_power=m if center_power is None else float(center_power), tol=tol,
                           max_iter=max_iter, min_variance=min_variance, max_condition=max_condition,
                           min_mass=self.min_mass)
        self.notes: list[str] = []
        self.partitions: list[KPartition] = []
        self._states: list[GGState] = []
        t0 = time.perf_counter()
        state = gg_fit(mom, np.ones((1, mom.n)), **self._gg_kw)
        self._d0 = max(10.0 * float(np.trace(state.gaussians.covariances[0])), 10.0 * min_variance)
        self._keep(state, 0, t0)

    @property
    def k(self) -> int:
        return self.partitions[-1].k

    @property
    def n_fit(self) -> int:
        return int(self.fit.moments.X.shape[0])

    def _keep(self, state: GGState, n_fcm: int, t0: float) -> KPartition:
        mom = self.fit.moments
        fhv, pd, apd = validity(state.memberships, mom.w, state.maha, state.gaussians.logdet)
        if not state.converged:
            self.notes.append(f"K={state.centers.shape[0]}: Gath-Geva stopped at max_iter={self.max_iter} "
                              f"before max |dU| < {self.tol:g}")
        part = KPartition(
            k=state.centers.shape[0], centers=state.centers + self.fit.offset,
            covariances=state.gaussians.covariances, priors=state.priors, fhv=fhv, pd=pd, apd=apd,
            n_iter_fcm=n_fcm, n_iter_gg=state.n_iter, converged=state.converged,
            seconds=time.perf_counter() - t0, m=self.m, fit_memberships=state.memberships.T,
            offset=self.fit.offset, gaussians=state.gaussians,
        )
        self._states.append(state)
        self.partitions.append(part)
        return part

    @property
    def _state(self) -> GGState:
        return self._states[-1]

    def back_to(self, k: int) -> None:
        """Forget the partitions after K = ``k``: the next :meth:`grow` starts from the K-partition."""
        if not 1 <= k <= self.k:
            raise ValueError(f"no partition with K = {k} to go back to (K = 1 .. {self.k})")
        del self.partitions[k:], self._states[k:]

    def seed_memberships(self, target: int | None = None) -> np.ndarray:
        """Initial memberships (K+1, n_fit) of the next K (see the module's docstring)."""
        mom, st = self.fit.moments, self._state
        if target is None:
            return new_prototype_memberships(mom.XT, st.centers, self._d0, self.m)
        if not 0 <= target < st.centers.shape[0]:
            raise ValueError(f"target must be a cluster of the K = {st.centers.shape[0]} partition, got {target}")
        u = st.memberships
        normal = st.gaussians.eigenvectors[target][:, int(np.argmin(st.gaussians.eigenvalues[target]))]
        side = (mom.X - st.centers[target]) @ normal > 0
        u0 = np.vstack([u, u[target] * side])
        u0[target] = u[target] * ~side
        return u0

    def grow(self, target: int | None = None, name: str | None = None) -> KPartition | None:
        """Compute the (K+1)-partition from the K-partition and keep it; None (nothing kept) when a
        cluster dies in it. ``target``: the cluster of the K-partition to seed the new prototype in
        (None: UFP-ONC's way (V), anywhere); ``name``: how the notes call it (default 'cluster j')."""
        t0 = time.perf_counter()
        mom = self.fit.moments
        u0 = self.seed_memberships(target)
        k1 = u0.shape[0]
        n_fcm = 0
        if target is None:
            fcm = fcm_fit(mom, u0, m=self.m, tol=self.fcm_tol, max_iter=self.fcm_max_iter, min_mass=self.min_mass,
                          stop_at_drop=True)
            dropped, u0, n_fcm = fcm.dropped, fcm.memberships, fcm.n_iter
        else:
            dropped = ()
        state = None
        if not dropped:
            state = gg_fit(mom, u0, stop_at_drop=True, **self._gg_kw)
            dropped = state.dropped
        if dropped or state is None:
            where = "" if target is None else f" (seeded in {name or f'cluster {target}'})"
            self.notes.append(f"K={k1}{where}: " + "; ".join(str(d) for d in dropped) + f"; K={k1 - 1} kept")
            return None
        return self._keep(state, n_fcm, t0)

    def memberships(self, X: np.ndarray, k: int | None = None) -> np.ndarray:
        """Memberships (n, K) of points ``X`` in the K-partition (the last one when ``k`` is None)."""
        part = self.partitions[-1] if k is None else next(p for p in self.partitions if p.k == k)
        return part.predict_proba(X, self.chunk_size)

