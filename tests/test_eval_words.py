"""Evaluation a person can act on (issue #42): words, labels, colours and ``compare``.

Synthetic metrics with known answers: an interval without a level (withdrawn where the
policy left the data's support, or never measured) is never printed as "95%" in the CLI,
the report or the comparison; the verdict's colour is its outcome word's; the verdict
compares with the demonstrator and counts failures; the fit's discount is noted when the
evaluation uses another; warnings are gathered with their sources; and a comparison of two
candidates whose intervals overlap says the logs cannot separate them (no top pick).
"""

from __future__ import annotations

import copy
import html
import json
import re

import pytest

from offline_adp.evaluation.compare import compare_lines, separation
from offline_adp.evaluation.compare_report import write_compare_report
from offline_adp.evaluation.report import _summary_box, verdict_colour, verdict_html
from offline_adp.evaluation.summary import (
    OUTCOME_CLASS,
    gather_warnings,
    headline,
    outcome_of,
    rank_estimators,
    summary_lines,
    verdict_line,
    withdraw_levels,
)

CONVERGED = {"verdict": "converged", "text": "fit converged"}
STALE = {"verdict": "still changing", "text": "fit did NOT converge"}

# a policy that left the data's support (classifier: separable at 12 of 200 steps), FQE's interval below the behaviour
LEFT = {
    "estimand": {"quantity": "expected cost", "possible_range": [0.0, 1000.0], "gamma": 0.95},
    "ope": {"fqe": {"estimate": 4.348, "interval": [2.607, 9.963], "level": 0.95, "warnings": ["w1", "w2"]},
            "is": {"estimate": 3.0, "interval": [0.1, 40.0], "level": 0.95, "degenerate": True, "ess": 1.2,
                   "warnings": ["degenerate"]}},
    "behaviour_value": {"mean": 20.3, "interval": [18.0, 22.6], "episodes": 135},
    "behaviour": {"support_violations": {"fraction": 0.05}, "warnings": ["clipped"]},
    "shift": {"classifier": {"per_step": [{"step": 0, "ess_fraction": 0.5, "auc": 0.6, "uncovered": 0.0},
                                          {"step": 1, "ess_fraction": 0.02, "auc": 0.99, "uncovered": 0.58}],
                             "warnings": ["thin step"]}},
    "warnings": ["no options recorded"],
    "dataset": {"transitions": 100, "episodes": 10, "sources": {}},
}


def _rollout(policy, demo, pf=0, df=0):
    return {"policy": {"mean_discounted_cost": policy[0], "interval": [policy[1], policy[2]], "n_episodes": 50,
                       "failures": pf},
            "demonstrator": {"mean_discounted_cost": demo[0], "interval": [demo[1], demo[2]], "n_episodes": 50,
                             "failures": df}}


def _no_95(text: str) -> None:
    """No 95% claimed (the words denying it, "not a 95% interval", are no claim)."""
    assert "95%" not in text.replace("not a 95% interval", ""), text


def test_a_withdrawn_level_is_never_printed_as_95():
    m = copy.deepcopy(LEFT)
    w = withdraw_levels(m)
    fq = w["ope"]["fqe"]
    assert fq["level"] is None and fq["nominal_level"] == 0.95 and "left the data's support" in fq["level_note"]
    assert fq["withdrawn_by"] == "support" and "where the value model extrapolates" in fq["level_note"]
    assert m["ope"]["fqe"]["level"] == 0.95  # the input is not changed
    m2 = copy.deepcopy(LEFT)
    m2["ope"]["model"] = {**m2["ope"]["fqe"], "method": "model"}  # MODEL's own words: no value model
    note = withdraw_levels(m2)["ope"]["model"]["level_note"]
    assert "where the model of the logged dynamics extrapolates" in note and "value model" not in note
    assert withdraw_levels(w) == w  # idempotent
    h = headline(m)
    assert h["best"] is None  # an interval without a level is never the quoted best
    lines = summary_lines(m)
    off = next(ln for ln in lines if ln.startswith("off-policy"))
    assert "[2.607, 9.963] (no level" in off
    for ln in lines:
        _no_95(ln)
    v = next(ln for ln in lines if ln.startswith("verdict:"))
    assert "FQE 4.348 vs logged 20.3 [18, 22.6] would say better" in v and "[2.607" not in v  # said, never claimed
    box = _summary_box(m, h)
    _no_95(re.sub(r"<[^>]+>", "", box))
    assert "(no level)" in box


def test_a_level_null_interval_is_never_printed_as_95():
    m = copy.deepcopy(LEFT)
    m["shift"] = {}
    m["behaviour"]["support_violations"]["fraction"] = 0.0
    m["ope"]["fqe"]["level"] = None  # e.g. continuous commands: coverage not measured
    lines = summary_lines(m)
    for ln in lines:
        _no_95(ln)
    assert any("no level" in ln for ln in lines)


def test_levels_are_written_as_they_are_in_the_cli_when_they_hold():
    m = copy.deepcopy(LEFT)
    m["shift"] = {}
    m["behaviour"]["support_violations"]["fraction"] = 0.0
    m["worst_step"] = {"step": 3, "ess_fraction": 0.4}
    off = next(ln for ln in summary_lines(m) if ln.startswith("off-policy"))
    assert "[2.607, 9.963] (95%)" in off


@pytest.mark.parametrize("perf, fit, demo, word", [
    ("better", "converged", None, "better"), ("worse", "converged", None, "worse"),
    ("unknown", "converged", None, "cannot tell"), ("indistinguishable", "converged", None, "cannot tell"),
    ("better", "still changing", None, "not converged"), ("worse", "diverging", None, "worse"),
    ("better", "converged", "worse", "worse"), ("better", "converged", "indistinguishable", "better"),
])
def test_the_colour_is_the_outcome_words(perf, fit, demo, word):
    assert outcome_of(perf, fit, demo) == word
    v = {"performance": perf, "against_demonstrator": demo, "text": "x"}
    assert verdict_colour(v, {"verdict": fit}) == OUTCOME_CLASS[word]
    box = verdict_html({**v, "outcome": word}, {"verdict": fit})
    assert box.startswith(f"<p class='verdict {OUTCOME_CLASS[word]}'><span class='outcome {OUTCOME_CLASS[word]}'>"
                          f"{word}</span>")
    assert len(set(OUTCOME_CLASS.values())) == 4  # one colour per outcome


def test_the_cli_verdict_line_carries_the_outcome_word_and_its_colour():
    m = copy.deepcopy(LEFT)
    m["rollout"] = _rollout((3.544, 3.403, 3.684), (5.494, 5.2, 5.8))
    line = next(ln for ln in summary_lines(m) if ln.startswith("verdict:"))
    assert line.startswith("verdict: [better] better than the behaviour; better than the demonstrator in the simulator")
    coloured = next(ln for ln in summary_lines(m, colour=True) if ln.startswith("verdict:"))
    assert "\x1b[1;32m[better]\x1b[0m" in coloured  # green, as the report's box


def test_the_verdict_against_the_demonstrator_with_failures():
    """The issue's pt-fqi5: 6.843 vs demonstrator 4.608, failures 3 vs 0, behaviour 13.28."""
    m = copy.deepcopy(LEFT)
    m["behaviour_value"]["mean"] = 13.28
    m["rollout"] = _rollout((6.843, 6.2, 7.5), (4.608, 4.4, 4.8), pf=3, df=0)
    h = headline(m)
    v = h["verdict"]
    assert v["outcome"] == "worse" and v["against_demonstrator"] == "worse"
    assert v["text"].startswith("WORSE than the demonstrator (better than the behaviour) in the simulator")
    assert "failures 3 vs 0 (demonstrator): the policy fails more often" in v["text"]
    assert verdict_colour(v, h["convergence"]) == "bad"
    # cheaper than the demonstrator but failing more often is not "better"
    m["rollout"] = _rollout((3.0, 2.9, 3.1), (4.608, 4.4, 4.8), pf=3, df=0)
    assert headline(m)["verdict"]["outcome"] == "cannot tell"


def test_the_discount_note():
    m = copy.deepcopy(LEFT)
    m["discount"] = {"fit": 0.8, "evaluation": 0.95, "evaluation_source": "the dataset's"}
    h = headline(m)
    assert "fitted with gamma 0.8" in h["discount_note"] and "uses gamma 0.95" in h["discount_note"]
    assert any(ln.startswith("discount: the policy was fitted with gamma 0.8") for ln in summary_lines(m))
    assert "Discount" in _summary_box(m, h)
    m["discount"]["fit"] = 0.95
    assert headline(m)["discount_note"] is None


def test_fit_discount_is_read_from_the_model(tmp_path):
    from offline_adp.evaluation.run import fit_discount

    (tmp_path / "model").mkdir()
    assert fit_discount(tmp_path) is None and fit_discount(None) is None
    (tmp_path / "model" / "params.json").write_text(json.dumps({"gamma": None}))
    assert fit_discount(tmp_path) is None
    (tmp_path / "model" / "q.json").write_text(json.dumps({"gamma": 0.8}))
    assert fit_discount(tmp_path) == 0.8


def test_warnings_gathered_with_their_sources():
    ws = gather_warnings(LEFT)
    assert {"source": "evaluation", "message": "no options recorded"} in ws
    assert {"source": "ope.fqe", "message": "w1"} in ws and {"source": "ope.is", "message": "degenerate"} in ws
    assert {"source": "behaviour", "message": "clipped"} in ws and {"source": "shift.classifier",
                                                                    "message": "thin step"} in ws
    assert len(ws) == 6
    again = {**LEFT, "warnings": ws}
    assert headline(again)["n_warnings"] == 6  # gathered once, not counted twice
    assert any(
        ln.startswith("6 warnings (metrics.json 'warnings', each with its source") for ln in summary_lines(again)
    )


def _cand(name, rank, est, iv, outcome="cannot tell", fit="converged", level=0.95):
    return {"run": f"/tmp/runs/{name}", "name": name, "algorithm": "fqi", "estimator": "fqe", "estimate": est,
            "interval": iv, "level": level, "level_words": "95%" if level else "no level",
            "reliability": "reliable" if level else "no interval", "shift": "ratio recursion (logs only)",
            "support_left": False, "convergence": f"fit {fit}", "truth": None, "truth_interval": None,
            "verdict": f"{name} verdict", "performance": "unknown", "outcome": outcome, "fit_verdict": fit,
            "fit": fit, "rank": rank, "cost_distribution": None}


def test_compare_of_overlapping_candidates_names_no_top_pick(tmp_path):
    """The issue's case: [0, 61.7] and [0, 69.3] from the logs alone got 'Top pick car2d'."""
    cands = [_cand("car2d", 1, 30.0, [0.0, 61.7]), _cand("car3d", 2, 35.0, [0.0, 69.3], fit="still changing",
                                                             outcome="not converged")]
    for c in cands:
        c["run"] = str(tmp_path / "runs" / c["name"])
    sep = separation(cands)
    assert len(sep) == 1 and not sep[0]["separated"] and "cannot separate car2d and car3d" in sep[0]["text"]
    res = {"dataset": {"path": str(tmp_path / "ds"), "fingerprint": "f"}, "estimator": "fqe",
           "estimand": "expected cost", "method": "ranked",
           "behaviour": {"mean": 50.0, "interval": [45.0, 55.0], "episodes": 40},
           "candidates": cands, "separation": sep, "top_pick": None, "cannot_separate": [sep[0]["text"]]}
    lines = compare_lines(res)
    assert any(ln.startswith("no top pick: the logs cannot separate car2d and car3d") for ln in lines)
    assert not any("top pick: car2d" in ln for ln in lines)
    page = write_compare_report(res, tmp_path / "cmp.html").read_text()
    text = re.sub(r"<img[^>]*>", "", page)
    assert "Top pick</th><td><span" in text
    assert "<b>no top pick</b></span> The logs cannot separate car2d and car3d" in text
    assert "<b>car2d</b>" not in text
    assert "50 [45, 55] over 40 episodes" in text
    assert "Shaded: the logged cost&#x27;s own 95% interval [45, 55]" in page or \
        "Shaded: the logged cost's own 95% interval [45, 55]" in page  # the ranking figure's caption
    # one logged episode (metrics.json: [null, null]) crashed the page; a truncated log says why it is not the value
    res["behaviour"] = {"mean": 50.0, "interval": [None, None], "episodes": 1}
    assert "(no interval: one episode)" in write_compare_report(res, tmp_path / "c1.html").read_text()
    res["behaviour"] = {"mean": 50.0, "interval": [45.0, 55.0], "episodes": 40, "comparable": False,
                        "not_comparable": "3 of 40 logged episodes stop before step 100"}
    page = html.unescape(write_compare_report(res, tmp_path / "c2.html").read_text())
    assert "not the behaviour's value of the estimand: 3 of 40 logged episodes" in page
    caption = re.search(r"<figure id=\"ranking\">.*?<figcaption>(.*?)</figcaption>", page, re.S).group(1)
    assert "simulator" not in caption and "black crosses" not in caption  # none drawn: none mentioned
    assert "amber cannot tell" in caption
    assert "fit converged?" in text and "still changing" in text  # the convergence column
    assert "<td class='verdict stale'><b>not converged</b></td>" in text  # its colour
    assert str(tmp_path) not in text and "(runs/car2d)" in text  # relative to the report's folder
    # separated intervals with levels: a top pick
    far = [_cand("a", 1, 3.0, [2.0, 4.0]), _cand("b", 2, 9.0, [8.0, 10.0])]
    assert separation(far)[0]["separated"]
    # an interval without a level separates nothing
    assert not separation([far[0], {**far[1], "level": None}])[0]["separated"]


def test_compare_shows_the_demonstrator_and_levels_as_they_are(tmp_path):
    cands = [_cand("a", 1, 3.0, [2.0, 4.0], outcome="better"), _cand("b", 2, 9.0, [1.0, 19.0], level=None)]
    cands[1]["support_left"] = True
    cands[1]["discount_note"] = "the policy was fitted with gamma 0.8, the evaluation uses gamma 0.95 (the dataset's)"
    res = {"dataset": {"path": "/tmp/ds", "fingerprint": "f"}, "estimator": "fqe", "estimand": "expected cost",
           "method": "ranked", "behaviour": {"mean": 12.0}, "candidates": cands, "separation": separation(cands),
           "top_pick": None, "cannot_separate": [],
           "demonstrator": {"mean": 5.0, "interval": [4.8, 5.2], "failures": 0, "simulator": "path_tracking",
                            "n_episodes": 50}}
    page = re.sub(r"<img[^>]*>", "", write_compare_report(res, tmp_path / "c.html").read_text())
    assert "Demonstrator (simulator)</th><td>5 [4.8, 5.2], failures 0 over 50 episodes" in page
    assert "[1, 19] (no level)" in page and "[1, 19] (95%)" not in page
    assert "cannot separate a and b: b has no interval with a level" in page
    lines = compare_lines(res)
    assert any(ln.startswith("demonstrator (path_tracking simulator): 5.000, failures 0") for ln in lines)
    assert any(ln.startswith("b: the policy was fitted with gamma 0.8") for ln in lines) and "Discount (b)" in page


def test_verdict_rules_still_claim_with_a_level():
    m = {"estimand": {"possible_range": [0.0, 1000.0]},
         "ope": {"fqe": {"estimate": 8.2, "interval": [7.1, 9.0], "level": 0.95}},
         "behaviour_value": {"mean": 15.0, "interval": [14.0, 16.0]},
         "behaviour": {"support_violations": {"fraction": 0.0}}}
    v = verdict_line(m, rank_estimators(m), {"method": "recursion", "enough_data": True}, CONVERGED)
    assert v["outcome"] == "better" and "its 95% interval lies below" in v["text"]
    v = verdict_line(m, rank_estimators(m), {"method": "recursion", "enough_data": True}, STALE)
    assert v["outcome"] == "not converged"


def test_the_simulator_s_verdict_says_whether_the_logs_alone_agree():
    """Where the logs alone claimed a side and the simulator confirms it, the verdict says so
    (it said nothing, as if the logs had not been asked); where they could not tell, that."""
    m = {"estimand": {"possible_range": [0.0, 1000.0]},
         "ope": {"fqe": {"estimate": 8.2, "interval": [7.1, 9.0], "level": 0.95}},
         "behaviour_value": {"mean": 15.0, "interval": [14.0, 16.0]},
         "behaviour": {"support_violations": {"fraction": 0.0}},
         "rollout": _rollout((8.0, 7.5, 8.5), (9.0, 8.8, 9.2))}
    shift = {"method": "recursion", "enough_data": True}
    v = verdict_line(m, rank_estimators(m), shift, CONVERGED)
    assert "in the simulator" in v["text"] and "(from the logs alone: better too, " in v["text"]
    assert v["lines"][1].endswith("; from the logs alone: better too")
    m["ope"]["fqe"]["interval"] = [7.1, 15.5]  # overlaps the behaviour's: not distinguishable from the logs
    v = verdict_line(m, rank_estimators(m), shift, CONVERGED)
    assert "better too" not in v["text"] and "(from the logs alone: not distinguishable from the behaviour" in v["text"]
    assert v["lines"][1].endswith("; from the logs alone: not distinguishable from the behaviour")
    m["ope"]["fqe"]["level"] = None  # no level: the logs cannot tell
    v = verdict_line(m, rank_estimators(m), shift, CONVERGED)
    assert v["lines"][1].endswith("; from the logs alone: cannot tell")


def test_the_psdp_bound_is_printed_as_an_estimate_never_as_a_bound():
    """The plug-in PSDP bound multiplies estimated factors and has fallen below the true gap
    (issue #42): the report must not print it as a bound."""
    from offline_adp.evaluation.report import PSDP_LABELS, psdp_section

    m = {"psdp_bound": {"eps": [0.1, 0.2], "label": "plug-in estimate (Bagnell et al. 2003, Theorem 2)",
                        "references": {"self": {"per_step": 0.5, "averaged": 0.6, "eps_sum": 0.3,
                                                "ratio_ucb_max": 1.5, "ratio_ucb_step": 1, "pooled_ratio_ucb": 2.0}}}}
    html = "".join(psdp_section(m, {"shift": {}, "verdict": {}}))
    assert "not a bound" in html
    assert not any(v.lower().startswith("bound") for v in PSDP_LABELS.values())
    assert "estimate: sum_t eps_t UCB_t" in html


def test_the_headline_is_three_lines_estimate_verdict_why():
    """Issue #42: the estimate with its interval and its true level, the verdict (against the
    demonstrator with failures where a simulator has one) without its reasons, one line of why."""
    m = copy.deepcopy(LEFT)
    est, verdict, why = headline(m)["verdict"]["lines"]
    assert est == "estimate: FQE 4.348 [2.607, 9.963] (no level)"  # the level withdrawn: support left
    assert verdict.startswith("cannot tell from these logs") and "would say better" in verdict
    assert ", but" not in verdict  # the reasons are the why line's
    assert why.startswith("why: policy LEFT the data's support")
    assert why.endswith("; fit convergence unknown (no run directory)")
    lines = summary_lines(m)
    at = lines.index(f"verdict: [cannot tell] {verdict}")  # the CLI: the verdict, then its why
    assert lines[at + 1] == why
    m["rollout"] = _rollout((6.843, 6.2, 7.5), (4.608, 4.4, 4.8), pf=3, df=0)
    est, verdict, why = headline(m)["verdict"]["lines"]
    assert est.startswith("estimate: simulator rollouts 6.843 [6.2, 7.5]; from the logs alone FQE 4.348")
    assert "WORSE than the demonstrator" in verdict and "failures 3 vs 0" in verdict
    assert verdict.endswith("from the logs alone: cannot tell")
    box = verdict_html(headline(m)["verdict"], {"verdict": "converged"})
    assert box.startswith("<p class='verdict bad'><span class='outcome bad'>worse</span><b>")
    for text in (est, verdict, why, re.sub(r"<[^>]+>", "", box)):
        _no_95(text)


@pytest.mark.parametrize("bad", [["only one"], [1, 2, 3], "three", None, ["a", "b", {"c": 1}]])
def test_stored_lines_of_an_untrusted_metrics_json_fall_back_to_the_sentence(bad):
    m = copy.deepcopy(LEFT)
    h = headline(m)
    h["verdict"]["lines"] = bad
    m["headline"] = h
    line = next(ln for ln in summary_lines(m) if ln.startswith("verdict:"))
    assert line.endswith(h["verdict"]["text"])
    box = verdict_html(h["verdict"], {"verdict": "converged"})  # the sentence, its first letter capitalised
    assert box.endswith(html.escape(h["verdict"]["text"][1:]) + "</p>") and "<br>" not in box


def test_the_report_box_of_a_single_episode_has_no_logged_interval():
    """One logged episode: its cost has no spread to measure (metrics.json interval [null, null]);
    the report crashed formatting None."""
    from offline_adp.evaluation.report import _summary_box

    m = copy.deepcopy(LEFT)
    m["behaviour_value"] = {"mean": 20.3, "interval": [None, None], "episodes": 1}
    box = _summary_box(m, headline(m))
    assert "20.3 (no interval: one episode) over 1 episodes" in box
    m["behaviour_value"] = {"mean": 20.3, "interval": [18.0, 22.6], "episodes": 135, "comparable": False,
                            "not_comparable": "3 of 135 logged episodes stop before step 200"}
    assert "not the behaviour's value of the estimand: 3 of 135" in html.unescape(_summary_box(m, headline(m)))


def test_the_ope_figure_gives_each_unlabelled_estimator_its_own_reason(tmp_path):
    """FQE's and MODEL's levels withdrawn for different reasons: the caption gave both FQE's."""
    from offline_adp.evaluation.figures import Figures, ope_figure

    m = copy.deepcopy(LEFT)
    m["ope"]["model"] = {**m["ope"]["fqe"], "estimate": 4.0, "method": "model"}
    m = withdraw_levels(m)
    m["estimand"]["horizon"] = 200
    figs = Figures(tmp_path)
    ope_figure(figs, m, rank_estimators(m))
    caption = figs.items[0][1]
    assert "FQE (the policy left the data's support, where the value model extrapolates" in caption
    assert "MODEL (the policy left the data's support, where the model of the logged dynamics extrapolates" in caption
    one = copy.deepcopy(LEFT)
    figs = Figures(tmp_path / "one")
    ope_figure(figs, withdraw_levels(one), rank_estimators(withdraw_levels(one)))
    assert "Dashed, without a level: FQE (the policy left" in figs.items[0][1]


def test_rollouts_of_another_value_than_the_estimand_say_which_and_a_verdict_keeps_its_parentheses():
    """With --estimand infinite the simulator's rollouts measure the T-step value: the CLI line and
    the headline's estimate said "simulator rollouts 1.337 [...]" under an infinite-horizon estimand
    (an audit: the truth was 1.990). The verdict's first sentence was cut inside a parenthesis."""
    from offline_adp.evaluation.verdict import _before_but

    m = copy.deepcopy(LEFT)
    m["estimand"]["quantity"] = "expected discounted cost sum_t 0.95^t c_t over an infinite horizon from the data"
    m["rollout"] = _rollout((6.843, 6.2, 7.5), (4.608, 4.4, 4.8))
    m["rollout"]["estimand"] = "the 20-step value (rollouts cannot measure the infinite-horizon one)"
    sim = next(ln for ln in summary_lines(m) if ln.startswith("simulator"))
    assert sim.startswith("simulator (the 20-step value (rollouts cannot measure the infinite-horizon one)): policy")
    est = headline(m)["verdict"]["lines"][0]
    assert "simulator rollouts 6.843 [6.2, 7.5] (the 20-step value" in est and "not the estimand)" in est
    m["estimand"]["form"], m["rollout"]["horizon"] = "infinite", 20
    assert "in the simulator over 20 steps (not the estimand's infinite horizon): rollouts 6.843" in \
        headline(m)["verdict"]["text"]
    m["estimand"]["form"] = "finite"
    m["rollout"]["estimand"] = m["estimand"]["quantity"]  # the rollouts measured it: quoted as it
    assert "not the estimand" not in headline(m)["verdict"]["lines"][0]
    assert next(ln for ln in summary_lines(m) if ln.startswith("simulator")).startswith("simulator: policy cost")
    assert "in the simulator: rollouts 6.843" in headline(m)["verdict"]["text"]
    assert _before_but("not compared (the value, but past the logs) here, but why") == \
        "not compared (the value, but past the logs) here"
