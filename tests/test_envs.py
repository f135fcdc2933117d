"""Reference problems against independent computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from offline_adp import dp
from offline_adp.access import (
    AccessModelError,
    FullModel,
    GenerativeModel,
    ResetModel,
    Simulator,
    require,
)
from offline_adp.envs import CarOnHill, Gridworld, PathTracking, TabularMDP, TwoState, make_problem
from offline_adp.envs.car_on_hill import score, score_grid
from offline_adp.envs.gridworld import optimal_cost_to_go
from offline_adp.errors import UnknownNameError
from offline_adp.policies import FunctionPolicy


def _scalar_car_step(p, s, u):
    """Independent scalar Euler integration written from the paper's equations."""
    for _ in range(100):
        if p < 0:
            h1, h2 = 2 * p + 1, 2.0
        else:
            h1 = 1 / (1 + 5 * p * p) ** 1.5
            h2 = -15 * p / (1 + 5 * p * p) ** 2.5
        acc = u / (1 + h1 * h1) - 9.81 * h1 / (1 + h1 * h1) - s * s * h1 * h2 / (1 + h1 * h1)
        p, s = p + 0.001 * s, s + 0.001 * acc
    return p, s


@pytest.mark.parametrize("start", [(-0.5, 0.0), (0.0, 0.0), (0.3, 1.2), (-0.9, -0.5)])
def test_car_on_hill_matches_independent_integration(start):
    prob = CarOnHill()
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 2, size=30)
    x = np.array([start])
    p, s = start
    for a in actions:
        r = prob.step_seeded(x, np.array([a]))
        p, s = _scalar_car_step(p, s, [-4.0, 4.0][a])
        np.testing.assert_allclose(r.next_states[0], [p, s], atol=1e-6, rtol=0)
        x = r.next_states
        lose = p < -1 or abs(s) > 3
        win = p > 1 and abs(s) <= 3
        assert bool(r.terminated[0]) == (lose or win)
        assert r.costs[0] == (1.0 if lose else -1.0 if win else 0.0)
        if lose or win:
            break


@pytest.mark.slow
def test_car_on_hill_score_grid_and_terminal_rewards():
    g = score_grid()
    assert g.shape == (289, 2) and g[:, 0].min() == -1 and g[:, 1].max() == 3
    # Always pushing left from the grid: every start eventually leaves at p < -1 or overspeeds,
    # so each return is -gamma^k for some k >= 0: the mean lies in [-1, 0).
    sc = score(FunctionPolicy(lambda x, t: np.zeros(len(x), int), 2))
    assert -1.0 <= sc < 0.0


def test_gridworld_optimal_cost_to_go_is_linear():
    gw = Gridworld()
    fm = gw.full_model()
    sol = dp.value_iteration_finite(fm.P, fm.C, horizon=60)  # 40 moves suffice from anywhere
    xy = gw.lattice_states()
    np.testing.assert_allclose(sol.V[0], optimal_cost_to_go(xy), atol=1e-12)
    # and that is an affine function of (x, y): a least-squares plane fits exactly
    A = np.column_stack([np.ones(len(xy)), xy])
    coef, *_ = np.linalg.lstsq(A, sol.V[0], rcond=None)
    np.testing.assert_allclose(coef, [20.0, -10.0, -10.0], atol=1e-9)
    np.testing.assert_allclose(A @ coef, sol.V[0], atol=1e-9)


def test_gridworld_simulator_agrees_with_full_model():
    gw = Gridworld()
    fm = gw.full_model()
    xy = gw.lattice_states()
    for a in range(4):
        r = gw.step_seeded(xy, np.full(len(xy), a))
        k = np.round(r.next_states / 0.05).astype(int)
        idx = k[:, 0] * 21 + k[:, 1]
        nonterm = np.arange(len(xy)) != len(xy) - 1
        assert (fm.P[a, np.arange(len(xy)), idx][nonterm] == 1.0).all()
        assert (r.terminated == fm.terminal[idx]).all()


def test_two_state_full_model():
    m = TwoState()
    assert (m.P[0][:, 1] == 1).all() and (m.C == 0).all() and m.gamma == 0.9
    V = dp.policy_evaluation_discounted(m.P, m.C, np.array([0, 0]), m.gamma).V
    np.testing.assert_allclose(V, 0.0)


def test_full_model_sampling_frequencies():
    m = TabularMDP(n_states=5, n_actions=2, seed=3)
    rng = np.random.default_rng(0)
    n = 40000
    r = m.step(np.full((n, 1), 2.0), np.ones(n, int), rng)
    freq = np.bincount(r.next_states[:, 0].astype(int), minlength=5) / n
    assert np.abs(freq - m.P[1, 2]).max() < 0.015
    np.testing.assert_allclose(r.costs, m.C[2, 1])


def test_simulator_is_deterministic_given_seed_and_common_random_numbers():
    pt = PathTracking()
    x = pt.initial_states(50, np.random.default_rng(0))
    a = pt.step_seeded(x, np.full(50, 3), seed=7)
    b = pt.step_seeded(x, np.full(50, 3), seed=7)
    np.testing.assert_array_equal(a.next_states, b.next_states)
    c = pt.step_seeded(x, np.full(50, 3), seed=8)
    assert not np.allclose(a.next_states, c.next_states)


def test_access_model_hierarchy_and_require():
    assert isinstance(TabularMDP(), FullModel) and isinstance(TabularMDP(), Simulator)
    assert isinstance(CarOnHill(), Simulator) and isinstance(CarOnHill(), GenerativeModel)
    assert isinstance(PathTracking(), ResetModel)
    require(PathTracking(), GenerativeModel)
    with pytest.raises(AccessModelError, match="FullModel"):
        require(PathTracking(), FullModel)


def test_path_tracking_dynamics():
    pt = PathTracking(heading_noise=0.0)
    L = pt.course.length
    assert 380 < L < 430
    assert pt.course.curvature.min() < -0.03 and pt.course.curvature.max() > 0.02  # bends both ways
    # on the centre line, aligned, steering at the course's curvature: stays close to the line
    s0 = np.array([10.0])
    x = pt.observe(s0, np.zeros(1), np.zeros(1), np.arctan(2.7 * pt.course.kappa(s0)), np.array([8.0]))
    for _ in range(10):
        k = pt.course.kappa(x[:, 0])
        a = np.abs(pt.action_table.values[:, 0] - np.arctan(2.7 * k)).argmin()
        r = pt.step_seeded(x, np.array([a]), 0)
        x = r.next_states
    assert abs(x[0, 1]) < 0.3
    assert x[0, 0] == pytest.approx((10 + 8.0 * 1.0) % L, abs=0.2)  # ~8 m travelled in 1 s
    # leaving the road is terminal with the failure cost
    off = pt.observe(np.array([5.0]), np.array([1.99]), np.array([0.3]), np.zeros(1), np.array([9.0]))
    r = pt.step_seeded(off, np.array([6]), 0)
    assert r.terminated[0] and r.costs[0] == 50.0
    # cost of a normal step is |e'| + 0.1 cmd^2
    y = pt.initial_states(20, np.random.default_rng(1))
    r = pt.step_seeded(y, np.full(20, 5), 3)
    ok = ~r.terminated
    np.testing.assert_allclose(r.costs[ok], np.abs(r.next_states[ok, 1]) + 0.1 * 0.2**2)


def test_demonstrator_probabilities_are_distributions():
    pt = PathTracking()
    x = pt.initial_states(100, np.random.default_rng(2))
    p = pt.demonstrator().probabilities(x, 0)
    np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-12)
    assert (p >= 0.05 / 7 - 1e-12).all()  # epsilon mixture keeps every action possible


@pytest.mark.filterwarnings("ignore:.*Box observation space")
@pytest.mark.parametrize("name", ["car_on_hill", "gridworld", "path_tracking", "tabular", "two_state"])
def test_problems_are_gymnasium_envs(name):
    env = make_problem(name).make_env()
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    for _ in range(300):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert reward == -info["cost"]
        if terminated or truncated:
            break
    assert terminated or truncated


def test_unknown_problem_lists_known_names():
    with pytest.raises(UnknownNameError, match="car_on_hill"):
        make_problem("car_on_mountain")


def test_tabular_seeded_and_valid():
    a, b = TabularMDP(seed=9), TabularMDP(seed=9)
    np.testing.assert_array_equal(a.P, b.P)
    np.testing.assert_allclose(a.P.sum(-1), 1.0)
    assert math.isclose(a.initial_distribution.sum(), 1.0)
