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


@pytest.mark.parametrize("radius_scale", [0.37, 1.37, 50.0])
@pytest.mark.parametrize("policy", ["deterministic", "uniform"])
def test_near_pairs_give_the_filtered_product(small_pt, monkeypatch, radius_scale, policy):
    """Where leaves hold many rows of an action the per-action read streams the product's terms
    and keeps only the pairs within the radius (fqe_bootstrap.near_pairs) instead of making
    every (query, row) term and filtering: the same operators and the same bounds, on leaves
    of 10+ rows, at a radius that keeps few pairs, one that keeps more, and one that keeps all."""
    from offline_adp.algorithms import fqe_bootstrap
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.policies import UniformPolicy

    A = small_pt.n_actions
    pol = UniformPolicy(A) if policy == "uniform" else \
        FunctionPolicy(lambda x, t=0: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    fqe = FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=8,
                            regressor_params={"n_estimators": 5, "min_samples_leaf": 10}).fit(small_pt)
    fit = fqe.fit_state_
    d = fit.data
    radius = radius_scale * fqe_bootstrap.support_radius(d.obs, np.asarray(d.train.actions), d.obs_std)
    out = {}
    for name, limit in (("product", np.inf), ("near", 0.0)):
        monkeypatch.setattr(fqe_bootstrap, "MAX_PAIRS_PER_ENTRY", limit)
        out[name] = fqe_bootstrap.support_operators(d, fit.backup, fit.learner, None, 1e-9, radius)
    (P, u, P0, u0), (Pn, un, P0n, u0n) = out["product"], out["near"]
    assert P.nnz > 0 and Pn.nnz > 0
    np.testing.assert_allclose(Pn.toarray(), P.toarray(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(P0n.toarray(), P0.toarray(), rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(un, u)
    np.testing.assert_array_equal(u0n, u0)
    for B in (-5.0, 5.0):
        assert fqe_bootstrap.bounded_value(d, Pn, un, P0n, u0n, B) == pytest.approx(
            fqe_bootstrap.bounded_value(d, P, u, P0, u0, B), rel=1e-9, abs=1e-12)
    L = len(fit.learner.leaf_ids)
    terms, entries = fqe_bootstrap.query_terms(fit.learner.pos["next"], slice(0, d.n),
                                               fqe_bootstrap.leaf_counts(fit.learner, np.ones(d.n, bool)), L)
    assert terms > 4.0 * entries  # leaves of 10+ rows: the streamed path


def test_near_pairs_keep_exact_duplicates_at_radius_zero_in_many_dimensions():
    """Repeated states give a support radius of 0; in 16 features every query still pairs
    with the rows at its very state (distances taken as the product path takes them), and
    a leaf's weight is split over its rows of the action."""
    from offline_adp.algorithms.fqe_bootstrap import near_pairs

    rng = np.random.default_rng(0)
    X = np.repeat(rng.normal(size=(6, 16)) * 1e3, 3, axis=0)  # 6 states, each logged 3 times
    n = len(X)
    pos = np.repeat(np.arange(2)[:, None], n, axis=1)  # two trees, one leaf each (leaves 0, 1) holding every row
    K = near_pairs(pos, 0, pos, X, X, np.full(16, 7.0), np.ones(n), np.full(2, float(n)), 0.0, 2)
    same = (np.arange(n)[:, None] // 3) == (np.arange(n)[None, :] // 3)
    np.testing.assert_array_equal(K.toarray() > 0, same)
    np.testing.assert_allclose(K.toarray()[same], 1.0 / n)  # both trees, (1/2) (1/n) each


def test_support_radius_reads_the_spacing_of_all_rows_not_of_its_sample():
    """The radius is a quantile of each sampled row's distance to its nearest other row of its
    action among *all* of them (brute force here), so above ``max_rows`` it is the data's spacing
    (uniform states: ~``n ** -1/2`` in 2-D), not the sample's ``(n / max_rows) ** 1/2`` times
    wider one."""
    from offline_adp.algorithms.fqe_bootstrap import support_radius

    rng = np.random.default_rng(1)
    obs = rng.uniform(size=(40_000, 2))
    actions = rng.integers(0, 2, len(obs))
    std = obs.std(axis=0)
    full = support_radius(obs, actions, std, max_rows=len(obs))
    sampled = support_radius(obs, actions, std, max_rows=2_000)
    assert sampled == pytest.approx(full, rel=0.15)
    # the brute-force reading of the same sample
    r = np.random.default_rng(0)
    d = []
    for b in (0, 1):
        X = obs[actions == b] / std
        q = X[r.choice(len(X), 2_000, replace=False)]
        for c in range(0, len(q), 250):  # (250, ~20k) distances at a time
            d2 = ((q[c:c + 250, None, :] - X[None, :, :]) ** 2).sum(axis=2)
            d.append(np.sqrt(np.partition(d2, 1, axis=1)[:, 1]))
    assert sampled == pytest.approx(float(np.quantile(np.concatenate(d), 0.99)), rel=1e-12)
