"""Leaves of a loaded tree ensemble by numpy descents of its node records and by the
compiled lookups (trees.loaded): the same leaves, so the same numbers, whichever runs.

Ground truth: scikit-learn's own ``apply`` on the forest that was saved (float32 inputs),
and the in-memory ensemble before saving. Random forests of random depth and width on
inputs with repeated values and values on float32 boundaries (a hypothesis property,
bounded in CI), plus the rule that picks the path (trees.loaded._Structure.use_compiled).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sklearn.ensemble import ExtraTreesRegressor, RandomForestRegressor

from offline_adp.artifacts.tree_tables import load_compact_ensemble
from offline_adp.trees import TreeEnsemble, jit
from offline_adp.trees import loaded as L
from offline_adp.trees.ensemble import descend

pytestmark = pytest.mark.skipif(not jit.available(), reason="the compiled lookups need numba")


def _forest(seed: int, n_trees: int, depth: int | None, d: int, kind: str) -> tuple[object, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(400, d))
    X[:, 0] = np.round(X[:, 0], 1)  # repeated values: cuts between neighbours
    X[: 40, -1] = np.float32(0.1)  # a float32 value stored as float64, next to its double neighbours
    X[40: 80, -1] = 0.1
    y = np.sin(X[:, 0]) + X[:, -1] + rng.normal(0, 0.1, len(X))
    cls = ExtraTreesRegressor if kind == "extra" else RandomForestRegressor
    return cls(n_estimators=n_trees, max_depth=depth, random_state=seed).fit(X, y), X


def _loaded(forest: object) -> tuple[TreeEnsemble, L.LoadedEnsemble]:
    ens = TreeEnsemble.from_sklearn(forest)
    out = load_compact_ensemble(ens.to_arrays(), "", "test")
    assert isinstance(out, L.LoadedEnsemble) and out._structure.records is not None
    return ens, out


def _queries(X: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    Q = np.r_[X[:50], rng.normal(size=(200, X.shape[1])) * 3]
    Q[:20, -1] = np.nextafter(np.float32(0.1), np.float32(1))  # just above the float32 value
    Q[20:40, -1] = np.nextafter(0.1, 1.0)  # a double that rounds to float32(0.1)
    Q[40, 0], Q[41, 0], Q[42, -1] = np.inf, -np.inf, np.nan  # compared as the compiled lookups compare them
    return Q


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), n_trees=st.integers(1, 9), depth=st.one_of(st.none(), st.integers(1, 12)),
       d=st.integers(1, 4), kind=st.sampled_from(["extra", "forest"]))
def test_numpy_descents_reach_the_compiled_lookups_leaves(seed, n_trees, depth, d, kind):
    forest, X = _forest(seed, n_trees, depth, d, kind)
    ens, loaded = _loaded(forest)
    Q = _queries(X, np.random.default_rng(seed))
    numpy_leaves = loaded._structure.numpy_leaves(Q)
    assert loaded._structure._trees is None  # no compiled lookup was built for it
    compiled = TreeEnsemble.apply(loaded, Q)  # builds the per-tree lookups from the records
    np.testing.assert_array_equal(numpy_leaves, compiled)
    finite = np.isfinite(Q).all(axis=1)
    offs = np.r_[0, np.cumsum([e.tree_.node_count for e in forest.estimators_])[:-1]]
    truth = forest.apply(Q[finite].astype(np.float32)) + offs
    np.testing.assert_array_equal(numpy_leaves[finite], truth)
    # the per-node arrays' numpy descent (TreeEnsemble.apply without compiled lookups): float64 thresholds
    per_node = descend(ens.left, ens.right, ens.feature, ens.threshold, ens.roots,
                       Q.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(per_node, numpy_leaves)
    np.testing.assert_array_equal(loaded.predict(Q[finite]), ens.predict(Q[finite]))


def test_the_path_is_numpy_for_small_lookups_and_compiled_for_large_or_many(monkeypatch):
    forest, X = _forest(1, 5, None, 3, "extra")
    _, loaded = _loaded(forest)
    s = loaded._structure
    monkeypatch.setattr(jit, "warm", lambda: False)  # as in a fresh process that ran no kernel
    assert not s.use_compiled(10 * loaded.n_trees)
    assert s.use_compiled(L.NUMPY_PAIRS + 1)
    small = np.random.default_rng(0).normal(size=(10, 3))
    first = loaded.predict(small)
    assert s._trees is None  # the small lookup descended the records
    monkeypatch.setattr(s, "numpy_seconds", L.NUMPY_SECONDS + 1.0)  # many small lookups made
    assert s.use_compiled(10 * loaded.n_trees)
    np.testing.assert_array_equal(loaded.predict(small), first)
    assert s._trees is not None  # now built, and used from here on
    monkeypatch.setattr(s, "numpy_seconds", 0.0)
    assert s.use_compiled(1)


def test_a_process_with_kernels_running_uses_the_compiled_lookups(monkeypatch):
    forest, _ = _forest(2, 3, 6, 2, "extra")
    _, loaded = _loaded(forest)
    monkeypatch.setattr(jit, "warm", lambda: True)
    assert loaded._structure.use_compiled(1)


def test_per_node_arrays_from_the_records_are_the_lookups_export():
    forest, _ = _forest(3, 4, None, 3, "forest")
    ens, a = _loaded(forest)
    _, b = _loaded(forest)
    b._structure.trees  # noqa: B018 - built: the arrays then come from the lookups
    for k in ("left", "right", "feature", "threshold"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    for k in ("left", "right", "feature"):  # (the file holds a threshold's float32 where that is the same test)
        np.testing.assert_array_equal(getattr(a, k), getattr(ens, k))
    np.testing.assert_array_equal(a.leaf_mask(), b.leaf_mask())


def test_joint_greedy_actions_are_the_same_by_either_path(monkeypatch, tmp_path):
    """A loaded joint (x, a) Q: small batches descend with numpy (each pair of state and
    action), large ones through the compiled all-actions descent (trees.pairs): the greedy
    actions and values are those of the Q before saving."""
    from offline_adp.artifacts import load_q, save_q
    from offline_adp.policies import GreedyPolicy
    from offline_adp.qfunctions import QEncoder, TreeQ

    rng = np.random.default_rng(4)
    S = rng.normal(size=(600, 2))
    A = rng.integers(0, 3, 600)
    y = np.sin(S[:, 0]) * (A - 1) + S[:, 1]
    enc = QEncoder(3, np.arange(3.0).reshape(3, 1), per_action=False)
    forest = ExtraTreesRegressor(n_estimators=6, random_state=0).fit(np.c_[S, A.astype(float)], y)
    ens = TreeEnsemble.from_sklearn(forest)
    ens.n_features_in_ = 3  # type: ignore[attr-defined]
    q = TreeQ([ens], enc)
    save_q(q, tmp_path / "m")
    monkeypatch.setattr(jit, "warm", lambda: False)  # as in a fresh process that ran no kernel
    q2, _ = load_q(tmp_path / "m")
    obs = rng.normal(size=(40, 2)) * 2
    want = GreedyPolicy(q).actions(obs)
    np.testing.assert_array_equal(GreedyPolicy(q2).actions(obs), want)
    assert q2.models[0]._structure._trees is None
    monkeypatch.setattr(L, "NUMPY_PAIRS", 0)  # every lookup compiled from here
    np.testing.assert_array_equal(GreedyPolicy(q2).actions(obs), want)
    np.testing.assert_array_equal(q2.values(obs), q.values(obs))


@pytest.mark.parametrize("shift", [-1, 10**6])
def test_a_right_child_outside_its_tree_is_refused(monkeypatch, shift):
    """The records are read unchecked by the compiled lookups: a right child before its left
    child or past its tree's end (which flags that passed the depth-first check never give)
    is refused, naming the member, not looked up."""
    from offline_adp.artifacts import tree_tables as TT
    from offline_adp.errors import ArtifactError

    forest, _ = _forest(5, 3, 4, 2, "extra")
    arrays = TreeEnsemble.from_sklearn(forest).to_arrays()
    real = TT.preorder_children

    def broken(is_leaf):
        splits, right = real(is_leaf)
        right = right.copy()
        right[-1] = splits[-1] if shift < 0 else len(is_leaf) + shift  # the last tree's last split
        return splits, right

    monkeypatch.setattr(TT, "preorder_children", broken)
    with pytest.raises(ArtifactError, match="leaf_bits"):
        load_compact_ensemble(arrays, "", "test")


def test_a_pickled_loaded_ensemble_sends_its_records_once():
    """A loaded ensemble shipped to a worker after its compiled lookups were made (views of
    its records) is pickled without them: the structure is sent once, and the copy predicts
    the same numbers with lookups that are again views of its own records."""
    import pickle

    forest, X = _forest(6, 6, None, 3, "extra")
    _, loaded = _loaded(forest)
    trees = loaded._structure.trees
    assert all(np.shares_memory(t.packed, loaded._structure.records) for t in trees)
    blob = pickle.dumps(loaded)
    assert len(blob) < 1.5 * loaded._structure.records.nbytes + 2 * loaded.value.nbytes + 10_000
    back = pickle.loads(blob)
    assert back._structure._trees is None
    np.testing.assert_array_equal(back.predict(X), loaded.predict(X))
    assert all(np.shares_memory(t.packed, back._structure.records) for t in back._structure.trees)


def test_a_lazy_kernel_pickles_by_name_and_compiles_once():
    """A kernel compiled on first call is pickled by name (as numba's dispatchers of module
    functions are) and compiles to one dispatcher whatever the threads."""
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from offline_adp.trees import compact

    assert pickle.loads(pickle.dumps(compact._apply)) is compact._apply

    def double(x, out):
        for i in range(len(x)):
            out[i] = 2 * x[i]

    k = jit.LazyKernel(double, {"nogil": True})
    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(lambda _: (k.compiled(), k(np.arange(3.0), np.empty(3)))[0], range(8)))
    assert all(o is outs[0] for o in outs)
    x, out = np.arange(5.0), np.empty(5)
    k(x, out)
    np.testing.assert_array_equal(out, 2 * x)


def _chain(depth: int) -> dict[str, np.ndarray]:
    """Compact arrays of one tree that is a chain (split, leaf, split, leaf, ...) of ``depth``
    splits on feature 0 at thresholds 0, 1, ..., depth - 1: x goes left at the first
    threshold at or above it, so leaf k (value k) holds x in (k - 1, k]; the last leaf
    (value depth) holds x > depth - 1."""
    is_leaf = np.zeros(2 * depth + 1, bool)
    is_leaf[1::2] = True
    is_leaf[-1] = True
    # preorder: split k is node 2k, its left child (leaf k) node 2k + 1, its right child split k + 1
    return {"leaf_bits": np.packbits(is_leaf), "roots": np.array([0]), "feature": np.zeros(depth, np.uint8),
            "threshold": np.arange(depth, dtype=np.float64), "value": np.arange(depth + 1, dtype=np.float64)}


def test_a_structure_deeper_than_the_numpy_passes_goes_to_the_compiled_lookups(monkeypatch):
    """A file's chain of splits (a crafted one can be millions deep) costs a numpy pass a
    level: past NUMPY_PASSES levels the structure is handed to the compiled lookups, which
    reach the same leaves; shallower ones stay with numpy."""
    monkeypatch.setattr(jit, "warm", lambda: False)  # a fresh process: small lookups by numpy
    x = np.array([[-5.0], [0.0], [0.5], [3.0], [L.NUMPY_PASSES - 1.5], [L.NUMPY_PASSES + 7.0], [1e9]])
    truth = np.clip(np.ceil(x[:, 0]), 0, None)  # the leaf's value: the first threshold at or above x
    for depth, deep in ((L.NUMPY_PASSES - 1, False), (L.NUMPY_PASSES + 40, True)):
        loaded = load_compact_ensemble(_chain(depth), "", "chain")
        assert isinstance(loaded, L.LoadedEnsemble)
        np.testing.assert_array_equal(loaded.predict(x), np.minimum(truth, depth))
        assert loaded._structure.deep is deep
        assert (loaded._structure._trees is not None) is deep  # compiled lookups built only for the deep one
        np.testing.assert_array_equal(loaded.predict(x), np.minimum(truth, depth))  # and again, the same path


def test_threshold_edges_load_cleanly():
    """A double threshold below -float32 max loads without an overflow warning (its float32
    floor is -inf); a long double that is finite but beyond float64 is refused as non-finite."""
    import warnings

    from offline_adp.errors import ArtifactError

    a = _chain(3)
    a["threshold"] = np.array([-3.5e38, 0.0, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = load_compact_ensemble(a, "", "chain")
    np.testing.assert_array_equal(loaded.predict(np.array([[-np.inf], [-3.0e38], [0.5]])), [0.0, 1.0, 2.0])
    if np.dtype(np.longdouble).itemsize > 8 and np.finfo(np.longdouble).max > 1e400:
        a["threshold"] = np.array([np.longdouble("1e400"), 0.0, 1.0], dtype=np.longdouble)
        with pytest.raises(ArtifactError, match="non-finite split threshold"):
            load_compact_ensemble(a, "", "chain")


def test_pickling_leaves_the_pair_descents_copy_behind_and_keeps_sharing():
    """The pair descents' node records (trees.pairs, a copy of the structure) stay out of a
    pickle; ensembles of one structure still share their cache after unpickling."""
    import pickle

    from offline_adp.trees.pairs import pair_leaves

    forest, X = _forest(5, 4, None, 2, "extra")
    _, a = _loaded(forest)
    b = a.with_values(a.value * 2)
    phi, af = X[:, :1], np.array([[0.0], [1.0]])
    first = pair_leaves(a, phi, af)
    assert first is not None and "pair_packed" in a._same_structure
    a2, b2 = pickle.loads(pickle.dumps((a, b)))
    assert "pair_packed" not in a2._same_structure and a2._same_structure is b2._same_structure
    np.testing.assert_array_equal(pair_leaves(a2, phi, af), first)
    c = TreeEnsemble.from_sklearn(forest)
    assert pair_leaves(c, phi, af) is not None and "pair_packed" in c.__dict__
    assert "pair_packed" not in pickle.loads(pickle.dumps(c)).__dict__
