"""``offline-adp evaluate RUN_DIR``: every number about a fitted policy, into ``RUN_DIR/evaluation/``.

Writes (atomically: a temporary directory, then rename)::

    evaluation/metrics.json     every number with the method that produced it
    evaluation/per_step.csv     shift diagnostics per step and method
    evaluation/ratios.parquet   the data's states with their step, source and ratio w_t(x)
    evaluation/rollout_states.npz  pi's states per step (when a simulator was used)
    evaluation/rollout_states_demonstrator.npz  the same for the problem's demonstrator

A simulator is used when ``--simulator NAME`` is given or the dataset names its reference problem (``info.problem``);
``--simulator none`` forces logs only. A run fitted with ``--holdout``: its held-out episodes (evaluation/logs.py).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from offline_adp.data.dataset import TransitionDataset, read_dataset
from offline_adp.data.files import read_json_file
from offline_adp.data.rundir import RunDirectory
from offline_adp.data.validate import require_usable
from offline_adp.errors import DatasetNotFoundError, RunDirectoryError
from offline_adp.evaluation.logs import evaluated_logs
from offline_adp.evaluation.metrics_file import frame_records as _frame_records
from offline_adp.evaluation.offpolicy import OffPolicyResult, off_policy
from offline_adp.evaluation.run_checks import _check_recorded_data, _check_same_actions, _fitted_info
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.evaluation.verdict import start_states_check
from offline_adp.parallel import TaskMap
from offline_adp.rollout import RolloutResult, rollout_pieces


def _rollout_block(res: RolloutResult, problem: Any) -> dict[str, Any]:
    lo, hi = res.interval()
    out = {"mean_discounted_cost": res.mean, "interval": [lo, hi], "level": 0.95, "n_episodes": int(len(res.length)),
           "mean_length": float(res.length.mean()), "terminated": int(res.terminated.sum())}
    out.update(problem.rollout_summary(res.states or [], res.terminated))
    return out


def _per_source(ds: TransitionDataset, w: np.ndarray, gamma: float) -> dict[str, Any]:
    a = ds.arrays()
    src = np.asarray(ds.table.column("source").to_numpy(zero_copy_only=False)).astype(str)
    disc_cost = a.cost * gamma ** a.step.astype(np.float64)
    out = {}
    for s in sorted(set(src)):
        m = src == s
        eps = np.unique(a.episode[m])
        per_ep = np.bincount(a.episode[m], weights=disc_cost[m], minlength=int(a.episode.max()) + 1)[eps]
        out[s] = {"episodes": int(len(eps)), "transitions": int(m.sum()),
                  "logged_mean_discounted_cost": float(per_ep.mean()),
                  "mean_ratio": float(w[m].mean()), "policy_mass": float(w[m].sum() / max(w.sum(), 1e-300)),
                  "data_mass": float(m.mean())}
    return out


def json_safe(obj: Any) -> Any:
    """Standard JSON: NaN and infinities become null (an undefined estimate, e.g. WIS with no weight)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _simulator_note(asked: str | None, dataset_problem: str | None, known: list[str]) -> str | None:
    """Why no simulator was used, and how to name one (None when one was)."""
    if asked is not None and asked not in ("none", ""):
        return None
    if asked in ("none", ""):
        return ("no simulator used (--simulator none): every number comes from the logs alone; name one with "
                f"--simulator NAME ({', '.join(known)}) to add rollout truth and classifier shift diagnostics")
    if not dataset_problem:
        return ("no simulator used: the dataset names no reference problem (meta/info.json has no 'problem'); "
                f"every number comes from the logs alone. If a simulator exists, pass --simulator NAME "
                f"({', '.join(known)})")
    return None


def evaluate_run(
    run_dir: str | PathLike[str],
    settings: EvaluationSettings | None = None,
    *,
    dataset: str | PathLike[str] | None = None,
    progress: Callable[[str], None] | None = None,
    task_map: TaskMap | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Evaluate the policy of a run directory (see the module docstring); returns the metrics.

    ``settings``: the evaluation's settings (:class:`~offline_adp.evaluation.settings.EvaluationSettings`:
    ``simulator``, ``episodes``, ``bootstrap``, ``fqe_bootstrap``, ``fqe_params``,
    ``horizon``, ``estimand``, ``seed``, ``model_particles``), or the same as keywords in
    ``options`` (also by the former names ``n_episodes``, ``n_boot``, ``n_boot_fqe``);
    checked before anything is read.

    ``task_map`` runs the rollout pieces and the FQE bootstrap replicates (default: here;
    :class:`offline_adp.engines.dask.DaskTaskMap` spreads them over Dask workers with the
    same result).

    The settings: ``horizon`` caps the evaluation horizon T (default: the data's longest episode,
    capped by the dataset's horizon). With a gymnasium simulator (``gym:ENV_ID``) T is the
    environment's own horizon instead (its registered ``max_episode_steps`` unless
    ``horizon`` is given), the rollouts start from ``env.reset()`` and the estimand says so;
    estimators that see only the shorter logged horizon are marked ``comparable=False``. ``estimand`` is ``"finite"``
    (the T-step value the rollouts measure) or ``"infinite"`` (FQE only; see
    :func:`offline_adp.evaluation.offpolicy.declare_estimand`). ``fqe_bootstrap`` None: the
    default replicate count (:func:`offline_adp.evaluation.offpolicy.fqe_replicates`).
    ``model_particles``: particles of the model rollouts of the logs (0: none; see
    :mod:`offline_adp.evaluation.model_rollouts`).
    """
    cfg = EvaluationSettings.resolve(settings, options)  # before any work
    say = progress or (lambda _m: None)
    run = Path(run_dir)
    info, ds_path = _run_and_dataset(run, dataset)
    # the one writer of RUN/evaluation at a time: a second evaluate (or a fit of the same run)
    # gets LockedError at once (exit 2), instead of silently replacing the other's results
    with RunDirectory(run).lock():
        t0 = time.perf_counter()
        ds = read_dataset(ds_path)
        # empty or failing the doctor (actions outside the table, negative steps...): one error
        # naming the part file and row, not an IndexError deep in an estimator or wrong numbers
        require_usable(ds, ds_path, use="evaluate on")
        policy = _run_policy(run, info, ds, ds_path)  # its actions and features first: the sharper message
        if dataset is None:  # the path run.json names: the data it was fitted on, or say so
            _check_recorded_data(run, info, ds, ds_path)
        ds, logs = evaluated_logs(run, info, ds, ds_path, dataset is not None)  # held-out episodes, or all
        sim_name, problem, note = _simulator(cfg.simulator, ds)
        metrics, res, states, demo_states = evaluation_metrics(
            ds, policy, problem, cfg, sim_name=sim_name, ds_path=ds_path, algorithm=info.get("algorithm"), note=note,
            progress=say, task_map=task_map, run_dir=run, logs=logs)
        # no timings in metrics.json: it is deterministic
        say(f"writing evaluation/ ({time.perf_counter() - t0:.1f} s)")
        _write(run, metrics, res, ds, states, demo_states)
        return metrics


def _run_and_dataset(run: Path, dataset: str | PathLike[str] | None) -> tuple[dict[str, Any], Path]:
    """The run's ``run.json`` (empty when absent) and its dataset's path (``dataset``, else
    the one the run names); an error when ``run`` is not a run directory or the path no dataset."""
    if not (run / "model").is_dir():
        from offline_adp.data.rundir import pipeline_hint

        raise RunDirectoryError(f"{run}: not a run directory (no model/)"
                                + (pipeline_hint(run) or "; fit one with `offline-adp fit`"))
    info = read_json_file(run / "run.json") if (run / "run.json").exists() else {}
    if dataset is None:
        from offline_adp.data.rundir import recorded_dataset

        dataset = recorded_dataset(run / "run.json", info) if info else None
        if dataset is None:
            raise DatasetNotFoundError(f"{run}: names no dataset (no 'dataset' in its run.json); pass --dataset DIR")
    ds_path = Path(dataset)
    if not (ds_path / "meta" / "info.json").exists():
        raise DatasetNotFoundError(f"{run}: its dataset {str(ds_path)!r} is not a dataset directory; pass "
                                   "--dataset DIR")
    return info, ds_path


def _run_policy(run: Path, info: dict[str, Any], ds: TransitionDataset, ds_path: Path) -> Any:
    """The run's policy, checked against the dataset's actions and features (a continuous one
    with its signature: the data it was fitted on, else these logs)."""
    from offline_adp.artifacts import load_index_policy

    policy = load_index_policy(run / "model")
    if getattr(policy, "continuous", False):  # its bounds: the data it was fitted on (else these logs)
        from offline_adp.policies import attach_signature

        attach_signature(policy, _fitted_info(info) or ds)
    _check_same_actions(run, info, policy, ds, ds_path)
    return policy


def _simulator(simulator: str | None, ds: TransitionDataset) -> tuple[str | None, Any, str | None]:
    """``(name, problem, note)``: the simulator asked for (else the dataset's reference
    problem; ``"none"``: none), the problem or gymnasium model, and what the metrics say about it."""
    from offline_adp.envs import PROBLEM_NAMES, recorded_problem_options
    from offline_adp.envs.gym import resolve_simulator

    sim_name = simulator if simulator is not None else ds.info.problem
    if sim_name in ("none", ""):
        sim_name = None
    problem = resolve_simulator(sim_name, ds.info)  # a reference problem or gym:ENV_ID
    note = _simulator_note(simulator, ds.info.problem, [*PROBLEM_NAMES, "gym:ENV_ID"])
    if problem is not None and sim_name == ds.info.problem and recorded_problem_options(ds.info) is None:
        note = ((note + "; ") if note else "") + (
            f"the dataset does not record the options its {sim_name!r} problem was made with "
            "(meta/info.json provenance.problem_options): the rollouts use the default problem")
    return sim_name, problem, note


def evaluation_metrics(
    ds: TransitionDataset,
    policy: Any,
    problem: Any,
    settings: EvaluationSettings | None = None,
    *,
    sim_name: str | None = None,
    ds_path: str | PathLike[str] | None = None,
    algorithm: str | None = None,
    note: str | None = None,
    progress: Callable[[str], None] | None = None,
    task_map: TaskMap | None = None,
    run_dir: str | PathLike[str] | None = None,
    logs: dict[str, Any] | None = None,
    **options: Any,
) -> tuple[dict[str, Any], OffPolicyResult, list[np.ndarray] | None, list[np.ndarray] | None]:
    """The metrics of :func:`evaluate_run` for ``policy`` on ``ds`` without a run directory:
    ``(metrics, off-policy result, pi's rollout states, the demonstrator's)``. ``problem``
    None: logs only (the settings' ``simulator`` is not read: ``problem`` and ``sim_name``
    say it). ``settings`` or ``options`` as for :func:`evaluate_run`, checked before the
    rollouts and fits. ``run_dir`` is read for the fit's convergence in the headline (None:
    unknown). ``logs``: which logs ``ds`` is (:func:`~offline_adp.evaluation.logs.evaluated_logs`).
    Used by ``evaluate_run`` and by the off-policy coverage benchmark."""
    cfg = EvaluationSettings.resolve(settings, options)
    say = progress or (lambda _m: None)
    metrics = _metrics_head(ds, cfg, ds_path, algorithm, sim_name, note) | ({"logs": logs} if logs else {})
    ope_horizon, target, start = _gym_estimand(problem, ds, cfg.horizon, sim_name)
    pol = demo = None
    refs: dict[str, Any] = {}
    if problem is not None:
        pol, demo, refs = _rollouts(metrics, ds, policy, problem, cfg, sim_name, target, task_map, say)
    states, demo_states = (None, None) if pol is None else (pol.states, demo.states if demo is not None else None)
    ope_cfg = cfg.model_copy(update={"horizon": ope_horizon})
    res = _estimates(metrics, ds, policy, ope_cfg, refs, states, target, start, task_map, say)
    if problem is not None and res is not None:  # the rollouts' per-episode costs: the measured distributions
        _rollout_distributions(metrics, pol, demo, sim_name)
    if "rollout" in metrics:
        _rollout_errors(metrics, cfg.estimand)
    _discount(metrics, ds, run_dir)
    _levels_warnings_headline(metrics, run_dir)
    return metrics, res, states, demo_states


def _metrics_head(ds: TransitionDataset, cfg: EvaluationSettings, ds_path: str | PathLike[str] | None,
                  algorithm: str | None, sim_name: str | None, note: str | None) -> dict[str, Any]:
    """The metrics' first keys: the dataset, algorithm, simulator, seed, settings, and the note on the simulator."""
    metrics: dict[str, Any] = {"dataset": {"path": None if ds_path is None else str(ds_path),
                                           "fingerprint": ds.fingerprint(),
                                           "transitions": len(ds), "episodes": len(ds.episode_ids),
                                           "sources": ds.source_counts()},
                               "algorithm": algorithm, "simulator": sim_name, "seed": cfg.seed, "warnings": [],
                               "settings": cfg.model_dump()}  # what compare reuses an evaluation by
    if note:
        metrics["simulator_note"] = note
        metrics["warnings"].append(note)
    return metrics


def _gym_estimand(problem: Any, ds: TransitionDataset, horizon: int | None,
                  sim_name: str | None) -> tuple[int | None, int | None, str | None]:
    """``(off-policy horizon, target horizon, start)``: a gymnasium environment's own horizon and
    start distribution, else ``(horizon, None, None)``."""
    from offline_adp.envs.gym import GymResetModel

    if not isinstance(problem, GymResetModel):
        return horizon, None, None
    # the environment's own horizon: its registered time limit unless --horizon says otherwise;
    # rollouts start from env.reset(), and the off-policy estimators target the same value
    from offline_adp.evaluation.offpolicy import evaluation_horizon

    logged = evaluation_horizon(ds)[0]
    target = int(horizon) if horizon is not None else (problem.horizon or logged)
    # past the logs the off-policy estimators read the logged steps (the estimand says so): no "asked for" warning
    return (target if target < logged else None), target, f"env.reset() of {sim_name}"


def _rollouts(metrics: dict[str, Any], ds: TransitionDataset, policy: Any, problem: Any, cfg: EvaluationSettings,
              sim_name: str | None, target: int | None, task_map: TaskMap | None,
              say: Callable[[str], None]) -> tuple[RolloutResult, RolloutResult | None, dict[str, Any]]:
    """Roll the policy (and the problem's demonstrator, if any) out in the simulator; fills
    ``metrics["rollout"]`` (and ``"named"``) and returns ``(pi's rollouts, the demonstrator's, reference policies)``."""
    from offline_adp.evaluation.offpolicy import evaluation_horizon

    rng = np.random.default_rng(cfg.seed)
    T, gamma, _ = evaluation_horizon(ds, cfg.horizon)
    if target is not None:
        T = target
    say(f"rollouts in {sim_name} ({cfg.episodes} episodes x {T} steps)")
    x0 = problem.initial_states(cfg.episodes, rng)
    demonstrator = problem.demonstrator()  # None for a gymnasium environment
    pols = {"policy": policy} if demonstrator is None else {"policy": policy, "demonstrator": demonstrator}
    from offline_adp.progress import PhaseLines

    ro = rollout_pieces(problem, pols, x0, cfg.seed + 1, horizon=T, gamma=gamma, record_states=True, task_map=task_map,
                        on_done=PhaseLines(say, "rollouts", min(8, cfg.episodes)))
    pol, demo = ro["policy"], ro.get("demonstrator")
    metrics["rollout"] = {"method": f"Monte-Carlo in the {sim_name} simulator, same start states and seeds for both",
                          "horizon": T, "policy": _rollout_block(pol, problem)}
    a = ds.arrays()
    if pol.states and len(pol.states[0]) and (a.step == 0).any():  # the rollouts' starts against the logs'
        metrics["rollout"]["start_states"] = start_states_check(a.obs[a.step == 0], pol.states[0])
    refs = {}
    if demo is None:
        metrics["rollout"]["note"] = f"the {sim_name} simulator has no demonstrator: comparison skipped"
    else:
        metrics["rollout"]["demonstrator"] = _rollout_block(demo, problem)
        refs["demonstrator"] = demonstrator
    named = problem.named_scores(policy) if hasattr(problem, "named_scores") else {}  # ReferenceProblem hook
    if named:
        metrics["named"] = named
    return pol, demo, refs


def _estimates(metrics: dict[str, Any], ds: TransitionDataset, policy: Any, cfg: EvaluationSettings,
               refs: dict[str, Any], states: list[np.ndarray] | None, target: int | None, start: str | None,
               task_map: TaskMap | None, say: Callable[[str], None]) -> OffPolicyResult | None:
    """The off-policy estimates into ``metrics``: :func:`off_policy`, or FQE over commands for a
    continuous policy (returns None then; what cannot run is listed, evaluation/continuous.py)."""
    if getattr(policy, "continuous", False):
        from offline_adp.evaluation.continuous import continuous_offpolicy

        block = continuous_offpolicy(ds, policy, cfg, target_horizon=target, start=start, progress=say)
        metrics["warnings"].extend(block.pop("warnings"))
        metrics.update(block)
        return None
    res = off_policy(ds, policy, cfg, reference_policies=refs, policy_states=states, progress=say, task_map=task_map,
                     target_horizon=target, start=start)
    metrics.update(_offpolicy_block(res, ds))
    return res


def _rollout_distributions(metrics: dict[str, Any], pol: RolloutResult, demo: RolloutResult | None,
                           sim_name: str | None) -> None:
    """The rollouts' per-episode discounted costs as measured distributions in ``metrics["cost_distribution"]``."""
    from offline_adp.evaluation.risk import distribution_summary

    cd = metrics["cost_distribution"]
    how = f"per-episode discounted costs of the {sim_name} rollouts"
    cd["policy_rollouts"] = distribution_summary(pol.discounted_cost, alpha=cd["alpha"], source="simulator", method=how)
    if demo is not None:
        cd["demonstrator_rollouts"] = distribution_summary(demo.discounted_cost, alpha=cd["alpha"],
                                                           source="simulator", method=how)


def _rollout_errors(metrics: dict[str, Any], estimand: str) -> None:
    """What the rollouts measure, and each estimate's error against them."""
    T = metrics["rollout"]["horizon"]
    truth = metrics["rollout"]["policy"]["mean_discounted_cost"]
    metrics["rollout"]["estimand"] = metrics["estimand"]["quantity"] if estimand == "finite" else \
        f"the {T}-step value (rollouts cannot measure the infinite-horizon one)"
    if (metrics["rollout"].get("start_states") or {}).get("differ"):  # another estimand: no error to read
        return metrics["rollout"].update(estimand="the value from the simulator's start states, not the logs'")
    for r in metrics["ope"].values():
        r["rollout_error"] = r["estimate"] - truth


def _levels_warnings_headline(metrics: dict[str, Any], run_dir: str | PathLike[str] | None) -> None:
    """The last stage: levels withdrawn where the policy left the data's support, the warnings
    gathered into one list, and the headline."""
    from offline_adp.evaluation.summary import (
        gather_warnings,
        headline,
        left_support,
        shift_verdict,
        withdraw_levels,
    )

    # an interval's level is the level it has: none where the policy left the data's support
    fm = json_safe(metrics)
    for k, r in withdraw_levels(fm, left_support(fm, shift_verdict(fm)))["ope"].items():
        if "level_note" in r and "level_note" not in metrics["ope"][k]:
            metrics["ope"][k].update(level=None, nominal_level=r["nominal_level"], level_note=r["level_note"],
                                     withdrawn_by=r["withdrawn_by"])
            if "nominal_vs_logged" in r:  # the paired difference goes with the level
                metrics["ope"][k]["nominal_vs_logged"] = metrics["ope"][k].pop("vs_logged")
    metrics["warnings"] = gather_warnings(metrics)  # one list, each with its source (also kept where it arose)
    metrics["headline"] = headline(json_safe(metrics), run_dir)


def fit_discount(run_dir: str | PathLike[str] | None) -> float | None:
    """The discount the run's policy was fitted with: ``model/q.json``'s resolved ``gamma``,
    else ``model/params.json``'s when set; None when neither says (or no run directory)."""
    if run_dir is None:
        return None
    for name in ("q.json", "params.json"):
        p = Path(run_dir) / "model" / name
        if not p.is_file():
            continue
        try:
            g = read_json_file(p).get("gamma")
        except Exception:  # noqa: BLE001 - a model file the loader rejects says nothing about the discount here
            continue
        if isinstance(g, int | float) and not isinstance(g, bool) and 0 < g <= 1:
            return float(g)
    return None


def _discount(metrics: dict[str, Any], ds: TransitionDataset, run_dir: str | PathLike[str] | None) -> None:
    """``metrics["discount"]``: the estimand's discount against the fit's, and a warning when they differ."""
    from offline_adp.data.discount import resolve_discount

    ev = (metrics.get("estimand") or {}).get("gamma", metrics.get("gamma"))
    fit = fit_discount(run_dir)
    src = {"dataset": "the dataset's", "default": "the package default", "explicit": "explicit"}.get(
        resolve_discount(ds.info).gamma_source, "the dataset's")
    metrics["discount"] = {"evaluation": ev, "evaluation_source": src, "fit": fit}
    if fit is not None and ev is not None and abs(fit - float(ev)) > 1e-12:
        metrics["warnings"].append(f"the policy was fitted with gamma {fit:g}, the evaluation uses gamma {float(ev):g} "
                                   f"({src}): its values are judged by another objective than the one it optimised")


def _offpolicy_block(res: OffPolicyResult, ds: TransitionDataset) -> dict[str, Any]:
    beh = res.behaviour
    shift_block = {"recursion": {"method": "ratio recursion fitted with extra-trees (logs only)",
                                 "per_step": _frame_records(res.diagnostics), **res.ratios.notes()}}
    for name, (r, d) in res.extra_ratios.items():
        label = "classifier" if name == "classifier" else f"reference:{name}"
        method = ("probabilistic classifier between pi's simulated states and the data's, cross-fitted"
                  if name == "classifier" else f"ratio recursion for the reference policy {name!r}")
        shift_block[label] = {"method": method, "per_step": _frame_records(d), **r.notes()}
    worst = res.diagnostics.iloc[1:] if len(res.diagnostics) > 1 else res.diagnostics
    from offline_adp.evaluation.shift import MIN_STATES_PER_STEP

    thin = len(res.per_step_counts) > 1 and int(res.per_step_counts[1:].min()) < MIN_STATES_PER_STEP
    extra: dict[str, Any] = {"per_step_counts": [int(c) for c in res.per_step_counts],
                             "min_states_per_step": MIN_STATES_PER_STEP, "behaviour_value": res.behaviour_value}
    if res.pooled is not None:
        extra["pooled_shift"] = {**res.pooled[1],
                                 "method": "ratio recursion pooled over time (stationary approximation)",
                                 **res.pooled[0].notes()}
    return {
        "estimand": res.estimand.as_dict(),
        **extra,
        "horizon": res.horizon,
        "gamma": res.gamma,
        "behaviour": {"source": beh.source, "clip": beh.clip, "n_clipped": beh.n_clipped, "classifier": beh.classifier,
                      "support_violations": res.support, "warnings": beh.warnings},
        "ope": {k: {**v.as_dict(), "method": k} for k, v in res.estimates.items()},
        "shift": shift_block,
        "worst_step": {"step": int(worst.loc[worst["ess_fraction"].idxmin(), "step"]), "method": "recursion",
                       "ess_fraction": float(worst["ess_fraction"].min())},  # the headline's: summary.shift_verdict
        "psdp_bound": {"eps": res.eps.tolist(), "label": "plug-in estimate (Bagnell et al. 2003, Theorem 2)",
                       "eps_method": res.eps_note
                       or (f"cross-fitted over {res.eps_folds} folds of episodes: FQE fitted on the other folds, "
                                      "the policy's advantage deficit measured on the held-out fold's states")
                       if res.eps_folds else "in sample (FQE fitted on all the data; 0 for a policy greedy in it)",
                       "eps_in_sample": None if res.eps_in_sample is None else res.eps_in_sample.tolist(),
                       "references": res.bounds},
        "per_source": _per_source(ds, res.extra_ratios["classifier"][0].w if "classifier" in res.extra_ratios
                                  else res.pooled[0].w if thin and res.pooled is not None else res.ratios.w, res.gamma),
        "cost_distribution": {"definition": "CVaR_alpha: the mean of the worst (highest-cost) alpha fraction of "
                                            "episode costs, each episode's cost its sum_{t<T} gamma^t c_t",
                              **(res.cost_distribution or {})},
        "per_source_ratio_method": "classifier" if "classifier" in res.extra_ratios else
        "pooled" if thin and res.pooled is not None else "recursion",
    }


def _write(run: Path, metrics: dict[str, Any], res: OffPolicyResult | None, ds: TransitionDataset,
           states: list[np.ndarray] | None, demo_states: list[np.ndarray] | None) -> None:
    from offline_adp.data.files import atomic_directory

    with atomic_directory(run / "evaluation", overwrite=True) as tmp:
        if res is None:  # continuous commands: no density ratios (evaluation/continuous.py): w is NaN
            (tmp / "metrics.json").write_text(json.dumps(json_safe(metrics), indent=1, default=float, allow_nan=False))
            a = ds.arrays()
            cols = {name: a.obs[:, j] for j, name in enumerate(ds.feature_names)}
            pq.write_table(pa.table({**cols, "step": a.step, "source": ds.table.column("source"),
                                     "w": np.full(len(ds), np.nan)}), tmp / "ratios.parquet")
            for name, st in (("rollout_states", states), ("rollout_states_demonstrator", demo_states)):
                if st is not None:
                    np.savez_compressed(tmp / f"{name}.npz", **{f"t{t}": s for t, s in enumerate(st)})
            return
        _write_files(tmp, metrics, res, ds, states, demo_states)


def _write_files(tmp: Path, metrics: dict[str, Any], res: OffPolicyResult, ds: TransitionDataset,
                 states: list[np.ndarray] | None, demo_states: list[np.ndarray] | None) -> None:
    (tmp / "metrics.json").write_text(json.dumps(json_safe(metrics), indent=1, default=float, allow_nan=False))
    frames = [res.diagnostics.assign(method="recursion")]
    frames += [d.assign(method=k) for k, (_, d) in res.extra_ratios.items()]
    pd.concat(frames, ignore_index=True).to_csv(tmp / "per_step.csv", index=False)
    a = ds.arrays()
    cols = {name: a.obs[:, j] for j, name in enumerate(ds.feature_names)}
    src = ds.table.column("source")
    extra = {"w_classifier": res.extra_ratios["classifier"][0].w} if "classifier" in res.extra_ratios else {}
    if res.pooled is not None:
        extra["w_pooled"] = res.pooled[0].w
    pq.write_table(pa.table({**cols, "step": a.step, "source": src, "w": res.ratios.w, **extra}),
                   tmp / "ratios.parquet")
    if states is not None:
        np.savez_compressed(tmp / "rollout_states.npz", **{f"t{t}": s for t, s in enumerate(states)})
    if demo_states is not None:
        np.savez_compressed(tmp / "rollout_states_demonstrator.npz", **{f"t{t}": s for t, s in enumerate(demo_states)})
