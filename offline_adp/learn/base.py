"""What every LEARN step is built from (:class:`LearnSpec`) and its interface (:class:`Learner`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.qfunctions import QEncoder, QFunction

#: a query set: regression inputs ``phi`` and the action per row (None: all actions)
Query = tuple[np.ndarray, np.ndarray | None]


@dataclass(frozen=True, eq=False)
class LearnSpec:
    """The inputs of a LEARN step: the training pairs and every query set the loop reads.

    Parameters
    ----------
    regressor : estimator
        The (unfitted) scikit-learn regressor LEARN clones.
    encoder : QEncoder
        How observations and actions become regression inputs.
    phi : ndarray (n, d)
        ``phi(x_i)`` of the training pairs.
    actions : ndarray (n,)
        ``a_i`` of the training pairs.
    queries : mapping of str to (phi, actions or None)
        Named query sets (``"next"``: next states, all actions; ``"start"``; held-out
        pairs); ``"train"`` (the training pairs) is added by the learner.
    weights : ndarray (n,), optional
        Per-row sample weights.
    seed : int
        Iteration ``k`` seeds its regressor with ``seed + k``.
    """

    regressor: Any
    encoder: QEncoder
    phi: np.ndarray
    actions: np.ndarray
    queries: Mapping[str, Query]
    weights: np.ndarray | None = None
    seed: int = 0


def seeded(model: Any, seed: int) -> Any:
    """``model`` with ``random_state=seed`` where it has one."""
    if "random_state" in model.get_params():
        model.set_params(random_state=seed)
    return model


def fit_model(model: Any, X: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> Any:
    """``model.fit(X, y)`` with sample weights ``w`` (routed to a pipeline's last step)."""
    if w is None:
        return model.fit(X, y)
    try:
        return model.fit(X, y, sample_weight=w)
    except TypeError:  # pipelines route weights by step name
        last = model.steps[-1][0]
        return model.fit(X, y, **{f"{last}__sample_weight": w})


class Learner:
    """Base: training pairs ``(phi, actions)``, weights, and named query sets (from a :class:`LearnSpec`)."""

    def __init__(self, spec: LearnSpec) -> None:
        self.spec = spec
        self.regressor, self.encoder = spec.regressor, spec.encoder
        # continuous commands (a CommandEncoder): each pair's command vector, else action indices
        self.phi = spec.phi
        self.actions = (np.asarray(spec.actions, dtype=np.float64) if spec.encoder.continuous
                        else np.asarray(spec.actions, dtype=np.int64))
        self.weights, self.seed = spec.weights, spec.seed
        self.queries: dict[str, Query] = {"train": (self.phi, self.actions), **spec.queries}

    def fit(self, y: np.ndarray, k: int) -> None:
        """``Q_k = LEARN({((x_i, a_i), y_i)})``; iteration ``k``'s randomness depends on ``k`` only."""
        raise NotImplementedError

    def predict(self, name: str) -> np.ndarray:
        raise NotImplementedError

    def support(self, name: str) -> np.ndarray | None:
        """The current Q's :meth:`~offline_adp.qfunctions.QFunction.support` on the query
        set ``name`` (all actions per row), or None: every action (no Q yet, or a Q that is
        not made of lookup tables)."""
        return None

    def snapshot(self) -> QFunction:
        """The current Q as a standalone Q-function."""
        raise NotImplementedError

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        """Continue from a saved ``Q_k`` (iteration ``k`` done; ``rows``: the history 1..k)."""
        raise NotImplementedError(f"{type(self).__name__} cannot resume")

    def state(self) -> dict[str, Any]:
        """Extra per-iteration facts for the history row (e.g. the structures built)."""
        return {}

    def _joint(self, phi: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        """Joint regression inputs of a query set: every action per row (action-major) or the given ones."""
        return self.encoder.all_pairs(phi) if actions is None else self.encoder.pairs(phi, actions)

    @staticmethod
    def _select(q_all: np.ndarray, actions: np.ndarray | None) -> np.ndarray:
        return q_all if actions is None else q_all[np.arange(len(actions)), actions]
