"""The off-policy evaluation's independent fits as one batch of tasks on a task map.

Given a task map (:mod:`offline_adp.parallel`; under the Dask engine
:class:`offline_adp.engines.dask.DaskTaskMap`), :func:`fit_batch` sends, as one call, every
fit of :func:`~offline_adp.evaluation.offpolicy.off_policy` that needs only the data, the
policy and the behaviour model's ratios:

- the main FQE fit (:func:`~offline_adp.evaluation.fqe_interval.fit_fqe`, settled as locally)
  and everything read from it: Q at every row, its bootstrap replicates (in order, on that
  worker) and its support bounds
  (:func:`~offline_adp.evaluation.fqe_interval.read_where_fitted`; only these numbers come
  back, never the fitted FQE and its training state, several times the data's size);
- the model rollouts (:func:`~offline_adp.evaluation.fqe_interval.model_reading`: the
  :class:`~offline_adp.evaluation.model_rollouts.LoggedDynamics` fit and its rollouts);
- each fold of the cross-fitted FQE (:func:`~offline_adp.evaluation.psdp_eps.fold_q`);
- the density ratios: the per-step recursion of the policy and of every reference policy,
  the pooled ratios (a stationary policy) and the classifier ratios (with a simulator's
  states) (:mod:`~offline_adp.evaluation.shift`).

Each task is a function of its arguments and its own seed (the evaluation's seed, as in the
local evaluation), never of where or after which other task it runs, so the results equal
the local evaluation's on any number of workers. The dataset and the policy are broadcast
once. The main FQE runs as one task on a worker, not through the Dask fit engine (which
splits the trees over the workers): its bootstrap replicates, fixed point and support
bounds read the fit's training state (leaf positions of every row, the operators), which
that engine leaves on the workers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.data.dataset import TransitionArrays, TransitionDataset
from offline_adp.evaluation import shift
from offline_adp.evaluation.estimand import Estimand
from offline_adp.evaluation.fqe_interval import FQEFit, fit_fqe, fqe_settings, model_reading, read_where_fitted
from offline_adp.evaluation.psdp_eps import CrossFitError, crossfit_folds, fold_q
from offline_adp.evaluation.settings import EvaluationSettings
from offline_adp.parallel import TaskMap
from offline_adp.policies import Policy, is_stationary


@dataclass(frozen=True)
class BatchFits:
    """What :func:`fit_batch` computed, for the stages of ``off_policy`` to use instead of fitting."""

    fit: FQEFit  #: the main FQE fit
    model: dict[str, Any] | None  #: the model rollouts' reading (None: not run in the batch)
    #: ``(row_fold, k, held Q per fold)`` of the cross-fitted FQE, a CrossFitError, or None (no folds)
    folds: tuple[np.ndarray, int, list[np.ndarray]] | CrossFitError | None
    ratios: dict[str, shift.DensityRatios]  #: "self", "pooled", "ref:NAME", "classifier"


def _fqe(*, ds: TransitionDataset, policy: Policy, est_def: Estimand, cfg: EvaluationSettings, x0: np.ndarray,
         pi_x0: np.ndarray) -> FQEFit:
    fit = fit_fqe(ds, policy, est_def, cfg.fqe_params, cfg.seed, x0, pi_x0)
    return read_where_fitted(fit, ds, policy, est_def, cfg, x0, pi_x0)


def _model(*, ds: TransitionDataset, policy: Policy, est_def: Estimand, particles: int, level: float,
           seed: int) -> dict[str, Any]:
    return model_reading(ds, policy, est_def, particles, level, seed, ds.arrays())


def _fold(*, ds: TransitionDataset, policy: Policy, vectors: dict[str, np.ndarray], f: int,
          **kw: Any) -> np.ndarray | CrossFitError:
    try:
        return fold_q(f, ds=ds, policy=policy, row_fold=vectors["row_fold"], **kw)
    except CrossFitError as exc:  # returned, so that the other tasks' results are kept
        return exc


def _recursion(*, ds: TransitionDataset, policy: Policy, vectors: dict[str, np.ndarray], rho: str, T: int,
               ratio_fit: dict[str, Any]) -> shift.DensityRatios:
    a = ds.arrays()
    return shift.ratios_by_recursion(a.obs, a.next_obs, a.step, a.episode, vectors[rho], horizon=T, **ratio_fit)


def _pooled(*, ds: TransitionDataset, policy: Policy, vectors: dict[str, np.ndarray], rho: str, T: int,
            ratio_fit: dict[str, Any]) -> shift.DensityRatios:
    a = ds.arrays()
    return shift.ratios_pooled(a.obs, a.next_obs, a.step, vectors[rho], horizon=T, **ratio_fit)


def _classifier(*, ds: TransitionDataset, policy: Policy, states: list[np.ndarray], seed: int) -> shift.DensityRatios:
    a = ds.arrays()
    return shift.ratios_by_classifier(a.obs, a.step, states, seed=seed)


_JOBS: dict[str, Callable[..., Any]] = {"fqe": _fqe, "model": _model, "fold": _fold, "recursion": _recursion,
                                        "pooled": _pooled, "classifier": _classifier}


def run_job(job: tuple[str, str, dict[str, Any]], *, ds: TransitionDataset, policy: Policy,
            vectors: dict[str, np.ndarray]) -> Any:
    """One task of the batch: ``job = (kind, name, arguments)`` with the broadcast dataset,
    policy and per-row ``vectors`` (the ratios' rho, the folds), which the jobs name."""
    kind, _name, kw = job
    if kind in ("fold", "recursion", "pooled"):
        kw = {**kw, "vectors": vectors}
    return _JOBS[kind](ds=ds, policy=policy, **kw)


@dataclass(frozen=True)
class BatchInputs:
    """What the batch's fits read besides the dataset and the policy (the client's, computed once)."""

    a: TransitionArrays
    rho: np.ndarray  #: rho_i of the policy at every row
    logged_prob: np.ndarray  #: pi_b(a_i | x_i) (the reference policies' ratios)
    row_episode: np.ndarray  #: each row's episode index (the cross-fit's folds)
    level: float
    ratio_fit: dict[str, Any]
    psdp_folds: int


def batch_jobs(policy: Policy, est_def: Estimand, cfg: EvaluationSettings, b: BatchInputs,
               reference_policies: dict[str, Policy] | None,
               policy_states: list[np.ndarray] | None) -> tuple[list[tuple[str, str, dict[str, Any]]], Any,
                                                                dict[str, np.ndarray]]:
    """The batch's jobs ``(kind, name, arguments)``, longest first, the folds' ``(row_fold, k)``
    and the per-row vectors the jobs name (broadcast with the dataset, not sent per job)."""
    a, T, seed = b.a, est_def.horizon, cfg.seed
    vectors = {"rho": b.rho}
    x0 = a.obs[a.step == 0]
    jobs: list[tuple[str, str, dict[str, Any]]] = [
        ("fqe", "fqe", {"est_def": est_def, "cfg": cfg, "x0": x0, "pi_x0": policy.probabilities(x0, 0)})]
    folds = None
    if b.psdp_folds:
        row_fold, k = crossfit_folds(b.row_episode, b.psdp_folds, seed)
        folds, vectors["row_fold"] = (row_fold, k), row_fold
        kw = {"fqe_params": fqe_settings(cfg.fqe_params, est_def.fqe_horizon), "fqe_T": est_def.fqe_horizon,
              "gamma": est_def.gamma, "seed": seed, "k": k}
        jobs += [("fold", f"fold {f + 1}", {"f": f, **kw}) for f in range(k)]
    if est_def.form == "finite" and cfg.model_particles:
        jobs.append(("model", "model", {"est_def": est_def, "particles": cfg.model_particles, "level": b.level,
                                        "seed": seed}))
    jobs.append(("recursion", "self", {"rho": "rho", "T": T, "ratio_fit": b.ratio_fit}))
    if is_stationary(policy, a.obs, T):
        jobs.append(("pooled", "pooled", {"rho": "rho", "T": T, "ratio_fit": b.ratio_fit}))
    for name, ref in (reference_policies or {}).items():
        vectors[f"rho:{name}"] = ref.probabilities(a.obs, a.step)[np.arange(len(a)), a.action] / b.logged_prob
        jobs.append(("recursion", f"ref:{name}", {"rho": f"rho:{name}", "T": T, "ratio_fit": b.ratio_fit}))
    if policy_states is not None:
        jobs.append(("classifier", "classifier", {"states": policy_states[:T], "seed": seed}))
    return jobs, folds, vectors


def fit_batch(ds: TransitionDataset, policy: Policy, est_def: Estimand, cfg: EvaluationSettings, b: BatchInputs,
              reference_policies: dict[str, Policy] | None, policy_states: list[np.ndarray] | None,
              task_map: TaskMap, say: Callable[[str], None]) -> BatchFits:
    """Run the batch (module docstring) on ``task_map``; the dataset and policy are broadcast once."""
    from offline_adp.progress import PhaseLines

    jobs, folds, vectors = batch_jobs(policy, est_def, cfg, b, reference_policies, policy_states)
    say(f"fits on the task map: {', '.join(name for _k, name, _a in jobs)}")
    out = dict(zip([name for _k, name, _a in jobs],
                   task_map(run_job, jobs, shared={"ds": ds, "policy": policy, "vectors": vectors},
                            on_done=PhaseLines(say, "fits on the task map", len(jobs), lines=len(jobs))), strict=True))
    held = None
    if folds is not None:
        qs = [out.pop(f"fold {f + 1}") for f in range(folds[1])]
        err = next((q for q in qs if isinstance(q, CrossFitError)), None)
        held = err if err is not None else (folds[0], folds[1], qs)
    ratios = {k: v for k, v in out.items() if k not in ("fqe", "model")}
    return BatchFits(out["fqe"], out.get("model"), held, ratios)
