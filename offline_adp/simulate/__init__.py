"""Logged datasets from reference problems: demonstrations plus exploration.

``collect`` (from :mod:`offline_adp.rollout`, the one rollout loop) rolls a behaviour
policy out on a problem in one batch and records every transition with its
logged propensity. ``simulate`` mixes the problem's demonstrator and exploration
policies, labelled by ``source``. Writers for a raw Parquet table and MCAP live in
:mod:`offline_adp.simulate.raw` and :mod:`offline_adp.simulate.mcap_writer`.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from offline_adp._version import __version__
from offline_adp.config import parse_json_object
from offline_adp.data.dataset import TransitionDataset
from offline_adp.envs import make_problem
from offline_adp.envs.base import ReferenceProblem
from offline_adp.errors import InvalidArgumentError, OfflineADPError
from offline_adp.rollout import DT_NS, EPISODE_GAP_NS, T0_NS, collect

__all__ = ["collect", "simulate", "DT_NS", "EPISODE_GAP_NS", "T0_NS"]


def _count(value: Any, name: str, lo: int = 0, hi: int = 10**9) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not lo <= value <= hi:
        raise InvalidArgumentError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def parse_problem_options(text: str | None) -> dict[str, Any]:
    """``--problem-options`` (a JSON object of constructor keywords) as a dict."""
    return parse_json_object(text, "--problem-options", '{"n_states": 30}')


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
    if problem_options is not None and not (isinstance(problem_options,
                                                       Mapping) and all(isinstance(k, str) for k in problem_options)):
        raise InvalidArgumentError(f"problem_options must map option names to values, got {problem_options!r}")
    if isinstance(problem, str):
        try:
            prob = make_problem(problem, **(problem_options or {}))
        except OfflineADPError:
            raise
        except (ValueError, TypeError, OverflowError, MemoryError) as exc:  # the constructor rejected a value
            raise InvalidArgumentError(f"problem {problem!r}: options {dict(problem_options or {})} "
                                       f"rejected ({exc})") from None
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
        "problem_options": dict(problem_options or {}) if isinstance(problem, str) else prob.problem_options,
        "seed": seed,
        "n_demonstrations": n_demonstrations,
        "n_exploration": n_exploration,
        "horizon": H,
        "package_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }
    return TransitionDataset(ds.table, prob.dataset_info(**prov).replace(horizon=H))
