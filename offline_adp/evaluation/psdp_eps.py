"""The PSDP performance bound's inputs from logs alone (Bagnell et al. 2003, Theorem 2): the
per-step residual advantages ``eps_t`` of a policy against a value model fitted *out of
sample* (cross-fitted over episode folds, so the greedy policy of the same data does not
get ``eps = 0`` by construction), and the bound ``sum_t eps_t x ratio``. Used by
:func:`offline_adp.evaluation.offpolicy.off_policy`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset
from offline_adp.evaluation import ope
from offline_adp.policies import Policy


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


#: Folds of the cross-fitted eps_t (:func:`crossfit_residual_advantage`).
PSDP_EPS_FOLDS = 2


def episode_groups(ds: TransitionDataset, em: ope.EpisodeMatrix) -> np.ndarray | None:
    """Each episode's ``source`` label (the behaviour component that logged it), ordered as
    ``em``'s episodes; ``None`` when the dataset has no ``source`` column."""
    if "source" not in ds.table.column_names:
        return None
    src = np.asarray(ds.table.column("source").to_numpy(zero_copy_only=False)).astype(str)
    out = np.empty(em.n_episodes, dtype=object)
    out[em.row_episode[::-1]] = src[::-1]  # the first row of each episode wins
    return out.astype(str)


class CrossFitError(ValueError):
    """A held-out fold of the PSDP epsilon could not be fitted."""


def crossfit_residual_advantage(ds: TransitionDataset, policy: Policy, fqe_params: dict[str, Any], fqe_T: int | None,
                                gamma: float, T: int, n_episodes_index: np.ndarray, *, folds: int = PSDP_EPS_FOLDS,
                                seed: int = 0, return_q: bool = False, target: np.ndarray | None = None,
                                on_fold: Any = None) -> Any:
    """``eps_t`` of :func:`residual_advantage` measured out of sample, by cross-fitting.
    With ``return_q``: ``(eps, q)``, ``q`` (n, n_actions) each row's Q-values from the FQE
    fitted without its episode (the cross-fitted Q the DR estimators use).

    The episodes are split at random into ``folds`` folds; for each fold, FQE of
    ``policy`` (``fqe_params``, the evaluation's settings) is fitted on the other folds and
    the policy's advantage deficit ``sum_a pi(a|x) Q^pi_t(x, a) - min_a Q^pi_t(x, a)`` is
    measured at the held-out fold's step-t states; ``eps_t`` is ``gamma^t`` times its mean
    over all held-out rows (every row is held out once). Measured with the FQE fitted on
    the same data, the deficit of a policy greedy in a Q fitted on that data (FQI's) is 0
    by construction, and so was the bound (Bagnell et al. 2003, Theorem 2, needs eps_t of
    the policy's true Q^pi_t on mu_t; an estimate fitted on other episodes is not tuned to
    the policy). ``n_episodes_index`` is each row's episode index (0 .. N-1); ``target``:
    ``policy.probabilities`` at every row when the caller has them (not computed again);
    ``on_fold()`` is called after each fold (progress).
    """
    a = ds.arrays()
    row_fold, k = crossfit_folds(n_episodes_index, folds, seed)
    held_q = []
    for f in range(k):
        held_q.append(fold_q(f, ds=ds, policy=policy, fqe_params=fqe_params, fqe_T=fqe_T, gamma=gamma, seed=seed,
                             row_fold=row_fold, k=k))
        if on_fold is not None:
            on_fold()
    return crossfit_combine(a, policy, held_q, row_fold, gamma, T, return_q=return_q, target=target,
                            n_actions=ds.n_actions)


def crossfit_folds(n_episodes_index: np.ndarray, folds: int, seed: int) -> tuple[np.ndarray, int]:
    """``(each row's fold, number of folds k)``: the episodes split at random (``seed``)
    into ``k = max(2, min(folds, episodes))`` folds."""
    n_ep = int(n_episodes_index.max()) + 1
    k = int(max(2, min(folds, n_ep)))
    fold_of = np.random.default_rng(seed).permutation(n_ep) % k
    return fold_of[n_episodes_index], k


def fold_q(f: int, *, ds: TransitionDataset, policy: Policy, fqe_params: dict[str, Any], fqe_T: int | None,
           gamma: float, seed: int, row_fold: np.ndarray, k: int) -> np.ndarray:
    """Q-values ``(held rows, n_actions)`` at the rows of fold ``f`` from FQE fitted on the
    other folds (settled as the estimate's own FQE in the structure-conditional case); one
    task of :func:`crossfit_residual_advantage`, the same wherever it runs."""
    a = ds.arrays()
    held = row_fold == f
    fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=gamma, random_state=seed, **fqe_params)
    try:
        fqe.fit(ds.take(np.flatnonzero(~held)))
    except ValueError as exc:  # a fold the settings cannot fit on (per_action: an action it lacks)
        raise CrossFitError(f"fold {f + 1} of {k}: {exc}") from None
    if fqe_params.get("mode") == "frozen" and fqe_T is None and not fqe_params.get("validation_fraction"):
        fqe.settle()  # as the estimate's own FQE
    return fqe.q_function_.values(a.obs[held], a.step[held])


def crossfit_combine(a: Any, policy: Policy, held_q: list[np.ndarray], row_fold: np.ndarray, gamma: float, T: int,
                     *, return_q: bool, target: np.ndarray | None, n_actions: int) -> Any:
    """``eps`` (and with ``return_q`` the cross-fitted Q of every row) from each fold's
    held-out Q-values ``held_q[f]`` (:func:`fold_q`)."""
    gap = np.zeros(len(a))
    q_out = np.zeros((len(a), n_actions)) if return_q else None
    for f, qv in enumerate(held_q):
        held = row_fold == f
        probs = policy.probabilities(a.obs[held], a.step[held]) if target is None else target[held]
        gap[held] = (probs * qv).sum(axis=1) - qv.min(axis=1)
        if q_out is not None:
            q_out[held] = qv
    eps = np.zeros(T)
    for t in range(T):
        m = a.step == t
        if m.any():
            eps[t] = gamma**t * float(gap[m].mean())
    return (eps, q_out) if return_q else eps


def psdp_bound(eps: np.ndarray, ratio_ucb: np.ndarray, pooled_ucb: float | None = None) -> dict[str, float]:
    """PSDP's performance bound (Bagnell et al. 2003, Theorem 2) as a plug-in estimate.

    ``J(pi) - J(pi_ref) <= sum_t eps_t * ||mu_ref^t / mu^t||_inf`` (per-step form), and
    with the averaged distributions ``T * mean_t(eps_t) * ||sum_t mu_ref^t / sum_t mu^t||_inf``.
    """
    def times(e: np.ndarray, r: np.ndarray) -> float:  # 0 x inf is no bound: +inf
        r = np.asarray(r, dtype=np.float64)
        return float("inf") if np.isinf(r).any() or np.isnan(r).any() else float(np.sum(e * r))

    out = {"per_step": times(np.asarray(eps), ratio_ucb)}
    if pooled_ucb is not None:
        out["averaged"] = times(np.array([len(eps) * np.mean(eps)]), np.array([pooled_ucb]))
    return out


def bound_entry(eps: np.ndarray, diag: pd.DataFrame, pooled_ucb: float, T: int) -> dict[str, Any]:
    """One reference policy's PSDP bound with the pieces it multiplies, as the report shows
    them: ``sum_t eps_t``, the per-step ratio upper bounds (their max and the step), the
    pooled one, and the ratio recursion's own coverage reading (optimistic where steps have
    few states: its regressions shrink the ratios towards 1)."""
    ucb = diag["sup_ucb"].to_numpy()[:T]
    e = np.asarray(eps, dtype=np.float64)
    worst = int(np.argmax(ucb)) if len(ucb) else 0
    return {**psdp_bound(eps, ucb, pooled_ucb), "eps_sum": float(np.sum(e)) if np.isfinite(e).all() else None,
            "ratio_ucb_max": float(ucb.max()) if len(ucb) else None,
            "ratio_ucb_step": int(diag["step"].to_numpy()[worst]) if len(ucb) else None,
            "pooled_ratio_ucb": float(pooled_ucb), "poorly_covered_mass": float(diag["poorly_covered_mass"].max()),
            "method": "recursion"}
