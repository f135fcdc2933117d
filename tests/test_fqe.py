"""Fitted Q evaluation against exact policy evaluation; the two-state divergence example."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqe_bootstrap import leaf_operator, query_operators
from offline_adp.envs import TabularMDP
from offline_adp.errors import DivergenceWarning
from offline_adp.examples import two_state
from offline_adp.policies import TabularPolicy
from tests.test_fqi import full_support_dataset


def test_finite_horizon_fqe_equals_exact_policy_evaluation():
    m = TabularMDP(n_states=10, n_actions=3, horizon=5, seed=7)
    ds, w = full_support_dataset(m)
    pi = np.random.default_rng(0).dirichlet(np.ones(3), size=(5, 10))  # stochastic, time-varying
    fqe = FittedQEvaluation(policy=TabularPolicy(pi), horizon=5, gamma=1.0, regressor="tabular", action_input="onehot")
    fqe.fit(ds, sample_weight=w)
    exact = dp.policy_evaluation_finite(m.P, m.C, pi, 5)
    for t in range(5):
        np.testing.assert_allclose(fqe.q_functions_[t].values(np.arange(10.0)[:, None]), exact.Q[t], atol=1e-8, rtol=0)


def test_discounted_fqe_equals_exact_policy_evaluation():
    m = TabularMDP(n_states=10, n_actions=3, horizon=None, gamma=0.8, seed=8)
    ds, w = full_support_dataset(m)
    pi = np.random.default_rng(1).dirichlet(np.ones(3), size=10)
    fqe = FittedQEvaluation(policy=TabularPolicy(pi), gamma=0.8, regressor="tabular", action_input="onehot",
                            n_iterations=300, tol=1e-14).fit(ds, sample_weight=w)
    exact = dp.policy_evaluation_discounted(m.P, m.C, pi, 0.8)
    np.testing.assert_allclose(fqe.q_function_.values(np.arange(10.0)[:, None]), exact.Q, atol=1e-8, rtol=0)
    assert fqe.policy_.probabilities(np.zeros((1, 1)))[0] == pytest.approx(pi[0])


def test_two_state_unweighted_backup_multiplies_w_by_six_gamma_over_five():
    # bound max|Q_0| = 2 (costs 0): 2 * 1.08 is inside the 10% margin, 2 * 1.08^2 = 2.33 is not
    with pytest.warns(DivergenceWarning, match="iteration 2: max \\|Q\\| = 2.333 exceeds the bound"):
        ws, fqe = two_state.run(weighted=False, n_backups=12)
    assert ws[0] == pytest.approx(1.08, abs=1e-12)  # not 1.2 as the chapter's text has it
    np.testing.assert_allclose(ws, 1.08 ** np.arange(1, 13), rtol=1e-12)  # geometric divergence
    assert fqe.diverged_


def test_two_state_on_policy_weighting_converges():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", DivergenceWarning)
        ws, fqe = two_state.run(weighted=True, n_backups=60)
    assert ws[0] == pytest.approx(34.2 / 37, abs=1e-12) and round(ws[0], 3) == 0.924
    np.testing.assert_allclose(ws, (34.2 / 37) ** np.arange(1, 61), rtol=1e-10)
    assert abs(ws[-1]) < 0.01 and not fqe.diverged_


def test_reweighted_value_is_the_same_fixed_point_for_uniform_weights(small_pt):
    """Structure-conditional bootstrap: with uniform weights (any scale) the re-averaged
    fixed point is the fitted FQE's value; other weights move it."""
    from offline_adp.policies import UniformPolicy

    fqe = FittedQEvaluation(policy=UniformPolicy(small_pt.n_actions), gamma=0.9, mode="frozen", n_iterations=400,
                            tol=1e-10, regressor_params={"n_estimators": 5}).fit(small_pt)
    n = len(small_pt)
    assert fqe.reweighted_value(np.ones(n), n_iterations=3000, tol=1e-12) == pytest.approx(fqe.value_, rel=1e-6)
    assert fqe.reweighted_value(np.full(n, 3.0), n_iterations=3000, tol=1e-12) == pytest.approx(fqe.value_, rel=1e-6)
    w = np.random.default_rng(0).poisson(1.0, n).astype(float)
    assert fqe.reweighted_value(w) != pytest.approx(fqe.value_, rel=1e-6)


def test_settle_reaches_the_structures_fixed_point_by_a_linear_solve(small_pt):
    """A short frozen fit (4 structures over 20 iterations: the last one averaged 5 times)
    is not at its structure's fixed point; ``settle`` brings it there. Oracle: the fixed
    point solved directly, ``(I - M diag(gamma (1 - term)) P_pi A_next) v = M c``. The
    replicate with uniform weights is then the estimate itself."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    from offline_adp.policies import UniformPolicy

    fqe = FittedQEvaluation(policy=UniformPolicy(small_pt.n_actions), gamma=0.9, mode="frozen", n_iterations=20,
                            regressor_params={"n_estimators": 5}).fit(small_pt)
    fit = fqe.fit_state_
    d, learner, backup = fit.data, fit.learner, fit.backup
    n, A = d.n, d.n_actions
    pi = backup.probabilities("next", 0)
    P = sparse.csr_matrix((pi.T.reshape(-1), (np.tile(np.arange(n), A), np.arange(A * n))), shape=(n, A * n))
    boot = sparse.diags(np.where(d.train.no_boot, 0.0, 0.9))
    M, ops = leaf_operator(learner), query_operators(learner)
    op = (M @ boot @ P @ ops["next"]).tocsc()
    v = spsolve((sparse.identity(op.shape[0], format="csc") - op), M @ d.train.cost)
    q0 = (ops["start"] @ v).reshape(A, -1).T
    exact = float((backup.probabilities("start", 0) * q0).sum(axis=1).mean())
    before = fqe.value_
    assert abs(before - exact) > 1e-3 * (1 + abs(exact))  # 5 sweeps on the last structure: not there yet
    sweeps = fqe.settle()
    assert sweeps > 5
    assert fqe.value_ == pytest.approx(exact, rel=1e-6)
    q = fqe.q_function_.values(d.start_obs, 0)
    assert float((backup.probabilities("start", 0) * q).sum(axis=1).mean()) == pytest.approx(exact, rel=1e-6)
    assert fqe.reweighted_value(np.ones(n)) == pytest.approx(fqe.value_, rel=1e-6)


def _reweighted_fixed_point_oracle(fqe, w):
    """The replicate's value computed independently, tree by tree: ``M_w[leaf, i] = w_i /
    sum_{j in leaf} w_j``; a query averages (weight 1/m each) the trees whose reached leaf
    kept some weight, renormalised over them (unchanged when none did); then the linear
    solve ``(I - M_w diag(gamma (1 - term)) P_pi A_next) v = M_w c`` and the w-weighted
    start value."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    fit = fqe.fit_state_
    d, learner, backup = fit.data, fit.learner, fit.backup
    n, A, L = d.n, d.n_actions, len(learner.leaf_ids)
    m = learner.pos["train"].shape[0]
    comp = learner.pos["train"]
    wsum = np.zeros(L)
    for t in range(m):
        np.add.at(wsum, comp[t], w)
    rows, cols, vals = [], [], []
    for t in range(m):
        ok = wsum[comp[t]] > 0
        rows.append(comp[t][ok]), cols.append(np.arange(n)[ok]), vals.append(w[ok] / wsum[comp[t][ok]])
    M = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(L, n))

    def query(name):
        pos = learner.pos[name]  # (m, queries); L = no training leaf
        hit = pos < L
        alive = hit & (wsum[np.minimum(pos, L - 1)] > 0)
        use = np.where(alive.any(axis=0)[None, :], alive, hit)
        weight = use / np.maximum(np.where(alive.any(axis=0), use.sum(axis=0), m), 1)
        q, t = np.nonzero(use.T)
        return sparse.csr_matrix((weight.T[q, t], (q, pos.T[q, t])), shape=(pos.shape[1], L))

    nxt, start = query("next"), query("start")
    pi = backup.probabilities("next", 0)
    P = sparse.csr_matrix((pi.T.reshape(-1), (np.tile(np.arange(n), A), np.arange(A * n))), shape=(n, A * n))
    boot = sparse.diags(np.where(d.train.no_boot, 0.0, d.gamma))
    op = (M @ boot @ P @ nxt).tocsc()
    v = spsolve(sparse.identity(L, format="csc") - op, M @ d.train.cost)
    v0 = (backup.probabilities("start", 0) * (start @ v).reshape(A, -1).T).sum(axis=1)
    w0 = w[d.start_rows]
    return float(np.sum(w0 * v0) / np.sum(w0))


@pytest.mark.parametrize("policy", ["uniform", "deterministic"])
def test_reweighted_replicate_equals_an_independent_linear_solve(small_pt, policy):
    """Bootstrap weights with many zeros (leaves left empty, queries renormalised over the
    trees that kept weight): the replicate's fixed point equals the oracle's solve, for a
    stochastic policy and for a deterministic one (whose untaken next actions the sweep
    leaves out); the bootstrap's looser ``rtol`` stays within its bound."""
    from offline_adp.evaluation.fqe_interval import REPLICATE_RTOL
    from offline_adp.policies import FunctionPolicy, UniformPolicy

    A = small_pt.n_actions
    pol = UniformPolicy(A) if policy == "uniform" else \
        FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    fqe = FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=20,
                            regressor_params={"n_estimators": 5}).fit(small_pt)
    rng = np.random.default_rng(3)
    for _ in range(3):
        w = rng.poisson(0.7, len(small_pt)).astype(float)  # ~half the rows out: empty leaves
        exact = _reweighted_fixed_point_oracle(fqe, w)
        assert fqe.reweighted_value(w, tol=1e-12) == pytest.approx(exact, rel=1e-8, abs=1e-10)
        scale = 1 + np.max(np.abs(fqe.fit_state_.learner.leaf_values))
        assert abs(fqe.reweighted_value(w, rtol=REPLICATE_RTOL) - exact) <= 2 * REPLICATE_RTOL * scale


@pytest.mark.parametrize("gamma", [0.9, 0.5])
def test_finite_horizon_fqe_on_discounted_data_any_gamma(gamma):
    """FittedQEvaluation(policy, horizon=T, gamma=g): the T-step discounted evaluation of a
    time-varying policy, Q_t backed up with pi at t+1 (issue 15 relies on it)."""
    m = TabularMDP(n_states=8, n_actions=2, horizon=None, gamma=0.95, seed=11)
    ds, w = full_support_dataset(m)
    pi = np.random.default_rng(2).dirichlet(np.ones(2), size=(4, 8))
    fqe = FittedQEvaluation(policy=TabularPolicy(pi), horizon=4, gamma=gamma, regressor="tabular",
                            action_input="onehot")
    fqe.fit(ds, sample_weight=w)
    exact = dp.policy_evaluation_finite(m.P, m.C, pi, 4, gamma=gamma)
    for t in range(4):
        np.testing.assert_allclose(fqe.q_functions_[t].values(np.arange(8.0)[:, None]), exact.Q[t], atol=1e-10, rtol=0)
    np.testing.assert_allclose(fqe.value_, exact.V[0][ds.arrays().obs[ds.arrays().step == 0, 0].astype(int)].mean(),
                               atol=1e-10)
    assert fqe.verdict_ == "completed"


def test_settle_and_replicates_refuse_what_they_cannot_do(small_pt):
    """Unfitted, wrong weight length, undiscounted: a clear error, not a traceback or a silent answer."""
    from offline_adp.errors import NotFittedError
    from offline_adp.policies import UniformPolicy

    pi = UniformPolicy(small_pt.n_actions)
    with pytest.raises(NotFittedError):
        FittedQEvaluation(policy=pi, gamma=0.9, mode="frozen").settle()
    fqe = FittedQEvaluation(policy=pi, gamma=0.9, mode="frozen", n_iterations=4,
                            regressor_params={"n_estimators": 3}).fit(small_pt)
    with pytest.raises(ValueError, match="training rows"):
        fqe.reweighted_value(np.ones(len(small_pt) + 1))
    for bad in (0.0, -1e-5, float("nan")):  # would run every sweep allowed instead of stopping
        with pytest.raises(ValueError, match="rtol must be > 0"):
            fqe.reweighted_value(np.ones(len(small_pt)), rtol=bad)
    with pytest.raises(TypeError, match="TransitionDataset"):
        FittedQEvaluation(policy=pi).fit("not a dataset")
    fit = fqe.fit_state_
    gamma_one = dataclasses.replace(fit.data, gamma=1.0)
    fqe.fit_state_ = dataclasses.replace(fit, data=gamma_one)  # the guard, not a division by 1 - gamma
    with pytest.raises(ValueError, match="gamma < 1"):
        fqe.settle()


def test_a_stationary_policys_probabilities_are_computed_once_per_query_set_in_a_finite_horizon_fqe(small_pt):
    """A 200-step FQE of a greedy policy re-ran the policy's model at every step (MountainCar:
    50 bootstrap refits x 200 steps x a 50-tree forest on 50k states)."""
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.policies import FunctionPolicy, GreedyPolicy, is_stationary

    q = FittedQIteration(n_iterations=2, regressor_params={"n_estimators": 3}).fit(small_pt).q_function_
    calls = {"n": 0}

    class Counting:
        n_actions = q.n_actions

        def values(self, obs, t=0):
            calls["n"] += 1
            return q.values(obs, t)

    pol = GreedyPolicy(Counting())
    assert pol.time_varying is False
    FittedQEvaluation(policy=pol, horizon=12, regressor_params={"n_estimators": 3}).fit(small_pt)
    assert calls["n"] <= 3  # once per query set (next states, start states), not 12 times each
    undeclared = FunctionPolicy(lambda x, t: np.zeros(len(x), int), small_pt.n_actions)
    assert is_stationary(undeclared, small_pt.arrays().obs, 12)
    varying = FunctionPolicy(lambda x, t: np.full(len(x), int(np.max(t)) % 2), small_pt.n_actions)
    assert not is_stationary(varying, small_pt.arrays().obs, 12)
