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
    n_ep = int(n_episodes_index.max()) + 1
    k = int(max(2, min(folds, n_ep)))
    fold_of = np.random.default_rng(seed).permutation(n_ep) % k
    row_fold = fold_of[n_episodes_index]
    gap = np.zeros(len(a))
    q_out = np.zeros((len(a), ds.n_actions)) if return_q else None
    for f in range(k):
        held = row_fold == f
        train = np.flatnonzero(~held)
        fqe = FittedQEvaluation(policy=policy, horizon=fqe_T, gamma=gamma, random_state=seed, **fqe_params)
        try:
            fqe.fit(ds.take(train))
        except ValueError as exc:  # a fold the settings cannot fit on (per_action: an action it lacks)
            raise CrossFitError(f"fold {f + 1} of {k}: {exc}") from None
        if fqe_params.get("mode") == "frozen" and fqe_T is None and not fqe_params.get("validation_fraction"):
            fqe.settle()  # as the estimate's own FQE
        qv = fqe.q_function_.values(a.obs[held], a.step[held])
        probs = policy.probabilities(a.obs[held], a.step[held]) if target is None else target[held]
        gap[held] = (probs * qv).sum(axis=1) - qv.min(axis=1)
        if q_out is not None:
            q_out[held] = qv
        if on_fold is not None:
            on_fold()
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
