"""One estimand, intervals that cover: every off-policy estimator against exact truth.

Seeded tabular MDPs (30 states, 3 actions) with 10-step logs and gamma in {0.9, 1.0}; the
truth is exact dynamic programming of the declared estimand
``E[sum_{t<10} gamma^t c_t]``, which is also what a Monte-Carlo rollout measures.
The per-seed pipeline mirrors :func:`offline_adp.evaluation.offpolicy.off_policy` with
logged propensities (no behaviour classifier, no shift diagnostics) so 30 seeds stay cheap;
one test checks that ``off_policy`` itself gives the same numbers.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.envs.tabular import TabularMDP
from offline_adp.evaluation import ope, shift
from offline_adp.evaluation.estimand import declare_estimand
from offline_adp.evaluation.fqe_interval import fqe_interval, tabular_fqe_replicates
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.policies import EpsilonPolicy, TabularPolicy
from offline_adp.rollout import rollout
from offline_adp.simulate import collect

T = 10
N_SEEDS = 30
TABULAR_FQE = {"regressor": "tabular", "action_encoding": "per_action"}
GAMMAS = (0.9, 1.0)


def problem(gamma: float, case: str):
    mdp = TabularMDP(30, 3, horizon=T, gamma=gamma, seed=3)
    sol = mdp.optimal()
    opt, worst = TabularPolicy(sol.policy, 3), TabularPolicy(sol.Q.argmax(axis=2), 3)
    if case == "mild":
        pib, pi = EpsilonPolicy(opt, 0.8), EpsilonPolicy(opt, 0.3)
    else:  # heavy weights: the target follows the worst policy, the logs mostly the best
        pib, pi = EpsilonPolicy(opt, 0.5), EpsilonPolicy(worst, 0.3)
    return mdp, pib, pi


def truth(mdp, pi, gamma: float) -> float:
    V = dp.policy_evaluation_finite(mdp.P, mdp.C, shift.policy_table(pi, mdp.n_states, T), T, gamma).V[0]
    return float(mdp.initial_distribution @ V)


def _logs(mdp, pib, pi, n: int, seed: int):
    ds = collect(mdp, pib, n, np.random.default_rng(1000 + seed), horizon=T)
    a = ds.arrays()
    target = pi.probabilities(a.obs, a.step)
    rho = target[np.arange(len(a)), a.action] / a.behavior_prob
    return ds, a, target, rho, ope.EpisodeMatrix.build(a.episode, a.step, T)


def fqe_estimate(mdp, pib, pi, gamma: float, n: int, seed: int, n_boot: int = 200) -> ope.OPEResult:
    """Time-indexed tabular FQE with its trajectory-bootstrap interval (as off_policy computes it)."""
    ds, a, _, _, em = _logs(mdp, pib, pi, n, seed)
    counts = ope.bootstrap_counts(em.n_episodes, n_boot, seed)
    W = np.vstack([np.ones(len(a))] + [c[em.row_episode] for c in counts])
    vals = tabular_fqe_replicates(a.obs, a.action, a.cost, a.next_obs, a.terminated, a.step == 0, pi, 3, T, gamma, W)
    return fqe_interval(vals[0], vals[1:], em.n_episodes)


def estimates(mdp, pib, pi, gamma: float, n: int, seed: int, n_boot: int = 200, fqe: bool = True
              ) -> dict[str, ope.OPEResult]:
    """Every estimator of off_policy on one logged dataset (logged propensities)."""
    ds, a, target, rho, em = _logs(mdp, pib, pi, n, seed)
    out = {"fqe": fqe_estimate(mdp, pib, pi, gamma, n, seed, n_boot)} if fqe else {}
    out.update(ope.importance_sampling_estimates(em, a.cost, rho, gamma, n_boot=n_boot, seed=seed))
    fit = FittedQEvaluation(policy=pi, horizon=T, gamma=gamma, **TABULAR_FQE).fit(ds)
    qv = fit.q_function_.values(a.obs, a.step)
    out.update(ope.doubly_robust_estimates(em, a.cost, rho, qv[np.arange(len(a)), a.action], (target * qv).sum(axis=1),
                                           gamma, n_boot=n_boot, seed=seed))
    if fqe:
        w = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho, regressor="tabular", horizon=T).w
        out["mis"] = ope.marginalised_is_estimate(em, a.cost, rho, w, gamma, n_boot=n_boot, seed=seed)
        out["_fqe_fit"] = fit.value_  # type: ignore[assignment]
    return out


@pytest.mark.parametrize("gamma", GAMMAS)
def test_rollout_truth_and_declared_estimand_are_the_dp_value(gamma):
    mdp, pib, pi = problem(gamma, "mild")
    J = truth(mdp, pi, gamma)
    ro = rollout(mdp, pi, 20_000, np.random.default_rng(0), horizon=T, gamma=gamma)
    se = ro.discounted_cost.std() / np.sqrt(20_000)
    assert abs(ro.mean - J) <= 4 * se
    ds = collect(mdp, pib, 50, np.random.default_rng(1), horizon=T)
    est = declare_estimand(ds, pi)
    assert (est.horizon, est.gamma, est.form, est.fqe_form) == (T, gamma, "finite", "time-indexed")
    assert f"{T} steps" in est.describe()


def test_vectorised_tabular_replicates_equal_fqe_refits():
    """The fast bootstrap path is FittedQEvaluation refitted with each replicate's weights."""
    mdp, pib, pi = problem(0.9, "mild")
    ds = collect(mdp, pib, 200, np.random.default_rng(5), horizon=T)
    a = ds.arrays()
    em = ope.EpisodeMatrix.build(a.episode, a.step, T)
    start = a.step == 0
    W = np.array([c[em.row_episode] for c in ope.bootstrap_counts(em.n_episodes, 4, 1)])
    fast = tabular_fqe_replicates(a.obs, a.action, a.cost, a.next_obs, a.terminated, start, pi, 3, T, 0.9, W)
    for w, v in zip(W, fast, strict=True):
        q = FittedQEvaluation(policy=pi, horizon=T, gamma=0.9, **TABULAR_FQE).fit(ds, sample_weight=w).q_function_
        v0 = (pi.probabilities(a.obs[start], 0) * q.values(a.obs[start], 0)).sum(axis=1)
        assert v == pytest.approx(np.average(v0, weights=w[start]), abs=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("gamma", GAMMAS)
def test_every_estimator_targets_the_declared_estimand(gamma):
    """30 seeds x 300 ten-step episodes: each estimator's mean error is within sampling
    error of 0 (bias-free estimators) or small against its spread; FQE's bias is within
    its interval's width (the old infinite-horizon FQE was off by +1.02 on 1.88 here)."""
    mdp, pib, pi = problem(gamma, "mild")
    J = truth(mdp, pi, gamma)
    errs: dict[str, list[float]] = {}
    widths = []
    for seed in range(N_SEEDS):
        res = estimates(mdp, pib, pi, gamma, 300, seed, n_boot=50)
        assert res.pop("_fqe_fit") == pytest.approx(res["fqe"].estimate, abs=1e-10)
        widths.append(np.diff(res["fqe"].interval)[0])
        for k, r in res.items():
            errs.setdefault(k, []).append(r.estimate - J)
    fqe_bias = float(np.mean(errs["fqe"]))
    assert abs(fqe_bias) <= np.mean(widths), (fqe_bias, np.mean(widths))
    for k, e in errs.items():
        e = np.asarray(e)
        se = e.std(ddof=1) / np.sqrt(len(e))
        # unbiased (IS, PDIS, DR) or O(1/n)-biased (weighted, FQE, MIS) estimators of the SAME quantity:
        # a different estimand (e.g. an infinite-horizon value) would be off by far more than this
        assert abs(e.mean()) <= 4 * se + 0.02 * J, (k, e.mean(), se, J)


#: Coverage is a binomial proportion: over 30 seeds its standard error is ~0.045, too coarse to tell 0.90 from
#: 0.95, so the coverage test runs 100 seeds per gamma (issue 15 asked for 30).
N_COVERAGE_SEEDS = 100


@pytest.mark.slow
@pytest.mark.parametrize("gamma", GAMMAS)
def test_fqe_interval_coverage_over_seeds(gamma):
    """FQE's 95% interval (200 replicates, 1000 ten-step episodes, mild shift) covers the exact value at least
    90% of the time over 100 seeds.

    Measured with the same estimator and seeds: 0.92 (gamma 0.9) and 0.93 (gamma 1.0)
    on seeds 0-99; 0.935 over seeds 0-599 at gamma 0.9 (the bootstrap standard deviation 0.0110 equals the
    estimator's spread over seeds, 0.0109). The old infinite-horizon FQE covered 0 of 30."""
    mdp, pib, pi = problem(gamma, "mild")
    J = truth(mdp, pi, gamma)
    hits = 0
    for seed in range(N_COVERAGE_SEEDS):
        lo, hi = fqe_estimate(mdp, pib, pi, gamma, 1000, seed).interval
        hits += lo <= J <= hi
    assert hits >= 0.90 * N_COVERAGE_SEEDS, (gamma, hits)


@pytest.mark.slow
@pytest.mark.parametrize("gamma", GAMMAS)
def test_is_family_intervals_under_heavy_weights(gamma):
    """Under heavy importance weights (target near the worst policy, logs near the best), 30 seeds x 500 episodes:
    every IS-family interval still labelled 95% covers >= 85% of the times it is given; the others are withheld
    (interval NaN, level None, the method says why)."""
    mdp, pib, pi = problem(gamma, "strong")
    J = truth(mdp, pi, gamma)
    given: dict[str, list[bool]] = {}
    withheld = 0
    for seed in range(N_SEEDS):
        h = estimates(mdp, pib, pi, gamma, 500, seed, fqe=False)
        for k in ("is", "wis", "pdis", "wpdis", "dr", "wdr"):
            if h[k].level is not None:
                lo, hi = h[k].interval
                given.setdefault(k, []).append(lo <= J <= hi)
            else:
                withheld += 1
                assert np.isnan(h[k].interval).all() and "none" in h[k].interval_method
    assert withheld > 0  # the case is heavy: some intervals must have been withheld
    for k, hits in given.items():
        assert np.mean(hits) >= 0.85, (k, hits)


def test_off_policy_declares_its_estimand_and_matches_the_pieces():
    gamma = 0.9
    mdp, pib, pi = problem(gamma, "mild")
    ds = collect(mdp, pib, 300, np.random.default_rng(1000), horizon=T)
    res = off_policy(ds, pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular", n_boot=50, n_boot_fqe=10, seed=0,
                     psdp_folds=0)  # DR then uses the in-sample FQE, as the pieces do
    assert res.estimand.fqe_form == "time-indexed" and res.estimand.horizon == T
    pieces = estimates(mdp, pib, pi, gamma, 300, 0, n_boot=50)
    for k in ("fqe", "is", "pdis", "dr"):
        assert res.estimates[k].estimate == pytest.approx(pieces[k].estimate, abs=1e-9), k
    # cheap replicates are raised to the floor: 10 asked for, 200 run
    assert np.isfinite(res.estimates["fqe"].interval).all()
    # DR's Q fitted on the same episodes (no folds): no paired difference from the logged cost
    assert res.estimates["dr"].vs_logged is None and res.estimates["wdr"].vs_logged is None


def test_infinite_horizon_estimand_only_fqe_can_answer():
    gamma = 0.9
    mdp = TabularMDP(30, 3, horizon=T, gamma=gamma, seed=3)
    pol = TabularPolicy(dp.value_iteration_discounted(mdp.P, mdp.C, gamma).policy, 3)  # stationary
    pib, pi = EpsilonPolicy(pol, 0.8), EpsilonPolicy(pol, 0.3)
    ds = collect(mdp, pib, 600, np.random.default_rng(2), horizon=T)
    res = off_policy(ds, pi, fqe_params={**TABULAR_FQE, "n_iterations": 150, "tol": 1e-8}, ratio_regressor="tabular",
                     n_boot=20, n_boot_fqe=0, estimand="infinite")
    table = shift.policy_table(pi, 30, 1)[0]
    V = dp.policy_evaluation_discounted(mdp.P, mdp.C, table, gamma).V
    a = ds.arrays()
    starts = a.obs[a.step == 0, 0].astype(int)
    assert res.estimates["fqe"].estimate == pytest.approx(V[starts].mean(), rel=0.03)
    for k, r in res.estimates.items():
        if k != "fqe":
            assert not r.comparable and "not the infinite-horizon value" in r.warnings[0]
    with pytest.raises(Exception, match="infinite"):
        declare_estimand(collect(TabularMDP(30, 3, horizon=T, gamma=1.0, seed=3), pib, 5, np.random.default_rng(0),
                                 horizon=T), pi, form="infinite")


def test_a_horizon_past_the_logs_is_said_not_silently_cut():
    from offline_adp.evaluation.estimand import evaluation_horizon
    from offline_adp.simulate import simulate

    ds = simulate("car_on_hill", 0, 3, seed=0, horizon=20)
    T = int(ds.arrays().step.max()) + 1
    with pytest.warns(UserWarning, match=f"horizon 500 asked for, but the longest logged episode has {T} steps"):
        assert evaluation_horizon(ds, 500)[0] == T
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert evaluation_horizon(ds, T)[0] == T and evaluation_horizon(ds)[0] == T


def test_the_model_rollouts_recorded_with_fqe_are_clipped_to_the_possible_range():
    """metrics.json held the model's bootstrap interval [-107.5, 913.7] for costs >= 0 whose
    possible range was [0, 730.9] (a rosbag audit); the report printed it clipped. Clipped
    where it is recorded now, saying from what; readings inside the range are untouched."""
    from offline_adp.evaluation.estimand import clip_to_range
    from offline_adp.evaluation.ope import OPEResult

    mr = {"estimate": 400.0, "interval": [300.0, 500.0], "exit_mass": 0.0,
          "bootstrap": {"interval": [-107.49, 913.69], "readings": [1.0, 2.0]}}
    r = OPEResult("fqe", 400.0, (350.0, 450.0), None, model_rollouts=mr)
    out = clip_to_range(r, (0.0, 730.9)).model_rollouts
    assert out["bootstrap"]["interval"] == [0.0, 730.9]
    assert "from [-107.5, 913.7]" in out["bootstrap"]["interval_note"]
    assert out["interval"] == [300.0, 500.0] and "interval_note" not in out
    assert out["bootstrap"]["readings"] == [1.0, 2.0] and mr["bootstrap"]["interval"] == [-107.49, 913.69]
