"""The one rollout loop: batched Monte-Carlo episodes of a policy on a simulator.

Every rollout in the package runs through :func:`run_episodes`: policy evaluation
(:func:`rollout`, :func:`rollout_pieces`), logging transitions (:func:`collect`, used by
``simulate``, API and iterated FQI), the Ernst et al. car-on-the-hill score, PSDP's
state samples and its Q estimates. All episodes advance together: one batched action
call and one batched ``step`` per time step, never a per-state Python loop.

A continuous policy (``policy.continuous``, e.g. a
:class:`~offline_adp.policies.CommandPolicy`) acts with its commands, an ``(n, m)`` float
array passed to ``model.step``; that needs a model that accepts commands
(``model.accepts_commands``), else :class:`~offline_adp.errors.IncompatibleError` -- a
continuous policy is never silently rolled out through its binned view.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from offline_adp.access import ResetModel, StepResult
from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import IncompatibleError, InvalidArgumentError
from offline_adp.parallel import TaskMap, local_map
from offline_adp.policies import Policy, nearest_entry

#: Start of simulated logs (2024-01-01T00:00:00Z), so timestamps look like a real log's.
T0_NS = 1_704_067_200_000_000_000
EPISODE_GAP_NS = 5_000_000_000
DT_NS = 100_000_000

#: ``act(states, t, rng) -> action indices (n,)`` (or commands (n, m)) for the running episodes.
ActFn = Callable[[np.ndarray, int, np.random.Generator], np.ndarray]
#: ``step(states, actions, rng) -> StepResult`` (a model's ``step`` by default).
StepFn = Callable[[np.ndarray, np.ndarray, np.random.Generator], StepResult]
#: ``visit(t, rows, states, actions, result)``: called after every batched step.
VisitFn = Callable[[int, np.ndarray, np.ndarray, np.ndarray, StepResult], None]


def policy_actor(model: Any, policy: Policy) -> ActFn:
    """How ``policy`` acts in ``model``: its action indices (``act_index``), or, for a
    continuous policy, its commands ``(n, m)`` (``sample_commands(obs, t, rng)`` when it
    has it -- stochastic behaviour -- else ``commands(obs, t)``).

    Raises :class:`IncompatibleError` for a continuous policy and a model that does not
    accept commands (``accepts_commands`` false), naming both.
    """
    if not getattr(policy, "continuous", False):
        return policy.act_index
    if not getattr(model, "accepts_commands", False):
        name = getattr(model, "name", "") or type(model).__name__
        raise IncompatibleError(
            f"simulator {name!r} takes action indices only (it does not accept continuous commands), and the "
            f"policy {type(policy).__name__} commands continuous values; rolling out its binned view instead would "
            "score another policy. Roll it out in a simulator that accepts commands (e.g. gym:ENV_ID with a Box "
            "action space, path_tracking with the problem option commands = \"continuous\"), or bin it explicitly")
    sample = getattr(policy, "sample_commands", None)
    if sample is not None:
        return sample
    return lambda x, t, rng: policy.commands(x, t)  # type: ignore[attr-defined]


def run_episodes(
    step: StepFn,
    act: ActFn,
    start_states: np.ndarray,
    horizon: int,
    rng: np.random.Generator,
    *,
    visit: VisitFn | None = None,
    restart: Callable[[int, np.random.Generator], np.ndarray] | None = None,
) -> np.ndarray:
    """Advance every episode one step at a time for at most ``horizon`` steps.

    At step t the running episodes' rows ``idx`` act (``act(x[idx], t, rng)``), step
    (``step(x[idx], a, rng)``) and are reported to ``visit``; an episode whose step
    terminates stops, or, with ``restart``, continues from ``restart(k, rng)`` fresh
    start states (every step then keeps all rows). Returns the final states.
    """
    x = np.array(start_states, dtype=np.float64)
    alive = np.ones(len(x), bool)
    for t in range(horizon):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        xs = x[idx]
        a = act(xs, t, rng)
        r = step(xs, a, rng)
        if visit is not None:
            visit(t, idx, xs, a, r)
        x[idx] = r.next_states
        if r.terminated.any():
            done = idx[r.terminated]
            if restart is None:
                alive[done] = False
            else:
                x[done] = restart(len(done), rng)
    return x


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
    step: StepFn | None = None,
    on_step: VisitFn | None = None,
) -> RolloutResult:
    """Run ``n_episodes`` episodes of ``policy`` for at most ``horizon`` steps.

    Episode cost ``sum_t gamma^t c_t`` (and the undiscounted sum). With
    ``record_states`` the result keeps every step's states (memory: n x H x d).
    ``step`` replaces ``model.step`` (e.g. a deterministic simulator's seeded step).
    ``on_step(t, rows, states, actions, result)`` sees every batched step (``rows``: the
    running episodes; ``actions``: indices, or the commands of a continuous policy).
    A continuous policy steps with its commands (:func:`policy_actor`; the model must
    accept commands, else :class:`IncompatibleError`).
    """
    H = horizon if horizon is not None else model.horizon
    if H is None:
        raise InvalidArgumentError("rollout needs a horizon (the model has none)")
    g = model.gamma if gamma is None else gamma
    x0 = model.initial_states(n_episodes, rng) if start_states is None else np.asarray(start_states, dtype=np.float64)
    n = len(x0)
    disc, total = np.zeros(n), np.zeros(n)
    length = np.zeros(n, np.int64)
    term = np.zeros(n, bool)
    states: list[np.ndarray] = []

    def visit(t: int, idx: np.ndarray, xs: np.ndarray, a: np.ndarray, r: StepResult) -> None:
        if record_states:
            states.append(xs.copy())
        disc[idx] += g**t * r.costs
        total[idx] += r.costs
        length[idx] += 1
        term[idx] = r.terminated
        if on_step is not None:
            on_step(t, idx, xs, a, r)

    run_episodes(step or model.step, policy_actor(model, policy), x0, H, rng, visit=visit)
    return RolloutResult(disc, total, length, term, states if record_states else None)


def collect(
    problem: Any,
    policy: Policy,
    n_episodes: int,
    rng: np.random.Generator,
    *,
    horizon: int | None = None,
    source: str = "policy",
    episode_prefix: str = "ep",
    start_states: np.ndarray | None = None,
    t0_ns: int = T0_NS,
    dt_ns: int = DT_NS,
    episode_gap_ns: int = EPISODE_GAP_NS,
    on_step: Callable[[int], None] | None = None,
) -> TransitionDataset:
    """Roll ``policy`` out for ``n_episodes`` episodes and log every transition.

    ``problem`` is a reset model with ``dataset_info()`` (a reference problem).
    Episodes run until ``terminated`` or ``horizon`` steps (then the last transition is
    ``truncated`` and kept). Actions are sampled from ``policy.probabilities`` and
    ``behavior_prob`` is the probability of the logged action.

    A continuous behaviour policy (``policy.continuous``) acts with its commands
    (:func:`policy_actor`: sampled, for a stochastic one), which the problem must accept, and
    the problem's action table must be of kind ``"continuous"``. Each row then logs its exact
    command in the ``action_value.<dim>`` columns and, in ``action``, the nearest table entry
    (the coarse bin); no ``behavior_prob`` column is written, since the behaviour's law of a
    command is a density, not the probability of a logged action. Episode ids are
    ``{episode_prefix}-{k:06d}``; episode ``k`` starts at
    ``t0_ns + k * (horizon * dt_ns + episode_gap_ns)``.
    """
    H = horizon if horizon is not None else problem.horizon
    if H is None or H <= 0:
        raise InvalidArgumentError(f"{getattr(problem, 'name', problem)}: collecting needs a positive horizon, got {H}")
    x0 = problem.initial_states(n_episodes, rng) if start_states is None else np.asarray(start_states, dtype=np.float64)
    info = problem.dataset_info()
    table = info.action_table
    continuous = bool(getattr(policy, "continuous", False))
    keys = ("ep", "step", "obs", "a", "c", "nxt", "term", "trunc") + (() if continuous else ("prob",))
    rec: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    probs: list[np.ndarray] = []
    if continuous:
        actor = policy_actor(problem, policy)
        if not table.continuous:
            raise IncompatibleError(
                f"{getattr(problem, 'name', problem)}: its action table is of kind {table.kind!r}, so a dataset of it "
                f"cannot keep the exact commands of the continuous policy {type(policy).__name__}; use a problem whose "
                "action table is continuous (e.g. path_tracking with commands = \"continuous\")")
        m = len(table.dims)

        def act(xs: np.ndarray, t: int, r: np.random.Generator) -> np.ndarray:
            return np.asarray(actor(xs, t, r), dtype=np.float64).reshape(len(xs), m)
    else:
        def act(xs: np.ndarray, t: int, r: np.random.Generator) -> np.ndarray:
            p = policy.probabilities(xs, t)
            u = r.random(len(xs))
            a = np.minimum((u[:, None] >= np.cumsum(p, axis=1)).sum(axis=1), p.shape[1] - 1)
            probs.append(p[np.arange(len(xs)), a])
            return a

    def visit(t: int, idx: np.ndarray, xs: np.ndarray, a: np.ndarray, r: StepResult) -> None:
        for k, v in (("ep", idx), ("step", np.full(len(idx), t, np.int32)), ("obs", xs), ("a", a), ("c", r.costs),
                     ("nxt", r.next_states), ("term", r.terminated), ("trunc", ~r.terminated & (t == H - 1)),
                     ("prob", probs[-1] if probs else None)):
            if v is not None:
                rec[k].append(v)
        if on_step is not None:
            on_step(t)

    run_episodes(problem.step, act, x0, H, rng, visit=visit)
    cat = {k: np.concatenate(v) for k, v in rec.items()}
    order = np.lexsort((cat["step"], cat["ep"]))
    cat = {k: v[order] for k, v in cat.items()}
    ep = cat["ep"]
    ids = np.char.add(f"{episode_prefix}-", np.char.zfill(ep.astype(str), 6))
    t_ns = t0_ns + ep.astype(np.int64) * (H * dt_ns + episode_gap_ns) + cat["step"].astype(np.int64) * dt_ns
    if continuous:  # the exact commands, their coarse bins in ``action``, no propensity
        u = cat["a"]
        return TransitionDataset.from_arrays(
            info, episode_id=ids, step=cat["step"], obs=cat["obs"], action=nearest_entry(table, u), cost=cat["c"],
            next_obs=cat["nxt"], terminated=cat["term"], truncated=cat["trunc"], source=source, t_ns=t_ns,
            extra={c: u[:, j] for j, c in enumerate(table.command_columns)},
        )
    return TransitionDataset.from_arrays(
        info, episode_id=ids, step=cat["step"], obs=cat["obs"], action=cat["a"], cost=cat["c"],
        next_obs=cat["nxt"], terminated=cat["term"], truncated=cat["trunc"], source=source, behavior_prob=cat["prob"],
        t_ns=t_ns,
    )


def state_samples(model: ResetModel, policy: Policy, n: int, T: int, rng: np.random.Generator) -> list[np.ndarray]:
    """States of ``n`` rollouts of ``policy`` at each step t < T (Monte-Carlo mu_t).

    Episodes that terminated early are restarted from a reset so every step has ``n``
    samples (the distribution over the states occupied at step t of non-terminated
    episodes, the PSDP baseline).
    """
    out: list[np.ndarray] = []
    run_episodes(model.step, policy_actor(model, policy), model.initial_states(n, rng), T, rng,
                 visit=lambda t, idx, xs, a, r: out.append(xs.copy()), restart=model.initial_states)
    return out


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
    (:class:`offline_adp.engines.dask.DaskTaskMap`). The split does not depend on the
    engine, so local and distributed runs give identical results.
    """
    pieces = [(x0, [seed, k]) for k, x0 in enumerate(np.array_split(np.asarray(start_states, dtype=np.float64),
                                                                    n_pieces))
              if len(x0)]
    run = task_map or local_map
    out = run(_rollout_piece, pieces, shared={"model": model, "policies": policies, "horizon": horizon, "gamma": gamma,
                                              "record_states": record_states}, on_done=on_done)
    return {name: _merge([o[name] for o in out], record_states) for name in policies}
