"""Any registered gymnasium environment as a simulator (a reset model) for rollouts.

``--simulator gym:ENV_ID`` (CLI ``offline-adp evaluate``, pipeline ``[evaluate]
simulator``, Python :func:`resolve_simulator`) rolls a fitted policy out in
``gymnasium.make(ENV_ID)``:

- **Observations.** The dataset's observation features, in their declared order, are the
  environment's observation vector (a 1-D ``Box``); the widths must agree. Column names
  do not matter (a log may call CartPole's features ``cart_x, cart_v, pole, pole_rate``).
- **Actions.** Action ``i`` of the dataset's action table is the environment action
  ``values[i]``. For a ``Discrete`` space the table holds one number per action, a valid
  integer action. For a 1-D ``Box`` space of ``d`` entries (continuous commands, e.g.
  Pendulum's torque) the table holds ``d`` numbers per action, each within the box's bounds
  -- typically the bins' representative commands of a log binned at ingestion
  (``type = "continuous"`` with ``n_bins`` or ``edges``).
- **Commands.** For a 1-D ``Box`` space of floats, ``step`` also takes continuous commands,
  an ``(n, d)`` float array (one command per state; :attr:`GymResetModel.accepts_commands`
  is true), checked finite and of width ``d`` and clipped into the box: how a continuous
  policy (a :class:`~offline_adp.policies.CommandPolicy`) is rolled out. A ``Discrete``
  (or integer ``Box``) environment takes action indices only.
- **Costs** are ``-reward``; ``terminated`` ends an episode (absorbing). The rollout's
  horizon is the evaluation's ``T``, which for a gymnasium simulator is the environment's
  registered time limit (``max_episode_steps``, :attr:`GymResetModel.horizon`, e.g. 500 for
  CartPole-v1) unless ``--horizon`` sets another; the loop applies it (the stepped
  environment is unwrapped, so gymnasium's own truncation does not cut it short).
- **Start states** are ``env.reset()`` draws, not the data's start states; the estimand says so.

A gymnasium environment can be reset and stepped, not teleported: :meth:`GymResetModel.step`
accepts only states that it produced itself (from :meth:`~GymResetModel.initial_states` or
an earlier step), which is how rollouts use a reset model. Each live episode is one
environment instance, found by its current observation. There is no demonstrator for an
arbitrary environment (:meth:`~GymResetModel.demonstrator` returns ``None``; the
evaluation then skips the comparison and says so).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.access import ResetModel, StepResult, command_matrix, is_command_array
from offline_adp.data.info import DatasetInfo
from offline_adp.errors import (
    AccessModelError,
    IncompatibleError,
    InvalidArgumentError,
    UnknownNameError,
)

PREFIX = "gym:"


class GymResetModel(ResetModel):
    """A registered gymnasium environment as a batched reset model (see the module docstring).

    Parameters
    ----------
    env_id : str
        A registered gymnasium id, e.g. ``"CartPole-v1"``.
    info : DatasetInfo
        The dataset's metadata: features (width and order) and action table.
    gamma : float, optional
        Default: the dataset's hint, else 1.0.
    make_kwargs
        Passed to ``gymnasium.make``.
    """

    def __init__(self, env_id: str, info: DatasetInfo, gamma: float | None = None, **make_kwargs: Any) -> None:
        import gymnasium

        self.env_id, self.make_kwargs, self.name = env_id, make_kwargs, PREFIX + env_id
        try:
            probe = gymnasium.make(env_id, **make_kwargs)
        except gymnasium.error.Error as exc:
            raise UnknownNameError(f"simulator {self.name!r}: gymnasium cannot make {env_id!r} ({exc})") from None
        obs_space, act_space = probe.observation_space, probe.action_space
        spec = probe.spec
        probe.close()
        if not isinstance(obs_space, gymnasium.spaces.Box) or len(obs_space.shape) != 1:
            raise IncompatibleError(f"simulator {self.name!r}: observations must be a 1-D Box, got {obs_space}")
        width = int(obs_space.shape[0])
        names = [f.name for f in info.features]
        if len(names) != width:
            raise IncompatibleError(f"simulator {self.name!r}: its observation vector has {width} entries, the "
                                    f"dataset has {len(names)} features {names}; they are matched by declared order")
        self.env_actions = _env_actions(self.name, act_space, np.asarray(info.action_table.values, dtype=np.float64))
        #: Whether ``step`` takes continuous commands (a 1-D ``Box`` of floats).
        self.accepts_commands = bool(isinstance(act_space, gymnasium.spaces.Box) and len(act_space.shape) == 1
                                     and np.issubdtype(act_space.dtype, np.floating))
        self._box = (np.asarray(act_space.low, np.float64), np.asarray(act_space.high, np.float64),
                     act_space.dtype) if self.accepts_commands else None
        self.n_actions, self.obs_dim = len(self.env_actions), width
        self.gamma = float(gamma if gamma is not None else (info.gamma if info.gamma is not None else 1.0))
        self.horizon = spec.max_episode_steps if spec is not None else None
        self._live: dict[bytes, list[Any]] = {}

    def _make(self) -> Any:
        import gymnasium

        return gymnasium.make(self.env_id, **self.make_kwargs).unwrapped  # no time limit, no checker

    def initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        seeds = rng.integers(0, 2**31 - 1, size=n)
        out = np.empty((n, self.obs_dim))
        for i, seed in enumerate(seeds):  # one environment per episode
            env = self._make()
            obs, _ = env.reset(seed=int(seed))
            out[i] = obs
            self._live.setdefault(out[i].tobytes(), []).append(env)
        return out

    def step(self, states: np.ndarray, actions: np.ndarray, rng: np.random.Generator) -> StepResult:
        """One environment step per state: ``actions`` are indices ``(n,)`` into the action
        table, or (a 1-D float ``Box`` space) commands ``(n, d)``, clipped into the box."""
        states = np.asarray(states, dtype=np.float64)
        n = len(states)
        if is_command_array(actions):
            if self._box is None:
                raise IncompatibleError(f"simulator {self.name!r}: its action space is not a 1-D Box of floats, so it "
                                        "takes action indices (n,) only, not commands (n, d)")
            low, high, dtype = self._box
            cmds = command_matrix(actions, n, low, high, self.name).astype(dtype)
            env_actions: Any = list(cmds)
        else:
            idx = np.asarray(actions, dtype=np.int64)
            env_actions = [self.env_actions[a] for a in idx]
        nxt, costs, term = np.empty((n, self.obs_dim)), np.empty(n), np.zeros(n, bool)
        envs = []
        for i in range(n):
            stack = self._live.get(states[i].tobytes())
            if not stack:
                raise AccessModelError(f"simulator {self.name!r} is a reset model: it can only step states it produced "
                                       "(from initial_states or an earlier step)")
            envs.append(stack.pop())
        for i, (env, action) in enumerate(zip(envs, env_actions, strict=True)):
            # a fresh copy: an environment may change its action in place
            obs, reward, terminated, _truncated, _ = env.step(action.copy() if isinstance(action, np.ndarray)
                                                              else action)
            nxt[i], costs[i], term[i] = obs, -float(reward), terminated
            if terminated:
                env.close()
            else:
                self._live.setdefault(nxt[i].tobytes(), []).append(env)
        return StepResult(nxt, costs, term)

    def demonstrator(self) -> None:
        """No demonstrator for an arbitrary environment."""
        return None

    def rollout_summary(self, states: list[np.ndarray], terminated: np.ndarray) -> dict[str, float]:
        return {"terminated_fraction": float(np.mean(terminated))}


def _env_actions(name: str, space: Any, values: np.ndarray) -> list[Any]:
    """The environment action for each row of the action table's ``values`` (see the module
    docstring), checked against ``space``."""
    import gymnasium

    if isinstance(space, gymnasium.spaces.Discrete):
        if values.ndim != 2 or values.shape[1] != 1:
            raise IncompatibleError(f"simulator {name!r}: the action table must hold one number per action "
                                    f"(the environment's action), got shape {values.shape}")
        lo, n = int(space.start), int(space.n)
        bad = [float(v) for v in values[:, 0] if not np.isfinite(v) or v != round(v) or not lo <= v < lo + n]
        if bad:
            raise IncompatibleError(f"simulator {name!r}: action values {bad} are not actions of {space} "
                                    f"(the action table's values are passed to the environment)")
        return [int(v) for v in values[:, 0]]
    if isinstance(space, gymnasium.spaces.Box) and len(space.shape) == 1:
        d = int(space.shape[0])
        if values.ndim != 2 or values.shape[1] != d:
            raise IncompatibleError(f"simulator {name!r}: its actions are vectors of {d} numbers ({space}); the action "
                                    f"table's values have shape {values.shape}, one row of {d} per action is needed")
        low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
        with np.errstate(invalid="ignore"):  # each side its own slack (float32 bounds, rounded commands)
            inside = (values >= low - 1e-6 * (1.0 + np.abs(low))) & (values <= high + 1e-6 * (1.0 + np.abs(high)))
        outside = np.flatnonzero(~inside.all(axis=1))  # NaN is never inside
        if len(outside):
            raise IncompatibleError(f"simulator {name!r}: action(s) {outside.tolist()} with values "
                                    f"{values[outside].tolist()} are outside the action box [{low.tolist()}, "
                                    f"{high.tolist()}]")
        if np.issubdtype(space.dtype, np.integer) and not (values == np.round(values)).all():
            rows = np.flatnonzero((values != np.round(values)).any(axis=1))
            raise IncompatibleError(f"simulator {name!r}: its action box holds integers ({space}); action(s) "
                                    f"{rows.tolist()} have values {values[rows].tolist()}")
        return list(np.clip(values, low, high).astype(space.dtype))
    raise IncompatibleError(f"simulator {name!r}: actions must be Discrete or a 1-D Box, got {space}")


def resolve_simulator(name: str | None, info: DatasetInfo) -> Any:
    """The simulator for ``--simulator NAME``: ``None`` for ``None``/``""``/``"none"``,
    a :class:`GymResetModel` for ``"gym:ENV_ID"``, else a named reference problem."""
    if name is None or name in ("", "none"):
        return None
    if name.startswith(PREFIX):
        return GymResetModel(name[len(PREFIX):], info)
    from offline_adp.envs import PROBLEM_NAMES, problem_for_dataset

    if name not in PROBLEM_NAMES:
        raise UnknownNameError(f"unknown simulator {name!r}; known: {list(PROBLEM_NAMES)}, "
                               "gym:ENV_ID (a registered gymnasium environment) or 'none'")
    return problem_for_dataset(name, info)  # the dataset's own problem with the options it was made with


def record_random_log(env_id: str, n_transitions: int, seed: int = 0, max_hold: int = 8,
                      **make_kwargs: Any) -> dict[str, np.ndarray]:
    """A log of uniformly random actions, each held for 1..``max_hold`` steps, in
    ``gymnasium.make(env_id)`` (with its time limit), as numpy columns: ``episode, step,
    obs (n, d), action, reward, next_obs, terminated, truncated`` (gymnasium's flags as
    returned: both may be true on one row). Episodes run to their end, so the log may
    exceed ``n_transitions`` by one episode.

    ``action`` is an integer per row for a ``Discrete`` action space; for a 1-D ``Box``
    (continuous commands, drawn uniformly within its bounds) a float per row when the box
    has one entry, else a ``(n, d)`` array."""
    import gymnasium

    env = gymnasium.make(env_id, **make_kwargs)
    rng = np.random.default_rng(seed)
    space = env.action_space
    if isinstance(space, gymnasium.spaces.Discrete):
        start, n_act = int(space.start), int(space.n)

        def draw() -> Any:
            return start + int(rng.integers(n_act))
    elif isinstance(space, gymnasium.spaces.Box) and len(space.shape) == 1:
        low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
        if not (np.isfinite(low).all() and np.isfinite(high).all()):
            raise InvalidArgumentError(f"record_random_log({env_id!r}): the action box {space} is unbounded; "
                                       "uniformly random actions need finite bounds")

        if np.issubdtype(space.dtype, np.integer):
            def draw() -> Any:
                return rng.integers(low.astype(np.int64), high.astype(np.int64), endpoint=True).astype(space.dtype)
        else:
            def draw() -> Any:
                return rng.uniform(low, high).astype(space.dtype)
    else:
        raise InvalidArgumentError(f"record_random_log({env_id!r}): actions must be Discrete or a 1-D Box, got {space}")
    cols: dict[str, list[Any]] = {k: [] for k in ("episode", "step", "obs", "action", "reward", "next_obs",
                                                  "terminated", "truncated")}
    ep = 0
    while len(cols["step"]) < n_transitions:
        obs, _ = env.reset(seed=int(rng.integers(2**31 - 1)))
        t, hold, a, done = 0, 0, None, False
        while not done:
            if hold == 0:
                a, hold = draw(), int(rng.integers(1, max_hold + 1))
            nxt, r, term, trunc, _ = env.step(a.copy() if isinstance(a, np.ndarray) else a)  # the log keeps a
            for k, v in zip(cols, (ep, t, obs, a, r, nxt, term, trunc), strict=True):
                cols[k].append(v)
            obs, t, hold, done = nxt, t + 1, hold - 1, term or trunc
        ep += 1
    env.close()
    out = {k: np.asarray(v, dtype=np.float64 if k in ("obs", "next_obs", "reward") else None) for k, v in cols.items()}
    if out["action"].ndim == 2 and out["action"].shape[1] == 1:
        out["action"] = out["action"][:, 0]
    if out["action"].dtype.kind == "f":
        out["action"] = out["action"].astype(np.float64)
    return out
