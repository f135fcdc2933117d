"""Off-policy evaluation of a deterministic policy over continuous commands (from the logs).

What runs, and why the rest does not:

- **FQE over commands** (Algorithm 13 with ``Q(x, u)`` on the exact logged commands and the
  backup ``Q(x', pi(x'))``, :class:`~offline_adp.algorithms.fqe.FittedQEvaluation`), the
  quantity of :func:`~offline_adp.evaluation.offpolicy.declare_estimand`; its interval is
  the structure-conditional bootstrap over episodes (tree structure fixed, leaves
  re-averaged with each replicate's episode weights; a refit per replicate for a
  time-indexed FQE), hulled, for a finite-horizon estimand, with the **model rollouts of
  the logs over commands** (:class:`CommandDynamics`: the discrete evaluation's model of the
  logged increments with the exact command in place of the action table's entry, rolled
  out with the policy's commands, each particle's remaining steps valued at the ends of
  the logged costs' range once it leaves the data; :func:`command_model_rollouts`), then
  widened by the truncation bound. The bootstrap alone measured only the sampling noise:
  FQE read policies that leave the road in most episodes at a third to a half of their
  cost (path_tracking, docs/continuous-commands.md), and the model rollouts, whose errors
  are not FQE's, read them within a few percent.
- **Its level** (:data:`LEVEL`, 95%) is the coverage measured by the coverage suite
  (``benchmarks/ope_coverage.py``, docs/continuous-commands.md "Coverage"). It is withdrawn
  (``level: null``, ``nominal_level``, ``level_note``) as the discrete evaluation's are
  (:func:`~offline_adp.evaluation.summary.withdraw_levels`): where the commands are
  unsupported at more than 5% of the logged states (below) or the model rollouts put at
  least 10% of the policy's discounted mass past the logged states; and here also where
  the policy **replays the logs** (:func:`replayed_commands`): it commands the very command
  logged at the state at most logged states, so its value at the logged states, which
  FQE and the model rollouts read, is not its value in a new episode (a one-nearest-
  neighbour clone of the logged commands read 14.9 at the data's start states, 14.6 in
  the simulator from them, 10.2 from fresh ones).
- **Command support**: at each logged state, the distance from the policy's command to the
  nearest command logged at the ``k`` nearest logged states, per component in units of the
  command's bound range (sup over components), against the same distance of the logged
  commands themselves to their neighbours' (leave-own-row-out); the share of states beyond
  the logged commands' 95% quantile is the policy's unsupported share. (A greedy policy of
  FQI over commands picks among the commands logged at its 16 nearest states, so it always
  passes; where it drives is what the model rollouts' exit mass measures.)
- **Not usable**: IS, WIS, PDIS, WPDIS, DR, WDR and MIS weight each logged action by
  ``pi(a | x) / mu(a | x)``; a deterministic continuous policy puts probability 0 on every
  logged command it does not equal, so the weights need a smoothing kernel whose bandwidth
  trades bias for variance, and no kernel's coverage has been measured here. They are listed
  as not usable with that reason. The per-step density ratios and the PSDP bound need the
  policy's action probabilities too; both are listed the same way. A policy that samples its
  commands (stochastic) is refused: FQE over commands evaluates one command per state.

- **The model's own interval** (:func:`command_model_estimate`): the model over commands
  refitted on episodes resampled with replacement
  (:mod:`~offline_adp.evaluation.model_bootstrap`; each refit reads its rows' own commands),
  an estimator of its own (``model``), labelled as the discrete one is and withdrawn also
  where the commands are unsupported or the policy replays the logs.

The verdict rules are the discrete evaluation's (:mod:`~offline_adp.evaluation.summary`),
fed with what ran: from the logs alone a side is claimed only when the labelled interval
lies on it and the logs show support (the command support and the model rollouts' exit
mass, with at least 200 particles), and the fit converged (where the labelled model leads,
its reading of the policy does not depend on the fit's convergence, as for discrete policies).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import InvalidArgumentError
from offline_adp.evaluation import ope
from offline_adp.evaluation.estimand import clip_to_range, declare_estimand, with_possible_range
from offline_adp.evaluation.fqe_interval import (
    fqe_interval,
    fqe_replicates,
    fqe_settings,
    widen_fqe,
    with_fqe_interval,
    with_truncation_bound,
)
from offline_adp.evaluation.model_bootstrap import MODEL_REPLICATES, bootstrap_reading, model_estimate
from offline_adp.evaluation.model_rollouts import (
    LoggedDynamics,
    model_rollout_value,
    remainder_ranges,
)
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.policies import CommandPolicy, GaussianCommandPolicy
from offline_adp.progress import PhaseLines
from offline_adp.qfunctions import (
    COMMAND_SUPPORT_NEIGHBOURS,
    COMMAND_SUPPORT_QUANTILE,
    command_support_distances,
)

#: Neighbours whose logged commands count as "near" a state for the support check.
SUPPORT_NEIGHBOURS = COMMAND_SUPPORT_NEIGHBOURS
#: The logged commands' own quantile that calibrates the support radius.
SUPPORT_QUANTILE = COMMAND_SUPPORT_QUANTILE

NOT_USABLE = {
    "importance sampling (IS, WIS, PDIS, WPDIS, DR, WDR, MIS)": (
        "a deterministic continuous policy gives probability 0 to every logged command it does not equal: the "
        "importance weights need a smoothing kernel, and no kernel's bandwidth has a measured coverage here"),
    "per-step density ratios and the PSDP bound": "they read the policy's action probabilities (see above)",
}
#: The level of FQE's interval over commands, as measured by the coverage suite
#: (``benchmarks/ope_coverage.py``, docs/continuous-commands.md): withdrawn where the policy
#: left the data's support, as for the discrete estimators (:func:`~offline_adp.evaluation.summary.withdraw_levels`).
#: The model's own interval over commands (:func:`command_model_estimate`) is labelled at it too; its
#: own measurement is small: the 12 MODEL headlines labelled on the steering problems' seeds 2-4 all covered.
LEVEL = 0.95
#: The level is withdrawn when the policy commands the very command logged at the state at more
#: than this share of the logged states (:func:`replayed_commands`): a majority.
REPLAY_FRACTION = 0.5


def is_deterministic(policy: Any) -> bool:
    """Whether a continuous policy sends one command per state: a :class:`CommandPolicy`
    (its ``sample_commands`` is its ``commands``), or a :class:`GaussianCommandPolicy`
    without noise or random commands. Anything that samples its commands is not."""
    if isinstance(policy, GaussianCommandPolicy):
        return not policy.std.any() and policy.epsilon == 0.0
    sample = getattr(type(policy), "sample_commands", None)
    return sample is None or sample is CommandPolicy.sample_commands


class CommandDynamics(LoggedDynamics):
    """:class:`~offline_adp.evaluation.model_rollouts.LoggedDynamics` over the exact
    commands: the increment, cost and termination models take each row's command (in units
    of its logged standard deviation) where the discrete model takes the action table's
    value and one-hot; the support radii, noise and rollout are that model's own."""

    def fit(self, ds: TransitionDataset, arrays: Any = None) -> CommandDynamics:
        a = arrays if arrays is not None else ds.arrays()
        u = np.asarray(ds.commands(), np.float64).reshape(len(a.cost), -1)
        sd = u.std(axis=0)
        self.command_sd_ = np.where(sd > 0, sd, 1.0)
        self.commands_ = u  # the rows' commands: the parent (and the bootstrap's refits) fit on row indices
        return super().fit(ds, row_actions(a))

    def _features(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        act = np.asarray(action)
        u = self.commands_[act] if act.ndim == 1 else act.astype(np.float64)  # fit: row indices; step: commands
        return np.column_stack([obs / self.sd_, u / self.command_sd_])


def row_actions(a: Any) -> Any:
    """``a`` with each row's action its own row index: how :class:`CommandDynamics` fits
    (its features look the row's command up)."""
    return replace(a, action=np.arange(len(a.cost)))


class _CommandActor:
    """A continuous policy as :func:`model_rollout_value` reads a policy: its commands."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    def act_index(self, obs: np.ndarray, t: Any = 0, rng: Any = None) -> np.ndarray:
        return np.asarray(self.policy.commands(obs, t), np.float64).reshape(len(obs), -1)


def command_model_rollouts(ds: TransitionDataset, policy: Any, horizon: int, gamma: float, *, n: int,
                           level: float, seed: int, replicates: int = MODEL_REPLICATES,
                           say: Any = None) -> dict[str, Any]:
    """Model rollouts of the logs over commands (:class:`CommandDynamics`): the discrete
    evaluation's second reading and support measure
    (:func:`~offline_adp.evaluation.model_rollouts.model_rollouts`), the policy's commands
    stepping the model, with the model's own interval (``bootstrap``: ``replicates`` refits on
    episodes resampled with replacement, :func:`~offline_adp.evaluation.model_bootstrap.bootstrap_reading`).
    ``{"skipped": reason}`` where it does not apply."""
    if not n:
        return {"skipped": "model_particles=0: model rollouts turned off"}
    a = ds.arrays()
    if not (a.step == 0).any():
        return {"skipped": "no episode is logged from step 0: no start states to roll out from"}
    model = CommandDynamics(random_state=seed).fit(ds, a)
    if model.radius_ <= 0:
        return {"skipped": "the logged states repeat exactly (a lattice): a model's next states are never on it"}
    actor = _CommandActor(policy)
    steps = None if say is None else PhaseLines(say, "model rollouts over commands: step", horizon)
    out = model_rollout_value(model, actor, horizon, gamma, remainder_ranges(a.cost, a.terminated, gamma, horizon),
                              n=n, level=level, seed=seed, on_step=steps)
    if say is not None and replicates >= 2:  # the refits are most of the time (a long silence otherwise)
        say(f"model rollouts over commands: {replicates} bootstrap refits of the model")
    out["bootstrap"] = bootstrap_reading(model, row_actions(a), actor, horizon, gamma, out["estimate"], n=n,
                                         level=level, seed=seed, replicates=replicates)
    return {**out, "noise": model.noise_source_,
            "method": f"{n} rollouts of a model fitted on the logs over the exact commands (increments: ridge + "
                      "extra-trees on its residuals + out-of-fold residual noise; cost and termination: extra-trees "
                      "on state, command, next state), each particle's remaining steps valued at the ends of the "
                      "logged costs' range once it is farther from the logged states than they are from each other"}


def command_support(ds: TransitionDataset, policy: Any, k: int = SUPPORT_NEIGHBOURS) -> dict[str, Any]:
    """The share of logged states where ``policy`` commands farther from the commands
    logged nearby than the logged commands themselves are (see the module docstring;
    :func:`~offline_adp.qfunctions.command_support_distances`)."""
    a, u = ds.arrays(), ds.commands()
    assert u is not None
    d_pi, radius = command_support_distances(a.obs, u, ds.info.action_table.bounds(), a.obs,
                                             np.asarray(policy.commands(a.obs, a.step), np.float64), k)
    return {"fraction": float(np.mean(d_pi > radius)), "radius": radius, "neighbours": k,
            "method": f"the policy's command against the commands logged at the {k} nearest logged states (sup over "
                      "components, in units of each bound range); unsupported beyond the logged commands' own "
                      f"{SUPPORT_QUANTILE:.0%} quantile ({radius:.3g})"}


def replayed_commands(ds: TransitionDataset, policy: Any) -> dict[str, Any]:
    """The share of logged states where ``policy`` commands exactly the command logged at
    that state, over the rows whose command no other row shares (a continuous draw: no
    policy meets it except by reading that row; commands repeated in the logs, e.g. clipped
    at a bound, are left out). A policy that does this at most states replays the logs (a
    one-nearest-neighbour clone of them, or a regression that interpolates its training
    rows): at the logged states, which is where FQE and the model rollouts read it, it does
    what the logged episode did, and in a new episode it does not. ``fraction`` is None
    when no logged command is unique."""
    a, u = ds.arrays(), ds.commands()
    assert u is not None
    lo, hi = ds.info.action_table.bounds()
    span = np.where(np.isfinite(hi - lo) & (hi > lo), hi - lo, np.ptp(u, axis=0))
    span = np.where(span > 0, span, 1.0)
    _, inverse, counts = np.unique(u, axis=0, return_inverse=True, return_counts=True)
    unique = counts[inverse.reshape(-1)] == 1
    pi = np.asarray(policy.commands(a.obs[unique], a.step[unique]), np.float64).reshape(int(unique.sum()), -1)
    same = (np.abs(pi - u[unique]) / span).max(axis=1) <= 1e-9 if unique.any() else np.zeros(0, bool)
    return {"fraction": float(same.mean()) if len(same) else None, "rows_checked": int(unique.sum()),
            "method": "the policy's command at each logged state equal to the command logged there (to 1e-9 of the "
                      "bound range), over the rows whose command no other row shares"}


def fqe_over_commands(ds: TransitionDataset, policy: Any, cfg: EvaluationSettings, est_def: Any,
                      say: Callable[[str], None]) -> ope.OPEResult:
    """FQE's estimate and its interval at :data:`LEVEL`: the bootstrap over episodes, hulled
    with the model rollouts over commands for a finite-horizon estimand, widened by the
    truncation bound (module docstring)."""
    a = ds.arrays()
    fqe_T = est_def.fqe_horizon
    params = fqe_settings(cfg.fqe_params, fqe_T, counted=True)  # the discrete path's merge (a count of iterations)
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
    res = fqe_interval(est, reps, em.n_episodes, LEVEL if LEVEL is not None else 0.95)
    res = replace(res, interval_method=res.interval_method + (
        " (structure-conditional: tree structure fixed, leaves re-averaged)" if conditional else ""))
    if LEVEL is None:
        res = replace(res, level=None, warnings=[*res.warnings, "continuous commands: this interval's coverage has not "
                                                 "been measured, so it carries no level (it is not a 95% interval)"])
    elif est_def.form != "finite" and res.level is not None:  # LEVEL was measured on finite estimands only: 3 of 3
        # LQ seeds missed the truth here (no interval at all, e.g. --fqe-bootstrap 0: nothing to withdraw)
        why = ("the infinite-horizon value over commands: this interval's coverage has not been measured (the level "
               "was measured on finite estimands; an audit's 3 linear-quadratic logs missed the truth), so it is "
               f"not a {res.level:.0%} interval")
        res = replace(res, level=None, level_note=why, warnings=[*res.warnings, f"no level: {why}"])
    # as the discrete FQE: hulled with the model rollouts where they read the same quantity
    if est_def.form == "finite":
        if cfg.model_particles:
            say("model rollouts over commands")
        mr = command_model_rollouts(ds, policy, est_def.value_horizon, est_def.gamma, n=cfg.model_particles,
                                    level=0.95, seed=cfg.seed, say=say)
        hull = not est_def.beyond_logs or est_def.fqe_form == "stationary"
        res = widen_fqe(res, with_fqe_interval(mr, res, est_def.tail_bound, res.interval) if hull else mr, hull=hull)
    return with_truncation_bound(res, est_def.tail_bound)


def command_model_estimate(mr: dict[str, Any] | None, support: dict[str, Any],
                           replay: dict[str, Any]) -> ope.OPEResult | None:
    """The model rollouts over commands as an estimator (``"model"``,
    :func:`~offline_adp.evaluation.model_bootstrap.model_estimate`), its level withdrawn also
    where the policy's commands are unsupported at more than
    :data:`~offline_adp.evaluation.verdict.SUPPORT_FRACTION` of the logged states (FQE's
    interval over commands has no support bounds to check the model's extrapolation in the
    command against, as the discrete label has) or where the policy replays the logs."""
    from offline_adp.evaluation.verdict import SUPPORT_FRACTION

    model = model_estimate(mr, LEVEL)
    if model is None:
        return None
    why = []
    if support["fraction"] > SUPPORT_FRACTION:
        why.append(f"the policy's commands are unsupported at {support['fraction']:.0%} of the logged states, where "
                   "the model extrapolates in the command and FQE's interval over commands cannot check it")
    if replay["fraction"] is not None and replay["fraction"] > REPLAY_FRACTION:
        why.append(f"the policy replays the logged commands at {replay['fraction']:.0%} of the logged states: its "
                   "value from the logged start states is not its value in a new episode")
    if not why:
        return model
    note = "; ".join([model.level_note, *why] if model.level is None and model.level_note else why)
    return replace(model, level=None, level_note=note, warnings=[*model.warnings, *(f"no level: {w}" for w in why)])


def continuous_offpolicy(ds: TransitionDataset, policy: Any, cfg: EvaluationSettings, *, target_horizon: int | None,
                         start: str | None, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The off-policy part of ``metrics.json`` for a continuous policy (module docstring)."""
    say = progress or (lambda _m: None)
    if not is_deterministic(policy):
        raise InvalidArgumentError(
            f"{type(policy).__name__} samples its commands (a stochastic policy): FQE over commands evaluates one "
            "command per state, pi(x), so its value would be that of another policy; evaluate a deterministic command "
            "policy (policy.commands(obs, t))")
    est_def = declare_estimand(ds, policy, cfg.horizon, cfg.estimand, target_horizon=target_horizon, start=start)
    a = ds.arrays()
    em = ope.EpisodeMatrix.build(a.episode, a.step, est_def.horizon)
    est_def, _ = with_possible_range(est_def, a, em)  # recorded, and FQE's and the model's intervals clipped to it
    fq = clip_to_range(fqe_over_commands(ds, policy, cfg, est_def, say), est_def.possible_range)
    fq = ope.with_enough_episodes({"fqe": fq}, ds.n_episodes)["fqe"]
    say("command support")
    support = command_support(ds, policy)
    replay = replayed_commands(ds, policy)
    fq_d = fq.as_dict()
    if replay["fraction"] is not None and replay["fraction"] > REPLAY_FRACTION and fq_d.get("level") is not None:
        fq_d.update(nominal_level=fq_d["level"], level=None, withdrawn_by="replay", level_note=(
            f"the policy commands the very command logged at the state at {replay['fraction']:.0%} of the "
            "logged states: "
            "it replays the logs, so its value at the logged states, which FQE and the model rollouts read, is not its "
            f"value in a new episode; this is not a {fq_d['level']:.0%} interval"))
    model = command_model_estimate(fq.model_rollouts, support, replay)
    if model is not None:
        model = ope.with_enough_episodes({"model": model}, em.n_episodes)["model"]
        # the allowances can reach past what the costs make possible: clipped there
        model = clip_to_range(model, est_def.possible_range)
    from offline_adp.evaluation.offpolicy import behaviour_value

    warnings = [f"not computed for continuous commands: {k}: {why}" for k, why in NOT_USABLE.items()]
    return {
        "estimand": est_def.as_dict(),
        "horizon": est_def.horizon,
        "gamma": est_def.gamma,
        "commands": {"dims": list(ds.info.action_table.dims), "units": list(ds.info.action_table.units),
                     "low": None if ds.info.action_table.low is None else list(ds.info.action_table.low),
                     "high": None if ds.info.action_table.high is None else list(ds.info.action_table.high)},
        "behaviour_value": behaviour_value(em, a.cost, est_def.gamma, terminated=a.terminated, est_def=est_def),
        "behaviour": {"source": "logged commands", "support_violations": support, "replayed_commands": replay,
                      "warnings": []},
        "ope": {"fqe": {**fq_d, "method": "fqe"},
                **({"model": {**model.as_dict(), "method": "model"}} if model is not None else {})},
        "not_usable": dict(NOT_USABLE),
        "shift": {},
        "warnings": warnings,
    }
