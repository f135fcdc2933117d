"""``n_iterations="auto"``'s schedule (issue #44): structures built at geometrically spaced
iterations, the final one settled by an accelerated solver (:mod:`offline_adp.learn.settle`),
and the convergence statement still true: the verdict's distance holds against the exact
fixed point of the final structure, computed by solving its linear system."""

from __future__ import annotations

import re

import numpy as np
import pytest

from offline_adp.algorithms.fqi import FittedQIteration, structure_builds
from offline_adp.algorithms.fqi_modes import geometric_builds
from offline_adp.algorithms.fqi_monitor import auto_iterations, distance_bound, rounding_allowance
from offline_adp.learn.settle import Settle, _least_squares, settle_solve
from offline_adp.simulate import simulate

TREES = {"n_estimators": 5, "n_jobs": 1}


@pytest.fixture(scope="module")
def tab():
    """A discounted random MDP of 12 states, 3 actions, no termination (the values only
    accumulate: plain iteration from 0 is slow at gamma 0.99)."""
    return simulate("tabular", 10, 10, seed=0, horizon=30,
                    problem_options={"horizon": None, "gamma": 0.95, "n_states": 12})


def test_geometric_builds_end_at_a_power_of_two_up_to_a_quarter_of_k_b():
    for gamma, expected in ((0.99, (1, 4, 16, 64)), (0.97, (1, 4, 16)), (0.95, (1, 2, 8)), (0.9, (1, 4)),
                            (0.8, (1, 2)), (0.5, (1,))):
        kb = auto_iterations(gamma, settles=True)[0]
        got = geometric_builds(kb)
        assert got == expected, gamma
        last = got[-1]
        assert last & (last - 1) == 0 and last <= max(1, kb / 4) < 2 * last  # the largest power of two
        assert all(b == 4 * a for a, b in zip(got[1:], got[2:], strict=False))  # a factor 4 apart before it
    assert geometric_builds(100, last=0.5, ratio=2) == (1, 2, 4, 8, 16, 32)


def test_the_schedule_is_geometric_only_for_auto_iterations_without_a_count(tab):
    auto = FittedQIteration(gamma=0.99)
    auto.gamma_ = 0.99
    assert auto._schedule() == (1, 4, 16, 64)
    fixed = FittedQIteration(gamma=0.99, n_iterations=50)
    fixed.gamma_ = 0.99
    assert fixed._schedule() == (1, 13, 26, 38)  # one per 12.5 iterations, as before
    counted = FittedQIteration(gamma=0.99, n_structures=3)
    counted.gamma_ = 0.99
    assert counted._schedule() == (1, 100, 200)  # n_structures evenly over K_b, as before
    finite = FittedQIteration(horizon=20)
    assert finite._schedule() == (1, 11)


def test_builds_happen_where_the_rule_says_and_the_fit_converges(tab):
    est = FittedQIteration(gamma=0.99, regressor_params=TREES).fit(tab)
    assert est.mode_ == "frozen" and est.verdict_ == "converged", est.verdict_message_
    builds = structure_builds(est.history_)
    assert [b["iteration"] for b in builds] == [1, 4, 16, 64]
    assert [b["trees"] for b in builds] == [1, 1, 1, 5]  # a fifth of the forest before the last build
    h = est.history_
    solved = h.loc[h["inner_backups"] > 0, "iteration"].tolist()
    assert solved == [65]  # the first iteration in the final structure ran the solver ...
    assert len(h) == 66  # ... and the next, a plain backup, certified the fixed point
    assert int(h["inner_backups"].sum()) < auto_iterations(0.99, settles=True)[0]  # fewer than plain iteration's
    assert "backups in the final structure's solver" in est.verdict_message_


def _exact_fixed_point(est):
    """The final structure's fixed point ``y = c + gamma (1 - term) min_a K_a y`` by policy
    iteration with exact linear solves (``K_a``: the structure's averaging of training
    targets at the next states with action ``a``, built densely from its leaves)."""
    learner, data = est.fit_state_.learner, est.fit_state_.data
    P_train, P_next = learner.pos["train"], learner.pos["next"]
    n, A, m = data.n, data.n_actions, P_train.shape[0]
    w = np.ones(n) if data.weights is None else np.asarray(data.weights, float)
    K = np.zeros((A * n, n))
    for t in range(m):
        same = P_next[t][:, None] == P_train[t][None, :]
        W = same @ w
        K += np.where(W[:, None] > 0, same * w[None, :] / np.where(W > 0, W, 1.0)[:, None], 0.0)
    K /= m
    Ka = K.reshape(A, n, n)
    c = data.targets(np.zeros(n))
    d = data.targets(np.ones(n)) - c
    pi = learner.predict("next").argmin(axis=1)
    for _ in range(100):
        Kpi = Ka[pi, np.arange(n)]
        y = np.linalg.solve(np.eye(n) - d[:, None] * Kpi, c)
        new = (Ka @ y).argmin(axis=0)
        if np.array_equal(new, pi):
            break
        pi = new
    assert np.abs(c + d * (Ka @ y).min(axis=0) - y).max() < 1e-8  # a fixed point of the greedy backup
    return y


def test_the_stated_distance_holds_against_the_exact_fixed_point(tab):
    est = FittedQIteration(gamma=0.99, regressor_params=TREES).fit(tab)
    assert est.verdict_ == "converged"
    last = est.history_.iloc[-1]
    rounding = rounding_allowance(last["max_abs_q"], np.abs(tab.arrays().cost).max(), len(tab))  # float64's part
    bound = distance_bound(last["sup_dq"], 0.99, rounding)
    assert bound <= 0.01 * last["max_abs_q"]
    stated = float(re.search(r"within ([0-9.e+-]+) of the final tree structure", est.verdict_message_).group(1))
    assert stated == pytest.approx(bound, rel=1e-2)
    y_star = _exact_fixed_point(est)
    learner = est.fit_state_.learner
    learner.leaf_values = learner._leaf_means(y_star)  # the structure with its fixed point's leaf values
    q_star = learner.snapshot()
    x = np.linspace(-1.0, 13.0, 300)[:, None]  # every state, and beyond the data
    gap = np.abs(est.q_function_.values(x) - q_star.values(x)).max()
    assert 0 < gap <= bound + 1e-9


def test_plain_iteration_reaches_the_same_fixed_point_more_slowly(tab):
    """Without the solver (a fixed count of iterations: plain backups all along) the final
    structure's values approach the same fixed point, the bound shrinking by gamma per step."""
    whole = {"regressor_params": TREES, "early_build_trees": None}  # whole forests: the same builds either way
    est = FittedQIteration(gamma=0.99, **whole).fit(tab)
    assert est.verdict_ == "converged" and est.history_["inner_backups"].sum() > 0
    y_star = _exact_fixed_point(est)
    plain = FittedQIteration(gamma=0.99, n_iterations=len(est.history_), **whole)
    plain._schedule = lambda: (1, 4, 16, 64)  # the same builds, plain backups after
    plain.fit(tab)
    assert plain.history_["inner_backups"].sum() == 0 and plain.verdict_ == "still changing"
    learner = plain.fit_state_.learner
    np.testing.assert_array_equal(learner.pos["train"], est.fit_state_.learner.pos["train"])  # the same structure
    q_plain = learner.predict("train")
    learner.leaf_values = learner._leaf_means(y_star)
    learner._values, learner._cache = np.r_[learner.leaf_values, 0.0], {}
    q_star = learner.predict("train")
    assert np.abs(q_plain - q_star).max() > 5 * np.abs(est.fit_state_.learner.predict("train") - q_star).max()


def test_an_iteration_that_ran_the_solver_is_never_called_converged():
    est = FittedQIteration(gamma=0.9, n_iterations=10)
    est.gamma_, est.horizon_, est.mode_ = 0.9, None, "frozen"
    row = {"iteration": 5, "sup_dq": 0.0, "max_abs_q": 1.0, "structure": 2, "structure_on_constant": False}
    rows = [{**row, "iteration": 4}, {**row, "inner_backups": 0}]
    est._schedule = lambda: (1, 2)
    assert est._converged(rows)
    rows[-1]["inner_backups"] = 12
    assert not est._converged(rows)
    rows[-1]["inner_backups"] = float("nan")  # not recorded (a history from before): not a solver row
    assert est._converged(rows)


def _mdp(n=200, actions=1, seed=0):
    rng = np.random.default_rng(seed)
    P = rng.random((actions, n, n)) * (rng.random((actions, n, n)) < 0.05)
    P /= P.sum(axis=2, keepdims=True)
    return P, rng.random(n)


@pytest.mark.parametrize("actions", [1, 3])
def test_the_solver_reaches_the_fixed_point_in_fewer_backups(actions):
    """A policy's values (one action: linear, Anderson alone) and the optimal values of a
    random MDP (three actions, the minimum: modified policy iteration), against the exact
    solution (policy iteration with exact solves); plain iteration would need over 1,000
    backups for this tolerance at gamma 0.99."""
    gamma, n = 0.99, 200
    P, c = _mdp(n, actions)
    pi = np.zeros(n, int)
    for _ in range(50):  # exact policy iteration
        exact = np.linalg.solve(np.eye(n) - gamma * P[pi, np.arange(n)], c)
        new = (P @ exact).argmin(axis=0)
        if np.array_equal(new, pi):
            break
        pi = new
    settle = Settle(gamma=gamma, after=0, rtol=1e-6, memory=10)
    calls = []

    def evaluate(y):
        calls.append(1)
        return (P @ y).T  # Q(x', a) for every row and action

    targets, value = (lambda v: c + gamma * v), (lambda q: q.min(axis=1))
    g, used = settle_solve(np.zeros(n), evaluate, targets, value, settle, 5000, greedy=actions > 1)
    assert used == len(calls) < 200
    residual = np.abs(targets(value(evaluate(g))) - g).max()
    assert gamma / (1 - gamma) * residual <= 1e-6 * np.abs(g).max()  # certified by one more plain backup
    assert np.abs(g - exact).max() <= 1e-6 * np.abs(exact).max()  # and it is the fixed point
    again, _ = settle_solve(np.zeros(n), evaluate, targets, value, settle, 5000, greedy=actions > 1)
    np.testing.assert_array_equal(g, again)  # deterministic
    _, used = settle_solve(np.zeros(n), evaluate, targets, value, settle, 7, greedy=actions > 1)
    assert used == 7  # the budget


def test_least_squares_by_hand_matches_numpy():
    rng = np.random.default_rng(1)
    for m in (1, 3, 10):
        df = [rng.normal(size=500) for _ in range(m)]
        f = rng.normal(size=500)
        ref = np.linalg.lstsq(np.array(df).T, f, rcond=None)[0]
        np.testing.assert_allclose(_least_squares(df, f), ref, rtol=1e-6, atol=1e-9)
    assert _least_squares([np.zeros(5)], np.ones(5)) == [0.0]  # degenerate: no step


@pytest.mark.parametrize("stop_at", [64, 65])  # before the solver's iteration, and on it
def test_a_fit_interrupted_around_the_solver_resumes_to_the_same_fit(tmp_path, tab, stop_at):
    from offline_adp.runs import fit_run

    path = tmp_path / "ds"
    tab.save(path)
    params = {"gamma": 0.99, "regressor_params": TREES, "random_state": 2}
    ref = fit_run(path, tmp_path / "ref", params=params)
    assert ref.history_["inner_backups"].iloc[64] > 0

    def interrupt(row):
        if row["iteration"] == stop_at:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_run(path, tmp_path / "run", params=params, on_iteration=interrupt)
    est = fit_run(path, tmp_path / "run", params=params, resume=True)
    x = np.arange(12, dtype=float)[:, None]
    np.testing.assert_array_equal(est.q_function_.values(x), ref.q_function_.values(x))
    for c in ("sup_dq", "inner_backups", "structure"):
        np.testing.assert_array_equal(est.history_[c].to_numpy(float), ref.history_[c].to_numpy(float))
    assert est.verdict_ == ref.verdict_ == "converged"


def test_the_settled_fit_does_not_depend_on_the_thread_count(tab):
    a = FittedQIteration(gamma=0.99, regressor_params={"n_estimators": 5, "n_jobs": 1}).fit(tab)
    b = FittedQIteration(gamma=0.99, regressor_params={"n_estimators": 5, "n_jobs": 3}).fit(tab)
    assert a.history_["inner_backups"].sum() > 0
    x = np.arange(12, dtype=float)[:, None]
    np.testing.assert_array_equal(a.q_function_.values(x), b.q_function_.values(x))
    np.testing.assert_array_equal(a.history_["sup_dq"].to_numpy(), b.history_["sup_dq"].to_numpy())


def test_the_dask_engine_settles_as_the_local_fit(tmp_path, tab):
    pytest.importorskip("distributed")
    from distributed import Client, LocalCluster

    from offline_adp.engines.dask import DaskFit

    path = tmp_path / "ds"
    tab.save(path, rows_per_part=150)
    kw = {"gamma": 0.99, "regressor_params": {"n_estimators": 4, "n_jobs": 1}, "random_state": 1}
    local = FittedQIteration(**kw).fit(tab)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as c, Client(c) as cl:
        dist = FittedQIteration(**kw)
        list(DaskFit(cl).fit_iter(dist, path))
    assert local.history_["inner_backups"].sum() > 0
    x = np.arange(12, dtype=float)[:, None]
    np.testing.assert_array_equal(dist.q_function_.values(x), local.q_function_.values(x))
    for c in ("sup_dq", "max_abs_q", "inner_backups"):
        np.testing.assert_array_equal(dist.history_[c].to_numpy(float), local.history_[c].to_numpy(float))
    assert dist.verdict_ == local.verdict_ == "converged"
