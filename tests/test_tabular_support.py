"""Fitted Q-iteration with the lookup table is exact DP on the data's empirical model, whose
actions at a state are the actions logged there.

The oracle (:func:`empirical_dp`) builds that model by hand from the logged transitions and
solves it by value iteration, without the package: at a state with at least one logged
action, ``Q(s, a)`` is the mean over the rows logging ``(s, a)`` of ``c + gamma (1 - term)
V(s')`` and ``V(s)`` is the minimum over the logged actions only; at a state never logged
as a source state (only reached), no action is logged, every action's Q is the table's
``fill_value`` and so is ``V``. The greedy policy is the argmin over the logged actions
(every action at a state with none), ties to the lowest index.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp import TransitionDataset
from offline_adp.algorithms.fqi import FittedQIteration, load_fqi, save_fqi
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.errors import ExportError


def dataset(s, a, c, sp, term, n_actions, episodes=None):
    """Transitions of a finite problem: obs ``[[s]]``, each row its own episode unless given."""
    n = len(s)
    info = DatasetInfo(features=(Feature("s"),),
                       action_table=ActionTable.from_values(np.arange(n_actions, dtype=float)))
    ep = np.char.zfill(np.arange(n).astype(str), 7) if episodes is None else episodes
    step = np.zeros(n) if episodes is None else np.arange(n)
    return TransitionDataset.from_arrays(info, episode_id=ep, step=step, obs=np.asarray(s, float)[:, None],
                                         action=a, cost=c, next_obs=np.asarray(sp, float)[:, None],
                                         terminated=term, truncated=~np.asarray(term))


def empirical_dp(s, a, c, sp, term, S, A, gamma, horizon=None, fill_value=0.0, sweeps=2000):
    """``(Q, logged, policy)``: the empirical model's Q (``(S, A)``, or ``(T, S, A)`` for a
    finite horizon; ``fill_value`` where not logged), the logged mask ``(S, A)`` and the greedy
    policy restricted to the logged actions (``(S,)`` or ``(T, S)``)."""
    logged = np.zeros((S, A), bool)
    logged[s, a] = True
    count = np.zeros((S, A))
    np.add.at(count, (s, a), 1.0)

    def backup(V):
        q = np.full((S, A), float(fill_value))
        tot = np.zeros((S, A))
        np.add.at(tot, (s, a), c + gamma * np.where(term, 0.0, V[sp]))
        q[logged] = tot[logged] / count[logged]
        return q

    def value(q):
        masked = np.where(logged, q, np.inf)
        return np.where(logged.any(axis=1), masked.min(axis=1), q.min(axis=1))

    def greedy(q):
        masked = np.where(logged | ~logged.any(axis=1, keepdims=True), q, np.inf)
        return masked.argmin(axis=1)

    if horizon is None:
        V = np.zeros(S)
        for _ in range(sweeps):
            q = backup(V)
            V_new = value(q)
            if np.abs(V_new - V).max() < 1e-14:
                break
            V = V_new
        q = backup(V)
        return q, logged, greedy(q)
    V = np.zeros(S)  # V_T = 0: no Q beyond the horizon
    Q = np.zeros((horizon, S, A))
    for t in range(horizon - 1, -1, -1):
        Q[t] = backup(V)
        V = value(Q[t])
    return Q, logged, np.stack([greedy(Q[t]) for t in range(horizon)])


def random_problem(seed, S, A, n, terminal=0.1):
    """Random logs where each state has its own random non-empty subset of logged actions
    (every action logged somewhere, so per-action tables exist) and positive costs; some
    states are only ever reached."""
    rng = np.random.default_rng(seed)
    allowed = rng.random((S, A)) < 0.5
    allowed[np.arange(S), rng.integers(0, A, S)] = True
    sources = S - 1 if S > 2 else S  # the last state: only reached, never a source
    s = rng.integers(0, sources, n)
    a = np.array([rng.choice(np.flatnonzero(allowed[x])) for x in s])
    missing = np.setdiff1d(np.arange(A), a)
    a[: len(missing)] = missing  # every action somewhere (a per-action table each)
    s[: len(missing)] = 0
    c = rng.uniform(0.1, 1.0, n)
    sp = rng.integers(0, S, n)
    term = rng.random(n) < terminal
    return s, a, c, sp, term


def fit(s, a, c, sp, term, A, *, encoding="joint", gamma=0.8, horizon=None, action_input="onehot",
        regressor="tabular", **kw):
    ds = dataset(s, a, c, sp, term, A)
    return FittedQIteration(gamma=gamma, horizon=horizon, regressor=regressor, action_encoding=encoding,
                            action_input=action_input, n_iterations=400, tol=1e-13, **kw).fit(ds)


def check_against_oracle(f, s, a, c, sp, term, S, A, gamma, horizon=None, fill_value=0.0):
    Q, logged, pi = empirical_dp(s, a, c, sp, term, S, A, gamma, horizon, fill_value)
    states = np.arange(S, dtype=float)[:, None]
    for t in range(horizon or 1):
        q_oracle, pi_oracle = (Q, pi) if horizon is None else (Q[t], pi[t])
        q_fit = f.q_function_.values(states, t)
        np.testing.assert_allclose(q_fit[logged], q_oracle[logged], atol=1e-8, rtol=0)
        assert (q_fit[~logged] == fill_value).all()  # the table still answers fill_value there
        np.testing.assert_array_equal(f.policy_.actions(states, t), pi_oracle)
        at_logged = np.take_along_axis(logged, np.asarray(f.policy_.actions(states, t))[:, None], 1)[:, 0]
        assert at_logged[logged.any(axis=1)].all()  # never an unlogged action where one is logged


def test_one_episode_always_taking_action_1_gives_a_greedy_policy_of_action_1():
    """The helper's example (docs/fqi-modes.md): one episode always taking action 1 of 3."""
    rng = np.random.default_rng(0)
    n, S = 40, 5
    states = rng.integers(0, S, n + 1)
    s, sp = states[:-1], states[1:]
    a = np.ones(n, np.int64)
    c = rng.uniform(0.5, 1.0, n)
    term = np.zeros(n, bool)
    ds = dataset(s, a, c, sp, term, 3, episodes=np.full(n, "e0"))
    f = FittedQIteration(gamma=0.9, regressor="tabular", action_input="onehot", n_iterations=400, tol=1e-13).fit(ds)
    logged_states = np.unique(s).astype(float)[:, None]
    assert (f.policy_.actions(logged_states) == 1).all()
    Q, _, pi = empirical_dp(s, a, c, sp, term, S, 3, 0.9)
    np.testing.assert_allclose(f.q_function_.values(logged_states)[:, 1], Q[np.unique(s), 1], atol=1e-8, rtol=0)
    assert (f.history_["start_value"].iloc[-1] > 0)  # the backup's minimum never reached an unlogged 0


@pytest.mark.parametrize("encoding", ["joint", "per_action"])
@pytest.mark.parametrize("action_input", ["onehot", "value"])
def test_infinite_horizon_matches_dp_on_the_empirical_model(encoding, action_input):
    S, A, gamma = 7, 4, 0.8
    s, a, c, sp, term = random_problem(3, S, A, 120)
    f = fit(s, a, c, sp, term, A, encoding=encoding, gamma=gamma, action_input=action_input)
    check_against_oracle(f, s, a, c, sp, term, S, A, gamma)
    assert f.verdict_ == "converged"  # a min over a fixed action set per state: still a gamma-contraction


@pytest.mark.parametrize("encoding", ["joint", "per_action"])
def test_finite_horizon_matches_dp_on_the_empirical_model(encoding):
    S, A, T = 6, 3, 5
    s, a, c, sp, term = random_problem(5, S, A, 90)
    f = fit(s, a, c, sp, term, A, encoding=encoding, gamma=1.0, horizon=T)
    check_against_oracle(f, s, a, c, sp, term, S, A, 1.0, horizon=T)


def test_a_pessimistic_fill_value_still_fills_states_without_a_logged_action():
    """``fill_value`` stays the answer at unlogged pairs, and the value of states where
    nothing is logged (here 5, only reached)."""
    S, A, gamma = 6, 3, 0.7
    s, a, c, sp, term = random_problem(11, S, A, 80)
    f = fit(s, a, c, sp, term, A, gamma=gamma, regressor_params={"fill_value": 3.0})
    check_against_oracle(f, s, a, c, sp, term, S, A, gamma, fill_value=3.0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), S=st.integers(2, 7), A=st.integers(2, 4), n=st.integers(10, 80),
       encoding=st.sampled_from(["joint", "per_action"]), horizon=st.sampled_from([None, 1, 3]),
       gamma=st.sampled_from([0.5, 0.9]))
def test_property_tabular_fqi_is_dp_on_the_empirical_model(seed, S, A, n, encoding, horizon, gamma):
    s, a, c, sp, term = random_problem(seed, S, A, n)
    f = fit(s, a, c, sp, term, A, encoding=encoding, gamma=gamma, horizon=horizon)
    check_against_oracle(f, s, a, c, sp, term, S, A, gamma, horizon)


@pytest.mark.parametrize("horizon", [None, 3])
def test_a_saved_tabular_policy_loads_and_acts_the_same(tmp_path, horizon):
    from offline_adp.artifacts import load_index_policy, save_policy

    S, A = 6, 3
    s, a, c, sp, term = random_problem(2, S, A, 60)
    f = fit(s, a, c, sp, term, A, horizon=horizon, gamma=0.8)
    states = np.arange(S, dtype=float)[:, None]
    save_fqi(f, tmp_path / "fqi")
    g = load_fqi(tmp_path / "fqi")
    save_policy(f.policy_, tmp_path / "pi")
    pi = load_index_policy(tmp_path / "pi")
    for t in range(horizon or 1):
        want = f.policy_.actions(states, t)
        np.testing.assert_array_equal(g.policy_.actions(states, t), want)
        np.testing.assert_array_equal(pi.actions(states, t), want)
    _, logged, oracle = empirical_dp(s, a, c, sp, term, S, A, 0.8, horizon)
    np.testing.assert_array_equal(pi.actions(states, 0), oracle if horizon is None else oracle[0])


def test_onnx_export_of_a_tabular_policy_is_refused_with_export_error(tmp_path):
    pytest.importorskip("onnx")
    from offline_adp.onnx_export import save_onnx

    s, a, c, sp, term = random_problem(2, 5, 3, 40)
    f = fit(s, a, c, sp, term, 3)
    with pytest.raises(ExportError, match="TabularRegressor"):
        save_onnx(f.policy_, tmp_path / "pi.onnx")


def test_other_regressors_ignore_the_support():
    """Only the lookup table restricts: a k-NN Q has no support and acts on the plain argmin."""
    from offline_adp.qfunctions import restrict_to_support

    s, a, c, sp, term = random_problem(4, 5, 3, 60)
    f = fit(s, a, c, sp, term, 3, regressor="knn")
    states = np.arange(5, dtype=float)[:, None]
    assert f.q_function_.support(states) is None
    np.testing.assert_array_equal(f.policy_.actions(states), f.q_function_.values(states).argmin(axis=1))
    q = np.array([[3.0, 1.0], [2.0, 5.0]])
    assert restrict_to_support(q, None) is q


def test_fqe_with_the_lookup_table_does_not_restrict():
    """FQE evaluates the given policy: its backups read that policy's actions, unlogged or not."""
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.policies import TabularPolicy

    S, A, gamma = 5, 3, 0.8
    s, a, c, sp, term = random_problem(6, S, A, 60)
    pi = TabularPolicy(np.zeros(S, np.int64), n_actions=A)  # action 0 everywhere, logged or not
    ds = dataset(s, a, c, sp, term, A)
    fqe = FittedQEvaluation(policy=pi, gamma=gamma, regressor="tabular", action_input="onehot", n_iterations=400,
                            tol=1e-13).fit(ds)
    # exact evaluation of pi on the empirical model: Q(s, a) logged pairs, fill_value 0 at unlogged ones
    logged = np.zeros((S, A), bool)
    logged[s, a] = True
    count = np.zeros((S, A))
    np.add.at(count, (s, a), 1.0)
    V = np.zeros(S)
    for _ in range(2000):
        tot = np.zeros((S, A))
        np.add.at(tot, (s, a), c + gamma * np.where(term, 0.0, V[sp]))
        q = np.where(logged, tot / np.maximum(count, 1), 0.0)
        V = q[:, 0]
    np.testing.assert_allclose(fqe.q_function_.values(np.arange(S, dtype=float)[:, None]), q, atol=1e-8, rtol=0)


@pytest.mark.parametrize("horizon", [None, 4])
def test_a_fit_resumed_from_a_saved_q_equals_the_uninterrupted_one(tmp_path, horizon):
    """A resumed fit's learner holds a loaded Q (guarded lookup tables): its backups still
    range over the logged actions."""
    from offline_adp.artifacts import load_q, save_q

    S, A, gamma = 6, 3, 0.8
    s, a, c, sp, term = random_problem(8, S, A, 70)
    ds = dataset(s, a, c, sp, term, A)
    params = dict(gamma=gamma, horizon=horizon, regressor="tabular", action_input="onehot", n_iterations=30)
    whole = FittedQIteration(**params).fit(ds)
    part = FittedQIteration(**params)
    rows = []
    for row in part.fit_iter(ds):
        rows.append(dict(row))
        if len(rows) == 2:
            break
    q, done = part.checkpoint_q()
    save_q(q, tmp_path / "q")
    loaded = load_q(tmp_path / "q")[0]
    resume = {"q": list(loaded.qs) if horizon else loaded, "history": rows[:done]}
    resumed = FittedQIteration(**params)
    for _ in resumed.fit_iter(ds, resume=resume):
        pass
    states = np.arange(S, dtype=float)[:, None]
    for t in range(horizon or 1):
        np.testing.assert_array_equal(resumed.q_function_.values(states, t), whole.q_function_.values(states, t))
        np.testing.assert_array_equal(resumed.policy_.actions(states, t), whole.policy_.actions(states, t))


def test_next_state_noise_reads_the_support_at_the_perturbed_states():
    """With next-state noise the backup reads Q at perturbed next states; a rounding feature map
    takes them back to the logged states, so the fit is still DP on the empirical model."""
    from sklearn.preprocessing import FunctionTransformer

    S, A, gamma = 6, 3, 0.7
    s, a, c, sp, term = random_problem(9, S, A, 80)
    f = fit(s, a, c, sp, term, A, gamma=gamma, mode="refit", next_state_noise=1e-3,
            feature_map=FunctionTransformer(np.rint))
    check_against_oracle(f, s, a, c, sp, term, S, A, gamma)
