"""The IS-family interval rule looks at the weights' shape (ope.interval_unreliable), checked
against exact DP on seeded tabular MDPs (T = 10, 30 states, 3 actions)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs.tabular import TabularMDP
from offline_adp.evaluation import ope, shift
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.policies import EpsilonPolicy, TabularPolicy, UniformPolicy
from offline_adp.simulate import collect

T = 10
MDP = TabularMDP(30, 3, horizon=T, seed=3)
SOL = MDP.optimal()
OPT, WORST = TabularPolicy(SOL.policy, 3), TabularPolicy(SOL.Q.argmax(axis=2), 3)
TABULAR_FQE = {"regressor": "tabular", "action_encoding": "per_action"}
IS_FAMILY = ("is", "wis", "pdis", "wpdis", "dr", "wdr")


def truth(pi) -> float:
    V = dp.policy_evaluation_finite(MDP.P, MDP.C, shift.policy_table(pi, MDP.n_states, T), T).V[0]
    return float(MDP.initial_distribution @ V)


def test_pareto_k_reads_tail_heaviness():
    rng = np.random.default_rng(0)
    light = rng.exponential(size=4000)  # exponential tail: k ~ 0
    heavy = rng.pareto(1.0, size=4000) + 1  # Pareto tail with index 1: k ~ 1
    assert abs(ope.pareto_k(light)) < 0.25
    assert 0.8 < ope.pareto_k(heavy) < 1.3
    assert np.isnan(ope.pareto_k(np.r_[np.ones(100), np.zeros(100)]))  # flat: no tail to fit


def test_pareto_k_on_many_weights_says_nothing_of_overflow():
    """With ~600k weights (a 1M-row evaluation) the profile log-likelihoods differ by more than
    exp can hold: the weights over them are a softmax, read without a RuntimeWarning, and the
    shape is still the tail's (Pareto index 1: k ~ 1; index 3: k ~ 1/3)."""
    rng = np.random.default_rng(1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        heavy = ope.pareto_k(rng.pareto(1.0, size=600_000) + 1)
        lighter = ope.pareto_k(rng.pareto(3.0, size=600_000) + 1)
    assert 0.8 < heavy < 1.3
    assert 0.2 < lighter < 0.5


def test_mixed_behaviour_is_interval_withheld_with_the_reason():
    """Half the episodes from a near-deterministic policy equal to the target, half uniform:
    only the first half carries weight and plain IS is scaled down by about 2."""
    pi = EpsilonPolicy(OPT, 0.05)
    rng = np.random.default_rng(0)
    ds = TransitionDataset.concat([
        collect(MDP, pi, 100, rng, horizon=T, source="demonstration", episode_prefix="demo"),
        collect(MDP, UniformPolicy(3), 100, rng, horizon=T, source="exploration", episode_prefix="explore")])
    res = off_policy(ds, pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular", n_boot=100, n_boot_fqe=0, psdp_folds=0)
    J = truth(pi)
    r = res.estimates["is"]
    assert r.estimate < 0.65 * J  # the failure the rule must catch: IS off by ~2
    assert r.ess >= 90  # an absolute ESS rule of < 100 would barely (and by luck) see it
    assert r.level is None and np.isnan(r.interval).all()
    assert "average" in r.interval_method and "not 1" in r.interval_method
    assert "'demonstration'" in res.estimates["wis"].interval_method  # the subset, named
    assert "no interval" in " ".join(r.warnings)
    assert r.as_dict()["weight_diagnostics"]["carrying_fraction"] == pytest.approx(0.5)


def test_well_shaped_weights_keep_dr_intervals():
    """ESS ~ 40 of 1000 episodes, light tail: DR and WDR intervals are given and hold the truth."""
    pib, pi = EpsilonPolicy(OPT, 0.8), EpsilonPolicy(OPT, 0.3)
    res = off_policy(collect(MDP, pib, 1000, np.random.default_rng(11), horizon=T), pi, fqe_params=TABULAR_FQE,
                     ratio_regressor="tabular", n_boot=200, n_boot_fqe=0, psdp_folds=0)
    J = truth(pi)
    for k in ("dr", "wdr"):
        r = res.estimates[k]
        assert r.ess < 100  # the old absolute rule withheld these
        assert r.level == 0.95, r.interval_method
        assert r.interval[0] <= J <= r.interval[1]


def _is_family(pib, pi, n: int, seed: int) -> dict[str, ope.OPEResult]:
    ds = collect(MDP, pib, n, np.random.default_rng(1000 + seed), horizon=T)
    a = ds.arrays()
    target = pi.probabilities(a.obs, a.step)
    rho = target[np.arange(len(a)), a.action] / a.behavior_prob
    em = ope.EpisodeMatrix.build(a.episode, a.step, T)
    out = ope.importance_sampling_estimates(em, a.cost, rho, 1.0, n_boot=200, seed=seed)
    qv = FittedQEvaluation(policy=pi, horizon=T, gamma=1.0, **TABULAR_FQE).fit(ds).q_function_.values(a.obs, a.step)
    out.update(ope.doubly_robust_estimates(em, a.cost, rho, qv[np.arange(len(a)), a.action], (target * qv).sum(axis=1),
                                           1.0, n_boot=200, seed=seed))
    return out


@pytest.mark.slow
def test_labelled_intervals_cover_over_seeds():
    """30 seeds each of a mild and a heavy shift: every IS-family interval still labelled 95%
    holds the exact DP value (pooled over estimators and cases; measured 0.89 of 36 given, all of the
    heavy case's withheld; a binomial standard error of ~0.05 at 36, hence the 0.85 floor)."""
    cases = [(EpsilonPolicy(OPT, 0.8), EpsilonPolicy(OPT, 0.3), 1000),
             (EpsilonPolicy(OPT, 0.5), EpsilonPolicy(WORST, 0.3), 500)]
    hits: list[bool] = []
    withheld = 0
    for pib, pi, n in cases:
        J = truth(pi)
        for seed in range(30):
            for r in _is_family(pib, pi, n, seed).values():
                if r.level is None:
                    withheld += 1
                    assert np.isnan(r.interval).all() and r.interval_method.startswith("none: ")
                else:
                    hits.append(r.interval[0] <= J <= r.interval[1])
    assert withheld > 0 and len(hits) >= 30
    assert np.mean(hits) >= 0.85, (np.mean(hits), len(hits))


def test_a_mean_weight_far_from_1_withholds_only_unnormalised_intervals():
    """WIS, WPDIS and WDR divide by the weights' sum: their scale cancels, so a mean weight of
    0.5 says nothing against them (it did withhold them: the flag was ignored)."""
    from offline_adp.evaluation.ope import interval_unreliable, weight_diagnostics

    rng = np.random.default_rng(0)
    w = 0.5 * rng.uniform(0.8, 1.2, 400)  # well shaped, scaled to mean 0.5
    d = weight_diagnostics(w[:, None])
    assert interval_unreliable(d, normalised=True) == []
    assert any("average" in r for r in interval_unreliable(d, normalised=False))


@pytest.mark.parametrize("n", [40, 135, 1000])
def test_fewer_than_two_effective_episodes_are_degenerate_at_any_n(n):
    """ESS 1.0 of 40 episodes (one episode holding all the weight) was ranked as "no interval"
    with its point estimate quoted (ESS below 1% of n was the only rule); below two effective
    episodes the estimate is one or two episodes' returns, "not usable". Above, the interval is
    withheld but the estimate stays ranked."""
    from offline_adp.evaluation.summary import rank_estimators

    for w_big, degenerate in ((1e6, True), (3.0, False)):
        W = np.ones(n)
        W[:1 if degenerate else 0] = w_big
        if not degenerate:
            W[: n // 2] = 1e-3  # ESS ~ n/2: well shaped (interval kept or withheld by the other rules only)
        r = ope.OPEResult("wis", 1.0, (0.5, 1.5), ope._ess(W), 0.95)
        ope._judge_weights(r, W)
        assert r.degenerate is degenerate, (r.ess, n)
        tier = rank_estimators({"ope": {"wis": r.as_dict()}})[0]["tier"]
        assert (tier == 2) is degenerate
    W = np.r_[np.full(3, 1e3), np.ones(n - 3)]  # ESS ~3 whatever n: no interval, not degenerate unless 1% of n says so
    r = ope.OPEResult("wis", 1.0, (0.5, 1.5), ope._ess(W), 0.95)
    ope._judge_weights(r, W)
    assert r.degenerate is (r.ess < 0.01 * n) and r.level is None


def test_mis_is_not_degenerate_for_one_episode_outliving_the_others():
    """MIS's ESS is the worst step's among the episodes still running: 1.0 wherever one episode
    runs longer than every other, with every weight 1 (a review's counterexample to the floor of
    two episodes, which is not applied to it); IS-type weights with one episode carrying all are."""
    from offline_adp.evaluation.summary import rank_estimators

    n, T = 60, 20
    W = np.zeros((n, T))
    W[:, :10] = 1.0
    W[0, :] = 1.0  # one episode of 20 steps, 59 of 10: the last steps have one episode alive
    ess = min(ope._ess(W[W[:, t] > 0, t]) for t in range(T))
    assert ess == 1.0
    r = ope.OPEResult("mis", 1.0, (0.5, 1.5), ess, 0.95)
    ope._judge_weights(r, W)
    assert not r.degenerate
    m = {"ope": {"mis": r.as_dict(), "wis": {**r.as_dict(), "degenerate": False}}}
    tiers = {e["name"]: e["tier"] for e in rank_estimators(m)}
    # a stored file's WIS at ESS 1 (written before the floor) is read as degenerate; MIS is not
    assert tiers["wis"] == 2 and tiers["mis"] != 2
