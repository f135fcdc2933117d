"""Seeded random finite MDPs exposing the full model (the oracle's playground).

Each (s, a) moves to ``branching`` successor states drawn at random, with Dirichlet(1)
probabilities; expected costs are uniform on [0, 1]; the start distribution is
Dirichlet(1) over states. Observations are the state index ``s``.
"""

from __future__ import annotations

import numpy as np

from offline_adp import dp
from offline_adp.access import FullModel
from offline_adp.data.info import ActionTable, Feature
from offline_adp.envs.base import ReferenceProblem
from offline_adp.policies import EpsilonPolicy, Policy, TabularPolicy


class TabularMDP(ReferenceProblem, FullModel):
    """A random finite MDP.

    Parameters
    ----------
    n_states, n_actions : int
    horizon : int or None
        Finite horizon T (with ``gamma`` 1 by default) or None for a discounted MDP.
    gamma : float, optional
        Defaults to 1.0 with a horizon, 0.9 without.
    branching : int
        Successors per (s, a).
    seed : int
    """

    name = "tabular"
    features = (Feature("s", "", "state index"),)

    def __init__(
        self,
        n_states: int = 30,
        n_actions: int = 3,
        horizon: int | None = 10,
        gamma: float | None = None,
        branching: int = 5,
        seed: int = 0,
    ) -> None:
        rng = np.random.default_rng(seed)
        P = np.zeros((n_actions, n_states, n_states))
        k = min(branching, n_states)
        for a in range(n_actions):
            for s in range(n_states):
                succ = rng.choice(n_states, size=k, replace=False)
                P[a, s, succ] = rng.dirichlet(np.ones(k))
        C = rng.random((n_states, n_actions))
        mu0 = rng.dirichlet(np.ones(n_states))
        if gamma is None:
            gamma = 1.0 if horizon is not None else 0.9
        self.action_table = ActionTable.from_values(np.arange(n_actions, dtype=float),
                                                    names=[f"a{i}" for i in range(n_actions)])
        self.seed = seed
        super().__init__(P, C, mu0, gamma=gamma, horizon=horizon)

    def optimal(self) -> dp.DPSolution:
        """Exact optimal solution (finite horizon if ``horizon`` is set, else discounted)."""
        if self.horizon is not None:
            return dp.value_iteration_finite(self.P, self.C, self.horizon, self.gamma)
        return dp.value_iteration_discounted(self.P, self.C, self.gamma)

    def demonstrator(self, epsilon: float = 0.3) -> Policy:
        """The optimal policy with ``epsilon`` uniformly random actions."""
        return EpsilonPolicy(TabularPolicy(self.optimal().policy, self.n_actions), epsilon)
