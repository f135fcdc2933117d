"""Scoring a command policy in a gymnasium environment: numpy and gymnasium only, so the
peers' own virtual environments (``benchmarks/continuous_vs_d3rlpy.py``'s d3rlpy worker)
score with the same code as ours (``benchmarks/continuous_commands.py``)."""

from __future__ import annotations

import numpy as np


def returns(env_id: str, command, n_episodes: int, low=None, high=None) -> tuple[np.ndarray, float]:
    """Each episode's return (episodes seeded 10_000 + i, stepped together) and the mean
    ``|u_t - u_{t-1}|`` per step; ``command(obs (n, d), t) -> (n, m)``, clipped to
    ``[low, high]`` when given. A ``Discrete`` environment is stepped with ``int(u[0])``
    (the command is the action's value)."""
    import gymnasium

    envs = [gymnasium.make(env_id) for _ in range(n_episodes)]
    discrete = isinstance(envs[0].action_space, gymnasium.spaces.Discrete)
    obs = np.array([e.reset(seed=10_000 + i)[0] for i, e in enumerate(envs)], dtype=np.float64)
    ret, alive = np.zeros(n_episodes), np.ones(n_episodes, bool)
    last: np.ndarray | None = None
    jumps: list[np.ndarray] = []
    t = 0
    while alive.any():
        idx = np.flatnonzero(alive)
        u = np.asarray(command(obs[idx], t), np.float64).reshape(len(idx), -1)
        if low is not None:
            u = np.clip(u, low, high)
        if last is not None:
            jumps.append(np.abs(u - last[idx]).sum(axis=1))
        full = np.zeros((n_episodes, u.shape[1])) if last is None else last.copy()
        full[idx] = u
        last = full
        for j, i in enumerate(idx):
            o, r, term, trunc, _ = envs[i].step(int(u[j, 0]) if discrete else u[j].astype(np.float32))
            obs[i], ret[i] = o, ret[i] + r
            alive[i] = not (term or trunc)
        t += 1
    return ret, float(np.concatenate(jumps).mean()) if jumps else 0.0
