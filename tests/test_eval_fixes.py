"""Small fixes with known answers: CPI's Kakade-Langford step at gamma = 1, the PSDP bound's
0 x inf, PSDP's eps measured on held-out states,
FQE's bias-corrected estimate when its bootstrap replicates are shifted."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.cpi import ConservativePolicyIteration, effective_horizon
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.psdp import PSDP, psdp_bound
from offline_adp.envs import TabularMDP
from offline_adp.evaluation.psdp_eps import psdp_bound as plugin_bound
from offline_adp.policies import UniformPolicy
from tests.test_fqi import full_support_dataset


def _exact_finite(m, policy, T):
    states = np.arange(float(m.n_states))[:, None]
    pi = np.stack([policy.probabilities(states, t) for t in range(T)])
    return float(m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, pi, T, m.gamma).V[0])


def test_effective_horizon():
    assert effective_horizon(0.9, None) == pytest.approx(10.0)
    assert effective_horizon(1.0, 7) == 7.0
    assert effective_horizon(0.5, 7) == pytest.approx(2.0)
    with pytest.raises(ValueError):
        effective_horizon(1.0, None)


def test_kakade_langford_step_is_positive_at_gamma_one():
    """At gamma = 1 the old step (1 - gamma) A / 4R was always 0: CPI never moved."""
    T = 5
    m = TabularMDP(n_states=8, n_actions=3, horizon=T, gamma=1.0, seed=2)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(horizon=T, gamma=1.0, regressor="tabular", action_input="onehot")
    cpi = ConservativePolicyIteration(fqe, n_iterations=4, step_rule="kakade_langford", model=m,
                                      n_eval_episodes=2000).fit(ds, sample_weight=w)
    alphas = cpi.history_["alpha"].to_numpy()[1:]
    assert (alphas > 0).any(), alphas
    assert (alphas <= 1.0 / (4 * T) + 1e-12).all()  # A <= R: the step is at most 1 / (4 T)
    assert _exact_finite(m, cpi.policy_, T) < _exact_finite(m, UniformPolicy(3), T)


def test_psdp_bound_is_infinite_not_nan_when_eps_is_zero_off_support():
    eps = np.array([0.0, 0.3])
    mu = np.array([[1.0, 0.0], [0.5, 0.5]])
    mu_ref = np.array([[0.5, 0.5], [0.5, 0.5]])  # step 0: mu misses a state mu_ref visits, and eps_0 = 0
    assert psdp_bound(eps, mu_ref, mu) == np.inf
    assert psdp_bound(eps, mu, mu) == pytest.approx(0.3)
    out = plugin_bound(eps, np.array([np.inf, 2.0]), pooled_ucb=np.inf)
    assert out["per_step"] == np.inf and out["averaged"] == np.inf
    assert plugin_bound(eps, np.array([3.0, 2.0]))["per_step"] == pytest.approx(0.6)


@pytest.mark.parametrize("seed", [0, 1])
def test_psdp_eps_hat_is_measured_on_held_out_states(seed):
    """With exact Q, eps_hat on fresh states from mu_t estimates the exact
    E_{mu_t}[Q_t(s, pi_t(s)) - min_a Q_t(s, a)] without bias; on the training states it is
    too low (the tabular classifier is perfect on the 8 states it saw)."""
    S, A, T = 12, 3, 6
    m = TabularMDP(n_states=S, n_actions=A, horizon=T, seed=10 + seed)
    rng = np.random.default_rng(seed)
    mu = rng.dirichlet(np.ones(S), size=T)

    def sampler(t, n, r):
        return r.choice(S, size=n, p=mu[t]).astype(float)[:, None]

    p = PSDP(horizon=T, n_samples=8, q_estimator="exact", classifier="tabular", n_holdout=4000,
             random_state=seed).fit(m, sampler)
    states = np.arange(float(S))[:, None]
    pi = np.stack([p.policy_.probabilities(states, t) for t in range(T)])
    ev = dp.policy_evaluation_finite(m.P, m.C, pi, T)
    gap = (pi * ev.Q).sum(axis=2) - ev.Q.min(axis=2)  # (T, S)
    exact = (mu * gap).sum(axis=1)
    sd = np.sqrt((mu * gap**2).sum(axis=1) - exact**2)
    h = p.history_.set_index("step").sort_index()
    assert np.all(np.abs(h["eps_hat"].to_numpy() - exact) <= 4 * sd / np.sqrt(4000) + 1e-12)
    assert h["eps_train"].sum() < h["eps_hat"].sum()


def test_shifted_fqe_replicates_widen_the_interval_and_never_move_the_estimate():
    """Replicates shifted from the estimate measure a bias of unknown sign: in one world the
    estimator is biased the way its bootstrap shifts (the basic interval holds the truth),
    in the other the estimate is accurate and only resampling shifts (the percentile
    interval may miss it the other way). The estimate stays the plug-in and the interval
    (the hull of both readings) covers the truth in both worlds; the percentile interval
    alone fails the first, the old bias correction moved an accurate estimate in the second."""
    from offline_adp.evaluation.fqe_interval import fqe_interval

    rng = np.random.default_rng(0)
    truth, bias, sd = 3.0, 0.4, 0.2
    for estimator_bias in (bias, 0.0):  # biased as the bootstrap says / accurate, resampling shifts
        covered, covered_pct = 0, 0
        for _ in range(300):
            est = truth + estimator_bias + sd * rng.standard_normal()
            reps = est + bias + sd * rng.standard_normal(200)
            r = fqe_interval(est, reps, 100)
            assert r.estimate == est and r.plugin_estimate is None and r.interval_method.startswith("hull")
            assert r.interval[0] <= r.estimate <= r.interval[1]
            covered += r.interval[0] <= truth <= r.interval[1]
            lo, hi = r.percentile_interval
            covered_pct += lo <= truth <= hi
        assert covered / 300 >= 0.9, (estimator_bias, covered)
        if estimator_bias:
            assert covered_pct / 300 < 0.5
    reps = 1.0 + 0.1 * rng.standard_normal(200)
    r = fqe_interval(1.0, reps, 100)
    assert r.estimate == 1.0 and r.plugin_estimate is None and r.interval == r.percentile_interval
