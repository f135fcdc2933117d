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
from offline_adp.data.discount import resolve_discount
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.evaluation import ope, risk, shift
from offline_adp.evaluation.behaviour import (
    BehaviourEstimate,
    estimate_behaviour,
    support_violations,
)
from offline_adp.evaluation.model_rollouts import model_rollouts, widen_fqe
from offline_adp.evaluation.psdp_eps import (  # crossfit_residual_advantage, CrossFitError: also reached from here
    PSDP_EPS_FOLDS,
    CrossFitError,
    bound_entry,
    crossfit_residual_advantage,
    episode_groups,
    residual_advantage,
)
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.evaluation.support_bounds import fqe_support_bounds
from offline_adp.parallel import TaskMap, local_map
from offline_adp.policies import Policy, is_stationary

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


def evaluation_horizon(ds: TransitionDataset, horizon: int | None = None) -> tuple[int, float, int | None]:
    """(T for trajectory estimators and rollouts, gamma, T again: the finite-horizon FQE).

    T is the data's longest episode, capped by ``info.horizon`` and by ``horizon``.
    (See :func:`declare_estimand` for the quantity every estimator targets.)
    """
    a = ds.arrays()
    gamma = resolve_discount(ds.info).gamma  # the package's one rule, as the fit used
    T = int(a.step.max()) + 1
    for cap in (ds.info.horizon, horizon):
        if cap is not None:
            T = min(T, int(cap))
    return T, float(gamma), T


#: FQE bootstrap replicates when replicates are cheap (structure-conditional re-weighting or
#: tabular / linear refits): enough for stable 2.5% / 97.5% percentiles (measured on tabular
#: problems: 10 replicates covered 77-80% at nominal 95%, 200 covered 97%).
FQE_REPLICATE_FLOOR = 200
#: Below this many replicates a percentile interval is called rough.
FQE_REPLICATE_ROUGH = 50
#: The stationary (discounted) FQE stands in for the T-step FQE when ``gamma^T`` is below this:
#: the two differ by at most ``gamma^T max|c| / (1 - gamma)``, which is added to its interval.
TAIL_NEGLIGIBLE = 0.01


@dataclass
class Estimand:
    """The one quantity every estimator and the rollout truth estimate.

    ``J(pi) = E[ sum_{t < T} gamma^t c_t ]`` from the start distribution ``start`` (the
    data's start states unless a simulator's own reset names it, e.g. ``env.reset()`` of a
    gymnasium environment) (``form="finite"``, the default), or the infinite-horizon discounted value
    ``E[ sum_t gamma^t c_t ]`` (``form="infinite"``, which only FQE can estimate from
    T-step logs; the trajectory estimators then say they cannot).

    ``fqe_form`` says how FQE computes it: ``time-indexed`` (Q_0 .. Q_{T-1}, Algorithm 12)
    or ``stationary`` (one discounted Q; used for the finite estimand only when the
    policy is stationary on the data and ``gamma^T <= TAIL_NEGLIGIBLE``, with the
    truncation bound ``tail_bound`` added to its interval).

    ``target_horizon``: the estimand's horizon when it exceeds the logged one ``horizon``
    (a gymnasium simulator's own time limit, e.g. 500 steps over 83-step random-play
    logs). The trajectory estimators still see only ``horizon`` steps and say
    so (``comparable=False``), as for the infinite-horizon value.
    """

    horizon: int
    gamma: float
    form: str = "finite"
    fqe_form: str = "time-indexed"
    tail_bound: float = 0.0
    reason: str = ""
    possible_range: tuple[float, float] | None = None
    target_horizon: int | None = None
    start: str = "the data's start states"

    @property
    def value_horizon(self) -> int:
        """The estimand's horizon (``target_horizon`` when set, else the logged ``horizon``)."""
        return self.target_horizon if self.target_horizon is not None else self.horizon

    @property
    def beyond_logs(self) -> bool:
        """Whether the estimand's horizon exceeds the logged horizon the estimators see."""
        return self.target_horizon is not None and self.target_horizon > self.horizon

    @property
    def fqe_horizon(self) -> int | None:
        return self.horizon if self.fqe_form == "time-indexed" else None

    def describe(self) -> str:
        if self.form == "infinite":
            return f"expected discounted cost sum_t {self.gamma:g}^t c_t over an infinite horizon from {self.start}"
        disc = "" if self.gamma >= 1.0 else f"{self.gamma:g}^t "
        T = self.value_horizon
        return f"expected cost sum_{{t<{T}}} {disc}c_t over {T} steps from {self.start}"

    def as_dict(self) -> dict[str, Any]:
        return {"quantity": self.describe(), "form": self.form, "horizon": self.value_horizon,
                "logged_horizon": self.horizon, "start": self.start, "gamma": self.gamma,
                "fqe_form": self.fqe_form, "fqe_truncation_bound": self.tail_bound, "reason": self.reason,
                "possible_range": None if self.possible_range is None else list(self.possible_range)}


def clip_to_range(r: ope.OPEResult, rng: tuple[float, float]) -> None:
    """An interval reaching past what the cost makes possible is clipped there (and says so)."""
    lo, hi = r.interval
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return
    c_lo, c_hi = max(lo, rng[0]), min(hi, rng[1])
    if (c_lo, c_hi) != (lo, hi) and c_lo <= c_hi:
        r.interval = (c_lo, c_hi)
        r.interval_method += f"; clipped to the possible range [{rng[0]:.4g}, {rng[1]:.4g}]"


def stationary_onto_range(fq: ope.OPEResult, est_def: Estimand) -> None:
    """The stationary FQE estimates the infinite-horizon value, within ``tail_bound`` of the
    T-step one. Past the T-step range by no more than that, the estimate is moved onto the
    range's edge (e.g. a policy that never ends an episode early reads -99.89 against a
    500-step floor of -99.34), with a warning, instead of being called impossible."""
    if not (est_def.fqe_form == "stationary" and est_def.tail_bound > 0 and est_def.possible_range
            and np.isfinite(fq.estimate)):
        return
    lo_r, hi_r = est_def.possible_range
    near = min(max(fq.estimate, lo_r), hi_r)
    if near != fq.estimate and abs(near - fq.estimate) <= est_def.tail_bound + 1e-9 * max(1.0, abs(near)):
        fq.warnings.append(f"the stationary estimate {fq.estimate:.4g} lies past the {est_def.horizon}-step range by "
                           f"less than the truncation bound {est_def.tail_bound:.3g}: reported at the range's edge "
                           f"{near:.4g}")
        fq.estimate = near


def behaviour_value(em: ope.EpisodeMatrix, cost: np.ndarray, gamma: float, level: float = 0.95) -> dict[str, Any]:
    """The logged behaviour's own value of the estimand: mean over episodes of
    ``sum_{t<T} gamma^t c_t`` with a normal-approximation interval."""
    from scipy.stats import norm

    G = em.lay(cost) @ (gamma ** np.arange(em.horizon))
    se = float(G.std(ddof=1) / np.sqrt(len(G))) if len(G) > 1 else float("inf")
    z = float(norm.ppf(0.5 + level / 2))
    return {"mean": float(G.mean()), "se": se, "interval": [float(G.mean() - z * se), float(G.mean() + z * se)],
            "episodes": int(len(G)), "method": "mean logged discounted cost over the data's episodes"}


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


#: Regressors whose FQE refits are cheap enough for the full replicate floor.
CHEAP_REGRESSORS = ("tabular", "linear")


def fqe_replicates(requested: int | None, cheap: bool) -> int:
    """FQE bootstrap replicates to run: ``requested`` as given (a user's setting is never
    overridden; below :data:`FQE_REPLICATE_ROUGH` the interval is called rough);
    ``None`` means :data:`FQE_REPLICATE_FLOOR` when replicates are cheap, else
    :data:`FQE_REPLICATE_ROUGH`; 0 means no interval."""
    if requested is None:
        return FQE_REPLICATE_FLOOR if cheap else FQE_REPLICATE_ROUGH
    return max(int(requested), 0)  # an explicit request is honoured (fewer than ROUGH: the interval says so)


def _stationary_on(policy: Policy, obs: np.ndarray, T: int) -> bool:
    """Whether ``policy`` gives the same probabilities at every step t < T on the data's
    states (:func:`offline_adp.policies.is_stationary`: declared, else probed)."""
    return is_stationary(policy, obs, T)


def declare_estimand(ds: TransitionDataset, policy: Policy, horizon: int | None = None, form: str = "finite", *,
                     target_horizon: int | None = None, start: str | None = None) -> Estimand:
    """The quantity :func:`off_policy` estimates (see :class:`Estimand`).

    ``target_horizon``: the horizon of the value asked for when it is not the logged one
    (a simulator's rollout horizon); ``start``: its start distribution when it is not the
    data's start states (e.g. ``"env.reset() of gym:ENV_ID"``)."""
    if form not in ("finite", "infinite"):
        raise InvalidArgumentError(f"estimand must be 'finite' or 'infinite', got {form!r}")
    T, gamma, _ = evaluation_horizon(ds, horizon)
    a = ds.arrays()
    where = {"start": start} if start else {}
    if form == "infinite":
        if not gamma < 1.0:
            raise IncompatibleError("the infinite-horizon value needs gamma < 1 (the dataset's gamma is 1)")
        return Estimand(T, gamma, "infinite", "stationary", 0.0, "asked for the infinite-horizon value", **where)
    c_max = float(np.abs(a.cost).max()) if len(a.cost) else 0.0
    if target_horizon is not None and int(target_horizon) > T:
        H = int(target_horizon)
        if gamma < 1.0 and gamma**H <= TAIL_NEGLIGIBLE and _stationary_on(policy, a.obs, T):
            tail = gamma**H * c_max / (1.0 - gamma)
            return Estimand(T, gamma, "finite", "stationary", tail,
                            f"the {H}-step value asked for exceeds the {T} logged steps; gamma^{H} = {gamma**H:.2g}: the "
                            f"stationary discounted FQE differs from it by at most gamma^{H} max|c| / (1 - gamma) = "
                            f"{tail:.3g}, added to its interval; the trajectory estimators see only {T} steps",
                            target_horizon=H, **where)
        return Estimand(T, gamma, "finite", "time-indexed", 0.0,
                        f"the {H}-step value asked for exceeds the {T} logged steps: no estimator of these logs sees "
                        f"past step {T} (time-indexed FQE over the {T} logged steps)", target_horizon=H, **where)
    if gamma < 1.0 and gamma**T <= TAIL_NEGLIGIBLE and _stationary_on(policy, a.obs, T):
        tail = gamma**T * c_max / (1.0 - gamma)
        return Estimand(T, gamma, "finite", "stationary", tail,
                        f"gamma^T = {gamma**T:.2g}: the stationary discounted FQE differs from the {T}-step value by at "
                        f"most gamma^T max|c| / (1 - gamma) = {tail:.3g}, added to its interval")
    why = "the policy changes with t" if gamma < 1.0 and gamma**T <= TAIL_NEGLIGIBLE else (
        "undiscounted" if gamma >= 1.0 else f"gamma^T = {gamma**T:.2g} is not negligible")
    return Estimand(T, gamma, "finite", "time-indexed", 0.0, f"time-indexed FQE over the {T} logged steps ({why})",
                    target_horizon=int(target_horizon) if target_horizon is not None else None, **where)
















def _start_value(fqe: FittedQEvaluation, x0: np.ndarray, pi_x0: np.ndarray, w0: np.ndarray | None) -> float:
    """sum_a pi(a|x0) Q(x0, a), averaged over the start states (weighted by ``w0``)."""
    v0 = (pi_x0 * fqe.q_function_.values(x0, 0)).sum(axis=1)
    return float(v0.mean()) if w0 is None else float(np.sum(w0 * v0) / np.sum(w0))


#: Relative accuracy of a structure-conditional bootstrap replicate's fixed point: its value
#: is within ``REPLICATE_RTOL (1 + max|v|)`` of the replicate's exact fixed point, far below
#: the replicates' spread, at ~2/3 of the sweeps the point estimate's ``1e-7`` needs.
REPLICATE_RTOL = 1e-5


def _reweighted_replicate(w: np.ndarray, *, fqe: FittedQEvaluation) -> float:
    return fqe.reweighted_value(w, rtol=REPLICATE_RTOL)


def _refit_replicate(w: np.ndarray, *, ds: TransitionDataset, params: dict[str, Any], x0: np.ndarray,
                     pi_x0: np.ndarray, start: np.ndarray) -> float:
    import gc

    fqe = FittedQEvaluation(**params).fit(ds, sample_weight=w)
    value = _start_value(fqe, x0, pi_x0, w[start])
    del fqe
    # a fitted estimator sits in reference cycles (its learner and backups point back at it),
    # which only the cyclic collector frees, and its arrays do not trigger that collector: a
    # T-step replicate holds T Q-functions (e.g. 79 steps of 20 trees on 50k rows: ~1 GB),
    # and 50 replicates piled up to 19.8 GB before one ran
    gc.collect()
    return value


_TABULAR_KEYS = {"regressor", "action_encoding", "action_input", "mode", "n_iterations", "tol"}


def _tabular_fast(params: dict[str, Any], fqe_T: int | None) -> bool:
    """Finite-horizon FQE with the plain tabular learner: replicates can be vectorised."""
    return (fqe_T is not None and params.get("regressor") == "tabular" and set(params) <= _TABULAR_KEYS)


def tabular_fqe_replicates(obs: np.ndarray, action: np.ndarray, cost: np.ndarray, next_obs: np.ndarray,
                           terminated: np.ndarray, start: np.ndarray, policy: Policy, n_actions: int, horizon: int,
                           gamma: float, weights: np.ndarray) -> np.ndarray:
    """Time-indexed tabular FQE (Algorithm 12 with the lookup-table learner) for many row
    weightings at once: one value per row of ``weights`` (B, n).

    ``Q_t[b, (x, a)]`` is the ``weights[b]``-weighted mean over the rows with input
    ``(x, a)`` of ``c + gamma (1 - term) sum_a' pi(a' | x', t + 1) Q_{t+1}[b, (x', a')]``
    (0 for inputs without weight, as the lookup table's fill value), ``Q_T = 0``; the value
    is the ``weights[b]``-weighted mean of ``sum_a pi(a | x_0, 0) Q_0[b, (x_0, a)]`` over
    the start rows. Equals refitting ``FittedQEvaluation(regressor="tabular", horizon=T)``
    with each weighting (tests check this), without the per-fit overhead.
    """
    from scipy import sparse

    codes, inv = np.unique(np.vstack([obs, next_obs]), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n, A, K = len(obs), n_actions, len(codes)
    sid, nsid = inv[:n], inv[n:]
    onehot = sparse.csr_matrix((np.ones(n), (np.arange(n), sid * A + action)), shape=(n, K * A))
    W = np.asarray(weights, dtype=np.float64)
    den = (onehot.T @ W.T).T  # (B, K*A)
    boot = gamma * (1.0 - terminated.astype(np.float64))
    Q = np.zeros((len(W), K * A))  # Q_T = 0
    # V_{t+1}(x') once per distinct state (K of them), then read at every row's next state
    stationary = is_stationary(policy, next_obs, horizon)  # then pi(. | x', t) is computed once
    pi_once = policy.probabilities(codes, 1) if stationary else None
    for t in range(horizon - 1, -1, -1):
        if t < horizon - 1:
            pi_codes = pi_once if stationary else policy.probabilities(codes, t + 1)  # (K, A)
            v_next = (pi_codes[None] * Q.reshape(len(W), K, A)).sum(axis=2)[:, nsid]  # (B, n)
        else:
            v_next = 0.0
        Y = cost[None, :] + boot[None, :] * v_next
        num = (onehot.T @ (W * Y).T).T
        Q = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    s_idx = sid[start][:, None] * A + np.arange(A)[None, :]
    v0 = (policy.probabilities(obs[start], 0)[None] * Q[:, s_idx]).sum(axis=2)  # (B, n_start)
    w0 = W[:, start]
    tot = w0.sum(axis=1)
    return np.where(tot > 0, (w0 * v0).sum(axis=1) / np.where(tot > 0, tot, 1.0), np.nan)


def off_policy(
    ds: TransitionDataset,
    policy: Policy,
    settings: EvaluationSettings | None = None,
    *,
    level: float = 0.95,
    behaviour_classifier: Any = "lightgbm",
    clip: float = 1e-3,
    ratio_regressor: Any = "extra_trees",
    ratio_params: dict | None = None,
    reference_policies: dict[str, Policy] | None = None,
    policy_states: list[np.ndarray] | None = None,
    k_support: int = 20,
    progress: Callable[[str], None] | None = None,
    task_map: TaskMap | None = None,
    psdp_folds: int = PSDP_EPS_FOLDS,
    target_horizon: int | None = None,
    start: str | None = None,
    **options: Any,
) -> OffPolicyResult:
    """Evaluate ``policy`` from the dataset alone.

    ``settings`` (:class:`~offline_adp.evaluation.settings.EvaluationSettings`, or its fields
    as keywords in ``options``: ``fqe_params``, ``bootstrap`` (``n_boot``), ``fqe_bootstrap``
    (``n_boot_fqe``), ``horizon``, ``estimand``, ``seed``, ``model_particles``; the rest are
    not read here) is checked before any work.

    Every estimator targets the quantity of :func:`declare_estimand` (``estimand``:
    ``"finite"``, the T-step value the rollout truth measures, or ``"infinite"``).
    ``n_boot_fqe`` FQE bootstrap replicates are raised to :data:`FQE_REPLICATE_FLOOR`
    when they are cheap (see :func:`fqe_replicates`).

    Steps: behaviour probabilities (logged or a classifier) and support violations;
    FQE with a trajectory bootstrap; IS, WIS, PDIS, WPDIS, DR, WDR; per-step density
    ratios by the recursion and MIS from them; diagnostics; eps_t cross-fitted over
    ``psdp_folds`` folds of episodes (:func:`crossfit_residual_advantage`; 0: from the
    FQE fitted on all the data, which is 0 for FQI's greedy policy) and the PSDP bound for each reference policy (``self`` always; others
    from ``reference_policies``). With ``policy_states`` (pi's states per step from a
    simulator) the classifier ratios are added. ``model_particles``: particles of the model
    rollouts FQE's interval is widened to (:mod:`~offline_adp.evaluation.model_rollouts`;
    0: none), for the finite-horizon estimand (past the logged horizon too). ``task_map`` runs the FQE bootstrap
    replicates (default: here; see :mod:`offline_adp.parallel`). ``target_horizon`` and
    ``start``: the estimand's horizon and start distribution when they are a simulator's
    (see :func:`declare_estimand`); estimators that cannot see that far say so
    (``comparable=False`` and a warning), as for the infinite-horizon value.
    """
    cfg = EvaluationSettings.resolve(settings, options)  # every setting's one check
    fqe_params, n_boot, n_boot_fqe, horizon = cfg.fqe_params, cfg.bootstrap, cfg.fqe_bootstrap, cfg.horizon
    estimand, seed, model_particles = cfg.estimand, cfg.seed, cfg.model_particles
    say = progress or (lambda _msg: None)
    a = ds.arrays()
    est_def = declare_estimand(ds, policy, horizon, estimand, target_horizon=target_horizon, start=start)
    T, gamma = est_def.horizon, est_def.gamma
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
    fqe_T = est_def.fqe_horizon
    if fqe_T is not None:
        params.pop("tol", None)
        params.pop("n_iterations", None)
    start = a.step == 0
    x0 = a.obs[start]
    pi_x0 = policy.probabilities(x0, 0)  # once, not per bootstrap replicate
    conditional = params.get("mode") == "frozen" and fqe_T is None and not params.get("validation_fraction")
    fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=gamma, random_state=seed, **params).fit(ds)
    if conditional:  # the estimate is the fixed point of the final structure, as each replicate's is
        fqe.settle()
    est = _start_value(fqe, x0, pi_x0, None)
    cheap = conditional or params.get("regressor") in CHEAP_REGRESSORS
    n_reps = fqe_replicates(n_boot_fqe, cheap)
    counts = ope.bootstrap_counts(em.n_episodes, n_reps, seed)
    quarters = {max(1, (n_reps * q) // 4) for q in (1, 2, 3, 4)}  # four progress lines, not one per replicate

    def on_done(b: int) -> None:
        if b + 1 in quarters:
            say(f"FQE bootstrap {b + 1}/{n_reps}")
    run = task_map or local_map
    if _tabular_fast(params, fqe_T) and n_reps:
        reps = list(tabular_fqe_replicates(a.obs, a.action, a.cost, a.next_obs, a.terminated, start, policy,
                                           ds.n_actions, fqe_T, gamma, np.array([c[em.row_episode] for c in counts])))
    elif conditional:  # same trees, leaves re-averaged with the replicate's weights
        reps = run(_reweighted_replicate, [c[em.row_episode] for c in counts], shared={"fqe": fqe}, on_done=on_done)
    else:
        reps = run(_refit_replicate, [c[em.row_episode] for c in counts], on_done=on_done,
                   shared={"ds": ds, "params": {"policy": policy, "horizon": fqe_T, "gamma": gamma, "random_state": seed,
                                                **params}, "x0": x0, "pi_x0": pi_x0, "start": start})
    estimates = {"fqe": ope.fqe_interval(est, reps, em.n_episodes, level)}
    fq = estimates["fqe"]
    if conditional and n_reps:
        fq.interval_method += " (structure-conditional: tree structure fixed, leaves re-averaged)"
        fq.warnings.append("the interval keeps the fitted tree structure, so it omits the structure's own "
                           "variability (a structure-conditional bootstrap)")
    if conditional:  # what the model cannot know: widen to the support bounds
        say("FQE support bounds")
        sb = fqe_support_bounds(fqe, ds, seed)
        fq.support_bounds = sb
        widened = fq.widen(sb["lower"], sb["upper"], f"widened to the support bounds [{sb['lower']:.4g}, "
                           f"{sb['upper']:.4g}] (the value with the pairs the logs hold no row of the queried action "
                           "near valued at the cost range's ends; not a bound on the trees' smoothing within an action)")
        if widened is not None and sb["unsupported_next"] > 0:
            fq.warnings.append(f"{sb['unsupported_next']:.1%} of the policy's next-state action mass has no logged "
                               "row of that action near the state: the interval is widened to what those pairs "
                               f"could be worth ([{sb['lower']:.4g}, {sb['upper']:.4g}])")
    # the model is stationary, so it also reads past the logged horizon; hulled with FQE only where
    # FQE's interval is of the same quantity (a time-indexed FQE past the logs reads the T-step value)
    if model_particles and est_def.form == "finite":
        say("model rollouts")
        widen_fqe(fq, model_rollouts(ds, policy, est_def.value_horizon, gamma, n=model_particles, level=level,
                                     seed=seed, arrays=a),
                  hull=not est_def.beyond_logs or est_def.fqe_form == "stationary")
    elif est_def.form == "finite":  # said, so metrics.json tells "turned off" from "not yet a feature"
        fq.model_rollouts = {"skipped": "model_particles=0: model rollouts turned off"}
    if 0 < n_reps < FQE_REPLICATE_ROUGH:
        fq.warnings.append(f"only {n_reps} bootstrap refits: the interval's percentiles are rough "
                           f"(use at least {FQE_REPLICATE_ROUGH}; {FQE_REPLICATE_FLOOR} for stable ones)")
    if est_def.tail_bound > 0 and np.all(np.isfinite(fq.interval)):
        fq.interval = (fq.interval[0] - est_def.tail_bound, fq.interval[1] + est_def.tail_bound)
        fq.interval_method += f", widened by the truncation bound {est_def.tail_bound:.3g}"
    say("importance sampling")
    groups = episode_groups(ds, em)
    estimates.update(ope.importance_sampling_estimates(em, a.cost, rho, gamma, n_boot=n_boot, level=level, seed=seed,
                                                       groups=groups))
    qv = fqe.q_function_.values(a.obs, a.step)
    eps_in_sample = residual_advantage(qv, target, a.step, gamma, T)
    eps_note, q_dr = None, None
    if psdp_folds:
        say("PSDP eps and DR's Q, cross-fitted")
        try:
            eps, q_dr = crossfit_residual_advantage(ds, policy, params, fqe_T, gamma, T, em.row_episode,
                                                    folds=psdp_folds, seed=seed, return_q=True)
        except CrossFitError as exc:  # no out-of-sample eps: the bound is unknown (the in-sample one is 0 by construction)
            eps, eps_note = np.full(T, np.nan), f"not measured: {exc}"
    else:
        eps = eps_in_sample
    # DR's Q cross-fitted (each episode's from an FQE fitted without it): an in-sample Q of trees with
    # small leaves reproduces the logged returns, so the corrections vanish and the bootstrap sees no
    # spread (car_on_hill, the logging policy: [0.1294, 0.1296] against a truth of 0.127)
    q_used = q_dr if q_dr is not None else qv
    estimates.update(ope.doubly_robust_estimates(em, a.cost, rho, q_used[np.arange(len(a)), a.action],
                                                 (target * q_used).sum(axis=1), gamma, n_boot=n_boot, level=level,
                                                 seed=seed, groups=groups))
    for name in ("dr", "wdr"):
        estimates[name].interval_method += (f" (Q cross-fitted over {psdp_folds} folds of episodes)" if q_dr is not None
                                            else " (Q fitted on the same episodes: the interval omits its error)")
    say("density ratios")
    ratios = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho, regressor=ratio_regressor,
                                       regressor_params=ratio_params, horizon=T)
    estimates["mis"] = ope.marginalised_is_estimate(em, a.cost, rho, ratios.w, gamma, n_boot=n_boot, level=level, seed=seed,
                                                    groups=groups)
    ope.flag_against(estimates, "fqe")
    diag = shift.diagnostics(ratios, a.obs, k=k_support, seed=seed)
    lo_c, hi_c = float(a.cost.min()), float(a.cost.max())
    if a.terminated.any() or not em.mask.all():  # episodes that stop early add 0 from then on
        lo_c, hi_c = min(lo_c, 0.0), max(hi_c, 0.0)
    span = float(np.sum(gamma ** np.arange(T))) if est_def.form == "finite" else 1.0 / (1.0 - gamma)
    logged_range = (lo_c * span, hi_c * span)
    est_def.possible_range = logged_range
    beyond = est_def.beyond_logs
    H = est_def.value_horizon
    if beyond:  # the estimand's own range; estimates of the T logged steps keep theirs
        span_h = float(np.sum(gamma ** np.arange(H)))
        est_def.possible_range = (min(lo_c, 0.0) * span_h, max(hi_c, 0.0) * span_h)  # the logs end before H
    for name, r in estimates.items():
        sees_h = not beyond or (name == "fqe" and est_def.fqe_form == "stationary")
        clip_to_range(r, est_def.possible_range if sees_h else logged_range)
    stationary_onto_range(estimates["fqe"], est_def)
    if beyond:
        for name, r in estimates.items():
            if name == "fqe" and est_def.fqe_form == "stationary":
                continue
            r.warnings.insert(0, f"estimates the {T}-step value, not the {H}-step value asked for: the logs' episodes "
                                 f"end by step {T} and no estimator of them sees past it")
            r.comparable = False
    if est_def.form == "infinite":
        for name, r in estimates.items():
            if name != "fqe":
                r.warnings.insert(0, f"estimates the {T}-step value, not the infinite-horizon value asked for: "
                                     "trajectory estimators cannot see past the logged horizon")
                r.comparable = False
    res = OffPolicyResult(gamma, T, beh, estimates, ratios, diag, support, eps, fqe, estimand=est_def,
                          eps_in_sample=eps_in_sample, eps_folds=int(psdp_folds or 0), eps_note=eps_note,
                          behaviour_value=behaviour_value(em, a.cost, gamma, level),
                          per_step_counts=shift.per_step_counts(a.step, T),
                          cost_distribution=logged_cost_distributions(em, a.cost, rho, gamma, groups,
                                                                      comparable=not beyond and est_def.form == "finite"))
    if _stationary_on(policy, a.obs, T):
        say("pooled density ratios")
        pooled = shift.ratios_pooled(a.obs, a.next_obs, a.step, rho, regressor=ratio_regressor,
                                     regressor_params=ratio_params, horizon=T)
        res.pooled = (pooled, shift.pooled_summary(pooled))
    res.bounds["self"] = bound_entry(eps, diag, shift.pooled_ratio_ucb(ratios, a.obs, k=k_support, seed=seed), T)
    for name, ref in (reference_policies or {}).items():
        say(f"reference policy {name}")
        rho_ref = ref.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / beh.logged_prob
        r = shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, rho_ref, regressor=ratio_regressor,
                                      regressor_params=ratio_params, horizon=T)
        d = shift.diagnostics(r, a.obs, k=k_support, seed=seed)
        res.extra_ratios[name] = (r, d)
        res.bounds[name] = bound_entry(eps, d, shift.pooled_ratio_ucb(r, a.obs, k=k_support, seed=seed), T)
    if policy_states is not None:
        say("classifier density ratios")
        r = shift.ratios_by_classifier(a.obs, a.step, policy_states[:T], seed=seed)
        res.extra_ratios["classifier"] = (r, shift.diagnostics(r, a.obs, k=k_support, seed=seed))
    return res
