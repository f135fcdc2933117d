"""Typed, prepared inputs of the fitted-Q loop (Algorithms 10-13) and its two backups.

:func:`prepare` turns a :class:`~offline_adp.data.dataset.TransitionDataset` into a
frozen :class:`Prepared`: the regression inputs of the training pairs ``(phi(x_i), a_i)``,
their costs and bootstrap mask, the next states, the start states, an optional held-out
:class:`Samples` set for the Bellman residual, and the value bound the monitor checks.

A *backup* maps ``Q_{k-1}(x', .)`` (shape (n, n_actions)) to the value of the next
states that enters the target ``y_i = c_i + gamma (1 - term_i) V(x'_i)``:

- :class:`GreedyBackup` (FQI, Algorithms 10/11): ``V(x') = min_a' Q(x', a')`` (with the
  lookup table over the actions logged at ``x'``);
- :class:`PolicyBackup` (FQE, Algorithms 12/13): ``V(x') = sum_a' pi(a' | x', t+1) Q(x', a')``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

import numpy as np

from offline_adp.algorithms.params import invalid_parameter
from offline_adp.data.dataset import TransitionDataset
from offline_adp.data.discount import resolve_discount
from offline_adp.data.levels import cell_means, level_edges
from offline_adp.errors import InvalidArgumentError, InvalidTypeError
from offline_adp.qfunctions import CommandEncoder, NeighbourCommands, PolicyCommands, QEncoder, restrict_to_support


@dataclass(frozen=True)
class Samples:
    """One set of transitions as the loop needs them."""

    phi: np.ndarray  #: phi(x_i), (n, d)
    actions: np.ndarray  #: a_i, (n,) int; continuous commands: u_i, (n, m) float
    cost: np.ndarray  #: c_i
    no_boot: np.ndarray  #: terminated (or infeasible): no bootstrap
    phi_next: np.ndarray  #: phi(x'_i)
    next_obs: np.ndarray  #: x'_i (raw, for policies and next-state noise)


@dataclass(frozen=True)
class Prepared:
    """Everything the fitted-Q loop reads; built once per fit by :func:`prepare`."""

    train: Samples
    valid: Samples | None
    weights: np.ndarray | None
    gamma: float
    n_actions: int
    encoder: QEncoder
    obs: np.ndarray  #: training x_i (raw)
    obs_std: np.ndarray  #: per-feature std (next-state noise unit)
    start_phi: np.ndarray
    start_obs: np.ndarray
    start_rows: np.ndarray  #: rows of the training set that start an episode
    bound: float  #: the monitor's value bound
    bound_text: str
    infeasible_cost: float | None = None
    q0_abs: float = 0.0  #: max |Q_0| on the data (0 without initial_q)

    @property
    def n(self) -> int:
        return len(self.train.cost)

    @cached_property
    def cost_unit(self) -> float:
        """The costs' size: the power of two ``u`` with ``u <= max |c_i| < 2u`` over the
        training rows (1 where every cost is 0). The unit of the fit's absolute constants
        (a build grows its trees on ``y / u``, with a tie jitter of ``1e-6 (u + std(y))``;
        the default tolerance of the evaluation's solves is ``rtol (u + max |v|)``), so that
        with every cost multiplied by ``2^k`` the fit is the same with ``2^k`` times the
        values, exactly, and costs of 1e-5 fit as costs of 1 do."""
        return cost_unit(self.train.cost)

    def targets(self, v_next: np.ndarray) -> np.ndarray:
        """``y_i = c_i + gamma (1 - term_i) V(x'_i)``, clamped at ``c^-``."""
        s = self.train
        y = s.cost + self.gamma * np.where(s.no_boot, 0.0, v_next)
        return y if self.infeasible_cost is None else np.minimum(y, self.infeasible_cost)


def cost_unit(cost: np.ndarray) -> float:
    """The power of two ``u`` with ``u <= max |c| < 2u`` (1 where every cost is 0 or one is
    not finite): :attr:`Prepared.cost_unit`."""
    m = float(np.max(np.abs(cost), initial=0.0))
    return math.ldexp(1.0, math.frexp(m)[1] - 1) if 0.0 < m < math.inf else 1.0


def _read_only(v: np.ndarray) -> np.ndarray:
    """A read-only view of ``v`` (the dataset's own arrays are shared, never written)."""
    out = v.view()
    out.flags.writeable = False
    return out


def value_bound(cmax: float, g: float, horizon: int | None, infeasible_cost: float | None = None,
                target_noise: float = 0.0, initial_q_abs: float = 0.0, cmin: float | None = None) -> tuple[float, str]:
    """The monitor's bound on ``|Q|`` from ``max |c|`` (and how it was computed). With the
    chapter's ``c^-`` (``infeasible_cost``) the targets are clamped from above only: values
    stay below ``max(|c^-|, max|c|)`` but may still fall to ``min(c, 0) / (1 - gamma)``
    (``cmin``: the smallest cost; None: ``-cmax``)."""
    if horizon is not None:  # |Q_t| <= max|c| sum_{j < T} gamma^j + max|Q_T|
        scale, times = float(np.sum(g ** np.arange(horizon))), " sum_{j<T} gamma^j"
    elif g < 1:
        scale, times = 1.0 / (1.0 - g), " / (1 - gamma)"
    else:
        scale, times = np.inf, " x inf (undiscounted)"
    bound, text = (cmax * scale if cmax else 0.0), "max|c|" + times
    if infeasible_cost is not None:
        neg = max(-(-cmax if cmin is None else cmin), 0.0)
        below = neg * scale if neg else 0.0  # the clamp does not hold values up
        bound = max(min(bound, abs(infeasible_cost)), below, cmax)
        text = f"max(min({text}, |c^-|), max(-c, 0){times}, max|c|)"
    elif not np.isfinite(bound):
        text = "none (undiscounted)"
    if target_noise and g < 1:  # noisy targets may overshoot by a few noise std
        bound, text = bound + 4 * target_noise / (1.0 - g), text + " + 4 noise / (1 - gamma)"
    if initial_q_abs:
        bound, text = bound + initial_q_abs, text + " + max|Q_0|"
    return float(bound), text


#: below these the tree builders (as scikit-learn's) lose what the data says: a node is pure when
#: its target variance is at most float64 eps, a feature constant when it spans at most 1e-7
TINY_COSTS, TINY_FEATURE_SPAN = 1e-6, 1e-5


def _warn_scale(cost: np.ndarray, obs: np.ndarray, names: list[str], who: str, costs_in_unit: bool = False) -> None:
    """A :class:`~offline_adp.errors.ScaleWarning` for costs or features too small for the
    tree builders to resolve: the fit would say nothing went wrong and learn a flat Q.
    ``costs_in_unit``: the learner reads the targets in the costs' unit (the frozen mode grows
    on ``y / cost_unit``): no warning for the costs."""
    import warnings

    from offline_adp.errors import ScaleWarning

    cmax = float(np.abs(cost).max()) if len(cost) else 0.0
    if 0.0 < cmax < TINY_COSTS and not costs_in_unit:
        warnings.warn(f"{who}: the costs are at most {cmax:.3g} in size: the tree builders (as scikit-learn's) take a "
                      "node whose target variance is below 2.2e-16 as pure, so differences this small may not be "
                      "learned; multiply the costs by a constant (the optimal policy is the same)", ScaleWarning,
                      stacklevel=3)
    if len(obs):
        span = obs.max(axis=0) - obs.min(axis=0)
        tiny = [(n, float(s)) for n, s in zip(names, span, strict=False) if 0.0 < s < TINY_FEATURE_SPAN]
        if tiny:
            warnings.warn(f"{who}: feature {tiny[0][0]!r} spans only {tiny[0][1]:.3g}"
                          + (f" (and {len(tiny) - 1} more)" if len(tiny) > 1 else "")
                          + ": the tree builders (as scikit-learn's) take a feature spanning at most 1e-7 on a node as "
                          "constant there; rescale it", ScaleWarning, stacklevel=3)


def _warn_time_limit(episode: np.ndarray, terminated: np.ndarray, who: str, min_episodes: int = 5) -> None:
    """A :class:`~offline_adp.errors.LogWarning` where every episode (at least
    ``min_episodes``) ends in a terminal state after the same number of steps: what a time
    limit does, and a time limit is a truncation. A terminal state ends all cost, so
    flagging a cut terminal teaches the fit (and a time-indexed FQE, which pools the steps)
    that the cut state costs nothing more (an audit, 2026-11-29: FQE 1.355 against 2.391 for
    the same logs with the flag right, truth 2.628)."""
    import warnings

    from offline_adp.errors import LogWarning

    lengths = np.bincount(episode)
    ends = np.bincount(episode, weights=terminated.astype(np.float64), minlength=len(lengths))
    if len(lengths) >= min_episodes and lengths.min() == lengths.max() > 1 and bool(np.all(ends > 0)):
        warnings.warn(f"{who}: every one of the {len(lengths)} logged episodes ends in a terminal state after exactly "
                      f"{int(lengths[0])} steps, as a time limit would cut them: if a time limit did, flag those rows "
                      "truncated, not terminated (a terminal state ends all cost; a cut episode's cost goes on)",
                      LogWarning, stacklevel=3)


def prepare(ds: TransitionDataset, *, gamma: float | None, horizon: int | None, sample_weight: np.ndarray | None,
            validation_fraction: float, random_state: int, feature_map: Any, action_input: str,
            action_encoding: str, infeasible_cost: float | None, target_noise: float,
            initial_q_abs: float, who: str, n_candidates: int | None = None,
            policy_commands: PolicyCommands | None = None, n_representatives: int = 0,
            costs_in_unit: bool = False) -> Prepared:
    """Validate the dataset and build the loop's inputs (see the module docstring).
    ``n_candidates``: learn over the dataset's exact continuous commands, the minimum over
    each next state's ``n_candidates`` neighbour commands (:class:`NeighbourCommands`), or,
    for an evaluation, the policy's own command (``policy_commands``); ``n_representatives``:
    each next state's candidates also hold up to that many representative commands of the
    training rows (:func:`command_representatives`); ``costs_in_unit``: the learner fits the
    targets in the costs' unit (:attr:`Prepared.cost_unit`), so tiny costs raise no warning."""
    if not isinstance(ds, TransitionDataset):
        raise InvalidTypeError(f"{who}.fit needs a TransitionDataset (trace data), got {type(ds).__name__}")
    if len(ds) == 0:
        raise InvalidArgumentError("the dataset is empty")
    # callers pass the resolved values; this keeps prepare() usable alone
    g = resolve_discount(ds.info, gamma, horizon).gamma
    a = ds.arrays()
    _warn_scale(a.cost, a.obs, ds.feature_names, who, costs_in_unit)
    _warn_time_limit(ds.episode_index, a.terminated, who)
    if horizon is None and not g < 1.0 and not a.terminated.any():
        raise InvalidArgumentError(f"the infinite-horizon algorithm needs gamma < 1 (got {g}) unless "
                                   "episodes terminate (a shortest-path problem); give a horizon instead")
    w_all = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
    if w_all is not None and w_all.shape != (len(ds),):
        raise InvalidArgumentError(f"sample_weight has shape {w_all.shape}, expected ({len(ds)},)")
    if w_all is not None and not (np.isfinite(w_all).all() and (w_all >= 0).all() and w_all.sum() > 0):
        bad = np.flatnonzero(~np.isfinite(w_all) | (w_all < 0))
        where = f"row {int(bad[0])}: {w_all[bad[0]]!r}" if len(bad) else "all rows 0"
        raise InvalidArgumentError("sample_weight must be finite numbers >= 0, not all 0 (the Bellman backup "
                                   f"averages with them); {where}")
    tr = np.ones(len(ds), bool)
    if validation_fraction:
        rng = np.random.default_rng(random_state)
        n_ep = ds.n_episodes
        val_eps = np.zeros(n_ep, bool)
        val_eps[rng.permutation(n_ep)[: max(1, int(round(validation_fraction * n_ep)))]] = True
        tr = ~val_eps[ds.episode_index]
    fmap = None
    if feature_map is not None:
        from sklearn.base import clone

        fmap = clone(feature_map).fit(a.obs[tr])
    at = ds.info.action_table
    if action_encoding == "per_action" and n_candidates is None:  # one model per action: each needs its rows
        held = np.bincount(a.action[tr], weights=None if w_all is None else w_all[tr], minlength=len(at)) > 0
        if not held.all():
            k = int(np.flatnonzero(~held)[0])
            why = ("has weight 0 on every row" if w_all is not None and (a.action[tr] == k).any()
                   else "never occurs in the data" + (" (its training rows)" if validation_fraction else ""))
            raise InvalidArgumentError(f"action {k} {why}: a per-action model cannot be fitted for it; "
                                       "use action_encoding='joint'")
    af = at.values if action_input == "value" else np.eye(len(at))
    enc: QEncoder = QEncoder(len(at), af, per_action=action_encoding == "per_action", feature_map=fmap)
    no_boot = a.terminated.copy()
    if infeasible_cost is not None:
        no_boot |= a.cost >= infeasible_cost
    phi_obs, phi_next = enc.phi(a.obs), enc.phi(a.next_obs)
    actions: np.ndarray = a.action.astype(np.int64, copy=False)
    if n_candidates is not None:  # continuous commands: u_i itself, and C(x') from the training rows
        actions = logged_commands(ds, who)
        if action_encoding == "per_action":
            raise InvalidArgumentError(f"{who}: continuous commands need action_encoding='joint' (a model per "
                                       "command cannot exist)")
        if action_input != "value":  # it was ignored: the command itself is the model's input
            raise InvalidArgumentError(f"{who}: continuous commands need action_input='value' (the exact command "
                                       "is the model's input: there is no table of entries to one-hot)")
        extra = command_representatives(actions[tr], n_representatives)
        cands = (NeighbourCommands.from_data(phi_obs[tr], actions[tr], n_candidates, extra)
                 if policy_commands is None else policy_commands)
        if policy_commands is not None and fmap is not None:
            raise InvalidArgumentError(f"{who}: evaluating a continuous policy reads the states themselves; "
                                       "feature_map must be None")
        enc = CommandEncoder(cands.n_slots, np.zeros((cands.n_slots, actions.shape[1])), feature_map=fmap,
                             candidates=cands)

    def samples(rows: np.ndarray) -> Samples:
        if rows.all():  # every row: read-only views, not copies (the dataset's arrays at 1M rows: ~0.1 GB)
            return Samples(*(_read_only(v) for v in (phi_obs, actions, a.cost, no_boot, phi_next, a.next_obs)))
        return Samples(phi_obs[rows], actions[rows], a.cost[rows], no_boot[rows], phi_next[rows], a.next_obs[rows])

    start = (a.step == 0) & tr
    bound, text = value_bound(float(np.abs(a.cost).max()), g, horizon, infeasible_cost, target_noise, initial_q_abs,
                              cmin=float(a.cost.min()))
    return Prepared(
        train=samples(tr), valid=samples(~tr) if (~tr).any() else None,
        weights=None if w_all is None else w_all[tr], gamma=g, n_actions=enc.n_actions, encoder=enc,
        obs=_read_only(a.obs) if tr.all() else a.obs[tr],
        obs_std=a.obs.std(axis=0) + 1e-12,
        start_phi=phi_obs[start] if start.any() else phi_obs[tr][:1],
        start_obs=a.obs[start] if start.any() else a.obs[tr][:1],
        start_rows=np.flatnonzero(start[tr]) if start.any() else np.zeros(1, np.int64),
        bound=float(bound), bound_text=text, infeasible_cost=infeasible_cost, q0_abs=float(initial_q_abs),
    )


def command_representatives(commands: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` representative commands of a log, ``(e, m)``, each a command the log holds:
    each varying component cut at the quantiles of its logged values into
    ``B = floor(n^(1/m'))`` bins (``m'``: the components logged at more than one value; a
    constant one takes no share of ``n``), and of every occupied cell of that grid the logged
    command nearest the cell's mean (distances in units of each component's logged range,
    ties to the first row), in row-major cell order. Dense where the log's commands are
    dense, and never a command nobody logged: a mean of integer levels (gears, PWM steps) is
    not one of them, and a mean of two steering levels is not a level. A level logged on at
    least ``1/B`` of the rows (a teleop's fixed steering values) is a bin of its own
    (:func:`~offline_adp.data.levels.level_edges`)."""
    u = np.asarray(commands, np.float64)
    if n <= 0 or len(u) == 0:
        return np.zeros((0, u.shape[1] if u.ndim == 2 else 1))
    span = np.ptp(u, axis=0)
    varying = np.flatnonzero(span > 0)
    B = max(1, int(np.floor(n ** (1.0 / max(len(varying), 1)) + 1e-9)))
    cell = np.zeros(len(u), np.int64)
    for j in varying:
        edges = level_edges(u[:, j], B)  # a level logged often is a bin of its own (data/levels.py)
        inner = edges[1:-1]
        cell = cell * (len(inner) + 1) + np.searchsorted(inner, u[:, j], side="right")
    cells, inverse = np.unique(cell, return_inverse=True)
    inverse = inverse.reshape(-1)
    mean = np.column_stack([cell_means(inverse, u[:, j], len(cells))[0] for j in range(u.shape[1])])
    d = (((u - mean[inverse]) / np.where(span > 0, span, 1.0)) ** 2).sum(axis=1)
    order = np.lexsort((np.arange(len(u)), d, inverse))  # by cell, then distance, then row
    first = order[np.r_[True, inverse[order][1:] != inverse[order][:-1]]]
    return u[first]


def logged_commands(ds: TransitionDataset, who: str) -> np.ndarray:
    """The exact command of every row, ``(n, m)``, checked finite; an error naming the
    dataset's action table when it does not carry them."""
    u = ds.commands()
    at = ds.info.action_table
    if u is None:
        raise InvalidArgumentError(
            f"{who}: continuous commands need the exact command of each row (columns {at.command_columns}); this "
            f"dataset's action table is {at.kind!r} without them. Ingest the commands with type = 'continuous' and "
            "no bins, or fit with commands='binned'")
    bad = ~np.isfinite(u)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InvalidArgumentError(f"{who}: row {int(i)} column {at.command_columns[j]!r}: command is not finite "
                                   f"({u[i, j]!r}); run `offline-adp validate` on the dataset")
    return u


class Backup(Protocol):
    """``V(x') from Q(x', .)`` for the query set ``which`` (``"next"`` or ``"valid_next"``)
    at the step ``t`` being fitted (``None``: infinite horizon)."""

    def __call__(self, q_next: np.ndarray, which: str, t: int | None) -> np.ndarray: ...


class GreedyBackup:
    """FQI: ``V(x') = min_a' Q(x', a')`` (costs are minimised).

    Bound to the fit's learner (:meth:`bind`), the minimum runs over the actions the
    learner's current Q supports at ``x'`` (:meth:`~offline_adp.learn.Learner.support`:
    with the lookup table, the actions logged at ``x'``, wherever one is; every action for
    any other Q), which is exact DP on the data's empirical model."""

    def __init__(self) -> None:
        self.learner: Any = None

    def bind(self, learner: Any) -> None:
        """Read the support of ``learner``'s current Q (the Q whose values are backed up)."""
        self.learner = learner

    def __call__(self, q_next: np.ndarray, which: str, t: int | None) -> np.ndarray:
        support = None if self.learner is None else self.learner.support(which)
        return self.over(q_next, support)

    @staticmethod
    def over(q_next: np.ndarray, support: np.ndarray | None) -> np.ndarray:
        """The minimum of ``q_next`` over the ``support`` (None: every action)."""
        return restrict_to_support(q_next, support).min(axis=1)


class CommandBackup:
    """FQE over continuous commands: one candidate per state, the policy's own command, so
    ``V(x') = Q(x', pi(x'))``; ``probabilities`` (all mass on that one slot) lets the
    structure-conditional operators (:mod:`~offline_adp.algorithms.fqe_bootstrap`) read it
    as they read :class:`PolicyBackup`."""

    def __init__(self, sizes: dict[str, int]) -> None:
        self.sizes = sizes

    def probabilities(self, which: str, t_next: int) -> np.ndarray:
        return np.ones((self.sizes[which], 1))

    def __call__(self, q_next: np.ndarray, which: str, t: int | None) -> np.ndarray:
        return q_next[:, 0]


class PolicyBackup:
    """FQE: ``V(x') = sum_a' pi(a' | x', t+1) Q(x', a')``; probabilities computed once per
    (query set, step) (once per query set for a stationary policy)."""

    def __init__(self, policy: Any, next_obs: dict[str, np.ndarray], stationary: bool) -> None:
        self.policy, self.next_obs, self.stationary = policy, next_obs, stationary
        self.cache: dict[tuple[str, int | None], np.ndarray] = {}

    def probabilities(self, which: str, t_next: int) -> np.ndarray:
        key = (which, None if self.stationary else t_next)
        if key not in self.cache:
            self.cache[key] = self.policy.probabilities(self.next_obs[which], t_next)
        return self.cache[key]

    def __call__(self, q_next: np.ndarray, which: str, t: int | None) -> np.ndarray:
        return (self.probabilities(which, 0 if t is None else t + 1) * q_next).sum(axis=1)


def resolve_commands(est: Any, ds: TransitionDataset) -> str:
    """``est.commands`` with ``"auto"`` resolved on ``ds`` (continuous where its action table
    is; for an evaluation, where the policy commands continuous values); continuous
    commands refuse an ``initial_q`` (a Q over the table's entries)."""
    at = ds.info.action_table
    policy = getattr(est, "policy", None)  # an evaluation: what the policy commands decides
    auto = getattr(policy, "continuous", False) if policy is not None else at.continuous
    out = ("continuous" if auto else "binned") if est.commands == "auto" else est.commands
    if out == "continuous" and policy is not None and not getattr(policy, "continuous", False):
        raise invalid_parameter(est, "commands", "'auto' or 'binned' for a policy over the action table's entries "
                                "(evaluating it over commands would back up another policy)", est.commands)
    if out == "continuous" and getattr(est, "initial_q", None) is not None:
        raise invalid_parameter(est, "initial_q", "None with continuous commands (a Q over the action table's "
                                "entries cannot start a Q over commands)", est.initial_q)
    return out
