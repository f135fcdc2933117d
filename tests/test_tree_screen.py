"""The frozen builds' tree screen (issue 14) against independent references.

- :func:`greedy_min_bias` against Monte Carlo sampling of ``min(X_a, X_b)``.
- The screen value a build records against a brute-force computation from the fitted
  forest's own per-tree leaves.
- A screened build that grows the whole forest gives the unscreened fit bit for bit; one
  that keeps the screen's trees gives the fit of a forest of that size.
- The decision follows ``screen_tol`` on both sides of the recorded value.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp import TransitionDataset
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.learn import greedy_min_bias
from offline_adp.regressors import make_regressor
from offline_adp.trees import builder as extra_trees
from offline_adp.trees.sklearn import sklearn_tree


def _walk(n: int = 240, seed: int = 0, n_actions: int = 3) -> TransitionDataset:
    """A noisy 2-d walk under random actions, distinct costs, a few terminal rows."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(n + 1, 2)), axis=0) * 0.1
    obs, nxt = x[:-1], x[1:].copy()
    info = DatasetInfo(features=(Feature("x"), Feature("v")),
                       action_table=ActionTable.from_values(np.arange(n_actions, dtype=float)))
    term = np.zeros(n, bool)
    term[[n // 3, n - 1]] = True
    ep = np.cumsum(np.r_[0, term[:-1]])
    step = np.concatenate([np.arange(c) for c in np.bincount(ep)])
    return TransitionDataset.from_arrays(
        info, episode_id=np.char.zfill(ep.astype(str), 3), step=step, obs=obs, action=rng.integers(0, n_actions, n),
        cost=rng.uniform(0, 1, n), next_obs=nxt, terminated=term, truncated=np.zeros(n, bool))


@settings(max_examples=25, deadline=None)
@given(z=st.floats(0.0, 3.5), tau=st.floats(0.05, 2.0))
def test_min_bias_is_the_shortfall_of_a_noisy_min(z, tau):
    # gap = z * tau with z <= 3.5: the sample holds ~90 or more negative draws, enough for the
    # normal approximation of its standard error (further out a miss of one rare draw fails it)
    gap = z * tau
    d = np.random.default_rng(0).normal(gap, tau, 400_000)  # X_b - X_a; E[min(X_a, X_b)] - mu_a = E[min(0, D)]
    sampled = -np.minimum(0.0, d).mean()
    se = np.minimum(0.0, d).std() / np.sqrt(len(d))
    assert abs(float(greedy_min_bias(np.array(gap), np.array(tau))) - sampled) <= 5 * se + 1e-12


def test_min_bias_shape():
    tau = np.array([0.0, 0.5, 1.0, 1.0, 1.0])
    gap = np.array([1.0, 0.0, 0.0, 1.0, 5.0])
    b = greedy_min_bias(gap, tau)
    assert b[0] == 0.0  # no noise, no bias
    np.testing.assert_allclose(b[1:3], tau[1:3] / np.sqrt(2 * np.pi))  # a tie: E[min] = -tau / sqrt(2 pi)
    assert b[2] > b[3] > b[4] > 0.0  # clearer decisions, less bias


def _brute_screen(ds: TransitionDataset, est: FittedQIteration, m: int, full: int, seed: int,
                  w: np.ndarray | None, builder: str = "sklearn") -> float:
    """The screen of the first build (k = 1, targets = costs), tree by tree from scikit-learn,
    state by state: the best action against each other one, summed; weighted mean over the
    non-terminal next states; times 1 / (1 - gamma); over the weighted std of the costs."""
    a = ds.arrays()
    enc = est._encoder
    X = enc.pairs(a.obs, a.action)
    y = a.cost
    w = np.ones(len(y)) if w is None else w
    forest = make_regressor("extra_trees", n_estimators=m, n_jobs=1).set_params(random_state=seed + 1)
    if builder == "sklearn":
        trees = forest.fit(X, y, sample_weight=w).estimators_
    else:  # the compiled builder's trees, looked up through scikit-learn trees set from their arrays
        grown = extra_trees.grow_trees(X, y, w, extra_trees.native_params(forest, *X.shape))
        trees = [SimpleNamespace(tree_=sklearn_tree(g.left, g.right, g.feature, g.threshold, g.value, X.shape[1]))
                 for g in grown]
        for t in trees:
            t.apply = t.tree_.apply
    A = enc.n_actions
    per_tree = np.empty((m, len(a.obs), A))
    for t, tree in enumerate(trees):
        leaf = tree.apply(X.astype(np.float32))
        total = np.bincount(leaf, weights=w * y, minlength=tree.tree_.node_count)
        mass = np.bincount(leaf, weights=w, minlength=tree.tree_.node_count)
        mean = np.divide(total, mass, out=np.zeros_like(total), where=mass > 0)
        for act in range(A):
            per_tree[t, :, act] = mean[tree.apply(enc.pairs(a.next_obs, np.full(len(a.obs), act)).astype(np.float32))]
    rows = np.flatnonzero(~a.terminated)
    short = np.zeros(len(rows))
    for k, i in enumerate(rows):
        v = per_tree[:, i, :]
        best = int(np.argmin(v.mean(axis=0)))
        for other in range(A):
            if other != best:
                d = v[:, other] - v[:, best]
                sd = d.std(ddof=1)
                short[k] += greedy_min_bias(d.mean(), sd / np.sqrt(m)) - greedy_min_bias(d.mean(), sd / np.sqrt(full))
    mu = np.average(y, weights=w)
    return float(np.average(short, weights=w[rows]) / (1 - est.gamma_) / np.sqrt(np.average((y - mu) ** 2, weights=w)))


@pytest.mark.parametrize("builder", ["auto", "sklearn"])
@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("n_actions", [2, 3])
def test_the_recorded_screen_is_the_brute_force_one(n_actions, weighted, builder):
    ds = _walk(n_actions=n_actions)
    w = np.random.default_rng(1).uniform(0.2, 3.0, len(ds)) if weighted else None
    est = FittedQIteration(gamma=0.9, n_iterations=1, mode="frozen", regressor_params={"n_estimators": 8, "n_jobs": 1},
                           screen_trees=3, screen_tol=1e9, random_state=5,
                           tree_builder=builder).fit(ds, sample_weight=w)
    row = est.history_.iloc[0]
    assert row["structure_trees"] == 3
    assert row["structure_screen"] == pytest.approx(_brute_screen(ds, est, 3, 8, 5, w, builder), rel=1e-9)


def test_growing_the_whole_forest_is_the_unscreened_fit_and_keeping_is_a_smaller_forest():
    ds = _walk(seed=1)
    obs = np.random.default_rng(3).normal(size=(40, 2)) * 0.3
    kw = dict(gamma=0.95, n_iterations=9, mode="frozen", n_structures=3, random_state=2)
    plain = FittedQIteration(regressor_params={"n_estimators": 8, "n_jobs": 1}, screen_trees=None, **kw).fit(ds)
    grown = FittedQIteration(regressor_params={"n_estimators": 8, "n_jobs": 1}, screen_trees=3, screen_tol=1e-12,
                             **kw).fit(ds)
    np.testing.assert_array_equal(grown.predict(obs), plain.predict(obs))
    np.testing.assert_array_equal(grown.history_["sup_dq"], plain.history_["sup_dq"])
    assert set(grown.history_["structure_trees"]) == {8} and grown.history_["structure_screen"].notna().all()
    assert plain.history_["structure_screen"].isna().all()

    kept = FittedQIteration(regressor_params={"n_estimators": 8, "n_jobs": 1}, screen_trees=3, screen_tol=1e9,
                            **kw).fit(ds)
    small = FittedQIteration(regressor_params={"n_estimators": 3, "n_jobs": 1}, screen_trees=None, **kw).fit(ds)
    np.testing.assert_array_equal(kept.predict(obs), small.predict(obs))
    assert set(kept.history_["structure_trees"]) == {3}


def test_the_decision_follows_the_tolerance_on_both_sides():
    ds = _walk(seed=2)
    kw = dict(gamma=0.99, n_iterations=1, mode="frozen", regressor_params={"n_estimators": 8, "n_jobs": 1},
              screen_trees=3, random_state=0)
    value = FittedQIteration(screen_tol=1e-12, **kw).fit(ds).history_["structure_screen"].iloc[0]
    assert value > 0
    assert FittedQIteration(screen_tol=value * 1.001, **kw).fit(ds).history_["structure_trees"].iloc[0] == 3
    assert FittedQIteration(screen_tol=value * 0.999, **kw).fit(ds).history_["structure_trees"].iloc[0] == 8


@pytest.mark.parametrize("case", ["tol0", "gamma1", "one_action", "small_forest"])
def test_no_screen_where_it_has_nothing_to_decide(case):
    """tol 0, gamma 1, one action, or a forest no larger than the screen: the whole forest,
    no screen value."""
    ds = _walk(n_actions=1 if case == "one_action" else 2)
    kw = dict(gamma=1.0 if case == "gamma1" else 0.9, n_iterations=2, mode="frozen", n_structures=2,
              regressor_params={"n_estimators": 3 if case == "small_forest" else 8, "n_jobs": 1},
              screen_trees=3, screen_tol=0.0 if case == "tol0" else 1e9)
    h = FittedQIteration(**kw).fit(ds).history_
    assert set(h["structure_trees"]) == {kw["regressor_params"]["n_estimators"]}
    assert h["structure_screen"].isna().all()


def test_weighted_grown_build_is_the_unscreened_one_with_bootstrap_rows():
    ds = _walk(seed=4)
    w = np.random.default_rng(2).uniform(0.2, 3.0, len(ds))
    obs = np.random.default_rng(3).normal(size=(30, 2)) * 0.3
    kw = dict(gamma=0.95, n_iterations=5, mode="frozen", n_structures=2, structure_max_samples=0.5, random_state=1,
              regressor_params={"n_estimators": 7, "n_jobs": 2})
    plain = FittedQIteration(screen_trees=None, **kw).fit(ds, sample_weight=w)
    grown = FittedQIteration(screen_trees=2, screen_tol=1e-12, **kw).fit(ds, sample_weight=w)
    assert set(grown.history_["structure_trees"]) == {7}
    np.testing.assert_array_equal(grown.predict(obs), plain.predict(obs))


def test_policy_evaluation_fits_without_screening():
    from offline_adp.policies import FunctionPolicy

    ds = _walk(n_actions=2)
    fqe = FittedQEvaluation(policy=FunctionPolicy(lambda x, t: np.zeros(len(x), int), n_actions=2), gamma=0.9,
                            n_iterations=2, mode="frozen", regressor_params={"n_estimators": 12, "n_jobs": 1}).fit(ds)
    assert set(fqe.history_["structure_trees"]) == {12} and fqe.history_["structure_screen"].isna().all()


def test_structure_builds_reads_histories_from_before_the_screen():
    import pandas as pd

    from offline_adp.algorithms.fqi import structure_builds

    h = pd.DataFrame({"iteration": [1, 2, 3, 4], "structure": [1, 1, 2, 3],
                      "structure_trees": [np.nan, np.nan, 10, 50], "structure_screen": [np.nan, np.nan, 0.001, np.nan],
                      "structure_on_constant": [True, True, False, np.nan]})
    assert structure_builds(h) == [{"iteration": 1, "trees": None, "screen": None, "constant": True, "builder": None},
                                   {"iteration": 3, "trees": 10, "screen": 0.001, "constant": False, "builder": None},
                                   {"iteration": 4, "trees": 50, "screen": None, "constant": False, "builder": None}]
    h["structure_builder"] = [None, None, "scikit-learn", "compiled"]  # recorded since the compiled builder
    assert [b["builder"] for b in structure_builds(h)] == [None, "scikit-learn", "compiled"]


@pytest.mark.parametrize("bad", [{"screen_trees": 0}, {"screen_trees": 1}, {"screen_trees": True},
                                 {"screen_trees": "10"},
                                 {"screen_tol": -0.1}, {"screen_tol": float("nan")}, {"screen_tol": True}])
def test_bad_screen_parameters_are_refused_before_fitting(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        FittedQIteration(gamma=0.9, n_iterations=1, **bad).fit(_walk())
