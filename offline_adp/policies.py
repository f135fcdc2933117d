"""Policies: ``probabilities(obs, t) -> (n, n_actions)`` and ``act(obs, t, rng)``.

Everything is batched over rows of ``obs`` (shape (n, d)); ``t`` is the time step, a
scalar or one per row. Deterministic policies return one-hot probabilities, so density
ratios and mixtures treat every policy alike.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import numpy as np

TimeArg = int | np.ndarray


class Policy(ABC):
    """A (possibly stochastic, possibly time-varying) policy over a finite action set."""

    n_actions: int

    @abstractmethod
    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """Action probabilities, shape (n, n_actions), rows summing to 1."""

    def act(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        """Sample one action per row (inverse CDF, vectorised)."""
        rng = rng if rng is not None else np.random.default_rng()
        p = self.probabilities(obs, t)
        u = rng.random(p.shape[0])
        return np.minimum((u[:, None] >= np.cumsum(p, axis=1)).sum(axis=1), self.n_actions - 1).astype(np.int32)


class DeterministicPolicy(Policy):
    """A policy that picks one action per (obs, t); ``probabilities`` are one-hot."""

    @abstractmethod
    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """The chosen action per row, shape (n,) int."""

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        a = self.actions(obs, t)
        p = np.zeros((len(a), self.n_actions))
        p[np.arange(len(a)), a] = 1.0
        return p

    def act(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        return np.asarray(self.actions(obs, t), dtype=np.int32)


class FunctionPolicy(DeterministicPolicy):
    """Deterministic policy from a vectorised function ``fn(obs, t) -> actions``."""

    def __init__(self, fn: Callable[[np.ndarray, TimeArg], np.ndarray], n_actions: int, name: str = "") -> None:
        self.fn, self.n_actions, self.name = fn, n_actions, name

    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.asarray(self.fn(np.asarray(obs), t), dtype=np.int32)


class StochasticFunctionPolicy(Policy):
    """Stochastic policy from a vectorised function ``fn(obs, t) -> probabilities``."""

    def __init__(self, fn: Callable[[np.ndarray, TimeArg], np.ndarray], n_actions: int, name: str = "") -> None:
        self.fn, self.n_actions, self.name = fn, n_actions, name

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.asarray(self.fn(np.asarray(obs), t), dtype=np.float64)


class UniformPolicy(Policy):
    """Uniformly random actions (exploration)."""

    def __init__(self, n_actions: int) -> None:
        self.n_actions = n_actions

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.full((np.asarray(obs).shape[0], self.n_actions), 1.0 / self.n_actions)


class EpsilonPolicy(Policy):
    """``(1 - epsilon) * base + epsilon * uniform``: a noisy version of ``base``."""

    def __init__(self, base: Policy, epsilon: float) -> None:
        if not 0.0 <= epsilon <= 1.0:
            raise ValueError(f"epsilon must be in [0, 1], got {epsilon}")
        self.base, self.epsilon, self.n_actions = base, float(epsilon), base.n_actions

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return (1.0 - self.epsilon) * self.base.probabilities(obs, t) + self.epsilon / self.n_actions


class TabularPolicy(Policy):
    """Policy over a finite state space given as a table; obs are ``[[s]]`` indices.

    Parameters
    ----------
    table : ndarray
        ``(S,)`` or ``(T, S)`` int actions, or ``(S, A)`` / ``(T, S, A)`` probabilities.
        With a leading T axis the policy is time-varying (non-stationary); a step
        ``t >= T`` uses the last row.
    n_actions : int, optional
        Needed when ``table`` holds actions.
    """

    def __init__(self, table: np.ndarray, n_actions: int | None = None) -> None:
        table = np.asarray(table)
        if np.issubdtype(table.dtype, np.integer):
            if n_actions is None:
                raise ValueError("n_actions is required for a table of actions")
            table = np.eye(n_actions)[table]
        self.table = table.astype(np.float64)
        self.n_actions = self.table.shape[-1]
        self.time_varying = self.table.ndim == 3

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        s = np.asarray(obs).reshape(len(obs), -1)[:, 0].astype(np.int64)
        if not self.time_varying:
            return self.table[s]
        tt = np.minimum(np.broadcast_to(np.asarray(t), s.shape), self.table.shape[0] - 1)
        return self.table[tt, s]


class GreedyPolicy(DeterministicPolicy):
    """``pi(x, t) = argmin_a Q(x, a, t)``: greedy with respect to a cost Q-function.

    Ties go to the lowest action index.
    """

    def __init__(self, q: object) -> None:
        self.q = q
        self.n_actions = q.n_actions  # type: ignore[attr-defined]

    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.argmin(self.q.values(np.asarray(obs), t), axis=1).astype(np.int32)  # type: ignore[attr-defined]


class MixturePolicy(Policy):
    """``sum_k w_k pi_k``: at each time step a component is drawn with probability
    ``w_k`` and acts (so the action probabilities are the weighted sum). Conservative
    policy iteration builds these; the components and weights are kept.
    """

    def __init__(self, components: list[Policy], weights: list[float] | np.ndarray) -> None:
        w = np.asarray(weights, dtype=np.float64)
        if len(components) != len(w) or not len(w):
            raise ValueError("a mixture needs one weight per component")
        if (w < 0).any() or not np.isclose(w.sum(), 1.0):
            raise ValueError(f"mixture weights must be >= 0 and sum to 1, got {w}")
        self.components, self.weights = list(components), w
        self.n_actions = components[0].n_actions

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return sum(w * c.probabilities(obs, t) for w, c in zip(self.weights, self.components, strict=True) if w > 0)

    def mix(self, other: Policy, alpha: float) -> MixturePolicy:
        """``alpha * other + (1 - alpha) * self`` (flattened)."""
        return MixturePolicy([*self.components, other], [*((1 - alpha) * self.weights), alpha])


class NonStationaryPolicy(Policy):
    """One policy per time step (PSDP's ``pi_0, ..., pi_{T-1}``); steps >= T use the last."""

    def __init__(self, steps: list[Policy]) -> None:
        self.steps, self.n_actions = list(steps), steps[0].n_actions
        self.time_varying = True

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        from offline_adp.qfunctions import per_step

        return per_step(obs, t, len(self.steps), self.n_actions, lambda k, x: self.steps[k].probabilities(x, k))


def apply_feature_map(feature_map: Any, obs: np.ndarray) -> np.ndarray:
    """``feature_map(obs)`` (a callable or a fitted transformer), or ``obs`` itself."""
    obs = np.asarray(obs, dtype=np.float64)
    if feature_map is None:
        return obs
    return np.asarray(feature_map.transform(obs) if hasattr(feature_map, "transform") else feature_map(obs), dtype=np.float64)


class ClassifierPolicy(DeterministicPolicy):
    """A deterministic policy that predicts the action with a fitted classifier
    (on ``feature_map(obs)`` when a feature map is given); PSDP's per-step policies."""

    def __init__(self, classifier: Any, n_actions: int, constant: int | None = None, feature_map: Any = None) -> None:
        self.classifier, self.n_actions, self.constant, self.feature_map = classifier, n_actions, constant, feature_map

    def actions(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        if self.constant is not None:
            return np.full(len(obs), self.constant, np.int32)
        return np.asarray(self.classifier.predict(apply_feature_map(self.feature_map, obs)), dtype=np.int32)
