"""Off-policy selection: ``offline-adp compare`` ranks candidate policies on the same logs."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from offline_adp.cli import main
from offline_adp.errors import InvalidArgumentError, RunDirectoryError
from offline_adp.evaluation.compare import compare_runs, selection_scores
from offline_adp.evaluation.compare_report import write_compare_report


def test_selection_scores_known_answers():
    truth = [1.0, 2.0, 3.0, 4.0]
    s = selection_scores([10.0, 20.0, 30.0, 40.0], truth)  # same order, other scale
    assert s["spearman"] == pytest.approx(1.0) and s["kendall"] == pytest.approx(1.0)
    assert s["regret_top1"] == 0.0 and s["top_pick_is_best"]
    s = selection_scores([4.0, 3.0, 2.0, 1.0], truth)  # reversed: picks the worst
    assert s["spearman"] == pytest.approx(-1.0) and s["regret_top1"] == pytest.approx(3.0)
    assert s["relative_regret_top1"] == pytest.approx(1.0)
    s = selection_scores([1.0, 3.0, 2.0, 4.0], truth)  # one swap in the middle
    assert s["spearman"] == pytest.approx(1 - 6 * 2 / (4 * 15)) and s["regret_top1"] == 0.0


@pytest.fixture(scope="module")
def candidates(tmp_path_factory, small_pt):
    root = tmp_path_factory.mktemp("cmp")
    small_pt.save(root / "ds")
    runs = []
    for k in (1, 4, 10):
        cfg = root / f"fqi{k}.toml"
        cfg.write_text(f"[fqi]\nmode = \"frozen\"\nn_iterations = {k}\n[fqi.regressor_params]\nn_estimators = 10\n")
        assert main(["fit", str(root / "ds"), "--config", str(cfg), "--out", str(root / f"fqi{k}"), "--quiet"]) == 0
        runs.append(root / f"fqi{k}")
    return root, runs


@pytest.mark.integration
def test_compare_ranks_candidates_with_simulator_truth(candidates, capsys):
    root, runs = candidates
    res = compare_runs(runs, evaluate_params={"n_episodes": 30, "n_boot": 20, "n_boot_fqe": 0})
    c = res["candidates"]
    assert len(c) == 3 and {x["run"] for x in c} == {str(r) for r in runs}
    ranked = [x for x in c if x["rank"] is not None]
    assert [x["rank"] for x in ranked] == list(range(1, len(ranked) + 1))
    assert all(a["estimate"] <= b["estimate"] for a, b in zip(ranked, ranked[1:], strict=False))
    assert all(x["truth"] is not None and x["shift"] for x in c)
    sel = res["selection"]
    # the scores are recomputed from the candidates' own numbers (an independent check of the bookkeeping)
    again = selection_scores([x["estimate"] for x in ranked], [x["truth"] for x in ranked])
    assert sel["spearman"] == pytest.approx(again["spearman"])
    assert sel["regret_top1"] == pytest.approx(ranked[0]["truth"] - min(x["truth"] for x in ranked))
    assert -1.0 <= sel["spearman"] <= 1.0 and sel["regret_top1"] >= 0.0
    # the CLI reuses the matching evaluations and prints the table
    out_json = root / "cmp.json"
    assert main(["compare", *map(str, runs), "--json", str(out_json), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Spearman" in out
    # the regret is of the top pick only where there is one (else of the lowest estimate, said so)
    who = "the top pick" if res.get("top_pick") else "the lowest estimate (not a pick)"
    assert f"regret of {who} " in out and ("no top pick" in out) == (not res.get("top_pick"))
    assert json.loads(out_json.read_text())["selection"]["spearman"] == pytest.approx(sel["spearman"])
    assert np.isfinite(sel["kendall"])
    # ... and writes its HTML report next to the JSON: the ranking figure, every candidate, the truth
    page = (root / "cmp.html").read_text()
    assert str(root / "cmp.html") in out
    assert re.search(r'<figure id="ranking"><img alt="ranking" src="data:image/png;base64,', page)
    assert all(x["name"] in page for x in c) and "simulator truth" in page and "Spearman" in page
    assert "CVaR_0.1" in page  # each candidate's cost distribution (the rollouts') beside its mean
    for x in json.loads(out_json.read_text())["candidates"]:
        ro = x["cost_distribution"]["rollouts"]
        assert ro["cvar"] >= ro["mean"] and ro["mean"] == pytest.approx(x["truth"])


def test_compare_needs_two_runs_on_the_same_logs(candidates, tmp_path):
    _, runs = candidates
    with pytest.raises(InvalidArgumentError, match="at least two"):
        compare_runs(runs[:1])
    with pytest.raises(RunDirectoryError, match="not a run directory"):
        compare_runs([runs[0], tmp_path])
    assert main(["compare", str(runs[0]), str(tmp_path)]) == 2


def test_compare_refuses_an_unknown_estimator_before_any_work(tmp_path):
    from offline_adp.evaluation.compare import compare_runs

    runs = [tmp_path / "a", tmp_path / "b"]
    for r in runs:
        (r / "model").mkdir(parents=True)
    with pytest.raises(InvalidArgumentError, match="unknown estimator 'fqee'"):
        compare_runs(runs, estimator="fqee")


def test_report_path_defaults(tmp_path):
    from offline_adp.evaluation.compare import report_path

    runs = [tmp_path / "runs" / "a", tmp_path / "runs" / "b"]
    assert report_path(runs, None, "x/y.html") == tmp_path.__class__("x/y.html")
    assert report_path(runs, str(tmp_path / "c.json"), None) == tmp_path / "c.html"
    assert report_path(runs, str(tmp_path / "c.html"), None) == tmp_path / "c.html.html"  # never the JSON itself
    assert report_path(runs, None, None) == (tmp_path / "runs").resolve() / "compare.html"


def _dist(mean, cvar):
    return {"mean": mean, "cvar": cvar, "alpha": 0.1, "n_episodes": 50, "ess": 50.0, "median": mean, "q90": cvar,
            "min": 0.0, "max": cvar + 1, "quantiles": {"levels": [0.0, 0.5, 0.9, 1.0],
                                                       "values": [0.0, mean, cvar, cvar + 1]}}


def _candidate(name, rank, est, iv, truth, left, performance, fit, logs):
    return {"run": f"/r/{name}", "name": name, "algorithm": "fqi", "estimator": "fqe", "estimate": est, "interval": iv,
            "reliability": "reliable", "shift": "classifier ratios (simulator): ...", "support_left": left,
            "convergence": f"fit {fit}", "truth": truth, "truth_interval": [truth - 0.1, truth + 0.1],
            "verdict": f"{name} verdict", "performance": performance, "fit_verdict": fit, "rank": rank,
            "cost_distribution": {"alpha": 0.1, "rollouts": _dist(truth, truth + 2), "logs": logs}}


def test_compare_report_shows_what_the_comparison_says(tmp_path):
    """The HTML writer on a known comparison: candidates in rank order, the behaviour's cost,
    the truth, the verdict colour of each (weakest clause), the CVaR, and 'cannot tell'."""
    res = {"dataset": {"path": "/d", "fingerprint": "f"}, "estimator": "fqe", "estimand": "expected cost",
           "method": "ranked", "behaviour": {"mean": 9.0, "interval": [8.5, 9.5], "episodes": 40,
                                              "cost_distribution": _dist(9.0, 14.0)},
           "candidates": [
               _candidate("good", 1, 3.0, [2.5, 3.5], 3.1, False, "better", "converged",
                          {**_dist(3.0, 4.0), "usable": True}),
               _candidate("doubt", 2, 4.0, [3.0, 5.0], 4.2, True, "unknown", "converged",
                          {"usable": False, "reason": "effective sample size 1.2 of 40 episodes"}),
               _candidate("bad", 3, 12.0, [11.0, 13.0], 12.5, False, "worse", "still changing", None)],
           "selection": {"spearman": 1.0, "kendall": 1.0, "regret_top1": 0.0, "relative_regret_top1": 0.0,
                         "top_pick_is_best": True, "n_candidates": 3, "method": "rollouts"}}
    out = write_compare_report(res, tmp_path / "cmp.html")
    page = out.read_text()
    figs = re.findall(r'<figure id="([a-z_]+)"><img alt="[a-z_]+" src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert {n for n, _ in figs} == {"ranking", "cost_distribution"}
    for _, data in figs:
        assert base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n"
    assert page.index("1. good") < page.index("2. doubt") < page.index("3. bad")
    assert "<b>good</b>: 3" in page and "9 [8.5, 9.5] over 40 episodes" in page and "Spearman 1.00" in page
    colour = {name.lower(): cls for cls, name in re.findall(
        r"<div class='verdict (good|meh|bad|stale)'><span class='outcome \w+'>[a-z ]+</span>(\w+) verdict</div>", page)}
    assert colour == {"good": "good", "doubt": "meh", "bad": "bad"}
    assert "cannot tell from these logs: effective sample size 1.2" in page and "LEFT the data" in page
    assert "CVaR_0.1 (simulator)" in page and "None" not in re.sub(r"<img[^>]*>", "", page)


def test_a_stored_evaluation_before_the_past_data_allowance_is_redone():
    from offline_adp.evaluation.compare import _same_model_rollouts

    mr = {"n_particles": 1000, "trust_radius": 0.3, "past_data_cost": 0.1}
    assert _same_model_rollouts({"ope": {"fqe": {"model_rollouts": mr}}}, 1000)
    old = {k: v for k, v in mr.items() if k != "past_data_cost"}
    assert not _same_model_rollouts({"ope": {"fqe": {"model_rollouts": old}}}, 1000)
    # recorded FQE's interval but not its bootstrap interval: made before the hull where they disagree
    before_hull = {**mr, "fqe_interval": [1.0, 20.0]}
    assert not _same_model_rollouts({"ope": {"fqe": {"model_rollouts": before_hull}}}, 1000)
    for fb in ([2.0, 3.0], None):  # written by this version (None: FQE had no bootstrap interval)
        assert _same_model_rollouts({"ope": {"fqe": {"model_rollouts": {**before_hull,
                                                                         "fqe_bootstrap_interval": fb}}}}, 1000)


def test_without_a_top_pick_the_regret_is_said_of_the_lowest_estimate():
    """'no top pick' followed by 'regret of the top pick' contradicted itself (a newcomer's
    walk through the README's tour)."""
    from offline_adp.evaluation.compare import compare_lines

    cand = {"name": "a", "rank": 1, "estimate": 1.0, "interval": [0.5, 1.5], "truth": 1.1, "support_left": False,
            "shift": "s", "outcome": "cannot tell", "fit": "converged"}
    sel = {"spearman": 1.0, "kendall": 1.0, "regret_top1": 0.0, "relative_regret_top1": 0.0,
           "top_pick_is_best": True}
    res = {"dataset": {"path": "d"}, "estimator": "fqe", "estimand": "e", "candidates": [cand], "selection": sel,
           "top_pick": None, "cannot_separate": ["a and b overlap"]}
    text = "\n".join(compare_lines(res))
    assert "no top pick" in text and "regret of the lowest estimate (not a pick) 0.000" in text
    assert "top pick 0" not in text
    res["top_pick"] = "a"
    assert "regret of the top pick 0.000" in "\n".join(compare_lines(res))


def test_a_stored_evaluation_replaced_by_compare_is_named_with_the_reason():
    from offline_adp.evaluation.compare import _why_again

    fp, mr = "abc", {"ope": {"fqe": {"model_rollouts": {"skipped": "model_particles=0: model rollouts turned off"}}}}
    assert _why_again(None, fp, None, 0) == ""  # never evaluated: nothing replaced
    m = {"dataset": {"fingerprint": "other"}, "simulator": "none", **mr}
    assert "other logs: its evaluation/ is replaced" in _why_again(m, fp, None, 0)
    m = {"dataset": {"fingerprint": fp}, "simulator": "none", **mr}
    assert "simulator 'none', not 'path_tracking'" in _why_again(m, fp, "path_tracking", 0)
    assert "model rollouts are not this one's (500 particles" in _why_again(m, fp, None, 500)


def test_a_share_over_the_support_rule_never_reads_as_the_rule_itself():
    from offline_adp.evaluation.verdict import SUPPORT_FRACTION, _share_over

    assert SUPPORT_FRACTION == 0.05
    assert _share_over(0.0517) == "5.2%" and _share_over(0.0549) == "5.5%"
    assert _share_over(0.0551) == "6%" and _share_over(0.63) == "63%"
