"""The divergence monitor flags only unambiguous evidence; every fit ends with a verdict."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.fqi_monitor import DivergenceMonitor, trend
from offline_adp.errors import DivergenceWarning


def _rows(M):
    return [{"iteration": k + 1, "max_abs_q": float(m), "sup_dq": 1.0} for k, m in enumerate(M)]


def _first_flag(monitor, M):
    rows = _rows(M)
    for k in range(1, len(rows) + 1):
        if monitor.check(rows[:k]):
            return k
    return None


@pytest.mark.parametrize("seed", range(5))
def test_noisy_approach_to_a_fixed_point_is_never_flagged(seed):
    # max|Q_k| = 100 (1 - 0.99^k) with 1% multiplicative noise (refit trees), 300 iterations
    k = np.arange(1, 301)
    M = 100 * (1 - 0.99**k) * (1 + 0.01 * np.random.default_rng(seed).standard_normal(len(k)))
    assert _first_flag(DivergenceMonitor(bound=100.0, bound_text="b"), np.abs(M)) is None


def test_linear_growth_and_a_single_jump_are_not_flagged_geometric_growth_is():
    inf = DivergenceMonitor(bound=np.inf, bound_text="none")
    assert _first_flag(inf, 0.5 * np.arange(1, 200)) is None  # undiscounted shortest path: linear
    jump = np.r_[np.full(30, 60.0), np.full(30, 68.0)]  # a rebuilt structure lifts the values once
    assert _first_flag(inf, jump) is None
    k = np.arange(1, 60)
    assert 22 <= _first_flag(inf, 2 * 1.08**k) <= 23  # two windows of 10 (1.08^10 = 2.16 >= 1.5), held 3 times
    assert _first_flag(inf, 2 * 1.02**k) is None  # 1.02^10 = 1.22: slow, keep watching (the bound catches it)


def test_bound_with_margin():
    m = DivergenceMonitor(bound=10.0, bound_text="b", margin=0.1)
    assert m.check(_rows([10.9])) is None
    assert "exceeds the bound" in m.check(_rows([11.1]))
    assert trend([1.0, 0.5, 0.25, 0.12]) == "decreasing" and trend([1.0, 1.0, 1.0]) == "flat"


def test_every_fit_ends_with_a_verdict(small_pt):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DivergenceWarning)
        f = FittedQIteration(regressor_params={"n_estimators": 5, "n_jobs": 1}, n_iterations=6).fit(small_pt)
        assert f.verdict_ == "still changing" and "sup|dQ|" in f.verdict_message_
        assert f.history_["verdict"].iloc[-1] == "still changing"
        g = FittedQIteration(regressor="tabular", n_iterations=500, tol=1e-9, gamma=0.5).fit(small_pt)
        assert g.verdict_ == "converged" and len(g.history_) < 500
        h = FittedQIteration(horizon=3, regressor_params={"n_estimators": 5, "n_jobs": 1}).fit(small_pt)
        assert h.verdict_ == "completed"
    assert (f.history_["cpu_time"] >= 0).all()


def test_a_lookup_tables_verdict_states_the_contraction_bound_and_it_holds():
    """A refit with the lookup table is exact value iteration on the logs' empirical model: its
    backup is a gamma-contraction, so the distance bound holds. It said "still changing (no
    contraction bound here)" at the exact fixed point, and "converged" on sup|dQ| < tol when the
    values were 0.98 from it (gamma 0.99, tol 0.01)."""
    import numpy as np

    from offline_adp import dp
    from offline_adp.algorithms.fqi import FittedQIteration
    from offline_adp.envs import TabularMDP
    from offline_adp.rollout import collect

    mdp = TabularMDP(n_states=5, n_actions=2, horizon=30, gamma=0.9, seed=2)
    ds = collect(mdp, mdp.exploration(), 300, np.random.default_rng(0), horizon=30)
    a = ds.arrays()
    S, A = 5, 2
    s, x2 = a.obs[:, 0].astype(int), a.next_obs[:, 0].astype(int)
    P, C, N = np.zeros((A, S + 1, S + 1)), np.zeros((S + 1, A)), np.zeros((S, A))
    np.add.at(N, (s, a.action), 1)
    np.add.at(C, (s, a.action), a.cost)
    np.add.at(P, (a.action, s, np.where(a.terminated, S, x2)), 1)
    C[:S] /= np.maximum(N, 1)
    P[:, :S] /= np.maximum(N.T[:, :, None], 1)
    P[:, S, S] = 1.0
    assert (N > 0).all()
    exact = dp.value_iteration_discounted(P, C, 0.9).Q[:S]
    for kw in ({"n_iterations": 1000}, {"n_iterations": 1000, "tol": 0.05}, {"n_iterations": 20}):
        f = FittedQIteration(gamma=0.9, regressor="tabular", action_input="onehot", **kw).fit(ds)
        err = np.abs(f.q_function_.values(np.arange(S, dtype=float)[:, None]) - exact).max()
        last = f.history_.iloc[-1]
        stated = float(re.search(r"within (\S+) of its fixed point", f.verdict_message_).group(1))
        # gamma/(1-gamma) sup|dQ| plus float64 rounding's allowance (tiny at these values)
        assert 9.0 * last["sup_dq"] * (1 - 5e-3) <= stated <= 9.0 * last["sup_dq"] * (1 + 5e-3) + 1e-8
        assert err <= stated * (1 + 5e-3) and "lookup table" in f.verdict_message_  # (stated to 3 digits)
        assert (f.verdict_ == "converged") == (stated <= max(kw.get("tol", 0.0), 0.01 * last["max_abs_q"]))
    assert FittedQIteration(gamma=0.9, regressor="tabular", action_input="onehot",
                            n_iterations=1000).fit(ds).verdict_ == "converged"  # was "still changing"
