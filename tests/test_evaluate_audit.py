"""What ``evaluate`` prints where the logs cannot support it (an audit of 2026-11-29):

- fewer than ``MIN_LEVEL_EPISODES`` logged episodes: no interval carries a level;
- equal bootstrap replicates: no "shifted replicates" warning from their mean's rounding;
- a density-ratio fit that left ratios at 1: the shift headline says NOT MEASURED, not "no shift";
- a run evaluated on data with another action order, or on another dataset found under the
  relative path its run.json names: refused, naming both, before any estimator runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from offline_adp.data.dataset import read_dataset
from offline_adp.data.info import ActionTable
from offline_adp.errors import IncompatibleError
from offline_adp.evaluation import ope
from offline_adp.evaluation.fqe_interval import fqe_interval
from offline_adp.evaluation.summary import shift_verdict


def _result(name: str, level: float | None = 0.95) -> ope.OPEResult:
    return ope.OPEResult(name, 1.0, (0.5, 1.5), 3.0, level)


@pytest.mark.parametrize("n", [1, 2, ope.MIN_LEVEL_EPISODES - 1, ope.MIN_LEVEL_EPISODES])
def test_too_few_episodes_withdraw_every_level(n):
    out = ope.with_enough_episodes({"fqe": _result("fqe"), "model": _result("model"), "is": _result("is", None)}, n)
    if n >= ope.MIN_LEVEL_EPISODES:
        assert all(out[k].level == 0.95 for k in ("fqe", "model"))
    else:
        for k in ("fqe", "model"):
            assert out[k].level is None and f"{n} logged episode" in out[k].level_note
            assert out[k].warnings[0].startswith("no level:") and out[k].interval == (0.5, 1.5)
    assert out["is"].level is None and out["is"].level_note is None  # withheld before, for its own reason


def test_equal_replicates_are_not_shifted():
    est = 0.1 + 0.2  # replicates whose mean rounds away from the estimate by one ulp
    reps = [0.30000000000000004] * 7 + [0.3] * 3
    r = fqe_interval(est, reps, 12)
    assert not r.warnings and r.interval_method == "percentile bootstrap over episodes"


def test_a_ratio_fit_that_could_not_run_is_not_read_as_no_shift():
    per_step = [{"step": 0, "ess_fraction": 1.0}, {"step": 1, "ess_fraction": 1.0}]
    m = {"shift": {"recursion": {"per_step": per_step, "warnings": []}}, "worst_step": {"step": 1, "ess_fraction": 1.0}}
    assert shift_verdict(m)["enough_data"] and "NOT MEASURED" not in shift_verdict(m)["text"]
    m["shift"]["recursion"]["warnings"] = ["step 1: the ratio regression returned no positive mass; ratios set to 1"]
    v = shift_verdict(m)
    assert not v["enough_data"] and "NOT MEASURED at 1 step" in v["text"]
    m["shift"]["classifier"] = {"per_step": [{"step": 0, "ess_fraction": 1.0, "auc": 0.5}],
                                "warnings": ["step 0: 1 data and 1 policy states: too few for a classifier, ratio "
                                             "left at 1"]}
    v = shift_verdict(m)
    assert v["method"] == "classifier" and not v["enough_data"] and "NOT MEASURED" in v["text"]


def test_the_ratio_fits_list_what_they_could_not_measure_apart_from_their_words():
    """The summary reads the fits' own list of unmeasured steps, whatever a warning says."""
    from offline_adp.evaluation.shift import ratios_by_classifier, ratios_pooled

    rng = np.random.default_rng(0)
    obs, step = rng.normal(size=(60, 2)), np.repeat([0, 1, 2], 20)
    r = ratios_by_classifier(obs, step, [rng.normal(size=(20, 2)), rng.normal(size=(1, 2)), rng.normal(size=(9, 2))],
                             classifier="extra_trees", classifier_params={"n_estimators": 5})
    assert len(r.unmeasured) == 1 and r.unmeasured[0].startswith("step 1:") and r.unmeasured[0] in r.warnings
    assert (r.w[step == 1] == 1.0).all() and 0 in r.auc and 2 in r.auc
    one = ratios_pooled(obs[:20], obs[:20], np.zeros(20, np.int64), np.ones(20))
    assert one.unmeasured == one.warnings == ["one step only: nothing to pool"]
    per_step = [{"step": 0, "ess_fraction": 1.0}, {"step": 1, "ess_fraction": 1.0}]
    m = {"shift": {"recursion": {"per_step": per_step, **r.notes()}}, "worst_step": {"step": 1, "ess_fraction": 1.0}}
    m["shift"]["recursion"]["warnings"] = ["reworded"]  # the list decides, not the wording
    v = shift_verdict(m)
    assert not v["enough_data"] and "NOT MEASURED at 1 step(s) (step 1:" in v["text"]
    m["shift"]["recursion"] = {"per_step": per_step, "warnings": ["ratios set to 1 elsewhere"], "unmeasured": []}
    assert shift_verdict(m)["enough_data"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from offline_adp.runs import fit_run
    from offline_adp.simulate import simulate

    tmp = tmp_path_factory.mktemp("evaluate_audit")
    simulate("tabular", 10, 10, seed=3).save(tmp / "base")
    here = os.getcwd()
    os.chdir(tmp)
    try:  # the dataset named as typed at the fit: relative
        fit_run("base", "run", params={"n_iterations": 3, "regressor_params": {"n_estimators": 3, "n_jobs": 1}})
    finally:
        os.chdir(here)
    return tmp


def test_another_action_order_is_refused_wherever_evaluate_runs(fitted, tmp_path):
    from offline_adp.evaluation.run import evaluate_run

    ds = read_dataset(fitted / "base")
    at = ds.info.action_table
    df = ds.to_pandas()
    df["action"] = df["action"].map({0: 1, 1: 0}).fillna(df["action"]).astype("int32")
    swapped = type(ds).from_pandas(df, ds.info.replace(action_table=ActionTable((at.actions[1], at.actions[0],
                                                                                  *at.actions[2:]))))
    swapped.save(tmp_path / "swapped")
    with pytest.raises(IncompatibleError, match=r"fitted with the action table .*\(run.json\)"):
        evaluate_run(fitted / "run", dataset=tmp_path / "swapped", simulator="none")
    from offline_adp.simulate import simulate

    (tmp_path / "other").mkdir()
    simulate("tabular", 10, 10, seed=4).save(tmp_path / "other" / "base")  # other logs under the name run.json gives
    import json
    import shutil

    old_run = tmp_path / "old_run"  # a run written before run.json kept the path's absolute form
    shutil.copytree(fitted / "run", old_run)
    rj = json.loads((old_run / "run.json").read_text())
    rj.pop("dataset_resolved", None)
    (old_run / "run.json").write_text(json.dumps(rj))
    here = os.getcwd()
    os.chdir(tmp_path / "other")
    try:
        with pytest.raises(IncompatibleError, match="is not the data the run was fitted on"):
            evaluate_run(old_run, simulator="none")
        # a run fitted since finds its own logs from any directory (dataset_resolved)
        shutil.copytree(fitted / "run", tmp_path / "new_run")
        m = evaluate_run(tmp_path / "new_run", simulator="none")
        assert Path(m["dataset"]["path"]).resolve() == (fitted / "base").resolve()
    finally:
        os.chdir(here)


def test_the_summary_prints_small_costs_in_significant_digits():
    from offline_adp.evaluation.summary import _f

    assert (_f(2.45361), _f(-0.0123), _f(0.0), _f(4.975e-12), _f(-3.1e-5), _f(float("nan"))) == (
        "2.454", "-0.012", "0.000", "4.98e-12", "-3.1e-05", "n/a")


def test_rollouts_from_other_start_states_are_not_set_against_the_logged_cost():
    from offline_adp.evaluation.verdict import _simulator_side, start_states_check

    rng = np.random.default_rng(0)
    same = start_states_check(rng.normal(size=(60, 2)), rng.normal(size=(200, 2)))
    assert not same["differ"]
    hard = start_states_check(rng.normal(size=(60, 2)) + [0.0, 1.5], rng.normal(size=(200, 2)))
    assert hard["differ"] and hard["feature"] == 1
    ro = {"mean_discounted_cost": 2.6, "interval": [2.55, 2.65]}
    beh = {"mean": 2.97, "interval": [2.91, 3.02], "n_episodes": 60}
    side, text = _simulator_side(ro, beh, None, "unknown", "cannot tell", None, same)
    assert side == "better"
    side, text = _simulator_side(ro, beh, None, "unknown", "cannot tell", None, hard)
    assert side == "unknown" and "start from the simulator's start states" in text


def test_a_repeated_state_is_judged_by_its_own_action_counts():
    """Oracle: the logged counts. State 0 never saw action 2; a classifier's smoothing gave it mass."""
    from offline_adp.evaluation.behaviour import exact_state_support, support_violations

    obs = np.r_[np.zeros(10), np.ones(10), np.arange(2.0, 5.0)][:, None]  # two repeated states, three seen once
    action = np.r_[np.tile([0, 1], 5), np.tile([1, 2], 5), [0, 1, 2]]
    smooth = np.full((len(obs), 3), 1 / 3)
    probs = exact_state_support(obs, action, 3, smooth)
    np.testing.assert_allclose(probs[:10], [[0.5, 0.5, 0.0]] * 10)
    np.testing.assert_allclose(probs[10:20], [[0.0, 0.5, 0.5]] * 10)
    np.testing.assert_allclose(probs[20:], smooth[20:])  # seen once: the classifier's
    target = np.zeros((len(obs), 3))
    target[:, 2] = 1.0  # the policy always takes action 2
    v = support_violations(target, probs, np.zeros(len(obs), int))
    assert v["count"] == 10 and support_violations(target, smooth, np.zeros(len(obs), int))["count"] == 0


def test_compare_prints_small_costs_as_evaluate_does():
    from offline_adp.evaluation.compare import compare_lines

    cand = {"rank": 1, "name": "a", "estimate": 4.975e-12, "interval": [4.6e-12, 5.3e-12], "level_words": "95%",
            "truth": 5.0e-12, "outcome": "better", "fit": "converged", "support_left": False, "shift": "-"}
    text = "\n".join(compare_lines({"candidates": [cand], "estimand": "e", "estimator": "fqe",
                                    "dataset": {"path": "d"}}))
    assert "4.98e-12" in text and "[4.6e-12, 5.3e-12]" in text and "0.000" not in text


def test_the_logged_cost_interval_stays_within_what_the_costs_allow():
    """No episode's discounted cost lies outside ``[c_lo, c_hi] sum_t gamma^t``, so neither does the
    behaviour's value: its Student-t interval is clipped there (the truth is never cut off)."""
    from scipy.stats import t as student_t

    from offline_adp.evaluation.offpolicy import behaviour_value

    episode, step = np.repeat([0, 1, 2], 2), np.tile([0, 1], 3)
    cost = np.array([0.0, 0.0, 0.0, 0.0, 5.0, 5.0])  # episode costs 0, 0, 7.5 at gamma 0.5
    v = behaviour_value(ope.EpisodeMatrix.build(episode, step), cost, 0.5)
    half = float(student_t.ppf(0.975, 2)) * np.std([0, 0, 7.5], ddof=1) / np.sqrt(3)
    assert v["mean"] == pytest.approx(2.5) and 2.5 - half < 0 and 2.5 + half > 7.5  # the t-interval: past both ends
    assert v["interval"] == [0.0, 7.5] and "clipped to the possible range [0, 7.5]" in v["method"]
    one = behaviour_value(ope.EpisodeMatrix.build(np.zeros(2), np.arange(2)), np.array([1.0, 2.0]), 0.5)
    assert one["interval"] == [-np.inf, np.inf] and "clipped" not in one["method"]  # one episode: no interval
    # a constant cost: each episode's sum may differ from c * sum_t gamma^t by a rounding; the mean stays inside
    flat = behaviour_value(ope.EpisodeMatrix.build(np.repeat(np.arange(5), 200), np.tile(np.arange(200), 5)),
                           np.full(1000, 0.013), 1.0)
    assert flat["interval"][0] <= flat["mean"] <= flat["interval"][1]
    many = behaviour_value(ope.EpisodeMatrix.build(np.repeat(np.arange(20), 2), np.tile([0, 1], 20)),
                           np.random.default_rng(0).uniform(0.0, 1.0, 40), 0.5)
    assert "clipped" not in many["method"] and 0.0 < many["interval"][0] < many["mean"] < many["interval"][1] < 1.5


def test_the_headline_counts_the_separable_steps_the_warning_counts():
    """metrics.json keeps the AUCs exact (pandas' to_json kept 10 digits: 0.950000000004 read
    0.95, and the headline said 64 steps where the warning said 65)."""
    import pandas as pd

    from offline_adp.evaluation.metrics_file import frame_records
    from offline_adp.evaluation.shift import _separable_warning

    auc = {0: 0.5, 1: 0.95 + 4e-12, 2: 0.99, 3: 0.95}
    d = pd.DataFrame({"step": list(auc), "auc": list(auc.values()), "ess_fraction": [1.0, 0.5, 0.1, np.nan]})
    rows = frame_records(d)
    assert rows[1]["auc"] == 0.95 + 4e-12 and rows[3]["ess_fraction"] is None and type(rows[0]["step"]) is int
    said = _separable_warning(auc, 4)[0]
    v = shift_verdict({"shift": {"classifier": {"per_step": rows, "warnings": [said]}}})
    assert said.startswith("classifier AUC > 0.95 at 2 of 4 steps") and "AUC > 0.95 at 2 of 4 steps" in v["text"]
