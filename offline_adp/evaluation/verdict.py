"""The verdict of an evaluation: better or worse than the behaviour, claimed only when the
evidence behind it holds (:func:`verdict_line`), and its parts: why the policy left the
data's support (:func:`left_support`), the side of an interval against the behaviour's cost
or the demonstrator's, how an interval's level is worded, and the one outcome word every
view colours (:func:`outcome_of`). :mod:`offline_adp.evaluation.summary` builds the headline
around it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.evaluation.model_rollouts import EXIT_FRACTION
from offline_adp.evaluation.ope import is_finite_number as _is_finite_number
from offline_adp.evaluation.ope import rounding_tol

#: Support is "left" when more than this fraction of the data's states see pi choose unlogged actions.
SUPPORT_FRACTION = 0.05
#: the policy left the data's support (from the logs alone) when more than this share of its
#: discounted survival mass in the model rollouts (``evaluation.model_rollouts``) lies past the
#: logged states; measured on path_tracking (medium, seed 1): 0.03 for the demonstrator, 0.07 for
#: the default fit, 0.13-0.51 for candidates that leave the road in most episodes
MODEL_EXIT_FRACTION = EXIT_FRACTION
#: model rollouts show support (with few states per step) only from this many particles: with
#: 2 or 5, a policy with an exit mass of 0.18 read <= 0.1 in 11 or 3 of 20 seeds (review)
MIN_SUPPORT_PARTICLES = 200


#: Fit verdicts that raise no doubt about the policy's values (converged, backward induction,
#: an algorithm without a convergence notion that ran to completion).
FIT_SETTLED = ("converged", "finite horizon", "completed")


def side_of_behaviour(lo: float, hi: float, b: float) -> str:
    """Which side of the behaviour's cost ``b`` an interval lies on; equal up to rounding
    (e.g. every MountainCar policy that never reaches the goal: 86.602 against 86.602 summed
    in another order) is not a side. The tolerance is relative: costs in any unit."""
    tol = rounding_tol(b, lo, hi)
    return "better" if hi < b - tol else "worse" if lo > b + tol else "indistinguishable"


_SIDE_WORDS = {"better": "better than", "worse": "worse than", "indistinguishable": "not distinguishable from"}
#: Where an interval lies against the logged cost's own interval, for each side.
_WHERE_LOGGED = {"better": "lies below", "worse": "lies above", "indistinguishable": "overlaps"}


def logged_interval(beh: dict[str, Any]) -> tuple[float, float] | None:
    """The behaviour's logged cost's own interval (``behaviour_value.interval``, untrusted), or
    None where it has none (a single episode: no spread to measure)."""
    bi = beh.get("interval")
    if isinstance(bi, list | tuple) and len(bi) == 2 and all(_is_finite_number(x) for x in bi) and bi[0] <= bi[1]:
        return float(bi[0]), float(bi[1])
    return None


def logged_side(lo: float, hi: float, beh: dict[str, Any]) -> str:
    """The side of an interval ``[lo, hi]`` of the policy's cost against the behaviour's logged
    cost, which is itself a mean of the logged episodes: ``better`` only when the interval lies
    below the logged cost's own interval, ``worse`` above it, ``indistinguishable`` when they
    overlap. A false "better" needs the policy's interval to miss its value above or the logged
    interval to miss the behaviour's below: each 95% interval does so at most 2.5% of the time,
    so "better" (and, alike, "worse") is claimed falsely at most 5% of the time. Read against the
    logged mean as if it were exact, a policy with the behaviour's own value was called better
    or worse in 5 of 20 seeds (a tabular problem with its exact value). ``unknown`` without a
    logged interval (one episode: no spread to measure): no side, not even "not distinguishable"."""
    bi = logged_interval(beh)
    if bi is None:
        return "unknown"
    tol = rounding_tol(beh["mean"], *bi, lo, hi)
    return "better" if hi < bi[0] - tol else "worse" if lo > bi[1] + tol else "indistinguishable"


def behaviour_words(beh: dict[str, Any]) -> str:
    """The report's and compare's behaviour row: the logged cost, its interval (or why none),
    its episodes, and why it is not the behaviour's value of the estimand where it is not."""
    bi = logged_interval(beh)
    words = f"{beh['mean']:.4g} " + (f"[{bi[0]:.4g}, {bi[1]:.4g}]" if bi else "(no interval: one episode)")
    words += f" over {beh['episodes']} episodes" if isinstance(beh.get("episodes"), int) else ""
    off = behaviour_not_comparable(beh)
    return words + (f"; not the behaviour's value of the estimand: {off}" if off else "")


def behaviour_not_comparable(beh: Any) -> str | None:
    """Why the logged cost is not the behaviour's value of the estimand (``comparable: false``
    in metrics.json, untrusted), else None."""
    if not isinstance(beh, dict) or beh.get("comparable") is not False:
        return None
    why = beh.get("not_comparable")
    return why if isinstance(why, str) and why else "the logged cost is not the behaviour's value of the estimand"


#: the rollouts' start states and the logs' differ when a feature's two-sample
#: Kolmogorov-Smirnov p-value, times the number of features (Bonferroni), is below this
START_STATES_P = 1e-3


def start_states_check(logged: np.ndarray, rolled: np.ndarray) -> dict[str, Any]:
    """Whether the simulator's rollouts start where the logged episodes do: per feature, a
    two-sample Kolmogorov-Smirnov test of the logged first observations against the
    rollouts'. Where they differ, the rollouts' cost and the logged cost are values from
    different starts, and the verdict does not set them against each other (an audit,
    2026-11-29: logs started only from hard states read "better" for a worse policy)."""
    from scipy.stats import ks_2samp

    d = min(logged.shape[1], rolled.shape[1])
    p = [float(ks_2samp(logged[:, j], rolled[:, j]).pvalue) for j in range(d)]
    j = int(np.argmin(p)) if p else 0
    differ = bool(p) and p[j] * d < START_STATES_P
    return {"differ": differ, "min_p": p[j] if p else None, "feature": j, "n_logged": int(len(logged)),
            "n_rolled": int(len(rolled)), "test": "two-sample Kolmogorov-Smirnov per feature, Bonferroni"}


def _no_side_against(beh: dict[str, Any]) -> str | None:
    """Why no side can be read against the logged cost (not the estimand's value, or no interval:
    one episode), else None."""
    return behaviour_not_comparable(beh) or (
        "one logged episode: its cost has no interval" if logged_interval(beh) is None else None)


def logged_words(beh: dict[str, Any]) -> str:
    """``logged 2.93 [2.88, 2.98]``: the logged cost and its own interval, where it has one."""
    bi = logged_interval(beh)
    return f"logged {beh['mean']:.4g}" + (f" [{bi[0]:.4g}, {bi[1]:.4g}]" if bi else "")


def _disagreeing(best: dict[str, Any], ranking: list[dict[str, Any]]) -> list[str]:
    """Other reliable estimators whose interval does not overlap the best one's."""
    lo, hi = best["interval"]
    return [f"{e['name'].upper()} {e['estimate']:.4g} [{e['interval'][0]:.4g}, {e['interval'][1]:.4g}]"
            for e in ranking if e["tier"] == 0 and e is not best and (e["interval"][1] < lo or e["interval"][0] > hi)]


#: The one-word outcomes of a verdict, each with one colour everywhere it is shown: the CLI
#: summary (ANSI), the report's verdict box and the comparison (CSS class, figure colour).
OUTCOMES = ("better", "worse", "cannot tell", "not converged")
#: CSS class of each outcome (html_blocks.STYLE): green, red, amber, purple.
OUTCOME_CLASS = {"better": "good", "worse": "bad", "cannot tell": "meh", "not converged": "stale"}
#: The same colours for figures and the terminal (ANSI SGR codes of the nearest basic colour).
OUTCOME_COLOUR = {"better": "#2e7d32", "worse": "#c62828", "cannot tell": "#b58900", "not converged": "#7b1fa2"}
OUTCOME_ANSI = {"better": "32", "worse": "31", "cannot tell": "33", "not converged": "35"}
#: Fit verdicts that make the outcome "not converged" (unless the policy is worse anyway).
FIT_UNSETTLED = ("still changing", "not converged", "diverging", "diverged")


def outcome_of(performance: str | None, fit_verdict: str | None, against_demonstrator: str | None = None,
               more_failures: bool = False) -> str:
    """The verdict's one word (:data:`OUTCOMES`), computed here once for the CLI, the report
    and ``compare``: ``worse`` when the policy is worse than the behaviour or, where the
    simulator has one, than the demonstrator; else ``not converged`` when its fit did not
    converge (or diverged); else ``better`` when it is better than the behaviour and not
    worse than the demonstrator (nor failing more often); else ``cannot tell``."""
    if performance == "worse" or against_demonstrator == "worse":
        return "worse"
    if fit_verdict in FIT_UNSETTLED:
        return "not converged"
    if performance == "better" and not more_failures and against_demonstrator in (None, "better", "indistinguishable"):
        return "better"
    return "cannot tell"


def _share_over(x: float) -> str:
    """A share above :data:`SUPPORT_FRACTION` as a percentage that does not read as the rule's
    own 5% (0.0517 is "5.2%", not "5%"): whole percents, a decimal where those would not show
    it above the rule."""
    limit = round(SUPPORT_FRACTION * 100, 6)
    for digits in range(4):
        words = f"{x:.{digits}%}"
        if float(words[:-1]) > limit:
            return words
    return f"{x:.6%}"


def left_support(m: dict[str, Any], shift: dict[str, Any]) -> list[str]:
    """Why the policy left the data's support (empty: it did not, as far as measured): actions
    the data rarely took, states almost separable from the data's or without data near them
    (simulator), or model rollouts of the logs that reach past the logged states."""
    sv = (m.get("behaviour") or {}).get("support_violations", {}).get("fraction")
    left = []
    if _is_finite_number(sv) and sv > SUPPORT_FRACTION:
        left.append(f"chooses actions the data rarely took at {_share_over(sv)} of the data's states")
    return left + left_states(m, shift)


def left_states(m: dict[str, Any], shift: dict[str, Any]) -> list[str]:
    """The reasons of :func:`left_support` about the policy's *states* (not its actions at the
    logged states): what undermines the model rollouts' reading, which steps the model under
    any action and is checked against FQE's interval with its per-action support bounds."""
    left = []
    if shift.get("method") == "classifier":
        if shift.get("separable_steps"):
            left.append(f"its states are almost separable from the data's at {shift['separable_steps']} of "
                        f"{shift['n_steps']} steps")
        if shift.get("max_uncovered", 0) > SUPPORT_FRACTION:
            left.append(f"up to {_share_over(shift['max_uncovered'])} of its simulated states have no data near them")
    mr = (m.get("ope", {}).get("fqe") or {}).get("model_rollouts") or {}
    if _is_finite_number(mr.get("exit_mass")) and mr["exit_mass"] >= MODEL_EXIT_FRACTION:
        left.append(f"{mr['exit_mass']:.0%} of its discounted mass in model rollouts of the logs reaches states no "
                    "logged state is near")
    return left


def level_words(e: dict[str, Any]) -> str:
    """How an interval of :func:`rank_estimators` is labelled wherever it is printed: its
    level ("95%"), or "no level" when it has none."""
    lvl = e.get("level")
    return f"{lvl:.0%}" if _is_finite_number(lvl) and e.get("interval") else "no level"


def demonstrator_side(m: dict[str, Any]) -> dict[str, Any] | None:
    """The policy against the simulator's demonstrator (same start states and seeds): the
    side of their rollout intervals (``better`` only when the policy's lies below the
    demonstrator's, ``worse`` above it, else ``indistinguishable``) and their failures where
    the problem counts them; None without a demonstrator."""
    ro = m.get("rollout") or {}
    p, d = ro.get("policy"), ro.get("demonstrator")
    if not (isinstance(p, dict) and isinstance(d, dict) and _is_finite_number(p.get("mean_discounted_cost"))
            and _is_finite_number(d.get("mean_discounted_cost"))):
        return None
    pi, di = p.get("interval") or [None, None], d.get("interval") or [None, None]
    if all(_is_finite_number(x) for x in (*pi, *di)):
        side = "better" if pi[1] < di[0] else "worse" if pi[0] > di[1] else "indistinguishable"
    else:
        side = side_of_behaviour(p["mean_discounted_cost"], p["mean_discounted_cost"], d["mean_discounted_cost"])
    out = {"side": side, "policy": p["mean_discounted_cost"], "demonstrator": d["mean_discounted_cost"],
           "demonstrator_interval": d.get("interval"), "more_failures": False}
    if isinstance(p.get("failures"), int | float) and isinstance(d.get("failures"), int | float):
        out.update(failures=int(p["failures"]), demonstrator_failures=int(d["failures"]),
                   more_failures=bool(p["failures"] > d["failures"]))
    return out


def verdict_line(m: dict[str, Any], ranking: list[dict[str, Any]], shift: dict[str, Any],
                 conv: dict[str, Any]) -> dict[str, Any]:
    """Better or worse than the behaviour, only when the evidence behind it holds.

    The logs alone say "better" or "worse" only when the most reliable estimator has an
    interval with a level on one side of the behaviour's logged cost *and* nothing in the same
    evaluation undermines it: the policy did not leave the data's support (actions the
    data rarely took; states the model rollouts of the logs reach and no logged state is
    near, at least :data:`MODEL_EXIT_FRACTION` of the discounted mass; or, with a
    simulator, states the data does not cover), the logs can show it (a per-step shift
    estimate, or, where the logs are too thin per step for one, both the candidate's
    actions at the logged states and the model rollouts' exit mass measured), the fit
    converged, and no other reliable estimator's interval disagrees. Otherwise the
    performance clause reads "cannot tell from these logs" and names the reasons
    (an off-policy interval assumes the value model holds where the policy goes; past the
    data's support it extrapolates, and on continuous problems it did so by 20-50%,
    docs/evaluation.md). Where a simulator's rollouts measured the same estimand, the
    verdict is theirs (the truth), against the behaviour and, where the simulator has one,
    against the demonstrator with both failure counts; an off-policy side that disagrees
    is said so. ``performance`` is the side against the behaviour that was claimed, or
    ``"unknown"``; ``outcome`` the one word (:func:`outcome_of`) every view colours.
    """
    beh = m.get("behaviour_value")
    beh_off = _no_side_against(beh) if isinstance(beh, dict) else None
    left = left_support(m, shift)
    support, logs_show = _support_clause(m, shift, left)
    cv = conv.get("verdict")
    best = next((e for e in ranking if e["tier"] == 0), None)
    doubts = _model_doubts(m, shift) if best and best["name"] == "model" else _doubts(left, shift, logs_show, cv)
    side, perf, claim = _offpolicy_side(ranking, None if beh_off else beh, doubts)
    if beh_off:
        perf = f"cannot tell from these logs whether the policy is better than the behaviour: {beh_off}"
    demo = None
    ro = (m.get("rollout") or {}).get("policy")
    starts = (m.get("rollout") or {}).get("start_states") or {}
    if beh is not None and ro and _is_finite_number(ro.get("mean_discounted_cost")) and ro.get("interval"):
        demo = demonstrator_side(m)
        finite_only = (m.get("rollout") or {}).get("horizon") if (m.get("estimand") or {}).get("form") == "infinite" \
            else None  # the rollouts measure T steps of an infinite-horizon estimand: the verdict says so
        side, perf = _simulator_side(ro, beh, demo, side, perf, claim, starts, finite_only)
    outcome = outcome_of(side, cv, demo["side"] if demo else None, bool(demo and demo["more_failures"]))
    ct = conv["text"][:1].upper() + conv["text"][1:]
    return {"performance": side, "outcome": outcome, "against_demonstrator": demo["side"] if demo else None,
            "text": f"{perf}. Policy {support}. {ct}.", "support_left": bool(left),
            "lines": headline_lines(m, ranking, perf, support, doubts, conv)}


def stored_lines(v: Any) -> list[str] | None:
    """A verdict's three lines as stored in a ``metrics.json`` (untrusted): three strings, else None."""
    lines = v.get("lines") if isinstance(v, dict) else None
    ok = isinstance(lines, list) and len(lines) == 3 and all(isinstance(x, str) for x in lines)
    return lines if ok else None


def model_hull_words(m: dict[str, Any]) -> str | None:
    """The why-clause of a model interval that is the hull of the model rollouts' own interval
    and FQE's bootstrap interval, which did not overlap (``metrics.json``'s ``ope.model.hull``,
    untrusted: None unless both are pairs of finite numbers)."""
    hull = ((m.get("ope") or {}).get("model") or {}).get("hull")
    if not isinstance(hull, dict):
        return None
    mod, fqe = hull.get("model"), hull.get("fqe_bootstrap")
    if not all(isinstance(p, list) and len(p) == 2 and all(map(_is_finite_number, p)) for p in (mod, fqe)):
        return None
    return (f"the model rollouts [{mod[0]:.4g}, {mod[1]:.4g}] and FQE's bootstrap interval [{fqe[0]:.4g}, "
            f"{fqe[1]:.4g}] (before its support bounds) disagree on what the logs hold, so the interval spans both")


def rollouts_of_another_value(m: dict[str, Any]) -> str | None:
    """What the simulator's rollouts measured when it is not the estimand (``metrics.json``'s
    ``rollout.estimand``: the T-step value of an infinite-horizon estimand, or the value
    from the simulator's own start states), else None."""
    said, quantity = (m.get("rollout") or {}).get("estimand"), (m.get("estimand") or {}).get("quantity")
    return said if isinstance(said, str) and said and said != quantity else None


def _before_but(text: str) -> str:
    """``text`` up to its first ", but " outside parentheses (the reasons are the why line's;
    a clause in parentheses is kept whole)."""
    depth = 0
    for i, ch in enumerate(text):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and text.startswith(", but ", i):
            return text[:i]
    return text


def headline_lines(m: dict[str, Any], ranking: list[dict[str, Any]], perf: str, support: str, doubts: list[str],
                   conv: dict[str, Any]) -> list[str]:
    """The verdict in three lines, read in seconds: the estimate with its interval and its true
    level (the simulator's rollouts first where they measured the estimand); the verdict
    against the behaviour (and the demonstrator, with failures), without the reasons; and one
    line of why (support, convergence, disagreeing estimators). ``text`` keeps the whole
    sentence for the record."""
    est = []
    ro = (m.get("rollout") or {}).get("policy") or {}
    if _is_finite_number(ro.get("mean_discounted_cost")) and ro.get("interval"):
        lo, hi = ro["interval"]
        other = rollouts_of_another_value(m)  # e.g. T steps of an infinite-horizon estimand: said, not quoted as it
        est.append(f"simulator rollouts {ro['mean_discounted_cost']:.4g} [{lo:.4g}, {hi:.4g}]"
                   + (f" ({other}, not the estimand)" if other else ""))
    top = next((e for e in ranking if e["tier"] == 0), None) or next((e for e in ranking if e["tier"] == 1), None)
    if top is not None:
        iv = top.get("interval") or top.get("shown_interval")
        where = "from the logs alone " if est else ""
        est.append(f"{where}{top['name'].upper()} {top['estimate']:.4g}"
                   + (f" [{iv[0]:.4g}, {iv[1]:.4g}] ({level_words(top)})" if iv and all(map(_is_finite_number, iv))
                      else " (no interval)"))
    verdict, _, logs = perf.partition(" (from the logs alone: ")
    if logs:  # the simulator's verdict, then the logs' own in a word
        confirmed = logs.startswith(("better too", "worse too", "not distinguishable"))
        verdict += "; from the logs alone: " + (logs.split(", ", 1)[0] if confirmed else "cannot tell")
    verdict = _before_but(verdict)
    fit = conv["text"].split(": ", 1)[0]  # "fit converged", "fit still changing", ...; its numbers are in the report
    why = [f"policy {support}"] + [d for d in doubts if d.startswith("other reliable")] + [fit]
    best = next((e for e in ranking if e["tier"] == 0), None)
    hulled = model_hull_words(m) if top is not None and top["name"] == "model" else None
    if best is not None and best.get("on_policy"):
        why.insert(1, f"the logged episodes are nearly the policy's own (its importance weights keep "
                      f"{best['ess_fraction']:.0%} of them), so the doubly robust estimate leads")
    if hulled:
        why.insert(1, hulled)
    elif best is not None and best["name"] == "model" and support.startswith("LEFT") and not doubts:
        why.insert(1, "the model rollouts' reading holds there (they step any action, stay within the logged "
                      "states and agree with FQE's per-action support bounds)")
    return ["estimate: " + ("; ".join(est) if est else "none usable"), verdict, "why: " + "; ".join(why)]


def _support_clause(m: dict[str, Any], shift: dict[str, Any], left: list[str]) -> tuple[str, bool]:
    """The verdict's support clause, and whether the logs alone show the policy stays within
    the data's support (where the per-step shift is too thin to estimate)."""
    sv = (m.get("behaviour") or {}).get("support_violations", {}).get("fraction")
    mr = (m.get("ope", {}).get("fqe") or {}).get("model_rollouts") or {}
    # from the logs alone, when the per-step shift is too thin to estimate: the candidate's actions
    # at the logged states (measured) and where the model rollouts of the logs drive it (ran)
    logs_show = (not left and _is_finite_number(sv) and _is_finite_number(mr.get("exit_mass"))
                 and (mr.get("n_particles") or 0) >= MIN_SUPPORT_PARTICLES)
    if left:
        support = "LEFT the data's support: " + "; ".join(left)
    elif shift.get("enough_data"):
        support = "stays within the data's support"
    elif logs_show:
        support = (f"stays within the data's support as far as the logs show (actions the data rarely took at "
                   f"{sv:.1%} of the data's states; {mr['exit_mass']:.1%} of the discounted mass of model "
                   "rollouts of the logs past the logged states)")
    else:
        support = "support: cannot tell from these logs" + (f" (action support violations {sv:.1%})"
                                                            if _is_finite_number(sv) else "")
    return support, logs_show


def _model_doubts(m: dict[str, Any], shift: dict[str, Any]) -> list[str]:
    """What undermines a side read from the model rollouts' labelled interval: only states past
    the data (its label already needs the rollouts within the logged states and its interval
    overlapping FQE's with the per-action support bounds), not the candidate's fit (the model
    reads the policy as given, however it was fitted)."""
    return ["the policy left the data's support, where the model extrapolates"] if left_states(m, shift) else []


def _doubts(left: list[str], shift: dict[str, Any], logs_show: bool, cv: str | None) -> list[str]:
    """What undermines an off-policy side: the support left or not shown, the fit's convergence."""
    doubts = []
    if left:
        doubts.append("the policy left the data's support, where the value model extrapolates")
    elif not (shift.get("enough_data") or logs_show):
        doubts.append("the logs cannot show whether the policy stays within their support")
    if cv in ("still changing", "not converged"):
        doubts.append("the fit did not converge")
    elif cv in ("diverging", "diverged"):
        doubts.append("the fit diverged")
    elif cv not in FIT_SETTLED:
        doubts.append("the fit's convergence is unknown")
    return doubts


def _offpolicy_side(ranking: list[dict[str, Any]], beh: dict[str, Any] | None,
                    doubts: list[str]) -> tuple[str, str, str | None]:
    """``(side, performance clause, claim)`` from the logs alone: the most reliable estimator's
    interval against the behaviour's logged cost, claimed only when no doubt holds."""
    best = next((e for e in ranking if e["tier"] == 0), None)
    side, perf, claim = "unknown", "", None
    top = next((e for e in ranking if e["tier"] == 1), None)
    if best is None and top is not None and top.get("shown_interval") and beh is not None:
        # an interval without a level: its side is said, never claimed (nor its numbers quoted as an interval)
        lo, hi = top["shown_interval"]
        would = logged_side(lo, hi, beh)
        claim = f"{top['name'].upper()} {top['estimate']:.4g} vs {logged_words(beh)}"
        why = doubts or [f"its interval carries no level ({top.get('level_note') or 'coverage not measured'})"]
        words = {"better": "better", "worse": "worse", "indistinguishable": "not distinguishable"}[would]
        perf = (f"cannot tell from these logs whether the policy is better than the behaviour: {claim} would say "
                f"{words}, but " + "; ".join(why))
    elif best is None:
        perf = ("cannot tell from these logs whether the policy is better than the behaviour: "
                + (f"the best available estimate ({top['name'].upper()} {top['estimate']:.4g}) has no interval"
                   if top else "no estimator is reliable here"))
    elif beh is None:
        perf = f"best estimate {best['estimate']:.4g} (no behaviour baseline)"
    else:
        lo, hi = best["interval"]
        ope_side = logged_side(lo, hi, beh)
        claim = f"{best['name'].upper()} {best['estimate']:.4g} [{lo:.4g}, {hi:.4g}] vs {logged_words(beh)}"
        paired = best.get("vs_logged")
        if paired:  # on the logging policy's own weights: the difference, read on the same episodes
            ope_side = side_of_behaviour(paired[0], paired[1], 0.0)
            claim = f"{best['name'].upper()} {best['estimate']:.4g} [{lo:.4g}, {hi:.4g}] vs logged {beh['mean']:.4g}"
        dis = _disagreeing(best, ranking)
        if dis:
            doubts.append("other reliable estimators disagree (" + "; ".join(dis) + ")")
        if not doubts:  # an interval across the behaviour's cost is a side too: only without doubts (issue #42)
            side = ope_side
            where = {"better": "lies below", "worse": "lies above", "indistinguishable": "contains"}[ope_side]
            conf = (f"its {level_words(best)} interval of the difference from the logged cost of the same episodes, "
                    f"[{paired[0]:.4g}, {paired[1]:.4g}], {where} 0" if paired
                    else f"its {level_words(best)} interval {_WHERE_LOGGED[ope_side]} the logged cost's own 95% "
                    "interval")
            perf = f"{_SIDE_WORDS[ope_side]} the behaviour: {claim} ({conf})"
        else:
            words = {"better": "better", "worse": "worse", "indistinguishable": "not distinguishable"}[ope_side]
            perf = (f"cannot tell from these logs whether the policy is better than the behaviour: {claim} would "
                    f"say {words}, but " + "; ".join(doubts))
    return side, perf, claim


def _simulator_side(ro: dict[str, Any], beh: dict[str, Any], demo: dict[str, Any] | None, side: str, perf: str,
                    claim: str | None, starts: dict[str, Any] | None = None,
                    steps: int | None = None) -> tuple[str, str]:
    """``(side, performance clause)`` of the simulator's rollouts (the truth) against the
    behaviour's logged cost (with its own interval, :func:`logged_side`) and the demonstrator,
    saying where the logs' side disagrees; not against the logged cost where the rollouts
    start elsewhere than the logs (``starts``: :func:`start_states_check`); ``steps``: the
    rollouts' horizon where they measure a T-step value of an infinite-horizon estimand."""
    r_lo, r_hi = ro["interval"]
    off = _no_side_against(beh)
    if off is None and (starts or {}).get("differ"):
        off = (f"the rollouts start from the simulator's start states and the logs from others (feature "
               f"{starts['feature']}: two-sample KS p = {starts['min_p']:.2g}), so their costs are values from "
               "different starts")
    truth_side = "unknown" if off else logged_side(r_lo, r_hi, beh)
    against = f"not compared with the behaviour ({off})" if off else f"{_SIDE_WORDS[truth_side]} the behaviour"
    if demo is not None:  # the demonstrator first when the policy is worse than it
        d_words = {"better": "better than the demonstrator", "worse": "WORSE than the demonstrator",
                   "indistinguishable": "not distinguishable from the demonstrator"}[demo["side"]]
        against = (f"{d_words} ({against})" if demo["side"] == "worse" and truth_side != "worse"
                   else f"{against}; {d_words}")
    over = f" over {steps} steps (not the estimand's infinite horizon)" if steps else ""
    truth = (f"{against} in the simulator{over}: rollouts {ro['mean_discounted_cost']:.4g} [{r_lo:.4g}, {r_hi:.4g}] vs "
             f"{logged_words(beh)}")
    if demo is not None:
        di = demo.get("demonstrator_interval") or []
        truth += f", demonstrator {demo['demonstrator']:.4g}" + (
            f" [{di[0]:.4g}, {di[1]:.4g}]" if len(di) == 2 and all(_is_finite_number(x) for x in di) else "")
        if "failures" in demo:
            truth += (f"; failures {demo['failures']} vs {demo['demonstrator_failures']} (demonstrator)"
                      + (": the policy fails more often" if demo["more_failures"] else ""))
    if side in ("better", "worse") and truth_side != side and not off:
        truth += (f" (the off-policy estimate, {claim}, said {side}: it is contradicted here)"
                  if truth_side in ("better", "worse") else
                  f" (the off-policy estimate, {claim}, said {side}: the rollouts do not confirm it against the "
                  "logged cost's own interval)")
    elif side == "unknown" and not off:
        truth += f" (from the logs alone: {perf})"
    elif side in ("better", "worse") and not off:  # the logs' own side, confirmed: say so
        truth += f" (from the logs alone: {side} too, {claim})"
    elif side == "indistinguishable" and not off:
        truth += f" (from the logs alone: not distinguishable from the behaviour, {claim})"
    return truth_side, truth
