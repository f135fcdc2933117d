"""Car on the hill, exactly as in Ernst, Geurts & Wehenkel (2005), JMLR 6, Appendix.

State ``(p, s)``: position and speed. Dynamics (m = 1, g = 9.81)::

    p' = s
    s' = u / (m (1 + H'(p)^2)) - g H'(p) / (1 + H'(p)^2) - s^2 H'(p) H''(p) / (1 + H'(p)^2)
    H(p) = p^2 + p            (p < 0)
         = p / sqrt(1 + 5 p^2)  (p >= 0)

integrated by Euler steps of 0.001 s inside each 0.1 s control step, u in {-4, +4}.
Reward +1 on leaving at p > 1 with |s| <= 3, -1 on p < -1 or |s| > 3, 0 otherwise; the
state after leaving is terminal; gamma = 0.95. This library minimises ``cost = -reward``.
The paper's score is the mean discounted return over the 289 start states
``(0.125 i, 0.375 j)``, i, j in -8..8.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.access import Simulator, StepResult
from offline_adp.data.info import ActionTable, Feature
from offline_adp.envs.base import ReferenceProblem
from offline_adp.policies import EpsilonPolicy, FunctionPolicy, Policy
from offline_adp.rollout import rollout

M, G = 1.0, 9.81
DT_CONTROL, DT_EULER = 0.1, 0.001
N_EULER = 100  # 0.1 / 0.001


def hill_slopes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H'(p) and H''(p)."""
    neg = p < 0
    q = 1.0 + 5.0 * p * p
    d1 = np.where(neg, 2.0 * p + 1.0, q**-1.5)
    d2 = np.where(neg, 2.0, -15.0 * p * q**-2.5)
    return d1, d2


class CarOnHill(ReferenceProblem, Simulator):
    """Car on the hill (Ernst et al. 2005); deterministic, so a :class:`Simulator`."""

    name = "car_on_hill"
    features = (Feature("p", "m", "position"), Feature("s", "m/s", "speed"))
    action_table = ActionTable.from_values([-4.0, 4.0], names=["push_left", "push_right"], dims=("u",), units=("N",))
    gamma = 0.95
    n_actions = 2
    obs_dim = 2

    def __init__(self, horizon: int | None = 100, start: tuple[float, float] = (-0.5, 0.0)) -> None:
        self.horizon = horizon
        self.start = np.asarray(start, dtype=np.float64)

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return np.tile(self.start, (n, 1))

    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int = 0) -> StepResult:
        x = np.asarray(states, dtype=np.float64).reshape(-1, 2)
        u = self.action_table.values[np.asarray(actions, dtype=np.int64), 0]
        p, s = x[:, 0].copy(), x[:, 1].copy()
        for _ in range(N_EULER):
            d1, d2 = hill_slopes(p)
            den = 1.0 + d1 * d1
            acc = u / (M * den) - G * d1 / den - s * s * d1 * d2 / den
            p, s = p + DT_EULER * s, s + DT_EULER * acc
        lose = (p < -1.0) | (np.abs(s) > 3.0)
        win = (p > 1.0) & (np.abs(s) <= 3.0)
        reward = np.where(lose, -1.0, np.where(win, 1.0, 0.0))
        return StepResult(np.column_stack([p, s]), 0.0 - reward, lose | win)  # 0.0 - 0.0 is +0.0, not -0.0

    map_features = ("p", "s")

    def named_scores(self, policy: Policy) -> dict[str, dict[str, Any]]:
        return {"car_on_hill_score": {"value": score(policy), "method": "Ernst et al. (2005): mean discounted return "
                                      "over the 289-state grid (higher is better)"}}

    def demonstrator(self) -> Policy:
        """Energy pumping with limits, plus 10% random pushes.

        Push in the direction of motion, but push right near the left edge (p < -0.6)
        and brake when faster than 2.5 m/s.
        """

        def pump(x: np.ndarray, t: object) -> np.ndarray:
            return np.where(x[:, 0] < -0.6, 1, np.where(x[:, 1] > 2.5, 0, x[:, 1] >= 0)).astype(np.int32)

        return EpsilonPolicy(FunctionPolicy(pump, 2, name="pump"), 0.1)


def score_grid() -> np.ndarray:
    """The 289 start states of Ernst et al.'s score, shape (289, 2)."""
    i, j = np.meshgrid(np.arange(-8, 9), np.arange(-8, 9), indexing="ij")
    return np.column_stack([0.125 * i.ravel(), 0.375 * j.ravel()])


def score(policy: Policy, max_steps: int = 1000) -> float:
    """Mean discounted return over the 289-state grid (higher is better).

    Rolls out all 289 start states in one batch until termination (or ``max_steps``;
    0.95^1000 is negligible).
    """
    prob = CarOnHill(horizon=None)
    res = rollout(prob, policy, 0, np.random.default_rng(0), horizon=max_steps, gamma=prob.gamma,
                  start_states=score_grid(), step=lambda x, a, rng: prob.step_seeded(x, a))
    return float(-res.mean)
