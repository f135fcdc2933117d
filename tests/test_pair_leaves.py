"""One descent per state for every action (trees/pairs.py): the leaves and the greedy
policy's values are the ones of ``apply(all_pairs(phi))``, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.ensemble import ExtraTreesRegressor

from offline_adp.policies import GreedyPolicy, joint_tree_values
from offline_adp.qfunctions import QEncoder, RegressorQ, TreeQ
from offline_adp.trees.ensemble import TreeEnsemble
from offline_adp.trees.pairs import pair_leaves


def _ensemble(action_features: np.ndarray, d: int = 3, seed: int = 0, n: int = 600) -> tuple[TreeEnsemble, QEncoder]:
    rng = np.random.default_rng(seed)
    enc = QEncoder(len(action_features), action_features)
    X = rng.normal(size=(n, d))
    a = rng.integers(0, len(action_features), n)
    Z = enc.pairs(X, a)
    y = np.sin(Z[:, 0]) + Z[:, -1] * Z[:, 1] + 0.1 * rng.normal(size=n)
    forest = ExtraTreesRegressor(n_estimators=7, min_samples_leaf=1, random_state=seed).fit(Z, y)
    e = TreeEnsemble.from_sklearn(forest)
    return TreeEnsemble(e.left, e.right, e.feature, e.threshold, e.value, e.roots), enc  # no scikit-learn forest behind


@pytest.mark.parametrize("features", [np.linspace(-0.3, 0.3, 7)[:, None],  # steering values
                                      np.eye(4),  # one-hot
                                      np.array([[0.0, 1.0], [0.5, -1.0], [1.0, 0.0]])])  # two action dimensions
def test_pair_leaves_are_the_all_pairs_leaves(features):
    e, enc = _ensemble(features, seed=len(features))
    rng = np.random.default_rng(1)
    X = np.vstack([rng.normal(size=(300, 3)) * 2, np.zeros((1, 3))])
    X[5, 1] = np.nan  # compared with TreeEnsemble.apply, where NaN goes right
    X[6] = np.float32(e.threshold[e.feature == 0][0])  # on a threshold: left
    got = pair_leaves(e, enc.phi(X), enc.action_features)
    assert np.array_equal(got, e.apply(enc.all_pairs(enc.phi(X))))


@pytest.mark.parametrize("wrap", [RegressorQ, TreeQ])
def test_greedy_values_bit_identical(wrap):
    e, enc = _ensemble(np.linspace(-1, 1, 5)[:, None])
    q = wrap([e], enc)
    X = np.random.default_rng(2).normal(size=(257, 3))
    fast = joint_tree_values(q, X)
    assert fast is not None and np.array_equal(fast, q.values(X, 0))  # same bits, not just close
    assert np.array_equal(GreedyPolicy(q).actions(X), np.argmin(q.values(X, 0), axis=1))


def test_other_q_functions_are_left_to_their_values():
    e, enc = _ensemble(np.linspace(-1, 1, 3)[:, None])
    per_action = RegressorQ([e, e, e], QEncoder(3, np.zeros((3, 0)), per_action=True))
    assert joint_tree_values(per_action, np.zeros((2, 3))) is None
    assert pair_leaves(e, np.zeros((0, 3)), enc.action_features) is None  # no rows: apply's own path


def test_a_loaded_ensemble_takes_the_one_descent_path():
    """A policy read back from its artifact holds a LoadedEnsemble (lookups built, per-node
    arrays made only when asked for): its values come from the one-descent path, bit for
    bit, without making the per-node arrays."""
    from offline_adp.artifacts.tree_tables import LoadedEnsemble, load_compact_ensemble

    e, enc = _ensemble(np.linspace(-1, 1, 5)[:, None])
    loaded = load_compact_ensemble(e.to_arrays("q/"), "q/", "test")
    assert isinstance(loaded, LoadedEnsemble)
    q = RegressorQ([loaded], enc)
    X = np.random.default_rng(3).normal(size=(301, 3))
    fast = joint_tree_values(q, X)
    assert "left" not in loaded.__dict__  # the lookups' records, not the per-node arrays
    assert fast is not None and np.array_equal(fast, RegressorQ([e], enc).values(X, 0))
    assert np.array_equal(fast, q.values(X, 0))


def test_values_in_row_chunks_are_the_whole_set_values(monkeypatch):
    """TreeEnsemble.predict and the one-descent values run in row chunks of LOOKUP_CHUNK (no
    (rows, trees) matrix of a whole query set): the same numbers bit for bit as one chunk."""
    import offline_adp.trees.ensemble as ens_mod
    from offline_adp.trees.ensemble import ensemble_predict

    e, enc = _ensemble(np.linspace(-1, 1, 3)[:, None])
    q = RegressorQ([e], enc)
    X = np.random.default_rng(4).normal(size=(1001, 3))
    Z = enc.all_pairs(enc.phi(X))
    whole, fast = ensemble_predict(e.value, e.apply(Z)), joint_tree_values(q, X)
    monkeypatch.setattr(ens_mod, "LOOKUP_CHUNK", 97)  # chunks of 97 rows, 32 states of 3 pairs, a short last one
    assert np.array_equal(e.predict(Z), whole)
    chunked = joint_tree_values(q, X)
    assert chunked is not None and np.array_equal(chunked, fast)
    assert np.array_equal(chunked, whole.reshape(3, -1).T)
