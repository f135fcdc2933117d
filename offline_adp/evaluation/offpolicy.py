"""From logs alone: behaviour model, FQE, importance-sampling family, density ratios,
shift diagnostics and the PSDP bound, for one policy on one dataset.

Access model: trace data only (a simulator, when given, adds the classifier ratios).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset
from offline_adp.evaluation import ope, shift
from offline_adp.evaluation.behaviour import (
    BehaviourEstimate,
    estimate_behaviour,
    support_violations,
)
from offline_adp.parallel import TaskMap, local_map
from offline_adp.policies import Policy

#: FQE settings for evaluation: the frozen-structure fast path keeps bootstrap refits cheap.
#: Ernst's extra-trees defaults matter: larger leaves average Q over actions and bias FQE
#: (measured on path_tracking: min_samples_leaf=5 doubled the estimated cost).
#: 20 trees instead of 50 keep a 100k-transition evaluation within two minutes.
DEFAULT_FQE = {"regressor": "extra_trees", "mode": "frozen", "n_iterations": 60, "tol": 1e-4,
               "regressor_params": {"n_estimators": 20}}


@dataclass
class OffPolicyResult:
    """Everything :func:`off_policy` computed (see its docstring)."""

    gamma: float
    horizon: int
    behaviour: BehaviourEstimate
    estimates: dict[str, ope.OPEResult]
    ratios: shift.DensityRatios
    diagnostics: pd.DataFrame
    support: dict[str, Any]
    eps: np.ndarray
    fqe: FittedQEvaluation
    extra_ratios: dict[str, tuple[shift.DensityRatios, pd.DataFrame]] = field(default_factory=dict)
    bounds: dict[str, dict[str, Any]] = field(default_factory=dict)


def evaluation_horizon(ds: TransitionDataset, horizon: int | None = None) -> tuple[int, float, int | None]:
    """(T for trajectory estimators, gamma, FQE horizon or None for discounted FQE).

    T is the data's longest episode, capped by ``info.horizon`` and by ``horizon``.
    """
    a = ds.arrays()
    gamma = ds.info.gamma if ds.info.gamma is not None else 1.0
    T = int(a.step.max()) + 1
    for cap in (ds.info.horizon, horizon):
        if cap is not None:
            T = min(T, int(cap))
    return T, float(gamma), (T if gamma >= 1.0 else None)


def residual_advantage(qv: np.ndarray, probs: np.ndarray, step: np.ndarray, gamma: float, T: int) -> np.ndarray:
    """``eps_t = gamma^t E_{mu_t}[ sum_a pi(a|x) Q^pi_t(x, a) - min_a Q^pi_t(x, a) ]`` over the data's
    step-t states, from ``qv = Q^pi(x_i, .)`` and ``probs = pi(. | x_i)`` at every row."""
    gap = (probs * qv).sum(axis=1) - qv.min(axis=1)
    eps = np.zeros(T)
    for t in range(T):
        m = step == t
        if m.any():
            eps[t] = gamma**t * float(gap[m].mean())
    return eps


def psdp_bound(eps: np.ndarray, ratio_ucb: np.ndarray, pooled_ucb: float | None = None) -> dict[str, float]:
    """PSDP's performance bound (Bagnell et al. 2003, Theorem 2) as a plug-in estimate.

    ``J(pi) - J(pi_ref) <= sum_t eps_t * ||mu_ref^t / mu^t||_inf`` (per-step form), and
    with the averaged distributions ``T * mean_t(eps_t) * ||sum_t mu_ref^t / sum_t mu^t||_inf``.
    """
    out = {"per_step": float(np.sum(eps * ratio_ucb))}
    if pooled_ucb is not None:
        out["averaged"] = float(len(eps) * np.mean(eps) * pooled_ucb)
    return out


def _start_value(fqe: FittedQEvaluation, x0: np.ndarray, pi_x0: np.ndarray, w0: np.ndarray | None) -> float:
    """sum_a pi(a|x0) Q(x0, a), averaged over the start states (weighted by ``w0``)."""
    v0 = (pi_x0 * fqe.q_function_.values(x0, 0)).sum(axis=1)
    return float(v0.mean()) if w0 is None else float(np.sum(w0 * v0) / np.sum(w0))


def _reweighted_replicate(w: np.ndarray, *, fqe: FittedQEvaluation) -> float:
    return fqe.reweighted_value(w)


def _refit_replicate(w: np.ndarray, *, ds: TransitionDataset, params: dict[str, Any], x0: np.ndarray,
                     pi_x0: np.ndarray, start: np.ndarray) -> float:
    return _start_value(FittedQEvaluation(**params).fit(ds, sample_weight=w), x0, pi_x0, w[start])


def off_policy(
    ds: TransitionDataset,
    policy: Policy,
    *,
    fqe_params: dict[str, Any] | None = None,
    n_boot: int = 200,
    n_boot_fqe: int = 10,
    level: float = 0.95,
    behaviour_classifier: Any = "lightgbm",
    clip: float = 1e-3,
    ratio_regressor: Any = "extra_trees",
    ratio_params: dict | None = None,
    reference_policies: dict[str, Policy] | None = None,
    policy_states: list[np.ndarray] | None = None,
    k_support: int = 20,
    horizon: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    task_map: TaskMap | None = None,
) -> OffPolicyResult:
    """Evaluate ``policy`` from the dataset alone.

    Steps: behaviour probabilities (logged or a classifier) and support violations;
    FQE with a trajectory bootstrap; IS, WIS, PDIS, WPDIS, DR, WDR; per-step density
    ratios by the recursion and MIS from them; diagnostics; eps_t from the FQE
    Q-functions and the PSDP bound for each reference policy (``self`` always; others
    from ``reference_policies``). With ``policy_states`` (pi's states per step from a
    simulator) the classifier ratios are added. ``task_map`` runs the FQE bootstrap
    replicates (default: here; see :mod:`offline_adp.parallel`).
    """
    say = progress or (lambda _msg: None)
    a = ds.arrays()
    T, gamma, fqe_T = evaluation_horizon(ds, horizon)
    say("behaviour policy")
    beh = estimate_behaviour(a.obs, a.action, ds.n_actions, a.behavior_prob, classifier=behaviour_classifier, clip=clip)
    target = policy.probabilities(a.obs, a.step)
    support = support_violations(target, beh.all_probs, a.step)
    rho = target[np.arange(len(a)), a.action] / beh.logged_prob
    em = ope.EpisodeMatrix.build(a.episode, a.step, T)

    say("fitted Q evaluation")
    user = dict(fqe_params or {})
    base = DEFAULT_FQE if user.get("regressor", DEFAULT_FQE["regressor"]) == DEFAULT_FQE["regressor"] else \
        {k: v for k, v in DEFAULT_FQE.items() if k not in ("mode", "regressor_params")}
    params = {**base, **user}
    if fqe_T is not None:
        params.pop("tol", None)
        params.pop("n_iterations", None)
    start = a.step == 0
    x0 = a.obs[start]
    pi_x0 = policy.probabilities(x0, 0)  # once, not per bootstrap replicate
    conditional = params.get("mode") == "frozen" and fqe_T is None and not params.get("validation_fraction")
    fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=gamma, random_state=seed, **params).fit(ds)
    est = _start_value(fqe, x0, pi_x0, None)
    counts = ope.bootstrap_counts(em.n_episodes, n_boot_fqe, seed)
    on_done = lambda b: say(f"FQE bootstrap {b + 1}/{n_boot_fqe}")  # noqa: E731
    run = task_map or local_map
    if conditional:  # same trees, leaves re-averaged with the replicate's weights
        reps = run(_reweighted_replicate, [c[em.row_episode] for c in counts], shared={"fqe": fqe}, on_done=on_done)
    else:
        reps = run(_refit_replicate, [c[em.row_episode] for c in counts], on_done=on_done,
                   shared={"ds": ds, "params": {"policy": policy, "horizon": fqe_T, "gamma": gamma, "random_state": seed,
                                                **params}, "x0": x0, "pi_x0": pi_x0, "start": start})
    estimates = {"fqe": ope.fqe_interval(est, reps, em.n_episodes, level)}
    if conditional and n_boot_fqe:
        estimates["fqe"].interval_method += " (structure-conditional: tree structure fixed, leaves re-averaged)"
        estimates["fqe"].warnings.append("the interval keeps the fitted tree structure, so it omits the structure's own "
                                         "variability (a structure-conditional bootstrap)")
    say("importance sampling")
    estimates.update(ope.importance_sampling_estimates(em, a.cost, rho, gamma, n_boot=n_boot, level=level, seed=seed))
    qv = fqe.q_function_.values(a.obs, a.step)
    estimates.update(ope.doubly_robust_estimates(em, a.cost, rho, qv[np.arange(len(a)), a.action],
                                                 (target * qv).sum(axis=1), gamma, n_boot=n_boot, level=level, seed=seed))
    say("density ratios")
    ratios = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho, regressor=ratio_regressor,
                                       regressor_params=ratio_params, horizon=T)
    estimates["mis"] = ope.marginalised_is_estimate(em, a.cost, rho, ratios.w, gamma, n_boot=n_boot, level=level, seed=seed)
    ope.flag_against(estimates, "fqe")
    diag = shift.diagnostics(ratios, a.obs, k=k_support, seed=seed)
    eps = residual_advantage(qv, target, a.step, gamma, T)
    res = OffPolicyResult(gamma, T, beh, estimates, ratios, diag, support, eps, fqe)
    res.bounds["self"] = {**psdp_bound(eps, diag["sup_ucb"].to_numpy()[:T],
                                       shift.pooled_ratio_ucb(ratios, a.obs, k=k_support, seed=seed)),
                          "poorly_covered_mass": float(diag["poorly_covered_mass"].max()), "method": "recursion"}
    for name, ref in (reference_policies or {}).items():
        say(f"reference policy {name}")
        rho_ref = ref.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / beh.logged_prob
        r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho_ref, regressor=ratio_regressor,
                                      regressor_params=ratio_params, horizon=T)
        d = shift.diagnostics(r, a.obs, k=k_support, seed=seed)
        res.extra_ratios[name] = (r, d)
        res.bounds[name] = {**psdp_bound(eps, d["sup_ucb"].to_numpy()[:T], shift.pooled_ratio_ucb(r, a.obs, k=k_support, seed=seed)),
                            "poorly_covered_mass": float(d["poorly_covered_mass"].max()), "method": "recursion"}
    if policy_states is not None:
        say("classifier density ratios")
        r = shift.ratios_by_classifier(a.obs, a.step, policy_states[:T], seed=seed)
        res.extra_ratios["classifier"] = (r, shift.diagnostics(r, a.obs, k=k_support, seed=seed))
    return res
