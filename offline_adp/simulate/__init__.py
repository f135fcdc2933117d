"""Logged datasets from reference problems: demonstrations plus exploration.

``collect`` rolls a behaviour policy out on a problem in one batch (vectorised over
episodes; one Python iteration per time step) and records every transition with its
logged propensity. ``simulate`` mixes the problem's demonstrator and exploration
policies, labelled by ``source``. Writers for a raw Parquet table and MCAP live in
:mod:`offline_adp.simulate.raw` and :mod:`offline_adp.simulate.mcap_writer`.
"""

from __future__ import annotations

import datetime as _dt
import json
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.access import ResetModel
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs import make_problem
from offline_adp.envs.base import ReferenceProblem
from offline_adp.errors import InvalidArgumentError, OfflineADPError
from offline_adp.policies import Policy

#: Start of simulated logs (2024-01-01T00:00:00Z), so timestamps look like a real log's.
T0_NS = 1_704_067_200_000_000_000
EPISODE_GAP_NS = 5_000_000_000
DT_NS = 100_000_000


def collect(
    problem: ReferenceProblem,
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
    on_step: Callable[[int], None] | None = None,
) -> TransitionDataset:
    """Roll ``policy`` out for ``n_episodes`` episodes and log every transition.

    Episodes run until ``terminated`` or ``horizon`` steps (then the last transition is
    ``truncated`` and kept). ``behavior_prob`` is the policy's probability of the
    logged action. Episode ids are ``{episode_prefix}-{k:06d}``; episode ``k`` starts at
    ``t0_ns + k * (horizon * dt_ns + 5 s)``.
    """
    assert isinstance(problem, ResetModel)
    H = horizon if horizon is not None else problem.horizon
    if H is None or H <= 0:
        raise InvalidArgumentError(f"{problem.name}: collecting needs a positive horizon, got {H}")
    x = problem.initial_states(n_episodes, rng) if start_states is None else np.array(start_states, dtype=np.float64)
    n = len(x)
    alive = np.ones(n, bool)
    rec: dict[str, list[np.ndarray]] = {k: [] for k in ("ep", "step", "obs", "a", "c", "nxt", "term", "trunc", "prob")}
    for t in range(H):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        p = policy.probabilities(x[idx], t)
        u = rng.random(len(idx))
        a = np.minimum((u[:, None] >= np.cumsum(p, axis=1)).sum(axis=1), problem.n_actions - 1)
        r = problem.step(x[idx], a, rng)
        rec["ep"].append(idx)
        rec["step"].append(np.full(len(idx), t, np.int32))
        rec["obs"].append(x[idx])
        rec["a"].append(a)
        rec["c"].append(r.costs)
        rec["nxt"].append(r.next_states)
        rec["term"].append(r.terminated)
        rec["trunc"].append(~r.terminated & (t == H - 1))
        rec["prob"].append(p[np.arange(len(idx)), a])
        x[idx] = r.next_states
        alive[idx[r.terminated]] = False
        if on_step is not None:
            on_step(t)
    cat = {k: np.concatenate(v) for k, v in rec.items()}
    order = np.lexsort((cat["step"], cat["ep"]))
    cat = {k: v[order] for k, v in cat.items()}
    ep = cat["ep"]
    ids = np.char.add(f"{episode_prefix}-", np.char.zfill(ep.astype(str), 6))
    t_ns = t0_ns + ep.astype(np.int64) * (H * dt_ns + EPISODE_GAP_NS) + cat["step"].astype(np.int64) * dt_ns
    info = problem.dataset_info()
    return TransitionDataset.from_arrays(
        info,
        episode_id=ids,
        step=cat["step"],
        obs=cat["obs"],
        action=cat["a"],
        cost=cat["c"],
        next_obs=cat["nxt"],
        terminated=cat["term"],
        truncated=cat["trunc"],
        source=source,
        behavior_prob=cat["prob"],
        t_ns=t_ns,
    )


def _count(value: Any, name: str, lo: int = 0, hi: int = 10**9) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not lo <= value <= hi:
        raise InvalidArgumentError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def parse_problem_options(text: str | None) -> dict[str, Any]:
    """``--problem-options`` (a JSON object of constructor keywords) as a dict."""
    if not text:
        return {}
    try:
        opts = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InvalidArgumentError(f"--problem-options: not valid JSON ({exc.msg} at character {exc.pos}): {text!r}") from None
    if not isinstance(opts, dict):
        raise InvalidArgumentError(f"--problem-options: expected a JSON object such as '{{\"n_states\": 30}}', got {text!r}")
    return opts


def simulate(
    problem: str | ReferenceProblem,
    n_demonstrations: int = 100,
    n_exploration: int = 100,
    *,
    seed: int = 0,
    horizon: int | None = None,
    problem_options: dict | None = None,
    on_step: Callable[[int], None] | None = None,
) -> TransitionDataset:
    """A logged dataset of demonstrations plus exploration on a reference problem.

    Demonstration episodes (ids ``demo-NNNNNN``) follow ``problem.demonstrator()``,
    exploration episodes (``explore-NNNNNN``) ``problem.exploration()``; both log their
    propensities. Deterministic for a given seed.
    """
    n_demonstrations = _count(n_demonstrations, "n_demonstrations")
    n_exploration = _count(n_exploration, "n_exploration")
    if n_demonstrations + n_exploration == 0:
        raise InvalidArgumentError("simulate needs at least one demonstration or exploration episode")
    seed = _count(seed, "seed", 0, 2**63 - 1)
    if horizon is not None:
        horizon = _count(horizon, "horizon", 1, 10**7)
    if problem_options is not None and not (isinstance(problem_options, Mapping) and all(isinstance(k, str) for k in problem_options)):
        raise InvalidArgumentError(f"problem_options must map option names to values, got {problem_options!r}")
    if isinstance(problem, str):
        try:
            prob = make_problem(problem, **(problem_options or {}))
        except OfflineADPError:
            raise
        except (ValueError, TypeError, OverflowError, MemoryError) as exc:  # the constructor rejected a value
            raise InvalidArgumentError(f"problem {problem!r}: options {dict(problem_options or {})} rejected ({exc})") from None
    else:
        prob = problem
    rng = np.random.default_rng(seed)
    H = horizon if horizon is not None else prob.horizon  # type: ignore[attr-defined]
    parts = []
    if n_demonstrations:
        parts.append(collect(prob, prob.demonstrator(), n_demonstrations, rng, horizon=H, source="demonstration",
                             episode_prefix="demo", on_step=on_step))
    if n_exploration:
        t0 = T0_NS + n_demonstrations * (H * DT_NS + EPISODE_GAP_NS)
        parts.append(collect(prob, prob.exploration(), n_exploration, rng, horizon=H, source="exploration",
                             episode_prefix="explore", t0_ns=t0, on_step=on_step))
    if not parts:
        raise InvalidArgumentError("simulate needs at least one demonstration or exploration episode")
    ds = TransitionDataset.concat(parts) if len(parts) > 1 else parts[0]
    prov = {
        "generator": "offline-adp simulate",
        "problem": prob.name,
        "problem_options": problem_options or {},
        "seed": seed,
        "n_demonstrations": n_demonstrations,
        "n_exploration": n_exploration,
        "horizon": H,
        "package_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    return TransitionDataset(ds.table, prob.dataset_info(**prov).replace(horizon=H))
