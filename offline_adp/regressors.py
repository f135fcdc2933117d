"""LEARN plug-ins: a registry of scikit-learn / LightGBM regressors by name.

Every entry is an *unfitted prototype*; algorithms ``sklearn.base.clone`` it for each
fit. Names resolve from TOML (``regressor = "extra_trees"`` with ``[regressor_params]``).

==================  ===========================================================
name                prototype
==================  ===========================================================
``extra_trees``     Ernst et al. (2005) defaults: 50 trees, ``min_samples_split=2``,
                    all features considered at each split (``max_features=1.0``);
                    fitted on all cores (``n_jobs=-1``; the frozen mode's
                    lookups and averaging too, with the same numbers for any
                    count), the refit mode predicting on one unless ``n_jobs`` is given
``random_forest``   50 bootstrapped trees, ``min_samples_split=2``, all features
``lightgbm``        ``LGBMRegressor`` (100 trees, 31 leaves, learning rate 0.1), one
                    thread unless ``n_jobs`` is given (see ``LIGHTGBM_DEFAULT_THREADS``)
``knn``             5 nearest neighbours, distance-weighted
``ridge``           polynomial features (degree 2) + ridge (alpha 1e-8): quadratic regression
``linear``          ordinary least squares
``mlp``             two hidden layers of 64 units
``tabular``         :class:`TabularRegressor`: the mean target of each distinct input
==================  ===========================================================
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin, RegressorMixin, clone
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import _check_sample_weight, check_is_fitted, validate_data

from offline_adp.errors import InvalidArgumentError, UnknownNameError


class TabularRegressor(RegressorMixin, BaseEstimator):
    """A lookup table: the (weighted) mean target of each distinct input row.

    With one-hot or index inputs this is the tabular learner of the chapter, for which
    fitted Q-iteration is exact dynamic programming on the data's empirical model.
    Rows with zero weight (e.g. left out of a bootstrap replicate) are not data.

    The table answers only for the rows it holds (:meth:`seen`). In the empirical model
    the actions available at a state are the actions logged there, so a Q-function made
    of lookup tables (:class:`~offline_adp.qfunctions.RegressorQ`, either action
    encoding) exposes the (state, action) pairs its tables hold as its ``support``, and
    fitted Q-iteration's Bellman minimum ``min_a' Q(x', a')`` and its greedy policy's
    ``argmin_a Q(x, a)`` range over the actions logged at that state, whenever at least
    one is (:func:`~offline_adp.qfunctions.restrict_to_support`). At a state with no
    logged action at all every action answers ``fill_value`` and counts, as before.
    Fitted Q *evaluation* does not restrict anything: the evaluated policy chooses the action.

    Parameters
    ----------
    fill_value : float
        Prediction for input rows never seen in ``fit``: the value of a (state, action)
        the logs never took, and, where no action at a state was logged, the value of
        every action there (so of the state, in the backup). Unlogged actions at a state
        with a logged one never enter a minimum, whatever this is.

    Attributes
    ----------
    keys_ : ndarray
        The codes of the distinct rows held, sorted.
    values_ : ndarray
        Their weighted mean targets.
    columns_ : list of ndarray
        Each input column's distinct values; ``radix_`` (and ``rows_``, the distinct rows,
        where the columns have too many combinations for one int64) turn a row into its code.
    """

    def __init__(self, fill_value: float = 0.0) -> None:
        self.fill_value = fill_value

    def fit(self, X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None = None) -> TabularRegressor:
        X, y = validate_data(self, X, y, dtype=np.float64, y_numeric=True)
        w = _check_sample_weight(sample_weight, X, dtype=np.float64)
        if not (w > 0).any():
            raise InvalidArgumentError("TabularRegressor: every sample weight is zero; there is no data to fit")
        X, y, w = X[w > 0], y[w > 0], w[w > 0]
        rows = _fit_codes(self, X)
        keys, inv = np.unique(rows, return_inverse=True)
        inv = inv.reshape(-1)
        wsum = np.bincount(inv, weights=w, minlength=len(keys))
        self.keys_ = keys
        self.values_ = np.bincount(inv, weights=w * y, minlength=len(keys)) / np.where(wsum > 0, wsum, 1.0)
        return self

    def predict(self, X: np.ndarray) -> np.ndarray:
        pos, hit = _table_rows(self, X)
        return np.where(hit, self.values_[pos], self.fill_value)

    def seen(self, X: np.ndarray) -> np.ndarray:
        """Whether each input row is one the table holds (a row of ``fit`` with positive
        weight), shape ``(n,)`` bool; elsewhere :meth:`predict` answers ``fill_value``."""
        return _table_rows(self, X)[1]


def _fit_codes(est: Any, X: np.ndarray) -> np.ndarray:
    """Store each column's distinct values (``columns_``) and mixed-radix multipliers
    (``radix_``) on ``est``; return one int64 code per row."""
    X = np.asarray(X, dtype=np.float64) + 0.0  # -0.0 -> 0.0
    est.columns_ = [np.unique(X[:, j]) for j in range(X.shape[1])]
    sizes = np.array([len(c) for c in est.columns_], dtype=np.float64)
    if np.prod(sizes) >= 2.0**62:  # too many combinations for one int64: code the distinct rows instead
        est.rows_ = np.unique(_rows(X))
        est.radix_ = np.zeros(0, np.int64)
    else:
        est.radix_ = np.concatenate([[1], np.cumprod(sizes[:-1])]).astype(np.int64)
    return _codes(est, X)


def _rows(X: np.ndarray) -> np.ndarray:
    """Rows of a float matrix as one structured value each (sortable, searchable)."""
    X = np.ascontiguousarray(X)
    return X.view([(f"f{j}", np.float64) for j in range(X.shape[1])]).reshape(-1)


def _table_rows(est: Any, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For a fitted table estimator: each row's position in ``keys_`` and whether it is there."""
    check_is_fitted(est, "keys_")
    X = validate_data(est, X, dtype=np.float64, reset=False)
    rows = _codes(est, X)
    pos = np.minimum(np.searchsorted(est.keys_, rows), len(est.keys_) - 1)
    return pos, (est.keys_[pos] == rows) & (rows >= 0)


def _codes(est: Any, X: np.ndarray) -> np.ndarray:
    """Row codes from the fitted columns; -1 for rows with a value never seen in fit."""
    X = np.asarray(X, dtype=np.float64) + 0.0
    if not len(est.radix_):
        rows = _rows(X)
        pos = np.minimum(np.searchsorted(est.rows_, rows), len(est.rows_) - 1)
        return np.where(est.rows_[pos] == rows, pos, -1).astype(np.int64)
    code = np.zeros(len(X), np.int64)
    seen = np.ones(len(X), bool)
    for j, (vals, r) in enumerate(zip(est.columns_, est.radix_, strict=True)):
        pos = np.minimum(np.searchsorted(vals, X[:, j]), len(vals) - 1)
        seen &= vals[pos] == X[:, j]
        code += pos.astype(np.int64) * r
    return np.where(seen, code, -1)


def _extra_trees(**kw: Any) -> BaseEstimator:
    from sklearn.ensemble import ExtraTreesRegressor

    params = {"n_estimators": 50, "min_samples_split": 2, "max_features": 1.0, "n_jobs": -1, "random_state": 0}
    return ExtraTreesRegressor(**{**params, **kw})


def _random_forest(**kw: Any) -> BaseEstimator:
    from sklearn.ensemble import RandomForestRegressor

    params = {"n_estimators": 50, "min_samples_split": 2, "max_features": 1.0, "n_jobs": -1, "random_state": 0}
    return RandomForestRegressor(**{**params, **kw})


#: LightGBM's default thread count. One thread: FQI fits many small boosters (one per
#: iteration, on at most a few million rows), where LightGBM's OpenMP threads cost more than
#: they give, and on a machine that is also running other work they spin-wait at every
#: parallel region for a core that is busy elsewhere: a car-on-the-hill fit with ``n_jobs=-1``
#: burned more than 190 CPU-s without finishing on a loaded 2-core machine that ``n_jobs=1``
#: fitted in 14 CPU-s (docs/scaling.md, "LightGBM threads"). The OpenMP wait policy
#: (``OMP_WAIT_POLICY=passive``) would stop the spinning, but it is read once, when the
#: OpenMP runtime loads (often already done by numpy/scikit-learn before this module is
#: imported), so a library cannot set it reliably; a user can, in the environment, before
#: starting Python, and then pass ``regressor_params = {n_jobs = <physical cores>}`` for
#: large fits on an otherwise idle machine.
LIGHTGBM_DEFAULT_THREADS = 1


def _lightgbm(**kw: Any) -> BaseEstimator:
    from lightgbm import LGBMRegressor

    params = {"n_estimators": 100, "num_leaves": 31, "learning_rate": 0.1, "verbose": -1, "random_state": 0,
              "n_jobs": LIGHTGBM_DEFAULT_THREADS}
    return LGBMRegressor(**{**params, **kw})


def _knn(**kw: Any) -> BaseEstimator:
    from sklearn.neighbors import KNeighborsRegressor

    return KNeighborsRegressor(**{"n_neighbors": 5, "weights": "distance", **kw})


def _ridge(degree: int = 2, alpha: float = 1e-8, **kw: Any) -> BaseEstimator:
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures

    return make_pipeline(PolynomialFeatures(degree=degree), Ridge(alpha=alpha, **kw))


def _linear(**kw: Any) -> BaseEstimator:
    from sklearn.linear_model import LinearRegression

    return LinearRegression(**kw)


def _mlp(**kw: Any) -> BaseEstimator:
    from sklearn.neural_network import MLPRegressor

    return MLPRegressor(**{"hidden_layer_sizes": (64, 64), "max_iter": 500, "random_state": 0, **kw})


REGRESSORS: dict[str, Callable[..., BaseEstimator]] = {
    "extra_trees": _extra_trees,
    "random_forest": _random_forest,
    "lightgbm": _lightgbm,
    "knn": _knn,
    "ridge": _ridge,
    "linear": _linear,
    "mlp": _mlp,
    "tabular": lambda **kw: TabularRegressor(**kw),
}


def make_regressor(spec: str | BaseEstimator, **params: Any) -> BaseEstimator:
    """An unfitted regressor from a registry name (with parameters) or a clone of an estimator."""
    if not isinstance(spec, str):
        if params:
            return clone(spec).set_params(**params)
        return clone(spec)
    try:
        factory = REGRESSORS[spec]
    except KeyError:
        raise UnknownNameError(f"unknown regressor {spec!r}; known: {sorted(REGRESSORS)}") from None
    try:
        return factory(**params)
    except TypeError as exc:
        raise UnknownNameError(f"regressor {spec!r}: bad parameters {sorted(params)} ({exc})") from None


#: registry forests that fit on all cores but predict on one thread unless ``n_jobs`` is given
_PREDICT_ON_ONE_THREAD = ("extra_trees", "random_forest")


def predict_n_jobs(spec: str | BaseEstimator, params: dict[str, Any] | None = None) -> int | None:
    """The ``n_jobs`` the refit learner predicts with for a regressor made by
    :func:`make_regressor` (None: as fitted). Registry forests fit on all cores by default;
    unless ``n_jobs`` was given they predict on one thread (threaded ``apply`` cost a few
    percent more CPU on a loaded machine, for no result change)."""
    if isinstance(spec, str) and spec in _PREDICT_ON_ONE_THREAD and "n_jobs" not in (params or {}):
        return 1
    return None


class TabularClassifier(ClassifierMixin, BaseEstimator):
    """Weighted majority label of each distinct input row (a lookup-table classifier).

    Unseen rows get the overall weighted majority label; ties go to the smallest label.
    """

    def fit(self, X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None = None) -> TabularClassifier:
        X, y = validate_data(self, X, y, dtype=np.float64)
        check_classification_targets(y)
        w = _check_sample_weight(sample_weight, X, dtype=np.float64)
        if not (w > 0).any():
            raise InvalidArgumentError("TabularClassifier: every sample weight is zero; there is no data to fit")
        X, y, w = X[w > 0], y[w > 0], w[w > 0]
        rows = _fit_codes(self, X)
        self.classes_, yi = np.unique(y, return_inverse=True)
        keys, inv = np.unique(rows, return_inverse=True)
        votes = np.zeros((len(keys), len(self.classes_)))
        np.add.at(votes, (inv.reshape(-1), yi.reshape(-1)), w)
        self.keys_, self.labels_ = keys, self.classes_[votes.argmax(axis=1)]
        self.default_ = self.classes_[np.bincount(yi.reshape(-1), weights=w, minlength=len(self.classes_)).argmax()]
        return self

    def predict(self, X: np.ndarray) -> np.ndarray:
        pos, hit = _table_rows(self, X)
        return np.where(hit, self.labels_[pos], self.default_)


def _lgbm_classifier(**kw: Any) -> BaseEstimator:
    from lightgbm import LGBMClassifier

    return LGBMClassifier(**{"n_estimators": 50, "num_leaves": 15, "verbose": -1, "random_state": 0, "n_jobs": 1, **kw})


def _extra_trees_classifier(**kw: Any) -> BaseEstimator:
    from sklearn.ensemble import ExtraTreesClassifier

    return ExtraTreesClassifier(**{"n_estimators": 30, "min_samples_leaf": 2, "max_features": 1.0, "n_jobs": 1,
                                   "random_state": 0, **kw})


CLASSIFIERS: dict[str, Callable[..., BaseEstimator]] = {
    "lightgbm": _lgbm_classifier,
    "extra_trees": _extra_trees_classifier,
    "tabular": lambda **kw: TabularClassifier(**kw),
}


def make_classifier(spec: str | BaseEstimator, **params: Any) -> BaseEstimator:
    """An unfitted classifier from a registry name (``lightgbm``, ``extra_trees``,
    ``tabular``) or a clone of a scikit-learn classifier."""
    if not isinstance(spec, str):
        return clone(spec).set_params(**params) if params else clone(spec)
    try:
        return CLASSIFIERS[spec](**params)
    except KeyError:
        raise UnknownNameError(f"unknown classifier {spec!r}; known: {sorted(CLASSIFIERS)}") from None


def binary_proba(spec: str | BaseEstimator, params: dict[str, Any] | None, X: np.ndarray, y: np.ndarray,
                 X_new: np.ndarray) -> np.ndarray:
    """``make_classifier(spec, **params).fit(X, y).predict_proba(X_new)[:, 1]`` for two
    classes. The registry's LightGBM classifier trains with the calls ``LGBMClassifier.fit``
    makes (its own parameters, labels and rounds into ``lightgbm.train``) and predicts with
    the ones ``predict_proba`` makes, without the wrapper's per-fit parameter copies and the
    trained model's round trip through text (about half of a fit's CPU on a few hundred
    rows): the same probabilities bit for bit (``tests/test_forest_predict.py``). Any other
    classifier, or a LightGBM that does not take these calls, is fitted as given."""
    clf = make_classifier(spec, **(params or {}))
    fast = _lightgbm_binary(clf, X, y, X_new) if spec == "lightgbm" else None
    return clf.fit(X, y).predict_proba(X_new)[:, 1] if fast is None else fast


def _lightgbm_binary(clf: Any, X: np.ndarray, y: np.ndarray, X_new: np.ndarray) -> np.ndarray | None:
    from lightgbm import Dataset, LGBMClassifier, train

    classes = np.unique(y)
    if (
        type(clf) is not LGBMClassifier
        or clf.objective is not None
        or clf.class_weight is not None
        or len(classes) != 2
    ):
        return None
    try:
        clf._n_classes, clf._objective = 2, None  # what fit sets for two classes before reading its parameters
        params = clf._process_params(stage="fit")
        metric = params["metric"]
        params["metric"] = [m for m in ([metric] if isinstance(metric, str | None) else metric) if m is not None]
        data = Dataset(data=np.asarray(X, dtype=np.float64), label=np.searchsorted(classes, y), weight=None, group=None,
                       init_score=None, categorical_feature="auto", feature_name="auto", params=params)
        booster = train(params=params, train_set=data, num_boost_round=clf.n_estimators, valid_sets=[],
                        valid_names=None, feval=[], init_model=None, callbacks=[], keep_training_booster=True)
        pred = clf._process_params(stage="predict")
        for alias in ("data", "X", "raw_score", "start_iteration", "num_iteration", "pred_leaf", "pred_contrib"):
            pred.pop(alias, None)
        pred.pop("n_jobs", None)
        pred["num_threads"] = clf._process_n_jobs(clf.n_jobs)
        out = booster.predict(np.asarray(X_new, dtype=np.float64), raw_score=False, start_iteration=0,
                              num_iteration=None, pred_leaf=False, pred_contrib=False, validate_features=False, **pred)
    except (AttributeError, TypeError, KeyError):  # a LightGBM whose wrapper works otherwise: fit it
        return None
    return np.asarray(out, dtype=np.float64)
