"""scikit-learn forests read and built without their per-call overhead
(trees/forest_predict.py): the numbers of ``predict`` / ``fit`` + ``predict_model``, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor
from sklearn.linear_model import Ridge

from offline_adp.evaluation.shift import RATIO_TREES
from offline_adp.qfunctions import predict_model
from offline_adp.regressors import make_regressor
from offline_adp.trees.forest_predict import (
    extra_trees_fit_predict,
    forest_predictor,
    linear_predictor,
)


@pytest.mark.parametrize("outputs", [1, 2])
@pytest.mark.parametrize("cls", [ExtraTreesRegressor, RandomForestRegressor])
def test_forest_predictor_is_predict(cls, outputs):
    rng = np.random.default_rng(outputs)
    X = rng.normal(size=(400, 5))
    y = np.column_stack([np.sin(X[:, 0]), X[:, 1] > 0])[:, :outputs]
    forest = cls(n_estimators=9, min_samples_leaf=3, random_state=0, n_jobs=1).fit(X, y[:, 0] if outputs == 1 else y)
    Xn = rng.normal(size=(123, 5)) * 3
    Xn[4, 2] = np.float32(forest.estimators_[0].tree_.threshold[0])  # on a threshold
    assert np.array_equal(forest_predictor(forest)(Xn), forest.predict(Xn))
    ridge = Ridge(alpha=1e-3).fit(X, y)
    assert np.array_equal(linear_predictor(ridge)(Xn), ridge.predict(Xn))


@pytest.mark.parametrize("n", [1, 39, 40, 47, 300])
@pytest.mark.parametrize("params", [RATIO_TREES, {**RATIO_TREES, "min_samples_leaf": 1}, {"n_estimators": 3}])
def test_extra_trees_fit_predict_is_the_forest(n, params):
    rng = np.random.default_rng(n)
    X = rng.normal(size=(n, 4))
    y = rng.random(n) * (rng.random(n) < 0.7)
    Xn = rng.normal(size=(77, 4))
    ref = predict_model(make_regressor("extra_trees", **params).fit(X, y), Xn)
    got = extra_trees_fit_predict(make_regressor("extra_trees", **params), X, y, Xn)
    assert got is not None and np.array_equal(got, ref)
    assert extra_trees_fit_predict(make_regressor("extra_trees", bootstrap=True), X, y, Xn) is None


@pytest.mark.parametrize("n0, n1", [(30, 300), (47, 47), (2, 5), (500, 600)])
def test_lightgbm_binary_proba_is_the_wrapper(n0, n1):
    """The classifier density ratios' LightGBM fits (evaluation/shift.py), trained with the
    calls LGBMClassifier makes: the wrapper's probabilities, bit for bit."""
    from offline_adp.regressors import binary_proba, make_classifier

    rng = np.random.default_rng(n0)
    for _ in range(3):
        X = rng.normal(size=(n0 + n1, 4))
        X[n0:] += rng.normal() * 0.5
        y = np.r_[np.zeros(n0), np.ones(n1)]
        Xn = rng.normal(size=(111, 4))
        ref = make_classifier("lightgbm").fit(X, y).predict_proba(Xn)[:, 1]
        assert np.array_equal(binary_proba("lightgbm", None, X, y, Xn), ref)
    assert np.array_equal(binary_proba("extra_trees", {"n_estimators": 3}, X, y, Xn),
                          make_classifier("extra_trees", n_estimators=3).fit(X, y).predict_proba(Xn)[:, 1])


@pytest.mark.parametrize("cls", [ExtraTreesRegressor, RandomForestRegressor])
def test_inputs_that_are_not_all_finite_take_scikit_learns_own_path(cls):
    """NaN goes to a learned side in scikit-learn (not always right) and inf is refused: the
    compiled path steps aside (review finding)."""
    rng = np.random.default_rng(3)
    X = rng.normal(size=(300, 3))
    Xnan = X.copy()
    Xnan[::7, 0] = np.nan  # trees that learned where NaN goes
    y = np.sin(X[:, 0]) + X[:, 1]
    for train in (X, Xnan):
        forest = cls(n_estimators=5, random_state=0, n_jobs=1).fit(train, y)
        Xn = rng.normal(size=(50, 3))
        Xn[:10, 0] = np.nan
        assert np.array_equal(forest_predictor(forest)(Xn), forest.predict(Xn))
        with pytest.raises(ValueError):
            forest_predictor(forest)(np.full((2, 3), np.inf))
    unfitted = ExtraTreesRegressor(n_estimators=5, random_state=0)
    Xn = rng.normal(size=(20, 3))
    assert extra_trees_fit_predict(unfitted, X, y, Xn) is not None
    Xn[0, 1] = np.nan
    assert extra_trees_fit_predict(unfitted, X, y, Xn) is None
    assert extra_trees_fit_predict(unfitted, X, np.r_[np.inf, y[1:]], Xn[1:]) is None
    assert extra_trees_fit_predict(ExtraTreesRegressor(n_estimators=5, random_state=0, max_samples=0.5), X, y,
                                   Xn[1:]) is None
