"""On the logging policy's own weights the doubly robust estimate leads (issue #42).

Ground truth: exact dynamic programming on the seeded tabular MDP of
``test_eval_estimand`` (10-step logs, logged propensities), and closed forms: with every
weight 1 and a zero Q, DR is the logged mean, so its paired difference from the logged
cost is exactly 0 on every replicate; the cost past the logs is the logged cost range
times ``sum_{T <= t < H} gamma^t``.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from offline_adp.evaluation import ope
from offline_adp.evaluation.estimand import Estimand, confined, episode_ends, past_the_logs
from offline_adp.evaluation.summary import rank_estimators, verdict_line
from offline_adp.policies import EpsilonPolicy, TabularPolicy
from tests.test_eval_estimand import T, estimates, problem, truth


def test_dr_on_the_logged_mean_has_a_paired_difference_of_zero():
    rng = np.random.default_rng(0)
    n, steps = 60, 5
    em = ope.EpisodeMatrix.build(np.repeat(np.arange(n), steps), np.tile(np.arange(steps), n))
    cost = rng.normal(3.0, 2.0, n * steps)
    zeros, ones = np.zeros(n * steps), np.ones(n * steps)
    dr = ope.doubly_robust_estimates(em, cost, ones, zeros, zeros, 0.9, n_boot=100, seed=4)
    is_ = ope.importance_sampling_estimates(em, cost, ones, 0.9, n_boot=100, seed=4)["is"]
    G = em.lay(cost) @ 0.9 ** np.arange(steps)
    for r in dr.values():
        assert r.estimate == pytest.approx(G.mean())
        assert r.vs_logged == pytest.approx((0.0, 0.0), abs=1e-12)
        assert ope.on_policy(r)
    assert dr["dr"].interval == pytest.approx(is_.interval)  # the same replicates as before the pairing


@pytest.mark.slow
def test_paired_difference_and_interval_cover_the_exact_values():
    """Over 30 seeds x 500 episodes: the logging policy evaluated on its own logs (WDR on-policy, its
    paired difference's truth 0) and a nearby target (epsilon 0.6 against the logs' 0.8: ESS about half
    the episodes; the truth J(pi) - J(b) by DP): each 95% interval given covers its exact value at least
    85% of the time."""
    gamma = 0.9
    mdp, pib, _ = problem(gamma, "mild")
    pi = EpsilonPolicy(TabularPolicy(mdp.optimal().policy, 3), 0.6)
    J_b, J_pi = truth(mdp, pib, gamma), truth(mdp, pi, gamma)
    hits = {"self": [], "self_diff": [], "pi": [], "pi_diff": []}
    for seed in range(30):
        own = estimates(mdp, pib, pib, gamma, 500, seed, fqe=False)["wdr"]
        assert ope.on_policy(own)
        hits["self"].append(own.interval[0] <= J_b <= own.interval[1])
        hits["self_diff"].append(own.vs_logged[0] <= 0.0 <= own.vs_logged[1])
        other = estimates(mdp, pib, pi, gamma, 500, seed, fqe=False)["wdr"]
        if other.vs_logged is not None:
            hits["pi"].append(other.interval[0] <= J_pi <= other.interval[1])
            hits["pi_diff"].append(other.vs_logged[0] <= J_pi - J_b <= other.vs_logged[1])
    assert len(hits["pi_diff"]) >= 20 and J_pi - J_b < -0.3  # a real difference, mostly given
    for k, h in hits.items():
        assert np.mean(h) >= 0.85, (k, h)


def _wdr(frac: float, iv: list[float], vs: list[float]) -> dict:
    return {"estimate": sum(iv) / 2, "interval": iv, "level": 0.95, "vs_logged": vs,
            "weight_diagnostics": {"ess_fraction": frac}}


BASE = {"estimand": {"possible_range": [-20.0, 0.0]},
        "ope": {"fqe": {"estimate": -12.6, "interval": [-14.1, -12.2], "level": 0.95},
                "model": {"estimate": -12.7, "interval": [-13.3, -12.0], "level": 0.95},
                "wdr": _wdr(1.0, [-12.88, -12.57], [-0.10, 0.25])},
        "behaviour_value": {"mean": -12.9, "interval": [-13.3, -12.5]},
        "behaviour": {"support_violations": {"fraction": 0.0}}}
IN_SUPPORT = {"method": "recursion", "enough_data": True}
CONVERGED = {"verdict": "converged", "text": "fit converged"}


def test_wdr_leads_on_the_logging_policys_weights_and_the_verdict_reads_the_paired_difference():
    rank = rank_estimators(BASE)
    assert rank[0]["name"] == "wdr" and rank[0]["vs_logged"] == [-0.10, 0.25]
    # its interval lies above the logged -12.9, but the difference on the same episodes holds 0
    v = verdict_line(BASE, rank, IN_SUPPORT, CONVERGED)
    assert v["performance"] == "indistinguishable" and "difference from the logged cost" in v["text"]
    assert "nearly the policy's own (its importance weights keep 100% of them)" in v["lines"][2]
    worse = copy.deepcopy(BASE)
    worse["ope"]["wdr"]["vs_logged"] = [0.05, 0.4]
    assert verdict_line(worse, rank_estimators(worse), IN_SUPPORT, CONVERGED)["performance"] == "worse"


@pytest.mark.parametrize("change", ["thin weights", "no level", "degenerate", "no paired interval", "bad number",
                                    "reversed paired interval", "fraction above 1"])
def test_without_the_logging_policys_weights_the_model_leads(change):
    m = copy.deepcopy(BASE)
    w = m["ope"]["wdr"]
    if change == "thin weights":
        w["weight_diagnostics"]["ess_fraction"] = 0.3
    elif change == "no level":
        w["level"] = None
    elif change == "degenerate":
        w["degenerate"] = True
    elif change == "no paired interval":
        del w["vs_logged"]
    elif change == "reversed paired interval":
        w["vs_logged"] = [0.25, -0.10]
    elif change == "fraction above 1":
        w["weight_diagnostics"]["ess_fraction"] = 1.5
    else:
        w["weight_diagnostics"]["ess_fraction"] = "1.0"
    rank = rank_estimators(m)
    assert rank[0]["name"] == "model" and rank[0]["vs_logged"] is None
    # the model's interval holds the logged cost: no side, and no paired words
    v = verdict_line(m, rank, IN_SUPPORT, CONVERGED)
    assert "difference from the logged cost" not in v["text"]


def _est(name: str, frac: float, iv: tuple[float, float] = (4.0, 6.0)) -> ope.OPEResult:
    return ope.OPEResult(name, 5.0, iv, 100.0 * frac, vs_logged=(-1.0, 1.0),
                         weight_diagnostics={"ess_fraction": frac})


@pytest.mark.parametrize("ends", ["terminal", "horizon", "short"])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_past_the_logs_the_cost_after_step_T_is_added(ends, sign):
    gamma, T_, H, n = 0.5, 3, 5, 20
    span = sum(gamma**t for t in range(T_))
    est_def = Estimand(T_, gamma, target_horizon=H, possible_range=(-1e3, 1e3))
    logged_range = (sign * 1.0 * span, sign * 2.0 * span)  # costs in [1, 2] (or [-2, -1])
    logged_range = (min(logged_range), max(logged_range))
    out = confined({"fqe": _est("fqe", 1.0), "wdr": _est("wdr", 1.0), "dr": _est("dr", 0.3),
                    "wis": _est("wis", 1.0)}, est_def, logged_range, ends, n)
    tail = 2.0 * (gamma**3 + gamma**4)  # the cost of steps 3 and 4 lies in [0, tail] (or [-tail, 0])
    if ends == "terminal":
        tail *= 3 / n
    lo_t, hi_t = (0.0, tail) if sign > 0 else (-tail, 0.0)
    w = out["wdr"]
    if ends == "short":  # an episode stopped early unterminated: its later cost is unknown
        assert not w.comparable and w.interval == (4.0, 6.0)
    else:
        assert w.comparable and f"{T_}..{H - 1}" in w.warnings[0]
        assert w.interval == pytest.approx((4.0 + lo_t, 6.0 + hi_t))
        assert w.vs_logged == pytest.approx((-1.0 + lo_t, 1.0 + hi_t))
    # thin weights (DR at ESS 30%) and the other trajectory estimators still see only the T logged steps
    assert not out["dr"].comparable and not out["wis"].comparable
    # an allowance wider than the estimate's own interval: it stays a T-step estimate
    narrow = confined({"fqe": _est("fqe", 1.0), "wdr": _est("wdr", 1.0, (5.0, 5.0 + 1e-3))}, est_def, logged_range,
                      "horizon", n)
    assert not narrow["wdr"].comparable


def test_how_the_episodes_end_is_read_within_the_T_steps():
    # three episodes of 4, 2 and 6 steps, read over T = 4
    episode = np.repeat([0, 1, 2], [4, 2, 6])
    step = np.concatenate([np.arange(4), np.arange(2), np.arange(6)])
    em = ope.EpisodeMatrix.build(episode, step, 4)

    def ends(last_terminated):
        term = np.zeros(len(step), bool)
        for e, flag in enumerate(last_terminated):
            if flag:
                term[np.flatnonzero(episode == e)[-1]] = True
        return episode_ends(em, term)

    assert ends([True, True, True]) == "horizon"  # the third's terminal state (step 5) is past T: not seen
    assert ends([True, True, False]) == "horizon"  # the third runs past T: cut there, not ended
    assert ends([True, False, False]) == "short"  # the second stopped at step 2 without ending
    assert ends([False, True, True]) == "horizon"  # the third's terminal state is past T: not seen
    term = np.zeros(len(step), bool)
    term[[3, 5, 9]] = True  # the third ends at its step 3, within T
    assert episode_ends(em, term) == "terminal"


def test_without_bootstrap_replicates_nothing_is_on_policy():
    n, steps = 40, 4
    em = ope.EpisodeMatrix.build(np.repeat(np.arange(n), steps), np.tile(np.arange(steps), n))
    ones, zeros = np.ones(n * steps), np.zeros(n * steps)
    for r in ope.doubly_robust_estimates(em, ones, ones, zeros, zeros, 0.9, n_boot=0).values():
        assert not ope.on_policy(r)


def test_compare_ranks_by_a_promoted_estimator_only_where_every_candidate_promotes_it():
    from offline_adp.evaluation.compare import _common_estimator

    own = rank_estimators(BASE)
    other = copy.deepcopy(BASE)
    other["ope"]["wdr"]["weight_diagnostics"]["ess_fraction"] = 0.2
    far = rank_estimators(other)
    assert own[0]["name"] == "wdr" and far[0]["name"] == "model"
    assert _common_estimator([own, far]) == _common_estimator([far, own]) == "model"
    assert _common_estimator([own, own]) == "wdr"


def test_the_cost_past_the_logs_holds_the_exact_value():
    """Exact DP: the H-step value of the logging policy lies within its T-step value plus the tail bound."""
    gamma = 0.9
    mdp, pib, _ = problem(gamma, "mild")
    from offline_adp import dp
    from offline_adp.evaluation import shift

    table = shift.policy_table(pib, mdp.n_states, T)
    V = {h: float(mdp.initial_distribution @ dp.policy_evaluation_finite(mdp.P, mdp.C, table[:h], h, gamma).V[0])
         for h in (6, T)}
    c_lo, c_hi = float(mdp.C.min()), float(mdp.C.max())
    tail = sum(gamma**t for t in range(6, T))
    assert min(c_lo, 0.0) * tail - 1e-12 <= V[T] - V[6] <= max(c_hi, 0.0) * tail + 1e-12
    # the library's reading past the logs: an interval that holds exactly the 6-step value at either end,
    # read as the T-step value (episodes that run to step 6), holds the exact T-step value
    span = sum(gamma**t for t in range(6))
    est_def = Estimand(6, gamma, target_horizon=T, possible_range=(-1e6, 1e6))
    width = 2 * (max(c_hi, 0.0) - min(c_lo, 0.0)) * tail
    for iv in ((V[6] - width, V[6]), (V[6], V[6] + width)):
        r = past_the_logs(ope.OPEResult("wdr", V[6], iv, 100.0, vs_logged=(0.0, 0.0),
                                        weight_diagnostics={"ess_fraction": 1.0}), est_def,
                          (c_lo * span, c_hi * span), "horizon", 100)
        assert r.comparable and r.interval[0] - 1e-12 <= V[T] <= r.interval[1] + 1e-12, (iv, r.interval, V[T])
        assert r.interval[1] - r.interval[0] == pytest.approx(width + (max(c_hi, 0.0) - min(c_lo, 0.0)) * tail)


def test_the_figure_shades_the_logged_costs_interval_and_names_the_paired_difference(tmp_path):
    """The paired difference is named only where WDR leads on the logging policy's own weights."""
    from offline_adp.evaluation.figures import Figures, ope_figure

    for m, shaded in ((BASE, True), ({**BASE, "ope": {**BASE["ope"], "wdr": _wdr(0.3, [-12.88, -12.57],
                                                                                  [-0.1, 0.25])}}, False)):
        m = {**m, "behaviour_value": {"mean": -12.9, "interval": [-13.5, -12.3]},
             "estimand": {**m["estimand"], "horizon": 100, "gamma": 0.95}}
        figs = Figures(tmp_path / str(shaded))
        ope_figure(figs, m, rank_estimators(m))
        caption = figs.items[0][1]
        assert ("[-0.1, 0.25] (not drawn), against 0" in caption) == shaded
        # the logged cost's own interval is shaded wherever it exists now: every verdict reads a side against it
        assert "Shaded: the logged cost's own 95% interval [-13.5, -12.3]" in caption


def test_compare_keeps_the_plain_order_of_shared_estimators():
    """Where one candidate promotes WDR and another does not, the shared estimators go by the plain
    order (WDR before WIS), in either order of the candidates."""
    from offline_adp.evaluation.compare import _common_estimator

    def case(frac):
        return {"estimand": {"possible_range": [-20.0, 0.0]}, "behaviour_value": {"mean": -12.9},
                "ope": {"fqe": {"estimate": 1e9}, "model": {"estimate": 1e9},
                        "wdr": _wdr(frac, [-12.9, -12.5], [-0.1, 0.2]), "dr": _wdr(frac, [-12.9, -12.4], [-0.1, 0.2]),
                        "wis": {"estimate": -12.7, "interval": [-13.4, -12.0], "level": 0.95}}}

    a, b = rank_estimators(case(0.3)), rank_estimators(case(1.0))
    assert b[0]["name"] == "wdr" and a[0]["name"] == "wdr" and not a[0]["on_policy"]
    assert _common_estimator([a, b]) == _common_estimator([b, a]) == "wdr"


def test_a_withdrawn_level_takes_the_paired_difference_with_it():
    from offline_adp.evaluation.summary import withdraw_levels

    m = withdraw_levels(copy.deepcopy(BASE), ["its states left the data"])
    w = m["ope"]["wdr"]
    assert w["level"] is None and "vs_logged" not in w and w["nominal_vs_logged"] == [-0.10, 0.25]
    assert rank_estimators(m)[0]["vs_logged"] is None


def test_without_a_paired_difference_nothing_is_read_past_the_logs():
    est_def = Estimand(3, 0.5, target_horizon=5, possible_range=(0.0, 10.0))
    r = _est("wdr", 1.0)
    r.vs_logged = None
    assert not confined({"fqe": _est("fqe", 1.0), "wdr": r}, est_def, (0.0, 3.5), "terminal", 20)["wdr"].comparable


@pytest.mark.parametrize("folds", [0, 2])
def test_the_paired_difference_needs_a_cross_fitted_q(folds):
    from offline_adp.evaluation.offpolicy import off_policy
    from offline_adp.simulate import collect
    from tests.test_eval_estimand import TABULAR_FQE

    mdp, pib, _ = problem(0.9, "mild")
    ds = collect(mdp, pib, 300, np.random.default_rng(1000), horizon=T)
    res = off_policy(ds, pib, fqe_params=TABULAR_FQE, ratio_regressor="tabular", n_boot=50, n_boot_fqe=10, seed=0,
                     psdp_folds=folds)
    w = res.estimates["wdr"]
    assert w.level is not None and ope.on_policy(w)  # the logging policy: every weight 1
    assert (w.vs_logged is not None) == (folds > 0)


def test_truncated_episodes_within_T_make_the_trajectory_estimators_not_comparable():
    """Episodes stopped before step T without a terminal state (truncated logs): IS, WIS, PDIS,
    WPDIS, DR, WDR and MIS sum each episode's own costs, zero after it stops, so they estimate
    less than the T-step value (a helper measured WDR at 6.19 [3.83, 8.83], labelled 95%,
    against a truth of 16.39 on 40-step logs cut at 2, 5 or 40 steps); FQE bootstraps at a
    truncated end and keeps its level; the logged cost is not the behaviour's T-step value."""
    from offline_adp.evaluation.estimand import short_episodes

    est_def = Estimand(40, 0.95, possible_range=(0.0, 1e3))
    names = ("fqe", "model", "is", "wis", "pdis", "wpdis", "dr", "wdr", "mis")
    est = {k: ope.OPEResult(k, 6.0, (4.0, 8.0), 100.0) for k in names}
    out = confined(est, est_def, (0.0, 1e3), "short", 60)
    for k in names:
        traj = k not in ("fqe", "model")
        assert out[k].comparable is not traj, k
        if traj:
            assert "stop before step 40 without a terminal state" in out[k].warnings[0]
    assert all(r.comparable for r in confined(est, est_def, (0.0, 1e3), "horizon", 60).values())
    # the count the logged cost's reason gives
    episode = np.repeat([0, 1, 2], [4, 2, 6])
    step = np.concatenate([np.arange(4), np.arange(2), np.arange(6)])
    em = ope.EpisodeMatrix.build(episode, step, 4)
    assert short_episodes(em, np.zeros(len(step), bool)) == 1
    # the verdict claims no side against a logged cost that is not the T-step value
    m = {"estimand": {"possible_range": [0.0, 1000.0]},
         "ope": {"fqe": {"estimate": 8.2, "interval": [7.1, 9.0], "level": 0.95}},
         "behaviour_value": {"mean": 15.0, "interval": [14.0, 16.0], "comparable": False,
                             "not_comparable": "2 of 60 logged episodes stop before step 40"},
         "behaviour": {"support_violations": {"fraction": 0.0}}}
    conv = {"verdict": "converged", "text": "fit converged"}
    v = verdict_line(m, rank_estimators(m), {"method": "recursion", "enough_data": True}, conv)
    assert v["performance"] == "unknown" and "2 of 60 logged episodes stop before step 40" in v["text"]
    m["rollout"] = {"policy": {"mean_discounted_cost": 3.0, "interval": [2.9, 3.1]}}
    v = verdict_line(m, rank_estimators(m), {"method": "recursion", "enough_data": True}, conv)
    assert v["performance"] == "unknown" and v["text"].startswith("not compared with the behaviour")


def test_the_logged_cost_has_a_student_t_interval_and_says_when_it_is_not_the_T_step_value():
    from scipy.stats import t as student_t

    from offline_adp.evaluation.offpolicy import behaviour_value

    em = ope.EpisodeMatrix.build(np.repeat([0, 1, 2], 4), np.tile(np.arange(4), 3), 4)
    cost = np.r_[np.ones(4), 2 * np.ones(4), 4 * np.ones(4)]
    G = np.array([4.0, 8.0, 16.0])  # gamma 1
    bv = behaviour_value(em, cost, 1.0, terminated=np.zeros(12, bool))
    half = student_t.ppf(0.975, 2) * G.std(ddof=1) / np.sqrt(3)  # 4.30 standard errors, not 1.96
    assert bv["se"] == pytest.approx(G.std(ddof=1) / np.sqrt(3))
    # clipped to what the costs allow: every episode costs between 4 x 1 and 4 x 4
    assert bv["interval"] == pytest.approx([max(G.mean() - half, 4.0), min(G.mean() + half, 16.0)]) == [4.0, 16.0]
    assert "clipped to the possible range [4, 16]" in bv["method"]
    assert "comparable" not in bv  # every episode runs to T
    # the third stops after 2 steps without a terminal state: its steps 2 and 3 count as 0
    em = ope.EpisodeMatrix.build(np.repeat([0, 1, 2], [4, 4, 2]), np.r_[np.arange(4), np.arange(4), np.arange(2)], 4)
    bv = behaviour_value(em, np.ones(10), 1.0, terminated=np.zeros(10, bool))
    assert bv["comparable"] is False and bv["not_comparable"].startswith("1 of 3 logged episodes stop before step 4")
    term = np.zeros(10, bool)
    term[9] = True  # it ended in a terminal state: its cost after that is 0 indeed
    assert "comparable" not in behaviour_value(em, np.ones(10), 1.0, terminated=term)


def test_past_the_logs_the_logged_cost_of_episodes_cut_at_T_is_not_the_behaviours_value():
    from offline_adp.evaluation.offpolicy import behaviour_value

    em = ope.EpisodeMatrix.build(np.repeat([0, 1], 4), np.tile(np.arange(4), 2), 4)
    cost, term = np.ones(8), np.zeros(8, bool)
    assert "comparable" not in behaviour_value(em, cost, 0.9, terminated=term, est_def=Estimand(4, 0.9))
    bv = behaviour_value(em, cost, 0.9, terminated=term, est_def=Estimand(4, 0.9, target_horizon=10))
    assert bv["comparable"] is False and "reads 10 steps" in bv["not_comparable"]
    bv = behaviour_value(em, cost, 0.9, terminated=term, est_def=Estimand(4, 0.9, form="infinite"))
    assert bv["comparable"] is False and "infinite-horizon value" in bv["not_comparable"]
    term[[3, 7]] = True  # both ended in a terminal state: their cost after it is 0 indeed
    assert "comparable" not in behaviour_value(em, cost, 0.9, terminated=term, est_def=Estimand(4, 0.9,
                                                                                                target_horizon=10))


def test_an_estimate_is_flagged_against_fqe_s_interval_as_quoted():
    """FQE's interval is clipped to the possible range before another estimate is checked
    against it: the warning quotes the interval the ranking shows (a tour run printed
    "outside the FQE interval [-1.653, 9.846]" beside FQE's [0, 9.846])."""
    from offline_adp.evaluation.estimand import as_quoted

    est_def = Estimand(40, 0.95, possible_range=(0.0, 20.0))
    est = {"fqe": ope.OPEResult("fqe", 3.0, (-1.653, 9.846), None), "is": ope.OPEResult("is", 0.0, (0.0, 5.0), 50.0),
           "wis": ope.OPEResult("wis", 12.0, (10.0, 14.0), 50.0)}
    out = as_quoted(est, est_def, (0.0, 20.0), "terminal", 60)
    assert out["fqe"].interval == (0.0, 9.846)
    assert not any("outside" in w for w in out["is"].warnings)  # 0 lies in [0, 9.846]
    assert "outside the FQE interval [0, 9.846]" in out["wis"].warnings
