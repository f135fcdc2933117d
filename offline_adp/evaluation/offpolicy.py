"""From logs alone: one policy's value on one dataset, as a short list of named stages.

:func:`off_policy` runs them in order; each is a function here or in the module named,
whose docstring states its mathematics:

1. **Estimand** (:func:`~offline_adp.evaluation.estimand.declare_estimand`): the quantity
   ``J(pi) = E[sum_{t<T} gamma^t c_t]`` (or the infinite-horizon value) every estimator targets.
2. **Behaviour model** (:func:`behaviour_model`): ``pi_b``, the ratios
   ``rho_i = pi(a_i | x_i, t_i) / pi_b(a_i | x_i)`` and the support violations.
3. **FQE and its interval** (:func:`~offline_adp.evaluation.fqe_interval.fqe_with_interval`):
   bootstrap, support bounds, model-rollout hull and truncation bound, in one module.
4. **Importance-weighted estimators**: IS, WIS, PDIS, WPDIS (:mod:`~offline_adp.evaluation.ope`);
   DR and WDR with a cross-fitted Q (:func:`residual_advantages`, :func:`doubly_robust`);
   MIS with per-step density ratios (:func:`marginalised`).
5. **Support** (:func:`~offline_adp.evaluation.estimand.with_possible_range`,
   :func:`~offline_adp.evaluation.estimand.confined`): the value's possible range, and every
   estimator that cannot see the estimand said so.
6. **Verdict inputs** (:func:`verdict_inputs`, :func:`shift_and_bounds`): the behaviour's
   logged value, the logged cost distributions, the density-ratio diagnostics and the
   PSDP bound for each reference policy.

Each stage returns new values (an :class:`~offline_adp.evaluation.ope.OPEResult` is built,
never changed in place). Access model: trace data only (a simulator, when given, adds the
classifier ratios).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.evaluation import ope, risk, shift
from offline_adp.evaluation.batch import BatchInputs, fit_batch
from offline_adp.evaluation.behaviour import (
    BehaviourEstimate,
    estimate_behaviour,
    exact_state_support,
    support_violations,
)

# Estimand and FQE names are importable from here too (evaluation/run.py, scripts).
from offline_adp.evaluation.estimand import (  # noqa: F401
    TAIL_NEGLIGIBLE,
    Estimand,
    as_quoted,
    declare_estimand,
    episode_ends,
    evaluation_horizon,
    short_episodes,
    step_cost_range,
    with_possible_range,
)
from offline_adp.evaluation.fqe_interval import (  # noqa: F401
    DEFAULT_FQE,
    FQE_REPLICATE_FLOOR,
    FQE_REPLICATE_ROUGH,
    FQEFit,
    fqe_replicates,
    fqe_with_interval,
)
from offline_adp.evaluation.model_bootstrap import model_estimate
from offline_adp.evaluation.psdp_eps import (  # crossfit_residual_advantage, CrossFitError: also reached from here
    PSDP_EPS_FOLDS,
    CrossFitError,
    bound_entry,
    crossfit_combine,
    crossfit_residual_advantage,
    episode_groups,
    residual_advantage,
)
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.parallel import TaskMap
from offline_adp.policies import Policy, is_stationary


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
    fqe: FittedQEvaluation | None  #: the main FQE; None when fitted on a worker (task map: evaluation/batch.py)
    extra_ratios: dict[str, tuple[shift.DensityRatios, pd.DataFrame]] = field(default_factory=dict)
    bounds: dict[str, dict[str, Any]] = field(default_factory=dict)
    estimand: Estimand | None = None
    pooled: tuple[shift.DensityRatios, dict[str, Any]] | None = None
    behaviour_value: dict[str, Any] | None = None
    per_step_counts: np.ndarray | None = None
    #: eps_t measured with the FQE fitted on all the data (0 for a policy greedy in it): for reference only.
    eps_in_sample: np.ndarray | None = None
    eps_note: str | None = None  #: why eps could not be measured out of sample (then NaN)
    #: Folds of the cross-fitted ``eps`` (0: measured in sample).
    eps_folds: int = 0
    #: Episode-cost distributions from the logs (:mod:`offline_adp.evaluation.risk`): the behaviour's
    #: logged one (``behaviour_logged``) and the policy's importance-weighted one (``policy_logs``).
    cost_distribution: dict[str, Any] | None = None


@dataclass(frozen=True)
class Weighting:
    """The behaviour model's reading of the logs for the evaluated policy."""

    behaviour: BehaviourEstimate
    target: np.ndarray  #: pi(. | x_i, t_i) at every row, (n, A)
    support: dict[str, Any]  #: where pi takes actions pi_b (almost) never took
    rho: np.ndarray  #: rho_i = pi(a_i | x_i, t_i) / pi_b(a_i | x_i)
    em: ope.EpisodeMatrix  #: rows laid out as (episodes, T steps)
    groups: np.ndarray | None  #: each episode's ``source`` label (the behaviour component that logged it)


@dataclass(frozen=True)
class ResidualAdvantage:
    """The PSDP bound's ``eps_t`` and the Q-values the DR estimators use."""

    eps: np.ndarray  #: cross-fitted eps_t (NaN where not measurable; in sample when ``folds`` is 0)
    in_sample: np.ndarray  #: eps_t of the FQE fitted on all the data (0 for a policy greedy in it)
    note: str | None  #: why eps could not be measured out of sample
    q: np.ndarray  #: Q(x_i, .) at every row: cross-fitted when ``crossfit``, else the in-sample FQE's
    crossfit: bool


def behaviour_value(em: ope.EpisodeMatrix, cost: np.ndarray, gamma: float, level: float = 0.95,
                    terminated: np.ndarray | None = None, est_def: Estimand | None = None) -> dict[str, Any]:
    """The logged behaviour's own value of the estimand: mean over episodes of ``sum_{t<T} gamma^t
    c_t`` with a Student-t interval (n - 1 degrees of freedom: with few episodes a normal one
    covers far less than its level), clipped to the range the logged costs make possible
    (``[c_lo, c_hi] sum_{t<T} gamma^t``, with 0 where episodes stop early:
    :func:`~offline_adp.evaluation.estimand.step_cost_range`; with one episode no interval). With
    ``terminated``, it is marked ``comparable: false`` where it is not the behaviour's value of the estimand:
    episodes that stop before step T without a terminal state (truncated: their missing steps
    count as zero cost in it), or, for an estimand past the T logged steps (``est_def``: a
    longer horizon or the infinite-horizon value), episodes that run to step T without a
    terminal state (their cost after step T is not in it)."""
    from scipy.stats import t as student_t

    disc = gamma ** np.arange(em.horizon)
    G = em.lay(cost) @ disc
    n = len(G)
    se = float(G.std(ddof=1) / np.sqrt(n)) if n > 1 else float("inf")
    q = float(student_t.ppf(0.5 + level / 2, n - 1)) if n > 1 else float("inf")
    lo, hi = float(G.mean() - q * se), float(G.mean() + q * se)
    # no episode's cost lies past [c_lo, c_hi] sum_t gamma^t (0 in it where episodes stop early): nor their mean
    c_lo, c_hi = step_cost_range(cost, terminated, em)
    # (the mean itself in it: G summed step by step may differ from c * sum_t gamma^t by a rounding)
    r_lo, r_hi = min(c_lo * float(disc.sum()), float(G.mean())), max(c_hi * float(disc.sum()), float(G.mean()))
    method = "mean logged discounted cost over the data's episodes (Student-t interval"
    if n > 1 and (lo < r_lo or hi > r_hi):  # one episode: no spread to measure, no interval (not the range)
        lo, hi = max(lo, r_lo), min(hi, r_hi)
        method += f", clipped to the possible range [{r_lo:.4g}, {r_hi:.4g}]"
    out = {"mean": float(G.mean()), "se": se, "interval": [lo, hi], "episodes": int(n), "method": method + ")"}
    ends = None if terminated is None else episode_ends(em, terminated)
    if ends == "short":
        out |= {"comparable": False,
                "not_comparable": f"{short_episodes(em, terminated)} of {em.n_episodes} logged episodes stop before "
                                  f"step {em.horizon} without a terminal state: their missing steps count as zero "
                                  "cost in the logged mean"}
    elif ends == "horizon" and est_def is not None and (est_def.beyond_logs or est_def.form == "infinite"):
        what = "the infinite-horizon value" if est_def.form == "infinite" else f"{est_def.value_horizon} steps"
        out |= {"comparable": False,
                "not_comparable": f"the estimand reads {what}, but logged episodes run to step {em.horizon} without "
                                  f"a terminal state: the logged mean holds none of their cost after step "
                                  f"{em.horizon}"}
    return out


def logged_cost_distributions(em: ope.EpisodeMatrix, cost: np.ndarray, rho: np.ndarray, gamma: float,
                              groups: np.ndarray | None = None, *, comparable: bool = True,
                              alpha: float = risk.CVAR_ALPHA) -> dict[str, Any]:
    """Episode-cost distributions the logs give (:mod:`offline_adp.evaluation.risk`): the
    behaviour's (its logged ``sum_{t<T} gamma^t c_t`` per episode) and the policy's, the same
    costs weighted by ``prod_t rho_t`` where those weights are usable (else why not)."""
    G = em.lay(cost) @ (gamma ** np.arange(em.horizon))
    W = np.cumprod(em.lay(rho, fill=1.0), axis=1)[:, -1]
    return {"alpha": alpha,
            "behaviour_logged": risk.distribution_summary(G, alpha=alpha, source="logs",
                                                          method="the logged episodes' discounted costs"),
            "policy_logs": risk.weighted_policy_distribution(G, W, alpha=alpha, groups=groups, comparable=comparable)}


def behaviour_model(ds: TransitionDataset, a: TransitionArrays, policy: Policy, T: int, classifier: Any,
                    clip: float) -> Weighting:
    """The behaviour policy ``pi_b(a | x)`` (the logged propensities, else a ``classifier``
    of the logged actions, clipped at ``clip``), the policy's ``pi(. | x_i, t_i)`` at every
    row, where it takes actions ``pi_b`` (almost) never took, and the per-row ratios
    ``rho_i = pi(a_i | x_i, t_i) / pi_b(a_i | x_i)`` the importance-weighted estimators use."""
    beh = estimate_behaviour(a.obs, a.action, ds.n_actions, a.behavior_prob, classifier=classifier, clip=clip)
    target = policy.probabilities(a.obs, a.step)
    support = support_violations(target, exact_state_support(a.obs, a.action, ds.n_actions, beh.all_probs), a.step)
    rho = target[np.arange(len(a)), a.action] / beh.logged_prob
    em = ope.EpisodeMatrix.build(a.episode, a.step, T)
    return Weighting(beh, target, support, rho, em, episode_groups(ds, em))


def residual_advantages(ds: TransitionDataset, policy: Policy, fit: FQEFit, w: Weighting, a: TransitionArrays,
                        T: int, gamma: float, folds: int, seed: int, say: Callable[[str], None],
                        held: Any = None) -> ResidualAdvantage:
    """``eps_t = gamma^t E_{mu_t}[sum_a pi(a|x) Q_t(x, a) - min_a Q_t(x, a)]``
    (:func:`~offline_adp.evaluation.psdp_eps.residual_advantage`) with ``Q`` cross-fitted over
    ``folds`` folds of episodes (:func:`~offline_adp.evaluation.psdp_eps.crossfit_residual_advantage`:
    each episode's Q from an FQE fitted without it; 0 folds: the FQE fitted on all the data,
    which gives 0 for FQI's greedy policy). The cross-fitted Q is also DR's: an in-sample Q of
    trees with small leaves reproduces the logged returns, so DR's corrections vanish and its
    bootstrap sees no spread (car_on_hill, the logging policy: [0.1294, 0.1296] against a truth
    of 0.127). ``held``: the folds' held-out Q-values already fitted on a task map
    (:class:`~offline_adp.evaluation.batch.BatchFits`' ``folds``)."""
    qv = fit.q if fit.q is not None else fit.fqe.q_function_.values(a.obs, a.step)
    in_sample = residual_advantage(qv, w.target, a.step, gamma, T)
    if not folds:
        return ResidualAdvantage(in_sample, in_sample, None, qv, False)
    if held is None:
        say("PSDP eps and DR's Q, cross-fitted")
    try:
        from offline_adp.progress import PhaseLines

        if isinstance(held, CrossFitError):
            raise held
        if held is not None:
            eps, q = crossfit_combine(a, policy, held[2], held[0], gamma, T, return_q=True, target=w.target,
                                      n_actions=ds.n_actions)
            return ResidualAdvantage(eps, in_sample, None, q, True)
        eps, q = crossfit_residual_advantage(ds, policy, fit.params, fit.horizon, gamma, T, w.em.row_episode,
                                             folds=folds, seed=seed, return_q=True, target=w.target,
                                             on_fold=PhaseLines(say, "PSDP eps and DR's Q: fold", folds))
    except CrossFitError as exc:  # no out-of-sample eps: the bound is unknown (the in-sample one is 0 by construction)
        return ResidualAdvantage(np.full(T, np.nan), in_sample, f"not measured: {exc}", qv, False)
    return ResidualAdvantage(eps, in_sample, None, q, True)


def doubly_robust(w: Weighting, a: TransitionArrays, ra: ResidualAdvantage, gamma: float, folds: int,
                  boot: dict[str, Any]) -> dict[str, ope.OPEResult]:
    """DR and WDR (:func:`~offline_adp.evaluation.ope.doubly_robust_estimates`) with
    ``Q^(x_i, a_i)`` and ``V^(x_i) = sum_a pi(a | x_i) Q^(x_i, a)`` from ``ra.q``; the
    interval method says whether Q was cross-fitted (else its error is omitted)."""
    q = ra.q
    est = ope.doubly_robust_estimates(w.em, a.cost, w.rho, q[np.arange(len(a)), a.action], (w.target * q).sum(axis=1),
                                      gamma, **boot)
    note = (f" (Q cross-fitted over {folds} folds of episodes)" if ra.crossfit
            else " (Q fitted on the same episodes: the interval omits its error)")
    # the paired difference from the logged cost only with a cross-fitted Q: one fitted on the same
    # episodes correlates its control variate with their own costs
    return {name: replace(r, interval_method=r.interval_method + note,
                          vs_logged=r.vs_logged if ra.crossfit else None) for name, r in est.items()}


def marginalised(a: TransitionArrays, w: Weighting, T: int, gamma: float, ratio_fit: dict[str, Any],
                 boot: dict[str, Any], ratios: shift.DensityRatios | None = None,
                 ) -> tuple[shift.DensityRatios, ope.OPEResult]:
    """Per-step state density ratios ``w_t(x) = d^pi_t(x) / d^b_t(x)`` by the recursion
    ``w_{t+1}(x') = E_b[w_t(x) rho | x']`` (:func:`~offline_adp.evaluation.shift.ratios_by_recursion`;
    ``ratios`` when already fitted) and marginalised IS ``sum_t gamma^t (1/N) sum_{i at t} w_t(x_i) rho_i c_i``."""
    if ratios is None:
        ratios = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, w.rho, horizon=T, **ratio_fit)
    return ratios, ope.marginalised_is_estimate(w.em, a.cost, w.rho, ratios.w, gamma, **boot)


def verdict_inputs(a: TransitionArrays, w: Weighting, est_def: Estimand, level: float) -> dict[str, Any]:
    """What the verdict compares the estimates with: the behaviour's logged value
    (:func:`behaviour_value`), the states logged per step, and the episode-cost distributions
    (:func:`logged_cost_distributions`; the policy's only where the estimators see the estimand)."""
    T, gamma = est_def.horizon, est_def.gamma
    # the weighted distribution is WIS's: not the estimand's where truncated episodes count their missing steps as 0
    comparable = (not est_def.beyond_logs and est_def.form == "finite"
                  and episode_ends(w.em, a.terminated) != "short")
    return {"behaviour_value": behaviour_value(w.em, a.cost, gamma, level, a.terminated, est_def),
            "per_step_counts": shift.per_step_counts(a.step, T),
            "cost_distribution": logged_cost_distributions(w.em, a.cost, w.rho, gamma, w.groups, comparable=comparable)}


def shift_and_bounds(a: TransitionArrays, policy: Policy, w: Weighting, ratios: shift.DensityRatios, diag: pd.DataFrame,
                     eps: np.ndarray, T: int, ratio_fit: dict[str, Any], k: int, seed: int,
                     reference_policies: dict[str, Policy] | None, policy_states: list[np.ndarray] | None,
                     say: Callable[[str], None],
                     fitted: dict[str, shift.DensityRatios] | None = None) -> dict[str, Any]:
    """The shift diagnostics and the PSDP bound ``sum_t eps_t x ratio``
    (:func:`~offline_adp.evaluation.psdp_eps.bound_entry`): the ratios pooled over time (a
    stationary policy), the bound for the policy itself (``self``) and for each reference
    policy (its own ratio recursion), and with ``policy_states`` (pi's states per step from a
    simulator) the classifier ratios. ``fitted``: the ratios already fitted on a task map
    (:class:`~offline_adp.evaluation.batch.BatchFits`' ``ratios``)."""
    pooled = None
    if fitted is not None and "pooled" in fitted:
        pooled = (fitted["pooled"], shift.pooled_summary(fitted["pooled"]))
    elif fitted is None and is_stationary(policy, a.obs, T):
        say("pooled density ratios")
        p = shift.ratios_pooled(a.obs, a.next_obs, a.step, w.rho, horizon=T, **ratio_fit)
        pooled = (p, shift.pooled_summary(p))
    bounds = {"self": bound_entry(eps, diag, shift.pooled_ratio_ucb(ratios, a.obs, k=k, seed=seed), T)}
    extra: dict[str, tuple[shift.DensityRatios, pd.DataFrame]] = {}
    for name, ref in (reference_policies or {}).items():
        say(f"reference policy {name}")
        if fitted is not None:
            r = fitted[f"ref:{name}"]
        else:
            rho_ref = ref.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / w.behaviour.logged_prob
            r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho_ref, horizon=T, **ratio_fit)
        d = shift.diagnostics(r, a.obs, k=k, seed=seed)
        extra[name] = (r, d)
        bounds[name] = bound_entry(eps, d, shift.pooled_ratio_ucb(r, a.obs, k=k, seed=seed), T)
    if policy_states is not None:
        from offline_adp.progress import PhaseLines

        say("classifier density ratios")
        steps = PhaseLines(say, "classifier density ratios: step", len(policy_states[:T]))
        r = (fitted["classifier"] if fitted is not None
             else shift.ratios_by_classifier(a.obs, a.step, policy_states[:T], seed=seed, on_step=steps))
        extra["classifier"] = (r, shift.diagnostics(r, a.obs, k=k, seed=seed))
    return {"pooled": pooled, "bounds": bounds, "extra_ratios": extra}


def off_policy(ds: TransitionDataset, policy: Policy, settings: EvaluationSettings | None = None, *,
               level: float = 0.95, behaviour_classifier: Any = "lightgbm", clip: float = 1e-3,
               ratio_regressor: Any = "extra_trees", ratio_params: dict | None = None,
               reference_policies: dict[str, Policy] | None = None, policy_states: list[np.ndarray] | None = None,
               k_support: int = 20, progress: Callable[[str], None] | None = None, task_map: TaskMap | None = None,
               psdp_folds: int = PSDP_EPS_FOLDS, target_horizon: int | None = None, start: str | None = None,
               **options: Any) -> OffPolicyResult:
    """Evaluate ``policy`` from the dataset alone, stage by stage (module docstring).

    ``settings`` (:class:`~offline_adp.evaluation.settings.EvaluationSettings`, or its fields
    as keywords in ``options``: ``fqe_params``, ``bootstrap``, ``fqe_bootstrap``, ``horizon``,
    ``estimand``, ``seed``, ``model_particles``) is checked before any work. ``target_horizon``
    and ``start``: the estimand's horizon and start distribution when they are a simulator's
    (:func:`~offline_adp.evaluation.estimand.declare_estimand`). ``psdp_folds``: folds of the
    cross-fitted eps_t and DR's Q (0: in sample). ``reference_policies``: more PSDP bounds;
    ``policy_states``: pi's states per step from a simulator (classifier ratios). ``task_map``
    (:mod:`offline_adp.parallel`), when given, runs the main FQE fit, the model rollouts, the
    cross-fitted FQE's folds and the density ratios as one batch of tasks
    (:mod:`~offline_adp.evaluation.batch`), then the FQE bootstrap replicates; the same
    numbers as without it.
    """
    cfg = EvaluationSettings.resolve(settings, options)  # every setting's one check
    say = progress or (lambda _msg: None)
    a = ds.arrays()
    est_def = declare_estimand(ds, policy, cfg.horizon, cfg.estimand, target_horizon=target_horizon, start=start)
    T, gamma, seed = est_def.horizon, est_def.gamma, cfg.seed
    say("behaviour policy")
    w = behaviour_model(ds, a, policy, T, behaviour_classifier, clip)
    ratio_fit = {"regressor": ratio_regressor, "regressor_params": ratio_params}
    bf = None if task_map is None else fit_batch(
        ds, policy, est_def, cfg, BatchInputs(a, w.rho, w.behaviour.logged_prob, w.em.row_episode, level, ratio_fit,
                                              psdp_folds), reference_policies, policy_states, task_map, say)
    say("fitted Q evaluation")
    fit, fq = fqe_with_interval(ds, policy, est_def, cfg, a=a, em=w.em, level=level, task_map=task_map, say=say,
                                fit=bf and bf.fit, model=bf and bf.model)
    say("importance sampling")
    boot = {"n_boot": cfg.bootstrap, "level": level, "seed": seed, "groups": w.groups}
    model = model_estimate(fq.model_rollouts, level)  # the model rollouts' own interval, checked against FQE's
    estimates = {"fqe": fq, **({"model": model} if model is not None else {}),
                 **ope.importance_sampling_estimates(w.em, a.cost, w.rho, gamma, **boot)}
    ra = residual_advantages(ds, policy, fit, w, a, T, gamma, psdp_folds, seed, say, held=bf and bf.folds)
    estimates.update(doubly_robust(w, a, ra, gamma, psdp_folds, boot))
    say("density ratios")
    ratios, estimates["mis"] = marginalised(a, w, T, gamma, ratio_fit, boot, ratios=bf and bf.ratios["self"])
    diag = shift.diagnostics(ratios, a.obs, k=k_support, seed=seed)
    est_def, logged_range = with_possible_range(est_def, a, w.em)
    estimates = as_quoted(estimates, est_def, logged_range, episode_ends(w.em, a.terminated), w.em.n_episodes)
    return OffPolicyResult(gamma, T, w.behaviour, estimates, ratios, diag, w.support, ra.eps, fit.fqe, estimand=est_def,
                           eps_in_sample=ra.in_sample, eps_folds=int(psdp_folds or 0), eps_note=ra.note,
                           **verdict_inputs(a, w, est_def, level),
                           **shift_and_bounds(a, policy, w, ratios, diag, ra.eps, T, ratio_fit, k_support, seed,
                                              reference_policies, policy_states, say, bf and bf.ratios))
