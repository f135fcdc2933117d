"""scikit-learn's own estimator checks on every scikit-learn estimator we ship.

The chapter's algorithms (FittedQIteration, FQE, API, CPI, PSDP) are scikit-learn *style*
(hyper-parameters in ``__init__``, fitted attributes with ``_``, ``get_params`` /
``clone``), but ``fit`` takes a TransitionDataset or an access model rather than
``(X, y)``, so ``check_estimator`` does not apply to them; their conventions are checked
below with ``clone`` and ``get_params`` instead, and their parameter declarations
(``_parameter_constraints``, one per parameter, checked by scikit-learn's own
``_validate_params``) with scikit-learn's validation.

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


def _all_algorithm_classes():
    from offline_adp.algorithms.iterated_fqi import IteratedFQI
    from offline_adp.algorithms.psdp import IteratedPSDP

    return [ALGORITHMS[n].estimator_class() for n in ALGORITHMS] + [IteratedFQI, IteratedPSDP]


@pytest.mark.parametrize("cls", _all_algorithm_classes(), ids=lambda c: c.__name__)
def test_every_parameter_is_declared_and_checked_by_sklearn(cls):
    """One declaration per parameter (``_parameter_constraints``), checked by scikit-learn's
    own ``BaseEstimator._validate_params``: no class of ours redefines it."""
    from sklearn.base import BaseEstimator
    from sklearn.utils._param_validation import InvalidParameterError

    est = cls()
    assert set(est._parameter_constraints) == set(est.get_params(deep=False))
    assert type(est)._validate_params is BaseEstimator._validate_params
    est._validate_params()
    est._check_param_combinations()  # the defaults pass
    name = next(k for k, c in est._parameter_constraints.items() if "random_state" == k or any(
        getattr(x, "left", None) is not None for x in c))
    with pytest.raises(InvalidParameterError, match=f"'{name}' parameter of {cls.__name__}"):
        clone(est).set_params(**{name: -1})._validate_params()


def test_fqe_defaults_are_fqis_except_those_its_docstring_names():
    """FittedQEvaluation's docstring: its parameters are FittedQIteration's, with the same
    defaults, except ``mode``, ``n_structures``, ``structure_max_samples`` and
    ``early_build_trees`` (and without the screen)."""
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.algorithms.fqi import FittedQIteration

    fqi, fqe = FittedQIteration().get_params(deep=False), FittedQEvaluation().get_params(deep=False)
    assert set(fqi) - set(fqe) == {"screen_trees", "screen_tol"} and set(fqe) - set(fqi) == {"policy"}
    differ = {k for k in fqe if k in fqi and fqe[k] != fqi[k]}
    assert differ == {"mode", "n_structures", "structure_max_samples", "early_build_trees"}
    doc = FittedQEvaluation.__doc__
    assert all(f"{k} : " in doc for k in differ) and doc.count("**the default differs**") == len(differ)
