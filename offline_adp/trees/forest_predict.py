"""``predict`` of a fitted scikit-learn regression forest by the compiled leaf lookups, with
scikit-learn's numbers.

A forest's ``predict`` validates its input and dispatches every tree through joblib: about
0.2 ms a tree whatever the rows, which a model rolled out step by step pays at every step
(20 trees, two forests, 200 steps: 8,000 dispatches). :func:`forest_predictor` reads the
same trees with :class:`~offline_adp.trees.compact.CompactTree` (the leaves scikit-learn's
``apply`` reaches, inputs compared as float32) and sums the trees' leaf values as
``ForestRegressor.predict`` does on one thread (``y = 0; y += tree_k(X)`` in the trees'
order, then ``y /= n_trees``): the same numbers bit for bit (tests/test_forest_predict.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from offline_adp.trees.compact import CompactTree
from offline_adp.trees.jit import available, kernel


def forest_predictor(forest: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """``forest.predict`` (a fitted scikit-learn ``ExtraTreesRegressor`` or
    ``RandomForestRegressor`` on dense inputs) as a function of a float array, or None when
    the compiled lookup is not available or the forest is not one of those."""
    from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor

    if not available() or type(forest) not in (ExtraTreesRegressor, RandomForestRegressor):
        return None
    from offline_adp.trees.pairs import packed_nodes

    trees = [est.tree_ for est in forest.estimators_]
    sizes = np.array([t.node_count for t in trees], dtype=np.int64)
    roots = np.r_[0, np.cumsum(sizes)[:-1]]
    if sizes.sum() >= 2**31 - 1:
        return None
    left = np.concatenate([np.where(t.children_left < 0, -1,
                                    t.children_left + r) for t, r in zip(trees, roots, strict=True)])
    right = np.concatenate([np.where(t.children_right < 0, -1, t.children_right + r)
                            for t, r in zip(trees, roots, strict=True)])
    packed = packed_nodes(left, right, np.concatenate([t.feature for t in trees]),
                          np.concatenate([t.threshold for t in trees]))
    # (nodes, outputs)
    values = np.ascontiguousarray(np.concatenate([t.value[:, :, 0] for t in trees]), dtype=np.float64)
    n_features, n_outputs = forest.n_features_in_, forest.n_outputs_

    def predict(X: np.ndarray) -> np.ndarray:
        X32 = np.ascontiguousarray(X, dtype=np.float32)
        if X32.ndim != 2 or X32.shape[1] != n_features:
            raise ValueError(f"the forest reads {n_features} features, got an input of shape {np.shape(X)}")
        if not np.isfinite(X32).all():  # NaN (scikit-learn sends it to a learned side) or inf: its own predict
            return forest.predict(X)
        y = np.zeros((len(X32), n_outputs))
        _forest_sum(packed, packed.view(np.float32), roots, values, X32, y)
        return y if n_outputs > 1 else y[:, 0]

    return predict


def _forest_sum(packed: Any, packed_f: Any, roots: Any, values: Any, X: Any, y: Any) -> None:
    """``y[i] = (sum over trees, in order, of the value of the leaf row i reaches) / n_trees``,
    each sum accumulated from 0 tree by tree as ``ForestRegressor.predict`` accumulates its
    ``y_hat`` (then divided in place by the tree count): the same numbers."""
    n, m = X.shape[0], roots.shape[0]
    for j in range(m):
        for i in range(n):
            node = roots[j]
            while True:
                rec = 4 * node
                if packed[rec] < 0:
                    break
                node = packed[rec] if X[i, packed[rec + 2]] <= packed_f[rec + 3] else packed[rec + 1]
            for o in range(y.shape[1]):
                y[i, o] += values[node, o]
    for i in range(n):
        for o in range(y.shape[1]):
            y[i, o] /= m


_forest_sum = kernel(_forest_sum, cache=True, nogil=True, boundscheck=False)


def linear_predictor(model: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """``model.predict`` of a fitted scikit-learn ``Ridge`` or ``LinearRegression`` on dense
    float64 inputs, ``X @ coef_.T + intercept_`` as scikit-learn computes it, without its
    input validation; None for any other model."""
    from sklearn.linear_model import LinearRegression, Ridge

    if type(model) not in (Ridge, LinearRegression):
        return None
    coef_t, intercept = model.coef_.T, model.intercept_

    def predict(X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != model.n_features_in_:
            raise ValueError(f"the model reads {model.n_features_in_} features, got an input of shape {np.shape(X)}")
        return X @ coef_t + intercept

    return predict


def extra_trees_fit_predict(forest: Any, X: np.ndarray, y: np.ndarray, X_new: np.ndarray) -> np.ndarray | None:
    """``predict_model(forest.fit(X, y), X_new)`` for an unfitted scikit-learn
    ``ExtraTreesRegressor`` (one output, no sample weights) bit for bit, without the forest's per-tree clone and
    parameter introspection (about 4 of the 5 ms a fit of ten trees on a few hundred rows
    costs): the trees are scikit-learn's own, built as ``ForestRegressor.fit`` builds them
    without a bootstrap (each tree's seed drawn in turn from ``RandomState(random_state)``,
    ``tree._fit`` on the float32 inputs), read by the compiled lookups and averaged over
    trees in order as :func:`~offline_adp.trees.ensemble.ensemble_predict` does. None when
    it does not apply (numba missing, a bootstrap or ``max_samples``, an integer seed not given,
    inputs that are not all finite, or a
    scikit-learn whose private tree-building differs: then fit the forest)."""
    from sklearn.ensemble import ExtraTreesRegressor

    if (
        not available()
        or type(forest) is not ExtraTreesRegressor
        or forest.bootstrap
        or not isinstance(forest.random_state, int)
        or np.ndim(y) != 1
        or forest.max_samples is not None  # scikit-learn refuses it without a bootstrap
        or forest.criterion == "poisson"  # its checks on y are scikit-learn's fit's
        or not (np.isfinite(X).all() and np.isfinite(y).all() and np.isfinite(X_new).all())
    ):
        return None
    try:
        X32 = np.ascontiguousarray(X, dtype=np.float32)
        y2 = np.ascontiguousarray(np.reshape(y, (-1, 1)), dtype=np.float64)
        tree_params = {p: getattr(forest, p) for p in forest.estimator_params}
        mask = type(forest.estimator)(criterion=forest.criterion)._compute_missing_values_in_feature_mask(
            X32, estimator_name=type(forest).__name__)
        rs = np.random.RandomState(forest.random_state)
        new32 = np.ascontiguousarray(X_new, dtype=np.float32)
        out = np.empty((len(new32), forest.n_estimators))
        for j in range(forest.n_estimators):
            tree = type(forest.estimator)(**{**tree_params, "random_state": rs.randint(np.iinfo(np.int32).max)})
            tree._fit(X32, y2, sample_weight=None, check_input=False, missing_values_in_feature_mask=mask)
            t = tree.tree_
            lookup = CompactTree(t.children_left, t.children_right, t.feature, t.threshold, t.value[:, 0, 0])
            out[:, j] = t.value[:, 0, 0][lookup.apply(new32)]
    except (AttributeError, TypeError):  # scikit-learn's private tree-building changed shape
        return None
    return out.mean(axis=1)
