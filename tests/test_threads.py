"""The default fit uses every core, and its numbers do not depend on how many.

The frozen-structure learner grows trees, looks leaves up and re-averages leaf values in
``n_jobs`` threads (the regressor's; -1, the extra_trees default: every core). Each tree's
work is independent and every sum is taken in one fixed order, so one thread and several
must give the same Q-values to the last bit.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from joblib import effective_n_jobs

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.simulate import simulate
from offline_adp.trees import averaging
from offline_adp.trees import builder as extra_trees
from offline_adp.trees.compact import CompactTree


@pytest.fixture(scope="module")
def ds():
    return simulate("car_on_hill", 12, 60, seed=5, horizon=50)


def _fit(ds, n_jobs, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return FittedQIteration(gamma=0.9, n_iterations=6, random_state=0, regressor_params={"n_jobs": n_jobs},
                                **kw).fit(ds)


@pytest.mark.parametrize("kw", [{}, {"structure_max_samples": 0.5, "n_structures": 3},
                                {"n_structures": 2, "screen_trees": 10, "screen_tol": 1e-12}])
def test_fqi_q_values_are_bit_identical_for_one_and_two_threads(ds, kw):
    obs = ds.arrays().obs
    one, two = _fit(ds, 1, **kw), _fit(ds, 2, **kw)
    assert one.mode_ == "frozen"
    q1, q2 = one.q_function_.values(obs), two.q_function_.values(obs)
    assert q1.tobytes() == q2.tobytes()
    assert np.array_equal(one.history_["start_value"].to_numpy(), two.history_["start_value"].to_numpy())


def test_leaf_sums_is_bincount_per_tree_for_any_thread_count():
    rng = np.random.default_rng(0)
    m, n = 7, 5000
    per = rng.integers(1, 300, m)
    bounds = np.r_[0, np.cumsum(per)]
    pos = np.stack([rng.integers(bounds[t], bounds[t + 1], n) for t in range(m)]).astype(np.int32)
    v = rng.normal(size=n) * 10.0 ** rng.integers(-8, 8, n)  # magnitudes that make the order matter
    ref = np.concatenate([np.bincount(pos[t] - bounds[t], weights=v, minlength=per[t]) for t in range(m)])
    for jobs in (1, 2, 3):
        assert averaging.leaf_sums(pos, bounds, v, jobs).tobytes() == ref.tobytes()


def test_tree_mean_is_a_running_sum_over_trees_for_any_thread_count():
    rng = np.random.default_rng(1)
    m, nq = 9, 70_000
    values = rng.normal(size=400) * 10.0 ** rng.integers(-8, 8, 400)
    pos = rng.integers(0, len(values), (m, nq)).astype(np.int32)
    acc = np.zeros(nq)
    for t in range(m):  # tree order, as the learner has always summed
        acc += values[pos[t]]
    ref = acc / m
    for jobs in (1, 2, 3):
        assert averaging.tree_mean(values, pos, jobs).tobytes() == ref.tobytes()


def test_thread_count_follows_scikit_learn():
    assert averaging.resolve_n_jobs(None) == 1
    assert averaging.resolve_n_jobs(1) == 1
    assert averaging.resolve_n_jobs(-1) == effective_n_jobs(-1) >= 1


@pytest.mark.skipif(not extra_trees.available(), reason="numba is not installed")
def test_default_regressor_uses_every_core(ds):
    from offline_adp.regressors import make_regressor

    assert averaging.resolve_n_jobs(make_regressor("extra_trees").get_params()["n_jobs"]) == effective_n_jobs(-1)


@pytest.mark.skipif(not extra_trees.available(), reason="numba is not installed")
def test_compact_tree_reaches_scikit_learns_leaves():
    """The frozen learner's trees (CompactTree: float32-floored thresholds, 32 bytes a node)
    reach the leaf scikit-learn's ``Tree.apply`` reaches on the same node records, inputs
    equal to a threshold included, and export the same arrays."""
    from offline_adp.trees.sklearn import sklearn_tree_from_records, tree_arrays

    rng = np.random.default_rng(2)
    n, d = 3000, 3
    X = rng.normal(size=(n, d))
    X[:, 2] = np.round(X[:, 2], 1)  # repeated values: cuts between close float32 values
    y = X[:, 0] - X[:, 2] + 0.1 * rng.normal(size=n)
    params = extra_trees.TreeParams(3, d, 2, 1, 2**31 - 1, False, n, 0, 1)
    pairs = extra_trees.grow_trees(X, y, None, params, finish=lambda t: (
        CompactTree.from_grown(t), sklearn_tree_from_records(t.nodes.copy(), t.value.copy(), d)))
    for compact, tree in pairs:
        inner = tree.feature >= 0
        at = np.tile(np.float32(X[:50]), (2, 1))  # rows that sit exactly on cuts, and just above
        at[:50, 0] = np.float32(tree.threshold[inner][:50].mean())
        Q = np.ascontiguousarray(np.r_[np.float32(X), np.float32(rng.normal(size=(2000, d))) * 3, at], dtype=np.float32)
        on = np.repeat(Q[:1], int(inner.sum()), axis=0)
        on[np.arange(len(on)), tree.feature[inner]] = np.float32(tree.threshold[inner])  # may round above the cut
        Q = np.ascontiguousarray(np.r_[Q, on])
        assert np.array_equal(compact.apply(Q), tree.apply(Q))
        ours, theirs = tree_arrays([compact]), tree_arrays([tree])
        assert all(np.array_equal(ours[k], theirs[k]) for k in theirs)


@pytest.mark.parametrize("n_jobs", [1, 3])
def test_leaf_sums_continued_block_after_block_are_the_sums_over_all_rows(n_jobs):
    """``carry``: sums taken over rows [0, k) then continued over [k, n) are the sums over
    all n rows bit for bit (rows added in order), for any split and thread count; the same
    with numpy's unbuffered np.add.at as the reference."""
    from offline_adp.trees.averaging import leaf_sums

    rng = np.random.default_rng(7)
    m, n, leaves = 5, 2_000, 37
    bounds = np.arange(m + 1, dtype=np.int64) * leaves
    pos = (rng.integers(0, leaves, (m, n)) + bounds[:-1, None]).astype(np.int32)
    v = rng.normal(size=n) * 10.0 ** rng.integers(-6, 6, n)  # magnitudes that make the order matter
    whole = leaf_sums(pos, bounds, v, n_jobs)
    for k in (1, 700, 1999):
        first = leaf_sums(pos[:, :k], bounds, v[:k], n_jobs)
        np.testing.assert_array_equal(leaf_sums(pos[:, k:], bounds, v[k:], n_jobs, carry=first), whole)
    ref = np.zeros(int(bounds[-1]))
    for t in range(m):
        np.add.at(ref, pos[t], v)
    np.testing.assert_array_equal(whole, ref)
