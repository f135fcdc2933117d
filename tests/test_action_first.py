"""Action-first trees (offline_adp.trees.action_first): per-action extra-trees held as one
joint forest, checked against per-action forests grown on each action's rows alone."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.trees import builder as compiled
from offline_adp.trees.action_first import action_groups, compose, grow_action_first, router
from offline_adp.trees.compact import CompactTree

pytestmark = pytest.mark.skipif(not compiled.available(), reason="the compiled builder needs numba")


def _leaf(value: float) -> CompactTree:
    return CompactTree(np.array([-1]), np.array([-1]), np.array([-2]), np.array([-2.0]), np.array([value]))


@pytest.mark.parametrize("keys", [np.array([[-4.0], [4.0]]), np.eye(4), np.array([[0.0, 1.0], [0.0, 2.0], [1.0, 1.0],
                                                                                    [2.5, -1.0], [3.0, 1.0]])])
def test_the_router_sends_every_action_row_to_its_own_subtree(keys):
    ks, group = action_groups(keys)
    assert len(ks) == len(keys)
    route = router(ks, first=3)
    tree, roots = compose(route, [_leaf(float(g)) for g in range(len(ks))], np.arange(len(ks), dtype=float),
                          np.ones(len(ks)))
    X = np.hstack([np.random.default_rng(0).normal(size=(len(keys), 3)), keys])
    leaves = tree.apply(X.astype(np.float32))
    np.testing.assert_array_equal(leaves, roots[group])  # each row reaches its own action's (one-leaf) tree
    np.testing.assert_array_equal(tree.values[leaves], group)
    assert tree.node_count == 2 * len(keys) - 1
    assert set(tree.feature[tree.children_left >= 0]) <= set(range(3, 3 + keys.shape[1]))  # routing reads f(a) only


@pytest.mark.parametrize("weighted", [False, True])
def test_each_action_reads_the_forest_grown_on_its_rows_alone(weighted):
    rng = np.random.default_rng(1)
    n, values = 400, np.array([-4.0, 0.5, 4.0])
    a = rng.integers(0, 3, n)
    x = rng.normal(size=(n, 2))
    y = np.sin(3 * x[:, 0]) + a * x[:, 1] + rng.normal(0, 0.1, n)
    w = rng.uniform(0.5, 2.0, n) if weighted else None
    X = np.hstack([x, values[a][:, None]])
    params = compiled.TreeParams(n_estimators=4, max_features=3, min_samples_split=2, min_samples_leaf=1,
                                 max_depth=2**31 - 1, bootstrap=False, n_bootstrap=n, random_state=7, n_jobs=1)
    forest = grow_action_first(X, y, w, params, range(4), n_action_columns=1)
    queries = rng.normal(size=(50, 2))
    for g in range(3):
        r = np.flatnonzero(a == g)
        alone = compiled.grow_trees(X[r], y[r], None if w is None else w[r], params, range(4))
        for (tree, train_leaf), own in zip(forest, alone, strict=True):
            own_tree = CompactTree.from_grown(own)
            # the training rows' leaves and every query's value are those of the action's own tree
            np.testing.assert_array_equal(train_leaf[r] - train_leaf[r].min() + own.train_leaf.min(), own.train_leaf)
            np.testing.assert_array_equal(tree.apply(X[r].astype(np.float32)), train_leaf[r])
            Xq = np.hstack([queries, np.full((50, 1), values[g])]).astype(np.float32)
            np.testing.assert_array_equal(tree.values[tree.apply(Xq)], own_tree.values[own_tree.apply(Xq)])
