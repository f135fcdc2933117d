"""The behaviour policy pi_b(a | x): logged propensities where present, else a classifier.

Off-policy estimates need ``pi_b(a_i | x_i)`` of every logged action; the support check
needs ``pi_b(. | x)`` of every action. Logged propensities are used for the first when
every row has one; a classifier (LightGBM by default) trained on (x, a) pairs supplies
the rest, with probabilities clipped to ``[clip, 1]`` so no ratio divides by zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from offline_adp.regressors import make_classifier


@dataclass
class BehaviourEstimate:
    """pi_b at the data.

    Attributes
    ----------
    logged_prob : ndarray (n,)
        ``pi_b(a_i | x_i)`` of each logged action (clipped).
    all_probs : ndarray (n, n_actions)
        Classifier estimate of ``pi_b(. | x_i)`` (clipped, renormalised).
    source : str
        ``logged`` (every row had a propensity), ``estimated`` (none had), or ``mixed``.
    clip : float
    n_clipped : int
        Rows whose logged-action probability was raised to ``clip``.
    classifier : str
    """

    logged_prob: np.ndarray
    all_probs: np.ndarray
    source: str
    clip: float
    n_clipped: int
    classifier: str
    warnings: list[str] = field(default_factory=list)


def estimate_behaviour(
    obs: np.ndarray,
    action: np.ndarray,
    n_actions: int,
    logged: np.ndarray | None = None,
    *,
    classifier: Any = "lightgbm",
    classifier_params: dict | None = None,
    clip: float = 1e-3,
    max_fit_rows: int = 20_000,
    seed: int = 0,
) -> BehaviourEstimate:
    """Behaviour probabilities at the data (see module docstring); the classifier is
    trained on at most ``max_fit_rows`` rows drawn at random."""
    fit_rows = np.arange(len(action))
    if len(fit_rows) > max_fit_rows:  # a random subsample is plenty for pi_b(. | x)
        fit_rows = np.sort(np.random.default_rng(seed).choice(len(action), max_fit_rows, replace=False))
    probs = np.zeros((len(action), n_actions))
    taken = np.unique(action[fit_rows])
    if len(taken) == 1:  # one action in the logs (e.g. a one-action chain): pi_b(a | x) = 1, no classifier to fit
        probs[:, int(taken[0])] = 1.0
    else:
        clf = make_classifier(classifier, **(classifier_params or {})).fit(obs[fit_rows], action[fit_rows])
        probs[:, np.asarray(clf.classes_, dtype=np.int64)] = clf.predict_proba(obs)
    probs = np.maximum(probs, clip)
    probs /= probs.sum(axis=1, keepdims=True)
    est = probs[np.arange(len(action)), action]
    have = np.zeros(len(action), bool) if logged is None else np.isfinite(logged) & (logged > 0)
    source = "logged" if have.all() else "estimated" if not have.any() else "mixed"
    p = np.where(have, logged if logged is not None else 0.0, est)
    n_clipped = int(np.sum(p < clip))
    warnings = []
    if n_clipped:
        warnings.append(f"{n_clipped} behaviour probabilities below {clip} were clipped to it")
    name = classifier if isinstance(classifier, str) else type(classifier).__name__
    return BehaviourEstimate(np.maximum(p, clip), probs, source, clip, n_clipped, name, warnings)


#: a state logged at least this many times is judged by its own action counts, not the classifier
EXACT_STATE_VISITS = 5


def exact_state_support(obs: np.ndarray, action: np.ndarray, n_actions: int, probs: np.ndarray,
                        min_visits: int = EXACT_STATE_VISITS) -> np.ndarray:
    """``probs`` (``pi_b(. | x_i)`` by the classifier) where, at a state the logs hold at least
    ``min_visits`` times (the same observation: a discrete state space), the logged
    frequencies of the actions there instead. A classifier smooths across states: at a
    tabular state where the logs never took an action it gave that action 0.01-0.06, above
    the support threshold, and the policy that takes it read as "within the data's support"
    (an audit, 2026-11-29). Pooled over time steps, as the classifier is."""
    if len(obs) == 0:
        return probs
    rows = np.ascontiguousarray(obs, dtype=np.float64)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    _, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    seen = counts[inv] >= min_visits
    if not seen.any():
        return probs
    freq = np.zeros((len(counts), n_actions))
    np.add.at(freq, (inv, np.asarray(action, dtype=np.int64)), 1.0)
    out = np.array(probs, dtype=np.float64, copy=True)
    out[seen] = freq[inv[seen]] / counts[inv[seen], None]
    return out


def support_violations(target_probs: np.ndarray, behaviour_probs: np.ndarray, step: np.ndarray,
                       threshold: float = 0.01) -> dict[str, Any]:
    """Where the evaluated policy puts mass on actions the data (almost) never took there.

    A row violates support when pi gives at least half its mass to actions with
    ``pi_b(a | x) < threshold``. Returns the overall fraction, the count, and the
    fraction per step.
    """
    bad_mass = np.sum(target_probs * (behaviour_probs < threshold), axis=1)
    viol = bad_mass >= 0.5
    steps = np.unique(step)
    per_step = {int(t): float(viol[step == t].mean()) for t in steps}
    return {"threshold": threshold, "fraction": float(viol.mean()), "count": int(viol.sum()), "per_step": per_step,
            "mean_unsupported_mass": float(bad_mass.mean())}
