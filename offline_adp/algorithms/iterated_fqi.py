"""Iterated fitted Q-iteration: alternate FQI with collecting data from its policy.

Access model: a reset model (or stronger) plus optional initial trace data. The chapter:
"run [FQI] repeatedly, augmenting the data set with new samples from the resulting
policies"::

    D_0 = initial data (or episodes of the exploration policy)
    for r = 1, ..., R:
        Q_r = FQI(D_{r-1})
        pi_r = greedy(Q_r)
        V_r = rollout value of pi_r                      (for the history only)
        D_r = D_{r-1} + episodes of (1 - eps) pi_r + eps uniform
    return the pi_r with the best V_r
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from sklearn.base import clone

from offline_adp.access import ResetModel, require
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.params import FRACTION, POSITIVE_INT, SEED, CheckedEstimator
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import IncompatibleError
from offline_adp.policies import EpsilonPolicy, UniformPolicy
from offline_adp.rollout import rollout


class IteratedFQI(CheckedEstimator):
    """Fitted Q-iteration with data collection between rounds.

    Parameters
    ----------
    fqi : FittedQIteration
        The prototype, cloned for every round.
    n_rounds : int
    episodes_per_round : int
        Episodes collected from the current policy after each round.
    epsilon : float
        Exploration mixed into the collecting policy.
    n_eval_episodes : int
        Rollouts to estimate each round's policy value (mean discounted cost).
    horizon : int or None
        Episode length for collection and evaluation (default: the model's).
    random_state : int

    Attributes
    ----------
    policy_ : the best round's greedy policy
    fqi_ : the best round's fitted FQI
    dataset_ : the final, augmented dataset
    history_ : DataFrame with ``round, n_transitions, value, value_low, value_high, fit_seconds``
    """

    _parameter_constraints: ClassVar[dict[str, list[Any]]] = {
        "fqi": [FittedQIteration, None],
        "n_rounds": [POSITIVE_INT],
        "episodes_per_round": [POSITIVE_INT],
        "epsilon": [FRACTION],
        "n_eval_episodes": [POSITIVE_INT],
        "horizon": [POSITIVE_INT, None],
        "random_state": [SEED],
    }

    def __init__(self, fqi: FittedQIteration | None = None, n_rounds: int = 5, episodes_per_round: int = 50,
                 epsilon: float = 0.1, n_eval_episodes: int = 200, horizon: int | None = None,
                 random_state: int = 0) -> None:
        self.fqi = fqi
        self.n_rounds = n_rounds
        self.episodes_per_round = episodes_per_round
        self.epsilon = epsilon
        self.n_eval_episodes = n_eval_episodes
        self.horizon = horizon
        self.random_state = random_state

    def fit(self, model: ResetModel, dataset: TransitionDataset | None = None) -> IteratedFQI:
        self.check_params()  # _parameter_constraints, then the combinations
        require(model, ResetModel)
        rng = np.random.default_rng(self.random_state)
        proto = self.fqi if self.fqi is not None else FittedQIteration()
        if dataset is not None and dataset.info.action_table.continuous and proto.commands != "binned":
            raise IncompatibleError(
                f"{type(self).__name__} adds episodes of an epsilon-greedy policy over the action table, which logs "
                f"no exact commands ({list(dataset.info.action_table.dims)} in this dataset are continuous); fit "
                "'fqi' on the logs, or give it FittedQIteration(commands='binned') to iterate over the bins")
        H = self.horizon if self.horizon is not None else model.horizon
        from offline_adp.rollout import collect

        data = dataset
        if data is None:
            data = collect(model, UniformPolicy(model.n_actions), self.episodes_per_round, rng, horizon=H,  # type: ignore[arg-type]
                           source="exploration", episode_prefix="r00")
        rows: list[dict[str, Any]] = []
        best = None
        for r in range(1, self.n_rounds + 1):
            t0 = time.perf_counter()
            fqi = clone(proto).fit(data)  # Q_r = FQI(D_{r-1})
            fit_s = time.perf_counter() - t0
            res = rollout(model, fqi.policy_, self.n_eval_episodes, rng, horizon=H)  # V_r
            lo, hi = res.interval()
            rows.append({"round": r, "n_transitions": len(data), "value": res.mean, "value_low": lo, "value_high": hi,
                         "fit_seconds": fit_s})
            if best is None or res.mean < best[0]:
                best = (res.mean, fqi)
            if r < self.n_rounds:  # D_r = D_{r-1} + episodes of the eps-greedy pi_r
                new = collect(model, EpsilonPolicy(fqi.policy_, self.epsilon), self.episodes_per_round, rng,  # type: ignore[arg-type]
                              horizon=H, source="policy", episode_prefix=f"r{r:02d}")
                data = TransitionDataset.concat([data, new])
        assert best is not None
        self.fqi_, self.policy_ = best[1], best[1].policy_
        self.dataset_ = data
        self.history_ = pd.DataFrame(rows)
        return self
