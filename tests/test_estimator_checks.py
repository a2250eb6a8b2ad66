"""FuzzyCMeans and GathGeva against scikit-learn's own contract suite (``parametrize_with_checks``),
and the cases behind the checks that were failing, one by one, with kbs's messages."""
from __future__ import annotations

import inspect

import numpy as np
import pytest
import scipy.sparse
from sklearn.exceptions import NotFittedError
from sklearn.utils.estimator_checks import parametrize_with_checks

from kbs.errors import ExitCode, FitError, KbsError, ParameterError
from kbs.inference import FuzzyCMeans, GathGeva
from scenes import anisotropic_blobs

_OPTIONS = inspect.signature(parametrize_with_checks).parameters
if "expected_failed_checks" not in _OPTIONS:  # scikit-learn < 1.6
    pytest.skip("scikit-learn >= 1.6 is needed for expected_failed_checks", allow_module_level=True)

#: Checks FuzzyCMeans and GathGeva fail on purpose, and why.
EXPECTED_FAILED_CHECKS = {
    "check_sample_weight_equivalence_on_dense_data": (
        "the check fits 15 samples of total weight about 27 in 30 dimensions, and a fuzzy cluster needs a weight "
        "of at least n_features + 1 = 31 (the default minimum cluster size: a full covariance in 30 dimensions "
        "needs 31 points), so both fits raise FitError. The equivalence of "
        "integer weights and repeated points is tested on data the estimators can fit "
        "(test_integer_sample_weight_equals_repeated_points)"
    ),
}


def expected_failed_checks(estimator) -> dict[str, str]:
    return EXPECTED_FAILED_CHECKS


@parametrize_with_checks([FuzzyCMeans(), GathGeva()], expected_failed_checks=expected_failed_checks,
                         **({"xfail_strict": True} if "xfail_strict" in _OPTIONS else {}))
def test_sklearn_estimator_checks(estimator, check):
    check(estimator)


ESTIMATORS = [FuzzyCMeans, GathGeva]


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_integer_sample_weight_equals_repeated_points(cls):
    X, _ = anisotropic_blobs(60)
    rng = np.random.default_rng(7)
    sw = rng.integers(0, 5, len(X))
    order = rng.permutation(len(X))
    repeated = cls(3).fit(X.repeat(sw, axis=0))
    weighted = cls(3).fit(X[order], sample_weight=sw[order])
    np.testing.assert_allclose(weighted.predict_proba(X), repeated.predict_proba(X), atol=1e-8)
    np.testing.assert_array_equal(weighted.predict(X), repeated.predict(X))


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_predicting_before_fitting_is_a_not_fitted_error(cls):
    with pytest.raises(NotFittedError, match=f"This {cls.__name__} instance is not fitted yet") as info:
        cls(2).predict(np.zeros((3, 3)))
    assert isinstance(info.value, ParameterError) and info.value.exit_code == ExitCode.PARAMETER


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_n_features_in_is_set_and_checked(cls):
    X, _ = anisotropic_blobs(50)
    est = cls(2)
    assert not hasattr(est, "n_features_in_")
    est.fit(X)
    assert est.n_features_in_ == 3
    for method in (est.predict, est.predict_proba):
        with pytest.raises(ParameterError, match=f"X has 2 features, but {cls.__name__} is expecting 3 features "
                                                 "as input"):
            method(X[:, :2])


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize("X, error, message", [
    (np.ones((12, 3)) + 1j, ParameterError, "Complex data not supported"),
    (scipy.sparse.csr_array(np.eye(12, 3)), ParameterError, "sparse input is not supported.*toarray"),
    (scipy.sparse.csr_matrix(np.eye(12, 3)), ParameterError, "sparse input is not supported.*toarray"),
    (np.array([[1.0, 2.0, 3.0]] * 11 + [[1.0, {"a": 1}, 3.0]], dtype=object), TypeError,
     "float.. argument must be a string or a real number"),
    (np.zeros((0, 3)), ParameterError, r"0 sample\(s\) \(shape=\(0, 3\)\) while a minimum of 2 is required"),
    (np.zeros((12, 0)), ParameterError, r"0 feature\(s\) \(shape=\(12, 0\)\) while a minimum of 1 is required"),
    (np.arange(12.0), ParameterError, "Reshape your data"),
])
def test_bad_input_is_a_clear_value_or_type_error(cls, X, error, message):
    with pytest.raises(error, match=message) as info:
        cls(2).fit(X)
    assert isinstance(info.value, KbsError) and isinstance(info.value, (ValueError, TypeError))


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_predicting_one_point_as_a_1d_array_says_to_reshape(cls):
    X, _ = anisotropic_blobs(50)
    est = cls(2).fit(X)
    with pytest.raises(ParameterError, match=r"Reshape your data .* X.reshape\(1, -1\)"):
        est.predict(X[0])


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_too_little_weight_is_a_fit_error_that_is_also_a_value_error(cls):
    X = np.random.default_rng(0).uniform(size=(1, 10))
    with pytest.raises(FitError, match=r"n_samples=1, total weight 1\) is below the minimum cluster size 11") as info:
        cls(1).fit(X)
    assert isinstance(info.value, ValueError) and info.value.exit_code == ExitCode.FIT
