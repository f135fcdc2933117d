"""Policies: ``probabilities(obs, t) -> (n, n_actions)``, ``act_index(obs, t, rng)`` and
the user-facing ``act(obs, t, rng)``.

The algorithm-facing methods (``probabilities``, ``act_index``, ``actions``) are batched
over rows of a float array ``obs`` (shape (n, d)); ``t`` is the time step, a scalar or
one per row. Deterministic policies return one-hot probabilities, so density ratios and
mixtures treat every policy alike.

``act`` is the deployment API: it accepts a dict ``{feature: value}``, a pandas
DataFrame (columns matched by name), or an array (width checked), for one observation
or a batch, and returns the action *values* from the action table (indices with
``return_index=True``). It needs the policy's :class:`PolicySignature` (feature names,
units, action table), which fitting on a dataset attaches (``policy.signature``); a
policy without one accepts arrays only and its action values are its indices.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from offline_adp.data.info import ActionTable
from offline_adp.errors import InvalidArgumentError, SchemaError

# the policy interface (policy_base.py), importable from here too
from offline_adp.policy_base import (  # noqa: F401
    DeterministicPolicy,
    Policy,
    PolicySignature,
    TimeArg,
    observation_matrix,
)


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
    """Uniformly random actions (exploration): over all ``n_actions``, or over ``actions``
    (e.g. the actions a dataset logs), the others never taken."""

    def __init__(self, n_actions: int, actions: Sequence[int] | None = None) -> None:
        self.n_actions = n_actions
        self.actions = None if actions is None else [int(a) for a in actions]
        if self.actions is not None and not (self.actions and len(set(self.actions)) == len(self.actions)
                                             and all(0 <= a < n_actions for a in self.actions)):
            raise InvalidArgumentError(f"actions must be distinct action indices in [0, {n_actions}), "
                                       f"got {actions!r}")

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        n = np.asarray(obs).shape[0]
        if self.actions is None:
            return np.full((n, self.n_actions), 1.0 / self.n_actions)
        p = np.zeros((n, self.n_actions))
        p[:, self.actions] = 1.0 / len(self.actions)
        return p


class EpsilonPolicy(Policy):
    """``(1 - epsilon) * base + epsilon * uniform``: a noisy version of ``base``."""

    def __init__(self, base: Policy, epsilon: float) -> None:
        if not 0.0 <= epsilon <= 1.0:
            raise InvalidArgumentError(f"epsilon must be in [0, 1], got {epsilon}")
        self.base, self.epsilon, self.n_actions = base, float(epsilon), base.n_actions

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return (1.0 - self.epsilon) * self.base.probabilities(obs, t) + self.epsilon / self.n_actions

    @property
    def time_varying(self) -> bool | None:
        """As its base policy's (None: unknown)."""
        return getattr(self.base, "time_varying", None)


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
                raise InvalidArgumentError("n_actions is required for a table of actions")
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


def joint_tree_values(q: object, obs: np.ndarray) -> np.ndarray | None:
    """``q.values(obs)`` (n, A) of a Q-function that is one tree ensemble on joint ``(x, a)``
    inputs (a :class:`~offline_adp.qfunctions.RegressorQ` or ``TreeQ`` of one
    :class:`~offline_adp.trees.ensemble.TreeEnsemble`), with every tree descended once per
    state for all actions (:func:`~offline_adp.trees.pairs.pair_leaves`): the same leaves
    and the same mean over trees, so the same numbers bit for bit. None for any other
    Q-function (then call ``q.values``)."""
    from offline_adp.qfunctions import QEncoder, RegressorQ, TreeQ
    from offline_adp.trees.ensemble import LOOKUP_CHUNK, TreeEnsemble, ensemble_predict
    from offline_adp.trees.loaded import LoadedEnsemble
    from offline_adp.trees.pairs import pair_leaves

    if type(q) not in (RegressorQ, TreeQ) or type(q.encoder) is not QEncoder or q.encoder.per_action:  # type: ignore[attr-defined]
        return None
    model = q.models[0]  # type: ignore[attr-defined]
    if (not isinstance(model, TreeEnsemble) or type(model).apply not in (TreeEnsemble.apply, LoadedEnsemble.apply)
            or type(model).predict is not TreeEnsemble.predict or getattr(model, "_forest", None) is not None
            or obs.ndim != 2):
        return None
    phi = q.encoder.phi(obs)  # type: ignore[attr-defined]
    A, out = q.n_actions, None  # type: ignore[attr-defined]
    step = max(1, LOOKUP_CHUNK // A)  # states a chunk: no (pairs, trees) matrix of a whole set is held
    for lo in range(0, max(len(phi), 1), step):
        leaves = pair_leaves(model, phi[lo:lo + step], q.encoder.action_features)  # type: ignore[attr-defined]
        if leaves is None:
            return None
        part = ensemble_predict(model.value, leaves).reshape(A, -1).T  # type: ignore[attr-defined]
        if len(phi) <= step:
            return np.asarray(part, dtype=np.float64)
        out = np.empty((len(phi), A)) if out is None else out
        out[lo:lo + step] = part
    return out


class GreedyPolicy(DeterministicPolicy):
    """``pi(x, t) = argmin_a Q(x, a, t)``: greedy with respect to a cost Q-function.

    Ties go to the lowest action index. Over a Q with a ``support`` (lookup tables: the
    actions logged at each state) the minimum runs over the supported actions wherever a
    state has one (:func:`~offline_adp.qfunctions.restrict_to_support`).
    """

    def __init__(self, q: object) -> None:
        self.q = q
        self.n_actions = q.n_actions  # type: ignore[attr-defined]

    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        obs = np.asarray(obs)
        q = joint_tree_values(self.q, obs)  # the same values, the trees descended once per state
        q = self.q.values(obs, t) if q is None else q  # type: ignore[attr-defined]
        from offline_adp.qfunctions import q_support, restrict_to_support

        return np.argmin(restrict_to_support(q, q_support(self.q, obs, t)), axis=1).astype(np.int32)

    @property
    def time_varying(self) -> bool:
        """Greedy in a time-indexed Q (one per step) changes with t; in one Q it does not."""
        from offline_adp.qfunctions import TimeIndexedQ

        return isinstance(self.q, TimeIndexedQ)


class CommandPolicy(DeterministicPolicy):
    """A deterministic policy over continuous commands: :meth:`commands` returns one command
    vector per row, ``(n, m)``, within the action table's bounds. ``act`` returns those
    commands; the discrete view (``actions``, ``probabilities``, ``act_index``), which
    binned consumers read, is the action-table entry whose representative command is
    nearest (in units of each component's bound range, else of the entries' spread)."""

    continuous = True

    @abstractmethod
    def commands(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """The command per row, shape (n, m) float64."""

    def sample_commands(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        """The commands a rollout sends: :meth:`commands` (a deterministic policy; ``rng`` unused)."""
        return self.commands(obs, t)

    @property
    def n_actions(self) -> int:  # type: ignore[override]
        return len(self._table())

    def _table(self) -> ActionTable:
        if self.signature is None:
            raise SchemaError("a continuous policy's discrete view needs its action table; attach a signature "
                              "(policy.signature = PolicySignature.from_info(dataset.info))")
        return self.signature.action_table

    def clip(self, u: np.ndarray) -> np.ndarray:
        """``u`` within the action table's bounds (where the policy has a signature)."""
        if self.signature is None:
            return u
        lo, hi = self.signature.action_table.bounds()
        return np.clip(u, lo, hi)

    def actions(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return nearest_entry(self._table(), self.commands(obs, t))

    def act(self, obs: Any, t: TimeArg = 0, rng: np.random.Generator | None = None, *,
            return_index: bool = False) -> Any:
        """The command for each observation (see :meth:`Policy.act`): ``(n, m)``, or ``(n,)``
        for a one-component command; a single observation drops the leading axis.
        ``return_index``: the nearest action-table entry instead."""
        sig = self.signature
        X, single = observation_matrix(obs, None if sig is None else sig.feature_names, t)
        if return_index:
            idx = self.actions(X, t)
            return int(idx[0]) if single else idx
        u = self.commands(X, t)
        if u.shape[1] == 1:
            u = u[:, 0]
        return u[0] if single else u


def nearest_entry(table: ActionTable, u: np.ndarray) -> np.ndarray:
    """The index of the table entry whose value is nearest each command ``u`` (n, m), each
    component scaled by its bound range (else by the entries' spread)."""
    vals = table.values
    lo, hi = table.bounds()
    span = np.where(np.isfinite(hi - lo) & (hi > lo), hi - lo, np.ptp(vals, axis=0))
    span = np.where(span > 0, span, 1.0)
    d = (((np.asarray(u, np.float64)[:, None, :] - vals[None, :, :]) / span) ** 2).sum(axis=2)
    return np.argmin(d, axis=1).astype(np.int32)


class GreedyCommandPolicy(CommandPolicy):
    """``pi(x, t) = argmin_{u in C(x)} Q(x, u, t)`` over the candidate commands ``C(x)`` of
    ``x`` (:class:`~offline_adp.qfunctions.NeighbourCommands`: commands logged at the
    nearest logged states, and, when the fit offers them, representative commands of the
    whole log: means of commands logged together, logged commands themselves where each
    component has few levels), so a representative may be a command nobody logged exactly,
    or one not tried near ``x`` (the evaluation's command support measures how often).
    Ties go to the nearest neighbour's command."""

    def __init__(self, q: Any) -> None:
        from offline_adp.qfunctions import command_encoder

        enc = command_encoder(q)
        if enc is None:
            raise SchemaError("GreedyCommandPolicy needs a Q-function over continuous commands (a CommandEncoder)")
        self.q, self.encoder = q, enc

    def commands(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if not len(obs):  # no observations: no commands (as the discrete greedy policy returns none)
            logged = getattr(self.encoder.candidates, "commands", None)
            m = len(self.signature.action_table.dims) if self.signature is not None else np.shape(logged)[-1]
            return np.zeros((0, m))
        cand = self.encoder.commands(self.encoder.phi(obs))
        j = np.argmin(self.q.values(obs, t), axis=1)
        return self.clip(cand[np.arange(len(obs)), j])

    @property
    def time_varying(self) -> bool:
        from offline_adp.qfunctions import TimeIndexedQ

        return isinstance(self.q, TimeIndexedQ)


class NearestCommandPolicy(CommandPolicy):
    """The command logged at the nearest logged state (a one-nearest-neighbour clone of the
    behaviour): approximate policy iteration's default start over continuous commands."""

    def __init__(self, candidates: Any) -> None:
        self.candidates = candidates  # a NeighbourCommands (its k ignored: the nearest one)

    def commands(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        rows = self.candidates.neighbours(np.asarray(obs, np.float64))[1][:, 0]
        return self.clip(self.candidates.commands[rows])


class GaussianCommandPolicy(Policy):
    """A stochastic behaviour over continuous commands (a driver, an exploration policy).

    With probability ``1 - epsilon`` the command is ``mean(obs, t) + N(0, diag(std^2))``,
    with probability ``epsilon`` uniform in ``[low, high]``; then clipped into
    ``[low, high]``. Rollouts and ``collect`` send :meth:`sample_commands`;
    :meth:`commands` is the noise-free controller ``clip(mean(obs, t))``.

    The discrete view (``probabilities``, ``act_index``) is exact when the action table's
    entries are the product grid of ``grid`` (one array of values per component, entries in
    ``itertools.product`` order): the probability that the sampled command's nearest entry
    (per component: the Voronoi cell of its grid value) is each entry.

    Parameters
    ----------
    mean : callable ``(obs (n, d), t) -> (n, m)``
    std : sequence of float
        Noise standard deviation per component (> 0, or 0 for none).
    low, high : sequence of float
        Bounds per component (finite).
    epsilon : float
        Probability of a uniformly random command.
    grid : sequence of arrays, optional
        The action table's per-component values (needed by the discrete view only).
    """

    continuous = True
    time_varying = False

    def __init__(self, mean: Callable[[np.ndarray, TimeArg], np.ndarray], std: Sequence[float], low: Sequence[float],
                 high: Sequence[float], epsilon: float = 0.0, grid: Sequence[Sequence[float]] | None = None,
                 name: str = "") -> None:
        self.mean, self.name = mean, name
        self.std, self.low, self.high = (np.asarray(v, np.float64).reshape(-1) for v in (std, low, high))
        if not (len(self.std) == len(self.low) == len(self.high)) or not (np.isfinite(self.low).all()
                                                                         and np.isfinite(self.high).all()):
            raise InvalidArgumentError("std, low and high need one finite number per command component")
        if (self.std < 0).any() or (self.low > self.high).any():
            raise InvalidArgumentError(f"std must be >= 0 and low <= high; got std {self.std}, low {self.low}, "
                                       f"high {self.high}")
        if not 0.0 <= epsilon <= 1.0:
            raise InvalidArgumentError(f"epsilon must be in [0, 1], got {epsilon}")
        self.epsilon = float(epsilon)
        self.grid = None if grid is None else [np.asarray(g, np.float64).reshape(-1) for g in grid]
        self.n_actions = int(np.prod([len(g) for g in self.grid])) if self.grid is not None else 0

    def commands(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        mu = np.asarray(self.mean(np.asarray(obs, np.float64), t), np.float64).reshape(len(obs), len(self.low))
        return np.clip(mu, self.low, self.high)

    def sample_commands(self, obs: np.ndarray, t: TimeArg = 0, rng: np.random.Generator | None = None) -> np.ndarray:
        rng = rng if rng is not None else np.random.default_rng()
        mu = np.asarray(self.mean(np.asarray(obs, np.float64), t), np.float64).reshape(len(obs), len(self.low))
        n, m = mu.shape
        noisy = mu + self.std * rng.standard_normal((n, m))
        uniform = self.low + (self.high - self.low) * rng.random((n, m))
        explore = rng.random(n) < self.epsilon
        return np.clip(np.where(explore[:, None], uniform, noisy), self.low, self.high)

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        from scipy.special import ndtr

        if self.grid is None:
            raise SchemaError("this continuous behaviour has no discrete view (no grid of action-table values)")
        mu = np.asarray(self.mean(np.asarray(obs, np.float64), t), np.float64).reshape(len(obs), len(self.low))
        gauss = uni = np.ones((len(mu), 1))
        for k, g in enumerate(self.grid):
            edges = np.r_[-np.inf, (g[1:] + g[:-1]) / 2, np.inf]
            if self.std[k] > 0:
                with np.errstate(invalid="ignore"):
                    pk = np.diff(ndtr((edges[None, :] - mu[:, k:k + 1]) / self.std[k]), axis=1)
            else:  # no noise: the cell of the clipped mean
                c = np.clip(mu[:, k], self.low[k], self.high[k])
                pk = np.eye(len(g))[np.clip(np.searchsorted(edges, c, side="right") - 1, 0, len(g) - 1)]
            width = self.high[k] - self.low[k]
            inside = np.clip(edges[1:], self.low[k], self.high[k]) - np.clip(edges[:-1], self.low[k], self.high[k])
            uk = inside / width if width > 0 else (np.arange(len(g))
                                                   == np.argmin(np.abs(g - self.low[k]))).astype(float)
            gauss = (gauss[:, :, None] * pk[:, None, :]).reshape(len(mu), -1)
            uni = (uni[:, :, None] * np.broadcast_to(uk, pk.shape)[:, None, :]).reshape(len(mu), -1)
        return (1.0 - self.epsilon) * gauss + self.epsilon * uni

    def act(self, obs: Any, t: TimeArg = 0, rng: np.random.Generator | None = None, *,
            return_index: bool = False) -> Any:
        """Sampled commands (see :meth:`CommandPolicy.act`); ``return_index``: a sampled table entry."""
        sig = self.signature
        X, single = observation_matrix(obs, None if sig is None else sig.feature_names, t)
        if return_index:
            idx = self.act_index(X, t, rng)
            return int(idx[0]) if single else idx
        u = self.sample_commands(X, t, rng)
        if u.shape[1] == 1:
            u = u[:, 0]
        return u[0] if single else u


def greedy_policy(q: Any) -> DeterministicPolicy:
    """The greedy policy of ``q``: :class:`GreedyCommandPolicy` over continuous commands,
    else :class:`GreedyPolicy`."""
    from offline_adp.qfunctions import command_encoder

    return GreedyCommandPolicy(q) if command_encoder(q) is not None else GreedyPolicy(q)


class MixturePolicy(Policy):
    """``sum_k w_k pi_k``: at each time step a component is drawn with probability
    ``w_k`` and acts (so the action probabilities are the weighted sum). Conservative
    policy iteration builds these; the components and weights are kept.
    """

    def __init__(self, components: list[Policy], weights: list[float] | np.ndarray) -> None:
        w = np.asarray(weights, dtype=np.float64)
        if len(components) != len(w) or not len(w):
            raise InvalidArgumentError("a mixture needs one weight per component")
        if (w < 0).any() or not np.isclose(w.sum(), 1.0):
            raise InvalidArgumentError(f"mixture weights must be >= 0 and sum to 1, got {w}")
        self.components, self.weights = list(components), w
        self.n_actions = components[0].n_actions

    def probabilities(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return sum(w * c.probabilities(obs, t) for w, c in zip(self.weights, self.components, strict=True) if w > 0)

    @property
    def time_varying(self) -> bool | None:
        """True if a component changes with t, False if none does, None if unknown."""
        flags = [getattr(c, "time_varying", None) for c in self.components]
        return True if any(f is True for f in flags) else False if all(f is False for f in flags) else None

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


def is_stationary(policy: Policy, obs: np.ndarray, horizon: int | None) -> bool:
    """Whether ``policy`` gives the same action probabilities at every step t < ``horizon``.

    A policy's own ``time_varying`` (True/False) decides; where it is unknown (None or
    absent: a function of ``(obs, t)``), the probabilities on (up to 2,000 of) ``obs`` at
    steps 0, 1, T/2 and T-1 are compared. With no horizon, a policy is stationary unless it
    says it varies."""
    declared = getattr(policy, "time_varying", None)
    if declared is not None or horizon is None:
        return declared is not True
    x = np.asarray(obs, dtype=np.float64)[:2000]
    if not len(x):
        return True
    p0 = policy.probabilities(x, 0)
    return all(np.array_equal(policy.probabilities(x, t), p0) for t in sorted({1, horizon // 2, horizon - 1}) if 0 < t)


def apply_feature_map(feature_map: Any, obs: np.ndarray) -> np.ndarray:
    """``feature_map(obs)`` (a callable or a fitted transformer), or ``obs`` itself."""
    obs = np.asarray(obs, dtype=np.float64)
    if feature_map is None:
        return obs
    return np.asarray(feature_map.transform(obs) if hasattr(feature_map, "transform") else feature_map(obs),
                      dtype=np.float64)


class ClassifierPolicy(DeterministicPolicy):
    """A deterministic policy that predicts the action with a fitted classifier
    (on ``feature_map(obs)`` when a feature map is given); PSDP's per-step policies."""

    def __init__(self, classifier: Any, n_actions: int, constant: int | None = None, feature_map: Any = None) -> None:
        self.classifier, self.n_actions, self.constant, self.feature_map = classifier, n_actions, constant, feature_map

    def actions(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        if self.constant is not None:
            return np.full(len(obs), self.constant, np.int32)
        return np.asarray(self.classifier.predict(apply_feature_map(self.feature_map, obs)), dtype=np.int32)


def attach_signature(policy: Any, source: Any) -> Any:
    """Give ``policy`` (and, for mixtures and time-indexed policies, its parts) the
    signature of ``source`` (a dataset, its info, a reference problem); returns it.
    A no-op when ``policy`` or ``source`` is None or the source has no features."""
    if policy is None or source is None:
        return policy
    info = getattr(source, "info", source)
    if not hasattr(info, "features") or not hasattr(info, "action_table"):
        return policy
    policy.signature = PolicySignature.from_info(info)
    return policy
