"""Batched Monte-Carlo evaluation of a policy on a simulator (reset model or stronger).

All episodes advance together: one batched ``policy.act`` and one batched ``step`` per
time step, never a per-state Python loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from offline_adp.access import ResetModel
from offline_adp.parallel import TaskMap, local_map
from offline_adp.policies import Policy


@dataclass(frozen=True)
class RolloutResult:
    """Per-episode discounted costs and outcomes.

    Attributes
    ----------
    discounted_cost : ndarray (n_episodes,)
    total_cost : ndarray (n_episodes,)
        Undiscounted sum of costs.
    length : ndarray (n_episodes,)
    terminated : ndarray of bool (n_episodes,)
    states : list of ndarray, optional
        ``states[t]``: the states of the episodes still running at step t (pi's
        Monte-Carlo ``mu_t``; they feed the classifier density ratios).
    """

    discounted_cost: np.ndarray
    total_cost: np.ndarray
    length: np.ndarray
    terminated: np.ndarray
    states: list[np.ndarray] | None = None

    @property
    def mean(self) -> float:
        return float(self.discounted_cost.mean())

    def interval(self, level: float = 0.95) -> tuple[float, float]:
        """Normal-approximation confidence interval of the mean discounted cost."""
        from scipy.stats import norm

        n = len(self.discounted_cost)
        half = norm.ppf(0.5 + level / 2) * self.discounted_cost.std(ddof=1) / np.sqrt(n) if n > 1 else np.inf
        return self.mean - half, self.mean + half


def rollout(
    model: ResetModel,
    policy: Policy,
    n_episodes: int,
    rng: np.random.Generator,
    *,
    horizon: int | None = None,
    gamma: float | None = None,
    start_states: np.ndarray | None = None,
    record_states: bool = False,
) -> RolloutResult:
    """Run ``n_episodes`` episodes of ``policy`` for at most ``horizon`` steps.

    With ``record_states`` the result keeps every step's states (memory: n x H x d).
    """
    H = horizon if horizon is not None else model.horizon
    if H is None:
        raise ValueError("rollout needs a horizon (the model has none)")
    g = model.gamma if gamma is None else gamma
    x = model.initial_states(n_episodes, rng) if start_states is None else np.array(start_states, dtype=np.float64)
    n = len(x)
    disc, total = np.zeros(n), np.zeros(n)
    length = np.zeros(n, np.int64)
    term = np.zeros(n, bool)
    alive = np.ones(n, bool)
    states: list[np.ndarray] = []
    for t in range(H):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        if record_states:
            states.append(x[idx].copy())
        a = policy.act_index(x[idx], t, rng)
        r = model.step(x[idx], a, rng)
        disc[idx] += g**t * r.costs
        total[idx] += r.costs
        length[idx] += 1
        x[idx] = r.next_states
        term[idx] = r.terminated
        alive[idx[r.terminated]] = False
    return RolloutResult(disc, total, length, term, states if record_states else None)


def _rollout_piece(piece: tuple[np.ndarray, list[int]], *, model: ResetModel, policies: dict[str, Policy],
                   horizon: int | None, gamma: float | None, record_states: bool) -> dict[str, RolloutResult]:
    x0, seed = piece
    return {name: rollout(model, pol, len(x0), np.random.default_rng(seed), horizon=horizon, gamma=gamma,
                          start_states=x0, record_states=record_states) for name, pol in policies.items()}


def _merge(results: list[RolloutResult], record_states: bool) -> RolloutResult:
    cat = lambda name: np.concatenate([getattr(r, name) for r in results])  # noqa: E731
    states = None
    if record_states:
        H = max(len(r.states or []) for r in results)
        states = [np.concatenate([r.states[t] for r in results if r.states is not None and len(r.states) > t])
                  for t in range(H)]
    return RolloutResult(cat("discounted_cost"), cat("total_cost"), cat("length"), cat("terminated"), states)


def rollout_pieces(
    model: ResetModel,
    policies: dict[str, Policy],
    start_states: np.ndarray,
    seed: int,
    *,
    horizon: int | None = None,
    gamma: float | None = None,
    record_states: bool = False,
    n_pieces: int = 8,
    task_map: TaskMap | None = None,
    on_done: Callable[[int], None] | None = None,
) -> dict[str, RolloutResult]:
    """Roll out several policies from the same start states with common random numbers,
    split into ``n_pieces`` pieces of episodes (seed ``[seed, k]`` for piece k, shared by
    all policies) that ``task_map`` may run anywhere, e.g. on Dask workers
    (:class:`offline_adp.distributed.DaskTaskMap`). The split does not depend on the
    engine, so local and distributed runs give identical results.
    """
    pieces = [(x0, [seed, k]) for k, x0 in enumerate(np.array_split(np.asarray(start_states, dtype=np.float64), n_pieces))
              if len(x0)]
    run = task_map or local_map
    out = run(_rollout_piece, pieces, shared={"model": model, "policies": policies, "horizon": horizon, "gamma": gamma,
                                              "record_states": record_states}, on_done=on_done)
    return {name: _merge([o[name] for o in out], record_states) for name in policies}
