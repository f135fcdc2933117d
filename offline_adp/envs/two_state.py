"""The two-state example of Tsitsiklis & Van Roy (1996), as told in the chapter.

Two states, one action; both states move to S2; all costs zero; gamma = 0.9. The
value is approximated linearly, ``V(s) = w * x(s)`` with feature ``x(S1) = 1``,
``x(S2) = 2``. The true value is 0 everywhere, but unweighted least-squares fitted
value iteration multiplies ``w`` by ``6 gamma / 5`` per backup and diverges, while
on-policy weighting converges (see the FQE example).

Observations are the state index ``s`` (S1 = 0, S2 = 1); the feature is
:func:`feature` ``x = s + 1``.
"""

from __future__ import annotations

import numpy as np

from offline_adp.access import FullModel
from offline_adp.data.info import ActionTable, Feature
from offline_adp.envs.base import ReferenceProblem


def feature(s: np.ndarray) -> np.ndarray:
    """The chapter's feature x(S1) = 1, x(S2) = 2 of state indices, shape (n, 1)."""
    return np.asarray(s, dtype=np.float64).reshape(-1, 1) + 1.0


class TwoState(ReferenceProblem, FullModel):
    """Tsitsiklis & Van Roy's two-state chain as a full model."""

    name = "two_state"
    features = (Feature("s", "", "state index: 0 = S1, 1 = S2 (chapter feature x = s + 1)"),)
    action_table = ActionTable.from_values([0.0], names=["stay"], dims=("a",))

    def __init__(self, gamma: float = 0.9, horizon: int | None = 20) -> None:
        P = np.array([[[0.0, 1.0], [0.0, 1.0]]])
        C = np.zeros((2, 1))
        super().__init__(P, C, np.array([0.5, 0.5]), gamma=gamma, horizon=horizon)
