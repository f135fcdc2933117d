"""FQE's support bounds: what the logs cannot tell about a policy's value through the
fitted structure (docs/evaluation.md, section 2). The FQE interval of
:func:`~offline_adp.evaluation.offpolicy.off_policy` is widened to contain them."""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.algorithms.fqe import FittedQEvaluation
from offline_adp.data.dataset import TransitionDataset

#: The support bounds' radius: a row of the queried action counts when it is at most as far from
#: the queried state as 99% of the logged states are from their nearest same-action neighbour.
SUPPORT_RADIUS_QUANTILE = 0.99


def q_value_range(cost: np.ndarray, terminated: np.ndarray, gamma: float,
                  infeasible_cost: float | None = None) -> tuple[float, float]:
    """Bounds on any discounted value ``Q(x, a)`` if the costs of unseen pairs lie in the
    logged ranges: with non-terminal costs in ``[c_lo, c_hi]`` and costs of terminating
    steps in ``[k_lo, k_hi]``, any path's value lies in
    ``[min(c_lo / (1 - gamma), k_lo), max(c_hi / (1 - gamma), k_hi)]`` (its value after k
    non-terminal steps then a terminating one is monotone in k); the upper end capped at
    the fit's ``infeasible_cost`` clamp."""
    cost = np.asarray(cost, dtype=np.float64)
    term = np.asarray(terminated, dtype=bool)
    lo, hi = np.inf, -np.inf
    if (~term).any():
        lo, hi = float(cost[~term].min()) / (1.0 - gamma), float(cost[~term].max()) / (1.0 - gamma)
    if term.any():
        lo, hi = min(lo, float(cost[term].min())), max(hi, float(cost[term].max()))
    if infeasible_cost is not None:
        hi = min(hi, float(infeasible_cost))
    return lo, hi


def fqe_support_bounds(fqe: FittedQEvaluation, ds: TransitionDataset, seed: int = 0) -> dict[str, Any]:
    """What the logs cannot tell about the policy's value through the fitted structure:
    the value of its *per-action read* (:func:`~offline_adp.algorithms.fqe_bootstrap.support_operators`:
    only rows of the queried action, within the data's own spacing of the queried state)
    with every pair the logs hold no such row for valued at the lowest and then the highest
    value the cost range allows (:func:`q_value_range`). The FQE interval is widened to
    contain both."""
    from offline_adp.algorithms.fqe_bootstrap import support_radius

    d = fqe.fit_state_.data
    a = ds.arrays()
    radius = support_radius(d.obs, np.asarray(d.train.actions), d.obs_std, SUPPORT_RADIUS_QUANTILE, seed=seed)
    lo_q, hi_q = q_value_range(a.cost, a.terminated, d.gamma, getattr(fqe, "infeasible_cost", None))
    sb = fqe.support_bounds(lo_q, hi_q, radius=radius)
    return {**sb, "value_range": [lo_q, hi_q], "radius": radius, "radius_quantile": SUPPORT_RADIUS_QUANTILE,
            "method": "per-action read of the fitted trees (rows of the queried action within the data's own "
                      f"{SUPPORT_RADIUS_QUANTILE:.0%} nearest-neighbour spacing of the queried state), unsupported "
                      "pairs valued at the ends of the cost's value range"}
