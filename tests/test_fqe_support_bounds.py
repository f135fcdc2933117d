"""FQE's interval accounts for pairs the logs never saw (docs/evaluation.md, section 2).

A deterministic chain with a known value: every action moves s -> s + 1 (s = 0..9, 9
absorbing); action 1 costs 1 at s >= 5, everything else costs 0. The logs take both
actions at s < 5 and only action 0 at s >= 5; a few episodes sit at a far state s = 100
(action 0, cost 1, absorbing), so the logged costs span [0, 1]. The policy "always 1" pays
from step 5 on in the chain (``sum_{t=5}^{T-1} gamma^t``) and at every step at s = 100.
The joint (x, a) trees read ``Q(s >= 5, 1)`` from action 0's rows (cost 0), so the sampling
interval sits far below the truth; the support bounds value the unseen pairs at the ends
of the cost's value range, and the widened interval holds the truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.evaluation.fqe_interval import q_value_range
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.policies import FunctionPolicy

GAMMA, T, N_EPISODES, N_FAR = 0.95, 100, 30, 4


def _chain_logs(seed: int = 0) -> TransitionDataset:
    rng = np.random.default_rng(seed)
    s = np.r_[np.tile(np.minimum(np.arange(T), 9), N_EPISODES), np.full(T * N_FAR, 100)].astype(np.float64)
    action = np.where(s < 5, rng.integers(0, 2, len(s)), 0)
    cost = (((action == 1) & (s >= 5)) | (s == 100)).astype(np.float64)
    n_ep = N_EPISODES + N_FAR
    info = DatasetInfo(features=(Feature("s"),), action_table=ActionTable.from_values([0.0, 1.0]), gamma=GAMMA,
                       horizon=T)
    return TransitionDataset.from_arrays(
        info, episode_id=np.repeat(np.arange(n_ep).astype(str), T), step=np.tile(np.arange(T), n_ep),
        obs=s[:, None], action=action, cost=cost, next_obs=np.where(s == 100, s, np.minimum(s + 1, 9))[:, None],
        terminated=np.zeros(len(s), bool), truncated=np.tile(np.arange(T) == T - 1, n_ep))


def _always(a: int) -> FunctionPolicy:
    return FunctionPolicy(lambda x, t=0: np.full(len(x), a, np.int64), 2)


@pytest.fixture(scope="module")
def logs() -> TransitionDataset:
    return _chain_logs()


def test_an_unlogged_action_widens_the_interval_to_hold_the_truth(logs):
    chain, far = float(np.sum(GAMMA ** np.arange(5, T))), float(np.sum(GAMMA ** np.arange(T)))
    truth = (N_EPISODES * chain + N_FAR * far) / (N_EPISODES + N_FAR)  # the data's start states
    res = off_policy(logs, _always(1), n_boot=20, psdp_folds=0, seed=0)
    fq = res.estimates["fqe"]
    assert fq.level == 0.95
    assert fq.interval[0] <= truth <= fq.interval[1]
    # the sampling interval alone (the interval before the widening) misses the truth by far
    assert fq.percentile_interval[1] < truth - 5
    sb = fq.support_bounds
    assert sb["unsupported_next"] > 0.3  # the policy's action at s >= 5 has no logged row there
    assert sb["upper"] >= truth - 1e-6


def test_a_policy_the_logs_cover_keeps_a_tight_interval(logs):
    # "always 0" is logged at every state: nothing is unsupported, the bounds are the estimate itself
    # (the support bounds alone: the model rollouts' own widening is tests/test_model_rollouts.py's)
    truth = N_FAR * float(np.sum(GAMMA ** np.arange(T))) / (N_EPISODES + N_FAR)
    res = off_policy(logs, _always(0), n_boot=20, psdp_folds=0, seed=0, model_particles=0)
    fq = res.estimates["fqe"]
    sb = fq.support_bounds
    assert sb["unsupported_next"] == 0.0 and sb["unsupported_start"] == 0.0
    assert sb["lower"] == pytest.approx(fq.estimate, abs=1e-4) and sb["upper"] == pytest.approx(fq.estimate, abs=1e-4)
    assert fq.interval[0] <= truth <= fq.interval[1]
    assert "widened to the support bounds" in fq.interval_method
    lo, hi = fq.percentile_interval
    assert (
        lo - res.estimand.tail_bound - 1e-9 <= fq.interval[0] and fq.interval[1] <= hi + res.estimand.tail_bound + 1e-9
    )


def test_q_value_range_bounds_every_path():
    cost = np.array([0.2, 1.0, 50.0, 0.5])
    term = np.array([False, False, True, False])
    lo, hi = q_value_range(cost, term, 0.9)
    assert lo == pytest.approx(min(0.2 / 0.1, 50.0)) and hi == pytest.approx(max(1.0 / 0.1, 50.0))
    assert q_value_range(cost, term, 0.9, infeasible_cost=20.0)[1] == 20.0
