"""Exact DP against brute-force enumeration and Monte-Carlo, on small tabular MDPs."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.envs import TabularMDP
from offline_adp.policies import TabularPolicy
from offline_adp.simulate import collect


def _eval_by_forward_distributions(P, C, mu0, policy_actions, T):
    """Expected total cost of a non-stationary deterministic policy by propagating mu_t."""
    S = P.shape[1]
    mu, total = mu0.copy(), 0.0
    for t in range(T):
        a = policy_actions[t]
        total += mu @ C[np.arange(S), a]
        mu = np.einsum("s,st->t", mu, P[a, np.arange(S)])
    return total


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_finite_horizon_vi_equals_brute_force(seed):
    m = TabularMDP(n_states=3, n_actions=2, horizon=3, branching=3, seed=seed)
    sol = dp.value_iteration_finite(m.P, m.C, m.horizon)
    per_step = list(itertools.product(range(2), repeat=3))  # 8 decision rules per step
    best = min(
        _eval_by_forward_distributions(m.P, m.C, m.initial_distribution, np.array(rules), 3)
        for rules in itertools.product(per_step, repeat=3)  # 512 non-stationary policies
    )
    assert sol.V[0] @ m.initial_distribution == pytest.approx(best, abs=1e-12)
    # per-state optimality: V_0(s) is the min over policies of the cost from s
    for s in range(3):
        e = np.eye(3)[s]
        best_s = min(_eval_by_forward_distributions(m.P, m.C, e, np.array(r),
                                                    3) for r in itertools.product(per_step, repeat=3))
        assert sol.V[0, s] == pytest.approx(best_s, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 3])
def test_discounted_vi_equals_brute_force(seed):
    m = TabularMDP(n_states=4, n_actions=3, horizon=None, gamma=0.9, branching=3, seed=seed)
    sol = dp.value_iteration_discounted(m.P, m.C, m.gamma)
    values = [dp.policy_evaluation_discounted(m.P, m.C, np.array(pol),
                                              m.gamma).V for pol in itertools.product(range(3), repeat=4)]
    best = np.min(values, axis=0)  # an optimal policy is optimal in every state simultaneously
    np.testing.assert_allclose(sol.V, best, atol=1e-10)
    # Bellman optimality holds
    q = m.C + m.gamma * np.einsum("ast,t->sa", m.P, sol.V)
    np.testing.assert_allclose(q.min(axis=1), sol.V, atol=1e-10)


def test_policy_evaluation_finite_matches_forward_propagation():
    m = TabularMDP(n_states=6, n_actions=3, horizon=5, seed=4)
    rng = np.random.default_rng(0)
    pi = rng.dirichlet(np.ones(3), size=(5, 6))  # stochastic non-stationary
    V = dp.policy_evaluation_finite(m.P, m.C, pi, 5).V
    mu = dp.state_distributions(m.P, pi, m.initial_distribution, 5)
    expected = sum(mu[t] @ (pi[t] * m.C).sum(axis=1) for t in range(5))
    assert V[0] @ m.initial_distribution == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, atol=1e-12)


def test_state_distributions_match_monte_carlo():
    m = TabularMDP(n_states=8, n_actions=2, horizon=6, seed=5)
    pol = m.demonstrator(epsilon=0.3)
    probs = np.stack([pol.probabilities(np.arange(8.0)[:, None], t) for t in range(6)])
    mu = dp.state_distributions(m.P, probs, m.initial_distribution, 6)
    ds = collect(m, pol, 20000, np.random.default_rng(1), horizon=6)
    for t in range(6):
        s = ds.states_at(t)[:, 0].astype(int)
        freq = np.bincount(s, minlength=8) / len(s)
        assert np.abs(freq - mu[t]).max() < 0.02  # ~4.5 sigma at n = 20000


def test_discounted_occupancy_sums_to_one_and_matches_series():
    m = TabularMDP(n_states=5, n_actions=2, horizon=None, gamma=0.8, seed=6)
    pi = np.full((5, 2), 0.5)
    d = dp.discounted_occupancy(m.P, pi, m.initial_distribution, 0.8)
    mu = dp.state_distributions(m.P, pi, m.initial_distribution, 200)
    series = (1 - 0.8) * sum(0.8**t * mu[t] for t in range(200))
    np.testing.assert_allclose(d, series, atol=1e-12)
    assert d.sum() == pytest.approx(1.0)


def test_tabular_policy_time_varying():
    pol = TabularPolicy(np.array([[0, 1], [1, 0]]), n_actions=2)
    obs = np.array([[0.0], [1.0]])
    np.testing.assert_array_equal(pol.act(obs, 0, return_index=True), [0, 1])
    np.testing.assert_array_equal(pol.act(obs, 1, return_index=True), [1, 0])
    np.testing.assert_array_equal(pol.act(obs, 7, return_index=True), [1, 0])  # beyond T: last rule
