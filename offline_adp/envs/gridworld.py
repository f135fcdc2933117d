"""Boyan & Moore (1995) continuous 2-D gridworld, the chapter's divergence example.

State ``(x, y)`` in [0, 1]^2; four compass moves of 0.05 (clipped at the walls); goal
at the corner (1, 1), absorbing; cost 0.5 per step; undiscounted. States live on the
0.05 lattice (start states are drawn from it and moves keep them there), where the
optimal cost-to-go is exactly linear in the L1 distance to the goal::

    J*(x, y) = 0.5 * ((1 - x) + (1 - y)) / 0.05 = 20 - 10 (x + y)

Boyan, J. & Moore, A. (1995), "Generalization in reinforcement learning: safely
approximating the value function", NIPS 7.
"""

from __future__ import annotations

import numpy as np

from offline_adp.access import FullModel, Simulator, StepResult
from offline_adp.data.info import ActionTable, Feature
from offline_adp.envs.base import ReferenceProblem
from offline_adp.policies import EpsilonPolicy, FunctionPolicy, Policy

STEP = 0.05
N_CELLS = 21  # lattice points per axis: 0, 0.05, ..., 1
STEP_COST = 0.5
MOVES = np.array([[0.0, STEP], [STEP, 0.0], [0.0, -STEP], [-STEP, 0.0]])


def optimal_cost_to_go(xy: np.ndarray) -> np.ndarray:
    """J*(x, y) = 20 - 10 (x + y) on the lattice."""
    xy = np.asarray(xy).reshape(-1, 2)
    return STEP_COST * ((1 - xy[:, 0]) + (1 - xy[:, 1])) / STEP


class Gridworld(ReferenceProblem, Simulator):
    """The gridworld as a deterministic simulator, with its lattice :meth:`full_model`."""

    name = "gridworld"
    features = (Feature("x", "", "east coordinate"), Feature("y", "", "north coordinate"))
    action_table = ActionTable.from_values(MOVES, names=["N", "E", "S", "W"], dims=("dx", "dy"))
    gamma = 1.0
    n_actions = 4
    obs_dim = 2

    def __init__(self, horizon: int | None = 200) -> None:
        self.horizon = horizon

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        k = rng.integers(0, N_CELLS * N_CELLS - 1, size=n)  # every lattice point but the goal
        return np.column_stack([k // N_CELLS, k % N_CELLS]).astype(np.float64) * STEP

    def step_seeded(self, states: np.ndarray, actions: np.ndarray, seed: int = 0) -> StepResult:
        x = np.asarray(states, dtype=np.float64).reshape(-1, 2)
        nxt = np.clip(np.round((x + MOVES[np.asarray(actions, dtype=np.int64)]) / STEP) * STEP, 0.0, 1.0)
        goal = (nxt >= 1.0 - 1e-9).all(axis=1)
        return StepResult(nxt, np.full(len(x), STEP_COST), goal)

    def demonstrator(self) -> Policy:
        """Head for the goal along the longer remaining axis, with 10% random moves."""
        greedy = FunctionPolicy(lambda x, t: np.where(1 - x[:, 0] > 1 - x[:, 1] + 1e-9, 1, 0), 4, name="toward_goal")
        return EpsilonPolicy(greedy, 0.1)

    def full_model(self) -> FullModel:
        """The lattice MDP: state ``k = i * 21 + j`` is ``(0.05 i, 0.05 j)``; goal absorbing."""
        S = N_CELLS * N_CELLS
        ij = np.stack(np.meshgrid(np.arange(N_CELLS), np.arange(N_CELLS), indexing="ij"), -1).reshape(-1, 2)
        P = np.zeros((4, S, S))
        C = np.full((S, 4), STEP_COST)
        goal = S - 1
        for a in range(4):
            nij = np.clip(ij + np.round(MOVES[a] / STEP).astype(int), 0, N_CELLS - 1)
            P[a, np.arange(S), nij[:, 0] * N_CELLS + nij[:, 1]] = 1.0
        P[:, goal, :] = 0.0
        P[:, goal, goal] = 1.0
        C[goal] = 0.0
        mu0 = np.ones(S) / (S - 1)
        mu0[goal] = 0.0
        terminal = np.zeros(S, bool)
        terminal[goal] = True
        return FullModel(P, C, mu0, gamma=1.0, horizon=self.horizon, terminal=terminal)

    @staticmethod
    def lattice_states() -> np.ndarray:
        """(x, y) of lattice state k = i * 21 + j, shape (441, 2)."""
        ij = np.stack(np.meshgrid(np.arange(N_CELLS), np.arange(N_CELLS), indexing="ij"), -1).reshape(-1, 2)
        return ij * STEP
