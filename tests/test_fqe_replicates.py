"""Bootstrap replicates solved over the training rows (algorithms/fqe_replicates.py) reach
the fixed point of the leaf-space iteration (fqe_bootstrap.fixed_point) they replace,
where the clamp at c^- binds, episodes terminate and queries lose every tree's leaf."""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.algorithms.fqe_bootstrap import fixed_point, reweighted_operators
from offline_adp.evaluation.fqe_interval import REPLICATE_RTOL
from offline_adp.policies import FunctionPolicy, UniformPolicy


def _leaf_space_value(fqe: FittedQEvaluation, w: np.ndarray, tol: float) -> float:
    """The replicate as it was computed before: the leaf-space sweeps to ``tol``."""
    fit = fqe.fit_state_
    d, learner, backup = fit.data, fit.learner, fit.backup
    M, ops = reweighted_operators(learner, w, base=fqe._query_operators())
    v, _ = fixed_point(d, backup, M, ops, learner.leaf_values, tol, 100_000)
    q0 = (ops["start"] @ v).reshape(d.n_actions, -1).T
    v0 = (backup.probabilities("start", 0) * q0).sum(axis=1)
    w0 = w[d.start_rows]
    return float(np.sum(w0 * v0) / np.sum(w0))


@pytest.mark.parametrize("policy", ["deterministic", "uniform"])
def test_row_space_replicates_reach_the_leaf_space_fixed_point(small_pt, policy):
    A = small_pt.n_actions
    pol = UniformPolicy(A) if policy == "uniform" else \
        FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    cost = small_pt.arrays().cost
    cap = float(np.quantile(cost, 0.9))  # c^- below the largest costs: the clamp binds
    fqe = FittedQEvaluation(policy=pol, gamma=0.95, mode="frozen", n_iterations=30, infeasible_cost=cap,
                            regressor_params={"n_estimators": 6}).fit(small_pt)
    fqe.settle()
    scale = 1 + np.max(np.abs(fqe.fit_state_.learner.leaf_values))
    rng = np.random.default_rng(5)
    n = len(small_pt)
    for lam in (0.3, 1.0):  # 0.3: most leaves empty, queries whose every tree lost its leaf
        w = rng.poisson(lam, n).astype(float)
        w[fqe.fit_state_.data.start_rows[0]] = 1.0  # a start row with weight
        exact = _leaf_space_value(fqe, w, tol=1e-13)
        assert fqe.reweighted_value(w, tol=1e-11) == pytest.approx(exact, rel=1e-9, abs=1e-10)
        assert abs(fqe.reweighted_value(w, rtol=REPLICATE_RTOL) - exact) <= REPLICATE_RTOL * scale
    assert fqe.reweighted_value(np.ones(n), tol=1e-11) == pytest.approx(fqe.value_, rel=1e-6)


def test_row_space_structure_is_built_once_and_follows_settle(small_pt):
    fqe = FittedQEvaluation(policy=UniformPolicy(small_pt.n_actions), gamma=0.9, mode="frozen", n_iterations=8,
                            regressor_params={"n_estimators": 3}).fit(small_pt)
    w = np.ones(len(small_pt))
    fqe.reweighted_value(w)
    rs, ve = fqe._row_space()
    assert fqe._row_space()[0] is rs
    fqe.settle()  # new leaf values: the start point follows them, the structure stays
    rs2, ve2 = fqe._row_space()
    assert rs2 is rs and ve2 is not ve
    np.testing.assert_array_equal(ve2, fqe.fit_state_.learner.leaf_values[rs.q_leaf])


@pytest.mark.parametrize("policy", ["deterministic", "uniform"])
@pytest.mark.parametrize("lam", [0.3, 1.0])
def test_dense_row_space_falls_back_to_the_leaf_space_sweeps(small_pt, monkeypatch, policy, lam):
    """Where P_w M_w would be dense (leaves of many rows) the replicate runs the leaf-space
    sweeps with M_w and P_w applied from the leaf positions (fqe_sweeps), the numbers of
    fqe_bootstrap.fixed_point on reweighted_operators' matrices bit for bit: a policy that
    reads one action or all, most leaves kept or most dropped (lam 0.3: queries whose every
    tree lost its leaf keep their entries)."""
    from offline_adp.algorithms import fqe_replicates

    monkeypatch.setattr(fqe_replicates, "MAX_TRIPLES_RATIO", 0.0)
    A = small_pt.n_actions
    pol = UniformPolicy(A) if policy == "uniform" else \
        FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    fqe = FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=8,
                            regressor_params={"n_estimators": 3}).fit(small_pt)
    assert fqe._row_space()[0] is None
    w = np.random.default_rng(0).poisson(lam, len(small_pt)).astype(float)
    w[fqe.fit_state_.data.start_rows[0]] = 1.0
    fit = fqe.fit_state_
    M, ops = reweighted_operators(fit.learner, w, base=fqe._query_operators())
    v, _ = fixed_point(fit.data, fit.backup, M, ops, fit.learner.leaf_values, None, 10_000, REPLICATE_RTOL)
    q0 = (ops["start"] @ v).reshape(fit.data.n_actions, -1).T
    v0 = (fit.backup.probabilities("start", 0) * q0).sum(axis=1)
    w0 = w[fit.data.start_rows]
    assert fqe.reweighted_value(w, rtol=REPLICATE_RTOL) == float(np.sum(w0 * v0) / np.sum(w0))


@pytest.mark.parametrize("ratio", [0.0, 1.0, 2.0, 4.0, 1e9])
def test_row_space_sparse_decides_as_the_row_space_build(small_pt, monkeypatch, ratio):
    """The decision read from the positions alone (the next-state operator not made) is the
    one row_space makes from that operator, at every threshold."""
    from offline_adp.algorithms import fqe_replicates
    from offline_adp.algorithms.fqe_bootstrap import query_operators

    monkeypatch.setattr(fqe_replicates, "MAX_TRIPLES_RATIO", ratio)
    A = small_pt.n_actions
    pol = FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    fqe = FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=5,
                            regressor_params={"n_estimators": 4, "min_samples_leaf": 3}).fit(small_pt)
    learner = fqe.fit_state_.learner
    pi = np.asarray(fqe.fit_state_.backup.probabilities("next", 0), dtype=np.float64)
    built = fqe_replicates.row_space(learner, query_operators(learner, ("next",))["next"], pi)
    assert fqe_replicates.row_space_sparse(learner, pi) == (built is not None)


def _row_space_numpy(learner, op_next, pi_next):
    """The row space as it was built before 2026-11-28 (int64 numpy temporaries, np.unique)."""
    from scipy import sparse

    n = pi_next.shape[0]
    i_, a_ = np.nonzero(pi_next > 0)
    sub = op_next[a_ * n + i_].tocsr()
    pos = learner.pos["train"]
    L = len(learner.leaf_ids)
    M = sparse.csr_matrix((np.ones(pos.size), (pos.reshape(-1), np.tile(np.arange(n), pos.shape[0]))), shape=(L, n))
    M.sort_indices()
    m_ptr, m_idx = M.indptr.astype(np.int64), M.indices.astype(np.int64)
    counts = np.diff(m_ptr)[sub.indices]
    q_of_entry = np.repeat(np.arange(sub.shape[0]), np.diff(sub.indptr))
    starts = np.repeat(m_ptr[sub.indices], counts)
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cols = m_idx[starts + within]
    rows = np.repeat(i_[q_of_entry], counts)
    keys, slots = np.unique(rows * np.int64(n) + cols, return_inverse=True)
    k_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(keys // n, minlength=n), out=k_ptr[1:])
    t_ptr = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=t_ptr[1:])
    return {"q_ptr": sub.indptr, "q_leaf": sub.indices, "q_dat": sub.data, "q_pi": pi_next[i_, a_], "q_row": i_,
            "m_ptr": m_ptr, "m_idx": m_idx, "k_ptr": k_ptr, "k_idx": keys % n, "t_ptr": t_ptr, "t_col": cols,
            "slots": slots.reshape(-1), "order": np.arange(n - 1, -1, -1)}


@pytest.mark.parametrize("policy", ["deterministic", "uniform"])
def test_row_space_equals_the_numpy_construction_in_int32(small_pt, policy):
    """The compiled construction (no (triples,) int64 temporaries, int32 indices) holds the
    same numbers as the numpy one it replaced, so the replicates are the same bit for bit."""
    from offline_adp.algorithms.fqe_replicates import row_space

    A = small_pt.n_actions
    pol = UniformPolicy(A) if policy == "uniform" else \
        FunctionPolicy(lambda x, t: (np.abs(x[:, 0] * 7).astype(int)) % A, A)
    fqe = FittedQEvaluation(policy=pol, gamma=0.95, mode="frozen", n_iterations=10,
                            regressor_params={"n_estimators": 5, "min_samples_leaf": 3}).fit(small_pt)
    fit = fqe.fit_state_
    pi = np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64)
    op = fqe._query_operators()["next"]
    rs, ref = row_space(fit.learner, op, pi), _row_space_numpy(fit.learner, op, pi)
    for k, v in ref.items():
        got = getattr(rs, k)
        assert got.dtype == (np.float64 if k in ("q_dat", "q_pi") else np.int32), k
        np.testing.assert_array_equal(got, v, err_msg=k)


def test_replicates_and_support_bounds_without_the_trees(small_pt):
    """drop_trees frees the trees; the replicates and the support bounds read leaf positions only."""
    pol = UniformPolicy(small_pt.n_actions)
    fqe = FittedQEvaluation(policy=pol, gamma=0.9, mode="frozen", n_iterations=8,
                            regressor_params={"n_estimators": 4}).fit(small_pt)
    fqe.settle()
    w = np.random.default_rng(1).poisson(1.0, len(small_pt)).astype(float)
    before = (fqe.reweighted_value(w), fqe.support_bounds(-1.0, 3.0))
    fqe.drop_replicate_cache()
    fqe.drop_trees()
    assert fqe.q_function_ is None and fqe.fit_state_.learner.ensemble is None
    assert (fqe.reweighted_value(w), fqe.support_bounds(-1.0, 3.0)) == before


def _leaf_operator_csc(pos, w, wsum, L):
    """The averaging matrix as it was built before 2026-11-28: a (n, trees) CSC, then CSR."""
    from scipy import sparse

    m, n = pos.shape
    idx = np.ascontiguousarray(pos.T)
    data = wsum[idx]
    np.divide(w[:, None], data, out=data, where=data > 0)
    return sparse.csc_matrix((data.reshape(-1), idx.reshape(-1), np.arange(0, n * m + 1, m, dtype=np.int64)),
                             shape=(L, n)).tocsr()


def test_settle_and_its_operators_are_the_ones_built_before(small_pt, monkeypatch):
    """The averaging matrix built in place holds the entries the CSC conversion gave, in the
    same order, and the sweeps with the change taken a chunk at a time stop where the whole
    difference vector stopped them: settle gives the same leaf values bit for bit."""
    import offline_adp.algorithms.fqe_bootstrap as fb

    fqe = FittedQEvaluation(policy=UniformPolicy(small_pt.n_actions), gamma=0.9, mode="frozen", n_iterations=6,
                            regressor_params={"n_estimators": 4}).fit(small_pt)
    fit = fqe.fit_state_
    d, learner = fit.data, fit.learner
    w = np.random.default_rng(3).poisson(1.0, d.n).astype(float)
    wsum = learner.leaf_weight_sums(w)
    pos, L = learner.pos["train"], len(learner.leaf_ids)
    new, old = fb._averaging_matrix(pos, w, wsum, L), _leaf_operator_csc(pos, w, wsum, L)
    for k in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(new, k), getattr(old, k), err_msg=k)
    M, P, v0 = fb.leaf_operator(learner), fb.policy_operator(d, fit.backup, fqe._query_operators()["next"]), \
        learner.leaf_values.copy()
    v, sweeps, diff = v0.copy(), 0, np.empty_like(v0)  # the loop as it was: one difference vector
    while True:
        sweeps += 1
        v_new = M @ d.targets(P @ v)
        np.subtract(v_new, v, out=diff)
        change, v = max(float(diff.max()), -float(diff.min())), v_new
        if change * d.gamma / (1 - d.gamma) <= 1e-7 * (d.cost_unit + max(float(v.max()), -float(v.min()))):
            break
    monkeypatch.setattr(fb, "_CHANGE_CHUNK", 700)  # several chunks, a short last one
    assert len(v0) > 2100 and len(v0) % 700
    assert fqe.settle() == sweeps
    np.testing.assert_array_equal(learner.leaf_values, v)


@pytest.mark.parametrize("lam", [0.05, 0.3, 1.0])
def test_policy_read_with_kept_leaves_is_the_reweighted_product(small_pt, lam):
    """P_w v applied from the positions (PolicyRead(keep=...)) equals the CSR product of the
    reweighted query operator bit for bit, for a stochastic policy reading several actions
    (some with probability 0): a leaf one action's query drops and another's falls back to
    keeps the product's order."""
    from offline_adp.algorithms.fqe_bootstrap import policy_operator, query_operators, reweight_query_operator
    from offline_adp.algorithms.fqe_sweeps import PolicyRead

    A = small_pt.n_actions

    class Mixed(UniformPolicy):
        def probabilities(self, x, t=0):
            p = np.abs(np.sin(np.arange(A)[None, :] + 3.0 * x[:, :1]))
            p[np.arange(len(x)), (np.abs(x[:, 0]) * 5).astype(int) % A] = 0.0
            return p / p.sum(axis=1, keepdims=True)

    fqe = FittedQEvaluation(policy=Mixed(A), gamma=0.9, mode="frozen", n_iterations=5,
                            regressor_params={"n_estimators": 7}).fit(small_pt)
    fit = fqe.fit_state_
    learner = fit.learner
    rng = np.random.default_rng(3)
    W = learner.leaf_weight_sums(rng.poisson(lam, fit.data.n).astype(float))
    op = reweight_query_operator(query_operators(learner, ("next",))["next"], W > 0)
    v = rng.normal(size=len(learner.leaf_ids))
    pi = np.asarray(fit.backup.probabilities("next", 0), dtype=np.float64)
    assert ((pi > 0).sum(axis=1) > 1).all() and (pi == 0).any()
    want = policy_operator(fit.data, fit.backup, op) @ v
    got = PolicyRead(learner.pos["next"], pi, len(learner.leaf_ids), keep=W > 0) @ v
    np.testing.assert_array_equal(got, want)
