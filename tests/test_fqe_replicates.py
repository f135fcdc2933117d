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


def test_dense_row_space_falls_back_to_the_leaf_space_sweeps(small_pt, monkeypatch):
    """Where P_w M_w would be dense (leaves of many rows) the replicate runs the leaf-space
    sweeps, the numbers of fqe_bootstrap.fixed_point."""
    from offline_adp.algorithms import fqe_replicates

    monkeypatch.setattr(fqe_replicates, "MAX_TRIPLES_RATIO", 0.0)
    fqe = FittedQEvaluation(policy=UniformPolicy(small_pt.n_actions), gamma=0.9, mode="frozen", n_iterations=8,
                            regressor_params={"n_estimators": 3}).fit(small_pt)
    assert fqe._row_space()[0] is None
    w = np.random.default_rng(0).poisson(1.0, len(small_pt)).astype(float)
    w[fqe.fit_state_.data.start_rows[0]] = 1.0
    fit = fqe.fit_state_
    M, ops = reweighted_operators(fit.learner, w, base=fqe._query_operators())
    v, _ = fixed_point(fit.data, fit.backup, M, ops, fit.learner.leaf_values, None, 10_000, REPLICATE_RTOL)
    q0 = (ops["start"] @ v).reshape(fit.data.n_actions, -1).T
    v0 = (fit.backup.probabilities("start", 0) * q0).sum(axis=1)
    w0 = w[fit.data.start_rows]
    assert fqe.reweighted_value(w, rtol=REPLICATE_RTOL) == float(np.sum(w0 * v0) / np.sum(w0))
