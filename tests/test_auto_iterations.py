"""``n_iterations="auto"`` and the convergence verdict (issue #34): a fit that says
"converged" is within the stated distance of the final structure's fixed point. The
oracle: the same learner (same structure) iterated on until it no longer moves."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from offline_adp.algorithms.fqi import FittedQIteration
from offline_adp.algorithms.fqi_loop import fitted_q_loop
from offline_adp.algorithms.fqi_monitor import auto_iterations, distance_bound
from offline_adp.simulate import simulate


@pytest.fixture(scope="module")
def coh():
    return simulate("car_on_hill", 60, 0, seed=3)


def test_auto_iterations_follow_the_discount():
    for gamma in (0.5, 0.9, 0.95, 0.99):
        kb, kmax = auto_iterations(gamma, settles=True)
        assert gamma**kb <= 0.05 < gamma ** (kb - 1)  # the smallest K with gamma^K <= 5%
        assert kmax == 4 * kb and auto_iterations(gamma, settles=False) == (kb, kb)
    assert auto_iterations(1.0, True)[0] == 100
    assert distance_bound(0.1, 0.9) == pytest.approx(0.9) and math.isinf(distance_bound(0.1, 1.0))


@pytest.mark.parametrize("gamma", [0.9, 0.95])
def test_converged_means_within_the_bound_of_the_final_structures_fixed_point(coh, gamma):
    est = FittedQIteration(gamma=gamma, regressor_params={"n_estimators": 10}).fit(coh)
    assert est.mode_ == "frozen" and est.verdict_ == "converged", est.verdict_message_
    kb, kmax = est.iteration_plan()
    K = len(est.history_)
    assert max(est._schedule()) < K < kmax  # stopped by the criterion, after the last build
    assert est.history_["inner_backups"].iloc[-2] > 0 == est.history_["inner_backups"].iloc[-1]  # solved, then plain
    last = est.history_.iloc[-1]
    bound = distance_bound(last["sup_dq"], gamma)
    assert bound <= 0.01 * last["max_abs_q"]  # the default rtol
    stated = float(re.search(r"within ([0-9.e+-]+) of the final tree structure", est.verdict_message_).group(1))
    assert stated == pytest.approx(bound, rel=1e-2)
    # the message's own arithmetic: the bound it states is gamma/(1-gamma) x the sup|dQ| it states
    sd = float(re.search(r"sup\|dQ\| = ([0-9.e+-]+);", est.verdict_message_).group(1))
    assert sd == pytest.approx(last["sup_dq"], rel=1e-2) and stated == pytest.approx(gamma / (1 - gamma) * sd, rel=2e-2)
    # the oracle: go on in the same structure until nothing moves
    fit = est.fit_state_
    x0 = coh.arrays().obs[:500]
    q_K = est.q_function_.values(x0)
    learner = fit.learner
    learner.settle = None  # the oracle: plain backups
    q_next = learner.predict("next")
    for it in fitted_q_loop(fit.data, learner, fit.backup, ((k, None) for k in range(K + 1, K + 3000)), q_next):
        if np.abs(it.q_next - it.q_next_old).max() < 1e-12:
            break
    q_inf = learner.snapshot().values(x0)
    gap = np.abs(q_K - q_inf).max()
    assert gap <= bound + 1e-9  # the verdict's distance holds at states it never saw as such
    assert gap > 0 or bound == 0


def test_a_fixed_count_too_small_says_still_changing_with_the_distance(coh):
    est = FittedQIteration(gamma=0.95, n_iterations=12, regressor_params={"n_estimators": 10}).fit(coh)
    assert est.verdict_ == "still changing"
    assert "of the final tree structure's fixed point" in est.verdict_message_ and "> tolerance" in est.verdict_message_


def test_refit_mode_never_claims_the_contraction_bound(coh):
    est = FittedQIteration(gamma=0.9, mode="refit", regressor_params={"n_estimators": 5}).fit(coh)
    assert len(est.history_) == auto_iterations(0.9, settles=False)[0]  # no settling phase without a fixed structure
    assert est.verdict_ == "still changing" and "no contraction bound" in est.verdict_message_


def test_target_noise_has_no_fixed_point_so_no_bound_is_claimed(coh):
    est = FittedQIteration(gamma=0.9, target_noise=0.1, regressor_params={"n_estimators": 5}).fit(coh)
    assert est.mode_ == "frozen" and est.iteration_plan() == auto_iterations(0.9, settles=False)
    assert est.verdict_ == "still changing" and "no contraction bound" in est.verdict_message_


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_sample_weights_must_be_averaging_weights(coh, bad):
    w = np.ones(len(coh))
    w[7] = bad
    with pytest.raises(ValueError, match="sample_weight must be finite numbers >= 0.*row 7"):
        FittedQIteration(gamma=0.9, n_iterations=2, regressor_params={"n_estimators": 5}).fit(coh, sample_weight=w)
    with pytest.raises(ValueError, match="not all 0"):
        FittedQIteration(gamma=0.9, n_iterations=2).fit(coh, sample_weight=np.zeros(len(coh)))


def test_bad_sample_weights_are_our_error_type(coh):
    from offline_adp.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="sample_weight"):
        FittedQIteration(gamma=0.9, n_iterations=2).fit(coh, sample_weight=-np.ones(len(coh)))
