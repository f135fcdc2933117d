"""The distribution of a policy's episode cost, and its CVaR, alongside the mean.

Costs are minimised, so the *worst* episodes are the ones with the **highest** cost:

    CVaR_alpha = mean of the worst alpha fraction of episode costs
               = (1 / alpha) * integral_{1 - alpha}^{1} F^{-1}(u) du,

with ``F`` the (possibly weighted) empirical distribution of the per-episode discounted
costs ``G_i = sum_{t<T} gamma^t c_t`` (the estimand's quantity, episode by episode). An
atom that straddles the ``1 - alpha`` quantile counts with the part of its mass inside
the tail, so for costs 1..100 (equal weights) CVaR_0.1 is the mean of 91..100, 95.5.

Where the distributions come from (:func:`cost_distributions`):

- with a simulator, the rollouts' per-episode costs: the policy's distribution (and the
  demonstrator's), measured;
- from the logs alone, the behaviour's logged episode costs: the behaviour's distribution;
- the policy's from the logs alone: the logged episode costs re-weighted by the per-episode
  importance weights ``R_i = prod_t pi(a_t | x_t, t) / pi_b(a_t | x_t)`` (self-normalised,
  the distribution whose mean is WIS), only where the weight diagnostics
  (:func:`~offline_adp.evaluation.ope.weight_diagnostics`,
  :func:`~offline_adp.evaluation.ope.interval_unreliable`) say the weights are usable;
  otherwise ``{"usable": False, "reason": ...}`` ("cannot tell from these logs").
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: The default tail fraction of CVaR: the worst 10% of episodes.
CVAR_ALPHA = 0.1
#: Levels of the stored quantile function (enough to draw the distribution).
QUANTILE_LEVELS = tuple(np.round(np.linspace(0.0, 1.0, 41), 3).tolist())


def _prepare(costs: Any, weights: Any | None) -> tuple[np.ndarray, np.ndarray]:
    from offline_adp.errors import InvalidArgumentError

    c = np.asarray(costs, dtype=np.float64).ravel()
    if not len(c):
        raise InvalidArgumentError("costs: empty; a distribution needs at least one episode")
    if not np.isfinite(c).all():
        raise InvalidArgumentError("costs: not all finite")
    if weights is None:
        w = np.full(len(c), 1.0 / len(c))
    else:
        w = np.asarray(weights, dtype=np.float64).ravel()
        if w.shape != c.shape:
            raise InvalidArgumentError(f"weights: {len(w)} for {len(c)} costs; give one weight per episode")
        if not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise InvalidArgumentError("weights: must be finite, >= 0 and not all 0")
        w = w / w.sum()
    return c, w


def cvar(costs: Any, alpha: float = CVAR_ALPHA, weights: Any | None = None) -> float:
    """Mean of the worst (highest-cost) ``alpha`` fraction of episodes, under the empirical
    distribution of ``costs`` (weighted by ``weights`` when given; see the module docstring).

    Parameters
    ----------
    costs : array-like (n,)
        Per-episode costs.
    alpha : float in (0, 1]
        Tail fraction; 1 gives the mean.
    weights : array-like (n,), optional
        Non-negative per-episode weights (normalised here); default equal.

    Returns
    -------
    float
    """
    from offline_adp.errors import InvalidArgumentError

    if not 0.0 < float(alpha) <= 1.0:
        raise InvalidArgumentError(f"alpha: {alpha!r}; the tail fraction must be in (0, 1]")
    c, w = _prepare(costs, weights)
    order = np.argsort(-c, kind="stable")  # worst (highest cost) first
    c, w = c[order], w[order]
    before = np.concatenate([[0.0], np.cumsum(w)[:-1]])  # mass strictly worse than each atom
    take = np.clip(alpha - before, 0.0, w)  # the part of each atom inside the tail
    return float(np.sum(take * c) / alpha)


def weighted_quantiles(costs: Any, levels: Any, weights: Any | None = None) -> np.ndarray:
    """The (lower) quantile function of the weighted empirical distribution: for each level
    ``u``, the smallest cost ``c`` with ``F(c) >= u`` (``u = 0``: the minimum)."""
    c, w = _prepare(costs, weights)
    c, w = c[w > 0], w[w > 0]  # an episode of weight 0 is not in the distribution
    order = np.argsort(c, kind="stable")
    c, cum = c[order], np.cumsum(w[order])
    u = np.asarray(levels, dtype=np.float64)
    idx = np.searchsorted(cum, u - 1e-12, side="left")
    return c[np.minimum(idx, len(c) - 1)]


def distribution_summary(costs: Any, *, weights: Any | None = None, alpha: float = CVAR_ALPHA,
                         source: str = "", method: str = "") -> dict[str, Any]:
    """Mean, CVaR_alpha, quantiles and the stored quantile function of per-episode costs.

    Returns
    -------
    dict with ``mean, cvar, alpha, median, q90, min, max, n_episodes``, ``ess`` (the
    weights' effective number of episodes; ``n_episodes`` unweighted), ``quantiles``
    (``{"levels": QUANTILE_LEVELS, "values": [...]}``), ``source`` and ``method``.
    """
    c, w = _prepare(costs, weights)
    q = weighted_quantiles(c, QUANTILE_LEVELS, w)
    med, q90 = weighted_quantiles(c, [0.5, 0.9], w)
    return {"mean": float(np.sum(w * c)), "cvar": cvar(c, alpha, w), "alpha": float(alpha), "median": float(med),
            "q90": float(q90), "min": float(q[0]), "max": float(q[-1]), "n_episodes": int(len(c)),
            "ess": float(1.0 / np.sum(w**2)), "quantiles": {"levels": list(QUANTILE_LEVELS), "values": q.tolist()},
            "source": source, "method": method}


def weighted_policy_distribution(G: np.ndarray, W: np.ndarray, *, alpha: float = CVAR_ALPHA,
                                 groups: np.ndarray | None = None, comparable: bool = True) -> dict[str, Any]:
    """The policy's episode-cost distribution from logs alone: logged episode costs ``G``
    re-weighted by the per-episode importance weights ``W`` (self-normalised), when the
    weights are usable; else ``{"usable": False, "reason": ...}`` (cannot tell).

    Usable means: ``W`` not degenerate (ESS at least 1% of the episodes) and none of the
    reasons of :func:`~offline_adp.evaluation.ope.interval_unreliable` (normalised weights)."""
    from offline_adp.evaluation import ope

    W = np.asarray(W, dtype=np.float64)
    if not comparable:
        return {"usable": False, "reason": "the estimand reaches past the logged episodes: the logged costs do not "
                "hold it", "source": "logs (importance-weighted)"}
    if not np.isfinite(W).all() or W.sum() <= 0:
        return {"usable": False, "reason": "every importance weight is 0: no logged episode takes only actions the "
                "policy could take", "ess": 0.0, "source": "logs (importance-weighted)"}
    d = ope.weight_diagnostics(W, groups)
    why = ope.interval_unreliable(d, normalised=True)
    if d["ess_fraction"] < ope.MIN_ESS_FRACTION and not why:
        why = [f"effective sample size {d['ess']:.1f} of {d['n']} episodes: the weights are degenerate"]
    if why:
        return {"usable": False, "reason": "; ".join(why), "ess": float(d["ess"]),
                "source": "logs (importance-weighted)"}
    out = distribution_summary(G, weights=W, alpha=alpha, source="logs (importance-weighted)",
                               method="logged episode costs weighted by the per-episode importance weights "
                                      "prod_t pi/pi_b, self-normalised (the distribution whose mean is WIS)")
    return {"usable": True, **out}
