"""Off-policy estimates of a policy's expected discounted cost from logged trajectories.

Notation: episode i, step t, cost c_t, discount gamma, per-step ratio
``rho_t = pi(a_t | x_t, t) / pi_b(a_t | x_t)`` and cumulative ``R_t = prod_{k<=t} rho_k``
(Precup, Sutton & Singh 2000). With N episodes (padded with zero cost after they end):

- **IS**: ``(1/N) sum_i R_{T-1} G_i`` with ``G_i = sum_t gamma^t c_t``.
- **WIS**: ``sum_i R_{T-1} G_i / sum_i R_{T-1}``.
- **PDIS** (per-decision): ``(1/N) sum_i sum_t gamma^t R_t c_t``.
- **WPDIS**: ``sum_t gamma^t sum_i R_t c_t / sum_i R_t``.
- **DR** (Jiang & Li 2016, unrolled)::

      (1/N) sum_i sum_t gamma^t [ R_t (c_t - Q^(x_t, a_t)) + R_{t-1} V^(x_t) ],  R_{-1} = 1

  with ``V^(x) = sum_a pi(a | x) Q^(x, a)`` from the FQE fit.
- **WDR** (Thomas & Brunskill 2016): DR with ``R_t`` replaced by ``R_t / mean_i R_t``.
- **MIS** (marginalised IS): ``sum_t gamma^t (1/N) sum_{i at t} w_t(x_i) rho_i c_i`` with
  the state density ratios ``w_t`` of :mod:`offline_adp.evaluation.shift`.

Intervals are trajectory-bootstrap percentile intervals: episodes resampled with
replacement; the fitted pieces (behaviour model, Q^, ratios w_t) are held fixed across
replicates; a resample is read through sums over episodes (:mod:`~offline_adp.evaluation.resample`).
FQE's own value and interval (the default estimate, the mean over start
states of ``V^(x_0)``, bootstrapped through FQE itself) are in
:mod:`offline_adp.evaluation.fqe_interval`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.special import softmax

from offline_adp.evaluation import resample


@dataclass
class OPEResult:
    """One estimator's answer.

    Attributes
    ----------
    name : str
    estimate : float
        Expected discounted cost of the evaluated policy.
    interval : (float, float)
        Bootstrap percentile interval at ``level`` (NaN when withheld: see ``level``).
    level : float or None
        The interval's nominal coverage; ``None`` when no interval is given because it
        would not mean what its level says (degenerate importance weights).
    ess : float or None
        Effective sample size (episodes), ``(sum w)^2 / sum w^2`` of the final weights
        (the worst step for per-decision estimators).
    warnings : list of str
    """

    name: str
    estimate: float
    interval: tuple[float, float]
    ess: float | None
    level: float | None = 0.95
    warnings: list[str] = field(default_factory=list)
    percentile_interval: tuple[float, float] | None = None
    interval_method: str = "percentile bootstrap over episodes"
    plugin_estimate: float | None = None  #: the uncorrected estimate, when ``estimate`` is bias-corrected
    comparable: bool = True
    degenerate: bool = False
    weight_diagnostics: dict[str, Any] | None = None  #: the weights' shape (:func:`weight_diagnostics`)
    #: FQE only: the support bounds the interval was widened to (``fqe_interval.fqe_support_bounds``).
    support_bounds: dict[str, Any] | None = None
    #: FQE only: the model rollouts the interval was widened to (``fqe_interval.widen_fqe``).
    model_rollouts: dict[str, Any] | None = None
    #: why the interval carries no level (``level`` None), where that was decided with a reason
    level_note: str | None = None
    #: the model rollouts only: where their interval and FQE's bootstrap interval did not overlap, the two
    #: intervals it is the hull of (``{"model": [lo, hi], "fqe_bootstrap": [lo, hi]}``; model_bootstrap.py)
    hull: dict[str, Any] | None = None
    #: DR and WDR only: the bootstrap interval of the estimate minus the logged mean cost of the same
    #: episodes, both read on each replicate's episodes (a paired difference: what the verdict against
    #: the behaviour reads where this estimator leads on the logging policy's own weights)
    vs_logged: tuple[float, float] | None = None

    def widened(self, lo: float, hi: float, why: str) -> tuple[OPEResult, tuple[float, float] | None]:
        """This result with its interval widened to the hull of it and ``[lo, hi]`` and ``why``
        appended to its method, and the interval before; ``(self, None)`` (nothing done) when
        either is not finite."""
        if not (np.all(np.isfinite(self.interval)) and np.isfinite(lo) and np.isfinite(hi)):
            return self, None
        before = (float(self.interval[0]), float(self.interval[1]))
        return replace(self, interval=(min(before[0], lo), max(before[1], hi)),
                       interval_method=self.interval_method + "; " + why), before

    def as_dict(self) -> dict[str, Any]:
        d = {"estimate": self.estimate, "interval": list(self.interval), "interval_method": self.interval_method,
             "level": self.level, "ess": self.ess, "warnings": list(self.warnings), "degenerate": self.degenerate,
             "comparable": self.comparable}
        if self.percentile_interval is not None:
            d["percentile_interval"] = list(self.percentile_interval)
        if self.plugin_estimate is not None:
            d["plugin_estimate"] = self.plugin_estimate
        if self.weight_diagnostics is not None:
            d["weight_diagnostics"] = dict(self.weight_diagnostics)
        if self.support_bounds is not None:
            d["support_bounds"] = dict(self.support_bounds)
        if self.model_rollouts is not None:
            d["model_rollouts"] = dict(self.model_rollouts)
        if self.level_note is not None:
            d["level_note"] = self.level_note
        if self.hull is not None:
            d["hull"] = {k: list(v) for k, v in self.hull.items()}
        if self.vs_logged is not None:
            d["vs_logged"] = list(self.vs_logged)
        return d


@dataclass
class EpisodeMatrix:
    """Per-row quantities laid out as (N episodes, T steps), zero-padded after an episode ends."""

    n_episodes: int
    horizon: int
    row_episode: np.ndarray
    row_step: np.ndarray
    mask: np.ndarray

    @classmethod
    def build(cls, episode: np.ndarray, step: np.ndarray, horizon: int | None = None) -> EpisodeMatrix:
        _, ep = np.unique(episode, return_inverse=True)
        T = int(step.max()) + 1 if horizon is None else int(horizon)
        keep = step < T
        mask = np.zeros((int(ep.max()) + 1, T), bool)
        mask[ep[keep], step[keep]] = True
        return cls(mask.shape[0], T, ep, step, mask)

    def lay(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        out = np.full(self.mask.shape, fill)
        keep = self.row_step < self.horizon
        out[self.row_episode[keep], self.row_step[keep]] = values[keep]
        return out


def _ess(w: np.ndarray) -> float:
    s2 = float(np.sum(w**2))
    return float(np.sum(w) ** 2 / s2) if s2 > 0 else 0.0


def importance_sampling_estimates(
    em: EpisodeMatrix, cost: np.ndarray, rho: np.ndarray, gamma: float, *, n_boot: int = 200, level: float = 0.95,
    seed: int = 0, groups: np.ndarray | None = None,
) -> dict[str, OPEResult]:
    """IS, WIS, PDIS and WPDIS (formulas in the module docstring).

    ``groups`` (a label per episode, e.g. the behaviour component that logged it) lets the
    interval rule (:func:`interval_unreliable`) see weight carried by a subset of them.
    """
    C = em.lay(cost)
    R = np.cumprod(em.lay(rho, fill=1.0), axis=1)  # after the end: ratio 1, cost 0
    disc = gamma ** np.arange(em.horizon)
    G = C @ disc
    RT = R[:, -1]
    N, T = em.n_episodes, em.horizon
    # each estimator: its per-episode sums M (made when its turn comes) and f of their totals S
    forms: tuple[tuple[str, Callable[[], np.ndarray], Callable[[np.ndarray], np.ndarray]], ...] = (
        ("is", lambda: (RT * G)[:, None], lambda S: S[:, 0] / N),
        ("wis", lambda: np.column_stack([RT * G, RT]), lambda S: resample.ratio(S[:, 0], S[:, 1], np.nan)),
        ("pdis", lambda: ((R * C) @ disc)[:, None], lambda S: S[:, 0] / N),
        ("wpdis", lambda: np.hstack([R * C, R]), lambda S: resample.ratio(S[:, :T], S[:, T:]) @ disc),
    )
    rng = np.random.default_rng(seed)
    step_ess = min(_ess(R[:, t]) for t in range(em.horizon))
    out = {}
    for name, make, f in forms:
        M = make()
        bad = resample.nonfinite_episodes(M)
        est, iv, _ = resample.estimate_and_interval(M, f, n_boot, level, rng, nonfinite=bad)
        out[name] = OPEResult(name, est, iv, _ess(RT) if name in ("is", "wis") else step_ess, level)
        _judge_weights(out[name], RT if name in ("is", "wis") else R, groups, bad)
    return out


def doubly_robust_estimates(
    em: EpisodeMatrix, cost: np.ndarray, rho: np.ndarray, q_logged: np.ndarray, v_obs: np.ndarray, gamma: float, *,
    n_boot: int = 200, level: float = 0.95, seed: int = 0, groups: np.ndarray | None = None,
) -> dict[str, OPEResult]:
    """DR (Jiang & Li 2016) and weighted DR (Thomas & Brunskill 2016).

    Parameters
    ----------
    q_logged : ndarray (n,)
        ``Q^(x_i, a_i)`` at each row's step.
    v_obs : ndarray (n,)
        ``V^(x_i) = sum_a pi(a | x_i) Q^(x_i, a)``.
    """
    C, Q, V = em.lay(cost), em.lay(q_logged), em.lay(v_obs)
    R = np.cumprod(em.lay(rho, fill=1.0), axis=1)
    R_prev = np.hstack([np.ones((em.n_episodes, 1)), R[:, :-1]])
    disc = gamma ** np.arange(em.horizon)
    N, T = em.n_episodes, em.horizon
    forms: tuple[tuple[str, Callable[[], np.ndarray], Callable[[np.ndarray], np.ndarray]], ...] = (
        ("dr", lambda: ((R * (C - Q) + R_prev * V) @ disc)[:, None], lambda S: S[:, 0] / N),
        # WDR: R_t / mean_i R_t, so the step's sum over the resample divides its weighted terms
        ("wdr", lambda: np.hstack([R * (C - Q), R, R_prev * V, R_prev]),
         lambda S: (resample.ratio(S[:, :T], S[:, T:2 * T]) + resample.ratio(S[:, 2 * T:3 * T], S[:, 3 * T:])) @ disc),
    )
    rng = np.random.default_rng(seed)
    ess = min(_ess(R[:, t]) for t in range(em.horizon))
    G = C @ disc  # each episode's logged discounted cost: the paired difference's other half
    out = {}
    for name, make, f in forms:
        M = make()
        bad = resample.nonfinite_episodes(M, G)
        est, iv, diff = resample.estimate_and_interval(M, f, n_boot, level, rng, g=G, nonfinite=bad)
        out[name] = OPEResult(name, est, iv, ess, level, vs_logged=diff)
        _judge_weights(out[name], R, groups, bad)
    return out


#: An IS-family interval is withheld below this effective sample size (episodes): too few
#: for bootstrap percentiles at all (measured on tabular problems, T = 10, 30 seeds: intervals
#: labelled 95% covered 3-67% at ESS ~ 2, 60-90% at ESS ~ 9, 87-93% at ESS ~ 45).
MIN_ESS = 30.0
#: ... or below this fraction of the episodes (ESS/n): the weights are degenerate.
MIN_ESS_FRACTION = 0.01
#: ... as they are below this many episodes whatever n: one or two episodes' returns, not an estimate
#: (ESS 1.0 of 40 episodes, one episode holding all the weight, was "no interval" and ranked, not "not usable").
#: Not for MIS: its ESS is the worst step's among the episodes still running there, 1.0 wherever one
#: episode runs longer than every other, whatever the weights (:func:`degenerate_floor`).
MIN_ESS_DEGENERATE = 2.0


def degenerate_floor(name: str, n: int) -> float:
    """The ESS below which estimator ``name``'s weights over ``n`` episodes are degenerate
    (0 for FQE and the model rollouts: their ``ess`` is no importance weights' ESS)."""
    if name in ("fqe", "model"):
        return 0.0
    return max(MIN_ESS_FRACTION * n, 0.0 if name == "mis" else MIN_ESS_DEGENERATE)

#: Weights whose ESS keeps at least this share of the episodes at every step are the logging
#: policy's own, nearly: the logged episodes are (almost) draws of the policy's trajectories, and
#: the doubly robust estimate is their mean cost with FQE as a control variate (unbiased with right
#: weights, whatever FQE's error). There WDR leads the headline (``summary.rank_estimators``), reads
#: past the logged horizon with the tail allowance (``estimand.confined``) and the verdict against
#: the behaviour reads its paired difference from the logged cost (``vs_logged``).
ON_POLICY_ESS_FRACTION = 0.5


def on_policy(r: dict[str, Any] | OPEResult) -> bool:
    """Whether DR/WDR result ``r`` (an :class:`OPEResult` or its stored dict) has a labelled
    interval from weights that keep :data:`ON_POLICY_ESS_FRACTION` of the episodes' effective size."""
    d = r.as_dict() if isinstance(r, OPEResult) else r
    wd = d.get("weight_diagnostics")
    frac = wd.get("ess_fraction") if isinstance(wd, dict) else None
    iv = d.get("interval")
    ok = is_finite_number(frac) and ON_POLICY_ESS_FRACTION <= frac <= 1.0 + 1e-9
    labelled = (d.get("level") is not None and isinstance(iv, (list, tuple)) and len(iv) == 2
                and all(map(is_finite_number, iv)))
    return bool(labelled and ok and not d.get("degenerate"))


def rounding_tol(*values: float) -> float:
    """The slack for "equal up to rounding" between costs: ``1e-9`` of the largest of
    ``values`` in size, relative, so that a comparison reads alike in any unit of the costs."""
    return 1e-9 * max((abs(float(v)) for v in values), default=0.0)


def is_finite_number(x: Any) -> bool:
    """A finite int or float (not a bool; an int too large for a float is not one: numpy cannot
    test it and no formatting of ours would read it)."""
    if isinstance(x, bool) or not isinstance(x, int | float | np.floating | np.integer):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False

#: ... or when one episode holds more than this share of the total weight.
MAX_WEIGHT_SHARE = 0.1
#: ... or when the generalized Pareto shape of the weights' upper tail exceeds this
#: (Vehtari, Simpson, Gelman, Yao & Gabry, Pareto smoothed importance sampling: k > 0.7,
#: the variance is effectively infinite and the estimate's error is not normal).
MAX_PARETO_K = 0.7
#: ... or when the weight mean is this far (and 3 standard errors) from 1: E[w] = 1 for
#: correct propensities, so a mean well below 1 says the weight pi puts on trajectories the
#: logs (almost) never show is missing, and an unnormalised estimate is biased by that factor.
MAX_MEAN_WEIGHT_ERROR = 0.2
#: ... or when episode groups (behaviour components, the data's ``source``) holding at most
#: this fraction of the episodes carry all but 1% of the weight.
MAX_SUBSET_FRACTION = 0.9


def _gpd_shape(x: np.ndarray) -> float:
    """Shape ``k`` of a generalized Pareto fit to exceedances ``x`` (ascending, > 0) by
    Zhang & Stephens (2009)'s empirical Bayes estimate, with the weakly informative prior
    towards 0.5 that Pareto smoothed importance sampling uses (Vehtari et al. 2015, 2024)."""
    n = len(x)
    m = 30 + int(np.sqrt(n))
    bs = 1.0 / x[-1] + (1.0 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))) / (3.0 * x[int(n / 4 + 0.5) - 1])
    ks = np.log1p(-bs[:, None] * x).mean(axis=1)
    L = n * (np.log(-bs / ks) - ks - 1.0)
    w = softmax(L)  # = 1 / sum_j exp(L_j - L_i), without overflowing where one L dominates
    keep = w >= 10 * np.finfo(float).eps
    w, bs = w[keep] / w[keep].sum(), bs[keep]
    b = float(np.sum(bs * w))
    k = float(np.mean(np.log1p(-b * x)))  # the shape (k > 0: heavy tail)
    return (k * n + 10 * 0.5) / (n + 10)


def pareto_k(w: np.ndarray) -> float:
    """PSIS diagnostic: the generalized Pareto shape of the largest ``M = min(n/5, 3 sqrt(n))``
    weights above the next one (Vehtari et al.); ``nan`` when the tail is flat (fewer than 5
    distinct exceedances: no heavy tail to fit), ``inf`` when fewer than 5 weights are positive."""
    w = np.sort(np.asarray(w, dtype=np.float64))
    pos = w[w > 0]
    if len(pos) < 5:
        return float("inf")
    M = int(np.ceil(min(0.2 * len(w), 3 * np.sqrt(len(w)))))
    if M < 5 or M >= len(w):
        return float("nan")
    cut = w[-M - 1]
    x = w[-M:] - cut
    x = x[x > 1e-12 * max(w[-1], 1e-300)]
    if len(x) < 5 or np.ptp(x) <= 1e-12 * x[-1]:
        return float("nan")
    return _gpd_shape(x)


def weight_diagnostics(W: np.ndarray, groups: np.ndarray | None = None) -> dict[str, Any]:
    """Shape of importance weights, worst over columns (steps).

    ``W`` is (n episodes,) or (n, T) (the cumulative weights ``R_t`` of every step).
    Per column: ESS ``(sum w)^2 / sum w^2``, ESS/n, the largest weight's share of the total,
    the Pareto ``k`` of the upper tail (:func:`pareto_k`), the mean weight and its standard
    error, and with ``groups`` (a label per episode) each group's share of the weight. The
    worst column is reported for each (lowest ESS, largest share and k, mean farthest from 1,
    most concentrated groups).
    """
    W = np.asarray(W, dtype=np.float64)
    W = W[:, None] if W.ndim == 1 else W
    n = W.shape[0]
    out: dict[str, Any] = {"n": n, "ess": np.inf, "max_share": 0.0, "pareto_k": float("nan"), "mean": 1.0,
                           "mean_se": 0.0, "carrying_fraction": 1.0, "carrying_groups": None}
    for j in range(W.shape[1]):
        w = W[:, j]
        tot = float(w.sum())
        out["ess"] = min(out["ess"], _ess(w))
        out["max_share"] = max(out["max_share"], float(w.max() / tot) if tot > 0 else 1.0)
        k = pareto_k(w)
        if np.isfinite(k) or np.isinf(k):
            out["pareto_k"] = k if not np.isfinite(out["pareto_k"]) else max(out["pareto_k"], k)
        m, se = float(w.mean()), float(w.std(ddof=1) / np.sqrt(n)) if n > 1 else float("inf")
        if abs(m - 1.0) > abs(out["mean"] - 1.0):
            out["mean"], out["mean_se"] = m, se
        if groups is not None and tot > 0:
            labels = np.unique(groups)
            share = {g: float(w[groups == g].sum() / tot) for g in labels}
            carrying = [g for g in labels if share[g] >= 0.01]
            frac = float(np.isin(groups, carrying).mean())
            if frac < out["carrying_fraction"]:
                out["carrying_fraction"], out["carrying_groups"] = frac, {str(g): share[g] for g in carrying}
    out["ess_fraction"] = out["ess"] / n if n else 0.0
    return out


def interval_unreliable(d: dict[str, Any], *, normalised: bool) -> list[str]:
    """Reasons, in words, why a bootstrap interval of an IS-family estimate would not cover as
    labelled (empty: it may be given). The rule looks at the weights' shape, not a count: ESS
    below :data:`MIN_ESS` or :data:`MIN_ESS_FRACTION` of the episodes; one episode with more than
    :data:`MAX_WEIGHT_SHARE` of the weight; a heavy upper tail (Pareto k > :data:`MAX_PARETO_K`);
    for unnormalised estimators (IS, PDIS, DR, MIS) a mean weight far from 1; and weight carried by
    a subset of the episode groups (e.g. only one behaviour component's episodes)."""
    n, why = d["n"], []
    if d["ess"] < MIN_ESS or d["ess_fraction"] < MIN_ESS_FRACTION:
        why.append(f"effective sample size {d['ess']:.1f} of {n} episodes (below {MIN_ESS:g}, or "
                   f"{MIN_ESS_FRACTION:.0%} of the episodes)")
    if d["max_share"] > MAX_WEIGHT_SHARE:
        why.append(f"one episode holds {d['max_share']:.0%} of the total weight")
    k = d["pareto_k"]
    if np.isfinite(k) and k > MAX_PARETO_K or np.isinf(k):
        why.append(f"the weights' upper tail is heavy (Pareto k {k:.2f} > {MAX_PARETO_K})")
    err = abs(d["mean"] - 1.0)
    if not normalised and err > MAX_MEAN_WEIGHT_ERROR and err > 3 * d["mean_se"]:  # a scale normalising cancels
        why.append(f"the weights average {d['mean']:.3g}, not 1 (standard error {d['mean_se']:.2g}): the trajectories "
                   "the policy would take are missing from the logs, and the estimate is scaled down by their absent "
                   "weight")
    if d["carrying_groups"] is not None and d["carrying_fraction"] <= MAX_SUBSET_FRACTION:
        groups = ", ".join(f"{g!r} ({s:.0%} of the weight)" for g, s in d["carrying_groups"].items())
        why.append(f"only the episodes of {groups}, {d['carrying_fraction']:.0%} of the episodes, carry weight: the "
                   "estimate speaks only for those episodes and their start states")
    return why


#: Estimators whose weights are normalised (their scale cancels).
NORMALISED = ("wis", "wpdis", "wdr")


def _judge_weights(r: OPEResult, W: np.ndarray, groups: np.ndarray | None = None, nonfinite: int = 0) -> None:
    """Degenerate weights and intervals that would not cover as labelled: say so and withhold.

    ``r.ess`` is the worst step's ESS; ``r.weight_diagnostics`` keeps the shape measured.
    ``nonfinite``: episodes whose terms were NaN or infinite (no estimate at all, said so).
    """
    if nonfinite:
        r.level, r.vs_logged = None, None
        r.interval_method = "none: no estimate"
        r.warnings.append(f"no estimate: {nonfinite} of {len(W)} episodes give a NaN or infinite term (ratios, "
                          "costs or Q-values)")
        return
    d = weight_diagnostics(W, groups)
    r.weight_diagnostics = {k: v for k, v in d.items() if k != "n"}
    n = d["n"]
    if r.ess is not None and r.ess < degenerate_floor(r.name, n):
        r.degenerate = True
        r.warnings.append(f"effective sample size {r.ess:.1f} of {n} episodes: the weights are degenerate")
    why = interval_unreliable(d, normalised=r.name in NORMALISED)
    if why and np.all(np.isfinite(r.interval)):
        r.percentile_interval = r.interval
        r.interval = (float("nan"), float("nan"))
        r.level = None
        r.vs_logged = None  # the paired difference's weights are the same
        r.interval_method = ("none: " + "; ".join(why) + ", so a bootstrap interval would not cover as labelled "
                             "(its raw percentiles are kept as percentile_interval)")
        if not r.degenerate:
            r.warnings.append("no interval: " + "; ".join(why))


def marginalised_is_estimate(
    em: EpisodeMatrix, cost: np.ndarray, rho: np.ndarray, w_state: np.ndarray, gamma: float, *, n_boot: int = 200,
    level: float = 0.95, seed: int = 0, groups: np.ndarray | None = None,
) -> OPEResult:
    """Marginalised IS with state density ratios ``w_state`` (one per row, its own step)."""
    Y = em.lay(w_state * rho * cost)
    Wt = em.lay(w_state * rho)
    disc = gamma ** np.arange(em.horizon)

    rng = np.random.default_rng(seed)
    ess = min(_ess(Wt[em.mask[:, t], t]) for t in range(em.horizon) if em.mask[:, t].any())
    N = em.n_episodes
    M = (Y @ disc)[:, None]
    bad = resample.nonfinite_episodes(M)
    est, iv, _ = resample.estimate_and_interval(M, lambda S: S[:, 0] / N, n_boot, level, rng, nonfinite=bad)
    res = OPEResult("mis", est, iv, ess, level)
    res.warnings.append("interval holds the fitted ratios fixed (it omits their estimation error)")
    _judge_weights(res, Wt, groups, bad)
    return res


def bootstrap_counts(n_episodes: int, n_boot: int, seed: int = 0) -> list[np.ndarray]:
    """Episode multiplicities of ``n_boot`` trajectory-bootstrap replicates (seeded)."""
    rng = np.random.default_rng(seed)
    return [resample.multiplicities(n_episodes, rng) for _ in range(n_boot)]


#: fewer logged episodes than this: no interval of the evaluation carries a level. An episode
#: bootstrap of n episodes has at most C(2n - 1, n) distinct resamples (1 for one episode,
#: 3 for two), and its percentile interval's coverage is unknown that small (an audit,
#: 2026-11-29: one or two episodes gave "95%" intervals that missed the exact truth)
MIN_LEVEL_EPISODES = 10


def with_enough_episodes(results: dict[str, OPEResult], n_episodes: int) -> dict[str, OPEResult]:
    """``results`` with every level withdrawn (the intervals kept, unlabelled) when the logs
    hold fewer than :data:`MIN_LEVEL_EPISODES` episodes, saying so."""
    if n_episodes >= MIN_LEVEL_EPISODES:
        return results
    why = (f"{n_episodes} logged episode{'s' if n_episodes != 1 else ''}: an episode bootstrap needs at least "
           f"{MIN_LEVEL_EPISODES} for an interval of known coverage")
    return {k: r if r.level is None else replace(r, level=None, level_note=why, warnings=[f"no level: {why}",
                                                                                          *r.warnings])
            for k, r in results.items()}


def flagged_against(results: dict[str, OPEResult], reference: str = "fqe") -> dict[str, OPEResult]:
    """The results, each comparable estimate that falls outside the reference's interval
    with a warning saying so."""
    ref = results.get(reference)
    if ref is None or not np.all(np.isfinite(ref.interval)):
        return dict(results)
    lo, hi = ref.interval
    return {name: replace(r, warnings=[*r.warnings, f"outside the {reference.upper()} interval [{lo:.4g}, {hi:.4g}]"])
            if name != reference and r.comparable and np.isfinite(r.estimate) and not lo <= r.estimate <= hi else r
            for name, r in results.items()}
