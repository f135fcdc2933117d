"""The settle's pieces rebuilt for memory (docs/scaling.md, "Distributed evaluation") give
the numbers of the constructions they replaced: the policy's operator applied from the
next-state leaf positions (no query operator, no matrix), the sweeps written into the fit's buffer,
the leaf-averaging matrix from the fit's held leaf weights.

Ground truth besides those constructions (which share their inputs and conventions with the
new code): the two products written plainly here with dense loops on small inputs
(:func:`_leaf_average_oracle`, :func:`_policy_read_oracle`), the training leaves the trees'
own lookup reaches, hand-computed sums, and the saved model read back from disk."""

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


def _policy_read_oracle(pos, pi, L, v):
    """``(P v)_i`` written plainly: the sum over actions ``b`` and trees ``t`` of
    ``pi[i, b] / m * v[pos[t, b n + i]]``; a position ``L`` (no training leaf) adds nothing,
    its 1/m not given to the other trees (the query operator keeps leaves below ``L`` only,
    and a query without a training leaf reads the fit's trailing 0)."""
    m, (n, A) = pos.shape[0], pi.shape
    out = np.zeros(n)
    for i in range(n):
        for b in range(A):
            for t in range(m):
                leaf = int(pos[t, b * n + i])
                assert 0 <= leaf <= L
                if leaf < L:
                    out[i] += pi[i, b] / m * v[leaf]
    return out


def _leaf_average_oracle(train, w, y, L):
    """Each leaf's weighted mean of ``y`` over the training rows whose tree-major position
    ``train[t, i]`` is that leaf (a position ``L``: none, ignored); a leaf without weight 0."""
    num, den = np.zeros(L), np.zeros(L)
    for t in range(train.shape[0]):
        for i in range(train.shape[1]):
            leaf = int(train[t, i])
            if leaf < L:
                num[leaf] += w[i] * y[i]
                den[leaf] += w[i]
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _close(got, want, scale):
    """The oracles sum in another order: equal to rounding (relative to the terms' scale near 0)."""
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * scale)


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
        _close(new @ v, _policy_read_oracle(pos, pi, L, v), scale)
        np.testing.assert_array_equal(new @ v, old @ v)


def _rule(x, t, A=7):
    """The fitted fixture's deterministic policy (path_tracking's 7 actions)."""
    return (np.abs(x[:, 0] * 7).astype(int)) % A


def _compact(learner, reached):
    """Tree-major compact positions (trees, rows) of the global leaves ``reached`` (rows,
    trees) the trees' own lookup gives: each leaf's index in ``leaf_ids``, ``L`` for a leaf
    without training rows."""
    index, L = {int(g): k for k, g in enumerate(learner.leaf_ids)}, len(learner.leaf_ids)
    return np.array([[index.get(int(g), L) for g in reached[:, t]] for t in range(reached.shape[1])])


@pytest.fixture(scope="module")
def fitted():
    from offline_adp.simulate import simulate

    ds = simulate("path_tracking", 8, 8, seed=11, horizon=60)
    A = ds.n_actions
    assert A == 7
    pol = FunctionPolicy(_rule, A)
    return ds, FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=6,
                                 regressor_params={"n_estimators": 4}).fit(ds)


def test_the_settles_policy_operator_is_the_product_on_a_fit(fitted):
    """Against the plain sum over the next-state leaves the trees' own lookup reaches (every
    action of each next state, action-major) with the policy's own rule (and the CSR product
    bit for bit)."""
    ds, fqe = fitted
    fit = fqe.fit_state_
    learner = fit.learner
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    a, A = ds.arrays(), ds.n_actions
    pos = _compact(learner, learner.ensemble.apply(learner.encoder.all_pairs(a.next_obs)))
    np.testing.assert_array_equal(learner.pos["next"], pos)
    pi = np.eye(A)[_rule(a.next_obs, 0)]
    np.testing.assert_array_equal(fit.backup.probabilities("next", 0), pi)
    old = fb.policy_operator(fit.data, fit.backup, fb.query_operators(learner, ("next",))["next"])
    new = PolicyRead(learner.pos["next"], np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64),
                     len(learner.leaf_ids))
    v = learner.leaf_values.copy()
    _close(new @ v, _policy_read_oracle(pos, pi, len(learner.leaf_ids), v), np.abs(v).max())
    np.testing.assert_array_equal(new @ v, old @ v)


def test_leaf_operator_from_the_held_weight_sums_is_the_one_summed_again(fitted):
    """The same CSR arrays as from the weight sums made again, and, densely, ``1 / (rows in
    the leaf)`` at each (leaf, row) the trees' own lookup pairs."""
    ds, fqe = fitted
    learner = fqe.fit_state_.learner
    assert learner.weight_sums is not None
    pos, L = learner.pos["train"], len(learner.leaf_ids)
    w = np.ones(pos.shape[1])
    old = fb._averaging_matrix(pos, w, learner.leaf_weight_sums(w), L)
    new = fb.leaf_operator(learner)
    a = ds.arrays()
    train = _compact(learner, learner.ensemble.apply(learner.encoder.pairs(a.obs, a.action)))
    count, dense = np.bincount(train.ravel(), minlength=L), np.zeros((L, train.shape[1]))
    for t in range(train.shape[0]):
        for i in range(train.shape[1]):
            dense[train[t, i], i] = 1.0 / count[train[t, i]]
    _close(new.toarray(), dense, 1.0)
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


def _float32_down(t):
    """Each double rounded down to a float32 (the largest float32 not above it), plainly."""
    t32 = np.asarray(t, dtype=np.float64).astype(np.float32)
    return np.where(t32.astype(np.float64) > t, np.nextafter(t32, np.float32(-np.inf)), t32)


def _preorder(ens, root):
    """A tree's nodes depth first, left child first, as ``(is_leaf, feature, threshold, value)``
    arrays (the same tree whatever its nodes' numbering)."""
    left, right = np.asarray(ens.left), np.asarray(ens.right)
    order, stack = [], [int(root)]
    while stack:
        k = stack.pop()
        order.append(k)
        if left[k] >= 0:
            stack += [int(right[k]), int(left[k])]
    order = np.array(order)
    value = np.asarray(ens.value).reshape(len(left), -1)[:, 0]
    leaf = left[order] < 0
    return leaf, np.asarray(ens.feature)[order], np.asarray(ens.threshold)[order], np.where(leaf, value[order], 0.0)


def test_a_frozen_fits_saved_trees_are_the_same(tmp_path, fitted):
    """The frozen FQE's Q written to disk by the library's save path (``save_q``, as a run
    writes its model/) and read back (``load_q``): the same trees node for node (the file
    holds each split's threshold rounded down to a float32, the rounding the compact lookup
    holds too, both computed plainly here; a leaf's value exact), and the same Q-values on
    fresh states, on states at the splits' thresholds and one float32 step either side."""
    from offline_adp.artifacts import load_q, save_q
    from offline_adp.simulate import simulate

    _, fqe = fitted
    q = fqe.q_function_
    save_q(q, tmp_path / "model")
    q2, _ = load_q(tmp_path / "model")
    assert q2 is not q and q2.models[0] is not q.models[0]
    ens, back = q.models[0], q2.models[0]
    thr, left, feature = np.asarray(ens.threshold), np.asarray(ens.left), np.asarray(ens.feature)
    assert (thr[left < 0] == -2.0).all()
    inner = left >= 0
    lookup = np.concatenate([t.packed[:, 3] for t in ens._structure.trees]).view(np.float32)
    np.testing.assert_array_equal(lookup[inner], _float32_down(thr[inner]))
    roots = np.asarray(ens.roots)
    np.testing.assert_array_equal(np.asarray(back.roots), roots)
    for r in roots:
        (leaf, f, t, v), (leaf2, f2, t2, v2) = _preorder(ens, r), _preorder(back, r)
        np.testing.assert_array_equal(leaf2, leaf)
        np.testing.assert_array_equal(f2[~leaf], f[~leaf])
        np.testing.assert_array_equal(t2[~leaf], _float32_down(t[~leaf]))
        np.testing.assert_array_equal(v2, v)
    obs = simulate("path_tracking", 3, 3, seed=99, horizon=30).arrays().obs
    splits = np.flatnonzero(inner & (feature < obs.shape[1]))[:400]  # splits on the state's own columns
    at = np.repeat(obs[:1], 3 * len(splits), axis=0)
    t32 = thr[splits].astype(np.float32)
    for k, t in enumerate((thr[splits], np.nextafter(t32, np.float32(np.inf)), np.nextafter(t32, np.float32(-np.inf)))):
        at[k * len(splits) + np.arange(len(splits)), feature[splits]] = t
    states = np.r_[obs, at]
    np.testing.assert_array_equal(q2.values(states, 0), q.values(states, 0))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("deterministic", [False, True])
def test_policy_read_is_the_matrix_product(seed, deterministic):
    """Against the plain sum (and the CSR product bit for bit): probabilities with zeros and
    ties, or one action a row; action 1 repeating action 0's leaves in about 30% of the rows
    (entries summed), positions without a training leaf."""
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    pos, pi, L, n, A = _synthetic(seed, n=150)
    if deterministic:
        pi = np.eye(A)[np.random.default_rng(seed).integers(0, A, n)]
    assert (pos == L).any() and (pos[:, :n] == pos[:, n:2 * n]).all(axis=0).any()
    learner = SimpleNamespace(leaf_ids=np.arange(L), pos={"next": pos})
    data, backup = SimpleNamespace(n=n, n_actions=A), SimpleNamespace(probabilities=lambda name, t: pi)
    old = fb.policy_operator(data, backup, fb.query_operators(learner, ("next",))["next"])
    v = np.random.default_rng(seed).normal(size=L) * 1e3
    got = PolicyRead(pos, pi, L) @ v
    _close(got, _policy_read_oracle(pos, pi, L, v), 1e3)
    np.testing.assert_array_equal(got, old @ v)


def test_policy_read_by_hand():
    """Two rows, two actions, two trees (leaves 0-1 and 2-3, ``L = 4``): row 0's actions reach
    the same leaves (each leaf's probabilities summed), row 1's action 1 no leaf in tree 0
    (it adds nothing; its 1/2 not moved to tree 1). Sums exact in binary."""
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    #                 a0:x0 a0:x1 a1:x0 a1:x1
    pos = np.array([[0, 1, 0, 4],
                    [2, 3, 2, 3]], np.int32)
    v = np.array([1.0, 10.0, 100.0, 1000.0])
    for pi, want in (([[0.25, 0.75], [0.5, 0.5]], [(1 + 100) / 2, 0.25 * (10 + 1000) + 0.25 * (0 + 1000)]),
                     ([[0.0, 1.0], [1.0, 0.0]], [(1 + 100) / 2, (10 + 1000) / 2]),
                     ([[1.0, 0.0], [0.0, 1.0]], [(1 + 100) / 2, 1000 / 2])):
        pi = np.array(pi)
        np.testing.assert_array_equal(_policy_read_oracle(pos, pi, 4, v), want)
        np.testing.assert_array_equal(PolicyRead(pos, pi, 4) @ v, want)


@pytest.mark.parametrize("n_jobs", [1, 2])
@pytest.mark.parametrize("weighted", [False, True])
def test_leaf_average_from_reused_positions_by_the_plain_mean(weighted, n_jobs):
    """Hand-made reused positions: about half the training rows read their leaves from a
    next-state column (``src``), the others from ``rest`` in order; weights with zeros, a leaf
    whose rows all weigh 0 (its average 0), leaves no row reaches."""
    from offline_adp.algorithms.fqe_sweeps import LeafAverage

    rng = np.random.default_rng(5)
    n, m, sizes, A = 300, 4, 30, 2
    L = m * sizes
    train = np.stack([rng.integers(t * sizes, (t + 1) * sizes - 2, n) for t in range(m)]).astype(np.int32)
    nxt = np.stack([rng.integers(t * sizes, (t + 1) * sizes, A * n) for t in range(m)]).astype(np.int32)
    nxt[rng.random(nxt.shape) < 0.1] = L
    reuse = rng.random(n) < 0.5
    cols = rng.choice(A * n, int(reuse.sum()), replace=False)
    nxt[:, cols] = train[:, reuse]
    src = np.full(n, -1, np.int64)
    src[reuse] = cols
    rest = np.ascontiguousarray(train[:, ~reuse])
    w = rng.poisson(1.0, n).astype(float) if weighted else None
    if weighted:
        w[train[0] == train[0, 0]] = 0.0
    ww = np.ones(n) if w is None else w
    wsum = np.zeros(L)
    for t in range(m):
        for i in range(n):
            wsum[train[t, i]] += ww[i]
    learner = SimpleNamespace(reused_positions=lambda: (nxt, src, rest, wsum), weights=w, n_jobs=n_jobs,
                              leaf_ids=np.arange(L))
    y = rng.normal(size=n) * 10
    got = LeafAverage(learner) @ y
    want = _leaf_average_oracle(train, ww, y, L)
    assert (want == 0).sum() >= m * 2 + weighted
    _close(got, want, 10.0)
    np.testing.assert_array_equal(got, fb._averaging_matrix(train, ww, wsum, L) @ y)


@pytest.mark.parametrize("held", [True, False])
@pytest.mark.parametrize("weighted", [False, True])
def test_leaf_average_is_the_matrix_product(monkeypatch, held, weighted):
    """Rows read through the next-state positions (most of them) or all held; with weights
    (zeros included; the builder leaves no leaf without weight here: the hand-made positions
    above have one). Against each leaf's plain weighted mean over the rows the trees' own
    lookup sends there, and the CSR product bit for bit."""
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
    a, L = ds.arrays(), len(learner.leaf_ids)
    # each training row's leaf in each tree from the trees themselves (every one a training leaf)
    train = _compact(learner, learner.ensemble.apply(learner.encoder.pairs(a.obs, a.action)))
    assert (train < L).all()
    np.testing.assert_array_equal(learner.pos["train"], train)
    y = rng.normal(size=len(ds)) * 10
    got = LeafAverage(learner) @ y
    want = _leaf_average_oracle(train, np.ones(len(ds)) if w is None else w, y, L)
    _close(got, want, 10.0)
    np.testing.assert_array_equal(got, fb.leaf_operator(learner) @ y)


def test_query_rows_are_the_operators_rows(fitted):
    _, fqe = fitted
    learner = fqe.fit_state_.learner
    ops = fb.query_operators(learner)
    for name in ("next", "start"):
        nq = learner.pos[name].shape[1]
        for lo, hi in ((0, nq // 2), (nq // 2, nq), (3, 4)):
            new, old = fb.query_rows(learner, name, lo, hi), ops[name][lo:hi]
            assert new.shape == old.shape
            pos, L = learner.pos[name], len(learner.leaf_ids)
            dense = np.zeros((hi - lo, L))  # 1/m for each tree whose leaf of the query has training rows
            for t in range(pos.shape[0]):
                for q in range(lo, hi):
                    if pos[t, q] < L:
                        dense[q - lo, pos[t, q]] += 1.0 / pos.shape[0]
            _close(new.toarray(), dense, 1.0)
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
