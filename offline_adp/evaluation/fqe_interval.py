"""FQE's value and its interval, in one place (docs/evaluation.md, sections 1-3).

The estimate is the value of the evaluated policy pi at the data's start states,
``J^ = mean_{x0} sum_a pi(a | x0) Q^(x0, a)``, with ``Q^`` fitted by FQE on all the data
(:func:`fit_fqe`). Its interval is built in these steps, each a function returning a new
:class:`~offline_adp.evaluation.ope.OPEResult`:

1. **Bootstrap** (:func:`bootstrap_values`): episodes resampled with replacement, each
   replicate's ``J^`` computed with the rows weighted by how often their episode was drawn,
   one of three ways: the vectorised tabular recursion (:func:`tabular_fqe_replicates`);
   the structure-conditional replicate, which keeps the frozen tree structure and
   re-averages its leaves to the fixed point for the new weights
   (:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.reweighted_value`, the operators
   of :mod:`offline_adp.algorithms.fqe_bootstrap` solved over the training rows,
   :mod:`offline_adp.algorithms.fqe_replicates`); or a full refit.
2. **Percentile / basic hull** (:func:`fqe_interval`): the percentile interval, or, when
   the replicates are shifted from ``J^``, the hull of it and the basic interval.
3. **Support bounds** (:func:`with_support_bounds`, structure-conditional fits): the hull
   with the value of the per-action read with every pair the logs cannot read valued at
   the ends of the cost's value range (:func:`fqe_support_bounds`, :func:`q_value_range`).
4. **Model rollouts** (:func:`model_reading`, :func:`widen_fqe`; finite-horizon estimand): the hull with the interval of
   rollouts of a model of the logged increments (:mod:`~offline_adp.evaluation.model_rollouts`); the model's own
   bootstrap interval (:mod:`~offline_adp.evaluation.model_bootstrap`) is recorded with FQE's interval before the
   hull (:func:`with_fqe_interval`), which it is checked against before it becomes an estimator of its own.
5. **Truncation** (:func:`with_truncation_bound`): a stationary FQE standing in for the
   T-step value is widened by ``gamma^T max|c| / (1 - gamma)`` on both sides.

:func:`fqe_with_interval` runs them in that order.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.evaluation.estimand import Estimand
from offline_adp.evaluation.model_bootstrap import MODEL_REPLICATES, bootstrap_reading
from offline_adp.evaluation.model_rollouts import EXIT_FRACTION, model_rollouts
from offline_adp.evaluation.ope import EpisodeMatrix, OPEResult, bootstrap_counts
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.parallel import TaskMap, local_map
from offline_adp.policies import Policy, is_stationary

#: FQE settings for evaluation: the frozen-structure fast path keeps bootstrap refits cheap.
#: Ernst's extra-trees defaults matter: larger leaves average Q over actions and bias FQE
#: (measured on path_tracking: min_samples_leaf=5 doubled the estimated cost).
#: 20 trees instead of 50 keep a 100k-transition evaluation within two minutes.
#: The fit's default schedule (docs/fqi-modes.md, "The default schedule"): structures built at
#: 1, 2, 8 at gamma 0.95, the last one's fixed point solved (then :meth:`settle` to 1e-7 as
#: before). Until 2026-11-27 it was 60 iterations with 4 structures (1, 16, 31, 46) and tol
#: 1e-4; measured (docs/evaluation.md, "Cost"): the FQE and cross-fitted FQE stages 28.6 -> 21.1
#: CPU-s on a 50k-transition path_tracking log, the estimate 3.335 -> 2.647 against a rollout
#: truth of 2.221 there and 4.208 -> 3.541 against 2.454 on the demo.
DEFAULT_FQE = {"regressor": "extra_trees", "mode": "frozen", "n_iterations": "auto", "n_structures": None,
               "regressor_params": {"n_estimators": 20}}
#: The settings with another regressor, an explicit iteration count or over continuous
#: commands: a count of iterations with a tolerance, and FittedQEvaluation's 4 structures.
COUNTED_FQE = {"n_iterations": 60, "tol": 1e-4}
#: FQE bootstrap replicates when replicates are cheap (structure-conditional re-weighting or
#: tabular / linear refits): enough for stable 2.5% / 97.5% percentiles (measured on tabular
#: problems: 10 replicates covered 77-80% at nominal 95%, 200 covered 97%).
FQE_REPLICATE_FLOOR = 200
#: Below this many replicates a percentile interval is called rough.
FQE_REPLICATE_ROUGH = 50
#: Regressors whose FQE refits are cheap enough for the full replicate floor.
CHEAP_REGRESSORS = ("tabular", "linear")
#: Relative accuracy of a structure-conditional bootstrap replicate's fixed point: its value
#: is within ``REPLICATE_RTOL (u + max|v|)`` of the replicate's exact fixed point, far below
#: the replicates' spread, at ~2/3 of the sweeps the point estimate's ``1e-7`` needs.
REPLICATE_RTOL = 1e-5
#: The support bounds' radius: a row of the queried action counts when it is at most as far from
#: the queried state as 99% of the logged states are from their nearest same-action neighbour.
SUPPORT_RADIUS_QUANTILE = 0.99


@dataclass(frozen=True)
class FQEFit:
    """FQE of the policy fitted on all the data, and how its interval is bootstrapped."""

    fqe: FittedQEvaluation | None  #: None: fitted and read on a worker (:func:`read_where_fitted`)
    params: dict[str, Any]  #: its FittedQEvaluation settings (policy, horizon, gamma and seed aside)
    horizon: int | None  #: T of the time-indexed FQE; None: the stationary (discounted) one
    conditional: bool  #: structure-conditional bootstrap (frozen trees, discounted, no validation rows)
    estimate: float  #: J^ = mean over start states of sum_a pi(a | x0) Q^(x0, a)
    q: np.ndarray | None = None  #: Q^(x_i, .) at every row, when read where it was fitted
    reps: list[float] | None = None  #: its bootstrap replicates' J^, when read where it was fitted
    support: dict[str, Any] | None = None  #: its support bounds (conditional), when read where it was fitted


def read_where_fitted(fit: FQEFit, ds: TransitionDataset, policy: Policy, est_def: Estimand, cfg: EvaluationSettings,
                      x0: np.ndarray, pi_x0: np.ndarray) -> FQEFit:
    """``fit`` without its fitted FQE, with what the evaluation reads from it instead: Q at
    every row, the bootstrap replicates (:func:`bootstrap_values`, here, in order) and the
    support bounds (structure-conditional fits). A task on a worker returns this, so that
    the fitted FQE and its training state never travel (they are several times the data)."""
    from offline_adp.evaluation.ope import EpisodeMatrix

    a = ds.arrays()
    em = EpisodeMatrix.build(a.episode, a.step, est_def.horizon)
    n_reps = fqe_replicates(cfg.fqe_bootstrap, fit.conditional or fit.params.get("regressor") in CHEAP_REGRESSORS)
    q = fit.fqe.q_function_.values(a.obs, a.step)
    if fit.conditional:  # the replicates and the support bounds read leaf positions, not the trees
        fit.fqe.drop_trees()
    reps = bootstrap_values(fit, ds, policy, a, em, n_reps, cfg.seed, est_def.gamma, x0, pi_x0, None, lambda _m: None)
    if fit.conditional:
        fit.fqe.drop_replicate_cache()  # not held through the support bounds' operators
    support = fqe_support_bounds(fit.fqe, ds, cfg.seed) if fit.conditional else None
    return replace(fit, fqe=None, q=q, reps=[float(r) for r in reps], support=support)


def fqe_replicates(requested: int | None, cheap: bool) -> int:
    """FQE bootstrap replicates to run: ``requested`` as given (a user's setting is never
    overridden; below :data:`FQE_REPLICATE_ROUGH` the interval is called rough);
    ``None`` means :data:`FQE_REPLICATE_FLOOR` when replicates are cheap, else
    :data:`FQE_REPLICATE_ROUGH`; 0 means no interval."""
    if requested is None:
        return FQE_REPLICATE_FLOOR if cheap else FQE_REPLICATE_ROUGH
    return max(int(requested), 0)  # an explicit request is honoured (fewer than ROUGH: the interval says so)


def fqe_settings(fqe_params: dict[str, Any] | None, fqe_T: int | None, counted: bool = False) -> dict[str, Any]:
    """The user's FQE settings over :data:`DEFAULT_FQE` (its frozen mode, tree count and
    schedule only for its own regressor, else :data:`COUNTED_FQE`; also with an explicit
    ``n_iterations`` or ``counted``); a time-indexed FQE (``fqe_T``) runs exactly T steps, so no
    ``tol`` or ``n_iterations``, and FittedQEvaluation's own structure count."""
    user = dict(fqe_params or {})
    own = user.get("regressor", DEFAULT_FQE["regressor"]) == DEFAULT_FQE["regressor"]
    base = {k: v for k, v in DEFAULT_FQE.items() if own or k not in ("mode", "regressor_params")}
    if not own or counted or user.get("n_iterations", "auto") != "auto":
        base = {k: v for k, v in base.items() if k not in ("n_iterations", "n_structures")} | COUNTED_FQE
    params = {**base, **user}
    if fqe_T is not None:
        params.pop("tol", None)
        params.pop("n_iterations", None)
        if "n_structures" not in user:
            params.pop("n_structures", None)
    return params


def _start_value(fqe: FittedQEvaluation, x0: np.ndarray, pi_x0: np.ndarray, w0: np.ndarray | None) -> float:
    """sum_a pi(a|x0) Q(x0, a), averaged over the start states (weighted by ``w0``)."""
    v0 = (pi_x0 * fqe.q_function_.values(x0, 0)).sum(axis=1)
    return float(v0.mean()) if w0 is None else float(np.sum(w0 * v0) / np.sum(w0))


def fit_fqe(ds: TransitionDataset, policy: Policy, est_def: Estimand, fqe_params: dict[str, Any] | None, seed: int,
            x0: np.ndarray, pi_x0: np.ndarray) -> FQEFit:
    """FQE of ``policy`` on all of ``ds`` in the estimand's form (time-indexed
    ``Q_0 .. Q_{T-1}``, Algorithm 12, or one discounted ``Q``), and its estimate ``J^``. A
    structure-conditional fit is first settled to its structure's fixed point
    (:meth:`~offline_adp.algorithms.fqe.FittedQEvaluation.settle`), the quantity each of
    its bootstrap replicates computes for other weights."""
    fqe_T = est_def.fqe_horizon
    params = fqe_settings(fqe_params, fqe_T)
    conditional = params.get("mode") == "frozen" and fqe_T is None and not params.get("validation_fraction")
    fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=est_def.gamma, random_state=seed, **params).fit(ds)
    if conditional:  # the estimate is the fixed point of the final structure, as each replicate's is
        fqe.settle()
    return FQEFit(fqe, params, fqe_T, conditional, _start_value(fqe, x0, pi_x0, None))


def _reweighted_replicate(c: np.ndarray, *, fqe: FittedQEvaluation, row_episode: np.ndarray) -> float:
    """The replicate of episode counts ``c``: its row weights ``c[row_episode]`` made here, one
    replicate's at a time (200 replicates' on 1M rows held at once: 1.5 GiB)."""
    return fqe.reweighted_value(c[row_episode], rtol=REPLICATE_RTOL)


def _refit_replicate(c: np.ndarray, *, ds: TransitionDataset, params: dict[str, Any], x0: np.ndarray,
                     pi_x0: np.ndarray, start: np.ndarray, row_episode: np.ndarray) -> float:
    import gc

    w = c[row_episode]
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


def bootstrap_values(fit: FQEFit, ds: TransitionDataset, policy: Policy, a: TransitionArrays, em: EpisodeMatrix,
                     n_reps: int, seed: int, gamma: float, x0: np.ndarray, pi_x0: np.ndarray,
                     task_map: TaskMap | None, say: Callable[[str], None]) -> list[float]:
    """``J^`` of ``n_reps`` trajectory-bootstrap replicates: episode ``i`` drawn ``k_i`` times
    weights its rows by ``k_i`` (:func:`~offline_adp.evaluation.ope.bootstrap_counts`, seeded).
    Tabular time-indexed FQE: all at once (:func:`tabular_fqe_replicates`); a
    structure-conditional fit: its leaves re-averaged to the fixed point for the weights
    (:data:`REPLICATE_RTOL`); otherwise a full refit each. Replicates run on ``task_map``."""
    from offline_adp.progress import PhaseLines

    counts = bootstrap_counts(em.n_episodes, n_reps, seed)  # per episode: each replicate's row weights made in it
    on_done = PhaseLines(say, "FQE bootstrap", n_reps, lines=4)  # four lines with an ETA, not one per replicate
    run = task_map or local_map
    start = a.step == 0
    if _tabular_fast(fit.params, fit.horizon) and n_reps:
        return list(tabular_fqe_replicates(a.obs, a.action, a.cost, a.next_obs, a.terminated, start, policy,
                                           ds.n_actions, fit.horizon, gamma,
                                           np.array([c[em.row_episode] for c in counts])))
    if fit.conditional:  # same trees, leaves re-averaged with the replicate's weights
        return run(_reweighted_replicate, counts, shared={"fqe": fit.fqe, "row_episode": em.row_episode},
                   on_done=on_done)
    params = {"policy": policy, "horizon": fit.horizon, "gamma": gamma, "random_state": seed, **fit.params}
    return run(_refit_replicate, counts, on_done=on_done, shared={"ds": ds, "params": params, "x0": x0,
                                                                  "pi_x0": pi_x0, "start": start,
                                                                  "row_episode": em.row_episode})


def _check_interval(r: OPEResult) -> OPEResult:
    """Warn when an interval excludes its own estimate (a shifted bootstrap)."""
    lo, hi = r.interval
    if np.isfinite(lo) and np.isfinite(hi) and np.isfinite(r.estimate) and not lo <= r.estimate <= hi:
        return replace(r, warnings=[*r.warnings, f"the interval [{lo:.4g}, {hi:.4g}] excludes the estimate "
                                    f"{r.estimate:.4g}: the bootstrap replicates are shifted; treat the interval as "
                                    "unreliable"])
    return r


def fqe_interval(est: float, reps: Sequence[float], n_episodes: int, level: float = 0.95) -> OPEResult:
    """FQE's value ``est`` with the interval from its bootstrap replicates ``reps``.

    The estimate is the plug-in ``est``, never moved. The interval is the percentile
    interval ``[q_lo, q_hi]`` of the replicates when they are centred on the estimate.
    When their mean is shifted from it by more than a quarter of the percentile width
    (about one bootstrap standard error), resampling has changed the regression (a tree
    fit on ~63% distinct episodes is coarser), and the shift is a bias of unknown sign for
    the estimate: the percentile interval reads it one way, the *basic* bootstrap interval
    ``[2 est - q_hi, 2 est - q_lo]`` (Efron & Tibshirani 1993, 13.4) the other. The interval
    is then the hull of the two, which holds the estimate and both readings.

    Until 2026-11 the shift was subtracted from the estimate (a bias correction). On
    continuous problems it fired 6 times and moved an accurate plug-in away from the
    rollout truth 4 times (path_tracking 3.623 -> 3.279 against 3.610; car_on_the_hill
    -0.390 -> -0.577 against -0.397), so it is gone.
    """
    if not len(reps):
        return OPEResult("fqe", est, (np.nan, np.nan), float(n_episodes), None,
                         interval_method="none (no bootstrap replicates)")
    q_lo, q_hi = float(np.quantile(reps, (1 - level) / 2)), float(np.quantile(reps, (1 + level) / 2))
    shift = float(np.mean(reps)) - est
    rounding = 64 * np.finfo(np.float64).eps * max(abs(est), float(np.max(np.abs(reps))))  # equal replicates' mean
    if abs(shift) <= max(0.25 * (q_hi - q_lo), rounding):
        return _check_interval(OPEResult("fqe", est, (q_lo, q_hi), float(n_episodes), level,
                                         percentile_interval=(q_lo, q_hi)))
    why = (f"bootstrap replicates are shifted by {shift:+.4g} from the estimate {est:.4g} (resampling changes the "
           "regression): the interval covers both the percentile and the basic bootstrap reading of that shift")
    return _check_interval(OPEResult("fqe", est, (min(q_lo, 2 * est - q_hi), max(q_hi, 2 * est - q_lo)),
                                     float(n_episodes), level, warnings=[why], percentile_interval=(q_lo, q_hi),
                                     interval_method="hull of the percentile and basic bootstrap intervals"))


def with_structure_note(fq: OPEResult) -> OPEResult:
    """A structure-conditional interval says that it keeps the fitted tree structure."""
    return replace(fq, interval_method=fq.interval_method + " (structure-conditional: tree structure fixed, leaves "
                   "re-averaged)", warnings=[*fq.warnings, "the interval keeps the fitted tree structure, so it omits "
                                             "the structure's own variability (a structure-conditional bootstrap)"])


def q_value_range(cost: np.ndarray, terminated: np.ndarray, gamma: float,
                  infeasible_cost: float | None = None) -> tuple[float, float]:
    """Bounds on any discounted value ``Q(x, a)`` if the costs of unseen pairs lie in the
    logged ranges: with non-terminal costs in ``[c_lo, c_hi]`` and costs of terminating
    steps in ``[k_lo, k_hi]``, any path's value lies in
    ``[min(c_lo / (1 - gamma), k_lo), max(c_hi / (1 - gamma), k_hi)]`` (its value after k
    non-terminal steps then a terminating one is monotone in k); the upper end capped at
    the fit's ``infeasible_cost`` clamp."""
    cost = np.asarray(cost, dtype=np.float64)
    term = np.asarray(terminated, dtype=bool)
    lo, hi = np.inf, -np.inf
    if (~term).any():
        lo, hi = float(cost[~term].min()) / (1.0 - gamma), float(cost[~term].max()) / (1.0 - gamma)
    if term.any():
        lo, hi = min(lo, float(cost[term].min())), max(hi, float(cost[term].max()))
    if infeasible_cost is not None:
        hi = min(hi, float(infeasible_cost))
    return lo, hi


def fqe_support_bounds(fqe: FittedQEvaluation, ds: TransitionDataset, seed: int = 0) -> dict[str, Any]:
    """What the logs cannot tell about the policy's value through the fitted structure:
    the value of its *per-action read* (:func:`~offline_adp.algorithms.fqe_bootstrap.support_operators`:
    only rows of the queried action, within the data's own spacing of the queried state)
    with every pair the logs hold no such row for valued at the lowest and then the highest
    value the cost range allows (:func:`q_value_range`)."""
    from offline_adp.algorithms.fqe_bootstrap import support_radius

    d = fqe.fit_state_.data
    a = ds.arrays()
    radius = support_radius(d.obs, np.asarray(d.train.actions), d.obs_std, SUPPORT_RADIUS_QUANTILE, seed=seed)
    lo_q, hi_q = q_value_range(a.cost, a.terminated, d.gamma, getattr(fqe, "infeasible_cost", None))
    sb = fqe.support_bounds(lo_q, hi_q, radius=radius)
    return {**sb, "value_range": [lo_q, hi_q], "radius": radius, "radius_quantile": SUPPORT_RADIUS_QUANTILE,
            "method": "per-action read of the fitted trees (rows of the queried action within the data's own "
                      f"{SUPPORT_RADIUS_QUANTILE:.0%} nearest-neighbour spacing of the queried state), unsupported "
                      "pairs valued at the ends of the cost's value range"}


def with_support_bounds(fq: OPEResult, sb: dict[str, Any]) -> OPEResult:
    """FQE's interval widened to the hull of it and the support bounds ``sb``
    (:func:`fqe_support_bounds`), which are recorded; a warning names the policy's
    next-state action mass the logs cannot read when the widening applied."""
    lo, hi = sb["lower"], sb["upper"]
    out, before = replace(fq, support_bounds=sb).widened(
        lo, hi, f"widened to the support bounds [{lo:.4g}, {hi:.4g}] (the value with the pairs the logs hold no row "
        "of the queried action near valued at the cost range's ends; not a bound on the trees' smoothing within an "
        "action)")
    if before is None or not sb["unsupported_next"] > 0:
        return out
    return replace(out, warnings=[*out.warnings, f"{sb['unsupported_next']:.1%} of the policy's next-state action mass "
                                  "has no logged row of that action near the state: the interval is widened to what "
                                  f"those pairs could be worth ([{lo:.4g}, {hi:.4g}])"])


def widen_fqe(fq: OPEResult, mr: dict[str, Any], hull: bool = True) -> OPEResult:
    """FQE's result with the model rollouts ``mr`` recorded and its interval widened to the
    hull of it and the rollouts' interval, saying where the two readings part: the interval
    then holds the value if either reading is right, and a verdict drawn from it needs both.
    ``hull=False``: record the rollouts and their drift warning only (FQE's interval is of
    another quantity)."""
    out = replace(fq, model_rollouts=mr)
    if "skipped" in mr:
        return out
    if mr["exit_mass"] >= EXIT_FRACTION:
        out = replace(out, warnings=[*out.warnings,
                                     f"the policy drives where the logs do not go: {mr['exit_mass']:.0%} "
                                     "of its discounted model-rollout mass lies past the logged states (an expected "
                                     f"{mr['exit_share']:.0%} of its episodes get there)"])
    if not hull:
        return out
    lo_m, hi_m = mr["interval"]
    out, before = out.widened(lo_m, hi_m, f"widened to the model rollouts' bounds [{lo_m:.4g}, {hi_m:.4g}] (a model "
                              "of the logged increments rolled out, valued at the cost range's ends where it leaves "
                              "the data)")
    if before is None or before[0] <= mr["estimate"] <= before[1]:
        return out
    return replace(out, warnings=[*out.warnings, f"model rollouts of the logs read {mr['estimate']:.4g}, outside FQE's "
                                  f"interval [{before[0]:.4g}, {before[1]:.4g}]: the two readings disagree and the "
                                  "interval holds both"])


def with_fqe_interval(mr: dict[str, Any], fq: OPEResult, tail: float,
                      boot: tuple[float, float] | None = None) -> dict[str, Any]:
    """The model rollouts ``mr`` with FQE's interval before their hull (its bootstrap and support
    bounds, widened by the truncation bound ``tail`` as :func:`with_truncation_bound` will) as
    ``fqe_interval``: what :func:`~offline_adp.evaluation.model_bootstrap.model_estimate` checks
    the model's own interval against; and ``boot``, FQE's bootstrap interval alone (before the
    support bounds; widened by ``tail`` too), as ``fqe_bootstrap_interval``: where the model's
    interval misses it, the two readings disagree on what the logs do hold, and the model's
    labelled interval becomes the hull of both (``model_estimate``)."""
    if "skipped" in mr or not np.all(np.isfinite(fq.interval)):
        return mr
    t = tail if tail > 0 else 0.0
    ok = boot is not None and bool(np.all(np.isfinite(boot)))  # the key is always written: it dates the evaluation
    return {**mr, "fqe_interval": [float(fq.interval[0]) - t, float(fq.interval[1]) + t],
            "fqe_bootstrap_interval": [float(boot[0]) - t, float(boot[1]) + t] if ok else None}


def model_reading(ds: TransitionDataset, policy: Policy, est_def: Estimand, particles: int, level: float, seed: int,
                  a: TransitionArrays, say: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The model rollouts :func:`widen_fqe` hulls FQE's interval with: ``particles`` rollouts
    of a model of the logged increments over the estimand's horizon (the model is stationary,
    so it reads past the logged horizon too; :func:`~offline_adp.evaluation.model_rollouts.model_rollouts`);
    ``particles=0`` says they were turned off (so metrics.json tells "turned off" from "not a feature");
    ``say``: progress lines over the rollout's steps."""
    from offline_adp.progress import PhaseLines

    if not particles:
        return {"skipped": "model_particles=0: model rollouts turned off"}
    steps = None if say is None else PhaseLines(say, "model rollouts: step", est_def.value_horizon)
    def boot(model: Any, arrays: TransitionArrays, ranges: Any, estimate: float) -> dict[str, Any]:
        if say is not None:
            say(f"model rollouts: {MODEL_REPLICATES} bootstrap refits of the model")
        return bootstrap_reading(model, arrays, policy, est_def.value_horizon, est_def.gamma, estimate,
                                 n=particles, level=level, seed=seed, replicates=MODEL_REPLICATES)

    return model_rollouts(ds, policy, est_def.value_horizon, est_def.gamma, n=particles, level=level, seed=seed,
                          arrays=a, on_step=steps, bootstrap=boot)


def with_rough_note(fq: OPEResult, n_reps: int) -> OPEResult:
    """Fewer than :data:`FQE_REPLICATE_ROUGH` replicates: the percentiles are called rough."""
    if not 0 < n_reps < FQE_REPLICATE_ROUGH:
        return fq
    return replace(fq, warnings=[*fq.warnings, f"only {n_reps} bootstrap refits: the interval's percentiles are rough "
                                 f"(use at least {FQE_REPLICATE_ROUGH}; {FQE_REPLICATE_FLOOR} for stable ones)"])


def with_truncation_bound(fq: OPEResult, tail: float) -> OPEResult:
    """A stationary FQE read as the T-step value is within ``tail = gamma^T max|c| / (1 - gamma)``
    of it: the interval is widened by ``tail`` on both sides."""
    if not (tail > 0 and np.all(np.isfinite(fq.interval))):
        return fq
    return replace(fq, interval=(fq.interval[0] - tail, fq.interval[1] + tail),
                   interval_method=fq.interval_method + f", widened by the truncation bound {tail:.3g}")


def fqe_with_interval(ds: TransitionDataset, policy: Policy, est_def: Estimand, cfg: EvaluationSettings, *,
                      a: TransitionArrays, em: EpisodeMatrix, level: float, task_map: TaskMap | None,
                      say: Callable[[str], None], fit: FQEFit | None = None,
                      model: dict[str, Any] | None = None) -> tuple[FQEFit, OPEResult]:
    """FQE's estimate ``J^`` and its interval: fit (:func:`fit_fqe`), bootstrap
    (:func:`bootstrap_values`, :func:`fqe_replicates` replicates), percentile / basic hull
    (:func:`fqe_interval`), then widened by the support bounds (structure-conditional fits),
    the model rollouts and the truncation bound, in that order (module docstring). ``fit``
    and ``model``: the fit and the model rollouts' reading when already computed (on a
    task map, :mod:`~offline_adp.evaluation.batch`)."""
    x0 = a.obs[a.step == 0]
    pi_x0 = policy.probabilities(x0, 0)  # once, not per bootstrap replicate
    if fit is None:
        fit = fit_fqe(ds, policy, est_def, cfg.fqe_params, cfg.seed, x0, pi_x0)
    cheap = fit.conditional or fit.params.get("regressor") in CHEAP_REGRESSORS
    n_reps = fqe_replicates(cfg.fqe_bootstrap, cheap)
    reps = fit.reps if fit.reps is not None else bootstrap_values(fit, ds, policy, a, em, n_reps, cfg.seed,
                                                                  est_def.gamma, x0, pi_x0, task_map, say)
    fq = fqe_interval(fit.estimate, reps, em.n_episodes, level)
    if fit.conditional and n_reps:
        fq = with_structure_note(fq)
    boot = fq.interval  # FQE's own bootstrap interval: the model's interval is checked against it
    if fit.conditional:  # what the model cannot know: widen to the support bounds
        say("FQE support bounds")
        fq = with_support_bounds(fq, fit.support if fit.support is not None else fqe_support_bounds(fit.fqe, ds,
                                                                                                     cfg.seed))
    if est_def.form == "finite":  # hulled only where FQE's interval is of the same quantity (a
        if cfg.model_particles and model is None:  # time-indexed FQE past the logs reads the T-step value)
            say("model rollouts")
        hull = not est_def.beyond_logs or est_def.fqe_form == "stationary"
        mr = model if model is not None else model_reading(ds, policy, est_def, cfg.model_particles, level, cfg.seed,
                                                           a, say)
        fq = widen_fqe(fq, with_fqe_interval(mr, fq, est_def.tail_bound, boot) if hull else mr, hull=hull)
    return fit, with_truncation_bound(with_rough_note(fq, n_reps), est_def.tail_bound)
