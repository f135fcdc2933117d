"""The frozen-structure learner against independent references (issue 14).

- A structure rebuilt on every iteration from all rows is the refit loop: same Q.
- Structures grown on a row subsample keep *honest* leaves: each leaf's value is the
  (weighted) mean target over every training row that falls in it, and a prediction is the
  mean over trees; checked against a brute-force per-tree computation from the forest's
  own leaf lookups.
- Constant targets (one cost per step) give the constant Q without growing a forest.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import TransitionDataset
from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.simulate import simulate

TREES = {"n_estimators": 6, "n_jobs": 1}


@pytest.fixture(scope="module")
def pt():
    return simulate("path_tracking", 6, 6, seed=3, horizon=30)


def _continuous(n: int = 300, cost: np.ndarray | None = None, seed: int = 0) -> TransitionDataset:
    """Two episodes of a noisy 2-d walk under random actions; distinct costs unless given."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(n + 1, 2)), axis=0) * 0.1
    obs, nxt = x[:-1], x[1:]
    info = DatasetInfo(features=(Feature("x"), Feature("v")), action_table=ActionTable.from_values([0.0, 1.0]))
    half = n // 2
    nxt = nxt.copy()
    nxt[half - 1] = obs[half - 1] + 0.05  # the first episode ends there (not continued by row half)
    return TransitionDataset.from_arrays(
        info, episode_id=np.repeat(["a", "b"], [half, n - half]), step=np.r_[np.arange(half), np.arange(n - half)],
        obs=obs, action=rng.integers(0, 2, n), cost=rng.uniform(0, 1, n) if cost is None else cost, next_obs=nxt,
        terminated=np.zeros(n, bool), truncated=np.arange(n) == half - 1)


def test_a_structure_rebuilt_every_iteration_from_all_rows_is_the_refit_loop():
    ds = _continuous()
    kw = dict(gamma=0.9, n_iterations=4, regressor_params=TREES, random_state=2)
    refit = FittedQIteration(mode="refit", **kw).fit(ds)
    frozen = FittedQIteration(mode="frozen", n_structures=4, tree_builder="sklearn", **kw).fit(ds)
    obs = np.random.default_rng(5).normal(size=(50, 2)) * 0.5
    assert list(frozen.history_["structure"]) == [1, 2, 3, 4]
    np.testing.assert_allclose(frozen.predict(obs), refit.predict(obs), rtol=0, atol=1e-9)
    np.testing.assert_allclose(frozen.history_["sup_dq"], refit.history_["sup_dq"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("weighted", [False, True])
def test_subsampled_structures_average_every_training_row_in_a_leaf(pt, weighted):
    a = pt.arrays()
    w = np.random.default_rng(0).uniform(0.2, 2.0, len(pt)) if weighted else None
    f = FittedQIteration(gamma=0.9, n_iterations=1, mode="frozen", structure_max_samples=0.3, regressor_params=TREES,
                         random_state=1).fit(pt, sample_weight=w)
    learner = f.fit_state_.learner
    model = learner._structure_model(1)
    assert model.bootstrap and model.max_samples == 0.3
    ens = learner.ensemble
    full = FittedQIteration(gamma=0.9, n_iterations=1, mode="frozen", regressor_params=TREES, random_state=1).fit(pt)
    assert len(ens.value) < 0.5 * len(full.fit_state_.learner.ensemble.value)  # trees grown on ~30% of the rows
    enc = learner.encoder
    X = enc.pairs(a.obs, a.action)
    y = a.cost  # iteration 1: the targets are the costs
    ww = np.ones(len(y)) if w is None else w
    obs = simulate("path_tracking", 2, 2, seed=8, horizon=20).arrays().obs
    Xq = enc.all_pairs(obs)
    leaf_train, leaf_q = ens.apply(X), ens.apply(Xq)
    expect = np.zeros(len(Xq))
    for t in range(ens.n_trees):  # brute force, tree by tree: weighted mean of y over the rows in the query's leaf
        for i, leaf in enumerate(leaf_q[:, t]):
            rows = leaf_train[:, t] == leaf
            expect[i] += (ww[rows] * y[rows]).sum() / ww[rows].sum() if rows.any() else 0.0
    expect /= ens.n_trees
    np.testing.assert_allclose(f.predict(obs), expect.reshape(enc.n_actions, len(obs)).T, rtol=1e-12, atol=1e-12)
    # the training predictions (partly read from the next-state lookups) are the same averages
    np.testing.assert_allclose(learner.predict("train"),
                               f.q_function_.values(a.obs)[np.arange(len(a.obs)), a.action], rtol=1e-12, atol=1e-12)


def test_constant_targets_give_the_constant_without_a_forest():
    ds = _continuous(cost=np.ones(300))
    obs = ds.arrays().obs
    f = FittedQIteration(gamma=0.9, n_iterations=1, mode="frozen", regressor_params=TREES).fit(ds)
    assert not hasattr(f.fit_state_.learner.ensemble, "_forest")
    np.testing.assert_allclose(f.predict(obs), np.ones((len(obs), 2)), rtol=1e-12)
    f2 = FittedQIteration(gamma=0.9, n_iterations=3, mode="frozen", n_structures=1, regressor_params=TREES).fit(ds)
    # targets stay constant (1 + 0.9 * 1, ...): a one-leaf "build" each time
    assert list(f2.history_["structure"]) == [1, 2, 3]
    np.testing.assert_allclose(f2.predict(obs), np.full((len(obs), 2), 1 + 0.9 + 0.81), rtol=1e-12)


def test_a_list_gives_each_scheduled_build_its_row_fraction():
    ds = _continuous()
    f = FittedQIteration(gamma=0.9, n_iterations=4, mode="frozen", n_structures=2, structure_max_samples=[0.3, 1.0],
                         regressor_params=TREES).fit(ds)
    learner = f.fit_state_.learner
    assert [learner.schedule.fraction(k) for k in (1, 2, 3, 4)] == [0.3, 0.3, 1.0, 1.0]  # builds at 1 and 3
    assert len(learner.ensemble.value) == TREES["n_estimators"] * (2 * len(ds) - 1)  # the last: grown on every row
    with pytest.raises(ValueError, match="max_samples"):
        FittedQIteration(mode="frozen", structure_max_samples=[0.5, 1.5], regressor_params=TREES).fit(ds)


def test_the_auto_mode_runs_frozen_where_it_applies_and_refit_elsewhere():
    ds = _continuous()
    f = FittedQIteration(gamma=0.9, n_iterations=25, regressor_params=TREES).fit(ds)  # the defaults
    assert (f.mode, f.mode_) == ("auto", "frozen")
    assert f.history_["structure"].max() == 2  # round(0.08 * 25) builds, evenly spaced
    assert FittedQIteration(n_iterations=100)._schedule() == (1, 13, 26, 38, 51, 63, 76, 88)
    for other in ({"regressor": "lightgbm", "regressor_params": {"n_estimators": 5}}, {"action_encoding": "per_action"},
                  {"horizon": 3}, {"next_state_noise": 0.1}):
        g = FittedQIteration(gamma=0.9, n_iterations=2, **({"regressor_params": TREES} | other)).fit(ds)
        assert g.mode_ == "refit", other
    # the same schedule asked for explicitly is the same fit
    h = FittedQIteration(gamma=0.9, n_iterations=25, mode="frozen", n_structures=2, regressor_params=TREES).fit(ds)
    obs = np.random.default_rng(1).normal(size=(40, 2)) * 0.5
    np.testing.assert_array_equal(f.predict(obs), h.predict(obs))


def test_auto_structure_rows_cap_the_rows_a_structure_is_grown_on(monkeypatch):
    import offline_adp.algorithms.fqi_modes as fqi_modes

    ds = _continuous(400)
    kw = dict(gamma=0.9, n_iterations=2, mode="frozen", n_structures=1, regressor_params=TREES)
    full = FittedQIteration(**kw).fit(ds).fit_state_.learner
    assert full.schedule.fraction(1) is None and len(full.ensemble.value) == TREES["n_estimators"] * (2 * len(ds) - 1)
    monkeypatch.setattr(fqi_modes, "STRUCTURE_ROWS", 100)
    capped = FittedQIteration(**kw).fit(ds).fit_state_.learner
    assert capped.schedule.fraction(1) == pytest.approx(100 / 400)
    # a bootstrap of 100 rows: at most 100 distinct samples, so fewer than 2 * 100 nodes a tree
    assert len(capped.ensemble.value) < TREES["n_estimators"] * 2 * 100
    # ... while every training row still reads a leaf averaged over all rows in it
    assert np.isfinite(capped.predict("train")).all()


def test_fit_builds_the_result_once_and_fit_iter_keeps_it_current(monkeypatch):
    """``fit`` exports the frozen structure once, at the end; ``fit_iter`` sets ``q_function_``
    after every iteration (a caller may read it in between). Both end on the same Q."""
    from offline_adp import learn

    ds = _continuous()
    calls = []
    original = learn.FrozenTreesLearner.snapshot
    monkeypatch.setattr(learn.FrozenTreesLearner, "snapshot", lambda self: calls.append(1) or original(self))
    params = dict(gamma=0.9, n_iterations=6, mode="frozen", n_structures=2, regressor_params=TREES, random_state=1)
    a = FittedQIteration(**params).fit(ds)
    assert len(calls) == 1
    calls.clear()
    b = FittedQIteration(**params)
    seen = []
    for _ in b.fit_iter(ds):
        seen.append(b.q_function_.values(ds.arrays().obs[:5]).copy())
    assert len(calls) == 6 and len(seen) == 6
    assert not np.array_equal(seen[0], seen[-1])
    X = ds.arrays().obs
    np.testing.assert_array_equal(a.q_function_.values(X), b.q_function_.values(X))


def test_fqe_fit_also_builds_its_result_once(monkeypatch):
    """FQE runs the same loop: ``fit`` defers, ``fit_iter`` does not, same Q."""
    from offline_adp import learn
    from offline_adp.algorithms.fqe import FittedQEvaluation
    from offline_adp.policies import UniformPolicy

    ds = _continuous()
    calls = []
    original = learn.FrozenTreesLearner.snapshot
    monkeypatch.setattr(learn.FrozenTreesLearner, "snapshot", lambda self: calls.append(1) or original(self))
    params = dict(policy=UniformPolicy(2), gamma=0.9, n_iterations=5, mode="frozen", n_structures=2,
                  regressor_params=TREES, random_state=2)
    a = FittedQEvaluation(**params).fit(ds)
    assert len(calls) == 1
    calls.clear()
    b = FittedQEvaluation(**params)
    for _ in b.fit_iter(ds):
        pass
    assert len(calls) == 5
    X = ds.arrays().obs
    np.testing.assert_array_equal(a.q_function_.values(X), b.q_function_.values(X))


def test_training_positions_held_or_read_through_the_next_state_positions_give_the_same_fit(pt, monkeypatch):
    """Small structures hold the whole (trees, rows) training-position matrix; above
    ``TRAIN_POSITIONS_HELD`` bytes the leaf sums read the reused rows' leaves from the
    next-state positions instead (the memory of a 1M-row fit). Same rows, same order: the
    same Q-values bit for bit, and the same training positions on access."""
    import offline_adp.learn.frozen as frozen

    kw = {"gamma": 0.9, "n_iterations": 8, "regressor_params": {"n_estimators": 10}, "random_state": 1,
          "n_structures": 2}
    held = FittedQIteration(**kw).fit(pt)
    assert held.fit_state_.learner._train is not None
    monkeypatch.setattr(frozen, "TRAIN_POSITIONS_HELD", 0)
    read = FittedQIteration(**kw).fit(pt)
    assert read.fit_state_.learner._train is None and len(read.fit_state_.learner.reuse) > 0
    x = pt.arrays().obs
    np.testing.assert_array_equal(held.q_function_.values(x), read.q_function_.values(x))
    np.testing.assert_array_equal(held.fit_state_.learner.pos["train"], read.fit_state_.learner.pos["train"])


def test_the_compiled_builders_structure_is_held_as_its_lookups(pt, monkeypatch):
    """A frozen fit's Q over the compiled builder's trees holds the trees themselves
    (trees/loaded.py: no per-node int64 arrays, no second copy of the lookups or values):
    its predictions and its saved arrays are the ones of the per-node export it replaced."""
    import offline_adp.learn.frozen as frozen_mod
    from offline_adp.trees.ensemble import TreeEnsemble
    from offline_adp.trees.loaded import LoadedEnsemble

    params = {"gamma": 0.9, "n_iterations": 4, "mode": "frozen", "regressor_params": TREES}
    lazy = FittedQIteration(**params).fit(pt)
    ens = lazy.q_function_.models[0]
    assert isinstance(ens, LoadedEnsemble) and "left" not in ens.__dict__
    assert all(t.values.base is not None for t in ens._structure.trees)  # views of one value array
    monkeypatch.setattr(frozen_mod, "compact_ensemble", lambda trees: TreeEnsemble.from_trees(trees, consume=True))
    eager = FittedQIteration(**params).fit(pt)
    assert type(eager.q_function_.models[0]) is TreeEnsemble
    x = pt.arrays().obs
    np.testing.assert_array_equal(lazy.q_function_.values(x, 0), eager.q_function_.values(x, 0))
    a, b = ens.to_arrays("q/"), eager.q_function_.models[0].to_arrays("q/")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for k in ("left", "right", "feature", "threshold", "value", "roots"):
        np.testing.assert_array_equal(getattr(ens, k), getattr(eager.q_function_.models[0], k), err_msg=k)
