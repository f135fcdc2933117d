"""Reference problems: each a batched access model plus a ``gymnasium.Env`` via ``make_env``."""

from __future__ import annotations

from typing import Any

from offline_adp.envs.base import ProblemEnv, ReferenceProblem
from offline_adp.envs.car_on_hill import CarOnHill
from offline_adp.envs.gridworld import Gridworld
from offline_adp.envs.path_tracking import PathTracking
from offline_adp.envs.tabular import TabularMDP
from offline_adp.envs.two_state import TwoState
from offline_adp.errors import UnknownNameError

PROBLEMS: dict[str, type] = {
    "car_on_hill": CarOnHill,
    "gridworld": Gridworld,
    "path_tracking": PathTracking,
    "tabular": TabularMDP,
    "two_state": TwoState,
}


def make_problem(name: str, **kwargs: Any) -> ReferenceProblem:
    """Instantiate a reference problem by name (keyword arguments go to its constructor)."""
    try:
        cls = PROBLEMS[name]
    except KeyError:
        raise UnknownNameError(f"unknown problem {name!r}; known problems: {sorted(PROBLEMS)}") from None
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise UnknownNameError(f"problem {name!r}: bad options {sorted(kwargs)} ({exc})") from None


__all__ = ["PROBLEMS", "make_problem", "ProblemEnv", "ReferenceProblem", "CarOnHill", "Gridworld", "PathTracking", "TabularMDP", "TwoState"]
