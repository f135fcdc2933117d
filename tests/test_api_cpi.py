"""Approximate and conservative policy iteration on tabular MDPs with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.api import ApproximatePolicyIteration
from offline_adp.algorithms.cpi import ConservativePolicyIteration
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.envs import TabularMDP
from offline_adp.policies import MixturePolicy, TabularPolicy, UniformPolicy
from offline_adp.qfunctions import FunctionQ
from tests.test_fqi import full_support_dataset


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_api_with_a_tabular_learner_reaches_the_optimal_policy_within_S_iterations(seed):
    S = 12
    m = TabularMDP(n_states=S, n_actions=3, horizon=None, gamma=0.8, seed=seed)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(gamma=0.8, regressor="tabular", action_input="onehot", n_iterations=400, tol=1e-14)
    api = ApproximatePolicyIteration(fqe, n_iterations=S + 1).fit(ds, sample_weight=w)
    opt = dp.value_iteration_discounted(m.P, m.C, 0.8)
    np.testing.assert_array_equal(api.policy_.act(np.arange(float(S))[:, None], return_index=True), opt.policy)
    assert len(api.history_) <= S + 1 and api.history_["changed"].iloc[-1] == 0.0  # stopped: no change
    v = api.history_["value"].to_numpy()
    assert api.verdict_ == "converged" and "fixed point of policy iteration" in api.verdict_message_
    assert api.value_ == v[-1]  # the returned policy is the last evaluated one (on every state)
    starts = ds.arrays().obs[ds.arrays().step == 0, 0].astype(int)
    assert api.value_ == pytest.approx(opt.V[starts].mean(), abs=1e-9)  # the optimal cost from the start states
    # values estimated by FQE decrease (policy improvement), ending at the optimal value
    assert (np.diff(v) <= 1e-9).all()


class _Contrary(FittedQEvaluation):
    """An evaluator whose Q says the evaluated policy's action is the worst one: its greedy
    policy takes the other action, so policy iteration on it goes round a cycle."""

    def fit(self, dataset, sample_weight=None):
        pi = self.policy

        def q(obs, t):
            return (pi.probabilities(obs, t).argmax(axis=1)[:, None] == np.arange(2)).astype(float)

        self.q_function_, self.value_ = FunctionQ(q, 2), self.cost(pi)
        self.verdict_, self.verdict_message_ = "converged", "by construction"
        return self

    def cost(self, pi):
        return 0.0


def test_a_cycle_of_greedy_policies_stops_the_iteration_and_says_so():
    m = TabularMDP(n_states=4, n_actions=2, horizon=None, gamma=0.8, seed=0)
    ds, _ = full_support_dataset(m)
    api = ApproximatePolicyIteration(_Contrary(), n_iterations=10).fit(ds)
    # pi_0 uniform (argmax: action 0), pi_1 = action 1, pi_2 = action 0, pi_3 = action 1 = pi_1
    assert api.history_["changed"].tolist() == [1.0, 1.0, 1.0] and api.verdict_ == "still changing"
    assert "cycle" in api.verdict_message_ and "pi_1" in api.verdict_message_
    short = ApproximatePolicyIteration(_Contrary(), n_iterations=2).fit(ds)  # stopped by the budget
    assert len(short.history_) == 2 and short.verdict_ == "still changing" and "budget" in short.verdict_message_
    assert api.value_ == 0.0 and short.value_ is None  # pi_1's estimate; pi_2 was not evaluated


class _ContraryRising(_Contrary):
    """... whose estimate of the policy taking action 1 is the lowest."""

    def cost(self, pi):
        return 1.0 - 0.5 * float(pi.probabilities(np.zeros((1, 1)), 0).argmax() == 1)


def test_a_rise_of_the_estimated_cost_stops_the_iteration_with_the_lowest_estimate():
    m = TabularMDP(n_states=4, n_actions=2, horizon=None, gamma=0.8, seed=0)
    ds, _ = full_support_dataset(m)
    api = ApproximatePolicyIteration(_ContraryRising(), n_iterations=10).fit(ds)
    # J(pi_0) = 1 (uniform: argmax 0), J(pi_1) = 0.5 (action 1), J(pi_2) = 1 (action 0): a rise
    assert api.history_["value"].tolist() == [1.0, 0.5, 1.0] and api.verdict_ == "still changing"
    assert "pi_1 returned" in api.verdict_message_
    x = np.arange(4.0)[:, None]
    assert (api.policy_.act(x, return_index=True) == 1).all()  # pi_1, and the Q it is greedy over: Q^{pi_0}
    assert (api.q_function_.values(x).argmin(axis=1) == 1).all() and api.fqe_.value_ == api.value_ == 0.5


def test_api_finite_horizon():
    m = TabularMDP(n_states=8, n_actions=2, horizon=4, seed=5)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(horizon=4, gamma=1.0, regressor="tabular", action_input="onehot")
    api = ApproximatePolicyIteration(fqe, n_iterations=10).fit(ds, sample_weight=w)
    opt = dp.value_iteration_finite(m.P, m.C, 4)
    for t in range(4):
        np.testing.assert_array_equal(api.policy_.act(np.arange(8.0)[:, None], t, return_index=True), opt.policy[t])


def _exact_cost(m, policy):
    pi = policy.probabilities(np.arange(float(m.n_states))[:, None])
    return float(m.initial_distribution @ dp.policy_evaluation_discounted(m.P, m.C, pi, m.gamma).V)


@pytest.mark.slow
@pytest.mark.parametrize("rule", ["line_search", "kakade_langford"])
def test_cpi_estimated_value_never_increases_and_policy_improves(rule):
    m = TabularMDP(n_states=10, n_actions=3, horizon=30, gamma=0.9, seed=4)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(gamma=0.9, regressor="tabular", action_input="onehot", n_iterations=200, tol=1e-12)
    cpi = ConservativePolicyIteration(fqe, n_iterations=6, step_rule=rule, model=m,
                                      n_eval_episodes=400).fit(ds, sample_weight=w)
    v = cpi.history_["value"].to_numpy()
    assert (np.diff(v) <= 0).all()  # the estimated cost is monotone non-increasing
    assert isinstance(cpi.policy_, MixturePolicy) and abs(cpi.policy_.weights.sum() - 1) < 1e-12
    assert _exact_cost(m, cpi.policy_) < _exact_cost(m, UniformPolicy(3))


@pytest.mark.slow
def test_cpi_off_policy_estimates_from_logs():
    m = TabularMDP(n_states=10, n_actions=3, horizon=None, gamma=0.9, seed=6)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(gamma=0.9, regressor="tabular", action_input="onehot", n_iterations=200, tol=1e-12)
    cpi = ConservativePolicyIteration(fqe, n_iterations=4, step_sizes=(0.25, 0.5, 1.0)).fit(ds, sample_weight=w)
    v = cpi.history_["value"].to_numpy()
    assert (np.diff(v) <= 1e-12).all() and v[-1] < v[0]
    # the FQE estimate of the final mixture is its exact value from the data's start states (all states here)
    pi = cpi.policy_.probabilities(np.arange(10.0)[:, None])
    exact = dp.policy_evaluation_discounted(m.P, m.C, pi, 0.9).V
    starts = np.unique(ds.arrays().obs[ds.arrays().step == 0, 0].astype(int), return_counts=True)
    assert v[-1] == pytest.approx(np.average(exact[starts[0]], weights=starts[1]), abs=1e-8)


def test_mixture_policy():
    a = TabularPolicy(np.array([0, 1]), n_actions=2)
    b = TabularPolicy(np.array([1, 1]), n_actions=2)
    mix = MixturePolicy([a], [1.0]).mix(b, 0.25)
    np.testing.assert_allclose(mix.probabilities(np.array([[0.0], [1.0]])), [[0.75, 0.25], [0.0, 1.0]])
    acts = mix.act(np.zeros((20000, 1)), 0, np.random.default_rng(0), return_index=True)
    assert abs(acts.mean() - 0.25) < 0.02
    with pytest.raises(ValueError):
        MixturePolicy([a, b], [0.5, 0.6])


def test_cpi_evaluates_with_apis_evaluator_by_default(monkeypatch):
    """CPI's FQE (one per iteration, one per line-search step from the logs) is API's evaluator
    unless given: FittedQIteration's tree schedule, not FQE's own refit loop (201 against 3.7
    CPU-s an evaluation on a 22k-row path_tracking log); the CLI's [cpi.fqe] keys go on top."""
    from offline_adp.algorithms import registry
    from offline_adp.algorithms.api import EVALUATOR_DEFAULTS

    proto = ConservativePolicyIteration()._proto().get_params()
    assert {k: proto[k] for k in EVALUATOR_DEFAULTS} == EVALUATOR_DEFAULTS
    seen = {}

    class Capture(ConservativePolicyIteration):
        def fit(self, dataset, sample_weight=None):
            seen.update(self.fqe.get_params())
            return self

    entry = type("E", (), {"estimator_class": staticmethod(lambda: Capture)})()
    monkeypatch.setattr(registry, "_simulator", lambda p, ds=None: None)
    from offline_adp.simulate import simulate

    registry._fit_cpi(entry, {"fqe": {"n_iterations": 7}}, simulate("car_on_hill", 0, 3, seed=0, horizon=10))
    assert seen["n_iterations"] == 7 and all(seen[k] == v for k, v in EVALUATOR_DEFAULTS.items())


@pytest.mark.parametrize("budget", [1, 12])
def test_cpi_stops_at_its_fixed_point_and_says_so(budget):
    """A step of 0 leaves pi unchanged, so the next iteration would see the same evaluation
    and candidates: CPI stops there, "converged". The oracle: one more CPI iteration started
    from the returned policy chooses alpha = 0 again at the same estimate."""
    m = TabularMDP(n_states=6, n_actions=3, horizon=None, gamma=0.8, seed=2)
    ds, w = full_support_dataset(m)
    fqe = FittedQEvaluation(gamma=0.8, regressor="tabular", action_input="onehot", n_iterations=200, tol=1e-12)
    cpi = ConservativePolicyIteration(fqe, n_iterations=budget, step_sizes=(0.5, 1.0)).fit(ds, sample_weight=w)
    h = cpi.history_
    if cpi.verdict_ == "converged":
        assert h["alpha"].iloc[-1] == 0.0 and len(h) <= budget + 1 and (h["alpha"].iloc[1:-1] > 0).all()
        again = ConservativePolicyIteration(fqe, n_iterations=1, step_sizes=(0.5, 1.0),
                                            initial_policy=cpi.policy_).fit(ds, sample_weight=w)
        assert again.history_["alpha"].iloc[-1] == 0.0
        assert again.history_["value"].iloc[-1] == pytest.approx(h["value"].iloc[-1], abs=1e-9)
    else:
        assert cpi.verdict_ == "still changing" and len(h) == budget + 1 and h["alpha"].iloc[-1] > 0
    assert budget == 1 or cpi.verdict_ == "converged"  # 12 steps reach the fixed point on 6 states


def test_api_with_the_datas_own_finite_horizon_reaches_the_exact_optimum():
    """The evaluator's horizon came from the dataset (the CLI's default), but API compared and
    handed on only the step-0 actions: it said "converged" at 2.5604 where the tabular optimum
    (finite-horizon FQI on the same lookup table: backward induction) is 2.49959, and its policy
    cost 2.5157."""
    from offline_adp.algorithms.api import ApproximatePolicyIteration, default_evaluator
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.simulate import simulate

    ds = simulate("tabular", 20, 20, seed=3, problem_options={"n_states": 6, "n_actions": 3})
    assert ds.info.horizon is not None
    opt = FittedQIteration(regressor="tabular", action_input="onehot").fit(ds).history_["start_value"].iloc[-1]
    api = ApproximatePolicyIteration(fqe=default_evaluator(regressor="tabular", action_input="onehot")).fit(ds)
    assert api.verdict_ == "converged" and api.value_ == pytest.approx(opt, abs=1e-9)
    own = FittedQEvaluation(policy=api.policy_, regressor="tabular", action_input="onehot").fit(ds).value_
    assert own == pytest.approx(api.value_, abs=1e-9)  # the value printed is the returned policy's


@pytest.mark.parametrize("seed", [3, 4])
def test_the_default_start_takes_only_logged_actions_and_is_never_the_answer(seed):
    """An action the logs never take: a lookup table values it at its fill value (0, an
    optimistic cost), so a start uniform over every action read better than its successor and
    API returned it (an audit: 1.399 against the successor's 1.116, exact). The start is
    uniform over the logged actions, and API returns a greedy policy: here the optimum over
    the logged actions (exact DP on the restricted model)."""
    from offline_adp.algorithms.api import uniform_over_logged

    m = TabularMDP(n_states=8, n_actions=3, horizon=None, gamma=0.8, seed=seed)
    ds, w = full_support_dataset(m)
    w = np.where(ds.arrays().action == 2, 0.0, w)  # action 2 never logged
    start = uniform_over_logged(ds, w)
    assert start.actions == [0, 1] and (start.probabilities(np.zeros((2, 1)))[:, 2] == 0).all()
    fqe = FittedQEvaluation(gamma=0.8, regressor="tabular", action_input="onehot", n_iterations=400, tol=1e-14)
    api = ApproximatePolicyIteration(fqe, n_iterations=9).fit(ds, sample_weight=w)
    opt = dp.value_iteration_discounted(m.P[:2], m.C[:, :2], 0.8)  # the model of the logged actions
    np.testing.assert_array_equal(api.policy_.act(np.arange(8.0)[:, None], return_index=True), opt.policy)
    cpi = ConservativePolicyIteration(fqe=fqe, n_iterations=6).fit(ds, sample_weight=w)
    assert (cpi.policy_.probabilities(np.arange(8.0)[:, None])[:, 2] == 0).all()
    assert _exact_cost(m, cpi.policy_) <= _exact_cost(m, start) + 1e-12
    assert uniform_over_logged(*full_support_dataset(m)).actions is None  # every action logged: all of them


def test_a_uniform_policy_over_some_actions_is_stored_and_read_back(tmp_path):
    from offline_adp.artifacts.policy_kinds import load_index_policy, save_policy

    pi = UniformPolicy(4, [1, 3])
    np.testing.assert_array_equal(pi.probabilities(np.zeros((1, 2))), [[0, 0.5, 0, 0.5]])
    save_policy(pi, tmp_path / "p")
    back = load_index_policy(tmp_path / "p")
    assert back.actions == [1, 3] and back.n_actions == 4
    with pytest.raises(Exception, match="distinct action indices"):
        UniformPolicy(4, [1, 1])
