"""Off-policy evaluation of a deterministic policy over continuous commands (from the logs).

What runs, and why the rest does not:

- **FQE over commands** (Algorithm 13 with ``Q(x, u)`` on the exact logged commands and the
  backup ``Q(x', pi(x'))``, :class:`~offline_adp.algorithms.fqe.FittedQEvaluation`), the
  quantity of :func:`~offline_adp.evaluation.offpolicy.declare_estimand`; its interval is
  the structure-conditional bootstrap over episodes (tree structure fixed, leaves
  re-averaged with each replicate's episode weights; a refit per replicate for a
  time-indexed FQE). Its coverage has not been measured on continuous commands, so the
  interval carries **no level** (``level: null``) and says so: a number printed as a 95%
  interval would be a claim nobody checked.
- **Command support**: at each logged state, the distance from the policy's command to the
  nearest command logged at the ``k`` nearest logged states, per component in units of the
  command's bound range (sup over components), against the same distance of the logged
  commands themselves to their neighbours' (leave-own-row-out); the share of states beyond
  the logged commands' 95% quantile is the policy's unsupported share.
- **Not usable**: IS, WIS, PDIS, WPDIS, DR, WDR and MIS weight each logged action by
  ``pi(a | x) / mu(a | x)``; a deterministic continuous policy puts probability 0 on every
  logged command it does not equal, so the weights need a smoothing kernel whose bandwidth
  trades bias for variance, and no kernel's coverage has been measured here. They are listed
  as not usable with that reason. The per-step density ratios and the PSDP bound need the
  policy's action probabilities too; the model rollouts of the logs read the action table's
  entries. All are listed the same way.

The verdict rules are the discrete evaluation's (:mod:`~offline_adp.evaluation.summary`),
fed with what ran: without a model rollout's exit mass or per-step ratios the logs alone
do not show support, so a logs-only verdict says it cannot tell.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset
from offline_adp.evaluation import ope
from offline_adp.evaluation.estimand import declare_estimand
from offline_adp.evaluation.fqe_interval import (
    fqe_interval,
    fqe_replicates,
    fqe_settings,
    with_truncation_bound,
)
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.qfunctions import NeighbourCommands

#: Neighbours whose logged commands count as "near" a state for the support check.
SUPPORT_NEIGHBOURS = 20
#: The logged commands' own quantile that calibrates the support radius.
SUPPORT_QUANTILE = 0.95

NOT_USABLE = {
    "importance sampling (IS, WIS, PDIS, WPDIS, DR, WDR, MIS)": (
        "a deterministic continuous policy gives probability 0 to every logged command it does not equal: the "
        "importance weights need a smoothing kernel, and no kernel's bandwidth has a measured coverage here"),
    "per-step density ratios and the PSDP bound": "they read the policy's action probabilities (see above)",
    "model rollouts of the logs": "the dynamics model reads the action table's entries, not commands",
}


def command_support(ds: TransitionDataset, policy: Any, k: int = SUPPORT_NEIGHBOURS) -> dict[str, Any]:
    """The share of logged states where ``policy`` commands farther from the commands
    logged nearby than the logged commands themselves are (see the module docstring)."""
    a, u = ds.arrays(), ds.commands()
    assert u is not None
    lo, hi = ds.info.action_table.bounds()
    span = np.where(np.isfinite(hi - lo) & (hi > lo), hi - lo, np.ptp(u, axis=0))
    span = np.where(span > 0, span, 1.0)
    cands = NeighbourCommands.from_data(a.obs, u, k + 1)
    _, rows = cands.neighbours(a.obs)

    def nearest(v: np.ndarray, cols: np.ndarray, own: np.ndarray | None) -> np.ndarray:
        d = (np.abs(v[:, None, :] - u[cols]) / span).max(axis=2)
        if own is not None:
            d = np.where(cols == own[:, None], np.inf, d)
        return d.min(axis=1)

    idx = np.arange(len(u))
    d_logged = nearest(u, rows, idx)  # each logged command against its neighbours' (not its own row)
    radius = float(np.quantile(d_logged[np.isfinite(d_logged)], SUPPORT_QUANTILE))
    d_pi = nearest(np.asarray(policy.commands(a.obs, a.step), np.float64), rows[:, :k], None)
    return {"fraction": float(np.mean(d_pi > radius)), "radius": radius, "neighbours": k,
            "method": f"the policy's command against the commands logged at the {k} nearest logged states (sup over "
                      "components, in units of each bound range); unsupported beyond the logged commands' own "
                      f"{SUPPORT_QUANTILE:.0%} quantile ({radius:.3g})"}


def fqe_over_commands(ds: TransitionDataset, policy: Any, cfg: EvaluationSettings, est_def: Any,
                      say: Callable[[str], None]) -> ope.OPEResult:
    """FQE's estimate and its (unlabelled) bootstrap interval over episodes."""
    a = ds.arrays()
    fqe_T = est_def.fqe_horizon
    params = fqe_settings(cfg.fqe_params, fqe_T)  # the discrete path's merge of the user's settings
    conditional = params.get("mode") == "frozen" and fqe_T is None and not params.get("validation_fraction")
    say("fitted Q evaluation over commands")
    fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=est_def.gamma, random_state=cfg.seed, **params).fit(ds)
    if conditional:
        fqe.settle()
    est = float(fqe.value_)
    em = ope.EpisodeMatrix.build(a.episode, a.step, est_def.horizon)
    n_reps = fqe_replicates(cfg.fqe_bootstrap, conditional)
    counts = ope.bootstrap_counts(em.n_episodes, n_reps, cfg.seed)
    if n_reps:
        say(f"FQE bootstrap ({n_reps} replicates)")
    start = a.step == 0
    if conditional:
        reps = [fqe.reweighted_value(c[em.row_episode], rtol=1e-5) for c in counts]
    else:  # a refit per replicate; its start value weighted by the replicate's episode counts
        reps = []
        for c in counts:
            w = c[em.row_episode].astype(np.float64)
            rep = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=est_def.gamma, random_state=cfg.seed,
                                    **params).fit(ds, sample_weight=w)
            v0, w0 = rep.q_function_.values(a.obs[start], 0)[:, 0], w[start]
            reps.append(float(np.sum(w0 * v0) / np.sum(w0)) if np.sum(w0) > 0 else float("nan"))
    res = fqe_interval(est, reps, em.n_episodes)
    res = replace(res, level=None, interval_method=res.interval_method + (
        " (structure-conditional: tree structure fixed, leaves re-averaged)" if conditional else ""),
        warnings=[*res.warnings, "continuous commands: this interval's coverage has not been measured, so it carries "
                  "no level (it is not a 95% interval)"])
    return with_truncation_bound(res, est_def.tail_bound)


def continuous_offpolicy(ds: TransitionDataset, policy: Any, cfg: EvaluationSettings, *, target_horizon: int | None,
                         start: str | None, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The off-policy part of ``metrics.json`` for a continuous policy (module docstring)."""
    say = progress or (lambda _m: None)
    est_def = declare_estimand(ds, policy, cfg.horizon, cfg.estimand, target_horizon=target_horizon, start=start)
    fq = fqe_over_commands(ds, policy, cfg, est_def, say)
    say("command support")
    support = command_support(ds, policy)
    a = ds.arrays()
    em = ope.EpisodeMatrix.build(a.episode, a.step, est_def.horizon)
    from offline_adp.evaluation.offpolicy import behaviour_value

    warnings = [f"not computed for continuous commands: {k}: {why}" for k, why in NOT_USABLE.items()]
    return {
        "estimand": est_def.as_dict(),
        "horizon": est_def.horizon,
        "gamma": est_def.gamma,
        "commands": {"dims": list(ds.info.action_table.dims), "units": list(ds.info.action_table.units),
                     "low": None if ds.info.action_table.low is None else list(ds.info.action_table.low),
                     "high": None if ds.info.action_table.high is None else list(ds.info.action_table.high)},
        "behaviour_value": behaviour_value(em, a.cost, est_def.gamma),
        "behaviour": {"source": "logged commands", "support_violations": support, "warnings": []},
        "ope": {"fqe": {**fq.as_dict(), "method": "fqe"}},
        "ope_default": "fqe",
        "not_usable": dict(NOT_USABLE),
        "shift": {},
        "warnings": warnings,
    }
