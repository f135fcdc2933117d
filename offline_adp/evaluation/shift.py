"""Distribution shift: per-step density ratios ``w_t(x) = mu_pi^t(x) / mu_data^t(x)``.

Three ways to get them, from the weakest access model to the strongest:

(a) **Trace data only** — the ratio recursion (a regression form of marginalised
    importance sampling)::

        w_0 = 1
        w_{t+1}(x') = E_data[ w_t(x_t) * pi(a_t | x_t, t) / pi_b(a_t | x_t) | x_{t+1} = x' ]

    fitted step by step with a regressor (extra-trees by default) on the pairs
    ``(x_{t+1}, w_t(x_t) * rho_t)``, clipped at 0 and normalised to mean 1 over the
    data's step-(t+1) states. It holds because, under the data, ``x_{t+1}`` given
    ``(x_t, a_t)`` follows the true dynamics, so re-weighting the step-t pairs by
    ``w_t * rho_t`` turns their successor distribution into ``mu_pi^{t+1}``.

(b) **Simulator** — a probabilistic classifier tells states visited by pi at step t
    (label 1) from the data's step-t states (label 0); with cross-fitted probabilities
    ``p``, ``w = p / (1 - p) * n_data / n_pi`` (``p`` clipped). Its AUC says how
    separable the two are: near 1 the ratio cannot be trusted.

(c) **Full model** — exact ``mu_t`` by forward recursion (the oracle for tests).

:func:`diagnostics` summarises any set of ratios per step; the raw max is never
reported alone (see the field list there).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from offline_adp import dp
from offline_adp.access import FullModel
from offline_adp.policies import Policy
from offline_adp.qfunctions import predict_model
from offline_adp.regressors import binary_proba, make_regressor


@dataclass
class DensityRatios:
    """Density ratios at the data's own states.

    Attributes
    ----------
    method : str
        ``recursion``, ``classifier`` or ``exact``.
    w : ndarray (n,)
        ``w_{step_i}(x_i)`` for every data row ``i`` (mean 1 within each step).
    step : ndarray (n,)
    auc : dict step -> AUC (classifier method only)
    uncovered : dict step -> fraction of pi's samples the classifier found (almost) no data near
    warnings : list of str
    unmeasured : list of str
        The warnings of the steps (or the pooled fit) whose ratios could not be fitted and
        were left at 1: no measurement there, not a finding of no shift.
    """

    method: str
    w: np.ndarray
    step: np.ndarray
    auc: dict[int, float] = field(default_factory=dict)
    uncovered: dict[int, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    unmeasured: list[str] = field(default_factory=list)

    def notes(self) -> dict[str, list[str]]:
        """The block of ``metrics.json`` for these ratios' warnings (``unmeasured``: a subset)."""
        return {"warnings": list(self.warnings), "unmeasured": list(self.unmeasured)}


# --------------------------------------------------------------------------- exact
def policy_table(policy: Policy, n_states: int, horizon: int) -> np.ndarray:
    """``pi_t(a | s)`` for every state index, shape (T, S, A) (observations are ``[[s]]``)."""
    obs = np.arange(n_states, dtype=np.float64)[:, None]
    return np.stack([policy.probabilities(obs, t) for t in range(horizon)])


def exact_distributions(model: FullModel, policy: Policy, horizon: int) -> np.ndarray:
    """Exact ``mu_t`` of ``policy`` on a full model, shape (T + 1, S); each row sums to 1."""
    return dp.state_distributions(model.P, policy_table(policy, model.n_states, horizon), model.initial_distribution,
                                  horizon)


def exact_ratios(model: FullModel, policy: Policy, behaviour: Policy, horizon: int) -> np.ndarray:
    """Exact ``w_t(s) = mu_pi^t(s) / mu_b^t(s)``, shape (T, S); ``inf`` where only pi goes, 0 where neither."""
    mu_pi = exact_distributions(model, policy, horizon)[:horizon]
    mu_b = exact_distributions(model, behaviour, horizon)[:horizon]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(mu_b > 0, mu_pi / np.where(mu_b > 0, mu_b, 1.0), np.where(mu_pi > 0, np.inf, 0.0))


# --------------------------------------------------------------------------- (a) recursion
#: The ratio regressions' extra-trees. One thread: a step's regression holds a few hundred
#: rows, where starting threads cost more than the trees (8.4 against 5.3 ms CPU a fit of 47
#: rows); the trees are the same (their seeds are drawn before any thread starts).
RATIO_TREES = {"n_estimators": 10, "min_samples_leaf": 20, "max_features": 1.0, "n_jobs": 1}


#: The ratio regressions are fitted on at most this many rows (a uniform sample above it, the
#: same sample at every sweep of :func:`ratios_pooled`) and read at every row; as the model
#: rollouts' :data:`~offline_adp.evaluation.model_rollouts.MAX_FIT_ROWS`. Below it nothing
#: changes. At 10M transitions the pooled regression's 20 sweeps on all ~9.4M rows cost
#: ~80 CPU-s each; on 1M rows ~7 (docs/scaling.md, "The 10M evaluate").
RATIO_MAX_FIT_ROWS = 1_000_000


def _fit_predict(regressor: Any, params: dict | None, X: np.ndarray, y: np.ndarray, X_new: np.ndarray) -> np.ndarray:
    """The ratio regression fitted on ``(X, y)`` and read at ``X_new`` (a forest's read is
    deterministic: :func:`~offline_adp.qfunctions.predict_model`); the registry's
    extra-trees are built and read without the forest's per-tree overhead, with the same
    numbers (:func:`~offline_adp.trees.forest_predict.extra_trees_fit_predict`). Above
    :data:`RATIO_MAX_FIT_ROWS` rows the fit sees a uniform sample of them (seeded: the same
    rows for the same ``len(X)``)."""
    from offline_adp.trees.forest_predict import extra_trees_fit_predict

    if len(X) > RATIO_MAX_FIT_ROWS:
        rows = np.sort(np.random.default_rng(len(X)).choice(len(X), RATIO_MAX_FIT_ROWS, replace=False))
        X, y = X[rows], y[rows]
    model = make_regressor(regressor, **(params or {}))
    out = extra_trees_fit_predict(model, X, y, X_new) if regressor == "extra_trees" else None
    return predict_model(model.fit(X, y), X_new) if out is None else out


def _sampled_warning(n_rows: int, what: str) -> list[str]:
    """The warning that ``what`` was fitted on a sample (:data:`RATIO_MAX_FIT_ROWS` of
    ``n_rows``), or none: a cap the user did not ask for is said, not silent."""
    if n_rows <= RATIO_MAX_FIT_ROWS:
        return []
    return [f"{what} fitted on a uniform sample of {RATIO_MAX_FIT_ROWS:,} of {n_rows:,} rows "
            "(shift.RATIO_MAX_FIT_ROWS) and read at every row"]


def _normalise(w: np.ndarray) -> np.ndarray:
    m = w.mean() if len(w) else 1.0
    return w / m if m > 0 else np.ones_like(w)


def ratios_by_recursion(
    obs: np.ndarray,
    next_obs: np.ndarray,
    step: np.ndarray,
    episode: np.ndarray,
    rho: np.ndarray,
    *,
    regressor: Any = "extra_trees",
    regressor_params: dict | None = None,
    horizon: int | None = None,
) -> DensityRatios:
    """Per-step ratios from logs alone (method (a), see the module docstring).

    Parameters
    ----------
    obs, next_obs : ndarray (n, d)
    step, episode : ndarray (n,)
    rho : ndarray (n,)
        ``pi(a_i | x_i, t_i) / pi_b(a_i | x_i)`` for the logged action of every row.
    regressor, regressor_params
        The regression learner (registry name or estimator); trees default to
        ``min_samples_leaf=20`` so the conditional mean is not a single noisy sample.
    horizon : int, optional
        Last step + 1 to compute (default: all steps in the data).
    """
    if regressor == "extra_trees" and not regressor_params:
        regressor_params = RATIO_TREES
    T = int(step.max()) + 1 if horizon is None else min(int(horizon), int(step.max()) + 1)
    w = np.ones(len(step))
    warnings: list[str] = []
    unmeasured: list[str] = []
    # row of step t+1 that follows row i (same episode), found with one sort
    order = np.lexsort((step, episode))
    nxt = np.full(len(step), -1)
    same = (episode[order][1:] == episode[order][:-1]) & (step[order][1:] == step[order][:-1] + 1)
    nxt[order[:-1][same]] = order[1:][same]
    thin = []
    for t in range(T - 1):
        here = np.flatnonzero(step == t)
        there = np.flatnonzero(step == t + 1)
        if not len(there):
            break
        if len(here) < 500:
            thin.append(t)
        y = w[here] * rho[here]
        w_next = np.maximum(_fit_predict(regressor, regressor_params, next_obs[here], y, obs[there]), 0.0)
        if not np.isfinite(w_next).all() or w_next.sum() <= 0:
            unmeasured.append(f"step {t + 1}: the ratio regression returned no positive mass; ratios set to 1")
            w_next = np.ones(len(there))
        w[there] = _normalise(w_next)
    if thin:
        warnings.append(f"{len(thin)} steps have fewer than 500 samples (as few as "
                        f"{int(min(np.sum(step == t) for t in thin))}): "
                        "the per-step regressions shrink the ratios towards 1, so these diagnostics are optimistic; "
                        "with a simulator prefer the classifier ratios")
    counts = np.bincount(step[step < T - 1].astype(np.int64)) if T > 1 else np.zeros(1, np.int64)
    warnings += _sampled_warning(int(counts.max(initial=0)), "the per-step ratio regressions (largest step)")
    return DensityRatios("recursion", w, step.copy(), warnings=unmeasured + warnings, unmeasured=unmeasured)


#: Below this many data states per step, per-step ratios cannot be estimated (the
#: regressions shrink them to 1 and ESS/n reads 1.0 whatever the shift).
MIN_STATES_PER_STEP = 500


def ratios_pooled(
    obs: np.ndarray,
    next_obs: np.ndarray,
    step: np.ndarray,
    rho: np.ndarray,
    *,
    regressor: Any = "extra_trees",
    regressor_params: dict | None = None,
    horizon: int | None = None,
    n_sweeps: int | None = None,
) -> DensityRatios:
    """Ratios of the time-averaged distributions ``W(x) = sum_t mu_pi^t(x) / sum_t mu_data^t(x)``
    from logs alone, pooling every step into one regression (stationary problems: the
    dynamics and the policy do not depend on t).

    The recursion of method (a) with one regressor for all steps, iterated to a fixed
    point (``w = 1`` at the start states)::

        W_{k+1}(x') = E_data[ W_k(x_t) * rho_t | x_{t+1} = x' ]   (all t < T - 1 pooled)

    normalised to mean 1 over the data's states at steps >= 1. Pooling gives the
    regression T times the samples of one step, at the price of the stationarity
    assumption (it averages the per-step ratios). ``w`` holds ``W(x_i)`` for every row.
    """
    if regressor == "extra_trees" and not regressor_params:
        regressor_params = RATIO_TREES
    T = int(step.max()) + 1 if horizon is None else min(int(horizon), int(step.max()) + 1)
    keep = step < T
    src = np.flatnonzero(keep & (step < T - 1))
    dst = np.flatnonzero(keep & (step >= 1))
    w = np.ones(len(step))
    if not len(src) or not len(dst):
        why = ["one step only: nothing to pool"]
        return DensityRatios("pooled", w, step.copy(), warnings=why, unmeasured=why)
    for _ in range(n_sweeps if n_sweeps is not None else min(T, 20)):
        new = np.maximum(_fit_predict(regressor, regressor_params, next_obs[src], w[src] * rho[src], obs[dst]), 0.0)
        if not np.isfinite(new).all() or new.sum() <= 0:
            why = ["the pooled ratio regression returned no positive mass; ratios set to 1"]
            return DensityRatios("pooled", np.ones(len(step)), step.copy(), warnings=why, unmeasured=why)
        new = _normalise(new)
        done = np.max(np.abs(new - w[dst])) < 1e-6
        w[dst] = new
        if done:
            break
    return DensityRatios("pooled", w, step.copy(),
                         warnings=["pooled over time: assumes the problem and the policy are stationary",
                                   *_sampled_warning(len(src), "the pooled ratio regression")])


def pooled_summary(ratios: DensityRatios) -> dict[str, Any]:
    """ESS/n, total variation and quantiles of pooled ratios (all rows at steps >= 1)."""
    w = ratios.w[ratios.step >= 1] if (ratios.step >= 1).any() else ratios.w
    e2 = float(np.mean(w**2))
    q = np.quantile(w, [0.5, 0.9, 0.99])
    return {"n": int(len(w)), "ess_fraction": 1.0 / e2 if e2 > 0 else 0.0, "tv": 0.5 * float(np.mean(np.abs(w - 1.0))),
            "q50": float(q[0]), "q90": float(q[1]), "q99": float(q[2]), "max": float(w.max())}


def per_step_counts(step: np.ndarray, horizon: int) -> np.ndarray:
    """Data states at each step t < horizon."""
    return np.bincount(step[step < horizon].astype(np.int64), minlength=horizon)[:horizon]


# --------------------------------------------------------------------------- (b) classifier
def ratios_by_classifier(
    obs: np.ndarray,
    step: np.ndarray,
    policy_states: list[np.ndarray],
    *,
    classifier: Any = "lightgbm",
    classifier_params: dict | None = None,
    clip: float = 1e-3,
    normalise: bool = True,
    seed: int = 0,
    on_step: Any = None,
) -> DensityRatios:
    """Per-step ratios from a classifier between pi's states and the data's (method (b)).

    Parameters
    ----------
    obs, step : the data's states and their steps
    policy_states : list of ndarray
        ``policy_states[t]``: states visited by pi at step t (e.g. from
        :func:`offline_adp.algorithms.psdp.state_samples`).
    clip : float
        Probabilities are clipped to ``[clip, 1 - clip]``; pi samples at the upper clip
        count as *uncovered* (no data near them).
    normalise : bool
        Rescale to mean 1 per step (self-normalised; removes the class-prior error).
    on_step : callable, optional (called once per step of ``policy_states``: progress)
    """
    from sklearn.metrics import roc_auc_score
    from sklearn.model_selection import StratifiedKFold

    w = np.ones(len(step))
    auc: dict[int, float] = {}
    uncovered: dict[int, float] = {}
    warnings: list[str] = []
    unmeasured: list[str] = []
    for t, xp in enumerate(policy_states):
        if on_step is not None and t:  # step t - 1 is done
            on_step()
        here = np.flatnonzero(step == t)
        if not len(here) or not len(xp):
            continue
        if min(len(here), len(xp)) < 2:  # the 2-fold cross-fit needs two of each; e.g. one rollout still alive
            unmeasured.append(f"step {t}: {len(here)} data and {len(xp)} policy states: too few for a classifier, "
                              "ratio left at 1")
            continue
        X = np.vstack([obs[here], xp])
        y = np.r_[np.zeros(len(here)), np.ones(len(xp))]
        p = np.empty(len(y))
        for train, test in StratifiedKFold(2, shuffle=True, random_state=seed + t).split(X, y):
            p[test] = binary_proba(classifier, classifier_params, X[train], y[train], X[test])
        auc[t] = float(roc_auc_score(y, p))
        pc = np.clip(p, clip, 1 - clip)
        uncovered[t] = float(np.mean(pc[len(here):] >= 1 - clip))
        r = pc[: len(here)] / (1 - pc[: len(here)]) * len(here) / len(xp)
        w[here] = _normalise(r) if normalise else r
    warnings += _separable_warning(auc, len(policy_states))
    if on_step is not None and len(policy_states):
        on_step()
    return DensityRatios("classifier", w, step.copy(), auc=auc, uncovered=uncovered, warnings=unmeasured + warnings,
                         unmeasured=unmeasured)


def _separable_warning(auc: dict[int, float], n_steps: int) -> list[str]:
    """One warning for every step whose classifier AUC is above 0.95 (not one per step)."""
    sep = np.array(sorted(t for t, a in auc.items() if a > 0.95), np.int64)
    if not len(sep):
        return []
    top = max(sep.tolist(), key=lambda t: auc[t])
    return [f"classifier AUC > 0.95 at {len(sep)} of {n_steps} steps ({step_ranges(sep)}; highest {auc[top]:.3f} "
            f"at t = {top}): pi's states and the data's are almost separable there; the ratios at those steps "
            "cannot be trusted"]


def step_ranges(steps: np.ndarray, k: int = 8) -> str:
    """Sorted steps as runs, ``"12-17, 28-35, 40"``; the first ``k`` runs, then how many more."""
    runs = np.split(steps, np.flatnonzero(np.diff(steps) != 1) + 1)
    words = [f"{r[0]}-{r[-1]}" if len(r) > 1 else f"{r[0]}" for r in runs]
    return ", ".join(words[:k]) + (f" and {len(words) - k} more runs" if len(words) > k else "")


# --------------------------------------------------------------------------- diagnostics
def _leaves(obs: np.ndarray, w: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Regions with at least ``k`` data samples: leaves of a regression tree of w on x."""
    from sklearn.tree import DecisionTreeRegressor

    if len(w) < 2 * k:
        return np.zeros(len(w), np.int64)
    tree = DecisionTreeRegressor(min_samples_leaf=k, max_leaf_nodes=max(2, len(w) // k), random_state=seed)
    return tree.fit(obs, w).apply(obs)


#: rows x replicates drawn at once by :func:`_resampled_sups` (bounded temporaries)
_RESAMPLE_BLOCK = 1 << 21


def _resampled_sups(inv: np.ndarray, w: np.ndarray, n_regions: int, min_rows: int, n_boot: int,
                    rng: np.random.Generator) -> np.ndarray:
    """Per bootstrap replicate (rows resampled with replacement within the fixed regions
    ``inv``): the largest region mean of ``w`` over the regions drawn at least ``min_rows``
    times (0 where none is). The replicates of a block are drawn by one call and counted by
    one ``bincount`` over (replicate, region) bins: the draws, and each bin's sum in draw
    order, are those of one call per replicate."""
    n = len(w)
    sups = np.empty(n_boot)
    block = max(1, min(n_boot, _RESAMPLE_BLOCK // max(n, 1)))
    for b0 in range(0, n_boot, block):
        nb = min(block, n_boot - b0)
        idx = rng.integers(0, n, (nb, n))
        bins = (inv[idx] + n_regions * np.arange(nb)[:, None]).reshape(-1)
        c = np.bincount(bins, minlength=nb * n_regions).reshape(nb, n_regions)
        s = np.bincount(bins, weights=w[idx].reshape(-1), minlength=nb * n_regions).reshape(nb, n_regions)
        sups[b0:b0 + nb] = np.max(np.where(c >= min_rows, s / np.maximum(c, 1), 0.0), axis=1)
    return sups


def supported_sup(obs: np.ndarray, w: np.ndarray, *, k: int = 20, n_boot: int = 200, level: float = 0.95,
                  cover_ratio: float = 20.0, seed: int = 0) -> dict[str, float]:
    """Sup of the ratio over regions with at least ``k`` samples, its bootstrap upper bound,
    and pi's mass in poorly covered regions (region mean ratio above ``cover_ratio``)."""
    leaf = _leaves(obs, w, k, seed)
    _, inv = np.unique(leaf, return_inverse=True)
    inv = inv.reshape(-1)
    cnt = np.bincount(inv)
    mean = np.bincount(inv, weights=w) / cnt
    sups = _resampled_sups(inv, w, len(cnt), max(1, k // 2), n_boot, np.random.default_rng(seed))
    poorly = mean[inv] > cover_ratio
    ucb = max(float(np.quantile(sups, level)), float(mean.max())) if n_boot else float(mean.max())
    return {"supported_sup": float(mean.max()), "sup_ucb": ucb,
            "poorly_covered_mass": float(np.sum(w[poorly]) / max(np.sum(w), 1e-300)), "n_regions": int(len(cnt))}


def diagnostics(ratios: DensityRatios, obs: np.ndarray, *, k: int = 20, n_boot: int = 200, cover_ratio: float = 20.0,
                seed: int = 0) -> pd.DataFrame:
    """Per-step summary of density ratios.

    Columns: ``step, n, ess_fraction`` (1 / E[w^2]), ``tv`` (0.5 E|w - 1|), ``q50, q90,
    q99, q999, max``, ``supported_sup`` (max over regions with >= k samples),
    ``sup_ucb`` (bootstrap upper bound of that sup), ``poorly_covered_mass``, and for
    the classifier method ``auc`` and ``uncovered`` (pi's samples with no data near).
    """
    rows = []
    for t in np.unique(ratios.step):
        m = ratios.step == t
        w = ratios.w[m]
        e2 = float(np.mean(w**2))
        row: dict[str, Any] = {"step": int(t), "n": int(m.sum()), "ess_fraction": 1.0 / e2 if e2 > 0 else 0.0,
                               "tv": 0.5 * float(np.mean(np.abs(w - 1.0)))}
        q = np.quantile(w, [0.5, 0.9, 0.99, 0.999])
        row.update(q50=q[0], q90=q[1], q99=q[2], q999=q[3], max=float(w.max()))
        row.update(supported_sup(obs[m], w, k=k, n_boot=n_boot, cover_ratio=cover_ratio, seed=seed + int(t)))
        if ratios.auc:
            row["auc"] = ratios.auc.get(int(t), np.nan)
            row["uncovered"] = ratios.uncovered.get(int(t), np.nan)
        rows.append(row)
    return pd.DataFrame(rows)


def pooled_ratio_ucb(ratios: DensityRatios, obs: np.ndarray, *, k: int = 20, n_boot: int = 200, seed: int = 0) -> float:
    """Bootstrap upper bound on ``sup_x sum_t mu_pi^t(x) / sum_t mu_data^t(x)`` (the
    averaged-distribution ratio of PSDP's bound), from all steps' ratios pooled."""
    return supported_sup(obs, ratios.w, k=k, n_boot=n_boot, seed=seed)["sup_ucb"]
