"""The refit learner reads Q on the training pairs and start states from its next-state
predictions where the input is the same: checked against direct predictions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.learn import LearnSpec, RefitLearner
from offline_adp.learn.refit import _row_sources
from offline_adp.qfunctions import QEncoder
from offline_adp.regressors import make_regressor


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(0, 30), st.integers(0, 30))
def test_row_sources_point_at_a_bitwise_equal_row(seed, n_base, n_a, n_b):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 4, (n_base, 2)).astype(float)
    pool = np.r_[base, rng.integers(0, 6, (10, 2)).astype(float), [[-0.0, 0.0]]]  # -0.0: bitwise different
    a, b = pool[rng.integers(0, len(pool), n_a)], pool[rng.integers(0, len(pool), n_b)]
    (ia, ib), extra = _row_sources(base, [a, b])
    table = np.r_[base, extra]
    for rows, idx in ((a, ia), (b, ib)):
        assert table[idx].tobytes() == rows.tobytes()
    # extra: distinct rows, none bitwise equal to a base row
    keys = {r.tobytes() for r in base}
    assert len({r.tobytes() for r in extra}) == len(extra)
    assert not any(r.tobytes() in keys for r in extra)


@pytest.mark.parametrize("encoding", ["joint", "per_action"])
def test_derived_queries_equal_direct_predictions_on_shuffled_rows(encoding):
    """Rows in random order (a next state is rarely the following row's state), plus
    episode starts that are no next state: every value equals a direct prediction."""
    rng = np.random.default_rng(3)
    n_ep, T = 40, 6
    x = rng.normal(size=(n_ep, T + 1, 2)).round(2)
    phi, phi_next = x[:, :-1].reshape(-1, 2), x[:, 1:].reshape(-1, 2)
    actions = rng.integers(0, 3, len(phi))
    order = rng.permutation(len(phi))
    phi, phi_next, actions = phi[order], phi_next[order], actions[order]
    start = x[:, 0]
    enc = QEncoder(3, np.array([[-1.0], [0.0], [1.0]]), per_action=encoding == "per_action")
    reg = make_regressor("extra_trees", n_estimators=5, n_jobs=1)
    lr = RefitLearner(LearnSpec(reg, enc, phi, actions, {"next": (phi_next, None), "start": (start, None)}))
    assert len(lr.queries["extra"][0]) == n_ep  # only the episode starts are predicted besides the next states
    y = rng.normal(size=len(phi))
    lr.fit(y, 1)
    direct_all = lr.q.values_phi(phi)
    np.testing.assert_array_equal(lr.predict("train"), direct_all[np.arange(len(phi)), actions])
    np.testing.assert_array_equal(lr.predict("start"), lr.q.values_phi(start))
    np.testing.assert_array_equal(lr.predict("next"), lr.q.values_phi(phi_next))


def test_history_is_measured_on_the_training_pairs(small_pt):
    """sup_dq in the history is sup |Q_k - Q_{k-1}| over the training pairs and every
    next-state pair a target reads (the contraction's sup norm, fqi_monitor), max_abs_q
    max |Q_k| on the training pairs (computed here independently from each iteration's
    saved Q)."""
    qs = []
    f = FittedQIteration(gamma=0.9, mode="refit", n_iterations=4, regressor_params={"n_estimators": 5, "n_jobs": 1})
    for _ in f.fit_iter(small_pt):
        qs.append(f.q_function_)
    a = small_pt.arrays()
    boot = ~a.terminated.astype(bool)
    vals = [q.values(a.obs)[np.arange(len(a.obs)), a.action] for q in qs]
    nxt = [q.values(a.next_obs)[boot] for q in qs]
    prev, prev_next = np.zeros(len(a.obs)), np.zeros_like(nxt[0])
    for k, (v, w) in enumerate(zip(vals, nxt, strict=True)):
        row = f.history_.iloc[k]
        want = max(np.abs(v - prev).max(), np.abs(w - prev_next).max())
        assert row["sup_dq"] == pytest.approx(want, rel=1e-12, abs=1e-12)
        assert row["sup_dq"] >= np.abs(v - prev).max()  # never below the training pairs' own change
        assert row["max_abs_q"] == pytest.approx(np.abs(v).max(), rel=1e-12)
        prev, prev_next = v, w


@pytest.mark.parametrize(("params", "jobs"), [({}, 1), ({"n_jobs": 2}, 2)])
def test_registry_forests_predict_on_one_thread_unless_n_jobs_is_given(small_pt, params, jobs):
    f = FittedQIteration(gamma=0.9, mode="refit", n_iterations=1,
                         regressor_params={"n_estimators": 3, **params}).fit(small_pt)
    assert f.q_function_.models[0].n_jobs == jobs
    assert make_regressor("extra_trees", **params).n_jobs == params.get("n_jobs", -1)  # fitting still uses all cores
