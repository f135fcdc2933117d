"""Q-functions over (x, a) for a finite action set.

A Q-function answers ``values(obs, t) -> (n, n_actions)`` for all actions in one
batched call. Representations:

- :class:`QEncoder` turns observations (and actions) into regressor inputs: an optional
  feature map ``phi(x)`` (any fitted scikit-learn transformer), and either one *joint*
  model on ``[phi(x), action features]`` (the action's value vector or a one-hot code)
  or one model *per action* on ``phi(x)``.
- :class:`RegressorQ` wraps fitted regressors (one joint or one per action).
- :class:`TreeQ` reads :class:`~offline_adp.trees.ensemble.TreeEnsemble` s (tree
  ensembles as plain arrays, :mod:`offline_adp.trees`).
- :class:`BoostedSumQ` sums LightGBM boosters (the warm-start LEARN step's Q).
- :class:`TimeIndexedQ` holds one Q per step for finite horizons (Algorithm 10).
"""

from __future__ import annotations

import weakref
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from offline_adp.errors import InvalidArgumentError, InvalidTypeError
from offline_adp.trees.ensemble import TreeEnsemble, ensemble_predict
from offline_adp.trees.sklearn import forest_leaf_values, is_sklearn_forest, sklearn_leaves

TimeArg = int | np.ndarray


class QFunction(ABC):
    """Q(x, a[, t]) for all actions at once."""

    n_actions: int

    @abstractmethod
    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        """Q-values, shape (n, n_actions)."""

    def support(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray | None:
        """Which actions the greedy minimum may choose at each state, ``(n, n_actions)``
        bool, or None: every action (any Q but one made of lookup tables; see
        :func:`restrict_to_support`)."""
        return None

    def has_support(self) -> bool:
        """Whether :meth:`support` can restrict anything (False: it is always None)."""
        return False


def q_support(q: Any, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray | None:
    """``q.support(obs, t)`` of any Q-like object (None where it has no ``support``)."""
    support = getattr(q, "support", None)
    return None if support is None else support(obs, t)


def restrict_to_support(values: np.ndarray, support: np.ndarray | None) -> np.ndarray:
    """``values`` (n, A) for a minimum over the supported actions: ``+inf`` at the actions
    ``support`` leaves out, in the rows where it holds at least one action; rows where it
    holds none keep every value (all actions count, e.g. a lookup table's ``fill_value``
    at a state where nothing was logged). ``support`` None: ``values`` itself."""
    if support is None:
        return values
    keep = support | ~support.any(axis=1, keepdims=True)
    return np.where(keep, values, np.inf)


@dataclass
class QEncoder:
    """Builds regressor inputs from observations and actions.

    Parameters
    ----------
    n_actions : int
    action_features : ndarray (n_actions, k)
        What a joint model sees of each action (value vectors or one-hot rows).
    per_action : bool
        One model per action on ``phi(x)`` instead of a joint model.
    feature_map : fitted transformer, optional
        ``phi``; applied to observations before anything else.
    """

    n_actions: int
    action_features: np.ndarray
    per_action: bool = False
    feature_map: Any = None
    #: whether the "actions" are per-state candidate commands (:class:`CommandEncoder`)
    continuous: ClassVar[bool] = False

    def phi(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        return obs if self.feature_map is None else np.asarray(self.feature_map.transform(obs), dtype=np.float64)

    def pairs(self, phi: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Joint inputs ``[phi(x_i), f(a_i)]``, shape (n, d + k)."""
        return np.hstack([phi, self.action_features[np.asarray(actions, dtype=np.int64)]])

    def all_pairs(self, phi: np.ndarray) -> np.ndarray:
        """Joint inputs for every action, action-major: row ``a * n + i`` is (x_i, a)."""
        n = len(phi)
        return np.hstack([np.tile(phi, (self.n_actions, 1)), np.repeat(self.action_features, n, axis=0)])


#: States are compared in units of each feature's logged spread, clipped to this magnitude so
#: that a squared distance never overflows (a state 1e100 spreads away is as far as any).
SCALED_LIMIT = 1e100


@dataclass(eq=False)
class NeighbourCommands:
    """The candidate commands ``C(x)`` of a state: the commands logged at the ``k`` logged
    states nearest to ``phi(x)`` (Euclidean distance after scaling each feature by its
    logged standard deviation). In the spirit of batch-constrained Q-learning (Fujimoto,
    Meger & Precup 2019), every neighbour candidate is a command that was logged in the
    data's neighbourhood of ``x``; ``extra`` commands (representatives of the whole log) are
    offered at every state after them.

    Parameters
    ----------
    points : ndarray (N, d)
        The logged states' ``phi``, already scaled (``(phi - center) / scale``).
    commands : ndarray (N, m)
        The command logged at each of them.
    center, scale : ndarray (d,)
    k : int
        Neighbours per state (at most ``N``).
    extra : ndarray (e, m) or None
        Commands offered at every state after the ``k`` neighbours' (FittedQIteration's
        ``n_representatives``: representative commands of the whole log), so ``C(x)`` has ``n_slots = k + e`` commands.
    """

    points: np.ndarray
    commands: np.ndarray
    center: np.ndarray
    scale: np.ndarray
    k: int
    _tree: Any = field(default=None, repr=False)
    extra: np.ndarray | None = None
    #: the candidate sets of read-only query arrays, by identity (a fit queries the same next
    #: states at every structure build): ``id -> (weak reference to the array, result)``
    _memo: dict[int, tuple[Any, np.ndarray]] = field(default_factory=dict, repr=False)

    @classmethod
    def from_data(cls, phi: np.ndarray, commands: np.ndarray, k: int,
                  extra: np.ndarray | None = None) -> NeighbourCommands:
        """The candidate set of a dataset's logged states ``phi`` and commands (plus
        ``extra`` commands offered everywhere)."""
        phi = np.asarray(phi, np.float64)
        center, scale = phi.mean(axis=0), phi.std(axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        cmd = np.ascontiguousarray(np.asarray(commands, np.float64).reshape(len(phi), -1))
        ext = None if extra is None or len(extra) == 0 else np.ascontiguousarray(
            np.asarray(extra, np.float64).reshape(-1, cmd.shape[1]))
        return cls(np.ascontiguousarray((phi - center) / scale), cmd, center, scale, int(min(k, len(phi))), extra=ext)

    @property
    def n_dims(self) -> int:
        return int(self.commands.shape[1])

    @property
    def n_slots(self) -> int:
        """Candidates per state: the ``k`` neighbours' commands, then the ``extra`` ones."""
        return self.k + (0 if self.extra is None else len(self.extra))

    def neighbours(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(squared distances, rows)`` of the ``k`` nearest logged states, each ``(n, k)``.

        The order is defined exactly, so that an exported graph can reproduce it
        (:mod:`offline_adp.onnx_export`): the squared distance is the sum over features, in
        feature order, of ``(q_j - p_j)^2`` in the scaled units, and ties go to the lower
        row. A k-d tree proposes ``k + 1`` rows; where the ``k``-th and the next are tied
        to 1e-9 (duplicated logged states, a robot reset to one pose), every row within
        that distance is gathered and ordered the same way."""
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points)
        q = (np.asarray(phi, np.float64) - self.center) / self.scale
        k, N = self.k, len(self.points)
        if len(q) == 0:
            return np.zeros((0, k)), np.zeros((0, k), np.int64)
        if not np.isfinite(q).all():
            bad = int(np.flatnonzero(~np.isfinite(q).all(axis=1))[0])
            raise InvalidArgumentError(f"state {bad}: {np.asarray(phi)[bad].tolist()} is not finite (or too large to "
                                       "compare with the logged states)")
        q = np.clip(q, -SCALED_LIMIT, SCALED_LIMIT)  # squared distances stay finite (the exported graph clips too)
        kk = min(k + 1, N)
        _, rows = self._tree.query(q, k=kk)
        rows = np.asarray(rows, np.int64).reshape(len(q), kk)
        d2 = self._sq_dist(q[:, None, :], rows)
        order = np.lexsort((rows, d2), axis=1)
        d2, rows = np.take_along_axis(d2, order, 1), np.take_along_axis(rows, order, 1)
        if kk > k:
            tied = np.flatnonzero(d2[:, k] <= d2[:, k - 1] * (1 + 1e-9))
            # a tie across the k-th place (duplicated logged states): settled once per distinct
            # query point among every row that close (a reset pose queried 5,000 times: once)
            points, which = np.unique(q[tied], axis=0, return_inverse=True)
            for j, qj in enumerate(points):
                at = tied[which.reshape(-1) == j]
                near = np.asarray(self._tree.query_ball_point(qj, np.sqrt(d2[at[0], k - 1]) * (1 + 1e-6) + 1e-300),
                                  np.int64)
                dd = self._sq_dist(qj[None, None, :], near[None, :])[0]
                o = np.lexsort((near, dd))[:k]
                d2[at, :k], rows[at, :k] = dd[o], near[o]
        return d2[:, :k], rows[:, :k]

    def _sq_dist(self, q: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """``sum_j (q_j - p_j)^2`` over features in order (the exported graph's sum)."""
        p = self.points[rows]  # (n, r, d)
        diff = q - p
        acc = diff[..., 0] * diff[..., 0]
        for j in range(1, p.shape[-1]):
            acc = acc + diff[..., j] * diff[..., j]
        return acc

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        """``C(x)`` for each row of ``phi``: ``(n, n_slots, m)`` commands (the neighbours'
        in order of distance, then ``extra``)."""
        frozen = isinstance(phi, np.ndarray) and not phi.flags.writeable  # cannot change under the memo
        if frozen and id(phi) in self._memo:
            ref, out = self._memo[id(phi)]
            if ref() is phi:
                return out
        near = self.commands[self.neighbours(phi)[1]]
        out = near if self.extra is None else np.concatenate(
            [near, np.broadcast_to(self.extra[None], (len(near), *self.extra.shape))], axis=1)
        if frozen:
            out.setflags(write=False)
            self._memo = {i: v for i, v in self._memo.items() if v[0]() is not None}  # drop the dead ones
            self._memo[id(phi)] = (weakref.ref(phi), out)
        return out


#: Command support: the logged states whose commands a command is compared with, and the
#: quantile of the logged commands' own distances beyond which it is unsupported.
COMMAND_SUPPORT_NEIGHBOURS = 20
COMMAND_SUPPORT_QUANTILE = 0.95


def command_support_distances(obs: np.ndarray, u: np.ndarray, bounds: tuple[np.ndarray, np.ndarray],
                              query_obs: np.ndarray, query_u: np.ndarray,
                              k: int = COMMAND_SUPPORT_NEIGHBOURS) -> tuple[np.ndarray, float]:
    """How far each command ``query_u[i]`` lies from the commands logged at the ``k`` logged
    states nearest ``query_obs[i]`` (sup over components, in units of each component's
    bound range, else its logged range), and the ``radius`` beyond which a command counts
    as unsupported: the :data:`COMMAND_SUPPORT_QUANTILE` of each logged command's distance
    to its neighbours' (not its own row's). ``query_obs is obs``: the logged states
    themselves (their nearest is their own row)."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    span = np.where(np.isfinite(hi - lo) & (hi > lo), hi - lo, np.ptp(u, axis=0))
    span = np.where(span > 0, span, 1.0)
    cands = NeighbourCommands.from_data(obs, u, k + 1)
    _, rows = cands.neighbours(obs)

    def nearest(v: np.ndarray, cols: np.ndarray, own: np.ndarray | None) -> np.ndarray:
        d = (np.abs(v[:, None, :] - u[cols]) / span).max(axis=2)
        if own is not None:
            d = np.where(cols == own[:, None], np.inf, d)
        return d.min(axis=1)

    d_logged = nearest(u, rows, np.arange(len(u)))
    radius = float(np.quantile(d_logged[np.isfinite(d_logged)], COMMAND_SUPPORT_QUANTILE))
    q_rows = rows[:, :k] if query_obs is obs else cands.neighbours(np.asarray(query_obs, np.float64))[1][:, :k]
    return nearest(np.asarray(query_u, np.float64).reshape(len(q_rows), -1), q_rows, None), radius


class PolicyCommands:
    """The one candidate command of a state under a deterministic continuous policy,
    ``C(x) = {pi(x)}``: fitted Q *evaluation* over commands backs up ``Q(x', pi(x'))``.
    Reads observations, so the encoder it serves has no feature map."""

    k = 1
    n_slots = 1

    def __init__(self, policy: Any) -> None:
        self.policy = policy

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        u = np.asarray(self.policy.commands(np.asarray(phi, np.float64), 0), dtype=np.float64)
        return u.reshape(len(phi), 1, -1)


@dataclass(eq=False)
class CommandEncoder(QEncoder):
    """A joint encoder over continuous commands: the regression input of ``(x, u)`` is
    ``[phi(x), u]`` with ``u`` the command itself, and "all actions" of a state are its
    ``k`` candidate commands (:class:`NeighbourCommands`), so ``values`` has one column per
    candidate slot (``n_actions = k``) and the slot that minimises it names the command."""

    candidates: NeighbourCommands | PolicyCommands | None = None
    continuous: ClassVar[bool] = True

    def pairs(self, phi: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """``[phi(x_i), u_i]`` for commands ``u`` of shape (n, m)."""
        u = np.asarray(actions, dtype=np.float64).reshape(len(phi), -1)
        return np.hstack([phi, u])

    def commands(self, phi: np.ndarray) -> np.ndarray:
        """The candidate commands of each row, ``(n, k, m)``."""
        assert self.candidates is not None
        return self.candidates(phi)

    def all_pairs(self, phi: np.ndarray) -> np.ndarray:
        """Every candidate of every row, slot-major: row ``j * n + i`` is ``(x_i, C_j(x_i))``."""
        n = len(phi)
        cand = self.commands(phi)
        return np.hstack([np.tile(phi, (self.n_actions, 1)), cand.transpose(1, 0, 2).reshape(self.n_actions * n, -1)])


def with_candidates(q: Any, candidates: NeighbourCommands | PolicyCommands) -> Any:
    """``q`` (a Q-function over continuous commands, or a time-indexed one) reading another
    candidate set: the same models, ``values`` over ``candidates`` (e.g. the greedy
    improvement of an evaluation, whose own candidate is the evaluated policy's command)."""
    import copy

    if hasattr(q, "qs"):
        return TimeIndexedQ([with_candidates(x, candidates) for x in q.qs])
    enc = command_encoder(q)
    if enc is None:
        raise InvalidTypeError(f"{type(q).__name__} is not a Q-function over continuous commands")
    out = copy.copy(q)
    out.encoder = CommandEncoder(candidates.n_slots, np.zeros((candidates.n_slots, enc.action_features.shape[1])),
                                 feature_map=enc.feature_map, candidates=candidates)
    out.n_actions = candidates.n_slots
    return out


def command_encoder(q: Any) -> CommandEncoder | None:
    """The :class:`CommandEncoder` of a Q-function (or of a time-indexed Q's steps), else None."""
    enc = getattr(q, "encoder", None)
    if enc is None and hasattr(q, "qs"):
        enc = getattr(q.qs[0], "encoder", None)
    return enc if isinstance(enc, CommandEncoder) else None


def predict_model(model: Any, X: np.ndarray, leaf_values: np.ndarray | None = None) -> np.ndarray:
    """``model.predict(X)`` as float64; scikit-learn forests go through their leaves
    (``apply`` + a fixed-order mean), which is deterministic (the threaded
    ``predict`` sums trees in a racy order) and equal to a saved :class:`TreeEnsemble`.
    ``leaf_values``: the forest's node values
    (:func:`~offline_adp.trees.sklearn.forest_leaf_values`), when the caller keeps them."""
    if is_sklearn_forest(model):
        values = forest_leaf_values(model) if leaf_values is None else leaf_values
        return ensemble_predict(values, sklearn_leaves(model, X))
    return np.asarray(model.predict(X), dtype=np.float64)


class RegressorQ(QFunction):
    """Q from fitted regressors: one joint model, or one model per action."""

    def __init__(self, models: list[Any], encoder: QEncoder) -> None:
        self.models, self.encoder, self.n_actions = models, encoder, encoder.n_actions
        self._leaf_values: dict[int, np.ndarray] = {}  # a forest's node values, by model index

    def predict_model(self, j: int, X: np.ndarray) -> np.ndarray:
        """Model ``j``'s predictions (:func:`predict_model`; a forest's node values gathered once)."""
        model = self.models[j]
        if not is_sklearn_forest(model):
            return predict_model(model, X)
        values = self.__dict__.setdefault("_leaf_values", {}).get(j)
        if values is None:
            values = self._leaf_values[j] = forest_leaf_values(model)
        return predict_model(model, X, values)

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        phi = self.encoder.phi(obs)
        return self.values_phi(phi)

    def support(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray | None:
        """The (state, action) pairs the models hold, where every model is a lookup table
        (it has ``seen(X)``, :class:`~offline_adp.regressors.TabularRegressor`): the
        actions logged at each state, ``(n, n_actions)``; else None. In the empirical
        model a lookup-table Q is exact DP on, those are the actions available at a state.
        Over continuous commands None (the candidate set already restricts the minimum)."""
        return self.support_phi(self.encoder.phi(obs)) if self._tables() else None

    def has_support(self) -> bool:
        return self._tables()

    def _tables(self) -> bool:
        """Whether every model is a lookup table (has ``seen``) over a finite action set."""
        return not self.encoder.continuous and all(callable(getattr(m, "seen", None)) for m in self.models)

    def support_phi(self, phi: np.ndarray) -> np.ndarray | None:
        """:meth:`support` from regression inputs ``phi(x)``."""
        if not self._tables():
            return None
        n = len(phi)
        if self.encoder.per_action:
            return np.column_stack([np.asarray(m.seen(phi), bool) for m in self.models]).reshape(n, self.n_actions)
        return np.asarray(self.models[0].seen(self.encoder.all_pairs(phi)), bool).reshape(self.n_actions, n).T

    def values_phi(self, phi: np.ndarray) -> np.ndarray:
        n = len(phi)
        if self.encoder.per_action:
            return np.column_stack([self.predict_model(a, phi) for a in range(len(self.models))])
        return self.predict_model(0, self.encoder.all_pairs(phi)).reshape(self.n_actions, n).T


def per_step(obs: np.ndarray, t: TimeArg, n_steps: int, width: int, fn: Any) -> np.ndarray:
    """Evaluate ``fn(step, obs_rows) -> (m, width)`` once per distinct step in ``t``
    (a scalar or one per row; steps >= ``n_steps`` use the last)."""
    obs = np.asarray(obs)
    tt = np.broadcast_to(np.minimum(np.asarray(t), n_steps - 1), (len(obs),))
    out = np.empty((len(obs), width))
    for step in np.unique(tt):
        rows = tt == step
        out[rows] = fn(int(step), obs[rows])
    return out


class TimeIndexedQ(QFunction):
    """One Q-function per step t = 0..T-1 (finite horizon); steps >= T use the last."""

    def __init__(self, qs: list[QFunction]) -> None:
        self.qs, self.n_actions = qs, qs[0].n_actions

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return per_step(obs, t, len(self.qs), self.n_actions, lambda k, x: self.qs[k].values(x, k))

    def support(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray | None:
        """Each step's Q's :meth:`QFunction.support` (None where no step has one; a step
        without one supports every action)."""
        if not self.has_support():  # no step's Q restricts: no pass over the rows
            return None
        found: list[bool] = []

        def step(k: int, x: np.ndarray) -> np.ndarray:
            s = q_support(self.qs[k], x, k)
            found.append(s is not None)
            return np.ones((len(x), self.n_actions), bool) if s is None else s

        out = per_step(obs, t, len(self.qs), self.n_actions, step)
        return out.astype(bool) if any(found) else None

    def has_support(self) -> bool:
        return any(q.has_support() if hasattr(q, "has_support") else hasattr(q, "support") for q in self.qs)


class TreeQ(QFunction):
    """Q from :class:`TreeEnsemble` s (one joint, or one per action)."""

    def __init__(self, ensembles: list[TreeEnsemble], encoder: QEncoder) -> None:
        self.ensembles, self.encoder, self.n_actions = ensembles, encoder, encoder.n_actions
        self.models = ensembles  # same interface as RegressorQ

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        phi, n = self.encoder.phi(obs), len(obs)
        if self.encoder.per_action:
            return np.column_stack([e.predict(phi) for e in self.ensembles])
        return self.ensembles[0].predict(self.encoder.all_pairs(phi)).reshape(self.n_actions, n).T


class BoostedSumQ(QFunction):
    """Q = sum of LightGBM boosters' raw scores on joint inputs (the warm-start LEARN step's,
    :class:`~offline_adp.learn.warm_start.LightGBMWarmStartLearner`)."""

    def __init__(self, boosters: list[Any], encoder: QEncoder) -> None:
        self.boosters, self.encoder, self.n_actions = boosters, encoder, encoder.n_actions

    def values(self, obs: np.ndarray, t: Any = 0) -> np.ndarray:
        X = self.encoder.all_pairs(self.encoder.phi(obs))
        s = sum(b.predict(X, raw_score=True) for b in self.boosters)
        return np.asarray(s, dtype=np.float64).reshape(self.n_actions, len(obs)).T


class FunctionQ(QFunction):
    """Q from a vectorised function ``fn(obs, t) -> (n, n_actions)`` (e.g. a linear start)."""

    def __init__(self, fn: Any, n_actions: int) -> None:
        self.fn, self.n_actions = fn, n_actions

    def values(self, obs: np.ndarray, t: TimeArg = 0) -> np.ndarray:
        return np.asarray(self.fn(np.asarray(obs, dtype=np.float64), t),
                          dtype=np.float64).reshape(len(obs), self.n_actions)
