"""scikit-learn-style estimators over the engine: :class:`FuzzyCMeans` and :class:`GathGeva`.

Constructors only store settings; ``fit`` returns ``self``; learned attributes end in ``_``.
Both are deterministic by default (``init='incremental'``, the UFP-ONC growth scheme). They pass
scikit-learn's ``check_estimator`` suite (tests/test_estimator_checks.py): bad input is a
``ValueError`` (or ``TypeError``) saying what is wrong, predicting before fitting a
``NotFittedError``, ``n_features_in_`` is set by ``fit`` and checked by ``predict``.
"""
from __future__ import annotations

import numbers
import warnings

import numpy as np
import scipy.sparse
from sklearn.base import BaseEstimator, ClusterMixin
from sklearn.cluster import kmeans_plusplus
from sklearn.exceptions import NotFittedError as _SklearnNotFittedError
from sklearn.utils import check_random_state

from kbs.errors import FitError, ParameterError
from kbs.inference._validation import (
    ArrayLike,
    Interval,
    NoneValue,
    Options,
    RandomStateLike,
    check_points,
    check_weights,
    validate_params,
)
from kbs.inference.engine import fcm_fit, gg_fit, gg_memberships, memberships_in_chunks, new_prototype_memberships
from kbs.inference.kernels import memberships_from_sq_dist, sq_euclidean
from kbs.inference.settings import FIT_DEFAULTS as _D
from kbs.inference.settings import constraints
from kbs.inference.ufp_onc import FitSet, prepare_fit_set, ufp_onc


class NotFittedError(ParameterError, _SklearnNotFittedError):
    """``predict`` before ``fit``: a :class:`~kbs.errors.ParameterError` and scikit-learn's
    ``NotFittedError``."""


class InputTypeError(ParameterError, TypeError):
    """``X`` holds something that is not a number (a ``ParameterError`` and a ``TypeError``, as
    numpy raises for it)."""


class _FuzzyBase(ClusterMixin, BaseEstimator):
    def _check_fitted(self) -> None:
        if not hasattr(self, "centers_"):
            raise NotFittedError(f"This {type(self).__name__} instance is not fitted yet; call 'fit' first.")

    def _check_X(self, X, *, reset: bool, min_samples: int = 1) -> np.ndarray:
        """``X`` as a C-contiguous float64 (n_samples, n_features) array, with scikit-learn's
        messages for what its checks feed: sparse, complex, non-numeric, 1-D, empty input, and
        (``reset=False``) a number of features other than ``fit``'s. ``reset=True`` (``fit``)
        sets ``n_features_in_``."""
        owner = type(self).__name__
        if scipy.sparse.issparse(X):
            raise ParameterError(f"{owner}: sparse input is not supported (got a {type(X).__name__}): X holds "
                                 "points; pass a dense array, X.toarray()")
        try:
            arr = np.asarray(X)
            complex_ = arr.dtype.kind == "c"
            if not complex_:
                arr = np.asarray(arr, dtype=np.float64)
        except TypeError as exc:
            raise InputTypeError(f"{owner}: X must be a numeric array of shape (n_samples, n_features): {exc}") from exc
        except ValueError as exc:
            raise ParameterError(f"{owner}: X must be a numeric array of shape (n_samples, n_features): {exc}") from exc
        if complex_:
            raise ParameterError(f"{owner}: Complex data not supported; X must hold real numbers")
        if arr.ndim == 1:
            raise ParameterError(f"{owner}: expected a 2-D array (n_samples, n_features), got a 1-D array of shape "
                                 f"{arr.shape}. Reshape your data either using X.reshape(-1, 1) if it has a single "
                                 "feature or X.reshape(1, -1) if it is a single sample.")
        if arr.ndim == 2 and arr.shape[1] == 0:
            raise ParameterError(f"{owner}: found an array with 0 feature(s) (shape={arr.shape}) while a minimum of "
                                 "1 is required.")
        if arr.ndim == 2 and arr.shape[0] < min_samples:
            raise ParameterError(f"{owner}: found an array with {arr.shape[0]} sample(s) (shape={arr.shape}) while "
                                 f"a minimum of {min_samples} is required.")
        arr = check_points(arr, owner=owner, min_samples=min_samples)
        if reset:
            self.n_features_in_ = arr.shape[1]
        elif arr.shape[1] != self.n_features_in_:
            raise ParameterError(f"X has {arr.shape[1]} features, but {owner} is expecting {self.n_features_in_} "
                                 "features as input.")
        return arr

    def _prepare(self, X, sample_weight) -> tuple[np.ndarray, np.ndarray, FitSet]:
        owner = type(self).__name__
        validate_params(owner, self.get_params(), self._constraints)
        X = self._check_X(X, reset=True, min_samples=max(1, self.n_clusters))
        w = check_weights(sample_weight, X.shape[0], owner=owner)
        fit = prepare_fit_set(X, w, max_fit_points=None, voxel_size=None)
        total, min_mass = float(fit.moments.w.sum()), self._min_mass(fit)
        if total < min_mass:  # the engine would fail the same way; say it with the sample count
            what = ("min_cluster_size" if self.min_cluster_size is not None else
                    "by default max(n_features + 1, 0.001 x total weight): a full covariance needs n_features + 1 "
                    "points")
            raise FitError(f"{owner}: the samples' weight (n_samples={X.shape[0]}, total weight {total:g}) is below "
                           f"the minimum cluster size {min_mass:g} ({what}); give more samples"
                           + (", or a smaller min_cluster_size" if self.min_cluster_size is not None else ""))
        return X, w, fit

    def _initial_centers(self, fit: FitSet) -> np.ndarray:
        """Initial centres (K, D) in centred coordinates, for 'k-means++' or an array init."""
        Xc, w = fit.moments.X, fit.moments.w
        if isinstance(self.init, str) and self.init == "k-means++":
            centers, _ = kmeans_plusplus(Xc, self.n_clusters, sample_weight=w,
                                         random_state=check_random_state(self.random_state))
            return centers
        centers = np.asarray(self.init, dtype=np.float64)
        if centers.shape != (self.n_clusters, Xc.shape[1]):
            raise ParameterError(
                f"{type(self).__name__}: init centres must have shape ({self.n_clusters}, {Xc.shape[1]}); "
                f"got {centers.shape}."
            )
        return centers - fit.offset

    def _min_mass(self, fit: FitSet) -> float:
        if self.min_cluster_size is not None:
            return float(self.min_cluster_size)
        return max(fit.moments.X.shape[1] + 1.0, 1e-3 * float(fit.moments.w.sum()))

    def fit_predict(self, X, y=None, sample_weight=None) -> np.ndarray:
        return self.fit(X, sample_weight=sample_weight).labels_

    def predict(self, X) -> np.ndarray:
        """Index of the cluster of highest membership (n_samples,)."""
        return self.predict_proba(X).argmax(axis=1)


class FuzzyCMeans(_FuzzyBase):
    """Fuzzy c-means (Bezdek), layer 1 of UFP-ONC.

    Parameters
    ----------
    n_clusters : int
    m : float
        Fuzzifier (> 1).
    init : {'incremental', 'k-means++'} or array (n_clusters, n_features)
        'incremental' grows K = 1 .. n_clusters, each new prototype entering with a constant squared
        distance ``10 trace(Cov X)`` (deterministic); 'k-means++' seeds with scikit-learn's
        ``kmeans_plusplus`` and ``random_state``; an array gives the initial centres.
    tol : float
        Stop when ``max |dU| < tol``.
    max_iter : int
    min_cluster_size : float, optional
        Effective size below which a cluster dies (default ``max(D + 1, 0.001 * total weight)``).
    random_state : int, RandomState or None
        Used by 'k-means++' only.

    Attributes
    ----------
    centers_ : ndarray (n_clusters_, n_features)
    memberships_ : ndarray (n_samples, n_clusters_)
    labels_ : ndarray (n_samples,)
    n_clusters_ : int
    n_iter_ : int
    converged_ : bool
    dropped_ : tuple of DroppedCluster
    """

    #: the engine settings' constraints are the table's (:mod:`kbs.inference.settings`)
    _constraints = {
        "n_clusters": [Interval(numbers.Integral, 1, None)],
        **constraints(("m", "tol", "max_iter", "min_cluster_size")),
        "init": [Options(("incremental", "k-means++")), ArrayLike()],
        "random_state": [Interval(numbers.Integral, 0, None), NoneValue(), RandomStateLike()],
    }

    def __init__(self, n_clusters: int = 2, *, m: float = _D["m"], init="incremental", tol: float = _D["tol"],
                 max_iter: int = _D["max_iter"], min_cluster_size: float | None = _D["min_cluster_size"],
                 random_state=None) -> None:
        self.n_clusters = n_clusters
        self.m = m
        self.init = init
        self.tol = tol
        self.max_iter = max_iter
        self.min_cluster_size = min_cluster_size
        self.random_state = random_state

    def fit(self, X, y=None, sample_weight=None) -> FuzzyCMeans:
        """Fit on points ``X`` (n_samples, n_features) with optional ``sample_weight``."""
        X, w, fit = self._prepare(X, sample_weight)
        mom = fit.moments
        kw = dict(m=self.m, tol=self.tol, max_iter=self.max_iter, min_mass=self._min_mass(fit))
        if isinstance(self.init, str) and self.init == "incremental":
            centers = (mom.wX.sum(axis=0) / mom.w.sum())[None, :]
            d0 = 10.0 * float(np.trace(np.cov(mom.X.T, aweights=mom.w, bias=True).reshape(mom.X.shape[1], -1)))
            state = None
            for _ in range(2, self.n_clusters + 1):
                state = fcm_fit(mom, new_prototype_memberships(mom.XT, centers, d0, self.m), **kw)
                centers = state.centers
                if state.dropped:
                    break
            if state is None:  # n_clusters == 1
                state = fcm_fit(mom, np.ones((1, mom.n)), **kw)
        else:
            c0 = self._initial_centers(fit)
            state = fcm_fit(mom, memberships_from_sq_dist(sq_euclidean(mom.XT, c0), self.m), **kw)
        self.centers_ = state.centers + fit.offset
        self.n_clusters_ = self.centers_.shape[0]
        self.n_iter_ = state.n_iter
        self.converged_ = state.converged
        self.dropped_ = state.dropped
        _warn_fewer(self, state.dropped)
        self.memberships_ = self.predict_proba(X)
        self.labels_ = self.memberships_.argmax(axis=1)
        return self

    def predict_proba(self, X) -> np.ndarray:
        """Fuzzy c-means memberships (n_samples, n_clusters_) of ``X`` under the fitted centres."""
        self._check_fitted()
        X = self._check_X(X, reset=False)
        return memberships_from_sq_dist(sq_euclidean(np.ascontiguousarray(X.T), self.centers_), self.m).T


class GathGeva(_FuzzyBase):
    """Gath-Geva fuzzy maximum-likelihood clustering (exponential distance), layer 2 of UFP-ONC.

    Memberships ``u_ij = 1 / sum_k (d_ij / d_kj)^(1/(m-1))`` with
    ``d_ij = sqrt(det F_i) / P_i exp((x_j - v_i)^T F_i^-1 (x_j - v_i) / 2)``; fuzzy covariances and
    priors weighted by ``u``, centres by ``u^center_power``. All in the log domain, with floored
    eigenvalues. With ``m = 2`` the memberships are the posteriors of the Gaussian mixture
    ``(priors_, centers_, covariances_)``.

    Parameters
    ----------
    n_clusters : int
    m : float
        Fuzzifier (> 1).
    center_power : float, optional
        Power of the memberships in the centre update (default ``m``; 1 for the EM-like centre).
    init : {'incremental', 'fcm'} or array (n_clusters, n_features)
        'incremental' runs the UFP-ONC sweep K = 1 .. n_clusters (deterministic); 'fcm' starts from
        fuzzy c-means seeded by k-means++ (``random_state``); an array gives initial centres for
        the fuzzy c-means layer.
    tol, fcm_tol : float
        Stop each layer when ``max |dU| < tol``.
    max_iter, fcm_max_iter : int
    min_variance, max_condition : float
        Eigenvalue floor ``max(min_variance, lambda_max / max_condition)``.
    min_cluster_size : float, optional
    random_state : int, RandomState or None

    Attributes
    ----------
    centers_ : ndarray (n_clusters_, n_features)
    covariances_ : ndarray (n_clusters_, n_features, n_features)
        The floored fuzzy covariances used by the distance.
    priors_ : ndarray (n_clusters_,)
    memberships_ : ndarray (n_samples, n_clusters_)
    labels_ : ndarray (n_samples,)
    n_clusters_ : int
    n_iter_ : int
        Gath-Geva iterations of the final K.
    converged_ : bool
    dropped_ : tuple of DroppedCluster
    """

    #: the engine settings' constraints are the table's (:mod:`kbs.inference.settings`)
    _constraints = {
        **constraints(("m", "center_power", "tol", "fcm_tol", "max_iter", "fcm_max_iter", "min_variance",
                       "max_condition", "min_cluster_size")),
        "n_clusters": [Interval(numbers.Integral, 1, None)],
        "init": [Options(("incremental", "fcm")), ArrayLike()],
        "random_state": FuzzyCMeans._constraints["random_state"],
    }

    def __init__(self, n_clusters: int = 2, *, m: float = _D["m"], center_power: float | None = _D["center_power"],
                 init="incremental", tol: float = _D["tol"], fcm_tol: float = _D["fcm_tol"],
                 max_iter: int = _D["max_iter"], fcm_max_iter: int = _D["fcm_max_iter"],
                 min_variance: float = _D["min_variance"], max_condition: float = _D["max_condition"],
                 min_cluster_size: float | None = _D["min_cluster_size"], random_state=None) -> None:
        self.n_clusters = n_clusters
        self.m = m
        self.center_power = center_power
        self.init = init
        self.tol = tol
        self.fcm_tol = fcm_tol
        self.max_iter = max_iter
        self.fcm_max_iter = fcm_max_iter
        self.min_variance = min_variance
        self.max_condition = max_condition
        self.min_cluster_size = min_cluster_size
        self.random_state = random_state

    def fit(self, X, y=None, sample_weight=None) -> GathGeva:
        """Fit on points ``X`` (n_samples, n_features) with optional ``sample_weight``."""
        X, w, fit = self._prepare(X, sample_weight)
        if isinstance(self.init, str) and self.init == "incremental":
            res = ufp_onc(X, k_max=self.n_clusters, sample_weight=w, m=self.m, center_power=self.center_power,
                          tol=self.tol, fcm_tol=self.fcm_tol, max_iter=self.max_iter,
                          fcm_max_iter=self.fcm_max_iter, min_variance=self.min_variance,
                          max_condition=self.max_condition, min_cluster_size=self.min_cluster_size,
                          max_fit_points=None, stop="k_max")
            part = res.partitions[-1]
            self.centers_, self.covariances_, self.priors_ = part.centers, part.covariances, part.priors
            self._gaussians, self._offset = part.gaussians, part.offset
            self.n_iter_, self.converged_ = part.n_iter_gg, part.converged
            self.dropped_ = ()
            if part.k < self.n_clusters:
                warnings.warn(f"GathGeva found {part.k} clusters, not {self.n_clusters}: " + "; ".join(res.notes),
                              UserWarning, stacklevel=2)
        else:
            mom = fit.moments
            fcm = FuzzyCMeans(self.n_clusters, m=self.m, init="k-means++" if isinstance(self.init, str) else self.init,
                              tol=self.fcm_tol, max_iter=self.fcm_max_iter, min_cluster_size=self.min_cluster_size,
                              random_state=self.random_state)
            u0 = memberships_from_sq_dist(sq_euclidean(mom.XT, fcm._initial_centers(fit)), self.m)
            min_mass = self._min_mass(fit)
            state = fcm_fit(mom, u0, m=self.m, tol=self.fcm_tol, max_iter=self.fcm_max_iter, min_mass=min_mass)
            power = self.m if self.center_power is None else float(self.center_power)
            gg = gg_fit(mom, state.memberships, m=self.m, center_power=power, tol=self.tol, max_iter=self.max_iter,
                        min_variance=self.min_variance, max_condition=self.max_condition, min_mass=min_mass)
            self.centers_ = gg.centers + fit.offset
            self.covariances_, self.priors_ = gg.gaussians.covariances, gg.priors
            self._gaussians, self._offset = gg.gaussians, fit.offset
            self.n_iter_, self.converged_ = gg.n_iter, gg.converged
            self.dropped_ = state.dropped + gg.dropped
            _warn_fewer(self, self.dropped_)
        self.n_clusters_ = self.centers_.shape[0]
        self.memberships_ = self.predict_proba(X)
        self.labels_ = self.memberships_.argmax(axis=1)
        return self

    def predict_proba(self, X) -> np.ndarray:
        """Gath-Geva memberships (n_samples, n_clusters_) of ``X`` under the fitted parameters."""
        self._check_fitted()
        X = self._check_X(X, reset=False)
        centers = self.centers_ - self._offset
        return memberships_in_chunks(
            X, self._offset, lambda XT: gg_memberships(XT, centers, self._gaussians, self.priors_, self.m),
            self.n_clusters_, 65536,
        )


def _warn_fewer(est: _FuzzyBase, dropped) -> None:
    if dropped:
        warnings.warn(
            f"{type(est).__name__} ended with {est.centers_.shape[0]} clusters, not {est.n_clusters}: "
            + "; ".join(str(d) for d in dropped),
            UserWarning,
            stacklevel=3,
        )
