"""The headline of an evaluation: what a person is told first, and nothing that flatters.

:func:`headline` condenses ``metrics.json`` into

- the **best estimate**: estimators ranked by reliability (:func:`rank_estimators`), the
  degenerate and the impossible ones never quoted;
- the **shift verdict**: the most trustworthy diagnostic available, named: classifier
  ratios when a simulator was used; from logs only, per-step ratios only when every step
  has enough states (:data:`~offline_adp.evaluation.shift.MIN_STATES_PER_STEP`), else
  "not enough data per step" and, for a stationary policy, ratios pooled over time;
- the **verdict line** (:mod:`offline_adp.evaluation.verdict`): better or worse than the
  behaviour, with what confidence; whether the policy left the data's support; whether the
  fit converged (``run.json`` / ``model/history.csv``);
- the count of warnings;
- where the logs are the fit's own (``metrics.json``'s ``logs``), one clause in the verdict
  saying FQE-based readings may read optimistic (:mod:`offline_adp.evaluation.logs`).

:func:`summary_lines` prints it (the CLI's summary after ``evaluate`` and ``run``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.data.files import read_json_file, read_table_file

# the structure of metrics.json and its reader (evaluation/metrics_file.py), importable from here too
from offline_adp.evaluation.metrics_file import MetricsFile, read_metrics  # noqa: F401
from offline_adp.evaluation.ope import degenerate_floor, on_policy, rounding_tol

# the verdict and its parts (evaluation/verdict.py), importable from here too
from offline_adp.evaluation.verdict import (  # noqa: F401
    FIT_SETTLED,
    FIT_UNSETTLED,
    MIN_SUPPORT_PARTICLES,
    MODEL_EXIT_FRACTION,
    OUTCOME_ANSI,
    OUTCOME_CLASS,
    OUTCOME_COLOUR,
    OUTCOMES,
    SUPPORT_FRACTION,
    _is_finite_number,
    demonstrator_side,
    left_states,
    left_support,
    level_words,
    outcome_of,
    rollouts_of_another_value,
    side_of_behaviour,
    stored_lines,
    verdict_line,
)

#: Human names of the estimators.
ESTIMATOR_NAMES = {
    "fqe": "FQE (fitted Q evaluation)", "is": "IS (trajectory importance sampling)", "wis": "WIS (weighted IS)",
    "pdis": "PDIS (per-decision IS)", "wpdis": "WPDIS (weighted per-decision IS)", "dr": "DR (doubly robust)",
    "wdr": "WDR (weighted doubly robust)", "mis": "MIS (marginalised IS)",
    "model": "MODEL (rollouts of a model of the logged dynamics)",
}
#: Estimators from the least to the most fragile under distribution shift: model-based FQE
#: (the default), doubly robust, marginalised IS (state ratios), then the trajectory-weighted ones.
ROBUSTNESS = ("fqe", "wdr", "dr", "mis", "wpdis", "pdis", "wis", "is")
#: A classifier AUC above this: pi's states and the data's are almost separable at that step.
AUC_SEPARABLE = 0.95


def rank_estimators(m: dict[str, Any]) -> list[dict[str, Any]]:
    """Estimators ordered by reliability, each with a tier and the reason.

    Tier 0 ``reliable``: finite, inside the possible range, targets the declared estimand,
    has an interval. Tier 1 ``no interval``: the interval was withheld (degenerate-ish
    weights) or not computed. Tier 2 ``not usable``: degenerate weights, an estimate outside
    the possible range of the cost, or another estimand. Within a tier, by
    :data:`ROBUSTNESS` (never by interval width: a narrow interval from fixed, wrong
    ratios would flatter), with two regimes ahead of it: on the logging policy's own weights
    (:func:`~offline_adp.evaluation.ope.on_policy`) WDR, then DR, lead, with their paired
    difference from the logged cost (``vs_logged``); else the model rollouts lead where they
    carry a level.
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
        elif rng and not (rng[0] - rounding_tol(*rng) <= est <= rng[1] + rounding_tol(*rng)):
            reasons.append(f"outside the possible range [{rng[0]:.4g}, {rng[1]:.4g}] of the cost")
        # the ESS floor again for files written before it (compare reuses them): the 1% rule is in their flag
        if r.get("degenerate") or (_is_finite_number(r.get("ess")) and r["ess"] < degenerate_floor(name, 0)):
            ess = r.get("ess")
            reasons.append("degenerate importance weights" + (f" (effective sample size {ess:.1f})"
                                                              if _is_finite_number(ess) else ""))
        if r.get("comparable") is False:
            reasons.append("estimates another quantity than the one asked for")
        tier = 2 if reasons else (0 if has_iv else 1)
        # level withdrawn (support left)
        if tier == 1 and _is_finite_number(iv[0]) and _is_finite_number(iv[1]) and r.get("level_note"):
            reasons.append(f"its interval [{iv[0]:.4g}, {iv[1]:.4g}] carries no level: {r['level_note']}")
        # an interval without a level: shown, never quoted
        elif tier == 1 and _is_finite_number(iv[0]) and _is_finite_number(iv[1]):
            reasons.append(f"its interval [{iv[0]:.4g}, {iv[1]:.4g}] has no measured coverage (no level)")
        elif tier == 1:
            reasons.append(r.get("interval_method", "no interval"))
        width = (iv[1] - iv[0]) if has_iv else np.inf
        vs = r.get("vs_logged") or [None, None]
        paired = (tier == 0 and name in ("dr", "wdr") and on_policy(r) and all(_is_finite_number(v) for v in vs)
                  and vs[0] <= vs[1])
        out.append({"name": name, "label": ESTIMATOR_NAMES.get(name, name.upper()), "tier": tier,
                    "on_policy": paired, "vs_logged": list(vs) if paired else None,
                    "ess_fraction": r["weight_diagnostics"]["ess_fraction"] if paired else None,
                    "tier_label": ("reliable", "no interval", "not usable")[tier], "reason": "; ".join(reasons),
                    "estimate": est, "interval": iv if has_iv else None, "level": r.get("level") if has_iv else None,
                    "shown_interval": iv if _is_finite_number(iv[0]) and _is_finite_number(iv[1]) else None,
                    "level_note": r.get("level_note"), "width": width,
                    "plugin_estimate": r.get("plugin_estimate")})
    order = estimator_order(out)
    out.sort(key=lambda e: (e["tier"], order.get(e["name"], len(order)), e["name"]))
    for i, e in enumerate(out):
        e["rank"] = i + 1
        e["width"] = None if not np.isfinite(e["width"]) else e["width"]
    return out


def estimator_order(entries: list[dict[str, Any]]) -> dict[str, float]:
    """The order within a tier: :data:`ROBUSTNESS`, with the model rollouts first where they carry a
    level (overlapping FQE's interval, within the logged states: evaluation/model_bootstrap.py; without
    one, FQE's hull of both readings comes first), and before them, on the logging policy's own
    weights, the doubly robust estimate (WDR before DR: the logged episodes are nearly the policy's
    own, with FQE only a control variate; ope.ON_POLICY_ESS_FRACTION)."""
    order: dict[str, float] = {k: i for i, k in enumerate(ROBUSTNESS)}
    order["model"] = -1 if any(e["name"] == "model" and e["tier"] == 0 for e in entries) else 0.5
    for name, key in (("dr", -2.5), ("wdr", -3)):
        if any(e["name"] == name and e["on_policy"] for e in entries):
            order[name] = key
    return order


#: what a density-ratio fit's warnings said where it left the ratios at 1, in a metrics.json
#: written before the fits listed those warnings apart (``unmeasured``)
_UNMEASURED = ("set to 1", "left at 1", "nothing to pool")


def _unmeasured(d: dict[str, Any], block: dict[str, Any] | None) -> dict[str, Any]:
    """``d`` (a shift verdict) where ``block``'s ratio fit left ratios at 1 somewhere
    (:attr:`~offline_adp.evaluation.shift.DensityRatios.unmeasured`): those ratios are no
    measurement, so the verdict does not read as "no shift"."""
    block = block or {}
    gone = (list(block["unmeasured"]) if "unmeasured" in block else
            [w for w in block.get("warnings") or [] if isinstance(w, str) and any(u in w for u in _UNMEASURED)])
    if not gone:
        return d
    return {**d, "enough_data": False, "unmeasured": gone,
            "text": d["text"] + f"; NOT MEASURED at {len(gone)} step(s) ({gone[0]}): ratios of 1 there are no "
                                "finding of no shift"}


def shift_verdict(m: dict[str, Any]) -> dict[str, Any]:
    """The most trustworthy shift diagnostic available, named, with its verdict text (and
    where its ratio fit could not run, saying so: :func:`_unmeasured`)."""
    shift = m.get("shift", {})
    if "classifier" in shift:
        d = pd.DataFrame(shift["classifier"]["per_step"])
        if not d.empty:
            i = d["ess_fraction"].idxmin()
            sep = int((d.get("auc", pd.Series(dtype=float)) > AUC_SEPARABLE).sum())
            unc = float(d["uncovered"].max()) if "uncovered" in d else 0.0
            text = (f"classifier ratios (simulator): worst-step ESS/n {d.loc[i, 'ess_fraction']:.3f} at t = "
                    f"{int(d.loc[i, 'step'])}; AUC > {AUC_SEPARABLE} at {sep} of {len(d)} steps")
            return _unmeasured({"method": "classifier", "ess_fraction": float(d.loc[i, "ess_fraction"]),
                                "step": int(d.loc[i, "step"]),
                                "separable_steps": sep, "n_steps": int(len(d)), "max_uncovered": unc, "text": text,
                                "enough_data": True}, shift["classifier"])
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
            return _unmeasured(out, pooled)
        return out
    ws = m.get("worst_step", {})
    if ws:
        return _unmeasured({"method": "recursion", "ess_fraction": ws.get("ess_fraction"), "step": ws.get("step"),
                            "text": f"ratio recursion (logs only): worst-step ESS/n {ws['ess_fraction']:.3f} at t = "
                                    f"{ws['step']}", "enough_data": True}, shift.get("recursion"))
    return {"method": "none", "ess_fraction": None, "text": "no shift diagnostic", "enough_data": False}


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
    from_history = _history_convergence(hist, tol) if hist.exists() else None
    if from_history is not None:
        return from_history
    status = info.get("status")
    return {"verdict": "unknown", "text": f"fit convergence unknown (status {status})" if status else
            "fit convergence unknown"}


def _history_convergence(hist: Path, tol: Any) -> dict[str, Any] | None:
    """The convergence a run's ``model/history.csv`` shows (its last ``sup_dq`` against
    ``tol``; a finite-horizon fit's ``step`` rows), or None when it shows none."""
    h = read_fit_history(hist)
    if "sup_dq" in h and h["sup_dq"].notna().any() and ("step" not in h or h["step"].isna().all()):
        last = float(h["sup_dq"].dropna().iloc[-1])
        k = int(h["iteration"].iloc[-1]) if "iteration" in h else len(h)
        if tol is not None:
            if not _is_finite_number(tol):
                from offline_adp.errors import ArtifactError

                raise ArtifactError(f"{hist.parent.parent / 'config.json'}: params.tol must be a finite number, "
                                    f"found {tol!r:.60}")
            ok = last < float(tol)
            return {"verdict": "converged" if ok else "not converged", "last_change": last, "tol": tol,
                    "text": f"fit {'converged' if ok else 'did NOT converge'}: last change {last:.3g} "
                            f"{'<' if ok else '>='} tol {tol:g} after {k} iterations", "source": "history.csv"}
        return {"verdict": "unknown", "last_change": last,
                "text": f"fit ran {k} iterations, last change {last:.3g} (no tol set)", "source": "history.csv"}
    if "step" in h and h["step"].notna().any():
        return {"verdict": "finite horizon", "text": "fit: finite horizon (backward induction, no convergence to "
                "check)", "source": "history.csv"}
    return None


def read_fit_history(path: Path) -> pd.DataFrame:
    """A run's ``model/history.csv`` with the columns the convergence summary reads checked:
    at most :data:`~offline_adp.algorithms.checkpoint.MAX_HISTORY_BYTES`; ``iteration``
    whole numbers from 1, ``sup_dq`` numbers >= 0 (NaN: not measured), ``step`` numbers.
    Anything else is an :class:`~offline_adp.errors.ArtifactError` naming the file, the
    column and the row, not a ValueError from ``float()`` or ``int()``."""
    from offline_adp.algorithms.checkpoint import MAX_HISTORY_BYTES
    from offline_adp.errors import ArtifactError

    size = path.stat().st_size if path.is_file() else 0
    if size > MAX_HISTORY_BYTES:
        raise ArtifactError(f"{path}: {size} bytes, more than a fit's history can be ({MAX_HISTORY_BYTES}); "
                            "fit the run again")
    h = read_table_file(path)
    for col, ok, what in (("iteration", lambda v: v.notna() & (v >= 1) & (v <= 2**53) & (v == np.floor(v)),
                           "whole numbers 1, 2, ..."),
                          ("sup_dq", lambda v: v.isna() | (v >= 0), "numbers >= 0"),
                          ("step", lambda v: v.isna() | np.isfinite(v), "numbers")):
        if col not in h.columns or not len(h):
            continue
        raw = h[col]
        v = pd.Series(np.nan, index=raw.index) if pd.api.types.is_bool_dtype(raw) else pd.to_numeric(
            raw, errors="coerce")
        bad = ~ok(v.astype(np.float64)) | (v.isna() & raw.notna())
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            found = raw.iloc[i].item() if hasattr(raw.iloc[i], "item") else raw.iloc[i]
            raise ArtifactError(f"{path}: column {col!r} must hold {what}, found {found!r:.40} (row {i + 1}); "
                                "the file is damaged: fit the run again")
        h[col] = v
    return h


#: Why an off-policy interval carries no level once the policy left the data's support.
LEVEL_WITHDRAWN = ("the policy left the data's support, where the {model} extrapolates: the bootstrap measures "
                   "the sampling noise, not that extrapolation, so this is not a {level:.0%} interval there")


def withdraw_levels(m: dict[str, Any], left: list[str] | None = None) -> dict[str, Any]:
    """``m`` with every off-policy interval's level withdrawn (``level: null``, the former
    one as ``nominal_level``, the reason as ``level_note``, ``withdrawn_by: "support"``) when the policy left the data's
    support (``left``, default :func:`left_support`): the interval is still shown, never
    quoted with a level it does not have. The model rollouts' level stays where only the
    policy's actions left the data (:func:`~offline_adp.evaluation.verdict.left_states` empty).
    Returns a new dict (``m`` is not changed); idempotent."""
    if left is None:
        left = left_support(m, shift_verdict(m))
    if not left:
        return m
    # the model rollouts' label already answers for the policy's actions (checked against FQE's
    # per-action support bounds); it is withdrawn only where the policy's states leave the data
    keep_model = not left_states(m, shift_verdict(m))
    ope = {}
    for k, r in m["ope"].items():
        if r.get("level") is not None and not (k == "model" and keep_model):
            # DR/WDR's paired difference is kept aside with the level (nominal_vs_logged): never read without one
            paired = {"nominal_vs_logged": r["vs_logged"]} if r.get("vs_logged") is not None else {}
            r = {**{kk: v for kk, v in r.items() if kk != "vs_logged"}, **paired, "nominal_level": r["level"],
                 "level": None, "withdrawn_by": "support",
                 "level_note": LEVEL_WITHDRAWN.format(level=r["level"], model="model of the logged dynamics"
                                                      if k == "model" else "value model")}
        ope[k] = r
    return {**m, "ope": ope}


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
    return (f"the policy was fitted with gamma {fit:g}, the evaluation uses gamma {ev:g} "
            f"({d.get('evaluation_source', 'the dataset')}): "
            f"its values are judged by another objective than the one it optimised")


def headline(m: dict[str, Any], run_dir: str | Path | None = None) -> dict[str, Any]:
    """The summary box of an evaluation (see the module docstring). Intervals lose their level
    where the policy left the data's support (:func:`withdraw_levels`)."""
    shift = shift_verdict(m)
    m = withdraw_levels(m, left_support(m, shift))
    ranking = rank_estimators(m)
    conv = fit_convergence(run_dir)
    from offline_adp.evaluation.logs import in_sample_note, with_note

    logs_note = in_sample_note(m)  # the logs are the fit's own: one clause in the why line
    v = with_note(verdict_line(m, ranking, shift, conv), logs_note)
    best = next((e for e in ranking if e["tier"] == 0), None)
    return {"best": best, "ranking": ranking, "shift": shift, "convergence": conv, "verdict": v,
            "n_warnings": warning_count(m), "outcome": v["outcome"], "discount_note": discount_note(m),
            "logs_note": logs_note}


def _f(x: Any) -> str:
    """Three decimals; three significant digits below 0.01 in size (costs of 1e-12 read as
    such, not as 0.000)."""
    if not _is_finite_number(x):
        return "n/a"
    return f"{x:.3f}" if x == 0 or abs(x) >= 0.01 else f"{x:.3g}"


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
    if (m.get("estimand") or {}).get("quantity"):
        lines.append(f"estimand: {m['estimand']['quantity']}")
    if "rollout" in m:
        p, d = m["rollout"]["policy"], m["rollout"].get("demonstrator")
        other = rollouts_of_another_value(m)
        cost = (f"simulator{f' ({other})' if other else ''}: policy cost {_f(p['mean_discounted_cost'])} "
                f"[{_f(p['interval'][0])}, {_f(p['interval'][1])}]")
        if d is None:  # a simulator without a demonstrator (gym:ENV_ID)
            lines.append(f"{cost}; {m['rollout'].get('note', 'no demonstrator to compare with')}")
        else:
            words = _problem_words(m.get("simulator"), p, d)  # the ReferenceProblem's own summary words
            lines.append(f"{cost} vs demonstrator {d['mean_discounted_cost']:.3f}" + (f"; {words}" if words else ""))
    elif m.get("simulator_note"):
        lines.append(m["simulator_note"])
    if h.get("discount_note"):
        lines.append(f"discount: {h['discount_note']}")
    lines += [f"logs: {m['logs']['description']}"] if (m.get("logs") or {}).get("kind") == "held_out" else []
    b = h["best"]
    others = [e for e in h["ranking"] if e["tier"] == 0 and (b is None or e["name"] != b["name"])][:2]
    top = b or next((e for e in h["ranking"] if e["tier"] == 1), None)
    if top is not None and (b is not None or top.get("shown_interval")):
        lo, hi = top["interval"] or top["shown_interval"]
        tol = 0.0 if lo is None or hi is None else rounding_tol(top["estimate"], lo, hi)
        outside = lo is not None and hi is not None and not lo - tol <= top["estimate"] <= hi + tol
        label = level_words(top)
        lines.append(f"off-policy ({top['name'].upper()}, most reliable): {_f(top['estimate'])} [{_f(lo)}, {_f(hi)}] "
                     f"({label}" + (f": {top['level_note'].split(':')[0]}" if top.get("level_note") and b is None
                                    else "")
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
    three = stored_lines(h["verdict"])  # the headline's verdict and why (the estimate is printed above)
    lines += [f"verdict: {word} {three[1]}", three[2]] if three else [f"verdict: {word} {h['verdict']['text']}"]
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
