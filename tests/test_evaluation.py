"""Evaluation against exact ground truth on seeded tabular MDPs (T = 10, 30 states, 3 actions).

Behaviour and target policies are noisy versions of the optimal policy (mild shift) or
of the optimal and the *worst* policy (strong shift). Truth comes from exact dynamic
programming (:mod:`offline_adp.dp`) and exact state distributions.
"""

from __future__ import annotations

import numpy as np
import pytest

from offline_adp import dp
from offline_adp.algorithms.psdp import state_samples
from offline_adp.envs.tabular import TabularMDP
from offline_adp.evaluation import shift
from offline_adp.evaluation.offpolicy import off_policy
from offline_adp.policies import EpsilonPolicy, TabularPolicy
from offline_adp.simulate import collect

T = 10
MDP = TabularMDP(30, 3, horizon=T, seed=3)
OPT = MDP.optimal().policy
WORST = MDP.optimal().Q.argmax(axis=2)
CASES = {
    "mild": (EpsilonPolicy(TabularPolicy(OPT, 3), 0.8), EpsilonPolicy(TabularPolicy(OPT, 3), 0.3)),
    "strong": (EpsilonPolicy(TabularPolicy(OPT, 3), 0.5), EpsilonPolicy(TabularPolicy(WORST, 3), 0.3)),
}
TABULAR_FQE = {"regressor": "tabular", "action_encoding": "per_action"}


def true_value(pi) -> float:
    V = dp.policy_evaluation_finite(MDP.P, MDP.C, shift.policy_table(pi, MDP.n_states, T), T).V[0]
    return float(MDP.initial_distribution @ V)


def logged(pib, n: int, seed: int):
    return collect(MDP, pib, n, np.random.default_rng(seed), horizon=T)


def rho_of(ds, pi):
    a = ds.arrays()
    return a, pi.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / a.behavior_prob


def recursion_errors(case: str, n: int, seed: int = 1) -> tuple[float, float]:
    pib, pi = CASES[case]
    W = shift.exact_ratios(MDP, pi, pib, T)
    a, rho = rho_of(logged(pib, n, seed), pi)
    r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho, regressor="tabular")
    w = W[a.step, a.obs[:, 0].astype(int)]
    return float(np.mean(np.abs(r.w - w))), abs(float(np.mean(r.w**2) - np.mean(w**2)))


def test_exact_distributions_sum_to_one_and_match_monte_carlo():
    pib, pi = CASES["strong"]
    mu = shift.exact_distributions(MDP, pi, T)
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, atol=1e-12)
    n = 20_000
    a = logged(pi, n, 7).arrays()
    for t in range(T):
        freq = np.bincount(a.obs[a.step == t, 0].astype(int), minlength=MDP.n_states) / n
        se = np.sqrt(mu[t] * (1 - mu[t]) / n)
        assert np.all(np.abs(freq - mu[t]) <= 5 * se + 1e-9), t


def test_ratios_are_one_when_target_is_behaviour():
    pib, _ = CASES["mild"]
    np.testing.assert_allclose(shift.exact_ratios(MDP, pib, pib, T), 1.0)
    a, rho = rho_of(logged(pib, 2000, 2), pib)
    np.testing.assert_allclose(rho, 1.0)
    r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho, regressor="tabular")
    np.testing.assert_allclose(r.w, 1.0, atol=1e-12)
    r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho)  # extra-trees
    np.testing.assert_allclose(r.w, 1.0, atol=1e-9)
    assert not [m for m in r.warnings if "sample" in m]  # below the cap: every row fitted, nothing said


@pytest.mark.parametrize("case,l1_max,w2_max", [("mild", 0.05, 0.01), ("strong", 0.12, 0.03)])
def test_recursion_matches_exact_ratios_and_improves_with_data(case, l1_max, w2_max):
    l1_10k, w2_10k = recursion_errors(case, 10_000)
    assert l1_10k <= l1_max
    assert w2_10k <= w2_max
    l1_100k, _ = recursion_errors(case, 100_000)
    assert l1_100k <= 0.45 * l1_10k


def test_ratio_regressions_above_the_row_cap_fit_a_sample_and_still_match_exact(monkeypatch):
    """Above ``RATIO_MAX_FIT_ROWS`` each ratio regression is fitted on a sample of that many rows
    (and read at every row): on 100k episodes (100k rows a step) capped to 15,000 the recursion
    still meets the 10k-episode bound against the exact ratios, and pooling stays the exact
    fixed point of the same sampled regressions: a sweep's output depends on its input only
    through the sampled rows."""
    fitted: list[int] = []
    real = shift.make_regressor

    def counting(*args, **kw):
        model = real(*args, **kw)
        fit = model.fit
        model.fit = lambda X, y: (fitted.append(len(X)), fit(X, y))[1]
        return model

    monkeypatch.setattr(shift, "make_regressor", counting)
    monkeypatch.setattr(shift, "RATIO_MAX_FIT_ROWS", 15_000)
    l1, w2 = recursion_errors("strong", 100_000)
    assert fitted and max(fitted) == 15_000
    a, rho = rho_of(logged(CASES["strong"][0], 100_000, 1), CASES["strong"][1])
    (said,) = [m for m in shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho,
                                                    regressor="tabular").warnings if "sample" in m]
    assert "15,000 of 100,000 rows" in said  # the cap is said, not silent
    assert l1 <= 0.12 and w2 <= 0.03
    # the same sample at every sweep: rows outside it do not move the pooled ratios
    a, rho = rho_of(logged(CASES["strong"][0], 2_000, 4), CASES["strong"][1])
    pooled = shift.ratios_pooled(a.obs, a.next_obs, a.step, rho, regressor="tabular")
    assert any("15,000 of 18,000 rows" in m for m in pooled.warnings)
    base = pooled.w
    src = np.flatnonzero(a.step < a.step.max())
    sample = np.sort(np.random.default_rng(len(src)).choice(len(src), 15_000, replace=False))
    outside = np.setdiff1d(np.arange(len(src)), sample)
    rho2 = rho.copy()
    rho2[src[outside]] *= 3.0
    np.testing.assert_allclose(shift.ratios_pooled(a.obs, a.next_obs, a.step, rho2, regressor="tabular").w, base,
                               rtol=1e-12)
    rho2[src[sample[:50]]] *= 3.0
    assert not np.allclose(shift.ratios_pooled(a.obs, a.next_obs, a.step, rho2, regressor="tabular").w, base)


@pytest.mark.parametrize("case", ["mild", "strong"])
def test_classifier_ratios_match_exact(case):
    pib, pi = CASES[case]
    W = shift.exact_ratios(MDP, pi, pib, T)
    a = logged(pib, 10_000, 1).arrays()
    states = state_samples(MDP, pi, 10_000, T, np.random.default_rng(5))
    r = shift.ratios_by_classifier(a.obs, a.step, states)
    w = W[a.step, a.obs[:, 0].astype(int)]
    assert np.mean(np.abs(r.w - w)) <= 0.10
    assert all(0.4 <= v < 0.95 for v in r.auc.values())
    assert not r.warnings


def test_separable_steps_are_one_warning_naming_their_runs():
    """Policy states far from the data's at steps 1-3 and 6 (of 8): one warning, not four."""
    rng = np.random.default_rng(0)
    step = np.repeat(np.arange(8), 200)
    obs = rng.normal(size=(len(step), 2))
    far = {1, 2, 3, 6}
    states = [rng.normal(size=(200, 2)) + (20.0 if t in far else 0.0) for t in range(8)]
    r = shift.ratios_by_classifier(obs, step, states)
    assert {t for t, a in r.auc.items() if a > 0.95} == far
    (w,) = [w for w in r.warnings if "AUC" in w]
    assert w.startswith("classifier AUC > 0.95 at 4 of 8 steps (1-3, 6; highest ")


def test_diagnostics_of_exact_ratios():
    pib, pi = CASES["strong"]
    W = shift.exact_ratios(MDP, pi, pib, T)
    a = logged(pib, 5000, 3).arrays()
    r = shift.DensityRatios("exact", W[a.step, a.obs[:, 0].astype(int)], a.step)
    d = shift.diagnostics(r, a.obs, k=20)
    mu_b = shift.exact_distributions(MDP, pib, T)
    for t in (1, 5, 9):
        row = d.set_index("step").loc[t]
        # ESS/n = 1 / E_b[w^2] with the exact expectation over mu_b
        e2 = np.sum(mu_b[t] * np.where(mu_b[t] > 0, W[t], 0.0) ** 2)
        assert row["ess_fraction"] == pytest.approx(1 / e2, rel=0.1)
        assert row["supported_sup"] <= W[t][np.isfinite(W[t])].max() + 1e-9
        assert row["sup_ucb"] >= row["supported_sup"] - 1e-12
        assert row["q50"] <= row["q90"] <= row["q99"] <= row["max"]


@pytest.fixture(scope="module")
def mild_1k():
    pib, pi = CASES["mild"]
    return off_policy(logged(pib, 1000, 11), pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular",
                      n_boot=100, n_boot_fqe=10)


def test_fqe_within_one_percent_at_1k(mild_1k):
    truth = true_value(CASES["mild"][1])
    assert abs(mild_1k.estimates["fqe"].estimate - truth) <= 0.01 * truth


def test_wdr_within_eight_percent_at_1k(mild_1k):
    truth = true_value(CASES["mild"][1])
    for name in ("wdr", "dr"):
        assert abs(mild_1k.estimates[name].estimate - truth) <= 0.08 * truth, name
    wdr = mild_1k.estimates["wdr"]
    if wdr.level is not None:  # the weights are well-shaped (ope.interval_unreliable)
        lo, hi = wdr.interval
        assert lo < wdr.estimate < hi
    else:  # too few effective episodes for a bootstrap interval to cover as labelled: withheld, said so
        assert wdr.level is None and np.isnan(wdr.interval).all() and "none" in wdr.interval_method
        lo, hi = wdr.percentile_interval
        assert lo < wdr.estimate < hi


@pytest.mark.slow
def test_mis_within_three_percent_at_10k():
    pib, pi = CASES["strong"]
    res = off_policy(logged(pib, 10_000, 12), pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular", n_boot=50,
                     n_boot_fqe=0)
    truth = true_value(pi)
    assert abs(res.estimates["mis"].estimate - truth) <= 0.03 * truth
    # trajectory IS over 10 steps of a strong shift is degenerate: it must say so
    assert res.estimates["is"].ess < 100 and "degenerate" in " ".join(res.estimates["is"].warnings)
    assert res.behaviour.source == "logged"


def test_importance_sampling_family_on_mild_shift(mild_1k):
    truth = true_value(CASES["mild"][1])
    for name, tol in (("is", 0.10), ("wis", 0.10), ("pdis", 0.05), ("wpdis", 0.05)):
        assert abs(mild_1k.estimates[name].estimate - truth) <= tol * truth, name


# Interval coverage over seeds (FQE, and the IS family under heavy weights): tests/test_eval_estimand.py.


@pytest.mark.slow
def test_psdp_bound_matches_exact_and_holds():
    """Theorem 2 with mu = the data's distribution and pi_ref = the optimal policy."""
    pib, pi = CASES["mild"]
    ref = TabularPolicy(OPT, 3)
    # exact: eps_t = E_{mu_b^t}[V^pi_t - min_a Q^pi_t], ratio_t = max_s mu_ref^t / mu_b^t
    sol = dp.policy_evaluation_finite(MDP.P, MDP.C, shift.policy_table(pi, MDP.n_states, T), T)
    table = shift.policy_table(pi, MDP.n_states, T)
    gap = (table * sol.Q).sum(axis=2) - sol.Q.min(axis=2)
    mu_b = shift.exact_distributions(MDP, pib, T)[:T]
    eps = (mu_b * gap).sum(axis=1)
    bound = float(np.sum(eps * shift.exact_ratios(MDP, ref, pib, T).max(axis=1)))
    achieved = true_value(pi) - true_value(ref)
    assert 0 < achieved <= bound
    res = off_policy(logged(pib, 10_000, 13), pi, fqe_params=TABULAR_FQE, ratio_regressor="tabular",
                     reference_policies={"optimal": ref}, n_boot=20, n_boot_fqe=0)
    np.testing.assert_allclose(res.eps, eps, atol=0.01)
    est = res.bounds["optimal"]["per_step"]
    assert est == pytest.approx(bound, rel=0.10)
    assert achieved <= est
