"""The settle's pieces rebuilt for memory (docs/scaling.md, "Distributed evaluation") give
the numbers of the constructions they replaced: the policy's operator applied from the
next-state leaf positions (no query operator, no matrix), the sweeps written into the fit's buffer,
the leaf-averaging matrix from the fit's held leaf weights."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from offline_adp.algorithms import fqe_bootstrap as fb
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.policies import FunctionPolicy, UniformPolicy


def _synthetic(seed: int, n: int = 400, A: int = 3, m: int = 5, sizes: int = 60):
    """Tree-major next-state positions (trees, A n) over ``m`` trees of ``sizes`` leaves each,
    some queries without a training leaf (``L``), actions reaching the same leaf as another
    action of the same state (summed entries), and probabilities with zeros and ties."""
    rng = np.random.default_rng(seed)
    L = m * sizes
    pos = np.stack([rng.integers(t * sizes, (t + 1) * sizes, A * n) for t in range(m)]).astype(np.int32)
    pos[rng.random(pos.shape) < 0.1] = L
    same = rng.random(n) < 0.3  # action 1 reads action 0's leaves in every tree
    pos[:, n:2 * n][:, same] = pos[:, :n][:, same]
    pi = rng.random((n, A))
    pi[rng.random((n, A)) < 0.3] = 0.0
    pi[rng.random(n) < 0.2] = [1.0] + [0.0] * (A - 1)  # deterministic rows
    pi /= np.maximum(pi.sum(axis=1, keepdims=True), 1e-300)
    pi[:5, 0] = 5e-324  # products that underflow to 0: scipy drops them
    return pos, pi, L, n, A


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_policy_read_from_positions_is_the_product_it_replaced(seed):
    """The settle's ``P @ v`` from the next-state positions (no query operator, no ``P``) is
    the CSR product's bit for bit, on vectors of several scales."""
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    pos, pi, L, n, A = _synthetic(seed)
    learner = SimpleNamespace(leaf_ids=np.arange(L), pos={"next": pos})
    data, backup = SimpleNamespace(n=n, n_actions=A), SimpleNamespace(probabilities=lambda name, t: pi)
    old = fb.policy_operator(data, backup, fb.query_operators(learner, ("next",))["next"])
    new = PolicyRead(pos, pi, L)
    rng = np.random.default_rng(seed)
    for scale in (1.0, 1e-3, 1e6):  # the same entries summed in the same order: the same bits
        v = rng.normal(size=L) * scale
        np.testing.assert_array_equal(new @ v, old @ v)


@pytest.fixture(scope="module")
def fitted():
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 8, 8, seed=11, horizon=60)
    A = ds.n_actions
    pol = FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    return ds, FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=6,
                                 regressor_params={"n_estimators": 4}).fit(ds)


def test_the_settles_policy_operator_is_the_product_on_a_fit(fitted):
    _, fqe = fitted
    fit = fqe.fit_state_
    learner = fit.learner
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    old = fb.policy_operator(fit.data, fit.backup, fb.query_operators(learner, ("next",))["next"])
    new = PolicyRead(learner.pos["next"], np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64),
                     len(learner.leaf_ids))
    v = learner.leaf_values.copy()
    np.testing.assert_array_equal(new @ v, old @ v)


def test_leaf_operator_from_the_held_weight_sums_is_the_one_summed_again(fitted):
    _, fqe = fitted
    learner = fqe.fit_state_.learner
    assert learner.weight_sums is not None
    pos, L = learner.pos["train"], len(learner.leaf_ids)
    w = np.ones(pos.shape[1])
    old = fb._averaging_matrix(pos, w, learner.leaf_weight_sums(w), L)
    new = fb.leaf_operator(learner)
    for k in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(new, k), getattr(old, k), err_msg=k)


def test_sweeps_in_place_are_the_sweeps_on_copies(fitted):
    """``in_place``: the same values and sweep count, written into the given buffer; without
    it the starting values are never written (and no copy of them is made first)."""
    _, fqe = fitted
    fit = fqe.fit_state_
    d, learner = fit.data, fit.learner
    M = fb.leaf_operator(learner)
    P = fb.policy_operator(d, fit.backup, fb.query_operators(learner, ("next",))["next"])
    start = learner.leaf_values.copy()
    v0 = start.copy()
    v, sweeps = fb.averaged_fixed_point(d, M, P, v0, None, 10_000)
    np.testing.assert_array_equal(v0, start)  # not written
    buf = start.copy()
    w, sweeps2 = fb.averaged_fixed_point(d, M, P, buf, None, 10_000, in_place=True)
    assert w is buf and sweeps2 == sweeps > 1
    np.testing.assert_array_equal(buf, v)
    for cut in (1, 2):  # stopped early: the last completed sweep's values, both ways
        buf = start.copy()
        a, _ = fb.averaged_fixed_point(d, M, P, start, None, cut)
        fb.averaged_fixed_point(d, M, P, buf, None, cut, in_place=True)
        np.testing.assert_array_equal(buf, a)
    with pytest.raises(Exception, match="writable"):
        ro = start.copy()
        ro.flags.writeable = False
        fb.averaged_fixed_point(d, M, P, ro, None, 3, in_place=True)


def test_settle_solves_in_the_fits_buffer():
    """After ``settle`` the leaf values are still the view of the fit's buffer (its trailing 0
    kept: a query without a training leaf reads 0), Q reads them, and an uniform policy's
    settle gives the values of the solve on a copy."""
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 6, 6, seed=3, horizon=40)
    fqe = FittedQEvaluation(policy=UniformPolicy(ds.n_actions), gamma=0.9, mode="frozen", n_iterations=5,
                            regressor_params={"n_estimators": 3}).fit(ds)
    fit = fqe.fit_state_
    d, learner = fit.data, fit.learner
    buf = learner._values
    M = fb.leaf_operator(learner)
    P = fb.policy_operator(d, fit.backup, fqe._query_operators()["next"])
    expect, sweeps = fb.averaged_fixed_point(d, M, P, learner.leaf_values.copy(), None, 10_000)
    assert fqe.settle() == sweeps
    assert learner._values is buf and learner.leaf_values.base is buf and buf[-1] == 0.0
    np.testing.assert_array_equal(learner.leaf_values, expect)
    a = ds.arrays()
    np.testing.assert_array_equal(fqe.q_function_.values(d.start_obs, 0), learner.snapshot().values(d.start_obs, 0))
    assert np.isfinite(fqe.q_function_.values(a.obs, a.step)).all()


def test_compact_trees_hold_the_splits_thresholds_only():
    """A compiled tree's thresholds read back as given (a leaf's -2 made again), held for the
    splits only; a tree whose leaves carry other thresholds keeps them all."""
    from offline_adp.trees.compact import CompactTree

    left = np.array([1, 3, -1, -1, -1], np.int32)
    right = np.array([2, 4, -1, -1, -1], np.int32)
    feature = np.array([0, 1, -2, -2, -2], np.int32)
    thr = np.array([0.1 + 1e-12, -3.7, -2.0, -2.0, -2.0])
    t = CompactTree(left, right, feature, thr, np.arange(5.0))
    assert t._thresholds.shape == (2,)
    np.testing.assert_array_equal(t.threshold, thr)
    np.testing.assert_array_equal(t.thresholds.view(np.int64), thr.view(np.int64))
    odd = thr.copy()
    odd[3] = 0.0
    u = CompactTree(left, right, feature, odd, np.arange(5.0))
    assert u._thresholds.shape == (5,)
    np.testing.assert_array_equal(u.threshold, odd)
    x = np.array([[0.1, -3.8], [0.1, 0.0], [0.2, 0.0]], np.float32)
    np.testing.assert_array_equal(t.apply(x), u.apply(x))


def test_a_frozen_fits_saved_trees_are_the_same(tmp_path, fitted):
    """The structure exported from the compact trees (per-node arrays, saved file) has the
    thresholds the builder drew: per node, a split's as the lookup reads it."""
    _, fqe = fitted
    ens = fqe.q_function_.models[0]
    thr, left = np.asarray(ens.threshold), np.asarray(ens.left)
    assert (thr[left < 0] == -2.0).all()
    inner = left >= 0
    lookup = np.concatenate([t.packed[:, 3] for t in ens._structure.trees]).view(np.float32)
    assert (lookup[inner].astype(np.float64) <= thr[inner]).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_policy_read_is_the_matrix_product(seed):
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    pos, pi, L, n, A = _synthetic(seed)
    learner = SimpleNamespace(leaf_ids=np.arange(L), pos={"next": pos})
    data, backup = SimpleNamespace(n=n, n_actions=A), SimpleNamespace(probabilities=lambda name, t: pi)
    old = fb.policy_operator(data, backup, fb.query_operators(learner, ("next",))["next"])
    v = np.random.default_rng(seed).normal(size=L) * 1e3
    np.testing.assert_array_equal(PolicyRead(pos, pi, L) @ v, old @ v)


@pytest.mark.parametrize("held", [True, False])
@pytest.mark.parametrize("weighted", [False, True])
def test_leaf_average_is_the_matrix_product(monkeypatch, held, weighted):
    """Rows read through the next-state positions (most of them) or all held; with weights
    (zeros included: a leaf without weight)."""
    import offline_adp.learn.frozen as fr
    from offline_adp.algorithms.fqe_sweeps import LeafAverage
    from offline_adp.simulate import simulate

    monkeypatch.setattr(fr, "TRAIN_POSITIONS_HELD", 2**40 if held else 0)
    ds = simulate("path_tracking", 6, 6, seed=4, horizon=40)
    rng = np.random.default_rng(1)
    w = rng.poisson(1.0, len(ds)).astype(float) if weighted else None
    fqe = FittedQEvaluation(policy=UniformPolicy(ds.n_actions), gamma=0.9, mode="frozen", n_iterations=3,
                            regressor_params={"n_estimators": 3}).fit(ds, sample_weight=w)
    learner = fqe.fit_state_.learner
    assert (learner._train is not None) == held and (learner._src >= 0).any()
    y = rng.normal(size=len(ds)) * 10
    np.testing.assert_array_equal(LeafAverage(learner) @ y, fb.leaf_operator(learner) @ y)


def test_query_rows_are_the_operators_rows(fitted):
    _, fqe = fitted
    learner = fqe.fit_state_.learner
    ops = fb.query_operators(learner)
    for name in ("next", "start"):
        nq = learner.pos[name].shape[1]
        for lo, hi in ((0, nq // 2), (nq // 2, nq), (3, 4)):
            new, old = fb.query_rows(learner, name, lo, hi), ops[name][lo:hi]
            assert new.shape == old.shape
            for k in ("indptr", "indices", "data"):
                np.testing.assert_array_equal(getattr(new, k), getattr(old, k), err_msg=f"{name} {k}")


@pytest.mark.parametrize("radius", [None, 0.5])
def test_support_bounds_without_the_whole_query_operator_are_the_same(fitted, radius):
    """``support_bounds`` makes each action's query rows when it reads them: the same bounds
    as with the whole operators held."""
    _, fqe = fitted
    fit = fqe.fit_state_
    d = fit.data
    P, u, P0, u0 = fb.support_operators(d, fit.backup, fit.learner, fb.query_operators(fit.learner), 1e-9, radius)
    old = {"lower": fb.bounded_value(d, P, u, P0, u0, -2.0), "upper": fb.bounded_value(d, P, u, P0, u0, 3.0),
           "unsupported_next": float(u.mean()), "unsupported_start": float(u0.mean())}
    assert fqe.support_bounds(-2.0, 3.0, radius=radius) == old
    assert "_ops_cache" not in fqe.__dict__ or "next" not in fqe.__dict__["_ops_cache"][1]


def test_an_interrupted_settle_leaves_q_and_its_value_agreeing(monkeypatch):
    """The sweeps write into the fit's buffer: an exception mid-solve leaves moved leaf
    values, and the estimate must be read from those (never the value before the solve
    beside a Q of later values); the sweep count is unknown (None)."""
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 6, 6, seed=3, horizon=40)
    fqe = FittedQEvaluation(policy=UniformPolicy(ds.n_actions), gamma=0.9, mode="frozen", n_iterations=5,
                            regressor_params={"n_estimators": 3}).fit(ds)
    fit = fqe.fit_state_
    d = fit.data
    before = fit.learner.leaf_values.copy()
    orig, calls = type(d).targets, {"k": 0}

    def boom(self, x):
        calls["k"] += 1
        if calls["k"] == 4:
            raise MemoryError("simulated")
        return orig(self, x)

    monkeypatch.setattr(type(d), "targets", boom)
    with pytest.raises(MemoryError):
        fqe.settle()
    assert not np.array_equal(fit.learner.leaf_values, before)  # the solve had moved the values
    read = float((fit.backup.probabilities("start", 0) * fqe.q_function_.values(d.start_obs, 0)).sum(axis=1).mean())
    assert fqe.value_ == read and fqe.settled_iterations_ is None
