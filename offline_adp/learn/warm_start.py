"""The warm-started LightGBM LEARN step: a few boosted trees per iteration on the change in targets."""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError
from offline_adp.learn.base import Learner, LearnSpec
from offline_adp.qfunctions import BoostedSumQ, QFunction


class LightGBMWarmStartLearner(Learner):
    """Warm-started boosting: each iteration adds ``trees_per_iteration`` trees fitted to
    the residual ``y_k - Q_{k-1}`` on the training pairs, boosted from its (weighted)
    mean, so ``Q_k = Q_{k-1} + mean residual + new trees``: a constant change of the
    targets (every logged cost the same) is learned, not lost. Cached predictions make
    each step cost only the new trees. Joint encoding only. LightGBM parameters come from
    a LightGBM regressor; any other regressor gets ``num_leaves=63, learning_rate=0.3``
    (10 trees then go ~97% of the way to each iteration's targets).
    """

    def __init__(self, spec: LearnSpec, trees_per_iteration: int = 10) -> None:
        super().__init__(spec)
        if self.encoder.per_action:
            raise InvalidArgumentError("the LightGBM warm-start mode needs action_encoding='joint'")
        import lightgbm as lgb

        self.lgb = lgb
        self.params = self.booster_params(self.regressor, self.seed)
        self.trees_per_iteration = trees_per_iteration
        self.X = {name: self._joint(phi, a) for name, (phi, a) in self.queries.items()}
        self.cache = {name: np.zeros(len(X)) for name, X in self.X.items()}
        self.boosters: list[Any] = []
        self.data = self.lgb.Dataset(self.X["train"], label=np.zeros(len(self.X["train"])), weight=self.weights,
                                     free_raw_data=False, params={"verbose": -1})

    @staticmethod
    def booster_params(regressor: Any, seed: int) -> dict[str, Any]:
        """``lightgbm.train`` parameters of one iteration's trees (also the Dask engine's)."""
        p = regressor.get_params() if type(regressor).__name__.startswith("LGBM") else {}
        return {
            "objective": "regression",
            "num_leaves": p.get("num_leaves", 63),
            "learning_rate": p.get("learning_rate") if p.get("learning_rate") is not None else 0.3,
            "min_data_in_leaf": p.get("min_child_samples", 20),
            "verbose": -1,
            # one thread unless the regressor asks for more: on a loaded machine LightGBM's
            # spinning OpenMP threads burned 5-50x the CPU of a single thread at 10k-50k rows
            "num_threads": p.get("n_jobs") if (p.get("n_jobs") or 0) > 0 else 1,
            "seed": seed,
            "deterministic": True,
            "boost_from_average": True,
        }

    def fit(self, y: np.ndarray, k: int) -> None:
        self.data.set_label(y - self.cache["train"])  # the residual; its mean goes into the first tree
        booster = self.lgb.train({**self.params, "seed": self.seed + k}, self.data,
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

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        self.boosters = [getattr(b, "booster", b) for b in q.boosters]  # type: ignore[attr-defined]
        for name, X in self.X.items():  # the same sums, in the same order, as when fitting
            c = np.zeros(len(X))
            for b in self.boosters:
                c = c + b.predict(X, raw_score=True)
            self.cache[name] = c
