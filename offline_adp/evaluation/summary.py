"""The headline of an evaluation: what a person is told first, and nothing that flatters.

:func:`headline` condenses ``metrics.json`` into

- the **best estimate**: estimators ranked by reliability (:func:`rank_estimators`), the
  degenerate and the impossible ones never quoted;
- the **shift verdict**: the most trustworthy diagnostic available, named: classifier
  ratios when a simulator was used; from logs only, per-step ratios only when every step
  has enough states (:data:`~offline_adp.evaluation.shift.MIN_STATES_PER_STEP`), else
  "not enough data per step" and, for a stationary policy, ratios pooled over time;
- the **verdict line**: better or worse than the behaviour, with what confidence; whether
  the policy left the data's support; whether the fit converged (``run.json`` /
  ``model/history.csv``);
- the count of warnings.

:func:`summary_lines` prints it (the CLI's summary after ``evaluate`` and ``run``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict

from offline_adp.data.files import read_json_file, read_table_file
from offline_adp.evaluation.model_rollouts import EXIT_FRACTION

#: Human names of the estimators.
ESTIMATOR_NAMES = {
    "fqe": "FQE (fitted Q evaluation)", "is": "IS (trajectory importance sampling)", "wis": "WIS (weighted IS)",
    "pdis": "PDIS (per-decision IS)", "wpdis": "WPDIS (weighted per-decision IS)", "dr": "DR (doubly robust)",
    "wdr": "WDR (weighted doubly robust)", "mis": "MIS (marginalised IS)",
}
#: Estimators from the least to the most fragile under distribution shift: model-based FQE
#: (the default), doubly robust, marginalised IS (state ratios), then the trajectory-weighted ones.
ROBUSTNESS = ("fqe", "wdr", "dr", "mis", "wpdis", "pdis", "wis", "is")
#: A classifier AUC above this: pi's states and the data's are almost separable at that step.
AUC_SEPARABLE = 0.95
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


class _Open(BaseModel):
    """A part of ``metrics.json``: the keys read are typed, others pass (lax: ints fill floats)."""

    model_config = ConfigDict(extra="allow")


class _Estimate(_Open):
    estimate: float | None = None
    interval: list[float | None] | None = None
    degenerate: bool | None = None
    comparable: bool | None = None
    ess: float | None = None
    warnings: list[Any] = []


class _Estimand(_Open):
    form: str | None = None
    quantity: str | None = None
    horizon: int | None = None
    gamma: float | None = None
    possible_range: list[float | None] | None = None


class MetricsFile(_Open):
    """The structure of ``metrics.json`` that ``report``, ``compare`` and ``run`` read: a
    file without it (``"ope": "nonsense"``) is an :class:`~offline_adp.errors.ArtifactError`
    naming the file and key before anything indexes into it."""

    ope: dict[str, _Estimate]
    estimand: _Estimand = _Estimand()
    dataset: dict[str, Any] = {}
    algorithm: str | None = None
    simulator: str | None = None
    simulator_note: str | None = None
    warnings: list[Any] = []
    rollout: dict[str, dict[str, Any] | Any] | None = None
    shift: dict[str, dict[str, Any]] = {}
    pooled_shift: dict[str, Any] | None = None
    psdp_bound: dict[str, Any] | None = None
    per_source: dict[str, dict[str, Any]] | None = None
    behaviour: dict[str, Any] | None = None
    behaviour_value: dict[str, Any] | None = None
    cost_distribution: dict[str, Any] | None = None
    headline: dict[str, Any] | None = None
    worst_step: dict[str, Any] | None = None
    per_step_counts: list[int] | None = None
    min_states_per_step: int | None = None


def read_metrics(path: str | Path) -> dict[str, Any]:
    """``metrics.json`` through the gates of every file we read: a regular file of bounded
    size and nesting (:func:`~offline_adp.data.rundir.read_json_file`), then the structure
    of :class:`MetricsFile`; the file's own dict is returned."""
    from pydantic import ValidationError as PydanticValidationError

    from offline_adp.config import format_validation_error
    from offline_adp.errors import ArtifactError

    m = read_json_file(path)
    try:
        MetricsFile.model_validate(m)
    except PydanticValidationError as exc:
        raise ArtifactError(format_validation_error(exc, MetricsFile, str(path)).replace("\n", " ")
                            + "; not a metrics.json this version reads (run `offline-adp evaluate` again)") from None
    return m


def _is_finite_number(x: Any) -> bool:
    return x is not None and isinstance(x, int | float) and bool(np.isfinite(x))


def rank_estimators(m: dict[str, Any]) -> list[dict[str, Any]]:
    """Estimators ordered by reliability, each with a tier and the reason.

    Tier 0 ``reliable``: finite, inside the possible range, targets the declared estimand,
    has an interval. Tier 1 ``no interval``: the interval was withheld (degenerate-ish
    weights) or not computed. Tier 2 ``not usable``: degenerate weights, an estimate outside
    the possible range of the cost, or another estimand. Within a tier, by
    :data:`ROBUSTNESS` (never by interval width: a narrow interval from fixed, wrong
    ratios would flatter).
    """
    rng = m.get("estimand", {}).get("possible_range")
    out = []
    for name, r in m["ope"].items():
        est, iv = r.get("estimate"), r.get("interval") or [None, None]
        # an interval counts only with a level: one whose coverage nobody measured (level null) is not quoted
        has_iv = _is_finite_number(iv[0]) and _is_finite_number(iv[1]) and r.get("level") is not None
        reasons = []
        if not _is_finite_number(est):
            reasons.append("no finite estimate")
        elif rng and not (rng[0] - 1e-9 <= est <= rng[1] + 1e-9):
            reasons.append(f"outside the possible range [{rng[0]:.4g}, {rng[1]:.4g}] of the cost")
        if r.get("degenerate"):
            ess = r.get("ess")
            reasons.append("degenerate importance weights" + (f" (effective sample size {ess:.1f})" if _is_finite_number(ess) else ""))
        if r.get("comparable") is False:
            reasons.append("estimates another quantity than the one asked for")
        tier = 2 if reasons else (0 if has_iv else 1)
        if tier == 1 and _is_finite_number(iv[0]) and _is_finite_number(iv[1]) and r.get("level_note"):  # level withdrawn (support left)
            reasons.append(f"its interval [{iv[0]:.4g}, {iv[1]:.4g}] carries no level: {r['level_note']}")
        elif tier == 1 and _is_finite_number(iv[0]) and _is_finite_number(iv[1]):  # an interval without a level: shown, never quoted
            reasons.append(f"its interval [{iv[0]:.4g}, {iv[1]:.4g}] has no measured coverage (no level)")
        elif tier == 1:
            reasons.append(r.get("interval_method", "no interval"))
        width = (iv[1] - iv[0]) if has_iv else np.inf
        out.append({"name": name, "label": ESTIMATOR_NAMES.get(name, name.upper()), "tier": tier,
                    "tier_label": ("reliable", "no interval", "not usable")[tier], "reason": "; ".join(reasons),
                    "estimate": est, "interval": iv if has_iv else None, "level": r.get("level") if has_iv else None,
                    "shown_interval": iv if _is_finite_number(iv[0]) and _is_finite_number(iv[1]) else None,
                    "level_note": r.get("level_note"), "width": width,
                    "plugin_estimate": r.get("plugin_estimate")})
    order = {k: i for i, k in enumerate(ROBUSTNESS)}
    out.sort(key=lambda e: (e["tier"], order.get(e["name"], len(order)), e["name"]))
    for i, e in enumerate(out):
        e["rank"] = i + 1
        e["width"] = None if not np.isfinite(e["width"]) else e["width"]
    return out


def shift_verdict(m: dict[str, Any]) -> dict[str, Any]:
    """The most trustworthy shift diagnostic available, named, with its verdict text."""
    shift = m.get("shift", {})
    if "classifier" in shift:
        d = pd.DataFrame(shift["classifier"]["per_step"])
        if not d.empty:
            i = d["ess_fraction"].idxmin()
            sep = int((d.get("auc", pd.Series(dtype=float)) > AUC_SEPARABLE).sum())
            unc = float(d["uncovered"].max()) if "uncovered" in d else 0.0
            text = (f"classifier ratios (simulator): worst-step ESS/n {d.loc[i, 'ess_fraction']:.3f} at t = "
                    f"{int(d.loc[i, 'step'])}; AUC > {AUC_SEPARABLE} at {sep} of {len(d)} steps")
            return {"method": "classifier", "ess_fraction": float(d.loc[i, "ess_fraction"]), "step": int(d.loc[i, "step"]),
                    "separable_steps": sep, "n_steps": int(len(d)), "max_uncovered": unc, "text": text,
                    "enough_data": True}
    counts = m.get("per_step_counts")
    thin = counts is not None and len(counts) > 1 and min(counts[1:] or counts) < m.get("min_states_per_step", 500)
    pooled = m.get("pooled_shift")
    if thin:
        few = int(min(counts[1:] or counts))
        text = f"not enough data per step to estimate the shift (as few as {few} states per step)"
        out = {"method": "none", "ess_fraction": None, "text": text, "enough_data": False}
        if pooled:
            out.update(method="pooled", ess_fraction=pooled["ess_fraction"], pooled=pooled)
            out["text"] = (text + f"; ratios pooled over time (stationary approximation): ESS/n "
                           f"{pooled['ess_fraction']:.3f}, 99% quantile {pooled['q99']:.3g}")
        return out
    ws = m.get("worst_step", {})
    if ws:
        return {"method": "recursion", "ess_fraction": ws.get("ess_fraction"), "step": ws.get("step"),
                "text": f"ratio recursion (logs only): worst-step ESS/n {ws['ess_fraction']:.3f} at t = {ws['step']}",
                "enough_data": True}
    return {"method": "none", "ess_fraction": None, "text": "no shift diagnostic", "enough_data": False}


#: Fit verdicts that raise no doubt about the policy's values (converged, backward induction,
#: an algorithm without a convergence notion that ran to completion).
FIT_SETTLED = ("converged", "finite horizon", "completed")

#: How the summary words the fit's own verdict (:func:`offline_adp.algorithms.fqi_monitor.convergence_verdict`,
#: stored in ``run.json`` as ``verdict`` and ``verdict_message``).
_FIT_VERDICT_WORDS = {"converged": "fit converged", "still changing": "fit did NOT converge",
                      "diverging": "fit DIVERGED", "completed": "fit completed"}


def fit_convergence(run_dir: str | Path | None) -> dict[str, Any]:
    """Did the fit converge? The fit's own verdict stored in ``run.json`` (``verdict`` and
    ``verdict_message``, written by :func:`offline_adp.runs.fit_run` and the Dask engine)
    when present. Run directories written before the verdict was stored: ``diverged``,
    else the last change in ``model/history.csv`` against the fit's ``tol``. Missing files
    give ``unknown``; a corrupt one is an :class:`~offline_adp.errors.ArtifactError`."""
    if run_dir is None:
        return {"verdict": "unknown", "text": "fit convergence unknown (no run directory)"}
    run = Path(run_dir)
    info = read_json_file(run / "run.json") if (run / "run.json").is_file() else {}
    cfg = read_json_file(run / "config.json") if (run / "config.json").is_file() else {}
    tol = cfg.get("params", {}).get("tol") if isinstance(cfg.get("params"), dict) else None
    stored = info.get("verdict")
    if isinstance(stored, str) and stored:
        msg = info.get("verdict_message")
        words = _FIT_VERDICT_WORDS.get(stored, f"fit: {stored}")
        text = f"{words}: {msg}" if isinstance(msg, str) and msg else words
        if stored == "diverging":
            text += "; its policy and values are not to be trusted"
        return {"verdict": stored, "text": text, "source": "run.json"}
    if info.get("diverged"):
        return {"verdict": "diverged", "text": "fit DIVERGED (run.json): its policy and values are not to be trusted",
                "source": "run.json"}
    hist = run / "model" / "history.csv"
    if hist.exists():
        h = read_table_file(hist)
        if "sup_dq" in h and h["sup_dq"].notna().any() and ("step" not in h or h["step"].isna().all()):
            last = float(h["sup_dq"].dropna().iloc[-1])
            k = int(h["iteration"].iloc[-1]) if "iteration" in h else len(h)
            if tol is not None:
                ok = last < float(tol)
                return {"verdict": "converged" if ok else "not converged", "last_change": last, "tol": tol,
                        "text": f"fit {'converged' if ok else 'did NOT converge'}: last change {last:.3g} "
                                f"{'<' if ok else '>='} tol {tol:g} after {k} iterations", "source": "history.csv"}
            return {"verdict": "unknown", "last_change": last,
                    "text": f"fit ran {k} iterations, last change {last:.3g} (no tol set)", "source": "history.csv"}
        if "step" in h and h["step"].notna().any():
            return {"verdict": "finite horizon", "text": "fit: finite horizon (backward induction, no convergence to "
                    "check)", "source": "history.csv"}
    status = info.get("status")
    return {"verdict": "unknown", "text": f"fit convergence unknown (status {status})" if status else
            "fit convergence unknown"}


def side_of_behaviour(lo: float, hi: float, b: float) -> str:
    """Which side of the behaviour's cost ``b`` an interval lies on; equal up to rounding
    (e.g. every MountainCar policy that never reaches the goal: 86.602 against 86.602 summed
    in another order) is not a side."""
    tol = 1e-9 * max(1.0, abs(b))
    return "better" if hi < b - tol else "worse" if lo > b + tol else "indistinguishable"


_SIDE_WORDS = {"better": "better than", "worse": "worse than", "indistinguishable": "not distinguishable from"}


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


def left_support(m: dict[str, Any], shift: dict[str, Any]) -> list[str]:
    """Why the policy left the data's support (empty: it did not, as far as measured): actions
    the data rarely took, states almost separable from the data's or without data near them
    (simulator), or model rollouts of the logs that reach past the logged states."""
    sv = (m.get("behaviour") or {}).get("support_violations", {}).get("fraction")
    left = []
    if _is_finite_number(sv) and sv > SUPPORT_FRACTION:
        left.append(f"chooses actions the data rarely took at {sv:.0%} of the data's states")
    if shift.get("method") == "classifier":
        if shift.get("separable_steps"):
            left.append(f"its states are almost separable from the data's at {shift['separable_steps']} of "
                        f"{shift['n_steps']} steps")
        if shift.get("max_uncovered", 0) > SUPPORT_FRACTION:
            left.append(f"up to {shift['max_uncovered']:.0%} of its simulated states have no data near them")
    mr = (m.get("ope", {}).get("fqe") or {}).get("model_rollouts") or {}
    if _is_finite_number(mr.get("exit_mass")) and mr["exit_mass"] >= MODEL_EXIT_FRACTION:
        left.append(f"{mr['exit_mass']:.0%} of its discounted mass in model rollouts of the logs reaches states no "
                    "logged state is near")
    return left


#: Why an off-policy interval carries no level once the policy left the data's support.
LEVEL_WITHDRAWN = ("the policy left the data's support, where the value model extrapolates: the bootstrap measures "
                   "the sampling noise, not that extrapolation, so this is not a {level:.0%} interval there")


def withdraw_levels(m: dict[str, Any], left: list[str] | None = None) -> dict[str, Any]:
    """``m`` with every off-policy interval's level withdrawn (``level: null``, the former
    one as ``nominal_level``, the reason as ``level_note``) when the policy left the data's
    support (``left``, default :func:`left_support`): the interval is still shown, never
    quoted with a level it does not have. Returns a new dict (``m`` is not changed);
    idempotent."""
    if left is None:
        left = left_support(m, shift_verdict(m))
    if not left:
        return m
    ope = {}
    for k, r in m["ope"].items():
        if r.get("level") is not None:
            r = {**r, "nominal_level": r["level"], "level": None, "level_note": LEVEL_WITHDRAWN.format(level=r["level"])}
        ope[k] = r
    return {**m, "ope": ope}


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


def verdict_line(m: dict[str, Any], ranking: list[dict[str, Any]], shift: dict[str, Any], conv: dict[str, Any]) -> dict[str, Any]:
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
    left = left_support(m, shift)
    support, logs_show = _support_clause(m, shift, left)
    cv = conv.get("verdict")
    doubts = _doubts(left, shift, logs_show, cv)
    side, perf, claim = _offpolicy_side(ranking, beh, doubts)
    demo = None
    ro = (m.get("rollout") or {}).get("policy")
    if beh is not None and ro and _is_finite_number(ro.get("mean_discounted_cost")) and ro.get("interval"):
        demo = demonstrator_side(m)
        side, perf = _simulator_side(ro, beh["mean"], demo, side, perf, claim)
    outcome = outcome_of(side, cv, demo["side"] if demo else None, bool(demo and demo["more_failures"]))
    ct = conv["text"][:1].upper() + conv["text"][1:]
    return {"performance": side, "outcome": outcome, "against_demonstrator": demo["side"] if demo else None,
            "text": f"{perf}. Policy {support}. {ct}.", "support_left": bool(left)}


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
                   f"{sv:.1%} of the data's states; {mr['exit_mass']:.1%} of the discounted mass of model rollouts of the "
                   "logs past the logged states)")
    else:
        support = "support: cannot tell from these logs" + (f" (action support violations {sv:.1%})" if _is_finite_number(sv) else "")
    return support, logs_show


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
        would = side_of_behaviour(lo, hi, beh["mean"])
        claim = f"{top['name'].upper()} {top['estimate']:.4g} vs logged {beh['mean']:.4g}"
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
        b = beh["mean"]
        ope_side = side_of_behaviour(lo, hi, b)
        claim = f"{best['name'].upper()} {best['estimate']:.4g} [{lo:.4g}, {hi:.4g}] vs logged {b:.4g}"
        dis = _disagreeing(best, ranking)
        if dis:
            doubts.append("other reliable estimators disagree (" + "; ".join(dis) + ")")
        if ope_side == "indistinguishable" or not doubts:
            side = ope_side
            where = {"better": "lies below", "worse": "lies above", "indistinguishable": "contains"}[ope_side]
            conf = f"its {level_words(best)} interval {where} the behaviour's logged cost"
            perf = f"{_SIDE_WORDS[ope_side]} the behaviour: {claim} ({conf})"
        else:
            perf = (f"cannot tell from these logs whether the policy is better than the behaviour: {claim} would "
                    f"say {ope_side}, but " + "; ".join(doubts))
    return side, perf, claim


def _simulator_side(ro: dict[str, Any], b: float, demo: dict[str, Any] | None, side: str, perf: str,
                    claim: str | None) -> tuple[str, str]:
    """``(side, performance clause)`` of the simulator's rollouts (the truth) against the
    behaviour's logged cost ``b`` and the demonstrator, saying where the logs' side disagrees."""
    r_lo, r_hi = ro["interval"]
    truth_side = side_of_behaviour(r_lo, r_hi, b)
    against = f"{_SIDE_WORDS[truth_side]} the behaviour"
    if demo is not None:  # the demonstrator first when the policy is worse than it
        d_words = {"better": "better than the demonstrator", "worse": "WORSE than the demonstrator",
                   "indistinguishable": "not distinguishable from the demonstrator"}[demo["side"]]
        against = (f"{d_words} ({against})" if demo["side"] == "worse" and truth_side != "worse"
                   else f"{against}; {d_words}")
    truth = (f"{against} in the simulator: rollouts {ro['mean_discounted_cost']:.4g} [{r_lo:.4g}, {r_hi:.4g}] vs "
             f"logged {b:.4g}")
    if demo is not None:
        di = demo.get("demonstrator_interval") or []
        truth += f", demonstrator {demo['demonstrator']:.4g}" + (
            f" [{di[0]:.4g}, {di[1]:.4g}]" if len(di) == 2 and all(_is_finite_number(x) for x in di) else "")
        if "failures" in demo:
            truth += (f"; failures {demo['failures']} vs {demo['demonstrator_failures']} (demonstrator)"
                      + (": the policy fails more often" if demo["more_failures"] else ""))
    if side in ("better", "worse") and truth_side != side:
        truth += f" (the off-policy estimate, {claim}, said {side}: it is contradicted here)"
    elif side == "unknown":
        truth += f" (from the logs alone: {perf})"
    return truth_side, truth


def gather_warnings(m: dict[str, Any]) -> list[dict[str, str]]:
    """Every warning of an evaluation in one list, each with its source: the evaluation's own
    (``evaluation``), each estimator's (``ope.NAME``), the behaviour model's (``behaviour``),
    each shift diagnostic's (``shift.NAME``) and the pooled ratios' (``pooled_shift``).
    Entries already gathered (dicts with a ``source``) are kept as they are."""
    out: list[dict[str, str]] = []

    def add(source: str, items: Any) -> None:
        for w in items or []:
            if isinstance(w, dict) and "message" in w:
                out.append({"source": str(w.get("source", source)), "message": str(w["message"])})
            else:
                out.append({"source": source, "message": str(w)})

    add("evaluation", m.get("warnings"))
    for name, r in (m.get("ope") or {}).items():
        add(f"ope.{name}", r.get("warnings"))
    add("behaviour", (m.get("behaviour") or {}).get("warnings"))
    for name, block in (m.get("shift") or {}).items():
        add(f"shift.{name}", (block or {}).get("warnings"))
    add("pooled_shift", (m.get("pooled_shift") or {}).get("warnings"))
    return out


def warning_count(m: dict[str, Any]) -> int:
    """How many warnings ``m`` holds: its gathered list when it has one (entries with a
    source), else (metrics written before) what :func:`gather_warnings` would gather."""
    top = m.get("warnings") or []
    if top and all(isinstance(w, dict) and "source" in w for w in top):
        return len(top)
    return len(gather_warnings(m))


def discount_note(m: dict[str, Any]) -> str | None:
    """A note when the policy was fitted with another discount than the one the evaluation
    uses (``metrics.json``'s ``discount``), else None."""
    d = m.get("discount") or {}
    fit, ev = d.get("fit"), d.get("evaluation")
    if not (_is_finite_number(fit) and _is_finite_number(ev)) or abs(fit - ev) <= 1e-12:
        return None
    return (f"the policy was fitted with gamma {fit:g}, the evaluation uses gamma {ev:g} ({d.get('evaluation_source', 'the dataset')}): "
            f"its values are judged by another objective than the one it optimised")


def headline(m: dict[str, Any], run_dir: str | Path | None = None) -> dict[str, Any]:
    """The summary box of an evaluation (see the module docstring). Intervals lose their level
    where the policy left the data's support (:func:`withdraw_levels`)."""
    shift = shift_verdict(m)
    m = withdraw_levels(m, left_support(m, shift))
    ranking = rank_estimators(m)
    conv = fit_convergence(run_dir)
    v = verdict_line(m, ranking, shift, conv)
    best = next((e for e in ranking if e["tier"] == 0), None)
    return {"best": best, "ranking": ranking, "shift": shift, "convergence": conv, "verdict": v,
            "n_warnings": warning_count(m), "outcome": v["outcome"], "discount_note": discount_note(m)}


def _f(x: Any) -> str:
    return f"{x:.3f}" if _is_finite_number(x) else "n/a"


def _problem_words(sim: str | None, policy: dict[str, Any], demonstrator: dict[str, Any]) -> str:
    from offline_adp.envs import PROBLEM_NAMES, problem_class

    if sim not in PROBLEM_NAMES:
        return ""
    return problem_class(sim).summary_line(policy, demonstrator)


def summary_lines(m: dict[str, Any], colour: bool = False) -> list[str]:
    """A short human summary of ``metrics.json``: estimand, simulator truth, best estimate,
    shift verdict, verdict line (its outcome word first, in the outcome's colour when
    ``colour``: a terminal), the discount note, the warnings. An interval is printed with
    its level, or "no level"."""
    h = m.get("headline")
    if not h or "outcome" not in h:  # written before the outcome word (or not at all)
        h = headline(m)
    lines = []
    if m.get("estimand"):
        lines.append(f"estimand: {m['estimand']['quantity']}")
    if "rollout" in m:
        p, d = m["rollout"]["policy"], m["rollout"].get("demonstrator")
        cost = f"simulator: policy cost {p['mean_discounted_cost']:.3f} [{p['interval'][0]:.3f}, {p['interval'][1]:.3f}]"
        if d is None:  # a simulator without a demonstrator (gym:ENV_ID)
            lines.append(f"{cost}; {m['rollout'].get('note', 'no demonstrator to compare with')}")
        else:
            words = _problem_words(m.get("simulator"), p, d)  # the ReferenceProblem's own summary words
            lines.append(f"{cost} vs demonstrator {d['mean_discounted_cost']:.3f}" + (f"; {words}" if words else ""))
    elif m.get("simulator_note"):
        lines.append(m["simulator_note"])
    if h.get("discount_note"):
        lines.append(f"discount: {h['discount_note']}")
    b = h["best"]
    others = [e for e in h["ranking"] if e["tier"] == 0 and (b is None or e["name"] != b["name"])][:2]
    top = b or next((e for e in h["ranking"] if e["tier"] == 1), None)
    if top is not None and (b is not None or top.get("shown_interval")):
        lo, hi = top["interval"] or top["shown_interval"]
        tol = 1e-9 * max(1.0, abs(top["estimate"]))
        outside = lo is not None and hi is not None and not lo - tol <= top["estimate"] <= hi + tol
        label = level_words(top)
        lines.append(f"off-policy ({top['name'].upper()}, most reliable): {_f(top['estimate'])} [{_f(lo)}, {_f(hi)}] "
                     f"({label}" + (f": {top['level_note'].split(':')[0]}" if top.get("level_note") and b is None else "")
                     + ")"
                     + (" (the interval excludes the estimate: its bootstrap replicates are shifted, so treat the "
                        "interval as unreliable)" if outside else "")
                     + (f" (bias-corrected by the bootstrap; plug-in {_f(top['plugin_estimate'])})"
                        if top.get("plugin_estimate") is not None else "")
                     + _model_reading(m, top)
                     + "".join(f"; {e['name'].upper()} {_f(e['estimate'])}" for e in others))
    else:
        lines.append(f"off-policy: {top['name'].upper()} {_f(top['estimate'])} (no interval: {top['reason']})" if top
                     else "off-policy: no usable estimate (see the report)")
    bad = [e["name"].upper() for e in h["ranking"] if e["tier"] == 2]
    if bad:
        lines.append(f"not usable here: {', '.join(bad)}")
    lines.append(f"shift: {h['shift']['text']}")
    out = h.get("outcome") or h["verdict"].get("outcome") or "cannot tell"
    word = f"[{out}]"
    if colour:
        word = f"\x1b[1;{OUTCOME_ANSI[out]}m{word}\x1b[0m"
    lines.append(f"verdict: {word} {h['verdict']['text']}")
    if h["n_warnings"]:
        lines.append(f"{h['n_warnings']} warnings (metrics.json 'warnings', each with its source; report)")
    return lines


def model_reading(m: dict[str, Any], name: str) -> float | None:
    """The model rollouts' reading of the value beside estimator ``name``'s, where they ran
    (None otherwise): a second reading (``evaluation.model_rollouts``) that FQE's interval
    holds; on path_tracking and CartPole it was the nearer one, on car_on_hill often not
    (docs/evaluation.md). The summary line and the report print it."""
    mr = (m.get("ope", {}).get(name) or {}).get("model_rollouts") or {}
    return float(mr["estimate"]) if _is_finite_number(mr.get("estimate")) else None


def _model_reading(m: dict[str, Any], best: dict[str, Any]) -> str:
    """', model rollouts of the logs read X' after the best estimate, where they ran."""
    x = model_reading(m, best["name"])
    return "" if x is None else f", model rollouts of the logs read {_f(x)}"
