"""The model rollouts' own interval (evaluation/model_bootstrap.py) and the rule that labels it.

Oracles: the lane-keeping simulator of tests/test_model_rollouts.py (its Monte-Carlo truth)
over independent data seeds for the coverage of the bootstrap interval; direct computation
for the resample and the interval's formula; synthetic metrics for the label and the verdict.
"""

from __future__ import annotations

import copy
from functools import partial

import numpy as np
import pytest
from scipy.stats import t as student

from offline_adp.evaluation.model_bootstrap import (
    MIN_LABEL_PARTICLES,
    bootstrap_interval,
    bootstrap_reading,
    model_estimate,
    resampled_rows,
)
from offline_adp.evaluation.model_rollouts import model_rollouts
from offline_adp.evaluation.summary import rank_estimators, verdict_line, withdraw_levels
from offline_adp.evaluation.verdict import left_states
from offline_adp.policies import EpsilonPolicy, UniformPolicy
from offline_adp.rollout import collect
from tests.test_model_rollouts import COAST, GAMMA, STABILISE, Lane, T, _truth


def test_a_resample_draws_whole_episodes_with_replacement():
    from offline_adp.data.dataset import TransitionDataset

    rng = np.random.default_rng(0)
    ds = collect(Lane(), UniformPolicy(3), 12, rng, horizon=30, source="x")
    a = ds.arrays()
    rows = np.sort(rng.choice(len(a.cost), len(a.cost) - 7, replace=False))  # a row sample, as above MAX_FIT_ROWS
    drawn, ep = resampled_rows(a, rows, np.random.default_rng(3))
    assert np.isin(drawn, rows).all()
    sizes = {e: (a.episode[rows] == e).sum() for e in np.unique(a.episode[rows])}
    for k in np.unique(ep):  # each replicate episode: one logged episode's sampled rows, in order
        r = drawn[ep == k]
        assert len(np.unique(a.episode[r])) == 1 and np.all(np.diff(r) > 0)
        assert len(r) == sizes[a.episode[r[0]]]
    assert len(np.unique(ep)) == len(sizes)  # as many draws as episodes
    assert isinstance(ds, TransitionDataset)


def test_the_interval_is_students_spread_plus_the_bootstrap_bias():
    r = np.array([1.0, 1.5, 2.0, 2.5, 3.0])
    lo, hi = bootstrap_interval(2.5, r, 0.95)
    half = student.ppf(0.975, 4) * r.std(ddof=1) + 0.5
    assert (lo, hi) == pytest.approx((2.5 - half, 2.5 + half))


def _lane_logs(seed: int):
    demo = collect(Lane(), EpsilonPolicy(STABILISE, 0.1), 12, np.random.default_rng(seed), horizon=T, source="d")
    explore = collect(Lane(), UniformPolicy(3), 6, np.random.default_rng(seed + 100), horizon=T, source="x",
                      episode_prefix="x")
    from offline_adp.data.dataset import TransitionDataset

    return TransitionDataset.concat([demo, explore])


def _boot(model, a, ranges, estimate, *, policy, seed):
    return bootstrap_reading(model, a, policy, T, GAMMA, estimate, n=400, level=0.95, seed=seed,
                             replicates=10)


@pytest.mark.parametrize("name, policy", [("stabilise", STABILISE), ("coast", COAST)])
def test_the_bootstrap_interval_covers_the_simulators_truth_over_data_seeds(name, policy):
    """Eight independent small logs (18 episodes): the interval holds the simulator's value
    at least 7 times of 8 (95% nominal; P[<= 6 of 8] = 0.6% at 95%), and it is not the
    particles' noise alone: the replicates spread."""
    truth = _truth(policy)
    covered, spreads = 0, []
    for seed in range(8):
        boot = partial(_boot, policy=policy, seed=seed)
        mr = model_rollouts(_lane_logs(seed), policy, T, GAMMA, n=400, seed=seed, bootstrap=boot)
        lo, hi = mr["bootstrap"]["interval"]
        covered += lo <= truth <= hi
        spreads.append(mr["bootstrap"]["spread"])
    assert covered >= 7, (name, covered)
    assert min(spreads) > 0


BASE = {
    "estimand": {"possible_range": [0.0, 100.0]},
    "ope": {"fqe": {"estimate": 9.0, "interval": [3.0, 20.0], "level": None, "level_note": "support left",
                    "model_rollouts": {"exit_mass": 0.02, "exit_share": 0.1, "n_particles": 1000}},
            "model": {"estimate": 6.0, "interval": [5.0, 7.0], "level": 0.95}},
    "behaviour_value": {"mean": 15.0, "interval": [14.0, 16.0]},
    "behaviour": {"support_violations": {"fraction": 0.3}},
}
IN_SUPPORT = {"method": "recursion", "enough_data": True}


def _mr(**kw):
    mr = {"estimate": 6.0, "exit_mass": 0.02, "n_particles": 1000, "fqe_interval": [3.0, 20.0],
          "bootstrap": {"interval": [5.0, 7.0], "method": "m"}}
    return {**mr, **kw}


def test_the_model_is_labelled_only_where_the_logs_validate_it():
    assert model_estimate(_mr(), 0.95).level == 0.95
    assert model_estimate(_mr(fqe_interval=[6.5, 30.0]), 0.95).level == 0.95  # overlapping is agreeing
    for why, mr in {"drifts past the data": _mr(exit_mass=0.2), "disagrees with FQE": _mr(fqe_interval=[8.0, 30.0]),
                    "nothing to check against": _mr(fqe_interval=None),
                    "too few particles": _mr(n_particles=MIN_LABEL_PARTICLES - 1)}.items():
        r = model_estimate(mr, 0.95)
        assert r.level is None and r.level_note, why
        assert r.interval == (5.0, 7.0)  # still shown
    assert model_estimate({"skipped": "lattice"}, 0.95) is None
    assert model_estimate({**_mr(), "bootstrap": {"skipped": "1 replicate"}}, 0.95) is None


def test_the_reading_past_the_data_widens_the_interval_by_its_own_size():
    r = model_estimate(_mr(past_data_cost=0.5), 0.95)
    assert r.interval == (4.5, 7.5) and r.level == 0.95
    # the overlap with FQE's interval is judged on the widened interval
    assert model_estimate(_mr(fqe_interval=[7.2, 30.0]), 0.95).level is None
    assert model_estimate(_mr(fqe_interval=[7.2, 30.0], past_data_cost=0.5), 0.95).level == 0.95


def test_a_model_interval_missing_fqes_own_bootstrap_interval_becomes_the_hull_of_both():
    """FQE's support bounds make its interval wide enough to overlap almost any reading; its
    bootstrap interval alone is what the logs hold. Where the model's interval misses it,
    the two readings disagree there, and the labelled interval holds both."""
    same = model_estimate(_mr(fqe_bootstrap_interval=[6.5, 9.0]), 0.95)  # overlapping: the model's own
    assert same.interval == (5.0, 7.0) and same.level == 0.95
    for fb, hull in (([7.5, 9.0], (5.0, 9.0)), ([2.0, 4.0], (2.0, 7.0))):  # above, below
        r = model_estimate(_mr(fqe_bootstrap_interval=fb), 0.95)
        assert r.interval == hull and r.level == 0.95 and r.estimate == 6.0
        assert any("hull of both" in w for w in r.warnings)
        assert r.hull == {"model": [5.0, 7.0], "fqe_bootstrap": list(fb)}  # what it is the hull of, recorded
        assert r.as_dict()["hull"] == r.hull
    assert same.hull is None and "hull" not in same.as_dict()
    # judged after the widening past the data: [4.5, 7.5] reaches [7.2, 9.0]
    assert model_estimate(_mr(fqe_bootstrap_interval=[7.2, 9.0], past_data_cost=0.5), 0.95).interval == (4.5, 7.5)
    # without a level from these checks (its support-bound interval missed too): shown as it is, not hulled
    r = model_estimate(_mr(fqe_interval=[8.0, 30.0], fqe_bootstrap_interval=[8.0, 9.0]), 0.95)
    assert r.level is None and r.interval == (5.0, 7.0)


def test_the_fqe_intervals_recorded_for_the_model_are_widened_by_the_truncation_bound():
    from offline_adp.evaluation.fqe_interval import with_fqe_interval
    from offline_adp.evaluation.ope import OPEResult

    fq = OPEResult("fqe", 5.0, (2.0, 20.0), 10.0, 0.95)
    mr = with_fqe_interval({"estimate": 6.0}, fq, 0.25, (4.0, 6.0))
    assert mr["fqe_interval"] == [1.75, 20.25] and mr["fqe_bootstrap_interval"] == [3.75, 6.25]
    assert with_fqe_interval({"estimate": 6.0}, fq, 0.25)["fqe_bootstrap_interval"] is None  # written: it dates it
    assert with_fqe_interval({"skipped": "x"}, fq, 0.25, (4.0, 6.0)) == {"skipped": "x"}


def test_an_evaluation_records_fqes_bootstrap_interval_from_before_its_support_bounds(tmp_path):
    """In a real evaluation, ``fqe_bootstrap_interval`` is FQE's bootstrap (percentile)
    interval and ``fqe_interval`` its hull with the support bounds, both widened by the same
    truncation bound: on logs where the support bounds do widen it, the two differ."""
    import json

    from offline_adp.evaluation.run import evaluate_run
    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    simulate("path_tracking", 8, 8, seed=11, horizon=100).save(tmp_path / "ds")  # gamma^100 < 0.01: stationary
    fit_run(tmp_path / "ds", tmp_path / "run", params={"gamma": 0.95, "n_iterations": 3,
                                                       "regressor_params": {"n_jobs": 1}})
    evaluate_run(tmp_path / "run", dataset=tmp_path / "ds", episodes=8, bootstrap=10, fqe_bootstrap=10,
                 model_particles=20)
    fqe = json.loads((tmp_path / "run" / "evaluation" / "metrics.json").read_text())["ope"]["fqe"]
    mr, sb = fqe["model_rollouts"], fqe["support_bounds"]
    assert "hull of the percentile" not in fqe["interval_method"]  # unshifted: the bootstrap interval is the percentile
    p_lo, p_hi = fqe["percentile_interval"]
    fb, fi = mr["fqe_bootstrap_interval"], mr["fqe_interval"]
    t = p_lo - fb[0]
    assert t >= 0 and fb[1] - p_hi == pytest.approx(t, abs=1e-12)
    assert sb["lower"] < p_lo or sb["upper"] > p_hi  # the support bounds widen FQE's interval here
    assert fi == pytest.approx([min(p_lo, sb["lower"]) - t, max(p_hi, sb["upper"]) + t], abs=1e-12)
    assert fi != pytest.approx(fb)


def _v(m, shift=IN_SUPPORT, conv=None):
    conv = conv or {"verdict": "still changing", "text": "fit did NOT converge"}
    m = withdraw_levels(m)
    return verdict_line(m, rank_estimators(m), shift, conv)


def test_a_labelled_model_leads_and_claims_a_side_where_only_the_actions_left_the_data():
    """The candidate chose actions the data rarely took (30%) and its fit did not converge: FQE
    cannot claim, the model (checked against FQE's per-action support bounds) can."""
    ranking = rank_estimators(withdraw_levels(BASE))
    assert ranking[0]["name"] == "model" and ranking[0]["level"] == 0.95
    v = _v(BASE)
    assert v["performance"] == "better" and v["text"].startswith("better than the behaviour: MODEL 6")
    assert v["outcome"] == "not converged"  # the colour still says the fit did not settle
    assert v["lines"][0].startswith("estimate: MODEL 6 [5, 7] (95%)")
    assert "LEFT the data's support: chooses actions" in v["lines"][2]  # said, and why it does not undermine
    assert "the model rollouts' reading holds there" in v["lines"][2]


def test_states_past_the_data_withdraw_the_models_level_and_its_claim():
    for shift in ({"method": "classifier", "separable_steps": 12, "n_steps": 200, "max_uncovered": 0.0,
                   "enough_data": True},
                  {"method": "classifier", "separable_steps": 0, "n_steps": 200, "max_uncovered": 0.4,
                   "enough_data": True}):
        assert left_states(BASE, shift)
        v = verdict_line(BASE, rank_estimators(BASE), shift, {"verdict": "converged", "text": "fit converged"})
        assert v["performance"] == "unknown" and "where the model extrapolates" in v["text"]
    drift = copy.deepcopy(BASE)
    drift["ope"]["fqe"]["model_rollouts"]["exit_mass"] = 0.3
    m = withdraw_levels(drift)
    assert m["ope"]["model"]["level"] is None
    assert _v(drift)["performance"] == "unknown"


def test_an_unlabelled_model_does_not_lead():
    m = copy.deepcopy(BASE)
    m["ope"]["model"]["level"] = None
    m["ope"]["fqe"]["level"] = 0.95
    m["behaviour"]["support_violations"]["fraction"] = 0.0
    ranking = rank_estimators(m)
    assert [e["name"] for e in ranking[:2]] == ["fqe", "model"]


def test_the_why_line_says_the_model_interval_is_the_hull_where_it_is():
    """A hulled model interval is asymmetric around its estimate; the why line says why, with
    both intervals, instead of claiming the two readings agree. A malformed record (metrics.json
    is untrusted) adds nothing and raises nothing."""
    m = copy.deepcopy(BASE)
    m["ope"]["model"]["interval"] = [5.0, 9.0]
    m["ope"]["model"]["hull"] = {"model": [5.0, 7.0], "fqe_bootstrap": [7.5, 9.0]}
    why = _v(m)["lines"][2]
    assert ("the model rollouts [5, 7] and FQE's bootstrap interval [7.5, 9] (before its support bounds) disagree on "
            "what the logs hold, so the interval spans both") in why
    assert "the model rollouts' reading holds there" not in why  # it would say they agree
    for bad in ("x", {"model": [5.0], "fqe_bootstrap": [7.5, 9.0]}, {"model": [5.0, "7"], "fqe_bootstrap": [7.5, 9.0]},
                {"model": [5.0, float("nan")], "fqe_bootstrap": [7.5, 9.0]}, {"model": [5.0, 7.0]}):
        m["ope"]["model"]["hull"] = bad
        assert "spans both" not in _v(m)["lines"][2]
