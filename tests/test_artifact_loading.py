"""Loading compact tree artifacts straight into their lookups (artifacts.tree_tables):
the loaded Q predicts bit for bit what the saved one did and what the per-node decoding
(checks.check_compact_tree_arrays) gives, its per-node arrays are the same when made,
re-saving writes the same arrays, and loading a policy imports none of the libraries
scoring does not need.

Ground truth: the in-memory Q-function before saving; the per-node decoding of the same
file (the reader of before); ``trees.ensemble.preorder_children`` for the children.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from sklearn.ensemble import ExtraTreesRegressor

import offline_adp.artifacts.checks as C
from offline_adp.artifacts import load_q, save_q
from offline_adp.artifacts.tree_tables import (
    LoadedEnsemble,
    load_compact_ensemble,
    preorder_children,
)
from offline_adp.qfunctions import QEncoder, TimeIndexedQ, TreeQ
from offline_adp.trees import TreeEnsemble
from offline_adp.trees import ensemble as E


@pytest.fixture(scope="module")
def forest():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(3000, 4))
    y = np.sin(X[:, 0]) + X[:, 1] * X[:, 2] + rng.normal(0, 0.1, 3000)
    return TreeEnsemble.from_sklearn(ExtraTreesRegressor(n_estimators=12, random_state=0).fit(X, y)), X


def _q(ens: TreeEnsemble) -> TreeQ:
    ens.n_features_in_ = 4  # type: ignore[attr-defined]
    return TreeQ([ens], QEncoder(1, np.zeros((1, 0)), per_action=False))


def _obs(X: np.ndarray, n: int = 5000) -> np.ndarray:
    return np.r_[np.random.default_rng(9).normal(size=(n, X.shape[1])) * 2, X[:500]]


def test_loaded_ensemble_predicts_bit_for_bit_and_makes_no_per_node_arrays(forest, tmp_path):
    ens, X = forest
    q = _q(ens)
    save_q(q, tmp_path / "m")
    q2, _ = load_q(tmp_path / "m")
    loaded = q2.models[0]
    assert isinstance(loaded, LoadedEnsemble)
    obs = _obs(X)
    np.testing.assert_array_equal(q2.values(obs), q.values(obs))
    assert not {"left", "right", "feature", "threshold"} & set(vars(loaded))  # scoring made none of them
    with np.load(tmp_path / "m" / "q.npz") as z:  # the reader of before: per-node arrays from the same members
        arrays = {k: z[k] for k in z.files}
    old = TreeEnsemble(**C.check_compact_tree_arrays(arrays, "q.m0.", "here", 4))
    np.testing.assert_array_equal(old.predict(obs), loaded.predict(obs))
    for k in ("left", "right", "feature", "threshold", "value", "roots"):  # made from the lookups on demand
        a, b = getattr(old, k), getattr(loaded, k)
        assert a.dtype == b.dtype, k
        np.testing.assert_array_equal(a, b, err_msg=k)


def test_resaving_a_loaded_q_writes_the_same_arrays(forest, tmp_path):
    ens, X = forest
    save_q(_q(ens), tmp_path / "a")
    save_q(load_q(tmp_path / "a")[0], tmp_path / "b")
    with zipfile.ZipFile(tmp_path / "a" / "q.npz") as za, zipfile.ZipFile(tmp_path / "b" / "q.npz") as zb:
        assert sorted((i.filename, i.CRC, i.file_size) for i in za.infolist()) == \
            sorted((i.filename, i.CRC, i.file_size) for i in zb.infolist())


def test_shared_structure_steps_load_lazily_and_predict_the_same(forest, tmp_path):
    ens, X = forest
    steps = [ens.with_values(ens.value * (t + 1) - t) for t in range(3)]  # one structure, three sets of leaf values
    for s in steps:
        s.n_features_in_ = 4  # type: ignore[attr-defined]
    q = TimeIndexedQ([TreeQ([s], QEncoder(1, np.zeros((1, 0)), per_action=False)) for s in steps])
    save_q(q, tmp_path / "m")
    q2, _ = load_q(tmp_path / "m")
    obs = _obs(X, 2000)
    for t in range(3):
        np.testing.assert_array_equal(q2.values(obs, t), q.values(obs, t))
    loaded = [m.models[0] for m in q2.qs]
    assert all(isinstance(e, LoadedEnsemble) for e in loaded)
    # one set for the structure
    assert loaded[0].compiled_trees() is loaded[1].compiled_trees() is loaded[2].compiled_trees()
    assert not {"left", "right"} & set(vars(loaded[0]))


def test_without_compiled_lookups_the_per_node_ensemble_predicts_the_same(forest, tmp_path, monkeypatch):
    from offline_adp.trees import jit

    ens, X = forest
    q = _q(ens)
    save_q(q, tmp_path / "m")
    monkeypatch.setattr(jit, "installed", lambda: False)
    q2, _ = load_q(tmp_path / "m")
    assert type(q2.models[0]) is TreeEnsemble
    obs = _obs(X, 2000)
    np.testing.assert_array_equal(q2.values(obs), q.values(obs))


def test_loaded_ensemble_pickles_and_copies_its_values(forest, tmp_path):
    ens, X = forest
    save_q(_q(ens), tmp_path / "m")
    loaded = load_q(tmp_path / "m")[0].models[0]
    back = pickle.loads(pickle.dumps(loaded))  # e.g. shipped to a Dask worker
    obs = _obs(X, 1000)
    np.testing.assert_array_equal(back.predict(obs), loaded.predict(obs))
    np.testing.assert_array_equal(back.left, loaded.left)
    other = loaded.with_values(loaded.value * 2)
    np.testing.assert_array_equal(other.predict(obs), 2 * loaded.predict(obs))
    np.testing.assert_array_equal(loaded.predict(obs), back.predict(obs))  # its own values untouched


@pytest.mark.parametrize("seed", range(5))
def test_children_match_the_reference_decoder(seed):
    """Random full binary trees in depth-first order (from random forests of random
    depth): the splits' right children are those trees.ensemble.preorder_children gives."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(300, 3))
    f = ExtraTreesRegressor(n_estimators=int(rng.integers(1, 8)), max_depth=int(rng.integers(1, 12)),
                            random_state=seed).fit(X, rng.normal(size=300))
    a = TreeEnsemble.from_sklearn(f).to_arrays()
    n = len(a["feature"]) + len(E.leaf_values_of(a, ""))
    is_leaf = np.unpackbits(a["leaf_bits"], count=n).astype(bool)
    splits, right = preorder_children(is_leaf)
    _, ref_right = E.preorder_children(is_leaf)
    np.testing.assert_array_equal(splits, np.flatnonzero(~is_leaf))
    np.testing.assert_array_equal(right, ref_right[splits])
    ens = load_compact_ensemble(a, "", "here", 3)
    np.testing.assert_array_equal(ens.predict(X), TreeEnsemble.from_sklearn(f).predict(X))


def test_loading_a_policy_imports_neither_scikit_learn_lightgbm_pandas_nor_numba(forest, tmp_path):
    """What scoring does not need is not imported: reading the versions a model was saved
    with comes from the installed metadata, the signature from info.json as JSON, and a few
    states are looked up by numpy descents (numba and its scipy imports: about 0.6 CPU-s)."""
    from offline_adp.artifacts import save_policy
    from offline_adp.policies import greedy_policy

    ens, _ = forest
    save_policy(greedy_policy(_q(ens)), tmp_path / "m")
    code = ("import sys, warnings; warnings.simplefilter('ignore'); import offline_adp; "
            f"p = offline_adp.load_policy({str(tmp_path / 'm')!r}); p.act_index(__import__('numpy').zeros((3, 4)), 0); "
            "print(sorted(m for m in ('sklearn', 'lightgbm', 'pandas', 'numba', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


# ----------------------------------------------------------------------------- writing
@pytest.mark.parametrize("compiled", [True, False])
def test_compact_arrays_are_to_arrays(forest, compiled, monkeypatch):
    """The writer's arrays are TreeEnsemble.to_arrays' (the format's definition), by the
    compiled walk and by the numpy passes, for a new structure and one written before."""
    from offline_adp.artifacts import tree_tables as TT

    ens, _ = forest
    monkeypatch.setattr(TT, "COMPILED_WALK_NODES", 1 if compiled else 1 << 62)
    TT._WRITTEN.clear()
    for e in (ens, ens.with_values(np.round(ens.value, 1)), E.constant_ensemble(1.5, 4)):
        for structure in (True, False):
            want, got = e.to_arrays("k.", structure=structure), TT.compact_arrays(e, "k.", structure=structure)
            assert sorted(want) == sorted(got)
            for k in want:
                assert want[k].dtype == got[k].dtype, k
                np.testing.assert_array_equal(want[k], got[k], err_msg=k)


def test_a_structure_that_is_not_trees_is_written_node_by_node(forest):
    from offline_adp.artifacts import tree_tables as TT

    ens, _ = forest
    left = ens.left.copy()
    left[ens.roots[1]] = ens.roots[0]  # the second tree's root points back into the first tree
    bad = TreeEnsemble(left, ens.right, ens.feature, ens.threshold, ens.value, ens.roots)
    assert TT.preorder_nodes(np.asarray(left), ens.right, ens.roots) is None
    assert "k.left" in TT.compact_arrays(bad, "k.")


def test_members_are_deflated_where_it_pays_and_read_back_alike(tmp_path):
    from offline_adp.artifacts.storage import savez

    rng = np.random.default_rng(0)
    arrays = {"a.codes": rng.integers(0, 4, 200_000).astype(np.uint8),
              "a.noise": rng.normal(size=50_000).astype(np.float32),
              "a.small": np.arange(3)}
    savez(tmp_path / "x.npz", arrays)
    savez(tmp_path / "y.npz", arrays, compress=False)
    with zipfile.ZipFile(tmp_path / "x.npz") as z:
        kinds = {i.filename: i.compress_type for i in z.infolist()}
    assert kinds["a.codes.npy"] == zipfile.ZIP_DEFLATED and kinds["a.noise.npy"] == zipfile.ZIP_STORED
    with zipfile.ZipFile(tmp_path / "y.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    for f in ("x.npz", "y.npz"):
        C.check_npz(tmp_path / f)
        with np.load(tmp_path / f, allow_pickle=False) as z:
            for k, v in arrays.items():
                assert z[k].dtype == v.dtype
                np.testing.assert_array_equal(z[k], v)


def test_a_constant_member_is_written_so_that_our_loader_reads_it(tmp_path):
    """A constant array deflates ~1000-fold, past the expansion the loader accepts from an
    untrusted file: it is stored instead (a fit on a constant command saved a model its own
    loader refused)."""
    from offline_adp.artifacts.storage import savez

    rng = np.random.default_rng(1)
    arrays = {"q.commands": np.full((2416, 1), 0.1), "q.zeros": np.zeros(1_000_000),
              "q.codes": rng.integers(0, 4, 200_000).astype(np.uint8)}
    savez(tmp_path / "c.npz", arrays)
    C.check_npz(tmp_path / "c.npz")  # raised "declares 19328 bytes from 236 compressed bytes" before
    with zipfile.ZipFile(tmp_path / "c.npz") as z:
        kinds = {i.filename: i.compress_type for i in z.infolist()}
    assert kinds["q.zeros.npy"] == zipfile.ZIP_STORED and kinds["q.codes.npy"] == zipfile.ZIP_DEFLATED
    with np.load(tmp_path / "c.npz", allow_pickle=False) as z:
        for k, v in arrays.items():
            np.testing.assert_array_equal(z[k], v)
    # many small constant members: each past the per-member limit, so each stored, and the file loads
    many = {f"m.k{i}": np.zeros(3000) for i in range(400)}
    savez(tmp_path / "m.npz", many)
    C.check_npz(tmp_path / "m.npz")
