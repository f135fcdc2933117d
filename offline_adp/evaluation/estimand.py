"""The quantity every off-policy estimator targets (:class:`Estimand`), the horizon and
discount it is read at, and the range its value can take: what
:func:`~offline_adp.evaluation.offpolicy.off_policy` declares first and confines its
estimates to last.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.data.discount import resolve_discount
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.evaluation import ope
from offline_adp.policies import Policy, is_stationary

#: The stationary (discounted) FQE stands in for the T-step FQE when ``gamma^T`` is below this:
#: the two differ by at most ``gamma^T max|c| / (1 - gamma)``, which is added to its interval.
TAIL_NEGLIGIBLE = 0.01


def evaluation_horizon(ds: TransitionDataset, horizon: int | None = None) -> tuple[int, float, int | None]:
    """(T for trajectory estimators and rollouts, gamma, T again: the finite-horizon FQE).

    T is the data's longest episode, capped by ``info.horizon`` and by ``horizon``.
    (See :func:`declare_estimand` for the quantity every estimator targets.)
    """
    a = ds.arrays()
    gamma = resolve_discount(ds.info).gamma  # the package's one rule, as the fit used
    T = int(a.step.max()) + 1
    if horizon is not None and int(horizon) > T:
        import warnings

        warnings.warn(f"horizon {int(horizon)} asked for, but the longest logged episode has {T} steps: the "
                      f"estimand is the {T}-step value (a simulator's rollout horizon, target_horizon, reads past "
                      "the logs)", UserWarning, stacklevel=2)
    for cap in (ds.info.horizon, horizon):
        if cap is not None:
            T = min(T, int(cap))
    return T, float(gamma), T


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


def _stationary_on(policy: Policy, obs: np.ndarray, T: int) -> bool:
    """Whether ``policy`` gives the same probabilities at every step t < T on the data's
    states (:func:`offline_adp.policies.is_stationary`: declared, else probed)."""
    return is_stationary(policy, obs, T)


def declare_estimand(ds: TransitionDataset, policy: Policy, horizon: int | None = None, form: str = "finite", *,
                     target_horizon: int | None = None, start: str | None = None) -> Estimand:
    """The quantity :func:`~offline_adp.evaluation.offpolicy.off_policy` estimates (see :class:`Estimand`).

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
                            f"the {H}-step value asked for exceeds the {T} logged steps; gamma^{H} = "
                            f"{gamma**H:.2g}: the "
                            f"stationary discounted FQE differs from it by at most gamma^{H} max|c| / (1 - gamma) = "
                            f"{tail:.3g}, added to its interval; the trajectory estimators see only {T} steps",
                            target_horizon=H, **where)
        return Estimand(T, gamma, "finite", "time-indexed", 0.0,
                        f"the {H}-step value asked for exceeds the {T} logged steps: no estimator of these logs sees "
                        f"past step {T} (time-indexed FQE over the {T} logged steps)", target_horizon=H, **where)
    if gamma < 1.0 and gamma**T <= TAIL_NEGLIGIBLE and _stationary_on(policy, a.obs, T):
        tail = gamma**T * c_max / (1.0 - gamma)
        return Estimand(T, gamma, "finite", "stationary", tail,
                        f"gamma^T = {gamma**T:.2g}: the stationary discounted FQE differs from the {T}-step "
                        f"value by at most gamma^T max|c| / (1 - gamma) = {tail:.3g}, added to its interval", **where)
    why = "the policy changes with t" if gamma < 1.0 and gamma**T <= TAIL_NEGLIGIBLE else (
        "undiscounted" if gamma >= 1.0 else f"gamma^T = {gamma**T:.2g} is not negligible")
    return Estimand(T, gamma, "finite", "time-indexed", 0.0, f"time-indexed FQE over the {T} logged steps ({why})",
                    target_horizon=int(target_horizon) if target_horizon is not None else None, **where)


def step_cost_range(cost: np.ndarray, terminated: np.ndarray | None, em: ope.EpisodeMatrix) -> tuple[float, float]:
    """``[c_lo, c_hi]``: what one of the T logged steps can cost, the logged costs' range with 0
    in it where episodes stop early (a terminal state, or shorter than T: they add 0 from then on)."""
    lo_c, hi_c = float(np.min(cost)), float(np.max(cost))
    if (terminated is not None and bool(np.any(terminated))) or not em.mask.all():
        lo_c, hi_c = min(lo_c, 0.0), max(hi_c, 0.0)
    return lo_c, hi_c


def with_possible_range(est_def: Estimand, a: TransitionArrays,
                        em: ope.EpisodeMatrix) -> tuple[Estimand, tuple[float, float]]:
    """The range the estimand's value can take, from the logged costs ``[c_lo, c_hi]`` (with 0
    when episodes stop early: they add 0 from then on): ``[c_lo, c_hi] sum_{t<T} gamma^t``
    (``1 / (1 - gamma)`` for the infinite-horizon value). Returns the estimand with its
    ``possible_range`` set and the logged T steps' range; past the logs (``beyond_logs``) the
    estimand's own range is over its H steps with 0 in it (the logs end before H)."""
    gamma, T, H = est_def.gamma, est_def.horizon, est_def.value_horizon
    lo_c, hi_c = step_cost_range(a.cost, a.terminated, em)
    span = float(np.sum(gamma ** np.arange(T))) if est_def.form == "finite" else 1.0 / (1.0 - gamma)
    logged_range = (lo_c * span, hi_c * span)
    if not est_def.beyond_logs:
        return replace(est_def, possible_range=logged_range), logged_range
    span_h = float(np.sum(gamma ** np.arange(H)))
    return replace(est_def, possible_range=(min(lo_c, 0.0) * span_h, max(hi_c, 0.0) * span_h)), logged_range


def _clipped_readings(mr: dict[str, Any], rng: tuple[float, float]) -> dict[str, Any]:
    """The model rollouts' own intervals (``interval``, ``bootstrap.interval``) clipped to the
    possible range as FQE's is, each saying from what: metrics.json held a model bootstrap of
    [-107.5, 913.7] for costs >= 0 of range [0, 730.9] while the report printed it clipped."""
    def clip(d: dict[str, Any]) -> dict[str, Any]:
        iv = d.get("interval")
        if not (isinstance(iv, list | tuple) and len(iv) == 2 and all(np.isfinite(x) for x in iv)):
            return d
        c_lo, c_hi = max(iv[0], rng[0]), min(iv[1], rng[1])
        if (c_lo, c_hi) == tuple(iv) or c_lo > c_hi:
            return d
        return {**d, "interval": [c_lo, c_hi],
                "interval_note": f"clipped to the possible range [{rng[0]:.4g}, {rng[1]:.4g}] from "
                                 f"[{iv[0]:.4g}, {iv[1]:.4g}]"}
    out = clip(mr)
    if isinstance(out.get("bootstrap"), dict):
        out = {**out, "bootstrap": clip(out["bootstrap"])}
    return out


def clip_to_range(r: ope.OPEResult, rng: tuple[float, float]) -> ope.OPEResult:
    """An interval reaching past what the cost makes possible is clipped there (and says so),
    and so are the model rollouts' readings recorded with it."""
    if r.model_rollouts and "skipped" not in r.model_rollouts:
        r = replace(r, model_rollouts=_clipped_readings(r.model_rollouts, rng))
    lo, hi = r.interval
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return r
    c_lo, c_hi = max(lo, rng[0]), min(hi, rng[1])
    if (c_lo, c_hi) == (lo, hi) or c_lo > c_hi:
        return r
    return replace(r, interval=(c_lo, c_hi),
                   interval_method=r.interval_method + f"; clipped to the possible range [{rng[0]:.4g}, {rng[1]:.4g}]")


def stationary_onto_range(fq: ope.OPEResult, est_def: Estimand) -> ope.OPEResult:
    """The stationary FQE estimates the infinite-horizon value, within ``tail_bound`` of the
    T-step one. Past the T-step range by no more than that, the estimate is moved onto the
    range's edge (e.g. a policy that never ends an episode early reads -99.89 against a
    500-step floor of -99.34), with a warning, instead of being called impossible."""
    if not (est_def.fqe_form == "stationary" and est_def.tail_bound > 0 and est_def.possible_range
            and np.isfinite(fq.estimate)):
        return fq
    lo_r, hi_r = est_def.possible_range
    near = min(max(fq.estimate, lo_r), hi_r)
    if near == fq.estimate or abs(near - fq.estimate) > est_def.tail_bound + ope.rounding_tol(fq.estimate):
        return fq
    why = (f"the stationary estimate {fq.estimate:.4g} lies past the {est_def.horizon}-step range by less than the "
           f"truncation bound {est_def.tail_bound:.3g}: reported at the range's edge {near:.4g}")
    return replace(fq, estimate=near, warnings=[*fq.warnings, why])


def episode_ends(em: ope.EpisodeMatrix, terminated: np.ndarray) -> str:
    """How the logged episodes end within the T steps the estimators read: ``"terminal"`` (every
    one in a terminal state), ``"horizon"`` (each in a terminal state or running to step T), or
    ``"short"`` (one stops before T without a terminal state: its cost after that is unknown)."""
    ended = _ended(em, terminated)
    if ended.all():
        return "terminal"
    return "horizon" if bool(np.all(ended | em.mask[:, -1])) else "short"


def _ended(em: ope.EpisodeMatrix, terminated: np.ndarray) -> np.ndarray:
    """Per episode: does it reach a terminal state within the T steps the estimators read?"""
    keep = em.row_step < em.horizon
    return np.bincount(em.row_episode[keep], weights=np.asarray(terminated, float)[keep],
                       minlength=em.n_episodes) > 0


def short_episodes(em: ope.EpisodeMatrix, terminated: np.ndarray) -> int:
    """How many logged episodes stop before step T without a terminal state (truncated)."""
    return int(np.sum(~(_ended(em, terminated) | em.mask[:, -1])))


def past_the_logs(r: ope.OPEResult, est_def: Estimand, logged_range: tuple[float, float],
                  ends: str = "short", n_episodes: int = 1) -> ope.OPEResult:
    """A doubly robust estimate on the logging policy's own weights (:func:`ope.on_policy`) read
    as the estimand's H-step value, past the T logged steps (``ends``: :func:`episode_ends`, over ``n_episodes``).

    The two differ by the cost of steps T .. H-1, within ``[lo_t, hi_t] = [min(c_lo, 0),
    max(c_hi, 0)] sum_{T <= t < H} gamma^t`` (the logged cost range; 0 for an episode that has
    ended). ``"horizon"``: that range is added to the interval and to the paired difference
    from the logged cost, as the stationary FQE's truncation bound is. ``"terminal"``: each
    logged episode's cost after its end is 0, so its logged cost is its H-step cost; what the
    logs cannot show is a run of the policy past step T, which no episode of ``n`` made (at 95%,
    probability at most ``3 / ESS``, the rule of three over the episodes the weights keep, at
    least n/2 of them): ``3 / ESS`` of the range is added (a 95% bound added to a 95% interval:
    at least 90% together, by the union bound). ``"short"``
    (an episode stopped early without a terminal state), or an allowance wider than the
    estimate's own interval: the estimate stays a T-step one, not comparable.
    """
    T, H, gamma = est_def.horizon, est_def.value_horizon, est_def.gamma
    span_t = float(np.sum(gamma ** np.arange(T)))
    tail = float(np.sum(gamma ** np.arange(T, H)))
    c_lo, c_hi = (logged_range[0] / span_t, logged_range[1] / span_t) if span_t > 0 else (0.0, 0.0)
    lo_t, hi_t = min(c_lo, 0.0) * tail, max(c_hi, 0.0) * tail
    # the policy's own chance of a run past T, from the episodes its weights keep (ESS >= n/2 here)
    n_eff = min(float(n_episodes), float(r.ess)) if r.ess is not None and r.ess > 0 else float(n_episodes)
    if ends == "terminal":
        lo_t, hi_t = lo_t * min(1.0, 3.0 / n_eff), hi_t * min(1.0, 3.0 / n_eff)
    iv = r.interval
    if ends == "short" or hi_t - lo_t > iv[1] - iv[0]:
        return r
    what = (f"every logged episode ended in a terminal state by step {T}; a run of the policy past it, which "
            f"none of the {n_episodes} episodes (effective sample size {n_eff:.4g}) made, adds at most 3/{n_eff:.4g} "
            f"of the cost of steps {T}..{H - 1}" if ends == "terminal" else f"the cost of steps {T}..{H - 1}")
    why = (f"reads the {H}-step value from {T} logged steps: {what}, within [{lo_t:.4g}, {hi_t:.4g}] (the logged "
           f"cost range times sum_{{{T}<=t<{H}}} {gamma:g}^t{' x 3/ESS' if ends == 'terminal' else ''}), added to "
           "its interval")
    vs = None if r.vs_logged is None else (r.vs_logged[0] + lo_t, r.vs_logged[1] + hi_t)
    return replace(r, interval=(iv[0] + lo_t, iv[1] + hi_t), vs_logged=vs, warnings=[why, *r.warnings],
                   comparable=True, interval_method=r.interval_method + f"; plus the cost past the {T} logged "
                   f"steps, [{lo_t:.4g}, {hi_t:.4g}]")


#: The estimators that sum each logged episode's own costs (zero after it stops): a truncated
#: episode's missing steps count as zero cost in them.
TRAJECTORY_ESTIMATORS = ("is", "wis", "pdis", "wpdis", "dr", "wdr", "mis")


def confined(estimates: dict[str, ope.OPEResult], est_def: Estimand,
             logged_range: tuple[float, float], ends: str = "short",
             n_episodes: int = 1) -> dict[str, ope.OPEResult]:
    """The estimates confined to what the estimand allows: intervals clipped to the possible
    range (the estimand's for an estimator that reads it, the logged T steps' otherwise;
    :func:`clip_to_range`), the stationary FQE moved onto the range within its truncation
    bound (:func:`stationary_onto_range`), and every estimator that cannot see the estimand's
    horizon marked not comparable, with the reason first among its warnings -- but DR and WDR
    on the logging policy's own weights, read past the logs by :func:`past_the_logs` where
    the way the logged episodes end allows (``ends``: :func:`episode_ends`)."""
    T, H = est_def.horizon, est_def.value_horizon
    beyond = est_def.beyond_logs
    # the estimators that read the estimand's horizon past the logs: a stationary FQE, the model rollouts
    sees_past = ({"fqe"} if est_def.fqe_form == "stationary" else set()) | {"model"}
    out = {name: clip_to_range(r, est_def.possible_range if not beyond or name in sees_past else logged_range)
           for name, r in estimates.items()}
    out["fqe"] = stationary_onto_range(out["fqe"], est_def)
    for name, r in out.items():
        why = []
        if beyond and name in ("dr", "wdr") and est_def.form == "finite" and ope.on_policy(r) and r.vs_logged:
            read = past_the_logs(r, est_def, logged_range, ends, n_episodes)
            if read is not r:
                out[name] = clip_to_range(read, est_def.possible_range or logged_range)
                continue
        if beyond and name not in sees_past:
            why.append(f"estimates the {T}-step value, not the {H}-step value asked for: the logs' episodes "
                       f"end by step {T} and no estimator of them sees past it")
        if est_def.form == "infinite" and name != "fqe":
            why.append(f"estimates the {T}-step value, not the infinite-horizon value asked for: "
                       "trajectory estimators cannot see past the logged horizon")
        elif ends == "short" and name in TRAJECTORY_ESTIMATORS and not beyond:
            why.append(f"some logged episodes stop before step {T} without a terminal state (truncated): this "
                       "estimator counts their missing steps as zero cost, so it does not estimate the "
                       f"{T}-step value")
        if why:
            out[name] = replace(r, warnings=[*reversed(why), *r.warnings], comparable=False)
    return out


def as_quoted(estimates: dict[str, ope.OPEResult], est_def: Estimand, logged_range: tuple[float, float],
              ends: str = "short", n_episodes: int = 1) -> dict[str, ope.OPEResult]:
    """The estimates as the evaluation quotes them: :func:`confined`, then each comparable
    estimate outside FQE's interval *as quoted* (clipped to the possible range) flagged
    (:func:`~offline_adp.evaluation.ope.flagged_against`: flagged before the clip, a warning
    quoted [-1.653, 9.846] beside the ranking's [0, 9.846]), then the levels withdrawn on
    too few episodes (:func:`~offline_adp.evaluation.ope.with_enough_episodes`)."""
    out = ope.flagged_against(confined(estimates, est_def, logged_range, ends, n_episodes), "fqe")
    return ope.with_enough_episodes(out, n_episodes)
