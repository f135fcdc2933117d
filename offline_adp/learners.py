"""How one fitted-Q step ``Q_k = LEARN({(x_i, a_i), y_i})`` is carried out.

Fitted Q-iteration and fitted Q evaluation share the same inner step; what differs is
the targets. A *learner* owns the regression inputs of the training pairs and of every
query set the algorithm needs (next states for the targets, start states, held-out
pairs) and answers ``fit(y)`` then ``predict(name)``:

- :class:`RefitLearner` (the naive loop): clone and fit the regressor on every
  iteration; prediction is one batched call per query set.
- :class:`FrozenTreesLearner` (Ernst et al. 2005, section 4.3): fit a tree ensemble's
  *structure* once (and again on demand), precompute the leaf reached by every training
  and query input, and thereafter only re-average leaf values: an O(n * trees) gather,
  no tree fitting or traversal. With a fixed structure the update is a kernel averager,
  hence a gamma-contraction: it converges.
- :class:`LightGBMWarmStartLearner`: each iteration adds a few boosted trees fitted to
  the change in targets, with the previous Q's predictions on the fixed training and
  query inputs cached, so only the new trees are evaluated.

Query sets are ``(phi, actions)`` pairs: ``actions=None`` asks for all actions
(result (m, n_actions)), otherwise for the given action per row (result (m,)).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.base import clone

from offline_adp.qfunctions import (
    QEncoder,
    QFunction,
    RegressorQ,
    TreeEnsemble,
    TreeQ,
    predict_model,
    sklearn_leaves,
)

Query = tuple[np.ndarray, np.ndarray | None]


def _seeded(model: Any, seed: int) -> Any:
    if "random_state" in model.get_params():
        model.set_params(random_state=seed)
    return model


def _fit(model: Any, X: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> Any:
    if w is None:
        return model.fit(X, y)
    try:
        return model.fit(X, y, sample_weight=w)
    except TypeError:  # pipelines route weights by step name
        last = model.steps[-1][0]
        return model.fit(X, y, **{f"{last}__sample_weight": w})


class Learner:
    """Base: training pairs ``(phi, actions)``, weights, and named query sets."""

    def __init__(self, regressor: Any, encoder: QEncoder, phi: np.ndarray, actions: np.ndarray,
                 queries: dict[str, Query], weights: np.ndarray | None = None, seed: int = 0) -> None:
        self.regressor, self.encoder = regressor, encoder
        self.phi, self.actions, self.weights, self.seed = phi, np.asarray(actions, dtype=np.int64), weights, seed
        self.queries = {"train": (phi, self.actions), **queries}
        self.iteration = 0

    def fit(self, y: np.ndarray) -> None:
        raise NotImplementedError

    def predict(self, name: str) -> np.ndarray:
        raise NotImplementedError

    def snapshot(self) -> QFunction:
        """The current Q as a standalone Q-function."""
        raise NotImplementedError

    def restore(self, q: QFunction, iteration: int) -> None:
        """Continue from a saved ``Q_k`` (iteration ``k`` done)."""
        raise NotImplementedError(f"{type(self).__name__} cannot resume")

    @staticmethod
    def _select(q_all: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return q_all if actions is None else q_all[np.arange(len(actions)), actions]


class RefitLearner(Learner):
    """Clone and refit LEARN on every iteration (any scikit-learn regressor)."""

    def fit(self, y: np.ndarray) -> None:
        self.iteration += 1
        seed = self.seed + self.iteration
        if self.encoder.per_action:
            models = []
            for a in range(self.encoder.n_actions):
                rows = self.actions == a
                m = _seeded(clone(self.regressor), seed)
                if not rows.any():
                    raise ValueError(f"action {a} never occurs in the data: a per-action model cannot be fitted")
                models.append(_fit(m, self.phi[rows], y[rows], None if self.weights is None else self.weights[rows]))
        else:
            m = _seeded(clone(self.regressor), seed)
            models = [_fit(m, self.encoder.pairs(self.phi, self.actions), y, self.weights)]
        self.q = RegressorQ(models, self.encoder)

    def predict(self, name: str) -> np.ndarray:
        phi, actions = self.queries[name]
        if actions is not None and not self.encoder.per_action:
            return predict_model(self.q.models[0], self.encoder.pairs(phi, actions))
        return self._select(self.q.values_phi(phi), actions)

    def snapshot(self) -> QFunction:
        return self.q

    def restore(self, q: QFunction, iteration: int) -> None:
        self.q, self.iteration = q, iteration  # type: ignore[assignment]


class FrozenTreesLearner(Learner):
    """Fixed tree structure, leaf values re-averaged each iteration (joint encoding only).

    The structure is (re)built by the next ``fit`` after :meth:`restructure` (and on the
    first ``fit``): the ensemble is fitted to that iteration's targets plus a tiny jitter
    (std ``1e-6 * (1 + std(y))``, so that trees grow fully even where the first targets
    are constant), and the leaves of every training and query input are computed once.
    With the structure fixed, each leaf's value is the weighted mean target of its
    training samples and a prediction is the mean over trees: two fixed sparse operators
    (a kernel averager whose rows sum to 1)::

        v_k = M @ y_k              M[leaf, i] = w_i / (sum of w in the leaf)
        Q_k(query) = A_query @ v_k  A_query[q, leaf] = 1 / n_trees for the q's leaves

    An iteration is a few sparse mat-vecs: no tree fitting, no traversal.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.encoder.per_action:
            raise ValueError("the frozen-structure mode needs action_encoding='joint'")
        self._rebuild = True
        self.structures = 0

    def restructure(self) -> None:
        self._rebuild = True

    def _build(self, y: np.ndarray) -> None:
        from scipy import sparse

        X = self.encoder.pairs(self.phi, self.actions)
        rng = np.random.default_rng([self.seed, self.iteration, 7])
        jitter = rng.normal(0.0, 1e-6 * (1.0 + float(np.std(y))), len(y))
        forest = _fit(_seeded(clone(self.regressor), self.seed + self.iteration), X, y + jitter, self.weights)
        if not hasattr(forest, "estimators_") or not hasattr(forest.estimators_[0], "tree_"):
            raise ValueError("the frozen-structure mode needs a scikit-learn tree ensemble (extra_trees, random_forest)")
        self.ensemble = TreeEnsemble.from_sklearn(forest)
        n, m = len(y), self.ensemble.n_trees
        train = sklearn_leaves(forest, X)  # (n, m) global leaf ids
        used = np.zeros(len(self.ensemble.value), bool)
        used[train.reshape(-1)] = True
        self.leaf_ids = np.flatnonzero(used)  # leaves holding training samples, compact index
        lookup = np.full(len(used), -1, np.int64)
        lookup[self.leaf_ids] = np.arange(len(self.leaf_ids))
        compact = lookup[train.reshape(-1)]
        w = np.ones(n) if self.weights is None else np.asarray(self.weights, dtype=np.float64)
        rows = np.repeat(np.arange(n), m)
        wsum = np.bincount(compact, weights=w[rows], minlength=len(self.leaf_ids))
        self.M = sparse.csr_matrix((w[rows] / wsum[compact], (compact, rows)), shape=(len(self.leaf_ids), n))
        self._compact, self._rows = compact, rows
        self.A: dict[str, Any] = {}
        for name, (phi, a) in self.queries.items():
            leaves = train if name == "train" else sklearn_leaves(forest, self._joint(phi, a))
            pos = lookup[leaves.reshape(-1)]
            hit = pos >= 0  # every leaf holds training samples unless their weights are 0
            qrows = np.repeat(np.arange(len(leaves)), m)[hit]
            self.A[name] = sparse.csr_matrix((np.full(hit.sum(), 1.0 / m), (qrows, pos[hit])), shape=(len(leaves), len(self.leaf_ids)))
        self._rebuild = False
        self.structures += 1

    def reweighted_operators(self, weights: np.ndarray) -> tuple[Any, dict[str, Any]]:
        """Leaf-averaging operator ``M`` and query operators ``A`` for other sample weights
        on the same structure. A leaf left with no weight is dropped from every query's
        average over trees (rows of ``A`` renormalised over the remaining trees; a query
        with none left keeps its original row)."""
        from scipy import sparse

        w = np.asarray(weights, dtype=np.float64)[self._rows]
        wsum = np.bincount(self._compact, weights=w, minlength=len(self.leaf_ids))
        vals = w / np.where(wsum[self._compact] > 0, wsum[self._compact], 1.0)
        M = sparse.csr_matrix((vals, (self._compact, self._rows)), shape=self.M.shape)
        keep = sparse.diags((wsum > 0).astype(np.float64))
        A = {}
        for name, op in self.A.items():
            kept = (op @ keep).tocsr()
            total = np.asarray(kept.sum(axis=1)).ravel()
            scale = sparse.diags(np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0))
            fallback = sparse.diags((total <= 0).astype(np.float64))
            A[name] = (scale @ kept + fallback @ op).tocsr()
        return M, A

    def fit(self, y: np.ndarray) -> None:
        self.iteration += 1
        if self._rebuild:
            self._build(y)
        self.leaf_values = self.M @ np.asarray(y, dtype=np.float64)  # leaf means of y_k

    def _joint(self, phi: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return self.encoder.all_pairs(phi) if actions is None else self.encoder.pairs(phi, actions)

    def predict(self, name: str) -> np.ndarray:
        phi, actions = self.queries[name]
        v = self.A[name] @ self.leaf_values  # mean over trees of the reached leaves
        return v if actions is not None else v.reshape(self.encoder.n_actions, len(phi)).T

    def snapshot(self) -> QFunction:
        value = self.ensemble.value.copy()
        value[self.leaf_ids] = self.leaf_values
        return TreeQ([self.ensemble.with_values(value)], self.encoder)


class BoostedSumQ(QFunction):
    """Q = sum of LightGBM boosters' raw scores on joint inputs."""

    def __init__(self, boosters: list[Any], encoder: QEncoder) -> None:
        self.boosters, self.encoder, self.n_actions = boosters, encoder, encoder.n_actions

    def values(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        X = self.encoder.all_pairs(self.encoder.phi(obs))
        s = sum(b.predict(X, raw_score=True) for b in self.boosters)
        return np.asarray(s, dtype=np.float64).reshape(self.n_actions, len(obs)).T


class LightGBMWarmStartLearner(Learner):
    """Warm-started boosting: each iteration adds ``trees_per_iteration`` trees fitted to
    ``y_k - Q_{k-1}`` on the training pairs; cached predictions make each step cost only
    the new trees. Joint encoding only; the regressor's LightGBM parameters are reused.
    """

    def __init__(self, *args: Any, trees_per_iteration: int = 10, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self.encoder.per_action:
            raise ValueError("the LightGBM warm-start mode needs action_encoding='joint'")
        import lightgbm as lgb

        self.lgb = lgb
        p = self.regressor.get_params() if hasattr(self.regressor, "get_params") else {}
        self.params = {
            "objective": "regression",
            "num_leaves": p.get("num_leaves", 31),
            "learning_rate": p.get("learning_rate", 0.1) if p.get("learning_rate") is not None else 0.1,
            "min_data_in_leaf": p.get("min_child_samples", 20),
            "verbose": -1,
            "num_threads": p.get("n_jobs", 0) if (p.get("n_jobs") or 0) > 0 else 0,
            "seed": self.seed,
            "deterministic": True,
        }
        self.trees_per_iteration = trees_per_iteration
        self.X = {name: self._joint(phi, a) for name, (phi, a) in self.queries.items()}
        self.cache = {name: np.zeros(len(X)) for name, X in self.X.items()}
        self.boosters: list[Any] = []
        self.data = self.lgb.Dataset(self.X["train"], label=np.zeros(len(self.X["train"])), weight=self.weights,
                                     free_raw_data=False, params={"verbose": -1})

    def _joint(self, phi: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return self.encoder.all_pairs(phi) if actions is None else self.encoder.pairs(phi, actions)

    def fit(self, y: np.ndarray) -> None:
        self.iteration += 1
        self.data.set_label(y)
        self.data.set_init_score(self.cache["train"])  # boost from the previous Q
        booster = self.lgb.train({**self.params, "seed": self.seed + self.iteration}, self.data,
                                 num_boost_round=self.trees_per_iteration)
        self.boosters.append(booster)
        for name, X in self.X.items():  # only the new trees are evaluated
            self.cache[name] = self.cache[name] + booster.predict(X, raw_score=True)

    def predict(self, name: str) -> np.ndarray:
        phi, actions = self.queries[name]
        v = self.cache[name]
        return v if actions is not None else v.reshape(self.encoder.n_actions, len(phi)).T

    def snapshot(self) -> QFunction:
        return BoostedSumQ(list(self.boosters), self.encoder)

    def restore(self, q: QFunction, iteration: int) -> None:
        self.boosters = [getattr(b, "booster", b) for b in q.boosters]  # type: ignore[attr-defined]
        self.iteration = iteration
        for name, X in self.X.items():  # the same sums, in the same order, as when fitting
            c = np.zeros(len(X))
            for b in self.boosters:
                c = c + b.predict(X, raw_score=True)
            self.cache[name] = c
