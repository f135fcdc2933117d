"""PSDP and iterated PSDP against exact dynamic programming on tabular MDPs."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.psdp import PSDP, IteratedPSDP, psdp_bound
from offline_adp.envs import TabularMDP
from offline_adp.policies import TabularPolicy, UniformPolicy

S, A, T = 12, 3, 6


def _uniform_mu(m):
    states = np.arange(float(m.n_states))[:, None]
    return [states] * T  # every state once per step: mu_t uniform


def _tables(m, policy):
    states = np.arange(float(m.n_states))[:, None]
    return np.stack([policy.probabilities(states, t) for t in range(T)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psdp_with_exact_q_and_a_tabular_classifier_is_optimal(seed):
    m = TabularMDP(n_states=S, n_actions=A, horizon=T, seed=seed)
    # S * 30 draws with replacement from mu_t cover every state (a miss has probability < 1e-9)
    p = PSDP(horizon=T, n_samples=S * 30, q_estimator="exact", classifier="tabular",
             random_state=seed).fit(m, _uniform_mu(m))
    opt = dp.value_iteration_finite(m.P, m.C, T)
    states = np.arange(float(S))[:, None]
    for t in range(T):
        np.testing.assert_array_equal(p.policy_.act(states, t, return_index=True), opt.policy[t])


def test_psdp_rollout_estimates_approach_the_optimum():
    m = TabularMDP(n_states=S, n_actions=A, horizon=T, seed=3)
    p = PSDP(horizon=T, n_samples=S * 20, n_rollouts=20, classifier="tabular", random_state=0).fit(m, _uniform_mu(m))
    opt = dp.value_iteration_finite(m.P, m.C, T)
    J = m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, _tables(m, p.policy_), T).V[0]
    J_opt = m.initial_distribution @ opt.V[0]
    J_unif = m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, np.full((S, A), 1 / A), T).V[0]
    assert J_opt <= J <= J_opt + 0.05 * (J_unif - J_opt)
    assert p.simulator_steps_ > 0
    # regression variant too
    r = PSDP(horizon=T, n_samples=S * 20, n_rollouts=20, learner="regression", regressor="tabular",
             random_state=0).fit(m, _uniform_mu(m))
    Jr = m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, _tables(m, r.policy_), T).V[0]
    assert Jr <= J_opt + 0.05 * (J_unif - J_opt)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_theorem_2_bound_holds_with_eps_measured_exactly(seed):
    m = TabularMDP(n_states=S, n_actions=A, horizon=T, seed=10 + seed)
    rng = np.random.default_rng(seed)
    # mu_t: a random full-support distribution per step, sampled sparsely so the policy is imperfect
    mu = rng.dirichlet(np.ones(S), size=T)
    baseline = [rng.choice(S, size=8, p=mu[t]).astype(float)[:, None] for t in range(T)]
    p = PSDP(horizon=T, n_samples=8, n_rollouts=2, classifier="tabular", random_state=seed).fit(m, baseline)
    pi = _tables(m, p.policy_)
    # eps_t exactly: E_{mu_t}[Q_t(s, pi_t(s)) - min_a Q_t(s, a)], Q_t with pi's own future
    ev = dp.policy_evaluation_finite(m.P, m.C, pi, T)
    eps = np.array([mu[t] @ ((pi[t] * ev.Q[t]).sum(axis=1) - ev.Q[t].min(axis=1)) for t in range(T)])
    opt = dp.value_iteration_finite(m.P, m.C, T)
    mu_ref = dp.state_distributions(m.P, opt.policy, m.initial_distribution, T)[:T]
    J, J_ref = m.initial_distribution @ ev.V[0], m.initial_distribution @ opt.V[0]
    bound = psdp_bound(eps, mu_ref, mu)
    assert J - J_ref <= bound + 1e-12
    assert eps.sum() > 0  # the test is not vacuous: the learned policy is imperfect
    assert J - J_ref > 0


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_iterated_psdp_never_returns_a_policy_worse_than_its_start(seed):
    m = TabularMDP(n_states=S, n_actions=A, horizon=T, seed=20 + seed)
    start = TabularPolicy(m.demonstrator(epsilon=0.6).probabilities(np.arange(float(S))[:, None]))
    it = IteratedPSDP(PSDP(horizon=T, n_samples=30, n_rollouts=3, classifier="tabular"), n_rounds=4, exact_values=True,
                      random_state=seed).fit(m, start)
    pi = _tables(m, it.policy_)
    J = m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, pi, T).V[0]
    J_start = m.initial_distribution @ dp.policy_evaluation_finite(m.P, m.C, _tables(m, start), T).V[0]
    assert J <= J_start + 1e-12
    assert it.value_ == pytest.approx(J, abs=1e-12)
    h = it.history_
    accepted = h[h.accepted]["value"].to_numpy()
    assert (np.diff(accepted) < 0).all()  # each accepted round improved


def test_psdp_needs_a_generative_model_for_arbitrary_baselines():
    from offline_adp.access import AccessModelError, ResetModel

    class ResetOnly(ResetModel):  # can only simulate forward from its own start states
        n_actions, obs_dim, gamma, horizon = 2, 1, 1.0, 3

        def initial_states(self, n, rng):
            return np.zeros((n, 1))

        def step(self, states, actions, rng):
            from offline_adp.access import StepResult

            return StepResult(states + 1.0, np.asarray(actions, float), np.zeros(len(states), bool))

    with pytest.raises(AccessModelError, match="GenerativeModel"):
        PSDP(horizon=3).fit(ResetOnly(), [np.zeros((1, 1))] * 3)
    # with mu_t from rollouts of a baseline policy, a reset model is enough: pushing 0 is cheaper
    p = PSDP(horizon=3, n_samples=10, n_rollouts=1, classifier="tabular").fit(ResetOnly(), UniformPolicy(2))
    assert (p.policy_.act(np.array([[0.0], [1.0], [2.0]]), 0, return_index=True) == 0).all()
