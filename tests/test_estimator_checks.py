"""scikit-learn's own estimator checks on every scikit-learn estimator we ship.

The chapter's algorithms (FittedQIteration, FQE, API, CPI, PSDP) are scikit-learn *style*
(hyper-parameters in ``__init__``, fitted attributes with ``_``, ``get_params`` /
``clone``), but ``fit`` takes a TransitionDataset or an access model rather than
``(X, y)``, so ``check_estimator`` does not apply to them; their conventions are checked
below with ``clone`` and ``get_params`` instead.

The only skips are scikit-learn's array-API checks, which run only when the
``SCIPY_ARRAY_API`` environment variable is set (our estimators take NumPy arrays).
"""

from __future__ import annotations

import pytest
from sklearn.base import clone
from sklearn.utils.estimator_checks import parametrize_with_checks

from offline_adp.algorithms.registry import ALGORITHMS
from offline_adp.features import SelectColumns
from offline_adp.regressors import TabularClassifier, TabularRegressor


@parametrize_with_checks([TabularRegressor(), TabularClassifier(), SelectColumns()])
def test_sklearn_check_estimator(estimator, check):
    check(estimator)


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_algorithms_follow_sklearn_conventions(name):
    cls = ALGORITHMS[name].estimator_class()
    est = cls()
    params = est.get_params(deep=False)
    assert set(params) == set(clone(est).get_params(deep=False))
    assert not any(k.endswith("_") for k in vars(est)), "no fitted attributes before fit"
