"""The two-state divergence example (Tsitsiklis & Van Roy), as told in the chapter.

Both states move to S2, all costs are zero, gamma = 0.9, and the value is linear,
``V(s) = w * x(s)`` with ``x(S1) = 1``, ``x(S2) = 2``. Start from ``w = 1``. One fitted
value backup computes the targets ``gamma * V(S2) = 0.9 * 2 * w = 1.8 w`` for both
samples and refits ``w`` by least squares:

- unweighted: ``w' = (1.8 w * 1 + 1.8 w * 2) / (1^2 + 2^2) = 5.4 w / 5 = 1.08 w``, i.e.
  ``w`` is multiplied by ``6 gamma / 5`` every backup and diverges geometrically although
  the true value is 0. (The chapter's text says ``w = 1.2`` after one backup; that is an
  arithmetic slip: ``(1.8 * 1 + 1.8 * 2) / (1 + 4) = 1.08``.)
- on-policy weighting (the time the chain spends in each state from S1: 1 step in S1,
  ``gamma / (1 - gamma) = 9`` discounted steps in S2):
  ``w' = (1 * 1 * 1.8 w + 9 * 2 * 1.8 w) / (1 * 1 + 9 * 4) = 34.2 w / 37 = 0.924 w``,
  which converges to 0.

Both runs go through :class:`~offline_adp.algorithms.fqe.FittedQEvaluation` with a
linear learner on the chapter's feature; the divergence monitor flags the first.

Run ``python -m offline_adp.examples.two_state`` to print both sequences of ``w``.
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.linear_model import LinearRegression
from sklearn.preprocessing import FunctionTransformer

from offline_adp.algorithms.fqe import FittedQEvaluation, on_policy_weights
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs.two_state import TwoState, feature
from offline_adp.policies import UniformPolicy
from offline_adp.qfunctions import FunctionQ

GAMMA = 0.9


def dataset() -> TransitionDataset:
    """One transition from each state: S1 -> S2 and S2 -> S2, cost 0."""
    m = TwoState(gamma=GAMMA)
    return TransitionDataset.from_arrays(
        m.dataset_info(), episode_id=["s1", "s2"], step=[0, 0], obs=[[0.0], [1.0]], action=[0, 0], cost=[0.0, 0.0],
        next_obs=[[1.0], [1.0]], terminated=[False, False], truncated=[True, True],
    )


def run(weighted: bool, n_backups: int = 10, w0: float = 1.0) -> tuple[list[float], FittedQEvaluation]:
    """``w`` after each fitted backup, and the fitted evaluator (its monitor's verdict)."""
    ds = dataset()
    fqe = FittedQEvaluation(
        policy=UniformPolicy(1), gamma=GAMMA, regressor=LinearRegression(fit_intercept=False),
        feature_map=FunctionTransformer(feature), action_encoding="per_action", n_iterations=n_backups,
        initial_q=FunctionQ(lambda obs, t: w0 * feature(obs), 1), on_divergence="warn",
    )
    # occupancy from S1 (discounted steps): S1 once, S2 gamma / (1 - gamma) times
    w = on_policy_weights(ds.arrays().obs[:, 0], np.array([1.0, GAMMA / (1 - GAMMA)])) if weighted else None
    ws = [float(fqe.q_function_.models[0].coef_[0]) for _ in fqe.fit_iter(ds, sample_weight=w)]
    return ws, fqe


if __name__ == "__main__":
    for weighted in (False, True):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ws, fqe = run(weighted)
        name = "on-policy weighted" if weighted else "unweighted"
        print(f"{name:>18}: w = " + ", ".join(f"{w:.4f}" for w in ws))
        for c in caught:
            print(f"{'':>18}  {c.category.__name__}: {c.message}")
