"""Fitted Q-iteration against exact DP, and the chapter's divergence example."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from sklearn.preprocessing import OneHotEncoder

from offline_adp import TransitionDataset, dp
from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.envs import Gridworld, TabularMDP
from offline_adp.envs.gridworld import optimal_cost_to_go
from offline_adp.errors import DivergenceWarning


def full_support_dataset(m: TabularMDP) -> tuple[TransitionDataset, np.ndarray]:
    """One transition per (s, a, s') with P > 0, and weights P(s'|s, a): weighted means
    over this data are exact expectations, so a tabular learner does exact DP."""
    a_, s_, sp = np.nonzero(m.P)
    n = len(s_)
    info = DatasetInfo(features=(Feature("s"),),
                       action_table=ActionTable.from_values(np.arange(m.n_actions, dtype=float)))
    ds = TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(np.arange(n).astype(str), 7), step=np.zeros(n), obs=s_[:, None],
        action=a_, cost=m.C[s_, a_], next_obs=sp[:, None], terminated=np.zeros(n, bool), truncated=np.ones(n, bool),
    )
    arr = ds.arrays()
    w = m.P[arr.action, arr.obs[:, 0].astype(int), arr.next_obs[:, 0].astype(int)]
    return ds, w


def _q_table(q, S, t=0):
    return q.values(np.arange(S, dtype=float)[:, None], t)


@pytest.mark.parametrize("seed", [0, 1])
def test_finite_horizon_tabular_equals_value_iteration(seed):
    m = TabularMDP(n_states=12, n_actions=3, horizon=6, seed=seed)
    ds, w = full_support_dataset(m)
    f = FittedQIteration(horizon=6, gamma=1.0, regressor="tabular", action_input="onehot").fit(ds, sample_weight=w)
    sol = dp.value_iteration_finite(m.P, m.C, 6)
    for t in range(6):
        np.testing.assert_allclose(_q_table(f.q_functions_[t], 12), sol.Q[t], atol=1e-8, rtol=0)
    np.testing.assert_array_equal(f.policy_.act(np.arange(12.0)[:, None], 2, return_index=True), sol.policy[2])
    assert list(f.history_["step"]) == [5, 4, 3, 2, 1, 0]


@pytest.mark.parametrize("encoding", ["joint", "per_action"])
def test_infinite_horizon_tabular_equals_value_iteration(encoding):
    m = TabularMDP(n_states=10, n_actions=3, horizon=None, gamma=0.8, seed=2)
    ds, w = full_support_dataset(m)
    f = FittedQIteration(gamma=0.8, regressor="tabular", action_encoding=encoding, action_input="onehot",
                         n_iterations=200, tol=1e-13).fit(ds, sample_weight=w)
    sol = dp.value_iteration_discounted(m.P, m.C, 0.8)
    np.testing.assert_allclose(_q_table(f.q_function_, 10), sol.Q, atol=1e-8, rtol=0)
    assert len(f.history_) < 200  # stopped on the tolerance
    assert not f.diverged_


@pytest.mark.parametrize(("mode", "builder", "encoding"), [("refit", "auto", "joint"), ("frozen", "auto", "joint"),
                                                          ("frozen", "sklearn", "joint"),
                                                          ("frozen", "auto", "per_action")])
def test_extra_trees_on_one_hot_features_reach_the_optimal_policy(mode, builder, encoding):
    """Exact DP is the oracle, for scikit-learn's trees and the compiled builder's
    (weighted rows: the dataset's sample weights), and for frozen per-action structures
    (trees that split on the action first)."""
    m = TabularMDP(n_states=15, n_actions=3, horizon=None, gamma=0.9, seed=3)
    ds, w = full_support_dataset(m)
    f = FittedQIteration(gamma=0.9, regressor="extra_trees", regressor_params={"n_estimators": 10, "n_jobs": 1},
                         feature_map=OneHotEncoder(sparse_output=False), action_input="onehot", n_iterations=150,
                         tol=1e-7, mode=mode, tree_builder=builder, action_encoding=encoding)
    f.fit(ds, sample_weight=w)
    if mode == "frozen":
        assert {b["builder"] for b in structure_builds(f.history_)} == {"compiled" if builder == "auto"
                                                                        else "scikit-learn"}
    sol = dp.value_iteration_discounted(m.P, m.C, 0.9)
    np.testing.assert_array_equal(f.policy_.act(np.arange(15.0)[:, None], return_index=True), sol.policy)
    np.testing.assert_allclose(_q_table(f.q_function_, 15), sol.Q, atol=1e-5)


def gridworld_dataset() -> TransitionDataset:
    from offline_adp.examples.gridworld_divergence import dataset

    return dataset()


def test_boyan_moore_divergence_quadratic_vs_trees_and_table():
    from offline_adp.examples.gridworld_divergence import run

    J = optimal_cost_to_go(Gridworld.lattice_states())
    # quadratic regression: the corner is underestimated and the error grows; the monitor flags it
    with pytest.warns(DivergenceWarning, match="diverging"):
        errors, corner_values, f = run("ridge", n_iterations=90)
    assert f.diverged_
    k_flag = int(f.divergence_message_.split(":")[0].split()[-1])
    assert corner_values[k_flag - 1] < J[0] - 5.0  # underestimated at the corner (0, 0) when flagged
    assert errors[-1] > 2.0 * min(errors)  # the error grows across iterations
    # extra-trees and a table converge to the linear true cost-to-go
    lattice = Gridworld.lattice_states()
    for reg in ("extra_trees", "tabular"):
        with warnings.catch_warnings():
            warnings.simplefilter("error", DivergenceWarning)
            params = {"n_estimators": 10, "n_jobs": 1} if reg == "extra_trees" else {}
            g = FittedQIteration(gamma=1.0, regressor=reg, regressor_params=params, n_iterations=80,
                                 tol=1e-12).fit(gridworld_dataset())
        np.testing.assert_allclose(g.q_function_.values(lattice).min(axis=1)[:-1], J[:-1], atol=1e-9)


def test_terminated_transitions_are_not_bootstrapped():
    # a chain 0 -> 1 -> 2 (terminal); cost 1 per step; truncated copies bootstrap
    info = DatasetInfo(features=(Feature("s"),), action_table=ActionTable.from_values([0.0]))
    ds = TransitionDataset.from_arrays(
        info, episode_id=["a", "a", "b"], step=[0, 1, 0], obs=[[0.0], [1.0], [0.0]], action=[0, 0, 0],
        cost=[1.0, 1.0, 1.0], next_obs=[[1.0], [2.0], [1.0]], terminated=[False, True, False],
        truncated=[False, False, True],
    )
    f = FittedQIteration(gamma=0.5, regressor="tabular", n_iterations=50).fit(ds)
    q = f.q_function_.values(np.array([[0.0], [1.0]]))[:, 0]
    np.testing.assert_allclose(q, [1.0 + 0.5 * 1.0, 1.0])  # Q(1) = c (terminal), Q(0) = c + gamma Q(1)


def test_infeasible_cost_clamps_targets():
    info = DatasetInfo(features=(Feature("s"),), action_table=ActionTable.from_values([0.0]))
    # self-loop with cost 1 and gamma 0.99 would reach 100; c^- = 10 caps it
    ds = TransitionDataset.from_arrays(info, episode_id=["a"], step=[0], obs=[[0.0]], action=[0], cost=[1.0],
                                       next_obs=[[0.0]], terminated=[False], truncated=[True])
    f = FittedQIteration(gamma=0.99, regressor="tabular", n_iterations=500, infeasible_cost=10.0).fit(ds)
    assert f.q_function_.values(np.array([[0.0]]))[0, 0] == pytest.approx(10.0)


def test_history_columns_and_validation_residual(small_pt):
    f = FittedQIteration(regressor="extra_trees", regressor_params={"n_estimators": 5}, n_iterations=3,
                         validation_fraction=0.25)
    rows = list(f.fit_iter(small_pt))
    assert len(rows) == 3 == len(f.history_)
    for c in ("sup_dq", "mean_dq", "bellman_residual", "greedy_changed", "start_value", "wall_time"):
        assert np.isfinite(f.history_[c]).all(), c
    assert f.predict(small_pt.arrays().obs[:4]).shape == (4, small_pt.n_actions)


def test_bad_parameters_are_reported():
    from offline_adp.errors import NotFittedError

    with pytest.raises(NotFittedError):
        FittedQIteration().predict(np.zeros((1, 1)))
    with pytest.raises(ValueError, match="'regressor' parameter .*extra_trees"):  # scikit-learn's InvalidParameterError
        FittedQIteration(regressor="extra_tree", n_iterations=1).fit(gridworld_dataset())
    with pytest.raises(ValueError, match="mode"):
        FittedQIteration(mode="fast").fit(gridworld_dataset())


@pytest.mark.slow
def test_iterated_fqi_improves_on_exploration_data():
    from offline_adp.algorithms.iterated_fqi import IteratedFQI
    from offline_adp.envs import CarOnHill
    from offline_adp.policies import UniformPolicy
    from offline_adp.rollout import rollout

    model = CarOnHill(horizon=100)
    it = IteratedFQI(FittedQIteration(gamma=0.95, n_iterations=20, mode="frozen",
                                      regressor_params={"n_estimators": 10}),
                     n_rounds=3, episodes_per_round=100, n_eval_episodes=50, random_state=0).fit(model)
    assert list(it.history_["round"]) == [1, 2, 3]
    assert (np.diff(it.history_["n_transitions"]) > 0).all()
    rng = np.random.default_rng(5)
    random_value = rollout(model, UniformPolicy(2), 50, rng).mean
    # from (-0.5, 0) random pushes mostly fall off the hill; the learned policy does better
    assert it.history_["value"].min() < random_value
    assert rollout(model, it.policy_, 50, rng).mean == pytest.approx(it.history_["value"].min(), abs=1e-12)


def test_target_and_next_state_noise_average_out():
    # one state looping on itself with cost 1: Q = 1 / (1 - gamma) = 2 for gamma = 0.5
    info = DatasetInfo(features=(Feature("s"),), action_table=ActionTable.from_values([0.0]))
    n = 4000
    ds = TransitionDataset.from_arrays(info, episode_id=np.char.zfill(np.arange(n).astype(str), 5), step=np.zeros(n),
                                       obs=np.zeros((n, 1)), action=np.zeros(n), cost=np.ones(n),
                                       next_obs=np.zeros((n, 1)),
                                       terminated=np.zeros(n, bool), truncated=np.ones(n, bool))
    exact = FittedQIteration(gamma=0.5, regressor="tabular", n_iterations=40).fit(ds)
    noisy = FittedQIteration(gamma=0.5, regressor="tabular", n_iterations=40, target_noise=0.5, random_state=1).fit(ds)
    q0 = np.zeros((1, 1))
    assert exact.predict(q0)[0, 0] == pytest.approx(2.0, abs=1e-9)
    assert noisy.predict(q0)[0, 0] == pytest.approx(2.0, abs=0.05)  # noise std 0.5 / sqrt(4000), amplified <= 2x
    assert noisy.predict(q0)[0, 0] != exact.predict(q0)[0, 0]
    # next-state noise perturbs x' before evaluating Q: with a k-NN learner on a constant value it changes nothing
    small = ds.take(np.arange(200))
    smooth = FittedQIteration(gamma=0.5, regressor="knn", regressor_params={"weights": "uniform"}, n_iterations=40,
                              next_state_noise=0.3).fit(small)
    assert smooth.predict(q0)[0, 0] == pytest.approx(2.0, abs=1e-9)
    with pytest.raises(ValueError, match="'next_state_noise' parameter .* unless mode='refit'"):
        FittedQIteration(mode="frozen", next_state_noise=0.1).fit(ds)
